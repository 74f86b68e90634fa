"""One run's frames and what it finds and leaves in the output folder: the frames to send (the
chunk's range, its pre-roll and its post-roll), their shots, each output's state against this
run (done, in the way, or to write), and the job file that remembers the run's sessions
(client/sequence.py sends the frames)."""

from __future__ import annotations

import json
import os
import re
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import OpenEXR

from quietframe.client import output_records as records
from quietframe.client import shots
from quietframe.client.frame_source import SequenceError, frame_number, select_frames
from quietframe.client.interrupt import signals_deferred
from quietframe.client.session_fields import AUTO
from quietframe.wire.protocol import view_layers

JOB_FILE = ".quietframe-job.json"
def file_view_layers(path: Path) -> tuple[str, ...]:
    """View layers of an EXR (every part), from its header only."""
    try:
        parts = OpenEXR.File(str(path), header_only=True).parts
    except Exception as exc:
        raise SequenceError(f"{path} is not a readable EXR file: {exc}") from exc
    return view_layers(c.name for part in parts for c in part.header["channels"])


def frame_size(path: Path) -> tuple[int, int]:
    """(width, height) of an EXR's data window, from its header only."""
    try:
        header = OpenEXR.File(str(path), header_only=True).header()
    except Exception as exc:
        raise SequenceError(f"{path} is not a readable EXR file: {exc}") from exc
    low, high = header["dataWindow"]
    return int(high[0] - low[0] + 1), int(high[1] - low[1] + 1)


@dataclass
class Job:
    """One run's frames: `files[:first_written]` are pre-roll (sent, never written), the last
    `post_roll` post-roll (sent for the look-ahead of the frames before them, never written)."""

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
    post_roll: int = 0  # post-roll files at the end of `files`
    post_roll_missing: tuple[int, ...] = ()  # post-roll frame numbers without a file

    @classmethod
    def plan(
        cls,
        source: str | Path,
        out_dir: str | Path,
        frames: tuple[int, ...] | None = None,
        pre_roll: int = 0,
        cuts: tuple[int, ...] = (),
        create_out: bool = True,
        post_roll: int = 0,
    ) -> Job:
        chosen = select_frames(source, frames, pre_roll, post_roll)
        out = Path(out_dir)
        sent = [*chosen.pre_roll, *chosen.files, *chosen.post_roll]
        if any(f.parent.resolve() == out.resolve() for f in sent):
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
        # the post-roll stays in the shot of the chunk's last frame: a frame after a cut does
        # not look back across it
        after, post_missing = _before_next_cut(indices[-1], chosen.post_roll,
                                               chosen.post_roll_missing, set(cuts))
        files = [*pre_roll_files, *chosen.files, *after]
        indices = [*(frame_number(f) for f in pre_roll_files), *indices,  # type: ignore[misc]
                   *(frame_number(f) for f in after)]
        all_cuts = frozenset(flagged | ({start} if start is not None else set()))
        problem = out_dir_problem(out)
        if problem is not None:
            raise ValueError(problem)
        if create_out:  # a dry run leaves no trace
            out.mkdir(parents=True, exist_ok=True)
        width, height = frame_size(chosen.files[0])
        job_file = JOB_FILE
        if frames is not None:
            job_file = f".quietframe-job.{frames[0]}-{frames[-1]}.json"
        return cls(files, indices, out, width, height, len(pre_roll_files), chosen.missing,
                   all_cuts, job_file, pre_missing, sequence,  # type: ignore[arg-type]
                   [_shot_of(n, all_cuts) for n in indices], post_roll=len(after),
                   post_roll_missing=post_missing)

    @property
    def end_written(self) -> int:
        """The position after the last one whose output this job writes (the first post-roll
        position, or len(files))."""
        return len(self.files) - self.post_roll

    @property
    def written(self) -> range:
        """Positions whose output this job writes."""
        return range(self.first_written, self.end_written)

    def output(self, i: int) -> Path:
        return self.out_dir / self.files[i].name

    def check(self, i: int, settings: dict) -> records.Check:
        """Position `i`'s output against this run: its settings, its shot's model, the source,
        and whether a pre-roll frame missing when it was made is there now."""
        return records.check(self.output(i), self.files[i], settings,
                             self.models_at(i, settings), self.sequence.keys())

    def first_pending(self, settings: dict | None = None) -> int:
        """Position of the first written frame that is not this job's output (end_written when
        all are done); with `settings` None, the first without an output file at all."""
        for i in self.written:
            if settings is None:
                if not self.output(i).exists():
                    return i
            elif self.check(i, settings).status is not records.Status.DONE:
                return i
        return self.end_written

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

    def undecided_starts(self, layers: tuple[str | None, ...]) -> list[int]:
        """Cuts that start shots this job sends whose own frame is not rendered yet while no
        record holds the shot's model: auto decides a shot from its first frame only, so these
        must wait for it (a later frame could choose another model than the shot's other
        chunks)."""
        if not self.sequence:
            return []
        return [start for start in self.shots_sent()
                if start is not None and start not in self.sequence
                and any(self.shot_record(start, layer or "") is None for layer in layers)]

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

    def short_lookahead(self, i: int, lookahead: int) -> tuple[int, ...]:
        """The missing post-roll frames within position `i`'s look-ahead (its `lookahead` next
        frame numbers), unless a cut or a gap between it and the chunk's end ends its run
        first: frames whose absence its output inherits, like short_history's."""
        reach = [n for n in self.post_roll_missing if n <= self.indices[i] + lookahead]
        if not reach:
            return ()
        for j in range(i + 1, self.end_written):
            if self.is_cut(j) or self.indices[j] != self.indices[j - 1] + 1:
                return ()
        return tuple(reach)

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
        (on_damage or warn)(f"the job file {path} is damaged ({problem}): ignored, a new "
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
    # look-ahead sessions: the frames they hold back, oldest first
    "held": lambda v: isinstance(v, list) and all(map(records.is_int, v)),
}


