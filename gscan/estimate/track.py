"""Tracking an object through an RGB-D sequence, the previous pose as a prior.

Per frame (`Tracker.step`):

1. local refinement, when the previous frame had a pose: the pose is predicted (the previous one, moved by
   the last frame-to-frame motion when the two frames before both had poses) and refined by ICP coarse to
   fine (`icp_max_dists`) on the depth around it. Every `appearance_every`-th tracked frame, and whenever
   ICP moved the prediction by more than `max_icp_shift` / `max_icp_turn_deg` or the depth no longer agrees,
   the appearance is checked too: keypoints are detected only in the predicted silhouette's bounding box
   (grown by `bbox_margin`), each is matched to the template keypoint with the most similar descriptor among
   those predicted within `search_radius` of it, the pairs give a trimmed Kabsch pose, ICP refines it with
   the pairs as anchors, and the result must pass the same acceptance as a full estimate (depth agreement,
   keypoint support, gscan.estimate.verify). In every tracked frame the depth score must not drop more than
   `max_score_drop` below the last full estimate's, and the pose must satisfy the depth rules of a full
   estimate (score, confirmed surface): otherwise the prior no longer holds.
2. otherwise a full estimate (`Estimator.estimate`).

Each frame's status: "found" (a full estimate found it, the first time or right after a tracked frame whose
prior failed), "tracked" (the local refinement held), "lost" (no pose), "refound" (a full estimate found it
again after lost frames). No frame-wide work is done in a tracked frame: no plane fit, no full-frame
features or back-projection, no retrieval over the whole template.
"""
from __future__ import annotations

import json
import logging
import os
import shutil
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gscan.errors import InputError
from gscan.estimate.estimator import Estimator
from gscan.estimate.query import QueryFrame
from gscan.estimate.result import STAGES, EstimateResult, ms_since
from gscan.estimate.verify import Evidence, accept, depth_votes, list_spread, visible
from gscan.features import descriptor_distances, extract_features_in_mask
from gscan.geometry.kabsch import kabsch_trimmed
from gscan.geometry.pointset import coincident_groups
from gscan.geometry.transforms import inv_T, transform_points
from gscan.io.camera import RGBDFrame

log = logging.getLogger(__name__)

STATUSES = ("found", "tracked", "refound", "lost")


@dataclass(frozen=True)
class TrackParams:
    icp_max_dists: tuple[float, ...] = (0.02, 0.01, 0.005)  # m, ICP correspondence distances, coarse to fine
    icp_iterations: int = 6  # per distance
    bbox_margin: float = 0.15  # the predicted silhouette's bounding box grows by this fraction on every side
    search_radius: float = 0.03  # m, a keypoint is matched among template keypoints predicted this close
    max_score_drop: float = 0.15  # a local pose whose depth score falls this far below the last full one's fails
    constant_velocity: bool = True  # predict with the last frame-to-frame motion
    appearance_every: int = 3  # keypoints checked in every n-th tracked frame (1: every frame)
    max_icp_shift: float = 0.01  # m: ICP moving the prediction further checks the keypoints in that frame ...
    max_icp_turn_deg: float = 5.0  # ... as does turning it further
    icp_max_points: int = 800  # template points ICP uses (evenly subsampled)


@dataclass
class TrackStep:
    """One frame of a track: its name, status (STATUSES) and the estimate (method "track" when refined
    locally)."""

    frame: str
    status: str
    result: EstimateResult

    def to_json(self) -> dict:
        return {"frame": self.frame, "status": self.status, **self.result.to_json()}


