"""The validation zoo: Cycles shots whose content the g2 generator (scenes/generator.py) does not
make, so `auto`'s tables and the history tiers are checked on shots unlike the ones they were
built from. This module is the shot list only (no bpy): the evaluation reads it beside the
renders; scenes/zoo_scene.py builds the shots in Blender and scenes/zoo_render.py renders them.

Every shot is written here, independently of the generator: Blender primitives (Suzanne, UV
spheres, boxes written as vertex lists), Blender's procedural textures at fine scales (brick,
wave, checker, noise), photographs that scikit-image's wheel ships (brick, grass, gravel, a
printed page, text, photos hung as posters; scenes/zoo_assets.py fetches them from PyPI),
Blender's bundled HDR environments (Poly Haven studio lights: courtyard, forest, city, ...)
and its physical Nishita sky with a sun lamp. The shots cover the camera work and content a
farm sends that the generator does not: a locked-off camera, a slow dolly, a fast pan, hand-held
sub-pixel shake, fine textures, a daylight exterior, motion blur (Cycles then writes an all-zero
`Vector` while the camera moves), depth of field, a first frame without motion and a cut.

The split is by shot: validation shots give `auto` its tables, test shots are reported only.
Each split has one shot of every camera kind, on different sets, lights and textures.

Round 2 (`zoo2`) holds the shots a reprojected history finds hard, longer (24 frames) and
larger (320x180): thin geometry in front of a distant background under a camera truck
(parallax), rotating wireframe objects, a defocused foreground crossing the frame, a wide range
of screen motion in one frame, caustic fireflies, and a locked-off shot of that content for
the still/moving verdict at low spp. Its sets are in scenes/zoo_sets2.py.

Round 3 (`zoo3`) holds motion-blur twins: a shot rendered with motion blur (Cycles then writes an
all-zero `Vector`) and the same shot without, whose vectors score motion estimated from the aux.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path

ZOO_VERSION = "zoo1"  # round 1; bump a round when a shot's content changes (new folder)
ZOO_ROUNDS = ("zoo1", "zoo2", "zoo3")
ZOO_SPLITS = ("validation", "test")
ROUND1_SPP = (1, 2, 4, 8, 16, 64)
ROUND2_SPP = (1, 4, 16, 64)


@dataclass(frozen=True)
class Shot:
    name: str
    split: str  # validation (auto's tables) or test (reported only)
    set: str  # a builder in zoo_scene.SETS
    camera: str  # locked | dolly | pan | shake | orbit
    tags: tuple[str, ...]  # what the shot covers (camera work, content), for the report
    seed: int
    frames: int = 8
    size: tuple[int, int] = (192, 192)
    speed: float = 0.0  # dolly m/frame, pan px/frame, orbit degrees/frame, shake px (std)
    motion_blur: bool = False
    dof: bool = False
    zero_first_motion: bool = False  # no motion keyed before frame 1: its Vector is all zero
    cut_at: int | None = None  # frame index (0-based) where a second camera takes over
    variant: dict = field(default_factory=dict)  # set options (environment, textures)
    zoo: str = ZOO_VERSION  # the round: renders land in <data>/<zoo>-cycles/<split>/
    spp_levels: tuple[int, ...] = ROUND1_SPP
    reference_spp: int = 512  # both adaptive halves together

    @property
    def locked_off(self) -> bool:
        return self.camera == "locked"

    def record(self) -> dict:
        d = asdict(self)
        d["tags"], d["size"] = list(self.tags), list(self.size)
        d["spp_levels"] = list(self.spp_levels)
        return d


def _round2(name: str, split: str, set_: str, camera: str, tags: tuple[str, ...], seed: int,
            **kw) -> Shot:
    """A round-2 shot: 24 frames at 320x180, inputs at 1/4/16/64 spp, references of 256 spp
    (both halves; 4x on a locked-off shot): 2.6x round 1's pixels per shot, so half the
    reference samples keep a split near 4 CPU-hours (docs/zoo.md states the ceilings)."""
    kw.setdefault("size", (320, 180))
    return Shot(name, split, set_, camera, tags, seed, frames=24, zoo="zoo2",
                spp_levels=ROUND2_SPP, reference_spp=256, **kw)


def _blur_twins(name: str, split: str, set_: str, camera: str, tags: tuple[str, ...],
                seed: int, **kw) -> tuple[Shot, Shot]:
    """A round-3 pair: a shot with motion blur (Cycles then writes no vectors) and its twin
    without, the same scene and camera (the same seed), whose vectors are the ground truth for
    motion estimated from the aux. 12 frames at 256x144, inputs at 1/4/16 spp, references of
    256 spp: ~0.2 CPU-hours a shot."""
    kw = {"size": (256, 144), "frames": 12, "zoo": "zoo3", "spp_levels": (1, 4, 16),
          "reference_spp": 256, **kw}
    return (Shot(f"{name}-blur", split, set_, camera, (*tags, "motion blur"), seed,
                 motion_blur=True, **kw),
            Shot(name, split, set_, camera, (*tags, "motion-blur twin"), seed, **kw))


SHOTS: tuple[Shot, ...] = (
    # --- validation: auto's tables ------------------------------------------------------------
    Shot("study-locked", "validation", "study", "locked",
         ("locked-off", "printed text", "fabric"), seed=8_000_001),
    Shot("street-dolly", "validation", "street", "dolly",
         ("slow dolly", "daylight exterior", "fine brick", "foliage", "first frame zero motion"),
         seed=8_000_002, size=(256, 144), speed=0.06, zero_first_motion=True),
    Shot("gallery-pan", "validation", "gallery", "pan",
         ("fast pan", "fine brick", "printed text"), seed=8_000_003, size=(256, 144),
         speed=10.0),
    Shot("tabletop-shake", "validation", "tabletop", "shake",
         ("hand-held shake", "depth of field", "printed text", "fabric"), seed=8_000_004,
         speed=0.35, dof=True),
    Shot("garden-blur", "validation", "garden", "orbit",
         ("motion blur", "foliage"), seed=8_000_005, speed=2.0, motion_blur=True),
    Shot("courtyard-cut", "validation", "courtyard", "dolly",
         ("camera cut", "daylight exterior", "fine brick"), seed=8_000_006, size=(256, 144),
         speed=0.08, cut_at=4),
    # --- test: reported only ------------------------------------------------------------------
    Shot("tabletop-locked", "test", "tabletop", "locked",
         ("locked-off", "fabric", "printed text"), seed=8_100_001,
         variant={"environment": "city"}),
    Shot("courtyard-dolly", "test", "courtyard", "dolly",
         ("slow dolly", "daylight exterior", "fine brick", "first frame zero motion"),
         seed=8_100_002, size=(256, 144), speed=0.05, zero_first_motion=True,
         variant={"sun_elevation": 55.0}),
    Shot("street-pan", "test", "street", "pan",
         ("fast pan", "daylight exterior", "foliage", "fine brick"), seed=8_100_003,
         size=(256, 144), speed=12.0, variant={"sun_elevation": 20.0}),
    Shot("study-shake", "test", "study", "shake",
         ("hand-held shake", "depth of field", "printed text", "fabric"), seed=8_100_004,
         speed=0.3, dof=True, variant={"environment": "sunset"}),
    Shot("gallery-blur", "test", "gallery", "pan",
         ("motion blur", "fine brick"), seed=8_100_005, size=(256, 144), speed=6.0,
         motion_blur=True),
    Shot("garden-cut", "test", "garden", "orbit",
         ("camera cut", "foliage", "depth of field"), seed=8_100_006, speed=1.5, cut_at=5,
         dof=True, variant={"environment": "sunrise"}),
    # --- round 2, validation: shots the history finds hard -------------------------------------
    # truck speeds are metres a frame: 0.07 m moves the fence (3 m) ~6 px, the near post
    # (1.1 m) ~18 px and the far facades (40 m) ~0.5 px a frame at 320 px and 60 degrees
    _round2("fence-truck", "validation", "yard", "truck",
            ("thin geometry", "parallax", "wide motion range", "daylight exterior",
             "bare branches", "cables"), seed=8_200_001, speed=0.07),
    _round2("studio-spin", "validation", "studio", "orbit",
            ("rotating wireframe", "thin geometry", "caustic fireflies", "dark"),
            seed=8_200_002, speed=0.8, variant={"spin": 4.0}),
    _round2("shelf-whip", "validation", "library", "truck",
            ("fast move", "thin geometry", "defocused foreground", "wide motion range",
             "parallax", "depth of field"), seed=8_200_003, speed=0.09, dof=True),
    _round2("studio-locked", "validation", "studio", "locked",
            ("locked-off", "thin geometry", "caustic fireflies", "dark"), seed=8_200_004,
            variant={"spin": 0.0, "environment": "night"}),
    # added after yard-locked (test) showed the plain-aux tiers losing at 1 spp on a locked-off
    # exterior of thin geometry, which no validation shot had: the fence set, locked off
    _round2("fence-locked", "validation", "yard", "locked",
            ("locked-off", "thin geometry", "bare branches", "cables", "daylight exterior"),
            seed=8_200_005, variant={"sun_elevation": 35.0}),
    # --- round 2, test: reported only ----------------------------------------------------------
    _round2("railing-truck-blur", "test", "yard", "truck",
            ("thin geometry", "parallax", "wide motion range", "daylight exterior",
             "bare branches", "cables", "motion blur"), seed=8_300_001, speed=-0.06,
            motion_blur=True, variant={"railing": True, "sun_elevation": 25.0}),
    _round2("wire-dolly", "test", "studio", "dolly",
            ("rotating wireframe", "thin geometry", "caustic fireflies", "dark"),
            seed=8_300_002, speed=0.05, variant={"spin": -5.0, "environment": "studio"}),
    _round2("comb-whip", "test", "library", "truck",
            ("fast move", "thin geometry", "defocused foreground", "wide motion range",
             "parallax", "depth of field"), seed=8_300_003, speed=-0.11, dof=True,
            variant={"combs": True, "environment": "sunset"}),
    _round2("yard-locked", "test", "yard", "locked",
            ("locked-off", "thin geometry", "bare branches", "daylight exterior"),
            seed=8_300_004, variant={"sun_elevation": 8.0}),
    # --- round 3, validation: motion estimated from the aux ------------------------------------
    *_blur_twins("study-dolly", "validation", "study", "dolly", ("slow dolly", "printed text",
                 "fabric"), seed=8_400_001, speed=0.06),
)


def zoo_dir(data: Path | str, split: str, zoo: str = ZOO_VERSION) -> Path:
    """Where a zoo round's split is rendered: <data>/<zoo>-cycles/<split>/<shot>/."""
    return Path(data).expanduser() / f"{zoo}-cycles" / split


def shots(split: str | None = None, zoo: str | None = ZOO_VERSION) -> list[Shot]:
    """A round's shots (`zoo=None`: every round's), of one split or all."""
    return [s for s in SHOTS if (split is None or s.split == split)
            and (zoo is None or s.zoo == zoo)]


def shot(name: str) -> Shot:
    for s in SHOTS:
        if s.name == name:
            return s
    raise KeyError(f"no zoo shot {name!r} (have {', '.join(s.name for s in SHOTS)})")
