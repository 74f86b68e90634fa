"""Stream a sequence of EXR frames (client/frame_source.py) through one session, resumably.

Frames are sent in frame-number order; that number is the index sent to the server (a missing
number is a gap: the server starts a fresh history there, as for a camera cut). Outputs are
written atomically under the input names, each with a record (client/output_records.py) that
says from which source and with which settings it was made: only such an output counts as done
on a rerun; any other file in the way, a re-rendered source or changed flags are refused
(OutputConflict) unless `force`, which redoes them in a new session.

A job file in the output folder (one per frame range, so farm chunks keep their own) remembers
the session: a resumed run continues it when the server still has it at the last finished frame
and the settings are the same; otherwise a new session is first sent up to `warmup` finished
frames (outputs not rewritten) to rebuild the history. A chunk of a longer shot starts the same
way from the `pre_roll` frames before its range (sent, never written), so it does not begin on an
empty history (a visible pop at every chunk boundary). Pre-roll frames not rendered yet are
named (Job.pre_roll_missing) and recorded with the outputs whose history they shorten: a rerun
redoes those once the frames are there (output_records.Status.INCOMPLETE).

With model=auto, each shot keeps one model across chunks and reruns (client/shots.py): decided
once, recorded in the output folder, sent with every frame.

Several view layers of one file (`layers`): one session per layer, each frame sent to every
session; each reply is the whole file with its layer denoised, so the output is the first reply
with every other layer's channels taken from that layer's reply (one file per frame).
"""

from __future__ import annotations

import json
import re
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path

from quietframe.client import output_records as records
from quietframe.client import shots
from quietframe.client.core import AsyncClient, FrameResult, QuietframeError, SyncClient
from quietframe.client.frame_source import (
    SequenceError,
    find_frames,
    frame_number,
    select_frames,
)
from quietframe.client.interrupt import signals_deferred
from quietframe.client.output_records import OutputConflict
from quietframe.client.protocol import view_layers
from quietframe.client.session_fields import AUTO

