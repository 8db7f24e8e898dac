"""BOP datasets with model-free onboarding captures (`gscan.synth.bop`) and their scan (`gscan.io.captures`).

- the written folder reads back with gscan's BOP reader (always) and with the BOP toolkit's own loaders
  (`bop_toolkit_lib.inout`, where the toolkit is importable: it is not a dependency of gscan; put a checkout of it
  and its imports pypng and imageio on PYTHONPATH to run that test);
- a dataset's onboarding folder given to `gscan scan` without --obj-id while it holds several objects, or with an
  id it does not hold: exit code 2 and one line naming the folder;
- (slow) `gscan scan DATASET -o OUT --obj-id N --json`: both captures registered into one frame, every frame
  within 5 deg / 2 cm of its ground truth (read for the evaluation only), frames named `obj_XXXXXX_up/IMID`.
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gscan import synth
from gscan.evaluate.metrics import frame_errors
from gscan.geometry.transforms import inv_T
from gscan.io import open_sequence
from gscan.synth.bop import BopOnboarding, write_bop_onboarding
from gscan.synth.cases import two_sided_frames
from gscan.template.db import TemplateDB

ROOT = Path(__file__).resolve().parents[1]
SMALL = synth.DEFAULT_INTRINSICS.scaled(0.5)  # 320 x 240: the read-back and error tests render few small images
WRONG = (5.0, 0.02)  # deg, m: a frame registered beyond this from its ground truth is wrong (issue 17's bound)


def _box(seed: int = 3) -> synth.TexturedMesh:
    return synth.box_mesh((0.08, 0.06, 0.12), synth.procedural_box_texture(seed, (256, 384)), name=f"box{seed}")


@pytest.fixture(scope="module")
def small_dataset(tmp_path_factory) -> BopOnboarding:
    """Object 3's onboarding captures, 2 small images each, with masks; object 7's beside them."""
    root = tmp_path_factory.mktemp("bop") / "dataset"
    write_bop_onboarding(root, 7, _box(5), n_views=2, intr=SMALL, model=False)
    return write_bop_onboarding(root, 3, _box(), n_views=2, intr=SMALL, masks=True)


def test_reads_back_with_gscan(small_dataset: BopOnboarding):
    """Images, intrinsics, depth in metres and ground truth read back with gscan's BOP reader as rendered."""
    up, down = two_sided_frames(_box(), n_views=2, intr=SMALL)  # the same renders (seeded)
    assert list(small_dataset.captures) == ["obj_000003_up", "obj_000003_down"]
    for (name, path), rendered in zip(small_dataset.captures.items(), (up, down), strict=True):
        seq = open_sequence(path, obj_id=3)
        assert seq.names == small_dataset.frames[name] == ["000000", "000001"]
        for i, f in enumerate(rendered):
            frame = seq[i]
            np.testing.assert_allclose(frame.intrinsics.K, SMALL.K)
            np.testing.assert_allclose(frame.depth, f.depth, atol=0.6e-4)  # 0.1 mm steps
            assert (frame.color == f.color).all()
            assert (frame.mask == f.mask).all()
            np.testing.assert_allclose(seq.gt_T_cam_obj[f"{i:06d}"], f.T_cam_obj, atol=1e-9)
        # the other side's poses: the object was moved against the table between the two
    T_up, T_down = up[0].T_cam_obj, down[0].T_cam_obj
    assert np.abs(T_up[:3, :3] - T_down[:3, :3]).max() > 0.5


