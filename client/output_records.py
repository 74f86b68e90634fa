"""What makes an output "done": a record written next to it, per frame, in `<out>/.quietframe/`.

A file in the output folder counts as this job's output only if its record names the same
source (size and mtime, or else the same SHA-256: a touched but identical render still counts)
and the same settings (model, options, channel flags), and the output still has the size it
was written with. One record per frame, not one manifest per folder: farm chunks of one shot
write into one folder at the same time and must not rewrite each other's bookkeeping.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass
from enum import Enum
from pathlib import Path

RECORD_DIR = ".quietframe"
RECORD_VERSION = 1


class Status(str, Enum):
    DONE = "done"  # this job's output for this source
    ABSENT = "absent"  # no output yet
    FOREIGN = "foreign"  # a file quietframe did not write (or wrote before records existed)
    STALE = "stale"  # written from a source file that has changed since (a re-render)
    CHANGED = "changed"  # written with other settings (model, options, channel flags)
    DAMAGED = "damaged"  # the output's size differs from what was written (truncated copy)


@dataclass(frozen=True)
class Check:
    status: Status
    detail: str = ""  # for CHANGED: which settings differ


def record_path(output: Path) -> Path:
    return output.parent / RECORD_DIR / f"{output.name}.json"


def source_stamp(source: Path, data: bytes | None = None) -> dict:
    """Size, mtime and SHA-256 of a source file (`data`: its bytes, already read)."""
    stat = source.stat()
    digest = hashlib.sha256(data if data is not None else source.read_bytes()).hexdigest()
    return {"name": source.name, "size": stat.st_size, "mtime_ns": stat.st_mtime_ns,
            "sha256": digest}


def write_record(output: Path, source: dict, settings: dict, size: int, **extra) -> None:
    """After the output itself is in place (so a record never vouches for a missing file)."""
    path = record_path(output)
    path.parent.mkdir(exist_ok=True)
    body = {"version": RECORD_VERSION, "source": source, "settings": settings,
            "output_size": size, **extra}
    temp = path.with_name(f".{path.name}.part")
    temp.write_text(json.dumps(body, indent=1, sort_keys=True))
    os.replace(temp, path)


def read_record(output: Path) -> dict | None:
    try:
        record = json.loads(record_path(output).read_text())
    except (OSError, ValueError):
        return None
    return record if isinstance(record, dict) else None


def check(output: Path, source: Path, settings: dict) -> Check:
    """Whether `output` is this job's output of `source` made with `settings`."""
    if not output.exists():
        return Check(Status.ABSENT)
    record = read_record(output)
    if record is None or record.get("version") != RECORD_VERSION:
        return Check(Status.FOREIGN)
    if record.get("settings") != settings:
        return Check(Status.CHANGED, differences(record.get("settings") or {}, settings))
    if not _same_source(record.get("source") or {}, source):
        return Check(Status.STALE)
    if output.stat().st_size != record.get("output_size"):
        return Check(Status.DAMAGED)
    return Check(Status.DONE)


def _same_source(stamp: dict, source: Path) -> bool:
    stat = source.stat()
    if stat.st_size != stamp.get("size"):
        return False
    if stat.st_mtime_ns == stamp.get("mtime_ns"):
        return True
    return hashlib.sha256(source.read_bytes()).hexdigest() == stamp.get("sha256")


def differences(before: dict, now: dict) -> str:
    """`--model auto -> oidn-frame; --channels none -> {...}` for the settings that differ."""
    keys = sorted(set(before) | set(now))
    changed = [k for k in keys if before.get(k) != now.get(k)]
    return "; ".join(
        f"{flag(k)} {_shown(before.get(k))} -> {_shown(now.get(k))}" for k in changed
    )


def flag(setting: str) -> str:
    return "--" + setting.replace("_", "-")


def _shown(value) -> str:
    if value is None or value == {} or value == []:
        return "(unset)"
    return value if isinstance(value, str) else json.dumps(value, sort_keys=True)
