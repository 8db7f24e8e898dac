"""Template database: round trips, status, refusal cases, overwrite rules, crash safety."""
from __future__ import annotations

import json
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gscan.errors import InputError
from gscan.features import Features
from gscan.geometry.mesh import MeshData
from gscan.geometry.transforms import make_T, rotvec_to_R
from gscan.io.camera import Intrinsics, RGBDFrame
from gscan.template.db import SCHEMA_VERSION, Edge, TemplateDB, View, open_template

K = Intrinsics(520.0, 515.0, 31.5, 23.5, 64, 48)


def _pose(rng: np.random.Generator) -> np.ndarray:
    return make_T(rotvec_to_R(rng.normal(size=3)), rng.normal(size=3))


def _view(name: str, rng: np.random.Generator, T: np.ndarray | None = None, idx: int | None = None) -> View:
    color = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
    depth = (rng.integers(0, 4000, (48, 64)) / 1000.0).astype(np.float32)  # whole millimetres: exact in 16-bit PNG
    depth[rng.random((48, 64)) < 0.1] = 0.0
    return View(name=name, intrinsics=K, T_obj_cam=T, color=color, depth=depth, mask=depth > 1.0, keyframe=True,
                quality=0.75, input_index=idx)


def _feats(rng: np.random.Generator, n: int, kind: str = "rootsift") -> Features:
    desc = rng.integers(0, 256, (n, 32), dtype=np.uint8) if kind == "orb" else rng.random((n, 128), dtype=np.float32)
    return Features(pixels=rng.random((n, 2), dtype=np.float32) * 60, points=rng.normal(size=(n, 3)).astype(np.float32),
                    descriptors=desc, kind=kind, scales=rng.random(n, dtype=np.float32))


@pytest.fixture()
def db_path(tmp_path: Path) -> Path:
    return tmp_path / "obj.gscan"


def test_view_round_trip_png_exact_and_jpeg_close(db_path: Path) -> None:
    rng = np.random.default_rng(0)
    v_png, v_jpg = _view("a", rng, _pose(rng), 0), _view("b", rng, None, 1)
    v_jpg.color = np.full((48, 64, 3), (200, 120, 40), dtype=np.uint8)
    with TemplateDB.create(db_path) as db:
        assert db.add_view(v_png, color_codec="png") != db.add_view(v_jpg, color_codec="jpg")
        a, b = db.view("a"), db.view("b")
        lazy = db.views()
    assert np.array_equal(a.color, v_png.color) and a.color.dtype == np.uint8
    assert np.array_equal(a.depth, v_png.depth) and a.depth.dtype == np.float32
    assert np.array_equal(a.mask, v_png.mask) and a.mask.dtype == bool
    assert np.array_equal(a.T_obj_cam, v_png.T_obj_cam) and b.T_obj_cam is None
    assert a.intrinsics == K and a.quality == 0.75 and a.keyframe and a.input_index == 0
    assert np.abs(b.color.astype(int) - v_jpg.color).max() <= 3  # JPEG q90 of a flat colour
    assert [v.name for v in lazy] == ["a", "b"] and all(v.color is None and v.depth is None for v in lazy)


def test_depth_quantised_to_millimetres(db_path: Path) -> None:
    depth = np.array([[0.0, 0.0004, 0.5004, 1.2346, 70.0, np.nan]], dtype=np.float32)
    with TemplateDB.create(db_path) as db:
        db.add_view(View(name="d", intrinsics=Intrinsics(1, 1, 0, 0, 6, 1), depth=depth))
        out = db.view("d").depth
    # whole millimetres read back as float32 metres: 1.235 is rounded by 6e-8 at most; 1e-7 covers it (a wrong
    # quantisation is off by 0.4 mm or more)
    assert np.allclose(out, [0.0, 0.0, 0.5, 1.235, 0.0, 0.0], atol=1e-7)


@settings(max_examples=15, deadline=None)
@given(n=st.integers(0, 40), kind=st.sampled_from(["rootsift", "sift", "orb"]), seed=st.integers(0, 2**31))
def test_features_round_trip_bit_exact(tmp_path_factory: pytest.TempPathFactory, n: int, kind: str, seed: int) -> None:
    rng = np.random.default_rng(seed)
    path = tmp_path_factory.mktemp("f") / "f.gscan"
    f = _feats(rng, n, kind)
    with TemplateDB.create(path) as db:
        db.add_view(View("v", K, _pose(rng)), features=f)
        g = db.features("v")
    for x, y in ((f.pixels, g.pixels), (f.points, g.points), (f.descriptors, g.descriptors), (f.scales, g.scales)):
        assert x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes()
    assert g.kind == kind


