"""Coverage of viewing directions (gscan.geometry.coverage): the lattice, the one definition the capture preview
and the template share, the regions named missing, what a template stores and what `scan`, `info` and the viewer
report."""
from __future__ import annotations

import json
import sqlite3
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from gscan import synth
from gscan.capture.motion import Coverage, up_frame
from gscan.errors import InputError
from gscan.geometry.coverage import (
    COVERAGE_DIRECTIONS,
    CoverageMap,
    cells_within,
    coverage_map,
    lattice,
    regions,
    template_coverage,
    view_counts,
)
from gscan.geometry.mesh import MeshData
from gscan.geometry.transforms import look_at
from gscan.template.db import TemplateDB
from gscan.template.reports import template_info

ROOT = Path(__file__).resolve().parents[1]
INTR = synth.DEFAULT_INTRINSICS.scaled(0.5)  # 320 x 240: small and fast, still registers


def _dir(elev_deg: float, az_deg: float) -> np.ndarray:
    e, a = np.radians(elev_deg), np.radians(az_deg)
    return np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])


def _upright_dirs(step_deg: float = 10.0) -> np.ndarray:
    """Views of an upright capture: two rings at 30 and 55 deg above the table, every `step_deg` of azimuth, the
    first one from -y."""
    return np.array([_dir(el, -90.0 + az) for el in (30.0, 55.0) for az in np.arange(0.0, 360.0, step_deg)])


def _poses(dirs: np.ndarray, centre: np.ndarray, dist: float = 0.5) -> list[np.ndarray]:
    """T_obj_cam of cameras at `dist` from `centre` along `dirs` [V x 3], looking at it."""
    return [look_at(centre + dist * d, centre) for d in dirs]


def _open_box(size=(0.14, 0.09, 0.07)) -> MeshData:
    """A box standing on z = 0 as a fused scan sees it: every face but the bottom (split finely, so that the
    faces' areas are spread as a TSDF mesh's are)."""
    box = synth.box_mesh(size, np.full((8, 8, 3), 128, np.uint8))
    V, F = box.vertices - [0.0, 0.0, box.vertices[:, 2].min()], box.triangles
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    return MeshData(V, F[n[:, 2] > -1e-9 * np.abs(n).max()])


# ----------------------------------------------------------------------------------------- the lattice
@given(st.integers(1, 2000))
def test_lattice_is_unit_equal_area_and_symmetric(n):
    D = lattice(n)
    assert D.shape == (n, 3)
    np.testing.assert_allclose(np.linalg.norm(D, axis=1), 1.0, atol=1e-12)
    z = D[:, 2]
    k = np.arange(n)
    # cell k is the centre of the k-th of n bands of equal height (equal area on the sphere)
    assert np.all((z < 1 - 2 * k / n) & (z > 1 - 2 * (k + 1) / n))
    np.testing.assert_allclose(z + z[::-1], 0.0, atol=1e-12)  # as many cells below the equator as above
    if n > 1:  # consecutive cells turn by the golden angle
        turn = np.angle((D[1:, 0] + 1j * D[1:, 1]) / (D[:-1, 0] + 1j * D[:-1, 1]))
        np.testing.assert_allclose(np.mod(turn, 2 * np.pi), np.mod(np.pi * (1 + 5 ** 0.5), 2 * np.pi), atol=1e-9)


@given(st.tuples(*(st.floats(-1.0, 1.0),) * 3).filter(lambda v: np.linalg.norm(v) > 1e-3))
def test_every_view_sees_a_few_cells(v):
    """The lattice's cells are closer together than the radius: any one view marks at least one cell, and a
    handful at most."""
    hit = cells_within(lattice(), np.array(v))
    assert 1 <= hit.sum() <= 8
    assert view_counts(np.array([v]), lattice()).tolist() == hit.astype(int).tolist()


def test_views_from_everywhere_cover_everything_and_nothing_is_missing():
    c = coverage_map(lattice())
    assert c.share == 1.0 and c.covered == COVERAGE_DIRECTIONS and c.missing() == []
    assert coverage_map(np.zeros((0, 3))).share == 0.0


