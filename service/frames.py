"""EXR bytes <-> canonical float32 buffers: the header check, the one alias table, pixel I/O.

A frame goes through three steps, so that a bad request is refused before any pixel is decoded:
1. `read_header` parses the EXR header bytes in pure Python (size limits, channel list, flags);
2. `resolve` maps the header's channel names onto the canonical buffers (ALIASES below, or the
   session's own mapping), naming what was found and what was expected when something is missing;
3. `decode` reads the pixels with OpenEXR into planar (C, H, W) float32 buffers, converting
   renderer conventions to ours (motion vectors, "no hit" depths, an all-zero motion layer);
   `encode` writes the input back, every part, channel and attribute as decoded, with the
   denoised (3, H, W) planes in place of the beauty's R, G, B (or as a layer of their own).

Canonical buffers (runtime/buffers.py): color (RGB), albedo (RGB), normal (XYZ), depth (Z), motion
(XY, backward, in pixels, x right and y down: pixel p of frame t was at p + motion in frame t-1).
"""

from __future__ import annotations

import contextlib
import io
import logging
import struct
import sys
import threading
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import OpenEXR

from quietframe.client.protocol import CUT_ATTRIBUTE, view_layers
from quietframe.runtime.buffers import BUFFER_CHANNELS, MissingBuffers, check_buffers
from quietframe.service.errors import (
    AmbiguousChannels,
    BadExr,
    ExrHeaderTooLarge,
    MissingChannels,
    ResolutionTooLarge,
    SizeMismatch,
    UnsupportedExr,
)

log = logging.getLogger("quietframe.service")

# Component spellings tried for each buffer, in order (matched case-insensitively).
COMPONENTS: dict[str, tuple[str, ...]] = {
    "color": ("RGB",),
    "albedo": ("RGB",),
    "normal": ("XYZ", "RGB"),
    "depth": ("Z", "V", "R", "Y"),
    "motion": ("XY", "RG", "UV"),
}


@dataclass(frozen=True)
class Alias:
    """A renderer's name for a buffer. `layer` matches a channel prefix (case-insensitive),
    optionally behind a view-layer prefix (`<ViewLayer>.Combined`); `bare` aliases match whole
    channel names only. `motion_scale` converts the renderer's motion vectors to ours."""

    layer: str
    source: str
    bare: bool = False
    motion_scale: tuple[float, float] = (1.0, 1.0)


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
        # y pointing up; EXR rows go down, so y flips. Vector.ZW (to t+1) is not used.
        Alias("Vector", "Blender Cycles", motion_scale=(1.0, -1.0)),
        # RenderMan: backward = raster offset to the previous frame (raster y down).
        Alias("backward", "RenderMan"),
        # Arnold: raw screen-space motion from shutter open to close (forward in time, y up),
        # taken as one frame of motion: negate x for backward; y: -(-y) = y.
        Alias("motionvector", "Arnold", motion_scale=(-1.0, 1.0)),
        # RenderMan forward (to t+1), negated: the constant-velocity estimate of backward.
        Alias("forward", "RenderMan (constant-velocity estimate)", motion_scale=(-1.0, -1.0)),
    ),
}

_io = {"threads": 1}  # decoding threads, set once per process by configure_io


def configure_io(threads: int) -> None:
    """Decode EXR chunks on `threads` threads: OpenEXR's process-wide pool must hold them
    (measured at 1280x720, ZIP half, 2 cores: 77 ms on one thread, 38 ms on two)."""
    threads = max(1, threads)
    OpenEXR.set_global_thread_count(threads)
    _io["threads"] = threads
    _stdout_router()  # installed once, before worker threads decode



