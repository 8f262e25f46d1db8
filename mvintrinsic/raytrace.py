"""Ray casting against the proxy (open3d / Embree) and Step 1 of the paper (Sec. 4).

A :class:`Tracer` is built once per proxy and answers batched queries: first hits and occlusion.
On it, :func:`step1` estimates what the paper's Step 1 computes "by ray-tracing the inaccurate 3D
model and sky map": the completed environment map and sky model (via :mod:`.skymodel`), the
median radiance of every proxy vertex, ``S_sky`` and ``S_ind`` by hemisphere ray casting with
the paper's attenuation factor, and the proxy sun visibility ``~v`` (Duchêne et al. 2015,
Sec. 4). The same tracer lifts the user's two sun clicks to 3D (Sec. 3.2).

Point-cloud proxies (the paper uses the vertices of the reconstructed mesh as a point cloud) are
traced as *surfels*: every point becomes a small square of two triangles centred on the point,
normal to its normal, with half-width ``surfel_scale`` times the mean distance to its
``surfel_neighbors`` nearest neighbours, so neighbouring squares overlap and the surface is
closed where the sampling is dense.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType

import numpy as np
from scipy.spatial import cKDTree

from ._libusb import ensure_libusb
from ._validation import describe, is_real
from .camera import Camera
from .image_model import clamped_cosine
from .scene import Proxy, Scene, View
from .skymodel import EnvironmentMap, HorizonPlane, SkyConfig, SkyModel, estimate_environment, find_horizon

__all__ = [
    "PointShading",
    "RayHits",
    "Step1Config",
    "Step1Result",
    "Tracer",
    "cosine_hemisphere",
    "depth_map",
    "environment_shading",
    "fill_unseen",
    "interpolate_points",
    "morton_order",
    "rasterize",
    "ray_radiance",
    "smooth_normals",
    "step1",
    "subdivide",
    "sun_visibility",
    "triangle_scene",
    "tangent_frames",
    "vertex_normals",
    "vertex_observations",
    "vertex_radiance",
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
        barycentric = np.full((n, 3), np.nan)
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
                barycentric[idx] = bary
                vertex[idx] = self._triangle_vertices[prim[local], np.argmax(bary, axis=1)]
            nrm = nrm[local]
            nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
            flip = np.einsum("ij,ij->i", nrm, directions[idx]) > 0
            nrm[flip] *= -1
            normals[idx] = nrm
        hit = np.isfinite(t)
        points = np.where(hit[:, None], origins + np.where(hit, t, 0.0)[:, None] * directions, np.nan)
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
            corners = self._triangle_vertices[hits.triangle[idx]]
            weights = hits.barycentric[idx].reshape(len(idx), 3, *([1] * (values.ndim - 1)))
            out[idx] = np.sum(values[corners] * weights, axis=1)
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
            answer = self._scene.cast_rays(self._o3c.Tensor(chunk))
            t_hit = answer["t_hit"].numpy()
            ok = np.isfinite(t_hit)
            t[start:start + m] = np.where(ok, t_hit + np.float32(t_min), np.inf)
            prim = answer["primitive_ids"].numpy().astype(np.int64)
            if self._triangle_vertices is None:
                prim //= 2
            primitive[start:start + m] = np.where(ok, prim, -1)
        return t, primitive

    def __repr__(self) -> str:
        return f"Tracer({self.proxy!r})"


# ---------------------------------------------------------------------------------------------
# Step 1 (paper Sec. 4): proxy radiance, sky and indirect shading, proxy sun visibility
# ---------------------------------------------------------------------------------------------
#: Where the paper's indirect attenuation factor applies (:class:`Step1Config`).
ATTENUATION_MODES = ("all", "unseen", "none")


def _attenuation_mode(value: object, name: str = "attenuation") -> str:
    """``value`` as one of :data:`ATTENUATION_MODES` (``True`` -> ``"all"``, ``False`` -> ``"none"``)."""
    if value is True:
        return "all"
    if value is False:
        return "none"
    if isinstance(value, str) and value in ATTENUATION_MODES:
        return value
    raise ValueError(f"{name} must be one of {', '.join(map(repr, ATTENUATION_MODES))} (or a bool), got {value!r}")


@dataclass(frozen=True)
class Step1Config:
    """Options of Step 1 (paper Sec. 4); defaults measured in ``benchmarks/bench_step1.py``.

    Parameters
    ----------
    n_rays : int
        Cosine-weighted, stratified hemisphere rays per point for ``S_sky`` and ``S_ind`` (the
        paper does not give its count): 64 is within 5% of a 256-ray reference on the benchmark.
    ray_offset : float
        Metres the ray origins move along the normal, against self-intersection with a noisy
        proxy (about a TSDF voxel).
    indirect_attenuation : {"all", "unseen", "none"}
        Where gathered proxy radiance is scaled by the cosine of the contributing surface's
        normal, the paper's attenuation factor against over-estimated indirect light (Sec. 4):
        ``"all"`` (the paper, default) on every hit; ``"unseen"`` only on the radiance of
        vertices no view sees (filled from their nearest seen neighbour), which is the only
        extrapolated radiance when the proxy is exact and complete (a CAD model, a LiDAR scan,
        the synthetic ``proxy_clean.ply``); ``"none"`` nowhere. ``True``/``False`` are read as
        ``"all"``/``"none"``. Measured in ``docs/step1.md``: with exact geometry ``"unseen"``
        keeps the shadowed ``S_env`` of all four test scenes within 25%, the paper's ``"all"``
        of three (in the umbra of our synthetic scenes ``"all"`` is the closer one); with MVS
        proxies ``"all"`` is better on three of the four. Use ``"unseen"`` with an exact proxy,
        the default with an MVS one.
    normal_smoothing : float
        Standard deviation (metres) of the smoothing of the proxy's vertex normals before any
        quantity is computed from them (:func:`smooth_normals`); 0: the proxy's own normals (the
        paper). Not in the paper. An MVS proxy's normals are noisy (30-40 degrees median
        deviation on the synthetic streets' facades), and ``max(0, cos w_sun)`` and the shadow
        rays of ``~v`` are most sensitive to them where the sun grazes a surface: there the noisy
        normals give a biased ``S_sun`` and the bumps shadow their own surface. 0.4 m, measured
        with the multi-view shadow labels on eight scenes (``docs/step1.md``): it lowered the
        balanced error on seven, most on the 1000x750 street (0.173 to 0.091 with the true
        ``L_sun``), where a grazing-lit facade was labelled shadow, and raised it by 0.003 on
        one. With an exact proxy (CAD, LiDAR) use 0: there it only rounds the creases.
    subsample : float or None
        Voxel size (metres) of the points at which ``S_sky`` and ``S_ind`` are ray traced; the
        other vertices interpolate them (they are smooth). ``None``: every vertex.
    interpolation_neighbors : int
        Traced points interpolated per vertex (inverse distance, weighted by normal agreement).
    depth_tolerance : float
        Relative depth slack of the visibility test when gathering vertex radiance from views.
    sky : SkyConfig
        Environment-map, sky-detector and sky-fit options.
    batch_rays : int
        Rays per Embree call.
    ray_tolerance : float or None
        A convergence test instead of the fixed ``n_rays`` (beyond the paper;
        :func:`environment_shading` ``tolerance``): a point whose relative standard error is above
        this gets another stratified round of four times the rays, up to ``max_rays``. ``None``
        (default): ``n_rays`` rays at every point. Measured (``docs/presets.md``, courtyard_s1,
        33.5k points, median error of the luminance against 1024 rays): fixed 64 rays 2.6%, 256
        rays 1.05%; the test from 16 rays at 5% 2.0% with 124 rays on average, at 3% 1.1% with
        310: on the fixed counts' own cost-accuracy curve, because a single stratified round of
        ``n`` rays beats several smaller rounds of the same total, so it is not the default.
    max_rays : int or None
        Most rays per point with ``ray_tolerance``; ``None``: ``21 n_rays`` (three rounds).
    sky_colour_tolerance : float or None
        Used when the quantities are carried to the pixels (:func:`mvintrinsic.pixels.pixel_quantities`):
        a pixel whose ray misses the proxy is sky only when its direction is sky in the environment
        map *and* its colour is within this distance (norm of the log-RGB difference) of the fitted
        sky model's or the environment map's radiance in that direction; otherwise it is a surface
        the proxy lost (``filled``). ``None``: the direction alone. Not in the paper. The
        environment map's sky texels are coarse, so a tree crown or a pole against the sky, missing
        from an MVS proxy, was taken for sky and got no layers: 0.4-1.8% of the scored pixels of the
        synthetic scenes, 11-23% of Step 3's reflectance LMSE. 0.5 (about 65% per channel) keeps
        98.5-98.8% of them as surfaces and loses 0.5-0.6% of the true sky (courtyard_s1, demo_480;
        ``docs/step1.md``).
    """

    n_rays: int = 64
    ray_offset: float = 0.02
    indirect_attenuation: str = "all"
    normal_smoothing: float = 0.4
    subsample: float | None = 0.1
    interpolation_neighbors: int = 8
    depth_tolerance: float = 0.02
    sky: SkyConfig = field(default_factory=SkyConfig)
    batch_rays: int = 1 << 21
    sky_colour_tolerance: float | None = 0.5
    ray_tolerance: float | None = None
    max_rays: int | None = None

    def __post_init__(self) -> None:
        if self.sky_colour_tolerance is not None and (
                not is_real(self.sky_colour_tolerance) or not 0 < self.sky_colour_tolerance < np.inf):
            raise ValueError(f"sky_colour_tolerance must be a finite number > 0 or None, got {self.sky_colour_tolerance!r}")
        object.__setattr__(self, "indirect_attenuation",
                           _attenuation_mode(self.indirect_attenuation, "indirect_attenuation"))
        if isinstance(self.n_rays, bool) or not isinstance(self.n_rays, int) or self.n_rays < 1:
            raise ValueError(f"n_rays must be a positive integer, got {self.n_rays!r}")
        if not self.ray_offset >= 0:
            raise ValueError(f"ray_offset must be >= 0 metres, got {self.ray_offset!r}")
        if not is_real(self.normal_smoothing) or not 0 <= self.normal_smoothing < np.inf:
            raise ValueError(f"normal_smoothing must be a finite number >= 0 (metres), got {self.normal_smoothing!r}")
        if self.subsample is not None and not self.subsample > 0:
            raise ValueError(f"subsample must be a positive voxel size in metres or None, got {self.subsample!r}")
        if self.interpolation_neighbors < 1:
            raise ValueError(f"interpolation_neighbors must be >= 1, got {self.interpolation_neighbors!r}")
        if not self.depth_tolerance > 0:
            raise ValueError(f"depth_tolerance must be positive, got {self.depth_tolerance!r}")
        if self.ray_tolerance is not None and not (is_real(self.ray_tolerance) and 0 < self.ray_tolerance < np.inf):
            raise ValueError(f"ray_tolerance must be a finite number > 0 or None, got {self.ray_tolerance!r}")
        if self.max_rays is not None and (isinstance(self.max_rays, bool) or not isinstance(self.max_rays, int)
                                          or self.max_rays < self.n_rays):
            raise ValueError(f"max_rays must be an integer >= n_rays ({self.n_rays}) or None, got {self.max_rays!r}")


@dataclass(frozen=True, eq=False)
class PointShading:
    """Step-1 shading at every proxy vertex (paper Sec. 4).

    Parameters
    ----------
    sky : (N, 3) float32
        ``S_sky``: sky radiance integrated over the normal's hemisphere, shading units.
    indirect : (N, 3) float32
        ``S_ind``: radiance from the proxy and from non-sky texels of the environment map.
    visibility : (N,) float32
        Proxy sun visibility ``~v`` in {0, 1}: 0 when a shadow ray toward the sun hits the proxy
        or the point faces away from the sun (attached shadow).
    cosine : (N,) float32
        ``max(0, cos omega_sun)`` with the vertex normal.
    """

    sky: np.ndarray
    indirect: np.ndarray
    visibility: np.ndarray
    cosine: np.ndarray

    @property
    def env(self) -> np.ndarray:
        """``S_env = S_sky + S_ind`` (Eq. 3), (N, 3) float32."""
        return self.sky + self.indirect


@dataclass(frozen=True, eq=False)
class Step1Result:
    """Everything Step 1 estimates and later steps read.

    Parameters
    ----------
    environment : EnvironmentMap
        Completed environment map with its sky mask.
    sky_model : SkyModel
        The fitted sky (Eq. 4; its family chosen by :attr:`SkyConfig.model`).
    horizon : HorizonPlane
        Main horizontal plane of the proxy.
    radiance : (N, 3) float32
        Median observed radiance of every proxy vertex over the views that see it (NaN: unseen).
    observations : (N,) int32
        Number of views that see each vertex.
    shading : PointShading
        ``S_sky``, ``S_ind``, ``~v`` and the sun cosine per vertex.
    normals : (N, 3) float64
        The unit vertex normals the quantities refer to: the proxy's, smoothed by
        :attr:`Step1Config.normal_smoothing`.
    timings : mapping of str to float
        Seconds per sub-stage.
    config : Step1Config
    rays_per_point : float
        Mean hemisphere rays cast per traced point (``n_rays`` unless
        :attr:`Step1Config.ray_tolerance` set a convergence test).
    """

    environment: EnvironmentMap
    sky_model: SkyModel
    horizon: HorizonPlane
    radiance: np.ndarray
    observations: np.ndarray
    shading: PointShading
    normals: np.ndarray
    timings: Mapping[str, float]
    config: Step1Config
    rays_per_point: float = 0.0


def _rng(rng: np.random.Generator | int | None) -> np.random.Generator:
    return rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)


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
    gen = _rng(rng)
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


def vertex_observations(
    views: Sequence[View],
    tracer: Tracer,
    *,
    depth_tolerance: float = 0.02,
    depths: Sequence[np.ndarray] | None = None,
    progress: bool = False,
) -> np.ndarray:
    """What every view sees of every proxy vertex: the samples :func:`vertex_radiance` takes the
    median of.

    Each vertex is projected into every view; it counts as seen when it lies in the image, in
    front of the camera, faces it, its pixel is valid and its distance is within
    ``depth_tolerance`` (relative) of the proxy's depth map at that pixel (occlusion test). Its
    value there is the bilinearly interpolated image value.

    Returns
    -------
    (V, N, 3) float32
        Per view (in the order given) and vertex, linear RGB in the image's units; NaN where the
        view does not see the vertex.
    """
    from tqdm.auto import tqdm

    proxy = tracer.proxy
    n = len(proxy.vertices)
    samples = np.full((len(views), n, 3), np.nan, dtype=np.float32)
    for k, view in enumerate(tqdm(views, desc="vertex radiance", unit="view", disable=not progress)):
        camera = view.camera
        depth = depths[k] if depths is not None else depth_map(camera, tracer)
        pixels, z = camera.project(proxy.vertices)
        inside = (z > 0) & camera.in_image(pixels)
        to_camera = camera.center - proxy.vertices
        distance = np.linalg.norm(to_camera, axis=1)
        facing = np.einsum("ij,ij->i", proxy.normals, to_camera) > 0
        idx = np.flatnonzero(inside & facing)
        col = np.clip(pixels[idx, 0].astype(np.int64), 0, camera.width - 1)
        row = np.clip(pixels[idx, 1].astype(np.int64), 0, camera.height - 1)
        seen = (distance[idx] <= depth[row, col] * (1.0 + depth_tolerance)) & view.mask[row, col]
        idx, col, row = idx[seen], col[seen], row[seen]
        image = np.where(view.mask[..., None], view.image, 0.0).astype(np.float32)
        samples[k, idx] = _bilinear(image, pixels[idx, 0] - 0.5, pixels[idx, 1] - 0.5)
    return samples


def vertex_radiance(
    views: Sequence[View],
    tracer: Tracer,
    *,
    depth_tolerance: float = 0.02,
    depths: Sequence[np.ndarray] | None = None,
    progress: bool = False,
) -> tuple[np.ndarray, np.ndarray]:
    """Median observed radiance of every proxy vertex (paper Sec. 4).

    The samples are those of :func:`vertex_observations`; the estimate is their per-channel
    median over the views that see the vertex ("We assign the median of the gathered values as
    the approximate diffuse radiance of the vertex").

    Returns
    -------
    radiance : (N, 3) float32
        NaN for vertices no view sees.
    count : (N,) int32
        Number of views that see each vertex.
    """
    samples = vertex_observations(views, tracer, depth_tolerance=depth_tolerance, depths=depths, progress=progress)
    n = samples.shape[1]
    count = np.sum(np.isfinite(samples[..., 0]), axis=0).astype(np.int32)
    radiance = np.full((n, 3), np.nan, dtype=np.float32)
    seen = count > 0
    radiance[seen] = np.nanmedian(samples[:, seen], axis=0)
    return radiance, count


def _bilinear(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``image (H, W, C)`` at array coordinates ``(x, y)`` (column, row of
    pixel centres), edges clamped; (N, C)."""
    h, w = image.shape[:2]
    x = np.clip(x, 0.0, w - 1.0)
    y = np.clip(y, 0.0, h - 1.0)
    x0 = np.minimum(x.astype(np.int64), w - 2) if w > 1 else np.zeros(len(x), np.int64)
    y0 = np.minimum(y.astype(np.int64), h - 2) if h > 1 else np.zeros(len(y), np.int64)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    top = image[y0, x0] * (1 - fx) + image[y0, x1] * fx
    bottom = image[y1, x0] * (1 - fx) + image[y1, x1] * fx
    return top * (1 - fy) + bottom * fy


def fill_unseen(values: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Rows of ``values (N, C)`` with a NaN take the value of the nearest finite row (by ``points
    (N, 3)``): the radiance Step 1 gives vertices no view sees (they still reflect light). All
    rows NaN: zeros. (N, C) float64."""
    bad = ~np.isfinite(values).all(axis=1)
    if not bad.any() or bad.all():
        return np.where(np.isfinite(values), values, 0.0)
    _, nearest = cKDTree(points[~bad]).query(points[bad])
    filled = values.copy()
    filled[bad] = values[~bad][nearest]
    return filled


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


def environment_shading(
    points: np.ndarray,
    normals: np.ndarray,
    tracer: Tracer,
    environment: EnvironmentMap,
    radiance: np.ndarray,
    *,
    n_rays: int = 64,
    ray_offset: float = 0.02,
    attenuation: str | bool = "all",
    rng: np.random.Generator | int | None = None,
    batch_rays: int = 1 << 21,
    progress: bool = False,
    tolerance: float | None = None,
    max_rays: int | None = None,
    return_counts: bool = False,
) -> tuple[np.ndarray, np.ndarray] | tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``S_sky`` and ``S_ind`` of Eq. (1) at points by hemisphere ray casting (paper Sec. 4).

    For each point, ``n_rays`` cosine-weighted stratified rays about its normal are cast against
    the proxy (points are processed in Morton order, a batch at a time, so neighbouring rays
    traverse the same part of the BVH). A ray that misses the proxy reads the environment map in
    its direction: sky texels feed ``S_sky``, other texels ``S_ind``. A ray that hits the proxy
    feeds ``S_ind`` with the radiance interpolated from the hit triangle's vertices, times the
    paper's attenuation factor, the cosine between the hit surface's normal and the ray:
    on every hit with ``attenuation="all"``, on the share of the hit's radiance that comes
    from unseen vertices (NaN rows of ``radiance``, barycentric weights) with ``"unseen"``,
    nowhere with ``"none"``. With cosine-weighted sampling the mean over the rays is the
    shading (irradiance / pi).

    Parameters
    ----------
    points, normals : (P, 3) array_like
        World positions (m) and unit normals.
    tracer : Tracer
    environment : EnvironmentMap
    radiance : (N, 3) array_like
        Radiance of every proxy vertex (NaN rows, vertices no view sees, get their nearest seen
        neighbour's value).
    attenuation : {"all", "unseen", "none"} or bool, optional
        See :class:`Step1Config` ``indirect_attenuation``.
    tolerance : float, optional
        Convergence test (beyond the paper, :class:`Step1Config` ``ray_tolerance``): a point whose
        relative standard error of its shading's luminance exceeds ``tolerance`` gets another
        stratified round of four times the rays of its last (``n_rays``, ``4 n_rays``, ...) while
        its total stays within ``max_rays``. The standard error of a round is the collapsed-strata
        estimate for one ray per stratum, ``sqrt(sum (y_a - y_b)^2) / n`` over the pairs of
        neighbouring strata (Cochran, *Sampling Techniques*, 3rd ed., Sec. 5A.12; slightly
        conservative); rounds are combined with fixed weights ``n^1.5``. ``None``: one round of
        ``n_rays``, the fixed count.
    max_rays : int, optional
        Most rays per point with ``tolerance``; default ``21 * n_rays`` (three rounds).
    return_counts : bool, optional
        Also return the rays cast per point.

    Returns
    -------
    sky, indirect : (P, 3) float32
    counts : (P,) int32
        Only with ``return_counts``.
    """
    from tqdm.auto import tqdm

    mode = _attenuation_mode(attenuation)
    points = np.asarray(points, dtype=np.float64)
    normals = np.asarray(normals, dtype=np.float64)
    gen = _rng(rng)
    radiance = np.asarray(radiance, dtype=np.float64)
    unseen = (~np.isfinite(radiance).all(axis=1)).astype(np.float64)[:, None]
    vertex_values = fill_unseen(radiance, tracer.proxy.vertices)
    max_rays = 21 * n_rays if max_rays is None else int(max_rays)
    if tolerance is not None and not (is_real(tolerance) and 0 < tolerance < np.inf):
        raise ValueError(f"tolerance must be a finite number > 0 or None, got {tolerance!r}")
    if max_rays < n_rays:
        raise ValueError(f"max_rays must be at least n_rays ({n_rays}), got {max_rays}")
    luminance_weights = np.array([0.2126, 0.7152, 0.0722])  # Rec.709
    # Per point, the rounds' estimates weighted by n^1.5 (a stratified round of 4n rays has about
    # 8 times less variance than one of n: fixed weights, so the combination stays unbiased).
    sky = np.zeros((len(points), 3))
    indirect = np.zeros((len(points), 3))
    weight = np.zeros(len(points))
    variance = np.zeros(len(points))  # sum of weight^2 * the rounds' variances
    counts = np.zeros(len(points), np.int32)
    todo = morton_order(points)
    round_rays = n_rays
    while len(todo):
        per_batch = max(1, batch_rays // round_rays)
        w = round_rays ** 1.5
        for start in tqdm(range(0, len(todo), per_batch), desc="hemisphere rays", unit="batch",
                          disable=not progress):
            idx = todo[start:start + per_batch]
            directions = cosine_hemisphere(normals[idx], round_rays, rng=gen).reshape(-1, 3)
            origins = np.repeat(points[idx] + ray_offset * normals[idx], round_rays, axis=0)
            hits = tracer.intersect(origins, directions, batch=len(directions))
            to_sky, contribution = ray_radiance(tracer, hits, directions, environment, vertex_values, unseen,
                                                attenuation=mode)
            to_sky = to_sky.reshape(len(idx), round_rays, 3)
            contribution = contribution.reshape(len(idx), round_rays, 3)
            sky[idx] += w * to_sky.mean(axis=1)
            indirect[idx] += w * contribution.mean(axis=1)
            weight[idx] += w
            counts[idx] += round_rays
            if tolerance is not None:  # collapsed strata: rays come in stratum order, neighbours paired
                y = (to_sky + contribution) @ luminance_weights
                pairs = y[:, : round_rays // 2 * 2].reshape(len(idx), -1, 2)
                variance[idx] += w * w * ((pairs[..., 0] - pairs[..., 1]) ** 2).sum(axis=1) / round_rays**2
        if tolerance is None:
            break
        mean = (sky[todo] + indirect[todo]) @ luminance_weights / weight[todo]
        unconverged = np.sqrt(variance[todo]) / weight[todo] > tolerance * np.maximum(mean, 1e-12)
        round_rays *= 4  # the next round has twice the strata per axis
        todo = todo[unconverged & (counts[todo] + round_rays <= max_rays)]
    sky /= weight[:, None]
    indirect /= weight[:, None]
    if return_counts:
        return sky.astype(np.float32), indirect.astype(np.float32), counts
    return sky.astype(np.float32), indirect.astype(np.float32)


def ray_radiance(
    tracer: Tracer,
    hits: RayHits,
    directions: np.ndarray,
    environment: EnvironmentMap,
    vertex_values: np.ndarray,
    unseen: np.ndarray,
    *,
    attenuation: str | bool = "all",
) -> tuple[np.ndarray, np.ndarray]:
    """Radiance each hemisphere ray of Step 1 brings (paper Sec. 4), split into sky and indirect.

    A ray that misses the proxy reads the environment map in its direction (sky texels: sky, other
    texels: indirect); a ray that hits it brings the vertex radiance interpolated at the hit, times
    the paper's attenuation factor where ``attenuation`` applies it (see
    :func:`environment_shading`). The mean over a point's cosine-weighted rays is its shading.

    Parameters
    ----------
    tracer : Tracer
    hits : RayHits
        ``tracer.intersect`` of the rays.
    directions : (R, 3) array_like
        Unit world directions of the rays.
    environment : EnvironmentMap
    vertex_values : (N, 3) array_like
        Radiance of every proxy vertex, unseen ones filled (:func:`fill_unseen`).
    unseen : (N, 1) array_like
        1.0 for the vertices no view sees, else 0.0 (used by ``attenuation="unseen"``).
    attenuation : {"all", "unseen", "none"} or bool, optional
        See :class:`Step1Config` ``indirect_attenuation``.

    Returns
    -------
    sky, indirect : (R, 3) float64
    """
    mode = _attenuation_mode(attenuation)
    directions = np.asarray(directions, dtype=np.float64)
    indirect = np.zeros((len(directions), 3))
    miss = ~hits.hit
    env = environment.lookup(directions[miss]).astype(np.float64)
    is_sky = environment.is_sky(directions[miss])
    sky = np.zeros((len(directions), 3))
    sky[np.flatnonzero(miss)[is_sky]] = env[is_sky]
    indirect[np.flatnonzero(miss)[~is_sky]] = env[~is_sky]
    gathered = tracer.interpolate(vertex_values, hits)
    if mode != "none":
        cosine = np.abs(np.einsum("ij,ij->i", hits.normals, directions))
        if mode == "unseen":  # attenuate only the unseen vertices' share of the hit
            share = tracer.interpolate(unseen, hits)[:, 0]
            cosine = 1.0 - share + share * cosine
        gathered *= cosine[:, None]
    indirect[hits.hit] = gathered[hits.hit]
    return sky, indirect


def vertex_normals(proxy: Proxy, normal_smoothing: float) -> np.ndarray:
    """The vertex normals every shading term uses: the proxy's, smoothed by ``normal_smoothing`` metres.

    :func:`smooth_normals` when ``normal_smoothing > 0``, the proxy's own normals (read-only) at 0
    (:attr:`Step1Config.normal_smoothing`, :attr:`mvintrinsic.relight.RelightConfig.normal_smoothing`).
    """
    return smooth_normals(proxy, normal_smoothing) if normal_smoothing > 0 else proxy.normals


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


def step1(
    scene: Scene,
    *,
    config: Step1Config | None = None,
    tracer: Tracer | None = None,
    depths: Sequence[np.ndarray] | None = None,
    rng: np.random.Generator | int | None = None,
    progress: bool = False,
) -> Step1Result:
    """Step 1 of the paper (Sec. 4): environment map, sky model, ``S_sky``, ``S_ind`` and ``~v``.

    1. horizon: the main horizontal plane of the proxy (RANSAC), or, when it has none, the
       scene's up vector (:func:`~mvintrinsic.skymodel.find_horizon`, ``SkyConfig.horizon``);
    2. coverage: camera rays of every view against the proxy; the valid pixels they miss are
       splatted into a partial environment map (median over views);
    3. sky: colour sky detector above the horizon, Preetham sky fit (Eq. 4), completion of the
       map (model above the horizon, diffusion below);
    4. proxy radiance: median of each vertex's observations;
    5. normals: the proxy's vertex normals smoothed (:attr:`Step1Config.normal_smoothing`, not in
       the paper); every quantity below uses them;
    6. ``S_sky`` and ``S_ind`` by cosine-weighted hemisphere rays at the proxy vertices (or at a
       voxel subsample, interpolated to all vertices), ``~v`` by one shadow ray per vertex, and
       ``max(0, cos w_sun)`` (Eq. 1).

    Parameters
    ----------
    scene : Scene
    config : Step1Config, optional
    tracer : Tracer, optional
        A tracer already built over ``scene.proxy`` (saves rebuilding it).
    depths : sequence of (H, W) arrays, optional
        The views' proxy depth maps (:func:`depth_map`), if already cast (saves casting them).
    rng : numpy.random.Generator or int, optional
        Seeds RANSAC and the hemisphere sampling.
    progress : bool, optional
        Progress bars for the long parts.

    Returns
    -------
    Step1Result
    """
    config = config or Step1Config()
    gen = _rng(rng)
    timings: dict[str, float] = {}
    start = time.perf_counter()
    tracer = tracer if tracer is not None else Tracer(scene.proxy)
    if tracer.proxy is not scene.proxy:
        raise ValueError("tracer must be built over scene.proxy")
    timings["tracer"] = time.perf_counter() - start

    start = time.perf_counter()
    horizon = find_horizon(scene.proxy.vertices, up=scene.up, config=config.sky, rng=gen,
                           camera_centers=np.stack([v.camera.center for v in scene.views]),
                           camera_ups=np.stack([-v.camera.rotation[1] for v in scene.views]))  # -y axis, world
    timings["horizon"] = time.perf_counter() - start

    start = time.perf_counter()
    if depths is None:
        depths = [depth_map(v.camera, tracer) for v in scene.views]
    elif len(depths) != len(scene.views) or any(
            np.shape(d) != v.camera.shape for d, v in zip(depths, scene.views, strict=True)):
        raise ValueError("depths must hold one (H, W) depth map per view of the scene, in scene order")
    uncovered = [np.isinf(d) & v.mask for d, v in zip(depths, scene.views, strict=True)]
    environment, sky_model = estimate_environment(
        scene.views, uncovered, sun_direction=scene.sun.direction, horizon_normal=horizon.plane[:3],
        up=scene.up, config=config.sky,
    )
    timings["environment"] = time.perf_counter() - start

    start = time.perf_counter()
    radiance, count = vertex_radiance(scene.views, tracer, depth_tolerance=config.depth_tolerance, depths=depths,
                                      progress=progress)
    timings["vertex_radiance"] = time.perf_counter() - start

    start = time.perf_counter()
    points, normals = scene.proxy.vertices, vertex_normals(scene.proxy, config.normal_smoothing)
    timings["normals"] = time.perf_counter() - start

    start = time.perf_counter()
    traced = np.arange(len(points)) if config.subsample is None else voxel_subsample(points, config.subsample)
    sky, indirect, rays = environment_shading(
        points[traced], normals[traced], tracer, environment, radiance, n_rays=config.n_rays,
        ray_offset=config.ray_offset, attenuation=config.indirect_attenuation, rng=gen,
        batch_rays=config.batch_rays, progress=progress, tolerance=config.ray_tolerance,
        max_rays=config.max_rays, return_counts=True,
    )
    if len(traced) < len(points):
        both = interpolate_points(points[traced], normals[traced], np.concatenate([sky, indirect], axis=1),
                                  points, normals, neighbors=config.interpolation_neighbors)
        sky, indirect = both[:, :3].astype(np.float32), both[:, 3:].astype(np.float32)
    timings["environment_shading"] = time.perf_counter() - start

    start = time.perf_counter()
    visibility = sun_visibility(points, normals, scene.sun.direction, tracer, ray_offset=config.ray_offset)
    cosine = clamped_cosine(normals, scene.sun.direction).astype(np.float32)  # max(0, cos w_sun), Eq. (1)
    timings["sun_visibility"] = time.perf_counter() - start

    for array in (radiance, count, sky, indirect, visibility, cosine):
        array.flags.writeable = False
    return Step1Result(
        environment=environment, sky_model=sky_model, horizon=horizon, radiance=radiance, observations=count,
        shading=PointShading(sky=sky, indirect=indirect, visibility=visibility, cosine=cosine),
        normals=normals, timings=MappingProxyType(timings), config=config,
        rays_per_point=float(rays.mean()) if len(rays) else 0.0,
    )


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
