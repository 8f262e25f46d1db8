"""Procedural albedo textures for the synthetic scenes (edge layer, pure numpy / OpenCV).

Every function returns a tileable ``(Ht, Wt, 3)`` float32 image of **linear** RGB diffuse albedo
(Rec.709 primaries, ``docs/conventions.md``) clipped to ``[ALBEDO_MIN, ALBEDO_MAX]`` =
``[0.02, 0.9]``. Row 0 is the top of the texture (``v = 1``), as :class:`~.types.Material` wants.
The result depends only on the ``rng`` argument (a seed or a :class:`numpy.random.Generator`).

Reflectance varies *within* every surface (per-element colour jitter, joints, low-frequency
blotches and fine grain), as real facades do: a piecewise-constant albedo would make the
intrinsic decomposition artificially easy.

The physical size of one texture tile is set by the UVs a recipe assigns (UVs are measured in
tiles and wrap with ``repeat``); each function documents the tile size it is drawn for. Textures
whose documented tile is "one object" (window, door, sign) are meant to be mapped once with UVs in
``[0, 1]``; all others tile seamlessly (the noise is periodic and the patterns repeat exactly).
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np

__all__ = [
    "ALBEDO_MAX",
    "ALBEDO_MIN",
    "TEXTURES",
    "asphalt",
    "bark",
    "brick",
    "door",
    "grass",
    "leaves",
    "painted_metal",
    "paving",
    "plaster",
    "sign",
    "stone",
    "window",
    "wood",
]

#: Albedo range of every texture: darker than coal and brighter than fresh snow do not occur on
#: facades, and the bounds keep the ground-truth shading ``I / R`` well conditioned.
ALBEDO_MIN = 0.02
ALBEDO_MAX = 0.9

Shape = tuple[int, int]


# -- helpers ---------------------------------------------------------------------------------------
def _generator(rng: np.random.Generator | int | None) -> np.random.Generator:
    if isinstance(rng, bool):
        raise TypeError(f"rng must be a numpy Generator, an int or None, got {rng!r}")
    if rng is None or isinstance(rng, (int, np.integer, np.random.Generator)):
        return np.random.default_rng(rng)
    raise TypeError(f"rng must be a numpy Generator, an int or None, got {type(rng).__name__}")


def _shape(shape: Shape) -> Shape:
    try:
        h, w = (int(s) for s in shape)
    except (TypeError, ValueError) as exc:
        raise TypeError(f"shape must be a pair of ints (Ht, Wt), got {shape!r}") from exc
    if h < 16 or w < 16 or h > 4096 or w > 4096:
        raise ValueError(f"shape must be between 16 and 4096 pixels per side, got {shape!r}")
    return h, w


def _color(value, name: str) -> np.ndarray:
    c = np.asarray(value, dtype=np.float64)
    if c.shape != (3,) or not np.isfinite(c).all() or (c < 0).any() or (c > 1).any():
        raise ValueError(f"{name} must be a linear RGB triple in [0, 1], got {value!r}")
    return c


def _noise(rng: np.random.Generator, shape: Shape, scale: float | tuple[float, float]) -> np.ndarray:
    """Periodic (tileable) Gaussian noise, zero mean and unit standard deviation, (H, W) float64.

    White noise low-passed in the Fourier domain by a Gaussian of standard deviation ``scale``
    pixels (``(sy, sx)`` for anisotropic grain); the FFT makes it wrap around exactly.
    """
    sy, sx = (scale, scale) if np.isscalar(scale) else scale
    h, w = shape
    white = rng.standard_normal(shape)
    fy = np.fft.fftfreq(h)[:, None]
    fx = np.fft.rfftfreq(w)[None, :]
    transfer = np.exp(-2.0 * np.pi**2 * ((sy * fy) ** 2 + (sx * fx) ** 2))
    out = np.fft.irfft2(np.fft.rfft2(white) * transfer, s=shape)
    out -= out.mean()
    return out / max(out.std(), 1e-12)


def _smoothstep(e0: float, e1: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _finish(image: np.ndarray) -> np.ndarray:
    return np.clip(image, ALBEDO_MIN, ALBEDO_MAX).astype(np.float32)


def _cells(
    shape: Shape, rows: int, cols: int, *, stagger: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Cell index and distance to the nearest joint (pixels) of a (staggered) rectangular grid.

    Returns ``(row, col, dist, (fy, fx))``: per pixel the cell row and column (``col`` already
    wrapped), the distance in pixels to the nearest cell border, and the position inside the cell
    in ``[0, 1)``. With ``stagger`` odd rows are offset by half a cell (running bond).
    """
    h, w = shape
    ch, cw = h / rows, w / cols
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64) + 0.5
    row = np.floor(yy / ch).astype(np.int64)
    shift = (row % 2) * (0.5 * cw) if stagger else 0.0
    xs = xx + shift
    col = np.floor(xs / cw).astype(np.int64) % cols
    fy = yy / ch - row
    fx = xs / cw - np.floor(xs / cw)
    dist = np.minimum(np.minimum(fy, 1 - fy) * ch, np.minimum(fx, 1 - fx) * cw)
    return row % rows, col, dist, np.stack([fy, fx])


