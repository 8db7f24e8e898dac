"""`Player`: a ROS 2 recording (rosbag2 folder or `.db3`, `.mcap`) published onto the node's topics, so that the
node runs on a recording as on a camera (`gscan ros2 ... --play RECORDING`).

The recording's colour, depth and colour CameraInfo topics are found as `gscan track` finds them
(`gscan.io.recordings.ros.ros_setup`) and republished, as recorded (stamps and frame ids kept), on the topics the
node subscribes to, paced by their log times (`rate` times as fast). The depth must be registered to colour
(aligned_depth_to_color), as the node needs. The recorded bytes are CDR, ROS 2's own serialisation: they are
deserialised into rclpy messages without a copy of gscan's.
"""
from __future__ import annotations

import logging
import threading
import time
from pathlib import Path
from typing import Any

from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import CameraInfo, Image

from gscan.errors import InputError
from gscan.io.recordings.ros import camera_info_topic, ros_setup
from gscan.io.recordings.source import open_source
from gscan.ros2.settings import Ros2Params

log = logging.getLogger(__name__)

#: seconds between the subscriptions' discovery and the first message: a publisher that sees a subscription
#: matched may still be unknown to it for a moment, and what it sends then is lost
SETTLE_S = 0.5


class Player(Node):
    """Publishes a recording's images and CameraInfo on `params`' topics from a thread (`start`); `done` is set when
    the last message is out (or `stop` was called). InputError naming the file when the recording cannot be
    played: not found, unreadable, a ROS 1 bag, no colour / depth / CameraInfo, depth not registered to colour."""

    def __init__(self, path: Path, params: Ros2Params, *, rate: float = 1.0, context: Any = None):
        if rate <= 0:
            raise ValueError(f"rate must be > 0, not {rate}")
        src = open_source(Path(path))
        try:
            if src.wire != "cdr":
                raise InputError(path, "a ROS 1 bag cannot be played onto ROS 2 topics (convert it with "
                                 "`rosbags-convert`, or play a rosbag2 / MCAP recording)")
            setup = ros_setup(src)
            if not setup.registered:
                raise InputError(path, f"depth {setup.depth_topic} is not registered to colour {setup.color_topic}: "
                                 "the node needs depth aligned to colour (realsense2_camera's align_depth)")
        except BaseException:
            src.close()
            raise
        super().__init__("gscan_player", context=context)
        self.path = Path(path)
        self._src = src
        self.rate = rate
        qos = QoSProfile(depth=params.queue, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE)
        # recorded topic -> (message type, publisher on the node's topic)
        self._routes = {
            setup.color_topic: (Image, self.create_publisher(Image, params.color_topic, qos)),
            setup.depth_topic: (Image, self.create_publisher(Image, params.depth_topic, qos)),
            camera_info_topic(setup.color_topic): (CameraInfo,
                                                   self.create_publisher(CameraInfo, params.camera_info_topic, qos)),
        }
        self.color_topic, self.depth_topic = setup.color_topic, setup.depth_topic
        self.published = dict.fromkeys(self._routes, 0)
        self.done = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._play, name="gscan-ros2-player", daemon=True)

    def start(self, wait_subscribers_s: float = 10.0) -> None:
        """Start publishing once every topic has a subscriber (or after wait_subscribers_s)."""
        self._wait_subscribers = wait_subscribers_s
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()
        self._src.close()

    def _play(self) -> None:
        try:
            end = time.monotonic() + self._wait_subscribers
            while (any(pub.get_subscription_count() == 0 for _, pub in self._routes.values())
                   and time.monotonic() < end and not self._stop.is_set()):
                time.sleep(0.02)
            self._stop.wait(SETTLE_S)
            t0_rec: int | None = None
            t0 = time.monotonic()
            for topic, t_ns, data in self._src.messages(list(self._routes)):
                if self._stop.is_set():
                    break
                if t0_rec is None:
                    t0_rec = t_ns
                wait = t0 + (t_ns - t0_rec) / 1e9 / self.rate - time.monotonic()
                if wait > 0 and self._stop.wait(wait):
                    break
                kind, pub = self._routes[topic]
                pub.publish(deserialize_message(bytes(data), kind))
                self.published[topic] += 1
        except InputError as e:  # a damaged record: the frames before it were played
            log.warning("%s", e)
        finally:
            self.done.set()

    @property
    def frames(self) -> int:
        """Colour images published so far."""
        return self.published[self.color_topic]

    @property
    def depth_frames(self) -> int:
        """Depth images published so far."""
        return self.published[self.depth_topic]
