"""The ROS 2 node's settings: each field is a ROS parameter of the node (`--ros-args -p name:=value`), its default
here and nowhere else."""
from __future__ import annotations

import itertools
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

from pydantic import Field

from gscan.settings import SETTINGS

_CAMERA = "/camera/camera"  # realsense2_camera's default namespace and node name


@dataclass(frozen=True)
class Ros2Params:
    """The node's ROS parameters (docs/ros2.md). Read once when the node starts."""

    color_topic: Annotated[str, Field(description="colour image topic (sensor_msgs/Image: rgb8, bgr8, rgba8, bgra8, "
                                      "yuyv, uyvy, mono8)", min_length=1)] = f"{_CAMERA}/color/image_raw"
    depth_topic: Annotated[str, Field(description="depth image topic, registered to the colour image (16UC1 / mono16 "
                                      "raw units, or 32FC1 metres)", min_length=1)] = (
        f"{_CAMERA}/aligned_depth_to_color/image_raw")
    camera_info_topic: Annotated[str, Field(description="the colour camera's sensor_msgs/CameraInfo",
                                            min_length=1)] = f"{_CAMERA}/color/camera_info"
    depth_scale: Annotated[float, Field(description="metres per raw unit of 16-bit depth (32FC1 depth is in metres)",
                                        gt=0)] = 0.001
    frame_id: Annotated[str, Field(description="frame of the published poses (empty: the colour image's "
                                   "header.frame_id)")] = ""
    sync_tolerance: Annotated[float, Field(description="s, the largest stamp difference of a colour and a depth image "
                                           "paired into one frame", ge=0)] = 0.02
    queue: Annotated[int, Field(description="images kept per stream while waiting for their partner (and the "
                                "subscriptions' history depth); older ones are dropped", ge=1, le=100)] = 5
    best_effort: Annotated[bool, Field(description="subscribe with best-effort reliability (sensor data QoS: "
                                       "matches reliable and best-effort publishers)")] = True
    marker_triangles: Annotated[int, Field(description="the mesh in the MarkerArray is simplified to at most this "
                                           "many triangles", ge=12)] = 3000
    instances: Annotated[bool, Field(description="~/<template>/poses holds every instance found in the frame "
                                     "(Estimator.estimate_all, beside the tracker: more CPU per frame) instead of "
                                     "the tracker's one pose")] = False
    __pydantic_config__ = SETTINGS


#: parameters every rclpy node has besides the node's own
BUILTIN_PARAMS = ("use_sim_time", "start_type_description_service")


def check_ros_args(args: list[str]) -> None:
    """Refuse `-p` / `--param` arguments (`--ros-args -p name:=value`) that are malformed or name no parameter of the
    node (`Ros2Params`' fields, `BUILTIN_PARAMS`, `qos_overrides.*`): a typo would otherwise be ignored silently.
    A `node:name:=value` rule for another node is left alone. InputError naming the argument (or the
    `--params-file` that is not a file)."""
    from dataclasses import fields

    from gscan.errors import InputError, not_a_file

    known = {f.name for f in fields(Ros2Params)} | set(BUILTIN_PARAMS)
    for flag, rule in itertools.pairwise(args):
        if flag == "--params-file" and not Path(rule).is_file():  # rcl would log its own line before refusing it
            raise not_a_file(rule, "ROS parameters file")
        if flag not in ("-p", "--param"):
            continue
        name, sep, _ = rule.partition(":=")
        if not sep or not name:
            raise InputError(None, f"ROS argument {flag} {rule!r}: expected name:=value")
        node, _, name = name.rpartition(":")
        if node not in ("", "gscan") or name in known or name.startswith("qos_overrides."):
            continue
        raise InputError(None, f"ROS argument {flag} {rule!r}: the node has no parameter {name!r} (its "
                         f"parameters: {', '.join(sorted(known))})")
