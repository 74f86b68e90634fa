"""One way to time things, shared by every benchmark, so all reported figures are comparable.

Rule: `warmup` untimed calls (first-call allocations, OIDN/ORT plan building, caches), then
`repeats` timed calls with `time.perf_counter_ns`; the figure is the median wall time in
milliseconds (robust to the odd scheduler hiccup, unlike the mean). The median process CPU time
per call (all threads) comes with it: on a shared machine, wall time far above CPU time / threads
means the run waited for a core, not that the code got slower.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass


@dataclass(frozen=True)
class Timing:
    median_ms: float
    min_ms: float
    max_ms: float
    samples_ms: tuple[float, ...]
    cpu_ms: float = float("nan")  # median process CPU time per call, all threads

    def __str__(self) -> str:
        return (
            f"{self.median_ms:.1f} ms (median of {len(self.samples_ms)}, "
            f"min {self.min_ms:.1f}, max {self.max_ms:.1f}; CPU {self.cpu_ms:.1f} ms)"
        )


def time_ms(fn: Callable[[], object], *, warmup: int = 2, repeats: int = 10) -> Timing:
    """Time `fn()` (no arguments: bind inputs with a lambda or functools.partial)."""
    if repeats < 1 or warmup < 0:
        raise ValueError(f"time_ms: need repeats >= 1 and warmup >= 0, got {repeats}, {warmup}")
    for _ in range(warmup):
        fn()
    samples, cpu = [], []
    for _ in range(repeats):
        cpu_start, start = time.process_time_ns(), time.perf_counter_ns()
        fn()
        samples.append((time.perf_counter_ns() - start) / 1e6)
        cpu.append((time.process_time_ns() - cpu_start) / 1e6)
    return Timing(
        statistics.median(samples), min(samples), max(samples), tuple(samples),
        statistics.median(cpu),
    )


def timing_table(title: str, first: str, columns: Sequence[str],
                 rows: Mapping[str, Mapping[str, Timing]]) -> str:
    """Markdown: `title`, then a row per label with a cell per column: median wall ms (minimum;
    CPU), "–" where that column was not timed."""
    lines = [title, "", f"| {first} | " + " | ".join(columns) + " |",
             "|---|" + "---:|" * len(columns)]
    for label, timings in rows.items():
        cells = [f"{t.median_ms:.1f} ({t.min_ms:.1f}; {t.cpu_ms:.1f})" if (t := timings.get(c))
                 else "–" for c in columns]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def interleaved_rounds(runs: Mapping[str, Callable[[], object]], rounds: int, repeats: int
                       ) -> tuple[dict[str, list[float]], dict[str, list[float]]]:
    """Each of `runs` timed once a round (time_ms, one warm-up), `rounds` times, interleaved
    so a background load falls on all of them alike; prints each round's medians. Returns
    per run the median wall ms and CPU ms of every round."""
    wall: dict[str, list[float]] = {k: [] for k in runs}
    cpu: dict[str, list[float]] = {k: [] for k in runs}
    for r in range(rounds):
        for name, run in runs.items():
            timing = time_ms(run, warmup=1, repeats=repeats)
            wall[name].append(timing.median_ms)
            cpu[name].append(timing.cpu_ms)
        print(f"round {r + 1}: " + ", ".join(f"{k} {v[-1]:.0f} ms" for k, v in wall.items()),
              flush=True)
    return wall, cpu
