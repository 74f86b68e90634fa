"""`quietframe` command: denoise | models, and the commands other parts of quietframe register
under the `quietframe.commands` entry point (`serve`, from quietframe.service.cli).

`denoise` and `models --server` import only the client extra.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from importlib.metadata import entry_points
from pathlib import Path

EXIT_FAILURE, EXIT_USAGE = 1, 2
COMMANDS_GROUP = "quietframe.commands"


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
    """Session fields from the command line (besides model, precision, compression); ValueError
    for a --channels that is not a JSON object (or @file holding one)."""
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
    return {
        "channels": mapping or None,
        "motion_scale": tuple(args.motion_scale) if args.motion_scale else None,
        "quality": args.quality,
        "latency_ms": args.latency_ms,
        "denoised_layer": args.denoised_layer,
        "model_options": dict(args.model_option or ()),  # a repeated name: the last one
    }


def _layers(job, layer: str | None, options: dict) -> tuple[str | None, ...]:
    """The view layers to denoise, one session each: `all` reads them from the first frame."""
    from quietframe.client.sequence import file_view_layers

    if layer != "all":
        return (layer,)
    if options["channels"]:
        raise ValueError(
            "--channels names whole channels, the same for every session; with --layer all "
            "leave it out (each view layer's passes are found by name) or run one --layer each"
        )
    return file_view_layers(job.files[0]) or (None,)


def _denoise(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from quietframe.client.api import Client, QuietframeError, RetryPolicy
    from quietframe.client.sequence import Job, SequenceError, run_sequence

    if not args.server:
        print("quietframe: error: pass --server URL (or set QUIETFRAME_SERVER)", file=sys.stderr)
        return EXIT_USAGE
    try:
        options = session_options(args)
    except ValueError as exc:
        print(f"quietframe: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    try:
        job = Job.plan(args.input, args.out)
        layers = _layers(job, args.layer, options)
    except (SequenceError, ValueError) as exc:
        print(f"quietframe: error: {exc}", file=sys.stderr)
        return EXIT_FAILURE
    done = job.first_pending()
    bar = tqdm(
        total=len(job.files), initial=done, unit="frame", dynamic_ncols=True, disable=args.quiet
    )
    if done:
        bar.write(f"resuming: {done} of {len(job.files)} frames already in {job.out_dir}")
    if len(layers) > 1:
        bar.write(f"view layers {', '.join(map(str, layers))}: one session each, one file out")
    current = {"path": job.files[min(done, len(job.files) - 1)]}

    def progress(p) -> None:
        current["path"] = job.files[min(p.position + 1, len(job.files) - 1)]
        if p.result is None:
            bar.set_postfix_str(f"warm-up {p.path.name}")
            return
        bar.update(1)
        notes = [] if p.result.reset == "none" else [f"reset={p.result.reset}"]
        if p.result.sanitized:
            notes.append(f"sanitized={p.result.sanitized}")
        if p.result.missing:
            notes.append(f"missing={','.join(p.result.missing)}")
        bar.set_postfix_str(" ".join(notes))

    token = args.token or os.environ.get("QUIETFRAME_TOKEN")
    try:
        retry = RetryPolicy(retries=args.retries)
        with Client(args.server, token=token, timeout_s=args.timeout, retry=retry) as client:
            run_sequence(
                client,
                job,
                args.server,
                model=args.model,
                precision=args.precision,
                warmup=args.warmup,
                compression=args.compression,
                on_progress=progress,
                layers=layers,
                **options,
            )
    except (QuietframeError, SequenceError, OSError) as exc:
        bar.close()
        print(f"quietframe: error at {current['path'].name}: {exc}", file=sys.stderr)
        print("quietframe: run the same command again to resume", file=sys.stderr)
        return EXIT_FAILURE
    bar.close()
    if not args.quiet:
        print(f"{len(job.files)} frames in {job.out_dir}")
    return 0


def _models(args: argparse.Namespace) -> int:
    if args.server:
        from quietframe.client.api import Client, QuietframeError

        token = args.token or os.environ.get("QUIETFRAME_TOKEN")
        try:
            with Client(args.server, token=token) as client:
                listing = client.models()
        except QuietframeError as exc:
            print(f"quietframe: error: {exc}", file=sys.stderr)
            return EXIT_FAILURE
        models, default = listing["models"], listing["default"]
    else:
        try:
            from quietframe.service.model_registry import ModelRegistry
            from quietframe.service.settings import Settings
        except ImportError as exc:
            print(
                f"quietframe: error: listing local models needs the serve extra ({exc}); "
                "pass --server URL to ask a server",
                file=sys.stderr,
            )
            return EXIT_FAILURE
        registry = ModelRegistry(Settings(threads=1))
        models = [m.model_dump() for m in registry.public()]
        default = registry.default
    for m in models:
        metrics = m.get("metrics") or {}
        figures = ", ".join(f"{k}={v}" for k, v in metrics.items() if not isinstance(v, dict))
        mark = " (default)" if m["name"] == default else ""
        print(f"{m['name']} {m['version']}{mark}")
        print(
            f"  needs: {', '.join(m['required_buffers'])}; "
            f"optional: {', '.join(m['optional_buffers']) or '-'}"
        )
        if m.get("options"):  # run-time options a session can set (--model-option)
            print(f"  options: {'; '.join(_option_text(o) for o in m['options'])}")
        print(f"  figures: {figures or 'none recorded (untrained export)'}")
    return 0


def _option_text(option: dict) -> str:
    """A listed model option: 'kernel_size (default 13; one of 5, 7, 9, 11, 13): <doc>'."""
    allowed = option.get("allowed")
    values = f"; one of {', '.join(map(str, allowed))}" if allowed else ""
    doc = f": {option['doc']}" if option.get("doc") else ""
    return f"{option['name']} (default {option['default']}{values}){doc}"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="quietframe", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)

    denoise = sub.add_parser("denoise", help="denoise a folder or glob of EXR frames")
    denoise.add_argument("input", help="folder of .exr frames, or a glob like 'shot/*.exr'")
    denoise.add_argument("--out", required=True, help="output folder (same file names)")
    denoise.add_argument(
        "--server",
        default=os.environ.get("QUIETFRAME_SERVER"),
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
    denoise.add_argument("--quiet", action="store_true", help="no progress bar")
    denoise.set_defaults(func=_denoise)

    models = sub.add_parser("models", help="list models (installed here, or on --server)")
    models.add_argument("--server", default=os.environ.get("QUIETFRAME_SERVER"))
    models.add_argument("--token")
    models.set_defaults(func=_models)
    for command in entry_points(group=COMMANDS_GROUP):  # e.g. `serve`, from quietframe.service
        command.load()(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return args.func(args)


if __name__ == "__main__":
    sys.exit(main())
