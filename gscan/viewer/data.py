"""A template loaded for the viewer (numpy only, no viser): views with downscaled snapshots, keypoints,
edges, mesh, cloud, grasps, each view's registration quality and the object's box.

View quality: `View.quality` when the database stores one (read as a score in [0, 1], 1 = best), else
derived from the view's accepted edges: 1 - median RMSE / `ViewerOptions.rmse_red_m` (0 without any).
"""
from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gscan.geometry.coverage import CoverageMap
from gscan.geometry.symmetry import Symmetries
from gscan.template.db import Edge, MeshData, TemplateDB, View
from gscan.viewer.draw import image_wh, outline_mask, thumbnail


@dataclass(frozen=True)
class ViewerOptions:
    thumb_px: int = 320            # longest side of the view / match images sent to the browser (JPEG)
    frustum_px: int = 160          # longest side of the snapshot shown on each frustum
    jpeg_quality: int = 80
    rmse_red_m: float = 0.01       # edge RMSE drawn fully red (and view quality 0)
    max_cloud_points: int = 200_000
    max_keypoints: int = 60_000
    scene_stride: int = 2          # pixel stride of the query frame's cloud
    max_match_lines: int = 150     # matched pairs drawn in the match panel


@dataclass
class ViewerData:
    """A template loaded for display (numpy only). thumbs[name]: downscaled RGB uint8 image; image_wh[name]:
    (width, height) of the stored image; keypoints[name] = (pixels [N x 2], points [N x 3])."""

    path: Path
    meta: dict
    views: list[View]  # images dropped (None) once downscaled into `thumbs`
    thumbs: dict[str, np.ndarray]
    image_wh: dict[str, tuple[int, int]]
    keypoints: dict[str, tuple[np.ndarray, np.ndarray]]
    edges: list[Edge]
    mesh: MeshData | None
    cloud: tuple[np.ndarray, np.ndarray | None] | None
    grasps: dict[str, np.ndarray]
    quality: dict[str, float | None] = field(default_factory=dict)
    center: np.ndarray = field(default_factory=lambda: np.zeros(3))
    size: float = 0.1  # largest side of the object's bounding box (m)
    coverage: CoverageMap | None = None  # which viewing directions the template saw (None: not recorded)
    symmetries: Symmetries = field(default_factory=Symmetries)  # the object's (none when not found)

    @property
    def registered(self) -> list[View]:
        return [v for v in self.views if v.T_obj_cam is not None]


def load_viewer_data(db_path: str | Path, options: ViewerOptions = ViewerOptions()) -> ViewerData:
    """Read a complete template database (InputError for a partial, missing or foreign one)."""
    with TemplateDB.open(db_path, require_complete=True) as db:
        meta, edges = db.meta(), db.edges()
        mesh, cloud, grasps = db.mesh(), db.cloud(), db.grasps()
        coverage, symmetries = db.coverage(), db.symmetries()
        names = db.view_names()
        # Image decoding (OpenCV releases the GIL) dominates opening a large template: one view per task.
        with ThreadPoolExecutor(max_workers=min(4, os.cpu_count() or 1)) as pool:
            views = list(pool.map(lambda n: db.view(n, load_images=True), names))
        feats = {v.name: db.features(v.name) for v in views}
    thumbs, sizes, kps = {}, {}, {}
    for v in views:
        img = v.color if v.color is not None else np.full((v.intrinsics.height, v.intrinsics.width, 3), 90, np.uint8)
        thumbs[v.name], sizes[v.name] = thumbnail(img, options.thumb_px), image_wh(img)
        if v.keyframe and v.mask is not None and v.mask.any():  # the object segmentation chose
            thumbs[v.name] = outline_mask(thumbs[v.name], v.mask)
        v.color = v.depth = v.mask = None  # only the thumbnail is shown: free the memory
        f = feats[v.name]
        kps[v.name] = ((np.zeros((0, 2), np.float32), np.zeros((0, 3), np.float32)) if f is None
                       else (np.asarray(f.pixels, np.float32), np.asarray(f.points, np.float32)))
    data = ViewerData(Path(db_path), meta, views, thumbs, sizes, kps, edges, mesh, cloud, grasps,
                      symmetries=symmetries)
    data.coverage = coverage
    data.quality = _view_quality(views, edges, options.rmse_red_m)
    data.center, data.size = _object_box(data)
    return data


def _view_quality(views: list[View], edges: list[Edge], rmse_red_m: float) -> dict[str, float | None]:
    rm: dict[str, list[float]] = {v.name: [] for v in views}
    for e in edges:
        if e.accepted and e.rmse is not None and np.isfinite(e.rmse):
            for n in (e.src, e.tgt):
                rm.setdefault(n, []).append(float(e.rmse))
    out: dict[str, float | None] = {}
    for v in views:
        if v.T_obj_cam is None:
            out[v.name] = None
        elif v.quality is not None and np.isfinite(v.quality):
            out[v.name] = float(np.clip(v.quality, 0.0, 1.0))
        else:
            out[v.name] = float(np.clip(1.0 - np.median(rm[v.name]) / rmse_red_m, 0, 1)) if rm[v.name] else 0.0
    return out


def _object_box(d: ViewerData) -> tuple[np.ndarray, float]:
    """Centre [3] and largest side (m) of the mesh, else cloud, else registered keypoints, else cameras."""
    cands = [None if d.mesh is None else d.mesh.vertices, None if d.cloud is None else d.cloud[0]]
    reg = d.registered
    kp = [d.keypoints[v.name][1] for v in reg if len(d.keypoints[v.name][1])]
    cands.append(np.concatenate(kp) if kp else None)
    cands.append(np.array([v.T_obj_cam[:3, 3] for v in reg if v.T_obj_cam is not None]) if len(reg) >= 2 else None)
    for pts in cands:
        if pts is not None and len(pts):
            pts = np.asarray(pts, dtype=np.float64)
            lo, hi = np.percentile(pts, 1, axis=0), np.percentile(pts, 99, axis=0)
            size = float(np.max(hi - lo))
            if size > 1e-6:
                return (lo + hi) / 2, size
    return np.zeros(3), 0.1
