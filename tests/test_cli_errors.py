"""Bad input through the real command line (GitHub issue 7; README, "Command line").

The contract: bad input exits with code 2 and one line on stderr, `error: ...`, naming the
offending file; never a traceback; never a half-written output. A capture in which only some
frames are unusable is not bad input: those frames are reported by name and the scan goes on.

Every case is built in its own folder and all cases run as concurrent subprocesses in one
module fixture (each is dominated by interpreter start-up); the parametrised tests then check
one result each. The output of a failing command goes into an empty folder `out/` that must
still be empty afterwards (no output, no journal, no temporary sibling left behind).
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import sqlite3
import subprocess
import sys
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import pytest

from gscan import synth

ROOT = Path(__file__).resolve().parents[1]
INTR = synth.DEFAULT_INTRINSICS.scaled(0.5)  # 320 x 240: small and fast, still registers
N_VIEWS = 8  # 45 degree steps on one ring
TIMEOUT_S = 240
# lines libpng / libjpeg print on stderr themselves while OpenCV decodes a corrupt file (OpenCV's own
# log is silenced by the CLI)
LIBRARY_NOISE = ("libpng", "corrupt jpeg", "premature end", "warning:")


# ------------------------------------------------------------------------------------------ fixtures


@dataclass
class Ctx:
    """Shared, read-only inputs the cases copy from."""

    capture: Path  # a good capture (rgb/ depth/ masks/ cam_K.txt annotated_poses/)
    template: Path  # a complete template database
    mesh: Path  # the box as a textured OBJ


@dataclass
class Run:
    """One command to run and what it must leave behind."""

    argv: list[str]
    names: list[str]  # strings the error line must contain (file names, option values)
    out_dir: Path | None = None  # must exist and be empty afterwards
    unchanged: list[Path] = field(default_factory=list)  # files / folders whose content must not change
    unreadable: bool = False  # run without root's right to read any file (setpriv)
    expect_rc: int = 2


def _cli(*args: str | Path) -> list[str]:
    return [sys.executable, "-m", "gscan.cli", *map(str, args)]


def _snapshot(p: Path) -> dict[str, str]:
    if p.is_file():
        return {"": hashlib.sha256(p.read_bytes()).hexdigest()}
    if not p.exists():
        return {}
    return {str(f.relative_to(p)): (hashlib.sha256(f.read_bytes()).hexdigest() if f.is_file() else "dir")
            for f in sorted(p.rglob("*"))}


def _copy_capture(ctx: Ctx, work: Path, name: str = "cap") -> Path:
    dst = work / name
    shutil.copytree(ctx.capture, dst)
    return dst


def _for_each(folder: Path, pattern: str, fn: Callable[[Path], None]) -> list[Path]:
    files = sorted(folder.glob(pattern))
    assert files, f"no {pattern} under {folder}"
    for f in files:
        fn(f)
    return files


def _rewrite_depth(fn: Callable[[np.ndarray], np.ndarray], ext: str = ".png") -> Callable[[Path], None]:
    def apply(p: Path) -> None:
        d = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        p.unlink()
        assert cv2.imwrite(str(p.with_suffix(ext)), fn(d))
    return apply


def _scan_case(work: Path, cap: Path, *names: str, extra: tuple[str, ...] = ()) -> Run:
    out = work / "out"
    out.mkdir(exist_ok=True)
    return Run(_cli("scan", cap, "-o", out / "obj.gscan", "--json", *extra), list(names), out_dir=out)


def _template_copy(ctx: Ctx, work: Path, name: str = "obj.gscan", **meta: object) -> Path:
    dst = work / name
    shutil.copy(ctx.template, dst)
    if meta:
        with sqlite3.connect(dst) as c:
            for k, v in meta.items():
                c.execute("UPDATE meta SET value=? WHERE key=?", (json.dumps(v), k))
    return dst


def _query_files(ctx: Ctx, work: Path) -> tuple[Path, Path, Path]:
    q = work / "query"
    q.mkdir()
    for sub, ext in (("rgb", ".png"), ("depth", ".png")):
        shutil.copy(ctx.capture / sub / f"000002{ext}", q / f"{sub}.png")
    shutil.copy(ctx.capture / "cam_K.txt", q / "cam_K.txt")
    return q / "rgb.png", q / "depth.png", q / "cam_K.txt"


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _template_command(cmd: str, db: Path, ctx: Ctx, work: Path) -> Run:
    """`cmd` run on template `db`; commands that write get an empty out/ folder to keep empty."""
    out = work / "out"
    out.mkdir(exist_ok=True)
    if cmd == "estimate":
        c, d, k = _query_files(ctx, work)
        return Run(_cli("estimate", db, "--color", c, "--depth", d, "--intrinsics", k, "--json"), [db.name], out)
    if cmd == "export":
        return Run(_cli("export", db, "--format", "json", "-o", out / "x.json"), [db.name], out)
    if cmd == "view":
        return Run(_cli("view", db, "--port", str(_free_port())), [db.name], out)
    if cmd in ("info", "poses"):
        return Run(_cli(cmd, db, "--json"), [db.name], out)
    raise ValueError(cmd)


# ------------------------------------------------------------------------------------------ the corpus

CASES: dict[str, Callable[[Ctx, Path], Run]] = {}


def case(name: str):
    def deco(fn: Callable[[Ctx, Path], Run]) -> Callable[[Ctx, Path], Run]:
        assert name not in CASES
        CASES[name] = fn
        return fn
    return deco


@case("scan-empty-folder")
def _(ctx: Ctx, work: Path) -> Run:
    (work / "empty capture").mkdir()
    return _scan_case(work, work / "empty capture", "empty capture")


@case("scan-empty-folder-without-json")  # the progress display is on: it must not leave a blank line first
def _(ctx: Ctx, work: Path) -> Run:
    (work / "empty capture").mkdir()
    out = work / "out"
    out.mkdir()
    return Run(_cli("scan", work / "empty capture", "-o", out / "obj.gscan"), ["empty capture"], out_dir=out)


@case("scan-missing-folder")
def _(ctx: Ctx, work: Path) -> Run:
    return _scan_case(work, work / "no_such_capture", "no_such_capture")


@case("scan-unrecognised-layout")
def _(ctx: Ctx, work: Path) -> Run:
    cap = work / "holiday_photos"
    (cap / "pictures").mkdir(parents=True)
    (cap / "notes.txt").write_text("not a capture\n")
    shutil.copy(ctx.capture / "rgb" / "000000.png", cap / "pictures" / "a.png")
    return _scan_case(work, cap, "holiday_photos")


@case("scan-no-depth-for-any-frame")
def _(ctx: Ctx, work: Path) -> Run:
    cap = _copy_capture(ctx, work, "nodepth")
    _for_each(cap / "depth", "*.png", Path.unlink)
    return _scan_case(work, cap, "nodepth", "000000")


@case("scan-size-mismatch-all-frames")
def _(ctx: Ctx, work: Path) -> Run:
    cap = _copy_capture(ctx, work, "mismatch")
    _for_each(cap / "depth", "*.png",
              _rewrite_depth(lambda d: cv2.resize(d, (160, 120), interpolation=cv2.INTER_NEAREST)))
    return _scan_case(work, cap, "mismatch", "000000")


@case("scan-depth-to-color-without-depth-intrinsics")
def _(ctx: Ctx, work: Path) -> Run:
    cap = _copy_capture(ctx, work)
    np.savetxt(work / "T_color_depth.txt", np.eye(4))
    return _scan_case(work, cap, "T_color_depth.txt", "--depth-intrinsics",
                      extra=("--depth-to-color", str(work / "T_color_depth.txt")))


@case("scan-depth-intrinsics-for-the-wrong-size")  # every frame's depth is 320x240, the depth camera's 640x480
def _(ctx: Ctx, work: Path) -> Run:
    cap = _copy_capture(ctx, work)
    (work / "depth_K.json").write_text(json.dumps({"fx": 500.0, "fy": 500.0, "cx": 319.5, "cy": 239.5,
                                                   "width": 640, "height": 480}))
    return _scan_case(work, cap, "depth_K.json", "640x480", "320x240",
                      extra=("--depth-intrinsics", str(work / "depth_K.json")))


@case("scan-not-rigid-depth-to-color")
def _(ctx: Ctx, work: Path) -> Run:
    cap = _copy_capture(ctx, work)
    np.savetxt(work / "depth_K.txt", np.loadtxt(cap / "cam_K.txt"))
    np.savetxt(work / "skewed.txt", np.diag([1.0, 2.0, 1.0, 1.0]))
    return _scan_case(work, cap, "skewed.txt", extra=("--depth-intrinsics", str(work / "depth_K.txt"),
                                                      "--depth-to-color", str(work / "skewed.txt")))


@case("scan-8bit-depth")
def _(ctx: Ctx, work: Path) -> Run:
    cap = _copy_capture(ctx, work, "depth8")
    _for_each(cap / "depth", "*.png", _rewrite_depth(lambda d: (d // 8).clip(0, 255).astype(np.uint8)))
    return _scan_case(work, cap, "depth8", "000000")


@case("scan-float-depth-tiff")
def _(ctx: Ctx, work: Path) -> Run:
    cap = _copy_capture(ctx, work, "depthf")
    _for_each(cap / "depth", "*.png", _rewrite_depth(lambda d: d.astype(np.float32) / 1000.0, ".tiff"))
    return _scan_case(work, cap, "depthf", "000000.tiff")


@case("scan-float-depth-32bit-png-rgba")
def _(ctx: Ctx, work: Path) -> Run:
    # float32 metres smuggled into an 8-bit RGBA PNG (4 bytes per pixel): a 4-channel "depth"
    cap = _copy_capture(ctx, work, "depthrgba")
    _for_each(cap / "depth", "*.png", _rewrite_depth(
        lambda d: (d.astype(np.float32) / 1000.0).view(np.uint8).reshape(d.shape[0], d.shape[1], 4)))
    return _scan_case(work, cap, "depthrgba", "000000.png")


@case("scan-all-zero-depth")
def _(ctx: Ctx, work: Path) -> Run:
    cap = _copy_capture(ctx, work, "zerodepth")
    _for_each(cap / "depth", "*.png", _rewrite_depth(np.zeros_like))
    return _scan_case(work, cap, "zerodepth", "000000.png")


@case("scan-corrupt-png")
def _(ctx: Ctx, work: Path) -> Run:
    cap = _copy_capture(ctx, work, "corruptpng")
    rng = np.random.default_rng(1)

    def corrupt(p: Path) -> None:  # PNG signature and IHDR kept, image data garbled
        b = bytearray(p.read_bytes())
        b[60:] = rng.integers(0, 256, len(b) - 60, dtype=np.uint8).tobytes()
        p.write_bytes(bytes(b))
    _for_each(cap / "rgb", "*.png", corrupt)
    return _scan_case(work, cap, "corruptpng", "000000.png")


@case("scan-corrupt-jpeg")
def _(ctx: Ctx, work: Path) -> Run:
    cap = _copy_capture(ctx, work, "corruptjpg")
    rng = np.random.default_rng(2)

    def to_bad_jpeg(p: Path) -> None:  # JPEG start-of-image marker, then garbage
        p.unlink()
        p.with_suffix(".jpg").write_bytes(b"\xff\xd8\xff\xe0" + rng.integers(0, 256, 4000, dtype=np.uint8).tobytes())
    _for_each(cap / "rgb", "*.png", to_bad_jpeg)
    return _scan_case(work, cap, "corruptjpg", "000000.jpg")


@case("scan-truncated-png")
def _(ctx: Ctx, work: Path) -> Run:
    cap = _copy_capture(ctx, work, "truncpng")
    _for_each(cap / "rgb", "*.png", lambda p: p.write_bytes(p.read_bytes()[: p.stat().st_size // 2]))
    return _scan_case(work, cap, "truncpng", "000000.png")


@case("scan-tum-malformed-list")
def _(ctx: Ctx, work: Path) -> Run:
    cap = work / "tum"
    for sub in ("rgb", "depth"):
        (cap / sub).mkdir(parents=True)
        shutil.copy(ctx.capture / sub / "000000.png", cap / sub / "1.0.png")
    (cap / "rgb.txt").write_text("# timestamp filename\nyesterday rgb/1.0.png\n")
    (cap / "depth.txt").write_text("# timestamp filename\n1.0 depth/1.0.png\n")
    return _scan_case(work, cap, "rgb.txt")


@case("scan-bop-malformed-scene-camera")
def _(ctx: Ctx, work: Path) -> Run:
    cap = work / "bop_scene"
    for sub in ("rgb", "depth"):
        (cap / sub).mkdir(parents=True)
        shutil.copy(ctx.capture / sub / "000000.png", cap / sub / "000000.png")
    (cap / "scene_camera.json").write_text('{"0": {"cam_K": [1, 0')
    return _scan_case(work, cap, "scene_camera.json")


@case("scan-masks-wrong-size")
def _(ctx: Ctx, work: Path) -> Run:
    cap = _copy_capture(ctx, work, "badmasks")
    _for_each(cap / "masks", "*.png", lambda p: cv2.imwrite(str(p), np.zeros((10, 10), np.uint8)))
    return _scan_case(work, cap, "badmasks", "000000.png")


@case("scan-missing-cam-K")
def _(ctx: Ctx, work: Path) -> Run:
    cap = _copy_capture(ctx, work)
    (cap / "cam_K.txt").unlink()
    return _scan_case(work, cap, "cam_K.txt")


@case("scan-malformed-cam-K")
def _(ctx: Ctx, work: Path) -> Run:
    cap = _copy_capture(ctx, work)
    (cap / "cam_K.txt").write_text("focal length: about 600\n")
    return _scan_case(work, cap, "cam_K.txt")


@case("scan-nan-intrinsics")
def _(ctx: Ctx, work: Path) -> Run:
    cap = _copy_capture(ctx, work)
    (cap / "cam_K.txt").write_text("nan 0 160\n0 307.5 120\n0 0 1\n")
    return _scan_case(work, cap, "cam_K.txt")


@case("scan-negative-focal-length")
def _(ctx: Ctx, work: Path) -> Run:
    cap = _copy_capture(ctx, work)
    (cap / "cam_K.txt").write_text("-307.5 0 160\n0 307.5 120\n0 0 1\n")
    return _scan_case(work, cap, "cam_K.txt")


@case("scan-missing-intrinsics-option-file")
def _(ctx: Ctx, work: Path) -> Run:
    cap = _copy_capture(ctx, work)
    return _scan_case(work, cap, "other_K.txt", extra=("--intrinsics", str(work / "other_K.txt")))


@case("scan-depth-scale-kilometres")
def _(ctx: Ctx, work: Path) -> Run:
    cap = _copy_capture(ctx, work)
    return _scan_case(work, cap, "000000.png", extra=("--depth-scale", "10"))


@case("scan-depth-beyond-fusion-range")
def _(ctx: Ctx, work: Path) -> Run:
    # a plausible scene depth (8 m) that registers, but lies beyond a configured fusion.depth_max: nothing to fuse
    # (the default range follows the capture's depth)
    (work / "near.yaml").write_text("fusion:\n  depth_max: 2.0\n")
    cap = work / "far"
    for sub in ("rgb", "depth"):
        (cap / sub).mkdir(parents=True)
        for k in range(3):
            shutil.copy(ctx.capture / sub / f"00000{k}.png", cap / sub / f"00000{k}.png")
    shutil.copy(ctx.capture / "cam_K.txt", cap / "cam_K.txt")
    out = work / "out"
    out.mkdir()
    return Run(_cli("scan", cap, "-o", out / "deeper" / "obj.gscan", "--depth-scale", "0.02", "--json", "--config",
                    work / "near.yaml"),
               ["far", "depth_max"], out_dir=out)


@case("scan-invalid-depth-scale")
def _(ctx: Ctx, work: Path) -> Run:
    cap = _copy_capture(ctx, work, "negscale")
    return _scan_case(work, cap, "negscale", "-0.001", extra=("--depth-scale", "-0.001"))


# --roi / --mask: the object in the first frame (320 x 240 here)
@case("scan-roi-outside-the-image")
def _(ctx: Ctx, work: Path) -> Run:
    return _scan_case(work, ctx.capture, "--roi", "320 x 240", extra=("--roi", "300,200,50,50"))


@case("scan-roi-not-four-numbers")
def _(ctx: Ctx, work: Path) -> Run:
    return _scan_case(work, ctx.capture, "--roi", "1,2,3", extra=("--roi", "1,2,3"))


@case("scan-mask-empty")
def _(ctx: Ctx, work: Path) -> Run:
    assert cv2.imwrite(str(work / "empty_mask.png"), np.zeros((INTR.height, INTR.width), np.uint8))
    return _scan_case(work, ctx.capture, "--mask", "empty_mask.png", "empty",
                      extra=("--mask", str(work / "empty_mask.png")))


@case("scan-mask-of-another-size")
def _(ctx: Ctx, work: Path) -> Run:
    assert cv2.imwrite(str(work / "big_mask.png"), np.full((2 * INTR.height, 2 * INTR.width), 255, np.uint8))
    return _scan_case(work, ctx.capture, "--mask", "big_mask.png", f"{2 * INTR.width} x {2 * INTR.height}",
                      extra=("--mask", str(work / "big_mask.png")))


@case("scan-roi-and-mask")
def _(ctx: Ctx, work: Path) -> Run:
    assert cv2.imwrite(str(work / "m.png"), np.full((INTR.height, INTR.width), 255, np.uint8))
    return _scan_case(work, ctx.capture, "--roi", "--mask", extra=("--roi", "0,0,10,10", "--mask", str(work / "m.png")))


@case("scan-duplicate-frame-names")
def _(ctx: Ctx, work: Path) -> Run:
    cap = _copy_capture(ctx, work)
    img = cv2.imread(str(cap / "rgb" / "000001.png"))
    assert cv2.imwrite(str(cap / "rgb" / "000001.jpg"), img)
    return _scan_case(work, cap, "000001")


@case("scan-unreadable-permissions")
def _(ctx: Ctx, work: Path) -> Run:
    cap = _copy_capture(ctx, work, "locked")
    _for_each(cap / "depth", "*.png", lambda p: p.chmod(0))
    run = _scan_case(work, cap, "locked", "000000.png", "permission denied")
    run.unreadable = True
    return run


@case("scan-output-exists")
def _(ctx: Ctx, work: Path) -> Run:
    cap = _copy_capture(ctx, work)
    existing = work / "keep.gscan"
    existing.write_bytes(b"precious")
    return Run(_cli("scan", cap, "-o", existing, "--json"), ["keep.gscan", "--force"], unchanged=[existing])


@case("scan-output-is-folder")
def _(ctx: Ctx, work: Path) -> Run:
    cap = _copy_capture(ctx, work)
    (work / "dir.gscan").mkdir()
    return Run(_cli("scan", cap, "-o", work / "dir.gscan", "--force", "--json"), ["dir.gscan"],
               unchanged=[work / "dir.gscan"])


@case("scan-resume-and-force")
def _(ctx: Ctx, work: Path) -> Run:
    cap = _copy_capture(ctx, work)
    run = _scan_case(work, cap, "obj.gscan", "--resume", "--force")
    run.argv += ["--resume", "--force"]
    return run


@case("scan-invalid-format")
def _(ctx: Ctx, work: Path) -> Run:
    cap = _copy_capture(ctx, work)
    return _scan_case(work, cap, "'kinect'", extra=("--format", "kinect"))


@case("scan-wrong-format")
def _(ctx: Ctx, work: Path) -> Run:
    cap = _copy_capture(ctx, work, "capfolder")
    return _scan_case(work, cap, "capfolder", extra=("--format", "tum"))


@case("scan-config-malformed-yaml")
def _(ctx: Ctx, work: Path) -> Run:
    cap = _copy_capture(ctx, work)
    (work / "bad.yaml").write_text("features: [kind: sift\n  max_keypoints: {\n")
    return _scan_case(work, cap, "bad.yaml", extra=("--config", str(work / "bad.yaml")))


@case("scan-config-unknown-key")
def _(ctx: Ctx, work: Path) -> Run:
    cap = _copy_capture(ctx, work)
    (work / "unknown.yaml").write_text("features:\n  kind: sift\n  max_keypointz: 500\n")
    return _scan_case(work, cap, "unknown.yaml", "max_keypointz", extra=("--config", str(work / "unknown.yaml")))


@case("scan-config-invalid-value")
def _(ctx: Ctx, work: Path) -> Run:
    cap = _copy_capture(ctx, work)
    (work / "invalid.yaml").write_text("match:\n  eps_c: -3\n")
    return _scan_case(work, cap, "invalid.yaml", "eps_c", extra=("--config", str(work / "invalid.yaml")))


@case("scan-config-missing-file")
def _(ctx: Ctx, work: Path) -> Run:
    cap = _copy_capture(ctx, work)
    return _scan_case(work, cap, "nothere.yaml", extra=("--config", str(work / "nothere.yaml")))


def _random_bytes_file(work: Path) -> Path:
    p = work / "random.gscan"
    p.write_bytes(np.random.default_rng(3).integers(0, 256, 5000, dtype=np.uint8).tobytes())
    return p


def _foreign_sqlite_file(work: Path) -> Path:
    p = work / "foreign.gscan"
    with sqlite3.connect(p) as c:
        c.execute("CREATE TABLE songs(title TEXT, artist TEXT)")
        c.execute("INSERT INTO songs VALUES ('a', 'b')")
    c.close()
    return p


for _cmd in ("estimate", "info", "export", "view", "poses"):
    case(f"{_cmd}-random-bytes")(lambda ctx, work, c=_cmd: _template_command(c, _random_bytes_file(work), ctx, work))
    case(f"{_cmd}-sqlite-of-another-app")(
        lambda ctx, work, c=_cmd: _template_command(c, _foreign_sqlite_file(work), ctx, work))

for _cmd in ("info", "estimate"):
    case(f"{_cmd}-newer-schema")(
        lambda ctx, work, c=_cmd: _template_command(c, _template_copy(ctx, work, "future.gscan", schema=99), ctx, work))

for _cmd in ("estimate", "export", "view", "poses"):
    def _partial(ctx: Ctx, work: Path, c: str = _cmd) -> Run:
        run = _template_command(c, _template_copy(ctx, work, "half.gscan", status="partial"), ctx, work)
        run.names.append("--resume")
        return run
    case(f"{_cmd}-partial-template")(_partial)


def _corrupt_views_table(ctx: Ctx, work: Path) -> Path:
    """A template whose meta table is intact (it opens) but whose views table's root page is garbage."""
    db = _template_copy(ctx, work, "damaged.gscan")
    with sqlite3.connect(db) as c:
        page = c.execute("PRAGMA page_size").fetchone()[0]
        root = c.execute("SELECT rootpage FROM sqlite_master WHERE name='views'").fetchone()[0]
    c.close()
    with open(db, "r+b") as f:
        f.seek((root - 1) * page)
        f.write(np.random.default_rng(4).integers(0, 256, page, dtype=np.uint8).tobytes())
    return db