# -- textures --------------------------------------------------------------------------------------
def brick(
    rng: np.random.Generator | int | None = None,
    *,
    shape: Shape = (256, 256),
    courses: int = 12,
    columns: int = 4,
    color: tuple[float, float, float] = (0.32, 0.11, 0.06),
    mortar: tuple[float, float, float] = (0.50, 0.47, 0.42),
    jitter: float = 0.18,
) -> np.ndarray:
    """Running-bond brickwork with per-brick colour jitter, mortar joints and fine grain.

    Intended tile: **1.0 m wide x 0.9 m tall** with the defaults (4 bricks of 25 cm per course,
    12 courses of 7.5 cm, joints about 1 cm), ``v`` up.

    Parameters
    ----------
    rng : numpy.random.Generator or int or None
        Source of randomness (seed or generator).
    shape : (int, int), optional
        ``(Ht, Wt)`` in pixels.
    courses, columns : int, optional
        Brick courses (rows) and bricks per course in one tile; ``courses`` must be even so the
        staggered bond tiles.
    color, mortar : (3,) float, optional
        Mean linear RGB albedo of the bricks and of the mortar.
    jitter : float, optional
        Relative standard deviation of the per-brick brightness.

    Returns
    -------
    (Ht, Wt, 3) float32
        Linear RGB albedo in [0.02, 0.9].
    """
    rng = _generator(rng)
    shape = _shape(shape)
    if courses < 2 or courses % 2 or columns < 1:
        raise ValueError(f"courses must be even and >= 2 and columns >= 1, got {courses}, {columns}")
    base, mortar_c = _color(color, "color"), _color(mortar, "mortar")
    row, col, dist, _ = _cells(shape, courses, columns, stagger=True)
    joint = 0.065 * shape[0] / courses  # half joint, pixels (1 cm of a 7.5 cm course)
    is_brick = _smoothstep(joint - 0.6, joint + 0.6, dist)[..., None]
    # Per-brick brightness (log-normal) and hue (towards orange or towards brown-purple).
    gain = np.exp(jitter * rng.standard_normal((courses, columns)))[row, col][..., None]
    hue = rng.uniform(-1.0, 1.0, (courses, columns))[row, col][..., None]
    tint = np.array([1.0, 1.0, 1.0]) + hue * np.array([0.10, 0.18, -0.05])
    fired = base * gain * tint
    # Edges of each brick slightly darker (worn arrises), plus grain and a slow dirt pattern.
    edge = 1.0 - 0.12 * np.exp(-np.maximum(dist - joint, 0.0) / 2.0)[..., None]
    grain = 1.0 + 0.08 * _noise(rng, shape, 0.7)[..., None] + 0.06 * _noise(rng, shape, 3.0)[..., None]
    dirt = 1.0 + 0.08 * _noise(rng, shape, 24.0)[..., None]
    bricks = fired * edge * grain
    mortar_img = mortar_c * (1.0 + 0.10 * _noise(rng, shape, 0.8)[..., None])
    return _finish((is_brick * bricks + (1.0 - is_brick) * mortar_img) * dirt)


