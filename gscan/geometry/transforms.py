"""SE(3) helpers: rigid transforms, poses and their errors, look-at cameras, the mean of poses.

Transforms are [4 x 4] float64 matrices named by frames: `T_a_b` maps points in frame b
into frame a (`p_a = T_a_b @ p_b`).
"""
from __future__ import annotations

import numpy as np


def make_T(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """[3 x 3] rotation and [3] translation -> [4 x 4] transform."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return T


RIGID_ATOL = 1e-3  # tolerance on R^T R = I: poses written with 4-5 decimals still count as rigid
MAX_TRANSLATION_M = 1e4  # a camera or object pose 10 km away is a unit or parsing error


def is_rigid(T: np.ndarray, atol: float = RIGID_ATOL, max_translation: float = MAX_TRANSLATION_M) -> bool:
    """T [4 x 4] is finite, its rotation orthonormal (to `atol`) with det +1, its last row 0 0 0 1 and
    its translation within `max_translation` (metres) on every axis."""
    T = np.asarray(T, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        return False
    R = T[:3, :3]
    return bool(np.allclose(R.T @ R, np.eye(3), atol=atol) and np.linalg.det(R) > 0
                and np.allclose(T[3], [0, 0, 0, 1], atol=1e-6) and np.abs(T[:3, 3]).max() <= max_translation)


def nearest_rigid(T: np.ndarray) -> np.ndarray:
    """T [4 x 4] with its rotation block replaced by the nearest rotation (SVD, det +1) and the last row
    0 0 0 1: a pose written with limited precision (or scaled, as KinectFusion's trajectories are: det
    0.9997) otherwise reads as a rotation of about 1.4 deg when compared with an exact one."""
    T = np.asarray(T, dtype=np.float64)
    U, _, Vt = np.linalg.svd(T[:3, :3])
    D = np.diag([1.0, 1.0, float(np.sign(np.linalg.det(U @ Vt)))])
    return make_T(U @ D @ Vt, T[:3, 3])


def inv_T(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid [4 x 4] transform."""
    R, t = T[:3, :3], T[:3, 3]
    return make_T(R.T, -R.T @ t)


def transform_points(T: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Apply [4 x 4] T to [N x 3] points."""
    pts = np.asarray(pts, dtype=np.float64)
    return pts @ T[:3, :3].T + T[:3, 3]


def rotvec_to_R(rotvec: np.ndarray) -> np.ndarray:
    """Rodrigues: axis * angle [3] -> [3 x 3] rotation."""
    rv = np.asarray(rotvec, dtype=float).reshape(3)
    theta = np.linalg.norm(rv)
    if theta < 1e-12:
        return np.eye(3)
    k = rv / theta
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(theta) * K + (1 - np.cos(theta)) * K @ K


def rotation_angle_deg(R: np.ndarray) -> float:
    """Angle of a rotation matrix, degrees in [0, 180]: atan2(sin, cos) of the angle, from the skew part and
    the trace (arccos of the trace alone loses half the digits near 0: a rounding of 1e-16 reads 1e-6 deg)."""
    R = np.asarray(R, dtype=np.float64)[:3, :3]
    c = (np.trace(R) - 1.0) / 2.0
    s = 0.5 * np.linalg.norm([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return float(np.degrees(np.arctan2(s, c)))


def pose_error(T_est: np.ndarray, T_gt: np.ndarray) -> tuple[float, float]:
    """(rotation error in degrees, translation error in metres) between two transforms."""
    dR = T_est[:3, :3] @ T_gt[:3, :3].T
    return rotation_angle_deg(dR), float(np.linalg.norm(T_est[:3, 3] - T_gt[:3, 3]))


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray | tuple[float, float, float] = (0.0, 0.0, 1.0)
            ) -> np.ndarray:
    """T_world_cam of an OpenCV camera at `eye` looking at `target` (x right, y down, z forward)."""
    eye, target, up = (np.asarray(a, dtype=float) for a in (eye, target, up))
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-9:  # looking along up: pick any perpendicular
        x = np.cross(z, np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return make_T(np.stack([x, y, z], axis=1), eye)


def mean_pose(Ts: list[np.ndarray] | np.ndarray) -> np.ndarray:
    """Chordal mean of rigid transforms: mean translation, rotation projected onto SO(3)."""
    Ts = np.asarray(Ts, dtype=np.float64)
    M = Ts[:, :3, :3].mean(0)
    U, _, Vt = np.linalg.svd(M)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return make_T(U @ D @ Vt, Ts[:, :3, 3].mean(0))
