"""The ROS 2 node (gscan.ros2, `gscan ros2`) on a real ROS 2 graph in the test process: rclpy over Fast DDS, each
test in its own DDS domain on the loopback interface. A driver node plays the bundled sample's held-back frames
(gscan.demo.SAMPLES) to the node and checks the published poses against their ground truth."""
from __future__ import annotations

import dataclasses
import itertools
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from gscan.demo import SAMPLES
from gscan.evaluate.metrics import add
from gscan.geometry.transforms import pose_error
from gscan.io import open_sequence
from gscan.ros2.inputs import LatestSlot, Pair, Pairer

try:  # the wheels exist for CPython 3.11 on Linux (x86-64, aarch64) only; the test extra installs them there
    import rclpy
    from geometry_msgs.msg import PoseArray, PoseStamped
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import CameraInfo, Image
    from std_msgs.msg import String
    from visualization_msgs.msg import Marker, MarkerArray
    HAVE_RCLPY, WHY = True, ""
except ImportError as e:
    HAVE_RCLPY, WHY = False, str(e)
needs_rclpy = pytest.mark.skipif(not HAVE_RCLPY, reason="the ROS 2 wheels (gscan[ros2]: ros-rclpy, cp311 manylinux) "
                                 f"cannot be imported on this platform ({WHY})")

ROOT = Path(__file__).resolve().parents[1]
_domains = itertools.count()
# the demo's tolerance on the held-back frames (tests/test_demo.py): ADD under 5 mm, rotation under a degree
MAX_ADD_MM, MAX_ROT_DEG = 5.0, 1.0


def _domain() -> int:
    """A DDS domain of this test alone (parallel runs of the suite do not hear each other)."""
    return 1 + (os.getpid() * 7 + next(_domains)) % 200


@pytest.fixture(autouse=True)
def _loopback(monkeypatch):
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")  # Kilted's name for ROS_LOCALHOST_ONLY=1
    monkeypatch.setenv("ROS_LOCALHOST_ONLY", "1")


@pytest.fixture(scope="module")
def template(tmp_path_factory) -> Path:
    """The sample box's template from its mesh (the mesh's frame is the ground truth's object frame)."""
    from gscan.scanning.cad import template_from_mesh

    out = tmp_path_factory.mktemp("ros2") / "box.gscan"
    template_from_mesh(SAMPLES / "object" / "box.obj", out, n_views=8)  # 8 views find all 4 frames
    return out


@pytest.fixture(scope="module")
def heldout():
    return open_sequence(SAMPLES / "heldout")


# ------------------------------------------------------------------------------------------ without ROS


class _Msg:
    def __init__(self, t_ns: int):
        class _S:
            sec, nanosec = divmod(t_ns, 1_000_000_000)

        class _H:
            stamp = _S()

        self.header = _H()


def test_pairer_pairs_by_stamp_within_the_tolerance_and_keeps_a_bounded_queue():
    p = Pairer(tolerance_ns=10_000_000, queue=3)
    c0, d0 = _Msg(1_000_000_000), _Msg(1_004_000_000)
    assert p.add("color", c0, 0.0) is None
    pair = p.add("depth", d0, 0.0)
    assert pair is not None and pair.color is c0 and pair.depth is d0
    assert p.add("depth", _Msg(2_000_000_000), 0.0) is None  # 1 s from any colour: waits
    assert p.add("color", _Msg(2_050_000_000), 0.0) is None  # 50 ms off: no pair
    for i in range(5):  # colour images whose depth never comes: at most `queue` wait, the others are dropped
        assert p.add("color", _Msg(3_000_000_000 + i * 100_000_000), 0.0) is None
    assert len(p._waiting["color"]) == 3 and p.unpaired >= 3
    late = p.add("depth", _Msg(3_400_000_000), 0.0)
    assert late is not None and late.color.header.stamp.nanosec == 400_000_000
    assert not p._waiting["color"] and not p._waiting["depth"]  # everything older went with the pair


