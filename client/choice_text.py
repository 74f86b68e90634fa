"""A model choice in plain words, for the people who read farm logs: which model, why, and what
quality to expect (from the model's measured tables), from the session's `choice` fields
(the API's ChoicePublic)."""

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
    """The time per frame to expect: measured on this server when frames of this model are
    done (Server-Timing), else the tables' figure said for what it is: a 720p timing from
    another machine scaled to this frame size, often several times off on a farm node."""
    if measured_ms is not None:
        return f"{measured_ms:.0f} ms per frame measured on this server"
    if choice.get("expected_ms") is None:
        return ""
    return (f"{choice['expected_ms']:.0f} ms per frame by the tables (timed on another "
            "machine, scaled from 720p; not measured here)")


def describe_choice(choice: dict, pixels: int | None = None,
                    measured_ms: float | None = None) -> str:
    """`oidn-frame: the fastest within 0.3 dB of the best (...); 4 samples/pixel (render
    header), no usable motion vectors; expect about 27.1 dB PSNR (validation tables), 40 ms
    per frame by the tables (...)`; `measured_ms`: this server's time for the model so far."""
    lacking = [words for name, words in BUFFER_WORDS.items()
               if name not in (choice.get("buffers") or ())]
    facts = [noise_words(choice)]
    if lacking:
        facts.append(f"no usable {', '.join(lacking)}")
    text = f"{choice['model']}: {why_words(choice.get('reason') or '')}; {', '.join(facts)}"
    expect = []
    if choice.get("expected_psnr") is not None:
        expect.append(f"about {choice['expected_psnr']:.1f} dB PSNR (validation tables)")
    timing = time_words(choice, measured_ms)
    if timing:
        expect.append(timing)
    if expect:
        text += f"; expect {', '.join(expect)}"
    return text
