"""Ctrl-C and SIGTERM stop a run in the request under way, as one exception the CLI turns into
one line and exit code 130 / 143 (a farm manager stops a task with SIGTERM, then SIGKILL).

A few steps must not be cut in two (an output and the record that vouches for it): inside
`signals_deferred()` a signal is noted and raised when the block ends."""

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


class _Deferral:
    depth = 0  # nesting of signals_deferred() blocks in the main thread
    pending: str | None = None  # the signal that arrived inside one


@contextlib.contextmanager
def stop_on_signals() -> Iterator[None]:
    """SIGINT and SIGTERM raise Interrupted in the main thread (a blocking socket read is
    interrupted: Python runs the handler there, and the exception ends the call)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def stop(number: int, _frame) -> None:
        name = signal.Signals(number).name
        if _Deferral.depth:
            _Deferral.pending = _Deferral.pending or name
            return
        raise Interrupted(name)

    previous = {s: signal.signal(s, stop) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)


@contextlib.contextmanager
def signals_deferred() -> Iterator[None]:
    """Run the block whole: a signal that arrives inside it raises Interrupted once it ends."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    _Deferral.depth += 1
    try:
        yield
    finally:
        _Deferral.depth -= 1
        if not _Deferral.depth and _Deferral.pending:
            name, _Deferral.pending = _Deferral.pending, None
            raise Interrupted(name)
