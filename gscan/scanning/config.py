"""Typed configuration of the scan pipeline (pydantic), loaded from YAML by the CLI.

Every key has a default and a one-line description; `gscan config dump` prints them as
commented YAML. The algorithms never see this object: `gscan.scanning.pipeline` turns each section into
the parameter dataclass of the module it configures.
"""
from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from gscan.features import FeatureParams
from gscan.matching.gmatch import GMatchParams
from gscan.registration.pairwise import RegisterParams
from gscan.registration.posegraph import LoopParams, PoseGraphParams
from gscan.scanning.calibration import FocalCheckParams
from gscan.scanning.fuse import FusionParams
from gscan.scanning.keyframes import KeyframeParams
from gscan.scanning.segment import SegmentParams
from gscan.scanning.select import SelectionParams
from gscan.settings import dump_yaml, read_yaml, validate


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


# each section's defaults are its stage's parameter defaults, read from them; the named choices (typed as
# Literal for validation) are written out; tests/test_config.py checks that every key equals its stage's default
_FP, _GM, _RP, _SP, _FU, _KP, _SEL, _FC = (FeatureParams(), GMatchParams(), RegisterParams(), SegmentParams(),
                                           FusionParams(), KeyframeParams(), SelectionParams(), FocalCheckParams())


class FeaturesConfig(_Section):
    kind: Literal["sift", "rootsift", "orb"] = Field("rootsift", description="keypoint descriptor")
    max_keypoints: int = Field(_FP.max_keypoints, ge=50, le=20000, description="strongest keypoints kept per frame")


class MatchConfig(_Section):
    method: Literal["gmatch", "ratio", "mutual", "ransac", "lo-ransac", "fgr"] = Field(
        "gmatch", description="pairwise matcher: GMatch or a baseline (for comparison)")
    eps_f: float | None = Field(_GM.eps_f, gt=0,
                                description="descriptor distance threshold; null = the descriptor's default, "
                                "tighter for rootsift on a static scene's whole frames")
    eps_c: float = Field(_GM.eps_c, gt=0, lt=1, description="GMatch relative pairwise-distance tolerance")
    eta: float = Field(_GM.eta, gt=0,
                       description="GMatch absolute distance margin at 0.5 m depth (m), grows with depth^2")
    order: Literal["ratio", "distance"] = Field(
        "ratio",
        description="GMatch candidate order: Lowe ratio (distinctive first) or descriptor distance (the paper's)")
    T: int = Field(_GM.T, ge=1, le=256, description="GMatch seeds (the first T candidates in that order)")
    L: int = Field(_GM.L, ge=3, le=256, description="GMatch maximum match-list length")
    constraint: Literal["flip", "triple"] = Field("flip", description="flip-over or scalar-triple-product constraint")


class NoiseModelConfig(_Section):
    c0: float = Field(ge=0, description="per-axis variance floor (m^2)")
    c1: float = Field(ge=0, description="... growing with depth^2 (localisation: m^2 per m^2)")
    c2: float = Field(ge=0, description="... growing with depth^4 (axial sensor noise: m^2 per m^4)")

    @model_validator(mode="after")
    def _positive(self) -> NoiseModelConfig:
        if self.c0 + self.c1 + self.c2 <= 0:
            raise ValueError("a noise model needs a positive coefficient")
        return self


class NoiseConfig(_Section):
    keypoint: NoiseModelConfig = Field(description="noise of a lifted keypoint (window median of the depth)")
    depth: NoiseModelConfig = Field(description="noise of one depth pixel")


class RegisterConfig(_Section):
    min_matches: int = Field(_RP.min_matches, ge=3, description="an edge needs at least this many geometric matches")
    noise: NoiseConfig | None = Field(
        None, description="noise of lifted keypoints and of depth pixels, sigma^2(z) = c0 + c1 z^2 + c2 z^4 per axis, "
        "the unit of every residual threshold; null = estimated from the capture (a few sequential pairs)")
    max_rms: float = Field(_RP.max_rms, gt=0, description="an edge's keypoint residual RMS may be at most this many "
                           "noise sigmas")
    max_sigma_deg: float = Field(_RP.max_sigma_deg, gt=0, description="an edge's pose, as its matched points pin it, "
                                 "may be uncertain by at most this (deg, 1 sigma)")
    max_sigma_rel: float = Field(_RP.max_sigma_rel, gt=0, description="... and by at most this share of its depth "
                                 "(position, 1 sigma)")
    max_see_through: float = Field(_RP.max_see_through, ge=0, le=1, description="an edge is rejected when its pose "
                                   "lets one frame see through this share of the other frame's surfaces")
    min_colour_agreement: float = Field(_RP.min_colour_agreement, ge=0, le=1, description="an edge is rejected when "
                                        "the texture of fewer than this share of the overlap's textured tiles lines "
                                        "up under its pose (unrelated texture: about 1 in 17)")
    dense_refine: bool | None = Field(None, description="refine each edge's pose on its keypoints and both frames' "
                                      "depth together (point-to-plane); null = for a moving object only (a static "
                                      "scene's depth drifts from the truth where the camera moves fast)")
    verify: int = Field(_RP.verify, ge=0, le=256, description="other GMatch hypothesis lists whose support is checked "
                        "against the longest's (0 = the paper's pick)")
    support_eps_scale: float = Field(_RP.support_eps_scale, ge=1, le=4, description="the support of those lists counts "
                                     "pairs with descriptor distance below this x eps_f (1 = GMatch's candidates)")
    icp: bool = Field(_RP.icp, description="refine each edge by point-to-plane ICP (off: on textured planar scenes "
                      "ICP slides; GMatch + Kabsch is measured more accurate)")
    icp_max_dist: float = Field(_RP.icp_max_dist, gt=0, description="ICP correspondence distance (m)")
    icp_voxel: float = Field(_RP.icp_voxel, ge=0, description="voxel size for ICP clouds (m), 0 = no downsampling")
    min_fitness: float = Field(_RP.min_fitness, ge=0, le=1, description="an edge needs ICP fitness at least this")
    max_rmse: float = Field(_RP.max_rmse, gt=0, description="an edge needs ICP inlier RMSE at most this (m)")
    max_icp_shift_deg: float = Field(_RP.max_icp_shift_deg, gt=0, description="reject an edge whose ICP moved the "
                                     "match pose more (deg)")
    max_icp_shift_m: float = Field(_RP.max_icp_shift_m, gt=0, description="reject an edge whose ICP moved the match "
                                   "pose more (m)")


