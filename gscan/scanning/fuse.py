"""TSDF fusion of segmented, registered RGB-D frames into a mesh, and the template frame.

Fusion uses open3d's tensor `VoxelBlockGrid` on CPU:0 (the legacy ScalableTSDFVolume of open3d
0.20 returns empty meshes). Only the masked depth of each frame is integrated (the object's
pixels; the caller passes `frame.depth > 0` as the mask for a whole-scene scan). Small floating
fragments are removed from the mesh; the point cloud keeps only points near the kept mesh.

Template frame: origin at the centre of the object's bounding
box, z along the support-plane normal (up) when a plane is known, x and y along the principal
axes of the object's points projected on the plane; otherwise the axes of the first camera.
"""
from __future__ import annotations

import logging
import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Annotated

import numpy as np
from pydantic import Field

from gscan.geometry.mesh import MeshData, to_u8_colors
from gscan.geometry.plane import Plane
from gscan.geometry.transforms import inv_T, make_T, transform_points
from gscan.io.camera import RGBDFrame, backproject
from gscan.io.sequence import spread_indices
from gscan.settings import SETTINGS

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FusionParams:
    """TSDF fusion of the object's depth and the mesh taken from it."""

    __pydantic_config__ = SETTINGS

    voxel: Annotated[float | None, Field(gt=0, description="TSDF voxel size (m); null = object extent / 150 within "
                                         "voxel_min - voxel_max")] = None
    voxel_min: Annotated[float, Field(gt=0, description="smallest automatic voxel (m)")] = 0.002
    voxel_max: Annotated[float, Field(gt=0, description="largest automatic voxel (m)")] = 0.01
    trunc_voxels: Annotated[float, Field(gt=0, description="truncation distance, in voxels")] = 4.0
    block_resolution: Annotated[int, Field(ge=1, description="voxels per TSDF block side")] = 16
    depth_max: Annotated[float | None, Field(gt=0, description="depth beyond this is ignored when fusing (m); null = "
                                             "just beyond the farthest object pixel")] = None
    weight_threshold: Annotated[float, Field(ge=0, description="voxels with less weight (about observations) are not "
                                             "surfaced (capped below the number of fused frames)")] = 1.5
    min_component_fraction: Annotated[float, Field(ge=0, le=1, description="mesh components below this share of the "
                                                   "largest one's triangles are dropped")] = 0.1
    keep_largest_only: Annotated[bool, Field(description="keep just the largest connected component")] = False


@dataclass
class FusedModel:
    """Fused surface in the world frame of the poses.

    mesh: vertices [V x 3] float64 m, triangles [F x 3] int32, vertex_colors [V x 3] uint8;
    points [P x 3] float64 and point_colors [P x 3] uint8 (TSDF zero crossings); voxel_size m.
    """

    mesh: MeshData
    points: np.ndarray
    point_colors: np.ndarray
    voxel_size: float


def auto_voxel_size(extent_m: float, params: FusionParams = FusionParams()) -> float:
    """Voxel edge (m) for an object of largest extent `extent_m`: extent / 150 within the bounds."""
    return float(np.clip(extent_m / 150.0, params.voxel_min, params.voxel_max))


def _masked_depth(frame: RGBDFrame, mask: np.ndarray | None) -> np.ndarray:
    d = np.ascontiguousarray(frame.depth, dtype=np.float32).copy()
    if mask is not None:
        if mask.shape != d.shape:
            raise ValueError(f"mask {mask.shape} does not match depth {d.shape} of frame {frame.name}")
        d[~mask] = 0.0
    d[~np.isfinite(d)] = 0.0
    return d


def _extent_estimate(use: list[int], frames: Sequence[RGBDFrame], masks: Sequence[np.ndarray | None],
                     T_world_cam: list[np.ndarray | None]) -> float:
    """Largest extent (m) of the masked points of a few of the frames `use` in the world frame (robust
    percentiles)."""
    pts = []
    for i in spread_indices(len(use), 6, nearest=True):
        k = use[i]
        f = frames[k]
        d = _masked_depth(f, masks[k])
        p = backproject(d, f.intrinsics)[::4, ::4][d[::4, ::4] > 0]
        T = T_world_cam[k]
        assert T is not None, "the frames used are registered"
        pts.append(transform_points(T, p))
    P = np.concatenate(pts) if pts else np.zeros((0, 3))
    if len(P) < 10:
        return 0.0
    lo, hi = np.percentile(P, [1, 99], axis=0)
    return float((hi - lo).max())


