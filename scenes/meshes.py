"""Procedural triangle meshes in numpy (no asset files ship with quietframe).

Every builder returns a `MeshData` in object space, roughly centred at the origin and with
smooth or flat vertex normals and a UV parameterisation, so procedural textures can be applied.
`to_mitsuba` turns one into a `mi.Mesh` once the scene generator has placed it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class MeshData:
    positions: np.ndarray  # (V, 3) float32
    normals: np.ndarray  # (V, 3) float32, unit length
    uvs: np.ndarray  # (V, 2) float32
    faces: np.ndarray  # (F, 3) uint32, counter-clockwise seen from the normal side

    def transformed(self, matrix: np.ndarray) -> MeshData:
        """Apply a 4x4 affine transform; normals use the inverse transpose."""
        lin, shift = matrix[:3, :3], matrix[:3, 3]
        normals = self.normals @ np.linalg.inv(lin)
        normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
        flip = np.linalg.det(lin) < 0  # mirroring turns the winding inside out
        faces = self.faces[:, ::-1] if flip else self.faces
        return MeshData(
            (self.positions @ lin.T + shift).astype(np.float32),
            normals.astype(np.float32),
            self.uvs,
            np.ascontiguousarray(faces),
        )

    def bounding_radius(self) -> float:
        return float(np.linalg.norm(self.positions, axis=1).max())


def merge(meshes: list[MeshData]) -> MeshData:
    offsets = np.cumsum([0] + [len(m.positions) for m in meshes[:-1]])
    return MeshData(
        np.concatenate([m.positions for m in meshes]).astype(np.float32),
        np.concatenate([m.normals for m in meshes]).astype(np.float32),
        np.concatenate([m.uvs for m in meshes]).astype(np.float32),
        np.concatenate([m.faces + o for m, o in zip(meshes, offsets, strict=True)]).astype(
            np.uint32
        ),
    )


def _grid_faces(rows: int, cols: int) -> np.ndarray:
    """Two triangles per cell of a (rows+1) x (cols+1) vertex grid (row-major)."""
    stride = cols + 1
    r, c = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
    a = r * stride + c
    b = a + 1
    d = a + stride
    e = d + 1
    tris = np.stack([np.stack([a, d, b], -1), np.stack([b, d, e], -1)], axis=2)
    return tris.reshape(-1, 3).astype(np.uint32)


def _parametric(fn, rows: int, cols: int) -> MeshData:
    """Mesh a parametric surface fn(u, v) -> (positions, normals) on [0,1]^2."""
    u, v = np.meshgrid(np.linspace(0, 1, cols + 1), np.linspace(0, 1, rows + 1))
    pos, nrm = fn(u, v)
    uvs = np.stack([u, v], -1).reshape(-1, 2)
    nrm = nrm.reshape(-1, 3)
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    return orient(
        MeshData(
            pos.reshape(-1, 3).astype(np.float32),
            nrm.astype(np.float32),
            uvs.astype(np.float32),
            _grid_faces(rows, cols),
        )
    )


def quad(width: float = 2.0, height: float = 2.0) -> MeshData:
    """Rectangle in the XY plane facing +Z."""
    x, y = width / 2, height / 2
    pos = np.array([[-x, -y, 0], [x, -y, 0], [x, y, 0], [-x, y, 0]], np.float32)
    nrm = np.tile(np.array([[0, 0, 1]], np.float32), (4, 1))
    uvs = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32) * [width, height]
    return MeshData(pos, nrm, uvs.astype(np.float32), np.array([[0, 1, 2], [0, 2, 3]], np.uint32))


def uv_sphere(radius: float = 1.0, rows: int = 24, cols: int = 48) -> MeshData:
    def fn(u, v):
        theta, phi = v * np.pi, u * 2 * np.pi
        n = np.stack(
            [np.sin(theta) * np.cos(phi), -np.cos(theta), -np.sin(theta) * np.sin(phi)], -1
        )
        return n * radius, n

    return _parametric(fn, rows, cols)


def torus(major: float = 1.0, minor: float = 0.3, rows: int = 24, cols: int = 48) -> MeshData:
    def fn(u, v):
        phi, theta = u * 2 * np.pi, v * 2 * np.pi
        ring = np.stack([np.cos(phi), np.zeros_like(phi), -np.sin(phi)], -1)
        n = ring * np.cos(theta)[..., None] + np.array([0, 1, 0]) * np.sin(theta)[..., None]
        return ring * major + n * minor, n

    return _parametric(fn, rows, cols)


def cylinder(
    radius: float = 1.0, height: float = 2.0, cols: int = 32, caps: bool = True
) -> MeshData:
    """Y-axis cylinder centred at the origin."""

    def side(u, v):
        phi = u * 2 * np.pi
        n = np.stack([np.cos(phi), np.zeros_like(phi), -np.sin(phi)], -1)
        p = n * radius
        p[..., 1] = (v - 0.5) * height
        return p, n

    parts = [_parametric(side, 1, cols)]
    if caps:
        for sign in (1.0, -1.0):
            phi = np.linspace(0, 2 * np.pi, cols, endpoint=False)
            rim = np.stack(
                [np.cos(phi) * radius, np.full(cols, sign * height / 2), -np.sin(phi) * radius], -1
            )
            pos = np.concatenate([[[0, sign * height / 2, 0]], rim]).astype(np.float32)
            nrm = np.tile(np.array([[0, sign, 0]], np.float32), (cols + 1, 1))
            uvs = (pos[:, [0, 2]] / (2 * radius) + 0.5).astype(np.float32)
            i = np.arange(cols)
            tri = np.stack([np.zeros(cols, int), 1 + i, 1 + (i + 1) % cols], -1)
            parts.append(orient(MeshData(pos, nrm, uvs, tri.astype(np.uint32))))
    return merge(parts)


def box(size: tuple[float, float, float] = (2.0, 2.0, 2.0)) -> MeshData:
    """Axis-aligned box with flat faces (24 vertices, so normals stay sharp)."""
    half = np.asarray(size, np.float64) / 2
    faces = []
    for axis in range(3):
        for sign in (1.0, -1.0):
            a, b = (axis + 1) % 3, (axis + 2) % 3
            basis = np.eye(4)[:, [a, b, axis, 3]]  # quad X->a, Y->b, +Z->outward axis
            basis[:3, 2] *= sign
            basis[axis, 3] = sign * half[axis]
            faces.append(orient(quad(2 * half[a], 2 * half[b]).transformed(basis)))
    return merge(faces)


def orient(m: MeshData) -> MeshData:
    """Make each triangle's winding agree with its vertex normals (Mitsuba derives the
    geometric normal from the winding; emitters and dielectrics need it outward)."""
    p = m.positions[m.faces]
    geo = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    flip = np.sum(geo * m.normals[m.faces].sum(axis=1), axis=1) < 0
    faces = m.faces.copy()
    faces[flip] = faces[flip][:, ::-1]
    return MeshData(m.positions, m.normals, m.uvs, faces)


def rounded_box(
    size: tuple[float, float, float] = (2.0, 2.0, 2.0), radius: float = 0.2, res: int = 12
) -> MeshData:
    """A box with rounded edges: push a subdivided cube onto the offset surface of its core."""
    half = np.asarray(size, np.float64) / 2
    radius = float(min(radius, half.min() * 0.95))
    core = half - radius
    parts = []
    for axis in range(3):
        for sign in (1.0, -1.0):
            a, b = (axis + 1) % 3, (axis + 2) % 3

            def fn(u, v, axis=axis, sign=sign, a=a, b=b):
                p = np.zeros(u.shape + (3,))
                p[..., axis] = sign * half[axis]
                p[..., a] = (u * 2 - 1) * half[a]
                p[..., b] = (v * 2 - 1) * half[b]
                inner = np.clip(p, -core, core)
                d = p - inner
                d /= np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-12)
                return inner + d * radius, d

            parts.append(_parametric(fn, res, res))
    return merge(parts)


def heightfield(
    heights: np.ndarray, size: tuple[float, float] = (2.0, 2.0), amplitude: float = 0.3
) -> MeshData:
    """Displaced grid in XZ (Y up) from a (rows+1, cols+1) height map in [0, 1]."""
    rows, cols = heights.shape[0] - 1, heights.shape[1] - 1
    x = np.linspace(-size[0] / 2, size[0] / 2, cols + 1)
    z = np.linspace(-size[1] / 2, size[1] / 2, rows + 1)
    xx, zz = np.meshgrid(x, z)
    yy = (heights - 0.5) * amplitude
    # Central differences give smooth shading normals of the displaced surface.
    dydx = np.gradient(yy, x, axis=1)
    dydz = np.gradient(yy, z, axis=0)
    nrm = np.stack([-dydx, np.ones_like(yy), -dydz], -1).reshape(-1, 3)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    pos = np.stack([xx, yy, zz], -1).reshape(-1, 3)
    u, v = np.meshgrid(np.linspace(0, 1, cols + 1), np.linspace(0, 1, rows + 1))
    return orient(
        MeshData(
            pos.astype(np.float32),
            nrm.astype(np.float32),
            np.stack([u, v], -1).reshape(-1, 2).astype(np.float32),
            _grid_faces(rows, cols),
        )
    )


def slats(count: int, length: float, width: float, thickness: float, gap: float) -> MeshData:
    """Parallel thin boards along X stacked in Z: blinds, grilles, shelves; fine shadows."""
    span = count * width + (count - 1) * gap
    parts = []
    for i in range(count):
        z = -span / 2 + width / 2 + i * (width + gap)
        t = np.eye(4)
        t[2, 3] = z
        parts.append(box((length, thickness, width)).transformed(t))
    return merge(parts)


def _box_at(size: tuple[float, float, float], center: tuple[float, float, float]) -> MeshData:
    t = np.eye(4)
    t[:3, 3] = center
    return box(size).transformed(t)


def table(width: float, depth: float, height: float, top: float, leg: float) -> MeshData:
    """Slab on four legs, feet at y = -height/2 (the generator rests it on the floor)."""
    y0 = -height / 2
    parts = [_box_at((width, top, depth), (0, y0 + height - top / 2, 0))]
    for sx in (-1, 1):
        for sz in (-1, 1):
            c = (sx * (width / 2 - leg), y0 + (height - top) / 2, sz * (depth / 2 - leg))
            parts.append(_box_at((leg, height - top, leg), c))
    return merge(parts)


def to_mitsuba(mesh: MeshData, name: str, bsdf, emitter=None):
    """Build a `mi.Mesh` (needs an active variant) with the given BSDF and optional emitter."""
    import mitsuba as mi

    props = mi.Properties()
    props["bsdf"] = bsdf
    if emitter is not None:
        props["emitter"] = emitter
    out = mi.Mesh(
        name,
        len(mesh.positions),
        len(mesh.faces),
        props=props,
        has_vertex_normals=True,
        has_vertex_texcoords=True,
    )
    params = mi.traverse(out)
    params["vertex_positions"] = np.ascontiguousarray(mesh.positions, np.float32).ravel()
    params["vertex_normals"] = np.ascontiguousarray(mesh.normals, np.float32).ravel()
    params["vertex_texcoords"] = np.ascontiguousarray(mesh.uvs, np.float32).ravel()
    params["faces"] = np.ascontiguousarray(mesh.faces, np.uint32).ravel()
    params.update()
    out.set_id(name)
    return out


def lathe(radii: list[float], heights: list[float], cols: int = 32) -> MeshData:
    """Surface of revolution about +Y through the profile (radius, height) points, open at
    both ends: vases, bowls, pots, lamp shades. Normals point away from the axis."""
    r, y = np.asarray(radii, np.float64), np.asarray(heights, np.float64)
    rows = len(r) - 1
    dr, dy = np.gradient(r), np.gradient(y)

    def fn(u, v):
        i = np.rint(v * rows).astype(int)
        ring = np.stack([np.cos(u * 2 * np.pi), np.zeros_like(u), -np.sin(u * 2 * np.pi)], -1)
        pos = ring * r[i][..., None]
        pos[..., 1] = y[i]
        n = ring * dy[i][..., None]  # the profile tangent (dr, dy) turned outwards: (dy, -dr)
        n[..., 1] = -dr[i]
        return pos, n

    return _parametric(fn, rows, cols)


def leaf(length: float, width: float) -> MeshData:
    """A flat pointed leaf in the XZ plane along +X from the origin, facing +Y."""
    pos = np.array(
        [[0, 0, 0], [length * 0.35, 0, width / 2], [length, 0, 0], [length * 0.35, 0, -width / 2]],
        np.float32,
    )
    nrm = np.tile(np.array([[0, 1, 0]], np.float32), (4, 1))
    uvs = (pos[:, [0, 2]] + [0, width / 2]).astype(np.float32)
    return orient(MeshData(pos, nrm, uvs, np.array([[0, 1, 2], [0, 2, 3]], np.uint32)))


def box_at(size: tuple[float, float, float], center: tuple[float, float, float]) -> MeshData:
    """Axis-aligned box of `size` centred at `center`."""
    return _box_at(size, center)


def cylinder_at(radius: float, height: float, base: tuple[float, float, float]) -> MeshData:
    """Y-axis cylinder standing on `base` (its bottom centre)."""
    t = np.eye(4)
    t[:3, 3] = (base[0], base[1] + height / 2, base[2])
    return cylinder(radius, height, cols=16).transformed(t)
