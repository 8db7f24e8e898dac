"""Piles: several copies of one or more objects resting side by side on a table, touching and partly hiding one
another, some lying on a side (the rendered scenes of the many-instances tests and bench/instances.py).

`pile_poses` places the objects in a row along the world x axis, each separated from the next by a small gap
measured on their rotated vertices (so no two interpenetrate, whatever their yaw), with a random sideways offset;
`render_pile` renders them on a textured table seen from a random elevation and azimuth; `render_row_sequence`
renders a sequence of a row of copies under a static camera, one moving, one hidden for some frames (the tests
and bench of tracking every instance); `write_bop_piles` writes piles as a BOP test split (several instances
of an object per image, the test targets with their `inst_count`), which `gscan eval` scores as the BOP
toolkit does.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from gscan.geometry.transforms import look_at, make_T, rotvec_to_R, transform_points
from gscan.io.camera import Intrinsics
from gscan.synth.capture import rest_on_table
from gscan.synth.mesh import TexturedMesh
from gscan.synth.render import DEFAULT_INTRINSICS, RenderedFrame, SynthScene

SIDE = rotvec_to_R(np.array([np.pi / 2, 0.0, 0.0]))  # lying on a side: turned 90 deg about a horizontal axis


@dataclass
class Pile:
    """A rendered pile: the frame (`RenderedFrame`, its labels k = objects[k]), the objects' meshes,
    T_cam_obj [K x 4 x 4] of each and visible [K] the fraction of each object's silhouette (rendered alone from the
    same camera) the others and the image border leave in sight (BOP's visib_fract)."""

    frame: RenderedFrame
    meshes: list[TexturedMesh]
    T_cam_objs: np.ndarray
    visible: np.ndarray


def pile_poses(meshes: list[TexturedMesh], rng: np.random.Generator, lying_frac: float = 0.3,
               gap: tuple[float, float] = (0.002, 0.02), sideways: float = 0.03) -> list[np.ndarray]:
    """T_world_obj [4 x 4] of each mesh: a random yaw (and on a side with probability `lying_frac`), resting on
    z = 0, in a row along +x with a gap drawn from `gap` (m) between neighbours' extents and a sideways offset
    drawn from +-`sideways` (m); the row is centred on the origin."""
    poses, x = [], 0.0
    for m in meshes:
        R = rotvec_to_R(np.array([0.0, 0.0, rng.uniform(0.0, 2 * np.pi)]))
        if rng.uniform() < lying_frac:
            R = R @ SIDE
        v = m.vertices @ R.T
        lo, hi = v.min(0), v.max(0)
        cx = x - lo[0]
        poses.append(rest_on_table(m, R, (float(cx + 0.5 * (lo[0] + hi[0])), float(rng.uniform(-sideways, sideways)))))
        x = cx + hi[0] + rng.uniform(*gap)
    shift = np.eye(4)
    shift[0, 3] = -0.5 * (x - gap[0])
    return [shift @ T for T in poses]


def render_pile(meshes: list[TexturedMesh], seed: int, distance: float = 0.6, elevation: tuple[float, float] = (35, 70),
                table_kind: str = "newspaper", lying_frac: float = 0.3) -> Pile:
    """The meshes piled (`pile_poses`, seeded by `seed`) and seen from `distance` (m; farther, 1.1 times the row's
    length, for a long row) at an elevation drawn from `elevation` (deg) and any azimuth, towards the pile's
    centre; depth noise seeded by `seed`."""
    rng = np.random.default_rng(seed)
    T_wo = pile_poses(meshes, rng, lying_frac)
    ends = np.array([transform_points(T, m.vertices)[:, 0] for m, T in zip(meshes, T_wo, strict=True)],
                    dtype=object)
    row = max(float(e.max()) for e in ends) - min(float(e.min()) for e in ends)
    distance = max(distance, 1.1 * row)  # the whole row in sight from any azimuth
    c = np.mean([transform_points(T, m.center[None])[0] for m, T in zip(meshes, T_wo, strict=True)], axis=0)
    e, a = np.radians(rng.uniform(*elevation)), rng.uniform(0.0, 2 * np.pi)
    T_wc = look_at(c + distance * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)]), c)
    r = SynthScene(list(zip(meshes, T_wo, strict=True)), seed=seed, table_kind=table_kind).render(
        T_wc, DEFAULT_INTRINSICS, rng=np.random.default_rng([seed, 1]))
    T_cw = np.linalg.inv(T_wc)
    visible = [float((r.labels == k).sum()) / max(1, silhouette_px(m, T_cw @ T, DEFAULT_INTRINSICS))
               for k, (m, T) in enumerate(zip(meshes, T_wo, strict=True))]
    return Pile(r, meshes, np.stack([T_cw @ T for T in T_wo]), np.array(visible))


