"""How a sequence of frames is registered: pairwise edges, then one pose per frame from the pose graph.

- edges (`register_edges`): each frame against the previous one, falling back to the next earlier ones
  (`max_skip` frames in all), then loop closures chosen by view overlap and bag-of-words votes
  (`gscan.registration.loops`); each edge by `gscan.registration.pairwise`, handed to the sink as computed
- noise (`capture_noise`): the capture's own keypoint and depth noise, from a few sequential pairs
- pose graph (`optimise_sequence`): edges that contradict the capture's odometry are rejected, loop closures
  the depth alone decided that the capture's steady motion tells from the object's turns, and poses the shape's
  checks refused that it pins, accepted (`admit_by_motion`), the rest
  optimised robustly (`gscan.registration.posegraph`); a frame it cuts loose is registered to
  `second_opinions` more frames and the graph optimised again; frames not joined to the reference stay
  without a pose, each with its reason

`SequenceParams` holds the settings of all three; the frames are read through `SequenceFrames`, the edges
stored through an `EdgeSink` (`gscan.registration.edges`).
"""
from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import overload

import numpy as np

from gscan.geometry.transforms import inv_T, rotation_angle_deg, transform_points
from gscan.registration.dense import plane_residuals
from gscan.registration.edge import PRUNED, Edge
from gscan.registration.edges import (
    AGAINST_ODOMETRY,
    LOOP_DEPTH_ONLY,
    SEQUENTIAL_MAX_TURN_DEG,
    Evidence,
    Registrar,
    SequenceFrames,
    edge_evidence,
    source_depth,
)
from gscan.registration.loops import select_loop_candidates
from gscan.registration.motion import SteadyMotion, steady_motion
from gscan.registration.noise import DepthNoise, estimate_noise
from gscan.registration.pairwise import RegisterParams, refused_by_shape, register_features
from gscan.registration.params import LoopParams, PoseGraphParams, SequenceParams  # noqa: F401 - its importers read it here too
from gscan.registration.posegraph import (
    INCONSISTENT,
    GraphEdge,
    PoseGraphResult,
    optimize_pose_graph,
    spanning_poses,
)

log = logging.getLogger(__name__)

NO_KEYPOINTS = "no keypoint with depth (dark or textureless image, or no valid depth)"


@dataclass
class SequenceResult:
    """A registered sequence: its edges (registration's and the pose graph's verdicts), T_world_cam [4 x 4] per
    frame (None: unregistered), each registered frame's quality in [0, 1], the pose graph's result, why each
    unregistered frame is, the frames of the parts not joined to the reference, the edges whose stored verdict
    this run changed (pruned ones a resumed run restored, refused ones the steady motion admitted), and the
    capture's steady motion with the edges it decided that stayed accepted (`SteadyMotion.to_json`; None
    with too few consecutive edges)."""

    edges: list[Edge]
    T_world_cam: list[np.ndarray | None]
    quality: dict[int, float]
    graph: PoseGraphResult
    unregistered_reasons: dict[str, str]
    parts: list[list[str]]
    restored: set[tuple[str, str]]
    motion: dict | None = None


