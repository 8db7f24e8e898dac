"""Does the depth line up with the colour under the given intrinsics? The colour camera's focal length, from the data.

Many RGB-D captures record colour and depth with two cameras. A folder that holds one set of intrinsics says
the depth is registered to the colour; when it is not (7-Scenes gives one focal length, 585 px, for a depth
camera of 585 px and a colour camera of about 525 px), every keypoint is lifted with the depth of another
pixel and a ray of the wrong angle. The frames' geometry bends by about 10 %, and whole stretches of a scan
are registered wrongly while each edge looks fine.

The texture tells (gscan.registration.colour): under a right pose and a right camera model, a frame's
texture, carried through its depth into a neighbouring frame, lands on the same texture there. The check
treats the given intrinsics as the depth camera's and tries colour cameras of focal length s times the
given one (same principal point, no baseline: a baseline of a few centimetres shifts every point alike and
is absorbed by the poses and the colour check's shift search). For each s, pairs of frames one and two apart
are registered with the scan's own rules, and each pair's share of textured tiles lining up is averaged over
the pairs (a pair that fails to register counts 0):
- s = 1 and its neighbours in `SCALES` first, on every other group: when s = 1 lines up the most and the verdict
  below keeps it, the given intrinsics stand;
- else a walk over `SCALES` on those groups, away from 1 towards the better neighbour, until two scales in a row
  line up no more than the best so far (registered texture has one peak; the far side of 1 lines up less than 1);
  then the best scale, `FIT` scales either side of it and s = 1 on every group, moving on while a neighbour lines
  up more there (the walk's groups may say little: their pairs may fail to register), and one scale further out
  on every group while the peak may lie beyond the scales tried;
- the estimate is the vertex of the least-squares parabola through the best scale and `FIT` scales either side
  (single evaluations are noisy to about 0.01-0.02 near the peak: the fit is the better figure), and its
  uncertainty the interval of that vertex over resamples of the pairs (a bootstrap, level 1 - alpha), widened by
  the fit's own error (`GRID_ERROR`);
- the verdict: "kept" when the interval holds 1 and is at most +-`max_uncertainty` wide; "corrected" when it
  excludes 1 (the given focal length is then the worse one, however wide the interval) and the best scale lines
  up more tiles than s = 1 significantly (Wilcoxon's signed-rank test over the pairs at level `alpha`: a pair a
  few tiles worse weighs little, a failed pair a lot) and by at least `min_gain` on average; otherwise "could
  not confirm", with the reason (too few pairs registered, a peak at the edge of the scales, an interval too
  wide, a preference not significant). A focal length it could not confirm is the given one, scanned with and
  reported as a warning (gscan.scanning.camera); so is one the depth's edges contradict
  (gscan.scanning.depth_edges).

With depth registered to the colour (a rendered capture, a RealSense aligned stream), any s other than 1
moves the depth off its colour pixels and the texture lines up best at 1. The pairs are registered over whole
frames, as a camera moving over a still scene is: before a static camera (a turntable) the check is not run
(gscan.scanning.camera).
"""
from __future__ import annotations

import logging
import threading
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace

import numpy as np

from gscan.features import Detection, FeatureParams, Features, detect, extract_features
from gscan.io.align import align_depth_to_color
from gscan.io.camera import DepthCamera, Intrinsics, RGBDFrame, lift_keypoints
from gscan.registration.dense import DenseGeometry, image_texture
from gscan.registration.pairwise import RegisterParams, register_features
from gscan.scanning.params import FocalCheckParams

log = logging.getLogger(__name__)

SCALES = (0.8, 0.85, 0.9, 0.95, 1.0, 1.05, 1.1, 1.15, 1.2)  # colour focal length / given: the grid the check walks
FIT = 2  # the vertex's parabola: the best scale and this many on each side (the texture's peak is about that wide)
WINDOW = FIT * 0.05  # ... the same as a difference of scales
# the parabola's own error: its vertex sits off a peak that is not a parabola by up to a quarter of the grid step
# (0.010 measured at a rendered capture's sharp peak, colour camera 1.12), added to each side of the interval
GRID_ERROR = 0.0125


