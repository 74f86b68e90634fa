"""Checkpoint selection on Cycles shots from outside the generator (`quietframe-train
--select-on zoo|corpus|zoo+corpus`).

The learned tiers' weakness is content unlike the generator's, so a run may keep the
checkpoint that is best on the zoo's validation shots (scenes/zoo_shots.py,
<data>/<zoo>-cycles/validation/<shot>/, every round), on the training corpus's validation
shots (scenes/corpus_shots.py, <data>/corpus-cycles/validation/<shot>/: the zoo's layout, drawn
from the corpus's parts, none of them trained on) or on both, rather than on the generator's
validation split.

A shot is scored as the runtime would run it: its frames through `runtime.Stream` (the
motion-evidence gate, motion estimated from the aux where a frame moves without vectors, a
fresh history at the first frame and at a cut), with the PyTorch model in place of the
exported graph (`TorchDenoiser`) and the inputs through the runtime's sanitising rule. The
score is the mean per-frame PSNR (τ-mapped, model/metrics) against the shot's reference, per
shot and spp, averaged over every (shot, spp) scored. To keep one pass cheap on two cores
only the first `select_frames` rendered frames of each shot are read, and each frame is
centre-cropped to `select_crop` pixels square (the whole frame where smaller); the crop is
then the shot the runtime sees. A shot still rendering is scored on the frames it has.

Checked against the shipped path: on garden-blur (192x192, so uncropped; motion blur, so the
gate and the aux motion estimate at work) the shipped checkpoints of nbg-2l-3g and
affinity-h16-k5gc score within 0.05 dB of bench/zoo_eval's figures for their exported models
(docs/evaluation/zoo-validation) at 1, 4 and 16 spp.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch
from torch import nn

from quietframe.model.metrics import psnr
from quietframe.model.oidn_temporal import VARIANTS as OIDN_VARIANTS
from quietframe.runtime.buffers import BUFFER_CHANNELS, BUFFER_NAMES
from quietframe.runtime.card import SAMPLES_INPUT
from quietframe.runtime.denoiser import DenoiseResult
from quietframe.runtime.sanitize import sanitize_buffer, sanitize_output
from quietframe.runtime.scalar_inputs import InputSpec
from quietframe.runtime.stream import Stream
from quietframe.scenes import cycles_io
from quietframe.scenes.corpus_shots import corpus_dir, corpus_shots
from quietframe.scenes.zoo_shots import ZOO_ROUNDS, shots, zoo_dir

# "validation": the generator's split (model/train.validate); the others score shots here
SHOT_SOURCES = ("zoo", "corpus")
SELECT_ON = ("validation", "zoo", "corpus", "zoo+corpus")
CORPUS = "corpus"  # ZooSequence.zoo of a corpus shot
MODEL_STATE = "torch_state"  # the model's own state inside the stream's state dict

Frame = tuple[dict[str, np.ndarray], np.ndarray, bool]  # (C, H, W) planes, (H, W, 3) ref, reset


class SelectionConfig(Protocol):
    """The fields of model/train.TrainConfig a selection reads (train imports this module)."""

    variant: str
    data: str
    select_on: str
    select_spp: str
    select_frames: int
    select_crop: int


@dataclass(frozen=True)
class ZooSequence:
    """One (shot, spp) a selection pass scores: the first `frames` rendered frames."""

    shot: str
    zoo: str
    folder: Path
    spp: int
    frames: int


def select_spp(cfg: SelectionConfig) -> tuple[int, ...]:
    """The spp levels scored; ValueError for a list that is not positive integers."""
    try:
        levels = tuple(int(s) for s in cfg.select_spp.split(",") if s.strip())
    except ValueError:
        levels = ()
    if not levels or min(levels) < 1:
        raise ValueError(f"select_spp {cfg.select_spp!r}: comma-separated spp levels, e.g. 1,4,16")
    return levels


def sources(cfg: SelectionConfig) -> tuple[str, ...]:
    """Where the shots a selection scores come from (SHOT_SOURCES); () for the generator's
    validation split."""
    return tuple(s for s in cfg.select_on.split("+") if s in SHOT_SOURCES)


def check(cfg: SelectionConfig) -> None:
    """ValueError for a selection setting the run cannot use (before any step is taken)."""
    if cfg.select_on not in SELECT_ON:
        raise ValueError(f"select_on {cfg.select_on!r}: one of {', '.join(SELECT_ON)}")
    if not sources(cfg):
        return
    select_spp(cfg)
    if cfg.select_frames < 1 or cfg.select_crop < 16:
        raise ValueError("select_frames must be at least 1 and select_crop at least 16 px")
    if cfg.variant in OIDN_VARIANTS:
        raise ValueError(f"--select-on {cfg.select_on} scores NBG and affinity variants; "
                         f"{cfg.variant} reads OIDN's output, which the shots' frames do not "
                         "carry: use --select-on validation")


def rendered_frames(folder: Path, spp: int) -> int:
    """How many frames of a shot (its first, without a gap) have their spp-`spp` input and
    their reference: a shot still rendering counts the frames it has."""
    manifest = json.loads((folder / cycles_io.MANIFEST).read_text())
    done = sorted(f["index"] for f in manifest["frames"])
    count = 0
    for i, t in enumerate(done):
        reference = cycles_io.frame_file(cycles_io.reference_frame(folder, t))
        if t != i or not (folder / cycles_io.level_dir(spp) / cycles_io.frame_file(t)).exists() \
                or not all((folder / h / reference).exists() for h in cycles_io.REFERENCE_HALVES):
            break
        count += 1
    return count


def shot_folders(cfg: SelectionConfig) -> list[tuple[str, str, Path]]:
    """(source, shot, folder) of every validation shot the selection reads: each zoo round's
    (scenes/zoo_shots.py) and the corpus's (scenes/corpus_shots.py), as `select_on` asks."""
    out = []
    for source in sources(cfg):
        if source == CORPUS:
            root = corpus_dir(cfg.data, "validation")
            out += [(CORPUS, s.name, root / s.name) for s in corpus_shots("validation")]
            continue
        for zoo in ZOO_ROUNDS:
            root = zoo_dir(cfg.data, "validation", zoo)
            out += [(zoo, shot.name, root / shot.name) for shot in shots("validation", zoo)]
    return out


