"""Pairwise registration: features -> match (GMatch or a baseline) -> pose -> verdict.

`register_features(fs, ft, params, clouds, dense)` registers two frames' keypoints (`register_frames`, in
`gscan.registration.frames`, also extracts them and samples the depth). T_tgt_src maps source-camera points into
the target camera (p_t = T_tgt_src @ p_s).

Every residual is measured in units of the depth noise (`gscan.registration.noise`): a pair of keypoints
at depths z_s, z_t has the per-axis standard deviation s = params.noise.pair_sigma(z_s, z_t, l), so a gate of
3.4 s keeps 99 % of the true pairs of a Kinect at 2 m (s about 12 mm) and of a render at 0.6 m (s about
1.5 mm) alike; l combines the two keypoints' location sigmas in quadrature (`Features.location_sigma`: 0 for
image keypoints, 0.58 voxel for depth keypoints, `gscan.features.depth.location_sigma`), in every gate, rule 2
and the information.

Acceptance rules, applied in this order (the first failing one is the `reason`):
1. "too few matches": fewer than `min_matches` geometric matches (the pairs the pose rests on).
2. "keypoint residual": the RMS of |T p_s - p_t| / s over those pairs above `max_rms` (a right pose gives
   about 1.7, the chi distribution of three axes truncated at the gate). With the depth samples (`dense`)
   the pose is then refined on the pairs and the depth together (`gscan.registration.dense.refine_pose`).
   "weak geometry": the pose's
   standard deviation predicted by its information matrix (the pairs' noise and layout, and the depth's
   when it took part: a few pairs on one face of a box pin it badly) beyond `max_sigma_deg` in rotation, or the
   RMS positional standard deviation of its pairs' points beyond `max_sigma_rel` of their median depth
   (1 sigma; both a third or less of the 5 deg / 2 cm at 0.6 m that a wrong pose is). An edge that alone places
   a frame (a two-frame capture, `alone`) and is pinned too loosely so is refined on both frames' texture pixel
   by pixel (`gscan.registration.photometric`, with the depth refinement) and judged by that pose's sigma;
   "texture disagrees" where the pixels turn the pose farther from the keypoints' and depth's than both allow
   (`rotation_disagreement`), and rule 3's colour check judges the pose before that refinement too.
3. "depth disagrees" (with `dense`, both frames' `DenseGeometry`): under the pose, more than
   `max_see_through` of the overlap of the two depth images is seen through (`gscan.registration.dense`);
   "too little depth overlap" when fewer than `min_overlap` samples land on the other frame's depth.
   "colour disagrees" (with the frames' texture in `dense`): of the overlap's textured tiles, fewer than
   `min_colour_agreement` line up under the pose (`gscan.registration.colour`: depth cannot tell a pose
   from its mirror on a symmetric object, the texture around it can); no verdict with fewer than
   `min_colour_tiles` textured tiles. Where the depth decides (depth keypoints and no texture verdict, or the
   pose resting mostly on depth keypoints: `PairResult.depth_only`), the pose is refined on the depth alone and
   judged again, with stricter bounds (`_judge_on_depth`).
4. with ICP (params.icp and both clouds given), point-to-plane ICP from the match pose, then
   "icp fitness" below `min_fitness`, "icp rmse" above `max_rmse`, or "icp shift": ICP moved the
   match pose by more than `max_icp_shift_deg` / `max_icp_shift_m` (a slide, not a refinement).
   A rejected ICP leaves the match pose in T_tgt_src; an accepted one replaces it.

Pose from a GMatch list: `geometry.kabsch_trimmed` with each pair's tau = `trim_gate` s: plain Kabsch when
every pair fits, else the pairs within tau of the best-scoring triple's pose (a consensus over every
triple of the list), re-solved; then the worst pair by leave-one-out residual is dropped while it lies
beyond its tau, never below half of the list. Pairwise distances cannot tell a point from its mirror
image across a plane holding the other matches, and a background pair can join a whole-frame list
through the depth-grown eta: one such pair tilts plain Kabsch by degrees. Trimmed pairs do not count for
rule 1.

Support check (GMatch only, `verify`): the longest list is not always the right one (a short wrong list
that happens to be consistent can outgrow the true lists when noisy depth breaks eps_c on short true
distances). The winner and up to `verify` other distinct lists of the search (`lists_to_verify`) are each
posed and refined as below on the pairs with descriptor distance below `support_eps_scale` x eps_f (a
true pair seen 60 deg apart is often beyond eps_f); the refined inlier count is the list's support.
Another list replaces the winner only with >= `verify_ratio` times its support (`pose_by_support`). The
chosen pose's inliers (what rules 1-2 and the pose graph weigh an edge by) are the GMatch candidates
alone that agree with it (`consistent_pairs`): on a repetitive table a wrong pose that maps the table
plane onto itself collects hundreds of look-alike pairs under the looser bound. `verify=0` is the
paper's pick alone.

Guided refinement (GMatch only, `refine`): GMatch stops at L (24) matches. From the list's pose, every
pair of the pool whose transformed source point lies within gate x s of its target point is collected,
made one-to-one by normalised residual, and the pose re-solved by Kabsch weighted by 1 / s^2; the gate
shrinks over `refine_gates`. A round that keeps fewer pairs than the list stops the refinement.

`PairResult.information` is the [6 x 6] information of the pose from its inlier pairs, each weighted by
1 / s^2 (`information_from_points`): what the pose graph weighs the edge by.
"""
from __future__ import annotations

