"""All service configuration in one typed object, read from `QUIETFRAME_*` environment variables."""

from __future__ import annotations

import os
from pathlib import Path

from pydantic import Field, SecretStr, field_validator
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
    # An 8K UHD (7680x4320) multi-layer render with the layers a denoiser needs and a renderer
    # writes beside them (beauty RGBA, albedo, normal, depth, vector XYZW: 15 channels) is
    # 1898 MiB as float32 without compression, the largest such a file gets (compression only
    # shrinks it); 1920 MiB adds the offset tables and headers. Every body is also held to its
    # own header's uncompressed size as soon as the header has arrived (frames.py).
    max_body_mb: float = Field(1920.0, gt=0, description="frame (EXR) body limit")
    max_json_body_bytes: int = Field(
        8192, ge=256, description="JSON body limit (a session with a channel mapping: ~1 KiB)"
    )
    body_read_timeout_s: float = Field(
        30.0, gt=0, description="a body that sends no byte for this long gets 408"
    )
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

    @field_validator("auth_token")
    @classmethod
    def _token_not_empty(cls, value: SecretStr | None) -> SecretStr | None:
        # An empty token would turn auth on with an empty secret (a bare "Bearer" passes).
        if value is not None and not value.get_secret_value().strip():
            raise ValueError(
                "QUIETFRAME_AUTH_TOKEN is set but empty; unset it for no auth or set a secret"
            )
        return value

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
