"""Where the photographs show something the proxy lacks: occupancy along rays (beyond the paper).

The relighting caster (paper Sec. 8, :func:`mvintrinsic.caster.build_caster`) lifts each shadow
pixel toward the sun by the distance its sun ray travels to the proxy. Where the proxy lost the
occluder (tree crowns, poles, railings: an MVS proxy keeps little of them) the ray misses, and the
paper drops the pixel's cluster: its shadow cannot move. The occluder is usually in the
photographs even so. This module reads, from the views alone, where along a ray something the
proxy lacks stands, and so gives those rays a distance (:attr:`RelightConfig.lost_occluders
<mvintrinsic.caster.RelightConfig>`).

Evidence, per view and pixel (a form of space carving, Kutulakos and Seitz 2000):

* **occupied**: the pixel has an estimate and the proxy does not explain it: its camera ray
  misses the proxy (a crown against the sky), or its colour is at least ``consistency`` in log
  radiance from what each of the other views that see its receiver point sees there
  (:attr:`RelightConfig.consistency <mvintrinsic.caster.RelightConfig>`'s test: a crown before
  the facade the proxy kept);
* **free**: the pixel looks at the sky (no estimate, its ray misses the proxy), or at a proxy
  surface another view confirms (a colour within ``consistency`` there): the space before that
  surface is empty;
* neither: no evidence (no other view sees the receiver point).

A point of a ray counts as *seen occupied* by a view when it projects into the view in front of
the camera, lies in front of the view's proxy surface at that pixel (by ``depth_margin``,
relative: a point behind the surface is hidden from the view) and the pixel is occupied; *seen
free* likewise on a free pixel. The ray's distance is the first sample (every ``step`` metres
from ``start`` to ``max_distance``) seen occupied by at least ``min_views`` views and free by none
of them (``share`` 1). No view alone places a point along its own ray; the other views'
parallax does.

Measured (``docs/relight.md``, "Occluders the proxy lost, from the photographs";
``benchmarks/bench_relight.py --lost-occluders``, five 480x360 scenes, 22 scene-suns): with the
true shadow layers (row (d)) the relit PSNR rises at all 22, by 1.05 dB on average at +-15
degrees (row (c) - (d) from 3.91 to 2.86 dB); with the pipeline's layers (row (e)) by 0.27 dB on
average, -0.01 to +0.52 ((e) - (a) at +-15 degrees from 1.91 to 2.17 dB). With it a cluster must
have ``min_hits`` (60%) of its rays hit instead of the paper's 30%: with 30%, row (e) lost up to
4.8 dB, because where the proxy has no occluder a third to a half of the pixels the pipeline
labels shadow are lit in the truth (dark windows, a lost crown's own leaves, lit gaps under it),
their sheets cast false shadows at the new sun and their reflectance, made for a shadow, is
brighter than the paper's dropping leaves it in the light; a false shadow finds an occluder on
fewer of its rays. The clusters it keeps still mix the two hypotheses (``belief``). The relighter's
default since 2026-11-29 with ``silhouette=1`` (``caster.LOST_OCCLUDERS``; with 0 the 240x180 demo
loses 0.7-1.0 dB, the phantom eave of ``OccupancyConfig.silhouette``): row (e) - (a) at +-15 degrees
2.41 dB against 2.07 without it on five 480x360 scenes, row (e)'s cross-view agreement 0.006 lower
on average (``benchmarks/bench_occupancy_silhouette.py``); each new sun about 25 ms per view more at
1000x750 (within the 100 ms budget since the relighter's two threads: 0.074-0.078 s;
``docs/relight.md``, "The default since 2026-11-29" and "Speed"; profiled on demo_480
resampled: 22% more caster rays per view, 15% of them occluded against 2.5%, 4x the time in the occlusion
tests; the caster holds 7x the triangles, but decimating its sheets did not make them faster). Building takes
0.5-1.3 s per 480x360 view with the true layers and 0.5-1.9 s with the pipeline's, against 0.3-0.9
s without it; 2.8-4.1 s per view at 1000x750 (three scenes resampled; 1.8-2.8 s without it). A
solid occluder seen from every side
in front of a surface is missed: the views that see it at the surface's point agree with each
other, so no pixel of it looks unexplained.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage

from ._validation import as_array, as_count, is_real
from .camera import Camera
from .correspondence import seen_pixels, surface_points
from .pixels import PixelQuantities
from .scene import View

__all__ = ["ClearRaysConfig", "OccupancyConfig", "PhotoOccupancy", "blend_rescued", "clear_sun_rays", "nearest_colour",
           "photo_occupancy", "shared_receivers", "silhouette_band", "unexplained_pixels"]


@dataclass(frozen=True)
class OccupancyConfig:
    """Options of :func:`photo_occupancy` (not in the paper; module docstring).

    Parameters
    ----------
    min_views : int
        Views that must see a ray's sample occupied; >= 1. 4 (chosen on street_s0, exploratory:
        2 views with ``share`` 0.7 let the crowns' fringes in, row (d) 0.2-0.3 dB and row (e)
        1.2-1.9 dB lower; 3 with 0.9 row (d) within 0.02 dB, row (e) 0.2-0.5 dB lower).
    share : float
        Least share of occupied among the views that see the sample occupied or free; in (0, 1].
        1: no view may see through the sample.
    step, start, max_distance : float
        Metres along the ray between samples, to the first and up to the last; > 0,
        ``start < max_distance``. 0.1, 0.3 and 20: a 4 cm TSDF voxel is finer than the
        occupancy the photographs resolve at 480x360, and a crown stands within 20 m of its
        shadow.
    depth_margin : float
        A sample counts for a view only if nearer its camera than ``(1 - depth_margin)`` times the
        view's proxy surface at the pixel; in [0, 1). 0.03.
    consistency : float
        Log-radiance distance under which two views see the same colour; > 0. 0.3, as
        :attr:`RelightConfig.consistency <mvintrinsic.caster.RelightConfig>`.
    belief : float
        Weight of the hypothesis that a cluster kept only thanks to these distances (*rescued*:
        the paper's rule drops it) is a lost occluder's shadow; in [0, 1]. At its pixels the
        relighter renders ``belief`` times the moved shadow plus ``1 - belief`` times the paper's
        image (the cluster dropped, as :attr:`RelightConfig.dropped` says): the
        expected image over the two hypotheses (:func:`blend_rescued`). With the pipeline's
        labels 52-72% of the rescued pixels were shadowed at capture (street_s0, exploratory), and
        even with the true labels the new shadow of a crown's dappled light is not where a sheet
        of its shadow pixels puts it. 0.5 against 1 (``bench_relight.py --lost-occluders``, five
        scenes, 22 scene-suns): row (d) above at 20 (-0.01 to +0.37 dB, mean +0.16), row (e)
        -0.03 to +0.30 (mean +0.06), and row (e) now within 0.01 dB of the option off or above it
        at all 22. Exploratory, on four of them: 0.7 within -0.12..+0.07 dB of 0.5 (means 0.00),
        0.3 0.08 dB below with the true layers, 0 below at all 17 with them. 1: the moved shadow alone.
    silhouette : int
        Pixels: an unexplained pixel within this many of the proxy's silhouette in its view (where
        the camera rays pass from hitting the proxy to missing it, :func:`silhouette_band`) is no
        evidence; >= 0. Such a pixel may mix the proxy's surface with the sky beyond it (a roof's
        edge): no other view sees its colour at its receiver point, so it looks unexplained in
        every view, and with cameras at one height the bands of all views line up: the samples
        under the roof's edge, metres in front of the facade, are seen occupied by all of them (a
        phantom eave). It may as well be the edge of an eave or a crown the proxy lost. 0 (every
        unexplained pixel counts) against 1 (``benchmarks/bench_occupancy_silhouette.py``, seven
        scenes, row (e) - (a) with ``lost_occluders``): on the 240x180 demo, whose band is twice as
        wide in metres as at 480x360, the upper windows' false shadows find the phantom eave 2-4 m
        up their sun rays: -0.94 / -0.08 dB at az+15 / el+10 with 0, +1.12 / +1.04 with 1 (the
        default relighter +0.44 / +0.82); on the five 480x360 scenes and dev_courtyard (320x240) 1
        is -0.37 to +0.07 dB per scene (street_s0 the lowest: its rescued pixels fall from 6.3% to
        1.3%, the band held the lost eaves' own evidence), mean -0.03 at +-15 degrees. 0 here (Step 3's
        :class:`ClearRaysConfig`); 1 in the relighter's default (``caster.LOST_OCCLUDERS``): never
        below the relighter without the option on those five scenes and the demo.
    min_hits : float
        With these distances the relighter keeps a shadow cluster only when at least this share
        of its sun rays hit the proxy or find an occluder here (instead of
        :attr:`RelightConfig.min_proxy_hits <mvintrinsic.caster.RelightConfig>`, 0.3, when it is
        lower); in [0, 1]. 0.6: a false shadow the labels put where the proxy has no occluder
        finds one on fewer of its rays than a true shadow does. On five scenes (exploratory, then
        ``bench_relight.py --lost-occluders``) 0.5 let the false clusters of demo_480 through
        (row (e) 2.4-2.7 dB below 0.6), 0.7 lost true ones on street_s2 and street_sky (row (e)
        0.2-0.8 dB below 0.6).
    """

    min_views: int = 4
    share: float = 1.0
    step: float = 0.1
    start: float = 0.3
    max_distance: float = 20.0
    depth_margin: float = 0.03
    consistency: float = 0.3
    belief: float = 0.5
    min_hits: float = 0.6
    silhouette: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "min_views", as_count(self.min_views, "min_views", least=1))
        object.__setattr__(self, "silhouette", as_count(self.silhouette, "silhouette", least=0))
        for name, inside, interval in (("share", lambda v: 0.0 < v <= 1.0, "(0, 1]"),
                                       ("depth_margin", lambda v: 0.0 <= v < 1.0, "[0, 1)"),
                                       ("min_hits", lambda v: 0.0 <= v <= 1.0, "[0, 1]"),
                                       ("belief", lambda v: 0.0 <= v <= 1.0, "[0, 1]")):
            value = getattr(self, name)
            if not is_real(value) or not inside(value):
                raise ValueError(f"{name} must be a number in {interval}, got {value!r}")
            object.__setattr__(self, name, float(value))
        for name in ("step", "start", "max_distance", "consistency"):
            value = getattr(self, name)
            if not is_real(value) or not 0.0 < value < np.inf:
                raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
            object.__setattr__(self, name, float(value))
        if self.start >= self.max_distance:
            raise ValueError(f"start ({self.start}) must be below max_distance ({self.max_distance})")


@dataclass(frozen=True)
class ClearRaysConfig:
    """Options of :func:`clear_sun_rays`: Step 3's lit prior where the photographs see the sun ray free.

    Beyond the paper (``docs/step3.md``, "Sun rays the photographs see free"). Step 3 trusts the proxy's
    visibility ``~v`` four times less where it says lit (``prior_lit``) than where it says shadow, because an
    MVS proxy loses casters (crowns, poles) far more often than it invents them. Where the photographs
    themselves see the sun ray's path empty, no lost caster stands on it, and the proxy's "lit" is trusted
    at ``prior`` instead: dark materials that look like a shadowed neighbour (window glass in a painted frame,
    whose ratio to it is a sunlit wall's shadow ratio) are then labelled lit.

    Parameters
    ----------
    prior : float
        Weight of the proxy's lit visibility at the clear pixels (instead of
        :attr:`MultiViewShadowConfig.prior_lit <mvintrinsic.multiview_shadows.MultiViewShadowConfig>`, 0.05);
        >= 0. 0.3: on courtyard_s1 and street_s0 (480x360, exploratory) the pooled BER fell from 0.132 to
        0.112 and 0.114 to 0.077 with 0.3, to 0.113 and 0.076 with 0.6, 0.116 on courtyard_s1 with 1.0.
    distance, share, step : float
        :meth:`PhotoOccupancy.clear`: the first ``distance`` metres of the sun ray, sampled every ``step``,
        seen free at ``share`` of the samples at least. 8, 0.5, 0.2.
    stride : int
        The rays are cast from every ``k``-th pixel in both directions and the result is shared by the
        ``k x k`` block, ``k = max(stride, round(stride * side / 480))`` for a view whose longer side is
        ``side`` pixels (>= 1): 2 up to 720 pixels, 4 at 1000x750, so that the rays and the time per view
        stay those of a 480x360 view (the free paths are metres long, not pixels).
    occupancy : OccupancyConfig
        The occupancy evidence (:func:`photo_occupancy`); its rule for a sample seen occupied is the relighter's.
        ``OccupancyConfig()`` (``silhouette`` 0): the labelling measured in ``benchmarks/results/clear_rays.json``
        (with ``silhouette=1``, exploratory: the demo's BER 0.1638 -> 0.1625, courtyard_s1's unchanged to 0.0001).
    """

    prior: float = 0.3
    distance: float = 8.0
    share: float = 0.5
    step: float = 0.2
    stride: int = 2
    occupancy: OccupancyConfig = OccupancyConfig()

    def __post_init__(self) -> None:
        if not is_real(self.prior) or not 0.0 <= self.prior < np.inf:
            raise ValueError(f"prior must be a finite number >= 0, got {self.prior!r}")
        if not is_real(self.share) or not 0.0 <= self.share <= 1.0:
            raise ValueError(f"share must be a number in [0, 1], got {self.share!r}")
        for name in ("distance", "step"):
            value = getattr(self, name)
            if not is_real(value) or not 0.0 < value < np.inf:
                raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
        object.__setattr__(self, "stride", as_count(self.stride, "stride", least=1))
        if not isinstance(self.occupancy, OccupancyConfig):
            raise TypeError(f"occupancy must be an OccupancyConfig, got {type(self.occupancy).__name__}")
        if self.distance <= self.occupancy.start:
            raise ValueError(f"distance ({self.distance}) must be above occupancy.start ({self.occupancy.start})")
        for name in ("prior", "distance", "share", "step"):
            object.__setattr__(self, name, float(getattr(self, name)))


@dataclass(frozen=True, eq=False)
class PhotoOccupancy:
    """What the views say about the space before their proxy surfaces (module docstring).

    Parameters
    ----------
    cameras : tuple of Camera
        The views' cameras.
    depth : tuple of (H, W) float64
        Per view, the distance (metres, along the unit pixel ray) to the proxy; ``inf`` where the
        ray misses it.
    occupied, free : tuple of (H, W) bool
        Per view, the pixels that see something the proxy lacks, and those that see through to
        the sky or to a confirmed proxy surface (disjoint).
    config : OccupancyConfig
    """

    cameras: tuple[Camera, ...]
    depth: tuple[np.ndarray, ...]
    occupied: tuple[np.ndarray, ...]
    free: tuple[np.ndarray, ...]
    config: OccupancyConfig

    def first_occupied(self, origins: np.ndarray, directions: np.ndarray, *, chunk: int = 10000,
                       block: int = 20) -> np.ndarray:
        """Distance along each ray to its first sample seen occupied, metres; ``inf`` where none.

        Parameters
        ----------
        origins : (N, 3) array_like
            World-frame ray origins, metres.
        directions : (3,) or (N, 3) array_like
            Unit directions, one for all rays or one per ray, world frame.
        chunk, block : int, optional
            Rays and samples per batch (memory: ``chunk`` times ``block`` points). The samples are
            tested ``block`` at a time in order of distance, and a ray found stops there; the
            result does not depend on either.

        Returns
        -------
        (N,) float64
        """
        origins = as_array(origins, "origins", shape=(None, 3), dtype=np.float64)
        directions = np.asarray(directions, dtype=np.float64)
        if directions.shape not in ((3,), origins.shape):
            raise ValueError(f"directions must have shape (3,) or {origins.shape}, got {directions.shape}")
        config = self.config
        samples = np.arange(config.start, config.max_distance, config.step)
        out = np.full(len(origins), np.inf)
        active = np.arange(len(origins) if len(self.cameras) >= config.min_views else 0)  # else none can count
        for first in range(0, len(samples), block):
            near = samples[first:first + block]
            for begin in range(0, len(active), chunk):
                rays = active[begin:begin + chunk]
                step = directions if directions.ndim == 1 else directions[rays][:, None, :]
                points = (origins[rays][:, None, :] + near[None, :, None] * step).reshape(-1, 3)
                good = self._good(points).reshape(-1, len(near))
                found = good.any(axis=1)
                out[rays[found]] = near[np.argmax(good[found], axis=1)]
            active = active[np.isinf(out[active])]
            if not len(active):
                break
        return out

    @functools.cached_property
    def _lookup(self) -> tuple[tuple[np.ndarray, np.ndarray], ...]:
        """Per view, flat (H*W,) int8 state (1 occupied, 2 free, 0 neither) and float64 squared
        distance under which a point is in front of the proxy surface (-1 where the state is 0)."""
        keep = 1.0 - self.config.depth_margin
        out = []
        for depth, occupied, free in zip(self.depth, self.occupied, self.free, strict=True):
            state = np.where(occupied, 1, np.where(free, 2, 0)).astype(np.int8).ravel()
            out.append((state, np.where(state > 0, (keep * depth.ravel()) ** 2, -1.0)))
        return tuple(out)

    def _good(self, points: np.ndarray) -> np.ndarray:
        """Whether each point (M, 3) is seen occupied by at least ``min_views`` views and by at
        least ``share`` of those that see it occupied or free, (M,) bool.

        The views are counted one after the other; a point stops being projected once even the
        remaining views all seeing it occupied could not make it count (exact: 3-4x fewer
        projections on street_s0, where most samples are seen free early).
        """
        config = self.config
        n_occupied = np.zeros(len(points), np.int16)
        n_free = np.zeros(len(points), np.int16)
        alive = np.arange(len(points))
        for done, (camera, lookup) in enumerate(zip(self.cameras, self._lookup, strict=True), 1):
            front, seen = _seen(camera, lookup, points[alive])
            n_occupied[alive[front]] += seen == 1
            n_free[alive[front]] += seen == 2
            best = n_occupied[alive] + (len(self.cameras) - done)  # every view still to come seeing it occupied
            alive = alive[(best >= config.min_views) & (best >= config.share * (best + n_free[alive]))]
            if not len(alive):
                break
        good = np.zeros(len(points), dtype=bool)
        good[alive] = True
        return good

    def clear(self, origins: np.ndarray, direction: np.ndarray, *, distance: float = 8.0, share: float = 0.5,
              step: float = 0.2, chunk: int = 20000) -> np.ndarray:
        """Whether the views see each ray's path free: no occluder the proxy lacks stands on it.

        A ray is clear when no sample of it is seen occupied (the rule of :meth:`first_occupied`, on
        samples every ``step`` metres from ``config.start`` to ``distance``, then every
        ``config.step`` to ``config.max_distance``) and at least ``share`` of its samples up to
        ``distance`` are seen free by two views or more and occupied by none: positive evidence, so
        that a ray no view sees is not clear.

        Parameters
        ----------
        origins : (N, 3) array_like
            World-frame ray origins, metres.
        direction : (3,) array_like
            Unit direction of every ray, world frame.
        distance, step : float, optional
            Metres: the stretch of the ray the views must see free, and the spacing of its samples.
        share : float, optional
            In [0, 1].
        chunk : int, optional
            Rays per batch (memory); the result does not depend on it.

        Returns
        -------
        (N,) bool
        """
        origins = as_array(origins, "origins", shape=(None, 3), dtype=np.float64)
        direction = np.asarray(direction, dtype=np.float64)
        if direction.shape != (3,):
            raise ValueError(f"direction must have shape (3,), got {direction.shape}")
        if not is_real(share) or not 0.0 <= share <= 1.0:
            raise ValueError(f"share must be a number in [0, 1], got {share!r}")
        config = self.config
        samples = np.arange(config.start, distance, step)
        if not len(samples):
            raise ValueError(f"no sample between start ({config.start}) and distance ({distance})")
        out = np.zeros(len(origins), dtype=bool)
        for begin in range(0, len(origins), chunk):
            rays = np.arange(begin, min(begin + chunk, len(origins)))
            points = (origins[rays][:, None, :] + samples[None, :, None] * direction).reshape(-1, 3)
            n_occupied = np.zeros(len(points), np.int16)
            n_free = np.zeros(len(points), np.int16)
            for camera, lookup in zip(self.cameras, self._lookup, strict=True):
                front, seen = _seen(camera, lookup, points)
                n_occupied[front] += seen == 1
                n_free[front] += seen == 2
            occupied = (n_occupied >= config.min_views) & (n_occupied >= config.share * (n_occupied + n_free))
            free = (n_free >= 2) & (n_occupied == 0)
            shape = (len(rays), len(samples))
            out[rays] = ~occupied.reshape(shape).any(axis=1) & (free.reshape(shape).mean(axis=1) >= share)
        if distance < config.max_distance and out.any():  # the rest of the ray: no sample seen occupied there
            beyond = PhotoOccupancy(self.cameras, self.depth, self.occupied, self.free,
                                    replace(config, start=distance))
            out[out] = np.isinf(beyond.first_occupied(origins[out], direction))
        return out

    def sun_ray_distance(self, index: int, receivers: np.ndarray, *, asked: np.ndarray | None = None
                         ) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
        """The ``occluder_distance`` of :func:`~mvintrinsic.caster.build_caster` for view ``index``.

        Only the pixels that see a proxy surface another view confirms (``free`` and on the
        proxy) take a distance: a pixel that sees the lost occluder itself casts no shadow ray.

        Parameters
        ----------
        index : int
            The view's position in :attr:`cameras`.
        receivers : (H, W, 3) array_like
            The view's receiver points, world frame, metres.
        asked : (H, W) bool ndarray, optional
            Every call ors its ``miss`` into it (the shadow pixels whose sun ray missed the proxy:
            the paper's cluster rule needs them).

        Returns
        -------
        callable
            ``f(miss, sun) -> (H, W) float64``: for those pixels of ``miss`` ((H, W) bool),
            :meth:`first_occupied` along ``sun`` from their receiver; ``inf`` elsewhere.
        """
        receivers = np.asarray(receivers, dtype=np.float64)
        confirmed = self.free[index] & np.isfinite(self.depth[index])

        def distance(miss: np.ndarray, sun: np.ndarray) -> np.ndarray:
            miss = np.asarray(miss, dtype=bool)
            if asked is not None:
                asked[miss] = True
            out = np.full(miss.shape, np.inf)
            use = miss & confirmed
            out[use] = self.first_occupied(receivers[use], sun)
            return out

        return distance


def _seen(camera: Camera, lookup: tuple[np.ndarray, np.ndarray], points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The points (M, 3) in front of ``camera`` and inside its image, and the state each is seen in there
    (:attr:`PhotoOccupancy._lookup`: 1 occupied, 2 free, 0 neither or behind the proxy surface)."""
    state, limit = lookup
    local = camera.world_to_camera(points)  # its norm: the distance to the camera centre
    front = np.flatnonzero(local[:, 2] > 0)
    near = local if len(front) == len(local) else local[front]
    if camera._pinhole:  # Camera.normalized_to_pixels on 1D columns: the same numbers, without the (N, 2) arrays
        (fx, fy), (cx, cy) = camera.focal, camera.principal_point
        u = near[:, 0] / near[:, 2]
        u *= fx
        u += cx
        v = near[:, 1] / near[:, 2]
        v *= fy
        v += cy
    else:
        u, v = camera.normalized_to_pixels(near[:, :2] / near[:, 2:]).T
    inside = (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)  # Camera.in_image
    distance2 = np.einsum("ij,ij->i", near, near)[inside]
    front = front[inside]
    flat = v[inside].astype(np.int64) * camera.width + u[inside].astype(np.int64)  # >= 0 inside: truncation floors
    return front, np.where(distance2 < limit[flat], state[flat], 0)


def shared_receivers(views: Sequence[View], receivers: Mapping[str, np.ndarray], depth: Mapping[str, np.ndarray], *,
                     depth_tolerance: float = 0.02) -> dict[str, list[tuple[int, np.ndarray, np.ndarray]]]:
    """Per view, the other views' pixels that see its pixels' receiver points.

    A pixel whose ray hits the proxy has its receiver point projected into every other view;
    where that view sees it (:func:`~mvintrinsic.correspondence.seen_pixels`: in the image, in
    front of the camera, on a valid pixel whose own ray hits the proxy at a depth within
    ``depth_tolerance`` of the point's distance), that view's pixel (nearest) sees the same proxy
    point.

    Parameters
    ----------
    views : sequence of View
    receivers : mapping of str to (H, W, 3) array_like
        Per view stem, the pixels' receiver points, world frame, metres.
    depth : mapping of str to (H, W) array_like
        Per view stem, the distance along each unit pixel ray to the proxy, metres; ``inf`` where the ray misses.
    depth_tolerance : float, optional
        Relative.

    Returns
    -------
    dict of str to list of (int, (K,) int64, (K,) int64)
        Per view stem, per other view: its index in ``views``, the flat indices of the view's
        pixels (ascending) and those of the other view's pixels that see them.
    """
    links = _links_task(views, receivers, depth, depth_tolerance)
    return {view.stem: links(view) for view in views}


def _links_task(views: Sequence[View], receivers: Mapping[str, np.ndarray], depth: Mapping[str, np.ndarray],
                depth_tolerance: float) -> Callable[[View], list[tuple[int, np.ndarray, np.ndarray]]]:
    """:func:`shared_receivers` as a task: ``task(view)`` is one view's list, and the views' tasks are independent
    (they may run at once)."""
    depths = {v.stem: np.asarray(depth[v.stem], dtype=np.float64).reshape(v.shape) for v in views}
    usable = {v.stem: v.mask & np.isfinite(depths[v.stem]) for v in views}

    def links(view: View) -> list[tuple[int, np.ndarray, np.ndarray]]:
        own = np.flatnonzero(np.isfinite(depths[view.stem]))
        points = np.asarray(receivers[view.stem], dtype=np.float64).reshape(-1, 3)[own]
        out = []
        for k, other in enumerate(views):
            if other.stem != view.stem:
                seen, flat = seen_pixels(other.camera, depths[other.stem], usable[other.stem], points, depth_tolerance)
                out.append((k, own[seen], flat[seen]))
        return out

    return links


def nearest_colour(views: Sequence[View], gains: Mapping[str, np.ndarray] | None,
                   shared: Mapping[str, list[tuple[int, np.ndarray, np.ndarray]]]) -> dict[str, np.ndarray]:
    """Per view, the smallest distance from each pixel's colour to what another view sees at its
    receiver point (``shared``, :func:`shared_receivers`), (H, W) float32; ``inf`` where no other
    view sees it. The distance is the median over the channels of ``|log(I + 1e-3) - log(I_other +
    1e-3)|``, every image divided by its exposure gain (``gains``, the decomposition's
    ``lighting.gain``; None: images already in common units)."""
    def scaled(view: View) -> np.ndarray:
        image = np.asarray(view.image, np.float32)
        return image if gains is None else image / np.asarray(gains[view.stem], np.float32)

    logs = {v.stem: np.log(np.maximum(scaled(v), 0.0) + np.float32(1e-3)).reshape(-1, 3) for v in views}
    out = {}
    for view in views:
        own_logs = logs[view.stem]
        nearest = np.full(len(own_logs), np.inf, dtype=np.float32)
        for k, own, theirs in shared[view.stem]:  # a pixel appears at most once per other view
            distance = _median3(np.abs(own_logs[own] - logs[views[k].stem][theirs]))
            nearest[own] = np.minimum(nearest[own], distance)
        out[view.stem] = nearest.reshape(view.shape)
    return out


def _median3(values: np.ndarray) -> np.ndarray:
    """The median of each row of ``values`` (N, 3): ``np.median(values, axis=-1)``'s numbers (the middle value
    itself; NaN where a value is), by minima and maxima instead of a partition (27 -> 4 ms for 600k rows)."""
    a, b, c = values[:, 0], values[:, 1], values[:, 2]
    return np.maximum(np.minimum(a, b), np.minimum(np.maximum(a, b), c))


def unexplained_pixels(known: np.ndarray, hit: np.ndarray, nearest_colour: np.ndarray,
                       consistency: float) -> np.ndarray:
    """The pixels the proxy does not explain, (H, W) bool (:attr:`RelightConfig.consistency
    <mvintrinsic.caster.RelightConfig>`): with an estimate (``known``) and a camera ray that misses
    the proxy (``~hit``), or a colour at least ``consistency`` from what each other view sees at
    the receiver point (``nearest_colour`` finite and not below it; ``inf``: no other view sees the
    point, no evidence)."""
    inconsistent = np.isfinite(nearest_colour) & ~(nearest_colour < consistency)
    return known & (~hit | inconsistent)


def silhouette_band(hit: np.ndarray, width: int) -> np.ndarray:
    """The pixels within ``width`` pixels (chessboard distance) of both a pixel whose camera ray hits the
    proxy and one whose ray misses it, (H, W) bool: both sides of the proxy's silhouette in the view.

    Parameters
    ----------
    hit : (H, W) bool array_like
        Whether each pixel's camera ray hits the proxy.
    width : int
        >= 0; 0 gives no pixel.

    Raises
    ------
    ValueError
        If ``width`` is not an integer >= 0 or ``hit`` is not 2-D (the message names it).
    """
    width = as_count(width, "width", least=0)
    hit = as_array(hit, "hit", shape=(None, None), dtype=bool)
    if width == 0:
        return np.zeros(hit.shape, dtype=bool)
    structure = np.ones((2 * width + 1, 2 * width + 1), dtype=bool)
    return ndimage.binary_dilation(hit, structure) & ndimage.binary_dilation(~hit, structure)


def photo_occupancy(views: Sequence[View], depth: Mapping[str, np.ndarray], known: Mapping[str, np.ndarray],
                    nearest_colour: Mapping[str, np.ndarray], *, config: OccupancyConfig | None = None
                    ) -> PhotoOccupancy:
    """The occupancy evidence of every view (module docstring).

    Parameters
    ----------
    views : sequence of View
        The views (their cameras and ``mask`` of valid pixels).
    depth : mapping of str to (H, W) array_like
        Per view stem, the distance to the proxy along each unit pixel ray, metres; ``inf`` (or
        NaN) where the ray misses it.
    known : mapping of str to (H, W) bool array_like
        Per view stem, the pixels with an estimate (the decomposition's; the sky has none).
    nearest_colour : mapping of str to (H, W) array_like
        Per view stem, the smallest log-radiance distance between the pixel's colour and what
        another view sees at its receiver point; ``inf`` where no other view sees it (as the
        relighter's ``consistency`` test measures it).
    config : OccupancyConfig, optional

    Returns
    -------
    PhotoOccupancy

    Raises
    ------
    ValueError
        If a view's arrays are missing or have the wrong shape (the message names them).
    """
    config = OccupancyConfig() if config is None else config
    if not isinstance(config, OccupancyConfig):
        raise TypeError(f"config must be an OccupancyConfig, got {type(config).__name__}")
    depths, occupied, free = [], [], []
    for view in views:
        shape, stem = view.shape, view.stem
        for name, mapping in (("depth", depth), ("known", known), ("nearest_colour", nearest_colour)):
            if stem not in mapping:
                raise ValueError(f"{name}: no array for view {stem!r}")
        d = as_array(depth[stem], f"depth[{stem!r}]", shape=shape, dtype=np.float64, finite=False)
        hit = np.isfinite(d)
        k = as_array(known[stem], f"known[{stem!r}]", shape=shape, dtype=bool)
        c = as_array(nearest_colour[stem], f"nearest_colour[{stem!r}]", shape=shape, dtype=np.float64, finite=False)
        depths.append(np.where(hit, d, np.inf))
        unexplained = unexplained_pixels(k, hit, c, config.consistency)
        if config.silhouette:  # mixed pixels at the proxy's silhouette are no evidence (OccupancyConfig.silhouette)
            unexplained &= ~silhouette_band(hit, config.silhouette)
        occupied.append(unexplained)
        free.append((view.mask & ~k & ~hit) | (hit & (c < config.consistency)))  # sky; a surface another view confirms
    return PhotoOccupancy(tuple(v.camera for v in views), tuple(depths), tuple(occupied), tuple(free), config)


def clear_sun_rays(views: Sequence[View], quantities: Mapping[str, PixelQuantities], sun_direction: np.ndarray, *,
                   config: ClearRaysConfig | None = None) -> dict[str, np.ndarray]:
    """Per view, the pixels whose sun ray the photographs see free (:class:`ClearRaysConfig`).

    From Step 1's quantities alone: each pixel whose camera ray hits the proxy has its receiver point
    (:func:`~mvintrinsic.correspondence.surface_points`) and the colour the other views see there
    (:func:`shared_receivers`, :func:`nearest_colour`; the images in common units); these give the occupancy
    evidence (:func:`photo_occupancy`). A pixel is clear when the proxy says lit (``~v >= 1/2``) and its sun
    ray, from the receiver point, is :meth:`PhotoOccupancy.clear`.

    Parameters
    ----------
    views : sequence of View
    quantities : mapping of str to PixelQuantities
        Per view stem (:func:`mvintrinsic.pixels.pixel_quantities`).
    sun_direction : (3,) array_like
        Unit vector toward the sun, world frame.
    config : ClearRaysConfig, optional

    Returns
    -------
    dict of str to (H, W) bool
        In the order of ``views``; all False when fewer views than ``config.occupancy.min_views`` are given
        (no sample could be seen occupied, so no evidence either way).

    Raises
    ------
    ValueError, TypeError
        Naming the argument: a view without quantities, a sun direction that is not a unit vector, a config
        of another type.
    """
    config = ClearRaysConfig() if config is None else config
    if not isinstance(config, ClearRaysConfig):
        raise TypeError(f"config must be a ClearRaysConfig, got {type(config).__name__}")
    sun = np.asarray(sun_direction, dtype=np.float64)
    if sun.shape != (3,) or not np.all(np.isfinite(sun)) or abs(np.linalg.norm(sun) - 1.0) > 1e-6:
        raise ValueError(f"sun_direction must be a finite unit (3,) vector, got {sun_direction!r}")
    missing = [v.stem for v in views if v.stem not in quantities]
    if missing:
        raise ValueError(f"quantities: no PixelQuantities for view(s) {missing}")
    out = {v.stem: np.zeros(v.shape, dtype=bool) for v in views}
    if len(views) < config.occupancy.min_views:
        return out
    depth = {v.stem: np.asarray(quantities[v.stem].depth, dtype=np.float64) for v in views}
    receivers = {v.stem: surface_points(v, quantities[v.stem]) for v in views}
    nearest = nearest_colour(views, None, shared_receivers(views, receivers, depth))
    occupancy = photo_occupancy(views, depth, {v.stem: quantities[v.stem].valid for v in views}, nearest,
                                config=config.occupancy)
    for view in views:
        q = quantities[view.stem]
        k = max(config.stride, round(config.stride * max(view.shape) / 480))
        eligible = q.valid & np.isfinite(depth[view.stem]) & (np.asarray(q.visibility) >= 0.5)
        grid = np.zeros(view.shape, dtype=bool)
        grid[::k, ::k] = eligible[::k, ::k]
        cleared = np.zeros(view.shape, dtype=bool)
        cleared[grid] = occupancy.clear(receivers[view.stem][grid], sun, distance=config.distance,
                                        share=config.share, step=config.step)
        blocks = np.repeat(np.repeat(cleared[::k, ::k], k, axis=0), k, axis=1)[:view.shape[0], :view.shape[1]]
        out[view.stem] = blocks & eligible
    return out


def blend_rescued(moved: Mapping[str, np.ndarray], paper: Mapping[str, np.ndarray], rescued: Mapping[str, np.ndarray],
                  belief: float) -> dict[str, np.ndarray]:
    """The expected relit image at the rescued pixels (:attr:`OccupancyConfig.belief`).

    Parameters
    ----------
    moved : mapping of str to (H, W, 3) array_like
        Per view stem, the image relit with the distances of :func:`photo_occupancy`.
    paper : mapping of str to (N, 3) array_like
        Per stem of ``rescued``, the paper's image at its rescued pixels, in row-major order (the
        cluster dropped; the same sun).
    rescued : mapping of str to (H, W) bool array_like
        Per view stem (those without are not mixed), the pixels of the clusters the paper's rule
        drops and the distances keep (N of them).
    belief : float
        In [0, 1].

    Returns
    -------
    dict of str to (H, W, 3) float32
        ``belief * moved + (1 - belief) * paper`` at the rescued pixels, ``moved`` elsewhere.
    """
    if not is_real(belief) or not 0.0 <= belief <= 1.0:
        raise ValueError(f"belief must be a number in [0, 1], got {belief!r}")
    out = {}
    for stem, image in moved.items():
        out[stem] = image = np.array(image, dtype=np.float32)
        if stem in rescued:
            mask = as_array(rescued[stem], f"rescued[{stem!r}]", shape=image.shape[:2], dtype=bool)
            other = as_array(paper[stem], f"paper[{stem!r}]", shape=(int(mask.sum()), 3), dtype=np.float32)
            _blend_into(image, np.flatnonzero(mask), other, belief)
    return out


def _blend_into(image: np.ndarray, pixels: np.ndarray, paper: np.ndarray, belief: float) -> None:
    """:func:`blend_rescued` of one view in place: (H, W, 3) float32 C-contiguous ``image``, (N,) flat indices of
    the rescued ``pixels`` in row-major order, (N, 3) ``paper``."""
    flat = image.reshape(-1, 3)  # a view: the blend writes into the image
    mixed = np.take(flat, pixels, axis=0)
    mixed *= np.float32(belief)
    mixed += np.float32(1.0 - belief) * paper
    flat[pixels] = mixed
