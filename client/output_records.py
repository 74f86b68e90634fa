"""What makes an output "done": a record written next to it, per frame, in `<out>/.quietframe/`.

A file in the output folder counts as this job's output only if its record names the same
source (size and mtime, or else the same SHA-256: a touched but identical render still counts),
the same settings (model, options, channel flags), and the output is still the file written:
the same size and mtime, or else the same SHA-256 (a copied folder still counts, a file swapped
for garbage of the same size does not). One record per frame, not one manifest per folder: farm
chunks of one shot write into one folder at the same time and must not rewrite each other's
bookkeeping.

An output and its record are written in steps that leave, wherever a run stops between them (a
crash, a full disk, SIGKILL), a state its rerun resumes from (`write_output`). Nothing is written
through a link: temporary files are created exclusively, and the record folder is opened
without following one. Records are read as untrusted input: any other shape counts as damaged.
"""

from __future__ import annotations

import contextlib
import errno
import functools
import hashlib
import json
import os
import secrets
import stat
from collections.abc import Collection, Iterator
from dataclasses import dataclass
from enum import Enum
from pathlib import Path

from quietframe.client.frame_source import SequenceError
from quietframe.client.session_fields import AUTO

RECORD_DIR = ".quietframe"
RECORD_VERSION = 2  # 2 stamps the output (size, mtime, SHA-256) and says `pending`; 1: size only
READABLE_VERSIONS = (1, 2)
MAX_RECORD_BYTES = 1 << 20  # records and job files are a few hundred bytes
_NEW_FILE = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC
_NO_LINK = os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC  # NONBLOCK: a FIFO
_SOURCE_FIELDS = ("size", "mtime_ns", "sha256")


class OutputConflict(SequenceError):
    """Files in the output folder that this run would overwrite but did not make with these
    sources and settings; `changed` when only the settings differ (a configuration matter)."""

    def __init__(self, message: str, changed: bool) -> None:
        super().__init__(message)
        self.changed = changed


class Status(str, Enum):
    DONE = "done"  # this job's output for this source
    ABSENT = "absent"  # no output yet
    FOREIGN = "foreign"  # a file quietframe did not write (or wrote before records existed)
    STALE = "stale"  # written from a source file that has changed since (a re-render)
    CHANGED = "changed"  # written with other settings (model, options, channel flags)
    DAMAGED = "damaged"  # not the file written (truncated copy, other bytes of the same size)
    PENDING = "pending"  # a write that a stopped run left half-way, by its record: redone
    # made without its full pre-roll or post-roll (frames not rendered then), which exist
    # now: redone
    INCOMPLETE = "incomplete"


@dataclass(frozen=True)
class Check:
    status: Status
    detail: str = ""  # for CHANGED: which settings differ; for FOREIGN: what ails its record


@dataclass(frozen=True)
class Record:
    source: dict  # size, mtime_ns, sha256 of the source it was made from
    settings: dict
    output: dict  # size; from version 2 on also mtime_ns and sha256
    pending: bool  # written before the output was in place (see write_output)
    # The model that made each view layer ("" for none), by name; None where not recorded
    # (older records): `auto` resolved, so `--model X` and auto's X compare as one model.
    models: dict | None = None
    # Pre-roll frame numbers that were missing when it was made (its history started short)
    pre_roll_missing: tuple[int, ...] = ()
    # Post-roll frame numbers within its look-ahead that were missing when it was made
    post_roll_missing: tuple[int, ...] = ()


class DamagedRecord(ValueError):
    """A record file that is not a record (unreadable, not JSON, or fields of another type)."""


class UnsafePath(SequenceError):
    """A link (or a file) where quietframe keeps its records: it writes nothing through one."""


def record_path(output: Path) -> Path:
    return output.parent / RECORD_DIR / f"{output.name}.json"


def temp_path(path: Path) -> Path:
    return path.with_name(f".{path.name}.part")


def source_stamp(source: Path, data: bytes | None = None) -> dict:
    """Size, mtime and SHA-256 of a source file (`data`: its bytes, already read)."""
    stat_now = source.stat()
    digest = hashlib.sha256(data if data is not None else source.read_bytes()).hexdigest()
    return {"name": source.name, "size": stat_now.st_size, "mtime_ns": stat_now.st_mtime_ns,
            "sha256": digest}