def test_reads_back_with_the_bop_toolkit(small_dataset: BopOnboarding):
    """The BOP toolkit's own loaders read the dataset: cam_K, depth_scale (raw * scale = mm), the poses in mm and
    the model in mm."""
    inout = pytest.importorskip("bop_toolkit_lib.inout", reason="the BOP toolkit is not on PYTHONPATH")
    up, _ = two_sided_frames(_box(), n_views=2, intr=SMALL)
    path = small_dataset.captures["obj_000003_up"]
    cams = inout.load_scene_camera(path / "scene_camera.json")
    gts = inout.load_scene_gt(path / "scene_gt.json")
    assert sorted(cams) == sorted(gts) == [0, 1]
    for im_id, f in enumerate(up):
        np.testing.assert_allclose(cams[im_id]["cam_K"], SMALL.K)
        depth_mm = inout.load_depth(path / "depth" / f"{im_id:06d}.png") * cams[im_id]["depth_scale"]
        np.testing.assert_allclose(depth_mm, f.depth * 1000.0, atol=0.06)
        (gt,) = gts[im_id]
        assert gt["obj_id"] == 3
        np.testing.assert_allclose(gt["cam_R_m2c"], f.T_cam_obj[:3, :3], atol=1e-9)
        np.testing.assert_allclose(gt["cam_t_m2c"].ravel(), 1000.0 * f.T_cam_obj[:3, 3], atol=1e-6)
        mask = inout.load_im(path / "mask_visib" / f"{im_id:06d}_000000.png")
        assert ((mask > 0) == f.mask).all()
    assert small_dataset.model is not None
    model = inout.load_ply(small_dataset.model)
    np.testing.assert_allclose(np.ptp(model["pts"], axis=0), [80.0, 60.0, 120.0], atol=1e-3)
    assert len(model["faces"]) == len(_box().triangles)
    cam = inout.load_cam_params(small_dataset.root / "camera.json")
    np.testing.assert_allclose(cam["K"], SMALL.K)


def test_scan_meta_names_the_captures_layout(small_dataset: BopOnboarding):
    """The template's meta records the onboarding captures' layout (bop); the dataset folder itself is no RGB-D
    layout (detecting one refused it)."""
    from gscan.scanning.options import ScanOptions
    from gscan.scanning.output import scan_meta

    assert scan_meta([small_dataset.root], ScanOptions(obj_id=3))["format"] == "bop"


def _cli(*args: str | Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "gscan.cli", *map(str, args)], capture_output=True, text=True,
                          cwd=ROOT, timeout=600, check=False)


@pytest.mark.parametrize(("extra", "words"), [((), ["3, 7", "choose one", "--obj-id"]),
                                              (("--obj-id", "9"), ["object 9", "3, 7"])])
def test_onboarding_errors(small_dataset: BopOnboarding, tmp_path: Path, extra: tuple[str, ...], words: list[str]):
    """Several objects and no --obj-id, or an id the folder does not hold: exit 2, one line naming the folder,
    no output written."""
    out = tmp_path / "out"
    out.mkdir()
    r = _cli("scan", small_dataset.root, "-o", out / "obj.gscan", "--json", *extra)
    assert r.returncode == 2, r.stderr
    assert r.stdout == "" and "Traceback" not in r.stderr
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, r.stderr
    assert str(small_dataset.root) in lines[0] or small_dataset.root.name in lines[0], lines[0]
    for w in words:
        assert w in lines[0], lines[0]
    assert list(out.iterdir()) == []


@pytest.mark.slow
def test_scan_of_onboarding_captures(tmp_path: Path):
    """`gscan scan DATASET -o OUT --obj-id 2 --json` of 12 + 12 views of a box, upright then upside down: both
    captures joined, every frame registered within 5 deg / 2 cm of its ground truth; frames named
    `obj_000002_up/IMID` and `obj_000002_down/IMID`."""
    data = write_bop_onboarding(tmp_path / "dataset", 2, _box(), n_views=12)
    out = tmp_path / "obj.gscan"
    r = _cli("scan", data.root, "-o", out, "--obj-id", "2", "--json")
    assert r.returncode == 0, r.stderr[-3000:]
    res = json.loads(r.stdout)
    assert [c["name"] for c in res["captures"]] == ["obj_000002_up", "obj_000002_down"]
    assert all(c["joined"] for c in res["captures"]), res["captures"]
    names = {f"{c}/{f}" for c, fs in data.frames.items() for f in fs}
    assert res["frames"] == res["registered"] == 24 and res["unregistered"] == [], res
    with TemplateDB.open(out) as db:
        poses = {n: np.asarray(T) for n, T in db.poses()["frames"].items()}
        assert db.get_meta("format") == "bop"  # the onboarding captures' layout, not the dataset folder's
    assert set(poses) == names
    gt = {f"{c}/{n}": inv_T(T) for c, p in data.captures.items()
          for n, T in open_sequence(p, obj_id=2).gt_T_cam_obj.items()}  # evaluation only
    fe = frame_errors(poses, gt)
    assert fe.wrong(*WRONG) == [], {n: (fe.rot_deg[n], fe.trans_m[n]) for n in fe.wrong(*WRONG)}
