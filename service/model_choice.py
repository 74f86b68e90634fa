"""`model=auto`: which installed model a session uses, from what its first frame shows.

Pure functions (no service state): the session registry calls `choose` in the plan step of a
session's first frame and of a cut, and nowhere else, so a shot never switches model mid-way
(a switch changes the look: that would be flicker). Inputs:

- the buffers the frame carries (from the EXR header, before any pixel is decoded);
- its noise level as an equivalent spp: the session's `model_options.spp` where set, else the
  renderer's own count where the header has one (`stated_samples`), else estimated from the
  decoded colour without a reference (`estimate_spp`, calibrated on rendered frames by
  `bench/noise_calibration.py`);
- how noisy the frame looks (`noise_statistic`, always measured when the service can decode
  the colour): the same spp is a clean frame in a sunlit room and a speckled one in a room lit
  through a window, and which model is good enough depends on that, not on the spp;
- the session's target: `quality` (fast | balanced | best) and/or `latency_ms`;
- each model's measured table (`ModelProfile.from_card`: the card's measurements for the
  frame's renderer, written by measurements into the ONNX metadata, docs/model-interface.md).

Among the models that fit the latency budget and are not below the per-frame floor
(per-frame OIDN-high's expected PSNR less PER_FRAME_FLOOR_DB: the product's promise is never to
lose to the renderer's own per-frame denoise), those that meet the flicker target are kept where
any does; of these, the ones within the quality's tolerance of the best expected PSNR among
them, less the unsteady, and the cheapest of the rest wins. Before that (quality balanced or
best), where some candidate held on every validation-zoo shot (its worst shot at most
EVERY_SHOT_SLACK_DB below Blender's own denoise, or the best worst shot of the candidates), only
those: an average lead is not traded for a loss on content like one shot's. A model
that keeps a history is a candidate only where its table vouches for it: with the motion
vectors or a measured cost of their absence, and at an spp its table reaches
(MEASURED_SPP_REACH). Steadiness is the measured flicker on locked-off validation shots where
every candidate has it (at most STEADY_FLICKER_SHARE of per-frame OIDN's), else TRMAE (at most
STABILITY_SLACK above the steadiest candidate's). Expected PSNR comes from each model's
`by_noise` points (validation sequences: the statistic of their first frame, the model's PSNR
on them) weighted by closeness in log2 of the statistic, when every candidate has them and the
frame's statistic is known; otherwise from the `by_spp` table at the frame's spp.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from quietframe.runtime.card import SAMPLES_INPUT, Measurements, ModelCard, finite_figure
from quietframe.runtime.exr_header import attribute_number

# dB below the best expected PSNR a quality accepts in exchange for speed. "balanced" matches
# the acceptance target of bench/auto_choice.py (within 0.3 dB of the best fixed model).
QUALITY_TOLERANCE_DB = {"fast": 1.0, "balanced": 0.3, "best": 0.0}
# Among the models within the PSNR tolerance, one whose measured TRMAE is more than this
# fraction above the steadiest of them is not chosen: quietframe's promise is a stable sequence,
# and OIDN on each frame alone can come within the tolerance of the accumulated tiers while
# flickering more (docs/benchmarks.md). A model that is better than the tolerance is not held
# back by it (e.g. per-frame OIDN where the accumulation would ghost without motion vectors).
STABILITY_SLACK = 0.10
# Issue 24: auto never picks a model whose validation figure at the shot's spp is more than
# 0.3 dB below per-frame OIDN-high's; the default (balanced) and best do not go below it at all.
PER_FRAME_FLOOR_DB = {"fast": 0.3, "balanced": 0.0, "best": 0.0}
# Every shot, not the average: a model whose worst validation-zoo shot fell more than this below
# Blender's own denoise is left out where another held within it (holding_on_every_shot). On the
# zoo at 1 spp the plain-aux history tier leads on average (+1.38 dB) but loses 0.21 dB on the
# motion-blurred foliage shot, where the prefiltered-aux one holds (+0.11; docs/zoo.md).
EVERY_SHOT_SLACK_DB = 0.05
# Issue 24's steadiness target: flicker on locked-off shots at most half of per-frame OIDN's.
STEADY_FLICKER_SHARE = 0.5
# A temporal model's table vouches for it up to this factor above the highest spp it was measured
# at (half a level of the 1, 2, 4, … grid). Beyond that its flat extrapolation is a guess the
# other way: a history blurs more, relative to the frame's own detail, the cleaner the frame
# (on Cycles the accumulation tiers went from ahead of per-frame OIDN at 1-4 spp to 2.7-4.7 dB
# behind Blender's denoise at 16), so a table measured to 8 spp says nothing of a 64-spp farm frame.
MEASURED_SPP_REACH = 2**0.5
DEFAULT_QUALITY = "balanced"
REFERENCE_PIXELS = 1280 * 720  # `ms_720p` is per 1280×720 frame

# Header attributes that state a frame's samples per pixel, by renderer. Only Cycles is known to
# write one (`cycles.<view layer>.samples`, a string, tests/fixtures/blender/README.md). Arnold,
# RenderMan and V-Ray write none we are confident of (V-Ray's `vrayInfo/*` carries no sample
# count): their frames use the estimate.
CYCLES_PREFIX, CYCLES_SUFFIX = "cycles.", ".samples"
# The renderers whose headers state the spp (`renderer_from_header` names them)
RENDERERS_STATING_SPP = ("cycles",)
# A NoiseLevel's source where the session set the spp (model_options)
SESSION_SAMPLES = f"model_options.{SAMPLES_INPUT}"

CALIBRATION_FILE = Path(__file__).with_name("noise_calibration.json")
ZOO_RENDERER = "cycles"  # the validation zoo's renderer (scenes/zoo_shots.py)


# Width (in log2 of the noise statistic) of the Gaussian weights over a model's by_noise points:
# about the statistic's spread between frames of one sequence at one spp, and the step between
# two spp levels (σ ∝ 1/spp^0.5 on rendered frames, service/noise_calibration.json).
NOISE_BANDWIDTH_LOG2 = 0.75


@dataclass(frozen=True)
class NoiseLevel:
    spp: float
    source: str  # the header attribute it came from, "estimate" or "unknown"
    # log2 of noise_statistic of the deciding frame (None: not measured), and whether it was
    # demodulated by the frame's albedo (by_noise points carry both kinds).
    log2_sigma: float | None = None
    demodulated: bool = True


@dataclass(frozen=True)
class ModelProfile:
    """What the choice knows of one installed model."""

    name: str
    required: tuple[str, ...]
    optional: tuple[str, ...]
    ms_720p: float | None = None
    psnr_by_spp: tuple[tuple[float, float], ...] = ()  # (spp, PSNR), spp ascending
    trmae_by_spp: tuple[tuple[float, float], ...] = ()  # (spp, TRMAE) where measured
    flicker_by_spp: tuple[tuple[float, float], ...] = ()  # (spp, locked-off flicker)
    # (spp, PSNR of the renderer's own denoise of the same validation frames): the floor where
    # the frame's renderer has a denoise of its own (Blender's on Cycles)
    renderer_denoise_by_spp: tuple[tuple[float, float], ...] = ()
    # Per-frame OIDN-high on the frame's own colour and plain aux, no state: the baseline of the
    # per-frame floor (what a renderer's own denoise gives, near enough; docs/benchmarks.md).
    per_frame_oidn: bool = False
    temporal: bool = False  # keeps state between frames: reads the motion vectors' history
    absent_db: Mapping[str, float] = field(default_factory=dict)  # PSNR change, buffer absent
    # The largest loss measured per absent buffer; planned for when stamped (see expected_psnr)
    absent_db_worst: Mapping[str, float] = field(default_factory=dict)
    # (log2 σ demodulated, log2 σ of the colour alone, PSNR) per validation (sequence, spp)
    psnr_by_noise: tuple[tuple[float, float, float], ...] = ()
    # (spp, dB ≤ 0): how much less the model held on the validation zoo (shots from outside the
    # scene generator) than its table promises, against per-frame OIDN-high (runtime/card.ZooRow)
    zoo_shortfall_by_spp: tuple[tuple[float, float], ...] = ()
    # (spp, dB): the worst validation-zoo shot's PSNR less Blender's own denoise's (ZooRow)
    zoo_worst_vs_denoise_by_spp: tuple[tuple[float, float], ...] = ()

    @classmethod
    def from_card(cls, card: ModelCard, renderer: str | None = None) -> ModelProfile:
        """A model's profile from its card: the renderer's measured table where it has one,
        else the default renderer's (runtime/card.py ModelCard.measured)."""
        table = card.measured(renderer)
        if not (table.absent_db or table.absent_db_worst):
            # What a missing buffer costs is the model's design more than the renderer's look:
            # the default renderer's figures stand in where this renderer's were not measured.
            default = card.measured(None)
            table = replace(table, absent_db=default.absent_db,
                            absent_db_worst=default.absent_db_worst)
        if not table.zoo:
            # The zoo (Cycles shots from outside the generator) measures how far a table from
            # the generator carries to other content; it stands for every renderer's table.
            table = replace(table, zoo=card.measured(ZOO_RENDERER).zoo)
        profile = cls.from_measurements(card.name, card.required, card.optional, table)
        return replace(profile, per_frame_oidn=is_per_frame_oidn(card),
                       temporal=bool(card.state))

    @classmethod
    def from_metadata(
        cls, name: str, required: Sequence[str], optional: Sequence[str], metrics: Mapping
    ) -> ModelProfile:
        """From a `quietframe.metrics` dict as written (tests, tables built by hand)."""
        return cls.from_measurements(name, required, optional, Measurements.from_dict(metrics))

    @classmethod
    def from_measurements(
        cls, name: str, required: Sequence[str], optional: Sequence[str], table: Measurements
    ) -> ModelProfile:
        return cls(
            name=name,
            required=tuple(required),
            optional=tuple(optional),
            ms_720p=float(table.ms_720p) if table.ms_720p is not None else None,
            psnr_by_spp=tuple((float(r.spp), float(r.psnr)) for r in table.by_spp),
            trmae_by_spp=tuple((float(r.spp), float(r.trmae)) for r in table.by_spp
                               if finite_figure(r.trmae)),
            flicker_by_spp=tuple((float(r.spp), float(r.flicker)) for r in table.by_spp
                                 if finite_figure(r.flicker)),
            renderer_denoise_by_spp=tuple((float(r.spp), float(r.renderer_denoise))
                                          for r in table.by_spp
                                          if finite_figure(r.renderer_denoise)),
            absent_db={k: float(v) for k, v in table.absent_db.items()},
            absent_db_worst={k: float(v) for k, v in table.absent_db_worst.items()},
            psnr_by_noise=tuple((float(a), float(b), float(p)) for a, b, p in table.by_noise),
            zoo_shortfall_by_spp=tuple((float(r.spp), min(0.0, float(r.shortfall_db)))
                                       for r in table.zoo),
            zoo_worst_vs_denoise_by_spp=tuple((float(r.spp), float(r.worst_vs_denoise_db))
                                              for r in table.zoo
                                              if finite_figure(r.worst_vs_denoise_db)),
        )

    @property
    def measured(self) -> bool:
        return self.ms_720p is not None and bool(self.psnr_by_spp)

    def measured_at(self, spp: float) -> bool:
        """Whether the table reaches `spp` (within MEASURED_SPP_REACH of its highest level)."""
        top = max((s for s, _ in self.psnr_by_spp), default=0.0)
        return spp <= MEASURED_SPP_REACH * top

    def accepts(self, present: Iterable[str]) -> bool:
        return set(self.required) <= set(present)

    def expected_psnr(self, spp: float, present: Iterable[str],
                      noise: NoiseLevel | None = None) -> float:
        """With `noise` (a measured statistic) and by_noise points: their PSNR weighted by
        closeness of the statistic (Gaussian in log2 σ, NOISE_BANDWIDTH_LOG2), so a frame is
        compared with validation sequences that looked as noisy. Otherwise the PSNR at `spp`,
        linear in log2(spp) between measured levels and flat beyond them (no extrapolation: a
        model is never credited with more than was measured). Either way plus the measured
        change for each optional buffer the frame lacks (0 where unmeasured), and less the
        shortfall the validation zoo showed at this spp (0 where unmeasured): a table from one
        scene generator is trusted only as far as shots from outside it confirm."""
        if noise is not None and noise.log2_sigma is not None and self.psnr_by_noise:
            points = np.array(self.psnr_by_noise)
            x = points[:, 0 if noise.demodulated else 1]
            z = (x - noise.log2_sigma) / NOISE_BANDWIDTH_LOG2
            weights = np.exp(-0.5 * (z**2 - np.min(z**2)))  # the nearest point weighs 1
            psnr = float(weights @ points[:, 2] / weights.sum())
        else:
            levels = np.log2([s for s, _ in self.psnr_by_spp])
            psnr = float(np.interp(math.log2(max(spp, 1e-3)), levels,
                                   [p for _, p in self.psnr_by_spp]))
        # Absent buffers: the worst measured loss where stamped, else the mean. Risk-averse on
        # purpose: without motion vectors an accumulating model loses nothing on a static shot
        # and 2-3 dB on a moving camera (validation), and auto cannot tell which this shot is.
        change = {**self.absent_db, **self.absent_db_worst}
        have = set(present)
        psnr += at_spp(self.zoo_shortfall_by_spp, spp) or 0.0
        return psnr + sum(change.get(b, 0.0) for b in self.optional if b not in have)

    def expected_trmae(self, spp: float) -> float | None:
        """Measured TRMAE (all buffers) at `spp`, as expected_psnr interpolates."""
        return at_spp(self.trmae_by_spp, spp)

    def expected_flicker(self, spp: float) -> float | None:
        """Measured flicker on locked-off shots at `spp`, as expected_psnr interpolates."""
        return at_spp(self.flicker_by_spp, spp)

    def expected_ms(self, pixels: int) -> float:
        assert self.ms_720p is not None
        return self.ms_720p * pixels / REFERENCE_PIXELS


