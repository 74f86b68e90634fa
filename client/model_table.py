"""`quietframe models` as a table: one row per model with what sets it apart in one line, its
measured speed and quality on the chosen renderer's frames (Cycles unless told otherwise), what
Blender's own denoise scores on the same frames, and what `auto` (every session's default) does
with them.

Every figure comes from the model cards (GET /v1/models `metrics`: the default renderer's table
at the top level, the others under `by_renderer`; runtime/card.py), every description from the
cards' architecture metadata, so two models that differ only in a setting say which setting.
"""

from __future__ import annotations

SPP_COLUMNS = (1, 4, 8)  # PSNR shown at these samples per pixel (the validation levels)
# Blender's denoise (Accurate prefilter + high) in CPU time per 720p frame, as a multiple of
# plain per-frame OIDN-high (oidn-frame), measured in one run (experiments/oidn_floor,
# docs/evaluation/oidn-floor): the cards time quietframe's models, not Blender.
BLENDER_DENOISE_COST = 6.88
# A model is for final frames where its table is within this of Blender's denoise at every spp
# shown (and measured); else a preview: quicker, or cheaper passes, at a visible loss.
FINAL_FRAMES_SLACK_DB = 0.1
CARD_DEFAULT_RENDERER = "mitsuba"  # the table at the top level of `metrics` (runtime/card.py)
ZOO_RENDERER = "cycles"  # the validation zoo's shots: its figures stand for every renderer's
RENDERER_NAMES = {"cycles": "Cycles", "mitsuba": "Mitsuba"}


def describe(model: dict) -> str:
    """One line on what the model is and what sets it apart from its neighbours, from its
    architecture metadata (the model card's JSON)."""
    arch = model.get("architecture") if isinstance(model.get("architecture"), dict) else {}
    family = str(arch.get("family") or "")
    if "quality" in arch:
        return _describe_oidn(arch, family)
    if family == "affinity":
        size = arch.get("kernel_size", "?")
        return (f"learned: affinity kernels (Isik et al.; {arch.get('kernels', '?')} kernels of "
                f"{size}x{size} px, the size a run-time option), temporal")
    if arch.get("layers") == 0 or arch.get("grids") == 0:
        aligned = "motion-aligned" if arch.get("aligned_history") else "not motion-aligned"
        return (f"temporal accumulation alone ({aligned} history, no spatial filter): a "
                "baseline, and the history stage of the OIDN models")
    if "grids" in arch:
        grids = f"{arch.get('grids', '?')} grid{'s' if arch.get('grids') != 1 else ''}"
        if arch.get("passthrough"):
            grids += " and a pass-through that can keep a clean input"
        return (f"learned preview: Neural Bilateral Grid ({arch.get('layers', '?')} layers, "
                f"{grids}), temporal; needs only colour")
    return str(arch.get("name", "")) or "-"


def _describe_oidn(arch: dict, family: str) -> str:
    """OIDN-based models: what feeds OIDN, at which quality, with which aux, and what follows."""
    quality = ("OIDN high quality" if arch.get("quality") == "high"
               else f"OIDN {arch.get('quality')} (quicker, softer detail)")
    source = str(arch.get("color_from") or "")
    if not source:
        return (f"{quality} on each frame alone, no history: what Blender's own denoise does "
                "(for frames without motion vectors)")
    history = ("the motion-aligned accumulation" if source.startswith("aligned")
               else "the temporal accumulation (not motion-aligned)")
    if arch.get("prefilter_aux"):
        aux = (f"albedo/normal prefiltered by OIDN {arch.get('aux_quality') or 'high'} first "
               "(cleaner aux at low spp, slower)")
    else:
        aux = "albedo/normal as rendered (plain aux)"
    after = ""
    if family == "output-history":
        after = ", blended with its own previous output along the motion"
    elif "temporal_kernel_size" in arch:
        after = ", then a learned temporal stage"
    return f"{quality} on {history}{after}; {aux}"


def renderer_table(model: dict, renderer: str) -> tuple[dict, bool]:
    """The model's measured table for `renderer`, and whether it is that renderer's own: a
    model without one shows the cards' default renderer's (which is what `auto` reads too)."""
    metrics = model.get("metrics") or {}
    if renderer == CARD_DEFAULT_RENDERER:
        return metrics, True
    table = (metrics.get("by_renderer") or {}).get(renderer)
    if isinstance(table, dict) and table.get("by_spp"):
        return table, True
    return metrics, False