def zoo_sequences(cfg: SelectionConfig, notes: list[str] | None = None) -> list[ZooSequence]:
    """The (shot, spp) pairs a pass scores: the validation shots `select_on` names (the zoo's,
    the corpus's) rendered on this machine, at each of `select_spp`. What is skipped (a shot not
    rendered, an spp level it lacks) is appended to `notes`. FileNotFoundError when nothing is
    rendered."""
    notes = [] if notes is None else notes
    out = []
    for source, name, folder in shot_folders(cfg):
        if not (folder / cycles_io.MANIFEST).exists():
            notes.append(f"selection: {source}/{name} not rendered, skipped")
            continue
        for spp in select_spp(cfg):
            frames = min(rendered_frames(folder, spp), cfg.select_frames)
            if frames:
                out.append(ZooSequence(name, source, folder, spp, frames))
            else:
                notes.append(f"selection: {source}/{name} has no frame at {spp} spp, skipped")
    if not out:
        where = {"zoo": f"<zoo>-cycles/validation/<shot>/ for {', '.join(ZOO_ROUNDS)}: "
                        "docs/zoo.md",
                 CORPUS: "corpus-cycles/validation/<shot>/: docs/data.md, 'Training corpus'"}
        raise FileNotFoundError(
            f"--select-on {cfg.select_on}: no validation shot is rendered under {cfg.data} at "
            f"{cfg.select_spp} spp ({'; '.join(where[s] for s in sources(cfg))}); render some "
            "or select on the generator's split (--select-on validation)")
    return out


def centre_crop(a: np.ndarray, size: int) -> np.ndarray:
    """The centre `size`² of (..., H, W), or the whole of a side shorter than `size`."""
    h, w = a.shape[-2:]
    y, x = max(h - size, 0) // 2, max(w - size, 0) // 2
    return np.ascontiguousarray(a[..., y : y + min(size, h), x : x + min(size, w)])


def load_frames(seq: ZooSequence, crop: int,
                references: dict[int, np.ndarray] | None = None) -> list[Frame]:
    """The sequence's frames as the service decodes them (cycles_io), centre-cropped: planes,
    reference and whether the frame starts a history (first frame or a cut). `references`
    caches the shot's references by frame (shared between its spp levels)."""
    references = {} if references is None else references
    resets = cycles_io.frame_resets(seq.folder)
    frames = []
    for t in range(seq.frames):
        planes = {k: centre_crop(v.transpose(2, 0, 1), crop)
                  for k, v in cycles_io.load_inputs(seq.folder, t, seq.spp).items()}
        if t not in references:
            reference = cycles_io.load_reference(seq.folder, t).transpose(2, 0, 1)
            references[t] = centre_crop(reference, crop).transpose(1, 2, 0)
        frames.append((planes, references[t], resets[t]))
    return frames


@dataclass(frozen=True)
class _Info:
    """The part of runtime.ModelInfo a Stream reads: that the model keeps a state, and its
    run-time inputs (the frame's spp, for a model that reads it; not a kernel size: the
    model's own, as `validate` runs it)."""

    state_specs: tuple[str, ...] = (MODEL_STATE,)
    inputs: tuple[InputSpec, ...] = ()


