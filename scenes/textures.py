"""Procedural texture bitmaps in numpy, all driven by an explicit `np.random.Generator`.

Patterns return a scalar field (H, W) in [0, 1]; `colorize` maps it to linear RGB between two
or three random colours. High-frequency patterns (text, fine stripes, noise) matter: they are
what a denoiser must not blur.
"""

from __future__ import annotations

import numpy as np

SIZE = 256  # texels per side: small enough to build in milliseconds, tiled through to_uv


def checker(rng: np.random.Generator, size: int = SIZE) -> np.ndarray:
    n = int(rng.choice([2, 4, 8, 16]))
    y, x = np.mgrid[0:size, 0:size] * n // size
    return ((x + y) % 2).astype(np.float32)


def stripes(rng: np.random.Generator, size: int = SIZE) -> np.ndarray:
    n = min(int(rng.choice([4, 8, 16, 32, 64])), size // 4)  # >= 4 texels per period
    duty = rng.uniform(0.2, 0.8)
    x = np.arange(size) / size * n
    row = ((x % 1.0) < duty).astype(np.float32)
    img = np.tile(row, (size, 1))
    return img if rng.random() < 0.5 else img.T.copy()


def value_noise(rng: np.random.Generator, size: int = SIZE, octaves: int = 5) -> np.ndarray:
    """Fractal value noise: bilinearly upsampled random lattices, halving amplitude per octave.
    Lattices wrap so the texture tiles without seams."""
    out = np.zeros((size, size), np.float64)
    amp, total = 1.0, 0.0
    base = int(rng.choice([2, 4, 8]))
    for o in range(octaves):
        cells = base * 2**o
        if cells > size:
            break
        lattice = rng.random((cells, cells))
        t = np.arange(size) / size * cells
        i0 = np.floor(t).astype(int)
        f = t - i0
        f = f * f * (3 - 2 * f)  # smoothstep hides the lattice
        i1 = (i0 + 1) % cells
        rows = lattice[i0] * (1 - f)[:, None] + lattice[i1] * f[:, None]
        out += amp * (rows[:, i0] * (1 - f) + rows[:, i1] * f)
        total += amp
        amp *= 0.5
    out /= total
    lo, hi = np.percentile(out, [1, 99])
    return np.clip((out - lo) / max(hi - lo, 1e-6), 0, 1).astype(np.float32)


def text(rng: np.random.Generator, size: int = SIZE, scale: int = 0) -> np.ndarray:
    """Lines of random 5x7 dot-matrix glyphs: printed-page-like high-frequency detail.
    `scale` 0 draws 1 or 2 texels per glyph dot."""
    glyphs = rng.random((40, 7, 5)) < 0.45
    scale = scale or int(rng.choice([1, 2]))
    gh, gw = 9 * scale, 6 * scale  # glyph cell with one blank column and two blank rows
    img = np.zeros((size, size), np.float32)
    for row in range(size // gh):
        col = 0
        line_end = size - int(rng.integers(0, size // 3))
        while col + gw <= line_end:
            if rng.random() < 0.15:  # word gap
                col += gw
                continue
            g = np.kron(glyphs[rng.integers(40)], np.ones((scale, scale)))
            y0 = row * gh + scale
            img[y0 : y0 + 7 * scale, col : col + 5 * scale] = g
            col += gw
    return img


def bricks(rng: np.random.Generator, size: int = SIZE) -> np.ndarray:
    rows = int(rng.choice([4, 8, 16]))
    h = size // rows
    w = 2 * h
    mortar = max(1, h // 8)
    y, x = np.mgrid[0:size, 0:size]
    shift = (y // h % 2) * (w // 2)
    inside = ((y % h) >= mortar) & (((x + shift) % w) >= mortar)
    tone = rng.uniform(0.7, 1.0, (rows + 1, size // w + 2))
    return np.where(inside, tone[y // h, (x + shift) // w], 0.0).astype(np.float32)


def wood(rng: np.random.Generator, size: int = SIZE) -> np.ndarray:
    """Rings distorted by noise: long thin stripes like planks or grain."""
    n = value_noise(rng, size, octaves=4)
    freq = rng.uniform(8, 30)
    x = np.arange(size)[None, :] / size
    return (0.5 + 0.5 * np.sin(2 * np.pi * (x * freq + 2.0 * n))).astype(np.float32)


def tiles(rng: np.random.Generator, size: int = SIZE) -> np.ndarray:
    """Square tiles with grout lines and a slightly different tone per tile."""
    n = int(rng.choice([2, 4, 8]))
    cell = size // n
    grout = max(1, cell // int(rng.choice([10, 16, 32])))
    y, x = np.mgrid[0:size, 0:size]
    tone = rng.uniform(0.75, 1.0, (n, n))
    inside = ((x % cell) >= grout) & ((y % cell) >= grout)
    return np.where(inside, tone[y // cell % n, x // cell % n], 0.08).astype(np.float32)


def planks(rng: np.random.Generator, size: int = SIZE) -> np.ndarray:
    """Floor boards along u: wood grain, staggered butt joints, dark seams, tone per board."""
    rows = int(rng.choice([4, 6, 8]))
    h = size // rows
    grain = wood(rng, size).T  # grain runs along the boards
    y, x = np.mgrid[0:size, 0:size]
    row = np.minimum(y // h, rows - 1)
    shift = rng.integers(0, size, rows)[row]
    length = size // int(rng.choice([1, 2]))
    seam = ((y % h) < 1) | (((x + shift) % length) < 1)
    tone = rng.uniform(0.6, 1.0, rows)[row]
    return np.where(seam, 0.03, tone * (0.55 + 0.45 * grain)).astype(np.float32)


def fabric(rng: np.random.Generator, size: int = SIZE) -> np.ndarray:
    """Plain weave: alternating warp and weft threads with a little fibre noise."""
    period = int(rng.choice([2, 4, 8]))
    y, x = np.mgrid[0:size, 0:size]
    warp = 0.5 + 0.5 * np.cos(np.pi * ((x % period) / period - 0.5))
    weft = 0.5 + 0.5 * np.cos(np.pi * ((y % period) / period - 0.5))
    over = ((x // period + y // period) % 2).astype(bool)
    base = np.where(over, warp, weft)
    return np.clip(0.7 * base + 0.3 * value_noise(rng, size, 6), 0, 1).astype(np.float32)


def wallpaper(rng: np.random.Generator, size: int = SIZE) -> np.ndarray:
    """Repeating motif (diamonds, dots or a lattice) over pin stripes."""
    n = int(rng.choice([4, 8, 16]))
    y, x = np.mgrid[0:size, 0:size] % (size // n) / (size // n) - 0.5
    motif = int(rng.integers(3))
    r = rng.uniform(0.15, 0.35)
    if motif == 0:
        field = np.abs(x) + np.abs(y) < r
    elif motif == 1:
        field = x * x + y * y < r * r
    else:
        field = (np.abs(np.abs(x) - np.abs(y)) < 0.06) | (np.abs(x) > 0.46)
    return np.where(field, 1.0, rng.uniform(0.2, 0.6)).astype(np.float32)


def poster(rng: np.random.Generator, size: int = SIZE) -> np.ndarray:
    """A printed poster: a title in large glyphs, a picture block, then body text."""
    img = np.full((size, size), rng.uniform(0.8, 1.0), np.float32)
    t1, t2 = int(size * rng.uniform(0.15, 0.25)), int(size * rng.uniform(0.5, 0.65))
    m = size // 16
    title = 1 - text(rng, size, scale=3)
    img[m:t1] = np.minimum(img[m:t1], title[m:t1] + 0.1)
    pic = value_noise(rng, size, 4)
    y, x = np.mgrid[0:size, 0:size] / size
    cx, cy, rr = rng.uniform(0.3, 0.7), rng.uniform(0.3, 0.7), rng.uniform(0.1, 0.3)
    pic = np.where((x - cx) ** 2 + (y - cy) ** 2 < rr * rr, 1 - pic, pic)
    img[t1 + m : t2, m:-m] = pic[t1 + m : t2, m:-m]
    body = 1 - text(rng, size, scale=1)
    img[t2 + m : -m, m:-m] = np.minimum(img[t2 + m : -m, m:-m], body[t2 + m : -m, m:-m] + 0.1)
    return img


PATTERNS = {
    "checker": checker,
    "stripes": stripes,
    "noise": value_noise,
    "text": text,
    "bricks": bricks,
    "wood": wood,
    "tiles": tiles,
    "planks": planks,
    "fabric": fabric,
    "wallpaper": wallpaper,
    "poster": poster,
}


def random_color(rng: np.random.Generator, lo: float = 0.05, hi: float = 0.85) -> np.ndarray:
    """Linear RGB reflectance; saturation varies from grey to strongly coloured."""
    grey = rng.uniform(lo, hi)
    hue = rng.uniform(lo, hi, 3)
    sat = rng.uniform(0, 1) ** 2
    return (grey * (1 - sat) + hue * sat).astype(np.float32)


def colorize(field: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Map a [0, 1] field to (H, W, 3) linear RGB between two random colours."""
    a, b = random_color(rng), random_color(rng)
    if rng.random() < 0.3:  # strong contrast: near-black ink on a light background
        a, b = a * 0.1, np.clip(b + 0.3, 0, 0.9)
    return (a[None, None] * (1 - field[..., None]) + b[None, None] * field[..., None]).astype(
        np.float32
    )


def make(kind: str, seed: int, size: int = SIZE) -> np.ndarray:
    """Scalar field of pattern `kind` from its own seed (textures rebuild from a description)."""
    return PATTERNS[kind](np.random.default_rng(seed), size)
