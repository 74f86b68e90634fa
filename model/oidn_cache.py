"""OIDN's output of rendered frames, computed once and cached on disk (training of oidn-temporal).

The temporal stage trains on what the runtime will feed it: the same sanitising rule and the
same prepass code (runtime/oidn_prepass.py) on the full frame (crops come after, as OIDN is not
crop-equivariant at the borders). One .npy per (sequence, frame, spp, OIDN settings):

    ~/.cache/quietframe/oidn/<generator>/<split>/<seed>/<frame>.spp<N>.<quality>[-cleanaux]
        [-<color_from stem>].npy

(QUIETFRAME_OIDN_CACHE overrides the root). With a prepass `color_from` model (e.g. the
reprojected accumulation), OIDN's input for frame t depends on frames 0..t: the whole sequence
goes through that model, from its first frame with resets at cuts exactly as the runtime runs
it (the runtime's own Denoiser on the shipped .onnx), and every frame is cached at once.
Files are written atomically, so concurrent loader processes and killed runs never leave a torn
one.
"""

from __future__ import annotations

import os
import threading
from pathlib import Path

import numpy as np

from quietframe.models import MODELS_DIR
from quietframe.runtime.buffers import planes_from_hwc
from quietframe.runtime.denoiser import Denoiser
from quietframe.runtime.oidn_prepass import OIDNPrepass, OIDNSettings
from quietframe.runtime.sanitize import sanitize_buffer
from quietframe.scenes.exr_io import color_layer, load_frame
from quietframe.scenes.layout import OIDN_CACHE_DIR

_prepasses: dict[OIDNSettings, OIDNPrepass] = {}
_lock = threading.Lock()


def cache_root() -> Path:
    return Path(os.environ.get("QUIETFRAME_OIDN_CACHE", OIDN_CACHE_DIR)).expanduser()


def cache_path(sequence_dir: Path, frame_file: str, spp: int, settings: OIDNSettings) -> Path:
    """Keyed by the sequence's last three path parts (generator/split/seed), frame, spp and
    the OIDN settings."""
    suffix = (f"{settings.quality}{'-cleanaux' if settings.prefilter_aux else ''}"
              f"{'-' + Path(settings.color_from).stem if settings.color_from else ''}")
    stem = Path(frame_file).stem
    return cache_root().joinpath(*Path(sequence_dir).parts[-3:], f"{stem}.spp{spp}.{suffix}.npy")


def _prepass(settings: OIDNSettings) -> OIDNPrepass:
    with _lock:
        if settings not in _prepasses:
            _prepasses[settings] = OIDNPrepass(settings)
        return _prepasses[settings]


def oidn_output(color: np.ndarray, albedo: np.ndarray, normal: np.ndarray,
                settings: OIDNSettings) -> np.ndarray:
    """OIDN of (H, W, 3) images through the runtime's rule and prepass -> (H, W, 3) float32."""
    planes = {}
    for name, image in (("color", color), ("albedo", albedo), ("normal", normal)):
        clean, _ = sanitize_buffer(name, np.ascontiguousarray(
            np.asarray(image, np.float32)[..., :3].transpose(2, 0, 1)))
        planes[name] = np.ascontiguousarray(clean)
    return np.ascontiguousarray(_prepass(settings)(planes)[0].transpose(1, 2, 0))


def cached_oidn_output(sequence_dir: Path, frame_file: str, spp: int, settings: OIDNSettings,
                       color: np.ndarray, albedo: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """The cached OIDN output of one frame ((H, W, 3) images in), computing and storing it on a
    miss. An entry of another size (same seed rendered again at another size) is recomputed."""
    path = cache_path(sequence_dir, frame_file, spp, settings)
    if path.exists():
        cached = np.load(path)
        if cached.shape == (*np.shape(color)[:2], 3):
            return cached
    result = oidn_output(color, albedo, normal, settings)
    save_array(path, result)
    return result


def save_array(path: Path, array: np.ndarray) -> None:
    """np.save to `path` atomically (a temp file per process and thread, then a rename): a
    killed or concurrent writer never leaves a torn cache file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(f".{os.getpid()}.{threading.get_ident()}.tmp")
    try:
        with tmp.open("wb") as f:
            np.save(f, array)
        tmp.replace(path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def cached_sequence_oidn_output(sequence_dir: Path, files: list[str], resets: list[bool],
                                index: int, spp: int, settings: OIDNSettings) -> np.ndarray:
    """OIDN's output of frame `index` for a prepass with `color_from`: on a miss, the whole
    sequence (`files` in order, `resets` per frame) runs through the color_from model and OIDN,
    and every frame is cached."""
    path = cache_path(sequence_dir, files[index], spp, settings)
    if path.exists():
        return np.load(path)
    first = Denoiser(MODELS_DIR / settings.color_from, threads=1, tile_pixels=None)
    aux = [b for b in (*first.info.required_buffers, *first.info.optional_buffers)
           if b != "color"]
    state, wanted = None, None
    for i, name in enumerate(files):
        layers = load_frame(Path(sequence_dir) / name, [color_layer(spp), *aux])
        buffers = {"color": layers[color_layer(spp)], **{b: layers[b] for b in aux}}
        result = first.denoise(planes_from_hwc(buffers), None if resets[i] else state)
        state = result.state
        color = result.color.transpose(1, 2, 0)
        output = oidn_output(color, buffers["albedo"], buffers["normal"], settings)
        save_array(cache_path(sequence_dir, name, spp, settings), output)
        if i == index:
            wanted = output
    return wanted
