"""`model=auto`'s policy: which installed model a shot uses, from the frame's evidence
(service/frame_evidence.py, service/noise_estimate.py) and each model's measured table
(service/model_profiles.py). Pure functions: a session calls `choose` once per shot (its first
frame, a cut), so a shot never switches model mid-way (a switch changes the look: flicker).

The rule, in order (docs/service.md, "How auto chooses"): the models that accept the frame's
buffers and have a table; a temporal model only where its table vouches for it (motion vectors
present or their absence measured, the spp within reach); none whose worst validation-zoo shot
was worse than its own noisy input at the frame's spp; within the latency budget; not below
the per-frame floor (the renderer's own denoise, else per-frame OIDN-high); for balanced and
best, those that held on every validation-zoo shot; then the steady ones (locked-off flicker,
else TRMAE), within the quality's tolerance of the best expected PSNR; the cheapest of those."""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass

from quietframe.service.model_profiles import REFERENCE_PIXELS, ModelProfile, at_spp
from quietframe.service.noise_estimate import NoiseLevel

# dB below the best expected PSNR a quality accepts in exchange for speed. "balanced" matches
# the acceptance target of bench/auto_choice.py (within 0.3 dB of the best fixed model).
QUALITY_TOLERANCE_DB = {"fast": 1.0, "balanced": 0.3, "best": 0.0}
# Among the models within the PSNR tolerance, one whose measured TRMAE is more than this
# fraction above the steadiest of them is not chosen: quietframe's promise is a stable sequence,
# and OIDN on each frame alone can come within the tolerance of the accumulated tiers while
# flickering more (docs/benchmarks.md). A model that is better than the tolerance is not held
# back by it (e.g. per-frame OIDN where the accumulation would ghost without motion vectors).
STABILITY_SLACK = 0.10
# The per-frame floor: auto never picks a model whose validation figure at the shot's spp is
# more than this below per-frame OIDN-high's (the product's promise is never to lose to the
# renderer's own per-frame denoise); the default (balanced) and best do not go below it at all.
PER_FRAME_FLOOR_DB = {"fast": 0.3, "balanced": 0.0, "best": 0.0}
# Every shot, not the average: a model whose worst validation-zoo shot fell more than this below
# Blender's own denoise is left out where another held within it (holding_on_every_shot). On the
# zoo at 1 spp the plain-aux history tier leads on average (+1.38 dB) but loses 0.21 dB on the
# motion-blurred foliage shot, where the prefiltered-aux one holds (+0.11; docs/zoo.md).
EVERY_SHOT_SLACK_DB = 0.05
# The steadiness target of a temporal tier: flicker on locked-off shots at most half of
# per-frame OIDN's (docs/architecture.md, "The bar for a temporal tier").
STEADY_FLICKER_SHARE = 0.5
DEFAULT_QUALITY = "balanced"


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


def choose(
    present: Iterable[str],
    noise: NoiseLevel,
    profiles: Sequence[ModelProfile],
    default: str,
    quality: str | None = None,
    latency_ms: float | None = None,
    pixels: int = REFERENCE_PIXELS,
) -> Choice:
    """The cheapest model expected to meet the target (the rule of the module docstring)."""
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
    # Never a model that made a validation shot worse than leaving the frame alone.
    measured, below_note = not_below_input(measured, noise.spp)
    blind_note += below_note
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
                f"no model fits {latency_ms:g} ms; the fastest ({fastest[2]:.0f} ms expected)"
                f"{blind_note}",
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


def not_below_input(pool: list[ModelProfile], spp: float) -> tuple[list[ModelProfile], str]:
    """`pool` less the models whose worst validation-zoo shot at `spp` was below their own
    noisy input (ModelProfile.input_margin < 0), and a note naming them; a model without the
    figure stays. Where every candidate is below (no other model installed), the least below,
    and the note says so: auto must serve the frame with some model."""
    margin = {p.name: p.input_margin(spp) for p in pool}
    below = [p for p in pool if (m := margin[p.name]) is not None and m < 0]
    if not below:
        return pool, ""
    names = ", ".join(f"{p.name} ({margin[p.name]:+.2f} dB)" for p in below)
    if len(below) < len(pool):
        return ([p for p in pool if p not in below],
                f", left out as worse than their noisy input at {spp:g} spp on a validation-zoo "
                f"shot: {names}")
    least = max(margin[p.name] for p in below)
    return ([p for p in below if margin[p.name] >= least - 1e-9],
            f", every candidate worse than its noisy input at {spp:g} spp on a validation-zoo "
            f"shot ({names}): the least below")


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
