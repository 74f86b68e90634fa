"""Channels: which EXR channels hold each canonical buffer (the one renderer alias table).

`resolve` maps a header's channel names onto the canonical buffers (runtime/buffers.py: color
RGB, albedo RGB, normal XYZ, depth Z, motion XY, backward, in pixels, x right and y down; and
`forward`, the motion to the next frame, which only a look-ahead session reads) by ALIASES
below or by the session's own mapping, naming what was found and what was expected when a
required buffer is missing; `Source.motion_scale` converts a renderer's motion vectors to ours.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass

from quietframe.runtime.buffers import BUFFER_CHANNELS, MissingBuffers, check_buffers
from quietframe.runtime.frame_errors import AmbiguousChannels, MissingChannels
from quietframe.wire.protocol import view_layers

# Component spellings tried for each buffer, in order (matched case-insensitively).
COMPONENTS: dict[str, tuple[str, ...]] = {
    "color": ("RGB",),
    "albedo": ("RGB",),
    "normal": ("XYZ", "RGB"),
    "depth": ("Z", "V", "R", "Y"),
    "motion": ("XY", "RG", "UV"),
    "forward": ("XY", "RG", "UV"),
}


@dataclass(frozen=True)
class Alias:
    """A renderer's name for a buffer. `layer` matches a channel prefix (case-insensitive),
    optionally behind a view-layer prefix (`<ViewLayer>.Combined`); `bare` aliases match whole
    channel names only. `motion_scale` converts the renderer's motion vectors to ours;
    `components`: the spellings this alias reads instead of the buffer's COMPONENTS (Cycles'
    Vector holds both motions: XY backward, ZW forward)."""

    layer: str
    source: str
    bare: bool = False
    motion_scale: tuple[float, float] = (1.0, 1.0)
    components: tuple[str, ...] | None = None


# The one alias table. Order is priority: the first alias with a match wins.
ALIASES: dict[str, tuple[Alias, ...]] = {
    "color": (
        # Blender writes the noisy beauty as "Noisy Image" when its own denoiser ran; then
        # "Combined" is already denoised, so the noisy one comes first.
        Alias("Noisy Image", "Blender Cycles"),
        Alias("Combined", "Blender Cycles"),
        Alias("Ci", "RenderMan"),
        Alias("RGBA", "Arnold (beauty as a named layer)"),
        Alias("beauty", "generic"),
        Alias("", "Arnold, RenderMan, V-Ray, Mitsuba, plain R,G,B"),
    ),
    "albedo": (
        Alias("Denoising Albedo", "Blender Cycles"),
        Alias("denoise_albedo", "Arnold"),
        Alias("diffuse_albedo", "Arnold (older)"),
        Alias("albedo", "RenderMan, Mitsuba, plain"),
        Alias("VRayDiffuseFilter", "V-Ray"),
    ),
    "normal": (
        Alias("Denoising Normal", "Blender Cycles"),
        Alias("N", "Arnold, plain"),
        Alias("Nn", "RenderMan"),
        Alias("normal", "RenderMan denoise set, Blender Normal pass, plain"),
        Alias("sh_normal", "Mitsuba"),
        Alias("VRayNormals", "V-Ray"),
    ),
    "depth": (
        Alias("Denoising Depth", "Blender Cycles"),
        Alias("depth", "Blender Depth pass (<ViewLayer>.Depth.Z), Mitsuba, plain"),
        Alias("Z", "Arnold, RenderMan (z), plain", bare=True),
        Alias("depth", "plain single channel", bare=True),
        Alias("zfiltered", "RenderMan denoise set"),
    ),
    "motion": (
        Alias("motion", "quietframe convention"),
        # Cycles: Vector.XY = raster position in t-1 minus position in t (our direction), raster
        # y pointing up; EXR rows go down, so y flips. Vector.ZW (to t+1): `forward` below.
        Alias("Vector", "Blender Cycles", motion_scale=(1.0, -1.0)),
        # RenderMan: backward = raster offset to the previous frame (raster y down).
        Alias("backward", "RenderMan"),
        # Arnold: raw screen-space motion from shutter open to close (forward in time, y up),
        # taken as one frame of motion: negate x for backward; y: -(-y) = y.
        Alias("motionvector", "Arnold", motion_scale=(-1.0, 1.0)),
        # RenderMan forward (to t+1), negated: the constant-velocity estimate of backward.
        Alias("forward", "RenderMan (constant-velocity estimate)", motion_scale=(-1.0, -1.0)),
    ),
    # Motion to the next frame, read only by a look-ahead session (runtime/lookahead.py).
    "forward": (
        Alias("forward_motion", "quietframe convention"),
        # Cycles: Vector.ZW = raster position in t minus position in t+1, y up (checked by
        # warping the references: experiments/lookahead.py): forward is (-Z, +W).
        Alias("Vector", "Blender Cycles", motion_scale=(-1.0, 1.0), components=("ZW",)),
        # RenderMan: forward = raster offset to the next frame (raster y down).
        Alias("forward", "RenderMan"),
    ),
}


@dataclass(frozen=True)
class Source:
    """Where one canonical buffer comes from in the file."""

    channels: tuple[str, ...]
    alias: str  # the alias or mapping that matched, for messages and the status
    motion_scale: tuple[float, float] = (1.0, 1.0)


def split_name(name: str) -> tuple[str, str]:
    """Layer and component: "ViewLayer.Combined.R" -> ("ViewLayer.Combined", "R")."""
    layer, _, component = name.rpartition(".")
    return layer, component


def _layer_matches(layer: str, alias: str) -> bool:
    layer, alias = layer.lower(), alias.lower()
    return layer == alias or layer.endswith("." + alias)


def _components(
    layers: Mapping[str, dict[str, list[str]]], layer: str, buffer: str,
    spellings: tuple[str, ...] | None = None,
) -> tuple[str, ...] | None:
    """Channel names of `layer` for `buffer`, in canonical order, or None if incomplete;
    `spellings`: an alias's own (else the buffer's COMPONENTS)."""
    present = layers.get(layer, {})
    for spelling in spellings or COMPONENTS[buffer]:
        wanted = spelling[: BUFFER_CHANNELS[buffer]]
        found = [present.get(c.lower(), []) for c in wanted]
        if all(found):
            clashes = [names for names in found if len(names) > 1]
            if clashes:  # R and r side by side: which one is the beauty is not ours to guess
                raise AmbiguousChannels(
                    f"buffer {buffer!r}: the channels {clashes} differ only in case; pass a "
                    "channel mapping (`channels`, e.g. {\"color\": [\"R\", \"G\", \"B\"]}) "
                    "when creating the session"
                )
            return tuple(names[0] for names in found)
    return None


def _layers(names: Iterable[str]) -> dict[str, dict[str, list[str]]]:
    """layer -> lower-case component -> the channel names spelling it (several: a clash)."""
    layers: dict[str, dict[str, list[str]]] = {}
    for name in names:
        layer, component = split_name(name)
        layers.setdefault(layer, {}).setdefault(component.lower(), []).append(name)
    return layers


def _find_alias(buffer: str, names: Sequence[str], layers) -> Source | None:
    for alias in ALIASES[buffer]:
        if alias.bare:
            hits = [(n,) for n in names if n.lower() == alias.layer.lower()]  # "Z" and "z"
        else:
            matching = [layer for layer in layers if _layer_matches(layer, alias.layer)]
            if alias.layer == "":
                matching = [""] if "" in layers else []
            hits = [c for layer in matching
                    if (c := _components(layers, layer, buffer, alias.components))]
        if len(hits) > 1:
            raise AmbiguousChannels(
                f"buffer {buffer!r} matches several layers {[h[0] for h in hits]}; "
                "pass a channel mapping when creating the session"
            )
        if hits:
            return Source(hits[0], f"{alias.layer or 'R,G,B'} ({alias.source})", alias.motion_scale)
    return None


def _mapped_source(buffer: str, spec: str | Sequence[str], names, layers, scale) -> Source | None:
    if not isinstance(spec, str):
        channels = tuple(spec)
        return Source(channels, "mapping", scale) if all(c in names for c in channels) else None
    if buffer == "depth" and spec in names:
        return Source((spec,), "mapping", scale)
    exact = _components(layers, spec, buffer)
    if exact is None:  # case-insensitive layer name
        layer = next((name for name in layers if name.lower() == spec.lower()), None)
        exact = _components(layers, layer, buffer) if layer is not None else None
    return Source(exact, "mapping", scale) if exact else None


def resolve(
    channel_names: Iterable[str],
    required: Sequence[str],
    optional: Sequence[str],
    mapping: Mapping[str, str | Sequence[str]] | None = None,
    mapped_motion_scale: tuple[float, float] = (1.0, 1.0),
    model: str = "",
    layer: str | None = None,
    installed: Mapping[str, tuple[Sequence[str], Sequence[str]]] | None = None,
) -> dict[str, Source]:
    """Canonical buffer -> Source for the model's buffers. A required buffer that is absent is
    refused by the runtime's one buffer check, here with the EXR names that were looked for
    (MissingChannels); optional ones are simply left out (the runtime fills them, says so).
    `layer` restricts the alias table to one view layer (`<layer>.<pass>.<channel>`); a mapping
    names whole channels and is not restricted. `installed` (model -> required, optional
    buffers) lets the refusal name the models that would accept the frame."""
    names = sorted(channel_names)
    candidates = names
    if layer:
        candidates = [n for n in names if n.startswith(layer + ".")]
        if not candidates:
            raise MissingChannels(
                f"no channels of view layer {layer!r}; the file's view layers are "
                f"{list(view_layers(names))}, its channels {names}"
            )
    layers = _layers(candidates)
    every_layer = _layers(names) if mapping else {}
    sources: dict[str, Source] = {}
    for buffer in (*required, *optional):
        if mapping and buffer in mapping:
            spec, scale = mapping[buffer], mapped_motion_scale
            source = _mapped_source(buffer, spec, names, every_layer, scale)
            if source is None:
                raise MissingChannels(
                    f"session mapping {buffer}={mapping[buffer]!r} names channels that are not in "
                    f"the file; found {names}"
                )
        else:
            source = _find_alias(buffer, candidates, layers)
        if source is not None:
            sources[buffer] = source
    return for_model(sources, names, required, optional, model, installed)


def for_model(
    sources: Mapping[str, Source],
    channel_names: Iterable[str],
    required: Sequence[str],
    optional: Sequence[str],
    model: str = "",
    installed: Mapping[str, tuple[Sequence[str], Sequence[str]]] | None = None,
) -> dict[str, Source]:
    """Of the buffers `resolve` found (each is found alone, whatever else is asked for), a
    model's; MissingChannels, as from `resolve`, where a required one is absent."""
    chosen = {buffer: sources[buffer] for buffer in (*required, *optional) if buffer in sources}
    try:
        check_buffers(model, required, optional, chosen)
    except MissingBuffers as exc:
        raise MissingChannels(_missing_detail(exc, sorted(channel_names), installed)) from exc
    return chosen


