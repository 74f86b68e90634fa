"""`quietframe` command: denoise | models, and the commands other parts of quietframe register
under the `quietframe.commands` entry point (`serve`, from quietframe.service.cli).

`denoise` and `models --server` need only the client extra; listing the models installed here
(`models` without --server) needs the serve extra, and imports the runtime only then.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import json
import os
import sys
import time
from collections.abc import Iterator
from importlib.metadata import PackageNotFoundError, entry_points, version

from quietframe.client import outcome
from quietframe.client.api import Client, QuietframeError, RetryPolicy
from quietframe.client.choice_text import describe_choice
from quietframe.client.cli_args import add_denoise_arguments, flag_problem, session_options
from quietframe.client.core import base_url
from quietframe.client.frame_source import SequenceError, parse_frame_range
from quietframe.client.interrupt import Interrupted, stop_on_signals
from quietframe.client.job import Job, file_view_layers
from quietframe.client.model_table import model_table
from quietframe.client.output_records import OutputConflict, UnsafePath
from quietframe.client.preflight import (
    check_frames,
    check_mapping,
    check_model,
    check_view_layers,
    format_numbers,
    model_names,
)
from quietframe.client.report import Reporter
from quietframe.client.sequence import (
    job_settings,
    refuse_conflicts,
    run_sequence,
    warm_positions,
)
from quietframe.client.session_fields import AUTO
from quietframe.client.settings import client_settings

COMMANDS_GROUP = "quietframe.commands"
RENDERERS = ("cycles", "mitsuba")  # the renderers the model cards hold tables for
DEFAULT_RENDERER = "cycles"
EXIT_CODES_HELP = """exit codes: 0 done; 1 unexpected failure; 2 configuration (flags, server URL,
token, model, channel mapping, changed flags); 3 input (unreadable or truncated frames, size
changes, missing passes, files in the way); 75 server unavailable or busy (retry later);
130 / 143 interrupted by Ctrl-C / SIGTERM (run again to resume)."""


def _layers(job, layer: str | None, options: dict) -> tuple[str | None, ...]:
    """The view layers to denoise, one session each: `all` reads them from the first frame."""
    if layer != "all":
        return (layer,)
    if options["channels"]:
        raise ValueError(
            "--channels names whole channels, the same for every session; with --layer all "
            "leave it out (each view layer's passes are found by name) or run one --layer each"
        )
    return file_view_layers(job.files[job.first_written]) or (None,)


_NOT_WRITABLE = frozenset({errno.EACCES, errno.EPERM, errno.EROFS, errno.ENOTDIR, errno.EISDIR})


class _Stop(Exception):
    """A failure decided before or during the run: its exit code, message and advice."""

    def __init__(self, code: int, message: str, advice: str = "") -> None:
        super().__init__(message)
        self.code, self.message, self.advice = code, message, advice


def _plan(args: argparse.Namespace):
    """(server URL, session options, job, layers) from the command line; _Stop otherwise."""
    if not args.server:
        raise _Stop(outcome.CONFIG, "no server", "pass --server URL (or set QUIETFRAME_SERVER)")
    try:
        server = base_url(args.server)
        options = session_options(args)
        frames = parse_frame_range(args.frames) if args.frames else None
    except ValueError as exc:
        raise _Stop(outcome.CONFIG, str(exc)) from exc
    problem = flag_problem(args, options)
    if problem is not None:
        raise _Stop(outcome.CONFIG, *problem)
    try:
        job = Job.plan(args.input, args.out, frames, args.pre_roll, tuple(args.cut or ()),
                       create_out=not args.dry_run, post_roll=args.post_roll)
    except SequenceError as exc:
        raise _Stop(outcome.INPUT, str(exc)) from exc
    except ValueError as exc:
        raise _Stop(outcome.CONFIG, str(exc)) from exc
    try:
        layers = _layers(job, args.layer, options)
    except SequenceError as exc:
        raise _Stop(outcome.INPUT, str(exc)) from exc
    except ValueError as exc:
        raise _Stop(outcome.CONFIG, str(exc)) from exc
    return server, options, job, layers


def _reporter(args: argparse.Namespace, total: int, done: int):
    if args.json:
        mode = "json"
    elif args.quiet:
        mode = "quiet"
    elif sys.stderr.isatty() and sys.stdout.isatty():
        mode = "bar"
    else:
        mode = "lines"
    return Reporter(mode, total, done)


def _preflight(args, job, reporter):
    """Every frame's header before the first upload (the preflight.Report); _Stop for what
    would fail later."""
    report = check_frames(job.files, job.missing, pre_roll_missing=job.pre_roll_missing,
                          post_roll_missing=job.post_roll_missing)
    for warning in report.warnings:
        if args.strict:
            raise _Stop(outcome.INPUT, warning, "render the missing frames, or leave out "
                        "--strict to denoise across the gap")
        reporter.warn(warning)
    if report.errors:
        raise _Stop(outcome.INPUT, "pre-flight found problems in the frames:\n  "
                    + "\n  ".join(report.errors), "fix or re-render those frames first")
    size = f"{report.size[0]}x{report.size[1]}" if report.size else "?"
    layers = f", view layers {', '.join(report.layers)}" if report.layers else ""
    reporter.event("preflight", f"quietframe: {report.frames} frame(s) checked: {size}"
                   f"{layers}, {report.channels} channels each", frames=report.frames,
                   size=report.size, layers=report.layers, channels=report.channels,
                   warnings=report.warnings)
    return report


def _denoise(args: argparse.Namespace) -> int:
    try:
        server, options, job, layers = _plan(args)
    except _Stop as stop:
        Reporter("json" if args.json else "quiet", 0).error(stop.message, stop.advice, stop.code)
        return stop.code
    total = len(job.written)
    reporter = _reporter(args, total, 0)
    try:
        job = _shot_starts_rendered(args, job, layers, reporter)
    except _Stop as stop:
        reporter.error(stop.message, stop.advice, stop.code)
        return stop.code
    position = {"at": job.first_written}
    with stop_on_signals():
        try:
            report = _preflight(args, job, reporter)
            if args.dry_run:
                _dry_run(args, server, options, job, layers, report, reporter)
                reporter.summary(0, job.out_dir)
                return outcome.OK
            written = _run(args, server, options, job, layers, reporter, position)
        except _Stop as stop:
            reporter.error(stop.message, stop.advice, stop.code)
            return stop.code
        except Interrupted as stop:
            return _interrupted(reporter, job, position["at"], stop.signal_name)
        except KeyboardInterrupt:
            return _interrupted(reporter, job, position["at"], "SIGINT")
    reporter.summary(written, job.out_dir)
    return outcome.OK


def _shot_starts_rendered(args, job, layers, reporter):
    """The job, once the first frame of every shot it sends whose model is not recorded yet
    is rendered (auto decides a shot from that frame only): waited for up to
    --wait-for-shot-start seconds, re-reading the input; _Stop (75: retry later) after."""
    if args.model != AUTO:
        return job
    deadline = time.monotonic() + (0 if args.dry_run else args.wait_for_shot_start)
    while missing := job.undecided_starts(layers):
        if time.monotonic() >= deadline:
            shots = ", ".join(str(n) for n in missing)
            raise _Stop(outcome.UNAVAILABLE, f"the first frame of the shot from frame {shots} "
                        "is not rendered yet, and --model auto decides a shot's model from it",
                        "retry once it is rendered (the farm's retry of exit 75), wait for it "
                        "with --wait-for-shot-start SECONDS, or name the model with --model")
        reporter.note(f"waiting for frame {missing[0]}, the first of its shot")
        time.sleep(min(5.0, max(0.0, deadline - time.monotonic())))
        job = _plan(args)[2]  # the input read again
    return job


def _interrupted(reporter, job, at: int, signal_name: str) -> int:
    name = job.files[min(at, len(job.files) - 1)].name
    reporter.error(f"interrupted ({signal_name}) at {name}",
                   "finished frames are kept: run the same command again to resume",
                   outcome.INTERRUPTED[signal_name])
    return outcome.INTERRUPTED[signal_name]


def _dry_run(args, server, options, job, layers, report, reporter) -> None:
    """What the run checks before its first frame is denoised, without sending one: the files
    in the way, the server (reachable, token), the model and its options, the view layers, the
    channel mapping against the first frame, the session's settings (a session is opened and
    deleted).
    _Stop for the first that fails, with the run's exit code and words (the run's failures
    name the first frame to write, so these do too)."""
    settings = job_settings(args.model, args.precision, args.compression, layers, **options)
    at = job.files[job.first_written].name
    mapping = bool(options["channels"] or args.layer)
    if not args.force:
        try:
            refuse_conflicts(job, settings)
        except OutputConflict as exc:
            raise _conflict_stop(exc, job, settings) from exc
    with _client(args, server, reporter) as client:
        try:
            listing = client.models()
        except QuietframeError as exc:
            raise _server_stop(exc, at, server, mapping, report.layers) from exc
        failure = (check_model(listing, args.model, options["model_options"], server)
                   or check_view_layers(report, args.layer, bool(options["channels"]), server)
                   or check_mapping(report, options["channels"], server))
        if failure is not None:
            raise _Stop(failure.code, f"at {at}: {failure.message}", failure.advice)
        try:  # the server judges the settings as it will the run's sessions (a newer server
            for layer in layers:  # may take values this client does not know): open, delete
                created = client.create_session(job.width, job.height, args.model,
                                                precision=args.precision,
                                                compression=args.compression, layer=layer,
                                                **options)
                client.delete_session(created["id"])
        except QuietframeError as exc:
            raise _server_stop(exc, at, server, mapping, report.layers) from exc
    pending = job.first_pending(settings) - job.first_written
    todo = len(job.written) - pending
    redo = f"; --force redoes {_force_redoes(job, settings)}" if args.force and todo else ""
    sent, words = _frames_sent(job, settings, args.warmup, bool(options.get("lookahead")))
    reporter.event("dry-run", f"quietframe: dry run: {server} answers ({len(model_names(listing))} "
                   f"models), --model {args.model} accepted; {todo} of {len(job.written)} "
                   f"frame(s) to denoise{redo}; {words}; no frame was sent", server=server,
                   model=args.model, to_denoise=todo, total=len(job.written),
                   lookahead=options.get("lookahead") or 0, **sent)


def _frames_sent(job, settings: dict, warmup: int, lookahead: bool) -> tuple[dict, str]:
    """The frames a run would send in a new session, by role, and that in words: the pre-roll
    or, resuming, the warm-up (not written), the frames to write, the post-roll (look-ahead
    only; not written)."""
    pending = job.first_pending(settings)
    warm = warm_positions(job, pending, warmup if pending > job.first_written else
                          job.first_written) if pending < job.end_written else []
    todo = range(pending, job.end_written)
    sent = {"pre_roll": [job.indices[i] for i in warm],
            "frames": [job.indices[i] for i in todo],
            "post_roll": job.indices[job.end_written:] if lookahead and todo else []}
    said = [f"{format_numbers(numbers)}{role}" for numbers, role in (
        (sent["pre_roll"], " (pre-roll, not written)"), (sent["frames"], ""),
        (sent["post_roll"], " (post-roll, not written)")) if numbers]
    return sent, "would send frame(s) " + ", ".join(said) if said else "would send nothing"


def _client(args, server, reporter):
    """The run's client: its token, timeout and retries, each retry said as it happens."""
    def on_retry(r) -> None:
        reporter.warn_retry(f"server {server}: {r.describe()}")

    token = args.token or client_settings().token
    return Client(server, token=token, timeout_s=args.timeout,
                  retry=RetryPolicy(retries=args.retries), on_retry=on_retry)


