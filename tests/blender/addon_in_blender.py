"""Run by tests/blender/test_blender_addon_bpy.py in the Cycles venv (bpy 4.5, headless):

    python addon_in_blender.py EXTENSION_ZIP SERVER_URL WORK_DIR UNREACHABLE_URL

Installs the extension from its zip the way Blender's "Install from Disk" does (into the user
resources that BLENDER_USER_RESOURCES points at), builds a tiny Cycles scene whose camera moves
and which a timeline marker switches to a second camera at frame 3, then:

0. draws the panel into a recording layout (every property and operator it names exists);
1. renders frames 1-3 with "Denoise while rendering" on (the render_write handler queues each
   written frame; Blender waits for the uploads at render_complete);
2. runs the operator "Denoise rendered frames" into a folder (in line: background mode);
3. runs it against a URL where nothing listens, which must fail with that URL in the message,
   and against an internet host while Blender's online access is off, which it must not reach;
4. renders a frame as PNG with the toggle on, and runs the operator on it: both refuse.

Prints one line `@@<json>` with what the test checks: Blender's camera per frame beside the
add-on's shot plan, each run's frames (session, reset, files) and the error message.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import bpy  # first: it puts Blender's own modules (addon_utils) on the path

ZIP, URL, WORK, UNREACHABLE = sys.argv[1], sys.argv[2], Path(sys.argv[3]), sys.argv[4]
FRAMES = (1, 2, 3)


def install() -> str:
    result = bpy.ops.extensions.package_install_files(
        filepath=ZIP, repo="user_default", enable_on_install=True)
    assert result == {"FINISHED"}, result
    name = "bl_ext.user_default.quietframe"
    assert name in bpy.context.preferences.addons, list(bpy.context.preferences.addons.keys())
    return name


def camera(scene, name: str, location, rotation):
    obj = bpy.data.objects.new(name, bpy.data.cameras.new(name))
    scene.collection.objects.link(obj)
    obj.location, obj.rotation_euler = location, rotation
    return obj


def build_scene():
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    bpy.ops.mesh.primitive_plane_add(size=20, location=(0, 0, 0))
    bpy.ops.mesh.primitive_cube_add(size=1.5, location=(0, 0, 0.75))
    bpy.ops.mesh.primitive_uv_sphere_add(radius=0.6, location=(1.6, 0.8, 0.6))
    sun = bpy.data.objects.new("sun", bpy.data.lights.new("sun", "SUN"))
    sun.data.energy, sun.rotation_euler = 3.0, (0.6, 0.2, 0.4)
    scene.collection.objects.link(sun)
    world = bpy.data.worlds.new("sky")
    world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.4, 0.5, 0.7, 1)
    scene.world = world
    moving = camera(scene, "moving", (6, -6, 4), (1.1, 0, 0.8))
    moving.keyframe_insert("location", frame=1)
    moving.location.x += 0.4
    moving.keyframe_insert("location", frame=3)
    other = camera(scene, "other", (-6, -6, 3), (1.2, 0, -0.8))
    scene.camera = moving
    scene.timeline_markers.new("A", frame=1).camera = moving
    scene.timeline_markers.new("B", frame=3).camera = other
    r, c = scene.render, scene.cycles
    r.engine, r.resolution_x, r.resolution_y, r.resolution_percentage = "CYCLES", 64, 36, 100
    r.threads_mode, r.threads = "FIXED", 2
    c.device, c.samples, c.use_denoising, c.use_adaptive_sampling = "CPU", 2, False, False
    scene.frame_start, scene.frame_end = FRAMES[0], FRAMES[-1]
    r.filepath = str(WORK / "render" / "shot_")
    return scene


class RecordingLayout:
    """Stands in for a panel's layout (background mode draws no UI): records every property and
    operator the panel names, so that a misspelt one is found."""

    def __init__(self, record: dict) -> None:
        self.record = record

    def __getattr__(self, name):
        if name in ("row", "column", "box"):
            return lambda *a, **k: self
        if name == "operator":
            return lambda idname, **k: self.record["operators"].append(idname)
        if name in ("prop", "prop_search"):
            return lambda data, prop, *a, **k: self.record["props"].append(
                (data.bl_rna.identifier, prop, prop in data.bl_rna.properties))
        return lambda *a, **k: None

    def __setattr__(self, name, value) -> None:
        object.__setattr__(self, name, value)


def draw_panel(ui) -> dict:
    record = {"operators": [], "props": []}
    panel = type("Panel", (), {"layout": RecordingLayout(record)})()
    ui.RENDER_PT_quietframe.draw(panel, bpy.context)
    record["operators_exist"] = all(
        hasattr(getattr(bpy.ops, op.split(".")[0]), op.split(".")[1])
        for op in record["operators"])
    return record


def outcomes(result) -> list[dict]:
    return [{"frame": o.frame, "session": o.session, "reset": o.reset,
             "source": str(o.source), "output": str(o.output)} for o in result.outcomes]


def main() -> None:
    scene = build_scene()  # first: factory settings would disable the add-on again
    name = install()
    addon = sys.modules[name]
    state = sys.modules[f"{name}.job_state"]
    scene_job = sys.modules[f"{name}.scene_job"]
    wire = sys.modules[f"{name}.wire"]
    bpy.ops.quietframe.set_up_passes()  # the panel's button: multilayer EXR, data passes
    prefs = bpy.context.preferences.addons[name].preferences
    prefs.server_url = URL
    out = {"wire": wire.protocol.__name__, "addon_file": addon.__file__}

    cameras = {}
    for frame in FRAMES:
        scene.frame_set(frame)
        cameras[frame] = scene.camera.name
    out["blender_cameras"] = cameras
    plan = scene_job.scene_job(bpy.context).shots
    out["plan"] = [{"camera": s.camera, "frames": list(s.frames)} for s in plan]

    second = scene.view_layers.new("Second")  # without passes; the panel offers a choice
    scene.quietframe.output = "FOLDER"
    out["panel"] = draw_panel(sys.modules[f"{name}.ui"])
    scene.view_layers.remove(second)
    scene.quietframe.output = "BESIDE"

    scene.quietframe.live = True
    bpy.ops.render.render()  # a still, not written: the live job opens and ends with nothing
    running, done, total, message, error = state.LIVE_STATE.snapshot()
    out["still"] = {"result": state.LIVE_STATE.last_result is not None, "running": running,
                    "message": message, "error": error}
    bpy.ops.render.render(animation=True)
    live = state.LIVE_STATE.last_result
    out["live"] = outcomes(live) if live else None
    out["live_error"] = state.LIVE_STATE.error

    scene.quietframe.live = False
    scene.quietframe.output, scene.quietframe.folder = "FOLDER", str(WORK / "denoised")
    assert bpy.ops.quietframe.denoise_frames() == {"FINISHED"}
    out["operator"] = outcomes(state.STATE.last_result)

    prefs.server_url = UNREACHABLE
    try:
        bpy.ops.quietframe.denoise_frames()
        out["unreachable_error"] = None
    except RuntimeError as exc:  # the operator's ERROR report, as a script sees it
        out["unreachable_error"] = str(exc)

    # a server on the internet while Blender's online access is off (the bpy module's default)
    prefs.server_url = "http://quietframe.example.com:8000"
    out["online_access"] = bpy.app.online_access
    try:
        bpy.ops.quietframe.denoise_frames()
        out["offline_error"] = None
    except RuntimeError as exc:
        out["offline_error"] = str(exc)

    # a render written as PNG: the toggle and the operator both say what to change
    prefs.server_url = URL
    scene.render.image_settings.file_format = "PNG"
    scene.frame_end, scene.render.filepath = 1, str(WORK / "png" / "shot_")
    scene.quietframe.live = True
    bpy.ops.render.render(animation=True)
    out["png_live_error"] = state.LIVE_STATE.error
    scene.quietframe.live = False
    try:
        bpy.ops.quietframe.denoise_frames()
        out["png_error"] = None
    except RuntimeError as exc:
        out["png_error"] = str(exc)

    # Handlers and timers left registered keep the bpy module from exiting: unregister them
    import addon_utils

    addon_utils.disable(name)
    print("@@" + json.dumps(out), flush=True)


main()
