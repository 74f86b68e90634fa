"""Where quietframe's data and training runs live, and the defaults its command-line tools share
(quietframe-render, -train, -eval and the benchmarks): one definition each.

Data lands in <data>/<generator version>/<split>/<sequence seed>/. Sequence seeds come from
disjoint ranges per split, so train, validation and test (and their locked-off `*-static`
variants) never share a scene.
"""

from __future__ import annotations

from pathlib import Path

from quietframe.scenes.generator import GENERATOR_VERSION

CACHE_DIR = Path("~/.cache/quietframe")  # large data, out of git (expanded where used)
DATA_DIR = CACHE_DIR / "data"
RUNS_DIR = CACHE_DIR / "runs"
OIDN_CACHE_DIR = CACHE_DIR / "oidn"
DEFAULT_THREADS = 2  # this project's machines have 2 cores

# The locked-off shots (static camera and scene, animated noise; they measure flicker) are splits
# of their own, `*-static`, on both renderers; a split of that name renders and scores them
# locked off.
SPLIT_BASE = {
    "train": 1_000_000,
    "validation": 2_000_000,
    "test": 3_000_000,
    "validation-static": 2_500_000,
    "test-static": 3_500_000,
}
# Cycles splits draw from their own ranges, disjoint from Mitsuba's and from each other.
CYCLES_SPLIT_BASE = {
    "train": 5_000_000,
    "validation": 6_000_000,
    "test": 7_000_000,
    "validation-static": 6_500_000,
    "test-static": 7_500_000,
}
RENDERERS = ("mitsuba", "cycles")


def is_locked_off(split: str) -> bool:
    """A locked-off split (static camera and scene): rendered with one reference, scored for
    flicker."""
    return split.endswith("-static")


def split_seeds(split: str, count: int, start: int = 0, renderer: str = "mitsuba") -> list[int]:
    """Scene seeds of a split: disjoint ranges, so no scene is in two splits."""
    base = CYCLES_SPLIT_BASE if renderer == "cycles" else SPLIT_BASE
    return [base[split] + i for i in range(start, start + count)]


def split_dir(data: Path | str, split: str, renderer: str = "mitsuba") -> Path:
    """The folder of a split rendered by today's generator (Cycles: `<version>-cycles`)."""
    version = GENERATOR_VERSION + ("-cycles" if renderer == "cycles" else "")
    return Path(data).expanduser() / version / split
