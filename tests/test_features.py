"""gscan.features on the real Open3D RGB-D frames and on small synthetic images."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gscan.features import (
    KINDS,
    FeatureParams,
    Features,
    descriptor_distances,
    empty_features,
    extract_features,
)
from gscan.io.camera import Intrinsics, RGBDFrame, lift_keypoints, load_intrinsics, project


def _load_real(real_dir: Path, idx: int) -> RGBDFrame:
    root = real_dir / "open3d_rgbd"
    intr = load_intrinsics(root / "camera_primesense.json")
    color = cv2.imread(str(root / "RGBD" / "color" / f"{idx:05d}.jpg"), cv2.IMREAD_COLOR)
    depth = cv2.imread(str(root / "RGBD" / "depth" / f"{idx:05d}.png"), cv2.IMREAD_UNCHANGED)
    assert color is not None and depth is not None and depth.dtype == np.uint16
    return RGBDFrame(f"{idx:05d}", cv2.cvtColor(color, cv2.COLOR_BGR2RGB), depth.astype(np.float32) / 1000.0, intr)


@pytest.fixture(scope="module")
def real_frame(real_dir: Path) -> RGBDFrame:
    return _load_real(real_dir, 0)


@pytest.fixture(scope="module")
def real_features(real_frame: RGBDFrame) -> dict[str, Features]:
    return {k: extract_features(real_frame, FeatureParams(kind=k, max_keypoints=100000)) for k in KINDS}


def _synthetic_frame(depth: np.ndarray, seed: int = 0) -> RGBDFrame:
    """[H x W] depth with a random blob texture (plenty of SIFT/ORB corners)."""
    H, W = depth.shape
    rng = np.random.default_rng(seed)
    img = np.full((H, W, 3), 128, np.uint8)
    for _ in range(120):
        c = (int(rng.integers(0, W)), int(rng.integers(0, H)))
        cv2.circle(img, c, int(rng.integers(3, 12)), tuple(int(x) for x in rng.integers(0, 256, 3)), -1)
        p1 = (int(rng.integers(0, W)), int(rng.integers(0, H)))
        cv2.rectangle(img, p1, (p1[0] + int(rng.integers(4, 20)), p1[1] + int(rng.integers(4, 20))),
                      tuple(int(x) for x in rng.integers(0, 256, 3)), -1)
    intr = Intrinsics(300.0, 300.0, (W - 1) / 2, (H - 1) / 2, W, H)
    return RGBDFrame("synthetic", img, depth.astype(np.float32), intr)


def _arrays(f: Features) -> tuple[np.ndarray, ...]:
    return f.pixels, f.points, f.descriptors, f.scales


@pytest.mark.parametrize("kind", KINDS)
def test_deterministic_and_thread_independent(real_frame, real_features, kind):
    a = real_features[kind]
    b = extract_features(real_frame, FeatureParams(kind=kind, max_keypoints=100000))
    assert len(a) > 200
    for x, y in zip(_arrays(a), _arrays(b), strict=True):
        assert np.array_equal(x, y)
    n_threads = cv2.getNumThreads()
    try:
        cv2.setNumThreads(1)
        c = extract_features(real_frame, FeatureParams(kind=kind, max_keypoints=100000))
    finally:
        cv2.setNumThreads(n_threads)
    for x, y in zip(_arrays(a), _arrays(c), strict=True):
        assert np.array_equal(x, y)


@pytest.mark.parametrize("kind", KINDS)
def test_dtypes_shapes_and_order(real_features, kind):
    f = real_features[kind]
    assert f.pixels.dtype == np.float32 and f.points.dtype == np.float32 and f.scales.dtype == np.float32
    assert f.descriptors.shape == (len(f), 32 if kind == "orb" else 128)
    assert f.descriptors.dtype == (np.uint8 if kind == "orb" else np.float32)
    assert f.metric == ("hamming" if kind == "orb" else "l2")
    assert np.all(f.scales > 0)


@pytest.mark.parametrize("kind", ["sift", "orb"])
def test_cap_keeps_the_strongest_prefix(real_frame, real_features, kind):
    full = real_features[kind]
    capped = extract_features(real_frame, FeatureParams(kind=kind, max_keypoints=50))
    assert len(capped) == 50
    if kind == "sift":  # SIFT detects everything; the cap only truncates the strength-sorted list
        for x, y in zip(_arrays(capped), _arrays(full.subset(np.arange(50))), strict=True):
            assert np.array_equal(x, y)


def test_cap_matches_opencv_reference(real_frame):
    """The 50 kept SIFT keypoints are the 50 largest responses among OpenCV's valid-depth keypoints."""
    gray = cv2.cvtColor(real_frame.color, cv2.COLOR_RGB2GRAY)
    kps = cv2.SIFT_create().detect(gray, None)
    px = np.array([k.pt for k in kps])
    resp = np.array([k.response for k in kps])
    _, valid = lift_keypoints(px, real_frame.depth, real_frame.intrinsics, window=2)
    top = np.argsort(-resp[valid], kind="stable")[:50]
    ref = {tuple(p) for p in px[valid][top].astype(np.float32).tolist()}
    capped = extract_features(real_frame, FeatureParams(kind="sift", max_keypoints=50))
    assert {tuple(p) for p in capped.pixels.tolist()} == ref


