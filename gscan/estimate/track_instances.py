"""Tracking every instance of one template through a sequence, each with an identity (`InstanceTracker`,
`gscan track --all`).

Each instance has an identity (1, 2, ... in the order first found; best score first within a frame) and the state
of a single-instance `Tracker` (gscan.estimate.track). Per frame:

1. every instance that had a pose in the previous frame is refined locally from its prediction exactly as the
   single tracker refines its object (same prediction, ICP, keypoint checks and acceptance). Two refined onto one
   instance (centres closer than the object's thinnest extent) are one: the identity whose pose moved less from
   its own prediction keeps it, the other's prior failed.
2. a search, `estimate_all` on the pixels the instances held in step 1 do not explain (their pixels are removed
   from its keypoints and depth before it starts), runs whenever an identity has no pose yet in this frame (its
   prior failed, or it is lost: the single tracker re-estimates in every such frame), in every frame until an
   instance is found, and every `search_every`-th frame while every identity is held (instances coming into
   view), as long as fewer than `instances.max_instances` identities exist. It seeks at most max_instances less
   the instances held.
3. its poses (each verified as every `estimate_all` pose is) go to the identities without a pose, one to one by
   pose continuity: a minimum-cost assignment (scipy's `linear_sum_assignment`) of the distance between a pose's
   centre and the identity's predicted centre (its last one when lost), pairs farther than `gate` times the
   object's diameter excluded. A pose left over is a new identity; when max_instances identities exist already
   it goes to the nearest identity still without a pose whatever the distance (the cap says no other can be
   there). A pose on an instance held in step 1 is dropped. A pose given to an identity is, for an object with
   symmetries, the equivalent nearest that identity's last pose.
4. statuses as the single tracker's: "found" (a new identity, or found by the search right after its prior
   failed), "tracked", "refound" (found again after lost frames, its identity kept), "lost" (no pose this frame;
   identities are never forgotten).

Two identical instances that do not move keep their identities: each is held by its own prior (step 1), and a
re-found one goes to the identity whose last pose is nearest.
"""
from __future__ import annotations

import logging
import time

import numpy as np
from scipy.optimize import linear_sum_assignment

from gscan.estimate.estimator import Estimator
from gscan.estimate.instances import explained_pixels, thinnest_extent
from gscan.estimate.query import QueryFrame
from gscan.estimate.result import EstimateResult, ms_since, not_found
from gscan.estimate.track import InstanceStep, Tracker, TrackParams, TrackStep
from gscan.geometry.transforms import transform_points
from gscan.io.camera import RGBDFrame

log = logging.getLogger(__name__)

LOST = "no pose found near its last one"


