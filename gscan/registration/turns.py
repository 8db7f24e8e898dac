"""Turns of an object about its principal axes, and whether two views' depth and texture refute them.

A pose between two views of an object is told from the object's own turns (the same views with the object turned
about a principal axis) only by what the turn changes: the shape where it is not symmetric, the print where there
is some. On a plain box the half turn about any of its axes leaves the shape, the silhouette and the shading alike,
and keypoints found on its corners and edges match either way: an edge posed at the half turn passes every check
of `gscan.registration.pairwise`. `turn_not_refuted` asks the checks about the edge's turned poses: where one of
them passes as well, the views cannot tell the pose from it. Capture joins (`gscan.registration.join`) ask the
same of their motion.

- `principal_turns(points)`: the principal axes of an object's points and the centre they are turned about
- `texture_refutes(colour, params)`: whether texture refutes a pose as it does an edge's
- `turn_not_refuted(src, tgt, T_tgt_src, params, texture, unseen, fine)`: the first turn of an edge (half; with
  `fine`, quarter too) two views cannot refute
- `support_plane(src, tgt, T_tgt_src, params)`: the printed table two whole views see from one side, under which no
  turn may put a camera
- `has_print(fs, ft, min_keypoints)`: whether both frames have print (enough keypoints the image found)
- `edge_turn(fs, ft, src, tgt, r, params, min_print_keypoints, min_agreement, unseen)`: the first half turn an accepted
  edge's views do not refute, unless its print settles the pose (loop closures: any texture verdict)
- `lone_edge_turn(fs, ft, src, tgt, r, params, min_print_keypoints)`: the rule for an edge that alone places a
  frame (a two-frame capture): refused (`LONE_TURN`) when one of its turns survives the depth and the texture (the
  object's pixels judged finely)
"""
from __future__ import annotations

import logging

import numpy as np

from gscan.features import Features
from gscan.geometry.plane import Plane, dominant_plane
from gscan.geometry.symmetry import axis_rotation
from gscan.geometry.transforms import inv_T, transform_points
from gscan.registration.colour import PRINT_REACH_PX, ColourAgreement
from gscan.registration.dense import (
    DenseGeometry,
    colour_agreement,
    depth_agreement,
    interior_pixels,
    outside_silhouette,
    refine_pose,
)
from gscan.registration.pairwise import PairResult, RegisterParams

log = logging.getLogger(__name__)

AXES = ("first", "second", "third")  # principal axes, by decreasing spread
REACH = 0.1  # ICP pairing distance of a turned pose, as a share of the points' RMS radius (a turn's axis error)
CENTRE_STEPS = 7  # centres tried across a turn's axis, a side (`_best_centre`)
PLANE_ITERATIONS = 64  # RANSAC hypotheses of a view's dominant plane (`support_plane`; seeded)
SAME_PLANE_DEG = 10.0  # two views' dominant planes are one under a pose only with normals this near (`support_plane`)
TURNS = ((np.pi, "half"), (0.5 * np.pi, "a quarter"), (1.5 * np.pi, "three quarters"))  # (rad, in words)
LONE_TURN = "ambiguous shape: the only edge placing its frame, which the views cannot tell from {}"  # {}: the turn


def principal_turns(points: np.ndarray, axes: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, float]:
    """(axes [3 x 3] (rows, unit, by decreasing spread), centre [3], reach (m)) of an object's points [N x 3], N >= 3.

    axes: the points' principal axes unless given (rows, orthonormal). The centre is that of the points' box in the
    axes, not their mean: the points seen from one side miss the faces turned away (and the one the object stands
    on), so their mean is off the centre a symmetric shape turns about. reach: how far a turned pose is let slide
    when it is refined (`REACH` of the RMS radius)."""
    m = points.mean(0)
    if axes is None:
        axes = np.linalg.svd(points - m, full_matrices=False)[2]
    q = (points - m) @ axes.T
    centre = m + (0.5 * (q.min(0) + q.max(0))) @ axes
    return axes, centre, REACH * float(np.sqrt(np.mean(np.sum((points - m) ** 2, axis=1))))


def texture_refutes(colour: ColourAgreement, params: RegisterParams) -> bool:
    """Whether texture refutes a pose as it does an edge's (rule 3: enough textured tiles in the overlap, too few of
    them lining up)."""
    return colour.refutes(params.min_colour_tiles, params.min_colour_agreement)


