"""model=auto's pure parts: the renderer's sample count, the reference-free noise estimate, the
choice from measured tables (service/frame_evidence.py, noise_estimate.py, model_profiles.py,
choice_policy.py)."""

from __future__ import annotations

import struct
from dataclasses import replace

import numpy as np
import pytest

from quietframe.bench.noise_calibration import fit, synthetic_points
from quietframe.service.choice_policy import choose
from quietframe.service.frame_evidence import renderer_from_header, samples_from_header
from quietframe.service.model_profiles import ModelProfile
from quietframe.service.noise_estimate import (
    NoiseLevel,
    estimate_spp,
    noise_statistic,
    spp_from_sigma,
)

ALL = ("color", "albedo", "normal", "depth", "motion")


def profile(name, ms, table, required=("color", "albedo", "normal", "depth"), **kw):
    metrics = {"ms_720p": ms, "by_spp": [{"spp": s, "psnr": p} for s, p in table], **kw}
    optional = tuple(b for b in ALL if b not in required)
    return ModelProfile.from_metadata(name, required, optional, metrics)


CHEAP = profile("cheap", 10, [(1, 20.0), (16, 29.5)])
MID = profile("mid", 50, [(1, 25.0), (16, 30.0)])
BEST = profile("best", 400, [(1, 25.5), (16, 30.1)])
COLOUR_ONLY = profile("colour", 30, [(1, 24.0), (16, 29.0)], required=("color",),
                      absent_db={"albedo": -1.0, "normal": -0.5})


def test_samples_from_cycles_header():
    text = {"cycles.ViewLayer.samples": ("string", b"16"), "Frame": ("string", b"2")}
    assert samples_from_header(text) == NoiseLevel(16.0, "cycles.ViewLayer.samples")
    binary = {"cycles.A.samples": ("int", struct.pack("<i", 64)),
              "cycles.B.samples": ("string", b"4")}
    assert samples_from_header(binary).spp == 4  # no layer chosen: the noisiest one
    assert samples_from_header(binary, layer="A") == NoiseLevel(64.0, "cycles.A.samples")
    assert samples_from_header({"cycles.A.samples": ("string", b"lots")}) is None
    assert samples_from_header({"cycles.A.samples": ("string", b"0")}) is None
    assert samples_from_header({"vrayInfo/rendertime": ("string", b"0h 1m")}) is None


def test_renderer_from_header_picks_that_renderers_tables():
    cycles = {"cycles.ViewLayer.samples": ("string", b"16"), "BlenderMultiChannel": ("string",
                                                                                    b"Blender")}
    assert renderer_from_header(cycles) == "cycles"
    assert renderer_from_header({"Frame": ("string", b"2")}) is None
    from quietframe.runtime.card import Measurements, ModelCard

    mitsuba = Measurements.from_dict({"by_spp": [{"spp": 1, "psnr": 25.0}]})
    blender = Measurements.from_dict({"by_spp": [{"spp": 1, "psnr": 21.0}]})
    card = ModelCard(name="m", measurements={"mitsuba": mitsuba, "cycles": blender})
    assert ModelProfile.from_card(card, "cycles").expected_psnr(1, ALL) == 21.0
    assert ModelProfile.from_card(card, None).expected_psnr(1, ALL) == 25.0
    only_mitsuba = ModelCard(name="m", measurements={"mitsuba": mitsuba})
    assert ModelProfile.from_card(only_mitsuba, "cycles").expected_psnr(1, ALL) == 25.0


def test_expected_psnr_interpolates_in_log_spp_and_never_extrapolates():
    assert MID.expected_psnr(4, ALL) == pytest.approx(27.5)  # halfway between 1 and 16 in log2
    assert MID.expected_psnr(0.5, ALL) == 25.0 and MID.expected_psnr(256, ALL) == 30.0
    assert COLOUR_ONLY.expected_psnr(1, ALL) == 24.0
    assert COLOUR_ONLY.expected_psnr(1, ("color", "normal")) == 23.0  # albedo absent: -1 dB
    assert MID.expected_ms(1280 * 720 * 2) == 100


