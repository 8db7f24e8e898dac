"""The estimator's settings read from the YAML configuration file the scan reads its sections from.

The file's `estimate:` section holds `EstimateParams`' sections (gscan.estimate.params); the file's other
sections are the scan's and are ignored here. A key left out keeps the estimator's default (not the default
of the section's class: the query keypoints' defaults are the template's object keypoint settings).

- `load_estimate_params(path) -> EstimateParams`: the `estimate:` section of a file (None, or no such
  section: the defaults); InputError naming the file and the key (`estimate.refine.max_dist`)
- `dump_estimate_defaults() -> str`: the commented YAML of the defaults under a top-level `estimate:` key,
  to follow the scan's sections in `gscan config dump`
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

from pydantic import BaseModel, Field

from gscan.errors import InputError
from gscan.estimate.params import DEFAULT_PARAMS, EstimateParams
from gscan.settings import SETTINGS, dump_yaml, read_yaml, to_data, validate

SECTION = "estimate"


class _EstimateFile(BaseModel):
    """The part of a configuration file read here: its `estimate:` section (the scan's sections pass through)."""

    model_config = SETTINGS | {"extra": "ignore"}
    estimate: EstimateParams = Field(DEFAULT_PARAMS, description="pose estimation (gscan estimate, track, serve)")


def load_estimate_params(path: str | Path | None) -> EstimateParams:
    """`EstimateParams` from the `estimate:` section of the YAML configuration at `path` (module docstring);
    None or a file without that section gives the defaults. InputError naming the file and the key."""
    if path is None:
        return DEFAULT_PARAMS
    data = read_yaml(path)
    section = data.get(SECTION)
    if section is None:
        return DEFAULT_PARAMS
    if not isinstance(section, dict):
        raise InputError(path, f"invalid config key {SECTION}: must be a mapping of sections")
    merged = _over(to_data(DEFAULT_PARAMS), section)
    return validate(_EstimateFile, {SECTION: merged}, path).estimate


def dump_estimate_defaults() -> str:
    """The commented YAML of the estimator's defaults, nested under a top-level `estimate:` key; appended to
    the scan's dump, the whole text loads back (`load_estimate_params`, the scan's loader)."""
    return dump_yaml(_EstimateFile(), "")


def _over(defaults: Any, given: Any) -> Any:
    """`given` laid over `defaults` key by key (mappings merged, anything else replaced): the keys left out keep
    the estimator's defaults; unknown keys stay for validation to refuse."""
    if not isinstance(defaults, dict) or not isinstance(given, dict):
        return given
    out = dict(defaults)
    for k, v in given.items():
        out[k] = _over(defaults.get(k), v)
    return out
