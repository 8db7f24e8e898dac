"""Pose graph: loop-closure candidate selection, robust global optimisation, edge pruning.

Conventions (match open3d's `PoseGraphEdge(source, target, transformation)`):

- An edge `(i, j, T_j_i)` has source node `i`, target node `j` and the measured transform
  `T_j_i` that maps points of frame `i` into frame `j` (what `registration_icp(source=i,
  target=j)` returns, and what `register.PairResult.T_tgt_src` holds).
- A node pose is `T_world_node` (open3d's `PoseGraphNode.pose`): it maps node-frame points
  into the common frame. An edge is consistent when `T_world_j @ T_j_i == T_world_i`.
- The residual of an edge is `E = inv(T_j_i) @ inv(T_world_j) @ T_world_i` (identity when
  consistent), reported as (rotation angle in degrees, |translation| in metres).

`optimize_pose_graph` runs open3d's Levenberg-Marquardt optimiser with the line process
(uncertain edges = loop closures may be switched off), graduated: the correspondence distance
starts at `graduated_start` times the requested one (so the odometry drift does not switch off
correct loop closures) and is halved down to it. Then edges whose residual exceeds explicit
rotation / translation thresholds are rejected (all offending loop closures, else the worst
odometry edge) and the graph is re-optimised until every accepted edge is consistent; edges
dropped on the way that agree with the final poses are re-admitted once. Nodes that are no
longer connected to the reference node through accepted edges are reported as unregistered
and get no pose, and so is a node held by a single uncertain edge while another of its edges was
rejected (two measurements disagree, no cycle decides). Information matrices follow open3d's scale
(per correspondence, translation block = number of correspondences), which the line process
relies on.

Loop-closure candidates (`select_loop_candidates`) live in `gscan.registration.loops` and are re-exported.
"""
from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from gscan.geometry.transforms import inv_T, rotation_angle_deg
from gscan.registration.loops import LoopCandidate, LoopParams, bow_vectors, select_loop_candidates

__all__ = ["GraphEdge", "EdgeReport", "PoseGraphParams", "PoseGraphResult", "optimize_pose_graph",
           "chain_odometry", "edge_residual", "information_matrix", "information_from_points",
           "information_from_clouds", "information_from_count", "LoopCandidate", "LoopParams", "bow_vectors",
           "select_loop_candidates"]

log = logging.getLogger(__name__)


# ----------------------------------------------------------------------------- edges / information

def information_from_points(points_tgt: np.ndarray) -> np.ndarray:
    """[6 x 6] information matrix of an edge from its matched points in the TARGET frame.

    Same formula as open3d's `get_information_matrix_from_point_clouds` (sum of G^T G with
    G = [-[p]x | I] per correspondence, rotation first), so edges built from matches and
    edges built from dense clouds are on the same scale per correspondence.
    points_tgt: [N x 3] metres.
    """
    p = np.asarray(points_tgt, dtype=np.float64).reshape(-1, 3)
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    zero, one = np.zeros(len(p)), np.ones(len(p))
    info = np.zeros((6, 6))
    for G in (np.stack([zero, z, -y, one, zero, zero], 1),
              np.stack([-z, zero, x, zero, one, zero], 1),
              np.stack([y, -x, zero, zero, zero, one], 1)):
        info += G.T @ G
    return info


def information_from_clouds(src_pts: np.ndarray, tgt_pts: np.ndarray, T_tgt_src: np.ndarray,
                            max_correspondence_distance: float) -> np.ndarray:
    """[6 x 6] information via open3d's `get_information_matrix_from_point_clouds`.

    src_pts: [N x 3] source-frame points; tgt_pts: [M x 3] target-frame points; T_tgt_src: [4 x 4].
    """
    import open3d as o3d

    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(src_pts, dtype=np.float64)))
    tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(tgt_pts, dtype=np.float64)))
    return np.asarray(o3d.pipelines.registration.get_information_matrix_from_point_clouds(
        src, tgt, float(max_correspondence_distance), np.asarray(T_tgt_src, dtype=np.float64))).copy()


def information_from_count(n_matches: int, depth_m: float = 0.5, spread_m: float = 0.1) -> np.ndarray:
    """[6 x 6] diagonal information for `n_matches` correspondences when no points are at hand.

    Approximates `information_from_points` for n points at mean depth `depth_m` (along z) with a
    lateral spread `spread_m` (std in x and y): n * diag(d^2 + s^2, d^2 + s^2, 2 s^2, 1, 1, 1)
    (rotation first, cross terms dropped).
    """
    d2, s2 = depth_m ** 2, spread_m ** 2
    return float(max(n_matches, 1)) * np.diag([d2 + s2, d2 + s2, 2.0 * s2, 1.0, 1.0, 1.0])


