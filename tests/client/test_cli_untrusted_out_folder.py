"""`quietframe denoise` in an output folder that is not what it expects, against a real server:
links planted where it writes, a full disk (or any stop) between an output and its record,
outputs swapped for other bytes, and job files and records of any JSON shape."""

from __future__ import annotations

import errno
import json
import os
import shutil
import threading
from pathlib import Path

import httpx
import pytest
from conftest import read_exr
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_cli_dry_run import sessions_created
from test_cli_safe_runs import cli, write_shot

from quietframe.client import output_records as records
from quietframe.client.cli import main
from quietframe.client.core import FrameResult
from quietframe.client.sequence import JOB_FILE, Job, job_settings, run_sequence

SERVER = "http://quietframe.test"
VICTIM = b"a file outside --out that must not change"
json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=4),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=4), inner,
                                                                 max_size=3),
    max_leaves=6,
)


def small_shot(tmp_path: Path, n: int = 3) -> tuple[Path, Path]:
    src, out = tmp_path / "in", tmp_path / "out"
    write_shot(src, n, height=24, width=32)
    return src, out


def outputs(out: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(out.glob("*.exr"))}


# ---- links -------------------------------------------------------------------------------


@pytest.mark.parametrize("planted", [".shot_1002.exr.part", ".quietframe/.shot_1002.exr.json.part",
                                     f".{JOB_FILE}.part"], ids=["output", "record", "job-file"])
def test_a_link_at_a_temporary_path_is_never_followed(tmp_path, live_server, planted):
    src, out = small_shot(tmp_path)
    victim = tmp_path / "victim"
    victim.write_bytes(VICTIM)
    (out / records.RECORD_DIR).mkdir(parents=True)
    (out / planted).symlink_to(victim)
    assert main(cli(live_server, src, out)) == 0
    assert victim.read_bytes() == VICTIM
    assert len(outputs(out)) == 3
    assert not any(p.is_symlink() for p in out.rglob("*"))  # replaced, not written through


def test_a_link_in_place_of_the_record_folder_is_refused(tmp_path, live_server, capsys):
    src, out = small_shot(tmp_path)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    out.mkdir()
    (out / records.RECORD_DIR).symlink_to(elsewhere)
    assert main(cli(live_server, src, out)) == 3
    err = capsys.readouterr().err
    assert "writes nothing through a link" in err and "remove it" in err
    assert not list(elsewhere.iterdir())


# ---- a stop between an output and its record -----------------------------------------------


def test_a_full_disk_while_recording_an_output_leaves_a_run_that_resumes(
    tmp_path, live_server, monkeypatch, capsys
):
    src, out = small_shot(tmp_path)
    write_record = records.write_record
    calls = {"n": 0}

    def disk_full_at_the_second_frame(output, *args, **kwargs):
        if output.name == "shot_1002.exr":
            calls["n"] += 1
            raise OSError(errno.ENOSPC, "No space left on device")
        write_record(output, *args, **kwargs)

    monkeypatch.setattr(records, "write_record", disk_full_at_the_second_frame)
    assert main(cli(live_server, src, out)) == 1
    assert "run the same command again" in capsys.readouterr().err and calls["n"] == 1
    monkeypatch.undo()  # space freed
    assert main(cli(live_server, src, out)) == 0, capsys.readouterr().err
    assert len(outputs(out)) == 3
    assert main(cli(live_server, src, out)) == 0  # and every output now counts as done


@pytest.mark.parametrize("error, code, kept", [(errno.EACCES, 2, False), (errno.ENOSPC, 1, True)],
                         ids=["out-not-writable", "disk-full"])
