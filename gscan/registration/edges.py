"""The edges of a sequence: frame pairs registered into edges (`Registrar`), and the evidence the pose graph weighs
an accepted edge by (`edge_evidence`).

What the sequence's registration sees of a scan's frames is the small `SequenceFrames` interface (names, the
registration data of frame k, its descriptors, keypoint count and median depth); edges are handed to an
`EdgeSink` as they are computed (the scan stores them in its database).

- `Edge` (gscan.registration.edge): an edge between two frames of the sequence, as the template stores it
- `RegData`, `icp_cloud`: what registration uses of a frame
- `Registrar(frames, params, sink, stored)`: `.register(pairs, kind, pool) -> list[Edge]`
"""
from __future__ import annotations

import contextlib
import functools
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from itertools import islice
from typing import Protocol, TypeVar

import numpy as np

from gscan.features import FeatureParams, Features
from gscan.geometry.transforms import rotation_angle_deg, transform_points
from gscan.io.camera import Intrinsics, backproject
from gscan.registration.dense import DenseGeometry, in_source_frame, pose_information
from gscan.registration.edge import Edge
from gscan.registration.pairwise import PairResult, RegisterParams, register_features
from gscan.registration.posegraph import information_from_points
from gscan.registration.turns import edge_turn, lone_edge_turn

LOOP_DEPTH_ONLY = ("ambiguous shape: a loop closure the depth alone decides (a plain surface: the shape's own "
                   "symmetry would fit as well)")
LOOP_TURN = "ambiguous shape: a loop closure the views cannot tell from {}"  # {}: the turn, in words
SEQUENTIAL_TURN = "ambiguous shape: a sequential edge {}, which the views cannot tell from {}"  # {}: why, the turn
SEQUENTIAL_MAX_TURN_DEG = 90.0  # an edge of consecutive frames turning more may have a half turn that turns less
SKIPPED_STEP_FACTOR = 2.0  # frames that failed to register are assumed to turn at most this x the largest step
AGAINST_ODOMETRY = "contradicts the capture's odometry"  # how the reason of such an edge begins (`against_odometry`)
ICP_VOXEL_STRIDE = 2  # pixel stride of the clouds kept for ICP before voxel downsampling (a sampling internal)
COMMIT_ROWS = 64  # database writes are committed in chunks of this many edges or views (a transaction size)

T_in = TypeVar("T_in")
T_out = TypeVar("T_out")


@dataclass
class RegData:
    """What registration uses of a frame: keypoints (camera frame), ICP cloud [P x 3] (or None), depth samples."""

    feats: Features
    cloud: np.ndarray | None
    dense: DenseGeometry

    @classmethod
    def of_frame(cls, feats: Features, depth: np.ndarray, color: np.ndarray, intrinsics: Intrinsics,
                 mask: np.ndarray | None, icp_voxel: float | None) -> RegData:
        """A frame's registration data: its keypoints, and its depth [H x W] (m) and colour [H x W x 3] sampled
        inside `mask` (all of it: None), with the ICP cloud when `icp_voxel` is given."""
        cloud = None if icp_voxel is None else icp_cloud(depth, intrinsics, mask, icp_voxel)
        return cls(feats, cloud, DenseGeometry.from_depth(depth, intrinsics, mask, image=color))


class SequenceFrames(Protocol):
    """The frames of a sequence as its registration reads them (frame k: 0 <= k < len). Thread-safe."""

    @property
    def names(self) -> Sequence[str]: ...

    def __len__(self) -> int: ...

    def reg(self, k: int) -> RegData:
        """Registration data of frame k."""
        ...

    def descriptors(self, k: int) -> np.ndarray:
        """Frame k's registration descriptors [N x D]."""
        ...

    def n_keypoints(self, k: int) -> int:
        """Frame k's registration keypoints with depth."""
        ...

    def depth_m(self, k: int) -> float | None:
        """The median depth of frame k's keypoints (m), None without keypoints."""
        ...


