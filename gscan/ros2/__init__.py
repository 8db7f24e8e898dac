"""gscan as a ROS 2 node (`gscan ros2`, the optional extra `gscan[ros2]`: rclpy and the message packages as wheels).

- settings: `Ros2Params`, the node's ROS parameters and their defaults (RealSense's topic names)
- inputs: rclpy-free parts: image messages to arrays, CameraInfo checked, colour and depth paired by stamp, the
  newest pair handed to the worker (older ones dropped, counted)
- node: `PoseNode`, the subscriptions, one `Tracker` per template, the publishers
- play: `Player`, a rosbag2 / MCAP recording published onto the node's topics at its recorded pace

`require_rclpy()` raises a one-line GscanError naming the extra where rclpy cannot be imported.
"""
from __future__ import annotations

from gscan.errors import GscanError

EXTRA = "gscan[ros2]"


class MissingExtra(GscanError):
    """An optional dependency is not installed (the CLI exits 2 with this one line)."""


def require_rclpy() -> None:
    """Import rclpy and the message packages the node uses; MissingExtra naming the extra when they fail."""
    try:
        import geometry_msgs.msg  # noqa: F401
        import rclpy  # noqa: F401
        import sensor_msgs.msg  # noqa: F401
        import std_msgs.msg  # noqa: F401
        import visualization_msgs.msg  # noqa: F401
    except ImportError as e:  # the wheels missing, or built for another Python / platform
        why = " ".join(str(e).split())
        raise MissingExtra(f"the ROS 2 node needs rclpy and the ROS 2 message packages: pip install '{EXTRA}' "
                           f"(Python 3.11 on Linux x86-64 or aarch64) ({why})") from None
