"""Joining two captures of one object: the rigid motion from one capture's world into the other's.

Between two captures the object moved against the table (turned upside down, put elsewhere, another day), so
only the object's own points may vote: each capture offers a few registered views (`JoinView`: keypoints and
depth samples inside the object mask, camera frame, and the view's pose in its capture's world). Every pair of
views, one per capture, is registered like every edge of a sequence (GMatch, Kabsch, guided refinement, the
dense and texture checks of `gscan.registration.pairwise`), on the object alone; an accepted pair proposes a
motion T_worldA_worldB. Two proposals agree when they differ by less than `agree_sigmas` of their own predicted
uncertainty (the poses' sigmas from the keypoint noise, floored at the noise of one keypoint pair at the
views' depth). The captures are joined when the largest agreeing group holds at least `min_pairs` pairs, with
at least two views of each capture among them. The motion is the mean of the group's. Last, the object of B
turned about its principal axes (90, 180, 270 deg) must be refuted by the views' depth or texture, as an edge's pose
is, or its texture be outweighed by the motion found's: a print repeated on the top and the bottom matches at a
turned motion, which only the other sides can tell (`_turn_not_refuted`; `_Alike` compares two motions on the
surface patches both overlap). Where those patches refute the motion found in a turn's favour instead, the turn
(refined on the keypoints) is judged in its place, the motion found among the motions it must refute, and the
captures are joined at it when it stands (`Join.turned`). Depth and texture are judged over the whole overlap:
every view of B against every view of A. Where another group holds at least half as many pairs (a symmetric
object turned over may match two ways), each motion must refute the other as well as its own turns: the captures
are joined at the one that does, and not at all when both or neither do (no join is guessed).
"""
from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from gscan.features import descriptor_distances
from gscan.features.keypoints import JOINT
from gscan.geometry.icp import icp_point_to_plane
from gscan.geometry.kabsch import kabsch
from gscan.geometry.symmetry import axis_rotation
from gscan.geometry.transforms import inv_T, mean_pose, rotation_angle_deg
from gscan.matching.gmatch import default_eps_f
from gscan.registration.colour import TILE, ColourAgreement
from gscan.registration.dense import ColourTiles, DepthAgreement, colour_agreement, colour_tiles, depth_agreement
from gscan.registration.edges import RegData
from gscan.registration.noise import sign_test
from gscan.registration.pairwise import GuidedPool, PairResult, RegisterParams, consistent_pairs, register_features
from gscan.registration.params import JoinParams
from gscan.registration.turns import AXES, principal_turns, texture_refutes

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class JoinView:
    """A registered view a capture offers for joining: name, object-only registration data (camera frame), and
    T_world_cam [4 x 4] in its capture's world."""

    name: str
    reg: RegData
    T_world_cam: np.ndarray


@dataclass
class Join:
    """The outcome of joining capture B to capture A: T_a_b [4 x 4] (B's world into A's) or None with the
    reason; the view pairs tried and those that agree on the motion (names, A's first)."""

    T_a_b: np.ndarray | None
    reason: str | None
    tried: int
    accepted: int
    agreeing: list[tuple[str, str]] = field(default_factory=list)
    turned: str | None = None  # joined at a turn of the motion the view pairs agree on, in words

    def to_meta(self) -> dict:
        return {"joined": self.T_a_b is not None, "reason": self.reason, "pairs_tried": self.tried,
                "pairs_accepted": self.accepted, "pairs_agreeing": [list(p) for p in self.agreeing],
                "joined_at_turn": self.turned, "T_a_b": None if self.T_a_b is None else self.T_a_b.tolist()}


@dataclass(frozen=True)
class _Standing:
    """A motion the views do not refute beside the one judged, in words; `better` [4 x 4]: it refined on the
    keypoints where the texture both overlap refutes the one judged in its favour (the sign test the other way
    round), else None."""

    words: str
    better: np.ndarray | None


@dataclass(frozen=True)
class _Proposal:
    a: str
    b: str
    T_a_b: np.ndarray
    sigma_deg: float
    sigma_m: float
    n: int  # inliers the pair's pose rests on


