"""`quietframe-render`: render dataset splits, measure throughput, draw a contact sheet.

    quietframe-render render --split train --sequences 72 --frames 8 --size 128x128 \\
        --spp 1,2,4,8 --reference-spp 64 --jobs 2
    quietframe-render bench --size 128x128 --seeds 3
    quietframe-render sheet --split train --output docs/contact_sheet.png
    quietframe-render topup --split test --spp 16
    quietframe-render render --split test-static --sequences 2 --frames 8  # locked-off shots

Data lands in <out>/<generator version>/<split>/<sequence seed>/ (default out:
~/.cache/quietframe/data). Sequence seeds come from disjoint ranges per split, so train,
validation and test never share a scene. A `*-static` split (test-static, validation-static)
renders locked-off shots: static camera and scene, noise animated per frame, one reference at
4x the reference spp for every frame. Re-running skips finished frames.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import sys
import time
import traceback
from pathlib import Path

import numpy as np

from quietframe.scenes.camera import Camera
from quietframe.scenes.generator import generate, summary
from quietframe.scenes.layout import DATA_DIR, SPLIT_BASE, is_locked_off, split_dir, split_seeds
from quietframe.scenes.manifest import write_json
from quietframe.scenes.mitsuba_scene import set_frame, set_variant
from quietframe.scenes.mitsuba_trace import render_passes
from quietframe.scenes.render import (
    RenderConfig,
    choose_scene,
    frame_count,
    load_scene,
    render_sequence,
)
from quietframe.scenes.sheet import contact_sheet
from quietframe.scenes.stored_sequence import reference_noise, topup_sequence


def _size(text: str) -> tuple[int, int]:
    w, h = text.lower().split("x")
    return int(w), int(h)


def _frames(text: str) -> tuple[int, int]:
    lo, _, hi = text.partition("-")
    return int(lo), int(hi or lo)


def _config(args: argparse.Namespace) -> RenderConfig:
    w, h = _size(args.size)
    return RenderConfig(
        width=w,
        height=h,
        frames=_frames(args.frames),
        spp_levels=tuple(int(s) for s in args.spp.split(",")),
        reference_spp=args.reference_spp,
        max_depth=args.max_depth,
        variant=args.variant,
        locked_off=is_locked_off(getattr(args, "split", "")),  # bench has no split
    )


# ---------------------------------------------------------------------------------------------
# render


_queue = None


def _init_worker(variant: str, threads: int, queue) -> None:
    global _queue
    _queue = queue
    set_variant(variant)
    if threads > 0:
        import drjit as dr

        dr.set_thread_count(threads)


def _render_one(job: tuple[int, str, object]) -> tuple[int, str]:
    seed, out, cfg = job
    try:
        t0 = time.perf_counter()
        render_sequence(seed, out, cfg, on_frame=lambda t, rec: _queue.put((seed, t, rec)))
        return seed, f"ok {time.perf_counter() - t0:.1f}s"
    except Exception:  # noqa: BLE001 - one bad scene must not stop a night-long render
        return seed, "failed\n" + traceback.format_exc()


def _done_frames(seq_dir: Path) -> int:
    m = seq_dir / "manifest.json"
    if not m.exists():
        return 0
    frames = json.loads(m.read_text())["frames"]
    return sum((seq_dir / f["file"]).exists() for f in frames)


def cmd_render(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    t_start = time.perf_counter()
    cfg = _config(args)
    root = split_dir(args.out, args.split)
    seeds = split_seeds(args.split, args.sequences, args.start)
    total = sum(frame_count(s, cfg) for s in seeds)
    done = sum(_done_frames(root / str(s)) for s in seeds)
    jobs = [
        (s, str(root / str(s)), cfg)
        for s in seeds
        if _done_frames(root / str(s)) < frame_count(s, cfg)
    ]
    print(
        f"{args.split}: {len(seeds)} sequences, {total} frames ({done} done) -> {root}", flush=True
    )
    print(f"config: {json.dumps(cfg.key())} jobs={args.jobs}", flush=True)
    ctx = mp.get_context("spawn")  # fresh interpreters: Mitsuba variants are per process
    queue = ctx.Manager().Queue()
    threads = args.threads if args.threads is not None else (1 if args.jobs > 1 else 0)
    bar = tqdm(
        total=total,
        initial=done,
        unit="frame",
        mininterval=1 if sys.stderr.isatty() else 60,
        smoothing=0.05,
    )
    results: list[tuple[int, str]] = []
    with ctx.Pool(args.jobs, _init_worker, (args.variant, threads, queue)) as pool:
        for job in jobs:
            pool.apply_async(_render_one, (job,), callback=results.append)
        reported = 0
        while reported < len(jobs):
            time.sleep(0.5)
            while not queue.empty():
                seed, t, rec = queue.get()
                bar.update(1)
                bar.set_postfix_str(
                    f"seq {seed} frame {t}: passes {rec['passes_s']:.1f}s "
                    f"reference {rec['reference_s']:.1f}s"
                )
            for seed, status in results[reported:]:
                tqdm.write(f"sequence {seed}: {status}")
                reported += 1
    while not queue.empty():
        queue.get()
        bar.update(1)
    bar.close()
    failed = sum(status.startswith("failed") for _, status in results)
    print(f"finished: {len(jobs) - failed} sequences rendered, {failed} failed", flush=True)
    write_split_manifest(root, args, cfg, seeds, time.perf_counter() - t_start)
    return 1 if failed else 0


def _noise_job(job: tuple[str, int]) -> dict:
    return reference_noise(*job)


def write_split_manifest(root: Path, args: argparse.Namespace, cfg, seeds: list[int], wall: float):
    """<split>/split.json: command, seeds, config, render times and CPU time summed from the
    sequence manifests, and the reference noise (a second independent reference of frame 1
    of `--noise-frames` sequences spread over the split; measured once per config)."""
    path = root / "split.json"
    old = json.loads(path.read_text()) if path.exists() else {}
    seqs = [
        json.loads((root / str(s) / "manifest.json").read_text())
        for s in seeds
        if _done_frames(root / str(s))
    ]
    frames = [f for m in seqs for f in m["frames"]]
    noise = old.get("reference_noise") if old.get("config") == cfg.key() else None
    complete = all(_done_frames(root / str(s)) >= _frame_count_of(root / str(s)) for s in seeds)
    if noise is None and args.noise_frames > 0 and seqs and complete and len(seqs) == len(seeds):
        spread = np.linspace(0, len(seqs) - 1, args.noise_frames).round().astype(int)
        pick = [seqs[i] for i in np.unique(spread)]
        jobs = [(str(root / str(m["seed"])), 1) for m in pick]
        ctx = mp.get_context("spawn")
        with ctx.Pool(
            min(args.jobs, len(jobs)), _init_worker, (args.variant, 1 if args.jobs > 1 else 0, None)
        ) as pool:
            per_frame = pool.map(_noise_job, jobs)
        med = [r["median_relative_difference"] for r in per_frame]
        noise = {
            "median_relative_difference": float(np.median(med)),
            "frames": per_frame,
            "eps": 0.01,
            "definition": "median over pixels of |a-b| / ((a+b)/2 + eps), luminance, two "
            "independent references of the same spp; the median over the frames",
        }
        print(
            f"reference noise: median relative difference "
            f"{noise['median_relative_difference']:.4f}",
            flush=True,
        )
    stats = [m.get("lighting_stats", {}) for m in seqs]
    manifest = {
        "command": "quietframe-render " + " ".join(sys.argv[1:]),
        "split": args.split,
        "seeds": seeds,
        "config": cfg.key(),
        "sequences_done": sum(
            _done_frames(root / str(s)) >= _frame_count_of(root / str(s)) for s in seeds
        ),
        "frames_done": len(frames),
        "render_s": round(
            sum(m["scene_setup_s"] for m in seqs)
            + sum(f["passes_s"] + f["reference_s"] + f["write_s"] for f in frames),
            1,
        ),
        "cpu_s": round(sum(f.get("cpu_s", 0.0) for f in frames), 1),
        "wall_s_last_run": round(wall, 1),
        "reference_noise": noise,
        "lighting": {
            "indirect_sequences": sum(s.get("direct_fraction", 1) < 0.5 for s in stats),
            "direct_fraction_median": float(np.median([s["direct_fraction"] for s in stats if s]))
            if any(stats)
            else None,
            "black_1spp_fraction_median": float(
                np.median([s["preview_black_fraction"] for s in stats if s])
            )
            if any(stats)
            else None,
        },
    }
    write_json(path, manifest)


def _frame_count_of(seq_dir: Path) -> int:
    m = seq_dir / "manifest.json"
    return json.loads(m.read_text())["frame_count"] if m.exists() else 1 << 30


# ---------------------------------------------------------------------------------------------
# bench


def cmd_bench(args: argparse.Namespace) -> int:
    """Throughput per scene: seconds for the S one-sample passes and for the reference of a
    frame (after the scene's kernels are compiled), and samples per second."""
    import mitsuba as mi

    variant = set_variant(args.variant)
    cfg = _config(args)
    rows = []
    for seed in split_seeds("test", args.seeds, 500):  # bench scenes: not in train/validation
        desc = generate(seed, 4)
        t0 = time.perf_counter()
        scene, ref, table = load_scene(desc, cfg)
        load_s = time.perf_counter() - t0
        set_frame(scene, Camera(**desc["cameras"][0]), [], 0)
        t0 = time.perf_counter()
        render_passes(scene, ref, 1, cfg.passes, table)
        np.array(mi.render(scene, integrator=ref, seed=2, spp=1))
        compile_s = time.perf_counter() - t0
        for f in (1, 2):
            set_frame(scene, Camera(**desc["cameras"][f]), [], f)
            t0 = time.perf_counter()
            render_passes(scene, ref, 10 + f, cfg.passes, table)
            pass_s = time.perf_counter() - t0
            t0 = time.perf_counter()
            np.array(mi.render(scene, integrator=ref, seed=20 + f, spp=cfg.reference_spp))
            ref_s = time.perf_counter() - t0
            rows.append((seed, summary(desc)["lighting"], load_s, compile_s, pass_s, ref_s))
    px = cfg.width * cfg.height
    print(
        f"variant {variant}, {cfg.width}x{cfg.height}, {cfg.passes} passes, reference "
        f"{cfg.reference_spp} spp, max_depth {cfg.max_depth}"
    )
    print("seed     lighting  load_s compile_s passes_s pass_Msps ref_s ref_Msps")
    for seed, env, load_s, compile_s, pass_s, ref_s in rows:
        print(
            f"{seed} {env:9s} {load_s:6.2f} {compile_s:9.2f} {pass_s:8.2f} "
            f"{px * cfg.passes / pass_s / 1e6:9.3f} {ref_s:5.2f} "
            f"{px * cfg.reference_spp / ref_s / 1e6:8.3f}"
        )
    a = np.array([r[2:] for r in rows])
    print(
        f"mean: load {a[:, 0].mean():.2f}s compile {a[:, 1].mean():.2f}s passes "
        f"{a[:, 2].mean():.2f}s reference {a[:, 3].mean():.2f}s; "
        f"{px * (cfg.passes + cfg.reference_spp) / (a[:, 2] + a[:, 3]).mean() / 1e6:.3f} "
        f"Msamples/s overall"
    )
    return 0


# ---------------------------------------------------------------------------------------------
# survey


def cmd_survey(args: argparse.Namespace) -> int:
    """How each scene of a split is lit, without rendering it: the same scene choice, exposure
    and 8-spp previews as `render` (at a small size), then the direct-light share and the black
    fraction of a 1-spp pass per sequence."""
    set_variant(args.variant)
    cfg = _config(args)
    rows = []
    for seed in split_seeds(args.split, args.sequences, args.start):
        desc, *_, attempt, _, stats = choose_scene(seed, frame_count(seed, cfg), cfg)
        s = summary(desc)
        rows.append(stats["direct_fraction"])
        print(
            f"{seed} attempt {attempt} {s['layout']:9s} {s['lighting']:8s} sun={int(s['sun'])} "
            f"lights_on={s['lights_on']} movers={','.join(s['movers']) or '-'} "
            f"direct {stats['direct_fraction']:.2f} black@1spp "
            f"{stats['preview_black_fraction']:.2f}",
            flush=True,
        )
    indirect = sum(d < 0.5 for d in rows)
    print(
        f"{args.split}: {indirect} of {len(rows)} sequences lit mainly indirectly "
        f"(direct share < 0.5); median direct share {np.median(rows):.2f}"
    )
    return 0


# ---------------------------------------------------------------------------------------------
# sheet


def cmd_sheet(args: argparse.Namespace) -> int:
    root = split_dir(args.out, args.split)
    path = contact_sheet(root, Path(args.output), rows=args.rows)
    print(f"wrote {path}")
    return 0


def cmd_topup(args: argparse.Namespace) -> int:
    """Add a colour level above the stored passes (e.g. 16 spp) to every finished sequence of a
    split, for evaluation at higher spp (stored_sequence.topup_sequence); resumable, frames that
    have it are skipped."""
    set_variant(args.variant)
    root = split_dir(args.out, args.split)
    folders = sorted(p for p in root.iterdir() if (p / "manifest.json").exists())
    t0, cpu0, written = time.perf_counter(), time.process_time(), 0
    for folder in folders:
        n = topup_sequence(folder, args.spp)
        written += n
        print(f"{folder.name}: {n} frames given {args.spp} spp", flush=True)
    print(f"{args.split}: {written} frames in {time.perf_counter() - t0:.0f} s wall, "
          f"{time.process_time() - cpu0:.0f} s CPU", flush=True)
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="quietframe-render",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    sub = ap.add_subparsers(dest="command", required=True)

    def common(p: argparse.ArgumentParser) -> None:
        p.add_argument("--size", default="256x256", help="WxH (default 256x256)")
        p.add_argument("--frames", default="8-16", help="frames per sequence, N or MIN-MAX")
        p.add_argument("--spp", default="1,2,4,8", help="stored noisy spp levels; passes = max")
        p.add_argument("--reference-spp", type=int, default=1024)
        p.add_argument("--max-depth", type=int, default=8)
        p.add_argument("--variant", default="auto", help="auto | llvm_ad_rgb | scalar_rgb")
        p.add_argument("--out", type=Path, default=DATA_DIR)

    r = sub.add_parser("render", help="render (or finish) sequences of a split")
    common(r)
    r.add_argument("--split", choices=list(SPLIT_BASE), required=True)
    r.add_argument("--sequences", type=int, required=True)
    r.add_argument("--start", type=int, default=0, help="index of the first sequence")
    r.add_argument("--jobs", type=int, default=1)
    r.add_argument("--threads", type=int, default=None, help="render threads per job")
    r.add_argument(
        "--noise-frames",
        type=int,
        default=3,
        help="frames that get a second reference to measure the reference noise (0: none)",
    )
    b = sub.add_parser("bench", help="measure render throughput on this machine")
    common(b)
    b.add_argument("--seeds", type=int, default=3)
    v = sub.add_parser("survey", help="how the scenes of a split are lit (previews only)")
    common(v)
    v.add_argument("--split", choices=list(SPLIT_BASE), required=True)
    v.add_argument("--sequences", type=int, required=True)
    v.add_argument("--start", type=int, default=0)
    s = sub.add_parser("sheet", help="contact sheet PNG of rendered sequences")
    s.add_argument("--split", default="train")
    s.add_argument("--out", type=Path, default=DATA_DIR)
    s.add_argument("--output", default="docs/contact_sheet.png")
    s.add_argument("--rows", type=int, default=6)
    u = sub.add_parser("topup", help="add a colour level above the stored passes (evaluation)")
    u.add_argument("--split", choices=list(SPLIT_BASE), required=True)
    u.add_argument("--spp", type=int, default=16)
    u.add_argument("--variant", default="auto", help="auto | llvm_ad_rgb | scalar_rgb")
    u.add_argument("--out", type=Path, default=DATA_DIR)
    args = ap.parse_args(argv)
    commands = {"render": cmd_render, "bench": cmd_bench, "survey": cmd_survey, "sheet": cmd_sheet,
                "topup": cmd_topup}
    return commands[args.command](args)


if __name__ == "__main__":
    sys.exit(main())