@pytest.mark.parametrize(
    ("spp", "quality", "expected"),
    [
        (1, "balanced", "best"),  # mid is 0.5 dB behind best: beyond 0.3
        (1, "fast", "mid"),  # within 1 dB, cheaper
        (16, "balanced", "mid"),  # 0.1 dB behind best
        (16, "fast", "cheap"),
        (16, "best", "best"),
        (16, None, "mid"),  # balanced by default
    ],
)
def test_cheapest_model_within_the_quality_tolerance(spp, quality, expected):
    choice = choose(ALL, NoiseLevel(spp, "x"), [BEST, MID, CHEAP], "mid", quality=quality)
    assert choice.model == expected, choice.reason
    assert choice.spp == spp and choice.buffers == tuple(sorted(ALL))


def test_latency_budget_filters_then_quality_applies():
    profiles = [BEST, MID, CHEAP]
    at_1spp = NoiseLevel(1, "x")
    assert choose(ALL, at_1spp, profiles, "mid", quality="best", latency_ms=100).model == "mid"
    # ms scale with the session's pixels: at 4x 720p mid takes 200 ms
    large = choose(ALL, at_1spp, profiles, "mid", latency_ms=100, pixels=4 * 1280 * 720)
    assert large.model == "cheap"
    none_fits = choose(ALL, at_1spp, profiles, "mid", latency_ms=1)
    assert none_fits.model == "cheap" and "no model fits" in none_fits.reason


def test_buffers_decide_which_models_can_run():
    profiles = [BEST, MID, CHEAP, COLOUR_ONLY]
    colour = choose(("color",), NoiseLevel(4, "x"), profiles, "mid")
    assert colour.model == "colour"
    nothing = choose(("albedo",), NoiseLevel(4, "x"), [BEST], "best")
    assert nothing.model == "best" and "no installed model accepts" in nothing.reason
    unmeasured = ModelProfile("plain", ("color",), ())
    fallback = choose(ALL, NoiseLevel(4, "x"), [unmeasured], "plain")
    assert fallback.model == "plain" and "no measured" in fallback.reason


def _noisy_frame(spp: int, seed: int = 0, size: int = 96) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:size, 0:size] / size
    shading = 0.3 + np.exp(-((xx - 0.4) ** 2 + (yy - 0.6) ** 2) * 6)
    albedo = rng.uniform(0.1, 0.9, (3, size, size))  # texture the demodulation must remove
    noise = rng.gamma(spp / 2, 2 / spp, (size, size))  # as bench/noise_calibration draws
    return (albedo * (shading * noise)[None]).astype(np.float32), albedo.astype(np.float32)


def test_noise_statistic_falls_with_spp_and_ignores_albedo_texture():
    stats = [noise_statistic(*_noisy_frame(spp)) for spp in (1, 2, 4, 8, 16, 32)]
    assert all(a > b for a, b in zip(stats, stats[1:], strict=False)), stats
    ratio = stats[0] / stats[-1]
    assert 16 < ratio < 64  # variance ∝ 1/spp: 32x over five octaves
    color, albedo = _noisy_frame(1024)
    assert noise_statistic(color, albedo) < 0.1 * noise_statistic(color)  # texture divided out
    assert noise_statistic(np.zeros((3, 8, 8)), None) == 0.0


def test_estimate_maps_through_the_calibration():
    slope, intercept, rms = fit(synthetic_points(frames=2, size=64))
    calibration = {"slope": slope, "intercept": intercept, "max_spp": 64}
    assert -1.3 < slope < -0.7 and rms < 0.5
    estimates = [estimate_spp(*_noisy_frame(s, seed=3), calibration).spp for s in (1, 4, 16)]
    assert estimates[0] < estimates[1] < estimates[2]
    assert 0.5 < estimates[1] / 4 < 2, estimates
    unknown = estimate_spp(*_noisy_frame(4), None)
    assert (unknown.spp, unknown.source) == (1.0, "unknown")
    assert spp_from_sigma(0.0, calibration) == 64


