"""Hostile files through the real command line (GitHub issue 21): no data loss, no writes outside the output,
no terminal injection, bounded memory, no silent resume on other frames, true messages.

Every case runs `python -m gscan.cli ...` in a subprocess on small captures and templates built here. The
viewer's cases (markup in names, --host, --token) are in test_hostile_viewer.py, the property test of names
through every export in test_safe_names.py.
"""
from __future__ import annotations

import hashlib
import json
import os
import resource
import shutil
import sqlite3
import struct
import subprocess
import sys
import zlib
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from gscan import synth
from gscan.template.db import TemplateDB

ROOT = Path(__file__).resolve().parents[1]
INTR = synth.DEFAULT_INTRINSICS.scaled(0.5)  # 320 x 240
N_VIEWS = 6
TIMEOUT_S = 300
BOMB_SIDE = 12000  # a 12000 x 12000 RGB PNG of zeros: 0.4 MB on disk, 432 MB decoded
LONG = 250  # characters of a legal long file name (NAME_MAX is 255 bytes)


def _cli(*args: str | Path) -> list[str]:
    return [sys.executable, "-m", "gscan.cli", *map(str, args)]


def _gscan(*args: str | Path, env: dict | None = None, fsize: int | None = None,
           unreadable: bool = False) -> subprocess.CompletedProcess:
    """Run the CLI; `fsize`: the process's file size limit (RLIMIT_FSIZE, what `ulimit -f` sets), `unreadable`:
    without root's right to read any file (util-linux setpriv)."""
    cmd = _cli(*args)
    if unreadable and os.geteuid() == 0:
        if shutil.which("setpriv") is None:
            pytest.fail("running as root without util-linux setpriv: cannot drop the right to read any file")
        cmd = ["setpriv", "--bounding-set", "-dac_override,-dac_read_search"] + cmd

    def limit() -> None:
        if fsize is not None:
            resource.setrlimit(resource.RLIMIT_FSIZE, (fsize, fsize))

    return subprocess.run(cmd, capture_output=True, text=True, timeout=TIMEOUT_S, cwd=ROOT,
                          env={**os.environ, **(env or {})}, preexec_fn=limit, check=False)


def _parallel(*calls):
    """Run the zero-argument `calls` (CLI runs) two at a time; their results in order."""
    with ThreadPoolExecutor(max_workers=2) as pool:
        return list(pool.map(lambda c: c(), calls))


def _error(proc: subprocess.CompletedProcess, *names: str) -> str:
    """The one `error:` line of a run that must exit 2 naming `names`; no traceback, nothing on stdout."""
    detail = f"rc {proc.returncode}\nstdout: {proc.stdout!r}\nstderr: {proc.stderr!r}"
    assert proc.returncode == 2, detail
    assert "Traceback" not in proc.stderr and proc.stdout == "", detail
    lines = [ln for ln in proc.stderr.splitlines() if ln.startswith("error: ")]
    assert len(lines) == 1, detail
    for n in names:
        assert n in lines[0], f"{n!r} not in {lines[0]!r}"
    return lines[0]


def _ok(proc: subprocess.CompletedProcess) -> subprocess.CompletedProcess:
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc


def _sha(p: Path) -> str | dict:
    if p.is_dir():
        return {str(f.relative_to(p)): _sha(f) for f in sorted(p.rglob("*")) if f.is_file()}
    return hashlib.sha256(p.read_bytes()).hexdigest()


def _hidden(folder: Path) -> list[str]:
    """Temporary siblings (and SQLite journals) left in `folder`."""
    return sorted(p.name for p in folder.iterdir() if p.name.startswith(".") or p.name.endswith("-journal"))


def _png_bomb(path: Path, w: int, h: int, depth16: bool = False) -> Path:
    """A PNG of zeros that declares w x h pixels (8-bit RGB, or 16-bit grey), written row by row so that the
    test never holds the decoded image."""
    ctype, bpp = (0, 2) if depth16 else (2, 3)

    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    comp = zlib.compressobj(9)
    row = b"\x00" * (1 + w * bpp)
    idat = b"".join([comp.compress(row) for _ in range(h)] + [comp.flush()])
    ihdr = struct.pack(">IIBBBBB", w, h, 16 if depth16 else 8, ctype, 0, 0, 0)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", idat) + chunk(b"IEND", b""))
    return path


# ------------------------------------------------------------------------------------------ fixtures
@dataclass
class Ctx:
    capture: Path  # a capture that scans (rgb/ depth/ masks/ annotated_poses/ cam_K.txt)
    dark: Path  # the same capture with every colour image black and every depth image empty: a scan of it fails
    mesh: Path  # the box as a textured OBJ
    template: Path  # a complete scanned template of `capture`
    cad: Path  # a complete CAD template of `mesh`
    bomb: Path  # a BOMB_SIDE x BOMB_SIDE colour PNG


