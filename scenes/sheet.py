"""Contact sheet: one row per sequence (first frame): 1 spp, max spp, reference, albedo,
normal, motion magnitude of the last rendered frame, and that frame's reference. Row labels: seed,
layout, lighting (+sun), the direct-light share of the preview, camera moves (+moving objects)."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np

from .exr_io import color_layer, load_frame


def _tonemap(x: np.ndarray) -> np.ndarray:
    x = np.maximum(x, 0)
    return np.clip(x / (1 + x), 0, 1) ** (1 / 2.2)


def contact_sheet(split_root: Path, output: Path, rows: int = 6) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    seqs = sorted(p.parent for p in Path(split_root).glob("*/manifest.json"))
    manifests = [json.loads((d / "manifest.json").read_text()) for d in seqs]
    # Sequences with at least two frames on disk (a split may still be rendering).
    picked = [
        (d, m)
        for d, m in zip(seqs, manifests, strict=True)
        if sum((d / f["file"]).exists() for f in m["frames"]) >= 2
    ]
    # Spread the rows over the rendered sequences rather than showing the first few.
    picked = [
        picked[i] for i in np.linspace(0, len(picked) - 1, min(rows, len(picked))).astype(int)
    ]
    if not picked:
        raise FileNotFoundError(f"no finished sequences under {split_root}")
    cols = [
        "1 spp",
        "max spp",
        "reference",
        "albedo",
        "normal",
        "|motion| (last frame)",
        "last frame (reference)",
    ]
    fig, axes = plt.subplots(len(picked), len(cols), figsize=(2.2 * len(cols), 2.3 * len(picked)))
    axes = np.atleast_2d(axes)
    for r, (d, m) in enumerate(picked):
        levels = m["config"]["spp_levels"]
        f0 = load_frame(d / m["frames"][0]["file"])
        last = load_frame(d / m["frames"][-1]["file"], ["motion", "reference"])
        s = m["summary"]
        mag = np.linalg.norm(last["motion"], axis=-1)
        panels = [
            _tonemap(f0[color_layer(min(levels))]),
            _tonemap(f0[color_layer(max(levels))]),
            _tonemap(f0["reference"]),
            np.clip(f0["albedo"], 0, 1),
            np.clip(f0["normal"] * 0.5 + 0.5, 0, 1),
            mag / max(float(mag.max()), 1e-6),
            _tonemap(last["reference"]),
        ]
        for c, img in enumerate(panels):
            ax = axes[r, c]
            ax.imshow(img, cmap="magma" if img.ndim == 2 else None, interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(cols[c], fontsize=9)
        sun = "+sun" if s["sun"] else ""
        moves = "/".join(sh["move"] for sh in s["shots"])
        movers = "".join(f"+{k}" for k in s.get("movers", []))
        direct = m.get("lighting_stats", {}).get("direct_fraction")
        share = f" direct {direct:.0%}" if direct is not None else ""
        axes[r, 0].set_ylabel(
            f"{m['seed']}\n{s['layout']} {s['lighting']}{sun}{share}\n{moves}{movers}",
            fontsize=8,
        )
    fig.tight_layout()
    output.parent.mkdir(parents=True, exist_ok=True)
    buf = io.BytesIO()
    fig.savefig(buf, dpi=72)
    plt.close(fig)
    # Noisy renders compress badly as RGB PNG; a 256-colour palette keeps the file ~1/3 the size.
    from PIL import Image

    Image.open(buf).convert("RGB").quantize(256).save(output, optimize=True)
    return output
