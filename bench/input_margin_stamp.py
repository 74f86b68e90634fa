"""Stamp how each model compares with its own noisy input on the validation zoo into its card.

    python -m quietframe.bench.model_card --no-card models/*.onnx \
        --input-margin docs/evaluation/learned-vs-input/zoo1-validation.json \
        docs/evaluation/learned-vs-input/zoo3-validation.json

From `bench/zoo_eval.py` runs on the zoo's **validation** split that scored the `noisy` method
(the input itself) beside the models: per model and spp, (model − noisy input) PSNR of each shot,
paired within one run; several runs (zoo rounds) are joined by shot, a shot measured in two runs
counting as the later run gave it. Written as the Cycles table's `input_margin` (runtime/card.py
InputMarginRow: the worst shot's margin and the mean), apart from the `zoo` rows so a run on a
few shots does not touch them. `auto` never chooses a model at an spp where its worst shot is
below its input (service/choice_policy.py); the cards and `quietframe models` say from which spp.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from quietframe.bench.model_metrics import RunProblem, stamp
from quietframe.bench.zoo_stamp import RENDERER
from quietframe.runtime.card import InputMarginRow, worse_than_input_from

INPUT_METHOD = "noisy"  # bench/zoo_eval's row of the input itself, scored like any method


def read_runs(paths: list[Path]) -> list[dict]:
    """The runs, checked: validation's, each with `noisy` rows. RunProblem otherwise, before
    anything is written."""
    runs = []
    for path in paths:
        try:
            run = json.loads(path.read_text())
            split, rows = run["meta"]["split"], run["rows"]
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise RunProblem(f"{path}: not a zoo.json of bench/zoo_eval.py ({exc})") from None
        if split != "validation":
            raise RunProblem(f"{path}: a {split} run; what auto may choose is measured on the "
                             "validation zoo only (the test zoo is reported, never used for "
                             "selection)")
        if not any(r["method"] == INPUT_METHOD for r in rows):
            raise RunProblem(f"{path}: no {INPUT_METHOD!r} rows; run bench/zoo_eval.py with "
                             f"--methods {INPUT_METHOD},<models> so each model is measured "
                             "against its own input")
        runs.append(run)
    return runs


def margins_by_shot(runs: list[dict], method: str) -> dict[float, dict[str, float]]:
    """spp -> shot -> the method's PSNR less the noisy input's in the same run (later runs
    win for a shot measured twice)."""
    out: dict[float, dict[str, float]] = {}
    for run in runs:
        noisy = {(r["shot"], r["spp"]): r["psnr"] for r in run["rows"]
                 if r["method"] == INPUT_METHOD}
        for r in run["rows"]:
            if r["method"] == method and (r["shot"], r["spp"]) in noisy:
                margin = r["psnr"] - noisy[(r["shot"], r["spp"])]
                out.setdefault(float(r["spp"]), {})[r["shot"]] = margin
    return out


def margin_rows(margins: dict[float, dict[str, float]]) -> list[InputMarginRow]:
    rows = []
    for spp, shots in sorted(margins.items()):
        worst = min(shots, key=shots.__getitem__)
        rows.append(InputMarginRow(spp, round(float(shots[worst]), 3),
                                   round(float(np.mean(list(shots.values()))), 3), worst,
                                   len(shots)))
    return rows


def measured_by(runs: list[dict], method: str) -> dict:
    """What measured a model's rows: the runs' commands and zoo rounds, the shots."""
    used = [run for run in runs if any(r["method"] == method for r in run["rows"])]
    shots = sorted({r["shot"] for run in used for r in run["rows"] if r["method"] == method})
    return {"commands": [run["meta"].get("command", "") for run in used],
            "zoo": [run["meta"].get("zoo", "") for run in used],
            "shots": shots, "split": "validation", "baseline": INPUT_METHOD}


def stamp_input_margin(paths: list[Path], models: list[Path]) -> list[str]:
    """Stamp each model's input margin from the runs at `paths`; one line per model (a model
    without rows is left as it is)."""
    runs = read_runs(paths)
    lines = []
    for path in models:
        margins = margins_by_shot(runs, path.stem)
        if not margins:
            lines.append(f"{path}: no rows for {path.stem!r} beside {INPUT_METHOD!r}; left as "
                         "it is")
            continue
        rows = margin_rows(margins)
        section = {"by_spp": [r.to_dict() for r in rows],
                   "measured": measured_by(runs, path.stem)}
        stamp(path, {"input_margin": section}, RENDERER)
        worse = worse_than_input_from(rows)
        lines.append(f"{path}: " + ", ".join(
            f"{r.spp:g} spp worst {r.worst_db:+.2f} ({r.worst_shot}), mean {r.mean_db:+.2f}"
            for r in rows) + (f"; worse than its input from {worse:g} spp" if worse is not None
                              else "; never below its input"))
    return lines
