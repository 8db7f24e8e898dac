"""`PoseNode`: the templates' poses on ROS 2 topics (docs/ros2.md).

Subscriptions (topic names are parameters, `Ros2Params`): a colour image, a depth image registered to it, and the
colour camera's CameraInfo. Colour and depth are paired by stamp (`Pairer`) on the executor's thread; the newest
pair waits in a one-frame slot (`LatestSlot`) for the worker thread, which runs each template's `Tracker` (a full
estimate when the object is lost, tracking while it is found) and publishes, stamped with the colour image's
header:

- `~/<template>/pose` (geometry_msgs/PoseStamped): T_cam_obj, only when the estimator accepted a pose
- `~/<template>/poses` (geometry_msgs/PoseArray): the accepted poses of the frame (the tracker's one pose, or
  none; with the parameter `instances`, every instance `Estimator.estimate_all` finds, best score first)
- `~/markers` (visualization_msgs/MarkerArray): each template's mesh at its pose (DELETE when lost)
- `~/status` (std_msgs/String): one JSON object per frame (`FrameStatus`)

Input the node cannot use (a wrong encoding or size, a CameraInfo without focal length, depth before any
CameraInfo) is logged once per topic and cause; the frame gets a status with the error and the node runs on.
"""
from __future__ import annotations

import json
import logging
import re
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import rclpy
from geometry_msgs.msg import Point, Pose, PoseArray, PoseStamped
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import ColorRGBA, Header, String
from visualization_msgs.msg import Marker, MarkerArray

from gscan.errors import InputError
from gscan.estimate.estimator import Estimator
from gscan.estimate.settings import DEFAULT_PARAMS, EstimateParams
from gscan.estimate.track import Tracker, TrackParams
from gscan.geometry.mesh import MeshData
from gscan.io.camera import Intrinsics
from gscan.ros2.inputs import InputProblem, LatestSlot, Pair, Pairer, camera_intrinsics, pose_fields, rgbd_frame
from gscan.ros2.inputs import stamp_ns as msg_stamp_ns
from gscan.ros2.settings import Ros2Params
from gscan.settings import setting_fields, validate

log = logging.getLogger(__name__)

NODE_NAME = "gscan"
_NAME = re.compile(r"[^A-Za-z0-9_]")


def topic_name(path: Path) -> str:
    """A template's name in topic names: its file stem, characters other than letters, digits and _ as _, and a
    leading digit or _ prefixed with t (a ROS name token starts with a letter)."""
    name = _NAME.sub("_", path.stem) or "t"
    return name if name[0].isalpha() else f"t{name}"


@dataclass
class TemplateTrack:
    """One template the node follows: its topic name, tracker and marker mesh (object frame)."""

    name: str
    path: Path
    tracker: Tracker
    mesh: MeshData | None


def load_templates(paths: list[Path], estimate: EstimateParams = DEFAULT_PARAMS,
                   track: TrackParams = TrackParams()) -> list[TemplateTrack]:
    """The trackers of `paths` (InputError naming the file for a template that cannot be read, or two templates
    that would publish on one topic)."""
    from gscan.template.db import TemplateDB

    out: list[TemplateTrack] = []
    for path in paths:
        name = topic_name(path)
        if any(t.name == name for t in out):
            raise InputError(path, f"another template already publishes as '{name}' (rename one of the files)")
        with TemplateDB.open(path) as db:
            mesh = db.mesh()
        out.append(TemplateTrack(name, path, Tracker(Estimator.from_path(path, estimate), track), mesh))
    return out


def marker_points(mesh: MeshData, max_triangles: int) -> tuple[list[Point], list[ColorRGBA]]:
    """A TRIANGLE_LIST marker's points and colours (object frame) of `mesh`, simplified to at most
    `max_triangles` triangles (open3d's quadric decimation)."""
    mesh = mesh.simplified(max_triangles)
    V, F, C = mesh.vertices, mesh.triangles, mesh.vertex_colors
    corners = F.reshape(-1)
    points = [Point(x=float(p[0]), y=float(p[1]), z=float(p[2])) for p in V[corners]]
    colors = [] if C is None else [ColorRGBA(r=c[0] / 255.0, g=c[1] / 255.0, b=c[2] / 255.0, a=1.0)
                                   for c in C[corners].astype(float)]
    return points, colors


