"""quietframe denoise: a Blender extension that sends an animation's rendered frames to a
quietframe server, one session per camera shot, and writes the denoised EXRs beside them (or
into a folder), from the Render properties, after the render or while it runs.

The logic without bpy (shot planning, the HTTP API, the upload loop, the files) is in modules
that import no bpy: `shots`, `server_api`, `frame_files`, `denoise_job`, so that plain Python
tests them. This package imports none of the bpy modules until Blender registers it.
"""

from __future__ import annotations

_MODULES = ("properties", "operators", "live", "ui")  # registered in this order


def _modules():
    import importlib

    return [importlib.import_module(f".{name}", __package__) for name in _MODULES]


def register() -> None:
    for module in _modules():
        module.register()


def unregister() -> None:
    for module in reversed(_modules()):
        module.unregister()
