"""The scan's configuration: one section per stage, each section that stage's own settings class (`gscan.settings`
convention), loaded from YAML by the CLI.

Sections: camera (`FocalCheckParams`), selection (`SelectionParams`), features (`FeatureParams`), registration
(`RegisterParams`, GMatch's settings in registration.gmatch), posegraph (`SequenceParams`: which pairs are
registered, the noise estimate, the pose graph), segmentation (`SegmentParams`), fusion (`FusionParams`), keyframes
(`KeyframeParams`), join (`JoinParams`: how the captures of a scan of several are joined), symmetry
(`SymmetryParams`). `gscan config dump` prints them as commented YAML. The defaults that depend on the capture (a
static scene's whole frames, a moving object's masked views) are set by one function, `for_capture`.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, model_validator

from gscan.features import FeatureParams
from gscan.registration.params import (
    NOISE_MODELS,
    REQUIRED_NOISE_MODELS,
    JoinParams,
    RegisterParams,
    SequenceParams,
)
from gscan.scanning.fuse import FusionParams
from gscan.scanning.keyframes import KeyframeParams
from gscan.scanning.modes import MOVING_OBJECT, STATIC_OBJECT
from gscan.scanning.params import FocalCheckParams, SymmetryParams
from gscan.scanning.segment import SegmentParams
from gscan.scanning.select import SelectionParams
from gscan.settings import dump_yaml, read_yaml, validate

# sections another reader takes from the same file (`gscan.estimate.settings.load_estimate_params`): accepted here
# and ignored
FOREIGN_SECTIONS = ("estimate",)

# eps_f for whole-frame registration (static object) when the config leaves it unset: on whole frames
# RootSIFT 0.5 is as accurate as the object-only default 0.6 and gives far fewer candidates, so the search is
# faster (see BENCHMARKS.md, section Parameter studies)
WHOLE_FRAME_EPS_F = {"rootsift": 0.5}


class ScanConfig(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    camera: FocalCheckParams = FocalCheckParams()
    selection: SelectionParams = SelectionParams()
    features: FeatureParams = FeatureParams()
    registration: RegisterParams = RegisterParams()
    posegraph: SequenceParams = SequenceParams()
    segmentation: SegmentParams = SegmentParams()
    fusion: FusionParams = FusionParams()
    keyframes: KeyframeParams = KeyframeParams()
    join: JoinParams = JoinParams()
    symmetry: SymmetryParams = SymmetryParams()

    @model_validator(mode="before")
    @classmethod
    def _earlier_keys(cls, data: Any) -> Any:
        """Files written for earlier versions keep working: the `match` section is registration.gmatch (its
        `method`, registration.method); `registration.noise` was null (estimated) or the models used as given
        (keypoint, depth, and depth_ray where written)."""
        if not isinstance(data, dict) or not isinstance(data.get("registration") or {}, dict):
            return data
        data = dict(data)
        reg = dict(data.get("registration") or {})
        match = data.pop("match", None)
        if isinstance(match, dict):
            match = dict(match)
            if "method" in match:
                reg.setdefault("method", match.pop("method"))
            reg["gmatch"] = {**match, **(reg.get("gmatch") or {})}
        elif match is not None:
            reg["gmatch"] = match  # refused below, named as a section
        noise = reg.get("noise", {})
        if noise is None or (isinstance(noise, dict)
                             and set(REQUIRED_NOISE_MODELS) <= set(noise) <= set(NOISE_MODELS)):
            models = reg.pop("noise", None)
            if models is not None:
                reg.update({NOISE_MODELS[name]: model for name, model in models.items()})
                data["posegraph"] = {"estimate_noise": False, **(data.get("posegraph") or {})}
        if reg or "registration" in data:
            data["registration"] = reg
        return data

    @model_validator(mode="after")
    def _segment_within_fusion(self) -> ScanConfig:
        if self.fusion.depth_max is not None and self.segmentation.depth_min >= self.fusion.depth_max:
            raise ValueError("segmentation.depth_min must be below fusion.depth_max (nothing could be fused)")
        if self.keyframes.object_keypoints == "both" and self.features.kind != "rootsift":
            raise ValueError(f"keyframes.object_keypoints: both joins depth keypoints to rootsift ones, not "
                             f"{self.features.kind}; set object_keypoints: sift or features.kind: rootsift")
        return self


def for_capture(config: ScanConfig, mode: str) -> ScanConfig:
    """The configuration with the defaults that depend on the capture's mode (STATIC_OBJECT | MOVING_OBJECT) set:
    GMatch's eps_f for a static scene's whole frames, and whether edges are refined on the depth (for a moving
    object, whose masked views hold few keypoints; a static scene's whole-frame depth pulls real Kinect edges off
    the truth where the camera moves fast, see BENCHMARKS.md, section Real Kinect frames)."""
    reg = config.registration
    gm = reg.gmatch
    if gm.eps_f is None and mode == STATIC_OBJECT and config.features.kind in WHOLE_FRAME_EPS_F:
        gm = dataclasses.replace(gm, eps_f=WHOLE_FRAME_EPS_F[config.features.kind])
    dense = reg.dense_refine if reg.dense_refine is not None else mode == MOVING_OBJECT
    return config.model_copy(update={"registration": dataclasses.replace(reg, gmatch=gm, dense_refine=dense)})


def load_config(path: str | Path | None) -> ScanConfig:
    """Read and validate a YAML config (its `FOREIGN_SECTIONS` ignored); None gives the defaults. Raises InputError
    naming the file and the key."""
    if path is None:
        return ScanConfig()
    data = {k: v for k, v in read_yaml(path).items() if k not in FOREIGN_SECTIONS}
    return validate(ScanConfig, data, path)


def dump_defaults() -> str:
    """The default configuration as YAML with a comment per key."""
    return dump_yaml(ScanConfig(), "gscan scan configuration (defaults). Pass an edited copy with --config.")
