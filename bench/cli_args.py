"""The flags every benchmark and experiment shares: one meaning and one default each.

A script adds the ones it reads (`add_threads(parser)`, `add_renderer(parser)`, ...). These name
the machine and the data, so `--threads 2` or `--split validation` mean the same in every
command; flags that describe one measurement (its spp levels, repeats, frame sizes) stay with
their script (`add_sequences` parses `--spp` the one way, but its default list is the script's).
A documented command that needs another value than the default states it.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

from quietframe.runtime.card import DEFAULT_RENDERER
from quietframe.scenes.layout import DATA_DIR, DEFAULT_THREADS, RENDERERS
from quietframe.scenes.zoo_shots import ZOO_ROUNDS, ZOO_SPLITS, ZOO_VERSION

# Model selection's split: every choice and table is made on it, and a run that reports a
# figure for the test split names it.
DEFAULT_SPLIT = "validation"
# Frames a benchmarked server runs at once: 0 is the server's own rule (CPUs / threads), so
# the default never oversubscribes the cores the default threads already fill.
DEFAULT_WORKERS = 0


def add_threads(parser: argparse.ArgumentParser, *, sweep: bool = False,
                help: str = "CPU threads of the measured code") -> None:
    """`--threads N` (`--threads 1 2 ...` with `sweep`: one measurement per count)."""
    if sweep:
        parser.add_argument("--threads", type=int, nargs="+", default=[DEFAULT_THREADS],
                            help=f"{help}, one measurement each (default {DEFAULT_THREADS})")
    else:
        parser.add_argument("--threads", type=int, default=DEFAULT_THREADS,
                            help=f"{help} (default {DEFAULT_THREADS})")


def add_workers(parser: argparse.ArgumentParser) -> None:
    """`--workers N`: the server's frames in flight (QUIETFRAME_WORKERS)."""
    parser.add_argument("--workers", type=int, default=DEFAULT_WORKERS,
                        help="server frames in flight (default 0: CPUs / threads)")


def add_renderer(parser: argparse.ArgumentParser, help: str = "whose frames") -> None:
    """`--renderer`: whose frames are read (and whose table a card keeps)."""
    parser.add_argument("--renderer", choices=RENDERERS, default=DEFAULT_RENDERER,
                        help=f"{help} (default {DEFAULT_RENDERER})")


def add_data(parser: argparse.ArgumentParser) -> None:
    """`--data`: the rendered splits' root (quietframe-render's)."""
    parser.add_argument("--data", type=Path, default=DATA_DIR,
                        help=f"rendered data (default {DATA_DIR})")


def add_split(parser: argparse.ArgumentParser, choices: Sequence[str] | None = None,
              help: str = "") -> None:
    """`--split`: train, validation, test or a locked-off `*-static` split (or `choices`)."""
    parser.add_argument("--split", choices=choices, default=DEFAULT_SPLIT,
                        help=help or f"the split read (default {DEFAULT_SPLIT})")


def add_zoo_shots(parser: argparse.ArgumentParser, zoo: str = ZOO_VERSION,
                  also: tuple[str, ...] = ()) -> None:
    """`--split` (validation or test), `--zoo` (the round, default `zoo`, or one of `also`),
    `--shots` (a comma list of shot names, default every one) and `--data`: which zoo shots a
    run reads."""
    add_split(parser, choices=ZOO_SPLITS)
    parser.add_argument("--zoo", default=zoo, choices=(*ZOO_ROUNDS, *also),
                        help=f"the round (default {zoo})")
    parser.add_argument("--shots", type=lambda text: tuple(text.split(",")) if text else (),
                        default=(), help="comma list of shot names (default: every one)")
    add_data(parser)


def spp_levels(text: str) -> tuple[int, ...]:
    """`"1,4,16"` -> (1, 4, 16): the samples per pixel a run measures, in the order given."""
    return tuple(int(s) for s in text.split(","))


def add_sequences(parser: argparse.ArgumentParser, spp: str) -> None:
    """`--data`, `--renderer`, `--split` and `--spp`: which rendered sequences a run reads, at
    which sample counts (`spp`: the script's default comma list; `args.spp` is a tuple of ints)."""
    add_data(parser)
    add_renderer(parser)
    add_split(parser)
    # argparse runs `type` over a string default too, so args.spp is always parsed
    parser.add_argument("--spp", type=spp_levels, default=spp,
                        help=f"comma list of samples per pixel (default {spp})")


def add_json(parser: argparse.ArgumentParser,
             help: str = "also write the rows here (JSON)") -> None:
    """`--json PATH`: the printed results, also as JSON."""
    parser.add_argument("--json", type=Path, default=None, help=help)
