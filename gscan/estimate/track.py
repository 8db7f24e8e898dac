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

An object that looks the same under some turns (its template's symmetries in shape and texture,
gscan.estimate.symmetric) has several right poses in every frame: each frame's pose is the equivalent nearest the
previous pose (the prediction in a tracked frame, the last pose found before a full estimate), so the track never
flips between them; the first frame's is the estimator's rule's.

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
from typing import Annotated, Protocol

import numpy as np
from pydantic import Field

from gscan.errors import InputError
from gscan.estimate.estimator import Estimator
from gscan.estimate.hypotheses import query_keypoints
from gscan.estimate.query import QueryFrame, join_depth
from gscan.estimate.refine import refine_pose
from gscan.estimate.result import EstimateResult, found
from gscan.estimate.verify import Evidence, accept, depth_votes, list_spread, visible
from gscan.features import descriptor_distances, extract_features_in_mask
from gscan.features.keypoints import JOINT
from gscan.geometry.kabsch import kabsch_trimmed
from gscan.geometry.transforms import inv_T, transform_points
from gscan.io.camera import RGBDFrame
from gscan.progress import StageTimer
from gscan.settings import SETTINGS

log = logging.getLogger(__name__)

STATUSES = ("found", "tracked", "refound", "lost")


@dataclass(frozen=True)
class TrackParams:
    """Tracking's settings (module docstring); the refinement's others are the estimator's (`EstimateParams`)."""

    icp_max_dists: Annotated[tuple[float, ...], Field(description="m, ICP correspondence distances, coarse to fine",
                                                      min_length=1)] = (0.02, 0.01, 0.005)
    icp_iterations: Annotated[int, Field(description="not read: a tracked frame's ICP runs the estimator's "
                                         "refine.iterations per distance", ge=1)] = 6
    bbox_margin: Annotated[float, Field(description="the predicted silhouette's bounding box grows by this fraction "
                                        "on every side", ge=0)] = 0.15
    search_radius: Annotated[float, Field(description="m, a keypoint is matched among template keypoints predicted "
                                          "this close", gt=0)] = 0.03
    max_score_drop: Annotated[float, Field(description="a local pose whose depth score falls this far below the last "
                                           "full one's fails", ge=0, le=1)] = 0.15
    constant_velocity: Annotated[bool, Field(description="predict with the last frame-to-frame motion")] = True
    appearance_every: Annotated[int, Field(description="keypoints checked in every n-th tracked frame (1: every "
                                           "frame)", ge=1)] = 3
    max_icp_shift: Annotated[float, Field(description="m: ICP moving the prediction further checks the keypoints in "
                                          "that frame ...", ge=0)] = 0.01
    max_icp_turn_deg: Annotated[float, Field(description="... as does turning it further (deg)", ge=0)] = 5.0
    icp_max_points: Annotated[int, Field(description="template points ICP uses (evenly subsampled)", ge=10)] = 800
    search_every: Annotated[int, Field(description="every instance (--all): frames between searches for new "
                                       "instances while every known one is held (0: only when one is not)",
                                       ge=0)] = 10
    gate: Annotated[float, Field(description="every instance (--all): a pose found by a search takes the identity "
                                 "of an instance without a pose whose centre lies within this fraction of the "
                                 "object's diameter", gt=0)] = 0.5
    __pydantic_config__ = SETTINGS


@dataclass
class InstanceStep:
    """One instance in one frame of a track of every instance: its identity (1, 2, ... in the order first found),
    status (STATUSES) and estimate (not found when lost)."""

    id: int
    status: str
    result: EstimateResult

    def to_json(self) -> dict:
        return {"id": self.id, "status": self.status, **self.result.to_json()}