def _differ(p: _Proposal, q: _Proposal, centre: np.ndarray, radius: float) -> tuple[float, float]:
    """How far two proposals differ, in their predicted sigmas: (rotation angle / its sigma, displacement of the
    object's points (within `radius` of its `centre` [3] in A's world: at most the centre's displacement +
    angle * radius) / its sigma)."""
    D = p.T_a_b @ inv_T(q.T_a_b)
    ang = rotation_angle_deg(D[:3, :3])
    disp = float(np.linalg.norm(D[:3, :3] @ centre + D[:3, 3] - centre)) + np.radians(ang) * radius
    s_deg = np.hypot(p.sigma_deg, q.sigma_deg)
    s_m = np.hypot(p.sigma_m, q.sigma_m)
    return ang / s_deg, disp / s_m


def join_captures(a: Sequence[JoinView], b: Sequence[JoinView], rparams: RegisterParams, params: JoinParams,
                  pool: ThreadPoolExecutor) -> Join:
    """Join capture B's world to capture A's (module docstring) from their offered views."""
    pairs = [(va, vb) for va in a for vb in b]
    if not pairs:
        return Join(None, "no registered view with the object in view to join by", 0, 0)

    def register(pair: tuple[JoinView, JoinView]) -> PairResult:
        va, vb = pair
        return register_features(vb.reg.feats, va.reg.feats, rparams, clouds=(vb.reg.cloud, va.reg.cloud),
                                 dense=(vb.reg.dense, va.reg.dense))

    results = list(pool.map(register, pairs))
    proposals: list[_Proposal] = []
    reasons: Counter[str] = Counter()
    for (va, vb), r in zip(pairs, results, strict=True):
        if not r.accepted or r.T_tgt_src is None:
            reasons[(r.reason or "not accepted").split(":")[0]] += 1
            continue
        # r maps B's camera into A's: world A <- cam A <- cam B <- world B
        T = va.T_world_cam @ r.T_tgt_src @ inv_T(vb.T_world_cam)
        z = float(np.median(va.reg.feats.points[:, 2])) if len(va.reg.feats) else 1.0
        floor = float(rparams.noise.pair_sigma(z, z))
        n = len(r.inliers) if r.inliers is not None else r.n_matches
        proposals.append(_Proposal(va.name, vb.name, T, max(r.sigma_deg or 0.0, 0.0), max(r.sigma_m or 0.0, floor),
                                   n))
    tried = len(pairs)
    if not proposals:
        common = ", ".join(f"{why} ({k})" for why, k in reasons.most_common(2))
        return Join(None, f"none of {tried} view pairs matched the object of the other capture: {common}", tried, 0)

    centre, radius = _object_extent(a)
    floor_deg = np.degrees(max(p.sigma_m for p in proposals) / max(radius, 1e-3))

    def agree(p: _Proposal, q: _Proposal) -> bool:
        pd = _Proposal(p.a, p.b, p.T_a_b, max(p.sigma_deg, floor_deg), p.sigma_m, p.n)
        qd = _Proposal(q.a, q.b, q.T_a_b, max(q.sigma_deg, floor_deg), q.sigma_m, q.n)
        d_rot, d_pos = _differ(pd, qd, centre, radius)
        return d_rot <= params.agree_sigmas and d_pos <= params.agree_sigmas

    groups = [[q for q in proposals if agree(p, q)] for p in proposals]
    order = sorted(range(len(groups)), key=lambda i: (-len(groups[i]), -sum(q.n for q in groups[i]), i))
    best = groups[order[0]]
    rival = next((groups[i] for i in order[1:] if not any(agree(p, q) for p in best for q in groups[i])), [])
    accepted = len(proposals)
    names_a, names_b = {p.a for p in best}, {p.b for p in best}
    if len(best) < params.min_pairs or len(names_a) < 2 or len(names_b) < 2:
        return Join(None, f"too little agreement: {len(best)} of {accepted} accepted view pairs ({tried} tried) "
                    f"agree on one motion ({len(names_a)} and {len(names_b)} views of the two captures), "
                    f"{params.min_pairs} needed", tried, accepted, [(p.a, p.b) for p in best])
    T = mean_pose([p.T_a_b for p in best])
    if len(rival) >= max(params.min_pairs, len(best) / 2):
        # two motions: each must refute the other (and its own turns) on the evidence both share
        T_rival = mean_pose([p.T_a_b for p in rival])
        standing = [(g, M) for g, M, other in ((best, T, T_rival), (rival, T_rival, T))
                    if len({p.a for p in g}) >= 2 and len({p.b for p in g}) >= 2
                    and _turn_not_refuted(M, a, b, rparams, params, pool, others=(other,)) is None]
        if len(standing) != 1:
            return Join(None, f"ambiguous: two motions join the captures ({len(best)} and {len(rival)} view pairs "
                        "agree on each; a symmetric object?)", tried, accepted, [(p.a, p.b) for p in best])
        log.info("join: of two motions (%d and %d view pairs), the texture refutes one", len(best), len(rival))
        best, T = standing[0]
    else:
        turned = _turn_not_refuted(T, a, b, rparams, params, pool)
        # the texture both overlap may refute the motion found in favour of its turn (a print repeated on two
        # sides matched the view pairs to the turned object): the turn is judged as the motion found is, the motion
        # found among those it must refute, and the captures are joined at it when it stands
        if turned is not None and turned.better is not None and \
                _turn_not_refuted(turned.better, a, b, rparams, params, pool, others=(T,)) is None:
            log.info("join: the texture refutes the motion %d view pairs agree on in favour of %s", len(best),
                     turned.words)
            return Join(turned.better, None, tried, accepted, [(p.a, p.b) for p in best], turned.words)
        if turned is not None:
            return Join(None, f"ambiguous: {turned.words} joins the captures as well ({len(best)} view pairs agree "
                        "on the motion found; a side seen alike in both?)", tried, accepted,
                        [(p.a, p.b) for p in best])
    log.info("joined: %d of %d accepted view pairs (%d tried) agree", len(best), accepted, tried)
    return Join(T, None, tried, accepted, [(p.a, p.b) for p in best])


