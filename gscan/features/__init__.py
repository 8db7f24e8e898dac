"""Keypoints and descriptors of RGB-D frames, lifted to 3D with the frame's depth.

- keypoints: `extract_features(frame, params) -> Features` (SIFT / RootSIFT / ORB, OpenCV), in a mask
  (`extract_features_in_mask`), detection alone (`detect -> Detection`), `descriptor_distances`, `FeatureParams`
  (the `features` settings section)
"""
from gscan.features.keypoints import (
    DESCRIPTOR_KINDS,
    KINDS,
    OBJECT_FEATURES,
    Detection,
    FeatureParams,
    Features,
    descriptor_distances,
    detect,
    empty_features,
    extract_features,
    extract_features_in_mask,
    metric_of,
)

__all__ = ["DESCRIPTOR_KINDS", "KINDS", "OBJECT_FEATURES", "Detection", "FeatureParams", "Features",
           "descriptor_distances", "detect", "empty_features", "extract_features", "extract_features_in_mask",
           "metric_of"]