def profile_of(name: str, denoiser, renderer: str | None = None) -> ModelProfile:
    """What `auto` knows of an installed model (a runtime Denoiser) for frames of `renderer`:
    its own card's table (a composition is chosen on it), the buffers of the whole
    composition."""
    return replace(ModelProfile.from_card(denoiser.card, renderer), name=name,
                   required=tuple(denoiser.info.required_buffers),
                   optional=tuple(denoiser.info.optional_buffers),
                   temporal=bool(denoiser.info.state_specs))


def at_spp(table: Sequence[tuple[float, float]], spp: float) -> float | None:
    """A per-spp figure, linear in log2(spp) between measured levels and flat beyond them."""
    if not table:
        return None
    levels = np.log2([s for s, _ in table])
    return float(np.interp(math.log2(max(spp, 1e-3)), levels, [v for _, v in table]))


def is_per_frame_oidn(card: ModelCard) -> bool:
    """Whether a card is per-frame OIDN-high: one OIDN stage (high, on the frame's colour, plain
    albedo and normal) and a graph without state."""
    oidn = card.prepass
    return (oidn is not None and not card.state and len(card.stages) == 2
            and oidn.quality == "high" and not oidn.prefilter_aux and not oidn.color_from
            and set(oidn.aux) == {"albedo", "normal"})