def _turn_not_refuted(T_a_b: np.ndarray, a: Sequence[JoinView], b: Sequence[JoinView], rparams: RegisterParams,
                      params: JoinParams, pool: ThreadPoolExecutor, others: Sequence[np.ndarray] = ()
                      ) -> _Standing | None:
    """The first turn of capture B's object about one of its principal axes (90, 180, 270 deg, through its centre),
    or of the `others` motions [4 x 4] (a second group of view pairs'), that the views do not refute when it is
    joined so (`_Standing`: with it refined on the keypoints where the texture both overlap refutes T_a_b in its
    favour); None when every one is refuted. A view pair may match a side the object shows alike both
    ways up (a print repeated on its top and bottom): the motion found then turns the object, and only the views of
    its other sides can tell. A turn is refuted as an edge's pose is (`gscan.registration.pairwise`, rule 3): by
    the depth (more than `max_see_through` of the overlap seen through) or by the texture (fewer than
    `min_colour_agreement` of the overlap's textured tiles line up); or its texture is outweighed by the motion
    found's: it lines up in less than `params.turn_texture_ratio` of the share of tiles the motion found lines up
    in, each over `min_colour_tiles` or more (two motions overlap different sides, so the shares are compared with
    a wide margin); or, both refined alike on the keypoints and compared on the surface patches both overlap, the
    texture favours the motion found (`_Alike`). A turned motion is judged by the first three rules refined on the
    object's depth; an `others` motion, as its view pairs solved it, by the depth and by `_Alike` only (the shares
    of tiles measure different sides); the amount of depth two motions explain is not compared: a print repeated on
    the top and bottom, seen squarely by both captures, lines up better and explains more depth under the wrong
    motion than the sides, seen obliquely, under the right one (docs/method.md, the join)."""
    pts = _in_world(b, lambda v: v.reg.dense.points)
    if len(pts) < 3:
        return None
    axes, c, reach = principal_turns(pts)
    # a turned motion is first refined on the object's depth (point to plane, A's surface onto B's), so that a turn
    # about an approximate axis is judged at its best (the motion found is judged as the view pairs solved it)
    src = _in_world(a, lambda v: v.reg.dense.points)
    normals = _in_world(a, lambda v: v.reg.dense.point_normals, directions=True)

    def refined(T: np.ndarray) -> np.ndarray:
        if len(src) < 10:
            return T
        T_b_a, _ = icp_point_to_plane(src[::4], normals[::4], pts[::4], inv_T(T), reach)
        return inv_T(T_b_a)

    found = _agreement(T_a_b, a, b, rparams, pool)
    log.debug("join: the motion found: depth %s, texture %s", found[0], found[1])
    if texture_refutes(found[1], rparams):
        return _Standing("the views' texture disagrees under the motion found; any motion", None)
    # (words, the motion, whether it is a turn: judged refined on the depth, and refuted by any rule; another
    # group's motion is judged as its view pairs solved it, like the motion found, and refuted by the depth or by
    # the texture both overlap only: the shares of tiles two motions line up in are measured on different sides,
    # and a second group of view pairs was refused outright before the two could be compared on the same evidence)
    rivals = [(f"the object turned {deg} deg about its {AXES[k]} principal axis",
               T_a_b @ axis_rotation(axis, c, np.radians(deg)), True) for k, axis in enumerate(axes)
              for deg in (180, 90, 270)]
    rivals += [("another group of view pairs' motion", T, False) for T in others]
    alike: _Alike | None = None
    for words, T, turn in rivals:
        T_depth = refined(T)
        depth, colour = _agreement(T_depth if turn else T, a, b, rparams, pool)
        if turn and depth.consistent == 0:  # the refinement slid the object off the views: judge the turn as given
            depth, colour = _agreement(T, a, b, rparams, pool)
        log.debug("join: %s: depth %s, texture %s", words, depth, colour)
        if depth.see_through_fraction > rparams.max_see_through:
            continue  # the shape refutes it
        if turn and (texture_refutes(colour, rparams)
                     or _texture_outweighs(found[1], colour, params.turn_texture_ratio, rparams)):
            continue
        if alike is None:
            alike = _Alike(T_a_b, refined(T_a_b), a, b, rparams, pool)
        mine, theirs, M = alike.compare(T, T_depth, words)
        if sign_test(mine, theirs) <= params.turn_sign_alpha:
            continue
        return _Standing(words, M if sign_test(theirs, mine) <= params.turn_sign_alpha else None)
    return None