def fuse_tsdf(frames: Sequence[RGBDFrame], T_world_cam: list[np.ndarray | None],
              masks: Sequence[np.ndarray | None] | None = None, params: FusionParams = FusionParams()) -> FusedModel:
    """Integrate the masked depth (and colour) of registered frames; extract mesh + point cloud.

    frames: N RGB-D frames; T_world_cam: N [4 x 4] poses (None = unregistered, skipped);
    masks: N [H x W] bool (None entry / None list: the whole valid depth). Frames and masks may be lazy sequences:
    they are read one at a time (twice each: the depth range, then the integration).
    Raises ValueError when nothing can be fused.
    """
    import open3d as o3d
    import open3d.core as o3c

    if masks is None:
        masks = [None] * len(frames)
    if not (len(frames) == len(T_world_cam) == len(masks)):
        raise ValueError(f"{len(frames)} frames, {len(T_world_cam)} poses, {len(masks)} masks")
    use: list[int] = []
    farthest = 0.0
    for k in range(len(frames)):
        if T_world_cam[k] is None:
            continue
        d = _masked_depth(frames[k], masks[k])
        # frames with no masked depth in range are left out: open3d's integration aborts on them
        if np.any((d > 0) & (d <= (params.depth_max or np.inf))):
            use.append(k)
            farthest = max(farthest, float(d.max()))
    if not use:
        raise ValueError("no registered frame with masked depth to fuse"
                         + (f" within {params.depth_max} m" if params.depth_max else ""))
    voxel = params.voxel or auto_voxel_size(_extent_estimate(use, frames, masks, T_world_cam), params)
    depth_max = params.depth_max or 1.05 * farthest
    trunc = params.trunc_voxels * voxel
    dev = o3c.Device("CPU:0")
    vbg = o3d.t.geometry.VoxelBlockGrid(attr_names=("tsdf", "weight", "color"),
                                        attr_dtypes=(o3c.float32, o3c.float32, o3c.float32),
                                        attr_channels=[o3c.SizeVector([1]), o3c.SizeVector([1]), o3c.SizeVector([3])],
                                        voxel_size=voxel,
                                        block_resolution=params.block_resolution, block_count=4000, device=dev)
    wt = min(params.weight_threshold, max(len(use) - 0.5, 0.5))  # a single frame still gives a surface
    try:
        for k in use:
            f = frames[k]
            K = o3c.Tensor(f.intrinsics.K, o3c.float64, dev)
            extr = o3c.Tensor(inv_T(np.asarray(T_world_cam[k], dtype=np.float64)), o3c.float64, dev)  # T_cam_world
            depth = o3d.t.geometry.Image(o3c.Tensor(_masked_depth(f, masks[k])[..., None], o3c.float32, dev))
            color = o3d.t.geometry.Image(
                o3c.Tensor(np.ascontiguousarray(f.color, dtype=np.float32) / 255.0, o3c.float32, dev))
            blocks = vbg.compute_unique_block_coordinates(depth, K, extr, 1.0, depth_max, params.trunc_voxels)
            vbg.integrate(blocks, depth, color, K, extr, 1.0, depth_max, params.trunc_voxels)
        o3d_mesh = vbg.extract_triangle_mesh(weight_threshold=wt).to_legacy()
        pcd = vbg.extract_point_cloud(weight_threshold=wt)
    except RuntimeError as e:  # open3d's check that the depth touched the volume (a few pixels, far depth)
        if "No block is touched" not in str(e):
            raise  # memory, capacity: internal, not the input's fault
        raise ValueError(f"TSDF fusion failed: {open3d_message(e)}") from None
    V, F, C = _mesh_arrays(o3d_mesh)
    V, F, C = remove_small_components(V, F, C, params.min_component_fraction, params.keep_largest_only)
    P = pcd.point.positions.numpy().astype(np.float64) if "positions" in pcd.point else np.zeros((0, 3))
    PC = pcd.point.colors.numpy().astype(np.float32) if "colors" in pcd.point else np.zeros((len(P), 3), np.float32)
    if len(V) and len(P):
        from scipy.spatial import cKDTree

        near = cKDTree(V).query(P, distance_upper_bound=2.0 * voxel)[0] < np.inf
        P, PC = P[near], PC[near]
    order = np.lexsort((P[:, 2], P[:, 1], P[:, 0]))  # independent of hash-map order
    P, PC = P[order], PC[order]
    log.info("fused %d frames at %.1f mm voxels (trunc %.1f mm): %d vertices, %d triangles, %d points",
             len(use), voxel * 1000, trunc * 1000, len(V), len(F), len(P))
    mesh = MeshData(vertices=V, triangles=F, vertex_colors=to_u8_colors(np.clip(C, 0.0, 1.0).astype(np.float32)))
    return FusedModel(mesh=mesh, points=P, point_colors=to_u8_colors(np.clip(PC, 0.0, 1.0)), voxel_size=voxel)


def open3d_message(e: Exception) -> str:
    """The sentence of an open3d error without its colour codes and C++ signature ("[Open3D Error] (void
    ...) file.cpp:186: No block is touched ..." -> "No block is touched ...")."""
    text = " ".join(re.sub(r"\x1b\[[0-9;]*m", "", str(e)).split())
    m = re.search(r"\.(?:cpp|h):\d+: (.*)$", text)
    return m.group(1) if m else text


