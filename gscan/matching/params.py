"""GMatch's settings and its defaults per descriptor kind (`gscan.matching.gmatch` runs the search): numpy and
pydantic only, so that the configuration is read and validated without loading the compiled kernels."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Literal

from pydantic import Field

from gscan.settings import SETTINGS

CONSTRAINTS = {"distance": 0, "flip": 1, "triple": 2}
ORDERS = ("ratio", "distance")

# Default feature thresholds per descriptor kind (distance metric of gscan.features.descriptor_distances:
# L2 on unit-norm RootSIFT vectors, L2 on raw OpenCV SIFT vectors (norm ~512), Hamming bits for ORB).
# Chosen by the sweeps in BENCHMARKS.md, section Parameter studies: RootSIFT 0.6 has the best success on
# object-pixel keypoints at wide view changes (whole frames succeed at every value, and a scan of a static
# object uses a lower one there: fewer candidates, a faster search). SIFT / ORB: the smallest value at the
# best whole-frame rate of their sweeps.
# rootsift+fpfh: RootSIFT's, its FPFH part scaled to match (`gscan.features.depth.FPFH_SCALE`).
_DEFAULT_EPS_F = {"rootsift": 0.6, "sift": 150.0, "orb": 64.0, "rootsift+fpfh": 0.6}


def default_eps_f(kind: str) -> float:
    """Default feature threshold eps_f of a descriptor kind ("rootsift" | "sift" | "orb")."""
    try:
        return _DEFAULT_EPS_F[kind]
    except KeyError:
        raise ValueError(f"unknown descriptor kind {kind!r}; expected one of {sorted(_DEFAULT_EPS_F)}") from None


@dataclass(frozen=True)
class GMatchParams:
    """GMatch's settings (gscan.matching.gmatch's docstring)."""

    __pydantic_config__ = SETTINGS

    eps_f: Annotated[float | None, Field(gt=0, description="descriptor distance threshold; null = the descriptor's "
                                         "default (a scan: tighter for rootsift on a static scene's whole "
                                         "frames)")] = None
    eps_c: Annotated[float, Field(gt=0, lt=1, description="relative pairwise-distance tolerance")] = 0.08
    eta: Annotated[float, Field(gt=0, description="absolute distance margin at eta_ref_depth (m)")] = 0.01
    eta_depth: Annotated[bool, Field(description="eta grows with (z / eta_ref_depth)^2 beyond eta_ref_depth")] = True
    eta_ref_depth: Annotated[float, Field(gt=0, description="the depth eta holds at (m)")] = 0.5
    T: Annotated[int, Field(ge=1, le=256, description="seeds (the first T candidates in the search order)")] = 24
    L: Annotated[int, Field(ge=3, le=256, description="maximum match-list length")] = 24
    constraint: Annotated[Literal["flip", "triple", "distance"], Field(
        description="flip-over or scalar-triple-product constraint (distance: none, an ablation)")] = "flip"
    K2: Annotated[int, Field(ge=1, le=256, description="second pairs per seed (level 2 of the hypothesis "
                             "search)")] = 8
    K3: Annotated[int, Field(ge=1, le=256, description="third pairs per second pair (level 3)")] = 4
    flip_margin: Annotated[float, Field(ge=0, description="|z_s - z_t| above which opposite-signed normals count "
                                        "as a flip-over")] = 0.8
    collinear_sin: Annotated[float, Field(ge=0, lt=1, description="triangles with a smaller sine are degenerate "
                                          "(not flip-tested)")] = 0.1
    order: Annotated[Literal["ratio", "distance"], Field(
        description="candidate order: Lowe ratio (distinctive first) or descriptor distance (the paper's)")] = "ratio"

    def __post_init__(self) -> None:
        if self.order not in ORDERS:
            raise ValueError(f"order must be one of {ORDERS}, got {self.order!r}")
        if self.constraint not in CONSTRAINTS:
            raise ValueError(f"constraint must be one of {sorted(CONSTRAINTS)}, got {self.constraint!r}")
        if self.T < 1 or self.L < 3 or self.K2 < 1 or self.K3 < 1:
            raise ValueError("need T >= 1, L >= 3, K2 >= 1, K3 >= 1")
        if not (0 < self.eps_c < 1 and self.eta > 0 and self.eta_ref_depth > 0):
            raise ValueError("need 0 < eps_c < 1 (a relative distance error) and positive eta, eta_ref_depth")


BASELINES = ("ratio", "mutual", "ransac", "lo-ransac", "fgr")


@dataclass(frozen=True)
class BaselineParams:
    """The baseline matchers' settings (for comparison with GMatch)."""

    __pydantic_config__ = SETTINGS

    ratio: Annotated[float, Field(gt=0, le=1, description="Lowe's ratio")] = 0.75
    inlier_dist: Annotated[float, Field(gt=0, description="RANSAC / LO-RANSAC inlier threshold (m)")] = 0.01
    iterations: Annotated[int, Field(ge=1, description="RANSAC / LO-RANSAC maximum trials")] = 100_000
    confidence: Annotated[float, Field(gt=0, lt=1, description="RANSAC confidence")] = 0.999
    fgr_dist_factor: Annotated[float, Field(gt=0, description="FGR's final correspondence distance, in "
                                            "inlier_dist")] = 2.5
    seed: Annotated[int, Field(ge=0, description="random seed")] = 0
