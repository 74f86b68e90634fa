"""One run's frames going to its sessions (one per view layer) and their outputs coming back:
each reply written as the output of the frame it carries, the job file kept at the last frame
sent, and, in a look-ahead session (session field `lookahead` k > 0), the frames it still holds
finished at the end of the run (client/sequence.py opens the sessions and says what to send).

With look-ahead the reply to frame t carries frame t - k (X-Quietframe-Frame) once the session
holds more than k frames, and is 202 before: frames come back in the order they were sent, so
the run keeps the list of the frames each session holds (`HeldFrames`) and checks every reply
against it, and the job file records that list, so that a rerun can continue the session where
it stopped (`continuation`). A reply carrying a pre-roll, warm-up or post-roll frame is not
written. At the end the held frames are finished in order up to the last one this run writes;
the post-roll frames after it are dropped with the session.
"""

from __future__ import annotations

import io
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, replace
from pathlib import Path

import OpenEXR

from quietframe.client import output_records as records
from quietframe.client.core import AsyncClient, FrameResult, QuietframeError
from quietframe.client.frame_source import SequenceError
from quietframe.client.job import Job, frame_size
from quietframe.client.session_fields import AUTO

# The code of a reply that does not carry the frame the run expects (HeldFramesMismatch)
MISMATCH = "held_frames_mismatch"


class HeldFramesMismatch(QuietframeError):
    """A session answered with another frame than the oldest it holds, or said it holds another
    number of frames than the run sent it: its state is not what this run's job file says."""

    def __init__(self, detail: str) -> None:
        super().__init__(409, MISMATCH, detail + "; the job file no longer names the session, "
                         "so the next run starts a new one")


@dataclass
class Progress:
    position: int  # 0-based position in job.files
    path: Path
    result: FrameResult | None  # None: a frame sent whose output is not written now
    session: str | None = None  # the (first layer's) session that made it
    resumed: bool = False  # the first output of a run that continued an existing session
    # the position of the frame whose reply carried it (look-ahead: a later frame than
    # `position`); None where a finish call returned it
    sent: int | None = None
    held: bool = False  # a frame of the range the session holds back (its output comes later)
    post_roll: bool = False  # a frame after the range, sent for the look-ahead of those before


class HeldFrames:
    """The frames one session holds back, oldest first: every frame sent joins the end, and the
    reply that carries a frame must carry the oldest."""

    def __init__(self, held: Iterable[int] = ()) -> None:
        self.order: deque[int] = deque(held)

    def take(self, reply: FrameResult | None) -> int | None:
        """The index of the frame `reply` carries (None for 202), checked and let go."""
        if reply is None:
            return None
        expected = self.order[0] if self.order else None
        if reply.index != expected:
            raise HeldFramesMismatch(f"the server returned frame {reply.index} where frame "
                                     f"{expected} was the oldest sent and not returned")
        self.order.popleft()
        if reply.pending is not None and reply.pending != len(self.order):
            raise HeldFramesMismatch(f"the server holds {reply.pending} frame(s) back after "
                                     f"frame {reply.index}; this run sent it {len(self.order)} "
                                     "more")
        return reply.index


def continuation(job: Job, stored: dict, pending: int) -> tuple[int, tuple[int, ...]] | None:
    """Where a look-ahead run goes on in the sessions of its job file: (the position it sends
    next, the frames they hold); None where they cannot go on: the job file does not say, or an
    output before the frames they hold is not done (those frames are gone from the sessions)."""
    positions = {index: i for i, index in enumerate(job.indices)}
    last, held = stored.get("last_index"), stored.get("held")
    if last not in positions or not isinstance(held, list) or not all(
            n in positions for n in held):
        return None
    at = positions[last] + 1
    if pending < (positions[held[0]] if held else at):
        return None
    return at, tuple(held)


def check_size(job: Job, i: int) -> bytes:
    """Frame `i`'s bytes; SequenceError where its size is not the sequence's."""
    width, height = frame_size(job.files[i])
    if (width, height) != (job.width, job.height):
        raise SequenceError(
            f"{job.files[i].name} is {width}x{height}, the sequence is {job.width}x{job.height}; "
            "denoise different sizes as separate sequences"
        )
    return job.files[i].read_bytes()


