"""Render throughput of the data pipeline next to the machine's limit on the same scene.

    python -m quietframe.experiments.render_throughput [--size 256x256] [--frames 3] \\
        [--reference-spp 128] [--limit-spp 256] [--seed 3000500]

Pipeline: `render_sequence` end to end on a fresh directory (scene generation and load, kernel
compile, previews, S one-sample passes with AOVs, the reference, motion vectors, EXR writing),
samples/s = frames x pixels x (passes + reference spp) / wall time, with the stages from the
manifest. Limit: the same scene loaded once more and rendered as one long `mi.render` of
`--limit-spp` samples per pixel after a warm-up (the kernel compiled; no AOVs, no I/O), and as
the reference path (`render_reference`), next to the reference as rendered before the
restructuring (the AOV pass kernel in ~2M-sample launches), all on the same scene. The
machine is shared, so the load average and the process CPU time are printed too: wall time
well above CPU time / cores means the run waited for a core.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time

import numpy as np

from quietframe.scenes.camera import Camera
from quietframe.scenes.generator import GENERATOR_VERSION, generate
from quietframe.scenes.mitsuba_scene import set_frame, set_variant
from quietframe.scenes.mitsuba_trace import _trace_passes, render_reference
from quietframe.scenes.render import RenderConfig, load_scene, render_sequence


def _msps(samples: float, seconds: float) -> float:
    return samples / max(seconds, 1e-9) / 1e6


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", default="256x256")
    ap.add_argument("--frames", type=int, default=3)
    ap.add_argument("--spp", default="1,2,4,8")
    ap.add_argument("--reference-spp", type=int, default=128)
    ap.add_argument("--limit-spp", type=int, default=256)
    ap.add_argument("--seed", type=int, default=3_000_500, help="a bench seed (test range)")
    ap.add_argument("--variant", default="auto")
    args = ap.parse_args(argv)

    import mitsuba as mi

    variant = set_variant(args.variant)
    w, h = (int(v) for v in args.size.lower().split("x"))
    cfg = RenderConfig(
        width=w,
        height=h,
        frames=(args.frames, args.frames),
        spp_levels=tuple(int(s) for s in args.spp.split(",")),
        reference_spp=args.reference_spp,
    )
    px = w * h
    print(
        f"generator {GENERATOR_VERSION}, variant {variant}, seed {args.seed}, {w}x{h}, "
        f"{args.frames} frames, {cfg.passes} passes + reference {cfg.reference_spp} spp, "
        f"max_depth {cfg.max_depth}, load average {os.getloadavg()[0]:.1f} on "
        f"{os.cpu_count()} cores"
    )

    with tempfile.TemporaryDirectory() as tmp:
        c0, t0 = time.process_time(), time.perf_counter()
        m = render_sequence(args.seed, tmp, cfg)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    frames = m["frames"]
    n = len(frames)
    samples = n * px * (cfg.passes + cfg.reference_spp)
    stage = {k: float(np.mean([f[k] for f in frames])) for k in ("passes_s", "reference_s")}
    write = float(np.mean([f["write_s"] for f in frames]))
    print(
        f"pipeline: {n} frames in {wall:.1f} s (CPU {cpu:.1f} s): "
        f"{_msps(samples, wall):.3f} Msamples/s, {_msps(samples, cpu):.3f} per CPU-second"
    )
    print(
        f"  scene set-up (generate, load, compile, previews) {m['scene_setup_s']:.2f} s; per "
        f"frame: passes {stage['passes_s']:.2f} s "
        f"({_msps(px * cfg.passes, stage['passes_s']):.3f} Msamples/s), reference "
        f"{stage['reference_s']:.2f} s "
        f"({_msps(px * cfg.reference_spp, stage['reference_s']):.3f} Msamples/s), "
        f"motion + EXR {write:.2f} s"
    )

    desc = generate(args.seed, args.frames, m["attempt"])
    t0 = time.perf_counter()
    scene, path, _ = load_scene(desc, cfg)
    load_s = time.perf_counter() - t0
    set_frame(scene, Camera(**desc["cameras"][0]), [], 0)
    t0 = time.perf_counter()
    np.array(mi.render(scene, integrator=path, seed=1, spp=4))
    render_reference(scene, path, 1, 4)
    warm_s = time.perf_counter() - t0
    c0, t0 = time.process_time(), time.perf_counter()
    np.array(mi.render(scene, integrator=path, seed=2, spp=args.limit_spp))
    long_s, long_cpu = time.perf_counter() - t0, time.process_time() - c0
    c0, t0 = time.process_time(), time.perf_counter()
    render_reference(scene, path, 3, args.limit_spp)
    launch_s, launch_cpu = time.perf_counter() - t0, time.process_time() - c0
    # The reference as rendered before the restructuring: the pass kernel (path + primary AOV
    # intersection, 15 channels per sample copied to the host), pass-major lanes, ~2M per launch.
    c0, t0 = time.process_time(), time.perf_counter()
    batch, done = max(1, (1 << 21) // px), 0
    while done < args.limit_spp:
        n = min(batch, args.limit_spp - done)
        _trace_passes(scene, path, 4 + done, n)[..., :3].sum(0)
        done += n
    old_s, old_cpu = time.perf_counter() - t0, time.process_time() - c0
    lim = px * args.limit_spp
    print(
        f"limit: one long mi.render of {args.limit_spp} spp {long_s:.1f} s: "
        f"{_msps(lim, long_s):.3f} Msamples/s ({_msps(lim, long_cpu):.3f} per CPU-second); "
        f"reference path, {args.limit_spp} spp: {launch_s:.1f} s: "
        f"{_msps(lim, launch_s):.3f} Msamples/s ({_msps(lim, launch_cpu):.3f} per CPU-second) "
        f"(scene load {load_s:.2f} s, warm-up incl. compile {warm_s:.2f} s)"
    )
    print(
        f"reference path before the restructuring (pass kernel with AOVs, 2M-lane launches), "
        f"{args.limit_spp} spp: {old_s:.1f} s: {_msps(lim, old_s):.3f} Msamples/s "
        f"({_msps(lim, old_cpu):.3f} per CPU-second)"
    )
    best = max(_msps(lim, long_s), _msps(lim, launch_s))
    best_cpu = max(_msps(lim, long_cpu), _msps(lim, launch_cpu))
    print(
        f"pipeline / limit: {_msps(samples, wall) / best:.2f} (wall), "
        f"{_msps(samples, cpu) / best_cpu:.2f} (CPU); "
        f"load average now {os.getloadavg()[0]:.1f}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
