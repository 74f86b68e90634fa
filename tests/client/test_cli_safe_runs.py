"""Safe runs of `quietframe denoise` against a real server: Ctrl-C / SIGTERM stop within one
frame, outputs that are not this job's are refused (or redone with --force), and changed flags
are never silently ignored."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from conftest import read_exr, shot, write_exr

from quietframe.client.cli import main


def write_shot(folder: Path, n: int, start: int = 1001, height: int = 48, width: int = 64):
    folder.mkdir(parents=True, exist_ok=True)
    for i, data in enumerate(shot(n, "blender", height=height, width=width)):
        (folder / f"shot_{start + i}.exr").write_bytes(data)


def cli(server, src, out, *flags) -> list[str]:
    return ["denoise", "--server", server.url, str(src), "--out", str(out), "--quiet", *flags]


def size_of(path: Path) -> tuple[int, int]:
    header, _ = read_exr(path.read_bytes())
    (x0, y0), (x1, y1) = header["dataWindow"]
    return int(x1 - x0 + 1), int(y1 - y0 + 1)


@pytest.mark.parametrize("signal_name, code", [("SIGINT", 130), ("SIGTERM", 143)])
def test_a_signal_stops_the_run_within_one_frame(tmp_path, live_server, signal_name, code):
    src, out = tmp_path / "in", tmp_path / "out"
    total = 60
    write_shot(src, total, height=24, width=32)
    command = [sys.executable, "-m", "quietframe.client.cli",
               *cli(live_server, src, out, "--model", "nbg-2l-3g")]
    run = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 60
    while not list(out.glob("*.exr")) and run.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    at_signal = len(list(out.glob("*.exr")))
    run.send_signal(getattr(signal, signal_name))
    sent = time.monotonic()
    _, err = run.communicate(timeout=30)
    stopped_s = time.monotonic() - sent
    written = len(list(out.glob("*.exr")))
    assert run.returncode == code, err
    assert 0 < at_signal <= written <= at_signal + 1 < total, (at_signal, written)
    assert stopped_s < 5, stopped_s
    assert "Traceback" not in err and f"interrupted ({signal_name})" in err
    assert err.count("run the same command again to resume") == 1
    assert main(cli(live_server, src, out, "--model", "nbg-2l-3g")) == 0  # it resumes
    assert len(list(out.glob("*.exr"))) == total


def test_a_signal_between_an_output_and_its_record_waits_for_the_record(tmp_path, monkeypatch):
    """The race CI once hit: SIGINT after the output was in place but before its record left a
    file the resume refused as foreign. The pair is written whole, then the run stops."""
    from quietframe.client import output_records
    from quietframe.client.interrupt import Interrupted, stop_on_signals
    from quietframe.client.sequence import Job, job_settings

    src, out = tmp_path / "in", tmp_path / "out"
    write_shot(src, 2, height=24, width=32)
    job = Job.plan(src, out)
    settings = job_settings(model="nbg-2l-3g")
    write_record = output_records.write_record

    def signal_first(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGINT)  # arrives with the output written, the record not
        write_record(*args, **kwargs)

    monkeypatch.setattr(output_records, "write_record", signal_first)
    with stop_on_signals(), pytest.raises(Interrupted):
        job.write_output(0, (src / "shot_1001.exr").read_bytes(), settings)
    check = output_records.check(job.output(0), job.files[0], settings)
    assert check.status is output_records.Status.DONE


def test_files_not_written_by_this_job_are_refused_or_redone_with_force(
    tmp_path, live_server, capsys
):
    src, out, other = tmp_path / "in", tmp_path / "out", tmp_path / "other"
    write_shot(src, 6)
    write_shot(other, 3, height=36, width=64)  # another shot, another size, the same names
    out.mkdir()
    for path in other.iterdir():
        (out / path.name).write_bytes(path.read_bytes())
    assert main(cli(live_server, src, out)) == 3
    err = capsys.readouterr().err
    assert "3 file(s)" in err and "were not written by quietframe" in err and "--force" in err
    assert {size_of(p) for p in out.glob("*.exr")} == {(64, 36)}  # nothing was overwritten
    assert main(cli(live_server, src, out, "--force")) == 0
    assert {size_of(p) for p in out.glob("*.exr")} == {(64, 48)}
    assert len(list(out.glob("*.exr"))) == 6


def test_a_re_rendered_source_is_refused_then_redone_with_force(tmp_path, live_server, capsys):
    src, out = tmp_path / "in", tmp_path / "out"
    write_shot(src, 3)
    temporal = ("--model", "nbg-2l-3g")  # frame 1003's output depends on 1002 through history
    assert main(cli(live_server, src, out, *temporal)) == 0
    before = (out / "shot_1003.exr").read_bytes()
    _, rerendered = read_exr(shot(4, "blender")[3])  # new noise: a re-render of the frame
    (src / "shot_1002.exr").write_bytes(write_exr(rerendered))
    assert main(cli(live_server, src, out, *temporal)) == 3
    assert "re-rendered" in capsys.readouterr().err
    assert main(cli(live_server, src, out, *temporal, "--force")) == 0
    assert (out / "shot_1003.exr").read_bytes() != before  # redone from the changed frame on
    assert main(cli(live_server, src, out, *temporal)) == 0  # and now it is this job's output


def test_changed_flags_are_refused_not_ignored(tmp_path, live_server, capsys):
    """A run that stopped after two frames, rerun with another model: refused (exit 2) with
    the flags that differ; --force redoes every frame with the new model."""
    src, out = tmp_path / "in", tmp_path / "out"
    write_shot(src, 4)
    assert main(cli(live_server, src, out)) == 0
    for name in ("shot_1003.exr", "shot_1004.exr"):  # as if it had stopped after two frames
        (out / name).unlink()
    assert main(cli(live_server, src, out, "--model", "nbg-2l-3g")) == 2
    err = capsys.readouterr().err
    assert "--model auto -> nbg-2l-3g" in err and "--force" in err
    assert len(list(out.glob("*.exr"))) == 2
    assert main(cli(live_server, src, out, "--model", "nbg-2l-3g", "--force")) == 0
    for path in sorted(out.glob("*.exr")):
        header, _ = read_exr(path.read_bytes())
        assert header["quietframe.model"].startswith("nbg-2l-3g"), path.name
    assert main(cli(live_server, src, out, "--model-option", "kernel_size=9")) == 2
    assert "--model-option" in capsys.readouterr().err
