"""Durable sessions on disk: one .npz per session, written atomically after each frame.

A file holds the session's settings and progress (`meta`, JSON), its state and the last reply
(for an idempotent retry after a restart), in state_codec's compact form: what the next frame
reads, in the narrowest type that leaves results unchanged, and the reply as a recipe where its
colour is a state plane; a look-ahead session's held-back frames are part of its state (1-D
arrays among them, its requests, as their bytes: `record`). Files of the earlier form (float32
tensors, the reply's bytes) still load. The registry decides when to write and read; this
module only knows the file format. All calls do disk I/O: run them off the event loop.

Reading verifies the file: every member is read whole, so the zip format's CRC-32 of each one is
checked; the meta lists every member with its shape (`manifest`), its id must be the file's
name, and state tensors must have the shapes the session's model gives them at its frame size
(the registry says which: a half-resolution history is not the frame's size). Anything else
raises StateDamaged; `quarantine` moves such a file aside (`quarantine/`), where it is never
read again.

Beside it, `<id>.json` holds the session's settings, written once at creation: when the .npz
is damaged (or gone), the session can still continue from a fresh history.

Two backends behind one small interface (`Store`): this folder (one server owns it; `shared`
False) and Redis (`state_store_redis.py`, `shared` True: every replica behind the load balancer
reads it, and each write is a compare-and-set on the session's version, so two replicas never
both advance one session). service/stores.py `open_store` picks one from the settings.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import os
import re
import time
import zipfile
import zlib
from collections.abc import Iterator, Mapping, MutableMapping
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np

from quietframe.service import state_codec
from quietframe.service.errors import StoreUnavailable
from quietframe.service.state_codec import ReplyRecipe
from quietframe.service.stored_record import parse_meta

SESSION_ID = re.compile(r"[A-Za-z0-9_-]{22}")  # secrets.token_urlsafe(16): 128 random bits


def is_session_id(text: str) -> bool:
    """Whether `text` has the form of the ids this server issues (the whole of it: `$` would
    let a trailing newline through)."""
    return SESSION_ID.fullmatch(text) is not None


def checked_session_id(text: str) -> str:
    """`text`, if it is a session id (ValueError otherwise): a store builds a file name or a
    key from nothing else. The registry answers 404 for any other id before asking a store."""
    if not is_session_id(text):
        raise ValueError(f"not a session id: {text!r}")
    return text


def request_digest(body: bytes | bytearray) -> str:
    """What identifies a frame's request body for a retry: a CRC can be forged to match a
    different body; BLAKE2b-256 cannot."""
    return hashlib.blake2b(body, digest_size=32).hexdigest()


class StateDamaged(Exception):
    """A stored session file that cannot be trusted: unreadable, truncated, another session's."""


@dataclass
class Reply:
    """A frame's response, kept for an idempotent retry of the same index.

    `recipe`: how the body is written from the request (state_codec.ReplyRecipe), where its
    colour is a plane of the session's state; a store then keeps the recipe, not the body. A
    reply loaded so has no body yet (`color`: its colour planes): `matches` writes it from the
    resent request once the digest shows that request is the same."""

    index: int
    body: bytes
    headers: dict[str, str]
    request_len: int
    request_digest: str | None  # None: a file written before digests (has request_crc)
    request_crc: int | None = None
    recipe: ReplyRecipe | None = None
    color: np.ndarray | None = None  # (3, H, W) float32 until the body is written again
    # A look-ahead session's: 202 while the frame is held back (an empty body); `finish`: the
    # reply to POST .../frames/{index}/finish (no request body), not to a frame
    status: int = 200
    finish: bool = False

    def matches(self, body: bytes | bytearray) -> bool:
        """Whether `body` is the request this reply answered (a retry); if so, the reply has
        its body from then on (runs on the worker pool: hashing, and a stored reply's
        rewrite, take up to seconds on a large frame)."""
        if len(body) != self.request_len:
            return False
        if self.request_digest is not None:
            same = hmac.compare_digest(self.request_digest, request_digest(body))
        else:
            same = self.request_crc == zlib.crc32(body)  # the one reply of an older file
        if same and self.color is not None and self.recipe is not None:
            self.body = state_codec.rebuild_reply(self.recipe, self.color, body)
            self.color = None
        return same


