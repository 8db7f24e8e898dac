"""The public API in gscan/__init__.py: every name is there, typed, documented and used here on the bundled
sample; `gscan.scan()` from Python writes the same poses as `gscan scan`."""
from __future__ import annotations

import ast
import inspect
import json
import subprocess
import sys
import typing

import numpy as np
import pytest

import gscan
from gscan.demo import SAMPLES
from gscan.features import descriptor_distances
from gscan.geometry.transforms import inv_T, pose_error
from gscan.matching.gmatch import default_eps_f
from gscan.template.db import TemplateDB
from tests.conftest import ROOT

CAPTURE = SAMPLES / "capture"
HELDOUT = SAMPLES / "heldout"

PUBLIC = {
    "__version__", "open_sequence", "load_frame", "Intrinsics", "RGBDFrame", "extract_features", "Features",
    "FeatureParams", "gmatch", "GMatchParams", "register_frames", "RegisterParams", "PairResult", "scan",
    "ScanConfig", "ScanResult", "template_from_mesh", "TemplateResult", "TemplateDB", "Estimator", "EstimateParams",
    "EstimateResult", "export", "serve", "GscanError", "InputError", "DepthCamera", "ScanOptions", "Tracker",
    "ExportResult",
}
FUNCTIONS = ("open_sequence", "load_frame", "extract_features", "gmatch", "register_frames", "scan",
             "template_from_mesh", "export", "serve")


def test_the_public_names_are_typed_and_documented():
    assert set(gscan.__all__) == PUBLIC and set(dir(gscan)) == PUBLIC
    # __all__ names exactly what the package resolves lazily, and the version
    lazy = set(gscan._EXPORTS) | {"__version__"}
    assert set(gscan.__all__) == lazy, sorted(set(gscan.__all__) ^ lazy)
    assert isinstance(gscan.__version__, str) and len(gscan.__version__.split(".")) == 3
    for name in PUBLIC - {"__version__"}:
        obj = getattr(gscan, name)
        assert inspect.getdoc(obj), name
    for name in FUNCTIONS:
        sig = inspect.signature(getattr(gscan, name))
        missing = [p for p in sig.parameters.values() if p.annotation is inspect.Parameter.empty]
        assert not missing and sig.return_annotation is not inspect.Signature.empty, (name, missing)
    with pytest.raises(AttributeError):
        gscan.match_frames  # noqa: B018 - replaced by register_frames


def public_names_used(source: str, skip: frozenset[str] = frozenset()) -> set[str]:
    """The names `gscan.NAME` or `from gscan import NAME` in Python source, outside the functions named in skip."""
    used: set[str] = set()

    class Uses(ast.NodeVisitor):
        def visit_FunctionDef(self, node: ast.FunctionDef) -> None:
            if node.name not in skip:
                self.generic_visit(node)

        def visit_Attribute(self, node: ast.Attribute) -> None:
            if isinstance(node.value, ast.Name) and node.value.id == "gscan":
                used.add(node.attr)
            self.generic_visit(node)

        def visit_ImportFrom(self, node: ast.ImportFrom) -> None:
            if node.module == "gscan" and node.level == 0:
                used.update(alias.name for alias in node.names)

    Uses().visit(ast.parse(source))
    return used


def test_every_public_name_is_used_by_a_test():
    """Each name of `gscan.__all__` is used (`gscan.NAME`, `from gscan import NAME`) by some test or fixture in
    tests/ other than the listing test above and this one."""
    skip = frozenset({"test_the_public_names_are_typed_and_documented", "test_every_public_name_is_used_by_a_test"})
    used: set[str] = set()
    for path in sorted((ROOT / "tests").glob("*.py")):
        used |= public_names_used(path.read_text(encoding="utf-8"), skip)
    assert not set(gscan.__all__) - used, sorted(set(gscan.__all__) - used)
    # the check itself: a name only the skipped functions use is not counted
    probe = "import gscan\ndef f():\n    gscan.Tracker\nfrom gscan import scan\n"
    assert public_names_used(probe) == {"Tracker", "scan"} and public_names_used(probe, frozenset({"f"})) == {"scan"}


