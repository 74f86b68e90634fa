"""More renders of a finished sequence, from its scene loaded again (`SequenceScene`): a second
reference of a frame (how noisy the stored reference is, `reference_noise`) and colour levels
above the stored passes (`topup_sequence`, for evaluation at higher spp).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from . import exr_io
from .camera import Camera
from .manifest import MANIFEST, write_json
from .mitsuba_scene import movers_of, set_frame
from .mitsuba_trace import render_passes, render_reference, sampler_seed
from .preview import LUMA
from .render import RenderConfig, load_scene

# Salt of the second reference `reference_noise` renders (the stored one uses 1_000_003).
REFERENCE_NOISE_SALT = 2_000_003


def _config_of(manifest: dict) -> RenderConfig:
    c = manifest["config"]
    return RenderConfig(
        width=c["width"],
        height=c["height"],
        frames=tuple(c["frames"]),
        spp_levels=tuple(c["spp_levels"]),
        reference_spp=c["reference_spp"],
        max_depth=c["max_depth"],
        locked_off=c.get("locked_off", False),
    )


class SequenceScene:
    """A finished sequence's scene loaded again (one load, then any of its frames): what a
    second reference or extra passes of a stored frame are rendered from. Needs a Mitsuba
    variant set (`set_variant`)."""

    def __init__(self, seq_dir: str | Path) -> None:
        self.dir = Path(seq_dir)
        self.manifest = json.loads((self.dir / MANIFEST).read_text())
        self.config = _config_of(self.manifest)
        desc = self.manifest["scene"]
        self.scene, self.path, self.albedo_table = load_scene(desc, self.config)
        self._cameras = desc["cameras"]
        self._movers = movers_of(self.scene, desc)

    @property
    def seed(self) -> int:
        return self.manifest["seed"]

    @property
    def exposure(self) -> float:
        return self.manifest["exposure"]

    def at(self, frame: int) -> SequenceScene:
        set_frame(self.scene, Camera(**self._cameras[frame]), self._movers, frame)
        return self


def render_second_reference(
    seq_dir: str | Path, frame: int, salt: int = REFERENCE_NOISE_SALT
) -> tuple[np.ndarray, float]:
    """Render another reference of one finished frame, independent of the stored one: the
    sequence's scene, camera and movers at `frame`, as many samples as the stored reference
    (`RenderConfig.reference_samples`) seeded from (sequence seed, frame, `salt`). Returns the
    (H, W, 3) float32 radiance times the sequence's exposure (comparable with the stored
    `reference` layer) and the render's seconds. A salt other than 1_000_003 (the stored
    reference's) and REFERENCE_NOISE_SALT gives a reference independent of both. Needs a
    Mitsuba variant set (`set_variant`)."""
    seq = SequenceScene(seq_dir).at(frame)
    t0 = time.perf_counter()
    second, _ = render_reference(seq.scene, seq.path, sampler_seed(seq.seed, frame, salt),
                                 seq.config.reference_samples)
    seconds = time.perf_counter() - t0
    return (second * seq.exposure).astype(np.float32), seconds


def reference_noise(seq_dir: str | Path, frame: int, eps: float = 0.01) -> dict:
    """Render a second reference of one finished frame with an independent seed and compare
    it with the stored one (luminance, after exposure): the median over pixels of
    |a - b| / ((a + b) / 2 + eps). eps (in units of the exposed image, whose mean is
    0.15-0.6) keeps black pixels from dominating. For independent references of equal spp
    this is ~0.95 x the per-pixel relative standard deviation of one reference (Gaussian)."""
    seq = Path(seq_dir)
    m = json.loads((seq / MANIFEST).read_text())
    second, seconds = render_second_reference(seq, frame)
    stored = exr_io.load_frame(seq / f"frame_{frame:04d}.exr", ["reference"])["reference"]
    a, b = stored @ LUMA, second @ LUMA
    rel = np.abs(a - b) / ((a + b) / 2 + eps)
    return {
        "seed": m["seed"],
        "frame": frame,
        "median_relative_difference": float(np.median(rel)),
        "mean_relative_difference": float(np.mean(rel)),
        "seconds": round(seconds, 1),
    }


# ---------------------------------------------------------------------------------------------
# Colour levels above the stored passes (evaluation at higher spp)

TOPUP_SALT = 4_000_037  # extra passes' seeds: independent of the stored passes and references
TOPUP_KEY = "topup_spp_levels"


def topup_sequence(seq_dir: str | Path, spp: int) -> int:
    """Add a colour level of `spp` samples (more than the stored passes, e.g. 16 over 8) to
    every frame of a finished sequence: spp − passes further one-sample passes, seeded from
    (sequence seed, frame, TOPUP_SALT), averaged with the stored passes into `color_<spp>spp`.
    The aux buffers and motion stay those of the stored passes (means over 8 samples: nearly
    noise-free already). Frames that have the level are skipped; the level is listed under
    `topup_spp_levels` in the manifest and the frames' metadata, not in `config.spp_levels`,
    so the render config (and resuming `render`) is unchanged and training never draws it.
    Returns the number of frames written."""
    seq_dir = Path(seq_dir)
    manifest = json.loads((seq_dir / MANIFEST).read_text())
    stored = max(manifest["config"]["spp_levels"])
    if spp <= stored:
        raise ValueError(f"{seq_dir}: {spp} spp is stored already (passes: {stored})")
    layer = exr_io.color_layer(spp)
    todo = [f for f in sorted(seq_dir.glob("frame_*.exr")) if layer not in exr_io.frame_layers(f)]
    seq = SequenceScene(seq_dir) if todo else None
    for path in todo:
        meta = exr_io.read_meta(path)
        frame = int(meta["frame"])
        layers = exr_io.load_frame(path)
        extra = render_passes(seq.at(frame).scene, seq.path,
                              sampler_seed(seq.seed, frame, TOPUP_SALT), spp - stored,
                              seq.albedo_table)
        total = layers[exr_io.color_layer(stored)].astype(np.float64) * stored
        total += np.sum([p["radiance"] for p in extra], 0, dtype=np.float64) * seq.exposure
        layers[layer] = (total / spp).astype(np.float32)
        meta[TOPUP_KEY] = sorted({*meta.get(TOPUP_KEY, []), spp})
        exr_io.write_frame(path, layers, meta)
    if todo or spp not in manifest.get(TOPUP_KEY, []):
        manifest[TOPUP_KEY] = sorted({*manifest.get(TOPUP_KEY, []), spp})
        write_json(seq_dir / MANIFEST, manifest)
    return len(todo)
