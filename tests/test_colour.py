"""The colour check of an edge (`gscan.registration.colour`, `dense.colour_agreement`): a textured plane seen
by one camera, posed right, posed turned 180 deg about the optical axis (every depth sample lands back on the
plane, so the depth cannot refute it), and without texture."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from gscan.geometry.transforms import make_T
from gscan.io.camera import Intrinsics
from gscan.registration.colour import image_noise
from gscan.registration.dense import (
    DenseGeometry,
    colour_agreement,
    depth_agreement,
    interior,
    interior_pixels,
    print_agreement,
)
from gscan.registration.noise import DepthNoise

W, H = 320, 240
INTR = Intrinsics(300.0, 300.0, (W - 1) / 2, (H - 1) / 2, W, H)  # principal point at the image's centre
NOISE = DepthNoise()


def _texture(seed: int) -> np.ndarray:
    """[H x W x 3] uint8: blurred noise, texture at a few pixels' scale, like print or wood grain."""
    rng = np.random.default_rng(seed)
    g = cv2.GaussianBlur(rng.uniform(0, 255, (H, W)).astype(np.float32), (0, 0), 1.5)
    g = (g - g.mean()) / g.std() * 40 + 128
    return np.repeat(np.clip(g, 0, 255).astype(np.uint8)[..., None], 3, axis=2)


def _plane(image: np.ndarray) -> DenseGeometry:
    return DenseGeometry.from_depth(np.full((H, W), 1.0, np.float32), INTR, image=image)


def test_right_pose_lines_up_and_a_turned_one_does_not_though_the_depth_agrees():
    g = _plane(_texture(0))
    right = colour_agreement(g, g, np.eye(4), NOISE)
    assert right.informative >= 40 and right.agreeing_fraction > 0.9, right
    turned = make_T(np.diag([-1.0, -1.0, 1.0]), np.zeros(3))  # 180 deg about the optical axis
    assert depth_agreement(g, g, turned, NOISE).see_through == 0  # the depth cannot tell
    wrong = colour_agreement(g, g, turned, NOISE)
    # unrelated texture passes a tile's rank test against 16 baselines about 1 time in 17
    assert wrong.informative >= 40 and wrong.agreeing_fraction < 1 / 3, wrong


def test_another_texture_does_not_line_up():
    a, b = _plane(_texture(0)), _plane(_texture(1))
    c = colour_agreement(a, b, np.eye(4), NOISE)
    assert c.informative >= 40 and c.agreeing_fraction < 1 / 3, c


def test_no_texture_gives_no_verdict():
    rng = np.random.default_rng(2)
    flat = np.clip(128 + rng.normal(0, 2.0, (H, W, 1)), 0, 255).astype(np.uint8).repeat(3, axis=2)
    g = _plane(flat)
    assert colour_agreement(g, g, np.eye(4), NOISE).informative == 0  # pixel noise alone is no texture
    assert colour_agreement(_plane(_texture(0)), DenseGeometry.from_depth(np.full((H, W), 1.0), INTR),
                            np.eye(4), NOISE).informative == 0  # a frame without its image


def test_print_one_frame_lacks_is_one_sided_and_never_lines_up():
    """`print_agreement`: a printed plane against the same plane plain (pixel noise only): every tile textured in
    the printed frame is one-sided, none lines up, and the plain frame's tiles are not informative; against itself
    the tiles line up and none is one-sided."""
    rng = np.random.default_rng(3)
    plain = _plane(np.clip(128 + rng.normal(0, 2.0, (H, W, 1)), 0, 255).astype(np.uint8).repeat(3, axis=2))
    printed = _plane(_texture(0))
    c = print_agreement(printed, plain, np.eye(4), NOISE)
    assert c.informative >= 20 and c.one_sided == c.informative and c.agreeing == 0, c
    assert print_agreement(plain, printed, np.eye(4), NOISE) == c  # both directions are counted
    same = print_agreement(printed, printed, np.eye(4), NOISE)
    assert same.informative == 2 * c.informative and same.one_sided == 0, same
    assert same.agreeing > 0.9 * same.informative, same