def test_scan_export_and_serve_are_plain_functions():
    """`gscan.scan`, `gscan.export` and `gscan.serve` are functions (the stages are the subpackages `scanning`,
    `exporters`, `service`), whatever was imported first; `scan` takes one `ScanOptions` value."""
    import types

    import gscan.exporters.jsonfmt as jsonfmt
    import gscan.scanning.pipeline as pipeline
    from gscan import export, scan, serve

    assert scan is gscan.scan and export is gscan.export and serve is gscan.serve
    assert gscan.scanning.pipeline is pipeline and gscan.exporters.jsonfmt is jsonfmt
    assert all(isinstance(f, types.FunctionType) for f in (gscan.scan, gscan.export, gscan.serve))
    assert list(inspect.signature(gscan.scan).parameters)[:3] == ["source", "output", "options"]
    assert list(inspect.signature(gscan.export).parameters)[:3] == ["db_path", "fmt", "out"]
    # in a fresh interpreter the subpackages may be imported (by the estimator) before `gscan.scan` is looked up
    code = ("from gscan.estimate.estimator import Estimator\nimport gscan.service, gscan.exporters\n"
            "import gscan, types\n"
            "print(*(isinstance(f, types.FunctionType) for f in (gscan.scan, gscan.export, gscan.serve)))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert out.stdout.split() == ["True", "True", "True"], out.stderr


def test_reading_frames():
    seq = gscan.open_sequence(CAPTURE)
    assert seq.names[:2] == ["000000", "000001"] and len(seq.names) == 30
    frame = gscan.load_frame(CAPTURE / "rgb" / "000001.jpg", CAPTURE / "depth" / "000001.png", CAPTURE / "cam_K.txt",
                             depth_scale=0.001)
    assert isinstance(frame, gscan.RGBDFrame) and isinstance(frame.intrinsics, gscan.Intrinsics)
    ref = seq["000001"]
    assert frame.intrinsics == ref.intrinsics == gscan.Intrinsics(615.0, 615.0, 319.5, 239.5, 640, 480)
    assert np.array_equal(frame.color, ref.color) and np.array_equal(frame.depth, ref.depth)
    with pytest.raises(gscan.InputError, match="missing.png") as e:
        gscan.load_frame(CAPTURE / "rgb" / "000001.jpg", CAPTURE / "missing.png", CAPTURE / "cam_K.txt")
    assert isinstance(e.value, gscan.GscanError)


def test_reading_a_frame_through_a_depth_camera():
    """A `DepthCamera` at the colour camera's centre and axes, with its intrinsics: the depth reprojected into the
    colour camera lands where it was (the sample's depth is registered to its colour)."""
    K = gscan.Intrinsics(615.0, 615.0, 319.5, 239.5, 640, 480)
    camera = gscan.DepthCamera(K, np.eye(4))
    assert camera.intrinsics == K and gscan.DepthCamera.from_dict(camera.to_dict()) == camera
    rgb, depth = CAPTURE / "rgb" / "000001.jpg", CAPTURE / "depth" / "000001.png"
    plain = gscan.load_frame(rgb, depth, K, depth_scale=0.001)
    frame = gscan.load_frame(rgb, depth, K, depth_scale=0.001, depth_camera=camera)
    assert frame.intrinsics == K and frame.depth.shape == plain.depth.shape
    both = (frame.depth > 0) & (plain.depth > 0)
    assert both.sum() > 0.9 * (plain.depth > 0).sum()
    assert np.median(np.abs(frame.depth[both] - plain.depth[both])) < 1e-4
    # depth images of another size than the depth camera's are refused, naming the file
    small = gscan.DepthCamera(gscan.Intrinsics(300.0, 300.0, 159.5, 119.5, 320, 240))
    with pytest.raises(gscan.InputError, match="000001.png"):
        gscan.load_frame(rgb, depth, K, depth_scale=0.001, depth_camera=small)


def test_keypoints_gmatch_and_registration_of_two_sample_frames():
    """register_frames = extract_features + depth samples + register_features; its pose agrees with the sample's
    ground truth, and GMatch's own list on the same keypoints is consistent with it."""
    seq = gscan.open_sequence(CAPTURE)
    fs_, ft_ = seq["000000"], seq["000001"]
    gt = seq.gt_T_cam_obj
    T_gt = gt["000001"] @ inv_T(gt["000000"])  # source camera -> target camera (the box stands still)
    fp = gscan.FeatureParams(max_keypoints=1000)
    pair = gscan.register_frames(fs_, ft_, gscan.RegisterParams(), feature_params=fp)
    assert isinstance(pair, gscan.PairResult) and pair.accepted, pair.reason
    rot, trans = pose_error(pair.T_tgt_src, T_gt)
    assert rot < 1.0 and trans < 0.005, (rot, trans)
    assert pair.timings_ms["features"] > 0

    fs, ft = gscan.extract_features(fs_, fp), gscan.extract_features(ft_, fp)
    assert isinstance(fs, gscan.Features) and fs.kind == "rootsift" and 100 < len(fs) <= 1000
    assert fs.points.shape == (len(fs), 3) and fs.descriptors.shape == (len(fs), 128)
    from gscan.registration.dense import DenseGeometry
    from gscan.registration.pairwise import register_features

    dense = tuple(DenseGeometry.from_depth(f.depth, f.intrinsics) for f in (fs_, ft_))
    again = register_features(fs, ft, gscan.RegisterParams(), dense=dense)
    assert np.array_equal(again.T_tgt_src, pair.T_tgt_src) and np.array_equal(again.matches, pair.matches)

    params = gscan.GMatchParams()
    res = gscan.gmatch(fs.points, ft.points, descriptor_distances(fs.descriptors, ft.descriptors, fs.kind),
                       default_eps_f(fs.kind), params)
    assert 6 <= len(res.matches) <= params.L
    moved = fs.points[res.matches[:, 0]] @ T_gt[:3, :3].T + T_gt[:3, 3]
    assert np.median(np.linalg.norm(moved - ft.points[res.matches[:, 1]], axis=1)) < 0.01


def test_scan_refuses_bad_input_with_one_line(tmp_path):
    from gscan.scanning.api import scan as scan_function

    assert typing.get_type_hints(scan_function)["return"] is gscan.ScanResult
    with pytest.raises(gscan.InputError, match="nowhere"):
        gscan.scan(tmp_path / "nowhere", tmp_path / "o.gscan", config=gscan.ScanConfig())
    bad = tmp_path / "bad.yaml"
    bad.write_text("registration: {min_matches: -4}\n")
    with pytest.raises(gscan.InputError, match="bad.yaml"):
        gscan.scan(CAPTURE, tmp_path / "o.gscan", config=bad)
    with pytest.raises(ValueError, match="mode"):
        gscan.scan(CAPTURE, tmp_path / "o.gscan", mode="sideways")
    assert not (tmp_path / "o.gscan").exists()


def test_scan_options_are_one_typed_value(tmp_path):
    """`ScanOptions` carries a scan's options: validated when made, changed by name in `gscan.scan(..., **changes)`,
    and taken as is by `gscan.scan(source, output, options)`."""
    opts = gscan.ScanOptions(mode="static-object", intrinsics=str(CAPTURE / "cam_K.txt"))
    assert opts.intrinsics == CAPTURE / "cam_K.txt" and isinstance(opts.config, gscan.ScanConfig)
    assert opts.format == "auto" and opts.segment and not opts.force
    with pytest.raises(ValueError, match="mode"):
        gscan.ScanOptions(mode="sideways")
    with pytest.raises(ValueError, match="format"):
        gscan.ScanOptions(format="jpeg")
    with pytest.raises(TypeError, match="colour"):
        gscan.scan(CAPTURE, tmp_path / "o.gscan", opts, colour="red")
    # an existing output is refused through the options' force = False, and replaced with force = True
    out = tmp_path / "o.gscan"
    out.write_bytes(b"not a template")
    with pytest.raises(gscan.InputError, match="o.gscan"):
        gscan.scan(CAPTURE, out, opts)
    assert out.read_bytes() == b"not a template"
    with pytest.raises(gscan.InputError, match="nowhere"):
        gscan.scan(tmp_path / "nowhere", out, opts, force=True)


def test_scan_result_template_db_estimator_and_export(sample_template, tmp_path):
    """The session's sample template comes from gscan.scan(); estimate a held-back frame, export as JSON."""
    with TemplateDB.open(sample_template) as db:
        s = db.summary()
        assert (s.status, s.views, s.registered, s.source) == ("complete", 30, 30, "scan")
    est = gscan.Estimator.from_path(sample_template, gscan.EstimateParams())
    r = est.estimate(gscan.open_sequence(HELDOUT)["000000"])
    assert isinstance(r, gscan.EstimateResult) and r.found and r.T_cam_obj.shape == (4, 4)
    out = gscan.export(sample_template, "json", tmp_path / "sample.json")
    assert isinstance(out, gscan.ExportResult) and "30 views" in str(out)
    assert out.format == "json" and out.views == 30 and out.path == tmp_path / "sample.json"
    assert json.loads((tmp_path / "sample.json").read_text())["format"] == "gscan-template-json"


def test_tracker_follows_the_sample_capture(sample_template):
    """`Tracker`: a full estimate on the first frame, then each next frame refined from the last pose; every pose
    agrees with the capture's ground truth mapped into the template's frame."""
    from gscan.evaluate.bop19 import template_to_gt

    seq = gscan.open_sequence(CAPTURE)
    T_obj_gt = template_to_gt(sample_template, seq.gt_T_cam_obj)
    tracker = gscan.Tracker(gscan.Estimator.from_path(sample_template))
    steps = [tracker.step(seq[name]) for name in seq.names[:4]]
    assert steps[0].status == "found" and all(s.status in ("found", "tracked") for s in steps[1:])
    assert any(s.status == "tracked" for s in steps[1:])
    for name, s in zip(seq.names[:4], steps, strict=True):
        assert isinstance(s.result, gscan.EstimateResult) and s.frame == name
        rot, trans = pose_error(s.result.T_cam_obj @ T_obj_gt, seq.gt_T_cam_obj[name])
        assert rot < 1.0 and trans < 0.005, (name, s.status, rot, trans)


def test_template_from_mesh_returns_a_record(tmp_path):
    res = gscan.template_from_mesh(SAMPLES / "object" / "box.obj", tmp_path / "box.gscan", n_views=4)
    assert isinstance(res, gscan.TemplateResult)
    assert (res.output, res.views, res.descriptor, res.source) == (tmp_path / "box.gscan", 4, "rootsift", "mesh")
    np.testing.assert_allclose(res.extent_m, [0.16, 0.10, 0.07], atol=1e-6)
    with gscan.TemplateDB.open(res.output) as db:
        assert db.summary().views == 4


@pytest.mark.slow
def test_python_scan_writes_the_poses_of_the_command_line(sample_template, tmp_path):
    """`gscan scan` on the bundled sample and `gscan.scan()` (the session's sample template) agree bit for bit."""
    out = tmp_path / "cli.gscan"
    r = subprocess.run([sys.executable, "-m", "gscan.cli", "scan", str(CAPTURE), "-o", str(out), "--json"],
                       capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert r.returncode == 0, r.stderr[-2000:]
    assert json.loads(r.stdout)["registered"] == 30
    with TemplateDB.open(out) as cli, TemplateDB.open(sample_template) as py:
        a, b = cli.poses(), py.poses()
    assert a["unregistered"] == b["unregistered"] and list(a["frames"]) == list(b["frames"])
    for name in a["frames"]:
        assert np.array_equal(a["frames"][name], b["frames"][name]), name


def test_py_typed_ships():
    assert (ROOT / "gscan" / "py.typed").is_file()
    import tomllib

    data = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert "py.typed" in data["tool"]["setuptools"]["package-data"]["gscan"]