def _with_points(name, ms, points, required=("color", "albedo", "normal", "depth")):
    """A profile whose by_noise points are (log2 σ, PSNR); the colour-only σ one unit higher."""
    return profile(name, ms, [(1, 25.0), (16, 30.0)], required=required,
                   by_noise={"points": [[x, x + 1, p] for x, p in points]})


# On clean-looking validation sequences (low σ) the expensive model is 1 dB ahead; on noisy-
# looking ones both are limited by the noise and 0.1 dB apart.
QUALITY = _with_points("quality", 100, [(-6, 36.0), (-5, 35.0), (2, 21.0), (3, 20.0)])
QUICK = _with_points("quick", 60, [(-6, 35.0), (-5, 34.0), (2, 20.9), (3, 19.9)])


@pytest.mark.parametrize(("log2_sigma", "expected"), [(-5.5, "quality"), (2.5, "quick")])
def test_by_noise_points_decide_at_the_same_spp(log2_sigma, expected):
    noise = NoiseLevel(4, "cycles.ViewLayer.samples", log2_sigma=log2_sigma)
    choice = choose(ALL, noise, [QUALITY, QUICK], "quick", quality="balanced")
    assert choice.model == expected, choice.reason
    assert "by_noise" in choice.reason and choice.log2_sigma == log2_sigma
    # without the statistic both fall back to the by_spp tables, which are equal: the cheaper
    assert choose(ALL, NoiseLevel(4, "x"), [QUALITY, QUICK], "quick").model == "quick"


def test_by_noise_weights_nearby_points_and_uses_the_matching_statistic():
    demodulated = NoiseLevel(1, "x", log2_sigma=-5.5)
    assert QUALITY.expected_psnr(1, ALL, demodulated) == pytest.approx(35.5, abs=0.01)
    far = NoiseLevel(1, "x", log2_sigma=40.0)  # far beyond every point: the nearest decides
    assert QUALITY.expected_psnr(1, ALL, far) == pytest.approx(20.0, abs=0.01)
    colour = NoiseLevel(1, "x", log2_sigma=-4.5, demodulated=False)  # = demodulated -5.5
    assert QUALITY.expected_psnr(1, ALL, colour) == pytest.approx(35.5, abs=0.01)


def test_by_noise_needs_every_candidate_to_have_points():
    # CHEAP has only a by_spp table: mixing the two kinds of figures would compare unrelated
    # absolute PSNRs, so the by_spp tables decide for all.
    choice = choose(ALL, NoiseLevel(16, "x", log2_sigma=-5.5), [QUALITY, CHEAP], "cheap",
                    quality="fast")
    assert "by_noise" not in choice.reason and choice.model == "cheap"


def test_estimate_keeps_the_stated_spp_and_measures_the_statistic():
    color, albedo = _noisy_frame(4)
    stated = estimate_spp(color, albedo, None, header=NoiseLevel(16, "cycles.A.samples"))
    assert (stated.spp, stated.source) == (16, "cycles.A.samples")
    assert stated.log2_sigma == pytest.approx(np.log2(noise_statistic(color, albedo)))
    assert stated.demodulated
    assert estimate_spp(color, None, None).demodulated is False


def _flicker(name, ms, psnr, trmae, required=("color",)):
    metrics = {"ms_720p": ms, "by_spp": [{"spp": s, "psnr": psnr, "trmae": trmae} for s in (1, 16)]}
    return ModelProfile.from_metadata(name, required, (), metrics)


