"""Dominant planes of the proxy, and vertex normals snapped to them (beyond the paper).

Every shading term of the image model reads the receiver's normal: Step 1's sun shading
``S_sun = L_sun max(0, n . w_sun)`` (Eq. 3), the cosines of Step 2's light/shadow pairs (Eq. 5)
and the relit cosine of Sec. 8. The paper takes the normals of the reconstructed mesh. An MVS
proxy's normals, even smoothed over 0.4 m (:func:`~mvintrinsic.raytrace.smooth_normals`), keep a
low-frequency waviness of its fusion: on the MVS-like proxy of a synthetic street (480x360, 8
views) the smoothed normals of the pixels the proxy explains are a median 5.8 degrees from the
exact mesh's, and 30% of them more than 10 degrees (the facades; the ground is right), which is
a 17% error of the cosine at a sun 80 degrees from the normal.

Man-made outdoor scenes are mostly planes. :func:`detect_planes` finds the proxy's dominant
planes by RANSAC [1]_ with one-point hypotheses (a vertex and its smoothed normal, [2]_), each
refined by a least-squares fit to its inliers; :func:`planar_normals` gives a vertex within
:attr:`PlaneConfig.distance` of a plane, whose smoothed normal is within
:attr:`PlaneConfig.angle` of the plane's, the plane's normal (on the side of its own). Creases
stay sharp (a building's corner belongs to two planes, each vertex to the nearer), and a vertex
on no plane keeps its smoothed normal. On that street the explained pixels' median error falls
to 0.3 degrees (8% above 10: the window reveals, cornices and edges the proxy rounds).

**Curved surfaces.** A plane's inliers lie in a slab of half-width ``d`` (``distance``); a
surface of curvature radius ``r`` fits in it over an arc of half-angle ``acos(1 - d / r)``, the
error a snapped normal could take there (26 degrees at 1 m, 11 at 5 m). On a curved surface the
normals tilt away from the plane's as a linear function of the position (``(x - c) / r``); on a
plane, even a wavy MVS facade, the tilt is noise. A candidate whose tilt the position explains
(``R^2`` of a linear fit above :attr:`PlaneConfig.curvature`, 0.6) is not kept: spheres and
cylinders of 1 to 5 m radius score 1.00, the planes of four synthetic scenes' MVS proxies
0.03-0.45.

References
----------
.. [1] M. A. Fischler and R. C. Bolles, "Random sample consensus: a paradigm for model fitting
   with applications to image analysis and automated cartography", Communications of the ACM
   24(6), 381-395, 1981.
.. [2] R. Schnabel, R. Wahl and R. Klein, "Efficient RANSAC for Point-Cloud Shape Detection",
   Computer Graphics Forum 26(2), 214-226, 2007 (a plane from one point and its normal).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ._validation import as_array, is_real

__all__ = ["PlaneConfig", "Planes", "detect_planes", "planar_normals"]


@dataclass(frozen=True)
class PlaneConfig:
    """Options of the proxy's plane detection (:func:`detect_planes`) and snapping (:func:`planar_normals`).

    Not in the paper; the values were chosen on one synthetic street (module docstring) and kept on
    every scene of the benchmarks.

    Parameters
    ----------
    distance : float
        Metres; a vertex farther than this from a plane is not its inlier; > 0. 0.1, about the MVS
        proxy's waviness (90% of its vertices within 10 cm of the exact mesh).
    angle : float
        Degrees; a vertex whose smoothed normal is farther than this from the plane's is not its
        inlier; in (0, 90). 30, above the smoothed normals' 90th-percentile error on the facades (21).
    curvature : float
        A candidate whose inliers' normals tilt away from its normal as a linear function of their
        position in the plane (a least-squares fit of the tilt's two in-plane components on the
        in-plane coordinates) with ``R^2`` above this is a curved surface's cap, not a plane: it is
        not kept and its inliers are not sought again; in (0, 1]. 0.6: spheres and cylinders of 1-5 m
        radius score 1.00, the planes of four synthetic scenes' MVS proxies 0.03-0.45 (their
        waviness is not a function of position; module docstring, "Curved surfaces").
    min_share : float
        A plane with fewer inliers than this share of the sampled vertices ends the detection; in (0, 1].
    max_planes : int
        At most this many planes; >= 1.
    hypotheses : int
        One-point hypotheses drawn per plane; >= 1.
    sample : int
        Vertices (drawn at random) the detection runs on; the snapping reads every vertex; >= 100.
    seed : int
        Seed of the draws (:func:`numpy.random.default_rng`): the planes are the same on every run.
    """

    distance: float = 0.1
    angle: float = 30.0
    curvature: float = 0.6
    min_share: float = 0.01
    max_planes: int = 30
    hypotheses: int = 256
    sample: int = 50_000
    seed: int = 0

    def __post_init__(self) -> None:
        if not is_real(self.distance) or not 0.0 < self.distance < math.inf:
            raise ValueError(f"distance must be a finite number > 0 (metres), got {self.distance!r}")
        if not is_real(self.angle) or not 0.0 < self.angle < 90.0:
            raise ValueError(f"angle must be a number in (0, 90) (degrees), got {self.angle!r}")
        if not is_real(self.curvature) or not 0.0 < self.curvature <= 1.0:
            raise ValueError(f"curvature must be a number in (0, 1], got {self.curvature!r}")
        object.__setattr__(self, "angle", float(self.angle))
        object.__setattr__(self, "curvature", float(self.curvature))
        if not is_real(self.min_share) or not 0.0 < self.min_share <= 1.0:
            raise ValueError(f"min_share must be a number in (0, 1], got {self.min_share!r}")
        for name, least in (("max_planes", 1), ("hypotheses", 1), ("sample", 100), ("seed", 0)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
                raise ValueError(f"{name} must be an integer >= {least}, got {value!r}")
        object.__setattr__(self, "distance", float(self.distance))
        object.__setattr__(self, "min_share", float(self.min_share))


@dataclass(frozen=True, eq=False)
class Planes:
    """Planes ``n @ x + c = 0`` in the world frame (:func:`detect_planes`).

    Parameters
    ----------
    normals : (K, 3) float64
        Unit plane normals (their sign is arbitrary).
    offsets : (K,) float64
        ``c``, metres.
    support : (K,) int64
        Inliers among the sampled vertices when the plane was found, in the order found (largest first).
    """

    normals: np.ndarray
    offsets: np.ndarray
    support: np.ndarray

    def __len__(self) -> int:
        return len(self.offsets)


def _refit(points: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares plane through ``points`` (M, 3): the unit normal of least variance and its offset."""
    centre = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - centre, full_matrices=False)
    normal = vt[2]
    return normal, -float(normal @ centre)


