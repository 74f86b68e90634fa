"""The model card: everything the runtime, tiling, model choice and the registry know about an
exported model, typed and versioned (docs/model-interface.md).

Exporters build a `ModelCard` and write it with `to_props` into the ONNX metadata_props; every
reader gets it back with `ModelCard.from_props`. Nothing else parses metadata strings. No torch.

The metadata layout stays the one every shipped model was written with (`quietframe.name`,
`.buffers.*`, `.state`, `.inputs`, `.prepass`, `.metrics`, ...), so older readers and files keep
working; the card adds `quietframe.card` (its version), `quietframe.stages` (the composition) and
`quietframe.tiling`. A file without them (version 0: every model shipped before the card) gets
its stages from `quietframe.prepass` and its tiling from its family's rule (runtime/receptive.py).
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

from quietframe.runtime.ops_library import OPS_DOMAIN
from quietframe.runtime.receptive import Tiling, tiling_for
from quietframe.runtime.scalar_inputs import InputSpec

CARD_VERSION = 1
PREFIX = "quietframe."
# Every figure measured before tables were kept per renderer came from Mitsuba renders.
DEFAULT_RENDERER = "mitsuba"
# The state namespace of a prepass's `color_from` model in version-0 cards: sessions stored
# under it (`color_from.accumulation`) stay readable.
LEGACY_STAGE_NAMESPACE = "color_from"

# Graph I/O names (docs/model-interface.md), spelled here only.
OUTPUT = "denoised"
RESET = "reset"
STATE_IN, STATE_OUT = "state_in.", "state_out."

OIDN_QUALITIES = ("fast", "balanced", "high")


@dataclass(frozen=True)
class StateSpec:
    name: str
    channels: int
    scale: int = 1  # the tensor is ⌈H/scale⌉ × ⌈W/scale⌉ (e.g. a half-resolution history)

    def shape(self, height: int, width: int) -> tuple[int, int, int, int]:
        return (1, self.channels, -(-height // self.scale), -(-width // self.scale))

    def to_dict(self) -> dict:
        return {"name": self.name, "channels": self.channels, "scale": self.scale}


# The run-time input of a model whose behaviour depends on the frame's samples per pixel
# (model/output_history.py): the service feeds it from the EXR header where the renderer wrote
# its count, else auto's estimate of the shot, unless the session sets it (model_options).
SAMPLES_INPUT = "spp"


# ---- the composition ------------------------------------------------------------------------


@dataclass(frozen=True)
class GraphStage:
    """An ONNX graph: this file (`file` ""), or another model file in the same folder, run with
    its own state under `namespace` (state `x` is kept as `<namespace>.x`; "" : as `x`)."""

    file: str = ""
    namespace: str = ""

    def __post_init__(self) -> None:
        if self.file and (Path(self.file).name != self.file or not self.file.endswith(".onnx")):
            raise ValueError(f"a graph stage must name an .onnx file in the model's own folder, "
                             f"got {self.file!r}")
        if bool(self.file) != bool(self.namespace):
            raise ValueError("a graph stage of another file needs a state namespace of its own "
                             "(and this file's graph none)")

    def state_key(self, name: str) -> str:
        return f"{self.namespace}.{name}" if self.namespace else name


@dataclass(frozen=True)
class OIDNStage:
    """Open Image Denoise's RT filter on the previous stage's output (or the frame's colour when
    it is the first stage), with the frame's albedo/normal; its output is fed to the next graph
    as input `input`. `color_from`: only in what `quietframe.prepass` says (a graph stage run
    first), never set in a card's stage list."""

    quality: str = "high"
    prefilter_aux: bool = False
    input: str = "oidn"  # the graph input that receives OIDN's output
    aux: tuple[str, ...] = ("albedo", "normal")  # what OIDN is given besides the colour
    color_from: str = ""
    aux_quality: str = ""  # the aux prefilters' quality ("": the main filter's)

    def __post_init__(self) -> None:
        if self.color_from and (Path(self.color_from).name != self.color_from
                                or not self.color_from.endswith(".onnx")):
            raise ValueError(f"prepass: color_from must name an .onnx file in the model's own "
                             f"folder, got {self.color_from!r}")
        for quality in (self.quality, self.aux_quality or self.quality):
            if quality not in OIDN_QUALITIES:
                raise ValueError(f"prepass: OIDN quality must be one of {list(OIDN_QUALITIES)}, "
                                 f"got {quality!r}")
        if set(self.aux) - {"albedo", "normal"} or ("normal" in self.aux
                                                     and "albedo" not in self.aux):
            raise ValueError(f"prepass: OIDN aux must be (), ('albedo',) or ('albedo', 'normal') "
                             f"(a normal only with an albedo), got {self.aux!r}")

    def oidn_dict(self) -> dict:
        out: dict = {"quality": self.quality, "prefilter_aux": self.prefilter_aux}
        if self.aux != OIDNStage.aux:
            out["aux"] = list(self.aux)
        if self.aux_quality:
            out["aux_quality"] = self.aux_quality
        return out


