"""The stored form of a session: what its next frame reads, in the narrowest type that leaves
the results unchanged, and its reply as a recipe instead of a copy. Both stores write it
(session_store.record / unpack), so a folder and Redis hold the same bytes.

What the next frame reads of a history in the accumulation layout (model/temporal.py: radiance
3, depth 1, normal 3, history length 1; every temporal tier but the affinity model and
oidn-temporal-acc keeps its state so):
- radiance: blended into the new frame with weight ≥ 0.2, so an error in it decays at 0.8 a
  frame. float16 (relative step 2^-11); values beyond its range (±65504) are kept exactly as
  float32 patches, so nothing overflows to Inf.
- depth and normal: the surface test reads them with tolerance (|Δdepth| ≤ 10%, cos > 0.9,
  history_valid), but the aligned accumulation's repeated-sample test compares them with the
  next frame's to the last bit (model/temporal.repeated_sample), where rounding would read as
  a new sample. float16 (with patches) only where every value is a float16 already (a half
  EXR's aux), else float32; the stages of a composition hold the frame's same depth and
  normal, stored once.
- history length: whole numbers 1..6; uint8 where every value is one (else float32).
The motion probe stays float32: on a locked-off shot the motion test compares it with the next
frame's to the last bit, where rounding would read as a change (runtime/motion_evidence.py).
A state of any other layout is stored as it is (float32). experiments/state_codec.py
measures that the rounding leaves PSNR and flicker within 0.01 dB / 1% on the Cycles zoo and
test sequence at 1-64 spp.

The aux planes (depth, normal, history length, probe) are smooth or constant over large areas:
they are stored zlib-compressed (level 1) after a byte shuffle; radiance is not (noise barely
compresses, and it is most of the bytes).

Nothing non-finite is stored: encode writes 0 for a NaN or ±Inf (as the runtime's output guard
does), and decode refuses a record that would give one back (ValueError: the store treats the
record as damaged and the session continues from a fresh history).

The reply is the request's EXR with the denoised colour written in (exr_codec.encode). Where
the colour is a plane of the state (the oidn-history tiers' output history), the record keeps a
recipe (`ReplyRecipe`: channel names, pixel types, attributes) and no copy: a retry resends the
same body, checked against the stored digest, and the reply is written again from that body and
the stored plane, byte for byte the same, on whichever replica answers it. A float32 reply
channel needs the plane exact: it is then stored as float32.

`encode` also returns the state as the record holds it: the replica that wrote it continues
from exactly what another replica (or this one after a restart) would load, so a failover or a
restart changes no pixel.
"""

from __future__ import annotations

import zlib
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass

import numpy as np

from quietframe.runtime.motion_evidence import STREAM_STATES
from quietframe.service import frames

FORMAT = 1  # meta["codec"]["format"]; a record without meta["codec"] is the float32 form
HALF_MAX = np.float32(np.finfo(np.float16).max)
ZLIB_LEVEL = 1  # ~100 MB/s: a 1080p frame's aux planes in ~0.2 s; higher levels gain little
# Patches beyond this share of a plane cost more than float32 (8 bytes each against 4 - 2)
MAX_PATCH_SHARE = 1 / 8
# The accumulation layout: (role, first channel, end) of an 8-channel state named so
ACCUMULATION = (("radiance", 0, 3), ("depth", 3, 4), ("normal", 4, 7), ("count", 7, 8))
ACCUMULATION_NAME, ACCUMULATION_CHANNELS = "accumulation", 8
LOSSY = frozenset({"radiance"})  # float16 with patches
HALF_IF_EXACT = frozenset({"depth", "normal"})  # float16 with patches where that loses nothing
COMPRESSED = frozenset({"depth", "normal", "count", "probe"})
SHARED = frozenset({"depth", "normal"})  # equal planes of two stages are stored once
KINDS = {"f32": np.float32, "f16": np.float16, "u8": np.uint8}


