"""The sky and the sun of a generated scene (generator g2).

`draw` picks the environment of a lighting mode: a procedural sky and, in sun or evening light,
a sun aimed through a window of the main room so its patch lands on the floor; `sky_bitmap`
renders the sky for both renderers; `sun_patches` / `sun_enters` say where the sun comes in.
"""

from __future__ import annotations

import numpy as np

from . import architecture, materials, textures
from .architecture import Y_UP


def sky_bitmap(env: dict, width: int = 256) -> np.ndarray:
    """Equirectangular linear-RGB sky (H = W/2) in Mitsuba's envmap parameterisation:
    u = atan2(d.x, -d.z) / 2pi, v = acos(d.y) / pi."""
    rng = np.random.default_rng(env["seed"])
    h = width // 2
    u, v = np.meshgrid((np.arange(width) + 0.5) / width, (np.arange(h) + 0.5) / h)
    theta, phi = v * np.pi, u * 2 * np.pi
    d = np.stack([np.sin(theta) * np.sin(phi), np.cos(theta), -np.sin(theta) * np.cos(phi)], -1)
    el = np.arcsin(np.clip(d[..., 1], -1, 1))
    zenith = np.array([0.12, 0.25, 0.75]) * rng.uniform(0.7, 1.3, 3)
    horizon = np.array([0.75, 0.85, 1.0]) * rng.uniform(0.8, 1.1, 3)
    ground = textures.random_color(rng, 0.1, 0.35)
    t = np.exp(-np.maximum(el, 0) / rng.uniform(0.15, 0.4))[..., None]
    sky = zenith * (1 - t) + horizon * t
    if env["overcast"]:  # CIE overcast sky: zenith three times the horizon
        sky = np.full_like(sky, 0.8) * ((1 + 2 * np.sin(np.maximum(el, 0))) / 3)[..., None]
    if env["clouds"] > 0:
        noise = textures.value_noise(rng, width, octaves=6)[:h]
        cover = np.clip((noise - (1 - env["clouds"])) * 3, 0, 1)[..., None] * (el > 0)[..., None]
        sky = sky * (1 - cover) + 0.9 * cover
    sun_dir = env.get("sun", {}).get("to_sun") or env.get("glow_dir")
    if sun_dir is not None:  # aureole around the sun; the disc itself is a directional light
        c = np.sum(d * np.asarray(sun_dir), -1)
        sky = sky + (2.0 * np.exp((c - 1) / 0.01) + 0.4 * np.exp((c - 1) / 0.15))[..., None]
    fade = np.clip(el / 0.03 + 1, 0, 1)[..., None]  # soft horizon into the ground colour
    sky = sky * fade + ground * 0.5 * (1 - fade)
    return (sky * env["scale"]).astype(np.float32)


def _window_sun(rng: np.random.Generator, layout: dict, low: bool) -> np.ndarray | None:
    """Direction to a sun that shines through a window of the main room onto its floor (or,
    `low`, a low evening sun), or None without windows."""
    wins = [o for o in layout["openings"] if o["kind"] == "window" and o.get("space") == 0]
    if not wins:
        return None
    o = wins[int(rng.integers(len(wins)))]
    ax = np.array([1.0, 0, 0]) if o["axis"] == "x" else np.array([0, 0, 1.0])
    inward = np.array([0, 0, o["inward"]]) if o["axis"] == "x" else np.array([o["inward"], 0, 0])
    x0, z0, x1, z1 = layout["spaces"][0]["rect"]
    depth = (z1 - z0) if o["axis"] == "x" else (x1 - x0)
    centre = (o["v"][0] + o["v"][1]) / 2
    if low:
        elevation = rng.uniform(3, 10)
    else:  # the patch through the window's centre lands on the floor within 85% of the depth
        lo = max(10.0, float(np.degrees(np.arctan2(centre, 0.85 * depth))))
        elevation = rng.uniform(lo, max(lo, 60.0))
    az = np.radians(rng.uniform(-45, 45))
    el = np.radians(elevation)
    to_sun = np.cos(el) * (-np.cos(az) * inward + np.sin(az) * ax) + np.sin(el) * Y_UP
    return to_sun / np.linalg.norm(to_sun)