def test_interior_leaves_out_the_crease_and_the_rim():
    """`interior`: a roof (two planes meeting at 90 deg along the image's middle column) inside a mask keeps the
    samples farther than the reach from the ridge and from the mask's edge, and none nearer."""
    u = np.arange(W, dtype=np.float64)[None, :].repeat(H, axis=0)
    depth = (1.0 / (1.0 - np.abs(u - INTR.cx) / INTR.fx)).astype(np.float32)  # z = 1 + |x|: a box's edge
    mask = np.zeros((H, W), bool)
    mask[40:200, 40:280] = True
    g = DenseGeometry.from_depth(depth, INTR, mask, image=_texture(0))
    reach = 12.0
    kept = interior(g, NOISE, reach)
    assert 0 < len(kept.points) < len(g.points) and kept.pixels is not None and g.pixels is not None
    pu, pv = kept.pixels[:, 0], kept.pixels[:, 1]
    edge = np.minimum.reduce([pu - 40, 279 - pu, pv - 40, 199 - pv])
    assert np.all(np.abs(pu - INTR.cx) > reach) and np.all(edge >= reach), (pu, pv)
    gu, gv = g.pixels[:, 0], g.pixels[:, 1]
    far = (np.abs(gu - INTR.cx) > 2 * reach + 8) & (np.minimum.reduce([gu - 40, 279 - gu, gv - 40, 199 - gv]) >
                                                     2 * reach + 8)
    assert far.sum() > 50 and {tuple(p) for p in g.pixels[far]} <= {tuple(p) for p in kept.pixels}
    np.testing.assert_array_equal(kept.points, kept.grid[kept.depth > 0])  # the samples listed as kept


def test_interior_pixels_find_the_print_of_a_face_seen_nearly_edge_on():
    """`interior_pixels`: the same roof with a face 34 px wide beside the ridge (a box's side seen nearly edge on),
    sampled every 2 px: its pixels at least the reach from the mask's edge and the reach less a stride of g from
    the ridge are kept, to the pixel, and none nearer."""
    u = np.arange(W, dtype=np.float64)[None, :].repeat(H, axis=0)
    depth = (1.0 / (1.0 - np.abs(u - INTR.cx) / INTR.fx)).astype(np.float32)
    mask = np.zeros((H, W), bool)
    mask[40:200, 126:280] = True  # the face left of the ridge (cx = 159.5) is 34 px wide
    g = DenseGeometry.from_depth(depth, INTR, mask, samples=1600, image=_texture(0))
    s = int(round(INTR.fx / g.fx))
    reach = 12.0
    kept = interior_pixels(g, NOISE, reach)
    assert kept.pixels is not None and g.fine.pixels is not None and s >= 4
    pu, pv = kept.pixels[:, 0], kept.pixels[:, 1]
    edge = np.minimum.reduce([pu - 126 + 1, 280 - pu, pv - 40 + 1, 200 - pv])  # px to the nearest pixel outside
    assert np.all(edge >= reach) and np.all(np.abs(pu - INTR.cx) >= reach - s - 1), (pu, pv)
    narrow = pu < INTR.cx
    assert narrow.sum() > 100  # the narrow face keeps its middle strip (x > 137 px, x < 145 px)
    fu, fv = g.fine.pixels[:, 0], g.fine.pixels[:, 1]
    clear = (np.minimum.reduce([fu - 126 + 1, 280 - fu, fv - 40 + 1, 200 - fv]) >= reach + 1) & \
        (np.abs(fu - INTR.cx) >= reach + s + 1)
    assert {tuple(p) for p in g.fine.pixels[clear]} <= {tuple(p) for p in kept.pixels}


@pytest.mark.parametrize("sigma", [1.0, 3.0, 8.0])
def test_image_noise_is_estimated_from_the_image(sigma):
    """Immerkaer's estimator on a smooth ramp plus Gaussian noise: within 5 % (the estimate's relative standard
    error over 76 000 pixels is about 0.3 %; the ramp adds nothing, its second differences are zero)."""
    rng = np.random.default_rng(3)
    ramp = np.add.outer(np.linspace(0, 60, H), np.linspace(0, 90, W))
    assert image_noise(ramp + rng.normal(0, sigma, (H, W))) == pytest.approx(sigma, rel=0.05)


def _tile_zncc_numpy(Ia, t, tgt_texture, u, v, shifts):
    """The correlation of `colour._tile_zncc` in plain numpy ([shifts x samples] arrays, np.add.reduceat)."""
    order = np.argsort(t, kind="stable")
    t, Ia, u, v = t[order], Ia[order], u[order], v[order]
    starts = np.flatnonzero(np.r_[True, t[1:] != t[:-1]])
    W = tgt_texture.shape[1]
    x0, y0 = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    fx, fy = u - x0, v - y0
    flat = tgt_texture.ravel()
    at = (y0 * W + x0)[None, :] + np.array([dy * W + dx for dx, dy in shifts], dtype=np.int64)[:, None]
    Ib = ((flat[at] * (1 - fx) + flat[at + 1] * fx) * (1 - fy) + (flat[at + W] * (1 - fx) + flat[at + W + 1] * fx) * fy)
    n = np.diff(np.r_[starts, len(t)]).astype(np.float64)
    sa = np.add.reduceat(Ia, starts)
    var_a = np.add.reduceat(Ia * Ia, starts) - sa * sa / n
    sb = np.add.reduceat(Ib, starts, axis=1)
    var_b = np.add.reduceat(Ib * Ib, starts, axis=1) - sb * sb / n
    cov = np.add.reduceat(Ib * Ia, starts, axis=1) - sa * sb / n
    return cov / np.sqrt(np.maximum(var_a * var_b, 1e-12))


