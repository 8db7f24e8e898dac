"""Tests of the synthetic RGB-D renderer gscan.synth against independent geometry."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gscan.geometry.transforms import inv_T, look_at, rotvec_to_R, transform_points
from gscan.io.camera import Intrinsics, backproject, load_intrinsics, project
from gscan.synth import (
    DEFAULT_INTRINSICS,
    DepthNoise,
    SynthScene,
    TexturedMesh,
    apply_depth_noise,
    box_mesh,
    default_distance,
    depth_sigma,
    load_textured_mesh,
    orbit_poses,
    place_distractors,
    procedural_box_texture,
    render_capture,
    rest_on_table,
    save_textured_mesh,
    table_texture,
    write_capture,
)

SMALL = Intrinsics(fx=307.5, fy=307.5, cx=159.5, cy=119.5, width=320, height=240)
MESH_NAME = "Apples_to_Apples_Kids_Edition"


@pytest.fixture(scope="module")
def shared_mesh(meshes_dir: Path) -> TexturedMesh:
    return load_textured_mesh(meshes_dir / MESH_NAME / "model_0.obj")


@pytest.fixture(scope="module")
def box() -> TexturedMesh:
    return box_mesh((0.16, 0.10, 0.07), procedural_box_texture(0))


def silhouette(mesh: TexturedMesh, T_cam_obj: np.ndarray, intr: Intrinsics, ss: int = 4) -> np.ndarray:
    """Reference [H x W] bool silhouette: triangles projected by the pose, filled at ss x ss supersampling,
    a pixel counts when more than half of it is covered."""
    px = project(transform_points(T_cam_obj, mesh.vertices), intr)
    px_ss = (px + 0.5) * ss - 0.5
    img = np.zeros((intr.height * ss, intr.width * ss), np.uint8)
    for tri in np.round(px_ss[mesh.triangles] * 16).astype(np.int32):
        cv2.fillConvexPoly(img, tri, 1, lineType=cv2.LINE_8, shift=4)
    cover = cv2.resize(img.astype(np.float32), (intr.width, intr.height), interpolation=cv2.INTER_AREA)
    return cover > 0.5


def test_load_shared_mesh_has_corner_uvs_and_texture(shared_mesh: TexturedMesh) -> None:
    m = shared_mesh
    assert m.uv.shape == (len(m.triangles), 3, 2)
    assert m.texture.shape == (256, 256, 3) and m.texture.dtype == np.uint8
    # UV corners computed in float64 from float32 texture coordinates: 1e-6 covers their rounding
    assert np.all((m.uv >= -1e-6) & (m.uv <= 1 + 1e-6))
    assert 0.05 < m.radius < 0.5  # metres


def test_load_missing_mesh_names_the_file(tmp_path: Path) -> None:
    from gscan.errors import InputError
    with pytest.raises(InputError, match="nothere.obj"):
        load_textured_mesh(tmp_path / "nothere.obj")


def first_hits(origin: np.ndarray, dirs: np.ndarray, tri: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Independent Moller-Trumbore ray casting: origin [3], dirs [R x 3], triangles [F x 3 x 3] ->
    (hit triangle [R], barycentric (w0, w1, w2) [R x 3]); triangle -1 where nothing is hit."""
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    p = np.cross(dirs[:, None], e2[None])  # [R x F x 3]
    det = np.einsum("rfk,fk->rf", p, e1)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / det
        s = origin[None, None] - tri[None, :, 0]
        u = np.einsum("rfk,rfk->rf", s, p) * inv
        q = np.cross(s, e1[None])
        v = np.einsum("rk,rfk->rf", dirs, q) * inv
        t = np.einsum("fk,rfk->rf", e2, q) * inv
    ok = (np.abs(det) > 1e-15) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-9)
    t = np.where(ok, t, np.inf)
    f = np.argmin(t, axis=1)
    r = np.arange(len(dirs))
    hit = np.where(np.isfinite(t[r, f]), f, -1)
    return hit, np.stack([1 - u[r, f] - v[r, f], u[r, f], v[r, f]], 1)


