"""The Blender add-on (blender/quietframe_blender) for the tests of tests/blender/: its folder on
sys.path, so that its bpy-free modules import as `quietframe_blender.*` in plain Python (from a
checkout they take the wire package from quietframe.wire), and checks of the files it writes."""

from __future__ import annotations

import importlib
import io
import shutil
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
ADDON_PARENT = ROOT / "blender"
SEQUENCES = ROOT / "tests" / "fixtures" / "blender_sequences"

if str(ADDON_PARENT) not in sys.path:
    sys.path.insert(0, str(ADDON_PARENT))


def extension_builder():
    """blender/build_extension.py, the script `make blender-addon` runs, as a module."""
    return importlib.import_module("build_extension")


def channels(path: Path) -> tuple[tuple[int, int], dict[str, np.ndarray]]:
    """(width, height) of the data window and every channel's pixels of an EXR file."""
    import OpenEXR

    exr = OpenEXR.File(io.BytesIO(path.read_bytes()), separate_channels=True)
    (x0, y0), (x1, y1) = exr.header()["dataWindow"]
    return (int(x1 - x0 + 1), int(y1 - y0 + 1)), {k: v.pixels for k, v in exr.channels().items()}


def assert_denoised(source: Path, output: Path, size: tuple[int, int]) -> None:
    """`output` is the server's reply for `source`: a readable EXR of `size`, every value finite,
    the source's channels, the beauty's colour changed and the aux passes carried through."""
    got_size, got = channels(output)
    _, given = channels(source)
    assert got_size == size, (output, got_size)
    assert set(got) == set(given), output
    assert all(np.isfinite(v).all() for v in got.values()), output
    colour = [n for n in given if ".Combined." in n and n[-1] in "RGB"]
    assert colour and any(not np.array_equal(got[n], given[n]) for n in colour), output
    for name in given:
        if "Denoising" in name or ".Vector." in name:
            np.testing.assert_array_equal(got[name], given[name], err_msg=name)


def copy_sequence(folder: Path, name: str, frames, as_name: str = "shot") -> dict[int, Path]:
    """Cycles fixture frames `name`.000N.exr copied as `as_name`_000N.exr (Blender's default
    frame naming); frame -> its copy."""
    folder.mkdir(parents=True, exist_ok=True)
    sources = {}
    for frame in frames:
        target = folder / f"{as_name}_{frame:04d}.exr"
        shutil.copy(SEQUENCES / f"{name}.{frame:04d}.exr", target)
        sources[frame] = target
    return sources