# ---- writing ------------------------------------------------------------------------------


def write_new(path: Path | str, data: bytes, dir_fd: int | None = None) -> os.stat_result:
    """`data` in a file created at `path` exclusively, after removing whatever entry was there
    (a stale temporary file, or a link planted to redirect the write): a link is never
    followed, and one that appears in between makes the open fail instead."""
    with contextlib.suppress(FileNotFoundError):
        os.unlink(path, dir_fd=dir_fd)
    with open(os.open(path, _NEW_FILE, 0o666, dir_fd=dir_fd), "wb") as file:
        file.write(data)
    return os.stat(path, dir_fd=dir_fd, follow_symlinks=False)


def rename(temp: Path | str, path: Path | str, dir_fd: int | None = None) -> None:
    """`temp` becomes `path`; a link at `path` is replaced itself, never followed."""
    os.replace(temp, path, src_dir_fd=dir_fd, dst_dir_fd=dir_fd)


def atomic_write(path: Path, data: bytes) -> None:
    """`data` at `path`, whole or not at all (a temporary file next to it, renamed)."""
    temp = temp_path(path)
    write_new(temp, data)
    rename(temp, path)


def write_output(output: Path, data: bytes, source: dict, settings: dict, **extra) -> None:
    """`data` at `output` with its record, in steps; wherever a run stops between two, its
    rerun resumes (never refuses the output as foreign):
    1. the output at its temporary name: the old output and record are as they were;
    2. the record, pending, stamping the new output: an output unlike the stamp is redone;
    3. the output renamed into place: it matches the stamp, so it is done;
    4. the record again, no longer pending: from now on an output unlike it is damaged."""
    temp = temp_path(output)
    written = write_new(temp, data)
    stamp = {"size": written.st_size, "mtime_ns": written.st_mtime_ns,
             "sha256": hashlib.sha256(data).hexdigest()}
    write_record(output, source, settings, stamp, pending=True, **extra)
    rename(temp, output)
    write_record(output, source, settings, stamp, **extra)


def write_record(output: Path, source: dict, settings: dict, stamp: dict,
                 pending: bool = False, **extra) -> None:
    body = {"version": RECORD_VERSION, "source": source, "settings": settings,
            "output": stamp, "pending": pending, **extra}
    name = record_path(output).name
    temp = temp_path(Path(name)).name
    with _record_folder(output) as folder:
        write_new(temp, json.dumps(body, indent=1, sort_keys=True).encode(), folder)
        rename(temp, name, folder)


def create_in_records(out_dir: Path, name: str, data: bytes) -> bool:
    """`data` as `<out>/.quietframe/<name>` unless that file exists (then False): written whole
    under a name of this process's own, then linked into place, which fails where a file is
    (one another process linked a moment before included): a reader never sees half a file."""
    temp = f".{name}.{os.getpid()}-{secrets.token_hex(4)}.part"
    with record_folder(out_dir) as folder:
        write_new(temp, data, folder)
        try:
            os.link(temp, name, src_dir_fd=folder, dst_dir_fd=folder, follow_symlinks=False)
        except FileExistsError:
            return False
        finally:
            os.unlink(temp, dir_fd=folder)
    return True


def replace_in_records(out_dir: Path, name: str, data: bytes) -> None:
    """`data` as `<out>/.quietframe/<name>`, whole, whatever was there."""
    temp = f".{name}.{os.getpid()}-{secrets.token_hex(4)}.part"
    with record_folder(out_dir) as folder:
        write_new(temp, data, folder)
        rename(temp, name, folder)


def _record_folder(output: Path) -> contextlib.AbstractContextManager[int]:
    return record_folder(output.parent)


@contextlib.contextmanager
def record_folder(out_dir: Path) -> Iterator[int]:
    """`<out>/.quietframe` (made if need be), opened without following a link."""
    folder = out_dir / RECORD_DIR
    with contextlib.suppress(FileExistsError):
        folder.mkdir()
    try:
        fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC)
    except OSError as exc:
        if exc.errno not in (errno.ELOOP, errno.ENOTDIR):
            raise
        raise UnsafePath(
            f"{folder} is a link or a file, not a folder: quietframe keeps its records there "
            "and writes nothing through a link") from exc
    try:
        yield fd
    finally:
        os.close(fd)


