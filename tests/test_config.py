"""Scan configuration: `gscan config dump` round-trips through --config; edits take effect; bad files refused."""
from __future__ import annotations

import json
import subprocess
import sys

import pytest
import yaml

from gscan.errors import InputError
from gscan.features import FeatureParams
from gscan.matching.gmatch import GMatchParams
from gscan.registration.pairwise import RegisterParams
from gscan.registration.posegraph import LoopParams, PoseGraphParams
from gscan.scanning.calibration import FocalCheckParams
from gscan.scanning.config import ScanConfig, dump_defaults, load_config
from gscan.scanning.fuse import FusionParams
from gscan.scanning.keyframes import KeyframeParams
from gscan.scanning.segment import SegmentParams
from gscan.scanning.select import SelectionParams


def test_dump_has_a_comment_per_key_and_loads_back_as_the_defaults(tmp_path):
    text = subprocess.run([sys.executable, "-m", "gscan.cli", "config", "dump"], capture_output=True, text=True,
                          check=True).stdout
    assert text == dump_defaults()
    keys = [line for line in text.splitlines() if line.startswith("  ")]
    assert keys and all("  # " in line for line in keys)
    n_fields = sum(len(type(section).model_fields) for _, section in ScanConfig())
    assert len(keys) == n_fields
    path = tmp_path / "scan.yaml"
    path.write_text(text)
    assert load_config(path) == ScanConfig()


def test_an_edited_value_is_used(tmp_path):
    data = yaml.safe_load(dump_defaults())
    data["features"]["max_keypoints"] = 500
    data["match"]["method"] = "lo-ransac"
    path = tmp_path / "scan.yaml"
    path.write_text(yaml.safe_dump(data))
    cfg = load_config(path)
    assert cfg.features.max_keypoints == 500 and cfg.match.method == "lo-ransac"
    assert cfg.registration == ScanConfig().registration


@pytest.mark.parametrize("text, words", [
    ("features: [1, 2\n", "malformed YAML"),
    ("features:\n  colour: 3\n", "features.colour"),
    ("match:\n  eps_c: 2.0\n", "match.eps_c"),
    ("- a list\n", "mapping"),
    ("segmentation:\n  depth_min: 2.0\n  depth_max: 1.0\n", "segmentation"),
    ("segmentation:\n  height_max: 0.001\n", "segmentation.height_max"),
    ("segmentation:\n  depth_max: 1.0e+300\n", "segmentation.depth_max"),
    ("segmentation:\n  depth_min: 5\n  depth_max: 10\nfusion:\n  depth_max: 2\n",
     "segmentation.depth_min must be below fusion.depth_max"),
])
def test_bad_config_names_the_file_and_the_key(tmp_path, text, words):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(InputError) as e:
        load_config(path)
    assert "bad.yaml" in str(e.value) and words in str(e.value)


def test_every_registration_key_reaches_the_registration_parameters():
    from gscan.registration.noise import DepthNoise
    from gscan.scanning.capture_mode import MOVING_OBJECT, STATIC_OBJECT
    from gscan.scanning.config import NoiseConfig
    from gscan.scanning.params import register_params as _register_params

    base = ScanConfig()
    for key, value in base.registration.model_dump().items():
        if key == "noise":  # null: the capture's own; given, both models reach the parameters
            new = NoiseConfig.model_validate({"keypoint": {"c0": 1e-6, "c1": 0, "c2": 0},
                                              "depth": {"c0": 2e-6, "c1": 0, "c2": 1e-6}})
            cfg = base.model_copy(update={"registration": base.registration.model_copy(update={key: new})})
            p = _register_params(cfg, MOVING_OBJECT)
            assert (p.noise, p.depth_noise) == (DepthNoise(1e-6, 0, 0), DepthNoise(2e-6, 0, 1e-6))
            continue
        if key == "dense_refine":  # null: on for a moving object, off for a static scene; given, it reaches both
            assert value is None
            assert _register_params(base, MOVING_OBJECT).dense_refine and not _register_params(base, STATIC_OBJECT
                                                                                            ).dense_refine
            for new in (True, False):
                cfg = base.model_copy(update={"registration": base.registration.model_copy(update={key: new})})
                assert _register_params(cfg, STATIC_OBJECT).dense_refine is new
                assert _register_params(cfg, MOVING_OBJECT).dense_refine is new
            continue
        shares = ("max_see_through", "min_colour_agreement")  # in [0, 1]
        new = (not value) if isinstance(value, bool) else value / 2 if key in shares else value + 1
        cfg = base.model_copy(update={"registration": base.registration.model_copy(update={key: new})})
        assert getattr(_register_params(cfg, MOVING_OBJECT), key) == new, key


