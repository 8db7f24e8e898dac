"""Two RGB-D frames registered in one call: `register_frames(frame_s, frame_t) -> PairResult`, the one-call Python
API. It extracts both frames' keypoints, samples their depth, registers them (`gscan.registration.pairwise`) and
weighs the pose of a two-frame capture, which no other edge vouches for, against the object's turns
(`gscan.registration.turns.lone_edge_turn`). T_tgt_src maps source-camera points into the target camera."""
from __future__ import annotations

import time

from gscan.features import FeatureParams, extract_features
from gscan.io.camera import RGBDFrame
from gscan.registration.dense import DenseGeometry
from gscan.registration.pairwise import PairResult, RegisterParams, frame_cloud, register_features
from gscan.registration.turns import lone_edge_turn


def register_frames(frame_s: RGBDFrame, frame_t: RGBDFrame, params: RegisterParams | None = None, *,
                    feature_params: FeatureParams | None = None, use_masks: bool = False,
                    icp_stride: int = 2, alone: bool = True) -> PairResult:
    """Register two RGB-D frames: keypoints and depth samples of both, then `register_features` (ICP on their
    clouds when params.icp); with `alone`, an accepted pose is then weighed against the object's turns.

    Args:
        frame_s, frame_t: the source and target frames.
        params: matcher, pose and acceptance parameters (default RegisterParams()).
        feature_params: the keypoints extracted (default FeatureParams()).
        use_masks: keypoints and ICP clouds inside the frames' masks only (whole frames by default).
        icp_stride: pixel stride of the ICP clouds.
        alone: the pair is the only evidence placing one frame against the other (a two-frame capture): no cycle
            of further edges can catch a pose turned about the object, so the edge is refused ("ambiguous shape:
            the only edge placing its frame ...", `gscan.registration.turns.lone_edge_turn`) when a turn of the
            object (half; on masked frames, quarter too) survives the depth and texture checks as well. False: the
            pose is one edge of a sequence, judged with the others.

    Returns:
        PairResult as `register_features`; T_tgt_src [4 x 4] maps source-camera points into the target camera.
        timings_ms["features"] is the extraction time.
    """
    params = params if params is not None else RegisterParams()
    fp = feature_params if feature_params is not None else FeatureParams()
    ms = frame_s.mask if use_masks else None
    mt = frame_t.mask if use_masks else None
    t0 = time.perf_counter()
    fs = extract_features(frame_s, fp, mask=ms)
    ft = extract_features(frame_t, fp, mask=mt)
    t_feat = (time.perf_counter() - t0) * 1e3
    clouds = (frame_cloud(frame_s, icp_stride, ms), frame_cloud(frame_t, icp_stride, mt)) if params.icp else None
    dense = (DenseGeometry.from_depth(frame_s.depth, frame_s.intrinsics, ms, image=frame_s.color),
             DenseGeometry.from_depth(frame_t.depth, frame_t.intrinsics, mt, image=frame_t.color))
    out = register_features(fs, ft, params, clouds, dense, alone=alone)
    out.timings_ms["features"] = t_feat
    if alone and out.accepted:
        t0 = time.perf_counter()
        why = lone_edge_turn(fs, ft, dense[0], dense[1], out, params, fp.auto_min_keypoints)
        out.timings_ms["turns"] = (time.perf_counter() - t0) * 1e3
        if why is not None:
            out.accepted, out.reason = False, why
    return out
