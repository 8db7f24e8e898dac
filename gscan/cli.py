"""gscan command line (typer). The only module that prints or exits.

Exit codes: 0 ok, 2 bad input (one line naming the file), 1 internal error.
`--json` prints exactly one JSON object on stdout; progress and logs go to stderr.
Heavy modules are imported inside the commands so `gscan --help` stays fast.
"""
from __future__ import annotations

import contextlib
import errno
import json
import logging
import os
import sys
from enum import Enum
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn

import typer
from rich.console import Console

from gscan.errors import GscanError, InputError

if TYPE_CHECKING:
    from gscan.io.camera import DepthCamera

try:  # typer >= 0.2x vendors click as typer._click; older releases use click itself
    from typer._click import exceptions as _cx
except ImportError:  # pragma: no cover - depends on the installed typer
    import click.exceptions as _cx  # type: ignore[no-redef]

# rich_markup_mode=None: click's plain help, which wraps the help text and never cuts an option's name or its
# choice list (typer's boxed layout cuts both in a narrow terminal)
app = typer.Typer(add_completion=False, pretty_exceptions_enable=False, no_args_is_help=True, rich_markup_mode=None,
                  help="Scan objects with an RGB-D camera into GMatch templates; estimate their 6DoF pose on a CPU.")
grasp_app = typer.Typer(no_args_is_help=True, help="Named grasp poses stored in a template (object frame).")
config_app = typer.Typer(no_args_is_help=True, help="Scan configuration.")
app.add_typer(grasp_app, name="grasp")
app.add_typer(config_app, name="config")

# Choice options: their values are the command-line contract (the tests check them against the library's lists).


class ScanFormat(str, Enum):
    auto = "auto"
    capture = "capture"
    open3d = "open3d"
    tum = "tum"
    bop = "bop"


class ScanMode(str, Enum):
    auto = "auto"
    static_object = "static-object"
    moving_object = "moving-object"


class ExportFormat(str, Enum):
    bop = "bop"
    foundationpose = "foundationpose"
    colmap = "colmap"
    ply = "ply"
    obj = "obj"
    glb = "glb"
    json = "json"


def _version(value: bool) -> None:
    if value:
        from gscan._version import __version__

        sys.stdout.write(f"gscan {__version__}\n")
        raise typer.Exit()


@app.callback()
def _main_options(
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True,
                                 help="print the version and exit"),
) -> None:
    """Scan objects with an RGB-D camera into GMatch templates; estimate their 6DoF pose on a CPU."""
    # every command is a process gscan owns: one BLAS / OpenMP thread unless the environment names a count
    # (the rule and its reasons: gscan.threads), set before a command imports numpy
    from gscan.threads import one_blas_thread

    one_blas_thread()


# no markup or emoji codes: file and frame names ("[x]", ":smile:") are printed as they are; styles go
# through `_say`
err = Console(stderr=True, highlight=False, markup=False, emoji=False, soft_wrap=True)

# characters that would act on the terminal instead of being shown (ANSI escape sequences, carriage returns,
# line breaks, bidirectional overrides): names from files and templates are printed with these escaped
_BIDI = "\u061c\u200e\u200f\u202a\u202b\u202c\u202d\u202e\u2066\u2067\u2068\u2069\u2028\u2029"
_UNPRINTABLE = {c: f"\\x{c:02x}" for c in (*range(0x20), *range(0x7F, 0xA0))} | {
    ord(c): f"\\u{ord(c):04x}" for c in _BIDI} | {ord("\n"): "\\n", ord("\r"): "\\r", ord("\t"): "\\t"}


def printable(text: object) -> str:
    """`text` as one line that shows what it holds: control characters written as \\x1b, \\n, \\u202e."""
    return str(text).translate(_UNPRINTABLE)


def _say(*parts: str | tuple[str, str]) -> None:
    """One line on stderr; a (text, style) part is styled, a str part printed as it is (control characters
    escaped: names come from files and templates)."""
    from rich.text import Text

    line = Text()
    for p in parts:
        text, style = p if isinstance(p, tuple) else (p, None)
        line.append(printable(text), style)
    err.print(line)


def _line(text: object) -> None:
    """One line of plain text on stderr, control characters escaped."""
    err.print(printable(text))


# the option or command that addresses an InputError's `fix` (gscan.errors.FIXES)
_FIXES = {
    "replace": "pass --force to replace it",
    "resume": "pass --resume to continue it or --force to replace it",
    "restart": "pass --force to start over",
    "finish": "run `gscan scan --resume` to finish it",
    "depth_scale": "pass --depth-scale",
    "intrinsics": "pass --intrinsics (cam_K.txt or an Open3D camera JSON)",
    "obj_id": "choose the object with --obj-id",
    "gt_capture": "pass --gt-capture with the capture (rgb/, depth/, annotated_poses/ or scene_gt.json) to relate "
                  "it to the ground truth",
    "port": "choose another --port",
    "host": "choose another --host",
    "output": "choose another output with -o",
}


def error_line(e: BaseException) -> str:
    """The one line an error is reported with: its message (control characters escaped) and, for an
    InputError with a `fix`, the option of this CLI that addresses it."""
    fix = _FIXES.get(getattr(e, "fix", None) or "")
    return printable(f"error: {e}" + (f"; {fix}" if fix else ""))


class UsageError(InputError):
    """Bad command-line usage that names a file or option (exit 2)."""


def _print_json(obj: Any) -> None:
    sys.stdout.write(json.dumps(obj, indent=None, default=_json_default) + "\n")
    sys.stdout.flush()


def _json_default(o: Any) -> Any:
    import numpy as np

    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o)}")


def _matrix(T: Any) -> list[list[float]] | None:
    return None if T is None else [[float(x) for x in row] for row in T]


def _format_matrix(T: list[list[float]]) -> str:
    return "\n".join("  [" + " ".join(f"{x:+.5f}" for x in row) + "]" for row in T)


class _PrintableFormatter(logging.Formatter):
    """Log lines with control characters escaped (frame and file names come from the input)."""

    def format(self, record: logging.LogRecord) -> str:
        return printable(super().format(record))
def _format_pose(T: Any) -> str:
    """One line: translation (m) and rotation as an angle (deg) about a unit axis, e.g.
    `t = [+0.1000, -0.0200, +0.5000] m, R = 30.00 deg about [+0.000, +0.000, +1.000]`."""
    import cv2
    import numpy as np

    T = np.asarray(T, dtype=np.float64)
    rotvec = cv2.Rodrigues(T[:3, :3])[0].reshape(3)
    angle = float(np.linalg.norm(rotvec))
    axis = rotvec / angle if angle > 0 else np.array([0.0, 0.0, 1.0])
    t = T[:3, 3]
    return (f"t = [{t[0]:+.4f}, {t[1]:+.4f}, {t[2]:+.4f}] m, "
            f"R = {np.degrees(angle):.2f} deg about [{axis[0]:+.3f}, {axis[1]:+.3f}, {axis[2]:+.3f}]")


