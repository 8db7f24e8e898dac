"""The template mesh closed into a watertight model for the exports (BOP, FoundationPose, meshes).

A scan never sees the object's bottom: the support plane cut it, and the fused mesh is open there. Model users
(BOP's renderers and scorers, FoundationPose, physics and grasp planners) expect a closed surface, so the
exports close it by default (`gscan.geometry.meshfill.close_holes_cleanly`): the mesh is cut flat just above
its ragged bottom loop, which gets walls down to the support plane and a flat cap on it; other holes are closed
by fans; no two triangles of the result cross (open3d's `is_watertight` holds). The triangles the closing added
are flagged (`MeshData.filled`; the PLY export's face property `filled`).

The support plane's height in the template frame (whose z axis is the plane's normal when the scan found a
plane) is measured again from the stored views: the median height of the measured points on a ring around
the mesh's footprint, near its bottom (the table beside the object). Without a plane the frame's z is no
plane's normal, and every hole is closed by a fan.
"""
from __future__ import annotations

import logging

import numpy as np

from gscan.geometry.meshfill import close_holes_cleanly, non_manifold_edges
from gscan.geometry.transforms import transform_points
from gscan.io.camera import backproject
from gscan.io.sequence import spread_indices
from gscan.template.db import MeshData, TemplateDB

log = logging.getLogger(__name__)

FLOOR_VIEWS = 8  # views whose depth measures the plane (spread over the registered ones)
RING = (0.01, 0.06)  # m: the ring around the footprint's box where the table is looked for
FLOOR_BAND = (-0.05, 0.02)  # m: heights relative to the mesh's lowest vertex where the table may lie
FLOOR_ACCEPT = (-0.02, 0.005)  # m: a plane farther below (the object on a stand) or above is not used
MIN_FLOOR_POINTS = 500
DEPTH_STRIDE = 4  # every 4th pixel row and column


def support_floor_z(db: TemplateDB, mesh: MeshData) -> float | None:
    """Height (m) of the support plane in the template frame, or None when the scan found no plane or the
    stored views do not show it close below the mesh (see the module docstring)."""
    if not db.get_meta("support_plane"):
        return None
    V = np.asarray(mesh.vertices, dtype=np.float64)
    lo, hi = V[:, :2].min(0), V[:, :2].max(0)
    z_lo = float(V[:, 2].min())
    names = [v.name for v in db.views(load_images=False) if v.T_obj_cam is not None]
    if not names:
        return None
    pick = [names[i] for i in spread_indices(len(names), FLOOR_VIEWS)]
    heights = []
    for name in pick:
        v = db.view(name, load_images=True)
        if v.depth is None or v.T_obj_cam is None:
            continue
        P = backproject(v.depth, v.intrinsics)[::DEPTH_STRIDE, ::DEPTH_STRIDE].reshape(-1, 3)
        P = transform_points(v.T_obj_cam, P[P[:, 2] > 0].astype(np.float64))
        outside = np.max(np.maximum(lo - P[:, :2], P[:, :2] - hi), axis=1)  # distance beyond the box (Chebyshev)
        near = (outside > RING[0]) & (outside < RING[1])
        near &= (P[:, 2] > z_lo + FLOOR_BAND[0]) & (P[:, 2] < z_lo + FLOOR_BAND[1])
        heights.append(P[near, 2])
    z = np.concatenate(heights) if heights else np.zeros(0)
    if len(z) < MIN_FLOOR_POINTS:
        log.info("%s: the views show too little of the support plane around the object (%d points)", db.path, len(z))
        return None
    floor = float(np.median(z))
    if not FLOOR_ACCEPT[0] <= floor - z_lo <= FLOOR_ACCEPT[1]:
        log.info("%s: support plane %.1f mm from the mesh's lowest point: not the cut bottom's plane", db.path,
                 1000 * (floor - z_lo))
        return None
    return floor


def closed_mesh(db: TemplateDB, mesh: MeshData) -> MeshData:
    """`mesh` with its holes closed (module docstring): the observed vertices and triangles kept come first, and
    `filled` flags the added triangles. Logs what was closed, and warns when the result is still not watertight
    (edges shared by more than two triangles, which no cap can mend)."""
    floor = support_floor_z(db, mesh)
    if floor is None and db.get_meta("support_plane"):
        floor = float(np.min(np.asarray(mesh.vertices)[:, 2]))  # the plane's normal is z: close at the lowest point
    c, filled = close_holes_cleanly(mesh.vertices, mesh.triangles, mesh.vertex_colors, floor_z=floor)
    if c.holes_closed:
        log.info("%s: closed %d hole(s) of the mesh (%d cut bottom(s) walled down to z = %s m; %d of %d triangles "
                 "filled)", db.path, c.holes_closed, c.bottom_loops, "none" if floor is None else f"{floor:+.4f}",
                 int(filled.sum()), len(filled))
    shared = non_manifold_edges(c.triangles)
    if c.boundary_edges_left or shared:
        log.warning("%s: the exported mesh is not watertight: %d open edge(s), %d edge(s) shared by more than two "
                    "triangles", db.path, c.boundary_edges_left, shared)
    colors = None if c.vertex_colors is None else np.asarray(c.vertex_colors, dtype=np.uint8)
    return MeshData(c.vertices, c.triangles, colors, filled=filled)