@dataclass(frozen=True)
class ReplyRecipe:
    """How to write a frame's reply again from its request body: exr_codec.encode of the
    decoded body with the colour from state `tensor`'s channels `first`..`first`+2 (float32
    channels written at `dtypes`: the session's precision, a half one clamped to ±65504)."""

    tensor: str
    first: int
    dtypes: tuple[str, ...]  # numpy names, one per R, G, B
    color_channels: tuple[str, ...]
    precision: str
    compression: str
    denoised_layer: str | None
    extra: dict[str, str]

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: Mapping) -> ReplyRecipe:
        return cls(str(d["tensor"]), int(d["first"]), tuple(map(str, d["dtypes"])),
                   tuple(map(str, d["color_channels"])), str(d["precision"]),
                   str(d["compression"]), d["denoised_layer"], dict(d["extra"]))


@dataclass
class Encoded:
    """A session's state and reply colour as stored: `layout` (JSON, in the meta), `planes`
    (uint8 arrays, one stored member each), and `state`, the state as decoding gives it back."""

    layout: dict
    planes: list[np.ndarray]
    state: dict[str, np.ndarray]
    reply: bool  # the recipe's colour is in the record (the reply needs no body)


def reply_recipe(color: np.ndarray, state: Mapping[str, np.ndarray],
                 dtypes: Sequence[type], color_channels: Sequence[str], precision: str,
                 compression: str, denoised_layer: str | None,
                 extra: Mapping[str, str]) -> ReplyRecipe | None:
    """The recipe of a reply whose denoised (3, H, W) `color` equals a radiance plane of
    `state` (the output history's), else None (the store keeps the reply's body)."""
    for name, tensor in state.items():
        if _roles(name, tensor) is not None and np.array_equal(tensor[0, 0:3], color):
            return ReplyRecipe(name, 0, tuple(np.dtype(d).name for d in dtypes),
                               tuple(color_channels), precision, compression, denoised_layer,
                               dict(extra))
    return None


def rebuild_reply(recipe: ReplyRecipe, color: np.ndarray, body: bytes | bytearray) -> bytes:
    """The reply's bytes again, from the request `body` it answered (the caller has checked its
    digest) and the stored `color` (3, H, W) float32: what process_frame wrote."""
    frame = frames.decode(body, {"color": frames.Source(recipe.color_channels, "stored")})
    return frames.encode_denoised(np.asarray(color, np.float32), frame, recipe.color_channels,
                                  recipe.precision, recipe.extra, recipe.compression,
                                  recipe.denoised_layer)[0]


# ---- encode --------------------------------------------------------------------------------------


def encode(state: Mapping[str, np.ndarray], recipe: ReplyRecipe | None = None) -> Encoded:
    """The stored form of `state` (and of `recipe`'s colour plane, when it is one of them)."""
    exact = _exact_channels(state, recipe)
    planes: list[np.ndarray] = []
    descriptors: list[dict] = []
    decoded: list[np.ndarray] = []  # each plane's values as decoding gives them
    shared: list[tuple[str, int, np.ndarray]] = []  # (role, plane, source) of SHARED planes
    tensors: dict[str, dict] = {}
    stored: dict[str, np.ndarray] = {}
    for name, tensor in state.items():
        tensor = _finite(np.asarray(tensor, np.float32))
        back, parts = tensor, []
        for role, start, end in _parts(name, tensor):
            source = tensor[:, start:end] if tensor.ndim == 4 else tensor
            index = next((i for r, i, s in shared if r == role and np.array_equal(s, source)),
                         None)
            if index is None:
                blob, descriptor, values = _encode_plane(source, role, (name, start) in exact)
                index = len(planes)
                planes.append(blob)
                descriptors.append(descriptor)
                decoded.append(values)
                if role in SHARED:
                    shared.append((role, index, source))
            if decoded[index] is not source:  # rounded: the state continues as stored
                if tensor.ndim != 4:
                    back = decoded[index]
                else:
                    back = tensor.copy() if back is tensor else back
                    back[:, start:end] = decoded[index]
            parts.append([index, start, end])
        tensors[name] = {"shape": list(tensor.shape), "parts": parts}
        stored[name] = back
    layout = {"format": FORMAT, "planes": descriptors, "tensors": tensors}
    return Encoded(layout, planes, stored, recipe is not None and recipe.tensor in state)


