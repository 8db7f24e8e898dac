"""Camera paths, object placement on the table, and writing synthetic captures to disk.

Capture layout (README, "Input layouts"): rgb/NNNNNN.png|jpg, depth/NNNNNN.png (uint16 mm), masks/NNNNNN.png (0/255),
cam_K.txt (3x3), annotated_poses/NNNNNN.txt (4x4 T_cam_obj, metres).
"""
from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np

from gscan.geometry.transforms import look_at, make_T, rotvec_to_R, transform_points
from gscan.io.camera import Intrinsics
from gscan.synth.mesh import TexturedMesh, box_mesh
from gscan.synth.render import DEFAULT_INTRINSICS, DEFAULT_LIGHT_DIR, Gloss, RenderedFrame, SynthScene
from gscan.synth.textures import procedural_box_texture

log = logging.getLogger(__name__)


def orbit_poses(center: np.ndarray, radius: float, elevations_deg: list[float] | tuple[float, ...],
                n_per_ring: int, up: tuple[float, float, float] = (0.0, 0.0, 1.0),
                azimuth0_deg: float = 0.0) -> list[np.ndarray]:
    """T_world_cam [4 x 4] of cameras on rings around `center` [3], looking at it, image "up" along `up`.

    Ring i (elevation elevations_deg[i] above the plane normal to `up`) holds n_per_ring cameras at
    equal azimuth steps, rotated by half a step against the previous ring. Ordered ring by ring.
    """
    center = np.asarray(center, dtype=np.float64).reshape(3)
    up_v = np.asarray(up, dtype=np.float64)
    up_v = up_v / np.linalg.norm(up_v)
    a = np.cross(up_v, [1.0, 0.0, 0.0] if abs(up_v[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(up_v, a)
    if np.allclose(up_v, [0, 0, 1]):
        a, b = np.array([1.0, 0, 0]), np.array([0, 1.0, 0])
    poses = []
    for i, el in enumerate(elevations_deg):
        e = np.radians(el)
        for j in range(n_per_ring):
            az = np.radians(azimuth0_deg + 360.0 * (j + 0.5 * (i % 2)) / n_per_ring)
            d = np.cos(e) * (np.cos(az) * a + np.sin(az) * b) + np.sin(e) * up_v
            poses.append(look_at(center + radius * d, center, up_v))
    return poses


def rest_on_table(mesh: TexturedMesh, R_world_obj: np.ndarray | None = None,
                  xy: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """T_world_obj placing `mesh` (rotated by R_world_obj) with its lowest point on z = 0 and its
    bounding-box centre above `xy`."""
    R = np.eye(3) if R_world_obj is None else np.asarray(R_world_obj, dtype=np.float64)
    v = mesh.vertices @ R.T
    lo, hi = v.min(0), v.max(0)
    t = np.array([xy[0] - 0.5 * (lo[0] + hi[0]), xy[1] - 0.5 * (lo[1] + hi[1]), -lo[2]])
    return make_T(R, t)


def view_on_table(mesh: TexturedMesh, yaw: float, azimuth_deg: float, elevation_deg: float, distance: float,
                  scene_seed: int = 0, noise_seed: int | list[int] = 0) -> RenderedFrame:
    """`mesh` resting on the table (`rest_on_table`) turned by `yaw` (rad) about the vertical, seen from `distance`
    (m) at `azimuth_deg` and `elevation_deg` towards its bounding-box centre (`DEFAULT_INTRINSICS`); the table's
    texture seeded by scene_seed, the depth noise by noise_seed."""
    T_world_obj = rest_on_table(mesh, rotvec_to_R(np.array([0.0, 0.0, yaw])))
    c = transform_points(T_world_obj, mesh.center[None])[0]
    el, az = np.radians(elevation_deg), np.radians(azimuth_deg)
    eye = c + distance * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    return SynthScene([(mesh, T_world_obj)], seed=scene_seed).render(look_at(eye, c), DEFAULT_INTRINSICS,
                                                                     rng=np.random.default_rng(noise_seed))


def turntable_poses(T_world_obj: np.ndarray, mesh: TexturedMesh, n: int, total_deg: float = 360.0) -> list[np.ndarray]:
    """n poses of an object spinning about the vertical axis through its bounding-box centre (step total/n)."""
    c = transform_points(T_world_obj, mesh.center[None])[0]
    out = []
    for i in range(n):
        R = rotvec_to_R(np.array([0.0, 0.0, np.radians(total_deg * i / n)]))
        T_spin = make_T(R, c - R @ c)
        out.append(T_spin @ T_world_obj)
    return out


def default_distance(mesh: TexturedMesh, intr: Intrinsics = DEFAULT_INTRINSICS, fill: float = 0.4) -> float:
    """Camera distance (m) at which the mesh's bounding sphere spans `fill` of the image width."""
    return float(mesh.radius * intr.fx / (0.5 * fill * intr.width))


def footprint_radius(mesh: TexturedMesh, T_world_obj: np.ndarray) -> tuple[np.ndarray, float]:
    """(centre [2], radius) of a circle in the table plane holding the placed mesh's footprint."""
    v = transform_points(T_world_obj, mesh.vertices)[:, :2]
    c = 0.5 * (v.min(0) + v.max(0))
    return c, float(np.linalg.norm(v - c, axis=1).max())


def place_distractors(target: TexturedMesh, T_world_target: np.ndarray, distractors: list[TexturedMesh],
                      rng: np.random.Generator, gap: float = 0.02, max_tries: int = 200) -> list[np.ndarray]:
    """T_world_obj of each distractor resting on the table around the target, footprints not overlapping."""
    placed = [footprint_radius(target, T_world_target)]
    c0 = placed[0][0]
    poses = []
    for m in distractors:
        r = float(np.linalg.norm(m.extent[:2]) / 2)
        for _ in range(max_tries):
            ang = rng.uniform(0, 2 * np.pi)
            dist = placed[0][1] + r + gap + rng.uniform(0.0, 0.08)
            xy = c0 + dist * np.array([np.cos(ang), np.sin(ang)])
            if all(np.linalg.norm(xy - c) > rc + r + gap for c, rc in placed):
                break
        else:
            raise ValueError(f"cannot place distractor {m.name} without overlap after {max_tries} tries")
        R = rotvec_to_R(np.array([0.0, 0.0, rng.uniform(0, 2 * np.pi)]))
        T = rest_on_table(m, R, (float(xy[0]), float(xy[1])))
        placed.append(footprint_radius(m, T))
        poses.append(T)
    return poses


def write_capture(out_dir: str | Path, frames: list[RenderedFrame], intr: Intrinsics,
                  names: list[str] | None = None, write_masks: bool = True, jpeg: bool = False,
                  jpeg_quality: int = 92) -> Path:
    """Write frames in the capture layout (see module docstring). Depth is rounded to whole millimetres."""
    out = Path(out_dir)
    names = [f"{i:06d}" for i in range(len(frames))] if names is None else list(names)
    if len(names) != len(frames):
        raise ValueError(f"{len(names)} names for {len(frames)} frames")
    subdirs = ["rgb", "depth", "annotated_poses"] + (["masks"] if write_masks else [])
    for d in subdirs:
        (out / d).mkdir(parents=True, exist_ok=True)
    np.savetxt(out / "cam_K.txt", intr.K, fmt="%.10g")
    for name, f in zip(names, frames, strict=True):
        if f.color.shape[:2] != (intr.height, intr.width):
            raise ValueError(f"frame {name} is {f.color.shape[1]}x{f.color.shape[0]}, "
                             f"intrinsics {intr.width}x{intr.height}")
        bgr = cv2.cvtColor(f.color, cv2.COLOR_RGB2BGR)
        ok = (cv2.imwrite(str(out / "rgb" / f"{name}.jpg"), bgr, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
              if jpeg else cv2.imwrite(str(out / "rgb" / f"{name}.png"), bgr))
        mm = np.clip(np.rint(f.depth.astype(np.float64) * 1000.0), 0, 65535).astype(np.uint16)
        ok &= cv2.imwrite(str(out / "depth" / f"{name}.png"), mm)
        if write_masks:
            ok &= cv2.imwrite(str(out / "masks" / f"{name}.png"), f.mask.astype(np.uint8) * 255)
        if not ok:
            raise OSError(f"cannot write frame {name} under {out}")
        np.savetxt(out / "annotated_poses" / f"{name}.txt", f.T_cam_obj, fmt="%.10g")
    log.info("wrote %d frames to %s", len(frames), out)
    return out


def render_capture(mesh: TexturedMesh, out_dir: str | Path | None, n_views: int, mode: str = "static",
                   intr: Intrinsics = DEFAULT_INTRINSICS, seed: int = 0, distractors: int = 0,
                   distractor_meshes: list[TexturedMesh] | None = None, distance: float | None = None,
                   elevations_deg: tuple[float, ...] = (30.0, 55.0), table_kind: str = "newspaper",
                   noise: bool = True, shadows: bool = True, jpeg: bool = False, write_masks: bool = True,
                   R_world_obj: np.ndarray | None = None, table: bool = True,
                   wall_y: float | None = None, gloss: Gloss | None = None,
                   light_dir: tuple[float, float, float] = DEFAULT_LIGHT_DIR,
                   view_angles_deg: list[tuple[float, float]] | None = None) -> list[RenderedFrame]:
    """Render (and, when out_dir is given, write) a capture of `mesh` resting on a textured table.

    mode "static": object fixed, cameras on orbit rings at `elevations_deg` (views spread evenly over
    the rings) looking at the object centre. mode "turntable": one static camera at elevations_deg[0],
    the object spins 360 degrees about the vertical axis through its centre over the n_views frames.
    distance defaults to `default_distance` (object ~40% of the frame). Distractors are
    `distractor_meshes` or procedural boxes, placed around the target without overlap.
    R_world_obj turns the object before it is put on the table; table=False renders it floating
    over an empty background; wall_y adds a textured back wall in the plane y = wall_y. gloss makes the
    target (or the objects it names) glossy (`Gloss`); light_dir is the direction towards the light (world).
    view_angles_deg (static mode): the cameras' own (elevation, azimuth) pairs in degrees, one per view,
    instead of the rings (n_views must match).
    """
    if mode not in ("static", "turntable"):
        raise ValueError(f"mode must be 'static' or 'turntable', got {mode!r}")
    if n_views < 1:
        raise ValueError("n_views must be >= 1")
    if view_angles_deg is not None and (mode != "static" or len(view_angles_deg) != n_views):
        raise ValueError("view_angles_deg: one (elevation, azimuth) per view, in static mode")
    rng = np.random.default_rng([seed, 0xCA9])
    T_world_obj = rest_on_table(mesh, R_world_obj)
    if distractor_meshes is None:
        distractor_meshes = [box_mesh(rng.uniform(0.05, 0.12, 3),
                                      procedural_box_texture(seed * 100 + 17 + i, (512, 768)), name=f"distractor_{i}")
                             for i in range(distractors)]
    else:
        distractor_meshes = list(distractor_meshes)[:distractors]
    d_poses = place_distractors(mesh, T_world_obj, distractor_meshes, rng)
    scene = SynthScene([(mesh, T_world_obj)] + list(zip(distractor_meshes, d_poses, strict=True)), seed=seed,
                       table_kind=table_kind, shadows=shadows, table=table, wall_y=wall_y, gloss=gloss,
                       light_dir=light_dir)
    center = transform_points(T_world_obj, mesh.center[None])[0]
    dist = default_distance(mesh, intr) if distance is None else float(distance)
    frames = []
    if mode == "static":
        n_rings = len(elevations_deg)
        per = int(np.ceil(n_views / n_rings))
        cams = (orbit_poses(center, dist, elevations_deg, per)[:n_views] if view_angles_deg is None  # ring by ring
                else [orbit_poses(center, dist, [el], 1, azimuth0_deg=az)[0] for el, az in view_angles_deg])
        for i, T_wc in enumerate(cams):
            frames.append(scene.render(T_wc, intr, noise=noise, rng=np.random.default_rng([seed, i])))
    else:
        T_wc = orbit_poses(center, dist, [elevations_deg[0]], 1, azimuth0_deg=-90.0)[0]
        for i, T_wo in enumerate(turntable_poses(T_world_obj, mesh, n_views)):
            frames.append(scene.render(T_wc, intr, noise=noise, rng=np.random.default_rng([seed, i]),
                                       T_world_obj_override=T_wo))
    if out_dir is not None:
        write_capture(out_dir, frames, intr, write_masks=write_masks, jpeg=jpeg)
    return frames

