"""What a session is, fixed at its creation and stored with a durable session: the shared
session fields (client/session_fields.py) with `model` an installed model's name or "auto"."""

from __future__ import annotations

from collections.abc import Mapping

from pydantic import ConfigDict

from quietframe.client.session_fields import SessionFields


class SessionSpec(SessionFields):
    # Run-time options (e.g. kernel_size) are checked at creation; each model that runs gets
    # those it declares (runtime/stream.options_for).
    model_config = ConfigDict(frozen=True)

    @classmethod
    def from_record(cls, record: Mapping, model: str) -> SessionSpec:
        """The spec a stored record holds (fields an older record lacks take their defaults),
        with `model` as this server resolves the stored one."""
        return cls.model_validate({**stored_fields(record), "model": model})


def stored_fields(record: Mapping) -> dict:
    """The spec's fields a stored record holds (absent in older records: left out)."""
    return {name: record[name] for name in SessionSpec.model_fields
            if record.get(name) is not None}


def spec_difference(record: Mapping, settings: Mapping) -> str:
    """Where a state record and the session's settings file disagree on what the session is
    (empty: they agree)."""
    a, b = _compared(record), _compared(settings)
    return ", ".join(f"{k} {a[k]!r} (settings file: {b[k]!r})" for k in a if a[k] != b[k])


def _compared(record: Mapping) -> dict:
    fields = {name: record.get(name) for name in SessionSpec.model_fields}
    fields["model_options"] = fields["model_options"] or {}  # absent in older files
    fields["lookahead"] = fields["lookahead"] or 0  # absent in older files
    return fields