class Store(Protocol):
    """What the registry asks of a durable store. `write` returns the session's new version
    (None where the store has no versions: one server owns a local folder); a shared store
    refuses a write whose `expect` is not the stored version (another replica advanced it).
    `write` replaces `state`'s tensors by their values as stored (`record`)."""

    shared: bool

    def write_spec(self, meta: Mapping) -> None: ...
    def read_spec(self, session_id: str) -> dict | None: ...
    def write(self, meta: Mapping, state: MutableMapping[str, np.ndarray] | None,
              reply: Reply | None, expect: str | None = None) -> str | None: ...
    def read(self, session_id: str, shapes: Mapping[str, tuple[int, ...]]
             ) -> tuple[dict[str, np.ndarray] | None, Reply | None]: ...
    def quarantine(self, session_id: str) -> object: ...
    def delete(self, session_id: str) -> None: ...


def record(
    meta: Mapping, state: MutableMapping[str, np.ndarray] | None, reply: Reply | None
) -> tuple[dict, dict[str, np.ndarray]]:
    """The stored form of a session, either backend: the meta (with the reply's identity, the
    state's layout (state_codec) and a manifest of every member's length) and the members
    (uint8: the state's planes, and the reply's bytes unless its recipe is kept instead).
    `state`'s tensors are replaced by their values as stored (state_codec.encode), so the
    writer continues from what any reader of the record gets."""
    meta = dict(meta)
    meta["reply"] = None
    recipe = reply.recipe if reply is not None else None
    # 1-D arrays (a look-ahead window's indices and held requests: service/lookahead_queue.py)
    # are kept as their bytes; every other tensor in state_codec's form
    raw = {name: np.asarray(a) for name, a in (state or {}).items() if np.ndim(a) == 1}
    encoded = state_codec.encode({k: v for k, v in (state or {}).items() if k not in raw},
                                 recipe)
    if state is not None:
        state.update(encoded.state)
    meta["codec"] = encoded.layout
    # "state." names: a replica that predates this form finds no tensor of its model's shapes
    # under them and refuses the record as damaged (a fresh history), never reads it as empty
    arrays = {f"state.plane{i}": plane for i, plane in enumerate(encoded.planes)}
    if raw:
        meta["raw"] = {name: a.dtype.name for name, a in raw.items()}
        arrays |= {f"raw.{name}": np.ascontiguousarray(a).view(np.uint8).reshape(-1)
                   for name, a in raw.items()}
    if reply is not None:
        meta["reply"] = {
            "index": reply.index,
            "headers": reply.headers,
            "digest": reply.request_digest,
            "crc": reply.request_crc,
            "len": reply.request_len,
            "recipe": recipe.to_dict() if encoded.reply and recipe is not None else None,
        }
        if reply.status != 200 or reply.finish:  # a look-ahead session's (absent: 200, a frame)
            meta["reply"] |= {"status": reply.status, "finish": reply.finish}
        if meta["reply"]["recipe"] is None:
            arrays["reply"] = np.frombuffer(reply.body, np.uint8)
    meta["manifest"] = {name: list(array.shape) for name, array in arrays.items()}
    return meta, arrays


