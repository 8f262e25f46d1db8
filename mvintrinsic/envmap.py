"""Equirectangular environment maps: the world frame, texel directions and solid angles.

The map follows the parameterisation of ``docs/conventions.md`` exactly: ``(He, 2 He, 3)``
float32, row ``v`` at polar angle ``θ = π (v + 0.5) / He`` from ``up``, column ``u`` at azimuth
``φ = 2π (u + 0.5) / W`` counter-clockwise seen from above from ``x_h`` (horizontal projection of
world +X, or of +Y when ``up`` is along ±X), ``y_h = up × x_h``. Colours are linear RGB with
Rec.709 / sRGB primaries; radiance is in the images' own units.
"""

from __future__ import annotations

import math

import numpy as np

from ._validation import as_array, as_unit_vector, describe

__all__ = [
    "direction_to_texel",
    "envmap_directions",
    "horizontal_frame",
    "texel_solid_angles",
]

_Z_UP = (0.0, 0.0, 1.0)


# ------------------------------------------------------------------------------------------------
# Environment-map geometry (docs/conventions.md, "Environment maps")
# ------------------------------------------------------------------------------------------------
def horizontal_frame(up: object, reference: object | None = None) -> np.ndarray:
    """Orthonormal world frame ``(x_h, y_h, up)`` with ``x_h`` horizontal, (3, 3) float64 rows.

    Parameters
    ----------
    up : (3,) array_like
        World up vector (normalised here).
    reference : (3,) array_like, optional
        Direction whose horizontal projection becomes ``x_h``. Default: world +X, or +Y when
        ``up`` is along +/-X: the environment-map frame of ``docs/conventions.md``.

    Returns
    -------
    (3, 3) float64
        Rows ``x_h``, ``y_h = up x x_h``, ``up``: azimuth grows counter-clockwise from ``x_h``
        seen from above.
    """
    up = as_unit_vector(up, "up")
    if reference is None:
        reference = np.array([0.0, 1.0, 0.0]) if abs(up[0]) > 1.0 - 1e-9 else np.array([1.0, 0.0, 0.0])
    ref = np.asarray(reference, dtype=np.float64)
    x_h = ref - (ref @ up) * up
    if np.linalg.norm(x_h) < 1e-9:
        raise ValueError(f"reference {ref.tolist()} is parallel to up {up.tolist()}")
    x_h /= np.linalg.norm(x_h)
    return np.stack([x_h, np.cross(up, x_h), up])


def _check_height(height: object, name: str = "height") -> int:
    if isinstance(height, bool) or not isinstance(height, (int, np.integer)) or height < 2:
        raise ValueError(f"{name} must be an integer >= 2 (rows of the environment map), got {describe(height)}")
    return int(height)


def _unit_rows(value: object, name: str) -> np.ndarray:
    """``(N, 3)`` finite non-zero vectors, normalised to unit length (float64)."""
    array = as_array(value, name, shape=(None, 3), dtype=np.float64)
    norms = np.linalg.norm(array, axis=1)
    if len(array) and norms.min() < 1e-12:
        raise ValueError(f"{name} must be non-zero vectors, got {int((norms < 1e-12).sum())} zero rows")
    return array / norms[:, None] if len(array) else array.copy()


def envmap_directions(height: int, *, up: object = _Z_UP) -> np.ndarray:
    """World direction of the centre of every texel of an equirectangular map.

    Parameters
    ----------
    height : int
        ``He``, number of rows; the map has ``2 He`` columns.
    up : (3,) array_like, optional
        World up vector (normalised here), default +Z.

    Returns
    -------
    (He, 2 He, 3) float64
        Unit directions, world frame: texel ``(v, u)`` looks at polar angle
        ``θ = π (v + 0.5) / He`` from ``up`` and azimuth ``φ = 2π (u + 0.5) / (2 He)``,
        ``d = sin θ cos φ x_h + sin θ sin φ y_h + cos θ up`` (``docs/conventions.md``).
    """
    height = _check_height(height)
    frame = horizontal_frame(up)
    width = 2 * height
    theta = math.pi * (np.arange(height) + 0.5) / height
    phi = 2.0 * math.pi * (np.arange(width) + 0.5) / width
    st, ct = np.sin(theta)[:, None, None], np.cos(theta)[:, None, None]
    local = np.concatenate(
        [
            st * np.cos(phi)[None, :, None],
            st * np.sin(phi)[None, :, None],
            np.broadcast_to(ct, (height, width, 1)),
        ],
        axis=2,
    )
    return local @ frame  # sum_i local_i * frame[i]


def direction_to_texel(directions: object, height: int, *, up: object = _Z_UP) -> tuple[np.ndarray, np.ndarray]:
    """Texel of the equirectangular map that contains each direction.

    Parameters
    ----------
    directions : (N, 3) array_like
        World directions (normalised here; zero vectors are rejected).
    height : int
        ``He`` of the map.
    up : (3,) array_like, optional
        World up vector, default +Z.

    Returns
    -------
    rows : (N,) int64
        ``v = floor(θ He / π)`` in ``[0, He)``.
    cols : (N,) int64
        ``u = floor(φ W / 2π)`` in ``[0, W)``, ``W = 2 He``.
    """
    height = _check_height(height)
    d = _unit_rows(directions, "directions")
    local = d @ horizontal_frame(up).T
    theta = np.arccos(np.clip(local[:, 2], -1.0, 1.0))
    phi = np.mod(np.arctan2(local[:, 1], local[:, 0]), 2.0 * math.pi)
    width = 2 * height
    rows = np.clip(np.floor(theta * height / math.pi).astype(np.int64), 0, height - 1)
    cols = np.mod(np.floor(phi * width / (2.0 * math.pi)).astype(np.int64), width)
    return rows, cols


def texel_solid_angles(height: int) -> np.ndarray:
    """Exact solid angle of every texel of an equirectangular map.

    Parameters
    ----------
    height : int
        ``He`` of the map.

    Returns
    -------
    (He, 2 He) float64
        Steradians, ``Δφ (cos θ_top − cos θ_bottom)`` for the texel's row; they sum to ``4π``.
    """
    height = _check_height(height)
    edges = np.cos(math.pi * np.arange(height + 1) / height)
    row = (2.0 * math.pi / (2 * height)) * (edges[:-1] - edges[1:])
    return np.repeat(row[:, None], 2 * height, axis=1)