@dataclass
class TrackStep:
    """One frame of a track: its name, status (STATUSES) and the estimate (method "track" when refined
    locally). A track of every instance (`gscan.estimate.track_instances`) adds `instances`, every identity known
    so far by id, and `total_ms`, the frame's time; its status and estimate are then those of the first instance
    with a pose (lowest id), or lost."""

    frame: str
    status: str
    result: EstimateResult
    instances: list[InstanceStep] | None = None
    total_ms: float | None = None

    def to_json(self) -> dict:
        out = {"frame": self.frame, "status": self.status, **self.result.to_json()}
        if self.instances is not None:
            out["instances"] = [i.to_json() for i in self.instances]
            out["frame_ms"] = self.ms()
        return out

    def ms(self) -> float:
        """The frame's time in milliseconds."""
        return self.total_ms if self.total_ms is not None else float(self.result.timings_ms.get("total", 0.0))


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
        self._T_last: np.ndarray | None = None  # the last pose found, across lost frames (symmetric equivalents)
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
        T_pred = self.predicted()
        if T_pred is not None:
            res = self.local(frame, mask, T_pred)
        if res is not None:
            return TrackStep(frame.name, self.record(res, True), res)
        res = self.est.estimate(frame, mask=mask, near=self._T_last)
        return TrackStep(frame.name, self.record(res, False), res)

    def predicted(self) -> np.ndarray | None:
        """The pose [4 x 4] the next frame is refined from (the last one, moved by the last frame-to-frame motion
        when `constant_velocity`), or None when the last frame had no pose."""
        if self._T is None:
            return None
        if self.params.constant_velocity and self._T_before is not None:
            return self._T @ inv_T(self._T_before) @ self._T
        return self._T

    @property
    def last_pose(self) -> np.ndarray | None:
        """The last pose found [4 x 4], across lost frames (None before the first)."""
        return self._T_last

    def record(self, res: EstimateResult, local: bool) -> str:
        """Take `res` as this frame's estimate (local: the refinement from the prior held; otherwise a full
        estimate's, found or not) and return the frame's status (STATUSES)."""
        if local:
            status = "tracked"
        else:
            status = "lost" if res.T_cam_obj is None else ("refound" if self._lost and self._seen else "found")
            if res.T_cam_obj is not None:
                self._ref_score = res.score
                self._unchecked = 0
        if res.T_cam_obj is None:
            self._T = self._T_before = None
            self._lost = True
        else:
            self._T_before = self._T
            self._T = self._T_last = res.T_cam_obj
            self._lost, self._seen = False, True
        return status

    def local(self, frame: RGBDFrame, mask: np.ndarray | None, T_pred: np.ndarray) -> EstimateResult | None:
        """The local refinement from the predicted pose T_pred [4 x 4] in a frame already `as_scanned` (module
        docstring), or None when the prior does not hold; the pose is taken by `record`."""
        est, p = self.est, self.params
        with est.limit_threads():
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
        t0 = time.perf_counter()
        timer = StageTimer()
        with timer.stage("refine"):
            q = QueryFrame(frame, mask, 1.0)
            T = refine_pose(est.model, q, T_pred, None, None, est.params.refine, p.icp_max_dists, p.icp_max_points)
            dR = T[:3, :3] @ T_pred[:3, :3].T
            turn = np.degrees(np.arccos(np.clip(0.5 * (np.trace(dR) - 1.0), -1.0, 1.0)))
            if np.linalg.norm(T[:3, 3] - T_pred[:3, 3]) > p.max_icp_shift or turn > p.max_icp_turn_deg:
                return None
            n_c, n_b, n = depth_votes(frame.depth, frame.intrinsics, T, est.model.samples, est.params.verify.depth_tol)
            score, confirmed = n_c / max(1, n_c + n_b), n_c / max(1, n)
        a = est.params.accept
        if score < a.min_score or confirmed < a.min_confirmed or score < self._ref_score - p.max_score_drop:
            return None
        view = est.view_names[int(np.argmax(est.index.axes @ (T[:3, :3].T @ np.array([0.0, 0.0, 1.0]))))]
        return est.result(found(T, score, 0, view, "track", Evidence(score=score, confirmed=confirmed)), timer, t0,
                          T_pred)

    def _with_keypoints(self, frame: RGBDFrame, mask: np.ndarray | None, T_pred: np.ndarray, est: Estimator,
                        p: TrackParams) -> EstimateResult | None:
        t0 = time.perf_counter()
        timer = StageTimer()
        intr = frame.intrinsics
        ix = est.index
        with timer.stage("features"):
            _, _, uv = visible(T_pred, intr, est.model.samples)
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
            feats = join_depth(frame, region, extract_features_in_mask(frame, region, est.params.features,
                                                                       est.params.query.crop_margin),
                               est.params.features, est.query_depth)
        if len(feats) < 3:
            log.debug("%s: too few keypoints around the prior pose", frame.name)
            return None
        with timer.stage("retrieval"):
            kp_idx = ix.offered_keypoints(T_pred, est.params.verify.support_views_deg)
            kp_idx = kp_idx[visible(T_pred, intr, ix.points_obj[kp_idx])[0]]  # the side the prediction shows
            if ix.unit:
                S = np.matmul(feats.descriptors, ix.descriptors[kp_idx].T)
            else:
                S = descriptor_distances(feats.descriptors, ix.descriptors[kp_idx], ix.kind)
        with timer.stage("match"):
            src, dst, rows = self._pairs(feats.points.astype(np.float64), S, kp_idx, T_pred)
        with timer.stage("solve"):
            T1, keep = T_pred, np.zeros(len(src), bool)
            if len(src) >= 3:
                T_k, keep = kabsch_trimmed(src, dst, est.params.hypotheses.trim_tau)
                if keep.sum() >= 3:
                    T1 = T_k
        with timer.stage("refine"):
            q = QueryFrame(frame, mask, 1.0)
            anchors = (src[keep], dst[keep]) if keep.sum() >= 3 else None
            T2 = refine_pose(est.model, q, T1, anchors, None, est.params.refine, p.icp_max_dists, p.icp_max_points)
            location = query_keypoints(feats, S).location
            ev = est.verifier.evidence(q, T2, feats, S, location, kp_idx, np.arange(len(kp_idx)))
            ev.n_matches = len(src)
            ev.n_inliers = int(keep.sum())
            ev.spread_m = list_spread(src[keep])
        why = accept(ev, est.model.radius, est.params.accept)
        if why is None and ix.kind == JOINT:  # the depth alone may decide: the stricter shape rules (rivals), on
            # the frame prepared as an estimate's is (the silhouettes need its pixels off the table)
            why = est.verifier.by_depth(est.prepare(frame, mask), T2, ev, feats.from_depth, location, rows[keep])
        if why is None and ev.score < self._ref_score - p.max_score_drop:
            why = f"depth score dropped to {ev.score:.2f} from {self._ref_score:.2f}"
        if why is not None:
            log.debug("%s: the prior no longer holds: %s", frame.name, why)
            return None
        view = est.view_names[int(np.argmax(ix.axes @ (T2[:3, :3].T @ np.array([0.0, 0.0, 1.0]))))]
        return est.result(found(T2, ev.score, ev.n_inliers, view, "track", ev), timer, t0, T_pred)

    def _pairs(self, q_pts: np.ndarray, S: np.ndarray, kp_idx: np.ndarray,
               T_pred: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Each query keypoint [M x 3] paired with the template keypoint (of kp_idx, descriptor similarities or
        distances S [M x K]) most similar to it among those predicted within search_radius at T_pred, when it
        agrees (support_dist): (object-frame points [P x 3], camera-frame points [P x 3], the query keypoints
        paired [P])."""
        from scipy.spatial import cKDTree

        est = self.est
        kp_obj = est.index.points_obj[kp_idx]
        kp_cam = transform_points(T_pred, kp_obj)
        k = min(16, len(kp_cam))
        if k == 0:
            return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, np.int64)
        d, j = cKDTree(kp_cam).query(q_pts, k=k, distance_upper_bound=self.params.search_radius)
        d, j = d.reshape(len(q_pts), k), j.reshape(len(q_pts), k)
        near = np.isfinite(d)
        jj = np.where(near, j, 0)
        sim = np.take_along_axis(S, jj, axis=1) if est.index.unit else -np.take_along_axis(S, jj, axis=1)
        sim = np.where(near, sim, -np.inf)
        best = np.argmax(sim, axis=1)
        ok = sim[np.arange(len(q_pts)), best] >= est.verifier.support_sim
        rows = np.flatnonzero(ok)
        return kp_obj[jj[rows, best[rows]]], q_pts[rows], rows


# ------------------------------------------------------------------------------------------------ sequences


@dataclass
class TrackRun:
    """A tracked sequence: steps in frame order; problems {frame: reason} for frames that could not be read; damage:
    a recording's damaged records, one line each (`RecordingSequence.damage`)."""

    steps: list[TrackStep]
    problems: dict[str, str] = field(default_factory=dict)
    damage: list[str] = field(default_factory=list)

    def names(self, status: str) -> list[str]:
        return [s.frame for s in self.steps if s.status == status]

    def instances(self) -> list[dict] | None:
        """Per identity of a track of every instance (None for a single-instance track), by id: "id", "frames"
        (with a pose), "first" and "last" (frames with a pose), "lost" and "refound" (frame names)."""
        if not any(s.instances is not None for s in self.steps):
            return None
        out: dict[int, dict] = {}
        for s in self.steps:
            for i in s.instances or []:
                e = out.setdefault(i.id, {"id": i.id, "frames": 0, "first": None, "last": None, "lost": [],
                                          "refound": []})
                if i.result.T_cam_obj is not None:
                    e["frames"] += 1
                    e["first"] = e["first"] or s.frame
                    e["last"] = s.frame
                if i.status in ("lost", "refound"):
                    e[i.status].append(s.frame)
        return [out[k] for k in sorted(out)]

    def to_json(self, output: Path | None = None) -> dict:
        """The `gscan track --json` object (a track of every instance adds "instances", `instances()`)."""
        ms = np.array([s.ms() for s in self.steps]) if self.steps else np.zeros(1)
        instances = self.instances()
        extra = {} if instances is None else {"instances": instances}
        return {"output": None if output is None else str(output), "frames": len(self.steps),
                "with_pose": sum(s.result.T_cam_obj is not None for s in self.steps),
                "status": {k: len(self.names(k)) for k in STATUSES},
                "lost": self.names("lost"), "refound": self.names("refound"),
                "unreadable": dict(self.problems), "damage": list(self.damage),
                "timings_ms": {"median": float(np.median(ms)), "p90": float(np.percentile(ms, 90)),
                               "total": float(ms.sum())},
                **extra, "per_frame": [s.to_json() for s in self.steps]}


class FrameTracker(Protocol):
    """What `track_sequence` steps through a sequence: `Tracker`, or
    `gscan.estimate.track_instances.InstanceTracker` (every instance, each with its identity)."""

    def step(self, frame: RGBDFrame, mask: np.ndarray | None = None) -> TrackStep: ...

    def skip(self) -> None: ...


def track_sequence(estimator: Estimator, sequence, params: TrackParams = TrackParams(),
                   on_step: Callable[[TrackStep], None] | None = None,
                   tracker: FrameTracker | None = None) -> TrackRun:
    """Track the estimator's object through a `gscan.io.sequence.Sequence` (every readable frame in order;
    the sequence's masks are not used) with `tracker` (default: a `Tracker` of the estimator with `params`). Frames
    that cannot be read are recorded in `problems` and skipped."""
    if tracker is None:
        tracker = Tracker(estimator, params)
    run = TrackRun([], dict(sequence.problems), list(sequence.damage))
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


def instance_folder(instance_id: int) -> str:
    """The folder of one instance's poses in a track of every instance."""
    return f"instance_{instance_id}"


def write_poses(run: TrackRun, out: str | Path, force: bool = False) -> Path:
    """Write one T_cam_obj per frame with a pose (4x4 text, FoundationPose / BOP `ob_in_cam`, metres, named
    after the frame) and `summary.json` (TrackRun.to_json) into folder `out`. Frames without a pose get no
    file (the summary lists them lost). A track of every instance writes each frame's first instance there
    (`TrackStep`) and every instance's poses into `instance_<id>/`, the same layout. Written into a hidden
    temporary sibling and renamed into place, so `out` is never half-written; an existing non-empty `out` is
    refused without `force` (InputError)."""
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
            for i in s.instances or []:
                if i.result.T_cam_obj is not None:
                    (tmp / instance_folder(i.id)).mkdir(exist_ok=True)
                    np.savetxt(tmp / instance_folder(i.id) / pose_file_name(s.frame), i.result.T_cam_obj, fmt="%.10g")
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
