"""One model per shot: `auto` decides once for a shot, and every chunk and rerun of it keeps
that decision, recorded next to the outputs in `<out>/.quietframe/`.

A farm denoises a shot in chunks, each its own run and session, and the server's `auto` chooses
from a session's first frame: chunks that began on frames of another noise level (a range
re-rendered at more samples) chose other models, and the look changed mid-shot. Here a shot's
model is decided once, from the shot's first frame present in the input (the lowest-numbered
frame of the sequence, or the cut that starts the shot), by the server itself (a throwaway
`auto` session sent that frame alone: the server has no other way to ask), and recorded in
`.shot[.cut<N>][.layer-<name>].json`. Every frame is then sent with its shot's recorded model
(`shot_model`), which the server takes wherever the shot's history starts instead of choosing.

Chunks that start at once agree without waiting for each other: each decides from the same frame
(the choice is a function of the frame and the flags), and the record is created exclusively,
so where two raced, the later adopts the first's record before it sends a frame. `--model X`
records X where nothing is recorded; a recorded model the run's flags contradict is refused as
changed flags (`--force` records the run's instead).

A shot starts at the sequence's first frame and at each cut: `--cut FRAME`, or a frame whose
header carries the `quietframe.cut` attribute (read here too, back from the run's first frame to
the previous cut, so that every chunk finds the same shot). The server chooses afresh at a cut,
so each shot has its own record.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol
from urllib.parse import quote

import OpenEXR

from quietframe.client import output_records as records
from quietframe.client.core import AsyncClient
from quietframe.client.output_records import OutputConflict
from quietframe.client.session_fields import AUTO
from quietframe.wire.protocol import CUT_ATTRIBUTE

SHOT_VERSION = 1
# The flags that steer auto's choice (besides the view layer, which has its own record)
STEERING = ("quality", "latency_ms", "model_option", "channels", "motion_scale")
CUT_WORDS = ("1", "true", "yes", "cut")  # as the server reads the attribute (exr_header)


@dataclass(frozen=True)
class ShotRecord:
    """A shot's model and how it was decided."""

    model: str
    choice: dict | None = None  # the server's choice (auto); None where --model named it
    steering: dict = field(default_factory=dict)  # the flags auto chose with
    decided_from: str | None = None  # the frame auto chose from

    def to_json(self) -> bytes:
        body = {"version": SHOT_VERSION, "model": self.model, "choice": self.choice,
                "steering": self.steering, "decided_from": self.decided_from}
        return json.dumps(body, indent=1, sort_keys=True).encode()

    @classmethod
    def parse(cls, raw: object) -> ShotRecord:
        """DamagedRecord naming what is not as written (read as untrusted input)."""
        if not isinstance(raw, dict) or raw.get("version") != SHOT_VERSION:
            raise records.DamagedRecord(f"not a shot record of version {SHOT_VERSION}")
        model, choice, steering = raw.get("model"), raw.get("choice"), raw.get("steering")
        decided_from = raw.get("decided_from")
        if not isinstance(model, str) or not model:
            raise records.DamagedRecord("model is not a name")
        if not (choice is None or isinstance(choice, dict)) or not isinstance(steering, dict):
            raise records.DamagedRecord("choice or steering is not an object")
        if not (decided_from is None or isinstance(decided_from, str)):
            raise records.DamagedRecord("decided_from is not a file name")
        return cls(model, choice, steering, decided_from)


class Job(Protocol):
    """What settling a run's shots reads of its job (sequence.Job, which reads the shots' records
    through this module)."""

    out_dir: Path
    width: int
    height: int
    shot_records: dict[tuple[int | None, str], ShotRecord]

    def shots_sent(self) -> list[int | None]: ...

    def shot_record(self, start: int | None, layer: str) -> ShotRecord | None: ...

    def deciding_frame(self, start: int | None) -> tuple[Path, int]: ...


