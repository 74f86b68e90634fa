"""The rendered frames on disk, without bpy: what an EXR's header says (its size and view layers,
read by quietframe's own header reader, wire.exr_layout), where a denoised frame goes, and
writing it so that a reader never sees half a file."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from .server_api import DenoiseError
from .wire import exr_layout, protocol

DENOISED_SUFFIX = "_denoised"


@dataclass(frozen=True)
class FrameHeader:
    width: int
    height: int
    view_layers: tuple[str, ...]  # Blender's `<layer>.<pass>.<channel>` names; () single-layer


def read_header(data: bytes, name: str) -> FrameHeader:
    """The data window's size and the view layers of an EXR's bytes; DenoiseError naming the
    file when it is not a complete EXR header."""
    try:
        version, name_limit = exr_layout.read_version(data)
        walk = exr_layout.PartsWalk(version, name_limit)
        if not walk.advance(data):
            raise exr_layout.HeaderTruncated("EXR header is truncated")
        channels: list[str] = []
        for part in walk.parts:
            ref = part.get("channels")
            if ref is not None:
                raw = exr_layout.raw_value(data, ref)
                channels.extend(exr_layout.read_channels(raw, name_limit))  # the names
        window = exr_layout.attribute(data, walk.parts[0], "dataWindow", "box2i")
    except exr_layout.HeaderError as exc:
        raise DenoiseError(f"{name} is not a readable EXR: {exc}") from exc
    if window is None:
        raise DenoiseError(f"{name} is not a readable EXR: its header has no dataWindow")
    x0, y0, x1, y1 = window
    return FrameHeader(x1 - x0 + 1, y1 - y0 + 1, protocol.view_layers(channels))


def session_layer(header: FrameHeader, wanted: str | None, name: str) -> str | None:
    """The session's `layer`: the view layer to denoise where the file holds several (the
    server refuses such a file without one), None where it holds one or none."""
    layers = header.view_layers
    if len(layers) <= 1:
        return None
    if wanted in layers:
        return wanted
    raise DenoiseError(
        f"{name} holds the view layers {', '.join(layers)}: choose the one to denoise in the "
        f"quietframe panel (now {wanted or 'none'})"
    )


def output_path(source: Path, folder: Path | None) -> Path:
    """Where the denoised frame goes: beside its source as `<name>_denoised.exr`, or in
    `folder` under the source's own name (never over the source itself)."""
    if folder is None:
        stem = source.name[: -len(".exr")] if source.name.lower().endswith(".exr") else source.name
        return source.with_name(f"{stem}{DENOISED_SUFFIX}.exr")
    target = folder / source.name
    if target.resolve() == source.resolve():
        raise DenoiseError(
            f"the denoised folder {folder} is the render's own folder: the denoised frames "
            "would replace the renders; choose another folder or 'Beside the render'"
        )
    return target


def write_atomically(path: Path, data: bytes) -> None:
    """Write to a temporary name in the same folder, then rename over `path`."""
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(f".{path.name}.part")
    try:
        with open(partial, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(partial, path)
    except OSError as exc:
        partial.unlink(missing_ok=True)
        raise DenoiseError(f"could not write {path}: {exc.strerror or exc}") from exc


def is_rendered(path: Path) -> bool:
    """A frame that exists and is not one of Blender's empty placeholder files."""
    try:
        return path.stat().st_size > 0
    except OSError:
        return False
