"""`quietframe denoise --lookahead K` and `--post-roll Q` through the real CLI over a socket,
against a stand-in of the look-ahead protocol (tests/lookahead_support.py) that "denoises" each
frame as itself: an output equal to its own input was written from the reply that carried its
frame. A chunk writes exactly its frames, a 202 writes nothing, the frames still held are
finished in order, lost replies are replayed as the same frame, a rerun continues the session
with the frames it holds, missing post-roll frames are recorded and redone, and bad flags are
exit 2 before anything is sent."""

from __future__ import annotations

import json

import pytest
from conftest import layout_blender, make_buffers, read_exr, write_exr
from farm_cli_support import events, write_shot
from lookahead_support import FakeServer

from quietframe.client.api import Client, QuietframeError
from quietframe.client.cli import main
from quietframe.client.output_records import read_record


@pytest.fixture
def fake():
    with FakeServer() as server:
        yield server


def denoise(server, src, out, *flags: str) -> list[str]:
    return ["denoise", "--server", server.url, str(src / "shot.####.exr"), "--out", str(out),
            "--model", "fake", "--retries", "0", *flags]


def written(src, out) -> dict[int, bool]:
    """Frame number -> whether its output is its own input (the fake's reply for that frame)."""
    return {int(p.name.split(".")[1]): p.read_bytes() == (src / p.name).read_bytes()
            for p in sorted(out.glob("*.exr"))}


def test_chunk_with_pre_and_post_roll_writes_exactly_its_frames(tmp_path, fake, capsys):
    src, out = tmp_path / "in", tmp_path / "out"
    write_shot(src, 10)
    args = denoise(fake, src, out, "--frames", "1004-1006", "--pre-roll", "2", "--post-roll",
                   "2", "--lookahead", "2", "--json")
    assert main(args) == 0
    seen = events(capsys.readouterr().out)
    assert fake.fake.sent("frame") == list(range(1002, 1009))
    assert fake.fake.sent("finish") == []  # the held 1007, 1008 are post-roll: dropped
    assert written(src, out) == {1004: True, 1005: True, 1006: True}
    frames = [(e["frame"], e["reply_to"]) for e in seen if e["event"] == "frame"]
    assert frames == [(1004, 1006), (1005, 1007), (1006, 1008)]  # each 2 frames later
    assert [e["frame"] for e in seen if e["event"] == "warmup"] == [1002, 1003]
    assert [e["frame"] for e in seen if e["event"] == "post-roll"] == [1007, 1008]
    assert seen[-1]["event"] == "summary" and seen[-1]["written"] == 3
    record = read_record(out / "shot.1005.exr")
    assert record.settings["lookahead"] == 2 and record.post_roll_missing == ()
    job = json.loads((out / ".quietframe-job.1004-1006.json").read_text())
    assert job["held"] == [1007, 1008] and job["last_index"] == 1008
    assert fake.fake.sent("delete") and not fake.fake.sessions  # the session is deleted


def test_a_202_writes_nothing_and_the_held_frames_are_finished_in_order(tmp_path, fake):
    src, out = tmp_path / "in", tmp_path / "out"
    write_shot(src, 4)
    seen = []

    def progress(p) -> None:  # what is on disk when each reply has been handled
        seen.append((p.path.name, p.held, p.sent, sorted(f.name for f in out.glob("*.exr"))))

    with Client(fake.url) as client:
        client.denoise_sequence(src, out, model="fake", lookahead=2, on_progress=progress)
    assert seen[:2] == [("shot.1001.exr", True, 0, []), ("shot.1002.exr", True, 1, [])]
    assert seen[2][:3] == ("shot.1001.exr", False, 2)  # the reply to 1003 carries 1001
    assert fake.fake.sent("finish") == [1003, 1004]  # the end of the run, oldest first
    assert [(name, sent) for name, _, sent, _ in seen[-2:]] == [("shot.1003.exr", None),
                                                               ("shot.1004.exr", None)]
    assert written(src, out) == {1001: True, 1002: True, 1003: True, 1004: True}