_MAGIC = b"\x76\x2f\x31\x01"
_TILED, _LONG_NAMES, _NON_IMAGE, _MULTIPART = 0x200, 0x400, 0x800, 0x1000
_MAX_ATTRIBUTES = 4096  # a header with more is not a render's
_MAX_ATTRIBUTE_BYTES = 64 << 20  # a preview image or ICC profile is far smaller
# Attribute values up to this size are copied into ExrHeader.attributes (what the service reads:
# windows, strings, the sample count); larger ones (previews, ICC profiles) stay in the body.
_COPIED_ATTRIBUTE_BYTES = 64 << 10
_COMPRESSION_METHODS = int(OpenEXR.NUM_COMPRESSION_METHODS)  # compression bytes this build reads
_LINE_ORDERS = ("increasing", "decreasing", "random")


@dataclass(frozen=True)
class ChannelInfo:
    name: str
    pixel_type: int  # 0 uint, 1 half, 2 float
    x_sampling: int
    y_sampling: int


@dataclass(frozen=True)
class _Ref:
    """Where one attribute's value lies in the body (parsed without copying it)."""

    kind: str
    start: int
    size: int


Box = tuple[int, int, int, int]  # x0, y0, x1, y1 (inclusive, as EXR stores it)


@dataclass
class ExrHeader:
    """What the service needs from an EXR header, parsed without decoding pixels."""

    width: int
    height: int
    channels: dict[str, ChannelInfo]
    parts: int
    header_bytes: int  # where the offset tables and pixels start
    max_bytes: int  # the largest file this header can describe (uncompressed pixels + tables)
    cut: bool = False
    # First part: name -> (kind, raw value), values up to _COPIED_ATTRIBUTE_BYTES only.
    attributes: dict[str, tuple[str, bytes]] = field(default_factory=dict)
    data_window: Box = (0, 0, 0, 0)
    display_window: Box | None = None
    pixel_bytes: int = 0  # every part's pixels, uncompressed (what decoding them holds)


class TruncatedExr(BadExr):
    """The bytes end inside the header: a whole body is bad, a body still arriving is not yet
    complete (the frame route reads on)."""


class _Reader:
    """Walks the header without copying attribute values; past `cap` bytes the header is
    refused (ExrHeaderTooLarge), however many of them have arrived."""

    def __init__(self, data, pos: int, cap: int | None = None) -> None:
        self.data, self.pos, self.cap = data, pos, cap

    def skip(self, n: int) -> int:
        """Advance past `n` bytes; returns where they start."""
        if n < 0:
            raise BadExr("EXR header has an attribute of negative size")
        if self.cap is not None and self.pos + n > self.cap:
            raise ExrHeaderTooLarge(
                f"the EXR header is over {self.cap} bytes (QUIETFRAME_MAX_HEADER_BYTES): leave "
                "large attributes (previews, ICC profiles, metadata blobs) out of the frames "
                "sent for denoising, or raise the limit"
            )
        if self.pos + n > len(self.data):
            raise TruncatedExr("EXR header is truncated")
        start, self.pos = self.pos, self.pos + n
        return start

    def take(self, n: int) -> bytes:
        start = self.skip(n)
        return bytes(self.data[start : start + n])

    def cstring(self, limit: int) -> str:
        end = self.data.find(b"\0", self.pos, self.pos + limit + 1)
        if end < 0:
            if len(self.data) <= self.pos + limit:
                raise TruncatedExr("EXR header is truncated")
            raise BadExr("EXR header has an over-long name")
        raw = self.take(end - self.pos)
        self.pos = end + 1
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise BadExr("EXR header has a name that is not UTF-8") from exc


def _raw(data, ref: _Ref) -> bytes:
    """The one place an attribute's bytes are read (copied) out of the body."""
    with memoryview(data) as view:
        return bytes(view[ref.start : ref.start + ref.size])


# attribute kind -> (struct format, size) of the fixed-size kinds the service reads
_FORMATS = {
    "box2i": ("<iiii", 16),
    "tiledesc": ("<IIB", 9),
    "int": ("<i", 4),
    "compression": ("<B", 1),
    "lineOrder": ("<B", 1),
}


