"""Write measured speed/error tables into shipped models' metadata (`quietframe.metrics`).

    python -m quietframe.bench.model_card --stamp --no-card --evaluation docs/benchmarks.json \
        models/*.onnx

(bench/model_card.py's command: it stamps, then writes the markdown cards unless `--no-card`).
The rows of one `quietframe-eval` run (benchmarks.json: method = model file stem) become
`by_spp` (spp, PSNR, TRMAE) and `ms_720p` (the same run's 1280×720 timing), with the run's
command and machine as `measured`; `--absent` adds `absent_db` (mean PSNR change per absent
buffer) and `absent_db_worst` (the largest loss over the run's sequences) from
bench/auto_choice.py's buffer-absence rows; `--noise-points` adds `by_noise` from a validation
run of bench/auto_choice.py (rows with every buffer: the first frame's log2 noise statistic,
demodulated and not, and the model's PSNR on the sequence; service/model_profiles.py).
`--static-evaluation` adds each spp row's `flicker` from a run on locked-off shots (a
`*-static` split: the temporal std of τ(output), which no reference noise limits), and
`--timing` takes `ms_720p` from another run (a quiet one, e.g. with the renders paused) instead
of the evaluation's own. Where the renderer has its own denoise and the run measured it
(Blender's on Cycles: `blender-denoise`), each row also gets `renderer_denoise`, its PSNR on
the same frames. `--measured-as` stamps one model from another method's rows: a candidate
measured beside the shipped models under its own name (e.g. `affinity-h16-k5gc-mix`), then
installed under the shipped name. Existing keys (training's validation score) are kept.
`--renderer` names whose frames were measured (the card keeps a table per renderer,
runtime/card.py; default: the renderer the evaluation ran on, and every run must agree).
Nothing here is typed in: `model=auto` reads what a
measurement wrote (docs/model-interface.md).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import onnx

from quietframe.runtime.card import DEFAULT_RENDERER, Measurements, ModelCard, finite_figure

RUN_KEYS = ("command", "machine", "threads", "split", "resolution", "sequences")
# The method of a quietframe-eval run that is the renderer's own denoise of the same frames
# (stamped into every row as `renderer_denoise`: auto's floor on that renderer's frames).
RENDERER_DENOISE_METHOD = {"cycles": "blender-denoise"}


def metrics_from_rows(rows: list[dict], meta: dict, static_rows: list[dict] = (),
                      static_meta: dict | None = None, timing_rows: list[dict] | None = None,
                      timing_meta: dict | None = None, renderer_rows: list[dict] = ()) -> dict:
    """`quietframe.metrics` additions for one model from its evaluation rows, plus flicker per
    spp from its rows of a locked-off run, the 720p time from a timing run where given, and
    the renderer's own denoise PSNR per spp from the same evaluation's rows of it."""
    rows = sorted(rows, key=lambda r: r["spp"])
    flicker = {r["spp"]: r["flicker"] for r in static_rows if finite_figure(r.get("flicker"))}
    own = {r["spp"]: r["psnr"] for r in renderer_rows if finite_figure(r.get("psnr"))}
    table = [{"spp": r["spp"], "psnr": round(r["psnr"], 3), "trmae": round(r["trmae"], 4),
              **({"flicker": round(flicker[r["spp"]], 5)} if r["spp"] in flicker else {}),
              **({"renderer_denoise": round(own[r["spp"]], 3)} if r["spp"] in own else {})}
             for r in rows]
    out: dict = {"by_spp": table}
    timed = [r["ms_720p"] for r in (rows if timing_rows is None else timing_rows)
             if finite_figure(r.get("ms_720p"))]
    if timed:
        out["ms_720p"] = round(float(timed[0]), 1)
    out["measured"] = {k: meta[k] for k in RUN_KEYS if k in meta}
    if flicker and static_meta:
        out["measured"]["flicker"] = {k: static_meta[k] for k in RUN_KEYS if k in static_meta}
    if timed and timing_rows is not None and timing_meta:
        out["measured"]["timing"] = {k: timing_meta[k] for k in RUN_KEYS if k in timing_meta}
    return out


def rows_of(run: dict, method: str) -> list[dict]:
    """One method's rows of a quietframe-eval run (benchmarks.json)."""
    return [r for r in run["rows"] if r["method"] == method]


def run_problem(renderer: str, **runs: dict | None) -> str | None:
    """Why these quietframe-eval runs (benchmarks.json, by option name) cannot make `renderer`'s
    table, or None: a quality run on the test split (model selection never reads it), or a run
    on another renderer's frames."""
    for option, run in runs.items():
        if run is None:
            continue
        flag, meta = "--" + option.replace("_", "-"), run.get("meta", {})
        if option != "timing" and meta.get("split", "").startswith("test"):
            return (f"{flag}: a test-split run; auto's tables come from validation (model "
                    "selection never reads the test split)")
        if meta.get("renderer", DEFAULT_RENDERER) != renderer:
            return (f"{flag}: a run on {meta.get('renderer', DEFAULT_RENDERER)} frames, not "
                    f"{renderer}")
    return None