def job_file_problem(stored: object) -> str | None:
    """What makes a job file's JSON unusable (read as untrusted), None if nothing."""
    if not isinstance(stored, dict):
        return "not a JSON object"
    wrong = [name for name, valid in _JOB_FIELDS.items()
             if name in stored and not valid(stored[name])]
    return f"{', '.join(wrong)} of another type" if wrong else None


def warn(text: str) -> None:
    """A damaged file worked around, where the caller did not ask to be told (RuntimeWarning)."""
    warnings.warn(text, RuntimeWarning, stacklevel=3)


def out_dir_problem(out: Path) -> str | None:
    """Why outputs cannot be written into `out` (a file where a folder must be, a folder this
    user cannot write), found before anything is sent (audit R4-24); None when they can."""
    existing = out
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        return f"--out {out}: {existing} is a file, not a folder"
    if not os.access(existing, os.W_OK | os.X_OK):
        return f"--out {out}: {existing} is not writable by this user"
    return None


def _before_next_cut(last: int, post_roll: tuple[Path, ...], missing: tuple[int, ...],
                     cuts: set[int]) -> tuple[list[Path], tuple[int, ...]]:
    """The post-roll files and missing numbers before the first cut after frame `last` (a
    --cut, or a post-roll frame whose header flags one)."""
    flagged = cuts | {frame_number(f) for f in post_roll if shots.is_cut_frame(f)}
    end = min((c for c in flagged if c is not None and c > last), default=None)
    if end is None:
        return list(post_roll), missing
    return ([f for f in post_roll if frame_number(f) < end],  # type: ignore[operator]
            tuple(n for n in missing if n < end))


def _shot_of(index: int, cuts: frozenset[int]) -> int | None:
    """The cut that starts the shot of frame `index` (None: the sequence's first shot)."""
    return max((c for c in cuts if c <= index), default=None)


# Outputs that are not in the way: this job's, none, one this job was writing when it stopped,
# or one it made before its pre-roll frames were rendered.
_NOT_IN_THE_WAY = (records.Status.DONE, records.Status.ABSENT, records.Status.PENDING,
                   records.Status.INCOMPLETE)
