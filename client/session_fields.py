"""A session's settings, as created: the one list of its fields, with their types, defaults and
meanings. The server's create request and public view (service/schemas.py), the session it
stores (service/session_spec.py) and this client's request (client/core.py) all derive from
`SessionFields`. It lives in the client package, not in the wire leaf (quietframe.wire, standard
library only), because it needs pydantic, which the client extra installs; the server imports it
from the client and never the other way round: a farm node installs only the client extra.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import AfterValidator, BaseModel, Field, field_validator

AUTO = "auto"  # the model that is chosen per shot by the server
Precision = Literal["input", "half", "float"]
Quality = Literal["fast", "balanced", "best"]
Compression = Literal[
    "input", "none", "rle", "zips", "zip", "piz", "pxr24", "b44", "b44a", "dwaa", "dwab"
]

# A finite number, not a boolean (strict: JSON true is not 1.0) nor NaN/Infinity (Python's json
# reads those literals).
Factor = Annotated[float, Field(strict=True, allow_inf_nan=False)]
MAX_LAYER_NAME_BYTES = 120  # two of them and ".R" fit in an EXR channel name (255 bytes)
# The largest magnitude of a model option's value: I-JSON's interoperable integers (RFC 7493),
# exact as a float64 and within every graph input's type (int64, float32). Python's int has no
# bound: 10**400 would pass as a JSON integer and overflow where it becomes a float.
MAX_OPTION_MAGNITUDE = 2**53 - 1
# The most frames a session may hold back for its look-ahead (docs/service.md, "Look-ahead")
MAX_LOOKAHEAD = 4


def _within_option_range(value: int | float) -> int | float:
    if abs(value) <= MAX_OPTION_MAGNITUDE:
        return value
    digits = len(str(abs(value))) if isinstance(value, int) else None
    got = f"an integer of {digits} digits" if digits and digits > 20 else f"{value:g}"
    raise ValueError(f"a model option's value is at most {MAX_OPTION_MAGNITUDE} (2**53 - 1) "
                     f"in magnitude; got {got}")


# A model option's value: an integer stays one (kernel_size 9), else a finite number.
OptionValue = Annotated[
    Annotated[int, Field(strict=True)] | Factor, AfterValidator(_within_option_range)
]


class SessionFields(BaseModel):
    """What a session is, fixed at its creation (the API's words for each field)."""

    width: int = Field(ge=1, description="frame width in pixels (EXR data window)")
    height: int = Field(ge=1, description="frame height in pixels")
    model: str = Field(
        AUTO,
        description="installed model name, or 'auto': chosen per shot from the first frame's "
        "buffers and noise level and the session's quality / latency_ms (docs/service.md)",
    )
    channels: dict[str, str | list[str]] | None = Field(
        None,
        description="own AOV mapping, buffer -> layer name or list of channel names; buffers "
        "not listed use the built-in alias table (Blender, Arnold, RenderMan, V-Ray, plain)",
    )
    motion_scale: tuple[Factor, Factor] = Field(
        (1.0, 1.0),
        description="factors for (x, y) of a mapped motion layer, to reach quietframe's "
        "convention: backward motion in pixels, y down",
    )
    camera: Literal["auto", "locked"] = Field(
        "auto",
        description="'locked': the camera is locked off for the whole session, so frames "
        "without motion vectors keep their history without being judged from their aux (which "
        "at 1-4 spp can look like motion); a cut the aux show still resets it. 'auto' judges "
        "every such frame (docs/service.md, 'Motion evidence')",
    )
    motion: Literal["estimated", "rendered-only"] = Field(
        "estimated",
        description="'estimated': where a moving frame has no motion vectors (Cycles with "
        "motion blur on writes none), a temporal model follows motion estimated from the aux "
        "buffers, trusted per pixel; 'rendered-only': such frames start the history afresh "
        "(docs/service.md, 'Motion evidence')",
    )
    layer: str | None = Field(
        None,
        description="view layer to denoise in a multilayer file (`<layer>.<pass>.<channel>`): "
        "the alias table looks only at its channels; the rest of the file passes through",
    )
    denoised_layer: str | None = Field(
        None,
        description="write the denoised colour as a new layer `<view layer>.<denoised_layer>` "
        "(e.g. 'Denoised') and keep the noisy beauty; unset: it replaces the beauty's R, G, B",
    )
    quality: Quality | None = Field(
        None,
        description="target for model 'auto': the cheapest model expected within 1 dB (fast), "
        "0.3 dB (balanced, the default) or 0 dB (best) of the best expected PSNR",
    )
    latency_ms: Annotated[float, Field(strict=True, gt=0, allow_inf_nan=False)] | None = Field(
        None,
        description="budget for model 'auto': expected denoise ms per frame at this session's "
        "size (from each model's measured 720p time); models over it are not chosen",
    )
    precision: Precision = Field(
        "input",
        description="pixel type of the denoised colour channels (every other channel keeps "
        "its own); 'input' is that of the input's colour",
    )
    compression: Compression = Field(
        "input",
        description="compression of the denoised EXR; 'input' keeps the input's (a header "
        "attribute) unless it is lossy (dwaa, dwab, b44, b44a, pxr24: then zip, so passed-through "
        "data keep their values), 'none' is the fastest to write",
    )
    lookahead: Annotated[int, Field(strict=True, ge=0, le=MAX_LOOKAHEAD)] = Field(
        0,
        description="frames the session holds back so frame t can use frames t+1..t+k: a "
        "frame's reply then carries the frame k before it (X-Quietframe-Frame), 202 while "
        "fewer than k+1 are pending, and POST .../frames/{t}/finish returns a pending frame "
        "at the end of a shot or chunk; 0 (default): each reply carries its own frame",
    )
    model_options: dict[str, OptionValue] = Field(
        default_factory=dict,
        description="run-time options of the model, name -> value, e.g. {'kernel_size': 9} for "
        "an affinity model; GET /v1/models lists each model's options and allowed values. With "
        "'auto' an option must be one some installed model has, and is given only to models "
        "that have it",
    )

    @field_validator("layer", "denoised_layer")
    @classmethod
    def _layer_name(cls, value: str | None) -> str | None:
        if value is None:
            return value
        if not value or value.startswith(".") or value.endswith("."):
            raise ValueError("a layer name is not empty and neither starts nor ends with '.'")
        # It becomes part of EXR channel names: no control characters (a NUL ends a name in
        # the file), and with the view layer and component within OpenEXR's 255 bytes.
        if any(ord(c) < 32 or ord(c) == 127 for c in value):
            raise ValueError("a layer name has no control characters (NUL, tab, newline, ...)")
        if len(value.encode()) > MAX_LAYER_NAME_BYTES:
            raise ValueError(f"a layer name is at most {MAX_LAYER_NAME_BYTES} bytes (UTF-8)")
        return value
