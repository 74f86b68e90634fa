"""`quietframe denoise --dry-run` refuses what the run refuses (a model or option, view layers,
the server and its token, files in the way, every setting), with the run's exit code and words,
without sending a frame, and leaves no trace (no --out folder, no open session); flags that
cannot work or would be ignored are configuration errors (exit 2) before anything is sent."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import httpx
import pytest
from farm_cli_support import denoise, error_lines, events, run_and_dry_run, write_shot

from quietframe.client.cli import main

FIXTURES = Path(__file__).resolve().parents[1] / "fixtures" / "blender"


def sessions_created(server) -> float:
    text = httpx.get(f"{server.url}/metrics").text
    return float(re.search(r"^quietframe_sessions_created_total (\S+)", text, re.M).group(1))


def open_sessions(server) -> float:
    text = httpx.get(f"{server.url}/metrics").text
    return float(re.search(r"^quietframe_sessions (\S+)", text, re.M).group(1))


@pytest.mark.parametrize("flags, code", [
    (("--model", "no-such-model"), 2),
    (("--model", "affinity-h16-k5gc", "--model-option", "kernel_size=6"), 2),
    (("--model", "nbg-2l-3g", "--model-option", "kernel_size=5"), 2),
])
def test_dry_run_refuses_a_model_or_option_as_the_run_does(tmp_path, live_server, capsys,
                                                           flags, code):
    write_shot(tmp_path / "in", 2)
    before = sessions_created(live_server)
    (run_code, run_err), (dry_code, dry_err) = run_and_dry_run(
        capsys, denoise(live_server.url, tmp_path / "in", tmp_path / "out", *flags))
    assert run_code == dry_code == code
    assert error_lines(dry_err) == error_lines(run_err)  # the same message and advice
    assert sessions_created(live_server) == before  # refused at creation; the dry run made none


def test_dry_run_refuses_view_layers_as_the_run_does(tmp_path, live_server, capsys):
    src = tmp_path / "in"
    src.mkdir()
    shutil.copy(FIXTURES / "two_view_layers.0002.exr", src / "v.0002.exr")
    args = denoise(live_server.url, src, tmp_path / "out")
    (run_code, run_err), (dry_code, dry_err) = run_and_dry_run(capsys, args)
    assert run_code == dry_code == 3
    assert "--layer NAME, or --layer all" in run_err and "--layer NAME, or --layer all" in dry_err
    (run_code, run_err), (dry_code, dry_err) = run_and_dry_run(capsys, [*args, "--layer", "Nope"])
    assert run_code == dry_code == 2
    assert error_lines(dry_err) == error_lines(run_err)
    assert main([*args, "--layer", "Objects", "--dry-run"]) == 0


def test_dry_run_checks_the_server_and_its_token(tmp_path, live_server, capsys, monkeypatch):
    from pydantic import SecretStr

    write_shot(tmp_path / "in", 2)
    down = ["denoise", "--server", "http://127.0.0.1:9", str(tmp_path / "in"), "--out",
            str(tmp_path / "out"), "--quiet", "--retries", "0"]
    (run_code, run_err), (dry_code, dry_err) = run_and_dry_run(capsys, down)
    assert run_code == dry_code == 75
    assert "cannot reach the quietframe server at http://127.0.0.1:9" in dry_err
    assert error_lines(dry_err) == error_lines(run_err)
    monkeypatch.setattr(live_server.app.state.settings, "auth_token", SecretStr("s3cret"))
    args = denoise(live_server.url, tmp_path / "in", tmp_path / "out")
    (run_code, run_err), (dry_code, dry_err) = run_and_dry_run(capsys, args)
    assert run_code == dry_code == 2 and "--token" in dry_err
    assert error_lines(dry_err) == error_lines(run_err)
    assert main([*args, "--dry-run", "--token", "s3cret"]) == 0
    assert not list((tmp_path / "out").glob("*.exr"))


def test_dry_run_refuses_files_in_the_way_and_says_what_is_to_do(tmp_path, live_server,
                                                                 capsys):
    write_shot(tmp_path / "in", 3)
    out = tmp_path / "out"
    out.mkdir()
    (out / "shot.1002.exr").write_bytes(b"someone else's file")
    args = denoise(live_server.url, tmp_path / "in", out)
    assert main([*args, "--dry-run"]) == 3
    assert "were not written by quietframe" in capsys.readouterr().err
    assert main([*args, "--dry-run", "--force", "--json"]) == 0
    (dry,) = [e for e in events(capsys.readouterr().out) if e["event"] == "dry-run"]
    assert dry["to_denoise"] == 3 and (out / "shot.1002.exr").read_bytes().startswith(b"some")


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