def _setup_logging(verbose: bool) -> None:
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(_PrintableFormatter("%(levelname)s %(name)s: %(message)s"))
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING, handlers=[handler])


# --------------------------------------------------------------------------------------------- scan

DEPTH_INTRINSICS_HELP = ("depth not registered to colour: the depth camera's cam_K.txt or Open3D intrinsics JSON "
                         "(the depth is reprojected into the colour camera)")
DEPTH_TO_COLOR_HELP = ("with --depth-intrinsics: T_color_depth, the depth camera's pose in the colour camera "
                       "(4x4 text or JSON matrix, metres; default: the same centre and axes)")


def _depth_camera(depth_intrinsics: Path | None, depth_to_color: Path | None) -> DepthCamera | None:
    """The DepthCamera of the --depth-intrinsics / --depth-to-color options (None without them)."""
    from gscan.io.camera import load_depth_camera

    if depth_intrinsics is None:
        if depth_to_color is not None:
            raise InputError(depth_to_color, "a depth-to-colour pose needs the depth camera's intrinsics too "
                             "(--depth-intrinsics)")
        return None
    return load_depth_camera(depth_intrinsics, depth_to_color)


@app.command()
def scan(
    input_dir: Path = typer.Argument(..., help="RGB-D folder (capture, Open3D, TUM or BOP layout) or recording "
                                     "(.bag, .db3, .mcap, rosbag2 folder)"),
    output: Path = typer.Option(..., "-o", "--output", help="template database to write (OBJ.gscan)"),
    format: ScanFormat = typer.Option("auto", "--format", help="input layout (auto: detected)"),
    intrinsics: Path | None = typer.Option(None, "--intrinsics", help="cam_K.txt or Open3D intrinsics JSON"),
    depth_scale: float | None = typer.Option(None, "--depth-scale", help="metres per raw depth unit"),
    mode: ScanMode = typer.Option("auto", "--mode", help="capture mode (auto: detected)"),
    no_segment: bool = typer.Option(False, "--no-segment", help="fuse the whole scene, not the object alone"),
    resume: bool = typer.Option(False, "--resume", help="continue an interrupted scan into OUTPUT"),
    force: bool = typer.Option(False, "--force", help="replace an existing OUTPUT"),
    config: Path | None = typer.Option(None, "--config", help="YAML configuration (see `gscan config dump`)"),
    obj_id: int | None = typer.Option(None, "--obj-id", min=1, max=2**31 - 1,
                                         help="BOP folder: the object to scan (default: the first in scene_gt.json)"),
    color_topic: str | None = typer.Option(None, "--color-topic",
                                              help="recording: the colour image topic (default: detected)"),
    depth_topic: str | None = typer.Option(None, "--depth-topic",
                                              help="recording: the depth image topic (default: detected)"),
    depth_intrinsics: Path | None = typer.Option(None, "--depth-intrinsics", help=DEPTH_INTRINSICS_HELP),
    depth_to_color: Path | None = typer.Option(None, "--depth-to-color", help=DEPTH_TO_COLOR_HELP),
    json_out: bool = typer.Option(False, "--json", help="print one JSON object on stdout"),
    verbose: bool = typer.Option(False, "-v", "--verbose", help="log progress details to stderr"),
) -> None:
    """Register every view of an RGB-D capture into one object frame and write a template database."""
    _setup_logging(verbose)
    _import_holding_ctrl_c(*_SCAN_IMPORTS)
    from gscan.progress import RichProgress
    from gscan.scanning.api import scan as scan_capture
    from gscan.scanning.config import load_config

    if resume and force:
        raise UsageError(output, "--resume and --force exclude each other")
    cfg = load_config(config)
    try:
        with RichProgress(err, enabled=not json_out or sys.stderr.isatty()) as progress:
            result = scan_capture(input_dir, output, config=cfg, format=format.value, intrinsics=intrinsics,
                                  depth_scale=depth_scale, mode=mode.value, segment=not no_segment, resume=resume,
                                  force=force, obj_id=obj_id, color_topic=color_topic, depth_topic=depth_topic,
                                  depth_camera=_depth_camera(depth_intrinsics, depth_to_color),
                                  progress=progress)
    except KeyboardInterrupt:  # Ctrl+C: the partial database is kept for --resume (typer exits 130)
        _say_interrupted(_interrupted_scan_line(output, force))
        raise
    if json_out:
        _print_json(result.to_json())
    else:
        _print_scan_summary(result)


_SCAN_IMPORTS = ("gscan.scanning.api", "open3d", "scipy.spatial")  # with the scan's lazy C-extension imports


def _import_holding_ctrl_c(*modules: str) -> None:
    """Import `modules` with Ctrl+C held: a SIGINT that comes meanwhile is delivered again after them.

    Ctrl+C inside a C extension's initialisation turns into "ImportError: initialization failed", which would be
    reported as an internal error (open3d's initialisation is long enough to be hit, and the scan imports it
    lazily). The handler is swapped, not the signal blocked: a blocked signal goes to another
    thread (numpy's BLAS pool) and interrupts the import all the same. Main thread only."""
    import importlib
    import signal

    caught: list[int] = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: caught.append(signum))
    try:
        for m in modules:
            importlib.import_module(m)
    finally:
        signal.signal(signal.SIGINT, previous)
    if caught:  # again, to the handler it would have met (KeyboardInterrupt, or nothing where it is ignored)
        signal.raise_signal(signal.SIGINT)


def _interrupted_scan_line(output: Path, force: bool) -> str:
    """What an interrupted scan left: a partial database to resume, or the output as it was."""
    from gscan.template.db import TemplateDB

    try:
        with TemplateDB.open(output, require_complete=False) as db:
            partial = db.status == "partial"
    except Exception:  # noqa: BLE001 - no database (yet), or an unreadable one: nothing to resume
        partial = False
    if partial:
        how = "--resume instead of --force" if force else "--resume"
        return f"interrupted: {output} keeps the work done so far; run the command again with {how} to continue it"
    return f"interrupted: {output} was left as it was" if output.exists() else "interrupted: nothing was written"


