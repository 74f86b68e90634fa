"""Ctrl-C and SIGTERM stop a run in the request under way, as one exception the CLI turns into
one line and exit code 130 / 143 (a farm manager stops a task with SIGTERM, then SIGKILL)."""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator


class Interrupted(BaseException):
    """The run was stopped by `signal_name` (SIGINT or SIGTERM). A BaseException, as
    KeyboardInterrupt is, so no `except Exception` on the way swallows it."""

    def __init__(self, signal_name: str) -> None:
        super().__init__(signal_name)
        self.signal_name = signal_name


@contextlib.contextmanager
def stop_on_signals() -> Iterator[None]:
    """SIGINT and SIGTERM raise Interrupted in the main thread (a blocking socket read is
    interrupted: Python runs the handler there, and the exception ends the call)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def stop(number: int, _frame) -> None:
        raise Interrupted(signal.Signals(number).name)

    previous = {s: signal.signal(s, stop) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)
