"""Which per-frame OIDN floor reaches Blender's denoise at OIDN-high's cost: an ablation of the
prefiltered-aux path, quality per spp beside CPU time at 720p, measured in one run.

    python -m quietframe.experiments.oidn_floor --split validation [--spp 1,4,16,64]
        [--json out.json] [--timing-only | --quality-only]

Question: Blender's denoise (aux prefiltered by OIDN at high quality, then the main filter with
`cleanAux`) costs ~7x plain OIDN-high on this CPU, because `cleanAux` at high quality and the
high-quality aux filters run OIDN's large network. Which cheaper settings keep its PSNR within
0.05 dB? Variants: the main filter's quality (high: the large network; balanced: the default
network; fast: the small one), the aux prefilters' quality, the aux prefiltered at half
resolution (2x2 means, bilinear back), and the rendered aux given as clean without a prefilter
(does a high-spp render's aux need one?). Every variant sees Cycles' rows bottom-up, as the
runtime does (runtime/oidn_prepass.py).

Quality: mean tone-mapped PSNR over each zoo shot's frames, per spp, and the difference to
`blender` (the stage Blender runs, reproduced: bench/blender_denoise_match.py) per shot.
Speed: CPU seconds (process time, all OIDN threads) of each variant on one synthetic 1280x720
frame, median of interleaved repeats, as a ratio to plain OIDN-high measured in the same run.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from quietframe.bench import cli_args
from quietframe.bench.synthetic import frame_buffers
from quietframe.model import metrics
from quietframe.scenes import cycles_io
from quietframe.scenes.zoo_shots import ZOO_SPLITS, zoo_dir

QUALITY = {"fast": "OIDN_QUALITY_FAST", "balanced": "OIDN_QUALITY_BALANCED",
           "high": "OIDN_QUALITY_HIGH"}


@dataclass(frozen=True)
class Floor:
    """One per-frame OIDN floor: the main filter's quality, and the aux prefilters' quality
    and scale (None: aux given as rendered, no cleanAux)."""

    main: str
    aux_quality: str | None = None
    aux_scale: int = 1
    raw_as_clean: bool = False  # the rendered aux given as clean (`cleanAux`), not prefiltered

    @property
    def clean(self) -> bool:
        return self.aux_quality is not None or self.raw_as_clean


FLOORS = {
    "plain-high": Floor("high"),  # OIDN-high, noisy aux: the 1x of the ratios
    "blender": Floor("high", "high"),  # Blender's prefilter Accurate, quality High
    "shipped": Floor("high", "fast"),  # oidn-history-cleanaux's stage
    "clean-balanced": Floor("balanced", "fast"),
    "clean-fast": Floor("fast", "fast"),
    "half-aux/clean-high": Floor("high", "fast", 2),
    "half-aux/clean-balanced": Floor("balanced", "fast", 2),
    "raw-aux/clean-high": Floor("high", raw_as_clean=True),  # no prefilter: at high spp?
}


def _down(x: np.ndarray, s: int) -> np.ndarray:
    h, w, c = x.shape
    h2, w2 = -(-h // s), -(-w // s)
    pad = np.pad(x, ((0, h2 * s - h), (0, w2 * s - w), (0, 0)), mode="edge")
    return pad.reshape(h2, s, w2, s, c).mean((1, 3)).astype(np.float32)


def _up(x: np.ndarray, s: int, h: int, w: int) -> np.ndarray:
    """Bilinear, pixel centres aligned (as a half-resolution render would be)."""
    def coords(n: int, m: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        c = np.clip((np.arange(n) + 0.5) / s - 0.5, 0, m - 1)
        lo = np.floor(c).astype(int)
        return lo, np.minimum(lo + 1, m - 1), (c - lo).astype(np.float32)

    y0, y1, fy = coords(h, x.shape[0])
    x0, x1, fx = coords(w, x.shape[1])
    top = x[y0][:, x0] * (1 - fx)[None, :, None] + x[y0][:, x1] * fx[None, :, None]
    bot = x[y1][:, x0] * (1 - fx)[None, :, None] + x[y1][:, x1] * fx[None, :, None]
    return (top * (1 - fy)[:, None, None] + bot * fy[:, None, None]).astype(np.float32)


class FloorRunner:
    """A Floor on (H, W, 3) images given bottom-up to OIDN; one device, filters per call.
    It drives pyoidn itself rather than the runtime's stage (runtime/oidn_prepass.py) for what
    the stage has no use for: each filter timed alone, and the aux resampled between the
    prefilters and the main filter. `blender` and `shipped` are the stage's own calls."""

    def __init__(self, threads: int) -> None:
        import pyoidn

        self.oidn = pyoidn
        self.device = pyoidn.Device(pyoidn.OIDN_DEVICE_TYPE_CPU)
        self.device.set_int("numThreads", threads)
        self.device.commit()
        self.seconds: dict[str, float] = {}  # CPU seconds of the last call, per filter

    def _filter(self, images: dict[str, np.ndarray], quality: str, color: bool,
                clean: bool) -> None:
        oidn = self.oidn
        flt = oidn.Filter(self.device, oidn.OIDN_FILTER_TYPE_RT)
        for slot, array in images.items():
            flt.set_image(slot, array, oidn.OIDN_FORMAT_FLOAT3)
        flt.set_quality(getattr(oidn, QUALITY[quality]))
        if color:
            flt.set_bool("hdr", True)
            flt.set_bool("cleanAux", clean)
        flt.commit()
        start = time.process_time()
        flt.execute()
        self.seconds["main" if color else next(iter(images))] = time.process_time() - start
        error = self.device.get_error()
        flt.release()
        if error is not None:
            raise RuntimeError(f"OIDN: {error}")

    def __call__(self, floor: Floor, color: np.ndarray, albedo: np.ndarray,
                 normal: np.ndarray) -> np.ndarray:
        h, w, _ = color.shape
        self.seconds = {}
        flip = [np.ascontiguousarray(x[::-1], np.float32) for x in (color, albedo, normal)]
        aux = {"albedo": flip[1], "normal": flip[2]}
        if floor.aux_quality is not None:
            for name in ("albedo", "normal"):
                src = _down(aux[name], floor.aux_scale) if floor.aux_scale > 1 else aux[name]
                out = np.zeros_like(src)
                self._filter({name: src, "output": out}, floor.aux_quality, False, False)
                aux[name] = (np.ascontiguousarray(_up(out, floor.aux_scale, h, w))
                             if floor.aux_scale > 1 else out)
        out = np.zeros_like(flip[0])
        self._filter({"color": flip[0], **aux, "output": out}, floor.main, True, floor.clean)
        return out[::-1]


