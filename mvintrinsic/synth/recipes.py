"""Procedural scene recipes for the synthetic ground truth (edge layer).

A recipe builds a :class:`~mvintrinsic.synth.types.SynthScene`: textured triangle meshes,
their materials, a camera path and named marker points. The scenes imitate the outdoor scenes
of Duchêne et al. 2015 (Sec. 9.3 evaluates on rendered scenes with known reflectance and
shading): facades with windows and doors, paving and grass, a tree whose foliage casts *dappled*
shadows, and thin structures (lamp pole, fence, pergola) that multi-view stereo loses.

World frame: right-handed, metres, Z up (:mod:`mvintrinsic.synth.types`). The sun is not part
of a recipe; the renderer chooses it.

Geometry conventions (see :mod:`mvintrinsic.synth._geometry`): triangles are counter-clockwise
seen from outside; closed solids (buildings, boxes, cylinders, the statue parts) are watertight
once coincident vertices are welded; UVs are world-anchored texture tiles with ``v`` up on
vertical faces, so a recipe picks the physical tile size of each texture (``_TILE``).
Objects standing on the ground sink 2 cm into it, so no face is coplanar with the ground.

Labels (:data:`~mvintrinsic.synth.types.LABELS`): ``"ground"`` for the ground, ``"solid"`` for
buildings and bulky objects, ``"foliage"`` for leaves, ``"thin"`` for poles, pickets, rails,
beams and branches.
"""

from __future__ import annotations

import zlib
from collections.abc import Callable, Sequence
from functools import partial

import numpy as np

from . import textures as tex
from ._geometry import Part, axis_grid, box, concat, frustum, leaf_cluster, rotation_z, sphere
from .types import Material, SynthMesh, SynthScene, ViewPath

__all__ = ["GLOSS_ROUGHNESS", "RECIPES", "build_scene", "courtyard", "street"]

#: Texture tile sizes (u, v) in metres, matching the tile each texture function documents.
_TILE = {
    "brick": (1.0, 0.9),
    "paving": (2.0, 2.0),
    "plaster": (4.0, 4.0),
    "grass": (1.0, 1.0),
    "meadow": (4.0, 4.0),
    "bark": (0.5, 1.0),
    "wood": (0.5, 1.0),
    "stone": (1.0, 1.0),
    "metal": (0.5, 0.5),
    "asphalt": (2.0, 2.0),
}

#: GGX roughness given to the few glossy materials when ``gloss=True`` (mild gloss).
GLOSS_ROUGHNESS = 0.3

#: Objects standing on the ground start this far below it (metres): no face coplanar with it.
_SINK = 0.02

#: Half-size of the detailed ground square and radius of the far ground ring, metres.
_GROUND_HALF = 15.0
_FAR_RADIUS = 600.0


# -- scene assembly ------------------------------------------------------------------------------
class _Builder:
    """Collects meshes, materials and markers; derives independent random streams per purpose."""

    def __init__(self, recipe: str, seed: int, gloss: bool) -> None:
        self.recipe, self.seed, self.gloss = recipe, seed, gloss
        self.meshes: list[SynthMesh] = []
        self.materials: dict[str, Material] = {}
        self.markers: dict[str, np.ndarray] = {}

    def rng(self, key: str) -> np.random.Generator:
        """A generator that depends on the seed and on ``key`` only (stable across edits)."""
        return np.random.default_rng([self.seed, zlib.crc32(key.encode())])

    def material(
        self, name: str, texture: Callable[..., np.ndarray], *, glossy: bool = False, two_sided: bool = False
    ) -> str:
        """Add a material whose albedo is ``texture(rng)`` (options bound with functools.partial)."""
        albedo = texture(self.rng("texture/" + name))
        roughness = GLOSS_ROUGHNESS if (glossy and self.gloss) else None
        self.materials[name] = Material(name, albedo, roughness=roughness, two_sided=two_sided)
        return name

    def add(self, name: str, part: Part, material: str, label: str) -> None:
        # Fresh C-contiguous arrays, left writeable: open3d's Vector3dVector and mitsuba.Bitmap
        # refuse read-only numpy arrays.
        self.meshes.append(
            SynthMesh(
                name=name,
                vertices=np.array(part.vertices, dtype=np.float64, order="C"),
                triangles=np.array(part.triangles, dtype=np.int64, order="C"),
                uvs=np.array(part.uvs, dtype=np.float32, order="C"),
                material=material,
                label=label,
            )
        )

    def mark(self, name: str, point: Sequence[float]) -> None:
        self.markers[name] = np.array(point, dtype=np.float64)

    def mark_all(self, markers: dict[str, Sequence[float]]) -> None:
        for name, point in markers.items():
            self.mark(name, point)

    def add_tree(self, base: np.ndarray, bark: str, leaves: str, **shape: float) -> None:
        """Trunk (solid), branches (thin) and leaves (foliage) of :func:`_tree`, with its markers."""
        trunk, branches, foliage, markers = _tree(self.rng("tree"), base, **shape)
        self.add("tree_trunk", trunk, bark, "solid")
        self.add("tree_branches", branches, bark, "thin")
        self.add("tree_leaves", foliage, leaves, "foliage")
        self.mark_all(markers)

    def scene(self, path: ViewPath) -> SynthScene:
        return SynthScene(self.recipe, self.seed, self.meshes, self.materials, path, self.markers)


