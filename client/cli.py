"""`quietframe` command: denoise | models, and the commands other parts of quietframe register
under the `quietframe.commands` entry point (`serve`, from quietframe.service.cli).

`denoise` and `models --server` import only the client extra.
"""

from __future__ import annotations

import argparse
import os
import sys
from importlib.metadata import entry_points

EXIT_FAILURE, EXIT_USAGE = 1, 2
COMMANDS_GROUP = "quietframe.commands"


def _denoise(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from quietframe.client.api import Client, QuietframeError, RetryPolicy
    from quietframe.client.sequence import Job, SequenceError, run_sequence

    if not args.server:
        print("quietframe: error: pass --server URL (or set QUIETFRAME_SERVER)", file=sys.stderr)
        return EXIT_USAGE
    try:
        job = Job.plan(args.input, args.out)
    except SequenceError as exc:
        print(f"quietframe: error: {exc}", file=sys.stderr)
        return EXIT_FAILURE
    done = job.first_pending()
    bar = tqdm(
        total=len(job.files), initial=done, unit="frame", dynamic_ncols=True, disable=args.quiet
    )
    if done:
        bar.write(f"resuming: {done} of {len(job.files)} frames already in {job.out_dir}")
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
        print(f"  figures: {figures or 'none recorded (untrained export)'}")
    return 0


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
    denoise.add_argument("--model", default="auto")
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
