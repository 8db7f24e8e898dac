"""`run_batch(captures_dir, templates_dir)`: scan every capture under a folder into a template each, on Ray.

Captures: every folder directly under `captures_dir` (an RGB-D folder in any layout `gscan scan` reads, or a
rosbag2 folder) and every recording file (.bag, .db3, .mcap); hidden entries, other files and the templates
folder itself are left out. Capture `NAME` (a recording `NAME.bag`) becomes `templates_dir/NAME.gscan`.

Each capture is decided first:
- its template is complete: "skipped" (its facts are read from the template; not scanned again) unless
  `force`; a complete template scanned from another capture is refused (it is not this capture's);
- its template is partial (an interrupted scan): the task resumes it ("resumed");
- otherwise the task scans it ("scanned"); an existing file that is not a template is refused;
and the captures left are scanned as one Ray task each (`gscan.batch.jobs`), `scan()` in a child process
(the code of `gscan scan`). A capture that fails (bad input, a crash, a worker lost on every attempt) is
reported and the others go on. Each task's failure leaves no half-written template: a new scan that fails
removes its output, a killed one leaves a partial template the next run resumes.

The report (`BatchReport`, also written to `templates_dir/batch.json` and `batch.csv`) has a row per capture:
status, frames, registered, the unregistered frames with their reasons, keyframes, seconds, peak memory of
the scan's process, and with ground truth in the capture the ATE and the frames registered at a wrong pose
(`gscan.batch.facts`); a failure's one-line error.
"""
from __future__ import annotations

import errno
import logging
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from gscan.batch.driver import (
    BatchMonitor,
    BatchState,
    batch_exit_code,
    fill_row,
    gscan_version,
    job_row_json,
    run_on_ray,
    write_csv,
    write_json,
)
from gscan.batch.facts import ground_truth_check, template_facts
from gscan.batch.runtime import MAX_RETRIES, TASK_CPUS, require_ray
from gscan.errors import InputError
from gscan.io.layouts import detect_format
from gscan.io.output import check_not_input, check_output_path, describe_os_error, real_path
from gscan.io.recordings.kinds import SUFFIXES, recording_format
from gscan.scanning.config import ScanConfig, load_config
from gscan.template.db import TemplateDB

log = logging.getLogger(__name__)

REPORT_JSON, REPORT_CSV = "batch.json", "batch.csv"
STATUSES = ("scanned", "resumed", "skipped", "failed")
# what a scan job's result gives its row (`gscan.batch.child`)
ROW_KEYS = ("frames", "registered", "unregistered", "unregistered_reasons", "keyframes", "mode", "ground_truth",
            "threads")
CSV_HEADER = ("name", "status", "attempts", "frames", "registered", "unregistered", "keyframes", "seconds",
              "peak_rss_mb", "gt_frames", "ate_rmse_mm", "wrong_frames", "error", "unregistered_reasons", "input")


@dataclass
class Capture:
    """A capture of the batch: its name, its folder or recording, its template."""

    name: str
    source: Path
    output: Path
    problem: str | None = None  # why the entry cannot be read (a loop of links): its row fails with it


@dataclass
class CaptureRow:
    """The report's row of one capture (see the module docstring); sizes in bytes, times in seconds, the ATE
    in metres. `error_kind`: "input" (bad input), "internal", "crashed", "killed" or "lost"; `fix`: a key of
    gscan.errors.FIXES (the CLI names its option)."""

    name: str
    input: str
    output: str
    status: str
    attempts: int = 0
    frames: int | None = None
    registered: int | None = None
    unregistered: list[str] = field(default_factory=list)
    unregistered_reasons: dict[str, str] = field(default_factory=dict)
    keyframes: int | None = None
    mode: str | None = None
    seconds: float = 0.0
    peak_rss_bytes: int | None = None
    ground_truth: dict[str, Any] | None = None
    error: str | None = None
    error_kind: str | None = None
    fix: str | None = None
    node: str | None = None
    threads: dict[str, int | None] | None = None

    @property
    def ok(self) -> bool:
        return self.status != "failed"

    def to_json(self) -> dict[str, Any]:
        return job_row_json(self)

    def csv_row(self) -> list[Any]:
        gt = self.ground_truth or {}
        ate = gt.get("ate_rmse_m")
        j = self.to_json()
        return [self.name, self.status, self.attempts, _blank(self.frames), _blank(self.registered),
                len(self.unregistered), _blank(self.keyframes), f"{self.seconds:.2f}", _blank(j["peak_rss_mb"]),
                _blank(gt.get("gt_frames")), "" if ate is None else f"{1000 * ate:.3f}",
                " ".join(gt.get("wrong_frames", [])) if gt else "", self.error or "",
                "; ".join(f"{n}: {r}" for n, r in self.unregistered_reasons.items()), self.input]