def attribute(data, refs: Mapping[str, _Ref], name: str, kind: str):
    """The one attribute reader: the value of attribute `name`, which must be of `kind`, as a
    Python value (tuple for box2i/tiledesc, int, str); None when absent; BadExr when it has
    another kind or size."""
    ref = refs.get(name)
    if ref is None:
        return None
    if ref.kind != kind:
        raise BadExr(f"EXR attribute {name!r} is a {ref.kind}, not a {kind}")
    if kind == "string":
        return _raw(data, ref).decode("utf-8", "replace")
    fmt, size = _FORMATS[kind]
    if ref.size != size:
        raise BadExr(f"EXR attribute {name!r} ({kind}) is malformed")
    value = struct.unpack(fmt, _raw(data, ref))
    return value if len(value) > 1 else value[0]


def _parse_chlist(value: bytes, limit: int) -> dict[str, ChannelInfo]:
    reader, channels = _Reader(value, 0), {}
    while True:
        if reader.pos >= len(value):
            raise BadExr("EXR channel list is not terminated")
        if value[reader.pos] == 0:
            return channels
        name = reader.cstring(limit)
        pixel_type, _, x_sampling, y_sampling = struct.unpack("<iB3xii", reader.take(16))
        if pixel_type not in (0, 1, 2) or x_sampling < 1 or y_sampling < 1:
            raise BadExr(f"EXR channel {name!r} has an invalid type or sampling")
        channels[name] = ChannelInfo(name, pixel_type, x_sampling, y_sampling)


def _parse_part(reader: _Reader, limit: int) -> dict[str, _Ref]:
    refs: dict[str, _Ref] = {}
    while True:
        if reader.pos >= len(reader.data):
            raise TruncatedExr("EXR header is truncated")
        if reader.data[reader.pos] == 0:
            reader.pos += 1
            return refs
        if len(refs) >= _MAX_ATTRIBUTES:
            raise BadExr("EXR header has too many attributes")
        name = reader.cstring(limit)
        kind = reader.cstring(limit)
        (size,) = struct.unpack("<i", reader.take(4))
        if size > _MAX_ATTRIBUTE_BYTES:  # refused now, not after reading that much
            raise BadExr(f"EXR header attribute {name!r} claims {size} bytes")
        refs[name] = _Ref(kind, reader.skip(size), size)