def _exact_channels(state: Mapping[str, np.ndarray],
                    recipe: ReplyRecipe | None) -> set[tuple[str, int]]:
    """(tensor, first channel) of the plane a float32 reply channel is read from: kept exact."""
    if recipe is None or recipe.tensor not in state or all(
            d == "float16" for d in recipe.dtypes):
        return set()
    return {(recipe.tensor, recipe.first)}


def _roles(name: str, tensor: np.ndarray) -> tuple | None:
    if (name.rpartition(".")[2] == ACCUMULATION_NAME and tensor.ndim == 4
            and tensor.shape[1] == ACCUMULATION_CHANNELS):
        return ACCUMULATION
    return None


def _parts(name: str, tensor: np.ndarray) -> tuple[tuple[str, int, int], ...]:
    roles = _roles(name, tensor)
    if roles is not None:
        return roles
    channels = tensor.shape[1] if tensor.ndim == 4 else tensor.shape[0]
    return (("probe" if name in STREAM_STATES else "exact", 0, channels),)


def _finite(x: np.ndarray) -> np.ndarray:
    """`x` with 0 for every NaN and ±Inf (a copy only where there is one)."""
    if np.isfinite(x).all():
        return x
    return np.where(np.isfinite(x), x, np.float32(0))


def _encode_plane(x: np.ndarray, role: str, exact: bool
                  ) -> tuple[np.ndarray, dict, np.ndarray]:
    """(blob, descriptor, the values as decoded) of one plane."""
    kind, data, patches, decoded = "f32", x, None, x
    if role == "count" and _whole_bytes(x):
        kind, data = "u8", x.astype(np.uint8)
    elif (role in LOSSY or role in HALF_IF_EXACT) and not exact:
        half = _half(x)
        if half is not None and (role in LOSSY or np.array_equal(half[2], x)):
            kind, (data, patches, decoded) = "f16", half
    raw = np.ascontiguousarray(data)
    compress = role in COMPRESSED
    body = _shuffle(raw) if compress else raw.reshape(-1).view(np.uint8)
    if compress:
        body = np.frombuffer(zlib.compress(body, ZLIB_LEVEL), np.uint8)
    descriptor = {"kind": kind, "shape": list(x.shape), "zlib": compress, "bytes": body.size,
                  "patches": 0}
    if patches is not None:
        index, values = patches
        descriptor["patches"] = int(index.size)
        body = np.concatenate([body, index.view(np.uint8), values.view(np.uint8)])
    return body, descriptor, decoded


def _whole_bytes(x: np.ndarray) -> bool:
    return bool(x.size == 0 or (x.min() >= 0 and x.max() <= 255
                                and np.array_equal(x, np.round(x))))


def _half(x: np.ndarray) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray] | None,
                                  np.ndarray] | None:
    """(float16 values clamped to ±65504, (flat indices, float32 values) of those beyond, the
    values as decoded), or None where too many are beyond for float16 to pay."""
    over = None
    if x.size and (x.max() > HALF_MAX or x.min() < -HALF_MAX):
        over = np.flatnonzero(np.abs(x) > HALF_MAX)
        if over.size > MAX_PATCH_SHARE * x.size or x.size >= 2**32:
            return None
        half = np.clip(x, -HALF_MAX, HALF_MAX).astype(np.float16)
    else:
        half = x.astype(np.float16)
    decoded = half.astype(np.float32)
    patches = None
    if over is not None:
        values = x.reshape(-1)[over]
        decoded.reshape(-1)[over] = values
        patches = (over.astype(np.uint32), values.astype(np.float32))
    return half, patches, decoded


def _shuffle(raw: np.ndarray) -> np.ndarray:
    """The bytes of `raw` grouped by their place in each value (all first bytes, then all
    second...): exponents and high bytes of neighbours repeat, which zlib finds."""
    size = raw.dtype.itemsize
    flat = raw.reshape(-1).view(np.uint8)
    return flat if size == 1 else np.ascontiguousarray(flat.reshape(-1, size).T).reshape(-1)


def _unshuffle(flat: np.ndarray, size: int) -> np.ndarray:
    return flat if size == 1 else np.ascontiguousarray(flat.reshape(size, -1).T).reshape(-1)