def _print_scan_summary(result: Any) -> None:
    from rich.table import Table

    table = Table(title="stage timings", show_header=True)
    table.add_column("stage")
    table.add_column("seconds", justify="right")
    for stage, sec in result.timings_s.items():
        table.add_row(stage, f"{sec:.2f}")
    err.print(table)
    _say((str(result.output), "bold"), f": {result.registered}/{result.frames} frames registered "
              f"({result.mode}), edges {result.edges_accepted} accepted / {result.edges_rejected} rejected, "
              f"mesh {result.mesh_vertices} vertices / {result.mesh_triangles} triangles, "
              f"{result.keyframes} keyframes (the views estimate matches)")
    cam = result.camera
    if cam is not None and cam["corrected"]:
        given, used = cam["given_focal_px"][0], cam["colour_focal_px"][0]
        _say(("colour camera:", "yellow"), f" the depth did not line up with the colour at the given focal length "
             f"{given:g} px; the texture lines up at {used:g} px ({cam['texture_agreement']['used']:.0%} of textured "
             f"tiles against {cam['texture_agreement']['given']:.0%}), used with the given intrinsics as the depth "
             "camera's. --intrinsics and --depth-intrinsics set both cameras")
    sel = result.selection
    if sel.get("skipped"):  # frame selection: not failures, counted by reason
        why = "; ".join(f"{k} frames {w}" for w, k in sel["reasons"].items())
        _say(("frame selection:", "bold"), f" {sel['kept']} frames kept, {sel['skipped']} skipped ({why}); "
             "`gscan poses --json` lists each")
    for name in result.unregistered:  # each with its reason (a frame that could not be read: why)
        what = "skipped frame" if name in result.problems else "unregistered frame"
        _say((f"{what} {name}:", "yellow"), f" {result.unregistered_reasons.get(name, '')}")
    for k, part in enumerate(result.parts, 1):
        _say((f"separate part {k}:", "yellow"), f" {len(part)} frames ({', '.join(part)}), not joined to the "
             "template's frames with confidence: scanned again with views between them, they can be")


# ------------------------------------------------------------------------------------- template-from-mesh


@app.command("template-from-mesh")
def template_from_mesh(
    mesh: Path = typer.Argument(..., help="textured mesh (OBJ with texture, PLY, GLB)"),
    output: Path = typer.Option(..., "-o", "--output", help="template database to write"),
    views: int = typer.Option(36, "--views", min=4, max=500, help="snapshots rendered around the mesh"),
    scale: float = typer.Option(1.0, "--scale", help="mesh units to metres (0.001 for millimetres)"),
    force: bool = typer.Option(False, "--force", help="replace an existing OUTPUT"),
    json_out: bool = typer.Option(False, "--json", help="print one JSON object on stdout"),
) -> None:
    """Render snapshots around a CAD mesh into a template database (mesh frame kept)."""
    from gscan.progress import RichProgress
    from gscan.scanning.cad import template_from_mesh as render_template

    if scale <= 0:
        raise UsageError(mesh, f"--scale must be positive, not {scale}")
    with RichProgress(err, enabled=not json_out) as progress:
        result = render_template(mesh, output, n_views=views, scale=scale, force=force, progress=progress)
    if json_out:  # the `template-from-mesh --json` object
        _print_json({"output": str(result.output), "views": result.views, "descriptor": result.descriptor,
                     "source": result.source, "extent_m": list(result.extent_m)})
    else:
        _say((str(output), "bold"), f": {result.views} views rendered from {mesh}")


# ------------------------------------------------------------------------------------------- estimate


def _load_query_frame(color: Path, depth: Path, intrinsics: Path, depth_scale: float, mask: Path | None,
                      depth_intrinsics: Path | None = None, depth_to_color: Path | None = None):
    from gscan.io import load_frame

    cam = _depth_camera(depth_intrinsics, depth_to_color)
    return load_frame(color, depth, intrinsics, depth_scale=depth_scale, mask_path=mask, depth_camera=cam)


@app.command()
def estimate(
    template: Path = typer.Argument(..., help="template database (OBJ.gscan)"),
    color: Path = typer.Option(..., "--color", help="colour image"),
    depth: Path = typer.Option(..., "--depth", help="16-bit depth image"),
    intrinsics: Path = typer.Option(..., "--intrinsics", help="cam_K.txt or Open3D intrinsics JSON"),
    depth_scale: float = typer.Option(0.001, "--depth-scale", help="metres per raw depth unit"),
    mask: Path | None = typer.Option(None, "--mask", help="restrict the search to this mask"),
    no_icp: bool = typer.Option(False, "--no-icp", help="skip the ICP refinement"),
    depth_intrinsics: Path | None = typer.Option(None, "--depth-intrinsics", help=DEPTH_INTRINSICS_HELP),
    depth_to_color: Path | None = typer.Option(None, "--depth-to-color", help=DEPTH_TO_COLOR_HELP),
    json_out: bool = typer.Option(False, "--json", help="print one JSON object on stdout"),
) -> None:
    """Estimate the object's pose T_cam_obj in a new RGB-D frame."""
    from gscan.estimate.estimator import Estimator

    estimator = Estimator.from_path(template)
    frame = _load_query_frame(color, depth, intrinsics, depth_scale, mask, depth_intrinsics, depth_to_color)
    result = estimator.estimate(frame, mask=frame.mask, refine=not no_icp)
    out = result.to_json()
    if json_out:
        _print_json(out)
        return
    if result.T_cam_obj is None:
        _say(("object not found", "yellow"), f": {result.reason}")
    else:
        _line(f"found: view {result.view}, {result.n_matches} matched keypoint pairs (GMatch's list), "
              f"score {result.score:.3f}")
        err.print("T_cam_obj =\n" + _format_matrix(out["T_cam_obj"]))
        for name, T in out["grasps"].items():
            _line(f"grasp {name}: T_cam_grasp =")
            err.print(_format_matrix(T))
    err.print("timings (ms): " + ", ".join(f"{k} {v:.1f}" for k, v in out["timings_ms"].items()))


# ------------------------------------------------------------------------------------------- track


