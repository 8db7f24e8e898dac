"""Depth images of a triangle mesh seen by a pinhole camera (open3d `RaycastingScene`, CPU)."""
from __future__ import annotations

from typing import Protocol

import numpy as np


class PinholeCamera(Protocol):
    """What a ray-cast needs of a camera (`gscan.io.camera.Intrinsics` has it): pixels, focal lengths and the
    principal point (pixel centres at integer coordinates)."""

    @property
    def fx(self) -> float: ...
    @property
    def fy(self) -> float: ...
    @property
    def cx(self) -> float: ...
    @property
    def cy(self) -> float: ...
    @property
    def width(self) -> int: ...
    @property
    def height(self) -> int: ...


class MeshRaycaster:
    """Ray-casts one mesh (vertices [V x 3], triangles [F x 3]) from many cameras; the BVH is built once."""

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray):
        import open3d as o3d

        self._o3d = o3d
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor.from_numpy(np.ascontiguousarray(vertices, dtype=np.float32)),
                                 o3d.core.Tensor.from_numpy(np.ascontiguousarray(triangles, dtype=np.uint32)))

    def depth(self, cam: PinholeCamera, T_obj_cam: np.ndarray, pixel_offset: float = 0.0) -> np.ndarray:
        """[H x W] float32 depth (m, along the optical axis) of the mesh seen by a camera at T_obj_cam [4 x 4]
        (the camera's pose in the mesh's frame), 0 where no triangle is hit. Back faces count: the first surface
        along each pixel's ray. Pixel (u, v)'s ray passes through (u + pixel_offset, v + pixel_offset) in the
        camera's pixel coordinates: 0 at its centre; 0.5 samples where OpenGL does with a projection built from
        the same K (at the centre of a pixel whose corner is at integer coordinates)."""
        u, v = np.meshgrid(np.arange(cam.width, dtype=np.float64) + pixel_offset,
                           np.arange(cam.height, dtype=np.float64) + pixel_offset)
        d_cam = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u)], -1).reshape(-1, 3)
        d_obj = d_cam @ np.asarray(T_obj_cam, dtype=np.float64)[:3, :3].T  # z = 1 in the camera: t_hit is depth
        o_obj = np.broadcast_to(np.asarray(T_obj_cam, dtype=np.float64)[:3, 3], d_obj.shape)
        rays = np.concatenate([o_obj, d_obj], axis=1).astype(np.float32)
        t = self.scene.cast_rays(self._o3d.core.Tensor.from_numpy(rays))["t_hit"].numpy().reshape(cam.height, cam.width)
        return np.where(np.isfinite(t), t, 0.0).astype(np.float32)
