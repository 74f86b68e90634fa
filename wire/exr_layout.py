"""The byte layout of an OpenEXR header, read in pure Python (standard library only): the one
place EXR header bytes are parsed. The server's frame checks (runtime/exr_header.py) and the
client's completeness check (client/exr_check.py) walk a header here and say what it means.

Layout per the OpenEXR file format: magic number, version and flags, then per part its
attributes (name NUL kind NUL int32 size, value) and a NUL; a multi-part header ends with one
more NUL. `PartsWalk` reads the attributes as the bytes arrive (a body still streaming in) without
copying their values: each is an `AttributeRef` (its kind and where its value lies), read out by
`attribute` / `attribute_value`, the one attribute decoder. Any buffer works: bytes, bytearray,
mmap. Errors are `HeaderError`s (ValueErrors) whose message says what is wrong; the limits a
reader sets (header bytes, attributes, parts, channels) raise their own subclasses.
"""

from __future__ import annotations

import struct
from collections.abc import Mapping
from dataclasses import dataclass
from typing import NamedTuple

MAGIC = b"\x76\x2f\x31\x01"
# Version field flags
TILED, LONG_NAMES, NON_IMAGE, MULTIPART = 0x200, 0x400, 0x800, 0x1000
_INT32 = struct.Struct("<i")


class HeaderError(ValueError):
    """The bytes are not a well-formed EXR header."""


class HeaderTruncated(HeaderError):
    """The bytes end inside the header."""


class HeaderOverCap(HeaderError):
    """The header runs past the reader's cap on its bytes."""

    def __init__(self, cap: int) -> None:
        super().__init__(f"the EXR header is over {cap} bytes")
        self.cap = cap


class TooManyParts(HeaderError):
    def __init__(self, limit: int) -> None:
        super().__init__(f"the EXR has over {limit} parts")
        self.limit = limit


class TooManyChannels(HeaderError):
    def __init__(self, limit: int) -> None:
        super().__init__(f"the EXR has over {limit} channels")
        self.limit = limit


@dataclass(frozen=True)
class ChannelInfo:
    name: str
    pixel_type: int  # 0 uint, 1 half, 2 float
    x_sampling: int
    y_sampling: int


class AttributeRef(NamedTuple):  # a tuple: one is made per attribute, 100 000s in a header
    """Where one attribute's value lies in the body (parsed without copying it)."""

    kind: str
    start: int
    size: int


class Cursor:
    """Reads the header forward from `pos` without copying attribute values; past `cap` bytes
    the header is refused (HeaderOverCap), however many of them have arrived."""

    def __init__(self, data, pos: int, cap: int | None = None) -> None:
        self.data, self.pos, self.cap = data, pos, cap

    def skip(self, n: int) -> int:
        """Advance past `n` bytes; returns where they start."""
        start, end = self.pos, self.pos + n
        if n < 0:
            raise HeaderError("EXR header has an attribute of negative size")
        self._within_cap(end)
        if end > len(self.data):
            raise HeaderTruncated("EXR header is truncated")
        self.pos = end
        return start

    def _within_cap(self, end: int) -> None:
        if self.cap is not None and end > self.cap:
            raise HeaderOverCap(self.cap)

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
                raise HeaderTruncated("EXR header is truncated")
            raise HeaderError("EXR header has an over-long name")
        self._within_cap(end)
        self.pos = end + 1
        try:
            return str(data[start:end], "utf-8")
        except UnicodeDecodeError as exc:
            raise HeaderError("EXR header has a name that is not UTF-8") from exc


def read_version(data) -> tuple[int, int]:
    """The version field's flags and the longest name they allow, after the magic number;
    HeaderTruncated when `data` is a start of the magic number, HeaderError when it is not an
    EXR or a version this layout does not describe."""
    if len(data) < 8 or data[:4] != MAGIC:
        if len(data) < 4 and MAGIC.startswith(bytes(data)):
            raise HeaderTruncated("EXR header is truncated")
        raise HeaderError("body is not an OpenEXR file (bad magic number)")
    (version,) = struct.unpack("<I", data[4:8])
    if version & 0xFF != 2:
        raise HeaderError(f"unsupported OpenEXR file version {version & 0xFF}")
    return version, 255 if version & LONG_NAMES else 31