class Tracker:
    """Frame-by-frame pose of one template's object (module docstring). Not thread-safe: one per stream."""

    def __init__(self, estimator: Estimator, params: TrackParams = TrackParams()):
        self.est = estimator
        self.params = params
        self.reset()

    def reset(self) -> None:
        """Forget the prior: the next frame gets a full estimate."""
        self._T: np.ndarray | None = None  # the last pose
        self._T_before: np.ndarray | None = None  # the pose before it (consecutive frames only)
        self._ref_score = 0.0  # the last full estimate's depth score
        self._lost = False  # frames were lost since the last pose
        self._seen = False  # a pose was ever found
        self._unchecked = 0  # tracked frames since the keypoints were last checked

    def skip(self) -> None:
        """A frame that could not be read: the motion model restarts (the prior pose is kept)."""
        self._T_before = None

    def step(self, frame: RGBDFrame, mask: np.ndarray | None = None) -> TrackStep:
        """The object's pose in `frame` (mask: optional [H x W] bool search region)."""
        frame = self.est.as_scanned(frame)
        res = None
        if self._T is not None:
            T_pred = self._T
            if self.params.constant_velocity and self._T_before is not None:
                T_pred = self._T @ inv_T(self._T_before) @ self._T
            res = self._local(frame, mask, T_pred)
        if res is not None:
            status = "tracked"
        else:
            res = self.est.estimate(frame, mask=mask)
            status = "lost" if res.T_cam_obj is None else ("refound" if self._lost and self._seen else "found")
            if res.T_cam_obj is not None:
                self._ref_score = res.score
                self._unchecked = 0
        if res.T_cam_obj is None:
            self._T = self._T_before = None
            self._lost = True
        else:
            self._T_before = self._T
            self._T = res.T_cam_obj
            self._lost, self._seen = False, True
        return TrackStep(frame.name, status, res)

    def _local(self, frame: RGBDFrame, mask: np.ndarray | None, T_pred: np.ndarray) -> EstimateResult | None:
        """The local refinement from the predicted pose (module docstring), or None when the prior does not
        hold."""
        est, p = self.est, self.params
        with est._blas_limit():
            if self._unchecked + 1 < p.appearance_every:
                res = self._depth_only(frame, mask, T_pred, est, p)
                if res is not None:
                    self._unchecked += 1
                    return res
            res = self._with_keypoints(frame, mask, T_pred, est, p)
            if res is not None:
                self._unchecked = 0
            return res

    def _depth_only(self, frame: RGBDFrame, mask: np.ndarray | None, T_pred: np.ndarray, est: Estimator,
                    p: TrackParams) -> EstimateResult | None:
        """ICP from the prediction and the depth rules alone; None when ICP had to move the prediction far (the
        keypoints decide then) or the depth does not agree."""
        t_all = time.perf_counter()
        tm = dict.fromkeys(STAGES, 0.0)
        q = QueryFrame(frame, mask, 1.0)
        T = est.refine(q, T_pred, None, None, p.icp_max_dists, p.icp_max_points)
        dR = T[:3, :3] @ T_pred[:3, :3].T
        turn = np.degrees(np.arccos(np.clip(0.5 * (np.trace(dR) - 1.0), -1.0, 1.0)))
        if np.linalg.norm(T[:3, 3] - T_pred[:3, 3]) > p.max_icp_shift or turn > p.max_icp_turn_deg:
            return None
        n_c, n_b, n = depth_votes(frame.depth, frame.intrinsics, T, est.cloud_icp, est.params.depth_tol)
        score, confirmed = n_c / max(1, n_c + n_b), n_c / max(1, n)
        a = est.params.accept
        tm["refine"] = ms_since(t_all)
        if score < a.min_score or confirmed < a.min_confirmed or score < self._ref_score - p.max_score_drop:
            return None
        view = est.view_names[int(np.argmax(est.axes @ (T[:3, :3].T @ np.array([0.0, 0.0, 1.0]))))]
        return est._found(T, score, 0, view, tm, t_all, "track", Evidence(score=score, confirmed=confirmed))

    def _with_keypoints(self, frame: RGBDFrame, mask: np.ndarray | None, T_pred: np.ndarray, est: Estimator,
                        p: TrackParams) -> EstimateResult | None:
        t_all = time.perf_counter()
        tm = dict.fromkeys(STAGES, 0.0)
        intr = frame.intrinsics
        t = time.perf_counter()
        _, _, uv = visible(T_pred, intr, est.cloud_icp)
        if len(uv) < 30:
            log.debug("%s: the prior pose shows too little of the object", frame.name)
            return None
        lo, hi = uv.min(0), uv.max(0)
        grow = p.bbox_margin * (hi - lo) + 8
        x0, y0 = np.maximum(lo - grow, 0).astype(int)
        x1, y1 = np.minimum(hi + grow + 1, [intr.width, intr.height]).astype(int)
        region = np.zeros(frame.depth.shape, bool)
        region[y0:y1, x0:x1] = True
        if mask is not None:
            region &= mask
        feats = extract_features_in_mask(frame, region, est.params.features, est.params.crop_margin)
        tm["features"] = ms_since(t)
        if len(feats) < 3:
            log.debug("%s: too few keypoints around the prior pose", frame.name)
            return None
        t = time.perf_counter()
        kp_idx = est._offered_keypoints(T_pred)
        kp_idx = kp_idx[visible(T_pred, intr, est.points_obj[kp_idx])[0]]  # the side the prediction shows
        if est.unit:
            S = np.matmul(feats.descriptors, est.descriptors[kp_idx].T)
        else:
            S = descriptor_distances(feats.descriptors, est.descriptors[kp_idx], est.kind)
        tm["retrieval"] = ms_since(t)
        t = time.perf_counter()
        src, dst = self._pairs(feats.points.astype(np.float64), S, kp_idx, T_pred)
        tm["match"] = ms_since(t)
        t = time.perf_counter()
        T1, keep = T_pred, np.zeros(len(src), bool)
        if len(src) >= 3:
            T_k, keep = kabsch_trimmed(src, dst, est.params.trim_tau)
            if keep.sum() >= 3:
                T1 = T_k
        tm["solve"] = ms_since(t)
        t = time.perf_counter()
        q = QueryFrame(frame, mask, 1.0)
        anchors = (src[keep], dst[keep]) if keep.sum() >= 3 else None
        T2 = est.refine(q, T1, anchors, None, p.icp_max_dists, p.icp_max_points)
        order, starts = coincident_groups(feats.points)
        location = np.empty(len(feats), np.int64)
        location[order] = np.repeat(np.arange(len(starts)), np.diff(np.r_[starts, len(feats)]))
        ev = est.evidence(q, T2, feats, S, location, kp_idx, np.arange(len(kp_idx)))
        ev.n_matches = len(src)
        ev.n_inliers = int(keep.sum())
        ev.spread_m = list_spread(src[keep])
        tm["refine"] = ms_since(t)
        why = accept(ev, est.radius, est.params.accept)
        if why is None and ev.score < self._ref_score - p.max_score_drop:
            why = f"depth score dropped to {ev.score:.2f} from {self._ref_score:.2f}"
        if why is not None:
            log.debug("%s: the prior no longer holds: %s", frame.name, why)
            return None
        view = est.view_names[int(np.argmax(est.axes @ (T2[:3, :3].T @ np.array([0.0, 0.0, 1.0]))))]
        return est._found(T2, ev.score, ev.n_inliers, view, tm, t_all, "track", ev)

    def _pairs(self, q_pts: np.ndarray, S: np.ndarray, kp_idx: np.ndarray,
               T_pred: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Each query keypoint [M x 3] paired with the template keypoint (of kp_idx, descriptor similarities or
        distances S [M x K]) most similar to it among those predicted within search_radius at T_pred, when it
        agrees (support_dist): (object-frame points [P x 3], camera-frame points [P x 3])."""
        from scipy.spatial import cKDTree

        est = self.est
        kp_obj = est.points_obj[kp_idx]
        kp_cam = transform_points(T_pred, kp_obj)
        k = min(16, len(kp_cam))
        if k == 0:
            return np.zeros((0, 3)), np.zeros((0, 3))
        d, j = cKDTree(kp_cam).query(q_pts, k=k, distance_upper_bound=self.params.search_radius)
        d, j = d.reshape(len(q_pts), k), j.reshape(len(q_pts), k)
        near = np.isfinite(d)
        jj = np.where(near, j, 0)
        sim = np.take_along_axis(S, jj, axis=1) if est.unit else -np.take_along_axis(S, jj, axis=1)
        sim = np.where(near, sim, -np.inf)
        best = np.argmax(sim, axis=1)
        ok = sim[np.arange(len(q_pts)), best] >= est.support_sim
        rows = np.flatnonzero(ok)
        return kp_obj[jj[rows, best[rows]]], q_pts[rows]


# ------------------------------------------------------------------------------------------------ sequences


@dataclass
class TrackRun:
    """A tracked sequence: steps in frame order; problems {frame: reason} for frames that could not be read."""

    steps: list[TrackStep]
    problems: dict[str, str] = field(default_factory=dict)

    def names(self, status: str) -> list[str]:
        return [s.frame for s in self.steps if s.status == status]

    def to_json(self, output: Path | None = None) -> dict:
        """The `gscan track --json` object."""
        ms = np.array([s.result.timings_ms.get("total", 0.0) for s in self.steps]) if self.steps else np.zeros(1)
        return {"output": None if output is None else str(output), "frames": len(self.steps),
                "with_pose": sum(s.result.T_cam_obj is not None for s in self.steps),
                "status": {k: len(self.names(k)) for k in STATUSES},
                "lost": self.names("lost"), "refound": self.names("refound"),
                "unreadable": dict(self.problems),
                "timings_ms": {"median": float(np.median(ms)), "p90": float(np.percentile(ms, 90)),
                               "total": float(ms.sum())},
                "per_frame": [s.to_json() for s in self.steps]}


def track_sequence(estimator: Estimator, sequence, params: TrackParams = TrackParams(),
                   on_step: Callable[[TrackStep], None] | None = None) -> TrackRun:
    """Track the estimator's object through a `gscan.io.sequence.Sequence` (every readable frame in order;
    the sequence's masks are not used). Frames that cannot be read are recorded in `problems` and skipped."""
    tracker = Tracker(estimator, params)
    run = TrackRun([], dict(sequence.problems))
    for name in sequence.names:
        try:
            frame = sequence[name]
        except InputError as e:
            run.problems[name] = str(e)
            tracker.skip()
            continue
        step = tracker.step(frame)
        run.steps.append(step)
        if on_step is not None:
            on_step(step)
    return run


def pose_file_name(frame: str) -> str:
    """The file of a frame's pose: its name + .txt (FoundationPose's ob_in_cam layout)."""
    return f"{frame}.txt"


def write_poses(run: TrackRun, out: str | Path, force: bool = False) -> Path:
    """Write one T_cam_obj per frame with a pose (4x4 text, FoundationPose / BOP `ob_in_cam`, metres, named
    after the frame) and `summary.json` (TrackRun.to_json) into folder `out`. Frames without a pose get no
    file (the summary lists them lost). Written into a hidden temporary sibling and renamed into place, so
    `out` is never half-written; an existing non-empty `out` is refused without `force` (InputError)."""
    from gscan.io import check_output_path, missing_folders, remove_empty_folders

    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError(out, "exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not force:
        raise InputError(out, "exists and is not empty (pass --force to replace it)")
    check_output_path(out)
    made = missing_folders(out / "x")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        for s in run.steps:
            if s.result.T_cam_obj is not None:
                np.savetxt(tmp / pose_file_name(s.frame), s.result.T_cam_obj, fmt="%.10g")
        (tmp / "summary.json").write_text(json.dumps(run.to_json(out), indent=1) + "\n", encoding="utf-8")
        if out.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old.", dir=out.parent))
            os.replace(out, old / out.name)
            os.replace(tmp, out)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        remove_empty_folders(made)
        raise
    return out