KP_GATES = (16.0, 8.0, 5.0, 3.0, 3.0)  # noise sigmas: a joint keypoint refinement's gates (`_Alike.refined`)


class _Alike:
    """Two motions joining captures A and B, refined alike and compared on the same evidence.

    Each motion is refined on the keypoint pairs of every view pair that agree with it (guided, as an edge's pose
    is: descriptor distance below GMatch's eps_f, one-to-one, within the gate's sigmas of the keypoint noise; one
    rigid motion over all view pairs, the gates shrinking from `KP_GATES[0]`, wide enough to draw in a turn about an
    approximate axis), from the motion as given and from it refined on the depth, whichever start keeps more pairs:
    each is judged at its best supported pose, neither favoured by how it was found. The texture then compares them
    on the tiles informative under both (the same patches of the same images, `colour_tiles`, each landing where
    its motion puts it), grouped into surface patches of one tile's footprint (`TILE` px at the views' median
    depth: the views see one patch many times, and its texture is one piece of evidence). A patch favours the motion
    under which more of its tiles line up. The other motion is refuted when a sign test rejects that the patches
    favour either motion alike: at most `turn_sign_alpha` chance that a fair coin gives the other motion as few
    patches. A print repeated under the turn lines up alike under both (no patch favours either); a wrong motion
    loses where the print differs."""

    def __init__(self, T_a_b: np.ndarray, T_depth: np.ndarray, a: Sequence[JoinView], b: Sequence[JoinView],
                 rparams: RegisterParams, pool: ThreadPoolExecutor):
        self.a, self.b, self.rparams, self.pool = a, b, rparams, pool
        kind = a[0].reg.feats.kind if a else "sift"
        eps = rparams.gmatch.eps_f if rparams.gmatch.eps_f is not None else default_eps_f(kind)
        self.pools = {(i, j): GuidedPool(va.reg.feats.points, descriptor_distances(
            vb.reg.feats.descriptors, va.reg.feats.descriptors, kind), eps)
            for i, va in enumerate(a) for j, vb in enumerate(b) if len(va.reg.feats) and len(vb.reg.feats)}
        self.T_a_b, self.pairs = self.refined(T_a_b, T_depth)
        z = np.concatenate([v.reg.dense.points[:, 2] for v in a]) if a else np.ones(1)
        fx = max(a[0].reg.dense.full_intrinsics[0], 1.0) if a else 1.0
        self.patch = TILE * float(np.median(z)) / fx
        self.patches = self._patches(_tiles(self.T_a_b, a, b, rparams, pool))

    def refined(self, T: np.ndarray, T_depth: np.ndarray) -> tuple[np.ndarray, int]:
        """(T_a_b [4 x 4], keypoint pairs it rests on): the better supported of the keypoint refinements from T
        and from T_depth (the former on a tie)."""
        one, two = self._on_keypoints(T), self._on_keypoints(T_depth)
        return one if one[1] >= two[1] else two

    def _on_keypoints(self, T: np.ndarray) -> tuple[np.ndarray, int]:
        noise, n = self.rparams.noise, 0
        for gate in KP_GATES:
            src, dst, w = [], [], []
            for (i, j), gp in self.pools.items():
                va, vb = self.a[i], self.b[j]
                fa, fb = va.reg.feats, vb.reg.feats
                loc_b, loc_a = (fb.location_sigma, fa.location_sigma) if fb.kind == JOINT else (None, None)
                pr = consistent_pairs(fb.points, fa.points, gp, inv_T(va.T_world_cam) @ T @ vb.T_world_cam, gate,
                                      noise, loc_b, loc_a)
                ps, pt = fb.points[pr[:, 0]].astype(np.float64), fa.points[pr[:, 1]].astype(np.float64)
                loc = 0.0 if loc_b is None or loc_a is None else np.hypot(loc_b[pr[:, 0]], loc_a[pr[:, 1]])
                src.append(ps @ vb.T_world_cam[:3, :3].T + vb.T_world_cam[:3, 3])
                dst.append(pt @ va.T_world_cam[:3, :3].T + va.T_world_cam[:3, 3])
                w.append(1.0 / np.square(noise.pair_sigma(ps[:, 2], pt[:, 2], loc)))
            k = sum(len(x) for x in src)
            if k < self.rparams.min_matches:
                break
            T, n = kabsch(np.concatenate(src), np.concatenate(dst), np.concatenate(w)), k
        return T, n

    def compare(self, T: np.ndarray, T_depth: np.ndarray, words: str) -> tuple[int, int, np.ndarray]:
        """(surface patches that favour this motion, those that favour the other, the other refined on the
        keypoints [4 x 4]) for the other motion T_a_b [4 x 4] (T_depth: it refined on the depth; class
        docstring)."""
        M, n = self.refined(T, T_depth)
        other = self._patches(_tiles(M, self.a, self.b, self.rparams, self.pool))
        mine = theirs = both = 0
        for patch in self.patches.keys() & other.keys():
            (n1, k1), (n2, k2) = self.patches[patch], other[patch]
            both += 1
            mine += k1 * n2 > k2 * n1
            theirs += k2 * n1 > k1 * n2
        log.debug("join: %s, refined on %d keypoint pairs (the motion found: %d): %d surface patches favour the "
                  "motion found, %d it (of %d both overlap), p = %.2g", words, n, self.pairs, mine, theirs, both,
                  sign_test(mine, theirs))
        return mine, theirs, M

    def _patches(self, tiles: dict[_TileKey, tuple[bool, np.ndarray]]) -> dict[tuple[int, ...], tuple[int, int]]:
        """(informative tiles, tiles that line up) of each surface patch: a tile's direction (whose view, so whose
        capture world) and the cube of side `self.patch` its centre lies in."""
        out: dict[tuple[int, ...], tuple[int, int]] = {}
        for key, (g, centre) in tiles.items():
            patch = (key[2], *(int(x) for x in np.floor(centre / self.patch)))
            n, k = out.get(patch, (0, 0))
            out[patch] = (n + 1, k + int(g))
        return out


