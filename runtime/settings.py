"""The runtime's settings: the `QUIETFRAME_*` variables the inference runtime reads, read here
and nowhere else in runtime/ (every name, its layer and default: docs/configuration.md).

Read once per process (`runtime_settings()`); a test that changes a variable in-process calls
`runtime_settings.cache_clear()` to have them read again. A leaf: it imports nothing of the
runtime, so every runtime module may import it.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import dataclass
from functools import cache
from pathlib import Path

OPS_LIBRARY = "QUIETFRAME_OPS_LIBRARY"
MAX_MEMORY_MB = "QUIETFRAME_MAX_MEMORY_MB"

# The working set one tile may hold, in MiB (OIDN's maxMemoryMB); QUIETFRAME_MAX_MEMORY_MB
# overrides. At 1536 MiB 1080p still runs whole through NBG's 2-layer models (tiles cost their
# overlap) and a 4K frame through affinity-h16-k5gc adds 2.5 GiB of peak RSS (the frame's own
# buffers, state and output come on top of the tile: ~0.15 KiB/px for it).
DEFAULT_MAX_MEMORY_MB = 1536


@dataclass(frozen=True)
class RuntimeSettings:
    # The custom-op library to load instead of the installed copy (e.g. a debug build of
    # export/ops); None: the installed one (runtime/ops_library.py). Set but empty: None.
    ops_library: Path | None = None
    # The bound on one model's working set, in MiB: every model runs in tiles that fit it
    # (runtime/tiling.py).
    max_memory_mb: float = DEFAULT_MAX_MEMORY_MB

    @classmethod
    def from_environ(cls, environ: Mapping[str, str] = os.environ) -> RuntimeSettings:
        """The settings in `environ` (the process's environment unless given), unset ones at
        their defaults; ValueError names the variable whose value is not what it must be."""
        library = environ.get(OPS_LIBRARY)
        return cls(
            ops_library=Path(library) if library else None,
            max_memory_mb=_positive_float(environ, MAX_MEMORY_MB, DEFAULT_MAX_MEMORY_MB),
        )


def _positive_float(environ: Mapping[str, str], name: str, default: float) -> float:
    text = environ.get(name)
    if text is None:
        return float(default)
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise ValueError(f"{name}={text!r}: expected a number of MiB greater than 0 "
                         f"(unset: {default})")
    return value


@cache
def runtime_settings() -> RuntimeSettings:
    """The process's runtime settings, read from the environment on the first call."""
    return RuntimeSettings.from_environ()