def draw(rng: np.random.Generator, layout: dict, mode: str) -> dict:
    """The description's `environment` for a lighting mode: the sky (seed, scale, overcast,
    clouds) and, in sun or evening light, a sun aimed through a window (or its glow alone)."""
    scale = {
        "sun": (0.3, 1.5),
        "overcast": (0.5, 2.0),
        "evening": (0.02, 0.12),
        "night": (0.002, 0.01),
    }
    env: dict = {
        "kind": "sky",
        "seed": int(rng.integers(2**31)),
        "scale": float(rng.uniform(*scale[mode])),
        "overcast": mode == "overcast",
        "clouds": float(rng.uniform(0, 0.7)) if rng.random() < 0.5 else 0.0,
    }
    if mode in ("sun", "evening"):
        if layout["kind"] == "courtyard":
            el, az = np.radians(rng.uniform(15, 65)), rng.uniform(0, 2 * np.pi)
            to_sun = np.array([np.cos(el) * np.cos(az), np.sin(el), np.cos(el) * np.sin(az)])
        else:
            to_sun = _window_sun(rng, layout, low=mode == "evening")
        if to_sun is not None and (mode == "sun" or rng.random() < 0.5):
            kelvin = rng.uniform(4500, 6500) if mode == "sun" else rng.uniform(2500, 3500)
            env["sun"] = {
                "to_sun": to_sun.tolist(),
                "irradiance": float(
                    env["scale"] * rng.uniform(15, 40) * (1 if mode == "sun" else 8)
                ),
                "color": materials.blackbody_rgb(float(kelvin)).tolist(),
            }
        elif to_sun is not None:
            env["glow_dir"] = to_sun.tolist()
    return env


def sun_patches(desc: dict) -> list[np.ndarray]:
    """Where the sun comes in: for each window of the main room that a ray from its centre
    towards the sun gets out through (past the reveal), the floor point that ray reaches
    inside the room, or None when it lands on a wall (a low sun)."""
    sun = desc["environment"].get("sun")
    if sun is None or desc["layout"]["kind"] == "courtyard" or sun["to_sun"][1] <= 0:
        return []
    d = np.asarray(sun["to_sun"])
    x0, z0, x1, z1 = desc["layout"]["spaces"][0]["rect"]
    out = []
    for o in desc["layout"]["openings"]:
        if o["kind"] != "window" or o.get("space") != 0:
            continue
        along = d[0] if o["axis"] == "x" else d[2]
        away = -o["inward"] * (d[2] if o["axis"] == "x" else d[0])
        if away <= 0:
            continue
        s = architecture.WALL / away  # distance to the outer face of the wall
        if abs(s * along) > (o["u"][1] - o["u"][0]) / 2 or s * d[1] > (o["v"][1] - o["v"][0]) / 2:
            continue
        u, v = (o["u"][0] + o["u"][1]) / 2, (o["v"][0] + o["v"][1]) / 2
        plane = o["planes"][0]
        p = np.array([u, v, plane]) if o["axis"] == "x" else np.array([plane, v, u])
        hit = p - d * (v / d[1])  # follow the sunlight from the window centre to the floor
        out.append(hit if x0 < hit[0] < x1 and z0 < hit[2] < z1 else None)
    return out


def sun_enters(desc: dict) -> bool:
    """The sun shines into the main room through a window, and with a high sun ("sun"
    lighting) its patch lands on the room's floor. Courtyards: any sun."""
    if desc["layout"]["kind"] == "courtyard":
        return "sun" in desc["environment"]
    patches = sun_patches(desc)
    if desc["lighting"] == "sun":
        return any(p is not None for p in patches)
    return bool(patches)