@pytest.fixture(scope="module")
def ctx(tmp_path_factory: pytest.TempPathFactory) -> Ctx:
    from gscan.scanning.api import scan
    from gscan.scanning.cad import template_from_mesh

    base = tmp_path_factory.mktemp("hostile")
    mesh = synth.box_mesh((0.14, 0.09, 0.07), synth.procedural_box_texture(3, (512, 768)))
    synth.render_capture(mesh, base / "capture", N_VIEWS, mode="static", elevations_deg=(40.0,), intr=INTR)
    dark = base / "dark"
    shutil.copytree(base / "capture", dark)
    for p in (dark / "rgb").iterdir():
        p.write_bytes(_black_png(INTR))
    for p in (dark / "depth").iterdir():  # depth alone registers a plain object: none either
        p.write_bytes(_black_png(INTR, np.uint16))
    mesh_path = synth.save_textured_mesh(mesh, base / "box" / "box.obj")
    scan(base / "capture", base / "scanned.gscan")
    template_from_mesh(mesh_path, base / "cad.gscan", n_views=6)
    bomb = _png_bomb(base / "bomb" / "color.png", BOMB_SIDE, BOMB_SIDE)
    return Ctx(base / "capture", dark, mesh_path, base / "scanned.gscan", base / "cad.gscan", bomb)


def _black_png(intr, dtype=np.uint8) -> bytes:
    """A PNG of zeros of the camera's size: colour (uint8, three channels) or depth (uint16)."""
    import cv2

    shape = (intr.height, intr.width) + ((3,) if dtype == np.uint8 else ())
    return cv2.imencode(".png", np.zeros(shape, dtype))[1].tobytes()


