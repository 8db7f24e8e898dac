"""`gscan scan`, `gscan template-from-mesh` and `gscan config dump`: a template from a capture or a CAD mesh,
and the configuration they (and the estimator) read."""
from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import typer

from gscan.cli.choices import ScanFormat, ScanMode
from gscan.cli.imports import SCAN_IMPORTS, STAGE_IMPORTS, ImportsAtFirstStage, import_holding_ctrl_c
from gscan.cli.output import (
    UsageError,
    camera_line,
    coverage_text,
    err,
    object_line,
    print_json,
    say,
    say_interrupted,
    setup_logging,
    symmetry_texts,
)
from gscan.cli.texts import DEPTH_INTRINSICS_HELP, DEPTH_TO_COLOR_HELP, JSON_HELP, RECORDING_HELP


def scan(
    inputs: list[Path] = typer.Argument(..., help="RGB-D folder (capture, Open3D, TUM or BOP layout) or "
                                        f"{RECORDING_HELP}; several: captures of one object (upright, upside down, "
                                        "...) joined into one template; a BOP dataset folder: its onboarding "
                                        "captures of --obj-id"),
    output: Path = typer.Option(..., "-o", "--output", help="template database to write (OBJ.gscan)"),
    format: ScanFormat = typer.Option("auto", "--format", help="input layout (auto: detected)"),
    intrinsics: Path | None = typer.Option(None, "--intrinsics", help="cam_K.txt or Open3D intrinsics JSON"),
    depth_scale: float | None = typer.Option(None, "--depth-scale", help="metres per raw depth unit"),
    mode: ScanMode = typer.Option("auto", "--mode", help="capture mode (auto: detected)"),
    no_segment: bool = typer.Option(False, "--no-segment", help="fuse the whole scene, not the object alone"),
    resume: bool = typer.Option(False, "--resume", help="continue an interrupted scan into OUTPUT"),
    append: bool = typer.Option(False, "--append", help="add the captures to the template OUTPUT (its views and "
                                "frame kept; left as it was when a capture cannot be joined to it)"),
    force: bool = typer.Option(False, "--force", help="replace an existing OUTPUT"),
    config: Path | None = typer.Option(None, "--config", help="YAML configuration (see `gscan config dump`)"),
    obj_id: int | None = typer.Option(None, "--obj-id", min=1, max=2**31 - 1,
                                      help="BOP folder: the object to scan (default: the first in scene_gt.json; "
                                      "a BOP dataset's onboarding captures: the only object there)"),
    color_topic: str | None = typer.Option(None, "--color-topic",
                                           help="recording: the colour image topic (default: detected)"),
    depth_topic: str | None = typer.Option(None, "--depth-topic",
                                           help="recording: the depth image topic (default: detected)"),
    depth_intrinsics: Path | None = typer.Option(None, "--depth-intrinsics", help=DEPTH_INTRINSICS_HELP),
    depth_to_color: Path | None = typer.Option(None, "--depth-to-color", help=DEPTH_TO_COLOR_HELP),
    roi: str | None = typer.Option(None, "--roi", metavar="X,Y,W,H", help="the object's box in the first frame "
                                   "(pixels; default: the object the views are centred on)"),
    mask: Path | None = typer.Option(None, "--mask", help="a mask image of the first frame, non-zero on the object "
                                     "(as BundleSDF and FoundationPose take)"),
    json_out: bool = typer.Option(False, "--json", help=JSON_HELP),
    verbose: bool = typer.Option(False, "-v", "--verbose", help="log progress details to stderr"),
) -> None:
    """Register every view of an RGB-D capture (or of several captures of one object) into one object frame and
    write a template database."""
    setup_logging(verbose)
    from gscan.io.camera import depth_camera_of
    from gscan.io.output import check_not_input
    from gscan.progress import RichProgress
    from gscan.scanning.config import load_config
    from gscan.scanning.opening import open_scan
    from gscan.scanning.options import ScanOptions

    if resume and force:
        raise UsageError(output, "--resume and --force exclude each other")
    if append and (resume or force):
        raise UsageError(output, f"--append and {'--resume' if resume else '--force'} exclude each other")
    if roi is not None and mask is not None:
        raise UsageError(mask, "--roi and --mask exclude each other")
    if mask is not None and no_segment:
        raise UsageError(mask, "--mask chooses the object to segment; --no-segment keeps the whole scene")
    if roi is not None and no_segment:
        raise UsageError(None, "--roi chooses the object to segment; --no-segment keeps the whole scene")
    if mask is not None and not mask.is_file():
        raise UsageError(mask, "--mask: not a file; expected a mask image of the first frame")
    check_not_input(output, [*inputs, intrinsics, config, depth_intrinsics, depth_to_color, mask])
    options = ScanOptions(format=format.value, intrinsics=intrinsics, depth_scale=depth_scale, mode=mode.value,
                          segment=not no_segment, resume=resume, append=append, force=force,
                          config=load_config(config),
                          obj_id=obj_id, color_topic=color_topic, depth_topic=depth_topic,
                          depth_camera=depth_camera_of(depth_intrinsics, depth_to_color),
                          roi=None if roi is None else parse_roi(roi), mask=mask)
    try:
        with RichProgress(err, enabled=not json_out or sys.stderr.isatty()) as progress:
            opened = open_scan(inputs, output, options)  # a bad input is refused before the pipeline loads
            try:
                import_holding_ctrl_c(*(m for m in SCAN_IMPORTS if m not in STAGE_IMPORTS))
            except BaseException:
                opened.discard()
                raise
            from gscan.scanning.pipeline import run_scan

            result = run_scan(inputs, output, options, progress=ImportsAtFirstStage(progress, STAGE_IMPORTS),
                              opened=opened)
    except KeyboardInterrupt:  # Ctrl+C: the partial database is kept for --resume (typer exits 130)
        say_interrupted(interrupted_scan_line(output, force))
        raise
    if json_out:
        print_json(result.to_json())
    else:
        print_scan_summary(result)