def _garbled_blobs(ctx: Ctx, work: Path) -> Path:
    """A template whose pages are sound but whose stored arrays and images do not decode (one byte of each
    blob's header flipped, as a bit flip on disk would): poses, keypoints, mesh vertices, colour images."""
    db = _template_copy(ctx, work, "garbled.gscan")
    with sqlite3.connect(db) as c:
        for table, col in (("views", "T_obj_cam"), ("views", "color"), ("features", "points"), ("mesh", "vertices")):
            for rowid, blob in c.execute(f"SELECT rowid, {col} FROM {table} WHERE {col} IS NOT NULL").fetchall():
                b = bytearray(blob)
                b[1] ^= 0x40
                c.execute(f"UPDATE {table} SET {col}=? WHERE rowid=?", (bytes(b), rowid))
    c.close()
    return db


for _cmd in ("info", "estimate", "export", "poses", "view"):
    case(f"{_cmd}-garbled-blobs")(lambda ctx, work, c=_cmd: _template_command(c, _garbled_blobs(ctx, work), ctx, work))

for _cmd in ("info", "estimate", "export", "poses"):
    case(f"{_cmd}-damaged-pages")(
        lambda ctx, work, c=_cmd: _template_command(c, _corrupt_views_table(ctx, work), ctx, work))