def _describe_all(frame: RGBDFrame, params: FeatureParams, mask: np.ndarray | None) -> tuple[np.ndarray, ...]:
    """The reference: every keypoint described (detectAndCompute, no strongest-n cut), then the same filter,
    order and cap as extract_features. Returns (pixels, descriptors)."""
    gray = cv2.cvtColor(frame.color, cv2.COLOR_RGB2GRAY)
    det = cv2.SIFT_create(nfeatures=0, nOctaveLayers=params.sift_n_octave_layers,
                          contrastThreshold=params.sift_contrast_threshold,
                          edgeThreshold=params.sift_edge_threshold, sigma=params.sift_sigma)
    kps, desc = det.detectAndCompute(gray, None if mask is None else mask.astype(np.uint8) * 255)
    px = np.array([k.pt for k in kps], dtype=np.float64)
    resp, angle = np.array([k.response for k in kps]), np.array([k.angle for k in kps])
    size = np.array([k.size for k in kps], dtype=np.float32)
    _, keep = lift_keypoints(px, frame.depth, frame.intrinsics, window=params.lift_window,
                             max_rel_spread=params.lift_max_rel_spread, min_valid_frac=params.lift_min_valid_frac)
    if mask is not None:
        keep &= mask[np.rint(px[:, 1]).astype(int).clip(0, mask.shape[0] - 1),
                     np.rint(px[:, 0]).astype(int).clip(0, mask.shape[1] - 1)]
    idx = np.flatnonzero(keep)
    idx = idx[np.lexsort((size[idx], angle[idx], px[idx, 0], px[idx, 1], -resp[idx]))][: params.max_keypoints]
    return px[idx].astype(np.float32), desc[idx]


