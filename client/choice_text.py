"""A model choice in plain words, for the people who read farm logs: which model, why, what the
validation tables say of its quality and what time per frame to plan with (this server's
measured time where it has one), from the session's `choice` fields (the API's ChoicePublic)."""

from __future__ import annotations

import re

BUFFER_WORDS = {
    "albedo": "albedo",
    "normal": "normals",
    "depth": "depth",
    "motion": "motion vectors",
}


def noise_words(choice: dict) -> str:
    spp, source = choice.get("spp"), choice.get("noise_source") or ""
    if spp is None or source == "unknown":
        return "noise level unknown"
    if source == "estimate":
        return f"looks like about {spp:g} samples/pixel"
    return f"{spp:g} samples/pixel (render header)"


def why_words(reason: str) -> str:
    """The reason's gist: the model selection rule that decided."""
    if reason.startswith("kept:"):  # the server kept the shot's recorded model (shot_model)
        return "the shot's model, chosen once for the shot (recorded in --out/.quietframe)"
    if reason.startswith("no installed model accepts"):
        return "no model takes these passes; the server's default"
    if reason.startswith("no measured"):
        return "no measured tables; the server's default"
    fits = re.match(r"no model fits ([\d.]+) ms", reason)
    if fits:
        return f"nothing meets the {fits.group(1)} ms budget; the fastest"
    quality = reason.split(":", 1)[0] if ":" in reason else ""
    within = re.search(r"within ([\d.]+) dB of ([\w.-]+)", reason)
    if within:
        return (f"the fastest within {within.group(1)} dB of the best ({within.group(2)}), "
                f"quality {quality}")
    if "the best expected" in reason:
        return f"the best expected, quality {quality}"
    return reason


def time_words(choice: dict, measured_ms: float | None) -> str:
    """The time per frame to expect, the best-founded figure there is: the server's median
    denoise time of the model at the session's size (`measured_ms` of the choice, over its
    recent frames), else this run's frames of the model (`measured_ms`, their Server-Timing),
    else the tables' figure said for what it is: a 720p timing from another machine scaled to
    this frame size, often several times off on a farm node."""
    served = choice.get("measured_ms")
    if served is not None:
        frames = choice.get("measured_frames") or 0
        size = f" at {choice['measured_size']}" if choice.get("measured_size") else ""
        return (f"{served:.0f} ms per frame measured on this server{size} "
                f"({frames} frame{'' if frames == 1 else 's'})")
    if measured_ms is not None:
        return f"{measured_ms:.0f} ms per frame measured on this server"
    if choice.get("expected_ms") is None:
        return ""
    return (f"{choice['expected_ms']:.0f} ms per frame by the tables (timed on another "
            "machine, scaled from 720p; not measured here)")


def quality_words(choice: dict) -> str:
    """The tables' PSNR said for what it is: what the model averaged on the validation shots
    at this noise, not a prediction for this shot."""
    if choice.get("expected_psnr") is None:
        return ""
    return (f"{choice['expected_psnr']:.1f} dB PSNR on the validation shots at this noise (their "
            f"average, not a prediction for this shot)")


def describe_choice(choice: dict, pixels: int | None = None,
                    measured_ms: float | None = None) -> str:
    """`oidn-frame: the fastest within 0.3 dB of the best (...); 4 samples/pixel (render
    header), no usable motion vectors; 27.1 dB PSNR on the validation shots at this noise
    (...), 40 ms per frame measured on this server at 1920x1080 (32 frames)`; `measured_ms`:
    this run's time for the model so far, used where the server has measured none."""
    lacking = [words for name, words in BUFFER_WORDS.items()
               if name not in (choice.get("buffers") or ())]
    facts = [noise_words(choice)]
    if lacking:
        facts.append(f"no usable {', '.join(lacking)}")
    text = f"{choice['model']}: {why_words(choice.get('reason') or '')}; {', '.join(facts)}"
    figures = [words for words in (quality_words(choice), time_words(choice, measured_ms))
               if words]
    if figures:
        text += f"; {', '.join(figures)}"
    return text
