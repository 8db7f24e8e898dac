"""Feature extraction time of this checkout against the features module at a git ref, as a ratio in one process,
with a check that both give the same keypoints, points and descriptors bit for bit.

The ref's module is loaded from `git show REF:gscan/features/keypoints.py` (gscan/features.py in a ref before the
features package) under another name (it imports the rest of
this checkout's gscan: only the features module is compared). Frames: the bundled sample's 30 capture frames
and the first `--real` frames of the shared 7-Scenes scan (real Kinect frames, 640x480), each extracted with the
scan's whole-frame parameters (FeatureParams(), at most 2000 keypoints) and the object parameters
(OBJECT_FEATURES, contrast threshold 0.02). The two modules alternate frame by frame; CPU time
(time.process_time: every thread of the process) and wall time, summed over the frames, best of `--repeats`.

    python bench/features.py --ref 8146a4d
    python bench/features.py --ref 8146a4d --repeats 5 --real 30 --json out.json
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import subprocess
import sys
import time
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


#: where the features module was: gscan/features/keypoints.py, and gscan/features.py before the features package
PATHS = ("gscan/features/keypoints.py", "gscan/features.py")


def module_at(ref: str) -> ModuleType:
    """The features module (PATHS) as it was at `ref`, loaded as the module `gscan_features_at_ref`."""
    for path in PATHS:
        got = subprocess.run(["git", "show", f"{ref}:{path}"], cwd=ROOT, capture_output=True, text=True)
        if got.returncode == 0:
            break
    else:
        raise SystemExit(f"{ref} holds none of {', '.join(PATHS)}: {got.stderr.strip()}")
    spec = importlib.util.spec_from_loader("gscan_features_at_ref", loader=None)
    assert spec is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up
    exec(compile(got.stdout, f"{ref}:{path}", "exec"), mod.__dict__)
    return mod


def same(a, b) -> bool:
    return all(np.array_equal(x, y) for x, y in ((a.pixels, b.pixels), (a.points, b.points),
                                                  (a.descriptors, b.descriptors), (a.scales, b.scales)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--ref", required=True, help="git ref whose gscan/features/keypoints.py is the baseline")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--real", type=int, default=20, help="7-Scenes scan frames to add (0: none)")
    ap.add_argument("--data", type=Path, default=ROOT.parent / "shared" / "data")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()

    import gscan.features.keypoints as cur
    from gscan.demo import SAMPLES
    from gscan.io import open_sequence

    old = module_at(args.ref)
    sets = {"sample": open_sequence(SAMPLES / "capture")}
    real = args.data / "real" / "7scenes_redkitchen" / "scan"
    if args.real and real.is_dir():
        sets["7-Scenes"] = open_sequence(real)
    rows = []
    for set_name, seq in sets.items():
        names = seq.names if set_name == "sample" else seq.names[: args.real]
        frames = [seq[n] for n in names]
        for p_name, params in (("whole frame", cur.FeatureParams()), ("object", cur.OBJECT_FEATURES)):
            old_params = old.FeatureParams(**{k: getattr(params, k) for k in params.__dataclass_fields__})
            best = {"ref": [np.inf, np.inf], "this": [np.inf, np.inf]}
            identical, kept = True, 0
            for rep in range(args.repeats):
                tot = {"ref": [0.0, 0.0], "this": [0.0, 0.0]}
                for i, f in enumerate(frames):
                    order = (("ref", old, old_params), ("this", cur, params))
                    got = {}
                    for key, mod, prm in (order if (i + rep) % 2 == 0 else order[::-1]):
                        c0, w0 = time.process_time(), time.perf_counter()
                        got[key] = mod.extract_features(f, prm)
                        tot[key][0] += time.process_time() - c0
                        tot[key][1] += time.perf_counter() - w0
                    if rep == 0:
                        identical &= same(got["ref"], got["this"])
                        kept += len(got["this"])
                for key in best:
                    best[key] = [min(best[key][j], tot[key][j]) for j in range(2)]
            n = len(frames)
            row: dict[str, Any] = {"frames": set_name, "params": p_name, "n": n, "kept_per_frame": kept / n,
                   "ref_cpu_ms": 1e3 * best["ref"][0] / n, "this_cpu_ms": 1e3 * best["this"][0] / n,
                   "ref_wall_ms": 1e3 * best["ref"][1] / n, "this_wall_ms": 1e3 * best["this"][1] / n,
                   "identical": bool(identical)}
            row["cpu_ratio"] = row["this_cpu_ms"] / row["ref_cpu_ms"]
            row["wall_ratio"] = row["this_wall_ms"] / row["ref_wall_ms"]
            rows.append(row)
            print(json.dumps(row), flush=True)
    print(f"\n| frames | parameters | keypoints kept / frame | {args.ref} CPU ms | this CPU ms | CPU ratio | "
          "wall ratio | identical |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['frames']} ({r['n']}) | {r['params']} | {r['kept_per_frame']:.0f} | {r['ref_cpu_ms']:.1f} | "
              f"{r['this_cpu_ms']:.1f} | **{r['cpu_ratio']:.2f}** | {r['wall_ratio']:.2f} | "
              f"{'yes' if r['identical'] else 'NO'} |")
    if args.json:
        args.json.write_text(json.dumps({"ref": args.ref, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