Stage = GraphStage | OIDNStage


def parse_prepass(text: str | None) -> OIDNStage | None:
    """`quietframe.prepass` as written since the oidn-temporal tier (docs/model-interface.md)."""
    return prepass_stage(json.loads(text)) if text else None


def prepass_stage(spec: Mapping) -> OIDNStage:
    """The OIDN stage of a prepass spec {"oidn": {...}, "input": ..., "color_from": ...}."""
    if set(spec) - {"oidn", "input", "color_from"} or "oidn" not in spec:
        raise ValueError(f"{PREFIX}prepass: only an 'oidn' prepass is known, got {sorted(spec)}")
    oidn = spec["oidn"]
    return OIDNStage(quality=oidn.get("quality", "high"),
                     prefilter_aux=bool(oidn.get("prefilter_aux", False)),
                     input=spec.get("input", "oidn"),
                     aux=tuple(oidn.get("aux", OIDNStage.aux)),
                     color_from=spec.get("color_from", ""),
                     aux_quality=oidn.get("aux_quality", ""))


def stages_from_prepass(prepass: OIDNStage | None) -> tuple[Stage, ...]:
    if prepass is None:
        return (GraphStage(),)
    first = ((GraphStage(prepass.color_from, LEGACY_STAGE_NAMESPACE),)
             if prepass.color_from else ())
    return (*first, replace(prepass, color_from=""), GraphStage())


def prepass_of(stages: Sequence[Stage]) -> dict | None:
    """The `quietframe.prepass` form of a composition ([graph,] OIDN, this graph), or None
    when it has no OIDN stage."""
    oidn = [s for s in stages if isinstance(s, OIDNStage)]
    if not oidn:
        return None
    before = stages[: stages.index(oidn[0])]
    spec: dict = {"oidn": oidn[0].oidn_dict(), "input": oidn[0].input}
    if before:
        spec["color_from"] = before[0].file
    return spec


def stage_to_dict(stage: Stage) -> dict:
    if isinstance(stage, GraphStage):
        return {"graph": stage.file, "namespace": stage.namespace}
    return {"oidn": stage.oidn_dict(), "input": stage.input}


def stage_from_dict(d: Mapping) -> Stage:
    if "graph" in d:
        return GraphStage(d["graph"], d.get("namespace", ""))
    # the prepass form's parser, so every key of oidn_dict (aux_quality too) is read back
    return prepass_stage({"oidn": d["oidn"], "input": d.get("input", "oidn")})


def check_stages(stages: Sequence[Stage]) -> None:
    """Graphs and OIDN passes in sequence, ending with this file's graph; an OIDN stage feeds
    a graph."""
    if not stages or stages[-1] != GraphStage():
        raise ValueError(f"a composition ends with this file's graph, got {stages!r}")
    for a, b in zip(stages, stages[1:], strict=False):
        if isinstance(a, OIDNStage) and not isinstance(b, GraphStage):
            raise ValueError("an OIDN stage must feed a graph")
    spaces = [s.namespace for s in stages if isinstance(s, GraphStage)]
    if len(set(spaces)) != len(spaces):
        raise ValueError(f"graph stages need distinct state namespaces, got {spaces}")


# ---- measurements ---------------------------------------------------------------------------


