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
- `turn_not_refuted(src, tgt, T_tgt_src, params, texture)`: the first half turn of an edge two views cannot refute
"""
from __future__ import annotations

import logging

import numpy as np

from gscan.geometry.icp import icp_point_to_plane
from gscan.geometry.symmetry import axis_rotation
from gscan.geometry.transforms import inv_T, transform_points
from gscan.registration.colour import ColourAgreement
from gscan.registration.dense import DenseGeometry, colour_agreement, depth_agreement, outside_silhouette
from gscan.registration.pairwise import RegisterParams

log = logging.getLogger(__name__)

AXES = ("first", "second", "third")  # principal axes, by decreasing spread
REACH = 0.1  # ICP pairing distance of a turned pose, as a share of the points' RMS radius (a turn's axis error)
# an edge's turned pose is refined from afar: under a wrong pose both views' points lie on the same faces, so their
# box misses the object's far half and the turn's axis is off by up to the object's depth
REFINE_REACH = (1.0, 0.3, REACH)


def principal_turns(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """(axes [3 x 3] (rows, unit, by decreasing spread), centre [3], reach (m)) of an object's points [N x 3], N >= 3.

    The centre is that of the points' box in the principal axes, not their mean: the points seen from one side
    miss the faces turned away (and the one the object stands on), so their mean is off the centre a symmetric
    shape turns about. reach: how far a turned pose is let slide when it is refined (`REACH` of the RMS radius)."""
    m = points.mean(0)
    axes = np.linalg.svd(points - m, full_matrices=False)[2]
    q = (points - m) @ axes.T
    centre = m + (0.5 * (q.min(0) + q.max(0))) @ axes
    return axes, centre, REACH * float(np.sqrt(np.mean(np.sum((points - m) ** 2, axis=1))))


def texture_refutes(colour: ColourAgreement, params: RegisterParams) -> bool:
    """Whether texture refutes a pose as it does an edge's (rule 3: enough textured tiles in the overlap, too few of
    them lining up)."""
    return colour.informative >= params.min_colour_tiles and colour.agreeing_fraction < params.min_colour_agreement


def turn_not_refuted(src: DenseGeometry, tgt: DenseGeometry, T_tgt_src: np.ndarray, params: RegisterParams,
                     texture: bool = True) -> str | None:
    """The first half turn of the object about one of its axes that src's and tgt's depth and texture do not refute,
    in words; None when each is refuted.

    src, tgt: the two views' depth samples (the object's: a masked scan's); T_tgt_src [4 x 4] the edge's pose. The
    axes are the principal axes of both views' points in src's camera (tgt's moved by the pose) and those of their
    normals (`_turn_axes`), through the points' centre (`principal_turns`). A turned pose is refined first
    (point to plane, tgt's surface onto src's, within `principal_turns`'s reach), so that a turn about an
    approximate axis is judged at its best. It is refuted only by what contradicts it: the depth (more than
    `params.max_see_through` of the overlap seen through, the bound the pose itself passed), the silhouette (more
    than `params.max_outside_shape` of the samples off the other view's object) or, with `texture` (the views have
    print), the texture (`texture_refutes`).
    Less overlap is no evidence against it: a half turn of a plain box seen from opposite sides lays the faces
    each view sees onto each other, and overlaps more than the right pose, which shares the top alone."""
    pts = np.concatenate([src.points, transform_points(inv_T(T_tgt_src), tgt.points)])
    if len(pts) < 10 or len(tgt) < 10:
        return None
    axes, centre, reach = principal_turns(pts)
    radius = reach / REACH
    normals = np.concatenate([src.point_normals, tgt.point_normals @ T_tgt_src[:3, :3]])
    for name, axis in _turn_axes(axes, normals):
        T0 = T_tgt_src @ axis_rotation(axis, centre, np.pi)
        T_src_tgt = inv_T(T0)
        for scale in REFINE_REACH:
            T_src_tgt, _ = icp_point_to_plane(tgt.points[::2], tgt.point_normals[::2], src.points, T_src_tgt,
                                              scale * radius)
        T = inv_T(T_src_tgt)
        depth = depth_agreement(src, tgt, T, params.depth_noise)
        off = outside_silhouette(src, tgt, T)
        log.debug("half turn about the %s axis: depth %s, %.1f %% off the silhouette", name, depth, 100 * off)
        if depth.see_through_fraction > params.max_see_through or off > params.max_outside_shape:
            continue  # the shape refutes it
        if texture and texture_refutes(colour_agreement(src, tgt, T, params.depth_noise), params):
            continue
        return f"the object turned half about its {name} axis"
    return None


def _turn_axes(axes: np.ndarray, normals: np.ndarray) -> list[tuple[str, np.ndarray]]:
    """(name, axis [3]) of the axes an edge's object is turned about: its points' principal axes (rows of `axes`
    [3 x 3]), then the principal directions of its surface normals [N x 3] (a box's face normals, which its points'
    axes miss when both views see the same faces), each unless within 10 deg of one before."""
    faces = np.linalg.eigh(normals.T @ normals)[1][:, ::-1].T
    out: list[tuple[str, np.ndarray]] = []
    for name, a in [(f"{n} principal", a) for n, a in zip(AXES, axes, strict=True)] + \
            [(f"{n} face", a) for n, a in zip(AXES, faces, strict=True)]:
        if all(abs(float(a @ b)) < np.cos(np.radians(10.0)) for _, b in out):
            out.append((name, a))
    return out
