"""Small mesh builders with texture coordinates for the scene recipes (private).

Conventions shared by every builder (world frame: metres, Z up):

* triangles are counter-clockwise seen from the outside, so ``(b - a) x (c - a)`` is the outward
  normal; closed solids (boxes, cylinders with caps, spheres) are watertight once coincident
  vertices are welded (vertices are duplicated along UV seams and at sharp edges only);
* UVs are in *texture tiles*, world-anchored: on a face with outward normal ``n``, ``u`` grows
  to the right as seen from outside (along ``Z x n`` on vertical faces, along ``+X`` on
  horizontal ones) and ``v`` grows upward (``+Z``; ``+Y`` on a top face, ``-Y`` on a bottom face),
  both divided by the tile size in metres. ``uv_box`` instead maps each face once onto a UV
  rectangle (for windows, doors, signs).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = [
    "Part",
    "area_weighted_normals",
    "axis_grid",
    "box",
    "concat",
    "frustum",
    "leaf_cluster",
    "quad",
    "rotation_z",
    "sphere",
]

_UP = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True, eq=False)
class Part:
    """A piece of triangle mesh: vertices (N, 3) float64, triangles (M, 3) int64, uvs (N, 2) float64."""

    vertices: np.ndarray
    triangles: np.ndarray
    uvs: np.ndarray

    def transformed(self, rotation: np.ndarray | None = None, translation: Sequence[float] = (0.0, 0.0, 0.0)) -> Part:
        """The part moved by ``x -> rotation @ x + translation`` (UVs unchanged)."""
        v = self.vertices if rotation is None else self.vertices @ np.asarray(rotation, float).T
        return Part(v + np.asarray(translation, float), self.triangles, self.uvs)

    @property
    def face_normals(self) -> np.ndarray:
        """Unit face normals, (M, 3) float64."""
        a, b, c = (self.vertices[self.triangles[:, i]] for i in range(3))
        n = np.cross(b - a, c - a)
        return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


def area_weighted_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals of a mesh, (N, 3) float64; +Z for a vertex used only by
    zero-area faces (or by none)."""
    a, b, c = (vertices[triangles[:, i]] for i in range(3))
    face = np.cross(b - a, c - a)
    normals = np.zeros_like(vertices, dtype=np.float64)
    for i in range(3):
        np.add.at(normals, triangles[:, i], face)
    length = np.linalg.norm(normals, axis=1)
    bad = length < 1e-15
    normals[bad] = _UP
    length[bad] = 1.0
    return normals / length[:, None]


def concat(parts: Sequence[Part]) -> Part:
    """Concatenate parts into one (triangle indices offset)."""
    parts = [p for p in parts if len(p.triangles)]
    if not parts:
        return Part(np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros((0, 2)))
    offsets = np.cumsum([0] + [len(p.vertices) for p in parts[:-1]])
    return Part(
        np.concatenate([p.vertices for p in parts]),
        np.concatenate([p.triangles + o for p, o in zip(parts, offsets, strict=True)]).astype(np.int64),
        np.concatenate([p.uvs for p in parts]),
    )


