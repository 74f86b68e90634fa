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
    # Memory of frames in flight (admission.py), beside the history budget: a frame reserves
    # its body, decoded channels, buffers, model working set, new state and reply before any of
    # it is allocated; the server's memory is then bounded by base + history + this budget.
    # An 8K float frame with 15 channels needs ~10.5 GiB; the default admits one at a time.
    memory_budget_mb: float = Field(
        12288.0, gt=0, description="frames in flight: bodies, decoding, model, reply"
    )
    admission_wait_s: float = Field(
        10.0, ge=0, description="a frame waits this long for memory, then gets 429"
    )
    max_uploads: int = Field(32, ge=1, description="frame bodies received at once; more get 429")
    max_uploads_per_session: int = Field(
        2, ge=1, description="frame bodies of one session received at once; more get 429 (a "
        "session's frames come one at a time: 2 leaves room for a retry beside a dropped upload "
        "the server has not seen end yet)"
    )
    # Slow uploads cannot hold every slot (upload_slots.py): while all are taken, an upload that
    # has had its share (the pause grace + its size at this rate) gives its slot to a new one.
    # 1 MiB/s (8.4 Mbit/s): a 4K multilayer frame of 290-475 MiB (15 float channels, ZIP to
    # uncompressed) has 5-8 min, enough from a 10 Mbit/s link (docs/reliability.md).
    upload_share_rate_kib_s: float = Field(
        1024.0, gt=0, description="while every upload slot is taken, an upload that has had "
        "body_read_timeout_s plus its body's size at this rate gives its slot to a new one (408)"
    )
    max_upload_s: float = Field(
        0.0, ge=0, description="the longest one frame body may take, slots wanted or not (408); "
        "0: body_read_timeout_s + max_body_mb at upload_share_rate_kib_s"
    )
    max_header_bytes: int = Field(
        16 << 20, ge=4096, description="EXR header (attributes of all parts) limit"
    )
    header_timeout_s: float = Field(
        10.0,
        gt=0,
        description="a connection whose request line and headers are not complete this long "
        "after it opened (or after the request's first byte) is closed",
    )
    max_connections: int = Field(
        0,
        ge=0,
        description="open connections; past it the one waiting longest for a request is closed. "
        "0: the open-file limit (ulimit -n) less a quarter of it (at least 64)",
    )
    min_body_rate_kib_s: float = Field(
        64.0,
        ge=0,
        description="after body_read_timeout_s of grace a body must arrive at this mean rate "
        "(408 otherwise: a drip of bytes cannot hold a connection); 0: no minimum",
    )

    # Durable sessions: with a directory, every session's state is written after each frame.
    state_dir: Path | None = None
    state_fsync: bool = Field(False, description="fsync state files (survive power loss, slower)")
    # Past one box (docs/deployment.md): replicas behind a load balancer that hashes the session
    # id share the sessions through Redis; a replica loads a session it does not hold from it.
    store_url: str | None = Field(
        None,
        description="redis://host:port/db or redis+cluster://seed:port: sessions shared by "
        "every replica (not state_dir)",
    )
    store_timeout_s: float = Field(
        10.0, gt=0, description="a store call that takes longer is a 503 (the frame is not lost)"
    )
    replica_id: str | None = Field(
        None, description="this replica's name in logs and stored records; None: the host name"
    )

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
    def memory_budget_bytes(self) -> int:
        return int(self.memory_budget_mb * 2**20)

    @property
    def oidn_memory_mb(self) -> float:
        """OIDN's scratch cap for one frame (its maxMemoryMB; past it OIDN tiles, at ~25% more
        CPU at 1080p): an eighth of a frame's share of the memory budget, at least 768 MiB.
        At the defaults (12 GiB, one frame at a time) 1536 MiB: a 1080p frame runs whole, even
        through OIDN's large network (quality high with clean aux: ~1.4 GiB, ~700 B a pixel,
        runtime/oidn_prepass.py)."""
        return max(768.0, self.memory_budget_mb / self.worker_count / 8)

    @property
    def min_body_rate_bytes_s(self) -> float:
        return self.min_body_rate_kib_s * 1024

    @property
    def upload_share_rate_bytes_s(self) -> float:
        return self.upload_share_rate_kib_s * 1024

    @property
    def upload_cap_s(self) -> float:
        """max_upload_s, or (0) the largest frame's share: the grace + max_body_mb at the share
        rate (1950 s at the defaults)."""
        return self.max_upload_s or (
            self.body_read_timeout_s + self.max_body_bytes / self.upload_share_rate_bytes_s)

    @property
    def model_threads(self) -> int:
        return self.threads or os.cpu_count() or 1

    @property
    def worker_count(self) -> int:
        # Each frame already runs on `threads` cores; more frames at once than cores / threads
        # only oversubscribe the CPU (onnxruntime's spinning threads then slow every frame).
        return self.workers or max(1, (os.cpu_count() or 1) // self.model_threads)
