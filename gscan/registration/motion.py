"""The capture's steady motion: where the poses between consecutive frames agree with each other (a turntable, an
even orbit), that motion predicts the pose between frames further apart.

A scan uses the prediction where the frames' own evidence leaves a choice open (`gscan.registration.sequence`):
whether an edge that alone joins two parts of the pose graph stands, a loop closure that the views cannot tell
from the object's turns (a plain box's half turn fits its depth as well), a pose the shape's checks refused, and
across the chain's breaks, as weak edges a cycle must confirm. The motion is what the capture's
accepted consecutive edges measure: their mean step and how far each lies from it. Over `gap` frames the
prediction is the step taken `gap` times, and it may be off by `gap` times the steps' spread (the steps' deviations
taken to add up in one direction, as a hand's slowly changing speed does, not to average out). Positions are
compared at the object (`at`: a point on the source camera's optical axis at the capture's depth), as registration
bounds its pairs' points: a step turned 0.4 deg about an object 0.4 m away moves the camera's origin 2.8 mm and the
object's points a fraction of that.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from gscan.geometry.transforms import rotation_angle_deg


@dataclass(frozen=True)
class SteadyMotion:
    """The mean motion between consecutive frames. T_step [4 x 4]: T_{k+1 <- k}; sigma_deg, sigma_m: the RMS
    rotation (deg) and displacement of the point `at` [3] (m, source camera frame) of the consecutive edges' poses
    about it; steps: how many edges."""

    T_step: np.ndarray
    sigma_deg: float
    sigma_m: float
    steps: int
    at: np.ndarray

    def predict(self, gap: int) -> np.ndarray:
        """[4 x 4] T_{k+gap <- k}: the step taken gap times (gap >= 1)."""
        return np.linalg.matrix_power(self.T_step, gap)

    def sigma(self, gap: int) -> tuple[float, float]:
        """How far (deg, m) the prediction over `gap` frames may be off: gap times the steps' spread."""
        return gap * self.sigma_deg, gap * self.sigma_m

    def deviation(self, T_tgt_src: np.ndarray, gap: int) -> tuple[float, float]:
        """(deg, m) between an edge's pose T_tgt_src [4 x 4] over `gap` frames and the prediction."""
        P = self.predict(gap)
        return (rotation_angle_deg(T_tgt_src[:3, :3] @ P[:3, :3].T),
                float(np.linalg.norm((T_tgt_src[:3, :3] - P[:3, :3]) @ self.at + T_tgt_src[:3, 3] - P[:3, 3])))

    def agrees(self, T_tgt_src: np.ndarray, gap: int, sigmas: float) -> bool:
        """Whether the edge's pose lies within `sigmas` times the prediction's spread, in rotation and translation."""
        deg, m = self.deviation(T_tgt_src, gap)
        s_deg, s_m = self.sigma(gap)
        return deg <= sigmas * s_deg and m <= sigmas * s_m

    def to_json(self, decided: int, bridges: list[list[str]]) -> dict:
        """`{step_deg, spread_deg, spread_mm, steps, decided_edges, bridges}`: the step's rotation, the spread, how
        many edges measured them, how many refused edges it vouched for, and the breaks its predictions bridged
        ([first frame, last frame] each; the scan's summary)."""
        return {"step_deg": round(rotation_angle_deg(self.T_step), 3), "spread_deg": round(self.sigma_deg, 3),
                "spread_mm": round(1000 * self.sigma_m, 2), "steps": self.steps, "decided_edges": decided,
                "bridges": bridges}


def steady_motion(steps: list[np.ndarray], min_steps: int, depth: float = 0.0) -> SteadyMotion | None:
    """The mean of the consecutive edges' poses `steps` ([4 x 4] T_{k+1 <- k} each): the rotations' chordal mean
    (their sum projected onto a rotation), the translations' mean, and the RMS deviations from it, every step
    counted (a step registered off widens the spread, and the prediction decides less), positions compared at
    the point `depth` m along the source camera's optical axis (0: its origin); None with fewer than `min_steps`
    steps (too few to measure a spread)."""
    if len(steps) < max(min_steps, 2):
        return None
    Ts = np.asarray(steps, dtype=float)
    U, _, Vt = np.linalg.svd(Ts[:, :3, :3].sum(0))
    T_step = np.eye(4)
    T_step[:3, :3] = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    T_step[:3, 3] = Ts[:, :3, 3].mean(0)
    at = np.array([0.0, 0.0, depth])
    deg = np.array([rotation_angle_deg(R @ T_step[:3, :3].T) for R in Ts[:, :3, :3]])
    m = np.linalg.norm((Ts[:, :3, :3] - T_step[:3, :3]) @ at + Ts[:, :3, 3] - T_step[:3, 3], axis=1)
    return SteadyMotion(T_step, float(np.sqrt(np.mean(deg ** 2))), float(np.sqrt(np.mean(m ** 2))), len(Ts), at)