def test_within_the_tolerance_a_model_that_flickers_more_is_not_chosen():
    steady = _flicker("accumulated", 100, 30.0, 0.80)
    per_frame = _flicker("per-frame", 90, 30.2, 1.00)  # higher PSNR, cheaper, 25% more flicker
    for quality in ("fast", "balanced"):
        choice = choose(ALL, NoiseLevel(16, "x"), [steady, per_frame], "accumulated",
                        quality=quality)
        assert choice.model == "accumulated", choice.reason
        assert "flickering more" in choice.reason
    # beyond the tolerance the better model wins: flicker is weighed among the good enough
    assert choose(ALL, NoiseLevel(16, "x"), [steady, per_frame], "accumulated",
                  quality="best").model == "per-frame"
    better = _flicker("per-frame", 90, 30.6, 1.00)
    assert choose(ALL, NoiseLevel(16, "x"), [steady, better], "accumulated").model == "per-frame"
    # within the slack both stay candidates: then the cheaper within tolerance wins
    close = _flicker("per-frame", 90, 30.1, 0.85)
    assert choose(ALL, NoiseLevel(16, "x"), [steady, close], "accumulated").model == "per-frame"
    # the guard never leaves the pool empty, and a model without TRMAE is not judged by it
    assert choose(("color",), NoiseLevel(4, "x"), [per_frame], "x").model == "per-frame"
    unmeasured_flicker = profile("no-trmae", 200, [(1, 31.0), (16, 31.0)])
    assert choose(ALL, NoiseLevel(4, "x"), [steady, unmeasured_flicker], "x",
                  quality="best").model == "no-trmae"


def test_an_absent_buffer_costs_its_worst_measured_loss():
    metrics = {"ms_720p": 50, "by_spp": [{"spp": 1, "psnr": 25.0}],
               "absent_db": {"motion": -0.4}, "absent_db_worst": {"motion": -2.9}}
    accumulating = ModelProfile.from_metadata("acc", ("color",), ("motion",), metrics)
    per_frame = profile("frame", 60, [(1, 24.5), (16, 24.5)], required=("color",))
    assert accumulating.expected_psnr(1, ("color",)) == pytest.approx(22.1)
    assert accumulating.expected_psnr(1, ("color", "motion")) == 25.0
    assert choose(("color",), NoiseLevel(1, "x"), [accumulating, per_frame], "acc").model == "frame"
    assert choose(("color", "motion"), NoiseLevel(1, "x"), [accumulating, per_frame],
                  "acc").model == "acc"


def _tier(name, ms, psnr_by_spp, flicker=None, per_frame=False):
    """A profile with PSNR (and locked-off flicker) per spp; `per_frame`: the floor's baseline."""
    rows = [{"spp": s, "psnr": p, "trmae": 1.0,
             **({} if flicker is None else {"flicker": flicker})} for s, p in psnr_by_spp]
    base = ModelProfile.from_metadata(name, ("color",), (), {"ms_720p": ms, "by_spp": rows})
    return replace(base, per_frame_oidn=per_frame)


def test_no_choice_below_per_frame_oidn_balanced_and_best_none_below_it_fast_within_03_db():
    frame = _tier("oidn-frame", 100, [(1, 30.0), (64, 36.0)], per_frame=True)
    cheap = _tier("cheap", 60, [(1, 29.8), (64, 35.8)])  # within 0.3 dB of the best, 0.2 below
    cheaper = _tier("cheaper", 30, [(1, 29.5), (64, 35.5)])  # 0.5 below per-frame OIDN
    tiers = [frame, cheap, cheaper]
    balanced = choose(ALL, NoiseLevel(64, "x"), tiers, "oidn-frame")
    assert balanced.model == "oidn-frame", balanced.reason
    assert "2 below per-frame oidn-frame left out" in balanced.reason
    fast = choose(ALL, NoiseLevel(1, "x"), tiers, "oidn-frame", quality="fast")
    assert fast.model == "cheap", fast.reason  # 'cheaper' is within 1 dB of the best, not 0.3
    # without a per-frame baseline installed the rule has nothing to hold to
    assert choose(ALL, NoiseLevel(1, "x"), [cheap, cheaper], "cheap",
                  quality="fast").model == "cheaper"
    # a latency budget only the cheapest fits: the user's budget decides, and says so
    budget = choose(ALL, NoiseLevel(1, "x"), tiers, "oidn-frame", latency_ms=40)
    assert budget.model == "cheaper" and "none that fits is above" in budget.reason