def test_latest_slot_drops_the_waiting_frame_for_a_newer_one():
    slot = LatestSlot()
    a, b = Pair(1, 1, 0.0), Pair(2, 2, 0.0)
    slot.put(a)
    slot.put(b)
    assert slot.dropped == 1 and slot.take(0) is b
    assert not slot.wait_idle(0.01)  # the worker holds b
    slot.done()
    assert slot.wait_idle(0.01) and slot.take(0.01) is None


def test_ros_arguments_are_checked_before_the_node_starts(tmp_path):
    from gscan.errors import InputError
    from gscan.ros2.settings import check_ros_args

    check_ros_args(["--ros-args", "-p", "depth_scale:=0.0001", "-p", "gscan:queue:=3", "-p", "camera:fps:=30",
                    "-p", "use_sim_time:=true", "-r", "__ns:=/robot", "--log-level", "debug"])
    with pytest.raises(InputError, match="'colr_topic:=/x': the node has no parameter 'colr_topic'"):
        check_ros_args(["--ros-args", "-p", "colr_topic:=/x"])
    with pytest.raises(InputError, match="expected name:=value"):
        check_ros_args(["--ros-args", "--param", "queue=3"])
    with pytest.raises(InputError, match="ROS parameters file"):
        check_ros_args(["--ros-args", "--params-file", str(tmp_path / "none.yaml")])


# ------------------------------------------------------------------------------------------ the graph


def _image(rgb_or_depth: np.ndarray, encoding: str, t_ns: int, frame_id: str = "camera_color_optical_frame"):
    msg = Image()
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(t_ns), 1_000_000_000)
    msg.header.frame_id = frame_id
    a = np.ascontiguousarray(rgb_or_depth)
    msg.height, msg.width = a.shape[:2]
    msg.encoding = encoding
    msg.step = a.strides[0]
    msg.data = a.tobytes()
    return msg


def _info(K: np.ndarray, w: int, h: int, t_ns: int):
    msg = CameraInfo()
    msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(int(t_ns), 1_000_000_000)
    msg.width, msg.height = w, h
    msg.k = [float(x) for x in K.ravel()]
    return msg