def test_segmentation_keys_reach_the_segmentation_and_a_far_object_is_found(meshes_dir):
    """The object 1.9 m away: the default working depth, from the depth at the image centre, finds it on its table;
    a fixed `segmentation.depth_max: 1.5` misses it (it takes the whole near scene, IoU 0), 2.5 finds it."""
    from gscan.io.camera import RGBDFrame
    from gscan.scanning.params import segment_params as _segment_params
    from gscan.scanning.segment import segment_frame
    from gscan.synth import load_textured_mesh, render_capture

    base = ScanConfig()
    for key, value in base.segmentation.model_dump().items():
        value = 1.0 if value is None else value
        cfg = base.model_copy(update={"segmentation": base.segmentation.model_copy(update={key: value + 0.5})})
        assert getattr(_segment_params(cfg), key) == value + 0.5, key
    mesh = load_textured_mesh(meshes_dir / "Crayola_Bonus_64_Crayons" / "model_0.obj")
    fr = render_capture(mesh, None, 1, distance=1.9, elevations_deg=(40.0,))[0]
    frame = RGBDFrame("far", fr.color, fr.depth, fr.intrinsics)
    near = ScanConfig.model_validate({"segmentation": {"depth_max": 1.5}})
    far = ScanConfig.model_validate({"segmentation": {"depth_max": 2.5}})
    for cfg, min_iou, max_iou in ((base, 0.6, 1.0), (near, 0.0, 0.1), (far, 0.6, 1.0)):
        m = segment_frame(frame, _segment_params(cfg)).mask
        iou = (m & fr.mask).sum() / max(1, (m | fr.mask).sum())
        assert min_iou <= iou <= max_iou, (cfg.segmentation.depth_max, iou)


# every key of `gscan config dump`: the stage parameter (class, field) whose default it is ...
STAGE_DEFAULTS = {
    "camera.check_colour_focal": (FocalCheckParams, "enabled"),
    "features.kind": (FeatureParams, "kind"), "features.max_keypoints": (FeatureParams, "max_keypoints"),
    "match.method": (RegisterParams, "method"),
    **{f"match.{k}": (GMatchParams, k) for k in ("eps_f", "eps_c", "eta", "order", "T", "L", "constraint")},
    **{f"registration.{k}": (RegisterParams, k) for k in (
        "min_matches", "max_rms", "max_sigma_deg", "max_sigma_rel", "max_see_through", "min_colour_agreement",
        "verify", "support_eps_scale",
        "icp", "icp_max_dist", "icp_voxel", "min_fitness", "max_rmse", "max_icp_shift_deg", "max_icp_shift_m")},
    "posegraph.loop_candidates": (LoopParams, "max_per_node"),
    "posegraph.max_view_angle_deg": (LoopParams, "max_angle_deg"),
    "posegraph.alpha": (PoseGraphParams, "alpha"),
    **{f"segmentation.{k}": (SegmentParams, k) for k in ("depth_min", "depth_max", "height_max")},
    "fusion.voxel": (FusionParams, "voxel_size"), "fusion.depth_max": (FusionParams, "depth_max"),
    **{f"keyframes.{k}": (KeyframeParams, k) for k in ("min_angle_deg", "max_views", "min_views",
                                                       "min_object_keypoints")},
    **{f"selection.{k}": (SelectionParams, k) for k in ("min_motion_deg", "blur_ratio")},
}
# ... or null, decided per capture (the stage's own default is what a caller without a capture gets) ...
FROM_THE_CAPTURE = {
    "registration.noise": (RegisterParams, "noise"),  # estimated from the capture, starting from this prior
    "registration.dense_refine": (RegisterParams, "dense_refine"),  # on for a moving object, off for a static scene
}
# ... or derived from another stage default
DERIVED = {"posegraph.bridge_min_matches": 2 * RegisterParams().min_matches}


def test_config_dump_holds_the_stage_parameter_defaults_key_by_key():
    """One source of defaults: each value `gscan config dump` prints is the default of the stage parameter it
    configures (a key missing from the lists above fails: a new key must name its source)."""
    text = subprocess.run([sys.executable, "-m", "gscan.cli", "config", "dump"], capture_output=True, text=True,
                          check=True).stdout
    dumped = {f"{section}.{key}": value
              for section, keys in yaml.safe_load(text).items() for key, value in keys.items()}
    assert set(dumped) == set(STAGE_DEFAULTS) | set(FROM_THE_CAPTURE) | set(DERIVED)
    for key, (params, name) in STAGE_DEFAULTS.items():
        assert dumped[key] == getattr(params(), name), key
    for key, (params, name) in FROM_THE_CAPTURE.items():
        assert dumped[key] is None and getattr(params(), name) is not None, key
    for key, value in DERIVED.items():
        assert dumped[key] == value, key


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
