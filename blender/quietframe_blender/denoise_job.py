"""Denoising rendered frames shot by shot, without bpy: the upload loop the add-on's operator runs
on a background thread (or in line in background mode), and the queue that denoises frames while
Blender renders them (the render_write handler feeds it).

Each camera shot gets a session of its own, created on its first frame (size and view layer from
that frame's header) and deleted after its last, so the server's history never carries across a
camera switch. Frames go in frame order with the frame number as the index: a frame not rendered
is a gap, where the server starts the history afresh. Each reply is checked to be an EXR of the
frame's size and written atomically beside its source (or into the chosen folder).

With a look-ahead (`lookahead` k > 0) the session holds k frames back: the reply to a frame
carries the frame k before it, and the frames still held at the end of the shot are finished
there, in order, before the session is deleted.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from . import frame_files
from .server_api import Cancelled, DenoiseError, FrameReply, RetryPolicy, ServerApi
from .shots import Shot


@dataclass(frozen=True)
class JobSettings:
    server_url: str
    token: str | None = None
    model: str = "auto"
    quality: str | None = None  # the session's target for model auto (None: the server's)
    layer: str | None = None  # the view layer to denoise where the files hold several
    out_folder: Path | None = None  # None: beside each render, as <name>_denoised.exr
    lookahead: int = 0  # later frames each frame's denoise uses (the session's `lookahead`)
    timeout_s: float = 300.0
    retry: RetryPolicy = field(default_factory=RetryPolicy)

    def api(self, cancel: threading.Event, on_retry=None) -> ServerApi:
        return ServerApi(self.server_url, self.token, self.timeout_s, self.retry, cancel,
                         on_retry)


@dataclass(frozen=True)
class Progress:
    done: int  # frames denoised so far
    total: int  # frames to denoise (live: frames written so far)
    message: str


@dataclass(frozen=True)
class FrameOutcome:
    frame: int
    source: Path
    output: Path
    session: str
    reset: str  # why the history was (not) used: wire.protocol.Reset values
    model: str


@dataclass
class JobResult:
    outcomes: list[FrameOutcome] = field(default_factory=list)
    missing: list[int] = field(default_factory=list)  # frames of the range not rendered
    shots: int = 0
    cancelled: bool = False
    error: str | None = None  # live jobs keep their error here (no caller to raise to)

    def summary(self) -> str:
        done = len(self.outcomes)
        text = f"denoised {done} frame{'s' * (done != 1)} in {self.shots} shot" \
               f"{'s' * (self.shots != 1)}"
        models = sorted({o.model.split(" ")[0] for o in self.outcomes if o.model})
        if models:
            text += f" ({', '.join(models)})"
        if self.missing:
            text += f"; not rendered, skipped: {_frames_text(self.missing)}"
        if self.cancelled:
            text = "cancelled: " + text
        return text


ProgressCallback = Callable[[Progress], None]


class ShotSession:
    """One camera shot's session on the server: opened on the shot's first frame, each frame
    sent in order and the reply written as the frame it carries, the frames still held
    finished by `finish`, deleted by `close`."""

    def __init__(self, api: ServerApi, settings: JobSettings) -> None:
        self.api, self.settings = api, settings
        self.session_id: str | None = None
        self.size: tuple[int, int] | None = None
        self.held: dict[int, Path] = {}  # frames sent whose reply has not come: their sources

    def send(self, frame: int, source: Path) -> FrameOutcome | None:
        """The outcome of the frame the reply carries; None while the session holds it."""
        if frame < 0:
            raise DenoiseError(f"frame {frame} is negative: the server numbers frames from 0; "
                               "move the animation to frame 0 or later")
        try:
            exr = source.read_bytes()
        except OSError as exc:
            raise DenoiseError(f"could not read {source}: {exc.strerror or exc}") from exc
        header = frame_files.read_header(exr, str(source))
        if self.session_id is None:
            self._open(header, source)
        elif (header.width, header.height) != self.size:
            raise DenoiseError(
                f"{source} is {header.width}x{header.height}, the shot's first frame "
                f"{self.size[0]}x{self.size[1]}: re-render the shot at one resolution"
            )
        self.held[frame] = source
        reply = self.api.send_frame(self.session_id, frame, exr)
        return None if reply is None else self._write(reply)

    def finish(self) -> list[FrameOutcome]:
        """The frames the session still holds, oldest first, finished with what it has."""
        return [self._write(self.api.finish_frame(self.session_id, frame))
                for frame in list(self.held)]

    def _write(self, reply: FrameReply) -> FrameOutcome:
        frame = reply.frame
        oldest = next(iter(self.held), None)
        if frame != oldest:
            raise DenoiseError(f"the server returned frame {frame} where frame {oldest} was "
                               "the oldest sent and not returned: denoise the shot again")
        source = self.held.pop(frame)
        got = frame_files.read_header(reply.exr, f"the server's reply for frame {frame}")
        if (got.width, got.height) != self.size:
            raise DenoiseError(f"the server's reply for frame {frame} is {got.width}x"
                               f"{got.height}, not the frame's size")
        output = frame_files.output_path(source, self.settings.out_folder)
        frame_files.write_atomically(output, reply.exr)
        return FrameOutcome(frame, source, output, self.session_id, reply.reset, reply.model)

    def _open(self, header: frame_files.FrameHeader, source: Path) -> None:
        layer = frame_files.session_layer(header, self.settings.layer, str(source))
        session = self.api.create_session(
            header.width, header.height, model=self.settings.model or "auto",
            quality=self.settings.quality, layer=layer,
            lookahead=self.settings.lookahead or None,
        )
        self.session_id, self.size = session["id"], (header.width, header.height)

    def close(self) -> None:
        if self.session_id is not None:
            self.api.delete_session(self.session_id)
            self.session_id = None


def denoise_shots(
    shots: Sequence[Shot],
    sources: Mapping[int, Path],
    settings: JobSettings,
    on_progress: ProgressCallback | None = None,
    cancel: threading.Event | None = None,
) -> JobResult:
    """Denoise every rendered frame of `shots` (`sources`: frame -> its file), one session per
    shot. Raises DenoiseError on a refusal (the frames before it are written); a set `cancel`
    stops after the frame in flight and returns the result so far, marked cancelled."""
    cancel = cancel or threading.Event()
    report = on_progress or (lambda _: None)
    result = JobResult()
    todo = {s: [f for f in s.frames if frame_files.is_rendered(sources[f])] for s in shots}
    rendered = {f for frames in todo.values() for f in frames}
    result.missing = sorted(f for s in shots for f in s.frames if f not in rendered)
    total = sum(len(frames) for frames in todo.values())
    if total == 0:
        first = sources[shots[0].frames[0]] if shots and shots[0].frames else "?"
        raise DenoiseError(f"no rendered frames to denoise (looked for {first} and the rest of "
                           "the frame range): render the animation first")
    api = settings.api(cancel, lambda why: report(Progress(len(result.outcomes), total, why)))
    for number, shot in enumerate(s for s in shots if todo[s]):
        result.shots += 1
        session = ShotSession(api, settings)
        try:
            for frame in todo[shot]:
                report(Progress(len(result.outcomes), total,
                                f"shot {number + 1}: {shot.describe()}, frame {frame}"))
                if cancel.is_set():
                    raise Cancelled()
                outcome = session.send(frame, sources[frame])
                result.outcomes += [outcome] if outcome is not None else []
            result.outcomes += session.finish()  # the frames held for the look-ahead
        except Cancelled:
            result.cancelled = True
            return result
        finally:
            session.close()
    report(Progress(total, total, result.summary()))
    return result


class LiveJob:
    """Denoises frames as Blender writes them: `add` queues each written frame with the camera
    that rendered it, a thread sends them in order (a new session whenever the camera changes),
    `finish` ends the queue once the render is done. An error stops the uploads (later frames
    are dropped) and is kept in the result."""

    def __init__(self, settings: JobSettings, on_progress: ProgressCallback | None = None) -> None:
        self.settings = settings
        self.cancel = threading.Event()
        self.result = JobResult()
        self._report = on_progress or (lambda _: None)
        self._queue: queue.Queue = queue.Queue()
        self._queued = 0
        self._thread = threading.Thread(target=self._run, name="quietframe-live", daemon=True)
        self._thread.start()

    def add(self, frame: int, source: Path, camera: str) -> None:
        self._queued += 1
        self._queue.put((frame, Path(source), camera))

    def finish(self) -> None:
        self._queue.put(None)

    def wait(self, timeout: float | None = None) -> JobResult:
        self._thread.join(timeout)
        return self.result

    @property
    def running(self) -> bool:
        return self._thread.is_alive()

    def _progress(self, message: str) -> None:
        self._report(Progress(len(self.result.outcomes), self._queued, message))

    def _run(self) -> None:
        api = self.settings.api(self.cancel, self._progress)
        session: ShotSession | None = None
        camera = None
        try:
            while (item := self._queue.get()) is not None:
                frame, source, this_camera = item
                if self._stopped:
                    continue  # stopped: drain the queue
                if session is None or this_camera != camera:
                    if session is not None:  # the last shot's held frames, then its session
                        self._step(session.finish)
                        session.close()
                    session, camera = ShotSession(api, self.settings), this_camera
                    self.result.shots += 1
                self._progress(f"frame {frame} ({this_camera})")
                self._step(session.send, frame, source)
            if session is not None:
                self._step(session.finish)
        finally:
            if session is not None:
                session.close()
            if self.result.error is None:
                self._progress(self.result.summary())

    @property
    def _stopped(self) -> bool:
        return self.result.error is not None or self.result.cancelled

    def _step(self, step: Callable, *args) -> None:
        """One send or finish: the outcomes it returns kept (one, none or a list), a cancel or
        an error kept in the result (a thread of its own: nobody else would see it), after
        which nothing more is sent."""
        if self._stopped:
            return
        try:
            got = step(*args)
            for outcome in got if isinstance(got, list) else [got] if got else []:
                self.result.outcomes.append(outcome)
                self._progress(f"denoised frame {outcome.frame}")
        except Cancelled:
            self.result.cancelled = True
        except Exception as exc:
            known = isinstance(exc, DenoiseError)
            self.result.error = str(exc) if known else f"{type(exc).__name__}: {exc}"
            self._progress(f"stopped: {self.result.error}")


def _frames_text(frames: Sequence[int]) -> str:
    """1, 2, 3, 7 -> "1-3, 7"."""
    runs: list[list[int]] = []
    for f in frames:
        if runs and f == runs[-1][-1] + 1:
            runs[-1].append(f)
        else:
            runs.append([f])
    return ", ".join(str(r[0]) if len(r) == 1 else f"{r[0]}-{r[-1]}" for r in runs)