def capture_noise(frames: SequenceFrames, params: RegisterParams, pilot_pairs: int, pool: ThreadPoolExecutor
                  ) -> tuple[DepthNoise, DepthNoise, DepthNoise]:
    """The capture's noise, of a lifted keypoint and of a depth pixel, the latter per axis and along the ray
    (`gscan.registration.noise`; `RegisterParams.noise`, `depth_noise`, `depth_noise_ray`): up to
    `pilot_pairs` sequential pairs spread evenly over the capture, registered under the priors of `params`;
    the keypoint residuals of their inliers (less their keypoints' known location sigmas), and the distances of
    their depth samples to the other frame's surface within 5 prior sigmas, are fitted. A prior stays when too
    few pairs are left."""
    n = len(frames)
    picks = sorted({int(j) for j in np.linspace(1, n - 1, min(pilot_pairs, n - 1))}) if n > 1 else []

    def pair(j: int) -> tuple[np.ndarray, ...]:
        fs, ft = frames.reg(j - 1), frames.reg(j)
        r = register_features(fs.feats, ft.feats, params, dense=(fs.dense, ft.dense))
        if not r.accepted or r.T_tgt_src is None or r.inliers is None or not len(r.inliers):
            return (np.zeros(0),) * 9
        ps = fs.feats.points[r.inliers[:, 0]].astype(np.float64)
        pt = ft.feats.points[r.inliers[:, 1]].astype(np.float64)
        loc = np.hypot(fs.feats.location_sigma[r.inliers[:, 0]], ft.feats.location_sigma[r.inliers[:, 1]])
        d = plane_residuals(fs.dense, ft.dense, r.T_tgt_src)
        near = np.abs(d.e) < 5.0 * params.depth_noise.pair_sigma(d.z_src, d.z_tgt)
        return (np.linalg.norm(transform_points(r.T_tgt_src, ps) - pt, axis=1), ps[:, 2], pt[:, 2], loc,
                d.e[near], d.z_src[near], d.z_tgt[near], d.cos_src[near], d.cos_tgt[near])

    got = list(pool.map(pair, picks))
    if not got:
        return params.noise, params.depth_noise, params.depth_noise_ray
    r, za, zb, loc, e, da, db, ca, cb = (np.concatenate(x) for x in zip(*got, strict=True))
    return (estimate_noise(r, za, zb, prior=params.noise, loc=loc),
            estimate_noise(e, da, db, prior=params.depth_noise, dof=1),
            estimate_noise(e, da, db, prior=params.depth_noise_ray, dof=1, cosines=(ca, cb)))


def register_edges(reg: Registrar, params: SequenceParams, pool: ThreadPoolExecutor,
                   advance: Callable[[int], None]) -> list[Edge]:
    """Sequential edges (with fall-back to earlier frames), then loop closures; each handed to the sink as
    computed, the sequential ones committed before the loop closures. `advance(1)` per frame after the first."""
    frames, names = reg.frames, reg.names
    n = len(names)
    index = {nm: k for k, nm in enumerate(names)}
    edges: list[Edge] = []
    # each frame against its predecessor; a frame that fails is tried against earlier ones
    for e in reg.register([(j - 1, j) for j in range(1, n)], "sequential", pool):
        edges.append(e)
        j = index[e.tgt]
        for i in range(j - 2, max(-1, j - 1 - params.max_skip), -1):
            if edges[-1].accepted:
                break
            edges += reg.register([(i, j)], "sequential", pool)
        advance(1)
    reg.sink.commit()  # the sequential edges, before the loop closures

    seq_graph = [GraphEdge(index[e.src], index[e.tgt], e.T_tgt_src, weight=len(e.matches))
                 for e in edges if e.accepted and e.T_tgt_src is not None]
    T_init = spanning_poses(n, seq_graph)
    existing = [(index[e.src], index[e.tgt]) for e in edges]
    # frames without any keypoint (textureless, dark) take no part: bag-of-words needs descriptors
    kp = [k for k in range(n) if frames.n_keypoints(k)]
    sub = {k: s for s, k in enumerate(kp)}
    cands = [] if len(kp) < 2 else select_loop_candidates(
        [T_init[k] for k in kp], _Lazy(len(kp), lambda s: frames.descriptors(kp[s])),
        [(sub[a], sub[b]) for a, b in existing if a in sub and b in sub], params.loop_params(),
        [frames.depth_m(k) for k in kp])
    edges += reg.register([(kp[c.i], kp[c.j]) for c in cands], "loop", pool)
    return edges


class _Lazy(Sequence[np.ndarray]):
    """[n] arrays made on demand by `get(i)` (a sequence read one item at a time, nothing kept)."""

    def __init__(self, n: int, get: Callable[[int], np.ndarray]):
        self.n, self.get = n, get

    def __len__(self) -> int:
        return self.n

    @overload
    def __getitem__(self, i: int) -> np.ndarray: ...

    @overload
    def __getitem__(self, i: slice) -> list[np.ndarray]: ...

    def __getitem__(self, i: int | slice) -> np.ndarray | list[np.ndarray]:
        if isinstance(i, slice):
            return [self[j] for j in range(*i.indices(self.n))]
        if not -self.n <= i < self.n:
            raise IndexError(i)
        return self.get(i % self.n)


