"""The estimator's settings: `EstimateParams`, one section per stage (gscan.settings' convention).

Each section is a frozen dataclass of `name: Annotated[type, Field(description=..., bounds)] = default`; the
YAML configuration's `estimate:` section holds the same sections (`gscan.estimate.settings`). The stages are
those of `gscan.estimate.estimator`'s module docstring.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated

from pydantic import Field

from gscan.features import OBJECT_FEATURES, FeatureParams
from gscan.matching.params import GMatchParams
from gscan.registration.params import RegisterParams
from gscan.settings import SETTINGS

_REGISTER = RegisterParams()  # registration's rules for a pose the depth alone decides: the one source of both


@dataclass(frozen=True)
class AcceptParams:
    """The rule a pose is accepted by (`accept`)."""

    min_score: Annotated[float, Field(description="depth-consistency score below this -> not found", ge=0,
                                      le=1)] = 0.6
    min_confirmed: Annotated[float, Field(description="share of the visible template surface the depth confirms "
                                          "below this -> not found", ge=0, le=1)] = 0.15
    strong_matches: Annotated[int, Field(description="the best-supported list, this long (and as many inliers), is "
                                         "evidence enough ...", ge=3)] = 14
    strong_min_ratio: Annotated[float, Field(description="... when at least this fraction of the keypoints there "
                                             "agree with the template", ge=0, le=1)] = 0.1
    min_matches: Annotated[int, Field(description="lists with fewer inliers are never accepted", ge=3)] = 5
    min_support: Annotated[int, Field(description="a shorter list needs this many supporting keypoint locations ...",
                                      ge=0)] = 10
    min_support_ratio: Annotated[float, Field(description="... and this fraction of what the frame and the template "
                                              "show there ...", ge=0, le=1)] = 0.2
    min_spread: Annotated[float, Field(description="... and inliers spread across this fraction of the object radius "
                                       "(not a line)", ge=0)] = 0.05
    max_see_through: Annotated[float, Field(description="a pose the depth alone decides (a template with depth "
                                            "keypoints, no image keypoints to judge it) is refused when the depth "
                                            "is seen through at more than this share of the surface it shows that "
                                            "the depth judges (registration's bound for an edge) ...", ge=0,
                                            le=1)] = _REGISTER.max_see_through
    max_outside_shape: Annotated[float, Field(description="... or when more than this share of the surface it shows "
                                              "lands off the objects in the frame, or of the object it lies on "
                                              "outside its outline (registration's silhouette bound) ...", ge=0,
                                              le=1)] = _REGISTER.max_outside_shape
    min_colour_tiles: Annotated[int, Field(description="... or when at least this many textured tiles of the query and "
                                           "the nearest keyframe overlap under it ...", ge=1)] = (
        _REGISTER.min_colour_tiles)
    min_colour_agreement: Annotated[float, Field(description="... and fewer than this share of them line up "
                                                 "(registration's texture rule)", ge=0, le=1)] = (
        _REGISTER.min_colour_agreement)
    max_chroma_shift: Annotated[float, Field(description="... or when its surface's colour lies farther than this "
                                             "from the nearest keyframe's, in rg chromaticity (shading leaves it; a "
                                             "grey lit at 4500 K instead of 6500 K, the white balance unchanged, "
                                             "moves about as far)", ge=0, le=1)] = 0.05
    __pydantic_config__ = SETTINGS


@dataclass(frozen=True)
class QueryParams:
    """The frame's search region (gscan.estimate.query) and the detection boxes inside it."""

    remove_plane: Annotated[bool, Field(description="without a mask: leave out the dominant plane (table) from the "
                                        "search region")] = True
    plane_min_frac: Annotated[float, Field(description="a plane counts as dominant when it holds this fraction of "
                                           "the valid depth", gt=0, le=1)] = 0.3
    plane_iterations: Annotated[int, Field(description="RANSAC plane hypotheses (seeded)", ge=1)] = 64
    min_depth_frac: Annotated[float, Field(description="valid-depth fraction of the search region below which the "
                                           "pose is solved 2D-3D (PnP)", ge=0, le=1)] = 0.05
    crop_margin: Annotated[int, Field(description="px around the search region's blobs kept for detection",
                                      ge=0)] = 16
    min_region_px: Annotated[int, Field(description="search-region blobs smaller than this (px) are left out of the "
                                        "detection boxes", ge=0)] = 150
    depth_keypoints: Annotated[bool, Field(description="a template whose keyframes hold depth keypoints (scanned on "
                                           "features.keypoints depth or both, or auto on a plain object): the "
                                           "query's depth keypoints join its image keypoints, and a pose the depth "
                                           "alone decides meets the stricter rules (method.md, plain objects); off, "
                                           "the template's image keypoints alone are matched")] = True
    __pydantic_config__ = SETTINGS


