"""Rendered captures written in BOP's scene layout, and a BOP dataset folder with model-free onboarding captures.

The BOP toolkit's dataset format (its docs/bop_datasets_format.md; millimetres, matrices row-major):

    DATASET/camera.json                          {cx, cy, fx, fy, width, height, depth_scale} (the sensor)
    DATASET/models/obj_OBJID.ply                 the object's mesh in millimetres, in its own (ground-truth) frame
    DATASET/onboarding_static/obj_OBJID_up/      the object upright: a BOP scene folder
    DATASET/onboarding_static/obj_OBJID_down/    the object upside down (or on its side), moved against the table
      rgb/IMID.png                               colour (IMID: the image id, 6 digits)
      depth/IMID.png                             uint16; raw * depth_scale = millimetres
      mask_visib/IMID_000000.png                 the object's visible pixels, 0/255 (only when asked for)
      scene_camera.json                          {im_id: {cam_K: [9 numbers, row-major], depth_scale}}
      scene_gt.json                              {im_id: [{obj_id, cam_R_m2c: [9], cam_t_m2c: [3] mm}]}

scene_gt holds T_cam_obj of the object in its mesh's frame, for evaluation: a model-free method reads the
images and camera only.
"""
from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from gscan.io.camera import Intrinsics
from gscan.synth.cases import two_sided_frames
from gscan.synth.mesh import TexturedMesh
from gscan.synth.render import DEFAULT_INTRINSICS, RenderedFrame

log = logging.getLogger(__name__)

#: raw depth * DEPTH_SCALE = millimetres: 0.1 mm steps, up to 6.5 m (what YCB-Video's depth uses)
DEPTH_SCALE = 0.1


@dataclass(frozen=True)
class BopOnboarding:
    """A written BOP dataset folder with one object's static onboarding captures. captures: capture name
    (`obj_XXXXXX_up`, `obj_XXXXXX_down`) -> its scene folder; frames: capture name -> its image names (`IMID`);
    model: the mesh in millimetres (None: not written)."""

    root: Path
    obj_id: int
    captures: dict[str, Path]
    frames: dict[str, list[str]]
    model: Path | None


def write_bop_scene(scene_dir: str | Path, frames: list[RenderedFrame], intr: Intrinsics, obj_id: int,
                    depth_scale: float = DEPTH_SCALE, masks: bool = False) -> list[str]:
    """Write rendered frames as a BOP scene folder (module docstring), the target of each frame annotated as
    object `obj_id`; returns the image names (IMID, ids from 0). ValueError: a depth that uint16 cannot hold at
    `depth_scale`, or a frame not of the intrinsics' size."""
    out = Path(scene_dir)
    if depth_scale <= 0:
        raise ValueError(f"depth_scale must be positive, got {depth_scale}")
    for d in ("rgb", "depth") + (("mask_visib",) if masks else ()):
        (out / d).mkdir(parents=True, exist_ok=True)
    cams: dict[str, dict] = {}
    gts: dict[str, list[dict]] = {}
    names = []
    for im_id, f in enumerate(frames):
        name = f"{im_id:06d}"
        if f.color.shape[:2] != (intr.height, intr.width):
            raise ValueError(f"frame {im_id} is {f.color.shape[1]}x{f.color.shape[0]}, "
                             f"intrinsics {intr.width}x{intr.height}")
        raw = np.rint(f.depth.astype(np.float64) * 1000.0 / depth_scale)
        if raw.max(initial=0) > 65535:
            raise ValueError(f"frame {im_id}: depth {f.depth.max():.2f} m does not fit uint16 at depth_scale "
                             f"{depth_scale} mm")
        ok = cv2.imwrite(str(out / "rgb" / f"{name}.png"), cv2.cvtColor(f.color, cv2.COLOR_RGB2BGR))
        ok &= cv2.imwrite(str(out / "depth" / f"{name}.png"), raw.astype(np.uint16))
        if masks:
            ok &= cv2.imwrite(str(out / "mask_visib" / f"{name}_000000.png"), f.mask.astype(np.uint8) * 255)
        if not ok:
            raise OSError(f"cannot write image {name} under {out}")
        cams[str(im_id)] = {"cam_K": intr.K.reshape(-1).tolist(), "depth_scale": depth_scale}
        T = np.asarray(f.T_cam_obj, dtype=np.float64)
        gts[str(im_id)] = [{"obj_id": int(obj_id), "cam_R_m2c": T[:3, :3].reshape(-1).tolist(),
                            "cam_t_m2c": (T[:3, 3] * 1000.0).tolist()}]
        names.append(name)
    (out / "scene_camera.json").write_text(json.dumps(cams, indent=1))
    (out / "scene_gt.json").write_text(json.dumps(gts, indent=1))
    log.info("wrote %d images of object %d to %s", len(frames), obj_id, out)
    return names


def write_model_ply(mesh: TexturedMesh, path: str | Path) -> Path:
    """The mesh in millimetres (binary PLY: vertices and triangles), as BOP's models/ holds it."""
    import trimesh

    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    tm = trimesh.Trimesh(mesh.vertices * 1000.0, mesh.triangles, process=False)
    tm.export(str(p), file_type="ply", encoding="binary")
    return p


def write_bop_onboarding(dataset_dir: str | Path, obj_id: int, mesh: TexturedMesh, n_views: int = 12,
                         upside_down: bool = True, elevations_deg: tuple[float, ...] = (30.0, 55.0),
                         table_kind: str = "newspaper", seed: int = 0, intr: Intrinsics = DEFAULT_INTRINSICS,
                         depth_scale: float = DEPTH_SCALE, masks: bool = False, model: bool = True,
                         ) -> BopOnboarding:
    """Render the two static onboarding captures of `mesh` as object `obj_id` of a BOP dataset folder: the
    captures of `gscan.synth.cases.two_sided_captures` (n_views each, the object upright, then upside down or on
    its side and turned against the table) as onboarding_static/obj_XXXXXX_up and _down, the dataset's
    camera.json and (model) models/obj_XXXXXX.ply. Other objects' captures already in the folder are kept."""
    if obj_id < 1:
        raise ValueError(f"BOP object ids start at 1, got {obj_id}")
    root = Path(dataset_dir)
    root.mkdir(parents=True, exist_ok=True)
    sides = two_sided_frames(mesh, n_views, upside_down, elevations_deg, table_kind, seed, intr)
    captures, frames = {}, {}
    for side, side_frames in zip(("up", "down"), sides, strict=True):
        name = f"obj_{obj_id:06d}_{side}"
        captures[name] = root / "onboarding_static" / name
        frames[name] = write_bop_scene(captures[name], side_frames, intr, obj_id, depth_scale, masks)
    cam = {"cx": intr.cx, "cy": intr.cy, "fx": intr.fx, "fy": intr.fy, "width": intr.width,
           "height": intr.height, "depth_scale": depth_scale}
    (root / "camera.json").write_text(json.dumps(cam, indent=1))
    ply = write_model_ply(mesh, root / "models" / f"obj_{obj_id:06d}.ply") if model else None
    return BopOnboarding(root, obj_id, captures, frames, ply)
