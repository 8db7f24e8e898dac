"""Each stage's parameters from the scan configuration (`ScanConfig`), for the capture's mode."""
from __future__ import annotations

from dataclasses import replace

from gscan.features import FeatureParams
from gscan.matching.gmatch import GMatchParams
from gscan.registration.noise import DepthNoise
from gscan.registration.pairwise import RegisterParams
from gscan.registration.sequence import SequenceParams
from gscan.scanning.capture_mode import MOVING_OBJECT, STATIC_OBJECT
from gscan.scanning.config import ScanConfig
from gscan.scanning.segment import SegmentParams
from gscan.scanning.select import SelectionParams

# eps_f for whole-frame registration (static object) when the config leaves it unset: on whole frames
# RootSIFT 0.5 is as accurate as the object-only default 0.6 and gives far fewer candidates, so the search is
# faster (see BENCHMARKS.md, section Parameter studies)
WHOLE_FRAME_EPS_F = {"rootsift": 0.5}


def feature_params(cfg: ScanConfig) -> FeatureParams:
    """The registration keypoints' parameters from the config."""
    return FeatureParams(kind=cfg.features.kind, max_keypoints=cfg.features.max_keypoints)


def register_params(cfg: ScanConfig, mode: str) -> RegisterParams:
    """Registration's parameters from the config; the noise models are the configured ones, or the priors a
    capture's own noise is estimated from (`capture_noise`)."""
    m, r = cfg.match, cfg.registration
    eps_f = m.eps_f
    if eps_f is None and mode == STATIC_OBJECT:
        eps_f = WHOLE_FRAME_EPS_F.get(cfg.features.kind)
    # the depth refines edges of a moving object, whose masked views hold few keypoints; a static scene's
    # whole-frame depth pulls real Kinect edges off the truth where the camera moves fast (see BENCHMARKS.md,
    # section Real Kinect frames)
    dense = r.dense_refine if r.dense_refine is not None else mode == MOVING_OBJECT
    gm = GMatchParams(eps_f=eps_f, eps_c=m.eps_c, eta=m.eta, T=m.T, L=m.L, constraint=m.constraint, order=m.order)
    params = RegisterParams(method=m.method, gmatch=gm, min_matches=r.min_matches, max_rms=r.max_rms,
                            max_sigma_deg=r.max_sigma_deg, max_sigma_rel=r.max_sigma_rel,
                            max_see_through=r.max_see_through, min_colour_agreement=r.min_colour_agreement,
                            dense_refine=dense, verify=r.verify,
                            support_eps_scale=r.support_eps_scale, icp=r.icp, icp_max_dist=r.icp_max_dist,
                            icp_voxel=r.icp_voxel, min_fitness=r.min_fitness, max_rmse=r.max_rmse,
                            max_icp_shift_deg=r.max_icp_shift_deg, max_icp_shift_m=r.max_icp_shift_m)
    if r.noise is None:
        return params
    return replace(params, noise=DepthNoise(**r.noise.keypoint.model_dump()),
                   depth_noise=DepthNoise(**r.noise.depth.model_dump()))


def sequence_params(cfg: ScanConfig) -> SequenceParams:
    """The sequence registration's parameters from the config."""
    p = cfg.posegraph
    return SequenceParams(loop_candidates=p.loop_candidates, max_view_angle_deg=p.max_view_angle_deg, alpha=p.alpha,
                          bridge_min_matches=p.bridge_min_matches)


def segment_params(cfg: ScanConfig) -> SegmentParams:
    s = cfg.segmentation
    return SegmentParams(depth_min=s.depth_min, depth_max=s.depth_max, height_max=s.height_max)


def selection_params(cfg: ScanConfig) -> SelectionParams:
    s = cfg.selection
    return SelectionParams(min_motion_deg=s.min_motion_deg, blur_ratio=s.blur_ratio)


def icp_voxel(cfg: ScanConfig) -> float | None:
    """The voxel of the clouds ICP refines edges on (m); None without ICP."""
    return cfg.registration.icp_voxel if cfg.registration.icp else None
