"""Rendered views for the recording and capture tests: colour from one camera, depth from the same or another.

Views orbit a shared mesh resting on a textured table (as `gscan.synth.render_capture` renders a static
capture). For unaligned depth the depth camera sits at `T_color_depth` from the colour camera (depth points
map into the colour camera by it) and is rendered from there with its own intrinsics.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gscan.geometry.transforms import transform_points
from gscan.io.camera import Intrinsics
from gscan.synth import SynthScene, default_distance, load_textured_mesh, orbit_poses, rest_on_table, write_capture
from gscan.synth.recordings import RecordingFrame, depth_to_raw

MESH = "Crayola_Bonus_64_Crayons"
K_COLOR = Intrinsics(307.5, 307.5, 159.5, 119.5, 320, 240)
K_DEPTH = Intrinsics(290.0, 291.0, 163.0, 117.0, 320, 240)  # the depth camera of the unaligned recordings
T0_NS = 1_700_000_000_000_000_000
PERIOD_NS = 33_333_333  # 30 fps


def T_depth_offset() -> np.ndarray:
    """T_color_depth of the unaligned recordings: the depth camera 5 cm to the colour camera's left, 1.5 cm
    up, turned 2 degrees about y (a stereo module beside an RGB sensor)."""
    a = np.radians(2.0)
    T = np.eye(4)
    T[:3, :3] = [[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]]
    T[:3, 3] = [0.05, 0.015, 0.0]
    return T


@dataclass
class Views:
    """colors [H x W x 3] RGB and depths (m) of the colour camera, the depth camera's depths (m; None when depth
    was not rendered apart), T_cam_obj (colour camera, ground truth) and the colour camera's RenderedFrames."""

    colors: list[np.ndarray]
    depths: list[np.ndarray]
    offset_depths: list[np.ndarray] | None
    T_cam_obj: list[np.ndarray]
    rendered: list

    def frames(self, unaligned: bool = False, period_ns: int = PERIOD_NS, depth_units: float = 0.001,
               color: bool = True) -> list[RecordingFrame]:
        """Recording frames: colour with the colour camera's depth, or with the depth camera's (unaligned)."""
        depths = self.offset_depths if unaligned else self.depths
        assert depths is not None
        return [RecordingFrame(c if color else None, depth_to_raw(d, depth_units), T0_NS + i * period_ns)
                for i, (c, d) in enumerate(zip(self.colors, depths, strict=True))]

    def write_folder(self, out: Path) -> Path:
        """The aligned capture (colour camera depth) as a capture folder without masks."""
        write_capture(out, self.rendered, K_COLOR, write_masks=False)
        return out


def render_views(meshes_dir: Path, n: int, of_ring: int | None = None, seed: int = 0, elevation: float = 40.0,
                 T_color_depth: np.ndarray | None = None, depth_intr: Intrinsics = K_DEPTH,
                 clean: bool = False) -> Views:
    """n views: the first n of `of_ring` (default n) evenly spaced around one ring at `elevation` degrees, and
    with T_color_depth the depth camera's view of each. clean: depth without noise (depth_clean)."""
    mesh = load_textured_mesh(meshes_dir / MESH / "model_0.obj")
    T_world_obj = rest_on_table(mesh)
    scene = SynthScene([(mesh, T_world_obj)], seed=seed)
    center = transform_points(T_world_obj, mesh.center[None])[0]
    cams = orbit_poses(center, default_distance(mesh, K_COLOR), [elevation], of_ring or n)[:n]
    colors, depths, offset, gts, rendered = [], [], [], [], []
    for i, T_wc in enumerate(cams):
        f = scene.render(T_wc, K_COLOR, rng=np.random.default_rng([seed, i]))
        rendered.append(f)
        colors.append(f.color)
        depths.append(f.depth_clean if clean else f.depth)
        gts.append(f.T_cam_obj)
        if T_color_depth is not None:
            fd = scene.render(T_wc @ T_color_depth, depth_intr, rng=np.random.default_rng([seed, i, 1]))
            offset.append(fd.depth_clean if clean else fd.depth)
    return Views(colors, depths, offset if T_color_depth is not None else None, gts, rendered)


def playback(bag: Path) -> tuple[list[tuple[np.ndarray, np.ndarray]], dict]:
    """Every frameset pyrealsense2's playback device returns for a recording (.bag or .db3; no alignment) and its
    stream parameters: depth scale, T_color_depth, the colour and depth rs2_intrinsics, and "numbers": each
    frameset's (colour, depth) frame numbers."""
    import pyrealsense2 as rs

    cfg = rs.config()
    cfg.enable_device_from_file(str(bag), repeat_playback=False)
    pipe = rs.pipeline()
    cfg.resolve(rs.pipeline_wrapper(pipe)).get_device().as_playback().set_real_time(False)
    prof = pipe.start(cfg)
    try:
        dp = prof.get_stream(rs.stream.depth).as_video_stream_profile()
        cp = prof.get_stream(rs.stream.color).as_video_stream_profile()
        ex = dp.get_extrinsics_to(cp)
        T = np.eye(4)
        T[:3, :3] = np.asarray(ex.rotation).reshape(3, 3).T  # rs2_extrinsics rotation is column-major
        T[:3, 3] = ex.translation
        info = {"scale": prof.get_device().first_depth_sensor().get_depth_scale(), "T_color_depth": T,
                "color": cp.get_intrinsics(), "depth": dp.get_intrinsics()}
        frames, info["numbers"] = [], []
        while True:
            ok, fs = pipe.try_wait_for_frames(2000)
            if not ok:
                break
            cf, df = fs.get_color_frame(), fs.get_depth_frame()
            frames.append((np.asanyarray(cf.get_data()).copy(), np.asanyarray(df.get_data()).copy()))
            info["numbers"].append((cf.get_frame_number(), df.get_frame_number()))
    finally:
        pipe.stop()
    return frames, info


def same_rs_intrinsics(rs_intr, intr: Intrinsics) -> bool:
    return (rs_intr.width, rs_intr.height) == (intr.width, intr.height) and np.allclose(
        [rs_intr.fx, rs_intr.fy, rs_intr.ppx, rs_intr.ppy], [intr.fx, intr.fy, intr.cx, intr.cy], atol=1e-4)
