"""The settings of the scan's own checks (gscan.settings' convention): the colour focal length check
(`FocalCheckParams`, gscan.scanning.calibration) and the symmetry search (`SymmetryParams`,
gscan.scanning.symmetry). numpy and pydantic only: the scan's configuration is read without loading them."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

from pydantic import Field

from gscan.settings import SETTINGS


@dataclass(frozen=True)
class FocalCheckParams:
    """The check's settings (gscan.scanning.calibration's docstring)."""

    __pydantic_config__ = SETTINGS

    check_colour_focal: Annotated[bool, Field(description="a folder capture with one set of intrinsics: check that "
                                              "its depth lines up with its colour, and when the texture says the "
                                              "colour camera's focal length differs, scan with the one the data "
                                              "give")] = True
    steps: Annotated[tuple[int, ...], Field(min_length=1, description="frame pairs (i, i + step) registered")] = (1, 2)
    groups: Annotated[int, Field(ge=1, description="first frames i spread over the capture")] = 8
    keypoints: Annotated[int, Field(ge=50, description="the strongest keypoints kept per frame (enough to register "
                                    "neighbours, and fast)")] = 800
    alpha: Annotated[float, Field(gt=0, lt=1, description="the level of the signed-rank test and of the estimate's "
                                  "interval (1 - alpha)")] = 0.05
    min_gain: Annotated[float, Field(ge=0, le=1, description="the least gain in the mean share of textured tiles "
                                     "lining up")] = 0.03
    edge_frames: Annotated[int, Field(ge=1, description="frames spread over the capture whose depth jumps are "
                                      "compared with their colour edges (gscan.scanning.depth_edges)")] = 8
    bootstrap: Annotated[int, Field(ge=50, description="resamples of the pairs for the estimate's "
                                    "uncertainty")] = 400
    max_uncertainty: Annotated[float, Field(gt=0, lt=1, description="the widest interval (half of it, relative to the "
                                            "focal length) that keeps the given focal length: a focal length off "
                                            "by x bends the frames' geometry by about x (3 cm at 1 m for the 3 % of "
                                            "the default)")] = 0.03


@dataclass(frozen=True)
class SymmetryParams:
    """How an object's symmetries are found (`gscan.scanning.symmetry.find_symmetries`, that module's docstring)."""

    __pydantic_config__ = SETTINGS

    enabled: Annotated[bool, Field(description="find the object's symmetries at the end of the scan")] = True
    reference_samples: Annotated[int, Field(ge=1000, description="surface samples the rotated ones are compared "
                                            "with (their spacing is part of the tolerance)")] = 60000
    test_samples: Annotated[int, Field(ge=100, description="surface samples rotated by each candidate")] = 3000
    tolerance_sigmas: Annotated[float, Field(gt=0, description="tolerance in standard deviations of the template's "
                                             "surface error (module docstring)")] = 2.0
    inlier_share: Annotated[float, Field(gt=0, le=1, description="a rotation holds when this share of the tested "
                                         "samples lands within the tolerance of the surface")] = 0.9
    min_tested_share: Annotated[float, Field(gt=0, le=1, description="... and at least this share of them landed "
                                             "on seen parts (not in a hole of the surface)")] = 0.5
    continuous_steps: Annotated[int, Field(ge=8, description="revolution is tested at this many angles")] = 36
    plane_step_deg: Annotated[float, Field(gt=0, le=15, description="angle step of the search for 2-fold axes "
                                           "perpendicular to a 4-fold axis (5 steps coarse, then 1, then 1/5 "
                                           "about the best)")] = 1.0
