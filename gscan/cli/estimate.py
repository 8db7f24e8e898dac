"""`gscan estimate` (one frame) and `gscan track` (a sequence, the previous pose as a prior)."""
from __future__ import annotations

from pathlib import Path
from typing import Any

import typer

from gscan.cli.choices import format_choices
from gscan.cli.output import UsageError, err, format_matrix, line, print_json, say, setup_logging
from gscan.cli.texts import (
    DEPTH_INTRINSICS_HELP,
    DEPTH_TO_COLOR_HELP,
    ESTIMATE_CONFIG_HELP,
    JSON_HELP,
    RECORDING_HELP,
)


def load_query_frame(color: Path, depth: Path, intrinsics: Path, depth_scale: float, mask: Path | None,
                     depth_intrinsics: Path | None = None, depth_to_color: Path | None = None) -> Any:
    """The RGBDFrame of a query's files (`estimate`, `view --color`), its depth in the colour camera."""
    from gscan.io import load_frame
    from gscan.io.camera import depth_camera_of

    return load_frame(color, depth, intrinsics, depth_scale=depth_scale, mask_path=mask,
                      depth_camera=depth_camera_of(depth_intrinsics, depth_to_color))


def estimate(
    templates: list[Path] = typer.Argument(..., metavar="TEMPLATE...",
                                           help="template database(s) (OBJ.gscan); several need --all"),
    color: Path = typer.Option(..., "--color", help="colour image"),
    depth: Path = typer.Option(..., "--depth", help="16-bit depth image"),
    intrinsics: Path = typer.Option(..., "--intrinsics", help="cam_K.txt or Open3D intrinsics JSON"),
    depth_scale: float = typer.Option(0.001, "--depth-scale", help="metres per raw depth unit"),
    mask: Path | None = typer.Option(None, "--mask", help="restrict the search to this mask"),
    no_icp: bool = typer.Option(False, "--no-icp", help="skip the ICP refinement"),
    depth_intrinsics: Path | None = typer.Option(None, "--depth-intrinsics", help=DEPTH_INTRINSICS_HELP),
    depth_to_color: Path | None = typer.Option(None, "--depth-to-color", help=DEPTH_TO_COLOR_HELP),
    config: Path | None = typer.Option(None, "--config", help=ESTIMATE_CONFIG_HELP),
    all_instances: bool = typer.Option(False, "--all", help="every instance of every template (a list per "
                                       "template, best score first)"),
    max_instances: int | None = typer.Option(None, "--max-instances", min=1, help="with --all: instances sought "
                                             "per template at most (default: the configuration's "
                                             "estimate.instances.max_instances, 8)"),
    json_out: bool = typer.Option(False, "--json", help=JSON_HELP),
) -> None:
    """Estimate the object's pose T_cam_obj in a new RGB-D frame (--all: every instance of every template)."""
    from dataclasses import replace

    from gscan.estimate.settings import load_estimate_params
    from gscan.template.db import open_estimable

    if len(templates) > 1 and not all_instances:
        raise UsageError(templates[1], "several templates are estimated together with --all only")
    if max_instances is not None and not all_instances:
        raise UsageError(None, "--max-instances is a setting of --all")
    params = load_estimate_params(config)
    if max_instances is not None:
        params = replace(params, instances=replace(params.instances, max_instances=max_instances))
    # the templates and the query's files are read and checked before the estimator's stages load: a bad input
    # is answered without numba and scipy
    opened = [open_estimable(t) for t in templates]
    frame = load_query_frame(color, depth, intrinsics, depth_scale, mask, depth_intrinsics, depth_to_color)
    from gscan.estimate.estimator import Estimator

    estimators = [Estimator(t, params) for t in opened]
    if all_instances:
        estimate_every_instance(estimators, frame, not no_icp, json_out)
        return
    result = estimators[0].estimate(frame, mask=frame.mask, refine=not no_icp)
    out = result.to_json()
    if json_out:
        print_json(out)
        return
    if result.T_cam_obj is None:
        say(("object not found", "yellow"), f": {result.reason}")
    else:
        line(f"found: view {result.view}, {result.n_matches} matched keypoint pairs (GMatch's list), "
             f"score {result.score:.3f}")
        err.print("T_cam_obj =\n" + format_matrix(out["T_cam_obj"]))
        if result.symmetry is not None:
            line(f"the object looks the same under {result.symmetry}: this is the pose its fixed rule picks "
                 "(docs/method.md, Symmetric objects)")
        for name, T in out["grasps"].items():
            line(f"grasp {name}: T_cam_grasp =")
            err.print(format_matrix(T))
    err.print("timings (ms): " + ", ".join(f"{k} {v:.1f}" for k, v in out["timings_ms"].items()))


def estimate_every_instance(estimators: list[Any], frame: Any, refine: bool, json_out: bool) -> None:
    """`estimate --all`: every instance of every template (gscan.estimate.instances.estimate_templates), printed
    or as the JSON object {"templates": [Instances.to_json(), ...], "timings_ms": {"total"}}."""
    import time

    from gscan.estimate.instances import estimate_templates

    t0 = time.perf_counter()
    outs = estimate_templates(estimators, frame, frame.mask, refine)
    total = 1e3 * (time.perf_counter() - t0)
    if json_out:
        print_json({"templates": [o.to_json() for o in outs], "timings_ms": {"total": total}})
        return
    for o in outs:
        if not o.results:
            say((f"{o.template}: no instance found", "yellow"), f": {o.reason}")
        else:
            line(f"{o.template}: {len(o.results)} instance{'s' if len(o.results) > 1 else ''} found "
                 f"(search stopped: {o.stopped})")
        for k, r in enumerate(o.results):
            js = r.to_json()
            line(f"  instance {k + 1}: score {r.score:.3f}, {r.n_matches} matched keypoint pairs, "
                 f"{int(r.pixels.sum()) if r.pixels is not None else 0} pixels explained; T_cam_obj =")
            err.print(format_matrix(js["T_cam_obj"]))
        for r in o.refused:
            say(("  refused:", "yellow"), f" {r.reason}")
    err.print(f"timings (ms): total {total:.1f}")