def test_colour_equals_texture_at_interpolated_uv(shared_mesh: TexturedMesh) -> None:
    """Unshaded colour at hit pixels = bilinear texture at the barycentric UV (OBJ v flipped), with the hit
    found by an independent ray-triangle intersection."""
    m = shared_mesh
    T_wo = rest_on_table(m)
    scene = SynthScene([(m, T_wo)], table=True, shadows=False)
    c = transform_points(T_wo, m.center[None])[0]
    T_wc = orbit_poses(c, 0.45, [35.0], 3)[1]  # close: texels about pixel size, no mip blur
    f = scene.render(T_wc, SMALL, noise=False, shading=False)
    rng = np.random.default_rng(1)
    ys, xs = np.nonzero(cv2.erode(f.mask.astype(np.uint8), np.ones((5, 5), np.uint8)))
    pick = rng.choice(len(xs), 60, replace=False)
    px = np.stack([xs[pick], ys[pick]], 1).astype(float)
    T_oc = inv_T(f.T_cam_obj)
    dirs_c = np.c_[(px[:, 0] - SMALL.cx) / SMALL.fx, (px[:, 1] - SMALL.cy) / SMALL.fy, np.ones(len(pick))]
    hit, bary = first_hits(T_oc[:3, 3], dirs_c @ T_oc[:3, :3].T, m.vertices[m.triangles])
    assert (hit >= 0).all()
    tex = m.texture.astype(np.float32)
    h, w = tex.shape[:2]
    errs = []
    for i in range(len(pick)):
        u, v = bary[i] @ m.uv[hit[i]]
        ref = cv2.getRectSubPix(tex, (1, 1), (float(u * w - 0.5), float((1 - v) * h - 0.5)))[0, 0]
        errs.append(np.abs(ref - f.color[int(px[i, 1]), int(px[i, 0])]).max())
    errs = np.asarray(errs)
    assert np.median(errs) <= 3.0, errs
    assert np.mean(errs <= 8.0) >= 0.9, errs
    # a v-unflipped lookup would disagree: the test can tell the conventions apart
    flipped = [np.abs(cv2.getRectSubPix(tex, (1, 1), (float((bary[i] @ m.uv[hit[i]])[0] * w - 0.5),
                                                       float((bary[i] @ m.uv[hit[i]])[1] * h - 0.5)))[0, 0]
                      - f.color[int(px[i, 1]), int(px[i, 0])]).max() for i in range(len(pick))]
    assert np.median(flipped) > 3 * max(np.median(errs), 1.0)


def test_mask_matches_projected_silhouette_and_depth_lies_on_surface(shared_mesh: TexturedMesh) -> None:
    m = shared_mesh
    frames = render_capture(m, None, 2, intr=DEFAULT_INTRINSICS, seed=3, noise=False)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(m.vertices.astype(np.float32)), o3d.core.Tensor(m.triangles.astype(np.uint32)))
    for f in frames:
        ref = silhouette(m, f.T_cam_obj, DEFAULT_INTRINSICS)
        iou = (ref & f.mask).sum() / (ref | f.mask).sum()
        assert iou >= 0.99, iou  # measured >= 0.9978 over all 21 shared meshes
        assert f.mask.sum() > 5000
        pts_c = backproject(f.depth_clean, DEFAULT_INTRINSICS)[f.mask]
        pts_o = transform_points(inv_T(f.T_cam_obj), pts_c).astype(np.float32)
        dist = scene.compute_distance(o3d.core.Tensor(pts_o)).numpy()
        # the clean rendered depth lifted back lies on the mesh: open3d ray-casts in float32 (1e-7 m at 1 m); 0.1 mm
        # median and 1 mm at the 99.5th percentile allow grazing-angle pixels
        assert np.percentile(dist, 99.5) < 1e-3 and np.median(dist) < 1e-4, (np.median(dist), dist.max())
        table = (f.labels == -1) & (f.depth_clean > 0)
        z_world = transform_points(f.T_world_cam, backproject(f.depth_clean, DEFAULT_INTRINSICS)[table])[:, 2]
        assert np.abs(z_world).max() < 1e-4  # table pixels lie on z = 0
        assert np.array_equal(f.depth, f.depth_clean)  # noise=False is exact