def _blank(x: Any) -> Any:
    return "" if x is None else x


@dataclass
class BatchReport:
    """The batch's rows (in capture order) and where it ran; `exit_code` as the CLI's: 0 when every capture
    succeeded, 2 when some had bad input and none failed otherwise, 1 otherwise."""

    captures_dir: Path
    templates_dir: Path
    rows: list[CaptureRow]
    seconds: float
    runtime: str | None  # "local", the cluster's address, or None when nothing had to be scanned
    capacity: int

    def count(self, status: str) -> int:
        return sum(r.status == status for r in self.rows)

    @property
    def exit_code(self) -> int:
        return batch_exit_code(self.rows)

    def summary(self) -> dict[str, Any]:
        done = [r for r in self.rows if r.status in ("scanned", "resumed")]
        peaks = [r.peak_rss_bytes for r in done if r.peak_rss_bytes]
        return {"captures": len(self.rows), **{s: self.count(s) for s in STATUSES},
                "failed_input": sum(r.status == "failed" and r.error_kind == "input" for r in self.rows),
                "exit_code": self.exit_code, "seconds": round(self.seconds, 3),
                "task_seconds": round(sum(r.seconds for r in done), 3),
                "peak_rss_mb_max": round(max(peaks) / 2**20, 1) if peaks else None,
                "runtime": self.runtime, "cpus": self.capacity, "cpus_per_task": TASK_CPUS,
                "max_retries": MAX_RETRIES, "captures_dir": str(self.captures_dir),
                "templates_dir": str(self.templates_dir)}

    def to_json(self) -> dict[str, Any]:
        """The `batch --json` object: {"summary": {...}, "captures": [row, ...]}."""
        return {"summary": self.summary(), "captures": [r.to_json() for r in self.rows]}


# ------------------------------------------------------------------------------------------ captures
def find_captures(captures_dir: str | Path, templates_dir: str | Path) -> list[Capture]:
    """The captures under `captures_dir` (see the module docstring), by name. InputError when the folder is
    missing, is itself a capture, holds none, or two captures would write one template."""
    captures_dir, templates_dir = Path(captures_dir), Path(templates_dir)
    if not captures_dir.is_dir():
        raise InputError(captures_dir, "captures folder not found" if not captures_dir.exists() else
                         "is not a folder (expected a folder of capture folders and recordings)")
    try:
        kind = detect_format(captures_dir)
    except InputError:
        kind = None
    if kind is not None:
        raise InputError(captures_dir, f"is a capture itself ({kind} layout), not a folder of captures: scan it "
                         "alone, or put it in a folder")
    out_resolved = real_path(templates_dir)
    found: dict[str, Capture] = {}
    for entry in sorted(captures_dir.iterdir(), key=lambda p: p.name):
        if entry.name.startswith(".") or real_path(entry) == out_resolved:
            continue
        problem = broken_link(entry)
        if problem is not None:  # reported as a failed capture, never followed
            found[entry.name] = Capture(entry.name, entry, templates_dir / f"{entry.name}.gscan", problem)
            continue
        if entry.is_dir():
            name = entry.name
        elif entry.is_file() and recording_format(entry) is not None and entry.suffix.lower() in SUFFIXES:
            name = entry.stem
        else:
            continue
        if name in found:
            raise InputError(entry, f"would write the same template as {found[name].source.name} "
                             f"({name}.gscan): rename one of them")
        found[name] = Capture(name, entry, templates_dir / f"{name}.gscan")
    if not found:
        raise InputError(captures_dir, "holds no capture folder or recording (.bag, .db3, .mcap)")
    return list(found.values())


