"""Occluders the proxy lost, carved from the shadows and the photos (beyond the paper).

An MVS proxy loses thin and porous occluders: tree crowns, poles, railings. Step 1 then integrates
``S_sky`` and ``S_ind`` at the points under them as if nothing stood between them and the sky near
the sun, the brightest part of it: in the umbra of our synthetic scenes ``S_env`` came out 35-114%
above the truth, and Step 2's ``L_sun``, calibrated against it (Eq. 5), 1.45-2.51 times the truth
(``docs/step4.md``). Adding the exact mesh's missing triangles to the proxy brought the demo's umbra
error from +39/+54/+91% to within -17..+9% (an oracle study, ``docs/step4.md``).

Once Step 3 has labelled the shadows, the lost occluders leave evidence a voxel grid can collect
(a form of space carving, Kutulakos and Seitz 2000, with shadows as in Savarese et al. 2007):

* **Sun rays.** A pixel labelled shadow whose proxy point the proxy leaves in the sun (``~v = 1``)
  has an occluder somewhere along its ray toward the sun; a lit pixel has none along its own. Per
  voxel, ``n_shadow`` and ``n_lit`` count the rays of each kind that cross it.
* **Camera rays.** A pixel that sees the sky, or sees the proxy with the colour the proxy has there
  (its vertices' median radiance, within ``consistency`` in log radiance), looks through empty
  space up to that surface; a pixel of a surface the proxy lost (``filled``), or one whose colour
  disagrees with the proxy behind it, may be looking at an occluder. Per voxel, ``n_free`` and
  ``n_blocked`` count the camera rays of each kind that cross it.

A voxel is an occluder when at least ``min_shadow_rays`` shadow rays cross it, shadow rays are
more than ``shadow_share`` of its sun rays, the camera rays that cross it are blocked more than
``camera_share`` of the time (or no camera ray crosses it: space no photo sees is not carved), and
it lies more than ``clearance`` voxels from every proxy vertex (what the proxy holds is not added
twice). One sun direction alone cannot tell where along a shadow ray the occluder sits; the
camera rays carve the free part of each ray.

:func:`occluded_step1` then integrates Step 1's ``S_sky`` and ``S_ind`` again against the proxy and
the occluders (:func:`~mvintrinsic.env_shading.environment_shading`); a ray that hits an occluder
brings its radiance (``OccluderConfig.radiance``: none by default; the photos show the side of a
crown that faces the cameras, not the side that faces the ground below it). The pipeline runs
Steps 2 and 3 again on the result (``Config.occluders``).

The pixels that see an occluder (their camera ray meets a voxel before the proxy,
:func:`seen_occluders`) have no surface in the model: their cosine and ``S_env`` are those of the
proxy surface behind the crown. Where such a pixel is labelled shadow its shading is ``S_env``
alone, which varies from leaf to leaf with nothing in the proxy to predict it; there
:func:`smooth_occluder_reflectance` takes the reflectance as smooth (a crown's leaves share one
material more than they share one light) and gives the shading the rest, ``S_tot = I / R``: the
single-image prior where the multi-view model has no geometry. Measurements: ``docs/step4.md``.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from types import MappingProxyType

import numpy as np
from scipy.spatial import cKDTree

from ._validation import describe, is_real
from .env_refine import with_reflectance
from .env_shading import PointShading, Step1Result, vertex_shading
from .pixels import PixelQuantities, masked_gaussian_mean
from .raytrace import Tracer, rasterize
from .results import SHADOW_LABELS, IntrinsicLayers
from .scene import Proxy, View

__all__ = ["OCCLUDER_RADIANCE", "OccluderConfig", "Occluders", "carve_occluders", "occluded_step1",
           "seen_occluders", "smooth_occluder_reflectance", "unexplained_shadow_share"]

#: What a hemisphere ray that hits an occluder brings (:class:`OccluderConfig`).
OCCLUDER_RADIANCE = ("zero", "observed")


@dataclass(frozen=True)
class OccluderConfig:
    """Options of the lost-occluder carving (not in the paper; module docstring).

    Parameters
    ----------
    voxel : float
        Edge of the voxels, metres. 0.5 with ``clearance`` 3 (1.5 m) kept the reflectance LMSE of
        the demo at both sizes where it was (0.25 m and 1.5 voxels: +10% on the 240x180 demo;
        ``docs/step4.md``): voxels that sit near the surfaces they shade change ``S_env`` there in
        patches the truth does not have.
    margin : float
        Metres the grid extends beyond the bounding box of the proxy and the camera centres on
        every side.
    min_shadow_rays : int
        Fewest shadow rays that must cross an occluder voxel.
    shadow_share : float
        Share of a voxel's sun rays that must come from shadow pixels, in (0, 1).
    camera_share : float
        Share of the camera rays crossing a voxel that must be blocked (not sky, not consistent
        with the proxy behind), in (0, 1).
    consistency : float
        Median over R, G, B of ``|log I - log radiance|`` below which a pixel is consistent with
        the proxy surface it sees (about 35%).
    clearance : float
        Voxels (edge lengths) an occluder keeps from every proxy vertex (see ``voxel``).
    ray_start : float
        Metres along a sun ray before its voxels count (off the receiver's own surface).
    shadow_visibility, lit_visibility : float
        A shadow pixel has ``v_sun`` below the first, a lit pixel above the second.
    radiance : {"zero", "observed"}
        What a hemisphere ray that hits an occluder brings to ``S_ind``: nothing (default), or the
        mean colour of the pixels whose camera rays first hit the voxel (voxels no pixel sees take
        their nearest seen voxel's). On demo_480 the umbra's ``S_env`` was +2/+5/+18% off with
        ``"zero"`` and +22/+27/+38% with ``"observed"`` (``docs/step4.md``): the photos see the
        sunlit outside of a crown, the ground below it sees its dark underside.
    max_voxels : int
        Largest grid (voxels); the voxel edge grows to stay within it.
    when : {"auto", "always"}
        ``"auto"`` (default): carve only when the proxy leaves in the sun at least
        ``min_unexplained`` of the labelled shadow pixels (:func:`unexplained_shadow_share`; the
        choice is recorded in ``lighting.json`` "model"); ``"always"``: whenever Step 3 ran.
    min_unexplained : float
        The share of ``when="auto"``, in (0, 1): 0.5, a majority of the shadow the proxy cannot
        cast. Measured (``docs/step4.md``): 0.68-0.87 on the four scenes whose proxy lost their
        trees (where carving brought the umbra's ``S_env`` from +36..+91% to -16..+36% and lowered
        both LMSEs at 480x360), 0.31-0.41 on the three whose proxy kept most occluders (where it
        overshot, -9..-33%, and moved ``L_sun`` away from the truth).
    reflectance_smoothing : float or None
        Standard deviation of the Gaussian over which the reflectance of shadow-labelled pixels
        that see an occluder is averaged (:func:`smooth_occluder_reflectance`), as a fraction of
        the image's longer side, in (0, 1); None keeps the model's layers there. 0.05 (24 px at
        480x360) lowered both LMSEs on the four scenes that carve (``docs/step4.md``); 0.025
        lowered the reflectance LMSE a little more (2.8% on average against 2.1%) and the shading
        LMSE less (6.4% against 7.6%), 0.1 the shading LMSE as much (7.8%) and the reflectance
        LMSE less (1.3%).
    """

    voxel: float = 0.5
    margin: float = 2.0
    min_shadow_rays: int = 2
    shadow_share: float = 0.5
    camera_share: float = 0.5
    consistency: float = 0.3
    clearance: float = 3.0
    ray_start: float = 0.3
    shadow_visibility: float = 0.5
    lit_visibility: float = 0.9
    radiance: str = "zero"
    max_voxels: int = 20_000_000
    when: str = "auto"
    min_unexplained: float = 0.5
    reflectance_smoothing: float | None = 0.05

    def __post_init__(self) -> None:
        for name in ("voxel", "consistency", "clearance"):
            value = getattr(self, name)
            if not is_real(value) or not 0 < value < np.inf:
                raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
        for name in ("margin", "ray_start"):
            value = getattr(self, name)
            if not is_real(value) or not 0 <= value < np.inf:
                raise ValueError(f"{name} must be a finite number >= 0 (metres), got {value!r}")
        if self.when not in ("auto", "always"):
            raise ValueError(f"when must be 'auto' or 'always', got {self.when!r}")
        for name in ("shadow_share", "camera_share", "shadow_visibility", "lit_visibility", "min_unexplained"):
            value = getattr(self, name)
            if not is_real(value) or not 0 < value < 1:
                raise ValueError(f"{name} must be in (0, 1), got {value!r}")
        for name in ("min_shadow_rays", "max_voxels"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise ValueError(f"{name} must be a positive integer, got {value!r}")
        smoothing = self.reflectance_smoothing
        if smoothing is not None and (not is_real(smoothing) or not 0 < smoothing < 1):
            raise ValueError(f"reflectance_smoothing must be None or in (0, 1), got {smoothing!r}")
        if self.radiance not in OCCLUDER_RADIANCE:
            raise ValueError(f"radiance must be one of {', '.join(map(repr, OCCLUDER_RADIANCE))}, got {self.radiance!r}")


@dataclass(frozen=True, eq=False)
class Occluders:
    """Voxels of occluders the proxy lost, world frame.

    Parameters
    ----------
    centres : (K, 3) float64
        Voxel centres, metres.
    size : float
        Voxel edge, metres.
    radiance : (K, 3) float32
        What a hemisphere ray that hits the voxel brings (:attr:`OccluderConfig.radiance`), in the
        views' radiance units.
    counts : mapping of str to int
        Rays used: ``shadow``, ``lit`` (sun rays), ``free``, ``blocked`` (camera rays).
    seconds : float
        Time spent carving.
    """

    centres: np.ndarray
    size: float
    radiance: np.ndarray
    counts: Mapping[str, int] = field(default_factory=dict)
    seconds: float = 0.0

    def __len__(self) -> int:
        return len(self.centres)

    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """The voxels as closed cubes: ``vertices (8K, 3) float64`` and ``triangles (12K, 3) int64``
        (eight vertices and twelve triangles per voxel, in voxel order)."""
        h = self.size / 2.0
        corners = np.array([[x, y, z] for x in (-h, h) for y in (-h, h) for z in (-h, h)])
        vertices = (self.centres[:, None, :] + corners[None]).reshape(-1, 3)
        faces = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                          [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
        triangles = (np.arange(len(self.centres))[:, None, None] * 8 + faces[None]).reshape(-1, 3)
        return vertices, triangles.astype(np.int64)

    def proxy(self) -> Proxy:
        """:meth:`mesh` as a :class:`~mvintrinsic.scene.Proxy` (normals unused: hits take the
        triangles' geometric normals)."""
        vertices, triangles = self.mesh()
        return Proxy(vertices=vertices, normals=np.tile([0.0, 0.0, 1.0], (len(vertices), 1)), triangles=triangles)

    def __repr__(self) -> str:
        return f"Occluders({len(self)} voxels of {self.size:g} m, {dict(self.counts)})"


class _Grid:
    """An axis-aligned voxel grid (world frame) and ray counts per voxel."""

    def __init__(self, low: np.ndarray, high: np.ndarray, voxel: float, max_voxels: int) -> None:
        extent = np.maximum(high - low, 1e-6)
        voxel = max(voxel, float(np.cbrt(np.prod(extent) / max_voxels)))
        self.low, self.voxel = low, voxel
        self.dims = np.maximum(np.ceil(extent / voxel).astype(np.int64), 1)
        self.size = int(np.prod(self.dims))
        self._span = float(np.linalg.norm(self.dims * voxel))

    def count(self, origins: np.ndarray, directions: np.ndarray, t_start: float | np.ndarray,
              t_end: float | np.ndarray, *, chunk: int = 8192) -> np.ndarray:
        """Rays crossing each voxel (each ray counted once per voxel), (size,) float64: samples
        every half voxel along ``origins + t directions`` for ``t_start <= t < t_end``."""
        out = np.zeros(self.size)
        n = len(origins)
        if n == 0:
            return out
        step = 0.5 * self.voxel
        offsets = (np.arange(int(self._span / step) + 1) + 0.5) * step
        start = np.broadcast_to(np.asarray(t_start, dtype=np.float64), (n,))
        end = np.broadcast_to(np.asarray(t_end, dtype=np.float64), (n,))
        # Where each ray leaves the grid (a convex box it starts in or never enters): samples past it
        # fall outside and count nothing, so each batch of rays, sorted by length, stops there.
        high = self.low + self.dims * self.voxel
        with np.errstate(divide="ignore", invalid="ignore"):
            inverse = 1.0 / directions
            leave = np.nanmin(np.maximum((self.low - origins) * inverse, (high - origins) * inverse), axis=1)
        length = np.clip(np.minimum(end, leave) - start, 0.0, offsets[-1] + step)
        order = np.argsort(length, kind="stable")
        for a in range(0, n, chunk):
            rays = order[a:a + chunk]
            k = min(len(offsets), int(np.ceil(length[rays].max() / step)) + 1)
            t = start[rays, None] + offsets[None, :k]
            inside = t < end[rays, None]
            points = origins[rays, None, :] + t[..., None] * directions[rays, None, :]
            ijk = np.floor((points - self.low) / self.voxel).astype(np.int64)
            inside &= ((ijk >= 0) & (ijk < self.dims)).all(axis=-1)
            flat = np.ravel_multi_index(tuple(np.clip(ijk, 0, self.dims - 1).transpose(2, 0, 1)), self.dims)
            flat = np.where(inside, flat, -1)
            first = np.ones_like(inside)
            first[:, 1:] = flat[:, 1:] != flat[:, :-1]  # consecutive samples in one voxel count once
            out += np.bincount(flat[inside & first], minlength=self.size)
        return out

    def centres(self, index: np.ndarray) -> np.ndarray:
        return self.low + (np.stack(np.unravel_index(index, self.dims), axis=1) + 0.5) * self.voxel


def _check(views: Sequence[View], quantities: Mapping[str, PixelQuantities],
           layers: Mapping[str, IntrinsicLayers]) -> None:
    for view in views:
        if view.stem not in quantities or view.stem not in layers:
            raise ValueError(f"quantities and layers must hold view {view.stem!r}")
        if quantities[view.stem].shape != view.shape or layers[view.stem].shape != view.shape:
            raise ValueError(f"quantities and layers of view {view.stem!r} must have its shape {view.shape}")


def _sun_ray_pixels(q: PixelQuantities, layer: IntrinsicLayers, config: OccluderConfig
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pixels on the proxy; labelled shadow; shadow the proxy does not cast; lit. (H, W) bool each."""
    on_proxy = q.valid & ~q.filled & np.isfinite(q.depth)
    labelled = on_proxy & (layer.shadow_labels == SHADOW_LABELS["shadow"]) & (layer.visibility < config.shadow_visibility)
    # shadowed, though the proxy leaves the point in the sun (and it faces the sun)
    unexplained = labelled & (q.visibility > 0.5) & (q.cosine > 0.05)
    lit = on_proxy & (layer.shadow_labels == SHADOW_LABELS["lit"]) & (layer.visibility > config.lit_visibility)
    return on_proxy, labelled, unexplained, lit


def unexplained_shadow_share(quantities: Mapping[str, PixelQuantities], layers: Mapping[str, IntrinsicLayers], *,
                             config: OccluderConfig | None = None) -> float | None:
    """Share of the labelled shadow pixels that the proxy leaves in the sun, over all views.

    A pixel counts when it is labelled shadow by Step 3 (``v_sun`` below
    ``config.shadow_visibility``) on the proxy; it is unexplained when its point faces the sun and
    the proxy's own shadow ray escapes (``~v = 1``): an occluder the proxy lost, or a wrong label.

    Parameters
    ----------
    quantities : mapping of str to PixelQuantities
    layers : mapping of str to IntrinsicLayers
        Step 3's layers of the same views.
    config : OccluderConfig, optional

    Returns
    -------
    float or None
        None when no pixel is labelled shadow.
    """
    config = config or OccluderConfig()
    labelled = unexplained = 0
    for stem, q in quantities.items():
        if stem not in layers or layers[stem].shape != q.shape:
            raise ValueError(f"layers must hold view {stem!r} with its shape {q.shape}")
        _, shadow, lost, _ = _sun_ray_pixels(q, layers[stem], config)
        labelled += int(shadow.sum())
        unexplained += int(lost.sum())
    return unexplained / labelled if labelled else None


def carve_occluders(
    views: Sequence[View],
    quantities: Mapping[str, PixelQuantities],
    layers: Mapping[str, IntrinsicLayers],
    radiance: np.ndarray,
    tracer: Tracer,
    sun_direction: np.ndarray,
    *,
    config: OccluderConfig | None = None,
) -> Occluders:
    """Voxels of the occluders the proxy lost, from Step 3's shadows and the photos (module docstring).

    Parameters
    ----------
    views : sequence of View
    quantities : mapping of str to PixelQuantities
        Step 1's per-pixel quantities of every view (``~v``, depth, sky and filled masks).
    layers : mapping of str to IntrinsicLayers
        Step 3's layers of every view (``shadow_labels`` and ``v_sun``).
    radiance : (N, 3) array_like
        Median radiance of every proxy vertex (:attr:`Step1Result.radiance`, NaN: unseen).
    tracer : Tracer
        Over the proxy.
    sun_direction : (3,) array_like
        Unit vector toward the sun, world frame.
    config : OccluderConfig, optional

    Returns
    -------
    Occluders
        Possibly empty.
    """
    config = config or OccluderConfig()
    _check(views, quantities, layers)
    start = time.perf_counter()
    sun = np.asarray(sun_direction, dtype=np.float64)
    vertices = np.asarray(tracer.proxy.vertices, dtype=np.float64)
    extent = np.vstack([vertices, [view.camera.center for view in views]])  # occluders above the proxy
    grid = _Grid(extent.min(axis=0) - config.margin, extent.max(axis=0) + config.margin, config.voxel,
                 config.max_voxels)
    shadow_rays, lit_rays = np.zeros(grid.size), np.zeros(grid.size)
    free_rays, blocked_rays = np.zeros(grid.size), np.zeros(grid.size)
    counts = {"shadow": 0, "lit": 0, "free": 0, "blocked": 0}
    looks: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = []
    for view in views:
        q, layer, camera = quantities[view.stem], layers[view.stem], view.camera
        rays = camera.pixel_rays().reshape(*camera.shape, 3)
        depth = q.depth.astype(np.float64)
        on_proxy, _, shadow, lit = _sun_ray_pixels(q, layer, config)
        points = camera.center + np.where(on_proxy, depth, 0.0)[..., None] * rays + 0.05 * q.normals
        for mask, acc, name in ((shadow, shadow_rays, "shadow"), (lit, lit_rays, "lit")):
            acc += grid.count(points[mask], np.broadcast_to(sun, (int(mask.sum()), 3)), config.ray_start, np.inf)
            counts[name] += int(mask.sum())
        expected = rasterize(radiance, camera, tracer)  # the proxy's radiance behind each pixel
        image = np.asarray(view.image, dtype=np.float64)
        with np.errstate(invalid="ignore"):
            distance = np.median(np.abs(np.log(image + 1e-3) - np.log(np.abs(expected) + 1e-3)), axis=-1)
        consistent = on_proxy & (distance < config.consistency)  # NaN (unseen vertices): not consistent
        blocked = (on_proxy & ~consistent) | q.filled
        # up to the surface behind: the proxy's (minus 0.3 m), none for the sky and lost surfaces
        reach = np.where(q.filled | q.sky_mask, np.inf, depth - 0.3)
        for mask, acc, name in ((q.sky_mask | consistent, free_rays, "free"), (blocked, blocked_rays, "blocked")):
            n = int(mask.sum())
            acc += grid.count(np.repeat(camera.center[None], n, axis=0), rays[mask], 0.0, reach[mask])
            counts[name] += n
        looks.append((camera.center, rays[blocked], image[blocked], reach[blocked]))
    seen = free_rays + blocked_rays
    occupied = (shadow_rays >= config.min_shadow_rays) \
        & (shadow_rays > config.shadow_share * (shadow_rays + lit_rays)) \
        & ((blocked_rays > config.camera_share * seen) | (seen == 0))
    index = np.flatnonzero(occupied)
    centres = grid.centres(index)
    if len(centres):  # what the proxy holds is not added twice
        near, _ = cKDTree(vertices).query(centres, distance_upper_bound=config.clearance * grid.voxel)
        centres = centres[~np.isfinite(near)]
    occluders = Occluders(centres=centres, size=grid.voxel, radiance=np.zeros((len(centres), 3), np.float32),
                          counts=MappingProxyType(counts))
    if config.radiance == "observed" and len(centres):
        occluders = replace(occluders, radiance=_observed_radiance(occluders, looks))
    for array in (occluders.centres, occluders.radiance):
        array.flags.writeable = False
    return replace(occluders, seconds=time.perf_counter() - start)


def _observed_radiance(occluders: Occluders, looks: Sequence[tuple]) -> np.ndarray:
    """Mean colour of the blocked pixels whose camera rays first hit each voxel; the nearest seen
    voxel's where none does; zero when no voxel is seen. (K, 3) float32."""
    cubes = Tracer(occluders.proxy())
    total = np.zeros((len(occluders), 3))
    n = np.zeros(len(occluders))
    for centre, rays, colours, reach in looks:
        hits = cubes.intersect(centre, rays)
        ok = hits.hit & (hits.t < reach)
        voxel = hits.triangle[ok] // 12
        np.add.at(total, voxel, colours[ok])
        np.add.at(n, voxel, 1.0)
    seen = n > 0
    out = np.zeros((len(occluders), 3))
    if seen.any():
        out[seen] = total[seen] / n[seen, None]
        if not seen.all():
            _, nearest = cKDTree(occluders.centres[seen]).query(occluders.centres[~seen])
            out[~seen] = out[seen][nearest]
    return out.astype(np.float32)


def occluded_step1(step1_result: Step1Result, tracer: Tracer, occluders: Occluders, *,
                   rng: np.random.Generator | int | None = None, progress: bool = False) -> Step1Result:
    """Step 1's ``S_sky`` and ``S_ind`` (paper Sec. 4, Eq. 1) integrated again against the proxy and the occluders.

    The same hemisphere rays as :func:`~mvintrinsic.env_shading.step1`
    (:func:`~mvintrinsic.env_shading.vertex_shading` with its config) at the proxy vertices, cast
    against the proxy plus the occluders' cubes; a ray that hits a cube brings the voxel's
    :attr:`Occluders.radiance`. ``~v``, the cosine, the environment map and the vertex radiance are
    kept.

    Parameters
    ----------
    step1_result : Step1Result
    tracer : Tracer
        Over the proxy of ``step1_result``.
    occluders : Occluders
    rng : numpy.random.Generator or int, optional
        Seeds the hemisphere sampling.
    progress : bool, optional

    Returns
    -------
    Step1Result
        ``step1_result`` with the new shading, and ``timings["occluded_shading"]``; itself when
        there is no occluder.
    """
    if not len(occluders):
        return step1_result
    start = time.perf_counter()
    proxy = tracer.proxy
    if proxy.triangles is None:
        raise ValueError("tracer: occluders can only be added to a triangle-mesh proxy")
    cubes = occluders.proxy()
    both = Proxy(vertices=np.vstack([proxy.vertices, cubes.vertices]), normals=np.vstack([proxy.normals, cubes.normals]),
                 triangles=np.vstack([proxy.triangles, cubes.triangles + len(proxy.vertices)]))
    radiance = np.vstack([step1_result.radiance, np.repeat(occluders.radiance, 8, axis=0)])  # 8 corners a voxel
    sky, indirect, _ = vertex_shading(np.asarray(proxy.vertices, dtype=np.float64), step1_result.normals,
                                      Tracer(both), step1_result.environment, radiance, config=step1_result.config,
                                      rng=rng, progress=progress)
    for array in (sky, indirect):
        array.flags.writeable = False
    shading = PointShading(sky=sky, indirect=indirect, visibility=step1_result.shading.visibility,
                           cosine=step1_result.shading.cosine)
    timings = dict(step1_result.timings, occluded_shading=time.perf_counter() - start)
    return replace(step1_result, shading=shading, timings=MappingProxyType(timings))


def seen_occluders(views: Sequence[View], quantities: Mapping[str, PixelQuantities], occluders: Occluders
                   ) -> dict[str, np.ndarray]:
    """The pixels that see an occluder: their centre ray meets a voxel before the proxy.

    Parameters
    ----------
    views : sequence of View
    quantities : mapping of str to PixelQuantities
        Step 1's per-pixel quantities of every view; ``depth`` is the distance to the proxy.
    occluders : Occluders

    Returns
    -------
    dict of str to (H, W) bool
        By stem; all False without occluders.
    """
    views = list(views)
    for view in views:
        if view.stem not in quantities:
            raise ValueError(f"quantities: no entry for view {view.stem!r}")
    if not len(occluders):
        return {view.stem: np.zeros(quantities[view.stem].depth.shape, dtype=bool) for view in views}
    cubes = Tracer(occluders.proxy())
    seen = {}
    for view in views:
        depth = quantities[view.stem].depth
        if depth.shape != view.camera.shape:
            raise ValueError(f"quantities[{view.stem!r}]: shape {depth.shape} is not the camera's {view.camera.shape}")
        t = cubes.intersect(view.camera.center, view.camera.pixel_rays()).t.reshape(depth.shape)
        with np.errstate(invalid="ignore"):
            seen[view.stem] = np.isfinite(t) & (t < depth - 1e-3 * occluders.size)
    return seen


def smooth_occluder_reflectance(layers: IntrinsicLayers, seen: np.ndarray, *, sigma: float) -> IntrinsicLayers:
    """Smooth reflectance, and the shading the rest, where a shadowed pixel sees an occluder the proxy lost.

    Over the pixels that see an occluder (``seen``), are labelled shadow and have a reflectance,
    the reflectance is replaced by its Gaussian mean over those pixels (normalised convolution,
    standard deviation ``sigma`` pixels) and every shading term is multiplied by ``R_old / R_new``
    (:func:`~mvintrinsic.env_refine.with_reflectance`), so ``R * S_tot`` still reproduces the image
    (Eq. 1). The labels and ``v_sun`` are kept; every other pixel is unchanged.

    Why (not in the paper): such a pixel's shading is ``S_env`` at a leaf the proxy does not hold,
    and the model gives it the ``S_env`` of the surface behind the crown. On the four scenes that
    carve, replacing ``S_env`` by the truth on these pixels alone (6-9% of the image) halved the
    demo_480's shading LMSE (0.115 -> 0.060); computing ``S_env`` at the voxels' faces did not
    move it (0.115). Smoothing the reflectance of the lit ones too helped the demos and hurt
    street_s0 (``docs/step4.md``).

    Parameters
    ----------
    layers : IntrinsicLayers
    seen : (H, W) array_like of bool
        The pixels that see an occluder (:func:`seen_occluders`).
    sigma : float
        Standard deviation of the Gaussian, pixels, > 0.

    Returns
    -------
    IntrinsicLayers
    """
    if not isinstance(layers, IntrinsicLayers):
        raise TypeError(f"layers must be an IntrinsicLayers, got {describe(layers)}")
    seen = np.asarray(seen)
    if seen.dtype != bool or seen.shape != layers.shape:
        raise ValueError(f"seen must be a boolean array of shape {layers.shape}, got {seen.dtype} {seen.shape}")
    if not is_real(sigma) or not 0 < sigma < np.inf:
        raise ValueError(f"sigma must be a finite number > 0 (pixels), got {sigma!r}")
    reflectance = layers.reflectance.astype(np.float64)
    region = seen & (layers.shadow_labels == SHADOW_LABELS["shadow"]) & (reflectance > 0).all(axis=-1)
    if not region.any():
        return layers
    smooth = masked_gaussian_mean(reflectance, region, float(sigma))
    return with_reflectance(layers, np.where(region[..., None], smooth, reflectance))
