"""Template from a CAD mesh: render snapshots on a sphere around the object into a template database.

This is the paper's own setting (GMatch matches a query against rendered snapshots of a CAD model).
The mesh's own frame is kept (units scaled to metres by `scale`), so poses estimated against the
template are poses of the CAD model, as BOP expects.

Views: `n_views` cameras on a Fibonacci sphere (both hemispheres, poles avoided) about the centre of
the mesh's bounding box, at the distance where the bounding sphere spans `FILL` of the image width
of `gscan.synth.DEFAULT_INTRINSICS` (640 x 480), image "up" along the mesh's +z. Each view is rendered
without table or background (black), with clean depth on the object only and mask = object. RootSIFT
keypoints inside the mask (the estimator's query feature parameters) are lifted with the depth and
stored in the OBJECT frame. The template
cloud is the union of the views' back-projected depth (surfaces actually visible from outside),
voxel-downsampled; the template mesh is the input mesh with per-vertex colours sampled from the texture.

Textures: OBJ + MTL + image via `gscan.synth.load_textured_mesh`; meshes with per-vertex colours
(PLY, GLB without texture) are rendered with flat per-face colours (the mean of the face's vertex
colours); meshes with neither render grey.

Symmetries (`gscan.scanning.symmetry`) are found on the exact mesh with colours from its texture, to the template
cloud's resolution (surface error voxel / 2), and stored in the "symmetries" meta.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from gscan.errors import InputError
from gscan.features import OBJECT_FEATURES, FeatureParams, extract_features
from gscan.features.depth import choose_source, depth_keypoints, joint_features, median_object_size, pilot_frames
from gscan.features.keypoints import JOINT
from gscan.geometry.coverage import template_coverage
from gscan.geometry.pointset import voxel_mean
from gscan.geometry.symmetry import Symmetries
from gscan.geometry.transforms import look_at, transform_points
from gscan.io.camera import RGBDFrame, backproject
from gscan.io.output import Output, remove_sqlite_sidecars
from gscan.progress import NullProgress, Progress
from gscan.registration.noise import DepthNoise
from gscan.scanning.symmetry import SymmetryParams, detect_symmetries, surface_of_textured_mesh
from gscan.synth.mesh import TexturedMesh, load_textured_mesh
from gscan.template.db import TemplateDB, View

log = logging.getLogger(__name__)

FILL = 0.45  # fraction of the image width spanned by the object's bounding sphere
CLOUD_VOXEL = 0.002  # m, voxel size of the template cloud (x radius / 15 cm for larger objects)
CLOUD_STRIDE = 2  # pixel stride of the back-projection of each view into the cloud
MAX_POLAR_COS = 0.97  # |cos| of the polar angle kept away from the poles (look_at up-vector degeneracy)


def fibonacci_directions(n: int) -> np.ndarray:
    """[n x 3] unit vectors spread evenly over the sphere (golden-angle spiral, poles avoided).

    z runs from +MAX_POLAR_COS to -MAX_POLAR_COS, so both hemispheres are covered equally.
    """
    if n < 1:
        raise ValueError("need at least one view")
    i = np.arange(n, dtype=np.float64)
    z = MAX_POLAR_COS * (1.0 - 2.0 * (i + 0.5) / n)
    r = np.sqrt(1.0 - z * z)
    phi = i * np.pi * (3.0 - np.sqrt(5.0))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def view_poses(mesh: TexturedMesh, n_views: int, fill: float = FILL) -> list[np.ndarray]:
    """T_obj_cam [4 x 4] of `n_views` cameras looking at the mesh's bounding-box centre."""
    from gscan.synth.render import DEFAULT_INTRINSICS  # the renderer (open3d), once a mesh is read

    intr = DEFAULT_INTRINSICS
    dist = mesh.radius * intr.fx / (0.5 * fill * intr.width)
    c = mesh.center
    return [look_at(c + dist * d, c, np.array([0.0, 0.0, 1.0])) for d in fibonacci_directions(n_views)]