def test_update_pose_moves_keypoints_into_the_new_object_frame(db_path: Path) -> None:
    rng = np.random.default_rng(1)
    pts_cam = rng.normal(size=(20, 3)).astype(np.float32)
    T1, T2 = _pose(rng), _pose(rng)
    with TemplateDB.create(db_path) as db:
        db.add_view(View(name="v", intrinsics=K))  # unregistered: keypoints in the camera frame
        db.add_features("v", Features(pixels=rng.random((20, 2), dtype=np.float32), points=pts_cam,
                                      descriptors=rng.random((20, 128), dtype=np.float32), kind="rootsift"))
        db.update_pose("v", T1)
        got1 = db.features("v").points
        db.update_pose("v", T2)
        got2 = db.features("v").points
        assert np.array_equal(db.view("v", load_images=False).T_obj_cam, T2)
    ref = lambda T: pts_cam.astype(np.float64) @ T[:3, :3].T + T[:3, 3]  # noqa: E731
    # points stored as float32 and moved in float64: float32 rounding (6e-8 relative) of ~1 m values
    assert np.allclose(got1, ref(T1), atol=1e-5) and np.allclose(got2, ref(T2), atol=1e-5)


def test_edges_mesh_cloud_grasps_meta_round_trip(db_path: Path) -> None:
    rng = np.random.default_rng(2)
    e1 = Edge(src="a", tgt="b", T_tgt_src=_pose(rng), matches=rng.integers(0, 100, (30, 2)).astype(np.int32),
              cost=0.01, rmse=0.002, fitness=0.9, kind="sequential")
    e2 = Edge(src="b", tgt="c", T_tgt_src=None, matches=np.zeros((0, 2), np.int32), kind="loop", accepted=False,
              reason="too few matches")
    V = rng.normal(size=(50, 3))
    F = rng.integers(0, 50, (80, 3)).astype(np.int32)
    C = rng.integers(0, 256, (50, 3), dtype=np.uint8)
    P = rng.normal(size=(100, 3)).astype(np.float32)
    Tg = _pose(rng)
    with TemplateDB.create(db_path, meta={"source": "mesh", "descriptor": {"kind": "orb", "max_keypoints": 500}}) as db:
        db.add_edge(e1)
        db.add_edge(e2)
        db.set_mesh(MeshData(vertices=V, triangles=F, vertex_colors=C))
        db.set_cloud(P, rng.random((100, 3)))
        db.add_grasp("top grip ü", Tg)
        with pytest.raises(InputError, match="already exists"):
            db.add_grasp("top grip ü", Tg)
        db.set_meta("config", {"voxel": 0.002, "nested": [1, 2]})
        edges, mesh, cloud, grasps, meta = db.edges(), db.mesh(), db.cloud(), db.grasps(), db.meta()
        assert [e.src for e in db.edges(accepted_only=True)] == ["a"]
    assert np.array_equal(edges[0].T_tgt_src, e1.T_tgt_src) and np.array_equal(edges[0].matches, e1.matches)
    assert (edges[0].cost, edges[0].rmse, edges[0].fitness, edges[0].kind, edges[0].accepted) == (0.01, 0.002, 0.9,
                                                                                                 "sequential", True)
    assert edges[1].T_tgt_src is None and edges[1].matches.shape == (0, 2) and edges[1].reason == "too few matches"
    assert np.array_equal(mesh.vertices, V) and np.array_equal(mesh.triangles, F)
    assert np.array_equal(mesh.vertex_colors, C)
    assert np.array_equal(cloud[0], P) and cloud[1].dtype == np.uint8
    assert np.array_equal(grasps["top grip ü"], Tg)
    assert meta["config"] == {"voxel": 0.002, "nested": [1, 2]} and meta["units"] == "m"
    assert meta["schema"] == SCHEMA_VERSION and meta["source"] == "mesh"