def noise_points(result: dict, model: str) -> dict | None:
    """`by_noise` for one model from a bench/auto_choice.py run (its rows with all buffers)."""
    points = [[round(r["noise"]["log2_sigma"], 4), round(r["noise"]["log2_sigma_colour"], 4),
               round(r["fixed"][model]["psnr"], 3)]
              for r in result["rows"]
              if r["buffers"] == "all" and model in r["fixed"] and r.get("noise")
              and None not in r["noise"].values()]
    if not points:
        return None
    return {"points": points, "measured": {"command": result["meta"]["command"],
                                           "data": result["meta"]["data"]}}


def worst_absent_db(result: dict, model: str) -> dict[str, float]:
    """Per absent buffer, the largest PSNR loss over the run's (sequence, spp) entries: what
    `model=auto` plans for (a missing motion buffer costs an accumulating model ~0 on a static
    shot and 2-3 dB on a moving camera; the mean hides that)."""
    none = {(e["sequence"], e["spp"]): e[model]["psnr"] for e in result["absence"]
            if e["absent"] == "none" and model in e}
    worst: dict[str, float] = {}
    for e in result["absence"]:
        key = (e["sequence"], e["spp"])
        if e["absent"] in ("none", "all-aux") or model not in e or key not in none:
            continue
        change = e[model]["psnr"] - none[key]
        worst[e["absent"]] = round(min(worst.get(e["absent"], 0.0), change), 3)
    return worst


def card_of(path: Path, model: onnx.ModelProto | None = None) -> ModelCard:
    """The card in a model file's metadata (read without an inference session); `model`: the
    file already loaded."""
    model = model or onnx.load(str(path), load_external_data=False)
    return ModelCard.from_props({p.key: p.value for p in model.metadata_props}, path.stem)


def stamp(path: Path, additions: dict, renderer: str = DEFAULT_RENDERER) -> dict:
    """Merge `additions` into the card's table for `renderer` (rewrites the file in place, its
    card in the current version) and return the card's `quietframe.metrics`."""
    model = onnx.load(str(path))
    card = card_of(path, model)
    table = Measurements.from_dict({**card.measured(renderer).to_dict(), **additions}
                                   if renderer in card.measurements else additions)
    card = card.with_measurements(renderer, table)
    del model.metadata_props[:]
    onnx.helper.set_model_props(model, card.to_props())
    onnx.save_model(model, str(path))
    return card.metrics()


class RunProblem(ValueError):
    """Runs that cannot make the table asked for: nothing is written (the command's error)."""


@dataclass(frozen=True)
class TableRuns:
    """The runs one renderer's table is stamped from, as their files were given."""

    evaluation: Path  # benchmarks.json: by_spp and ms_720p
    static_evaluation: Path | None = None  # benchmarks.json of locked-off shots: flicker
    timing: Path | None = None  # benchmarks.json of a quiet timing run: ms_720p instead
    absent: Path | None = None  # auto_choice.json: absent_db and absent_db_worst
    noise_points: Path | None = None  # auto_choice.json of a validation run: by_noise


def _read(path: Path | None) -> dict | None:
    return json.loads(path.read_text()) if path else None


def stamp_tables(models: list[Path], runs: TableRuns, renderer: str | None = None,
                 measured_as: str | None = None) -> list[str]:
    """Stamp each model's table for `renderer` (default: the renderer the evaluation ran on)
    from `runs`, the rows of method `measured_as` or else of the file's stem; one line per
    model. Raises RunProblem, before any file is written, where the runs cannot make that
    table."""
    if measured_as and len(models) != 1:
        raise RunProblem("--measured-as names one model's rows: give exactly one model")
    evaluation = _read(runs.evaluation)
    static, timing = _read(runs.static_evaluation), _read(runs.timing)
    renderer = renderer or evaluation.get("meta", {}).get("renderer", DEFAULT_RENDERER)
    problem = run_problem(renderer, evaluation=evaluation, static_evaluation=static,
                          timing=timing)
    if problem:
        raise RunProblem(problem)
    absence_run = _read(runs.absent) or {}
    absent = absence_run.get("absent_db", {})
    choice_run = _read(runs.noise_points)
    if choice_run and "validation" not in choice_run["meta"]["data"]:
        raise RunProblem(f"--noise-points {runs.noise_points}: not a validation run (model "
                         "selection never reads the test split)")
    lines = []
    for path in models:
        method = measured_as or path.stem
        rows = rows_of(evaluation, method)
        if not rows:
            lines.append(f"{path}: no rows for {method!r} in {runs.evaluation}; left as it is")
            continue
        additions = metrics_from_rows(
            rows, evaluation.get("meta", {}),
            rows_of(static, method) if static else (), static and static.get("meta"),
            rows_of(timing, method) if timing else None, timing and timing.get("meta"),
            rows_of(evaluation, RENDERER_DENOISE_METHOD.get(renderer, "")))
        if method in absent:
            additions["absent_db"] = absent[method]
            additions["absent_db_worst"] = worst_absent_db(absence_run, method)
        by_noise = noise_points(choice_run, method) if choice_run else None
        if by_noise:
            additions["by_noise"] = by_noise
        metrics = stamp(path, additions, renderer)
        lines.append(f"{path}: {json.dumps(metrics)[:200]}")
    return lines
