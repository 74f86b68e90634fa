"""The one inference pipeline: numpy buffers -> onnxruntime (+ custom ops) -> numpy frame.

Used by the service, the evaluation and the benchmarks, so every reported figure is a figure
of the shipped path. Knows the graph interface of docs/model-interface.md, nothing about what a
model does inside.
"""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import onnxruntime as ort

from quietframe.export import ops_library_path
from quietframe.runtime.sanitize import sanitize_buffer, sanitize_output

BUFFER_CHANNELS = {"color": 3, "albedo": 3, "normal": 3, "depth": 1, "motion": 2}


class BufferError(ValueError):
    """A frame's buffers do not fit the model: missing, wrong shape, or mismatched sizes."""


@dataclass(frozen=True)
class StateSpec:
    name: str
    channels: int


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


@dataclass
class DenoiseResult:
    color: np.ndarray  # (H, W, 3) float32, finite
    state: dict[str, np.ndarray]  # feed back as the next frame's state
    sanitized: dict[str, int]  # replaced input values per buffer (see sanitize.py)
    missing: tuple[str, ...]  # optional buffers that were absent and filled with defaults
    timings_ms: dict[str, float]


def read_model_info(path: Path, metadata: Mapping[str, str]) -> ModelInfo:
    def load(key: str, default: str):
        return json.loads(metadata.get(f"quietframe.{key}", default))

    return ModelInfo(
        name=metadata.get("quietframe.name", path.stem),
        version=metadata.get("quietframe.version", "0"),
        path=path,
        required_buffers=tuple(load("buffers.required", '["color"]')),
        optional_buffers=tuple(load("buffers.optional", "[]")),
        state_specs=tuple(StateSpec(s["name"], int(s["channels"])) for s in load("state", "[]")),
        metadata=dict(metadata),
        metrics=load("metrics", "{}"),
        training=load("training", "{}"),
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


def to_nchw(array: np.ndarray, channels: int) -> np.ndarray:
    if array.ndim == 2:
        array = array[:, :, None]
    return np.ascontiguousarray(array[:, :, :channels].transpose(2, 0, 1)[None])


class Denoiser:
    """A loaded model; `denoise` is thread-safe (onnxruntime runs sessions concurrently)."""

    def __init__(self, model_path: str | Path, threads: int = 2) -> None:
        path = Path(model_path)
        if not path.is_file():
            raise FileNotFoundError(f"model file {path} does not exist")
        self.session = make_session(path, threads)
        meta = self.session.get_modelmeta().custom_metadata_map
        self.info = read_model_info(path, meta)
        self._output_names = [o.name for o in self.session.get_outputs()]

    def initial_state(self, height: int, width: int) -> dict[str, np.ndarray]:
        return {
            s.name: np.zeros((1, s.channels, height, width), np.float32)
            for s in self.info.state_specs
        }

    def state_nbytes(self, height: int, width: int) -> int:
        return sum(4 * s.channels * height * width for s in self.info.state_specs)

    def _prepare(
        self, buffers: Mapping[str, np.ndarray]
    ) -> tuple[dict[str, np.ndarray], dict[str, int], tuple[str, ...], tuple[int, int]]:
        missing_required = [b for b in self.info.required_buffers if b not in buffers]
        if missing_required:
            raise BufferError(
                f"missing required buffers {missing_required}; got {sorted(buffers)}, "
                f"model {self.info.name} needs {list(self.info.required_buffers)} "
                f"(optional: {list(self.info.optional_buffers)})"
            )
        height, width = np.shape(buffers["color"])[:2]
        feeds: dict[str, np.ndarray] = {}
        sanitized: dict[str, int] = {}
        missing: list[str] = []
        for name in (*self.info.required_buffers, *self.info.optional_buffers):
            channels = BUFFER_CHANNELS[name]
            if name not in buffers:
                missing.append(name)  # documented default: zeros (motion: static camera)
                feeds[name] = np.zeros((1, channels, height, width), np.float32)
                continue
            array = np.asarray(buffers[name])
            have = 1 if array.ndim == 2 else array.shape[-1] if array.ndim == 3 else -1
            if array.shape[:2] != (height, width) or have < channels:
                raise BufferError(
                    f"buffer {name!r} has shape {array.shape}; expected ({height}, {width}, "
                    f"{channels}) to match color"
                )
            clean, count = sanitize_buffer(name, array)
            if count:
                sanitized[name] = count
            feeds[name] = to_nchw(clean, channels)
        return feeds, sanitized, tuple(missing), (height, width)

    def denoise(
        self,
        buffers: Mapping[str, np.ndarray],
        state: Mapping[str, np.ndarray] | None,
        reset: bool,
    ) -> DenoiseResult:
        start = time.perf_counter()
        feeds, sanitized, missing, (height, width) = self._prepare(buffers)
        if state is None:
            state, reset = self.initial_state(height, width), True
        for spec in self.info.state_specs:
            tensor = state[spec.name]
            if tensor.shape != (1, spec.channels, height, width):
                raise BufferError(
                    f"state {spec.name!r} has shape {tensor.shape}, frame is {height}x{width}"
                )
            feeds[f"state_in.{spec.name}"] = tensor
        feeds["reset"] = np.array([1.0 if reset else 0.0], np.float32)
        prepared = time.perf_counter()
        outputs = self.session.run(None, feeds)
        ran = time.perf_counter()
        result = dict(zip(self._output_names, outputs, strict=True))
        color, bad = sanitize_output(result["denoised"][0].transpose(1, 2, 0))
        if bad:
            sanitized["denoised"] = bad
        new_state = {s.name: result[f"state_out.{s.name}"] for s in self.info.state_specs}
        done = time.perf_counter()
        return DenoiseResult(
            color=np.ascontiguousarray(color),
            state=new_state,
            sanitized=sanitized,
            missing=missing,
            timings_ms={
                "prepare": 1e3 * (prepared - start),
                "model": 1e3 * (ran - prepared),
                "finish": 1e3 * (done - ran),
            },
        )