def test_status_summary_poses_and_template(db_path: Path) -> None:
    rng = np.random.default_rng(3)
    names = ["frame 0", "frame é 1", "frame 2"]
    Ts = [_pose(rng), None, _pose(rng)]
    with TemplateDB.create(db_path, meta={"descriptor": {"kind": "rootsift"}}) as db:
        for i, (n, T) in enumerate(zip(names, Ts, strict=True)):
            db.add_view(View(name=n, intrinsics=K, T_obj_cam=T, input_index=i), features=_feats(rng, 5 + i))
        db.set_mesh(MeshData(vertices=np.array([[0, 0, 0], [0.1, 0.2, 0.3], [0.05, 0, 0]]),
                             triangles=np.array([[0, 1, 2]])))
        db.add_grasp("g", np.eye(4))
        assert db.status == "partial"
    with pytest.raises(InputError, match=r"partial scan") as ei:
        TemplateDB.open(db_path)
    assert ei.value.fix == "finish"  # the CLI says `gscan scan --resume`
    with TemplateDB.open(db_path, require_complete=False, writable=True) as db:
        db.mark_complete()
    with TemplateDB.open(db_path) as db:
        s, p = db.summary(), db.poses()
        t = db.load_template()
    assert s.schema == 1 and s.status == "complete" and s.views == 3 and s.descriptor == "rootsift"
    assert s.registered == 2 and s.keyframes == 3
    # extent through float storage: approx's rel 1e-6 covers float32's 6e-8
    assert s.extent_m == pytest.approx((0.1, 0.2, 0.3)) and s.grasps == ("g",) and s.source == "scan"
    json.dumps(p)
    assert list(p["frames"]) == ["frame 0", "frame 2"] and p["unregistered"] == ["frame é 1"]
    assert np.allclose(p["frames"]["frame 2"], Ts[2])  # poses stored as float64: exact (np.allclose's atol 1e-8)
    assert t.view_names == ["frame 0", "frame 2"] and t.T_obj_cam.shape == (2, 4, 4)
    assert len(t.pixels) == len(t.points_obj) == len(t.descriptors) == len(t.kp_view) == 5 + 7
    assert list(t.view_offsets) == [0, 5, 12] and list(np.bincount(t.kp_view)) == [5, 7]
    assert open_template(db_path).grasps.keys() == {"g"}


def test_create_refuses_existing_without_force(db_path: Path) -> None:
    TemplateDB.create(db_path).close()
    with pytest.raises(InputError, match="already exists") as ei:
        TemplateDB.create(db_path)
    assert str(db_path) in str(ei.value) and "\n" not in str(ei.value)
    with TemplateDB.open(db_path, require_complete=False, writable=True) as db:
        db.add_view(View("x", K))
    with TemplateDB.create(db_path, force=True) as db:
        assert db.view_names() == []


