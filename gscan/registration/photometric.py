"""Photometric refinement: the pose that lines up two frames' texture pixel by pixel.

Where an edge's keypoints and depth pin its pose loosely on a textured surface (a bottle's curved label: its shape
says nothing of its turn, a few dozen keypoints say it to 2 deg, and those whose support crosses the static outline
lag behind the turn), every textured pixel says more. Each source pixel inside the object, away from its outline and
from depth edges (`inner_pixels`), whose texture gradient stands above the image's noise, is lifted on its depth
smoothed over SMOOTH_PX (a pixel's own depth noise, regressed against, shrinks the turn: errors in variables,
measured 1.2 deg of a 10 deg turn on the bottle), moved by the pose and projected into the target; the difference of
the two band-passed grey levels (`colour.texture_image`) there is minimised by Gauss-Newton together with the
depth's point-to-plane terms (their information about the pose, as a quadratic prior; not the keypoints', whose
lag is what the pixels correct), Huber-weighted, its scale the residuals' median absolute deviation. Only pixels
landing on the target's interior at a depth within three noise sigmas of the target's own count (the rest are hidden
or off the object there), and the solved pose counts only where the two textures then correlate (MIN_CORRELATION).

Its uncertainty: neighbouring pixels' residuals are not independent, and shading moves with the surface, so the
pixels' information overstates how well they pin the pose. The pose's rotation sigma is the larger of the model's and
a delete-a-group jackknife's: the source pixels are cut into JACKKNIFE_BANDS bands of rows, each left out in turn and
the pose solved again; the spread of those solutions is what the data say about it, correlated errors included.
Measured on the bottle's 36 consecutive pairs (10 deg apart, object pixels): the keypoints' and depth's poses a
median 2.5 deg off the truth (claiming 1.3-2.0 deg), the pixels' a median 0.4 deg and at most 1.6 deg off (claiming
0.25-2.0 deg, 32 of 36 within 1 deg; the error at most 2.8 times the sigma claimed).
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from gscan.geometry.transforms import inv_T, make_T, rotation_angle_deg, rotvec_to_R
from gscan.registration.colour import BAND_SIGMA
from gscan.registration.dense import EDGE_REL, HUBER, DenseGeometry, pose_sigma
from gscan.registration.noise import DepthNoise

SMOOTH_PX = 2.0  # px: the Gaussian the source depth is smoothed with before its pixels are lifted
EDGE_PX = int(round(1.5 * BAND_SIGMA))  # px: pixels this close to an outline or a depth edge are left out (the
# band-pass mixes what lies across it)
GRADIENT_NOISE = float(np.sqrt(12.0) / 8.0)  # the noise of `_gradients` per axis, in units of the image's noise
GRADIENT_SNR = 4.0  # a pixel takes part when its texture's gradient is this many times that: noise alone passes
# about one pixel in 3000 (the magnitude of two axes' noise is Rayleigh), a plain table's thousands of pixels
# would otherwise pose as information
MIN_CORRELATION = 0.5  # the pixels' texture must correlate this well under the solved pose (unrelated texture: 0)
MIN_PIXELS = 400  # textured pixels the refinement needs
MAX_PIXELS = 20000  # at most this many source pixels (a regular subsample of them)
ITERATIONS = 10  # Gauss-Newton steps of the full solve (fewer when a step moves less than STOP)
JACKKNIFE_BANDS = 6  # the jackknife's groups: quantile bands of the pixels' rows (bands of rows times bands of
# columns, 3 x 3, measured no better on the bottle: the pixels' error up to 3.5 sigmas against 2.8)
JACKKNIFE_ITERATIONS = 4  # steps of each band's solve, from the full solve's pose
DISAGREEING_CHI2 = 16.27  # chi-square of 3 dof beyond which two estimates of one rotation disagree (p = 0.001)
STOP = 1e-6  # rad / m: a step this small ends the solve


@dataclass
class PhotometricFit:
    """T_tgt_src [4 x 4]; information [6 x 6] (rotation first, a small motion in the target frame) of the pose from
    the pixels and the depth, scaled so that its rotation sigma is `sigma_deg`, the larger of the model's rotation
    sigma (`model_sigma_deg`) and the jackknife's; pixels: the source pixels that took part."""

    T_tgt_src: np.ndarray
    information: np.ndarray
    model_sigma_deg: float
    jackknife_sigma_deg: float
    pixels: int

    @property
    def sigma_deg(self) -> float:
        return max(self.model_sigma_deg, self.jackknife_sigma_deg)

    def turn_deg(self, T_tgt_src: np.ndarray) -> float:
        """The rotation (deg) between this pose and T_tgt_src [4 x 4]."""
        return rotation_angle_deg(self.T_tgt_src @ inv_T(T_tgt_src))