class EdgeSink(Protocol):
    """Where edges go as they are computed (a scan's database)."""

    def add(self, edge: Edge) -> None: ...

    def commit(self) -> None:
        """Commit what was added so far (inside a batch)."""
        ...

    def batch(self) -> contextlib.AbstractContextManager[None]:
        """The adds inside are one transaction."""
        ...


def icp_cloud(depth: np.ndarray, intrinsics: Intrinsics, mask: np.ndarray | None, voxel: float) -> np.ndarray:
    """[P x 3] camera-frame points for ICP: valid depth [H x W] (inside `mask`), pixel stride, voxel grid."""
    import open3d as o3d

    s = ICP_VOXEL_STRIDE
    valid = depth > 0
    if mask is not None:
        valid &= mask
    pts = backproject(depth, intrinsics)[::s, ::s][valid[::s, ::s]]
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts.astype(np.float64)))
    if voxel > 0:
        pc = pc.voxel_down_sample(voxel)
    return np.asarray(pc.points)


def bounded_map(pool: ThreadPoolExecutor, fn: Callable[[T_in], T_out], items: Iterable[T_in],
                ahead: int) -> Iterator[T_out]:
    """pool.map(fn, items) in order, with at most `ahead` items submitted and not yet consumed: the results of
    per-frame work (images, keypoints) do not pile up when the consumer is slower than the workers."""
    it = iter(items)
    pending = deque(pool.submit(fn, x) for x in islice(it, ahead))
    try:
        while pending:
            fut = pending.popleft()
            for x in islice(it, 1):
                pending.append(pool.submit(fn, x))
            yield fut.result()
    finally:
        for fut in pending:
            fut.cancel()


@dataclass(frozen=True)
class Evidence:
    """What the pose graph uses of an accepted edge: its information matrix [6 x 6] (source frame), the median
    depth of its source points, and its RMS keypoint residual in noise sigmas."""

    info: np.ndarray
    depth: float
    rms: float


def source_depth(e: Edge, a: RegData) -> float:
    """The median depth (m) of edge e's source points (frame a's matched keypoints); nan without matches."""
    z = a.feats.points[e.matches[:, 0], 2].astype(np.float64)
    return float(np.median(z)) if len(z) else float("nan")


def edge_evidence(e: Edge, a: RegData, b: RegData, rparams: RegisterParams) -> Evidence:
    """The evidence of the accepted edge e from frame a to frame b (their registration data)."""
    assert e.T_tgt_src is not None  # an accepted edge has a pose
    ps = a.feats.points[e.matches[:, 0]].astype(np.float64)
    pt = b.feats.points[e.matches[:, 1]].astype(np.float64)
    loc = np.hypot(a.feats.location_sigma[e.matches[:, 0]], b.feats.location_sigma[e.matches[:, 1]])
    sg = rparams.noise.pair_sigma(ps[:, 2], pt[:, 2], loc)
    # the precision the edge claims, as registration solved it (keypoints, and the depth when it took part),
    # in the source frame, the frame of the pose graph's residual: an edge whose pose the depth pins must
    # agree with the others to that precision (the graph's floor keeps strong edges from dominating)
    if rparams.refines_on_depth:
        kp = slice(0, 0) if e.depth_only else slice(None)  # the depth alone posed a depth-only edge
        depth_noise = rparams.depth_noise_ray if e.depth_only else rparams.depth_noise
        info = in_source_frame(pose_information(a.dense, b.dense, ps[kp], pt[kp], e.T_tgt_src, rparams.noise,
                                                depth_noise, kp_loc=loc[kp], rims=e.depth_only), e.T_tgt_src)
    else:
        info = information_from_points(ps, sg)
    r = np.linalg.norm(transform_points(e.T_tgt_src, ps) - pt, axis=1) / sg
    return Evidence(info, source_depth(e, a), float(np.sqrt(np.mean(r * r))))