@pytest.mark.parametrize("source,cap", [("sample", 2000), ("real", 50), ("real", 3)])
def test_sift_describing_the_strongest_gives_what_describing_all_gives(real_frame, source, cap, monkeypatch):
    """SIFT on a whole frame describes only its strongest keypoints: the kept keypoints, their order and their
    descriptors are those of describing every keypoint; also masked (every keypoint in the mask described),
    and when the strongest keypoints lack depth (the depth under them erased), which describes all of them in a
    second detection."""
    import gscan.features.keypoints as features
    from gscan.demo import SAMPLES
    from gscan.io import open_sequence

    frame = real_frame if source == "real" else open_sequence(SAMPLES / "capture")[0]
    described: list[int] = []  # keypoints OpenCV described, per detection
    detect = features._detect

    def counted(*a, **k):
        out = detect(*a, **k)
        described.append(len(out))
        return out

    monkeypatch.setattr(features, "_detect", counted)
    H, W = frame.depth.shape
    box = np.zeros((H, W), bool)
    box[H // 5:H * 4 // 5, W // 4:W * 3 // 4] = True
    every = extract_features(frame, FeatureParams(kind="sift", max_keypoints=100000))  # all with depth
    holes = frame.depth.copy()
    for u, v in np.rint(every.pixels[: cap + 40]).astype(int):  # no depth under the strongest cap + 40
        holes[max(0, v - 3):v + 4, max(0, u - 3):u + 4] = 0.0
    no_depth = RGBDFrame(frame.name, frame.color, holes, frame.intrinsics)
    params = FeatureParams(kind="sift", max_keypoints=cap)
    for f, mask, detections in ((frame, None, 1), (frame, box, 1), (no_depth, None, 2)):
        described.clear()
        got = extract_features(f, params, mask=mask)
        want_px, want_desc = _describe_all(f, params, mask)
        assert len(got) == len(want_px) >= min(cap, 50)
        assert np.array_equal(got.pixels, want_px) and np.array_equal(got.descriptors, want_desc)
        assert len(described) == detections, (mask is not None, described)
        if mask is None:  # the first detection described fewer keypoints than the frame has
            assert described[0] < len(every), (described, len(every))


@pytest.mark.parametrize("source, scan_cap, check_cap", [("sample", 2000, 800), ("real", 150, 60)])
def test_an_extraction_started_from_another_ones_detection_gets_its_own_result(real_frame, source, scan_cap,
                                                                              check_cap, monkeypatch):
    """A whole-frame detection (`detect`) made for one extraction serves another of the same colour image: the
    scan's camera check takes its 800 strongest keypoints on a flat depth from the detection the features stage
    makes, and the features stage then starts from it. Each gets exactly what it gets detecting alone (what
    describing every keypoint gives), without detecting again, unless the detection's cut leaves too few
    keypoints with depth (the depth under the strongest erased): then it detects again, with the same result."""
    import gscan.features.keypoints as features
    from gscan.demo import SAMPLES
    from gscan.io import open_sequence

    frame = real_frame if source == "real" else open_sequence(SAMPLES / "capture")[0]
    scan_params = FeatureParams(kind="rootsift", max_keypoints=scan_cap)
    check_params = FeatureParams(kind="rootsift", max_keypoints=check_cap, lift_window=0)
    flat = RGBDFrame(frame.name, frame.color, np.ones_like(frame.depth), frame.intrinsics)
    every = extract_features(frame, FeatureParams(kind="sift", max_keypoints=100000))
    n_all = len(features._detect(cv2.cvtColor(frame.color, cv2.COLOR_RGB2GRAY), None, scan_params))
    holes = frame.depth.copy()
    for u, v in np.rint(every.pixels[: scan_cap + 200]).astype(int):  # no depth under the strongest
        holes[max(0, v - 3):v + 4, max(0, u - 3):u + 4] = 0.0
    no_depth = RGBDFrame(frame.name, frame.color, holes, frame.intrinsics)
    calls: list[int] = []
    detect = features._detect

    def counted(*a, **k):
        calls.append(1)
        return detect(*a, **k)

    for f, params, again in ((flat, check_params, 0), (frame, scan_params, 0), (no_depth, scan_params, 1)):
        want = extract_features(f, params)
        det = features.detect(frame, scan_params)
        assert 0 < det.n_best <= len(det) < n_all  # a cut: fewer keypoints described than the frame has
        monkeypatch.setattr(features, "_detect", counted)
        calls.clear()
        got = extract_features(f, params, detection=det)
        monkeypatch.setattr(features, "_detect", detect)
        assert len(calls) == again
        assert len(got) == len(want) > 0
        for a, b in ((got.pixels, want.pixels), (got.points, want.points), (got.descriptors, want.descriptors),
                     (got.scales, want.scales)):
            assert np.array_equal(a, b)
    with pytest.raises(ValueError, match="other detector settings"):  # ORB's detection follows max_keypoints
        extract_features(frame, FeatureParams(kind="orb", max_keypoints=100),
                         detection=features.detect(frame, FeatureParams(kind="orb", max_keypoints=500)))


def test_sift_norm_and_rootsift_unit_norm(real_features):
    sift, root = real_features["sift"], real_features["rootsift"]
    assert np.array_equal(sift.pixels, root.pixels)  # same keypoints, same order
    n = np.linalg.norm(sift.descriptors, axis=1)
    assert 490 < np.median(n) < 530  # OpenCV's SIFT scale (documented for eps_f)
    # RootSIFT is L2-normalised in float32: rounding ~1e-7 over 128 values
    np.testing.assert_allclose(np.linalg.norm(root.descriptors, axis=1), 1.0, atol=1e-5)
    ref = np.sqrt(sift.descriptors / sift.descriptors.sum(axis=1, keepdims=True))
    # the reference in float32: the same operations in another order, rounding ~1e-7
    np.testing.assert_allclose(root.descriptors, ref, atol=1e-5)


def test_mask_restricts_keypoints(real_frame, real_features):
    H, W = real_frame.depth.shape
    mask = np.zeros((H, W), bool)
    mask[100:380, 150:400] = True
    for kind in ("rootsift", "orb"):
        f = extract_features(real_frame, FeatureParams(kind=kind, max_keypoints=100000), mask=mask)
        assert 20 < len(f) < len(real_features[kind])
        u = np.rint(f.pixels[:, 0]).astype(int)
        v = np.rint(f.pixels[:, 1]).astype(int)
        assert mask[v, u].all()
    assert len(extract_features(real_frame, FeatureParams(), mask=np.zeros((H, W), bool))) == 0
    with pytest.raises(ValueError):
        extract_features(real_frame, FeatureParams(), mask=np.ones((H, W + 1), bool))


def test_points_consistent_with_depth(real_frame, real_features):
    depth = real_frame.depth
    H, W = depth.shape
    for kind in KINDS:
        f = real_features[kind]
        # the 3D point re-projects onto its keypoint and its depth is a valid depth of the 5x5 window
        np.testing.assert_allclose(project(f.points, real_frame.intrinsics), f.pixels, atol=2e-3)
        u = np.rint(f.pixels[:, 0]).astype(int)
        v = np.rint(f.pixels[:, 1]).astype(int)
        for i in range(0, len(f), 7):
            win = depth[max(0, v[i] - 2):v[i] + 3, max(0, u[i] - 2):u[i] + 3]
            valid = win[win > 0]
            assert valid.size >= 0.5 * 25
            # the median of float32 depths, read back: float32 rounding (6e-8 m at 1 m)
            assert f.points[i, 2] == pytest.approx(np.median(valid), abs=1e-6)
    # keypoints where the frame has no depth are dropped: blank out a band and re-extract
    blank = real_frame.depth.copy()
    blank[:, 200:440] = 0.0
    fb = extract_features(RGBDFrame("blank", real_frame.color, blank, real_frame.intrinsics),
                          FeatureParams(kind="sift", max_keypoints=100000))
    ub = np.rint(fb.pixels[:, 0])
    assert len(fb) > 50 and not np.any((ub >= 203) & (ub <= 436))
    assert len(fb) < len(real_features["sift"])


def test_synthetic_step_depth():
    """Plane at 1 m (left) and 2 m (right): points sit on their plane; none straddles the step."""
    H, W = 240, 320
    depth = np.ones((H, W), np.float32)
    depth[:, W // 2:] = 2.0
    frame = _synthetic_frame(depth)
    for kind in KINDS:
        f = extract_features(frame, FeatureParams(kind=kind, max_keypoints=100000))
        assert len(f) > 30
        u = np.rint(f.pixels[:, 0])
        expected_z = np.where(u < W // 2, 1.0, 2.0)
        np.testing.assert_array_equal(f.points[:, 2], expected_z.astype(np.float32))
        assert not np.any(np.abs(u - (W // 2 - 0.5)) < 2.0)  # the 5x5 window would mix 1 m and 2 m


def test_orb_hamming_equals_bruteforce(real_features):
    d = real_features["orb"].descriptors
    a, b = d[:150], d[100:400]
    bits_a, bits_b = np.unpackbits(a, axis=1).astype(int), np.unpackbits(b, axis=1).astype(int)
    ref = (bits_a[:, None, :] != bits_b[None, :, :]).sum(axis=2)
    D = descriptor_distances(a, b, "orb")
    assert D.dtype == np.float32 and D.shape == (150, 300)
    np.testing.assert_array_equal(D, ref)
    np.testing.assert_array_equal(descriptor_distances(a, b, "orb", chunk_bytes=1000), ref)  # many chunks
    assert np.all(np.diag(descriptor_distances(a, a, "orb")) == 0)


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 40), st.integers(1, 40), st.integers(1, 12))
def test_hamming_arbitrary_width_bruteforce(seed, ns, nt, nbytes):
    rng = np.random.default_rng(seed)
    a = rng.integers(0, 256, (ns, nbytes), dtype=np.uint8)
    b = rng.integers(0, 256, (nt, nbytes), dtype=np.uint8)
    ref = (np.unpackbits(a, axis=1)[:, None, :] != np.unpackbits(b, axis=1)[None, :, :]).sum(axis=2)
    np.testing.assert_array_equal(descriptor_distances(a, b, "orb", chunk_bytes=64), ref)


@pytest.mark.parametrize("kind", ["sift", "rootsift"])
def test_l2_equals_bruteforce(real_features, kind):
    d = real_features[kind].descriptors
    a, b = d[:120], d[60:300]
    ref = np.linalg.norm(a.astype(np.float64)[:, None, :] - b.astype(np.float64)[None, :, :], axis=2)
    D = descriptor_distances(a, b, kind)
    assert D.dtype == np.float32 and D.shape == ref.shape
    scale = np.linalg.norm(a, axis=1).max()
    # distances by a float32 BLAS product (|a|^2 + |b|^2 - 2ab) against a float64 reference: cancellation costs ~1e-4 of
    # the descriptors' scale; 1e-3 leaves 10x
    np.testing.assert_allclose(D, ref, atol=1e-3 * scale, rtol=1e-5)
    assert np.all(D >= 0)


def test_feature_containers():
    e = empty_features("orb")
    assert len(e) == 0 and e.descriptors.shape == (0, 32) and e.descriptors.dtype == np.uint8
    assert empty_features("sift").descriptors.shape == (0, 128)
    assert descriptor_distances(e.descriptors, np.zeros((3, 32), np.uint8), "orb").shape == (0, 3)
    f = Features(np.arange(6, dtype=np.float32).reshape(3, 2), np.ones((3, 3), np.float32),
                 np.eye(3, 128, dtype=np.float32), "rootsift", np.array([1, 2, 3], np.float32))
    s = f.subset(np.array([2, 0]))
    np.testing.assert_array_equal(s.scales, [3, 1])
    np.testing.assert_array_equal(f.subset(np.array([True, False, True])).pixels, f.pixels[[0, 2]])
    with pytest.raises(ValueError):
        Features(f.pixels, f.points, f.descriptors[:, :32], "rootsift", f.scales)
    with pytest.raises(ValueError):
        FeatureParams(kind="surf")
    with pytest.raises(ValueError):
        descriptor_distances(np.zeros((2, 32), np.float32), np.zeros((2, 32), np.float32), "orb")
    with pytest.raises(ValueError):
        descriptor_distances(np.zeros((2, 128), np.float32), np.zeros((2, 64), np.float32), "sift")