@dataclass(frozen=True)
class RetrievalParams:
    """Stage 2: the views the query keypoints vote for, and the view neighbourhoods matched."""

    top_k: Annotated[int, Field(description="view neighbourhoods retrieved and matched", ge=1)] = 3
    joint_views: Annotated[int, Field(description="views matched jointly per neighbourhood (1: every view alone)",
                                      ge=1)] = 3
    joint_deg: Annotated[float, Field(description="... whose optical axes lie within this angle (deg) of the "
                                      "central view's", ge=0, le=180)] = 60.0
    max_dist: Annotated[float, Field(description="descriptor distance under which a query keypoint votes for a view "
                                     "(RootSIFT L2)", gt=0)] = 0.5
    next_round: Annotated[bool, Field(description="when no list of the top_k neighbourhoods gives an accepted pose "
                                      "(and the view is not ambiguous), the next top_k by votes are matched too "
                                      "(the single estimate)")] = True
    __pydantic_config__ = SETTINGS


@dataclass(frozen=True)
class HypothesesParams:
    """Stages 3-4: the GMatch lists kept, pooled and solved."""

    runner_up_margin: Annotated[int, Field(description="GMatch hypotheses this much shorter than a run's best list "
                                           "are pre-scored too", ge=0)] = 2
    merge_deg: Annotated[float, Field(description="lists whose poses agree within this angle (deg) ...",
                                      ge=0, le=180)] = 10.0
    merge_dist: Annotated[float, Field(description="... and this distance (m) are pooled into one list", ge=0)] = 0.02
    trim_tau: Annotated[float, Field(description="m, the match list's pose drops pairs off by more "
                                     "(geometry.kabsch.kabsch_trimmed)", gt=0)] = 0.008
    __pydantic_config__ = SETTINGS


@dataclass(frozen=True)
class VerifyParams:
    """Stage 6: the evidence a pose is verified on (gscan.estimate.verify); acceptance itself: `accept`."""

    lists: Annotated[int, Field(description="match lists whose poses are verified, best pre-score first, until one "
                                "is accepted", ge=1)] = 2
    depth_tol: Annotated[float, Field(description="m, depth agreement tolerance of the score (grows 2 % of depth "
                                      "beyond 0.5 m)", gt=0)] = 0.01
    support_dist: Annotated[float | None, Field(description="descriptor distance at which a supporting keypoint "
                                                "agrees (null: GMatch's eps_f)", gt=0)] = None
    support_radius: Annotated[float, Field(description="m, query keypoint to template keypoint at the pose (grows "
                                           "1 % of depth beyond 0.5 m)", gt=0)] = 0.006
    support_views_deg: Annotated[float, Field(description="template views within this angle (deg) of the query "
                                              "direction offer keypoints", ge=0, le=180)] = 90.0
    below_tol: Annotated[float, Field(description="m: a template point this far behind the support plane is inside "
                                      "it ...", ge=0)] = 0.015
    max_below_frac: Annotated[float, Field(description="... and a pose with more such points is not found",
                                           ge=0, le=1)] = 0.2
    __pydantic_config__ = SETTINGS


