"""COLMAP sparse model export through pycolmap (4.x: cameras, trivial rigs and frames, images, points),
with the views' colour images in images/ (PNG, named as the model's images); a registered view without a
stored colour image is left out (named in a warning).

World frame = the template's object frame, so each image's `cam_from_world` is inv(T_obj_cam).
Cameras are PINHOLE, one per distinct intrinsics. COLMAP puts the centre of the top-left pixel at
(0.5, 0.5) while gscan puts it at (0, 0): principal points and keypoints are shifted by +0.5.

3D points come from the stored template keypoints (object-frame points). Keypoints linked by the
matches of accepted edges are grouped into one track (union-find); a track keeps at most one
keypoint per image (the first) and its position is the mean of its members' points. Keypoints in
no accepted match become single-observation points.
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pycolmap

from gscan.export.common import imwrite, posed_views, safe_file_names
from gscan.geometry.transforms import inv_T
from gscan.template.db import TemplateDB

log = logging.getLogger(__name__)


class _UnionFind:
    def __init__(self, n: int):
        self.parent = np.arange(n, dtype=np.int64)

    def find(self, i: int) -> int:
        root = i
        while self.parent[root] != root:
            root = int(self.parent[root])
        while self.parent[i] != root:  # path compression
            self.parent[i], i = root, int(self.parent[i])
        return root

    def union(self, a: int, b: int) -> None:
        ra, rb = self.find(a), self.find(b)
        if ra != rb:
            self.parent[max(ra, rb)] = min(ra, rb)  # smallest index is the root: deterministic


def build_reconstruction(db: TemplateDB, images_dir: Path) -> pycolmap.Reconstruction:
    """The template as a pycolmap Reconstruction: the registered views that store a colour image, each written
    to `images_dir` as `<view name>.png` (the name made safe, `safe_file_names`), the name the model's image
    takes (COLMAP's image_path)."""
    views = posed_views(db, need_images=True, need_depth=False)
    file_names = [f"{stem}.png" for stem in safe_file_names([v.name for v in views])]  # names are data
    rec = pycolmap.Reconstruction()
    cam_ids: dict = {}
    feats, offsets, colors = [], [0], []
    for img_id, v in enumerate(views, start=1):
        k = v.intrinsics
        if k not in cam_ids:
            cam_ids[k] = len(cam_ids) + 1
            rec.add_camera_with_trivial_rig(pycolmap.Camera(
                camera_id=cam_ids[k], model="PINHOLE", width=k.width, height=k.height,
                params=[k.fx, k.fy, k.cx + 0.5, k.cy + 0.5]))
        f = db.features(v.name)
        px = np.zeros((0, 2)) if f is None else f.pixels.astype(np.float64) + 0.5
        feats.append(f)
        offsets.append(offsets[-1] + len(px))
        name = file_names[img_id - 1]
        imwrite(images_dir / name, v.color, rgb=True)
        image = pycolmap.Image(name=name, keypoints=px, camera_id=cam_ids[k], image_id=img_id)
        T_cam_obj = inv_T(v.T_obj_cam)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(T_cam_obj[:3, :4]))
        colors.append(_keypoint_colors(v.color, f))
    n = offsets[-1]
    index = {v.name: i for i, v in enumerate(views)}
    uf = _UnionFind(n)
    for e in db.edges(accepted_only=True):
        if e.src not in index or e.tgt not in index or len(e.matches) == 0:
            continue
        i, j = index[e.src], index[e.tgt]
        ns, nt = offsets[i + 1] - offsets[i], offsets[j + 1] - offsets[j]
        m = e.matches
        ok = (m[:, 0] >= 0) & (m[:, 0] < ns) & (m[:, 1] >= 0) & (m[:, 1] < nt)
        if not ok.all():
            log.warning("edge %s -> %s: %d matches index missing keypoints, ignored", e.src, e.tgt, int((~ok).sum()))
        for a, b in m[ok]:
            uf.union(offsets[i] + int(a), offsets[j] + int(b))
    view_of = np.repeat(np.arange(len(views)), np.diff(offsets))
    roots = np.array([uf.find(g) for g in range(n)], dtype=np.int64)
    pts_all = (np.concatenate([f.points for f in feats if f is not None and len(f.pixels)]) if n
               else np.zeros((0, 3)))
    col_all = np.concatenate([c for c in colors if len(c)]) if n else np.zeros((0, 3), np.uint8)
    order = np.argsort(roots, kind="stable")
    starts = np.flatnonzero(np.r_[True, roots[order][1:] != roots[order][:-1]]) if n else np.zeros(0, int)
    for s, e in zip(starts, np.r_[starts[1:], n]):
        members, seen = [], set()
        for g in order[s:e]:
            if view_of[g] not in seen:  # one observation per image
                seen.add(view_of[g])
                members.append(int(g))
        track = pycolmap.Track()
        for g in members:
            track.add_element(int(view_of[g]) + 1, g - offsets[view_of[g]])
        xyz = pts_all[members].astype(np.float64).mean(axis=0)
        rgb = np.rint(col_all[members].astype(np.float64).mean(axis=0)).astype(np.uint8)
        rec.add_point3D(xyz, track, rgb)
    return rec


def _keypoint_colors(color: np.ndarray, f) -> np.ndarray:
    """[N x 3] uint8 colour under each keypoint of view features `f` in its colour image."""
    if f is None or len(f.pixels) == 0:
        return np.zeros((0, 3), np.uint8)
    h, w = color.shape[:2]
    u = np.clip(np.rint(f.pixels[:, 0]).astype(int), 0, w - 1)
    v = np.clip(np.rint(f.pixels[:, 1]).astype(int), 0, h - 1)
    return color[v, u]


def write_colmap(db: TemplateDB, out: Path) -> int:
    """Write the binary COLMAP model (cameras/images/points3D/rigs/frames .bin) into `out` and the views'
    colour images into `out`/images (COLMAP's image_path)."""
    (out / "images").mkdir()
    rec = build_reconstruction(db, out / "images")
    rec.write(str(out))
    log.info("COLMAP model: %d images, %d points, mean track length %.2f", rec.num_images(), rec.num_points3D(),
             rec.compute_mean_track_length() if rec.num_points3D() else 0.0)
    return rec.num_images()