def paving(
    rng: np.random.Generator | int | None = None,
    *,
    shape: Shape = (256, 256),
    stones: tuple[int, int] = (4, 4),
    stagger: bool = True,
    color: tuple[float, float, float] = (0.30, 0.28, 0.25),
    joint_color: tuple[float, float, float] = (0.10, 0.10, 0.09),
    jitter: float = 0.15,
) -> np.ndarray:
    """Paving slabs with per-slab colour jitter and shading gradients, dark joints, fine grain.

    Intended tile: **2 m x 2 m** with the defaults (4 x 4 slabs of 50 cm, joints ~1 cm).

    Parameters
    ----------
    rng : numpy.random.Generator or int or None
        Source of randomness.
    shape : (int, int), optional
        ``(Ht, Wt)`` in pixels.
    stones : (int, int), optional
        Slab rows and columns in one tile (rows must be even when ``stagger``).
    stagger : bool, optional
        Offset every other row by half a slab.
    color, joint_color : (3,) float, optional
        Mean linear RGB albedo of the slabs and of the joints.
    jitter : float, optional
        Relative standard deviation of the per-slab brightness.

    Returns
    -------
    (Ht, Wt, 3) float32
        Linear RGB albedo in [0.02, 0.9].
    """
    rng = _generator(rng)
    shape = _shape(shape)
    rows, cols = (int(s) for s in stones)
    if rows < 1 or cols < 1 or (stagger and rows % 2):
        raise ValueError(f"stones must be positive (rows even when staggered), got {stones!r}")
    base, joint_c = _color(color, "color"), _color(joint_color, "joint_color")
    row, col, dist, (fy, fx) = _cells(shape, rows, cols, stagger=stagger)
    joint = 0.02 * shape[0] / rows  # half joint, pixels: 1 cm for 50 cm slabs
    is_stone = _smoothstep(joint - 0.7, joint + 0.7, dist)[..., None]
    gain = np.exp(jitter * rng.standard_normal((rows, cols)))[row, col]
    warm = rng.uniform(-1.0, 1.0, (rows, cols))[row, col]
    gx, gy = rng.uniform(-0.08, 0.08, (2, rows, cols))
    slope = 1.0 + gx[row, col] * (fx - 0.5) + gy[row, col] * (fy - 0.5)
    slab = base * (gain * slope)[..., None] * (1.0 + warm[..., None] * np.array([0.05, 0.0, -0.06]))
    grain = 1.0 + 0.10 * _noise(rng, shape, 0.6)[..., None] + 0.06 * _noise(rng, shape, 2.5)[..., None]
    stains = 1.0 + 0.07 * _noise(rng, shape, 20.0)[..., None]
    joints = joint_c * (1.0 + 0.2 * _noise(rng, shape, 1.0)[..., None])
    return _finish((is_stone * slab * grain + (1.0 - is_stone) * joints) * stains)


def plaster(
    rng: np.random.Generator | int | None = None,
    *,
    shape: Shape = (256, 256),
    color: tuple[float, float, float] = (0.62, 0.50, 0.36),
    blotch: float = 0.10,
    grain: float = 0.04,
) -> np.ndarray:
    """Rendered (plastered) wall: low-frequency blotches and weathering stains, fine grain.

    Intended tile: **4 m x 4 m** (blotches of ~0.5-1 m, grain of a few mm).

    Parameters
    ----------
    rng : numpy.random.Generator or int or None
        Source of randomness.
    shape : (int, int), optional
        ``(Ht, Wt)`` in pixels.
    color : (3,) float, optional
        Mean linear RGB albedo.
    blotch, grain : float, optional
        Relative amplitudes of the low-frequency blotches and of the per-pixel grain.

    Returns
    -------
    (Ht, Wt, 3) float32
        Linear RGB albedo in [0.02, 0.9].
    """
    rng = _generator(rng)
    shape = _shape(shape)
    base = _color(color, "color")
    h = shape[0]
    low = _noise(rng, shape, h / 12.0)
    mid = _noise(rng, shape, h / 40.0)
    hue = _noise(rng, shape, h / 10.0)
    # Sparse darker stains: thresholded mid-frequency noise, soft edged.
    stains = _smoothstep(1.2, 2.2, _noise(rng, shape, h / 30.0))
    value = 1.0 + blotch * (0.8 * low + 0.4 * mid) - 0.18 * stains
    fine = grain * _noise(rng, shape, 0.6) + 0.5 * grain * _noise(rng, shape, 2.0)
    tint = 1.0 + hue[..., None] * np.array([0.03, 0.0, -0.04])
    return _finish(base * tint * (value + fine)[..., None])