def rotation_z(angle: float) -> np.ndarray:
    """Rotation by ``angle`` radians about +Z (counter-clockwise seen from above), (3, 3)."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _face_axes(normal_axis: int, sign: int) -> tuple[np.ndarray, np.ndarray]:
    """(right, up) unit vectors of an axis-aligned face seen from outside (module conventions)."""
    n = np.zeros(3)
    n[normal_axis] = sign
    if normal_axis == 2:
        return np.array([1.0, 0.0, 0.0]), np.array([0.0, float(sign), 0.0])
    return np.cross(_UP, n), _UP.copy()


def axis_grid(
    normal_axis: int,
    sign: int,
    offset: float,
    coords_a: Sequence[float],
    coords_b: Sequence[float],
    *,
    tile: tuple[float, float] = (1.0, 1.0),
    keep: np.ndarray | None = None,
    uv_box: tuple[float, float, float, float] | None = None,
) -> Part:
    """An axis-aligned planar grid of quads, facing ``sign * e[normal_axis]``.

    Parameters
    ----------
    normal_axis : {0, 1, 2}
        World axis of the face normal.
    sign : {-1, +1}
        Direction of the outward normal along that axis.
    offset : float
        Coordinate of the plane along ``normal_axis``, metres.
    coords_a, coords_b : sequence of float
        Increasing grid-line coordinates along the two other world axes, in increasing axis order
        (``(y, z)`` for an X face, ``(x, z)`` for a Y face, ``(x, y)`` for a Z face), metres.
    tile : (float, float), optional
        Size of one texture tile along the face's ``u`` and ``v``, metres.
    keep : (len(coords_a) - 1, len(coords_b) - 1) bool, optional
        Which cells to emit (holes are cells left out).
    uv_box : (u0, v0, u1, v1), optional
        Map the whole grid once onto this UV rectangle instead of world-anchored tiles.
    """
    axes = [i for i in range(3) if i != normal_axis]
    a, b = np.asarray(coords_a, float), np.asarray(coords_b, float)
    na, nb = len(a), len(b)
    grid = np.zeros((na, nb, 3))
    grid[..., normal_axis] = offset
    grid[..., axes[0]] = a[:, None]
    grid[..., axes[1]] = b[None, :]
    vertices = grid.reshape(-1, 3)
    right, up = _face_axes(normal_axis, sign)
    ru = vertices @ right
    rv = vertices @ up
    if uv_box is None:
        uvs = np.stack([ru / tile[0], rv / tile[1]], axis=1)
    else:
        u0, v0, u1, v1 = uv_box
        su = (ru - ru.min()) / max(np.ptp(ru), 1e-12)
        sv = (rv - rv.min()) / max(np.ptp(rv), 1e-12)
        uvs = np.stack([u0 + (u1 - u0) * su, v0 + (v1 - v0) * sv], axis=1)
    i, j = np.meshgrid(np.arange(na - 1), np.arange(nb - 1), indexing="ij")
    if keep is not None:
        keep = np.asarray(keep, bool)
        i, j = i[keep], j[keep]
    i, j = i.ravel(), j.ravel()
    v00, v10, v11, v01 = i * nb + j, (i + 1) * nb + j, (i + 1) * nb + j + 1, i * nb + j + 1
    triangles = np.concatenate([np.stack([v00, v10, v11], 1), np.stack([v00, v11, v01], 1)])
    # (e_a x e_b) is +e_normal for the cyclic axis order; flip when the face looks the other way.
    e_a, e_b = np.eye(3)[axes[0]], np.eye(3)[axes[1]]
    if np.cross(e_a, e_b)[normal_axis] * sign < 0:
        triangles = triangles[:, [0, 2, 1]]
    return _compact(Part(vertices, triangles.astype(np.int64), uvs))


def _compact(part: Part) -> Part:
    """Drop the vertices no triangle uses (renumbering the triangles)."""
    used = np.zeros(len(part.vertices), bool)
    used[part.triangles.ravel()] = True
    if used.all():
        return part
    index = np.cumsum(used) - 1
    return Part(part.vertices[used], index[part.triangles].astype(np.int64), part.uvs[used])


def quad(
    origin: Sequence[float],
    edge_u: Sequence[float],
    edge_v: Sequence[float],
    *,
    uv_box: tuple[float, float, float, float] = (0.0, 0.0, 1.0, 1.0),
) -> Part:
    """A parallelogram ``origin + s edge_u + t edge_v`` (s, t in [0, 1]) facing ``edge_u x edge_v``.

    UVs map ``(s, t)`` linearly onto ``uv_box = (u0, v0, u1, v1)``.
    """
    o, eu, ev = (np.asarray(x, float) for x in (origin, edge_u, edge_v))
    vertices = np.array([o, o + eu, o + eu + ev, o + ev])
    u0, v0, u1, v1 = uv_box
    uvs = np.array([[u0, v0], [u1, v0], [u1, v1], [u0, v1]], float)
    return Part(vertices, np.array([[0, 1, 2], [0, 2, 3]], np.int64), uvs)


def box(
    lo: Sequence[float],
    hi: Sequence[float],
    *,
    tile: tuple[float, float] = (1.0, 1.0),
    lines: tuple[Sequence[float], Sequence[float], Sequence[float]] | None = None,
    front_keep: np.ndarray | None = None,
    uv_box: tuple[float, float, float, float] | None = None,
    faces: str = "xXyYzZ",
) -> Part:
    """An axis-aligned box ``[lo, hi]`` with outward-facing triangles and per-face UVs.

    Parameters
    ----------
    lo, hi : (3,) float
        Opposite corners, metres.
    tile : (float, float), optional
        Texture tile size (u, v) in metres (world-anchored UVs).
    lines : (xs, ys, zs), optional
        Increasing grid lines (including ``lo`` and ``hi``) along each axis; every face is split
        along them so that faces share vertices with anything built on the same lines (e.g. the
        reveals of holes cut in the front face).
    front_keep : bool array, optional
        Cells of the front (``-Y``) face to keep, shape ``(len(xs) - 1, len(zs) - 1)``.
    uv_box : (u0, v0, u1, v1), optional
        Map every face once onto this UV rectangle.
    faces : str, optional
        Which faces to emit: ``x``/``X`` for -X/+X, ``y``/``Y``, ``z``/``Z``.
    """
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    if lines is None:
        lines = tuple([lo[k], hi[k]] for k in range(3))
    xs, ys, zs = (np.asarray(l_, float) for l_ in lines)
    coords = {0: (ys, zs), 1: (xs, zs), 2: (xs, ys)}
    parts = []
    for letter, axis, sign, value in (
        ("x", 0, -1, lo[0]),
        ("X", 0, 1, hi[0]),
        ("y", 1, -1, lo[1]),
        ("Y", 1, 1, hi[1]),
        ("z", 2, -1, lo[2]),
        ("Z", 2, 1, hi[2]),
    ):
        if letter not in faces:
            continue
        keep = front_keep if letter == "y" else None
        parts.append(axis_grid(axis, sign, value, *coords[axis], tile=tile, keep=keep, uv_box=uv_box))
    return concat(parts)


def _frame(axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors (e1, e2) with (e1, e2, axis) right-handed."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(helper, axis)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(axis, e1)


def frustum(
    p0: Sequence[float],
    p1: Sequence[float],
    r0: float,
    r1: float,
    *,
    segments: int = 16,
    caps: bool = True,
    tile: tuple[float, float] = (1.0, 1.0),
) -> Part:
    """A (truncated) cone from ``p0`` (radius ``r0``) to ``p1`` (radius ``r1``), metres.

    ``r0 == r1`` gives a cylinder. UVs: ``u`` = arc length around the axis (at the mean radius),
    ``v`` = distance along the axis, both in tiles; caps get planar world-scaled UVs. With
    ``caps`` the solid is closed.
    """
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    axis = p1 - p0
    length = np.linalg.norm(axis)
    axis = axis / length
    e1, e2 = _frame(axis)
    n = int(segments)
    theta = np.linspace(0.0, 2.0 * np.pi, n + 1)  # seam duplicated for the UVs
    ring = np.cos(theta)[:, None] * e1 + np.sin(theta)[:, None] * e2
    bottom, top = p0 + r0 * ring, p1 + r1 * ring
    vertices = np.concatenate([bottom, top])
    u = theta * 0.5 * (r0 + r1) / tile[0]
    uvs = np.concatenate([np.stack([u, np.zeros_like(u)], 1), np.stack([u, np.full_like(u, length / tile[1])], 1)])
    k = np.arange(n)
    b0, b1, t0, t1 = k, k + 1, k + n + 1, k + n + 2
    # Counter-clockwise around the axis (e1 -> e2): (b0, b1, t1) faces outward. A zero radius
    # (cone apex) drops the triangles that would be degenerate there.
    sides = []
    if r0 > 0:
        sides.append(np.stack([b0, b1, t1], 1))
    if r1 > 0:
        sides.append(np.stack([b0, t1, t0], 1))
    triangles = np.concatenate(sides)
    parts = [Part(vertices, triangles.astype(np.int64), uvs)]
    if caps:
        for centre, radius, points, outward in ((p0, r0, bottom, -1), (p1, r1, top, 1)):
            if radius <= 0:
                continue
            cv = np.concatenate([centre[None], points[:-1]])
            local = (points[:-1] - centre) @ np.stack([e1, e2], 1)
            cuv = np.concatenate([[[0.0, 0.0]], local / np.asarray(tile)])
            kk = np.arange(n)
            tri = np.stack([np.zeros(n, int), 1 + kk, 1 + (kk + 1) % n], 1)
            if outward < 0:
                tri = tri[:, [0, 2, 1]]
            parts.append(Part(cv, tri.astype(np.int64), cuv))
    return _compact(concat(parts))


def sphere(
    center: Sequence[float],
    radius: float,
    *,
    rings: int = 12,
    segments: int = 24,
    tile: tuple[float, float] = (1.0, 1.0),
) -> Part:
    """A closed UV sphere (triangle fans at the poles), outward-facing.

    UVs: ``u`` = arc length along the equator direction, ``v`` = arc length from the south pole,
    in tiles.
    """
    c = np.asarray(center, float)
    phi = np.linspace(0.0, np.pi, rings + 1)[1:-1]  # from the north pole, poles excluded
    theta = np.linspace(0.0, 2.0 * np.pi, segments + 1)
    pp, tt = np.meshgrid(phi, theta, indexing="ij")
    dirs = np.stack([np.sin(pp) * np.cos(tt), np.sin(pp) * np.sin(tt), np.cos(pp)], -1).reshape(-1, 3)
    vertices = [c + radius * dirs]
    uv = np.stack([tt * radius / tile[0], (np.pi - pp) * radius / tile[1]], -1).reshape(-1, 2)
    uvs = [uv]
    n_ring = segments + 1
    tris = []
    for r in range(rings - 2):
        k = np.arange(segments)
        a, b = r * n_ring + k, r * n_ring + k + 1
        c_, d = (r + 1) * n_ring + k + 1, (r + 1) * n_ring + k
        # Rows go north to south, theta counter-clockwise seen from above: (a, d, c) faces out.
        tris += [np.stack([a, d, c_], 1), np.stack([a, c_, b], 1)]
    base = len(uv)
    poles_v, poles_uv, k = [], [], np.arange(segments)
    for idx, (z, ring_row) in enumerate(((1.0, 0), (-1.0, rings - 2))):
        pv = c + radius * np.array([0.0, 0.0, z])
        start = base + idx * segments
        poles_v.append(np.repeat(pv[None], segments, 0))
        poles_uv.append(
            np.stack(
                [
                    (theta[:-1] + np.pi / segments) * radius / tile[0],
                    np.full(segments, (np.pi if z > 0 else 0.0) * radius / tile[1]),
                ],
                1,
            )
        )
        a, b = ring_row * n_ring + k, ring_row * n_ring + k + 1
        p = start + k
        tris.append(np.stack([p, a, b], 1) if z > 0 else np.stack([p, b, a], 1))
    vertices += poles_v
    uvs += poles_uv
    return Part(np.concatenate(vertices), np.concatenate(tris).astype(np.int64), np.concatenate(uvs))


def leaf_cluster(
    rng: np.random.Generator,
    center: Sequence[float],
    radius: float,
    count: int,
    *,
    size: tuple[float, float] = (0.16, 0.10),
    squash: float = 0.8,
    uv_window: float = 0.15,
) -> Part:
    """``count`` small diamond-shaped leaves scattered in an ellipsoidal blob.

    Parameters
    ----------
    rng : numpy.random.Generator
        Source of randomness (positions, orientations, sizes, UV windows).
    center : (3,) float
        Blob centre, metres.
    radius : float
        Horizontal radius of the blob, metres (vertical radius ``squash * radius``).
    count : int
        Number of leaves (2 triangles each).
    size : (float, float), optional
        Mean leaf length and width, metres (each leaf is scaled by a factor in [0.7, 1.3]).
    squash : float, optional
        Vertical / horizontal radius ratio.
    uv_window : float, optional
        Each leaf maps a random ``uv_window x uv_window`` window of the leaf texture.

    Notes
    -----
    Positions are uniform in the volume with a bias toward the surface (real crowns hold most
    leaves in their outer shell), which leaves gaps for dappled sunlight. Normals mix the outward
    radial direction with a random one; leaves are single-sided quads meant for a two-sided
    material.
    """
    c = np.asarray(center, float)
    d = rng.standard_normal((count, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = radius * rng.uniform(0.0, 1.0, count) ** 0.25  # density grows toward the shell
    pos = c + d * r[:, None] * np.array([1.0, 1.0, squash])
    normal = 0.8 * d + rng.standard_normal((count, 3)) * 0.7 + np.array([0.0, 0.0, 0.4])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    helper = rng.standard_normal((count, 3))
    a = np.cross(normal, helper)
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b = np.cross(normal, a)
    scale = rng.uniform(0.7, 1.3, count)[:, None]
    half_l, half_w = 0.5 * size[0] * scale, 0.5 * size[1] * scale
    # Diamond -a, -b, +a, +b: counter-clockwise about the normal (b = n x a).
    corners = np.stack([pos - a * half_l, pos - b * half_w, pos + a * half_l, pos + b * half_w], 1)
    uc = rng.uniform(0.0, 1.0, (count, 2))
    h = 0.5 * uv_window
    offsets = np.array([[-h, 0.0], [0.0, -h], [h, 0.0], [0.0, h]])
    uvs = uc[:, None, :] + offsets[None]
    base = 4 * np.arange(count)[:, None]
    triangles = np.concatenate([base + [0, 1, 2], base + [0, 2, 3]], 1).reshape(-1, 3)
    return Part(corners.reshape(-1, 3), triangles.astype(np.int64), uvs.reshape(-1, 2))
