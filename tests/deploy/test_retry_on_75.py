"""deploy/farm/retry_on_75.py, the farm wrapper around `quietframe denoise`: exit 75 is rerun in
place with growing waits a bounded number of times; 2 and 3 (and anything else) end it at once
with the command's code and what to fix; a signal that stops the wrapper stops the command and
is not followed by a rerun. Run as the farms run it: a subprocess around fake commands that exit
with given codes, and around the real client."""

from __future__ import annotations

import importlib.util
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import shot

WRAPPER = Path(__file__).resolve().parents[2] / "deploy" / "farm" / "retry_on_75.py"
QUIETFRAME = [sys.executable, "-m", "quietframe.client.cli"]
FAST = ["--first-wait", "0.05", "--max-wait", "0.2"]

# A command that exits with the next code of CODES (the last one repeats), logging each run; on
# SIGTERM it logs "term" and exits with ON_TERM.
FAKE = """
import signal, sys, time
from pathlib import Path
codes, log = sys.argv[1].split(","), Path(sys.argv[2])
on_term = int(sys.argv[3]) if len(sys.argv) > 3 else 143
def term(*_):
    with log.open("a") as f:
        f.write("term\\n")
    sys.exit(on_term)
signal.signal(signal.SIGTERM, term)
runs = log.read_text().count("run") if log.exists() else 0
with log.open("a") as f:
    f.write("run\\n")
code = codes[min(runs, len(codes) - 1)]
if code == "sleep":
    time.sleep(30)
    code = "0"
sys.exit(int(code))
"""


@pytest.fixture()
def fake(tmp_path: Path):
    script = tmp_path / "fake_command.py"
    script.write_text(FAKE)
    log = tmp_path / "runs.log"

    def command(codes: str, *extra: str) -> list[str]:
        return [sys.executable, str(script), codes, str(log), *extra]

    command.log = log  # type: ignore[attr-defined]
    return command


def wrap(*args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(WRAPPER), *args], capture_output=True, text=True,
                          timeout=timeout)


def runs(log: Path) -> int:
    return log.read_text().count("run") if log.exists() else 0


def test_exit_75_is_rerun_after_growing_waits_until_the_command_succeeds(fake):
    started = time.monotonic()
    result = wrap("--attempts", "5", *FAST, "--", *fake("75,75,0"))
    assert result.returncode == 0, result.stderr
    assert runs(fake.log) == 3
    assert "run 2 of 5" in result.stderr and "run 3 of 5" in result.stderr
    assert time.monotonic() - started >= 0.8 * (0.05 + 0.1)  # the waits double: 0.05, 0.1


def test_exit_75_gives_up_after_the_attempts_and_exits_75(fake):
    result = wrap("--attempts", "3", *FAST, "--", *fake("75"))
    assert result.returncode == 75
    assert runs(fake.log) == 3
    assert "still exit 75 after 3 run(s)" in result.stderr


@pytest.mark.parametrize(("code", "words"), [(2, "configuration error"), (3, "input error")])
def test_configuration_and_input_errors_end_the_task_at_once(fake, code, words):
    result = wrap("--attempts", "5", *FAST, "--", *fake(f"{code},0"))
    assert result.returncode == code
    assert runs(fake.log) == 1  # a second run would have succeeded: it was never made
    assert words in result.stderr and "not retried" in result.stderr
    assert "run 2" not in result.stderr


def test_other_codes_pass_through_unretried(fake):
    result = wrap(*FAST, "--", *fake("1,0"))
    assert result.returncode == 1 and runs(fake.log) == 1
    assert "only 75 is" in result.stderr
    done = wrap(*FAST, "--", *fake("0"))
    assert done.returncode == 0 and done.stderr == "" and runs(fake.log) == 2


