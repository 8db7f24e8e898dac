"""Benchmark of the ROS 2 node (`gscan ros2`, gscan.ros2): the middleware's share of a frame's time.

The bundled sample's capture (gscan.demo.SAMPLES / "capture": 30 frames of the box, the camera moving around it,
ground truth) is replayed by a driver node in this process at --rates Hz (each image stamped when it is sent) to a
`PoseNode` following the box's template (rendered from its mesh, `template_from_mesh`, 16 views), over Fast DDS
on the loopback interface, in a DDS domain of its own. Per rate:

- latency: the image's stamp to the pose's publication (the status' `latency_ms`), median and p90, and the
  median wall time of the worker per frame, of `Tracker.step` in it, and of a frame's wait for the worker;
- CPU per processed frame: the whole process while the frames are replayed and processed (the driver's
  publishing, DDS, pairing, the node's worker), then `Tracker.step` alone: a fresh tracker in the same process on
  the frames the node processed, in its order, nothing else running; the middleware's share is
  1 - step alone / process (the driver's publishing, a camera driver's work in a real system, is counted in it).
  Also the worker thread's own CPU (time.thread_time: the estimator's helper threads are not in it);
- frames: sent, paired, processed, dropped because the node was busy (it keeps only the newest frame), and poses
  within 1 deg and 5 mm of the ground truth among those published.

    python bench/ros2.py                 # 15 and 30 Hz, the capture's 30 frames twice
    python bench/ros2.py --rates 5 15 30 --loops 3
Raw results go to --json (bench/out/ros2.json).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from gscan.threads import one_blas_thread  # noqa: E402

one_blas_thread()  # as the command line does before numpy loads

from gscan.demo import SAMPLES  # noqa: E402
from gscan.geometry.transforms import make_T, pose_error  # noqa: E402
from gscan.io import open_sequence  # noqa: E402


def replay(template: Path, rate_hz: float, loops: int, domain: int) -> dict:
    import rclpy
    from geometry_msgs.msg import PoseStamped
    from rclpy.executors import SingleThreadedExecutor
    from scipy.spatial.transform import Rotation
    from sensor_msgs.msg import CameraInfo, Image
    from std_msgs.msg import String

    from gscan.ros2.node import PoseNode, init_context, load_templates

    seq = open_sequence(SAMPLES / "capture")
    frames = [seq[n] for n in seq.names]
    gts = [seq.gt_T_cam_obj[n] for n in seq.names]
    ctx = init_context(None, domain)
    node = PoseNode(load_templates([template]), context=ctx)
    drv = rclpy.create_node("bench_driver", context=ctx)
    p = node.params
    pub_c, pub_d = drv.create_publisher(Image, p.color_topic, 5), drv.create_publisher(Image, p.depth_topic, 5)
    pub_i = drv.create_publisher(CameraInfo, p.camera_info_topic, 5)
    status: list[dict] = []
    poses: dict[int, PoseStamped] = {}
    drv.create_subscription(String, "/gscan/status", lambda m: status.append(json.loads(m.data)), 100)
    drv.create_subscription(PoseStamped, "/gscan/box/pose", lambda m: poses.__setitem__(
        m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec, m), 100)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    ex.add_node(drv)
    stop = threading.Event()

    def spin() -> None:
        while not stop.is_set():
            ex.spin_once(timeout_sec=0.02)

    th = threading.Thread(target=spin, daemon=True)
    th.start()
    while any(x.get_subscription_count() == 0 for x in (pub_c, pub_d, pub_i)):
        time.sleep(0.02)

    def image(a: np.ndarray, enc: str, t_ns: int) -> Image:
        m = Image()
        m.header.stamp.sec, m.header.stamp.nanosec = divmod(t_ns, 1_000_000_000)
        m.header.frame_id = "camera_color_optical_frame"
        m.height, m.width = a.shape[:2]
        m.encoding, m.step, m.data = enc, a.strides[0], a.tobytes()
        return m

    intr = frames[0].intrinsics
    info = CameraInfo(width=intr.width, height=intr.height, k=[float(x) for x in intr.K.ravel()])
    raw = [(np.ascontiguousarray(f.color), np.round(f.depth / 0.001).astype(np.uint16)) for f in frames]
    sent: dict[int, int] = {}  # stamp -> frame index
    cpu0 = time.process_time()
    t_start = time.monotonic()
    for k in range(loops * len(frames)):
        next_t = t_start + k / rate_hz
        time.sleep(max(0.0, next_t - time.monotonic()))
        t_ns = time.time_ns()
        sent[t_ns] = k % len(frames)
        info.header.stamp.sec, info.header.stamp.nanosec = divmod(t_ns, 1_000_000_000)
        pub_i.publish(info)
        pub_d.publish(image(raw[k % len(frames)][1], "16UC1", t_ns))
        pub_c.publish(image(raw[k % len(frames)][0], "rgb8", t_ns))
    end = time.monotonic() + 10
    while node.pairs < len(sent) and time.monotonic() < end:
        time.sleep(0.02)
    node.wait_idle(60)
    time.sleep(0.3)
    cpu = time.process_time() - cpu0
    stop.set()
    th.join()
    ex.shutdown()
    n = node.processed
    good = 0
    for stamp, msg in poses.items():
        q, t = msg.pose.orientation, msg.pose.position
        T = make_T(Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix(), [t.x, t.y, t.z])
        rot, trans = pose_error(T, gts[sent[stamp]])
        good += rot < 1.0 and trans < 0.005
    done = [s for s in status if "objects" in s]
    lat = np.array([s["latency_ms"] for s in done])
    # Tracker.step alone: a fresh tracker on the frames the node processed, in its order, nothing else running
    from gscan.estimate import Estimator, Tracker

    tracker = Tracker(Estimator.from_path(template))
    order = [sent[s["stamp_ns"]] for s in done]
    b_cpu0, b_wall = time.process_time(), []
    for i in order:
        w0 = time.perf_counter()
        tracker.step(frames[i])
        b_wall.append(time.perf_counter() - w0)
    b_cpu = time.process_time() - b_cpu0
    out = {"rate_hz": rate_hz, "sent": len(sent), "paired": node.pairs, "processed": n, "dropped": node.dropped,
           "unpaired": node.unpaired, "poses": len(poses), "poses_within_1deg_5mm": good,
           "latency_ms": {"median": float(np.median(lat)), "p90": float(np.percentile(lat, 90))},
           "wall_ms_median": {"worker": float(np.median([s["ms"] for s in done])),
                              "tracker_step": float(np.median([s["objects"]["box"]["ms"] for s in done])),
                              "waiting": float(np.median([s["queued_ms"] for s in done]))},
           "cpu_ms_per_frame": {"process": 1e3 * cpu / n, "worker_thread": 1e3 * node.cpu_frame_s / n,
                                "tracker_step_in_node_thread": 1e3 * node.cpu_step_s / n,
                                "tracker_step_alone": 1e3 * b_cpu / n},
           "wall_ms_median_alone": float(1e3 * np.median(b_wall)), "statuses": len(status)}
    out["wall_ms_median"]["tracker_step_alone"] = out.pop("wall_ms_median_alone")
    out["middleware_share"] = 1 - b_cpu / cpu
    node.close()
    drv.destroy_node()
    rclpy.try_shutdown(context=ctx)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rates", type=float, nargs="+", default=[15.0, 30.0])
    ap.add_argument("--loops", type=int, default=2, help="times the 30 frames are sent per rate")
    ap.add_argument("--json", type=Path, default=ROOT / "bench" / "out" / "ros2.json")
    args = ap.parse_args()
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    from gscan.scanning.cad import template_from_mesh

    with tempfile.TemporaryDirectory() as tmp:
        template = Path(tmp) / "box.gscan"
        template_from_mesh(SAMPLES / "object" / "box.obj", template, n_views=16)
        results = []
        for i, rate in enumerate(args.rates):
            r = replay(template, rate, args.loops, domain=150 + (os.getpid() + i) % 50)
            results.append(r)
            c, w = r["cpu_ms_per_frame"], r["wall_ms_median"]
            print(f"{rate:5.1f} Hz: sent {r['sent']}, processed {r['processed']}, dropped {r['dropped']} "
                  f"(unpaired {r['unpaired']}); poses {r['poses']} ({r['poses_within_1deg_5mm']} within 1 deg / 5 mm); "
                  f"latency median {r['latency_ms']['median']:.0f} ms, p90 {r['latency_ms']['p90']:.0f} ms (wall: "
                  f"worker {w['worker']:.0f} ms, Tracker.step {w['tracker_step']:.0f} ms, "
                  f"waiting {w['waiting']:.0f} ms; Tracker.step alone {w['tracker_step_alone']:.0f} ms); "
                  f"CPU per processed frame: process {c['process']:.0f} ms, Tracker.step alone "
                  f"{c['tracker_step_alone']:.0f} ms (middleware share {100 * r['middleware_share']:.0f}%)", flush=True)
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(results, indent=1) + "\n", encoding="utf-8")


if __name__ == "__main__":
    main()
