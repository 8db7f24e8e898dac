"""Pose graph: global optimisation of the frames' poses, with every edge tested against the others.

Conventions (open3d's `PoseGraphEdge(source, target, transformation)`):

- An edge `(i, j, T_j_i)` has source node `i`, target node `j` and the measured transform `T_j_i` that maps
  points of frame `i` into frame `j` (`registration.pairwise.PairResult.T_tgt_src`).
- A node pose is `T_world_node`: it maps node-frame points into the common frame. An edge is consistent
  when `T_world_j @ T_j_i == T_world_i`.
- An edge's residual under the node poses is the small motion e = (rotation vector, translation) of
  `inv(T_j_i) @ inv(T_world_j) @ T_world_i`, in the source frame (open3d's own residual), its information
  [6 x 6] (rotation first) that of its pose from the matched points in the SOURCE frame, each weighted by its
  noise (`information_from_points`), and its chi^2 = e^T information e.

`optimize_pose_graph` starts from poses chained along a maximum spanning tree (strongest edges first),
optimises each connected part of the graph (open3d Levenberg-Marquardt, no line process) a few times
with the edges re-weighted by how much they disagree (graduated Cauchy weights: a wrong edge cannot drag
the others, and drift is spread over its cycle), then tests every edge: an edge is inconsistent when its
chi^2 exceeds the chi^2 quantile of 6 degrees of freedom at `1 - alpha`. The most inconsistent edge is
rejected and the re-weighted optimisation repeated, until every edge is consistent; edges rejected on the
way that agree with the final poses are re-admitted once.

An edge's information counts its matched points as independent; the errors they share (a depth bias, a
colour/depth offset, an intrinsics error) do not average out, so an edge with 700 pairs is not 10 times
better than one with 70. Every edge's covariance gets a floor: inv(information) + f^2 diag(1, 1, 1, d^2,
d^2, d^2), f a rotation (rad) common to all edges, d the edge's median depth (a rotation error's lever on
the position). f is fitted once, after the re-weighted start, so that the median chi^2 over all edges is
the median of chi^2 with 6 degrees of freedom (0 when the noise alone explains them): edges are judged
against each other, not against an absolute constant, and the strong ones do not make a weak wrong one
look small.

Then no frame hangs on thin evidence:
- an edge that alone joins two parts of the graph (a bridge) must be `strong` (the caller decides: enough
  matches and the depth's agreement); a weak bridge is cut;
- a node held by a single edge while another of its edges was rejected is cut loose (two measurements
  disagree and no cycle decides between them).
The largest part (most nodes; the earliest on ties) is the registered one; its first node is the reference
(its initial pose is kept). Every other part is reported (`PoseGraphResult.parts`) and gets no pose.

Loop-closure candidates (`select_loop_candidates`) live in `gscan.registration.loops` and are re-exported.
"""
from __future__ import annotations

import heapq
import logging
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from gscan.geometry.transforms import inv_T, rotation_angle_deg
from gscan.registration.loops import LoopCandidate, LoopParams, bow_vectors, select_loop_candidates
from gscan.registration.params import PoseGraphParams

__all__ = [
    "EdgeReport",
    "GraphEdge",
    "LoopCandidate",
    "LoopParams",
    "PoseGraphParams",
    "PoseGraphResult",
    "bow_vectors",
    "bridges",
    "edge_chi2",
    "edge_residual",
    "information_from_points",
    "optimize_pose_graph",
    "select_loop_candidates",
    "spanning_poses",
]

log = logging.getLogger(__name__)

CHI2_6_MEDIAN = 5.3481  # median of the chi^2 distribution with 6 degrees of freedom (the floor's target)
INCONSISTENT = "inconsistent with the other edges"  # how the reason of an edge the others contradict begins
ROBUST_SCALES = (100.0, 10.0, 1.0, 1.0)  # the graduated re-weighted optimisations (robust_start)


