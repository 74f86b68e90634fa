"""Farm chunks of one shot against a real server: `auto` decides once per shot and every chunk
and rerun keeps that model (recorded in `<out>/.quietframe/`), also chunks that start at once;
`--model` naming the recorded model is the same setting, another is refused or redone with
--force; a cut starts a shot with a record of its own. A chunk whose pre-roll frames are not
rendered yet says so (an error under --strict), and is redone once they are."""

from __future__ import annotations

import asyncio
import json
import threading
from pathlib import Path

from conftest import LAYOUTS, make_buffers, read_exr, write_exr

from quietframe.client import AsyncClient
from quietframe.client import output_records as records
from quietframe.client.cli import main
from quietframe.client.sequence import Job, arun_sequence

# At 16 samples/pixel auto chooses oidn-history-cleanaux for these frames, at 256 oidn-frame:
# a shot whose later frames were re-rendered at more samples.
CLEAN, NOISY = 256, 16


def render(folder: Path, spp_of: dict[int, int], cuts: tuple[int, ...] = ()) -> None:
    """Frames of one locked-off shot, `shot.NNNN.exr`, each with its Cycles sample count;
    `cuts`: frames whose header flags a camera cut (`quietframe.cut`)."""
    folder.mkdir(parents=True, exist_ok=True)
    for number, spp in spp_of.items():
        buffers = make_buffers(noise=100 + number)
        buffers["motion"][:] = 0
        header: dict = {"cycles.ViewLayer.samples": str(spp)}
        if number in cuts:
            header["quietframe.cut"] = 1
        data = write_exr(LAYOUTS["blender"](buffers), header)
        (folder / f"shot.{number:04d}.exr").write_bytes(data)


def denoise(server, src: Path, out: Path, *flags: str) -> list[str]:
    return ["denoise", "--server", server.url, str(src / "shot.####.exr"), "--out", str(out),
            *flags]


def models_in(out: Path) -> dict[int, str]:
    """Frame number -> the model that made its output (the server's header in the file)."""
    found = {}
    for path in sorted(out.glob("*.exr")):
        header, _ = read_exr(path.read_bytes())
        found[int(path.stem.split(".")[-1])] = str(header["quietframe.model"]).split()[0]
    return found


def events(text: str) -> list[dict]:
    return [json.loads(line) for line in text.splitlines() if line.startswith("{")]


def test_a_later_chunk_keeps_the_model_chosen_from_the_shots_first_frame(
        tmp_path, live_server, capsys):
    """The second half of the shot, re-rendered at more samples, runs first: its own first
    frame would make auto choose another model; the shot's first frame decides instead, and
    the first half, run next, finds that choice recorded."""
    src, out = tmp_path / "in", tmp_path / "out"
    render(src, {1: NOISY, 2: NOISY, 3: NOISY, 4: CLEAN, 5: CLEAN, 6: CLEAN})
    assert main(denoise(live_server, src, out, "--frames", "4-6", "--quiet")) == 0
    assert main(denoise(live_server, src, out, "--frames", "1-3", "--quiet")) == 0
    made = models_in(out)
    assert sorted(made) == [1, 2, 3, 4, 5, 6]
    assert set(made.values()) == {"oidn-history-cleanaux"}, made
    shot = json.loads((out / records.RECORD_DIR / ".shot.json").read_text())
    assert shot["model"] == "oidn-history-cleanaux" and shot["decided_from"] == "shot.0001.exr"
    capsys.readouterr()


def test_chunks_started_at_once_agree_on_one_model(tmp_path, live_server):
    """Two chunks of a shot with no recorded choice yet, run concurrently: both decide from
    the same frame, and the record is made exclusively, so they cannot differ."""
    src, out = tmp_path / "in", tmp_path / "out"
    render(src, {1: NOISY, 2: NOISY, 3: CLEAN, 4: CLEAN})

    async def chunk(frames: tuple[int, ...]) -> None:
        job = Job.plan(src / "shot.####.exr", out, frames)
        async with AsyncClient(live_server.url) as client:
            await arun_sequence(client, job, live_server.url)

    async def both() -> None:
        await asyncio.gather(chunk((3, 4)), chunk((1, 2)))

    asyncio.run(both())
    made = models_in(out)
    assert sorted(made) == [1, 2, 3, 4] and len(set(made.values())) == 1, made


def test_model_naming_the_recorded_choice_is_the_same_setting(tmp_path, live_server, capsys):
    src, out = tmp_path / "in", tmp_path / "out"
    render(src, {1: NOISY, 2: NOISY, 3: CLEAN, 4: CLEAN})
    first = denoise(live_server, src, out, "--frames", "1-2", "--json")
    assert main(first) == 0
    capsys.readouterr()
    before = {p.name: p.read_bytes() for p in out.glob("*.exr")}
    # auto resolved to oidn-history-cleanaux: naming it is no change, nothing is redone
    same = denoise(live_server, src, out, "--frames", "1-2", "--json", "--model",
                   "oidn-history-cleanaux")
    assert main(same) == 0, capsys.readouterr().err
    assert events(capsys.readouterr().out)[-1]["written"] == 0
    assert {p.name: p.read_bytes() for p in out.glob("*.exr")} == before
    # the next chunk naming another model would change the shot's look: refused as changed flags
    other = denoise(live_server, src, out, "--frames", "3-4", "--quiet", "--model", "oidn-frame")
    assert main(other) == 2
    err = capsys.readouterr().err
    assert "oidn-history-cleanaux" in err and "--force" in err
    assert not (out / "shot.0003.exr").exists()
    # --force makes it the shot's model; the first chunk's outputs are then another model's
    assert main([*other, "--force"]) == 0
    assert models_in(out)[3] == "oidn-frame"
    assert main(denoise(live_server, src, out, "--frames", "1-2", "--quiet")) == 2
    assert "--model auto (oidn-history-cleanaux) -> auto (oidn-frame)" in capsys.readouterr().err