class InstanceTracker:
    """Frame-by-frame poses of every instance of one template's object, each with its identity (module
    docstring). Not thread-safe: one per stream."""

    def __init__(self, estimator: Estimator, params: TrackParams = TrackParams()):
        self.est = estimator
        self.params = params
        self.thin = thinnest_extent(estimator.model.samples)
        self.gate_m = params.gate * 2.0 * estimator.model.radius
        self.reset()

    def reset(self) -> None:
        """Forget every identity: the next frame is searched afresh."""
        self._trackers: dict[int, Tracker] = {}  # identity -> its single-instance state
        self._since_search = 0  # frames since the last search

    def skip(self) -> None:
        """A frame that could not be read: every identity's motion model restarts (their poses are kept)."""
        for t in self._trackers.values():
            t.skip()

    def step(self, frame: RGBDFrame, mask: np.ndarray | None = None) -> TrackStep:
        """Every instance's pose in `frame` (mask: optional [H x W] bool search region)."""
        t0 = time.perf_counter()
        est, p = self.est, self.params
        frame = est.as_scanned(frame)
        preds: dict[int, np.ndarray] = {}
        held: dict[int, EstimateResult] = {}
        for k, t in self._trackers.items():
            T_pred = t.predicted()
            if T_pred is None:
                continue
            preds[k] = T_pred
            res = t.local(frame, mask, T_pred)
            if res is not None:
                held[k] = res
        self._one_per_instance(held, preds)
        cap = est.params.instances.max_instances
        waiting = [k for k in self._trackers if k not in held]
        search = bool(waiting) or not self._trackers or (
            p.search_every > 0 and self._since_search + 1 >= p.search_every and len(self._trackers) < cap)
        steps: dict[int, InstanceStep] = {k: InstanceStep(k, self._trackers[k].record(r, True), r)
                                          for k, r in held.items()}
        reason: str | None = "every instance held by its prior"
        if search and len(held) < cap:
            self._since_search = 0
            found, reason = self._search(frame, mask, list(held.values()), cap - len(held))
            for k, r in self._assign(found, waiting, preds, cap).items():
                if k not in self._trackers:
                    self._trackers[k] = Tracker(est, p)
                else:
                    r = est.settle(r, self._trackers[k].last_pose)
                steps[k] = InstanceStep(k, self._trackers[k].record(r, False), r)
        else:
            self._since_search += 1
        for k in self._trackers:
            if k not in steps:
                r = not_found(LOST)
                steps[k] = InstanceStep(k, self._trackers[k].record(r, False), r)
        ordered = [steps[k] for k in sorted(steps)]
        first = next((s for s in ordered if s.result.T_cam_obj is not None), None)
        if first is None:
            return TrackStep(frame.name, "lost", not_found(reason or "no instance found"), ordered, ms_since(t0))
        return TrackStep(frame.name, first.status, first.result, ordered, ms_since(t0))

    def _centre(self, T_cam_obj: np.ndarray | None) -> np.ndarray:
        """[3] the object's centre at T_cam_obj [4 x 4] (a pose found), camera frame."""
        assert T_cam_obj is not None
        return transform_points(T_cam_obj, self.est.model.center[None])[0]

    def _one_per_instance(self, held: dict[int, EstimateResult], preds: dict[int, np.ndarray]) -> None:
        """Identities refined onto one instance (centres closer than the thinnest extent): the one whose pose
        moved less from its prediction keeps it, the others leave `held` (their prior failed)."""
        def moved(k: int) -> float:
            return float(np.linalg.norm(self._centre(held[k].T_cam_obj) - self._centre(preds[k])))

        for k in sorted(held, key=lambda k: (moved(k), k)):
            if k not in held:
                continue
            c = self._centre(held[k].T_cam_obj)
            for j in [j for j in held if j != k and moved(j) >= moved(k)]:
                if np.linalg.norm(self._centre(held[j].T_cam_obj) - c) < self.thin:
                    log.debug("identities %d and %d on one instance: %d keeps it", k, j, k)
                    del held[j]

    def _search(self, frame: RGBDFrame, mask: np.ndarray | None, held: list[EstimateResult],
                cap: int) -> tuple[list[EstimateResult], str | None]:
        """The instances `estimate_all` finds on what the held poses do not explain (at most `cap`), none on a
        held instance, best score first; and the search's reason when it found none."""
        est = self.est
        explained = None
        if held:
            q = QueryFrame(frame, mask, 1.0)
            ip = est.params.instances
            explained = np.zeros(frame.depth.shape, bool)
            for r in held:
                assert r.T_cam_obj is not None
                explained |= explained_pixels(q, est.model.samples, r.T_cam_obj, ip.explain_dist, ip.dilate_px)
        out = est.estimate_all(frame, mask, explained=explained, max_instances=cap)
        kept = []
        for r in out.results:
            c = self._centre(r.T_cam_obj)
            if any(np.linalg.norm(self._centre(h.T_cam_obj) - c) < self.thin for h in held):
                log.debug("a search pose on a held instance: dropped")
                continue
            kept.append(r)
        return kept, out.reason

    def _assign(self, found: list[EstimateResult], waiting: list[int], preds: dict[int, np.ndarray],
                cap: int) -> dict[int, EstimateResult]:
        """Identity -> pose for the search's poses (module docstring, step 3); new identities numbered on."""
        refs = [preds[k] if k in preds else self._trackers[k].last_pose for k in waiting]
        known = [(k, T) for k, T in zip(waiting, refs, strict=True) if T is not None]
        out: dict[int, EstimateResult] = {}
        left = list(range(len(found)))
        if known and found:
            dist = np.array([[np.linalg.norm(self._centre(r.T_cam_obj) - self._centre(T))
                           for _, T in known] for r in found])
            rows, cols = linear_sum_assignment(np.where(dist > self.gate_m, 1e6, dist))
            for i, j in zip(rows, cols, strict=True):
                if dist[i, j] <= self.gate_m:
                    out[known[j][0]] = found[i]
                    left.remove(i)
        free = [k for k in waiting if k not in out]
        next_id = max(self._trackers, default=0) + 1
        for i in left:  # best score first
            if len(self._trackers) + sum(k not in self._trackers for k in out) < cap:
                out[next_id] = found[i]
                next_id += 1
            elif free:  # the cap reached: the nearest identity still without a pose
                c = self._centre(found[i].T_cam_obj)
                k = min(free, key=lambda k: (self._dist(k, c, preds), k))
                out[k] = found[i]
                free.remove(k)
        return out

    def _dist(self, k: int, c: np.ndarray, preds: dict[int, np.ndarray]) -> float:
        """Distance (m) from centre c [3] to identity k's predicted (or last) centre; inf when it has none."""
        T = preds.get(k, self._trackers[k].last_pose)
        return float("inf") if T is None else float(np.linalg.norm(self._centre(T) - c))
