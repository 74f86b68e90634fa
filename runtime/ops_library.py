"""Where the custom-op library (export/ops, built by `QUIETFRAME_BUILD_OPS=1 pip install .`)
is, and its op domain.

Part of the runtime because serving loads it; the exporter only needs the domain name.
"""

from __future__ import annotations

import sys
from pathlib import Path

from quietframe.runtime.settings import OPS_LIBRARY, runtime_settings

OPS_DOMAIN = "ai.quietframe"
_LIBRARY_NAMES = {"linux": "libquietframe_ops.so", "darwin": "libquietframe_ops.dylib"}


def ops_library_path() -> Path:
    """Path of the built onnxruntime custom-op library (BilateralSplat, BilateralSlice,
    BackwardWarp).

    QUIETFRAME_OPS_LIBRARY overrides the installed copy (e.g. a debug build of export/ops).
    """
    override = runtime_settings().ops_library
    if override:
        if not override.is_file():
            raise FileNotFoundError(f"{OPS_LIBRARY}={override} is not a file: expected the "
                                    "path of a built custom-op library")
        return override
    name = _LIBRARY_NAMES.get(sys.platform, "quietframe_ops.dll")
    # Installed wheels put the library next to this package's files; editable installs keep
    # package sources and built files in different folders, so look at every package path.
    # The package is always imported before its modules: its path is read, not imported back.
    folders = list(sys.modules[__package__].__path__)
    for folder in folders:
        candidate = Path(folder) / name
        if candidate.is_file():
            return candidate
    # A plain `pip install .` (the client's install) builds no ops: say how to get them.
    raise FileNotFoundError(
        f"{name} not found next to quietframe.runtime ({folders}): this "
        "quietframe was installed without its C++ ops, which serving and training need. "
        "Reinstall with them: QUIETFRAME_BUILD_OPS=1 pip install \".[serve]\" (a C++17 "
        "compiler; make serve does this), or set QUIETFRAME_OPS_LIBRARY to a built library"
    )
