"""FoundationPose model-free reference views (the `--ref_view_dir` of its `bundlesdf/run_nerf.py`).

Matched against NVlabs/FoundationPose `bundlesdf/run_nerf.py::run_one_ob(base_dir, ...)`, which for
`base_dir = f'{ref_view_dir}/ob_{ob_id:07d}'` does:

    yaml.safe_load(open(f'{base_dir}/select_frames.yml'))          # loaded, content not used
    color_files = sorted(glob.glob(f'{base_dir}/rgb/*.png'))
    K = np.loadtxt(f'{base_dir}/K.txt')                               # one 3x3 K for all views
    rgb   = imageio.imread(color_file)                                # RGB
    depth = cv2.imread(color_file.replace('rgb', 'depth_enhanced'), -1) / 1e3   # uint16 mm -> m
    mask  = cv2.imread(color_file.replace('rgb', 'mask'), -1)         # used as a boolean mask
    cam_in_ob = np.loadtxt(color_file.replace('rgb', 'cam_in_ob').replace('.png', '.txt')).reshape(4, 4)

and `run_neural_object_field` right-multiplies `cam_in_ob` by `glcam_in_cvcam`, so `cam_in_ob` is the
OpenCV camera's pose in the object frame: gscan's `T_obj_cam`. The reconstructed mesh is written to
`{base_dir}/model/model.obj`, which `datareader.py` (`get_reconstructed_mesh`) loads; gscan writes its
own template mesh there (vertex colours, metres, closed: `template_mesh`), so FoundationPose can run without
retraining.

`depth_enhanced/` holds the stored depth as captured (no hole filling).
Written: `ob_0000001/{rgb,depth_enhanced,mask,cam_in_ob}/NNNNNNN.*`, `K.txt`, `select_frames.yml`
(YAML list of the exported gscan view names, in file order), `model/model.obj` (when there is a mesh).
Views: registered keyframes with colour, depth and a mask (or a mesh, whose ray-cast silhouette is
then the mask), all with the first exported view's intrinsics (others are skipped with a warning).
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import yaml

from gscan.errors import InputError
from gscan.exporters.common import MeshRaycaster, imwrite, posed_views, template_mesh
from gscan.template.codec import depth_to_mm_u16
from gscan.template.db import TemplateDB

log = logging.getLogger(__name__)

OB_DIR = "ob_0000001"


def write_foundationpose(db: TemplateDB, out: Path, close: bool = True) -> int:
    """Write the reference-view folder `out/ob_0000001/`; returns the number of views written. `close`: the
    model's holes closed (`template_mesh`)."""
    mesh = template_mesh(db, close)
    views = [v for v in posed_views(db, need_images=True) if v.keyframe]
    if not views:
        raise InputError(db.path, "no registered keyframe with colour and depth to export")
    intr = views[0].intrinsics
    kept = []
    for v in views:
        if v.intrinsics != intr:
            log.warning("view %s has other intrinsics than %s (FoundationPose takes one K): skipped", v.name,
                        views[0].name)
        elif v.mask is None and mesh is None:
            log.warning("view %s has no object mask and the template no mesh: skipped", v.name)
        else:
            kept.append(v)
    if not kept:
        raise InputError(db.path, "FoundationPose export needs object masks or a mesh; the template has neither")
    caster = MeshRaycaster(mesh) if mesh is not None and any(v.mask is None for v in kept) else None
    ob = out / OB_DIR
    for sub in ("rgb", "depth_enhanced", "mask", "cam_in_ob"):
        (ob / sub).mkdir(parents=True)
    for i, v in enumerate(kept):
        stem = f"{i:07d}"
        assert v.T_obj_cam is not None and v.color is not None and v.depth is not None  # posed_views
        if v.mask is not None:
            mask = v.mask
        else:
            assert caster is not None  # a view is kept with a mask, or with the mesh to render one
            mask = caster.depth(v.intrinsics, v.T_obj_cam) > 0
        imwrite(ob / "rgb" / f"{stem}.png", v.color, rgb=True)
        imwrite(ob / "depth_enhanced" / f"{stem}.png", depth_to_mm_u16(v.depth))
        imwrite(ob / "mask" / f"{stem}.png", np.where(mask, 255, 0).astype(np.uint8))
        np.savetxt(ob / "cam_in_ob" / f"{stem}.txt", v.T_obj_cam, fmt="%.17g")
    np.savetxt(ob / "K.txt", intr.K, fmt="%.17g")
    (ob / "select_frames.yml").write_text(yaml.safe_dump([v.name for v in kept], allow_unicode=True),
                                          encoding="utf-8")
    if mesh is not None:
        import trimesh

        from gscan.exporters.mesh import to_trimesh

        (ob / "model").mkdir()
        text = trimesh.exchange.obj.export_obj(to_trimesh(mesh), include_color=True, include_normals=True,
                                               include_texture=False)
        (ob / "model" / "model.obj").write_text(text, encoding="utf-8")
    else:
        log.warning("%s has no mesh: no model/model.obj (FoundationPose's run_nerf.py can build one)", db.path)
    return len(kept)
