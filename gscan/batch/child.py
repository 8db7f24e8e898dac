"""The child process a batch task runs one job in: `python -m gscan.batch.child REQUEST.json RESULT.json`.

A job is one capture to scan (`scan()`, the code of `gscan scan`, then the template's facts and its ground-truth
check) or one template to evaluate over scenes (`gscan.evaluate.bop19.evaluate`, the code of `gscan eval`).
Running it in a fresh process gives the task its own peak memory (the parent reads it from the process's
resource usage when it ends), returns every byte to the system afterwards, and keeps a crash of a C library
(a segmentation fault) to that job. The process runs with one thread in every pool: the parent sets the
environment variables (`gscan.threads.THREAD_ENV`) and the child limits the libraries it loaded
(threadpoolctl, OpenCV, numba) and reports the thread counts it ended with.

The child dies with its parent (the Ray worker): on Linux the kernel sends it SIGKILL when the parent goes
(PR_SET_PDEATHSIG), elsewhere a watchdog thread notices the parent's pid change. A retried task then resumes
the partial template instead of racing a scan that is still writing it.

The result file holds one JSON object: {"ok": true, ...job's fields..., "threads": {...}} or
{"ok": false, "error_kind": "input" | "internal", "error": one line, "fix": key of gscan.errors.FIXES or null}.
Exit code 0, 2 (bad input) or 1 (internal error), as the CLI's.
"""
from __future__ import annotations

import json
import os
import sys
import threading
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

_SCAN_IMPORTS = ("gscan.scanning.api", "open3d", "scipy.spatial", "cv2")


def _die_with_parent(parent: int) -> None:
    """Be killed when the parent process ends (it may have ended already)."""
    if sys.platform.startswith("linux"):
        try:
            import ctypes
            import signal

            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(1, signal.SIGKILL, 0, 0, 0)  # PR_SET_PDEATHSIG
        except (OSError, AttributeError):
            pass

    def watch() -> None:
        while True:
            if os.getppid() != parent:
                os._exit(137)
            time.sleep(1.0)

    if os.getppid() != parent:
        os._exit(137)
    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def _limit_threads() -> Any:
    """One thread in the pools of the libraries loaded now (BLAS, OpenMP) and in OpenCV's and numba's; the
    environment (THREAD_ENV) covers the ones loaded later. Returns threadpoolctl's limiter (kept alive)."""
    import importlib

    for m in _SCAN_IMPORTS:
        importlib.import_module(m)
    import cv2
    import numba
    from threadpoolctl import threadpool_limits

    cv2.setNumThreads(1)
    numba.set_num_threads(1)
    return threadpool_limits(limits=1)


def thread_counts() -> dict[str, int | None]:
    """The largest thread count of each kind of pool loaded in this process: BLAS, OpenMP, numba, OpenCV."""
    import cv2
    import numba
    from threadpoolctl import threadpool_info

    info = threadpool_info()

    def most(api: str) -> int | None:
        counts = [int(p["num_threads"]) for p in info if p.get("user_api") == api]
        return max(counts) if counts else None

    return {"blas": most("blas"), "openmp": most("openmp"), "numba": int(numba.get_num_threads()),
            "opencv": int(cv2.getNumThreads())}


def _scan_job(req: dict[str, Any]) -> dict[str, Any]:
    from gscan.batch.facts import ground_truth_check, template_facts
    from gscan.scanning.api import scan
    from gscan.scanning.config import ScanConfig
    from gscan.template.db import TemplateDB

    output = Path(req["output"])
    resumed = False
    if not req["force"] and output.is_file():
        with TemplateDB.open(output, require_complete=False) as db:
            resumed = db.status == "partial"
    cfg = None if req.get("config") is None else ScanConfig.model_validate(req["config"])
    result = scan(req["source"], output, config=cfg, resume=req["resume"], force=req["force"])
    facts = template_facts(output)
    gt = ground_truth_check(req["source"], facts)
    return {"status": "resumed" if resumed else "scanned", "frames": facts.frames, "registered": facts.registered,
            "unregistered": facts.unregistered, "unregistered_reasons": facts.unregistered_reasons,
            "keyframes": facts.keyframes, "mode": facts.mode, "edges": {"accepted": result.edges_accepted,
                                                                        "rejected": result.edges_rejected},
            "timings_s": {k: round(v, 3) for k, v in result.timings_s.items()},
            "ground_truth": None if gt is None else asdict(gt)}


def _eval_job(req: dict[str, Any]) -> dict[str, Any]:
    import numpy as np

    from gscan.evaluate.bop19 import evaluate

    csv = Path(req["csv"])
    report = evaluate(req["template"], req["scenes"], csv, obj_id=req["obj_id"], model_path=req.get("model"),
                      refine=req["refine"], force=True, gt_capture=req.get("gt_capture"))
    lines = csv.read_text(encoding="utf-8").splitlines()[1:]  # the header is the combined file's
    with_gt = [r for r in report.rows if not np.isnan(r.add)]
    diam = report.diameter_m
    wrong = sum(1 for r in with_gt if r.found and r.add > 0.1 * diam)  # ADD beyond 10 % of the diameter
    times = {(r.scene_id, r.im_id): r.time_s for r in report.rows}  # an image of several instances: one time
    return {"status": "evaluated", "images": report.n_images, "found": report.n_found, "gt_images": len(with_gt),
            "wrong_accepted": wrong, "diameter_m": diam, "metrics": {k: float(v) for k, v in report.metrics.items()},
            "csv_lines": lines, "image_times": [[s, i, t] for (s, i), t in times.items()]}


def run(req: dict[str, Any]) -> tuple[int, dict[str, Any]]:
    """(exit code, result object) of the job `req`."""
    from gscan._version import __version__
    from gscan.errors import InputError

    if req.get("version") not in (None, __version__):
        return 1, {"ok": False, "error_kind": "internal", "fix": None,
                   "error": f"this node runs gscan {__version__} from {Path(__file__).parents[2]}, the batch was "
                            f"started with gscan {req['version']}: install the same version on every node"}
    try:
        limiter = _limit_threads()
        out = _scan_job(req) if req["kind"] == "scan" else _eval_job(req)
        threads = thread_counts()
        limiter.restore_original_limits()
        return 0, {"ok": True, **out, "threads": threads}
    except InputError as e:
        return 2, {"ok": False, "error_kind": "input", "error": str(e), "fix": e.fix}
    except Exception as e:  # noqa: BLE001 - reported in the batch's report, as the CLI reports it
        msg = " ".join(f"{e.__class__.__name__}: {e}".split())
        return 1, {"ok": False, "error_kind": "internal", "error": f"internal error: {msg}", "fix": None}


def main(argv: list[str]) -> int:
    request, result = Path(argv[1]), Path(argv[2])
    req = json.loads(request.read_text(encoding="utf-8"))
    _die_with_parent(int(req["parent_pid"]))
    code, out = run(req)
    tmp = result.with_name(result.name + ".tmp")
    tmp.write_text(json.dumps(out), encoding="utf-8")
    os.replace(tmp, result)
    return code


if __name__ == "__main__":
    sys.exit(main(sys.argv))