def information_matrix(T_tgt_src: np.ndarray, n_matches: int,
                       clouds: tuple[np.ndarray, np.ndarray] | None = None,
                       max_correspondence_distance: float = 0.01) -> np.ndarray:
    """[6 x 6] information of an edge: from the clouds (src [N x 3] in the source frame, tgt [M x 3]
    in the target frame) through open3d when given, else from the match count."""
    if clouds is not None and len(clouds[0]) and len(clouds[1]):
        info = information_from_clouds(clouds[0], clouds[1], T_tgt_src, max_correspondence_distance)
        if info[5, 5] > 0:
            return info
    return information_from_count(n_matches)


@dataclass
class GraphEdge:
    """A measured relative pose: `T_tgt_src` maps source-node points into the target node frame."""

    src: int
    tgt: int
    T_tgt_src: np.ndarray                  # [4 x 4]
    information: np.ndarray = field(default_factory=lambda: np.eye(6))  # [6 x 6]
    uncertain: bool = False                # True for loop closures (line process may drop them)


@dataclass
class EdgeReport:
    """Outcome of one input edge (same order as the input list)."""

    src: int
    tgt: int
    uncertain: bool
    residual_deg: float                    # nan when an end node is unregistered
    residual_m: float
    accepted: bool
    reason: str | None                     # why it was rejected (None when accepted)


@dataclass
class PoseGraphResult:
    """Optimised poses and per-edge verdicts.

    T_world_node: per node [4 x 4] or None (unregistered). The world frame is the frame of the
    initial poses, anchored so that the reference node keeps its initial pose.
    """

    T_world_node: list[np.ndarray | None]
    edges: list[EdgeReport]
    reference_node: int
    rounds: int

    @property
    def registered(self) -> list[int]:
        return [i for i, T in enumerate(self.T_world_node) if T is not None]

    @property
    def unregistered(self) -> list[int]:
        return [i for i, T in enumerate(self.T_world_node) if T is None]

    def T_ref_node(self, i: int) -> np.ndarray | None:
        """[4 x 4] pose of node i in the reference node's frame (None when node i or the reference node
        is unregistered: the reference node can be left out as ambiguous, see `optimize_pose_graph`)."""
        T, R = self.T_world_node[i], self.T_world_node[self.reference_node]
        return None if T is None or R is None else inv_T(R) @ T


@dataclass(frozen=True)
class PoseGraphParams:
    max_correspondence_distance: float = 0.02   # m, scales the line process (open3d option), final stage
    # first stage uses this multiple of it, halved per stage; at 16 the first stage pruned right edges of
    # turntable scans (registered 10 / 24 and 8 / 24 frames; all 24 at 4), static scans unchanged
    graduated_start: float = 4.0
    edge_prune_threshold: float = 0.25           # line-process weight below which loop closures are dropped
    preference_loop_closure: float = 1.0         # open3d: weight of loop closures vs odometry
    max_residual_deg: float = 5.0                # explicit consistency thresholds after optimisation
    max_residual_m: float = 0.02
    prune_certain_edges: bool = True             # also check odometry (uncertain=False) edges
    max_rounds: int = 20                         # prune / re-optimise rounds
    max_iterations: int = 100                    # LM iterations per optimisation


def edge_residual(T_world_src: np.ndarray, T_world_tgt: np.ndarray, T_tgt_src: np.ndarray) -> tuple[float, float]:
    """(deg, m) of `inv(T_tgt_src) @ inv(T_world_tgt) @ T_world_src` (identity = consistent)."""
    E = inv_T(T_tgt_src) @ inv_T(T_world_tgt) @ T_world_src
    return rotation_angle_deg(E[:3, :3]), float(np.linalg.norm(E[:3, 3]))


def _component(n: int, edges: list[tuple[int, int]], root: int) -> list[int]:
    """Sorted node ids reachable from `root` through undirected `edges`."""
    adj: list[list[int]] = [[] for _ in range(n)]
    for a, b in edges:
        adj[a].append(b)
        adj[b].append(a)
    seen = np.zeros(n, dtype=bool)
    seen[root] = True
    q = deque([root])
    while q:
        a = q.popleft()
        for b in adj[a]:
            if not seen[b]:
                seen[b] = True
                q.append(b)
    return [int(i) for i in np.flatnonzero(seen)]