def odometry(n: int, edges: list[Edge], index: dict[str, int]) -> tuple[list[np.ndarray | None], np.ndarray]:
    """The capture's odometry: T_world_cam chained along the accepted sequential edges (between frames adjacent
    in the capture, or a frame and one of the few before it), per part of their chain ([n] poses or None; [n]
    part ids, -1 for a frame none of them reaches)."""
    seq = [GraphEdge(index[e.src], index[e.tgt], e.T_tgt_src, weight=len(e.matches)) for e in edges
           if e.accepted and e.kind == "sequential" and e.T_tgt_src is not None]
    T: list[np.ndarray | None] = [None] * n
    part = np.full(n, -1)
    for root in sorted({k for g in seq for k in (g.src, g.tgt)}):
        if part[root] < 0:
            for k, T_k in enumerate(spanning_poses(n, seq, root=root)):
                if T_k is not None:
                    T[k], part[k] = T_k, root
    return T, part


def against_odometry(n: int, edges: list[Edge], index: dict[str, int], max_sigma_deg: float,
                     sigmas: float = SequenceParams.odometry_sigmas) -> None:
    """Rejects the accepted edges between frames far apart in the capture whose rotation contradicts the
    capture's odometry (`odometry`) by more than its drift can: `sigmas` times registration's largest
    accepted rotation sigma (`max_sigma_deg`) for every frame between the two. Such an edge matched look-alike
    faces of the object (a box printed alike front and back, seen from opposite sides: 180 deg off), and several
    of them agree with each other: they would outvote the right edges in the pose graph. Edges between parts
    of the odometry are left to the pose graph."""
    T, part = odometry(n, edges, index)
    for e in edges:
        if not e.accepted or e.kind == "sequential" or e.T_tgt_src is None:
            continue
        i, j = index[e.src], index[e.tgt]
        T_i, T_j = T[i], T[j]
        if T_i is None or T_j is None or part[i] != part[j]:
            continue
        deg = rotation_angle_deg(e.T_tgt_src[:3, :3] @ T_i[:3, :3].T @ T_j[:3, :3])
        bound = sigmas * max_sigma_deg * abs(j - i)
        if deg > bound:
            e.accepted = False
            e.reason = (f"{PRUNED}{AGAINST_ODOMETRY} ({deg:.0f} deg from the pose the frames between its two give; "
                        f"their drift reaches {bound:.0f} deg at most)")


def capture_motion(edges: list[Edge], index: dict[str, int], min_steps: int, depth: float = 0.0
                   ) -> SteadyMotion | None:
    """The capture's steady motion (`gscan.registration.motion`) from the edges between consecutive frames that
    registration accepted (the pose graph's verdict aside: the same steps however often the graph is optimised),
    positions compared at `depth` m along the optical axis (the object's); None with fewer than `min_steps` of
    them."""
    return steady_motion([e.T_tgt_src for e in edges if e.kind == "sequential" and e.T_tgt_src is not None
                          and (e.accepted or e.pruned) and index[e.tgt] - index[e.src] == 1], min_steps, depth)


def _pinned(motion: SteadyMotion, gap: int, depth: float, rparams: RegisterParams) -> bool:
    """Whether the steady motion's prediction over `gap` frames is as tight as registration asks of an edge
    (`max_sigma_deg`, `max_sigma_rel` of the points' depth `depth`, m)."""
    s_deg, s_m = motion.sigma(gap)
    return gap >= 1 and s_deg <= rparams.max_sigma_deg and s_m <= rparams.max_sigma_rel * depth


def motion_pins(motion: SteadyMotion, T_tgt_src: np.ndarray, gap: int, depth: float, rparams: RegisterParams,
                sigmas: float) -> bool:
    """Whether the capture's steady motion pins the pose over `gap` frames (`_pinned`) and T_tgt_src [4 x 4] agrees
    with it (within `sigmas` of the spreads)."""
    return _pinned(motion, gap, depth, rparams) and motion.agrees(T_tgt_src, gap, sigmas)


