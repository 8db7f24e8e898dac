"""TSDF fusion accuracy against ground-truth meshes, fragment removal, and the template frame."""
from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gscan.geometry.plane import Plane
from gscan.geometry.transforms import inv_T, make_T, rotvec_to_R, transform_points
from gscan.io.camera import RGBDFrame
from gscan.scanning.fuse import FusionParams, auto_voxel_size, fuse_tsdf, remove_small_components, template_frame
from gscan.scanning.segment import segment_sequence
from gscan.synth import DEFAULT_INTRINSICS, DepthNoise, SynthScene, load_textured_mesh, orbit_poses, rest_on_table

INTR = DEFAULT_INTRINSICS.scaled(0.5)
NOISE = DepthNoise(edge_jump=0.04)  # half resolution: see tests/test_segment.py
MESH = "Whey_Protein_Chocolate_12_Packets"


@pytest.fixture(scope="module")
def capture(meshes_dir):
    """A scanned textured mesh resting on a textured table, seen from 10 views on two rings."""
    mesh = load_textured_mesh(meshes_dir / MESH / "model_0.obj")
    T_world_obj = rest_on_table(mesh, rotvec_to_R(np.radians([0, 0, 30.0])))
    sc = SynthScene([(mesh, T_world_obj)], seed=0, table_texture_size=1024)
    poses = orbit_poses(np.array([0.0, 0.0, 0.07]), 0.5, [25.0, 55.0], 5)
    renders = [sc.render(T, INTR, rng=np.random.default_rng(k), noise_params=NOISE) for k, T in enumerate(poses)]
    frames = [RGBDFrame(f"{k:06d}", r.color, r.depth, INTR) for k, r in enumerate(renders)]
    gt = o3d.t.geometry.RaycastingScene()
    gt.add_triangles(o3d.core.Tensor(transform_points(T_world_obj, mesh.vertices).astype(np.float32)),
                     o3d.core.Tensor(mesh.triangles.astype(np.uint32)))
    return mesh, T_world_obj, poses, renders, frames, gt


def distances(scene: o3d.t.geometry.RaycastingScene, pts: np.ndarray) -> np.ndarray:
    return scene.compute_distance(o3d.core.Tensor(np.asarray(pts, dtype=np.float32))).numpy()


def test_fused_mesh_matches_ground_truth_surface(capture):
    mesh, T_world_obj, poses, renders, frames, gt = capture
    model = fuse_tsdf(frames, poses, [r.mask for r in renders])
    # 0.15 m object / 150 = 1 mm, clamped to voxel_min: 0.002 (float64 arithmetic)
    assert model.voxel_size == pytest.approx(0.002)
    assert len(model.mesh.vertices) > 1000 and len(model.mesh.triangles) > 1000
    assert model.mesh.triangles.max() < len(model.mesh.vertices) and model.mesh.triangles.dtype == np.int32
    assert model.mesh.vertex_colors.shape == model.mesh.vertices.shape and model.mesh.vertex_colors.min() >= 0
    d = distances(gt, model.mesh.vertices)
    # TSDF at 2 mm voxels on noisy rendered depth: the surface within about half a voxel; 1.5 mm median and 3 mm at the
    # 95th percentile allow depth noise, not a misregistered view (centimetres)
    assert np.median(d) < 0.0015, np.median(d)
    # TSDF at 2 mm voxels on noisy rendered depth: the surface within about half a voxel; 1.5 mm median and 3 mm at the
    # 95th percentile allow depth noise, not a misregistered view (centimetres)
    assert np.percentile(d, 95) < 0.003, np.percentile(d, 95)
    # completeness: the visible part of the true surface (above the table) is covered by the fused mesh
    fused = o3d.t.geometry.RaycastingScene()
    fused.add_triangles(o3d.core.Tensor(model.mesh.vertices.astype(np.float32)),
                        o3d.core.Tensor(model.mesh.triangles.astype(np.uint32)))
    V_gt = transform_points(T_world_obj, mesh.vertices)
    V_gt = V_gt[V_gt[:, 2] > 0.01]
    # coverage: most of the visible ground-truth surface (above the table contact) lies within 2 voxels of the fused
    # mesh
    assert np.mean(distances(fused, V_gt) < 0.004) > 0.9
    # the point cloud lies on the surface too, coloured
    dp = distances(gt, model.points)
    # the cloud's points are the TSDF's zero crossings: on the surface like the mesh's vertices
    assert len(model.points) > 1000 and np.percentile(dp, 95) < 0.003
    assert model.point_colors.shape == model.points.shape


