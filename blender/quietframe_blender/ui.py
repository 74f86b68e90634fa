"""The quietframe panel in Render properties: the server, what the render writes that quietframe
reads, where the denoised frames go, the denoise button, and the job's progress or error."""

from __future__ import annotations

import bpy

from . import properties, scene_job
from .job_state import LIVE_STATE, STATE, JobState


def _draw_state(layout, state: JobState, title: str) -> None:
    running, done, total, message, error = state.snapshot()
    if not (running or message or error):
        return
    box = layout.box()
    if running:
        counted = f"{done}/{total}" if total else f"{done}"
        box.label(text=f"{title}: {counted} frames", icon="SORTTIME")
        box.operator("quietframe.cancel", icon="CANCEL")
    if message:
        box.label(text=message)
    if error:
        column = box.column()
        column.alert = True
        for i, line in enumerate(_wrap(error, 70)):
            column.label(text=line, icon="ERROR" if i == 0 else "BLANK1")


def _wrap(text: str, width: int) -> list[str]:
    lines, line = [], ""
    for word in text.split():
        if line and len(line) + 1 + len(word) > width:
            lines.append(line)
            line = word
        else:
            line = f"{line} {word}".strip()
    return lines + ([line] if line else [])


class RENDER_PT_quietframe(bpy.types.Panel):
    bl_label = "quietframe Denoise"
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "render"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context) -> None:
        layout = self.layout
        scene = context.scene
        qs = scene.quietframe
        layout.label(text=f"Server: {properties.preferences(context).server_url or 'not set'}",
                     icon="URL")

        checks = scene_job.pass_checks(scene)
        column = layout.column(align=True)
        for fine, what in checks:
            column.label(text=what, icon="CHECKMARK" if fine else "ERROR")
        if not all(fine for fine, _ in checks):
            column.operator("quietframe.set_up_passes", icon="MODIFIER")

        layout.use_property_split = True
        layout.prop(qs, "model")
        if (qs.model.strip() or "auto") == "auto":
            layout.prop(qs, "quality")
        layout.prop(qs, "lookahead")
        if sum(layer.use for layer in scene.view_layers) > 1:
            layout.prop_search(qs, "view_layer", scene, "view_layers")
        layout.prop(qs, "output")
        if qs.output == "FOLDER":
            layout.prop(qs, "folder")
        layout.prop(qs, "live")

        layout.use_property_split = False
        row = layout.row()
        row.scale_y = 1.4
        row.operator("quietframe.denoise_frames", icon="RENDER_ANIMATION")
        _draw_state(layout, STATE, "Denoising")
        _draw_state(layout, LIVE_STATE, "Denoising while rendering")


CLASSES = (RENDER_PT_quietframe,)


register, unregister = bpy.utils.register_classes_factory(CLASSES)
