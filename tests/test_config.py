"""Scan configuration: `gscan config dump` round-trips through --config; edits take effect; bad files refused."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest
import yaml

from gscan.errors import InputError
from gscan.scanning.capture_mode import MOVING_OBJECT, STATIC_OBJECT
from gscan.scanning.config import FOREIGN_SECTIONS, ScanConfig, dump_defaults, for_capture, load_config
from gscan.settings import to_data


def _leaves(data: dict, prefix: str = "") -> dict:
    """section.key -> value of every leaf of nested mappings."""
    out = {}
    for k, v in data.items():
        if isinstance(v, dict):
            out |= _leaves(v, f"{prefix}{k}.")
        else:
            out[f"{prefix}{k}"] = v
    return out


def test_dump_has_a_comment_per_key_and_loads_back_as_the_defaults(tmp_path):
    from gscan.estimate.settings import dump_estimate_defaults

    whole = subprocess.run([sys.executable, "-m", "gscan.cli", "config", "dump"], capture_output=True, text=True,
                           check=True).stdout
    assert whole == dump_defaults() + "\n" + dump_estimate_defaults()  # the scan's sections, then `estimate:`
    text = dump_defaults()
    keys = [line for line in text.splitlines() if line.startswith("  ")]
    assert keys and all("  # " in line for line in keys)
    # every field of every stage's settings class, nested sections included, is a key of the file
    assert set(_leaves(yaml.safe_load(text))) == set(_leaves(to_data(ScanConfig())))
    path = tmp_path / "scan.yaml"
    path.write_text(text)
    assert load_config(path) == ScanConfig()


def test_an_edited_value_is_used(tmp_path):
    data = yaml.safe_load(dump_defaults())
    data["features"]["max_keypoints"] = 500
    data["registration"]["method"] = "lo-ransac"
    data["registration"]["gmatch"]["T"] = 12
    path = tmp_path / "scan.yaml"
    path.write_text(yaml.safe_dump(data))
    cfg = load_config(path)
    assert cfg.features.max_keypoints == 500 and cfg.registration.method == "lo-ransac"
    assert cfg.registration.gmatch.T == 12 and cfg.posegraph == ScanConfig().posegraph


def test_a_file_of_the_earlier_keys_reads_the_same(tmp_path):
    """The `match` section (now registration.gmatch, its method registration.method) and `registration.noise`
    as two models used as given (now registration.noise and depth_noise, posegraph.estimate_noise false)."""
    path = tmp_path / "old.yaml"
    path.write_text("match:\n  method: lo-ransac\n  eps_c: 0.1\nregistration:\n  min_matches: 8\n  noise:\n"
                    "    keypoint: {c0: 1.0e-6, c1: 0, c2: 0}\n    depth: {c0: 2.0e-6, c1: 0, c2: 1.0e-6}\n")
    cfg = load_config(path)
    r = cfg.registration
    assert (r.method, r.gmatch.eps_c, r.min_matches) == ("lo-ransac", 0.1, 8)
    assert (r.noise.c0, r.depth_noise.c0, r.depth_noise.c2) == (1e-6, 2e-6, 1e-6)
    assert not cfg.posegraph.estimate_noise
    path.write_text("registration:\n  noise: null\n")
    assert load_config(path) == ScanConfig()
    # a template's noise meta as written now: the depth's model along the ray as well
    path.write_text("registration:\n  noise:\n    keypoint: {c0: 1.0e-6, c1: 0, c2: 0}\n"
                    "    depth: {c0: 2.0e-6, c1: 0, c2: 1.0e-6}\n"
                    "    depth_ray: {c0: 3.0e-6, c1: 1.0e-6, c2: 0, along_ray: true}\n")
    r = load_config(path).registration
    assert r.depth_noise_ray.along_ray and r.depth_noise_ray.c0 == 3e-6 and r.depth_noise.c0 == 2e-6


def test_foreign_sections_are_ignored_and_others_refused(tmp_path):
    """The estimator's section may share the file; any other unknown section is refused, named."""
    path = tmp_path / "both.yaml"
    path.write_text("estimate:\n  anything: 1\nfeatures:\n  max_keypoints: 700\n")
    assert FOREIGN_SECTIONS == ("estimate",)
    assert load_config(path).features.max_keypoints == 700
    path.write_text("estimator:\n  anything: 1\n")
    with pytest.raises(InputError, match="estimator"):
        load_config(path)