def _steps_depth(reg: Registrar, edges: list[Edge], index: dict[str, int]) -> float:
    """The median depth (m) of the source points of the accepted edges between consecutive frames (`source_depth`):
    where the object lies, at which the steady motion compares positions; 0 without such edges."""
    depths = [source_depth(e, reg.frames.reg(index[e.src])) for e in edges
              if e.accepted and e.kind == "sequential" and index[e.tgt] - index[e.src] == 1
              and e.T_tgt_src is not None and len(e.matches)]
    return float(np.median(depths)) if depths else 0.0


def admit_by_motion(motion: SteadyMotion, edges: list[Edge], index: dict[str, int], sigmas: float,
                    min_matches: int, rparams: RegisterParams, depth: Callable[[Edge], float]) -> list[Edge]:
    """Accepts the refused edges whose pose the capture's steady motion vouches for (the assumption of a sequential
    edge over skipped frames, `gscan.registration.edges.Registrar`: the capture turns as its accepted steps do);
    returns them, marked `depth_only` (the depth alone posed them).
    - Loop closures the depth alone decided, refused as ambiguous (`LOOP_DEPTH_ONLY`: a plain box's half turn fits
      its depth as well): the pose lies within `sigmas` of the prediction's spreads over its frames' gap, and that
      bound D stays below half a quarter turn, so each turn, at least 90 deg from the pose, lies at least 90 - D > D
      from the prediction. Only on `min_matches` or more (`bridge_min_matches`): the prediction over many frames
      tells the turns apart, not a slide of a centimetre, and two loop closures on a plain box's 7-8 image
      keypoints, 0.7-1.5 deg off, together joined two parts 2 cm apart. Not those on image keypoints of plain frames
      (`LOOP_TURN`): 12 of a plain box's corners and rims placed one 1.3 deg off.
    - Poses the depth alone decided that the shape's checks refused (`refused_by_shape`: the depth seen through,
      the silhouette, the outline; a plain box seen edge on loses depth at its rims, which these count against the
      pose): where the motion pins the pose as registration would (`motion_pins`, `depth`: the median depth of the
      edge's source points, m), a slide or turn those checks refute lies beyond it."""
    admitted = []
    for e in edges:
        if e.accepted or e.T_tgt_src is None:
            continue
        gap = index[e.tgt] - index[e.src]
        if e.kind == "loop" and e.reason == LOOP_DEPTH_ONLY and len(e.matches) >= min_matches:
            vouched = (gap >= 1 and sigmas * motion.sigma(gap)[0] < SEQUENTIAL_MAX_TURN_DEG / 2
                       and motion.agrees(e.T_tgt_src, gap, sigmas))
        else:
            vouched = refused_by_shape(e.reason) and motion_pins(motion, e.T_tgt_src, gap, depth(e), rparams, sigmas)
        if vouched:
            e.accepted, e.reason, e.depth_only = True, None, True
            admitted.append(e)
    return admitted


def bridge_strength(motion: SteadyMotion | None, e: Edge, gap: int, depth: float, rparams: RegisterParams,
                    params: SequenceParams) -> bool:
    """Whether edge e (over `gap` frames, its points `depth` m away) has evidence enough to join two parts of the
    pose graph alone: enough matches (`bridge_min_matches`; its depth agreement is a condition of every accepted
    edge), or the capture's steady motion pinning its pose over the gap and e agreeing with it (`motion_pins`)."""
    if len(e.matches) >= params.bridge_min_matches:
        return True
    return (motion is not None and e.T_tgt_src is not None
            and motion_pins(motion, e.T_tgt_src, gap, depth, rparams, params.steady_sigmas))


