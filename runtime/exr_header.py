"""EXR header checks: what a frame is, checked before any pixel is decoded.

The header's bytes are walked by the one EXR header reader, quietframe.wire.exr_layout (attribute
values are not copied; a header is capped at `max_header_bytes`; an attribute is refused when its
size is read). Here: what the decoder could not read (deep parts, mip/ripmaps, subsampling, bad
compression or line order), the resolution, how large the file can be, the cut flag, and the
reader's errors as the service's (BadExr, UnsupportedExr, ExrHeaderTooLarge: runtime/frame_errors).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import OpenEXR

from quietframe.runtime.frame_errors import (
    BadExr,
    ExrHeaderTooLarge,
    ResolutionTooLarge,
    ServiceError,
    SizeMismatch,
    UnsupportedExr,
)
from quietframe.wire.exr_layout import (
    MAGIC,
    NON_IMAGE,
    TILED,
    AttributeRef,
    ChannelInfo,
    HeaderError,
    HeaderOverCap,
    HeaderTruncated,
    PartsWalk,
    TooManyChannels,
    TooManyParts,
    attribute,
    raw_value,
    read_channels,
    read_version,
)
from quietframe.wire.protocol import CUT_ATTRIBUTE

_MAX_ATTRIBUTES = 4096  # a header with more is not a render's
# Nor a file with more channels (layers and AOVs: hundreds at most); the channel names are
# matched against the renderer aliases on the event loop, ~2 us each.
_MAX_CHANNELS = 4096
# Nor more parts: a renderer writes one per AOV at most (tens; Arnold and RenderMan a few
# hundred at the very most). Each part costs the decoder and the reply's writer memory of its
# own beyond its pixels (admission.PART_OVERHEAD_BYTES): 20 000 one-channel parts grew RSS by
# 4.7 GiB (the 2026-12-06 audit, R4-14), so the count is refused while the header streams in.
MAX_PARTS = 256
_MAX_ATTRIBUTE_BYTES = 64 << 20  # a preview image or ICC profile is far smaller
# Attribute values up to this size are copied into ExrHeader.attributes (what the service reads:
# windows, strings, the sample count); larger ones (previews, ICC profiles) stay in the body.
_COPIED_ATTRIBUTE_BYTES = 64 << 10
_COMPRESSION_METHODS = int(OpenEXR.NUM_COMPRESSION_METHODS)  # compression bytes this build reads
_LINE_ORDERS = ("increasing", "decreasing", "random")


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


def _frame_error(exc: HeaderError) -> ServiceError:
    """The header reader's error as the service answers it."""
    if isinstance(exc, HeaderTruncated):
        return TruncatedExr(str(exc))
    if isinstance(exc, HeaderOverCap):
        return ExrHeaderTooLarge(
            f"the EXR header is over {exc.cap} bytes (QUIETFRAME_MAX_HEADER_BYTES): leave "
            "large attributes (previews, ICC profiles, metadata blobs) out of the frames "
            "sent for denoising, or raise the limit"
        )
    if isinstance(exc, TooManyParts):
        return UnsupportedExr(
            f"the EXR has over {MAX_PARTS} parts; write the passes the denoiser reads (colour, "
            "albedo, normal, depth, motion) into a few parts, or one multilayer part, and leave "
            "the rest out")
    if isinstance(exc, TooManyChannels):
        return _too_many_channels()
    return BadExr(str(exc))


class HeaderScan:
    """A header parsed as its bytes arrive: each `advance` reads only the attributes completed
    since the last call (wire.exr_layout.PartsWalk), and the whole header is checked once its
    end is there."""

    def __init__(
        self, max_width: int, max_height: int, max_header_bytes: int | None = None
    ) -> None:
        self.max_width, self.max_height, self.cap = max_width, max_height, max_header_bytes
        self.walk: PartsWalk | None = None  # made once the magic number and version are read

    def advance(self, data) -> ExrHeader | None:
        """The checked header once `data` (the body so far; it only grows) holds all of it,
        else None; raises as read_header does."""
        try:
            walk = self.walk
            if walk is None:
                if len(data) < 8 and MAGIC.startswith(bytes(data[:4])):
                    return None  # the magic number so far: the version is still to come
                version, name_limit = _version(data)
                walk = self.walk = PartsWalk(
                    version, name_limit, self.cap, _MAX_ATTRIBUTES, MAX_PARTS, _MAX_ATTRIBUTE_BYTES
                )
            if not walk.advance(data):
                return None
            return _checked_header(data, walk, self.max_width, self.max_height)
        except HeaderError as exc:
            raise _frame_error(exc) from exc