def input_margin(model: dict, renderer: str) -> dict:
    """The card's `input_margin` (the model against its own noisy input on the validation zoo,
    runtime/card.py): the renderer's table's, else the zoo's renderer's, as `auto` reads it;
    {} where not measured."""
    table, _ = renderer_table(model, renderer)
    zoo = ((model.get("metrics") or {}).get("by_renderer") or {}).get(ZOO_RENDERER) or {}
    for candidate in (table, zoo):
        margin = candidate.get("input_margin") if isinstance(candidate, dict) else None
        if isinstance(margin, dict) and margin.get("by_spp"):
            return margin
    return {}


def worth_using(model: dict, renderer: str) -> str:
    """Where the model is worth using against its noisy input, one clause; "" unmeasured."""
    margin = input_margin(model, renderer)
    levels = [r["spp"] for r in margin.get("by_spp") or () if isinstance(r, dict) and "spp" in r]
    if not levels:
        return ""
    worse = margin.get("worse_than_input_from_spp")
    if not isinstance(worse, int | float):
        return (f"never worse than its noisy input on the validation zoo "
                f"({min(levels):g}-{max(levels):g} spp)")
    return (f"worth using below {worse:g} spp: from there worse than its noisy input on a "
            "validation-zoo shot (auto does not choose it there)")


def _rows_by_spp(table: dict) -> dict[float, dict]:
    return {float(r["spp"]): r for r in table.get("by_spp") or ()
            if isinstance(r, dict) and "spp" in r}


def _figures(values: list) -> str:
    """`26.0/27.8/28.5`, `-` where a level was not measured; `-` when none was."""
    if not any(isinstance(v, int | float) for v in values):
        return "-"
    return "/".join(f"{v:.1f}" if isinstance(v, int | float) else "-" for v in values)


def _psnr(table: dict) -> str:
    rows = _rows_by_spp(table)
    return _figures([rows.get(float(spp), {}).get("psnr") for spp in SPP_COLUMNS])


def _versus_denoise(table: dict) -> str:
    """The model's PSNR less Blender's denoise of the same frames, per spp: `+0.7/-0.1/+0.2`."""
    rows = _rows_by_spp(table)
    gaps = []
    for spp in SPP_COLUMNS:
        row = rows.get(float(spp), {})
        own, theirs = row.get("psnr"), row.get("renderer_denoise")
        numbers = isinstance(own, int | float) and isinstance(theirs, int | float)
        gaps.append(own - theirs if numbers else None)
    if not any(g is not None for g in gaps):
        return "-"
    return "/".join(f"{g:+.1f}" if g is not None else "-" for g in gaps)


def use_of(table: dict) -> str:
    """`final` or `preview` from the table's gap to Blender's denoise (FINAL_FRAMES_SLACK_DB),
    `-` where it was not measured."""
    rows = _rows_by_spp(table)
    gaps = [rows[float(spp)]["psnr"] - rows[float(spp)]["renderer_denoise"] for spp in SPP_COLUMNS
            if all(isinstance(rows.get(float(spp), {}).get(k), int | float)
                   for k in ("psnr", "renderer_denoise"))]
    if not gaps:
        return "-"
    return "final" if min(gaps) >= -FINAL_FRAMES_SLACK_DB else "preview"


def renderer_denoise(models: list[dict], renderer: str) -> list[float | None]:
    """PSNR of the renderer's own denoise at SPP_COLUMNS, from the first card that measured it
    (every card measured it on the same validation frames)."""
    for model in models:
        table, own = renderer_table(model, renderer)
        rows = _rows_by_spp(table) if own else {}
        values = [rows.get(float(spp), {}).get("renderer_denoise") for spp in SPP_COLUMNS]
        if any(isinstance(v, int | float) for v in values):
            return values
    return [None] * len(SPP_COLUMNS)


def _ms(table: dict) -> str:
    ms = table.get("ms_720p")
    return f"{ms:.0f} ms" if isinstance(ms, int | float) else "-"


