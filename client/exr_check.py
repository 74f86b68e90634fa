"""Is an EXR file complete? Read from its header and chunk offset table only (no pixels), so a
pre-flight can check a whole shot in seconds.

A render killed mid-write or a copy cut short still has a valid header; what gives it away is
the offset table OpenEXR writes after the header: an offset of 0 (never filled in), one past
the end of the file, or a last chunk that runs past the end. The header is walked by the one
EXR header reader (wire/exr_layout.py, shared with the server); after it, per the OpenEXR file
format, comes one table of 64-bit chunk offsets per part.
"""

from __future__ import annotations

import math
import mmap
import struct
from collections.abc import Mapping
from pathlib import Path

from quietframe.wire.exr_layout import (
    MAGIC,
    MULTIPART,
    NON_IMAGE,
    TILED,
    AttributeRef,
    HeaderError,
    PartsWalk,
    attribute,
    read_version,
)

# Scanlines per chunk by compression id (NONE, RLE, ZIPS, ZIP, PIZ, PXR24, B44, B44A, DWAA,
# DWAB, HTJ2K256, HTJ2K32).
_LINES = (1, 1, 1, 16, 32, 16, 32, 32, 32, 256, 256, 32)


def incomplete(path: Path) -> str | None:
    """Why `path` is not a complete EXR, or None when its chunk table checks out (or the layout
    is one this check does not cover: deep, mip-/rip-mapped tiles)."""
    with path.open("rb") as file:
        if path.stat().st_size < 8:
            return "not an OpenEXR file (too short)"
        with mmap.mmap(file.fileno(), 0, access=mmap.ACCESS_READ) as data:  # pages read lazily
            try:
                return _check(data)
            except (struct.error, IndexError, ValueError) as exc:  # HeaderError: a ValueError
                return f"the header is cut short or damaged ({exc})"


def _check(data: mmap.mmap) -> str | None:
    if data[:4] != MAGIC:
        return "not an OpenEXR file"
    flags, name_limit = read_version(data)
    if flags & NON_IMAGE:  # deep
        return None
    walk = PartsWalk(flags, name_limit)
    if not walk.advance(data):
        raise HeaderError("EXR header is truncated")
    headers = walk.parts
    position = walk.pos + 1 if flags & MULTIPART else walk.pos  # past the closing NUL
    counts = [_chunk_count(data, h, bool(flags & TILED)) for h in headers]
    if None in counts:
        return None
    offsets = []
    for count in counts:
        offsets += struct.unpack_from(f"<{count}Q", data, position)
        position += 8 * count  # type: ignore[operator]
    size = len(data)
    unwritten = sum(1 for o in offsets if o == 0 or o >= size)
    if unwritten:
        return f"{unwritten} of {len(offsets)} pixel blocks are missing (file cut short?)"
    last = max(offsets)
    prefix = 4 if flags & MULTIPART else 0
    tiled = flags & TILED or (attribute(data, headers[0], "type", "string") or "").startswith(
        "tiled"
    )
    fields = 4 if tiled else 1
    (packed,) = struct.unpack_from("<i", data, last + prefix + 4 * fields)
    if last + prefix + 4 * fields + 4 + packed > size:
        return "the last pixel block runs past the end of the file (file cut short?)"
    return None


def _chunk_count(data, header: Mapping[str, AttributeRef], tiled_flag: bool) -> int | None:
    count = attribute(data, header, "chunkCount", "int")
    if count is not None:
        return count
    window = attribute(data, header, "dataWindow", "box2i")
    if window is None:
        raise HeaderError("EXR header lacks its dataWindow attribute")
    x0, y0, x1, y1 = window
    width, height = x1 - x0 + 1, y1 - y0 + 1
    if tiled_flag or "tiles" in header:
        tiles = attribute(data, header, "tiles", "tiledesc")
        if tiles is None:
            raise HeaderError("tiled EXR header lacks its tiles attribute")
        tile_x, tile_y, mode = tiles
        if mode & 0x0F:  # mip- or rip-mapped: levels this check does not count
            return None
        return math.ceil(width / tile_x) * math.ceil(height / tile_y)
    compression = attribute(data, header, "compression", "compression")
    if compression is None:
        raise HeaderError("EXR header lacks its compression attribute")
    if compression >= len(_LINES):
        return None
    return math.ceil(height / _LINES[compression])
