"""The viewer's 3D scene (viser), in the template (object) frame: the template's axes, the fused mesh and
cloud, one camera frustum per registered view with its snapshot (coloured by quality, click selects the
view), pose-graph edges between camera centres, the views' 3D keypoints, grasp frames, the coverage map
(`coverage_points`: a sphere of points around the object, one per direction cell, coloured by how many views
saw the object from there, blue where only the observed surface did, grey where nothing did), the object's axes
of symmetry (`symmetry_segments`), optionally a query frame's cloud placed by an estimated pose, and the instances
an estimate found in it (`instance_poses`: the template's mesh, or its box, at each pose, labelled with its rank and
score).
`build_scene` returns each layer's handles (`SceneLayers`); the viewer app (`gscan.viewer.app.ViewerApp`) holds
them.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from gscan.geometry.coverage import CoverageMap
from gscan.geometry.symmetry import Symmetries
from gscan.geometry.transforms import inv_T, transform_points
from gscan.io.camera import Intrinsics, RGBDFrame, point_cloud
from gscan.template.db import MeshData, View
from gscan.viewer.data import ViewerData, ViewerOptions
from gscan.viewer.draw import (
    QUERY_CAMERA_COLOR,
    coverage_colors,
    edge_color,
    hue_colors,
    quality_color,
    symmetry_color,
    thumbnail,
)
from gscan.viewer.instances import ShownInstances

LAYERS = ("mesh", "cloud", "frustums", "edges", "rejected", "keypoints", "scene", "grasps", "coverage", "symmetries",
          "instances")
COVERAGE_RADIUS = 0.75  # the coverage map's sphere, in object sizes about the object's centre
INSTANCE_TRIANGLES = 3000  # an instance's mesh is the template's simplified to this many triangles (one colour)


@dataclass
class SceneLayers:
    """What `build_scene` drew: layer key -> viser scene handles (toggled together), the frustum depth (m) at
    "Frustum size" 1, and the query frame's cloud as drawn [N x 3] (template frame) or None."""

    layers: dict[str, list]
    frustum_scale: float
    scene_points_obj: np.ndarray | None
    instances_obj: list[np.ndarray] = field(default_factory=list)  # T_obj_inst [4 x 4] of each instance drawn


