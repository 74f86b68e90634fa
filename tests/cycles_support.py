"""Blender (bpy) runs in its own venv (the `cycles` extra pins numpy < 2 and one Python), so
tests reach it through a subprocess: QUIETFRAME_CYCLES_PYTHON, or .venv-cycles/bin/python
(`make cycles`). Without either, the tests that need Blender are skipped cleanly."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def cycles_python() -> str | None:
    given = os.environ.get("QUIETFRAME_CYCLES_PYTHON")
    if given:
        return given
    local = ROOT / ".venv-cycles" / "bin" / "python"
    return str(local) if local.exists() else None


def require_cycles() -> str:
    python = cycles_python()
    if python is None:
        pytest.skip("no Cycles venv: `make cycles` or QUIETFRAME_CYCLES_PYTHON (bpy 4.5)")
    return python


def run_blender(args: list[str], timeout: float = 600) -> str:
    """Run `python <args>` in the Cycles venv; its stdout (Blender's own chatter included)."""
    result = subprocess.run([require_cycles(), *args], capture_output=True, text=True,
                            timeout=timeout, cwd=ROOT)
    if result.returncode != 0:
        raise AssertionError(f"Cycles venv run failed ({result.returncode}):\n"
                             f"{result.stdout[-3000:]}\n{result.stderr[-3000:]}")
    return result.stdout


def blender_json(code: str, *args: str, timeout: float = 300):
    """Run a snippet in Blender's Python; it prints one JSON line starting with `@@`."""
    out = run_blender(["-c", code, *args], timeout)
    line = next(x for x in out.splitlines() if x.startswith("@@"))
    return json.loads(line[2:])
