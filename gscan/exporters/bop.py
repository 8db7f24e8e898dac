"""BOP dataset export: the template's captured views as one test scene with ground truth.

Layout (BOP toolkit conventions, docs/bop_datasets_format.md; millimetres, row-major matrices):

    camera.json                       {cx, cy, fx, fy, width, height, depth_scale}
    models/obj_000001.ply             template mesh in mm with vertex normals and colours
    models/models_info.json           {"1": {diameter, min_x/y/z, size_x/y/z[, symmetries_discrete,
                                      symmetries_continuous]}} in mm
    models_eval/obj_000001.ply        the same mesh, models_info.json the same: the models the BOP toolkit's
    models_eval/models_info.json      scorer reads (BOP resamples its CAD models there for even vertex spacing;
                                      a TSDF mesh's vertices already lie about one voxel apart)
    test/000001/rgb/IIIIII.png        colour
    test/000001/depth/IIIIII.png      uint16, depth_scale 1.0 (raw * 1.0 = millimetres)
    test/000001/mask/IIIIII_000000.png, mask_visib/IIIIII_000000.png   0/255
    test/000001/scene_camera.json     {im_id: {cam_K, depth_scale, cam_R_w2c, cam_t_w2c}} (world = object)
    test/000001/scene_gt.json         {im_id: [{cam_R_m2c, cam_t_m2c, obj_id: 1}]}, T_cam_obj = inv(T_obj_cam)
    test/000001/scene_gt_info.json    {im_id: [{bbox_obj, bbox_visib, px_count_all, px_count_valid,
                                                px_count_visib, visib_fract}]}
    test_targets_bop19.json           [{im_id, inst_count: 1, obj_id: 1, scene_id: 1}] (evaluation targets)
    gscan_views.json                  {im_id: template view name} (gscan's own addition)
    bop_toolkit.patch                 registers the dataset as "gscan" in a checkout of the BOP toolkit (below)

The BOP toolkit knows datasets by name only: their object ids, image size and VSD delta are written in its
`bop_toolkit_lib/dataset_params.py` and `scripts/eval_bop19_pose.py`, with no other place to add one. The
export's `bop_toolkit.patch` adds dataset "gscan" there (object 1, symmetric if the template is, scene 1, the
views' image size, delta 15 mm): `git apply` it in the toolkit's checkout, make the export BOP_PATH/gscan and
name results `METHOD_gscan-test.csv` (docs/exports.md). Its context lines are the toolkit's as of 2026-06 (commit
cea62d6); `git apply` finds them where they moved and refuses a checkout where they changed.

Symmetries (the template's, `TemplateDB.symmetries`): those that hold in shape and texture, as BOP keeps them (its
potential symmetries by shape, less those the texture resolves: the BOP Challenge 2019 page, section 2.3 of Hodan
et al., "BOP Challenge 2020 on 6D Object Localization"); `symmetries_discrete` lists each turn as a row-major 4 x 4
`T_obj_obj'` flattened to 16 numbers, translation in mm, `symmetries_continuous` each axis of revolution as
{"axis": [3] unit, "offset": [3] mm, a point on it}, what `bop_toolkit_lib.misc.get_symmetry_transformations` reads.
A template without symmetries gets neither key (BOP's own asymmetric objects have none).

The mesh is closed into a watertight model (`close`, see `gscan.exporters.watertight`: the scan's mesh is
open where the support plane cut it), which is what BOP's renderers and scorers expect.

Masks and counts: with a mesh, `mask` is the mesh silhouette ray-cast from the view's pose and
`mask_visib` the silhouette pixels whose measured depth is missing or is not more than 15 mm in front
of the rendered depth (the BOP toolkit's "bop19" visibility rule, delta 15 mm, on depth rather than
distance along the ray; a measurement behind the model counts as visible), intersected with the view's stored
object mask when it has one; bbox_obj and px_count_all are clipped to the image (the toolkit renders
a larger canvas for objects that leave the image). Without a mesh both are the stored mask (views
without one are skipped).
px_count_valid counts silhouette pixels with measured depth; visib_fract = px_count_visib / px_count_all.
"""
from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from gscan.errors import InputError
from gscan.evaluate.metrics import VSD_DELTA_M, diameter
from gscan.exporters.common import MeshRaycaster, bbox_xywh, imwrite, posed_views, template_mesh
from gscan.geometry.symmetry import Symmetries
from gscan.geometry.transforms import inv_T
from gscan.template.codec import depth_to_mm_u16
from gscan.template.db import MeshData, TemplateDB

log = logging.getLogger(__name__)

SCENE_ID = 1
OBJ_ID = 1
DEPTH_SCALE = 1.0  # raw uint16 * DEPTH_SCALE = millimetres
VISIB_DELTA_MM = 15.0
TOOLKIT_DATASET = "gscan"  # the name bop_toolkit.patch gives the export in the BOP toolkit