def test_a_cut_after_the_chunk_ends_its_post_roll(tmp_path, fake, capsys):
    """The frames after a cut are another shot's: not sent, so the chunk's last frames are
    finished with what they have, in order."""
    src, out = tmp_path / "in", tmp_path / "out"
    write_shot(src, 10)
    assert main(denoise(fake, src, out, "--frames", "1004-1006", "--pre-roll", "2",
                        "--post-roll", "2", "--lookahead", "2", "--cut", "1007", "--quiet")) == 0
    assert fake.fake.sent("frame") == list(range(1002, 1007))
    assert fake.fake.sent("finish") == [1005, 1006]
    assert written(src, out) == {1004: True, 1005: True, 1006: True}


def test_lost_replies_are_replayed_as_the_same_frame(tmp_path, fake):
    src, out = tmp_path / "in", tmp_path / "out"
    write_shot(src, 5)
    fake.fake.lose_reply_once |= {("frame", 1004), ("finish", 1005)}
    assert main(denoise(fake, src, out, "--lookahead", "2", "--retries", "2", "--quiet")) == 0
    assert fake.fake.sent("frame").count(1004) == 2  # sent again: the stored reply came back
    assert fake.fake.sent("finish") == [1004, 1005, 1005]
    assert written(src, out) == dict.fromkeys(range(1001, 1006), True)


def test_a_rerun_continues_the_session_with_the_frames_it_holds(tmp_path, fake, capsys):
    src, out = tmp_path / "in", tmp_path / "out"
    write_shot(src, 8)
    fake.fake.fail_once[("frame", 1006)] = 503  # busy, no retries: exit 75 at frame 1006
    args = denoise(fake, src, out, "--lookahead", "2", "--quiet")
    assert main(args) == 75
    assert "the run resumes" in capsys.readouterr().err
    assert written(src, out) == {1001: True, 1002: True, 1003: True}  # 1004, 1005 held
    job = json.loads((out / ".quietframe-job.json").read_text())
    assert job["held"] == [1004, 1005] and job["last_index"] == 1005
    before = len(fake.fake.log)
    assert main(args) == 0
    rerun = fake.fake.log[before:]
    assert [kind for kind, _, _ in rerun].count("create") == 0  # the same session goes on
    assert [i for kind, _, i in rerun if kind == "frame"] == [1006, 1007, 1008]
    assert written(src, out) == dict.fromkeys(range(1001, 1009), True)


def test_missing_post_roll_frames_are_recorded_and_redone_once_rendered(tmp_path, fake,
                                                                         capsys):
    src, out = tmp_path / "in", tmp_path / "out"
    write_shot(src, 8)
    later = {n: (src / f"shot.{n}.exr").read_bytes() for n in (1007, 1008)}
    for n in later:
        (src / f"shot.{n}.exr").unlink()
    args = denoise(fake, src, out, "--frames", "1004-1006", "--pre-roll", "2", "--post-roll",
                   "2", "--lookahead", "2", "--quiet")
    assert main([*args, "--strict"]) == 3
    assert "missing post-roll frame(s) 1007-1008" in capsys.readouterr().err
    assert main(args) == 0
    assert read_record(out / "shot.1004.exr").post_roll_missing == ()
    assert read_record(out / "shot.1005.exr").post_roll_missing == (1007,)
    assert read_record(out / "shot.1006.exr").post_roll_missing == (1007, 1008)
    for n, data in later.items():
        (src / f"shot.{n}.exr").write_bytes(data)
    before = len(fake.fake.log)
    assert main(args) == 0  # 1005 and 1006 redone, now with their look-ahead
    assert [i for kind, _, i in fake.fake.log[before:] if kind == "frame"] == [
        1002, 1003, 1004, 1005, 1006, 1007, 1008]  # warm-up (from the pre-roll), 1005-1006

    assert read_record(out / "shot.1006.exr").post_roll_missing == ()
    assert written(src, out) == {1004: True, 1005: True, 1006: True}


