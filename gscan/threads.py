"""Thread pools of the processes gscan owns: one BLAS thread and one OpenMP thread.

The rule, stated here once: a `gscan` command (the command line, and the service `gscan serve` starts, whose
request workers are threads of that process) runs its BLAS pools (OpenBLAS, MKL, BLIS, Accelerate) and
OpenMP pools with one thread, unless the environment names a thread count (any of `BLAS_ENV`): then every
library follows the environment. gscan's matrices are small (a few thousand rows): a pool's extra threads
spin waiting for work more than they share it, and take cores from the machine's other processes. Library
code (`gscan.scan`, `Estimator`, ... called from Python) leaves the pools of the caller's process as they
are (an `Estimator` limits BLAS only while it estimates: `EstimateParams.threads.blas`). Batch tasks
(`gscan.batch`) always run with one thread in every pool (`THREAD_ENV`): each holds one CPU.
"""
from __future__ import annotations

import os
import sys
from collections.abc import MutableMapping

# one thread for every pool a scan or an estimate could start: BLAS (OpenBLAS, MKL, BLIS, Accelerate), OpenMP,
# numba and numexpr; read by those libraries when they load
THREAD_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "BLIS_NUM_THREADS": "1",
              "VECLIB_MAXIMUM_THREADS": "1", "NUMEXPR_NUM_THREADS": "1", "NUMBA_NUM_THREADS": "1"}
# the variables that name a BLAS or OpenMP thread count: one of them set leaves every pool to the environment
BLAS_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "GOTO_NUM_THREADS", "MKL_NUM_THREADS", "BLIS_NUM_THREADS",
            "VECLIB_MAXIMUM_THREADS")


def one_blas_thread(environ: MutableMapping[str, str] | None = None) -> bool:
    """Apply the rule to this process: set `THREAD_ENV` (for the libraries loaded from now on and the child
    processes) and limit the BLAS and OpenMP pools already loaded to one thread, for the rest of the process.
    Nothing when the environment names a thread count. Returns whether the limit was applied. Only for
    processes gscan owns (the command line calls it); never from library code."""
    env = os.environ if environ is None else environ
    if any(k in env for k in BLAS_ENV):
        return False
    for k, v in THREAD_ENV.items():
        env.setdefault(k, v)
    if "numpy" in sys.modules:  # every BLAS gscan loads comes with numpy: without it nothing is loaded yet
        from threadpoolctl import threadpool_limits

        threadpool_limits(limits=1)
    return True