_unit_vectors = st.tuples(*(st.floats(-1.0, 1.0),) * 3).filter(lambda v: np.linalg.norm(v) > 1e-3)


@given(_unit_vectors, st.lists(_unit_vectors, min_size=1, max_size=6), _unit_vectors)
def test_regions_are_a_partition_and_more_views_never_see_less(front, views, extra):
    parts = regions(lattice(), np.array(front))
    assert np.array_equal(np.sum([m.astype(int) for m in parts.values()], axis=0), np.ones(COVERAGE_DIRECTIONS, int))
    assert parts["top"].sum() == np.sum(lattice()[:, 2] > np.sin(np.radians(50))) and parts["bottom"].any()
    V = np.array(views, dtype=float)
    before, after = coverage_map(V), coverage_map(np.vstack([V, extra]))
    assert np.all(after.counts >= before.counts) and after.share >= before.share
    b, a = before.region_shares(), after.region_shares()
    assert all(a[k] >= b[k] for k in b) and len(after.missing()) <= len(before.missing())


def test_regions_split_the_sphere_and_are_named_about_the_first_view():
    D = lattice()
    parts = regions(D, np.array([0.0, -1.0, 0.0]))
    assert sorted(parts) == ["back", "bottom", "front", "left", "right", "top"]
    assert np.array_equal(np.sum([m.astype(int) for m in parts.values()], axis=0), np.ones(len(D), int))
    # views only from the front quarter (-y) and a little above: back, sides and bottom missing, the front not
    c = coverage_map(np.array([_dir(el, -90.0 + az) for el in (0.0, 20.0, 40.0) for az in range(-40, 41, 10)]),
                     front=np.array([0.0, -1.0, 0.0]))
    missing = " ".join(c.missing())
    assert "the front" not in missing
    for name in ("the back", "the left side", "the right side", "the bottom", "the top"):
        assert name in missing, (name, c.missing())
    assert "the bottom was not seen: scan the object upside down" in missing


# ------------------------------------------------------------------------------- one definition
def test_the_capture_preview_and_the_template_use_one_definition():
    """The same viewing directions give the same counts, share and missing regions in the capture preview's
    `Coverage` and in a template's coverage (without a mesh: views alone)."""
    rng = np.random.default_rng(3)
    dirs = _upright_dirs(15.0)[rng.permutation(48)]
    preview = Coverage()
    for d in dirs:
        preview.add(d)
    centre = np.array([0.01, -0.02, 0.05])
    template = template_coverage(_poses(dirs, centre), None)  # no mesh: directions from the origin
    plain = coverage_map(dirs)
    shifted = template_coverage(_poses(dirs, np.zeros(3)), None)
    for c in (plain, shifted):
        assert np.array_equal(preview.counts, c.counts)
        assert preview.map().share == c.share and preview.map().missing() == c.missing()
    assert preview.covered == plain.covered
    assert not np.array_equal(template.counts, plain.counts)  # the centre matters: this is a real comparison
    # an upright capture from views alone: the bottom is not seen, nor the sides' lower parts
    said = plain.missing()
    assert said[0].startswith("the bottom was not seen"), said
    assert all(m.startswith("the lower part of the ") and m.endswith("as you go round") for m in said[1:]), said


