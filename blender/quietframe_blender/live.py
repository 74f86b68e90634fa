"""Denoise while rendering: with the scene's toggle on, an animation render queues each frame as
Blender writes it (the render_write handler) and a LiveJob thread sends it, a new session at
each camera switch. When the render ends the queue is closed; in background mode
(`blender -b file.blend -a`) Blender waits for the last frame's reply before it exits.

The handlers may run on the render thread: they only read the scene and put frames on the
queue. The UI (panel redraws, the final message) is updated by a timer on the main thread."""

from __future__ import annotations

import sys
import threading
from dataclasses import dataclass

import bpy
from bpy.app.handlers import persistent

from . import scene_job, shots
from .denoise_job import LiveJob
from .job_state import LIVE_STATE
from .operators import redraw_panels
from .server_api import DenoiseError


@dataclass(eq=False)  # one render is one object: found in the list by identity
class _LiveRender:
    markers: list[shots.CameraMarker]
    default_camera: str
    job: LiveJob | None = None  # started by the render's first written frame
    closed: bool = False


_renders: list[_LiveRender] = []  # the render under way last; earlier ones still uploading
_lock = threading.Lock()  # the handlers may run on the render thread, the timer on the main one


def _current() -> _LiveRender | None:
    with _lock:
        return _renders[-1] if _renders and not _renders[-1].closed else None


def _forget(render: _LiveRender) -> bool:
    """Drop `render` from the list; False when another thread already did."""
    with _lock:
        if render in _renders:
            _renders.remove(render)
            return True
        return False


def _first_layer(scene) -> str:
    used = [layer.name for layer in scene.view_layers if layer.use]
    return used[0] if used else scene.view_layers[0].name


@persistent
def on_render_init(scene, *_) -> None:
    if scene.quietframe.live:
        with _lock:
            _renders.append(_LiveRender(scene_job.camera_markers(scene),
                                        scene_job.default_camera(scene)))


def _start(render: _LiveRender, scene) -> bool:
    """The job, on the render's first written frame (a render that writes nothing, F12, sends
    nothing and says nothing); False when the scene's settings rule it out (said in the panel)."""
    try:
        scene_job.check_output(scene)
        settings = scene_job.job_settings(scene, _first_layer(scene))
    except DenoiseError as exc:
        render.closed = True
        _forget(render)
        LIVE_STATE.end(None, str(exc))
        print(f"quietframe: not denoising while rendering: {exc}", file=sys.stderr)
        return False
    render.job = LiveJob(settings, LIVE_STATE.update)
    LIVE_STATE.start(0, render.job.cancel, "denoising while rendering")
    return True


@persistent
def on_render_write(scene, *_) -> None:
    render = _current()
    if render is None or (render.job is None and not _start(render, scene)):
        return
    frame = scene.frame_current
    camera = shots.camera_at(frame, render.markers, render.default_camera)
    render.job.add(frame, scene_job.frame_file(scene, frame), camera)


@persistent
def on_render_end(scene, *_) -> None:
    render = _current()
    if render is None:
        return
    render.closed = True
    if render.job is None:  # nothing was written
        _forget(render)
        return
    render.job.finish()
    if bpy.app.background:  # nothing would keep Blender alive for the uploads: wait here
        _settle(render, render.job.wait())


def _settle(render: _LiveRender, result) -> None:
    if not _forget(render):
        return
    LIVE_STATE.end(result, result.error or "")
    if result.error:
        print(f"quietframe: denoising while rendering stopped: {result.error}", file=sys.stderr)
    else:
        print(f"quietframe: {result.summary()}", flush=True)


def poll_ui() -> float:
    """Main-thread timer: redraw the panel while frames go out; settle finished renders."""
    with _lock:
        renders = list(_renders)
    for render in renders:
        if render.closed and render.job is not None and not render.job.running:
            _settle(render, render.job.wait())
    if _renders or LIVE_STATE.running:
        redraw_panels()
        return 0.25
    return 1.0


HANDLERS = (
    (bpy.app.handlers.render_init, on_render_init),
    (bpy.app.handlers.render_write, on_render_write),
    (bpy.app.handlers.render_complete, on_render_end),
    (bpy.app.handlers.render_cancel, on_render_end),
)


def register() -> None:
    for handlers, handler in HANDLERS:
        handlers.append(handler)
    bpy.app.timers.register(poll_ui, first_interval=1.0, persistent=True)


def unregister() -> None:
    if bpy.app.timers.is_registered(poll_ui):
        bpy.app.timers.unregister(poll_ui)
    for handlers, handler in HANDLERS:
        if handler in handlers:
            handlers.remove(handler)
    with _lock:
        for render in _renders:
            if render.job is not None:
                render.job.cancel.set()
                render.job.finish()
        _renders.clear()