JOB_FILE = ".quietframe-job.json"
__all__ = ["JOB_FILE", "Job", "OutputConflict", "SequenceError", "find_frames", "frame_number",
           "run_sequence"]


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
    """One run's frames: `files[:first_written]` are pre-roll (sent, never written)."""

    files: list[Path]
    indices: list[int]
    out_dir: Path
    width: int
    height: int
    first_written: int = 0
    missing: tuple[int, ...] = ()  # frame numbers of the range without a file
    # frame numbers that start a new shot: --cut, and frames whose header flags a cut
    cuts: frozenset[int] = frozenset()
    job_file: str = JOB_FILE  # one per frame range: parallel chunks keep their own
    pre_roll_missing: tuple[int, ...] = ()  # pre-roll frame numbers without a file
    # Every frame of the input by number (the whole sequence, not only this run's); empty
    # when the names carry no numbers
    sequence: dict[int, Path] = field(default_factory=dict, repr=False)
    starts: list[int | None] = field(default_factory=list)  # per position: its shot's cut
    # (shot's cut, view layer or "") -> its model's record (client/shots.py), read lazily
    shot_records: dict[tuple[int | None, str], shots.ShotRecord] = field(
        default_factory=dict, repr=False)

    @classmethod
    def plan(
        cls,
        source: str | Path,
        out_dir: str | Path,
        frames: tuple[int, ...] | None = None,
        pre_roll: int = 0,
        cuts: tuple[int, ...] = (),
    ) -> Job:
        chosen = select_frames(source, frames, pre_roll)
        out = Path(out_dir)
        if any(f.parent.resolve() == out.resolve() for f in [*chosen.pre_roll, *chosen.files]):
            raise ValueError("--out must differ from the input folder (outputs keep the names)")
        numbers = [frame_number(f) for f in chosen.files]
        sequence = {} if None in numbers else {frame_number(p): p for p in chosen.found}
        indices = list(range(len(chosen.files))) if None in numbers else numbers
        flagged = set(cuts) | {n for n, f in zip(indices, chosen.files, strict=True)
                               if shots.is_cut_frame(f)}
        start = shots.latest_cut(indices[0], flagged, sequence)  # type: ignore[arg-type]
        # the pre-roll stays in the chunk's shot: a cut inside it starts the history anyway
        pre_roll_files = [f for f in chosen.pre_roll if start is None or frame_number(f) >= start]
        pre_missing = tuple(n for n in chosen.pre_roll_missing if start is None or n >= start)
        files = [*pre_roll_files, *chosen.files]
        indices = [*(frame_number(f) for f in pre_roll_files), *indices]  # type: ignore[misc]
        all_cuts = frozenset(flagged | ({start} if start is not None else set()))
        out.mkdir(parents=True, exist_ok=True)
        width, height = frame_size(chosen.files[0])
        job_file = JOB_FILE
        if frames is not None:
            job_file = f".quietframe-job.{frames[0]}-{frames[-1]}.json"
        return cls(files, indices, out, width, height, len(pre_roll_files), chosen.missing,
                   all_cuts, job_file, pre_missing, sequence,  # type: ignore[arg-type]
                   [_shot_of(n, all_cuts) for n in indices])

    @property
    def written(self) -> range:
        """Positions whose output this job writes."""
        return range(self.first_written, len(self.files))

    def output(self, i: int) -> Path:
        return self.out_dir / self.files[i].name

    def check(self, i: int, settings: dict) -> records.Check:
        """Position `i`'s output against this run: its settings, its shot's model, the source,
        and whether a pre-roll frame missing when it was made is there now."""
        return records.check(self.output(i), self.files[i], settings,
                             self.models_at(i, settings), self.sequence.keys())

    def first_pending(self, settings: dict | None = None) -> int:
        """Position of the first written frame that is not this job's output (len(files) when
        all are done); with `settings` None, the first without an output file at all."""
        for i in self.written:
            if settings is None:
                if not self.output(i).exists():
                    return i
            elif self.check(i, settings).status is not records.Status.DONE:
                return i
        return len(self.files)

    def conflicts(self, settings: dict) -> list[tuple[int, records.Check]]:
        """Outputs in the way: every written position whose file exists but is neither done
        nor one a stopped run of this job was writing."""
        found = []
        for i in self.written:
            check = self.check(i, settings)
            if check.status not in _NOT_IN_THE_WAY:
                found.append((i, check))
        return found

    def is_cut(self, i: int) -> bool:
        """A cut at this frame, or at a missing frame just before it (the shot starts here)."""
        if self.indices[i] in self.cuts:
            return True
        return i > 0 and any(self.indices[i - 1] < c < self.indices[i] for c in self.cuts)

    def shot_of(self, i: int) -> int | None:
        """The cut that starts position `i`'s shot (None: the sequence's first shot)."""
        return self.starts[i] if self.starts else _shot_of(self.indices[i], self.cuts)

    def shots_sent(self) -> list[int | None]:
        """The shots this job's frames belong to, in order (by the cut that starts each)."""
        starts = {self.shot_of(i) for i in range(len(self.files))}
        return sorted(starts, key=lambda start: -1 if start is None else start)

    def shot_record(self, start: int | None, layer: str) -> shots.ShotRecord | None:
        """The recorded model of a shot (None: none yet, or a damaged record, which
        shots.settle_shots replaces)."""
        if (start, layer) not in self.shot_records:
            try:
                record = shots.read_shot(self.out_dir, start, layer)
            except records.DamagedRecord:
                return None
            if record is None:
                return None
            self.shot_records[(start, layer)] = record
        return self.shot_records[(start, layer)]

    def models_at(self, i: int, settings: dict) -> dict[str, str] | None:
        """The model this run uses at position `i` per view layer ("" for none): the named
        one, or (auto) its shot's recorded one; None while a layer's shot has no record."""
        layers = settings.get("layer") or [""]
        if settings.get("model", AUTO) != AUTO:
            return dict.fromkeys(layers, settings["model"])
        found = {layer: self.shot_record(self.shot_of(i), layer) for layer in layers}
        if any(record is None for record in found.values()):
            return None
        return {layer: record.model for layer, record in found.items()}  # type: ignore

    def deciding_frame(self, start: int | None) -> tuple[Path, int]:
        """The frame auto decides a shot from: its first present, the cut's frame itself
        where it is there (any chunk finds the same), as (file, index)."""
        if self.sequence:
            number = min(n for n in self.sequence if start is None or n >= start)
            return self.sequence[number], number
        i = next(i for i, index in enumerate(self.indices) if start is None or index >= start)
        return self.files[i], self.indices[i]

    def short_history(self, i: int) -> tuple[int, ...]:
        """The missing pre-roll frames whose absence position `i`'s history inherits: those
        of the chunk, unless a cut or a gap since the chunk's first frame restarted it."""
        for j in range(self.first_written + 1, i + 1):
            if self.is_cut(j) or self.indices[j] != self.indices[j - 1] + 1:
                return ()
        return self.pre_roll_missing

    def read_job(self, on_damage: Callable[[str], None] | None = None) -> dict:
        """The job file's fields; {} when there is none, or when it is damaged (unreadable,
        not JSON, or a field of another type), which `on_damage` is told: a new session is
        then started, as without a job file."""
        path = self.out_dir / self.job_file
        try:
            stored = json.loads(records.read_small_file(path))
        except FileNotFoundError:
            return {}
        except OSError as exc:
            problem = exc.strerror or str(exc)
        except ValueError:
            problem = "not JSON"
        else:
            problem = job_file_problem(stored)
            if problem is None:
                return stored
        (on_damage or _warn)(f"the job file {path} is damaged ({problem}): ignored, a new "
                             "session is started")
        return {}

    def write_job(self, **fields) -> None:
        records.atomic_write(self.out_dir / self.job_file, json.dumps(fields).encode())

    def write_output(self, i: int, data: bytes, settings: dict | None = None,
                     source: dict | None = None, **extra) -> None:
        """The output and (with `settings`) its record: the source's stamp (`source`, or read
        now) and what made it (output_records.write_output). A signal waits until both are
        written, so that an interrupted run does not need to redo the frame."""
        if settings is None:
            records.atomic_write(self.output(i), data)
            return
        stamp = source or records.source_stamp(self.files[i])
        with signals_deferred():
            records.write_output(self.output(i), data, stamp, settings, **extra)


