"""Keypoints and descriptors of RGB-D frames, lifted to 3D with the frame's depth.

- keypoints: `extract_features(frame, params) -> Features` (SIFT / RootSIFT / ORB, OpenCV), in a mask
  (`extract_features_in_mask`), detection alone (`detect -> Detection`), `descriptor_distances`, `FeatureParams`
  (the `features` settings section)
- depth (`gscan.features.depth`): keypoints of the depth's shape (ISS +
  RootFPFH) for plain objects, and the rootsift+fpfh set joining them to the image's
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
