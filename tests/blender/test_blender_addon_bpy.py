"""The add-on in Blender itself (bpy 4.5, headless, in the Cycles venv) against a real server:
installed from the built zip as Blender installs an extension, it denoises three Cycles frames
while they render and again from the operator, one session per camera shot, and names the URL
of a server it cannot reach (tests/blender/addon_in_blender.py runs inside Blender)."""

from __future__ import annotations

import json
import os
import socket
import subprocess
from pathlib import Path

import pytest
from blender_addon_support import assert_denoised, extension_builder
from conftest import hard_timeout
from cycles_support import require_cycles

SCRIPT = Path(__file__).with_name("addon_in_blender.py")
SIZE = (64, 36)


@pytest.fixture
def blender_python() -> str:
    """The Cycles venv's interpreter (skips without one, before the server starts)."""
    python = require_cycles()
    if not Path(python).exists():
        pytest.skip(f"no Cycles venv at {python}: `make cycles` (bpy 4.5)")
    probe = subprocess.run([python, "-c", "import bpy"], capture_output=True, timeout=120)
    if probe.returncode != 0:
        pytest.skip(f"{python} cannot import bpy: `make cycles` installs Blender 4.5 (bpy)")
    return python


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]  # closed again: nothing listens there


def test_blender_renders_and_the_addon_denoises_each_camera_shot(blender_python, tmp_path,
                                                                  live_server):
    python = blender_python
    extension = extension_builder().build(tmp_path / "dist")
    unreachable = f"http://127.0.0.1:{free_port()}"
    env = {**os.environ, "BLENDER_USER_RESOURCES": str(tmp_path / "blender-user")}
    with hard_timeout(150):
        run = subprocess.run(
            [python, str(SCRIPT), str(extension), live_server.url, str(tmp_path), unreachable],
            capture_output=True, text=True, timeout=120, env=env, cwd=tmp_path)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    out = json.loads(next(x for x in run.stdout.splitlines() if x.startswith("@@"))[2:])

    # the installed extension runs on the wire package bundled in its zip
    assert out["wire"] == "bl_ext.user_default.quietframe._wire.protocol"
    assert out["addon_file"].startswith(str(tmp_path / "blender-user"))
    # the add-on's shots are Blender's own camera switch: a marker at frame 3 switches cameras
    assert out["blender_cameras"] == {"1": "moving", "2": "moving", "3": "other"}
    assert out["plan"] == [{"camera": "moving", "frames": [1, 2]},
                           {"camera": "other", "frames": [3]}]
    assert out["live_error"] == ""
    # a render that writes nothing (F12) with the toggle on starts no job and says nothing
    assert out["still"] == {"result": False, "running": False, "message": "", "error": ""}

    panel = out["panel"]  # drawn with a view layer that lacks the passes, into a folder
    assert panel["operators_exist"] and "quietframe.set_up_passes" in panel["operators"]
    assert "quietframe.denoise_frames" in panel["operators"]
    assert all(exists for _, _, exists in panel["props"]), panel["props"]
    assert {"view_layer", "folder", "live", "model"} <= {p for _, p, _ in panel["props"]}

    render = tmp_path / "render"
    for run_name, folder, suffix in (("live", render, "_denoised"),
                                     ("operator", tmp_path / "denoised", "")):
        frames = out[run_name]
        assert [f["frame"] for f in frames] == [1, 2, 3], run_name
        sessions = [f["session"] for f in frames]
        assert sessions[0] == sessions[1] != sessions[2], run_name  # one session per shot
        assert frames[2]["reset"] == "first-frame", run_name  # no history across the switch
        for f in frames:
            source = render / f"shot_{f['frame']:04d}.exr"
            output = folder / f"shot_{f['frame']:04d}{suffix}.exr"
            assert (f["source"], f["output"]) == (str(source), str(output))
            assert_denoised(source, output, SIZE)
    assert not set(f["session"] for f in out["live"]) & set(f["session"] for f in out["operator"])

    error = out["unreachable_error"]
    assert error and unreachable in error and "connection refused" in error
    # Blender's online access is off here: the loopback server above was reached all the same,
    # an internet host is not
    assert out["online_access"] is False
    assert "online access is off" in out["offline_error"]
    assert "Allow Online Access" in out["offline_error"]
    for refusal in (out["png_live_error"], out["png_error"]):
        assert refusal and "written as PNG" in refusal and "OpenEXR MultiLayer" in refusal
    assert not (tmp_path / "png" / "shot_0001_denoised.exr").exists()
