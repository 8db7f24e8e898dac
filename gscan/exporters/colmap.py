"""COLMAP sparse model export through pycolmap (4.x: cameras, trivial rigs and frames, images, points),
with the views' colour images in images/ (PNG, named as the model's images); a registered view without a
stored colour image is left out (named in a warning).

World frame = the template's object frame, so each image's `cam_from_world` is inv(T_obj_cam).
Cameras are PINHOLE, one per distinct intrinsics. COLMAP puts the centre of the top-left pixel at
(0.5, 0.5) while gscan puts it at (0, 0): principal points and keypoints are shifted by +0.5.

3D points come from the stored template keypoints (object-frame points). Keypoints linked by the
matches of accepted edges are grouped into one track (union-find); a track keeps at most one
keypoint per image (the first) and its position is the mean of its members' points, refined on its
reprojection errors. Only tracks of at least MIN_TRACK_LENGTH images become 3D points: a keypoint in no
accepted match, or split off its track, is seen in one image only (it has no reprojection error to speak of,
and COLMAP's own filters delete such points); its keypoint stays in its image, unlinked. Each point's `error`
is the mean reprojection error of its track in pixels (COLMAP's own definition, which its model statistics
average).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap

from gscan.exporters.common import imwrite, posed_views, safe_file_names
from gscan.geometry.transforms import inv_T
from gscan.template.db import TemplateDB

log = logging.getLogger(__name__)

# An observation farther off its track's point is split off into a point of its own. The views' poses are the
# registration's, fixed, so a track is kept only where it agrees with them to a pixel (COLMAP, which refines its
# poses by bundle adjustment, filters at 4 px)
MAX_REPROJ_PX = 1.0
MAX_SPLIT_ROUNDS = 10
PRIOR_PX_PER_M = 100.0  # the pull towards the depth-lifted position: 1 px per cm
REFINE_ITERATIONS = 8
MIN_TRACK_LENGTH = 2  # images that see a 3D point: one alone neither places it nor measures its error


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
        assert v.T_obj_cam is not None and v.color is not None  # posed_views
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
    pts_all = (np.concatenate([f.points for f in feats if f is not None and len(f.pixels)]).astype(np.float64)
               if n else np.zeros((0, 3)))
    px_all = (np.concatenate([f.pixels for f in feats if f is not None and len(f.pixels)]).astype(np.float64)
              if n else np.zeros((0, 2)))
    col_all = np.concatenate([c for c in colors if len(c)]) if n else np.zeros((0, 3), np.uint8)
    order = np.argsort(roots, kind="stable")
    starts = np.flatnonzero(np.r_[True, roots[order][1:] != roots[order][:-1]]) if n else np.zeros(0, int)
    tracks = []
    for s, e in zip(starts, np.r_[starts[1:], n], strict=True):
        members, seen = [], set()
        for g in order[s:e]:
            if view_of[g] not in seen:  # one observation per image
                seen.add(view_of[g])
                members.append(int(g))
        tracks.append(members)
    cams = _Cameras.of(views)
    tracks, xyz_all = _triangulate(tracks, pts_all, px_all, view_of, cams)
    kept = [p for p, t in enumerate(tracks) if len(t) >= MIN_TRACK_LENGTH]
    log.debug("COLMAP model: %d of %d tracks seen in >= %d images kept", len(kept), len(tracks), MIN_TRACK_LENGTH)
    for p in kept:
        members, xyz = tracks[p], xyz_all[p]
        track = pycolmap.Track()
        for g in members:
            track.add_element(int(view_of[g]) + 1, g - offsets[view_of[g]])
        rgb = np.rint(col_all[members].astype(np.float64).mean(axis=0)).astype(np.uint8)
        rec.add_point3D(xyz, track, rgb)
    rec.update_point_3d_errors()  # each point's error: the mean reprojection error over its track (px)
    return rec


@dataclass
class _Cameras:
    """Per view: R [V x 3 x 3] and t [V x 3] of T_cam_obj, focal lengths f [V x 2], principal points c [V x 2]
    (gscan's pixel convention, as the keypoints')."""

    R: np.ndarray
    t: np.ndarray
    f: np.ndarray
    c: np.ndarray

    @staticmethod
    def of(views: list) -> _Cameras:
        T = np.array([inv_T(v.T_obj_cam) for v in views]).reshape(-1, 4, 4)
        return _Cameras(T[:, :3, :3], T[:, :3, 3], np.array([[v.intrinsics.fx, v.intrinsics.fy] for v in views]),
                        np.array([[v.intrinsics.cx, v.intrinsics.cy] for v in views]))

    def residuals(self, X: np.ndarray, view: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Reprojection residuals [O x 2] (px) of points X [O x 3] seen at uv [O x 2] in views `view` [O], and
        their Jacobians [O x 2 x 3] with respect to X."""
        R = self.R[view]
        Xc = np.einsum("oij,oj->oi", R, X) + self.t[view]
        z = np.maximum(Xc[:, 2], 1e-9)
        f = self.f[view]
        r = f * Xc[:, :2] / z[:, None] + self.c[view] - uv
        Jc = np.zeros((len(X), 2, 3))
        Jc[:, 0, 0], Jc[:, 1, 1] = f[:, 0] / z, f[:, 1] / z
        Jc[:, :, 2] = -f * Xc[:, :2] / (z ** 2)[:, None]
        return r, Jc @ R


