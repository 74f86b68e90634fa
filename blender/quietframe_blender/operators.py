"""The add-on's operators: denoise the rendered frames (a background thread watched by a modal
timer in the UI: progress in the window manager's progress bar, the status bar and the panel,
Esc cancels; in line in background mode or when a script calls it), cancel, set up the passes."""

from __future__ import annotations

import threading

import bpy

from . import scene_job
from .denoise_job import JobResult, Progress, denoise_shots
from .job_state import LIVE_STATE, STATE
from .server_api import DenoiseError

PREFIX = "quietframe: "


def redraw_panels() -> None:
    for window in bpy.context.window_manager.windows:
        for area in window.screen.areas:
            if area.type == "PROPERTIES":
                area.tag_redraw()


class QF_OT_denoise_frames(bpy.types.Operator):
    bl_idname = "quietframe.denoise_frames"
    bl_label = "Denoise Rendered Frames"
    bl_description = ("Send the animation's rendered frames to the quietframe server, one "
                      "session per camera shot, and write the denoised files (Esc cancels)")

    @classmethod
    def poll(cls, context) -> bool:
        return context.scene is not None and not STATE.running

    def _plan(self, context) -> scene_job.SceneJob | None:
        try:
            return scene_job.scene_job(context)
        except DenoiseError as exc:
            self.report({"ERROR"}, PREFIX + str(exc))
            return None

    def execute(self, context):
        """In line: background mode (`blender -b`) and scripts."""
        job = self._plan(context)
        if job is None:
            return {"CANCELLED"}
        cancel = threading.Event()
        STATE.start(len(job.sources), cancel)
        on_progress = _print_progress if bpy.app.background else STATE.update
        try:
            result = denoise_shots(job.shots, job.sources, job.settings, on_progress, cancel)
        except DenoiseError as exc:
            STATE.end(None, str(exc))
            self.report({"ERROR"}, PREFIX + str(exc))
            return {"CANCELLED"}
        STATE.end(result)
        self.report({"INFO"}, PREFIX + result.summary())
        return {"FINISHED"}

    def invoke(self, context, event):
        if bpy.app.background:
            return self.execute(context)
        job = self._plan(context)
        if job is None:
            return {"CANCELLED"}
        self._cancel = threading.Event()
        self._result: JobResult | None = None
        self._error = ""
        STATE.start(len(job.sources), self._cancel)
        self._thread = threading.Thread(target=self._run, args=(job,), daemon=True,
                                        name="quietframe-denoise")
        self._thread.start()
        wm = context.window_manager
        self._timer = wm.event_timer_add(0.25, window=context.window)
        wm.progress_begin(0, max(1, len(job.sources)))
        wm.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def _run(self, job: scene_job.SceneJob) -> None:
        try:
            self._result = denoise_shots(job.shots, job.sources, job.settings, STATE.update,
                                         self._cancel)
        except DenoiseError as exc:
            self._error = str(exc)
        except Exception as exc:  # shown to the user, not lost in a thread
            self._error = f"unexpected error: {type(exc).__name__}: {exc}"

    def modal(self, context, event):
        if event.type == "ESC" and event.value == "PRESS":
            self._cancel.set()
            STATE.say("cancelling after the frame in flight")
            return {"RUNNING_MODAL"}  # Esc is ours while the job runs
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        _, done, total, message, _ = STATE.snapshot()
        context.window_manager.progress_update(done)
        context.workspace.status_text_set(f"quietframe: {done}/{total} frames, {message} "
                                          "(Esc to cancel)")
        redraw_panels()
        if self._thread.is_alive():
            return {"PASS_THROUGH"}
        return self._finish(context)

    def cancel(self, context) -> None:
        """Blender ends the operator (another file is opened): stop the job, let go of the UI."""
        self._cancel.set()
        self._release(context)
        STATE.end(None, "stopped: Blender ended the job (was another file opened?)")

    def _release(self, context) -> None:
        wm = context.window_manager
        wm.event_timer_remove(self._timer)
        wm.progress_end()
        context.workspace.status_text_set(None)

    def _finish(self, context):
        self._release(context)
        STATE.end(self._result, self._error)
        redraw_panels()
        if self._error:
            self.report({"ERROR"}, PREFIX + self._error)
            return {"CANCELLED"}
        result = self._result
        self.report({"WARNING" if result.cancelled else "INFO"}, PREFIX + result.summary())
        return {"CANCELLED"} if result.cancelled else {"FINISHED"}


def _print_progress(progress: Progress) -> None:
    STATE.update(progress)
    print(f"quietframe: [{progress.done}/{progress.total}] {progress.message}", flush=True)


class QF_OT_cancel(bpy.types.Operator):
    bl_idname = "quietframe.cancel"
    bl_label = "Cancel Denoising"
    bl_description = ("Stop after the frame in flight, the frames denoised so far stay "
                      "written")

    @classmethod
    def poll(cls, context) -> bool:
        return STATE.running or LIVE_STATE.running

    def execute(self, context):
        for state in (STATE, LIVE_STATE):
            if state.cancel is not None:
                state.cancel.set()
        return {"FINISHED"}


class QF_OT_set_up_passes(bpy.types.Operator):
    bl_idname = "quietframe.set_up_passes"
    bl_label = "Set Up Passes"
    bl_description = ("Write OpenEXR MultiLayer with the Denoising Data and Vector passes on "
                      "every view layer: what quietframe reads")
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        scene_job.set_up_passes(context.scene)
        return {"FINISHED"}


CLASSES = (QF_OT_denoise_frames, QF_OT_cancel, QF_OT_set_up_passes)


register, unregister = bpy.utils.register_classes_factory(CLASSES)