# ---- decode --------------------------------------------------------------------------------------


def decode(layout: Mapping, planes: Sequence[np.ndarray],
           shapes: Mapping[str, tuple[int, ...]]) -> dict[str, np.ndarray]:
    """The state of a stored record, each tensor of its `shapes` (the session's model's);
    ValueError (or KeyError, TypeError) for anything that does not add up: another shape, a
    plane of the wrong length, an index out of range, a non-finite value."""
    if layout.get("format") != FORMAT:
        raise ValueError(f"unknown state format {layout.get('format')!r}")
    descriptors = layout["planes"]
    if len(descriptors) != len(planes):
        raise ValueError(f"{len(planes)} stored planes, the layout lists {len(descriptors)}")
    for name, tensor in layout["tensors"].items():
        if tuple(tensor["shape"]) != shapes.get(name):
            raise ValueError(f"state {name} has shape {tuple(tensor['shape'])}; the session's "
                             f"model expects {shapes.get(name, 'no such state')}")
    # A plane holds channels of one tensor: never more values than the largest the session's
    # model keeps. The bound comes from the session, not the record (a record is untrusted: a
    # shape of [-1] once made the inflate unbounded, a zlib bomb).
    limit = max((int(np.prod(shape)) for shape in shapes.values()), default=0)
    values = [_decode_plane(d, p, limit) for d, p in zip(descriptors, planes, strict=True)]
    state = {}
    for name, tensor in layout["tensors"].items():
        shape = tuple(int(n) for n in tensor["shape"])
        out = np.empty(shape, np.float32)
        channels = shape[1] if len(shape) == 4 else shape[0]
        filled = np.zeros(channels, bool)
        for index, start, end in tensor["parts"]:
            if not (0 <= start < end <= channels and 0 <= index < len(values)):
                raise ValueError(f"{name}: channels {start}:{end} of {channels}, plane {index}")
            target = out[:, start:end] if len(shape) == 4 else out
            target[...] = values[index].reshape(target.shape)
            filled[start:end] = True
        if not filled.all():
            raise ValueError(f"{name}: channels without a stored plane")
        state[name] = out
    return state


def _decode_plane(descriptor: Mapping, blob: np.ndarray, limit: int) -> np.ndarray:
    """One stored plane, of at most `limit` values (ValueError beyond: checked before a byte
    is inflated)."""
    dtype = np.dtype(KINDS[descriptor["kind"]])
    shape = tuple(int(n) for n in descriptor["shape"])
    count = int(np.prod(shape, dtype=np.int64)) if shape else 1
    if any(n <= 0 for n in shape) or count > limit:
        raise ValueError(f"a stored plane of shape {list(shape)}: the session's state holds "
                         f"at most {limit} values a plane")
    size, patches = int(descriptor["bytes"]), int(descriptor["patches"])
    if size < 0 or patches < 0:
        raise ValueError("a stored plane's length does not match its layout")
    if blob.dtype != np.uint8 or blob.ndim != 1 or blob.size != size + 8 * patches:
        raise ValueError("a stored plane's length does not match its layout")
    body = blob[:size]
    if descriptor["zlib"]:
        inflate = zlib.decompressobj()
        try:
            raw = inflate.decompress(body.tobytes(), count * dtype.itemsize + 1)
        except zlib.error as exc:
            raise ValueError(f"a stored plane does not inflate: {exc}") from None
        if len(raw) != count * dtype.itemsize or not inflate.eof:
            raise ValueError("a stored plane does not inflate to its size")
        flat = _unshuffle(np.frombuffer(raw, np.uint8), dtype.itemsize)
    elif body.size != count * dtype.itemsize:
        raise ValueError("a stored plane's length does not match its layout")
    else:
        flat = body
    values = flat.view(dtype).astype(np.float32)
    if patches:
        index = blob[size:size + 4 * patches].view(np.uint32)
        if index.max() >= count:
            raise ValueError("a patch lies outside its plane")
        values[index] = blob[size + 4 * patches:].view(np.float32)
    if not np.isfinite(values).all():
        raise ValueError("a stored plane holds a non-finite value")
    return values.reshape(shape)