class Graph:
    """The node under test and a driver node (publishers of the camera's topics, subscribers of the node's) in one
    context, spun by a background thread."""

    def __init__(self, template: Path, **params):
        from rclpy.parameter import Parameter

        from gscan.ros2.node import PoseNode, init_context, load_templates
        from gscan.ros2.play import SETTLE_S

        self.ctx = init_context(None, _domain())
        overrides = [Parameter(k, value=v) for k, v in params.items()]
        self.node = PoseNode(load_templates([template]), context=self.ctx, parameter_overrides=overrides)
        p = self.node.params
        self.driver = rclpy.create_node("driver", context=self.ctx)
        self.color = self.driver.create_publisher(Image, p.color_topic, 5)
        self.depth = self.driver.create_publisher(Image, p.depth_topic, 5)
        self.info = self.driver.create_publisher(CameraInfo, p.camera_info_topic, 5)
        self.status: list[dict] = []
        self.poses: list[PoseStamped] = []
        self.arrays: list[PoseArray] = []
        self.markers: list[MarkerArray] = []
        self._cv = threading.Condition()
        ns = "/gscan"
        for kind, topic, store in ((PoseStamped, f"{ns}/box/pose", self.poses), (PoseArray, f"{ns}/box/poses",
                                   self.arrays), (MarkerArray, f"{ns}/markers", self.markers)):
            self.driver.create_subscription(kind, topic, lambda m, s=store: self._got(s, m), 50)
        self.driver.create_subscription(String, f"{ns}/status", lambda m: self._got(self.status, json.loads(m.data)),
                                        50)
        self.executor = SingleThreadedExecutor(context=self.ctx)
        self.executor.add_node(self.node)
        self.executor.add_node(self.driver)
        self._stop = threading.Event()
        self._spin = threading.Thread(target=self._run, daemon=True)
        self._spin.start()
        end = time.monotonic() + 10
        pubs = (self.color, self.depth, self.info)
        while any(p.get_subscription_count() == 0 for p in pubs) and time.monotonic() < end:
            time.sleep(0.02)
        assert all(p.get_subscription_count() for p in pubs), "the node's subscriptions were not discovered"
        time.sleep(SETTLE_S)  # discovery completes on both sides (gscan.ros2.play)

    def _run(self) -> None:
        while not self._stop.is_set():
            self.executor.spin_once(timeout_sec=0.05)

    def _got(self, store: list, msg) -> None:
        with self._cv:
            store.append(msg)
            self._cv.notify_all()

    def wait_status(self, n: int, timeout_s: float = 30.0) -> list[dict]:
        with self._cv:
            assert self._cv.wait_for(lambda: len(self.status) >= n, timeout_s), f"{len(self.status)} of {n} statuses"
        return self.status

    def send(self, frame, t_ns: int, info: bool = True, color_encoding: str = "rgb8", depth=None) -> None:
        if info:
            self.info.publish(_info(frame.intrinsics.K, frame.intrinsics.width, frame.intrinsics.height, t_ns))
            time.sleep(0.05)  # CameraInfo before its images, as a camera driver sends them
        raw = np.round(frame.depth / 0.001).astype(np.uint16) if depth is None else depth
        self.depth.publish(_image(raw, "16UC1", t_ns))
        self.color.publish(_image(frame.color, color_encoding, t_ns))

    def close(self) -> None:
        self._stop.set()
        self._spin.join()
        self.executor.shutdown()
        self.node.close()
        self.driver.destroy_node()
        rclpy.try_shutdown(context=self.ctx)


@pytest.fixture
def graph(template):
    graphs: list[Graph] = []

    def make(**params) -> Graph:
        graphs.append(Graph(template, **params))
        return graphs[-1]

    yield make
    for g in graphs:
        g.close()


@needs_rclpy
def test_node_publishes_the_sample_poses_within_the_demo_tolerance(graph, heldout, template):
    from scipy.spatial.transform import Rotation

    from gscan.estimate import Estimator
    from gscan.geometry.transforms import make_T

    g = graph()
    t0 = time.time_ns()
    stamps = []
    for i, name in enumerate(heldout.names):  # one frame at a time: none is dropped
        stamps.append(t0 + i * 100_000_000)
        g.send(heldout[name], stamps[-1])
        g.wait_status(i + 1)
    st = g.status
    assert [s["stamp_ns"] for s in st] == stamps  # every frame got its status, in order
    assert all(s["objects"]["box"]["status"] in ("found", "refound", "tracked") for s in st), st
    assert all(s["latency_ms"] > 0 and s["ms"] > 0 and s["dropped"] == 0 for s in st)
    time.sleep(0.2)
    assert len(g.poses) == len(g.arrays) == len(g.markers) == len(heldout.names)
    pts = Estimator.from_path(template).model_points
    for name, stamp, msg, arr in zip(heldout.names, stamps, g.poses, g.arrays, strict=True):
        assert msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec == stamp
        assert msg.header.frame_id == "camera_color_optical_frame"
        q, p = msg.pose.orientation, msg.pose.position
        T = make_T(Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix(), [p.x, p.y, p.z])
        T_gt = heldout.gt_T_cam_obj[name]
        rot, _ = pose_error(T, T_gt)
        assert rot < MAX_ROT_DEG and add(pts, T, T_gt) * 1000 < MAX_ADD_MM, (name, rot, add(pts, T, T_gt))
        assert len(arr.poses) == 1 and arr.poses[0].position.x == p.x
    m = g.markers[-1].markers[0]
    assert m.type == Marker.TRIANGLE_LIST and m.action == Marker.ADD and 0 < len(m.points) <= 3 * 3000
    assert m.pose.position.x == g.poses[-1].pose.position.x