def test_dry_run_says_what_it_would_send_including_the_post_roll(tmp_path, fake, capsys):
    src, out = tmp_path / "in", tmp_path / "out"
    write_shot(src, 10)
    args = denoise(fake, src, out, "--frames", "1004-1006", "--pre-roll", "2", "--post-roll",
                   "2", "--lookahead", "2", "--dry-run")
    assert main([*args, "--json"]) == 0
    (dry,) = [e for e in events(capsys.readouterr().out) if e["event"] == "dry-run"]
    assert (dry["pre_roll"], dry["frames"], dry["post_roll"], dry["lookahead"]) == (
        [1002, 1003], [1004, 1005, 1006], [1007, 1008], 2)
    assert fake.fake.sent("frame") == [] and not out.exists()
    assert main(args) == 0
    assert ("would send frame(s) 1002-1003 (pre-roll, not written), 1004-1006, 1007-1008 "
            "(post-roll, not written)") in capsys.readouterr().out


@pytest.mark.parametrize(("flags", "words"), [
    (("--lookahead", "7"), "--lookahead is how many later frames each frame may use, 0 to 4; "
                           "got 7"),
    (("--lookahead", "-1"), "0 to 4; got -1"),
    (("--post-roll", "2"), "--post-roll 2 sends frames after --frames only for the look-ahead"),
    (("--post-roll", "3", "--lookahead", "2"), "a frame looks at most --lookahead 2 frame(s)"),
])
def test_bad_lookahead_flags_are_configuration_errors(tmp_path, fake, capsys, flags, words):
    src = tmp_path / "in"
    write_shot(src, 3)
    assert main(denoise(fake, src, tmp_path / "out", "--frames", "1002", *flags)) == 2
    assert words in capsys.readouterr().err
    assert fake.fake.log == []  # refused before anything is sent


def test_the_client_api_speaks_the_protocol(tmp_path, fake):
    write_shot(tmp_path, 3)
    frames = [(tmp_path / f"shot.{1001 + i}.exr").read_bytes() for i in range(3)]
    with Client(fake.url) as client:
        session = client.create_session(64, 48, model="fake", lookahead=1)
        assert client.send_frame(session["id"], 1001, frames[0]) is None  # 202
        carried = client.send_frame(session["id"], 1002, frames[1])
        assert (carried.index, carried.exr, carried.pending) == (1001, frames[0], 1)
        with pytest.raises(QuietframeError) as refused:
            client.finish_frame(session["id"], 1003)  # not the oldest pending
        assert refused.value.status == 409 and "1002" in refused.value.detail
        finished = client.finish_frame(session["id"], 1002)
        assert (finished.index, finished.exr, finished.pending) == (1002, frames[1], 0)
        with pytest.raises(QuietframeError) as refused:
            client.create_session(64, 48, model="fake", lookahead=7)
        assert refused.value.status == 422


def test_every_view_layer_session_holds_the_same_frames(tmp_path, fake):
    """--layer all: one session per view layer, each looking ahead; each output merges the
    layers' replies for one frame, the frame they carry."""
    src, out = tmp_path / "in", tmp_path / "out"
    src.mkdir()
    for i in range(4):
        layers = {**layout_blender(make_buffers(noise=10 + i), view_layer="A"),
                  **layout_blender(make_buffers(noise=20 + i), view_layer="B")}
        (src / f"shot.{1001 + i}.exr").write_bytes(write_exr(layers))
    assert main(denoise(fake, src, out, "--layer", "all", "--lookahead", "1", "--quiet")) == 0
    assert len([kind for kind, _, _ in fake.fake.log if kind == "create"]) == 2
    assert fake.fake.sent("finish") == [1004, 1004]  # each layer's session
    for n in range(1001, 1005):
        _, got = read_exr((out / f"shot.{n}.exr").read_bytes())
        _, sent = read_exr((src / f"shot.{n}.exr").read_bytes())
        assert sorted(got) == sorted(sent)
        assert all((got[name] == sent[name]).all() for name in sent)