def _server_stop(exc, at: str, server: str, mapping: bool, view_layers) -> _Stop:
    """A request that failed for good, as the _Stop the run ends with (at frame `at`)."""
    failure = outcome.server_failure(exc.status, exc.code, exc.detail, server, mapping,
                                     tuple(view_layers))
    return _Stop(failure.code, f"at {at}: {failure.message}", failure.advice)


def _redone_positions(job, settings: dict) -> list[int]:
    """Positions whose existing output --force writes again: every one from the first frame
    that is not this job's on (each later frame's history runs through it)."""
    return [i for i in range(job.first_pending(settings), job.end_written)
            if os.path.lexists(job.output(i))]


def _force_redoes(job, settings: dict) -> str:
    redone = [job.indices[i] for i in _redone_positions(job, settings)]
    return f"{len(redone)} output(s), frame(s) {format_numbers(redone)}" if redone else (
        "no existing output")


def _conflict_stop(exc, job, settings: dict) -> _Stop:
    """A refusal of files in the way, with what --force would redo: not only the refused
    outputs but every one after the first, whose history runs through it."""
    return _Stop(outcome.CONFIG if exc.changed else outcome.INPUT, str(exc),
                 f"--force redoes {_force_redoes(job, settings)} (from the first frame not "
                 "done to the end of the range: each frame's history runs through the ones "
                 "before it)")