@app.command()
def track(
    template: Path = typer.Argument(..., help="template database (OBJ.gscan)"),
    input_path: Path = typer.Argument(..., metavar="INPUT", help="RGB-D sequence: a folder in any layout scan reads"),
    output: Path | None = typer.Option(
        None, "-o", "--output", help="folder for one T_cam_obj per frame (ob_in_cam 4x4 text) + summary.json"),
    format: str = typer.Option("auto", "--format", help="auto|capture|open3d|tum|bop"),
    intrinsics: Path | None = typer.Option(None, "--intrinsics", help="cam_K.txt or Open3D intrinsics JSON"),
    depth_scale: float | None = typer.Option(None, "--depth-scale", help="metres per raw depth unit"),
    depth_intrinsics: Path | None = typer.Option(None, "--depth-intrinsics", help=DEPTH_INTRINSICS_HELP),
    depth_to_color: Path | None = typer.Option(None, "--depth-to-color", help=DEPTH_TO_COLOR_HELP),
    force: bool = typer.Option(False, "--force", help="replace an existing OUTPUT"),
    json_out: bool = typer.Option(False, "--json", help="print one JSON object on stdout"),
    verbose: bool = typer.Option(False, "-v", "--verbose", help="log progress details to stderr"),
) -> None:
    """Estimate the object's pose through an RGB-D sequence, the previous pose as a prior."""
    _setup_logging(verbose)
    from gscan.estimate import Estimator, track_sequence, write_poses
    from gscan.io import check_output_path, open_sequence
    from gscan.io.layouts import FORMATS

    if format not in ("auto",) + FORMATS:
        raise UsageError(None, f"--format must be one of {', '.join(('auto',) + FORMATS)}, not {format!r}")
    if output is not None:  # refused before any work
        if output.exists() and (not output.is_dir() or any(output.iterdir())) and not force:
            raise UsageError(output, "exists and is not empty (pass --force to replace it)")
        check_output_path(output)
    estimator = Estimator.from_path(template)
    seq = open_sequence(input_path, format, intrinsics=intrinsics, depth_scale=depth_scale,
                        depth_camera=_depth_camera(depth_intrinsics, depth_to_color))

    def report(step) -> None:
        if json_out:
            return
        res = step.result
        what = f"score {res.score:.2f}" if res.T_cam_obj is not None else str(res.reason)
        style = "yellow" if step.status in ("lost", "refound") else None
        _say(f"{step.frame}: ", (step.status, style) if style else step.status,
             f" ({what}, {res.timings_ms.get('total', 0.0):.0f} ms)")

    run = track_sequence(estimator, seq, on_step=report)
    written = write_poses(run, output, force=force) if output is not None else None
    out = run.to_json(written)
    if json_out:
        _print_json(out)
        return
    st = out["status"]
    _say((f"{out['with_pose']}/{out['frames']} frames with a pose", "bold"),
         f": {st['found']} found, {st['tracked']} tracked, {st['refound']} re-found, {st['lost']} lost; "
         f"median {out['timings_ms']['median']:.0f} ms per frame"
         + (f"; poses written to {written}" if written is not None else ""))
    for name, reason in out["unreadable"].items():
        _say((f"skipped frame {name}:", "yellow"), f" {reason}")


# ------------------------------------------------------------------------------------- poses / info


@app.command()
def poses(
    template: Path = typer.Argument(..., help="template database"),
    json_out: bool = typer.Option(False, "--json", help="print one JSON object on stdout"),
) -> None:
    """Camera pose T_obj_cam of every registered input frame in the template frame (`--json`: the 4x4 matrices;
    otherwise translation and rotation angle / axis, one line per frame)."""
    from gscan.template.db import TemplateDB

    with TemplateDB.open(template, require_complete=True) as db:
        out = db.poses()
    if json_out:
        _print_json(out)
        return
    err.print("T_obj_cam (camera pose in the template frame) of each registered frame:")
    for name, T in out["frames"].items():
        _line(f"{name}: {_format_pose(T)}")
    for name in out["unregistered"]:
        _line(f"{name}: unregistered: {out['unregistered_reasons'][name]}")
    for name, why in out["skipped_by_selection"].items():
        _line(f"{name}: skipped by frame selection: {why}")
    _part_lines(out["parts"])


def _part_lines(parts: list[list[str]]) -> None:
    """One line per separate part of a scanned capture (`poses`, `info`)."""
    for k, part in enumerate(parts, 1):
        _line(f"separate part {k}: {len(part)} frames ({', '.join(part)}), not joined to the registered ones")


@app.command()
def info(
    template: Path = typer.Argument(..., help="template database"),
    json_out: bool = typer.Option(False, "--json", help="print one JSON object on stdout"),
) -> None:
    """Summary of a template database (works on partial ones too). `mesh` counts the stored mesh's vertices,
    triangles and open (boundary) edges: a scanned mesh is open where the support plane cut it; the exports
    close it unless `export --keep-holes`."""
    from gscan.geometry.meshfill import boundary_edges
    from gscan.template.db import TemplateDB

    with TemplateDB.open(template, require_complete=False) as db:
        s = db.summary()
        m = db.mesh()
        camera = db.get_meta("camera")  # the scan's colour camera check (gscan.scanning.calibration), None: not run
    # the `info --json` object of the CLI contract, and the mesh's size and open edges
    out: dict[str, Any] = {
        "schema": s.schema, "status": s.status, "views": s.views, "registered": s.registered,
        "keyframes": s.keyframes, "descriptor": s.descriptor, "source": s.source, "extent_m": list(s.extent_m),
        "grasps": list(s.grasps), "unregistered_reasons": dict(s.unregistered_reasons),
        "selection": dict(s.selection), "parts": [list(p) for p in s.parts]}
    out["mesh"] = None if m is None else {"vertices": len(m.vertices), "triangles": len(m.triangles),
                                          "open_edges": len(boundary_edges(m.triangles))}
    out["camera"] = camera
    if json_out:
        _print_json(out)
        return
    for k, v in out.items():
        if k == "unregistered_reasons":
            for name, reason in v.items():
                _line(f"unregistered {name}: {reason}")
            continue
        if k == "parts":
            _part_lines(v)
            continue
        if k == "selection":
            if v.get("skipped"):
                why = "; ".join(f"{n} frames {w}" for w, n in v["reasons"].items())
                _line(f"frame selection: {v['kept']} frames kept, {v['skipped']} skipped ({why})")
            continue
        if k == "camera":
            if v is not None:
                used = "used" if v["corrected"] else "checked, kept"
                _line(f"colour camera: focal length given {v['given_focal_px'][0]:g} px, {used} "
                      f"{v['colour_focal_px'][0]:g} px (from the texture of {v['pairs']} frame pairs)")
            continue
        if k == "mesh" and v is not None:
            holes = " (export closes them; --keep-holes keeps them)" if v["open_edges"] else ", watertight"
            v = f"{v['vertices']} vertices, {v['triangles']} triangles, {v['open_edges']} open edges{holes}"
        _line(f"{k}: {v}")


