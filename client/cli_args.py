"""The `quietframe denoise` command's flags: how each is parsed, and the session fields read
from them (cli.py runs the command)."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

from quietframe.client.session_fields import AUTO, MAX_LOOKAHEAD, SessionFields
from quietframe.client.settings import client_settings

# Session fields a run sets itself: the frames' size, one session per view layer, and the
# settings it passes apart (sequence.job_settings, run_sequence)
RUN_FIELDS = frozenset({"width", "height", "model", "precision", "compression", "layer"})


def model_option(text: str) -> tuple[str, int | float]:
    """One --model-option NAME=VALUE: the value an int when integral (kernel_size=9), else a
    float; argparse turns the ArgumentTypeError into a usage error."""
    name, sep, raw = text.partition("=")
    try:
        value = float(raw)
    except ValueError:
        value = math.nan
    if not sep or not name.strip() or not math.isfinite(value):
        raise argparse.ArgumentTypeError(
            f"expected NAME=VALUE with a number as VALUE, e.g. kernel_size=9; got {text!r}"
        )
    return name.strip(), int(value) if value.is_integer() else value


def session_options(args: argparse.Namespace) -> dict:
    """Session fields from the command line, each from the flag of its name (--latency-ms:
    latency_ms), besides those the run sets itself (RUN_FIELDS); ValueError for a --channels
    that is not a JSON object (or @file holding one)."""
    text = args.channels
    if text is not None and text.startswith("@"):
        try:
            text = Path(text[1:]).read_text()
        except OSError as exc:
            raise ValueError(f"--channels {args.channels}: {exc}") from exc
    try:
        mapping = json.loads(text) if text is not None else None
    except ValueError as exc:
        raise ValueError(f"--channels is not JSON ({exc}): {text!r}") from exc
    if mapping is not None and not isinstance(mapping, dict):
        raise ValueError('--channels must be a JSON object, e.g. \'{"albedo": "alb"}\'')
    given = {name: getattr(args, name) for name in SessionFields.model_fields
             if name not in RUN_FIELDS and hasattr(args, name)}
    if given.get("lookahead") == 0:  # today's session: no new setting in the records
        given["lookahead"] = None
    return given | {
        "channels": mapping or None,
        "motion_scale": tuple(args.motion_scale) if args.motion_scale else None,
        "model_options": dict(args.model_option or ()),  # a repeated name: the last one
    }


def flag_problem(args: argparse.Namespace, options: dict) -> tuple[str, str] | None:
    """(message, advice) for flags that contradict each other or cannot work, which the run
    would otherwise refuse late or ignore silently; None when they hold together."""
    if args.pre_roll < 0 or args.post_roll < 0 or args.warmup < 0:
        return "--pre-roll, --post-roll and --warmup take a frame count >= 0", ""
    lookahead = args.lookahead or 0
    if not 0 <= lookahead <= MAX_LOOKAHEAD:
        return (f"--lookahead is how many later frames each frame may use, 0 to "
                f"{MAX_LOOKAHEAD}; got {lookahead}", "e.g. --lookahead 2 (with --post-roll 2 "
                "for a chunk of a longer shot), or leave it out")
    if args.post_roll > lookahead:
        unused = "no output uses them" if not lookahead else (
            f"a frame looks at most --lookahead {lookahead} frame(s) ahead")
        return (f"--post-roll {args.post_roll} sends frames after --frames only for the "
                f"look-ahead of the chunk's last frames, and {unused}",
                f"pass --post-roll {lookahead}" if lookahead else
                "pass --lookahead K with --post-roll K, or leave out --post-roll")
    if not args.timeout > 0 or not math.isfinite(args.timeout):
        return (f"--timeout is seconds per request, > 0; got {args.timeout:g}",
                "e.g. --timeout 300 (a farm requeues a failure it cannot fix forever)")
    if not args.wait_for_shot_start >= 0 or not math.isfinite(args.wait_for_shot_start):
        return f"--wait-for-shot-start is seconds >= 0; got {args.wait_for_shot_start:g}", ""
    if args.retries < 0:
        return f"--retries is a count >= 0; got {args.retries}", "0: no retries"
    if args.motion_scale and "motion" not in (options["channels"] or {}):
        return ("--motion-scale scales the motion layer named in --channels, and --channels "
                "names none", 'map it too, e.g. --channels \'{"motion": "Vector"}\' '
                "--motion-scale 1 -1; a motion pass the alias table finds (Blender's Vector) "
                "is scaled by it")
    chosen = [flag for flag, value in (("--quality", args.quality),
                                       ("--latency-ms", args.latency_ms)) if value is not None]
    if chosen and args.model != AUTO:
        return (f"{' and '.join(chosen)} choose among models for --model auto; --model "
                f"{args.model} is fixed", f"leave out {' and '.join(chosen)}, or use --model auto")
    return None


def add_denoise_arguments(denoise: argparse.ArgumentParser) -> None:
    """The denoise command's flags, on its subparser."""
    denoise.add_argument(
        "input",
        help="folder of .exr frames, a glob like 'shot/*.exr', or a frame pattern like "
        "'shot.####.exr' or 'shot.%%04d.exr'",
    )
    denoise.add_argument("--out", required=True, help="output folder (same file names)")
    denoise.add_argument(
        "--frames",
        metavar="RANGE",
        help="frames to denoise and write, e.g. 1001-1100 (or Blender's 1001..1100) or "
        "1001-1012,1050 (default: all)",
    )
    denoise.add_argument(
        "--pre-roll",
        type=int,
        default=0,
        metavar="N",
        help="send the N frames before --frames first, to warm the history without writing "
        "them (a farm chunk then continues its shot without a visible pop)",
    )
    denoise.add_argument(
        "--post-roll",
        type=int,
        default=0,
        metavar="N",
        help="with --lookahead, send the N frames after --frames too, so the chunk's last "
        "frames see their later frames, without writing them (at most --lookahead; a shot's "
        "last chunk: --cut at the frame after the shot)",
    )
    denoise.add_argument(
        "--lookahead",
        type=int,
        default=None,  # unset: the server's default (0), and no new setting in the records
        metavar="K",
        help=f"frames (0-{MAX_LOOKAHEAD}) the server holds back so that each frame's denoise "
        "also uses the K frames after it: a frame's output comes K frames later, and those "
        "still held are finished at the end of the run (docs/service.md, 'Look-ahead')",
    )
    denoise.add_argument(
        "--cut",
        type=int,
        action="append",
        metavar="FRAME",
        help="a camera cut at FRAME: the history starts afresh there (repeatable)",
    )
    denoise.add_argument(
        "--wait-for-shot-start",
        type=float,
        default=0.0,
        metavar="SECONDS",
        help="with --model auto, wait up to SECONDS for the first frame of a shot this run "
        "sends (a cut) when it is not rendered yet and no chunk has recorded the shot's model: "
        "auto decides a shot from its first frame only. Then, or at once by default, exit 75 "
        "(retry later)",
    )
    denoise.add_argument(
        "--force",
        action="store_true",
        help="redo outputs that are not this job's (other files, re-rendered sources, changed "
        "flags) in a new session instead of refusing",
    )
    denoise.add_argument(
        "--dry-run",
        action="store_true",
        help="check what the run checks before it sends a frame, and send none: every frame's "
        "header (size, view layers, passes, truncation, gaps), the files in --out, the server "
        "(reachable, token), the model and its options, --layer, --channels, every session "
        "setting (a session is opened and deleted); writes nothing, the same exit codes",
    )
    denoise.add_argument(
        "--strict", action="store_true", help="a missing frame in the range is an error"
    )
    denoise.add_argument(
        "--json", action="store_true", help="one JSON event per line on stdout, for scripts"
    )
    denoise.add_argument(
        "--server",
        default=client_settings().server,
        help="server URL (env QUIETFRAME_SERVER)",
    )
    denoise.add_argument("--model", default="auto", help="installed model name, or auto")
    denoise.add_argument(
        "--quality",
        choices=("fast", "balanced", "best"),
        help="target for --model auto: fast (within 1 dB of the best expected), balanced "
        "(0.3 dB), best",
    )
    denoise.add_argument(
        "--latency-ms",
        type=float,
        help="budget for --model auto: expected denoise ms per frame at the frames' size",
    )
    denoise.add_argument(
        "--model-option",
        type=model_option,
        action="append",
        metavar="NAME=VALUE",
        help="a run-time option of the model, repeatable, e.g. kernel_size=9 for an affinity "
        "model (`quietframe models` lists each model's options)",
    )
    denoise.add_argument(
        "--layer",
        help="view layer to denoise (Blender: ViewLayer, ...); 'all': every view layer of the "
        "files, one session each, written into one output file per frame",
    )
    denoise.add_argument(
        "--channels",
        metavar="JSON",
        help="session channel mapping, buffer -> layer or channel list, as JSON or @file: "
        '\'{"albedo": "alb", "depth": "Z"}\'',
    )
    denoise.add_argument(
        "--motion-scale",
        nargs=2,
        type=float,
        metavar=("X", "Y"),
        help="factors for a motion layer named in --channels (Blender Vector: 1 -1)",
    )
    denoise.add_argument(
        "--locked-off",
        dest="camera",
        action="store_const",
        const="locked",
        default=None,  # unset: the server's default (auto), and no new setting in the records
        help="the camera is locked off for the whole shot: frames without motion vectors keep "
        "their history without being judged from their aux (at 1-4 spp aux noise can look "
        "like motion); a cut the aux show still resets it",
    )
    denoise.add_argument(
        "--motion",
        choices=("estimated", "rendered-only"),
        default=None,  # unset: the server's default (estimated)
        help="frames of a moving shot without motion vectors (motion blur on): follow motion "
        "estimated from the aux, trusted per pixel (estimated, the default), or start the "
        "history afresh on each (rendered-only)",
    )
    denoise.add_argument(
        "--denoised-layer",
        metavar="NAME",
        help="write the denoised colour as a new layer <view layer>.NAME and keep the noisy "
        "beauty (default: the denoised colour replaces the beauty's R, G, B)",
    )
    denoise.add_argument(
        "--precision",
        choices=("input", "half", "float"),
        default="input",
        help="output pixel type; input: that of the input colour",
    )
    denoise.add_argument(
        "--compression",
        default="input",
        help="output EXR compression: input (keep), none, zip, piz, dwaa, ...",
    )
    denoise.add_argument("--token", help="bearer token (env QUIETFRAME_TOKEN)")
    denoise.add_argument(
        "--warmup",
        type=int,
        default=4,
        help="frames re-sent to rebuild history when resuming in a new session",
    )
    denoise.add_argument("--timeout", type=float, default=300.0, help="seconds per request")
    denoise.add_argument(
        "--retries",
        type=int,
        default=5,
        help="retries per request on 429/5xx/connection errors (with backoff)",
    )
    denoise.add_argument(
        "--quiet", action="store_true", help="errors and warnings only (no progress)"
    )