def unpack(
    meta: dict, arrays: dict[str, np.ndarray], session_id: str,
    shapes: Mapping[str, tuple[int, ...]],
) -> tuple[dict[str, np.ndarray] | None, Reply | None]:
    """State and reply from a stored record, verified (ValueError and friends otherwise). A
    record without a layout is the earlier float32 form (a state tensor per member, the
    reply's bytes): it loads as it always did."""
    _verify(meta, arrays, session_id, shapes)
    layout = meta.get("codec")
    if layout is None:
        state = {k[6:]: v for k, v in arrays.items() if k.startswith("state.")} or None
    else:
        planes = [arrays[f"state.plane{i}"] for i in range(len(layout["planes"]))]
        state = state_codec.decode(layout, planes, shapes) or None
    if meta.get("raw"):
        state = (state or {}) | _raw_arrays(meta["raw"], arrays, shapes)
    r, reply = meta["reply"], None
    recipe = r.get("recipe") if r is not None else None
    if recipe is not None:
        recipe = ReplyRecipe.from_dict(recipe)
        tensor = (state or {}).get(recipe.tensor)
        if tensor is None or tensor.ndim != 4 or tensor.shape[1] < recipe.first + 3:
            raise ValueError(f"the reply's colour is in state {recipe.tensor!r}, not stored")
        reply = Reply(r["index"], b"", r["headers"], r["len"], r.get("digest"), r.get("crc"),
                      recipe, tensor[0, recipe.first:recipe.first + 3])
    elif r is not None and "reply" in arrays:
        reply = Reply(
            r["index"], arrays["reply"].tobytes(), r["headers"], r["len"], r.get("digest"),
            r.get("crc"), status=r.get("status", 200), finish=r.get("finish", False),
        )
    return state, reply


RAW_DTYPES = frozenset({"uint8", "int64", "float32"})  # float32: a window's limits
ANY_LENGTH = (-1,)  # a shape in `shapes`: a 1-D array of any length


def _raw_arrays(kinds: dict, arrays: dict[str, np.ndarray],
                shapes: Mapping[str, tuple[int, ...]]) -> dict[str, np.ndarray]:
    """The 1-D arrays `record` kept as bytes, each one the session's `shapes` names (ValueError
    otherwise: another dtype, length or name)."""
    out = {}
    for name, kind in kinds.items():
        want = shapes.get(name)
        if kind not in RAW_DTYPES or want is None or len(want) != 1:
            raise ValueError(f"stored array {name!r} ({kind}) is not one of the session's")
        data = arrays[f"raw.{name}"]
        size = np.dtype(kind).itemsize
        if data.size % size:
            raise ValueError(f"stored array {name!r}: {data.size} bytes of {kind}")
        value = data.view(kind)
        if want != ANY_LENGTH and value.shape != want:
            raise ValueError(f"stored array {name!r} has shape {value.shape}, not {want}")
        out[name] = value
    return out