def write_ply_mm(mesh: MeshData, path: Path) -> None:
    """Binary little-endian PLY in millimetres: x y z nx ny nz (float32) red green blue (uchar) and
    `vertex_indices` faces (list uchar int) — the properties `bop_toolkit_lib.inout.load_ply` reads."""
    from gscan.exporters.mesh import to_trimesh

    tm = to_trimesh(mesh)
    V = np.asarray(mesh.vertices, dtype=np.float64) * 1000.0
    N = np.asarray(tm.vertex_normals, dtype=np.float64)
    C = mesh.vertex_colors if mesh.vertex_colors is not None else np.full((len(V), 3), 255, np.uint8)
    vdt = np.dtype([(k, "<f4") for k in ("x", "y", "z", "nx", "ny", "nz")]
                   + [(k, "u1") for k in ("red", "green", "blue")])
    verts = np.empty(len(V), dtype=vdt)
    for i, k in enumerate(("x", "y", "z")):
        verts[k] = V[:, i]
        verts["n" + k] = N[:, i]
    for i, k in enumerate(("red", "green", "blue")):
        verts[k] = C[:, i]
    fdt = np.dtype([("n", "u1"), ("i", "<i4", (3,))])
    faces = np.empty(len(mesh.triangles), dtype=fdt)
    faces["n"] = 3
    faces["i"] = np.asarray(mesh.triangles, dtype=np.int64)
    header = ("ply\nformat binary_little_endian 1.0\ncomment gscan template mesh, millimetres\n"
              f"element vertex {len(V)}\n" + "".join(f"property float {k}\n" for k in ("x", "y", "z", "nx", "ny", "nz"))
              + "property uchar red\nproperty uchar green\nproperty uchar blue\n"
              f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n")
    path.write_bytes(header.encode("ascii") + verts.tobytes() + faces.tobytes())


def models_info(mesh: MeshData, symmetries: Symmetries | None = None) -> dict:
    """BOP models_info entry (mm): diameter (largest vertex distance), the axis-aligned box and the symmetries that
    hold in shape and texture (module docstring)."""
    V = np.asarray(mesh.vertices, dtype=np.float64) * 1000.0
    diam = diameter(V)
    lo, hi = V.min(axis=0), V.max(axis=0)
    info = {"diameter": diam, "min_x": float(lo[0]), "min_y": float(lo[1]), "min_z": float(lo[2]),
            "size_x": float(hi[0] - lo[0]), "size_y": float(hi[1] - lo[1]), "size_z": float(hi[2] - lo[2])}
    return info | bop_symmetries(symmetries or Symmetries())


def bop_symmetries(symmetries: Symmetries) -> dict:
    """The `symmetries_discrete` / `symmetries_continuous` keys of a models_info entry (mm; module docstring) for the
    symmetries that hold in shape and texture; {} without any."""
    s = symmetries.in_texture()
    out: dict = {}
    if s.discrete:
        scale = np.ones((4, 4))
        scale[:3, 3] = 1000.0  # the translation column in mm
        out["symmetries_discrete"] = [[float(x) for x in (np.asarray(S, np.float64) * scale).reshape(-1)]
                                      for S in s.discrete]
    if s.continuous:
        out["symmetries_continuous"] = [{"axis": [float(x) for x in a], "offset": [float(x) * 1000.0 for x in o]}
                                        for a, o in s.continuous]
    return out


def write_bop(db: TemplateDB, out: Path, close: bool = True) -> int:
    """Write the BOP dataset into the (empty) folder `out`, its mesh closed with `close`; returns the number
    of images."""
    mesh = template_mesh(db, close)
    views = posed_views(db, need_images=True)
    if mesh is None:
        log.warning("%s has no mesh: BOP export without models/, masks from the stored object masks", db.path)
        kept = [v for v in views if v.mask is not None]
        if len(kept) < len(views):
            log.warning("%d views without an object mask skipped", len(views) - len(kept))
        views = kept
        if not views:
            raise InputError(db.path, "BOP export needs a mesh or stored object masks; the template has neither")
    intr0 = views[0].intrinsics
    scene = out / "test" / f"{SCENE_ID:06d}"
    for sub in ("rgb", "depth", "mask", "mask_visib"):
        (scene / sub).mkdir(parents=True)
    cam = {"cx": intr0.cx, "cy": intr0.cy, "depth_scale": DEPTH_SCALE, "fx": intr0.fx, "fy": intr0.fy,
           "height": intr0.height, "width": intr0.width}
    _dump(out / "camera.json", cam)
    if mesh is not None:
        info = {str(OBJ_ID): models_info(mesh, db.symmetries())}
        for models in ("models", "models_eval"):
            (out / models).mkdir()
            write_ply_mm(mesh, out / models / f"obj_{OBJ_ID:06d}.ply")
            _dump(out / models / "models_info.json", info)
    caster = MeshRaycaster(mesh) if mesh is not None else None
    scene_camera, scene_gt, scene_gt_info, names = {}, {}, {}, {}
    for im_id, v in enumerate(views):
        assert v.T_obj_cam is not None and v.color is not None and v.depth is not None  # posed_views
        T_cam_obj = inv_T(v.T_obj_cam)
        depth_mm = depth_to_mm_u16(v.depth)
        if caster is not None:  # the mesh
            ren_mm = caster.depth(v.intrinsics, v.T_obj_cam).astype(np.float64) * 1000.0
            mask_all = ren_mm > 0
            meas = depth_mm.astype(np.float64)
            visib = mask_all & ((meas == 0) | (ren_mm - meas <= VISIB_DELTA_MM))
            if v.mask is not None:
                visib &= v.mask
        else:
            assert v.mask is not None  # without a mesh only views with a mask are exported
            mask_all = visib = v.mask
        key = str(im_id)
        stem = f"{im_id:06d}"
        imwrite(scene / "rgb" / f"{stem}.png", v.color, rgb=True)
        imwrite(scene / "depth" / f"{stem}.png", depth_mm)
        imwrite(scene / "mask" / f"{stem}_000000.png", np.where(mask_all, 255, 0).astype(np.uint8))
        imwrite(scene / "mask_visib" / f"{stem}_000000.png", np.where(visib, 255, 0).astype(np.uint8))
        R_flat = [float(x) for x in T_cam_obj[:3, :3].reshape(-1)]
        t_mm = [float(x) for x in T_cam_obj[:3, 3] * 1000.0]
        scene_camera[key] = {"cam_K": [float(x) for x in v.intrinsics.K.reshape(-1)], "depth_scale": DEPTH_SCALE,
                             "cam_R_w2c": R_flat, "cam_t_w2c": t_mm}
        scene_gt[key] = [{"cam_R_m2c": R_flat, "cam_t_m2c": t_mm, "obj_id": OBJ_ID}]
        n_all, n_visib = int(mask_all.sum()), int(visib.sum())
        scene_gt_info[key] = [{"bbox_obj": bbox_xywh(mask_all), "bbox_visib": bbox_xywh(visib),
                               "px_count_all": n_all, "px_count_valid": int((mask_all & (depth_mm > 0)).sum()),
                               "px_count_visib": n_visib, "visib_fract": n_visib / n_all if n_all else 0.0}]
        names[key] = v.name
    _dump(scene / "scene_camera.json", scene_camera)
    _dump(scene / "scene_gt.json", scene_gt)
    _dump(scene / "scene_gt_info.json", scene_gt_info)
    _dump(out / "gscan_views.json", names)
    targets = [{"im_id": int(k), "inst_count": 1, "obj_id": OBJ_ID, "scene_id": SCENE_ID} for k in scene_gt]
    (out / "test_targets_bop19.json").write_text(json.dumps(targets, indent=1) + "\n", encoding="utf-8")
    symmetric = bool(bop_symmetries(db.symmetries()))
    patch = toolkit_patch((intr0.width, intr0.height), symmetric)
    (out / "bop_toolkit.patch").write_text(patch, encoding="utf-8")
    return len(views)


def toolkit_patch(im_size: tuple[int, int], symmetric: bool, delta_mm: float = VSD_DELTA_M * 1000.0) -> str:
    """A unified diff for the BOP toolkit's checkout (`git apply`) that registers dataset TOOLKIT_DATASET: object
    OBJ_ID (in its symmetric ids if `symmetric`), test scene SCENE_ID, images of `im_size` (width, height), VSD
    delta `delta_mm` (gscan's VSD_DELTA_M). Each hunk anchors on one line before and one after the insertion
    (module docstring)."""
    name, (w, h) = TOOLKIT_DATASET, im_size
    sym = f"[{OBJ_ID}]" if symmetric else "[]"
    delta = f"{delta_mm:g}"
    return "\n".join([
        "--- a/bop_toolkit_lib/dataset_params.py",
        "+++ b/bop_toolkit_lib/dataset_params.py",
        "@@ -81,2 +81,3 @@",
        "     obj_ids = {",
        f'+        "{name}": [{OBJ_ID}],',
        '         "lm": list(range(1, 16)),',
        "@@ -105,2 +106,3 @@",
        "     symmetric_obj_ids = {",
        f'+        "{name}": {sym},',
        '         "lm": [3, 7, 10, 11],',
        "@@ -202,3 +204,7 @@",
        "     # Linemod (LM).",
        '-    if dataset_name == "lm":',
        f'+    if dataset_name == "{name}":  # a gscan BOP export (gscan export --format bop)',
        f'+        p["scene_ids"] = [{SCENE_ID}]',
        f'+        p["im_size"] = ({w}, {h})',
        "+",
        '+    elif dataset_name == "lm":',
        '         p["scene_ids"] = list(range(1, 16))',
        "--- a/scripts/eval_bop19_pose.py",
        "+++ b/scripts/eval_bop19_pose.py",
        "@@ -30,2 +30,3 @@",
        '             "vsd_deltas": {',
        f'+                "{name}": {delta},',
        '                 "hb": 15,',
        ""])


def _dump(path: Path, obj: dict) -> None:
    path.write_text(json.dumps(obj, indent=2) + "\n", encoding="utf-8")