class FrameStream:
    """Sends frames to the run's sessions and writes what comes back: outputs from position
    `first_output` to the job's last written one (earlier frames are warm-up, later post-roll)."""

    def __init__(self, client: AsyncClient, job: Job, server: str,
                 sessions: dict[str | None, str], settings: dict, first_output: int,
                 on_progress: Callable[[Progress], None] | None = None,
                 held: tuple[int, ...] = (), resumed: bool = False) -> None:
        self.client, self.job, self.server, self.settings = client, job, server, settings
        self.sessions, self.first_output = sessions, first_output
        self.on_progress = on_progress or (lambda _: None)
        self.lookahead = int(settings.get("lookahead") or 0)
        self.held = {layer: HeldFrames(held) for layer in sessions}
        self.positions = {index: i for i, index in enumerate(job.indices)}
        self.stamps: dict[int, dict] = {}  # sources of the frames held, stamped when read
        self.first_session = next(iter(sessions.values()))
        self.resumed, self.delivered = resumed, False

    async def warm(self, i: int, layers: Iterable[str | None]) -> None:
        """Frame `i` to the sessions of `layers` only, to rebuild their history (not written)."""
        data = check_size(self.job, i)
        results = {layer: await self._send(layer, i, data) for layer in layers}
        self._carried(results)  # a warm-up frame's reply carries an earlier one, never written
        self.on_progress(Progress(i, self.job.files[i], None, sent=i))

    async def send(self, i: int) -> None:
        """Frame `i` to every session; the output its replies carry written, the job file
        brought up to it."""
        data = check_size(self.job, i)
        if self._writes(i):
            self.stamps[self.job.indices[i]] = records.source_stamp(self.job.files[i], data)
        results = {layer: await self._send(layer, i, data) for layer in self.sessions}
        carried = self._carried(results)
        told = self._deliver(carried, results, sent=i) if carried is not None else None
        self._write_job(self.job.indices[i])
        if told is not None:
            self.on_progress(told)
        if i >= self.job.end_written:
            self.on_progress(Progress(i, self.job.files[i], None, sent=i, post_roll=True))
        elif carried is None:
            self.on_progress(Progress(i, self.job.files[i], None, sent=i, held=True))

    async def finish(self, last_index: int | None) -> None:
        """The held frames finished in order, up to the last one this run writes."""
        orders = {tuple(held.order) for held in self.held.values()}
        if len(orders) > 1:
            raise self._mismatch("the view layers' sessions hold different frames")
        (order,) = orders
        wanted = [n for n in order if self._writes(self.positions[n])]
        for index in order[: order.index(wanted[-1]) + 1] if wanted else ():
            results = {layer: await self.client.finish_frame(session_id, index)
                       for layer, session_id in self.sessions.items()}
            carried = self._carried(results)
            told = self._deliver(carried, results, sent=None) if carried is not None else None
            self._write_job(last_index)
            if told is not None:
                self.on_progress(told)

    # ---- the pieces -------------------------------------------------------------------

    def _writes(self, i: int) -> bool:
        return self.first_output <= i < self.job.end_written

    async def _send(self, layer: str | None, i: int, data: bytes) -> FrameResult | None:
        """Frame `i` to a layer's session, with its shot's recorded model (model=auto): the
        server takes it where the shot's history starts (a first frame, a cut) instead of
        choosing."""
        job, session_id = self.job, self.sessions[layer]
        shot = (job.shot_record(job.shot_of(i), layer or "")
                if self.settings["model"] == AUTO else None)
        keep = {"shot_model": shot.model} if shot is not None else {}
        self.held[layer].order.append(job.indices[i])
        return await self.client.send_frame(session_id, job.indices[i], data,
                                            cut=job.is_cut(i), **keep)

    def _carried(self, results: dict[str | None, FrameResult | None]) -> int | None:
        """The index of the frame the replies carry (the same for every layer), or None."""
        try:
            carried = {self.held[layer].take(reply) for layer, reply in results.items()}
        except HeldFramesMismatch:
            self._forget_sessions()
            raise
        if len(carried) > 1:
            shown = ", ".join("nothing" if n is None else str(n) for n in carried)
            raise self._mismatch(f"the view layers' sessions returned {shown} for one frame")
        return carried.pop()

    def _mismatch(self, detail: str) -> HeldFramesMismatch:
        self._forget_sessions()
        return HeldFramesMismatch(detail)

    def _forget_sessions(self) -> None:
        """A job file without sessions: a rerun does not continue sessions in another state."""
        self.job.write_job(server=self.server, settings=self.settings)

    def _deliver(self, index: int, results: dict[str | None, FrameResult | None],
                 sent: int | None) -> Progress | None:
        """The output of frame `index` written where this run writes it; its Progress."""
        i = self.positions[index]
        if not self._writes(i):
            self.stamps.pop(index, None)
            return None
        result = _combined({layer: r for layer, r in results.items() if r is not None})
        source = self.stamps.pop(index, None) or records.source_stamp(self.job.files[i])
        self.job.write_output(i, result.exr, self.settings, source, model=result.model,
                              session=self.first_session, index=index,
                              **self._made_with(i, results))
        resumed = self.resumed and not self.delivered
        self.delivered = True
        return Progress(i, self.job.files[i], result, self.first_session, resumed=resumed,
                        sent=sent)

    def _made_with(self, i: int, results: dict[str | None, FrameResult | None]) -> dict:
        """What the output's record says made it besides the flags: the model of each view
        layer (auto resolved), and the pre- and post-roll frames it lacked."""
        made: dict = {}
        models = {layer or "": r.model.partition(" ")[0] for layer, r in results.items() if r}
        if all(models.values()):
            made["models"] = models
        if self.job.short_history(i):
            made["pre_roll_missing"] = list(self.job.short_history(i))
        if self.job.short_lookahead(i, self.lookahead):
            made["post_roll_missing"] = list(self.job.short_lookahead(i, self.lookahead))
        return made

    def _write_job(self, last_index: int | None) -> None:
        keys = {layer or "": session_id for layer, session_id in self.sessions.items()}
        held = {"held": list(next(iter(self.held.values())).order)} if self.lookahead else {}
        self.job.write_job(server=self.server, sessions=keys, last_index=last_index,
                           settings=self.settings, **held)


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


def merge_layers(replies: dict[str | None, bytes]) -> bytes:
    """One file from the replies of one frame's sessions (one per view layer): the first reply,
    with each other layer's channels (`<layer>.*`) from that layer's reply. Channels keep
    their pixel types; parts, attributes and compression are the first reply's."""
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