def read_header(
    data: bytes | bytearray,
    max_width: int,
    max_height: int,
    max_header_bytes: int | None = None,
) -> ExrHeader:
    """Parse and check the header; raises BadExr (400), ResolutionTooLarge / ExrHeaderTooLarge
    (413), UnsupportedExr (422), TruncatedExr (a BadExr) when `data` ends inside the header.
    Attribute values are not copied (only those the service reads, and small ones)."""
    if len(data) < 8 or data[:4] != _MAGIC:
        if len(data) < 4 and _MAGIC.startswith(bytes(data)):
            raise TruncatedExr("EXR header is truncated")
        raise BadExr("body is not an OpenEXR file (bad magic number)")
    (version,) = struct.unpack("<I", data[4:8])
    if version & 0xFF != 2:
        raise BadExr(f"unsupported OpenEXR file version {version & 0xFF}")
    if version & _NON_IMAGE:
        raise UnsupportedExr(_DEEP_DETAIL)
    limit = 255 if version & _LONG_NAMES else 31
    reader = _Reader(data, 8, max_header_bytes)
    parts = [_parse_part(reader, limit)]
    while version & _MULTIPART:
        if reader.pos >= len(data):
            raise TruncatedExr("EXR header is truncated")
        if data[reader.pos] == 0:
            break
        parts.append(_parse_part(reader, limit))
    channels: dict[str, ChannelInfo] = {}
    window: Box | None = None
    max_bytes, pixel_bytes = reader.pos + 1, 0
    for number, refs in enumerate(parts):
        part_window, part_channels = _check_part(data, number, refs, limit, version)
        if window is not None and part_window != window:
            raise UnsupportedExr(
                f"EXR part {number} has the data window {part_window}, part 0 has {window}: "
                "parts must cover the same pixels (same size and origin); write the passes "
                "with one data window"
            )
        window = part_window
        for name, info in part_channels.items():
            channels.setdefault(name, info)  # a name in several parts: the first part's
        size = _box_size(part_window)
        pixels = size[0] * size[1] * sum(_PIXEL_BYTES[c.pixel_type] for c in part_channels.values())
        pixel_bytes += pixels
        max_bytes += _max_part_bytes(data, size, pixels, refs)
    assert window is not None
    width, height = _box_size(window)
    if width > max_width or height > max_height:
        raise ResolutionTooLarge(
            f"frame is {width}x{height}; this server accepts at most {max_width}x{max_height}"
        )
    subsampled = [c.name for c in channels.values() if (c.x_sampling, c.y_sampling) != (1, 1)]
    if subsampled:
        raise UnsupportedExr(f"subsampled channels are not supported: {subsampled}")
    first = parts[0]
    return ExrHeader(
        width,
        height,
        channels,
        len(parts),
        reader.pos,
        max_bytes,
        _cut_flag(data, first),
        {n: (r.kind, _raw(data, r)) for n, r in first.items() if r.size <= _COPIED_ATTRIBUTE_BYTES},
        window,
        attribute(data, first, "displayWindow", "box2i"),
        pixel_bytes,
    )


def check_windows(header: ExrHeader, width: int, height: int) -> None:
    """SizeMismatch (422) unless the frame's data window, and its display window where it has
    one, are the session's size: checked from the header, before any body buffer exists."""
    display = _box_size(header.display_window) if header.display_window else None
    if (header.width, header.height) == (width, height) and display in (None, (width, height)):
        return
    what = f"frame is {header.width}x{header.height}"
    if display is not None and display != (header.width, header.height):
        what += f" (display window {display[0]}x{display[1]})"
    raise SizeMismatch(
        f"{what}; this session is {width}x{height} (create a session per resolution; overscan "
        "or crop windows: send the frame with its data and display windows at the session size)"
    )


def _box_size(box: Box) -> tuple[int, int]:
    x0, y0, x1, y1 = box
    return x1 - x0 + 1, y1 - y0 + 1


_DEEP_DETAIL = (
    "deep EXR data is not supported; send a flat (scanline or tiled) image: flatten the deep "
    "samples in the renderer or compositor (e.g. Nuke DeepToImage) and write a flat EXR"
)
_IMAGE_TYPES = {"scanlineimage": False, "tiledimage": True}
_LEVEL_MODES = ("single-level", "mipmap", "ripmap")
_PIXEL_BYTES = {0: 4, 1: 2, 2: 4}  # uint, half, float


