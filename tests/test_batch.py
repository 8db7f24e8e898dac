"""`gscan batch` and `gscan batch-eval` (issue 22): many captures scanned and many templates scored on Ray.

End to end through the real CLI on a local Ray runtime of 2 workers: 4 rendered captures (8 views, 320 x 240), one
of them corrupt, beside three loops of symbolic links; the templates equal `gscan.scan()`'s in this process; the
corrupt capture and the loops are reported with their one-line reasons and exit code 2; the Ray worker scanning
box0 is killed in the middle of its scan, and its task is retried and the template resumed. Ray starts once for all
of that (a runtime's start and its workers' imports cost more than a small scan). A second run skips everything
without starting Ray; without Ray the command says how to install it. The fast tests cover the parts that need no
Ray: finding the captures, the plan, the exit codes, the manifest and the joined CSV.
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

import gscan
from gscan import synth
from gscan.batch.evaluate import BatchEvalReport, Pair, PairRow, assign_obj_ids, combined_csv, find_pairs, read_manifest
from gscan.batch.scan import BatchReport, CaptureRow, _plan, find_captures
from gscan.errors import InputError
from gscan.scanning.config import ScanConfig
from gscan.template.db import TemplateDB

INTR = synth.DEFAULT_INTRINSICS.scaled(0.5)  # 320 x 240
N_VIEWS = 8
NAMES = ("box0", "box1", "box2", "box3")
CORRUPT = "box3"
LOOPS = ("a", "b", "loop")  # `_loops`: broken entries beside the captures
TIMEOUT_S = 600


def _cli(*args: str | Path) -> list[str]:
    return [sys.executable, "-m", "gscan.cli", *map(str, args)]


def _gscan(*args: str | Path) -> subprocess.CompletedProcess:
    return subprocess.run(_cli(*args), check=False, capture_output=True, text=True, timeout=TIMEOUT_S)


def _render(root: Path, k: int, views: int = N_VIEWS, seed: int | None = None, elevation: float = 40.0) -> Path:
    mesh = synth.box_mesh((0.14, 0.09, 0.07), synth.procedural_box_texture(3 + k, (512, 768)))
    synth.render_capture(mesh, root, views, mode="static", elevations_deg=(elevation,), intr=INTR,
                         seed=k if seed is None else seed)
    return root


def _poses(db_path: Path) -> dict[str, np.ndarray | None]:
    with TemplateDB.open(db_path, require_complete=True) as db:
        return {v.name: v.T_obj_cam for v in db.views(load_images=False)}


def _assert_same_poses(a: Path, b: Path) -> None:
    pa, pb = _poses(a), _poses(b)
    assert sorted(pa) == sorted(pb)
    for name, T in pa.items():
        U = pb[name]
        assert (T is None) == (U is None), name
        if T is not None:
            assert np.max(np.abs(T - U)) <= 1e-9, (name, np.max(np.abs(T - U)))


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def captures(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """4 rendered captures (box3's intrinsics file is garbage) and three loops of links (`_loops`)."""
    root = tmp_path_factory.mktemp("batch") / "captures"
    for k, name in enumerate(NAMES):
        _render(root / name, k)
    (root / CORRUPT / "cam_K.txt").write_text("not a matrix\n")
    _loops(root)
    return root


@pytest.fixture(scope="module")
def reference_box0(captures: Path) -> Path:
    """`gscan.scan()` of box0 in this process."""
    out = captures.parent / "reference" / "box0.gscan"
    gscan.scan(captures / "box0", out)
    return out


@pytest.fixture(scope="module")
def references(captures: Path, reference_box0: Path) -> dict[str, Path]:
    """`gscan.scan()` of the good captures in this process."""
    refs = {"box0": reference_box0}
    for name in NAMES:
        if name not in refs and name != CORRUPT:
            refs[name] = reference_box0.parent / f"{name}.gscan"
            gscan.scan(captures / name, refs[name])
    return refs


@dataclass
class FirstRun:
    """The first `gscan batch` run: its process, its templates folder and the worker killed in it."""

    proc: subprocess.CompletedProcess
    out: Path
    killed: tuple[int, int, bool] | None  # (Ray worker, its scan's process, that process ended with the worker)


@pytest.fixture(scope="module")
def first_run(captures: Path) -> FirstRun:
    """`gscan batch` over `captures` on a local runtime of 2 workers; the Ray worker running box0's scan is killed
    (SIGKILL) once the scan has written a view to its partial template."""
    out = captures.parent / "templates"
    target = out / "box0.gscan"
    proc = subprocess.Popen(_cli("batch", captures, "-o", out, "--workers", "2", "--json"), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    killed = None
    try:
        t0 = time.monotonic()
        while proc.poll() is None and time.monotonic() - t0 < TIMEOUT_S and killed is None:
            child = next((pid for pid, req in _children().items() if req.get("key") == "box0"), None)
            if child is not None and _partial_with_views(target):
                worker = _parent(child)
                assert b"ray::" in Path(f"/proc/{worker}/cmdline").read_bytes()  # the Ray worker running the task
                os.kill(worker, signal.SIGKILL)
                killed = (worker, child, _gone(child))
            time.sleep(0.01)
        stdout, stderr = proc.communicate(timeout=TIMEOUT_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return FirstRun(subprocess.CompletedProcess(proc.args, proc.returncode, stdout, stderr), out, killed)


# ------------------------------------------------------------------------------------------ end to end (Ray)
PROC = Path("/proc/self/status").is_file()  # the first run finds the worker to kill through /proc (Linux)


@pytest.mark.slow
def test_batch_scans_as_scan_does_and_reports_the_corrupt_capture(captures: Path, references: dict[str, Path],
                                                                  first_run: FirstRun) -> None:
    """The good captures' templates equal `gscan.scan()`'s (box0's too, resumed after its worker was killed); the
    corrupt capture and each loop of links are a failed capture with a one-line reason naming it, and the run
    exits with code 2 (bad input only, nothing crashed); no output for a failed capture."""
    r, out = first_run.proc, first_run.out
    assert r.returncode == 2, r.stderr  # captures had bad input, none crashed
    report = json.loads(r.stdout)  # exactly one JSON object on stdout (Ray's messages about the dead worker: not)
    assert json.loads((out / "batch.json").read_text()) == report
    s = report["summary"]
    resumed = int(first_run.killed is not None)  # box0
    assert (s["captures"], s["scanned"], s["resumed"], s["failed"], s["failed_input"], s["skipped"]) == (
        7, 3 - resumed, resumed, 4, 4, 0)
    assert s["runtime"] == "local" and s["cpus"] == 2 and s["max_retries"] >= 1
    rows = {row["name"]: row for row in report["captures"]}
    assert list(rows) == sorted([*NAMES, *LOOPS])
    bad = rows[CORRUPT]
    assert bad["status"] == "failed" and bad["error_kind"] == "input"
    assert "\n" not in bad["error"] and str(captures / CORRUPT / "cam_K.txt") in bad["error"], bad["error"]
    assert f"failed {CORRUPT}: {bad['error']}" in r.stderr
    for name in LOOPS:  # once "internal error: RuntimeError: Symlink loop" and nothing scanned
        row = rows[name]
        assert row["status"] == "failed" and row["error_kind"] == "input", row
        assert "loop of symbolic links" in row["error"] and str(captures / name) in row["error"], row
    for name in (CORRUPT, *LOOPS):
        assert not (out / f"{name}.gscan").exists()  # no half-written output
    for name, ref in references.items():
        row = rows[name]
        resumed = name == "box0" and first_run.killed is not None
        assert (row["status"], row["attempts"]) == (("resumed", 2) if resumed else ("scanned", 1)), row
        _assert_same_poses(out / f"{name}.gscan", ref)
        with TemplateDB.open(ref) as db:
            summary = db.summary()
        assert (row["frames"], row["registered"], row["keyframes"]) == (N_VIEWS, summary.registered,
                                                                       summary.keyframes)
        assert row["threads"] == {"blas": 1, "openmp": 1, "numba": 1, "opencv": 1}, row["threads"]
        # the scan's own process: a Python with numpy, OpenCV and open3d loaded holds well over 100 MiB
        assert 100 * 2**20 < row["peak_rss_bytes"] < 8 * 2**30, row["peak_rss_bytes"]
        gt = row["ground_truth"]
        assert gt["reference"] == "T_cam_obj" and gt["gt_frames"] == row["registered"]
        assert gt["ate_rmse_m"] < 0.005 and gt["wrong_frames"] == [], gt
    lines = (out / "batch.csv").read_text().splitlines()
    assert lines[0].startswith("name,status,attempts,frames,registered,") and len(lines) == 1 + len(rows)
    assert [ln.split(",")[0] for ln in lines[1:]] == list(rows)
    assert lines[1 + list(rows).index(CORRUPT)].startswith(f"{CORRUPT},failed,")


@pytest.mark.slow
@pytest.mark.skipif(not PROC, reason="finds the worker through /proc (Linux)")
def test_a_worker_killed_mid_scan_is_retried_and_its_template_resumed(references: dict[str, Path],
                                                                     first_run: FirstRun) -> None:
    """The first run's Ray worker scanning box0, killed once the scan had written a view: the scan's own process
    ends with it, the task is retried and resumes the partial template, which ends complete, valid and equal to
    `gscan.scan()`'s; the other captures are scanned once."""
    killed = first_run.killed
    assert killed is not None, "the scan of box0 ended before its worker could be killed"
    assert killed[2], "the scan's process outlived its worker"
    rows = {row["name"]: row for row in json.loads(first_run.proc.stdout)["captures"]}
    assert rows["box0"]["attempts"] == 2 and rows["box0"]["status"] == "resumed", rows["box0"]
    assert rows["box1"]["status"] == "scanned" and rows["box1"]["attempts"] == 1
    target = first_run.out / "box0.gscan"
    with TemplateDB.open(target) as db:  # complete and valid
        assert db.status == "complete"
        conn = sqlite3.connect(target)
        try:
            assert conn.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
        finally:
            conn.close()
    _assert_same_poses(target, references["box0"])


@pytest.mark.slow
def test_second_run_skips_every_complete_template(captures: Path, first_run: FirstRun, tmp_path: Path) -> None:
    """The good captures again (links to them) into a copy of the first run's templates: every one is skipped
    (Ray is not even started) and no template is touched."""
    r, out = first_run.proc, first_run.out
    assert r.returncode == 2, r.stderr
    again, templates = tmp_path / "captures", tmp_path / "templates"
    again.mkdir()
    templates.mkdir()
    for name in NAMES:
        if name != CORRUPT:
            (again / name).symlink_to(captures / name, target_is_directory=True)
            shutil.copy2(out / f"{name}.gscan", templates / f"{name}.gscan")
    before = {p.name: _digest(p) for p in templates.glob("*.gscan")}
    r2 = _gscan("batch", again, "-o", templates, "--workers", "2", "--json")
    assert r2.returncode == 0, r2.stderr
    report = json.loads(r2.stdout)
    assert [row["status"] for row in report["captures"]] == ["skipped"] * 3
    assert report["summary"]["runtime"] is None  # nothing to scan: no Ray runtime started
    first = {row["name"]: row for row in json.loads(r.stdout)["captures"]}
    for row in report["captures"]:  # the facts come from the template itself
        for k in ("frames", "registered", "keyframes", "ground_truth"):
            assert row[k] == first[row["name"]][k], k
    assert {p.name: _digest(p) for p in templates.glob("*.gscan")} == before


def _children() -> dict[int, dict]:
    """pid -> request of every running `gscan.batch.child` process."""
    out = {}
    for p in Path("/proc").iterdir():
        if not p.name.isdigit():
            continue
        try:
            argv = (p / "cmdline").read_bytes().split(b"\0")
            if b"gscan.batch.child" not in argv:
                continue
            out[int(p.name)] = json.loads(Path(argv[argv.index(b"gscan.batch.child") + 1].decode()).read_text())
        except (OSError, ValueError, IndexError):
            continue
    return out


def _gone(pid: int, timeout_s: float = 5.0) -> bool:
    """Whether process `pid` ends (or is a zombie) within `timeout_s`."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        try:
            state = Path(f"/proc/{pid}/status").read_text().split("State:")[1].split()[0]
        except (OSError, IndexError):
            return True
        if state == "Z":
            return True
        time.sleep(0.02)
    return False


def _parent(pid: int) -> int:
    status = Path(f"/proc/{pid}/status").read_text()
    return int(next(ln for ln in status.splitlines() if ln.startswith("PPid:")).split()[1])


def _partial_with_views(db: Path) -> bool:
    """The database a scan writes is still partial and holds a view (the scan is under way)."""
    if not db.is_file():
        return False
    try:
        conn = sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=0.05)
        try:
            status = json.loads(conn.execute("SELECT value FROM meta WHERE key='status'").fetchone()[0])
            views = conn.execute("SELECT count(*) FROM views").fetchone()[0]
        finally:
            conn.close()
    except (sqlite3.Error, TypeError):
        return False
    return status == "partial" and views > 0


@pytest.fixture(scope="module")
def scenes(captures: Path) -> Path:
    """3 views of each good box from a higher ring (capture layout, ground-truth poses)."""
    root = captures.parent / "scenes"
    for k, name in enumerate(NAMES[:3]):
        _render(root / name, k, views=3, seed=10 + k, elevation=50.0)
    return root


@pytest.mark.slow
def test_batch_eval_joins_the_pairs_as_eval_scores_them(captures: Path, first_run: FirstRun, scenes: Path,
                                                        tmp_path: Path) -> None:
    from gscan.evaluate.bop19 import evaluate

    templates = first_run.out
    res = _gscan("batch-eval", templates, scenes, "-o", tmp_path / "gscan_test.csv", "--workers", "2", "--json")
    assert res.returncode == 0, res.stderr
    report = json.loads(res.stdout)
    s = report["summary"]
    assert (s["pairs"], s["evaluated"], s["failed"]) == (3, 3, 0) and s["wrong_accepted"] == 0
    assert json.loads((tmp_path / "gscan_test.objects.json").read_text()) == report
    rows = {row["name"]: row for row in report["pairs"]}
    lines = (tmp_path / "gscan_test.csv").read_text().splitlines()
    assert lines[0] == "scene_id,im_id,obj_id,score,R,t,time"
    csv_rows = [ln.split(",") for ln in lines[1:]]
    times: dict[tuple[str, str], set[str]] = {}
    for c in csv_rows:
        times.setdefault((c[0], c[1]), set()).add(c[6])
    assert all(len(t) == 1 for t in times.values())  # one time per image, as the BOP toolkit requires
    # each pair as `gscan eval` scores it alone
    for name in ("box0", "box2"):
        row = rows[name]
        single = evaluate(templates / f"{name}.gscan", scenes / name, tmp_path / f"{name}.csv", obj_id=row["obj_id"])
        assert _without_time(row["metrics"]) == pytest.approx(_without_time(single.metrics), abs=1e-6)
        assert (row["images"], row["found"]) == (single.n_images, single.n_found)
        own = [ln.split(",") for ln in (tmp_path / f"{name}.csv").read_text().splitlines()[1:]]
        mine = [c for c in csv_rows if int(c[2]) == row["obj_id"]]
        assert len(mine) == len(own) and len(own) == single.n_found
        for a, b in zip(mine, own, strict=True):
            assert a[:3] == b[:3]
            np.testing.assert_allclose([float(x) for x in a[4].split() + a[5].split()],
                                       [float(x) for x in b[4].split() + b[5].split()], atol=1e-6)
    assert sorted(row["obj_id"] for row in rows.values()) == [1, 2, 3]
    assert s["pooled"]["AR"] == pytest.approx(
        sum(row["gt_images"] * row["metrics"]["AR"] for row in rows.values()) / sum(row["gt_images"]
                                                                                  for row in rows.values()))


def _without_time(metrics: dict) -> dict:
    return {k: v for k, v in metrics.items() if k != "mean time ms"}


# ------------------------------------------------------------------------------------------ without Ray
@pytest.mark.parametrize("command", ["batch", "batch-eval"])
def test_without_ray_the_command_says_how_to_install_it(command: str, tmp_path: Path) -> None:
    """Inputs that pass the checks made before Ray loads (a recording to scan; a template and its scenes)."""
    (tmp_path / "caps").mkdir()
    (tmp_path / "caps" / "box.bag").write_bytes(b"")
    (tmp_path / "scenes" / "box").mkdir(parents=True)
    (tmp_path / "caps" / "box.gscan").write_bytes(b"")
    args = [command, str(tmp_path / "caps"), "-o", str(tmp_path / "out")]
    if command == "batch-eval":
        args.insert(2, str(tmp_path / "scenes"))
    code = ("import sys; sys.modules['ray'] = None; sys.argv = ['gscan'] + sys.argv[1:]; "
            "from gscan.cli import main; main()")
    r = subprocess.run([sys.executable, "-c", code, *args], check=False, capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 2, r.stderr
    assert r.stdout == ""
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "pip install 'gscan[ray]'" in lines[0], r.stderr
    assert not (tmp_path / "out").exists()


# ------------------------------------------------------------------------------------------ no Ray needed
def test_find_captures_takes_folders_and_recordings_by_name(tmp_path: Path) -> None:
    caps = tmp_path / "caps"
    for d in ("mug", "box", ".hidden", "templates"):
        (caps / d).mkdir(parents=True)
    (caps / "cereal.bag").write_bytes(b"")
    (caps / "tea.MCAP").write_bytes(b"")
    (caps / "notes.txt").write_text("not a capture")
    found = find_captures(caps, caps / "templates")  # the templates folder inside is no capture
    assert [(c.name, c.source.name, c.output.name) for c in found] == [
        ("box", "box", "box.gscan"), ("cereal", "cereal.bag", "cereal.gscan"), ("mug", "mug", "mug.gscan"),
        ("tea", "tea.MCAP", "tea.gscan")]
    (caps / "mug.db3").write_bytes(b"")
    with pytest.raises(InputError, match="same template"):
        find_captures(caps, tmp_path / "out")


def test_find_captures_refuses_a_capture_an_empty_folder_and_a_missing_one(captures: Path, tmp_path: Path) -> None:
    with pytest.raises(InputError, match="is a capture itself"):
        find_captures(captures / "box0", tmp_path / "out")
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="holds no capture"):
        find_captures(tmp_path / "empty", tmp_path / "out")
    with pytest.raises(InputError, match="not found"):
        find_captures(tmp_path / "missing", tmp_path / "out")


def test_plan_skips_only_a_complete_template_of_the_same_capture_and_configuration(captures: Path,
                                                                                   reference_box0: Path,
                                                                                   tmp_path: Path) -> None:
    from gscan.batch.scan import Capture

    cfg = ScanConfig()
    ref = reference_box0
    assert _plan(Capture("box0", captures / "box0", tmp_path / "none.gscan"), False, cfg) is None  # scanned
    skipped = _plan(Capture("box0", captures / "box0", ref), False, cfg)
    assert skipped is not None and skipped.status == "skipped" and skipped.registered == N_VIEWS
    assert skipped.ground_truth is not None and skipped.ground_truth["gt_frames"] == N_VIEWS
    assert _plan(Capture("box0", captures / "box0", ref), True, cfg) is None  # force: scanned again
    other = _plan(Capture("box1", captures / "box1", ref), False, cfg)  # box0's template
    assert other is not None and other.status == "failed" and other.fix == "replace" and "box0" in (other.error or "")
    changed = _plan(Capture("box0", captures / "box0", ref), False, ScanConfig.model_validate(
        {"features": {"max_keypoints": 500}}))
    assert changed is not None and changed.status == "failed" and "configuration" in (changed.error or "")
    junk = tmp_path / "junk.gscan"
    junk.write_text("not a database")
    row = _plan(Capture("junk", captures / "box0", junk), False, cfg)
    assert row is not None and row.status == "failed" and row.error_kind == "input" and str(junk) in (row.error or "")


def test_exit_codes_follow_the_failures() -> None:
    def report(*kinds: str | None) -> BatchReport:
        rows = [CaptureRow(f"c{k}", "in", "out", "scanned" if kind is None else "failed", error_kind=kind)
                for k, kind in enumerate(kinds)]
        return BatchReport(Path("in"), Path("out"), rows, 1.0, "local", 2)

    assert report(None, None).exit_code == 0
    assert report(None, "input", "input").exit_code == 2
    assert report("input", "internal").exit_code == 1
    assert report(None, "lost").exit_code == 1
    assert report("killed").exit_code == 1


def test_manifest_pairs_names_and_object_ids(tmp_path: Path) -> None:
    (tmp_path / "m.csv").write_text("# the lab's catalogue\ntemplate,scenes,obj_id\nt/mug.gscan,s/a,7\n"
                                    "t/mug.gscan,s/b,\nt/obj_000004.gscan,s/a,\nt/cup.gscan,s/a,\n")
    pairs = read_manifest(tmp_path / "m.csv")
    assert [p.name for p in pairs] == ["mug@a", "mug@b", "obj_000004", "cup"]
    assert pairs[0].template == tmp_path / "t" / "mug.gscan" and pairs[1].scenes == tmp_path / "s" / "b"
    assign_obj_ids(pairs)
    assert [p.obj_id for p in pairs] == [7, 7, 4, 1]  # given; the template's; a BOP name; the first free id
    for text, what in (("template,scene\na,b\n", "header"), ("template,scenes\na\n", "1 cells"),
                       ("template,scenes,obj_id\na,b,x\n", "positive integer"), ("template,scenes\n", "no pair"),
                       ("template,scenes\na,b\na,b\n", "two pairs"),
                       # an unclosed quote is refused on its own line, never joined with the lines after it
                       ('template,scenes\na,"b\nc,d\n', "line 2: not a CSV row")):
        (tmp_path / "bad.csv").write_text(text)
        with pytest.raises(InputError, match=what):
            read_manifest(tmp_path / "bad.csv")
    clash = [Pair("a", tmp_path / "a.gscan", tmp_path, 3), Pair("b", tmp_path / "b.gscan", tmp_path, 3)]
    with pytest.raises(InputError, match="object id 3"):
        assign_obj_ids(clash)


def test_find_pairs_by_name_lists_the_unpaired(tmp_path: Path) -> None:
    (tmp_path / "t").mkdir()
    for n in ("mug", "cup"):
        (tmp_path / "t" / f"{n}.gscan").write_bytes(b"")
    for n in ("mug", "bowl"):
        (tmp_path / "s" / n).mkdir(parents=True)
    pairs, lone_t, lone_s = find_pairs(tmp_path / "t", tmp_path / "s")
    assert [(p.name, p.scenes.name) for p in pairs] == [("mug", "mug")] and lone_t == ["cup"] and lone_s == ["bowl"]
    with pytest.raises(InputError, match="pair them with a manifest"):
        find_pairs(tmp_path / "t", tmp_path / "t")


def test_joined_csv_gives_each_image_the_time_of_every_object_scored_in_it(tmp_path: Path) -> None:
    scene = tmp_path / "000048"
    pairs = [Pair("a", tmp_path / "a.gscan", scene, 1), Pair("b", tmp_path / "b.gscan", scene, 2),
             Pair("c", tmp_path / "c.gscan", scene, 3)]
    R = "1 0 0 0 1 0 0 0 1"
    results = {
        "a": {"ok": True, "csv_lines": [f"48,1,1,0.9,{R},0 0 500,0.100000"],
              "image_times": [[48, 1, 0.1], [48, 2, 0.3]]},
        "b": {"ok": True, "csv_lines": [f"48,1,2,0.8,{R},0 0 400,0.200000", f"48,2,2,0.7,{R},1 2 3,0.050000"],
              "image_times": [[48, 1, 0.2], [48, 2, 0.05]]},
        "c": {"ok": False, "error": "failed"},
    }
    text, warnings = combined_csv(pairs, results)
    assert text.splitlines() == ["scene_id,im_id,obj_id,score,R,t,time", f"48,1,1,0.9,{R},0 0 500,0.300000",
                                 f"48,1,2,0.8,{R},0 0 400,0.300000", f"48,2,2,0.7,{R},1 2 3,0.350000"]
    assert warnings == []
    pairs[1].scenes = tmp_path / "elsewhere" / "000048"  # another folder, the same scene id
    assert len(combined_csv(pairs, results)[1]) == 1


def test_pooled_recall_weights_the_pairs_by_their_targets() -> None:
    rows = [PairRow("a", "a", "s", 1, "evaluated", images=10, gt_images=10, metrics={"AR": 50.0, "AR VSD": 40.0,
                                                                                    "AR MSSD": 60.0, "AR MSPD": 50.0}),
            PairRow("b", "b", "s", 2, "evaluated", images=30, gt_images=30, metrics={"AR": 90.0, "AR VSD": 80.0,
                                                                                    "AR MSSD": 100.0,
                                                                                    "AR MSPD": 90.0})]
    s = BatchEvalReport(Path("r.csv"), rows, [], [], [], 1.0, "local", 2).summary()
    assert s["pooled"]["AR"] == pytest.approx(80.0) and s["pooled"]["AR MSSD"] == pytest.approx(90.0)


# ------------------------------------------------------------------------------------------ loops of links
def _loops(caps: Path) -> None:
    """Three broken entries: a link to itself, two links to each other."""
    os.symlink("loop", caps / "loop")
    os.symlink("b", caps / "a")
    os.symlink("a", caps / "b")


def test_find_captures_reports_loops_of_links_as_failed_captures(tmp_path: Path) -> None:
    caps = tmp_path / "caps"
    (caps / "box").mkdir(parents=True)
    _loops(caps)
    os.symlink("missing", caps / "gone")
    found = {c.name: c for c in find_captures(caps, tmp_path / "out")}
    assert sorted(found) == ["a", "b", "box", "gone", "loop"]
    assert found["box"].problem is None
    for name in ("a", "b", "loop"):
        assert "loop of symbolic links" in str(found[name].problem)
    assert "does not exist" in str(found["gone"].problem)
    assert find_captures(caps, caps / "loop") and find_captures(caps, caps / "a")  # an output on a loop: no crash


def test_manifest_pairs_on_loops_of_links_get_object_ids(tmp_path: Path) -> None:
    """A manifest's template that is a loop of links once stopped assign_obj_ids with RuntimeError (resolve()):
    the pairs get their ids, the loop is left to fail as its pair's bad input."""
    _loops(tmp_path)
    pairs = [Pair("a", tmp_path / "a", tmp_path), Pair("loop", tmp_path / "loop", tmp_path)]
    assign_obj_ids(pairs)
    assert sorted(p.obj_id for p in pairs) == [1, 2]