def track(
    template: Path = typer.Argument(..., help="template database (OBJ.gscan)"),
    input_path: Path = typer.Argument(..., metavar="INPUT", help="RGB-D sequence: a folder in any layout scan "
                                      f"reads, or a {RECORDING_HELP}"),
    output: Path | None = typer.Option(
        None, "-o", "--output", help="folder for one T_cam_obj per frame (ob_in_cam 4x4 text) + summary.json"),
    format: str = typer.Option("auto", "--format", help="auto|capture|open3d|tum|bop"),
    intrinsics: Path | None = typer.Option(None, "--intrinsics", help="cam_K.txt or Open3D intrinsics JSON"),
    depth_scale: float | None = typer.Option(None, "--depth-scale", help="metres per raw depth unit"),
    depth_intrinsics: Path | None = typer.Option(None, "--depth-intrinsics", help=DEPTH_INTRINSICS_HELP),
    depth_to_color: Path | None = typer.Option(None, "--depth-to-color", help=DEPTH_TO_COLOR_HELP),
    force: bool = typer.Option(False, "--force", help="replace an existing OUTPUT"),
    all_instances: bool = typer.Option(False, "--all", help="every instance, each with its identity across frames "
                                       "(OUTPUT gets instance_<id>/ folders)"),
    max_instances: int | None = typer.Option(None, "--max-instances", min=1, help="with --all: identities at most "
                                             "(default: the configuration's estimate.instances.max_instances, 8)"),
    json_out: bool = typer.Option(False, "--json", help=JSON_HELP),
    verbose: bool = typer.Option(False, "-v", "--verbose", help="log progress details to stderr"),
) -> None:
    """Estimate the object's pose through an RGB-D sequence, the previous pose as a prior (--all: every instance,
    each with its identity)."""
    setup_logging(verbose)
    from dataclasses import replace

    from gscan.estimate.settings import load_estimate_params
    from gscan.io import check_output_path, open_sequence
    from gscan.io.camera import depth_camera_of
    from gscan.io.output import check_not_input
    from gscan.template.db import open_estimable

    if format not in format_choices():
        raise UsageError(None, f"--format must be one of {', '.join(format_choices())}, not {format!r}")
    if max_instances is not None and not all_instances:
        raise UsageError(None, "--max-instances is a setting of --all")
    if output is not None:  # refused before any work; never one of the inputs, whatever --force says
        check_not_input(output, [template, input_path, intrinsics, depth_intrinsics, depth_to_color])
        if output.exists() and (not output.is_dir() or any(output.iterdir())) and not force:
            raise UsageError(output, "exists and is not empty (pass --force to replace it)")
        check_output_path(output)
    params = load_estimate_params(None)
    if max_instances is not None:
        params = replace(params, instances=replace(params.instances, max_instances=max_instances))
    # the template and the sequence are opened and checked before the estimator's stages load (numba, scipy)
    tpl = open_estimable(template)
    seq = open_sequence(input_path, format, intrinsics=intrinsics, depth_scale=depth_scale,
                        depth_camera=depth_camera_of(depth_intrinsics, depth_to_color))
    from gscan.estimate import Estimator, InstanceTracker, track_sequence, write_poses

    estimator = Estimator(tpl, params)

    def report(step: Any) -> None:
        if json_out:
            return
        if step.instances is not None:
            held = ", ".join(f"{i.id} {i.status}" + (f" {i.result.score:.2f}" if i.result.T_cam_obj is not None
                                                     else "") for i in step.instances)
            n = sum(i.result.T_cam_obj is not None for i in step.instances)
            say(f"{step.frame}: ", f"{n} instance{'' if n == 1 else 's'} with a pose ({held or 'none'}; "
                f"{step.ms():.0f} ms)")
            return
        res = step.result
        what = f"score {res.score:.2f}" if res.T_cam_obj is not None else str(res.reason)
        style = "yellow" if step.status in ("lost", "refound") else None
        say(f"{step.frame}: ", (step.status, style) if style else step.status,
            f" ({what}, {res.timings_ms.get('total', 0.0):.0f} ms)")

    run = track_sequence(estimator, seq, on_step=report,
                         tracker=InstanceTracker(estimator) if all_instances else None)
    written = write_poses(run, output, force=force) if output is not None else None
    out = run.to_json(written)
    if json_out:
        print_json(out)
        return
    st = out["status"]
    say((f"{out['with_pose']}/{out['frames']} frames with a pose", "bold"),
        f": {st['found']} found, {st['tracked']} tracked, {st['refound']} re-found, {st['lost']} lost; "
        f"median {out['timings_ms']['median']:.0f} ms per frame"
        + (f"; poses written to {written}" if written is not None else ""))
    for inst in out.get("instances", []):
        line(f"instance {inst['id']}: {inst['frames']} frames with a pose ({inst['first']} to {inst['last']}), "
             f"lost in {len(inst['lost'])}, re-found in {len(inst['refound'])}")
    for damaged in out["damage"]:  # the recording's damaged records: damage, not missing frames
        say(("damaged recording:", "red"), f" {damaged}")
    for name, reason in out["unreadable"].items():
        say((f"skipped frame {name}:", "yellow"), f" {reason}")
