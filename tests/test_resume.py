"""Crash safety of `gscan scan` (GitHub issue 7).

A scan killed with SIGKILL leaves a consistent SQLite file whose status is `partial`; `info`
shows it, `estimate` and `export` refuse it (exit 2, suggesting `scan --resume`), and
`scan --resume` finishes it to exactly the result of an uninterrupted scan: the same poses (to
1e-9), the same accepted edges, the same mesh.
"""
from __future__ import annotations

import json
import os
import signal
import sqlite3
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from gscan import synth
from gscan.template.db import TemplateDB
from tests._scan_checks import box_ring_capture

INTR = synth.DEFAULT_INTRINSICS.scaled(0.5)  # 320 x 240
N_VIEWS = 6  # 60 degree steps on one ring
TIMEOUT_S = 300


def _cli(*args: str | Path) -> list[str]:
    return [sys.executable, "-m", "gscan.cli", *map(str, args)]


def _gscan(*args: str | Path) -> subprocess.CompletedProcess:
    return subprocess.run(_cli(*args), capture_output=True, text=True, timeout=TIMEOUT_S)


@dataclass
class ScanState:
    """What a finished scan database holds, for comparing two scans."""

    T_obj_cam: dict[str, np.ndarray | None]  # view name -> [4 x 4] or None
    accepted: set[tuple[str, str]]  # accepted edges (src, tgt)
    n_edges: int
    mesh_vertices: int
    mesh_triangles: int


def _state(db_path: Path) -> ScanState:
    with TemplateDB.open(db_path, require_complete=True) as db:
        poses = {v.name: v.T_obj_cam for v in db.views(load_images=False)}
        edges = db.edges()
        mesh = db.mesh()
    return ScanState(poses, {(e.src, e.tgt) for e in edges if e.accepted}, len(edges),
                     len(mesh.vertices), len(mesh.triangles))


def _assert_same(a: ScanState, b: ScanState) -> None:
    assert sorted(a.T_obj_cam) == sorted(b.T_obj_cam)
    for name, T in a.T_obj_cam.items():
        U = b.T_obj_cam[name]
        assert (T is None) == (U is None), name
        if T is not None:
            # a resumed scan redoes only float64 arithmetic in the same order: poses equal to rounding (1e-9 allows BLAS
            # threading to reorder sums)
            assert np.max(np.abs(T - U)) <= 1e-9, (name, np.max(np.abs(T - U)))
    assert a.accepted == b.accepted
    assert a.n_edges == b.n_edges
    assert (a.mesh_vertices, a.mesh_triangles) == (b.mesh_vertices, b.mesh_triangles)


def _count(db: Path, table: str) -> int | None:
    """Rows in `table` of the database being written by another process (None: not readable yet)."""
    if not db.exists():
        return None
    try:
        conn = sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=0.05)
        try:
            return int(conn.execute(f"SELECT count(*) FROM {table}").fetchone()[0])
        finally:
            conn.close()
    except sqlite3.Error:  # locked by the writer, or the schema is not written yet
        return None


