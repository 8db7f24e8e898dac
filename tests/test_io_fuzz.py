"""Fuzzing of the gscan.io readers: any file content gives a valid frame or InputError, nothing else."""
from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gscan.errors import InputError
from gscan.io import load_frame, open_sequence, read_mask, read_nyu_depth, read_sun_depth, read_ycbv_meta
from gscan.io.camera import Intrinsics, RGBDFrame

FUZZ = settings(max_examples=25, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])

HEADERS = [b"", b"\x89PNG\r\n\x1a\n", b"\xff\xd8\xff\xe0", b"P5 8 6 65535\n", b"P6 8 6 255\n", b"II*\x00",
           b"BM", b"MATLAB 5.0 MAT-file"]


def _write(path: Path, img: np.ndarray) -> bool:
    try:
        ok, buf = cv2.imencode(path.suffix, img)
    except cv2.error:
        return False
    if ok:
        buf.tofile(str(path))
    return bool(ok)


def _check_frame(fr: RGBDFrame, w: int, h: int) -> None:
    assert fr.color.shape == (h, w, 3) and fr.color.dtype == np.uint8
    assert fr.depth.shape == (h, w) and fr.depth.dtype == np.float32
    assert np.all(np.isfinite(fr.depth)) and np.all(fr.depth >= 0) and np.any(fr.depth > 0)
    assert fr.mask is None or (fr.mask.shape == (h, w) and fr.mask.dtype == bool)


