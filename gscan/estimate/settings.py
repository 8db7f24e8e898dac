"""The estimator's settings in the YAML configuration: its `estimate:` section (`EstimateParams`).

- `load_estimate_params(path) -> EstimateParams`: the file's `estimate:` section over the defaults (InputError
  naming the file and the key); the file's other sections are the scan's
- `dump_estimate_defaults() -> str`: the `estimate:` section of the defaults as YAML (loads back as them)
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import yaml

from gscan.errors import InputError
from gscan.estimate.estimator import EstimateParams
from gscan.settings import read_yaml, to_data, validate

SECTION = "estimate"


@dataclasses.dataclass(frozen=True)
class _Config:
    """The configuration's `estimate:` section (its other sections are left to the scan)."""

    estimate: EstimateParams = dataclasses.field(default_factory=EstimateParams)


def load_estimate_params(path: str | Path) -> EstimateParams:
    """The `estimate:` section of the YAML file `path` over the defaults (none: the defaults)."""
    section = read_yaml(path).get(SECTION) or {}
    if not isinstance(section, dict):
        raise InputError(path, f"invalid config key {SECTION}: must be a mapping of settings")
    _refuse_unknown(path, EstimateParams(), section, SECTION)
    return validate(_Config, {SECTION: section}, path).estimate


def _refuse_unknown(path: str | Path, settings: Any, data: dict[str, Any], where: str) -> None:
    """InputError naming the first key of `data` that is no field of the dataclass `settings` (at any depth):
    pydantic's validation of a plain dataclass ignores extra keys."""
    for key, value in data.items():
        if key not in {f.name for f in dataclasses.fields(settings)}:
            raise InputError(path, f"invalid config key {where}.{key}: Extra inputs are not permitted")
        nested = getattr(settings, key)
        if isinstance(value, dict) and dataclasses.is_dataclass(nested) and not isinstance(nested, type):
            _refuse_unknown(path, nested, value, f"{where}.{key}")


def dump_estimate_defaults() -> str:
    """The `estimate:` section of the default settings as YAML, under a comment line."""
    data: dict[str, Any] = to_data(EstimateParams())
    body = yaml.safe_dump({SECTION: data}, sort_keys=False, default_flow_style=None)
    return "# gscan estimate settings (defaults): the estimator of `gscan estimate` and `gscan serve`\n" + body
