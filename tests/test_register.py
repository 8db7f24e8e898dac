"""Pairwise registration (gscan.register) on rendered view pairs and on real RGB-D frames."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from gscan.camera import Intrinsics, RGBDFrame
from gscan.features import Features, FeatureParams, extract_features
from gscan.geometry import inv_T, look_at, make_T, pose_error, rotation_angle_deg, rotvec_to_R, transform_points
from gscan.register import METHODS, PairResult, RegisterParams, frame_cloud, register_features, relative_pose

N_MESHES = 10
AZIMUTHS = (0.0, 15.0, 30.0, 45.0)  # 4 views per mesh -> pairs at 15, 30 and 45 deg: 6 per mesh, 60 in all


def _render_views(mesh_dir: Path, seed: int) -> list[tuple[RGBDFrame, np.ndarray]]:
    """(frame, T_world_cam) per azimuth: the mesh rests on a textured table, camera at 40/45 deg elevation
    looking at its centre from gscan.synth's default distance, 640x480 with noisy depth."""
    from gscan.synth import DEFAULT_INTRINSICS, SynthScene, default_distance, load_textured_mesh, rest_on_table

    mesh = load_textured_mesh(mesh_dir / "model_0.obj")
    T_world_obj = rest_on_table(mesh)
    c = transform_points(T_world_obj, mesh.center[None])[0]
    scene = SynthScene([(mesh, T_world_obj)], table=True, seed=seed)
    r = default_distance(mesh)
    out = []
    for k, az in enumerate(AZIMUTHS):
        el, a = np.radians(40.0 + 5.0 * (k % 2)), np.radians(az)
        T = look_at(c + r * np.array([np.cos(el) * np.cos(a), np.cos(el) * np.sin(a), np.sin(el)]), c)
        f = scene.render(T, DEFAULT_INTRINSICS, rng=np.random.default_rng([seed, k]))
        out.append((RGBDFrame(f"{mesh_dir.name}_{k}", f.color, f.depth, DEFAULT_INTRINSICS, f.mask, None), T))
    return out


@pytest.fixture(scope="module")
def rendered(meshes_dir):
    """[(views, features)] for the first N_MESHES shared meshes."""
    dirs = sorted(p for p in meshes_dir.iterdir() if (p / "model_0.obj").is_file())[:N_MESHES]
    assert len(dirs) == N_MESHES, f"need {N_MESHES} meshes in {meshes_dir}"
    out = []
    for i, d in enumerate(dirs):
        views = _render_views(d, seed=i)
        fp = FeatureParams(kind="rootsift", max_keypoints=1000)  # keeps the 60 whole-frame pairs fast
        out.append((views, [extract_features(v[0], fp) for v in views]))
    return out


def test_rendered_pairs_whole_frame(rendered):
    errs = []
    for views, feats in rendered:
        for i in range(len(views)):
            for j in range(i + 1, len(views)):
                T_gt = relative_pose(views[i][1], views[j][1])
                gap = rotation_angle_deg(T_gt[:3, :3])
                assert 10.0 < gap < 50.0
                r = register_features(feats[i], feats[j], RegisterParams(icp=False))
                errs.append(pose_error(r.T_tgt_src, T_gt) if r.T_tgt_src is not None else (np.inf, np.inf))
    errs = np.array(errs)
    assert len(errs) >= 60
    good = (errs[:, 0] < 3.0) & (errs[:, 1] < 0.01)
    assert good.mean() >= 0.9, f"{good.sum()} / {len(good)} pairs within 3 deg / 1 cm"


def test_icp_refinement_and_rules(rendered):
    views, feats = rendered[0]
    T_gt = relative_pose(views[0][1], views[1][1])
    cs, ct = frame_cloud(views[0][0], 4), frame_cloud(views[1][0], 4)
    r = register_features(feats[0], feats[1], RegisterParams(icp=True), clouds=(cs, ct))
    assert r.accepted and r.reason is None and r.fitness is not None and r.fitness >= 0.3
    deg, m = pose_error(r.T_tgt_src, T_gt)
    assert deg < 1.0 and m < 0.005
    # a target cloud that does not overlap: ICP finds no support -> rejected, match pose kept
    far = register_features(feats[0], feats[1], RegisterParams(icp=True), clouds=(cs, ct + [1.0, 0.0, 0.0]))
    assert not far.accepted and far.reason.startswith("icp fitness")
    np.testing.assert_allclose(far.T_tgt_src, far.T_match)
    # without clouds: accepted on the matches alone, rmse = Kabsch residual
    nc = register_features(feats[0], feats[1], RegisterParams(icp=True))
    assert nc.accepted and nc.fitness is None and nc.rmse < 0.01