def motion_bridges(n: int, spans: list[tuple[int, int]], motion: SteadyMotion, max_skip: int,
                   rparams: RegisterParams) -> list[GraphEdge]:
    """Weak pose-graph edges the capture's steady motion lays over its breaks: where no accepted edge spans consecutive
    frames k0 .. k1 + 1 (`spans`: the accepted edges' (i, j), i < j; one over more than `max_skip` frames spans nothing:
    a loop closure), an edge from k0 to k1 + 1 at the motion's prediction, its information the prediction's spread over
    the gap, where that pins the pose as tightly as registration asks of an edge (`max_sigma_deg`, `max_sigma_rel` of
    the depth the motion compares positions at, `motion.at`). Not `strong`: the pose graph cuts one that alone joins two
    parts, so the motion never places a part alone; where two such edges join the same parts, or a loop closure joins
    them too, the cycle through them must close within the noise (the graph's consistency test), which checks the motion
    over the breaks against the registered frames (a ring of 36 turntable frames split twice: the halves' chains and the
    two predictions turn 360 deg together). The frames inside a break stay without a pose."""
    depth = float(motion.at[2])
    covered = np.zeros(max(n - 1, 0), bool)
    for i, j in spans:
        if j - i <= max_skip:
            covered[i:j] = True
    out, k = [], 0
    while k < n - 1:
        if covered[k]:
            k += 1
            continue
        k1 = k
        while k1 + 1 < n - 1 and not covered[k1 + 1]:
            k1 += 1
        a, b = k, k1 + 1
        s_deg, s_m = motion.sigma(b - a)
        if min(s_deg, s_m) > 0 and _pinned(motion, b - a, depth, rparams):
            info = np.diag([np.radians(s_deg) ** -2] * 3 + [s_m ** -2] * 3)
            out.append(GraphEdge(a, b, motion.predict(b - a), info, strong=False, weight=0.0, depth=depth))
        k = b
    return out


def _optimise(reg: Registrar, edges: list[Edge], index: dict[str, int], params: SequenceParams,
              motion: SteadyMotion | None) -> tuple[list[np.ndarray | None], dict[int, float], PoseGraphResult]:
    """Pose graph over accepted edges (those that contradict the odometry rejected first, `against_odometry`;
    refused edges the capture's steady motion vouches for accepted, `admit_by_motion`)
    -> (T_world_cam per frame or None, quality in [0, 1] per frame, the pose graph's result with edge indices
    into the accepted edges)."""
    n, rparams, evidence = len(reg.names), reg.rparams, reg.evidence
    if motion is not None:
        def depth(e: Edge) -> float:  # nan without matches: pins nothing
            return source_depth(e, reg.frames.reg(index[e.src]))

        admitted = admit_by_motion(motion, edges, index, params.steady_sigmas, params.bridge_min_matches, rparams,
                                   depth)
        reg.by_motion |= {(e.src, e.tgt) for e in admitted}
        reg.restored |= reg.by_motion  # stored refused: written again with this verdict
    against_odometry(n, edges, index, rparams.max_sigma_deg, params.odometry_sigmas)
    use = [e for e in edges if e.accepted and e.T_tgt_src is not None]
    graph = []
    found: list[Evidence] = []
    for e in use:
        assert e.T_tgt_src is not None  # use: accepted edges with a pose
        i, j = index[e.src], index[e.tgt]
        ev = evidence.get((e.src, e.tgt))
        if ev is None:  # an edge a resumed scan took from the database
            ev = evidence[(e.src, e.tgt)] = edge_evidence(e, reg.frames.reg(i), reg.frames.reg(j), rparams)
        found.append(ev)
        strong = bridge_strength(motion, e, j - i, ev.depth, rparams, params)
        graph.append(GraphEdge(i, j, e.T_tgt_src, ev.info, strong=strong, weight=len(e.matches), depth=ev.depth))
    bridges = [] if motion is None else motion_bridges(
        n, [(min(g.src, g.tgt), max(g.src, g.tgt)) for g in graph], motion, params.max_skip, rparams)
    res = optimize_pose_graph(n, graph + bridges, spanning_poses(n, graph + bridges), params.graph_params())
    reg.bridged = [(rep.src, rep.tgt) for rep in res.edges[len(graph):] if rep.accepted]
    res.edges = res.edges[:len(graph)]  # the registered edges' verdicts; the bridges' are reg.bridged
    best: dict[int, float] = {}
    for rep, e, ev in zip(res.edges, use, found, strict=True):
        # the pose graph's verdict joins the registration's: pruned edges are recorded as rejected
        if not rep.accepted:
            e.accepted = False
            e.reason = PRUNED + str(rep.reason)
            continue
        for k in (index[e.src], index[e.tgt]):
            best[k] = min(best.get(k, np.inf), ev.rms)
    # registration quality of a view in [0, 1] (1 = perfect): 1 - RMS / quality_rms_sigma of its best edge
    quality = {k: float(np.clip(1.0 - r / params.quality_rms_sigma, 0.0, 1.0)) for k, r in best.items()}
    return res.T_world_node, quality, res