def grass(
    rng: np.random.Generator | int | None = None,
    *,
    shape: Shape = (128, 128),
    color: tuple[float, float, float] = (0.07, 0.14, 0.035),
    dry: tuple[float, float, float] = (0.20, 0.18, 0.07),
    dryness: float = 0.3,
) -> np.ndarray:
    """Lawn: high-frequency blade-level variation between green and dry blades, soft patches.

    Intended tile: **1 m x 1 m** (blades of a few mm). With a larger tile (e.g. 4 m) it serves as
    the far meadow.

    Parameters
    ----------
    rng : numpy.random.Generator or int or None
        Source of randomness.
    shape : (int, int), optional
        ``(Ht, Wt)`` in pixels.
    color, dry : (3,) float, optional
        Linear RGB albedo of green and of dry blades.
    dryness : float, optional
        Mean fraction of dry blades, in [0, 1].

    Returns
    -------
    (Ht, Wt, 3) float32
        Linear RGB albedo in [0.02, 0.9].
    """
    rng = _generator(rng)
    shape = _shape(shape)
    green, dry_c = _color(color, "color"), _color(dry, "dry")
    if not 0.0 <= dryness <= 1.0:
        raise ValueError(f"dryness must be in [0, 1], got {dryness!r}")
    blades = _noise(rng, shape, (1.4, 0.5))  # slightly elongated vertically
    patches = _noise(rng, shape, shape[0] / 8.0)
    mix = np.clip(dryness + 0.25 * patches + 0.35 * _noise(rng, shape, 0.8), 0.0, 1.0)[..., None]
    value = np.exp(0.35 * blades + 0.15 * _noise(rng, shape, 3.0))[..., None]
    return _finish(((1.0 - mix) * green + mix * dry_c) * value)


def bark(
    rng: np.random.Generator | int | None = None,
    *,
    shape: Shape = (128, 128),
    color: tuple[float, float, float] = (0.13, 0.10, 0.08),
) -> np.ndarray:
    """Tree bark: dark vertical furrows between lighter ridges, lichen-grey patches.

    Intended tile: **0.5 m around x 1 m along the trunk** (``v`` along the axis, furrows run
    along ``v``).

    Parameters
    ----------
    rng : numpy.random.Generator or int or None
        Source of randomness.
    shape : (int, int), optional
        ``(Ht, Wt)`` in pixels.
    color : (3,) float, optional
        Mean linear RGB albedo.

    Returns
    -------
    (Ht, Wt, 3) float32
        Linear RGB albedo in [0.02, 0.9].
    """
    rng = _generator(rng)
    shape = _shape(shape)
    base = _color(color, "color")
    ridges = _noise(rng, shape, (10.0, 1.2))
    furrow = _smoothstep(-0.8, 0.6, ridges)
    lichen = _smoothstep(0.8, 1.6, _noise(rng, shape, 6.0))[..., None]
    value = (0.45 + 0.75 * furrow + 0.10 * _noise(rng, shape, 0.6))[..., None]
    grey = np.array([0.30, 0.31, 0.27])
    return _finish((1.0 - 0.6 * lichen) * base * value + 0.6 * lichen * grey * value)