@case("estimate-missing-template")
def _(ctx: Ctx, work: Path) -> Run:
    return _template_command("estimate", work / "ghost.gscan", ctx, work)


@case("export-non-empty-folder")
def _(ctx: Ctx, work: Path) -> Run:
    out = work / "bop_out"
    out.mkdir()
    (out / "mine.txt").write_text("do not delete\n")
    return Run(_cli("export", ctx.template, "--format", "bop", "-o", out), ["bop_out", "--force"], unchanged=[out])


@case("export-invalid-format")
def _(ctx: Ctx, work: Path) -> Run:
    out = work / "out"
    out.mkdir()
    return Run(_cli("export", ctx.template, "--format", "stl", "-o", out / "x.stl"), ["'stl'"], out)


@case("export-into-missing-parent-of-bad-template")
def _(ctx: Ctx, work: Path) -> Run:
    out = work / "out"
    out.mkdir()
    db = _random_bytes_file(work)
    return Run(_cli("export", db, "--format", "bop", "-o", out / "deeper" / "bop"), [db.name], out)


@case("export-mesh-of-meshless-template")
def _(ctx: Ctx, work: Path) -> Run:
    out = work / "out"
    out.mkdir()
    db = _template_copy(ctx, work, "meshless.gscan")
    with sqlite3.connect(db) as c:
        c.execute("DELETE FROM mesh")
    c.close()
    return Run(_cli("export", db, "--format", "obj", "-o", out / "deeper" / "m.obj"), [db.name, "mesh"], out)


