"""The one inference pipeline: planar numpy buffers -> onnxruntime (+ custom ops) -> planar frame.

Used by the service, the evaluation and the benchmarks, so every reported figure is a figure
of the shipped path. Knows the graph interface of docs/model-interface.md, nothing about what a
model does inside. Buffers go in and the frame comes out as (C, H, W) float32 planes: the layout
of EXR channels and of the NCHW graph alike, so nothing is transposed or re-copied on the way.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import onnxruntime as ort

from quietframe.runtime.buffers import BUFFER_CHANNELS, BufferError, check_buffers, check_plane
from quietframe.runtime.oidn_prepass import (
    PREPASS_BUFFERS,
    OIDNPrepass,
    PrepassUnavailable,
    read_prepass,
)
from quietframe.runtime.ops_library import ops_library_path
from quietframe.runtime.sanitize import sanitize_buffer, sanitize_output
from quietframe.runtime.tiling import (
    DEFAULT_TILE_PIXELS,
    add_ballast,
    crop,
    model_geometry,
    place,
    tiles_of,
)


@dataclass(frozen=True)
class StateSpec:
    name: str
    channels: int
    scale: int = 1  # the tensor is ⌈H/scale⌉ × ⌈W/scale⌉ (e.g. a half-resolution history)

    def shape(self, height: int, width: int) -> tuple[int, int, int, int]:
        return (1, self.channels, -(-height // self.scale), -(-width // self.scale))


@dataclass(frozen=True)
class InputSpec:
    """An extra scalar graph input (metadata `quietframe.inputs`), fed from its default or a
    session/call option: e.g. the affinity model's `kernel_size`."""

    name: str
    dtype: str  # numpy dtype name, e.g. "int64"
    shape: tuple[int, ...]
    default: float | int
    allowed: tuple[float | int, ...] | None = None  # None: any value
    doc: str = ""

    def check(self, value: float | int) -> None:
        """ValueError for a value this input does not take."""
        if self.allowed is not None and value not in self.allowed:
            raise ValueError(f"{self.name} must be one of {list(self.allowed)}, got {value!r}")
        if np.dtype(self.dtype).kind in "iu" and not float(value).is_integer():
            raise ValueError(f"{self.name} is an integer, got {value!r}")  # not truncated

    def array(self, value: float | int) -> np.ndarray:
        self.check(value)
        return np.full(self.shape, value, dtype=self.dtype)

    def describe(self) -> str:
        """E.g. 'kernel_size (one of [5, 7, 9], default 5)', for messages and listings."""
        values = f"one of {list(self.allowed)}, " if self.allowed is not None else ""
        return f"{self.name} ({values}default {self.default})"


@dataclass(frozen=True)
class ModelInfo:
    name: str
    version: str
    path: Path
    required_buffers: tuple[str, ...]
    optional_buffers: tuple[str, ...]
    state_specs: tuple[StateSpec, ...]
    metadata: dict[str, str]
    metrics: dict = field(default_factory=dict)
    training: dict = field(default_factory=dict)
    inputs: tuple[InputSpec, ...] = ()

    def state_nbytes(self, height: int, width: int) -> int:
        return sum(4 * int(np.prod(s.shape(height, width))) for s in self.state_specs)


@dataclass
class DenoiseResult:
    color: np.ndarray  # (3, H, W) float32, finite
    state: dict[str, np.ndarray]  # feed back as the next frame's state
    sanitized: dict[str, int]  # replaced input values per buffer (see sanitize.py)
    missing: tuple[str, ...]  # optional buffers that were absent and fed as zeros


COLOR_STAGE_PREFIX = "color_from."  # state names of a prepass's color_from model


def compose_info(info: ModelInfo, color_stage: ModelInfo) -> ModelInfo:
    """A composition's interface: the buffers either part requires or reads, and both parts'
    state (the color_from model's under COLOR_STAGE_PREFIX), so sessions persist and budget it
    like any model's."""
    required = tuple(dict.fromkeys((*info.required_buffers, *color_stage.required_buffers)))
    optional = tuple(b for b in dict.fromkeys((*info.optional_buffers,
                                               *color_stage.optional_buffers))
                     if b not in required)
    states = tuple(StateSpec(COLOR_STAGE_PREFIX + s.name, s.channels, s.scale)
                   for s in color_stage.state_specs)
    return replace(info, required_buffers=required, optional_buffers=optional,
                   state_specs=(*info.state_specs, *states))


def check_options(info: ModelInfo, options: Mapping[str, float | int]) -> None:
    """The one check of run-time options against a model's extra inputs: ValueError naming
    what is wrong (an option the model does not declare, a value it does not take) and what
    the model takes instead."""
    specs = {spec.name: spec for spec in info.inputs}
    unknown = sorted(set(options) - set(specs))
    if unknown and not specs:
        raise ValueError(f"model {info.name!r} has no option {', '.join(unknown)}: "
                         "it takes no run-time options")
    if unknown:
        raise ValueError(f"model {info.name!r} has no option {', '.join(unknown)}; its options: "
                         + "; ".join(spec.describe() for spec in specs.values()))
    for name, value in options.items():
        try:
            specs[name].check(value)
        except ValueError as exc:
            raise ValueError(f"model {info.name!r}: {exc}") from None