def leaves(
    rng: np.random.Generator | int | None = None,
    *,
    shape: Shape = (128, 128),
    color: tuple[float, float, float] = (0.06, 0.13, 0.03),
    yellow: tuple[float, float, float] = (0.16, 0.20, 0.04),
) -> np.ndarray:
    """Leaf material: patches of different greens (one leaf samples one patch), veins, grain.

    Intended mapping: each leaf quad samples a random window of about 0.15 x 0.15 tile, so
    different leaves get different greens.

    Parameters
    ----------
    rng : numpy.random.Generator or int or None
        Source of randomness.
    shape : (int, int), optional
        ``(Ht, Wt)`` in pixels.
    color, yellow : (3,) float, optional
        Linear RGB albedo of dark green and of yellow-green leaves.

    Returns
    -------
    (Ht, Wt, 3) float32
        Linear RGB albedo in [0.02, 0.9].
    """
    rng = _generator(rng)
    shape = _shape(shape)
    dark, light = _color(color, "color"), _color(yellow, "yellow")
    patches = _smoothstep(-1.0, 1.0, _noise(rng, shape, shape[0] / 14.0))[..., None]
    value = np.exp(0.25 * _noise(rng, shape, shape[0] / 20.0) + 0.12 * _noise(rng, shape, 0.7))[..., None]
    veins = _smoothstep(1.3, 2.0, np.abs(_noise(rng, shape, (0.6, 6.0))))[..., None]
    return _finish(((1.0 - patches) * dark + patches * light) * value * (1.0 + 0.35 * veins))


def wood(
    rng: np.random.Generator | int | None = None,
    *,
    shape: Shape = (128, 128),
    color: tuple[float, float, float] = (0.30, 0.17, 0.08),
    grain_contrast: float = 0.25,
    knots: int = 3,
) -> np.ndarray:
    """Sawn wood: grain lines along ``v``, growth-ring banding, a few knots.

    Intended tile: **0.5 m x 1 m**, grain along ``v`` (boxes get ``v`` up on their vertical
    faces, so pickets and posts show vertical grain). A light ``color`` with a low
    ``grain_contrast`` gives weathered painted wood.

    Parameters
    ----------
    rng : numpy.random.Generator or int or None
        Source of randomness.
    shape : (int, int), optional
        ``(Ht, Wt)`` in pixels.
    color : (3,) float, optional
        Mean linear RGB albedo.
    grain_contrast : float, optional
        Relative amplitude of the grain.
    knots : int, optional
        Number of knots per tile.

    Returns
    -------
    (Ht, Wt, 3) float32
        Linear RGB albedo in [0.02, 0.9].
    """
    rng = _generator(rng)
    shape = _shape(shape)
    base = _color(color, "color")
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    warp = 3.0 * _noise(rng, shape, (h / 6.0, w / 10.0))
    rings = np.sin(2.0 * np.pi * (xx + warp) / (w / 9.0))
    value = 1.0 + grain_contrast * (0.5 * rings + 0.6 * _noise(rng, shape, (8.0, 0.6)))
    for _ in range(int(knots)):
        cy, cx = rng.uniform(0, h), rng.uniform(0, w)
        dy = (yy - cy + h / 2) % h - h / 2  # periodic distance
        dx = (xx - cx + w / 2) % w - w / 2
        r = np.hypot(dx / 1.0, dy / 2.2)
        value -= grain_contrast * 1.4 * np.exp(-((r / 3.0) ** 2))
    value += 0.04 * _noise(rng, shape, 0.5)
    return _finish(base * value[..., None])


