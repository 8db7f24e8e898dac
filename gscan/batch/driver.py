"""The driver side of a batch: submit the jobs as Ray tasks, collect their results, keep a monitor informed.

`run_jobs(runtime, jobs, ...)` submits every job (at most `runtime.limit` at once), waits for the results
(polling every POLL_S), turns a task lost with its worker after its retries into a failure ("lost"), and
reports a `BatchState` (done / running / failed / queued, ETA) to a `BatchMonitor` after each poll and each
result. Ctrl+C cancels the tasks still pending (their workers, and the children with them, are stopped);
what they wrote stays (a partial template is resumed by the next run).

The ETA is the work left (queued jobs and the rest of the running ones, at the mean time of the jobs finished
so far) spread over the CPUs the runtime offers.

`run_on_ray(address, workers, jobs, ...)` does that on a runtime of its own (`ray_runtime`). The report rows of
both batches (`CaptureRow`, `PairRow`) share what a job gives every row: `fill_row` copies a job's result
onto its row, `job_row_json` is a row's JSON, `batch_exit_code` the CLI's exit code over the rows.
"""
from __future__ import annotations

import contextlib
import csv
import io
import json
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Protocol, TypeVar

from gscan.batch.jobs import run_job
from gscan.batch.runtime import MAX_RETRIES, Runtime, ray_runtime
from gscan.io.output import Output

POLL_S = 0.5
R = TypeVar("R", bound="JobRow")


@dataclass
class BatchState:
    """Where a batch stands: jobs in all, done (finished, skipped ones included), of which failed, the
    running ones (key, seconds since their attempt started, attempt), queued, the ETA in seconds (None until
    a job has finished), seconds since the start, CPUs offered."""

    total: int
    done: int = 0
    failed: int = 0
    running: list[tuple[str, float, int]] = field(default_factory=list)
    queued: int = 0
    eta_s: float | None = None
    elapsed_s: float = 0.0
    capacity: int = 1


class BatchMonitor(Protocol):
    """What a batch reports while it runs (the CLI's live table)."""

    def update(self, state: BatchState) -> None:
        ...

    def finished(self, key: str, status: str, detail: str, state: BatchState) -> None:
        """Job `key` ended with `status` ("scanned", "failed", ...); `detail`: one line about it."""
        ...


class NullMonitor:
    def update(self, state: BatchState) -> None:
        pass

    def finished(self, key: str, status: str, detail: str, state: BatchState) -> None:
        pass


def _lost(job: dict[str, Any], e: BaseException) -> dict[str, Any]:
    """The failure of a task Ray gave up on (its worker died on every attempt, or it was cancelled)."""
    subject = job.get("source") or job.get("template")
    reason = " ".join(str(e).split())[:200]
    return {"ok": False, "error_kind": "lost", "fix": None,
            "error": f"{subject}: the task was lost with its worker process on each of its {MAX_RETRIES + 1} "
                     f"attempts ({e.__class__.__name__}{': ' + reason if reason else ''})"}


def _eta(queued: int, running: list[tuple[str, float, int]], durations: list[float], capacity: int) -> float | None:
    if not durations:
        return None
    mean = sum(durations) / len(durations)
    work = queued * mean + sum(max(mean - elapsed, 0.0) for _, elapsed, _ in running)
    slots = max(1, min(capacity, queued + len(running)))
    return work / slots


def run_jobs(rt: Runtime, jobs: Sequence[dict[str, Any]], describe: Callable[[dict, dict], tuple[str, str]],
             monitor: BatchMonitor | None = None, total: int | None = None, done: int = 0,
             failed: int = 0) -> dict[str, dict[str, Any]]:
    """Run `jobs` (each with a unique "key") as Ray tasks; returns key -> result (`gscan.batch.jobs`).
    `describe(job, result)` gives the (status, detail line) the monitor shows; `total`, `done` and `failed`
    count the batch's jobs decided without a task (skipped, refused) too."""
    ray = rt.ray
    monitor = monitor or NullMonitor()
    task = rt.remote(run_job)
    queue = list(jobs)
    pending: dict[Any, dict[str, Any]] = {}
    results: dict[str, dict[str, Any]] = {}
    durations: list[float] = []
    state = BatchState(total=len(jobs) if total is None else total, done=done, failed=failed,
                       queued=len(queue), capacity=rt.capacity)
    t0 = time.monotonic()
    try:
        while queue or pending:
            while queue and (rt.limit is None or len(pending) < rt.limit):
                job = queue.pop(0)
                ref = task.options(name=f"gscan {job['kind']} {job['key']}"[:200]).remote(job, rt.tracker)
                pending[ref] = job
            ready, _ = ray.wait(list(pending), num_returns=len(pending), timeout=POLL_S)
            attempts = _snapshot(rt)
            for ref in ready:
                job = pending.pop(ref)
                try:
                    res = ray.get(ref)
                except ray.exceptions.RayError as e:
                    res = _lost(job, e) | {"attempts": attempts["attempts"].get(job["key"], MAX_RETRIES + 1)}
                results[job["key"]] = res
                if "seconds" in res:
                    durations.append(float(res["seconds"]))
                state.done += 1
                state.failed += not res.get("ok")
                status, detail = describe(job, res)
                _fill(state, queue, pending, attempts, durations, t0)
                monitor.finished(job["key"], status, detail, state)
            _fill(state, queue, pending, attempts, durations, t0)
            monitor.update(state)
    except BaseException:
        for ref in pending:
            with contextlib.suppress(Exception):  # best effort: the runtime is shut down next
                ray.cancel(ref, force=True)
        raise
    return results


