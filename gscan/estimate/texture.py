"""The texture check of a pose the depth alone decided (a template with depth keypoints, `decided_by_depth`).

A plain object's pose rests on its shape: its keypoint support is mostly depth keypoints, and the depth confirms
any pose that lays its surface on a surface of that shape. In clutter another box of about its size offers such
a surface: measured on the plain Fondant box's scenes without it, poses on a printed box fit the depth entirely
(score 1.0, 90 % of the visible surface confirmed, 0.3-1.7 % of it off the objects standing on the table), held by
15-20 consistent depth keypoint pairs. The print refutes them: the template's keyframes saw a plain surface there.

So the query's texture is compared with the keyframe nearest the pose's viewing direction by registration's
texture check (`gscan.registration.dense.colour_agreement`): the keyframe's object samples (its mask) and the
query's search region, each with its band-passed texture, moved into each other by the pose; a tile is
informative where its texture varies beyond the image's noise, in either image, and agrees where it lines up.
Print on the query where the keyframe is plain lines up nowhere. The pose is refused when at least
`accept.min_colour_tiles` tiles are informative and fewer than `accept.min_colour_agreement` of them agree
(registration's rule for an edge); no informative tile (plain against plain) leaves the pose to the depth. A
template without its keyframes' images cannot check the texture: the pose is refused.

That rule needs `accept.min_colour_tiles` tiles, and a box of about the object's size a little way off (0.7 m: 7 of
its 48-pixel tiles overlap) leaves it without a verdict; nor does its share tell the poses apart on a plain
template: its informative tiles are mostly the rims and creases, whose shading lines up under any pose that lays a
box's faces on a box's faces (bench/plain.py's look-alike frames, seeds 0-7: right poses 2-14 of 7-19 lining up,
the wrong ones on a printed box it let through 1-8 of 3-14). So the faces' interiors are judged on their own
(`gscan.registration.dense.interior`: the samples with no rim and no crease within the band-pass's reach,
`PRINT_REACH_PX`), where the band-passed texture is the surface's print and not its shading: a tile textured there
in one image whose counterpart in the other is plain (`gscan.registration.colour.print_tiles`: below that image's
informative level, both levels set by each image's own noise) is print the other lacks, a fact measured per tile
against the sensor's noise, not a rank test's chance. A pose with such a tile is refused when fewer than
`accept.min_colour_agreement` of the interiors' informative tiles line up (a one-sided tile never does); a plain
template seen on its own plain faces has none.

Plain against plain leaves the texture nothing to judge, and another plain object of about the object's size fits
its depth, its silhouettes and its (absent) print. Its colour tells them apart: the query's samples landing on the
keyframe's surface under the pose are paired with the keyframe's pixels there, each side's chromaticity (r and g over
the channels' sum, `gscan.registration.colour.chromaticity`: shading scales the channels alike and leaves it) is
compared pair by pair, and the pose is refused when the median of the pairs' distances lies beyond
`accept.max_chroma_shift` (0.05: a grey surface lit at 4500 K instead of 6500 K with the white balance unchanged
moves about that far, far more than a right pose's pairs differ: BENCHMARKS.md, "Plain objects"). Pixels too dark
to tell a chromaticity within a third of the bound count for neither side, and fewer than MIN_CHROMA_PAIRS pairs
give no verdict.

The keyframes' images are read from the template file on first use and their samples cached (`KeyframeTextures`).
"""
from __future__ import annotations

import logging
import threading
from pathlib import Path

import numpy as np

from gscan.estimate.params import AcceptParams
from gscan.estimate.query import QueryFrame
from gscan.geometry.transforms import inv_T
from gscan.registration.colour import PRINT_REACH_PX, chroma_shift, chromaticity
from gscan.registration.dense import DenseGeometry, chroma_pairs, colour_agreement, interior, print_agreement
from gscan.registration.noise import DepthNoise

log = logging.getLogger(__name__)

MIN_CHROMA_PAIRS = 16  # sample pairs the colour check needs for a verdict (a median over fewer is a few pixels')


