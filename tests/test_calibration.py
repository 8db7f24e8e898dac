"""The colour camera's focal length from the texture (gscan.scanning.calibration): a capture whose depth is
registered to its colour keeps its intrinsics; one whose colour camera has another focal length gets that one back."""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from gscan.io import open_sequence
from gscan.scanning.calibration import check_colour_focal
from gscan.scanning.capture_mode import STATIC_OBJECT
from gscan.scanning.config import ScanConfig, for_capture
from gscan.synth import cases as C
from gscan.synth import load_textured_mesh

pytestmark = pytest.mark.slow

CFG = for_capture(ScanConfig(), STATIC_OBJECT)
PARAMS = CFG.registration
FEATURES = CFG.features


@pytest.fixture(scope="module")
def box(meshes_dir: Path):
    return load_textured_mesh(meshes_dir / "Whey_Protein_Chocolate_12_Packets" / "model_0.obj")


@pytest.fixture(scope="module")
def capture(box, tmp_path_factory: pytest.TempPathFactory) -> Callable[[float, int], Path]:
    """(colour scale, views) -> the folder of `two_camera_capture(box, ...)` with that colour camera and that many
    views, rendered once for the module (several tests check the same capture); the tests only read it."""
    made: dict[tuple[float, int], Path] = {}

    def get(colour_scale: float, n_views: int) -> Path:
        if (colour_scale, n_views) not in made:
            out = tmp_path_factory.mktemp("capture")
            made[colour_scale, n_views] = C.two_camera_capture(box, out, colour_scale=colour_scale,
                                                               n_views=n_views).path
        return made[colour_scale, n_views]

    return get


def check(path: Path, n: int | None = None, workers: int = 1):
    seq = open_sequence(path)
    names = seq.names[:n]
    return check_colour_focal(lambda i: seq[names[i]], len(names), PARAMS, FEATURES, workers=workers)


def test_registered_depth_keeps_the_given_intrinsics(tmp_path, box):
    """Rendered depth lies on its colour pixels: the texture lines up best at the given focal length, and the
    check stops after s = 1 and its two neighbours."""
    got = check(C.two_camera_capture(box, tmp_path / "one", colour_scale=1.0, n_views=8).path)
    assert got.verdict == "kept" and got.scale == 1.0 and not got.significant, got
    assert got.low <= 1.0 <= got.high and got.high - got.low <= 0.06, got
    assert sorted(got.agreement) == [0.95, 1.0, 1.05] and got.agreement[1.0] > max(got.agreement[0.95],
                                                                                   got.agreement[1.05]) + 0.1


@pytest.mark.parametrize("scale", [0.88, 1.12])
def test_a_colour_camera_of_another_focal_length_is_found(capture, scale):
    """Colour from a camera of `scale` times the given focal length: found within 2 %, significantly better."""
    got = check(capture(scale, 8))
    assert got.verdict == "corrected" and got.significant and abs(got.scale / scale - 1) < 0.02, got
    assert got.low <= scale <= got.high and not got.low <= 1.0 <= got.high, got
    assert got.peak > got.agreement[1.0] + 0.2 and got.p_value < 0.05, got


def test_the_peak_is_sought_on_every_group_when_half_of_them_say_nothing(tmp_path, box):
    """The first frame of every other group unreadable (its two pairs never register): the walk on those groups
    has nothing to go on, and the check finds a colour camera of 1.12 times the focal length on the others."""
    from gscan.scanning.calibration import _starts

    seq = open_sequence(C.two_camera_capture(box, tmp_path / "half", colour_scale=1.12, n_views=24).path)
    names = seq.names
    starts = _starts(len(names), 2, 8)
    gone = set(starts[::2])  # the walk's groups (every other one) lose both their pairs
    assert not gone & {j for i in starts[1::2] for j in (i, i + 1, i + 2)}  # the other groups keep theirs
    got = check_colour_focal(lambda i: None if i in gone else seq[names[i]], len(names), PARAMS, FEATURES)
    assert got is not None and got.pairs == 8 and got.significant and abs(got.scale / 1.12 - 1) < 0.02, got


def test_too_few_frames_cannot_confirm(capture):
    """Three frames make two pairs at most: the check says it could not confirm the focal length, and why; two
    frames make no pair at all."""
    from gscan.scanning.calibration import UNCONFIRMED

    path = capture(0.9, 8)
    for n in (3, 2):
        got = check(path, n=n)
        assert got.verdict == UNCONFIRMED and not got.confirmed and not got.significant and got.scale == 1.0, got
        assert got.reason and ("pairs" in got.reason or "frames" in got.reason), got


