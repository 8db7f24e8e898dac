"""Many objects: scan a folder of captures, and evaluate many templates, on Ray (an optional extra).

Public API (imported on first use: a Ray worker that runs a task imports `gscan.batch.jobs` alone):
- `run_batch(captures_dir, templates_dir, ...)` -> `BatchReport` of `CaptureRow`s: every capture under a folder
  scanned into a template, one Ray task each, resumable, with a report (`gscan.batch.scan`; `gscan batch`);
- `run_batch_eval(...)` -> `BatchEvalReport` of `PairRow`s: many templates scored against their scenes, one Ray
  task per pair, into one BOP19 CSV and metrics per object (`gscan.batch.evaluate`; `gscan batch-eval`);
- `RayMissing`, `require_ray`, `ray_runtime`, `MAX_RETRIES` (`gscan.batch.runtime`): Ray's optional import and
  runtimes;
- `BatchMonitor`, `BatchState` (`gscan.batch.driver`) and `RichBatchMonitor` (`gscan.batch.display`): progress.

Importing this package imports neither Ray nor the scan; the commands import Ray when they start.
"""
from __future__ import annotations

from gscan._lazy import lazy_exports

_EXPORTS = {
    "run_batch": "gscan.batch.scan", "BatchReport": "gscan.batch.scan", "CaptureRow": "gscan.batch.scan",
    "find_captures": "gscan.batch.scan",
    "run_batch_eval": "gscan.batch.evaluate", "BatchEvalReport": "gscan.batch.evaluate",
    "PairRow": "gscan.batch.evaluate", "find_pairs": "gscan.batch.evaluate",
    "RayMissing": "gscan.batch.runtime", "require_ray": "gscan.batch.runtime", "ray_runtime": "gscan.batch.runtime",
    "MAX_RETRIES": "gscan.batch.runtime",
    "BatchMonitor": "gscan.batch.driver", "BatchState": "gscan.batch.driver",
    "RichBatchMonitor": "gscan.batch.display",
}
__all__ = ["MAX_RETRIES", "BatchEvalReport", "BatchMonitor", "BatchReport", "BatchState", "CaptureRow", "PairRow",
           "RayMissing", "RichBatchMonitor", "find_captures", "find_pairs", "ray_runtime", "require_ray", "run_batch",
           "run_batch_eval"]

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