KEPT, CORRECTED, UNCONFIRMED = "kept", "corrected", "could not confirm"


@dataclass(frozen=True)
class FocalCheck:
    """scale: the colour camera's focal length over the given one the scan uses (1.0 unless corrected); estimate:
    the one the texture lines up best at (the parabola's vertex; NaN when no pair registered) and low, high: its
    interval at level 1 - alpha (a bootstrap over the pairs, widened by GRID_ERROR; -inf / inf where the texture's
    peak lies at or beyond the scales tried in more than alpha / 2 of the resamples); verdict: KEPT (1 lies in the
    interval, which is narrow), CORRECTED (the interval excludes 1, and the pairs line up significantly better)
    or UNCONFIRMED, with `reason`; agreement: mean share of textured tiles lining up, per scale tried (over the
    pairs tried at that scale); peak: the share at `estimate`; pairs: frame pairs compared; better_pairs: pairs
    lining up more tiles at the best scale tried than at 1; p_value: the signed-rank test's; significant: the data
    reject the given intrinsics for the colour camera (verdict CORRECTED)."""

    scale: float
    agreement: dict[float, float]
    pairs: int
    better_pairs: int
    p_value: float
    significant: bool
    peak: float
    estimate: float = float("nan")
    low: float = -float("inf")
    high: float = float("inf")
    verdict: str = UNCONFIRMED
    reason: str | None = None

    @classmethod
    def not_confirmed(cls, reason: str, agreement: dict[float, float] | None = None, pairs: int = 0) -> FocalCheck:
        """A check that could not confirm the given focal length (kept: scale 1) for `reason`; agreement: each
        scale's mean share tried, pairs: the frame pairs compared."""
        agreement = dict(sorted((agreement or {}).items()))
        return cls(1.0, agreement, pairs, 0, 1.0, False, agreement.get(1.0, float("nan")), reason=reason)

    @property
    def confirmed(self) -> bool:
        """The focal length the scan uses is the one the data give (kept or corrected)."""
        return self.verdict != UNCONFIRMED

    def colour_intrinsics(self, given: Intrinsics) -> Intrinsics:
        """The colour camera's intrinsics: the given ones with the focal length scaled."""
        return replace(given, fx=given.fx * self.scale, fy=given.fy * self.scale)


def _keypoints(frame: RGBDFrame, fparams: FeatureParams, detection: Detection | None) -> Features:
    """Frame's keypoints and descriptors before lifting (pixels, descriptors; points meaningless), from
    `detection` when given (the same colour image)."""
    flat = RGBDFrame(frame.name, frame.color, np.ones_like(frame.depth), frame.intrinsics)
    return extract_features(flat, replace(fparams, lift_window=0), detection=detection)


def _geometry(f: RGBDFrame, kp: Features, s: float, fparams: FeatureParams, texture: tuple[np.ndarray, float]
              ) -> tuple[Features, DenseGeometry]:
    """Frame f read with a colour camera of s times its focal length (its depth reprojected into it): its
    keypoints kp lifted there, and its dense geometry with texture (f's `image_texture`, the same at every s)."""
    K = f.intrinsics
    Kc = replace(K, fx=K.fx * s, fy=K.fy * s)
    depth = f.depth if s == 1.0 else align_depth_to_color(f.depth, DepthCamera(K), Kc)
    pts, ok = lift_keypoints(kp.pixels.astype(np.float64), depth, Kc, fparams.lift_window,
                             fparams.lift_max_rel_spread, fparams.lift_min_valid_frac)
    lifted = kp.subset(np.flatnonzero(ok))
    lifted.points = pts[ok].astype(np.float32)
    return lifted, DenseGeometry.from_depth(depth, Kc, image=f.color, texture=texture)


def _starts(n: int, span: int, count: int) -> list[int]:
    """At most `count` first frames of groups of span + 1 consecutive frames, spread evenly over n frames."""
    if n <= span:
        return []
    return [int(i) for i in np.unique(np.linspace(0, n - span - 1, min(count, n - span)).astype(int))]


