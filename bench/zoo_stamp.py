"""Stamp how each model held on the validation zoo into its card, where `auto` reads it.

    python -m quietframe.bench.model_card --zoo docs/evaluation/zoo-validation/zoo.json \
        --no-card models/*.onnx

Per model and spp, from a `bench/zoo_eval.py` run on the zoo's **validation** split (the test
split is never read for selection): the gap to per-frame OIDN-high in the same run (mean over
shots and the worst shot), and the shortfall against the model's own table, which was measured
on the scene generator's validation split: min(0, zoo gap − table gap), where the table gap is
the model's Cycles PSNR less per-frame OIDN-high's (`oidn-frame`, the same filter as the
evaluation's `oidn-high`). `auto` takes the shortfall off the model's expected PSNR
(service/model_profiles.ModelProfile.expected_psnr), so a learned tier whose lead came from the
generator's look, and not from the shots, is not chosen for it. Also the worst shot's gap to
Blender's own denoise, which `auto` reads to prefer models that held on every shot
(service/choice_policy.holding_on_every_shot). Writes the cards' Cycles table
(`zoo`) in place; models without zoo rows are left as they are.
"""

from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path

import numpy as np

from quietframe.bench.model_metrics import RunProblem, card_of, stamp
from quietframe.runtime.card import ModelCard, ZooRow
from quietframe.service.model_profiles import at_spp

BASELINE_METHOD = "oidn-high"  # per-frame OIDN-high, plain aux: the evaluation's row
RENDERER_DENOISE = "blender-denoise"  # Blender's own denoise of the same frames
BASELINE_MODEL = "oidn-frame"  # the installed model that is the same filter (its table)
RENDERER = "cycles"


def zoo_gaps(rows: list[dict], method: str,
             baseline: str = BASELINE_METHOD) -> dict[float, list[float]]:
    """spp -> per shot, the method's PSNR less `baseline`'s in the same run."""
    base = {(r["shot"], r["spp"]): r["psnr"] for r in rows if r["method"] == baseline}
    gaps: dict[float, list[float]] = defaultdict(list)
    for r in rows:
        if r["method"] == method and (r["shot"], r["spp"]) in base:
            gaps[float(r["spp"])].append(r["psnr"] - base[(r["shot"], r["spp"])])
    return dict(gaps)


def table_psnr(card: ModelCard, spp: float) -> float | None:
    """The card's Cycles PSNR at `spp`, interpolated as `auto` reads it."""
    return at_spp([(r.spp, r.psnr) for r in card.measured(RENDERER).by_spp], spp)


def zoo_rows(gaps: dict[float, list[float]], card: ModelCard, baseline: ModelCard,
             vs_denoise: dict[float, list[float]]) -> list[ZooRow]:
    out = []
    for spp, values in sorted(gaps.items()):
        own, base = table_psnr(card, spp), table_psnr(baseline, spp)
        table_gap = own - base if own is not None and base is not None else 0.0
        gap = float(np.mean(values))
        worst_vs_denoise = (round(float(min(vs_denoise[spp])), 3) if vs_denoise.get(spp)
                            else None)
        out.append(ZooRow(spp, round(gap, 3), round(float(min(values)), 3),
                          round(min(0.0, gap - table_gap), 3), worst_vs_denoise))
    return out


def stamp_zoo(zoo: Path, models: list[Path]) -> list[str]:
    """Stamp each model's zoo rows from `zoo` (zoo.json of a validation run); one line per
    model. Raises RunProblem, before any file is written, for a run that is not validation's
    or without oidn-frame among `models` (its table is the baseline of the table gap)."""
    run = json.loads(zoo.read_text())
    if run["meta"]["split"] != "validation":
        raise RunProblem(f"{zoo}: a {run['meta']['split']} run; auto's tables come from the "
                         "validation zoo only (the test zoo is reported, never used for "
                         "selection)")
    baseline_path = next((m for m in models if m.stem == BASELINE_MODEL), None)
    if baseline_path is None:
        raise RunProblem(f"give {BASELINE_MODEL}.onnx too: its table is the baseline of the "
                         "table gap")
    baseline = card_of(baseline_path)
    measured = {"command": run["meta"]["command"], "zoo": run["meta"]["zoo"],
                "shots": run["meta"]["shots"], "baseline": BASELINE_METHOD}
    lines = []
    for path in models:
        gaps = zoo_gaps(run["rows"], path.stem)
        if not gaps:
            lines.append(f"{path}: no zoo rows for {path.stem!r}; left as it is")
            continue
        rows = zoo_rows(gaps, card_of(path), baseline,
                        zoo_gaps(run["rows"], path.stem, RENDERER_DENOISE))
        stamp(path, {"zoo": {"by_spp": [r.to_dict() for r in rows], "measured": measured}},
              RENDERER)
        lines.append(f"{path}: " + ", ".join(
            f"{r.spp:g} spp {r.gap_db:+.2f} (worst {r.worst_gap_db:+.2f}, shortfall "
            f"{r.shortfall_db:+.2f}, worst against Blender's denoise {r.worst_vs_denoise_db})"
            for r in rows))
    return lines
