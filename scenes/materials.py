"""Material descriptions by role (plain JSON-able dicts) and their Mitsuba plugin dicts.

A description is all that is stored; textures are rebuilt from their seeds, so a scene seed
reproduces every bitmap. The albedo buffer follows the OIDN convention for surfaces whose
Mitsuba `albedo` AOV is not a reflectance (delta and rough conductors, glass): `albedo_of`
gives the value the renderer writes there instead.
"""

from __future__ import annotations

import numpy as np

from . import textures

# Named Mitsuba conductors with approximate normal-incidence reflectance (linear sRGB); the
# latter only feeds the albedo buffer, Mitsuba renders the spectral eta/k itself.
METALS = {
    "Au": (1.0, 0.78, 0.34),
    "Ag": (0.97, 0.96, 0.91),
    "Cu": (0.96, 0.64, 0.54),
    "Al": (0.91, 0.92, 0.92),
    "Cr": (0.55, 0.56, 0.55),
    "Ni_palik": (0.66, 0.61, 0.53),
}


def texture_pixels(spec: dict, colored: bool) -> np.ndarray:
    """The bitmap of a texture spec, rebuilt from its seeds: (H, W, 3) linear RGB or (H, W)
    scalar; row 0 is sampled at v = 0 (both renderers' bitmaps are fed row 0 first)."""
    field = textures.make(spec["pattern"], spec["seed"])
    data = textures.colorize(field, np.random.default_rng(spec["color_seed"])) if colored else field
    return np.ascontiguousarray(data, np.float32)


def roughness_pixels(mat: dict) -> np.ndarray:
    """Spatially varying roughness alpha: between alpha/4 and alpha (gloss varies, never turns
    into a mirror)."""
    field = textures.make(mat["alpha_texture"]["pattern"], mat["alpha_texture"]["seed"])
    return np.ascontiguousarray(mat["alpha"] * (0.25 + 0.75 * field), np.float32)


def _bitmap(spec: dict, colored: bool) -> dict:
    import mitsuba as mi

    t = spec["tiling"]
    return {
        "type": "bitmap",
        "bitmap": mi.Bitmap(texture_pixels(spec, colored)),
        "raw": not colored,
        "to_uv": mi.ScalarTransform3f().scale([t, t]),
    }


def _reflectance(mat: dict) -> dict:
    if "texture" in mat:
        return _bitmap(mat["texture"], colored=True)
    return {"type": "rgb", "value": mat["color"]}


def _alpha(mat: dict) -> dict | float:
    if "alpha_texture" not in mat:
        return mat["alpha"]
    import mitsuba as mi

    tex = _bitmap(mat["alpha_texture"], colored=False)
    tex["bitmap"] = mi.Bitmap(roughness_pixels(mat))
    return tex


def bsdf_dict(mat: dict) -> dict:
    """Mitsuba BSDF plugin dict for a description (an active variant is required)."""
    kind = mat["kind"]
    if kind == "diffuse":
        bsdf: dict = {"type": "diffuse", "reflectance": _reflectance(mat)}
    elif kind in ("plastic", "roughplastic"):
        bsdf = {"type": kind, "diffuse_reflectance": _reflectance(mat)}
        if kind == "roughplastic":
            bsdf["alpha"] = _alpha(mat)
    elif kind == "conductor":
        bsdf = {"type": "conductor", "material": mat["metal"]}
    elif kind == "roughconductor":
        bsdf = {"type": "roughconductor", "material": mat["metal"], "alpha": _alpha(mat)}
    else:
        bsdf = {"type": kind, "int_ior": mat["ior"], "ext_ior": 1.0}
        bsdf["specular_transmittance"] = {"type": "rgb", "value": mat["tint"]}
        if kind == "roughdielectric":
            bsdf["alpha"] = mat["alpha"]
        return bsdf  # dielectrics are two-sided by nature and must not be wrapped
    if "bump" in mat:
        bsdf = {
            "type": "bumpmap",
            "arbitrary": _bitmap(mat["bump"], colored=False),
            "scale": mat["bump"]["scale"] * 0.02,
            "bsdf": bsdf,
        }
    return {"type": "twosided", "bsdf": bsdf}


def albedo_of(mat: dict) -> list[float] | None:
    """Albedo-buffer value for surfaces where Mitsuba's AOV is not a reflectance, else None."""
    if mat["kind"] in ("conductor", "roughconductor"):
        return list(METALS[mat["metal"]])
    if mat["kind"] in ("dielectric", "thindielectric", "roughdielectric"):
        return list(mat["tint"])
    return None


def blackbody_rgb(kelvin: float) -> np.ndarray:
    """Linear sRGB colour of a black body, normalised to luminance 1 (light colours)."""
    lam = np.linspace(380e-9, 780e-9, 81)
    h, c, k = 6.626e-34, 2.998e8, 1.381e-23
    spd = 1.0 / (lam**5 * (np.exp(h * c / (lam * k * kelvin)) - 1.0))
    nm = lam * 1e9

    def g(mu: float, s1: float, s2: float) -> np.ndarray:
        s = np.where(nm < mu, s1, s2)
        return np.exp(-0.5 * ((nm - mu) / s) ** 2)

    # CIE 1931 matching functions, multi-lobe Gaussian fit (Wyman, Sloan, Shirley 2013).
    x = 1.056 * g(599.8, 37.9, 31.0) + 0.362 * g(442.0, 16.0, 26.7) - 0.065 * g(501.1, 20.4, 26.2)
    y = 0.821 * g(568.8, 46.9, 40.5) + 0.286 * g(530.9, 16.3, 31.1)
    z = 1.217 * g(437.0, 11.8, 36.0) + 0.681 * g(459.0, 26.0, 13.8)
    xyz = np.array([np.sum(spd * x), np.sum(spd * y), np.sum(spd * z)])
    m = np.array([[3.2406, -1.5372, -0.4986], [-0.9689, 1.8758, 0.0415], [0.0557, -0.2040, 1.0570]])
    rgb = np.clip(m @ xyz, 0, None)
    lum = 0.2126 * rgb[0] + 0.7152 * rgb[1] + 0.0722 * rgb[2]
    return (rgb / lum).astype(np.float32)


