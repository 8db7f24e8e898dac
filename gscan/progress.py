"""Progress reporting: library code calls a `Progress`; the CLI supplies a rich progress bar.

Library functions take `progress: Progress | None` and use it as
`with progress.stage("features", total=n) as advance: ... advance()`.
"""
from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, Protocol

if TYPE_CHECKING:
    import rich.progress


class Progress(Protocol):
    def stage(self, name: str, total: int | None = None) -> contextlib.AbstractContextManager[Callable[[int], None]]:
        ...


def _no_advance(n: int = 1) -> None:
    """An `advance` that reports nothing."""


class NullProgress:
    """Progress that reports nothing (library default)."""

    @contextlib.contextmanager
    def stage(self, name: str, total: int | None = None) -> Iterator[Callable[[int], None]]:
        yield _no_advance


class StageTimer:
    """Wraps a Progress and records wall-clock seconds per stage (`timings`)."""

    def __init__(self, progress: Progress | None = None):
        self.progress = progress or NullProgress()
        self.timings: dict[str, float] = {}

    @contextlib.contextmanager
    def stage(self, name: str, total: int | None = None) -> Iterator[Callable[[int], None]]:
        t0 = time.perf_counter()
        with self.progress.stage(name, total) as advance:
            yield advance
        self.timings[name] = self.timings.get(name, 0.0) + time.perf_counter() - t0


class RichProgress:
    """A rich progress bar per stage, on the given (stderr) console."""

    def __init__(self, console, enabled: bool = True):
        self.console = console
        self.enabled = enabled
        self._progress: rich.progress.Progress | None = None  # made on __enter__ (rich imported only then)

    def __enter__(self) -> RichProgress:
        if self.enabled:
            from rich.progress import BarColumn, MofNCompleteColumn, TextColumn, TimeElapsedColumn
            from rich.progress import Progress as RP

            self._progress = RP(TextColumn("{task.description:<12}"), BarColumn(), MofNCompleteColumn(),
                                TimeElapsedColumn(), console=self.console, transient=False)
        return self

    def __exit__(self, *exc) -> None:
        if self._progress is not None and self._progress.tasks:  # started by the first stage (a progress that
            self._progress.stop()  # never showed one would leave a blank line, e.g. before an error line)

    @contextlib.contextmanager
    def stage(self, name: str, total: int | None = None) -> Iterator[Callable[[int], None]]:
        bar = self._progress
        if bar is None:
            yield _no_advance
            return
        if not bar.tasks:
            bar.start()
        task = bar.add_task(name, total=total if total else 1)

        def advance(n: int = 1) -> None:
            bar.advance(task, n)

        yield advance
        bar.update(task, completed=total if total else 1)