_TileKey = tuple[int, int, int, int]  # (view of A, view of B, direction (0: B's tiles), tile id)


def _tiles(T_a_b: np.ndarray, a: Sequence[JoinView], b: Sequence[JoinView], rparams: RegisterParams,
           pool: ThreadPoolExecutor) -> dict[_TileKey, tuple[bool, np.ndarray]]:
    """The informative tiles of every view pair of A and B joined by T_a_b: key -> (whether it lines up, its centre
    [3] in its own view's capture world), on the views sampled every 2 px (`DenseGeometry.fine`: on the default
    samples a tile along an outline holds too few to be judged, and the Tena pads' half turn was left standing on
    the 14 patches both motions overlapped)."""
    def check(pair: tuple[int, int]) -> dict[_TileKey, tuple[bool, np.ndarray]]:
        va, vb = a[pair[0]], b[pair[1]]
        T_va_vb = inv_T(va.T_world_cam) @ T_a_b @ vb.T_world_cam
        t: ColourTiles = colour_tiles(vb.reg.dense.fine, va.reg.dense.fine, T_va_vb, rparams.depth_noise)
        out = {}
        for d, tile, g, centre in zip(t.direction, t.tile, t.agrees, t.centre, strict=True):
            T = vb.T_world_cam if d == 0 else va.T_world_cam
            out[(pair[0], pair[1], int(d), int(tile))] = (bool(g), T[:3, :3] @ centre + T[:3, 3])
        return out

    tiles: dict[_TileKey, tuple[bool, np.ndarray]] = {}
    for got in pool.map(check, [(i, j) for i in range(len(a)) for j in range(len(b))]):
        tiles |= got
    return tiles