def _check_part(
    data, number: int, refs: Mapping[str, _Ref], limit: int, version: int
) -> tuple[Box, dict[str, ChannelInfo]]:
    """One part's data window and channels, after the checks that need no pixels: its type
    (deep parts are refused however the file's flags are set), tiling, compression."""
    if "dataWindow" not in refs or "channels" not in refs:
        raise BadExr("EXR header lacks its dataWindow or channels attribute")
    try:
        window: Box = attribute(data, refs, "dataWindow", "box2i")
    except BadExr as exc:
        raise BadExr("EXR dataWindow attribute is malformed") from exc
    width, height = _box_size(window)
    if width < 1 or height < 1:
        raise BadExr(f"EXR dataWindow is empty {window}")
    part_type = attribute(data, refs, "type", "string")
    if part_type is not None and part_type.startswith("deep"):
        raise UnsupportedExr(f"part {number} is {part_type}: {_DEEP_DETAIL}")
    if part_type is not None and part_type not in _IMAGE_TYPES:
        raise BadExr(f"part {number} has an unknown EXR part type {part_type!r}")
    tiled = _IMAGE_TYPES[part_type] if part_type is not None else bool(version & _TILED)
    if tiled:
        _check_tiles(data, number, refs)
    try:
        compression = attribute(data, refs, "compression", "compression")
    except BadExr:
        compression = -1
    if compression is not None and not 0 <= compression < _COMPRESSION_METHODS:
        raw = _raw(data, refs["compression"]).hex()
        raise BadExr(f"part {number} has an invalid EXR compression attribute ({raw})")
    order = attribute(data, refs, "lineOrder", "lineOrder")
    if order is not None and order >= len(_LINE_ORDERS):
        raise BadExr(f"part {number} has an invalid EXR lineOrder attribute ({order})")
    try:
        part_channels = _parse_chlist(_raw(data, refs["channels"]), limit)
    except TruncatedExr as exc:  # the attribute is whole: its content is malformed
        raise BadExr("EXR channel list is malformed") from exc
    return window, part_channels


def _tiles(data, refs: Mapping[str, _Ref]) -> tuple[int, int, int] | None:
    try:
        return attribute(data, refs, "tiles", "tiledesc")
    except BadExr:
        return None


def _check_tiles(data, number: int, refs: Mapping[str, _Ref]) -> None:
    tiles = _tiles(data, refs)
    if tiles is None:
        raise BadExr(f"tiled part {number} lacks a valid tile description")
    x_size, y_size, mode = tiles
    if x_size < 1 or y_size < 1 or mode & 0x0F >= len(_LEVEL_MODES):
        raise BadExr(f"tiled part {number} has an invalid tile description")
    if mode & 0x0F:
        # The decoder reads single-level files only; level 0 of a mip/ripmap is the image, but
        # reading it needs the level-aware API this service does not use.
        raise UnsupportedExr(
            f"part {number} is a {_LEVEL_MODES[mode & 0x0F]} tiled EXR; send a scanline or "
            "single-level tiled EXR (the render output, not a texture: e.g. oiiotool in.exr "
            "--scanline -o out.exr)"
        )