# A session id as the server makes them (URL-safe): any other text would go into a URL path.
_SESSION_ID = re.compile(r"[A-Za-z0-9_-]{1,256}")


def _is_session_id(value: object) -> bool:
    return isinstance(value, str) and _SESSION_ID.fullmatch(value) is not None


# A job file's fields and their JSON types; any other field is ignored (a newer client's).
_JOB_FIELDS: dict[str, Callable[[object], bool]] = {
    "server": lambda v: isinstance(v, str),
    "session": lambda v: v is None or _is_session_id(v),  # job files of one session
    "sessions": lambda v: isinstance(v, dict) and all(map(_is_session_id, v.values())),
    "last_index": lambda v: v is None or records.is_int(v),
    "settings": lambda v: v is None or isinstance(v, dict),
}


def job_file_problem(stored: object) -> str | None:
    """What makes a job file's JSON unusable (read as untrusted), None if nothing."""
    if not isinstance(stored, dict):
        return "not a JSON object"
    wrong = [name for name, valid in _JOB_FIELDS.items()
             if name in stored and not valid(stored[name])]
    return f"{', '.join(wrong)} of another type" if wrong else None


def _warn(text: str) -> None:
    warnings.warn(text, RuntimeWarning, stacklevel=3)


def _shot_of(index: int, cuts: frozenset[int]) -> int | None:
    """The cut that starts the shot of frame `index` (None: the sequence's first shot)."""
    return max((c for c in cuts if c <= index), default=None)


# Outputs that are not in the way: this job's, none, one this job was writing when it stopped,
# or one it made before its pre-roll frames were rendered.
_NOT_IN_THE_WAY = (records.Status.DONE, records.Status.ABSENT, records.Status.PENDING,
                   records.Status.INCOMPLETE)


def job_settings(
    model: str = "auto",
    precision: str = "input",
    compression: str = "input",
    layers: tuple[str | None, ...] = (None,),
    **options,
) -> dict:
    """What an output is made with, as CLI flag names (output_records compares them): every
    session field that changes the pixels or the file."""
    settings = {"model": model, "precision": precision, "compression": compression,
                "layer": [layer for layer in layers if layer is not None]}
    for name, value in sorted(options.items()):
        name = "model_option" if name == "model_options" else name
        settings[name] = list(value) if isinstance(value, tuple) else value
    return {k: v for k, v in settings.items() if v not in (None, {}, [])}  # unset: left out


