"""Evidence for and against a pose hypothesis, and the rule that accepts it.

A pose is accepted from what the frame shows, not from a fixed match count:

- depth: the template's surface visible at the pose is projected into the query depth. `score` = consistent /
  (consistent + see-through) points, `confirmed` = consistent / visible ("see-through": the measured surface
  lies behind the predicted object; a point over a pixel without depth, or occluded, counts for neither).
- keypoint support (appearance): of the query keypoints lying on the predicted surface, how many find their
  nearest template keypoint by descriptor within a few millimetres at the pose. The template keypoints
  considered are those of the views that saw the object from about the query's direction ("what the
  template can offer in that view"). A pose fitted to a look-alike shape (a box of the same size with
  another print, the table) has its surface confirmed by the depth but finds no appearance support.
- the list's geometry: the matched template points must span an area (not a line or a cluster), and the
  pose must keep enough of the list within the Kabsch tolerance.
- rivals: two accepted poses of one frame are told apart by the query keypoints that support one and not the
  other (`sign_test`); a box printed alike on two faces leaves few such keypoints, all on what differs.
- support plane: a pose that sinks the object into the frame's dominant plane is refused (an object rests on
  the table; such a pose fits the object's print to the table's texture), unless most of the plane lies
  inside the pose's silhouette (then the plane is the object's own face).
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import numpy as np

from gscan.estimate.params import AcceptParams, VerifyParams
from gscan.estimate.query import QueryFrame, off_plane_margin
from gscan.estimate.similarity import best_columns
from gscan.geometry.plane import Plane
from gscan.geometry.transforms import transform_points
from gscan.io.camera import Intrinsics, project
from gscan.registration.noise import DepthNoise


@dataclass
class Evidence:
    """What a pose hypothesis rests on (see the module docstring). n_matches: the match list's length;
    n_inliers: pairs within the Kabsch tolerance; spread_m: square root of the second principal variance of
    the inliers' template points (m, 0 for a line); score, confirmed: depth agreement; supporters: the distinct
    query keypoint locations on the predicted surface with an agreeing template keypoint (ids, sorted), support
    their number; on_surface: distinct query keypoint locations on the predicted surface; offer: distinct
    template keypoint locations the views near the query direction show at the pose, inside the image and not
    hidden by the measured depth."""

    n_matches: int = 0
    n_inliers: int = 0
    spread_m: float = 0.0
    score: float = 0.0
    confirmed: float = 0.0
    on_surface: int = 0
    offer: int = 0
    supporters: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64), repr=False)
    depth_only: bool = False  # the depth decided: no image keypoints could judge the pose (`decided_by_depth`)

    @property
    def support(self) -> int:
        return len(self.supporters)

    @property
    def support_ratio(self) -> float:
        """support over what the frame and the template can both show there (0 when nothing)."""
        return self.support / max(1, min(self.on_surface, self.offer))

    def to_json(self) -> dict:
        return {"n_matches": self.n_matches, "n_inliers": self.n_inliers, "spread_m": round(self.spread_m, 5),
                "score": round(self.score, 4), "confirmed": round(self.confirmed, 4), "support": self.support,
                "on_surface": self.on_surface, "offer": self.offer, "support_ratio": round(self.support_ratio, 4),
                "depth_only": self.depth_only}


def accept(ev: Evidence, radius: float, p: AcceptParams, best: bool = True) -> str | None:
    """None when the evidence is enough for the pose, else the reason it is not (one line). best: the pose is
    the frame's best-supported hypothesis; a long list's relaxed support rule applies to it only (a runner-up
    whose better-supported rival was refused must pass the short lists' rule: a box turned onto its twin face
    keeps a long list and some support)."""
    why = depth_refusal(ev, p) or list_refusal(ev, radius, p, best)
    if why is not None:
        return why
    shown = min(ev.on_surface, ev.offer)
    if strong_rule(ev, p, best):
        if ev.support_ratio >= p.strong_min_ratio:
            return None
        return f"the object's appearance does not agree ({ev.support} of {shown} keypoints on its surface match)"
    if ev.support >= p.min_support and ev.support_ratio >= p.min_support_ratio:
        return None
    return (f"too little evidence: {ev.support} of {shown} keypoints on the object's surface agree with the template "
            f"(need {p.min_support} and {p.min_support_ratio:.0%}), {ev.n_inliers} consistent matches (or a list of "
            f"{p.strong_matches})")


def decided_by_depth(ev: Evidence, location_depth: np.ndarray, inliers: np.ndarray, p: AcceptParams) -> bool:
    """Whether the depth alone decided the pose of a template with depth keypoints: its image keypoints would not
    carry it (fewer than `min_support` of its supporters are image keypoints: a plain object's print cannot
    judge the pose), or most of its list's inliers are depth keypoints. location_depth [G] bool: which query
    keypoint locations are depth keypoints; inliers [I]: the inliers' location ids, each once (a keypoint of
    several orientations is one location, as the supporters are)."""
    image = int(np.count_nonzero(~location_depth[ev.supporters])) if len(ev.supporters) else 0
    return image < p.min_support or 2 * int(np.count_nonzero(location_depth[inliers])) > len(inliers)


def silhouette_refusal(q: QueryFrame, T_cam_obj: np.ndarray, samples: np.ndarray, spacing: float,
                       noise: DepthNoise, p: AcceptParams) -> str | None:
    """The reason the silhouettes refute a pose the depth alone decided (`decided_by_depth`), else None: more than
    `max_outside_shape` of either side lies off the other's (`silhouette_outside`)."""
    tpl, query = silhouette_outside(q, T_cam_obj, samples, spacing, noise)
    if max(tpl, query) > p.max_outside_shape:
        return (f"silhouette disagrees ({tpl:.1%} of the surface the pose shows lands off the objects in the frame, "
                f"{query:.1%} of the object it lies on outside the pose's outline; no texture can judge the pose, so "
                f"at most {p.max_outside_shape:.1%})")
    return None


