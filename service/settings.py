"""All service configuration in one typed object, read from `QUIETFRAME_*` environment variables."""

from __future__ import annotations

import os
from pathlib import Path

from pydantic import Field, SecretStr
from pydantic_settings import BaseSettings, SettingsConfigDict


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="QUIETFRAME_", extra="ignore")

    # Models: the installed ones (quietframe.models) plus any *.onnx in models_dir.
    models_dir: Path | None = None
    default_model: str | None = Field(
        None, description="model name for 'auto'; None: the runtime's default"
    )
    threads: int = Field(
        0, ge=0, description="onnxruntime intra-op threads per model; 0: CPU count"
    )
    workers: int = Field(0, ge=0, description="frames in flight at once; 0: CPUs / threads")

    # Limits. Sizes carry their unit in the name.
    max_body_mb: float = Field(1024.0, gt=0)
    max_width: int = Field(8192, ge=1)
    max_height: int = Field(8192, ge=1)
    max_sessions: int = Field(64, ge=1)
    session_ttl_s: float = Field(900.0, gt=0, description="idle sessions are deleted after this")
    history_budget_mb: float = Field(8192.0, gt=0, description="state + last reply of all sessions")

    # Durable sessions: with a directory, every session's state is written after each frame.
    state_dir: Path | None = None
    state_fsync: bool = Field(False, description="fsync state files (survive power loss, slower)")

    auth_token: SecretStr | None = Field(None, description="bearer token for /v1; None: no auth")
    log_level: str = "info"
    log_json: bool = True

    @property
    def max_body_bytes(self) -> int:
        return int(self.max_body_mb * 2**20)

    @property
    def history_budget_bytes(self) -> int:
        return int(self.history_budget_mb * 2**20)

    @property
    def model_threads(self) -> int:
        return self.threads or os.cpu_count() or 1

    @property
    def worker_count(self) -> int:
        # Each frame already runs on `threads` cores; more frames at once than cores / threads
        # only oversubscribe the CPU (onnxruntime's spinning threads then slow every frame).
        return self.workers or max(1, (os.cpu_count() or 1) // self.model_threads)
