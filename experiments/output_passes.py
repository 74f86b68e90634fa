"""What a complete output costs: encoding every pass of the input versus the beauty alone.

    python -m quietframe.experiments.output_passes [--width 1280 --height 720] [--repeats 5]

The frame is Blender's multilayer layout (bench/synthetic.py's render-like buffers): the
passes the model reads (Combined RGBA, Denoising Albedo half; Denoising Normal, Denoising Depth
float) plus 10 extra passes a farm renders for compositing (Vector, Depth, Normal, Position,
Mist float; DiffCol, GlossCol, Emit, AO half; CryptoObject00 float). For each output
compression it times, through the service's own `frames.decode` / `frames.encode`:
- decode: the whole file (OpenEXR decodes every channel in either case);
- encode, beauty only: the denoised R, G, B with the input's header (what quietframe returned
  before outputs carried every pass), i.e. `encode` of the frame with no channel to carry through;
- encode, complete: the same denoised colour with every other channel carried through.
Times are medians (bench/timing.py) on `--threads` OpenEXR threads.
"""

from __future__ import annotations

import argparse
import io

import numpy as np

from quietframe.bench import cli_args
from quietframe.bench.synthetic import synthetic_buffers
from quietframe.bench.timing import time_ms
from quietframe.service import frames

LAYER = "ViewLayer"
TIMED = ("decode", "beauty", "complete")
# (pass, channel suffixes, half in a half file): Blender writes only colour passes as half.
MODEL_PASSES = (
    ("Combined", "RGBA", True),
    ("Denoising Albedo", "RGB", True),
    ("Denoising Normal", "XYZ", False),
    ("Denoising Depth", "Z", False),
)
EXTRA_PASSES = (
    ("Vector", "XYZW", False),
    ("Depth", "Z", False),
    ("Normal", "XYZ", False),
    ("Position", "XYZ", False),
    ("Mist", "Z", False),
    ("DiffCol", "RGB", True),
    ("GlossCol", "RGB", True),
    ("Emit", "RGB", True),
    ("AO", "RGB", True),
    ("CryptoObject00", "RGBA", False),
)


def blender_frame(width: int, height: int, extra: bool, compression: str) -> bytes:
    """A half Blender multilayer EXR with the model's passes (and the 10 extra ones)."""
    import OpenEXR

    b = synthetic_buffers(width, height, seed=1)
    rng = np.random.default_rng(1)
    sources = {
        "Combined": np.concatenate([b["color"], np.ones_like(b["color"][..., :1])], -1),
        "Denoising Albedo": b["albedo"],
        "Denoising Normal": b["normal"],
        "Denoising Depth": b["depth"][..., None],
        "Vector": np.concatenate([b["motion"], -b["motion"]], -1),
        "Depth": b["depth"][..., None] * 0.98,
        "Normal": b["normal"],
        "Position": np.stack([b["depth"], b["depth"] * 0.5, b["depth"] * 0.25], -1),
        "Mist": np.clip(b["depth"][..., None] / 10, 0, 1),
        "DiffCol": b["albedo"],
        "GlossCol": b["albedo"] * 0.3,
        "Emit": np.zeros_like(b["albedo"]),
        "AO": np.clip(b["normal"][..., 2:3].repeat(3, -1), 0, 1),
        "CryptoObject00": rng.integers(0, 8, (height, width, 4)).astype(np.float32) * 1e-3,
    }
    passes = MODEL_PASSES + (EXTRA_PASSES if extra else ())
    channels = {
        f"{LAYER}.{name}.{c}": np.ascontiguousarray(
            sources[name][..., i], np.float16 if half else np.float32
        )
        for name, comps, half in passes
        for i, c in enumerate(comps)
    }
    codec = "NO" if compression == "none" else compression.upper()
    header = {
        "compression": getattr(OpenEXR, f"{codec}_COMPRESSION"),
        "type": OpenEXR.scanlineimage,
    }
    out = io.BytesIO()
    OpenEXR.File(header, channels).write(out)
    return out.getvalue()


def measure(data: bytes, compression: str, warmup: int, repeats: int) -> dict[str, float]:
    header = frames.read_header(data, 8192, 8192)
    sources = frames.resolve(header.channels, ("color", "albedo", "normal", "depth"), ())
    decoded = frames.decode(data, sources)
    color = decoded.buffers["color"] * np.float32(0.9)  # (3, H, W), the runtime's output
    names = sources["color"].channels
    beauty_only = frames.DecodedFrame(
        {}, [frames.Part(p.name, p.attributes, {}) for p in decoded.parts], decoded.color_half
    )
    times = {
        "decode": time_ms(lambda: frames.decode(data, sources), warmup=warmup, repeats=repeats),
        "beauty": time_ms(
            lambda: frames.encode(color, beauty_only, names, "half", compression=compression),
            warmup=warmup,
            repeats=repeats,
        ),
        "complete": time_ms(
            lambda: frames.encode(color, decoded, names, "half", compression=compression),
            warmup=warmup,
            repeats=repeats,
        ),
    }
    sizes = {
        "beauty": len(frames.encode(color, beauty_only, names, "half", compression=compression)),
        "complete": len(frames.encode(color, decoded, names, "half", compression=compression)),
    }
    return {
        **{f"{k}_ms": t.median_ms for k, t in times.items()},
        **{f"{k}_cpu": t.cpu_ms for k, t in times.items()},
        **{f"{k}_mib": v / 2**20 for k, v in sizes.items()},
        "channels": len(header.channels),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--width", type=int, default=1280)
    parser.add_argument("--height", type=int, default=720)
    parser.add_argument("--compression", nargs="+", default=["zip", "piz", "none"])
    cli_args.add_threads(parser, help="OpenEXR threads")
    parser.add_argument("--warmup", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args(argv)
    frames.configure_io(args.threads)
    print(
        f"{args.width}x{args.height}, half colour / float data, {args.threads} OpenEXR "
        f"thread(s), median of {args.repeats}"
    )
    print(
        "| input compression = output | channels | decode ms | encode ms, beauty only | "
        "encode ms, complete | output MiB, beauty only / complete |   (wall ms, CPU ms)"
    )
    print("|---|---|---|---|---|---|")
    for compression in args.compression:
        for extra in (False, True):
            data = blender_frame(args.width, args.height, extra, compression)
            r = measure(data, "input", args.warmup, args.repeats)
            label = f"{compression}, {'model passes + 10 extra' if extra else 'model passes'}"
            wall_cpu = [f"{r[f'{k}_ms']:.0f} ({r[f'{k}_cpu']:.0f})" for k in TIMED]
            print(
                f"| {label} | {r['channels']} | {' | '.join(wall_cpu)} | "
                f"{r['beauty_mib']:.1f} / {r['complete_mib']:.1f} |"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