def _estimate(ctx: Ctx, work: Path, color: Path, depth: Path, K: Path, *extra: str | Path) -> Run:
    out = work / "out"
    out.mkdir(exist_ok=True)
    return Run(_cli("estimate", ctx.template, "--color", color, "--depth", depth, "--intrinsics", K, "--json",
                    *extra), [], out)


@case("estimate-missing-color")
def _(ctx: Ctx, work: Path) -> Run:
    c, d, k = _query_files(ctx, work)
    run = _estimate(ctx, work, work / "missing_color.png", d, k)
    run.names.append("missing_color.png")
    return run


@case("estimate-depth-intrinsics-unreadable")
def _(ctx: Ctx, work: Path) -> Run:
    c, d, k = _query_files(ctx, work)
    (work / "depth_K.txt").write_text("not a matrix\n")
    run = _estimate(ctx, work, c, d, k)
    run.argv += ["--depth-intrinsics", str(work / "depth_K.txt")]
    run.names.append("depth_K.txt")
    return run


@case("estimate-corrupt-depth")
def _(ctx: Ctx, work: Path) -> Run:
    c, d, k = _query_files(ctx, work)
    d.write_bytes(d.read_bytes()[:200])
    run = _estimate(ctx, work, c, d, k)
    run.names.append(d.name)
    return run