def test_observed_surface_sees_the_top_but_never_the_bottom():
    """A box's fused surface (open at the bottom) seen from 30 and 55 deg: its top faces count for the top
    cells no camera was above; nothing points down, so the bottom stays missing. Hole filling's faces do not
    count, and the faces' winding does not matter."""
    box = _open_box()
    centre = 0.5 * (box.vertices.min(0) + box.vertices.max(0))
    poses = _poses(_upright_dirs(), centre)
    c = template_coverage(poses, box)
    views_only = template_coverage(poses, None)
    shares = c.region_shares()
    assert shares["top"] == 1.0 and shares["bottom"] < 0.25, shares
    overhead = lattice()[:, 2] > np.sin(np.radians(80.0))  # beyond the 55 deg ring's reach
    assert not views_only.seen[overhead].any() and c.seen[overhead].all() and c.share > views_only.share
    assert 0.4 < c.share < 0.8, c.share
    assert [m.split(":")[0] for m in c.missing()] == ["the bottom was not seen"]
    flipped = template_coverage(poses, MeshData(box.vertices, box.triangles[:, ::-1]))
    assert np.array_equal(flipped.seen, c.seen)
    # a filled bottom (faces flagged `filled`) is no observation: the same map
    full = synth.box_mesh((0.14, 0.09, 0.07), np.full((8, 8, 3), 128, np.uint8))
    V = full.vertices - [0.0, 0.0, full.vertices[:, 2].min()]
    n = np.cross(V[full.triangles[:, 1]] - V[full.triangles[:, 0]], V[full.triangles[:, 2]] - V[full.triangles[:, 0]])
    filled = n[:, 2] < 0
    with_fill = template_coverage(poses, MeshData(V, full.triangles, filled=filled))
    assert np.array_equal(with_fill.seen, c.seen)
    # seen from below too (the object scanned upside down as well): the bottom is covered
    below = _poses(np.concatenate([_upright_dirs(), -_upright_dirs()]), centre)
    assert template_coverage(below, MeshData(V, full.triangles)).missing() == []


def test_a_template_whose_up_is_not_z_is_mapped_to_the_same_coverage():
    """A scan without a support plane keeps the first camera's axes (up = -y): the same views and surface in
    that frame, with up given, give the same map as in a z-up frame, and the viewer's points are in the
    object frame."""
    from gscan.geometry.coverage import up_rotation

    box = _open_box()
    centre = 0.5 * (box.vertices.min(0) + box.vertices.max(0))
    poses = _poses(_upright_dirs(), centre)
    z_up = template_coverage(poses, box)
    Q = np.eye(4)
    Q[:3, :3] = up_rotation(np.array([0.0, -1.0, 0.0])).T  # z-up coordinates -> the camera-like object frame
    assert np.allclose(Q[:3, :3] @ [0.0, 0.0, 1.0], [0.0, -1.0, 0.0])
    turned = template_coverage([Q @ T for T in poses], MeshData(box.vertices @ Q[:3, :3].T, box.triangles),
                               up=(0.0, -1.0, 0.0))
    assert np.array_equal(turned.counts, z_up.counts) and np.array_equal(turned.seen, z_up.seen)
    assert turned.missing() == z_up.missing() and turned.missing()[0].startswith("the bottom was not seen")
    np.testing.assert_allclose(turned.directions_obj, z_up.directions @ Q[:3, :3].T, atol=1e-12)
    back = CoverageMap.from_meta(json.loads(json.dumps(turned.to_meta())))
    np.testing.assert_allclose(back.directions_obj, turned.directions_obj, atol=1e-8)
    # the up not given: the camera-like frame's "bottom" would be its -z, and the words wrong
    assert template_coverage([Q @ T for T in poses], MeshData(box.vertices @ Q[:3, :3].T, box.triangles)
                             ).missing() != z_up.missing()


def test_up_frame_of_a_rendered_frame_is_the_table_normal():
    """The preview's up (`up_frame`) from one rendered frame 40 deg above a table: the table's normal in that
    camera, within 2 deg; the camera's x stays horizontal."""
    mesh = synth.box_mesh((0.14, 0.09, 0.07), synth.procedural_box_texture(3, (512, 768)))
    fr = synth.render_capture(mesh, None, 1, mode="static", elevations_deg=(40.0,), intr=INTR, seed=2)[0]
    R = up_frame(fr.depth, INTR)
    up_cam = np.linalg.inv(fr.T_world_cam)[:3, 2]  # world z (the table's normal) in the camera
    assert np.degrees(np.arccos(np.clip(R[2] @ up_cam, -1, 1))) < 2.0
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)
    assert abs(R[0][1]) < 1e-3 and R[0][0] > 0.999  # the camera's x, made horizontal: it was horizontal


