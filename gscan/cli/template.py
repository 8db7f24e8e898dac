"""Commands that read or edit a stored template: `info`, `poses`, `grasp add`, `grasp list`, `export`."""
from __future__ import annotations

from pathlib import Path

import typer

from gscan.cli.choices import ExportFormat
from gscan.cli.output import (
    camera_line,
    coverage_lines,
    err,
    format_pose,
    line,
    object_line,
    part_lines,
    print_json,
    symmetry_texts,
)
from gscan.cli.texts import JSON_HELP


def poses(
    template: Path = typer.Argument(..., help="template database"),
    json_out: bool = typer.Option(False, "--json", help=JSON_HELP),
) -> None:
    """Camera pose T_obj_cam of every registered input frame in the template frame (`--json`: the 4x4 matrices;
    otherwise translation and rotation angle / axis, one line per frame)."""
    from gscan.template.reports import template_poses

    result = template_poses(template)
    if json_out:
        print_json(result.to_json())
        return
    err.print("T_obj_cam (camera pose in the template frame) of each registered frame:")
    for name, T in result.frames.items():
        line(f"{name}: {format_pose(T)}")
    for name in result.unregistered:
        line(f"{name}: unregistered: {result.unregistered_reasons[name]}")
    for name, why in result.skipped_by_selection.items():
        line(f"{name}: skipped by frame selection: {why}")
    part_lines(result.parts)


def info(
    template: Path = typer.Argument(..., help="template database"),
    json_out: bool = typer.Option(False, "--json", help=JSON_HELP),
) -> None:
    """Summary of a template database (works on partial ones too). `mesh` counts the stored mesh's vertices,
    triangles and open (boundary) edges: a scanned mesh is open where the support plane cut it; the exports
    close it unless `export --keep-holes`."""
    from gscan.template.reports import template_info

    out = template_info(template).to_json()
    if json_out:
        print_json(out)
        return
    for k, v in out.items():  # a line per key of the JSON object, in its order
        if k == "unregistered_reasons":
            for name, reason in v.items():
                line(f"unregistered {name}: {reason}")
            continue
        if k == "parts":
            part_lines(v)
            continue
        if k == "selection":
            if v.get("skipped"):
                why = "; ".join(f"{n} frames {w}" for w, n in v["reasons"].items())
                line(f"frame selection: {v['kept']} frames kept, {v['skipped']} skipped ({why})")
            continue
        if k == "camera":
            if v is not None:
                tag, text = camera_line(v)
                line(f"{tag[0]}{text}")
            continue
        if k == "coverage":
            coverage_lines(v)
            continue
        if k == "symmetries":
            for text in symmetry_texts(v):
                line(f"symmetry: {text}")
            continue
        if k == "object":
            if v is not None:
                line(object_line(v))
            continue
        if k == "mesh" and v is not None:
            holes = " (export closes them; --keep-holes keeps them)" if v["open_edges"] else ", watertight"
            v = f"{v['vertices']} vertices, {v['triangles']} triangles, {v['open_edges']} open edges{holes}"
        line(f"{k}: {v}")


def export(
    template: Path = typer.Argument(..., help="template database"),
    format: ExportFormat = typer.Option(..., "--format", help="what to write (see the README's Exports)"),
    output: Path = typer.Option(..., "-o", "--output", help="output file or folder"),
    force: bool = typer.Option(False, "--force", help="replace an existing output"),
    keep_holes: bool = typer.Option(False, "--keep-holes", help="leave the mesh open where the scan saw no surface "
                                    "(by default the bottom the support plane cut off is closed: a watertight model)"),
    json_out: bool = typer.Option(False, "--json", help=JSON_HELP),
) -> None:
    """Export a template for other tools."""
    from gscan.exporters import export as do_export

    written = do_export(template, format.value, output, force=force, close=not keep_holes)
    if json_out:
        print_json(written.to_json())
    else:
        line(f"wrote {written}")


def grasp_add(
    template: Path = typer.Argument(..., help="template database"),
    name: str = typer.Option(..., "--name", help="grasp name"),
    pose: Path = typer.Option(..., "--pose", help='JSON file: {"T": 4x4} or a bare 4x4 list (object frame, metres)'),
) -> None:
    """Store a named grasp pose T_obj_grasp in the template."""
    from gscan.io import read_pose_file
    from gscan.template.reports import store_grasp

    store_grasp(template, name, read_pose_file(pose))
    line(f"grasp {name!r} stored in {template}")


def grasp_list(
    template: Path = typer.Argument(..., help="template database"),
    json_out: bool = typer.Option(False, "--json", help=JSON_HELP),
) -> None:
    """List the grasp poses stored in a template."""
    from gscan.template.reports import template_grasps

    result = template_grasps(template)
    if json_out:
        print_json(result.to_json())
        return
    if not result.grasps:
        err.print("no grasps")
    for k, T in result.grasps.items():
        line(f"{k}: T_obj_grasp {format_pose(T)}")
