"""Ray casting against the proxy (open3d / Embree), and the proxy's normals and mesh utilities.

A :class:`Tracer` is built once per proxy and answers batched queries: first hits and occlusion.
Step 1 (:mod:`.env_shading`) casts its hemisphere and sun rays with it, relighting its shadow
rays, and the same tracer lifts the user's two sun clicks to 3D (Sec. 3.2).

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
from ._validation import describe, is_real
from .camera import Camera
from .image_model import clamped_cosine
from .planes import PlaneConfig, detect_planes, planar_normals
from .scene import Proxy

__all__ = [
    "RayHits",
    "Tracer",
    "cosine_hemisphere",
    "depth_map",
    "interpolate_points",
    "morton_order",
    "rasterize",
    "smooth_normals",
    "subdivide",
    "sun_visibility",
    "triangle_scene",
    "tangent_frames",
    "vertex_normals",
    "voxel_subsample",
]

#: Rays per Embree call; bounds the temporary memory (about 100 bytes a ray).
DEFAULT_BATCH = 1 << 20

#: Variance per axis, in squared mean edge lengths, that one step of :func:`smooth_normals`'s
#: averaging (a vertex and its mesh neighbours, equal weights) adds on a regular triangle mesh:
#: six neighbours out of seven at one edge length, half of it along each in-plane axis,
#: ``(6 / 7) / 2``.
SMOOTHING_VARIANCE_PER_STEP = 3.0 / 7.0


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
    barycentric : (N, 3) float64
        Weights of the hit triangle's three vertices (``proxy.triangles[triangle]``) at the hit;
        NaN where ``hit`` is False or for point clouds.
    """

    hit: np.ndarray
    t: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    vertex: np.ndarray
    triangle: np.ndarray
    barycentric: np.ndarray


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


