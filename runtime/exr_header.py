"""EXR header parsing in pure Python: what a frame is, checked before any pixel is decoded.

`read_header` walks the header bytes without copying attribute values (a header is capped at
`max_header_bytes`; an attribute is refused when its size is read), checks what the decoder
could not read (deep parts, mip/ripmaps, subsampling, bad compression or line order) and the
resolution, and says how large the file can be. `attribute` / `attribute_value` are the one
attribute reader: everything that reads a header attribute (the windows, the cut flag, the
model choice's sample count) goes through them.
"""

from __future__ import annotations

import struct
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import NamedTuple

import OpenEXR

from quietframe.runtime.frame_errors import (
    BadExr,
    ExrHeaderTooLarge,
    ResolutionTooLarge,
    SizeMismatch,
    UnsupportedExr,
)
from quietframe.wire.protocol import CUT_ATTRIBUTE

_MAGIC = b"\x76\x2f\x31\x01"
_TILED, _LONG_NAMES, _NON_IMAGE, _MULTIPART = 0x200, 0x400, 0x800, 0x1000
_MAX_ATTRIBUTES = 4096  # a header with more is not a render's
# Nor a file with more channels (layers and AOVs: hundreds at most); the channel names are
# matched against the renderer aliases on the event loop, ~2 us each.
_MAX_CHANNELS = 4096
# Nor more parts: a renderer writes one per AOV at most (tens; Arnold and RenderMan a few
# hundred at the very most). Each part costs the decoder and the reply's writer memory of its
# own beyond its pixels (admission.PART_OVERHEAD_BYTES): 20 000 one-channel parts grew RSS by
# 4.7 GiB (audit round 4, R4-14), so the count is refused while the header streams in.
MAX_PARTS = 256
_MAX_ATTRIBUTE_BYTES = 64 << 20  # a preview image or ICC profile is far smaller
# Attribute values up to this size are copied into ExrHeader.attributes (what the service reads:
# windows, strings, the sample count); larger ones (previews, ICC profiles) stay in the body.
_COPIED_ATTRIBUTE_BYTES = 64 << 10
_COMPRESSION_METHODS = int(OpenEXR.NUM_COMPRESSION_METHODS)  # compression bytes this build reads
_LINE_ORDERS = ("increasing", "decreasing", "random")
_INT32 = struct.Struct("<i")


@dataclass(frozen=True)
class ChannelInfo:
    name: str
    pixel_type: int  # 0 uint, 1 half, 2 float
    x_sampling: int
    y_sampling: int


class _Ref(NamedTuple):  # a tuple: one is made per attribute, hundreds of thousands a header
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
        start, end = self.pos, self.pos + n
        if n < 0:
            raise BadExr("EXR header has an attribute of negative size")
        self._within_cap(end)
        if end > len(self.data):
            raise TruncatedExr("EXR header is truncated")
        self.pos = end
        return start

    def _within_cap(self, end: int) -> None:
        if self.cap is not None and end > self.cap:
            raise ExrHeaderTooLarge(
                f"the EXR header is over {self.cap} bytes (QUIETFRAME_MAX_HEADER_BYTES): leave "
                "large attributes (previews, ICC profiles, metadata blobs) out of the frames "
                "sent for denoising, or raise the limit"
            )

    def take(self, n: int) -> bytes:
        start = self.skip(n)
        return bytes(self.data[start : start + n])

    def int32(self) -> int:
        return _INT32.unpack_from(self.data, self.skip(4))[0]

    def cstring(self, limit: int) -> str:
        data, start = self.data, self.pos
        end = data.find(b"\0", start, start + limit + 1)
        if end < 0:
            if len(data) <= start + limit:
                raise TruncatedExr("EXR header is truncated")
            raise BadExr("EXR header has an over-long name")
        self._within_cap(end)
        self.pos = end + 1
        try:
            return str(data[start:end], "utf-8")
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
    "float": ("<f", 4),
    "compression": ("<B", 1),
    "lineOrder": ("<B", 1),
}


