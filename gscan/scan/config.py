"""Typed configuration of the scan pipeline (pydantic), loaded from YAML by the CLI.

Every key has a default and a one-line description; `gscan config dump` prints them as
commented YAML. The algorithms never see this object: `gscan.scan.pipeline` turns each section into
the parameter dataclass of the module it configures.
"""
from __future__ import annotations

from pathlib import Path
from typing import Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from gscan.errors import InputError, not_a_file


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class FeaturesConfig(_Section):
    kind: Literal["sift", "rootsift", "orb"] = Field("rootsift", description="keypoint descriptor")
    max_keypoints: int = Field(2000, ge=50, le=20000, description="strongest keypoints kept per frame")


class MatchConfig(_Section):
    method: Literal["gmatch", "ratio", "mutual", "ransac", "lo-ransac", "fgr"] = Field(
        "gmatch", description="pairwise matcher: GMatch or a baseline (for comparison)")
    eps_f: float | None = Field(None, gt=0, description="descriptor distance threshold; null = the descriptor's default")
    eps_c: float = Field(0.08, gt=0, lt=1, description="GMatch relative pairwise-distance tolerance")
    eta: float = Field(0.01, gt=0, description="GMatch absolute distance margin at 0.5 m depth (m), grows with depth^2")
    order: Literal["ratio", "distance"] = Field(
        "ratio", description="GMatch candidate order: Lowe ratio (distinctive first) or descriptor distance (the paper's)")
    T: int = Field(24, ge=1, le=256, description="GMatch seeds (the first T candidates in that order)")
    L: int = Field(24, ge=3, le=256, description="GMatch maximum match-list length")
    constraint: Literal["flip", "triple"] = Field("flip", description="flip-over or scalar-triple-product constraint")


class RegisterConfig(_Section):
    min_matches: int = Field(8, ge=3, description="an edge needs at least this many geometric matches")
    verify: int = Field(16, ge=0, le=256, description="other GMatch hypothesis lists whose support is checked against the longest's (0 = the paper's pick)")
    support_eps_scale: float = Field(1.5, ge=1, le=4, description="the support of those lists counts pairs with descriptor distance below this x eps_f (1 = GMatch's candidates)")
    icp: bool = Field(False, description="refine each edge by point-to-plane ICP (off: on textured planar scenes ICP slides; GMatch + Kabsch is measured more accurate)")
    icp_max_dist: float = Field(0.01, gt=0, description="ICP correspondence distance (m)")
    icp_voxel: float = Field(0.004, ge=0, description="voxel size for ICP clouds (m), 0 = no downsampling")
    min_fitness: float = Field(0.3, ge=0, le=1, description="an edge needs ICP fitness at least this")
    max_rmse: float = Field(0.006, gt=0, description="an edge needs ICP inlier RMSE at most this (m)")
    max_icp_shift_deg: float = Field(5.0, gt=0, description="reject an edge whose ICP moved the match pose more (deg)")
    max_icp_shift_m: float = Field(0.02, gt=0, description="reject an edge whose ICP moved the match pose more (m)")


class PoseGraphConfig(_Section):
    loop_candidates: int = Field(4, ge=0, description="loop-closure candidates tried per frame")
    certain_min_inliers: int = Field(48, ge=0, description="sequential edges with fewer inliers are treated like "
                                     "loop closures (the pose graph may switch them off)")
    max_view_angle_deg: float = Field(75.0, gt=0, le=180, description="loop candidates view the object within this angle")
    prune_rot_deg: float = Field(2.0, gt=0, description="edges disagreeing with the optimised graph by more are pruned")
    prune_trans_m: float = Field(0.01, gt=0, description="edges disagreeing with the optimised graph by more are pruned (m)")


class FusionConfig(_Section):
    voxel: float | None = Field(None, gt=0, description="TSDF voxel size (m); null = object extent / 150 within 2-10 mm")
    depth_max: float = Field(2.0, gt=0, description="depth beyond this is ignored when fusing (m)")


class SegmentationConfig(_Section):
    depth_min: float = Field(0.1, ge=0.05, le=20, description="the object is looked for at depths from this (m) ...")
    depth_max: float = Field(1.5, gt=0.05, le=20, description="... to this (m); raise it (and fusion.depth_max) for a far camera")
    height_max: float = Field(0.5, ge=0.01, le=5, description="the object stands at most this high above its support plane (m)")

    @model_validator(mode="after")
    def _range(self) -> "SegmentationConfig":
        if self.depth_max <= self.depth_min:
            raise ValueError("depth_max must be greater than depth_min")
        return self


class KeyframeConfig(_Section):
    min_angle_deg: float = Field(12.0, ge=0, description="a new keyframe views the object at least this far from all others")
    max_views: int = Field(120, ge=1, description="at most this many template views")


class ScanConfig(_Section):
    features: FeaturesConfig = FeaturesConfig()
    match: MatchConfig = MatchConfig()
    registration: RegisterConfig = RegisterConfig()
    posegraph: PoseGraphConfig = PoseGraphConfig()
    segmentation: SegmentationConfig = SegmentationConfig()
    fusion: FusionConfig = FusionConfig()
    keyframes: KeyframeConfig = KeyframeConfig()

    @model_validator(mode="after")
    def _segment_within_fusion(self) -> "ScanConfig":
        if self.segmentation.depth_min >= self.fusion.depth_max:
            raise ValueError("segmentation.depth_min must be below fusion.depth_max (nothing could be fused)")
        return self


def load_config(path: str | Path | None) -> ScanConfig:
    """Read and validate a YAML config; None gives the defaults. Raises InputError naming the file."""
    if path is None:
        return ScanConfig()
    path = Path(path)
    if not path.is_file():
        raise not_a_file(path, "configuration file")
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8-sig")) or {}
    except OSError as e:
        raise InputError(path, f"cannot read config ({e.strerror or e})") from None
    except UnicodeDecodeError:
        raise InputError(path, "cannot read config (not UTF-8 text)") from None
    except RecursionError:
        raise InputError(path, "malformed YAML: nested too deeply") from None
    except yaml.YAMLError as e:
        raise InputError(path, f"malformed YAML: {str(e).splitlines()[0]}") from None
    if not isinstance(data, dict):
        raise InputError(path, "config must be a mapping of sections")
    try:
        return ScanConfig.model_validate(data)
    except ValidationError as e:
        err = e.errors()[0]
        where = ".".join(str(x) for x in err["loc"])
        msg = err["msg"].removeprefix("Value error, ")
        raise InputError(path, f"invalid config key {where}: {msg}" if where else f"invalid config: {msg}") from None


def dump_defaults() -> str:
    """The default configuration as YAML with a comment per key."""
    lines = ["# gscan scan configuration (defaults). Pass an edited copy with --config."]
    cfg = ScanConfig()
    for section, model in cfg:
        lines.append(f"{section}:")
        for key, field in type(model).model_fields.items():
            value = yaml.safe_dump(getattr(model, key), default_flow_style=True).strip().removesuffix("\n...")
            value = value.removesuffix("...").strip()
            lines.append(f"  {key}: {value}  # {field.description}")
    return "\n".join(lines) + "\n"