def silhouette_px(mesh: TexturedMesh, T_cam_obj: np.ndarray, intr: Intrinsics) -> int:
    """Pixels of the mesh's whole silhouette at T_cam_obj [4 x 4], on an image plane reaching half an image past
    every border of intr's (triangles in front of the camera filled)."""
    pc = transform_points(T_cam_obj, mesh.vertices)
    tri = mesh.triangles[(pc[mesh.triangles, 2] > 1e-3).all(axis=1)]
    uv = np.stack([pc[:, 0] / np.maximum(pc[:, 2], 1e-3) * intr.fx + intr.cx + intr.width / 2,
                   pc[:, 1] / np.maximum(pc[:, 2], 1e-3) * intr.fy + intr.cy + intr.height / 2], 1)
    canvas = np.zeros((2 * intr.height, 2 * intr.width), np.uint8)
    for t in np.rint(uv[tri]).astype(np.int32):  # (one polygon list in one call would fill overlaps even-odd)
        cv2.fillConvexPoly(canvas, t, 1)
    return int(canvas.sum())


@dataclass
class RowSequence:
    """A rendered sequence of copies in a row: frames [F] (`RenderedFrame`), T_cam_objs [F x K x 4 x 4] of every copy
    in every frame, seen [F x K] each copy's pixels in sight as a fraction of its pixels in the first frame."""

    frames: list[RenderedFrame]
    T_cam_objs: np.ndarray
    seen: np.ndarray


def render_row_sequence(mesh: TexturedMesh, copies: int, n_frames: int, seed: int, moving: int | None = None,
                        moves: range = range(0), hidden: int | None = None, hides: tuple[int, ...] = (),
                        occluder: TexturedMesh | None = None, distance: float = 0.65) -> RowSequence:
    """`copies` copies of `mesh` upright in a row on a wood table (`pile_poses`, 3-4 cm apart, seeded by `seed`), a
    static camera at `distance` (m) from the row's centre, 50 deg above the table. Copy `moving` slides 1 cm and
    turns 3 deg about the vertical in each frame of `moves`; in the frames `hides` `occluder` is held upright
    between the camera and copy `hidden`, past half the way to the camera, its x-z face to the camera (elsewhere
    out of the view). Depth noise seeded by (seed, frame)."""
    T_wo = pile_poses([mesh] * copies, np.random.default_rng(seed), lying_frac=0.0, gap=(0.03, 0.04),
                      sideways=0.01)
    away = make_T(np.eye(3), np.array([3.0, 0.0, 0.0]))
    objects = [(mesh, T) for T in T_wo] + ([(occluder, away)] if occluder is not None else [])
    scene = SynthScene(objects, seed=seed, table_kind="wood")
    centres = [transform_points(T, mesh.center[None])[0] for T in T_wo]
    c = np.mean(centres, axis=0)
    el, az = np.radians(50.0), np.radians(-80.0)
    eye = c + distance * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    T_wc = look_at(eye, c)
    T_occ = away
    if occluder is not None and hidden is not None:
        T_occ = look_at(centres[hidden] + 0.55 * (eye - centres[hidden]), eye)
        T_occ[:3, :3] = T_occ[:3, :3] @ np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
        T_occ[:3, 3] -= T_occ[:3, :3] @ occluder.center
    T_cw = np.linalg.inv(T_wc)
    frames, truths, seen = [], [], []
    for i in range(n_frames):
        poses = list(T_wo)
        if moving is not None:
            k = sum(1 for f in moves if f <= i)
            cm = centres[moving]
            R = rotvec_to_R(np.array([0.0, 0.0, np.radians(3.0 * k)]))
            poses[moving] = make_T(R, cm - R @ cm + np.array([0.0, 0.01 * k, 0.0])) @ T_wo[moving]
        extra = [T_occ if i in hides else away] if occluder is not None else []
        r = scene.render(T_wc, DEFAULT_INTRINSICS, rng=np.random.default_rng([seed, i]),
                         T_world_obj_override=poses + extra)
        frames.append(r)
        truths.append([T_cw @ T for T in poses])
        seen.append([float((r.labels == j).sum()) for j in range(copies)])
    seen_a = np.array(seen)
    return RowSequence(frames, np.array(truths), seen_a / np.maximum(seen_a[:1], 1.0))


