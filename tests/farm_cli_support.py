"""Helpers of the farm CLI tests: a Blender-named shot on disk, the `denoise` command line, its
JSON events, and a run beside its `--dry-run`."""

from __future__ import annotations

import json
from pathlib import Path

from conftest import shot

from quietframe.client.cli import main


def write_shot(folder: Path, n: int, start: int = 1001) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for i, data in enumerate(shot(n, "blender")):
        (folder / f"shot.{start + i:04d}.exr").write_bytes(data)


def events(out: str) -> list[dict]:
    return [json.loads(line) for line in out.splitlines() if line.startswith("{")]


def denoise(server_url: str, source: Path, out: Path, *flags: str) -> list[str]:
    return ["denoise", "--server", server_url, str(source), "--out", str(out), "--quiet",
            *flags]


def run_and_dry_run(capsys, args: list[str]) -> tuple[tuple[int, str], tuple[int, str]]:
    """(exit code, stderr) of the run, then of the same command with --dry-run."""
    code = main(args)
    run = (code, capsys.readouterr().err)
    code = main([*args, "--dry-run"])
    return run, (code, capsys.readouterr().err)


def error_lines(err: str) -> list[str]:
    return [line for line in err.splitlines() if "error:" in line or "--" in line]
