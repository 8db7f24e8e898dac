"""The thread rule of gscan's processes (gscan.threads): a gscan command runs its BLAS / OpenMP pools with one
thread unless the environment names a count; library code leaves the caller's pools alone."""
from __future__ import annotations

import json
import os
import subprocess
import sys

from gscan.threads import BLAS_ENV, THREAD_ENV, one_blas_thread
from tests.conftest import ROOT

# runs a gscan command in this process (numpy imported before it or not), then reports the BLAS pools' thread
# counts, from the main thread and from a worker thread (the service's requests run on worker threads)
_PROBE = """
import json, sys, threading
if sys.argv[1] == "numpy-first":
    import numpy, cv2, scipy.linalg
    import gscan.scanning.api  # library code: must not touch the pools
    from threadpoolctl import threadpool_info
    before = sorted(p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas")
else:
    before = None
if sys.argv[2] == "cli":
    from gscan.cli import app
    app(["config", "dump"], standalone_mode=False)
import numpy, cv2, scipy.linalg
from threadpoolctl import threadpool_info
counts = {}
def probe(key):
    counts[key] = sorted(p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas")
probe("main")
t = threading.Thread(target=probe, args=("worker",)); t.start(); t.join()
print(json.dumps({"before": before, **counts}))
"""


def _probe(order: str, run: str, env: dict[str, str]) -> dict:
    out = subprocess.run([sys.executable, "-c", _PROBE, order, run], cwd=ROOT, env=env, capture_output=True,
                         text=True, timeout=120, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def _clean_env() -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in BLAS_ENV and k not in THREAD_ENV}
    env["PYTHONPATH"] = str(ROOT)
    return env


def test_a_command_runs_one_blas_thread_whether_numpy_was_loaded_or_not():
    env = _clean_env()
    for order in ("numpy-later", "numpy-first"):
        got = _probe(order, "cli", env)
        assert got["main"] and set(got["main"]) == {1}, (order, got)
        assert set(got["worker"]) == {1}, (order, got)


def test_library_code_and_a_set_environment_leave_the_pools_as_they_are():
    env = _clean_env()
    plain = _probe("numpy-first", "none", env)  # no command: the libraries' own choice on this machine
    assert plain["before"] == plain["main"]
    env["OPENBLAS_NUM_THREADS"] = env["OMP_NUM_THREADS"] = "2"
    want = _probe("numpy-first", "none", env)
    got = _probe("numpy-first", "cli", env)
    assert got["main"] == want["main"], (got, want)


def test_the_rule_sets_the_environment_only_where_no_count_is_named():
    env: dict[str, str] = {"PATH": "/bin"}
    assert one_blas_thread(env)
    assert {k: env[k] for k in THREAD_ENV} == THREAD_ENV
    for k in BLAS_ENV:
        named = {"PATH": "/bin", k: "3"}
        assert not one_blas_thread(named)
        assert named == {"PATH": "/bin", k: "3"}
    kept = {"NUMBA_NUM_THREADS": "4"}
    assert one_blas_thread(kept) and kept["NUMBA_NUM_THREADS"] == "4"
