"""`gscan eval` (one template against its scenes), `gscan batch` (many captures into templates) and
`gscan batch-eval` (many templates against their scenes), the batches one Ray task per job."""
from __future__ import annotations

import contextlib
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import typer

from gscan.cli.output import UsageError, err, line, print_json, printable, say, say_interrupted, setup_logging
from gscan.cli.texts import JSON_HELP, RECORDING_HELP


def eval_cmd(
    template: Path = typer.Argument(..., help="template database of the object"),
    scenes: Path = typer.Argument(..., help="BOP scene folder, a folder of rendered scenes (capture layout), or "
                                  f"a {RECORDING_HELP}"),
    output: Path = typer.Option(..., "-o", "--output", help="BOP19 results CSV to write"),
    obj_id: int = typer.Option(1, "--obj-id", min=1, max=2**31 - 1, help="object id in scene_gt.json and in the CSV"),
    model: Path | None = typer.Option(None, "--model",
                                      help="object model for ADD/ADD-S/MSSD/MSPD (default: template mesh)"),
    gt_capture: Path | None = typer.Option(
        None, "--gt-capture", help="capture a scanned template came from, with ground-truth poses, to relate its "
        "frame to the ground truth's (default: the template's own input folder)"),
    max_instances: int | None = typer.Option(
        None, "--max-instances", min=1, help="instances sought in every image (default: each image's target "
        "count, from test_targets_bop19.json or the ground truth; one instance: the single estimate)"),
    no_icp: bool = typer.Option(False, "--no-icp", help="skip the ICP refinement"),
    force: bool = typer.Option(False, "--force", help="replace an existing output"),
    json_out: bool = typer.Option(False, "--json", help=JSON_HELP),
) -> None:
    """Run estimation over scenes, write BOP19 results CSV and print a metrics table."""
    from rich.table import Table

    from gscan.evaluate.bop19 import evaluate

    report = evaluate(template, scenes, output, obj_id=obj_id, model_path=model, refine=not no_icp, force=force,
                      gt_capture=gt_capture, max_instances=max_instances)
    if json_out:
        print_json(report.to_json())
        return
    counted = f"{len(report.rows)} instances, " if len(report.rows) != report.n_images else ""
    table = Table(title=f"{report.n_images} images, {counted}{report.n_found} found")
    table.add_column("metric")
    table.add_column("value", justify="right")
    for k, v in report.metrics.items():
        table.add_row(k, f"{v:.2f}")
    err.print(table)
    line(f"results written to {output}")


# the options of `batch` / `batch-eval` that address a failed job's InputError `fix`
_BATCH_FIXES = {"replace": "pass --force to scan it again", "restart": "pass --force to scan it again",
                "resume": "pass --force to scan it again", "finish": "run `gscan batch` on its captures to finish it"}


def _job_error_line(name: str, error: str | None, fix: str | None) -> str:
    hint = _BATCH_FIXES.get(fix or "")
    return printable(f"{name}: {error or 'failed'}" + (f"; {hint}" if hint else ""))


def _run_batch(noun: str, run: Callable[[Any], Any], json_out: bool, table: Callable[[Any], None] | None = None,
               interrupted: str | None = None) -> Any:
    """The report of `run(monitor)` (a batch), run under the live progress table with Ray's own messages kept
    off stdout; then its JSON (--json) or `table(report)`, and a line per failed job."""
    from gscan.batch.display import RichBatchMonitor

    try:
        with (contextlib.redirect_stdout(sys.stderr),  # Ray's own messages (a worker died, ...) are not the JSON
              RichBatchMonitor(err, live=err.is_terminal, escape=printable, noun=noun) as monitor):
            report = run(monitor if err.is_terminal or not json_out else None)
    except KeyboardInterrupt:
        if interrupted:
            say_interrupted(interrupted)
        raise
    if json_out:
        print_json(report.to_json())
    elif table is not None:
        table(report)
    for row in report.rows:
        if row.status == "failed":
            say(("failed ", "red"), _job_error_line(row.name, row.error, row.fix))
    return report


def batch(
    captures_dir: Path = typer.Argument(..., help="folder of capture folders and recordings (.bag, .db3, .mcap, "
                                        "rosbag2 folders; RealSense ones of every SDK)"),
    output: Path = typer.Option(..., "-o", "--output", help="folder of the templates (NAME.gscan) and of the report "
                                "(batch.json, batch.csv)"),
    config: Path | None = typer.Option(None, "--config", help="YAML configuration of every scan"),
    address: str | None = typer.Option(None, "--address", help="Ray cluster to run on: auto (the one started on "
                                       "this machine) or ray://HOST:PORT (default: a local Ray runtime)"),
    workers: int | None = typer.Option(None, "--workers", min=1, help="local runtime: its CPUs (default: all); "
                                       "cluster: at most this many scans at once"),
    force: bool = typer.Option(False, "--force", help="scan every capture again, replacing complete templates"),
    json_out: bool = typer.Option(False, "--json", help=JSON_HELP),
    verbose: bool = typer.Option(False, "-v", "--verbose", help="log details to stderr"),
) -> None:
    """Scan every capture under CAPTURES_DIR into OUTPUT/NAME.gscan, one Ray task per capture.

    A complete template is skipped, a partial one resumed; a failing capture does not stop the others.
    Exit code 0 when every capture succeeded, 2 when some had bad input, 1 otherwise."""
    setup_logging(verbose)
    from gscan.batch.scan import run_batch

    report = _run_batch("captures", lambda monitor: run_batch(captures_dir, output, config=config, address=address,
                                                              workers=workers, force=force, monitor=monitor),
                        json_out, table=_print_batch_table,
                        interrupted="interrupted: the templates finished are kept; run the command again to resume "
                                    "the others")
    s = report.summary()
    say((f"{s['captures']} captures", "bold"), f": {s['scanned']} scanned, {s['resumed']} resumed, "
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
    json_out: bool = typer.Option(False, "--json", help=JSON_HELP),
    verbose: bool = typer.Option(False, "-v", "--verbose", help="log details to stderr"),
) -> None:
    """Score many templates against their scenes as `gscan eval` does, one Ray task per pair, into one BOP19 CSV.

    Pairs: NAME.gscan in TEMPLATES_DIR with SCENES_DIR/NAME, or the rows of --manifest.
    Exit code 0 when every pair was evaluated, 2 when some had bad input, 1 otherwise."""
    setup_logging(verbose)
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
        say(("warning: ", "yellow"), w)
    if s["unpaired_templates"] or s["unpaired_scenes"]:
        say(("not paired: ", "yellow"), f"{len(s['unpaired_templates'])} templates without scenes, "
            f"{len(s['unpaired_scenes'])} scene folders without a template (see the objects report)")
    ar = s["pooled"]["AR"]
    say((f"{s['pairs']} pairs", "bold"), f": {s['evaluated']} evaluated, {s['failed']} failed; {s['found']}/"
        f"{s['images']} poses found, {s['wrong_accepted']} wrong accepted"
        + (f", AR {ar:.1f}" if ar is not None else "") + f" in {report.seconds:.1f} s; results in {output}, "
        f"metrics per object in {objects_paths(output)[0].name} and .csv")
    if report.exit_code:
        raise typer.Exit(report.exit_code)
