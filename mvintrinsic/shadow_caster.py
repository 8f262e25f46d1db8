"""Receivers and new-sun shadows (paper Sec. 8): the caster's visibility for any sun.

Every pixel's receiver point and normal on the proxy, and, with the caster of :mod:`.caster` (one
per view, or merged) and the proxy's completion, the sun visibility of every pixel for a new sun
[1]_; :mod:`.relight` relights the views with it.

**Receiver** (:func:`receiver_depth`, :func:`receiver_points`). Every pixel gets the distance along
its camera ray to the proxy; pixels whose ray misses take the value of the nearest pixel that hits.


**Receiver by ray casting** (a deviation). The paper gives each pixel "the depth value of the closest projected
  3D point"; here the pixel ray is intersected with the proxy through the project's
  :class:`~mvintrinsic.raytrace.Tracer` (triangles of a mesh, surfels of a point cloud), which is
  the same depth without holes between projected points, and misses are filled as the paper fills
  caster distances (nearest valid pixel, ``scipy.ndimage.distance_transform_edt``).

**Moving shadows** (:class:`ShadowCaster`). For a new sun, a ray from every receiver point toward
it is tested against the caster (Embree, via open3d, the structure built once per caster). Where
the caster has no coverage the proxy's shadow completes it, and a Gaussian blur of ``blur``
pixels softens the result and fills the cracks between disconnected triangles. The casters of
several views can be merged into one (:func:`merge_casters`) that shades every view. With
``method="multiview"`` (the default) the lit pixels of every view vote against every caster and
against the proxy's completion (:mod:`.caster`, "Votes of every view").

Deviations from the paper, with their reasons
---------------------------------------------
* **Proxy completion, "no coverage".** The paper completes "the missing shadow in these areas using
  the shadow of the proxy geometry" without defining the areas. Here the caster records which
  proxy primitives (triangles; surfel points of a point cloud) the rays of its kept pixels hit:
  the occluders whose shadows the image shows and the caster stands for. For a new sun, a pixel
  whose shadow ray's first proxy hit is a primitive *not* in that set is occluded by geometry whose
  shadow the image never showed (it fell outside the frame, or on a part of the scene no view
  covers), and takes the proxy's shadow; elsewhere the caster decides. A plain OR of the two
  shadows would bring back the inaccurate proxy shadow boundaries the caster exists to replace.
* **Attached shadow.** When normals are given, a receiver point facing away from the new sun
  (``n . d <= 0``) has visibility 0, as the proxy visibility of Step 1
  (:func:`mvintrinsic.raytrace.sun_visibility`). The :class:`Relighter` gives none: the cosine of
  ``S_sun'`` shades the points that face away, and the proxy completion their cast shadow.

Speed (beyond the paper)
------------------------
Building costs one pass per view; every new sun then costs, per view, the shadow rays and a few
array passes. At 1000x750 (courtyard_1000, 6 views, a 484k-triangle proxy, 2 cores) a new sun
took 0.30 s per view with one caster ray and one proxy ray per pixel; now 0.086 s:

* **Rays only where the visibility varies** (:attr:`RelightConfig.ray_stride`): both queries run
  on a grid of every second pixel, then on every pixel of the grid cells whose corners disagree
  and of their neighbours (0.39 of the pixels at 1000x750). Against every pixel
  (``bench_relight.py --stride``, ``benchmarks/results/relight_stride.json``, the defaults of 2026-12-07,
  the true layers, five 480x360 scenes, 22 scene-suns), the sharp shadow state of 0.014-0.12% of
  the pixels changes, isolated pixels the blur mostly absorbs, and the relit PSNR by -0.006 to
  +0.025 dB (mean +0.007); stride 3 changed 0.03-0.16% and -0.011 to +0.047 dB (below stride 2 at
  10 of the 22) for a visibility 11% faster (24 against 27 ms per view; 36 for every pixel), so 2
  is the default (at 1000x750 in the run of 2026-11-24: 0.04-0.05% changed). The exact meshes' own shadows,
  with their one-pixel fence pickets and leaves, lose more to stride 2 (-0.03 to -0.18 dB on
  courtyard_s1): a caster that fine wants ``ray_stride=1``. Without the neighbour cells, 0.16%
  of the blurred state changed at 1000x750 and 0.01-0.28% at 480x360 (-0.05 to +0.01 dB).
* **The proxy is asked only where the caster let the ray through**, by a lean first-hit query
  (:meth:`~mvintrinsic.raytrace.Tracer.first_primitive`: no normals, points or barycentrics),
  and whether a hit completes the shadow is one lookup per primitive built once per view
  (:meth:`ShadowCaster.completion_blocked`), not two set-membership tests per sun.
* **The shading's sun-independent terms are computed once**, in float32: ``S_sun'`` is then
  ``max(base + L_sun max(0, n.d'), floor)`` with ``base`` and ``floor`` precomputed (-inf floor
  in full shadow), and the fill of the pixels without an estimate is an addition.

* **Two views at once** (:class:`~mvintrinsic.relight.Relighter`'s ``threads``): Embree casts
  each view's rays on both cores, but the blur, fusion, shading and composition are NumPy on
  one; two views at a time, the images identical to the bit. With the blur in OpenCV (6x
  faster than SciPy's, the same kernel, within 3e-7), a new sun at 1000x750 went from
  0.088-0.106 to 0.052-0.075 s per view (three scenes resampled, ``docs/relight.md``, "Speed").
* **One ray array per query, handed to Embree without a copy**: the origins gathered and offset in
  float64 once, cast to float32 into one (N, 6) array whose rows (and the subsets the caster lets
  through) go to every structure by ``open3d.core.Tensor.from_numpy``; the grid's states spread
  to the pixels by ``np.repeat`` and the neighbour cells by ``cv2.dilate``. The same rays and
  states; 14% less time per new sun on one core (street_s0 at 1000x750).
* **Long inner loops** (fourth session of 2026-12-07): NumPy runs an ``(N, 3)`` broadcast as N inner loops of 3
  elements, so the rays are written a coordinate at a time (:func:`_offset_rays`), the subsets of rays gathered
  by ``np.take`` (4x faster than ``rays[index]`` on 2-D arrays), the proxy's hits read as Embree gives them
  with a miss on the lookup table's last entry (:meth:`~mvintrinsic.raytrace.Tracer._completion_hits`), the
  mixture of hypotheses one table lookup, and the grid written by slices (:func:`_put_grid`). The same rays,
  states and images to the bit; open3d holds the GIL while Embree casts, so this NumPy time was not hidden by the
  second thread: a new sun 9-10% faster (three scenes at 1000x750, renders alternating with the code before in
  one process; ``docs/relight.md``, "Speed").

Ordering the rays in 8x8 or 16x16 tiles instead of rows changed the Embree time by under 6%:
not done.

References
----------
.. [1] S. Duchêne, C. Riant, G. Chaurasia, J. Lopez-Moreno, P.-Y. Laffont, S. Popov, A. Bousseau
   and G. Drettakis, "Multi-View Intrinsic Images of Outdoors Scenes with an Application to
   Relighting", ACM Transactions on Graphics 34(5), 2015, Sec. 8.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any, NamedTuple

import cv2
import numpy as np
from scipy import sparse

from ._validation import as_array, as_unit_vector, config_or_default, describe, is_real
from .camera import Camera
from .caster import (
    Caster,
    RelightConfig,
    _check_camera,
    _check_rays,
    _check_sun,
    _check_tracer,
    _image_array,
    capture_first_hits,
)
from .envmap import horizontal_frame
from .photo_occupancy import _links_task, nearest_colour, unexplained_pixels
from .pixels import nearest_fill
from .planes import PlaneConfig
from .raytrace import DEFAULT_BATCH, Tracer, _ray_array, triangle_scene, vertex_normals
from .results import Decomposition
from .scene import Scene, Sun, View

__all__ = ["AUTO_COMPLETION_DISTANCE", "SELF_SHADING_SHARE", "ShadowCaster", "choose_completion_distance", "proxy_self_shading", "as_sun_direction", "receiver_depth", "receiver_normals", "receiver_points"]


#: The completion distance ``RelightConfig(completion_distance="auto")`` gives a proxy that shades
#: itself, metres (the former fixed default; 0.3, 0.6 and 1.0 measured on MVS-like proxies).
AUTO_COMPLETION_DISTANCE = 0.6
#: Share of the lit pixels' capture-sun rays hitting the proxy within :data:`AUTO_COMPLETION_DISTANCE`
#: above which the proxy is taken to shade itself. Measured on MVS-like proxies: 0.87% (the embedded
#: demo, the pipeline's labels) to 30% (dev_courtyard), 2.6-21% on the five 480x360 scenes and
#: courtyard_1000 (true labels); 0.04% on the exact meshes (label noise at the shadow edges). The
#: threshold sits between them (their geometric middle).
SELF_SHADING_SHARE = 0.002


def proxy_self_shading(tracer: Tracer, lit_points: Sequence[np.ndarray], sun_direction: np.ndarray, *,
                       distance: float, config: RelightConfig | None = None, batch: int = DEFAULT_BATCH) -> float:
    """Share of lit receiver points whose ray toward the (capture) sun hits the proxy within ``distance`` metres.

    The image says these points are lit, so such a hit is the proxy shading itself: reconstruction
    noise, a receiver a few centimetres inside the surface. Rays start ``config.ray_offset`` toward
    the sun, as every shadow ray. Returns 0 without lit points.
    """
    t, _ = capture_first_hits(tracer, lit_points, sun_direction, config=config, batch=batch)
    return _share_within(t, distance)


def _share_within(t: np.ndarray, distance: float) -> float:
    """Share of the first-hit distances ``t`` below ``distance``; 0 without any."""
    return float(np.count_nonzero(t < distance) / len(t)) if len(t) else 0.0


def choose_completion_distance(config: RelightConfig, tracer: Tracer, lit_points: Sequence[np.ndarray],
                               sun_direction: np.ndarray, *, batch: int = DEFAULT_BATCH) -> tuple[float, float | None]:
    """The completion distance to use and, for ``"auto"``, the self-shading share it was chosen from.

    A number in ``config.completion_distance`` is returned as it is (share None). With ``"auto"``:
    :data:`AUTO_COMPLETION_DISTANCE` when :func:`proxy_self_shading` at that distance is at least
    :data:`SELF_SHADING_SHARE`, else 0. Measured with the true layers at +-15, +-30 degrees of
    azimuth and +10 of elevation (``docs/relight.md``): on the exact meshes of five scenes 0 instead
    of 0.6 raises row (d) by 0.35-0.62 dB per scene on average (20 of 25 scene-suns, at most 0.15 dB
    lower on the others); the MVS-like proxies all shade themselves and keep 0.6.
    """
    if config.completion_distance != "auto":
        return float(config.completion_distance), None
    t, _ = capture_first_hits(tracer, lit_points, sun_direction, config=config, batch=batch)
    return _completion_distance(config, t)


def _completion_distance(config: RelightConfig, t: np.ndarray) -> tuple[float, float | None]:
    """:func:`choose_completion_distance` from the lit points' first-hit distances ``t`` (:func:`capture_first_hits`)."""
    if config.completion_distance != "auto":
        return float(config.completion_distance), None
    share = _share_within(t, AUTO_COMPLETION_DISTANCE)
    return (AUTO_COMPLETION_DISTANCE if share >= SELF_SHADING_SHARE else 0.0), share


