"""The temporal tiers' targets table from `quietframe-eval` JSON: each method against the
per-frame baselines of the same run, at every spp, and whether it meets the targets (with the
amount where it misses).

    python -m quietframe.bench.compare_table RUN.json [--static STATIC.json]
        [--methods a,b] [--against oidn-frame,blender-denoise] [--trmae 0.7] [--flicker 0.5]
        [--wide]

RUN: an evaluation of moving shots (PSNR, TRMAE, ms at 720p); STATIC: one of locked-off shots
(`*-static` splits), whose flicker (model/metrics.flicker) is scored against the first
baseline's. Targets (docs/architecture.md, "Tiers"): PSNR at least every baseline's; TRMAE at
most `--trmae` × the first baseline's; flicker on locked-off shots at most `--flicker` × its.
Ratios and differences are of figures measured in one run, so machine load cancels out of them.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path


def load_rows(path: Path) -> dict[tuple[str, int], dict]:
    return {(r["method"], int(r["spp"])): r for r in json.loads(path.read_text())["rows"]}


def _ratio(value: float, base: float) -> float:
    return value / base if base and math.isfinite(base) and math.isfinite(value) else math.nan


def compare(run: dict, static: dict | None, methods: list[str], against: list[str],
            trmae_target: float, flicker_target: float) -> tuple[list[str], list[str]]:
    """(markdown lines of the per-spp table, markdown lines of the targets summary)."""
    spps = sorted({spp for (_, spp) in run})
    first = against[0]
    head = ["method", "spp", "PSNR", "SSIM"] + [f"Δ {b}" for b in against] + [f"TRMAE ÷ {first}"]
    head += [f"flicker ÷ {first} (locked-off)"] if static else []
    head += ["ms 720p", f"ms ÷ {first}"]
    table = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    summary = ["| method | worst Δ PSNR " + " | worst Δ PSNR ".join(against)
               + f" | worst TRMAE ÷ {first}" + (f" | worst flicker ÷ {first}" if static else "")
               + " | misses |", "|" + "---|" * (len(against) + 3 + bool(static))]
    for method in methods:
        worst = {b: math.inf for b in against}
        worst_trmae = worst_flicker = -math.inf
        for spp in spps:
            row = run.get((method, spp))
            if row is None:
                continue
            cells = [method, str(spp), f"{row['psnr']:.2f}", f"{row['ssim']:.4f}"]
            for b in against:
                delta = row["psnr"] - run[(b, spp)]["psnr"]
                worst[b] = min(worst[b], delta)
                cells.append(f"{delta:+.2f}")
            trmae = _ratio(row["trmae"], run[(first, spp)]["trmae"])
            worst_trmae = max(worst_trmae, trmae)
            cells.append(f"{trmae:.2f}")
            if static:
                still, base = static.get((method, spp)), static.get((first, spp))
                flicker = _ratio(still["flicker"], base["flicker"]) if still and base else math.nan
                if math.isfinite(flicker):
                    worst_flicker = max(worst_flicker, flicker)
                cells.append(f"{flicker:.2f}")
            ms, base_ms = row.get("ms_720p", math.nan), run[(first, spp)].get("ms_720p", math.nan)
            cells += [f"{ms:.0f}" if math.isfinite(ms) else "–",
                      f"{_ratio(ms, base_ms):.2f}" if math.isfinite(ms) else "–"]
            table.append("| " + " | ".join(cells) + " |")
        misses = [f"PSNR {-worst[b]:.2f} dB below {b}" for b in against if worst[b] < 0]
        if worst_trmae > trmae_target:
            misses.append(f"TRMAE {worst_trmae:.2f}× (target ≤ {trmae_target:g}×)")
        if static and worst_flicker > flicker_target:
            misses.append(f"flicker {worst_flicker:.2f}× (target ≤ {flicker_target:g}×)")
        cells = [method, *(f"{worst[b]:+.2f}" for b in against), f"{worst_trmae:.2f}"]
        cells += [f"{worst_flicker:.2f}"] if static else []
        summary.append("| " + " | ".join(cells) + " | " + ("; ".join(misses) or "none") + " |")
    return table, summary


def wide(run: dict, methods: list[str], base: str) -> list[str]:
    """One row per method: PSNR at each spp, with its difference to `base` in brackets, and
    the run's ms per 720p frame (markdown lines)."""
    spps = sorted({spp for (_, spp) in run})
    lines = ["| method | " + " | ".join(f"{s} spp" for s in spps) + " | ms 720p |",
             "|" + "---|" * (len(spps) + 2)]
    for method in methods:
        cells = []
        for spp in spps:
            row = run.get((method, spp))
            cells.append("–" if row is None else
                         f"{row['psnr']:.2f} ({row['psnr'] - run[(base, spp)]['psnr']:+.2f})")
        ms = next((r.get("ms_720p", math.nan) for (m, _), r in run.items() if m == method),
                  math.nan)
        lines.append(f"| {method} | " + " | ".join(cells)
                     + f" | {f'{ms:.0f}' if math.isfinite(ms) else '–'} |")
    return lines


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run", type=Path)
    p.add_argument("--static", type=Path)
    p.add_argument("--methods", help="comma list (default: every method of the run)")
    p.add_argument("--against", default="oidn-frame,blender-denoise")
    p.add_argument("--trmae", type=float, default=0.7)
    p.add_argument("--flicker", type=float, default=0.5)
    p.add_argument("--wide", action="store_true",
                   help="only PSNR by spp, one row per method, difference to the first baseline")
    args = p.parse_args(argv)
    run = load_rows(args.run)
    static = load_rows(args.static) if args.static else None
    against = args.against.split(",")
    missing = [b for b in against if not any(m == b for m, _ in run)]
    if missing:
        p.error(f"{args.run} has no rows of {', '.join(missing)}")
    methods = (args.methods.split(",") if args.methods
               else list(dict.fromkeys(m for m, _ in run)))
    if args.wide:
        print("\n".join(wide(run, methods, against[0])))
        return 0
    table, summary = compare(run, static, methods, against, args.trmae, args.flicker)
    print("\n".join(table), "", "\n".join(summary), sep="\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
