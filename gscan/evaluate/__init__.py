"""Evaluation against ground truth: BOP19 results and metrics over scenes, and the metrics themselves.

- bop19: `evaluate(template, scenes, output) -> EvalReport`, `score_results(results_csv, scenes, model_path)
  -> EvalReport` (a BOP19 results CSV scored without estimating), `template_to_gt`
- metrics: `add`, `adds`, `mssd`, `mspd`, `ar_mssd`, `ar_mspd`, `auc`, `ate`, `diameter`
"""
from __future__ import annotations

from gscan.evaluate.bop19 import EvalReport, EvalRow, evaluate, score_results, template_to_gt
from gscan.evaluate.metrics import ATEResult, add, adds, ar_mspd, ar_mssd, ate, auc, diameter, mspd, mssd

__all__ = ["ATEResult", "EvalReport", "EvalRow", "add", "adds", "ar_mspd", "ar_mssd", "ate", "auc", "diameter",
           "evaluate", "mspd", "mssd", "score_results", "template_to_gt"]
