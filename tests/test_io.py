"""Tests of gscan.io on real RGB-D data (Open3D, TUM, SUN, NYU, YCB-Video) and on small layouts built here."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from gscan.errors import InputError
from gscan.io import (
    associate,
    detect_format,
    load_frame,
    natural_key,
    open_sequence,
    read_depth,
    read_image_rgb,
    read_mask,
    read_nyu_depth,
    read_pose_file,
    read_pose_txt,
    read_sun_depth,
    read_ycbv_meta,
)
from gscan.io.camera import DepthCamera, Intrinsics, backproject, load_depth_camera

PRIMESENSE = Intrinsics(525.0, 525.0, 319.5, 239.5, 640, 480)
W, H = 64, 48
K_SMALL = np.array([[60.0, 0.0, 31.5], [0.0, 60.0, 23.5], [0.0, 0.0, 1.0]])


# ---------------------------------------------------------------- writers (non-ASCII safe)

def write_img(path: Path, img: np.ndarray) -> Path:
    """Write an image with cv2.imencode + tofile (cv2.imwrite fails on non-ASCII paths on some platforms)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    ok, buf = cv2.imencode(path.suffix, img)
    assert ok, path
    buf.tofile(str(path))
    return path


def color_img(seed: int, w: int = W, h: int = H) -> np.ndarray:
    """[h x w x 3] uint8 BGR with a red left half (to check the channel order after reading)."""
    rng = np.random.default_rng(seed)
    img = rng.integers(0, 60, (h, w, 3), dtype=np.uint8)
    img[:, : w // 2, 2] = 250  # BGR: red channel
    return img


def depth_mm(seed: int, w: int = W, h: int = H, z_m: float = 0.8) -> np.ndarray:
    """[h x w] uint16 millimetres around z_m with a few holes."""
    rng = np.random.default_rng(seed)
    d = (z_m * 1000 + rng.normal(0, 5, (h, w))).astype(np.uint16)
    d[rng.random((h, w)) < 0.05] = 0
    return d


def pose(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    if np.linalg.det(q) < 0:
        q[:, 0] *= -1
    T = np.eye(4)
    T[:3, :3] = q
    T[:3, 3] = rng.uniform(-0.2, 0.2, 3) + [0, 0, 0.8]
    return T


def make_capture(root: Path, names=("000000", "000001", "000002"), masks: bool = True, poses: bool = True,
                 jpg: bool = False) -> Path:
    for i, n in enumerate(names):
        write_img(root / "rgb" / f"{n}.{'jpg' if jpg else 'png'}", color_img(i))
        write_img(root / "depth" / f"{n}.png", depth_mm(i))
        if masks:
            m = np.zeros((H, W), np.uint8)
            m[10:30, 20:40] = 255
            write_img(root / "masks" / f"{n}.png", m)
        if poses:
            (root / "annotated_poses").mkdir(parents=True, exist_ok=True)
            np.savetxt(root / "annotated_poses" / f"{n}.txt", pose(i))
    np.savetxt(root / "cam_K.txt", K_SMALL)
    return root


def make_open3d(root: Path, n: int = 3) -> Path:
    for i in range(n):
        write_img(root / "color" / f"{i:05d}.jpg", color_img(i))
        write_img(root / "depth" / f"{i:05d}.png", depth_mm(i))
    (root / "camera_intrinsic.json").write_text(json.dumps(
        {"width": W, "height": H, "intrinsic_matrix": list(K_SMALL.T.ravel())}))
    with open(root / "trajectory.log", "w") as f:
        for i in range(n):
            f.write(f"{i} {i} {i + 1}\n")
            np.savetxt(f, pose(10 + i))
    return root


def make_tum(root: Path) -> Path:
    t0 = 1305031102.0
    rgb, dep, gt = [], [], []
    for i in range(4):
        t = t0 + 0.1 * i
        write_img(root / "rgb" / f"{t:.6f}.png", color_img(i))
        rgb.append(f"{t:.6f} rgb/{t:.6f}.png")
        td = t + (0.05 if i == 2 else 0.008)  # frame 2 has no depth within 0.02 s
        write_img(root / "depth" / f"{td:.6f}.png", (depth_mm(i).astype(np.float64) * 5).astype(np.uint16))
        dep.append(f"{td:.6f} depth/{td:.6f}.png")
        gt.append(f"{t + 0.001:.6f} 0.1 0.2 {0.3 + i} 0 0 0.7071067811865476 0.7071067811865476")
    (root / "rgb.txt").write_text("# color images\n# file\n# timestamp filename\n" + "\n".join(rgb) + "\n")
    (root / "depth.txt").write_text("# depth\n" + "\n".join(dep) + "\n")
    (root / "groundtruth.txt").write_text("# timestamp tx ty tz qx qy qz qw\n" + "\n".join(gt) + "\n")
    return root


def make_bop(root: Path, n: int = 3) -> Path:
    cams, gts = {}, {}
    for i in range(n):
        write_img(root / "rgb" / f"{i:06d}.png", color_img(i))
        # depth_scale 0.1: raw * 0.1 = mm
        write_img(root / "depth" / f"{i:06d}.png", (depth_mm(i).astype(np.float64) * 10).astype(np.uint16))
        K = K_SMALL.copy()
        K[0, 0] += i  # per-image intrinsics
        cams[str(i)] = {"cam_K": list(K.ravel()), "depth_scale": 0.1}
        entries = []
        for k, oid in enumerate((5, 7)):
            T = pose(100 * oid + i)
            entries.append({"cam_R_m2c": list(T[:3, :3].ravel()), "cam_t_m2c": list(T[:3, 3] * 1000), "obj_id": oid})
            m = np.zeros((H, W), np.uint8)
            m[5 + 10 * k:15 + 10 * k, 5:25] = 255
            write_img(root / "mask_visib" / f"{i:06d}_{k:06d}.png", m)
        gts[str(i)] = entries
    (root / "scene_camera.json").write_text(json.dumps(cams))
    (root / "scene_gt.json").write_text(json.dumps(gts))
    return root


# ---------------------------------------------------------------- real data

def test_open3d_sequence_real(real_dir: Path):
    base = real_dir / "open3d_rgbd"
    seq = open_sequence(base / "RGBD", format="auto", intrinsics=base / "camera_primesense.json")
    assert seq.format == "open3d"
    assert seq.names == ["00000", "00001", "00002", "00003", "00004"]
    assert len(seq) == 5 and seq.problems == {}
    assert seq.intrinsics == PRIMESENSE
    # a decimal scale parsed or derived in float64: approx's rel 1e-6 is far above its rounding
    assert seq.depth_scale == pytest.approx(0.001)
    for i in (0, 4):
        fr = seq[i]
        assert fr.color.shape == (480, 640, 3) and fr.color.dtype == np.uint8
        assert fr.depth.shape == (480, 640) and fr.depth.dtype == np.float32
        valid = fr.depth[fr.depth > 0]
        assert valid.size > 0.5 * fr.depth.size
        # plausible real depth (the scenes are 0.8-3.5 m away): catches a wrong unit, not a precision
        assert 0.5 < np.median(valid) < 5.0 and valid.max() < 10.0
    # colour is RGB: identical to cv2's BGR reversed
    bgr = cv2.imread(str(base / "RGBD" / "color" / "00002.jpg"))
    np.testing.assert_array_equal(seq[2].color, bgr[:, :, ::-1])
    gt = seq.gt_T_world_cam
    assert gt is not None and sorted(gt) == seq.names
    # second entry of trajectory.log ("1 1 2")
    expected = np.array([[-0.2693331107603073, 0.03329392381977483, -0.9624713970216773, -0.31035872146799454],
                         [0.0, -0.9994022291201125, -0.03457143950937459, 0.5963093994288613],
                         [-0.9630470785211782, -0.009311233346521649, 0.2691721112697053, 2.126036136362892],
                         [0.0, 0.0, 0.0, 1.0]])
    # a pose parsed from text: float64 parsing is exact to 1e-16 on these O(1) entries
    np.testing.assert_allclose(gt["00001"], expected, atol=1e-12)
    assert seq.gt_T_cam_obj is None and not seq.has_masks


def test_open3d_sequence_needs_intrinsics(real_dir: Path):
    with pytest.raises(InputError, match="camera_intrinsic.json"):
        open_sequence(real_dir / "open3d_rgbd" / "RGBD")


def _o3d_depth(o3d_color, o3d_depth, kind: str) -> np.ndarray:
    import open3d as o3d

    fn = {"tum": o3d.geometry.RGBDImage.create_from_tum_format,
          "sun": o3d.geometry.RGBDImage.create_from_sun_format,
          "nyu": o3d.geometry.RGBDImage.create_from_nyu_format}[kind]
    return np.asarray(fn(o3d_color, o3d_depth, convert_rgb_to_intensity=False).depth)


def test_tum_frame_matches_open3d(real_dir: Path):
    import open3d as o3d

    d = real_dir / "open3d_rgbd" / "RGBD" / "other_formats"
    fr = load_frame(d / "TUM_color.png", d / "TUM_depth.png", PRIMESENSE, depth_scale=1 / 5000)
    assert fr.name == "TUM_color" and fr.color.shape == (480, 640, 3)
    ref = _o3d_depth(o3d.io.read_image(str(d / "TUM_color.png")), o3d.io.read_image(str(d / "TUM_depth.png")), "tum")
    both = (ref > 0) & (fr.depth > 0)
    assert both.mean() > 0.5
    # open3d's own reader gives the same float32 depths up to rounding (1e-7 m); a wrong scale or a shifted image is off
    # by whole depth steps over many pixels
    assert np.abs(ref[both] - fr.depth[both]).max() < 1e-3
    assert 0.5 < np.median(fr.depth[fr.depth > 0]) < 5.0  # plausible real depth: catches a wrong unit


def test_sun_depth_matches_open3d(real_dir: Path):
    import open3d as o3d

    d = real_dir / "open3d_rgbd" / "RGBD" / "other_formats"
    fr = load_frame(d / "SUN_color.jpg", d / "SUN_depth.png", PRIMESENSE, depth_format="sun")
    ref = _o3d_depth(o3d.io.read_image(str(d / "SUN_color.jpg")), o3d.io.read_image(str(d / "SUN_depth.png")), "sun")
    valid = (ref > 0) | (fr.depth > 0)
    assert valid.mean() > 0.5
    # open3d's own reader: the same float32 depths up to rounding (1e-7 m); a wrong scale or shift is off by whole steps
    assert np.abs(ref[valid] - fr.depth[valid]).max() < 1e-3
    np.testing.assert_array_equal(read_sun_depth(d / "SUN_depth.png"), fr.depth)
    # the raw file read as plain millimetres is not the same depth: the bit rotation matters
    plain = read_depth(d / "SUN_depth.png", 0.001)
    assert np.abs(plain - fr.depth)[valid].max() > 1.0


def test_nyu_depth_matches_open3d(real_dir: Path):
    import open3d as o3d

    d = real_dir / "open3d_rgbd" / "RGBD" / "other_formats"
    fr = load_frame(d / "NYU_color.ppm", d / "NYU_depth.pgm", PRIMESENSE, depth_format="nyu")
    assert fr.color.shape == (480, 640, 3)
    # Open3D's tutorial: PGM read big-endian, then create_from_nyu_format (Open3D cannot read .pgm/.ppm itself)
    buf = (d / "NYU_depth.pgm").read_bytes()
    header_len = len(b"P5 640 480 65535\n")
    assert buf[:header_len] == b"P5 640 480 65535\n"
    raw_be = np.frombuffer(buf[header_len:], dtype=">u2").reshape(480, 640).astype(np.uint16)
    col = cv2.imread(str(d / "NYU_color.ppm"))[:, :, ::-1].copy()
    ref = _o3d_depth(o3d.geometry.Image(col), o3d.geometry.Image(raw_be.copy()), "nyu")
    valid = (ref > 0) | (fr.depth > 0)
    assert valid.mean() > 0.5
    # open3d's own reader: the same float32 depths up to rounding (1e-7 m); a wrong scale or shift is off by whole steps
    assert np.abs(ref[valid] - fr.depth[valid]).max() < 1e-3
    assert 1.0 < np.median(fr.depth[fr.depth > 0]) < 7.0  # plausible real depth: catches a wrong unit
    np.testing.assert_array_equal(read_nyu_depth(d / "NYU_depth.pgm"), fr.depth)
    with pytest.raises(InputError, match="TUM_depth.png"):
        read_nyu_depth(d / "TUM_depth.png")


@pytest.mark.parametrize("idx", [1, 2])
def test_ycbv_frames(real_dir: Path, idx: int):
    d = real_dir / "ycbv_frames" / "data"
    meta = read_ycbv_meta(d / f"{idx:06d}-meta.mat")
    K, depth_scale, poses = meta
    assert depth_scale == pytest.approx(1e-4)  # factor_depth 10000 read from the .mat file, inverted in float64
    intr = Intrinsics.from_matrix(K, 640, 480)
    fr = load_frame(d / f"{idx:06d}-color.png", d / f"{idx:06d}-depth.png", intr, depth_scale)
    # plausible YCB-Video depth (objects on a table 0.5-1.5 m away): catches a wrong unit
    assert 0.3 < np.median(fr.depth[fr.depth > 0]) < 2.0
    label = cv2.imread(str(d / f"{idx:06d}-label.png"), cv2.IMREAD_UNCHANGED)
    assert set(poses) == set(np.unique(label)) - {0}
    pts = backproject(fr.depth, intr)
    for cls, T_cam_obj in poses.items():
        assert np.allclose(T_cam_obj[3], [0, 0, 0, 1])  # the bottom row written by the reader: exact
        # the .mat stores the poses in float32-like precision; 1e-4 still tells a rotation from anything else
        np.testing.assert_allclose(T_cam_obj[:3, :3].T @ T_cam_obj[:3, :3], np.eye(3), atol=1e-4)
        sel = (label == cls) & (fr.depth > 0)
        assert sel.sum() > 1000
        centre = np.median(pts[sel], axis=0)
        # the object's visible pixels centre within 10 cm of its pose's origin (YCB objects are under 25 cm)
        assert np.linalg.norm(centre - T_cam_obj[:3, 3]) < 0.10, cls


# ---------------------------------------------------------------- layouts built here

def test_capture_layout_roundtrip(tmp_path: Path):
    root = make_capture(tmp_path / "cap")
    assert detect_format(root) == "capture"
    seq = open_sequence(root)
    assert seq.format == "capture" and seq.names == ["000000", "000001", "000002"] and seq.problems == {}
    assert seq.intrinsics == Intrinsics.from_matrix(K_SMALL, W, H)
    assert seq.has_masks and seq.gt_T_world_cam is None
    for i, name in enumerate(seq.names):
        fr = seq[name]
        np.testing.assert_array_equal(fr.color, color_img(i)[:, :, ::-1])
        assert fr.color[0, 0, 0] == 250  # red first: RGB
        # float32 depth scaled in float32: a few ulps (6e-8 each); rtol 1e-6 = 16 ulps
        np.testing.assert_allclose(fr.depth, depth_mm(i).astype(np.float32) * 0.001, rtol=1e-6)
        assert fr.mask.dtype == bool and fr.mask.sum() == 20 * 20 and fr.mask[20, 30]
        # a pose parsed from text: float64 parsing is exact to 1e-16 on these O(1) entries
        np.testing.assert_allclose(seq.gt_T_cam_obj[name], pose(i), atol=1e-12)
    assert [f.name for f in seq] == seq.names


def test_capture_depth_scale_override_and_forced_intrinsics(tmp_path: Path):
    root = make_capture(tmp_path / "cap", masks=False, poses=False, jpg=True)
    seq = open_sequence(root, depth_scale=0.002, intrinsics=Intrinsics(70.0, 70.0, 32.0, 24.0, W, H))
    assert seq.depth_scale == 0.002 and seq.intrinsics.fx == 70.0
    # float32 depth scaled in float32: a few ulps (6e-8 each); rtol 1e-6 = 16 ulps
    np.testing.assert_allclose(seq[0].depth, depth_mm(0).astype(np.float32) * 0.002, rtol=1e-6)
    assert not seq.has_masks and seq.gt_T_cam_obj is None
    # cam_K.txt given explicitly through the override
    seq2 = open_sequence(root, intrinsics=root / "cam_K.txt")
    assert seq2.intrinsics == Intrinsics.from_matrix(K_SMALL, W, H)


def _unregistered_capture(root: Path) -> tuple[Path, Path, np.ndarray]:
    """A capture whose depth images (80 x 60) come from their own camera, 2.5 cm beside the colour camera:
    the layout, the depth camera's cam_K.txt and T_color_depth."""
    names = ("000000", "000001")
    make_capture(root, names=names, masks=False, poses=False)
    for i, n in enumerate(names):
        write_img(root / "depth" / f"{n}.png", depth_mm(i, 80, 60, z_m=0.9))
    K_depth = np.array([[70.0, 0.0, 39.5], [0.0, 70.0, 29.5], [0.0, 0.0, 1.0]])
    np.savetxt(root.parent / "depth_K.txt", K_depth)
    T = np.eye(4)
    T[:3, 3] = [-0.025, 0.0, 0.002]
    return root, root.parent / "depth_K.txt", T


def test_unregistered_depth_is_reprojected_into_the_colour_camera(tmp_path: Path):
    from gscan.io.align import align_depth_to_color

    root, depth_K, T = _unregistered_capture(tmp_path / "cap")
    np.savetxt(tmp_path / "T_color_depth.txt", T)
    # read as registered, the depth's size gives it away: every frame is reported, none read
    with pytest.raises(InputError, match="no usable RGB-D frame.*80x60"):
        open_sequence(root)
    seq = open_sequence(root, depth_camera=load_depth_camera(depth_K, tmp_path / "T_color_depth.txt"))
    assert seq.problems == {} and seq.depth_camera.intrinsics == Intrinsics(70.0, 70.0, 39.5, 29.5, 80, 60)
    for i, name in enumerate(seq.names):
        raw = depth_mm(i, 80, 60, z_m=0.9).astype(np.float32) * np.float32(0.001)
        f = seq[name]
        assert f.depth.shape == (H, W) and f.intrinsics == seq.intrinsics
        np.testing.assert_array_equal(f.depth, align_depth_to_color(raw, seq.depth_camera, seq.intrinsics))
        # a flat scene 0.9 m away stays 0.9 m away (+ the 2 mm the depth camera sits behind), seen through the
        # colour camera's own pixels
        assert abs(float(np.median(f.depth[f.depth > 0])) - 0.902) < 0.01 and (f.depth > 0).mean() > 0.8
    # the same as a JSON matrix; without the pose, the depth camera shares the colour camera's centre and axes
    (tmp_path / "T.json").write_text(json.dumps({"T": T.tolist()}))
    js = open_sequence(root, depth_camera=load_depth_camera(depth_K, tmp_path / "T.json"))
    np.testing.assert_array_equal(js[0].depth, seq[0].depth)
    assert np.array_equal(open_sequence(root, depth_camera=load_depth_camera(depth_K)).depth_camera.T_color_depth,
                          np.eye(4))


def test_unregistered_depth_bad_calibration_names_the_file(tmp_path: Path):
    root, depth_K, T = _unregistered_capture(tmp_path / "cap")
    T[0, 0] = 2.0  # not a rotation
    np.savetxt(tmp_path / "bad_T.txt", T)
    with pytest.raises(InputError, match="not a rigid transform") as e:
        load_depth_camera(depth_K, tmp_path / "bad_T.txt")
    assert e.value.path == tmp_path / "bad_T.txt"
    (tmp_path / "bad_K.txt").write_text("70 0 39.5\n0 70\n")
    with pytest.raises(InputError, match="malformed cam_K.txt") as e:
        load_depth_camera(tmp_path / "bad_K.txt")
    assert e.value.path == tmp_path / "bad_K.txt"


def test_a_depth_camera_from_a_cam_k_txt_fits_depth_images_of_any_size(tmp_path: Path):
    """A cam_K.txt carries no image size: its depth camera reads depth images of two sizes, each reprojected with
    the calibration at that size; an intrinsics JSON with a size refuses depth of another, naming the image."""
    from gscan.io.align import align_depth_to_color

    K_depth = np.array([[70.0, 0.0, 39.5], [0.0, 70.0, 29.5], [0.0, 0.0, 1.0]])
    np.savetxt(tmp_path / "depth_K.txt", K_depth)
    np.savetxt(tmp_path / "cam_K.txt", K_SMALL)
    T = np.eye(4)
    T[:3, 3] = [-0.025, 0.0, 0.002]
    np.savetxt(tmp_path / "T.txt", T)
    cam = load_depth_camera(tmp_path / "depth_K.txt", tmp_path / "T.txt")
    assert cam.size is None
    color = write_img(tmp_path / "color.png", color_img(0))
    for w, h in ((80, 60), (40, 30)):
        raw = depth_mm(1, w, h, z_m=0.9)
        depth = write_img(tmp_path / f"depth_{w}x{h}.png", raw)
        f = load_frame(color, depth, tmp_path / "cam_K.txt", depth_camera=cam)
        assert f.depth.shape == (H, W) and f.intrinsics == Intrinsics.from_matrix(K_SMALL, W, H)
        sized = DepthCamera(Intrinsics.from_matrix(K_depth, w, h), T)
        np.testing.assert_array_equal(f.depth, align_depth_to_color(raw.astype(np.float32) * np.float32(0.001),
                                                                     sized, f.intrinsics))
        assert cam.sized(w, h) == sized and (f.depth > 0).mean() > 0.2
    (tmp_path / "depth_K.json").write_text(json.dumps({"fx": 70.0, "fy": 70.0, "cx": 39.5, "cy": 29.5,
                                                       "width": 80, "height": 60}))
    only_80x60 = load_depth_camera(tmp_path / "depth_K.json", tmp_path / "T.txt")
    assert only_80x60.size == (80, 60)
    load_frame(color, tmp_path / "depth_80x60.png", tmp_path / "cam_K.txt", depth_camera=only_80x60)
    with pytest.raises(InputError, match="depth is 40x30 but the depth camera's intrinsics are for 80x60") as e:
        load_frame(color, tmp_path / "depth_40x30.png", tmp_path / "cam_K.txt", depth_camera=only_80x60)
    assert e.value.path == tmp_path / "depth_40x30.png"
    # a size the calibration cannot be of (its principal point far outside a 16x12 image) names the cam_K.txt
    write_img(tmp_path / "depth_16x12.png", depth_mm(1, 16, 12, z_m=0.9))
    with pytest.raises(InputError, match="principal point") as e:
        load_frame(color, tmp_path / "depth_16x12.png", tmp_path / "cam_K.txt", depth_camera=cam)
    assert e.value.path == tmp_path / "depth_K.txt"


def test_open3d_layout_built(tmp_path: Path):
    root = make_open3d(tmp_path / "o3d")
    assert detect_format(root) == "open3d"
    seq = open_sequence(root)
    assert seq.names == ["00000", "00001", "00002"]
    assert seq.intrinsics == Intrinsics.from_matrix(K_SMALL, W, H)
    for i, n in enumerate(seq.names):
        # a pose parsed from text: float64 parsing is exact to 1e-16 on these O(1) entries
        np.testing.assert_allclose(seq.gt_T_world_cam[n], pose(10 + i), atol=1e-12)
    fr = seq[1]
    assert abs(int(fr.color[5, 5, 0]) - 250) < 30  # JPEG, red half


def test_open3d_layout_differently_numbered_folders(tmp_path: Path):
    root = make_open3d(tmp_path / "redwood", n=3)
    for i in range(3):  # Redwood-style: depth files numbered differently from the colour files
        (root / "depth" / f"{i:05d}.png").rename(root / "depth" / f"d{i + 1:06d}.png")
    seq = open_sequence(root)
    assert seq.names == ["00000", "00001", "00002"] and seq.problems == {}
    # float32 depth scaled in float32: a few ulps (6e-8 each); rtol 1e-6 = 16 ulps
    np.testing.assert_allclose(seq[2].depth, depth_mm(2).astype(np.float32) * 0.001, rtol=1e-6)
    (root / "depth" / "d000003.png").unlink()  # counts differ now: no pairing by order
    with pytest.raises(InputError, match="00000.jpg"):
        open_sequence(root)


def test_tum_layout_built(tmp_path: Path):
    root = make_tum(tmp_path / "tum")
    assert detect_format(root) == "tum"
    with pytest.raises(InputError, match="intrinsics"):
        open_sequence(root)
    intr = Intrinsics.from_matrix(K_SMALL, W, H)
    seq = open_sequence(root, intrinsics=intr)
    # 1/5000 in float64: approx's rel 1e-6 is far above its rounding
    assert seq.format == "tum" and seq.depth_scale == pytest.approx(1 / 5000)
    t2 = f"{1305031102.0 + 0.2:.6f}"
    assert t2 in seq.problems and "depth.txt" in seq.problems[t2] and t2 not in seq.names
    assert len(seq) == 3
    fr = seq[0]
    # raw / 5000 against mm * 0.001, each rounded in float32 (6e-8): 1e-5 leaves 100x
    np.testing.assert_allclose(fr.depth, depth_mm(0).astype(np.float32) * 0.001, rtol=1e-5)
    T = seq.gt_T_world_cam[seq.names[1]]
    # parsed from text: float64 parsing, within assert_allclose's rtol 1e-7
    np.testing.assert_allclose(T[:3, 3], [0.1, 0.2, 1.3])
    # a quaternion turned into a matrix: float64 rounding ~1e-16
    np.testing.assert_allclose(T[:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)


def test_bop_layout_built(tmp_path: Path):
    root = make_bop(tmp_path / "bop")
    assert detect_format(root) == "bop"
    seq = open_sequence(root)
    assert seq.format == "bop" and seq.names == ["000000", "000001", "000002"]
    # depth_scale 0.1 mm: parsed, then converted to metres in float64
    assert seq.depth_scale == pytest.approx(1e-4) and seq.has_masks
    for i, n in enumerate(seq.names):
        fr = seq[n]
        assert fr.intrinsics.fx == pytest.approx(60.0 + i)  # per-image cam_K
        # raw * 0.1 mm against mm * 0.001, each rounded in float32 (6e-8): 1e-5 leaves 100x
        np.testing.assert_allclose(fr.depth, depth_mm(i).astype(np.float32) * 0.001, rtol=1e-5)
        np.testing.assert_allclose(seq.gt_T_cam_obj[n], pose(500 + i), atol=1e-9)  # first obj_id = 5
        assert fr.mask[6, 6] and not fr.mask[16, 6]
    seq7 = open_sequence(root, obj_id=7)
    # a pose from mm text converted to metres: float64 rounding ~1e-16 of O(1) values
    np.testing.assert_allclose(seq7.gt_T_cam_obj["000001"], pose(701), atol=1e-9)
    assert seq7[1].mask[16, 6] and not seq7[1].mask[6, 6]


def test_format_detection_and_override(tmp_path: Path):
    root = make_capture(tmp_path / "both", masks=False, poses=False)
    make_open3d(root, n=2)  # the same folder also holds color/ and camera_intrinsic.json
    assert detect_format(root) == "capture"
    assert open_sequence(root).format == "capture"
    seq = open_sequence(root, format="open3d")
    assert seq.format == "open3d" and seq.names == ["00000", "00001"]
    cap = make_capture(tmp_path / "cap")
    with pytest.raises(InputError, match="color"):
        open_sequence(cap, format="open3d")
    with pytest.raises(InputError, match="scene_camera.json"):
        open_sequence(cap, format="bop")
    with pytest.raises(InputError, match="rgb.txt"):
        open_sequence(cap, format="tum")
    with pytest.raises(ValueError):
        open_sequence(cap, format="kitti")


def test_natural_order(tmp_path: Path):
    names = ["frame10", "frame2", "frame1", "frame 3"]
    root = make_capture(tmp_path / "nat", names=names, masks=False, poses=False)
    seq = open_sequence(root)
    assert seq.names == ["frame1", "frame2", "frame10", "frame 3"]
    assert sorted(["a10", "a9", "b1", "a09"], key=natural_key) == ["a09", "a9", "a10", "b1"]


def test_pose_files_share_one_rigidity_rule(tmp_path: Path):
    """A rotation written with 4 decimals reads from a JSON and a text pose file alike, projected onto the
    nearest rotation (within the 5e-5 of the rounding, exactly orthonormal); a 1 % shear, a mirror or a bad
    last row is refused by both, naming the file."""
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec([0.3, -1.1, 0.7]).as_matrix()
    T[:3, 3] = [0.1, -0.2, 0.5]
    T4 = np.round(T, 4)
    assert not np.array_equal(T4, T)

    def write(name: str, M: np.ndarray) -> tuple[Path, Path]:
        (tmp_path / f"{name}.json").write_text(json.dumps({"T": M.tolist()}))
        (tmp_path / f"{name}.txt").write_text("\n".join(" ".join(repr(float(x)) for x in row) for row in M))
        return tmp_path / f"{name}.json", tmp_path / f"{name}.txt"

    for path, read in zip(write("rounded", T4), (read_pose_file, read_pose_txt), strict=True):
        got = read(path)
        np.testing.assert_allclose(got, T4, atol=1e-4)
        np.testing.assert_allclose(got[:3, :3].T @ got[:3, :3], np.eye(3), atol=1e-12)
    shear, mirror, last = T.copy(), T.copy(), T.copy()
    shear[0, 1] += 0.01
    mirror[:3, 0] *= -1
    last[3, 0] = 0.1
    for name, M in (("shear", shear), ("mirror", mirror), ("last", last)):
        for path, read in zip(write(name, M), (read_pose_file, read_pose_txt), strict=True):
            with pytest.raises(InputError, match="not a rigid transform") as ei:
                read(path)
            assert path.name in str(ei.value)


def test_bop_frame_with_bad_calibration_is_left_out(tmp_path: Path):
    """Per-image calibrations are checked per image: a NaN or implausible cam_K (or depth_scale) of the
    FIRST image leaves that frame out, named, and the others open."""
    root = make_bop(tmp_path / "bop", n=4)
    cams = json.loads((root / "scene_camera.json").read_text())
    cams["0"]["cam_K"][0] = float("nan")
    cams["1"]["cam_K"][0] = 1e-300
    cams["2"]["depth_scale"] = 1e300
    (root / "scene_camera.json").write_text(json.dumps(cams))
    seq = open_sequence(root)
    assert seq.names == ["000003"] and seq[0].intrinsics.fx == pytest.approx(63.0)  # 63 parsed from text: exact
    assert sorted(seq.problems) == ["000000", "000001", "000002"]
    assert "focal" in seq.problems["000001"] and "depth_scale" in seq.problems["000002"]


def test_frame_names_that_are_not_utf8(tmp_path: Path):
    """A file name with bytes that are not UTF-8 still makes a frame; its name shows them as \\xNN."""
    import os

    root = make_capture(tmp_path / "cap", names=["a", "b"], masks=False, poses=False)
    for sub, ext in (("rgb", ".png"), ("depth", ".png")):
        os.rename(root / sub / f"b{ext}", os.fsdecode(bytes(root / sub) + b"/b\xff" + ext.encode()))
    seq = open_sequence(root)
    assert seq.names == ["a", "b\\xff"]
    assert seq["b\\xff"].name == "b\\xff"
    "".join(seq.names).encode("utf-8")  # storable in the template database


@pytest.mark.parametrize("dtype, on", [(np.uint8, 1), (np.uint8, 2), (np.uint8, 255), (np.uint16, 1), (np.uint16, 255),
                                       (np.uint16, 65535)])
def test_masks_0_1_and_full_range(tmp_path: Path, dtype, on: int):
    """Two-valued masks read as the object where non-zero, whatever the value and type (0/1, 0/2 labels,
    0/255 in 8 or 16 bits, 0/65535)."""
    m = np.zeros((H, W), dtype)
    m[5:20, 10:30] = on
    write_img(tmp_path / "m.png", m)
    got = read_mask(tmp_path / "m.png")
    assert got.dtype == bool and np.array_equal(got, m > 0)


def test_associate_greedy():
    t_rgb = np.array([0.0, 0.033, 0.066, 0.5])
    t_dep = np.array([0.001, 0.030, 0.040, 0.07])
    assert associate(t_rgb, t_dep) == {0: 0, 1: 1, 2: 3}


def test_unicode_and_spaces(tmp_path: Path):
    root = make_capture(tmp_path / "scan ä 日本 dir", names=("frame ü 1", "кадр 2"))
    seq = open_sequence(root)
    assert seq.names == ["frame ü 1", "кадр 2"] and seq.problems == {}
    fr = seq["кадр 2"]
    assert fr.name == "кадр 2" and fr.mask.sum() == 400
    np.testing.assert_array_equal(read_image_rgb(root / "rgb" / "frame ü 1.png"), color_img(0)[:, :, ::-1])
    fr2 = load_frame(root / "rgb" / "frame ü 1.png", root / "depth" / "frame ü 1.png", root / "cam_K.txt",
                     mask_path=root / "masks" / "frame ü 1.png")
    assert fr2.name == "frame ü 1" and fr2.intrinsics.width == W
    assert read_mask(root / "masks" / "кадр 2.png").dtype == bool


def test_jpeg_with_trailing_data_reads(tmp_path: Path):
    """Phones append metadata after the JPEG end-of-image marker: that is not a truncated file."""
    p = write_img(tmp_path / "trail.jpg", color_img(3))
    ref = read_image_rgb(p)
    p.write_bytes(p.read_bytes() + bytes(np.random.default_rng(1).integers(0, 256, 4000, dtype=np.uint8)))
    np.testing.assert_array_equal(read_image_rgb(p), ref)


# ---------------------------------------------------------------- bad inputs

def _frame_files(tmp: Path, color=None, depth=None, mask=None, ext="png"):
    c = write_img(tmp / f"col.{ext}", color_img(0) if color is None else color)
    d = write_img(tmp / "dep.png", depth_mm(0) if depth is None else depth)
    m = None if mask is None else write_img(tmp / "msk.png", mask)
    return c, d, m


def _lf(tmp: Path, **kw):
    c, d, m = _frame_files(tmp, **kw)
    return lambda: load_frame(c, d, Intrinsics.from_matrix(K_SMALL, W, H), mask_path=m)


def bad_missing_folder(tmp):
    return (lambda: open_sequence(tmp / "no_such_scan")), "no_such_scan"


def bad_empty_folder(tmp):
    (tmp / "empty_scan").mkdir()
    return (lambda: open_sequence(tmp / "empty_scan")), "empty_scan"


def bad_unknown_layout(tmp):
    (tmp / "odd_scan" / "images").mkdir(parents=True)
    return (lambda: open_sequence(tmp / "odd_scan")), "odd_scan"


def bad_missing_camk(tmp):
    root = make_capture(tmp / "cap")
    (root / "cam_K.txt").unlink()
    return (lambda: open_sequence(root)), "cam_K.txt"


def bad_malformed_camk(tmp):
    root = make_capture(tmp / "cap")
    (root / "cam_K.txt").write_text("600 0 320\n0 600\n")
    return (lambda: open_sequence(root)), "cam_K.txt"


def bad_nan_camk(tmp):
    root = make_capture(tmp / "cap")
    (root / "cam_K.txt").write_text("nan 0 31.5\n0 60 23.5\n0 0 1\n")
    return (lambda: open_sequence(root)), "cam_K.txt"


def bad_negative_camk(tmp):
    root = make_capture(tmp / "cap")
    (root / "cam_K.txt").write_text("-60 0 31.5\n0 60 23.5\n0 0 1\n")
    return (lambda: open_sequence(root)), "cam_K.txt"


def bad_zero_camk(tmp):
    root = make_capture(tmp / "cap")
    (root / "cam_K.txt").write_text("0 0 31.5\n0 0 23.5\n0 0 1\n")
    return (lambda: open_sequence(root)), "cam_K.txt"


def bad_no_depth_at_all(tmp):
    root = make_capture(tmp / "cap", names=("only_frame",))
    (root / "depth" / "only_frame.png").unlink()
    return (lambda: open_sequence(root)), "only_frame.png"


def bad_size_mismatch(tmp):
    return _lf(tmp, depth=depth_mm(0, w=W + 2)), "dep.png"


def bad_8bit_depth(tmp):
    return _lf(tmp, depth=np.full((H, W), 80, np.uint8)), "dep.png"


def bad_float_depth(tmp):
    c = write_img(tmp / "col.png", color_img(0))
    d = write_img(tmp / "dep_float.tiff", np.full((H, W), 0.8, np.float32))
    return (lambda: load_frame(c, d, Intrinsics.from_matrix(K_SMALL, W, H))), "dep_float.tiff"


def bad_zero_depth(tmp):
    return _lf(tmp, depth=np.zeros((H, W), np.uint16)), "dep.png"


def bad_corrupt_png(tmp):
    c, d, _ = _frame_files(tmp)
    c.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(np.random.default_rng(0).integers(0, 256, 300, dtype=np.uint8)))
    return (lambda: load_frame(c, d, Intrinsics.from_matrix(K_SMALL, W, H))), "col.png"


def bad_truncated_png(tmp):
    c, d, _ = _frame_files(tmp)
    data = d.read_bytes()
    d.write_bytes(data[: len(data) // 2])
    return (lambda: load_frame(c, d, Intrinsics.from_matrix(K_SMALL, W, H))), "dep.png"


def bad_truncated_jpeg(tmp):
    c, d, _ = _frame_files(tmp, ext="jpg")
    data = c.read_bytes()
    c.write_bytes(data[: int(len(data) * 0.8)])
    return (lambda: load_frame(c, d, Intrinsics.from_matrix(K_SMALL, W, H))), "col.jpg"


def bad_unreadable_depth(tmp):
    c, _, _ = _frame_files(tmp)
    d = tmp / "dep_dir.png"
    d.mkdir()  # a folder where a file is expected: reading it fails at the OS level
    return (lambda: load_frame(c, d, Intrinsics.from_matrix(K_SMALL, W, H))), "dep_dir.png"


def bad_missing_color(tmp):
    _, d, _ = _frame_files(tmp)
    return (lambda: load_frame(tmp / "gone.png", d, Intrinsics.from_matrix(K_SMALL, W, H))), "gone.png"


def bad_depth_scale_sequence(tmp):
    root = make_capture(tmp / "cap", names=("f0", "f1"))
    return (lambda: open_sequence(root, depth_scale=1.0)), "f0.png"


def bad_depth_scale_frame(tmp):
    c, d, _ = _frame_files(tmp, depth=(depth_mm(0) // 100).astype(np.uint16))  # decimetres read as mm
    return (lambda: load_frame(c, d, Intrinsics.from_matrix(K_SMALL, W, H), depth_scale=0.001)), "dep.png"


def bad_mask_size(tmp):
    return _lf(tmp, mask=np.zeros((H // 2, W // 2), np.uint8)), "msk.png"


def bad_duplicate_stems(tmp):
    root = make_capture(tmp / "cap")
    write_img(root / "rgb" / "000001.jpg", color_img(1))
    return (lambda: open_sequence(root)), "000001"


def bad_intrinsics_size(tmp):
    root = make_capture(tmp / "cap")
    p = tmp / "cam_640.json"
    p.write_text(json.dumps({"width": 640, "height": 480, "intrinsic_matrix": list(K_SMALL.T.ravel())}))
    return (lambda: open_sequence(root, intrinsics=p)), "cam_640.json"




def bad_scene_camera(tmp):
    root = make_bop(tmp / "bop", n=1)
    (root / "scene_camera.json").write_text("{not json")
    return (lambda: open_sequence(root)), "scene_camera.json"




def bad_ycbv_meta(tmp):
    p = tmp / "000001-meta.mat"
    p.write_bytes(b"MATLAB 5.0 MAT-file garbage" * 3)
    return (lambda: read_ycbv_meta(p)), "000001-meta.mat"


def bad_all_frames_unusable(tmp):
    root = make_capture(tmp / "cap", names=("a", "b"), masks=False, poses=False)
    write_img(root / "depth" / "a.png", np.full((H, W), 3, np.uint8))
    write_img(root / "depth" / "b.png", depth_mm(1, w=10))
    return (lambda: open_sequence(root)), "a.png"


BAD_CASES = [bad_missing_folder, bad_empty_folder, bad_unknown_layout, bad_missing_camk, bad_malformed_camk,
             bad_nan_camk, bad_negative_camk, bad_zero_camk, bad_no_depth_at_all, bad_size_mismatch, bad_8bit_depth,
             bad_float_depth, bad_zero_depth, bad_corrupt_png, bad_truncated_png, bad_truncated_jpeg,
             bad_unreadable_depth, bad_missing_color, bad_depth_scale_sequence, bad_depth_scale_frame, bad_mask_size,
             bad_duplicate_stems, bad_intrinsics_size, bad_scene_camera,
             bad_ycbv_meta, bad_all_frames_unusable]


@pytest.mark.parametrize("case", BAD_CASES, ids=[c.__name__[4:] for c in BAD_CASES])
def test_bad_input_names_file(tmp_path: Path, case):
    call, fname = case(tmp_path)
    with pytest.raises(InputError) as ei:
        call()
    msg = str(ei.value)
    assert fname in msg, msg
    assert "\n" not in msg


def test_unreadable_ground_truth_is_left_out_and_named(tmp_path: Path, caplog):
    """Ground truth is optional for a scan: an unreadable annotated pose, trajectory.log or groundtruth.txt is
    left out with a warning naming it (`gt_problems`), and the sequence opens; `require_ground_truth` (what
    evaluation calls) refuses it by name."""
    from gscan.io.layouts import require_ground_truth

    cap = make_capture(tmp_path / "cap")
    (cap / "annotated_poses" / "000001.txt").write_text("1 0 0\nfoo\n")
    o3d = make_open3d(tmp_path / "o3d")
    (o3d / "trajectory.log").write_text("0 0 1\n1 0 0 0\n0 1 0\n")
    for root, bad in ((cap, "000001.txt"), (o3d, "trajectory.log")):
        with caplog.at_level("WARNING"):
            seq = open_sequence(root)
        assert len(seq.names) >= 2
        assert [Path(p).name for p in seq.gt_problems] == [bad]
        assert bad in caplog.text
        with pytest.raises(InputError, match=f"{bad}: unreadable ground truth"):
            require_ground_truth(seq.gt_problems)
    seq = open_sequence(cap)
    assert "000001" not in seq.gt_T_cam_obj and len(seq.gt_T_cam_obj) == len(seq.names) - 1
    assert open_sequence(o3d).gt_T_world_cam is None


def test_unreadable_permissions(tmp_path: Path):
    """A file without read permission is refused by name (at open time it is a per-frame problem).

    Root reads anything, so as root the check runs in a child process whose capability bounding set
    lacks CAP_DAC_OVERRIDE / CAP_DAC_READ_SEARCH (util-linux setpriv).
    """
    import os
    import shutil
    import subprocess
    import sys

    root = make_capture(tmp_path / "perm", names=("a", "b"), masks=False, poses=False)
    (root / "depth" / "b.png").chmod(0)
    script = (
        "import sys\n"
        "from gscan.io import load_frame, open_sequence\n"
        "from gscan.errors import InputError\n"
        "r = sys.argv[1]\n"
        "seq = open_sequence(r)\n"
        "print('NAMES', seq.names)\n"
        "print('PROBLEM', seq.problems['b'])\n"
        "try:\n"
        "    load_frame(r + '/rgb/b.png', r + '/depth/b.png', r + '/cam_K.txt')\n"
        "except InputError as e:\n"
        "    print('ERROR', e)\n"
    )
    cmd = [sys.executable, "-c", script, str(root)]
    if os.geteuid() == 0:
        if shutil.which("setpriv") is None:
            pytest.fail("running as root without util-linux setpriv: cannot drop the right to read any file")
        cmd = ["setpriv", "--bounding-set", "-dac_override,-dac_read_search"] + cmd
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    lines = dict(line.split(" ", 1) for line in out.stdout.splitlines() if " " in line)
    assert lines["NAMES"] == "['a']"
    assert "b.png" in lines["PROBLEM"] and "permission denied" in lines["PROBLEM"]
    assert "b.png" in lines["ERROR"] and "permission denied" in lines["ERROR"]


def test_depth_scale_message(tmp_path: Path):
    call, _ = bad_depth_scale_sequence(tmp_path)
    with pytest.raises(InputError,
                       match=r"depth scale 1 puts the scene at 799 m.*0\.001 would put it at 0\.799 m") as ei:
        call()
    assert ei.value.fix == "depth_scale"  # the CLI names --depth-scale


def test_partial_bad_sequence(tmp_path: Path):
    names = [f"f{i}" for i in range(7)]
    root = make_capture(tmp_path / "partial", names=names, poses=False)
    (root / "depth" / "f1.png").unlink()                                       # no depth
    write_img(root / "depth" / "f2.png", np.full((H, W), 90, np.uint8))        # 8-bit depth
    write_img(root / "depth" / "f3.png", depth_mm(3, w=W // 2, h=H // 2))      # size mismatch
    (root / "rgb" / "f4.png").write_bytes(b"not an image at all")             # corrupt colour
    data = (root / "depth" / "f5.png").read_bytes()
    (root / "depth" / "f5.png").write_bytes(data[: len(data) // 2])          # truncated: found on load
    write_img(root / "masks" / "f6.png", np.zeros((10, 10), np.uint8))         # wrong mask size
    seq = open_sequence(root)
    assert seq.names == ["f0", "f5"]
    assert sorted(seq.problems) == ["f1", "f2", "f3", "f4", "f6"]
    assert "f1.png" in seq.problems["f1"] and "depth" in seq.problems["f1"]
    assert "8-bit" in seq.problems["f2"] and "f2.png" in seq.problems["f2"]
    assert "f3.png" in seq.problems["f3"]
    assert "f4.png" in seq.problems["f4"]
    assert "f6.png" in seq.problems["f6"] and "mask" in seq.problems["f6"]
    frames = list(seq.iter_frames(skip_bad=True))
    assert [f.name for f in frames] == ["f0"]
    assert "f5.png" in seq.problems["f5"]
    with pytest.raises(InputError, match="f5.png"):
        seq["f5"]
    with pytest.raises(InputError, match="f5.png"):
        list(seq)


def test_first_frame_zero_depth_is_skipped(tmp_path: Path):
    root = make_capture(tmp_path / "z", names=("a", "b", "c"), masks=False, poses=False)
    write_img(root / "depth" / "a.png", np.zeros((H, W), np.uint16))
    seq = open_sequence(root)
    assert seq.names == ["b", "c"] and "all zero" in seq.problems["a"]
