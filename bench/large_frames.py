"""Large frames through the runtime: peak memory and time per frame at 1080p, 4K and 8K.

    python -m quietframe.bench.large_frames [--sizes 1080p 4k 8k] [--frames 2] [--threads 2]
        [--model affinity-h16-k5gc[,blender-oidn,...]] [--max-memory-mb 1536 | --tile-pixels 0]

Each size runs in its own process (peak RSS = that process's VmHWM): synthetic render-like
buffers (float32, built without float64 temporaries), `frames` frames with the history carried,
through the runtime's per-sequence step (runtime/stream.py: OIDN's filters kept, its scratch
capped as the service caps it at its default memory budget) with the graphs' tiles sized by the
memory bound (runtime/tiling.py; `--tile-pixels N` fixes them, 0 runs untiled). Prints a
Markdown table: ms per frame (median), CPU seconds per frame (every thread's: what the frame
costs when other jobs share the cores) with the load average, peak RSS, the inputs' and state's
share of it, and the tile count. `--model` takes a comma list, each run at every size in the
same run; `blender-oidn` is per-frame OIDN as Blender's denoise runs it (RT filter, quality
high, aux prefiltered at high quality, `cleanAux`, OIDN's own memory default, rows bottom-up)
on the same buffers: the cost a farm compares with. Frames are given as Cycles' (OIDN sees
them bottom-up).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import time

import numpy as np

from quietframe.bench import cli_args
from quietframe.bench.loopback import rss_mib
from quietframe.runtime import Denoiser, default_model_path, find_model
from quietframe.runtime.denoiser import BY_MEMORY as RUNTIME_BY_MEMORY
from quietframe.runtime.oidn_prepass import OIDNPrepass, OIDNSettings
from quietframe.runtime.stream import Stream
from quietframe.runtime.tiling import overlap_for, plan_tiles
from quietframe.service.settings import Settings

BY_MEMORY = -1  # --tile-pixels: tiles sized by the runtime's max_memory_mb
BLENDER_OIDN = "blender-oidn"  # --model: OIDN as Blender's denoise runs it (module docstring)

SIZES = {"720p": (1280, 720), "1080p": (1920, 1080), "4k": (3840, 2160),
         "8k": (7680, 4320)}


def buffers(width: int, height: int, seed: int) -> dict[str, np.ndarray]:
    """(C, H, W) float32 planes: tiled albedo, smooth normal and depth, noisy colour, a pan."""
    rng = np.random.default_rng(seed)
    x = np.arange(width, dtype=np.float32)[None, :] + 2.0 * seed
    y = np.arange(height, dtype=np.float32)[:, None]
    tiles = ((x // 97).astype(np.int32) * 7 + (y // 61).astype(np.int32) * 13) % 17
    palette = np.random.default_rng(0).uniform(0.05, 0.9, size=(3, 17)).astype(np.float32)
    albedo = palette[:, tiles]  # (3, H, W)
    normal = np.empty((3, height, width), np.float32)
    normal[0], normal[1], normal[2] = np.sin(x / 300), np.cos(y / 200), 1.0
    normal /= np.sqrt((normal * normal).sum(0, keepdims=True))
    depth = (4.0 + 2.0 * np.sin(x / 400) * np.cos(y / 300))[None].astype(np.float32)
    color = albedo * (0.3 + 0.7 * normal[2:3])
    color *= 0.25 * rng.standard_gamma(4.0, size=color.shape, dtype=np.float32)  # mean 1
    motion = np.zeros((2, height, width), np.float32)
    motion[0] = 2.0
    return {"color": color, "albedo": albedo, "normal": normal, "depth": depth, "motion": motion}


def one(width: int, height: int, frames: int, threads: int, tile_pixels: int | None,
        model: str = "", max_memory_mb: float | None = None) -> dict:
    if model == BLENDER_OIDN:
        denoiser = OIDNPrepass(OIDNSettings("high", True), num_threads=threads)
    else:
        path = find_model(model) if model else default_model_path()
        tiles_by = RUNTIME_BY_MEMORY if tile_pixels == BY_MEMORY else tile_pixels
        denoiser = Denoiser(path, threads=threads, tile_pixels=tiles_by,
                            max_memory_mb=max_memory_mb,
                            oidn_memory_mb=Settings().oidn_memory_mb)  # as the service sizes it
        stream = Stream(denoiser)  # as a session runs it: OIDN's filters kept between frames
        tile_pixels = denoiser.tile_pixels
    base = rss_mib(os.getpid(), "VmHWM")
    times, cpu, state = [], [], {}
    for i in range(frames):
        planes = buffers(width, height, i)
        start, start_cpu = time.perf_counter(), time.process_time()
        if isinstance(denoiser, Denoiser):
            step = stream.step(planes, state or None, renderer="cycles")
            color, state = step.color, step.state
        else:
            color = denoiser(planes, "cycles")
        times.append(1e3 * (time.perf_counter() - start))
        cpu.append(time.process_time() - start_cpu)  # every thread's: robust to other load
        assert np.isfinite(color).all()
    inputs = sum(p.nbytes for p in planes.values()) / 2**20
    tiling = denoiser.graph.card.tiling if isinstance(denoiser, Denoiser) else None
    tiles = 1
    if tile_pixels is not None and tiling is not None:
        defaults = {spec.name: spec.default for spec in denoiser.graph.card.inputs}
        overlap = overlap_for(tiling, defaults, planes["motion"])
        tiles = len(plan_tiles(height, width, overlap, tiling.align, tile_pixels,
                               tiling.size_ratios))
    return {
        "model": model or default_model_path().stem,
        "size": f"{width}x{height}",
        "ms_per_frame": round(statistics.median(times), 0),
        "ms_all": [round(t) for t in times],
        "cpu_s_per_frame": round(statistics.median(cpu), 2),
        "load_average": round(os.getloadavg()[0], 1),
        "peak_rss_mib": round(rss_mib(os.getpid(), "VmHWM")),
        "base_rss_mib": round(base),
        "inputs_mib": round(inputs),
        "state_mib": round(sum(s.nbytes for s in state.values()) / 2**20),
        "tiles": tiles,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", nargs="+", default=["1080p", "4k", "8k"], choices=list(SIZES))
    parser.add_argument("--frames", type=int, default=2)
    cli_args.add_threads(parser)
    parser.add_argument(
        "--tile-pixels", type=int, default=BY_MEMORY,
        help="padded pixels per tile; 0: untiled (comparison); default: from the memory bound")
    parser.add_argument("--model", default="",
                        help=f"installed models, comma-separated, or {BLENDER_OIDN} "
                             "(default: the default model)")
    parser.add_argument("--max-memory-mb", type=float, help="the runtime's memory bound")
    parser.add_argument("--one", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.one:
        width, height = SIZES[args.one]
        tile_pixels = args.tile_pixels or None
        print(json.dumps(one(width, height, args.frames, args.threads, tile_pixels, args.model,
                             args.max_memory_mb)))
        return 0
    rows = []
    for size in args.sizes:
        for model in args.model.split(","):
            cmd = [sys.executable, "-m", "quietframe.bench.large_frames", "--one", size,
                   "--frames", str(args.frames), "--threads", str(args.threads),
                   "--tile-pixels", str(args.tile_pixels), "--model", model,
                   *(["--max-memory-mb", str(args.max_memory_mb)] if args.max_memory_mb else [])]
            out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout
            rows.append(json.loads(out.strip().splitlines()[-1]))
            print(json.dumps(rows[-1]), file=sys.stderr)
    print(f"{platform.node()}: {os.cpu_count()} CPUs, {args.threads} threads")
    print("| model | size | ms/frame (median) | CPU s/frame | load | peak RSS MiB "
          "| of which inputs + state MiB | tiles |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['model']} | {r['size']} | {r['ms_per_frame']:.0f} ({r['ms_all']}) "
              f"| {r['cpu_s_per_frame']} "
              f"| {r['load_average']} | {r['peak_rss_mib']} | {r['inputs_mib']} + 2 x "
              f"{r['state_mib']} | {r['tiles']} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
