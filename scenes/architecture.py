"""Procedural architecture for generator g2: rooms, an annex (corridor or second room) through a
doorway, windows with reveals, frames and blinds, and open courtyards with a colonnade.

`plan(rng)` draws a JSON-able layout; `meshes_of(layout)` rebuilds the geometry as
(surface, MeshData) pairs, surface being a key of the layout's material table ("wall0",
"floor0", "ceiling0", "frame", "blind", "stone", ...). Axis-aligned boxes only: every space is
a rectangle [x0, z0, x1, z1] with a height, walls are quads on its boundary facing inwards, and
an opening is a hole through one or two parallel walls (a doorway joins a space to its annex
across the wall thickness), lined by reveals so light through it is cut like a real window's.
"""

from __future__ import annotations

import numpy as np

from . import furniture, meshes
from .meshes import MeshData

WALL = 0.15  # wall thickness (m): the depth of the window and door reveals
Y_UP = np.array([0.0, 1.0, 0.0])
# Wall sides of a rectangle: (axis along the wall, fixed coordinate index in the rect,
# inward sign of the normal along the other axis).
SIDES = {"z0": ("x", 1, 1.0), "z1": ("x", 3, -1.0), "x0": ("z", 0, 1.0), "x1": ("z", 2, -1.0)}


def quad(origin, du, dv, normal, rect: list[float]) -> MeshData:
    """A quad origin + u*du + v*dv over rect [u0, u1, v0, v1], UVs in metres."""
    u0, u1, v0, v1 = rect
    corners = [(u0, v0), (u1, v0), (u1, v1), (u0, v1)]
    pos = np.array([np.add(origin, np.multiply(du, u) + np.multiply(dv, v)) for u, v in corners])
    m = MeshData(
        pos.astype(np.float32),
        np.tile(np.asarray(normal, np.float32), (4, 1)),
        np.array(corners, np.float32),
        np.array([[0, 1, 2], [0, 2, 3]], np.uint32),
    )
    return meshes.orient(m)


def _split_rect(u0: float, u1: float, v0: float, v1: float, holes: list) -> list[list[float]]:
    """Cover [u0,u1]x[v0,v1] minus non-overlapping holes with rectangles (columns)."""
    out, cursor = [], u0
    for h0, h1, g0, g1 in sorted(holes):
        out.append([cursor, h0, v0, v1])
        out += [[h0, h1, v0, g0], [h0, h1, g1, v1]]
        cursor = h1
    out.append([cursor, u1, v0, v1])
    return [r for r in out if r[1] - r[0] > 1e-6 and r[3] - r[2] > 1e-6]


def wall_frame(axis: str, plane: float, inward: float) -> np.ndarray:
    """4x4 from wall-local (u along the wall, v up, n into the space) to world; u is the world
    x (or z) coordinate itself, n = 0 on the wall plane."""
    m = np.eye(4)
    if axis == "x":
        m[:3, 0], m[:3, 2], m[2, 3] = [1, 0, 0], [0, 0, inward], plane
    else:
        m[:3, 0], m[:3, 2], m[0, 3] = [0, 0, 1], [inward, 0, 0], plane
    m[:3, 1] = Y_UP
    return m


# ---------------------------------------------------------------------------------------------
# Layout


