"""The estimator's settings in the YAML configuration's `estimate:` section (gscan.estimate.settings)."""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml

from gscan.errors import InputError
from gscan.estimate import EstimateParams, Estimator, dump_estimate_defaults, load_estimate_params
from gscan.estimate.params import DEFAULT_PARAMS, RefineParams
from gscan.scanning.cad import template_from_mesh
from gscan.scanning.config import dump_defaults


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "gscan.yaml"
    path.write_text(text, encoding="utf-8")
    return path


def test_the_dump_loads_back_after_the_scans_sections(tmp_path: Path):
    text = dump_estimate_defaults()
    assert text.startswith("estimate:") and "# " in text
    assert set(yaml.safe_load(text)) == {"estimate"}
    path = write(tmp_path, dump_defaults() + text)  # what `gscan config dump` prints: the scan's, then this
    assert load_estimate_params(path) == DEFAULT_PARAMS == EstimateParams()
    assert load_estimate_params(None) == DEFAULT_PARAMS
    assert load_estimate_params(write(tmp_path, "features: {kind: orb}\n")) == DEFAULT_PARAMS  # no estimate section
    assert load_estimate_params(write(tmp_path, "estimate:\n")) == DEFAULT_PARAMS


def test_a_key_left_out_keeps_the_estimators_default(tmp_path: Path):
    p = load_estimate_params(write(tmp_path, "estimate:\n  features: {max_keypoints: 1000}\n"
                                             "  rivals: {lists: 0}\n  verify: {support_dist: 0.3}\n"))
    assert p.features == replace(DEFAULT_PARAMS.features, max_keypoints=1000)  # the object keypoints' contrast
    assert p.rivals.lists == 0 and p.rivals.p == DEFAULT_PARAMS.rivals.p and p.verify.support_dist == 0.3
    assert p.refine == DEFAULT_PARAMS.refine


@pytest.mark.parametrize(("text", "key"), [
    ("estimate: {refine: {max_dist: -0.01}}", "estimate.refine.max_dist"),
    ("estimate: {refine: {icp_max_dist: 0.01}}", "estimate.refine.icp_max_dist"),
    ("estimate: {top_k: 4}", "estimate.top_k"),
    ("estimate: {retrieval: {top_k: many}}", "estimate.retrieval.top_k"),
    ("estimate: {accept: {min_score: 1.5}}", "estimate.accept.min_score"),
    ("estimate: {rivals: {p: .nan}}", "estimate.rivals.p"),
    ("estimate: {gmatch: {order: best}}", "estimate.gmatch"),
    ("estimate: {threads: {blas: 0}}", "estimate.threads.blas"),
    ("estimate: [1, 2]", "estimate"),
])
def test_bad_values_are_refused_naming_the_file_and_key(tmp_path: Path, text: str, key: str):
    path = write(tmp_path, text + "\n")
    with pytest.raises(InputError, match=rf"gscan\.yaml.*invalid config key {key.replace('.', '[.]')}\b"):
        load_estimate_params(path)


def test_an_edited_value_takes_effect_in_an_estimator(meshes_dir: Path, tmp_path: Path):
    tpl = tmp_path / "target.gscan"
    template_from_mesh(meshes_dir / "Frozen_Scrabble_Jr" / "model_0.obj", tpl, n_views=8)
    text = dump_estimate_defaults().replace("    voxel: 0.003", "    voxel: 0.009")
    assert text != dump_estimate_defaults()
    params = load_estimate_params(write(tmp_path, text))
    assert params.refine == RefineParams(voxel=0.009)
    coarse, fine = Estimator.from_path(tpl, params), Estimator.from_path(tpl)
    assert coarse.params.refine.voxel == 0.009 and len(coarse.model.samples) < len(fine.model.samples) / 4
    assert np.allclose(coarse.model.center, fine.model.center)


def test_every_estimate_setting_is_described():
    """Every key of the estimator's own sections carries its description into the dump (the features and gmatch
    sections are the keypoint and matcher settings the scan shares)."""
    section = None
    for line in dump_estimate_defaults().splitlines()[1:]:
        if not line.startswith("    "):
            section = line.split(":")[0].strip()
            assert "  # " in line, line
        elif section not in ("features", "gmatch"):
            assert "  # " in line, line
