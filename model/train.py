"""quietframe-train: train an NBG, oidn-temporal or affinity variant on rendered sequences (CPU
friendly, resumable).

One flat loop in a fixed order (nanoGPT style): sample a batch of short crop sequences, unroll
the state-in/state-out model over the frames (so reprojection, accumulation and reset are
trained), loss, step, log; every `eval_every` steps validate and checkpoint.

Run directory (--run): config.json, checkpoint.pt (latest, resumable), best.pt (best val PSNR,
or with --select-on zoo the best on the zoo's validation shots: model/zoo_selection.py),
log.txt (one line per logged step).

oidn-temporal variants (model/oidn_temporal.py) train the temporal stage on OIDN's output of the
training frames, computed once per (sequence, frame, spp, quality) and cached on disk
(model/oidn_cache.py); the loop, loss and schedule are the same.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import time
from pathlib import Path

import numpy as np
import torch
from torch import Tensor, nn
from torch.utils.data import default_collate

from quietframe.model import zoo_selection
from quietframe.model.data import CropDataset, SequenceDataset
from quietframe.model.families import family_of_checkpoint, family_of_variant
from quietframe.model.losses import (
    l1_tonemapped_loss,
    relmse_unbiased_loss,
    smape_loss,
    tau_mse_loss,
    temporal_loss,
    temporal_relmse_unbiased_loss,
    temporal_tau_mse_loss,
)
from quietframe.model.metrics import psnr
from quietframe.model.oidn_temporal import VARIANTS as OIDN_VARIANTS
from quietframe.runtime.buffers import BUFFER_NAMES
from quietframe.runtime.oidn_prepass import OIDNSettings
from quietframe.scenes.corpus_shots import corpus_dir
from quietframe.scenes.layout import DATA_DIR, DEFAULT_THREADS, RENDERERS, RUNS_DIR, split_dir


@dataclasses.dataclass
class TrainConfig:
    variant: str = "nbg-2l-3g"  # or oidn-temporal-high/-fast, affinity-… (model/affinity.py)
    width: int = 0  # NBG GuideNet / oidn-temporal CNN width; 0 = the variant's own (NBG: 20);
    # an affinity variant names its U-Net widths
    data: str = str(DATA_DIR)
    # The renderers whose splits are trained and validated on, comma-separated ("mitsuba",
    # "cycles", "mitsuba,cycles"): the train split is the union of theirs, validation too.
    renderers: str = "mitsuba"
    # 1: the train and validation splits also take the Cycles training corpus (shots from
    # outside the generator: scenes/corpus_shots.py, <data>/corpus-cycles/<split>; docs/data.md)
    corpus: int = 0
    # or "l1" (paper §4.4: L1 on the LDR-mapped output), or "relmse+temporal" (unbiased under
    # noisy targets, losses.relmse_unbiased_loss), or "tau+temporal" (squared error in the
    # evaluation's τ space, Işık eq. 14-15: the loss whose optimum is the best PSNR)
    loss: str = "smape+temporal"
    temporal_weight: float = 0.25  # Işık eq. 12 term next to the spatial one
    bandwidth_weight: float = 1e-5  # Işık eq. 9: weight of eq. 13 (affinity, oidn-temporal)
    kernel_size: int = 0  # affinity: spatial kernel size trained with (0: the variant's, 13)
    # affinity: e.g. "5,9,13" draws the kernel size per step (a function of seed and step), so
    # that one model serves every run-time size; empty: always kernel_size
    kernel_sizes: str = ""
    crop: int = 128
    frames: int = 4  # unrolled sub-sequence length
    batch: int = 4
    lr: float = 1e-3
    lr_final: float = 0.05  # cosine decay to lr·lr_final at `steps`: the last steps refine
    steps: int = 4000
    eval_every: int = 200
    log_every: int = 20
    seed: int = 0
    threads: int = DEFAULT_THREADS
    # Buffer dropout: each listed buffer is absent from a whole training sequence with this
    # probability, fed as the runtime feeds an absent optional buffer (zeros, runtime/buffers.py).
    # The exporter then lists these buffers as optional (a colour-only path when all four are).
    dropout: float = 0.0
    dropout_buffers: str = "albedo,normal,depth,motion"
    # NBG and affinity: the firefly clamp (NBGConfig/AffinityConfig.outlier_sigmas; 0 = off,
    # -1 = the variant's, or the --init checkpoint's: a fine-tune may switch it, it has no weights)
    outlier_sigmas: float = -1.0
    outlier_floor: float = -1.0  # NBGConfig/AffinityConfig.outlier_floor (-1 = as above)
    # NBG: the pass-through candidates (NBGConfig.passthrough; 1 on, 0 off, -1 the variant's or
    # the --init checkpoint's). A fine-tune may switch them on: the checkpoint's weights are
    # extended with their logits (model/nbg.add_passthrough).
    passthrough: int = -1
    # NBG: the noise-aware blend (NBGConfig.noise_blend, needs the pass-through; 1, 0, -1 as
    # above). A fine-tune may switch it on: its modulation starts at zero (adapt_state_dict).
    noise_blend: int = -1
    # affinity: the noise level as a U-Net input (AffinityConfig.noise_input; 1, 0, -1 as
    # above); a fine-tune may switch it on: its weights start at zero (adapt_state_dict).
    noise_input: int = -1
    # NBG and affinity: the resampled history's fade with the frame's spp
    # (NBGConfig/AffinityConfig.resampled_weight_per_doubling; 0 off, -1 as above). No weights:
    # training with it on lets the blend learn what the faded history looks like, and the
    # checkpoint then carries it (an export no longer has to set it again).
    resampled_weight_per_doubling: float = -1.0
    # NBG and affinity: the albedo's prefilter (NBGConfig/AffinityConfig.albedo_prefilter, σ px
    # at 1 spp; 0 off, -1 as above). No weights: training with it on lets the tiers learn from
    # the albedo they will be served.
    albedo_prefilter: float = -1.0
    net_scale: int = 0  # oidn-temporal: OIDNTemporalConfig.net_scale (0 = the variant's)
    # Fine-tuning: a checkpoint whose model (architecture and weights) starts a new run, with a
    # fresh optimizer and schedule (e.g. a shipped model on new data); empty: train from scratch
    init: str = ""
    # Which score keeps best.pt: "validation" (the generator's validation split, and the
    # corpus's with --corpus 1) or "zoo": the zoo's validation shots rendered on this machine
    # (every round: <data>/zoo1|zoo2|zoo3-cycles/validation/<shot>/, model/zoo_selection.py),
    # or "corpus": the training corpus's validation shots (corpus-cycles/validation/<shot>/),
    # or "zoo+corpus": both; each shot through a runtime Stream with its state carried, mean
    # per-frame PSNR per shot and spp.
    # A shot not rendered (or lacking an spp level) is skipped with a printed note; a shot still
    # rendering counts the frames it has; none rendered at all is an error at the start, never
    # a silent fall-back. The generator's validation is still logged beside it.
    select_on: str = "validation"
    select_spp: str = "1,4,16"  # zoo/corpus: the spp levels scored
    # zoo/corpus: the first frames of each shot, centre crop (whole frame where smaller). One pass
    # over the 8 shots rendered here (24 sequences of 8 frames at 1,4,16 spp, <= 192x192) costs
    # about 13 CPU-seconds on one thread for nbg-2l-3g and affinity-h16-k5gc alike (3 s of it
    # decoding the EXRs; 11-12 s wall on a loaded 2-core machine)
    select_frames: int = 8
    select_crop: int = 192


def learning_rate(cfg: TrainConfig, step: int) -> float:
    progress = min(step / max(cfg.steps, 1), 1.0)
    return cfg.lr * (cfg.lr_final + (1 - cfg.lr_final) * 0.5 * (1 + math.cos(math.pi * progress)))


def sequence_loss(cfg: TrainConfig, outputs: list[Tensor], refs: list[Tensor]) -> Tensor:
    """Mean per-frame loss plus, for `*+temporal`, the temporal term on frame differences."""
    if cfg.loss not in LOSSES:
        raise ValueError(f"loss {cfg.loss!r}: one of {sorted(LOSSES)}")
    spatial_loss, temporal_term = LOSSES[cfg.loss]
    spatial = torch.stack([spatial_loss(o, r) for o, r in zip(outputs, refs, strict=True)]).mean()
    if temporal_term is None or len(outputs) < 2:
        return spatial
    temporal = temporal_term(torch.stack(outputs, dim=1), torch.stack(refs, dim=1))
    return spatial + cfg.temporal_weight * temporal


# name -> (per-frame loss, temporal loss over (N, T, ...) or None)
LOSSES = {
    "smape+temporal": (smape_loss, temporal_loss),
    "l1": (l1_tonemapped_loss, None),
    "relmse+temporal": (relmse_unbiased_loss, temporal_relmse_unbiased_loss),
    "tau+temporal": (tau_mse_loss, temporal_tau_mse_loss),
}


def dropped_buffers(cfg: TrainConfig) -> tuple[str, ...]:
    """The buffers a run may drop (none without dropout); ValueError for an unknown one."""
    if cfg.dropout <= 0:
        return ()
    names = tuple(b.strip() for b in cfg.dropout_buffers.split(",") if b.strip())
    unknown = [b for b in names if b not in BUFFER_NAMES or b == "color"]
    if unknown:
        raise ValueError(f"dropout_buffers {unknown}: only {list(BUFFER_NAMES[1:])} can be absent")
    return names


def drop_buffers(cfg: TrainConfig, batch: dict[str, Tensor], step: int) -> dict[str, Tensor]:
    """Zero each droppable buffer of each (B, T, C, h, w) sequence with probability
    cfg.dropout, the same in all T frames (a session lacks a buffer for the whole shot). Drawn
    from (seed, step) alone, so a resumed run drops what an uninterrupted one would."""
    names = dropped_buffers(cfg)
    if not names:
        return batch
    generator = torch.Generator().manual_seed(cfg.seed * 1_000_003 + 7919 * step + 2)
    absent = torch.rand(len(names), batch["color"].shape[0], generator=generator) < cfg.dropout
    out = dict(batch)
    for name, drop in zip(names, absent, strict=True):
        if drop.any():
            keep = (~drop).to(batch[name].dtype).view(-1, *([1] * (batch[name].dim() - 1)))
            out[name] = batch[name] * keep
    return out


def build_model(cfg: TrainConfig, saved: dict | None = None) -> nn.Module:
    """The model of a run: the checkpoint's architecture (`saved`) when resuming or
    fine-tuning (the firefly clamp may still change), else the variant's with the flags its
    family takes (model/families.py): --width and --net-scale (0 keeps the variant's own),
    --kernel-size (affinity: also the exported graph's default, the size the model knows best)
    and the clamp."""
    if saved is not None:
        return family_of_checkpoint(saved).from_saved(saved, **weightless_flags(cfg))
    sizes = {"width": cfg.width, "net_scale": cfg.net_scale, "kernel_size": cfg.kernel_size}
    overrides = {k: v for k, v in sizes.items() if v} | weightless_flags(cfg)
    return family_of_variant(cfg.variant).variant(cfg.variant, **overrides)


def weightless_flags(cfg: TrainConfig) -> dict[str, float | bool]:
    """The settings a fine-tune may change on a checkpoint's model (-1: none given, the
    model's own stay): the firefly clamp, the resampled history's fade and the albedo's
    prefilter (no weights), NBG's
    pass-through (whose weights the model adds: load_weights) and the tiers' noise level (the
    same)."""
    given = {k: v for k, v in (("outlier_sigmas", cfg.outlier_sigmas),
                               ("outlier_floor", cfg.outlier_floor),
                               ("resampled_weight_per_doubling",
                                cfg.resampled_weight_per_doubling),
                               ("albedo_prefilter", cfg.albedo_prefilter)) if v >= 0}
    switches = {k: bool(v) for k, v in (("passthrough", cfg.passthrough),
                                         ("noise_blend", cfg.noise_blend),
                                         ("noise_input", cfg.noise_input)) if v >= 0}
    return given | switches


def load_weights(model: nn.Module, state: dict[str, Tensor]) -> None:
    """A checkpoint's weights into `model`, through the model's adapt_state_dict where it has
    one (a model that gained the pass-through or a noise level in a fine-tune)."""
    adapt = getattr(model, "adapt_state_dict", None)
    model.load_state_dict(adapt(state) if adapt else state)


def oidn_settings(cfg: TrainConfig) -> OIDNSettings | None:
    """The prepass whose output an oidn-temporal variant trains on (None for NBG)."""
    config = OIDN_VARIANTS.get(cfg.variant)
    return config.prepass_settings() if config else None


def step_kernel_size(cfg: TrainConfig, step: int) -> dict[str, int]:
    """The forward's kernel_size argument at `step`: {} (the model's own) or one drawn from
    cfg.kernel_sizes, seeded by (seed, step) so a resumed run draws what an uninterrupted one
    would."""
    if not cfg.kernel_sizes:
        return {}
    sizes = [int(k) for k in cfg.kernel_sizes.split(",")]
    draw = torch.randint(len(sizes), (), generator=torch.Generator().manual_seed(
        cfg.seed * 1_000_003 + 7919 * step + 3))
    return {"kernel_size": sizes[int(draw)]}


def unroll(model: nn.Module, batch: dict[str, Tensor],
           penalties: list[Tensor] | None = None, **options: int) -> list[Tensor]:
    """Run the model over a (B, T, C, h, w) batch, carrying the state; returns T outputs.
    A model that sets `bandwidth_penalty` (eq. 13) has each frame's appended to `penalties`;
    `options` go to every forward call (e.g. an affinity model's kernel_size)."""
    b, t, _, h, w = batch["color"].shape
    state = model.initial_state(b, h, w)
    outputs = []
    inputs = getattr(model, "inputs", BUFFER_NAMES)  # oidn-temporal: "oidn" first
    # A model that reads the frame's spp (a learned tier with a noise level) gets each item's.
    samples = {"spp": batch["spp"]} if getattr(model, "reads_spp", False) else {}
    for i in range(t):
        reset = torch.ones(b) if i == 0 else batch["reset"][:, i].float()
        out, state = model(*(batch[k][:, i] for k in inputs), reset, state, **samples,
                           **options)
        outputs.append(out)
        if penalties is not None and getattr(model, "bandwidth_penalty", None) is not None:
            penalties.append(model.bandwidth_penalty)
    return outputs


def batch_loss(cfg: TrainConfig, model: nn.Module, batch: dict[str, Tensor],
               **options: int) -> Tensor:
    """One batch's training loss: the sequence loss of the unrolled outputs plus, for a model
    with a bandwidth penalty, eq. 9's 1e-5 · eq. 13 (its expectation over frames too)."""
    penalties: list[Tensor] = []
    outputs = unroll(model, batch, penalties, **options)
    refs = [batch["reference"][:, i] for i in range(len(outputs))]
    loss = sequence_loss(cfg, outputs, refs)
    if penalties:
        loss = loss + cfg.bandwidth_weight * torch.stack(penalties).mean()
    return loss


@torch.no_grad()
def validate(model: nn.Module, batches: list[dict[str, Tensor]]) -> float:
    """Mean PSNR (τ-mapped, model/metrics) of the last frame of each validation sequence."""
    model.eval()
    scores = []
    for batch in batches:
        last = unroll(model, batch)[-1]
        for pred, ref in zip(last, batch["reference"][:, -1], strict=True):
            scores.append(psnr(pred.permute(1, 2, 0).numpy(), ref.permute(1, 2, 0).numpy()))
    model.train()
    return float(np.mean(scores))


def save(path: Path, model: nn.Module, optimizer, step: int, cfg: TrainConfig,
         best_psnr: float, metrics: dict) -> None:
    tmp = path.with_suffix(".tmp")
    torch.save({
        "config": model.config.to_dict(), "model": model.state_dict(),
        "optimizer": optimizer.state_dict(), "step": step, "best_psnr": best_psnr,
        "training": {**dataclasses.asdict(cfg), "steps_done": step}, "metrics": metrics,
    }, tmp)
    tmp.replace(path)  # atomic: a killed run never leaves a torn checkpoint


def renderers(cfg: TrainConfig) -> tuple[str, ...]:
    """The run's renderers, in the order given; ValueError for an unknown or missing one."""
    names = tuple(dict.fromkeys(r.strip() for r in cfg.renderers.split(",") if r.strip()))
    unknown = [r for r in names if r not in RENDERERS]
    if unknown or not names:
        raise ValueError(f"renderers {cfg.renderers!r}: a comma-separated list of {RENDERERS}")
    return names


def split_roots(cfg: TrainConfig, split: str) -> list[Path]:
    """The split's folder for each of the run's renderers (g2/<split>, g2-cycles/<split>),
    and the corpus's (corpus-cycles/<split>) where the run takes it."""
    roots = [split_dir(cfg.data, split, renderer=r) for r in renderers(cfg)]
    return [*roots, corpus_dir(cfg.data, split)] if cfg.corpus else roots


class TrainingBatches:
    """Batch k is a pure function of (seed, k): epoch permutations and crop/augmentation draws
    are seeded from them, so a resumed run sees exactly the batches an uninterrupted one would."""

    def __init__(self, cfg: TrainConfig) -> None:
        self.dataset = CropDataset(split_roots(cfg, "train"), crop=cfg.crop,
                                   history=cfg.frames - 1, oidn=oidn_settings(cfg))
        # Mitsuba frames are 256², Cycles train frames 128²: crops larger than the smallest
        # frame would differ in size and could not be stacked into one batch.
        crops = {(min(cfg.crop, s.size[0]), min(cfg.crop, s.size[1]))
                 for s in self.dataset.sequences}
        if cfg.batch > 1 and len(crops) > 1:
            raise ValueError(f"crop {cfg.crop}: the train frames give crops {sorted(crops)}, "
                             "which cannot share a batch; use a crop no larger than the "
                             "smallest frame, or batch 1")
        self.batch, self.seed = cfg.batch, cfg.seed
        self.per_epoch = max(len(self.dataset) // cfg.batch, 1)
        self._epoch, self._order = -1, torch.empty(0, dtype=torch.long)

    def __call__(self, step: int) -> dict[str, Tensor]:
        epoch, k = divmod(step, self.per_epoch)
        if epoch != self._epoch:
            generator = torch.Generator().manual_seed(self.seed * 1_000_003 + epoch)
            self._epoch = epoch
            self._order = torch.randperm(len(self.dataset), generator=generator)
        indices = self._order[k * self.batch : (k + 1) * self.batch].tolist()
        indices += self._order[: self.batch - len(indices)].tolist()  # dataset < one batch
        torch.manual_seed(self.seed * 1_000_003 + 7919 * step + 1)  # CropDataset draws here
        return default_collate([self.dataset[i] for i in indices])


def validation_batches(cfg: TrainConfig, spp: int = 1) -> list[dict[str, Tensor]]:
    """Whole validation sequences of the run's renderers (batch of one each); a renderer whose
    split is not rendered yet adds none."""
    roots = [root for root in split_roots(cfg, "validation") if root.exists()]
    if not roots:
        return []
    dataset = SequenceDataset(roots, spp=spp, oidn=oidn_settings(cfg))
    return [{k: v.unsqueeze(0) for k, v in dataset[i].items()} for i in range(len(dataset))]


def train(cfg: TrainConfig, run: Path, stop_at: int | None = None) -> Path:
    """Train (resuming from run/checkpoint.pt) up to cfg.steps, or pause at `stop_at` with a
    checkpoint: the schedule is the one of cfg.steps either way."""
    from tqdm import tqdm

    zoo_selection.check(cfg)
    on_shots = bool(zoo_selection.sources(cfg))  # zoo or corpus shots, not the generator's
    if on_shots:  # none rendered: an error now, not at the first evaluation
        notes: list[str] = []
        zoo_selection.zoo_sequences(cfg, notes)
        print("\n".join(notes) if notes else "selection: every validation shot rendered")
    run.mkdir(parents=True, exist_ok=True)
    (run / "config.json").write_text(json.dumps(dataclasses.asdict(cfg), indent=2))
    torch.manual_seed(cfg.seed)
    torch.set_num_threads(cfg.threads)
    step, best_psnr, metrics = 0, -math.inf, {}
    latest = run / "checkpoint.pt"
    ckpt = torch.load(latest, map_location="cpu", weights_only=False) if latest.exists() else None
    # A resumed run is the checkpoint's own model, whatever the flags say (resume_config).
    start = ckpt or (load_init(cfg.init) if cfg.init else None)
    model = build_model(cfg, start["config"] if start else None)
    if start:
        load_weights(model, start["model"])
    optimizer = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    if ckpt:
        optimizer.load_state_dict(ckpt["optimizer"])
        step, best_psnr, metrics = ckpt["step"], ckpt["best_psnr"], ckpt["metrics"]
    train_batches = TrainingBatches(cfg)
    log = (run / "log.txt").open("a")

    def evaluate(step: int) -> tuple[float, dict]:
        """Validate at `step`, keep best.pt where the score beats the best so far (or cannot be
        compared with it), checkpoint; returns the best score and its metrics."""
        best, kept_metrics = best_psnr, metrics
        # Re-listed each time: the validation split may still be rendering.
        val_batches = validation_batches(cfg)
        val_psnr = validate(model, val_batches) if val_batches else -math.inf
        record = {"step": step, "val_psnr": val_psnr, "val_sequences": len(val_batches)}
        # No validation split: no score (None; -inf is no JSON a card can carry).
        candidate = {"val_psnr_1spp_last_frame": round(val_psnr, 3) if val_batches else None,
                     "step": step, "val_sequences": len(val_batches)}
        if on_shots:
            zoo = zoo_selection.score(model, zoo_selection.zoo_sequences(cfg),
                                      cfg.select_crop, tqdm.write, cfg.select_on)
            score, comparable = zoo.psnr, zoo.same_set(kept_metrics)
            record |= {"zoo_psnr": zoo.psnr, "zoo_per_shot": zoo.per_shot}
            candidate |= zoo.metrics()
        else:
            # Scores are comparable only on the same validation set, which grows while
            # rendering (and not with a zoo score a resumed run kept).
            score = val_psnr
            comparable = (bool(val_batches) and "selected_on" not in kept_metrics
                          and kept_metrics.get("val_sequences") == len(val_batches))
        kept = score > best or not comparable
        log.write(json.dumps({**record, "kept": kept}) + "\n")
        log.flush()
        if kept:
            best, kept_metrics = score, candidate
            save(run / "best.pt", model, optimizer, step, cfg, best, kept_metrics)
        if on_shots:
            tqdm.write(f"step {step}: best.pt is step {kept_metrics['step']} "
                       f"({cfg.select_on} {best:.3f} dB)")
        save(latest, model, optimizer, step, cfg, best, kept_metrics)
        return best, kept_metrics

    bar = tqdm(total=cfg.steps, initial=step, desc=cfg.variant, dynamic_ncols=True)
    started, running = time.time(), None
    end = cfg.steps if stop_at is None else min(stop_at, cfg.steps)
    if cfg.init and not ckpt:  # the starting model is the score a fine-tune must beat
        best_psnr, metrics = evaluate(0)
    while step < end:
        batch = drop_buffers(cfg, train_batches(step), step)
        for group in optimizer.param_groups:
            group["lr"] = learning_rate(cfg, step)
        loss = batch_loss(cfg, model, batch, **step_kernel_size(cfg, step))
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        optimizer.step()
        step += 1
        running = loss.item() if running is None else 0.95 * running + 0.05 * loss.item()
        bar.update(1)
        bar.set_postfix(loss=f"{running:.4f}", best=f"{best_psnr:.2f}")  # the kept score
        if step % cfg.log_every == 0:
            log.write(json.dumps({"step": step, "loss": running,
                                  "seconds": round(time.time() - started, 1)}) + "\n")
            log.flush()
        if step % cfg.eval_every == 0 or step == cfg.steps:
            best_psnr, metrics = evaluate(step)
    if step % cfg.eval_every and step != cfg.steps:  # paused (--stop-at) between evaluations
        save(latest, model, optimizer, step, cfg, best_psnr, metrics)
    bar.close()
    return run / "best.pt"


ARCHITECTURE_FIELDS = ("variant", "width", "kernel_size", "kernel_sizes",  # fixed per run
                       "outlier_sigmas", "outlier_floor", "net_scale", "passthrough",
                       "noise_blend", "noise_input", "resampled_weight_per_doubling",
                       "albedo_prefilter")
# Architecture a fine-tune (--init) may still change: the clamp, the fade and the albedo's
# prefilter have no weights to load, the pass-through's and the noise level's weights are
# added (the models' adapt_state_dict).
FINE_TUNE_MAY_CHANGE = ("outlier_sigmas", "outlier_floor", "passthrough", "noise_blend",
                        "noise_input", "resampled_weight_per_doubling", "albedo_prefilter")


def load_init(init: str) -> dict:
    """The checkpoint a fine-tuning run starts from (FileNotFoundError naming it)."""
    path = Path(init).expanduser()
    if not path.is_file():
        raise FileNotFoundError(f"--init {init}: no such checkpoint")
    return torch.load(path, map_location="cpu", weights_only=False)


def resume_config(run: Path, flags: dict) -> TrainConfig:
    """The run's configuration: a new run's from the flags given (defaults elsewhere); a
    resumed run's from its checkpoint, with the flags given on top except the architecture,
    which a flag cannot change (ValueError naming the conflict). A new run with --init takes
    the architecture from the init checkpoint's training configuration the same way."""
    latest = run / "checkpoint.pt"
    if latest.exists():
        source, verb = latest, "resumes"
        base = torch.load(latest, map_location="cpu", weights_only=False)["training"]
    elif flags.get("init"):
        source, verb = Path(flags["init"]), "fine-tunes"
        saved = load_init(flags["init"])["training"]
        base = {k: saved[k] for k in ARCHITECTURE_FIELDS if k in saved}
    else:
        return TrainConfig(**flags)
    known = {f.name for f in dataclasses.fields(TrainConfig)}
    base = {k: v for k, v in base.items() if k in known}
    fixed = [k for k in ARCHITECTURE_FIELDS
             if verb == "resumes" or k not in FINE_TUNE_MAY_CHANGE]
    clashes = [k for k in fixed if k in flags and flags[k] != base.get(k)]
    if clashes:
        fix = "use a new --run" if verb == "resumes" else "drop the flag"
        raise ValueError(
            f"{run} {verb} a {base.get('variant')} model (width {base.get('width')}, from "
            f"{source}); --{'/--'.join(clashes)} cannot change a checkpoint's model: {fix}"
        )
    return TrainConfig(**{**base, **flags})


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="quietframe-train", description=__doc__.split("\n")[0])
    defaults = TrainConfig()
    for field in dataclasses.fields(TrainConfig):
        default = getattr(defaults, field.name)
        parser.add_argument(f"--{field.name.replace('_', '-')}", type=type(default),
                            default=argparse.SUPPRESS, help=f"default {default}")
    parser.add_argument("--run", type=Path,
                        help=f"run directory, resumed if it holds a checkpoint (default "
                        f"{RUNS_DIR}/<variant>)")
    parser.add_argument("--stop-at", type=int, help="pause at this step (resume later)")
    flags = vars(parser.parse_args(argv))
    run, stop_at = flags.pop("run"), flags.pop("stop_at")
    run = run or RUNS_DIR.expanduser() / flags.get("variant", TrainConfig.variant)
    try:
        cfg = resume_config(run, flags)
        dropped_buffers(cfg)
        renderers(cfg)
        zoo_selection.check(cfg)
        if zoo_selection.sources(cfg):
            zoo_selection.zoo_sequences(cfg)
    except (ValueError, FileNotFoundError) as exc:
        parser.error(str(exc))
    best = train(cfg, run, stop_at)
    print(f"best checkpoint: {best}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