def _optimize(poses: list[np.ndarray], edges: list[GraphEdge], active: list[int], nodes: list[int],
              ref: int, params: PoseGraphParams) -> tuple[dict[int, np.ndarray], set[int]]:
    """One open3d LM run over the sub-graph `nodes` with edges `active`.

    Returns (optimised T_world_node per node id, indices of edges removed by the line process).
    """
    import open3d as o3d

    reg = o3d.pipelines.registration
    local = {g: k for k, g in enumerate(nodes)}
    pg = reg.PoseGraph()
    for g in nodes:
        pg.nodes.append(reg.PoseGraphNode(np.asarray(poses[g], dtype=np.float64)))
    for e in active:
        ed = edges[e]
        pg.edges.append(reg.PoseGraphEdge(local[ed.src], local[ed.tgt], np.asarray(ed.T_tgt_src, dtype=np.float64),
                                          np.asarray(ed.information, dtype=np.float64), ed.uncertain, 1.0))
    criteria = reg.GlobalOptimizationConvergenceCriteria()
    criteria.max_iteration = params.max_iterations
    # graduated line process: a large correspondence distance first (tolerates the odometry
    # drift, drops only gross outliers), halved down to the requested one; open3d removes the
    # edges whose line-process weight falls below edge_prune_threshold at every stage
    d = params.max_correspondence_distance * max(params.graduated_start, 1.0)
    while True:
        option = reg.GlobalOptimizationOption(max_correspondence_distance=d,
                                              edge_prune_threshold=params.edge_prune_threshold,
                                              preference_loop_closure=params.preference_loop_closure,
                                              reference_node=local[ref])
        with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
            reg.global_optimization(pg, reg.GlobalOptimizationLevenbergMarquardt(), criteria, option)
        if d <= params.max_correspondence_distance * 1.0001:
            break
        d = max(d / 2.0, params.max_correspondence_distance)
    out = {g: np.asarray(pg.nodes[k].pose).copy() for k, g in enumerate(nodes)}
    # open3d keeps the surviving edges in order: match them back to find the pruned ones
    kept = [(int(ed.source_node_id), int(ed.target_node_id), np.asarray(ed.transformation)) for ed in pg.edges]
    pruned: set[int] = set()
    k = 0
    for e in active:
        ed = edges[e]
        if k < len(kept) and kept[k][0] == local[ed.src] and kept[k][1] == local[ed.tgt] \
                and np.allclose(kept[k][2], ed.T_tgt_src):
            k += 1
        else:
            pruned.add(e)
    return out, pruned


def _fill_initial(poses: list[np.ndarray | None], edges: list[GraphEdge], ref: int) -> list[np.ndarray]:
    """Give every node without an initial pose one propagated through edges (BFS from known poses)."""
    out = list(poses)
    if out[ref] is None:
        out[ref] = np.eye(4)
    q = deque(i for i, T in enumerate(out) if T is not None)
    adj: list[list[GraphEdge]] = [[] for _ in out]
    for ed in edges:
        adj[ed.src].append(ed)
        adj[ed.tgt].append(ed)
    while q:
        a = q.popleft()
        for ed in adj[a]:
            if ed.src == a and out[ed.tgt] is None:  # T_w_tgt = T_w_src @ inv(T_tgt_src)
                out[ed.tgt] = out[a] @ inv_T(ed.T_tgt_src)
                q.append(ed.tgt)
            elif ed.tgt == a and out[ed.src] is None:  # T_w_src = T_w_tgt @ T_tgt_src
                out[ed.src] = out[a] @ np.asarray(ed.T_tgt_src, dtype=np.float64)
                q.append(ed.src)
    return [np.eye(4) if T is None else T for T in out]


def spanning_poses(n: int, graph_edges: list[GraphEdge], weights: list[float] | None = None,
                   root: int | None = None, T_root: np.ndarray | None = None) -> list[np.ndarray | None]:
    """Initial T_world_node per node by chaining edges from `root` (default: the first node with an
    edge), whose pose is `T_root` (default identity); None for nodes the edges do not reach.

    Poses are chained along a maximum spanning tree (Prim, from the root): certain edges before
    uncertain ones, each kind strongest first (`weights`, e.g. inlier counts; ties by edge order),
    so that a weak or doubtful edge never sets a frame's initial pose when a better one reaches it.
    """
    import heapq

    T: list[np.ndarray | None] = [None] * n
    if root is None:
        root = next((k for k in range(n) if any(k in (e.src, e.tgt) for e in graph_edges)), 0)
    T[root] = np.eye(4) if T_root is None else np.asarray(T_root, dtype=np.float64)
    w = weights if weights is not None else [1.0] * len(graph_edges)
    adj: list[list[int]] = [[] for _ in range(n)]
    for k, e in enumerate(graph_edges):
        adj[e.src].append(k)
        adj[e.tgt].append(k)
    heap: list[tuple[bool, float, int]] = []

    def push(a: int) -> None:
        for k in adj[a]:
            heapq.heappush(heap, (bool(graph_edges[k].uncertain), -float(w[k]), k))

    push(root)
    while heap:
        _, _, k = heapq.heappop(heap)
        e = graph_edges[k]
        if T[e.src] is not None and T[e.tgt] is None:
            T[e.tgt] = T[e.src] @ inv_T(e.T_tgt_src)
            push(e.tgt)
        elif T[e.tgt] is not None and T[e.src] is None:
            T[e.src] = T[e.tgt] @ e.T_tgt_src
            push(e.src)
    return T