_LP, _PG = LoopParams(), PoseGraphParams()


class CameraConfig(_Section):
    check_colour_focal: bool = Field(_FC.enabled, description="a folder capture with one set of intrinsics: check "
                                     "that its depth lines up with its colour, and when the texture says the colour "
                                     "camera's focal length differs, scan with the one the data give")


class PoseGraphConfig(_Section):
    loop_candidates: int = Field(_LP.max_per_node, ge=0, description="loop-closure candidates tried per frame")
    max_view_angle_deg: float = Field(_LP.max_angle_deg, gt=0, le=180, description="loop candidates view the object "
                                      "within this angle")
    alpha: float = Field(_PG.alpha, gt=0, lt=1, description="an edge is inconsistent with the others when its "
                         "chi^2 is beyond the (1 - alpha) quantile (6 degrees of freedom)")
    bridge_min_matches: int = Field(2 * _RP.min_matches, ge=3, description="an edge that alone joins two parts of "
                                    "the graph needs this many matches; weaker, it is cut and the parts reported")


class FusionConfig(_Section):
    voxel: float | None = Field(_FU.voxel_size, gt=0,
                                description="TSDF voxel size (m); null = object extent / 150 within 2-10 mm")
    depth_max: float | None = Field(_FU.depth_max, gt=0, description="depth beyond this is ignored when fusing (m); "
                                    "null = just beyond the farthest object pixel")


class SegmentationConfig(_Section):
    depth_min: float = Field(_SP.depth_min, ge=0.05, le=20,
                             description="the object is looked for at depths from this (m) ...")
    depth_max: float | None = Field(_SP.depth_max, gt=0.05, le=20, description="... to this (m); null = 1.5 x the "
                                    "depth at the image centre, where a scan keeps the object")
    height_max: float = Field(_SP.height_max, ge=0.01, le=5,
                              description="the object stands at most this high above its support plane (m)")

    @model_validator(mode="after")
    def _range(self) -> SegmentationConfig:
        if self.depth_max is not None and self.depth_max <= self.depth_min:
            raise ValueError("depth_max must be greater than depth_min")
        return self


class KeyframeConfig(_Section):
    min_angle_deg: float = Field(_KP.min_angle_deg, ge=0,
                                 description="a new keyframe views the object at least this far from all others")
    max_views: int = Field(_KP.max_views, ge=1, description="at most this many template views")
    min_views: int = Field(_KP.min_views, ge=1, description="at least this many template views when the capture has "
                           "them (the angle shrinks for a short sweep)")
    min_object_keypoints: int = Field(_KP.min_object_keypoints, ge=0, description="keyframes are views with at least "
                                      "this many keypoints on the object (when any has)")


class SelectionConfig(_Section):
    min_motion_deg: float = Field(_SEL.min_motion_deg, ge=0, le=90,
                                  description="a frame is kept once the view moved this much since the last kept "
                                  "frame (rotation, or translation as an angle at the scene's depth); 0 keeps every "
                                  "frame")
    blur_ratio: float = Field(_SEL.blur_ratio, ge=0, lt=1,
                              description="a frame less sharp than this share of the frames before it is passed over "
                              "for a sharper one (until the view moved twice min_motion_deg); 0 never")


class ScanConfig(_Section):
    camera: CameraConfig = CameraConfig()
    selection: SelectionConfig = SelectionConfig()
    features: FeaturesConfig = FeaturesConfig()
    match: MatchConfig = MatchConfig()
    registration: RegisterConfig = RegisterConfig()
    posegraph: PoseGraphConfig = PoseGraphConfig()
    segmentation: SegmentationConfig = SegmentationConfig()
    fusion: FusionConfig = FusionConfig()
    keyframes: KeyframeConfig = KeyframeConfig()

    @model_validator(mode="after")
    def _segment_within_fusion(self) -> ScanConfig:
        if self.fusion.depth_max is not None and self.segmentation.depth_min >= self.fusion.depth_max:
            raise ValueError("segmentation.depth_min must be below fusion.depth_max (nothing could be fused)")
        return self


def load_config(path: str | Path | None) -> ScanConfig:
    """Read and validate a YAML config; None gives the defaults. Raises InputError naming the file."""
    if path is None:
        return ScanConfig()
    return validate(ScanConfig, read_yaml(path), path)


def dump_defaults() -> str:
    """The default configuration as YAML with a comment per key."""
    return dump_yaml(ScanConfig(), "gscan scan configuration (defaults). Pass an edited copy with --config.")
