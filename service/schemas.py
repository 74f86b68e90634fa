"""Request and response bodies of the /v1 API (separate create / public shapes)."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field, field_validator

from quietframe.client.session_fields import SessionFields
from quietframe.service.frames import validate_mapping


class SessionCreate(SessionFields):
    """One camera sequence: frames of one size, denoised in order with temporal history."""

    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={
            "examples": [
                {"width": 1920, "height": 1080},
                {
                    "width": 1280,
                    "height": 720,
                    "model": "auto",
                    "precision": "half",
                    "channels": {"color": "beauty", "albedo": ["alb.R", "alb.G", "alb.B"]},
                },
            ]
        },
    )

    @field_validator("channels")
    @classmethod
    def _known_buffers(cls, value: dict | None) -> dict | None:
        if value:
            validate_mapping(value)
        return value


class ModelRef(BaseModel):
    name: str
    version: str


class StageTimings(BaseModel):
    decode: float = 0.0
    denoise: float = 0.0
    encode: float = 0.0
    total: float = 0.0


class ChoicePublic(BaseModel):
    model: str
    reason: str
    spp: float | None = Field(description="noise level as equivalent samples per pixel")
    noise_source: str = Field(description="header attribute read, 'estimate' or 'unknown'")
    buffers: list[str] = Field(description="buffers the deciding frame carried")
    log2_sigma: float | None = Field(
        None, description="log2 of the deciding frame's measured noise statistic")
    expected_psnr: float | None = Field(
        None, description="the validation shots' average PSNR for the model at this noise "
        "(its tables), not a prediction for this shot")
    expected_ms: float | None = Field(
        None, description="the tables' time per frame: 720p on the machine that made them, "
        "scaled to the session's size")
    measured_ms: float | None = Field(
        None, description="this server's median denoise time per frame of the model at the "
        "session's size, over `measured_frames` recent frames; None before any")
    measured_frames: int = Field(0, description="frames `measured_ms` is the median of")
    measured_size: str | None = Field(None, description="the frame size measured, WxH")


class SessionPublic(SessionFields):
    """A session as created (its fields, `model` the model in use), and how it is doing."""

    id: str = Field(description="unguessable session id (the capability to use the session)")
    model: ModelRef | None = Field(  # type: ignore[assignment]  # as created: requested_model
        None, description="the model in use; none until the first frame of an 'auto' session "
        "has chosen one")
    required_buffers: list[str] = Field(description="buffers every frame must carry")
    optional_buffers: list[str] = Field(description="buffers used when present (else defaults)")
    requested_model: str = Field(description="as created: a model name or 'auto'")
    choice: ChoicePublic | None = Field(
        None, description="model 'auto': the current shot's choice and why (None: no frame yet)"
    )
    created_at: str
    frames_done: int = 0
    last_index: int | None = None
    resets: int = Field(0, description="frames that started from a zero history")
    sources: dict[str, list[str]] = Field(
        default_factory=dict, description="EXR channels used for each buffer in the last frame"
    )
    missing: list[str] = Field(default_factory=list, description="absent in the last frame")
    mean_ms: StageTimings = Field(default_factory=StageTimings)
    last_ms: StageTimings = Field(default_factory=StageTimings)
    memory_bytes: int = Field(0, description="history state + last reply held in memory")
    reserved_bytes: int = Field(0, description="what the session counts against the budget")
    expires_in_s: float = Field(description="deleted after this much more idle time")
    durable: bool = Field(False, description="state is written to the state directory")
    pending: list[int] = Field(
        default_factory=list,
        description="look-ahead sessions: the frames held back, oldest first (each leaves with "
        "the reply to a later frame, or through POST .../frames/{index}/finish)")


class BufferSpec(BaseModel):
    name: str
    channels: int


class ModelOption(BaseModel):
    name: str = Field(description="the key in a session's model_options")
    default: int | float = Field(description="the value when a session does not set it")
    allowed: list[int | float] | None = Field(description="the values it takes; None: any")
    minimum: float | None = Field(default=None, description="the smallest value it takes")
    doc: str = ""


class ModelPublic(BaseModel):
    name: str
    version: str
    file: str
    default: bool
    architecture: dict | str | None = None
    required_buffers: list[str]
    optional_buffers: list[str]
    state: list[BufferSpec]
    options: list[ModelOption] = Field(
        default_factory=list, description="run-time options a session can set (model_options)")
    metrics: dict = Field(description="validation error and speed figures from the model card")
    training: dict = Field(description="training data and settings from the model card")


class ModelList(BaseModel):
    models: list[ModelPublic]
    default: str


class ErrorBody(BaseModel):
    error: str = Field(description="machine-readable code", examples=["missing_channels"])
    detail: str = Field(description="what went wrong and what to do about it")


class Health(BaseModel):
    status: str
    detail: dict = Field(default_factory=dict)