def _pose_msg(T: np.ndarray) -> Pose:
    (x, y, z), (qx, qy, qz, qw) = pose_fields(T)
    p = Pose()
    p.position.x, p.position.y, p.position.z = x, y, z
    p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w = qx, qy, qz, qw
    return p


def declare_params(node: Node) -> Ros2Params:
    """Declare `Ros2Params`' fields as the node's read-only parameters (defaults from the class) and validate the
    values given (`--ros-args -p name:=value`); InputError naming the parameter for a bad one."""
    values: dict[str, Any] = {}
    for name, default, about in setting_fields(Ros2Params()):
        desc = ParameterDescriptor(description=about, read_only=True, dynamic_typing=True)
        values[name] = node.declare_parameter(name, default, desc).value
    return validate(Ros2Params, values, None, what="ROS parameter")


class PoseNode(Node):
    """The gscan node (module docstring). `close()` stops its worker thread."""

    def __init__(self, templates: list[TemplateTrack], *, context: Any = None, cli_args: list[str] | None = None,
                 parameter_overrides: list[Any] | None = None, name: str = NODE_NAME):
        super().__init__(name, context=context, cli_args=cli_args, parameter_overrides=parameter_overrides)
        self.params = p = declare_params(self)
        self.templates = templates
        self._pairer = Pairer(round(p.sync_tolerance * 1e9), p.queue)
        self._slot = LatestSlot()
        self._info: Intrinsics | None = None
        self._info_key: tuple | None = None
        self._info_problem: InputProblem | None = None
        self.problems: dict[tuple[str, str], int] = {}  # (topic, reason) -> times seen
        self.received = {"color": 0, "depth": 0, "camera_info": 0}
        self.pairs = self.processed = 0
        self.refused = 0  # paired frames the node could not use (bad input, an internal error): a status with `error`
        self.with_pose = {t.name: 0 for t in templates}
        self.cpu_step_s = 0.0  # CPU time of the trackers' steps (the worker thread's)
        self.cpu_frame_s = 0.0  # CPU time of the worker for whole frames (conversion, steps, publishing)
        self.latency_ms: list[float] = []  # image stamp -> pose publication, per processed frame
        sensor = QoSProfile(depth=p.queue, history=HistoryPolicy.KEEP_LAST,
                            reliability=ReliabilityPolicy.BEST_EFFORT if p.best_effort else ReliabilityPolicy.RELIABLE)
        self.create_subscription(Image, p.color_topic, lambda m: self._on_image("color", m), sensor)
        self.create_subscription(Image, p.depth_topic, lambda m: self._on_image("depth", m), sensor)
        self.create_subscription(CameraInfo, p.camera_info_topic, self._on_info, sensor)
        out = QoSProfile(depth=10, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE)
        self._pose_pub = {t.name: self.create_publisher(PoseStamped, f"~/{t.name}/pose", out) for t in templates}
        self._array_pub = {t.name: self.create_publisher(PoseArray, f"~/{t.name}/poses", out) for t in templates}
        self._marker_pub = self.create_publisher(MarkerArray, "~/markers", out)
        self._status_pub = self.create_publisher(String, "~/status", out)
        self._markers = {t.name: self._marker(i, t) for i, t in enumerate(templates)}
        self._worker = threading.Thread(target=self._work, name="gscan-ros2-worker", daemon=True)
        self._worker.start()

    # ------------------------------------------------------------------------------------- inputs (executor)

    def _on_image(self, stream: str, msg: Image) -> None:
        self.received[stream] += 1
        pair = self._pairer.add(stream, msg, time.monotonic())
        if pair is not None:
            self.pairs += 1
            self._slot.put(pair)

    def _on_info(self, msg: CameraInfo) -> None:
        self.received["camera_info"] += 1
        key = (tuple(msg.k), int(msg.width), int(msg.height), tuple(msg.d))
        if key == self._info_key:  # a camera publishes the same calibration with every frame
            return
        self._info_key = key
        try:
            self._info, self._info_problem = camera_intrinsics(msg, self.params.camera_info_topic), None
        except InputProblem as e:
            self._info, self._info_problem = None, e
            self._problem(e)

    def _problem(self, e: InputProblem) -> None:
        """Log an unusable input once per topic and cause."""
        key = (e.topic, e.reason)
        self.problems[key] = self.problems.get(key, 0) + 1
        if self.problems[key] == 1:
            text = f"{e} (logged once; the node keeps running)"
            log.warning("%s", text)
            self.get_logger().warning(text)

    # ------------------------------------------------------------------------------------- the worker

    @property
    def dropped(self) -> int:
        """Paired frames replaced by a newer one before the worker took them."""
        return self._slot.dropped

    @property
    def unpaired(self) -> int:
        """Images dropped without a partner within the sync tolerance."""
        return self._pairer.unpaired

    def wait_idle(self, timeout_s: float) -> bool:
        """Wait until every paired frame was processed or dropped; False after timeout_s."""
        return self._slot.wait_idle(timeout_s)

    def close(self) -> None:
        """Stop the worker (after the frame in hand) and destroy the node."""
        self._slot.close()
        self._worker.join()
        self.destroy_node()

    def _work(self) -> None:
        while (pair := self._slot.take()) is not None:
            try:
                self._process(pair)
            except InputError as e:  # a frame the template's estimator refuses (its size, say)
                problem = InputProblem(self.params.color_topic, e.reason)
                self._problem(problem)
                self._publish_status(pair, {"error": str(problem)}, 0.0, 0.0)
            except Exception as e:  # an internal error in one frame: logged, the node stays up
                log.exception("frame %s: internal error", msg_stamp_ns(pair.color))
                self._publish_status(pair, {"error": f"internal error: {e.__class__.__name__}: {e}"}, 0.0, 0.0)
            finally:
                self._slot.done()

    def _process(self, pair: Pair) -> None:
        t0, c0 = time.perf_counter(), time.thread_time()
        p = self.params
        try:
            if self._info_problem is not None:
                raise self._info_problem
            if self._info is None:
                raise InputProblem(p.camera_info_topic, f"no CameraInfo received yet: the images of {p.color_topic} "
                                   f"and {p.depth_topic} cannot be used without it")
            frame = rgbd_frame(pair.color, pair.depth, self._info, p.depth_scale, p.color_topic, p.depth_topic)
        except InputProblem as e:
            self._problem(e)
            self._publish_status(pair, {"error": str(e)}, time.perf_counter() - t0, time.thread_time() - c0)
            return
        header = Header(stamp=pair.color.header.stamp, frame_id=p.frame_id or pair.color.header.frame_id)
        objects: dict[str, dict] = {}
        markers = MarkerArray()
        for t in self.templates:
            s0, sc0 = time.perf_counter(), time.thread_time()
            step = t.tracker.step(frame)
            step_cpu = time.thread_time() - sc0
            self.cpu_step_s += step_cpu
            res = step.result
            objects[t.name] = {"status": step.status, "reason": res.reason, "score": round(float(res.score), 4),
                               "method": res.method, "ms": round((time.perf_counter() - s0) * 1e3, 2),
                               "cpu_ms": round(step_cpu * 1e3, 2)}
            array = PoseArray(header=header)
            marker = self._markers[t.name]
            marker.header = header
            if p.instances:  # every instance: each result passed the estimator's verification
                found = t.tracker.est.estimate_all(frame).results
                array.poses = [_pose_msg(r.T_cam_obj) for r in found if r.T_cam_obj is not None]
                objects[t.name]["instances"] = len(array.poses)
            if res.T_cam_obj is not None:  # only a pose the estimator accepted is published
                pose = _pose_msg(res.T_cam_obj)
                self._pose_pub[t.name].publish(PoseStamped(header=header, pose=pose))
                if not p.instances:
                    array.poses = [pose]
                marker.pose, marker.action = pose, Marker.ADD
                self.with_pose[t.name] += 1
            else:
                marker.action = Marker.DELETE
            self._array_pub[t.name].publish(array)
            markers.markers.append(marker)
        self._marker_pub.publish(markers)
        self.processed += 1
        self._publish_status(pair, {"objects": objects}, time.perf_counter() - t0, time.thread_time() - c0)

    def _publish_status(self, pair: Pair, body: dict, wall_s: float, cpu_s: float) -> None:
        """The frame's `~/status` JSON: stamp, frame id, latency (image stamp to now, ROS time), the time from
        pairing to now, the worker's wall and CPU time, the running drop counts, then `body`."""
        now_ns = self.get_clock().now().nanoseconds
        stamp = msg_stamp_ns(pair.color)
        latency_ms = (now_ns - stamp) / 1e6
        self.cpu_frame_s += cpu_s
        if "error" in body:
            self.refused += 1
        if "objects" in body:
            self.latency_ms.append(latency_ms)
        status = {"stamp_ns": stamp, "frame_id": pair.color.header.frame_id, "latency_ms": round(latency_ms, 2),
                  "queued_ms": round((time.monotonic() - pair.received_s) * 1e3 - wall_s * 1e3, 2),
                  "ms": round(wall_s * 1e3, 2), "cpu_ms": round(cpu_s * 1e3, 2), "dropped": self.dropped,
                  "unpaired": self.unpaired, **body}
        self._status_pub.publish(String(data=json.dumps(status)))

    def _marker(self, i: int, t: TemplateTrack) -> Marker:
        """The template's marker, its points built once (a frame sets its header, pose and action)."""
        m = Marker(ns=t.name, id=i)
        m.scale.x = m.scale.y = m.scale.z = 1.0
        m.color = ColorRGBA(r=0.2, g=0.8, b=0.3, a=1.0)
        m.frame_locked = False
        if t.mesh is not None and len(t.mesh.triangles):
            m.type = Marker.TRIANGLE_LIST
            m.points, m.colors = marker_points(t.mesh, self.params.marker_triangles)
        else:  # a template without a mesh: its model points
            m.type = Marker.POINTS
            m.scale.x = m.scale.y = 0.003
            pts = t.tracker.est.model.samples[:: max(1, len(t.tracker.est.model.samples) // 2000)]
            m.points = [Point(x=float(q[0]), y=float(q[1]), z=float(q[2])) for q in pts]
        return m

    def summary(self) -> dict:
        """Counts of the run so far (the CLI's last lines, `--json`)."""
        lat = np.array(self.latency_ms) if self.latency_ms else np.zeros(1)
        return {"received": dict(self.received), "pairs": self.pairs, "processed": self.processed,
                "refused": self.refused, "dropped": self.dropped, "unpaired": self.unpaired,
                "with_pose": dict(self.with_pose),
                "latency_ms": {"median": float(np.median(lat)), "p90": float(np.percentile(lat, 90))},
                "problems": [f"topic {topic}: {reason} ({n}x)" for (topic, reason), n in self.problems.items()]}


def init_context(args: list[str] | None = None, domain_id: int | None = None, signals: bool = True) -> Any:
    """A new rclpy Context, initialised with the ROS arguments `args` (`--ros-args ...`) and, when given, its own
    DDS domain; signals: whether rclpy installs its Ctrl+C and SIGTERM handlers (False: the caller handles
    them); InputError when rcl refuses the arguments."""
    from rclpy.signals import SignalHandlerOptions

    ctx = rclpy.Context()
    try:
        rclpy.init(args=args, context=ctx, domain_id=domain_id,
                   signal_handler_options=None if signals else SignalHandlerOptions.NO)
    except Exception as e:  # noqa: BLE001 - rclpy's RCLError (a private module): bad ROS arguments, params file
        why = " ".join(str(e).split()).removeprefix("failed to initialize rcl: ").split(". Error:")[0]
        raise InputError(None, f"ROS arguments: {why}") from None
    return ctx