def _run(args, server, options, job, layers, reporter, position) -> int:
    """The sequence itself; returns the frames written. _Stop for every failure."""
    settings = job_settings(args.model, args.precision, args.compression, layers, **options)
    done = job.first_pending(settings) - job.first_written  # --force keeps these too
    reporter.resume(done)
    if done and args.force:
        reporter.note(f"--force: redoing {_force_redoes(job, settings)}; the {done} frame(s) "
                      f"before them in {job.out_dir} are this job's and kept")
    elif done:
        reporter.note(f"resuming: {done} of {len(job.written)} frame(s) already in {job.out_dir}")
    if len(layers) > 1:
        reporter.note(f"view layers {', '.join(map(str, layers))}: one session each, one file")
    written = {"count": 0}

    with _client(args, server, reporter) as client, \
            _sessions_deleted_on_config_stop(args, server, reporter) as opened:
        watcher = _ShotWatcher(args, client, reporter, job)

        def progress(p) -> None:
            # after the frame just sent (or finished): a written one may be an earlier frame
            position["at"] = (p.position if p.sent is None else p.sent) + 1
            index = job.indices[p.position]
            if p.result is None:
                report = (reporter.post_roll if p.post_roll else
                          reporter.held if p.held else reporter.warm)
                report(index, p.path.name)
                return
            watcher.seen(p)
            reporter.frame(index, p.path.name, p.result, finished=p.sent is None,
                           reply_to=None if p.sent is None else job.indices[p.sent])
            written["count"] += 1

        try:
            run_options = dict(
                model=args.model, precision=args.precision, warmup=args.warmup,
                compression=args.compression, on_progress=progress, layers=layers,
                force=args.force, pre_roll=args.pre_roll, on_warning=reporter.warn,
                on_session=opened.append, **options,
            )
            run_sequence(client, job, server, **run_options)
        except OutputConflict as exc:
            raise _conflict_stop(exc, job, settings) from exc
        except QuietframeError as exc:
            at = job.files[min(position["at"], len(job.files) - 1)].name
            view_layers = tuple(layer for layer in layers if layer) or _file_layers(job)
            raise _server_stop(exc, at, server, bool(options["channels"] or args.layer),
                               view_layers) from exc
        except UnsafePath as exc:
            raise _Stop(outcome.INPUT, str(exc), "remove it, then run the same command again "
                        "to resume") from exc
        except SequenceError as exc:
            raise _Stop(outcome.INPUT, str(exc), "fix that frame, then run the same command "
                        "again to resume") from exc
        except OSError as exc:
            if exc.errno in _NOT_WRITABLE:  # the folder, not the run: running again cannot help
                raise _Stop(outcome.CONFIG, f"cannot write into --out: {exc}", "make --out a "
                            "folder this user can write, then run the same command") from exc
            raise _Stop(outcome.FAILURE, f"{exc}", "run the same command again to resume") from exc
    return written["count"]


