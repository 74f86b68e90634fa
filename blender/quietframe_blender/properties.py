"""The add-on's settings: the server and its token in the add-on's preferences (one per Blender
install), what to denoise and where to write it on the scene (saved with the .blend)."""

from __future__ import annotations

import bpy

ADDON = __package__  # the add-on's module name, as Blender registered it


class QuietframePreferences(bpy.types.AddonPreferences):
    bl_idname = ADDON

    server_url: bpy.props.StringProperty(
        name="Server URL",
        description="The quietframe server, e.g. http://denoise:8000 (`quietframe serve`)",
        default="http://127.0.0.1:8000",
    )
    token: bpy.props.StringProperty(
        name="Token",
        description="The server's bearer token (its QUIETFRAME_AUTH_TOKEN); empty: the "
        "QUIETFRAME_TOKEN environment variable, else none",
        subtype="PASSWORD",
    )
    timeout_s: bpy.props.IntProperty(
        name="Timeout (s)", description="Seconds to wait for one frame's reply",
        default=300, min=5, max=3600,
    )
    retries: bpy.props.IntProperty(
        name="Retries",
        description="Retries of a busy (429, 503) or unreachable server before giving up; "
        "each waits the server's Retry-After, at most 30 s",
        default=5, min=0, max=20,
    )

    def draw(self, context) -> None:
        layout = self.layout
        layout.prop(self, "server_url")
        layout.prop(self, "token")
        row = layout.row()
        row.prop(self, "timeout_s")
        row.prop(self, "retries")


def preferences(context=None) -> QuietframePreferences:
    return (context or bpy.context).preferences.addons[ADDON].preferences


class QuietframeSceneSettings(bpy.types.PropertyGroup):
    output: bpy.props.EnumProperty(
        name="Write",
        items=[
            ("BESIDE", "Beside the Render", "<name>_denoised.exr next to each rendered frame"),
            ("FOLDER", "Into a Folder", "The rendered frame's name, in a folder of its own"),
        ],
        default="BESIDE",
    )
    folder: bpy.props.StringProperty(
        name="Folder", description="Where the denoised frames go", subtype="DIR_PATH",
    )
    model: bpy.props.StringProperty(
        name="Model",
        description="An installed model (`quietframe models`), or auto: the server chooses "
        "once per shot from the first frame's passes and noise",
        default="auto",
    )
    quality: bpy.props.EnumProperty(
        name="Quality",
        description="What model auto aims for",
        items=[
            ("fast", "Fast", "Up to 1 dB below the best expected, cheaper"),
            ("balanced", "Balanced", "Within 0.3 dB of the best expected"),
            ("best", "Best", "The best expected"),
        ],
        default="balanced",
    )
    lookahead: bpy.props.IntProperty(
        name="Look-Ahead",
        description="Later frames each frame's denoise also uses (0: none): the server holds "
        "that many frames back and returns each once it has them; the shot's last frames are "
        "finished with what there is",
        default=0, min=0, max=4,
    )
    view_layer: bpy.props.StringProperty(
        name="View Layer",
        description="The view layer to denoise where the render writes several (empty: the "
        "active one); the others pass through",
    )
    live: bpy.props.BoolProperty(
        name="Denoise While Rendering",
        description="Send each frame as soon as Blender writes it during an animation render",
        default=False,
    )


CLASSES = (QuietframePreferences, QuietframeSceneSettings)


_register_classes, _unregister_classes = bpy.utils.register_classes_factory(CLASSES)


def register() -> None:
    _register_classes()
    bpy.types.Scene.quietframe = bpy.props.PointerProperty(type=QuietframeSceneSettings)


def unregister() -> None:
    del bpy.types.Scene.quietframe
    _unregister_classes()