def has_print(fs: Features, ft: Features, min_keypoints: int) -> bool:
    """Whether both frames have print: at least `min_keypoints` keypoints the image found (not the depth) in each;
    a plain frame's are its corners and rims, a few dozen."""
    return min(len(f) - int(f.from_depth.sum()) for f in (fs, ft)) >= min_keypoints


def edge_turn(fs: Features, ft: Features, src: DenseGeometry, tgt: DenseGeometry, r: PairResult,
              params: RegisterParams, min_print_keypoints: int, min_agreement: float, unseen: bool = False
              ) -> str | None:
    """The first of the object's half turns, in words, that the views do not refute for the accepted edge r (fs ->
    ft keypoints, src -> tgt depth samples); None when the print settles its pose (both frames have print,
    `has_print`, and at least `min_agreement` of the overlap's textured tiles line up: 0 for any texture verdict)
    or each turn is refuted (`turn_not_refuted`, by the texture too where both frames have print; unseen: as
    there)."""
    if not r.accepted or r.T_tgt_src is None:
        return None
    printed = has_print(fs, ft, min_print_keypoints)
    c = r.colour
    if printed and c is not None and c.settles(params.min_colour_tiles, min_agreement):
        return None
    return turn_not_refuted(src, tgt, r.T_tgt_src, params, texture=printed, unseen=unseen)


def lone_edge_turn(fs: Features, ft: Features, src: DenseGeometry, tgt: DenseGeometry, r: PairResult,
                   params: RegisterParams, min_print_keypoints: int) -> str | None:
    """Why the accepted edge r cannot place a frame alone, in words; None when nothing the views show rivals it.

    An edge that is the only evidence placing a frame has no cycle to catch a pose turned about the object: two
    views of a box whose sides look alike match strongly at a turn of it (measured: two-frame captures 120 deg
    apart registered 90 or 180 deg off with a rotation sigma of 0.2-0.3 deg, the texture lining up in 41-78 % of
    the overlap's tiles; right poses in 50-100 %). The edge is refused (`LONE_TURN`) when one of the object's turns
    survives the depth and the texture (`turn_not_refuted`), unless its print settles the pose: both frames have
    print and at least `params.alone_colour_agreement` of the overlap's textured tiles line up. A turn that lays the
    views' faces onto each other's hidden side leaves little overlap and no texture verdict: it is not refuted, and
    the edge is refused.

    Object pixels (both frames masked) are judged finely (`turn_not_refuted`'s `fine`): the texture on samples every
    `FINE_STRIDE` px (a small object's overlap holds few tiles of the default samples), the pose refused where rule
    3 refutes it there ("colour disagrees"); print where the frames have image keypoints enough or the faces'
    interiors (`interior_pixels`, where texture is not shading) hold a verdict's tiles, the interiors' print
    refuting turns too; and the quarter turns weighed too. Frames without print whose fine texture settles the pose
    (at least `params.alone_colour_agreement` of its tiles lining up: outlines, creases and shading seen alike from
    both views) have their turns judged by that texture too, a turn under which it does not line up (rule 3) being
    refuted: a box seen nearly edge on has no print verdict (Vans from 0 and 20 deg: 50 image keypoints, its faces'
    interiors 7 tiles), while its texture lines up in 18 of 18 fine tiles under the pose and 0 of 12 under the
    half turn its shape fits. That texture refutes only a turn whose tiles disagree, never one it cannot judge. A
    plain object's fine texture does not settle its pose (plain renders of the shared meshes, 20-120 deg apart:
    at most 72 % of the tiles line up under right poses), so its turns are judged as before. Whole frames keep the
    default samples and the half turns: there a plain table's faint texture lined up finely under poses 2.4 deg /
    23 mm off (Vans from 0 and 60 deg, accepted claiming 0.14 deg)."""
    if not r.accepted or r.T_tgt_src is None:
        return None
    if src.mask is None or tgt.mask is None:
        turned = edge_turn(fs, ft, src, tgt, r, params, min_print_keypoints, params.alone_colour_agreement)
        return None if turned is None else LONE_TURN.format(turned)
    fine = (src.fine, tgt.fine)
    inner = (interior_pixels(src, params.depth_noise, PRINT_REACH_PX),
             interior_pixels(tgt, params.depth_noise, PRINT_REACH_PX))
    # the texture judges the pose before the pixels refined it (which lines their texture up by construction)
    judged = r.T_textured if r.T_textured is not None else r.T_tgt_src
    printed = has_print(fs, ft, min_print_keypoints) or colour_agreement(
        *inner, judged, params.depth_noise).informative >= params.min_colour_tiles
    c = colour_agreement(*fine, judged, params.depth_noise)
    settled = c.settles(params.min_colour_tiles, params.alone_colour_agreement)
    if printed:
        if texture_refutes(c, params):
            return (f"colour disagrees (sampled finely, the texture lines up in {c.agreeing} of {c.informative} "
                    f"tiles of the overlap under the pose)")
        if settled:
            return None
    turned = turn_not_refuted(src, tgt, r.T_tgt_src, params, texture=printed or settled, fine=fine, inner=inner)
    return None if turned is None else LONE_TURN.format(turned)


