"""Object symmetries (gscan.scanning.symmetry): found on templates of rendered plain and printed shapes and a real
scanned object, stored in the template, exported to BOP's models_info.json and shown by `info`.

The BOP toolkit check reads the export with the toolkit's own `bop_toolkit_lib.misc.get_symmetry_transformations`
from a checkout of github.com/thodan/bop_toolkit named by the environment variable GSCAN_BOP_TOOLKIT (the toolkit is
not a package on PyPI); without it that one test is skipped and the same file is read by BOP's documented layout.
"""
from __future__ import annotations

import importlib
import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from gscan import synth
from gscan.errors import InputError
from gscan.exporters import export
from gscan.geometry.symmetry import SHAPE, SHAPE_TEXTURE, Symmetries, axis_rotation, turn_of
from gscan.scanning.cad import template_from_mesh
from gscan.scanning.symmetry import SymmetryParams, detect_symmetries, surface_of_mesh, surface_of_textured_mesh
from gscan.template.db import TemplateDB
from gscan.template.reports import template_info

PLAIN = np.full((64, 96, 3), 170, np.uint8)
# the cylinder and the unequal box lie off their mesh frame's origin, so their turns move points: a translation in
# the wrong units (BOP's are mm) cannot go unnoticed
CYLINDER_AT = np.array([0.02, -0.01, 0.03])
BOX_AT = np.array([-0.03, 0.02, 0.01])
ASYMMETRIC = "Tena_Pads_Heavy_Long_42_pads"  # a soft pack of pads: no turn maps it onto itself


def _moved(mesh: synth.TexturedMesh, t: np.ndarray) -> synth.TexturedMesh:
    return synth.TexturedMesh(mesh.vertices + t, mesh.triangles, mesh.uv, mesh.texture, name=mesh.name)


def _template(mesh: synth.TexturedMesh, path: Path) -> Path:
    obj = synth.save_textured_mesh(mesh, path.with_suffix(".obj"))
    template_from_mesh(obj, path, n_views=4)
    return path


def _turns(s: Symmetries) -> list[tuple[np.ndarray, float]]:
    return [turn_of(S) for S in s.discrete]


def _has_turn(s: Symmetries, axis: tuple[float, float, float], angle: float) -> bool:
    a = np.asarray(axis, float)
    return any(abs(abs(float(ax @ a)) - 1) < 1e-4 and (abs(ang - angle) < 1.0 or abs(ang - (360 - angle)) < 1.0)
               for ax, ang in _turns(s))


