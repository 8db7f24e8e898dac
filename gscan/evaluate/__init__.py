"""Evaluation against ground truth: BOP19 results and metrics over scenes, and the metrics themselves.

- bop19: `evaluate(template, scenes, output) -> EvalReport`, `score_results(results_csv, scenes, model_path)
  -> EvalReport` (a BOP19 results CSV scored without estimating), `template_to_gt`
- metrics: `add`, `adds`, `mssd`, `mspd`, `ar_mssd`, `ar_mspd`, `auc`, `ate`, `diameter`

Imported on first use: a module that needs the metrics alone (the batch's ground-truth check) does not load the
estimator that `bop19` runs.
"""
from __future__ import annotations

from gscan._lazy import lazy_exports

_EXPORTS = {
    **dict.fromkeys(("EvalReport", "EvalRow", "evaluate", "score_results", "template_to_gt"), "gscan.evaluate.bop19"),
    **dict.fromkeys(("ATEResult", "add", "adds", "ar_mspd", "ar_mssd", "ate", "auc", "diameter", "mspd", "mssd"),
                    "gscan.evaluate.metrics"),
}
__all__ = ["ATEResult", "EvalReport", "EvalRow", "add", "adds", "ar_mspd", "ar_mssd", "ate", "auc", "diameter",
           "evaluate", "mspd", "mssd", "score_results", "template_to_gt"]

__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
