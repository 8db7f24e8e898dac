"""RealSense-like depth noise model.

Applied to an exact depth image, in this order:
1. axial gaussian noise, sigma(z) = sigma_0 + sigma_2 * (z - z_ref)^2 (default 1.2 mm + 1.9 mm/m^2
   * (z - 0.4 m)^2, the structured-light model of Nguyen et al. 2012, close to a D435 at 0.3-1.5 m);
2. invalid pixels at depth discontinuities: pixels where the second difference of inverse depth
   along a row or column exceeds `edge_jump` relative to the inverse depth (a jump of about that
   fraction of the depth; planes of any slant give none), where two labels meet, or at the border
   of the valid region are dropped, and the band up to `edge_band_px` further pixels around them is
   dropped with probability `edge_drop_prob` (ragged edges);
3. grazing surfaces (|cos| between ray and normal below `grazing_cos`) are dropped;
4. random dropout clusters: a Poisson(`clusters_mean`) number of ellipses, radii 2-`cluster_max_px` px;
5. stereo occlusion (computed by the renderer): surface points that a second imager `baseline` m to
   the right of the camera (+x, the D435's 50 mm left-to-right imager baseline) cannot see are invalid,
   the band of missing depth left of foreground objects that active-stereo sensors show;
6. quantisation to `quantum` m (1 mm) and the valid range [min_range, max_range] (0.1-3 m).
The renderer also blurs the colour image slightly (`color_blur_sigma` px, lens / demosaicing
softness, which also hides ray-casting aliasing) and adds gaussian noise (`color_sigma`, 8-bit units).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class DepthNoise:
    sigma_0: float = 0.0012
    sigma_2: float = 0.0019
    z_ref: float = 0.4
    edge_jump: float = 0.02
    edge_band_px: int = 1
    edge_drop_prob: float = 0.6
    grazing_cos: float = 0.12
    clusters_mean: float = 3.0
    cluster_max_px: int = 9
    quantum: float = 0.001
    min_range: float = 0.1
    max_range: float = 3.0
    baseline: float = 0.05
    color_sigma: float = 1.5
    color_blur_sigma: float = 0.5


def depth_sigma(z: np.ndarray, p: DepthNoise = DepthNoise()) -> np.ndarray:
    """Axial noise standard deviation (m) at depth z (m)."""
    return p.sigma_0 + p.sigma_2 * (np.asarray(z) - p.z_ref) ** 2


def discontinuities(depth: np.ndarray, labels: np.ndarray | None, rel_jump: float) -> np.ndarray:
    """[H x W] bool: pixels at a depth discontinuity, a label change or the border of the valid region.

    A discontinuity is a second difference of inverse depth (zero on any plane, however oblique)
    along a row or column larger than `rel_jump` relative to the pixel's inverse depth; both
    pixels next to a jump are marked.
    """
    valid = depth > 0
    inv = np.where(valid, 1.0 / np.maximum(depth, 1e-6), 0.0).astype(np.float32)
    thr = rel_jump * inv
    edge = np.zeros(depth.shape, bool)
    d2 = np.abs(inv[:, 2:] - 2 * inv[:, 1:-1] + inv[:, :-2])
    edge[:, 1:-1] |= d2 > thr[:, 1:-1]
    d2 = np.abs(inv[2:] - 2 * inv[1:-1] + inv[:-2])
    edge[1:-1] |= d2 > thr[1:-1]
    kernel = np.ones((3, 3), np.uint8)
    edge |= cv2.erode(valid.astype(np.uint8), kernel) == 0  # border of the valid region
    if labels is not None:
        lab = labels.astype(np.float32)
        edge |= cv2.dilate(lab, kernel) != cv2.erode(lab, kernel)
    return edge & valid


def apply_depth_noise(depth_clean: np.ndarray, labels: np.ndarray | None, cos_view: np.ndarray | None,
                      rng: np.random.Generator, p: DepthNoise = DepthNoise(),
                      invalid: np.ndarray | None = None) -> np.ndarray:
    """Noisy [H x W] float32 depth (0 = invalid) from exact depth [H x W] m (0 where nothing was hit).

    labels: [H x W] object labels (label changes are discontinuities) or None; cos_view: [H x W]
    |cos| between ray and surface normal or None; invalid: [H x W] bool pixels to drop (the
    renderer's stereo-occlusion shadow) or None."""
    H, W = depth_clean.shape
    valid = depth_clean > 0
    z = depth_clean.astype(np.float64)
    noisy = z + rng.standard_normal((H, W)) * depth_sigma(z, p)
    drop = discontinuities(depth_clean, labels, p.edge_jump)
    if p.edge_band_px > 0:
        k = 2 * p.edge_band_px + 1
        band = cv2.dilate(drop.astype(np.uint8), np.ones((k, k), np.uint8)).astype(bool)
        drop |= band & (rng.random((H, W)) < p.edge_drop_prob)
    if cos_view is not None:
        drop |= valid & (cos_view < p.grazing_cos)
    holes = np.zeros((H, W), np.uint8)
    for _ in range(int(rng.poisson(p.clusters_mean))):
        c = (int(rng.integers(0, W)), int(rng.integers(0, H)))
        ax = (int(rng.integers(2, p.cluster_max_px + 1)), int(rng.integers(2, p.cluster_max_px + 1)))
        cv2.ellipse(holes, c, ax, float(rng.uniform(0, 180)), 0, 360, 1, -1)
    drop |= holes.astype(bool)
    if invalid is not None:
        drop |= invalid
    if p.quantum > 0:
        noisy = np.round(noisy / p.quantum) * p.quantum
    ok = valid & ~drop & (noisy >= p.min_range) & (noisy <= p.max_range)
    return np.where(ok, noisy, 0.0).astype(np.float32)