def border_refusal(intr: Intrinsics, T_cam_obj: np.ndarray, samples: np.ndarray, p: AcceptParams) -> str | None:
    """The reason a pose the depth alone decided cannot be told from a look-alike's, else None: more than
    `max_outside_shape` of the object's silhouette lies beyond the image's border (`beyond_border`), where no
    silhouette check bounds it (the checks that refute are asked first: their reason is the better one)."""
    cut = beyond_border(T_cam_obj, intr, samples)
    if cut > p.max_outside_shape:
        return (f"the object at this pose reaches beyond the image's border ({cut:.0%} of its silhouette), where its "
                f"outline cannot be checked; no texture can judge the pose, so at most {p.max_outside_shape:.1%}")
    return None


def beyond_border(T_cam_obj: np.ndarray, intr: Intrinsics, samples: np.ndarray) -> float:
    """The share of the object's samples [S x 3] (object frame; all of them: the silhouette is every point's
    projection) that fall outside the image, or behind the camera, at T_cam_obj. A pose the depth alone decided
    rests on the silhouette checks for the object's extent; a look-alike cut by the border fits any object whose
    surface in view is like its own (measured: poses on boxes at the border, 25-42 % beyond it)."""
    pc = transform_points(T_cam_obj, samples)
    if not len(pc):
        return 0.0
    uv = project(pc[pc[:, 2] > 1e-3], intr)
    inside = (uv >= 0).all(axis=1) & (uv[:, 0] < intr.width) & (uv[:, 1] < intr.height)
    return 1.0 - int(inside.sum()) / len(pc)