def refuse_conflicts(job: Job, settings: dict) -> None:
    """OutputConflict naming what is in the way and the fix, unless nothing is."""
    found = job.conflicts(settings)
    if not found:
        shots.refuse_contradicted(job, settings)  # a shot recorded with another model
        return
    names = ", ".join(job.output(i).name for i, _ in found[:3]) + (
        f" and {len(found) - 3} more" if len(found) > 3 else "")
    kinds = {check.status for _, check in found}
    S = records.Status
    if kinds == {S.CHANGED}:
        raise OutputConflict(
            f"{len(found)} output(s) in {job.out_dir} ({names}) were made with other settings "
            f"({found[0][1].detail}); pass --force to redo them with these flags in a new "
            "session, or use another --out", changed=True)
    damaged_records = sum(c.status is S.FOREIGN and bool(c.detail) for _, c in found)
    why = {
        S.FOREIGN: "were not written by quietframe for these inputs" + (
            f" ({damaged_records} with a damaged record in {records.RECORD_DIR}/: "
            f"{next(c.detail for _, c in found if c.detail)})" if damaged_records else ""),
        S.STALE: "come from source frames that changed since (re-rendered)",
        S.CHANGED: "were made with other settings",
        S.DAMAGED: "are not the files written (another size, or other bytes)",
    }
    reasons = "; ".join(f"{sum(c.status is k for _, c in found)} {why[k]}"
                        for k in S if k in kinds)
    raise OutputConflict(
        f"{len(found)} file(s) in {job.out_dir} ({names}) would be overwritten: {reasons}. "
        "Pass --force to denoise them again (a new session), or use another --out",
        changed=False)


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
    position: int  # 0-based position in job.files
    path: Path
    result: FrameResult | None  # None for warm-up / pre-roll frames (sent to build history)
    session: str | None = None  # the (first layer's) session that made it
    resumed: bool = False  # the first frame of a run that continued an existing session


def _warm_positions(job: Job, pending: int, count: int) -> list[int]:
    """Up to `count` positions before `pending` that rebuild its history: none across a cut
    or a gap (the server resets there anyway)."""
    start = max(0, pending - count)
    for j in range(pending, start, -1):
        if job.is_cut(j) or job.indices[j] != job.indices[j - 1] + 1:
            return list(range(j, pending))
    return list(range(start, pending))


def _matches(job: Job, server: str, pending: int, stored: dict, session: dict, layer) -> bool:
    """A stored session can go on at `pending`: same server and settings, at the previous
    frame, or at `pending` itself (its reply was lost; the server replays it)."""
    return (
        stored.get("server") == server
        and session.get("last_index") in (job.indices[pending - 1], job.indices[pending])
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


def run_sequence(client: SyncClient, job: Job, server: str, **options) -> str | None:
    """Denoise every pending frame of `job` (options of `arun_sequence`); returns the session id
    (the first layer's when several; None if nothing to do). The sequence protocol is written
    once, in `arun_sequence`; here its coroutine is stepped by hand on the sync client, whose
    calls never pause, so it runs in this thread as plain calls: Ctrl-C and SIGTERM stop it in
    the request under way (asyncio.run would defer them to the end of the run)."""
    coroutine = arun_sequence(_Awaitable(client), job, server, **options)
    try:
        coroutine.send(None)
    except StopIteration as finished:
        return finished.value
    coroutine.close()
    raise RuntimeError("the sequence paused on a synchronous client")


class _Awaitable:
    """A sync Client whose methods can be awaited (they run to completion when called)."""

    def __init__(self, client: SyncClient) -> None:
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
    force: bool = False,
    pre_roll: int | None = None,
    on_warning: Callable[[str], None] | None = None,
    **options,
) -> str | None:
    """`run_sequence` for AsyncClient (one task per sequence). `layers`: view layers to denoise,
    one session each (None: the server's alias table picks the beauty); `force`: redo outputs
    that are not this job's (else OutputConflict); `pre_roll`: frames sent before the job's
    first written frame (default: all of job's pre-roll files); `on_warning`: told what the run
    works around (a damaged job file; default: a RuntimeWarning); `options`: further session
    fields (channels, denoised_layer, quality, motion_scale, model_options)."""
    settings = job_settings(model, precision, compression, layers, **options)
    if not force:
        refuse_conflicts(job, settings)
    if job.first_pending(settings) == len(job.files):
        return None
    # Each shot's model before any frame is sent; then outputs of another model are in the way
    named = await shots.settle_shots(client, job, settings, layers, force,
                                     on_warning or _warn, precision=precision,
                                     compression=compression, **options)
    if not force:
        refuse_conflicts(job, settings)
    pending = job.first_pending(settings)
    if pending == len(job.files):
        return None
    stored = {} if force else job.read_job(on_warning)
    if stored.get("settings") not in (None, settings):
        stored = {}  # a session made with other flags is never continued
    sessions: dict[str | None, str] = {}
    fresh: set[str] = set()  # sessions created now: they get the warm-up frames
    for layer in layers:
        model_now = (job.models_at(pending, settings) or {}).get(layer or "")
        session = await _reusable_session(client, job, server, pending, stored, layer,
                                          model_now)
        if session is None:
            created = await client.create_session(
                job.width, job.height, model, precision=precision, compression=compression,
                layer=layer, **options,
            )
            session = created
            fresh.add(created["id"])
        sessions[layer] = session["id"]
    shots.write_deferred(job, named)  # the server has taken the named model
    resumed = not fresh
    count = warmup if pending > job.first_written else (
        job.first_written if pre_roll is None else pre_roll)
    for i in _warm_positions(job, pending, count) if fresh else []:
        data = _check_size(job, i)
        for layer, session_id in sessions.items():
            if session_id in fresh:
                await _send(client, job, session_id, i, data, layer, settings)
        _notify(on_progress, Progress(i, job.files[i], None))
    keys = {layer or "": session_id for layer, session_id in sessions.items()}
    first_session = next(iter(sessions.values()))
    for i in range(pending, len(job.files)):
        data = _check_size(job, i)
        source = records.source_stamp(job.files[i], data)
        results = {
            layer: await _send(client, job, session_id, i, data, layer, settings)
            for layer, session_id in sessions.items()
        }
        result = _combined(results)
        job.write_output(i, result.exr, settings, source, model=result.model,
                         session=first_session, index=job.indices[i],
                         **_made_with(job, i, results))
        job.write_job(server=server, sessions=keys, last_index=job.indices[i], settings=settings)
        _notify(on_progress, Progress(i, job.files[i], result, first_session,
                                      resumed=resumed and i == pending))
    for session_id in sessions.values():
        await client.delete_session(session_id)
    return first_session


