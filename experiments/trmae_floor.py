"""The floor that noisy references put under TRMAE, next to what the methods score.

    python -m quietframe.experiments.trmae_floor --split test [--sequences 3000000,3000001,...]
        [--frames 1,2] [--spp 1,4] [--methods oidn-high,oidn-temporal-acc,nbg-2l-3g]
        [--threads 2] [--json floor.json]

TRMAE (Işık eq. 16, `model/metrics.py::trmae`) is taken against the stored 1024-spp references,
whose per-pixel noise (~25 %) dominates ∂t r: even a perfect output scores well above 0. For
each sequence (default: the first 3 of the split) this renders a second reference of the frames
(`--frames`, consecutive; default 1,2) with a seed independent of both the stored reference and
`reference_noise`'s (`scenes/render.py::render_second_reference`, salt SECOND_REF_SALT), cached
as ~/.cache/quietframe/second_refs/<split>/<seed>/frame_<nnnn>.npy (re-runs skip the ~60-90 s
renders), and prints one table, rows × (sequences, mean):

- `second reference`: TRMAE(second reference, stored reference) over the frames: what an output
  exactly as good as a 1024-spp render scores.
- `perfect (estimate)`: that divided by √2, an estimate of a noise-free output's TRMAE. With
  p the truth and r = truth + n, |∂t p - ∂t r| = |∂t n|; with p a second reference, it is
  |∂t n' - ∂t n|, whose std is √2 that of ∂t n (independent noise of equal variance). The
  denominator |∂t r| + ε is the same for both, so the ratio is exactly √2 where the denominator
  does not depend on the noise (|∂t r| dominated by the signal's change ∂t s, or by ε). Where
  the reference noise is a sizeable part of |∂t r| the two are correlated and the ratio is not
  √2, in either direction: for Gaussian noise of std σ on ∂t r and ε ≪ σ it is ~3.4 at
  ∂t s = 0 (the perfect output scores ~1, the second reference a ratio of Gaussians), ~1.15 at
  ∂t s = 2σ, √2 again beyond ~5σ. Hence "estimate", not a bound; the real noise is also not
  Gaussian (fireflies).
- `frozen output`: an output that does not change over the frames (∂t p = 0) scores
  mean |∂t r| / (|∂t r| + ε) < 1, whatever its per-frame error: where this is below the
  methods, TRMAE against these references rewards temporal smoothing more than accuracy.
- `<method> @<spp>`: each of `--methods` run as quietframe-eval runs it (bench/evaluate.py:
  `build_methods`, `load_sequence`, `run_sequence`; over the sequence from frame 0, state
  carried, reset at cuts), TRMAE of its outputs at the same frames against the stored ones.

A sequence marked * has a cut inside the frames (∂t r is then the cut itself); `mean` is over
all listed sequences. The last lines compare the target the oidn-temporal tiers had
(0.5 × oidn-high's TRMAE) with the floor per spp. `--json PATH` writes every figure.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np

from quietframe.bench import cli_args
from quietframe.bench.evaluate import build_methods, load_sequence
from quietframe.bench.harness import planar_frames, score_sequence
from quietframe.model import metrics
from quietframe.model.oidn_cache import save_array
from quietframe.runtime.oidn_prepass import PrepassUnavailable
from quietframe.scenes.exr_io import load_frame
from quietframe.scenes.layout import CACHE_DIR, split_dir
from quietframe.scenes.mitsuba_scene import set_variant
from quietframe.scenes.stored_sequence import render_second_reference

# Salt of the second references here: the stored reference uses 1_000_003 and
# `reference_noise` REFERENCE_NOISE_SALT (2_000_003), so these are independent of both.
SECOND_REF_SALT = 3_000_003
SECOND_REFS_DIR = CACHE_DIR / "second_refs"
DEFAULT_METHODS = "oidn-high,oidn-temporal-acc,nbg-2l-3g"


def floor_figures(stored: np.ndarray, second: np.ndarray) -> dict[str, float]:
    """TRMAE of a second, independent reference against the stored one ((T, H, W, 3) each, T ≥
    2), the estimate for a noise-free output (the former / √2, see the module docstring) and
    the TRMAE of an output frozen in time (the stored first frame repeated)."""
    second_trmae = metrics.trmae(second, stored)
    frozen = metrics.trmae(np.repeat(stored[:1], len(stored), axis=0), stored)
    return {"second_reference": second_trmae, "perfect_estimate": second_trmae / np.sqrt(2.0),
            "frozen_output": frozen}


def cache_path(root: Path, split: str, seed: int, frame: int) -> Path:
    return Path(root).expanduser() / split / str(seed) / f"frame_{frame:04d}.npy"


def _render(seq_dir: Path, frame: int) -> np.ndarray:
    image, seconds = render_second_reference(seq_dir, frame, SECOND_REF_SALT)
    print(f"  rendered {seq_dir.name} frame {frame} in {seconds:.0f} s", flush=True)
    return image


def second_reference(
    seq_dir: Path,
    split: str,
    frame: int,
    root: Path = SECOND_REFS_DIR,
    render: Callable[[Path, int], np.ndarray] = _render,
) -> np.ndarray:
    """The (H, W, 3) exposed second reference of one frame: from the cache, else rendered and
    cached (atomic write)."""
    path = cache_path(root, split, int(seq_dir.name), frame)
    if path.is_file():
        return np.load(path)
    image = np.asarray(render(seq_dir, frame), np.float32)
    save_array(path, image)
    return image


def method_trmae(method: object, frames: list, at: list[int]) -> float:
    """TRMAE at frames `at` of a (planar) method run like quietframe-eval runs it (the
    harness's loop: from frame 0, state carried, reset at cuts); `frames` as
    `evaluate.load_sequence` returns them."""
    score = score_sequence(method, planar_frames(frames[: max(at) + 1]), ())
    preds = np.stack([score.outputs[t] for t in at])
    return metrics.trmae(preds, np.stack([frames[t][1] for t in at]))


def _ints(text: str) -> list[int]:
    return [int(s) for s in text.split(",") if s.strip()]


def format_table(rows: dict[str, dict[int, float]], seeds: list[int], cut: set[int]) -> str:
    names = [f"{s}{'*' if s in cut else ''}" for s in seeds]
    width = max(len(r) for r in rows)
    lines = [f"{'':<{width}}  " + "  ".join(f"{n:>9}" for n in names) + f"  {'mean':>7}"]
    for label, values in rows.items():
        cells = "  ".join(f"{values[s]:9.4f}" for s in seeds)
        lines.append(f"{label:<{width}}  {cells}  {np.mean([values[s] for s in seeds]):7.4f}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="trmae_floor", description=__doc__.split("\n")[0])
    cli_args.add_data(parser)
    cli_args.add_split(parser)
    parser.add_argument("--sequences", default="", help="comma list of seeds (default: first 3)")
    parser.add_argument("--frames", default="1,2", help="consecutive frame indices")
    parser.add_argument("--spp", default="1,4")
    parser.add_argument("--methods", default=DEFAULT_METHODS)
    cli_args.add_threads(parser)
    parser.add_argument("--cache", type=Path, default=SECOND_REFS_DIR)
    cli_args.add_json(parser)
    args = parser.parse_args(argv)
    frames = _ints(args.frames)
    if len(frames) < 2 or frames != list(range(frames[0], frames[0] + len(frames))):
        raise SystemExit(f"--frames: need ≥ 2 consecutive indices, got {frames}")
    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))
    root = split_dir(args.data, args.split)
    seeds = _ints(args.sequences) or [
        int(p.parent.name) for p in sorted(root.glob("*/manifest.json"))][:3]
    folders = [root / str(s) for s in seeds]
    missing = [str(f) for f in folders if not (f / "manifest.json").is_file()]
    if missing:
        raise SystemExit(f"no such sequences: {missing}")
    cut = {s for s, f in zip(seeds, folders, strict=True)
           if any(frames[0] < c <= frames[-1]
                  for c in json.loads((f / "manifest.json").read_text()).get("cuts", []))}

    if any(not cache_path(args.cache, args.split, s, t).is_file() for s in seeds for t in frames):
        variant = set_variant("auto")
        if variant != "scalar_rgb":
            import drjit as dr

            dr.set_thread_count(args.threads)
        print(f"rendering missing second references ({variant})", flush=True)
    labels = {"second_reference": "second reference", "perfect_estimate": "perfect (estimate)",
              "frozen_output": "frozen output"}
    floor: dict[str, dict[int, float]] = {label: {} for label in labels.values()}
    for seed, folder in zip(seeds, folders, strict=True):
        stored = np.stack([load_frame(folder / f"frame_{t:04d}.exr", ["reference"])["reference"]
                           for t in frames])
        second = np.stack([second_reference(folder, args.split, t, args.cache, _render)
                           for t in frames])
        figures = floor_figures(stored, second)
        for key, label in labels.items():
            floor[label][seed] = figures[key]

    wanted = [m for m in args.methods.split(",") if m]
    factories = build_methods(args.threads)
    unknown = [m for m in wanted if m not in factories]
    if unknown:
        raise SystemExit(f"--methods: unknown {unknown}; known: {sorted(factories)}")
    scores: dict[str, dict[int, float]] = {}
    for spp in _ints(args.spp):
        sequences = {s: load_sequence(f, spp) for s, f in zip(seeds, folders, strict=True)}
        for name in wanted:
            try:
                method = factories[name]()
            except PrepassUnavailable as exc:
                print(f"skipping {name}: {exc}", flush=True)
                continue
            scores[f"{name} @{spp}spp"] = {
                s: method_trmae(method, sequences[s], frames) for s in seeds}

    rows = floor | scores
    print(f"\nTRMAE over frames {args.frames} of {args.split} sequences, against the stored "
          "1024-spp references (* = cut inside the frames)")
    print(format_table(rows, seeds, cut))
    perfect = float(np.mean(list(floor["perfect (estimate)"].values())))
    second_mean = float(np.mean(list(floor["second reference"].values())))
    targets = {}
    for spp in _ints(args.spp):
        key = f"oidn-high @{spp}spp"
        if key in scores:
            target = 0.5 * float(np.mean(list(scores[key].values())))
            targets[spp] = target
            print(f"target 0.5 × oidn-high @{spp}spp = {target:.4f}; floor: perfect ≈ "
                  f"{perfect:.4f}, 1024-spp render {second_mean:.4f}")
    if args.json:
        out = {
            "command": "python -m quietframe.experiments.trmae_floor "
            + " ".join(sys.argv[1:] if argv is None else argv),
            "split": args.split, "frames": frames, "salt": SECOND_REF_SALT,
            "cut_in_frames": sorted(cut),
            "rows": {label: {str(s): v for s, v in values.items()}
                     for label, values in rows.items()},
            "means": {label: float(np.mean(list(values.values())))
                      for label, values in rows.items()},
            "target_half_oidn_high": {str(k): v for k, v in targets.items()},
        }
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(out, indent=1))
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