def stone(
    rng: np.random.Generator | int | None = None,
    *,
    shape: Shape = (128, 128),
    color: tuple[float, float, float] = (0.52, 0.49, 0.43),
) -> np.ndarray:
    """Limestone / sandstone: speckles (dark and light grains), veins, weathering.

    Intended tile: **1 m x 1 m** (statues, plinths, window reveals, sills, cornices).

    Parameters
    ----------
    rng : numpy.random.Generator or int or None
        Source of randomness.
    shape : (int, int), optional
        ``(Ht, Wt)`` in pixels.
    color : (3,) float, optional
        Mean linear RGB albedo.

    Returns
    -------
    (Ht, Wt, 3) float32
        Linear RGB albedo in [0.02, 0.9].
    """
    rng = _generator(rng)
    shape = _shape(shape)
    base = _color(color, "color")
    speck = _noise(rng, shape, 0.5)
    dark = _smoothstep(1.6, 2.4, speck)
    light = _smoothstep(1.6, 2.4, -speck)
    veins = np.exp(-((_noise(rng, shape, shape[0] / 10.0) / 0.08) ** 2))
    value = 1.0 + 0.07 * _noise(rng, shape, shape[0] / 8.0) + 0.04 * _noise(rng, shape, 1.5)
    value = value - 0.35 * dark + 0.2 * light - 0.12 * veins
    return _finish(base * value[..., None])


def painted_metal(
    rng: np.random.Generator | int | None = None,
    *,
    shape: Shape = (128, 128),
    color: tuple[float, float, float] = (0.04, 0.09, 0.06),
    wear: float = 0.5,
) -> np.ndarray:
    """Painted metal (poles, car body, bollards): slight paint unevenness, dirt, chips.

    Intended tile: **0.5 m x 0.5 m**.

    Parameters
    ----------
    rng : numpy.random.Generator or int or None
        Source of randomness.
    shape : (int, int), optional
        ``(Ht, Wt)`` in pixels.
    color : (3,) float, optional
        Paint colour, linear RGB albedo.
    wear : float, optional
        Amount of dirt and chipping, in [0, 1].

    Returns
    -------
    (Ht, Wt, 3) float32
        Linear RGB albedo in [0.02, 0.9].
    """
    rng = _generator(rng)
    shape = _shape(shape)
    paint = _color(color, "color")
    if not 0.0 <= wear <= 1.0:
        raise ValueError(f"wear must be in [0, 1], got {wear!r}")
    value = 1.0 + 0.06 * _noise(rng, shape, shape[0] / 10.0) + 0.035 * _noise(rng, shape, 0.6)
    dirt = 1.0 - 0.15 * wear * _smoothstep(0.0, 2.0, _noise(rng, shape, 5.0))
    chips = (wear * _smoothstep(2.3, 2.8, _noise(rng, shape, 1.2)))[..., None]
    primer = np.array([0.25, 0.23, 0.21])
    return _finish((1.0 - chips) * paint * (value * dirt)[..., None] + chips * primer)


def asphalt(
    rng: np.random.Generator | int | None = None,
    *,
    shape: Shape = (256, 256),
    color: tuple[float, float, float] = (0.07, 0.07, 0.065),
) -> np.ndarray:
    """Asphalt: dark binder with light and dark aggregate, worn patches.

    Intended tile: **2 m x 2 m**.

    Parameters
    ----------
    rng : numpy.random.Generator or int or None
        Source of randomness.
    shape : (int, int), optional
        ``(Ht, Wt)`` in pixels.
    color : (3,) float, optional
        Mean linear RGB albedo.

    Returns
    -------
    (Ht, Wt, 3) float32
        Linear RGB albedo in [0.02, 0.9].
    """
    rng = _generator(rng)
    shape = _shape(shape)
    base = _color(color, "color")
    aggregate = _noise(rng, shape, 0.8)
    light = _smoothstep(1.2, 2.2, aggregate)
    value = 1.0 + 0.18 * _noise(rng, shape, 0.5) + 0.12 * _noise(rng, shape, shape[0] / 12.0) + 1.2 * light
    worn = 1.0 + 0.25 * _smoothstep(0.5, 2.0, _noise(rng, shape, shape[0] / 16.0))
    return _finish(base * (value * worn)[..., None])


