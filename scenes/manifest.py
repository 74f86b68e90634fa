"""A sequence's manifest.json, the same way for both renderers: read (refusing a folder rendered
with another config) and written atomically, so a killed render never leaves a torn one."""

from __future__ import annotations

import json
import os
from pathlib import Path

MANIFEST = "manifest.json"


def open_sequence(out: Path, config: dict) -> dict | None:
    """Create `out` and return its manifest (None for a new sequence); ValueError when the
    folder holds a sequence rendered with another config."""
    out.mkdir(parents=True, exist_ok=True)
    path = out / MANIFEST
    manifest = json.loads(path.read_text()) if path.exists() else None
    if manifest and manifest["config"] != config:
        raise ValueError(f"{out}: rendered with {manifest['config']}, asked for {config}")
    return manifest


def write_json(path: Path, data: dict) -> None:
    """Write a manifest atomically (temp file, then rename)."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=1))
    os.replace(tmp, path)
