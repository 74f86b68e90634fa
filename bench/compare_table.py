"""The temporal tiers' targets table from `quietframe-eval` JSON: each method against the
per-frame baselines of the same run, at every spp, and whether it meets the targets (with the
amount where it misses).

    quietframe-eval --compare RUN.json [--static STATIC.json]
        [--methods a,b] [--against oidn-frame,blender-denoise] [--trmae 0.7] [--flicker 0.5]
        [--wide]

RUN: an evaluation of moving shots (PSNR, TRMAE, ms at 720p); STATIC: one of locked-off shots
(`*-static` splits), whose flicker (model/metrics.flicker) is scored against the first
baseline's. Targets (docs/architecture.md, "Tiers"): PSNR at least every baseline's; TRMAE at
most `--trmae` × the first baseline's; flicker on locked-off shots at most `--flicker` × its.
Ratios and differences are of figures measured in one run, so machine load cancels out of them.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path

DEFAULT_AGAINST = ("oidn-frame", "blender-denoise")  # the per-frame baselines of a Cycles run
TRMAE_TARGET = 0.7  # × the first baseline's
FLICKER_TARGET = 0.5  # × the first baseline's, on locked-off shots


def load_rows(path: Path) -> dict[tuple[str, int], dict]:
    return {(r["method"], int(r["spp"])): r for r in json.loads(path.read_text())["rows"]}


def _ratio(value: float, base: float) -> float:
    return value / base if base and math.isfinite(base) and math.isfinite(value) else math.nan


def compare(run: dict, static: dict | None, methods: list[str], against: Sequence[str],
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


def table_text(run_path: Path, static_path: Path | None = None, methods: Sequence[str] = (),
               against: Sequence[str] = DEFAULT_AGAINST, trmae: float = TRMAE_TARGET,
               flicker: float = FLICKER_TARGET, wide_only: bool = False) -> str:
    """The markdown `quietframe-eval --compare` prints: `methods` (default every method of the
    run) against the baselines `against`, as the targets table and its summary, or with
    `wide_only` PSNR by spp alone. Raises ValueError where the run lacks a baseline."""
    run = load_rows(run_path)
    static = load_rows(static_path) if static_path else None
    missing = [b for b in against if not any(m == b for m, _ in run)]
    if missing:
        raise ValueError(f"{run_path} has no rows of {', '.join(missing)}")
    methods = list(methods) or list(dict.fromkeys(m for m, _ in run))
    if wide_only:
        return "\n".join(wide(run, methods, against[0]))
    table, summary = compare(run, static, methods, against, trmae, flicker)
    return "\n".join([*table, "", *summary])