def triangle_scene(vertices: np.ndarray, triangles: np.ndarray):
    """An open3d ``RaycastingScene`` (Embree) over a triangle mesh, its BVH already built.

    Parameters
    ----------
    vertices : (V, 3) array_like
        World coordinates (stored as float32).
    triangles : (T, 3) array_like
        Vertex indices (stored as uint32).

    Returns
    -------
    open3d.t.geometry.RaycastingScene
        Embree builds its BVH on the first query; one is made here, so that construction carries
        the cost rather than the first real query.
    """
    ensure_libusb()
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.ascontiguousarray(vertices, dtype=np.float32)),
        o3d.core.Tensor(np.ascontiguousarray(triangles, dtype=np.uint32)),
    )
    scene.test_occlusions(o3d.core.Tensor(np.zeros((1, 6), dtype=np.float32)))
    return scene


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
        self._scene = triangle_scene(vertices, triangles)
        self._o3c = o3d.core

    @staticmethod
    def _surfels(proxy: Proxy, scale: float, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Two triangles per point: a square of half-width ``scale * spacing`` normal to it."""
        points, normals = proxy.vertices, proxy.normals
        distances, _ = cKDTree(points).query(points, k=min(k, len(points) - 1) + 1)
        spacing = distances[:, 1:].mean(axis=1)
        spacing = np.where(spacing > 0, spacing, np.median(spacing[spacing > 0]))
        half = (scale * spacing)[:, None]
        a, b = tangent_frames(normals)
        corners = np.stack(
            [points + half * (-a - b), points + half * (a - b), points + half * (a + b), points + half * (-a + b)],
            axis=1,
        ).reshape(-1, 3)
        base = 4 * np.arange(len(points))[:, None]
        triangles = np.concatenate([base + [0, 1, 2], base + [0, 2, 3]], axis=1).reshape(-1, 3)
        return corners, triangles

    def _rays(self, origins: np.ndarray, directions: np.ndarray):
        """Embree's ray tensor of ``origins`` and ``directions`` (N, 3) each (:func:`_ray_array`, no second copy)."""
        return self._o3c.Tensor.from_numpy(_ray_array(origins, directions))

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
        barycentric = np.full((n, 3), np.nan)
        # Embree's answers gathered at the hits before they are widened to float64, and the (N, 3) arithmetic a
        # column at a time (NumPy runs an (N, 3) broadcast as N inner loops of 3): the same numbers, fewer and
        # smaller temporaries (fresh memory is slow to touch on this project's machines).
        for start in range(0, n, batch):
            sl = slice(start, min(start + batch, n))
            o = origins[sl] + t_min * directions[sl]
            answer = self._scene.cast_rays(self._rays(o, directions[sl]))
            t_hit = answer["t_hit"].numpy().astype(np.float64) + t_min
            ok = np.isfinite(t_hit) & (t_hit <= t_max)
            t[sl] = np.where(ok, t_hit, np.inf)
            local = np.flatnonzero(ok)
            idx = local + start
            prim = answer["primitive_ids"].numpy()[local].astype(np.int64)
            if self._triangle_vertices is None:
                vertex[idx] = triangle[idx] = prim // 2
            else:
                triangle[idx] = prim
                uv = answer["primitive_uvs"].numpy()[local].astype(np.float64)
                weights = (1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1])
                for k, weight in enumerate(weights):
                    barycentric[idx, k] = weight
                # np.argmax over the three weights: the first of the largest
                corner = np.where(weights[1] > weights[0], 1, 0)
                corner[weights[2] > np.maximum(weights[0], weights[1])] = 2
                vertex[idx] = self._triangle_vertices[prim, corner]
            nrm = answer["primitive_normals"].numpy()[local].astype(np.float64)
            length = nrm[:, 0] * nrm[:, 0]
            length += nrm[:, 1] * nrm[:, 1]
            length += nrm[:, 2] * nrm[:, 2]
            np.sqrt(length, out=length)  # np.linalg.norm(nrm, axis=1), summed in its order
            for k in range(3):
                nrm[:, k] /= length
            flip = np.einsum("ij,ij->i", nrm, directions[idx]) > 0
            nrm[flip] *= -1
            normals[idx] = nrm
        hit = np.isfinite(t)
        along = np.where(hit, t, 0.0)
        points = np.empty((n, 3))
        for k in range(3):
            np.multiply(along, directions[:, k], out=points[:, k])
            points[:, k] += origins[:, k]  # origins + t d, as the (N, 3) sum
        points[~hit] = np.nan
        return RayHits(hit=hit, t=t, points=points, normals=normals, vertex=vertex, triangle=triangle,
                       barycentric=barycentric)

    def interpolate(self, values: np.ndarray, hits: RayHits) -> np.ndarray:
        """Per-vertex ``values (N, ...)`` at the hit points, ``(R, ...)`` float64, NaN on misses.

        Barycentric interpolation over the hit triangle for meshes, the surfel's point value for
        point clouds.
        """
        values = np.asarray(values, dtype=np.float64)
        if len(values) != len(self.proxy.vertices):
            raise ValueError(f"values must have one row per proxy vertex ({len(self.proxy.vertices)}), got {len(values)}")
        out = np.full((len(hits.hit), *values.shape[1:]), np.nan)
        idx = np.flatnonzero(hits.hit)
        if self._triangle_vertices is None:
            out[idx] = values[hits.vertex[idx]]
        else:
            # w0 v0 + w1 v1 + w2 v2 in that order (the sum over the corners as np.sum takes it), one value column
            # at a time: gathers of contiguous columns, no (R, 3, ...) temporaries (2-10x faster on a 1000x750 view).
            corners = np.take(self._triangle_vertices, np.take(hits.triangle, idx), axis=0)
            weights = np.take(hits.barycentric, idx, axis=0)
            columns = np.ascontiguousarray(values.reshape(len(values), -1).T)
            sums = np.empty((columns.shape[0], len(idx)))
            term = np.empty(len(idx))
            for column, total in zip(columns, sums, strict=True):
                np.multiply(np.take(column, corners[:, 0]), weights[:, 0], out=total)
                for k in (1, 2):
                    total += np.multiply(np.take(column, corners[:, k]), weights[:, k], out=term)
            out[idx] = sums.T.reshape(len(idx), *values.shape[1:])
        return out

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

    @property
    def n_primitives(self) -> int:
        """How many distinct :attr:`RayHits.triangle` indices there are (triangles, or points)."""
        return len(self.proxy.triangles) if self._triangle_vertices is not None else len(self.proxy.vertices)

    def first_primitive(self, origins: np.ndarray, direction: np.ndarray, *, t_min: float = 0.0,
                        batch: int = DEFAULT_BATCH) -> tuple[np.ndarray, np.ndarray]:
        """Distance and primitive of each ray's first hit, without :meth:`intersect`'s extras.

        The lean query of relighting's proxy completion: no normals, points or barycentrics.

        Parameters
        ----------
        origins : (N, 3) array_like
            Ray origins, world frame, metres.
        direction : (3,) array_like
            One unit direction shared by every ray, world frame.
        t_min : float, optional
            Hits closer than ``t_min`` metres are ignored (the origin moves forward).
        batch : int, optional
            Rays per Embree call.

        Returns
        -------
        t : (N,) float32
            Metres along the ray from the given origin; ``inf`` on a miss.
        primitive : (N,) int64
            As :attr:`RayHits.triangle` (a point's index for a point cloud); -1 on a miss.
        """
        origins = np.asarray(origins)
        if origins.dtype != np.float32:
            # Forward in float64, then float32 as Embree takes them (as :meth:`intersect` does).
            direction64 = np.asarray(direction, dtype=np.float64).reshape(3)
            origins = (origins.astype(np.float64) + t_min * direction64).astype(np.float32)
            shift = np.float32(0.0)
        else:
            shift = np.float32(t_min)
        direction = np.asarray(direction, dtype=np.float32).reshape(3)
        n = len(origins)
        t = np.full(n, np.inf, dtype=np.float32)
        primitive = np.full(n, -1, dtype=np.int64)
        rays = np.empty((min(batch, n), 6), dtype=np.float32)
        for start in range(0, n, batch):
            m = min(batch, n - start)
            chunk = rays[:m]
            np.add(origins[start:start + m], shift * direction, out=chunk[:, :3])
            chunk[:, 3:] = direction
            t[start:start + m], primitive[start:start + m] = self._first_primitive_rays(chunk, t_min=t_min, batch=m)
        return t, primitive

    def _first_primitive_rays(self, rays: np.ndarray, *, t_min: float = 0.0,
                              batch: int = DEFAULT_BATCH) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`first_primitive` of Embree's rays as they are: ``rays`` (N, 6) float32, C-contiguous, each row
        an origin and a direction (world frame), read without a copy; ``t`` counts ``t_min`` more."""
        t, primitive = self._completion_hits(rays, batch=batch)
        t += np.float32(t_min)  # inf stays inf on a miss
        primitive[primitive == self.n_primitives] = -1
        return t, primitive

    def _completion_hits(self, rays: np.ndarray, *, batch: int = DEFAULT_BATCH) -> tuple[np.ndarray, np.ndarray]:
        """The first hit of each of Embree's ``rays`` ((N, 6) float32, C-contiguous, read without a copy) as a
        lookup table wants it: ``t`` (N,) float32, ``inf`` on a miss, and the primitive (N,) int64,
        :attr:`n_primitives` on a miss (the last entry of a
        :meth:`~mvintrinsic.shadow_caster.ShadowCaster.completion_blocked` table). Embree's arrays taken as they
        are: no masking pass per output (the relighter's per-sun completion query)."""
        n = len(rays)
        t = np.empty(n, dtype=np.float32)
        primitive = np.empty(n, dtype=np.int64)
        last = self.n_primitives
        for start in range(0, n, batch):
            m = min(batch, n - start)
            answer = self._scene.cast_rays(self._o3c.Tensor.from_numpy(rays[start:start + m]))
            t[start:start + m] = answer["t_hit"].numpy()  # inf where the ray misses
            prim = answer["primitive_ids"].numpy()  # uint32, open3d's invalid id (2**32 - 1) on a miss
            if self._triangle_vertices is None:
                prim = prim // 2
            np.minimum(prim, last, out=primitive[start:start + m], casting="unsafe")
        return t, primitive

    def __repr__(self) -> str:
        return f"Tracer({self.proxy!r})"


def _ray_array(origins: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """Embree's rays (N, 6) float32, C-contiguous: ``origins`` (N, 3) and one ``direction`` (3,) or one per ray
    (N, 3), each cast to float32 as Embree takes them (``open3d.core.Tensor.from_numpy`` reads them without a copy)."""
    rays = np.empty((len(origins), 6), dtype=np.float32)
    rays[:, :3] = origins
    rays[:, 3:] = direction
    return rays


def tangent_frames(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit tangents ``(t, b)`` with ``(t, b, n)`` right-handed, each (N, 3)."""
    axis = np.eye(3)[np.argmin(np.abs(normals), axis=1)]
    t = np.cross(normals, axis)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    return t, np.cross(normals, t)


def cosine_hemisphere(normals: np.ndarray, n_rays: int, *, rng: np.random.Generator | int | None = None) -> np.ndarray:
    """Stratified cosine-weighted directions about each normal, (N, n_rays, 3).

    The unit square is split into ``n_rays`` strata (a ``k x k`` grid when ``n_rays = k^2``,
    otherwise ``n_rays`` rows), jittered, mapped to the disc by Shirley and Chiu's concentric map
    and lifted to the hemisphere (Malley's method), so the pdf is ``cos(theta) / pi`` and the
    mean of the incoming radiance over the rays estimates irradiance / pi, i.e. shading.
    """
    normals = np.asarray(normals, dtype=np.float64)
    gen = np.random.default_rng(rng)
    k = int(round(np.sqrt(n_rays)))
    if k * k == n_rays:
        i, j = np.divmod(np.arange(n_rays), k)
        nx, ny = k, k
    else:
        i, j, nx, ny = np.arange(n_rays), np.zeros(n_rays), n_rays, 1
    u = (i + gen.random((len(normals), n_rays))) / nx
    v = (j + gen.random((len(normals), n_rays))) / ny
    a, b = 2.0 * u - 1.0, 2.0 * v - 1.0  # concentric map (Shirley & Chiu 1997)
    first = np.abs(a) > np.abs(b)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where(first, a, b)
        phi = np.where(first, (np.pi / 4) * (b / a), (np.pi / 2) - (np.pi / 4) * (a / b))
    phi = np.where((a == 0) & (b == 0), 0.0, phi)
    x, y = r * np.cos(phi), r * np.sin(phi)
    z = np.sqrt(np.maximum(0.0, 1.0 - x * x - y * y))
    t, bt = tangent_frames(normals)
    return x[..., None] * t[:, None] + y[..., None] * bt[:, None] + z[..., None] * normals[:, None]


def morton_order(points: np.ndarray, *, bits: int = 10) -> np.ndarray:
    """Indices sorting ``points (N, 3)`` along a Z-order curve (spatially coherent ray batches)."""
    points = np.asarray(points, dtype=np.float64)
    lo, hi = points.min(axis=0), points.max(axis=0)
    q = ((points - lo) / np.maximum(hi - lo, 1e-12) * ((1 << bits) - 1)).astype(np.uint64)
    code = np.zeros(len(points), dtype=np.uint64)
    for bit in range(bits):
        for axis in range(3):
            code |= ((q[:, axis] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + axis)
    return np.argsort(code, kind="stable")


def depth_map(camera: Camera, tracer: Tracer) -> np.ndarray:
    """Distance (metres) from the camera centre to the proxy along every pixel ray, (H, W);
    ``inf`` where the ray misses the proxy."""
    return tracer.intersect(camera.center, camera.pixel_rays()).t.reshape(camera.shape)


def sun_visibility(points: np.ndarray, normals: np.ndarray, sun_direction: np.ndarray, tracer: Tracer, *,
                   ray_offset: float = 0.02, batch: int = DEFAULT_BATCH) -> np.ndarray:
    """Proxy sun visibility ``~v`` (Sec. 4): 1 when the point faces the sun and a shadow ray
    toward it, started ``ray_offset`` metres off the surface, escapes the proxy; else 0. (N,)."""
    sun = np.asarray(sun_direction, dtype=np.float64)
    facing = clamped_cosine(normals, sun) > 0  # attached shadow where max(0, cos) = 0 (Sec. 3.1)
    out = np.zeros(len(points), dtype=np.float32)
    idx = np.flatnonzero(facing)
    origins = points[idx] + ray_offset * normals[idx]
    out[idx] = ~tracer.occluded(origins, np.broadcast_to(sun, (len(idx), 3)), batch=batch)
    return out


def vertex_normals(proxy: Proxy, normal_smoothing: float, planes: PlaneConfig | None = None) -> np.ndarray:
    """The vertex normals every shading term uses: the proxy's, smoothed by ``normal_smoothing`` metres,
    snapped to the proxy's dominant planes with ``planes``.

    :func:`smooth_normals` when ``normal_smoothing > 0``, the proxy's own normals (read-only) at 0
    (:attr:`Step1Config.normal_smoothing`, :attr:`mvintrinsic.relight.RelightConfig.normal_smoothing`);
    then, with a :class:`~mvintrinsic.planes.PlaneConfig` (beyond the paper; :attr:`Step1Config.planes`,
    :attr:`mvintrinsic.relight.RelightConfig.planes`), a vertex on one of the planes
    :func:`~mvintrinsic.planes.detect_planes` finds takes the plane's normal
    (:func:`~mvintrinsic.planes.planar_normals`). A proxy without triangles (a point cloud) is
    snapped as well; with fewer vertices than three the normals are returned as they are.
    """
    normals = smooth_normals(proxy, normal_smoothing) if normal_smoothing > 0 else proxy.normals
    if planes is None or len(proxy.vertices) < 3:
        return normals
    found = detect_planes(proxy.vertices, normals, config=planes)
    return planar_normals(proxy.vertices, normals, found, config=planes)[0]


def smooth_normals(proxy: Proxy, sigma: float) -> np.ndarray:
    """Vertex normals averaged over the mesh, about a Gaussian of ``sigma`` metres (Step 1).

    Repeated averaging of each vertex's normal with its mesh neighbours (equal weights, the vertex
    included), renormalised at the end: a diffusion on the vertex graph, whose kernel after ``k``
    steps is close to a Gaussian of variance ``k`` :data:`SMOOTHING_VARIANCE_PER_STEP` ``e^2``
    per axis on a regular mesh of mean edge length ``e``; ``k`` is chosen so that it reaches
    ``sigma^2`` (the nearest integer: a mesh much coarser than ``sigma`` keeps its normals).
    Following the mesh rather than a ball in space, it does not mix surfaces that
    are near but not connected (a wall and a tree in front of it). Creases (a building's corner)
    are rounded over about ``sigma``.

    Parameters
    ----------
    proxy : Proxy
    sigma : float
        Standard deviation of the smoothing, metres (> 0).

    Returns
    -------
    (N, 3) float64
        Unit normals; a vertex whose averaged normal vanishes (opposite normals cancelling) keeps
        its own, and a proxy without triangles (a point cloud) keeps all its normals.
    """
    import scipy.sparse as sparse

    if not is_real(sigma) or not 0 < sigma < np.inf:
        raise ValueError(f"sigma must be a positive finite number (metres), got {sigma!r}")
    vertices, normals, triangles = proxy.vertices, proxy.normals, proxy.triangles
    n = len(vertices)
    if triangles is None or len(triangles) == 0:
        return normals.copy()
    start = np.concatenate([triangles[:, 0], triangles[:, 1], triangles[:, 2]])
    end = np.concatenate([triangles[:, 1], triangles[:, 2], triangles[:, 0]])
    edge = float(np.linalg.norm(vertices[start] - vertices[end], axis=1).mean())
    steps = int(round(sigma * sigma / (SMOOTHING_VARIANCE_PER_STEP * edge * edge))) if edge > 0 else 0
    if steps == 0:
        return normals.copy()
    rows = np.concatenate([start, end, np.arange(n)])
    cols = np.concatenate([end, start, np.arange(n)])
    adjacency = sparse.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
    adjacency.data[:] = 1.0  # an edge shared by two triangles counts once
    adjacency = sparse.diags(1.0 / np.asarray(adjacency.sum(axis=1)).ravel()) @ adjacency
    out = normals.copy()
    for _ in range(steps):
        out = adjacency @ out
    length = np.linalg.norm(out, axis=1, keepdims=True)
    return np.where(length > 1e-9, out / np.where(length > 1e-9, length, 1.0), normals)


def voxel_subsample(points: np.ndarray, voxel: float) -> np.ndarray:
    """Indices of one point per occupied ``voxel``-sized cell (the one nearest its centre)."""
    points = np.asarray(points, dtype=np.float64)
    cell = np.floor(points / voxel)
    offset = np.linalg.norm(points - (cell + 0.5) * voxel, axis=1)
    _, inverse = np.unique(cell, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    order = np.lexsort((offset, inverse))
    first = np.ones(len(order), dtype=bool)
    first[1:] = inverse[order][1:] != inverse[order][:-1]
    return np.sort(order[first])


def interpolate_points(
    source_points: np.ndarray,
    source_normals: np.ndarray,
    values: np.ndarray,
    points: np.ndarray,
    normals: np.ndarray,
    *,
    neighbors: int = 8,
) -> np.ndarray:
    """Scatter-to-vertex interpolation of smooth per-point quantities.

    Each target point averages its ``neighbors`` nearest source points with weights
    ``max(0, n . n_s)^4 / (d + eps)`` (inverse distance, and normal agreement so that values do not
    leak across creases, e.g. from a wall to the ground); a target whose neighbours all face
    elsewhere takes the nearest source's value.
    """
    k = min(neighbors, len(source_points))
    distance, nearest = cKDTree(source_points).query(points, k=k)
    distance, nearest = distance.reshape(len(points), k), nearest.reshape(len(points), k)
    agreement = np.maximum(np.einsum("ij,ikj->ik", normals, source_normals[nearest]), 0.0) ** 4
    weights = agreement / (distance + 1e-3)
    total = weights.sum(axis=1, keepdims=True)
    out = np.einsum("ik,ikc->ic", weights, values[nearest]) / np.where(total > 0, total, 1.0)
    lonely = total[:, 0] <= 0
    out[lonely] = values[nearest[lonely, 0]]
    return out


def subdivide(proxy: Proxy, *, max_edge: float, center: np.ndarray | None = None, radius: float = np.inf,
              max_passes: int = 16) -> Proxy:
    """Split the triangles of a mesh proxy until no edge near ``center`` exceeds ``max_edge``.

    Step 1 carries its quantities on vertices: a mesh whose triangles are metres wide (a CAD
    model, the exact geometry of a synthetic scene) interpolates shading and visibility across
    them. Each pass splits every triangle whose longest edge exceeds ``max_edge`` and which comes
    within ``radius`` of ``center`` (its bounding sphere does) into four at its edge midpoints; midpoint
    normals are the normalised mean of the edge's end normals. A split triangle next to an
    unsplit one leaves a T-junction: harmless for ray casting and interpolation here.

    Parameters
    ----------
    proxy : Proxy
        A mesh proxy (point clouds raise ValueError).
    max_edge : float
        Longest edge allowed, metres.
    center : (3,) array_like, optional
        Only triangles within ``radius`` metres of it are split (e.g. the cameras' centroid, so
        a far ground ring stays coarse). Default: all triangles.
    radius : float, optional
    max_passes : int, optional
        Each pass halves edges; 16 passes divide them by 65536.

    Returns
    -------
    Proxy
        Original vertices first (same indices), then the midpoints (colours averaged too).
    """
    if not proxy.is_mesh:
        raise ValueError("proxy must be a mesh to be subdivided, got a point cloud")
    if not max_edge > 0:
        raise ValueError(f"max_edge must be positive (metres), got {max_edge!r}")
    vertices, normals, triangles = proxy.vertices.copy(), proxy.normals.copy(), proxy.triangles.copy()
    colors = None if proxy.colors is None else proxy.colors.copy()
    center = None if center is None else np.asarray(center, dtype=np.float64)
    for _ in range(max_passes):
        a, b, c = (vertices[triangles[:, i]] for i in range(3))
        longest = np.max([np.linalg.norm(b - a, axis=1), np.linalg.norm(c - b, axis=1),
                          np.linalg.norm(a - c, axis=1)], axis=0)
        split = longest > max_edge
        if center is not None:
            # The triangle's bounding sphere (about its centroid) must reach into the ball: a
            # centroid test alone never splits a ground triangle hundreds of metres wide whose
            # centroid lies far away but which passes under the cameras.
            centroid = (a + b + c) / 3.0
            bound = np.max([np.linalg.norm(v - centroid, axis=1) for v in (a, b, c)], axis=0)
            split &= np.linalg.norm(centroid - center, axis=1) - bound < radius
        if not split.any():
            break
        parts = triangles[split]
        edges = np.concatenate([parts[:, [0, 1]], parts[:, [1, 2]], parts[:, [2, 0]]])
        unique, inverse = np.unique(np.sort(edges, axis=1), axis=0, return_inverse=True)
        inverse = inverse.ravel() + len(vertices)
        mid_normals = normals[unique[:, 0]] + normals[unique[:, 1]]
        length = np.linalg.norm(mid_normals, axis=1, keepdims=True)
        mid_normals = np.where(length > 1e-12, mid_normals / np.maximum(length, 1e-12), normals[unique[:, 0]])
        vertices = np.concatenate([vertices, 0.5 * (vertices[unique[:, 0]] + vertices[unique[:, 1]])])
        normals = np.concatenate([normals, mid_normals])
        if colors is not None:
            colors = np.concatenate([colors, 0.5 * (colors[unique[:, 0]] + colors[unique[:, 1]])])
        n = len(parts)
        m01, m12, m20 = inverse[:n], inverse[n:2 * n], inverse[2 * n:]
        triangles = np.concatenate([
            triangles[~split],
            np.stack([parts[:, 0], m01, m20], axis=1),
            np.stack([m01, parts[:, 1], m12], axis=1),
            np.stack([m20, m12, parts[:, 2]], axis=1),
            np.stack([m01, m12, m20], axis=1),
        ])
    return Proxy(vertices, normals, triangles, colors)


def rasterize(values: np.ndarray, camera: Camera, tracer: Tracer) -> np.ndarray:
    """Per-vertex quantities seen through a camera, for inspection and evaluation.

    Parameters
    ----------
    values : (N, ...) array_like
        One row per proxy vertex.
    camera : Camera
    tracer : Tracer

    Returns
    -------
    (H, W, ...) float64
        Each pixel's value interpolated at the proxy point its centre ray hits; NaN where the ray
        misses the proxy.
    """
    values = np.asarray(values)
    hits = tracer.intersect(camera.center, camera.pixel_rays())
    return tracer.interpolate(values, hits).reshape(*camera.shape, *values.shape[1:])
