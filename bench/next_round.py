"""The CPU cost of the single estimate's next round of neighbourhoods (`retrieval.next_round`): where no list of
the first `retrieval.top_k` retrieved neighbourhoods gives an accepted pose, the next `top_k` by votes are matched.

Every scene of bench/two_sided.py (its objects, templates and scenes, the negative included; templates read from
its cache, scanned there when missing) is estimated with the next round and without it, alternating which goes
first, twice each; an estimate's CPU time is the lesser of its two. Reported over the estimates whose first round
accepted a pose or called the view ambiguous (the next round never runs there), those where it found nothing
(where the next round's cost falls), the negatives, and all: the ratio of the summed CPU times with / without,
and the medians. The answers are compared too: a scene whose answer differs is listed.

    python bench/next_round.py --objects box_tests,scrabble,crayola,box_tall   # the tune split
    python bench/next_round.py --json out.json                                # every object of bench/two_sided.py
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from recall import build_mesh, distractor_pool
from two_sided import OBJECTS, scan_both, scenes

from gscan.estimate.params import DEFAULT_PARAMS

WITHOUT = replace(DEFAULT_PARAMS, retrieval=replace(DEFAULT_PARAMS.retrieval, next_round=False))


def run(args: argparse.Namespace) -> dict:
    from gscan.estimate.estimator import Estimator

    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    pool = distractor_pool()
    rows: list[dict] = []
    for oi, (spec, _) in enumerate(OBJECTS):
        if args.objects and spec.name not in args.objects.split(","):
            continue
        mesh = build_mesh(spec)
        for kind, s in scan_both(spec, mesh, work, args.views).items():
            ests = {"with": Estimator.from_path(s["tpl"]), "without": Estimator.from_path(s["tpl"], WITHOUT)}
            for k, (label, _pose, frame, T_gt) in enumerate(scenes(spec, oi, mesh, pool, args.scenes)):
                if k == 0:
                    for e in ests.values():
                        e.estimate(frame)  # untimed: the first call
                cpu: dict[str, list[float]] = {"with": [], "without": []}
                res = {}
                for rep in range(2):
                    order = ("with", "without") if (k + rep) % 2 == 0 else ("without", "with")
                    for name in order:
                        t0 = time.process_time()
                        res[name] = ests[name].estimate(frame)
                        cpu[name].append(time.process_time() - t0)
                first = res["without"].found or (res["without"].reason or "").startswith("ambiguous view")
                same = res["with"].found == res["without"].found and (
                    not res["with"].found or np.allclose(res["with"].T_cam_obj, res["without"].T_cam_obj))
                rows.append({"scene": label, "template": kind, "negative": T_gt is None, "first_round": bool(first),
                             "same_answer": bool(same), "cpu_ms_with": 1e3 * min(cpu["with"]),
                             "cpu_ms_without": 1e3 * min(cpu["without"])})
                r = rows[-1]
                print(f"  {label:18s} {kind:9s} first round {'accepted' if first else 'nothing':8s} "
                      f"{r['cpu_ms_with']:6.0f} / {r['cpu_ms_without']:6.0f} ms{'' if same else '  ANSWER DIFFERS'}",
                      file=sys.stderr, flush=True)
    return {"rows": rows, "summary": summary(rows)}


def summary(rows: list[dict]) -> dict:
    """group -> estimates, CPU with / without (summed), medians (ms)."""
    groups = {"first round accepted or ambiguous": [r for r in rows if r["first_round"]],
              "nothing in the first round": [r for r in rows if not r["first_round"]],
              "negatives": [r for r in rows if r["negative"]], "all": rows}
    return {g: {"estimates": len(rs),
                "with / without": sum(r["cpu_ms_with"] for r in rs) / sum(r["cpu_ms_without"] for r in rs),
                "median ms with": float(np.median([r["cpu_ms_with"] for r in rs])),
                "median ms without": float(np.median([r["cpu_ms_without"] for r in rs])),
                "answers differ": [f"{r['scene']} {r['template']}" for r in rs if not r["same_answer"]]}
            for g, rs in groups.items() if rs}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--objects", default="", help="comma-separated object names of bench/two_sided.py (default: all)")
    ap.add_argument("--views", type=int, default=12, help="views per capture")
    ap.add_argument("--scenes", type=int, default=10, help="positive scenes per object")
    ap.add_argument("--work", default="/tmp/gscan-bench-two-sided", help="bench/two_sided.py's cache")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    out = run(args)
    print("\n| estimates | n | CPU with / without the next round | median ms with | median ms without | "
          "answers differ |")
    print("|---|---|---|---|---|---|")
    for g, v in out["summary"].items():
        print(f"| {g} | {v['estimates']} | {v['with / without']:.2f} | {v['median ms with']:.0f} | "
              f"{v['median ms without']:.0f} | {', '.join(v['answers differ']) or '-'} |")
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