class KeyframeTextures:
    """The keyframes' object samples with their texture (`DenseGeometry`) and their images' chromaticity
    (`chromaticity`, told as the colour check of bound max_chroma_shift needs: `chroma_sigma`), read from the
    template file `path` (views `names`, poses T_obj_cam [V x 4 x 4]) when first asked for, then kept."""

    def __init__(self, path: str | Path | None, names: list[str], T_obj_cam: np.ndarray, max_chroma_shift: float):
        self.path, self.names, self.T_obj_cam = path, names, np.asarray(T_obj_cam, dtype=np.float64)
        self.chroma_sigma = chroma_sigma(max_chroma_shift)
        self._read_views: dict[int, tuple[DenseGeometry | None, np.ndarray | None]] = {}
        self._interiors: dict[tuple[int, DepthNoise], DenseGeometry] = {}
        self._lock = threading.Lock()

    def nearest(self, T_cam_obj: np.ndarray) -> int:
        """The keyframe whose optical axis lies nearest the query camera's at the pose T_cam_obj [4 x 4]."""
        axis = T_cam_obj[:3, :3].T @ np.array([0.0, 0.0, 1.0])
        return int(np.argmax(self.T_obj_cam[:, :3, 2] @ axis))

    def dense(self, v: int) -> DenseGeometry | None:
        """Keyframe v's object samples with texture; None when the template keeps no images of it."""
        return self._get(v)[0]

    def interior(self, v: int, noise: DepthNoise) -> DenseGeometry | None:
        """Keyframe v's samples on a face's interior (`gscan.registration.dense.interior`, within `PRINT_REACH_PX`),
        computed once per noise model; None when the template keeps no images of it."""
        kf = self.dense(v)
        if kf is None:
            return None
        with self._lock:
            if (v, noise) not in self._interiors:
                self._interiors[(v, noise)] = interior(kf, noise, PRINT_REACH_PX)
            return self._interiors[(v, noise)]

    def chroma(self, v: int) -> np.ndarray | None:
        """Keyframe v's image's chromaticity [H x W x 2]; None without a colour image of it."""
        return self._get(v)[1]

    def _get(self, v: int) -> tuple[DenseGeometry | None, np.ndarray | None]:
        with self._lock:
            if v not in self._read_views:
                self._read_views[v] = self._read(v)
            return self._read_views[v]

    def _read(self, v: int) -> tuple[DenseGeometry | None, np.ndarray | None]:
        from gscan.template.db import TemplateDB

        if self.path is None:
            return None, None
        with TemplateDB.open(self.path) as db:
            view = db.view(self.names[v])
        if view.color is None or view.depth is None:
            return None, None
        return (DenseGeometry.from_depth(view.depth, view.intrinsics, view.mask, image=view.color),
                chromaticity(view.color, self.chroma_sigma))


def texture_refusal(q: QueryFrame, T_cam_obj: np.ndarray, keyframes: KeyframeTextures, noise: DepthNoise,
                    p: AcceptParams) -> str | None:
    """The reason the query's texture refutes a pose the depth alone decided (module docstring), else None.
    noise: the template's depth noise (its capture's)."""
    v = keyframes.nearest(T_cam_obj)
    kf = keyframes.dense(v)
    if kf is None:
        return (f"the template keeps no image of its view {keyframes.names[v]} to check the texture of a pose the "
                "depth alone decided")
    query = q.textured
    T_kf_cam = inv_T(keyframes.T_obj_cam[v]) @ inv_T(T_cam_obj)  # query camera -> keyframe camera
    c = colour_agreement(query, kf, T_kf_cam, noise)
    log.debug("texture against keyframe %s: %d of %d informative tiles agree", keyframes.names[v], c.agreeing,
              c.informative)
    if c.refutes(p.min_colour_tiles, p.min_colour_agreement):
        return (f"texture disagrees ({c.agreeing} of {c.informative} textured tiles line up with the template's view "
                f"{keyframes.names[v]}; the depth alone decided the pose)")
    kf_interior = keyframes.interior(v, noise)
    assert kf_interior is not None  # the keyframe has samples (kf above)
    pr = print_agreement(q.textured_interior(noise, PRINT_REACH_PX), kf_interior, T_kf_cam, noise)
    log.debug("print against keyframe %s: %d of %d informative interior tiles one-sided, %d agree", keyframes.names[v],
              pr.one_sided, pr.informative, pr.agreeing)
    if pr.one_sided and pr.agreeing < p.min_colour_agreement * pr.informative:
        return (f"print disagrees ({pr.one_sided} of {pr.informative} textured tiles of the faces' interiors are print "
                f"that the query or the template's view {keyframes.names[v]} lacks, {pr.agreeing} line up; the depth "
                "alone decided the pose)")
    return chroma_refusal(query, kf, T_kf_cam, q.chroma(chroma_sigma(p.max_chroma_shift)), keyframes.chroma(v),
                          noise, p.max_chroma_shift, keyframes.names[v])


def chroma_sigma(max_shift: float) -> float:
    """How well a pixel's chromaticity must be told to count for the colour check of bound max_shift: a third of
    it (`chromaticity`'s max_sigma)."""
    return max_shift / 3.0


def chroma_refusal(query: DenseGeometry, kf: DenseGeometry, T_kf_cam: np.ndarray, q_chroma: np.ndarray | None,
                   kf_chroma: np.ndarray | None, noise: DepthNoise, max_shift: float, name: str) -> str | None:
    """The reason the colour of the surface under a pose refutes it (module docstring), else None: the query's
    samples (`query`, its image's chromaticity q_chroma) landing on the keyframe's surface (`kf`, its chromaticity
    kf_chroma, T_kf_cam the query camera in the keyframe's) at least MIN_CHROMA_PAIRS times, where both images are
    bright enough to tell a chromaticity within `chroma_sigma`, lie farther than max_shift from the keyframe's
    (`chroma_shift`). Without a colour image on either side, no verdict."""
    if q_chroma is None or kf_chroma is None:
        return None
    shift, n = chroma_shift(*chroma_pairs(query, kf, T_kf_cam, noise, q_chroma, kf_chroma))
    log.debug("colour against keyframe %s: %d pairs, chromaticity %.4f apart", name, n, shift)
    if n >= MIN_CHROMA_PAIRS and shift > max_shift:
        return (f"colour disagrees (the surface under the pose lies {shift:.3f} in chromaticity from the template's "
                f"view {name}'s, beyond {max_shift:.3f}; the depth alone decided the pose)")
    return None