def _load_mesh(path: Path, scale: float) -> TexturedMesh:
    """Textured OBJ through gscan.synth; vertex-coloured meshes (PLY/GLB) get a per-face colour texture."""
    mesh = load_textured_mesh(path, scale=scale)
    if mesh.texture.shape[:2] != (1, 1):
        return mesh
    import trimesh

    try:
        tm: Any = trimesh.load(str(path), force="mesh", process=False)  # a Trimesh, or a PointCloud, ...
        vc = getattr(tm.visual, "vertex_colors", None) if getattr(tm.visual, "kind", None) == "vertex" else None
    except Exception:  # noqa: BLE001 - the mesh loaded once already; colours are optional
        vc = None
    if vc is None or len(vc) != len(mesh.vertices):
        return mesh
    face_rgb = np.asarray(vc, dtype=np.float64)[:, :3][mesh.triangles].mean(axis=1)
    # one texel per face on a square grid (an image side stays far below OpenCV's 32767-pixel limit); all
    # three corners of a face map to its texel's centre, so it renders flat at the exact colour
    F = len(mesh.triangles)
    side = int(np.ceil(np.sqrt(F)))
    texels = np.zeros((side * side, 3), np.uint8)
    texels[:F] = np.clip(np.rint(face_rgb), 0, 255)
    col, row = np.arange(F) % side, np.arange(F) // side
    u, v = (col + 0.5) / side, 1.0 - (row + 0.5) / side  # OBJ convention: v = 0 at the image's bottom row
    uv = np.repeat(np.stack([u, v], axis=1)[:, None, :], 3, axis=1)  # [F x 3 x 2]
    texture = texels.reshape(side, side, 3)
    log.info("%s: per-vertex colours rendered as flat face colours", path)
    return TexturedMesh(mesh.vertices, mesh.triangles, uv, np.ascontiguousarray(texture), name=mesh.name)


def _keypoint_source(feature_params: FeatureParams, scene: Any, poses: list[np.ndarray], intr: Any
                     ) -> tuple[str, list[int]]:
    """(the keypoints the template stores, "sift" | "depth" | "both"; the image keypoint counts it was chosen from):
    `feature_params.keypoints`, or with auto the scan's rule (`choose_source`) on the image keypoints of up to
    views spread over the sphere (`pilot_frames`: a plain mesh stores its depth keypoints too)."""
    counts: list[int] = []
    if feature_params.keypoints == "auto" and feature_params.kind == "rootsift":
        image_params = replace(feature_params, keypoints="sift")
        for k in pilot_frames(len(poses)):
            r = scene.render(poses[k], intr, noise=False)
            frame = RGBDFrame(name=f"view_{k:03d}", color=r.color, depth=r.depth_clean, intrinsics=intr, mask=r.mask)
            counts.append(len(extract_features(frame, image_params, mask=r.mask)))
    return choose_source(feature_params, counts), counts


def _depth_size(scene: Any, poses: list[np.ndarray], intr: Any) -> float | None:
    """The object's size its depth keypoints are found at (`gscan.features.depth.object_size`): the median over
    the views of the size of the object's points in each (a scan's keyframes take the same median)."""
    def points(T_obj_cam: np.ndarray) -> np.ndarray:
        r = scene.render(T_obj_cam, intr, noise=False)
        return backproject(r.depth_clean, intr)[r.mask & (r.depth_clean > 0)]

    return median_object_size(points(T) for T in poses)