def read_model_info(path: Path, metadata: Mapping[str, str]) -> ModelInfo:
    def load(key: str, default: str):
        return json.loads(metadata.get(f"quietframe.{key}", default))

    return ModelInfo(
        name=metadata.get("quietframe.name", path.stem),
        version=metadata.get("quietframe.version", "0"),
        path=path,
        required_buffers=tuple(load("buffers.required", '["color"]')),
        optional_buffers=tuple(load("buffers.optional", "[]")),
        state_specs=tuple(StateSpec(s["name"], int(s["channels"]), int(s.get("scale", 1)))
                          for s in load("state", "[]")),
        metadata=dict(metadata),
        metrics=load("metrics", "{}"),
        training=load("training", "{}"),
        inputs=tuple(
            InputSpec(i["name"], i["dtype"], tuple(i["shape"]), i["default"],
                      tuple(i["allowed"]) if i.get("allowed") is not None else None,
                      i.get("doc", ""))
            for i in load("inputs", "[]")
        ),
    )


_ops_lock = threading.Lock()


def make_session(path: Path, threads: int) -> ort.InferenceSession:
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    with _ops_lock:
        options.register_custom_ops_library(str(ops_library_path()))
    return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])


class Denoiser:
    """A loaded model; `denoise` is thread-safe (onnxruntime runs sessions concurrently).
    Frames above `tile_pixels` run in overlapping tiles (tiling.py) when the model card gives
    the geometry to make them seamless; None runs every frame whole.

    A model whose metadata names a prepass (quietframe.prepass, runtime/oidn_prepass.py) is a
    composition: the runtime runs OIDN on the frame first and feeds its output to the graph.
    Such a model raises PrepassUnavailable here when pyoidn is not installed. A prepass with
    `color_from` runs that model (its own Denoiser and state) first and gives OIDN its output.

    `options`: values for the model's extra inputs (`info.inputs`), e.g. {"kernel_size": 7};
    the metadata default for the others."""

    def __init__(
        self,
        model_path: str | Path,
        threads: int = 2,
        tile_pixels: int | None = DEFAULT_TILE_PIXELS,
        options: Mapping[str, float | int] | None = None,
    ) -> None:
        path = Path(model_path)
        if not path.is_file():
            raise FileNotFoundError(f"model file {path} does not exist")
        self.session = make_session(path, threads)
        meta = self.session.get_modelmeta().custom_metadata_map
        self.info = read_model_info(path, meta)
        self.geometry = model_geometry(meta)
        self.tile_pixels = tile_pixels
        self._output_names = [o.name for o in self.session.get_outputs()]
        self.input_names = {i.name for i in self.session.get_inputs()}
        settings = read_prepass(meta)
        try:
            self.prepass = OIDNPrepass(settings, num_threads=threads) if settings else None
        except PrepassUnavailable as exc:
            exc.model = self.info.name  # for the service's log line and error
            raise
        self._graph_states = self.info.state_specs
        self.color_stage: Denoiser | None = None
        if settings and settings.color_from:
            first = path.parent / settings.color_from
            if not first.is_file():
                raise FileNotFoundError(f"model {self.info.name!r} denoises the output of "
                                        f"{settings.color_from}, which is not installed next to "
                                        f"it ({first})")
            self.color_stage = Denoiser(first, threads, tile_pixels)
            self.info = compose_info(self.info, self.color_stage.info)
        self._option_feeds = self._options({}, options or {})

    def _options(self, base: Mapping[str, np.ndarray],
                 options: Mapping[str, float | int]) -> dict[str, np.ndarray]:
        """Feeds of the extra inputs: `base` (or the defaults) with `options` on top."""
        check_options(self.info, options)
        specs = {spec.name: spec for spec in self.info.inputs}
        feeds = {name: base[name] if name in base else spec.array(spec.default)
                 for name, spec in specs.items()}
        feeds |= {name: specs[name].array(value) for name, value in options.items()}
        return feeds

    def check(self, present: Iterable[str]) -> tuple[str, ...]:
        """The one check of a frame's buffers against the model: the absent optional ones;
        MissingBuffers when a required one is absent. The service calls it from the EXR header,
        before any pixel is decoded."""
        info = self.info
        return check_buffers(info.name, info.required_buffers, info.optional_buffers, present)

    def initial_state(self, height: int, width: int) -> dict[str, np.ndarray]:
        return {
            s.name: np.zeros(s.shape(height, width), np.float32)
            for s in self.info.state_specs
        }

    def color_stage_state(self, state: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """The color_from model's own state, out of this composition's state dict."""
        assert self.color_stage is not None
        return {s.name: state[COLOR_STAGE_PREFIX + s.name]
                for s in self.color_stage.info.state_specs}

    def _feeds(
        self, planes: Mapping[str, np.ndarray]
    ) -> tuple[dict[str, np.ndarray], dict[str, int], tuple[str, ...], tuple[int, int]]:
        missing = self.check(planes)
        if "color" not in planes:
            raise BufferError("a frame needs its color buffer")
        _, height, width = np.shape(planes["color"])
        feeds: dict[str, np.ndarray] = {}
        sanitized: dict[str, int] = {}
        for name in (*self.info.required_buffers, *self.info.optional_buffers):
            if name in missing:
                feeds[name] = np.zeros((1, BUFFER_CHANNELS[name], height, width), np.float32)
                continue
            check_plane(name, planes[name], height, width)
            clean, count = sanitize_buffer(name, planes[name])
            if count:
                sanitized[name] = count
            feeds[name] = np.ascontiguousarray(clean)[None]  # a view when already contiguous
        return feeds, sanitized, missing, (height, width)

    def denoise(
        self, planes: Mapping[str, np.ndarray], state: Mapping[str, np.ndarray] | None,
        options: Mapping[str, float | int] | None = None,
    ) -> DenoiseResult:
        """Denoise one frame of (C, H, W) float32 planes. `state` is the previous frame's
        `DenoiseResult.state`, or None to start from a fresh history (first frame, camera cut).
        `options` overrides the Denoiser's options for this call."""
        feeds, sanitized, missing, (height, width) = self._feeds(planes)
        feeds |= self._options(self._option_feeds, options) if options else self._option_feeds
        fresh = state is None
        color_state: dict[str, np.ndarray] = {}
        if self.prepass is not None:
            # The sanitised planes, so OIDN sees exactly what a plain graph would; an absent
            # aux buffer is left out (OIDN then runs without it), not given as zeros.
            oidn_planes = {name: feeds[name][0] for name in PREPASS_BUFFERS
                           if name not in missing}
            if self.color_stage is not None:
                first = self.color_stage.denoise(
                    {k: v[0] for k, v in feeds.items() if k in BUFFER_CHANNELS},
                    None if fresh else self.color_stage_state(state))
                oidn_planes["color"] = first.color
                color_state = {COLOR_STAGE_PREFIX + k: v for k, v in first.state.items()}
                if "denoised" in first.sanitized:
                    sanitized["color_from"] = first.sanitized["denoised"]
            feeds[self.prepass.settings.input] = self.prepass(oidn_planes)
        feeds = {k: v for k, v in feeds.items() if k in self.input_names}
        if state is None:
            state = self.initial_state(height, width)
        for spec in self._graph_states:
            tensor = state[spec.name]
            if tensor.shape != spec.shape(height, width):
                raise BufferError(
                    f"state {spec.name!r} has shape {tensor.shape}, frame is {height}x{width}"
                )
            feeds[f"state_in.{spec.name}"] = tensor
        if "reset" in self.input_names:  # a prepass-only graph has no history of its own
            feeds["reset"] = np.array([1.0 if fresh else 0.0], np.float32)
        outputs = self._run(feeds, height, width)
        color, bad = sanitize_output(outputs["denoised"][0])
        if bad:
            sanitized["denoised"] = bad
        return DenoiseResult(
            color=color,
            state={**{s.name: outputs[f"state_out.{s.name}"] for s in self._graph_states},
                   **color_state},
            sanitized=sanitized,
            missing=missing,
        )

    def _run(self, feeds: dict[str, np.ndarray], height: int, width: int) -> dict[str, np.ndarray]:
        """One run, or one per tile with each tile's interior put in place."""
        run = self.session.run
        if self.geometry is None or self.tile_pixels is None:
            return dict(zip(self._output_names, run(None, feeds), strict=True))
        motion = feeds.get("motion")
        tiles = list(tiles_of(height, width, self.geometry, motion, self.tile_pixels))
        if len(tiles) == 1:
            return dict(zip(self._output_names, run(None, feeds), strict=True))
        geometry, dy, dx = self.geometry, 0, 0
        ballast = geometry.depth_mean and "depth" in feeds
        mean_depth = float(feeds["depth"].mean(dtype=np.float64)) if ballast else 0.0
        outputs: dict[str, np.ndarray] = {}
        for tile in tiles:
            part = {k: crop(v, tile) if v.ndim == 4 else v for k, v in feeds.items()}
            if ballast:
                part, dy, dx = add_ballast(part, tile, height, width, mean_depth, geometry.align)
            for name, result in zip(self._output_names, run(None, part), strict=True):
                if name not in outputs:  # (N, C, H, W) of the whole frame
                    outputs[name] = np.empty((*result.shape[:2], height, width), result.dtype)
                place(outputs[name], tile, result, dy, dx)
        return outputs