# ------------------------------------------------------------------------------------------ export


@app.command()
def export(
    template: Path = typer.Argument(..., help="template database"),
    format: ExportFormat = typer.Option(..., "--format", help="what to write (see the README's Exports)"),
    output: Path = typer.Option(..., "-o", "--output", help="output file or folder"),
    force: bool = typer.Option(False, "--force", help="replace an existing output"),
    keep_holes: bool = typer.Option(False, "--keep-holes", help="leave the mesh open where the scan saw no surface "
                                    "(by default the bottom the support plane cut off is closed: a watertight model)"),
    json_out: bool = typer.Option(False, "--json", help="print one JSON object on stdout"),
) -> None:
    """Export a template for other tools."""
    from gscan.exporters import export as do_export

    written = do_export(template, format.value, output, force=force, close=not keep_holes)
    if json_out:
        _print_json({"output": str(written.path), "format": written.format, "views": written.views,
                     "files": written.files})
    else:
        _line(f"wrote {written}")


# -------------------------------------------------------------------------------------------- view


@app.command()
def view(
    template: Path = typer.Argument(..., help="template database"),
    host: str = typer.Option("127.0.0.1", "--host", help="address to bind"),
    port: int = typer.Option(8080, "--port", min=1, max=65535, help="port to serve on"),
    color: Path | None = typer.Option(None, "--color", help="show this frame with the estimated pose"),
    depth: Path | None = typer.Option(None, "--depth", help="depth of --color"),
    intrinsics: Path | None = typer.Option(None, "--intrinsics", help="intrinsics of --color"),
    depth_scale: float = typer.Option(0.001, "--depth-scale", help="metres per raw depth unit"),
    pose: Path | None = typer.Option(
        None, "--pose", help='T_cam_obj of --color\'s frame instead of estimating it: {"T": 4x4} or a bare 4x4 list'),
    token: str | None = typer.Option(None, "--token", help="serve only browsers that open the URL with "
                                        "?token=TOKEN (1-256 of A-Z a-z 0-9 . _ ~ -)"),
) -> None:
    """Browse a template (views, matches, pose graph) in the web browser."""
    from gscan.viewer.access import check_token, is_loopback
    from gscan.viewer.app import run_viewer

    if token is not None:
        check_token(token)
    elif not is_loopback(host):
        _say(("warning:", "yellow"), f" --host {host} is not a loopback address: every image of {template.name} "
             "is served without authentication to anyone who can reach this port; pass --token to require one")

    frame = T_cam_obj = None
    if pose is not None and color is None:
        raise UsageError(pose, "--pose places a query frame: it needs --color, --depth and --intrinsics")
    if color is not None or depth is not None or intrinsics is not None:
        if color is None or depth is None or intrinsics is None:
            raise UsageError(None, "--color, --depth and --intrinsics go together")
        frame = _load_query_frame(color, depth, intrinsics, depth_scale, None)
        if pose is not None:
            from gscan.io import read_pose_file

            T_cam_obj = read_pose_file(pose)
        else:
            from gscan.estimate.estimator import Estimator

            result = Estimator.from_path(template).estimate(frame)
            T_cam_obj = result.T_cam_obj
            found = f"view {result.view}" if T_cam_obj is not None else f"not found ({result.reason})"
            _line(f"estimate: {found}")
    run_viewer(template, host=host, port=port, scene_frame=frame, T_cam_obj=T_cam_obj, token=token,
               on_ready=lambda url: _say("viewer ready at ", (url, "bold"), " (Ctrl+C to stop)"))


# ------------------------------------------------------------------------------------------- serve


@app.command()
def serve(
    templates: list[Path] = typer.Argument(..., metavar="OBJ.gscan...", help="template databases to serve"),
    host: str = typer.Option("127.0.0.1", "--host", help="address to bind (0.0.0.0: every interface)"),
    port: int = typer.Option(8765, "--port", min=0, max=65535, help="port to serve on (0: a free one)"),
    depth_intrinsics: Path | None = typer.Option(
        None, "--depth-intrinsics", help="depth not registered to colour: the depth camera's cam_K.txt or Open3D "
        "intrinsics JSON, for the requests that name none (a request's depth_intrinsics field overrides it)"),
    depth_to_color: Path | None = typer.Option(None, "--depth-to-color", help=DEPTH_TO_COLOR_HELP),
    verbose: bool = typer.Option(False, "-v", "--verbose", help="log requests' details to stderr"),
) -> None:
    """Serve pose estimation over HTTP with the templates kept warm (OpenAPI page at /docs)."""
    _setup_logging(verbose)
    from gscan.service.server import serve as run_service

    def ready(url: str) -> None:
        _say("serving ", (", ".join(t.name for t in templates), "bold"), " at ", (url, "bold"),
             f" (API at {url}/docs; Ctrl+C to stop)"
             + (f"; depth camera {depth_intrinsics}" if depth_intrinsics is not None else ""))

    run_service(templates, host=host, port=port, on_ready=ready,
                depth_camera=_depth_camera(depth_intrinsics, depth_to_color))


# ------------------------------------------------------------------------------------------- grasp


@grasp_app.command("add")
def grasp_add(
    template: Path = typer.Argument(..., help="template database"),
    name: str = typer.Option(..., "--name", help="grasp name"),
    pose: Path = typer.Option(..., "--pose", help='JSON file: {"T": 4x4} or a bare 4x4 list (object frame, metres)'),
) -> None:
    """Store a named grasp pose T_obj_grasp in the template."""
    from gscan.io import read_pose_file
    from gscan.template.db import TemplateDB

    T = read_pose_file(pose)
    with TemplateDB.open(template, require_complete=True, writable=True) as db:
        db.add_grasp(name, T)
    _line(f"grasp {name!r} stored in {template}")


@grasp_app.command("list")
def grasp_list(
    template: Path = typer.Argument(..., help="template database"),
    json_out: bool = typer.Option(False, "--json", help="print one JSON object on stdout"),
) -> None:
    """List the grasp poses stored in a template."""
    from gscan.template.db import TemplateDB

    with TemplateDB.open(template, require_complete=False) as db:
        grasps = db.grasps()
    if json_out:
        _print_json({"grasps": {k: _matrix(v) for k, v in grasps.items()}})
        return
    if not grasps:
        err.print("no grasps")
    for k, T in grasps.items():
        _line(f"{k}: T_obj_grasp {_format_pose(T)}")


# -------------------------------------------------------------------------------------------- eval


