"""Keypoint descriptors (SIFT, RootSIFT, ORB) lifted to 3D with the frame's depth.

Backends are OpenCV's `SIFT_create` / `ORB_create`. Every returned keypoint has a valid,
discontinuity-free depth (see `gscan.io.camera.lift_keypoints`) and a 3D point in the camera
frame. Output order is by decreasing detector response; ties are broken by (y, x, angle),
so the result does not depend on the order in which OpenCV's worker threads emit
keypoints: the same image always gives identical arrays, whatever OpenCV's thread count (the
tests compare extraction under `cv2.setNumThreads(1)` with the default), so this module never
changes OpenCV's global thread count.

Descriptor scales (they matter to GMatch's feature threshold `eps_f`):
- "sift": OpenCV's raw float32 vectors, 128-d, integer-valued in [0, 255], L2 norm ~512
  (OpenCV normalises to 512 before rounding); distances are Euclidean in those units.
- "rootsift": the SIFT vector L1-normalised then square-rooted (Arandjelovic & Zisserman
  2012), unit L2 norm, so L2 distances lie in [0, sqrt(2)] (Hellinger distance of SIFT).
- "orb": uint8 [N x 32] (256-bit) binary strings; distance = Hamming bit count in [0, 256].
- "rootsift+fpfh": float32 [N x 161], RootSIFT image keypoints and scaled RootFPFH depth keypoints in one set
  (`gscan.features.depth.joint_features`); L2 distances, RootSIFT's scale; two kinds are never close.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Annotated, Literal

import cv2
import numpy as np
from pydantic import Field

from gscan.geometry.transforms import transform_points
from gscan.io.camera import Intrinsics, RGBDFrame, lift_keypoints
from gscan.settings import SETTINGS

log = logging.getLogger(__name__)

KINDS = ("sift", "rootsift", "orb")  # the image descriptors (FeatureParams.kind)
# RootSIFT image keypoints and RootFPFH depth keypoints in one set (`gscan.features.depth.joint_features`)
JOINT = "rootsift+fpfh"
_DIMS = {"sift": 128, "rootsift": 128, "orb": 32, JOINT: 128 + 33}
_DTYPES = {"sift": np.float32, "rootsift": np.float32, "orb": np.uint8, JOINT: np.float32}
DESCRIPTOR_KINDS = {k: (_DIMS[k], _DTYPES[k]) for k in _DIMS}  # kind -> (descriptor length, dtype)


def depth_rows(descriptors: np.ndarray, kind: str) -> np.ndarray:
    """[N] bool: which keypoints of descriptors [N x D] of `kind` were found in the depth's geometry (rootsift+fpfh:
    a non-zero FPFH part; none of any other kind)."""
    if kind != JOINT:
        return np.zeros(len(descriptors), bool)
    return np.abs(descriptors[:, 128:]).sum(axis=1) > 0


@dataclass
class Features:
    """Keypoints of one frame (or template view) with descriptors and 3D points.

    pixels: [N x 2] float32 (u, v); points: [N x 3] float32 metres, in the camera frame as extracted (a
    template database stores a registered view's points in the object frame: `transformed`);
    descriptors: [N x 128] float32 (sift, rootsift), [N x 32] uint8 (orb) or [N x 161] float32 (rootsift+fpfh:
    an image keypoint's RootSIFT then 33 zeros, a depth keypoint's 128 zeros then its scaled RootFPFH);
    kind: "sift" | "rootsift" | "orb" | "rootsift+fpfh"; scales: [N] float32 keypoint size (pixels; a depth
    keypoint's: its location sigma in metres, `location_sigma`), or None (not stored).
    """

    pixels: np.ndarray
    points: np.ndarray
    descriptors: np.ndarray
    kind: str
    scales: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.kind not in DESCRIPTOR_KINDS:
            raise ValueError(f"unknown descriptor kind {self.kind!r}; expected one of {tuple(DESCRIPTOR_KINDS)}")
        n = len(self.pixels)
        if (self.pixels.shape != (n, 2) or self.points.shape != (n, 3)
                or (self.scales is not None and self.scales.shape != (n,))):
            raise ValueError(f"inconsistent feature shapes: pixels {self.pixels.shape}, points {self.points.shape}, "
                             f"scales {None if self.scales is None else self.scales.shape}")
        if self.descriptors.shape != (n, _DIMS[self.kind]):
            raise ValueError(f"{self.kind} descriptors must be [{n} x {_DIMS[self.kind]}], "
                             f"got {self.descriptors.shape}")

    def __len__(self) -> int:
        return len(self.pixels)

    @property
    def from_depth(self) -> np.ndarray:
        """[N] bool: the keypoints found in the depth's geometry (rootsift+fpfh: a non-zero FPFH part)."""
        return depth_rows(self.descriptors, self.kind)

    @property
    def location_sigma(self) -> np.ndarray:
        """[N] float64 per-axis standard deviation (m) of each keypoint's position on the surface beyond the
        depth noise model's (`gscan.registration.noise`): a depth keypoint's (`gscan.features.depth`, stored
        in `scales`), 0 for an image keypoint (the model holds its localisation)."""
        out = np.zeros(len(self))
        if self.kind == JOINT and self.scales is not None:
            d = self.from_depth
            out[d] = self.scales[d]
        return out

    @property
    def metric(self) -> str:
        """Descriptor distance: "l2" (sift, rootsift) or "hamming" (orb)."""
        return metric_of(self.kind)

    def subset(self, idx: np.ndarray) -> Features:
        """Features at `idx` ([K] int indices or [N] bool mask), copied."""
        idx = np.asarray(idx)
        if idx.dtype != bool:
            idx = idx.astype(np.intp).reshape(-1)
        return Features(pixels=self.pixels[idx].copy(), points=self.points[idx].copy(),
                        descriptors=self.descriptors[idx].copy(), kind=self.kind,
                        scales=None if self.scales is None else self.scales[idx].copy())

    def transformed(self, T_b_a: np.ndarray) -> Features:
        """The same keypoints with their points mapped from frame a into frame b (float32); the other arrays
        are shared, not copied."""
        return Features(pixels=self.pixels, points=transform_points(T_b_a, self.points).astype(np.float32),
                        descriptors=self.descriptors, kind=self.kind, scales=self.scales)


@dataclass(frozen=True)
class FeatureParams:
    """Keypoints and descriptors of a frame, lifted to 3D by the depth around them."""

    __pydantic_config__ = SETTINGS

    # a str (a template's descriptor kind is read as one), its choices a pattern
    kind: Annotated[str, Field(pattern="^(sift|rootsift|orb)$", description="keypoint descriptor: sift, rootsift "
                               "or orb")] = "rootsift"
    max_keypoints: Annotated[int, Field(ge=50, le=20000, description="strongest keypoints kept per frame (with "
                                        "valid depth)")] = 2000
    lift_window: Annotated[int, Field(ge=0, le=16, description="a keypoint's depth is the median over a (2w+1)^2 "
                                      "window around it")] = 2
    lift_max_rel_spread: Annotated[float, Field(gt=0, description="windows whose 10-90% depth spread exceeds this "
                                                "share of their median are rejected")] = 0.03
    lift_min_valid_frac: Annotated[float, Field(ge=0, le=1, description="windows with fewer valid depth pixels than "
                                                "this share are rejected")] = 0.5
    sift_contrast_threshold: Annotated[float, Field(gt=0, description="SIFT contrast threshold (OpenCV's default); "
                                                    "lower finds more keypoints on weak texture")] = 0.04
    sift_edge_threshold: Annotated[float, Field(gt=0, description="SIFT edge threshold (OpenCV's default)")] = 10.0
    sift_n_octave_layers: Annotated[int, Field(ge=1, description="SIFT layers per octave (OpenCV's default)")] = 3
    sift_sigma: Annotated[float, Field(gt=0, description="SIFT base Gaussian sigma (OpenCV's default)")] = 1.6
    orb_detect_factor: Annotated[float, Field(ge=1, description="ORB detects max_keypoints x this before the depth "
                                              "filter")] = 2.0
    orb_scale_factor: Annotated[float, Field(gt=1, description="ORB pyramid scale factor (OpenCV's default)")] = 1.2
    orb_n_levels: Annotated[int, Field(ge=1, description="ORB pyramid levels (OpenCV's default)")] = 8
    orb_fast_threshold: Annotated[int, Field(ge=1, description="ORB FAST threshold (OpenCV's default)")] = 20
    keypoints: Annotated[Literal["auto", "sift", "depth", "both"], Field(
        description="which keypoints a scan registers with: the image's (sift: of `kind`), the depth's shape "
        "(depth: ISS + FPFH on the object's points), both in one set, or auto: both when the capture's frames hold "
        "fewer than auto_min_keypoints image keypoints (median of up to 8 frames spread over it: a plain object), "
        "else the image's; depth and both need kind rootsift (auto keeps the image's with another kind)")] = "auto"
    auto_min_keypoints: Annotated[int, Field(ge=0, description="auto: below this median of image keypoints per "
                                             "frame (the object's, with a mask) the depth keypoints join; a frame "
                                             "with fewer is plain, and its texture (shading) cannot refute a loop "
                                             "closure's half turn (method.md, plain objects)")] = 60
    depth_max_keypoints: Annotated[int, Field(ge=10, le=5000, description="most salient depth keypoints kept per "
                                              "frame")] = 300
    depth_voxel_rel: Annotated[float, Field(gt=0, le=0.2, description="depth keypoints: the points' voxel, as a "
                                            "share of the object's size ...")] = 1 / 80
    depth_noise_voxel: Annotated[float, Field(ge=0, description="... and at least this many depth noise sigmas")] = 3.0
    depth_salient_rel: Annotated[float, Field(gt=0, le=1, description="ISS salient radius, as a share of the "
                                              "object's size")] = 0.08
    depth_nonmax_rel: Annotated[float, Field(gt=0, le=1, description="ISS non-maximum radius, as a share of the "
                                             "object's size")] = 0.04
    depth_fpfh_rel: Annotated[float, Field(gt=0, le=1, description="FPFH radius, as a share of the object's "
                                           "size")] = 0.25

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"unknown descriptor kind {self.kind!r}; expected one of {KINDS}")
        if self.keypoints in ("depth", "both") and self.kind != "rootsift":
            raise ValueError(f"keypoints {self.keypoints!r} joins depth keypoints to rootsift ones, not {self.kind}; "
                             "set keypoints: sift or kind: rootsift")
        if self.max_keypoints <= 0 or self.lift_window < 0:
            raise ValueError(f"max_keypoints must be > 0 and lift_window >= 0 "
                             f"(got {self.max_keypoints}, {self.lift_window})")


# keypoints on an object for pose estimation (template object keypoints and query frames): SIFT
# contrast threshold halved from OpenCV's 0.04, which finds more keypoints on weakly textured
# packaging (see BENCHMARKS.md, section Parameter studies)
OBJECT_FEATURES = FeatureParams(sift_contrast_threshold=0.02)


def metric_of(kind: str) -> str:
    """"l2" for sift/rootsift/rootsift+fpfh, "hamming" for orb."""
    if kind not in DESCRIPTOR_KINDS:
        raise ValueError(f"unknown descriptor kind {kind!r}; expected one of {tuple(DESCRIPTOR_KINDS)}")
    return "hamming" if kind == "orb" else "l2"


def empty_features(kind: str) -> Features:
    """A Features with N = 0 of the given kind (descriptor width and dtype set)."""
    if kind not in DESCRIPTOR_KINDS:
        raise ValueError(f"unknown descriptor kind {kind!r}; expected one of {tuple(DESCRIPTOR_KINDS)}")
    return Features(pixels=np.zeros((0, 2), np.float32), points=np.zeros((0, 3), np.float32),
                    descriptors=np.zeros((0, _DIMS[kind]), _DTYPES[kind]), kind=kind, scales=np.zeros(0, np.float32))


def _to_gray(color: np.ndarray) -> np.ndarray:
    """[H x W x 3] uint8 RGB (or [H x W] gray) -> [H x W] uint8 gray."""
    if color.ndim == 2:
        gray = color
    elif color.ndim == 3 and color.shape[2] == 3:
        gray = cv2.cvtColor(np.ascontiguousarray(color), cv2.COLOR_RGB2GRAY)
    else:
        raise ValueError(f"colour image must be [H x W x 3] or [H x W], got {color.shape}")
    if gray.dtype != np.uint8:
        raise ValueError(f"colour image must be uint8, got {gray.dtype}")
    return np.ascontiguousarray(gray)


# SIFT on a whole frame describes only its strongest DESCRIBE_MARGIN * max_keypoints / (fraction of pixels with
# depth) keypoints (OpenCV's `nfeatures`): the cap keeps fewer, and the rest would be described for nothing
DESCRIBE_MARGIN = 1.5


@dataclass
class Detection:
    """A frame's keypoints as OpenCV detected and described them, before any depth test: pixels [N x 2] float64,
    OpenCV's descriptors [N x D], response and angle [N] float64, size [N] float32; n_best: the strongest-n cut
    they were detected with (0: none); detector: the detector's settings (`_detector`). `extract_features` can
    start from one (`detect`)."""

    pixels: np.ndarray
    descriptors: np.ndarray | None
    response: np.ndarray
    angle: np.ndarray
    size: np.ndarray
    n_best: int
    detector: tuple

    def __len__(self) -> int:
        return len(self.pixels)


def _detector(params: FeatureParams) -> tuple:
    """The settings a detection depends on besides the image and the strongest-n cut (SIFT and RootSIFT share
    OpenCV's SIFT; ORB's keypoint count follows max_keypoints)."""
    if params.kind == "orb":
        return ("orb", params.max_keypoints, params.orb_detect_factor, params.orb_scale_factor, params.orb_n_levels,
                params.orb_fast_threshold)
    return ("sift", params.sift_n_octave_layers, params.sift_contrast_threshold, params.sift_edge_threshold,
            params.sift_sigma)


def _detect(gray: np.ndarray, mask_u8: np.ndarray | None, params: FeatureParams, n_best: int = 0) -> Detection:
    """OpenCV's keypoints and descriptors; n_best > 0 (SIFT): only the n_best strongest responses (and those
    equal to the n_best-th) are described and returned."""
    det: cv2.Feature2D
    if params.kind == "orb":
        n = max(params.max_keypoints, int(round(params.max_keypoints * params.orb_detect_factor)))
        det = cv2.ORB.create(nfeatures=n, scaleFactor=params.orb_scale_factor, nlevels=params.orb_n_levels,
                             fastThreshold=params.orb_fast_threshold)
    else:
        det = cv2.SIFT.create(nfeatures=n_best, nOctaveLayers=params.sift_n_octave_layers,
                              contrastThreshold=params.sift_contrast_threshold,
                              edgeThreshold=params.sift_edge_threshold, sigma=params.sift_sigma)
    kps, desc = det.detectAndCompute(gray, mask_u8)
    return Detection(np.array([k.pt for k in kps], dtype=np.float64).reshape(-1, 2), desc,
                     np.array([k.response for k in kps], dtype=np.float64),
                     np.array([k.angle for k in kps], dtype=np.float64),
                     np.array([k.size for k in kps], dtype=np.float32), n_best, _detector(params))


def detect(frame: RGBDFrame, params: FeatureParams = FeatureParams()) -> Detection:
    """The whole-frame detection `extract_features(frame, params)` starts from. Another extraction of the same
    colour image (other depth, intrinsics or `max_keypoints`, SIFT kinds) can start from it too, with the result
    it would get alone: of a SIFT detection only the strongest-n cut depends on those, and `extract_features`
    detects again when the cut left too few keypoints. ORB's detection depends on `max_keypoints`."""
    return _detect(_to_gray(frame.color), None, params, _n_best(frame.depth, None, params))


def _n_best(depth: np.ndarray, mask: np.ndarray | None, params: FeatureParams) -> int:
    """How many of the strongest SIFT keypoints to describe (0: all). A mask is applied by OpenCV after its
    strongest-n cut, so a masked detection describes every keypoint in the mask (0)."""
    if params.kind == "orb" or mask is not None:
        return 0
    frac = np.count_nonzero(depth > 0) / max(depth.size, 1)
    n = DESCRIBE_MARGIN * params.max_keypoints / max(frac, 1e-3)
    return int(np.ceil(n)) if n < 1e7 else 0


def _rootsift(desc: np.ndarray) -> np.ndarray:
    """[N x 128] SIFT -> RootSIFT: L1-normalise, square root, then unit L2 (guards rounding)."""
    d = np.maximum(desc.astype(np.float64), 0.0)
    d = np.sqrt(d / np.maximum(d.sum(axis=1, keepdims=True), 1e-12))
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
    return d.astype(np.float32)


def extract_features(frame: RGBDFrame, params: FeatureParams = FeatureParams(),
                     mask: np.ndarray | None = None, detection: Detection | None = None) -> Features:
    """Detect, describe and lift keypoints of `frame`.

    Keypoints without a robust depth (invalid or discontinuous window, see `lift_keypoints`) are dropped; of
    the rest the `params.max_keypoints` strongest are kept, ordered by decreasing response with ties broken by
    (y, x, angle, size). Deterministic. SIFT describes only the keypoints that can be kept: those in the mask,
    and on a whole frame the strongest (`DESCRIBE_MARGIN`); the result is the one describing every keypoint
    gives.

    Args:
        frame: the RGB-D frame.
        params: detector, descriptor kind and depth lifting.
        mask: optional [H x W] bool; detection is restricted to True pixels (a keypoint is kept only if its
            rounded pixel lies in the mask). `frame.mask` is NOT applied implicitly: pass `mask=frame.mask`.
        detection: the frame's colour image already detected (`detect`), used without a mask.

    Returns:
        Features: pixels [N x 2], camera-frame points [N x 3], descriptors [N x D], kind, scales [N].
    """
    gray = _to_gray(frame.color)
    H, W = gray.shape
    mask_u8 = None
    if mask is not None:
        mask = np.asarray(mask)
        if mask.shape != (H, W):
            raise ValueError(f"mask is {mask.shape[1] if mask.ndim > 1 else '?'}x{mask.shape[0]} "
                             f"but the frame {frame.name!r} is {W}x{H}")
        mask = mask.astype(bool)
        if not mask.any():
            return empty_features(params.kind)
        mask_u8 = mask.astype(np.uint8) * 255
    if detection is not None and detection.detector != _detector(params):
        raise ValueError(f"frame {frame.name!r}: a detection of other detector settings ({detection.detector}) "
                         f"than {_detector(params)}")
    n_best = _n_best(frame.depth, mask, params)
    det = detection if mask is None else None
    while True:
        if det is None:
            det = _detect(gray, mask_u8, params, n_best)
        if len(det) == 0 or det.descriptors is None:
            log.debug("frame %s: no keypoints", frame.name)
            return empty_features(params.kind)
        px = det.pixels
        keep = np.ones(len(det), dtype=bool)
        if mask is not None:
            u = np.clip(np.rint(px[:, 0]).astype(int), 0, W - 1)
            v = np.clip(np.rint(px[:, 1]).astype(int), 0, H - 1)
            keep &= mask[v, u]
        pts, valid = lift_keypoints(px, frame.depth, frame.intrinsics, window=params.lift_window,
                                    max_rel_spread=params.lift_max_rel_spread,
                                    min_valid_frac=params.lift_min_valid_frac)
        keep &= valid
        # the strongest n_best hold the max_keypoints strongest with depth, unless OpenCV cut keypoints (it
        # returns at least n_best then) and fewer than max_keypoints of those have depth: describe them all
        if det.n_best == 0 or len(det) < det.n_best or np.count_nonzero(keep) >= params.max_keypoints:
            break
        log.debug("frame %s: %d of the %d strongest keypoints have depth; describing all", frame.name,
                  int(keep.sum()), len(det))
        det, n_best = None, 0
    resp, angle, size = det.response, det.angle, det.size
    idx = np.flatnonzero(keep)
    # strongest first; ties by (y, x, angle, size); lexsort's primary key is the last one
    order = np.lexsort((size[idx], angle[idx], px[idx, 0], px[idx, 1], -resp[idx]))
    idx = idx[order][: params.max_keypoints]
    desc = det.descriptors[idx]
    if params.kind == "rootsift":
        desc = _rootsift(desc)
    elif params.kind == "sift":
        desc = desc.astype(np.float32)
    else:
        desc = np.ascontiguousarray(desc, dtype=np.uint8)
    log.debug("frame %s: %d %s keypoints detected, %d with depth, %d kept", frame.name, len(det), params.kind,
              int(keep.sum()), len(idx))
    return Features(pixels=px[idx].astype(np.float32), points=pts[idx].astype(np.float32),
                    descriptors=np.ascontiguousarray(desc), kind=params.kind, scales=size[idx])


_POPCOUNT8 = np.array([bin(i).count("1") for i in range(256)], dtype=np.uint8)


def _hamming(d_s: np.ndarray, d_t: np.ndarray, chunk_bytes: int) -> np.ndarray:
    """Bit-count distances of [Ns x B] and [Nt x B] uint8 codes -> [Ns x Nt] float32.

    Loops over the code's words (64-bit when B % 8 == 0), XOR-ing a [rows x Nt] block
    at a time and accumulating its popcount, so intermediates stay near `chunk_bytes`.
    """
    ns, nt = len(d_s), len(d_t)
    out = np.empty((ns, nt), dtype=np.float32)
    a, b = np.ascontiguousarray(d_s), np.ascontiguousarray(d_t)
    if a.shape[1] % 8 == 0:  # 64-bit words: 8x fewer element operations
        a, b = a.view(np.uint64), b.view(np.uint64)
    acc_t = np.uint16 if d_s.shape[1] * 8 < 65536 else np.uint32
    rows = max(1, chunk_bytes // max(1, nt * a.itemsize))
    bt = np.ascontiguousarray(b.T)  # [words x Nt]
    for i in range(0, ns, rows):
        blk = a[i:i + rows]
        acc = np.zeros((len(blk), nt), dtype=acc_t)
        for w in range(a.shape[1]):
            x = blk[:, w, None] ^ bt[w][None, :]
            if hasattr(np, "bitwise_count"):  # numpy >= 2.0
                acc += np.bitwise_count(x)
            else:
                acc += _POPCOUNT8[x.view(np.uint8)].reshape(len(blk), nt, a.itemsize).sum(axis=2, dtype=acc_t)
        out[i:i + rows] = acc
    return out


def descriptor_distances(d_s: np.ndarray, d_t: np.ndarray, kind: str,
                         chunk_bytes: int = 32 << 20) -> np.ndarray:
    """All pairwise descriptor distances, [Ns x D] x [Nt x D] -> [Ns x Nt] float32.

    sift / rootsift: exact Euclidean distance by GEMM in float32, |a|^2 + |b|^2 - 2 a.b
    clamped at 0 before the square root (float32 cancellation: near zero distance the result
    can be off by up to ~1e-3 * |a|, i.e. ~0.5 for SIFT's norm-512 vectors, ~1e-3 for RootSIFT). SIFT vectors
    are not normalised here. orb: Hamming bit count of uint8 [N x 32] codes, computed in
    chunks of about `chunk_bytes` of XOR intermediates.
    """
    metric = metric_of(kind)
    d_s, d_t = np.asarray(d_s), np.asarray(d_t)
    if d_s.ndim != 2 or d_t.ndim != 2 or d_s.shape[1] != d_t.shape[1]:
        raise ValueError(f"descriptor arrays must be [Ns x D] and [Nt x D], got {d_s.shape} and {d_t.shape}")
    ns, nt = len(d_s), len(d_t)
    if ns == 0 or nt == 0:
        return np.zeros((ns, nt), dtype=np.float32)
    if metric == "hamming":
        if d_s.dtype != np.uint8 or d_t.dtype != np.uint8:
            raise ValueError(f"orb descriptors must be uint8, got {d_s.dtype} and {d_t.dtype}")
        return _hamming(d_s, d_t, chunk_bytes)
    a = np.ascontiguousarray(d_s, dtype=np.float32)
    b = np.ascontiguousarray(d_t, dtype=np.float32)
    d2 = a @ b.T
    d2 *= -2.0
    d2 += np.einsum("ij,ij->i", a, a)[:, None]
    d2 += np.einsum("ij,ij->i", b, b)[None, :]
    np.maximum(d2, 0.0, out=d2)
    return np.sqrt(d2, out=d2)


def extract_features_in_mask(frame: RGBDFrame, mask: np.ndarray, params: FeatureParams = FeatureParams(),
                             margin: int = 16, within: tuple[int, int, int, int] | None = None) -> Features:
    """Features of `frame` inside `mask` [H x W] bool, detected on the mask's bounding box (+ `margin`
    px) only, which is faster than a masked full-frame detection; pixels in full-frame coordinates,
    points in the camera frame. within: a box (x0, y0, x1, y1) outside which the mask's pixels are left out
    (the same as clearing them, without a full-frame copy). An empty mask gives no features."""
    H, W = mask.shape
    bx0, by0, bx1, by1 = (0, 0, W, H) if within is None else within
    ys, xs = np.nonzero(mask[by0:by1, bx0:bx1])
    if len(ys) == 0:
        return empty_features(params.kind)
    x0, x1 = max(0, bx0 + xs.min() - margin), min(W, bx0 + xs.max() + margin + 1)
    y0, y1 = max(0, by0 + ys.min() - margin), min(H, by0 + ys.max() + margin + 1)
    if within is None:
        crop_mask = mask[y0:y1, x0:x1]
    else:  # the margin may reach past the box: only the box's part of the mask
        crop_mask = np.zeros((y1 - y0, x1 - x0), bool)
        iy0, iy1, ix0, ix1 = max(by0, y0), min(by1, y1), max(bx0, x0), min(bx1, x1)
        crop_mask[iy0 - y0:iy1 - y0, ix0 - x0:ix1 - x0] = mask[iy0:iy1, ix0:ix1]
    intr = frame.intrinsics
    sub = RGBDFrame(frame.name, np.ascontiguousarray(frame.color[y0:y1, x0:x1]),
                    np.ascontiguousarray(frame.depth[y0:y1, x0:x1]),
                    Intrinsics(intr.fx, intr.fy, intr.cx - x0, intr.cy - y0, x1 - x0, y1 - y0))
    f = extract_features(sub, params, mask=crop_mask)
    f.pixels = f.pixels + np.array([x0, y0], np.float32)
    return f
