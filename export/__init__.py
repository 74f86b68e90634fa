"""Export of trained models to ONNX, and the location of the custom-op library.

This module must stay importable without torch: the service calls ops_library_path().
The exporter itself lives in quietframe.export.onnx_export (needs torch).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

OPS_DOMAIN = "ai.quietframe"
_LIBRARY_NAMES = {"linux": "libquietframe_ops.so", "darwin": "libquietframe_ops.dylib"}


def ops_library_path() -> Path:
    """Path of the built onnxruntime custom-op library (BilateralSplat, BilateralSlice,
    BackwardWarp).

    QUIETFRAME_OPS_LIBRARY overrides the installed copy (e.g. a debug build of export/ops).
    """
    override = os.environ.get("QUIETFRAME_OPS_LIBRARY")
    if override:
        path = Path(override)
        if not path.is_file():
            raise FileNotFoundError(f"QUIETFRAME_OPS_LIBRARY={override} is not a file")
        return path
    name = _LIBRARY_NAMES.get(sys.platform, "quietframe_ops.dll")
    # Installed wheels put the library next to this file; editable installs keep package
    # sources and built files in different folders, so look at every package path.
    for folder in __path__:
        candidate = Path(folder) / name
        if candidate.is_file():
            return candidate
    raise FileNotFoundError(
        f"{name} not found next to quietframe.export ({list(__path__)}); "
        "reinstall quietframe (pip install .) so that its CMake build runs, "
        "or set QUIETFRAME_OPS_LIBRARY to a built library"
    )
