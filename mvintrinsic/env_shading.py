"""Step 1 of the paper (Sec. 4): environment map, sky model, and the shading they give the proxy.

:func:`step1` estimates what the paper's Step 1 computes "by ray-tracing the inaccurate 3D model
and sky map" (Duchêne et al. 2015, Sec. 4): the completed environment map and sky model (via
:mod:`.skymodel`), the median radiance of every proxy vertex seen in the photographs, ``S_sky``
and ``S_ind`` by hemisphere ray casting with the paper's attenuation factor, and the proxy sun
visibility ``~v``, all per proxy vertex (:class:`Step1Result`; :mod:`.pixels` carries them to the
pixels). The rays are cast by :class:`~mvintrinsic.raytrace.Tracer`. The choices and their
measurements are in ``docs/step1.md``.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType

import numpy as np
from scipy.spatial import cKDTree

from ._validation import is_real
from .environment import EnvironmentMap, HorizonPlane, estimate_environment, find_horizon
from .image_model import clamped_cosine
from .planes import PlaneConfig
from .raytrace import (
    RayHits,
    Tracer,
    cosine_hemisphere,
    depth_map,
    interpolate_points,
    morton_order,
    sun_visibility,
    vertex_normals,
    voxel_subsample,
)
from .scene import Scene, View
from .skymodel import SkyConfig, SkyModel

__all__ = [
    "ATTENUATION_MODES",
    "PointShading",
    "Step1Config",
    "Step1Result",
    "environment_shading",
    "fill_unseen",
    "ray_radiance",
    "step1",
    "vertex_observations",
    "vertex_radiance",
    "vertex_shading",
]


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
    planes : PlaneConfig or None
        The smoothed normals of the vertices on one of the proxy's dominant planes take the plane's
        normal (:mod:`mvintrinsic.planes`, :func:`~mvintrinsic.raytrace.vertex_normals`); None: the
        smoothed normals alone. Not in the paper (the ``"paper"`` preset sets None). The smoothing
        leaves an MVS proxy's facades wavy (explained pixels of street_s0: a median 5.8 degrees from
        the exact mesh, 30% above 10); on its planes the median falls to 0.3 degrees, and Step 2's
        cosines with it (``docs/step1.md``, "Normals on the proxy's planes").
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
    planes: PlaneConfig | None = field(default_factory=PlaneConfig)
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
        if not isinstance(self.planes, (PlaneConfig, type(None))):
            raise TypeError(f"planes must be a PlaneConfig or None, got {type(self.planes).__name__}")
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
    gen = np.random.default_rng(rng)
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


def vertex_shading(
    points: np.ndarray,
    normals: np.ndarray,
    tracer: Tracer,
    environment: EnvironmentMap,
    radiance: np.ndarray,
    *,
    config: Step1Config,
    rng: np.random.Generator | int | None = None,
    progress: bool = False,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``S_sky`` and ``S_ind`` at every proxy vertex as Step 1 computes them (Sec. 4, Eq. 1).

    :func:`environment_shading` with ``config``'s rays, offset, attenuation and convergence test at
    a voxel subsample of the vertices (``config.subsample``; every vertex when None), the other
    vertices interpolated from it (:func:`~mvintrinsic.raytrace.interpolate_points`).

    Parameters
    ----------
    points, normals : (N, 3) array_like
        The proxy's vertices (m) and unit normals.
    tracer : Tracer
        What the hemisphere rays are cast against (the proxy, or the proxy and more geometry whose
        vertices follow its own in ``radiance``).
    environment : EnvironmentMap
    radiance : (M, 3) array_like
        Radiance of every vertex of ``tracer``'s mesh (NaN: unseen).
    config : Step1Config
    rng : numpy.random.Generator or int, optional
    progress : bool, optional

    Returns
    -------
    sky, indirect : (N, 3) float32
    rays : (P,) int32
        Rays cast per traced point.
    """
    traced = np.arange(len(points)) if config.subsample is None else voxel_subsample(points, config.subsample)
    sky, indirect, rays = environment_shading(
        points[traced], normals[traced], tracer, environment, radiance, n_rays=config.n_rays,
        ray_offset=config.ray_offset, attenuation=config.indirect_attenuation, rng=rng,
        batch_rays=config.batch_rays, progress=progress, tolerance=config.ray_tolerance,
        max_rays=config.max_rays, return_counts=True,
    )
    if len(traced) < len(points):
        both = interpolate_points(points[traced], normals[traced], np.concatenate([sky, indirect], axis=1),
                                  points, normals, neighbors=config.interpolation_neighbors)
        sky, indirect = both[:, :3].astype(np.float32), both[:, 3:].astype(np.float32)
    return sky, indirect, rays


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
       scene's up vector (:func:`~mvintrinsic.environment.find_horizon`, ``SkyConfig.horizon``);
    2. coverage: camera rays of every view against the proxy; the valid pixels they miss are
       splatted into a partial environment map (median over views);
    3. sky: colour sky detector above the horizon, Preetham sky fit (Eq. 4), completion of the
       map (model above the horizon, diffusion below);
    4. proxy radiance: median of each vertex's observations;
    5. normals: the proxy's vertex normals smoothed (:attr:`Step1Config.normal_smoothing`, not in
       the paper) and snapped to its dominant planes (:attr:`Step1Config.planes`, not in the
       paper); every quantity below uses them;
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
    gen = np.random.default_rng(rng)
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
    points, normals = scene.proxy.vertices, vertex_normals(scene.proxy, config.normal_smoothing, config.planes)
    timings["normals"] = time.perf_counter() - start

    start = time.perf_counter()
    sky, indirect, rays = vertex_shading(points, normals, tracer, environment, radiance, config=config, rng=gen,
                                         progress=progress)
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