def score(runner: FloorRunner, folder: Path, spp: int, floors: dict[str, Floor]) -> dict:
    n = json.loads((folder / cycles_io.MANIFEST).read_text())["frame_count"]
    psnr: dict[str, list[float]] = {k: [] for k in floors}
    for t in range(n):
        f = cycles_io.load_frame(folder, t, spp)
        for name, floor in floors.items():
            out = runner(floor, f["color"], f["albedo"], f["normal"])
            psnr[name].append(metrics.psnr(out, f["reference"][..., :3]))
    return {"shot": folder.name, "spp": spp, **{k: float(np.mean(v)) for k, v in psnr.items()}}


def timing(runner: FloorRunner, floors: dict[str, Floor], repeats: int) -> dict[str, dict]:
    """CPU seconds per 1280x720 frame of each floor (median of interleaved repeats, after a
    warm-up), and per filter."""
    b = {k: np.ascontiguousarray(v.transpose(1, 2, 0)) for k, v in frame_buffers(720, 1280).items()}
    runs: dict[str, list[dict[str, float]]] = {k: [] for k in floors}
    for r in range(repeats + 1):
        for name, floor in floors.items():
            runner(floor, b["color"], b["albedo"], b["normal"])
            if r:
                runs[name].append(dict(runner.seconds))
    out = {}
    for name, rows in runs.items():
        parts = {k: float(np.median([row[k] for row in rows])) for k in rows[0]}
        out[name] = {"cpu_s": float(np.median([sum(row.values()) for row in rows])), **parts}
    base = out["plain-high"]["cpu_s"]
    for row in out.values():
        row["ratio"] = row["cpu_s"] / base
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    cli_args.add_split(p, ZOO_SPLITS)
    cli_args.add_data(p)
    p.add_argument("--spp", default="1,2,4,8,16,64")
    p.add_argument("--floors", default=",".join(FLOORS))
    cli_args.add_threads(p)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--timing-only", action="store_true")
    p.add_argument("--quality-only", action="store_true")
    cli_args.add_json(p)
    args = p.parse_args(argv)
    floors = {k: FLOORS[k] for k in args.floors.split(",")}
    floors = {"plain-high": FLOORS["plain-high"], "blender": FLOORS["blender"], **floors}
    runner = FloorRunner(args.threads)
    result: dict = {"floors": {k: vars(v) for k, v in floors.items()}, "threads": args.threads,
                    "command": "python -m quietframe.experiments.oidn_floor " + " ".join(
                        sys.argv[1:] if argv is None else argv)}
    if not args.quality_only:
        result["timing_720p"] = t = timing(runner, floors, args.repeats)
        print("| floor | CPU s per 720p frame | × plain OIDN-high | filters (s) |")
        print("|---|---|---|---|")
        for name, row in t.items():
            parts = ", ".join(f"{k} {v:.2f}" for k, v in row.items()
                              if k not in ("cpu_s", "ratio"))
            print(f"| {name} | {row['cpu_s']:.2f} | {row['ratio']:.2f} | {parts} |", flush=True)
    if not args.timing_only:
        root = zoo_dir(args.data, args.split)
        folders = [m.parent for m in sorted(root.glob("*/manifest.json"))]
        rows = []
        names = [k for k in floors if k != "blender"]
        print("\n| shot | spp | blender dB | " + " | ".join(f"{k} Δ" for k in names) + " |")
        print("|---|---|---|" + "---|" * len(names))
        for folder in folders:
            for spp in (int(s) for s in args.spp.split(",")):
                row = score(runner, folder, spp, floors)
                rows.append(row)
                print(f"| {row['shot']} | {spp} | {row['blender']:.2f} | " + " | ".join(
                    f"{row[k] - row['blender']:+.2f}" for k in names) + " |", flush=True)
        result["quality"] = rows
        for spp in sorted({r["spp"] for r in rows}):
            at = [r for r in rows if r["spp"] == spp]
            print(f"spp {spp}: " + ", ".join(
                f"{k} mean {np.mean([r[k] - r['blender'] for r in at]):+.3f} worst "
                f"{min(r[k] - r['blender'] for r in at):+.3f}" for k in names))
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