# ---- reading ------------------------------------------------------------------------------


def read_small_file(path: Path, limit: int = MAX_RECORD_BYTES) -> bytes:
    """A bookkeeping file's bytes, not through a link; OSError if it is not a regular file of
    at most `limit` bytes (a FIFO or /dev/zero planted there would hang the run)."""
    with open(os.open(path, _NO_LINK), "rb") as file:
        if not stat.S_ISREG(os.fstat(file.fileno()).st_mode):
            raise OSError(errno.EINVAL, "not a regular file", str(path))
        data = file.read(limit + 1)
    if len(data) > limit:
        raise OSError(errno.EFBIG, f"larger than {limit} bytes", str(path))
    return data


def read_record(output: Path) -> Record | None:
    """The output's record; None if it has none, DamagedRecord if that file is no record."""
    try:
        text = read_small_file(record_path(output))
    except FileNotFoundError:
        return None
    except OSError as exc:
        raise DamagedRecord(exc.strerror or str(exc)) from exc
    try:
        raw = json.loads(text)
    except ValueError as exc:
        raise DamagedRecord("not JSON") from exc
    return parse_record(raw)


def parse_record(raw: object) -> Record:
    """A record's JSON as a Record; DamagedRecord naming the first field of another type."""
    if not isinstance(raw, dict):
        raise DamagedRecord("not a JSON object")
    version = raw.get("version")
    if not is_int(version) or version not in READABLE_VERSIONS:
        raise DamagedRecord(f"version {json.dumps(version)} (this quietframe reads "
                            f"{' and '.join(map(str, READABLE_VERSIONS))})")
    source, settings = raw.get("source"), raw.get("settings")
    if not _has_fields(source, _SOURCE_FIELDS):
        raise DamagedRecord("source is not a stamp (size, mtime_ns, sha256)")
    if not isinstance(settings, dict):
        raise DamagedRecord("settings is not an object")
    if version == 1:
        output, pending, fields = {"size": raw.get("output_size")}, False, ("size",)
    else:
        output, pending, fields = raw.get("output"), raw.get("pending"), _SOURCE_FIELDS
    if not _has_fields(output, fields):
        raise DamagedRecord(f"output is not a stamp ({', '.join(fields)})")
    if not isinstance(pending, bool):
        raise DamagedRecord("pending is not true or false")
    models = raw.get("models")
    if models is not None and not (isinstance(models, dict) and all(
            isinstance(v, str) for v in models.values())):
        raise DamagedRecord("models is not an object of model names")
    missing = {name: raw.get(name, []) for name in ("pre_roll_missing", "post_roll_missing")}
    for name, numbers in missing.items():
        if not (isinstance(numbers, list) and all(map(is_int, numbers))):
            raise DamagedRecord(f"{name} is not a list of frame numbers")
    return Record(source, settings, output, pending, models,
                  tuple(missing["pre_roll_missing"]), tuple(missing["post_roll_missing"]))


def is_int(value: object) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)  # JSON true is not 1


def _has_fields(stamp: object, fields: tuple[str, ...]) -> bool:
    """A dict with each of `fields` of its type: sizes and mtimes integers, digests strings."""
    if not isinstance(stamp, dict):
        return False
    return all(isinstance(stamp.get(f), str) if f == "sha256" else is_int(stamp.get(f))
               for f in fields)


# ---- checking -----------------------------------------------------------------------------


def check(output: Path, source: Path, settings: dict, models: dict | None = None,
          present: Collection[int] = ()) -> Check:
    """Whether `output` is this job's output of `source` made with `settings`; `models`: the
    model this run uses per view layer (auto resolved, None if not known yet); `present`: the
    frame numbers in the input now (a record's missing pre- or post-roll frame among them:
    INCOMPLETE)."""
    try:
        stat_now = os.lstat(output)
    except FileNotFoundError:
        return Check(Status.ABSENT)
    if not stat.S_ISREG(stat_now.st_mode):  # quietframe writes regular files, never links
        return Check(Status.FOREIGN)
    try:
        record = read_record(output)
    except DamagedRecord as exc:
        return Check(Status.FOREIGN, str(exc))
    if record is None:
        return Check(Status.FOREIGN)
    if not same_settings(record, settings, models):
        return Check(Status.CHANGED, differences(record.settings, settings, record.models, models))
    if not _same_source(record.source, source):
        return Check(Status.STALE)
    if not _same_output(record.output, output, stat_now):
        return Check(Status.PENDING if record.pending else Status.DAMAGED)
    for kind, missing in (("pre", record.pre_roll_missing), ("post", record.post_roll_missing)):
        rendered_since = [n for n in missing if n in present]
        if rendered_since:
            return Check(Status.INCOMPLETE, f"{kind}-roll frame(s) {rendered_since} rendered since")
    return Check(Status.DONE)