def parse_roi(text: str) -> tuple[int, int, int, int]:
    """--roi X,Y,W,H: four integers, a positive width and height (UsageError naming the option)."""
    parts = [p.strip() for p in text.split(",")]
    try:
        x, y, w, h = (int(p) for p in parts)
    except ValueError:
        raise UsageError(None, f"--roi must be X,Y,W,H (four integers, pixels), not {text!r}") from None
    if w <= 0 or h <= 0 or x < 0 or y < 0:
        raise UsageError(None, f"--roi {text}: X and Y must be at least 0, W and H positive (pixels)")
    return x, y, w, h


def interrupted_scan_line(output: Path, force: bool) -> str:
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


def print_scan_summary(result: Any) -> None:
    """A scan's human summary on stderr: the stage timings table, then a line per finding (`ScanResult`)."""
    from rich.table import Table

    table = Table(title="stage timings", show_header=True)
    table.add_column("stage")
    table.add_column("seconds", justify="right")
    for stage, sec in result.timings_s.items():
        table.add_row(stage, f"{sec:.2f}")
    err.print(table)
    say((str(result.output), "bold"), f": {result.registered}/{result.frames} frames registered "
        f"({result.mode}), edges {result.edges_accepted} accepted / {result.edges_rejected} rejected, "
        f"mesh {result.mesh_vertices} vertices / {result.mesh_triangles} triangles, "
        f"{result.keyframes} keyframes (the views estimate matches)")
    for text in coverage_text(result.coverage):
        say(text)
    kp = result.keypoints
    if kp and kp.get("source") != "sift":  # depth keypoints took part: which, why, and how many edges they decided
        why = (f"auto: median {kp['median_image_keypoints']:g} image keypoints per frame"
               if kp.get("chosen_by") == "auto" and kp.get("median_image_keypoints") is not None else "configured")
        say(("keypoints:", "bold"), f" {kp['source']} ({why}); {kp.get('depth_only_edges', 0)} accepted edges decided "
            "by the depth alone (a plain surface: no texture to check them)")
    elif kp and kp.get("object_image_keypoints") is not None:  # registered on the image, a plain object on it
        say(("keypoints:", "bold"), f" registered on the image's; the keyframes keep the depth's on the object too "
            f"(auto: median {kp['object_image_keypoints']:g} image keypoints on the object a keyframe)")
    mo = result.motion
    if mo and (mo["decided_edges"] or mo["bridges"]):  # the steady motion decided what the views could not
        bridged = ", ".join(f"{a} -> {b}" for a, b in mo["bridges"]) or "none"
        say(("steady motion:", "bold"), f" {mo['step_deg']:.1f} deg a frame (spread {mo['spread_deg']:.2f} deg / "
            f"{mo['spread_mm']:.1f} mm over {mo['steps']} steps); {mo['decided_edges']} refused edges accepted by "
            "it (loop closures it told from the object's turns, edges the shape's checks refused that it pins); "
            f"breaks bridged by its prediction, in a cycle that closes: {bridged}")
    cam = result.camera
    if cam is not None:
        say(*camera_line(cam))
    if result.object is not None:
        say(("object:", "bold"), " " + object_line(result.object).removeprefix("object: "))
    for line in result.damage:  # the recording's damaged records: damage, not missing frames
        say(("damaged recording:", "red"), f" {line}")
    sel = result.selection
    if sel.get("skipped"):  # frame selection: not failures, counted by reason
        why = "; ".join(f"{k} frames {w}" for w, k in sel["reasons"].items())
        say(("frame selection:", "bold"), f" {sel['kept']} frames kept, {sel['skipped']} skipped ({why}); "
            "`gscan poses --json` lists each")
    for name in result.unregistered:  # each with its reason (a frame that could not be read: why)
        what = "skipped frame" if name in result.problems else "unregistered frame"
        say((f"{what} {name}:", "yellow"), f" {result.unregistered_reasons.get(name, '')}")
    for cap in result.captures:  # a scan of several captures: how each was joined
        if cap["joined"]:
            turned = cap.get("joined_at_turn")
            say((f"capture {cap['name']}:", "bold"), f" {cap['registered']}/{cap['frames']} frames registered, "
                "joined to the template" + (f" ({turned} from the motion its view pairs agree on: a print repeated "
                                            "under that turn, the texture both share decided)" if turned else ""))
        else:
            say((f"capture {cap['name']}:", "yellow"), f" not joined to the template ({cap['reason']}); its frames "
                "are a separate part, nothing of it was fused")
    for k, part in enumerate(result.parts, 1):
        say((f"separate part {k}:", "yellow"), f" {len(part)} frames ({', '.join(part)}), not joined to the "
            "template's frames with confidence: scanned again with views between them, they can be")
    say(("symmetries:", "bold"), " " + "; ".join(symmetry_texts(result.symmetries.to_json())))