def shot_file(start: int | None, layer: str) -> str:
    """The record's name in `.quietframe/` for the shot from cut `start` (None: from the
    sequence's first frame) and view layer `layer` ("" for none). Records of outputs are
    `<output name>.json`: a leading dot keeps the two apart."""
    name = ".shot" if start is None else f".shot.cut{start}"
    if layer:
        name += ".layer-" + quote(layer, safe="")
    return name + ".json"


def read_shot(out_dir: Path, start: int | None, layer: str) -> ShotRecord | None:
    """The shot's record; None if there is none, DamagedRecord if that file is no record."""
    path = out_dir / records.RECORD_DIR / shot_file(start, layer)
    try:
        text = records.read_small_file(path)
    except FileNotFoundError:
        return None
    except OSError as exc:
        raise records.DamagedRecord(exc.strerror or str(exc)) from exc
    try:
        return ShotRecord.parse(json.loads(text))
    except ValueError as exc:
        if isinstance(exc, records.DamagedRecord):
            raise
        raise records.DamagedRecord("not JSON") from exc


def steering(settings: dict) -> dict:
    return {k: settings[k] for k in STEERING if k in settings}


def is_cut_frame(path: Path) -> bool:
    """Whether the frame's header flags a camera cut (`quietframe.cut`); False for a file
    that cannot be read (the pre-flight reports it)."""
    try:
        flag = OpenEXR.File(str(path), header_only=True).parts[0].header.get(CUT_ATTRIBUTE)
    except Exception:
        return False
    if isinstance(flag, str):
        return flag.strip().lower() in CUT_WORDS
    return isinstance(flag, int) and not isinstance(flag, bool) and flag != 0


def latest_cut(first: int, flagged: set[int], frames: dict[int, Path]) -> int | None:
    """The last cut at or before frame `first`: a --cut, or a frame whose header flags one
    (headers read back from `first`, down to the latest --cut at most)."""
    floor = max((c for c in flagged if c <= first), default=None)
    earlier = sorted((n for n in frames if n <= first and (floor is None or n > floor)),
                     reverse=True)
    return next((n for n in earlier if is_cut_frame(frames[n])), floor)


# ---- settling a run's shots ---------------------------------------------------------------


@dataclass(frozen=True)
class Deferred:
    """A named model's shot record, written once the server has taken the name (its session
    exists): a mistyped --model must not become the shot's model."""

    name: str
    record: ShotRecord
    replace: bool  # over a record this run contradicts (--force) or a damaged one


async def settle_shots(client: AsyncClient, job: Job, settings: dict,
                       layers: tuple[str | None, ...], force: bool,
                       on_warning: Callable[[str], None], **session_fields) -> list[Deferred]:
    """The model of every shot `job` sends frames of, per view layer, settled before any is
    sent (job.shot_records): auto's decided and recorded, a named one's returned to record
    once its sessions exist (write_deferred). OutputConflict where a recorded model contradicts
    this run's flags (unless `force`, which records this run's). `session_fields`: of the run's
    sessions."""
    deferred: list[Deferred] = []
    for start in job.shots_sent():
        for layer in layers:
            record = await _settle(client, job, start, layer, settings, force, on_warning,
                                   session_fields, deferred)
            if record is not None:
                job.shot_records[(start, layer or "")] = record
    return deferred


def write_deferred(job: Job, deferred: list[Deferred]) -> None:
    """The named models' shot records (where another run recorded one meanwhile, it stays)."""
    for shot in deferred:
        if shot.replace:
            records.replace_in_records(job.out_dir, shot.name, shot.record.to_json())
        else:
            records.create_in_records(job.out_dir, shot.name, shot.record.to_json())