BOP_MIN_VISIB = 0.1  # BOP19's test targets count the instances with at least this visib_fract


def write_bop_piles(piles: list[Pile], root: Path, obj_ids: list[list[int]], scene_id: int = 1) -> Path:
    """Write `piles` as one BOP test scene, root/test/{scene_id:06d} (image k = piles[k]: rgb/, depth/ in 0.1 mm,
    scene_camera.json, scene_gt.json with every object of the pile, scene_gt_info.json with each one's
    visib_fract), and root/test_targets_bop19.json: per image and object, inst_count = its instances with at least
    BOP_MIN_VISIB in sight (BOP19's rule). obj_ids: per pile, the BOP id of each of its objects (copies of one mesh
    share one). Returns the scene folder. Existing files are replaced."""
    scene = root / "test" / f"{scene_id:06d}"
    for sub in ("rgb", "depth"):
        (scene / sub).mkdir(parents=True, exist_ok=True)
    cams, gts, infos, targets = {}, {}, {}, []
    if len(obj_ids) != len(piles):
        raise ValueError(f"{len(piles)} piles, obj_ids for {len(obj_ids)}")
    for im_id, (pile, ids) in enumerate(zip(piles, obj_ids, strict=True)):
        if len(pile.T_cam_objs) != len(ids):
            raise ValueError(f"pile {im_id} holds {len(pile.T_cam_objs)} objects, obj_ids names {len(ids)}")
        f = pile.frame
        cv2.imwrite(str(scene / "rgb" / f"{im_id:06d}.png"), cv2.cvtColor(f.color, cv2.COLOR_RGB2BGR))
        cv2.imwrite(str(scene / "depth" / f"{im_id:06d}.png"),
                    np.clip(np.rint(f.depth * 10000), 0, 65535).astype(np.uint16))
        cams[str(im_id)] = {"cam_K": f.intrinsics.K.reshape(-1).tolist(), "depth_scale": 0.1}
        gts[str(im_id)] = [{"obj_id": int(o), "cam_R_m2c": T[:3, :3].reshape(-1).tolist(),
                            "cam_t_m2c": (T[:3, 3] * 1000.0).tolist()}
                           for o, T in zip(ids, pile.T_cam_objs, strict=True)]
        infos[str(im_id)] = [{"visib_fract": float(v)} for v in pile.visible]
        for o in sorted(set(ids)):
            n = sum(int(oid == o and v >= BOP_MIN_VISIB) for oid, v in zip(ids, pile.visible, strict=True))
            if n:
                targets.append({"im_id": im_id, "inst_count": n, "obj_id": int(o), "scene_id": scene_id})
    for name, doc in (("scene_camera.json", cams), ("scene_gt.json", gts), ("scene_gt_info.json", infos)):
        (scene / name).write_text(json.dumps(doc), encoding="utf-8")
    (root / "test_targets_bop19.json").write_text(json.dumps(targets, indent=1) + "\n", encoding="utf-8")
    return scene