@dataclass(frozen=True)
class SppRow:
    spp: float  # samples per pixel of the inputs
    psnr: float  # dB on the τ-mapped image, mean over frames
    trmae: float | None = None  # mean over sequences
    # Mean over locked-off validation shots of the temporal std of τ(output) (flicker: no
    # reference needed); None where no locked-off shot was measured.
    flicker: float | None = None
    # PSNR of the renderer's own denoise of the same validation frames (Blender's, on Cycles),
    # measured in the same run: auto's floor where the renderer has one (service/choice_policy).
    renderer_denoise: float | None = None

    def to_dict(self) -> dict:
        return {"spp": self.spp, "psnr": self.psnr,
                **({} if self.trmae is None else {"trmae": self.trmae}),
                **({} if self.flicker is None else {"flicker": self.flicker}),
                **({} if self.renderer_denoise is None
                   else {"renderer_denoise": self.renderer_denoise})}


def finite_figure(value: object) -> bool:
    """A measured figure that is a finite number (tables carry NaN where nothing was measured)."""
    return isinstance(value, (int, float)) and math.isfinite(value)


def json_safe(value: object) -> object:
    """`value` with every non-finite float as None: JSON has no NaN or infinity, and a reader
    other than Python's (a farm's scripts, a browser) refuses `-Infinity` (e.g. a training
    run's validation score when it had no validation split)."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, Mapping):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    return value


MEASUREMENT_KEYS = ("by_spp", "ms_720p", "measured", "absent_db", "absent_db_worst", "by_noise",
                    "zoo", "input_margin")


@dataclass(frozen=True)
class ZooRow:
    """How a model held on the validation zoo (shots from outside the scene generator,
    scenes/zoo_shots.py) at one spp, against per-frame OIDN-high in the same run: `gap_db` the
    mean over shots of (model − OIDN-high) PSNR, `worst_gap_db` the lowest shot's, and
    `shortfall_db` = min(0, gap_db − the same gap on the generator's validation split): how much
    less the model's table promises than the zoo shows (≤ 0; `auto` takes it off).
    `worst_vs_denoise_db`: the lowest shot's (model − Blender's own denoise of the same frames)
    PSNR, what a user loses on the model's worst shot by not ticking Denoise (None where not
    measured)."""

    spp: float
    gap_db: float
    worst_gap_db: float
    shortfall_db: float
    worst_vs_denoise_db: float | None = None

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class InputMarginRow:
    """How a model's output compared with its own noisy input on the validation zoo at one spp:
    (model − noisy input) PSNR on the same frames, `worst_db` the lowest shot's (`worst_shot`),
    `mean_db` the mean over the `shots` measured. Below 0 the denoiser made the frame worse than
    leaving it alone; `auto` does not choose a model where its worst shot is (choice_policy)."""

    spp: float
    worst_db: float
    mean_db: float
    worst_shot: str = ""
    shots: int = 0

    def to_dict(self) -> dict:
        return asdict(self)


def worse_than_input_from(rows: Sequence[InputMarginRow]) -> float | None:
    """The lowest spp from which the worst shot's margin is below 0, read as `auto` reads it
    (linear in log2 spp between measured levels, flat beyond them): where it first crosses 0,
    the first level where it starts below; None where it never is."""
    rows = sorted(rows, key=lambda r: r.spp)
    if rows and rows[0].worst_db < 0:
        return float(rows[0].spp)
    for a, b in zip(rows, rows[1:], strict=False):
        if b.worst_db < 0 <= a.worst_db:
            t = a.worst_db / (a.worst_db - b.worst_db)
            return round(2 ** (math.log2(a.spp) + t * (math.log2(b.spp) - math.log2(a.spp))), 2)
    return None


@dataclass(frozen=True)
class Measurements:
    """One renderer's measured table of a model (docs/model-interface.md, what `auto` reads)."""

    by_spp: tuple[SppRow, ...] = ()  # spp ascending
    ms_720p: float | None = None  # median ms per 1280×720 frame through the runtime
    measured: Mapping = field(default_factory=dict)  # the run: command, machine, split, ...
    absent_db: Mapping[str, float] = field(default_factory=dict)  # mean PSNR change, absent
    absent_db_worst: Mapping[str, float] = field(default_factory=dict)  # the largest loss
    # (log2 σ demodulated, log2 σ of the colour alone, PSNR) per validation (sequence, spp)
    by_noise: tuple[tuple[float, float, float], ...] = ()
    by_noise_measured: Mapping = field(default_factory=dict)
    zoo: tuple[ZooRow, ...] = ()  # spp ascending; empty where the zoo was not measured
    zoo_measured: Mapping = field(default_factory=dict)  # the zoo run: command, shots
    # spp ascending; empty where not measured. Stamped apart from `zoo` (its own runs, which
    # may cover other shots), read as `worse_than_input_from`.
    input_margin: tuple[InputMarginRow, ...] = ()
    input_margin_measured: Mapping = field(default_factory=dict)  # the runs: commands, shots

    @property
    def complete(self) -> bool:
        """Enough for `auto` to choose this model: a speed and an error table."""
        return self.ms_720p is not None and bool(self.by_spp)

    def to_dict(self) -> dict:
        out: dict = {}
        if self.by_spp:
            out["by_spp"] = [r.to_dict() for r in self.by_spp]
        if self.ms_720p is not None:
            out["ms_720p"] = self.ms_720p
        if self.measured:
            out["measured"] = dict(self.measured)
        if self.absent_db:
            out["absent_db"] = dict(self.absent_db)
        if self.absent_db_worst:
            out["absent_db_worst"] = dict(self.absent_db_worst)
        if self.by_noise:
            out["by_noise"] = {"points": [list(p) for p in self.by_noise],
                               "measured": dict(self.by_noise_measured)}
        if self.zoo:
            out["zoo"] = {"by_spp": [r.to_dict() for r in self.zoo],
                          "measured": dict(self.zoo_measured)}
        if self.input_margin:
            # worse_than_input_from_spp is derived (from_dict recomputes it): written for the
            # readers without this module, GET /v1/models' clients
            out["input_margin"] = {
                "by_spp": [r.to_dict() for r in self.input_margin],
                "worse_than_input_from_spp": worse_than_input_from(self.input_margin),
                "measured": dict(self.input_margin_measured)}
        return out

    @classmethod
    def from_dict(cls, d: Mapping) -> Measurements:
        noise, zoo = d.get("by_noise") or {}, d.get("zoo") or {}
        margin = d.get("input_margin") or {}
        return cls(
            by_spp=tuple(SppRow(r["spp"], r["psnr"], r.get("trmae"), r.get("flicker"),
                                r.get("renderer_denoise"))
                         for r in sorted(d.get("by_spp") or [], key=lambda r: r["spp"])
                         if "psnr" in r),
            ms_720p=d.get("ms_720p"),
            measured=dict(d.get("measured") or {}),
            absent_db=dict(d.get("absent_db") or {}),
            absent_db_worst=dict(d.get("absent_db_worst") or {}),
            by_noise=tuple(tuple(p) for p in noise.get("points") or []),
            by_noise_measured=dict(noise.get("measured") or {}),
            zoo=tuple(ZooRow(**r) for r in sorted(zoo.get("by_spp") or [],
                                                  key=lambda r: r["spp"])),
            zoo_measured=dict(zoo.get("measured") or {}),
            input_margin=tuple(InputMarginRow(**r) for r in sorted(margin.get("by_spp") or [],
                                                                    key=lambda r: r["spp"])),
            input_margin_measured=dict(margin.get("measured") or {}),
        )


