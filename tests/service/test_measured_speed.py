"""This server's measured speed beside the tables' figure: the denoise times of recent frames per
model and frame size (bounded), their median in a session's `choice` as `measured_ms` with the
frames counted and the size, on a real server."""

from __future__ import annotations

import statistics

import pytest
from conftest import shot

from quietframe.client import Client
from quietframe.service.measured_speed import MeasuredSpeeds


def test_the_median_of_the_last_frames_per_model_and_size():
    speeds = MeasuredSpeeds(frames_per_size=4)
    assert speeds.at("oidn-frame", 1080, 1920) is None
    for ms in (900.0, 100.0, 110.0, 120.0, 130.0):  # the first falls out of the last 4
        speeds.record("oidn-frame", 1080, 1920, ms)
    measured = speeds.at("oidn-frame", 1080, 1920)
    assert (measured.ms, measured.frames) == (115.0, 4)
    assert (measured.width, measured.height) == (1920, 1080)
    speeds.record("oidn-frame", 720, 1280, 50.0)  # another size: its own figure
    speeds.record("nbg-2l-3g", 1080, 1920, 5.0)  # another model: its own figure
    assert speeds.at("oidn-frame", 720, 1280).ms == 50.0
    assert speeds.at("nbg-2l-3g", 1080, 1920).ms == 5.0
    assert speeds.at("oidn-frame", 1080, 1920).ms == 115.0


def test_the_sizes_kept_are_bounded_least_recently_measured_first():
    speeds = MeasuredSpeeds(frames_per_size=2, max_sizes=3)
    for width in (100, 200, 300):
        speeds.record("m", 10, width, float(width))
    speeds.record("m", 10, 100, 1.0)  # measured again: now the most recent
    speeds.record("m", 10, 400, 4.0)  # a fourth size lets the least recent (200) go
    assert len(speeds) == 3
    assert speeds.at("m", 10, 200) is None
    assert speeds.at("m", 10, 100).frames == 2 and speeds.at("m", 10, 400).frames == 1


def test_a_sessions_choice_carries_this_servers_time_at_its_size(live_server):
    """Frames of a size no other test sends (56x32), so the server's figure is these frames'
    own: measured_ms is the median of their Server-Timing denoise, counted; a session of
    another size gets the figure of its own size, not this one's."""
    frames = shot(3, "blender", height=32, width=56)
    with Client(live_server.url) as client:
        session = client.create_session(56, 32)
        other = client.create_session(40, 24)
        try:
            results = [client.send_frame(session["id"], i, data)
                       for i, data in enumerate(frames)]
            choice = client.session(session["id"])["choice"]
            client.send_frame(other["id"], 0, shot(1, "blender", height=24, width=40)[0])
            other_choice = client.session(other["id"])["choice"]
        finally:
            client.delete_session(session["id"])
            client.delete_session(other["id"])
    denoise_ms = [r.timings_ms["denoise"] for r in results]
    assert choice["measured_frames"] == 3 and choice["measured_size"] == "56x32"
    assert choice["measured_ms"] == pytest.approx(statistics.median(denoise_ms), abs=0.2)
    assert choice["expected_ms"] is not None  # the tables' figure stays beside it
    assert other_choice["measured_frames"] == 1 and other_choice["measured_size"] == "40x24"