def test_the_renderers_own_denoise_is_the_floor_where_it_was_measured():
    """On Cycles frames a user could tick Blender's Denoise: balanced does not choose below it
    (its figure stamped beside per-frame OIDN's); where nothing reaches it, per-frame OIDN's
    floor still holds."""
    rows = [{"spp": 16, "psnr": 31.4, "renderer_denoise": 31.7},
            {"spp": 64, "psnr": 32.3, "renderer_denoise": 32.5}]
    frame = replace(ModelProfile.from_metadata("oidn-frame", ("color",), (),
                                               {"ms_720p": 100, "by_spp": rows}),
                    per_frame_oidn=True)
    assert frame.renderer_denoise_by_spp == ((16.0, 31.7), (64.0, 32.5))
    history = _tier("history", 110, [(16, 31.55), (64, 32.25)])  # above oidn-frame at 16 only
    cleanaux = _tier("cleanaux", 400, [(16, 31.8), (64, 32.45)])  # above Blender at 16 only
    at16 = choose(ALL, NoiseLevel(16, "x"), [frame, history, cleanaux], "oidn-frame")
    assert at16.model == "cleanaux", at16.reason
    assert "2 below the renderer's own denoise left out" in at16.reason
    # at 64 spp none reaches Blender's 32.5: per-frame OIDN's floor (32.3) decides
    at64 = choose(ALL, NoiseLevel(64, "x"), [frame, history, cleanaux], "oidn-frame")
    assert at64.model == "oidn-frame", at64.reason  # the cheapest within 0.3 dB of the best
    assert "1 below per-frame oidn-frame left out" in at64.reason
    # a table without the renderer's figure (Mitsuba): per-frame OIDN alone
    plain = _tier("oidn-frame", 100, [(16, 31.4), (64, 32.3)], per_frame=True)
    assert choose(ALL, NoiseLevel(16, "x"), [plain, history, cleanaux],
                  "oidn-frame").model == "history"


def test_locked_off_flicker_decides_steadiness_where_every_candidate_has_it():
    frame = _tier("oidn-frame", 100, [(1, 30.0), (64, 36.0)], flicker=0.010, per_frame=True)
    history = _tier("history", 112, [(1, 30.4), (64, 36.1)], flicker=0.0038)
    fast = _tier("fast-history", 74, [(1, 30.2), (64, 36.0)], flicker=0.0042)
    shimmer = _tier("shimmer", 50, [(1, 30.3), (64, 36.2)], flicker=0.0060)  # 0.6×: not steady
    choice = choose(ALL, NoiseLevel(4, "x"), [frame, history, fast, shimmer], "oidn-frame")
    # both history tiers are under half of per-frame OIDN's flicker: the cheaper one wins, not
    # only the steadiest (TRMAE's 10% slack would have left out fast-history at 1.1× history)
    assert choice.model == "fast-history", choice.reason
    assert "2 flickering more than 0.5× oidn-frame on locked-off shots left out" in choice.reason
    # none under half: the steadiest within the slack, by flicker
    loose = [frame, replace(shimmer, name="a"), _tier("b", 40, [(1, 30.1), (64, 36.0)],
                                                      flicker=0.0090)]
    assert choose(ALL, NoiseLevel(4, "x"), loose, "oidn-frame").model == "a"
    # a candidate without flicker: back to TRMAE for all (here equal, so the cheapest)
    mixed = [frame, history, _tier("unmeasured", 60, [(1, 30.3), (64, 36.1)])]
    assert choose(ALL, NoiseLevel(4, "x"), mixed, "oidn-frame").model == "unmeasured"


