"""The learned tiers against their input, per-frame OIDN and Blender's denoise, in target terms.

    python -m quietframe.bench.learned_report RUN/zoo.json [RUN/zoo.json ...] \
        --tiers nbg-2l-3g,affinity-h16-k5gc,nbg-2l-3g-corpus --times times.json --out DIR

Reads `bench/zoo_eval.py` runs that scored the tiers beside `noisy` (the input itself), per-frame
OIDN at fast quality with plain aux (`oidn-fast-history/frame`, the OIDN-fast stage of the
service's history tier), per-frame OIDN-high (`oidn-high`) and Blender's denoise, all on the same
frames. Per tier it writes the three figures the learned tiers' quality targets are stated in
(docs/zoo.md, "After the corpus fine-tune"):

- the margin over the noisy input, per spp, on the worst shot (target: at least +3 dB);
- the mean gap to Blender's denoise at 1-4 spp (targets: -2.5 dB nbg, -2.0 dB affinity);
- the gap to per-frame OIDN-fast at 1-4 spp, mean and worst shot (target: within 1.5 dB);

with per-shot tables, and a speed-versus-error plot: each method's time per 1280x720 frame as a
multiple of plain OIDN-high's (`--times`: the JSON `bench/oidn_speedup.py --json` writes on the
same machine: keys `oidn-high`, `oidn-fast` and the model files' stems) against its mean gap to
Blender's denoise at 1-4 spp; Blender's denoise is the plot's zero line (its time is Blender's,
not measured here). Writes <out>/README.md and <out>/speed_vs_error.png.
"""

from __future__ import annotations

import argparse
import json
from collections import defaultdict
from pathlib import Path

import numpy as np

INPUT = "noisy"
OIDN_FAST = "oidn-fast-history/frame"
OIDN_HIGH = "oidn-high"
BLENDER = "blender-denoise"
BASELINES = (OIDN_FAST, OIDN_HIGH, BLENDER)
TIME_KEYS = {OIDN_FAST: "oidn-fast", OIDN_HIGH: "oidn-high"}  # their keys in --times
LOW_SPP = (1.0, 4.0)  # the targets' "1-4 spp": every level in this range the runs scored
# The targets per tier family (a candidate is named after its tier: nbg-2l-3g-corpus)
VS_BLENDER_TARGET = {"nbg": -2.5, "affinity": -2.0}
VS_INPUT_TARGET = 3.0
VS_OIDN_FAST_TARGET = -1.5

Table = dict[tuple[str, float], dict[str, float]]  # (shot, spp) -> method -> PSNR


def read_rows(paths: list[Path]) -> tuple[Table, list[str]]:
    """PSNR by (shot, spp) and method over the runs (a later run wins for a cell scored twice),
    and the runs' commands."""
    table: Table = defaultdict(dict)
    commands = []
    for path in paths:
        run = json.loads(path.read_text())
        commands.append(f"{run['meta'].get('zoo', '?')} {run['meta']['split']}: "
                        f"`{run['meta'].get('command', '?')}`")
        for r in run["rows"]:
            table[(r["shot"], float(r["spp"]))][r["method"]] = float(r["psnr"])
    return dict(table), commands


def gaps(table: Table, method: str, against: str,
         spp_range: tuple[float, float] | None = None) -> dict[tuple[str, float], float]:
    """(shot, spp) -> method's PSNR less `against`'s, where both were scored."""
    out = {}
    for (shot, spp), row in table.items():
        in_range = spp_range is None or spp_range[0] <= spp <= spp_range[1]
        if in_range and method in row and against in row:
            out[(shot, spp)] = row[method] - row[against]
    return out


def family_target(tier: str) -> float | None:
    return next((v for k, v in VS_BLENDER_TARGET.items() if tier.startswith(k)), None)


def summary(table: Table, tier: str) -> dict:
    """The tier's figures in the targets' terms (None where the runs lack them)."""
    vs_input = gaps(table, tier, INPUT)
    by_spp: dict[float, list[float]] = defaultdict(list)
    for (_, spp), gap in vs_input.items():
        by_spp[spp].append(gap)
    vs_blender = list(gaps(table, tier, BLENDER, LOW_SPP).values())
    vs_fast = list(gaps(table, tier, OIDN_FAST, LOW_SPP).values())
    return {
        "input_margin_worst": {spp: min(v) for spp, v in sorted(by_spp.items())},
        "vs_blender_low": float(np.mean(vs_blender)) if vs_blender else None,
        "vs_oidn_fast_low": float(np.mean(vs_fast)) if vs_fast else None,
        "vs_oidn_fast_low_worst": min(vs_fast) if vs_fast else None,
        "target_vs_blender": family_target(tier),
    }