def inner_pixels(depth: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
    """[H x W] bool: pixels of depth [H x W] (m) with depth, inside mask ([H x W] bool or None: everywhere), at least
    EDGE_PX from its outline, from lost depth and from a depth edge (neighbours differing by more than EDGE_REL)."""
    d = np.asarray(depth, dtype=np.float32)
    good = d > 0
    if mask is not None:
        good &= mask
    k = np.ones((3, 3), np.uint8)
    hi, lo = cv2.dilate(d, k), cv2.erode(np.where(good, d, np.float32(np.inf)), k)
    good &= (hi - lo) <= EDGE_REL * d
    ker = np.ones((2 * EDGE_PX + 1, 2 * EDGE_PX + 1), np.uint8)
    return cv2.erode(good.astype(np.uint8), ker, borderType=cv2.BORDER_CONSTANT, borderValue=0) > 0


def smoothed_depth(depth: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """[H x W] float32: depth [H x W] averaged over a Gaussian of SMOOTH_PX among the `valid` pixels ([H x W] bool;
    0 elsewhere)."""
    m = valid.astype(np.float32)
    num = cv2.GaussianBlur(np.asarray(depth, np.float32) * m, (0, 0), SMOOTH_PX)
    den = cv2.GaussianBlur(m, (0, 0), SMOOTH_PX)
    return np.where(valid, num / np.maximum(den, 1e-6), 0.0).astype(np.float32)


@dataclass
class _Source:
    points: np.ndarray  # [N x 3] lifted pixels (source camera, m)
    texture: np.ndarray  # [N] their band-passed grey levels
    rows: np.ndarray  # [N] their image rows


@dataclass
class _Target:
    texture: np.ndarray  # [H x W]
    gx: np.ndarray  # [H x W] d texture / du
    gy: np.ndarray  # [H x W] d texture / dv
    depth: np.ndarray  # [H x W] m, 0 off the interior
    K: tuple[float, float, float, float]


def _gradients(texture: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(d/du, d/dv) [H x W] of texture [H x W] (Sobel, grey levels per pixel)."""
    return (cv2.Sobel(texture, cv2.CV_32F, 1, 0, ksize=3) / 8.0, cv2.Sobel(texture, cv2.CV_32F, 0, 1, ksize=3) / 8.0)


def _source(view: DenseGeometry) -> _Source | None:
    """view's pixels that take part (module docstring), lifted; None when fewer than MIN_PIXELS."""
    assert view.image_depth is not None and view.texture is not None
    valid = inner_pixels(view.image_depth, view.mask)
    gx, gy = _gradients(view.texture)
    v, u = np.nonzero(valid & (np.hypot(gx, gy) > GRADIENT_SNR * GRADIENT_NOISE * view.texture_noise))
    if len(v) < MIN_PIXELS:
        return None
    step = int(np.ceil(len(v) / MAX_PIXELS))
    v, u = v[::step], u[::step]
    fx, fy, cx, cy = view.full_intrinsics
    z = smoothed_depth(view.image_depth, valid)[v, u].astype(np.float64)
    pts = np.stack([(u - cx) / fx * z, (v - cy) / fy * z, z], axis=1)
    return _Source(pts, view.texture[v, u].astype(np.float64), v)


def _target(view: DenseGeometry) -> _Target:
    """view's texture, its gradients and its depth on its interior."""
    assert view.image_depth is not None and view.texture is not None
    tex = view.texture
    depth = np.where(inner_pixels(view.image_depth, view.mask), view.image_depth, 0.0).astype(np.float32)
    return _Target(tex, *_gradients(tex), depth, view.full_intrinsics)


def _log(T: np.ndarray) -> np.ndarray:
    """[6] (rotation vector, translation) of a rigid T [4 x 4] near the identity."""
    return np.concatenate([Rotation.from_matrix(T[:3, :3]).as_rotvec(), T[:3, 3]])


def _equations(src: _Source, keep: np.ndarray, tgt: _Target, T: np.ndarray, noise: DepthNoise
               ) -> tuple[np.ndarray, np.ndarray, float, int]:
    """(J^T W J [6 x 6], J^T W r [6], correlation, pixels used) of the photometric residuals of the source pixels
    where keep [N] holds, at T (a small motion in the target frame), each divided by the residuals' scale^2; the
    correlation of the source's texture with the target's where the pixels land."""
    fx, fy, cx, cy = tgt.K
    H, W = tgt.depth.shape
    q = src.points[keep] @ T[:3, :3].T + T[:3, 3]
    z = q[:, 2]
    ok = z > 0
    up = fx * q[:, 0] / np.where(ok, z, 1.0) + cx
    vp = fy * q[:, 1] / np.where(ok, z, 1.0) + cy
    ok &= (up >= 1) & (up < W - 2) & (vp >= 1) & (vp < H - 2)
    ui = np.clip(np.round(up), 0, W - 1).astype(np.int64)
    vi = np.clip(np.round(vp), 0, H - 1).astype(np.int64)
    dt = tgt.depth[vi, ui].astype(np.float64)
    ok &= (dt > 0) & (np.abs(dt - z) <= 3.0 * noise.pair_sigma(z, dt))
    if ok.sum() < MIN_PIXELS // 2:
        return np.zeros((6, 6)), np.zeros(6), 0.0, int(ok.sum())
    mx, my = up[ok].astype(np.float32)[None], vp[ok].astype(np.float32)[None]
    It = cv2.remap(tgt.texture, mx, my, cv2.INTER_LINEAR)[0].astype(np.float64)
    Gx = cv2.remap(tgt.gx, mx, my, cv2.INTER_LINEAR)[0].astype(np.float64)
    Gy = cv2.remap(tgt.gy, mx, my, cv2.INTER_LINEAR)[0].astype(np.float64)
    Is = src.texture[keep][ok]
    r = It - Is
    corr = float(np.corrcoef(Is, It)[0, 1]) if np.std(Is) > 0 and np.std(It) > 0 else 0.0
    qq = q[ok]
    X, Y, Z = qq[:, 0], qq[:, 1], qq[:, 2]
    g = np.stack([Gx * fx / Z, Gy * fy / Z, -(Gx * fx * X + Gy * fy * Y) / (Z * Z)], axis=1)  # d texture / d q
    J = np.concatenate([np.cross(qq, g), g], axis=1)  # q moves by omega x q + tau
    scale = max(1.4826 * float(np.median(np.abs(r - np.median(r)))), 1e-6)
    a = np.abs(r) / scale
    w = np.where(a <= HUBER, 1.0, HUBER / np.maximum(a, 1e-12)) / scale ** 2
    return (J * w[:, None]).T @ J, (J * w[:, None]).T @ r, corr, int(ok.sum())


def _solve(src: _Source, keep: np.ndarray, tgt: _Target, T0: np.ndarray, prior: np.ndarray, T_start: np.ndarray,
           iterations: int, noise: DepthNoise) -> tuple[np.ndarray, np.ndarray, float, int]:
    """(T [4 x 4], information [6 x 6] at T, the texture's correlation there, pixels used): Gauss-Newton on the
    pixels where keep holds and the prior information [6 x 6] about T0 [4 x 4], from T_start."""
    T = T_start.copy()
    Hp, n = np.zeros((6, 6)), 0
    for _ in range(iterations):
        Hp, gp, _, n = _equations(src, keep, tgt, T, noise)
        H = Hp + prior
        g = gp + prior @ _log(T @ inv_T(T0))
        try:
            dx = -np.linalg.solve(H, g)
        except np.linalg.LinAlgError:
            break
        T = make_T(rotvec_to_R(dx[:3]), dx[3:]) @ T
        if np.abs(dx).max() < STOP:
            break
    Hp, _, corr, n = _equations(src, keep, tgt, T, noise)
    return T, Hp + prior, corr, n


def refine_photometric(src: DenseGeometry, tgt: DenseGeometry, T_tgt_src: np.ndarray, information: np.ndarray,
                       noise: DepthNoise) -> PhotometricFit | None:
    """The pose of src in tgt refined on both frames' texture (module docstring), from T_tgt_src [4 x 4] and the
    keypoints' and depth's information [6 x 6] about it (rotation first, a small motion in tgt's frame;
    `dense.pose_information`, the depth's alone); noise: one depth pixel's. None when either frame lacks its
    image or full depth, fewer than MIN_PIXELS textured pixels of src land on tgt's interior, or the two textures
    correlate less than MIN_CORRELATION under the solved pose."""
    if any(v.texture is None or v.image_depth is None for v in (src, tgt)):
        return None
    s = _source(src)
    if s is None:
        return None
    t = _target(tgt)
    T0 = np.asarray(T_tgt_src, dtype=np.float64)
    prior = np.asarray(information, dtype=np.float64)
    everything = np.ones(len(s.points), bool)
    T, info, corr, n = _solve(s, everything, t, T0, prior, T0, ITERATIONS, noise)
    if n < MIN_PIXELS or corr < MIN_CORRELATION:
        return None
    band = np.searchsorted(np.quantile(s.rows, np.linspace(0.0, 1.0, JACKKNIFE_BANDS + 1)[1:-1]), s.rows,
                           side="right")
    turns = []
    for k in range(JACKKNIFE_BANDS):
        Tk = _solve(s, band != k, t, T0, prior, T, JACKKNIFE_ITERATIONS, noise)[0]
        turns.append(_log(Tk @ inv_T(T))[:3])
    d = np.asarray(turns) - np.mean(turns, axis=0)
    C = (JACKKNIFE_BANDS - 1) / JACKKNIFE_BANDS * d.T @ d
    jack = float(np.degrees(np.sqrt(max(np.linalg.eigvalsh(C).max(), 0.0))))
    model = pose_sigma(info, np.zeros((0, 3)))[0]
    sigma = max(model, jack)
    scaled = info * (model / sigma) ** 2 if sigma > 0 and np.isfinite(sigma) else info
    return PhotometricFit(T, scaled, model, jack, n)


def rotation_disagreement(T_a: np.ndarray, information_a: np.ndarray, T_b: np.ndarray, information_b: np.ndarray
                          ) -> float:
    """Chi-square (3 dof) of the rotation between two estimates T_a, T_b [4 x 4] of one pose, each with its
    information [6 x 6] (rotation first, a small motion in the target frame): the keypoints' and depth's pose
    against the pixels'. Two estimates further apart than both allow cannot both be right, and one edge cannot tell
    which is wrong: the pixels' may sit in a false minimum of the texture (measured, pixels turning a pose
    sliding 2 cm along a plain table by 0.67 deg against its claimed 0.14 deg lined its texture up in 9 of 15 tiles
    instead of 3 of 14), the keypoints' may lag (the bottle: keypoints 6.0 deg off claiming 1.7 deg, which the
    pixels turned 7.0 deg)."""
    d = _log(np.asarray(T_b, np.float64) @ inv_T(np.asarray(T_a, np.float64)))[:3]
    try:
        C = np.linalg.inv(information_a)[:3, :3] + np.linalg.inv(information_b)[:3, :3]
        return float(d @ np.linalg.solve(C, d))
    except np.linalg.LinAlgError:
        return float("inf")
