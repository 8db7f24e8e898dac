"""The one rule for imports in the command modules: at module level only typer, rich, gscan.errors and gscan.cli's
own modules (the choice types read the library's lists when first used: `gscan.cli.choices`); the library
modules a command runs (numpy, OpenCV, open3d, the pipeline, the estimator, the service, Ray, ...) are imported
at the top of the command's function, so that `gscan --help` and a bad option are answered without loading them.
The scan imports its C extensions with Ctrl+C held (`import_holding_ctrl_c`)."""
from __future__ import annotations

import importlib
import signal

#: what a scan imports (with its lazy C-extension imports)
SCAN_IMPORTS = ("gscan.scanning.api", "open3d", "scipy.spatial")


def import_holding_ctrl_c(*modules: str) -> None:
    """Import `modules` with Ctrl+C held: a SIGINT that comes meanwhile is delivered again after them.

    Ctrl+C inside a C extension's initialisation turns into "ImportError: initialization failed", which would be
    reported as an internal error (open3d's initialisation is long enough to be hit, and the scan imports it
    lazily). The handler is swapped, not the signal blocked: a blocked signal goes to another
    thread (numpy's BLAS pool) and interrupts the import all the same. Main thread only."""
    caught: list[int] = []
    previous = signal.signal(signal.SIGINT, lambda signum, frame: caught.append(signum))
    try:
        for m in modules:
            importlib.import_module(m)
    finally:
        signal.signal(signal.SIGINT, previous)
    if caught:  # again, to the handler it would have met (KeyboardInterrupt, or nothing where it is ignored)
        signal.raise_signal(signal.SIGINT)


_import_holding_ctrl_c = import_holding_ctrl_c  # its name as `gscan.cli._import_holding_ctrl_c` (tests/test_resume.py)