def window(
    rng: np.random.Generator | int | None = None,
    *,
    shape: Shape = (128, 128),
    panes: tuple[int, int] = (3, 2),
    frame: tuple[float, float, float] = (0.10, 0.11, 0.10),
    glass: tuple[float, float, float] = (0.035, 0.04, 0.045),
    frame_width: float = 0.07,
) -> np.ndarray:
    """Window seen from outside: dark glass panes (albedo of the dim interior) in a frame.

    Intended mapping: **once per window**, UVs ``[0, 1]`` over the opening (``v`` up). The glass
    is dark but not uniform (dirt, interior variation); the frame and glazing bars are painted
    wood.

    Parameters
    ----------
    rng : numpy.random.Generator or int or None
        Source of randomness.
    shape : (int, int), optional
        ``(Ht, Wt)`` in pixels.
    panes : (int, int), optional
        Pane rows and columns.
    frame, glass : (3,) float, optional
        Linear RGB albedo of the frame and of the glass.
    frame_width : float, optional
        Outer frame width as a fraction of the texture width (glazing bars are half as wide).

    Returns
    -------
    (Ht, Wt, 3) float32
        Linear RGB albedo in [0.02, 0.9].
    """
    rng = _generator(rng)
    shape = _shape(shape)
    frame_c, glass_c = _color(frame, "frame"), _color(glass, "glass")
    h, w = shape
    rows, cols = (int(p) for p in panes)
    if rows < 1 or cols < 1:
        raise ValueError(f"panes must be positive, got {panes!r}")
    fw = frame_width * w
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64) + 0.5
    inner_x = (xx - fw) / (w - 2 * fw) * cols
    inner_y = (yy - fw) / (h - 2 * fw) * rows
    bar = 0.25 * fw
    dx = np.abs(inner_x - np.round(inner_x)) * (w - 2 * fw) / cols
    dy = np.abs(inner_y - np.round(inner_y)) * (h - 2 * fw) / rows
    is_frame = (xx < fw) | (xx > w - fw) | (yy < fw) | (yy > h - fw) | (dx < bar) | (dy < bar)
    is_frame = cv2.GaussianBlur(is_frame.astype(np.float64), (0, 0), 0.6)[..., None]
    gradient = 1.0 + 0.25 * (yy / h - 0.5)[..., None]
    interior = np.exp(0.25 * _noise(rng, shape, h / 8.0) + 0.08 * _noise(rng, shape, 0.6))[..., None]
    glass_img = glass_c * gradient * interior
    frame_img = frame_c * (1.0 + 0.06 * _noise(rng, shape, 0.7))[..., None]
    return _finish(is_frame * frame_img + (1.0 - is_frame) * glass_img)


def door(
    rng: np.random.Generator | int | None = None,
    *,
    shape: Shape = (256, 128),
    panels: tuple[int, int] = (3, 2),
    color: tuple[float, float, float] = (0.16, 0.07, 0.03),
) -> np.ndarray:
    """Panelled wooden door: stiles and rails, raised panels with dark mouldings, a brass handle.

    Intended mapping: **once per door**, UVs ``[0, 1]`` over the opening (``v`` up).

    Parameters
    ----------
    rng : numpy.random.Generator or int or None
        Source of randomness.
    shape : (int, int), optional
        ``(Ht, Wt)`` in pixels (a door is about twice as tall as wide).
    panels : (int, int), optional
        Panel rows and columns.
    color : (3,) float, optional
        Mean linear RGB albedo of the wood.

    Returns
    -------
    (Ht, Wt, 3) float32
        Linear RGB albedo in [0.02, 0.9].
    """
    rng = _generator(rng)
    shape = _shape(shape)
    base = _color(color, "color")
    rows, cols = (int(p) for p in panels)
    if rows < 1 or cols < 1:
        raise ValueError(f"panels must be positive, got {panels!r}")
    h, w = shape
    img = wood(rng, shape=shape, color=tuple(base), grain_contrast=0.2, knots=2).astype(np.float64)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64) + 0.5
    margin = 0.12 * w
    ph, pw = (h - margin) / rows, (w - margin) / cols
    py, px = (yy - margin / 2) / ph, (xx - margin / 2) / pw
    inside = (py > 0) & (py < rows) & (px > 0) & (px < cols)
    fy, fx = py - np.floor(py), px - np.floor(px)
    d = np.minimum(np.minimum(fy, 1 - fy) * ph, np.minimum(fx, 1 - fx) * pw)
    panel = inside & (d > 0.5 * margin)
    moulding = inside & (np.abs(d - 0.5 * margin) < 0.06 * w)
    shade = np.where(moulding, 0.55, np.where(panel, 1.12, 1.0))
    img *= cv2.GaussianBlur(shade, (0, 0), 0.8)[..., None]
    handle = np.hypot(xx - 0.85 * w, yy - 0.5 * h) < 0.035 * w
    img[handle] = np.array([0.45, 0.33, 0.10]) * (1.0 + 0.1 * rng.standard_normal((int(handle.sum()), 1)))
    return _finish(img)


