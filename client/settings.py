"""The client's settings: the `QUIETFRAME_*` variables the `quietframe` command reads, read here
and nowhere else in client/ (every name, its layer and default: docs/configuration.md).

Read at each call, not once per process: a command reads them once as it starts, and a script or
test that runs the command in-process sees the environment of that moment.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

SERVER = "QUIETFRAME_SERVER"
TOKEN = "QUIETFRAME_TOKEN"
# The server's own settings (service/settings.py), which `quietframe models` without --server
# applies too when it lists the models this machine would serve.
MODELS_DIR = "QUIETFRAME_MODELS_DIR"
DEFAULT_MODEL = "QUIETFRAME_DEFAULT_MODEL"


@dataclass(frozen=True)
class ClientSettings:
    server: str | None = None  # the server's URL when --server is not given
    token: str | None = None  # its bearer token when --token is not given
    models_dir: Path | None = None  # a folder of .onnx models besides the installed ones
    default_model: str | None = None  # the model `auto` reports before a frame; None: runtime's

    @classmethod
    def from_environ(cls, environ: Mapping[str, str] = os.environ) -> ClientSettings:
        """The settings in `environ` (the process's environment unless given); a folder or
        model set but empty counts as unset."""
        folder = environ.get(MODELS_DIR)
        return cls(
            server=environ.get(SERVER),
            token=environ.get(TOKEN),
            models_dir=Path(folder) if folder else None,
            default_model=environ.get(DEFAULT_MODEL) or None,
        )


def client_settings() -> ClientSettings:
    """The client's settings in the process's environment now."""
    return ClientSettings.from_environ()