def _max_part_bytes(data, size: tuple[int, int], pixels: int, refs: Mapping[str, _Ref]) -> int:
    """The most bytes a flat single-level part can take on disk: its `pixels` bytes
    uncompressed (OpenEXR stores a chunk raw when compression does not shrink it), plus per-row
    chunk headers and offsets (a chunk holds at least one row or one tile), plus 1% for writers
    whose compression expands data slightly."""
    width, height = size
    chunks = height
    tiles = _tiles(data, refs)  # checked by _check_tiles when the part is tiled
    if tiles is not None:
        x_size, y_size, _ = tiles
        chunks = max(chunks, -(-width // max(x_size, 1)) * -(-height // max(y_size, 1)))
    return pixels + pixels // 100 + 32 * chunks + 4096


def _cut_flag(data, refs: Mapping[str, _Ref]) -> bool:
    ref = refs.get(CUT_ATTRIBUTE)
    if ref is None:
        return False
    if ref.kind == "int" and ref.size == 4:
        return attribute(data, refs, CUT_ATTRIBUTE, "int") != 0
    if ref.kind == "string":
        flag = attribute(data, refs, CUT_ATTRIBUTE, "string")
        return flag.strip().lower() in ("1", "true", "yes", "cut")
    return False


# --------------------------------------------------------------------------------------------
# Channel resolution


@dataclass(frozen=True)
class Source:
    """Where one canonical buffer comes from in the file."""

    channels: tuple[str, ...]
    alias: str  # the alias or mapping that matched, for messages and the status
    motion_scale: tuple[float, float] = (1.0, 1.0)


def _split(name: str) -> tuple[str, str]:
    layer, _, component = name.rpartition(".")
    return layer, component


def _layer_matches(layer: str, alias: str) -> bool:
    layer, alias = layer.lower(), alias.lower()
    return layer == alias or layer.endswith("." + alias)


def _components(
    layers: Mapping[str, dict[str, list[str]]], layer: str, buffer: str
) -> tuple[str, ...] | None:
    """Channel names of `layer` for `buffer`, in canonical order, or None if incomplete."""
    present = layers.get(layer, {})
    for spelling in COMPONENTS[buffer]:
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
        layer, component = _split(name)
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
            hits = [c for layer in matching if (c := _components(layers, layer, buffer))]
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
    try:
        check_buffers(model, required, optional, sources)
    except MissingBuffers as exc:
        raise MissingChannels(_missing_detail(exc, names, installed)) from exc
    return sources


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


# --------------------------------------------------------------------------------------------
# Pixels


@dataclass
class Part:
    """One part of the input as decoded: its channels are handed to the writer unchanged."""

    name: str
    attributes: dict  # OpenEXR header attributes
    channels: dict  # channel name -> OpenEXR.Channel (pixels in their own type)


@dataclass
class DecodedFrame:
    buffers: dict[str, np.ndarray]  # canonical name -> (C, H, W) float32 planes
    parts: list[Part]  # everything the input holds, for the output
    color_half: bool  # the input colour is half float (its first channel)
    # each colour channel's own type, R, G, B: precision "input" keeps each (mixed types too)
    color_dtypes: tuple[np.dtype, ...] = ()

    @property
    def header(self) -> dict:
        """Attributes of the first part."""
        return self.parts[0].attributes


class _BufferStream(io.RawIOBase):
    """A read-only stream over the body's buffer: io.BytesIO would copy a bytearray whole; the
    decoder reads it in chunks, so this keeps one copy of the body in memory."""

    def __init__(self, data: bytes | bytearray | memoryview) -> None:
        self._view, self._pos = memoryview(data), 0

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def readinto(self, buffer) -> int:
        n = max(0, min(len(buffer), len(self._view) - self._pos))
        buffer[:n] = self._view[self._pos : self._pos + n]
        self._pos += n
        return n

    def read(self, size: int = -1) -> bytes:
        end = len(self._view) if size is None or size < 0 else self._pos + size
        chunk = self._view[self._pos : end].tobytes()
        self._pos += len(chunk)
        return chunk

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        base = {io.SEEK_SET: 0, io.SEEK_CUR: self._pos, io.SEEK_END: len(self._view)}[whence]
        self._pos = max(0, base + offset)
        return self._pos

    def tell(self) -> int:
        return self._pos


class _ThreadStdout(io.TextIOBase):
    """sys.stdout that hands the text a thread writes while `captured()` is active to that
    thread: the OpenEXR binding prints its `Warning: ...` lines with Python's print, which would
    land unstructured in the JSON log. Other threads write through."""

    def __init__(self, target) -> None:
        self.target, self.local = target, threading.local()

    def write(self, text: str) -> int:
        lines = getattr(self.local, "lines", None)
        if lines is None:
            return self.target.write(text)
        lines.append(text)
        return len(text)

    def flush(self) -> None:
        self.target.flush()

    @contextlib.contextmanager
    def captured(self) -> Iterator[list[str]]:
        self.local.lines = lines = []
        try:
            yield lines
        finally:
            self.local.lines = None


def _stdout_router() -> _ThreadStdout:
    if not isinstance(sys.stdout, _ThreadStdout):
        sys.stdout = _ThreadStdout(sys.stdout)
    return sys.stdout


def _openexr_output() -> contextlib.AbstractContextManager[list[str]]:
    return _stdout_router().captured()


def decode(data: bytes | bytearray, sources: Mapping[str, Source]) -> DecodedFrame:
    """Decode the pixels into planar (C, H, W) float32 buffers, the runtime's layout (one
    conversion per channel, no interleaving); BadExr for anything the decoder rejects.
    Depth is passed on as written: the runtime's sanitising rule turns every renderer's "no hit"
    marker (0, ≥ 1e10, ±inf) into the frame's farthest depth. An all-zero motion layer is left
    out (motion blur on in Blender), so the runtime fills it and reports it missing. The
    decoder's printed warnings go to the log as fields of one record."""
    with _openexr_output() as printed:
        try:
            return _decode(data, sources)
        finally:
            warnings = [line.strip() for line in "".join(printed).splitlines() if line.strip()]
            if warnings:
                log.warning("OpenEXR warnings while decoding", extra={"openexr": warnings})


def _decode(data: bytes | bytearray, sources: Mapping[str, Source]) -> DecodedFrame:
    wanted = {c for source in sources.values() for c in source.channels}
    try:
        stream = _BufferStream(data)  # reads the request's one buffer in place
        exr = OpenEXR.File(stream, separate_channels=True, num_threads=_io["threads"])
        parts = [Part(p.name(), dict(p.header), dict(p.channels)) for p in exr.parts]
        channels: dict = {}
        for part in parts:
            for name, channel in part.channels.items():
                channels.setdefault(name, channel)
        planes = {name: channels[name].pixels for name in wanted if name in channels}
    except Exception as exc:  # the binding raises RuntimeError/ValueError/UnicodeDecodeError
        raise BadExr(f"EXR pixel data could not be decoded: {exc}") from exc
    absent = sorted(wanted - set(planes))
    if absent:
        raise BadExr(f"EXR channels {absent} are listed in the header but have no data")
    buffers: dict[str, np.ndarray] = {}
    for buffer, source in sources.items():
        first = planes[source.channels[0]]
        planar = np.empty((len(source.channels), *first.shape), np.float32)  # (C, H, W)
        for i, name in enumerate(source.channels):
            planar[i] = planes[name]
        if buffer == "motion":
            if not planar.any():  # the whole frame: Cycles writes 0 on the sky of a moving camera
                continue
            if source.motion_scale != (1.0, 1.0):
                planar *= np.asarray(source.motion_scale, np.float32)[:, None, None]
        buffers[buffer] = planar
    color = [planes[name].dtype for name in sources["color"].channels] if "color" in sources else []
    color_half = bool(color) and color[0] == np.float16
    return DecodedFrame(buffers, parts, color_half, tuple(color))


def output_dtypes(frame: DecodedFrame, precision: str) -> tuple[type, ...]:
    """The pixel type of each denoised channel R, G, B: the session's precision, or for "input"
    each input colour channel's own (half stays half, float and uint become float)."""
    if precision != "input":
        return (np.float16 if precision == "half" else np.float32,) * 3
    given = frame.color_dtypes or ((np.float16 if frame.color_half else np.float32),) * 3
    return tuple(np.float16 if d == np.float16 else np.float32 for d in given)


def output_channels(color: Sequence[str], denoised_layer: str | None = None) -> tuple[str, ...]:
    """Where the denoised R, G, B go: in place of the colour read (Blender's `Noisy Image`:
    as `Combined`, the pass Blender shows), or as `<view layer>.<denoised_layer>.R/G/B`."""
    names = []
    for channel in color:
        layer, component = _split(channel)
        view_layer, _, name = layer.rpartition(".")
        if denoised_layer:
            layer = f"{view_layer}.{denoised_layer}" if view_layer else denoised_layer
        elif name.lower() == "noisy image":
            layer = f"{view_layer}.Combined" if view_layer else "Combined"
        names.append(f"{layer}.{component}" if layer else component)
    return tuple(names)


# Attributes that describe the layout of the input file, not the image; the writer sets them.
_LAYOUT_ATTRIBUTES = frozenset({"channels", "chunkCount", "name", "type", "tiles", "version"})
# Codecs that lose precision (DWA on channels named R, G, B, Y; B44 on half; PXR24 on float):
# the output does not recompress what it passes through with them unless the session asks.
LOSSY_CODECS = frozenset({"DWAA", "DWAB", "B44", "B44A", "PXR24"})


def output_compression(given, session: str):
    """The output's codec for a part written with `given`: the session's, else the input's,
    except that a lossy input codec becomes ZIP so passed-through data keep their values."""
    if session != "input":
        return getattr(OpenEXR, f"{'NO' if session == 'none' else session.upper()}_COMPRESSION")
    if given is None or given.name.removesuffix("_COMPRESSION") in LOSSY_CODECS:
        return OpenEXR.ZIP_COMPRESSION
    return given


def encode(
    color: np.ndarray,
    frame: DecodedFrame,
    color_channels: Sequence[str],
    precision: str,
    extra: Mapping[str, str] | None = None,
    compression: str = "input",
    denoised_layer: str | None = None,
) -> bytes:
    """The input frame with the denoised (3, H, W) float32 planes written in (`output_channels`),
    as scanline EXR bytes: every part, channel (its pixel type too) and header attribute of
    the input; only the denoised channels take the session's `precision` (`output_dtypes`)."""
    dtypes = output_dtypes(frame, precision)
    parts = []
    for part in frame.parts:
        attributes = {k: v for k, v in part.attributes.items() if k not in _LAYOUT_ATTRIBUTES}
        attributes["type"] = OpenEXR.scanlineimage
        if attributes.get("lineOrder") == OpenEXR.RANDOM_Y:  # tiles only; scanlines are not
            attributes["lineOrder"] = OpenEXR.INCREASING_Y
        given = part.attributes.get("compression")
        attributes["compression"] = output_compression(given, compression)
        attributes.update(extra or {})
        parts.append(Part(part.name, attributes, dict(part.channels)))  # the decoded channels
    home = next((p for p in parts if color_channels[0] in p.channels), parts[0])
    for i, name in enumerate(output_channels(color_channels, denoised_layer)):
        target = next((p for p in parts if name in p.channels), home)
        target.channels[name] = np.asarray(color[i], dtype=dtypes[i])
    try:
        return _write(parts)
    except Exception as exc:  # an attribute the binding reads but cannot write back
        dropped: set[str] = set()
        for part in parts:
            kept = {k: v for k, v in part.attributes.items() if k in _STANDARD_ATTRIBUTES}
            for key, value in part.attributes.items():
                if key not in kept and _writable({key: value}):
                    kept[key] = value
            dropped |= set(part.attributes) - set(kept)
            part.attributes = kept
        log.warning("dropped EXR attributes that could not be written: %s (%s)", dropped, exc)
        for part in parts:
            part.attributes["quietframe.dropped_attributes"] = ", ".join(sorted(dropped))
        return _write(parts)


# Attributes of every EXR; the rest are kept one by one if they can be written back.
_STANDARD_ATTRIBUTES = frozenset(
    {
        "compression",
        "dataWindow",
        "displayWindow",
        "lineOrder",
        "pixelAspectRatio",
        "screenWindowCenter",
        "screenWindowWidth",
        "type",
        "quietframe.model",
        "quietframe.frame",
    }
)


def _writable(attributes: Mapping) -> bool:
    attributes = {**attributes, "type": OpenEXR.scanlineimage}
    probe = [Part("", attributes, {"R": np.zeros((1, 1), np.float16)})]
    try:
        _write(probe)
        return True
    except Exception:
        return False


def _write(parts: Sequence[Part]) -> bytes:
    """One part: a single-part file; several: a multi-part file with the input's part names."""
    out = io.BytesIO()
    if len(parts) == 1:
        OpenEXR.File(dict(parts[0].attributes), dict(parts[0].channels)).write(out)
    else:
        OpenEXR.File([OpenEXR.Part(p.attributes, p.channels, p.name) for p in parts]).write(out)
    return out.getvalue()