import itertools
import logging
import time
from dataclasses import dataclass, field

import numpy as np

from gscan.features import Features, descriptor_distances
from gscan.features.keypoints import JOINT
from gscan.geometry.icp import icp
from gscan.geometry.kabsch import kabsch, kabsch_trimmed
from gscan.geometry.transforms import inv_T, pose_error, transform_points
from gscan.io.camera import RGBDFrame, point_cloud
from gscan.matching.baselines import run_baseline
from gscan.matching.gmatch import GMatchResult, default_eps_f, gmatch
from gscan.registration.colour import ColourAgreement
from gscan.registration.dense import (
    DenseGeometry,
    DepthAgreement,
    colour_agreement,
    depth_agreement,
    outside_outline,
    outside_silhouette,
    pose_information,
    pose_sigma,
)
from gscan.registration.dense import refine_pose as refine_with_depth
from gscan.registration.noise import DepthNoise
from gscan.registration.params import METHODS, RegisterParams  # noqa: F401 - its importers read it here too
from gscan.registration.photometric import DISAGREEING_CHI2, refine_photometric, rotation_disagreement
from gscan.registration.pool_kernel import near_pairs, pool_rows
from gscan.registration.posegraph import information_from_points

log = logging.getLogger(__name__)

NO_TEXTURE_VERDICT = "the texture cannot judge the pose"  # in the reasons of the shape's checks of a depth-alone pose
SHAPE_REFUSALS = ("depth disagrees", "silhouette disagrees", "outline disagrees")  # those checks' reasons begin so


def refused_by_shape(reason: str | None) -> bool:
    """Whether `reason` is the refusal of a pose the depth alone decided, pinned as tightly as rule 2 asks, by one of
    the shape's checks (`_judge_on_depth`: the depth seen through, the silhouette, the outline)."""
    return reason is not None and reason.startswith(SHAPE_REFUSALS) and NO_TEXTURE_VERDICT in reason


@dataclass
class PairResult:
    T_tgt_src: np.ndarray | None  # [4 x 4]; None when fewer than 3 matches
    matches: np.ndarray  # [M x 2] int32 (source keypoint, target keypoint)
    cost: float  # GMatch list cost; for baselines the Kabsch RMSE (m)
    n_matches: int
    rmse: float | None  # ICP inlier RMSE (m) when ICP ran, else the RMS keypoint residual over the inliers (m)
    fitness: float | None  # ICP fitness, None without ICP
    accepted: bool
    reason: str | None  # None when accepted, else the first failed rule (module docstring)
    method: str = "gmatch"
    T_match: np.ndarray | None = None  # [4 x 4] pose from the matches alone (before ICP)
    inliers: np.ndarray | None = None  # [K x 2] int32 correspondences the pose was solved from (refined)
    information: np.ndarray | None = None  # [6 x 6] of the pose from the inliers (module docstring)
    rms_sigma: float | None = None  # RMS of the inliers' residuals in units of s (rule 2)
    sigma_deg: float | None = None  # predicted rotation standard deviation of the pose (rule 2)
    sigma_m: float | None = None  # predicted RMS position standard deviation of its pairs' points (rule 2)
    agreement: DepthAgreement | None = None  # the depth check of rule 3, when it ran
    colour: ColourAgreement | None = None  # the colour check of rule 3, when it ran
    depth_only: bool = False  # accepted on depth keypoints with no texture verdict: the depth alone decided it
    outside: float | None = None  # the depth-alone verdict's share of samples landing off the other frame
    T_textured: np.ndarray | None = None  # [4 x 4] the pose the texture judges, where the pixels then refined it
    timings_ms: dict[str, float] = field(default_factory=dict)


ROWS_MAX_PER_SOURCE = 300  # pool pairs per source keypoint up to which the pool is looked up by rows