async def _send(client: AsyncClient, job: Job, session_id: str, i: int, data: bytes,
                layer: str | None, settings: dict) -> FrameResult:
    """Frame `i` to a layer's session, with its shot's recorded model (model=auto): the server
    takes it where the shot's history starts (a first frame, a cut) instead of choosing."""
    shot = job.shot_record(job.shot_of(i), layer or "") if settings["model"] == AUTO else None
    keep = {"shot_model": shot.model} if shot is not None else {}
    return await client.send_frame(session_id, job.indices[i], data, cut=job.is_cut(i), **keep)


def _made_with(job: Job, i: int, results: dict[str | None, FrameResult]) -> dict:
    """What the output's record says made it besides the flags: the model of each view layer
    (auto resolved), and the pre-roll frames its history lacked."""
    made: dict = {}
    models = {layer or "": r.model.partition(" ")[0] for layer, r in results.items()}
    if all(models.values()):
        made["models"] = models
    if job.short_history(i):
        made["pre_roll_missing"] = list(job.short_history(i))
    return made


def _combined(results: dict[str | None, FrameResult]) -> FrameResult:
    """One frame's results of every layer's session as one (the first's reset and timings)."""
    first = next(iter(results.values()))
    if len(results) == 1:
        return first
    sanitized: dict[str, int] = {}
    for r in results.values():
        for name, count in r.sanitized_buffers.items():
            sanitized[name] = sanitized.get(name, 0) + count
    return replace(
        first,
        exr=merge_layers({layer: r.exr for layer, r in results.items()}),
        sanitized=sum(r.sanitized for r in results.values()),
        sanitized_buffers=sanitized,
        missing=tuple(sorted({m for r in results.values() for m in r.missing})),
    )


async def _reusable_session(
    client: AsyncClient, job: Job, server: str, pending: int, stored: dict, layer: str | None,
    model: str | None = None,
):
    """The stored session of `layer`, where it can go on at `pending` (with `model`, this
    run's model there, where known)."""
    session_id = _stored_sessions(stored).get(layer or "")
    if pending == 0 or not session_id:
        return None
    try:
        session = await client.session(session_id)
    except QuietframeError:
        return None
    in_use = (session.get("model") or {}).get("name") if isinstance(session, dict) else None
    if model is not None and in_use != model:
        return None  # another model's history: the shot's model is not this session's
    return session if _matches(job, server, pending, stored, session, layer) else None


def _notify(callback, progress: Progress) -> None:
    if callback is not None:
        callback(progress)