def cut_frames(n: int, edges: list[Edge], index: dict[str, int], graph: PoseGraphResult) -> list[int]:
    """Frames the pose graph left without a pose although registration accepted an edge of theirs, each on its
    own (not in a separate part): their edges disagree with each other and no cycle decides, or a weak edge
    alone held them."""
    in_part = {k for part in graph.parts for k in part}
    pruned = {index[x] for e in edges if e.pruned for x in (e.src, e.tgt)}
    return [k for k in range(n) if graph.T_world_node[k] is None and k in pruned and k not in in_part]


def second_opinions(cut: list[int], edges: list[Edge], index: dict[str, int],
                    T_world: list[np.ndarray | None], count: int) -> list[tuple[int, int]]:
    """For each cut frame, pairs (earlier frame first) with the `count` registered frames it has no edge
    with whose orientation is nearest the one its strongest pruned edge to a registered frame puts it at (a view
    of the same surface): edges that close cycles through it, to decide between its edges."""
    tried = {frozenset((index[e.src], index[e.tgt])) for e in edges}
    pairs = []
    for k in cut:
        implied = []  # (matches, src, tgt, T_world_k) of its pruned edges to registered frames
        for e in edges:
            i, j = index[e.src], index[e.tgt]
            T_i, T_j, T_ji = T_world[i], T_world[j], e.T_tgt_src
            if not e.pruned or str(e.reason).startswith(PRUNED + AGAINST_ODOMETRY) or T_ji is None:
                continue
            if i == k and T_j is not None:
                implied.append((-len(e.matches), e.src, e.tgt, T_j @ T_ji))
            elif j == k and T_i is not None:
                implied.append((-len(e.matches), e.src, e.tgt, T_i @ inv_T(T_ji)))
        if not implied:
            continue
        T_k = min(implied, key=lambda x: x[:3])[3]
        R_k = T_k[:3, :3]
        near = sorted((rotation_angle_deg(R_k.T @ T[:3, :3]), i) for i, T in enumerate(T_world)
                      if T is not None and frozenset((i, k)) not in tried)
        pairs += [(min(i, k), max(i, k)) for _, i in near[:count]]
    return pairs


def optimise_sequence(reg: Registrar, edges: list[Edge], params: SequenceParams, pool: ThreadPoolExecutor
                      ) -> SequenceResult:
    """The pose graph over `edges` (`register_edges`'), and second opinions on the frames it cuts loose.

    A cut frame is registered to more frames (`second_opinions`, appended to `edges`); the edges that held it (cut
    as thin evidence, not rejected as inconsistent) are put back beside the accepted new ones and the graph is
    optimised again. New edges may only confirm: a frame the second optimisation places without one of its holding
    edges (the new ones overturned them) is cut again, its new edges rejected, and the graph optimised a third
    time without them."""
    index = {nm: k for k, nm in enumerate(reg.names)}
    # the steps are the same for every optimisation below: second opinions add loop closures only
    motion = capture_motion(edges, index, params.steady_min_steps, _steps_depth(reg, edges, index))
    T_world_cam, quality, graph = _optimise_with_second_opinions(reg, pool, edges, index, params, motion)
    names = reg.names
    decided = sum(1 for e in edges if e.accepted and (e.src, e.tgt) in reg.by_motion)
    bridges = [[names[a], names[b]] for a, b in reg.bridged]
    if motion is not None:
        log.info("steady motion: %.2f deg a frame (spread %.2f deg, %.1f mm over %d steps); %d refused edges it "
                 "accepted; %d breaks it bridged", rotation_angle_deg(motion.T_step), motion.sigma_deg,
                 1000 * motion.sigma_m, motion.steps, decided, len(bridges))
    return SequenceResult(edges, T_world_cam, quality, graph, unregistered_reasons(reg.frames, edges, graph, index),
                          [[names[k] for k in part] for part in graph.parts], reg.restored,
                          None if motion is None else motion.to_json(decided, bridges))