def receiver_depth(camera: Camera, tracer: Tracer) -> tuple[np.ndarray, np.ndarray]:
    """Distance to the proxy along every pixel ray, misses filled from the nearest hit (Sec. 8).

    Parameters
    ----------
    camera : Camera
        The view; rays through the pixel centres (:meth:`Camera.pixel_rays`).
    tracer : Tracer
        Ray caster over the proxy.

    Returns
    -------
    depth : (H, W) float64
        Distance, metres, from the camera centre along the unit pixel ray to the first proxy hit.
        A pixel whose ray misses the proxy takes the distance of the nearest (Euclidean, in
        pixels) pixel that hits.
    hit : (H, W) bool
        Where the pixel's own ray hits the proxy.

    Raises
    ------
    ValueError
        If no pixel ray hits the proxy.
    """
    _, depth, hit = _cast_pixels(_check_camera(camera), _check_tracer(tracer))
    return depth, hit


def _cast_pixels(camera: Camera, tracer: Tracer, batch: int = DEFAULT_BATCH, name: str = "tracer"):
    """The camera rays' hits on the proxy, their distances with misses filled from the nearest hit,
    and where they hit; a ``ValueError`` starting with ``name`` when none does."""
    hits = tracer.intersect(camera.center, camera.pixel_rays(), batch=batch)
    t = hits.t.reshape(camera.shape)
    hit = np.isfinite(t)
    if not hit.any():
        raise ValueError(f"{name}: no pixel ray of camera {camera!r} hits the proxy")
    return hits, nearest_fill(t, hit), hit