def silhouette_outside(q: QueryFrame, T_cam_obj: np.ndarray, samples: np.ndarray, spacing: float,
                       noise: DepthNoise) -> tuple[float, float]:
    """(template, query): how much of each side lies off the other's silhouette under the pose (registration's
    silhouette test, both directions, with a margin of two template samples: `spacing` m, projected at the pose's
    median depth).

    template: the share of the template surface samples [S x 3] visible at T_cam_obj and standing off the support
    plane by the search region's margin (`off_plane_margin`; all without a plane) that land farther than the
    margin from the search region (the mask, else the pixels off the plane): an object lies on something the
    frame shows standing there. query: the share of the query's object under the pose that lies farther than the
    margin outside the pose's outline (its visible samples' pixels, closed over the sample spacing): the object is
    the part of the search region, split at the depth's jumps (3 sigmas of `noise`), holding most of the pose's
    depth-confirmed samples. A pose laid on a larger object leaves the rest of it outside; a right pose leaves only
    what touches the object at its depth (then the pose is refused: a refusal, never a wrong pose). (0, 0) without
    a search region."""
    from gscan.scanning.depth_edges import depth_jumps

    region, frame = q.search, q.frame
    if region is None:
        return 0.0, 0.0
    intr = frame.intrinsics
    _, pc, uv = visible(T_cam_obj, intr, samples)
    if len(pc) == 0:
        return 0.0, 0.0
    r = int(np.ceil(2.0 * spacing * intr.fx / float(np.median(pc[:, 2]))))
    grow = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
    keep = q.plane.height(pc) > off_plane_margin(pc[:, 2]) if q.plane is not None else np.ones(len(pc), bool)
    near_region = cv2.dilate(region.astype(np.uint8), grow).astype(bool)
    tpl = float(np.mean(~near_region[uv[keep, 1], uv[keep, 0]])) if keep.any() else 0.0
    dots = np.zeros(region.shape, np.uint8)
    dots[uv[:, 1], uv[:, 0]] = 1
    outline = cv2.morphologyEx(dots, cv2.MORPH_CLOSE, grow)
    zq = frame.depth[uv[:, 1], uv[:, 0]].astype(np.float64)
    confirmed = (zq > 0) & (np.abs(zq - pc[:, 2]) < 3.0 * noise.pair_sigma(pc[:, 2], np.where(zq > 0, zq, 1.0)))
    parts = region & ~depth_jumps(frame.depth, 3.0, noise)
    _, label = cv2.connectedComponents(parts.astype(np.uint8), connectivity=4)
    held = label[uv[confirmed, 1], uv[confirmed, 0]]
    held = held[held > 0]
    if len(held) == 0:
        return tpl, 0.0
    obj = label == np.bincount(held).argmax()
    off = obj & ~cv2.dilate(outline, grow).astype(bool)
    return tpl, float(off.sum()) / max(1, int(obj.sum()))


def depth_refusal(ev: Evidence, p: AcceptParams) -> str | None:
    """The reason `accept` refuses the pose on its depth agreement alone (ev's score and confirmed), else None."""
    if ev.score < p.min_score or ev.confirmed < p.min_confirmed:
        return (f"pose not confirmed by the depth (score {ev.score:.2f}, {ev.confirmed:.0%} of visible surface "
                f"confirmed)")
    return None


def strong_rule(ev: Evidence, p: AcceptParams, best: bool) -> bool:
    """The pose takes the long list's relaxed support rule (`accept`): the frame's best-supported list, with
    `strong_matches` pairs in its longest list and as many inliers."""
    return best and ev.n_matches >= p.strong_matches and ev.n_inliers >= p.strong_matches


def list_refusal(ev: Evidence, radius: float, p: AcceptParams, best: bool = True) -> str | None:
    """The reason `accept` refuses the pose whatever the depth and the keypoints say, read from its list alone
    (ev's n_matches, n_inliers and spread_m, known once the list is solved, before it is refined): too few
    inliers, or, off the long list's rule, inliers on a line (spread under `min_spread` of the object `radius`,
    m); None when the list leaves the decision to the evidence."""
    if ev.n_inliers < p.min_matches:
        return f"too few geometrically consistent matches ({ev.n_inliers} < {p.min_matches} after trimming)"
    if not strong_rule(ev, p, best) and ev.spread_m < p.min_spread * radius:
        return f"the {ev.n_inliers} matches lie on a line ({ev.spread_m * 1000:.1f} mm across)"
    return None


def list_spread(points: np.ndarray) -> float:
    """Square root of the second-largest principal variance of [N x 3] points (m); 0 for fewer than 3."""
    if len(points) < 3:
        return 0.0
    c = np.asarray(points, dtype=np.float64) - np.mean(points, axis=0)
    ev = np.linalg.eigvalsh(c.T @ c / len(c))
    return float(np.sqrt(max(ev[1], 0.0)))


