"""The README's main job: `gscan demo` scans the bundled sample and estimates its held-back frames."""
from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import numpy as np

from gscan.demo import SAMPLES, evaluate_sample, kernel_modules
from gscan.evaluate.bop19 import template_to_gt
from gscan.geometry.transforms import inv_T, pose_error
from gscan.io import open_sequence


def test_sample_scan_matches_ground_truth(sample_template):
    """Every capture frame's registered pose agrees with the sample's ground truth (template frame mapped)."""
    from gscan.template.db import TemplateDB

    gt = open_sequence(SAMPLES / "capture").gt_T_cam_obj
    T_obj_gt = template_to_gt(sample_template, gt)
    with TemplateDB.open(sample_template) as db:
        poses = db.poses()["frames"]
    for name, T_obj_cam in poses.items():
        rot, trans = pose_error(np.asarray(T_obj_cam), T_obj_gt @ inv_T(gt[name]))
        # the sample's registration against its exact ground truth: every view within 0.5 deg / 3 mm (noisy rendered
        # depth)
        assert rot < 0.5 and trans < 0.003, (name, rot, trans)


def test_heldout_frames_are_found_accurately(sample_template):
    results = evaluate_sample(sample_template)
    assert len(results) == 4
    for r in results:
        assert r.found, r.name
        # held-back frames: ADD under 5 mm, rotation under a degree (the demo prints the measured values)
        assert r.add_mm < 5.0 and r.rot_err_deg < 1.0, r


def _python(code: str, cache: object, **env: str) -> subprocess.CompletedProcess:
    """`code` in a fresh interpreter whose numba cache is the folder `cache`."""
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, timeout=600,
                          env={**os.environ, "NUMBA_CACHE_DIR": str(cache), **env}, check=False)


def test_kernels_cached_says_whether_numba_compiled_them(tmp_path):
    """`kernels_cached` on a module of one cached kernel: False in a new cache folder, True once compiled there, False
    again when the module's source changes (numba compiles again); gscan's own kernels in a new cache: False."""
    (tmp_path / "kernels_probe.py").write_text("from numba import njit\n\n\n@njit(cache=True)\n"
                                               "def twice(x):\n    return 2 * x\n")
    code = """
        import sys
        from gscan.demo import kernels_cached
        before = kernels_cached(["kernels_probe"])
        if sys.argv[-1] == "compile":
            import kernels_probe
            assert kernels_probe.twice(3) == 6
        print(before, kernels_cached(["kernels_probe"]))
        """
    env = {"PYTHONPATH": os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")])}
    cache = tmp_path / "cache"
    out = _python(code + "\n", cache, **env)
    assert out.stdout.split() == ["False", "False"], out.stderr[-2000:]
    code_compiling = code.replace("sys.argv[-1]", '"compile"')
    assert _python(code_compiling, cache, **env).stdout.split() == ["False", "True"]
    assert _python(code, cache, **env).stdout.split() == ["True", "True"]  # another process reads the cache
    with (tmp_path / "kernels_probe.py").open("a") as f:
        f.write("# changed\n")
    assert _python(code, cache, **env).stdout.split() == ["False", "False"]
    # gscan's kernels are found (each kernel module of the scan and the estimator) and none is in a new cache
    names = kernel_modules()
    assert {"gscan.matching.kernel", "gscan.geometry.kabsch_kernel"} <= set(names), names
    out = _python("from gscan.demo import kernels_cached; print(kernels_cached())", tmp_path / "new")
    assert out.stdout.split() == ["False"], out.stderr[-2000:]