def receiver_points(camera: Camera, depth: np.ndarray) -> np.ndarray:
    """World points of the pixels at the given ray distances.

    Parameters
    ----------
    camera : Camera
    depth : (H, W) array_like
        Finite distances, metres, along the unit pixel rays (:func:`receiver_depth`).

    Returns
    -------
    (H, W, 3) float64
        ``camera.center + depth * ray``, world frame, metres.
    """
    camera = _check_camera(camera)
    depth = _image_array(depth, "depth", camera.shape, np.float64)
    rays = camera.pixel_rays().reshape(*camera.shape, 3)
    return camera.center + depth[..., None] * rays


# ---------------------------------------------------------------------------------------------
# shadow pixels
# ---------------------------------------------------------------------------------------------


def _strided(shaded: Callable[[np.ndarray], np.ndarray], shape: tuple[int, int], stride: int) -> np.ndarray:
    """A binary image of ``shaded(flat pixel indices)``, queried only where it varies; (H*W,) bool.

    ``shaded`` is asked for the pixels on a grid of step ``stride`` (the last row and column
    always included), then for every pixel of the grid cells whose four corners disagree and of
    their eight neighbour cells (an edge may bend through a cell whose corners agree); every
    other pixel takes the state of its cell's corners (:attr:`RelightConfig.ray_stride`).
    """
    h, w = shape
    if stride <= 1 or h < 2 or w < 2:
        return shaded(np.arange(h * w))
    ys = np.unique(np.r_[np.arange(0, h, stride), h - 1])
    xs = np.unique(np.r_[np.arange(0, w, stride), w - 1])
    corners = shaded((ys[:, None] * w + xs[None, :]).ravel()).reshape(len(ys), len(xs))
    # Cell (j, i) spans rows ys[j]..ys[j+1] and columns xs[i]..xs[i+1]; every pixel reads the
    # cell below and right of its nearest grid row and column above and left: the cells' rows and
    # columns repeated, the last cell's to the image's edge.
    mixed = ((corners[:-1, :-1] != corners[1:, :-1]) | (corners[:-1, :-1] != corners[:-1, 1:])
             | (corners[:-1, :-1] != corners[1:, 1:]))
    mixed = cv2.dilate(mixed.view(np.uint8), np.ones((3, 3), np.uint8)).view(bool)  # the 8 neighbour cells
    rows = np.diff(np.r_[ys[:-1], h])
    cols = np.diff(np.r_[xs[:-1], w])
    out = np.repeat(np.repeat(corners[:-1, :-1], rows, axis=0), cols, axis=1)  # the top-left corner's state
    refine = np.repeat(np.repeat(mixed, rows, axis=0), cols, axis=1)
    _put_grid(out, corners, stride)
    _put_grid(refine, False, stride)  # the corners are known
    index = np.flatnonzero(refine)
    out = out.ravel()
    if len(index):
        out[index] = shaded(index)
    return out


def _put_grid(image: np.ndarray, values: np.ndarray | bool, stride: int) -> None:
    """``image[np.ix_(ys, xs)] = values`` for :func:`_strided`'s grid rows ``ys`` and columns ``xs`` (every
    ``stride``-th, then the last if it is not one), by slices: 20x faster than the fancy index at 1000x750."""
    h, w = image.shape
    ny, nx = len(range(0, h, stride)), len(range(0, w, stride))  # the grid without the last row and column
    values = np.broadcast_to(values, (ny + ((h - 1) % stride > 0), nx + ((w - 1) % stride > 0)))
    image[::stride, ::stride] = values[:ny, :nx]
    image[-1, ::stride] = values[-1, :nx]  # the last row and column: the grid's own when they are on it
    image[::stride, -1] = values[:ny, -1]
    image[-1, -1] = values[-1, -1]