def test_object_rests_on_table(shared_mesh: TexturedMesh) -> None:
    R = rotvec_to_R(np.array([0.4, -0.2, 1.0]))
    T = rest_on_table(shared_mesh, R, (0.1, -0.05))
    v = transform_points(T, shared_mesh.vertices)
    # resting on z = 0: a translation by the lowest vertex's height, exact up to float64 rounding (1e-17 m)
    assert abs(v[:, 2].min()) < 1e-12
    # placed at (0.1, -0.05): float64 rounding of O(0.1) values
    np.testing.assert_allclose(0.5 * (v.min(0) + v.max(0))[:2], [0.1, -0.05], atol=1e-12)


def test_sift_keypoints_on_objects(shared_mesh: TexturedMesh, box: TexturedMesh) -> None:
    sift = cv2.SIFT_create()

    def n_kp(f) -> int:
        return len(sift.detect(cv2.cvtColor(f.color, cv2.COLOR_RGB2GRAY), f.mask.astype(np.uint8) * 255))
    # measured (seed 0, default distance, 640x480): shared mesh 204-337, procedural box 266-399
    shared = [n_kp(f) for f in render_capture(shared_mesh, None, 2, seed=0)]
    boxes = [n_kp(f) for f in render_capture(box, None, 2, seed=0)]
    assert min(shared) >= 150, shared
    assert min(boxes) >= 200, boxes
    f = render_capture(box, None, 1, seed=0)[0]
    table_kp = len(sift.detect(cv2.cvtColor(f.color, cv2.COLOR_RGB2GRAY), (~f.mask).astype(np.uint8) * 255))
    assert table_kp >= 1000, table_kp  # the table carries texture for whole-frame registration


def test_turntable_background_static_object_moves(box: TexturedMesh) -> None:
    f0, f1 = render_capture(box, None, 4, mode="turntable", intr=SMALL, noise=False, shadows=False)[:2]
    bg = (f0.labels == -1) & (f1.labels == -1)
    assert bg.sum() > 0.5 * bg.size
    assert np.array_equal(f0.color[bg], f1.color[bg]) and np.array_equal(f0.depth[bg], f1.depth[bg])
    np.testing.assert_allclose(f0.T_world_cam, f1.T_world_cam)  # the same camera path: computed identically (rtol 1e-7)
    obj = f0.mask & f1.mask
    assert np.abs(f0.color[obj].astype(int) - f1.color[obj]).mean() > 10
    ang = np.degrees(np.arccos(np.clip((np.trace(f0.T_cam_obj[:3, :3].T @ f1.T_cam_obj[:3, :3]) - 1) / 2, -1, 1)))
    # a turn of 90 deg read through arccos, well conditioned at 90 deg: float64 rounding ~1e-14 deg
    assert abs(ang - 90.0) < 1e-6
    # the spin axis is vertical through the object centre: the centre stays put
    c0 = transform_points(f0.T_world_objs[0], box.center[None])
    c1 = transform_points(f1.T_world_objs[0], box.center[None])
    # a rotation about the vertical through the centre: float64 rounding of O(1) values
    np.testing.assert_allclose(c0, c1, atol=1e-12)


def test_static_path_pose_consistency(box: TexturedMesh) -> None:
    frames = render_capture(box, None, 3, intr=SMALL, noise=True, distractors=1)
    for f in frames:
        # two products of O(1) transforms: float64 rounding ~1e-16
        np.testing.assert_allclose(f.T_cam_obj, inv_T(f.T_world_cam) @ f.T_world_objs[0], atol=1e-12)
        # the object does not move between frames: the same matrix (rtol 1e-7)
        np.testing.assert_allclose(f.T_world_objs[0], frames[0].T_world_objs[0])
        assert set(np.unique(f.labels)) <= {-1, 0, 1}
        assert np.array_equal(f.mask, f.labels == 0)
    assert frames[0].T_world_objs.shape == (2, 4, 4)
    assert (frames[0].labels == 1).any()  # the distractor is in view


@settings(max_examples=25, deadline=None)
@given(st.floats(0.2, 2.0), st.lists(st.floats(-80, 85), min_size=1, max_size=3), st.integers(1, 6),
       st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(0, 1)))