def _u(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(rng.uniform(lo, hi))


def plan(rng: np.random.Generator, courtyard: bool) -> dict:
    """Spaces and openings. Interior: a room, 60% with an annex through a doorway, 1-4 windows
    on the room's outer walls (0-1 in the annex). Courtyard: an open yard with high facades and
    a roofed colonnade along one side."""
    if courtyard:
        return _courtyard(rng)
    w, d, h = _u(rng, 3.5, 8.0), _u(rng, 3.5, 8.0), _u(rng, 2.6, 3.4)
    room = {"rect": [-w / 2, -d / 2, w / 2, d / 2], "h": h, "ceiling": True, "kind": "room"}
    spaces, openings = [room], []
    shared = None
    if rng.random() < 0.6:
        side = str(rng.choice(list(SIDES)))
        axis, idx, inward = SIDES[side]
        lo, hi = (
            (room["rect"][0], room["rect"][2])
            if axis == "x"
            else (room["rect"][1], room["rect"][3])
        )
        kind = str(rng.choice(["corridor", "corridor", "room"]))
        if kind == "corridor" and rng.random() < 0.5:
            along, depth = _u(rng, 3.0, 7.0), _u(rng, 1.3, 2.0)  # runs along the wall
        elif kind == "corridor":
            along, depth = _u(rng, 1.3, 2.0), _u(rng, 3.0, 6.0)  # leads away from the wall
        else:
            along, depth = _u(rng, 3.0, 5.0), _u(rng, 3.0, 5.0)
        c = _u(rng, lo + 1.2 - along / 2, hi - 1.2 + along / 2)  # the walls share >= 1.2 m
        a0, a1 = c - along / 2, c + along / 2
        plane = room["rect"][idx]
        b0 = plane - inward * WALL  # the annex starts on the far side of the wall
        b1 = b0 - inward * depth
        n0, n1 = min(b0, b1), max(b0, b1)
        rect = [a0, n0, a1, n1] if axis == "x" else [n0, a0, n1, a1]
        ha = min(h, _u(rng, 2.4, 3.0))
        spaces.append({"rect": rect, "h": ha, "ceiling": True, "kind": kind})
        o0, o1 = max(a0, lo) + 0.25, min(a1, hi) - 0.25  # where the two walls face each other
        dw = min(_u(rng, 0.9, 1.4), o1 - o0)
        if dw > 0.7 and o1 - o0 >= dw:
            u0 = _u(rng, o0, max(o0, o1 - dw))
            openings.append(
                {
                    "kind": "door",
                    "axis": axis,
                    "planes": [plane, b0],
                    "inward": inward,
                    "u": [u0, u0 + dw],
                    "v": [0.0, min(ha - 0.25, _u(rng, 2.0, 2.3))],
                }
            )
            shared = (side, a0 - 0.3, a1 + 0.3)
        else:
            spaces.pop()
    for si in range(len(spaces)):
        n_windows = int(rng.integers(1, 5)) if si == 0 else int(rng.integers(0, 2))
        for _ in range(n_windows * 4):
            if sum(o["kind"] == "window" and o.get("space") == si for o in openings) >= n_windows:
                break
            _try_window(rng, spaces, si, openings, shared if si == 0 else None)
    for _ in range(200):  # daylight needs a way in: the main room always has a window
        if any(o["kind"] == "window" and o.get("space") == 0 for o in openings):
            break
        _try_window(rng, spaces, 0, openings, shared)
    return {"kind": "interior", "spaces": spaces, "openings": openings}


def wall_span(rect: list[float], side: str) -> tuple[float, float]:
    axis = SIDES[side][0]
    return (rect[0], rect[2]) if axis == "x" else (rect[1], rect[3])


def _outside_others(spaces: list[dict], si: int, side: str, u0: float, u1: float) -> bool:
    """The wall stretch [u0, u1] of space si faces the outside (no other space behind it)."""
    axis, idx, inward = SIDES[side]
    plane = spaces[si]["rect"][idx]
    behind = plane - inward * (WALL + 0.5)
    for sj, other in enumerate(spaces):
        if sj == si:
            continue
        r = other["rect"]
        lo, hi = (r[0], r[2]) if axis == "x" else (r[1], r[3])
        n0, n1 = (r[1], r[3]) if axis == "x" else (r[0], r[2])
        if u1 > lo - 0.2 and u0 < hi + 0.2 and n0 - 1 < behind < n1 + 1:
            return False
    return True


def _try_window(rng, spaces, si, openings, shared) -> None:
    space = spaces[si]
    side = str(rng.choice(list(SIDES)))
    axis, idx, inward = SIDES[side]
    lo, hi = wall_span(space["rect"], side)
    length, h = hi - lo, space["h"]
    ww = _u(rng, 0.7, min(2.6, length - 0.6))
    if ww < 0.6:
        return
    u0 = _u(rng, lo + 0.3, max(lo + 0.3, hi - 0.3 - ww))
    if rng.random() < 0.15:  # french window: down to the floor
        v0, v1 = 0.05, h - _u(rng, 0.15, 0.4)
    else:
        v0 = _u(rng, 0.5, 1.0)
        v1 = min(h - 0.15, v0 + _u(rng, 0.9, 1.8))
    if not _outside_others(spaces, si, side, u0, u0 + ww):
        return
    if shared and shared[0] == side and u0 < shared[2] and u0 + ww > shared[1]:
        return
    plane = space["rect"][idx]
    for o in openings:
        same = o["axis"] == axis and any(abs(p - plane) < 1e-6 for p in o["planes"])
        if same and u0 < o["u"][1] + 0.3 and u0 + ww > o["u"][0] - 0.3:
            return
    openings.append(
        {
            "kind": "window",
            "space": si,
            "axis": axis,
            "planes": [plane, plane - inward * WALL],
            "inward": inward,
            "u": [u0, u0 + ww],
            "v": [v0, v1],
            "mullions": int(rng.integers(0, 3)),
            "transom": bool(rng.random() < 0.4),
            "blind": None,
        }
    )


def _courtyard(rng: np.random.Generator) -> dict:
    w, d, h = _u(rng, 8, 14), _u(rng, 8, 13), _u(rng, 5.0, 8.0)
    yard = {"rect": [-w / 2, -d / 2, w / 2, d / 2], "h": h, "ceiling": False, "kind": "yard"}
    depth = _u(rng, 2.5, 3.5)
    colonnade = {
        "depth": depth,
        "height": _u(rng, 3.0, 3.8),
        "spacing": _u(rng, 1.8, 2.8),
        "column": furniture.draw("column", rng),
        "floors": int(rng.integers(1, 3)),  # storeys of windows above the colonnade
    }
    colonnade["column"]["h"] = colonnade["height"]
    return {"kind": "courtyard", "spaces": [yard], "openings": [], "colonnade": colonnade}


def column_positions(layout: dict) -> list[list[float]]:
    """Floor positions (x, z) of the colonnade's columns (along the yard's z0 side)."""
    c = layout["colonnade"]
    x0, z0, x1, _ = layout["spaces"][0]["rect"]
    n = max(2, int((x1 - x0 - 1.0) / c["spacing"]) + 1)
    xs = np.linspace(x0 + 0.6, x1 - 0.6, n)
    return [[float(x), z0 + c["depth"]] for x in xs]


def add_blinds(rng: np.random.Generator, layout: dict, prob: float) -> None:
    """Venetian blinds in some windows: slats that cut the sun into stripes."""
    for o in layout["openings"]:
        if o["kind"] == "window" and rng.random() < prob:
            o["blind"] = {
                "tilt": _u(rng, 0.0, 1.2),  # radians from horizontal
                "width": _u(rng, 0.025, 0.06),
                "pitch": _u(rng, 0.8, 0.95),  # slat spacing / width: slats overlap when closed
                "lowered": _u(rng, 0.4, 1.0),
                "vertical": bool(rng.random() < 0.25),
            }


# ---------------------------------------------------------------------------------------------
# Meshes


def meshes_of(layout: dict) -> list[tuple[str, MeshData]]:
    """(surface key, mesh) pairs of walls, floors, ceilings, reveals, frames, blinds and the
    courtyard's colonnade and facade details. Keys: wall<i>, floor<i>, ceiling<i> per space,
    reveal, frame, blind, stone, dark."""
    out: list[tuple[str, MeshData]] = []
    for si, space in enumerate(layout["spaces"]):
        x0, z0, x1, z1 = space["rect"]
        h = space["h"]
        for side, (axis, idx, inward) in SIDES.items():
            plane = space["rect"][idx]
            lo, hi = wall_span(space["rect"], side)
            holes = [
                [o["u"][0], o["u"][1], o["v"][0], o["v"][1]]
                for o in layout["openings"]
                if o["axis"] == axis
                and any(abs(p - plane) < 1e-6 for p in o["planes"])
                and lo - 1e-6 <= o["u"][0] < o["u"][1] <= hi + 1e-6
            ]
            m = wall_frame(axis, plane, inward)
            for r in _split_rect(lo, hi, 0, h, holes):
                out.append((f"wall{si}", quad(m[:3, 3], m[:3, 0], m[:3, 1], m[:3, 2], r)))
        # Floors and ceilings reach under/over the walls so no crack lets light in.
        e = WALL
        out.append(
            (
                f"floor{si}",
                quad([0, 0, 0], [1, 0, 0], [0, 0, 1], Y_UP, [x0 - e, x1 + e, z0 - e, z1 + e]),
            )
        )
        if space["ceiling"]:
            out.append(
                (
                    f"ceiling{si}",
                    quad([0, h, 0], [1, 0, 0], [0, 0, 1], -Y_UP, [x0 - e, x1 + e, z0 - e, z1 + e]),
                )
            )
    for o in layout["openings"]:
        out += _opening_meshes(o)
    if layout["kind"] == "courtyard":
        out += _courtyard_meshes(layout)
    return out


def _opening_meshes(o: dict) -> list[tuple[str, MeshData]]:
    """Reveals (the wall's thickness around the hole), window frame and mullions, blinds."""
    u0, u1 = o["u"]
    v0, v1 = o["v"]
    m = wall_frame(o["axis"], o["planes"][0], o["inward"])
    t = WALL
    local = [  # in wall-local (u, v, n) coordinates; the reveal spans n in [-t, 0]
        quad([u0, 0, 0], [0, 0, -1], [0, 1, 0], [1, 0, 0], [0, t, v0, v1]),
        quad([u1, 0, 0], [0, 0, -1], [0, 1, 0], [-1, 0, 0], [0, t, v0, v1]),
        quad([0, v1, 0], [1, 0, 0], [0, 0, -1], [0, -1, 0], [u0, u1, 0, t]),
    ]
    out = [("reveal", q.transformed(m)) for q in local]
    sill = quad([0, v0, 0], [1, 0, 0], [0, 0, -1], [0, 1, 0], [u0, u1, 0, t])
    out.append(("floor0" if o["kind"] == "door" else "reveal", sill.transformed(m)))
    if o["kind"] != "window":
        return out
    f, n = 0.05, -t * 0.6  # frame bars sit in the reveal, 60% of the way out
    bars = [
        ((u1 - u0, f, 0.05), ((u0 + u1) / 2, v0 + f / 2, n)),
        ((u1 - u0, f, 0.05), ((u0 + u1) / 2, v1 - f / 2, n)),
        ((f, v1 - v0, 0.05), (u0 + f / 2, (v0 + v1) / 2, n)),
        ((f, v1 - v0, 0.05), (u1 - f / 2, (v0 + v1) / 2, n)),
    ]
    for k in range(o["mullions"]):
        u = u0 + (k + 1) / (o["mullions"] + 1) * (u1 - u0)
        bars.append(((0.035, v1 - v0, 0.04), (u, (v0 + v1) / 2, n)))
    if o["transom"]:
        bars.append(((u1 - u0, 0.035, 0.04), ((u0 + u1) / 2, v0 + 0.7 * (v1 - v0), n)))
    out += [("frame", meshes.box_at(s, c).transformed(m)) for s, c in bars]
    if o["blind"]:
        out += [("blind", b.transformed(m)) for b in _blind(o["blind"], u0, u1, v0, v1)]
    return out


def _blind(b: dict, u0: float, u1: float, v0: float, v1: float) -> list[MeshData]:
    """Slats just inside the window (wall-local coordinates), tilted about their long axis."""
    w, tilt = b["width"], b["tilt"]
    pitch = w * b["pitch"]
    c, s = np.cos(tilt), np.sin(tilt)
    out = []
    if b["vertical"]:  # vertical louvres across the whole height, turned about Y
        n = int((u1 - u0) / pitch)
        for i in range(n):
            u = u0 + (i + 0.5) * pitch
            rot = np.array([[c, 0, s, u], [0, 1, 0, (v0 + v1) / 2], [-s, 0, c, 0.06], [0, 0, 0, 1]])
            out.append(meshes.box((0.004, v1 - v0, w)).transformed(rot))
        return out
    bottom = v1 - b["lowered"] * (v1 - v0)
    n = int((v1 - bottom) / pitch)
    for i in range(n):
        v = v1 - (i + 0.5) * pitch
        rot = np.array([[1, 0, 0, (u0 + u1) / 2], [0, c, -s, v], [0, s, c, 0.06], [0, 0, 0, 1]])
        out.append(meshes.box((u1 - u0 + 0.04, 0.003, w)).transformed(rot))
    out.append(meshes.box_at((u1 - u0 + 0.04, 0.03, 0.05), ((u0 + u1) / 2, v1 - 0.015, 0.06)))
    return out


def _courtyard_meshes(layout: dict) -> list[tuple[str, MeshData]]:
    """Colonnade (roof slab, back-wall storeys above it) and facade windows (frames with dark
    glossy panes, no holes) on every wall, balconies with railings on upper storeys."""
    yard = layout["spaces"][0]
    c = layout["colonnade"]
    x0, z0, x1, z1 = yard["rect"]
    out: list[tuple[str, MeshData]] = []
    hc, depth = c["height"], c["depth"]
    out.append(
        (
            "stone",
            meshes.box_at((x1 - x0, 0.3, depth + 0.3), ((x0 + x1) / 2, hc + 0.15, z0 + depth / 2)),
        )
    )
    for x, z in column_positions(layout):
        for role, m in furniture.parts("column", c["column"]):
            t = np.eye(4)
            t[:3, 3] = (x, 0, z)
            out.append(("stone" if role == "stone" else role, m.transformed(t)))
    rng = np.random.default_rng(int(abs(x1 * 1000)) + int(abs(z1 * 1000)))
    for side, (axis, idx, inward) in SIDES.items():
        plane = yard["rect"][idx]
        lo, hi = wall_span(yard["rect"], side)
        m = wall_frame(axis, plane, inward)
        storey = 3.0
        y = hc + 0.6 if side == "z0" else 0.9
        while y + 1.6 < yard["h"] - 0.3:
            n = int((hi - lo) / 2.2)
            for k in range(n):
                u = lo + (k + 0.5) * (hi - lo) / n
                ww, wh = 0.9, 1.5
                out.append(
                    ("dark", meshes.box_at((ww, wh, 0.02), (u, y + wh / 2, 0.01)).transformed(m))
                )
                for s_, c_ in (
                    ((ww + 0.16, 0.08, 0.08), (u, y, 0.04)),
                    ((ww + 0.16, 0.08, 0.08), (u, y + wh, 0.04)),
                    ((0.08, wh, 0.08), (u - ww / 2 - 0.04, y + wh / 2, 0.04)),
                    ((0.08, wh, 0.08), (u + ww / 2 + 0.04, y + wh / 2, 0.04)),
                ):
                    out.append(("frame", meshes.box_at(s_, c_).transformed(m)))
                if y > 2.5 and rng.random() < 0.3:  # a balcony with a railing
                    out.append(
                        (
                            "stone",
                            meshes.box_at((ww + 0.6, 0.12, 0.7), (u, y - 0.06, 0.35)).transformed(
                                m
                            ),
                        )
                    )
                    rail = furniture.draw("railing", rng)
                    rail["l"] = ww + 0.5
                    t = np.eye(4)
                    t[:3, 3] = (u, y, 0.65)
                    for role, part in furniture.parts("railing", rail):
                        out.append(
                            ("metal" if role == "metal" else "frame", part.transformed(m @ t))
                        )
            y += storey
    return out


def inside(layout: dict, points: np.ndarray, margin: float) -> np.ndarray:
    """Which points (N, 3) are inside some space, `margin` from its walls, floor and ceiling."""
    ok = np.zeros(len(points), bool)
    for s in layout["spaces"]:
        x0, z0, x1, z1 = s["rect"]
        ok |= (
            (points[:, 0] > x0 + margin)
            & (points[:, 0] < x1 - margin)
            & (points[:, 2] > z0 + margin)
            & (points[:, 2] < z1 - margin)
            & (points[:, 1] > margin)
            & (points[:, 1] < s["h"] - margin)
        )
    return ok


def space_of(layout: dict, point: np.ndarray) -> int:
    """Index of the space containing `point` (x, z), or -1."""
    for i, s in enumerate(layout["spaces"]):
        x0, z0, x1, z1 = s["rect"]
        if x0 <= point[0] <= x1 and z0 <= point[2] <= z1:
            return i
    return -1
