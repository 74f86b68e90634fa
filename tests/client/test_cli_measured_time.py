"""The numbers the CLI says of auto's choice are what they are: the time per frame this server
measured at the session's size (with the frames it is the median of) once there are any, else
the tables' figure labelled as a timing from another machine; the PSNR as the validation shots'
average, not a prediction for the shot."""

from __future__ import annotations

import re
from pathlib import Path

from conftest import shot
from farm_cli_support import denoise, events

from quietframe.client.choice_text import describe_choice
from quietframe.client.cli import main

CHOICE = {"model": "oidn-history", "reason": "balanced: the best expected", "spp": 4,
          "noise_source": "header", "buffers": ["albedo", "normal", "depth", "motion"],
          "expected_psnr": 30.7, "expected_ms": 231.0}


def test_without_a_measurement_the_tables_figure_is_labelled_as_such():
    text = describe_choice({**CHOICE, "measured_ms": None, "measured_frames": 0})
    assert "231 ms per frame by the tables (timed on another machine" in text
    assert "not measured here" in text


def test_the_servers_measurement_at_the_sessions_size_replaces_the_tables_figure():
    served = {**CHOICE, "measured_ms": 803.4, "measured_frames": 12,
              "measured_size": "1920x1080"}
    text = describe_choice(served, measured_ms=640.0)  # the server's figure before the run's
    assert "803 ms per frame measured on this server at 1920x1080 (12 frames)" in text
    assert "231" not in text and "640" not in text
    one = describe_choice({**served, "measured_frames": 1})
    assert "(1 frame)" in one


def test_the_psnr_is_said_to_be_the_validation_average_not_a_prediction():
    text = describe_choice(CHOICE)
    assert ("30.7 dB PSNR on the validation shots at this noise (their average, not a "
            "prediction for this shot)") in text
    assert "expect about" not in text


def test_a_later_chunk_is_told_the_time_measured_on_the_earlier_ones(tmp_path: Path,
                                                                   live_server, capsys):
    """Two chunks of one shot at a size no other test sends (48x40): the second's shot line
    gives the server's median at that size over more frames than its own."""
    source = tmp_path / "render"
    source.mkdir()
    for i, data in enumerate(shot(6, "blender", height=40, width=48)):
        (source / f"sh.{1001 + i:04d}.exr").write_bytes(data)
    lines = []
    for frames in ("1001-1003", "1004-1006"):
        args = denoise(live_server.url, source / "sh.####.exr", tmp_path / "out", "--frames",
                       frames, "--pre-roll", "0", "--cut", "1001", "--json")
        args.remove("--quiet")
        assert main(args) == 0
        (said,) = [e for e in events(capsys.readouterr().out) if e["event"] == "shot"]
        lines.append(said)
    later = lines[1]
    found = re.search(r"(\d+) ms per frame measured on this server at 48x40 \((\d+) frames\)",
                      later["text"])
    assert found, later["text"]
    assert int(found.group(2)) > 1 and int(found.group(2)) == later["choice"]["measured_frames"]
    assert abs(int(found.group(1)) - later["choice"]["measured_ms"]) <= 1