@app.command("eval")
def eval_cmd(
    template: Path = typer.Argument(..., help="template database of the object"),
    scenes: Path = typer.Argument(..., help="BOP scene folder, or a folder of rendered scenes (capture layout)"),
    output: Path = typer.Option(..., "-o", "--output", help="BOP19 results CSV to write"),
    obj_id: int = typer.Option(1, "--obj-id", min=1, max=2**31 - 1, help="object id in scene_gt.json and in the CSV"),
    model: Path | None = typer.Option(None, "--model",
                                      help="object model for ADD/ADD-S/MSSD/MSPD (default: template mesh)"),
    gt_capture: Path | None = typer.Option(
        None, "--gt-capture", help="capture a scanned template came from, with ground-truth poses, to relate its "
        "frame to the ground truth's (default: the template's own input folder)"),
    no_icp: bool = typer.Option(False, "--no-icp", help="skip the ICP refinement"),
    force: bool = typer.Option(False, "--force", help="replace an existing output"),
    json_out: bool = typer.Option(False, "--json", help="print one JSON object on stdout"),
) -> None:
    """Run estimation over scenes, write BOP19 results CSV and print a metrics table."""
    from gscan.evaluate.bop19 import evaluate

    report = evaluate(template, scenes, output, obj_id=obj_id, model_path=model, refine=not no_icp, force=force,
                      gt_capture=gt_capture)
    if json_out:
        _print_json(report.to_json())
        return
    from rich.table import Table

    table = Table(title=f"{report.n_images} images, {report.n_found} found")
    table.add_column("metric")
    table.add_column("value", justify="right")
    for k, v in report.metrics.items():
        table.add_row(k, f"{v:.2f}")
    err.print(table)
    _line(f"results written to {output}")


# ------------------------------------------------------------------------------------------- batch

# the options of `batch` / `batch-eval` that address a failed job's InputError `fix`
_BATCH_FIXES = {"replace": "pass --force to scan it again", "restart": "pass --force to scan it again",
                "resume": "pass --force to scan it again", "finish": "run `gscan batch` on its captures to finish it"}


def _job_error_line(name: str, error: str | None, fix: str | None) -> str:
    hint = _BATCH_FIXES.get(fix or "")
    return printable(f"{name}: {error or 'failed'}" + (f"; {hint}" if hint else ""))


def _start_batch(verbose: bool) -> None:
    """Logging as asked; exit 2 with the install command when Ray is missing."""
    _setup_logging(verbose)
    from gscan.batch.runtime import require_ray

    require_ray()


def _run_batch(noun: str, run: Any, json_out: bool, table: Any = None, interrupted: str | None = None) -> Any:
    """The report of `run(monitor)` (a batch), run under the live progress table with Ray's own messages kept
    off stdout; then its JSON (--json) or `table(report)`, and a line per failed job."""
    from gscan.batch.display import RichBatchMonitor

    try:
        with (contextlib.redirect_stdout(sys.stderr),  # Ray's own messages (a worker died, ...) are not the JSON
              RichBatchMonitor(err, live=err.is_terminal, escape=printable, noun=noun) as monitor):
            report = run(monitor if err.is_terminal or not json_out else None)
    except KeyboardInterrupt:
        if interrupted:
            _say_interrupted(interrupted)
        raise
    if json_out:
        _print_json(report.to_json())
    elif table is not None:
        table(report)
    for row in report.rows:
        if row.status == "failed":
            _say(("failed ", "red"), _job_error_line(row.name, row.error, row.fix))
    return report


@app.command()
def batch(
    captures_dir: Path = typer.Argument(..., help="folder of capture folders and recordings (.bag, .db3, .mcap, "
                                        "rosbag2 folders)"),
    output: Path = typer.Option(..., "-o", "--output", help="folder of the templates (NAME.gscan) and of the report "
                                "(batch.json, batch.csv)"),
    config: Path | None = typer.Option(None, "--config", help="YAML configuration of every scan"),
    address: str | None = typer.Option(None, "--address", help="Ray cluster to run on: auto (the one started on "
                                          "this machine) or ray://HOST:PORT (default: a local Ray runtime)"),
    workers: int | None = typer.Option(None, "--workers", min=1, help="local runtime: its CPUs (default: all); "
                                          "cluster: at most this many scans at once"),
    force: bool = typer.Option(False, "--force", help="scan every capture again, replacing complete templates"),
    json_out: bool = typer.Option(False, "--json", help="print one JSON object on stdout"),
    verbose: bool = typer.Option(False, "-v", "--verbose", help="log details to stderr"),
) -> None:
    """Scan every capture under CAPTURES_DIR into OUTPUT/NAME.gscan, one Ray task per capture.

    A complete template is skipped, a partial one resumed; a failing capture does not stop the others.
    Exit code 0 when every capture succeeded, 2 when some had bad input, 1 otherwise."""
    _start_batch(verbose)
    from gscan.batch.scan import run_batch

    report = _run_batch("captures", lambda monitor: run_batch(captures_dir, output, config=config, address=address,
                                                              workers=workers, force=force, monitor=monitor),
                        json_out, table=_print_batch_table,
                        interrupted="interrupted: the templates finished are kept; run the command again to resume "
                                    "the others")
    s = report.summary()
    _say((f"{s['captures']} captures", "bold"), f": {s['scanned']} scanned, {s['resumed']} resumed, "
         f"{s['skipped']} skipped, {s['failed']} failed in {report.seconds:.1f} s"
         + (f" on {report.runtime} ({report.capacity} CPUs)" if report.runtime else "")
         + f"; report in {output / 'batch.json'} and batch.csv")
    if report.exit_code:
        raise typer.Exit(report.exit_code)


def _print_batch_table(report: Any) -> None:
    from rich.table import Table
    from rich.text import Text

    if len(report.rows) > 60:  # a catalogue: the failures are listed below, the rest is in batch.csv
        return
    table = Table(show_edge=False)
    for col in ("capture", "status", "registered", "keyframes", "s", "MiB", "ATE mm", "wrong"):
        table.add_column(col, justify="left" if col in ("capture", "status") else "right", no_wrap=col != "capture")
    for r in report.rows:
        gt = r.ground_truth or {}
        ate = gt.get("ate_rmse_m")
        table.add_row(Text(printable(r.name)), r.status,
                      "" if r.registered is None else f"{r.registered}/{r.frames}", str(r.keyframes or ""),
                      f"{r.seconds:.1f}" if r.status in ("scanned", "resumed") else "",
                      f"{r.peak_rss_bytes / 2**20:.0f}" if r.peak_rss_bytes else "",
                      "" if ate is None else f"{1000 * ate:.1f}", str(len(gt.get("wrong_frames", []))) if gt else "")
    err.print(table)


