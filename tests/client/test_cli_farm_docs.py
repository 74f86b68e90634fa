"""The farm examples in docs/farm.md run as written: the Flamenco job type (compiled with node,
Flamenco's `author` and `frameChunker` stubbed) and the Deadline CommandLine plugin files (cut
into chunks as Deadline does), each task's command run as the farm runs it (retry_on_75.py around
the client, the node's paths mapped to this checkout's) against a real server."""

from __future__ import annotations

import json
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import shot

ROOT = Path(__file__).resolve().parents[2]
DOC = (ROOT / "docs" / "farm.md").read_text()
# The docs' paths on a farm node -> this checkout's: Python, the wrapper, the installed client.
CLIENT = str(Path(sys.executable).with_name("quietframe"))
NODE_PATHS = {"python3": sys.executable, "/usr/bin/python3": sys.executable,
              "/opt/quietframe/bin/retry_on_75.py": str(ROOT / "deploy/farm/retry_on_75.py"),
              "quietframe": CLIENT, "/opt/quietframe/bin/quietframe": CLIENT}

FLAMENCO_STUBS = """
function frameChunker(frames, size) {  // Flamenco's: "1001-1006", 4 -> ["1001-1004", ...]
  const [first, last] = frames.split("-").map(Number);
  const chunks = [];
  for (let start = first; start <= last; start += size)
    chunks.push(`${start}-${Math.min(start + size - 1, last)}`);
  return chunks;
}
const tasks = [];
const author = {
  Task: (name, type) => ({ name, commands: [], addCommand(c) { this.commands.push(c); } }),
  Command: (kind, parameters) => ({ kind, ...parameters }),
};
"""


def block(language: str, first_line: str) -> str:
    """The fenced code block of `language` whose first line is `first_line`."""
    for match in re.finditer(rf"```{language}\n(.*?)```", DOC, re.S):
        if match.group(1).startswith(first_line):
            return match.group(1)
    raise AssertionError(f"no {language} block starting {first_line!r} in docs/farm.md")


def write_shot(folder: Path, n: int) -> None:
    folder.mkdir(parents=True)
    for i, data in enumerate(shot(n, "blender")):
        (folder / f"sh010.{1001 + i:04d}.exr").write_bytes(data)


def run(args: list[str]) -> subprocess.CompletedProcess:
    """A task's command as the farm runs it: `python3 retry_on_75.py -- quietframe denoise ...`
    (every example puts the wrapper around the client), the node's paths mapped to this
    checkout's."""
    assert args[:2] == ["python3", "/opt/quietframe/bin/retry_on_75.py"] or args[:2] == [
        "/usr/bin/python3", "/opt/quietframe/bin/retry_on_75.py"], args[:3]
    assert args[2] == "--" and args[3].endswith("quietframe") and args[4] == "denoise", args
    command = [NODE_PATHS.get(arg, arg) if i < 4 else arg for i, arg in enumerate(args)]
    return subprocess.run(command, capture_output=True, text=True, timeout=120)


def test_flamenco_job_type_compiles_and_its_tasks_run(tmp_path, live_server):
    node = shutil.which("node")
    if node is None:
        pytest.skip("node is not installed")
    write_shot(tmp_path / "render", 6)
    settings = {"input": str(tmp_path / "render" / "sh010.####.exr"),
                "output": str(tmp_path / "denoised"), "frames": "1001-1006", "chunk_size": 3,
                "pre_roll": 2, "server": live_server.url, "model": "nbg-2l-3g"}
    script = (FLAMENCO_STUBS + block("js", "// scripts/quietframe_denoise.js")
              + f"const job = {{ settings: {json.dumps(settings)}, tasks: [],"
              " addTask(t) { this.tasks.push(t); } };\n"
              "compileJob(job); console.log(JSON.stringify(job.tasks));")
    compiled = subprocess.run([node, "-e", script], capture_output=True, text=True, timeout=60)
    assert compiled.returncode == 0, compiled.stderr
    tasks = json.loads(compiled.stdout)
    assert [t["name"] for t in tasks] == ["denoise-1001-1003", "denoise-1004-1006"]
    for task in tasks:
        (command,) = task["commands"]
        assert command["kind"] == "exec"
        result = run([command["exe"], *command["args"]])
        assert result.returncode == 0, result.stderr
    assert len(list((tmp_path / "denoised").glob("*.exr"))) == 6


def test_deadline_command_line_runs_per_chunk(tmp_path, live_server):
    job = dict(line.split("=", 1) for line in block("ini", "# quietframe_job.txt").splitlines()
               if "=" in line)
    plugin = dict(line.split("=", 1)
                  for line in block("ini", "# quietframe_plugin.txt").splitlines() if "=" in line)
    assert job["Plugin"] == "CommandLine"
    # a task failing 2/3 (ended at once by the wrapper) fails after a few errors
    assert job["OverrideTaskFailureDetection"] == "true"
    assert int(job["FailureDetectionTaskErrors"]) > 0
    write_shot(tmp_path / "render", 6)
    first, size = 1001, 3  # the doc's Frames/ChunkSize, scaled down to a 6-frame test shot
    arguments = plugin["Arguments"].replace("http://denoise:8000", live_server.url)
    arguments = arguments.replace("/shots/sh010", str(tmp_path))
    for start in range(first, first + 6, size):  # Deadline's chunks, one task each
        line = arguments.replace("<STARTFRAME>", str(start)).replace(
            "<ENDFRAME>", str(start + size - 1))
        result = run([plugin["Executable"], *shlex.split(line)])
        assert result.returncode == 0, result.stderr
    assert len(list((tmp_path / "denoised").glob("*.exr"))) == 6
