"""Farm round 3: `--dry-run` refuses every flag the run refuses, with the run's exit
code and words, and leaves no trace (no --out folder, no open session); flags that cannot work
or would be ignored are configuration errors (exit 2) before anything is sent."""

from __future__ import annotations

import re

import httpx
import pytest
from test_cli_farm_round2 import denoise, error_lines, run_and_dry_run, write_shot

from quietframe.client.cli import main


def open_sessions(server) -> float:
    text = httpx.get(f"{server.url}/metrics").text
    return float(re.search(r"^quietframe_sessions (\S+)", text, re.M).group(1))


@pytest.mark.parametrize("flags, words", [
    (("--compression", "zipp"), "compression"),
    (("--channels", '{"albedo": "Nope"}'), "albedo='Nope'"),
    (("--channels", '{"albedo": ["Nope.R", "Nope.G", "Nope.B"]}'), "names channels"),
])
def test_dry_run_refuses_settings_as_the_run_does(tmp_path, live_server, capsys, flags, words):
    write_shot(tmp_path / "in", 2)
    args = denoise(live_server.url, tmp_path / "in", tmp_path / "out", *flags)
    (run_code, run_err), (dry_code, dry_err) = run_and_dry_run(capsys, args)
    assert run_code == dry_code == 2, (run_err, dry_err)
    assert words in dry_err
    # the dry run names the first frame as the run does; the run's message may add the frame's
    # index, so compare the refusal's own words
    assert [line.split(": ", 1)[-1] for line in error_lines(dry_err)] == \
        [line.split(": ", 1)[-1] for line in error_lines(run_err)]


def test_a_dry_run_leaves_no_trace(tmp_path, live_server, capsys):
    write_shot(tmp_path / "in", 2)
    before = open_sessions(live_server)
    out = tmp_path / "not" / "yet"
    assert main(denoise(live_server.url, tmp_path / "in", out, "--dry-run",
                        "--channels", '{"albedo": "ViewLayer.Denoising Albedo"}')) == 0, \
        capsys.readouterr().err
    assert not out.exists() and not (tmp_path / "not").exists()
    assert open_sessions(live_server) == before  # the session it opened is deleted


@pytest.mark.parametrize("flags, words", [
    (("--timeout", "0"), "--timeout"),
    (("--timeout", "nan"), "--timeout"),
    (("--retries", "-1"), "--retries"),
    (("--motion-scale", "1", "-1"), "--motion-scale"),
    (("--motion-scale", "1", "-1", "--channels", '{"albedo": "ViewLayer.Denoising Albedo"}'),
     "--motion-scale"),
    (("--model", "nbg-2l-3g", "--quality", "best"), "--quality"),
    (("--model", "nbg-2l-3g", "--latency-ms", "100"), "--latency-ms"),
    (("--pre-roll", "-1"), "--pre-roll"),
    (("--frames", "1-1000000000"), "at most 100000"),  # audit R4-25: refused, not built
    (("--wait-for-shot-start", "-1"), "--wait-for-shot-start"),
])
def test_flags_that_cannot_work_are_configuration_errors(tmp_path, capsys, flags, words):
    """Exit 2 before the server is asked (none listens at port 9: a flag checked later would
    exit 75, which a farm requeues forever)."""
    write_shot(tmp_path / "in", 1)
    args = ["denoise", "--server", "http://127.0.0.1:9", str(tmp_path / "in"), "--out",
            str(tmp_path / "out"), "--quiet", *flags]
    for dry in ((), ("--dry-run",)):
        assert main([*args, *dry]) == 2
        assert words in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_an_out_folder_that_cannot_be_written_is_a_configuration_error(tmp_path, live_server,
                                                                       capsys):
    """Audit R4-24: --out under a file was a traceback (exit 1); now exit 2 with the reason,
    before a session is opened, dry run or not."""
    write_shot(tmp_path / "in", 1)
    (tmp_path / "afile").write_text("x")
    before = open_sessions(live_server)
    for dry in ((), ("--dry-run",)):
        assert main([*denoise(live_server.url, tmp_path / "in", tmp_path / "afile" / "out"),
                     *dry]) == 2
        assert "is a file, not a folder" in capsys.readouterr().err
    assert open_sessions(live_server) == before
