"""The one inference pipeline: planar numpy buffers -> onnxruntime (+ custom ops) -> planar frame.

Used by the service, the evaluation and the benchmarks, so every reported figure is a figure
of the shipped path. Knows the graph interface of docs/model-interface.md, nothing about what a
model does inside: what it knows of a model comes from its card (runtime/card.py). Buffers go
in and the frame comes out as (C, H, W) float32 planes: the layout of EXR channels and of the
NCHW graph alike, so nothing is transposed or re-copied on the way.
"""

from __future__ import annotations

import threading
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnxruntime as ort

from quietframe.runtime.buffers import BUFFER_CHANNELS, BufferError, check_buffers, check_plane
from quietframe.runtime.card import (
    OUTPUT,
    RESET,
    STATE_IN,
    STATE_OUT,
    GraphStage,
    ModelCard,
    OIDNStage,
    StateSpec,
)
from quietframe.runtime.oidn_prepass import (
    PREPASS_BUFFERS,
    OIDNFilters,
    OIDNPrepass,
    PrepassUnavailable,
)
from quietframe.runtime.ops_library import ops_library_path
from quietframe.runtime.sanitize import sanitize_buffer, sanitize_output
from quietframe.runtime.scalar_inputs import InputSpec
from quietframe.runtime.statistics import split_statistics
from quietframe.runtime.tiling import (
    UNTILED_BYTES_PER_PIXEL,
    max_memory_mb_default,
    run_tiled,
    tile_bytes_per_pixel,
    tile_pixels_for,
)

__all__ = ["BY_MEMORY", "DenoiseResult", "Denoiser", "InputSpec", "ModelInfo", "StateSpec",
           "check_options", "read_model_info"]

BY_MEMORY = "by_memory"  # Denoiser(tile_pixels=...): tiles sized by max_memory_mb


@dataclass(frozen=True)
class ModelInfo:
    """A loaded model's interface as callers see it: for a composition, the buffers every stage
    reads and the state of every stage (each stage's under its namespace)."""

    name: str
    version: str
    path: Path
    required_buffers: tuple[str, ...]
    optional_buffers: tuple[str, ...]
    state_specs: tuple[StateSpec, ...]
    card: ModelCard
    inputs: tuple[InputSpec, ...] = ()

    @property
    def metrics(self) -> dict:
        """`quietframe.metrics` as written (the API lists it)."""
        return self.card.metrics()

    @property
    def training(self) -> dict:
        return dict(self.card.training)

    @property
    def metadata(self) -> dict[str, str]:
        """The card as metadata_props (what an exporter writes)."""
        return self.card.to_props()

    def state_nbytes(self, height: int, width: int) -> int:
        return sum(4 * int(np.prod(s.shape(height, width))) for s in self.state_specs)


def model_info(path: Path, card: ModelCard, parts: Iterable[tuple[GraphStage, ModelCard]] = ()
               ) -> ModelInfo:
    """The interface of `card`'s model; `parts`: its other graph stages with their cards."""
    cards = [c for _, c in parts]
    required = tuple(dict.fromkeys(b for c in (card, *cards) for b in c.required))
    optional = tuple(b for b in dict.fromkeys(b for c in (card, *cards) for b in c.optional)
                     if b not in required)
    states = tuple(StateSpec(stage.state_key(s.name), s.channels, s.scale)
                   for stage, c in parts for s in c.state)
    inputs = tuple({i.name: i for c in (*cards, card) for i in c.inputs}.values())
    return ModelInfo(card.name, card.version, path, required, optional,
                     (*card.state, *states), card, inputs)


def read_model_info(path: Path, metadata: Mapping[str, str]) -> ModelInfo:
    """A single graph's interface from its metadata_props (no composition resolved)."""
    return model_info(path, ModelCard.from_props(metadata, path.stem))


@dataclass
class DenoiseResult:
    color: np.ndarray  # (3, H, W) float32, finite
    state: dict[str, np.ndarray]  # feed back as the next frame's state
    sanitized: dict[str, int]  # replaced input values per buffer (see sanitize.py)
    missing: tuple[str, ...]  # optional buffers that were absent and fed as zeros
    oidn: np.ndarray | None = None  # (3, H, W) the last OIDN stage's output (a composition's)


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


_ops_lock = threading.Lock()