_DELETE_TIMEOUT_S = 5.0  # a delete's request; with one retry a stopped run ends within ~11 s


@contextlib.contextmanager
def _sessions_deleted_on_config_stop(args, server: str, reporter) -> Iterator[list[str]]:
    """The run's sessions (the list filled as they open), deleted when the run ends on a
    configuration failure (exit 2: --out cannot be written, flags the server refuses mid-run):
    the rerun needs another --out or other flags, which a person fixes, so the sessions would
    only hold the server's memory until their idle time ends. Every other stop keeps them: the
    rerun after 75, 130/143, 1, or 3 (its frame fixed) continues a session where it stopped."""
    opened: list[str] = []
    try:
        yield opened
    except _Stop as stop:
        if stop.code == outcome.CONFIG and opened:
            _delete_sessions(args, server, opened, reporter)
        raise


def _delete_sessions(args, server: str, session_ids: list[str], reporter) -> None:
    """Best effort, bounded: one retry, short timeouts; one that stays is a warning (the
    server ends it after its idle time)."""
    token = args.token or client_settings().token
    retry = RetryPolicy(retries=1, backoff_s=0.5, max_backoff_s=1.0)
    with Client(server, token=token, timeout_s=_DELETE_TIMEOUT_S, retry=retry) as client:
        for session_id in dict.fromkeys(session_ids):
            try:
                client.delete_session(session_id)
            except QuietframeError as exc:
                reporter.warn(f"session {session_id} on {server} was not deleted ({exc}); the "
                              "server ends it after its idle time")


def _file_layers(job) -> tuple[str, ...]:
    try:
        return file_view_layers(job.files[job.first_written])
    except SequenceError:
        return ()