@pytest.fixture(scope="module")
def fuzz_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder in the run's temporary folder for the examples' files (each example makes and removes its own
    sub-folder; Hypothesis runs many examples per test, so the function-scoped tmp_path does not fit)."""
    return tmp_path_factory.mktemp("fuzz")


@FUZZ
@given(header=st.sampled_from(HEADERS), body=st.binary(min_size=0, max_size=600),
       which=st.sampled_from(["color", "depth", "mask", "sun", "nyu", "meta"]))
def test_random_bytes(fuzz_dir: Path, header: bytes, body: bytes, which: str):
    tmp = Path(tempfile.mkdtemp(prefix="gscan_fuzz_", dir=fuzz_dir))
    try:
        good_c, good_d, good_m = tmp / "c.png", tmp / "d.png", tmp / "m.png"
        rng = np.random.default_rng(0)
        _write(good_c, rng.integers(0, 255, (6, 8, 3), dtype=np.uint8))
        _write(good_d, np.full((6, 8), 800, np.uint16))
        _write(good_m, np.full((6, 8), 255, np.uint8))
        junk = tmp / {"meta": "x-meta.mat", "nyu": "x.pgm"}.get(which, "x.png")
        junk.write_bytes(header + body)
        intr = Intrinsics(8.0, 8.0, 3.5, 2.5, 8, 6)
        try:
            if which == "color":
                _check_frame(load_frame(junk, good_d, intr), 8, 6)
            elif which == "depth":
                _check_frame(load_frame(good_c, junk, intr, check_range=False), 8, 6)
            elif which == "mask":
                _check_frame(load_frame(good_c, good_d, intr, mask_path=junk), 8, 6)
                read_mask(junk)
            elif which == "sun":
                assert read_sun_depth(junk).dtype == np.float32
            elif which == "nyu":
                assert read_nyu_depth(junk).dtype == np.float32
            else:
                read_ycbv_meta(junk)
        except InputError as e:
            assert junk.name in str(e) and "\n" not in str(e)
    finally:
        shutil.rmtree(tmp)


@st.composite
def images(draw):
    """Random arrays cv2 can write as PNG (uint8/uint16, 1/3/4 channels) plus float32 TIFF."""
    h = draw(st.integers(1, 24))
    w = draw(st.integers(1, 24))
    dtype = draw(st.sampled_from([np.uint8, np.uint16, np.float32]))
    ch = draw(st.sampled_from([1, 3, 4]))
    seed = draw(st.integers(0, 2**16))
    zero_frac = draw(st.sampled_from([0.0, 0.5, 1.0]))
    rng = np.random.default_rng(seed)
    shape = (h, w) if ch == 1 else (h, w, ch)
    if dtype == np.float32:
        a = rng.uniform(0, 3, shape).astype(np.float32)
    else:
        a = rng.integers(0, np.iinfo(dtype).max, shape, dtype=dtype, endpoint=True)
    a[rng.random((h, w)) < zero_frac] = 0
    return a


@FUZZ
@given(color=images(), depth=images(), scale=st.sampled_from([1e-4, 1e-3, 1 / 5000, 1.0]), same_size=st.booleans())
def test_random_images(fuzz_dir: Path, color: np.ndarray, depth: np.ndarray, scale: float, same_size: bool):
    tmp = Path(tempfile.mkdtemp(prefix="gscan_fuzz_", dir=fuzz_dir))
    if same_size:  # a plausible 16-bit depth of the colour's size, so that valid frames occur too
        mm = np.resize(depth.astype(np.float64).ravel(), color.shape[:2])
        depth = (300 + mm % 3000).astype(np.uint16)
        scale = 1e-3
    try:
        c = tmp / ("c.tiff" if color.dtype == np.float32 else "c.png")
        d = tmp / ("d.tiff" if depth.dtype == np.float32 else "d.png")
        if not (_write(c, color) and _write(d, depth)):
            return
        h, w = color.shape[:2]
        try:
            fr = load_frame(c, d, Intrinsics(10.0, 10.0, w / 2, h / 2, w, h), depth_scale=scale)
        except InputError as e:
            assert ("c." in str(e) or "d." in str(e)) and "\n" not in str(e)
            return
        _check_frame(fr, w, h)
        # raw * scale in float32 against the same product: rounding, 1e-6 relative = 16 float32 ulps
        np.testing.assert_allclose(fr.depth, depth * np.float32(scale), rtol=1e-6)
        assert depth.dtype == np.uint16 and depth.ndim == 2 and depth.shape == (h, w)
        med = float(np.median(fr.depth[fr.depth > 0]))
        assert 0.05 <= med <= 20.0
    finally:
        shutil.rmtree(tmp)


@FUZZ
@given(n=st.integers(1, 4), seed=st.integers(0, 2**16),
       damage=st.lists(st.sampled_from(["none", "junk_color", "junk_depth", "drop_depth", "small_depth",
                                        "byte_depth", "junk_mask", "junk_pose", "junk_camk"]), min_size=4,
                       max_size=4))
def test_random_capture_sequences(fuzz_dir: Path, n: int, seed: int, damage: list[str]):
    tmp = Path(tempfile.mkdtemp(prefix="gscan_fuzz_", dir=fuzz_dir))
    try:
        rng = np.random.default_rng(seed)
        root = tmp / "seq"
        for sub in ("rgb", "depth", "masks", "annotated_poses"):
            (root / sub).mkdir(parents=True)
        (root / "cam_K.txt").write_text("20 0 7.5\n0 20 5.5\n0 0 1\n")
        for i in range(n):
            name = f"{i:04d}"
            _write(root / "rgb" / f"{name}.png", rng.integers(0, 255, (12, 16, 3), dtype=np.uint8))
            _write(root / "depth" / f"{name}.png", rng.integers(500, 1500, (12, 16), dtype=np.uint16))
            _write(root / "masks" / f"{name}.png", (rng.random((12, 16)) > 0.5).astype(np.uint8) * 255)
            np.savetxt(root / "annotated_poses" / f"{name}.txt", np.eye(4))
            junk = rng.integers(0, 256, int(rng.integers(0, 200)), dtype=np.uint8).tobytes()
            kind = damage[i]
            if kind == "junk_color":
                (root / "rgb" / f"{name}.png").write_bytes(junk)
            elif kind == "junk_depth":
                (root / "depth" / f"{name}.png").write_bytes(b"\x89PNG\r\n\x1a\n" + junk)
            elif kind == "drop_depth":
                (root / "depth" / f"{name}.png").unlink()
            elif kind == "small_depth":
                _write(root / "depth" / f"{name}.png", np.full((6, 8), 900, np.uint16))
            elif kind == "byte_depth":
                _write(root / "depth" / f"{name}.png", np.full((12, 16), 90, np.uint8))
            elif kind == "junk_mask":
                (root / "masks" / f"{name}.png").write_bytes(junk)
            elif kind == "junk_pose":
                (root / "annotated_poses" / f"{name}.txt").write_bytes(junk)
            elif kind == "junk_camk":
                (root / "cam_K.txt").write_bytes(junk)
        try:
            seq = open_sequence(root)
        except InputError as e:
            assert "\n" not in str(e)
            return
        assert len(seq) + len(seq.problems) == n
        assert set(seq.names).isdisjoint(seq.problems)
        loaded = list(seq.iter_frames(skip_bad=True))
        for fr in loaded:
            _check_frame(fr, 16, 12)
        assert len(loaded) + len(seq.problems) == n
    finally:
        shutil.rmtree(tmp)
