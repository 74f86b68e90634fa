"""experiments/named_spp_estimate's summary: the estimate's gain over the default per spp
(mean, worst, best shot) and its error in stops, from rows bench/zoo_eval writes."""

from __future__ import annotations

from quietframe.experiments.named_spp_estimate import DEFAULT, SPP_LEVELS, TIERS, summary


def test_the_summary_pairs_each_tier_with_its_default_on_the_same_shot():
    rows = []
    for shot, gain in (("a", 0.5), ("b", -0.1)):
        for spp in SPP_LEVELS:
            for name in TIERS:
                rows.append({"shot": shot, "spp": spp, "method": name + DEFAULT, "psnr": 30.0})
                rows.append({"shot": shot, "spp": spp, "method": name, "psnr": 30.0 + gain,
                             "estimated_spp": spp * 2.0})
    lines = summary(rows)
    assert len(lines) == len(TIERS) * len(SPP_LEVELS)
    assert lines[0] == (f"{TIERS[0]}  1 spp: estimate - default +0.20 dB mean, -0.10 worst, "
                        "+0.50 best; estimated spp +1.00 stops off on the mean (rms 1.00)")
