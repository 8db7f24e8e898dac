"""Pairwise registration: features -> match (GMatch or a baseline) -> Kabsch -> ICP -> verdict.

`register_features(fs, ft, params, clouds)` registers two frames' keypoints; `register_frames(frame_s,
frame_t)` also extracts the features and back-projects the ICP clouds (the one-call Python API).
T_tgt_src maps source-camera points into the target camera (p_t = T_tgt_src @ p_s).

Acceptance rules, applied in this order (the first failing one is the `reason`):
1. "too few matches": fewer than `min_matches` geometric matches (trimmed GMatch list / baseline inliers).
2. "kabsch residual": RMS of |T p_s - p_t| over the pairs the pose rests on (`inliers`) above `max_kabsch_rmse`.
3. with ICP (params.icp and both clouds given), point-to-plane ICP from the match pose, then
   "icp fitness" below `min_fitness`, "icp rmse" above `max_rmse`, or "icp shift": ICP moved the
   match pose by more than `max_icp_shift_deg` / `max_icp_shift_m` (a slide, not a refinement).
   A rejected ICP leaves the match pose in T_tgt_src; an accepted one replaces it.
Without ICP, rmse is the Kabsch residual and fitness is None.

Pose from a GMatch list: `geometry.kabsch_trimmed` with `trim_tau`: plain Kabsch when every pair fits
within trim_tau, else the pairs within trim_tau of the best-scoring triple's pose (a consensus over every
triple of the list), re-solved; then the worst pair by leave-one-out residual is dropped while it lies
more than trim_tau off, never below half of the list. Pairwise distances cannot tell a point from its
mirror image across a plane holding the other matches, so on a flat, self-similar table a 24-pair list can
carry one pair 40 cm off (plain Kabsch: 24 deg error, trimmed: 0.3); the depth-grown eta lets a background
pair 36 cm off join a whole-frame list; one distant pair with a bad depth next to a clustered list tilts
plain Kabsch by 6 deg. The trimmed pairs are not inliers and do not count for rule 1.

Support check (GMatch only, `verify`): the longest list is not always the right one. On object pixels
at a 60 deg view change a wrong 5-8 pair list that happens to be consistent can outgrow the true lists
(noisy depth breaks eps_c on short true distances). The winner and up to `verify` other distinct lists
of the search (`lists_to_verify`: by length, cost, search order; >= `verify_min_len` pairs) are each
posed (kabsch_trimmed) and refined as below, but on the pairs with descriptor distance below
`support_eps_scale` (1.5) x eps_f: a true pair seen 60 deg apart has a RootSIFT distance of 0.8
(median over rendered pairs), beyond eps_f 0.6, so the GMatch candidates undercount a right pose's
support. The refined inlier count is the list's support. Another list replaces the winner only with
>= `verify_ratio` (1.5) times its support (`pose_by_support`); a list whose pose is within 2 deg / 1 cm
of one already checked is skipped. The chosen list's pose is that refinement's. Its inliers (what rule 2
and the pose graph weigh an edge by) are the candidates alone that agree with it (`consistent_pairs`):
on a repetitive table a wrong pose that maps the table plane onto itself collects hundreds of
look-alike pairs under the looser bound, and weighed by those, wrong edges outvoted right ones.
Measured on rendered pairs, object pixels, 60 deg (BENCHMARKS.md): newspaper / wood / fabric tables
67 / 76 / 76 % with the candidates alone, 71 / 86 / 86 % now; whole frames unchanged.
`verify=0` is the paper's pick alone.

Guided refinement (GMatch only, `refine`): GMatch stops at L (24) matches, and a pose from 24
points is limited by their depth noise. From the Kabsch pose, every pair with descriptor distance
< support_eps_scale x eps_f (eps_f, the candidates' bound, when that is 1) whose transformed source
point lies within tau of its target point is collected, made one-to-one by residual (each source its
closest target, then each target its closest source), and the pose re-solved by Kabsch on all of them;
tau shrinks over `refine_taus`.
A round that keeps fewer pairs than the GMatch list (trimmed pairs included) stops the refinement.
Measured on rendered captures: mean rotation error per edge 0.44 -> 0.28 deg (turntable, object
only) and 0.074 -> 0.029 deg (static object, whole frame).
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from gscan.features import FeatureParams, Features, descriptor_distances, extract_features
from gscan.geometry.icp import icp
from gscan.geometry.kabsch import kabsch, kabsch_trimmed
from gscan.geometry.transforms import inv_T, pose_error, transform_points
from gscan.io.camera import RGBDFrame, point_cloud
from gscan.matching.baselines import BASELINES, BaselineParams, run_baseline
from gscan.matching.gmatch import GMatchParams, GMatchResult, default_eps_f, gmatch

log = logging.getLogger(__name__)

METHODS = ("gmatch",) + BASELINES


@dataclass(frozen=True)
class RegisterParams:
    method: str = "gmatch"  # "gmatch" or a baseline name (gscan.matching.baselines.BASELINES)
    gmatch: GMatchParams = GMatchParams()  # matcher parameters (eps_f None -> default of the descriptor)
    baseline: BaselineParams = BaselineParams()  # fixed baseline parameters
    min_matches: int = 6  # rule 1
    max_kabsch_rmse: float = 0.01  # rule 2 (m)
    refine: bool = True  # guided refinement of the GMatch pose (module docstring); gmatch only
    refine_taus: tuple[float, ...] = (0.008, 0.004, 0.003)  # its inlier distances per round (m)
    trim_tau: float = 0.008  # GMatch list pairs off by more are trimmed from the pose (kabsch_trimmed, m)
    verify: int = 16  # other GMatch lists whose support is compared with the winner's (0: the paper's pick alone)
    verify_min_len: int = 4  # ... of at least this many pairs
    verify_ratio: float = 1.5  # ... one replaces the winner only with this many times its support
    support_eps_scale: float = 1.5  # ... support counted on pairs with descriptor distance < this x eps_f
    # refine by point-to-plane ICP when clouds are given; off by default: on textured planar scenes and
    # on the real Open3D pairs ICP slid away from the match pose (8.5 vs 0.34 mm ATE on the sample)
    icp: bool = False
    icp_max_dist: float = 0.01  # ICP correspondence distance (m)
    icp_voxel: float = 0.004  # ICP voxel downsampling (m), 0 = none
    icp_iterations: int = 30
    min_fitness: float = 0.3  # rule 3
    max_rmse: float = 0.006  # rule 3 (m)
    max_icp_shift_deg: float = 5.0  # rule 3
    max_icp_shift_m: float = 0.02  # rule 3 (m)

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"unknown registration method {self.method!r}; expected one of {METHODS}")
        if self.min_matches < 3:
            raise ValueError("min_matches must be >= 3")
        if self.verify < 0 or self.verify_min_len < 3 or self.verify_ratio < 1 or self.support_eps_scale < 1:
            raise ValueError("need verify >= 0, verify_min_len >= 3, verify_ratio >= 1 and support_eps_scale >= 1")


@dataclass
class PairResult:
    T_tgt_src: np.ndarray | None  # [4 x 4]; None when fewer than 3 matches
    matches: np.ndarray  # [M x 2] int32 (source keypoint, target keypoint)
    cost: float  # GMatch list cost; for baselines the Kabsch RMSE (m)
    n_matches: int
    rmse: float | None  # ICP inlier RMSE (m) when ICP ran, else the Kabsch RMSE over the matches
    fitness: float | None  # ICP fitness, None without ICP
    accepted: bool
    reason: str | None  # None when accepted, else the first failed rule (module docstring)
    method: str = "gmatch"
    T_match: np.ndarray | None = None  # [4 x 4] pose from the matches alone (before ICP)
    inliers: np.ndarray | None = None  # [K x 2] int32 correspondences the pose was solved from (refined)
    timings_ms: dict[str, float] = field(default_factory=dict)


def _kabsch_rmse(pts_s: np.ndarray, pts_t: np.ndarray, T: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((transform_points(T, pts_s) - pts_t) ** 2, axis=1))))


class GuidedPool:
    """Keypoint pairs with descriptor distance below `eps`, looked up near a pose (a k-d tree of the target
    points): what guided refinement (eps = eps_f, GMatch's candidates) and the support check (a looser
    bound: under a pose, geometry does the filtering) may use.

    pts_t [Nt x 3] target points, dist [Ns x Nt] descriptor distances.
    """

    def __init__(self, pts_t: np.ndarray, dist: np.ndarray, eps: float):
        from scipy.spatial import cKDTree

        self.pts_t = np.asarray(pts_t, np.float64)
        self.dist = dist
        self.eps = float(eps)
        self._tree = cKDTree(self.pts_t) if len(self.pts_t) else None

    def near(self, pts_s_in_t: np.ndarray, tau: float) -> tuple[np.ndarray, np.ndarray]:
        """(source indices [K], target indices [K]) int64 of the pool's pairs whose source point, given in the
        target frame ([Ns x 3]), lies within tau of the target point; in (source, target) order."""
        if self._tree is None or len(pts_s_in_t) == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        hits = self._tree.query_ball_point(pts_s_in_t, tau, return_sorted=True)
        ii = np.repeat(np.arange(len(hits)), [len(h) for h in hits]).astype(np.int64)
        jj = np.fromiter((j for h in hits for j in h), np.int64, count=len(ii))
        ok = self.dist[ii, jj] < self.eps
        return ii[ok], jj[ok]


def refine_pose(pts_s: np.ndarray, pts_t: np.ndarray, pool: GuidedPool, T: np.ndarray, taus: tuple[float, ...],
                min_pairs: int) -> tuple[np.ndarray, np.ndarray]:
    """Guided refinement (module docstring): (T_tgt_src [4 x 4], inliers [K x 2] int32).

    pts_s [Ns x 3], pts_t [Nt x 3], pool the pairs it may use, T the starting pose.
    Returns the input pose and an empty inlier set when no round keeps `min_pairs` pairs.
    """
    ps, pt = np.asarray(pts_s, np.float64), np.asarray(pts_t, np.float64)
    # pairs far from consistent under the starting pose never come back: keep the loosest band
    q = transform_points(T, ps)
    ii, jj = pool.near(q, max(taus))
    r = np.linalg.norm(q[ii] - pt[jj], axis=1)
    best = np.zeros((0, 2), np.int32)
    for tau in taus:
        ok = _one_to_one(ii, jj, r, tau)
        if len(ok) < min_pairs:
            break
        best = np.stack([ii[ok], jj[ok]], axis=1).astype(np.int32)
        T = kabsch(ps[best[:, 0]], pt[best[:, 1]])
        r = np.linalg.norm(transform_points(T, ps[ii]) - pt[jj], axis=1)
    return T, best


def consistent_pairs(pts_s: np.ndarray, pts_t: np.ndarray, pool: GuidedPool, T: np.ndarray, tau: float) -> np.ndarray:
    """[K x 2] int32 pairs of `pool` (source, target) within tau of each other under T_tgt_src, one-to-one."""
    ps, pt = np.asarray(pts_s, np.float64), np.asarray(pts_t, np.float64)
    q = transform_points(T, ps)
    ii, jj = pool.near(q, tau)
    ok = _one_to_one(ii, jj, np.linalg.norm(q[ii] - pt[jj], axis=1), tau)
    return np.stack([ii[ok], jj[ok]], axis=1).astype(np.int32)


def _one_to_one(ii: np.ndarray, jj: np.ndarray, r: np.ndarray, tau: float) -> np.ndarray:
    """Indices of the pairs (ii, jj) with residual r < tau kept one-to-one: each source its closest target,
    then each target its closest source (ties by index: deterministic)."""
    ok = np.flatnonzero(r < tau)
    ok = ok[np.lexsort((jj[ok], ii[ok], r[ok]))]
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
                    lists: list[np.ndarray], params: RegisterParams) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
    """(index of the chosen list, T_tgt_src [4 x 4], its kept pairs [K x 2], its refined inliers [R x 2] or empty).

    Each list's pose (kabsch_trimmed) is refined by `refine_pose` on `support_pool`; its support is the refined
    inlier count (the kept pairs when no round reached the list's length). lists[0] (GMatch's pick) is replaced
    by the best supported other list (first on ties) only if that has at least `verify_ratio` times its support.
    A list whose pairs all lie within trim_tau under a pose already checked, or whose pose lies within 2 deg /
    1 cm of one, is skipped (it would refine to the same). Supports of lists of different lengths compare as
    they are: a list's refinement must keep at least its own length, else its support is its kept pairs.
    With params.refine, T is the chosen list's pose refined on `support_pool`, and the returned inliers are
    the `refine_pool` pairs consistent with it within the last refinement radius (empty, as when no round
    kept the list's length, if they are fewer than the list); else T is the list's own pose.
    """
    if not lists:
        raise ValueError("pose_by_support needs at least GMatch's own list")
    best, verified = None, []
    for k, m in enumerate(lists):
        src, dst = pts_s[m[:, 0]], pts_t[m[:, 1]]
        if any(np.linalg.norm(transform_points(V, src) - dst, axis=1).max() < params.trim_tau for V in verified):
            continue  # every pair agrees with a pose already checked
        T, keep = kabsch_trimmed(src, dst, params.trim_tau)
        if any(e[0] < _SAME_POSE_DEG and e[1] < _SAME_POSE_M for e in (pose_error(T, V) for V in verified)):
            continue
        verified.append(T)
        if len(lists) == 1 and not params.refine:  # nothing to compare, nothing to refine
            return 0, T, m[keep], np.zeros((0, 2), np.int32)
        T_ref, refined = refine_pose(pts_s, pts_t, support_pool, T, params.refine_taus, len(m))
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
    inliers = consistent_pairs(pts_s, pts_t, refine_pool, T_ref, params.refine_taus[-1])
    return k, T_ref, lists[k][keep], (inliers if len(inliers) >= len(lists[k]) else np.zeros((0, 2), np.int32))


def register_points(pts_s: np.ndarray, pts_t: np.ndarray, desc_s: np.ndarray, desc_t: np.ndarray, kind: str,
                    params: RegisterParams = RegisterParams(), clouds: tuple | None = None) -> PairResult:
    """Register camera-frame keypoints pts_s [Ns x 3] -> pts_t [Nt x 3] (descriptors [N x D] of `kind`).

    clouds: optional (src [P x 3], tgt [Q x 3]) camera-frame clouds for ICP.
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
        k, T, kept, refined = pose_by_support(ps, pt, support_pool, refine_pool, lists, params)
        if k:
            log.debug("register: hypothesis list %d (%d pairs) outsupports GMatch's (%d pairs)", k, len(lists[k]), n)
            matches, n, cost = lists[k], len(lists[k]), costs[k]
        n_kept = len(kept)
        inliers = refined if params.refine and len(refined) else kept
    elif T is None:
        T = kabsch(ps[matches[:, 0]], pt[matches[:, 1]])
    krmse = _kabsch_rmse(ps[inliers[:, 0]], pt[inliers[:, 1]], T) if T is not None else float("inf")
    if params.method != "gmatch":
        cost = krmse
    out = PairResult(T, matches, float(cost), n, krmse if n >= 3 else None, None, False, None, params.method,
                     T_match=None if T is None else T.copy(), inliers=inliers, timings_ms=tm)
    if n_kept < params.min_matches:
        out.reason = f"too few matches ({n_kept} < {params.min_matches})"
        return out
    if krmse > params.max_kabsch_rmse:
        out.reason = f"kabsch residual ({krmse:.4f} m > {params.max_kabsch_rmse} m)"
        return out
    if params.icp and clouds is not None and clouds[0] is not None and clouds[1] is not None:
        t0 = time.perf_counter()
        r = icp(clouds[0], clouds[1], T, params.icp_max_dist, params.icp_voxel, params.icp_iterations, True)
        tm["icp"] = (time.perf_counter() - t0) * 1e3
        out.fitness, out.rmse = r.fitness, r.rmse
        deg, m = pose_error(r.T, T)
        if r.fitness < params.min_fitness:
            out.reason = f"icp fitness ({r.fitness:.2f} < {params.min_fitness})"
        elif r.rmse > params.max_rmse:
            out.reason = f"icp rmse ({r.rmse:.4f} m > {params.max_rmse} m)"
        elif deg > params.max_icp_shift_deg or m > params.max_icp_shift_m:
            out.reason = f"icp shift ({deg:.1f} deg, {m:.3f} m)"
        else:
            out.T_tgt_src = r.T
            out.accepted = True
        return out
    out.accepted = True
    return out


def register_features(fs: Features, ft: Features, params: RegisterParams = RegisterParams(),
                      clouds: tuple[np.ndarray | None, np.ndarray | None] | None = None) -> PairResult:
    """Register the keypoints of two frames (camera-frame points, viewed along +z): match, Kabsch, optional ICP,
    verdict (module docstring).

    Args:
        fs, ft: the source and target frames' keypoints, of one descriptor kind.
        params: matcher, pose and acceptance parameters.
        clouds: (source [P x 3], target [Q x 3]) camera-frame clouds for ICP (used when params.icp).

    Returns:
        PairResult: T_tgt_src [4 x 4] (source camera -> target camera) or None, the matches [M x 2] (source,
        target keypoint indices), the inliers the pose rests on [K x 2], quality numbers, and the verdict
        (`accepted`, `reason`).
    """
    if fs.kind != ft.kind:
        raise ValueError(f"descriptor kinds differ: {fs.kind} vs {ft.kind}")
    return register_points(fs.points, ft.points, fs.descriptors, ft.descriptors, fs.kind, params, clouds)


def frame_cloud(frame: RGBDFrame, stride: int = 2, mask: np.ndarray | None = None) -> np.ndarray:
    """Camera-frame ICP cloud [P x 3] of an RGBDFrame (valid depth, every `stride`-th pixel, optional mask)."""
    return point_cloud(frame, mask, stride)[0]


def register_frames(frame_s: RGBDFrame, frame_t: RGBDFrame, params: RegisterParams = RegisterParams(), *,
                    feature_params: FeatureParams | None = None, use_masks: bool = False,
                    icp_stride: int = 2) -> PairResult:
    """Register two RGB-D frames: keypoints of both, then `register_features` (ICP on their clouds when
    params.icp).

    Args:
        frame_s, frame_t: the source and target frames.
        params: matcher, pose and acceptance parameters.
        feature_params: the keypoints extracted (default FeatureParams()).
        use_masks: keypoints and ICP clouds inside the frames' masks only (whole frames by default).
        icp_stride: pixel stride of the ICP clouds.

    Returns:
        PairResult as `register_features`; T_tgt_src [4 x 4] maps source-camera points into the target camera.
        timings_ms["features"] is the extraction time.
    """
    fp = feature_params if feature_params is not None else FeatureParams()
    ms = frame_s.mask if use_masks else None
    mt = frame_t.mask if use_masks else None
    t0 = time.perf_counter()
    fs = extract_features(frame_s, fp, mask=ms)
    ft = extract_features(frame_t, fp, mask=mt)
    t_feat = (time.perf_counter() - t0) * 1e3
    clouds = (frame_cloud(frame_s, icp_stride, ms), frame_cloud(frame_t, icp_stride, mt)) if params.icp else None
    out = register_features(fs, ft, params, clouds)
    out.timings_ms["features"] = t_feat
    return out


def relative_pose(T_world_cam_s: np.ndarray, T_world_cam_t: np.ndarray) -> np.ndarray:
    """Ground-truth T_tgt_src from two camera poses: inv(T_world_cam_t) @ T_world_cam_s."""
    return inv_T(T_world_cam_t) @ T_world_cam_s