def kabsch_batch(src: np.ndarray, dst: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Rigid poses of many match lists at once: src, dst [H x L x 3] (lists padded to L), w [H x L] 1 for a
    pair, 0 for padding -> T [H x 4 x 4] minimising each list's sum |T src - dst|^2 (no reflection)."""
    n = np.maximum(w.sum(1), 1.0)[:, None]
    mu_s = np.einsum("hl,hlk->hk", w, src) / n
    mu_d = np.einsum("hl,hlk->hk", w, dst) / n
    C = np.einsum("hl,hli,hlj->hij", w, dst - mu_d[:, None], src - mu_s[:, None])
    U, _, Vt = np.linalg.svd(C)
    d = np.sign(np.linalg.det(U) * np.linalg.det(Vt))
    U[:, :, 2] *= np.where(d == 0, 1.0, d)[:, None]
    R = U @ Vt
    T = np.zeros((len(src), 4, 4))
    T[:, :3, :3] = R
    T[:, :3, 3] = mu_d - np.einsum("hij,hj->hi", R, mu_s)
    T[:, 3, 3] = 1.0
    return T


def nn_support(T: np.ndarray, nn_points: np.ndarray, q_points: np.ndarray, radius: float) -> np.ndarray:
    """[H] number of query keypoints whose nearest template keypoint by descriptor (object-frame point
    nn_points [M x 3], NaN where the nearest does not agree) lies within `radius` of the keypoint q_points
    [M x 3] under each pose T [H x 4 x 4]: a cheap appearance check of many poses."""
    d = np.matmul(nn_points[None], T[:, :3, :3].transpose(0, 2, 1))  # [H x M x 3]
    d += T[:, None, :3, 3] - q_points[None]
    d *= d
    return np.count_nonzero(d.sum(axis=2) < radius * radius, axis=1)


def visible(T_cam_obj: np.ndarray, intr: Intrinsics, pts: np.ndarray, cell: int = 4,
            tol: float = 0.01) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points [P x 3] (object frame) visible from the camera at T_cam_obj, by a coarse z-buffer of `cell` px.
    Returns (indices [K], camera points [K x 3], integer pixels [K x 2])."""
    pc = transform_points(T_cam_obj, pts)
    z = pc[:, 2]
    ok = z > 1e-3
    zs = np.where(ok, z, 1.0)
    ui = np.rint(pc[:, 0] / zs * intr.fx + intr.cx)
    vi = np.rint(pc[:, 1] / zs * intr.fy + intr.cy)
    ok &= (ui >= 0) & (ui < intr.width) & (vi >= 0) & (vi < intr.height)
    idx = np.flatnonzero(ok)
    ui, vi = ui[idx].astype(np.int64), vi[idx].astype(np.int64)
    gw, gh = (intr.width + cell - 1) // cell, (intr.height + cell - 1) // cell
    cid = (vi // cell) * gw + ui // cell
    zbuf = np.full(gw * gh, np.inf)
    np.minimum.at(zbuf, cid, z[idx])
    vis = z[idx] <= zbuf[cid] + tol + 0.01 * z[idx]
    return idx[vis], pc[idx[vis]], np.stack([ui[vis], vi[vis]], 1)


def depth_tolerance(z: np.ndarray, depth_tol: float) -> np.ndarray:
    """Depth agreement tolerance (m) at depth z: depth_tol, growing 2 % of the depth beyond 0.5 m."""
    return depth_tol + 0.02 * np.maximum(z - 0.5, 0.0)


def depth_votes(depth: np.ndarray, intr: Intrinsics, T_cam_obj: np.ndarray, cloud: np.ndarray, depth_tol: float,
                region: np.ndarray | None = None,
                seen: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> tuple[int, int, int]:
    """(consistent, see-through, visible) counts of the template cloud's points [P x 3] visible at T_cam_obj:
    consistent when the query depth [H x W] agrees within the tolerance (and, with `region` [H x W] bool, the
    pixel lies in it), see-through when the query surface lies behind the predicted object (a point over a pixel
    without depth counts for neither). seen: `visible(T_cam_obj, intr, cloud)` when the caller has it."""
    _, pc, uv = visible(T_cam_obj, intr, cloud) if seen is None else seen
    if len(pc) == 0:
        return 0, 0, 0
    zq = depth[uv[:, 1], uv[:, 0]].astype(np.float64)
    z = pc[:, 2]
    tol = depth_tolerance(z, depth_tol)
    has = zq > 0
    consistent = has & (np.abs(zq - z) < tol)
    if region is not None:
        consistent &= region[uv[:, 1], uv[:, 0]]
    behind = has & (zq > z + tol)
    return int(consistent.sum()), int(behind.sum()), len(pc)


def depth_score(depth: np.ndarray, intr: Intrinsics, T_cam_obj: np.ndarray, cloud: np.ndarray, depth_tol: float,
                region: np.ndarray | None = None) -> tuple[float, float]:
    """(score, confirmed) of `depth_votes`: consistent / (consistent + see-through), consistent / visible."""
    n_c, n_b, n = depth_votes(depth, intr, T_cam_obj, cloud, depth_tol, region)
    return n_c / max(1, n_c + n_b), n_c / max(1, n)


def keypoint_support(T_cam_obj: np.ndarray, kp_points: np.ndarray, kp_idx: np.ndarray, sim: np.ndarray,
                     sim_cols: np.ndarray, q_points: np.ndarray, q_location: np.ndarray, surface_obj: np.ndarray,
                     depth: np.ndarray, intr: Intrinsics, radius: float, min_sim: float,
                     depth_tol: float, sign: float = 1.0, surface_cam: np.ndarray | None = None,
                     sim_rows: np.ndarray | None = None,
                     local: np.ndarray | None = None) -> tuple[np.ndarray, int, int]:
    """(supporters, on_surface, offer) of a pose (Evidence): the location ids [support] of the supporting query
    keypoints, sorted.

    A query keypoint on the predicted visible surface supports the pose when its nearest template keypoint by
    descriptor, among those the template offers there, lies within `radius` of it at the pose (and agrees
    within `min_sim`): a chance agreement needs the one nearest descriptor of hundreds to fall within a few
    millimetres.

    kp_points [N x 3]: object-frame points of every template keypoint; kp_idx [K]: those of the views near the
    query direction; sim [M' x C]: descriptor similarity of the M query keypoints to template keypoints (cosine
    of unit descriptors, or the distance with sign -1: the similarity is sign * sim), sim_cols [K] the column of
    each of kp_idx, sim_rows [M] the row of each query keypoint (None: row i is keypoint i); q_points [M x 3]:
    camera-frame query keypoints;
    q_location [M]: a location id per query keypoint (keypoints of one point with several orientations share
    it); surface_obj [P x 3]: the template cloud, surface_cam its points visible at the pose (camera frame,
    `visible`'s) when the caller has them; radius: keypoint match distance (m).

    local [M] bool: query keypoints judged by the local rule instead (depth keypoints: FPFH describes a corner
    or a rim, which every corner or rim of a box resembles, so the nearest descriptor among hundreds is rarely
    the keypoint's own): such a keypoint supports the pose when any offered template keypoint within `radius`
    of it at the pose agrees (the rule `ListVerifier.local_support` weighs rivals by)."""
    from scipy.spatial import cKDTree

    from gscan.geometry.grid_kernel import NearestGrid

    none = np.zeros(0, np.int64)
    if sim_rows is None and len(sim) != len(q_points):  # a subset of S's rows read without its row map
        raise ValueError(f"the similarity has {len(sim)} rows for {len(q_points)} query keypoints: pass sim_rows")
    if len(q_points) == 0:
        return none, 0, 0
    # query keypoints on the predicted visible surface
    surf_cam = visible(T_cam_obj, intr, surface_obj)[1] if surface_cam is None else surface_cam
    if len(surf_cam) == 0:
        return none, 0, 0
    grid = NearestGrid.build(surf_cam, radius)
    if grid is not None:
        on = np.flatnonzero(grid.query(q_points)[0])
    else:  # (an exact search: the unbalanced tree builds faster and finds the same distances)
        tree = cKDTree(surf_cam, balanced_tree=False, compact_nodes=False)
        d, _ = tree.query(np.asarray(q_points, dtype=np.float64), distance_upper_bound=radius)
        on = np.flatnonzero(np.isfinite(d))
    on_surface = len(np.unique(q_location[on]))
    # template keypoints the frame can show: inside the image, in front of (or at) the measured depth
    vis, kp_cam, uv = visible(T_cam_obj, intr, kp_points[kp_idx])
    zq = depth[uv[:, 1], uv[:, 0]].astype(np.float64)
    shown = (zq <= 0) | (kp_cam[:, 2] < zq + depth_tolerance(kp_cam[:, 2], depth_tol))
    sel, kp_cam = vis[shown], kp_cam[shown]
    if len(sel) == 0 or len(on) == 0:
        return none, on_surface, 0
    offer = count_unique_rows(np.floor(kp_points[kp_idx[sel]] / 0.002).astype(np.int64))
    # the best offered keypoint of each query keypoint on
    nn, best = best_columns(sim, on if sim_rows is None else sim_rows[on], sim_cols[sel], sign)
    agree = best >= min_sim
    near = np.linalg.norm(kp_cam[nn] - q_points[on], axis=1) < radius
    if local is not None:
        lo = local[on]
        near[lo] = _local_agreement(on[lo], kp_cam, sel, sim, sim_cols, sim_rows, q_points, radius, min_sim, sign)
        agree[lo] = True
    return np.unique(q_location[on[agree & near]]).astype(np.int64), on_surface, offer


def _local_agreement(rows: np.ndarray, kp_cam: np.ndarray, sel: np.ndarray, sim: np.ndarray, sim_cols: np.ndarray,
                     sim_rows: np.ndarray | None, q_points: np.ndarray, radius: float, min_sim: float,
                     sign: float) -> np.ndarray:
    """[R] whether each query keypoint `rows` has a template keypoint within `radius` (kp_cam [K x 3] the offered
    ones shown, camera frame; sel [K] their positions in sim_cols) whose descriptor agrees (`keypoint_support`'s
    local rule)."""
    r, cols = (rows if sim_rows is None else sim_rows[rows]), sim_cols[sel]
    return near_agreeing(q_points[rows], kp_cam, radius,
                         lambda some, j: sim[r[some][:, None], cols[j]] * sign >= min_sim)


def near_agreeing(q_pts: np.ndarray, kp_cam: np.ndarray, radius: float,
                  agrees: Callable[[np.ndarray, np.ndarray], np.ndarray]) -> np.ndarray:
    """[R] bool: whether each query point q_pts [R x 3] has, among its 16 nearest template keypoints kp_cam [K x 3]
    (camera frame) within `radius` (m), one whose descriptor agrees. agrees(some [R'], j [R' x k]) -> [R' x k] bool
    judges the query rows `some` that have a template keypoint near against kp_cam's rows j (any row where none is
    near: masked out), so that the similarities are read only there."""
    from scipy.spatial import cKDTree

    out = np.zeros(len(q_pts), bool)
    if len(q_pts) == 0 or len(kp_cam) == 0:
        return out
    k = min(16, len(kp_cam))
    d, j = cKDTree(kp_cam).query(np.asarray(q_pts, dtype=np.float64), k=k, distance_upper_bound=radius)
    d, j = d.reshape(len(q_pts), k), j.reshape(len(q_pts), k)
    near = np.isfinite(d)
    some = np.flatnonzero(near.any(axis=1))
    near = near[some]
    out[some] = (near & agrees(some, np.where(near, j[some], 0))).any(axis=1)
    return out


def count_unique_rows(keys: np.ndarray) -> int:
    """Number of distinct rows of integer keys [K x 3] (np.unique(keys, axis=0), counted through one integer
    code per row when the keys' ranges allow it, which is faster than sorting rows)."""
    if len(keys) == 0:
        return 0
    lo = keys.min(axis=0)
    span = keys.max(axis=0) - lo + 1
    if float(np.prod(span.astype(np.float64))) >= 2.0 ** 62:
        return len(np.unique(keys, axis=0))
    k = keys - lo
    return len(np.unique((k[:, 0] * span[1] + k[:, 1]) * span[2] + k[:, 2]))


def sinks_into_plane(T_cam_obj: np.ndarray, cloud: np.ndarray, plane: Plane, heights: np.ndarray, depth: np.ndarray,
                     intr: Intrinsics, below_tol: float, max_below_frac: float) -> float | None:
    """The fraction of the template cloud's points [P x 3] more than `below_tol` behind the support plane at
    T_cam_obj when above `max_below_frac` and most of the plane's pixels lie outside the pose's silhouette, else
    None. heights: [H x W] every pixel's height above the plane (the query's, computed once)."""
    below = float(np.mean(plane.height(transform_points(T_cam_obj, cloud)) < -below_tol))
    if below <= max_below_frac:
        return None
    _, _, uv = visible(T_cam_obj, intr, cloud)
    sil = np.zeros(depth.shape, np.uint8)
    if len(uv) >= 3:
        cv2.fillConvexPoly(sil, cv2.convexHull(uv.astype(np.int32)), 1)
    on_plane = (depth > 0) & (np.abs(heights) < 0.01)
    if (on_plane & (sil > 0)).sum() > 0.5 * on_plane.sum():
        return None
    return below


def pose_evidence(q: QueryFrame, T_cam_obj: np.ndarray, samples: np.ndarray, center: np.ndarray,
                  kp_points: np.ndarray, kp_idx: np.ndarray, sim: np.ndarray, sim_cols: np.ndarray,
                  q_points: np.ndarray, q_location: np.ndarray, params: VerifyParams, min_sim: float,
                  sign: float, sim_rows: np.ndarray | None = None, gate: AcceptParams | None = None,
                  local: np.ndarray | None = None) -> Evidence:
    """Depth agreement and keypoint support of the pose T_cam_obj (module docstring); n_matches, n_inliers and
    spread_m are left to the caller. samples [S x 3]: the template surface (object frame), center [3] its
    centre; kp_points [N x 3]: template keypoints (object frame), kp_idx [K] those offered; sim [M x C]: the
    query keypoints' similarity (sign 1) or distance (sign -1) to template keypoints, sim_cols [K] the offered
    ones' columns, sim_rows [M] the query keypoints' rows (None: row i is keypoint i); q_points [M x 3],
    q_location [M]: the query keypoints (camera frame) and their location ids;
    min_sim: the similarity (or negated distance) at which a keypoint agrees. gate: when given and the depth
    agreement alone refuses the pose under that rule (`depth_refusal`), the keypoint support is not computed
    (left empty: for a caller that reads only whether the pose is accepted). local [M] bool: the query keypoints
    judged by `keypoint_support`'s local rule (depth keypoints)."""
    frame = q.frame
    seen = visible(T_cam_obj, frame.intrinsics, samples)  # the template surface the pose shows
    n_c, n_b, n = depth_votes(frame.depth, frame.intrinsics, T_cam_obj, samples, params.depth_tol, q.off_plane, seen)
    ev = Evidence(score=n_c / max(1, n_c + n_b), confirmed=n_c / max(1, n))
    if gate is not None and depth_refusal(ev, gate) is not None:
        return ev
    radius = support_radius(params, float(transform_points(T_cam_obj, center[None])[0, 2]))
    ev.supporters, ev.on_surface, ev.offer = keypoint_support(
        T_cam_obj, kp_points, kp_idx, sim, sim_cols, q_points, q_location, samples, frame.depth, frame.intrinsics,
        radius, min_sim, params.depth_tol, sign, seen[1], sim_rows, local)
    return ev


def support_radius(params: VerifyParams, z: float) -> float:
    """m: how near a query keypoint a template keypoint supports it, for an object at depth z (m):
    `support_radius`, growing 1 % of the depth beyond 0.5 m."""
    return params.support_radius + 0.01 * max(z - 0.5, 0.0)


def query_sinks(q: QueryFrame, T_cam_obj: np.ndarray, samples: np.ndarray, params: VerifyParams) -> float | None:
    """`sinks_into_plane` of the pose in the query frame (None when the frame has no support plane)."""
    if q.plane is None:
        return None
    assert q.heights is not None
    return sinks_into_plane(T_cam_obj, samples, q.plane, q.heights, q.frame.depth, q.frame.intrinsics,
                            params.below_tol, params.max_below_frac)