def test_fusion_of_automatically_segmented_frames(capture):
    """No masks given: the sequence working volume segments the frames, fusion stays on the object."""
    mesh, T_world_obj, poses, renders, frames, gt = capture
    segs, vol = segment_sequence(frames, poses)
    assert vol is not None
    ious = [(s.mask & r.mask & (r.depth > 0)).sum() / (s.mask | (r.mask & (r.depth > 0))).sum()
            for s, r in zip(segs, renders, strict=True)]
    assert min(ious) >= 0.9, ious
    model = fuse_tsdf(frames, poses, [s.mask for s in segs])
    d = distances(gt, model.mesh.vertices)
    # TSDF at 2 mm voxels on noisy rendered depth: the surface within about half a voxel; 1.5 mm median and 3 mm at the
    # 95th percentile allow depth noise, not a misregistered view (centimetres)
    assert np.median(d) < 0.0015 and np.percentile(d, 95) < 0.003, (np.median(d), np.percentile(d, 95))
    # template frame: z = table normal, origin at the bounding-box centre of the object
    T_obj_world = template_frame(model.mesh.vertices, vol.plane_world, poses[0])
    R = T_obj_world[:3, :3]
    np.testing.assert_allclose(R[2], [0, 0, 1], atol=0.01)  # obj z expressed in world = up
    V = transform_points(T_obj_world, model.mesh.vertices)
    # the origin is the vertices' bounding-box centre by construction: float64 rounding
    np.testing.assert_allclose(0.5 * (V.min(0) + V.max(0)), 0.0, atol=1e-9)
    bb_true = transform_points(T_world_obj, mesh.vertices)
    centre_true = 0.5 * (bb_true.min(0) + bb_true.max(0))  # axis-aligned in world; z-centre comparable
    centre = inv_T(T_obj_world)[:3, 3]
    assert abs(centre[2] - centre_true[2]) < 0.006  # bottom face unseen: top + table contact bound z
    # the fused box's footprint centre against the mesh's: the unseen bottom and TSDF smoothing shift it by millimetres;
    # 1 cm catches a wrong frame
    assert np.linalg.norm(centre[:2] - transform_points(T_world_obj, mesh.center[None])[0, :2]) < 0.01


def test_skips_unregistered_and_rejects_empty(capture):
    _, _, poses, renders, frames, _ = capture
    with pytest.raises(ValueError):
        fuse_tsdf(frames[:2], [None, None])
    with pytest.raises(ValueError):
        fuse_tsdf(frames[:2], poses[:1])
    a = fuse_tsdf(frames[:3], [poses[0], None, poses[2]], [r.mask for r in renders[:3]])
    b = fuse_tsdf([frames[0], frames[2]], [poses[0], poses[2]], [renders[0].mask, renders[2].mask])
    np.testing.assert_array_equal(a.mesh.vertices, b.mesh.vertices)  # also: deterministic
    np.testing.assert_array_equal(a.mesh.triangles, b.mesh.triangles)
    one = fuse_tsdf(frames[:1], poses[:1], [renders[0].mask])  # a single view still gives a surface
    assert len(one.mesh.triangles) > 100


def test_remove_small_components():
    big = o3d.geometry.TriangleMesh.create_sphere(0.05, resolution=20)
    small = o3d.geometry.TriangleMesh.create_sphere(0.005, resolution=4).translate((0.2, 0, 0))
    V = np.concatenate([np.asarray(big.vertices), np.asarray(small.vertices)])
    F = np.concatenate([np.asarray(big.triangles), np.asarray(small.triangles) + len(big.vertices)])
    V2, F2, C2 = remove_small_components(V, F, None, min_fraction=0.1)
    # the big sphere of radius 0.05 m kept; the small one far away dropped
    assert len(F2) == len(big.triangles) and np.all(np.linalg.norm(V2, axis=1) < 0.06)
    assert C2.shape == V2.shape
    V3, F3, _ = remove_small_components(V, F, None, min_fraction=0.0)
    assert len(F3) == len(F)
    V4, F4, _ = remove_small_components(V, F, None, keep_largest_only=True, min_fraction=0.0)
    assert len(F4) == len(big.triangles)


def test_auto_voxel_size():
    assert auto_voxel_size(0.15) == pytest.approx(0.002)  # extent / 150 clamped to [voxel_min, voxel_max], in float64
    assert auto_voxel_size(0.45) == pytest.approx(0.003)  # extent / 150 clamped to [voxel_min, voxel_max], in float64
    # extent / 150 clamped to [voxel_min, voxel_max], in float64
    assert auto_voxel_size(5.0) == pytest.approx(FusionParams().voxel_max)