def test_two_threads_give_the_same_check(capture):
    """The scan runs the check's frame groups on two threads: every figure is the one a single thread gives (the
    walk and the vertex, on a capture whose colour camera differs)."""
    path = capture(0.9, 8)
    one, two = check(path), check(path, workers=2)
    assert one is not None and len(one.agreement) > 3 and one == two, (one, two)


def test_the_scan_detects_each_frame_once(tmp_path, capture, monkeypatch):
    """The check's keypoints come from the detection the scan's features stage makes, and that stage starts from
    it: on a capture whose colour camera the check corrects (the sequence read again with other intrinsics),
    every frame's whole image is detected once, and every frame is registered."""
    import gscan.features.keypoints as features
    from gscan.scanning.api import scan

    path = capture(0.88, 8)
    shape = open_sequence(path)[0].depth.shape
    whole: list[int] = []
    detect = features._detect

    def counted(gray, mask_u8, params, n_best=0):
        if mask_u8 is None and gray.shape == shape:
            whole.append(1)
        return detect(gray, mask_u8, params, n_best)

    monkeypatch.setattr(features, "_detect", counted)
    res = scan(path, tmp_path / "cap.gscan")
    assert res.camera is not None and res.camera["corrected"], res.camera
    assert len(whole) == 8 and res.registered == 8, (len(whole), res.registered)


def test_a_frame_that_cannot_be_detected_raises_its_error_in_every_thread(tmp_path, box):
    """Two groups share a frame whose colour image SIFT refuses: the thread that detects it raises the error, and
    so does the thread that waited for it (not a missing-keypoints KeyError), whichever raises first."""
    seq = open_sequence(C.two_camera_capture(box, tmp_path / "bad", colour_scale=1.0, n_views=5).path)
    names = seq.names

    def read(i):
        f = seq[names[i]]
        if i == 2:  # groups (0, 1, 2) and (2, 3, 4) share it
            f = replace(f, color=f.color.astype(np.float32))
        return f

    with pytest.raises(ValueError, match="uint8"):
        check_colour_focal(read, len(names), PARAMS, FEATURES, workers=2, detections={})


def test_depth_edges_cannot_tell_without_depth_jumps(tmp_path, box):
    """A flat box lying on a table (rendered, depth registered): no neighbouring depths farther apart than the
    noise allows (1.4 cm at most, 0.6 m away), so the depth-edge test says it cannot tell rather than guess."""
    from gscan.scanning.calibration import SCALES
    from gscan.scanning.depth_edges import edge_evidence

    seq = open_sequence(C.two_camera_capture(box, tmp_path / "edges", colour_scale=1.0, n_views=4).path)
    got = edge_evidence([seq[n] for n in seq.names], SCALES)
    assert got.verdict == "undecided" and not got.frames, got


def test_depth_edges_on_real_frames(real_dir: Path):
    """Real sensors: 7-Scenes' Kinect v1 depth is not registered to its colour (read with the README's one set of
    intrinsics: its jumps lie 10-50 px off the colour edges); the Open3D sample's PrimeSense depth is registered by
    the sensor (its jumps on the colour edges)."""
    import cv2

    from gscan.io.camera import RGBDFrame, load_intrinsics
    from gscan.scanning.calibration import SCALES
    from gscan.scanning.depth_edges import edge_evidence

    seq = open_sequence(real_dir / "7scenes_redkitchen" / "scan")
    kinect = edge_evidence([seq[seq.names[i]] for i in range(0, 60, 8)], SCALES)
    assert kinect.verdict == "not registered" and kinect.offset_px > 10, kinect
    root = real_dir / "open3d_rgbd"
    K = load_intrinsics(root / "camera_primesense.json")
    frames = []
    for i in range(5):
        colour = cv2.cvtColor(cv2.imread(str(root / "RGBD" / "color" / f"{i:05d}.jpg")), cv2.COLOR_BGR2RGB)
        depth = cv2.imread(str(root / "RGBD" / "depth" / f"{i:05d}.png"), cv2.IMREAD_UNCHANGED) / 1000.0
        frames.append(RGBDFrame(f"{i}", colour, depth.astype(np.float32), K))
    primesense = edge_evidence(frames, SCALES)
    assert primesense.verdict == "registered" and primesense.offset_px < 2, primesense
