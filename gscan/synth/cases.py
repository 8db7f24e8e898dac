"""Rendered captures built to resemble the ones scanners get wrong, with exact ground truth.

Each builder writes a capture in the capture layout (`write_capture`; no masks: a hand-held capture has
none) and returns a `Case` saying which frames show the scanned object (their ground truth is in
annotated_poses/) and which show something else:

- `far_capture`: the object 1.5-2.5 m from the camera, where the depth noise grows with the square of the
  distance and the object fills a small part of the frame;
- `glossy_can_capture`: a can with a wrapped label lying on the table (curved), glossy: specular highlights
  that move with the viewpoint and lose the depth where they shine (`Gloss`); `glossy_bottle_capture`: a
  narrower one, farther away, standing on a turntable, whose label few pixels show (upright under the light from
  above, it shows no highlight);
- `ring_jump_capture`: 20-degree steps around two rings, the second 25 degrees higher than the first, joined
  by one 25-degree jump;
- `shifted_depth_capture`: the depth image shifted a few pixels against the colour image, as a sensor
  whose depth is not registered to its colour camera gives it;
- `two_camera_capture`: colour and depth from two cameras of different focal lengths, written with the depth
  camera's intrinsics only (a capture whose README gives one focal length for both);
- `inserted_frame_capture`: one frame of another object on another table in the middle of a capture;
- `twin_objects_capture`: copies of the same object side by side (a print repeated on the table);
- `two_scenes_capture`: a capture of one object followed by a few frames of another scene, two parts
  that no correct registration joins;
- `gap_orbit_capture`: two arcs of an orbit with a gap between them, low over a plain table: two parts of
  one scene that share no surface;
- `two_sided_captures`: two captures of one object, upright and upside down (or on its side), the object moved
  against the table between them: the captures of a template that knows both sides.

And objects that look the same from two sides: `half_turn_box`, a box printed alike under a half turn;
`half_turn_can`, a can whose label shows its print twice around. And `plain_part_scene`: a box of one colour
beside boxes of about its size, one printed and one plain, that its depth alone fits as well.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gscan.geometry.symmetry import Symmetries, axis_rotation
from gscan.geometry.transforms import rotvec_to_R, transform_points
from gscan.io.camera import Intrinsics
from gscan.synth.capture import default_distance, render_capture, write_capture
from gscan.synth.mesh import TexturedMesh, box_mesh, cylinder_mesh
from gscan.synth.render import DEFAULT_INTRINSICS, Gloss, RenderedFrame
from gscan.synth.textures import procedural_box_texture


@dataclass
class Case:
    """A written capture. frames: every frame name in order; object_frames: the frames of the scanned object
    (ground truth T_cam_obj in annotated_poses/); other_frames: frames of another scene (their annotated pose
    is that of another object, not comparable), which must stay unregistered or form a part of their own."""

    path: Path
    frames: list[str]
    object_frames: list[str]
    other_frames: list[str] = field(default_factory=list)
    mesh: TexturedMesh | None = None  # the scanned object


def _names(n: int) -> list[str]:
    return [f"{i:06d}" for i in range(n)]


def _write(out_dir: str | Path, frames: list[RenderedFrame], intr: Intrinsics, names: list[str] | None = None) -> Path:
    return write_capture(out_dir, frames, intr, names=names, write_masks=False)


def far_capture(mesh: TexturedMesh, out_dir: str | Path, distance: float, n_views: int = 10,
                elevation_deg: float = 30.0, table_kind: str = "newspaper", seed: int = 0,
                intr: Intrinsics = DEFAULT_INTRINSICS) -> Case:
    """n_views on one ring at `elevation_deg`, `distance` metres from the object's centre."""
    frames = render_capture(mesh, None, n_views, mode="static", intr=intr, seed=seed, distance=distance,
                            elevations_deg=(elevation_deg,), table_kind=table_kind)
    names = _names(len(frames))
    return Case(_write(out_dir, frames, intr), names, names, mesh=mesh)


def glossy_can(seed: int = 3, radius: float = 0.04, height: float = 0.2) -> TexturedMesh:
    """A can (closed cylinder) with a printed label wrapped around it."""
    return cylinder_mesh(radius, height, procedural_box_texture(seed, (1024, 768)), name="glossy_can")


