"""Camera shots of a scene's frame range, without bpy: which camera renders each frame (Blender's
rule for timeline markers bound to cameras) and the runs of frames one camera renders. Each shot
is denoised in a session of its own, so no history carries across a camera switch."""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass


@dataclass(frozen=True)
class CameraMarker:
    """A timeline marker bound to a camera (marker.camera), in the scene's marker order."""

    frame: int
    camera: str


@dataclass(frozen=True)
class Shot:
    camera: str
    frames: tuple[int, ...]

    def describe(self) -> str:
        first, last = self.frames[0], self.frames[-1]
        span = f"frame {first}" if first == last else f"frames {first}-{last}"
        return f"{span} ({self.camera})"


def camera_at(frame: int, markers: Sequence[CameraMarker], default: str) -> str:
    """The camera Blender renders `frame` with: that of the latest camera marker at or before
    the frame (the first in marker order among markers on one frame), before every marker the
    earliest marker's; `default` (the scene's camera) where no marker names a camera. The
    caller leaves out markers whose camera is hidden from rendering, as Blender does."""
    if not markers:
        return default
    at_or_before = [m for m in markers if m.frame <= frame]
    if at_or_before:
        latest = max(m.frame for m in at_or_before)
        return next(m.camera for m in at_or_before if m.frame == latest)
    earliest = min(m.frame for m in markers)
    return next(m.camera for m in markers if m.frame == earliest)


def frame_range(start: int, end: int, step: int = 1) -> list[int]:
    """The frames an animation render writes: start to end inclusive, every `step`."""
    if step < 1:
        raise ValueError(f"frame step must be at least 1, got {step}")
    return list(range(start, end + 1, step))


def plan_shots(
    frames: Iterable[int], markers: Sequence[CameraMarker], default: str
) -> list[Shot]:
    """Consecutive frames rendered by one camera form a shot; a switch to another camera starts
    the next one. Two markers in a row naming the same camera are one shot (the camera did not
    change: a hard cut within one camera's move is still found by the server, which starts
    that frame's history afresh when its aux changed almost everywhere)."""
    shots: list[Shot] = []
    run: list[int] = []
    camera = None
    for frame in sorted(frames):
        this = camera_at(frame, markers, default)
        if run and this != camera:
            shots.append(Shot(camera, tuple(run)))
            run = []
        camera = this
        run.append(frame)
    if run:
        shots.append(Shot(camera, tuple(run)))
    return shots
