"""A stored session record's meta, read as untrusted input: one schema for both stores (the state
folder's `.npz` files and Redis), checked before any field is used.

A record can be damaged or written by someone else (a full disk, a hand edit, an attacker with
the store's password). Whatever it holds, reading it ends in a dict of the expected types or a
ValueError, which the stores turn into StateDamaged: the record is quarantined and the session
goes on from a fresh history (`state-lost`). Before this, seven of eighteen wrongly shaped
records (audit R4-4: `reply` a string, `last_index` a string or absent, the meta a list, 200 000
nested brackets) gave a 500 on every frame of the session.
"""

from __future__ import annotations

import json
from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from quietframe.service.session_spec import SessionSpec

Count = Annotated[int, Field(strict=True, ge=0)]
Index = Annotated[int, Field(strict=True)]


class StoredReply(BaseModel):
    """The last reply's identity (its bytes or the recipe to rebuild them are stored beside)."""

    model_config = ConfigDict(extra="forbid")
    index: Index
    headers: dict[str, str]
    len: Count
    digest: str | None = None
    crc: Annotated[int, Field(strict=True)] | None = None
    recipe: dict[str, Any] | None = None
    # a look-ahead session's: 202 while its frame is held back; the reply to a finish
    status: Annotated[int, Field(strict=True, ge=200, le=299)] = 200
    finish: Annotated[bool, Field(strict=True)] = False


class StoredChoice(BaseModel):
    """Enough of `auto`'s recorded choice to be used (service/choice_policy.Choice reads it)."""

    model_config = ConfigDict(extra="allow")
    model: str


class StoredProgress(BaseModel):
    """A state record's progress and members (a settings record has none of these)."""

    model_config = ConfigDict(extra="allow")
    id: str
    created_at: float
    last_index: Index | None
    frames_done: Count
    resets: Count
    choice: StoredChoice | None = None
    shot_spp: Annotated[float, Field(strict=True, ge=1, allow_inf_nan=False)] | None = None
    reply: StoredReply | None = None
    codec: dict[str, Any] | None = None
    manifest: dict[str, list[Count]] | None = None
    raw: dict[str, str] | None = None  # 1-D state arrays stored as bytes: name -> dtype
    pending: list[Index] | None = None  # a look-ahead session's frames held back


def parse_meta(raw: bytes | str, session_id: str, progress: bool = True) -> dict:
    """The meta of session `session_id`'s record from its JSON text: its spec fields valid for a
    session (SessionSpec), and with `progress` (a state record, not a settings file) the
    progress fields too. ValueError naming what is wrong, for anything else."""
    try:
        meta = json.loads(raw)
    except RecursionError:  # 200 000 nested brackets: json's recursion, not a ValueError
        raise ValueError("the meta is nested too deeply to be a session record") from None
    if not isinstance(meta, dict):
        raise ValueError(f"the meta is a JSON {type(meta).__name__}, not an object")
    if meta.get("id") != session_id:
        raise ValueError(f"the record holds session {meta.get('id')!r}, not {session_id!r}")
    try:
        SessionSpec.model_validate({name: meta[name] for name in SessionSpec.model_fields
                                    if meta.get(name) is not None})
        if progress:
            StoredProgress.model_validate(meta)
    except ValidationError as exc:
        problems = "; ".join(f"{'.'.join(map(str, e['loc'])) or 'meta'}: {e['msg']}"
                             for e in exc.errors()[:3])
        raise ValueError(f"the meta is not a session record ({problems})") from None
    return meta