def build_scene(server: Any, data: ViewerData, options: ViewerOptions, frame: RGBDFrame | None,
                T_cam_obj: np.ndarray | None, grasps: dict[str, np.ndarray],
                on_select_view: Callable[[str], None], instances: ShownInstances | None = None) -> SceneLayers:
    """Populate `server.scene` (a viser server) and set its initial camera.

    frame / T_cam_obj [4 x 4]: a query frame and the object's pose in it (its cloud is drawn when both are given).
    grasps: {name: T_obj_grasp [4 x 4]}. on_select_view(name) is called when a view's frustum is clicked.
    instances: the poses an estimate found in the frame, drawn relative to T_cam_obj (`instance_poses`).
    """
    sc, d, o = server.scene, data, options
    s = d.size
    reg = d.registered
    # Scene up: the nearest axis to the cameras' mean image-up direction (-y of each camera).
    ups = np.array([-_pose(v)[:3, 1] for v in reg]) if reg else np.array([[0.0, 0.0, 1.0]])
    up = ups.mean(0) / max(np.linalg.norm(ups.mean(0)), 1e-9)
    axis = int(np.argmax(np.abs(up)))
    sc.set_up_direction(("+" if up[axis] > 0 else "-") + "xyz"[axis])
    if reg:  # beyond the first view's camera, raised along "up", far enough to see every frustum
        cams = np.array([_pose(v)[:3, 3] for v in reg])
        dist = float(np.median(np.linalg.norm(cams - d.center, axis=1)))
        d0 = cams[0] - d.center
        d0 = d0 - (d0 @ up) * up
        if np.linalg.norm(d0) < 1e-9:  # the first camera straight above: any horizontal direction
            d0 = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
        d0 = d0 / np.linalg.norm(d0)
        eye = d.center + _clear_direction(d0, up, cams - d.center) * max(1.9 * dist, 2.0 * s)
    else:
        eye = d.center + np.array([1.0, 1.0, 1.0]) * 1.5 * s
    # Frustum size: a quarter of the object, less where cameras are dense (half the median spacing).
    frustum_scale = 0.25 * s
    if len(reg) >= 2:
        cams = np.array([_pose(v)[:3, 3] for v in reg])
        spacing = float(np.median(cKDTree(cams).query(cams, k=2)[0][:, 1]))
        if spacing > 1e-6:
            frustum_scale = min(frustum_scale, 0.5 * spacing)
    server.initial_camera.position = eye
    server.initial_camera.look_at = d.center
    server.initial_camera.near = 0.01 * s
    server.initial_camera.far = 1000.0 * s

    layers: dict[str, list] = {k: [] for k in LAYERS}
    sc.add_frame("/template", axes_length=0.3 * s, axes_radius=0.008 * s, origin_radius=0.015 * s)
    pt = 0.004 * s
    if d.mesh is not None and len(d.mesh.triangles):
        layers["mesh"].append(_add_mesh(sc, d.mesh))
    if d.cloud is not None and len(d.cloud[0]):
        pts, cols = d.cloud
        step = max(1, int(np.ceil(len(pts) / o.max_cloud_points)))
        cols = np.full((len(pts), 3), 200, np.uint8) if cols is None else cols
        layers["cloud"].append(sc.add_point_cloud("/cloud", np.asarray(pts[::step], np.float32), cols[::step],
                                                  point_size=pt, visible=not layers["mesh"]))
    kp = [(d.keypoints[v.name][1], i) for i, v in enumerate(reg) if len(d.keypoints[v.name][1])]
    if kp:
        pts = np.concatenate([p for p, _ in kp])
        hues = hue_colors(len(reg))
        cols = np.concatenate([np.repeat(hues[i][None], len(p), 0) for p, i in kp])
        step = max(1, int(np.ceil(len(pts) / o.max_keypoints)))
        layers["keypoints"].append(sc.add_point_cloud("/keypoints", pts[::step], cols[::step], point_size=1.5 * pt,
                                                      visible=False))
    for v in reg:
        layers["frustums"].append(_add_frustum(sc, o, frustum_scale, f"/views/{_node(v.name)}", v.intrinsics,
                                               _pose(v), d.thumbs[v.name], quality_color(d.quality[v.name]),
                                               _on_click(on_select_view, v.name)))
    centres = {v.name: _pose(v)[:3, 3] for v in reg}
    for key, accepted, width in (("edges", True, 3.0), ("rejected", False, 1.5)):
        es = [e for e in d.edges if e.accepted == accepted and e.src in centres and e.tgt in centres]
        if es:
            seg = np.array([[centres[e.src], centres[e.tgt]] for e in es], np.float32)
            col = np.array([[edge_color(e, o.rmse_red_m)] * 2 for e in es], np.uint8)
            layers[key].append(sc.add_line_segments(f"/{key}", seg, col, thickness=width, thickness_units="screen",
                                                    visible=accepted))
    for name, T in grasps.items():
        layers["grasps"].append(sc.add_frame(f"/grasps/{_node(name)}", axes_length=0.15 * s, axes_radius=0.006 * s,
                                             wxyz=quat_wxyz(T[:3, :3]), position=T[:3, 3]))
        layers["grasps"].append(sc.add_label(f"/grasps/{_node(name)}/label", name))
    if d.coverage is not None:
        pts, cols = coverage_points(d.coverage, d.center, d.size)
        layers["coverage"].append(sc.add_point_cloud("/coverage", pts, cols, point_size=0.04 * s))
    seg, seg_cols, labels = symmetry_segments(d.symmetries, d.center, s)
    if len(seg):
        layers["symmetries"].append(sc.add_line_segments("/symmetries/axes", seg, seg_cols, thickness=4.0,
                                                         thickness_units="screen"))
        for i, (text, at) in enumerate(labels):
            layers["symmetries"].append(sc.add_label(f"/symmetries/label_{i}", text, position=at))
    scene_points_obj = None
    if frame is not None and T_cam_obj is not None:
        T_obj_cam = inv_T(np.asarray(T_cam_obj, dtype=np.float64))
        pts_cam, cols = point_cloud(frame, stride=o.scene_stride)
        scene_points_obj = transform_points(T_obj_cam, pts_cam).astype(np.float32)
        layers["scene"].append(sc.add_point_cloud("/scene/cloud", scene_points_obj,
                                                  (cols * 255).astype(np.uint8), point_size=pt))
        thumb = thumbnail(frame.color, o.frustum_px)
        layers["scene"].append(_add_frustum(sc, o, frustum_scale, "/scene/camera", frame.intrinsics, T_obj_cam,
                                            thumb, QUERY_CAMERA_COLOR, None))
    instances_obj = [] if instances is None or T_cam_obj is None else instance_poses(instances, T_cam_obj)
    if instances is not None:
        hues = hue_colors(len(instances_obj))
        light = None if d.mesh is None or not len(d.mesh.triangles) else d.mesh.simplified(INSTANCE_TRIANGLES)
        for f, T, hue in zip(instances.found, instances_obj, hues, strict=True):
            node = f"/instances/i{f.rank}"
            layers["instances"].append(sc.add_frame(node, axes_length=0.2 * s, axes_radius=0.005 * s,
                                                    wxyz=quat_wxyz(T[:3, :3]), position=T[:3, 3]))
            color = tuple(int(c) for c in hue)
            if light is not None:
                layers["instances"].append(sc.add_mesh_simple(
                    f"{node}/mesh", np.asarray(light.vertices, np.float32), np.asarray(light.triangles, np.uint32),
                    color=color, opacity=0.55, side="double"))
            else:  # no mesh: the object's box
                layers["instances"].append(sc.add_box(f"{node}/box", color=color, dimensions=(s, s, s), opacity=0.4,
                                                      position=d.center))
            layers["instances"].append(sc.add_label(f"{node}/label", f.label, position=d.center))
    return SceneLayers(layers, frustum_scale, scene_points_obj, instances_obj)