@app.command("batch-eval")
def batch_eval(
    templates_dir: Path | None = typer.Argument(None, help="folder of templates (NAME.gscan)"),
    scenes_dir: Path | None = typer.Argument(None, help="folder of scene folders, one per template (NAME/)"),
    output: Path = typer.Option(..., "-o", "--output", help="BOP19 results CSV to write (the metrics per object go "
                                "beside it: STEM.objects.json and STEM.objects.csv)"),
    manifest: Path | None = typer.Option(None, "--manifest", help="CSV of the pairs instead of the two folders: "
                                            "template,scenes[,obj_id,model,gt_capture,name]"),
    no_icp: bool = typer.Option(False, "--no-icp", help="skip the ICP refinement"),
    address: str | None = typer.Option(None, "--address", help="Ray cluster to run on: auto or ray://HOST:PORT "
                                          "(default: a local Ray runtime)"),
    workers: int | None = typer.Option(None, "--workers", min=1, help="local runtime: its CPUs (default: all); "
                                          "cluster: at most this many evaluations at once"),
    force: bool = typer.Option(False, "--force", help="replace existing outputs"),
    json_out: bool = typer.Option(False, "--json", help="print one JSON object on stdout"),
    verbose: bool = typer.Option(False, "-v", "--verbose", help="log details to stderr"),
) -> None:
    """Score many templates against their scenes as `gscan eval` does, one Ray task per pair, into one BOP19 CSV.

    Pairs: NAME.gscan in TEMPLATES_DIR with SCENES_DIR/NAME, or the rows of --manifest.
    Exit code 0 when every pair was evaluated, 2 when some had bad input, 1 otherwise."""
    _start_batch(verbose)
    if manifest is not None and (templates_dir is not None or scenes_dir is not None):
        raise UsageError(manifest, "--manifest names the pairs: leave out TEMPLATES_DIR and SCENES_DIR")
    if manifest is None and (templates_dir is None or scenes_dir is None):
        raise UsageError(None, "give TEMPLATES_DIR and SCENES_DIR, or --manifest")
    from gscan.batch.evaluate import objects_paths, run_batch_eval

    report = _run_batch("pairs", lambda monitor: run_batch_eval(
        output, templates_dir=templates_dir, scenes_dir=scenes_dir, manifest=manifest, refine=not no_icp,
        address=address, workers=workers, force=force, monitor=monitor), json_out)
    s = report.summary()
    for w in s["warnings"]:
        _say(("warning: ", "yellow"), w)
    if s["unpaired_templates"] or s["unpaired_scenes"]:
        _say(("not paired: ", "yellow"), f"{len(s['unpaired_templates'])} templates without scenes, "
             f"{len(s['unpaired_scenes'])} scene folders without a template (see the objects report)")
    ar = s["pooled"]["AR"]
    _say((f"{s['pairs']} pairs", "bold"), f": {s['evaluated']} evaluated, {s['failed']} failed; {s['found']}/"
         f"{s['images']} poses found, {s['wrong_accepted']} wrong accepted"
         + (f", AR {ar:.1f}" if ar is not None else "") + f" in {report.seconds:.1f} s; results in {output}, "
         f"metrics per object in {objects_paths(output)[0].name} and .csv")
    if report.exit_code:
        raise typer.Exit(report.exit_code)


# ------------------------------------------------------------------------------------------ config


@config_app.command("dump")
def config_dump() -> None:
    """Print the default scan configuration as commented YAML."""
    from gscan.scanning.config import dump_defaults

    sys.stdout.write(dump_defaults())


# ----------------------------------------------------------------------------------------- capture


@app.command()
def capture(
    output: Path = typer.Option(..., "-o", "--output", help="capture folder to write (rgb/, depth/, cam_K.txt)"),
    from_file: Path | None = typer.Option(None, "--from", help="play this RealSense .bag instead of a live camera"),
    fps: int | None = typer.Option(None, "--fps", min=1, max=1000,
                                      help="stream rate (live: 30 by default; --from: the recording's)"),
    every: int | None = typer.Option(None, "--every", min=1, help="keep every Nth frame instead of the motion rule"),
    width: int | None = typer.Option(None, "--width", min=1, help="stream width (live: 640 by default)"),
    height: int | None = typer.Option(None, "--height", min=1, help="stream height (live: 480 by default)"),
    min_motion: float = typer.Option(10.0, "--min-motion", min=0.1, max=90.0,
                                     help="degrees the view of the object must turn for a frame to be kept"),
    max_frames: int | None = typer.Option(None, "--max-frames", min=1, help="stop after keeping this many frames"),
    real_time: bool = typer.Option(False, "--real-time", help="--from: play at the recorded pace"),
    align: str = typer.Option("gscan", "--align", help="depth-to-colour alignment: gscan|librealsense (rs.align)"),
    preview: bool | None = typer.Option(None, "--preview/--no-preview",
                                           help="live preview in the browser (default: on live, off with --from)"),
    host: str = typer.Option("127.0.0.1", "--host", help="preview address to bind"),
    port: int = typer.Option(8080, "--port", min=1, max=65535, help="preview port"),
    json_out: bool = typer.Option(False, "--json", help="print one JSON object on stdout"),
    verbose: bool = typer.Option(False, "-v", "--verbose", help="log progress details to stderr"),
) -> None:
    """Record a capture folder from a RealSense camera (or a recording): the frames that moved enough, or every Nth.

    Ctrl+C ends the capture; the folder then holds the frames kept so far, a capture `gscan scan` reads."""
    import signal
    import threading
    from dataclasses import replace

    _setup_logging(verbose)
    from gscan.capture import CameraOptions, CaptureOptions, MotionParams, RealSenseCamera, run_capture

    if (width is None) != (height is None):
        raise UsageError(None, "--width and --height go together")
    if align not in ("gscan", "librealsense"):
        raise UsageError(None, f"--align must be gscan or librealsense, not {align!r}")
    opts = CaptureOptions(every=every, motion=replace(MotionParams(), min_angle_deg=min_motion), max_frames=max_frames)
    camera = RealSenseCamera(from_file, CameraOptions(width=width, height=height, fps=fps, real_time=real_time,
                                                      align=align))
    show = preview if preview is not None else from_file is None
    viewer = None
    if show:
        from gscan.capture.record import check_capture_output
        from gscan.viewer.capture_preview import CapturePreview

        check_capture_output(output)  # a bad output or a missing camera is named before the preview starts
        camera.check()
        viewer = CapturePreview(host, port)
        _say("preview at ", (viewer.url, "bold"))
    stop = threading.Event()

    def on_sigint(signum: int, frame: Any) -> None:  # the first Ctrl+C ends the capture; a second one aborts
        stop.set()
        signal.signal(signal.SIGINT, signal.default_int_handler)

    previous = signal.signal(signal.SIGINT, on_sigint)
    try:
        result = run_capture(camera, output, opts, stop=stop, on_frame=viewer.update if viewer else None)
    except KeyboardInterrupt:
        _say_interrupted("interrupted: nothing was written")
        raise
    finally:
        signal.signal(signal.SIGINT, previous)
        if viewer is not None:
            viewer.stop()
    if json_out:
        _print_json(result.to_json())
        return
    how = "stopped: " if result.interrupted else ""
    _say(f"{how}captured {len(result.kept)} frames (of {result.seen} seen) into {result.output}; "
         f"{result.covered} of {result.directions} viewing directions covered")


