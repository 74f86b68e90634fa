"""The Cycles training corpus: shots assembled at random (seeded) from the zoo's kinds of parts,
for training the learned tiers on content the g2 generator does not make. Pure numpy, no bpy:
`corpus_shots(split)` lists the shots, `describe(shot, attempt)` draws a shot's scene as a
JSON-able description (stored in its manifest); scenes/corpus_scene.py builds it in Blender
from zoo_parts' building blocks and scenes/corpus_render.py renders it in the zoo's layout.

What a scene is drawn from: a stage (an interior with windows, an exterior street or yard with
facades far behind, a dark studio, a still life on a table); surfaces over Blender's procedural
textures at fine scales (brick, woven fabric, checker, noise grain, wood rings) and the zoo's
photos (zoo_assets); an environment (Blender's bundled HDRIs or the Nishita sky with a sun
lamp, aimed through a window indoors); foliage; thin geometry before a distant background
(fences, railings, cables, bars, bare trees); glossy metals, glass balls under a small bulb
(caustics), LEDs; printed text and photo posters; objects that turn or roll. Camera work:
locked-off, dolly, truck, pan, hand-held shake, orbit; motion blur on ~25% of the shots, depth
of field on ~20%, a cut on ~10%; the exposure follows the g2 rule (scenes/preview.py).

Held out: no zoo set is built (its builders are not called; only zoo_parts' blocks are), no
zoo shot's (set, camera, seed) appears, the seeds are disjoint from the zoo's and the g2 splits',
and nothing is named after, or taken from, the scenes held out for evaluation (HELD_OUT_NAMES,
Bitterli's collection).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from .corpus_parts import (
    MOVING_PROPS,
    PROPS,
    STAGE_BUILDERS,
    THIN,
    THIN_P,
    draw_prop,
    draw_thin,
    near_foliage,
    pick,
    posters,
    rounded,
    stage_spot,
)
from .zoo_shots import Shot

CORPUS_VERSION = "corpus1"  # bump when a seed's description changes (a new folder)
CORPUS_FOLDER = "corpus-cycles"
SPLIT_BASE = {"train": 9_000_000, "validation": 9_500_000}  # seeds: disjoint from g2 and zoo
SPLIT_COUNT = {"train": 120, "validation": 12}
FRAMES = 8
SIZE = (160, 160)
SPP_LEVELS = (1, 4, 16, 64)
# both adaptive halves together (docs/data.md "Training corpus": the budget it was chosen from)
REFERENCE_SPP = 96
REFERENCE_MIN_SPP = 64  # both halves together
STAGES = ("interior", "exterior", "studio", "stilllife")
STAGE_P = (0.32, 0.34, 0.14, 0.20)
CAMERAS = ("locked", "dolly", "truck", "pan", "shake", "orbit")
CAMERA_P = (0.12, 0.18, 0.16, 0.18, 0.14, 0.22)
MOTION_BLUR_P, DOF_P, CUT_P, ZERO_FIRST_P = 0.25, 0.20, 0.10, 0.10
HELD_OUT_NAMES = ("classroom", "dining", "living room", "living-room", "livingroom", "sponza",
                  "staircase", "veach", "bitterli")


@dataclass(frozen=True)
class CorpusShot:
    """What a shot's seed fixes whatever the attempt: its stage and camera work (so its folder
    keeps its name when a blocked or black preview redraws the scene)."""

    name: str
    split: str
    seed: int
    stage: str
    camera: str
    speed: float  # dolly/truck m a frame, pan px a frame, orbit degrees a frame, shake px std
    motion_blur: bool
    dof: bool
    fstop: float
    zero_first_motion: bool
    cut_at: int | None
    frames: int = FRAMES
    size: tuple[int, int] = SIZE
    spp_levels: tuple[int, ...] = SPP_LEVELS
    reference_spp: int = REFERENCE_SPP

    @property
    def locked_off(self) -> bool:
        return self.camera == "locked"

    def camera_shot(self) -> Shot:
        """The zoo's Shot of this camera work, for zoo_scene.add_camera (the zoo's camera code
        keys the poses); its set is not a zoo set."""
        return Shot(self.name, self.split, f"corpus-{self.stage}", self.camera, (), self.seed,
                    frames=self.frames, size=self.size, speed=self.speed,
                    motion_blur=self.motion_blur, dof=self.dof,
                    zero_first_motion=self.zero_first_motion, cut_at=self.cut_at,
                    zoo=CORPUS_VERSION, spp_levels=self.spp_levels,
                    reference_spp=self.reference_spp)

    def record(self) -> dict:
        d = asdict(self)
        d["size"], d["spp_levels"] = list(self.size), list(self.spp_levels)
        return d



def draw_shot(split: str, index: int) -> CorpusShot:
    if split not in SPLIT_BASE:
        raise ValueError(f"corpus split {split!r}: one of {sorted(SPLIT_BASE)}")
    seed = SPLIT_BASE[split] + index
    rng = np.random.default_rng([seed, 3])
    stage = pick(rng, STAGES, STAGE_P)
    camera = pick(rng, CAMERAS, CAMERA_P)
    scale = 0.25 if stage == "stilllife" else 1.0
    sign = 1.0 if rng.random() < 0.5 else -1.0
    speed = {"locked": 0.0, "dolly": sign * scale * rng.uniform(0.02, 0.1),
             "truck": sign * scale * rng.uniform(0.02, 0.1), "pan": sign * rng.uniform(1.0, 14.0),
             "shake": rng.uniform(0.15, 1.2), "orbit": sign * rng.uniform(0.3, 2.5)}[camera]
    if camera == "dolly":
        speed = abs(speed)  # forward: a dolly backwards could leave the set behind it
    moving = camera != "locked"  # a locked-off shot has one reference: nothing may move
    blur, dof, cut, zero = (rng.random() < p for p in (MOTION_BLUR_P, DOF_P, CUT_P, ZERO_FIRST_P))
    fstop = float(rng.uniform(1.4, 4.0))
    cut_at = int(rng.integers(3, FRAMES - 1)) if cut and moving else None
    return CorpusShot(f"{seed}-{stage}-{camera}", split, seed, stage, camera, rounded(speed),
                      bool(blur and moving), bool(dof), rounded(fstop) if dof else 0.0,
                      bool(zero and moving), cut_at)


def corpus_shots(split: str | None = None) -> list[CorpusShot]:
    """Every shot of a split (None: both), in seed order."""
    splits = [split] if split is not None else list(SPLIT_BASE)
    return [draw_shot(s, i) for s in splits for i in range(SPLIT_COUNT[s])]


def corpus_dir(data: Path | str, split: str) -> Path:
    """<data>/corpus-cycles/<split>: the shots' folders, read by model/data.py as Cycles
    sequences (their manifests say renderer "cycles")."""
    return Path(data).expanduser() / CORPUS_FOLDER / split


def describe(shot: CorpusShot, attempt: int = 0) -> dict:
    """The shot's scene (JSON-able): stage geometry, lights, environment, props and camera
    anchors, drawn from (seed, attempt); `attempt` > 0 after a blocked or black preview."""
    rng = np.random.default_rng([shot.seed, attempt, 17])
    st = STAGE_BUILDERS[shot.stage](rng)
    eye, target = st["anchors"][0]["eye"], st["anchors"][0]["target"]
    moving = not shot.locked_off
    kinds = [k for k in PROPS[shot.stage] if moving or k not in MOVING_PROPS]
    props = [draw_prop(rng, pick(rng, kinds), stage_spot(rng, st, eye, target), st["scale"], moving)
             for _ in range(int(rng.integers(*st["props"])))]
    if shot.stage == "studio":  # a glass ball under the bulb and a chrome one: caustics
        bx, by, _ = st["glass_under_bulb"]
        props += [{"kind": "ball", "center": rounded((bx, by, 0.25)), "radius": 0.25,
                   "material": {"kind": "glass", "roughness": 0.0}},
                  {"kind": "ball", "center": rounded((bx - 0.8, by - 0.3, 0.15)), "radius": 0.15,
                   "material": {"kind": "metal", "rgb": [0.92] * 3, "roughness": 0.03}}]
    if THIN[shot.stage] and rng.random() < THIN_P[shot.stage]:
        props.append(draw_thin(rng, pick(rng, THIN[shot.stage]), st, eye, target))
    if shot.stage == "interior":
        props += posters(rng, st, st["shell"][0])
    if shot.stage in ("interior", "exterior") and rng.random() < 0.15:
        props.append(near_foliage(rng, eye, target))
    anchors = st["anchors"][: 2 if shot.cut_at is not None else 1]
    desc = {"version": CORPUS_VERSION, "stage": shot.stage, "attempt": attempt,
            "environment": st["environment"], "shell": st["shell"], "lights": st["lights"],
            "props": props, "anchors": anchors}
    desc["tags"] = tags(shot, desc)
    return desc


def _materials_of(desc: dict) -> list[dict]:
    out = []
    for part in (*desc["shell"], *desc["props"]):
        out += [v for k, v in part.items() if k in ("material", "wall", "floor", "ceiling",
                                                     "plinth_material") and isinstance(v, dict)]
    return out


def tags(shot: CorpusShot, desc: dict) -> list[str]:
    """What the shot covers, for the manifest and the corpus's coverage counts."""
    kinds = {p["kind"] for p in desc["props"]}
    mats = {m["kind"] for m in _materials_of(desc)}
    lights = {light["kind"] for light in desc["lights"]}
    glossy = mats & {"metal", "glass"} or any(
        m["kind"] == "plain" and m["roughness"] < 0.25 for m in _materials_of(desc))
    out = [shot.stage, shot.camera, desc["environment"]["kind"]]
    out += ["foliage"] * bool(kinds & {"foliage"})
    out += ["thin geometry"] * bool(kinds & {"fence", "railing", "bars", "cables", "trees", "tree",
                                             "wire", "comb", "pencils", "shelf"})
    out += ["distant background"] * bool(shot.stage == "exterior" or any(
        s.get("windows") for s in desc["shell"]))
    out += ["fine texture"] * bool(mats & {"fabric", "brick", "checker", "noise", "wood", "photo"})
    out += ["glossy"] * bool(glossy)
    out += ["caustics"] * bool("glass" in mats and "point" in lights)
    out += ["text"] * bool(kinds & {"sign", "page", "poster"})
    out += ["object motion"] * bool("roller" in kinds or any(p.get("spin") for p in desc["props"]))
    out += ["defocused foreground"] * any(p.get("near") for p in desc["props"])
    out += ["LEDs"] * bool("leds" in kinds)
    for flag, name in ((shot.motion_blur, "motion blur"), (shot.dof, "depth of field"),
                       (shot.cut_at is not None, "camera cut"),
                       (shot.zero_first_motion, "first frame zero motion")):
        out += [name] * bool(flag)
    return out