def _optimise_with_second_opinions(reg: Registrar, pool: ThreadPoolExecutor, edges: list[Edge],
                                   index: dict[str, int], params: SequenceParams, motion: SteadyMotion | None
                                   ) -> tuple[list[np.ndarray | None], dict[int, float], PoseGraphResult]:
    n = len(reg.names)
    first = _optimise(reg, edges, index, params, motion)
    cut = cut_frames(n, edges, index, first[2])
    if not cut:
        return first
    with reg.sink.batch():
        more = reg.register(second_opinions(cut, edges, index, first[0], params.second_opinions), "loop", pool)
    edges += more
    if not any(e.accepted for e in more):
        return first
    log.info("pose graph: %d frames cut loose, %d of %d more edges accepted; optimising again", len(cut),
             sum(e.accepted for e in more), len(more))
    held: dict[int, list[tuple[Edge, str]]] = {}  # cut frame -> its holding edges, with their first verdicts
    for e in edges:
        i, j = index[e.src], index[e.tgt]
        why = e.reason
        if not why or not why.startswith(PRUNED) or why.startswith((PRUNED + INCONSISTENT, PRUNED + AGAINST_ODOMETRY)):
            continue
        for k, other in ((i, j), (j, i)):
            if k in cut and first[0][other] is not None:
                held.setdefault(k, []).append((e, why))
                e.accepted, e.reason = True, None
    judged = [e for e in edges if e.accepted]
    second = _optimise(reg, edges, index, params, motion)
    overturned = [k for k in cut if second[0][k] is not None and not any(e.accepted for e, _ in held.get(k, []))]
    if not overturned:
        return second
    names = {reg.names[k] for k in overturned}
    log.info("pose graph: new edges overturn the edges of %s; cut again", ", ".join(sorted(names)))
    for e in judged:  # the second optimisation's input, without the overturning edges
        e.accepted, e.reason = True, None
    for e in more:
        if e.accepted and {e.src, e.tgt} & names:
            e.accepted, e.reason = False, PRUNED + "a second opinion that overturns its frame's edges instead of " \
                                                   "confirming them"
    for k in overturned:
        for e, why in held.get(k, []):
            e.accepted, e.reason = False, why
    return _optimise(reg, edges, index, params, motion)


def unregistered_reasons(frames: SequenceFrames, edges: list[Edge], graph: PoseGraphResult,
                         index: dict[str, int]) -> dict[str, str]:
    """Why each frame without a pose has none, in one line: no keypoints, no edge accepted (the reasons of
    its edges, the nearest frame first), edges rejected by the pose graph, or a part of its own."""
    out: dict[str, str] = {}
    for k, name in enumerate(frames.names):
        if graph.T_world_node[k] is not None:
            continue
        if not frames.n_keypoints(k):
            out[name] = NO_KEYPOINTS
            continue
        if k in graph.node_reasons:
            out[name] = graph.node_reasons[k]
            continue
        mine = sorted((e for e in edges if name in (e.src, e.tgt)),
                      key=lambda e: (abs(index[e.src] - index[e.tgt]), e.src, e.tgt))
        if not mine:
            out[name] = "no other frame to register it to"
            continue
        pruned = [e for e in mine if e.pruned]
        shown = pruned if pruned else mine
        detail = "; ".join(f"with {e.tgt if e.src == name else e.src}: "
                           f"{(e.reason or 'accepted').removeprefix(PRUNED)}" for e in shown[:2])
        more = f" (and {len(shown) - 2} more)" if len(shown) > 2 else ""
        what = "its edges were rejected by the pose graph" if pruned else "no edge accepted"
        out[name] = f"{what}: {detail}{more}"
    return out
