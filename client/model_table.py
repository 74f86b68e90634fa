"""`quietframe models` as a table: one row per model with what it is in one line, its measured
speed and quality, and what `auto` (every session's default) does with them."""

from __future__ import annotations

SPP_COLUMNS = (1, 4, 8)  # PSNR shown at these samples per pixel (the validation levels)


def describe(model: dict) -> str:
    """One line on what the model is, from its name and architecture."""
    name = model["name"]
    arch = model.get("architecture") if isinstance(model.get("architecture"), dict) else {}
    if name == "oidn-frame":
        return "Open Image Denoise on each frame alone: no history (frames without motion)"
    if name.startswith("oidn-temporal"):
        return "OIDN on the temporal accumulation, then a learned temporal stage"
    if name.startswith("oidn"):
        return f"OIDN ({arch.get('quality', 'high')}) on quietframe's temporal accumulation"
    if name.startswith("nbg"):
        return (f"Neural Bilateral Grid ({arch.get('layers', '?')} layers, "
                f"{arch.get('grids', '?')} grids), temporal: the fast tier")
    if name.startswith("affinity"):
        return "affinity kernels (Isik et al.), temporal: the quality tier"
    if name == "accumulation":
        return "temporal accumulation alone (no spatial filter): a baseline"
    return str(arch.get("name", "")) or "-"


def _psnr(model: dict) -> str:
    rows = {float(r["spp"]): r.get("psnr") for r in (model.get("metrics") or {}).get("by_spp")
            or [] if isinstance(r, dict) and "spp" in r}
    values = [rows.get(float(spp)) for spp in SPP_COLUMNS]
    if not any(isinstance(v, int | float) for v in values):
        return "-"
    return "/".join(f"{v:.1f}" if isinstance(v, int | float) else "-" for v in values)


def _ms(model: dict) -> str:
    ms = (model.get("metrics") or {}).get("ms_720p")
    return f"{ms:.0f} ms" if isinstance(ms, int | float) else "-"


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


def model_table(models: list[dict], default: str) -> str:
    header = ("MODEL", "NEEDS", "720p", "PSNR dB @1/4/8spp", "WHAT")
    rows = [("auto  [session default]", "color", "-", "-",
             "chooses per shot from the passes, noise and these tables; `quietframe denoise` "
             "prints each shot's choice")]
    for m in models:
        mark = "  [auto's fallback]" if m["name"] == default else ""
        what = describe(m)
        if m.get("options"):
            what += f"; options: {_options(m)} (--model-option NAME=VALUE)"
        rows.append((f"{m['name']} {m['version']}{mark}", ",".join(m["required_buffers"]),
                     _ms(m), _psnr(m), what))
    widths = [max(len(r[i]) for r in (header, *rows)) for i in range(4)]
    lines = ["  ".join(c.ljust(w) for c, w in zip(r[:4], widths, strict=True)) + "  " + r[4]
             for r in (header, *rows)]
    lines.append("")
    lines.append("PSNR: validation tables with every pass present (docs/benchmarks.md); 720p: "
                 "ms per 1280x720 frame on the machine that measured it.")
    return "\n".join(lines)
