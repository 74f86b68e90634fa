"""Which files make a sequence: a folder, a glob, or a farm frame pattern (`shot.####.exr`,
`shot.%04d.exr`), optionally limited to a frame range (`1001-1100`, Blender's `1001..1100`,
`1,5,9-12`).

Frames are numbered by the last number in their file name; that number is the index sent to the
server, so a number missing inside the range is a gap (the server starts a fresh history there).
"""

from __future__ import annotations

import glob
import re
from dataclasses import dataclass
from pathlib import Path

_NUMBER = re.compile(r"(\d+)(?!.*\d)")
_HASHES = re.compile(r"#+")
_PRINTF = re.compile(r"%0?(\d*)d")


class SequenceError(Exception):
    """The input cannot be streamed as one sequence (no frames, mixed sizes, name clashes)."""


def frame_number(path: Path) -> int | None:
    match = _NUMBER.search(path.stem)
    return int(match.group(1)) if match else None


# The most frames one --frames range may span: ~70 minutes at 24 fps, far beyond a shot or a
# farm chunk; a bound keeps a typo from allocating a billion numbers (audit R4-25).
MAX_RANGE_FRAMES = 100_000


def parse_frame_range(text: str) -> tuple[int, ...]:
    """`1001-1100` (or Blender's `1001..1100`), `1001` or a comma list of these, ascending and
    without repeats; ValueError with the accepted forms otherwise. No step: a temporal denoiser
    needs every frame (a skipped number is a gap, where the history starts afresh)."""
    numbers: set[int] = set()
    spans: list[tuple[int, int]] = []
    for part in (p.strip() for p in text.split(",")):
        match = re.fullmatch(r"(\d+)(?:(?:-|\.\.)(\d+))?", part)
        if not match:
            raise ValueError(
                f"frame range {text!r}: expected FIRST-LAST (or FIRST..LAST), FRAME or a comma "
                "list of these, e.g. 1001-1100"
            )
        first = int(match.group(1))
        last = int(match.group(2)) if match.group(2) is not None else first
        if last < first:
            raise ValueError(f"frame range {part!r}: LAST is below FIRST")
        spans.append((first, last))
    # counted before a number is made: `1-1000000000` would not fit in memory
    count = sum(last - first + 1 for first, last in spans)
    if count > MAX_RANGE_FRAMES:
        raise ValueError(f"frame range {text!r} spans {count} frames; at most "
                         f"{MAX_RANGE_FRAMES} a run (split the shot into chunks)")
    for first, last in spans:
        numbers.update(range(first, last + 1))
    return tuple(sorted(numbers))


def is_pattern(source: str) -> bool:
    """A farm frame pattern: `####` (one # per digit) or printf's `%04d`."""
    return bool(_HASHES.search(source) or _PRINTF.search(source))


def _pattern_parts(source: str) -> tuple[str, int, str]:
    """(prefix, digits (0: unpadded), suffix) of the one frame field in a pattern."""
    match = _HASHES.search(source)
    if match:
        return source[: match.start()], len(match.group(0)), source[match.end() :]
    match = _PRINTF.search(source)
    assert match is not None
    return source[: match.start()], int(match.group(1) or 0), source[match.end() :]


def _pattern_files(source: str) -> list[Path]:
    prefix, digits, suffix = _pattern_parts(source)
    field = r"\d{" + str(max(digits, 1)) + ",}"
    wanted = re.compile(re.escape(prefix) + f"({field})" + re.escape(suffix) + "$")
    candidates = glob.glob(glob.escape(prefix) + "*" + glob.escape(suffix))
    return [Path(p) for p in candidates if wanted.match(p) and Path(p).is_file()]


def find_frames(source: str | Path) -> list[Path]:
    """EXR files of a folder, a glob or a frame pattern, sorted by frame number then name."""
    path = Path(source)
    if path.is_dir():
        files = [p for p in path.iterdir() if p.suffix.lower() == ".exr" and p.is_file()]
    elif is_pattern(str(source)):
        files = _pattern_files(str(source))
    else:
        files = [Path(p) for p in glob.glob(str(source)) if Path(p).is_file()]
    if not files:
        raise SequenceError(f"no EXR frames in {source}")
    return sorted(files, key=lambda p: (frame_number(p) or 0, p.name))


@dataclass(frozen=True)
class Selection:
    """The files to write (ascending numbers), the pre-roll files before them (sent to warm the
    history, never written), the frame numbers of the range that have no file, those of the
    pre-roll, every frame of the source (`found`), and the post-roll files after the range
    (sent only for the look-ahead of its last frames, never written) with the post-roll
    numbers that have no file."""

    files: tuple[Path, ...]
    pre_roll: tuple[Path, ...]
    missing: tuple[int, ...]
    pre_roll_missing: tuple[int, ...] = ()
    found: tuple[Path, ...] = ()
    post_roll: tuple[Path, ...] = ()
    post_roll_missing: tuple[int, ...] = ()


def select_frames(
    source: str | Path, frames: tuple[int, ...] | None = None, pre_roll: int = 0,
    post_roll: int = 0,
) -> Selection:
    """The frames of `source` in `frames` (all when None), the `pre_roll` numbers just before
    the first of them (those with a file, and those without: not rendered yet, or before the
    shot), the `post_roll` numbers just after the last (the same), and the numbers in the range
    (or between the first and last file) that are absent. Files without a number are taken in
    sorted order (no range, no pre- or post-roll)."""
    found = find_frames(source)
    numbered = {frame_number(p): p for p in found}
    if None in numbered:
        if frames is not None or pre_roll or post_roll:
            raise SequenceError(f"{source}: file names carry no frame number for a range")
        return Selection(tuple(found), (), (), (), tuple(found))
    _check_clashes(found)
    numbers = sorted(numbered)  # type: ignore[type-var]
    wanted = list(frames) if frames is not None else list(range(numbers[0], numbers[-1] + 1))
    chosen = [numbered[n] for n in wanted if n in numbered]
    if not chosen:
        raise SequenceError(f"no frame of range {wanted[0]}-{wanted[-1]} in {source}")
    first, last = frame_number(chosen[0]), frame_number(chosen[-1])
    assert first is not None and last is not None
    # Only the numbers just before: a frame beyond a gap would warm a history the gap resets.
    # Without a range the run starts at the sequence's first frame: nothing is missing before.
    before = range(max(first - pre_roll, 0), first)
    missing = tuple(n for n in wanted if n not in numbered)
    absent = tuple(n for n in before if n not in numbered) if frames is not None else ()
    # After the range, up to the first absent number: a frame's look-ahead ends at a gap, so
    # frames beyond one would be sent for nothing. Without a range nothing follows the run.
    after = range(last + 1, last + 1 + post_roll) if frames is not None else range(0)
    gap = next((n for n in after if n not in numbered), None)
    sent_after = tuple(numbered[n] for n in after if gap is None or n < gap)
    return Selection(tuple(chosen), tuple(numbered[n] for n in before if n in numbered), missing,
                     absent, tuple(found), sent_after,
                     tuple(n for n in after if n not in numbered))


def _check_clashes(files: list[Path]) -> None:
    numbers = [frame_number(f) for f in files]
    clash = sorted({n for n in numbers if numbers.count(n) > 1})  # type: ignore[type-var]
    if clash:
        raise SequenceError(f"several files have frame number(s) {clash[:5]}")