def _path(center: Sequence[float], direction: Sequence[float], target: Sequence[float]) -> ViewPath:
    c, d, t = (np.array(x, dtype=np.float64) for x in (center, direction, target))
    return ViewPath(c, d / np.linalg.norm(d), t)


# -- ground ----------------------------------------------------------------------------------------
def _ground_cells() -> np.ndarray:
    """Grid lines of the 1 m ground square, metres."""
    n = int(2 * _GROUND_HALF)
    return np.linspace(-_GROUND_HALF, _GROUND_HALF, n + 1)


def _ground(cell_material: Callable[[float, float], int], n_materials: int, tiles) -> list[Part]:
    """The ground square split by material: ``cell_material(x, y)`` of each 1 m cell's centre."""
    lines = _ground_cells()
    centres = 0.5 * (lines[1:] + lines[:-1])
    which = np.array([[cell_material(x, y) for y in centres] for x in centres])
    return [axis_grid(2, 1, 0.0, lines, lines, tile=tiles[k], keep=which == k) for k in range(n_materials)]


def _far_ground(*, rings: int = 12) -> Part:
    """Annulus from the 1 m-sampled border of the ground square out to a circle of ``_FAR_RADIUS``.

    The inner boundary uses the same vertices as the square's border (watertight seam); rings
    are spaced geometrically, so the triangles grow with the distance. The ground extends far
    enough that the horizon seen from the cameras (1.7 m high) is 0.16 degrees below the
    geometric horizon: there is no hard edge of the world in view.
    """
    lines = _ground_cells()
    h = _GROUND_HALF
    # Counter-clockwise border (seen from above), without repeating corners.
    border = np.concatenate(
        [
            np.stack([lines[:-1], np.full(len(lines) - 1, -h)], 1),
            np.stack([np.full(len(lines) - 1, h), lines[:-1]], 1),
            np.stack([lines[::-1][:-1], np.full(len(lines) - 1, h)], 1),
            np.stack([np.full(len(lines) - 1, -h), lines[::-1][:-1]], 1),
        ]
    )
    r0 = np.linalg.norm(border, axis=1)
    k = np.arange(rings + 1)[:, None]
    radii = r0[None] * (_FAR_RADIUS / r0[None]) ** (k / rings)  # (rings + 1, n)
    pts = border[None] / r0[None, :, None] * radii[..., None]
    n = len(border)
    vertices = np.concatenate([pts.reshape(-1, 2), np.zeros((pts.size // 2, 1))], 1)
    i = np.arange(n)
    tris = []
    for ring in range(rings):
        a, b = ring * n + i, ring * n + (i + 1) % n
        c, d = (ring + 1) * n + (i + 1) % n, (ring + 1) * n + i
        # a -> b runs counter-clockwise and a -> d outward, so (b - a) x (d - a) points down:
        # (a, c, b) and (a, d, c) face up.
        tris += [np.stack([a, c, b], 1), np.stack([a, d, c], 1)]
    tile = _TILE["meadow"]
    uvs = vertices[:, :2] / np.asarray(tile)
    return Part(vertices, np.concatenate(tris).astype(np.int64), uvs)


# -- buildings -------------------------------------------------------------------------------------
def _building(
    width: float,
    depth: float,
    height: float,
    openings: Sequence[tuple[float, float, float, float, str]],
    *,
    wall_tile: tuple[float, float],
    recess: float = 0.18,
    door_recess: float = 0.25,
) -> dict[str, Part]:
    """A closed box building in its local frame: front face at ``y = 0`` facing ``-Y``.

    The box spans ``x`` in ``[0, width]``, ``y`` in ``[0, depth]``, ``z`` in ``[-_SINK, height]``.
    ``openings`` are ``(x0, x1, z0, z1, kind)`` rectangles on the front face, ``kind`` "window"
    or "door"; each is a recess (``recess`` / ``door_recess`` metres deep) lined with reveals and
    closed by a pane at its back. All faces are split along the same grid lines, so the union of
    ``"wall"``, ``"reveals"``, ``"glass"`` and ``"door"`` is a closed, consistently oriented
    surface. ``"sills"`` holds protruding stone sills below the windows and a step before the
    door (separate closed boxes).
    """
    xs = np.unique(np.concatenate([[0.0, width], [o[0] for o in openings], [o[1] for o in openings]]))
    zs = np.unique(np.concatenate([[-_SINK, height], [o[2] for o in openings], [o[3] for o in openings]]))
    ys = np.array([0.0, depth])
    xc, zc = 0.5 * (xs[1:] + xs[:-1]), 0.5 * (zs[1:] + zs[:-1])
    keep = np.ones((len(xc), len(zc)), bool)
    for x0, x1, z0, z1, _ in openings:
        keep &= ~(((xc > x0) & (xc < x1))[:, None] & ((zc > z0) & (zc < z1))[None, :])
    wall = box((0.0, 0.0, -_SINK), (width, depth, height), tile=wall_tile, lines=(xs, ys, zs), front_keep=keep)
    reveals, glass, doors, sills = [], [], [], []
    stone = _TILE["stone"]
    for x0, x1, z0, z1, kind in openings:
        d = door_recess if kind == "door" else recess
        xi = xs[(xs >= x0) & (xs <= x1)]
        zi = zs[(zs >= z0) & (zs <= z1)]
        reveals += [
            axis_grid(0, 1, x0, [0.0, d], zi, tile=stone),
            axis_grid(0, -1, x1, [0.0, d], zi, tile=stone),
            axis_grid(2, 1, z0, xi, [0.0, d], tile=stone),
            axis_grid(2, -1, z1, xi, [0.0, d], tile=stone),
        ]
        pane = axis_grid(1, -1, d, xi, zi, uv_box=(0.0, 0.0, 1.0, 1.0))
        if kind == "door":
            doors.append(pane)
            sills.append(box((x0 - 0.25, -0.45, -_SINK), (x1 + 0.25, 0.0, z0), tile=stone))
        else:
            glass.append(pane)
            sills.append(box((x0 - 0.06, -0.07, z0 - 0.07), (x1 + 0.06, 0.0, z0), tile=stone))
    return {
        "wall": wall,
        "reveals": concat(reveals),
        "glass": concat(glass),
        "door": concat(doors),
        "sills": concat(sills),
    }


def _window_grid(
    columns: Sequence[float], floors: Sequence[tuple[float, float]], width: float
) -> list[tuple[float, float, float, float, str]]:
    """Window openings ``width`` wide centred on ``columns`` (x), one per ``(z0, z1)`` floor."""
    return [(c - width / 2, c + width / 2, z0, z1, "window") for z0, z1 in floors for c in columns]


def _plaque(x0: float, x1: float, z0: float, z1: float, *, thickness: float = 0.03) -> Part:
    """A plaque box on a ``-Y`` facing wall at ``y = 0``: the sign texture on its front face,
    the texture's border colour elsewhere."""
    lo, hi = (x0, -thickness, z0), (x1, 0.0, z1)
    front = box(lo, hi, faces="y", uv_box=(0.0, 0.0, 1.0, 1.0))
    sides = box(lo, hi, faces="xXYzZ", uv_box=(0.0005, 0.0005, 0.001, 0.001))
    return concat([front, sides])


# -- vegetation ------------------------------------------------------------------------------------
def _tree(
    rng: np.random.Generator,
    base: Sequence[float],
    *,
    trunk_height: float = 2.6,
    crown_height: float = 4.6,
    crown_radius: float = 1.9,
    blobs: int = 5,
    leaves: int = 5000,
) -> tuple[Part, Part, Part, dict[str, np.ndarray]]:
    """A stylised deciduous tree: trunk, branches and a crown of leaf blobs.

    Returns ``(trunk, branches, foliage, markers)``. The crown is ``blobs`` spherical leaf
    clusters (radius 1.0-1.4 m) around ``crown_height`` metres, with gaps between and inside
    them so that the sun casts dappled shadows. Markers: ``tree_base`` (trunk axis at the
    ground), ``crown_center`` (mean of the blob centres) and ``tree_top`` (trunk axis at the height
    of the highest leaf).
    """
    base = np.asarray(base, float)
    top = base + [0.0, 0.0, trunk_height + 0.8]
    trunk = frustum(base - [0.0, 0.0, _SINK], top, 0.18, 0.09, segments=14, tile=_TILE["bark"])
    crown = base + [0.0, 0.0, crown_height]
    centres, radii = [], []
    for k in range(blobs):
        angle = 2.0 * np.pi * k / blobs + rng.uniform(-0.4, 0.4)
        dist = crown_radius * rng.uniform(0.45, 0.8) if k else 0.0
        c = crown + [dist * np.cos(angle), dist * np.sin(angle), rng.uniform(-0.3, 0.7) if k else 0.6]
        centres.append(c)
        radii.append(rng.uniform(1.0, 1.4))
    branches = []
    for c in centres[1:]:
        start = base + [0.0, 0.0, rng.uniform(0.75, 0.95) * trunk_height]
        end = start + 0.85 * (c - start)
        branches.append(frustum(start, end, 0.07, 0.025, segments=8, tile=_TILE["bark"]))
        # A side twig toward the blob's upper part.
        mid = start + 0.55 * (end - start)
        branches.append(frustum(mid, c + [0.0, 0.0, 0.5 * radii[0]], 0.035, 0.015, segments=6, tile=_TILE["bark"]))
    volumes = np.asarray(radii) ** 3
    counts = np.floor(leaves * volumes / volumes.sum()).astype(int)
    counts[0] += leaves - counts.sum()
    foliage = concat([leaf_cluster(rng, c, r, int(n)) for c, r, n in zip(centres, radii, counts, strict=True)])
    markers = {
        "tree_base": base.copy(),
        "crown_center": np.mean(centres, axis=0),
        "tree_top": np.array([base[0], base[1], foliage.vertices[:, 2].max()]),
    }
    return trunk, concat(branches), foliage, markers


# -- street furniture ----------------------------------------------------------------------------
def _lamp_pole(base: Sequence[float], *, height: float = 4.0, radius: float = 0.04) -> tuple[Part, dict]:
    """A lamp post: an 8 cm cylinder ``height`` metres tall on a collar, a lantern on top.

    Markers ``pole_base`` and ``pole_top`` are on the axis at the ground and at the top of the
    cylinder (the lantern sits above it).
    """
    b = np.asarray(base, float)
    metal = _TILE["metal"]
    top = b + [0.0, 0.0, height]
    parts = [
        frustum(b - [0.0, 0.0, _SINK], top, radius, radius, segments=12, tile=metal),
        frustum(b - [0.0, 0.0, _SINK], b + [0.0, 0.0, 0.45], 0.075, 0.05, segments=12, tile=metal),
        box(top + [-0.11, -0.11, 0.0], top + [0.11, 0.11, 0.32], tile=metal),
        frustum(top + [0.0, 0.0, 0.32], top + [0.0, 0.0, 0.52], 0.17, 0.0, segments=12, tile=metal),
    ]
    return concat(parts), {"pole_base": b.copy(), "pole_top": top}


def _fence(x0: float, x1: float, y: float, *, height: float = 1.0) -> tuple[Part, dict]:
    """A picket fence along ``x`` in ``[x0, x1]`` at ``y``: 8 x 2 cm pickets every 14 cm on two
    rails (behind, at larger ``y``), and posts every ~2 m. Every element is a closed box."""
    wood = _TILE["wood"]
    parts = []
    n = int(np.floor((x1 - x0 - 0.08) / 0.14)) + 1
    for k in range(n):
        cx = x0 + 0.04 + 0.14 * k
        parts.append(box((cx - 0.04, y - 0.01, 0.05), (cx + 0.04, y + 0.01, height), tile=wood))
    for z in (0.22, 0.75):
        parts.append(box((x0, y + 0.01, z), (x1, y + 0.04, z + 0.07), tile=wood))
    n_posts = max(2, int(np.ceil((x1 - x0) / 2.0)) + 1)
    for cx in np.linspace(x0 + 0.05, x1 - 0.05, n_posts):
        parts.append(box((cx - 0.045, y + 0.04, -_SINK), (cx + 0.045, y + 0.13, height - 0.05), tile=wood))
    return concat(parts), {"fence_center": np.array([0.5 * (x0 + x1), y, 0.5 * height])}


def _statue(rng: np.random.Generator, base: Sequence[float]) -> tuple[Part, Part, dict]:
    """A stylised standing figure (frusta and a sphere, one arm raised) on a stone plinth.

    Returns ``(plinth, figure, markers)``; markers ``statue_base`` and ``statue_top`` (the raised
    hand).
    """
    b = np.asarray(base, float)
    s = _TILE["stone"]
    ph = 1.1
    plinth = concat(
        [
            box(b + [-0.5, -0.5, -_SINK], b + [0.5, 0.5, 0.12], tile=s),
            box(b + [-0.42, -0.42, 0.12], b + [0.42, 0.42, ph], tile=s),
            box(b + [-0.48, -0.48, ph], b + [0.48, 0.48, ph + 0.08], tile=s),
        ]
    )
    z = ph + 0.08
    p = [
        frustum((-0.11, 0.0, z - 0.02), (-0.09, 0.0, z + 0.85), 0.085, 0.07, segments=12, tile=s),
        frustum((0.11, 0.0, z - 0.02), (0.09, 0.02, z + 0.85), 0.085, 0.07, segments=12, tile=s),
        frustum((0.0, 0.0, z + 0.8), (0.0, 0.0, z + 1.45), 0.17, 0.21, segments=16, tile=s),
        frustum((0.0, 0.0, z + 1.43), (0.0, 0.0, z + 1.55), 0.06, 0.055, segments=10, tile=s),
        sphere((0.0, 0.0, z + 1.66), 0.12, rings=10, segments=16, tile=s),
        frustum((-0.22, 0.0, z + 1.40), (-0.30, 0.08, z + 0.85), 0.06, 0.045, segments=10, tile=s),
        frustum((0.22, 0.0, z + 1.40), (0.38, 0.12, z + 2.0), 0.06, 0.045, segments=10, tile=s),
    ]
    yaw = rng.uniform(-0.5, 0.5)
    figure = concat(p).transformed(rotation_z(yaw), b)
    top = b + rotation_z(yaw) @ np.array([0.38, 0.12, z + 2.0 + 0.045])
    return plinth, figure, {"statue_base": b.copy(), "statue_top": top}


def _car(center: Sequence[float], yaw: float) -> tuple[Part, Part, Part, dict]:
    """A car-like object: box body, glazed cabin, four cylinder wheels. Returns
    ``(body, cabin, wheels, markers)`` (marker ``car_center``)."""
    metal = _TILE["metal"]
    body = concat(
        [
            box((-2.1, -0.87, 0.28), (2.1, 0.87, 0.95), tile=metal),
            box((-2.12, -0.8, 0.35), (-2.1, 0.8, 0.6), tile=metal),  # bumpers
            box((2.1, -0.8, 0.35), (2.12, 0.8, 0.6), tile=metal),
        ]
    )
    cabin = box((-1.05, -0.78, 0.95), (1.0, 0.78, 1.45), uv_box=(0.0, 0.0, 1.0, 1.0))
    wheels = []
    for wx in (-1.35, 1.35):
        for wy in (-1, 1):
            y0, y1 = (0.66, 0.9) if wy > 0 else (-0.66, -0.9)
            wheels.append(frustum((wx, y0, 0.32), (wx, y1, 0.32), 0.32, 0.32, segments=20, tile=metal))
    r, c = rotation_z(yaw), np.asarray(center, float)
    parts = [p.transformed(r, c) for p in (body, cabin, concat(wheels))]
    return parts[0], parts[1], parts[2], {"car_center": c + [0.0, 0.0, 0.8]}


def _pergola(width: float, depth: float, height: float = 2.5) -> tuple[Part, Part]:
    """A pergola in its local frame (centred on the origin): four 10 cm posts, two beams along
    ``x`` and slats along ``y`` every 30 cm. Returns ``(posts, roof)``."""
    wood = _TILE["wood"]
    hx, hy = width / 2, depth / 2
    posts = concat(
        [
            box((sx * hx - 0.05, sy * hy - 0.05, -_SINK), (sx * hx + 0.05, sy * hy + 0.05, height), tile=wood)
            for sx in (-1, 1)
            for sy in (-1, 1)
        ]
    )
    beams = [
        box((-hx - 0.3, sy * hy - 0.04, height), (hx + 0.3, sy * hy + 0.04, height + 0.2), tile=wood) for sy in (-1, 1)
    ]
    slats = [
        box((x - 0.025, -hy - 0.35, height + 0.2), (x + 0.025, hy + 0.35, height + 0.3), tile=wood)
        for x in np.arange(-hx - 0.15, hx + 0.16, 0.3)
    ]
    return posts, concat(beams + slats)


def _bollard(base: Sequence[float]) -> Part:
    """A 0.9 m tall, 18 cm diameter bollard with a domed top."""
    b = np.asarray(base, float)
    metal = _TILE["metal"]
    return concat(
        [
            frustum(b - [0.0, 0.0, _SINK], b + [0.0, 0.0, 0.85], 0.09, 0.09, segments=14, tile=metal),
            sphere(b + [0.0, 0.0, 0.85], 0.09, rings=6, segments=14, tile=metal),
        ]
    )


# -- recipes ---------------------------------------------------------------------------------------
def courtyard(*, seed: int = 0, gloss: bool = False, occluders: bool = True) -> SynthScene:
    """A paved courtyard before a plastered facade, with a tree, a statue, a lamp pole and a fence.

    Layout (metres, ``+Y`` from the cameras toward the facade):

    * ground: 30 x 30 m of paving slabs with a 7 x 6 m lawn (``x`` in [-7, 0], ``y`` in
      [0, 6]), continued by a meadow ring out to 600 m;
    * facade: a closed 16 x 6 x 8 m plastered box, front face at ``y = 8`` (``x`` in [-8, 8]),
      two storeys of five recessed windows with stone sills, a recessed door at ``x = 0`` with a
      step, a stone string course and cornice, a "PLACE DES ARTS" plaque above the door;
    * tree at about (-3.4, 3) in the lawn, ~6.5 m tall, ~5000 leaves in five blobs;
    * lamp pole (8 cm, 4 m) at about (1.5, -0.5); picket fence along ``y = -0.4`` before the lawn;
      statue on a plinth at about (4, 3).

    Cameras: ``path.center = (0, -9, 1.7)`` moving along ``+X``, looking at (0, 4, 3.2).

    Parameters
    ----------
    seed : int, optional
        Seed of the layout jitter, the foliage and the textures.
    gloss : bool, optional
        Mildly glossy glass, lamp pole and statue (``roughness`` = :data:`GLOSS_ROUGHNESS`).
    occluders : bool, optional
        False: the ground and the facade as a plain box (no openings, sills, bands, cornice or
        plaque), no tree, lamp pole, fence or statue (:func:`build_scene`).

    Returns
    -------
    SynthScene
    """
    b = _Builder("courtyard", seed, gloss)
    layout = b.rng("layout")
    # Materials.
    paving = b.material("paving", tex.paving)
    grass = b.material("grass", tex.grass)
    meadow = b.material("meadow", partial(tex.grass, dryness=0.45))
    plaster = b.material("plaster", tex.plaster)
    trim = b.material("trim_stone", partial(tex.stone, color=(0.55, 0.52, 0.46)))
    statue_stone = b.material("statue_stone", partial(tex.stone, color=(0.45, 0.44, 0.42)), glossy=True)
    glass = b.material("glass", tex.window, glossy=True)
    door = b.material("door", tex.door)
    plaque = b.material("plaque", partial(tex.sign, text="PLACE DES ARTS"), two_sided=True)
    bark = b.material("bark", tex.bark)
    leaves = b.material("leaves", tex.leaves, two_sided=True)
    metal = b.material("pole_metal", tex.painted_metal, glossy=True)
    fence_wood = b.material("fence_wood", partial(tex.wood, color=(0.55, 0.53, 0.48), grain_contrast=0.08, knots=1))

    # Ground: paving with a lawn, and the far meadow.
    def cell(x, y):
        return 1 if (-7.0 < x < 0.0 and 0.0 < y < 6.0) else 0

    pav, lawn = _ground(cell, 2, [_TILE["paving"], _TILE["grass"]])
    b.add("ground_paving", pav, paving, "ground")
    b.add("ground_grass", lawn, grass, "ground")
    b.add("ground_far", _far_ground(), meadow, "ground")

    # Facade: local frame moved to x0 = -8, front at y = 8.
    width, depth, height = 16.0, 6.0, 8.0
    columns = [2.0, 5.0, 8.0, 11.0, 14.0]
    openings = _window_grid([c for c in columns if c != 8.0], [(1.0, 2.8)], 1.2)
    openings += _window_grid(columns, [(4.6, 6.5)], 1.2)
    openings.append((7.2, 8.8, 0.15, 2.75, "door"))
    origin = np.array([-8.0, 8.0, 0.0])
    b.mark("facade_corner", origin + [0.0, 0.0, height])
    b.mark("facade_center", origin + [width / 2, 0.0, height / 2])
    path = _path((0.0, -9.0, 1.7), (1.0, 0.0, 0.0), (0.0, 4.0, 3.2))
    if not occluders:
        b.add("facade_wall", _building(width, depth, height, [], wall_tile=_TILE["plaster"])["wall"]
              .transformed(None, origin), plaster, "solid")
        return b.scene(path)
    parts = _building(width, depth, height, openings, wall_tile=_TILE["plaster"])
    stone_tile = _TILE["stone"]
    bands = concat(
        [
            box((-0.1, -0.1, 3.6), (width + 0.1, 0.0, 3.8), tile=stone_tile),
            box((-0.25, -0.3, height - 0.35), (width + 0.25, depth + 0.3, height + 0.05), tile=stone_tile),
        ]
    )
    b.add("facade_wall", parts["wall"].transformed(None, origin), plaster, "solid")
    b.add("facade_reveals", parts["reveals"].transformed(None, origin), trim, "solid")
    b.add("facade_windows", parts["glass"].transformed(None, origin), glass, "solid")
    b.add("facade_door", parts["door"].transformed(None, origin), door, "solid")
    b.add("facade_trim", concat([parts["sills"], bands]).transformed(None, origin), trim, "solid")
    b.add("plaque", _plaque(7.0, 9.0, 3.0, 3.45).transformed(None, origin), plaque, "solid")
    b.mark("door_center", origin + [8.0, 0.25, 1.45])
    b.mark("plaque_center", origin + [8.0, -0.03, 3.225])

    # Tree in the lawn.
    tree_base = np.array([-3.4, 3.0, 0.0]) + [*layout.uniform(-0.4, 0.4, 2), 0.0]
    b.add_tree(tree_base, bark, leaves)

    # Thin structures: lamp pole and picket fence.
    pole, markers = _lamp_pole(np.array([1.5, -0.5, 0.0]) + [*layout.uniform(-0.3, 0.3, 2), 0.0])
    b.add("lamp_pole", pole, metal, "thin")
    b.mark_all(markers)
    fence, markers = _fence(-6.4, -0.4, -0.4)
    b.add("fence", fence, fence_wood, "thin")
    b.mark_all(markers)

    # Statue on its plinth.
    plinth, figure, markers = _statue(layout, np.array([4.0, 3.0, 0.0]) + [*layout.uniform(-0.5, 0.5, 2), 0.0])
    b.add("statue_plinth", plinth, trim, "solid")
    b.add("statue", figure, statue_stone, "solid")
    b.mark_all(markers)

    return b.scene(path)


def street(*, seed: int = 0, gloss: bool = False, occluders: bool = True) -> SynthScene:
    """A street corner: brick and plaster facades at an angle, a car, a pergola, a tree, bollards.

    Layout (metres, ``+Y`` from the cameras toward the corner):

    * ground: asphalt road for ``y`` in [-13, -6] (the cameras stand on it), paving elsewhere in
      the 30 x 30 m square, a meadow ring out to 600 m;
    * facade A: a closed 13.5 x 8 x 9 m brick box, front at ``y = 8`` for ``x`` in [-11, 2.5],
      three storeys of windows, a shop door, a "BOULANGERIE" sign;
    * facade B: a 12 x 8 x 7 m plastered box whose front-left corner touches A's front-right
      corner (``facade_corner`` = (2.5, 8, 0)), turned 55 degrees toward the cameras;
    * a car near (-5.8, 1), a pergola of thin beams in front of B, a tree near (-1.8, 4.2) before
      facade A, a lamp pole at about (1.2, -1.5) and bollards along the kerb (``y = -5.5``).

    Cameras: ``path.center = (0, -10, 1.7)`` moving along ``+X``, looking at (1, 5, 3.2).

    Parameters
    ----------
    seed : int, optional
        Seed of the layout jitter, the foliage and the textures.
    gloss : bool, optional
        Mildly glossy glass, lamp pole, bollards and car paint (``roughness`` = :data:`GLOSS_ROUGHNESS`).
    occluders : bool, optional
        False: the ground and facades A and B as plain boxes (no openings, sills, cornices or
        sign), no car, pergola, tree, lamp pole or bollards (:func:`build_scene`).

    Returns
    -------
    SynthScene
    """
    b = _Builder("street", seed, gloss)
    layout = b.rng("layout")
    asphalt = b.material("asphalt", tex.asphalt)
    paving = b.material("paving", partial(tex.paving, shape=(192, 192), color=(0.34, 0.31, 0.28), stagger=False))
    meadow = b.material("meadow", partial(tex.grass, dryness=0.45))
    brick = b.material("brick", tex.brick)
    plaster = b.material("plaster", partial(tex.plaster, color=(0.58, 0.56, 0.50)))
    trim = b.material("trim_stone", partial(tex.stone, color=(0.55, 0.52, 0.46)))
    glass = b.material("glass", tex.window, glossy=True)
    door = b.material("door", partial(tex.door, color=(0.05, 0.09, 0.06)))
    sign_texture = partial(
        tex.sign, shape=(128, 384), text="BOULANGERIE", background=(0.25, 0.03, 0.03), ink=(0.75, 0.65, 0.35)
    )
    shop_sign = b.material("shop_sign", sign_texture, two_sided=True)
    bark = b.material("bark", tex.bark)
    leaves = b.material("leaves", tex.leaves, two_sided=True)
    metal = b.material("pole_metal", partial(tex.painted_metal, color=(0.05, 0.05, 0.05)), glossy=True)
    car_paint = b.material("car_paint", partial(tex.painted_metal, color=(0.45, 0.05, 0.04), wear=0.15), glossy=True)
    tyre = b.material("tyre", partial(tex.painted_metal, color=(0.03, 0.03, 0.03), wear=0.3))
    timber = b.material("timber", tex.wood)

    def cell(x, y):
        return 0 if -13.0 < y < -6.0 else 1

    road, pav = _ground(cell, 2, [_TILE["asphalt"], _TILE["paving"]])
    b.add("ground_road", road, asphalt, "ground")
    b.add("ground_paving", pav, paving, "ground")
    b.add("ground_far", _far_ground(), meadow, "ground")

    path = _path((0.0, -10.0, 1.7), (1.0, 0.0, 0.0), (1.0, 5.0, 3.2))
    wa, da, ha = 13.5, 8.0, 9.0
    origin_a = np.array([-11.0, 8.0, 0.0])
    wb, db, hb = 12.0, 8.0, 7.0
    corner = np.array([2.5, 8.0, 0.0])
    rb = rotation_z(np.deg2rad(-55.0))
    if not occluders:
        b.add("facade_a_wall", _building(wa, da, ha, [], wall_tile=_TILE["brick"])["wall"].transformed(None, origin_a),
              brick, "solid")
        b.add("facade_b_wall", _building(wb, db, hb, [], wall_tile=_TILE["plaster"])["wall"].transformed(rb, corner),
              plaster, "solid")
        b.mark_all({"facade_center": origin_a + [wa / 2, 0.0, ha / 2], "facade_corner": corner,
                    "facade_corner_top": corner + [0.0, 0.0, hb],
                    "facade_b_center": corner + rb @ np.array([wb / 2, 0.0, hb / 2])})
        return b.scene(path)

    # Facade A (brick), local frame at (-11, 8).
    cols_a = [1.4, 4.0, 6.6, 9.2, 11.8]
    openings = _window_grid([c for c in cols_a if c != 9.2], [(0.9, 2.5)], 1.1)
    openings += _window_grid(cols_a, [(3.9, 5.5), (6.9, 8.5)], 1.1)
    openings.append((8.6, 9.8, 0.15, 2.5, "door"))
    parts_a = _building(wa, da, ha, openings, wall_tile=_TILE["brick"])
    cornice_a = box((-0.2, -0.25, ha - 0.3), (wa + 0.2, da + 0.25, ha + 0.05), tile=_TILE["stone"])
    b.add("facade_a_wall", parts_a["wall"].transformed(None, origin_a), brick, "solid")
    b.add("facade_a_reveals", parts_a["reveals"].transformed(None, origin_a), trim, "solid")
    b.add("facade_a_windows", parts_a["glass"].transformed(None, origin_a), glass, "solid")
    b.add("facade_a_door", parts_a["door"].transformed(None, origin_a), door, "solid")
    b.add("facade_a_trim", concat([parts_a["sills"], cornice_a]).transformed(None, origin_a), trim, "solid")
    b.add("shop_sign", _plaque(8.0, 12.6, 2.75, 3.35, thickness=0.05).transformed(None, origin_a), shop_sign, "solid")
    b.mark("facade_center", origin_a + [wa / 2, 0.0, ha / 2])
    b.mark("door_center", origin_a + [9.2, 0.25, 1.3])
    b.mark("sign_center", origin_a + [10.3, -0.05, 3.05])

    # Facade B (plaster), turned toward the cameras about its front-left corner.
    cols_b = [1.5, 4.0, 6.5, 9.0]
    openings = _window_grid([c for c in cols_b if c != 6.5], [(1.0, 2.6)], 1.2)
    openings += _window_grid(cols_b, [(4.3, 5.9)], 1.2)
    openings.append((5.9, 7.1, 0.15, 2.6, "door"))
    parts_b = _building(wb, db, hb, openings, wall_tile=_TILE["plaster"])
    cornice_b = box((-0.2, -0.25, hb - 0.3), (wb + 0.2, db + 0.25, hb + 0.05), tile=_TILE["stone"])
    b.add("facade_b_wall", parts_b["wall"].transformed(rb, corner), plaster, "solid")
    b.add("facade_b_reveals", parts_b["reveals"].transformed(rb, corner), trim, "solid")
    b.add("facade_b_windows", parts_b["glass"].transformed(rb, corner), glass, "solid")
    b.add("facade_b_door", parts_b["door"].transformed(rb, corner), door, "solid")
    b.add("facade_b_trim", concat([parts_b["sills"], cornice_b]).transformed(rb, corner), trim, "solid")
    b.mark("facade_corner", corner)
    b.mark("facade_corner_top", corner + [0.0, 0.0, hb])
    b.mark("facade_b_center", corner + rb @ np.array([wb / 2, 0.0, hb / 2]))

    # Car.
    car_c = np.array([-5.8, 1.0, 0.0]) + [*layout.uniform(-0.6, 0.6, 2), 0.0]
    body, cabin, wheels, markers = _car(car_c, np.deg2rad(layout.uniform(-12.0, 12.0)))
    b.add("car_body", body, car_paint, "solid")
    b.add("car_cabin", cabin, glass, "solid")
    b.add("car_wheels", wheels, tyre, "solid")
    b.mark_all(markers)

    # Pergola in front of facade B, aligned with it.
    posts, roof = _pergola(3.2, 2.4)
    pc = np.array([4.6, -1.2, 0.0]) + [*layout.uniform(-0.3, 0.3, 2), 0.0]
    b.add("pergola_posts", posts.transformed(rb, pc), timber, "thin")
    b.add("pergola_roof", roof.transformed(rb, pc), timber, "thin")
    b.mark("pergola_center", pc + [0.0, 0.0, 2.6])

    # Tree.
    tree_base = np.array([-1.8, 4.2, 0.0]) + [*layout.uniform(-0.4, 0.4, 2), 0.0]
    b.add_tree(tree_base, bark, leaves, crown_height=4.8)

    # Lamp pole and bollards along the kerb.
    pole, markers = _lamp_pole(np.array([1.2, -1.5, 0.0]) + [*layout.uniform(-0.3, 0.3, 2), 0.0])
    b.add("lamp_pole", pole, metal, "thin")
    b.mark_all(markers)
    b.add("bollards", concat([_bollard((x, -5.5, 0.0)) for x in (-4.5, -3.0, 3.0, 4.5, 6.0)]), metal, "solid")

    return b.scene(path)


#: Scene recipes by name: ``name -> builder(*, seed, gloss, occluders) -> SynthScene``.
RECIPES: dict[str, Callable[..., SynthScene]] = {"courtyard": courtyard, "street": street}


def build_scene(recipe: str, *, seed: int = 0, gloss: bool = False, occluders: bool = True) -> SynthScene:
    """Build a procedural outdoor scene.

    Parameters
    ----------
    recipe : str
        One of :data:`RECIPES` (``"courtyard"``, ``"street"``).
    seed : int, optional
        Non-negative seed: the same seed gives the same scene; other seeds move the tree, pole,
        statue, car and pergola a little and redraw every texture and the foliage.
    gloss : bool, optional
        Give a mild gloss (GGX roughness :data:`GLOSS_ROUGHNESS`) to glass, painted metal and
        polished stone; otherwise every material is purely diffuse (``roughness=None``).
    occluders : bool, optional
        False keeps only the ground and the buildings, as plain closed boxes: no window or door
        recesses, sills, cornices or signs, and no tree, pole, car or other free-standing object.
        Each remaining solid is convex and stands on the ground, so a sun in front of the
        facades casts no shadow that the cameras see: a sunny scene without cast shadows, the
        case in which Step 2 finds no light/shadow pair (``benchmarks/bench_stability.py``,
        ``docs/stability.md``). Textures, camera path and markers of the buildings are those of
        the full recipe with the same seed.

    Raises
    ------
    ValueError
        If ``recipe`` is unknown (the message lists the valid names) or ``seed`` is negative.
    TypeError
        If ``seed`` is not an int, or ``gloss`` or ``occluders`` not a bool.
    """
    if not isinstance(recipe, str) or recipe not in RECIPES:
        raise ValueError(f"recipe must be one of {sorted(RECIPES)}, got {recipe!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
        raise TypeError(f"seed must be an int, got {type(seed).__name__} {seed!r}")
    if seed < 0:
        raise ValueError(f"seed must be non-negative, got {seed!r}")
    if not isinstance(gloss, (bool, np.bool_)):
        raise TypeError(f"gloss must be a bool, got {type(gloss).__name__} {gloss!r}")
    if not isinstance(occluders, (bool, np.bool_)):
        raise TypeError(f"occluders must be a bool, got {type(occluders).__name__} {occluders!r}")
    return RECIPES[recipe](seed=int(seed), gloss=bool(gloss), occluders=bool(occluders))
