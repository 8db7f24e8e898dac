"""`stop_on(signals)`: a long run (a capture, the ROS 2 node) ended cleanly by Ctrl+C or SIGTERM."""
from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager


@contextmanager
def stop_on(signums: tuple[int, ...] = (signal.SIGINT,)) -> Iterator[threading.Event]:
    """An event set by the first of `signums` while in the block (a second Ctrl+C then raises KeyboardInterrupt,
    to abort); the previous handlers back after it. Off the main thread no handler can be set: the event is only
    the caller's."""
    stop = threading.Event()
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return

    def on_signal(signum: int, frame: object) -> None:
        stop.set()
        signal.signal(signal.SIGINT, signal.default_int_handler)

    previous = {s: signal.signal(s, on_signal) for s in signums}
    try:
        yield stop
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
