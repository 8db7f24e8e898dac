"""The triangle mesh record (vertex colours, no texture) that scans, CAD templates, the template database,
the exporters and the viewer share, and the colour convention of meshes and clouds (uint8 RGB).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import overload

import numpy as np

from gscan.geometry.transforms import transform_points


@overload
def to_u8_colors(c: np.ndarray) -> np.ndarray: ...
@overload
def to_u8_colors(c: None) -> None: ...
@overload
def to_u8_colors(c: np.ndarray | None) -> np.ndarray | None: ...
def to_u8_colors(c: np.ndarray | None) -> np.ndarray | None:
    """[N x 3|4] colours, uint8 or float in [0, 1] -> [N x 3] uint8."""
    if c is None:
        return None
    c = np.asarray(c)[:, :3]
    if c.dtype == np.uint8:
        return np.ascontiguousarray(c)
    return np.clip(np.rint(c.astype(np.float64) * 255.0), 0, 255).astype(np.uint8)


@dataclass
class MeshData:
    """vertices [V x 3] float (m), triangles [F x 3] int, vertex_colors [V x 3] uint8 | None; the frame is the
    holder's (object frame in a template database). `filled` [F] bool | None: True for the triangles that closing
    the mesh's holes added (no camera saw them; `gscan.exporters.watertight`), None for a mesh as fused."""

    vertices: np.ndarray
    triangles: np.ndarray
    vertex_colors: np.ndarray | None = None
    filled: np.ndarray | None = None

    def transformed(self, T_b_a: np.ndarray) -> MeshData:
        """The same mesh with its vertices mapped from frame a into frame b ([V x 3] float64)."""
        return MeshData(vertices=transform_points(T_b_a, self.vertices), triangles=self.triangles,
                        vertex_colors=self.vertex_colors, filled=self.filled)

    def simplified(self, max_triangles: int) -> MeshData:
        """The mesh with at most `max_triangles` triangles (open3d's quadric decimation, colours carried; `filled`
        dropped), or itself when it has no more."""
        if len(self.triangles) <= max_triangles:
            return self
        import open3d as o3d

        m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.asarray(self.vertices, np.float64)),
                                      o3d.utility.Vector3iVector(np.asarray(self.triangles, np.int32)))
        if self.vertex_colors is not None:
            m.vertex_colors = o3d.utility.Vector3dVector(np.asarray(self.vertex_colors, np.float64) / 255.0)
        m = m.simplify_quadric_decimation(max_triangles)
        colors = None if self.vertex_colors is None else \
            (np.asarray(m.vertex_colors) * 255).round().astype(np.uint8)
        return MeshData(np.asarray(m.vertices), np.asarray(m.triangles), colors)