def test_rejection_rules():
    rng = np.random.default_rng(0)
    n = 300
    pts = np.array([0.0, 0.0, 0.6]) + rng.uniform(-0.2, 0.2, (n, 3))
    desc = rng.random((n, 128)).astype(np.float32)
    desc[:, 64:] = 0.0
    desc /= np.linalg.norm(desc, axis=1, keepdims=True)

    def feats(p, d):
        return Features(np.zeros((len(p), 2), np.float32), p.astype(np.float32), d, "rootsift",
                        np.ones(len(p), np.float32))

    # unrelated descriptors (disjoint support: RootSIFT distance sqrt(2)) -> no candidate at all
    other = np.roll(desc, 64, axis=1)
    r = register_features(feats(pts, desc), feats(pts, other), RegisterParams(icp=False))
    assert not r.accepted and r.reason.startswith("too few matches")
    # identical keypoints under a known motion -> accepted, exact pose
    T = make_T(rotvec_to_R([0.1, -0.2, 0.05]), [0.02, 0.01, -0.03])
    r = register_features(feats(pts, desc), feats(transform_points(T, pts), desc), RegisterParams(icp=False))
    assert isinstance(r, PairResult) and r.accepted and r.n_matches == 24
    deg, m = pose_error(r.T_tgt_src, T)
    assert deg < 0.01 and m < 1e-4
    # a loose matcher with a strict residual rule: the Kabsch rule fires
    noisy = transform_points(T, pts) + rng.normal(0, 0.006, (n, 3))
    p = RegisterParams(icp=False, max_kabsch_rmse=0.002)
    r = register_features(feats(pts, desc), feats(noisy, desc), p)
    assert not r.accepted and r.reason.startswith(("kabsch residual", "too few matches"))
    with pytest.raises(ValueError):
        RegisterParams(method="magic")
    assert set(METHODS) == {"gmatch", "ratio", "mutual", "ransac", "lo-ransac", "fgr"}


# ---------------------------------------------------------------------------------------------- real


def _trajectory(path: Path) -> list[np.ndarray]:
    """Open3D trajectory.log: per frame a header line then 4 rows of T_world_cam."""
    lines = [ln for ln in path.read_text().splitlines() if ln.strip()]
    return [np.array([[float(x) for x in lines[k + 1 + r].split()] for r in range(4)]) for k in range(0, len(lines), 5)]


def test_real_open3d_sequence_all_pairs(real_dir):
    from gscan.io import load_frame

    d = real_dir / "open3d_rgbd" / "RGBD"
    intr = Intrinsics(525.0, 525.0, 319.5, 239.5, 640, 480)
    colors, depths = sorted((d / "color").iterdir()), sorted((d / "depth").iterdir())
    Ts = _trajectory(d / "trajectory.log")
    assert len(colors) == len(depths) == len(Ts) == 5
    frames = [load_frame(c, dp, intr, depth_scale=0.001) for c, dp in zip(colors, depths)]
    feats = [extract_features(f) for f in frames]
    for i in range(5):
        for j in range(i + 1, 5):
            T_gt = relative_pose(Ts[i], Ts[j])
            r = register_features(feats[i], feats[j], RegisterParams(icp=False))
            assert r.accepted, (i, j, r.reason)
            deg, m = pose_error(r.T_tgt_src, T_gt)
            motion_deg, motion_m = pose_error(np.eye(4), T_gt)
            assert deg < 1.0 and m < 0.02, (i, j, deg, m)
            assert deg < 0.5 * motion_deg and m < 0.5 * motion_m, (i, j, deg, m, motion_deg, motion_m)
    assert np.allclose(inv_T(Ts[0]) @ Ts[0], np.eye(4))