def check_colour_focal(read: Callable[[int], RGBDFrame | None], n: int, params: RegisterParams,
                       fparams: FeatureParams, check: FocalCheckParams = FocalCheckParams(),
                       workers: int = 1, detections: dict[str, Detection] | None = None) -> FocalCheck:
    """The check of the module docstring on a capture of n frames, frame i read by read(i) (None: unusable), its
    depth registered to its colour as given. Pairs (i, i + step) for each of `check.steps` (neighbours move
    little, the next ones more) from `check.groups` first frames i spread over the capture, every other group
    only while s = 1 and its neighbours are tried (registered depth peaks sharply at 1) and while the walk runs;
    each group's frames are read when its pairs are registered and let go after (a few frames in memory at a time;
    keypoints, at most `check.keypoints` a frame, are kept); `workers` groups at a time, on threads. detections:
    when given (SIFT kinds), each frame read is detected as `extract_features(frame, fparams)` detects it
    (`detect`), its keypoints taken from that, and the detection left there by frame name, for the scan's features
    stage to start from (one detection of those frames, not two). The verdict UNCONFIRMED, with its reason, when
    fewer than 4 pairs register at the scales tried (or no pair can be formed)."""
    steps = check.steps
    starts = _starts(n, max(steps), check.groups)
    pairs = [(i, i + step) for i in starts for step in steps]
    keep_detections = detections is not None and fparams.kind != "orb"
    scan_fparams = fparams
    fparams = replace(fparams, max_keypoints=min(fparams.max_keypoints, check.keypoints))
    kps: dict[int, Features] = {}
    claimed: dict[int, threading.Event] = {}  # frames a thread is detecting or has detected (set when done)
    claim_lock = threading.Lock()
    failed: dict[int, Exception] = {}  # frames whose detection raised, with its error
    unusable: set[int] = set()
    per_pair: dict[float, np.ndarray] = {}  # scale -> each pair's share of textured tiles lining up (0: failed,
    ran: dict[float, np.ndarray] = {}  # NaN: not tried); scale -> the pairs whose colour check ran

    def keypoints(j: int, f: RGBDFrame) -> None:
        """kps[j], detected once: a frame two groups hold is detected by the first thread to reach it (a thread
        waiting for it raises the error the detection raised)."""
        with claim_lock:
            done = claimed.get(j)
            if done is None:
                claimed[j] = threading.Event()
        if done is not None:
            done.wait()
            if j in failed:
                raise failed[j]
            return
        try:
            det = detect(f, scan_fparams) if keep_detections else None
            kps[j] = _keypoints(f, fparams, det)
            if det is not None and detections is not None:
                detections[f.name] = det
        except Exception as e:
            failed[j] = e
            raise
        finally:
            claimed[j].set()

    def evaluate(scales: tuple[float, ...] | list[float], groups: list[int]) -> None:
        """The pairs of `groups` registered at each scale with the scan's rules, and their texture compared under
        that pose (a pose re-solved from one scale's matches is not precise enough: the peak moves by 5 %)."""
        for s in scales:
            per_pair.setdefault(s, np.full(len(pairs), np.nan))
            ran.setdefault(s, np.zeros(len(pairs), bool))
        def group(i: int) -> None:
            todo = [(k, s) for s in scales for k, (a, _) in enumerate(pairs) if a == i and np.isnan(per_pair[s][k])]
            if not todo:
                return
            frames = {}
            for j in range(i, i + max(steps) + 1):
                f = None if j in unusable else read(j)
                if f is None:
                    unusable.add(j)
                    continue
                frames[j] = f
                keypoints(j, f)
            textures = {j: image_texture(f.color) for j, f in frames.items()}
            for s in sorted({s for _, s in todo}):
                geo = {j: _geometry(f, kps[j], s, fparams, textures[j]) for j, f in frames.items()}
                for k, s_k in todo:
                    if s_k != s:
                        continue
                    a, b = pairs[k]
                    per_pair[s][k] = 0.0
                    if a in geo and b in geo:
                        (fa, da), (fb, db) = geo[a], geo[b]
                        c = register_features(fa, fb, params, dense=(da, db)).colour
                        if c is not None and c.informative >= params.min_colour_tiles:
                            per_pair[s][k], ran[s][k] = c.agreeing_fraction, True

        # groups share no pair (each result lands in its own slot): the same values in any order
        with ThreadPoolExecutor(max_workers=max(1, workers)) as pool:
            list(pool.map(group, groups))

    def means(tried: np.ndarray) -> tuple[np.ndarray, dict[float, float]]:
        """The live pairs (among `tried`, registered at some scale) and each scale's mean share over those of
        them tried at that scale."""
        live = tried & np.logical_or.reduce(list(ran.values()))
        out = {}
        for s, v in per_pair.items():
            at = live & ~np.isnan(v)
            out[s] = float(v[at].mean()) if at.any() else 0.0
        return live, out

    if not pairs:
        return FocalCheck.not_confirmed(f"too few frames ({n}) to register pairs {max(steps)} apart")
    one = SCALES.index(1.0)
    near = SCALES[one - 1:one + 2]
    walk = starts[::2]  # the groups the walk seeks the texture's peak on
    evaluate(near, walk)
    tried = ~np.isnan(per_pair[1.0])
    live, mean = means(tried)
    if live.sum() >= 4 and mean[1.0] >= max(mean.values()):  # the texture peaks at the given focal length
        first = _verdict(per_pair, live, check, mean)
        if first.verdict == KEPT:
            return first
    # towards the better neighbour (no walk when no pair registered on the walk's groups: the step below decides)
    step = 1 if mean[SCALES[one + 1]] > mean[SCALES[one - 1]] else -1
    walked = [one + step]

    def best_of(indices: Iterable[int]) -> int:
        return max(indices, key=lambda i: (mean[SCALES[i]], -abs(i - one)))  # ties: the nearer to 1

    while live.any() and abs(walked[-1] - best_of(walked)) < 2 and 0 <= walked[-1] + step < len(SCALES):
        walked.append(walked[-1] + step)
        evaluate([SCALES[walked[-1]]], walk)
        live, mean = means(tried)
    k = best_of([*walked, one])
    while True:  # the best and its neighbours on every group; a neighbour better there becomes the best
        evaluate(sorted({1.0, *SCALES[max(0, k - FIT):k + FIT + 1]}), starts)
        live, mean = means(np.ones(len(pairs), bool))
        top = best_of(range(max(0, k - 1), min(len(SCALES), k + 2)))
        if top == k:
            break
        k = top
    for s in sorted(mean):
        log.debug("colour focal x%.3f: %.3f of the textured tiles line up", s, mean[s])
    if live.sum() < 4:
        return FocalCheck.not_confirmed(
            f"{int(live.sum())} frame pairs registered at the focal lengths tried (at least 4 needed)", mean,
            int(live.sum()))
    while True:  # the next scale out on every group while the peak may lie beyond the scales tried on all of them
        got = _verdict(per_pair, live, check, mean)
        on_all = [i for i, s in enumerate(SCALES) if s in per_pair and not np.isnan(per_pair[s][live]).any()]
        beyond = on_all[0] - 1 if got.low == -np.inf else on_all[-1] + 1 if got.high == np.inf else -1
        if not 0 <= beyond < len(SCALES):
            return got
        evaluate([SCALES[beyond]], starts)
        live, mean = means(np.ones(len(pairs), bool))


