"""How a scan writes its database and holds its frames: each stage's writes in one transaction (a chunk of a long
stage at most), each view's images written once, the finished file a rollback-journal database."""
from __future__ import annotations

import sqlite3
from pathlib import Path

import pytest

from gscan import synth
from gscan.scan.api import scan
from gscan.template.db import TemplateDB

INTR = synth.DEFAULT_INTRINSICS.scaled(0.5)  # 320 x 240
N_VIEWS = 6  # 60 degree steps on one ring


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("stream") / "capture"
    mesh = synth.box_mesh((0.14, 0.09, 0.07), synth.procedural_box_texture(3, (512, 768)))
    synth.render_capture(mesh, root, N_VIEWS, mode="static", elevations_deg=(40.0,), intr=INTR)
    return root


def test_scan_commits_per_stage_and_writes_each_view_once(capture: Path, tmp_path: Path,
                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    """Every SQL statement the scan's connection runs is traced: each view row is inserted once (its images
    encoded once; the last stage sets its pose, mask and keyframe flag), and the scan commits once per stage (not
    once per view and edge: each commit of a rollback journal costs an fsync); the file it leaves is a
    rollback-journal database with nothing beside it."""
    statements: list[str] = []
    connect = TemplateDB._connect

    def traced(path: Path, writable: bool = True, wal: bool = False) -> sqlite3.Connection:
        conn = connect(path, writable, wal)
        conn.set_trace_callback(statements.append)
        return conn

    monkeypatch.setattr(TemplateDB, "_connect", staticmethod(traced))
    out = tmp_path / "obj.gscan"
    res = scan(capture, out)
    assert res.registered == N_VIEWS
    inserts = [s for s in statements if s.startswith("INSERT INTO views")]
    commits = [s for s in statements if s.startswith("COMMIT")]
    assert len(inserts) == N_VIEWS, len(inserts)
    # the schema, then the stages that write (features, noise, sequential edges, loop closures, the last stage)
    assert len(commits) <= 6, (len(commits), len(statements))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["obj.gscan"]
    assert out.read_bytes()[18:20] == b"\x01\x01"  # rollback journal, not WAL