def test_a_write_refused_after_the_session_opened_deletes_it_unless_a_rerun_resumes_it(
    tmp_path, live_server, monkeypatch, capsys, error, code, kept
):
    """--out refusing writes mid-run (EACCES: exit 2, make --out writable) deletes the run's
    server session: no rerun with this --out would continue it (it used to stay open until its
    idle time ended). A full disk (exit 1, run again) keeps it: the rerun continues it."""
    src, out = small_shot(tmp_path)
    write_record = records.write_record

    def refused_at_the_second_frame(output, *args, **kwargs):
        if output.name == "shot_1002.exr":
            raise OSError(error, os.strerror(error))
        write_record(output, *args, **kwargs)

    monkeypatch.setattr(records, "write_record", refused_at_the_second_frame)
    assert main(cli(live_server, src, out)) == code
    err = capsys.readouterr().err
    assert ("cannot write into --out" in err) == (not kept) and "Traceback" not in err
    session = json.loads((out / JOB_FILE).read_text())["sessions"][""]
    answer = httpx.get(f"{live_server.url}/v1/sessions/{session}")
    assert answer.status_code == (200 if kept else 404), answer.text
    monkeypatch.undo()
    created = sessions_created(live_server)
    assert main(cli(live_server, src, out)) == 0, capsys.readouterr().err
    assert sessions_created(live_server) == created + (0 if kept else 1)  # continued, or anew
    assert len(outputs(out)) == 3


def test_a_run_stopped_before_any_rename_resumes(tmp_path, live_server, monkeypatch, capsys):
    """Every step of writing an output or its bookkeeping ends in a rename: stopping a run
    just before its n-th one (a crash, a full disk), for each n over the first two frames,
    visits every state between two steps; each rerun must finish the job, never refuse a file
    as foreign."""
    replace = os.replace
    settings_now = job_settings()
    for stop_at in range(1, 9):
        src, out = small_shot(tmp_path / str(stop_at))
        count = {"n": 0}

        def stop_before_the_nth(*args, stop_at=stop_at, count=count, **kwargs):
            if threading.current_thread() is threading.main_thread():  # not the server's
                count["n"] += 1
                if count["n"] == stop_at:
                    raise OSError(errno.ENOSPC, "No space left on device")
            replace(*args, **kwargs)

        with monkeypatch.context() as patched:
            patched.setattr(os, "replace", stop_before_the_nth)
            assert main(cli(live_server, src, out)) == 1, stop_at
        capsys.readouterr()
        assert main(cli(live_server, src, out)) == 0, (stop_at, capsys.readouterr().err)
        for source in sorted(src.glob("*.exr")):
            check = records.check(out / source.name, source, settings_now)
            assert check.status is records.Status.DONE, (stop_at, source.name, check)


# ---- outputs swapped for other bytes --------------------------------------------------------


def test_an_output_swapped_for_same_size_garbage_is_not_done(tmp_path, live_server, capsys):
    """In a copy of the output folder (new mtimes: the digest says those are the files
    written), one output swapped for garbage of its size: refused, the others count as done."""
    src, first = small_shot(tmp_path)
    assert main(cli(live_server, src, first)) == 0
    out = tmp_path / "copy"
    shutil.copytree(first, out, copy_function=shutil.copyfile)
    target = out / "shot_1002.exr"
    written = target.stat()
    garbage = os.urandom(written.st_size)
    target.write_bytes(garbage)
    os.utime(target, ns=(written.st_atime_ns, written.st_mtime_ns + 10**9))  # a later copy
    capsys.readouterr()
    assert main(cli(live_server, src, out)) == 3
    err = capsys.readouterr().err
    assert "1 file(s)" in err and "shot_1002.exr" in err and "are not the files written" in err
    assert target.read_bytes() == garbage  # refused, not overwritten
    assert main(cli(live_server, src, out, "--force")) == 0
    read_exr(target.read_bytes())


# ---- job files and records of any shape -----------------------------------------------------


@pytest.mark.parametrize("text", ["[]", '{"sessions": "abc"}', '{"sessions": {"": 7}}',
                                  '{"server": 1, "last_index": true}', '"job"', "{not json",
                                  '{"settings": [1]}', '{"sessions": {"": "a b\\n"}}',
                                  '{"session": "?q"}'])
