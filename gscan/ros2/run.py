"""`run`: the gscan node (and a recording's player) spun in this process until Ctrl+C or the recording's end."""
from __future__ import annotations

import signal
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import rclpy
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor

from gscan.ros2.node import PoseNode, TemplateTrack, init_context
from gscan.ros2.play import Player
from gscan.signals import stop_on

#: after a recording's last message: how long the node may take to receive what is still on its way (s)
ARRIVAL_S = 2.0


def run(tracks: list[TemplateTrack], ros_args: list[str] | None = None, play: Path | None = None,
        rate: float = 1.0, on_ready: Callable[[PoseNode, Player | None], None] | None = None,
        domain_id: int | None = None) -> dict:
    """Spin a `PoseNode` for `tracks` (ROS arguments `ros_args`: `--ros-args -p name:=value -r ...`) until the
    context shuts down or Ctrl+C, or, with `play`, until the recording was played and its last frame processed;
    returns the node's `summary()` (with `played`: the colour images the player published). InputError for a
    bad parameter value or a recording that cannot be played."""
    # Ctrl+C (and SIGTERM) set a flag the loop below reads between spins: an exception raised at any point inside
    # rclpy's calls could leave one of its locks held and the shutdown waiting on it
    ctx = init_context(["gscan", *(ros_args or [])], domain_id, signals=False)
    executor = SingleThreadedExecutor(context=ctx)
    with stop_on((signal.SIGINT, signal.SIGTERM)) as stop:
        try:
            return _spin(ctx, executor, tracks, play, rate, on_ready, stop)
        finally:
            executor.shutdown()
            rclpy.try_shutdown(context=ctx)


def _spin(ctx: Any, executor: SingleThreadedExecutor, tracks: list[TemplateTrack], play: Path | None,
          rate: float, on_ready: Callable[[PoseNode, Player | None], None] | None, stop: threading.Event) -> dict:
    """`run`'s node (and player) on `executor` until `stop`, the context's end or the recording's."""
    node: PoseNode | None = None
    player: Player | None = None
    try:
        node = PoseNode(tracks, context=ctx)
        executor.add_node(node)
        if play is not None:
            player = Player(play, node.params, rate=rate, context=ctx)
            executor.add_node(player)
            player.start()
        try:
            if on_ready is not None:
                on_ready(node, player)
            while ctx.ok() and not stop.is_set():
                executor.spin_once(timeout_sec=0.1)
                if player is not None and player.done.is_set():
                    end = time.monotonic() + ARRIVAL_S
                    while ((node.received["color"] < player.frames or node.received["depth"] < player.depth_frames)
                           and time.monotonic() < end and ctx.ok()):
                        executor.spin_once(timeout_sec=0.05)
                    while not node.wait_idle(0.1) and ctx.ok():
                        executor.spin_once(timeout_sec=0)
                    break
        except (KeyboardInterrupt, ExternalShutdownException):  # Ctrl+C: how a node is stopped, not an error
            pass
        out = node.summary()
        if player is not None:
            out["played"] = player.frames
        return out
    finally:
        if player is not None:
            player.stop()
            player.destroy_node()
        if node is not None:
            node.close()