def test_a_command_killed_by_a_signal_exits_as_a_shell_says_it(tmp_path):
    result = wrap(*FAST, "--", sys.executable, "-c",
                  "import os, signal; os.kill(os.getpid(), signal.SIGKILL)")
    assert result.returncode == 128 + signal.SIGKILL


@pytest.mark.parametrize("args", [
    ["--"],  # no command
    ["quietframe", "denoise"],  # no --
    ["--attempts", "0", "--", "true"],
    ["--attempts", "1.5", "--", "true"],
    ["--first-wait", "10", "--max-wait", "5", "--", "true"],
    ["--retries", "3", "--", "true"],
    ["--attempts", "--", "true"],
    ["--", "/nonexistent/quietframe", "denoise"],
])
def test_a_wrong_invocation_is_a_configuration_error(args):
    result = wrap(*args)
    assert result.returncode == 2, result.stderr
    assert "retry_on_75:" in result.stderr


def start(*args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, str(WRAPPER), *args], stderr=subprocess.PIPE,
                            text=True)


def wait_for(condition, seconds: float = 10) -> None:
    deadline = time.monotonic() + seconds
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.02)


def test_sigterm_stops_the_command_and_is_not_followed_by_a_rerun(fake):
    # The command answers SIGTERM with 75 (as a client stopped mid-request may): a cancelled
    # task must still not be rerun.
    wrapper = start("--attempts", "5", *FAST, "--", *fake("sleep", "75"))
    wait_for(lambda: runs(fake.log) == 1)
    wrapper.send_signal(signal.SIGTERM)
    assert wrapper.wait(timeout=10) == 75
    assert fake.log.read_text().splitlines() == ["run", "term"]


def test_sigterm_while_waiting_to_rerun_ends_at_once(fake):
    wrapper = start("--attempts", "5", "--first-wait", "30", "--max-wait", "60", "--",
                    *fake("75"))
    wait_for(lambda: runs(fake.log) == 1)
    time.sleep(0.3)  # into the wait
    wrapper.send_signal(signal.SIGTERM)
    assert wrapper.wait(timeout=5) == 128 + signal.SIGTERM
    assert runs(fake.log) == 1


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def test_a_killed_wrapper_takes_its_command_with_it(fake):
    """Flamenco's Worker kills a cancelled task's process with SIGKILL: the command must not
    go on sending frames on its own."""
    wrapper = start(*FAST, "--", *fake("sleep"))
    wait_for(lambda: runs(fake.log) == 1)
    wrapper.kill()
    wrapper.wait(timeout=5)
    wait_for(lambda: "term" in fake.log.read_text(), seconds=5)


def test_waits_double_with_jitter_and_stay_under_the_longest():
    spec = importlib.util.spec_from_file_location("retry_on_75", WRAPPER)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    for _ in range(200):
        assert 24 <= module.wait_before(2, 30, 300) <= 36
        assert 48 <= module.wait_before(3, 30, 300) <= 72
        assert module.wait_before(12, 30, 300) <= 300


def closed_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def test_the_real_client_unreachable_server_is_retried_and_a_bad_flag_is_not(tmp_path):
    (tmp_path / "render").mkdir()
    (tmp_path / "render" / "sh010.1001.exr").write_bytes(shot(1, "blender")[0])
    denoise = [*QUIETFRAME, "denoise", "--server", f"http://127.0.0.1:{closed_port()}",
               str(tmp_path / "render" / "sh010.####.exr"), "--out", str(tmp_path / "out"),
               "--retries", "0", "--strict"]
    down = wrap("--attempts", "2", *FAST, "--", *denoise, timeout=120)
    assert down.returncode == 75, down.stderr
    assert down.stderr.count("run 2 of 2") == 1 and "still exit 75 after 2" in down.stderr
    bad = wrap("--attempts", "2", *FAST, "--", *denoise, "--timeout", "0", timeout=120)
    assert bad.returncode == 2, bad.stderr
    assert "configuration error" in bad.stderr and "run 2" not in bad.stderr
