"""The registration's settings, one class per step (gscan.settings' convention): how a pair of frames is
registered (`RegisterParams`, gscan.registration.pairwise), how a sequence is (`SequenceParams`,
gscan.registration.sequence, with the loop candidates' `LoopParams` and the pose graph's `PoseGraphParams`), how
captures are joined (`JoinParams`, gscan.registration.join). numpy and pydantic only: the scan's configuration is
read and validated without loading the compiled kernels."""
from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Annotated, Any, Literal

from pydantic import Field

from gscan.matching.params import BASELINES, BaselineParams, GMatchParams
from gscan.registration.noise import DepthNoise
from gscan.settings import SETTINGS

METHODS = ("gmatch",) + BASELINES


# the noise models by their names in a template's "noise" meta and in the settings' `registration.noise`, and the
# fields of RegisterParams they set; templates and settings written before the model along the ray lack it
NOISE_MODELS = {"keypoint": "noise", "depth": "depth_noise", "depth_ray": "depth_noise_ray"}
REQUIRED_NOISE_MODELS = ("keypoint", "depth")


@dataclass(frozen=True)
class RegisterParams:
    """How a pair of frames is registered and when the edge is accepted (rules 1-4 of gscan.registration.pairwise's
    docstring)."""

    __pydantic_config__ = SETTINGS

    method: Annotated[Literal["gmatch", "ratio", "mutual", "ransac", "lo-ransac", "fgr"], Field(
        description="pairwise matcher: GMatch or a baseline (for comparison)")] = "gmatch"
    gmatch: Annotated[GMatchParams, Field(description="GMatch's settings")] = GMatchParams()
    baseline: Annotated[BaselineParams, Field(description="the baselines' settings")] = BaselineParams()
    noise: Annotated[DepthNoise, Field(description="noise of a lifted keypoint (window median of the depth), the unit "
                                       "s of every keypoint residual threshold; a scan's prior, from which it "
                                       "estimates its capture's own (posegraph.estimate_noise)")] = DepthNoise()
    depth_noise: Annotated[DepthNoise, Field(description="noise of one depth pixel (the depth check and the depth "
                                             "refinement); a scan's prior, like noise")] = DepthNoise()
    depth_noise_ray: Annotated[DepthNoise, Field(description="the same noise with its error along the sensor's ray "
                                                 "(`DepthNoise.along_ray`): where the depth alone judges a pose "
                                                 "(a plain object); a scan's prior, like noise")] = DepthNoise(
        along_ray=True)
    min_matches: Annotated[int, Field(ge=3, description="rule 1: an edge needs at least this many geometric "
                                      "matches")] = 6
    max_rms: Annotated[float, Field(gt=0, description="rule 2: an edge's keypoint residual RMS may be at most this "
                                    "many noise sigmas")] = 2.5
    max_sigma_deg: Annotated[float, Field(gt=0, description="rule 2: an edge's pose, as its matched points pin it, "
                                          "may be uncertain by at most this (deg, 1 sigma)")] = 1.0
    max_sigma_rel: Annotated[float, Field(gt=0, description="rule 2: ... and by at most this share of its depth "
                                          "(position, 1 sigma)")] = 0.01
    refine: Annotated[bool, Field(description="guided refinement of the GMatch pose (gmatch only)")] = True
    refine_gates: Annotated[tuple[float, ...], Field(min_length=1, description="the refinement's inlier gate per "
                                                     "round, in noise sigmas")] = (5.0, 4.0, 3.4)
    trim_gate: Annotated[float, Field(gt=0, description="GMatch list pairs off by more noise sigmas are trimmed from "
                                      "the pose")] = 4.0
    verify: Annotated[int, Field(ge=0, le=256, description="other GMatch hypothesis lists whose support is checked "
                                 "against the longest's (0 = the paper's pick)")] = 16
    verify_min_len: Annotated[int, Field(ge=3, description="... of at least this many pairs")] = 4
    verify_ratio: Annotated[float, Field(ge=1, description="... one replaces the longest only with this many times "
                                         "its support")] = 1.5
    support_eps_scale: Annotated[float, Field(ge=1, le=4, description="the support of those lists counts pairs with "
                                              "descriptor distance below this x eps_f (1 = GMatch's "
                                              "candidates)")] = 1.5
    max_see_through: Annotated[float, Field(ge=0, le=1, description="rule 3: an edge is rejected when its pose lets "
                                            "one frame see through this share of the other frame's surfaces")] = 0.15
    min_colour_agreement: Annotated[float, Field(ge=0, le=1, description="rule 3: an edge is rejected when the "
                                                 "texture of fewer than this share of the overlap's textured tiles "
                                                 "lines up under its pose (unrelated texture: about 1 in 17)")] = 1 / 3
    min_colour_tiles: Annotated[int, Field(ge=1, description="rule 3: textured tiles the colour verdict needs")] = 8
    alone_colour_agreement: Annotated[float, Field(ge=0, le=1, description="an edge that alone places a frame (a "
                                                   "two-frame capture) is taken on its print, without weighing the "
                                                   "object's half turns, only when at least this share of the "
                                                   "overlap's textured tiles lines up (look-alike sides of a box "
                                                   "lined up in 41-78 % under wrong poses)")] = 0.9
    support_plane_min_frac: Annotated[float, Field(gt=0, le=1, description="a half turn of the object is refuted "
                                                   "when it puts the two cameras on opposite sides of a printed plane "
                                                   "both views see from one side under the edge's pose (the table "
                                                   "of a whole-frame capture), a plane holding at least this share "
                                                   "of each view's depth samples")] = 0.3
    max_see_through_shape: Annotated[float, Field(ge=0, le=1, description="rule 3: an edge of depth keypoints "
                                                  "(rootsift+fpfh) that the texture cannot judge (a plain object: "
                                                  "the depth alone decides) is rejected beyond this share seen "
                                                  "through")] = 0.005
    max_outside_shape: Annotated[float, Field(ge=0, le=1, description="rule 3: ... or when more than this share of "
                                              "either frame's depth samples lands off the other's (its "
                                              "silhouette, with masks)")] = 0.05
    max_outside_outline: Annotated[float, Field(ge=0, le=1, description="rule 3: ... or when more than this share "
                                                "of the samples land off the other frame's outline by more than "
                                                "three times the pose's positional sigma and two pixels (full "
                                                "resolution: a pose slid along a plain face)")] = 0.01
    dense_refine: Annotated[bool | None, Field(description="refine each edge's pose on its keypoints and both frames' "
                                               "depth together (point-to-plane); null = on, and in a scan for a "
                                               "moving object only (a static scene's depth drifts from the truth "
                                               "where the camera moves fast)")] = None
    photometric: Annotated[bool, Field(description="rule 2: where the keypoints and depth pin the pose of an edge "
                                       "that alone places a frame (a two-frame capture) too loosely, refine it on "
                                       "both frames' texture pixel by pixel and judge it by that "
                                       "(`gscan.registration.photometric`; with the depth refinement)")] = True
    min_overlap: Annotated[int, Field(ge=1, description="rule 3: depth samples that must land on the other frame to "
                                      "verify the pose")] = 50
    icp: Annotated[bool, Field(description="refine each edge by point-to-plane ICP (off: on textured planar scenes "
                               "ICP slides; GMatch + Kabsch is measured more accurate)")] = False
    icp_max_dist: Annotated[float, Field(gt=0, description="ICP correspondence distance (m)")] = 0.01
    icp_voxel: Annotated[float, Field(ge=0, description="voxel size for ICP clouds (m), 0 = no downsampling")] = 0.004
    icp_iterations: Annotated[int, Field(ge=1, description="ICP iterations")] = 30
    min_fitness: Annotated[float, Field(ge=0, le=1, description="rule 4: an edge needs ICP fitness at least "
                                        "this")] = 0.3
    max_rmse: Annotated[float, Field(gt=0, description="rule 4: an edge needs ICP inlier RMSE at most this "
                                     "(m)")] = 0.006
    max_icp_shift_deg: Annotated[float, Field(gt=0, description="rule 4: reject an edge whose ICP moved the match pose "
                                              "more (deg)")] = 5.0
    max_icp_shift_m: Annotated[float, Field(gt=0, description="rule 4: reject an edge whose ICP moved the match pose "
                                            "more (m)")] = 0.02

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"unknown registration method {self.method!r}; expected one of {METHODS}")
        if self.min_matches < 3:
            raise ValueError("min_matches must be >= 3")
        if self.verify < 0 or self.verify_min_len < 3 or self.verify_ratio < 1 or self.support_eps_scale < 1:
            raise ValueError("need verify >= 0, verify_min_len >= 3, verify_ratio >= 1 and support_eps_scale >= 1")
        if not self.refine_gates or min(self.refine_gates) <= 0 or self.trim_gate <= 0 or self.max_rms <= 0:
            raise ValueError("refine_gates, trim_gate and max_rms must be positive")
        if not 0 <= self.max_see_through <= 1 or not 0 <= self.min_colour_agreement <= 1:
            raise ValueError("max_see_through and min_colour_agreement must lie in [0, 1]")

    @property
    def refines_on_depth(self) -> bool:
        """Whether the pose is refined on keypoints and depth together (dense_refine; null: on)."""
        return self.dense_refine is not False

    def noise_models(self) -> dict[str, dict[str, float]]:
        """The noise models by their names in a template's "noise" meta (`NOISE_MODELS`)."""
        return {name: getattr(self, field).to_dict() for name, field in NOISE_MODELS.items()}

    def with_noise_models(self, models: dict) -> RegisterParams:
        """These settings with the noise models of `models` (`noise_models`' form; keypoint and depth needed, a
        model it lacks keeps this one's: templates written before the along-the-ray model have none). Raises
        TypeError, ValueError or KeyError on a damaged record."""
        changes: dict[str, Any] = {field: DepthNoise(**models[name]) for name, field in NOISE_MODELS.items()
                                   if name in models or name in REQUIRED_NOISE_MODELS}
        return replace(self, **changes)