def split_metrics(metrics: Mapping) -> tuple[dict, dict[str, Measurements]]:
    """A `quietframe.metrics` dict -> (notes, tables by renderer): the top-level table is the
    default renderer's, `by_renderer` holds the others."""
    metrics = dict(metrics)
    by_renderer = metrics.pop("by_renderer", {})
    notes = {k: v for k, v in metrics.items() if k not in MEASUREMENT_KEYS}
    tables = {r: Measurements.from_dict(m) for r, m in by_renderer.items()}
    if any(k in metrics for k in MEASUREMENT_KEYS):
        tables[DEFAULT_RENDERER] = Measurements.from_dict(metrics)
    return notes, tables


# ---- the card -------------------------------------------------------------------------------


@dataclass(frozen=True)
class ModelCard:
    name: str
    version: str = "0"
    architecture: Mapping = field(default_factory=dict)  # the exporter's config, as written
    required: tuple[str, ...] = ("color",)  # buffers
    optional: tuple[str, ...] = ()  # fed as zeros when absent
    state: tuple[StateSpec, ...] = ()  # this file's graph's own state
    inputs: tuple[InputSpec, ...] = ()  # run-time inputs, e.g. kernel_size
    stages: tuple[Stage, ...] = (GraphStage(),)
    tiling: Tiling | None = None  # None: no rule knows the graph; it runs whole
    training: Mapping = field(default_factory=dict)
    measurements: Mapping[str, Measurements] = field(default_factory=dict)  # by renderer
    notes: Mapping = field(default_factory=dict)  # other metrics, e.g. training's val score
    ops_domain: str = OPS_DOMAIN
    card_version: int = CARD_VERSION

    def __post_init__(self) -> None:
        check_stages(self.stages)

    @property
    def prepass(self) -> OIDNStage | None:
        return next((s for s in self.stages if isinstance(s, OIDNStage)), None)

    def measured(self, renderer: str | None = None) -> Measurements:
        """The renderer's table, else the default renderer's (the only one measured so far)."""
        table = self.measurements.get(renderer or DEFAULT_RENDERER)
        return table or self.measurements.get(DEFAULT_RENDERER) or Measurements()

    def metrics(self) -> dict:
        """`quietframe.metrics` as written: notes, the default renderer's table at the top level
        (as every model measured before per-renderer tables has it), others under
        `by_renderer`."""
        out = dict(self.notes) | self.measurements.get(DEFAULT_RENDERER, Measurements()).to_dict()
        others = {r: m.to_dict() for r, m in self.measurements.items() if r != DEFAULT_RENDERER}
        return out | ({"by_renderer": others} if others else {})

    def with_measurements(self, renderer: str, table: Measurements) -> ModelCard:
        return replace(self, measurements={**self.measurements, renderer: table})

    def to_props(self) -> dict[str, str]:
        props = {
            "name": self.name,
            "version": self.version,
            "card": str(CARD_VERSION),
            "architecture": json.dumps(dict(self.architecture)),
            "buffers.required": json.dumps(list(self.required)),
            "buffers.optional": json.dumps(list(self.optional)),
            "state": json.dumps([s.to_dict() for s in self.state]),
            "ops_domain": self.ops_domain,
            "training": json.dumps(json_safe(dict(self.training)), allow_nan=False),
            "metrics": json.dumps(json_safe(self.metrics()), allow_nan=False),
            "stages": json.dumps([stage_to_dict(s) for s in self.stages]),
        }
        if self.inputs:
            props["inputs"] = json.dumps([i.to_dict() for i in self.inputs])
        prepass = prepass_of(self.stages)
        if prepass is not None:  # what readers before the card know of the composition
            props["prepass"] = json.dumps(prepass)
        if self.tiling is not None:
            props["tiling"] = json.dumps(self.tiling.to_dict())
        return {PREFIX + k: v for k, v in props.items()}

    @classmethod
    def from_props(cls, props: Mapping[str, str], default_name: str = "") -> ModelCard:
        """The card of a file's metadata_props, any version up to CARD_VERSION."""
        def load(key: str, default: str):
            return json.loads(props.get(PREFIX + key) or default)

        version = int(props.get(PREFIX + "card", "0"))
        if version > CARD_VERSION:
            raise ValueError(f"model card version {version} is newer than this quietframe reads "
                             f"({CARD_VERSION}): upgrade quietframe")
        notes, tables = split_metrics(load("metrics", "{}"))
        stages_text = props.get(PREFIX + "stages")
        stages = (tuple(stage_from_dict(s) for s in json.loads(stages_text)) if stages_text
                  else stages_from_prepass(parse_prepass(props.get(PREFIX + "prepass"))))
        architecture = load("architecture", "{}")
        inputs = tuple(InputSpec.from_dict(i) for i in load("inputs", "[]"))
        tiling_text = props.get(PREFIX + "tiling")
        if tiling_text:
            tiling = Tiling.from_dict(json.loads(tiling_text))
        else:
            tiling = tiling_for(architecture if isinstance(architecture, dict) else {}, inputs,
                                any(isinstance(s, OIDNStage) for s in stages))
        return cls(
            name=props.get(PREFIX + "name", default_name),
            version=props.get(PREFIX + "version", "0"),
            architecture=architecture,
            required=tuple(load("buffers.required", '["color"]')),
            optional=tuple(load("buffers.optional", "[]")),
            state=tuple(StateSpec(s["name"], int(s["channels"]), int(s.get("scale", 1)))
                        for s in load("state", "[]")),
            inputs=inputs,
            stages=stages,
            tiling=tiling,
            training=load("training", "{}"),
            measurements=tables,
            notes=notes,
            ops_domain=props.get(PREFIX + "ops_domain", OPS_DOMAIN),
            card_version=version,
        )