def box_points(size, T_world_box, n=4000, seed=0) -> np.ndarray:
    """Points on the surface of a box of `size` (centred) placed at T_world_box."""
    rng = np.random.default_rng(seed)
    p = rng.uniform(-0.5, 0.5, size=(n, 3)) * size
    ax = rng.integers(0, 3, n)
    p[np.arange(n), ax] = np.sign(rng.uniform(-1, 1, n)) * 0.5 * np.asarray(size)[ax]
    return transform_points(T_world_box, p)


def test_template_frame_box_on_table():
    size = np.array([0.16, 0.06, 0.10])
    yaw = np.radians(35.0)
    T_world_box = make_T(rotvec_to_R([0, 0, yaw]), [0.03, -0.02, 0.05])
    P = box_points(size, T_world_box)
    cam0 = orbit_poses(np.array([0.03, -0.02, 0.05]), 0.5, [30.0], 4)[0]
    T_obj_world = template_frame(P, Plane(np.array([0, 0, 1.0]), 0.0), cam0)
    T_world_obj = inv_T(T_obj_world)
    # z is the plane's normal, copied: float64 rounding of one normalisation
    np.testing.assert_allclose(T_world_obj[:3, 2], [0, 0, 1], atol=1e-9)
    np.testing.assert_allclose(T_world_obj[:3, 3], [0.03, -0.02, 0.05], atol=2e-3)  # bbox centre
    long_axis = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    assert abs(T_world_obj[:3, 0] @ long_axis) > 0.999  # x along the longest side
    # x points along the first camera's x unless nearly perpendicular to it (|cos| <= 0.1)
    assert T_world_obj[:3, 0] @ cam0[:3, 0] >= 0 or abs(T_world_obj[:3, 0] @ cam0[:3, 0]) <= 0.1
    assert np.linalg.det(T_world_obj[:3, :3]) == pytest.approx(1.0)  # det of a float64 rotation: ~1e-15 off 1
    # no plane: first camera's axes, origin still the bbox centre in those axes
    T2 = inv_T(template_frame(P, None, cam0))
    # without a plane the axes are the first camera's, copied: float64 rounding
    np.testing.assert_allclose(T2[:3, :3], cam0[:3, :3], atol=1e-12)
    L = transform_points(inv_T(T2), P)
    # the origin is the bounding-box centre by construction: float64 rounding
    np.testing.assert_allclose(0.5 * (L.min(0) + L.max(0)), 0.0, atol=1e-12)


@settings(deadline=None, max_examples=25)
@given(st.lists(st.floats(-3.0, 3.0), min_size=6, max_size=6))
def test_template_frame_is_equivariant(g):
    """Moving the whole world (points, plane, camera) by G moves the template frame with it."""
    size = np.array([0.16, 0.06, 0.10])
    P = box_points(size, make_T(rotvec_to_R([0, 0, 0.4]), [0, 0, 0.05]), n=1500)
    cam0 = orbit_poses(np.zeros(3), 0.5, [30.0], 4)[1]
    plane = Plane(np.array([0, 0, 1.0]), 0.0)
    G = make_T(rotvec_to_R(np.array(g[:3])), g[3:])
    A = template_frame(P, plane, cam0)
    B = template_frame(transform_points(G, P), plane.transformed(G), G @ cam0)
    # equivariance through an eigen-decomposition and products of random transforms: float64 rounding amplified by the
    # points' spread, well under 1e-7
    np.testing.assert_allclose(B, A @ inv_T(G), atol=1e-7)


def test_open3d_refusal_is_a_value_error():
    """open3d aborts a TSDF integration that touches no block (a 1-pixel frame); fuse_tsdf turns it into
    the ValueError that scan reports as "nothing could be fused", with open3d's sentence alone."""
    from gscan.io.camera import Intrinsics

    f = RGBDFrame("tiny", np.zeros((1, 1, 3), np.uint8), np.full((1, 1), 0.5, np.float32),
                  Intrinsics(615.0, 615.0, 0.0, 0.0, 1, 1))
    with pytest.raises(ValueError, match=r"^TSDF fusion failed: No block is touched") as ei:
        fuse_tsdf([f], [np.eye(4)])
    assert "\x1b" not in str(ei.value) and "open3d::" not in str(ei.value)