@pytest.mark.parametrize("case", ["missing", "random", "empty", "truncated", "other_sqlite", "newer", "older"])
def test_open_refusals(tmp_path: Path, case: str) -> None:
    path = tmp_path / f"{case} é.gscan"
    expect = {"missing": "not found", "random": "not an SQLite file", "empty": "not an SQLite file",
              "other_sqlite": "not a gscan template database", "newer": "written by a newer gscan",
              "older": "old template schema", "truncated": "corrupt"}[case]
    if case == "random":
        path.write_bytes(np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    elif case == "empty":
        path.write_bytes(b"")
    elif case == "truncated":
        with TemplateDB.create(path) as db:
            db.mark_complete()
        path.write_bytes(path.read_bytes()[:100])
    elif case == "other_sqlite":
        with sqlite3.connect(path) as c:
            c.execute("CREATE TABLE meta (key TEXT, value TEXT)")
    elif case in ("newer", "older"):
        with TemplateDB.create(path) as db:
            db.mark_complete()
        with sqlite3.connect(path) as c:
            schema = SCHEMA_VERSION + 1 if case == "newer" else 0
            c.execute("UPDATE meta SET value=? WHERE key='schema'", (str(schema),))
    with pytest.raises(InputError, match=expect) as ei:
        TemplateDB.open(path, require_complete=False)
    assert str(path) in str(ei.value) and "\n" not in str(ei.value)


def test_duplicate_view_and_read_only(db_path: Path) -> None:
    with TemplateDB.create(db_path) as db:
        db.add_view(View("v", K), features=_feats(np.random.default_rng(0), 3))
        with pytest.raises(InputError, match="already exists"):
            db.add_view(View("v", K))
        db.add_view(View("v", K, np.eye(4)), replace=True)
        assert db.features("v") is None and db.view_names() == ["v"]
        db.mark_complete()
    with TemplateDB.open(db_path) as db, pytest.raises(Exception, match="read-only"):
        db.set_meta("x", 1)


_WRITER = textwrap.dedent("""
    import sys, numpy as np
    from gscan.io.camera import Intrinsics
    from gscan.features import Features
    from gscan.template.db import TemplateDB, View
    db = TemplateDB.create(sys.argv[1])
    K = Intrinsics(500.0, 500.0, 160.0, 120.0, 320, 240)
    rng = np.random.default_rng(0)
    for i in range(100000):
        c = rng.integers(0, 256, (240, 320, 3), dtype=np.uint8)
        d = rng.random((240, 320), dtype=np.float32)
        f = Features(pixels=rng.random((500, 2), dtype=np.float32), points=rng.random((500, 3), dtype=np.float32),
                     descriptors=rng.random((500, 128), dtype=np.float32), kind="rootsift")
        db.add_view(View(name=f"view {i}", intrinsics=K, T_obj_cam=np.eye(4), color=c, depth=d, mask=d > 0.5,
                         input_index=i), features=f, color_codec="png")
        print(i, flush=True)
""")


def test_sigkill_mid_write_leaves_consistent_partial_db(db_path: Path) -> None:
    proc = subprocess.Popen([sys.executable, "-c", _WRITER, str(db_path)], stdout=subprocess.PIPE, text=True)
    try:
        written = -1
        deadline = time.monotonic() + 60
        while written < 4 and time.monotonic() < deadline:
            line = proc.stdout.readline()
            assert line, "writer exited early"
            written = int(line)
        time.sleep(0.05)  # land the kill inside a later write
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
    with TemplateDB.open(db_path, require_complete=False) as db:  # replays a hot journal
        assert db.status == "partial"
        names = db.view_names()
        assert len(names) >= written + 1
        for n in names:  # every committed view is whole
            assert db.features(n) is not None and db.view(n).color.shape == (240, 320, 3)
    with sqlite3.connect(db_path) as c:
        assert c.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
    with pytest.raises(InputError, match="partial"):
        TemplateDB.open(db_path)


def test_grasp_names_are_printable_text(db_path: Path) -> None:
    TemplateDB.create(db_path).close()
    with TemplateDB.open(db_path, require_complete=False, writable=True) as db:
        for bad in ("", "  ", "a\nb", "\x1b[31mred", "x" * 201, "caf\udce9"):
            with pytest.raises(InputError, match="grasp name"):
                db.add_grasp(bad, np.eye(4))
        db.add_grasp("top grasp (é)", np.eye(4))
        assert list(db.grasps()) == ["top grasp (é)"]


def test_read_pose_file(tmp_path: Path) -> None:
    from gscan.io import read_pose_file

    T = _pose(np.random.default_rng(5))
    (tmp_path / "a.json").write_text(json.dumps({"T": T.tolist()}))
    (tmp_path / "b.json").write_text(json.dumps(T.tolist()))
    # rotations are projected onto SO(3): exact ones come back to rounding (1e-15)
    np.testing.assert_allclose(read_pose_file(tmp_path / "a.json"), T, atol=1e-12)
    np.testing.assert_allclose(read_pose_file(tmp_path / "b.json"), T, atol=1e-12)
    bad = {"c.json": "{not json", "d.json": json.dumps({"R": 1}), "e.json": json.dumps(np.eye(3).tolist()),
           "f.json": json.dumps((2 * np.eye(4)).tolist()), "missing.json": None}
    for name, text in bad.items():
        if text is not None:
            (tmp_path / name).write_text(text)
        with pytest.raises(InputError) as ei:
            read_pose_file(tmp_path / name)
        assert name in str(ei.value)


def test_object_keypoints_are_what_the_estimator_loads(db_path: Path) -> None:
    """A view's "object" keypoints replace its "registration" ones in load_template; both move with
    update_pose and both go when the view is replaced."""
    rng = np.random.default_rng(7)
    T = _pose(rng)
    reg, obj = _feats(rng, 30), _feats(rng, 12)
    with TemplateDB.create(db_path) as db:
        db.add_view(_view("a", rng, T, 0), reg)
        db.add_view(_view("b", rng, T, 1), _feats(rng, 5))
        db.add_features("a", obj, role="object")
        with pytest.raises(ValueError):
            db.add_features("a", obj, role="other")
        tpl = db.load_template()
        assert list(tpl.view_offsets) == [0, 12, 17]  # a: its 12 object keypoints; b: its registration ones
        np.testing.assert_array_equal(tpl.descriptors[:12], obj.descriptors)
        np.testing.assert_array_equal(db.features("a").descriptors, reg.descriptors)
        T2 = _pose(rng)
        db.update_pose("a", T2)
        A = T2 @ np.linalg.inv(T)
        for role, f in (("registration", reg), ("object", obj)):
            moved = db.features("a", role).points
            # points stored as float32 and moved in float64: float32 rounding (6e-8 relative) of ~1 m values
            np.testing.assert_allclose(moved, f.points @ A[:3, :3].T + A[:3, 3], atol=1e-5)
        # a keyframe whose object mask held no keypoint offers none: not its registration keypoints (the whole
        # frame, background included)
        db.add_features("b", _feats(rng, 0), role="object")
        assert list(db.load_template().view_offsets) == [0, 12, 12]
        db.add_view(_view("a", rng, T, 0), reg, replace=True)
        assert db.features("a", "object") is None


# every stored column and the read that decodes it; a bad value there must be an InputError naming the file
_READS = {
    ("views", "T_obj_cam"): lambda db: db.views(),
    ("views", "color"): lambda db: db.view("a"),
    ("views", "depth"): lambda db: db.views(load_images=True),
    ("views", "mask"): lambda db: db.view("a"),
    ("views", "intrinsics"): lambda db: db.views(),
    ("features", "points"): lambda db: db.features("a"),
    ("features", "descriptors"): lambda db: db.features("a"),
    ("edges", "T_tgt_src"): lambda db: db.edges(),
    ("edges", "matches"): lambda db: db.edges(),
    ("mesh", "vertices"): lambda db: db.mesh(),
    ("cloud", "points"): lambda db: db.cloud(),
    ("grasps", "T_obj_grasp"): lambda db: db.grasps(),
    ("meta", "value"): lambda db: db.meta(),
}


@pytest.mark.parametrize("table, column", sorted(_READS))
@pytest.mark.parametrize("damage", ["bit-flip", "empty", "wrong-shape"])
def test_undecodable_stored_value_is_input_error(tmp_path: Path, table: str, column: str, damage: str) -> None:
    path = _every_column_db(tmp_path / "obj.gscan")
    with sqlite3.connect(path) as c:
        where = " WHERE key = 'units'" if table == "meta" else ""
        (blob,) = c.execute(f"SELECT {column} FROM {table}{where}").fetchone()
        bad = {"bit-flip": bytes([blob[0], blob[1] ^ 0x40]) + bytes(blob[2:]) if isinstance(blob, bytes)
               else "{" + blob, "empty": b"" if isinstance(blob, bytes) else "",
               "wrong-shape": _encoded(np.zeros(3)) if isinstance(blob, bytes) else "[1, 2"}[damage]
        c.execute(f"UPDATE {table} SET {column} = ?{where}", (bad,))
    c.close()
    with TemplateDB.open(path) as db:
        try:
            _READS[(table, column)](db)
        except InputError as e:
            assert "obj.gscan" in str(e) and "corrupt template database" in str(e)
        else:
            raise AssertionError(f"{table}.{column} damaged ({damage}) was read without an error")


def _every_column_db(path: Path) -> Path:
    """A complete database with a value in every stored column (one view "a", png colour)."""
    rng = np.random.default_rng(4)
    with TemplateDB.create(path) as db:
        db.add_view(_view("a", rng, _pose(rng), 0), _feats(rng, 20), color_codec="png")
        db.add_edge(Edge(src="a", tgt="a", T_tgt_src=_pose(rng), matches=np.zeros((3, 2), np.int32), cost=0.0, rmse=0.0,
                         fitness=1.0, kind="loop"))
        db.set_mesh(MeshData(vertices=rng.normal(size=(5, 3)), triangles=np.array([[0, 1, 2]]),
                             vertex_colors=np.full((5, 3), 200, np.uint8)))
        db.set_cloud(rng.normal(size=(5, 3)))
        db.add_grasp("g", _pose(rng))
        db.mark_complete()
    return path


def _png(img: np.ndarray) -> bytes:
    return cv2.imencode(".png", img)[1].tobytes()


# values that decode but cannot be right: (table, column, stored value, the read, words of the error)
_IMPOSSIBLE = {
    "nan-points": ("features", "points", lambda: np.full((20, 3), np.nan, np.float32), lambda db: db.features("a"),
                   "NaN"),
    "inf-pose": ("views", "T_obj_cam", lambda: np.full((4, 4), np.inf), lambda db: db.views(), "infinite"),
    "nan-grasp": ("grasps", "T_obj_grasp", lambda: np.full((4, 4), np.nan), lambda db: db.grasps(), "NaN"),
    "grasp-1e6-m-away": ("grasps", "T_obj_grasp", lambda: np.array([[1.0, 0, 0, 1e6], [0, 1, 0, 0], [0, 0, 1, 0],
                                                                     [0, 0, 0, 1]]), lambda db: db.grasps(), "10000 m"),
    "zero-pose": ("views", "T_obj_cam", lambda: np.zeros((4, 4)), lambda db: db.views(), "not a rigid pose"),
    "scaled-edge": ("edges", "T_tgt_src", lambda: 2 * np.eye(4), lambda db: db.edges(), "not a rigid pose"),
    "text-pixels": ("features", "pixels", lambda: np.full((20, 2), "x"), lambda db: db.features("a"), "not numbers"),
    "short-descriptors": ("features", "descriptors", lambda: np.zeros((20, 64), np.float32),
                          lambda db: db.features("a"), "x 64"),
    "unknown-kind": ("features", "kind", lambda: "surf", lambda db: db.features("a"), "surf"),
    "triangle-out-of-range": ("mesh", "triangles", lambda: np.array([[0, 1, 10**8]]), lambda db: db.mesh(),
                              "triangles"),
    "negative-triangle": ("mesh", "triangles", lambda: np.array([[0, 1, -1]]), lambda db: db.mesh(), "triangles"),
    "float-triangles": ("mesh", "triangles", lambda: np.array([[0.0, 1.0, 2.0]]), lambda db: db.mesh(),
                        "triangles"),
    "short-mesh-colours": ("mesh", "colors", lambda: np.zeros((3, 3), np.uint8), lambda db: db.mesh(), "colours"),
    "float-cloud-colours": ("cloud", "colors", lambda: np.zeros((5, 3), np.float32), lambda db: db.cloud(),
                            "colours"),
    "colour-depth": ("views", "depth", lambda: _png(np.zeros((48, 64, 3), np.uint8)),
                     lambda db: db.view("a"), "uint16"),
    "grey-colour": ("views", "color", lambda: _png(np.zeros((48, 64), np.uint8)), lambda db: db.view("a"), "uint8"),
    "mask-of-another-size": ("views", "mask", lambda: _png(np.zeros((10, 10), np.uint8)), lambda db: db.view("a"),
                             "10x10"),  # refused from its header, before decoding
}


@pytest.mark.parametrize("case", sorted(_IMPOSSIBLE))
def test_impossible_stored_value_is_input_error(tmp_path: Path, case: str) -> None:
    """A value that decodes but cannot be a template's (NaN, an index past the mesh, a descriptor of the
    wrong length, an image of the wrong type or size) is refused like an undecodable one: an InputError
    naming the file, before it reaches the estimator, an export or a JSON output."""
    table, column, value, read, words = _IMPOSSIBLE[case]
    path = _every_column_db(tmp_path / "obj.gscan")
    v = value()
    with sqlite3.connect(path) as c:
        c.execute(f"UPDATE {table} SET {column} = ?", (_encoded(v) if isinstance(v, np.ndarray) else v,))
    c.close()
    with TemplateDB.open(path) as db, pytest.raises(InputError, match="corrupt template database") as ei:
        read(db)
    assert "obj.gscan" in str(ei.value) and words in str(ei.value)


def _encoded(a: np.ndarray) -> bytes:
    from gscan.template.codec import encode_array

    return encode_array(a)


def test_records_built_from_each_other() -> None:
    """View.from_frame takes a frame's images (its own mask unless another, or None, is given);
    Features.transformed and MeshData.transformed move points into another frame and share the rest."""
    rng = np.random.default_rng(8)
    color = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
    depth = rng.random((48, 64), dtype=np.float32)
    frame = RGBDFrame(name="f", color=color, depth=depth, intrinsics=K, mask=depth > 0.5)
    T = _pose(rng)
    v = View.from_frame(frame, T_obj_cam=T, keyframe=False, quality=0.5, input_index=3)
    assert (v.name, v.intrinsics, v.keyframe, v.quality, v.input_index) == ("f", K, False, 0.5, 3)
    assert v.color is color and v.depth is depth and v.mask is frame.mask and v.T_obj_cam is T
    assert View.from_frame(frame, mask=None).mask is None
    other = depth > 0.9
    assert View.from_frame(frame, mask=other).mask is other and View.from_frame(frame).T_obj_cam is None
    f = _feats(rng, 10)
    g = f.transformed(T)
    assert g.points.dtype == np.float32 and g.descriptors is f.descriptors and g.pixels is f.pixels
    np.testing.assert_allclose(g.points, f.points @ T[:3, :3].T + T[:3, 3], atol=1e-5)
    m = MeshData(vertices=rng.normal(size=(4, 3)), triangles=np.array([[0, 1, 2], [1, 2, 3]]))
    np.testing.assert_allclose(m.transformed(T).vertices, m.vertices @ T[:3, :3].T + T[:3, 3])
    assert m.transformed(T).triangles is m.triangles and m.transformed(T).vertex_colors is None


def test_info_json_keeps_its_keys(db_path: Path) -> None:
    """`gscan info --json` (the CLI contract) is shaped by the CLI from TemplateDB.summary()."""
    with TemplateDB.create(db_path, meta={"descriptor": {"kind": "rootsift"}}) as db:
        db.add_view(View(name="a", intrinsics=K, T_obj_cam=np.eye(4)), _feats(np.random.default_rng(0), 5))
        db.add_view(View(name="b", intrinsics=K), _feats(np.random.default_rng(1), 5))
        db.add_grasp("g", np.eye(4))
        db.set_meta("unregistered_reasons", {"b": "no accepted edge"})
    r = subprocess.run([sys.executable, "-m", "gscan.cli", "info", str(db_path), "--json"], capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert list(out) == ["schema", "status", "views", "registered", "keyframes", "descriptor", "source", "extent_m",
                         "grasps", "unregistered_reasons", "selection", "parts", "mesh", "camera", "coverage",
                         "symmetries", "object"]
    assert out["selection"] == {} and out["parts"] == []  # written without frame selection, in one part
    assert out["coverage"] is None  # no coverage recorded: unknown
    assert out["camera"] is None  # not written by a scan: no colour camera check
    assert out["symmetries"]["holds_in"] is None and out["symmetries"]["discrete"] == []  # none searched
    assert out["object"] is None  # nor an object chosen by segmentation
    assert out["status"] == "partial" and out["views"] == 2 and out["registered"] == 1 and out["grasps"] == ["g"]
    assert out["unregistered_reasons"] == {"b": "no accepted edge"}
    assert isinstance(out["extent_m"], list) and len(out["extent_m"]) == 3


def _header_journal(path: Path) -> tuple[int, int]:
    """The file format's write / read version bytes of an SQLite file: (1, 1) rollback journal, (2, 2) WAL."""
    head = path.read_bytes()[:20]
    return head[18], head[19]


def test_batch_commits_once_and_a_failed_write_leaves_none_of_its_rows(db_path: Path) -> None:
    """A batch is one transaction: its rows appear to other connections only at its commit (or at `commit()`
    inside it); a write that fails inside it leaves none of its rows; an exception out of it rolls the
    uncommitted rows back."""
    rng = np.random.default_rng(3)
    commits: list[str] = []
    with TemplateDB.create(db_path, wal=True) as db:
        db._conn.set_trace_callback(lambda sql: commits.append(sql) if sql.startswith("COMMIT") else None)

        def others() -> list[str]:
            with sqlite3.connect(db_path) as c:
                return [r[0] for r in c.execute("SELECT name FROM views ORDER BY id")]

        with db.batch():
            db.add_view(_view("a", rng), _feats(rng, 5))
            db.add_view(_view("b", rng), _feats(rng, 5))
            with pytest.raises(ValueError, match="disagree"):  # the view row goes with its bad keypoints
                bad = _feats(rng, 5)
                object.__setattr__(bad, "points", bad.points[:3])  # past the record's own check
                db.add_view(_view("c", rng), bad)
            assert others() == [] and db.view_names() == ["a", "b"]
            db.commit()
            assert others() == ["a", "b"]
            db.add_view(_view("d", rng), _feats(rng, 5))
        assert others() == ["a", "b", "d"] and len(commits) == 2
        with pytest.raises(KeyboardInterrupt), db.batch():
            db.add_view(_view("e", rng), _feats(rng, 5))
            raise KeyboardInterrupt
        assert db.view_names() == ["a", "b", "d"]
        db.add_view(_view("f", rng), _feats(rng, 5))  # outside a batch: a transaction of its own again
    assert others() == ["a", "b", "d", "f"]


def test_a_wal_writer_leaves_a_rollback_journal_file(db_path: Path) -> None:
    """A database written through a write-ahead log is, once closed, an ordinary rollback-journal file with
    nothing beside it (a reader needs no -wal / -shm file, nor write access to the folder); a file written
    before (rollback journal from the start) opens and reads as it did."""
    rng = np.random.default_rng(4)
    with TemplateDB.create(db_path, wal=True) as db:
        db.add_view(_view("a", rng, T=np.eye(4)), _feats(rng, 5))
        assert _header_journal(db_path) == (2, 2)
        db.mark_complete()
    assert _header_journal(db_path) == (1, 1)
    assert sorted(p.name for p in db_path.parent.iterdir()) == [db_path.name]
    old = db_path.with_name("old.gscan")
    with TemplateDB.create(old) as db:  # what every earlier gscan wrote
        db.add_view(_view("a", rng, T=np.eye(4)), _feats(rng, 5))
        db.mark_complete()
    for p in (db_path, old):
        assert _header_journal(p) == (1, 1)
        with TemplateDB.open(p) as db:
            assert db.view_names() == ["a"] and db.status == "complete"


_WAL_KILLED = textwrap.dedent("""
    import os, sys, numpy as np
    from gscan.io.camera import Intrinsics
    from gscan.template.db import TemplateDB, View
    db = TemplateDB.create(sys.argv[1], wal=True, meta={"note": "killed"})
    K = Intrinsics(500.0, 500.0, 32.0, 24.0, 64, 48)
    for i in range(5):
        with db.batch():
            db.add_view(View(name=f"old {i}", intrinsics=K, color=np.full((48, 64, 3), i, np.uint8)))
    os._exit(0)  # killed: the committed rows are in the log beside the file, not in it
""")


def test_a_new_database_never_meets_a_killed_writers_log(db_path: Path) -> None:
    """A killed WAL writer leaves its log beside the file; the log holds committed rows (the file reopened with
    it reads them). A new database created at that name, in place or replacing it, must not have the old log
    replayed into it: it reads as written, and intact."""
    for replace in (False, True):
        for p in db_path.parent.iterdir():
            p.unlink()
        subprocess.run([sys.executable, "-c", _WAL_KILLED, str(db_path)], check=True, timeout=120)
        assert Path(f"{db_path}-wal").stat().st_size > 0
        if replace:
            copy = db_path.with_name("copy.gscan")  # the file with its log holds the killed writer's rows
            shutil.copy(db_path, copy)
            shutil.copy(f"{db_path}-wal", f"{copy}-wal")
            with TemplateDB.open(copy, require_complete=False) as db:
                assert len(db.view_names()) == 5
        else:
            shutil.copy(f"{db_path}-wal", db_path.with_name("saved-wal"))
            db_path.unlink()  # the user removed the file, not its log
            os.replace(db_path.with_name("saved-wal"), f"{db_path}-wal")
        rng = np.random.default_rng(5)
        with TemplateDB.create(db_path, force=replace) as db:
            db.add_view(_view("new", rng), _feats(rng, 5))
        with TemplateDB.open(db_path, require_complete=False) as db:
            assert db.view_names() == ["new"] and db.get_meta("note") is None
        with sqlite3.connect(db_path) as c:
            assert c.execute("PRAGMA integrity_check").fetchone()[0] == "ok"


def test_a_write_ahead_log_held_read_only_is_not_called_corruption(tmp_path: Path, monkeypatch) -> None:
    """A template with SQLite's -wal beside it that SQLite may not write (simulated: the connection refuses
    as it does in a read-only folder, which root's tests cannot make): named held, not corrupt."""
    from gscan.template.db import TemplateDB

    path = tmp_path / "t.gscan"
    with TemplateDB.create(path):
        pass
    Path(f"{path}-wal").write_bytes(b"")

    def refuse(*_a, **_k):
        raise sqlite3.OperationalError("attempt to write a readonly database")

    monkeypatch.setattr(TemplateDB, "_connect", staticmethod(refuse))
    with pytest.raises(InputError, match=r"t\.gscan-wal beside it .* read-only; the template is not corrupt"):
        TemplateDB.open(path, require_complete=False)
