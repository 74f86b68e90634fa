"""Seeded procedural scenes built like real interiors: a JSON-able description of a sequence.

Generator g2 (replaces g1's boxes of floating primitives). From the sequence seed:
`architecture.plan` lays out a room (60% with a corridor or second room through a doorway) with
windows, reveals, frames and blinds, or an open courtyard with a colonnade; a lighting mode
(sun, overcast, evening, night) sets the sky, the sun (aimed through a window so it lands on
the floor) and which lamps are on (`environment.py`); `furnishing.furnish` places furniture
assembled from parts (`furniture.py`) against walls and in groups, pictures on walls, pendants
under the ceiling, props on tops, tiny bright LEDs; materials come by role
(`materials.role_material`). Cameras move like shots (`camera.animate`) inside the spaces and
outside furniture; half of the interiors have a moving object (a rolling ball or a sliding
chair, `furnishing.mover`) whose per-frame transform is in the description. The renderers build
their scenes from it (`scene_parts.py`, `mitsuba_scene.py`, `cycles_scene.py`).
`generate(seed, frames)` is pure numpy and deterministic; bump GENERATOR_VERSION whenever its
output for a seed changes (the data cache is keyed by it).
"""
from __future__ import annotations

import numpy as np

from . import architecture, environment, furnishing, materials, textures
from .camera import animate

GENERATOR_VERSION = "g2"
LIGHTING = ("sun", "overcast", "evening", "night")


# ---------------------------------------------------------------------------------------------
# Materials


WALL_ROLES = ("paint", "paint", "wallpaper", "wall_tiles", "brick")
FLOOR_ROLES = ("floor_wood", "floor_wood", "floor_tiles", "carpet", "stone")
PIECE_ROLES = ("wood", "fabric", "metal", "glass", "ceramic", "paper", "dark", "leaf",
               "carpet", "stone")


def _materials(rng: np.random.Generator, layout: dict) -> tuple[list[dict], dict, dict]:
    """Material list, surface key -> index (architecture) and role -> indices (furniture).
    Interiors reuse materials, and every distinct BSDF is one more callee in Mitsuba's JIT
    kernel, so the palette stays at 1-2 materials per role."""
    mats: list[dict] = []

    def add(m: dict) -> int:
        mats.append(m)
        return len(mats) - 1

    palette = {r: [add(materials.role_material(rng, r))] for r in PIECE_ROLES}
    for r in ("fabric", "ceramic", "paper", "wood"):
        if rng.random() < 0.5:
            palette[r].append(add(materials.role_material(rng, r)))
    surf: dict[str, int] = {}
    yard = layout["kind"] == "courtyard"
    for i, _ in enumerate(layout["spaces"]):
        wall_role = str(rng.choice(("paint", "brick", "stone") if yard else WALL_ROLES))
        surf[f"wall{i}"] = add(materials.role_material(rng, wall_role))
        surf[f"floor{i}"] = add(
            materials.role_material(rng, "stone" if yard else str(rng.choice(FLOOR_ROLES)))
        )
        surf[f"ceiling{i}"] = add(materials.role_material(rng, "ceiling"))
    surf["reveal"] = surf["wall0"]
    surf["frame"] = add(materials.role_material(rng, str(rng.choice(["paint", "wood", "metal"]))))
    surf["blind"] = add(materials.role_material(rng, str(rng.choice(["paint", "metal", "wood"]))))
    surf["stone"] = palette["stone"][0]
    surf["dark"] = add({"kind": "plastic", "color": [0.02, 0.025, 0.03]})  # facade glass
    surf["metal"] = palette["metal"][0]
    surf["ground"] = add(
        {"kind": "diffuse", "color": textures.random_color(rng, 0.1, 0.3).tolist()}
    )
    surf["bulb_off"] = add({"kind": "diffuse", "color": [0.8, 0.8, 0.8]})
    return mats, surf, palette


# ---------------------------------------------------------------------------------------------
# Scene


