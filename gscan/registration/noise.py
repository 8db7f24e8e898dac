"""The depth noise model behind every registration threshold: one rule, stated here.

A keypoint lifted with the depth image is off its true 3D position by a noise that grows with its
depth z: the sensor's axial noise (structured light and stereo: proportional to z^2), the keypoint's
localisation error in the image (proportional to z / f) and a floor (depth quantisation). Each axis
of a lifted point is modelled with variance

    sigma^2(z) = c0 + c1 z^2 + c2 z^4        (m^2; c0, c1, c2 >= 0)

and the difference of two lifted points of one surface point, seen in two frames, with
s^2 = sigma^2(z_a) + sigma^2(z_b) per axis: its length |r| follows a chi distribution with 3 degrees
of freedom scaled by s (median 1.54 s, 99 % below 3.37 s).

Registration uses s as the unit of every keypoint residual: a pair is an inlier of a pose when
|r| < gate * s; the pose is solved by Kabsch weighted by 1 / s^2; an edge's information matrix is the
sum of the pairs' information with that weight. The same model, with its own coefficients, describes a
single depth pixel (the depth samples that verify and refine an edge, `gscan.registration.dense`): a
keypoint's depth is the median of a window of pixels, so it is several times less noisy than one pixel.
A keypoint found in the depth's geometry (`gscan.features.depth`) is not a surface point seen twice: each
view picks it anew on its own voxel grid, so its position carries a location sigma of its own (per axis,
`Features.location_sigma`), added in quadrature: s^2 = sigma^2(z_a) + sigma^2(z_b) + l_a^2 + l_b^2 (l = 0
for image keypoints, whose localisation error the model's c1 term holds).
A depth pixel is compared with another frame's surface along that surface's normal (the depth check, the
depth refinement): there its noise is not the same on every axis. The sensor's error lies along the ray
(the floor, quantisation, and the axial term: c0 + c2 z^4), the pixel's lateral error across it (c1 z^2),
so a sample whose ray meets the normal at |cos| = c has the normal variance (c0 + c2 z^4) c^2 + c1 z^2
(1 - c^2): a face seen head-on is the noisiest along its normal, one seen at a slant much less (measured on a
rendered box at 0.6 m: residuals over the per-axis model's s spread 0.56 at |cos| < 0.5 and 1.37 above 0.95;
over the model along the ray, 1.04 and 1.07). A model of that form is `along_ray` (`DepthNoise.normal_sigma`;
a per-axis model gives its s at every angle). Where the depth alone judges a pose (a plain object), registration
uses the capture's depth noise along the ray (`RegisterParams.depth_noise_ray`); elsewhere the per-axis model,
with which the other rules' bounds were measured.
A scan estimates its models from the residuals of a few sequential pairs registered under a generous prior
(`estimate_noise`), so thresholds follow the sensor in hand (a Kinect at 2 m, a RealSense at 0.5 m, a
clean render) instead of a constant.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace
from typing import Annotated

import numpy as np
from pydantic import Field

from gscan.settings import SETTINGS

log = logging.getLogger(__name__)

CHI3_MEDIAN = 1.5382  # median of a chi distribution with 3 degrees of freedom
# the floor of the fit: 1 mm depth quantisation (uniform: 1 mm / sqrt(12) per axis) and a 0.3 px
# localisation error at f = 600 px (0.5 mm per metre of depth); a fit may not go below it
MIN_C0 = (0.001 / np.sqrt(12.0)) ** 2
MIN_C1 = (0.3 / 600.0) ** 2


@dataclass(frozen=True)
class DepthNoise:
    """Per-axis noise of a lifted point, sigma^2(z) = c0 + c1 z^2 + c2 z^4 (module docstring); `along_ray`, a depth
    pixel's with c0 + c2 z^4 along the sensor's ray and c1 z^2 across it (`normal_sigma`).

    The defaults are the generous prior a scan starts from: 1 mm + 2 mm per metre (lateral) + 1.5 mm per
    metre^2 (axial), about a Kinect v1 or a RealSense D435 (sigma 2.7 mm at 1 m, 8.7 mm at 2.2 m).
    """

    __pydantic_config__ = SETTINGS

    c0: Annotated[float, Field(ge=0, description="per-axis variance floor (m^2)")] = 0.001 ** 2
    c1: Annotated[float, Field(ge=0, description="... growing with depth^2 (localisation: m^2 per m^2)")] = 0.002 ** 2
    c2: Annotated[float, Field(ge=0, description="... growing with depth^4 (axial sensor noise: m^2 per m^4)")] = (
        0.0015 ** 2)
    along_ray: Annotated[bool, Field(description="the model's form: c0 + c2 z^4 along the sensor's ray and c1 z^2 "
                                     "across it (a depth pixel compared along a surface normal), or false: each "
                                     "term on every axis")] = False

    def __post_init__(self) -> None:
        if min(self.c0, self.c1, self.c2) < 0 or not np.isfinite([self.c0, self.c1, self.c2]).all():
            raise ValueError("noise coefficients must be finite and >= 0")
        if self.c0 + self.c1 + self.c2 <= 0:
            raise ValueError("a noise model needs a positive coefficient")

    def sigma(self, z: np.ndarray | float) -> np.ndarray:
        """[N] per-axis standard deviation (m) of points at depths z [N] (m)."""
        z2 = np.square(np.asarray(z, dtype=np.float64))
        return np.sqrt(self.c0 + self.c1 * z2 + self.c2 * z2 * z2)

    def pair_sigma(self, z_a: np.ndarray | float, z_b: np.ndarray | float,
                   loc: np.ndarray | float = 0.0) -> np.ndarray:
        """[N] per-axis standard deviation s (m) of the difference of two points at depths z_a, z_b [N], whose
        keypoints are located on the surface to a combined per-axis sigma loc [N] (m) beyond the model's own
        (module docstring: 0 for image keypoints, whose localisation the model holds)."""
        return np.sqrt(self.sigma(z_a) ** 2 + self.sigma(z_b) ** 2 + np.square(loc))

    def normal_sigma(self, z_a: np.ndarray | float, z_b: np.ndarray | float, cos_a: np.ndarray | float,
                     cos_b: np.ndarray | float) -> np.ndarray:
        """[N] standard deviation (m) of the distance along a surface normal between two depth samples at depths
        z_a, z_b [N] whose rays meet the normal at |cos| cos_a, cos_b [N] (module docstring: along the ray
        c0 + c2 z^4, across it c1 z^2; the per-axis model's `pair_sigma` unless `along_ray`)."""
        if not self.along_ray:
            return self.pair_sigma(z_a, z_b)
        return np.sqrt(self._normal_var(z_a, cos_a) + self._normal_var(z_b, cos_b))

    def _normal_var(self, z: np.ndarray | float, cos: np.ndarray | float) -> np.ndarray:
        z2, c2 = np.square(np.asarray(z, dtype=np.float64)), np.square(np.asarray(cos, dtype=np.float64))
        return (self.c0 + self.c2 * z2 * z2) * c2 + self.c1 * z2 * (1.0 - c2)

    def to_dict(self) -> dict[str, float]:
        out: dict = {"c0": float(self.c0), "c1": float(self.c1), "c2": float(self.c2)}
        return out | {"along_ray": True} if self.along_ray else out


def estimate_noise(residuals: np.ndarray, z_a: np.ndarray, z_b: np.ndarray, prior: DepthNoise = DepthNoise(),
                   dof: int = 3, min_pairs: int = 60, gate: float | None = None,
                   loc: np.ndarray | None = None,
                   cosines: tuple[np.ndarray, np.ndarray] | None = None) -> DepthNoise:
    """DepthNoise fitted to residuals [N] (m) of inlier pairs at depths z_a, z_b [N]: lengths of 3-D
    differences (dof 3: keypoint pairs) or signed distances along one direction (dof 1: a depth sample to
    the other frame's surface).

    E[r^2] = dof s^2 is linear in (c0, c1, c2): an iteratively re-weighted, non-negative least-squares fit,
    each round dropping the pairs beyond `gate` s of the current fit (default: the 99 % point of the chi
    distribution with `dof` degrees of freedom), starting from `prior`. Coefficients never go below the
    floor (MIN_C0, MIN_C1). Returns `prior` when fewer than `min_pairs` pairs are left. loc [N] (m): each pair's
    combined keypoint location sigma (`DepthNoise.pair_sigma`; None: 0), known and so not fitted: the model's
    coefficients describe the sensor alone. cosines: ([N], [N]) with dof 1, the |cos| at which each sample's ray
    meets the normal its distance is measured along (`DepthNoise.normal_sigma`); None: the per-axis model.
    """
    from scipy.optimize import nnls
    from scipy.stats import chi2

    r2 = np.square(np.asarray(residuals, dtype=np.float64))
    za2 = np.square(np.asarray(z_a, dtype=np.float64))
    zb2 = np.square(np.asarray(z_b, dtype=np.float64))
    l2 = np.zeros(len(r2)) if loc is None else np.square(np.asarray(loc, dtype=np.float64))
    ok = np.isfinite(r2) & (za2 > 0) & (zb2 > 0) & np.isfinite(l2)
    r2, za2, zb2, l2 = r2[ok], za2[ok], zb2[ok], l2[ok]
    if cosines is None:
        A = np.stack([np.full(len(r2), 2.0), za2 + zb2, za2 * za2 + zb2 * zb2], axis=1)  # s^2 = A @ c + l2
    else:  # along the ray c0 + c2 z^4, across it c1 z^2 (`DepthNoise.normal_sigma`)
        ca2, cb2 = (np.square(np.asarray(c, dtype=np.float64))[ok] for c in cosines)
        A = np.stack([ca2 + cb2, za2 * (1 - ca2) + zb2 * (1 - cb2), za2 * za2 * ca2 + zb2 * zb2 * cb2], axis=1)
    fin = np.isfinite(A).all(1)
    r2, A, l2 = r2[fin], A[fin], l2[fin]
    if gate is None:
        gate = float(np.sqrt(chi2.ppf(0.99, dof)))
    # the gate truncates the chi-square: E[r^2 | |r| < gate s] = k s^2 with k a little below dof
    k = dof * chi2.cdf(gate * gate, dof + 2) / chi2.cdf(gate * gate, dof)
    noise = replace(prior, along_ray=cosines is not None)
    for _ in range(6):
        c = np.array([noise.c0, noise.c1, noise.c2])
        s2 = A @ c + l2
        keep = r2 < gate * gate * s2
        if keep.sum() < min_pairs:
            log.info("noise: %d pairs within the gate, keeping %s", int(keep.sum()), noise)
            return noise
        w = 1.0 / s2[keep]  # relative weights: the variance of r^2 grows with s^4
        c_new, _ = nnls(A[keep] * w[:, None] * k, (r2[keep] - k * l2[keep]) * w)
        fitted = DepthNoise(max(float(c_new[0]), MIN_C0), max(float(c_new[1]), MIN_C1), float(c_new[2]),
                             along_ray=cosines is not None)
        if np.allclose([fitted.c0, fitted.c1, fitted.c2], c, rtol=1e-3, atol=1e-12):
            noise = fitted
            break
        noise = fitted
    log.info("noise fitted on %d pairs: sigma %.1f / %.1f / %.1f mm at 0.5 / 1 / 2 m", len(r2),
             *(1000 * noise.sigma(np.array([0.5, 1.0, 2.0]))))
    return noise


def sign_test(k: int, m: int) -> float:
    """One-sided p-value of a sign test: the chance that at least k of k + m discordant observations side with one
    of two equally good hypotheses (binomial, 1/2 each; a keypoint supporting one of two poses only, a frame pair
    lining up better under one of two camera models); 1 when there are none."""
    n = k + m
    return sum(math.comb(n, i) for i in range(k, n + 1)) / 2.0 ** n if n else 1.0