@needs_rclpy
def test_instances_publishes_every_instance_estimate_all_finds(graph, heldout, template):
    """With `instances`, the PoseArray holds the poses `Estimator.estimate_all` finds in the frame (the sample's
    one box, at the truth), counted in the status; the PoseStamped is still the tracker's."""
    from gscan.estimate import Estimator

    g = graph(instances=True)
    est = Estimator.from_path(template)
    t0 = time.time_ns()
    for i, name in enumerate(heldout.names[:2]):
        g.send(heldout[name], t0 + i * 100_000_000)
        g.wait_status(i + 1)
    time.sleep(0.2)
    pts = est.model_points
    for name, st, arr in zip(heldout.names[:2], g.status, g.arrays, strict=True):
        want = [r.T_cam_obj for r in est.estimate_all(heldout[name]).results]
        assert st["objects"]["box"]["instances"] == len(arr.poses) == len(want) == 1, st
        p = arr.poses[0].position
        assert np.allclose([p.x, p.y, p.z], want[0][:3, 3], atol=1e-6)
        assert add(pts, want[0], heldout.gt_T_cam_obj[name]) * 1000 < MAX_ADD_MM
    assert len(g.poses) == 2


@needs_rclpy
def test_no_pose_is_published_for_a_frame_without_the_object(graph, heldout):
    import cv2

    g = graph()
    frame = heldout[heldout.names[2]]  # the frame with a distractor beside the box
    gone = cv2.dilate(frame.mask.astype(np.uint8), np.ones((15, 15), np.uint8)) > 0
    color, depth = frame.color.copy(), np.round(frame.depth / 0.001).astype(np.uint16)
    color[gone], depth[gone] = 128, 0  # the box taken out: grey, no depth; the table and the distractor stay
    g.send(dataclasses.replace(frame, color=color), 1_000_000_000, depth=depth)
    st = g.wait_status(1)[0]
    assert st["objects"]["box"]["status"] == "lost" and st["objects"]["box"]["reason"]
    time.sleep(0.3)
    assert g.poses == [] and [len(a.poses) for a in g.arrays] == [0]
    assert g.markers[0].markers[0].action == Marker.DELETE


@needs_rclpy
def test_bad_input_is_logged_once_per_cause_and_the_node_stays_up(graph, heldout, caplog):
    g = graph()
    p = g.node.params
    frame = heldout[heldout.names[0]]
    intr = frame.intrinsics
    # depth before any CameraInfo: twice, logged once
    g.send(frame, 1_000_000_000, info=False)
    g.wait_status(1)
    g.send(frame, 1_100_000_000, info=False)
    st = g.wait_status(2)
    assert all(p.camera_info_topic in s["error"] and "no CameraInfo" in s["error"] for s in st)
    # a CameraInfo with zero focal length
    K0 = intr.K.copy()
    K0[0, 0] = K0[1, 1] = 0.0
    g.info.publish(_info(K0, intr.width, intr.height, 1_200_000_000))
    time.sleep(0.1)
    g.send(frame, 1_200_000_000, info=False)
    st = g.wait_status(3)
    assert p.camera_info_topic in st[2]["error"] and "focal" in st[2]["error"]
    # a colour image in a depth encoding; a depth image of another size
    g.send(frame, 1_300_000_000, color_encoding="mono16")
    st = g.wait_status(4)
    assert p.color_topic in st[3]["error"] and "mono16" in st[3]["error"]
    g.send(frame, 1_400_000_000, depth=np.zeros((240, 320), np.uint16))
    st = g.wait_status(5)
    assert p.depth_topic in st[4]["error"] and "320x240" in st[4]["error"]
    # the node is still up: a good frame gets a pose
    g.send(frame, 1_500_000_000)
    st = g.wait_status(6)
    assert st[5]["objects"]["box"]["status"] == "found"
    warnings = [r.getMessage() for r in caplog.records if r.name == "gscan.ros2.node"]
    assert len(warnings) == 4 and sum("no CameraInfo" in w for w in warnings) == 1, warnings
    assert len(g.node.problems) == 4 and g.node.problems[(p.camera_info_topic, st[0]["error"].split(": ", 1)[1])] == 2


