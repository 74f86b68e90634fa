"""Pixels: EXR bytes -> planar (C, H, W) float32 buffers, and the denoised frame back to EXR.

`decode` reads the channels `exr_channels.resolve` chose with OpenEXR, converting renderer
conventions to ours (motion vectors, an all-zero motion layer); `encode` writes the input
back, every part, channel and attribute as decoded, with the denoised (3, H, W) planes in
place of the beauty's R, G, B (or as a layer of their own).
"""

from __future__ import annotations

import io
import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import OpenEXR

from quietframe.runtime import exr_warnings
from quietframe.runtime.buffers import FORWARD
from quietframe.runtime.exr_channels import Source, split_name
from quietframe.runtime.frame_errors import BadExr
from quietframe.runtime.sanitize import clamp_to_half

MOTIONS = frozenset({"motion", FORWARD})  # scaled to ours; all zero: left out

log = logging.getLogger("quietframe.service")  # a decode's warnings are its request's

_io = {"threads": 1}  # decoding threads, set once per process by configure_io


def configure_io(threads: int) -> None:
    """Decode EXR chunks on `threads` threads: OpenEXR's process-wide pool must hold them
    (measured at 1280x720, ZIP half, 2 cores: 77 ms on one thread, 38 ms on two)."""
    threads = max(1, threads)
    OpenEXR.set_global_thread_count(threads)
    _io["threads"] = threads


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


def decode(data: bytes | bytearray, sources: Mapping[str, Source]) -> DecodedFrame:
    """Decode the pixels into planar (C, H, W) float32 buffers, the runtime's layout (one
    conversion per channel, no interleaving); BadExr for anything the decoder rejects.
    Depth is passed on as written: the runtime's sanitising rule turns every renderer's "no hit"
    marker (0, ≥ 1e10, ±inf) into the frame's farthest depth. An all-zero motion layer (either
    direction) is left out (motion blur on in Blender), so the runtime fills it and reports it
    missing. The
    decoder's printed warnings go to the log as fields of one record (exr_warnings)."""
    with exr_warnings.logged("decoding"):
        return _decode(data, sources)


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
        if buffer in MOTIONS:
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
        layer, component = split_name(channel)
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


def encode_denoised(
    color: np.ndarray,
    frame: DecodedFrame,
    color_channels: Sequence[str],
    precision: str,
    extra: Mapping[str, str] | None = None,
    compression: str = "input",
    denoised_layer: str | None = None,
) -> tuple[bytes, int]:
    """`encode` of a model's output: the channels written as half are first clamped to ±65504
    (a plain cast turns larger values into ±Inf); also how many values were clamped. One place
    for it, because a retry's reply is written again from the stored colour and must come out
    byte for byte the same (service/state_codec.py)."""
    half = [i for i, d in enumerate(output_dtypes(frame, precision)) if d == np.float16]
    clamped = 0
    if half:
        rows, clamped = clamp_to_half(color[half])
        if clamped:
            color = color.copy()
            color[half] = rows
    return encode(color, frame, color_channels, precision, extra, compression,
                  denoised_layer), clamped


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