async def _settle(client: AsyncClient, job: Job, start: int | None, layer: str | None,
                  settings: dict, force: bool, on_warning: Callable[[str], None],
                  session_fields: dict, deferred: list[Deferred]) -> ShotRecord | None:
    key = layer or ""
    name = shot_file(start, key)
    damaged = False
    for _ in range(2):  # once more where another chunk recorded the shot meanwhile
        try:
            recorded = read_shot(job.out_dir, start, key)
        except records.DamagedRecord as exc:
            on_warning(f"the shot record {job.out_dir / records.RECORD_DIR / name} is damaged "
                       f"({exc}): ignored, the shot's model is decided again")
            recorded, damaged = None, True
        if recorded is not None:
            conflict = contradiction(recorded, settings)
            if conflict is None:
                return recorded
            if not force:
                raise _refusal(job, start, name, recorded, settings, conflict)
        decided = await _decide(client, job, start, layer, settings, session_fields)
        if decided is None:
            return None  # no choice to record (the server said none): plain auto
        if decided.choice is None:  # a named model
            deferred.append(Deferred(name, decided, recorded is not None or damaged))
            return decided
        if recorded is not None or damaged:
            records.replace_in_records(job.out_dir, name, decided.to_json())
            return decided
        if records.create_in_records(job.out_dir, name, decided.to_json()):
            return decided
    raise RuntimeError(f"{name} changed twice while this run read it")


def refuse_contradicted(job: Job, settings: dict) -> None:
    """OutputConflict where a shot `job` sends frames of has a recorded model that this run's
    flags contradict (read from the records alone: a dry run says it too)."""
    for start in job.shots_sent():
        for layer in settings.get("layer") or [""]:
            recorded = job.shot_record(start, layer)
            conflict = None if recorded is None else contradiction(recorded, settings)
            if conflict is not None:
                raise _refusal(job, start, shot_file(start, layer), recorded, settings, conflict)


def contradiction(recorded: ShotRecord, settings: dict) -> str | None:
    """What in this run's flags contradicts a shot's record: another named model, or auto
    with other flags than those it chose with (a recorded named model is kept by auto)."""
    model = settings.get("model", AUTO)
    if model != AUTO:
        return None if model == recorded.model else f"--model {recorded.model} -> {model}"
    if recorded.choice is not None and recorded.steering != steering(settings):
        return records.differences(recorded.steering, steering(settings))
    return None


def _refusal(job: Job, start: int | None, name: str, recorded: ShotRecord, settings: dict,
             conflict: str) -> OutputConflict:
    shot = "the sequence's start" if start is None else f"the cut at frame {start}"
    how = (f"chosen by auto from {recorded.decided_from}" if recorded.choice is not None
           else f"named by --model {recorded.model}")
    return OutputConflict(
        f"the shot from {shot} is denoised with {recorded.model} ({how}; "
        f"{job.out_dir / records.RECORD_DIR / name}), and this run's flags differ ({conflict}): "
        "one shot keeps one model. Pass the recorded flags (or --model "
        f"{recorded.model}), or --force to record this run's model for the shot (then redo "
        "its other chunks with --force too)", changed=True)


async def _decide(client: AsyncClient, job: Job, start: int | None, layer: str | None,
                  settings: dict, session_fields: dict) -> ShotRecord | None:
    """The shot's model: the run's --model, or auto's choice from the shot's first frame
    present (a throwaway session sent that frame alone); None where the server gives none."""
    model = settings.get("model", AUTO)
    if model != AUTO:
        return ShotRecord(model)
    frame, index = job.deciding_frame(start)
    # auto chooses at the frame itself; a look-ahead would only hold it back
    fields = {name: value for name, value in session_fields.items() if name != "lookahead"}
    session = await client.create_session(job.width, job.height, AUTO, layer=layer, **fields)
    try:
        await client.send_frame(session["id"], index, frame.read_bytes())
        choice = (await client.session(session["id"])).get("choice")
    finally:
        await client.delete_session(session["id"])
    if not (isinstance(choice, dict) and isinstance(choice.get("model"), str)):
        return None
    return ShotRecord(choice["model"], choice, steering(settings), frame.name)