def _texture_outweighs(found: ColourAgreement, other: ColourAgreement, ratio: float, rparams: RegisterParams
                       ) -> bool:
    """Whether the texture under the motion found outweighs another motion's: both with enough textured tiles to
    judge by, the other's share of tiles that line up below `ratio` of the found one's."""
    return (min(found.informative, other.informative) >= rparams.min_colour_tiles
            and other.agreeing_fraction < ratio * found.agreeing_fraction)


def _agreement(T_a_b: np.ndarray, a: Sequence[JoinView], b: Sequence[JoinView], rparams: RegisterParams,
               pool: ThreadPoolExecutor) -> tuple[DepthAgreement, ColourAgreement]:
    """Depth and texture agreement of the views of B (joined by T_a_b) with the views of A, summed over every pair:
    the whole surface the two captures share under the motion (a pair that does not overlap adds nothing), so that
    a motion's share of textured tiles that line up is measured on all of it, not on the few views nearest each."""
    def check(pair: tuple[JoinView, JoinView]) -> tuple[DepthAgreement, ColourAgreement]:
        va, vb = pair
        T = inv_T(va.T_world_cam) @ T_a_b @ vb.T_world_cam  # B's camera into A's
        return (depth_agreement(vb.reg.dense, va.reg.dense, T, rparams.depth_noise),
                colour_agreement(vb.reg.dense, va.reg.dense, T, rparams.depth_noise))

    d, col = DepthAgreement(0, 0, 0, 0, 0), ColourAgreement(0, 0)
    for dd, cc in pool.map(check, [(va, vb) for vb in b for va in a]):
        d, col = d + dd, col + cc
    return d, col


def _in_world(views: Sequence[JoinView], of: Callable[[JoinView], np.ndarray], directions: bool = False
              ) -> np.ndarray:
    """[N x 3] the views' points (or, `directions`, unit vectors) `of(view)` [n x 3] (camera frame), in their
    capture's world, stacked."""
    out = [of(v).astype(np.float64) @ v.T_world_cam[:3, :3].T + (0.0 if directions else v.T_world_cam[:3, 3])
           for v in views]
    return np.concatenate(out) if out else np.zeros((0, 3))


def _object_extent(views: Sequence[JoinView]) -> tuple[np.ndarray, float]:
    """(centroid [3], RMS distance (m) from it) of the views' object keypoints in their capture's world."""
    p = _in_world(views, lambda v: v.reg.feats.points)
    if not len(p):
        return np.zeros(3), 0.0
    c = p.mean(0)
    return c, float(np.sqrt(np.mean(np.sum((p - c) ** 2, axis=1))))
