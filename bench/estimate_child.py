"""The estimator of whatever gscan is on sys.path, driven over stdin by another benchmark that compares two trees
(bench/recall.py --compare): each line "template frame.npz warm" (frame.npz: color, depth and K = fx, fy, cx, cy,
width, height; warm 1: estimate the frame once untimed first) is answered by a JSON line {cpu_ms, T_cam_obj (None:
not found), n_matches, reason}. Only the estimator and the frame types are imported, which every gscan tree since
the estimator's stage layout has.

    PYTHONPATH=/tmp/old python bench/estimate_child.py
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np


def main() -> None:
    from gscan.estimate.estimator import Estimator
    from gscan.io.camera import Intrinsics, RGBDFrame

    ests: dict[str, Estimator] = {}
    for line in sys.stdin:
        tpl, npz, warm = line.split()
        est = ests.get(tpl) or ests.setdefault(tpl, Estimator.from_path(tpl))
        d = np.load(npz)
        fx, fy, cx, cy, w, h = (float(x) for x in d["K"])
        frame = RGBDFrame(Path(npz).stem, d["color"], d["depth"], Intrinsics(fx, fy, cx, cy, int(w), int(h)))
        if warm == "1":
            est.estimate(frame)
        t0 = time.process_time()
        res = est.estimate(frame)
        cpu = (time.process_time() - t0) * 1e3
        print(json.dumps({"cpu_ms": cpu, "T_cam_obj": None if res.T_cam_obj is None else
                          np.asarray(res.T_cam_obj).tolist(), "n_matches": int(res.n_matches),
                          "reason": res.reason}), flush=True)


if __name__ == "__main__":
    main()