def generate(seed: int, n_frames: int, attempt: int = 0) -> dict:
    """The full, JSON-able description of sequence `seed`; `attempt` > 0 draws a replacement
    when the renderer rejects a scene (blocked or black)."""
    rng = np.random.default_rng([seed, attempt, 0x5CE7E2])
    courtyard = bool(rng.random() < 0.2)
    layout = architecture.plan(rng, courtyard)
    if courtyard:
        mode = str(rng.choice(["sun", "overcast"], p=[0.8, 0.2]))
    else:
        mode = str(rng.choice(LIGHTING, p=[0.45, 0.15, 0.25, 0.15]))
    architecture.add_blinds(rng, layout, 0.45 if mode == "sun" else 0.15)
    mats, surf, palette = _materials(rng, layout)
    env = environment.draw(rng, layout, mode)
    f = furnishing.furnish(rng, layout, palette, mode)
    desc = {
        "generator": GENERATOR_VERSION,
        "seed": seed,
        "attempt": attempt,
        "layout": layout,
        "lighting": mode,
        "environment": env,
        "materials": mats,
        "surfaces": surf,
        "pieces": f.pieces,
        "blockers": f.blockers,
    }
    spaces = layout["spaces"]
    yard = layout["kind"] == "courtyard"

    patch = [p for p in environment.sun_patches(desc) if p is not None]
    # Shots start in the annex only where light reaches it directly (a window, lamps on):
    # a windowless corridor in daylight is lit through the door alone, near black.
    lit = [0] + [
        i
        for i in range(1, len(spaces))
        if mode in ("evening", "night")
        or any(o["kind"] == "window" and o.get("space") == i for o in layout["openings"])
    ]

    def start(g: np.random.Generator) -> np.ndarray:
        """Eye height; 60% of shots stand near a wall and look across the space."""
        si = 0 if len(lit) == 1 or g.random() < 0.8 else int(g.choice(lit[1:]))
        x0, z0, x1, z1 = spaces[si]["rect"]
        p = np.array([g.uniform(x0 + 0.4, x1 - 0.4), 0, g.uniform(z0 + 0.4, z1 - 0.4)])
        if g.random() < 0.6:
            k = int(g.integers(4))
            off = g.uniform(0.45, 1.2)
            p[[0, 2][k % 2]] = [x0, z0, x1, z1][k] + (off if k < 2 else -off)
        p[1] = g.uniform(1.2, 1.8) if yard else g.uniform(1.0, 1.7)
        return p

    def target(g: np.random.Generator, s: np.ndarray) -> np.ndarray:
        """The sun patch (35%, sunny rooms), a piece of furniture in the same space (65%) or
        any point of it."""
        si = max(architecture.space_of(layout, s), 0)
        x0, z0, x1, z1 = spaces[si]["rect"]
        near = [
            np.asarray(p["transform"])[:3, 3]
            for p in f.pieces
            if p["kind"] not in ("pendant", "led", "rug")
            and architecture.space_of(layout, np.asarray(p["transform"])[:3, 3]) == si
        ]
        if patch and si == 0 and g.random() < 0.35:  # the sun patch: sharp-edged sun patterns
            return patch[int(g.integers(len(patch)))] + [g.normal(0, 0.3), 0, g.normal(0, 0.3)]
        if near and g.random() < 0.65:
            c = near[int(g.integers(len(near)))]
            return c + [g.normal(0, 0.2), g.uniform(0.2, 0.8), g.normal(0, 0.2)]
        y = g.uniform(0.5, 4.0) if yard else g.uniform(0.3, 1.6)
        return np.array([g.uniform(x0 + 0.2, x1 - 0.2), y, g.uniform(z0 + 0.2, z1 - 0.2)])

    shot = animate(
        rng,
        inside=lambda p: furnishing.camera_clear(desc, p),
        sample_point=start,
        sample_target=target,
        n_frames=n_frames,
    )
    cams = shot["frames"]
    movers = []
    if rng.random() < 0.5:
        m = furnishing.mover(rng, desc, f, cams)
        if m is not None:
            movers.append(m)
    desc.update(
        {
            "movers": movers,
            "cameras": [c.as_dict() for c in cams],
            "shots": shot["shots"],
            "cuts": shot["cuts"],
        }
    )
    return desc


# ---------------------------------------------------------------------------------------------
# Locked-off shots

# A locked-off sequence renders one reference, for frame 0, and every frame uses it (the true
# image is constant): it gets this many times the reference spp. Both back ends read it.
LOCKED_OFF_REFERENCE_SCALE = 4


def locked_off(desc: dict) -> dict:
    """The description with every frame given the first frame's camera and object poses, no
    cuts and one shot: the true image is constant, so frame-to-frame change in a denoised
    output is flicker (the stability measure). `desc` itself is left as it was."""
    n = len(desc["cameras"])
    out = dict(desc)
    out["cameras"] = [desc["cameras"][0]] * n
    out["movers"] = [{**m, "frames": [m["frames"][0]] * n} for m in desc["movers"]]
    out["cuts"], out["shots"] = [], desc["shots"][:1]
    return out


def summary(desc: dict) -> dict:
    """Short, human-readable digest of a description for the manifest."""
    layout = desc["layout"]
    kinds: dict[str, int] = {}
    for p in desc["pieces"]:
        kinds[p["kind"]] = kinds.get(p["kind"], 0) + 1
    lamps = [p for p in desc["pieces"] if "light" in p]
    return {
        "layout": layout["kind"],
        "spaces": [s["kind"] for s in layout["spaces"]],
        "windows": sum(o["kind"] == "window" for o in layout["openings"]),
        "blinds": sum(bool(o.get("blind")) for o in layout["openings"]),
        "doors": sum(o["kind"] == "door" for o in layout["openings"]),
        "lighting": desc["lighting"],
        "sun": "sun" in desc["environment"],
        "lights_on": sum(p["light"]["on"] for p in lamps),
        "pieces": kinds,
        "movers": [m["kind"] for m in desc["movers"]],
        "materials": len(desc["materials"]),
        "shots": desc["shots"],
    }