def turn_not_refuted(src: DenseGeometry, tgt: DenseGeometry, T_tgt_src: np.ndarray, params: RegisterParams,
                     texture: bool = True, unseen: bool = False,
                     fine: tuple[DenseGeometry, DenseGeometry] | None = None,
                     inner: tuple[DenseGeometry, DenseGeometry] | None = None) -> str | None:
    """The first turn of the object about one of its axes that src's and tgt's depth and texture do not refute, in
    words; None when each is refuted.

    src, tgt: the two views' depth samples (the object's: a masked scan's); T_tgt_src [4 x 4] the edge's pose. The
    axes are the principal axes of both views' points in src's camera (tgt's moved by the pose) and those of their
    normals (`_turn_axes`), through a centre where the views contradict the turned pose least (`_best_centre`);
    the turned pose is then refined on the depth (`gscan.registration.dense.refine_pose`), so that a turn about an
    approximate axis is judged at its best. It is refuted only by what contradicts it: the depth (more than
    `params.max_see_through` of the overlap seen through, the bound the pose itself passed), the silhouette (more
    than `params.max_outside_shape` of the samples off the other view's object) or, with `texture` (the views have
    print), the texture (`texture_refutes`); a turn is no rival where too little of it lands on the other view's
    depth for an edge to be verified (`params.min_overlap`, rule 3), unless `unseen`: then it stands, as nothing
    refutes it (a loop closure's: no chain of frames between vouches for the pose, and a plain package's views half
    a turn apart were registered at its half turn, the right pose's refined turn landing nothing on the other view).
    Less overlap is no evidence against a turn: a half turn of a plain box seen from opposite sides lays the faces
    each view sees onto each other, and overlaps more than the right pose, which shares the top alone.

    The turns are the half turns; with `fine` (the two views sampled finely, `DenseGeometry.fine`: the texture is
    judged on them) the quarter turns too (a box with two sides alike fits its quarter turn: Whey from 270 and 30
    deg was registered 90 deg off, its half turns refuted), each also as centred before the depth's refinement,
    where most of its print lines up: the refinement slides a box's faces along each other, and the right turn
    (0.7 deg off as centred, 16 of 23 tiles lining up) ended 2.7 deg off with 3 of 26. `inner`: the two views'
    samples on their faces' interiors (`interior_pixels`), whose texture is print: a turn is refuted by it too, where
    the fine tiles' share is lifted by outlines and creases that line up under a turn of a box as under its pose."""
    pts = np.concatenate([src.points, transform_points(inv_T(T_tgt_src), tgt.points)])
    if len(pts) < 10 or len(tgt) < 10:
        return None
    normals = np.concatenate([src.point_normals, tgt.point_normals @ T_tgt_src[:3, :3]])
    plane = support_plane(src, tgt, T_tgt_src, params)
    turns = TURNS if fine is not None else TURNS[:1]
    none = np.zeros((0, 3))
    for name, axis, centre in _turn_axes(pts, normals):
        for angle, turn in turns:
            centred = _best_centre(src, tgt, T_tgt_src, pts, axis, centre, params, angle)
            refined = refine_pose(src, tgt, none, none, centred, params.noise, params.depth_noise)[0]
            verdict = _turn_verdict(src, tgt, refined, params, plane, texture, fine, inner)
            log.debug("%s turn about the %s axis: %s", turn, name, verdict)
            if verdict == "unseen" and unseen:
                return f"the object turned {turn} about its {name} axis, out of the other view's sight"
            if verdict == "stands" or (fine is not None and texture and _turn_verdict(
                    src, tgt, centred, params, plane, texture, fine, inner, lined_up=True) == "stands"):
                return f"the object turned {turn} about its {name} axis"
    return None