@dataclass(frozen=True)
class Choice:
    model: str
    reason: str
    spp: float | None
    noise_source: str
    buffers: tuple[str, ...]  # what the deciding frame carried
    log2_sigma: float | None = None  # the deciding frame's noise statistic (NoiseLevel)
    expected_psnr: float | None = None
    expected_ms: float | None = None

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: Mapping) -> Choice:
        return cls(**{**data, "buffers": tuple(data["buffers"])})


# ---- noise level ----------------------------------------------------------------------------


def samples_from_header(
    attributes: Mapping[str, tuple[str, bytes]], layer: str | None = None
) -> NoiseLevel | None:
    """The renderer's samples per pixel from EXR header attributes (kind, raw bytes), or None.
    With several view layers and none chosen, the fewest samples (the noisiest layer) count."""
    found: dict[str, float] = {}
    for name, (kind, value) in attributes.items():
        if name.startswith(CYCLES_PREFIX) and name.endswith(CYCLES_SUFFIX):
            view = name[len(CYCLES_PREFIX) : -len(CYCLES_SUFFIX)]
            number = attribute_number(name, kind, value)
            if number is not None and math.isfinite(number) and number >= 1:
                found[view] = number
    if layer is not None and layer in found:
        return NoiseLevel(found[layer], f"{CYCLES_PREFIX}{layer}{CYCLES_SUFFIX}")
    if not found:
        return None
    view = min(found, key=found.__getitem__)
    return NoiseLevel(found[view], f"{CYCLES_PREFIX}{view}{CYCLES_SUFFIX}")