def _signed_rank(d: np.ndarray) -> float:
    """One-sided p-value of Wilcoxon's signed-rank test that the pairs' differences d [n] lean positive (1 when none
    differs): a pair lining up a few tiles fewer is weighed as the little it is, a failed pair as the lot."""
    from scipy.stats import wilcoxon

    if not np.any(d != 0):
        return 1.0
    return float(wilcoxon(d, alternative="greater", zero_method="wilcox").pvalue)


def _vertex(x: np.ndarray, y: np.ndarray, halfwidth: float) -> float:
    """The abscissa of the peak of y over x [m] (sorted): the vertex of the least-squares parabola through the
    points within `halfwidth` of the best one (a single scale's mean is noisy to about 0.01-0.02: more points
    steady the vertex), kept within them; -inf / inf when the best is the first / last (the peak may lie beyond)."""
    k = int(np.argmax(y))
    if k == 0:
        return -np.inf
    if k == len(x) - 1:
        return np.inf
    near = np.abs(x - x[k]) <= halfwidth + 1e-9
    xs, ys = x[near], y[near]
    fit = np.polyfit(xs, ys, 2)
    if fit[0] >= 0:  # no curvature: the best one
        return float(x[k])
    return float(np.clip(-fit[1] / (2 * fit[0]), xs[0], xs[-1]))