# Flags that only steer auto's choice: once the model is named, they change nothing.
AUTO_ONLY = ("quality", "latency_ms")


def same_settings(record: Record, settings: dict, models: dict | None) -> bool:
    """The record's settings are `settings`, where `--model auto` that resolved to X and
    `--model X` are one model (then auto's own flags do not count), and an output made by
    another model than this run's for its shot (both known) is not the same."""
    known = record.models is not None and models is not None
    if known and record.models != models:
        return False
    if record.settings == settings:
        return True
    before, now = dict(record.settings), dict(settings)
    if before.get("model") == now.get("model") or not known:
        return False
    if AUTO not in (before.get("model"), now.get("model")):
        return False  # two named models: the names differ
    for flags in (before, now):
        for name in ("model", *AUTO_ONLY):
            flags.pop(name, None)
    return before == now


def _same_source(stamp: dict, source: Path) -> bool:
    now = source.stat()
    if now.st_size != stamp["size"]:
        return False
    if now.st_mtime_ns == stamp["mtime_ns"]:
        return True
    return _sha256_of(source, now, follow=True) == stamp["sha256"]


def _same_output(stamp: dict, output: Path, present: os.stat_result) -> bool:
    """The file written: its size, and its mtime or else its digest (stat is trusted as for
    sources: hashing every output on every resume costs seconds per 4K frame)."""
    if present.st_size != stamp["size"]:
        return False
    if "sha256" not in stamp:  # version 1 records stamp the size only
        return True
    if present.st_mtime_ns == stamp["mtime_ns"]:
        return True
    return _sha256_of(output, present, follow=False) == stamp["sha256"]


def _sha256_of(path: Path, seen: os.stat_result, follow: bool) -> str | None:
    """SHA-256 of a regular file (None for anything else); hashed once per version of the
    file in this process, as a resume checks each output more than once."""
    return _file_sha256(str(path), follow, seen.st_dev, seen.st_ino, seen.st_size,
                        seen.st_mtime_ns, seen.st_ctime_ns)


@functools.lru_cache(maxsize=1024)
def _file_sha256(path: str, follow: bool, *version: int) -> str | None:
    try:
        fd = os.open(path, _NO_LINK & ~os.O_NOFOLLOW if follow else _NO_LINK)
    except OSError:
        return None
    digest = hashlib.sha256()
    with open(fd, "rb") as file:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            return None
        while chunk := file.read(1 << 20):
            digest.update(chunk)
    return digest.hexdigest()


def differences(before: dict, now: dict, models_before: dict | None = None,
                models_now: dict | None = None) -> str:
    """`--model auto -> oidn-frame; --channels none -> {...}` for the settings that differ;
    `--model auto (oidn-frame) -> auto (oidn-history)` where auto resolved to another model."""
    keys = sorted(set(before) | set(now))
    changed = [k for k in keys if before.get(k) != now.get(k)]
    said = [f"{flag(k)} {_shown(before.get(k))} -> {_shown(now.get(k))}" for k in changed]
    if "model" not in changed and None not in (models_before, models_now) and (
            models_before != models_now):
        said.insert(0, f"--model {_resolved(before, models_before)} -> "
                       f"{_resolved(now, models_now)}")
    return "; ".join(said)


def _resolved(settings: dict, models: dict | None) -> str:
    names = ", ".join(sorted(set((models or {}).values())))
    return f"{settings.get('model')} ({names})"


def flag(setting: str) -> str:
    return "--" + setting.replace("_", "-")


def _shown(value) -> str:
    if value is None or value == {} or value == []:
        return "(unset)"
    return value if isinstance(value, str) else json.dumps(value, sort_keys=True)