@needs_rclpy
def test_a_node_that_falls_behind_drops_old_frames(graph, heldout):
    g = graph(queue=2)
    frames = [heldout[n] for n in heldout.names]
    g.info.publish(_info(frames[0].intrinsics.K, 640, 480, 0))
    time.sleep(0.1)
    n = 12
    for i in range(n):  # much faster than the estimator: frames must be dropped, none may queue up
        f = frames[i % len(frames)]
        t = 1_000_000_000 + i * 10_000_000
        g.depth.publish(_image(np.round(f.depth / 0.001).astype(np.uint16), "16UC1", t))
        g.color.publish(_image(f.color, "rgb8", t))
        time.sleep(0.01)
    newest = 1_000_000_000 + (n - 1) * 10_000_000
    end = time.monotonic() + 30
    while not (g.status and g.status[-1]["stamp_ns"] == newest) and time.monotonic() < end:
        time.sleep(0.05)
    node = g.node
    assert node.wait_idle(1) and g.status[-1]["stamp_ns"] == newest  # the newest frame is always processed
    # frames are dropped (by the node while busy, or by the subscriptions' bounded history), never queued
    assert node.processed < n and node.dropped > 0 and node.processed + node.dropped == node.pairs <= n
    st = g.wait_status(node.processed)
    assert len(st) == node.processed and [s["stamp_ns"] for s in st] == sorted(s["stamp_ns"] for s in st)
    assert all(s["objects"]["box"]["status"] != "lost" for s in st)


@needs_rclpy
def test_the_marker_mesh_is_simplified_to_the_triangle_budget():
    import trimesh

    from gscan.geometry.mesh import MeshData
    from gscan.ros2.node import marker_points

    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.05)  # 5120 triangles
    colours = np.tile(np.array([[200, 10, 10]], np.uint8), (len(sphere.vertices), 1))
    mesh = MeshData(np.asarray(sphere.vertices), np.asarray(sphere.faces), colours)
    points, rgba = marker_points(mesh, 500)
    assert 0 < len(points) <= 3 * 500 and len(points) % 3 == 0 and len(rgba) == len(points)
    radii = np.linalg.norm([[p.x, p.y, p.z] for p in points], axis=1)
    assert np.all(np.abs(radii - 0.05) < 0.005)  # still the sphere
    assert abs(rgba[0].r - 200 / 255) < 0.02 and rgba[0].a == 1.0
    small, _ = marker_points(mesh, 6000)  # within the budget: every triangle as it is
    assert len(small) == 3 * len(sphere.faces)


# ------------------------------------------------------------------------------------------ --play, the CLI


def _recording(tmp_path: Path, heldout) -> Path:
    from gscan.synth.recordings import RecordingFrame, write_mcap

    frames = [RecordingFrame(f.color, np.round(f.depth / 0.001).astype(np.uint16), 1_700_000_000_000_000_000
                             + i * 500_000_000) for i, f in enumerate(heldout[n] for n in heldout.names)]
    return write_mcap(tmp_path / "sample.mcap", frames, heldout[heldout.names[0]].intrinsics, topics=("color",
                                                                                                       "aligned"))


@needs_rclpy
def test_play_feeds_a_recording_through_the_node(template, heldout, tmp_path, caplog):
    from gscan.ros2.node import load_templates
    from gscan.ros2.run import run

    path = _recording(tmp_path, heldout)
    out = run(load_templates([template]), play=path, domain_id=_domain())
    assert out["played"] == 4 and out["pairs"] == 4 and out["processed"] + out["dropped"] == 4, (out, caplog.text)
    assert out["with_pose"]["box"] == out["processed"] >= 2 and not out["problems"], out


