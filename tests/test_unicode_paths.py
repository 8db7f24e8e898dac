"""Spaces and non-ASCII characters in paths and frame names, through the real command line
(GitHub issue 7): scan, poses, info, estimate, export (bop, json, ply), grasp add / list, and an
error message that names such a file intact.
"""
from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gscan import synth
from gscan.geometry.transforms import inv_T, pose_error

INTR = synth.DEFAULT_INTRINSICS.scaled(0.5)  # 320 x 240
N_VIEWS = 8  # 45 degree steps on one ring
NAMES = [f"vue été {k:02d} – 視点" for k in range(N_VIEWS)]  # noqa: RUF001 - frame stems: spaces, accents, dash, CJK
TIMEOUT_S = 300


def _gscan(*args: str | Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "gscan.cli", *map(str, args)], capture_output=True,
                          timeout=TIMEOUT_S, encoding="utf-8", errors="strict")


def _ok(*args: str | Path) -> subprocess.CompletedProcess:
    r = _gscan(*args)
    assert r.returncode == 0, f"{args[0]}: {r.stderr}"
    assert "Traceback" not in r.stderr
    return r


@pytest.fixture(scope="module")
def scanned(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, list]:
    """(capture folder, template database, rendered frames), all under non-ASCII paths."""
    base = tmp_path_factory.mktemp("unicode") / "scän test"
    capture = base / "crème brûlée"
    mesh = synth.box_mesh((0.14, 0.09, 0.07), synth.procedural_box_texture(3, (512, 768)))
    frames = synth.render_capture(mesh, None, N_VIEWS, mode="static", elevations_deg=(40.0,), intr=INTR)
    synth.write_capture(capture, frames, INTR, names=NAMES)
    assert sorted(p.stem for p in (capture / "rgb").iterdir()) == NAMES
    db = base / "sortie ü" / "objet ñ 1.gscan"
    r = _ok("scan", capture, "-o", db, "--json")
    out = json.loads(r.stdout)
    assert out["output"] == str(db) and db.is_file()
    assert out["frames"] == N_VIEWS and out["registered"] >= N_VIEWS - 1, out
    assert out["skipped"] == {}
    return capture, db, frames


def test_poses_and_info(scanned):
    capture, db, frames = scanned
    poses = json.loads(_ok("poses", db, "--json").stdout)
    assert set(poses["frames"]) | set(poses["unregistered"]) == set(NAMES)
    # relative camera motion between two registered frames agrees with the rendering's ground truth
    a, b = [n for n in NAMES if n in poses["frames"]][:2]
    ia, ib = NAMES.index(a), NAMES.index(b)
    T_a_b = inv_T(np.array(poses["frames"][a])) @ np.array(poses["frames"][b])
    T_a_b_gt = frames[ia].T_cam_obj @ inv_T(frames[ib].T_cam_obj)
    deg, m = pose_error(T_a_b, T_a_b_gt)
    # a rendered pair registered through non-ASCII paths: within 2 deg / 1 cm (the path must not change the result)
    assert deg < 2.0 and m < 0.01, (deg, m)
    info = json.loads(_ok("info", db, "--json").stdout)
    assert info["status"] == "complete" and info["views"] == N_VIEWS
    text = _ok("info", db)  # the human-readable form prints non-ASCII text too
    assert text.stdout == "" and "complete" in text.stderr


def test_estimate_with_non_ascii_query_paths(scanned, tmp_path: Path):
    capture, db, frames = scanned
    k = 3
    q = tmp_path / "requête ß" / "prise n°1"
    q.mkdir(parents=True)
    color, depth, K = q / "couleur é.png", q / "profondeur é.png", q / "cam_K ü.txt"
    shutil.copy(capture / "rgb" / f"{NAMES[k]}.png", color)
    shutil.copy(capture / "depth" / f"{NAMES[k]}.png", depth)
    shutil.copy(capture / "cam_K.txt", K)
    mask = q / "masque à.png"
    shutil.copy(capture / "masks" / f"{NAMES[k]}.png", mask)
    out = json.loads(_ok("estimate", db, "--color", color, "--depth", depth, "--intrinsics", K,
                         "--mask", mask, "--json").stdout)
    assert out["T_cam_obj"] is not None, out["reason"]
    assert out["view"] in NAMES
    # the query is scanned view k itself: the estimate inverts that view's registered pose
    poses = json.loads(_ok("poses", db, "--json").stdout)["frames"]
    if NAMES[k] in poses:
        deg, m = pose_error(np.array(out["T_cam_obj"]), inv_T(np.array(poses[NAMES[k]])))
        # estimate through non-ASCII paths: within 3 deg / 1 cm of the template's own pose
        assert deg < 3.0 and m < 0.01, (deg, m)
    # a missing file under a non-ASCII path is named intact in the one-line error
    r = _gscan("estimate", db, "--color", q / "manquant ç.png", "--depth", depth, "--intrinsics", K)
    assert r.returncode == 2
    assert r.stderr.strip().splitlines()[-1].startswith("error: ") and "manquant ç.png" in r.stderr


@pytest.mark.parametrize("fmt", ["bop", "json", "ply"])
def test_export_to_non_ascii_folder(scanned, tmp_path: Path, fmt: str):
    _, db, _ = scanned
    out = tmp_path / "export ø" / ("résultat bop" if fmt == "bop" else f"modèle é.{fmt}")
    _ok("export", db, "--format", fmt, "-o", out)
    assert out.exists()
    assert [p.name for p in out.parent.iterdir()] == [out.name]  # no temporary sibling left
    if fmt == "bop":
        files = [p for p in out.rglob("*") if p.is_file()]
        assert len(files) >= N_VIEWS
        assert any(p.suffix == ".json" for p in files) and any(p.suffix == ".png" for p in files)
    elif fmt == "json":
        data = json.loads(out.read_text(encoding="utf-8"))
        assert {v["name"] for v in data["views"]} == set(NAMES)
    else:
        assert out.read_bytes().startswith(b"ply") and out.stat().st_size > 1000


def test_grasp_add_and_list(scanned, tmp_path: Path):
    _, db, _ = scanned
    local = tmp_path / "copie é" / "objet ß.gscan"
    local.parent.mkdir()
    shutil.copy(db, local)
    pose = tmp_path / "prise ü.json"
    T = np.eye(4)
    T[:3, 3] = [0.0, 0.0, 0.05]
    pose.write_text(json.dumps({"T": T.tolist()}), encoding="utf-8")
    name = "pince à gauche 把手"
    _ok("grasp", "add", local, "--name", name, "--pose", pose)
    listed = json.loads(_ok("grasp", "list", local, "--json").stdout)["grasps"]
    assert list(listed) == [name]
    # a grasp stored and listed as JSON floats: float64 round trip
    np.testing.assert_allclose(np.array(listed[name]), T, atol=1e-12)
    assert json.loads(_ok("info", local, "--json").stdout)["grasps"] == [name]