def optimize_pose_graph(n_nodes: int, edges: list[GraphEdge],
                        T_world_node_init: list[np.ndarray | None] | np.ndarray,
                        params: PoseGraphParams = PoseGraphParams(), reference_node: int = 0) -> PoseGraphResult:
    """Robust global optimisation of a pose graph, then pruning of inconsistent edges.

    n_nodes: number of frames; edges: measured relative poses (see module docstring);
    T_world_node_init: [n_nodes x 4 x 4] initial poses (e.g. `chain_odometry`); None entries
    are initialised by propagating neighbours' poses through the edges.

    Each round: optimise the component of `reference_node` (open3d LM + line process), compute
    every active edge's residual, reject the edges beyond the thresholds (all offending loop
    closures at once if any, else the single worst odometry edge), and repeat until every
    accepted edge is consistent. Deterministic.
    """
    if not 0 <= reference_node < n_nodes:
        raise ValueError(f"reference node {reference_node} outside 0..{n_nodes - 1}")
    if len(T_world_node_init) != n_nodes:
        raise ValueError(f"{len(T_world_node_init)} initial poses for {n_nodes} nodes")
    for e in edges:
        if not (0 <= e.src < n_nodes and 0 <= e.tgt < n_nodes) or e.src == e.tgt:
            raise ValueError(f"invalid edge {e.src} -> {e.tgt} for {n_nodes} nodes")
    poses = _fill_initial([None if T is None else np.asarray(T, dtype=np.float64).reshape(4, 4).copy()
                           for T in T_world_node_init], edges, reference_node)
    anchor = poses[reference_node].copy()
    reasons: dict[int, str] = {}
    active = list(range(len(edges)))
    rounds = 0
    result: dict[int, np.ndarray] = {reference_node: poses[reference_node]}

    def score_of(e: int, res: dict[int, np.ndarray]) -> tuple[float, float, float]:
        ed = edges[e]
        deg, m = edge_residual(res[ed.src], res[ed.tgt], ed.T_tgt_src)
        return max(deg / params.max_residual_deg, m / params.max_residual_m), deg, m

    for attempt in range(2):
        while True:
            rounds += 1
            nodes = _component(n_nodes, [(edges[e].src, edges[e].tgt) for e in active], reference_node)
            in_comp = set(nodes)
            sub = [e for e in active if edges[e].src in in_comp]
            if not sub:
                result = {reference_node: poses[reference_node]}
                break
            result, pruned = _optimize(poses, edges, sub, nodes, reference_node, params)
            for e in sorted(pruned):
                reasons[e] = f"line process weight < {params.edge_prune_threshold}"
            active = [e for e in active if e not in pruned]
            sub = [e for e in sub if e not in pruned]
            # keep optimised poses as the next initial guess
            for g, T in result.items():
                poses[g] = T
            bad: list[tuple[float, int, float, float]] = []
            for e in sub:
                ed = edges[e]
                if not ed.uncertain and not params.prune_certain_edges:
                    continue
                score, deg, m = score_of(e, result)
                if score > 1.0:
                    bad.append((score, e, deg, m))
            if not bad and not pruned:
                break
            if not bad:
                continue  # line process removed edges: re-optimise without them
            if rounds >= params.max_rounds:
                log.warning("pose graph: %d inconsistent edges left after %d rounds", len(bad), rounds)
                break
            loops = [b for b in bad if edges[b[1]].uncertain]
            reject = loops if loops else [max(bad, key=lambda b: (b[0], -b[1]))]
            for _, e, deg, m in reject:
                reasons[e] = (f"residual {deg:.2f} deg / {m * 1000:.1f} mm beyond "
                              f"{params.max_residual_deg:g} deg / {params.max_residual_m * 1000:g} mm")
            rej = {b[1] for b in reject}
            active = [e for e in active if e not in rej]
            # restart from the surviving edges (a maximum spanning tree, certain edges first): poses
            # pulled by a wrong edge can sit in a local minimum, e.g. a 180-degree flip, that LM
            # does not leave
            kept = [edges[e] for e in active]
            tree = spanning_poses(n_nodes, kept, [float(np.trace(ed.information)) for ed in kept],
                                  reference_node, anchor)
            poses = [T if T is not None else poses[k] for k, T in enumerate(tree)]

        # recovery: an edge dropped while the graph was still distorted (early line-process stages,
        # or before a wrong edge was found) is re-admitted once if the final poses agree with it
        if attempt == 1:
            break
        recover = sorted(e for e in reasons if edges[e].src in result and edges[e].tgt in result
                         and score_of(e, result)[0] <= 1.0)
        if not recover:
            break
        log.debug("pose graph: re-admitting %d edges consistent with the optimised poses", len(recover))
        for e in recover:
            del reasons[e]
        active = sorted(active + recover)

    T_out: list[np.ndarray | None] = [result.get(i) for i in range(n_nodes)]
    _drop_ambiguous_leaves(T_out, edges, reasons)
    reports = []
    for k, ed in enumerate(edges):
        Ts, Tt = T_out[ed.src], T_out[ed.tgt]
        deg, m = edge_residual(Ts, Tt, ed.T_tgt_src) if Ts is not None and Tt is not None else (float("nan"),) * 2
        reason = reasons.get(k)
        if reason is None and (Ts is None or Tt is None):
            reason = "not connected to the reference node"
        reports.append(EdgeReport(ed.src, ed.tgt, ed.uncertain, deg, m, reason is None, reason))
    n_unreg = sum(T is None for T in T_out)
    log.info("pose graph: %d nodes (%d unregistered), %d/%d edges accepted, %d rounds",
             n_nodes, n_unreg, sum(r.accepted for r in reports), len(reports), rounds)
    return PoseGraphResult(T_out, reports, reference_node, rounds)