def _verdict(per_pair: dict[float, np.ndarray], live: np.ndarray, check: FocalCheckParams,
             agreement: dict[float, float]) -> FocalCheck:
    """The estimate, its interval and the verdict (FocalCheck) from each live pair's share at each scale tried on
    all of them (agreement: every scale's mean share, `FocalCheck.agreement`). The interval: the vertex (`_vertex`)
    over `check.bootstrap` resamples of the pairs (a fixed seed: the same figures every run), its alpha / 2 and
    1 - alpha / 2 quantiles."""
    scales = np.array(sorted(s for s, v in per_pair.items() if not np.isnan(v[live]).any()))
    M = np.stack([per_pair[s][live] for s in scales], axis=1)  # pairs x scales
    mean = {float(s): float(m) for s, m in zip(scales, M.mean(axis=0), strict=True)}
    n = len(M)
    estimate = _vertex(scales, M.mean(axis=0), WINDOW)
    rng = np.random.default_rng(0)
    boot = np.array([_vertex(scales, M[rng.integers(0, n, n)].mean(axis=0), WINDOW)
                     for _ in range(check.bootstrap)])
    boot.sort()  # (with -inf / inf: no interpolation between resamples)
    B = len(boot)
    low, high = float(boot[int(np.floor(check.alpha / 2 * B))]), \
        float(boot[int(np.ceil((1 - check.alpha / 2) * B) - 1)])
    k = int(np.argmax(M.mean(axis=0)))
    best = float(scales[k])
    d = M[:, k] - M[:, list(scales).index(1.0)]
    better, worse = int(np.sum(d > 0)), int(np.sum(d < 0))
    p = _signed_rank(d)
    peak = mean[best]
    if np.isfinite(estimate):  # the parabola's value at its vertex
        near = np.abs(scales - best) <= WINDOW + 1e-9
        fit = np.polyfit(scales[near], M.mean(axis=0)[near], 2)
        peak = float(np.polyval(fit, estimate)) if fit[0] < 0 else peak
    for s, v in zip(scales, M.T, strict=True):
        log.debug("colour focal x%.2f, each pair's share: %s", s, np.round(v, 3).tolist())
    low, high = low - GRID_ERROR, high + GRID_ERROR
    half = (high - low) / 2
    tried = ", ".join(f"{s:g}" for s in scales)
    if not np.isfinite(half):
        verdict, why = UNCONFIRMED, (f"the texture of {n} frame pairs peaks at or beyond the edge of the focal lengths "
                                     f"tried (x{tried} the given) in more than {check.alpha / 2:.1%} of resamples")
    elif low <= 1.0 <= high and half <= check.max_uncertainty:
        verdict, why = KEPT, None
    elif low <= 1.0 <= high:
        verdict, why = UNCONFIRMED, (f"the texture of {n} frame pairs lines up about as well over x{low:.3f}-"
                                     f"x{high:.3f} the given focal length (wider than +-{check.max_uncertainty:.0%})")
    elif p < check.alpha and peak - mean[1.0] >= check.min_gain:
        verdict, why = CORRECTED, None
    else:
        verdict, why = UNCONFIRMED, (f"the texture lines up best at x{estimate:.3f} the given focal length but not "
                                     f"significantly better than at the given one ({better} pairs better, {worse} "
                                     f"worse, p = {p:.3f}; a gain of {peak - mean[1.0]:.3f})")
    corrected = verdict == CORRECTED
    log.debug("colour focal: x%.3f [%.3f, %.3f] from %d pairs: %s", estimate, low, high, n, verdict)
    return FocalCheck(round(estimate, 4) if corrected else 1.0, dict(sorted(agreement.items())), n, better, p,
                      corrected, peak if corrected else mean[1.0], estimate=round(estimate, 4), low=round(low, 4),
                      high=round(high, 4), verdict=verdict, reason=why)