def _mesh_arrays(mesh) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(V [V x 3] float64, F [F x 3] int32, C [V x 3] float32) of a legacy open3d TriangleMesh."""
    V = np.asarray(mesh.vertices, dtype=np.float64).reshape(-1, 3).copy()
    F = np.asarray(mesh.triangles).astype(np.int32).reshape(-1, 3).copy()
    C = np.asarray(mesh.vertex_colors).astype(np.float32).copy() if mesh.has_vertex_colors() \
        else np.full((len(V), 3), 0.5, np.float32)
    return V, F, C


def remove_small_components(vertices: np.ndarray, triangles: np.ndarray, colors: np.ndarray | None = None,
                            min_fraction: float = 0.1, keep_largest_only: bool = False
                            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Drop connected components (shared vertices, after merging duplicates) with fewer than
    `min_fraction` of the largest component's triangles (or all but the largest).

    vertices [V x 3], triangles [F x 3], colors [V x 3] | None -> (V', F' int32, C' float32).
    """
    import open3d as o3d

    V = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    F = np.asarray(triangles).reshape(-1, 3)
    if len(F) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int32), np.zeros((0, 3), np.float32)
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(V), o3d.utility.Vector3iVector(F.astype(np.int32)))
    if colors is not None:
        mesh.vertex_colors = o3d.utility.Vector3dVector(np.asarray(colors, dtype=np.float64).reshape(-1, 3))
    mesh.remove_duplicated_vertices()
    clusters, counts, _ = mesh.cluster_connected_triangles()
    tri_clusters, n_tri = np.asarray(clusters), np.asarray(counts)
    largest = int(np.argmax(n_tri))
    keep = tri_clusters == largest if keep_largest_only else n_tri[tri_clusters] >= min_fraction * n_tri[largest]
    mesh.remove_triangles_by_mask(~keep)
    mesh.remove_unreferenced_vertices()
    log.debug("mesh components: kept %d of %d", len(np.unique(tri_clusters[keep])), len(n_tri))
    return canonical_order(*_mesh_arrays(mesh))


def canonical_order(vertices: np.ndarray, triangles: np.ndarray, colors: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sort vertices lexicographically (x, y, z) and triangles by their (rotated, winding-preserving)
    indices, so that a mesh does not depend on hash-map / thread order. Shapes unchanged."""
    V = np.asarray(vertices, dtype=np.float64)
    order = np.lexsort((V[:, 2], V[:, 1], V[:, 0]))
    rank = np.empty(len(order), dtype=np.int64)
    rank[order] = np.arange(len(order))
    F = rank[np.asarray(triangles, dtype=np.int64)]
    if len(F):
        shift = np.argmin(F, axis=1)
        F = np.stack([F[np.arange(len(F)), (shift + k) % 3] for k in range(3)], axis=1)
        F = F[np.lexsort((F[:, 2], F[:, 1], F[:, 0]))]
    return V[order], F.astype(np.int32), np.asarray(colors, dtype=np.float32)[order]


def template_frame(points_world: np.ndarray, plane_world: Plane | None, T_world_cam0: np.ndarray) -> np.ndarray:
    """T_obj_world [4 x 4] of the template frame for object points [N x 3] in the world frame.

    With a plane: z = plane normal (up); x = major principal axis of the points projected on the
    plane, signed to point along the first camera's x axis (or, when nearly perpendicular to it,
    away from the first camera); y = z x x. Without: the first camera's axes. The origin is the
    centre of the points' bounding box in these axes. Deterministic.
    """
    P = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
    if len(P) < 3:
        raise ValueError(f"need at least 3 object points for the template frame, got {len(P)}")
    R_wc = np.asarray(T_world_cam0, dtype=np.float64)[:3, :3]
    if plane_world is None:
        R = R_wc.copy()
    else:
        z = np.asarray(plane_world.normal, dtype=np.float64)
        z = z / np.linalg.norm(z)
        Q = P - np.outer(P @ z, z)
        Q = Q - Q.mean(0)
        basis = np.linalg.svd(np.eye(3) - np.outer(z, z))[0][:, :2]  # two in-plane directions
        q2 = Q @ basis
        w, v = np.linalg.eigh(q2.T @ q2 / len(q2))
        x = basis @ v[:, np.argmax(w)]
        cam_x, cam_z = R_wc[:, 0], R_wc[:, 2]
        s = x @ cam_x if abs(x @ cam_x) > 0.1 else x @ cam_z
        x = x if s >= 0 else -x
        x /= np.linalg.norm(x)
        R = np.stack([x, np.cross(z, x), z], axis=1)
    local = P @ R  # coordinates along the axes
    centre_local = 0.5 * (local.min(0) + local.max(0))
    return inv_T(make_T(R, R @ centre_local))
