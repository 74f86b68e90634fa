"""The client installs wherever Python does: `pip install ".[client]"` (README, docs/farm.md) in a
fresh virtualenv whose PATH starts with compilers, CMake and Ninja that fail, then
`quietframe denoise` from it against a real server. A plain build of `.` compiles nothing (the
C++ ops are built only with QUIETFRAME_BUILD_OPS=1, pyproject.toml) and the client needs no
onnxruntime; a runtime without the ops says how to get them."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import read_exr, shot

pytestmark = pytest.mark.slow  # builds a virtualenv and installs the client from source

ROOT = Path(__file__).resolve().parents[2]
TOOLS = ("cc", "c++", "gcc", "g++", "cmake", "ninja")


@pytest.fixture(scope="module")
def client_venv(tmp_path_factory) -> tuple[Path, dict[str, str]]:
    """(venv bin folder, environment with the failing tools first on PATH), client installed."""
    root = tmp_path_factory.mktemp("client-install")
    fake, called = root / "fake-bin", root / "called.log"
    fake.mkdir()
    for tool in TOOLS:
        (fake / tool).write_text(f'#!/bin/sh\necho "$0 $*" >> {called}\nexit 1\n')
        (fake / tool).chmod(0o755)
    # A venv without its own pip (ensurepip costs ~3 s); this pip installs into it (--python)
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", root / "venv"], check=True)
    bin_dir = root / "venv" / "bin"
    # Nothing from this session may leak in: the opt-in to the ops, compilers named by CC/CXX,
    # the working tree on PYTHONPATH (the test runner's), scikit-build-core settings.
    env = {
        k: v
        for k, v in os.environ.items()
        if not k.startswith(("QUIETFRAME_", "SKBUILD_", "CMAKE_"))
        and k not in ("CC", "CXX", "PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV")
    }
    env["PATH"] = os.pathsep.join([str(fake), str(bin_dir), env.get("PATH", "")])
    result = subprocess.run(
        [sys.executable, "-m", "pip", "--python", bin_dir / "python", "install",
         "--disable-pip-version-check", "-q", ".[client]"],
        cwd=ROOT, env=env, capture_output=True, text=True, timeout=600,
    )
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    assert not called.exists(), f"the client's install ran a build tool:\n{called.read_text()}"
    return bin_dir, env


def test_client_installs_without_compiler_cmake_or_onnxruntime(client_venv):
    bin_dir, env = client_venv
    result = subprocess.run([bin_dir / "quietframe", "denoise", "--help"], env=env,
                            capture_output=True, text=True)
    assert result.returncode == 0 and "--server" in result.stdout, result.stderr
    # quietframe.runtime imports onnxruntime: find its folder without importing it.
    probe = (
        "import importlib.util as u, pathlib;"
        "folders = u.find_spec('quietframe.runtime').submodule_search_locations;"
        "print(u.find_spec('onnxruntime') is None);"
        "print(any(any(pathlib.Path(f).glob('libquietframe_ops*')) for f in folders))"
    )
    result = subprocess.run([bin_dir / "python", "-c", probe], env=env, cwd=bin_dir,
                            capture_output=True, text=True)
    assert result.stdout.split() == ["True", "False"], result.stdout + result.stderr
    result = subprocess.run([bin_dir / "python", "-c", "import onnxruntime"], env=env,
                            capture_output=True, text=True)
    assert result.returncode != 0 and "No module named 'onnxruntime'" in result.stderr


def test_client_install_denoises_against_a_server(client_venv, live_server, tmp_path):
    bin_dir, env = client_venv
    src, out = tmp_path / "in", tmp_path / "out"
    src.mkdir()
    for i, data in enumerate(shot(2, "blender")):
        (src / f"shot.{1001 + i:04d}.exr").write_bytes(data)
    result = subprocess.run(
        [bin_dir / "quietframe", "denoise", "--server", live_server.url,
         str(src / "shot.####.exr"), "--out", str(out)],
        env=env, capture_output=True, text=True, timeout=300,
    )
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    for frame in (1001, 1002):
        _, channels = read_exr((out / f"shot.{frame:04d}.exr").read_bytes())
        assert channels


def test_missing_ops_library_names_the_fix(monkeypatch, runtime_env, tmp_path):
    from quietframe import runtime
    from quietframe.runtime.ops_library import ops_library_path

    runtime_env("QUIETFRAME_OPS_LIBRARY", None)
    monkeypatch.setattr(runtime, "__path__", [str(tmp_path)])
    with pytest.raises(FileNotFoundError, match=r"QUIETFRAME_BUILD_OPS=1 pip install"):
        ops_library_path()
