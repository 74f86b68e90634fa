"""The cost of OIDN's prefiltered aux (Blender's Accurate mode) per 1280x720 frame, by the aux
prefilters' quality, next to plain OIDN-high (the temporal tiers' per-frame floor) in one run:

    python -m quietframe.experiments.aux_prefilter [--threads 2] [--repeats 3]

Quality of the same settings on Cycles frames: quietframe-eval --renderer cycles --methods
blender-denoise,oidn-high,oidn-high-cleanaux,oidn-high-cleanaux-fast,oidn-high-cleanaux-balanced.
"""

from __future__ import annotations

import argparse

from quietframe.bench import cli_args
from quietframe.bench.baselines import OIDNDenoiser
from quietframe.bench.synthetic import frame_buffers
from quietframe.bench.timing import time_ms

CONFIGS = {
    "oidn-high (plain aux)": {},
    "aux prefiltered, high": {"prefilter_aux": True},
    "aux prefiltered, balanced": {"prefilter_aux": True, "aux_quality": "balanced"},
    "aux prefiltered, fast": {"prefilter_aux": True, "aux_quality": "fast"},
}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    cli_args.add_threads(parser)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    images = {k: v.transpose(1, 2, 0) for k, v in frame_buffers().items()}  # (H, W, C)
    ms = {}
    for name, options in CONFIGS.items():
        denoiser = OIDNDenoiser("high", num_threads=args.threads, **options)
        denoiser(images)  # filters committed outside the timing
        ms[name] = time_ms(lambda d=denoiser: d(images), warmup=1,
                           repeats=args.repeats).median_ms
        denoiser.close()
    plain = ms["oidn-high (plain aux)"]
    print("| OIDN-high, 1280x720 | ms | x plain |\n|---|---|---|")
    for name, value in ms.items():
        print(f"| {name} | {value:.0f} | {value / plain:.2f} |")


if __name__ == "__main__":
    main()