def _version(data) -> tuple[int, int]:
    """The version field's flags and the longest name they allow; deep files refused."""
    version, name_limit = read_version(data)
    if version & NON_IMAGE:
        raise UnsupportedExr(_DEEP_DETAIL)
    return version, name_limit


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
        try:
            _version(data)  # raises: too short for a header
        except HeaderError as exc:
            raise _frame_error(exc) from exc
    header = HeaderScan(max_width, max_height, max_header_bytes).advance(data)
    if header is None:
        raise TruncatedExr("EXR header is truncated")
    return header


def _checked_header(data, walk: PartsWalk, max_width: int, max_height: int) -> ExrHeader:
    """The header `walk` has read, after the checks that need no pixels."""
    parts, end = walk.parts, walk.pos
    channels: dict[str, ChannelInfo] = {}
    window: Box | None = None
    max_bytes, pixel_bytes = end + 1, 0
    for number, refs in enumerate(parts):
        part_window, part_channels = _check_part(data, number, refs, walk)
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
        {n: (r.kind, raw_value(data, r)) for n, r in first.items()
         if r.size <= _COPIED_ATTRIBUTE_BYTES},
        window,
        attribute(data, first, "displayWindow", "box2i"),
        pixel_bytes,
    )


def _check_channel_count(count: int) -> None:
    if count > _MAX_CHANNELS:
        raise _too_many_channels()


def _too_many_channels() -> UnsupportedExr:
    return UnsupportedExr(
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
    data, number: int, refs: Mapping[str, AttributeRef], walk: PartsWalk
) -> tuple[Box, dict[str, ChannelInfo]]:
    """One part's data window and channels, after the checks that need no pixels: its type
    (deep parts are refused however the file's flags are set), tiling, compression."""
    if "dataWindow" not in refs or "channels" not in refs:
        raise BadExr("EXR header lacks its dataWindow or channels attribute")
    try:
        window: Box = attribute(data, refs, "dataWindow", "box2i")
    except HeaderError as exc:
        raise BadExr("EXR dataWindow attribute is malformed") from exc
    width, height = _box_size(window)
    if width < 1 or height < 1:
        raise BadExr(f"EXR dataWindow is empty {window}")
    part_type = attribute(data, refs, "type", "string")
    if part_type is not None and part_type.startswith("deep"):
        raise UnsupportedExr(f"part {number} is {part_type}: {_DEEP_DETAIL}")
    if part_type is not None and part_type not in _IMAGE_TYPES:
        raise BadExr(f"part {number} has an unknown EXR part type {part_type!r}")
    tiled = _IMAGE_TYPES[part_type] if part_type is not None else bool(walk.version & TILED)
    if tiled:
        _check_tiles(data, number, refs)
    try:
        compression = attribute(data, refs, "compression", "compression")
    except HeaderError:
        compression = -1
    if compression is not None and not 0 <= compression < _COMPRESSION_METHODS:
        raw = raw_value(data, refs["compression"]).hex()
        raise BadExr(f"part {number} has an invalid EXR compression attribute ({raw})")
    order = attribute(data, refs, "lineOrder", "lineOrder")
    if order is not None and order >= len(_LINE_ORDERS):
        raise BadExr(f"part {number} has an invalid EXR lineOrder attribute ({order})")
    try:
        channel_list = raw_value(data, refs["channels"])
        part_channels = read_channels(channel_list, walk.name_limit, _MAX_CHANNELS)
    except HeaderTruncated as exc:  # the attribute is whole: its content is malformed
        raise BadExr("EXR channel list is malformed") from exc
    return window, part_channels


def _tiles(data, refs: Mapping[str, AttributeRef]) -> tuple[int, int, int] | None:
    try:
        return attribute(data, refs, "tiles", "tiledesc")
    except HeaderError:
        return None


def _check_tiles(data, number: int, refs: Mapping[str, AttributeRef]) -> None:
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


def _max_part_bytes(
    data, size: tuple[int, int], pixels: int, refs: Mapping[str, AttributeRef]
) -> int:
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


def _cut_flag(data, refs: Mapping[str, AttributeRef]) -> bool:
    """The client's cut flag (wire/protocol.py): a non-zero int or a string such as "1"."""
    ref = refs.get(CUT_ATTRIBUTE)
    if ref is None or ref.kind not in ("int", "string"):
        return False
    try:
        flag = attribute(data, refs, CUT_ATTRIBUTE, ref.kind)
    except HeaderError:  # an int of another size: not a flag the client wrote
        return False
    if isinstance(flag, str):
        return flag.strip().lower() in ("1", "true", "yes", "cut")
    return flag != 0