def information_from_points(points: np.ndarray, sigma: np.ndarray | None = None) -> np.ndarray:
    """[6 x 6] information of a pose from matched points [N x 3], for a small motion (rotation first) applied
    in the frame the points are given in, each point with per-axis standard deviation sigma [N] (m; None: 1
    per point, open3d's scale of one unit per correspondence).

    Sum of G^T G / sigma^2 with G = [-[p]x | I] per correspondence: the formula of open3d's
    `get_information_matrix_from_point_clouds`, weighted.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    w = np.ones(len(p)) if sigma is None else 1.0 / np.square(np.asarray(sigma, dtype=np.float64))
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    zero, one = np.zeros(len(p)), np.ones(len(p))
    info = np.zeros((6, 6))
    for G in (np.stack([zero, z, -y, one, zero, zero], 1),
              np.stack([-z, zero, x, zero, one, zero], 1),
              np.stack([y, -x, zero, zero, zero, one], 1)):
        info += (G * w[:, None]).T @ G
    return info


@dataclass
class GraphEdge:
    """A measured relative pose: `T_tgt_src` maps source-node points into the target node frame."""

    src: int
    tgt: int
    T_tgt_src: np.ndarray                  # [4 x 4]
    information: np.ndarray = field(default_factory=lambda: np.eye(6))  # [6 x 6], rotation first
    strong: bool = True                    # evidence enough to join two parts of the graph alone
    weight: float = 1.0                    # preference when poses are chained (spanning tree): e.g. inliers
    depth: float = 1.0                     # m, median depth of its points in the source frame (the floor's lever)


@dataclass
class EdgeReport:
    """Outcome of one input edge (same order as the input list)."""

    src: int
    tgt: int
    residual_deg: float                    # nan when an end node is unregistered
    residual_m: float
    chi2: float                            # its chi^2 with the floor (nan: an end node unregistered)
    accepted: bool
    reason: str | None                     # why it was rejected (None when accepted)


@dataclass
class PoseGraphResult:
    """Optimised poses and per-edge verdicts.

    T_world_node: per node [4 x 4] or None (not in the registered part). The world frame is the frame of
    the initial poses, anchored so that the reference node keeps its initial pose. parts: the node lists of
    the other parts (two or more nodes joined by accepted edges, largest first), which get no pose.
    """

    T_world_node: list[np.ndarray | None]
    edges: list[EdgeReport]
    reference_node: int
    rounds: int
    floor_deg: float  # the systematic error every edge was given beyond its noise (module docstring)
    parts: list[list[int]] = field(default_factory=list)
    node_reasons: dict[int, str] = field(default_factory=dict)  # why a node has no pose

    @property
    def registered(self) -> list[int]:
        return [i for i, T in enumerate(self.T_world_node) if T is not None]

    @property
    def unregistered(self) -> list[int]:
        return [i for i, T in enumerate(self.T_world_node) if T is None]

    def T_ref_node(self, i: int) -> np.ndarray | None:
        """[4 x 4] pose of node i in the reference node's frame (None when node i is unregistered)."""
        T, R = self.T_world_node[i], self.T_world_node[self.reference_node]
        return None if T is None or R is None else inv_T(R) @ T


def _rotvecs(R: np.ndarray) -> np.ndarray:
    """Rotation vectors [E x 3] of rotations R [E x 3 x 3] (angle from atan2: exact near 0 and near 180 deg).
    The norms are stacked 1 x 3 products: each row has the bits a rotation's own `np.linalg.norm` gives it."""
    R = np.asarray(R, dtype=np.float64)
    w = 0.5 * np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=1)
    s = np.sqrt(np.matmul(w[:, None, :], w[:, :, None])[:, 0, 0])
    c = (R[:, 0, 0] + R[:, 1, 1] + R[:, 2, 2] - 1.0) / 2.0
    small = s < 1e-12
    out = w / np.where(small, 1.0, s)[:, None] * np.arctan2(s, c)[:, None]
    for k in np.flatnonzero(small):
        if c[k] > 0:
            out[k] = 0.0
        else:  # 180 degrees: the axis from the symmetric part
            M = (R[k] + np.eye(3)) / 2.0
            axis = M[:, int(np.argmax(np.diag(M)))]
            out[k] = np.pi * axis / np.linalg.norm(axis)
    return out


def _inv_Ts(T: np.ndarray) -> np.ndarray:
    """Inverses [E x 4 x 4] of rigid transforms T [E x 4 x 4] (each as `inv_T` gives it)."""
    Rt = T[:, :3, :3].transpose(0, 2, 1)
    out = np.zeros_like(T)
    out[:, :3, :3] = Rt
    out[:, :3, 3] = -np.matmul(Rt, T[:, :3, 3, None])[..., 0]
    out[:, 3, 3] = 1.0
    return out


