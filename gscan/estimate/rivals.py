"""Stages 4-7 on the pooled match lists: solve, refine and verify each, and weigh an accepted pose against its
rivals (`ListVerifier`).

- solve: the list's pose by Kabsch with gross outliers trimmed (`kabsch_trimmed`, object-frame template points
  -> query camera points); refine: `gscan.estimate.refine.refine_pose` with the list as weak anchors, on the
  query cloud cut to the off-plane pixels (a given mask does not cut it: a mask that clips the silhouette
  would pull the pose toward the cut).
- verify (`gscan.estimate.verify`): accepted from the evidence, never from the list length alone, and refused
  when it sinks the object into the support plane. When the best list's pose is refused, the next
  `verify.lists` - 1 lists are tried, under the short lists' stricter rule. Where a refusal's reason is not
  read (those later lists, the rivals below, the search elsewhere of gscan.estimate.instances), a list its solve
  alone rules out (`list_refusal`: too few inliers, or on a line) is refused before ICP, and a pose the depth
  refutes is refused before its keypoint support is counted: the same answers at less cost.
- rivals: a box printed alike on two faces fits a pose turned onto its twin face as well as the right one, in
  shape and in most keypoints. The next `rivals.lists` lists whose pre-score support reaches
  `rivals.min_support` of the accepted list's, and whose poses lie beyond the refinement's reach of the
  accepted pose (a list within it is the same pose sharpened), are solved, refined and verified too. A rival
  accepted at another pose is compared with the accepted pose on the query keypoints that support one pose and
  not the other (a sign test at level `rivals.p`): the pose they significantly favour is returned; when neither
  is favoured the view is ambiguous (the reason starts with `AMBIGUOUS`).
- symmetries: poses are compared up to the template's symmetries that hold in shape and texture
  (gscan.estimate.symmetric): a rival within the tolerance of an equivalent of the accepted pose is the same answer,
  not an ambiguous view. A symmetry in shape alone is no excuse: there the texture decides, as above, and the
  accepted pose turned by each discrete symmetry that holds in shape only is weighed as a rival too, whether or
  not a match list found it (a view that hides what tells the turn, such as a box's bottom on the table, is an
  exact tie: refused, never answered by the pre-score's order). Its keypoints are weighed by `local_support`:
  a query keypoint supports a pose when any template keypoint within `verify.support_radius` of it at the pose
  agrees (not only its nearest by descriptor, which on twin prints picks one twin by the template views' angles
  and so biases the count); a keypoint the print repeats under the turn supports both poses and decides nothing.
- unseen sides: a template from one upright capture has never seen the object's bottom, and the accepted pose
  turned by a symmetry in shape (upside down) would show the bottom where the pose shows the top. The keypoints
  on that part support the pose whatever the bottom looks like, so they cannot tell the two apart: a print
  repeated on the top and bottom (a drinks pack) is matched to the top with the object upside down. For each such
  turn not refuted by the depth, the pose's supporters (`local_support`) are split into those the turn puts on
  or beside surface the template has not seen (no template surface sample within twice the support radius, or
  within that reach of the template's surface turned where it has none: a keypoint on the top's rim lies on the
  bottom's rim under the turn, and its descriptor sees across the rim) and the rest (on seen surface under both
  poses). The view is ambiguous when the rest would not accept the pose on its own
  (`accept.min_support` supporters and `accept.min_support_ratio` of the keypoints there), or, when the unseen
  part holds `accept.min_support` supporters or more (enough to have carried the pose), when the rest supports it
  at less than `rivals.unseen_rate` of the unseen part's rate (a right pose is supported alike on both parts, a
  turned one mostly where the template cannot tell). The turned pose is not weighed itself: the template's views,
  all from above, barely predict how the sides look from below (5-17 supporters at the true pose of upside-down
  views of one-sided templates).
- weak poses: a pose accepted on the short lists' rule (not the long list's) whose turn by a symmetry in shape only
  fits the depth too is ambiguous unless the keypoints that support one of the two and not the other favour it
  (`against_alike_turns`): with a template of both sides no side is unseen, and a print repeated on the top and
  bottom leaves a pose on a few keypoints of it as undecided as the one-sided template's.
"""
from __future__ import annotations

