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

With look-ahead (session field `lookahead` k > 0) a reply carries the frame k before the one sent
and the run finishes the frames still held at its end (client/frame_stream.py); a chunk sends
the post-roll frames after its range (sent, never written) so that its last frames see their k
later frames too, and records the missing ones as it does the pre-roll's.

With model=auto, each shot keeps one model across chunks and reruns (client/shots.py): decided
once, recorded in the output folder, sent with every frame.

Several view layers of one file (`layers`): one session per layer, each frame sent to every
session; each reply is the whole file with its layer denoised, so the output is the first reply
with every other layer's channels taken from that layer's reply (one file per frame).
"""

from __future__ import annotations

from collections.abc import Callable

from quietframe.client import output_records as records
from quietframe.client import shots
from quietframe.client.core import AsyncClient, QuietframeError, SyncClient
from quietframe.client.frame_source import SequenceError, find_frames, frame_number
from quietframe.client.frame_stream import FrameStream, Progress, continuation, merge_layers
from quietframe.client.job import JOB_FILE, Job, file_view_layers, warn
from quietframe.client.output_records import OutputConflict

__all__ = ["JOB_FILE", "Job", "OutputConflict", "Progress", "SequenceError", "file_view_layers",
           "find_frames", "frame_number", "merge_layers", "run_sequence"]

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


def warm_positions(job: Job, pending: int, count: int) -> list[int]:
    """Up to `count` positions before `pending` that rebuild its history: none across a cut
    or a gap (the server resets there anyway)."""
    start = max(0, pending - count)
    for j in range(pending, start, -1):
        if job.is_cut(j) or job.indices[j] != job.indices[j - 1] + 1:
            return list(range(j, pending))
    return list(range(start, pending))


def _matches(job: Job, server: str, at: int, stored: dict, session: dict, layer) -> bool:
    """A stored session can go on at position `at` (the next frame to send): same server and
    settings, at the previous frame, or at `at` itself (its reply was lost; the server replays
    it)."""
    here = job.indices[at] if at < len(job.files) else None
    return (
        stored.get("server") == server
        and session.get("last_index") in (job.indices[at - 1], here)
        and (session.get("width"), session.get("height")) == (job.width, job.height)
        and session.get("layer") == layer
    )


def _stored_sessions(stored: dict) -> dict[str, str]:
    """Layer key ("" for none) -> session id; job files of one session store `session`."""
    if "sessions" in stored:
        return dict(stored["sessions"])
    return {"": stored["session"]} if stored.get("session") else {}


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
    on_session: Callable[[str], None] | None = None,
    **options,
) -> str | None:
    """`run_sequence` for AsyncClient (one task per sequence). `layers`: view layers to denoise,
    one session each (None: the server's alias table picks the beauty); `force`: redo outputs
    that are not this job's (else OutputConflict); `pre_roll`: frames sent before the job's
    first written frame (default: all of job's pre-roll files); `on_warning`: told what the run
    works around (a damaged job file; default: a RuntimeWarning); `on_session`: told the id of
    each session the run sends its frames to, as it is created or continued (the run deletes
    them once done; a caller whose run stops for good may delete them too); `options`:
    further session fields (channels, denoised_layer, quality, motion_scale, model_options,
    lookahead: then the job's post-roll frames are sent too, and the frames the sessions still
    hold at the end are finished)."""
    settings = job_settings(model, precision, compression, layers, **options)
    if not force:
        refuse_conflicts(job, settings)
    if job.first_pending(settings) == job.end_written:
        return None
    # Each shot's model before any frame is sent; then outputs of another model are in the way
    named = await shots.settle_shots(client, job, settings, layers, force,
                                     on_warning or warn, precision=precision,
                                     compression=compression, **options)
    if not force:
        refuse_conflicts(job, settings)
    pending = job.first_pending(settings)
    if pending == job.end_written:
        return None
    stored = {} if force else job.read_job(on_warning)
    if stored.get("settings") not in (None, settings):
        stored = {}  # a session made with other flags is never continued
    lookahead = int(options.get("lookahead") or 0)
    start, held = pending, ()  # the first position to send, the frames the sessions hold
    if lookahead:
        going_on = continuation(job, stored, pending)
        stored = stored if going_on is not None else {}
        start, held = going_on or (pending, ())
    found: dict[str | None, dict | None] = {}
    for layer in layers:
        model_now = (job.models_at(pending, settings) or {}).get(layer or "")
        found[layer] = await _reusable_session(client, job, server, start, stored, layer,
                                               model_now)
    if lookahead and None in found.values():  # every layer's session goes on, or none does:
        for session in filter(None, found.values()):  # they must hold the same frames
            await client.delete_session(session["id"])
        found = dict.fromkeys(layers)
        start, held = pending, ()
    sessions: dict[str | None, str] = {}
    fresh: set[str] = set()  # sessions created now: they get the warm-up frames
    for layer in layers:
        session = found[layer]
        if session is None:
            session = await client.create_session(
                job.width, job.height, model, precision=precision, compression=compression,
                layer=layer, **options,
            )
            fresh.add(session["id"])
        sessions[layer] = session["id"]
        if on_session is not None:
            on_session(session["id"])
    shots.write_deferred(job, named)  # the server has taken the named model
    stream = FrameStream(client, job, server, sessions, settings, pending, on_progress, held,
                         resumed=not fresh)
    count = warmup if pending > job.first_written else (
        job.first_written if pre_roll is None else pre_roll)
    for i in warm_positions(job, pending, count) if fresh else []:
        await stream.warm(i, [layer for layer, sid in sessions.items() if sid in fresh])
    # the post-roll only where a session looks ahead: otherwise no output uses it
    end = len(job.files) if lookahead else job.end_written
    for i in range(start, end):
        await stream.send(i)
    await stream.finish(job.indices[end - 1] if start < end else stored.get("last_index"))
    for session_id in sessions.values():
        await client.delete_session(session_id)
    return next(iter(sessions.values()))


async def _reusable_session(
    client: AsyncClient, job: Job, server: str, pending: int, stored: dict, layer: str | None,
    model: str | None = None,
):
    """The stored session of `layer`, where it can go on at position `pending` (the next frame
    to send; with `model`, this run's model there, where known)."""
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