def _residual_motions(T_world_src: np.ndarray, T_world_tgt: np.ndarray, T_tgt_src: np.ndarray) -> np.ndarray:
    """[E x 4 x 4] inv(T_tgt_src) @ inv(T_world_tgt) @ T_world_src of [E x 4 x 4] stacks: the motion, in the source
    frame, by which the node poses disagree with each edge (identity = consistent)."""
    return _inv_Ts(T_tgt_src) @ _inv_Ts(T_world_tgt) @ T_world_src


def _residual_motion(T_world_src: np.ndarray, T_world_tgt: np.ndarray, T_tgt_src: np.ndarray) -> np.ndarray:
    """`_residual_motions` of one edge: [4 x 4]."""
    return _residual_motions(*(np.asarray(T, dtype=np.float64)[None] for T in (T_world_src, T_world_tgt,
                                                                               T_tgt_src)))[0]


def edge_residual(T_world_src: np.ndarray, T_world_tgt: np.ndarray, T_tgt_src: np.ndarray) -> tuple[float, float]:
    """(deg, m) of the edge's residual motion under the node poses (0, 0 = consistent)."""
    D = _residual_motion(T_world_src, T_world_tgt, T_tgt_src)
    return rotation_angle_deg(D[:3, :3]), float(np.linalg.norm(D[:3, 3]))


def edge_chi2(T_world_src: np.ndarray, T_world_tgt: np.ndarray, edge: GraphEdge) -> float:
    """chi^2 = e^T information e of the edge's residual e under the node poses."""
    D = _residual_motion(T_world_src, T_world_tgt, edge.T_tgt_src)
    e = np.concatenate([_rotvecs(D[None, :3, :3])[0], D[:3, 3]])
    return float(e @ np.asarray(edge.information, dtype=np.float64) @ e)


def _components(n: int, edges: list[tuple[int, int]]) -> list[list[int]]:
    """Connected components (sorted node lists) of an undirected graph, in order of their first node."""
    adj: list[list[int]] = [[] for _ in range(n)]
    for a, b in edges:
        adj[a].append(b)
        adj[b].append(a)
    seen = np.zeros(n, dtype=bool)
    out = []
    for root in range(n):
        if seen[root]:
            continue
        seen[root] = True
        comp, q = [root], deque([root])
        while q:
            a = q.popleft()
            for b in adj[a]:
                if not seen[b]:
                    seen[b] = True
                    comp.append(b)
                    q.append(b)
        out.append(sorted(comp))
    return out


def bridges(n: int, edges: list[tuple[int, int]]) -> set[int]:
    """Indices of the edges whose removal disconnects their component (iterative Tarjan; parallel edges
    between two nodes are never bridges)."""
    adj: list[list[tuple[int, int]]] = [[] for _ in range(n)]
    for k, (a, b) in enumerate(edges):
        adj[a].append((b, k))
        adj[b].append((a, k))
    disc = [-1] * n
    low = [0] * n
    out: set[int] = set()
    t = 0
    for root in range(n):
        if disc[root] >= 0:
            continue
        disc[root] = low[root] = t
        t += 1
        stack = [(root, -1, 0)]  # node, edge it was reached by, next neighbour position
        while stack:
            a, via, pos = stack[-1]
            if pos < len(adj[a]):
                stack[-1] = (a, via, pos + 1)
                b, k = adj[a][pos]
                if k == via:
                    continue
                if disc[b] < 0:
                    disc[b] = low[b] = t
                    t += 1
                    stack.append((b, k, 0))
                else:
                    low[a] = min(low[a], disc[b])
            else:
                stack.pop()
                if stack:
                    p = stack[-1][0]
                    low[p] = min(low[p], low[a])
                    if low[a] > disc[p]:
                        out.add(via)
    return out