def glossy_can_capture(out_dir: str | Path, n_views: int = 24, mode: str = "turntable", seed: int = 0,
                       gloss: Gloss = Gloss(), table_kind: str = "newspaper",
                       intr: Intrinsics = DEFAULT_INTRINSICS) -> Case:
    """A glossy can lying on its side (its curved label faces the camera and the light, so highlights show):
    a turntable (the can turns under a static camera and light, the highlight stays while the label moves)
    or a static orbit (two rings)."""
    mesh = glossy_can()
    R_lying = rotvec_to_R(np.array([np.pi / 2, 0.0, 0.0]))
    frames = render_capture(mesh, None, n_views, mode=mode, intr=intr, seed=seed, R_world_obj=R_lying,
                            gloss=gloss, elevations_deg=(30.0,) if mode == "turntable" else (30.0, 55.0),
                            table_kind=table_kind)
    names = _names(len(frames))
    return Case(_write(out_dir, frames, intr), names, names, mesh=mesh)


def glossy_bottle_frames(n_views: int = 36, seed: int = 0, distance: float = 0.9, table_kind: str = "plain",
                         intr: Intrinsics = DEFAULT_INTRINSICS) -> tuple[TexturedMesh, list[RenderedFrame]]:
    """(mesh, frames) of `glossy_bottle_capture`, rendered and not written."""
    mesh = cylinder_mesh(0.03, 0.2, procedural_box_texture(5, (1024, 768)), name="glossy_bottle")
    return mesh, render_capture(mesh, None, n_views, mode="turntable", intr=intr, seed=seed,
                                gloss=Gloss(shininess=20.0, dropout=0.25), elevations_deg=(20.0,), distance=distance,
                                table_kind=table_kind)


def glossy_bottle_capture(out_dir: str | Path, n_views: int = 36, seed: int = 0, distance: float = 0.9,
                          table_kind: str = "plain", intr: Intrinsics = DEFAULT_INTRINSICS) -> Case:
    """A glossy bottle (a narrow cylinder, 6 cm across, 20 cm tall, a printed label) standing on a turntable,
    `distance` from the camera at 20 deg elevation: it turns about its own axis, so its shape says nothing of the
    turn and only the curved label does, which few pixels show. Glossy (shininess 20, depth lost above a
    highlight term of 0.25), but upright under the default light from above its side faces the half vector about
    40 deg off: the highlight stays below one grey level and loses no depth (bench/bottle_edges.py)."""
    mesh, frames = glossy_bottle_frames(n_views, seed, distance, table_kind, intr)
    names = _names(len(frames))
    return Case(_write(out_dir, frames, intr), names, names, mesh=mesh)


def ring_jump_angles(step_deg: float = 20.0, jump_deg: float = 25.0, elevation_deg: float = 20.0,
                     ) -> list[tuple[float, float]]:
    """(elevation, azimuth) of views every `step_deg` around a ring at `elevation_deg`, then every `step_deg`
    around a ring `jump_deg` higher that starts above the first ring's last view (one jump of jump_deg)."""
    n = int(round(360.0 / step_deg))
    first = [(elevation_deg, k * step_deg) for k in range(n)]
    last_az = first[-1][1]
    return first + [(elevation_deg + jump_deg, last_az + k * step_deg) for k in range(n)]


def ring_jump_capture(mesh: TexturedMesh, out_dir: str | Path, step_deg: float = 20.0, jump_deg: float = 25.0,
                      elevation_deg: float = 20.0, table_kind: str = "newspaper", seed: int = 0,
                      intr: Intrinsics = DEFAULT_INTRINSICS) -> Case:
    """Two rings of `step_deg` steps joined by one `jump_deg` jump (`ring_jump_angles`)."""
    angles = ring_jump_angles(step_deg, jump_deg, elevation_deg)
    frames = render_capture(mesh, None, len(angles), mode="static", intr=intr, seed=seed, view_angles_deg=angles,
                            table_kind=table_kind)
    names = _names(len(frames))
    return Case(_write(out_dir, frames, intr), names, names, mesh=mesh)


def shift_image(img: np.ndarray, dx: int, dy: int) -> np.ndarray:
    """[H x W] image moved by (dx, dy) pixels (right, down); the uncovered border is 0 (no depth)."""
    out = np.zeros_like(img)
    H, W = img.shape[:2]
    ys, yd = (slice(0, H - dy), slice(dy, H)) if dy >= 0 else (slice(-dy, H), slice(0, H + dy))
    xs, xd = (slice(0, W - dx), slice(dx, W)) if dx >= 0 else (slice(-dx, W), slice(0, W + dx))
    out[yd, xd] = img[ys, xs]
    return out


