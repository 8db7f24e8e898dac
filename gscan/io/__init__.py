"""RGB-D input: the camera model and frames, sequences in four folder layouts, single frames, odd depth
formats, pose files, and the checks of an output path.

    Intrinsics, RGBDFrame, load_intrinsics, backproject, point_cloud, project (camera)
    DepthCamera, load_depth_camera(intrinsics, T_color_depth=None): depth not registered to colour
    open_sequence(path, format="auto", intrinsics=None, depth_scale=None, obj_id=None, depth_camera=None) -> Sequence
    load_frame(color, depth, intrinsics, depth_scale=0.001, mask_path=None, name=None, depth_camera=None) -> RGBDFrame
    read_image_rgb / read_depth / read_mask / read_sun_depth / read_nyu_depth / read_ycbv_meta
    read_pose_file (JSON) / read_pose_txt / read_open3d_log -> rigid [4 x 4] poses

Bad input raises gscan.errors.InputError naming the offending file.
"""
from gscan.io.camera import (
    DepthCamera,
    Intrinsics,
    RGBDFrame,
    backproject,
    load_depth_camera,
    load_intrinsics,
    point_cloud,
    project,
)
from gscan.io.images import (
    DEPTH_RANGE_M,
    YcbvMeta,
    check_depth_range,
    check_depth_scale,
    load_frame,
    read_depth,
    read_depth_raw,
    read_image_rgb,
    read_mask,
    read_nyu_depth,
    read_sun_depth,
    read_ycbv_meta,
)
from gscan.io.layouts import FORMATS, FrameSpec, associate, detect_format, natural_key
from gscan.io.output import check_output_path, missing_folders, remove_empty_folders
from gscan.io.poses import check_rigid, read_open3d_log, read_pose_file, read_pose_txt
from gscan.io.sequence import Sequence, open_sequence

__all__ = [
    "DEPTH_RANGE_M", "FORMATS", "DepthCamera", "FrameSpec", "Intrinsics", "RGBDFrame", "Sequence", "YcbvMeta",
    "associate", "backproject", "check_depth_range", "check_depth_scale", "check_output_path", "check_rigid",
    "detect_format", "load_depth_camera", "load_frame", "load_intrinsics", "missing_folders", "natural_key",
    "open_sequence", "point_cloud", "project", "read_depth", "read_depth_raw", "read_image_rgb", "read_mask",
    "read_nyu_depth", "read_open3d_log", "read_pose_file", "read_pose_txt", "read_sun_depth", "read_ycbv_meta",
    "remove_empty_folders",
]