def test_a_cut_starts_a_shot_with_a_model_of_its_own_kept_across_chunks(tmp_path, live_server,
                                                                        capsys):
    """Shot two starts at the cut at frame 4. Its second chunk runs while frame 4 is not
    rendered: it never decides from frame 5 (at more samples: another model) but exits 75, or
    waits for frame 4 with --wait-for-shot-start; the shot is decided from frame 4 and named by
    it in the progress, and the other chunk keeps that model."""
    src, out = tmp_path / "in", tmp_path / "out"
    render(src, {1: NOISY, 2: NOISY, 3: NOISY, 5: CLEAN, 6: CLEAN})
    chunk = denoise(live_server, src, out, "--frames", "5-6", "--cut", "4", "--json")
    assert main(chunk) == 75
    assert "the first frame of the shot from frame 4 is not rendered yet" in \
        capsys.readouterr().err
    assert not list(out.glob("*.exr"))
    later = threading.Timer(1.0, render, (src, {4: NOISY}))
    later.start()
    assert main([*chunk, "--wait-for-shot-start", "30"]) == 0
    later.join()
    (shot,) = [e for e in events(capsys.readouterr().out) if e["event"] == "shot"]
    assert (shot["shot_start"], shot["frame"]) == (4, 5), shot  # named by its cut, not frame 5
    assert main(denoise(live_server, src, out, "--frames", "1-4", "--cut", "4", "--quiet")) == 0
    made = models_in(out)
    assert {made[n] for n in (1, 2, 3)} == {"oidn-history-cleanaux"}, made
    assert {made[n] for n in (4, 5, 6)} == {"oidn-history-cleanaux"}, made  # frame 4's choice
    folder = out / records.RECORD_DIR
    assert json.loads((folder / ".shot.cut4.json").read_text())["decided_from"] == "shot.0004.exr"


def test_a_cut_in_a_frame_header_is_found_by_the_chunks_after_it(tmp_path, live_server):
    """Frame 4's header flags a cut. The chunk 5-6, run first, reads back to it: its shot is
    decided from frame 4 as the chunk that holds the cut decides it, not from frame 5."""
    src, out = tmp_path / "in", tmp_path / "out"
    render(src, {1: CLEAN, 2: CLEAN, 3: CLEAN, 4: NOISY, 5: CLEAN, 6: CLEAN}, cuts=(4,))
    assert main(denoise(live_server, src, out, "--frames", "5-6", "--quiet")) == 0
    assert main(denoise(live_server, src, out, "--frames", "1-4", "--quiet")) == 0
    made = models_in(out)
    assert {made[n] for n in (1, 2, 3)} == {"oidn-frame"}, made
    assert {made[n] for n in (4, 5, 6)} == {"oidn-history-cleanaux"}, made


def test_a_missing_pre_roll_is_said_and_its_chunk_redone_once_rendered(
        tmp_path, live_server, capsys):
    src, out = tmp_path / "in", tmp_path / "out"
    render(src, {5: NOISY, 6: NOISY, 7: NOISY, 8: NOISY})  # frames 1-4 are not rendered yet
    chunk = denoise(live_server, src, out, "--frames", "5-8", "--pre-roll", "4", "--model",
                    "nbg-2l-3g", "--json")
    assert main([*chunk, "--strict"]) == 3
    assert "missing pre-roll frame(s) 1-4" in capsys.readouterr().err
    assert not list(out.glob("*.exr"))
    assert main(chunk) == 0
    summary = events(capsys.readouterr().out)[-1]
    assert summary["written"] == 4
    assert any("missing pre-roll frame(s) 1-4" in w for w in summary["warnings"])
    record = json.loads(records.record_path(out / "shot.0005.exr").read_text())
    assert record["pre_roll_missing"] == [1, 2, 3, 4]
    render(src, {1: NOISY, 2: NOISY, 3: NOISY, 4: NOISY})
    assert main(chunk) == 0  # not "4 of 4 already": redone with its pre-roll
    seen = events(capsys.readouterr().out)
    assert [e["frame"] for e in seen if e["event"] == "warmup"] == [1, 2, 3, 4]
    # nbg-2l-3g at these frames' 16 spp is also below its input: that warning stays
    assert seen[-1]["written"] == 4
    assert not [w for w in seen[-1]["warnings"] if "pre-roll" in w]
    assert "pre_roll_missing" not in json.loads(
        records.record_path(out / "shot.0005.exr").read_text())
    assert main(chunk) == 0 and events(capsys.readouterr().out)[-1]["written"] == 0
