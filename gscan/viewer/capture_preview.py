"""Live preview of `gscan capture` in the browser (viser): the colour image, the depth, and the coverage.

GUI panel: the latest colour image and its depth (colour-mapped 0.2-2 m, holes black), a line of numbers
(frames seen and kept, directions covered, the angle moved since the last kept frame, tracking state) and
what is still missing, in words (`gscan.geometry.coverage`: the bottom too, until a view sees it).
Scene: the object centre at the origin, z up (`gscan.capture.motion.up_frame`); a sphere of directions around
it coloured by how many kept views see the object from that side (grey none, orange one, yellow two,
green three or more: `gscan.capture.motion.Coverage`); a frustum per kept view and a white one for the
current camera. Images are refreshed at most `MAX_IMAGE_HZ` times a second, so the preview costs the
capture little. Only the viewer imports viser.
"""
from __future__ import annotations

import contextlib
import io
import logging
import threading
import time
from typing import Any

import cv2
import numpy as np

from gscan.capture.record import FrameUpdate
from gscan.viewer.app import PortInUseError, check_port, quiet_websockets
from gscan.viewer.draw import coverage_colors, thumbnail
from gscan.viewer.scene import quat_wxyz

log = logging.getLogger(__name__)

MAX_IMAGE_HZ = 8.0
IMAGE_PX = 320  # longest side of the preview images
DEPTH_RANGE_M = (0.2, 2.0)
# first kept camera (x right, y down, z forward) -> preview world (x right, y forward, z up) until the tracker
# has its up frame
R_WORLD_CAM0 = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def depth_image(depth_mm: np.ndarray, max_px: int = IMAGE_PX) -> np.ndarray:
    """[H x W] uint16 mm -> [h x w x 3] uint8 RGB colour map (near red .. far blue), holes black."""
    d = thumbnail(depth_mm, max_px) if depth_mm.ndim == 2 else depth_mm
    m = d.astype(np.float32) / 1000.0
    lo, hi = DEPTH_RANGE_M
    t = np.clip((m - lo) / (hi - lo), 0.0, 1.0)
    rgb = cv2.cvtColor(cv2.applyColorMap((255 - t * 255).astype(np.uint8), cv2.COLORMAP_TURBO), cv2.COLOR_BGR2RGB)
    rgb[m <= 0] = 0
    return rgb


def missing_text(missing: list[str]) -> str:
    """The panel's markdown naming what is still missing (`CoverageMap.missing`)."""
    if not missing:
        return "every side of the object seen"
    return "still missing:  \n" + "  \n".join(f"- {m}" for m in missing)


class CapturePreview:
    """A viser server showing a capture as it runs; `update(FrameUpdate)` after each frame, `stop()` at the end."""

    def __init__(self, host: str = "127.0.0.1", port: int = 8080):
        import viser

        check_port(host, port)
        quiet_websockets()
        with contextlib.redirect_stdout(io.StringIO()):  # viser prints a banner; library code never prints
            self.server = viser.ViserServer(host=host, port=port, label="gscan capture", verbose=False)
        if self.server.get_port() != port:
            with contextlib.redirect_stdout(io.StringIO()):
                self.server.stop()
            raise PortInUseError(host, port)
        self.url = f"http://[{host}]:{port}" if ":" in host else f"http://{host}:{port}"
        self._lock = threading.Lock()
        self._last_image = 0.0
        self._views = 0
        self._radius = 0.3
        self.updates = 0
        gui = self.server.gui
        self._stats = gui.add_markdown("waiting for the first frame")
        blank = np.full((240, 320, 3), 60, np.uint8)
        self._color = gui.add_image(blank, label="Colour", format="jpeg", jpeg_quality=80)
        self._depth = gui.add_image(blank, label="Depth (0.2-2 m)", format="jpeg", jpeg_quality=80)
        self._center: np.ndarray | None = None  # object centre in the first kept camera (m)
        self._R_world_first = R_WORLD_CAM0  # the first kept camera's axes into the preview world
        self._missing = gui.add_markdown("")
        self._cloud: Any = None  # viser handles of the coverage sphere and the current camera
        self._current: Any = None

    def update(self, u: FrameUpdate) -> None:
        """Show frame `u` (images throttled, kept views and coverage at once)."""
        with self._lock:
            self.updates += 1
            sc = self.server.scene
            if self._center is None and u.center is not None:
                self._center = np.asarray(u.center, dtype=np.float64)
                self._radius = 0.5 * max(float(np.linalg.norm(self._center)), 0.05)
                if u.R_up_first is not None:
                    self._R_world_first = np.asarray(u.R_up_first, dtype=np.float64)
            now = time.monotonic()
            if u.kept_now or now - self._last_image >= 1.0 / MAX_IMAGE_HZ:
                self._last_image = now
                self._color.image = thumbnail(u.frame.color, IMAGE_PX)
                self._depth.image = depth_image(u.frame.depth_mm)
            cov = u.coverage
            state = "lost (frame kept as a new reference)" if u.motion.lost else f"{u.motion.tracked} corners"
            self._stats.content = (f"frames seen **{u.seen}** · kept **{u.kept}**  \n"
                                   f"directions covered **{cov.covered} / {len(cov.counts)}**  \n"
                                   f"moved {u.motion.angle_deg:.1f}° since the last kept frame · tracking: {state}")
            if u.kept_now:
                self._missing.content = missing_text(cov.map().missing())
            if self._center is None:
                return
            R, t = self._pose(u.motion.T_first_cam)
            fov = float(2.0 * np.arctan2(u.intrinsics.height / 2.0, u.intrinsics.fy))
            aspect = u.intrinsics.width / u.intrinsics.height
            if u.kept_now:
                self._views += 1
                sc.add_camera_frustum(f"/views/{self._views:06d}", fov=fov, aspect=aspect, scale=0.15 * self._radius,
                                      color=(60, 170, 255), wxyz=quat_wxyz(R), position=t)
                pts = cov.directions * self._radius  # already in the up frame
                self._cloud = sc.add_point_cloud("/coverage", pts.astype(np.float32), coverage_colors(cov.counts),
                                                 point_size=0.06 * self._radius)
            if self._current is None:
                self._current = sc.add_camera_frustum("/current", fov=fov, aspect=aspect, scale=0.2 * self._radius,
                                                      color=(255, 255, 255), wxyz=quat_wxyz(R), position=t)
            else:
                self._current.wxyz, self._current.position = quat_wxyz(R), t

    def _pose(self, T_first_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        assert self._center is not None
        R = self._R_world_first
        return R @ T_first_cam[:3, :3], R @ (T_first_cam[:3, 3] - self._center)

    def stop(self) -> None:
        with contextlib.redirect_stdout(io.StringIO()):
            self.server.stop()
