"""The OpenEXR binding's printed warnings, turned into one log record per decode.

The binding reports a part whose pixels it could not read with pybind11's `print`, which writes
to whatever `sys.stdout` is at that moment: no logger, no warning category, no callback. Left
alone, the line lands unstructured beside the JSON log. So `logged` routes `sys.stdout` only
while a decode runs: text that a decoding thread prints is kept for that thread, every other
thread writes through unchanged, and when the last decode in flight ends `sys.stdout` is put
back (unless something replaced it meanwhile: then theirs stays). Between decodes nothing in
the process is replaced.
"""

from __future__ import annotations

import contextlib
import io
import logging
import sys
import threading
from collections.abc import Iterator

log = logging.getLogger("quietframe.service")  # a decode's warnings are its request's


class _Router(io.TextIOBase):
    """Stands in for sys.stdout during decodes: a capturing thread's text goes to its list."""

    def __init__(self, target) -> None:
        self.target, self.local = target, threading.local()

    def write(self, text: str) -> int:
        lines = getattr(self.local, "lines", None)
        if lines is None:
            return self.target.write(text)
        lines.append(text)
        return len(text)

    def flush(self) -> None:
        self.target.flush()

    def isatty(self) -> bool:
        return self.target.isatty()

    def fileno(self) -> int:
        return self.target.fileno()


_lock = threading.Lock()
_router: _Router | None = None
_decodes = 0  # decodes in flight (the router is installed while this is above 0)


@contextlib.contextmanager
def _captured() -> Iterator[list[str]]:
    global _router, _decodes
    with _lock:
        if _router is None:
            _router = _Router(sys.stdout)
            sys.stdout = _router
        router, _decodes = _router, _decodes + 1
    outer = getattr(router.local, "lines", None)
    router.local.lines = lines = []
    try:
        yield lines
    finally:
        router.local.lines = outer
        with _lock:
            _decodes -= 1
            if _decodes == 0:
                if sys.stdout is router:
                    sys.stdout = router.target
                _router = None


@contextlib.contextmanager
def logged(what: str) -> Iterator[None]:
    """Run the body with the binding's printed lines collected; if there were any, log them as
    the `openexr` field of one warning record ("OpenEXR warnings while <what>")."""
    with _captured() as printed:
        try:
            yield
        finally:
            warnings = [line.strip() for line in "".join(printed).splitlines() if line.strip()]
            if warnings:
                log.warning(f"OpenEXR warnings while {what}", extra={"openexr": warnings})