def _missing_detail(
    exc: MissingBuffers,
    names: Sequence[str],
    installed: Mapping[str, tuple[Sequence[str], Sequence[str]]] | None,
) -> str:
    """What is missing, what was looked for, and what would make the frame work."""
    looked_for = "; ".join(
        f"{buffer!r}: one of the layers {[a.layer or 'R,G,B' for a in ALIASES[buffer]]} "
        f"(components {'/'.join(COMPONENTS[buffer])})"
        for buffer in exc.missing
    )
    found = exc.present
    lead = (
        f"colour-only frame: only 'color' was found, and model {exc.model or '(this one)'} also "
        f"needs {', '.join(exc.missing)}. "
        if found == ["color"]
        else ""
    )
    accepting = [m for m, (req, opt) in (installed or {}).items() if _accepts(m, req, opt, found)]
    if accepting:
        models = f" Installed models that accept the buffers found: {accepting} (session model)."
    elif installed is not None:
        what = "colour-only input" if found == ["color"] else f"a frame with only {found}"
        models = f" No installed model accepts {what}."
    else:
        models = ""
    return (
        f"{lead}no channels for required buffer(s) {', '.join(repr(b) for b in exc.missing)}; "
        f"expected {looked_for}; found {list(names)}.{models} To make it work: render those AOVs "
        "(Blender: View Layer > Passes > Data > Denoising Data), or name the channels that hold "
        "them in the session's channel mapping (`channels`, CLI --channels "
        """'{"albedo": "myAlbedo"}')"""
    )


def _accepts(model: str, required: Sequence[str], optional: Sequence[str], found) -> bool:
    try:
        check_buffers(model, required, optional, found)  # the one buffer check
    except MissingBuffers:
        return False
    return True


def validate_mapping(mapping: Mapping[str, str | Sequence[str]]) -> None:
    """Raise ValueError for a session mapping that could never match (unknown buffer, count)."""
    for buffer, spec in mapping.items():
        if buffer not in BUFFER_CHANNELS:
            raise ValueError(f"unknown buffer {buffer!r}; buffers are {list(BUFFER_CHANNELS)}")
        if not isinstance(spec, str) and len(spec) != BUFFER_CHANNELS[buffer]:
            raise ValueError(
                f"{buffer} needs {BUFFER_CHANNELS[buffer]} channel names, got {len(spec)}"
            )