# ------------------------------------------------------------------------------- stored and reported
def test_the_map_round_trips_through_the_template_and_old_templates_say_unknown(tmp_path):
    c = template_coverage(_poses(_upright_dirs(), np.zeros(3)), _open_box())
    path = tmp_path / "t.gscan"
    with TemplateDB.create(path, meta={"source": "scan"}) as db:
        assert db.coverage() is None
        db.mark_complete()
    info = template_info(path).to_json()
    assert "coverage" in info and info["coverage"] is None  # a template made before coverage: unknown
    with TemplateDB.open(path, writable=True) as db:
        db.set_meta("coverage", c.to_meta())
    with TemplateDB.open(path) as db:
        back = db.coverage()
    assert back is not None and np.array_equal(back.counts, c.counts) and np.array_equal(back.seen, c.seen)
    info = template_info(path).to_json()
    assert set(info["coverage"]) == {"share", "missing"} and info["coverage"] == c.to_json()
    assert isinstance(info["coverage"]["share"], float) and all(isinstance(m, str) for m in info["coverage"]["missing"])
    con = sqlite3.connect(path)
    con.execute("UPDATE meta SET value=? WHERE key='coverage'", (json.dumps(c.to_meta() | {"counts": [1, 2]}),))
    con.commit()
    con.close()
    with pytest.raises(InputError, match="coverage"), TemplateDB.open(path) as db:
        db.coverage()
    with pytest.raises(ValueError):
        CoverageMap.from_meta({"lattice": "fibonacci", "directions": 2, "counts": [-1, 0], "surface": [0, 0],
                               "front": [0, -1, 0]})


def test_cli_info_names_unknown_and_missing_coverage(tmp_path):
    """`gscan info`: "coverage: unknown" for a template without a map; the share and each missing region
    otherwise; `--json` carries the contract's object."""
    path = tmp_path / "t.gscan"
    with TemplateDB.create(path, meta={"source": "scan"}) as db:
        db.mark_complete()
    r = _run("info", str(path))
    assert r.returncode == 0 and "coverage: unknown" in r.stderr, r.stderr
    c = template_coverage(_poses(_upright_dirs(), np.zeros(3)), _open_box())
    with TemplateDB.open(path, writable=True) as db:
        db.set_meta("coverage", c.to_meta())
    r = _run("info", str(path))
    assert f"coverage: {c.share:.0%} of the viewing directions seen" in r.stderr, r.stderr
    assert "missing: the bottom was not seen: scan the object upside down" in r.stderr
    r = _run("info", str(path), "--json")
    assert json.loads(r.stdout)["coverage"] == c.to_json()


def test_a_mesh_template_covers_the_whole_sphere(meshes_dir):
    """template-from-mesh's default 36 views around a CAD model (and its closed surface) see every side."""
    from gscan.scanning.cad import view_poses

    mesh = synth.load_textured_mesh(meshes_dir / "Vans_Cereal_Honey_Nut_Crunch_11_oz_box" / "model_0.obj")
    c = template_coverage(view_poses(mesh, 36), mesh.to_mesh())
    assert c.share >= 0.98 and c.missing() == [], (c.share, c.missing())
    assert template_coverage(view_poses(mesh, 8), mesh.to_mesh()).share < 0.6  # a real threshold


def test_viewer_draws_the_map():
    """The viewer's coverage layer: a point per cell around the object, grey where nothing saw it, blue where
    only the surface did, view-count colours elsewhere."""
    from gscan.viewer.draw import COUNT_COLORS, SURFACE_SEEN_COLOR
    from gscan.viewer.scene import COVERAGE_RADIUS, coverage_points

    box = _open_box()
    c = template_coverage(_poses(_upright_dirs(), np.zeros(3)), box)
    pts, cols = coverage_points(c, np.array([0.1, 0.0, 0.0]), 0.2)
    assert pts.shape == (COVERAGE_DIRECTIONS, 3) and cols.shape == (COVERAGE_DIRECTIONS, 3)
    np.testing.assert_allclose(np.linalg.norm(pts - [0.1, 0.0, 0.0], axis=1), COVERAGE_RADIUS * 0.2, rtol=1e-6)
    unseen = ~c.seen
    assert unseen.any() and (cols[unseen] == COUNT_COLORS[0]).all()
    only_surface = (c.counts == 0) & c.surface
    assert only_surface.any() and (cols[only_surface] == SURFACE_SEEN_COLOR).all()
    assert (cols[c.counts >= 3] == COUNT_COLORS[3]).all()