def attribute_value(name: str, kind: str, raw: bytes):
    """The one attribute decoder: `raw` bytes of attribute `name` of `kind` as a Python value
    (str for a string; int, float or a tuple for the fixed-size kinds); BadExr when `raw` is
    not that kind's size."""
    if kind == "string":
        return raw.decode("utf-8", "replace")
    fmt, size = _FORMATS[kind]
    if len(raw) != size:
        raise BadExr(f"EXR attribute {name!r} ({kind}) is malformed")
    value = struct.unpack(fmt, raw)
    return value if len(value) > 1 else value[0]


def attribute(data, refs: Mapping[str, _Ref], name: str, kind: str):
    """The value of attribute `name` in the body, which must be of `kind` (attribute_value);
    None when absent; BadExr when it has another kind or size. A fixed-size kind's size is
    checked before its bytes are copied."""
    ref = refs.get(name)
    if ref is None:
        return None
    if ref.kind != kind:
        raise BadExr(f"EXR attribute {name!r} is a {ref.kind}, not a {kind}")
    if kind != "string" and ref.size != _FORMATS[kind][1]:
        raise BadExr(f"EXR attribute {name!r} ({kind}) is malformed")
    return attribute_value(name, kind, _raw(data, ref))


def attribute_number(name: str, kind: str, raw: bytes) -> float | None:
    """A number an attribute states as a string, an int or a float (renderers differ), or
    None (another kind, a malformed value, text that is not a number)."""
    if kind not in ("string", "int", "float"):
        return None
    try:
        value = attribute_value(name, kind, raw)
        return float(value.strip() if isinstance(value, str) else value)
    except (BadExr, ValueError):
        return None


def _parse_chlist(value: bytes, limit: int) -> dict[str, ChannelInfo]:
    reader, channels = _Reader(value, 0), {}
    while True:
        if reader.pos >= len(value):
            raise BadExr("EXR channel list is not terminated")
        if value[reader.pos] == 0:
            return channels
        _check_channel_count(len(channels) + 1)
        name = reader.cstring(limit)
        pixel_type, _, x_sampling, y_sampling = struct.unpack("<iB3xii", reader.take(16))
        if pixel_type not in (0, 1, 2) or x_sampling < 1 or y_sampling < 1:
            raise BadExr(f"EXR channel {name!r} has an invalid type or sampling")
        channels[name] = ChannelInfo(name, pixel_type, x_sampling, y_sampling)


class HeaderScan:
    """A header parsed as its bytes arrive: each `advance` reads only the attributes completed
    since the last call (a header is walked once, not again from its start each time more of it
    arrives), and the whole header is checked once its end is there."""

    def __init__(
        self, max_width: int, max_height: int, max_header_bytes: int | None = None
    ) -> None:
        self.max_width, self.max_height, self.cap = max_width, max_height, max_header_bytes
        self.version = self.limit = 0
        self.pos = 0  # where the next attribute starts; 0: the magic number is not read yet
        self.parts: list[dict[str, _Ref]] = []
        self.part: dict[str, _Ref] | None = {}  # None: between two parts of a multi-part file

    def advance(self, data) -> ExrHeader | None:
        """The checked header once `data` (the body so far; it only grows) holds all of it,
        else None; raises as read_header does."""
        if self.pos == 0:
            if len(data) < 8 and _MAGIC.startswith(bytes(data[:4])):
                return None  # the magic number so far: the version is still to come
            self.version, self.limit = _version(data)
            self.pos = 8
        if not self._walk(_Reader(data, self.pos, self.cap)):
            return None
        return _checked_header(
            data, self.parts, self.pos, self.version, self.limit, self.max_width, self.max_height
        )

    def _walk(self, reader: _Reader) -> bool:
        """Read attributes up to the header's end (True) or the end of `reader`'s bytes
        (False); self.pos follows each whole attribute, part end and the header's end."""
        data, multipart = reader.data, bool(self.version & _MULTIPART)
        while True:
            if self.pos >= len(data):
                return False
            if self.part is None:  # a multi-part header ends with an empty part
                if data[self.pos] == 0:
                    return True
                self.part = {}
            if data[self.pos] == 0:
                self.pos += 1
                self.parts.append(self.part)
                self.part = None
                if len(self.parts) > MAX_PARTS:
                    raise UnsupportedExr(
                        f"the EXR has over {MAX_PARTS} parts; write the passes the denoiser "
                        "reads (colour, albedo, normal, depth, motion) into a few parts, or "
                        "one multilayer part, and leave the rest out")
                if not multipart:
                    return True
                continue
            if len(self.part) >= _MAX_ATTRIBUTES:
                raise BadExr("EXR header has too many attributes")
            reader.pos = self.pos
            try:
                name, ref = _read_attribute(reader, self.limit)
            except TruncatedExr:
                return False
            self.part[name] = ref
            self.pos = reader.pos


