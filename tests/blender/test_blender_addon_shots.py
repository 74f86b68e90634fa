"""The add-on's planning (no bpy): which camera renders each frame under Blender's rule for camera
markers, the runs of frames that become one session each (the rule itself is checked against
Blender's own camera switch in test_blender_addon_bpy.py), and which servers are on the local
network (reached without Blender's online access)."""

from __future__ import annotations

import pytest
from blender_addon_support import ADDON_PARENT  # noqa: F401  (puts the add-on on sys.path)
from quietframe_blender.server_api import on_local_network
from quietframe_blender.shots import CameraMarker, Shot, camera_at, frame_range, plan_shots


def test_no_markers_is_one_shot_on_the_scene_camera():
    assert plan_shots(range(1, 6), [], "Camera") == [Shot("Camera", (1, 2, 3, 4, 5))]


def test_each_camera_switch_starts_a_shot():
    markers = [CameraMarker(1, "A"), CameraMarker(4, "B"), CameraMarker(7, "A")]
    assert plan_shots(range(1, 10), markers, "Scene") == [
        Shot("A", (1, 2, 3)), Shot("B", (4, 5, 6)), Shot("A", (7, 8, 9)),
    ]


def test_frames_before_the_first_marker_take_its_camera():
    # Blender: before every camera marker, the earliest one's camera (not the scene's camera)
    markers = [CameraMarker(5, "B"), CameraMarker(3, "A")]
    assert [camera_at(f, markers, "Scene") for f in (0, 2, 3, 4, 5, 9)] == [
        "A", "A", "A", "A", "B", "B"]


def test_markers_in_any_order_and_ties_take_the_first_in_marker_order():
    markers = [CameraMarker(8, "C"), CameraMarker(2, "A"), CameraMarker(8, "B")]
    assert camera_at(8, markers, "Scene") == "C"
    assert camera_at(7, markers, "Scene") == "A"


def test_a_marker_repeating_the_camera_keeps_the_shot():
    markers = [CameraMarker(1, "A"), CameraMarker(3, "A"), CameraMarker(5, "B")]
    assert plan_shots(range(1, 7), markers, "A") == [Shot("A", (1, 2, 3, 4)), Shot("B", (5, 6))]


def test_frame_range_follows_the_step_and_refuses_zero():
    assert frame_range(1, 10, 3) == [1, 4, 7, 10]
    assert frame_range(5, 5) == [5]
    with pytest.raises(ValueError, match="at least 1"):
        frame_range(1, 10, 0)


def test_shot_describes_its_frames_and_camera():
    assert Shot("A", (1, 2, 3)).describe() == "frames 1-3 (A)"
    assert Shot("B", (7,)).describe() == "frame 7 (B)"


@pytest.mark.parametrize("url, local", [
    ("http://127.0.0.1:8000", True), ("http://localhost:8000/v1", True),
    ("http://denoise:8000", True), ("http://farm.local", True), ("http://10.1.2.3", True),
    ("http://192.168.1.5:8000", True), ("http://[::1]:8000", True),
    ("http://8.8.8.8", False), ("https://quietframe.example.com", False),
])
def test_a_server_on_the_local_network_needs_no_online_access(url, local):
    assert on_local_network(url) is local