def _refine(X0: np.ndarray, obs_point: np.ndarray, obs_view: np.ndarray, uv: np.ndarray,
            cams: _Cameras) -> np.ndarray:
    """Points [P x 3] that minimise their observations' squared reprojection errors (Gauss-Newton from X0, the
    depth-lifted positions, with a weak pull towards them: PRIOR_PX_PER_M px of error per metre of shift, so a
    point seen from nearly the same direction twice stays at its measured depth)."""
    X = X0.copy()
    eye = np.eye(3) * PRIOR_PX_PER_M ** 2
    for _ in range(REFINE_ITERATIONS):
        r, J = cams.residuals(X[obs_point], obs_view, uv)
        H = np.zeros((len(X), 3, 3))
        g = np.zeros((len(X), 3))
        np.add.at(H, obs_point, np.einsum("oki,okj->oij", J, J))
        np.add.at(g, obs_point, np.einsum("oki,ok->oi", J, r))
        H += eye
        g += PRIOR_PX_PER_M ** 2 * (X - X0)
        X = X - np.linalg.solve(H, g[..., None])[..., 0]
    return X


def _triangulate(tracks: list[list[int]], pts: np.ndarray, px: np.ndarray, view_of: np.ndarray,
                 cams: _Cameras) -> tuple[list[list[int]], np.ndarray]:
    """Positions of the tracks (lists of keypoint ids), refined on their reprojection errors (`_refine`); an
    observation more than MAX_REPROJ_PX off its track's point is split off into a point of its own (the worst
    of each track first, then the track is refined again), as COLMAP's own triangulation filters them.
    PRIOR_PX_PER_M pulls each point towards its keypoints' depth-lifted mean.
    Returns the tracks and their points [P x 3]; a single keypoint's point is its depth-lifted position."""
    tracks = [list(t) for t in tracks]
    for _ in range(MAX_SPLIT_ROUNDS):
        multi = [k for k, t in enumerate(tracks) if len(t) > 1]
        if not multi:
            break
        obs = np.concatenate([tracks[k] for k in multi])
        obs_point = np.repeat(np.arange(len(multi)), [len(tracks[k]) for k in multi])
        X0 = np.array([pts[tracks[k]].mean(0) for k in multi])
        X = _refine(X0, obs_point, view_of[obs], px[obs], cams)
        err = np.linalg.norm(cams.residuals(X[obs_point], view_of[obs], px[obs])[0], axis=1)
        worst = np.full(len(multi), -1.0)
        np.maximum.at(worst, obs_point, err)
        bad = np.flatnonzero(worst > MAX_REPROJ_PX)
        if len(bad) == 0:
            break
        for b in bad:
            members = tracks[multi[b]]
            e = err[obs_point == b]
            g = members.pop(int(np.argmax(e)))
            tracks.append([g])
    out = np.array([pts[t[0]] for t in tracks]).reshape(-1, 3)
    multi = [k for k, t in enumerate(tracks) if len(t) > 1]
    if multi:
        obs = np.concatenate([tracks[k] for k in multi])
        obs_point = np.repeat(np.arange(len(multi)), [len(tracks[k]) for k in multi])
        out[multi] = _refine(np.array([pts[tracks[k]].mean(0) for k in multi]), obs_point, view_of[obs], px[obs],
                             cams)
    return tracks, out


def _keypoint_colors(color: np.ndarray, f) -> np.ndarray:
    """[N x 3] uint8 colour under each keypoint of view features `f` in its colour image."""
    if f is None or len(f.pixels) == 0:
        return np.zeros((0, 3), np.uint8)
    h, w = color.shape[:2]
    u = np.clip(np.rint(f.pixels[:, 0]).astype(int), 0, w - 1)
    v = np.clip(np.rint(f.pixels[:, 1]).astype(int), 0, h - 1)
    return color[v, u]


def write_colmap(db: TemplateDB, out: Path) -> tuple[int, str]:
    """Write the binary COLMAP model (cameras/images/points3D/rigs/frames .bin) into `out` and the views'
    colour images into `out`/images (COLMAP's image_path). Returns (images, what the model holds: its points,
    mean track length and mean reprojection error as pycolmap computes them)."""
    (out / "images").mkdir()
    rec = build_reconstruction(db, out / "images")
    rec.write(str(out))
    n_points = rec.num_points3D()
    track = rec.compute_mean_track_length() if n_points else 0.0
    error = rec.compute_mean_reprojection_error() if n_points else 0.0
    log.info("COLMAP model: %d images, %d points, mean track length %.2f, mean reprojection error %.3f px",
             rec.num_images(), n_points, track, error)
    return rec.num_images(), (f"a COLMAP model of {rec.num_images()} images, {n_points} points seen in >= "
                              f"{MIN_TRACK_LENGTH} images (mean track length {track:.2f}), mean reprojection error "
                              f"{error:.4f} px")
