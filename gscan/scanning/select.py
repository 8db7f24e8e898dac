"""Frame selection: which frames of a capture a scan keeps, decided as the frames stream in.

A recording at 30 frames a second holds far more frames than a scan needs: frames a fraction of a degree apart,
or taken while the camera stood still, add time and nothing else. A frame is kept once the view has moved enough
since the last kept frame, and a blurred frame is passed over for a sharper one that follows:

- motion: the rigid motion of the scene (static object) or of the object (moving object: on the kept frame's
  object mask) between the last kept frame and this one. Corners of the kept frame (in the middle of the image,
  where a scan keeps the object) are lifted with its depth and tracked into this frame (pyramidal Lucas-Kanade,
  forward-backward checked); the pose that projects the lifted corners onto the tracked ones is solved (PnP,
  iterated from no motion, refit on the corners within `REPROJECTION_PX`). The image positions decide it, not
  the depth of both frames, so a still frame measures still through the depth noise. As an angle: the larger
  of its rotation and its translation seen from the kept frame's centre depth (degrees(|t| / z)). A frame is
  kept when that reaches `min_motion_deg`. Motion is measured against the last kept frame, never summed over
  frames, so it does not drift. The first frame is kept; so is every frame whose motion cannot be measured
  (fewer than `MIN_TRACKED` corners followed: a dark or textureless frame, a cut, a moving object without a
  mask to track it in), which keeps a capture the cue cannot follow as it was.
- sharpness: the variance of the Laplacian of the grey image at half resolution. A frame that moved enough but
  is below `blur_ratio` of the median sharpness of the `blur_window` frames before it is passed over while its
  motion is below `blur_wait` times `min_motion_deg`; beyond that it is kept (a blurred view beats a gap).

A capture whose every frame moves at least `blur_wait x min_motion_deg` keeps every frame. Deterministic.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import Annotated

import cv2
import numpy as np
from pydantic import Field

from gscan.io.camera import Intrinsics, RGBDFrame, backproject_pixels
from gscan.scanning.segment import centre_depth
from gscan.settings import SETTINGS

BLUR_MIN_HISTORY = 3  # the blur test needs this many frames before it (the first frames are never called blurred)
CORNERS = 300  # corners tracked from a kept frame ...
CORNER_REGION = 0.6  # ... taken in this central fraction of the image's width and height
MIN_TRACKED = 20  # fewer corners followed (with depth, consistent with one motion): the motion is unknown
REPROJECTION_PX = 1.5  # a tracked corner farther than this from the solved motion's projection is not used
LK_WINDOW = 21  # Lucas-Kanade window (px) ...
LK_LEVELS = 3  # ... and pyramid levels

LITTLE_MOTION = "little motion"  # the categories of skipped frames (`Selection.counts`)
BLURRED = "blurred"


@dataclass(frozen=True)
class SelectionParams:
    """Which input frames a scan keeps."""

    __pydantic_config__ = SETTINGS

    min_motion_deg: Annotated[float, Field(ge=0, le=90, description="a frame is kept once the view moved this much "
                                           "since the last kept frame (rotation, or translation as an angle at the "
                                           "scene's depth); 0 keeps every frame")] = 0.5
    blur_ratio: Annotated[float, Field(ge=0, lt=1, description="a frame less sharp than this share of the frames "
                                       "before it is passed over for a sharper one (until the view moved twice "
                                       "min_motion_deg); 0 never")] = 0.5
    blur_window: Annotated[int, Field(ge=1, le=1000, description="frames whose median sharpness a frame is compared "
                                      "with")] = 15
    blur_wait: Annotated[float, Field(ge=1, description="a blurred frame is passed over while it moved less than "
                                      "this many times min_motion_deg")] = 2.0


@dataclass
class Selection:
    """The frames a scan kept and skipped: kept names in order; skipped name -> (category, one-line reason)."""

    params: SelectionParams
    kept: list[str] = field(default_factory=list)
    skipped: dict[str, tuple[str, str]] = field(default_factory=dict)
    # a skipped frame -> the kept frame it was compared with (its pose is found by registration to that one)
    reference: dict[str, str] = field(default_factory=dict)

    def summary(self) -> dict:
        """{"kept": frames kept, "skipped": frames skipped, "reasons": {why, in words: frames}} (`scan --json`)."""
        counts: dict[str, int] = {}
        for cat, _ in self.skipped.values():
            key = describe(cat, self.params)
            counts[key] = counts.get(key, 0) + 1
        return {"kept": len(self.kept), "skipped": len(self.skipped), "reasons": counts}

    def to_meta(self) -> dict:
        """The template database's "selection" meta: `summary` and "frames": {skipped frame: why, in one line}."""
        return self.summary() | {"frames": {n: why for n, (_, why) in self.skipped.items()}}


