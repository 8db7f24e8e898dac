"""The batch commands' progress on a (stderr) console the CLI hands in: a live rich table on a terminal, plain
lines otherwise.

Live: a table redrawn a few times a second, headed by the counts (done / running / failed / queued) and the
ETA, listing the running jobs (elapsed time, attempt) and the last ones finished. Plain (a log file, a pipe,
CI): one line per finished job with the counts and the ETA. Names come from files: `escape` (the CLI's) writes
their control characters out.
"""
from __future__ import annotations

from collections import deque
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from typing_extensions import Self  # typing.Self from Python 3.11

from gscan.batch.driver import BatchState

RECENT = 6  # finished jobs listed under the running ones


def format_seconds(s: float | None) -> str:
    """`1h02m`, `3m05s`, `42s`; `?` for None."""
    if s is None:
        return "?"
    s = round(s)
    if s >= 3600:
        return f"{s // 3600}h{s % 3600 // 60:02d}m"
    if s >= 60:
        return f"{s // 60}m{s % 60:02d}s"
    return f"{s}s"


def counts_line(state: BatchState, noun: str) -> str:
    """`3/8 captures done, 2 running, 1 failed, 2 queued, ETA 1m20s`."""
    return (f"{state.done}/{state.total} {noun} done, {len(state.running)} running, {state.failed} failed, "
            f"{state.queued} queued, ETA {format_seconds(state.eta_s) if state.queued or state.running else '0s'}")


class RichBatchMonitor:
    """`gscan.batch.driver.BatchMonitor` on a rich console; use as a context manager around the batch."""

    def __init__(self, console: Any, live: bool, escape: Callable[[str], str], noun: str = "captures"):
        self.console, self.live_mode, self.escape, self.noun = console, live, escape, noun
        self.state = BatchState(total=0)
        self.recent: deque[tuple[str, str, str]] = deque(maxlen=RECENT)
        self._live: Any = None

    def __enter__(self) -> Self:
        if self.live_mode:
            from rich.live import Live

            self._live = Live(get_renderable=self._render, console=self.console, refresh_per_second=4,
                              transient=True)
            self._live.start()
        return self

    def __exit__(self, *exc: object) -> None:
        if self._live is not None:
            self._live.stop()
            self._live = None

    # -- BatchMonitor
    def update(self, state: BatchState) -> None:
        self.state = state

    def finished(self, key: str, status: str, detail: str, state: BatchState) -> None:
        self.state = state
        self.recent.append((key, status, detail))
        if self._live is None:
            from rich.text import Text

            line = Text(f"[{counts_line(state, self.noun)}] ")
            line.append(status, _STYLE.get(status))
            line.append(f" {self.escape(key)}: {self.escape(detail)}")
            self.console.print(line)

    # -- live table
    def _render(self) -> Any:
        from rich.table import Table
        from rich.text import Text

        st = self.state
        table = Table(title=counts_line(st, self.noun), title_justify="left", show_edge=False, expand=False)
        table.add_column("name", overflow="fold")
        table.add_column("state")
        table.add_column("", overflow="fold")
        for key, elapsed, attempt in st.running:
            table.add_row(Text(self.escape(key)), Text("running", "yellow"),
                          Text(format_seconds(elapsed) + (f", attempt {attempt}" if attempt > 1 else "")))
        for key, status, detail in reversed(self.recent):
            table.add_row(Text(self.escape(key)), Text(status, _STYLE.get(status) or ""), Text(self.escape(detail)))
        return table


_STYLE = {"failed": "red", "scanned": "green", "resumed": "green", "evaluated": "green", "skipped": "cyan"}