def broken_link(entry: Path) -> str | None:
    """Why the link `entry` leads nowhere (a loop of links, a missing target); None for anything else."""
    if not entry.is_symlink():
        return None
    try:
        entry.stat()
    except OSError as e:
        if e.errno == errno.ELOOP:
            return "is a loop of symbolic links (following it never ends)"
        if e.errno == errno.ENOENT:
            return f"is a symbolic link to {os.readlink(entry)}, which does not exist"
        return f"is a symbolic link that cannot be followed ({describe_os_error(e)})"
    return None


def check_templates_dir(captures_dir: Path, templates_dir: Path) -> None:
    """InputError naming both when the templates folder is, contains or lies inside the captures folder's
    entry (`check_not_input`); a new folder directly in the captures folder is allowed (it is no capture and
    the walk passes it), an existing capture there is not."""
    check_not_input(templates_dir, [captures_dir], inside_ok=True)
    caps, out = real_path(captures_dir), real_path(templates_dir)
    if caps not in out.parents:
        return
    parts = out.relative_to(caps).parts
    entry = caps / parts[0]
    if len(parts) > 1 or (entry.exists() and (not entry.is_dir() or _is_capture(entry))):
        check_not_input(templates_dir, [captures_dir / parts[0] if entry.exists() else captures_dir])


def _is_capture(folder: Path) -> bool:
    """Whether `folder` is in a layout `gscan scan` reads."""
    try:
        detect_format(folder)
    except InputError:
        return False
    return True


def _plan(cap: Capture, force: bool, cfg: ScanConfig) -> CaptureRow | None:
    """The row of a capture decided without a task (skipped, or refused); None when it is scanned."""
    row = CaptureRow(cap.name, str(cap.source), str(cap.output), "failed")
    if cap.problem is not None:
        row.error, row.error_kind, row.fix = str(InputError(cap.source, cap.problem)), "input", None
        return row
    if force or not cap.output.exists():
        return None
    if not cap.output.is_file():
        row.error, row.error_kind, row.fix = str(InputError(cap.output, "is a folder, not a template")), "input", None
        return row
    try:
        with TemplateDB.open(cap.output, require_complete=False) as db:
            status, stored, stored_cfg = db.status, db.get_meta("input"), db.get_meta("config")
    except InputError as e:
        row.error, row.error_kind, row.fix = str(e), "input", "replace"
        return row
    if status != "complete":
        return None
    if stored != str(real_path(cap.source)):
        row.error, row.error_kind, row.fix = str(InputError(
            cap.output, f"is complete but was scanned from {stored}, not from {cap.source}")), "input", "replace"
        return row
    if not _same_config(stored_cfg, cfg):
        row.error, row.error_kind, row.fix = str(InputError(
            cap.output, "is complete but was scanned with another configuration")), "input", "replace"
        return row
    try:
        facts = template_facts(cap.output)
    except InputError as e:
        row.error, row.error_kind, row.fix = str(e), "input", "replace"
        return row
    gt = ground_truth_check(cap.source, facts)
    return CaptureRow(cap.name, str(cap.source), str(cap.output), "skipped", frames=facts.frames,
                      registered=facts.registered, unregistered=facts.unregistered,
                      unregistered_reasons=facts.unregistered_reasons, keyframes=facts.keyframes, mode=facts.mode,
                      ground_truth=None if gt is None else asdict(gt))


def _same_config(stored: Any, cfg: ScanConfig) -> bool:
    """Whether a template's stored configuration is `cfg` (settings added since take their defaults)."""
    try:
        return bool(ScanConfig.model_validate(stored).model_dump(mode="json") == cfg.model_dump(mode="json"))
    except (ValueError, TypeError):
        return False


def _row(cap: Capture, res: dict[str, Any]) -> CaptureRow:
    status = res.get("status", "failed") if res.get("ok") else "failed"
    return fill_row(CaptureRow(cap.name, str(cap.source), str(cap.output), status), res, ROW_KEYS)


def describe_row(row: CaptureRow) -> str:
    """One line about a finished capture, for the progress display."""
    if row.status == "failed":
        return row.error or "failed"
    parts = [f"{row.registered}/{row.frames} registered", f"{row.keyframes} keyframes"]
    gt = row.ground_truth
    if gt and gt.get("ate_rmse_m") is not None:
        parts.append(f"ATE {1000 * gt['ate_rmse_m']:.1f} mm")
        if gt.get("wrong_frames"):
            parts.append(f"{len(gt['wrong_frames'])} at a wrong pose")
    if row.status != "skipped":
        parts.append(f"{row.seconds:.1f} s")
        if row.peak_rss_bytes:
            parts.append(f"{row.peak_rss_bytes / 2**20:.0f} MiB")
    return ", ".join(parts)


