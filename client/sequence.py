"""Stream a directory (or glob) of EXR frames through one session, resumably.

Frames are sorted by the last number in their file name, which is also the index sent to the
server (a missing frame number is a gap: the server starts a fresh history there, as for a camera
cut). Outputs are written atomically under the input names, so an output that exists is done.
A job file in the output folder remembers the session: a resumed run continues that session when
the server still has it at the last finished frame; otherwise it starts a new session and first
re-sends up to `warmup` finished frames (outputs not rewritten) to rebuild the history.
"""

from __future__ import annotations

import asyncio
import glob
import json
import os
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from quietframe.client.api import AsyncClient, Client, FrameResult, QuietframeError

JOB_FILE = ".quietframe-job.json"
_NUMBER = re.compile(r"(\d+)(?!.*\d)")


class SequenceError(Exception):
    """The input cannot be streamed as one sequence (no frames, mixed sizes, name clashes)."""


def find_frames(source: str | Path) -> list[Path]:
    """EXR files of a directory or a glob pattern, sorted by frame number then name."""
    path = Path(source)
    if path.is_dir():
        files = [p for p in path.iterdir() if p.suffix.lower() == ".exr" and p.is_file()]
    else:
        files = [Path(p) for p in glob.glob(str(source)) if Path(p).is_file()]
    if not files:
        raise SequenceError(f"no EXR frames in {source}")
    return sorted(files, key=lambda p: (frame_number(p) or 0, p.name))


def frame_number(path: Path) -> int | None:
    match = _NUMBER.search(path.stem)
    return int(match.group(1)) if match else None


def frame_size(path: Path) -> tuple[int, int]:
    """(width, height) of an EXR's data window, from its header only."""
    import OpenEXR

    try:
        header = OpenEXR.File(str(path), header_only=True).header()
    except Exception as exc:
        raise SequenceError(f"{path} is not a readable EXR file: {exc}") from exc
    low, high = header["dataWindow"]
    return int(high[0] - low[0] + 1), int(high[1] - low[1] + 1)


@dataclass
class Job:
    files: list[Path]
    indices: list[int]
    out_dir: Path
    width: int
    height: int

    @classmethod
    def plan(cls, source: str | Path, out_dir: str | Path) -> Job:
        files = find_frames(source)
        out = Path(out_dir)
        if any(f.parent.resolve() == out.resolve() for f in files):
            raise SequenceError("--out must differ from the input folder (outputs keep the names)")
        numbers = [frame_number(f) for f in files]
        if None in numbers:
            indices = list(range(len(files)))  # no frame numbers: the sorted order
        else:
            indices = numbers  # type: ignore[assignment]
            clash = {n for n in indices if indices.count(n) > 1}
            if clash:
                raise SequenceError(f"several files have frame number(s) {sorted(clash)[:5]}")
        out.mkdir(parents=True, exist_ok=True)
        width, height = frame_size(files[0])
        return cls(files, indices, out, width, height)

    def output(self, i: int) -> Path:
        return self.out_dir / self.files[i].name

    def first_pending(self) -> int:
        """Position of the first frame without output (len(files) when all are done)."""
        for i in range(len(self.files)):
            if not self.output(i).exists():
                return i
        return len(self.files)

    def read_job(self) -> dict:
        try:
            return json.loads((self.out_dir / JOB_FILE).read_text())
        except (OSError, ValueError):
            return {}

    def write_job(self, **fields) -> None:
        _atomic_write(self.out_dir / JOB_FILE, json.dumps(fields).encode())

    def write_output(self, i: int, data: bytes) -> None:
        _atomic_write(self.output(i), data)


def _atomic_write(path: Path, data: bytes) -> None:
    temp = path.with_name(f".{path.name}.part")
    temp.write_bytes(data)
    os.replace(temp, path)


def _check_size(job: Job, i: int) -> bytes:
    width, height = frame_size(job.files[i])
    if (width, height) != (job.width, job.height):
        raise SequenceError(
            f"{job.files[i].name} is {width}x{height}, the sequence is {job.width}x{job.height}; "
            "denoise different sizes as separate sequences"
        )
    return job.files[i].read_bytes()


@dataclass
class Progress:
    position: int  # 0-based position in the sorted files
    path: Path
    result: FrameResult | None  # None for warm-up frames (sent only to rebuild history)


def _resume_plan(pending: int, session: dict | None, warmup: int) -> tuple[str | None, list[int]]:
    """(session id to continue or None for a new one, positions to re-send for warm-up)."""
    if pending == 0 or session is None:
        return None, list(range(max(0, pending - warmup), pending))
    return session["id"], []


def _matches(job: Job, server: str, pending: int, stored: dict, session: dict) -> bool:
    return (
        stored.get("server") == server
        and session.get("last_index") == job.indices[pending - 1]
        and (session.get("width"), session.get("height")) == (job.width, job.height)
    )


def run_sequence(client: Client, job: Job, server: str, **options) -> str | None:
    """Denoise every pending frame of `job` (options of `arun_sequence`: model, precision,
    warmup, compression, on_progress); returns the session id (None if nothing to do). The
    sequence protocol is written once, in `arun_sequence`; here it drives the sync client (one
    frame at a time either way)."""
    return asyncio.run(arun_sequence(_Awaitable(client), job, server, **options))


class _Awaitable:
    """A sync Client whose methods can be awaited (they run to completion when called)."""

    def __init__(self, client: Client) -> None:
        self._client = client

    def __getattr__(self, name: str):
        method = getattr(self._client, name)

        async def call(*args, **kwargs):
            return method(*args, **kwargs)

        return call


async def arun_sequence(
    client: AsyncClient,
    job: Job,
    server: str,
    model: str = "auto",
    precision: str = "input",
    warmup: int = 4,
    compression: str = "input",
    on_progress: Callable[[Progress], None] | None = None,
) -> str | None:
    """`run_sequence` for AsyncClient (one task per sequence)."""
    pending = job.first_pending()
    if pending == len(job.files):
        return None
    session = await _reusable_session(client, job, server, pending)
    session_id, warm = _resume_plan(pending, session, warmup)
    if session_id is None:
        created = await client.create_session(
            job.width, job.height, model, precision=precision, compression=compression
        )
        session_id = created["id"]
    for i in warm:
        await client.send_frame(session_id, job.indices[i], _check_size(job, i))
        _notify(on_progress, Progress(i, job.files[i], None))
    for i in range(pending, len(job.files)):
        result = await client.send_frame(session_id, job.indices[i], _check_size(job, i))
        job.write_output(i, result.exr)
        job.write_job(server=server, session=session_id, last_index=job.indices[i])
        _notify(on_progress, Progress(i, job.files[i], result))
    await client.delete_session(session_id)
    return session_id


async def _reusable_session(client: AsyncClient, job: Job, server: str, pending: int):
    stored = job.read_job()
    if pending == 0 or not stored.get("session"):
        return None
    try:
        session = await client.session(stored["session"])
    except QuietframeError:
        return None
    return session if _matches(job, server, pending, stored, session) else None


def _notify(callback, progress: Progress) -> None:
    if callback is not None:
        callback(progress)