class Registrar:
    """Pairwise registration of frame pairs into edges handed to `sink`, with the evidence the pose graph weighs
    them by.

    A resumed scan reuses the edges the interrupted run stored (`stored`, kept in `done`); `restored` holds the
    edges stored with another verdict than this run's: those the interrupted run had pruned by the pose graph, put
    back for this run's pose graph to judge, and the refused edges the capture's steady motion admitted
    (`gscan.registration.sequence.admit_by_motion`); `evidence` holds the accepted edges' computed here (`optimise`
    computes that of stored ones). `ahead`: pairs submitted to the pool and not yet
    consumed. Loop closures: one the depth alone decides is refused (`LOOP_DEPTH_ONLY`); one whose frames are plain
    (fewer than `min_print_keypoints` image keypoints: the scan's `features.auto_min_keypoints`) or whose pose the
    texture did not judge is refused when the views do not refute the object's half turns (`LOOP_TURN`,
    `gscan.registration.turns`); so is a sequential edge turning more than its frames can
    (`_weighed_against_turns`, `SEQUENTIAL_TURN`). A capture of two frames has one edge and no cycle: it is weighed
    as `register_frames` weighs a lone edge (`gscan.registration.turns.lone_edge_turn`). `largest_step`: the most
    an accepted edge of consecutive frames registered so far turns (deg; None before the first)."""

    def __init__(self, frames: SequenceFrames, rparams: RegisterParams, sink: EdgeSink,
                 stored: Iterable[Edge] = (), ahead: int = 4,
                 min_print_keypoints: int = FeatureParams().auto_min_keypoints):
        self.frames, self.rparams, self.sink, self.ahead = frames, rparams, sink, ahead
        self.min_print_keypoints = min_print_keypoints  # fewer image keypoints: a plain frame (the loop turn rule)
        self.names = list(frames.names)
        self.done = {(e.src, e.tgt): e for e in stored}
        self.restored: set[tuple[str, str]] = set()
        self.by_motion: set[tuple[str, str]] = set()  # refused edges the steady motion admitted (in restored too)
        self.bridged: list[tuple[int, int]] = []  # breaks (k0, k1) the last pose graph joined by the motion's bridges
        self.evidence: dict[tuple[str, str], Evidence] = {}
        self.written = 0  # edges handed to the sink so far (committed every COMMIT_ROWS)
        self.largest_step: float | None = None

    def _pair(self, pair: tuple[int, int], loop: bool = False) -> tuple[Edge, Evidence | None] | None:
        i, j = pair
        if (self.names[i], self.names[j]) in self.done:
            return None
        a, b = self.frames.reg(i), self.frames.reg(j)
        alone = len(self.names) == 2  # a two-frame capture: its one edge alone places the second frame
        r = register_features(a.feats, b.feats, self.rparams, clouds=(a.cloud, b.cloud), dense=(a.dense, b.dense),
                              alone=alone)
        if loop and r.accepted and r.depth_only:
            # frames far apart on a plain shape: its own half turn fits the depth, the silhouette and the shading
            # as well (measured: every wrong loop closure of plain turntable boxes), and no chain of frames
            # between the two vouches for the pose; consecutive frames turn little, so theirs stay
            r.accepted, r.reason = False, LOOP_DEPTH_ONLY
        elif r.accepted and r.T_tgt_src is not None and (weighed := self._weighed_against_turns(i, j, r, loop)):
            # a plain box's half turn passes on image keypoints too (its corners match either way), and its
            # shading lines up either way (measured: the wrong loop closures of plain boxes scanned on sift had a
            # texture verdict): the views must refute each of the object's half turns, and where a frame has too
            # few image keypoints to have print, the shape alone must (its shading follows the faces' angle to
            # the camera and light, which the turn keeps: it favours the turned pose)
            # on printed frames a texture verdict is the print's, which a half turn does not keep: it decided
            turned = edge_turn(a.feats, b.feats, a.dense, b.dense, r, self.rparams, self.min_print_keypoints, 0.0,
                               unseen=loop)
            if turned is not None:
                r.accepted = False
                r.reason = LOOP_TURN.format(turned) if loop else SEQUENTIAL_TURN.format(weighed, turned)
        if alone and r.accepted:  # as in `register_frames`
            why = lone_edge_turn(a.feats, b.feats, a.dense, b.dense, r, self.rparams, self.min_print_keypoints)
            if why is not None:
                r.accepted, r.reason = False, why
        # the edge keeps the correspondences its pose was solved from (GMatch's list grown by the guided
        # refinement of gscan.registration.pairwise), which also weigh it in the pose graph
        used = r.inliers if r.inliers is not None and len(r.inliers) else r.matches
        e = Edge(self.names[i], self.names[j], r.T_tgt_src, used, r.cost, r.rmse, r.fitness, "sequential",
                 r.accepted, r.reason, r.accepted and r.depth_only)
        return e, (edge_evidence(e, a, b, self.rparams) if e.accepted and e.T_tgt_src is not None else None)

    def _weighed_against_turns(self, i: int, j: int, r: PairResult, loop: bool) -> str:
        """Why the accepted edge i -> j (pose r.T_tgt_src) must refute the object's half turns, in words; "" when
        it need not. A loop closure must. Of a pose and its half turns about the object, which the shape alone
        cannot tell apart, a sequential edge stands for its pose when the truth turns at most B < 90 deg and the
        pose does too: a half turn of a truth turning at most B turns at least 180 - B > B. Consecutive frames
        are taken to turn at most B = SEQUENTIAL_MAX_TURN_DEG. An edge over j - i frames, tried because the frames
        between failed, at most B = SKIPPED_STEP_FACTOR x (j - i) x the largest turn of the capture's accepted
        consecutive edges (`largest_step`; none yet: no bound); as that is an assumption, B must stay below 45 deg,
        which keeps a box's quarter turns apart too (90 - B > B). Measured without a bound: plain boxes' edges
        over 3 frames registered at their half turns, 158 deg for a true 30 (10 deg steps) and 45 deg for a true
        135 (45 deg steps)."""
        if loop:
            return "a loop closure"
        assert r.T_tgt_src is not None
        turn = rotation_angle_deg(r.T_tgt_src)
        if j - i == 1:
            return f"turning {turn:.0f} deg, more than consecutive frames do" if turn > SEQUENTIAL_MAX_TURN_DEG else ""
        bound = np.inf if self.largest_step is None else SKIPPED_STEP_FACTOR * (j - i) * self.largest_step
        if bound >= SEQUENTIAL_MAX_TURN_DEG / 2:
            return f"over {j - i} frames"
        return f"over {j - i} frames turning {turn:.0f} deg, more than {bound:.0f}" if turn > bound else ""

    def register(self, pairs: list[tuple[int, int]], kind: str, pool: ThreadPoolExecutor) -> list[Edge]:
        """Edges of `pairs`, computed on the pool (numba and OpenCV release the GIL) in the order of their frames
        (a frame's registration data stays in the cache for its next edges), handed to the sink in the order
        given."""
        order = sorted(range(len(pairs)), key=lambda k: pairs[k])
        work = functools.partial(self._pair, loop=kind != "sequential")
        computed = zip(order, bounded_map(pool, work, [pairs[k] for k in order], self.ahead), strict=True)
        ready: dict[int, tuple[Edge, Evidence | None] | None] = {}
        out = []
        for k, (i, j) in enumerate(pairs):
            while k not in ready:
                m, g = next(computed)
                ready[m] = g
            got = ready.pop(k)
            if got is None:  # stored by the interrupted run
                e = self.done[(self.names[i], self.names[j])]
                if e.pruned:  # restore the registration verdict
                    e.accepted, e.reason = True, None
                    self.restored.add((e.src, e.tgt))
            else:
                e, ev = got
                e.kind = kind
                if ev is not None:
                    self.evidence[(e.src, e.tgt)] = ev
                self.sink.add(e)
                self.written += 1
                if self.written % COMMIT_ROWS == 0:
                    self.sink.commit()
            if kind == "sequential" and j - i == 1 and e.accepted and e.T_tgt_src is not None:
                self.largest_step = max(self.largest_step or 0.0, rotation_angle_deg(e.T_tgt_src))
            out.append(e)
        return out