# -------------------------------------------------------------------------------------------- demo


@app.command()
def demo(
    no_view: bool = typer.Option(False, "--no-view", help="do not open the viewer at the end"),
    output: Path = typer.Option(Path("demo-output"), "-o", "--output", help="folder for the demo's template"),
    port: int = typer.Option(8080, "--port", min=1, max=65535, help="viewer port"),
) -> None:
    """Scan the bundled sample, estimate its held-back frames, then open the viewer."""
    _import_holding_ctrl_c(*_SCAN_IMPORTS)
    from rich.table import Table

    from gscan.demo import SAMPLES, check_demo_output, evaluate_sample, scan_sample
    from gscan.progress import RichProgress

    check_demo_output(output)  # before the first step is announced: only the demo's own template is replaced

    _say(("1/3 scanning", "bold"), f" {SAMPLES / 'capture'} -> {output / 'sample.gscan'}")
    with RichProgress(err) as progress:
        result = scan_sample(output, progress)
    _print_scan_summary(result)
    _say(("2/3 estimating", "bold"), " the held-back frames")
    table = Table(title="pose estimation on held-back frames (errors against ground truth)")
    for col in ("frame", "found", "rot err (deg)", "trans err (mm)", "ADD (mm)", "GMatch pairs", "time (ms)"):
        table.add_column(col, justify="right")
    held = evaluate_sample(result.output)
    for r in held:
        table.add_row(r.name, "yes" if r.found else "no", f"{r.rot_err_deg:.2f}", f"{r.trans_err_mm:.1f}",
                      f"{r.add_mm:.1f}", str(r.n_matches), f"{r.total_ms:.0f}")
    err.print(table)
    found = [r for r in held if r.found]
    worst = "" if not found else (f"; largest errors {max(r.rot_err_deg for r in found):.2f} deg, "
                                  f"{max(r.trans_err_mm for r in found):.1f} mm, "
                                  f"ADD {max(r.add_mm for r in found):.1f} mm")
    _say(f"held-back frames: {len(found)}/{len(held)} found{worst}")
    if no_view:
        _say(("3/3", "bold"), f" viewer skipped; run `gscan view {result.output}`")
        return
    from gscan.viewer.app import run_viewer

    _say(("3/3 viewer", "bold"))
    run_viewer(result.output, port=port,
               on_ready=lambda url: _say("viewer ready at ", (url, "bold"), " (Ctrl+C to stop)"))


_interrupt_said = False


def _say_interrupted(line: str) -> None:
    global _interrupt_said
    err.print(printable(line), markup=False, highlight=False, soft_wrap=True)
    _interrupt_said = True


def main() -> None:
    """Console entry point: maps errors to exit codes (2 bad input, 1 internal)."""
    if sys.stdout is None:  # started with stdout closed (`gscan ... >&-`): what it prints goes nowhere
        sys.stdout = open(os.devnull, "w")  # noqa: SIM115 - lives as long as the process
    # OpenCV's own log lines ("[ERROR:0@0.1] global grfmt_png.cpp ... readHeader") would precede the one
    # error line gscan prints for an undecodable image; it is read before cv2 is first imported
    os.environ.setdefault("OPENCV_LOG_LEVEL", "SILENT")
    try:
        rc = app(standalone_mode=False)
        if rc == 130 and not _interrupt_said:  # typer turns Ctrl+C into exit code 130 without a word
            err.print("interrupted")
        sys.exit(rc if isinstance(rc, int) else 0)
    except _cx.NoArgsIsHelpError as e:  # bare `gscan` or a bare group: show the help
        sys.stdout.write(e.ctx.get_help() + "\n" if e.ctx else "")
        sys.exit(0)
    except _cx.UsageError as e:  # a wrong option value or a missing argument: one line, exit 2
        cmd = e.ctx.command_path if e.ctx else "gscan"
        err.print(printable(f"error: {cmd}: {e.format_message()} (see `{cmd} --help`)"), markup=False,
                  highlight=False, soft_wrap=True)
        sys.exit(2)
    except typer.Abort:
        err.print("aborted")
        sys.exit(130)
    except GscanError as e:  # InputError and the other deliberate errors: bad input
        err.print(error_line(e), markup=False, highlight=False, soft_wrap=True)
        sys.exit(2)
    except KeyboardInterrupt:
        err.print("interrupted")
        sys.exit(130)
    except OSError as e:
        # the file system refused a write the library does not own (numba's kernel cache on first use, a
        # temporary file): disk full, quota, file size limit or a read-only file system, named as the writers
        # name it; any other OSError is an internal error
        if e.errno not in _RESOURCE_ERRNOS or os.environ.get("GSCAN_DEBUG"):
            _internal_error(e)
        from gscan.io.output import describe_os_error  # on this path only: the CLI starts without gscan.io

        err.print(printable(f"error: {e.filename or 'writing a file'}: {describe_os_error(e)}"), markup=False,
                  highlight=False, soft_wrap=True)
        sys.exit(2)
    except Exception as e:  # noqa: BLE001 - the last resort: one line, exit 1
        _internal_error(e)


_RESOURCE_ERRNOS = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS)


def _internal_error(e: Exception) -> NoReturn:
    """Exit 1 with one line naming the unexpected error (its traceback with GSCAN_DEBUG=1)."""
    if os.environ.get("GSCAN_DEBUG"):
        raise e
    msg = " ".join(f"{e.__class__.__name__}: {e}".split())
    err.print(printable(f"internal error: {msg} (set GSCAN_DEBUG=1 for the traceback)"), markup=False,
              soft_wrap=True)
    sys.exit(1)


if __name__ == "__main__":
    main()