def _version(data) -> tuple[int, int]:
    """The version field's flags and the longest name they allow, after the magic number."""
    if len(data) < 8 or data[:4] != _MAGIC:
        if len(data) < 4 and _MAGIC.startswith(bytes(data)):
            raise TruncatedExr("EXR header is truncated")
        raise BadExr("body is not an OpenEXR file (bad magic number)")
    (version,) = struct.unpack("<I", data[4:8])
    if version & 0xFF != 2:
        raise BadExr(f"unsupported OpenEXR file version {version & 0xFF}")
    if version & _NON_IMAGE:
        raise UnsupportedExr(_DEEP_DETAIL)
    return version, 255 if version & _LONG_NAMES else 31


def _read_attribute(reader: _Reader, limit: int) -> tuple[str, _Ref]:
    name = reader.cstring(limit)
    kind = reader.cstring(limit)
    size = reader.int32()
    if size > _MAX_ATTRIBUTE_BYTES:  # refused now, not after reading that much
        raise BadExr(f"EXR header attribute {name!r} claims {size} bytes")
    return name, _Ref(kind, reader.skip(size), size)


def read_header(
    data: bytes | bytearray,
    max_width: int,
    max_height: int,
    max_header_bytes: int | None = None,
) -> ExrHeader:
    """Parse and check the header; raises BadExr (400), ResolutionTooLarge / ExrHeaderTooLarge
    (413), UnsupportedExr (422), TruncatedExr (a BadExr) when `data` ends inside the header.
    Attribute values are not copied (only those the service reads, and small ones)."""
    if len(data) < 8:
        _version(data)  # raises: too short for a header
    header = HeaderScan(max_width, max_height, max_header_bytes).advance(data)
    if header is None:
        raise TruncatedExr("EXR header is truncated")
    return header


def _checked_header(
    data,
    parts: list[dict[str, _Ref]],
    end: int,
    version: int,
    limit: int,
    max_width: int,
    max_height: int,
) -> ExrHeader:
    """The header whose attributes `parts` end at `end`, after the checks that need no pixels."""
    channels: dict[str, ChannelInfo] = {}
    window: Box | None = None
    max_bytes, pixel_bytes = end + 1, 0
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
        _check_channel_count(len(channels))
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
        end,
        max_bytes,
        _cut_flag(data, first),
        {n: (r.kind, _raw(data, r)) for n, r in first.items() if r.size <= _COPIED_ATTRIBUTE_BYTES},
        window,
        attribute(data, first, "displayWindow", "box2i"),
        pixel_bytes,
    )


def _check_channel_count(count: int) -> None:
    if count > _MAX_CHANNELS:
        raise UnsupportedExr(
            f"the EXR has over {_MAX_CHANNELS} channels; send the layers the denoiser reads "
            "(colour, albedo, normal, depth, motion) and leave the rest out"
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
    """The client's cut flag (client/protocol.py): a non-zero int or a string such as "1"."""
    ref = refs.get(CUT_ATTRIBUTE)
    if ref is None or ref.kind not in ("int", "string"):
        return False
    try:
        flag = attribute(data, refs, CUT_ATTRIBUTE, ref.kind)
    except BadExr:  # an int of another size: not a flag the client wrote
        return False
    if isinstance(flag, str):
        return flag.strip().lower() in ("1", "true", "yes", "cut")
    return flag != 0