import logging
from collections.abc import Callable
from functools import cached_property
from typing import Any

import numpy as np

from gscan.estimate.hypotheses import MatchList, QueryKeypoints
from gscan.estimate.model import ObjectModel
from gscan.estimate.params import AcceptParams, EstimateParams
from gscan.estimate.query import QueryFrame
from gscan.estimate.refine import refine_pose
from gscan.estimate.result import EstimateResult, found, not_found
from gscan.estimate.retrieval import TemplateIndex
from gscan.estimate.symmetric import PoseGroup
from gscan.estimate.texture import KeyframeTextures, texture_refusal
from gscan.estimate.verify import (
    Evidence,
    accept,
    border_refusal,
    decided_by_depth,
    depth_refusal,
    list_refusal,
    list_spread,
    near_agreeing,
    pose_evidence,
    query_sinks,
    silhouette_refusal,
    strong_rule,
    support_radius,
    visible,
)
from gscan.features import Features
from gscan.features.keypoints import JOINT
from gscan.geometry.kabsch import kabsch_trimmed
from gscan.geometry.symmetry import Symmetries
from gscan.geometry.transforms import inv_T, pose_error, transform_points
from gscan.progress import StageTimer
from gscan.registration.noise import DepthNoise, sign_test

log = logging.getLogger(__name__)

AMBIGUOUS = "ambiguous view"  # the reason's start when two poses explain the frame alike

#: (accepted, rival) -> the rival is another instance of the object, on pixels of its own (`Estimator.estimate_all`)
Separate = Callable[[EstimateResult, EstimateResult], bool]