@pytest.mark.parametrize("seed", range(3))
def test_the_correlation_kernel_is_numpys_to_the_bit(seed):
    """`_tile_zncc` (a numba kernel) gives what numpy's arrays and np.add.reduceat give, bit for bit, on tiles of
    1 to 300 samples (numpy's pairwise sum: sequential below 8 values, blocks of 8 up to 128, halves beyond)."""
    from gscan.registration.colour import FAR, SEARCH, _tile_zncc, texture_image

    rng = np.random.default_rng(seed)
    tex = texture_image(_texture(seed)[..., 0].astype(np.float32))
    sizes = np.r_[1, 2, 7, 8, 9, 15, 16, 17, 127, 128, 129, 130, 200, 300, rng.integers(1, 60, 20)]
    t = rng.permutation(np.repeat(np.arange(len(sizes)), sizes))
    u = rng.uniform(40, W - 41, len(t))
    v = rng.uniform(40, H - 41, len(t))
    Ia = rng.normal(0, 20, len(t))
    for shifts in (SEARCH, FAR):
        got = _tile_zncc(Ia, t, len(sizes), tex, u, v, shifts)
        assert np.array_equal(got, _tile_zncc_numpy(Ia, t, tex, u, v, shifts))


def _shaded(colour: tuple[int, int, int], seed: int) -> np.ndarray:
    """[H x W x 3] uint8: one colour shaded from 40 % to 100 % across the image (a face turning from the light),
    with pixel noise of 2 grey levels."""
    rng = np.random.default_rng(seed)
    shade = np.linspace(0.4, 1.0, W)[None, :, None]
    img = np.asarray(colour, np.float64)[None, None, :] * shade + rng.normal(0, 2.0, (H, W, 3))
    return np.clip(img, 0, 255).astype(np.uint8)


def test_chromaticity_ignores_shading_and_tells_another_colour():
    """`chromaticity` / `chroma_shift` / `dense.chroma_pairs`: a plane seen right under two shadings of one colour
    lies within noise of itself (the shading turned the other way: each pair's brightness differs up to 2.5
    times); the same plane in a colour 0.1 away in chromaticity lies that far, and in stripes of two colours whose
    mean is the plane's, as far as each stripe; a dark image tells nothing, a grey one has no chromaticity."""
    from gscan.registration.colour import chroma_shift, chromaticity
    from gscan.registration.dense import chroma_pairs

    olive = (150, 152, 92)
    a = _shaded(olive, 0)
    b = np.ascontiguousarray(_shaded(olive, 1)[:, ::-1])
    ga = _plane(a)
    pairs = chroma_pairs(ga, _plane(b), np.eye(4), NOISE, chromaticity(a, 0.01), chromaticity(b, 0.01))
    same, n = chroma_shift(*pairs)
    assert n > 1000 and same < 0.003, (same, n)
    red = (200, 100, 92)  # r 0.51 instead of 0.38, g 0.26 instead of 0.38
    c = _shaded(red, 2)
    other, n = chroma_shift(*chroma_pairs(ga, _plane(c), np.eye(4), NOISE, chromaticity(a, 0.01),
                                          chromaticity(c, 0.01)))
    want = np.hypot(200 / 392 - 150 / 394, 100 / 392 - 152 / 394)
    assert n > 1000 and abs(other - want) < 0.01, (other, want)
    # a print of two colours either side of the olive: their mean chromaticity is the olive's, each pair far off
    half = np.zeros((H, W), bool)
    half[:, ::16] = True
    half = np.cumsum(half, axis=1) % 2 == 1
    two = np.where(half[..., None], _shaded((180, 122, 92), 4), _shaded((120, 182, 92), 5))
    printed, _ = chroma_shift(*chroma_pairs(ga, _plane(two), np.eye(4), NOISE, chromaticity(a, 0.01),
                                            chromaticity(two, 0.01)))
    assert printed > 0.05, printed
    dark = (_shaded(olive, 3) // 40).astype(np.uint8)  # channel sums of 3-10 grey levels: noise dominates
    assert np.isnan(chromaticity(dark, 0.01)).all()
    assert chromaticity(a[..., 0], 0.01) is None
    assert chroma_shift(np.full((3, 2), np.nan), np.zeros((3, 2))) == (0.0, 0)