def sign(
    rng: np.random.Generator | int | None = None,
    *,
    text: str = "PLACE DES ARTS",
    shape: Shape = (128, 512),
    background: tuple[float, float, float] = (0.03, 0.07, 0.22),
    ink: tuple[float, float, float] = (0.80, 0.80, 0.75),
) -> np.ndarray:
    """Enamelled street plaque with lettering (``cv2.putText``), a border and wear.

    Intended mapping: **once per plaque**, UVs ``[0, 1]`` over its front face (``v`` up, text
    reads left to right for increasing ``u``). The 1-pixel outer border has the background
    colour, so UVs pointing at a corner texel (e.g. ``(0.005, 0.005)``) give the plaque edges.

    Parameters
    ----------
    rng : numpy.random.Generator or int or None
        Source of randomness.
    text : str, optional
        ASCII text, scaled to fill about 85 % of the width.
    shape : (int, int), optional
        ``(Ht, Wt)`` in pixels.
    background, ink : (3,) float, optional
        Linear RGB albedo of the enamel and of the letters and border line.

    Returns
    -------
    (Ht, Wt, 3) float32
        Linear RGB albedo in [0.02, 0.9].
    """
    rng = _generator(rng)
    shape = _shape(shape)
    bg, fg = _color(background, "background"), _color(ink, "ink")
    if not isinstance(text, str) or not text.strip() or not text.isascii():
        raise ValueError(f"text must be a non-empty ASCII string, got {text!r}")
    h, w = shape
    mask = np.zeros(shape, np.uint8)
    font = cv2.FONT_HERSHEY_DUPLEX
    (tw, th), _ = cv2.getTextSize(text, font, 1.0, 2)
    scale = min(0.85 * w / tw, 0.55 * h / th)
    thickness = max(1, int(round(2.0 * scale)))
    (tw, th), base_line = cv2.getTextSize(text, font, scale, thickness)
    origin = (int((w - tw) / 2), int((h + th) / 2))
    cv2.putText(mask, text, origin, font, scale, 255, thickness, cv2.LINE_AA)
    b = max(2, int(0.08 * h))
    cv2.rectangle(mask, (b, b), (w - 1 - b, h - 1 - b), 255, max(1, int(0.03 * h)), cv2.LINE_AA)
    m = (mask.astype(np.float64) / 255.0)[..., None]
    enamel = bg * (1.0 + 0.08 * _noise(rng, shape, h / 6.0) + 0.05 * _noise(rng, shape, 0.6))[..., None]
    letters = fg * (1.0 + 0.04 * _noise(rng, shape, 0.6))[..., None]
    img = (1.0 - m) * enamel + m * letters
    rust = _smoothstep(2.0, 2.6, _noise(rng, shape, 2.0))[..., None]
    img = (1.0 - rust) * img + rust * np.array([0.20, 0.09, 0.04])
    img[0, :] = img[-1, :] = bg
    img[:, 0] = img[:, -1] = bg
    return _finish(img)


#: All texture functions by name (each takes ``rng`` and keyword-only options).
TEXTURES: dict[str, Callable[..., np.ndarray]] = {
    "asphalt": asphalt,
    "bark": bark,
    "brick": brick,
    "door": door,
    "grass": grass,
    "leaves": leaves,
    "painted_metal": painted_metal,
    "paving": paving,
    "plaster": plaster,
    "sign": sign,
    "stone": stone,
    "window": window,
    "wood": wood,
}