@dataclass(frozen=True)
class RivalParams:
    """Stage 7: the lists after the accepted one verified as its rivals."""

    lists: Annotated[int, Field(description="lists after the accepted one verified as its rivals ...", ge=0)] = 2
    min_support: Annotated[float, Field(description="... when their pre-score support reaches this fraction of the "
                                        "accepted list's", ge=0)] = 0.4
    p: Annotated[float, Field(description="one-sided level of the sign test that lets one of two accepted poses win",
                              gt=0, lt=1)] = 0.05
    turn_margin: Annotated[float, Field(description="a pose and its turn by a symmetry in shape only: one wins when "
                                        "its keypoints for it alone outnumber the other's by this fraction of the "
                                        "keypoints for either (and the sign test)", ge=0, le=1)] = 0.15
    unseen_rate: Annotated[float, Field(description="a pose whose turn by a symmetry in shape puts some of its "
                                        "supporting keypoints on surface the template has not seen: the keypoints "
                                        "elsewhere must support it at this fraction of the rate those do, else the "
                                        "view is ambiguous", ge=0, le=1)] = 0.5
    elsewhere: Annotated[bool, Field(description="the single estimate searches the frame outside the accepted pose's "
                                     "pixels (its depth and its holes) as `estimate --all` does; a pose accepted at "
                                     "another place there (a second copy, or a look-alike printed alike on the faces "
                                     "in view) refuses the view as ambiguous")] = True
    __pydantic_config__ = SETTINGS


@dataclass(frozen=True)
class SymmetryParams:
    """The template's symmetries that hold in shape and texture (gscan.estimate.symmetric): rival poses that differ
    by one are one answer, returned by a fixed rule."""

    enabled: Annotated[bool, Field(description="read the template's symmetries (false: every symmetric pose is a "
                                   "rival, as for an object without them)")] = True
    grasp_step_deg: Annotated[float, Field(description="deg: a grasp is offered at every turn of this step about a "
                                           "continuous axis", gt=0, le=180)] = 30.0
    weigh_shape_turns: Annotated[bool, Field(description="weigh every accepted pose against its turns by the "
                                             "template's symmetries in shape only, refusing a tie (off by default: "
                                             "scans find such turns on most boxes, and on the few keypoints that tell "
                                             "them apart the weighing refuses views a print decides)")] = False
    __pydantic_config__ = SETTINGS


@dataclass(frozen=True)
class RefineParams:
    """Stage 5: anchored point-to-plane ICP (gscan.estimate.refine)."""

    max_dist: Annotated[float, Field(description="m, ICP correspondence distance", gt=0)] = 0.005
    voxel: Annotated[float, Field(description="m, template cloud downsampling (ICP source, score)", gt=0)] = 0.003
    target_voxel: Annotated[float, Field(description="m, query cloud voxel averaging (ICP target)", gt=0)] = 0.004
    iterations: Annotated[int, Field(description="ICP steps per correspondence distance", ge=1)] = 20
    max_points: Annotated[int, Field(description="source (template) points used by ICP, evenly subsampled",
                                     ge=10)] = 1500
    anchor_weight: Annotated[float, Field(description="weight of a matched keypoint pair against one surface pair",
                                          ge=0)] = 0.1
    crop_radii: Annotated[float, Field(description="the query cloud is cropped to a sphere of this many object radii "
                                       "around the predicted centre", gt=0)] = 1.2
    max_turn_deg: Annotated[float, Field(description="a refinement turning the pose further (deg), or moving it more "
                                         "than the object radius, is discarded", gt=0, le=180)] = 30.0
    __pydantic_config__ = SETTINGS


@dataclass(frozen=True)
class PnPParams:
    """2D-3D fallback without usable depth (gscan.estimate.pnp)."""

    ratio: Annotated[float, Field(description="Lowe ratio of 2D-3D descriptor matches", gt=0, le=1)] = 0.8
    max_error_px: Annotated[float, Field(description="RANSAC reprojection threshold (px)", gt=0)] = 4.0
    min_inliers: Annotated[int, Field(description="PnP inliers needed", ge=4)] = 12
    min_inlier_ratio: Annotated[float, Field(description="PnP inliers / 2D-3D matches below this -> not found",
                                             ge=0, le=1)] = 0.25
    __pydantic_config__ = SETTINGS


