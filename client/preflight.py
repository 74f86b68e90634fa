"""Pre-flight of a sequence before the first upload: every frame's header and chunk table (no
pixels), so a size change, a truncated file, a missing pass or a gap is reported at once, for
the whole shot, instead of when its frame is reached.

The server's alias table (which channels are colour, albedo, ...) stays on the server; here
every frame is compared with the first one: the same size, view layers and channel names.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from quietframe.client.exr_check import incomplete
from quietframe.client.protocol import view_layers


@dataclass(frozen=True)
class FrameHeader:
    size: tuple[int, int]
    channels: frozenset[str]
    layers: tuple[str, ...]


@dataclass
class Report:
    frames: int
    size: tuple[int, int] | None = None
    layers: tuple[str, ...] = ()
    channels: int = 0
    errors: list[str] = field(default_factory=list)  # each stops the run
    warnings: list[str] = field(default_factory=list)  # said in the summary

    @property
    def ok(self) -> bool:
        return not self.errors


def read_header(path: Path) -> FrameHeader:
    """ValueError with the reason when the header cannot be read."""
    import OpenEXR

    try:
        parts = OpenEXR.File(str(path), header_only=True).parts
    except Exception as exc:
        raise ValueError(f"not a readable EXR file ({exc})") from exc
    low, high = parts[0].header["dataWindow"]
    names = frozenset(c.name for part in parts for c in part.header["channels"])
    size = (int(high[0] - low[0] + 1), int(high[1] - low[1] + 1))
    return FrameHeader(size, names, view_layers(names))


def check_frames(files: list[Path], missing: tuple[int, ...] = (), limit: int = 10) -> Report:
    """Every file against the first; `missing`: frame numbers of the range without a file
    (a gap: warned). At most `limit` errors are listed, then a count."""
    report = Report(len(files))
    first: FrameHeader | None = None
    problems: list[str] = []
    for path in files:
        try:
            header = read_header(path)
        except ValueError as exc:
            problems.append(f"{path.name}: {exc}")
            continue
        if first is None:
            first = header
        problems += [f"{path.name}: {p}" for p in _differences(first, header)]
        cut_short = incomplete(path)
        if cut_short:
            problems.append(f"{path.name}: {cut_short}")
    if first is not None:
        report.size, report.layers, report.channels = first.size, first.layers, len(first.channels)
    report.errors = problems[:limit]
    if len(problems) > limit:
        report.errors.append(f"... and {len(problems) - limit} more")
    if missing:
        report.warnings.append(f"missing frame(s) {format_numbers(missing)}: the history starts "
                               "afresh after each gap (as at a camera cut)")
    return report


def _differences(first: FrameHeader, header: FrameHeader) -> list[str]:
    found = []
    if header.size != first.size:
        found.append(f"is {header.size[0]}x{header.size[1]}, the first frame "
                     f"{first.size[0]}x{first.size[1]} (denoise sizes as separate sequences)")
    if header.layers != first.layers:
        found.append(f"view layers {list(header.layers)}, the first frame's {list(first.layers)}")
    lacking = sorted(first.channels - header.channels)
    if lacking:
        shown = ", ".join(lacking[:6]) + (" ..." if len(lacking) > 6 else "")
        found.append(f"lacks {len(lacking)} channel(s) the first frame has: {shown}")
    return found


def format_numbers(numbers: tuple[int, ...] | list[int]) -> str:
    """1001-1003, 1007 (runs of consecutive numbers joined)."""
    runs: list[list[int]] = []
    for n in sorted(numbers):
        if runs and n == runs[-1][-1] + 1:
            runs[-1].append(n)
        else:
            runs.append([n])
    return ", ".join(f"{r[0]}-{r[-1]}" if len(r) > 1 else str(r[0]) for r in runs)
