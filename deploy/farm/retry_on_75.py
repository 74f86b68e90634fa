#!/usr/bin/env python3
"""Run a farm task's command; rerun it in place when it exits 75, with growing waits, a bounded
number of times; end the task at once on any other failure, saying what to fix.

    python3 retry_on_75.py [--attempts 5] [--first-wait 30] [--max-wait 300] -- \\
        quietframe denoise --server http://denoise:8000 ... --strict

Why: neither Flamenco nor Deadline tells one non-zero exit from another. For `quietframe
denoise`, 75 means "try again later" (the server was unavailable or busy after the client's own
retries, or the shot's first frame is not rendered yet) while 2 (configuration: flags, server
URL, token, model) and 3 (input: missing, truncated or changed frames, files in the way) will
fail the same way on every rerun. Left to the farm, a server restart fails tasks like a wrong
flag does: each failure counts against the task's and the worker's error limits (Flamenco
blocklists a worker for a job after `blocklist_threshold` failures; Deadline marks workers bad
and fails the job after its error limits), so a few minutes of outage can fail a whole job.
This wrapper absorbs 75 where it happens (a rerun resumes: finished frames are not redone) and
lets 2 and 3 reach the farm at once, as failures. What the farm then does with them is its own
policy (docs/farm.md, "Exit codes on a farm").

Exit status: the command's own (0 done; 75 when it still exits 75 after the last attempt; 2, 3,
130, 143 and any other code at once). A command killed by a signal exits as a shell reports it
(128 + the signal). Interrupted itself (SIGTERM, SIGINT: the farm cancelled the task), the
wrapper passes the signal on to the command and exits with the command's status; on Linux the
command is also stopped (SIGTERM) when the wrapper is killed outright (Flamenco's Worker kills
a cancelled task's process with SIGKILL), so no orphaned run goes on sending frames.

Standard library only, Python >= 3.8: it runs wherever the farm's Python does.
"""

from __future__ import annotations

import random
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Sequence

RETRY = 75  # EX_TEMPFAIL (sysexits.h): the quietframe CLI's "server unavailable or busy"
NOT_RETRIED = {
    2: "a configuration error (flags, server URL, token, model or option): fix the job's "
       "settings; rerunning cannot help",
    3: "an input error (missing, truncated or changed frames, or files in the way of the "
       "outputs): fix the render or the output folder; rerunning cannot help",
    130: "interrupted (SIGINT): the rerun resumes",
    143: "interrupted (SIGTERM): the rerun resumes",
}
JITTER = 0.2  # each wait is +-20%, so the chunks a restart failed together do not return together
USAGE = ("usage: retry_on_75.py [--attempts N] [--first-wait SECONDS] [--max-wait SECONDS] "
         "-- COMMAND [ARGS...]")


