"""quietframe's wire package (the /v1 frame protocol and the EXR header reader), from where it
is: bundled as `_wire` in the extension built by `make blender-addon`, or `quietframe.wire` where
quietframe is installed (a checkout's development setup). Its modules use the standard library
only, so Blender's Python runs them as they are."""

from __future__ import annotations

try:
    from ._wire import exr_layout, protocol
except ImportError:  # the source folder, not the built extension
    try:
        from quietframe.wire import exr_layout, protocol
    except ImportError as exc:
        raise ImportError(
            "quietframe's wire package is missing: install the add-on from the zip that "
            "`make blender-addon` builds (build/quietframe-blender-<version>.zip)"
        ) from exc

__all__ = ["exr_layout", "protocol"]
