"""A batch task: one job (a capture to scan, a template to evaluate) run in a child process of the Ray worker.

`run_job(job, tracker)` is the function each Ray task runs. It records the attempt with the tracker actor,
runs `python -m gscan.batch.child` (see that module) with one thread per pool, waits for it with `os.wait4`
and returns the child's result with:
- `seconds`: the child's wall time;
- `peak_rss_bytes`: the child's peak resident memory (its own ru_maxrss from wait4, that process alone: the
  scan's numpy, OpenCV and open3d buffers included, the Ray worker's memory not);
- `attempts` (1 for the first) and `node` (the host name).
A child that ends without a result (killed by a signal, crashed) gives a failure naming the signal. A job's
fields are plain JSON values (they cross to the child as a file).
"""
from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from gscan.batch.runtime import with_package_path
from gscan.threads import THREAD_ENV

LOG_TAIL = 300  # characters of the child's last log line kept in a failure's message


def run_job(job: dict[str, Any], tracker: Any = None) -> dict[str, Any]:
    """Run `job` in a child process (see the module docstring); never raises for a failure of the job."""
    attempt = _start(tracker, job["key"])
    if job["kind"] == "scan" and job["force"] and attempt > 1 and _partial(Path(job["output"])):
        # an earlier attempt of this task was lost with its worker after it created the template: continue it
        job = job | {"force": False, "resume": True}
    try:
        out = run_child(job)
    finally:
        if tracker is not None:
            tracker.ended.remote(job["key"])  # no reply awaited
    return out | {"attempts": attempt, "node": socket.gethostname()}


def _start(tracker: Any, key: str) -> int:
    if tracker is None:
        return 1
    try:
        import ray

        return int(ray.get(tracker.started.remote(key), timeout=60))
    except Exception:  # noqa: BLE001 - the count is for the report; the job runs without it
        return 1


def _partial(path: Path) -> bool:
    from gscan.errors import InputError
    from gscan.template.db import TemplateDB

    if not path.is_file():
        return False
    try:
        with TemplateDB.open(path, require_complete=False) as db:
            return db.status == "partial"
    except InputError:
        return False


def child_env() -> dict[str, str]:
    """The child's environment: this one, with one thread per pool and this gscan first on the path."""
    return with_package_path(dict(os.environ)) | THREAD_ENV | {"OPENCV_LOG_LEVEL": "SILENT"}


def run_child(job: dict[str, Any]) -> dict[str, Any]:
    """The child's result for `job` (see the module docstring), with its seconds and peak memory."""
    work = Path(tempfile.mkdtemp(prefix="gscan-job-"))
    try:
        request, result, log = work / "request.json", work / "result.json", work / "child.log"
        req = job | {"parent_pid": os.getpid()}
        if job["kind"] == "eval":
            req["csv"] = str(work / "results.csv")
        request.write_text(json.dumps(req), encoding="utf-8")
        t0 = time.monotonic()
        with open(log, "wb") as log_file:
            proc = subprocess.Popen([sys.executable, "-m", "gscan.batch.child", str(request), str(result)],
                                    stdin=subprocess.DEVNULL, stdout=log_file, stderr=subprocess.STDOUT, cwd=work,
                                    env=child_env())
            try:
                _, status, usage = os.wait4(proc.pid, 0)
            except BaseException:  # interrupted (a cancelled task): the child goes with it
                proc.kill()
                proc.wait()
                raise
            proc.returncode = os.waitstatus_to_exitcode(status)
        seconds = time.monotonic() - t0
        peak = int(usage.ru_maxrss) * (1 if sys.platform == "darwin" else 1024)  # bytes on macOS, KiB elsewhere
        out = None
        if result.is_file():
            try:
                out = json.loads(result.read_text(encoding="utf-8"))
            except ValueError:
                out = None
        if out is None:
            out = {"ok": False, "fix": None, **_no_result(job, proc.returncode, log)}
        return out | {"seconds": seconds, "peak_rss_bytes": peak, "exit_code": proc.returncode}
    finally:
        shutil.rmtree(work, ignore_errors=True)


def _no_result(job: dict[str, Any], code: int, log: Path) -> dict[str, str]:
    """error_kind and error of a child that ended without writing its result."""
    what = f"the {'scan' if job['kind'] == 'scan' else 'evaluation'} process"
    subject = job.get("source") or job.get("template")
    if code < 0:
        try:
            name = signal.Signals(-code).name
        except ValueError:
            name = f"signal {-code}"
        if -code == signal.SIGKILL:
            return {"error_kind": "killed", "error": f"{subject}: {what} was killed (SIGKILL: by the system's "
                                                     "out-of-memory killer or a user)"}
        return {"error_kind": "crashed", "error": f"{subject}: {what} crashed ({name}){_last_line(log)}"}
    return {"error_kind": "crashed", "error": f"{subject}: {what} ended with exit code {code} and no "
                                              f"result{_last_line(log)}"}


def _last_line(log: Path) -> str:
    try:
        lines = [ln.strip() for ln in log.read_text(encoding="utf-8", errors="replace").splitlines() if ln.strip()]
    except OSError:
        return ""
    return f": {' '.join(lines[-1].split())[:LOG_TAIL]}" if lines else ""
