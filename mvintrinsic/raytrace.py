"""Ray casting against the proxy (open3d / Embree).

A :class:`Tracer` is built once per proxy and answers batched queries: first hits and occlusion.
The paper ray-traces the proxy to compute sky and indirect shading and the approximate sun
visibility (Duchêne et al. 2015, Sec. 4), and lifts the user's two sun clicks to 3D (Sec. 3.2).

Point-cloud proxies (the paper uses the vertices of the reconstructed mesh as a point cloud) are
traced as *surfels*: every point becomes a small square of two triangles centred on the point,
normal to its normal, with half-width ``surfel_scale`` times the mean distance to its
``surfel_neighbors`` nearest neighbours, so neighbouring squares overlap and the surface is
closed where the sampling is dense.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ._libusb import ensure_libusb
from ._validation import describe
from .scene import Proxy

__all__ = ["RayHits", "Tracer"]

#: Rays per Embree call; bounds the temporary memory (about 100 bytes a ray).
DEFAULT_BATCH = 1 << 20


@dataclass(frozen=True, eq=False)
class RayHits:
    """First intersections of a batch of rays with the proxy.

    Parameters
    ----------
    hit : (N,) bool
        Whether the ray hit the proxy within ``[t_min, t_max]``.
    t : (N,) float64
        Distance along the (unit) ray to the hit, metres; ``inf`` where ``hit`` is False.
    points : (N, 3) float64
        World-frame hit points; NaN where ``hit`` is False.
    normals : (N, 3) float64
        Unit geometric normal of the hit triangle (or surfel), oriented toward the ray origin;
        NaN where ``hit`` is False.
    vertex : (N,) int64
        Index of the proxy vertex nearest the hit (the surfel's point for point clouds); -1 where
        ``hit`` is False.
    triangle : (N,) int64
        Index of the hit triangle of a mesh proxy (of the surfel's point for point clouds); -1
        where ``hit`` is False.
    """

    hit: np.ndarray
    t: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    vertex: np.ndarray
    triangle: np.ndarray


def _check_rays(origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    directions = np.asarray(directions, dtype=np.float64)
    if directions.ndim != 2 or directions.shape[1] != 3:
        raise ValueError(f"directions must have shape (N, 3), got {describe(directions)}")
    origins = np.asarray(origins, dtype=np.float64)
    if origins.shape == (3,):
        origins = np.broadcast_to(origins, directions.shape)
    if origins.shape != directions.shape:
        raise ValueError(f"origins must have shape (3,) or {directions.shape}, got shape {origins.shape}")
    return origins, directions


class Tracer:
    """Embree acceleration structure over a :class:`~mvintrinsic.scene.Proxy`.

    Parameters
    ----------
    proxy : Proxy
        The geometry: traced as its triangles for a mesh, as surfels for a point cloud.
    surfel_scale : float, optional
        Half-width of a surfel in units of the mean distance to the point's nearest neighbours
        (point clouds only). 1.0 makes neighbouring surfels overlap by about a factor of two.
    surfel_neighbors : int, optional
        Number of nearest neighbours that set the local point spacing (point clouds only).

    Notes
    -----
    Embree works in float32: hits are accurate to about 1e-7 of the scene's extent.
    """

    def __init__(self, proxy: Proxy, *, surfel_scale: float = 1.0, surfel_neighbors: int = 6) -> None:
        if not isinstance(proxy, Proxy):
            raise TypeError(f"proxy must be a Proxy, got {describe(proxy)}")
        if not surfel_scale > 0:
            raise ValueError(f"surfel_scale must be positive, got {surfel_scale!r}")
        if surfel_neighbors < 1:
            raise ValueError(f"surfel_neighbors must be at least 1, got {surfel_neighbors!r}")
        ensure_libusb()
        import open3d as o3d

        self.proxy = proxy
        if proxy.is_mesh:
            vertices, triangles = proxy.vertices, proxy.triangles
            # Triangle -> its three vertices; the nearest one is picked per hit from barycentrics.
            self._triangle_vertices = triangles
        else:
            vertices, triangles = self._surfels(proxy, surfel_scale, surfel_neighbors)
            self._triangle_vertices = None
        self._scene = o3d.t.geometry.RaycastingScene()
        self._scene.add_triangles(
            o3d.core.Tensor(np.ascontiguousarray(vertices, dtype=np.float32)),
            o3d.core.Tensor(np.ascontiguousarray(triangles, dtype=np.uint32)),
        )
        self._o3c = o3d.core
        # Embree builds its BVH on the first query: do it now, so construction carries the cost.
        self._scene.test_occlusions(o3d.core.Tensor(np.zeros((1, 6), dtype=np.float32)))

    @staticmethod
    def _surfels(proxy: Proxy, scale: float, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Two triangles per point: a square of half-width ``scale * spacing`` normal to it."""
        points, normals = proxy.vertices, proxy.normals
        distances, _ = cKDTree(points).query(points, k=min(k, len(points) - 1) + 1)
        spacing = distances[:, 1:].mean(axis=1)
        spacing = np.where(spacing > 0, spacing, np.median(spacing[spacing > 0]))
        half = (scale * spacing)[:, None]
        # Tangent frame: a = n x e (e the axis least aligned with n), b = n x a.
        axis = np.eye(3)[np.argmin(np.abs(normals), axis=1)]
        a = np.cross(normals, axis)
        a /= np.linalg.norm(a, axis=1, keepdims=True)
        b = np.cross(normals, a)
        corners = np.stack(
            [points + half * (-a - b), points + half * (a - b), points + half * (a + b), points + half * (-a + b)],
            axis=1,
        ).reshape(-1, 3)
        base = 4 * np.arange(len(points))[:, None]
        triangles = np.concatenate([base + [0, 1, 2], base + [0, 2, 3]], axis=1).reshape(-1, 3)
        return corners, triangles

    def _rays(self, origins: np.ndarray, directions: np.ndarray):
        rays = np.concatenate([origins, directions], axis=1).astype(np.float32)
        return self._o3c.Tensor(rays)

    def intersect(
        self,
        origins: np.ndarray,
        directions: np.ndarray,
        *,
        t_min: float = 0.0,
        t_max: float = np.inf,
        batch: int = DEFAULT_BATCH,
    ) -> RayHits:
        """First hit of each ray.

        Parameters
        ----------
        origins : (3,) or (N, 3) array_like
            Ray origins, world frame, metres (one shared origin or one per ray).
        directions : (N, 3) array_like
            Unit ray directions, world frame.
        t_min, t_max : float, optional
            Hits closer than ``t_min`` or farther than ``t_max`` metres are ignored (``t_min``
            moves the origin forward, the usual offset against self-intersection).
        batch : int, optional
            Rays per Embree call.

        Returns
        -------
        RayHits
        """
        origins, directions = _check_rays(origins, directions)
        n = len(directions)
        t = np.full(n, np.inf)
        normals = np.full((n, 3), np.nan)
        vertex = np.full(n, -1, dtype=np.int64)
        triangle = np.full(n, -1, dtype=np.int64)
        for start in range(0, n, batch):
            sl = slice(start, min(start + batch, n))
            o = origins[sl] + t_min * directions[sl]
            answer = self._scene.cast_rays(self._rays(o, directions[sl]))
            t_hit = answer["t_hit"].numpy().astype(np.float64) + t_min
            ok = np.isfinite(t_hit) & (t_hit <= t_max)
            t[sl] = np.where(ok, t_hit, np.inf)
            prim = answer["primitive_ids"].numpy().astype(np.int64)
            nrm = answer["primitive_normals"].numpy().astype(np.float64)
            idx = np.flatnonzero(ok) + start
            local = idx - start
            if self._triangle_vertices is None:
                vertex[idx] = triangle[idx] = prim[local] // 2
            else:
                triangle[idx] = prim[local]
                uv = answer["primitive_uvs"].numpy().astype(np.float64)[local]
                bary = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)
                vertex[idx] = self._triangle_vertices[prim[local], np.argmax(bary, axis=1)]
            nrm = nrm[local]
            nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
            flip = np.einsum("ij,ij->i", nrm, directions[idx]) > 0
            nrm[flip] *= -1
            normals[idx] = nrm
        hit = np.isfinite(t)
        points = np.where(hit[:, None], origins + np.where(hit, t, 0.0)[:, None] * directions, np.nan)
        return RayHits(hit=hit, t=t, points=points, normals=normals, vertex=vertex, triangle=triangle)

    def occluded(
        self,
        origins: np.ndarray,
        directions: np.ndarray,
        *,
        t_min: float = 0.0,
        t_max: float = np.inf,
        batch: int = DEFAULT_BATCH,
    ) -> np.ndarray:
        """Whether anything blocks each ray between ``t_min`` and ``t_max``, (N,) bool.

        Cheaper than :meth:`intersect` (any hit stops the traversal).
        """
        origins, directions = _check_rays(origins, directions)
        n = len(directions)
        out = np.zeros(n, dtype=bool)
        for start in range(0, n, batch):
            sl = slice(start, min(start + batch, n))
            answer = self._scene.test_occlusions(
                self._rays(origins[sl], directions[sl]), tnear=float(t_min), tfar=float(min(t_max, 3.0e38))
            )
            out[sl] = answer.numpy().astype(bool)
        return out

    def __repr__(self) -> str:
        return f"Tracer({self.proxy!r})"