def _tilt_r2(points: np.ndarray, normals: np.ndarray, normal: np.ndarray) -> float:
    """``R^2`` of the least-squares fit of the normals' in-plane tilt on the points' in-plane position.

    ``points``, ``normals`` (M, 3): a candidate's inliers; ``normal`` (3,) unit, the plane's. On a
    sphere or a cylinder the tilt is a linear function of the position (``(x - c) / r``): 1; on a
    wavy plane it is not: near 0.
    """
    helper = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    first = np.cross(normal, helper)
    first /= np.linalg.norm(first)
    basis = np.stack([first, np.cross(normal, first)], axis=1)  # (3, 2), in the plane
    position = (points - points.mean(axis=0)) @ basis
    tilt = (normals * np.sign(normals @ normal)[:, None]) @ basis
    design = np.column_stack([np.ones(len(points)), position])
    coefficients, *_ = np.linalg.lstsq(design, tilt, rcond=None)
    total = float(((tilt - tilt.mean(axis=0)) ** 2).sum())
    return 1.0 - float(((tilt - design @ coefficients) ** 2).sum()) / total if total > 0 else 0.0


def _inliers(points: np.ndarray, normals: np.ndarray, normal: np.ndarray, offset: float,
             distance: float, cos_angle: float) -> np.ndarray:
    """(M,) bool: within ``distance`` of the plane, with a normal within the angle of its (either side)."""
    return (np.abs(points @ normal + offset) <= distance) & (np.abs(normals @ normal) >= cos_angle)


