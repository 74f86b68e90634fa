"""What a denoise job takes from Blender, read on the main thread before any upload starts: the
frame range and its camera shots, each frame's output file, the settings, and whether the render
writes what quietframe reads."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import bpy

from . import properties, server_api, shots
from .denoise_job import JobSettings
from .server_api import DenoiseError, RetryPolicy

EXR_FORMATS = {"OPEN_EXR_MULTILAYER", "OPEN_EXR"}


@dataclass(frozen=True)
class SceneJob:
    shots: list[shots.Shot]
    sources: dict[int, Path]
    settings: JobSettings


def camera_markers(scene) -> list[shots.CameraMarker]:
    """The scene's camera markers in marker order, leaving out cameras hidden from rendering
    (Blender's camera switch skips them too)."""
    return [shots.CameraMarker(m.frame, m.camera.name) for m in scene.timeline_markers
            if m.camera is not None and not m.camera.hide_render]


def default_camera(scene) -> str:
    return scene.camera.name if scene.camera is not None else ""


def frame_file(scene, frame: int) -> Path:
    return Path(bpy.path.abspath(scene.render.frame_path(frame=frame)))


def check_output(scene) -> None:
    settings = scene.render.image_settings
    if settings.file_format not in EXR_FORMATS:
        raise DenoiseError(
            f"the render is written as {settings.file_format}: quietframe denoises OpenEXR; "
            "set Output Properties > Output > File Format to OpenEXR MultiLayer (the panel's "
            "'Set Up Passes' does it) and render again"
        )


def check_online_access(url: str) -> None:
    """Blender's rule for add-ons: no internet without "Allow Online Access". A server on this
    machine or the local network (server_api.on_local_network) is the farm's own, reached
    either way."""
    if bpy.app.online_access or server_api.on_local_network(url):
        return
    # Blender 4.2 spelt it online_access_overriden
    overridden = getattr(bpy.app, "online_access_override",
                         getattr(bpy.app, "online_access_overriden", False))
    how = ("Blender was started with --offline-mode" if overridden
           else "turn on Edit > Preferences > System > Network > Allow Online Access, or start "
           "Blender with --online-mode")
    raise DenoiseError(f"the quietframe server {url} is on the internet and Blender's online "
                       f"access is off: {how} (servers on this machine or a private network "
                       "address need no online access)")


def job_settings(scene, active_layer: str, context=None) -> JobSettings:
    prefs = properties.preferences(context)
    qs = scene.quietframe
    out_folder = None
    if qs.output == "FOLDER":
        if not qs.folder.strip():
            raise DenoiseError("choose the folder for the denoised frames in the quietframe "
                               "panel, or write them beside the render")
        out_folder = Path(bpy.path.abspath(qs.folder))
    model = qs.model.strip() or "auto"
    check_online_access(prefs.server_url)
    return JobSettings(
        server_url=prefs.server_url,
        token=prefs.token or os.environ.get("QUIETFRAME_TOKEN") or None,
        model=model,
        quality=qs.quality if model == "auto" else None,
        layer=qs.view_layer.strip() or active_layer,
        out_folder=out_folder,
        lookahead=qs.lookahead,
        timeout_s=float(prefs.timeout_s),
        retry=RetryPolicy(retries=prefs.retries),
    )


def scene_job(context) -> SceneJob:
    """The rendered frames of the scene's range, planned into camera shots; DenoiseError when
    the scene's output cannot be denoised (not EXR) or a setting is missing."""
    scene = context.scene
    check_output(scene)
    settings = job_settings(scene, context.view_layer.name, context)
    frames = shots.frame_range(scene.frame_start, scene.frame_end, scene.frame_step)
    plan = shots.plan_shots(frames, camera_markers(scene), default_camera(scene))
    return SceneJob(plan, {f: frame_file(scene, f) for f in frames}, settings)


def pass_checks(scene) -> list[tuple[bool, str]]:
    """(fine, what) for each thing quietframe reads, as the panel lists them."""
    checks = [(scene.render.image_settings.file_format == "OPEN_EXR_MULTILAYER",
               "OpenEXR MultiLayer output")]
    if scene.render.engine != "CYCLES":
        checks.append((False, "Cycles (other engines write no Denoising Data)"))
        return checks
    layers = [layer for layer in scene.view_layers if layer.use]
    checks.append((all(layer.cycles.denoising_store_passes for layer in layers),
                   "Denoising Data passes (albedo, normal, depth)"))
    checks.append((all(layer.use_pass_vector for layer in layers), "Vector pass (motion)"))
    return checks


def set_up_passes(scene) -> None:
    """Multilayer EXR and, on every view layer, the passes quietframe reads."""
    scene.render.image_settings.file_format = "OPEN_EXR_MULTILAYER"
    for layer in scene.view_layers:
        layer.cycles.denoising_store_passes = True
        layer.use_pass_vector = True