def stated_samples(
    attributes: Mapping[str, tuple[str, bytes]], layer: str | None,
    model_options: Mapping[str, float | int],
) -> NoiseLevel | None:
    """The spp stated for a frame, or None (estimate it): the session's `model_options.spp`
    where set, else the renderer's header. The session's wins as it does for the model's input
    (model_registry.options_for), so the choice plans for the spp the chosen model is given."""
    if SAMPLES_INPUT in model_options:
        return NoiseLevel(float(model_options[SAMPLES_INPUT]), SESSION_SAMPLES)
    return samples_from_header(attributes, layer)


def renderer_from_header(attributes: Mapping[str, tuple[str, bytes]]) -> str | None:
    """Which renderer wrote a frame, where its header says so: Cycles writes
    `cycles.<view layer>.samples` (tests/fixtures/blender/README.md). None: unknown, and
    `auto` uses the default renderer's tables (runtime/card.py ModelCard.measured)."""
    if any(n.startswith(CYCLES_PREFIX) and n.endswith(CYCLES_SUFFIX) for n in attributes):
        return "cycles"
    return None


def _box(x: np.ndarray, size: int) -> np.ndarray:
    """Mean over a size×size window (edge-padded), by summed-area table."""
    h, w = x.shape
    padded = np.pad(x, size // 2, mode="edge")
    table = np.pad(padded, ((1, 0), (1, 0))).cumsum(0).cumsum(1)
    return (
        table[size : size + h, size : size + w] - table[:h, size : size + w]
        - table[size : size + h, :w] + table[:h, :w]
    ) / (size * size)


def noise_statistic(color: np.ndarray, albedo: np.ndarray | None = None) -> float:
    """A reference-free noise statistic of one (3, H, W) frame: the relative variance of the
    demodulated luminance around its 5×5 box mean. Dividing by albedo removes texture, so what
    is left around the local mean is mostly Monte Carlo noise (variance ∝ 1/spp). Not a robust
    (median) spread: at 1–2 spp most pixels of a dim scene are exactly 0, which a median reads
    as no noise; instead the brightest 0.1 % (fireflies) are clipped."""
    lum = np.nan_to_num(np.asarray(color, np.float64).mean(0), nan=0.0, posinf=0.0)
    lum = np.maximum(lum, 0.0)
    if albedo is not None:
        lum = lum / np.maximum(np.asarray(albedo, np.float64).mean(0), 0.05)
    lum = np.minimum(lum, np.percentile(lum, 99.9))
    smooth = _box(lum, 5)
    scale = float(smooth.mean()) ** 2
    if not math.isfinite(scale) or scale <= 0:
        return 0.0
    return float(((lum - smooth) ** 2).mean() / scale)


def load_calibration(path: Path = CALIBRATION_FILE) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def spp_from_sigma(sigma: float, calibration: Mapping) -> float:
    """Equivalent spp of a noise statistic: log2(spp) = intercept + slope·log2(σ) (fitted by
    bench/noise_calibration.py; σ is a variance ∝ 1/spp, so the slope is near -1)."""
    if sigma <= 0:
        return float(calibration.get("max_spp", 1024))
    log_spp = calibration["intercept"] + calibration["slope"] * math.log2(sigma)
    lo, hi = calibration.get("min_spp", 0.25), calibration.get("max_spp", 1024)
    return float(min(max(2.0**log_spp, lo), hi))


def log2_statistic(sigma: float) -> float | None:
    return math.log2(sigma) if sigma > 0 and math.isfinite(sigma) else None


def estimate_spp(
    color: np.ndarray, albedo: np.ndarray | None, calibration: Mapping | None,
    header: NoiseLevel | None = None,
) -> NoiseLevel:
    """The frame's noise: the header's spp where given (`header`), else the calibrated estimate,
    and in both cases the statistic itself (the choice's by_noise lookup)."""
    sigma = noise_statistic(color, albedo)
    measured = {"log2_sigma": log2_statistic(sigma), "demodulated": albedo is not None}
    if header is not None:
        return NoiseLevel(header.spp, header.source, **measured)
    if calibration is None:  # no fit shipped: the choice then plans for the noisiest input
        return NoiseLevel(1.0, "unknown", **measured)
    return NoiseLevel(round(spp_from_sigma(sigma, calibration), 2), "estimate", **measured)


# ---- the choice -----------------------------------------------------------------------------


def choose(
    present: Iterable[str],
    noise: NoiseLevel,
    profiles: Sequence[ModelProfile],
    default: str,
    quality: str | None = None,
    latency_ms: float | None = None,
    pixels: int = REFERENCE_PIXELS,
) -> Choice:
    """The cheapest model expected to meet the target (see the module docstring)."""
    have = tuple(sorted(set(present)))
    sigma = None if noise.log2_sigma is None else round(noise.log2_sigma, 3)
    base = {"spp": noise.spp, "noise_source": noise.source, "buffers": have, "log2_sigma": sigma}
    accepting = [p for p in profiles if p.accepts(have)]
    if not accepting:  # the frame check then names the buffers and the models that take them
        return Choice(default, f"no installed model accepts buffers {list(have)}", **base)
    measured = [p for p in accepting if p.measured]
    if not measured:
        name = default if any(p.name == default for p in accepting) else accepting[0].name
        return Choice(name, "no measured speed/error table: the default model", **base)
    # A temporal model reads a frame without motion as a static camera: where what that costs
    # it was never measured, it is not a candidate (on a moving shot it ghosts).
    blind = [p for p in measured if p.temporal and "motion" in p.optional and "motion" not in have
             and "motion" not in {**p.absent_db, **p.absent_db_worst}]
    measured, blind_note = leave_out(measured, blind,
                                     "temporal without a measured cost of absent motion")
    # Nor is a temporal model at an spp its table does not reach (MEASURED_SPP_REACH), where a
    # model that keeps no history can be chosen instead.
    unreached = [p for p in measured if p.temporal and not p.measured_at(noise.spp)]
    measured, unreached_note = leave_out(measured, unreached,
                                         f"temporal measured only below {noise.spp:g} spp")
    blind_note += unreached_note
    quality = quality or DEFAULT_QUALITY
    # by_noise only when every candidate has it: absolute PSNRs from different tables (or
    # different validation points) are not comparable.
    by_noise = noise.log2_sigma is not None and all(p.psnr_by_noise for p in measured)
    lookup = noise if by_noise else None
    scored = [(p, p.expected_psnr(noise.spp, have, lookup), p.expected_ms(pixels))
              for p in measured]
    pool, budget_note = scored, blind_note
    if latency_ms is not None:
        fits = [s for s in scored if s[2] <= latency_ms]
        if fits:
            pool, budget_note = fits, f", fits {latency_ms:g} ms"
        else:  # nothing fits: the fastest is the closest to the budget
            fastest = min(scored, key=lambda s: s[2])
            return Choice(
                fastest[0].name,
                f"no model fits {latency_ms:g} ms; the fastest ({fastest[2]:.0f} ms expected)",
                **base,
                expected_psnr=round(fastest[1], 2),
                expected_ms=round(fastest[2], 3),
            )
    baseline = next((s for s in scored if s[0].per_frame_oidn), None)
    if baseline is not None:
        pool, floor_note = above_floor(pool, baseline, noise.spp, quality)
        budget_note += floor_note
    if quality != "fast":
        pool, shot_note = holding_on_every_shot(pool, noise.spp)
        budget_note += shot_note
    # Steadiness first (auto is to be as good as per-frame OIDN and steadier):
    # where some candidate above the floor meets the flicker target, the tolerance is counted
    # from the best of those, so a sharper model that flickers more does not push them out.
    steady_pool, steady_note = meeting_flicker_target(pool, noise.spp, baseline)
    best_psnr = max(s[1] for s in steady_pool or pool)
    tolerance = QUALITY_TOLERANCE_DB[quality]
    good = [s for s in steady_pool or pool if s[1] >= best_psnr - tolerance - 1e-9]
    if not steady_pool:
        good, steady_note = steady_candidates(good, noise.spp, baseline)
    budget_note += steady_note
    profile, psnr, ms = min(good, key=lambda s: (s[2], -s[1]))
    best_name = max(steady_pool or pool, key=lambda s: (s[1], -s[2]))[0].name
    relation = (
        "the best expected" if profile.name == best_name
        else f"within {tolerance:g} dB of {best_name}"
    )
    looks = (f", looks like log2 σ {noise.log2_sigma:.2f} (by_noise)" if by_noise else "")
    reason = (
        f"{quality}: cheapest within tolerance at {noise.spp:g} spp ({noise.source}{looks}); "
        f"{psnr:.2f} dB expected, {relation}{budget_note}"
    )
    return Choice(
        profile.name, reason, **base, expected_psnr=round(psnr, 2), expected_ms=round(ms, 3)
    )


def leave_out(pool: list[ModelProfile], out: list[ModelProfile],
              why: str) -> tuple[list[ModelProfile], str]:
    """`pool` less `out`, and a note saying how many and why; all of `pool` where that would
    leave no candidate."""
    if not out or len(out) == len(pool):
        return pool, ""
    return [p for p in pool if p not in out], f", {len(out)} {why} left out"


Scored = tuple[ModelProfile, float, float]  # profile, expected PSNR, expected ms


def above_floor(pool: list[Scored], baseline: Scored, spp: float,
                quality: str) -> tuple[list[Scored], str]:
    """The candidates not below the per-frame floor, and a note on those left out. The floor
    is the renderer's own denoise where the baseline's table has it (Blender's on Cycles: a
    user could tick Denoise instead), else per-frame OIDN-high; less PER_FRAME_FLOOR_DB.
    Where nothing reaches the renderer's, per-frame OIDN-high's; where nothing reaches that
    either (only a latency budget can do it: the budget is the user's), all of `pool`."""
    slack = PER_FRAME_FLOOR_DB[quality]
    profile, expected = baseline[0], baseline[1]
    floors = []
    own, at = at_spp(profile.renderer_denoise_by_spp, spp), at_spp(profile.psnr_by_spp, spp)
    if own is not None and at is not None and own > at:  # relative to the baseline's table
        floors.append((expected + own - at - slack, "the renderer's own denoise"))
    floors.append((expected - slack, f"per-frame {profile.name}"))
    for floor, name in floors:
        above = [s for s in pool if s[1] >= floor - 1e-9]
        if above:
            left = len(pool) - len(above)
            margin = f" less {slack:g} dB" if slack else ""  # "less 0 dB" read as a typo
            return above, (f", {left} below {name}{margin} left out" if left else "")
    return pool, f", none that fits is above per-frame {profile.name}"


def holding_on_every_shot(pool: list[Scored], spp: float) -> tuple[list[Scored], str]:
    """The candidates whose worst validation-zoo shot at `spp` is within EVERY_SHOT_SLACK_DB of
    Blender's own denoise (or of the best worst shot among them, where none is), and a note on
    those left out. A candidate the zoo never measured has not held: it goes with them. All of
    `pool` where no candidate has the figure."""
    worst = {s[0].name: at_spp(s[0].zoo_worst_vs_denoise_by_spp, spp) for s in pool}
    known = [w for w in worst.values() if w is not None]
    if not known:
        return pool, ""
    threshold = min(-EVERY_SHOT_SLACK_DB, max(known) - EVERY_SHOT_SLACK_DB)
    held = [s for s in pool if (w := worst[s[0].name]) is not None and w >= threshold - 1e-9]
    left = len(pool) - len(held)
    return held, (f", {left} that lost over {-threshold:.2f} dB to Blender's denoise on a zoo "
                  "shot (or unmeasured there) left out" if left else "")


def meeting_flicker_target(pool: list[Scored], spp: float,
                           baseline: Scored | None) -> tuple[list[Scored], str]:
    """The candidates whose locked-off flicker is at most STEADY_FLICKER_SHARE of the per-frame
    baseline's, and a note on those left out; none (and no note) where some candidate or the
    baseline has no flicker figure, or none meets the target."""
    base = baseline[0].expected_flicker(spp) if baseline is not None else None
    flicker = {s[0].name: s[0].expected_flicker(spp) for s in pool}
    if base is None or None in flicker.values():
        return [], ""
    steady = [s for s in pool if flicker[s[0].name] <= STEADY_FLICKER_SHARE * base + 1e-12]
    left = len(pool) - len(steady)
    return steady, (f", {left} flickering more than {STEADY_FLICKER_SHARE:g}× "
                    f"{baseline[0].name} on locked-off shots left out" if steady and left else "")


def steady_candidates(good: list[Scored], spp: float,
                      baseline: Scored | None) -> tuple[list[Scored], str]:
    """The candidates steady enough, and a note on those left out. Where every candidate and
    the per-frame baseline have locked-off flicker: those at most STEADY_FLICKER_SHARE of the
    baseline's (none qualifying: the steadiest within STABILITY_SLACK); otherwise by TRMAE,
    none clearly above the steadiest (STABILITY_SLACK; unmeasured ones are kept)."""
    steady, note = meeting_flicker_target(good, spp, baseline)
    if steady:
        return steady, note
    flicker = {s[0].name: s[0].expected_flicker(spp) for s in good}
    base = baseline[0].expected_flicker(spp) if baseline is not None else None
    if base is not None and None not in flicker.values():
        measure, kind = flicker, "locked-off flicker"
    else:
        measure = {s[0].name: s[0].expected_trmae(spp) for s in good}
        kind = "TRMAE"
    steadiest = min((t for t in measure.values() if t is not None), default=None)
    if steadiest is None:
        return good, ""
    steady = [s for s in good if measure[s[0].name] is None
              or measure[s[0].name] <= (1 + STABILITY_SLACK) * steadiest]
    left = len(good) - len(steady)
    return steady, (f", {left} flickering more than {1 + STABILITY_SLACK:g}× the steadiest "
                    f"({kind}) left out" if left else "")
