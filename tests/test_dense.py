"""Dense evidence (gscan.registration.dense): the depth samples' normals where a face is only a few samples wide."""
from __future__ import annotations

import numpy as np

from gscan.io.camera import Intrinsics
from gscan.registration.dense import DenseGeometry

INTR = Intrinsics(fx=525.0, fy=525.0, cx=319.5, cy=239.5, width=640, height=480)


def test_a_face_a_few_samples_wide_keeps_its_own_normal():
    """A strip 9 pixels wide (one sample, its neighbouring samples off it) at 0.5 m before a wall at 1 m, facing
    the camera and turned 60 deg about the vertical: the strip's samples have the strip's normal, none a normal
    bent towards a neighbour on the wall; on the wall, far from the strip, the wall's."""
    depth = np.full((480, 640), 1.0)
    u = np.arange(640)
    strip = (u >= 307) & (u < 316)  # samples every 7 pixels from column 3: the strip holds the one at 311
    depth[:, strip] = 0.5
    g = DenseGeometry.from_depth(depth, INTR, mask=np.broadcast_to(strip, depth.shape))
    n = g.normals[g.depth > 0]
    assert len(n) >= 50
    np.testing.assert_allclose(n, np.tile([0.0, 0.0, -1.0], (len(n), 1)), atol=1e-9)

    # the strip turned 60 deg about the vertical: depth grows along u at tan(60 deg) times the lateral offset
    x = (u - INTR.cx) / INTR.fx  # ray slope
    t = np.tan(np.radians(60.0))
    z = 0.5 * (1.0 + t * x[311]) / (1.0 + t * x)  # the plane t X + Z = const through depth 0.5 m at column 311
    depth2 = np.full((480, 640), 1.5)
    depth2[:, strip] = z[strip]
    g2 = DenseGeometry.from_depth(depth2, INTR, mask=np.broadcast_to(strip, depth2.shape))
    n2 = g2.normals[g2.depth > 0]
    want = -np.array([t, 0.0, 1.0]) / np.hypot(t, 1.0)
    assert len(n2) >= 50
    np.testing.assert_allclose(n2, np.tile(want, (len(n2), 1)), atol=1e-6)

    wall = DenseGeometry.from_depth(depth, INTR, mask=np.broadcast_to(u < 200, depth.shape))
    np.testing.assert_allclose(wall.normals[wall.depth > 0][:, 2], -1.0, atol=1e-9)


def test_a_thin_box_turned_edge_on_gives_no_edge_at_a_wrong_pose(meshes_dir):
    """A card box 2.5 cm thick on a turntable, seen near edge on (views every 15 deg around the view that shows its
    narrow side: a face a few samples wide, its big faces at grazing angles), registered pair by pair as a moving
    object's scan does (masks, the pose refined on keypoints and depth): every accepted pair lies within 2 deg /
    2 cm of the truth, and pairs that see a big face are accepted. A side sample that landed on the big face near
    their common edge, or took a normal from across it, pulled such pairs 20 deg off at a claimed 0.5 deg."""
    from gscan.geometry.transforms import inv_T, pose_error
    from gscan.io.camera import RGBDFrame
    from gscan.registration.frames import register_frames
    from gscan.scanning.capture_mode import MOVING_OBJECT
    from gscan.scanning.config import ScanConfig, for_capture
    from gscan.synth import load_textured_mesh, render_capture

    mesh = load_textured_mesh(meshes_dir / "Mattel_SKIP_BO_Card_Game" / "model_0.obj")
    steps = (0, 1, 2, 10, 11, 12, 13, 22, 23)  # the turntable's step k turns the box by 15 k deg
    views = render_capture(mesh, None, len(steps), mode="static", seed=10,
                           view_angles_deg=[(30.0, -90.0 - 15.0 * k) for k in steps])
    frames = {k: RGBDFrame(str(k), v.color, v.depth, v.intrinsics, v.mask, None)
              for k, v in zip(steps, views, strict=True)}
    T_cam_obj = {k: v.T_cam_obj for k, v in zip(steps, views, strict=True)}
    cfg = for_capture(ScanConfig(), MOVING_OBJECT)
    params, fp = cfg.registration, cfg.features
    accepted = []
    for a, b in ((1, 2), (22, 23), (10, 11), (0, 1), (1, 23), (2, 23), (0, 23), (10, 12), (11, 12), (12, 13),
                 (11, 13), (10, 13)):
        # each pair as an edge of the scan's sequence (judged with its other edges), not a lone two-frame capture
        r = register_frames(frames[a], frames[b], params, feature_params=fp, use_masks=True, alone=False)
        if r.accepted:
            deg, m = pose_error(r.T_tgt_src, T_cam_obj[b] @ inv_T(T_cam_obj[a]))
            assert deg < 2.0 and m < 0.02, (a, b, deg, m, r.sigma_deg)
            accepted.append((a, b))
    assert {(1, 2), (22, 23), (10, 11)} <= set(accepted), accepted
