"""Loop-closure candidate selection for the pose graph (re-exported by `gscan.registration.posegraph`).

Pairs of frames are proposed from view overlap under the current pose estimates (viewing
directions, and camera centres apart by less than the depth the views look at) and from appearance
(tf-idf bag-of-visual-words built by a seeded k-means over the sequence's own descriptors), at most a
few per frame, deterministically.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from gscan.registration.params import LoopParams

DEFAULT_DEPTH_M = 0.5  # the depth a node looks at when it is not given (an object on a table at arm's length)


@dataclass
class LoopCandidate:
    """A pair of nodes worth registering: i < j."""

    i: int
    j: int
    score: float          # higher = more promising (overlap score + appearance similarity)
    angle_deg: float      # angle between the two viewing directions (current pose estimates)
    distance_m: float     # distance between the camera centres
    similarity: float     # appearance similarity (cosine of tf-idf bag-of-words vectors), 0 if unused
    reason: str           # "overlap" | "appearance" | "overlap+appearance"


def bow_vectors(descriptors: Sequence[np.ndarray], vocabulary_size: int = 64, seed: int = 0,
                max_train: int = 20000, iterations: int = 10) -> np.ndarray:
    """[N x K] L2-normalised tf-idf bag-of-visual-words vectors, one per frame.

    descriptors: per frame [n_i x D] float (SIFT/RootSIFT) or uint8 [n_i x 32] binary (ORB,
    unpacked to bits so that squared L2 equals Hamming distance); any sequence, read frame by frame (a lazy
    one holds one frame's descriptors at a time). The vocabulary is a k-means (seeded k-means++ init,
    `iterations` Lloyd steps) on at most `max_train` descriptors drawn from all frames.
    """
    def as_float(d: np.ndarray) -> np.ndarray:
        d = np.asarray(d)
        if d.dtype == np.uint8:
            return np.unpackbits(d, axis=1).astype(np.float32)
        return d.astype(np.float32)

    n = len(descriptors)
    sizes, dim = [], 0
    for i in range(n):
        f = as_float(descriptors[i]).reshape(len(descriptors[i]), -1)
        sizes.append(len(f))
        dim = dim or (f.shape[1] if len(f) else 0)
    if dim == 0:
        return np.zeros((n, vocabulary_size), dtype=np.float32)
    starts = np.concatenate([[0], np.cumsum(sizes)])
    total = int(starts[-1])
    rng = np.random.default_rng(seed)
    # the training rows: the same draw over all frames' descriptors stacked in order, gathered frame by frame
    pick = np.sort(rng.choice(total, min(max_train, total), replace=False))
    rows = []
    for i in range(n):
        lo, hi = np.searchsorted(pick, [starts[i], starts[i + 1]])
        if hi > lo:
            rows.append(as_float(descriptors[i]).reshape(sizes[i], -1)[pick[lo:hi] - starts[i]])
    train = np.concatenate(rows)
    k = min(vocabulary_size, len(train))
    centres = [train[rng.integers(len(train))]]
    d2 = ((train - centres[0]) ** 2).sum(1)
    for _ in range(1, k):  # k-means++
        p = d2 / d2.sum() if d2.sum() > 0 else np.full(len(train), 1.0 / len(train))
        centres.append(train[rng.choice(len(train), p=p)])
        d2 = np.minimum(d2, ((train - centres[-1]) ** 2).sum(1))
    C = np.stack(centres)

    def assign(X: np.ndarray) -> np.ndarray:
        return np.argmin((C ** 2).sum(1)[None] - 2.0 * X @ C.T, axis=1)

    for _ in range(iterations):
        a = assign(train)
        for c in range(k):
            if np.any(a == c):
                C[c] = train[a == c].mean(0)
    H = np.zeros((n, vocabulary_size), dtype=np.float64)
    for i in range(n):
        if sizes[i]:
            H[i, :k] = np.bincount(assign(as_float(descriptors[i]).reshape(sizes[i], -1)), minlength=k)
    df = (H > 0).sum(0)
    idf = np.log((n + 1.0) / (df + 1.0)) + 1.0
    H = H / np.maximum(H.sum(1, keepdims=True), 1.0) * idf
    H /= np.maximum(np.linalg.norm(H, axis=1, keepdims=True), 1e-12)
    return H.astype(np.float32)


def select_loop_candidates(T_world_node: list[np.ndarray | None], descriptors: Sequence[np.ndarray] | None = None,
                           existing: list[tuple[int, int]] | None = None,
                           params: LoopParams = LoopParams(),
                           depths: Sequence[float | None] | None = None) -> list[LoopCandidate]:
    """Pairs of nodes to try as loop closures, best first, at most `max_per_node` per node.

    A pair qualifies by view overlap (current pose estimates: viewing directions within
    `max_angle_deg` and camera centres within `max_baseline` times the mean depth of the two views: two views
    of a scene at depth d overlap while their centres are less than about d apart, so a ring of views around an
    object 1.5 m away overlaps as one 0.5 m away does) or by appearance (one is among
    the other's `appearance_top_k` most similar frames by bag-of-words, similarity >=
    `min_similarity`). Pairs closer than `min_index_gap` in index and pairs in `existing`
    (either order) are skipped. Score = overlap (1 - angle/max_angle)(1 - dist/max_dist) when
    overlapping, plus the similarity. Greedy by score (ties by (i, j)): deterministic.

    T_world_node: per node [4 x 4] camera pose (OpenCV camera, z = viewing direction) or None.
    descriptors: per node [n_i x D] descriptors (any sequence: read node by node), or None for geometry only.
    depths: per node the depth (m) it looks at (its keypoints' median, say), or None (`DEFAULT_DEPTH_M`).
    """
    n = len(T_world_node)
    have = np.array([T is not None for T in T_world_node])
    C = np.array([T[:3, 3] if T is not None else np.zeros(3) for T in T_world_node]).reshape(n, 3)
    Z = np.array([T[:3, 2] if T is not None else np.zeros(3) for T in T_world_node]).reshape(n, 3)
    ang = np.degrees(np.arccos(np.clip(Z @ Z.T, -1.0, 1.0)))
    dist = np.linalg.norm(C[:, None] - C[None], axis=2)
    z = np.array([DEFAULT_DEPTH_M if d is None else float(d) for d in (depths or [None] * n)])
    if len(z) != n:
        raise ValueError(f"{len(z)} depths for {n} nodes")
    max_dist = params.max_baseline * 0.5 * (z[:, None] + z[None])
    overlap = have[:, None] & have[None] & (ang <= params.max_angle_deg) & (dist <= max_dist)
    ov_score = np.where(overlap, (1 - ang / params.max_angle_deg) * (1 - dist / max_dist), 0.0)
    sim = np.zeros((n, n))
    appear = np.zeros((n, n), dtype=bool)
    if descriptors is not None:
        if len(descriptors) != n:
            raise ValueError(f"{len(descriptors)} descriptor sets for {n} nodes")
        H = bow_vectors(descriptors, params.vocabulary_size, params.seed)
        sim = (H @ H.T).astype(np.float64)
        idx = np.arange(n)
        for i in range(n):
            s = np.where(np.abs(idx - i) >= params.min_index_gap, sim[i], -np.inf)
            order = np.lexsort((idx, -s))[: params.appearance_top_k]
            for j in order:
                if s[j] >= params.min_similarity:
                    appear[i, j] = appear[j, i] = True
    skip = {(min(a, b), max(a, b)) for a, b in (existing or [])}
    cands = []
    for i in range(n):
        for j in range(i + params.min_index_gap, n):
            if (i, j) in skip or not (overlap[i, j] or appear[i, j]):
                continue
            reason = "overlap+appearance" if overlap[i, j] and appear[i, j] else \
                "overlap" if overlap[i, j] else "appearance"
            cands.append(LoopCandidate(i, j, float(ov_score[i, j] + sim[i, j]), float(ang[i, j]) if have[i] and
                                       have[j] else float("nan"), float(dist[i, j]) if have[i] and have[j]
                                       else float("nan"), float(sim[i, j]), reason))
    cands.sort(key=lambda c: (-c.score, c.i, c.j))
    count = np.zeros(n, dtype=int)
    out = []
    for c in cands:
        if count[c.i] < params.max_per_node and count[c.j] < params.max_per_node:
            out.append(c)
            count[c.i] += 1
            count[c.j] += 1
    return out