def _voxel_cloud(points: np.ndarray, colors: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """Voxel-grid mean of [N x 3] points and [N x 3] uint8 colours -> ([M x 3] float32, [M x 3] uint8)."""
    M = voxel_mean(np.hstack([np.asarray(points, np.float64).reshape(-1, 3),
                              np.asarray(colors, np.float64).reshape(-1, 3)]), voxel)
    return M[:, :3].astype(np.float32), np.clip(np.rint(M[:, 3:]), 0, 255).astype(np.uint8)


@dataclass(frozen=True)
class TemplateResult:
    """A template rendered from a mesh: the database written, its number of views, descriptor kind, source
    ("mesh"), the object's extent [3] (m, mesh frame) and its symmetries (mesh frame)."""

    output: Path
    views: int
    descriptor: str
    source: str
    extent_m: tuple[float, float, float]
    symmetries: Symmetries = field(default_factory=Symmetries)


def template_from_mesh(mesh_path: str | Path, output: str | Path, *, n_views: int = 36, scale: float = 1.0,
                       force: bool = False, progress: Progress | None = None,
                       feature_params: FeatureParams | None = None,
                       symmetry_params: SymmetryParams | None = None) -> TemplateResult:
    """Render `n_views` snapshots of a textured mesh into a new template database (the mesh's frame is kept).

    Args:
        mesh_path: a textured OBJ (with MTL and image), or a PLY / GLB with vertex colours.
        output: the template database to write (`OBJ.gscan`).
        n_views: snapshots rendered on a sphere around the mesh (module docstring).
        scale: mesh units to metres (0.001 for millimetres).
        force: replace an existing `output`.
        progress: stage progress reporting, none by default.
        feature_params: the keypoints stored (default: the estimator's query keypoints, OBJECT_FEATURES); with
            keypoints "depth" or "both", or "auto" on a plain mesh (`_keypoint_source`), the image's and the
            depth's in one set (a plain part: method.md, plain objects), the depth's at the views' median object
            size and the default depth noise.
        symmetry_params: how the mesh's symmetries are found (default `SymmetryParams()`; `enabled=False`: not).

    Returns:
        TemplateResult: output, views, descriptor kind, source "mesh", extent_m [3], symmetries.

    Raises:
        InputError: naming the file, for a missing / unreadable / degenerate mesh, a bad `n_views` or `scale`,
            an existing output without `force`; on any error the partly written output is removed.
    """
    mesh_path, output = Path(mesh_path), Path(output)
    if n_views < 1:
        raise InputError(mesh_path, f"need at least one view, not {n_views}")
    if not (np.isfinite(scale) and scale > 0):
        raise InputError(mesh_path, f"scale must be positive, not {scale}")
    progress = progress or NullProgress()
    feature_params = feature_params or OBJECT_FEATURES  # the estimator's query keypoints
    symmetry_params = symmetry_params or SymmetryParams()
    # checked before the mesh loads (trimesh, scipy) and is rendered
    target = Output(output, force=force, kind=".gscan file path")
    mesh = _load_mesh(mesh_path, scale)
    if mesh.radius <= 0:
        raise InputError(mesh_path, "mesh is degenerate (all vertices coincide)")
    from gscan.synth.render import DEFAULT_INTRINSICS, SynthScene  # open3d: a bad input is refused without it
    db = None
    try:
        intr = DEFAULT_INTRINSICS
        scene = SynthScene([(mesh, np.eye(4))], table=False, shadows=False, background_rgb=(0, 0, 0), seed=0)
        poses = view_poses(mesh, n_views)
        source, counts = _keypoint_source(feature_params, scene, poses, intr)
        joint = source in ("depth", "both")
        db = TemplateDB.create(target.open(), force=True, meta={
            "source": "mesh", "descriptor": {"kind": JOINT if joint else feature_params.kind,
                                             "max_keypoints": feature_params.max_keypoints,
                                             "sift_contrast_threshold": feature_params.sift_contrast_threshold},
            "mesh_source": {"path": str(mesh_path), "scale": float(scale), "views": int(n_views), "fill": FILL}})
        cloud_p, cloud_c = [], []
        n_kp = 0
        size = _depth_size(scene, poses, intr) if joint else None
        if joint:
            db.set_meta("keypoints", {"source": "both", "chosen_by": "auto" if counts else "config", "object": "both",
                                      "object_depth_size": size,
                                      "median_image_keypoints": float(np.median(counts)) if counts else None})
        image_params = replace(feature_params, keypoints="sift")
        with progress.stage("render", total=n_views) as advance:
            for i, T_obj_cam in enumerate(poses):
                r = scene.render(T_obj_cam, intr, noise=False)
                name = f"view_{i:03d}"
                frame = RGBDFrame(name=name, color=r.color, depth=r.depth_clean, intrinsics=intr, mask=r.mask)
                feats = extract_features(frame, image_params, mask=r.mask)
                if joint:  # at the one size a query's are found at, with the depth noise a query assumes
                    feats = joint_features(feats, depth_keypoints(frame, DepthNoise().sigma, feature_params, r.mask,
                                                                  size=size))
                db.add_view(View(name=name, intrinsics=intr, T_obj_cam=T_obj_cam, color=r.color,
                                 depth=np.where(r.mask, r.depth_clean, 0.0).astype(np.float32), mask=r.mask,
                                 keyframe=True, quality=float(len(feats)), input_index=i),
                            feats.transformed(T_obj_cam))
                n_kp += len(feats)
                sl = (slice(None, None, CLOUD_STRIDE),) * 2
                sel = (r.mask & (r.depth_clean > 0))[sl]
                cloud_p.append(transform_points(T_obj_cam, backproject(r.depth_clean, intr)[sl][sel]))
                cloud_c.append(r.color[sl][sel])
                advance(1)
        with progress.stage("store", total=1) as advance:
            voxel = CLOUD_VOXEL * max(1.0, mesh.radius / 0.15)  # ~same point count for large objects
            P, C = _voxel_cloud(np.concatenate(cloud_p), np.concatenate(cloud_c), voxel)
            db.set_cloud(P, C)
            db.set_mesh(mesh.to_mesh())
            db.set_meta("coverage", template_coverage(poses, mesh.to_mesh()).to_meta())  # mesh frame: +z is the top
            symmetries = Symmetries()
            if symmetry_params.enabled:
                symmetries = detect_symmetries(surface_of_textured_mesh(mesh, symmetry_params.reference_samples),
                                               0.5 * voxel, symmetry_params)
            db.set_meta("symmetries", symmetries.to_json())
            db.mark_complete()
            x, y, z = (float(v) for v in db.extent())
            result = TemplateResult(output=output, views=int(n_views),
                                    descriptor=JOINT if joint else feature_params.kind, source="mesh",
                                    extent_m=(x, y, z), symmetries=symmetries)
            advance(1)
        log.info("%s: %d views, %d keypoints, cloud %d points", output, n_views, n_kp, len(P))
    except BaseException as e:  # the sibling goes; an existing output stays as it was
        if db is not None:
            db.close()
        target.discard()
        t = target.translate(e)
        if t is not e:
            raise t from None
        raise
    db.close()
    remove_sqlite_sidecars(output)  # a killed writer's journal or log there would be replayed into the new file
    target.commit()
    return result
