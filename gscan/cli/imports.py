"""The one rule for imports in the command modules: at module level only typer, rich, gscan.errors and gscan.cli's
own modules (the choice types read the library's lists when first used: `gscan.cli.choices`); the library
modules a command runs (numpy, OpenCV, open3d, the pipeline, the estimator, the service, Ray, ...) are imported
at the top of the command's function, so that `gscan --help` and a bad option are answered without loading them.
The scan imports its C extensions with Ctrl+C held (`import_holding_ctrl_c`): the pipeline (numba, scipy) once its
input and output are opened and checked (`gscan.scanning.opening.open_scan`), open3d when its first stage begins
(`ImportsAtFirstStage`), so that a bad input is refused without them."""
from __future__ import annotations

import contextlib
import importlib
import signal
from collections.abc import Callable
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from gscan.progress import Progress

#: what a scan imports (with its lazy C-extension imports), once its input is opened (`gscan.scanning.opening`)
SCAN_IMPORTS = ("gscan.scanning.pipeline", "open3d", "scipy.spatial")
#: of those, what a scan needs only once its input is open: imported when its first stage begins
STAGE_IMPORTS = ("open3d",)


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


class ImportsAtFirstStage:
    """A `Progress` that imports `modules` (with Ctrl+C held) when the first stage begins, then reports every stage
    to `progress`. The scan opens and checks its input before its first stage: a bad input is refused without
    loading them."""

    def __init__(self, progress: Progress, modules: tuple[str, ...]):
        self.progress = progress
        self._modules = modules

    def stage(self, name: str, total: int | None = None) -> contextlib.AbstractContextManager[Callable[[int], None]]:
        if self._modules:
            modules, self._modules = self._modules, ()
            import_holding_ctrl_c(*modules)
        return self.progress.stage(name, total)


_import_holding_ctrl_c = import_holding_ctrl_c  # its name as `gscan.cli._import_holding_ctrl_c` (tests/test_resume.py)