def detect_planes(points: np.ndarray, normals: np.ndarray, *, config: PlaneConfig | None = None) -> Planes:
    """Dominant planes of a point set with normals, by one-point RANSAC (module docstring).

    Greedy: the plane with the most inliers among :attr:`PlaneConfig.hypotheses` candidates (the
    plane through a random remaining vertex, normal to its normal), refined twice by a
    least-squares fit to its inliers, is kept unless its inliers' normals tilt as a curved
    surface's do (:attr:`PlaneConfig.curvature`), and its inliers are removed; the detection ends when the
    best plane holds fewer than :attr:`PlaneConfig.min_share` of the sampled vertices, or after
    :attr:`PlaneConfig.max_planes`.

    Parameters
    ----------
    points : (N, 3) array_like
        World frame, metres (the proxy's vertices).
    normals : (N, 3) array_like
        Unit normals (e.g. :func:`~mvintrinsic.raytrace.smooth_normals`).
    config : PlaneConfig, optional

    Returns
    -------
    Planes
        Possibly empty (no plane holds ``min_share`` of the vertices).

    Raises
    ------
    ValueError
        If ``points`` and ``normals`` are not (N, 3) arrays of the same N, or hold non-finite values
        (the message names the argument).
    """
    config = PlaneConfig() if config is None else config
    if not isinstance(config, PlaneConfig):
        raise TypeError(f"config must be a PlaneConfig, got {type(config).__name__}")
    points = as_array(points, "points", shape=(None, 3), dtype=np.float64)
    normals = as_array(normals, "normals", shape=(len(points), 3), dtype=np.float64)
    rng = np.random.default_rng(config.seed)
    n = len(points)
    chosen = rng.choice(n, size=config.sample, replace=False) if n > config.sample else np.arange(n)
    p, q = points[chosen], normals[chosen]
    cos_angle = math.cos(math.radians(config.angle))
    least = max(3, math.ceil(config.min_share * len(p)))
    remaining = np.ones(len(p), dtype=bool)
    found: list[tuple[np.ndarray, float, int]] = []
    while len(found) < config.max_planes and remaining.sum() >= least:
        index = np.flatnonzero(remaining)
        seeds = rng.choice(index, size=min(config.hypotheses, len(index)), replace=False)
        rest_p, rest_q = p[index], q[index]
        best, best_count = None, 0
        for start in range(0, len(seeds), 64):  # (64, M) distance tables at a time
            cand_n = q[seeds[start:start + 64]]
            cand_c = -np.einsum("ij,ij->i", cand_n, p[seeds[start:start + 64]])
            near = np.abs(rest_p @ cand_n.T + cand_c) <= config.distance
            near &= np.abs(rest_q @ cand_n.T) >= cos_angle
            counts = near.sum(axis=0)
            k = int(np.argmax(counts))
            if counts[k] > best_count:
                best, best_count = (cand_n[k], float(cand_c[k])), int(counts[k])
        if best is None or best_count < least:
            break
        normal, offset = best
        for _ in range(2):  # least-squares refinement on the inliers
            inside = _inliers(rest_p, rest_q, normal, offset, config.distance, cos_angle)
            if inside.sum() < 3:
                break
            normal, offset = _refit(rest_p[inside])
        inside = _inliers(rest_p, rest_q, normal, offset, config.distance, cos_angle)
        if inside.sum() < least:
            break
        remaining[index[inside]] = False
        if _tilt_r2(rest_p[inside], rest_q[inside], normal) <= config.curvature:  # else a curved surface's cap
            found.append((normal, offset, int(inside.sum())))
    if not found:
        return Planes(np.zeros((0, 3)), np.zeros(0), np.zeros(0, np.int64))
    return Planes(np.array([f[0] for f in found]), np.array([f[1] for f in found]),
                  np.array([f[2] for f in found], dtype=np.int64))


def planar_normals(points: np.ndarray, normals: np.ndarray, planes: Planes, *,
                   config: PlaneConfig | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Normals snapped to the nearest plane each vertex is an inlier of (module docstring).

    Parameters
    ----------
    points, normals : (N, 3) array_like
        World frame; unit normals (the smoothed ones :func:`detect_planes` was given).
    planes : Planes
    config : PlaneConfig, optional
        Its ``distance`` and ``angle`` make an inlier.

    Returns
    -------
    normals : (N, 3) float64
        The plane's unit normal, on the side of the vertex's own, where the vertex is an inlier of
        a plane; its own normal elsewhere.
    plane : (N,) int64
        The plane each vertex took (index into ``planes``), -1 for none.
    """
    config = PlaneConfig() if config is None else config
    points = np.asarray(points, dtype=np.float64)
    normals = np.asarray(normals, dtype=np.float64)
    out = normals.copy()
    plane = np.full(len(points), -1, dtype=np.int64)
    nearest = np.full(len(points), np.inf)
    cos_angle = math.cos(math.radians(config.angle))
    for k in range(len(planes)):
        normal = planes.normals[k]
        distance = np.abs(points @ normal + planes.offsets[k])
        dot = normals @ normal
        take = (distance <= config.distance) & (np.abs(dot) >= cos_angle) & (distance < nearest)
        out[take] = np.where(dot[take, None] < 0, -normal, normal)
        plane[take], nearest[take] = k, distance[take]
    return out, plane