class PartsWalk:
    """Each part's attributes (name -> AttributeRef), read as the header's bytes arrive: each
    `advance` reads only the attributes completed since the last call (a header is walked once,
    not again from its start each time more of it arrives).

    Limits, each None for none: `cap` header bytes (HeaderOverCap), `max_attributes` a part
    (HeaderError), `max_parts` (TooManyParts, raised as the part past it ends), attributes of
    over `max_attribute_bytes` (HeaderError, when the size is read, not after reading that much).
    """

    def __init__(
        self,
        version: int,
        name_limit: int,
        cap: int | None = None,
        max_attributes: int | None = None,
        max_parts: int | None = None,
        max_attribute_bytes: int | None = None,
    ) -> None:
        self.version, self.name_limit, self.cap = version, name_limit, cap
        self.max_attributes, self.max_parts = max_attributes, max_parts
        self.max_attribute_bytes = max_attribute_bytes
        # Where the next attribute starts; once the header is read, where it ends: past the last
        # part's NUL (single part) or at the closing NUL (multi-part)
        self.pos = 8
        self.parts: list[dict[str, AttributeRef]] = []
        self.part: dict[str, AttributeRef] | None = {}  # None: between two parts

    def advance(self, data) -> bool:
        """Read attributes up to the header's end (True) or the end of `data`, the body so far,
        which only grows (False); self.pos follows each whole attribute, part end and the
        header's end."""
        reader = Cursor(data, self.pos, self.cap)
        multipart = bool(self.version & MULTIPART)
        max_attributes = self.max_attributes
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
                if self.max_parts is not None and len(self.parts) > self.max_parts:
                    raise TooManyParts(self.max_parts)
                if not multipart:
                    return True
                continue
            if max_attributes is not None and len(self.part) >= max_attributes:
                raise HeaderError("EXR header has too many attributes")
            reader.pos = self.pos
            try:
                name, ref = self._attribute(reader)
            except HeaderTruncated:
                return False
            self.part[name] = ref
            self.pos = reader.pos

    def _attribute(self, reader: Cursor) -> tuple[str, AttributeRef]:
        name = reader.cstring(self.name_limit)
        kind = reader.cstring(self.name_limit)
        size = reader.int32()
        if self.max_attribute_bytes is not None and size > self.max_attribute_bytes:
            raise HeaderError(f"EXR header attribute {name!r} claims {size} bytes")
        return name, AttributeRef(kind, reader.skip(size), size)


def raw_value(data, ref: AttributeRef) -> bytes:
    """The one place an attribute's bytes are read (copied) out of the body."""
    with memoryview(data) as view:
        return bytes(view[ref.start : ref.start + ref.size])


# attribute kind -> (struct format, size) of the fixed-size kinds read
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
    (str for a string; int, float or a tuple for the fixed-size kinds); HeaderError when `raw`
    is not that kind's size."""
    if kind == "string":
        return raw.decode("utf-8", "replace")
    fmt, size = _FORMATS[kind]
    if len(raw) != size:
        raise HeaderError(f"EXR attribute {name!r} ({kind}) is malformed")
    value = struct.unpack(fmt, raw)
    return value if len(value) > 1 else value[0]


def attribute(data, refs: Mapping[str, AttributeRef], name: str, kind: str):
    """The value of attribute `name` in the body, which must be of `kind` (attribute_value);
    None when absent; HeaderError when it has another kind or size. A fixed-size kind's size is
    checked before its bytes are copied."""
    ref = refs.get(name)
    if ref is None:
        return None
    if ref.kind != kind:
        raise HeaderError(f"EXR attribute {name!r} is a {ref.kind}, not a {kind}")
    if kind != "string" and ref.size != _FORMATS[kind][1]:
        raise HeaderError(f"EXR attribute {name!r} ({kind}) is malformed")
    return attribute_value(name, kind, raw_value(data, ref))


def attribute_number(name: str, kind: str, raw: bytes) -> float | None:
    """A number an attribute states as a string, an int or a float (renderers differ), or
    None (another kind, a malformed value, text that is not a number)."""
    if kind not in ("string", "int", "float"):
        return None
    try:
        value = attribute_value(name, kind, raw)
        return float(value.strip() if isinstance(value, str) else value)
    except ValueError:  # a HeaderError, or text that is not a number
        return None


def read_channels(
    value: bytes, name_limit: int, max_channels: int | None = None
) -> dict[str, ChannelInfo]:
    """A `chlist` attribute's channels; HeaderTruncated when a channel runs past its end,
    TooManyChannels as the channel past `max_channels` is reached (before its name is read)."""
    reader, channels = Cursor(value, 0), {}
    while True:
        if reader.pos >= len(value):
            raise HeaderError("EXR channel list is not terminated")
        if value[reader.pos] == 0:
            return channels
        if max_channels is not None and len(channels) >= max_channels:
            raise TooManyChannels(max_channels)
        name = reader.cstring(name_limit)
        pixel_type, _, x_sampling, y_sampling = struct.unpack("<iB3xii", reader.take(16))
        if pixel_type not in (0, 1, 2) or x_sampling < 1 or y_sampling < 1:
            raise HeaderError(f"EXR channel {name!r} has an invalid type or sampling")
        channels[name] = ChannelInfo(name, pixel_type, x_sampling, y_sampling)
