"""Depth registered to the colour camera: every depth pixel reprojected with the extrinsics and both intrinsics.

A depth pixel (u, v) with depth z is a small square of the depth image; its four corners
(u +- 0.5, v +- 0.5) at depth z are moved into the colour camera (the `DepthCamera`'s T_color_depth) and
projected with the colour intrinsics. Every colour pixel whose centre lies in the bounding box of the projected
corners, grown by `MARGIN_PX` on each side, receives the point's depth in the colour camera (its z after the
transform, not the depth camera's z). Where several depth pixels land on one colour pixel the nearest wins
(z-buffer); colour pixels that none reaches stay 0 (holes are not filled: occlusions stay empty).

The footprint makes resolution changes crack-free (a depth pixel covers every colour pixel under it), and the
margin closes the sub-pixel gaps that parallax opens between neighbouring pixels of a slanted surface; with
identical cameras each pixel maps onto itself alone. librealsense's `rs2::align` splats the same footprint
(two corners, inclusive rounding, which covers one pixel more per side) and writes the depth camera's z.

`align_depth_to_color` runs a numba kernel (`cache=True`); `align_depth_reference` is the same rule in plain
Python, the specification the tests hold the kernel to.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from gscan.io.camera import DepthCamera, Intrinsics

MARGIN_PX = 0.25  # growth of each projected footprint (colour pixels); < 0.5 keeps the identity mapping 1:1
# a depth pixel spanning more colour pixels (a point almost in the colour camera's plane) is dropped
MAX_FOOTPRINT_PX = 64
_CORNERS = ((-0.5, -0.5), (0.5, -0.5), (-0.5, 0.5), (0.5, 0.5))


@njit(cache=True, nogil=True)
def _splat(depth: np.ndarray, kd: np.ndarray, R: np.ndarray, t: np.ndarray, kc: np.ndarray, out: np.ndarray,
           margin: float, max_px: int, same: bool) -> None:  # pragma: no cover - compiled
    Hd, Wd = depth.shape
    Hc, Wc = out.shape
    fxd, fyd, cxd, cyd = kd[0], kd[1], kd[2], kd[3]
    fxc, fyc, cxc, cyc = kc[0], kc[1], kc[2], kc[3]
    for i in range(Hc):
        for j in range(Wc):
            out[i, j] = np.inf
    for v in range(Hd):
        for u in range(Wd):
            z = np.float64(depth[v, u])
            if not (z > 0.0) or not math.isfinite(z):
                continue
            if same:  # R = I, t = 0: the general branch's values, a corner's u or v alone deciding each
                zc = z
                pu0 = fxc * ((u - 0.5 - cxd) / fxd * z) / z + cxc
                pu1 = fxc * ((u + 0.5 - cxd) / fxd * z) / z + cxc
                pv0 = fyc * ((v - 0.5 - cyd) / fyd * z) / z + cyc
                pv1 = fyc * ((v + 0.5 - cyd) / fyd * z) / z + cyc
                umin, umax, vmin, vmax = min(pu0, pu1), max(pu0, pu1), min(pv0, pv1), max(pv0, pv1)
            else:
                x = (u - cxd) / fxd * z
                y = (v - cyd) / fyd * z
                zc = R[2, 0] * x + R[2, 1] * y + R[2, 2] * z + t[2]
                if not (zc > 0.0):
                    continue
                umin, umax, vmin, vmax = np.inf, -np.inf, np.inf, -np.inf
                ok = True
                for k in range(4):
                    du = -0.5 if k % 2 == 0 else 0.5
                    dv = -0.5 if k < 2 else 0.5
                    xk = (u + du - cxd) / fxd * z
                    yk = (v + dv - cyd) / fyd * z
                    X = R[0, 0] * xk + R[0, 1] * yk + R[0, 2] * z + t[0]
                    Y = R[1, 0] * xk + R[1, 1] * yk + R[1, 2] * z + t[1]
                    Z = R[2, 0] * xk + R[2, 1] * yk + R[2, 2] * z + t[2]
                    if not (Z > 0.0):
                        ok = False
                        break
                    pu = fxc * X / Z + cxc
                    pv = fyc * Y / Z + cyc
                    umin = min(umin, pu)
                    umax = max(umax, pu)
                    vmin = min(vmin, pv)
                    vmax = max(vmax, pv)
                if not ok:
                    continue
            x0 = math.ceil(umin - margin)
            x1 = math.floor(umax + margin)
            y0 = math.ceil(vmin - margin)
            y1 = math.floor(vmax + margin)
            if x1 - x0 >= max_px or y1 - y0 >= max_px:
                continue
            x0, y0 = max(x0, 0), max(y0, 0)
            x1, y1 = min(x1, Wc - 1), min(y1, Hc - 1)
            zf = np.float32(zc)
            for yy in range(y0, y1 + 1):
                for xx in range(x0, x1 + 1):
                    out[yy, xx] = min(out[yy, xx], zf)
    for i in range(Hc):
        for j in range(Wc):
            if out[i, j] == np.inf:
                out[i, j] = 0.0


def _params(intr: Intrinsics) -> np.ndarray:
    return np.array([intr.fx, intr.fy, intr.cx, intr.cy], dtype=np.float64)


def align_depth_to_color(depth: np.ndarray, depth_camera: DepthCamera, color_intr: Intrinsics) -> np.ndarray:
    """[Hd x Wd] depth (m, 0 = invalid) of `depth_camera` -> [Hc x Wc] float32 depth (m) in the colour camera.

    The depth camera's T_color_depth maps its points into the colour camera (see the module docstring); a camera of
    no particular size takes the depth image's. ValueError when the camera cannot be of the depth image's size.
    """
    depth_intr = depth_camera.for_size(depth.shape[1], depth.shape[0])
    T = depth_camera.T_color_depth
    out = np.empty((color_intr.height, color_intr.width), dtype=np.float32)
    _splat(np.ascontiguousarray(depth, dtype=np.float32), _params(depth_intr), np.ascontiguousarray(T[:3, :3]),
           np.ascontiguousarray(T[:3, 3]), _params(color_intr), out, MARGIN_PX, MAX_FOOTPRINT_PX,
           bool(np.array_equal(T, np.eye(4))))
    return out


def align_depth_reference(depth: np.ndarray, depth_camera: DepthCamera, color_intr: Intrinsics) -> np.ndarray:
    """`align_depth_to_color` in plain Python and numpy (slow; the specification for tests)."""
    T = depth_camera.T_color_depth
    R, t = T[:3, :3], T[:3, 3]
    d, c = depth_camera.for_size(depth.shape[1], depth.shape[0]), color_intr
    out = np.full((c.height, c.width), np.inf, dtype=np.float32)

    def cam_point(u: float, v: float, z: float) -> np.ndarray:  # depth pixel at depth z -> colour camera
        return R @ np.array([(u - d.cx) / d.fx * z, (v - d.cy) / d.fy * z, z]) + t

    for v, u in zip(*np.nonzero(np.isfinite(depth) & (depth > 0)), strict=True):
        z = float(depth[v, u])
        zc = cam_point(u, v, z)[2]
        if not zc > 0:
            continue
        corners = np.array([cam_point(u + du, v + dv, z) for du, dv in _CORNERS])
        if np.any(corners[:, 2] <= 0):
            continue
        pu = c.fx * corners[:, 0] / corners[:, 2] + c.cx
        pv = c.fy * corners[:, 1] / corners[:, 2] + c.cy
        x0, x1 = math.ceil(pu.min() - MARGIN_PX), math.floor(pu.max() + MARGIN_PX)
        y0, y1 = math.ceil(pv.min() - MARGIN_PX), math.floor(pv.max() + MARGIN_PX)
        if x1 - x0 >= MAX_FOOTPRINT_PX or y1 - y0 >= MAX_FOOTPRINT_PX:
            continue
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, c.width - 1), min(y1, c.height - 1)
        if x1 >= x0 and y1 >= y0:
            block = out[y0:y1 + 1, x0:x1 + 1]
            np.minimum(block, np.float32(zc), out=block)
    out[np.isinf(out)] = 0.0
    return out
