"""Read the Cycles splits (scenes/cycles_render.py) the way the service reads a farm's frames.

Inputs are decoded by the EXR code the service reads uploads with (runtime/exr_header.py,
exr_channels.py, exr_codec.py: header, alias table, decode), so the evaluation and training see
exactly what a Blender farm's upload turns into: `Noisy Image` as the colour, `Denoising
Albedo/Normal/Depth`, `Vector` as backward motion.
Also read: Blender's own denoise of the same render (`Combined`), and the reference (the mean
of its two independent halves). Numpy only (no bpy): runs in the project's venv.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from quietframe.runtime.buffers import BUFFER_CHANNELS, FORWARD
from quietframe.runtime.exr_channels import resolve
from quietframe.runtime.exr_codec import decode
from quietframe.runtime.exr_header import read_header

MANIFEST = "manifest.json"
REFERENCE_HALVES = ("reference_a", "reference_b")
INPUT_BUFFERS = ("color", "albedo", "normal", "depth", "motion")
_NO_LIMIT = 1 << 15


def is_cycles_sequence(folder: Path) -> bool:
    m = folder / MANIFEST
    return m.exists() and json.loads(m.read_text()).get("renderer") == "cycles"


def frame_file(t: int) -> str:
    """Frame t's file name (Blender numbers frames from 1)."""
    return f"frame_{t + 1:04d}.exr"


def level_dir(spp: int) -> str:
    return f"spp{spp:04d}"


def _decode(path: Path, mapping: dict | None = None) -> dict[str, np.ndarray]:
    """(H, W, C) float32 buffers of one Blender EXR through the service's decoder; a buffer
    the file lacks or carries unusable (Vector all zero: a static shot) is absent."""
    data = path.read_bytes()
    header = read_header(data, _NO_LIMIT, _NO_LIMIT)
    wanted = ("color",) if mapping else INPUT_BUFFERS
    sources = resolve(list(header.channels), ["color"], wanted[1:], mapping=mapping)
    decoded = decode(data, sources)
    return {k: v.transpose(1, 2, 0) for k, v in decoded.buffers.items()}


def load_inputs(folder: Path, t: int, spp: int) -> dict[str, np.ndarray]:
    """Frame t's input buffers at `spp` as the service decodes them; one the file lacks (motion
    where the Vector pass is all zero) is zeros, as the runtime feeds an absent buffer."""
    out = _decode(folder / level_dir(spp) / frame_file(t))
    h, w = out["color"].shape[:2]
    for name in INPUT_BUFFERS:
        if name not in out:
            out[name] = np.zeros((h, w, BUFFER_CHANNELS[name]), np.float32)
    return out


def load_forward(folder: Path, t: int, spp: int) -> np.ndarray | None:
    """Frame t's motion to frame t + 1 at `spp`, (H, W, 2), as a look-ahead session decodes it
    (Cycles' Vector.ZW: runtime/exr_channels); None where it is all zero (motion blur on)."""
    data = (folder / level_dir(spp) / frame_file(t)).read_bytes()
    header = read_header(data, _NO_LIMIT, _NO_LIMIT)
    sources = resolve(list(header.channels), [], [FORWARD])
    forward = decode(data, sources).buffers.get(FORWARD) if sources else None
    return None if forward is None else forward.transpose(1, 2, 0)


def load_frame(folder: Path, t: int, spp: int) -> dict[str, np.ndarray]:
    """Frame t of a Cycles sequence at `spp`: the input buffers (load_inputs),
    `blender_denoise` (Blender's OIDN output of that render) and `reference` (the mean of the
    two halves; a locked-off shot's frames share frame 1's)."""
    path = folder / level_dir(spp) / frame_file(t)
    out = load_inputs(folder, t, spp)
    out["blender_denoise"] = _decode(path, {"color": "ViewLayer.Combined"})["color"]
    out["reference"] = load_reference(folder, t)
    return out


def reference_frame(folder: Path, t: int) -> int:
    manifest = json.loads((folder / MANIFEST).read_text())
    return 0 if manifest["config"].get("locked_off") else t


def load_reference(folder: Path, t: int) -> np.ndarray:
    r = reference_frame(folder, t)
    halves = [_decode(folder / h / frame_file(r), {"color": "ViewLayer.Combined"})["color"]
              for h in REFERENCE_HALVES]
    return ((halves[0] + halves[1]) / 2).astype(np.float32)


def load_reference_aux(folder: Path, t: int) -> dict[str, np.ndarray]:
    """Frame t's buffers as the reference's first half holds them (hundreds of samples: aux
    far cleaner than any input's; experiments/albedo_noise.py)."""
    return _decode(folder / REFERENCE_HALVES[0] / frame_file(reference_frame(folder, t)))


def frame_resets(folder: Path) -> list[bool]:
    """Per frame: first frame or after a cut (history must restart)."""
    manifest = json.loads((folder / MANIFEST).read_text())
    cuts = set(manifest["cuts"])
    return [t == 0 or t in cuts for t in range(manifest["frame_count"])]


def finished(folder: Path, spp_levels: tuple[int, ...] = ()) -> bool:
    """Every frame has its inputs (at `spp_levels`, default all configured) and reference."""
    mpath = folder / MANIFEST
    if not mpath.exists():
        return False
    manifest = json.loads(mpath.read_text())
    levels = spp_levels or tuple(manifest["config"]["spp_levels"])
    n = manifest["frame_count"]
    inputs = all((folder / level_dir(s) / frame_file(t)).exists()
                 for s in levels for t in range(n))
    refs = {reference_frame(folder, t) for t in range(n)}
    return inputs and all((folder / h / frame_file(r)).exists()
                          for h in REFERENCE_HALVES for r in refs)