class TorchDenoiser:
    """The slice of runtime.Denoiser a runtime.Stream drives, over a PyTorch model: each
    buffer through the runtime's sanitising rule (an absent one as zeros), a fresh history
    where the stream gives no state, the output through the runtime's last guard."""

    prepass = None  # no OIDN stage

    def __init__(self, model: nn.Module) -> None:
        reads = [InputSpec.from_dict(i) for i in getattr(model, "run_time_inputs", list)()
                 if i["name"] == SAMPLES_INPUT]
        self.model, self.info = model, _Info(inputs=tuple(reads))

    def denoise(self, planes: Mapping[str, np.ndarray], state: Mapping[str, Any] | None,
                options: Mapping[str, float | int] | None = None, renderer: str | None = None,
                oidn: object = None) -> DenoiseResult:
        _, h, w = planes["color"].shape
        feeds = [torch.from_numpy(sanitize_buffer(name, planes[name])[0])[None]
                 if name in planes else torch.zeros(1, BUFFER_CHANNELS[name], h, w)
                 for name in BUFFER_NAMES]
        fresh = state is None or MODEL_STATE not in state
        previous = self.model.initial_state(1, h, w) if fresh else state[MODEL_STATE]
        reset = torch.ones(1) if fresh else torch.zeros(1)
        spp = (options or {}).get(SAMPLES_INPUT) if self.info.inputs else None
        extra = {} if spp is None else {"spp": torch.tensor([float(spp)])}
        out, new = self.model(*feeds, reset, previous, **extra)
        color, _ = sanitize_output(out[0].numpy())
        # The state holds tensors, not arrays: nothing but this class reads MODEL_STATE.
        return DenoiseResult(color=color, state={MODEL_STATE: new}, sanitized={}, missing=())


def score_frames(model: nn.Module, frames: list[Frame], spp: int) -> list[float]:
    """Per-frame PSNR of the model's output through a runtime Stream, state carried."""
    stream = Stream(TorchDenoiser(model), renderer="cycles")  # duck-typed: the slice it reads
    state = None
    scores = []
    for planes, reference, reset in frames:
        step = stream.step(planes, None if reset else state, stated_spp=spp)
        state = step.state
        scores.append(psnr(step.color.transpose(1, 2, 0), reference))
    return scores


@dataclass(frozen=True)
class ZooScore:
    psnr: float  # the mean over (shot, spp) of each one's mean per-frame PSNR
    per_shot: dict[str, dict[str, Any]]  # shot -> {"frames": n, "psnr": {spp: dB}}
    selected_on: str = "zoo"  # the run's select_on

    def metrics(self) -> dict[str, Any]:
        """What best.pt's metrics (and an exported card's notes) record of the selection (the
        keys keep the zoo's name whatever the shots: cards and reports read them)."""
        return {"selected_on": self.selected_on, "zoo_psnr": round(self.psnr, 3),
                "zoo_sequences": sum(len(s["psnr"]) for s in self.per_shot.values()),
                "zoo_per_shot": self.per_shot}

    def same_set(self, metrics: Mapping[str, Any]) -> bool:
        """Whether `metrics` (a kept checkpoint's) scored the same shots, frames and spp:
        scores are comparable only then (a shot still rendering changes the set)."""
        def shape(per_shot: Mapping) -> dict:
            return {k: (v["frames"], sorted(v["psnr"])) for k, v in per_shot.items()}
        return (metrics.get("selected_on") == self.selected_on
                and shape(metrics.get("zoo_per_shot", {})) == shape(self.per_shot))

    def lines(self) -> list[str]:
        return [f"zoo {shot} ({s['frames']} frames): "
                + "  ".join(f"{spp} spp {v:.2f}" for spp, v in s["psnr"].items())
                for shot, s in self.per_shot.items()] + [f"zoo mean {self.psnr:.3f} dB"]


@torch.no_grad()
def score(model: nn.Module, sequences: list[ZooSequence], crop: int,
          log: Callable[[str], None] | None = None, selected_on: str = "zoo") -> ZooScore:
    """The selection score of `model` on `sequences` (`selected_on`: the run's select_on, for
    the record); each shot's line goes to `log`."""
    model.eval()
    per_shot: dict[str, dict[str, Any]] = {}
    references: dict[Path, dict[int, np.ndarray]] = {}
    means = []
    try:
        for seq in sequences:
            frames = load_frames(seq, crop, references.setdefault(seq.folder, {}))
            mean = float(np.mean(score_frames(model, frames, seq.spp)))
            entry = per_shot.setdefault(seq.shot, {"frames": seq.frames, "psnr": {}})
            entry["frames"] = min(entry["frames"], seq.frames)
            entry["psnr"][str(seq.spp)] = round(mean, 3)
            means.append(mean)
    finally:
        model.train()
    result = ZooScore(float(np.mean(means)), per_shot, selected_on)
    for line in result.lines() if log else ():
        log(line)
    return result