# ------------------------------------------------------------------------------------------ the batch
def run_batch(captures_dir: str | Path, templates_dir: str | Path, *, config: ScanConfig | str | Path | None = None,
              address: str | None = None, workers: int | None = None, force: bool = False,
              monitor: BatchMonitor | None = None, write_report: bool = True) -> BatchReport:
    """Scan every capture under `captures_dir` into `templates_dir/NAME.gscan` (see the module docstring).

    Args:
        captures_dir: folder of capture folders and recordings.
        templates_dir: folder of the templates and of the report (made when missing).
        config: the scan configuration for every capture (a ScanConfig, a YAML file, or None: the defaults).
        address: None for a local Ray runtime sized to the machine; "auto" or "ray://HOST:PORT" for a cluster.
        workers: local runtime: its CPUs (default: all this process may use); cluster: at most this many tasks
            at once.
        force: scan every capture again, replacing complete templates.
        monitor: progress reporting (`gscan.batch.driver.BatchMonitor`).
        write_report: write batch.json and batch.csv into `templates_dir`.

    Returns:
        BatchReport: a row per capture, in name order.

    Raises:
        RayMissing: Ray is not installed.
        InputError: a missing or wrong captures folder, a templates folder that cannot be written, a
            configuration that does not validate, a cluster that cannot be reached. A capture's bad input is
            its row's error, not an exception.
    """
    t0 = time.monotonic()
    captures_dir, templates_dir = Path(captures_dir), Path(templates_dir)
    check_templates_dir(captures_dir, templates_dir)
    check_not_input(templates_dir, [config if isinstance(config, (str, Path)) else None])
    cfg = config if isinstance(config, ScanConfig) else load_config(config)
    if templates_dir.exists() and not templates_dir.is_dir():
        raise InputError(templates_dir, "is a file, expected the templates folder")
    check_output_path(templates_dir / REPORT_JSON)
    captures = find_captures(captures_dir, templates_dir)
    rows: dict[str, CaptureRow] = {}
    todo: list[Capture] = []
    for cap in captures:
        row = _plan(cap, force, cfg)
        if row is None:
            todo.append(cap)
        else:
            rows[cap.name] = row
    require_ray()  # after the input checks: a bad input is refused without loading Ray
    templates_dir.mkdir(parents=True, exist_ok=True)
    runtime, capacity = None, 0
    if todo:
        jobs = [{"kind": "scan", "key": c.name, "source": str(c.source), "output": str(c.output),
                 "config": cfg.model_dump(mode="json"), "force": force,
                 "resume": not force, "version": gscan_version()} for c in todo]
        by_name = {c.name: c for c in todo}

        def describe(job: dict, res: dict) -> tuple[str, str]:
            row = _row(by_name[job["key"]], res)
            return row.status, describe_row(row)

        results, runtime, capacity = run_on_ray(
            address, workers, jobs, describe, monitor, lambda cpus: _announce(monitor, rows, len(captures), len(todo),
                                                                              cpus),
            total=len(captures), done=len(rows), failed=sum(not r.ok for r in rows.values()))
        for name, res in results.items():
            rows[name] = _row(by_name[name], res)
    else:
        _announce(monitor, rows, len(captures), 0, 0)
    report = BatchReport(captures_dir, templates_dir, [rows[c.name] for c in captures], time.monotonic() - t0,
                         runtime, capacity)
    if write_report:
        write_json(templates_dir / REPORT_JSON, report.to_json())
        write_csv(templates_dir / REPORT_CSV, CSV_HEADER, [r.csv_row() for r in report.rows])
    return report


def _announce(monitor: BatchMonitor | None, rows: dict[str, CaptureRow], total: int, queued: int,
              capacity: int) -> None:
    """Tell the monitor about the captures decided without a task (skipped or refused)."""
    if monitor is None:
        return
    state = BatchState(total=total, queued=queued, capacity=max(1, capacity))
    for name, row in rows.items():
        state.done += 1
        state.failed += not row.ok
        monitor.finished(name, row.status, describe_row(row), state)