class _ShotWatcher:
    """Says which model runs per shot (model=auto: the server's choice, in plain words) and
    where the history restarts."""

    def __init__(self, args, client, reporter, job) -> None:
        self.args, self.client, self.reporter, self.job = args, client, reporter, job
        self.shown: str | None = None

    def seen(self, p) -> None:
        result, index = p.result, self.job.indices[p.position]
        if result.reset == "gap":
            previous = self.job.indices[p.position - 1] if p.position else None
            gap = list(range(previous + 1, index)) if previous is not None else []
            self.reporter.note(f"frame {index}: history restarted after missing frame(s) "
                               f"{format_numbers(gap) if gap else '(before this run)'}")
        new_shot = result.reset in ("first-frame", "cut") or p.resumed or self.shown is None
        if not new_shot:
            return
        if self.args.model != "auto":
            text = f"{result.model} (--model {self.args.model})"
            choice = None
        else:
            try:
                choice = self.client.session(p.session).get("choice") if p.session else None
            except Exception:  # the choice is said for the reader; never fails a run
                choice = None
            measured = self.reporter.measured_ms(choice["model"]) if choice else None
            text = describe_choice(choice, measured_ms=measured) if choice else result.model
        if text != self.shown or result.reset == "cut":
            start = self.job.shot_of(p.position)  # the shot by its cut, not this run's frame
            first = start if start is not None else min(self.job.sequence, default=index)
            here = "" if first == index else f" (this run from frame {index})"
            self.reporter.event("shot", f"quietframe: shot from frame {first}{here}: {text}",
                                frame=index,
                                shot_start=start, model=result.model, choice=choice, text=text)
            self.shown = text


def _models(args: argparse.Namespace) -> int:
    if args.server:
        token = args.token or client_settings().token
        try:
            server = base_url(args.server)
            with Client(server, token=token, retry=_quick_retry()) as client:
                listing = client.models()
        except ValueError as exc:
            print(f"quietframe: error: {exc}", file=sys.stderr)
            return outcome.CONFIG
        except QuietframeError as exc:
            failure = outcome.server_failure(exc.status, exc.code, exc.detail, server, False)
            print(f"quietframe: error: {failure.message}\nquietframe: {failure.advice}",
                  file=sys.stderr)
            return failure.code
    else:
        try:
            listing = _local_listing()
        except ImportError as exc:
            print(
                f"quietframe: error: listing local models needs the serve extra ({exc}); "
                "pass --server URL to ask a server",
                file=sys.stderr,
            )
            return outcome.CONFIG
    if args.json:
        print(json.dumps(listing, indent=1))
    else:
        print(model_table(listing["models"], listing["default"], args.renderer))
    return outcome.OK


def _local_listing() -> dict:
    """The models this machine would serve, as GET /v1/models lists them; the server's
    settings QUIETFRAME_MODELS_DIR and QUIETFRAME_DEFAULT_MODEL apply here too."""
    # onnxruntime and the ops library: the serve extra, which a client install lacks
    from quietframe.runtime.loaded_models import LoadedModels

    settings = client_settings()
    models = LoadedModels.load(settings.models_dir, threads=1)
    wanted = settings.default_model
    return models.listing(models.find(wanted) if wanted else None)


def _quick_retry():
    return RetryPolicy(retries=2, backoff_s=0.5, max_backoff_s=2.0)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="quietframe",
        description=__doc__.splitlines()[0],
        epilog=EXIT_CODES_HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
        allow_abbrev=False,
    )
    parser.add_argument("--version", action="version", version=f"quietframe {_version()}")
    sub = parser.add_subparsers(dest="command", required=True)

    denoise = sub.add_parser("denoise", help="denoise a folder or glob of EXR frames",
                             allow_abbrev=False)
    add_denoise_arguments(denoise)
    denoise.set_defaults(func=_denoise)

    models = sub.add_parser("models", help="list models (installed here, or on --server)",
                            allow_abbrev=False)
    models.add_argument("--server", default=client_settings().server)
    models.add_argument("--token")
    models.add_argument(
        "--renderer",
        choices=RENDERERS,
        default=DEFAULT_RENDERER,
        help="whose frames the tables were measured on (default cycles: farm frames are "
        "Blender's, and auto reads the Cycles tables for them; mitsuba: the tables auto reads "
        "for any other renderer)",
    )
    models.add_argument("--json", action="store_true", help="the listing as JSON")
    models.set_defaults(func=_models)
    for command in entry_points(group=COMMANDS_GROUP):  # e.g. `serve`, from quietframe.service
        command.load()(sub)
    for command_parser in sub.choices.values():  # registered ones too: `--pre-rol` is no flag
        command_parser.allow_abbrev = False
    return parser


def _version() -> str:
    try:
        return version("quietframe")
    except PackageNotFoundError:
        return "unknown (not installed)"


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except BrokenPipeError:  # `quietframe models | head`: the reader left, nothing is wrong
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())  # so the interpreter's final flush is quiet too
        return 0


if __name__ == "__main__":
    sys.exit(main())