def spanning_poses(n: int, graph_edges: list[GraphEdge], root: int | None = None,
                   T_root: np.ndarray | None = None) -> list[np.ndarray | None]:
    """Initial T_world_node per node by chaining edges from `root` (default: the first node with an edge),
    whose pose is `T_root` (default identity); None for nodes the edges do not reach.

    Poses are chained along a maximum spanning tree (Prim, from the root), strongest edge first (`weight`,
    ties by edge order), so that a weak edge never sets a frame's initial pose when a better one reaches it.
    """
    T: list[np.ndarray | None] = [None] * n
    if root is None:
        root = next((k for k in range(n) if any(k in (e.src, e.tgt) for e in graph_edges)), 0)
    T[root] = np.eye(4) if T_root is None else np.asarray(T_root, dtype=np.float64)
    adj: list[list[int]] = [[] for _ in range(n)]
    for k, e in enumerate(graph_edges):
        adj[e.src].append(k)
        adj[e.tgt].append(k)
    heap: list[tuple[float, int]] = []

    def push(a: int) -> None:
        for k in adj[a]:
            heapq.heappush(heap, (-float(graph_edges[k].weight), k))

    push(root)
    while heap:
        _, k = heapq.heappop(heap)
        e = graph_edges[k]
        if T[e.src] is not None and T[e.tgt] is None:
            T[e.tgt] = T[e.src] @ inv_T(e.T_tgt_src)
            push(e.tgt)
        elif T[e.tgt] is not None and T[e.src] is None:
            T[e.src] = T[e.tgt] @ e.T_tgt_src
            push(e.src)
    return T


def _optimize(poses: list[np.ndarray], edges: list[GraphEdge], active: list[int], nodes: list[int], ref: int,
              params: PoseGraphParams, infos: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
    """One open3d LM run (no line process) over the sub-graph `nodes` with edges `active` weighed by `infos`
    ([6 x 6] per edge), the reference node fixed. Returns the optimised T_world_node per node id."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    local = {g: k for k, g in enumerate(nodes)}
    pg = reg.PoseGraph()
    for g in nodes:
        pg.nodes.append(reg.PoseGraphNode(np.asarray(poses[g], dtype=np.float64)))
    for e in active:
        ed = edges[e]
        pg.edges.append(reg.PoseGraphEdge(local[ed.src], local[ed.tgt], np.asarray(ed.T_tgt_src, dtype=np.float64),
                                          infos[e], False, 1.0))
    criteria = reg.GlobalOptimizationConvergenceCriteria()
    criteria.max_iteration = params.max_iterations
    option = reg.GlobalOptimizationOption(max_correspondence_distance=1.0, edge_prune_threshold=0.0,
                                          preference_loop_closure=1.0, reference_node=local[ref])
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        reg.global_optimization(pg, reg.GlobalOptimizationLevenbergMarquardt(), criteria, option)
    return {g: np.asarray(pg.nodes[k].pose).copy() for k, g in enumerate(nodes)}


class _Graph:
    """The optimisation state of `optimize_pose_graph`: poses, and the floor of every edge's uncertainty. Edges'
    residuals, information and chi^2 are computed for many edges at once (stacks indexed by edge), each edge's
    value with the bits its own computation gives it."""

    def __init__(self, n: int, edges: list[GraphEdge], poses: list[np.ndarray], params: PoseGraphParams):
        from scipy.stats import chi2

        self.n, self.edges, self.params = n, edges, params
        self.poses = poses
        self.limit = float(chi2.ppf(1.0 - params.alpha, 6))
        self.floor = 0.0  # rad (module docstring)
        self.rounds = 0
        E = len(edges)
        self._src = np.array([ed.src for ed in edges], dtype=np.int64)
        self._tgt = np.array([ed.tgt for ed in edges], dtype=np.int64)
        self._T = np.array([ed.T_tgt_src for ed in edges], dtype=np.float64).reshape(E, 4, 4)
        self._info0 = np.array([ed.information for ed in edges], dtype=np.float64).reshape(E, 6, 6)
        self._cov = np.linalg.pinv(self._info0) if E else self._info0.copy()
        self._shape = np.array([np.diag([1.0, 1.0, 1.0] + [ed.depth ** 2] * 3) for ed in edges]).reshape(E, 6, 6)
        self._info: np.ndarray | None = None  # every edge's information with the current floor (when not 0)

    def infos(self, es: list[int] | np.ndarray) -> np.ndarray:
        """[E x 6 x 6] the edges' information with the current floor: inv(inv(information) + floor^2 diag(1, 1, 1,
        d, d, d)^2)."""
        if self.floor == 0.0:
            return self._info0[es]
        if self._info is None:
            self._info = np.linalg.inv(self._cov + self.floor ** 2 * self._shape)
        return self._info[es]

    def residuals(self, es: list[int] | np.ndarray) -> np.ndarray:
        """[E x 6] the edges' residuals (rotation vector, translation) under the current poses."""
        es = np.asarray(es, dtype=np.int64)
        P = np.array(self.poses, dtype=np.float64)
        D = _residual_motions(P[self._src[es]], P[self._tgt[es]], self._T[es])
        return np.concatenate([_rotvecs(D[:, :3, :3]), D[:, :3, 3]], axis=1)

    def chi2s(self, es: list[int] | np.ndarray) -> np.ndarray:
        """[E] the edges' chi^2 under the current poses and floor."""
        if len(es) == 0:
            return np.zeros(0)
        r = self.residuals(es)
        return np.matmul(np.matmul(r[:, None, :], self.infos(es)), r[:, :, None])[:, 0, 0]

    def chi2(self, e: int) -> float:
        return float(self.chi2s([e])[0])

    def set_floor(self, floor: float) -> None:
        self.floor, self._info = float(floor), None

    def update_floor(self, active: list[int]) -> None:
        """The floor at which the median chi^2 of the active edges is the median of chi^2_6 (0 when the noise
        alone explains them), by bisection on its logarithm over 1e-7..1 rad."""
        if not active:
            self.set_floor(0.0)
            return
        r = self.residuals(active)  # [E x 6]
        cov, shape = self._cov[active], self._shape[active]

        def median_chi2(f: float) -> float:  # one batched solve (each edge's value as its own solve gives it)
            x = np.linalg.solve(cov + f * f * shape, r[..., None])[..., 0]
            return float(np.median([a @ b for a, b in zip(r, x, strict=True)]))

        if median_chi2(0.0) <= CHI2_6_MEDIAN:
            self.set_floor(0.0)
            return
        lo, hi = np.log(1e-7), np.log(1.0)
        for _ in range(40):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if median_chi2(float(np.exp(mid))) > CHI2_6_MEDIAN else (lo, mid)
        self.set_floor(float(np.exp(hi)))

    def optimise(self, active: list[int], weights: dict[int, float] | None = None) -> None:
        """Optimise every part of the active graph; each part's first node keeps its pose."""
        infos = dict(zip(active, self.infos(active), strict=True)) if weights is None else \
            {e: weights[e] * info for e, info in zip(active, self.infos(active), strict=True)}
        for comp in _components(self.n, [(self.edges[e].src, self.edges[e].tgt) for e in active]):
            sub = [e for e in active if self.edges[e].src in set(comp)]
            if not sub:
                continue
            self.rounds += 1
            for g, T in _optimize(self.poses, self.edges, sub, comp, comp[0], self.params, infos).items():
                self.poses[g] = T

    def robust_start(self, active: list[int], fit_floor: bool) -> None:
        """Graduated, iteratively re-weighted optimisation: Cauchy weights 1 / (1 + chi2 / (scale x limit)) with
        the scale shrinking over ROBUST_SCALES (the floor refitted at each when `fit_floor`)."""
        for scale in ROBUST_SCALES:
            if fit_floor:
                self.update_floor(active)
            w = 1.0 / (1.0 + self.chi2s(active) / (scale * self.limit))
            self.optimise(active, dict(zip(active, w, strict=True)))


