"""Help texts that several commands' options share."""
from __future__ import annotations

DEPTH_INTRINSICS_HELP = ("depth not registered to colour: the depth camera's cam_K.txt or Open3D intrinsics JSON "
                         "(the depth is reprojected into the colour camera)")
DEPTH_TO_COLOR_HELP = ("with --depth-intrinsics: T_color_depth, the depth camera's pose in the colour camera "
                       "(4x4 text or JSON matrix, metres; default: the same centre and axes)")
JSON_HELP = "print one JSON object on stdout"
RECORDING_HELP = ("recording (RealSense .bag of SDK 2.57 and earlier, RealSense .db3 of SDK 2.58 and later, ROS 1 "
                  ".bag, rosbag2 .db3 / .mcap / folder; images raw or compressed: PNG, JPEG, compressedDepth, zstd)")
RS_PLAYBACK_HELP = ("play this RealSense recording (.bag, or the .db3 of SDK 2.58 and later) through pyrealsense2 "
                    "instead of a live camera")
ESTIMATE_CONFIG_HELP = "YAML configuration: the estimator's settings, its `estimate:` section (see `gscan config dump`)"