class ListVerifier:
    """Solves, refines and verifies match lists of one template (module docstring)."""

    def __init__(self, index: TemplateIndex, model: ObjectModel, params: EstimateParams):
        self.index, self.model, self.params = index, model, params
        sd = params.verify.support_dist if params.verify.support_dist is not None else index.eps_f
        # similarity at which a supporting keypoint's descriptor agrees (cosine for unit descriptors, else the
        # negated distance)
        self.support_sim = 1.0 - 0.5 * sd ** 2 if index.unit else -sd
        # the poses that look alike (none when the settings ignore the template's symmetries), and the turns that
        # hold in shape only (the texture must tell them)
        sym = model.symmetries if params.symmetry.enabled else Symmetries()
        self.group = PoseGroup.of(sym)
        turns = [S for S, t in zip(sym.discrete, sym.discrete_in_texture, strict=True) if not t]
        self.shape_turns = turns if params.symmetry.weigh_shape_turns else []
        self.unseen_turns = turns
        self._unseen: dict[bytes, Any] = {}  # (turn, radius) -> cKDTree of the surface the template has not seen
        # a template with depth keypoints: its keyframes' textures and its depth noise (`by_depth`)
        self.keyframes: KeyframeTextures | None = None
        self.depth_noise = DepthNoise()

    def apart(self, T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
        """(degrees, metres) between T_a and the nearest pose that looks as T_b does (T_b itself without
        symmetries)."""
        return self.group.apart(T_a, T_b) if self.group else pose_error(T_a, T_b)

    def evidence(self, q: QueryFrame, T_cam_obj: np.ndarray, feats: Features, S: np.ndarray,
                 q_location: np.ndarray, kp_idx: np.ndarray | None = None,
                 sim_cols: np.ndarray | None = None, sim_rows: np.ndarray | None = None,
                 gate: AcceptParams | None = None) -> Evidence:
        """Depth agreement and keypoint support of a pose (`gscan.estimate.verify.pose_evidence`). S [M' x C]: the
        query keypoints' similarity (unit descriptors) or distance to template keypoints, sim_rows [M] their rows
        in S (default: row i is keypoint i); kp_idx: the template keypoints offered (default: those of the views
        near the pose's viewing direction) and sim_cols their columns in S (default: S holds every keypoint);
        gate: the keypoint support is left empty when the depth alone refuses the pose under that rule."""
        if kp_idx is None:
            kp_idx = self.index.offered_keypoints(T_cam_obj, self.params.verify.support_views_deg)
        return pose_evidence(q, T_cam_obj, self.model.samples, self.model.center, self.index.points_obj, kp_idx,
                             S, kp_idx if sim_cols is None else sim_cols, feats.points, q_location,
                             self.params.verify, self.support_sim, 1.0 if self.index.unit else -1.0, sim_rows, gate,
                             feats.from_depth if self.index.kind == JOINT else None)

    def evidence_of(self, q: QueryFrame, T_cam_obj: np.ndarray, qk: QueryKeypoints,
                    gate: AcceptParams | None = None) -> Evidence:
        """`evidence` of the pose against the query keypoints qk, read through their rows in the retrieval matrix
        (gate: `evidence`'s)."""
        return self.evidence(q, T_cam_obj, qk.feats, qk.S, qk.location, sim_rows=qk.rows, gate=gate)

    def sinks(self, q: QueryFrame, T_cam_obj: np.ndarray) -> float | None:
        """The fraction of the object the pose puts inside the frame's support plane when too large, else None."""
        return query_sinks(q, T_cam_obj, self.model.samples, self.params.verify)

    def verify_lists(self, q: QueryFrame, qk: QueryKeypoints, lists: list[MatchList], refine: bool,
                     timer: StageTimer, separate: Separate | None = None, best: bool = True,
                     explain: bool = True) -> EstimateResult:
        """The pose of the pooled lists (best pre-score first): the first accepted of the `verify.lists` best,
        weighed against its rivals, else the best list's refusal. separate: when given, a rival it calls another
        instance is no rival (`against_rivals`); best: the first list is the frame's best-supported (False: every
        list is verified under the short lists' rule, `accept`); explain: False when a refusal's reason is not
        read (`verify_list`)."""
        p = self.params
        if not lists:
            return not_found("too few geometrically consistent matches (no list of 3)")
        first: EstimateResult | None = None
        refuted: list[EstimateResult] = []  # poses the rules for the depth alone refuted (`depth_only_refusal`)
        listed = [c for c in lists if c.n >= p.accept.min_matches]
        for i, c in enumerate(listed[: max(1, p.verify.lists)]):
            # the first refusal is the answer when none is accepted: the later ones' reasons are not read
            res = self.verify_list(q, qk, c, refine, timer, best=best and c is lists[0],
                                   explain=explain and first is None)
            if res.found:
                if (why := self.better_fit_refuted(res, refuted)) is not None:
                    return not_found(why, res.n_matches, res.view, res.score, evidence=res.evidence)
                rivals = [r for r in listed[i + 1:] if r.support >= p.rivals.min_support * c.support]
                return self.against_rivals(q, qk, res, rivals, refine, timer, separate)
            if res.T_refuted is not None:
                refuted.append(res)
            first = first or res
        if first is None:
            n = max(c.n for c in lists)
            return not_found(f"too few geometrically consistent matches ({n} < {p.accept.min_matches})", n,
                             self.index.view_names[lists[0].view])
        return first

    def better_fit_refuted(self, res: EstimateResult, refuted: list[EstimateResult]) -> str | None:
        """The reason a pose the depth alone decided (`res`, found) is refused because a pose of a list verified
        before it lies at the same place (its object's centre within the object's radius), fits the depth at least
        as well (depth score and share of the visible surface confirmed) and was refuted by the rules for a pose
        the depth alone decides (refuted: those poses' results, not found, with their evidence and `T_refuted`): the
        depth, which alone decides `res`, prefers a pose known wrong, so it cannot tell `res` right either (a
        right pose refuted by its shadows' texture, and the box turned 39 deg that the silhouettes' margin let
        through next to it). A refuted pose that is the same answer as `res` (within `hypotheses.merge_deg` and
        `merge_dist`, up to the object's symmetries) does not count: a rule's verdict at its edge. None when there
        is no such pose."""
        ev, p = res.evidence, self.params.hypotheses
        if ev is None or not ev.depth_only or res.T_cam_obj is None:
            return None
        centre = res.T_cam_obj[:3, :3] @ self.model.center + res.T_cam_obj[:3, 3]
        for r in refuted:
            e = r.evidence
            assert e is not None and r.T_refuted is not None
            there = r.T_refuted[:3, :3] @ self.model.center + r.T_refuted[:3, 3]
            deg, dist = self.apart(r.T_refuted, res.T_cam_obj)
            if deg <= p.merge_deg and dist <= p.merge_dist:  # the same answer (a rule's verdict at its edge)
                continue
            if np.linalg.norm(there - centre) <= self.model.radius and e.score >= ev.score and \
                    e.confirmed >= ev.confirmed:
                return (f"a pose that fits the depth there better (score {e.score:.2f} against {ev.score:.2f}, "
                        f"{e.confirmed:.0%} of its visible surface confirmed against {ev.confirmed:.0%}) was refuted "
                        f"({r.reason}); the depth alone decided this one and cannot tell it right")
        return None

    def verify_list(self, q: QueryFrame, qk: QueryKeypoints, c: MatchList, refine: bool, timer: StageTimer,
                    best: bool = True, explain: bool = True) -> EstimateResult:
        """Solve, refine and verify one match list (best: the frame's best-supported list, `accept`). explain:
        False when the caller reads only whether the list is accepted (a refusal's reason and evidence are not
        read): a list its solve alone refuses (`list_refusal`) is then refused before it is refined, with that
        reason and the list's evidence only, and a pose the depth refutes is refused without its keypoint
        support; accepted or not, the answer is the one explain=True gives."""
        p = self.params
        view = self.index.view_names[c.view]
        with timer.stage("solve"):
            src = self.index.points_obj[c.matches[:, 0]]
            dst = qk.feats.points[c.matches[:, 1]].astype(np.float64)
            T_cam_obj, keep = kabsch_trimmed(src, dst, p.hypotheses.trim_tau)
            # inliers count query keypoint locations (pooled lists pair one keypoint with several template views)
            listed = Evidence(n_matches=c.longest, n_inliers=len(np.unique(qk.location[c.matches[keep, 1]])),
                              spread_m=list_spread(src[keep]))
        if not explain and (why := list_refusal(listed, self.model.radius, p.accept, best)) is not None:
            return not_found(why, c.longest, view, evidence=listed)
        with timer.stage("refine"):
            if refine:  # not cut by a given mask: a mask that clips the silhouette pulls ICP to the cut
                T_cam_obj = refine_pose(self.model, q, T_cam_obj, (src[keep], dst[keep]), q.off_plane, p.refine)
            ev = self.evidence_of(q, T_cam_obj, qk, None if explain else p.accept)
            ev.n_matches, ev.n_inliers, ev.spread_m = listed.n_matches, listed.n_inliers, listed.spread_m
        below = self.sinks(q, T_cam_obj)
        why = accept(ev, self.model.radius, p.accept, best) if below is None else \
            f"pose puts {below:.0%} of the object inside the support plane"
        if why is None and self.index.kind == JOINT:
            why = self.by_depth(q, T_cam_obj, ev, qk.feats.from_depth, qk.location, c.matches[keep, 1])
        if why is not None:
            res = not_found(why, c.longest, view, ev.score, evidence=ev)
            res.T_refuted = T_cam_obj if ev.depth_only else None  # refuted by the rules for the depth alone
            return res
        return found(T_cam_obj, ev.score, c.longest, view, "gmatch", ev)

    def by_depth(self, q: QueryFrame, T_cam_obj: np.ndarray, ev: Evidence, from_depth: np.ndarray,
                 location: np.ndarray, inliers: np.ndarray) -> str | None:
        """For a template with depth keypoints, an accepted pose's evidence marked when the depth alone decided it
        (`decided_by_depth`: from_depth [M] which query keypoints are depth keypoints, location [M] their location
        ids, inliers [K] the list's inlier keypoints), and then the reason the stricter shape rules refuse it
        (`silhouette_refusal`, then the keyframes' texture: `texture_refusal`), else None."""
        loc_depth = np.zeros(int(location.max()) + 1 if len(location) else 0, bool)
        loc_depth[location[from_depth]] = True
        ev.depth_only = decided_by_depth(ev, loc_depth, np.unique(location[inliers]), self.params.accept)
        return self.depth_only_refusal(q, T_cam_obj, ev) if ev.depth_only else None

    def depth_only_refusal(self, q: QueryFrame, T_cam_obj: np.ndarray, ev: Evidence) -> str | None:
        """The reason the stricter rules refuse a pose the depth alone decided (its evidence `ev`), else None; the
        first of: `silhouette_refusal`; the keyframes' texture and colour, `texture_refusal`; the depth seen through
        beyond registration's bound for an edge, `accept.max_see_through`; the image's border, `border_refusal`."""
        p = self.params.accept
        why = silhouette_refusal(q, T_cam_obj, self.model.samples, self.params.refine.voxel, self.depth_noise, p)
        if why is None:
            why = "no texture check for a pose the depth alone decided (the template's keyframes are not known)" \
                if self.keyframes is None else texture_refusal(q, T_cam_obj, self.keyframes, self.depth_noise, p)
        if why is None and 1.0 - ev.score > p.max_see_through:
            why = (f"depth disagrees ({1.0 - ev.score:.0%} of the surface the pose shows is seen through; the depth "
                   f"alone decided the pose, so at most {p.max_see_through:.0%})")
        return why or border_refusal(q.frame.intrinsics, T_cam_obj, self.model.samples, p)

    def against_rivals(self, q: QueryFrame, qk: QueryKeypoints, res: EstimateResult, rivals: list[MatchList],
                       refine: bool, timer: StageTimer, separate: Separate | None = None) -> EstimateResult:
        """The accepted `res` against its rival lists (module docstring): the pose the keypoints significantly
        favour, or not found when the view cannot tell them apart. separate: when given, an accepted rival it
        calls another instance (apart, on pixels of its own) is left to a later search and does not count
        among the `rivals.lists` checked: a rival on the same pixels is still weighed."""
        p = self.params
        checked = 0
        for r in rivals:
            assert res.T_cam_obj is not None and res.evidence is not None
            if checked >= p.rivals.lists:
                break
            deg, dist = self.apart(r.T, res.T_cam_obj)
            if deg <= p.refine.max_turn_deg and dist <= self.model.radius:
                continue
            checked += 1
            alt = self.verify_list(q, qk, r, refine, timer, explain=False)
            if alt.T_refuted is not None and (why := self.better_fit_refuted(res, [alt])) is not None:
                return not_found(why, res.n_matches, res.view, res.score, evidence=res.evidence)
            if alt.T_cam_obj is None or alt.evidence is None:
                continue
            deg, dist = self.apart(alt.T_cam_obj, res.T_cam_obj)
            if deg <= p.hypotheses.merge_deg and dist <= p.hypotheses.merge_dist:  # the same answer: not a rival
                continue
            if separate is not None and separate(res, alt):
                checked -= 1
                continue
            if any(self.near(alt.T_cam_obj, res.T_cam_obj @ S) for S in self.shape_turns):
                res, tie = self.weigh_turn(q, qk, res, alt, deg)
            else:
                res, tie = self.weigh(res, alt, deg, dist)
            if tie is not None:
                return tie
        res = self.against_shape_turns(q, qk, res, refine, timer)
        if res.T_cam_obj is None:
            return res
        # the pose's turns by the symmetries in shape only, refined once for the two rules that weigh them
        turns = [(S, self.turned(q, res.T_cam_obj, S, refine, timer)) for S in self.unseen_turns]
        res = self.against_unseen_turns(q, qk, res, turns)
        return self.against_alike_turns(q, qk, res, turns) if res.found else res

    def turned(self, q: QueryFrame, T_cam_obj: np.ndarray, S: np.ndarray, refine: bool, timer: StageTimer
               ) -> np.ndarray:
        """The pose T_cam_obj [4 x 4] turned by the symmetry S [4 x 4] (object frame), refined on the query's depth
        when `refine` (without anchors: no keypoint was matched at the turn)."""
        T = T_cam_obj @ S
        with timer.stage("refine"):
            if refine:
                T = refine_pose(self.model, q, T, None, q.off_plane, self.params.refine)
        return T

    def near(self, T_a: np.ndarray, T_b: np.ndarray) -> bool:
        """T_a lies within the pooling tolerance of T_b or of a pose that looks as T_b does."""
        deg, dist = self.apart(T_a, T_b)
        return deg <= self.params.hypotheses.merge_deg and dist <= self.params.hypotheses.merge_dist

    def weigh(self, res: EstimateResult, alt: EstimateResult, deg: float,
              dist: float) -> tuple[EstimateResult, EstimateResult | None]:
        """(the pose the keypoints that support one of two accepted poses and not the other significantly favour,
        None), or (res, the ambiguous view's not-found result) when neither is favoured; deg, dist: how far apart
        they are (the reason's)."""
        assert res.evidence is not None and alt.evidence is not None
        a, b = res.evidence.supporters, alt.evidence.supporters
        only_res, only_alt = len(np.setdiff1d(a, b)), len(np.setdiff1d(b, a))
        if sign_test(only_res, only_alt) < self.params.rivals.p:
            return res, None
        if sign_test(only_alt, only_res) < self.params.rivals.p:
            log.debug("a rival pose wins (%d keypoints for it alone, %d against)", only_alt, only_res)
            return alt, None
        return res, not_found(f"{AMBIGUOUS}: a pose {deg:.0f} deg / {dist * 1000:.0f} mm away explains it as well "
                              f"({only_res} keypoints agree with one pose only, {only_alt} with the other)",
                              res.n_matches, res.view, res.score, evidence=res.evidence)

    def against_shape_turns(self, q: QueryFrame, qk: QueryKeypoints, res: EstimateResult, refine: bool,
                            timer: StageTimer) -> EstimateResult:
        """The accepted `res` against itself turned by each symmetry that holds in shape only (module docstring):
        the turned pose, refined, is a rival when its evidence is accepted as the pose's own was."""
        p = self.params
        for S in self.shape_turns:
            assert res.T_cam_obj is not None and res.evidence is not None
            T = self.turned(q, res.T_cam_obj, S, refine, timer)
            with timer.stage("refine"):
                ev = self.evidence_of(q, T, qk)
            ev.n_matches, ev.n_inliers, ev.spread_m = res.evidence.n_matches, res.evidence.n_inliers, \
                res.evidence.spread_m
            if self.sinks(q, T) is not None or accept(ev, self.model.radius, p.accept) is not None:
                continue
            if self.near(T, res.T_cam_obj):
                continue
            if res.evidence.depth_only:  # the turned pose rests on the same depth: the same stricter rules
                ev.depth_only = True
                if self.depth_only_refusal(q, T, ev) is not None:
                    continue
            res, tie = self.weigh_turn(q, qk, res, found(T, ev.score, res.n_matches, res.view, res.method, ev),
                                       self.apart(T, res.T_cam_obj)[0])
            if tie is not None:
                return tie
        return res

    @cached_property
    def seen(self) -> Any:
        """cKDTree of the template's surface samples (all seen: filled holes hold none), built when first asked."""
        from scipy.spatial import cKDTree

        return cKDTree(self.model.samples)

    @staticmethod
    def _distances(tree: Any, T_cam_obj: np.ndarray, qk: QueryKeypoints, among: np.ndarray | None) -> np.ndarray:
        """[M] each query keypoint's distance (m) at T_cam_obj to the nearest point of `tree` (object frame); among
        ([M] bool): only those keypoints are measured, the others are NaN (no comparison holds for them)."""
        pts = qk.feats.points if among is None else qk.feats.points[among]
        d, _ = tree.query(transform_points(inv_T(T_cam_obj), pts.astype(np.float64)))
        if among is None:
            return np.asarray(d)
        out = np.full(len(qk.feats.points), np.nan)
        out[among] = d
        return out

    def off_seen_surface(self, T_cam_obj: np.ndarray, qk: QueryKeypoints, radius: float,
                         among: np.ndarray | None = None) -> np.ndarray:
        """[M] bool: the query keypoints farther than `radius` (m) from the template's surface at T_cam_obj;
        among ([M] bool): only those keypoints are measured, the others are False (each keypoint's answer does
        not depend on the others)."""
        return self._distances(self.seen, T_cam_obj, qk, among) > radius

    def near_unseen(self, T_cam_obj: np.ndarray, S: np.ndarray, qk: QueryKeypoints, radius: float,
                    among: np.ndarray) -> np.ndarray:
        """[M] bool: the query keypoints (of `among` [M] bool) within `radius` (m) of surface the template has not
        seen, at T_cam_obj: of the template's surface turned by the symmetry in shape S [4 x 4], the part farther
        than `radius` from its seen surface (a keypoint on a face's rim is described by what lies beyond the
        rim too)."""
        from scipy.spatial import cKDTree

        key = S.tobytes() + np.float64(radius).tobytes()
        if key not in self._unseen:
            turned = transform_points(S, self.model.samples)
            d, _ = self.seen.query(turned)
            self._unseen[key] = cKDTree(turned[d > radius]) if (d > radius).any() else None
        tree = self._unseen[key]
        if tree is None:
            return np.zeros(len(qk.feats.points), bool)
        return self._distances(tree, T_cam_obj, qk, among) <= radius

    def against_unseen_turns(self, q: QueryFrame, qk: QueryKeypoints, res: EstimateResult,
                             turns: list[tuple[np.ndarray, np.ndarray]]) -> EstimateResult:
        """The accepted `res` against itself turned by each symmetry in shape onto surface the template has not
        seen (module docstring; turns: (each symmetry in shape only S [4 x 4], the pose turned by it and refined,
        `turned`)): res, or the ambiguous view's not-found result."""
        p = self.params
        assert res.T_cam_obj is not None and res.evidence is not None
        radius = support_radius(p.verify, float(transform_points(res.T_cam_obj, self.model.center[None])[0, 2]))
        on = ~self.off_seen_surface(res.T_cam_obj, qk, radius)
        support: np.ndarray | None = None
        for S, T in turns:
            off = self.off_seen_surface(T, qk, 2.0 * radius, among=on) | self.near_unseen(T, S, qk, 2.0 * radius, on)
            unseen = np.unique(qk.location[off])
            known = np.setdiff1d(np.unique(qk.location[on]), unseen)
            if support is None:
                support = self.local_support(q, res.T_cam_obj, qk)
            n_unseen = len(np.intersect1d(support, unseen))
            if n_unseen == 0:
                continue
            n_known = len(np.intersect1d(support, known))
            log.debug("turn onto unseen surface: %d of %d supporters there, %d of %d elsewhere", n_unseen, len(unseen),
                      n_known, len(known))
            rate_unseen, rate_known = n_unseen / len(unseen), n_known / max(1, len(known))
            if (n_known < p.accept.min_support or rate_known < p.accept.min_support_ratio
                    or (n_unseen >= p.accept.min_support and rate_known < p.rivals.unseen_rate * rate_unseen)):
                # the depth is asked only here: a turn it refutes and one the supporters do not make ambiguous
                # both leave the pose as it is
                if (self.evidence_of(q, T, qk).score < p.accept.min_score
                        or self.sinks(q, T) is not None):
                    continue  # the depth refutes the turn
                deg = self.apart(T, res.T_cam_obj)[0]
                return not_found(f"{AMBIGUOUS}: the pose turned {deg:.0f} deg by the object's symmetry in shape "
                                 f"would show a side the template has not seen where {n_unseen} of the keypoints "
                                 f"supporting the pose lie ({n_unseen} of {len(support)}; elsewhere {n_known} of "
                                 f"{len(known)} support it): scan the object upside down as well",
                                 res.n_matches, res.view, res.score, evidence=res.evidence)
        return res

    def against_alike_turns(self, q: QueryFrame, qk: QueryKeypoints, res: EstimateResult,
                            turns: list[tuple[np.ndarray, np.ndarray]]) -> EstimateResult:
        """A pose accepted on the short lists' rule (`accept`) against itself turned by each symmetry that holds in
        shape only (module docstring; turns: as `against_unseen_turns`'): where the depth does not refute the
        turn, the keypoints that support one of the two and not the other (`local_support`) must favour the pose (a
        sign test at `rivals.p`), else the view is ambiguous. res, or the ambiguous view's not-found result."""
        p = self.params
        assert res.T_cam_obj is not None and res.evidence is not None
        if not turns or strong_rule(res.evidence, p.accept, True):
            return res
        support = self.local_support(q, res.T_cam_obj, qk)
        for _, T in turns:
            if self.sinks(q, T) is not None or depth_refusal(self.evidence_of(q, T, qk), p.accept) is not None:
                continue  # the depth refutes the turn
            turned = self.local_support(q, T, qk)
            only_res, only_alt = len(np.setdiff1d(support, turned)), len(np.setdiff1d(turned, support))
            log.debug("turn by a symmetry in shape, fitting the depth: %d keypoints support the pose alone, %d it",
                      only_res, only_alt)
            if sign_test(only_res, only_alt) >= p.rivals.p:
                deg = self.apart(T, res.T_cam_obj)[0]
                return not_found(f"{AMBIGUOUS}: the pose turned {deg:.0f} deg by the object's symmetry in shape fits "
                                 f"the depth as well, and the keypoints do not tell them apart ({only_res} agree with "
                                 f"the pose only, {only_alt} with the turn)", res.n_matches, res.view, res.score,
                                 evidence=res.evidence)
        return res

    def weigh_turn(self, q: QueryFrame, qk: QueryKeypoints, res: EstimateResult, alt: EstimateResult,
                   deg: float) -> tuple[EstimateResult, EstimateResult | None]:
        """`weigh` for an accepted pose and its turn by a symmetry in shape: on `local_support`, and a pose wins
        only when its keypoints for it alone outnumber the other's by `rivals.turn_margin` of the keypoints for
        either (the template's views are not symmetric, so on an exact tie a twin print's keypoints still agree
        better on the side its views saw squarely: up to 6 % of them on the rendered boxes of
        tests/test_estimate_symmetry.py; the print that tells the turn gives 20 % and more)."""
        assert res.T_cam_obj is not None and alt.T_cam_obj is not None
        p = self.params.rivals
        a, b = self.local_support(q, res.T_cam_obj, qk), self.local_support(q, alt.T_cam_obj, qk)
        only_res, only_alt = len(np.setdiff1d(a, b)), len(np.setdiff1d(b, a))
        margin = p.turn_margin * len(np.union1d(a, b))
        if sign_test(only_res, only_alt) < p.p and only_res - only_alt >= margin:
            return res, None
        if sign_test(only_alt, only_res) < p.p and only_alt - only_res >= margin:
            log.debug("the pose turned by a shape symmetry wins (%d keypoints for it alone, %d against)",
                      only_alt, only_res)
            return alt, None
        return res, not_found(f"{AMBIGUOUS}: the pose turned {deg:.0f} deg by the object's symmetry in shape "
                              f"explains it as well ({only_res} keypoints agree with one pose only, {only_alt} with "
                              f"the other)", res.n_matches, res.view, res.score, evidence=res.evidence)

    def local_support(self, q: QueryFrame, T_cam_obj: np.ndarray, qk: QueryKeypoints) -> np.ndarray:
        """The location ids (sorted) of the query keypoints with a template keypoint (of the views near the pose's
        viewing direction, visible at the pose) within `verify.support_radius` of them at T_cam_obj [4 x 4] whose
        descriptor agrees (module docstring)."""
        p = self.params.verify
        kp_idx = self.index.offered_keypoints(T_cam_obj, p.support_views_deg)
        vis, kp_cam, _ = visible(T_cam_obj, q.frame.intrinsics, self.index.points_obj[kp_idx])
        cols, sign = kp_idx[vis], (1.0 if self.index.unit else -1.0)
        agree = near_agreeing(qk.feats.points, kp_cam, p.support_radius,
                              lambda some, j: qk.S[qk.row_of(some)[:, None], cols[j]] * sign >= self.support_sim)
        return np.unique(qk.location[agree]).astype(np.int64)