def shifted_depth_capture(mesh: TexturedMesh, out_dir: str | Path, shift_px: tuple[int, int] = (5, 0),
                          n_views: int = 12, table_kind: str = "newspaper", seed: int = 0,
                          intr: Intrinsics = DEFAULT_INTRINSICS) -> Case:
    """A static capture (two rings) whose depth images are all shifted by `shift_px` (dx, dy) against the
    colour images: the error of a depth sensor used without registering its depth to its colour camera."""
    frames = render_capture(mesh, None, n_views, mode="static", intr=intr, seed=seed, table_kind=table_kind)
    for f in frames:
        f.depth = shift_image(f.depth, *shift_px)
    names = _names(len(frames))
    return Case(_write(out_dir, frames, intr), names, names, mesh=mesh)


def two_camera_capture(mesh: TexturedMesh, out_dir: str | Path, colour_scale: float = 0.9, n_views: int = 12,
                       table_kind: str = "newspaper", seed: int = 0, intr: Intrinsics = DEFAULT_INTRINSICS) -> Case:
    """A static capture (two rings) whose colour camera's focal length is `colour_scale` times its depth camera's
    (same pose and principal point), written with the depth camera's intrinsics as the only ones: 7-Scenes' README
    gives one focal length for a depth camera of 585 px and a colour camera of about 525 px."""
    colour_intr = Intrinsics(intr.fx * colour_scale, intr.fy * colour_scale, intr.cx, intr.cy, intr.width, intr.height)
    dist = default_distance(mesh, intr)
    frames = render_capture(mesh, None, n_views, mode="static", intr=colour_intr, seed=seed, table_kind=table_kind,
                            distance=dist)
    depths = render_capture(mesh, None, n_views, mode="static", intr=intr, seed=seed, table_kind=table_kind,
                            distance=dist)
    for f, d in zip(frames, depths, strict=True):
        f.depth = d.depth
    names = _names(len(frames))
    return Case(_write(out_dir, frames, intr), names, names, mesh=mesh)


def inserted_frame_capture(mesh: TexturedMesh, other: TexturedMesh, out_dir: str | Path, n_views: int = 10,
                           at: int | None = None, seed: int = 0, intr: Intrinsics = DEFAULT_INTRINSICS) -> Case:
    """A static capture of `mesh` on the newspaper table (one ring) with one frame of `other` on a wooden
    table inserted after frame `at` (default: the middle); the names sort in that order."""
    frames = render_capture(mesh, None, n_views, mode="static", intr=intr, seed=seed, elevations_deg=(35.0,))
    odd = render_capture(other, None, 1, mode="static", intr=intr, seed=seed + 1, table_kind="wood",
                         elevations_deg=(35.0,))[0]
    k = n_views // 2 if at is None else at
    names = _names(n_views + 1)
    ordered = frames[:k] + [odd] + frames[k:]
    return Case(_write(out_dir, ordered, intr, names), names, names[:k] + names[k + 1:], [names[k]], mesh=mesh)


def twin_objects_capture(mesh: TexturedMesh, out_dir: str | Path, copies: int = 1, n_views: int = 12,
                         elevations_deg: tuple[float, ...] = (30.0, 55.0), table_kind: str = "newspaper",
                         seed: int = 0, intr: Intrinsics = DEFAULT_INTRINSICS) -> Case:
    """A static capture of `mesh` with `copies` identical copies of it standing around it on the table (the
    camera orbits the first)."""
    frames = render_capture(mesh, None, n_views, mode="static", intr=intr, seed=seed, distractors=copies,
                            distractor_meshes=[mesh] * copies, elevations_deg=elevations_deg,
                            table_kind=table_kind)
    names = _names(len(frames))
    return Case(_write(out_dir, frames, intr), names, names, mesh=mesh)


def two_scenes_capture(mesh: TexturedMesh, other: TexturedMesh, out_dir: str | Path, n_views: int = 8,
                       n_other: int = 4, seed: int = 0, intr: Intrinsics = DEFAULT_INTRINSICS) -> Case:
    """`n_views` of `mesh` on the newspaper table (a ring at 35 degrees), then `n_other` of `other` on a wooden
    table (20-degree steps at 35 degrees): two parts that share nothing."""
    frames = render_capture(mesh, None, n_views, mode="static", intr=intr, seed=seed, elevations_deg=(35.0,))
    more = render_capture(other, None, n_other, mode="static", intr=intr, seed=seed + 1, table_kind="wood",
                          view_angles_deg=[(35.0, 20.0 * k) for k in range(n_other)])
    names = _names(n_views + n_other)
    return Case(_write(out_dir, frames + more, intr, names), names, names[:n_views], names[n_views:], mesh=mesh)


