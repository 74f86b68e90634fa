"""Stream a directory (or glob) of EXR frames through one session, resumably.

Frames are sorted by the last number in their file name, which is also the index sent to the
server (a missing frame number is a gap: the server starts a fresh history there, as for a camera
cut). Outputs are written atomically under the input names, so an output that exists is done.
A job file in the output folder remembers the session: a resumed run continues that session when
the server still has it at the last finished frame; otherwise it starts a new session and first
re-sends up to `warmup` finished frames (outputs not rewritten) to rebuild the history.

Several view layers of one file (`layers`): one session per layer, each frame sent to every
session; each reply is the whole file with its layer denoised, so the output is the first reply
with every other layer's channels taken from that layer's reply (one file per frame).
"""

from __future__ import annotations

import asyncio
import glob
import json
import os
import re
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

from quietframe.client.api import AsyncClient, Client, FrameResult, QuietframeError
from quietframe.client.protocol import view_layers

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


def file_view_layers(path: Path) -> tuple[str, ...]:
    """View layers of an EXR (every part), from its header only."""
    import OpenEXR

    try:
        parts = OpenEXR.File(str(path), header_only=True).parts
    except Exception as exc:
        raise SequenceError(f"{path} is not a readable EXR file: {exc}") from exc
    return view_layers(c.name for part in parts for c in part.header["channels"])


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


def _matches(job: Job, server: str, pending: int, stored: dict, session: dict, layer) -> bool:
    return (
        stored.get("server") == server
        and session.get("last_index") == job.indices[pending - 1]
        and (session.get("width"), session.get("height")) == (job.width, job.height)
        and session.get("layer") == layer
    )


def _stored_sessions(stored: dict) -> dict[str, str]:
    """Layer key ("" for none) -> session id; job files of one session store `session`."""
    if "sessions" in stored:
        return dict(stored["sessions"])
    return {"": stored["session"]} if stored.get("session") else {}


def merge_layers(replies: dict[str | None, bytes]) -> bytes:
    """One file from the replies of one frame's sessions (one per view layer): the first reply,
    with each other layer's channels (`<layer>.*`) from that layer's reply. Channels keep
    their pixel types; parts, attributes and compression are the first reply's."""
    import io

    import OpenEXR

    (_, first), *others = replies.items()
    base = OpenEXR.File(io.BytesIO(first), separate_channels=True)
    for layer, data in others:
        reply = OpenEXR.File(io.BytesIO(data), separate_channels=True)
        for part in reply.parts:
            for name, channel in part.channels.items():
                if not name.startswith(f"{layer}."):
                    continue
                home = next((p for p in base.parts if name in p.channels), None)
                if home is None:  # a new layer (`denoised_layer`): next to the layer's others
                    home = next((p for p in base.parts if _holds(p, layer)), base.parts[0])
                home.channels[name] = channel
    out = io.BytesIO()
    base.write(out)
    return out.getvalue()


def _holds(part, layer: str) -> bool:
    return any(name.startswith(f"{layer}.") for name in part.channels)


def run_sequence(client: Client, job: Job, server: str, **options) -> str | None:
    """Denoise every pending frame of `job` (options of `arun_sequence`: model, precision,
    warmup, compression, on_progress, layers, further session fields); returns the session id
    (the first layer's when several; None if nothing to do). The sequence protocol is written
    once, in `arun_sequence`; here it drives the sync client (one frame at a time either way)."""
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
    layers: tuple[str | None, ...] = (None,),
    **options,
) -> str | None:
    """`run_sequence` for AsyncClient (one task per sequence). `layers`: view layers to denoise,
    one session each (None: the server's alias table picks the beauty); `options`: further
    session fields (channels, denoised_layer, quality, motion_scale)."""
    pending = job.first_pending()
    if pending == len(job.files):
        return None
    stored = job.read_job()
    sessions: dict[str | None, str] = {}
    warm: dict[str | None, list[int]] = {}
    for layer in layers:
        session = await _reusable_session(client, job, server, pending, stored, layer)
        session_id, warm[layer] = _resume_plan(pending, session, warmup)
        if session_id is None:
            created = await client.create_session(
                job.width,
                job.height,
                model,
                precision=precision,
                compression=compression,
                layer=layer,
                **options,
            )
            session_id = created["id"]
        sessions[layer] = session_id
    for i in sorted({i for positions in warm.values() for i in positions}):
        data = _check_size(job, i)
        for layer, session_id in sessions.items():
            if i in warm[layer]:
                await client.send_frame(session_id, job.indices[i], data)
        _notify(on_progress, Progress(i, job.files[i], None))
    keys = {layer or "": session_id for layer, session_id in sessions.items()}
    for i in range(pending, len(job.files)):
        data = _check_size(job, i)
        results = {
            layer: await client.send_frame(session_id, job.indices[i], data)
            for layer, session_id in sessions.items()
        }
        result = _combined(results)
        job.write_output(i, result.exr)
        job.write_job(server=server, sessions=keys, last_index=job.indices[i])
        _notify(on_progress, Progress(i, job.files[i], result))
    for session_id in sessions.values():
        await client.delete_session(session_id)
    return next(iter(sessions.values()))


def _combined(results: dict[str | None, FrameResult]) -> FrameResult:
    """One frame's results of every layer's session as one (the first's reset and timings)."""
    first = next(iter(results.values()))
    if len(results) == 1:
        return first
    return replace(
        first,
        exr=merge_layers({layer: r.exr for layer, r in results.items()}),
        sanitized=sum(r.sanitized for r in results.values()),
        missing=tuple(sorted({m for r in results.values() for m in r.missing})),
    )


async def _reusable_session(
    client: AsyncClient, job: Job, server: str, pending: int, stored: dict, layer: str | None
):
    session_id = _stored_sessions(stored).get(layer or "")
    if pending == 0 or not session_id:
        return None
    try:
        session = await client.session(session_id)
    except QuietframeError:
        return None
    return session if _matches(job, server, pending, stored, session, layer) else None


def _notify(callback, progress: Progress) -> None:
    if callback is not None:
        callback(progress)