def _turn_verdict(src: DenseGeometry, tgt: DenseGeometry, T: np.ndarray, params: RegisterParams,
                  plane: Plane | None, texture: bool, fine: tuple[DenseGeometry, DenseGeometry] | None,
                  inner: tuple[DenseGeometry, DenseGeometry] | None = None, lined_up: bool = False) -> str:
    """What the views say of a turned pose T [4 x 4] (`turn_not_refuted`): "unseen" (too little of it lands on the
    other view's depth to verify it), "stands", or what refutes it ("plane", "shape", "texture", "print": the
    interiors' texture, `inner`; with `lined_up`, the texture also where fewer than most of at least
    `params.min_colour_tiles` tiles line up: it stands only on the print's word)."""
    if plane is not None and plane.height(inv_T(T)[:3, 3]) < 0:
        return "plane"  # tgt's camera behind the table the views see from above: no camera sees through a table
    depth = depth_agreement(src, tgt, T, params.depth_noise)
    if depth.consistent + depth.see_through < params.min_overlap:
        return "unseen"
    if depth.see_through_fraction > params.max_see_through or \
            outside_silhouette(src, tgt, T) > params.max_outside_shape:
        return "shape"
    if texture:
        c = colour_agreement(*(fine or (src, tgt)), T, params.depth_noise)
        if texture_refutes(c, params) or (lined_up and not c.mostly_agrees(params.min_colour_tiles)):
            return "texture"
        if inner is not None and texture_refutes(colour_agreement(*inner, T, params.depth_noise), params):
            return "print"
    return "stands"


def support_plane(src: DenseGeometry, tgt: DenseGeometry, T_tgt_src: np.ndarray, params: RegisterParams
                  ) -> Plane | None:
    """The printed plane both views see from one side under the pose T_tgt_src [4 x 4], in src's camera frame
    (normal towards it), or None. Each view's dominant plane (`dominant_plane`: at most 5 % of its samples behind it,
    so a table and not an object's face seen head-on) must hold `params.support_plane_min_frac` of its depth
    samples; the pose must lay tgt's onto src's (normals within SAME_PLANE_DEG, tgt's plane through src's within
    three sigmas of the depth noise and of a pose turned by rule 2's bound, `max_sigma_deg`, at the plane's
    distance), and the plane's print confirm it: most of its textured tiles (at least `min_colour_tiles`, rule 3's
    verdict) line up. Whole frames only: a masked view holds the object alone, whose faces a camera may see from
    either side. The scene is rigid: a turn of the object is a turn of the table with it, and one that puts a
    camera under the table (a turn about an axis along it) is refuted by it. A plain table pins only its own tilt
    and height: the motion along it rests on the object's keypoints alone, and there poses 1-4 deg off claiming
    0.13-0.16 deg passed every other rule (two-frame captures on a plain table, whole frames; its faint texture
    lined up in 5 of 13-16 tiles under them, a printed table's in 70-85 % under right poses 120 deg apart): the
    turns stay to be refuted by the views."""
    if src.mask is not None or tgt.mask is not None:
        return None
    a, b = (dominant_plane(np.where((g.depth > 0)[..., None], g.grid, 0.0), params.support_plane_min_frac,
                           PLANE_ITERATIONS, stride=1) for g in (src, tgt))
    if a is None or b is None:
        return None
    b_src = b.transformed(inv_T(T_tgt_src))
    z = abs(a.offset)  # the plane's distance from src's camera
    foot = -a.offset * a.normal  # the point of src's plane nearest that camera
    tolerance = 3.0 * (float(params.depth_noise.sigma(z)) + z * np.radians(params.max_sigma_deg))
    if float(a.normal @ b_src.normal) < np.cos(np.radians(SAME_PLANE_DEG)) or abs(float(b_src.height(foot))) > \
            tolerance:
        return None
    on = [g.subset(np.abs(p.height(g.grid)) <= 3.0 * params.depth_noise.sigma(g.grid[..., 2]))
          for g, p in ((src, a), (tgt, b))]
    table = colour_agreement(on[0], on[1], T_tgt_src, params.depth_noise)
    log.debug("the plane both views see: its texture %s under the pose", table)
    if not table.mostly_agrees(params.min_colour_tiles):
        return None  # the table's print does not confirm the pose: fewer than most of its tiles line up
    return a


