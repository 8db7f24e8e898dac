"""Mesh exports (PLY / OBJ / GLB) through trimesh: metres, object frame, vertex colours, holes closed by default.
The PLY marks each face observed or filled (face property `filled`: 1 where closing the holes added it)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from gscan.errors import InputError
from gscan.exporters.common import require_mesh
from gscan.geometry.meshfill import boundary_edges, non_manifold_edges
from gscan.template.db import MeshData, TemplateDB


def to_trimesh(mesh: MeshData, scale: float = 1.0) -> trimesh.Trimesh:
    """The template mesh as a trimesh (vertex order kept; `scale` multiplies the vertices)."""
    tm = trimesh.Trimesh(vertices=np.asarray(mesh.vertices, dtype=np.float64) * scale,
                         faces=np.asarray(mesh.triangles, dtype=np.int64), process=False)
    if mesh.vertex_colors is not None:
        rgba = np.concatenate([mesh.vertex_colors, np.full((len(mesh.vertex_colors), 1), 255, np.uint8)], axis=1)
        tm.visual = trimesh.visual.ColorVisuals(tm, vertex_colors=rgba)
    return tm


def write_mesh(db: TemplateDB, path: Path, fmt: str, close: bool = True) -> tuple[int, str]:
    """Write the mesh as `fmt` ("ply" | "obj" | "glb") to the file `path`, with its holes closed (`close`,
    see `template_mesh`). A template without a mesh but with a point cloud exports the cloud as PLY;
    OBJ/GLB need a mesh. Returns (0 views, what the file holds)."""
    cloud = db.cloud() if fmt == "ply" and db.mesh() is None else None
    if cloud is not None:
        pts, cols = cloud
        pc = trimesh.PointCloud(np.asarray(pts, dtype=np.float64), colors=cols)
        path.write_bytes(pc.export(file_type="ply"))
        return 0, f"point cloud of {len(pts)} points (the template has no mesh)"
    mesh = require_mesh(db, close)
    tm = to_trimesh(mesh)
    if fmt == "ply":
        # a face property: 1 where closing the holes added the triangle (no camera saw it), 0 on the observed
        # surface; every face 0 for a mesh exported as fused (`close` off)
        filled = np.zeros(len(mesh.triangles), bool) if mesh.filled is None else mesh.filled
        tm.face_attributes["filled"] = np.asarray(filled, dtype=np.uint8)
        data = trimesh.exchange.ply.export_ply(tm, encoding="binary", vertex_normal=True)
    elif fmt == "obj":
        data = trimesh.exchange.obj.export_obj(tm, include_color=True, include_normals=True,
                                               include_texture=False).encode("utf-8")
    elif fmt == "glb":
        data = trimesh.exchange.gltf.export_glb(trimesh.Scene(tm))
    else:
        raise InputError(path, f"not a mesh format: {fmt}")
    path.write_bytes(data)
    open_edges = len(boundary_edges(mesh.triangles))
    shape = "watertight" if open_edges == 0 and non_manifold_edges(mesh.triangles) == 0 else (
        f"{open_edges} open edges" if open_edges else "closed, with edges shared by more than two triangles")
    return 0, f"mesh of {len(mesh.vertices)} vertices / {len(mesh.triangles)} triangles, {shape}"