def _drop_ambiguous_leaves(T_out: list[np.ndarray | None], edges: list[GraphEdge], reasons: dict[int, str]) -> None:
    """Unregister (in place) every node held by a single uncertain edge while another of its edges was
    rejected: two measurements disagree and no cycle decides between them (a turntable's first frame
    had a right 21-inlier edge and a 180-deg-wrong 22-inlier one; keeping the survivor fused it flipped).
    Only the optimisation's rejections count. Nodes left without an edge to a registered node are
    unregistered too; when nothing would be left registered, nothing changes (a lone cycle of three
    with one inconsistent edge keeps its nodes). The reference node may go: the world frame is only the
    frame of the initial poses."""
    rejected = set(reasons)
    inc: list[list[int]] = [[] for _ in T_out]
    for e, ed in enumerate(edges):
        inc[ed.src].append(e)
        inc[ed.tgt].append(e)
    held = [[e for e in inc[k] if e not in rejected] for k in range(len(T_out))]
    drop = {k for k, T in enumerate(T_out)
            if T is not None and len(held[k]) == 1 and edges[held[k][0]].uncertain and len(inc[k]) > 1}
    if not drop:
        return
    keep = {k for k, T in enumerate(T_out) if T is not None and k not in drop}
    while True:  # nodes whose every held edge led to a dropped node
        alone = {k for k in keep if not any((edges[e].src if edges[e].tgt == k else edges[e].tgt) in keep
                                            for e in held[k])}
        if not alone:
            break
        keep -= alone
    if not keep:
        return
    for k in drop:
        reasons[held[k][0]] = "the only edge left to its frame, contradicted by another one of that frame's edges"
    for k, T in enumerate(T_out):
        if T is not None and k not in keep:
            T_out[k] = None


def chain_odometry(n_nodes: int, edges: list[GraphEdge]) -> list[np.ndarray | None]:
    """Initial T_world_node (world = node 0) by chaining the certain edges i -> i+1 / i+1 -> i.

    Nodes that the chain does not reach get None.
    """
    T: list[np.ndarray | None] = [None] * n_nodes
    T[0] = np.eye(4)
    step = {}
    for ed in edges:
        if ed.uncertain:
            continue
        if ed.tgt == ed.src + 1:
            step.setdefault(ed.src, inv_T(ed.T_tgt_src))  # T_i_{i+1}
        elif ed.src == ed.tgt + 1:
            step.setdefault(ed.tgt, np.asarray(ed.T_tgt_src, dtype=np.float64))
    for i in range(n_nodes - 1):
        if T[i] is not None and i in step:
            T[i + 1] = T[i] @ step[i]
    return T