def gap_orbit_capture(mesh: TexturedMesh, out_dir: str | Path, n_first: int = 6, n_second: int = 4,
                      step_deg: float = 20.0, gap_deg: float = 120.0, elevation_deg: float = 10.0,
                      table_kind: str = "plain", seed: int = 0, intr: Intrinsics = DEFAULT_INTRINSICS) -> Case:
    """Two arcs of views `step_deg` apart on one ring, `n_first` then `n_second` views, the second starting
    `gap_deg` after the first ends: two halves of an orbit. Low (10 degrees) over a plain table, the halves see
    different faces of the object and nothing else in common: no correct registration joins them."""
    first = [(elevation_deg, k * step_deg) for k in range(n_first)]
    start = first[-1][1] + gap_deg
    angles = first + [(elevation_deg, start + k * step_deg) for k in range(n_second)]
    frames = render_capture(mesh, None, len(angles), mode="static", intr=intr, seed=seed, view_angles_deg=angles,
                            table_kind=table_kind)
    names = _names(len(frames))
    return Case(_write(out_dir, frames, intr), names, names, mesh=mesh)


#: the turn of the object about the vertical between the two captures of `two_sided_captures` (degrees)
TWO_SIDED_YAW_DEG = 40.0


def two_sided_frames(mesh: TexturedMesh, n_views: int = 12, upside_down: bool = True,
                     elevations_deg: tuple[float, ...] = (30.0, 55.0), table_kind: str = "newspaper",
                     seed: int = 0, intr: Intrinsics = DEFAULT_INTRINSICS,
                     ) -> tuple[list[RenderedFrame], list[RenderedFrame]]:
    """The frames of `two_sided_captures` (the up capture's, the down capture's), rendered, not written."""
    flip = rotvec_to_R(np.array([np.pi, 0.0, 0.0] if upside_down else [0.0, np.pi / 2, 0.0]))
    R_down = rotvec_to_R(np.array([0.0, 0.0, np.radians(TWO_SIDED_YAW_DEG)])) @ flip
    up, down = (render_capture(mesh, None, n_views, mode="static", intr=intr, seed=seed + k, R_world_obj=R,
                               elevations_deg=elevations_deg, table_kind=table_kind)
                for k, R in enumerate((None, R_down)))
    return up, down


def two_sided_captures(mesh: TexturedMesh, out_dir: str | Path, n_views: int = 12, upside_down: bool = True,
                       elevations_deg: tuple[float, ...] = (30.0, 55.0), table_kind: str = "newspaper",
                       seed: int = 0, intr: Intrinsics = DEFAULT_INTRINSICS) -> tuple[Case, Case]:
    """Two static captures of `mesh` on the same table, as a user scans both sides of an object: out_dir/up with
    the object upright, then out_dir/down with it turned upside down (about its x axis; on its side about y when
    `upside_down` is False) and by TWO_SIDED_YAW_DEG about the vertical: the object moved against the table, so
    the table agrees with no pose that joins the two. Ground truth (annotated_poses/) is in the mesh's frame in
    both, so the two captures' poses are comparable."""
    out = Path(out_dir)
    sides = two_sided_frames(mesh, n_views, upside_down, elevations_deg, table_kind, seed, intr)
    cases = []
    for name, frames in zip(("up", "down"), sides, strict=True):
        names = _names(len(frames))
        cases.append(Case(_write(out / name, frames, intr), names, names, mesh=mesh))
    return cases[0], cases[1]


def half_turn_box(size_xyz: tuple[float, float, float], seed: int = 0,
                  bottom_alike: bool = True) -> tuple[TexturedMesh, Symmetries]:
    """A box centred at the origin whose print is the same after a half turn about its z axis: the -x and -y faces
    repeat the +x and +y faces' print turned, the top's two triangles (split along a diagonal) carry one print,
    and so does the bottom's when bottom_alike (else the bottom keeps its own print, so only the bottom tells the
    turn). Returns the mesh and its symmetries: the three half turns hold in shape, the one about z in texture
    too when bottom_alike."""
    base = box_mesh(size_xyz, procedural_box_texture(seed), name="half-turn box")
    corners = base.vertices[base.triangles]  # [12 x 3 x 3]: two triangles per face, +x -x +y -y +z -z
    keep = [0, 1, 4, 5, 8, 10]
    Rz = axis_rotation(np.array([0.0, 0.0, 1.0]), np.zeros(3), np.pi)
    turned = transform_points(Rz, corners[keep].reshape(-1, 3)).reshape(-1, 3, 3)
    tris = [corners[keep], turned[:-1] if not bottom_alike else turned]
    uvs = [base.uv[keep], base.uv[keep[:-1]] if not bottom_alike else base.uv[keep]]
    if not bottom_alike:
        tris.append(corners[[11]])
        uvs.append(base.uv[[11]])
    flat = np.round(np.concatenate(tris).reshape(-1, 3), 9)
    verts, inverse = np.unique(flat, axis=0, return_inverse=True)
    mesh = TexturedMesh(verts, inverse.reshape(-1, 3).astype(np.int32), np.concatenate(uvs), base.texture,
                        name=base.name)
    turns = tuple(axis_rotation(np.eye(3)[i], np.zeros(3), np.pi) for i in (2, 0, 1))
    return mesh, Symmetries(turns, (bottom_alike, False, False))