class GuidedPool:
    """Keypoint pairs with descriptor distance below `eps`, looked up near a pose: what guided refinement
    (eps = eps_f, GMatch's candidates) and the support check (a looser bound: under a pose, geometry does the
    filtering) may use.

    Two lookups give the same pairs in the same order: by rows (`pool_kernel`: each source keypoint's pairs,
    checked one by one; it costs the pool's size a lookup and Ns x Nt to build) where the pool is sparse, as on
    real frames (a few to a few hundred pairs a keypoint), and a k-d tree of the target points (a ball query, then
    the descriptor filter; it costs about Ns a lookup) where look-alike texture makes the pool dense. `lookup`:
    "auto" (by the pool's density, estimated on every 8th row), "rows" or "tree".

    pts_t [Nt x 3] target points, dist [Ns x Nt] descriptor distances.
    """

    def __init__(self, pts_t: np.ndarray, dist: np.ndarray, eps: float, lookup: str = "auto"):
        self.pts_t = np.ascontiguousarray(pts_t, np.float64)
        self.dist = np.ascontiguousarray(dist)
        self.eps = self.dist.dtype.type(eps)  # compared in dist's own type, as numpy compares with a Python float
        if lookup == "auto":
            some = self.dist[::8] < self.eps
            lookup = "rows" if np.count_nonzero(some) <= ROWS_MAX_PER_SOURCE * len(some) else "tree"
        self._rows = pool_rows(self.dist, self.eps) if lookup == "rows" else None
        self._tree = None
        if lookup == "tree" and len(self.pts_t):
            from scipy.spatial import cKDTree

            self._tree = cKDTree(self.pts_t)

    def near(self, pts_s_in_t: np.ndarray, tau: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(source indices [K], target indices [K]) int64 of the pool's pairs whose source point, given in the
        target frame ([Ns x 3]), lies within tau (m; one for all or one per source point [Ns]) of the target
        point; in (source, target) order."""
        q = np.ascontiguousarray(pts_s_in_t, np.float64)
        if len(self.pts_t) == 0 or len(q) == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        if self._rows is not None:
            tau = np.ascontiguousarray(np.broadcast_to(np.asarray(tau, np.float64), (len(q),)))
            start, targets = self._rows
            return near_pairs(start, targets, q, self.pts_t, tau)
        assert self._tree is not None
        hits = self._tree.query_ball_point(q, tau, return_sorted=True)
        n = np.fromiter(map(len, hits), np.int64, count=len(hits))
        ii = np.repeat(np.arange(len(hits)), n)
        jj = np.fromiter(itertools.chain.from_iterable(hits), np.int64, count=int(n.sum()))
        ok = self.dist[ii, jj] < self.eps
        return ii[ok], jj[ok]


def _locations(loc: np.ndarray | None, n: int) -> np.ndarray:
    """[n] float64 keypoint location sigmas (m; `Features.location_sigma`), zeros when not given."""
    return np.zeros(n) if loc is None else np.asarray(loc, np.float64).reshape(n)


def _pairs_near(ps: np.ndarray, pt: np.ndarray, pool: GuidedPool, T: np.ndarray, gate: float, noise: DepthNoise,
                loc_s: np.ndarray | None = None, loc_t: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pool pairs within gate x s under T: (source idx [K], target idx [K], residual [K] m, s [K] m); loc_s [Ns],
    loc_t [Nt]: the keypoints' location sigmas (m, None: 0)."""
    ls, lt = _locations(loc_s, len(ps)), _locations(loc_t, len(pt))
    q = transform_points(T, ps)
    # the lookup radius takes the target depth as the source point's own depth in the target frame and the
    # largest target location sigma; the exact s of each found pair (its two depths and keypoints) decides below
    ii, jj = pool.near(q, 1.5 * gate * noise.pair_sigma(q[:, 2], q[:, 2], np.hypot(ls, lt.max(initial=0.0))))
    r = np.linalg.norm(q[ii] - pt[jj], axis=1)
    sg = noise.pair_sigma(ps[ii, 2], pt[jj, 2], np.hypot(ls[ii], lt[jj]))
    ok = r < gate * sg
    return ii[ok], jj[ok], r[ok], sg[ok]


def refine_pose(pts_s: np.ndarray, pts_t: np.ndarray, pool: GuidedPool, T: np.ndarray, gates: tuple[float, ...],
                noise: DepthNoise, min_pairs: int, loc_s: np.ndarray | None = None,
                loc_t: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Guided refinement (module docstring): (T_tgt_src [4 x 4], inliers [K x 2] int32).

    pts_s [Ns x 3], pts_t [Nt x 3], pool the pairs it may use, T the starting pose; loc_s [Ns], loc_t [Nt] the
    keypoints' location sigmas (m, None: 0).
    Returns the input pose and an empty inlier set when no round keeps `min_pairs` pairs.
    """
    ps, pt = np.asarray(pts_s, np.float64), np.asarray(pts_t, np.float64)
    best = np.zeros((0, 2), np.int32)
    for gate in gates:
        ii, jj, r, sg = _pairs_near(ps, pt, pool, T, gate, noise, loc_s, loc_t)
        ok = _one_to_one(ii, jj, r / sg)
        if len(ok) < min_pairs:
            break
        best = np.stack([ii[ok], jj[ok]], axis=1).astype(np.int32)
        T = kabsch(ps[best[:, 0]], pt[best[:, 1]], 1.0 / np.square(sg[ok]))
    return T, best


def consistent_pairs(pts_s: np.ndarray, pts_t: np.ndarray, pool: GuidedPool, T: np.ndarray, gate: float,
                     noise: DepthNoise, loc_s: np.ndarray | None = None, loc_t: np.ndarray | None = None
                     ) -> np.ndarray:
    """[K x 2] int32 pairs of `pool` (source, target) within gate x s of each other under T_tgt_src, one-to-one
    (loc_s [Ns], loc_t [Nt]: the keypoints' location sigmas, m, None: 0)."""
    ps, pt = np.asarray(pts_s, np.float64), np.asarray(pts_t, np.float64)
    ii, jj, r, sg = _pairs_near(ps, pt, pool, T, gate, noise, loc_s, loc_t)
    ok = _one_to_one(ii, jj, r / sg)
    return np.stack([ii[ok], jj[ok]], axis=1).astype(np.int32)


def _one_to_one(ii: np.ndarray, jj: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Indices of the pairs (ii, jj) kept one-to-one by residual r: each source its closest target, then each
    target its closest source (ties by index: deterministic)."""
    ok = np.lexsort((jj, ii, r))
    ok = ok[np.sort(np.unique(ii[ok], return_index=True)[1])]
    return ok[np.sort(np.unique(jj[ok], return_index=True)[1])]


_SAME_POSE_DEG, _SAME_POSE_M = 2.0, 0.01  # a list posed this close to one already checked is skipped


def lists_to_verify(res: GMatchResult, n_other: int, min_len: int) -> tuple[list[np.ndarray], list[float]]:
    """(lists, costs): the GMatch winner's list, then up to n_other other distinct hypothesis lists ([M x 2]
    int32 each) of at least min_len pairs, by (length descending, cost, search order), with their costs.
    Lists holding the same pairs are one."""
    def key(m: np.ndarray) -> bytes:  # the list's pairs as a set: sorted (source << 32 | target)
        return np.sort((m[:, 0].astype(np.int64) << 32) | m[:, 1]).tobytes()

    out, costs, seen = [res.matches], [res.cost], {key(res.matches)}
    for h in np.lexsort((np.arange(len(res.hyp_length)), res.hyp_cost, -res.hyp_length)):
        n = int(res.hyp_length[h])
        if len(out) > n_other or n < min_len:
            break
        m = res.hyp_matches[h, :n]
        k = key(m)
        if k not in seen:
            seen.add(k)
            out.append(m)
            costs.append(float(res.hyp_cost[h]))
    return out, costs


def pose_by_support(pts_s: np.ndarray, pts_t: np.ndarray, support_pool: GuidedPool, refine_pool: GuidedPool,
                    lists: list[np.ndarray], params: RegisterParams, loc_s: np.ndarray | None = None,
                    loc_t: np.ndarray | None = None) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
    """(index of the chosen list, T_tgt_src [4 x 4], its kept pairs [K x 2], its refined inliers [R x 2] or empty).

    Each list's pose (kabsch_trimmed) is refined by `refine_pose` on `support_pool`; its support is the refined
    inlier count (the kept pairs when no round reached the list's length). lists[0] (GMatch's pick) is replaced
    by the best supported other list (first on ties) only if that has at least `verify_ratio` times its support.
    A list whose pairs all lie within their tau under a pose already checked, or whose pose lies within 2 deg /
    1 cm of one, is skipped (it would refine to the same). Supports of lists of different lengths compare as
    they are: a list's refinement must keep at least its own length, else its support is its kept pairs.
    With params.refine, T is the chosen list's pose refined on `support_pool`, and the returned inliers are
    the `refine_pool` pairs consistent with it within the last refinement gate (empty, as when no round
    kept the list's length, if they are fewer than the list); else T is the list's own pose. loc_s [Ns], loc_t
    [Nt]: the keypoints' location sigmas (m, None: 0), in every pair's s.
    """
    if not lists:
        raise ValueError("pose_by_support needs at least GMatch's own list")
    noise = params.noise
    ls, lt = _locations(loc_s, len(pts_s)), _locations(loc_t, len(pts_t))
    best = None
    verified: list[np.ndarray] = []
    for k, m in enumerate(lists):
        src, dst = pts_s[m[:, 0]], pts_t[m[:, 1]]
        tau = params.trim_gate * noise.pair_sigma(src[:, 2], dst[:, 2], np.hypot(ls[m[:, 0]], lt[m[:, 1]]))
        if any((np.linalg.norm(transform_points(V, src) - dst, axis=1) < tau).all() for V in verified):
            continue  # every pair agrees with a pose already checked
        T, keep = kabsch_trimmed(src, dst, tau)
        if any(e[0] < _SAME_POSE_DEG and e[1] < _SAME_POSE_M for e in (pose_error(T, V) for V in verified)):
            continue
        verified.append(T)
        if len(lists) == 1 and not params.refine:  # nothing to compare, nothing to refine
            return 0, T, m[keep], np.zeros((0, 2), np.int32)
        T_ref, refined = refine_pose(pts_s, pts_t, support_pool, T, params.refine_gates, noise, len(m), ls, lt)
        support = len(refined) if len(refined) else int(keep.sum())
        if k == 0:
            first, support_0 = (k, T, keep, T_ref, refined), support
        elif support >= params.verify_ratio * support_0 and (best is None or support > best[0]):
            best = (support, (k, T, keep, T_ref, refined))
    k, T, keep, T_ref, refined = first if best is None else best[1]
    if not params.refine:
        return k, T, lists[k][keep], np.zeros((0, 2), np.int32)
    if not len(refined):
        return k, T, lists[k][keep], refined
    # the inliers (what the pose graph weighs an edge by): the candidates alone that agree with the pose
    inliers = consistent_pairs(pts_s, pts_t, refine_pool, T_ref, params.refine_gates[-1], noise, ls, lt)
    return k, T_ref, lists[k][keep], (inliers if len(inliers) >= len(lists[k]) else np.zeros((0, 2), np.int32))


def _loose(out: PairResult, max_deg: float, max_m: float) -> bool:
    """Whether rule 2 refuses the pose as weak geometry: its rotation or position sigma beyond the bounds."""
    return out.sigma_deg is not None and out.sigma_m is not None and (out.sigma_deg > max_deg or out.sigma_m > max_m)


def _mostly_depth(from_depth: np.ndarray | None, pairs: np.ndarray) -> bool:
    """Whether most of the pairs [K x 2] (source, target) have a depth keypoint as source (from_depth [Ns] bool)."""
    return from_depth is not None and len(pairs) > 0 and 2 * int(from_depth[pairs[:, 0]].sum()) > len(pairs)


def _judge_on_depth(out: PairResult, T_tgt_src: np.ndarray, dense: tuple[DenseGeometry, DenseGeometry],
                    dst: np.ndarray, params: RegisterParams) -> tuple[np.ndarray, str | None]:
    """The depth decides the edge `out` (the texture cannot judge: a plain surface, whose shading agrees under a
    turned pose too; or the pose rests mostly on depth keypoints): its pose is refined on the depth alone from the
    keypoints' (depth keypoints are picked anew in each view, and their bias pulls the pose: the tune box's
    turntable edges 1.4-4.5 deg off came within 0.4-1.2 deg), with the depth's noise along the ray and the frames'
    rims drawn onto each other's masks (docs/method.md, "Plain objects"), the depth alone must pin it (rule 2, on
    its information), and stricter bounds hold: a pose turned 10-20 deg on a box sees through 1-2 % of the overlap, a
    right one 0.1 % at most; a pose turned by a symmetry of the shape lands 14-27 % of its samples off the other
    silhouette, a right one 5 % at most (BENCHMARKS.md, plain objects); and the outline at the pixel agrees to
    the pose's own claimed precision (3 sigma): a pose slid along a plain face lands the object's outline off by
    the slide, far beyond what it claims. Returns the pose refined from T_tgt_src and the refusal's reason (None:
    accepted); sets out's pose, information, sigmas and checks. dst [K x 3]: the pairs' target points (where
    rule 2 weighs the pose)."""
    none = np.zeros((0, 3))
    T, out.information = refine_with_depth(dense[0], dense[1], none, none, T_tgt_src, params.noise,
                                           params.depth_noise_ray, rims=True)
    out.T_tgt_src = T
    out.sigma_deg, out.sigma_m = pose_sigma(out.information, dst)
    depth = float(np.median(dst[:, 2]))
    if out.sigma_deg > params.max_sigma_deg or out.sigma_m > params.max_sigma_rel * depth:
        return T, (f"weak geometry (the depth alone pins the pose to {out.sigma_deg:.1f} deg and the pairs' points to "
                   f"{out.sigma_m * 1000:.1f} mm, beyond {params.max_sigma_deg:g} deg / "
                   f"{params.max_sigma_rel * depth * 1000:.1f} mm; the texture cannot judge the pose)")
    a = out.agreement = depth_agreement(dense[0], dense[1], T, params.depth_noise_ray)
    if a.consistent + a.see_through < params.min_overlap:
        return T, f"too little depth overlap to verify the pose ({a.consistent + a.see_through} samples)"
    if a.see_through_fraction > params.max_see_through_shape:
        return T, (f"depth disagrees ({a.see_through_fraction:.1%} of the overlap of {a.consistent + a.see_through} "
                   f"samples seen through; {NO_TEXTURE_VERDICT}, so at most {params.max_see_through_shape:.1%})")
    c = out.colour = colour_agreement(dense[0], dense[1], T, params.depth_noise)
    if c.refutes(params.min_colour_tiles, params.min_colour_agreement):
        return T, f"colour disagrees (the texture lines up in {c.agreeing} of {c.informative} tiles of the overlap)"
    off = out.outside = outside_silhouette(dense[0], dense[1], T)
    if off > params.max_outside_shape:
        return T, (f"silhouette disagrees ({off:.1%} of the samples land off the other frame's surface; "
                   f"{NO_TEXTURE_VERDICT}, so at most {params.max_outside_shape:.1%})")
    margin = 3.0 * out.sigma_m
    off = outside_outline(dense[0], dense[1], T, margin)
    if off > params.max_outside_outline:
        return T, (f"outline disagrees ({off:.1%} of the rim points land over {margin * 1000:.1f} mm, three times "
                   f"the pose's sigma, off the other frame's outline; {NO_TEXTURE_VERDICT}, so at most "
                   f"{params.max_outside_outline:.1%})")
    return T, None


def register_points(pts_s: np.ndarray, pts_t: np.ndarray, desc_s: np.ndarray, desc_t: np.ndarray, kind: str,
                    params: RegisterParams = RegisterParams(), clouds: tuple | None = None,
                    dense: tuple[DenseGeometry, DenseGeometry] | None = None,
                    fs_depth: np.ndarray | None = None, loc_s: np.ndarray | None = None,
                    loc_t: np.ndarray | None = None, alone: bool = False) -> PairResult:
    """Register camera-frame keypoints pts_s [Ns x 3] -> pts_t [Nt x 3] (descriptors [N x D] of `kind`).

    clouds: optional (src [P x 3], tgt [Q x 3]) camera-frame clouds for ICP; dense: optional (source, target)
    depth samples for rule 3; fs_depth: [Ns] bool the source keypoints found in the depth (rootsift+fpfh);
    loc_s [Ns], loc_t [Nt]: the keypoints' location sigmas (m, `Features.location_sigma`; None: 0), in every
    pair's s (the gates, rule 2's residual and the information); alone: the edge alone places a frame (a two-frame
    capture; rule 2's photometric refinement).
    """
    tm: dict[str, float] = {}
    t0 = time.perf_counter()
    dist = descriptor_distances(desc_s, desc_t, kind)
    tm["distances"] = (time.perf_counter() - t0) * 1e3
    t0 = time.perf_counter()
    if params.method == "gmatch":
        eps_f = params.gmatch.eps_f if params.gmatch.eps_f is not None else default_eps_f(kind)
        res = gmatch(pts_s, pts_t, dist, eps_f, params.gmatch)
        matches, cost, T = res.matches, res.cost, None
        refine_pool = GuidedPool(pts_t, dist, eps_f)
        support_pool = GuidedPool(pts_t, dist, params.support_eps_scale * eps_f)
    else:
        b = run_baseline(params.method, pts_s, pts_t, dist, desc_s, desc_t, params.baseline)
        matches, cost, T = b.matches, float("nan"), b.T_tgt_src
    tm["match"] = (time.perf_counter() - t0) * 1e3
    n = len(matches)
    ps, pt = np.asarray(pts_s, np.float64), np.asarray(pts_t, np.float64)
    inliers = matches  # the pairs the pose rests on
    n_kept = n
    if n < 3:
        T = None
    elif params.method == "gmatch":  # a consistent list may hold a far-off pair (module docstring)
        lists, costs = lists_to_verify(res, params.verify, params.verify_min_len)
        k, T, kept, refined = pose_by_support(ps, pt, support_pool, refine_pool, lists, params, loc_s, loc_t)
        if k:
            log.debug("register: hypothesis list %d (%d pairs) outsupports GMatch's (%d pairs)", k, len(lists[k]), n)
            matches, n, cost = lists[k], len(lists[k]), costs[k]
        inliers = refined if params.refine and len(refined) else kept
        n_kept = len(inliers)
    elif T is None:
        T = kabsch(ps[matches[:, 0]], pt[matches[:, 1]])
    out = PairResult(T, matches, float(cost), n, None, None, False, None, params.method,
                     T_match=None if T is None else T.copy(), inliers=inliers, timings_ms=tm)
    if T is not None and len(inliers):
        src, dst = ps[inliers[:, 0]], pt[inliers[:, 1]]
        loc = np.hypot(_locations(loc_s, len(ps))[inliers[:, 0]], _locations(loc_t, len(pt))[inliers[:, 1]])
        sg = params.noise.pair_sigma(src[:, 2], dst[:, 2], loc)
        r = np.linalg.norm(transform_points(T, src) - dst, axis=1)
        out.rmse = float(np.sqrt(np.mean(r * r)))
        out.rms_sigma = float(np.sqrt(np.mean(np.square(r / sg))))
        out.information = information_from_points(dst, sg)
        out.sigma_deg, out.sigma_m = pose_sigma(out.information, dst)
        if params.method != "gmatch":
            out.cost = out.rmse
    if n_kept < params.min_matches:
        out.reason = f"too few matches ({n_kept} < {params.min_matches})"
        return out
    assert T is not None  # at least min_matches >= 3 pairs: a pose
    if out.rms_sigma is not None and out.rms_sigma > params.max_rms:
        out.reason = f"keypoint residual ({out.rms_sigma:.2f} > {params.max_rms} noise sigmas)"
        return out
    if dense is not None and params.refines_on_depth:
        t0 = time.perf_counter()
        T, out.information = refine_with_depth(dense[0], dense[1], src, dst, T, params.noise, params.depth_noise,
                                               kp_loc=loc)
        out.T_tgt_src = T
        out.sigma_deg, out.sigma_m = pose_sigma(out.information, dst)
        tm["refine"] = (time.perf_counter() - t0) * 1e3
    depth = float(np.median(pt[inliers[:, 1], 2]))
    what = "pairs and the depth" if dense is not None and params.refines_on_depth else "pairs"
    if (alone and dense is not None and params.photometric and params.refines_on_depth and out.information is not None
            and _loose(out, params.max_sigma_deg, params.max_sigma_rel * depth)):
        t0 = time.perf_counter()
        none = np.zeros((0, 3))  # the depth's information alone: the keypoints' lag is what the pixels correct
        by_depth = pose_information(dense[0], dense[1], none, none, T, params.noise, params.depth_noise)
        fit = refine_photometric(dense[0], dense[1], T, by_depth, params.depth_noise)
        tm["photometric"] = (time.perf_counter() - t0) * 1e3
        if fit is not None:
            apart = rotation_disagreement(T, out.information, fit.T_tgt_src, fit.information)
            if apart > DISAGREEING_CHI2:
                out.reason = (f"texture disagrees (the pixels turn the pose {fit.turn_deg(T):.2f} deg from where the "
                              f"keypoints and depth put it, {np.sqrt(apart):.1f} sigmas of both)")
                return out
            out.T_textured = T
            T = out.T_tgt_src = fit.T_tgt_src
            out.information = fit.information
            out.sigma_deg, out.sigma_m = fit.sigma_deg, pose_sigma(fit.information, dst)[1]
            what += f", and the texture of {fit.pixels} pixels"
    if _loose(out, params.max_sigma_deg, params.max_sigma_rel * depth):
        assert out.sigma_deg is not None and out.sigma_m is not None  # what _loose judged
        out.reason = (f"weak geometry (the {n_kept} {what} pin the pose to {out.sigma_deg:.1f} deg and the "
                      f"pairs' points to {out.sigma_m * 1000:.1f} mm, beyond {params.max_sigma_deg:g} deg / "
                      f"{params.max_sigma_rel * depth * 1000:.1f} mm)")
        return out
    if dense is not None:
        t0 = time.perf_counter()
        a = out.agreement = depth_agreement(dense[0], dense[1], T, params.depth_noise)
        tm["dense"] = (time.perf_counter() - t0) * 1e3
        if a.consistent + a.see_through < params.min_overlap:
            out.reason = f"too little depth overlap to verify the pose ({a.consistent + a.see_through} samples)"
            return out
        if a.see_through_fraction > params.max_see_through:
            out.reason = f"depth disagrees ({a.see_through_fraction:.0%} of the overlap seen through)"
            return out
        t0 = time.perf_counter()
        c = colour_agreement(dense[0], dense[1], T, params.depth_noise)
        if out.T_textured is not None and not c.refutes(params.min_colour_tiles, params.min_colour_agreement):
            # a pose refined on the texture lines it up by construction: the verdict (here and on the object's
            # turns, `gscan.registration.turns`) stands on the pose before
            c = colour_agreement(dense[0], dense[1], out.T_textured, params.depth_noise)
        out.colour = c
        tm["colour"] = (time.perf_counter() - t0) * 1e3
        if c.refutes(params.min_colour_tiles, params.min_colour_agreement):
            out.reason = (f"colour disagrees (the texture lines up in {c.agreeing} of {c.informative} tiles of the "
                          f"overlap under the pose)")
            return out
        if kind == JOINT and (c.informative < params.min_colour_tiles or _mostly_depth(fs_depth, inliers)):
            out.depth_only = True
            T, out.reason = _judge_on_depth(out, T, dense, dst, params)
            if out.reason is not None:
                return out
    elif kind == JOINT:
        out.reason = "depth keypoints need the depth check (no depth samples given)"
        return out
    if params.icp and clouds is not None and clouds[0] is not None and clouds[1] is not None:
        t0 = time.perf_counter()
        r_icp = icp(clouds[0], clouds[1], T, params.icp_max_dist, params.icp_voxel, params.icp_iterations, True)
        tm["icp"] = (time.perf_counter() - t0) * 1e3
        out.fitness, out.rmse = r_icp.fitness, r_icp.rmse
        deg, m = pose_error(r_icp.T, T)
        if r_icp.fitness < params.min_fitness:
            out.reason = f"icp fitness ({r_icp.fitness:.2f} < {params.min_fitness})"
        elif r_icp.rmse > params.max_rmse:
            out.reason = f"icp rmse ({r_icp.rmse:.4f} m > {params.max_rmse} m)"
        elif deg > params.max_icp_shift_deg or m > params.max_icp_shift_m:
            out.reason = f"icp shift ({deg:.1f} deg, {m:.3f} m)"
        else:
            out.T_tgt_src = r_icp.T
            out.accepted = True
        return out
    out.accepted = True
    return out


def register_features(fs: Features, ft: Features, params: RegisterParams = RegisterParams(),
                      clouds: tuple[np.ndarray | None, np.ndarray | None] | None = None,
                      dense: tuple[DenseGeometry, DenseGeometry] | None = None, alone: bool = False) -> PairResult:
    """Register the keypoints of two frames (camera-frame points, viewed along +z): match, pose, depth check,
    optional ICP, verdict (module docstring).

    Args:
        fs, ft: the source and target frames' keypoints, of one descriptor kind.
        params: matcher, pose and acceptance parameters.
        clouds: (source [P x 3], target [Q x 3]) camera-frame clouds for ICP (used when params.icp).
        dense: (source, target) depth samples: the pose is refined on them and checked against them.
        alone: the edge alone places a frame (a two-frame capture): where its keypoints and depth pin the pose too
            loosely, it is refined on the frames' texture too (rule 2, `gscan.registration.photometric`).

    Returns:
        PairResult: T_tgt_src [4 x 4] (source camera -> target camera) or None, the matches [M x 2] (source,
        target keypoint indices), the inliers the pose rests on [K x 2], quality numbers, and the verdict
        (`accepted`, `reason`).
    """
    if fs.kind != ft.kind:
        raise ValueError(f"descriptor kinds differ: {fs.kind} vs {ft.kind}")
    joint = fs.kind == JOINT
    return register_points(fs.points, ft.points, fs.descriptors, ft.descriptors, fs.kind, params, clouds, dense,
                           fs.from_depth if joint else None, fs.location_sigma if joint else None,
                           ft.location_sigma if joint else None, alone)


def frame_cloud(frame: RGBDFrame, stride: int = 2, mask: np.ndarray | None = None) -> np.ndarray:
    """Camera-frame ICP cloud [P x 3] of an RGBDFrame (valid depth, every `stride`-th pixel, optional mask)."""
    return point_cloud(frame, mask, stride)[0]


def relative_pose(T_world_cam_s: np.ndarray, T_world_cam_t: np.ndarray) -> np.ndarray:
    """Ground-truth T_tgt_src from two camera poses: inv(T_world_cam_t) @ T_world_cam_s."""
    return inv_T(T_world_cam_t) @ T_world_cam_s
