"""What `auto` knows of one installed model: its measured table for the frame's renderer (PSNR,
TRMAE and locked-off flicker by spp, by noise statistic, the cost of each absent buffer, how far
it held on the validation zoo and against its own noisy input there, ms at 720p), read from its
card (runtime/card.py), and what it is expected to give on a frame."""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from quietframe.runtime.card import (
    InputMarginRow,
    Measurements,
    ModelCard,
    finite_figure,
    worse_than_input_from,
)
from quietframe.service.noise_estimate import NoiseLevel

# A temporal model's table vouches for it up to this factor above the highest spp it was measured
# at (half a level of the 1, 2, 4, … grid). Beyond that its flat extrapolation is a guess the
# other way: a history blurs more, relative to the frame's own detail, the cleaner the frame
# (on Cycles the accumulation tiers went from ahead of per-frame OIDN at 1-4 spp to 2.7-4.7 dB
# behind Blender's denoise at 16), so a table measured to 8 spp says nothing of a 64-spp farm frame.
MEASURED_SPP_REACH = 2**0.5
REFERENCE_PIXELS = 1280 * 720  # `ms_720p` is per 1280×720 frame
ZOO_RENDERER = "cycles"  # the validation zoo's renderer (scenes/zoo_shots.py)

# Width (in log2 of the noise statistic) of the Gaussian weights over a model's by_noise points:
# about the statistic's spread between frames of one sequence at one spp, and the step between
# two spp levels (σ ∝ 1/spp^0.5 on rendered frames, service/noise_calibration.json).
NOISE_BANDWIDTH_LOG2 = 0.75


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
    # (spp, dB): the worst validation-zoo shot's PSNR less its own noisy input's
    # (runtime/card.InputMarginRow); below 0 the model made that shot worse than no denoise
    input_margin_by_spp: tuple[tuple[float, float], ...] = ()

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
        zoo = card.measured(ZOO_RENDERER)
        if not table.zoo:
            # The zoo (Cycles shots from outside the generator) measures how far a table from
            # the generator carries to other content; it stands for every renderer's table.
            table = replace(table, zoo=zoo.zoo)
        if not table.input_margin:  # the same content, the same reach
            table = replace(table, input_margin=zoo.input_margin)
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
            input_margin_by_spp=tuple((float(r.spp), float(r.worst_db))
                                      for r in table.input_margin if finite_figure(r.worst_db)),
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

    def input_margin(self, spp: float) -> float | None:
        """The worst validation-zoo shot's (model − noisy input) PSNR at `spp`, interpolated
        as the other tables (at_spp); None where not measured."""
        return at_spp(self.input_margin_by_spp, spp)

    def worse_than_input_from(self) -> float | None:
        """The lowest spp from which `input_margin` is below 0 (runtime/card.py
        worse_than_input_from, which reads only each row's spp and worst shot); None where it
        never is or was not measured."""
        return worse_than_input_from([InputMarginRow(spp, worst, worst)
                                      for spp, worst in self.input_margin_by_spp])

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
