"""Furniture placed in a laid-out space (generator g2), and the moving object of a shot.

`furnish` stands pieces assembled from parts (`furniture.py`) against walls and in groups, hangs
pictures and pendants, and puts props and tiny bright LEDs on tops, without overlaps; what the
camera must stay out of is kept as blockers (`camera_clear`). `mover` sends a ball rolling or
a chair sliding through the first frame's view, clear of furniture, walls and the cameras.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from . import architecture, furniture, materials, textures
from .architecture import Y_UP
from .camera import Camera


def _transform(theta: float, pos) -> np.ndarray:
    """Yaw `theta` about +Y (local +Z turns to (sin, 0, cos)), then translate to `pos`."""
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, 0, s, pos[0]], [0, 1, 0, pos[1]], [-s, 0, c, pos[2]], [0, 0, 0, 1.0]])


def _aabb(fw: float, fd: float, theta: float, x: float, z: float) -> list[float]:
    c, s = abs(np.cos(theta)), abs(np.sin(theta))
    wx, wz = c * fw + s * fd, s * fw + c * fd
    return [x - wx / 2, z - wz / 2, x + wx / 2, z + wz / 2]


def _overlap(a: list[float], b: list[float], margin: float = 0.0) -> bool:
    return (
        a[0] < b[2] + margin
        and b[0] < a[2] + margin
        and a[1] < b[3] + margin
        and b[1] < a[3] + margin
    )


def _within(r: list[float], space: dict, margin: float = 0.0) -> bool:
    x0, z0, x1, z1 = space["rect"]
    return (
        r[0] >= x0 + margin and r[1] >= z0 + margin and r[2] <= x1 - margin and r[3] <= z1 - margin
    )


def _overlaps_opening(u: float, width: float, opening: dict, pad: float) -> bool:
    """Something `width` wide centred at `u` along a wall reaches within `pad` of `opening`."""
    return u - width / 2 < opening["u"][1] + pad and u + width / 2 > opening["u"][0] - pad


def _on_wall(space: dict, side: str, u: float, y: float) -> tuple[np.ndarray, float, np.ndarray]:
    """Wall `side` of `space` at `u` along it and height `y`: (inward normal, the yaw that
    turns a piece's front (+Z) to face it, the point on the wall)."""
    axis, idx, inward = architecture.SIDES[side]
    plane = space["rect"][idx]
    n = np.array([0, 0, inward]) if axis == "x" else np.array([inward, 0, 0])
    on_plane = np.array([u, y, plane]) if axis == "x" else np.array([plane, y, u])
    return n, float(np.arctan2(n[0], n[2])), on_plane


class Furnisher:
    """Places pieces without overlaps; records blockers (boxes the camera must stay out of)."""

    def __init__(self, rng: np.random.Generator, layout: dict, palette: dict, mode: str):
        self.rng, self.layout, self.palette, self.mode = rng, layout, palette, mode
        self.pieces: list[dict] = []
        self.blockers: list[dict] = []  # {"rect": [x0, z0, x1, z1], "y": [y0, y1]}
        self.tops: list[tuple[list[float], float]] = []  # surfaces props can stand on

    def add(self, kind: str, params: dict, m: np.ndarray, light: dict | None = None) -> dict:
        roles = {r for r, _ in furniture.parts(kind, params) if r != "bulb"}
        mats = {r: int(self.rng.choice(self.palette[r])) for r in sorted(roles)}
        piece = {"kind": kind, "params": params, "transform": m.tolist(), "materials": mats}
        if light is not None:
            piece["light"] = light
        self.pieces.append(piece)
        return piece

    def wall_spots(
        self, space: dict, width: float, clear: float, margin: float, tries: int
    ) -> Iterator[tuple[str, float]]:
        """Random places for something `width` wide along the walls of `space`: (side, u), u
        at least `margin` from the wall's ends. Each of the `tries` draws a wall; one under
        `width + clear` long uses up its try."""
        for _ in range(tries):
            side = str(self.rng.choice(list(architecture.SIDES)))
            lo, hi = architecture.wall_span(space["rect"], side)
            if hi - lo >= width + clear:
                yield side, self.rng.uniform(lo + width / 2 + margin, hi - width / 2 - margin)

    def openings_on(self, space: dict, side: str) -> list[dict]:
        """The doors and windows in wall `side` of `space`."""
        axis, idx, _ = architecture.SIDES[side]
        plane = space["rect"][idx]
        return [
            o
            for o in self.layout["openings"]
            if o["axis"] == axis and any(abs(q - plane) < 1e-6 for q in o["planes"])
        ]

    def free(self, rect: list[float], skip: int = 0) -> bool:
        return not any(
            _overlap(rect, b["rect"], 0.05) for b in self.blockers[skip:] if b["y"][0] < 0.5
        )

    def lamp_light(self, force: bool = False) -> dict:
        on = force or self.mode in ("evening", "night") or self.rng.random() < 0.15
        return {
            "power": float(np.exp(self.rng.uniform(np.log(30), np.log(200)))),
            "color": materials.blackbody_rgb(float(self.rng.uniform(2600, 4200))).tolist(),
            "on": bool(on),
        }

    def on_wall(self, si: int, kind: str, params: dict | None = None, light=None) -> dict | None:
        """Stand a piece with its back to a wall, clear of doors (and of windows if taller
        than the sill)."""
        rng, space = self.rng, self.layout["spaces"][si]
        params = params or furniture.draw(kind, rng)
        fw, fd, fh = furniture.footprint(kind, params)
        for side, u in self.wall_spots(space, fw, clear=0.2, margin=0.05, tries=30):
            if any(
                _overlaps_opening(u, fw, o, 0.5 if o["kind"] == "door" else 0.05)
                and (o["kind"] == "door" or fh > o["v"][0] - 0.05)  # a window: if over the sill
                for o in self.openings_on(space, side)
            ):
                continue
            n, theta, on_plane = _on_wall(space, side, u, 0)
            c = on_plane + n * (fd / 2 + 0.02)
            rect = _aabb(fw, fd, theta, c[0], c[2])
            if not _within(rect, space, 0.01) or not self.free(rect):
                continue
            piece = self.add(kind, params, _transform(theta, c), light)
            self.blockers.append({"rect": rect, "y": [0.0, fh]})
            if kind == "cabinet":
                self.tops.append((rect, fh))
            piece["wall"] = [side, float(u), float(theta)]
            return piece
        return None

    def group(self, si: int) -> None:
        """A dining table with chairs around it (and a rug), in the open floor."""
        rng, space = self.rng, self.layout["spaces"][si]
        t = furniture.draw("table", rng)
        fw, fd, fh = furniture.footprint("table", t)
        for _ in range(30):
            x0, z0, x1, z1 = space["rect"]
            if x1 - x0 < fw + 2.0 or z1 - z0 < fd + 2.0:
                return
            c = np.array(
                [
                    rng.uniform(x0 + fw / 2 + 0.8, x1 - fw / 2 - 0.8),
                    0,
                    rng.uniform(z0 + fd / 2 + 0.8, z1 - fd / 2 - 0.8),
                ]
            )
            theta = float(rng.choice([0, np.pi / 2]) + rng.normal(0, 0.05))
            outer = _aabb(fw + 1.2, fd + 1.2, theta, c[0], c[2])
            if not _within(outer, space, 0.1) or not self.free(outer):
                continue
            if rng.random() < 0.5:
                rug = furniture.draw("rug", rng)
                rug["w"], rug["d"] = fw + rng.uniform(0.8, 1.6), fd + rng.uniform(0.8, 1.6)
                self.add("rug", rug, _transform(theta, c))
            self.add("table", t, _transform(theta, c))
            rect = _aabb(fw, fd, theta, c[0], c[2])
            self.blockers.append({"rect": rect, "y": [0.0, fh]})
            self.tops.append((rect, fh))
            if fh < 0.55:  # a coffee table: no chairs
                return
            chair = furniture.draw("chair", rng)
            cw = furniture.footprint("chair", chair)[0]
            per_side = max(1, int(fw / (cw + 0.25)))
            seats = [
                (x, side)
                for side in (-1, 1)
                for x in np.linspace(-fw / 2, fw / 2, per_side + 2)[1:-1]
            ]
            seats = [s for s in seats if rng.random() < 0.8]
            for x, side in seats:
                pull = rng.uniform(0.0, 0.25)
                local = np.array([x, 0, side * (fd / 2 + cw / 2 - 0.1 + pull)])
                pos = _transform(theta, c)[:3, :3] @ local + c
                phi = theta + (np.pi if side > 0 else 0.0) + rng.normal(0, 0.12)
                self.add("chair", chair, _transform(phi, pos))
                self.blockers.append({"rect": _aabb(cw, cw, phi, pos[0], pos[2]), "y": [0.0, 0.95]})
            return

    def picture(self, si: int) -> None:
        rng, space = self.rng, self.layout["spaces"][si]
        p = furniture.draw("picture", rng)
        w, h = p["w"] + 2 * p["frame"], p["h"] + 2 * p["frame"]
        for side, u in self.wall_spots(space, w, clear=0.4, margin=0.2, tries=20):
            y = rng.uniform(1.3, 1.8)
            if y + h / 2 > space["h"] - 0.1:
                continue
            if any(_overlaps_opening(u, w, o, 0.1) for o in self.openings_on(space, side)):
                continue
            n, theta, on_plane = _on_wall(space, side, u, y)
            strip = _aabb(w, 0.8, theta, *(on_plane + n * 0.4)[[0, 2]])
            if any(_overlap(strip, b["rect"]) and b["y"][1] > y - h / 2 for b in self.blockers):
                continue
            self.add("picture", p, _transform(theta, on_plane + n * 0.002))
            return

    def pendant(self, si: int, force_on: bool = False) -> None:
        rng, space = self.rng, self.layout["spaces"][si]
        p = furniture.draw("pendant", rng)
        p["drop"] = min(p["drop"], space["h"] - 2.0)
        if p["drop"] < 0.2:
            p["drop"] = 0.2
        x0, z0, x1, z1 = space["rect"]
        over = [t for t in self.tops if _within(t[0], space)]
        if over and rng.random() < 0.6:
            r = over[int(rng.integers(len(over)))][0]
            x, z = (r[0] + r[2]) / 2, (r[1] + r[3]) / 2
        else:
            mx, mz = min(0.7, (x1 - x0) / 2 - 0.05), min(0.7, (z1 - z0) / 2 - 0.05)
            x, z = rng.uniform(x0 + mx, x1 - mx), rng.uniform(z0 + mz, z1 - mz)
        self.add("pendant", p, _transform(0.0, [x, space["h"], z]), self.lamp_light(force_on))
        r = p["shade"] + 0.35
        self.blockers.append(
            {
                "rect": [x - r, z - r, x + r, z + r],
                "y": [space["h"] - p["drop"] - p["shade"] * 1.2, space["h"]],
            }
        )

    def props(self) -> None:
        """Vases, bowls, balls and tiny bright LEDs on tables and cabinets."""
        rng = self.rng
        for rect, h in self.tops:
            for _ in range(int(rng.integers(0, 4))):
                kind = str(rng.choice(["vase", "bowl", "ball", "led"], p=[0.35, 0.25, 0.2, 0.2]))
                p = furniture.draw(kind, rng)
                x = rng.uniform(rect[0] + 0.15, max(rect[0] + 0.15, rect[2] - 0.15))
                z = rng.uniform(rect[1] + 0.15, max(rect[1] + 0.15, rect[3] - 0.15))
                light = None
                if kind == "led":
                    tint = materials.blackbody_rgb(float(rng.uniform(2700, 6500)))
                    if rng.random() < 0.3:
                        tint = textures.random_color(rng, 0.2, 1.0) * 2
                    light = {
                        "radiance": float(np.exp(rng.uniform(np.log(200), np.log(5000)))),
                        "color": tint.tolist(),
                        "on": True,
                    }
                self.add(kind, p, _transform(rng.uniform(0, 2 * np.pi), [x, h, z]), light)


def furnish(rng: np.random.Generator, layout: dict, palette: dict, mode: str) -> Furnisher:
    """Furniture, pictures, lamps and props for every space of `layout`, materials drawn from
    `palette` (role -> material indices); evening and night scenes get a lamp that is on."""
    f = Furnisher(rng, layout, palette, mode)
    if layout["kind"] == "courtyard":
        for x, z in architecture.column_positions(layout):
            r = layout["colonnade"]["column"]["r"] * 1.3
            f.blockers.append({"rect": [x - r, z - r, x + r, z + r], "y": [0.0, 10.0]})
        if rng.random() < 0.5:
            f.group(0)
        for kind, n in (("bench", int(rng.integers(1, 4))), ("plant", int(rng.integers(2, 7)))):
            for _ in range(n):
                p = furniture.draw(kind, rng)
                if kind == "plant":
                    p["h"], p["pot"] = p["h"] * 1.5, p["pot"] * 1.8
                f.on_wall(0, kind, p)
        f.props()
        return f
    for si, space in enumerate(layout["spaces"]):
        if space["kind"] == "corridor":
            for kind in rng.choice(
                ["cabinet", "plant", "bookcase", "picture"], int(rng.integers(1, 4))
            ):
                f.picture(si) if kind == "picture" else f.on_wall(si, str(kind))
            f.pendant(si)
            continue
        big = ["sofa", "bed", "bookcase", "bookcase", "cabinet", "cabinet"]
        for kind in rng.choice(big, int(rng.integers(1, 4)), replace=False):
            f.on_wall(si, str(kind))
        if rng.random() < 0.8:
            f.group(si)
        for kind in ("plant", "plant", "floor_lamp"):
            if rng.random() < 0.5:
                f.on_wall(si, kind, light=f.lamp_light() if kind == "floor_lamp" else None)
        for _ in range(int(rng.integers(1, 5))):
            f.picture(si)
        for _ in range(int(rng.integers(1, 3))):
            f.pendant(si)
    if mode in ("evening", "night") and not any(
        "light" in p and p["light"]["on"] and p["kind"] != "led" for p in f.pieces
    ):
        f.pendant(0, force_on=True)
    f.props()
    return f


def camera_clear(desc: dict, points: np.ndarray) -> np.ndarray:
    """Which points (N, 3) are valid camera positions: inside a space (0.35 m from walls,
    floor and ceiling) and 0.3 m away from every piece of furniture and lamp."""
    ok = architecture.inside(desc["layout"], points, 0.35)
    for b in desc["blockers"]:
        x0, z0, x1, z1 = b["rect"]
        m = 0.3
        ok &= ~(
            (points[:, 0] > x0 - m)
            & (points[:, 0] < x1 + m)
            & (points[:, 2] > z0 - m)
            & (points[:, 2] < z1 + m)
            & (points[:, 1] > b["y"][0] - m)
            & (points[:, 1] < b["y"][1] + m)
        )
    return ok


# ---------------------------------------------------------------------------------------------
# Moving objects


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    a = axis / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def mover(rng: np.random.Generator, desc: dict, f: Furnisher, cams: list[Camera]) -> dict | None:
    """A ball rolling or a chair sliding across the floor in view of the first frame, clear of
    furniture, walls and every camera position."""
    kind = "ball" if rng.random() < 0.6 else "chair"
    p = furniture.draw(kind, rng)
    if kind == "ball":
        p["r"] = float(rng.uniform(0.08, 0.2))
    fw, fd, _ = furniture.footprint(kind, p)
    rad = max(fw, fd) / 2
    left, _, fwd = cams[0].basis()
    flat = np.array([fwd[0], 0, fwd[2]]) / max(np.hypot(fwd[0], fwd[2]), 1e-6)
    side = np.array([left[0], 0, left[2]]) / max(np.hypot(left[0], left[2]), 1e-6)
    n = len(cams)
    for _ in range(40):
        start = (
            np.asarray(cams[0].origin) * [1, 0, 1]
            + flat * rng.uniform(1.5, 3.5)
            + side * rng.uniform(-1, 1)
        )
        a = rng.uniform(0, 2 * np.pi)
        v = np.array([np.cos(a), 0, np.sin(a)]) * rng.uniform(0.02, 0.07)
        spin = rng.uniform(-0.06, 0.06)
        theta0 = rng.uniform(0, 2 * np.pi)
        frames, ok = [], True
        for k in range(n):
            pos = start + v * k
            rect = [pos[0] - rad, pos[2] - rad, pos[0] + rad, pos[2] + rad]
            si = architecture.space_of(desc["layout"], pos)
            cam = np.asarray(cams[k].origin)
            if si < 0 or not _within(rect, desc["layout"]["spaces"][si], 0.05) or not f.free(rect):
                ok = False
                break
            if np.hypot(*(cam - pos)[[0, 2]]) < rad + 0.6:
                ok = False
                break
            if kind == "ball":  # rolling without slipping: angle = distance / radius
                r = p["r"]
                m = np.eye(4)
                m[:3, :3] = _rotation(np.cross(Y_UP, v), np.linalg.norm(v) * k / r)
                centre = np.eye(4)
                centre[:3, 3] = pos + [0, r, 0]
                back = np.eye(4)
                back[1, 3] = -r
                frames.append((centre @ m @ back).tolist())
            else:
                frames.append(_transform(theta0 + spin * k, pos).tolist())
        if ok:
            piece = {"kind": kind, "params": p, "frames": frames, "transform": frames[0]}
            roles = {r for r, _ in furniture.parts(kind, p)}
            piece["materials"] = {r: int(rng.choice(f.palette[r])) for r in sorted(roles)}
            return piece
    return None
