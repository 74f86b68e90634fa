"""The wire protocol of /v1 frames, shared by the server and the clients: media type, header
names, reset reasons, the cut signal. Standard library only, so a farm node that installs just
the client extra can import it."""

from __future__ import annotations

from enum import Enum

EXR_MEDIA_TYPE = "image/x-exr"
# Request bodies the frame route accepts as EXR (an unset type is taken to be EXR).
ACCEPTED_FRAME_TYPES = frozenset({EXR_MEDIA_TYPE, "application/octet-stream", ""})

CUT_QUERY = "cut"  # POST .../frames/{index}?cut=true: camera cut, start a fresh history
CUT_ATTRIBUTE = "quietframe.cut"  # EXR header attribute: nonzero int or "1"/"true" = cut
# POST .../frames/{index}?shot_model=NAME (model=auto): the model already chosen for the frame's
# shot (by another chunk of it); a frame that starts the shot's history takes it
SHOT_MODEL_QUERY = "shot_model"


class Reset(str, Enum):
    """Why a frame started from a fresh history (the one representation, server and client)."""

    NONE = "none"  # history continued
    FIRST_FRAME = "first-frame"
    CUT = "cut"  # ?cut=true or the header attribute
    GAP = "gap"  # a frame index was skipped
    STATE_LOST = "state-lost"  # the session's stored history was damaged and set aside
    # A temporal model's frame without motion vectors whose aux moved (motion blur on, a
    # renderer that writes none): its history would ghost, so this frame did not use it.
    NO_MOTION = "no-usable-motion"
    # A frame whose aux changed almost everywhere along its motion vectors: a camera cut the
    # client did not flag (runtime/motion_evidence.judge_cut); the history starts afresh.
    DETECTED_CUT = "detected-cut"


class Header:
    """Response headers of a denoised frame (HTTP header names are case-insensitive)."""

    FRAME = "X-Quietframe-Frame"
    RESET = "X-Quietframe-Reset"  # a Reset value
    MODEL = "X-Quietframe-Model"  # "<name> <version>"
    SANITIZED = "X-Quietframe-Sanitized"  # input values replaced by the sanitising rule
    SANITIZED_BUFFERS = "X-Quietframe-Sanitized-Buffers"  # "color=3, depth=1"
    MISSING = "X-Quietframe-Missing"  # optional buffers absent, fed as zeros: "motion"
    # A temporal model's frame without usable motion vectors: what its aux showed and whether
    # the history was used, e.g. "moving (64% of 120 tiles moved); history not used"
    MOTION = "X-Quietframe-Motion"
    # model=auto sessions: "<model>; spp=<n>; source=<header attribute|estimate|unknown>;
    # reason=<why>" (the choice made at the shot's first frame, repeated on every frame of it)
    CHOICE = "X-Quietframe-Choice"
    # A session naming a model that reads the frame's spp, where neither its options nor the
    # header state one: "<spp>; source=estimate", the shot's estimate the model was given
    SAMPLES = "X-Quietframe-Samples"
    PENDING = "X-Quietframe-Pending"
    # A model asked for by name at an spp where its card says it is worse than its own noisy
    # input (service/below_input.py); on a frame's reply, and on a session's creation where
    # its spp option is in that range
    WARNING = "X-Quietframe-Warning"
    REPLAYED = "X-Quietframe-Replayed"  # "true": the stored reply of an idempotent retry
    SERVER_TIMING = "Server-Timing"  # "decode;dur=1.0, denoise;dur=..., encode;..., total;..."


def view_layers(names) -> tuple[str, ...]:
    """View layers of a multilayer EXR from its channel names: the first segment of
    `<layer>.<pass>.<channel>` (Blender's multilayer naming); empty for a single-layer file.
    The server's session `layer` and the CLI's `--layer all` read files the same way."""
    return tuple(sorted({n.split(".", 1)[0] for n in names if n.count(".") >= 2}))


def join_list(items) -> str:
    return ", ".join(items)


def split_list(value: str) -> tuple[str, ...]:
    return tuple(item.strip() for item in value.split(",") if item.strip())


def format_counts(counts: dict[str, int]) -> str:
    return join_list(f"{name}={count}" for name, count in sorted(counts.items()))


def parse_counts(value: str) -> dict[str, int]:
    """`format_counts` read back: "color=3, depth=1" -> {"color": 3, "depth": 1}."""
    counts = {}
    for part in split_list(value):
        name, _, count = part.partition("=")
        if name and count.isdigit():
            counts[name] = int(count)
    return counts


def format_timings(timings_ms: dict[str, float]) -> str:
    return join_list(f"{stage};dur={ms:.1f}" for stage, ms in timings_ms.items())


def parse_timings(value: str) -> dict[str, float]:
    timings = {}
    for part in split_list(value):
        stage, _, dur = part.partition(";dur=")
        if stage and dur:
            timings[stage] = float(dur)
    return timings


# X-Quietframe-Motion of a frame that followed motion estimated from the aux (no vectors)
_ESTIMATED = "motion estimated from the aux; history used on {:.0f}% of the frame"


def format_estimated_motion(evidence: str, share: float) -> str:
    """The Motion header where the history followed estimated motion on `share` of the frame."""
    return f"{evidence}; " + _ESTIMATED.format(100 * share)


def parse_estimated_motion(value: str) -> float | None:
    """The share of the frame whose history followed estimated motion, or None (not said)."""
    head, _, tail = _ESTIMATED.partition("{:.0f}")
    start = value.find(head)
    if start < 0:
        return None
    number = value[start + len(head):].split(tail, 1)[0]
    try:
        return float(number) / 100
    except ValueError:
        return None