def test_a_damaged_job_file_is_ignored_with_a_warning(tmp_path, live_server, capsys, text):
    src, out = small_shot(tmp_path)
    assert main(cli(live_server, src, out)) == 0
    (out / "shot_1003.exr").unlink()  # something left to do, so the job file is read
    (out / JOB_FILE).write_text(text)
    assert main(cli(live_server, src, out)) == 0
    err = capsys.readouterr().err
    assert "job file" in err and "is damaged" in err and "Traceback" not in err
    assert len(outputs(out)) == 3


@pytest.mark.parametrize("field, value", [("source", "abc"), ("source", {"size": "1"}),
                                          ("settings", []), ("version", True),
                                          ("output", None), ("pending", 0)])
def test_a_damaged_record_is_refused_by_name(tmp_path, live_server, capsys, field, value):
    """A record that is no record vouches for nothing: its output is refused as any file
    quietframe cannot vouch for, and the refusal says the record is damaged."""
    src, out = small_shot(tmp_path)
    assert main(cli(live_server, src, out)) == 0
    path = records.record_path(out / "shot_1002.exr")
    record = json.loads(path.read_text())
    path.write_text(json.dumps({**record, field: value}))
    assert main(cli(live_server, src, out)) == 3
    err = capsys.readouterr().err
    assert "1 with a damaged record" in err and "shot_1002.exr" in err and "--force" in err
    assert main(cli(live_server, src, out, "--force")) == 0


class EchoClient:
    """A server stand-in for the sequence logic: each frame comes back as sent."""

    def __init__(self, width: int, height: int) -> None:
        self.width, self.height = width, height

    def create_session(self, width, height, model="auto", **options) -> dict:
        return {"id": "new"}

    def session(self, session_id) -> dict:
        return {"id": session_id, "last_index": 1001, "width": self.width,
                "height": self.height, "layer": None}

    def send_frame(self, session_id, index, exr, cut=False) -> FrameResult:
        return FrameResult(index, exr, "none", 0, (), False)

    def delete_session(self, session_id) -> None:
        pass


def field_or_any(valid: dict) -> st.SearchStrategy:
    """`valid` with each field kept, left out or replaced by any JSON value."""
    return st.fixed_dictionaries(
        {}, optional={k: st.just(v) | json_values for k, v in valid.items()})


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                                  HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_any_json_in_a_job_file_is_used_or_ignored(tmp_path_factory, data):
    from quietframe.client.job import job_file_problem

    folder = tmp_path_factory.mktemp("job")
    src, out = small_shot(folder, 2)
    job = Job.plan(src, out)
    settings_now = job_settings()
    job.write_output(0, job.files[0].read_bytes(), settings_now)
    valid = {"server": SERVER, "sessions": {"": "s1"}, "session": "s1", "last_index": 1001,
             "settings": settings_now}
    stored = data.draw(json_values | field_or_any(valid), label="job file")
    (out / JOB_FILE).write_text(json.dumps(stored))
    warned: list[str] = []
    run_sequence(EchoClient(job.width, job.height), job, SERVER, on_warning=warned.append)
    assert (out / "shot_1002.exr").read_bytes() == job.files[1].read_bytes()
    assert bool(warned) == (job_file_problem(stored) is not None)  # warned when ignored


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                                   HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_any_json_in_a_record_is_checked_without_error(tmp_path_factory, data):
    folder = tmp_path_factory.mktemp("record")
    src, out = small_shot(folder, 1)
    job = Job.plan(src, out)
    settings_now = job_settings()
    job.write_output(0, job.files[0].read_bytes(), settings_now)
    path = records.record_path(job.output(0))
    valid = json.loads(path.read_text())
    mutated = {**valid, "source": field_or_any(valid["source"]),
               "output": field_or_any(valid["output"])}
    record = data.draw(json_values | st.fixed_dictionaries(
        {}, optional={k: (v if isinstance(v, st.SearchStrategy) else st.just(v)) | json_values
                      for k, v in mutated.items()}), label="record")
    path.write_text(json.dumps(record))
    check = records.check(job.output(0), job.files[0], settings_now)
    assert isinstance(check.status, records.Status)
    if check.status is records.Status.DONE:
        assert records.read_record(job.output(0)) is not None