class SessionStore:
    """The local folder: one server owns it (a restart, even after kill -9, reads it back)."""

    shared = False

    def __init__(self, folder: Path, fsync: bool) -> None:
        self.folder, self.fsync = Path(folder), fsync
        self.folder.mkdir(parents=True, exist_ok=True)

    def path(self, session_id: str) -> Path:
        return self.folder / f"{checked_session_id(session_id)}.npz"

    def spec_path(self, session_id: str) -> Path:
        return self.path(session_id).with_suffix(".json")

    def write_spec(self, meta: Mapping) -> None:
        """The session's settings, once, at creation (temp file + rename)."""
        path = self.spec_path(meta["id"])
        temp = path.with_name(f".{path.name}.tmp")
        try:
            temp.write_text(json.dumps(dict(meta)))
            os.replace(temp, path)
        except OSError as exc:
            temp.unlink(missing_ok=True)
            raise _refused(exc) from exc

    def read_spec(self, session_id: str) -> dict | None:
        """The settings written at creation, or None (absent, unreadable, another id)."""
        try:
            return parse_meta(self.spec_path(session_id).read_text(), session_id, progress=False)
        except (OSError, ValueError):
            return None

    def spec_ids(self) -> list[str]:
        return sorted(p.stem for p in self.folder.glob("*.json") if is_session_id(p.stem))

    def write(
        self,
        meta: Mapping,
        state: MutableMapping[str, np.ndarray] | None,
        reply: Reply | None,
        expect: str | None = None,
    ) -> None:
        """Replace the session's file (temp file + rename: a crash leaves the old one). `expect`
        is ignored: this server is the folder's one writer, there is nobody to fence out."""
        stored, arrays = record(meta, state, reply)
        arrays["meta"] = np.frombuffer(json.dumps(stored).encode(), np.uint8)
        path = self.path(meta["id"])
        temp = path.with_name(f".{path.name}.tmp")
        try:
            with open(temp, "wb") as f:
                np.savez(f, **arrays)
                f.flush()
                if self.fsync:
                    os.fsync(f.fileno())
            os.replace(temp, path)
        except BaseException as exc:
            temp.unlink(missing_ok=True)  # the previous state file stays as it was
            if isinstance(exc, OSError):
                raise _refused(exc) from exc
            raise

    def read(
        self, session_id: str, shapes: Mapping[str, tuple[int, ...]]
    ) -> tuple[dict[str, np.ndarray] | None, Reply | None]:
        """The state tensors and the last reply of a stored session, verified (StateDamaged);
        `shapes`: each state tensor's shape for the session's model and frame size."""
        try:
            with np.load(self.path(session_id)) as z:
                arrays = {name: z[name] for name in z.files}  # whole reads check each CRC-32
            meta = parse_meta(arrays.pop("meta").tobytes(), session_id)
            state, reply = unpack(meta, arrays, session_id, shapes)
        except (OSError, ValueError, KeyError, TypeError, EOFError, zipfile.BadZipFile) as exc:
            raise StateDamaged(f"{type(exc).__name__}: {exc}") from exc
        return state, reply

    def quarantine(self, session_id: str) -> Path | None:
        """Move a damaged file aside (kept for inspection, never loaded again)."""
        return self.quarantine_path(self.path(session_id))

    def quarantine_path(self, path: Path) -> Path | None:
        folder = self.folder / "quarantine"
        folder.mkdir(exist_ok=True)
        target = folder / f"{path.name}.{time.strftime('%Y%m%dT%H%M%S')}"
        try:
            os.replace(path, target)
        except FileNotFoundError:
            return None
        return target

    def metas(self) -> Iterator[tuple[Path, dict]]:
        """(path, meta) of every stored session file; an unreadable one, or one whose meta names
        another session, has the error as the meta's "error"."""
        for path in sorted(self.folder.glob("*.npz")):
            if not is_session_id(path.stem):
                continue
            try:
                with np.load(path) as z:
                    meta = parse_meta(z["meta"].tobytes(), path.stem)
                yield path, meta
            except Exception as exc:  # unreadable file
                yield path, {"error": f"{type(exc).__name__}: {exc}"}

    def delete(self, session_id: str) -> None:
        self.path(session_id).unlink(missing_ok=True)
        self.spec_path(session_id).unlink(missing_ok=True)


def _refused(exc: OSError) -> StoreUnavailable:
    """A write the state folder refused (full, read-only, gone): 503 with Retry-After, as a
    store that does not answer (audit R4-20: it was a 500 without one)."""
    return StoreUnavailable(
        f"the state folder refused the write ({exc.strerror or exc}); nothing was stored: "
        "retry after Retry-After (the server's QUIETFRAME_STATE_DIR needs space or write "
        "access)", headers={"Retry-After": "5"})


def _verify(
    meta: dict, arrays: dict, session_id: str, shapes: Mapping[str, tuple[int, ...]]
) -> None:
    if meta.get("id") != session_id:
        raise ValueError(f"the file holds session {meta.get('id')!r}, not {session_id!r}")
    manifest = meta.get("manifest")
    if manifest is not None:  # files written before manifests have none
        listed = {name: tuple(shape) for name, shape in manifest.items() if name != "meta"}
        if listed != {name: array.shape for name, array in arrays.items()}:
            raise ValueError("the file's members do not match its manifest")
    if meta.get("codec") is not None:  # every member is bytes; decode checks the state
        for name, array in arrays.items():
            if array.dtype != np.uint8 or array.ndim != 1:
                raise ValueError(f"{name} is {array.dtype} {array.shape}, not stored bytes")
        return
    for name, array in arrays.items():
        if name.startswith("state.") and array.shape != shapes.get(name[6:]):
            raise ValueError(f"{name} has shape {array.shape}; the session's model expects "
                             f"{shapes.get(name[6:], 'no such state')}")
        # The runtime feeds state as float32 and the reply is bytes: another dtype of the right
        # shape would pass this far and fail inside the model (a 500 on every frame).
        want = np.float32 if name.startswith("state.") else np.uint8
        if array.dtype != want:
            raise ValueError(f"{name} is {array.dtype}; a session file holds {np.dtype(want)}")