@case("estimate-8bit-depth")
def _(ctx: Ctx, work: Path) -> Run:
    c, d, k = _query_files(ctx, work)
    _rewrite_depth(lambda x: (x // 8).clip(0, 255).astype(np.uint8))(d)
    run = _estimate(ctx, work, c, d, k)
    run.names += [d.name, "8-bit"]
    return run


@case("estimate-size-mismatch")
def _(ctx: Ctx, work: Path) -> Run:
    c, d, k = _query_files(ctx, work)
    _rewrite_depth(lambda x: cv2.resize(x, (160, 120), interpolation=cv2.INTER_NEAREST))(d)
    run = _estimate(ctx, work, c, d, k)
    run.names.append(d.name)
    return run


@case("estimate-mask-wrong-size")
def _(ctx: Ctx, work: Path) -> Run:
    c, d, k = _query_files(ctx, work)
    m = work / "query" / "small_mask.png"
    assert cv2.imwrite(str(m), np.full((100, 100), 255, np.uint8))
    run = _estimate(ctx, work, c, d, k, "--mask", m)
    run.names.append(m.name)
    return run


@case("estimate-malformed-intrinsics")
def _(ctx: Ctx, work: Path) -> Run:
    c, d, k = _query_files(ctx, work)
    k.write_text("1 2 3\n")
    run = _estimate(ctx, work, c, d, k)
    run.names.append(k.name)
    return run


@case("estimate-depth-scale-kilometres")
def _(ctx: Ctx, work: Path) -> Run:
    c, d, k = _query_files(ctx, work)
    run = _estimate(ctx, work, c, d, k, "--depth-scale", "10")
    run.names.append(d.name)
    return run


def _grasp(ctx: Ctx, work: Path, content: str) -> Run:
    db = _template_copy(ctx, work)
    pose = work / "grasp_pose.json"
    pose.write_text(content)
    return Run(_cli("grasp", "add", db, "--name", "top", "--pose", pose), ["grasp_pose.json"], unchanged=[db])


@case("grasp-add-malformed-pose")
def _(ctx: Ctx, work: Path) -> Run:
    return _grasp(ctx, work, '{"T": [[1, 0, 0, 0], [0, 1, 0')


@case("grasp-add-not-a-matrix")
def _(ctx: Ctx, work: Path) -> Run:
    return _grasp(ctx, work, '{"T": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}')


@case("grasp-add-non-rigid")
def _(ctx: Ctx, work: Path) -> Run:
    return _grasp(ctx, work, json.dumps({"T": [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.1], [0, 0, 0, 1]]}))


@case("grasp-add-translation-beyond-10-km")
def _(ctx: Ctx, work: Path) -> Run:
    return _grasp(ctx, work, json.dumps({"T": [[1, 0, 0, 1.7e308], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}))


@case("grasp-add-integer-beyond-float")
def _(ctx: Ctx, work: Path) -> Run:
    return _grasp(ctx, work, '{"T": [[' + "1" + "0" * 400 + ', 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}')


@case("grasp-add-deeply-nested-json")
def _(ctx: Ctx, work: Path) -> Run:
    return _grasp(ctx, work, "[" * 100_000 + "]" * 100_000)


@case("grasp-add-name-with-newline")
def _(ctx: Ctx, work: Path) -> Run:
    db = _template_copy(ctx, work)
    pose = work / "grasp_pose.json"
    pose.write_text(json.dumps(np.eye(4).tolist()))
    return Run(_cli("grasp", "add", db, "--name", "top\nbottom", "--pose", pose), [db.name, "printable"],
               unchanged=[db])


@case("view-port-out-of-range")
def _(ctx: Ctx, work: Path) -> Run:
    return Run(_cli("view", ctx.template, "--port", "70000"), ["--port"])


@case("view-estimate-of-another-template")
def _(ctx: Ctx, work: Path) -> Run:
    result = work / "all.json"
    result.write_text(json.dumps({"templates": [{"template": "a", "instances": []},
                                                {"template": "b", "instances": []}]}))
    return Run(_cli("view", ctx.template, "--port", str(_free_port()), "--estimate", result),
               ["all.json", f"no result of template {ctx.template.stem}"])


@case("view-estimate-not-a-result")
def _(ctx: Ctx, work: Path) -> Run:
    result = work / "pose.json"
    result.write_text(json.dumps({"T": np.eye(4).tolist()}))
    return Run(_cli("view", ctx.template, "--port", str(_free_port()), "--estimate", result),
               ["pose.json", "not an estimate result"])


@case("serve-depth-to-color-without-depth-intrinsics")
def _(ctx: Ctx, work: Path) -> Run:
    np.savetxt(work / "T_color_depth.txt", np.eye(4))
    return Run(_cli("serve", ctx.template, "--port", "0", "--depth-to-color", work / "T_color_depth.txt"),
               ["T_color_depth.txt", "intrinsics"])


@case("serve-depth-intrinsics-malformed")
def _(ctx: Ctx, work: Path) -> Run:
    (work / "depth_K.txt").write_text("1 0 2\n0 1\n")
    return Run(_cli("serve", ctx.template, "--port", "0", "--depth-intrinsics", work / "depth_K.txt"),
               ["depth_K.txt", "3x3"])


@case("serve-depth-to-color-not-rigid")
def _(ctx: Ctx, work: Path) -> Run:
    np.savetxt(work / "depth_K.txt", synth.DEFAULT_INTRINSICS.K)
    np.savetxt(work / "T_color_depth.txt", 2 * np.eye(4))
    return Run(_cli("serve", ctx.template, "--port", "0", "--depth-intrinsics", work / "depth_K.txt",
                    "--depth-to-color", work / "T_color_depth.txt"), ["T_color_depth.txt", "rigid"])


@case("info-file-name-with-emoji-code")
def _(ctx: Ctx, work: Path) -> Run:
    db = work / "bad:smile:.gscan"
    db.write_bytes(b"garbage\n")
    return Run(_cli("info", db), ["bad:smile:.gscan"])


@case("demo-output-under-a-file")
def _(ctx: Ctx, work: Path) -> Run:
    f, out = _under_a_file(work)
    return Run(_cli("demo", "--no-view", "-o", out), [f.name], unchanged=[f])


@case("scan-every-frame-dark")
def _(ctx: Ctx, work: Path) -> Run:
    """Every colour frame black, scanned on the image's keypoints (`features.keypoints: sift`; by default the depth's
    join where the image holds too few, and register a black capture's shape: not bad input)."""
    cap = _copy_capture(ctx, work, "lens_cap_on")
    _for_each(cap / "rgb", "*.png", lambda p: cv2.imwrite(str(p), np.zeros((INTR.height, INTR.width, 3), np.uint8)))
    (work / "image_keypoints.yaml").write_text("features:\n  keypoints: sift\n")
    return _scan_case(work, cap, "lens_cap_on", "keypoint", extra=("--config", str(work / "image_keypoints.yaml")))


@case("grasp-add-missing-pose-file")
def _(ctx: Ctx, work: Path) -> Run:
    run = _grasp(ctx, work, "{}")
    run.argv[-1] = str(work / "nowhere.json")
    run.names = ["nowhere.json"]
    return run


@case("mesh-missing")
def _(ctx: Ctx, work: Path) -> Run:
    out = work / "out"
    out.mkdir()
    return Run(_cli("template-from-mesh", work / "ghost.obj", "-o", out / "m.gscan", "--views", "4"), ["ghost.obj"],
               out)


@case("mesh-corrupt")
def _(ctx: Ctx, work: Path) -> Run:
    out = work / "out"
    out.mkdir()
    bad = work / "broken.ply"
    bad.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 99\n" + bytes(range(256)) * 3)
    return Run(_cli("template-from-mesh", bad, "-o", out / "m.gscan", "--views", "4"), ["broken.ply"], out)


# -- values that parse but cannot be right (found by an adversarial pass over every command)


@case("scan-intrinsics-infinite-width")
def _(ctx: Ctx, work: Path) -> Run:
    cap = _copy_capture(ctx, work)
    k = work / "inf_width.json"
    k.write_text('{"width": 1e999, "height": 240, "intrinsic_matrix": [307.5, 0, 0, 0, 307.5, 0, 159.5, 119.5, 1]}')
    return _scan_case(work, cap, k.name, extra=("--intrinsics", str(k)))


@case("scan-implausible-focal-length")
def _(ctx: Ctx, work: Path) -> Run:
    cap = _copy_capture(ctx, work)
    (cap / "cam_K.txt").write_text("1e-300 0 159.5\n0 1e-300 119.5\n0 0 1\n")
    return _scan_case(work, cap, "cam_K.txt", "focal")


@case("estimate-principal-point-far-outside")
def _(ctx: Ctx, work: Path) -> Run:
    c, d, k = _query_files(ctx, work)
    k.write_text("307.5 0 1e300\n0 307.5 1e300\n0 0 1\n")
    run = _estimate(ctx, work, c, d, k)
    run.names += [k.name, "principal point"]
    return run


@case("scan-depth-scale-beyond-float")
def _(ctx: Ctx, work: Path) -> Run:
    cap = _copy_capture(ctx, work)
    return _scan_case(work, cap, "1e+300", extra=("--depth-scale", "1e300"))


@case("scan-config-not-utf8")
def _(ctx: Ctx, work: Path) -> Run:
    cap = _copy_capture(ctx, work)
    (work / "binary.yaml").write_bytes(b"\xff\xfe\x00match")
    return _scan_case(work, cap, "binary.yaml", extra=("--config", str(work / "binary.yaml")))


@case("scan-config-nested-too-deeply")
def _(ctx: Ctx, work: Path) -> Run:
    cap = _copy_capture(ctx, work)
    (work / "deep.yaml").write_text("[" * 5000 + "]" * 5000 + "\n")
    return _scan_case(work, cap, "deep.yaml", extra=("--config", str(work / "deep.yaml")))


@case("estimate-intrinsics-nested-too-deeply")
def _(ctx: Ctx, work: Path) -> Run:
    c, d, k = _query_files(ctx, work)
    deep = k.with_name("deep.json")
    deep.write_text("[" * 100_000 + "]" * 100_000)
    run = _estimate(ctx, work, c, d, deep)
    run.names.append(deep.name)
    return run


@case("scan-config-infinite-value")
def _(ctx: Ctx, work: Path) -> Run:
    cap = _copy_capture(ctx, work)
    (work / "inf.yaml").write_text("fusion:\n  voxel: .inf\n")
    return _scan_case(work, cap, "inf.yaml", "fusion.voxel", extra=("--config", str(work / "inf.yaml")))


def _under_a_file(work: Path) -> tuple[Path, Path]:
    """A file where the output's folder should be: (that file, an output path under it)."""
    f = work / "not_a_folder"
    f.write_text("a file\n")
    return f, f / "deeper" / "x"


@case("scan-output-under-a-file")
def _(ctx: Ctx, work: Path) -> Run:
    f, out = _under_a_file(work)
    return Run(_cli("scan", _copy_capture(ctx, work), "-o", out.with_suffix(".gscan"), "--json"), [f.name],
               unchanged=[f])


@case("export-output-under-a-file")
def _(ctx: Ctx, work: Path) -> Run:
    f, out = _under_a_file(work)
    return Run(_cli("export", ctx.template, "--format", "bop", "-o", out), [f.name], unchanged=[f, ctx.template])


@case("mesh-output-under-a-file")
def _(ctx: Ctx, work: Path) -> Run:
    f, out = _under_a_file(work)
    return Run(_cli("template-from-mesh", ctx.mesh, "-o", out.with_suffix(".gscan"), "--views", "4"), [f.name],
               unchanged=[f])


@case("scan-output-in-read-only-folder")
def _(ctx: Ctx, work: Path) -> Run:
    ro = work / "read_only"
    ro.mkdir()
    ro.chmod(0o555)
    return Run(_cli("scan", _copy_capture(ctx, work), "-o", ro / "x.gscan", "--json"), ["read_only"], out_dir=ro,
               unreadable=True)


@case("export-into-the-folder-holding-the-template")
def _(ctx: Ctx, work: Path) -> Run:
    folder = work / "project"
    folder.mkdir()
    db = _template_copy(ctx, folder, "obj.gscan")
    return Run(_cli("export", db, "--format", "bop", "-o", folder, "--force"), ["project", "obj.gscan"],
               unchanged=[folder])


@case("mesh-nan-vertex")
def _(ctx: Ctx, work: Path) -> Run:
    out = work / "out"
    out.mkdir()
    bad = work / "nan.obj"
    bad.write_text("v nan 0 0\nv 0.1 0 0\nv 0 0.1 0\nf 1 2 3\n")
    return Run(_cli("template-from-mesh", bad, "-o", out / "m.gscan", "--views", "4"), ["nan.obj"], out)


def _store(db: Path, sql: str, a: np.ndarray) -> None:
    import io

    buf = io.BytesIO()
    np.save(buf, a)
    with sqlite3.connect(db) as c:
        c.execute(sql, (buf.getvalue(),))
    c.close()


@case("estimate-template-nan-keypoints")
def _(ctx: Ctx, work: Path) -> Run:
    db = _template_copy(ctx, work, "nan_points.gscan")
    with sqlite3.connect(db) as c:
        n = c.execute("SELECT n FROM features LIMIT 1").fetchone()[0]
    c.close()
    _store(db, "UPDATE features SET points=?", np.full((n, 3), np.nan, np.float32))
    return _template_command("estimate", db, ctx, work)


@case("export-template-triangle-out-of-range")
def _(ctx: Ctx, work: Path) -> Run:
    db = _template_copy(ctx, work, "bad_triangles.gscan")
    _store(db, "UPDATE mesh SET triangles=?", np.array([[0, 1, 10**8]], np.int64))
    out = work / "out"
    out.mkdir()
    return Run(_cli("export", db, "--format", "ply", "-o", out / "m.ply"), [db.name, "triangles"], out)




# A capture with one corrupt frame among good ones is NOT bad input: exit 0, the frame is reported.
PARTIAL = "scan-one-corrupt-frame"


@case(PARTIAL)
def _(ctx: Ctx, work: Path) -> Run:
    cap = _copy_capture(ctx, work, "mostly_good")
    p = cap / "rgb" / "000005.png"
    p.write_bytes(p.read_bytes()[:300])
    out = work / "out"
    out.mkdir()
    return Run(_cli("scan", cap, "-o", out / "obj.gscan", "--json"), ["000005"], expect_rc=0)


# A frame without any keypoint (lens cap on, a blank wall) is not bad input either: it stays unregistered.
DARK = "scan-one-dark-frame"


@case(DARK)
def _(ctx: Ctx, work: Path) -> Run:
    cap = work / "dark"
    for sub in ("rgb", "depth"):
        (cap / sub).mkdir(parents=True)
        for k in range(3):
            shutil.copy(ctx.capture / sub / f"00000{k}.png", cap / sub / f"00000{k}.png")
    shutil.copy(ctx.capture / "cam_K.txt", cap / "cam_K.txt")
    assert cv2.imwrite(str(cap / "rgb" / "000001.png"), np.zeros((INTR.height, INTR.width, 3), np.uint8))
    out = work / "out"
    out.mkdir()
    return Run(_cli("scan", cap, "-o", out / "obj.gscan", "--json"), ["000001"], expect_rc=0)


# ------------------------------------------------------------------------------------------ running


def _run(run: Run) -> subprocess.CompletedProcess:
    cmd = list(run.argv)
    if run.unreadable and os.geteuid() == 0:
        if shutil.which("setpriv") is None:
            pytest.fail("running as root without util-linux setpriv: cannot drop the right to read any file")
        cmd = ["setpriv", "--bounding-set", "-dac_override,-dac_read_search"] + cmd
    env = dict(os.environ, GSCAN_DEBUG="")
    env.pop("GSCAN_DEBUG")
    return subprocess.run(cmd, capture_output=True, text=True, timeout=TIMEOUT_S, cwd=ROOT, env=env)


@pytest.fixture(scope="module")
def ctx(tmp_path_factory: pytest.TempPathFactory) -> Ctx:
    from gscan.scanning.cad import template_from_mesh

    base = tmp_path_factory.mktemp("inputs")
    mesh = synth.box_mesh((0.14, 0.09, 0.07), synth.procedural_box_texture(3, (512, 768)))
    synth.render_capture(mesh, base / "capture", N_VIEWS, mode="static", elevations_deg=(40.0,), intr=INTR)
    mesh_path = synth.save_textured_mesh(mesh, base / "box" / "box.obj")
    template_from_mesh(mesh_path, base / "good.gscan", n_views=6)
    return Ctx(base / "capture", base / "good.gscan", mesh_path)


@pytest.fixture(scope="module")
def results(ctx: Ctx, tmp_path_factory: pytest.TempPathFactory
            ) -> dict[str, tuple[Run, dict, subprocess.CompletedProcess]]:
    """Build every case, then run them all concurrently: name -> (run, snapshots before, process)."""
    runs: dict[str, tuple[Run, dict]] = {}
    for name, build in CASES.items():
        run = build(ctx, tmp_path_factory.mktemp(name))
        runs[name] = (run, {str(p): _snapshot(p) for p in run.unchanged})
    slow = [PARTIAL, DARK, "scan-depth-beyond-fusion-range"]  # cases that register frames: started first
    order = slow + [n for n in runs if n not in slow]
    with ThreadPoolExecutor(max_workers=4) as pool:
        procs = dict(zip(order, pool.map(lambda n: _run(runs[n][0]), order), strict=True))
    return {n: (runs[n][0], runs[n][1], procs[n]) for n in runs}


def _error_line(stderr: str) -> str:
    """The last stderr line once lines printed by image libraries themselves are set aside."""
    lines = [ln for ln in stderr.splitlines() if ln.strip()]
    own = [ln for ln in lines if not any(tag in ln.lower() for tag in LIBRARY_NOISE) or ln.startswith("error:")]
    assert own, f"nothing on stderr: {stderr!r}"
    return own[-1]


BAD = sorted(n for n in CASES if n not in (PARTIAL, DARK))


def test_corpus_is_large_enough():
    assert len(BAD) >= 30


@pytest.mark.parametrize("name", BAD)
def test_bad_input(name: str, results):
    run, before, proc = results[name]
    detail = f"{' '.join(run.argv[3:])}\nstdout: {proc.stdout!r}\nstderr: {proc.stderr!r}"
    assert proc.returncode == 2, detail
    assert "Traceback" not in proc.stderr, detail
    assert proc.stdout == "", detail  # a failing --json command prints no half JSON object
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert not proc.stderr.startswith("\n"), detail  # no blank line before the error line
    line = _error_line(proc.stderr)
    assert line.startswith("error: "), detail
    assert sum(ln.startswith("error: ") for ln in lines) == 1, detail
    # one line: everything gscan itself printed is that line (library noise aside)
    assert [ln for ln in lines if not any(t in ln.lower() for t in LIBRARY_NOISE)] in ([line], []), detail
    for s in run.names:
        assert s in line, f"{s!r} not named in {line!r}"
    if run.out_dir is not None:
        left = sorted(p.name for p in run.out_dir.iterdir())
        assert left == [], f"left behind in {run.out_dir}: {left}"
    for p in run.unchanged:
        assert _snapshot(p) == before[str(p)], f"{p} was changed"


def test_partially_bad_capture_is_scanned(results):
    run, _, proc = results[PARTIAL]
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    out = json.loads(proc.stdout)
    assert out["frames"] == N_VIEWS
    assert "000005" in out["skipped"] and "000005.png" in out["skipped"]["000005"]
    assert "000005" in out["unregistered"]
    assert out["registered"] >= N_VIEWS // 2
    assert "000005" in proc.stderr and "000005.png" in proc.stderr
    db = Path(out["output"])
    with sqlite3.connect(db) as c:
        names = [r[0] for r in c.execute("SELECT name FROM views")]
    c.close()
    assert "000005" not in names and len(names) == N_VIEWS - 1
    info = subprocess.run(_cli("info", db, "--json"), capture_output=True, text=True, timeout=TIMEOUT_S)
    assert info.returncode == 0 and json.loads(info.stdout)["status"] == "complete"
    poses = subprocess.run(_cli("poses", db, "--json"), capture_output=True, text=True, timeout=TIMEOUT_S)
    assert json.loads(poses.stdout)["unregistered"] == out["unregistered"]  # the unreadable frame too
    assert json.loads(poses.stdout)["unregistered_reasons"] == out["unregistered_reasons"]  # and why
    assert "000005.png" in out["unregistered_reasons"]["000005"]


def test_frame_without_keypoints_is_scanned(results):
    _, _, proc = results[DARK]
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    out = json.loads(proc.stdout)
    assert out["frames"] == 3 and out["registered"] >= 1
    assert "000001" in out["unregistered"]


def test_names_are_printed_as_they_are(ctx: Ctx, tmp_path: Path):
    """The human summary prints frame and file names verbatim: "[red]" is no markup tag (rich coloured the
    rest of the line and dropped it; a closing tag such as "[/b]" in a path made it raise), ":smile:" no
    emoji code."""
    cap = _copy_capture(ctx, tmp_path, "cap :smile:")
    for sub in ("rgb", "depth", "masks", "annotated_poses"):
        for p in (cap / sub).glob("000005.*") if (cap / sub).is_dir() else ():
            p.rename(p.with_name("[red]x" + p.suffix))
    bad = cap / "rgb" / "[red]x.png"
    bad.write_bytes(bad.read_bytes()[:300])
    r = subprocess.run(_cli("scan", cap, "-o", tmp_path / "obj.gscan"), capture_output=True, text=True,
                       timeout=TIMEOUT_S, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    assert "skipped frame [red]x:" in r.stderr and "cap :smile:" in r.stderr, r.stderr
