"""A complete template database rendered with gscan.synth, for the viewer's browser test and benchmark.

Until a template comes from `gscan scan`, this writes one directly with TemplateDB from rendered views of a
procedurally textured box on a table, with ground-truth poses: real RootSIFT keypoints (lifted with the
rendered depth), edges between views whose matches are the mutual descriptor nearest neighbours that
agree with the ground-truth relative pose, a fused point cloud and a vertex-coloured mesh.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gscan.features import FeatureParams, Features, descriptor_distances, extract_features
from gscan.geometry.mesh import MeshData
from gscan.geometry.transforms import inv_T, transform_points
from gscan.io.camera import RGBDFrame, point_cloud
from gscan.synth import (
    DEFAULT_INTRINSICS,
    SynthScene,
    box_mesh,
    default_distance,
    orbit_poses,
    procedural_box_texture,
    rest_on_table,
)
from gscan.template.db import Edge, TemplateDB, View

BOX_SIZE = (0.16, 0.10, 0.07)  # m


@dataclass
class SynthTemplate:
    """path of the written database; names of the views; T_obj_cam [4 x 4] ground truth per view (also for
    the unregistered ones); scene / T_world_obj to render more frames (object 0 of the scene)."""

    path: Path
    names: list[str]
    T_obj_cam: dict[str, np.ndarray]
    unregistered: list[str]
    scene: SynthScene
    T_world_obj: np.ndarray


def _match(fs: Features, ft: Features, tol_m: float = 0.005):
    """Mutual nearest neighbours in descriptor space whose object-frame points (ground-truth poses) lie
    within tol_m of each other.

    Returns (matches [M x 2] int32, rmse m, cost): cost = largest relative change of pairwise distances
    over 1 cm."""
    D = descriptor_distances(fs.descriptors, ft.descriptors, fs.kind)
    nn_st, nn_ts = D.argmin(1), D.argmin(0)
    i = np.flatnonzero(nn_ts[nn_st] == np.arange(len(nn_st)))
    j = nn_st[i]
    ps, pt = fs.points[i].astype(np.float64), ft.points[j].astype(np.float64)
    d = np.linalg.norm(ps - pt, axis=1)
    ok = d < tol_m
    m = np.stack([i[ok], j[ok]], 1).astype(np.int32)
    if len(m) < 2:
        return m, float("nan"), float("nan")
    a, b = ps[ok][:50], pt[ok][:50]
    ls = np.linalg.norm(a[:, None] - a[None], axis=2)
    lt = np.linalg.norm(b[:, None] - b[None], axis=2)
    far = np.triu(ls > 0.01, 1)  # pairs at least 1 cm apart (duplicate keypoints share a point)
    cost = float(np.max(np.abs(ls[far] - lt[far]) / ls[far])) if far.any() else float("nan")
    return m, float(np.sqrt(np.mean(d[ok] ** 2))), cost


def build_synth_template(path: str | Path, n_views: int = 6, elevations_deg: tuple[float, ...] = (35.0,),
                         unregistered: tuple[int, ...] = (), max_keypoints: int = 300, seed: int = 0,
                         loops: bool = True) -> SynthTemplate:
    """Render `n_views` views (rings at `elevations_deg`) and write a complete template database at `path`.

    Views whose index is in `unregistered` are stored without a pose (keypoints in their camera frame) and
    their edges as rejected. Edges: i -> i+1 "sequential"; with `loops`, last -> first and 0 -> n/2 "loop".
    """
    path = Path(path)
    intr = DEFAULT_INTRINSICS
    mesh = box_mesh(BOX_SIZE, procedural_box_texture(seed + 3))
    T_world_obj = rest_on_table(mesh)
    scene = SynthScene([(mesh, T_world_obj)], table=True, seed=seed)
    centre = T_world_obj[:3, 3]
    per_ring = int(np.ceil(n_views / len(elevations_deg)))
    poses = orbit_poses(centre, default_distance(mesh, intr), list(elevations_deg), per_ring)[:n_views]
    rng = np.random.default_rng(seed)
    names = [f"{i:06d}" for i in range(n_views)]
    T_obj_cam, feats, clouds = {}, {}, []
    db = TemplateDB.create(path, force=True, meta={"source": "scan", "descriptor": {"kind": "rootsift"}})
    try:
        for i, (name, T_world_cam) in enumerate(zip(names, poses, strict=True)):
            fr = scene.render(T_world_cam, intr, rng=rng)
            T = inv_T(T_world_obj) @ T_world_cam
            T_obj_cam[name] = T
            frame = RGBDFrame(name=name, color=fr.color, depth=fr.depth, intrinsics=intr, mask=fr.mask)
            f = extract_features(frame, FeatureParams(kind="rootsift", max_keypoints=max_keypoints), mask=fr.mask)
            reg = i not in unregistered
            feats[name] = f.transformed(T) if reg else f
            db.add_view(View.from_frame(frame, T_obj_cam=T if reg else None, input_index=i), feats[name])
            if reg:
                p, c = point_cloud(frame, mask=fr.mask, stride=3)
                clouds.append((transform_points(T, p), c))
        pairs = [(i, i + 1, "sequential") for i in range(n_views - 1)]
        if loops and n_views > 3:
            pairs += [(n_views - 1, 0, "loop"), (0, n_views // 2, "loop")]
        for s, t, kind in pairs:
            ns, nt = names[s], names[t]
            if s in unregistered or t in unregistered:  # the matcher failed on this pair
                db.add_edge(Edge(src=ns, tgt=nt, T_tgt_src=None, matches=np.zeros((0, 2), np.int32), fitness=0.0,
                                 kind=kind, accepted=False, reason="too few matches"))
                continue
            m, rmse, cost = _match(feats[ns], feats[nt])
            ok = len(m) >= 6
            db.add_edge(Edge(src=ns, tgt=nt, T_tgt_src=inv_T(T_obj_cam[nt]) @ T_obj_cam[ns] if ok else None, matches=m,
                             cost=cost if ok else None, rmse=rmse if ok else None,
                             fitness=len(m) / max(1, min(len(feats[ns].pixels), len(feats[nt].pixels))), kind=kind,
                             accepted=ok, reason=None if ok else "too few matches"))
        pts = np.concatenate([p for p, _ in clouds])
        cols = np.concatenate([c for _, c in clouds])
        _, keep = np.unique(np.floor(pts / 0.002).astype(np.int64), axis=0, return_index=True)
        keep.sort()
        db.set_cloud(pts[keep].astype(np.float32), cols[keep])
        db.set_mesh(_colored_box(pts[keep], cols[keep]))
        db.add_grasp("top", np.array([[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, -1, BOX_SIZE[2] / 2], [0, 0, 0, 1.0]]))
        db.mark_complete()
    finally:
        db.close()
    return SynthTemplate(path, names, T_obj_cam, [names[i] for i in unregistered], scene, T_world_obj)


def _colored_box(cloud: np.ndarray, colors: np.ndarray) -> MeshData:
    """A subdivided box of BOX_SIZE (object frame) coloured by its nearest fused-cloud point."""
    import trimesh
    from scipy.spatial import cKDTree

    box = trimesh.creation.box(extents=BOX_SIZE).subdivide_to_size(0.004)
    _, idx = cKDTree(cloud).query(box.vertices)
    return MeshData(vertices=np.asarray(box.vertices), triangles=np.asarray(box.faces),
                    vertex_colors=(colors[idx] * 255).astype(np.uint8))