def _offset_rays(points: np.ndarray, index: np.ndarray, offset: np.ndarray, sun32: np.ndarray) -> np.ndarray:
    """Embree's rays (N, 6) float32 from ``points[index] + offset`` ((H*W, 3) float64 points, (3,) float64
    offset; the sums in float64, then cast) toward ``sun32`` ((3,) float32).

    One coordinate at a time: an (N, 3) broadcast runs N inner loops of 3 elements, these three of N (the same
    numbers as :func:`~mvintrinsic.raytrace._ray_array` of the offset origins, 1.7x faster at 188k rays).
    """
    origins = np.take(points, index, axis=0)
    rays = np.empty((len(index), 6), np.float32)
    for c in range(3):
        np.add(origins[:, c], offset[c], out=rays[:, c], casting="unsafe")
        rays[:, 3 + c] = sun32[c]
    return rays


class ShadowCaster:
    """Embree structure over a :class:`Caster`, built once and queried for many suns (Sec. 8).

    Parameters
    ----------
    caster : Caster
        The caster of one view or of all views (:func:`merge_casters`).
    """

    def __init__(self, caster: Caster) -> None:
        if not isinstance(caster, Caster):
            raise TypeError(f"caster must be a Caster, got {describe(caster)}")
        self.caster = caster
        self._scene = triangle_scene(caster.vertices, caster.triangles) if len(caster.triangles) else None
        # With uncertain triangles (Caster.uncertain), the certain and the uncertain ones apart: a mixed query asks
        # the first of every ray and the second of the rays the first lets through, no dearer than the union.
        uncertain = caster.uncertain if caster.uncertain is not None and caster.uncertain.any() else None
        self._mixed = uncertain is not None
        self._certain = self._uncertain = None
        if uncertain is not None:
            self._uncertain = triangle_scene(caster.vertices, caster.triangles[uncertain])
            if not uncertain.all():
                self._certain = triangle_scene(caster.vertices, caster.triangles[~uncertain])

    def occluded(self, origins: np.ndarray, sun_direction: np.ndarray, *, batch: int = DEFAULT_BATCH) -> np.ndarray:
        """Whether the caster blocks each ray ``origins + s d``, ``s > 0``; (N,) bool.

        Parameters
        ----------
        origins : (N, 3) array_like
            World-frame ray origins, metres (already offset off the receiver).
        sun_direction : (3,) array_like
            Unit direction toward the sun, world frame.
        """
        return self._occluded(_ray_array(*_check_rays(origins, sun_direction)), batch=batch)

    def hit_distance(self, origins: np.ndarray, sun_direction: np.ndarray, *,
                     batch: int = DEFAULT_BATCH) -> np.ndarray:
        """How far along each ray ``origins + s d`` the caster first blocks it; (N,) float32.

        Metres from the origin, ``inf`` where the caster lets the ray through: the occluder
        distance a penumbra width scales with (``benchmarks/bench_relight.py --softness``).

        Parameters
        ----------
        origins : (N, 3) array_like
            World-frame ray origins, metres (already offset off the receiver).
        sun_direction : (3,) array_like
            Unit direction toward the sun, world frame.
        """
        rays = _ray_array(*_check_rays(origins, sun_direction))
        return self._query(rays, np.inf, np.float32, lambda tensor: self._scene.cast_rays(tensor)["t_hit"], batch)

    def _occluded(self, rays: np.ndarray, *, batch: int) -> np.ndarray:
        """:meth:`occluded` of :func:`_ray_array`'s rays (the per-sun hot path: no copy, no finiteness scan)."""
        return self._query(rays, False, bool, lambda tensor: self._scene.test_occlusions(tensor), batch)

    def _query(self, rays: np.ndarray, empty, dtype, query, batch: int, *, structure=True) -> np.ndarray:
        """``query`` (an Embree call on a ray tensor) over ``rays`` ((N, 6) float32, :func:`_ray_array`) in batches,
        each handed to Embree without a copy; ``empty`` when the structure it asks (``structure``; True: the whole
        caster's) does not exist."""
        import open3d as o3d

        out = np.full(len(rays), empty, dtype=dtype)
        if (self._scene if structure is True else structure) is None:
            return out
        for start in range(0, len(rays), batch):
            sl = slice(start, start + batch)
            out[sl] = query(o3d.core.Tensor.from_numpy(rays[sl])).numpy()
        return out

    def _blocks(self, structure, rays: np.ndarray, batch: int) -> np.ndarray:
        """Occlusion of each ray by the certain or the uncertain triangles' structure (None: none), (N,) bool."""
        return self._query(rays, False, bool, lambda tensor: structure.test_occlusions(tensor), batch,
                           structure=structure)

    def sun_visibility(
        self,
        receiver_points: np.ndarray,
        normals: np.ndarray | None,
        sun_direction: np.ndarray,
        *,
        proxy_tracer: Tracer | None = None,
        excluded: np.ndarray | None = None,
        min_distance: float = 0.0,
        up: np.ndarray = (0.0, 0.0, 1.0),
        config: RelightConfig | None = None,
        batch: int = DEFAULT_BATCH,
        belief: float = 1.0,
    ) -> np.ndarray:
        """The new shadow layer: sun visibility of every pixel for a new sun (paper Sec. 8).

        A ray from each receiver point (offset ``config.ray_offset`` toward the sun) is tested
        against the caster; with ``proxy_tracer``, a pixel whose first proxy hit is a primitive
        the caster does not stand for (:attr:`Caster.proxy_primitives`) is in the proxy's shadow
        ("We complete the missing shadow in these areas using the shadow of the proxy
        geometry"); with ``normals``, points facing away from the sun are in attached shadow.
        The binary visibility is then blurred with a Gaussian of ``config.blur`` pixels.

        Parameters
        ----------
        receiver_points : (H, W, 3) array_like
            Finite receiver points, world frame, metres (:func:`receiver_points`).
        normals : (H, W, 3) array_like or None
            Unit surface normals, world frame; NaN rows (no normal) skip the attached-shadow test.
            ``None``: no attached-shadow test.
        sun_direction : (3,) array_like
            Direction toward the new sun, world frame (normalised here); above the horizon.
        proxy_tracer : Tracer, optional
            Ray caster over the proxy the caster was built against, for the completion.
        excluded : (K,) int array_like, optional
            Further proxy primitives that complete no shadow
            (:func:`contradicted_primitives`).
        min_distance : float, optional
            Proxy hits nearer than this many metres along the sun ray complete no shadow
            (:attr:`RelightConfig.completion_distance`); >= 0.
        up : (3,) array_like, optional
            World up vector.
        config : RelightConfig, optional
            ``ray_offset`` and ``blur`` are used.
        batch : int, optional
            Rays per Embree call.
        belief : float, optional
            In [0, 1]. Below 1, every ray's shadow is ``belief`` times its shadow with every triangle plus ``1 -
            belief`` times its shadow without the :attr:`Caster.uncertain` ones, whose proxy primitives
            (:attr:`Caster.uncertain_primitives`) then complete shadows: the expected shadow over the hypotheses
            that their pixels' shadow is real or a mislabelling the paper drops (:mod:`.shadow_clusters`). 1: every
            triangle shadows.

        Returns
        -------
        (H, W) float32
            Sun visibility in [0, 1]: 1 lit, 0 in the new cast (or attached) shadow.

        Raises
        ------
        ValueError
            If the sun is at or below the horizon (the message names ``sun_direction``) or an
            array has the wrong shape.
        """
        config = config_or_default(config, RelightConfig)
        sun = _check_sun(sun_direction, up)
        if not is_real(belief) or not 0.0 <= belief <= 1.0:
            raise ValueError(f"belief must be a number in [0, 1], got {belief!r}")
        points = _image_array(receiver_points, "receiver_points", None, np.float64, trailing=(3,))
        shape = points.shape[:2]
        blocked = None
        if proxy_tracer is not None:
            proxy_tracer = _check_tracer(proxy_tracer, "proxy_tracer")
            if not is_real(min_distance) or not 0.0 <= min_distance < np.inf:
                raise ValueError(f"min_distance must be a finite number >= 0, got {min_distance!r}")
            if excluded is not None:
                excluded = as_array(excluded, "excluded", shape=(None,), dtype=np.int64)
            blocked = self.completion_blocked(proxy_tracer, excluded)
            if self._mixed and belief < 1.0:
                blocked = (blocked, self.completion_blocked(proxy_tracer, excluded, certain=True))
        facing = None
        if normals is not None:
            n = _image_array(normals, "normals", shape, np.float64, trailing=(3,), finite=False).reshape(-1, 3)
            with np.errstate(invalid="ignore"):
                facing = ~((n @ sun) <= 0.0)  # NaN <= 0 is False: no normal, no attached shadow
        return self._visibility(points.reshape(-1, 3), shape, sun, proxy_tracer=proxy_tracer, blocked=blocked,
                                min_distance=float(min_distance) if proxy_tracer is not None else 0.0,
                                facing=facing, config=config, batch=batch, belief=float(belief))

    def completion_blocked(self, proxy_tracer: Tracer, excluded: np.ndarray | None = None, *,
                           certain: bool = False) -> np.ndarray:
        """Per proxy primitive, whether a first hit on it completes no shadow; (P + 1,) bool.

        True for the primitives the caster stands for (:attr:`Caster.proxy_primitives`; with ``certain``, without
        :attr:`Caster.uncertain_primitives`: the paper's hypothesis of ``belief``), for ``excluded`` ones, and in
        the last entry, which a miss (primitive -1) reads. A lookup built once per view and sun-independent, so
        each new sun costs one gather.
        """
        n = proxy_tracer.n_primitives
        blocked = np.zeros(n + 1, dtype=bool)
        stands = self.caster.proxy_primitives
        if certain and self.caster.uncertain_primitives is not None:
            stands = np.setdiff1d(stands, self.caster.uncertain_primitives)
        for ids in (stands, () if excluded is None else excluded):
            ids = np.asarray(ids, dtype=np.int64)
            blocked[ids[(ids >= 0) & (ids < n)]] = True  # other ids name no primitive: no hit reads them
        blocked[-1] = True
        return blocked

    def _visibility(self, points: np.ndarray, shape: tuple[int, int], sun: np.ndarray, *,
                    proxy_tracer: Tracer | None, blocked, min_distance: float,
                    facing: np.ndarray | None, config: RelightConfig, batch: int, belief: float = 1.0,
                    full: np.ndarray | None = None) -> np.ndarray:
        """:meth:`sun_visibility` on checked inputs: ``points`` (H*W, 3) float64, ``sun`` unit; ``blocked``
        :meth:`completion_blocked`'s table, or with ``belief < 1`` its pair (all, certain); ``full`` (H*W,) bool:
        the pixels that take every sheet's shadow rather than the mixture."""
        offset = config.ray_offset * sun
        sun32 = sun.astype(np.float32)
        mixed = self._mixed and belief < 1.0
        blocked_certain = None
        if isinstance(blocked, tuple):
            blocked, blocked_certain = blocked
        if mixed:
            # The expected shadow over the hypotheses, belief * (all sheets) + (1 - belief) * (the paper's), as one
            # lookup of (every sheet's shadow, the paper's) read as 2 bits; with ``full``, a third bit: that pixel
            # takes every sheet's shadow. The same float32 sums as adding the two products.
            b, rest = np.float32(belief), np.float32(1.0 - belief)
            table = np.array([0.0, rest, b, b + rest, 0.0, 0.0, 1.0, 1.0], np.float32)

        def shaded(index: np.ndarray) -> np.ndarray:
            # One ray array for every query: offset toward the sun in float64, then float32 as Embree takes them.
            rays = _offset_rays(points, index, offset, sun32)
            paper = None  # with belief < 1: the shadow without the uncertain triangles (the paper's hypothesis)
            if mixed:
                paper = self._blocks(self._certain, rays, batch)
                through = np.flatnonzero(~paper)  # the uncertain triangles may block these alone
                shade = paper.copy()
                shade[through] = self._blocks(self._uncertain, np.take(rays, through, axis=0), batch)
                asked = through  # the proxy's completion under both hypotheses
            else:
                shade = self._occluded(rays, batch=batch)
                asked = np.flatnonzero(~shade)
            if proxy_tracer is not None:
                # Only rays the caster let through can change: the proxy's rays go to those alone.
                # A proxy hit completes the shadow unless the caster stands for its primitive, a
                # lit pixel contradicted it or it lies nearer than ``min_distance`` (``blocked``).
                t, primitive = proxy_tracer._completion_hits(np.take(rays, asked, axis=0), batch=batch)
                # t counts from the offset origin.
                far = t + np.float32(config.ray_offset) >= min_distance
                if mixed:
                    shade[asked] |= ~blocked[primitive] & far
                    if blocked_certain is not None:
                        paper[asked] = ~blocked_certain[primitive] & far
                else:
                    shade[asked] = ~blocked[primitive] & far
            if mixed:
                code = shade.view(np.uint8) << 1
                code |= paper.view(np.uint8)
                if full is not None:
                    code |= full[index].view(np.uint8) << 2
                shade = table[code]
            if facing is not None:
                shade[~facing[index]] = True
            return shade

        shade = _strided(shaded, shape, config.ray_stride)
        visibility = np.subtract(np.float32(1.0), shade, dtype=np.float32).reshape(shape)
        if config.blur > 0:
            # scipy.ndimage.gaussian_filter(sigma=blur, mode="nearest")'s kernel (radius 4 sigma, edges
            # repeated), 6x faster in OpenCV; the two differ by at most 3e-7.
            radius = int(4.0 * config.blur + 0.5)
            visibility = cv2.GaussianBlur(visibility, (2 * radius + 1, 2 * radius + 1), config.blur,
                                          borderType=cv2.BORDER_REPLICATE)
        return np.clip(visibility, 0.0, 1.0, out=visibility)

    def __repr__(self) -> str:
        return f"ShadowCaster({self.caster!r})"