@pytest.mark.parametrize("text, words", [
    ("features: [1, 2\n", "malformed YAML"),
    ("features:\n  colour: 3\n", "features.colour"),
    ("match:\n  eps_c: 2.0\n", "registration.gmatch.eps_c"),
    ("registration:\n  gmatch:\n    eps_c: 2.0\n", "registration.gmatch.eps_c"),
    ("features:\n  kind: surf\n", "features.kind"),
    ("posegraph:\n  max_skip: 0\n", "posegraph.max_skip"),
    ("- a list\n", "mapping"),
    ("segmentation:\n  depth_min: 2.0\n  depth_max: 1.0\n", "segmentation"),
    ("segmentation:\n  height_max: 0.001\n", "segmentation.height_max"),
    ("segmentation:\n  depth_max: 1.0e+300\n", "segmentation.depth_max"),
    ("segmentation:\n  depth_min: 5\n  depth_max: 10\nfusion:\n  depth_max: 2\n",
     "segmentation.depth_min must be below fusion.depth_max"),
    ("keyframes:\n  object_keypoints: both\nfeatures:\n  kind: sift\n",
     "keyframes.object_keypoints: both joins depth keypoints to rootsift ones, not sift"),
])
def test_bad_config_names_the_file_and_the_key(tmp_path, text, words):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(InputError) as e:
        load_config(path)
    assert "bad.yaml" in str(e.value) and words in str(e.value)


def test_the_capture_decides_what_the_config_leaves_null():
    """eps_f: tighter for rootsift on a static scene's whole frames, the descriptor's default otherwise; the depth
    refinement: on for a moving object, off for a static scene. Given values win in both modes."""
    base = ScanConfig()
    static, moving = for_capture(base, STATIC_OBJECT), for_capture(base, MOVING_OBJECT)
    assert static.registration.gmatch.eps_f == 0.5 and moving.registration.gmatch.eps_f is None
    assert moving.registration.dense_refine is True and static.registration.dense_refine is False
    assert for_capture(ScanConfig.model_validate({"features": {"kind": "sift"}}), STATIC_OBJECT
                       ).registration.gmatch.eps_f is None
    given = ScanConfig.model_validate({"registration": {"dense_refine": True, "gmatch": {"eps_f": 0.7}}})
    for mode in (STATIC_OBJECT, MOVING_OBJECT):
        r = for_capture(given, mode).registration
        assert r.dense_refine is True and r.gmatch.eps_f == 0.7
    assert for_capture(base, STATIC_OBJECT).posegraph == base.posegraph and base.registration.dense_refine is None


def test_segmentation_keys_reach_the_segmentation_and_a_far_object_is_found(meshes_dir):
    """The object 1.9 m away: the default working depth, from the depth at the image centre, finds it on its table;
    a fixed `segmentation.depth_max: 1.5` misses it (it takes the whole near scene, IoU 0), 2.5 finds it."""
    from gscan.io.camera import RGBDFrame
    from gscan.scanning.segment import segment_frame
    from gscan.synth import load_textured_mesh, render_capture

    base = ScanConfig()
    mesh = load_textured_mesh(meshes_dir / "Crayola_Bonus_64_Crayons" / "model_0.obj")
    fr = render_capture(mesh, None, 1, distance=1.9, elevations_deg=(40.0,))[0]
    frame = RGBDFrame("far", fr.color, fr.depth, fr.intrinsics)
    near = ScanConfig.model_validate({"segmentation": {"depth_max": 1.5}})
    far = ScanConfig.model_validate({"segmentation": {"depth_max": 2.5}})
    for cfg, min_iou, max_iou in ((base, 0.6, 1.0), (near, 0.0, 0.1), (far, 0.6, 1.0)):
        m = segment_frame(frame, cfg.segmentation).mask
        iou = (m & fr.mask).sum() / max(1, (m | fr.mask).sum())
        assert min_iou <= iou <= max_iou, (cfg.segmentation.depth_max, iou)


def test_python_scan_without_a_config_writes_the_poses_of_the_command_line(tmp_path):
    """`gscan.scan(capture, out)` with no configuration and `gscan scan capture -o out` on a small rendered capture
    (5 views, 320 x 240): the same result and the same poses, bit for bit."""
    import gscan
    from gscan import synth
    from gscan.template.db import TemplateDB

    capture = tmp_path / "capture"
    mesh = synth.box_mesh((0.14, 0.09, 0.07), synth.procedural_box_texture(3, (512, 768)))
    synth.render_capture(mesh, capture, 5, mode="static", elevations_deg=(40.0,),
                         intr=synth.DEFAULT_INTRINSICS.scaled(0.5))
    res = gscan.scan(capture, tmp_path / "python.gscan")
    r = subprocess.run([sys.executable, "-m", "gscan.cli", "scan", str(capture), "-o", str(tmp_path / "cli.gscan"),
                        "--json"], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    cli = json.loads(r.stdout)
    assert res.registered >= 4 and cli["registered"] == res.registered
    assert (cli["edges"], cli["mesh"]) == (res.to_json()["edges"], res.to_json()["mesh"])
    with TemplateDB.open(tmp_path / "python.gscan") as a, TemplateDB.open(tmp_path / "cli.gscan") as b:
        assert a.poses() == b.poses()