def describe(category: str, params: SelectionParams) -> str:
    """A category of skipped frames in words."""
    if category == LITTLE_MOTION:
        return f"moved less than {params.min_motion_deg:g} deg since the last kept frame"
    return "blurred (a sharper frame close by was kept)"


def sharpness(color: np.ndarray) -> float:
    """Variance of the Laplacian of the grey image [H x W x 3] uint8 RGB at half resolution (higher: sharper)."""
    grey = cv2.cvtColor(color, cv2.COLOR_RGB2GRAY)
    small = cv2.resize(grey, (max(1, grey.shape[1] // 2), max(1, grey.shape[0] // 2)), interpolation=cv2.INTER_AREA)
    return float(cv2.Laplacian(small, cv2.CV_32F).var())


def motion_deg(T_ref_cur: np.ndarray, depth_m: float) -> float:
    """The view change of a rigid motion T_ref_cur [4 x 4] seen from depth `depth_m` (m), in degrees: the larger
    of its rotation angle and its translation's angle at that depth."""
    T = np.asarray(T_ref_cur, dtype=np.float64)
    rot = float(np.degrees(np.arccos(np.clip((np.trace(T[:3, :3]) - 1.0) / 2.0, -1.0, 1.0))))
    return max(rot, float(np.degrees(np.linalg.norm(T[:3, 3]) / max(depth_m, 1e-6))))


@dataclass
class _Reference:
    """A kept frame's corners: grey image [H x W] uint8, pixels [N x 1 x 2] float32 and their camera points [N x 3]."""

    grey: np.ndarray
    px: np.ndarray
    pts: np.ndarray


def _reference(frame: RGBDFrame, grey: np.ndarray, mask: np.ndarray | None) -> _Reference:
    """The corners of a kept frame in the central region (and `mask` [H x W] bool) that have depth."""
    h, w = grey.shape
    region = np.zeros((h, w), np.uint8)
    my, mx = int((1 - CORNER_REGION) / 2 * h), int((1 - CORNER_REGION) / 2 * w)
    region[my:h - my, mx:w - mx] = 255
    if mask is not None:  # corners whose tracking window lies on the object: the background does not follow it
        half = LK_WINDOW // 2
        inside = cv2.erode(np.asarray(mask, dtype=np.uint8), np.ones((2 * half + 1, 2 * half + 1), np.uint8))
        region[inside == 0] = 0
    corners = cv2.goodFeaturesToTrack(grey, CORNERS, 0.01, 7, mask=region)
    if corners is None:
        return _Reference(grey, np.zeros((0, 1, 2), np.float32), np.zeros((0, 3)))
    px = corners[:, 0].astype(np.float64)
    z = frame.depth[np.rint(px[:, 1]).astype(int), np.rint(px[:, 0]).astype(int)]
    good = z > 0
    return _Reference(grey, corners[good].astype(np.float32), backproject_pixels(px[good], z[good], frame.intrinsics))


def _motion(ref: _Reference, grey: np.ndarray, intr: Intrinsics) -> np.ndarray | None:
    """T_cur_ref [4 x 4], the rigid motion from the kept frame `ref` to the frame of `grey`, or None when too few
    corners follow it (see the module docstring)."""
    if len(ref.px) < MIN_TRACKED:
        return None
    lk = {"winSize": (LK_WINDOW, LK_WINDOW), "maxLevel": LK_LEVELS}
    nxt, st, _ = cv2.calcOpticalFlowPyrLK(ref.grey, grey, ref.px, None, **lk)  # type: ignore[call-overload]
    back, st2, _ = cv2.calcOpticalFlowPyrLK(grey, ref.grey, nxt, None, **lk)  # type: ignore[call-overload]
    ok = (st[:, 0] == 1) & (st2[:, 0] == 1) & (np.linalg.norm((back - ref.px)[:, 0], axis=1) < 1.0)
    if ok.sum() < MIN_TRACKED:
        return None
    obj, img = ref.pts[ok].astype(np.float64), nxt[ok, 0].astype(np.float64)
    K = intr.K.astype(np.float64)
    rvec: np.ndarray = np.zeros((3, 1))
    tvec: np.ndarray = np.zeros((3, 1))
    for _ in range(2):  # solve from no motion, then again on the corners it explains
        good, r, t = cv2.solvePnP(obj, img, K, None, rvec, tvec, useExtrinsicGuess=True,
                                  flags=cv2.SOLVEPNP_ITERATIVE)
        rvec, tvec = np.asarray(r, dtype=np.float64), np.asarray(t, dtype=np.float64)
        if not good:
            return None
        proj = cv2.projectPoints(obj, rvec, tvec, K, None)[0][:, 0]
        inl = np.linalg.norm(proj - img, axis=1) <= REPROJECTION_PX
        if inl.sum() < MIN_TRACKED:
            return None
        obj, img = obj[inl], img[inl]
    T = np.eye(4)
    T[:3, :3] = np.asarray(cv2.Rodrigues(rvec)[0], dtype=np.float64)
    T[:3, 3] = tvec[:, 0]
    return T


class FrameSelector:
    """Feed every frame in order to `consider`; for each frame it keeps (None), call `keep` before the next one.

    mask_needed: the motion is an object's in front of a static camera, measured on the kept frame's object mask
    (`keep(frame, mask)`): a kept frame without one keeps the frames after it until one comes with one.
    """

    def __init__(self, params: SelectionParams = SelectionParams(), mask_needed: bool = False):
        self.params = params
        self.mask_needed = mask_needed
        self._ref: _Reference | None = None  # the last kept frame's corners (None: its motion cannot be followed)
        self._ref_name: str | None = None
        self._intrinsics: Intrinsics | None = None
        self._depth = 1.0  # its centre depth (m)
        self._sharpness: deque[float] = deque(maxlen=params.blur_window)
        self._grey: np.ndarray | None = None  # the frame last considered

    @property
    def reference(self) -> str | None:
        """The name of the last kept frame, the one a skipped frame was compared with."""
        return self._ref_name

    def consider(self, frame: RGBDFrame) -> tuple[str, str] | None:
        """None: keep the frame; else (category, reason) it is skipped for."""
        p = self.params
        self._grey = cv2.cvtColor(frame.color, cv2.COLOR_RGB2GRAY)
        s = sharpness(frame.color) if p.blur_ratio > 0 else 0.0
        recent = list(self._sharpness)
        self._sharpness.append(s)
        if p.min_motion_deg <= 0 or self._ref is None or frame.intrinsics != self._intrinsics:
            return None
        T = _motion(self._ref, self._grey, frame.intrinsics)
        if T is None:
            return None
        moved = motion_deg(T, self._depth)
        since = f"{moved:.2f} deg since frame {self._ref_name}"
        if moved < p.min_motion_deg:
            return LITTLE_MOTION, f"moved {since} (frames are kept every {p.min_motion_deg:g} deg)"
        if (p.blur_ratio > 0 and len(recent) >= BLUR_MIN_HISTORY and moved < p.blur_wait * p.min_motion_deg
                and s < p.blur_ratio * float(np.median(recent))):
            share = s / max(float(np.median(recent)), 1e-12)
            return BLURRED, (f"blurred: sharpness {share:.0%} of the median of the {len(recent)} frames before it "
                             f"(moved {since})")
        return None

    def keep(self, frame: RGBDFrame, mask: np.ndarray | None = None) -> None:
        """The frame just considered is kept: it becomes the reference (`mask` [H x W] bool: where the object is)."""
        if self.params.min_motion_deg <= 0:
            return
        grey = self._grey if self._grey is not None else cv2.cvtColor(frame.color, cv2.COLOR_RGB2GRAY)
        blind = self.mask_needed and (mask is None or not mask.any())
        self._ref = None if blind else _reference(frame, grey, mask)
        self._ref_name = frame.name
        self._intrinsics = frame.intrinsics
        z = centre_depth(frame)
        valid = frame.depth[frame.depth > 0]
        self._depth = z if z is not None else float(np.median(valid)) if valid.size else 1.0