def _turn_axes(pts: np.ndarray, normals: np.ndarray) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(name, axis [3], centre [3]) of each axis an edge's object [N x 3] is turned about: the
    principal directions of its surface normals [N x 3] first (a box's face normals: exact where the points' axes
    tilt, the two views seeing different parts of it), then its points' principal axes, each unless within 10 deg
    of one before; the centre that of the points' box in the axes of its set (`principal_turns`)."""
    faces = _face_axes(normals)
    out: list[tuple[str, np.ndarray, np.ndarray]] = []
    for kind, given in (("face", faces), ("principal", None)):
        axes, centre, _ = principal_turns(pts, given)
        for n, a in zip(AXES, axes, strict=True):
            if all(abs(float(a @ b[1])) < np.cos(np.radians(10.0)) for b in out):
                out.append((f"{n} {kind}", a, centre))
    return out


def _face_axes(normals: np.ndarray, rounds: int = 5) -> np.ndarray:
    """[3 x 3] rows: the directions a box's faces point along, from its surface normals [N x 3]: the normals'
    principal directions, then each made the mean of the normals within 20 deg of it (either sign) and the three
    made orthonormal again, a few rounds (edge and rim normals, and rounded parts, tilt the principal
    directions by up to 10 deg)."""
    axes = np.linalg.eigh(normals.T @ normals)[1][:, ::-1].T
    for _ in range(rounds):
        c = normals @ axes.T  # [N x 3] cosines
        near = np.abs(c) > np.cos(np.radians(20.0))
        if not near.any(axis=0).all():
            break
        m = np.stack([(normals[near[:, k]] * np.sign(c[near[:, k], k])[:, None]).sum(0) for k in range(3)])
        u, _, vt = np.linalg.svd(m)
        axes = u @ vt  # the orthonormal rows nearest the means
    return axes


def _best_centre(src: DenseGeometry, tgt: DenseGeometry, T_tgt_src: np.ndarray, pts: np.ndarray, axis: np.ndarray,
                 centre: np.ndarray, params: RegisterParams, angle: float = np.pi) -> np.ndarray:
    """T_tgt_src [4 x 4] turned by `angle` (rad; half by default) about `axis` [3] through the point [3] near
    `centre` (within half the points' [N x 3] extent across the axis, a grid of CENTRE_STEPS a side) where the views
    contradict it least (the shares of the overlap seen through and of the samples off the other silhouette beyond
    the bounds that refute a turn),
    and, among those they do not contradict, where most depth samples agree. The points' box misses the far
    half of the object where both views see the same faces under a wrong pose, which puts the centre off by up to
    half the object's depth; nearest-point refinement from there would pull the turned pose back onto the faces
    the wrong pose laid onto each other."""
    u = np.cross(axis, [1.0, 0.0, 0.0] if abs(axis[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(axis, u)
    half = 0.5 * np.ptp(pts @ np.stack([u, v]).T, axis=0)
    best, best_key = T_tgt_src, (np.inf, 0)
    for a in np.linspace(-1.0, 1.0, CENTRE_STEPS):
        for b in np.linspace(-1.0, 1.0, CENTRE_STEPS):
            T = T_tgt_src @ axis_rotation(axis, centre + a * half[0] * u + b * half[1] * v, angle)
            d = depth_agreement(src, tgt, T, params.depth_noise)
            off = outside_silhouette(src, tgt, T)
            # uncontradicted centres first (within the bounds that refute a turn), the best supported of them
            c = max(0.0, d.see_through_fraction - params.max_see_through) + max(0.0, off - params.max_outside_shape)
            if (c, -d.consistent) < best_key:
                best, best_key = T, (c, -d.consistent)
    return best