def _scan_and_kill(capture: Path, db: Path, ready, resume: bool = False,
                   sig: int = signal.SIGKILL) -> tuple[int, str, str]:
    """Start `gscan scan capture -o db [--resume]`, send it `sig` as soon as `ready(db)` holds.
    Returns (exit code, stdout, stderr); with SIGKILL the scan must have been killed by it."""
    argv = _cli("scan", capture, "-o", db, "--json", *(["--resume"] if resume else []))
    # SIGINT as in a terminal: a test run started in the background (`cmd &` in a script) ignores it, and
    # the scan would inherit that
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    t0 = time.monotonic()
    try:
        while proc.poll() is None and time.monotonic() - t0 < TIMEOUT_S:
            if ready(db):
                os.kill(proc.pid, sig)
                break
            time.sleep(0.005)
        proc.wait(timeout=TIMEOUT_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    out, err = proc.communicate()
    if sig == signal.SIGKILL:
        assert proc.returncode == -signal.SIGKILL, (f"the scan ended before it was killed (rc {proc.returncode}): "
                                                    f"{err!r}")
    return proc.returncode, out.decode(), err.decode()


def _check_partial(db: Path, capture: Path) -> None:
    """The killed scan's file: intact SQLite, status partial, refused by estimate and export."""
    conn = sqlite3.connect(db)  # a read-write connection rolls a hot journal back first
    try:
        assert conn.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
    finally:
        conn.close()
    info = _gscan("info", db, "--json")
    assert info.returncode == 0, info.stderr
    assert json.loads(info.stdout)["status"] == "partial"
    out = db.parent / "export_out"
    for argv in (("estimate", db, "--color", capture / "rgb" / "000001.png",
                  "--depth", capture / "depth" / "000001.png", "--intrinsics", capture / "cam_K.txt", "--json"),
                 ("export", db, "--format", "json", "-o", out)):
        r = _gscan(*argv)
        assert r.returncode == 2, (argv[0], r.stdout, r.stderr)
        line = r.stderr.strip().splitlines()[-1]
        assert line.startswith("error: ") and db.name in line and "--resume" in line, line
        assert r.stdout == ""
    assert not out.exists()


def _resume(capture: Path, db: Path) -> dict:
    r = _gscan("scan", capture, "-o", db, "--resume", "--json")
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return box_ring_capture(tmp_path_factory.mktemp("resume") / "capture", N_VIEWS, INTR)


@pytest.fixture(scope="module")
def reference(capture: Path) -> tuple[dict, ScanState]:
    """An uninterrupted scan: (its --json output, its database state)."""
    db = capture.parent / "reference.gscan"
    r = _gscan("scan", capture, "-o", db, "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["registered"] >= N_VIEWS - 1, out  # a precondition: the capture registers
    return out, _state(db)


def test_kill_before_any_view_then_during_registration_then_resume(capture: Path, reference, tmp_path: Path):
    """Killed twice: in the first stage (database created, no view written yet), then the resumed
    scan killed again in the middle of registration; the second resume completes it."""
    db = tmp_path / "killed.gscan"
    # 1. the database exists (schema and meta committed) and holds no view yet
    _scan_and_kill(capture, db, lambda p: _count(p, "views") == 0 and bool(_count(p, "meta")))
    conn = sqlite3.connect(db)
    try:
        assert conn.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
        assert conn.execute("SELECT count(*) FROM views").fetchone()[0] == 0
    finally:
        conn.close()
    info = _gscan("info", db, "--json")
    assert info.returncode == 0, info.stderr
    assert json.loads(info.stdout)["status"] == "partial"

    # 2. resume, killed again once some edges are stored
    _scan_and_kill(capture, db, lambda p: (_count(p, "edges") or 0) >= 2, resume=True)
    _check_partial(db, capture)
    with TemplateDB.open(db, require_complete=False) as part:
        n_views, n_edges = len(part.view_names()), len(part.edges())
    assert n_views == N_VIEWS and 2 <= n_edges < reference[1].n_edges  # killed mid-registration

    # 3. resume to the end: the uninterrupted scan's result
    out = _resume(capture, db)
    ref_out, ref_state = reference
    assert out["registered"] == ref_out["registered"]
    assert out["edges"] == ref_out["edges"] and out["mesh"] == ref_out["mesh"]
    _assert_same(_state(db), ref_state)
    info = _gscan("info", db, "--json")
    assert info.returncode == 0 and json.loads(info.stdout)["status"] == "complete"


def test_ctrl_c_keeps_the_partial_scan_and_says_how_to_resume(capture: Path, reference, tmp_path: Path):
    """Ctrl+C (SIGINT) in the middle of registration: exit 130, nothing on stdout (--json), one last stderr line
    saying that the work is kept and how to continue; the resumed scan ends as the uninterrupted one."""
    db = tmp_path / "interrupted.gscan"
    rc, out, err = _scan_and_kill(capture, db, lambda p: (_count(p, "edges") or 0) >= 2, sig=signal.SIGINT)
    assert rc == 130 and out == "", (rc, out, err)
    last = err.strip().splitlines()[-1]
    assert last.startswith(f"interrupted: {db}") and "--resume" in last and "Traceback" not in err, err
    _check_partial(db, capture)
    res = _resume(capture, db)
    assert res["registered"] == reference[0]["registered"] and res["edges"] == reference[0]["edges"]
    _assert_same(_state(db), reference[1])


def test_resume_accepts_a_scan_from_before_a_setting_existed(capture: Path, reference, tmp_path: Path):
    """A partial scan written before a configuration key was added (its stored config lacks it) resumes: the
    new key takes its default, and the scan ends as the uninterrupted one."""
    db = tmp_path / "older.gscan"
    _scan_and_kill(capture, db, lambda p: (_count(p, "edges") or 0) >= 2)
    with TemplateDB.open(db, require_complete=False, writable=True) as part:
        cfg = part.get_meta("config")
        del cfg["registration"]["support_eps_scale"]
        part.set_meta("config", cfg)
    out = _resume(capture, db)
    assert out["registered"] == reference[0]["registered"] and out["edges"] == reference[0]["edges"]


def test_resume_refuses_another_input(capture: Path, reference, tmp_path: Path):
    """--resume into a database written from another capture is bad input, and leaves it untouched."""
    other = tmp_path / "other"
    other.mkdir()
    for sub in ("rgb", "depth"):
        (other / sub).mkdir()
        for k in range(3):
            (other / sub / f"00000{k}.png").write_bytes((capture / sub / f"00000{k}.png").read_bytes())
    (other / "cam_K.txt").write_bytes((capture / "cam_K.txt").read_bytes())
    db = capture.parent / "reference.gscan"
    before = db.read_bytes()
    r = _gscan("scan", other, "-o", db, "--resume", "--json")
    assert r.returncode == 2, r.stderr
    line = r.stderr.strip().splitlines()[-1]
    assert line.startswith("error: ") and db.name in line, line
    assert db.read_bytes() == before


def test_resume_of_a_moved_capture_goes_on(capture: Path, reference, tmp_path: Path):
    """A partial scan whose capture was moved to another folder (the same frames, byte for byte) resumes from the
    new place, naming both paths, and ends as the uninterrupted scan; the template records the new path. A moved
    capture whose frames changed too is refused naming both paths."""
    import shutil

    moved = tmp_path / "moved"
    shutil.copytree(capture, moved)
    db = tmp_path / "partial.gscan"
    shutil.copy(capture.parent / "reference.gscan", db)
    with sqlite3.connect(db) as c:
        c.execute("UPDATE meta SET value='\"partial\"' WHERE key='status'")
    c.close()
    (moved / "depth" / "000001.png").write_bytes((moved / "depth" / "000002.png").read_bytes())
    before = db.read_bytes()
    r = _gscan("scan", moved, "-o", db, "--resume", "--json")
    assert r.returncode == 2, r.stderr
    line = r.stderr.strip().splitlines()[-1]
    assert str(capture.resolve()) in line and str(moved.resolve()) in line and "000001.png changed" in line, line
    assert db.read_bytes() == before
    (moved / "depth" / "000001.png").write_bytes((capture / "depth" / "000001.png").read_bytes())
    r = _gscan("scan", moved, "-o", db, "--resume", "--json")
    assert r.returncode == 0, r.stderr
    assert "the capture was moved" in r.stderr and str(moved.resolve()) in r.stderr
    out = json.loads(r.stdout)
    assert out["registered"] == reference[0]["registered"] and out["edges"] == reference[0]["edges"]
    with TemplateDB.open(db) as t:
        assert t.get_meta("input") == str(moved.resolve())


def test_resume_refuses_a_stored_view_without_keypoints(capture: Path, reference, tmp_path: Path):
    """A partial database whose unregistered view lost its keypoints (written by another tool, or damaged) cannot
    be resumed from: one line naming the database, not an internal error."""
    import shutil

    db = tmp_path / "damaged.gscan"
    shutil.copy(capture.parent / "reference.gscan", db)
    with sqlite3.connect(db) as c:
        c.execute("UPDATE meta SET value='\"partial\"' WHERE key='status'")
        c.execute("UPDATE views SET T_obj_cam=NULL WHERE name='000000'")
        c.execute("DELETE FROM features WHERE view_id=(SELECT id FROM views WHERE name='000000')")
    c.close()
    r = _gscan("scan", capture, "-o", db, "--resume", "--json")
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert lines[-1].startswith(f"error: {db}") and "'000000' is stored without its keypoints" in lines[-1], lines
    assert "internal error" not in r.stderr and r.stdout == ""


def test_resume_refuses_other_intrinsics_or_depth_scale(capture: Path, reference, tmp_path: Path):
    """A different --depth-scale or --intrinsics file would mix two calibrations in one template: --resume
    refuses them (and leaves the database untouched); the same options resume, naming the layout that
    `--format auto` detected included."""
    import shutil
    import sqlite3

    db = tmp_path / "partial.gscan"
    shutil.copy(capture.parent / "reference.gscan", db)
    with sqlite3.connect(db) as c:
        c.execute("UPDATE meta SET value='\"partial\"' WHERE key='status'")
    c.close()
    k700 = tmp_path / "K700.txt"
    k700.write_text((capture / "cam_K.txt").read_text().replace("307.5", "350.0", 1))
    same_k = tmp_path / "same_K.txt"
    same_k.write_bytes((capture / "cam_K.txt").read_bytes())
    before = db.read_bytes()
    for extra in (("--depth-scale", "0.0009"), ("--intrinsics", k700), ("--intrinsics", same_k)):
        r = _gscan("scan", capture, "-o", db, "--resume", "--json", *extra)
        assert r.returncode == 2, (extra, r.stderr)
        assert "another input or configuration" in r.stderr.strip().splitlines()[-1], r.stderr
        assert db.read_bytes() == before
    r = _gscan("scan", capture, "-o", db, "--resume", "--json", "--format", "capture")  # what auto detected
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["registered"] == reference[0]["registered"]


def test_ctrl_c_during_a_slow_import_arrives_after_it(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    """The scan imports open3d (about 0.5 s of C initialisation) with SIGINT held: a Ctrl+C in that window
    turned into "ImportError: initialization failed", reported as an internal error (exit 1) instead of an
    interruption. Here a module sends itself SIGINT in its body: the import completes, then the
    KeyboardInterrupt arrives."""
    from gscan.cli.imports import import_holding_ctrl_c

    (tmp_path / "gscan_test_slow_import.py").write_text(
        "import os, signal, time\nos.kill(os.getpid(), signal.SIGINT)\ntime.sleep(0.05)\nDONE = True\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.delitem(sys.modules, "gscan_test_slow_import", raising=False)
    outer = signal.signal(signal.SIGINT, signal.default_int_handler)  # as in a terminal (CI may ignore SIGINT)
    try:
        with pytest.raises(KeyboardInterrupt):
            import_holding_ctrl_c("gscan_test_slow_import")
        assert sys.modules["gscan_test_slow_import"].DONE
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # Ctrl+C interrupts again
    finally:
        signal.signal(signal.SIGINT, outer)