def _precious(ctx: Ctx, path: Path) -> Path:
    """A user's own template (a copy of the CAD template with a grasp of theirs)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    shutil.copy(ctx.cad, path)
    with TemplateDB.open(path, writable=True) as db:
        db.add_grasp("mine", np.eye(4))
    return path


# ------------------------------------------------------------------------------------------ 1. no data loss
def test_failed_force_scan_keeps_the_old_template(ctx: Ctx, tmp_path: Path):
    """`scan DARK -o precious.gscan --force` fails (no keypoint in any frame, no depth): the existing template is left
    byte for byte, nothing else is left beside it; a scan that succeeds does replace it."""
    keep = _precious(ctx, tmp_path / "out" / "precious.gscan")
    before = _sha(keep)
    _error(_gscan("scan", ctx.dark, "-o", keep, "--force", "--json"), "dark")
    assert _sha(keep) == before and _hidden(keep.parent) == []
    _ok(_gscan("scan", ctx.capture, "-o", keep, "--force", "--json"))
    with TemplateDB.open(keep) as db:
        assert db.status == "complete" and db.grasps() == {} and db.get_meta("source") == "scan"
    assert _hidden(keep.parent) == []


def test_black_images_with_depth_register_on_the_depth(ctx: Ctx, tmp_path: Path):
    """Every colour image black but the depth kept (a dark room, an infrared depth camera): not bad input. The scan
    takes the depth's keypoints (`features.keypoints: auto`: no image keypoint) and places what its shape pins,
    none wrong (5 deg / 2 cm relative to the others); each frame it leaves says why."""
    from gscan.evaluate.metrics import frame_errors
    from gscan.geometry.transforms import inv_T
    from gscan.io import open_sequence
    from gscan.scanning.api import scan

    dark = tmp_path / "dark_room"
    shutil.copytree(ctx.capture, dark)
    for p in (dark / "rgb").iterdir():
        p.write_bytes(_black_png(INTR))
    res = scan(dark, tmp_path / "dark.gscan")
    assert res.keypoints["source"] == "both" and res.keypoints["median_image_keypoints"] == 0, res.keypoints
    gt = {n: inv_T(T) for n, T in open_sequence(dark).gt_T_cam_obj.items()}
    with TemplateDB.open(tmp_path / "dark.gscan") as db:
        poses = {n: np.asarray(T) for n, T in db.poses()["frames"].items()}
    assert len(poses) >= 2 and not frame_errors(poses, {n: gt[n] for n in poses}).wrong(5.0, 0.02)
    assert set(res.unregistered_reasons) == set(gt) - set(poses)


def test_failed_force_writers_keep_old_outputs_and_name_the_file_size_limit(ctx: Ctx, tmp_path: Path):
    """scan, template-from-mesh, export (a file and a folder) and eval with --force, each stopped by the
    process's file size limit (RLIMIT_FSIZE: the real error a full file system also gives SQLite and Python):
    exit 2, one line naming the output and the limit; the old output as it was, no temporary sibling left."""
    out = tmp_path / "out"
    outs = {"scan": _precious(ctx, out / "scan.gscan"), "mesh": _precious(ctx, out / "mesh.gscan")}
    for name, content in (("x.json", "old"), ("r.csv", "old")):
        outs[name] = out / name
        outs[name].write_text(content)
    colmap = out / "colmap"
    colmap.mkdir()
    (colmap / "mine.txt").write_text("old")
    before = {k: _sha(p) for k, p in {**outs, "colmap": colmap}.items()}
    # eval's numba kernels compiled and cached first (as any earlier estimate does): on a cold cache the first
    # file eval writes under the limit is numba's cache, not the CSV under test
    from gscan.evaluate.bop19 import evaluate

    evaluate(ctx.cad, ctx.capture, tmp_path / "warm.csv", refine=False)
    runs = _parallel(
        lambda: _gscan("scan", ctx.capture, "-o", outs["scan"], "--force", "--json", fsize=1_000_000),
        lambda: _gscan("template-from-mesh", ctx.mesh, "-o", outs["mesh"], "--force", "--views", "4",
                       fsize=200_000),
        lambda: _gscan("export", ctx.template, "--format", "json", "-o", outs["x.json"], "--force", fsize=4_000),
        lambda: _gscan("export", ctx.template, "--format", "colmap", "-o", colmap, "--force", fsize=60_000),
        lambda: _gscan("eval", ctx.cad, ctx.capture, "-o", outs["r.csv"], "--force", "--no-icp", fsize=100),
    )
    for proc, target in zip(runs, [outs["scan"], outs["mesh"], outs["x.json"], colmap, outs["r.csv"]], strict=True):
        line = _error(proc, target.name)
        assert "file size limit" in line and "ulimit -f" in line, line
    assert {k: _sha(p) for k, p in {**outs, "colmap": colmap}.items()} == before
    assert _hidden(out) == []


def test_a_cold_kernel_cache_under_the_file_size_limit_is_named(ctx: Ctx, tmp_path: Path):
    """eval with an empty numba cache (a fresh install) under a file size limit: the first file it writes is
    numba's compiled kernel, which the limit stops (numba writes through a file object: the error names no
    file). One line naming the limit, exit 2, the old output kept (it was "internal error: OSError: [Errno 27]
    File too large", exit 1)."""
    old = tmp_path / "r.csv"
    old.write_text("old")
    proc = _gscan("eval", ctx.cad, ctx.capture, "-o", old, "--force", "--no-icp", fsize=100,
                  env={"NUMBA_CACHE_DIR": str(tmp_path / "numba")})
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "file size limit" in lines[0], proc.stderr
    assert old.read_text() == "old"


def test_disk_full_is_named(ctx: Ctx, tmp_path: Path):
    """ENOSPC met while an export writes (injected at Python's file writes, the exporters' normal path) is
    named "no space left on the device (disk full)", and the old output stays; SQLite's SQLITE_FULL (what it
    reports for ENOSPC) is named the same, not "corrupt template database"."""
    old = tmp_path / "x.json"
    old.write_text("old")
    inject = ("import errno, pathlib, sys\n"
              "def full(self, *a, **k):\n"
              "    raise OSError(errno.ENOSPC, 'No space left on device')\n"
              "pathlib.Path.write_text = pathlib.Path.write_bytes = full\n"
              "sys.argv = ['gscan'] + sys.argv[1:]\n"
              "from gscan.cli import main\nmain()\n")
    proc = subprocess.run([sys.executable, "-c", inject, "export", str(ctx.template), "--format", "json", "-o",
                           str(old), "--force"], capture_output=True, text=True, timeout=TIMEOUT_S, cwd=ROOT,
                          check=False)
    assert "no space left on the device (disk full)" in _error(proc, "x.json")
    assert old.read_text() == "old" and _hidden(tmp_path) == []

    from gscan.errors import InputError
    from gscan.template.db import View

    db = TemplateDB.create(tmp_path / "full.gscan")
    try:
        db._conn.execute("PRAGMA max_page_count=12")  # SQLite reports a full database as on a full disk
        with pytest.raises(InputError, match="no space left on the device"):
            for i in range(50):
                db.add_view(View(f"v{i}", INTR, np.eye(4), np.zeros((240, 320, 3), np.uint8)), color_codec="png")
    finally:
        db.close()


@pytest.mark.slow
def test_concurrent_force_writers_each_succeed_or_say_why(ctx: Ctx, tmp_path: Path):
    """Two `scan --force` onto one existing template, two `export --force` into one folder, two scans onto one
    new output without --force: each run succeeds or is refused with a true message (never "read-only");
    the output ends complete and readable; nothing is left beside it."""
    keep = _precious(ctx, tmp_path / "a" / "obj.gscan")
    folder = tmp_path / "b" / "colmap"
    folder.mkdir(parents=True)
    (folder / "old.txt").write_text("old")
    new = tmp_path / "c" / "new.gscan"
    new.parent.mkdir()
    scans = _parallel(*[lambda: _gscan("scan", ctx.capture, "-o", keep, "--force", "--json")] * 2)
    exports = _parallel(*[lambda: _gscan("export", ctx.template, "--format", "colmap", "-o", folder, "--force")] * 2)
    fresh = _parallel(*[lambda: _gscan("scan", ctx.capture, "-o", new, "--json")] * 2)
    for proc in scans + exports:
        _ok(proc)
    assert [p.returncode for p in fresh].count(0) >= 1
    for proc in fresh:
        if proc.returncode:
            assert "already exists" in _error(proc, "new.gscan")
    for proc in scans + exports + fresh:
        assert "read-only" not in proc.stderr
    for db in (keep, new):
        with TemplateDB.open(db) as t:
            assert t.status == "complete" and len(t.view_names()) == N_VIEWS
        conn = sqlite3.connect(db)
        assert conn.execute("PRAGMA integrity_check").fetchone()[0] == "ok"
        conn.close()
    import pycolmap

    assert pycolmap.Reconstruction(str(folder)).num_images() == N_VIEWS and not (folder / "old.txt").exists()
    for d in (keep.parent, folder.parent, new.parent):
        assert _hidden(d) == []


def test_demo_replaces_only_its_own_template(ctx: Ctx, tmp_path: Path):
    """`gscan demo -o DIR` refuses a DIR/sample.gscan it did not write (a user's template, or any other file):
    exit 2, one line saying so and how to go on, the file unchanged. Its own (marked) template it replaces."""
    from gscan.demo import DEMO_MARK, check_demo_output

    mine = _precious(ctx, tmp_path / "d1" / "sample.gscan")
    other = tmp_path / "d2" / "sample.gscan"
    other.parent.mkdir()
    other.write_text("my notes")
    before = {p: _sha(p) for p in (mine, other)}
    for proc in _parallel(*[lambda p=p: _gscan("demo", "--no-view", "-o", p.parent) for p in (mine, other)]):
        line = _error(proc, "sample.gscan")
        assert "not written by gscan demo" in line and "-o" in line
    assert {p: _sha(p) for p in (mine, other)} == before
    ours = tmp_path / "d3" / "sample.gscan"
    ours.parent.mkdir()
    shutil.copy(ctx.cad, ours)
    with TemplateDB.open(ours, writable=True) as db:
        for k, v in DEMO_MARK.items():
            db.set_meta(k, v)
    assert check_demo_output(ours.parent) == ours  # the demo's own: replaced (test_demo runs the demo itself)


# ------------------------------------------------------------------------------------------ 2. names are data
def _renamed_template(ctx: Ctx, path: Path, names: list[str]) -> Path:
    shutil.copy(ctx.template, path)
    with sqlite3.connect(path) as c:
        old = [r[0] for r in c.execute("SELECT name FROM views ORDER BY input_index")]
        for a, b in zip(old, names, strict=False):  # the first len(names) views are renamed, the others kept
            c.execute("UPDATE views SET name=? WHERE name=?", (b, a))
            c.execute("UPDATE edges SET src=? WHERE src=?", (b, a))
            c.execute("UPDATE edges SET tgt=? WHERE tgt=?", (b, a))
    c.close()
    return path


def test_exports_write_inside_their_output_only(ctx: Ctx, tmp_path: Path):
    """A template whose views are named `../../escaped`, an absolute path, `..`, with an escape sequence:
    `export --format colmap` (the export that names files after views) and the others write only inside
    their output; COLMAP's images get safe, unique names that its model references."""
    escaped = tmp_path / "escaped.png"
    absolute = tmp_path / "abs" / "owned"
    names = ["../../escaped", str(absolute), "..", "a\x1b[2Jb", "000004", "000005"]
    work = tmp_path / "w" / "x"
    work.mkdir(parents=True)
    db = _renamed_template(ctx, work / "t.gscan", names)
    before = set(tmp_path.rglob("*"))
    runs = _parallel(*[lambda f=f: _gscan("export", db, "--format", f, "-o", work / "out" / f)
                       for f in ("colmap", "bop", "foundationpose", "json")])
    for proc in runs:
        _ok(proc)
    after = set(tmp_path.rglob("*")) - before
    assert all(p.is_relative_to(work / "out") for p in after), sorted(map(str, after))
    assert not escaped.exists() and not (absolute.parent / "owned.png").exists()
    import pycolmap

    rec = pycolmap.Reconstruction(str(work / "out" / "colmap"))
    model = sorted(im.name for im in rec.images.values())
    files = sorted(p.name for p in (work / "out" / "colmap" / "images").iterdir())
    assert model == files and len(files) == N_VIEWS and "000004.png" in files and "000005.png" in files
    assert all("/" not in f and "\x1b" not in f and not f.startswith(".") for f in files)


def test_names_are_printed_with_control_characters_escaped(ctx: Ctx, tmp_path: Path):
    """Frame and view names holding terminal escape sequences are printed written out (`\\x1b`): in the scan's
    warning about an unreadable frame, its summary, `poses`, and an error line naming such a file."""
    cap = tmp_path / "cap"
    shutil.copytree(ctx.capture, cap)
    evil = "\x1b[2J\x1b]0;owned\x07x"
    for sub in ("rgb", "depth", "masks", "annotated_poses"):
        for p in (cap / sub).glob("000005.*"):
            p.rename(p.with_name(evil + p.suffix))
    bad = cap / "rgb" / f"{evil}.png"
    bad.write_bytes(bad.read_bytes()[:300])  # unreadable: the scan warns about it and goes on
    tpl = _renamed_template(ctx, tmp_path / "t.gscan", ["000000", evil])
    scan, poses, err = _parallel(
        lambda: _gscan("scan", cap, "-o", tmp_path / "o.gscan"),
        lambda: _gscan("poses", tpl),
        lambda: _gscan("estimate", tpl, "--color", bad, "--depth", cap / "depth" / f"{evil}.png",
                       "--intrinsics", cap / "cam_K.txt"))
    _ok(scan), _ok(poses)
    shown = "\\x1b[2J\\x1b]0;owned\\x07x"
    for proc in (scan, poses, err):
        assert "\x1b" not in proc.stderr and "\x07" not in proc.stderr, proc.stderr
    assert shown in scan.stderr and shown in poses.stderr and shown in _error(err)


# ------------------------------------------------------------------------------------------ 3. bounded memory
def _max_rss(*args: str | Path, env: dict | None = None) -> tuple[subprocess.CompletedProcess, float]:
    """Run the CLI in a child of a fresh interpreter that reports the child's peak RSS (MB)."""
    wrap = ("import resource, subprocess, sys\n"
            "r = subprocess.run(sys.argv[1:], capture_output=True, text=True)\n"
            "sys.stdout.write(r.stdout); sys.stderr.write(r.stderr)\n"
            "sys.stderr.write('MAXRSS %d\\n' % resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)\n"
            "sys.exit(r.returncode)\n")
    proc = subprocess.run([sys.executable, "-c", wrap, *_cli(*args)], capture_output=True, text=True,
                          timeout=TIMEOUT_S, cwd=ROOT, env={**os.environ, **(env or {})}, check=False)
    *rest, last = proc.stderr.rstrip("\n").split("\n")
    assert last.startswith("MAXRSS "), proc.stderr
    return subprocess.CompletedProcess(proc.args, proc.returncode, proc.stdout, "\n".join(rest) + "\n"), \
        int(last.split()[1]) / 1024


def test_image_bombs_are_refused_from_their_header(ctx: Ctx, tmp_path: Path):
    """A 0.4 MB PNG declaring 12000 x 12000 pixels (432 MB decoded) as estimate's colour image, and a capture
    whose frames are such images: refused from the header, exit 2 naming the file and the limit, and the peak
    memory stays that of a run refused before it reads any image (a colour image that does not exist; both are
    refused before the estimator loads), where a decode would add 432 MB."""
    cap = tmp_path / "bombcap"
    for sub in ("rgb", "depth"):
        (cap / sub).mkdir(parents=True)
    shutil.copy(ctx.bomb, cap / "rgb" / "000000.png")
    _png_bomb(cap / "depth" / "000000.png", BOMB_SIDE, BOMB_SIDE, depth16=True)
    s = BOMB_SIDE / INTR.width
    (cap / "cam_K.txt").write_text(f"{INTR.fx * s} 0 {BOMB_SIDE / 2}\n0 {INTR.fy * s} {BOMB_SIDE / 2}\n0 0 1\n")
    q = ctx.capture
    missing, base = _max_rss("estimate", ctx.template, "--color", tmp_path / "missing.png", "--depth",
                             q / "depth" / "000001.png", "--intrinsics", q / "cam_K.txt", "--json")
    _error(missing, "missing.png")
    bomb, rss = _max_rss("estimate", ctx.template, "--color", ctx.bomb, "--depth", q / "depth" / "000001.png",
                         "--intrinsics", q / "cam_K.txt", "--json")
    line = _error(bomb, "color.png")
    assert "12000x12000" in line and "limit" in line and "GSCAN_MAX_IMAGE_PIXELS" in line
    assert rss < base + 150, (rss, base)
    scan, rss = _max_rss("scan", cap, "-o", tmp_path / "o.gscan", "--json")
    assert "12000x12000" in _error(scan, "000000.png") and rss < base + 150, (rss, base)
    assert not (tmp_path / "o.gscan").exists()


def test_stored_image_and_array_bombs_are_refused(ctx: Ctx, tmp_path: Path):
    """A template whose view image is a 12000 x 12000 PNG (with intrinsics to match, or not), and one whose
    keypoint array declares 2^40 rows in a few bytes: exit 2 naming the template (no MemoryError, no exit 1),
    before anything is decoded or allocated."""
    big = tmp_path / "big.gscan"
    shutil.copy(ctx.template, big)
    odd = tmp_path / "odd.gscan"
    shutil.copy(ctx.template, odd)
    arr = tmp_path / "arr.gscan"
    shutil.copy(ctx.template, arr)
    k = json.dumps({"fx": 5000.0, "fy": 5000.0, "cx": 6000.0, "cy": 6000.0, "width": BOMB_SIDE, "height": BOMB_SIDE})
    for db, intr in ((big, k), (odd, None)):
        with sqlite3.connect(db) as c:
            c.execute("UPDATE views SET color=? WHERE input_index=0", (ctx.bomb.read_bytes(),))
            if intr:
                c.execute("UPDATE views SET intrinsics=? WHERE input_index=0", (intr,))
        c.close()
    import io

    buf = io.BytesIO()  # a valid .npy header that declares 2^40 x 2 float32 (8 TB), then 16 bytes of data
    np.lib.format.write_array_header_1_0(buf, {"descr": "<f4", "fortran_order": False, "shape": (2**40, 2)})
    forged = buf.getvalue() + b"\x00" * 16
    with sqlite3.connect(arr) as c:
        c.execute("UPDATE features SET pixels=?", (forged,))
    c.close()
    runs = _parallel(
        lambda: _max_rss("export", big, "--format", "bop", "-o", tmp_path / "bop"),
        lambda: _max_rss("export", odd, "--format", "colmap", "-o", tmp_path / "colmap"),
        lambda: _max_rss("export", arr, "--format", "colmap", "-o", tmp_path / "colmap2"),
        lambda: _max_rss("estimate", arr, "--color", ctx.capture / "rgb" / "000001.png", "--depth",
                         ctx.capture / "depth" / "000001.png", "--intrinsics", ctx.capture / "cam_K.txt"))
    (p_big, r_big), (p_odd, r_odd), (p_arr, r_arr), (p_est, r_est) = runs
    assert "12000x12000" in _error(p_big, "big.gscan") and "limit" in p_big.stderr
    assert "stored image is 12000x12000, expected 320x240" in _error(p_odd, "odd.gscan")
    for p in (p_arr, p_est):
        assert "1099511627776" in _error(p, "arr.gscan")
    assert max(r_big, r_odd, r_arr, r_est) < 1500  # far below a decoded bomb or a 2^40-row array
    for d in ("bop", "colmap", "colmap2"):
        assert not (tmp_path / d).exists()


def test_the_pixel_limit_is_configurable(ctx: Ctx, tmp_path: Path):
    """GSCAN_MAX_IMAGE_PIXELS sets the limit (here below 320 x 240: every frame refused, by name); a value that is
    not a positive number is one error line naming the variable."""
    low, bad = _parallel(
        lambda: _gscan("scan", ctx.capture, "-o", tmp_path / "a.gscan", env={"GSCAN_MAX_IMAGE_PIXELS": "50000"}),
        lambda: _gscan("export", ctx.template, "--format", "json", "-o", tmp_path / "x.json",
                       env={"GSCAN_MAX_IMAGE_PIXELS": "lots"}))
    assert "above the limit of 50000 pixels" in _error(low, "000000.png")
    assert "GSCAN_MAX_IMAGE_PIXELS" in _error(bad, "lots")
    big = _gscan("estimate", ctx.template, "--color", ctx.capture / "rgb" / "000001.png", "--depth",
                 ctx.capture / "depth" / "000001.png", "--intrinsics", ctx.capture / "cam_K.txt", "--json",
                 env={"GSCAN_MAX_IMAGE_PIXELS": str(10**9)})
    assert json.loads(_ok(big).stdout)["T_cam_obj"] is not None  # a higher limit reads as before


# ------------------------------------------------------------------------------------------ 4. resume
@pytest.mark.slow
def test_resume_refuses_frames_that_changed(ctx: Ctx, tmp_path: Path):
    """A partial scan resumed on input frames whose files changed (replaced under the same name, removed, or
    added) is refused on one line naming what changed, the database untouched; the unchanged input resumes."""
    cap = tmp_path / "cap"
    shutil.copytree(ctx.capture, cap)
    db = tmp_path / "partial.gscan"
    _ok(_gscan("scan", cap, "-o", db, "--json"))
    with sqlite3.connect(db) as c:
        c.execute("UPDATE meta SET value='\"partial\"' WHERE key='status'")
    c.close()
    before = _sha(db)
    swapped = (cap / "rgb" / "000002.png").read_bytes()
    (cap / "rgb" / "000002.png").write_bytes((cap / "rgb" / "000003.png").read_bytes())
    line = _error(_gscan("scan", cap, "-o", db, "--resume", "--json"), "partial.gscan", "000002.png")
    assert "not the ones this partial scan was started from" in line and "--force" in line
    (cap / "rgb" / "000002.png").write_bytes(swapped)
    moved = tmp_path / "moved"
    moved.mkdir()
    for sub in ("rgb", "depth", "masks", "annotated_poses"):
        for p in (cap / sub).glob("000005.*"):
            shutil.move(p, moved / f"{sub}{p.suffix}")
    assert "frame 000005 is no longer in the input" in _error(_gscan("scan", cap, "-o", db, "--resume"), "partial")
    assert _sha(db) == before
    for sub in ("rgb", "depth", "masks", "annotated_poses"):
        for p in moved.glob(f"{sub}.*"):
            shutil.move(p, cap / sub / f"000005{p.suffix}")
    added = [cap / sub / f"000099{p.suffix}" for sub in ("rgb", "depth", "masks", "annotated_poses")
             for p in (cap / sub).glob("000005.*")]
    for p in added:
        shutil.copy(p.parent / f"000005{p.suffix}", p)
    assert "frame 000099 was not in the input" in _error(_gscan("scan", cap, "-o", db, "--resume"), "partial")
    assert _sha(db) == before
    for p in added:
        p.unlink()
    out = json.loads(_ok(_gscan("scan", cap, "-o", db, "--resume", "--json")).stdout)
    assert out["registered"] == N_VIEWS


# ------------------------------------------------------------------------------------------ 6. messages
@pytest.mark.slow
def test_bom_intrinsics_exr_depth_and_folders_for_files(ctx: Ctx, tmp_path: Path):
    """A cam_K.txt with a UTF-8 byte-order mark is read; float OpenEXR depth is named as such with the
    conversion to do; a folder given where a file is expected is named as a folder."""
    cap = tmp_path / "bom"
    shutil.copytree(ctx.capture, cap)
    (cap / "cam_K.txt").write_bytes(b"\xef\xbb\xbf" + (ctx.capture / "cam_K.txt").read_bytes())
    exr = tmp_path / "exr"
    shutil.copytree(ctx.capture, exr)
    for p in sorted((exr / "depth").iterdir()):  # an OpenEXR file starts with its magic number
        p.unlink()
        p.with_suffix(".exr").write_bytes(b"\x76\x2f\x31\x01" + b"\x02\x00\x00\x00" + b"\x00" * 64)
    folder = tmp_path / "a_folder"
    folder.mkdir()
    q = ctx.capture
    runs = _parallel(
        lambda: _gscan("scan", cap, "-o", tmp_path / "bom.gscan", "--json"),
        lambda: _gscan("estimate", ctx.template, "--color", q / "rgb" / "000001.png", "--depth",
                       q / "depth" / "000001.png", "--intrinsics", cap / "cam_K.txt", "--json"),
        lambda: _gscan("scan", exr, "-o", tmp_path / "exr.gscan"),
        lambda: _gscan("estimate", ctx.template, "--color", q / "rgb" / "000001.png", "--depth",
                       exr / "depth" / "000001.exr", "--intrinsics", q / "cam_K.txt"),
        lambda: _gscan("scan", ctx.capture, "-o", tmp_path / "k.gscan", "--intrinsics", folder),
        lambda: _gscan("info", folder),
        lambda: _gscan("scan", ctx.capture, "-o", tmp_path / "c.gscan", "--config", folder),
        lambda: _gscan("grasp", "add", ctx.template, "--name", "g", "--pose", folder),
        lambda: _gscan("template-from-mesh", folder, "-o", tmp_path / "m.gscan"),
    )
    assert json.loads(_ok(runs[0]).stdout)["registered"] == N_VIEWS
    assert json.loads(_ok(runs[1]).stdout)["T_cam_obj"] is not None
    for proc in runs[2:4]:
        line = _error(proc, "000001.exr" if proc is runs[3] else ".exr")
        assert "OpenEXR" in line and "16-bit PNG in millimetres" in line
    for proc in runs[4:]:
        assert "a_folder: is a folder" in _error(proc, "a_folder")


def test_intrinsics_file_that_is_a_folder_is_named_a_folder(ctx: Ctx, tmp_path: Path):
    """A capture whose cam_K.txt is a folder: said to be a folder, not "intrinsics file not found"."""
    cap = tmp_path / "cap"
    shutil.copytree(ctx.capture, cap)
    (cap / "cam_K.txt").unlink()
    (cap / "cam_K.txt").mkdir()
    line = _error(_gscan("scan", cap, "-o", tmp_path / "o.gscan"), "cam_K.txt")
    assert "is a folder" in line and "not found" not in line and "--intrinsics" in line, line


def test_links_inside_the_capture_are_named_for_what_they_are(ctx: Ctx, tmp_path: Path):
    """Inside a capture's rgb/ and depth/: a link to itself, links to each other, a folder link named like an
    image. Each frame they spoil is reported by name for what it is (a loop of links, a folder), not as a missing
    depth image or a broken link; the other frames are scanned."""
    cap = tmp_path / "cap"
    shutil.copytree(ctx.capture, cap)
    os.symlink("990.png", cap / "rgb" / "990.png")  # a link to itself
    os.symlink("992.png", cap / "rgb" / "991.png")  # two links to each other
    os.symlink("991.png", cap / "rgb" / "992.png")
    for n in ("990", "991", "992"):
        shutil.copy(cap / "depth" / "000000.png", cap / "depth" / f"{n}.png")
    os.symlink("../rgb", cap / "rgb" / "993.png")  # a folder named like an image
    os.symlink("loop", cap / "depth" / "loop")  # not an image: no frame of its own
    res = json.loads(_ok(_gscan("scan", cap, "-o", tmp_path / "o.gscan", "--json")).stdout)
    why = res["unregistered_reasons"]
    assert res["registered"] == N_VIEWS and sorted(why) == ["990", "991", "992", "993"], why
    for n in ("990", "991", "992"):
        assert f"{n}.png: is a loop of symbolic links" in why[n], why
    assert "993.png: is a folder (a symbolic link to one), not a colour image" in why["993"], why


def _hot_journal(template: Path, path: Path) -> Path:
    """A copy of `template` left by a writer killed mid-transaction: its pages half written, the hot journal
    beside it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    shutil.copy(template, path)
    code = ("import os, sqlite3, sys; c = sqlite3.connect(sys.argv[1], isolation_level=None); "
            "c.execute('PRAGMA cache_size=1'); c.execute('BEGIN IMMEDIATE'); c.execute('CREATE TABLE zz(x)'); "
            "[c.execute('INSERT INTO zz VALUES (randomblob(5000))') for _ in range(200)]; os._exit(0)")
    subprocess.run([sys.executable, "-c", code, str(path)], check=True, timeout=TIMEOUT_S)
    assert Path(f"{path}-journal").is_file()
    return path


@pytest.mark.parametrize("file_mode", [0o644, 0o444])
def test_a_journal_in_a_read_only_folder_is_not_called_corruption(ctx: Ctx, tmp_path: Path, file_mode: int):
    """`gscan info` of a sound template whose writer left a journal, in a read-only folder: said to be held by
    the journal and the read-only folder, not corrupt (SQLite's "disk I/O error" / "attempt to write a
    readonly database")."""
    db = _hot_journal(ctx.cad, tmp_path / "ro" / "t.gscan")
    db.chmod(file_mode)
    db.parent.chmod(0o555)
    try:
        line = _error(_gscan("info", db, unreadable=True), "t.gscan")
    finally:
        db.parent.chmod(0o755)
    assert "read-only" in line and "t.gscan-journal" in line and "not corrupt" in line, line
    assert "corrupt or unreadable" not in line, line
    _ok(_gscan("info", db))  # where it can be written, the journal is rolled back: the template reads


@pytest.mark.slow
def test_long_output_names(ctx: Ctx, tmp_path: Path):
    """Legal 250-character output names work for every writer (the temporary sibling and SQLite's journal keep
    within NAME_MAX), and a scan into one can be continued with --force and --resume."""
    stem = "n" * (LONG - len(".gscan"))
    out = tmp_path / "long"
    out.mkdir()
    runs = _parallel(
        lambda: _gscan("scan", ctx.capture, "-o", out / f"{stem}.gscan", "--json"),
        lambda: _gscan("template-from-mesh", ctx.mesh, "-o", out / f"{'m' * (LONG - 6)}.gscan", "--views", "4"),
        lambda: _gscan("export", ctx.template, "--format", "json", "-o", out / f"{'j' * (LONG - 5)}.json"),
        lambda: _gscan("export", ctx.template, "--format", "colmap", "-o", out / ("c" * LONG)),
        lambda: _gscan("eval", ctx.cad, ctx.capture, "-o", out / f"{'e' * (LONG - 4)}.csv", "--no-icp"),
    )
    for proc in runs:
        _ok(proc)
    names = sorted(p.name for p in out.iterdir())
    assert len(names) == 5 and all(len(n) == LONG for n in names), names
    _ok(_gscan("scan", ctx.capture, "-o", out / f"{stem}.gscan", "--force"))
    _ok(_gscan("scan", ctx.capture, "-o", out / f"{stem}.gscan", "--resume"))
    with TemplateDB.open(out / f"{stem}.gscan") as db:
        assert db.status == "complete"
    assert _hidden(out) == []


def test_unreadable_optional_ground_truth_is_reported_and_skipped(ctx: Ctx, tmp_path: Path):
    """An annotated pose the scan does not use that cannot be read (no permission; garbage) is named in a
    warning and the scan goes on; eval, which scores against it, refuses it by name."""
    cap = tmp_path / "cap"
    shutil.copytree(ctx.capture, cap)
    (cap / "annotated_poses" / "000003.txt").chmod(0)
    (cap / "annotated_poses" / "000004.txt").write_bytes(b"\xff\xfe garbage")
    scan = _ok(_gscan("scan", cap, "-o", tmp_path / "o.gscan", "--json", unreadable=True))
    assert json.loads(scan.stdout)["registered"] == N_VIEWS
    warnings = [ln for ln in scan.stderr.splitlines() if "ground truth left out" in ln]
    assert len(warnings) == 2 and "000003.txt" in warnings[0] + warnings[1] and "000004.txt" in "".join(warnings)
    assert "permission denied" in "".join(warnings)
    ev = _gscan("eval", ctx.cad, cap, "-o", tmp_path / "r.csv", "--no-icp")
    assert "unreadable ground truth" in _error(ev, "000004.txt")
    assert not (tmp_path / "r.csv").exists()