def _timed_on(models: list[dict], renderer: str) -> str:
    """Where the 720p figures were timed: `a 192x192 run on Intel(R) Xeon(R) ..., 2 threads`."""
    places = set()
    for model in models:
        table, _ = renderer_table(model, renderer)
        measured = table.get("measured") if isinstance(table.get("measured"), dict) else {}
        timing = measured.get("timing") if isinstance(measured.get("timing"), dict) else measured
        if timing.get("machine"):
            size = str(timing.get("resolution") or "").replace("\u00d7", "x")
            places.add(f"{size + ' frames on ' if size else ''}{timing['machine']}")
    return "; ".join(sorted(places)) if places else "the machine that measured them"


def _options(model: dict) -> str:
    """`kernel_size (default 13; one of 5, 7, 9, 11, 13)` per run-time option."""
    parts = []
    for option in model.get("options") or ():
        allowed = option.get("allowed")
        values = f"; one of {', '.join(map(str, allowed))}" if allowed else ""
        if option.get("minimum") is not None:
            values += f"; at least {option['minimum']:g}"
        parts.append(f"{option['name']} (default {option['default']}{values})")
    return "; ".join(parts)


def model_table(models: list[dict], default: str, renderer: str = "cycles") -> str:
    name = RENDERER_NAMES.get(renderer, renderer)
    theirs = renderer_denoise(models, renderer)
    versus = any(v is not None for v in theirs)
    header = ["MODEL", "NEEDS", "720p", "PSNR dB @1/4/8spp"]
    header += [*(["vs BLENDER dB", "FOR"] if versus else []), "WHAT"]
    rows = [["auto  [session default]", "color", "-", "-", *(["-", "either"] if versus else []),
             "chooses per shot from the passes, noise and these tables; `quietframe denoise` "
             "prints each shot's choice"]]
    if versus:
        rows.append(["Blender's denoise", "-", f"{BLENDER_DENOISE_COST:.1f}x oidn-frame",
                     _figures(theirs), "-", "final",
                     "Blender's own denoise (OIDN, Accurate prefilter) of the same frames, for "
                     "comparison: what the farm has without quietframe"])
    for m in models:
        table, own = renderer_table(m, renderer)
        mark = "  [auto's fallback]" if m["name"] == default else ""
        what = describe(m)
        if not own:
            what += f" ({RENDERER_NAMES[CARD_DEFAULT_RENDERER]} table: none measured on {name})"
        if worth := worth_using(m, renderer):
            what += f"; {worth}"
        if m.get("options"):
            what += f"; options: {_options(m)} (--model-option NAME=VALUE)"
        row = [f"{m['name']} {m['version']}{mark}", ",".join(m["required_buffers"]), _ms(table),
               _psnr(table)]
        rows.append([*row, *([_versus_denoise(table), use_of(table)] if versus else []), what])
    columns = len(header) - 1  # the last, WHAT, runs on unpadded
    widths = [max(len(r[i]) for r in (header, *rows)) for i in range(columns)]
    lines = ["  ".join(c.ljust(w) for c, w in zip(r[:columns], widths, strict=True)) + "  "
             + r[columns] for r in (header, *rows)]  # the header first: `| head -1` reads it
    lines.append("")
    lines.append(f"Tables measured on {name} frames (--renderer {renderer}"
                 + (", the default: farm frames are Blender's, and auto reads these tables for "
                    "any frame whose header says Cycles" if renderer == "cycles" else "")
                 + "; --renderer " + " or ".join(r for r in RENDERER_NAMES if r != renderer)
                 + " for the others).")
    lines.append("PSNR: validation frames with every pass present (docs/benchmarks.md)"
                 + ("; vs BLENDER: the model's PSNR less Blender's denoise of the same frames; "
                    f"FOR: final frames where within {FINAL_FRAMES_SLACK_DB:g} dB of Blender's "
                    "denoise at every spp shown, else preview" if versus else "") + ".")
    if versus:
        lines.append(f"Blender's denoise costs {BLENDER_DENOISE_COST:g}x plain per-frame "
                     "OIDN-high (oidn-frame) in CPU time per 720p frame, measured in one run "
                     "(docs/evaluation/oidn-floor).")
    lines.append(f"720p: ms per 1280x720 frame scaled from timings of {_timed_on(models, renderer)}"
                 ": a table figure, not this server's time (`quietframe denoise` prints that "
                 "per frame and in its summary).")
    return "\n".join(lines)