@pytest.fixture(scope="module")
def templates(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("sym")
    meshes = {"cylinder": _moved(synth.cylinder_mesh(0.04, 0.12, PLAIN), CYLINDER_AT),
              "square_box": synth.box_mesh((0.06, 0.06, 0.12), PLAIN),
              "box": _moved(synth.box_mesh((0.05, 0.08, 0.12), PLAIN), BOX_AT),
              "printed_box": synth.box_mesh((0.05, 0.08, 0.12), synth.procedural_box_texture(3, (512, 768)))}
    return {k: _template(m, root / f"{k}.gscan") for k, m in meshes.items()}


def _symmetries(path: Path) -> Symmetries:
    with TemplateDB.open(path) as db:
        return db.symmetries()


def test_plain_cylinder_is_a_body_of_revolution(templates):
    s = _symmetries(templates["cylinder"])
    assert len(s.continuous) == 1
    axis, offset = s.continuous[0]
    assert abs(abs(axis[2]) - 1) < 1e-4  # z (axes from surface samples)
    assert np.linalg.norm((offset - CYLINDER_AT)[:2]) < 1e-3  # through the centre
    assert len(s.discrete) == 1  # and its flip end over end: an axis across it
    ax, ang = turn_of(s.discrete[0])
    assert abs(ang - 180) < 1 and abs(ax[2]) < 1e-2
    assert s.holds_in == SHAPE_TEXTURE


def test_plain_box_with_a_square_section_turns_by_quarters(templates):
    s = _symmetries(templates["square_box"])
    assert not s.continuous
    assert len(s.discrete) == 7  # the square prism's group: 4 turns about z, 4 flips across it, less the identity
    assert _has_turn(s, (0, 0, 1), 90) and _has_turn(s, (0, 0, 1), 180)
    assert _has_turn(s, (1, 0, 0), 180) and _has_turn(s, (0, 1, 0), 180)
    assert _has_turn(s, (np.sqrt(0.5), np.sqrt(0.5), 0), 180)
    assert s.holds_in == SHAPE_TEXTURE


def test_plain_box_with_unequal_sides_turns_by_halves(templates):
    s = _symmetries(templates["box"])
    assert not s.continuous and len(s.discrete) == 3
    for axis in ((1, 0, 0), (0, 1, 0), (0, 0, 1)):
        assert _has_turn(s, axis, 180)
    for S in s.discrete:  # each about an axis through the box's centre
        assert np.allclose(S[:3, :3] @ BOX_AT + S[:3, 3], BOX_AT, atol=1e-3)
    assert s.holds_in == SHAPE_TEXTURE


def test_printed_box_is_symmetric_in_shape_only(templates):
    s = _symmetries(templates["printed_box"])
    assert len(s.discrete) == 3
    assert s.holds_in == SHAPE and not any(s.discrete_in_texture)
    assert not s.in_texture()


def test_real_asymmetric_object_has_none(meshes_dir):
    mesh = synth.load_textured_mesh(meshes_dir / ASYMMETRIC / "model_0.obj")
    s = detect_symmetries(surface_of_textured_mesh(mesh, SymmetryParams().reference_samples), 0.001)
    assert not s and s.holds_in is None


def test_an_open_bottom_neither_makes_nor_breaks_a_symmetry():
    """A box whose bottom face was never seen (a scan's mesh is open there) keeps its turns; a box whose top is
    open too but whose one side is pushed out keeps only what that side allows: the hole does not decide."""
    box = synth.box_mesh((0.05, 0.08, 0.12), PLAIN).to_mesh()
    keep = box.vertices[box.triangles].mean(axis=1)[:, 2] > -0.059  # the two triangles of the -z face go
    from gscan.geometry.mesh import MeshData

    open_box = MeshData(box.vertices, box.triangles[keep], box.vertex_colors)
    s = detect_symmetries(surface_of_mesh(open_box, 60000), 0.001)
    assert len(s.discrete) == 3
    V = box.vertices.copy()
    V[V[:, 0] > 0, 0] += 0.012  # +x side moved out: the box is 6.2 cm deep, off centre in x by design
    V -= 0.5 * (V.max(axis=0) + V.min(axis=0))
    s2 = detect_symmetries(surface_of_mesh(MeshData(V, box.triangles[keep], box.vertex_colors), 60000), 0.001)
    assert len(s2.discrete) == 3  # a wider box is still a box
    wedge = V.copy()
    wedge[(wedge[:, 0] > 0) & (wedge[:, 1] > 0), 2] += 0.02  # one top corner raised: no turn left
    s3 = detect_symmetries(surface_of_mesh(MeshData(wedge, box.triangles[keep], box.vertex_colors), 60000), 0.001)
    assert not s3.discrete


def test_template_without_symmetries_meta_has_none(templates, tmp_path):
    import shutil
    import sqlite3

    path = tmp_path / "old.gscan"
    shutil.copy(templates["box"], path)
    with sqlite3.connect(path) as conn:  # as a template written before symmetries were found
        conn.execute("DELETE FROM meta WHERE key='symmetries'")
    conn.close()
    assert not _symmetries(path)
    assert template_info(path).to_json()["symmetries"]["holds_in"] is None
    with TemplateDB.open(path, writable=True) as db:
        db.set_meta("symmetries", {"discrete": [[1, 2, 3]]})
    with pytest.raises(InputError, match="old.gscan"):
        _symmetries(path)


def test_info_shows_symmetries(templates):
    from typer.testing import CliRunner

    from gscan.cli import app

    info = template_info(templates["square_box"]).to_json()["symmetries"]
    assert info["holds_in"] == SHAPE_TEXTURE and len(info["discrete"]) == 7 and info["continuous"] == []
    assert np.asarray(info["discrete"]).shape == (7, 4, 4)
    r = CliRunner().invoke(app, ["info", str(templates["cylinder"])])
    assert r.exit_code == 0, r.output
    lines = [ln for ln in r.output.splitlines() if ln.startswith("symmetry:")]
    assert len(lines) == 2 and "revolution about axis" in lines[0] and "shape and texture" in lines[0]
    r = CliRunner().invoke(app, ["info", str(templates["printed_box"])])
    assert sum("shape only" in ln for ln in r.output.splitlines()) == 3


def _bop_export(path: Path, out: Path) -> dict:
    # the template's mesh as it is (--keep-holes): closing the cylinder's unshared-vertex mesh moves its surface
    # near (40, 0, +-60) mm by several mm, which no symmetry of the object can follow
    export(path, "bop", out, close=False)
    return json.loads((out / "models" / "models_info.json").read_text())["1"]


def _model_surface(out: Path) -> tuple[np.ndarray, cKDTree, float]:
    """The exported model's vertices (mm), a tree of its dense surface samples, and its diameter (mm)."""
    import trimesh

    from gscan.geometry.mesh import MeshData

    tm = trimesh.load(str(out / "models" / "obj_000001.ply"), force="mesh", process=False)
    V = np.asarray(tm.vertices, np.float64)
    surf = surface_of_mesh(MeshData(V, np.asarray(tm.faces), None), 200000)
    info = json.loads((out / "models" / "models_info.json").read_text())["1"]
    return V, cKDTree(surf.points), float(info["diameter"])


def _maps_onto_itself(trans: list[tuple[np.ndarray, np.ndarray]], out: Path) -> None:
    """Each (R, t [mm]) maps the exported model's vertices onto its surface within BOP's own symmetry tolerance,
    max(15 um, 0.01 x diameter)."""
    V, tree, diam = _model_surface(out)
    for R, t in trans:
        d, _ = tree.query(V @ R.T + t.reshape(3))
        assert d.max() < max(0.015, 0.01 * diam), (R, t, d.max())


def test_bop_models_info_symmetries_by_the_documented_layout(templates, tmp_path):
    info = _bop_export(templates["cylinder"], tmp_path / "cyl")
    assert len(info["symmetries_continuous"]) == 1 and len(info["symmetries_discrete"]) == 1
    c = info["symmetries_continuous"][0]
    trans = [(S[:3, :3], S[:3, 3]) for S in (np.reshape(x, (4, 4)) for x in info["symmetries_discrete"])]
    trans += [(axis_rotation(np.asarray(c["axis"]), np.asarray(c["offset"]), np.radians(a))[:3, :3],
               axis_rotation(np.asarray(c["axis"]), np.asarray(c["offset"]), np.radians(a))[:3, 3])
              for a in (17.0, 90.0, 213.0)]
    _maps_onto_itself(trans, tmp_path / "cyl")
    printed = _bop_export(templates["printed_box"], tmp_path / "printed")  # BOP keeps what texture does not resolve
    assert "symmetries_discrete" not in printed and "symmetries_continuous" not in printed


def test_bop_models_info_read_by_the_bop_toolkit(templates, tmp_path):
    toolkit = os.environ.get("GSCAN_BOP_TOOLKIT")
    if not toolkit:
        pytest.skip("GSCAN_BOP_TOOLKIT does not name a checkout of the BOP toolkit")
    sys.path.insert(0, toolkit)
    try:  # the toolkit is not a dependency of gscan: imported by name from the checkout given
        misc = importlib.import_module("bop_toolkit_lib.misc")
    finally:
        sys.path.remove(toolkit)
    for name in ("cylinder", "square_box", "box"):
        out = tmp_path / name
        info = _bop_export(templates[name], out)
        trans = misc.get_symmetry_transformations(info, max_sym_disc_step=0.01)
        n = len(_symmetries(templates[name]).elements(steps=int(np.ceil(np.pi / 0.01))))
        assert len(trans) == n > 1
        _maps_onto_itself([(np.asarray(t["R"]), np.asarray(t["t"])) for t in trans[:: max(1, len(trans) // 40)]],
                          out)


@pytest.mark.slow
def test_scanned_printed_box_turns_in_shape_only(tmp_path):
    """A rendered scan of a printed box on a table (its bottom never seen, the mesh open there): its three half
    turns are found in the template frame (z up, x and y along the box), in shape only; stored as scan --json says."""
    from gscan.scanning.api import scan

    mesh = synth.box_mesh((0.14, 0.09, 0.07), synth.procedural_box_texture(3, (512, 768)))
    synth.render_capture(mesh, tmp_path / "cap", 12, mode="static", elevations_deg=(40.0,), seed=0)
    res = scan(tmp_path / "cap", tmp_path / "box.gscan")
    s = res.symmetries
    assert "symmetry" in res.timings_s
    assert not s.continuous and len(s.discrete) == 3 and s.holds_in == SHAPE
    for axis in ((1, 0, 0), (0, 1, 0), (0, 0, 1)):
        assert any(abs(ang - 180) < 1 and abs(float(ax @ np.asarray(axis, float))) > np.cos(np.radians(3))
                   for ax, ang in _turns(s)), axis
    assert res.to_json()["symmetries"] == template_info(tmp_path / "box.gscan").to_json()["symmetries"]


def test_viewer_draws_the_axes_of_symmetry(templates):
    """The viewer's scene holds a segment along each axis of symmetry, through the object, labelled with its fold
    and what it holds in; a template without symmetries draws none."""
    import socket

    from gscan.viewer.app import serve
    from gscan.viewer.scene import symmetry_segments

    s = _symmetries(templates["square_box"])
    seg, cols, labels = symmetry_segments(s, np.zeros(3), 0.12)
    assert seg.shape == (5, 2, 3) and cols.shape == (5, 2, 3)  # z (4-fold), x, y and the two diagonals (2-fold)
    dirs = seg[:, 1] - seg[:, 0]
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    assert sum(abs(d[2]) > 0.999 for d in dirs) == 1 and sum(abs(d[2]) < 0.01 for d in dirs) == 4
    assert np.allclose(seg.mean(axis=1), 0, atol=1e-3)  # through the box's centre
    texts = sorted(t for t, _ in labels)
    assert texts == ["2-fold (shape+texture)"] * 4 + ["4-fold (shape+texture)"]
    assert len(symmetry_segments(Symmetries(), np.zeros(3), 0.1)[0]) == 0
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    app = serve(templates["cylinder"], port=port)
    try:
        assert app.data.symmetries.continuous and len(app.layers["symmetries"]) == 3  # segments + 2 labels
    finally:
        app.stop()
