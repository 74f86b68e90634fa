"""A malformed-EXR corpus, generated (no binary blobs): each case is a name, the bytes, and the
status the frame route must answer. Built from valid frames by rewriting header attributes,
truncating, and damaging bytes, so every case is reproducible from this file alone.

`python tests/exr_corpus.py OUT_DIR` writes the cases as files (for a fuzzer or a look).
"""

from __future__ import annotations

import io
import struct
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from conftest import frame_bytes, layout_plain, make_buffers, write_exr

HEIGHT, WIDTH = 48, 64


@dataclass(frozen=True)
class Case:
    name: str
    data: bytes
    status: int  # what POST .../frames/{i} must answer (200: denoised, finite)
    code: str | None = None  # the error code of a 4xx


# ---- header surgery -------------------------------------------------------------------------


@dataclass
class Attribute:
    name: str
    kind: str
    value: bytes


def parse_header(data: bytes) -> tuple[list[list[Attribute]], int]:
    """The parts' attributes and where the header ends (a small independent parser)."""
    multipart = struct.unpack("<I", data[4:8])[0] & 0x1000
    pos, parts = 8, []
    while True:
        attributes = []
        while data[pos] != 0:
            name_end = data.index(b"\0", pos)
            kind_end = data.index(b"\0", name_end + 1)
            (size,) = struct.unpack("<i", data[kind_end + 1 : kind_end + 5])
            value = data[kind_end + 5 : kind_end + 5 + size]
            attributes.append(
                Attribute(
                    data[pos:name_end].decode(), data[name_end + 1 : kind_end].decode(), value
                )
            )
            pos = kind_end + 5 + size
        pos += 1
        parts.append(attributes)
        if not multipart or data[pos] == 0:
            return parts, pos + (1 if multipart else 0)


def build_header(version: bytes, parts: list[list[Attribute]], multipart: bool) -> bytes:
    out = bytearray(b"\x76\x2f\x31\x01" + version)
    for attributes in parts:
        for a in attributes:
            out += a.name.encode() + b"\0" + a.kind.encode() + b"\0"
            out += struct.pack("<i", len(a.value)) + a.value
        out += b"\0"
    if multipart:
        out += b"\0"
    return bytes(out)


def rewrite(data: bytes, edit: Callable[[list[list[Attribute]]], None], flags: int = 0) -> bytes:
    """Apply `edit` to the parsed header and put the file back together (offsets are not
    fixed: cases that change the header's length are refused from the header alone)."""
    parts, end = parse_header(data)
    edit(parts)
    (version,) = struct.unpack("<I", data[4:8])
    version |= flags
    head = build_header(struct.pack("<I", version), parts, bool(version & 0x1000))
    return head + data[end:]


def set_attribute(part: int, name: str, kind: str, value: bytes):
    def edit(parts):
        for a in parts[part]:
            if a.name == name:
                a.kind, a.value = kind, value
                return
        parts[part].append(Attribute(name, kind, value))

    return edit


def replace_same_length(data: bytes, needle: bytes, value: bytes) -> bytes:
    at = data.index(needle) + len(needle)
    return data[:at] + value + data[at + len(value) :]


# ---- valid files of other shapes --------------------------------------------------------------


def plain_channels(seed: int = 0) -> dict[str, np.ndarray]:
    return layout_plain(make_buffers(HEIGHT, WIDTH, seed))


def tiled(mode=None) -> bytes:
    import OpenEXR

    tiles = OpenEXR.TileDescription()
    tiles.xSize, tiles.ySize = 16, 16
    tiles.mode = mode if mode is not None else OpenEXR.ONE_LEVEL
    return write_exr(plain_channels(), {"type": OpenEXR.tiledimage, "tiles": tiles})


def multipart(second_type: str | None = None) -> bytes:
    """Two scanline parts (colour+albedo / normal+depth); `second_type` rewrites the second
    part's type attribute (a deep part in a file whose non-image flag is clear)."""
    import OpenEXR

    channels = plain_channels()
    first = {k: v for k, v in channels.items() if "." not in k or k.startswith("albedo")}
    second = {k: v for k, v in channels.items() if k not in first}
    def header():
        return {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}

    parts = [
        OpenEXR.Part(header(), {k: np.ascontiguousarray(v) for k, v in first.items()}, "beauty"),
        OpenEXR.Part(header(), {k: np.ascontiguousarray(v) for k, v in second.items()}, "aovs"),
    ]
    out = io.BytesIO()
    OpenEXR.File(parts).write(out)
    data = out.getvalue()
    if second_type is not None:
        data = rewrite(data, set_attribute(1, "type", "string", second_type.encode()))
    return data


def with_values(value: float, dtype=np.float32) -> bytes:
    """A valid frame whose colour holds `value` in a 4x4 block."""
    b = make_buffers(HEIGHT, WIDTH, 3)
    b["color"][8:12, 8:12] = value
    return write_exr(layout_plain(b), dtype=dtype)


