"""Helpers shared by the exporters: view selection, image writing, mesh rendering."""
from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np

from gscan.errors import GscanError, InputError
from gscan.geometry.raycast import MeshRaycaster as RaycasterBase
from gscan.io.camera import Intrinsics
from gscan.template.db import MeshData, TemplateDB, View

log = logging.getLogger(__name__)


def posed_views(db: TemplateDB, need_images: bool = True, need_depth: bool = True) -> list[View]:
    """Registered views in input order; with `need_images` their images decoded and only the views that store
    colour (and depth, with `need_depth`). InputError naming the database when none is left; otherwise the
    views left out are named in one warning."""
    out, missing = [], []
    for v in db.views(load_images=False):
        if v.T_obj_cam is None:
            continue
        if need_images:
            v = db.view(v.name, load_images=True)
            if v.color is None or (need_depth and v.depth is None):
                missing.append(v.name)
                continue
        out.append(v)
    what = "colour and depth images" if need_depth else "colour image"
    if not out:
        with_images = " with colour and depth images" if need_depth else " with a colour image"
        raise InputError(db.path, f"no registered view{with_images if need_images else ''} to export")
    if missing:
        log.warning("%d view(s) store no %s and are not exported: %s", len(missing), what, ", ".join(missing))
    return out


def template_mesh(db: TemplateDB, close: bool = True) -> MeshData | None:
    """The template's mesh for an export, closed into a watertight model with `close`
    (`gscan.export.watertight`); None when the template has no mesh with triangles."""
    m = db.mesh()
    if m is None or len(m.vertices) == 0 or len(m.triangles) == 0:
        return None
    if close:
        from gscan.export.watertight import closed_mesh

        m = closed_mesh(db, m)
    return m


def require_mesh(db: TemplateDB, close: bool = True) -> MeshData:
    """`template_mesh`, or InputError naming the database when it has no mesh."""
    m = template_mesh(db, close)
    if m is None:
        raise InputError(db.path, "the template has no mesh to export")
    return m


def imwrite(path: Path, img: np.ndarray, rgb: bool = False) -> None:
    """Write a PNG (`rgb`: [H x W x 3] RGB uint8 -> stored as a normal colour PNG)."""
    data = cv2.cvtColor(img, cv2.COLOR_RGB2BGR) if rgb else img
    ok, buf = cv2.imencode(path.suffix, data)
    if not ok:
        raise GscanError(f"cannot encode {path}")
    path.write_bytes(buf.tobytes())


class MeshRaycaster(RaycasterBase):
    """Ray-casts the template mesh from many cameras (`gscan.geometry.raycast.MeshRaycaster`)."""

    def __init__(self, mesh: MeshData):
        super().__init__(mesh.vertices, mesh.triangles)


def render_depth(mesh: MeshData, intr: Intrinsics, T_obj_cam: np.ndarray) -> np.ndarray:
    """One-off ray-cast of the mesh: [H x W] float32 depth (m), 0 = no hit (see MeshRaycaster)."""
    return MeshRaycaster(mesh).depth(intr, T_obj_cam)


def bbox_xywh(mask: np.ndarray) -> list[int]:
    """BOP bounding box [x, y, width, height] of a [H x W] bool mask; [-1, -1, -1, -1] if empty.

    As the BOP toolkit's `calc_2d_bbox`: width and height are max - min of the pixel coordinates (a
    one-pixel mask has width 0)."""
    ys, xs = np.nonzero(mask)
    if len(xs) == 0:
        return [-1, -1, -1, -1]
    x0, y0 = int(xs.min()), int(ys.min())
    return [x0, y0, int(xs.max()) - x0, int(ys.max()) - y0]