def run_on_ray(address: str | None, workers: int | None, jobs: Sequence[dict[str, Any]],
               describe: Callable[[dict, dict], tuple[str, str]], monitor: BatchMonitor | None,
               announce: Callable[[int], None], total: int | None = None, done: int = 0,
               failed: int = 0) -> tuple[dict[str, dict[str, Any]], str, int]:
    """`run_jobs` on `ray_runtime(address, workers)`: (key -> result, where it ran, the CPUs it offered).
    `announce(capacity)` runs once the runtime is up, before the first task (the monitor's first news)."""
    with ray_runtime(address, workers) as rt:
        announce(rt.capacity)
        results = run_jobs(rt, jobs, describe, monitor, total=total, done=done, failed=failed)
        return results, rt.where, rt.capacity


def _snapshot(rt: Runtime) -> dict[str, Any]:
    try:
        return dict(rt.ray.get(rt.tracker.snapshot.remote(), timeout=5))
    except Exception:  # noqa: BLE001 - progress only
        return {"running": {}, "attempts": {}}


def _fill(state: BatchState, queue: list, pending: dict, snap: dict[str, Any], durations: list[float],
          t0: float) -> None:
    keys = {job["key"] for job in pending.values()}
    state.running = sorted(((k, float(s), int(snap["attempts"].get(k, 1))) for k, s in snap["running"].items()
                            if k in keys), key=lambda r: -r[1])
    state.queued = len(queue) + len(keys) - len(state.running)
    state.eta_s = _eta(state.queued, state.running, durations, state.capacity)
    state.elapsed_s = time.monotonic() - t0


# ------------------------------------------------------------------------------------------ rows
class JobRow(Protocol):
    """What every report row holds about its job (`gscan.batch.jobs`): attempts, seconds, the peak memory of
    its process, the node, and a failure's one-line error, its kind and the key of its fix."""

    status: str
    attempts: int
    seconds: float
    peak_rss_bytes: int | None
    error: str | None
    error_kind: str | None
    fix: str | None
    node: str | None


def fill_row(row: R, res: dict[str, Any], ok_keys: Sequence[str]) -> R:
    """`row` with its job's result `res`: attempts, seconds, peak memory and node, then the job's own
    `ok_keys` when it succeeded, its error when it failed."""
    row.attempts, row.seconds = int(res.get("attempts", 1)), float(res.get("seconds", 0.0))
    row.peak_rss_bytes, row.node = res.get("peak_rss_bytes"), res.get("node")
    if res.get("ok"):
        for k in ok_keys:
            setattr(row, k, res.get(k))
    else:
        row.error, row.error_kind, row.fix = res.get("error"), res.get("error_kind"), res.get("fix")
    return row


def job_row_json(row: Any) -> dict[str, Any]:
    """A report row (a dataclass) as JSON: its fields, seconds rounded to the millisecond, the peak memory in
    MiB too (`peak_rss_mb`)."""
    d = asdict(row)
    d["peak_rss_mb"] = None if row.peak_rss_bytes is None else round(row.peak_rss_bytes / 2**20, 1)
    d["seconds"] = round(row.seconds, 3)
    return d


def batch_exit_code(rows: Sequence[JobRow]) -> int:
    """0 when no job failed, 2 when every failure was bad input, 1 otherwise (as the CLI's)."""
    failed = [r for r in rows if r.status == "failed"]
    if not failed:
        return 0
    return 2 if all(r.error_kind == "input" for r in failed) else 1


def gscan_version() -> str:
    """The driver's gscan version, which every job carries (a node with another refuses it)."""
    from gscan._version import __version__

    return __version__


# ------------------------------------------------------------------------------------------ reports
def write_json(path: Path, obj: Any) -> None:
    """Write `obj` as JSON to `path`, replacing the previous file only once the new one is complete."""
    with Output(path, force=True, kind=".json file path") as out:
        out.tmp.write_text(json.dumps(obj, indent=1) + "\n", encoding="utf-8")


def write_csv(path: Path, header: Sequence[str], rows: Sequence[Sequence[Any]]) -> None:
    """Write a CSV table (RFC 4180 quoting) to `path`, replacing the previous file only once complete."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(header)
    w.writerows(rows)
    with Output(path, force=True, kind=".csv file path") as out:
        out.tmp.write_text(buf.getvalue(), encoding="utf-8")