def _met(value: float | None, target: float | None) -> str:
    if value is None:
        return "–"
    if target is None:
        return f"{value:+.2f}"
    return f"{value:+.2f} ({'met' if value >= target else f'missed by {target - value:.2f}'})"


def report(table: Table, tiers: list[str], commands: list[str]) -> str:
    spps = sorted({spp for _, spp in table})
    lines = ["# The learned tiers against their input, per-frame OIDN and Blender's denoise", "",
             "From " + "; ".join(commands) + ".", "",
             "## Against the targets", "",
             "| tier | worst shot's margin over the input, " + " / ".join(
                 f"{s:g}" for s in spps) + " spp (target ≥ +3) | mean gap to Blender's denoise "
             "at 1–4 spp | to OIDN-fast at 1–4 spp, mean | worst shot |",
             "|---|---|---|---|---|"]
    for tier in tiers:
        s = summary(table, tier)
        margins = " / ".join(f"{s['input_margin_worst'][spp]:+.2f}"
                             if spp in s["input_margin_worst"] else "–" for spp in spps)
        lines.append(f"| {tier} | {margins} | "
                     f"{_met(s['vs_blender_low'], s['target_vs_blender'])} | "
                     f"{_met(s['vs_oidn_fast_low'], None)} | "
                     f"{_met(s['vs_oidn_fast_low_worst'], VS_OIDN_FAST_TARGET)} |")
    methods = [INPUT, *tiers, OIDN_FAST, OIDN_HIGH]
    lines += ["", "## Per shot and spp (dB: Blender's denoise, each method less it)", "",
              "| shot | spp | Blender | " + " | ".join(methods) + " |",
              "|---|---|---|" + "---|" * len(methods)]
    for (shot, spp), row in sorted(table.items()):
        if BLENDER not in row:
            continue
        cells = [f"{row[m] - row[BLENDER]:+.2f}" if m in row else "–" for m in methods]
        lines.append(f"| {shot} | {spp:g} | {row[BLENDER]:.2f} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def plot(table: Table, tiers: list[str], times: dict[str, float], out: Path) -> Path | None:
    """Time per 720p frame (× OIDN-high) against the mean gap to Blender's denoise at 1-4 spp."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    points = []
    for method in (*tiers, OIDN_FAST, OIDN_HIGH):
        low = list(gaps(table, method, BLENDER, LOW_SPP).values())
        key = TIME_KEYS.get(method, method)
        if key in times and low:
            points.append((method, times[key], float(np.mean(low))))
    if not points:
        return None
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for name, x, y in points:
        ax.scatter(x, y, s=30)
        ax.annotate(name, (x, y), textcoords="offset points", xytext=(5, 4), fontsize=8)
    ax.set_xscale("log")
    ax.set_xlabel("time per 1280×720 frame (× plain per-frame OIDN-high)")
    ax.set_ylabel("mean PSNR less Blender's denoise, 1–4 spp (dB)")
    ax.axhline(0, color="grey", linewidth=0.8)
    ax.annotate("Blender's denoise", (ax.get_xlim()[0], 0), textcoords="offset points",
                xytext=(4, 4), fontsize=8, color="grey")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    path = out / "speed_vs_error.png"
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("runs", type=Path, nargs="+", help="zoo.json files of bench/zoo_eval.py")
    p.add_argument("--tiers", required=True, help="comma list of the learned tiers' methods")
    p.add_argument("--times", type=Path, help="JSON: method -> time per 720p frame ÷ OIDN-high's")
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args(argv)
    table, commands = read_rows(args.runs)
    tiers = [t for t in args.tiers.split(",") if t]
    args.out.mkdir(parents=True, exist_ok=True)
    text = report(table, tiers, commands)
    if args.times:
        path = plot(table, tiers, json.loads(args.times.read_text()), args.out)
        if path:
            text += f"\n![speed against error]({path.name})\n\nTimes: `{args.times}`.\n"
    (args.out / "README.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