@dataclass(frozen=True)
class LoopParams:
    """Which pairs of nodes are tried as loop closures (gscan.registration.loops)."""

    max_per_node: int = 4          # each node takes part in at most this many candidates
    min_index_gap: int = 3         # skip near-sequential pairs (|i - j| < gap)
    max_angle_deg: float = 75.0    # views overlap when viewing directions are within this angle ...
    max_baseline: float = 1.0      # ... and the camera centres within this multiple of the depth they look at
    appearance_top_k: int = 2      # per node, the k most similar nodes by appearance are candidates
    min_similarity: float = 0.2    # ... if their similarity reaches this
    vocabulary_size: int = 64      # bag-of-words words (k-means on the descriptors)
    seed: int = 0


@dataclass(frozen=True)
class PoseGraphParams:
    """The robust pose-graph optimisation's rounds (gscan.registration.posegraph)."""

    alpha: float = 1e-6                          # an edge is inconsistent beyond the chi^2_6 (1 - alpha) quantile
    max_rounds: int = 200                        # reject / re-optimise rounds
    max_iterations: int = 100                    # LM iterations per optimisation

    def __post_init__(self) -> None:
        if not 0 < self.alpha < 1 or self.max_rounds < 1 or self.max_iterations < 1:
            raise ValueError("need 0 < alpha < 1, max_rounds >= 1 and max_iterations >= 1")