def instance_poses(instances: ShownInstances, T_cam_obj: np.ndarray) -> list[np.ndarray]:
    """T_obj_inst [4 x 4] of each instance found (rank order): its pose T_cam_inst seen from the template frame
    that `T_cam_obj` [4 x 4] places the query camera in, inv(T_cam_obj) @ T_cam_inst (the identity for the
    instance whose pose places the camera)."""
    T_obj_cam = inv_T(np.asarray(T_cam_obj, dtype=np.float64))
    return [T_obj_cam @ f.T_cam_obj for f in instances.found]


def coverage_points(coverage: CoverageMap, center: np.ndarray, size: float) -> tuple[np.ndarray, np.ndarray]:
    """The coverage map as points: [K x 3] float32 on a sphere of `COVERAGE_RADIUS` x size about `center` [3]
    (object frame), one per cell, and their [K x 3] uint8 colours (`coverage_colors`)."""
    pts = np.asarray(center, dtype=np.float64) + coverage.directions_obj * COVERAGE_RADIUS * size
    return pts.astype(np.float32), coverage_colors(coverage.counts, coverage.surface)
def symmetry_label(fold: int, in_texture: bool) -> str:
    """What an axis of symmetry is called in the scene and the GUI: "revolution" or "n-fold", and what it holds in."""
    return ("revolution" if fold == 0 else f"{fold}-fold") + (" (shape+texture)" if in_texture else " (shape)")


def symmetry_segments(symmetries: Symmetries, center: np.ndarray, size: float
                      ) -> tuple[np.ndarray, np.ndarray, list[tuple[str, np.ndarray]]]:
    """The axes of symmetry as drawn: segments [K x 2 x 3] float32 (1.5 x the object's size, centred where the axis
    passes nearest the object's centre [3]), their colours [K x 2 x 3] uint8 (`symmetry_color`) and a label
    (text, position [3]) at one end of each."""
    seg, cols, labels = [], [], []
    for ax in symmetries.axes():
        mid = ax.point + ax.direction * float((np.asarray(center) - ax.point) @ ax.direction)
        a, b = mid - 0.75 * size * ax.direction, mid + 0.75 * size * ax.direction
        seg.append([a, b])
        cols.append([symmetry_color(ax.fold, ax.in_texture)] * 2)
        labels.append((symmetry_label(ax.fold, ax.in_texture), b))
    if not seg:
        return np.zeros((0, 2, 3), np.float32), np.zeros((0, 2, 3), np.uint8), []
    return np.asarray(seg, np.float32), np.asarray(cols, np.uint8), labels