def _run(*args: str, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "gscan.cli", *args], capture_output=True, text=True, cwd=ROOT,
                          timeout=timeout, check=False)


@pytest.mark.slow
def test_an_upright_scan_reports_the_bottom_missing(tmp_path, capsys):
    """A rendered upright capture (cameras 30 and 55 deg above the table) scanned: the scan's `--json` object and
    `info --json` give the share (well below 1) and name the bottom missing; the scan's summary says it too."""
    import gscan
    from gscan.cli.scan import print_scan_summary

    mesh = synth.box_mesh((0.14, 0.09, 0.07), synth.procedural_box_texture(3, (512, 768)))
    synth.render_capture(mesh, tmp_path / "cap", 12, mode="static", elevations_deg=(30.0, 55.0), intr=INTR)
    out = tmp_path / "box.gscan"
    res = gscan.scan(tmp_path / "cap", out)
    cov = json.loads(json.dumps(res.to_json()))["coverage"]  # what `scan --json` prints
    assert set(cov) == {"share", "missing"} and 0.3 < cov["share"] < 0.8, cov
    assert any(m.startswith("the bottom was not seen") for m in cov["missing"]), cov
    assert not any(m.startswith("the top") for m in cov["missing"]), cov  # seen through its surface
    print_scan_summary(res)
    said = capsys.readouterr().err
    assert f"coverage: {cov['share']:.0%} of the viewing directions seen" in said
    assert "missing: the bottom was not seen: scan the object upside down" in said
    r = _run("info", str(out), "--json")
    assert json.loads(r.stdout)["coverage"] == cov, r.stderr
    with TemplateDB.open(out) as db:
        c = db.coverage()
        assert c is not None and int(c.counts.sum()) >= 12 and round(c.share, 4) == cov["share"]


def test_the_mesh_export_marks_observed_and_filled_faces(tmp_path):
    """The PLY export's face property `filled`, read back with trimesh: 0 on every face of the fused surface
    (the open box as a scan fuses it), 1 on the faces closing its open bottom added; all 0 with the holes kept."""
    import trimesh

    from gscan.exporters import export

    box = _open_box()
    path = tmp_path / "t.gscan"
    with TemplateDB.create(path, meta={"source": "scan"}) as db:
        db.set_mesh(box)
        db.mark_complete()
    export(path, "ply", tmp_path / "closed.ply")
    export(path, "ply", tmp_path / "open.ply", close=False)
    closed = trimesh.load(tmp_path / "closed.ply", process=False)
    filled = closed.metadata["_ply_raw"]["face"]["data"]["filled"].astype(bool)
    assert filled.shape == (len(closed.faces),) and filled.sum() == len(closed.faces) - len(box.triangles) > 0
    assert closed.is_watertight
    observed = closed.vertices[closed.faces[~filled]]
    np.testing.assert_allclose(np.sort(observed.reshape(-1, 3), axis=0),
                               np.sort(box.vertices[box.triangles].reshape(-1, 3), axis=0), atol=1e-6)
    assert np.allclose(closed.vertices[closed.faces[filled]][..., 2], 0.0, atol=1e-6)  # the bottom cap
    kept = trimesh.load(tmp_path / "open.ply", process=False)
    flags = kept.metadata["_ply_raw"]["face"]["data"]["filled"]
    assert len(kept.faces) == len(box.triangles) and flags.shape == (len(kept.faces),) and not flags.any()