_LP, _PG = LoopParams(), PoseGraphParams()


@dataclass(frozen=True)
class SequenceParams:
    """How a sequence is registered: which pairs, how the pose graph judges them, how a view's quality is scored."""

    __pydantic_config__ = SETTINGS

    loop_candidates: Annotated[int, Field(ge=0, description="loop-closure candidates tried per frame")] = (
        _LP.max_per_node)
    max_view_angle_deg: Annotated[float, Field(gt=0, le=180, description="loop candidates view the object within "
                                               "this angle")] = _LP.max_angle_deg
    alpha: Annotated[float, Field(gt=0, lt=1, description="an edge is inconsistent with the others when its chi^2 is "
                                  "beyond the (1 - alpha) quantile (6 degrees of freedom)")] = _PG.alpha
    bridge_min_matches: Annotated[int, Field(ge=3, description="an edge that alone joins two parts of the graph needs "
                                             "this many matches, or the capture's steady motion pinning it; weaker, it "
                                             "is cut and the parts reported")] = (
        2 * RegisterParams().min_matches)
    max_skip: Annotated[int, Field(ge=1, le=32, description="a frame is tried against up to this many preceding "
                                   "frames, its predecessor first, until one is accepted")] = 3
    second_opinions: Annotated[int, Field(ge=0, le=16, description="more frames a frame the pose graph cut loose is "
                                          "registered to (the views nearest its own); 0 = none")] = 2
    pilot_pairs: Annotated[int, Field(ge=0, le=256, description="sequential pairs, spread over the capture, whose "
                                      "residuals fit the capture's noise (estimate_noise)")] = 8
    steady_min_steps: Annotated[int, Field(ge=2, description="accepted edges of consecutive frames needed to measure "
                                           "the capture's steady motion (fewer: none is used)")] = 8
    steady_sigmas: Annotated[float, Field(gt=0, description="an edge agrees with the capture's steady motion when it "
                                          "lies within this many of the prediction's spreads, in rotation and "
                                          "translation")] = 3.0
    odometry_sigmas: Annotated[float, Field(gt=0, description="a loop edge is rejected when it turns the view "
                                            "against the capture's odometry by more than this many of registration's "
                                            "largest accepted rotation sigmas per frame between its two")] = 5.0
    estimate_noise: Annotated[bool, Field(description="estimate the capture's noise (registration.noise and "
                                          "depth_noise the priors); false = use those as given")] = True
    quality_rms_sigma: Annotated[float, Field(gt=0, description="a view whose best accepted edge has this RMS "
                                              "keypoint residual (noise sigmas) gets quality 0")] = 3.4

    def loop_params(self) -> LoopParams:
        """The loop-closure candidates' parameters."""
        return LoopParams(max_per_node=self.loop_candidates, max_angle_deg=self.max_view_angle_deg)

    def graph_params(self) -> PoseGraphParams:
        """The pose graph's parameters."""
        return PoseGraphParams(alpha=self.alpha)


@dataclass(frozen=True)
class JoinParams:
    """How captures of one object are joined."""

    __pydantic_config__ = SETTINGS

    views: Annotated[int, Field(ge=2, le=32, description="registered views of each capture tried against the "
                                "other's (spread over the capture)")] = 8
    min_pairs: Annotated[int, Field(ge=2, description="view pairs that must agree on the motion joining two "
                                    "captures")] = 3
    agree_sigmas: Annotated[float, Field(gt=0, description="two view pairs agree when their motions differ by "
                                         "less than this many of their predicted standard deviations")] = 4.0
    turn_texture_ratio: Annotated[float, Field(gt=0, lt=1, description="the object turned about a principal axis "
                                               "is outweighed when its share of the overlap's textured tiles that "
                                               "line up is below this fraction of the motion found's")] = 0.5
    turn_sign_alpha: Annotated[float, Field(gt=0, lt=0.5, description="another motion (a turn of the object, or a "
                                            "second group of view pairs') is refuted by the texture both line up "
                                            "on when so few of the surface patches where they differ favour it "
                                            "that a fair coin would give as few with at most this chance (a sign "
                                            "test: the risk of refuting a motion the texture supports as well)")] \
        = 1e-3