def _cli(*args: str, env_extra: dict | None = None, pre: str = "pass") -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "ROS_DOMAIN_ID": str(_domain()),
           "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", **(env_extra or {})}
    code = f"import sys; {pre}; from gscan.cli import main; sys.argv = ['gscan', *sys.argv[1:]]; main()"
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, env=env, timeout=120)


@needs_rclpy
def test_cli_plays_a_recording(template, heldout, tmp_path):
    path = _recording(tmp_path, heldout)
    r = _cli("ros2", str(template), "--play", str(path), "--rate", "2", "--json", "--ros-args", "-p",
             "sync_tolerance:=0.005")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["played"] == 4 and out["with_pose"]["box"] == out["processed"] >= 1


@needs_rclpy
def test_cli_refuses_bad_input_in_one_line(template, tmp_path):
    r = _cli("ros2", str(template), "--play", str(tmp_path / "none.mcap"))
    assert r.returncode == 2 and r.stderr.strip().splitlines() == [f"error: {tmp_path / 'none.mcap'}: recording "
                                                                    "not found"]
    r = _cli("ros2", str(template), "--ros-args", "-p", "depth_scale:=-1.0")
    assert r.stderr.strip().splitlines() == ["error: invalid ROS parameter depth_scale: Input should be greater than 0"]
    assert r.returncode == 2


@needs_rclpy
def test_cli_refuses_a_recording_whose_depth_is_not_registered(template, heldout, tmp_path):
    from gscan.io.camera import DepthCamera
    from gscan.synth.recordings import RecordingFrame, write_mcap

    f = heldout[heldout.names[0]]
    T = np.eye(4)
    T[0, 3] = 0.05  # a depth camera 5 cm beside the colour camera: depth_to_color would be needed
    path = write_mcap(tmp_path / "unaligned.mcap", [RecordingFrame(f.color, np.round(f.depth / 0.001).astype(
        np.uint16), 1_700_000_000_000_000_000)], f.intrinsics, depth_camera=DepthCamera(f.intrinsics, T))
    r = _cli("ros2", str(template), "--play", str(path))
    assert r.returncode == 2 and r.stderr.startswith(f"error: {path}: depth "), r.stderr
    assert "not registered" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1


@needs_rclpy
def test_ctrl_c_stops_the_node_with_its_counts(template):
    import signal

    # PYTHONFAULTHANDLER: a node that does not stop is aborted and its threads' stacks come back in the failure
    env = {**os.environ, "PYTHONPATH": str(ROOT), "ROS_DOMAIN_ID": str(_domain()),
           "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "PYTHONFAULTHANDLER": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "gscan.cli", "ros2", str(template), "--json"], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = proc.stderr.readline()  # the ready line: the node is up
        assert "ROS 2 node /gscan follows box" in line, line + proc.stderr.read()
        proc.send_signal(signal.SIGINT)
        try:
            out, err = proc.communicate(timeout=90)  # the shutdown is slow on a busy machine
        except subprocess.TimeoutExpired:
            proc.send_signal(signal.SIGABRT)
            out, err = proc.communicate(timeout=30)
            pytest.fail(f"the node did not stop within 90 s of Ctrl+C; its threads then:\n{err[-6000:]}")
    finally:
        proc.kill()
    assert proc.returncode == 0, err
    summary = json.loads(out)
    assert summary["processed"] == 0 and summary["with_pose"] == {"box": 0}


def test_cli_names_the_extra_when_rclpy_is_missing(template):
    r = _cli("ros2", str(template), pre="sys.modules['rclpy'] = None")
    assert r.returncode == 2, r.stderr
    assert r.stderr.strip().splitlines() == [r.stderr.strip()] and "gscan[ros2]" in r.stderr