def template_from_mesh(
    mesh: Path = typer.Argument(..., help="textured mesh (OBJ with texture, PLY, GLB)"),
    output: Path = typer.Option(..., "-o", "--output", help="template database to write"),
    views: int = typer.Option(36, "--views", min=4, max=500, help="snapshots rendered around the mesh"),
    scale: float = typer.Option(1.0, "--scale", help="mesh units to metres (0.001 for millimetres)"),
    force: bool = typer.Option(False, "--force", help="replace an existing OUTPUT"),
    json_out: bool = typer.Option(False, "--json", help=JSON_HELP),
) -> None:
    """Render snapshots around a CAD mesh into a template database (mesh frame kept)."""
    from gscan.io.output import check_not_input

    if scale <= 0:
        raise UsageError(mesh, f"--scale must be positive, not {scale}")
    check_not_input(output, [mesh])
    from gscan.progress import RichProgress
    from gscan.scanning.cad import template_from_mesh as render_template

    with RichProgress(err, enabled=not json_out) as progress:
        result = render_template(mesh, output, n_views=views, scale=scale, force=force, progress=progress)
    if json_out:  # the `template-from-mesh --json` object (TemplateResult has no to_json: gscan.scanning.cad)
        print_json({"output": str(result.output), "views": result.views, "descriptor": result.descriptor,
                    "source": result.source, "extent_m": list(result.extent_m),
                    "symmetries": result.symmetries.to_json()})
    else:
        say((str(output), "bold"), f": {result.views} views rendered from {mesh}")


def config_dump() -> None:
    """Print the default configuration as commented YAML (the scan's sections, then `estimate:`)."""
    from gscan.estimate.settings import dump_estimate_defaults
    from gscan.scanning.config import dump_defaults

    sys.stdout.write(dump_defaults() + "\n" + dump_estimate_defaults())


_print_scan_summary = print_scan_summary  # its name as `gscan.cli._print_scan_summary` (tests/test_scan_stream.py)
