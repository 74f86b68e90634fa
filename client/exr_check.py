"""Is an EXR file complete? Read from its header and chunk offset table only (no pixels), so a
pre-flight can check a whole shot in seconds.

A render killed mid-write or a copy cut short still has a valid header; what gives it away is
the offset table OpenEXR writes after the header: an offset of 0 (never filled in), one past
the end of the file, or a last chunk that runs past the end. Layout per the OpenEXR file
format: magic, version flags, attributes (name NUL type NUL size value), NUL (and one more NUL
after the last header of a multi-part file), then one table of 64-bit offsets per part.
"""

from __future__ import annotations

import math
import mmap
import struct
from pathlib import Path

_MAGIC = 20000630
_TILED, _DEEP, _MULTIPART = 0x200, 0x800, 0x1000
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
            except (struct.error, IndexError, ValueError) as exc:
                return f"the header is cut short or damaged ({exc})"


def _check(data: mmap.mmap) -> str | None:
    magic, flags = struct.unpack_from("<ii", data, 0)
    if magic != _MAGIC:
        return "not an OpenEXR file"
    if flags & _DEEP:
        return None
    position, headers = 8, []
    while True:
        header, position = _read_header(data, position)
        headers.append(header)
        if not flags & _MULTIPART or data[position] == 0:
            break
    if flags & _MULTIPART:
        position += 1
    counts = [_chunk_count(h, bool(flags & _TILED)) for h in headers]
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
    prefix = 4 if flags & _MULTIPART else 0
    tiled = flags & _TILED or headers[0].get("type", b"").startswith(b"tiled")
    fields = 4 if tiled else 1
    (packed,) = struct.unpack_from("<i", data, last + prefix + 4 * fields)
    if last + prefix + 4 * fields + 4 + packed > size:
        return "the last pixel block runs past the end of the file (file cut short?)"
    return None


def _read_header(data: mmap.mmap, position: int) -> tuple[dict[str, bytes], int]:
    header: dict[str, bytes] = {}
    while data[position] != 0:
        name_end = _find_nul(data, position)
        type_end = _find_nul(data, name_end + 1)
        (length,) = struct.unpack_from("<i", data, type_end + 1)
        start = type_end + 5
        header[data[position:name_end].decode("latin-1")] = data[start : start + length]
        position = start + length
    return header, position + 1


def _find_nul(data: mmap.mmap, start: int) -> int:
    end = data.find(b"\0", start)
    if end < 0:
        raise ValueError("no end of attribute name")
    return end


def _chunk_count(header: dict[str, bytes], tiled_flag: bool) -> int | None:
    if "chunkCount" in header:
        return struct.unpack("<i", header["chunkCount"])[0]
    x0, y0, x1, y1 = struct.unpack("<iiii", header["dataWindow"])
    width, height = x1 - x0 + 1, y1 - y0 + 1
    if tiled_flag or "tiles" in header:
        tile_x, tile_y, mode = struct.unpack("<IIB", header["tiles"])
        if mode & 0x0F:  # mip- or rip-mapped: levels this check does not count
            return None
        return math.ceil(width / tile_x) * math.ceil(height / tile_y)
    compression = header["compression"][0]
    if compression >= len(_LINES):
        return None
    return math.ceil(height / _LINES[compression])
