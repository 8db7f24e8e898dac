"""A cheap motion cue for keeping capture frames, and the coverage of viewing directions so far.

The cue tracks corners from the last kept frame into the current one (pyramidal Lucas-Kanade with a
forward-backward check), lifts both ends with their frame's depth and solves the rigid motion between the
two clouds (`kabsch_trimmed`, outliers trimmed at `tau`). Corners are taken in the central part of the image
(`region`), where the object is while it is scanned, so that the motion measured is the camera's motion
relative to the object in both capture modes: the whole central scene moves rigidly with a static object,
and a turning object fills most of it on a turntable. Chained over the kept frames this gives each frame's
pose in the first kept frame, and with the object centre (the median of the first frame's central depth)
each frame's viewing direction onto the object. A frame is kept when its viewing direction differs from the
last kept frame's by at least `min_angle_deg`, or when tracking is lost (too few corners followed: it
becomes the new reference, its motion assumed zero).

Coverage: `gscan.geometry.coverage`, the definition the template's coverage uses, over the kept views'
directions. Its cells are in the preview's up frame (`up_frame`): z along the normal of the table the first
kept frame shows (the image's up when it shows none), y horizontal away from the first kept camera, x to
its right; so the first view is the front, and the bottom the object stands on is named missing until a
view sees it from below.
Cheap enough for every frame of a live camera: a few hundred corners tracked and one small Kabsch.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from gscan.geometry.coverage import CoverageMap, cells_within, lattice
from gscan.geometry.kabsch import kabsch_trimmed
from gscan.geometry.plane import dominant_plane
from gscan.geometry.transforms import inv_T
from gscan.io.camera import Intrinsics, backproject, backproject_pixels


@dataclass(frozen=True)
class MotionParams:
    """min_angle_deg: change of viewing direction that keeps a frame; max_corners: corners tracked;
    min_tracked: fewer corners followed with depth means tracking is lost; region: central fraction of the
    image width and height where corners are taken; tau: Kabsch inlier distance (m); up_plane_min_frac,
    up_plane_iterations: the share of the first kept frame's depth a plane needs to be taken for the table that
    gives the coverage its up (`up_frame`), and the RANSAC hypotheses that look for it."""

    min_angle_deg: float = 10.0
    max_corners: int = 300
    min_tracked: int = 20
    region: float = 0.6
    tau: float = 0.015
    up_plane_min_frac: float = 0.2
    up_plane_iterations: int = 200


@dataclass
class MotionUpdate:
    """The current frame against the last kept one: angle_deg (change of viewing direction), T_first_cam
    [4 x 4] (its camera in the first kept frame), tracked (corners followed with depth), lost."""

    angle_deg: float
    T_first_cam: np.ndarray
    tracked: int
    lost: bool


def up_frame(depth: np.ndarray, intr: Intrinsics, params: MotionParams = MotionParams()) -> np.ndarray:
    """R_up_cam [3 x 3]: a camera's axes into the preview's up frame (module docstring), from its depth [H x W]
    (m): z = the dominant plane's normal when one holds `up_plane_min_frac` of the depth and faces the image's
    up (a table under the object), else the image's up (-y); x = the camera's x made horizontal; y = z x x."""
    up = np.array([0.0, -1.0, 0.0])
    plane = dominant_plane(backproject(depth, intr), params.up_plane_min_frac, params.up_plane_iterations)
    if plane is not None and plane.normal[1] < -0.3:
        up = plane.normal / np.linalg.norm(plane.normal)
    x = np.array([1.0, 0.0, 0.0]) - up[0] * up
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(up, x), up])


@dataclass
class Coverage:
    """How many kept views see the object from each cell of `gscan.geometry.coverage.lattice()` (cells in the
    preview's up frame); `views` are the kept views' directions in that frame."""

    directions: np.ndarray = field(default_factory=lattice)
    counts: np.ndarray = field(default_factory=lambda: np.zeros(len(lattice()), dtype=np.int64))
    views: list[np.ndarray] = field(default_factory=list)

    def add(self, direction: np.ndarray) -> None:
        """Count a kept view whose direction (object centre to camera, up frame) is `direction` [3]."""
        d = np.asarray(direction, dtype=np.float64)
        d = d / max(float(np.linalg.norm(d)), 1e-12)
        self.views.append(d)
        self.counts += cells_within(self.directions, d)

    def map(self) -> CoverageMap:
        """The coverage so far (the first kept view is the front)."""
        front = self.views[0] if self.views else np.array([0.0, -1.0, 0.0])
        return CoverageMap(self.counts.copy(), np.zeros(len(self.counts), dtype=bool), front)

    @property
    def covered(self) -> int:
        """Cells seen by at least one kept view."""
        return int(np.count_nonzero(self.counts))


class MotionTracker:
    """Feed every frame to `update`; call `keep` for the frames kept (the first frame must be kept)."""

    def __init__(self, intrinsics: Intrinsics, params: MotionParams = MotionParams()):
        self.intr = intrinsics
        self.params = params
        self.coverage = Coverage()
        self.center: np.ndarray | None = None  # object centre in the first kept camera (m)
        self.R_up_first: np.ndarray | None = None  # the first kept camera's axes into the up frame (`up_frame`)
        self._ref_grey: np.ndarray | None = None
        self._ref_px: np.ndarray | None = None  # [N x 1 x 2] float32 corners of the reference frame
        self._ref_pts: np.ndarray | None = None  # [N x 3] their camera points
        self._T_first_ref = np.eye(4)
        self._ref_dir: np.ndarray | None = None
        self._last: MotionUpdate | None = None

    def _region(self, shape: tuple[int, int]) -> np.ndarray:
        h, w = shape
        m = np.zeros((h, w), np.uint8)
        fy, fx = (1 - self.params.region) / 2 * h, (1 - self.params.region) / 2 * w
        m[int(fy):int(h - fy), int(fx):int(w - fx)] = 255
        return m

    def _direction(self, T_first_cam: np.ndarray) -> np.ndarray:
        assert self.center is not None
        d = T_first_cam[:3, 3] - self.center
        return d / max(float(np.linalg.norm(d)), 1e-9)

    def update(self, color: np.ndarray, depth: np.ndarray) -> MotionUpdate:
        """color [H x W x 3] uint8 RGB, depth [H x W] metres -> the motion since the last kept frame."""
        grey = cv2.cvtColor(color, cv2.COLOR_RGB2GRAY)
        self._grey, self._depth = grey, depth
        if self._ref_grey is None or self._ref_px is None or len(self._ref_px) == 0:
            up = MotionUpdate(0.0 if self._ref_grey is None else 180.0, self._T_first_ref.copy(), 0,
                              self._ref_grey is not None)
            self._last = up
            return up
        lk = {"winSize": (21, 21), "maxLevel": 3}
        nxt, st, _ = cv2.calcOpticalFlowPyrLK(self._ref_grey, grey, self._ref_px, None, **lk)  # type: ignore[call-overload]
        back, st2, _ = cv2.calcOpticalFlowPyrLK(grey, self._ref_grey, nxt, None, **lk)  # type: ignore[call-overload]
        ok = (st[:, 0] == 1) & (st2[:, 0] == 1) & (np.linalg.norm((back - self._ref_px)[:, 0], axis=1) < 1.0)
        px = nxt[:, 0]
        h, w = depth.shape
        u = np.rint(px[:, 0]).astype(int)
        v = np.rint(px[:, 1]).astype(int)
        ok &= (u >= 0) & (u < w) & (v >= 0) & (v < h)
        z = np.zeros(len(px))
        z[ok] = depth[v[ok], u[ok]]
        ok &= z > 0
        n = int(ok.sum())
        if n < max(self.params.min_tracked, 3):
            up = MotionUpdate(0.0, self._T_first_ref.copy(), n, True)
            self._last = up
            return up
        assert self._ref_pts is not None
        cur = backproject_pixels(px[ok], z[ok], self.intr)
        T_cur_ref, keep = kabsch_trimmed(self._ref_pts[ok], cur, self.params.tau)
        n = int(keep.sum())
        lost = n < max(self.params.min_tracked, 3)
        T_first_cam = self._T_first_ref if lost else self._T_first_ref @ inv_T(T_cur_ref)
        assert self._ref_dir is not None
        cosang = float(np.clip(self._direction(T_first_cam) @ self._ref_dir, -1.0, 1.0))
        up = MotionUpdate(0.0 if lost else float(np.degrees(np.arccos(cosang))), T_first_cam.copy(), n, lost)
        self._last = up
        return up

    def wants(self, up: MotionUpdate) -> bool:
        """Whether the frame of `up` moved enough (or lost tracking) to be kept."""
        return self._ref_grey is None or up.lost or up.angle_deg >= self.params.min_angle_deg

    def keep(self) -> np.ndarray:
        """Make the frame last passed to `update` the reference; returns its viewing direction (first kept axes)."""
        up = self._last
        assert up is not None, "update() first"
        grey, depth = self._grey, self._depth
        if self.center is None:  # first kept frame: the object is what the middle of the image shows
            h, w = depth.shape
            mid = depth[int(0.4 * h):int(0.6 * h), int(0.4 * w):int(0.6 * w)]
            valid = mid[mid > 0] if np.any(mid > 0) else depth[depth > 0]
            self.center = np.array([0.0, 0.0, float(np.median(valid)) if valid.size else 1.0])
            self.R_up_first = up_frame(depth, self.intr, self.params)
        self._T_first_ref = up.T_first_cam.copy()
        self._ref_dir = self._direction(self._T_first_ref)
        assert self.R_up_first is not None
        self.coverage.add(self.R_up_first @ self._ref_dir)
        corners = cv2.goodFeaturesToTrack(grey, self.params.max_corners, 0.01, 7, mask=self._region(grey.shape))
        if corners is None:
            self._ref_grey, self._ref_px, self._ref_pts = grey, np.zeros((0, 1, 2), np.float32), np.zeros((0, 3))
            return self._ref_dir
        px = corners[:, 0].astype(np.float64)
        u, v = np.rint(px[:, 0]).astype(int), np.rint(px[:, 1]).astype(int)
        z = depth[v, u]
        good = z > 0
        self._ref_grey = grey
        self._ref_px = corners[good].astype(np.float32)
        self._ref_pts = backproject_pixels(px[good], z[good], self.intr)
        return self._ref_dir
