"""`quietframe serve`: run the denoising server.

Registered into the `quietframe` command through the `quietframe.commands` entry point (the
client package defines no server command); `python -m quietframe.service.cli` runs it directly.
Imports the serve extra only when the command runs.
"""

from __future__ import annotations

import argparse
import sys


def add_parser(sub) -> None:
    """Add the `serve` subcommand to the `quietframe` command's subparsers."""
    serve = sub.add_parser("serve", help="run the denoising server with the bundled model")
    add_arguments(serve)
    serve.set_defaults(func=serve_command)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=8000)
    parser.add_argument("--model", help="default model for 'auto' (name); env QUIETFRAME_*")
    parser.add_argument("--models-dir", help="extra folder of .onnx models")
    parser.add_argument("--workers", type=int, help="frames processed at once")
    parser.add_argument("--threads", type=int, help="onnxruntime threads per model")
    parser.add_argument("--state-dir", help="durable sessions: write state here after each frame")
    parser.add_argument("--log-level", help="debug, info, warning, error")


def serve_command(args: argparse.Namespace) -> int:
    try:
        from quietframe.service.main import run
        from quietframe.service.settings import Settings
    except ImportError as exc:
        print(f"quietframe: error: serving needs the serve extra ({exc})", file=sys.stderr)
        return 1
    overrides = {
        "default_model": args.model,
        "models_dir": args.models_dir,
        "workers": args.workers,
        "threads": args.threads,
        "state_dir": args.state_dir,
        "log_level": args.log_level,
    }
    settings = Settings(**{k: v for k, v in overrides.items() if v is not None})
    run(args.host, args.port, settings)
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="quietframe serve", description=__doc__.splitlines()[0])
    add_arguments(parser)
    return serve_command(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