def _node(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name)


def _add_mesh(sc: Any, mesh: MeshData) -> Any:
    V = np.asarray(mesh.vertices, np.float64)
    F = np.asarray(mesh.triangles, np.int64)
    if mesh.vertex_colors is None:
        return sc.add_mesh_simple("/mesh", V.astype(np.float32), F.astype(np.uint32), color=(200, 170, 120),
                                  side="double")
    import trimesh  # only for vertex colours (sent as GLB)

    tm = trimesh.Trimesh(V, F, vertex_colors=np.asarray(mesh.vertex_colors, np.uint8), process=False)
    return sc.add_mesh_trimesh("/mesh", tm)


def _on_click(select: Callable[[str], None], name: str) -> Callable[[Any], None]:
    """A frustum's click handler: select view `name`."""
    return lambda _event: select(name)


def _add_frustum(sc: Any, o: ViewerOptions, scale: float, node: str, intr: Intrinsics, T_obj_cam: np.ndarray,
                 image: np.ndarray, color: tuple[int, int, int], on_click: Callable[[Any], None] | None) -> Any:
    img = thumbnail(image, o.frustum_px)
    h = sc.add_camera_frustum(
        node, fov=float(2.0 * np.arctan2(intr.height / 2.0, intr.fy)), aspect=intr.width / intr.height,
        scale=scale, thickness=1.5, thickness_units="screen", color=color, image=img, format="jpeg",
        jpeg_quality=o.jpeg_quality, wxyz=quat_wxyz(T_obj_cam[:3, :3]), position=T_obj_cam[:3, 3])
    if on_click is not None:
        h.on_click(on_click)
    return h


def _pose(v: View) -> np.ndarray:
    """T_obj_cam [4 x 4] of a registered view (`ViewerData.registered`)."""
    assert v.T_obj_cam is not None
    return v.T_obj_cam


def _clear_direction(d0: np.ndarray, up: np.ndarray, cam_dirs: np.ndarray) -> np.ndarray:
    """Unit direction from the object to the start camera: 58 deg above the horizon beyond the first view's
    camera (horizontal unit d0), unless a view's camera (cam_dirs [N x 3]) lies within 20 deg of it; then the
    first candidate turned about `up` and tilted that clears every view by 20 deg, or the one clearing them
    most, so that no frustum and its snapshot hide the object (a CAD template's views cover the sphere)."""
    side = np.cross(up, d0)
    cams = cam_dirs / np.maximum(np.linalg.norm(cam_dirs, axis=1, keepdims=True), 1e-12)
    best: np.ndarray | None = None
    best_gap = -1.0
    for el in np.radians([58.0, 45.0, 70.0, 35.0]):
        for az in np.radians([0.0, 15.0, -15.0, 30.0, -30.0, 45.0, -45.0, 90.0, -90.0, 135.0, -135.0, 180.0]):
            c = np.cos(el) * (np.cos(az) * d0 + np.sin(az) * side) + np.sin(el) * up
            gap = float(np.arccos(np.clip(cams @ c, -1.0, 1.0)).min())
            if gap >= np.radians(20.0):
                return c
            if gap > best_gap:
                best, best_gap = c, gap
    return best if best is not None else d0  # d0: every gap undefined (degenerate directions)


def quat_wxyz(R: np.ndarray) -> np.ndarray:
    """Rotation matrix [3 x 3] -> unit quaternion (w, x, y, z), as viser takes it."""
    x, y, z, w = Rotation.from_matrix(np.asarray(R, dtype=np.float64)).as_quat()
    return np.array([w, x, y, z])