def test_orbit_poses_look_at_centre(radius, elevations, n, center) -> None:
    c = np.asarray(center)
    poses = orbit_poses(c, radius, elevations, n)
    assert len(poses) == n * len(elevations)
    for i, T in enumerate(poses):
        R = T[:3, :3]
        # look_at builds an orthonormal frame by cross products: float64 rounding ~1e-16; 1e-9 for any BLAS
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-9)
        assert np.linalg.det(R) > 0
        # distances of ~0.5 m in float64: rounding ~1e-16 relative
        np.testing.assert_allclose(np.linalg.norm(T[:3, 3] - c), radius, rtol=1e-9)
        p_cam = transform_points(inv_T(T), c[None])[0]
        np.testing.assert_allclose(p_cam[:2], 0.0, atol=1e-9)  # centre on the optical axis
        el = elevations[i // n]
        # float64 trigonometry on O(1) values: rounding ~1e-16
        np.testing.assert_allclose(T[2, 3] - c[2], radius * np.sin(np.radians(el)), atol=1e-9)
        if abs(el) < 80:
            assert R[2, 1] < 0  # image y (down) points against world z (up): upright images


def test_depth_noise_statistics_and_holes() -> None:
    H, W = 240, 320
    z = np.full((H, W), 1.2, np.float32)
    z[:, 200:] = 0.7  # a step edge
    labels = np.full((H, W), -1, np.int16)
    p = DepthNoise(clusters_mean=0.0, edge_drop_prob=0.0)
    d = apply_depth_noise(z, labels, None, np.random.default_rng(0), p)
    region = d[5:-5, 5:190]
    ok = region > 0
    assert ok.mean() > 0.99
    std = region[ok].std()
    # the sample's standard deviation over thousands of pixels is within about 1 % of the model's (1 / sqrt(2N)),
    # the 1 mm quantisation adds about 1 %; 25 % catches a wrong model (e.g. the sigma of another depth)
    assert abs(std - depth_sigma(1.2)) < 0.25 * depth_sigma(1.2), (std, depth_sigma(1.2))
    assert np.allclose(np.round(d * 1000), d * 1000, atol=1e-3)  # 1 mm quantisation
    assert (d[:, 199] == 0).all() and (d[:, 200] == 0).all()  # both sides of the discontinuity dropped
    d2 = apply_depth_noise(z, labels, None, np.random.default_rng(0), DepthNoise(clusters_mean=20.0))
    assert (d2 == 0).mean() > (d == 0).mean()  # dropout clusters add holes
    far = apply_depth_noise(np.full((8, 8), 3.5, np.float32), None, None, np.random.default_rng(0))
    assert (far == 0).all()  # beyond max range
    again = apply_depth_noise(z, labels, None, np.random.default_rng(0), p)
    assert np.array_equal(d, again)  # seeded


def test_write_capture_layout_and_roundtrip(tmp_path: Path, box: TexturedMesh) -> None:
    frames = render_capture(box, tmp_path / "cap", 2, intr=SMALL, seed=1, jpeg=True)
    out = tmp_path / "cap"
    assert sorted(p.name for p in out.iterdir()) == ["annotated_poses", "cam_K.txt", "depth", "masks", "rgb"]
    for sub, ext in (("rgb", ".jpg"), ("depth", ".png"), ("masks", ".png"), ("annotated_poses", ".txt")):
        assert sorted(p.name for p in (out / sub).iterdir()) == [f"00000{i}{ext}" for i in range(2)]
    intr = load_intrinsics(out / "cam_K.txt", SMALL.width, SMALL.height)
    np.testing.assert_allclose(intr.K, SMALL.K)  # K parsed back from cam_K.txt written with full precision
    for i, f in enumerate(frames):
        d = cv2.imread(str(out / "depth" / f"00000{i}.png"), cv2.IMREAD_UNCHANGED)
        assert d.dtype == np.uint16 and d.shape == (SMALL.height, SMALL.width)
        # depth written as whole millimetres: at most half a millimetre of rounding, plus float32's 1e-6 m
        assert np.abs(d / 1000.0 - f.depth).max() <= 0.0005 + 1e-6
        m = cv2.imread(str(out / "masks" / f"00000{i}.png"), cv2.IMREAD_UNCHANGED)
        assert set(np.unique(m)) <= {0, 255} and np.array_equal(m == 255, f.mask)
        # poses written with 17 significant digits: parsing restores them to float64 rounding
        np.testing.assert_allclose(np.loadtxt(out / "annotated_poses" / f"00000{i}.txt"), f.T_cam_obj, atol=1e-9)
        rgb = cv2.cvtColor(cv2.imread(str(out / "rgb" / f"00000{i}.jpg")), cv2.COLOR_BGR2RGB)
        assert np.abs(rgb.astype(int) - f.color).mean() < 6  # JPEG
    out2 = write_capture(tmp_path / "named", frames, SMALL, names=["a", "b"], write_masks=False)
    assert sorted(p.name for p in out2.iterdir()) == ["annotated_poses", "cam_K.txt", "depth", "rgb"]
    rgb = cv2.cvtColor(cv2.imread(str(out2 / "rgb" / "b.png")), cv2.COLOR_BGR2RGB)
    assert np.array_equal(rgb, frames[1].color)  # PNG is lossless
    with pytest.raises(ValueError):
        write_capture(tmp_path / "bad", frames, SMALL, names=["only_one"])


def test_box_mesh_closed_and_textures_saved(tmp_path: Path, box: TexturedMesh) -> None:
    import trimesh
    assert len(box.vertices) == 8 and len(box.triangles) == 12
    tm = trimesh.Trimesh(box.vertices, box.triangles, process=False)
    assert tm.is_watertight and tm.is_winding_consistent and tm.volume > 0  # outward winding
    # a closed box's volume in float64: rounding ~1e-16 relative
    np.testing.assert_allclose(tm.volume, 0.16 * 0.10 * 0.07, rtol=1e-9)
    obj = save_textured_mesh(box, tmp_path / "box.obj")
    back = load_textured_mesh(obj)
    assert back.texture.shape == box.texture.shape and np.array_equal(back.texture, box.texture)
    # OBJ written with full float precision and read back: rounding ~1e-16
    np.testing.assert_allclose(back.bounds, box.bounds, atol=1e-9)
    # OBJ written with full float precision and read back: rounding ~1e-16
    np.testing.assert_allclose(back.vertices[back.triangles], box.vertices[box.triangles], atol=1e-9)
    # OBJ written with full float precision and read back: rounding ~1e-16
    np.testing.assert_allclose(back.uv, box.uv, atol=1e-9)


def test_textures_deterministic_and_distinct() -> None:
    a, b, c = (procedural_box_texture(seed, (256, 384)) for seed in (5, 5, 6))
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    for kind in ("newspaper", "wood", "fabric"):
        t = table_texture(kind, 2, 512)
        assert t.shape == (512, 512, 3) and t.std() > 10
    with pytest.raises(ValueError):
        table_texture("marble")


def test_distractors_do_not_overlap(box: TexturedMesh) -> None:
    rng = np.random.default_rng(0)
    T_t = rest_on_table(box)
    others = [box_mesh((0.08, 0.06, 0.1), procedural_box_texture(i, (128, 192))) for i in range(3)]
    poses = place_distractors(box, T_t, others, rng)
    from gscan.synth import footprint_radius
    circles = [footprint_radius(box, T_t)] + [footprint_radius(m, T) for m, T in zip(others, poses, strict=True)]
    for i in range(len(circles)):
        for j in range(i + 1, len(circles)):
            assert np.linalg.norm(circles[i][0] - circles[j][0]) > circles[i][1] + circles[j][1]
    for m, T in zip(others, poses, strict=True):
        # resting on z = 0: a translation by the lowest vertex's height, exact up to float64 rounding (1e-17 m)
        assert abs(transform_points(T, m.vertices)[:, 2].min()) < 1e-12


def test_default_distance_fills_frame(box: TexturedMesh) -> None:
    d = default_distance(box)
    f = render_capture(box, None, 1, noise=False)[0]
    # a camera placed d away from the centre: float64 rounding of O(1) values
    np.testing.assert_allclose(np.linalg.norm(transform_points(f.T_cam_obj, box.center[None])), d, rtol=1e-9)
    xs = np.nonzero(f.mask.any(0))[0]
    # default_distance frames the object at about a third of the width: a range around that, not a precision
    assert 0.2 * 640 < xs.max() - xs.min() < 0.5 * 640


@settings(max_examples=30, deadline=None)
@given(st.floats(0.3, 2.5), st.floats(0.0, 75.0), st.floats(0.0, 360.0))
def test_no_depth_holes_on_slanted_planes(dist, slant_deg, azimuth_deg) -> None:
    """Discontinuity detection marks depth jumps, never a smooth plane, however slanted."""
    from gscan.io.camera import pixel_rays
    from gscan.synth.noise import discontinuities
    s, a = np.radians(slant_deg), np.radians(azimuth_deg)
    n = np.array([np.sin(s) * np.cos(a), np.sin(s) * np.sin(a), -np.cos(s)])  # plane n.x = -dist, facing the camera
    z = (-dist / (pixel_rays(SMALL) @ n)).astype(np.float32)
    z[(z <= 0) | (z > 10)] = 0
    edge = discontinuities(z, None, DepthNoise().edge_jump)
    inner = cv2.erode((z > 0).astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    assert not edge[inner].any()
    z2 = z.copy()
    z2[:, 160:] *= 0.9  # a 10% step
    edge2 = discontinuities(z2, None, DepthNoise().edge_jump)
    rows = inner[:, 158:162].all(1)
    assert edge2[rows][:, 159].all() and edge2[rows][:, 160].all()


def test_render_deterministic_and_seed_dependent(box: TexturedMesh) -> None:
    T_wo = rest_on_table(box)
    intr = DEFAULT_INTRINSICS.scaled(0.25)
    T_wc = orbit_poses(transform_points(T_wo, box.center[None])[0], 0.5, [40.0], 2)
    a = SynthScene([(box, T_wo)], seed=3, table_texture_size=512)
    f1, f2, g = a.render(T_wc[0], intr), a.render(T_wc[0], intr), a.render(T_wc[1], intr)
    assert np.array_equal(f1.color, f2.color) and np.array_equal(f1.depth, f2.depth)
    h = SynthScene([(box, T_wo)], seed=4, table_texture_size=512).render(T_wc[0], intr)
    assert not np.array_equal(f1.color, h.color)  # another seed: other table, other noise
    assert np.array_equal(f1.depth_clean, h.depth_clean)  # same geometry
    holes_1, holes_g = (f1.depth == 0) & (f1.depth_clean > 0), (g.depth == 0) & (g.depth_clean > 0)
    assert holes_1.any() and holes_g.any()


SAMPLES = Path(__file__).resolve().parents[1] / "gscan" / "sample"  # the bundled sample (package data)
MAKE_SAMPLE = Path(__file__).resolve().parents[1] / "samples" / "make_sample.py"


def _load_make_sample():
    import importlib.util
    spec = importlib.util.spec_from_file_location("make_sample", MAKE_SAMPLE)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_bundled_sample_consistent_with_ground_truth() -> None:
    """The committed sample: layout, masks = GT silhouettes of object/box.obj, depth on the box surface."""
    box = load_textured_mesh(SAMPLES / "object" / "box.obj")
    # box.obj's vertices written with full precision: float64 rounding
    np.testing.assert_allclose(box.extent, [0.16, 0.10, 0.07], atol=1e-9)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(box.vertices.astype(np.float32)),
                        o3d.core.Tensor(box.triangles.astype(np.uint32)))
    for sub, n in (("capture", 30), ("heldout", 4)):
        d = SAMPLES / sub
        names = sorted(p.stem for p in (d / "rgb").glob("*.jpg"))
        assert names == [f"{i:06d}" for i in range(n)]
        intr = load_intrinsics(d / "cam_K.txt", 640, 480)
        for name in names[:: max(1, n // 4)]:
            T = np.loadtxt(d / "annotated_poses" / f"{name}.txt")
            mask = cv2.imread(str(d / "masks" / f"{name}.png"), cv2.IMREAD_UNCHANGED) == 255
            ref = silhouette(box, T, intr)
            assert (ref & mask).sum() / (ref | mask).sum() >= 0.98
            depth = cv2.imread(str(d / "depth" / f"{name}.png"), cv2.IMREAD_UNCHANGED) / 1000.0
            sel = mask & (depth > 0)
            pts = transform_points(inv_T(T), backproject(depth, intr)[sel]).astype(np.float32)
            dist = scene.compute_distance(o3d.core.Tensor(pts)).numpy()
            assert np.median(dist) < 0.002 and np.percentile(dist, 95) < 0.006  # noisy depth on the surface


def test_bundled_sample_regenerates() -> None:
    """make_sample.py reproduces committed capture frames (a few pixels may differ across CPUs)."""
    mod = _load_make_sample()
    box = mod.sample_box()
    scene, cams = mod.capture_setup(box, np.random.default_rng(2024))
    assert len(cams) == 30
    for i in (0, 22):
        f = mod.render_capture_frame(scene, cams[i], i)
        np.testing.assert_allclose(np.loadtxt(SAMPLES / "capture" / "annotated_poses" / f"{i:06d}.txt"), f.T_cam_obj,
                                   atol=1e-8)
        depth = cv2.imread(str(SAMPLES / "capture" / "depth" / f"{i:06d}.png"), cv2.IMREAD_UNCHANGED)
        assert np.mean(depth == np.rint(f.depth * 1000)) > 0.998
        rgb = cv2.cvtColor(cv2.imread(str(SAMPLES / "capture" / "rgb" / f"{i:06d}.jpg")), cv2.COLOR_BGR2RGB)
        # the committed JPEG (quality 92) against a fresh render: compression and the few pixels that differ across
        # CPUs stay well below a mean of 3 levels; another frame or a swapped channel order is far above
        assert np.abs(rgb.astype(int) - f.color).mean() < 3.0


def test_stereo_occlusion_band_left_of_objects(box: TexturedMesh) -> None:
    """With a 5 cm baseline to the right, table points hidden from the second imager (just left of the
    box in the image) lose their depth; no such band appears without a baseline."""
    T_wo = rest_on_table(box)
    sc = SynthScene([(box, T_wo)], table_texture_size=512)
    T_wc = orbit_poses(transform_points(T_wo, box.center[None])[0], 0.5, [25.0], 1, azimuth0_deg=-60)[0]
    quiet = {"clusters_mean": 0.0, "edge_band_px": 0, "sigma_0": 0.0, "sigma_2": 0.0}
    f0 = sc.render(T_wc, SMALL, noise_params=DepthNoise(baseline=0.0, **quiet))
    f1 = sc.render(T_wc, SMALL, noise_params=DepthNoise(baseline=0.05, **quiet))
    extra = (f1.depth == 0) & (f0.depth > 0)
    assert not ((f0.depth == 0) & (f1.depth > 0)).any()
    rows, cols = np.nonzero(extra & (f1.labels == -1))
    assert len(rows) > 20
    right_of = [f1.mask[r, c + 1:c + 12].any() for r, c in zip(rows, cols, strict=True)]
    assert all(right_of)  # every dropped table pixel lies just left of the box


def test_glossy_highlight_at_the_mirror_direction_loses_depth(box: TexturedMesh) -> None:
    """A glossy box seen along the light's mirror direction off its top face shows a saturated highlight at the top's
    centre, where the depth is lost; seen from another side the highlight is gone (it moves with the viewpoint).
    Everything else renders as without gloss, and a gloss naming no object changes nothing."""
    from gscan.synth import Gloss

    T_wo = rest_on_table(box)
    top = transform_points(T_wo, box.center[None])[0] + np.array([0.0, 0.0, 0.5 * box.extent[2]])
    light = np.array([0.35, -0.3, 1.0]) / np.linalg.norm([0.35, -0.3, 1.0])
    mirror = np.array([-light[0], -light[1], light[2]])  # the light reflected by the top face (normal +z)
    quiet = DepthNoise(clusters_mean=0.0, edge_band_px=0, baseline=0.0)
    matte = SynthScene([(box, T_wo)], seed=1, table_texture_size=512)
    shiny = SynthScene([(box, T_wo)], seed=1, table_texture_size=512, gloss=Gloss())
    nobody = SynthScene([(box, T_wo)], seed=1, table_texture_size=512, gloss=Gloss(objects=()))
    T_wc = look_at(top + 0.5 * mirror, top)
    u, v = np.rint(project(transform_points(inv_T(T_wc), top[None]), SMALL)[0]).astype(int)
    a, b, c = (s.render(T_wc, SMALL, noise_params=quiet) for s in (matte, shiny, nobody))
    assert np.array_equal(a.color, c.color) and np.array_equal(a.depth, c.depth)
    assert a.mask[v, u] and a.depth[v, u] > 0 and a.color[v, u].min() < 240
    assert b.color[v, u].min() >= 250 and b.depth[v, u] == 0
    spot = (b.depth == 0) & (a.depth > 0)
    assert spot.sum() >= 5 and spot[~a.mask].sum() == 0  # lost depth on the glossy object only
    away = cv2.dilate(a.mask.astype(np.uint8), np.ones((7, 7), np.uint8)) == 0  # beyond the colour blur's reach
    assert np.array_equal(a.color[away], b.color[away]) and np.array_equal(a.depth[~spot], b.depth[~spot])
    side = transform_points(T_wo, box.center[None])[0] + 0.5 * np.array([-mirror[0], -mirror[1], mirror[2]])
    T_other = look_at(side, top)  # the mirror direction turned 180 degrees about the vertical
    u2, v2 = np.rint(project(transform_points(inv_T(T_other), top[None]), SMALL)[0]).astype(int)
    a2, b2 = matte.render(T_other, SMALL, noise_params=quiet), shiny.render(T_other, SMALL, noise_params=quiet)
    # the highlight's tail there: 255 (n.h)^40 with n.h = cos(the light's angle from the vertical), 3.3 levels
    assert a2.mask[v2, u2] and np.abs(a2.color[v2, u2].astype(int) - b2.color[v2, u2]).max() <= 5
    assert np.array_equal(a2.depth, b2.depth)


def test_render_capture_view_angles_match_the_rings(box: TexturedMesh) -> None:
    """Views given by (elevation, azimuth) are the rings' cameras at those angles."""
    ring = render_capture(box, None, 3, elevations_deg=(30.0,), intr=SMALL, noise=False, table=False)
    own = render_capture(box, None, 3, elevations_deg=(30.0,), intr=SMALL, noise=False, table=False,
                         view_angles_deg=[(30.0, 0.0), (30.0, 120.0), (30.0, 240.0)])
    for f, g in zip(ring, own, strict=True):
        np.testing.assert_allclose(f.T_world_cam, g.T_world_cam, atol=1e-12)
        assert np.array_equal(f.color, g.color)
    with pytest.raises(ValueError):
        render_capture(box, None, 2, intr=SMALL, view_angles_deg=[(30.0, 0.0)])


def test_hard_case_builders() -> None:
    """The hard captures' parts: a depth image shifted with an empty border, two rings of 20-degree steps joined
    by one 25-degree jump."""
    from gscan.synth.cases import ring_jump_angles, shift_image

    img = np.arange(1.0, 13.0).reshape(3, 4)
    s = shift_image(img, 2, -1)
    assert np.array_equal(s[:2, 2:], img[1:, :2]) and not s[:, :2].any() and not s[2].any()
    assert np.array_equal(shift_image(shift_image(img, -1, 1), 1, -1)[:2, 1:], img[:2, 1:])
    ang = np.radians(np.array(ring_jump_angles(20.0, 25.0, 20.0)))
    d = np.stack([np.cos(ang[:, 0]) * np.cos(ang[:, 1]), np.cos(ang[:, 0]) * np.sin(ang[:, 1]), np.sin(ang[:, 0])], 1)
    steps = np.degrees(np.arccos(np.clip((d[1:] * d[:-1]).sum(1), -1, 1)))
    assert len(d) == 36 and steps.argmax() == 17
    np.testing.assert_allclose(steps[17], 25.0, atol=1e-6)
    low, high = np.delete(steps, 17)[:17], np.delete(steps, 17)[17:]
    # 20 degrees of azimuth: the view turns 20 * cos(elevation)-ish degrees on each ring
    assert np.all(low > 18.0) and np.all(high > 14.0) and np.all(np.delete(steps, 17) < 20.0 + 1e-9)
