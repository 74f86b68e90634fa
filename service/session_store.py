"""Durable sessions on disk: one .npz per session, written atomically after each frame.

A file holds the session's settings and progress (`meta`, JSON), its state tensors and the last
reply (for an idempotent retry after a restart). The registry decides when to write and read;
this module only knows the file format. All calls do disk I/O: run them off the event loop.
"""

from __future__ import annotations

import json
import os
import re
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

SESSION_ID = re.compile(r"^[A-Za-z0-9_-]{22}$")  # secrets.token_urlsafe(16): 128 random bits


@dataclass
class Reply:
    """A frame's response, kept for an idempotent retry of the same index."""

    index: int
    body: bytes
    headers: dict[str, str]
    request_crc: int
    request_len: int


class SessionStore:
    def __init__(self, folder: Path, fsync: bool) -> None:
        self.folder, self.fsync = Path(folder), fsync
        self.folder.mkdir(parents=True, exist_ok=True)

    def path(self, session_id: str) -> Path:
        if not SESSION_ID.match(session_id):
            raise ValueError(f"not a session id: {session_id!r}")
        return self.folder / f"{session_id}.npz"

    def write(
        self,
        meta: Mapping,
        state: Mapping[str, np.ndarray] | None,
        reply: Reply | None,
    ) -> None:
        """Replace the session's file (temp file + rename: a crash leaves the old one)."""
        record = dict(meta)
        record["reply"] = None
        arrays = {}
        for name, tensor in (state or {}).items():
            arrays[f"state.{name}"] = tensor
        if reply is not None:
            record["reply"] = {
                "index": reply.index,
                "headers": reply.headers,
                "crc": reply.request_crc,
                "len": reply.request_len,
            }
            arrays["reply"] = np.frombuffer(reply.body, np.uint8)
        arrays["meta"] = np.frombuffer(json.dumps(record).encode(), np.uint8)
        path = self.path(meta["id"])
        temp = path.with_name(f".{path.name}.tmp")
        try:
            with open(temp, "wb") as f:
                np.savez(f, **arrays)
                f.flush()
                if self.fsync:
                    os.fsync(f.fileno())
            os.replace(temp, path)
        except BaseException:
            temp.unlink(missing_ok=True)  # the previous state file stays as it was
            raise

    def read(
        self, session_id: str
    ) -> tuple[dict[str, np.ndarray] | None, Reply | None]:
        """The state tensors and the last reply of a stored session."""
        with np.load(self.path(session_id)) as z:
            meta = json.loads(z["meta"].tobytes())
            state = {k[6:]: z[k] for k in z.files if k.startswith("state.")} or None
            r = meta["reply"]
            reply = None
            if r is not None and "reply" in z.files:
                reply = Reply(
                    r["index"], z["reply"].tobytes(), r["headers"], r["crc"], r["len"]
                )
        return state, reply

    def metas(self) -> Iterator[tuple[Path, dict]]:
        """(path, meta) of every stored session file, skipping unreadable ones (with the error
        as the meta's "error")."""
        for path in sorted(self.folder.glob("*.npz")):
            if not SESSION_ID.match(path.stem):
                continue
            try:
                with np.load(path) as z:
                    yield path, json.loads(z["meta"].tobytes())
            except Exception as exc:  # unreadable file
                yield path, {"error": f"{type(exc).__name__}: {exc}"}

    def delete(self, session_id: str) -> None:
        self.path(session_id).unlink(missing_ok=True)