class Stopped(Exception):
    """The wrapper was asked to stop (SIGTERM / SIGINT) while no command was running."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


def say(text: str) -> None:
    sys.stderr.write(f"retry_on_75: {text}\n")
    sys.stderr.flush()


def refuse(problem: str) -> SystemExit:
    """Exit 2 (a job to fix, like the client's configuration errors), saying what is wrong."""
    sys.stderr.write(f"{USAGE}\n")
    say(problem)
    return SystemExit(2)


def parse(argv: Sequence[str]) -> tuple[int, float, float, list[str]]:
    """(attempts, first wait, longest wait, command); exit 2 with the usage when wrong. The
    command follows `--`, so none of its flags is taken for the wrapper's."""
    if "--" not in argv:
        raise refuse("the command goes after `--`")
    split = list(argv).index("--")
    options, command = list(argv[:split]), list(argv[split + 1:])
    values = {"--attempts": 5.0, "--first-wait": 30.0, "--max-wait": 300.0}
    while options:
        name = options.pop(0)
        if name not in values or not options:
            raise refuse(f"unknown option, or no value after it: {name}")
        try:
            values[name] = float(options.pop(0))
        except ValueError:
            raise refuse(f"{name} takes a number") from None
    attempts = values["--attempts"]
    if not command:
        raise refuse("no command after `--`")
    if attempts < 1 or attempts != int(attempts):
        raise refuse("--attempts takes a whole number >= 1 (1: no retry)")
    if values["--first-wait"] < 0 or values["--max-wait"] < values["--first-wait"]:
        raise refuse("the waits are >= 0 seconds and --max-wait >= --first-wait")
    return int(attempts), values["--first-wait"], values["--max-wait"], command


def wait_before(attempt: int, first: float, longest: float) -> float:
    """Seconds to wait before rerun number `attempt` (2, 3, ...): doubling from `first`,
    jittered, never past `longest`."""
    base = first * 2 ** (attempt - 2)
    return min(longest, base * random.uniform(1 - JITTER, 1 + JITTER))


def stop_with_parent() -> Callable[[], None] | None:
    """On Linux, a preexec_fn that has the kernel send the command SIGTERM when this wrapper
    dies, even by SIGKILL (prctl PR_SET_PDEATHSIG); elsewhere None (signals are passed on, a
    SIGKILL of the wrapper leaves the command running)."""
    if not sys.platform.startswith("linux"):
        return None
    import ctypes
    import os

    try:
        prctl = ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        return None
    parent = os.getpid()

    def arrange() -> None:
        prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
        if os.getppid() != parent:  # the wrapper died before the line above took effect
            os.kill(os.getpid(), signal.SIGTERM)

    return arrange


class Runner:
    """Runs the command, passing on the signals that ask the wrapper to stop."""

    def __init__(self) -> None:
        self.child: subprocess.Popen | None = None
        self.stopped: int | None = None
        self.unstartable = False  # the command could not be started at all (said already)
        for signum in (signal.SIGTERM, signal.SIGINT):
            signal.signal(signum, self.on_signal)

    def on_signal(self, signum: int, _frame) -> None:
        self.stopped = signum
        if self.child is not None and self.child.poll() is None:
            self.child.send_signal(signum)  # the command stops in its own way (quietframe: 143)
        else:
            raise Stopped(signum)

    def run(self, command: list[str]) -> int:
        try:
            self.child = subprocess.Popen(command, preexec_fn=stop_with_parent())
        except OSError as error:  # not found, not executable: a job to fix
            say(f"cannot run {command[0]!r}: {error.strerror or error}; fix the job's "
                f"command (exit 2, not retried)")
            self.unstartable = True
            return 2
        try:
            code = self.child.wait()
        finally:
            self.child = None
        return 128 - code if code < 0 else code  # killed by a signal: as a shell says it


def main(argv: Sequence[str] | None = None) -> int:
    attempts, first, longest, command = parse(sys.argv[1:] if argv is None else argv)
    runner = Runner()
    started = time.monotonic()
    try:
        for attempt in range(1, attempts + 1):
            if attempt > 1:
                pause = wait_before(attempt, first, longest)
                say(f"exit {RETRY} (server unavailable or busy, or the shot's first frame not "
                    f"rendered yet): run {attempt} of {attempts} in {pause:.0f} s")
                time.sleep(pause)
            code = runner.run(command)
            if code != RETRY or runner.stopped is not None:
                break
        else:
            say(f"still exit {RETRY} after {attempts} run(s) over "
                f"{time.monotonic() - started:.0f} s: the task fails as 'try later' (the "
                f"farm requeues it by its own rules)")
            return RETRY
    except Stopped as stop:
        say(f"stopped by signal {stop.signum} while waiting to rerun")
        return 128 + stop.signum
    if runner.unstartable:
        return code
    if code in NOT_RETRIED:
        say(f"exit {code}: {NOT_RETRIED[code]}; not retried")
    elif code not in (0, RETRY):
        say(f"exit {code}: not retried (only {RETRY} is)")
    return code


if __name__ == "__main__":
    sys.exit(main())