def test_a_steady_model_above_the_floor_is_not_pushed_out_by_a_sharper_one_that_flickers():
    """The target for auto is both: at least per-frame OIDN's PSNR and at most half its
    flicker. A sharper model that flickers more (an accumulation on a 1-spp Mitsuba frame:
    +0.5 dB, 0.62×) must not move the tolerance past the steady ones (+0.08 dB, 0.36×)."""
    frame = _tier("oidn-frame", 100, [(1, 30.0), (64, 36.0)], flicker=0.010, per_frame=True)
    sharp = _tier("acc", 60, [(1, 30.5), (64, 35.8)], flicker=0.0062)
    history = _tier("history", 112, [(1, 30.08), (64, 36.0)], flicker=0.0036)
    cleanaux = _tier("cleanaux", 460, [(1, 30.25), (64, 36.1)], flicker=0.0037)
    tiers = [frame, sharp, history, cleanaux]
    balanced = choose(ALL, NoiseLevel(1, "x"), tiers, "oidn-frame")
    assert balanced.model == "history", balanced.reason  # cheapest within 0.3 of cleanaux
    assert "2 flickering more than 0.5× oidn-frame" in balanced.reason
    assert choose(ALL, NoiseLevel(1, "x"), tiers, "oidn-frame", quality="best").model == "cleanaux"
    # at 64 spp the sharp one is below the floor anyway; the steady ones decide as before
    assert choose(ALL, NoiseLevel(64, "x"), tiers, "oidn-frame").model == "history"
    # where no candidate meets the flicker target, the tolerance counts from the best again
    unsteady = [frame, sharp, replace(history, name="h", flicker_by_spp=((1.0, 0.0070),))]
    assert choose(ALL, NoiseLevel(1, "x"), unsteady, "oidn-frame").model == "acc"


def test_the_per_frame_baseline_is_recognised_from_the_shipped_cards():
    import onnx

    from quietframe.runtime import installed_models
    from quietframe.runtime.card import ModelCard
    from quietframe.service.model_profiles import is_per_frame_oidn

    def card(path):
        model = onnx.load(str(path), load_external_data=False)
        return ModelCard.from_props({p.key: p.value for p in model.metadata_props}, path.stem)

    shipped = {p.stem: is_per_frame_oidn(card(p)) for p in installed_models()}
    if "oidn-frame" not in shipped:
        pytest.skip("no shipped oidn-frame model")
    assert shipped.pop("oidn-frame") is True
    assert not any(shipped.values()), shipped  # history, accumulation and learned tiers: no


def test_a_temporal_model_is_not_chosen_without_motion_where_that_was_never_measured():
    frame = _tier("oidn-frame", 100, [(1, 30.0), (64, 36.0)], per_frame=True)
    history = replace(_tier("history", 112, [(1, 30.6), (64, 36.4)]), temporal=True,
                      optional=("motion",))
    no_motion = ("color", "albedo", "normal", "depth")
    choice = choose(no_motion, NoiseLevel(4, "x"), [frame, history], "oidn-frame")
    assert choice.model == "oidn-frame" and "absent motion left out" in choice.reason
    assert choose(ALL, NoiseLevel(4, "x"), [frame, history], "oidn-frame").model == "history"
    # measured (its worst loss without motion is small): a candidate again
    measured = replace(history, absent_db_worst={"motion": -0.1})
    assert choose(no_motion, NoiseLevel(4, "x"), [frame, measured], "oidn-frame").model == \
        "history"


def test_a_temporal_model_is_not_chosen_above_the_spp_its_table_reaches():
    """A table measured to 8 spp (Mitsuba's) says nothing of a 64-spp farm frame: the history
    tiers that led at 8 spp may blur there, so a model without history is chosen instead."""
    frame = _tier("oidn-frame", 100, [(1, 30.0), (8, 34.0)], per_frame=True)
    acc = replace(_tier("acc", 60, [(1, 31.0), (8, 34.5)]), temporal=True)
    assert choose(ALL, NoiseLevel(8, "x"), [frame, acc], "oidn-frame").model == "acc"
    assert choose(ALL, NoiseLevel(11, "x"), [frame, acc], "oidn-frame").model == "acc"  # < √2·8
    high = choose(ALL, NoiseLevel(64, "x"), [frame, acc], "oidn-frame")
    assert high.model == "oidn-frame"
    assert "1 temporal measured only below 64 spp left out" in high.reason
    # a table that reaches 64 spp vouches for it there
    reaching = replace(_tier("acc64", 60, [(1, 31.0), (8, 34.5), (64, 37.0)]), temporal=True)
    assert choose(ALL, NoiseLevel(64, "x"), [frame, acc, reaching], "oidn-frame").model == "acc64"
    # with nothing but temporal models installed, one is still chosen
    assert choose(ALL, NoiseLevel(64, "x"), [acc], "acc").model == "acc"