def optimize_pose_graph(n_nodes: int, edges: list[GraphEdge],
                        T_world_node_init: list[np.ndarray | None] | np.ndarray,
                        params: PoseGraphParams = PoseGraphParams()) -> PoseGraphResult:
    """Robust global optimisation of a pose graph (module docstring).

    n_nodes: number of frames; edges: measured relative poses; T_world_node_init: [n_nodes x 4 x 4] initial
    poses (None entries are filled by chaining edges, e.g. from `spanning_poses`).
    """
    if len(T_world_node_init) != n_nodes:
        raise ValueError(f"{len(T_world_node_init)} initial poses for {n_nodes} nodes")
    for edge in edges:
        if not (0 <= edge.src < n_nodes and 0 <= edge.tgt < n_nodes) or edge.src == edge.tgt:
            raise ValueError(f"invalid edge {edge.src} -> {edge.tgt} for {n_nodes} nodes")
    init = [None if T is None else np.asarray(T, dtype=np.float64).reshape(4, 4).copy() for T in T_world_node_init]
    filled = spanning_poses(n_nodes, edges)
    poses = [T if T is not None else (S if S is not None else np.eye(4)) for T, S in zip(init, filled, strict=True)]
    g = _Graph(n_nodes, edges, poses, params)
    reasons: dict[int, str] = {}
    active = list(range(len(edges)))

    def reject_until_consistent(fit_floor: bool) -> None:
        while active:
            # poses where the agreeing edges put them, outliers down-weighted; the floor is fitted once, with
            # every edge there: the rejections must not talk it down
            g.robust_start(active, fit_floor)
            fit_floor = False
            scores = g.chi2s(active)  # (active is sorted: the first largest is the lowest edge of the largest)
            k = int(np.argmax(scores))
            worst, e = float(scores[k]), active[k]
            if worst <= g.limit:
                return
            if g.rounds >= params.max_rounds:
                log.warning("pose graph: inconsistent edges left after %d rounds", g.rounds)
                return
            deg, m = edge_residual(g.poses[edges[e].src], g.poses[edges[e].tgt], edges[e].T_tgt_src)
            reasons[e] = (f"{INCONSISTENT} ({deg:.2f} deg / {m * 1000:.1f} mm off, "
                          f"chi2 {worst:.0f} > {g.limit:.0f})")
            active.remove(e)

    reject_until_consistent(fit_floor=True)
    # re-admission: an edge rejected while the graph was still distorted by a wrong one
    rejected = sorted(reasons)
    again = [e for e, c in zip(rejected, g.chi2s(rejected), strict=True) if c <= g.limit]
    if again:
        log.debug("pose graph: re-admitting %d edges consistent with the optimised poses", len(again))
        for e in again:
            del reasons[e]
        active[:] = sorted(active + again)
        reject_until_consistent(fit_floor=False)

    # thin evidence: weak bridges and contradicted leaves are cut (module docstring)
    while True:
        pairs = [(edges[e].src, edges[e].tgt) for e in active]
        cut = [active[k] for k in sorted(bridges(n_nodes, pairs)) if not edges[active[k]].strong]
        for e in cut:
            reasons[e] = "the only link between two parts of the graph, on weak evidence"
        cut += _contradicted_leaves(n_nodes, edges, active, reasons)
        if not cut:
            break
        active[:] = [e for e in active if e not in set(cut)]
    g.optimise(active)

    comps = _components(n_nodes, [(edges[e].src, edges[e].tgt) for e in active])
    main = max(comps, key=lambda c: (len(c), -c[0]))
    ref = main[0]
    in_main = set(main)
    T_out: list[np.ndarray | None] = [g.poses[k] if k in in_main else None for k in range(n_nodes)]
    parts = sorted((c for c in comps if c is not main and len(c) > 1), key=lambda c: (-len(c), c[0]))
    node_reasons: dict[int, str] = {}
    for c in parts:
        for k in c:
            node_reasons[k] = (f"in a separate part of {len(c)} frames that no confident edge joins to the "
                               f"{len(main)} registered ones")
    reports = []
    for k, ed in enumerate(edges):
        Ts, Tt = T_out[ed.src], T_out[ed.tgt]
        reason = reasons.get(k)
        if Ts is None or Tt is None:
            deg = m = c2 = float("nan")
            if reason is None:
                reason = "not in the registered part of the graph"
        else:
            deg, m = edge_residual(Ts, Tt, ed.T_tgt_src)
            c2 = g.chi2(k)
        reports.append(EdgeReport(ed.src, ed.tgt, deg, m, c2, reason is None, reason))
    log.info("pose graph: %d nodes (%d registered, %d other parts), %d/%d edges accepted, floor %.3f deg, "
             "%d optimisations", n_nodes, len(main), len(parts), sum(r.accepted for r in reports), len(reports),
             np.degrees(g.floor), g.rounds)
    return PoseGraphResult(T_out, reports, ref, g.rounds, float(np.degrees(g.floor)), parts, node_reasons)


def _contradicted_leaves(n: int, edges: list[GraphEdge], active: list[int], reasons: dict[int, str]) -> list[int]:
    """Active edges that alone hold a node while another edge of that node was rejected as inconsistent (two
    measurements disagree, no cycle decides); each gets its reason."""
    on = set(active)
    inc: list[list[int]] = [[] for _ in range(n)]
    for e, ed in enumerate(edges):
        inc[ed.src].append(e)
        inc[ed.tgt].append(e)
    out = []
    for k in range(n):
        held = [e for e in inc[k] if e in on]
        contradicted = any(e in reasons and reasons[e].startswith(INCONSISTENT) for e in inc[k])
        if len(held) == 1 and contradicted and held[0] not in out:
            reasons[held[0]] = "the only edge left to its frame, contradicted by another one of that frame's edges"
            out.append(held[0])
    return out