# ---------------------------------------------------------------------------------------------
# Interior materials by role (generator g2): what a surface is decides its BSDF and pattern.


def _tex(rng: np.random.Generator, pattern: str, period: float) -> dict:
    """Texture spec whose pattern repeats every `period` UV units (metres on room surfaces)."""
    return {
        "pattern": pattern,
        "seed": int(rng.integers(2**31)),
        "color_seed": int(rng.integers(2**31)),
        "tiling": float(1.0 / period),
    }


def _textured(kind: str, color: list[float], alpha: float | None, texture: dict) -> dict:
    """A patterned surface: kind, colour, roughness `alpha` (glossy kinds; None: left out) and
    texture. A call draws its arguments in this order, the scenes' order: keep it."""
    mat: dict = {"kind": kind, "color": color}
    if alpha is not None:
        mat["alpha"] = alpha
    mat["texture"] = texture
    return mat


def _pale(rng: np.random.Generator) -> list[float]:
    return (0.45 + 0.4 * textures.random_color(rng, 0.5, 1.0)).clip(0, 0.9).tolist()


ROLES = (
    "paint",
    "wallpaper",
    "wall_tiles",
    "brick",
    "ceiling",
    "floor_wood",
    "floor_tiles",
    "carpet",
    "stone",
    "wood",
    "fabric",
    "metal",
    "glass",
    "ceramic",
    "paper",
    "dark",
    "leaf",
)


def role_material(rng: np.random.Generator, role: str) -> dict:
    """A material description for a surface role (walls, floors, furniture parts)."""
    u = lambda lo, hi: float(np.exp(rng.uniform(np.log(lo), np.log(hi))))  # noqa: E731
    if role == "paint":
        if rng.random() < 0.3:  # satin paint: a faint sheen
            return {"kind": "roughplastic", "color": _pale(rng), "alpha": u(0.15, 0.4)}
        return {"kind": "diffuse", "color": _pale(rng)}
    if role == "ceiling":
        return {"kind": "diffuse", "color": [float(rng.uniform(0.6, 0.85))] * 3}
    if role == "wallpaper":
        return _textured("diffuse", _pale(rng), None, _tex(rng, "wallpaper", u(0.2, 0.8)))
    if role == "wall_tiles":
        kind = str(rng.choice(["plastic", "roughplastic"]))
        return _textured(kind, _pale(rng), u(0.03, 0.15), _tex(rng, "tiles", u(0.4, 1.6)))
    if role == "brick":
        return _textured("diffuse", [0.5, 0.3, 0.2], None, _tex(rng, "bricks", u(1, 2.5)))
    if role == "floor_wood":
        kind = "plastic" if rng.random() < 0.3 else "roughplastic"  # polished: sharp reflections
        return _textured(kind, [0.4, 0.25, 0.12], u(0.04, 0.25), _tex(rng, "planks", u(1.2, 3.0)))
    if role == "floor_tiles":
        kind = str(rng.choice(["plastic", "roughplastic"]))
        return _textured(kind, _pale(rng), u(0.03, 0.2),
                         _tex(rng, str(rng.choice(["tiles", "checker"])), u(0.8, 3.0)))
    if role == "carpet":
        return _textured("diffuse", _pale(rng), None, _tex(rng, "fabric", u(0.03, 0.15)))
    if role == "stone":
        return _textured("roughplastic", [0.5, 0.48, 0.45], u(0.2, 0.5),
                         _tex(rng, str(rng.choice(["noise", "tiles"])), u(1.0, 4.0)))
    if role == "wood":
        return _textured("roughplastic", [0.4, 0.25, 0.12], u(0.05, 0.35),
                         _tex(rng, "wood", u(0.3, 1.2)))
    if role == "fabric":
        color = textures.random_color(rng).tolist()
        return _textured("diffuse", color, None, _tex(rng, "fabric", u(0.01, 0.05)))
    if role == "metal":
        mat: dict = {"kind": "conductor" if rng.random() < 0.3 else "roughconductor"}
        mat["metal"] = str(rng.choice(list(METALS)))
        if mat["kind"] == "roughconductor":
            mat["alpha"] = u(0.03, 0.4)
        return mat
    if role == "glass":
        kind = str(
            rng.choice(["dielectric", "thindielectric", "roughdielectric"], p=[0.4, 0.4, 0.2])
        )
        mat = {
            "kind": kind,
            "ior": 1.5,
            "tint": (1 - 0.3 * rng.random(3) * (rng.random() < 0.4)).tolist(),
        }
        if kind == "roughdielectric":
            mat["alpha"] = u(0.03, 0.2)
        return mat
    if role == "ceramic":
        return {"kind": "plastic", "color": textures.random_color(rng).tolist()}
    if role == "paper":
        return {"kind": "diffuse", "color": [0.8, 0.8, 0.8], "texture": _tex(rng, "poster", 1.0)}
    if role == "dark":
        return {"kind": "roughplastic", "color": [0.03, 0.03, 0.03], "alpha": u(0.05, 0.3)}
    if role == "leaf":
        g = rng.uniform(0.05, 0.25)
        return {"kind": "diffuse", "color": [g * 0.5, g, g * 0.3]}
    raise ValueError(f"unknown material role {role!r}")