def half_turn_can(radius: float, height: float, seed: int = 0) -> tuple[TexturedMesh, Symmetries]:
    """An upright can (`cylinder_mesh`, axis z) whose label repeats its print twice around and whose caps' prints are
    the same after a half turn. Returns the mesh and its symmetries: every turn about z and the flip about x hold
    in shape, the half turn about z in texture too."""
    tex = procedural_box_texture(seed, (512, 1024)).copy()
    h, w = tex.shape[:2]
    tex[h // 4:, w // 2:] = tex[h // 4:, :w // 2]  # the label: the side's texture, u in [0, 0.5) and [0.5, 1)
    ry, rx = int(np.ceil(0.12 * h)) + 2, int(np.ceil(0.12 * w)) + 2
    for cu in (0.25, 0.75):  # each cap's disc (uv centre (cu, 0.875)): its right half the left half turned
        cx, cy = int(round(cu * w)), int(round(0.125 * h))
        box = tex[cy - ry:cy + ry, cx - rx:cx + rx]
        box[:, rx:] = box[::-1, ::-1][:, rx:].copy()
    mesh = cylinder_mesh(radius, height, tex, name="half-turn can", segments=96)
    z, x = np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0])
    turns = (axis_rotation(z, np.zeros(3), np.pi), axis_rotation(x, np.zeros(3), np.pi))
    return mesh, Symmetries(turns, (True, False), ((z, np.zeros(3)),), (False,))


def plain_part_meshes() -> tuple[TexturedMesh, list[TexturedMesh]]:
    """A box of one colour (16 x 9 x 22 cm, centred at the origin) and the two boxes `plain_part_scene` puts beside
    it: a printed one of about its size (15 x 8 x 20 cm) and a flat plain one (20 x 12 x 6 cm)."""
    part = box_mesh((0.16, 0.09, 0.22), np.full((4, 4, 3), 235, np.uint8), name="plain_part")
    return part, [box_mesh((0.15, 0.08, 0.20), procedural_box_texture(3, (256, 384)), name="printed"),
                  box_mesh((0.20, 0.12, 0.06), np.full((4, 4, 3), 200, np.uint8), name="plain_flat")]


def plain_part_scene(seed: int, with_part: bool = True, colour: tuple[int, int, int] | None = None
                     ) -> tuple[RenderedFrame, np.ndarray]:
    """(frame, T_cam_part [4 x 4]) of `plain_part_meshes`' part upright at a random yaw (seeded) on a wood table with
    the two others around it (without it: they alone, the part's place empty), seen from 0.7 m at 35 deg
    elevation. colour: RGB, the part in that one colour instead (a twin of its shape in another colour)."""
    from gscan.geometry.transforms import look_at
    from gscan.synth.capture import place_distractors, rest_on_table
    from gscan.synth.render import SynthScene

    part, others = plain_part_meshes()
    if colour is not None:
        part = TexturedMesh(part.vertices, part.triangles, part.uv, np.full((4, 4, 3), colour, np.uint8),
                            name=f"{part.name}_twin")
    rng = np.random.default_rng(seed)
    T_world_part = rest_on_table(part, rotvec_to_R(np.array([0.0, 0.0, rng.uniform(0, 2 * np.pi)])))
    placed = list(zip(others, place_distractors(part, T_world_part, others, rng), strict=True))
    c = T_world_part[:3, 3] + [0.0, 0.0, 0.11]
    e, a = np.radians(35.0), np.radians(30.0)
    T_world_cam = look_at(c + 0.7 * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)]), c)
    objs = ([(part, T_world_part)] if with_part else []) + placed
    r = SynthScene(objs, seed=seed, table_kind="wood").render(T_world_cam, DEFAULT_INTRINSICS,
                                                              rng=np.random.default_rng([seed, 1]))
    return r, np.linalg.inv(T_world_cam) @ T_world_part