# ---- the corpus ---------------------------------------------------------------------------------


def cases() -> Iterator[Case]:
    import OpenEXR

    good = frame_bytes(height=HEIGHT, width=WIDTH)
    parts, end = parse_header(good)
    yield Case("valid", good, 200)
    yield Case("valid-half", frame_bytes(height=HEIGHT, width=WIDTH, dtype=np.float16), 200)
    yield Case("valid-tiled-one-level", tiled(), 200)
    yield Case("valid-multipart", multipart(), 200)
    for value in (1e5, 1e30, np.inf, -np.inf, np.nan, -1e30):
        yield Case(f"colour-{value}", with_values(value), 200)
    yield Case("colour-half-inf", with_values(np.inf, np.float16), 200)

    yield Case("empty", b"", 400, "bad_exr")
    yield Case("magic-only", good[:4], 400, "bad_exr")
    yield Case("not-exr", b"GIF89a" + bytes(4000), 400, "bad_exr")
    yield Case("version-3", good[:4] + b"\x03" + good[5:], 400, "bad_exr")
    for cut in (8, 40, end - 1, end, end + 8, len(good) // 2, len(good) - 1):
        yield Case(f"truncated-{cut}", good[:cut], 400, "bad_exr")
    yield Case("deep-flag", good[:5] + bytes([good[5] | 0x08]) + good[6:], 422, "unsupported_exr")
    yield Case("multipart-deep-part", multipart("deepscanline"), 422, "unsupported_exr")
    yield Case("multipart-deeptile-part", multipart("deeptile"), 422, "unsupported_exr")
    yield Case(
        "part-type-unknown", rewrite(good, set_attribute(0, "type", "string", b"x")), 400, "bad_exr"
    )
    yield Case("mipmap", tiled(OpenEXR.MIPMAP_LEVELS), 422, "unsupported_exr")
    yield Case("ripmap", tiled(OpenEXR.RIPMAP_LEVELS), 422, "unsupported_exr")
    yield Case(
        "tiled-flag-without-tiles", good[:5] + bytes([good[5] | 0x02]) + good[6:], 400, "bad_exr"
    )
    compression = b"compression\0compression\0\x01\0\0\0"
    yield Case("compression-255", replace_same_length(good, compression, b"\xff"), 400, "bad_exr")
    yield Case("compression-99", replace_same_length(good, compression, b"\x63"), 400, "bad_exr")
    window = b"dataWindow\0box2i\0\x10\0\0\0"
    yield Case(
        "window-empty",
        replace_same_length(good, window, struct.pack("<4i", 5, 5, 0, 0)),
        400,
        "bad_exr",
    )
    yield Case(
        "window-huge",
        replace_same_length(good, window, struct.pack("<4i", 0, 0, 99999, 9)),
        413,
        "resolution_too_large",
    )
    yield Case(
        "window-other-size",
        replace_same_length(good, window, struct.pack("<4i", 0, 0, WIDTH - 2, HEIGHT - 1)),
        422,
        "size_mismatch",
    )
    yield Case(
        "no-channels",
        rewrite(
            good,
            lambda p: p[0].__delitem__(next(i for i, a in enumerate(p[0]) if a.name == "channels")),
        ),
        400,
        "bad_exr",
    )
    yield Case(
        "channel-type-7",
        rewrite(
            good,
            set_attribute(
                0, "channels", "chlist", b"R\0" + struct.pack("<iB3xii", 7, 0, 1, 1) + b"\0"
            ),
        ),
        400,
        "bad_exr",
    )
    yield Case(
        "subsampled",
        rewrite(
            good,
            set_attribute(
                0, "channels", "chlist", b"R\0" + struct.pack("<iB3xii", 1, 0, 2, 2) + b"\0"
            ),
        ),
        422,
        "unsupported_exr",
    )
    yield Case("only-red", write_exr({"R": plain_channels()["R"]}), 422, "missing_channels")
    owner = rewrite(good, set_attribute(0, "owner", "string", b"x"))
    negative = owner.replace(b"owner\0string\0\x01\0\0\0x", b"owner\0string\0\xff\xff\xff\xffx")
    yield Case("attribute-size-negative", negative, 400, "bad_exr")
    damaged = bytearray(good)
    for i in range(end + 200, len(good) - 50, 97):
        damaged[i] ^= 0x5A
    yield Case("pixels-damaged", bytes(damaged), 400, "bad_exr")
    offsets = bytearray(good)
    offsets[end : end + 8 * HEIGHT] = b"\xff" * (8 * HEIGHT)
    yield Case("offset-table-garbage", bytes(offsets), 400, "bad_exr")


def main(out: str) -> None:
    folder = Path(out)
    folder.mkdir(parents=True, exist_ok=True)
    for case in cases():
        (folder / f"{case.name}.{case.status}.exr").write_bytes(case.data)


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).parent))
    main(sys.argv[1])