@dataclass(frozen=True)
class HoleParams:
    """PnP in the depth's holes after a failed 3D-3D estimate (gscan.estimate.pnp)."""

    enabled: Annotated[bool, Field(description="after a failed 3D-3D estimate, try PnP on the pixels without "
                                   "depth ...")] = True
    min_frac: Annotated[float, Field(description="... when at least this fraction of the search region lacks depth",
                                     ge=0, le=1)] = 0.01
    open_px: Annotated[int, Field(description="... counting holes that a (2r+1)-pixel square fits in (no speckle, "
                                  "no shadow band)", ge=0)] = 7
    dilate_px: Annotated[int, Field(description="... grown by this many pixels (keypoints at a hole's border)",
                                    ge=0)] = 4
    max_see_through: Annotated[float, Field(description="... and its pose refused when the depth shows through more "
                                            "of the object", ge=0, le=1)] = 0.2
    __pydantic_config__ = SETTINGS


@dataclass(frozen=True)
class ThreadParams:
    """Threads while estimating (the matrices and detection boxes are small: a pool costs more than it saves)."""

    blas: Annotated[int | None, Field(description="BLAS threads (threadpoolctl; null leaves them as they are)",
                                      ge=1)] = 1
    cv: Annotated[int | None, Field(description="OpenCV threads (SIFT; null leaves them as they are)", ge=1)] = 1
    __pydantic_config__ = SETTINGS


@dataclass(frozen=True)
class InstanceParams:
    """Every instance of a template in one frame (`Estimator.estimate_all`, gscan.estimate.instances)."""

    max_instances: Annotated[int, Field(description="instances sought per template and frame at most (each one more "
                                        "search on what the found ones leave)", ge=1)] = 8
    retries: Annotated[int, Field(description="searches after a refusal in a row, the refused lists' keypoints left "
                                  "out (another instance may lie beyond them; each costs a search of the frame)",
                                  ge=0)] = 0
    explain_dist: Annotated[float, Field(description="m: a pixel whose point lies this close to a found pose's surface "
                                         "is explained by it (its keypoints and depth leave the next search)",
                                         gt=0)] = 0.008
    dilate_px: Annotated[int, Field(description="px: the explained pixels grown by this much (keypoints at the "
                                    "object's border)", ge=0)] = 3
    max_overlap: Annotated[float, Field(description="two poses explaining more than this fraction of the smaller's "
                                        "pixels in common are one instance (a rival there is weighed as today, a "
                                        "second pose there is a duplicate)", gt=0, le=1)] = 0.3
    __pydantic_config__ = SETTINGS


@dataclass(frozen=True)
class EstimateParams:
    """Every setting of `Estimator`, a section per stage."""

    features: Annotated[FeatureParams, Field(description="query keypoints (kind follows the template's), the "
                                             "template's object keypoint settings")] = OBJECT_FEATURES
    query: Annotated[QueryParams, Field(description="the frame's search region")] = field(default_factory=QueryParams)
    retrieval: Annotated[RetrievalParams, Field(description="views voted for, neighbourhoods matched")] = field(
        default_factory=RetrievalParams)
    gmatch: Annotated[GMatchParams, Field(description="matcher parameters (eps_f null: the kind's default)")] = field(
        default_factory=GMatchParams)
    hypotheses: Annotated[HypothesesParams, Field(description="match lists pre-scored, pooled and solved")] = field(
        default_factory=HypothesesParams)
    refine: Annotated[RefineParams, Field(description="anchored ICP")] = field(default_factory=RefineParams)
    verify: Annotated[VerifyParams, Field(description="the evidence a pose is verified on")] = field(
        default_factory=VerifyParams)
    accept: Annotated[AcceptParams, Field(description="acceptance from the evidence")] = field(
        default_factory=AcceptParams)
    rivals: Annotated[RivalParams, Field(description="rival poses of an accepted one")] = field(
        default_factory=RivalParams)
    symmetry: Annotated[SymmetryParams, Field(description="the object's symmetries")] = field(
        default_factory=SymmetryParams)
    pnp: Annotated[PnPParams, Field(description="2D-3D fallback without depth")] = field(default_factory=PnPParams)
    holes: Annotated[HoleParams, Field(description="2D-3D in the depth's holes")] = field(default_factory=HoleParams)
    threads: Annotated[ThreadParams, Field(description="threads while estimating")] = field(
        default_factory=ThreadParams)
    instances: Annotated[InstanceParams, Field(description="every instance in a frame (estimate --all)")] = field(
        default_factory=InstanceParams)
    __pydantic_config__ = SETTINGS


#: the estimator's defaults (a shared, frozen value)
DEFAULT_PARAMS = EstimateParams()