# ---------------------------------------------------------------------------------------------
# the new sun
# ---------------------------------------------------------------------------------------------


def as_sun_direction(sun: object, *, up: np.ndarray = (0.0, 0.0, 1.0)) -> np.ndarray:
    """The unit direction toward a sun given in any of the forms :class:`Relighter` accepts.

    Parameters
    ----------
    sun : (3,) array_like, Sun or (2,) array_like
        A vector toward the sun, world frame (normalised here); a
        :class:`~mvintrinsic.scene.Sun`; or ``(azimuth_deg, elevation_deg)`` in the scene's
        horizontal frame, degrees: azimuth counter-clockwise seen from above from ``x_h``, the
        horizontal projection of world +X (+Y when ``up`` is along +/-X), elevation above the
        plane normal to ``up`` (:func:`mvintrinsic.sun_position.azimuth_elevation`, whose inverse
        this is; ``docs/conventions.md``).
    up : (3,) array_like, optional
        World up vector.

    Returns
    -------
    (3,) float64
        Unit vector toward the sun, world frame, above the horizon:
        ``d = cos(el) (cos(az) x_h + sin(az) y_h) + sin(el) up`` for the angle form.

    Raises
    ------
    TypeError
        If ``sun`` is none of these forms (the message names ``sun``).
    ValueError
        If it is not finite, a zero vector, at or below the horizon, or an elevation above 90
        degrees (the message names ``sun``).
    """
    up = as_unit_vector(up, "up")
    if isinstance(sun, Sun):
        direction = sun.direction
    else:
        if isinstance(sun, (str, bytes, Mapping)) or sun is None:
            raise TypeError("sun must be a vector toward the sun (3,), a Sun or (azimuth_deg, elevation_deg), "
                            f"got {describe(sun)}")
        try:
            value = np.array(sun, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise TypeError("sun must be a vector toward the sun (3,), a Sun or (azimuth_deg, elevation_deg), "
                            f"got {describe(sun)}") from exc
        if value.shape not in ((2,), (3,)):
            raise ValueError("sun must have shape (3,) (a vector toward the sun) or (2,) (azimuth_deg, "
                             f"elevation_deg), got shape {value.shape}")
        if not np.isfinite(value).all():
            raise ValueError(f"sun must be finite, got {value.tolist()}")
        if value.shape == (2,):
            if value[1] > 90.0:
                raise ValueError(f"sun: the elevation must be at most 90 degrees, got {float(value[1]):g}")
            azimuth, elevation = np.radians(value)
            frame = horizontal_frame(up)
            value = math.cos(elevation) * (math.cos(azimuth) * frame[0] + math.sin(azimuth) * frame[1]) \
                + math.sin(elevation) * frame[2]
        norm = float(np.linalg.norm(value))
        if norm < 1e-12:
            raise ValueError(f"sun must be a non-zero vector, got {value.tolist()}")
        direction = value / norm
    height = float(direction @ up)
    if height <= 0.0:
        elevation = math.degrees(math.asin(max(-1.0, min(1.0, height))))
        raise ValueError(f"sun must be above the horizon (direction . up > 0), got elevation {elevation:.2f} degrees "
                         f"(direction {np.round(direction, 4).tolist()}, up {up.tolist()})")
    out = np.array(direction, dtype=np.float64)
    out.flags.writeable = False
    return out


def _pixel_normals(tracer: Tracer, hits, shape: tuple[int, int], normals_at_vertices: np.ndarray) -> np.ndarray:
    """Unit normals of a view's pixels from its camera-ray ``hits``: ``normals_at_vertices`` (N, 3)
    interpolated (see :func:`receiver_normals`)."""
    covered = hits.hit.reshape(shape)
    normals = tracer.interpolate(normals_at_vertices, hits).reshape(*shape, 3)
    length = np.linalg.norm(np.nan_to_num(normals), axis=-1)
    # Opposite vertex normals can cancel in the interpolation: take the hit's geometric normal there.
    degenerate = covered & (length < 1e-6)
    if degenerate.any():
        normals[degenerate] = hits.normals.reshape(*shape, 3)[degenerate]
        length[degenerate] = 1.0
    normals = np.where(covered[..., None], normals / np.where(length > 0, length, 1.0)[..., None], 0.0)
    return nearest_fill(normals, covered)


def receiver_normals(camera: Camera, tracer: Tracer, *, normal_smoothing: float = 0.0,
                     planes: PlaneConfig | None = None) -> np.ndarray:
    """Unit proxy normal of every pixel's receiver point (the ``n`` of the relit ``S_sun``, Sec. 8).

    As :func:`mvintrinsic.pixels.pixel_quantities` does it: the proxy's vertex normals
    interpolated (barycentric; the surfel's normal for point clouds) at the first hit of the
    pixel's centre ray, renormalised; a pixel whose ray misses takes the normal of the nearest
    pixel that hits, as its receiver depth does (:func:`receiver_depth`).

    Parameters
    ----------
    camera : Camera
    tracer : Tracer
        Ray caster over the proxy.
    normal_smoothing : float, optional
        Standard deviation (metres) of the smoothing of the vertex normals first
        (:func:`mvintrinsic.raytrace.smooth_normals`; :attr:`RelightConfig.normal_smoothing`);
        0 (the default): the proxy's own normals.
    planes : PlaneConfig, optional
        Then snap them to the proxy's dominant planes (:func:`mvintrinsic.raytrace.vertex_normals`;
        :attr:`RelightConfig.planes`); None (the default): not.

    Returns
    -------
    (H, W, 3) float64
        Unit normals, world frame.

    Raises
    ------
    ValueError
        If no pixel ray hits the proxy, or ``normal_smoothing`` is negative or not finite.
    """
    camera = _check_camera(camera)
    tracer = _check_tracer(tracer)
    if not is_real(normal_smoothing) or not 0.0 <= normal_smoothing < np.inf:
        raise ValueError(f"normal_smoothing must be a finite number >= 0 (metres), got {normal_smoothing!r}")
    hits, _, _ = _cast_pixels(camera, tracer)
    return _pixel_normals(tracer, hits, camera.shape, vertex_normals(tracer.proxy, normal_smoothing, planes))


def _in_turn(views: Sequence[View]) -> Callable[[Callable[[Any], Any], Iterable[Any]], dict[str, Any]]:
    """The per-view mapper the relighter's helpers take as ``run``: ``run(task, items)`` is ``{stem: task(item)}``,
    ``items`` one per view in ``views`` order, here one after the other (the relighter's runs them on its threads,
    :meth:`~mvintrinsic.relight.Relighter._per_view`)."""
    def run(task: Callable[[Any], Any], items: Iterable[Any]) -> dict[str, Any]:
        return {view.stem: task(item) for view, item in zip(views, items, strict=True)}

    return run


def _shared_receivers(views: Sequence[View], receivers: Mapping[str, np.ndarray], hits: Mapping[str, _PixelHits],
                      depth_tolerance: float = 0.02, run: Callable | None = None
                      ) -> dict[str, list[tuple[int, np.ndarray, np.ndarray]]]:
    """:func:`~mvintrinsic.photo_occupancy.shared_receivers` with the camera rays' hits (``hits``) as the depths;
    ``run``: as :func:`_in_turn`'s, e.g. on several threads (default: in turn)."""
    depth = {v.stem: hits[v.stem].t.reshape(v.shape) for v in views}
    return (run or _in_turn(views))(_links_task(views, receivers, depth, depth_tolerance), views)


def _unexplained_pixels(views: Sequence[View], nearest: Mapping[str, np.ndarray], hits: Mapping[str, _PixelHits],
                        known: Mapping[str, np.ndarray], consistency: float) -> dict[str, np.ndarray]:
    """Per view, the pixels the proxy does not explain (:attr:`RelightConfig.consistency`), (H, W) bool.

    The pixel is unexplained when it has an estimate (``known``) and its ray misses the proxy,
    or when at least one other view sees its receiver point and none of them sees a colour near
    its own there: ``nearest`` (:func:`~mvintrinsic.photo_occupancy.nearest_colour`) finite and not below ``consistency``. A
    point no other view sees gives no evidence: the pixel keeps the moved shadow.
    """
    return {v.stem: unexplained_pixels(known[v.stem], hits[v.stem].hit.reshape(v.shape), nearest[v.stem], consistency)
            for v in views}


def _fusion_matrices(views: Sequence[View], shared: Mapping[str, list[tuple[int, np.ndarray, np.ndarray]]],
                     explained: Mapping[str, np.ndarray], capture: Mapping[str, np.ndarray], mode: str,
                     run: Callable | None = None) -> dict[str, sparse.csr_matrix]:
    """Per view, the (H*W, total pixels) averaging matrix of :attr:`RelightConfig.fusion`.

    Row ``i`` of a view's matrix averages, with weight 1 each, its own pixel ``i`` and the other
    views' pixels that see its receiver point (``shared``), where both are ``explained`` ((H, W)
    bool per view) and, with ``mode="capture"``, both have the same capture state
    (``capture >= 0.5``, (H, W) per view). Columns index the views' flattened pixels one view
    after the other, in ``views`` order; a row with no such pixel is the identity. ``run``: as
    :func:`_in_turn`'s, e.g. on several threads (default: in turn).
    """
    offsets = np.cumsum([0] + [int(np.prod(v.shape)) for v in views])
    flat_explained = [np.asarray(explained[v.stem], bool).ravel() for v in views]
    flat_lit = [(np.asarray(capture[v.stem]) >= 0.5).ravel() for v in views]

    def matrix(a: int) -> sparse.csr_matrix:
        n_pixels = offsets[a + 1] - offsets[a]
        rows, cols = [np.arange(n_pixels)], [offsets[a] + np.arange(n_pixels)]
        for k, own, theirs in shared[views[a].stem]:
            keep = flat_explained[a][own] & flat_explained[k][theirs]
            if mode == "capture":
                keep &= flat_lit[a][own] == flat_lit[k][theirs]
            rows.append(own[keep])
            cols.append(offsets[k] + theirs[keep])
        rows, cols = np.concatenate(rows), np.concatenate(cols)
        weights = (1.0 / np.bincount(rows, minlength=n_pixels))[rows].astype(np.float32)
        return sparse.csr_matrix((weights, (rows, cols)), shape=(n_pixels, offsets[-1]))

    return (run or _in_turn(views))(matrix, range(len(views)))


def _fuse(fusion: Mapping[str, sparse.csr_matrix], visibility: Mapping[str, np.ndarray],
          run: Callable[[Callable[[str], np.ndarray]], dict[str, np.ndarray]] | None = None) -> dict[str, np.ndarray]:
    """:func:`_fusion_matrices` applied to every view's ``v'`` ((H, W) per stem), in the matrices' view order;
    ``run(task)``: ``{stem: task(stem)}`` for every stem, e.g. on several threads."""
    stacked = np.concatenate([np.asarray(visibility[s], np.float32).ravel() for s in fusion])

    def fused(s: str) -> np.ndarray:
        mean = fusion[s] @ stacked  # float32, as the weights and the stacked values
        return np.clip(mean, 0.0, 1.0, out=mean).astype(np.float32, copy=False).reshape(np.shape(visibility[s]))

    return {s: fused(s) for s in fusion} if run is None else run(fused)


def _read_only(array: np.ndarray) -> np.ndarray:
    array.flags.writeable = False
    return array


class _PixelHits(NamedTuple):
    """What the relighter keeps of a view's camera-ray hits (:meth:`Tracer.intersect`'s ``hit`` and ``t``, (H*W,)
    each): their points, normals, barycentric weights and indices, 88 bytes a pixel, are dropped once the receivers'
    normals are interpolated (1000x750: 0.53 GB less for eight views)."""

    hit: np.ndarray
    t: np.ndarray


def _view_geometry(decomposition: Decomposition, scene: Scene, config: RelightConfig, tracer: Tracer, batch: int,
                   capture: np.ndarray, timings: dict[str, float], run: Callable | None = None) -> tuple:
    """What :class:`~mvintrinsic.relight.Relighter` reads of the views before its casters (seconds added to ``timings``): the
    proxy's vertex normals; per stem the receiver points, normals, camera-ray hits, capture cosine (Eq.
    (1)), pixels with an estimate; the shared receivers and nearest colours (``{}`` if unneeded). ``run``: as
    :func:`_in_turn`'s, e.g. on several threads (default: in turn)."""
    run = run or _in_turn(scene.views)
    start = time.perf_counter()
    smoothed = vertex_normals(tracer.proxy, config.normal_smoothing, config.planes)

    def geometry(view: View) -> tuple:
        stem, camera = view.stem, view.camera
        ray_hits, t, hit = _cast_pixels(camera, tracer, batch, name=f"scene (view {stem!r})")
        receivers = _read_only(receiver_points(camera, t))
        normals = _read_only(_pixel_normals(tracer, ray_hits, camera.shape, smoothed))
        cosine = np.maximum(normals @ capture, 0.0)  # max(0, cos w_sun), Eq. (1)
        layers = decomposition.layers[stem]
        known = _read_only((layers.reflectance > 0).any(axis=-1) | (layers.shading > 0).any(axis=-1))
        return receivers, normals, _PixelHits(ray_hits.hit, ray_hits.t), cosine, known

    per_view = run(geometry, scene.views)
    receivers, normals, hits, cosine, known = ({s: per_view[s][i] for s in scene.stems} for i in range(5))
    timings["receivers"] += time.perf_counter() - start
    start = time.perf_counter()  # what the other views see at each receiver point
    gains = {stem: decomposition.lighting.gain(stem) for stem in scene.stems}
    needed = config.consistency is not None or config.fusion is not None or config.lost_occluders is not None
    links = _shared_receivers(scene.views, receivers, hits, run=run) if needed else {}
    nearest = nearest_colour(scene.views, gains, links) if needed else {}
    timings["consistency"] += time.perf_counter() - start
    return smoothed, receivers, normals, hits, cosine, known, links, nearest