def make_session(model: Path | bytes, threads: int,
                 memory_patterns: bool = True) -> ort.InferenceSession:
    """`memory_patterns` False for tiled runs: onnxruntime plans one block per input shape and
    keeps each in its arena, so tiles of four shapes (interior, right, bottom, corner) held
    ~1.9 GiB more at 4K (affinity-h16-k5gc: +4.35 GiB peak RSS with patterns, +2.45 without);
    whole frames keep them (a few % faster per 720p frame)."""
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    options.enable_mem_pattern = memory_patterns
    with _ops_lock:
        options.register_custom_ops_library(str(ops_library_path()))
    source = model if isinstance(model, bytes) else str(model)
    return ort.InferenceSession(source, options, providers=["CPUExecutionProvider"])


class TiledGraph:
    """A graph as its tiles run it: without memory patterns (make_session), and with its
    frame-wide statistics computed on the whole frame and fed to every tile
    (runtime/statistics.py)."""

    def __init__(self, path: Path, threads: int) -> None:
        split = split_statistics(path)
        self.session = make_session(split.tiles if split else path, threads,
                                    memory_patterns=False)
        self._split = split
        self._statistics = make_session(split.statistics, threads) if split else None
        self._inputs = ({i.name for i in self._statistics.get_inputs()}
                        if self._statistics else set())

    def statistics(self, feeds: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """The frame's statistics, as the tile graph's inputs, from the whole frame's feeds."""
        if self._split is None or self._statistics is None:
            return {}
        values = self._statistics.run(list(self._split.names),
                                      {k: v for k, v in feeds.items() if k in self._inputs})
        return dict(zip(self._split.inputs, values, strict=True))


class GraphRunner:
    """One graph stage of a model: its session, its card, and its tiles. `run` feeds it the
    frame's buffers, the stage's state and reset, and returns its output and new state."""

    def __init__(self, session: ort.InferenceSession, card: ModelCard, stage: GraphStage,
                 tile_pixels: int | None, path: Path, threads: int) -> None:
        self.session, self.card, self.stage = session, card, stage
        self.tile_pixels = tile_pixels  # None: every frame whole
        self.path, self._threads = path, threads  # path: the graph file (tiles remake it)
        self._tiled: TiledGraph | None = None  # made at the first frame run in tiles
        self._lock = threading.Lock()
        self.input_names = {i.name for i in session.get_inputs()}
        self.output_names = [o.name for o in session.get_outputs()]
        self.scales = {f"{io}{s.name}": s.scale for s in card.state if s.scale != 1
                       for io in (STATE_IN, STATE_OUT)}

    def tiled(self) -> TiledGraph:
        """The graph as tiles run it (made once, at the first frame run in tiles)."""
        with self._lock:
            if self._tiled is None:
                self._tiled = TiledGraph(self.path, self._threads)
            return self._tiled

    def working_set_bytes(self, height: int, width: int) -> int:
        """About the most this graph holds while it runs an H×W frame, beyond the frame's own
        buffers and the state and output it returns: one tile's memory (or the whole frame's),
        from the card (runtime/tiling.py tile_bytes_per_pixel)."""
        pixels = height * width
        if self.card.tiling is None:  # runs whole: budgeted like the largest graphs per pixel
            return pixels * UNTILED_BYTES_PER_PIXEL
        if self.tile_pixels is not None:
            pixels = min(pixels, self.tile_pixels)
        return pixels * tile_bytes_per_pixel(self.card.tiling, self.card.state)

    @property
    def info(self) -> ModelInfo:
        """This graph's own interface (its state by its own names)."""
        return model_info(Path(self.stage.file or f"{self.card.name}.onnx"), self.card)

    def run(self, feeds: Mapping[str, np.ndarray], state: Mapping[str, np.ndarray] | None,
            height: int, width: int) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """(output (1, 3, H, W), new state by the stage's own names); `state` None: fresh."""
        feeds = {k: v for k, v in feeds.items() if k in self.input_names}
        zero_state: dict[str, StateSpec] = {}
        for spec in self.card.state:
            if state is None:
                zero_state[STATE_IN + spec.name] = spec
                continue
            tensor = state[self.stage.state_key(spec.name)]
            if tensor.shape != spec.shape(height, width):
                raise BufferError(f"state {self.stage.state_key(spec.name)!r} has shape "
                                  f"{tensor.shape}, frame is {height}x{width}")
            feeds[STATE_IN + spec.name] = tensor
        if RESET in self.input_names:  # a prepass-only graph has no history of its own
            feeds[RESET] = np.array([1.0 if state is None else 0.0], np.float32)
        tiling = self.card.tiling
        if tiling is None or self.tile_pixels is None or height * width <= self.tile_pixels:
            feeds |= {k: np.zeros(s.shape(height, width), np.float32)
                      for k, s in zero_state.items()}
            outputs = dict(zip(self.output_names, self.session.run(None, feeds), strict=True))
        else:
            tiled = self.tiled()
            frame_wide = tiled.statistics(feeds)  # computed once, fed to every tile

            def run_tile(part: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
                results = tiled.session.run(None, part | frame_wide)
                return dict(zip(self.output_names, results, strict=True))

            values = {k: v.reshape(-1)[0] for k, v in feeds.items() if v.ndim != 4 and v.size}
            outputs = run_tiled(run_tile, feeds, height, width, tiling, values,
                                self.tile_pixels, self.scales, zero_state)
        return outputs[OUTPUT], {s.name: outputs[STATE_OUT + s.name] for s in self.card.state}


class Denoiser:
    """A loaded model; `denoise` is thread-safe (onnxruntime runs sessions concurrently).

    The model card's stages run in order (runtime/card.py): graphs (this file's, last; others
    from files in its folder, each with its state under its namespace) and OIDN passes
    (runtime/oidn_prepass.py), which denoise the previous graph's output (or the frame's
    colour) and feed the next graph. A model with an OIDN stage raises PrepassUnavailable here
    when pyoidn is not installed.

    Memory: each graph runs in overlapping tiles (tiling.py) whose working set fits in
    `max_memory_mb` (default QUIETFRAME_MAX_MEMORY_MB or tiling.DEFAULT_MAX_MEMORY_MB). With an
    OIDN stage, OIDN's scratch is capped at `oidn_memory_mb` (its maxMemoryMB; its images are
    whole-frame, like the frame's buffers; past the cap OIDN tiles) and the graphs' tiles get
    half of `max_memory_mb`; without `oidn_memory_mb` OIDN gets the other half. The service
    sizes OIDN's cap from its memory budget (service/settings.py). `working_set_bytes` is what
    the service's admission reserves for the model. `tile_pixels` overrides the tile size
    (padded pixels); None runs every frame whole.

    `options`: values for the model's extra inputs (`info.inputs`), e.g. {"kernel_size": 7};
    the card's default for the others."""

    def __init__(
        self,
        model_path: str | Path,
        threads: int = 2,
        tile_pixels: int | None | str = BY_MEMORY,
        options: Mapping[str, float | int] | None = None,
        max_memory_mb: float | None = None,
        oidn_memory_mb: float | None = None,
    ) -> None:
        path = Path(model_path)
        if not path.is_file():
            raise FileNotFoundError(f"model file {path} does not exist")
        self.max_memory_mb = max_memory_mb or max_memory_mb_default()
        self.session = make_session(path, threads)
        self.card = ModelCard.from_props(self.session.get_modelmeta().custom_metadata_map,
                                         path.stem)
        prepass = self.card.prepass
        # The bound is shared between OIDN's scratch and the graphs' tiles (class docstring)
        self._graph_memory_mb = self.max_memory_mb / 2 if prepass else self.max_memory_mb
        try:
            self.prepass = (OIDNPrepass(prepass, num_threads=threads,
                                        max_memory_mb=oidn_memory_mb or self.max_memory_mb / 2)
                            if prepass else None)
        except PrepassUnavailable as exc:
            exc.model = self.card.name  # for the service's log line and error
            raise
        self.stages: list[GraphRunner | OIDNStage] = []
        parts: list[tuple[GraphStage, ModelCard]] = []
        for stage in self.card.stages:
            if isinstance(stage, OIDNStage):
                self.stages.append(stage)
                continue
            file = self._stage_file(path, stage) if stage.file else path
            if stage.file:
                session = make_session(file, threads)
                card = ModelCard.from_props(session.get_modelmeta().custom_metadata_map,
                                            file.stem)
                parts.append((stage, card))
            else:
                session, card = self.session, self.card
            self.stages.append(GraphRunner(session, card, stage,
                                           self._tile_pixels(card, tile_pixels), file, threads))
        self.graph = self.stages[-1]  # this file's graph
        assert isinstance(self.graph, GraphRunner)
        self.tile_pixels = self.graph.tile_pixels
        self.input_names = self.graph.input_names
        self.info = model_info(path, self.card, parts)
        self._option_feeds = self._options({}, options or {})

    def working_set_bytes(self, height: int, width: int) -> int:
        """About the most the model holds while it denoises an H×W frame beyond the frame's
        buffers, state and output: its graphs run one after another, so the largest graph's
        and an OIDN stage's filters (runtime/oidn_prepass.py), which live while they run."""
        oidn = self.prepass.working_set_bytes(height, width) if self.prepass is not None else 0
        return oidn + max(stage.working_set_bytes(height, width) for stage in self.stages
                          if isinstance(stage, GraphRunner))

    @property
    def color_stage(self) -> GraphRunner | None:
        """The graph of another file whose output the OIDN stage denoises, if any."""
        first = self.stages[0]
        return first if isinstance(first, GraphRunner) and first.stage.file else None

    def _stage_file(self, path: Path, stage: GraphStage) -> Path:
        first = path.parent / stage.file
        if not first.is_file():
            raise FileNotFoundError(f"model {self.card.name!r} denoises the output of "
                                    f"{stage.file}, which is not installed next to it ({first})")
        return first

    def _tile_pixels(self, card: ModelCard, tile_pixels: int | None | str) -> int | None:
        if tile_pixels != BY_MEMORY:
            return tile_pixels  # type: ignore[return-value]
        if card.tiling is None:
            return None
        return tile_pixels_for(card.tiling, card.state, self._graph_memory_mb)

    def _options(self, base: Mapping[str, np.ndarray],
                 options: Mapping[str, float | int]) -> dict[str, np.ndarray]:
        """Feeds of the extra inputs: `base` (or the defaults) with `options` on top."""
        check_options(self.info, options)
        specs = {spec.name: spec for spec in self.info.inputs}
        feeds = {name: base[name] if name in base else spec.array(spec.default)
                 for name, spec in specs.items()}
        feeds |= {name: specs[name].array(value) for name, value in options.items()}
        return feeds

    @property
    def option_feeds(self) -> dict[str, np.ndarray]:
        """The extra inputs as this Denoiser feeds them (defaults and its options)."""
        return dict(self._option_feeds)

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
        options: Mapping[str, float | int] | None = None, renderer: str | None = None,
        oidn: OIDNFilters | None = None,
    ) -> DenoiseResult:
        """Denoise one frame of (C, H, W) float32 planes. `state` is the previous frame's
        `DenoiseResult.state`, or None to start from a fresh history (first frame, camera cut).
        `options` overrides the Denoiser's options for this call. `renderer`: the frame's,
        where known (an OIDN stage gives OIDN the rows in that renderer's order:
        runtime/oidn_prepass.py). `oidn`: the sequence's kept OIDN filters (runtime/stream.py);
        None builds them for this call."""
        feeds, sanitized, missing, (height, width) = self._feeds(planes)
        feeds |= self._options(self._option_feeds, options) if options else self._option_feeds
        new_state: dict[str, np.ndarray] = {}
        color = feeds["color"]  # (1, 3, H, W): what the next OIDN stage denoises
        oidn_output = None
        for stage in self.stages:
            if isinstance(stage, OIDNStage):
                # The sanitised planes, so OIDN sees exactly what a plain graph would; an absent
                # aux buffer is left out (OIDN then runs without it), not given as zeros.
                oidn_planes = {name: feeds[name][0] for name in PREPASS_BUFFERS[1:]
                               if name not in missing}
                feeds[stage.input] = self.prepass({"color": color[0], **oidn_planes}, renderer,
                                                  filters=oidn)
                oidn_output = feeds[stage.input][0]
                continue
            output, stage_state = stage.run(feeds, state, height, width)
            clean, bad = sanitize_output(output[0])
            if bad:  # the last stage's under "denoised", an earlier one's under its namespace
                sanitized[stage.stage.namespace or OUTPUT] = bad
            color = clean[None]
            new_state |= {stage.stage.state_key(k): v for k, v in stage_state.items()}
        return DenoiseResult(color=color[0], state=new_state, sanitized=sanitized,
                             missing=missing, oidn=oidn_output)
