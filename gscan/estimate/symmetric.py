"""Poses that look alike: the object's symmetries that hold in shape and texture (gscan.geometry.symmetry, the
template's "symmetries" meta), as the estimator and the tracker use them (`PoseGroup`).

A pose T_cam_obj and T_cam_obj @ S, for S in the group of those symmetries, show the object alike: no frame can tell
them apart and both are right. The estimator returns one of them by a fixed rule (`canonical`), the tracker the one
nearest the previous frame's pose (`nearest`); two rival poses that differ by an element (`apart`) are one answer,
not an ambiguous view.

The rule (`canonical`): among the equivalents T_cam_obj @ S, the one whose rotation lies nearest (geodesic angle) to
R_REF, the orientation with the object's +z up in the image (camera -y), its +x to the right (camera +x) and its +y
away from the camera. The angle about a continuous axis is solved in closed form; among discrete elements as near as
each other (cosines within 1e-9) the first in the group's order wins. The rule reads the pose alone, never the
hypothesis it came from: poses that differ by a symmetry give the same answer, up to their noise (a pose midway
between two equivalents, such as a 2-fold box seen with its +x along the camera's axis, may go either way).

A symmetry in shape alone is not used here: the texture tells its poses apart (gscan.estimate.rivals), and when it
cannot, the view is ambiguous and refused.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gscan.geometry.symmetry import Symmetries, axis_rotation
from gscan.geometry.transforms import pose_error

# the reference orientation of `canonical`, its columns the object's x, y, z axes in the camera frame
R_REF = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
TIE = 1e-9  # cosines this close are a tie (the first element wins)


@dataclass(frozen=True)
class PoseGroup:
    """The rigid motions S [4 x 4] (object frame, metres) under which the object looks the same in shape and texture
    (module docstring): `discrete` elements, the identity first, each composed with every rotation about `axis`
    (unit direction [3], a point on it [3]; None without a continuous symmetry). A second continuous axis (a sphere)
    is sampled into `discrete` at `Symmetries.elements`' default step. Empty (false): no such symmetry."""

    discrete: tuple[np.ndarray, ...] = (np.eye(4),)
    axis: tuple[np.ndarray, np.ndarray] | None = None
    label: str | None = None

    @classmethod
    def of(cls, sym: Symmetries) -> PoseGroup:
        """The group of `sym`'s symmetries that hold in texture too."""
        tex = sym.in_texture()
        if not tex:
            return cls()
        axis = tex.continuous[0] if tex.continuous else None
        rest = Symmetries(tex.discrete, tex.discrete_in_texture, tex.continuous[1:], tex.continuous_in_texture[1:])
        return cls(tuple(rest.elements()), axis, describe(tex))

    def __bool__(self) -> bool:
        return self.axis is not None or len(self.discrete) > 1

    def _best(self, T: np.ndarray, R_target: np.ndarray) -> np.ndarray:
        """T @ S [4 x 4] for the element S whose rotation R_T R_S is nearest R_target [3 x 3] (geodesic angle)."""
        best, best_cos = T, -np.inf
        A = R_target.T @ T[:3, :3]
        for D in self.discrete:
            S = D
            if self.axis is not None:
                # trace(R_target^T R_T R(theta) R_D) = trace(M R(theta)), M = R_D A: a cos theta + b sin theta + c
                a, offset = self.axis
                M = D[:3, :3] @ A
                K = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
                theta = float(np.arctan2(np.trace(M @ K), np.trace(M) - a @ M @ a))
                S = axis_rotation(a, offset, theta) @ D
            cos = float(np.trace(A @ S[:3, :3]))
            if cos > best_cos + TIE:
                best, best_cos = T @ S, cos
        return best

    def canonical(self, T_cam_obj: np.ndarray) -> np.ndarray:
        """The equivalent of T_cam_obj [4 x 4] the estimator returns (module docstring: nearest R_REF)."""
        return self._best(np.asarray(T_cam_obj, dtype=np.float64), R_REF) if self else T_cam_obj

    def nearest(self, T_cam_obj: np.ndarray, T_ref: np.ndarray) -> np.ndarray:
        """The equivalent of T_cam_obj [4 x 4] whose rotation lies nearest T_ref's [4 x 4]."""
        return self._best(np.asarray(T_cam_obj, dtype=np.float64), np.asarray(T_ref)[:3, :3]) if self else T_cam_obj

    def apart(self, T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
        """(degrees, metres) between T_a and the equivalent of T_b nearest it (`pose_error`)."""
        return pose_error(T_a, self.nearest(T_b, T_a))

    def equivalents(self, T_cam_obj: np.ndarray, step_deg: float) -> list[np.ndarray]:
        """T_cam_obj @ S [4 x 4] for every element S, T_cam_obj first; a continuous axis sampled every step_deg."""
        T = np.asarray(T_cam_obj, dtype=np.float64)
        turns = [np.eye(4)]
        if self.axis is not None:
            n = max(1, int(round(360.0 / step_deg)))
            turns = [axis_rotation(*self.axis, 2 * np.pi * k / n) for k in range(n)]
        return [T @ A @ D for D in self.discrete for A in turns]


def describe(sym: Symmetries) -> str:
    """One line naming the symmetries: "180 deg about [0, 0, 1]; any turn about [0, 0, 1] through [0, 0, 0] m"."""
    from scipy.spatial.transform import Rotation

    def vec(v: np.ndarray) -> str:
        return "[" + ", ".join(f"{x:.3g}" for x in np.where(np.abs(v) < 5e-4, 0.0, v)) + "]"

    parts = []
    for S in sym.discrete:
        rv = Rotation.from_matrix(S[:3, :3]).as_rotvec()
        ang = float(np.linalg.norm(rv))
        parts.append(f"{np.degrees(ang):.0f} deg about {vec(rv / max(ang, 1e-12))}")
    parts += [f"any turn about {vec(a)} through {vec(o)} m" for a, o in sym.continuous]
    return "; ".join(parts)
