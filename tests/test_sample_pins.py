"""Pins the bundled sample's results: the scan of samples/capture (every frame's pose, as `gscan demo` scans
it) and the estimates on samples/heldout, stored in tests/sample_pins.json.

A refactoring must not move them. A change that is meant to move them re-pins with
`python3 -m tests.test_sample_pins` and says in its commit which result changed and why.

Tolerance: on one machine the results are bit-identical; across machines the BLAS kernels and the CPU's
vector width change the summation order of the SVDs, least-squares solves and reductions, which moves the
last bits of every float64 (about 1e-16 relative) and the iterative solvers (ICP, pose graph) carry that
along a few orders of magnitude. 1e-6 m and 1e-6 rad sit many orders above that noise and three orders below
the smallest change a behaviour change makes (a different match or edge moves a pose by 1e-4 or more), so a
pass means "same result" and a fail means "different behaviour".
"""
from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from gscan.demo import SAMPLES

PINS = Path(__file__).with_name("sample_pins.json")
TOL_M = 1e-6  # translation, metres
TOL_RAD = 1e-6  # rotation, radians


def _sample_results(db_path: Path) -> dict:
    """The pinned quantities of a scanned sample template: poses of the scan, estimates on samples/heldout."""
    from gscan.estimate.estimator import Estimator
    from gscan.io import open_sequence
    from gscan.template.db import TemplateDB

    with TemplateDB.open(db_path) as db:
        scan = db.poses()
    seq = open_sequence(SAMPLES / "heldout")
    est = Estimator.from_path(db_path)
    estimates = {}
    for name in seq.names:
        r = est.estimate(seq[name])
        estimates[name] = {"T_cam_obj": None if r.T_cam_obj is None else np.asarray(r.T_cam_obj).tolist(),
                           "view": r.view, "n_matches": int(r.n_matches), "method": r.method}
    return {"scan": {"T_obj_cam": scan["frames"], "unregistered": scan["unregistered"]}, "estimates": estimates}


def _rot_rad(A: np.ndarray, B: np.ndarray) -> float:
    """Rotation angle between two [4 x 4] poses, radians; from the skew part, precise near zero."""
    dR = A[:3, :3] @ B[:3, :3].T
    return float(np.linalg.norm(dR - dR.T) / (2 * np.sqrt(2)))


def _assert_pose_close(got: list, want: list, what: str) -> None:
    A, B = np.asarray(got, dtype=np.float64), np.asarray(want, dtype=np.float64)
    dt = float(np.linalg.norm(A[:3, 3] - B[:3, 3]))
    dr = _rot_rad(A, B)
    assert dt <= TOL_M and dr <= TOL_RAD, f"{what}: moved by {dt:.3g} m, {dr:.3g} rad"


def test_sample_results_match_the_pins(sample_template):
    want = json.loads(PINS.read_text())
    got = _sample_results(sample_template)
    assert sorted(got["scan"]["T_obj_cam"]) == sorted(want["scan"]["T_obj_cam"])
    assert got["scan"]["unregistered"] == want["scan"]["unregistered"]
    for name, T in want["scan"]["T_obj_cam"].items():
        _assert_pose_close(got["scan"]["T_obj_cam"][name], T, f"scan frame {name}")
    assert sorted(got["estimates"]) == sorted(want["estimates"])
    for name, w in want["estimates"].items():
        g = got["estimates"][name]
        assert (g["view"], g["n_matches"], g["method"]) == (w["view"], w["n_matches"], w["method"]), name
        assert (g["T_cam_obj"] is None) == (w["T_cam_obj"] is None), name
        if w["T_cam_obj"] is not None:
            _assert_pose_close(g["T_cam_obj"], w["T_cam_obj"], f"estimate on heldout {name}")


def test_pose_comparison_detects_a_small_move():
    """The comparison fails on a pose moved just beyond the tolerance, in rotation or in translation."""
    T = np.eye(4)
    _assert_pose_close(T.tolist(), T.tolist(), "same")
    moved = T.copy()
    moved[0, 3] = 2 * TOL_M
    c, s = np.cos(2 * TOL_RAD), np.sin(2 * TOL_RAD)
    turned = T.copy()
    turned[:2, :2] = [[c, -s], [s, c]]
    for bad in (moved, turned):
        try:
            _assert_pose_close(bad.tolist(), T.tolist(), "moved")
        except AssertionError:
            continue
        raise AssertionError("a pose moved beyond the tolerance passed")


def main() -> None:
    """Re-pin: scan the sample as `gscan demo` does and write tests/sample_pins.json."""
    import tempfile

    from gscan.scanning.api import scan

    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "sample.gscan"
        scan(SAMPLES / "capture", out)
        text = json.dumps(_sample_results(out), indent=1)
    # one matrix row a line
    text = re.sub(r"\[\s+([^\[\]{}]*?)\s+\]",
                  lambda m: "[" + ", ".join(x.strip() for x in m.group(1).split(",")) + "]", text)
    PINS.write_text(text + "\n")
    print(f"wrote {PINS}")


if __name__ == "__main__":
    main()
