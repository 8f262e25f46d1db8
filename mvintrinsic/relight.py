"""Relighting: shadow receivers, a 2.5D shadow caster, moving cast shadows and relit shading (Sec. 8).

The proxy's own shadows do not match the shadow boundaries of the photographs (paper Fig. 4b), so
the paper relights with a *caster* built from the shadows of the image itself (Duchêne et al.
2015, Sec. 8, "Creating Shadow Receiver and Caster Geometry" and "Moving Shadows and Adjusting
Shading"). The geometry is built in :mod:`.caster`, the new shadow layer for any sun computed in
:mod:`.shadow_caster`, the environment's change in :mod:`.relit_shading`; this module relights the
views (:class:`Relighter`, :func:`relight`) and exports the stage's public names.

**Adjusting shading** (:class:`Relighter`). The reflectance is fixed (paper Fig. 2, far right)
and the image model of Eq. (1) is evaluated at the new sun ``d'``:

.. math::

   I' = R \\, (v' \\, S_{sun}' + S_{sky}' + S_{ind}')

* ``v'``: the caster's visibility (merged caster of all views, proxy completion, blur);
* ``S_sun'``: where the pixel saw the sun at capture (``v_sun > 0``), the layers' own ``S_sun``
  plus the change of the proxy's cosine term,
  ``S_sun' = S_sun + L_sun (max(0, n . d') - max(0, n . d))``; in full shadow (``v_sun = 0``),
  where the image never observed ``S_sun``, ``S_sun' = L_sun max(0, n . d')``. ``n`` is the
  proxy normal of the pixel, smoothed as in Step 1 (:func:`receiver_normals`,
  :attr:`RelightConfig.normal_smoothing`), ``L_sun`` the decomposition's;
* ``S_sky'``, ``S_ind'``: :attr:`RelightConfig.sky` selects

  - ``"paper"`` (default): our reading of the paper's adjustment, "shifting S_sky towards red in
    the morning and afternoon. We also diminish S_ind with a similar amount":
    ``S_sky' = g * S_sky`` with ``g`` the luminance-normalised change of the Rayleigh
    transmittance of the atmosphere between the two sun elevations (a red shift for a lower sun),
    ``S_ind' = f S_ind`` with ``f = sin(el') / sin(el)``, the change of the sun's irradiance on a
    horizontal plane (:func:`paper_environment_factors`);
  - ``"model"``: the fitted Preetham sky (Eq. 4, its turbidity from ``lighting.sky``)
    re-evaluated at the new sun: ``S_sky`` scaled per pixel normal by the model's sky irradiance
    at ``d'`` over that at ``d`` (:func:`sky_irradiance_ratio`), and ``S_ind`` by the change of
    the sun irradiance of all the views' receivers,
    ``mean(max(0, n . d') v') / mean(max(0, n . d) v_sun)``;

* dropped shadow clusters (too small or unsupported by the proxy, :func:`build_caster`; their
  occluder is unknown): the paper brings them "in light using the v_sun layer" (``dropped="light"``:
  ``v_sun`` 1, reflectance ``I / (S_sun + S_sky + S_ind)``); ``"static"`` (default, beyond the
  paper) keeps the shadow in the shadow layer, ``v' = v_sun v'_caster`` (with the other defaults of
  2026-11-29 the cross-view agreement at least 0.95 at 20 of 22 scene-suns instead of 16 and 13, rows
  (d) and (e) +0.12 and +0.13 dB on average: ``docs/relight.md``); with
  :attr:`RelightConfig.lost_occluders` the photographs may place their occluder
  (:mod:`.photo_occupancy`), and the pixels of the clusters kept only thanks to it mix the two
  images (:attr:`Relighter.rescued`, ``OccupancyConfig.belief``);
* the caster from the labelled shadow alone (beyond the paper, ``caster_pixels="labels"``, not the
  default): the pixels with ``v_sun < tau_s`` outside its kept clusters are dropped instead of
  lifted; for labels better than Step 3's (with the true labels and ``lost_occluders``, (e) - (a)
  at +-15 degrees 2.51 -> 3.01 dB; with Step 3's labels it loses: ``docs/relight.md``);
* pixels the proxy does not explain (beyond the paper, :attr:`RelightConfig.consistency`) keep
  their capture ``v_sun`` at every sun (below);
* one shadow in every view (beyond the paper, :attr:`RelightConfig.fusion`): a pixel's new
  ``v'`` is averaged with the other views' at the pixels that see the same point (below);
* the capture anchors the new shadow (beyond the paper, :attr:`RelightConfig.anchor`, ``"shadow"`` by
  default): ``v' = clip(C(d') + min(0, v_sun - C(d)), 0, 1)`` with ``C`` the caster's fused ``v'``, so a
  captured shadow the caster does not cast stays where it was (``docs/relight.md``, "The anchor");
* the receivers' normals on the proxy's planes (beyond the paper, :attr:`RelightConfig.planes`), as
  Step 1's (:mod:`.planes`).

At the capture sun with the (fixed) visibility of the layers every factor is 1 and every
correction 0: the relit image is ``R S_tot``, the decomposition's reconstruction, exactly
(``tests/test_relight.py``).

Relit shading: deviations and readings, with their reasons. Numbers are PSNR (dB) against the
demo's path-traced relit renders (sun azimuth +15 degrees / elevation +10 degrees), as
``benchmarks/bench_relight.py`` scores them (linear RGB, non-sky pixels, clipped at the truth's
99.5th percentile):

* **The sun term keeps the layers' own S_sun.** The paper adjusts "the sun shading intensity
  according to a cosine factor"; the layers' ``S_sun`` is not ``L_sun max(0, n . d)`` of the
  proxy, so only the *change* of the proxy's term is added: the identity stays exact and the
  layers' detail is kept (27.02 / 26.10 dB with the true layers and the true relit visibility,
  against 22.59 / 20.72 for ``L_sun max(0, n . d')`` alone; ``docs/relight.md``, "Relit shading").
* **The environment "paper" is our reading** (:func:`paper_environment_factors`). ``L_sun`` keeps
  its colour and intensity, as in the paper (Sec. 9.4); on the demo the renderer's sun is brighter
  at a higher elevation and the lit pixels at +10 degrees come out 4.6% darker (median).
* **Default "paper" by measurement**: on the demo it scores higher than ``"model"`` in every row
  (the full pipeline 23.55 / 22.75 against 23.45 / 22.18; the pixel classes in ``docs/relight.md``,
  "Relit shading").
* **Sky irradiance ratio, not re-integration**: ``"model"`` scales the layers' ``S_sky``, which
  holds the occlusion Step 1 traced, by the ratio of *unoccluded* sky irradiances (a ratio over
  each receiver's unoccluded directions moved row (d) by -0.02 to +0.13 dB, ``docs/relight.md``).
  The scale ``k`` of Eq. (4) cancels; the absolute zenith luminance of Preetham et al. (Appendix
  A.2), which the relative model leaves to ``k``, does not, and is applied.
* **Pixels without an estimate** (sky, invalid pixels) show the input image (``fill``); sky pixels
  change colour (Sec. 8; :attr:`RelightConfig.sky_pixels`, :func:`~mvintrinsic.relit_shading.sky_pixel_factors`).
* **On the demo the paper's caster keeps no cluster** (the proxy lost 90% of the foliage and of
  the thin structures; ``docs/relight.md``, "The demo's clusters").

**Pixels the proxy does not explain** (:attr:`RelightConfig.consistency`, :attr:`Relighter.unexplained`).
The new shadow is traced from each pixel's receiver point, the first proxy hit of its ray. Where
the proxy lost the surface the photograph shows (a crown, a pole, a railing in front of the facade
the proxy kept), that point is the facade behind, and its new shadow says nothing about the
pixel: the leaves of a crown would take the shadow state of the wall behind them. Such a pixel
shows a colour the other views do not see at its receiver point (they see it through the gaps,
or the lost surface from elsewhere); where its colour is at least 0.3 in log radiance from what
each of the other views sees there (the threshold :mod:`.occluders` applies to its camera rays),
or its ray misses the proxy, it keeps its capture visibility at every sun (one view that agrees
keeps the pixel moving). On five 480x360 scenes (22 scene-suns, with the fusion below) it raises
the relit PSNR by -0.02 to +0.63 dB with the true layers (row (d) of ``bench_relight.py``, mean
+0.18) and by -0.06 to +0.38 dB with the pipeline's (row (e), mean +0.10; tables and the three
scene-suns below each pixel moved in ``docs/relight.md``). A point no other view sees gives no
evidence: the pixel keeps the moved shadow. 0.56 s per view to build at 1000x750 with six views
(measured with the median form), nothing per new sun.

**One shadow in every view** (:attr:`RelightConfig.fusion`). Each view's caster is built from
its own labels, so two views can move the shadow of one point differently. A pixel whose receiver
point other views see (the projection and depth test above) takes the mean of its own ``v'`` and
theirs, over the pixels the proxy explains on both sides, by default only from the views whose
capture state there is its own (a view's reflectance was made for its own label). On the five
scenes it raises rows (d), (e) and the cross-view agreement at all 22 scene-suns (``"all"`` the
agreement more, but row (e) by up to 0.93 dB less; ``docs/relight.md``). 0.05 s per view to
build, 5 ms per view and new sun at 1000x750.

Sources: the paper's Sec. 8 [1]_; the Preetham sky [2]_; the Rayleigh optical depth [3]_ and the air
mass [4]_ of the "paper" sky adjustment.

References
----------
.. [1] S. Duchêne, C. Riant, G. Chaurasia, J. Lopez-Moreno, P.-Y. Laffont, S. Popov, A. Bousseau
   and G. Drettakis, "Multi-View Intrinsic Images of Outdoors Scenes with an Application to
   Relighting", ACM Transactions on Graphics 34(5), 2015, Sec. 8.
.. [2] A. J. Preetham, P. Shirley and B. Smits, "A Practical Analytic Model for Daylight", Proc.
   SIGGRAPH 99, 91-100, 1999. Appendix A.2: the absolute zenith luminance.
.. [3] J. E. Hansen and L. D. Travis, "Light scattering in planetary atmospheres", Space Science
   Reviews 16, 527-610, 1974: the Rayleigh optical depth at sea level,
   ``0.008569 lambda^-4 (1 + 0.0113 lambda^-2 + 0.00013 lambda^-4)``, lambda in micrometres.
.. [4] F. Kasten and A. T. Young, "Revised optical air mass tables and approximation formula",
   Applied Optics 28(22), 4735-4738, 1989.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from types import MappingProxyType
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

from ._cluster import _as_client, _Rebuilt, _ViewTasks
from ._validation import as_array, as_count, config_or_default, describe
from .caster import (
    ANCHOR_MODES,
    CASTER_MODES,
    CASTER_PIXEL_MODES,
    DROPPED_MODES,
    RELIGHT_METHODS,
    SKY_ADJUSTMENTS,
    SKY_PIXEL_MODES,
    Caster,
    RelightConfig,
    _check_sun,
    _check_tracer,
    _contradicted,
    _revote,
    build_caster,
    capture_first_hits,
    contradicted_primitives,
    kept_clusters,
    merge_casters,
    remove_contradicted,
    shadow_pixels,
)
from .photo_occupancy import _blend_into, blend_rescued, photo_occupancy
from .pixels import nearest_fill
from .raytrace import DEFAULT_BATCH, Tracer
from .raytrace import sun_visibility as proxy_vertex_visibility
from .relit_shading import (
    NORMAL_GRID_HEIGHT,
    RGB_WAVELENGTHS_UM,
    SKY_GRID_HEIGHT,
    SKY_RATIO_FLOOR,
    _build_task,
    _grid_ratio,
    _image_task,
    _into_light,
    _irradiance_task,
    _new_sun_terms,
    _NewSun,
    _PaperPixels,
    _render_view,
    _sky_irradiance_grid,
    _SkyPixels,
    _SphereLookup,
    _sun_terms,
    paper_environment_factors,
    sky_irradiance_ratio,
    sky_pixel_factors,
)
from .results import SHADOW_LABELS, Decomposition, IntrinsicLayers
from .scene import Scene
from .shadow_caster import (
    ShadowCaster,
    _completion_distance,
    _fuse,
    _fusion_matrices,
    _read_only,
    _unexplained_pixels,
    _view_geometry,
    as_sun_direction,
    receiver_depth,
    receiver_normals,
    receiver_points,
)

__all__ = ["NORMAL_GRID_HEIGHT", "RGB_WAVELENGTHS_UM", "ANCHOR_MODES", "CASTER_MODES", "CASTER_PIXEL_MODES", "DROPPED_MODES", "RELIGHT_METHODS",
           "SKY_ADJUSTMENTS", "SKY_GRID_HEIGHT", "SKY_PIXEL_MODES", "SKY_RATIO_FLOOR", "Caster",
           "RelightConfig", "Relighter", "ShadowCaster", "as_sun_direction", "build_caster",
           "contradicted_primitives", "merge_casters", "paper_environment_factors", "receiver_depth",
           "receiver_normals", "receiver_points", "relight", "remove_contradicted", "shadow_pixels",
           "sky_irradiance_ratio", "sky_pixel_factors"]


def _anchor_offsets(capture: np.ndarray, moved: np.ndarray, mode: str) -> tuple[np.ndarray, np.ndarray]:
    """The anchor of :attr:`RelightConfig.anchor` where it is not 0: flat indices (int64) and ``a`` (float32).

    ``a = capture - moved`` (``"both"``) or ``min(0, capture - moved)`` (``"shadow"``), both (H, W) in [0, 1]:
    the capture ``v_sun`` and the caster's ``v'`` at the capture sun."""
    offset = np.asarray(capture, np.float32).reshape(-1) - np.asarray(moved, np.float32).reshape(-1)
    if mode == "shadow":
        np.minimum(offset, 0.0, out=offset)
    index = np.flatnonzero(offset)
    return _read_only(index), _read_only(offset[index])


def _check_decomposition(decomposition: object, scene: object) -> tuple[Decomposition, Scene]:
    if not isinstance(scene, Scene):
        raise TypeError(f"scene must be a Scene, got {describe(scene)}")
    if not isinstance(decomposition, Decomposition):
        raise TypeError(f"decomposition must be a Decomposition, got {describe(decomposition)}")
    ours, theirs = set(decomposition.stems), set(scene.stems)
    if ours != theirs:
        missing, extra = sorted(theirs - ours), sorted(ours - theirs)
        raise ValueError(f"decomposition must hold the layers of the scene's views {list(scene.stems)}: "
                         f"missing {missing}, not in the scene {extra}")
    for view in scene.views:
        shape = decomposition.layers[view.stem].shape
        if shape != view.shape:
            raise ValueError(f"decomposition: the layers of view {view.stem!r} are {shape[1]}x{shape[0]} pixels, "
                             f"the view is {view.shape[1]}x{view.shape[0]}")
    return decomposition, scene



class Relighter:
    """Relight every view of a decomposition under new suns (paper Sec. 8).

    Built once per decomposition: per view the receiver points and normals, the shadow pixels and
    the caster (:func:`build_caster` at the capture sun, lit pixels voting), the dropped clusters'
    handling (``config.dropped``); then one caster merged over all views
    (:func:`merge_casters`) and its Embree structure (:class:`ShadowCaster`). Each
    :meth:`render` then moves the shadows (caster, proxy completion, blur) and adjusts the shading
    (module docstring, "Adjusting shading"):

    .. math::

        I' = R \\, (v' S_{sun}' + S_{sky}' + S_{ind}')

    Parameters
    ----------
    decomposition : Decomposition
        The layers of every view of ``scene`` (and no other view) and the lighting they were
        computed under: ``lighting.sun`` is the capture sun, ``lighting.sun_radiance`` is
        ``L_sun``, ``lighting.sky`` the fitted sky (``sky="model"``).
    scene : Scene
        The views' cameras, the proxy and ``up``.
    config : RelightConfig, optional
    tracer : Tracer, optional
        A tracer already built over ``scene.proxy``.
    batch : int, optional
        Rays per Embree call.
    threads : int, optional
        Views worked on at once in this process, when building and by :meth:`render` (default 2; 1:
        one after the other). Embree already casts each view's rays on every core; the rest is
        NumPy and SciPy on one core per view. Two threads (and the OpenCV blur) took a new sun at
        1000x750 from 0.088-0.106 to 0.052-0.075 s per view on two cores, and the building (with
        one BLAS thread) from 6.1-6.3 to 3.7 s per view on street_s0 (``docs/relight.md``, "Speed");
        the casters and images are identical to one thread's.
    client : distributed.Client, optional
        A dask.distributed client: :meth:`render` then runs one task per view on its cluster
        (``docs/distributed.md``). Building stays here; each view's inputs of a new sun (about
        120 bytes per pixel, 180 with ``sky="model"``) are shipped once to one worker, the proxy
        once to every worker, where ``Tracer(scene.proxy)`` is rebuilt (a ``tracer`` built with
        other surfel parameters would not be matched). The images are identical to those
        rendered here. None (default): everything runs in this process; dask is not imported.

    Attributes
    ----------
    config : RelightConfig
        The configuration the relighter was built with; read-only (its casters and every view's
        per-sun inputs were built from it): build another relighter for other options.
    stems : tuple of str
        The views, in the scene's order.
    sun : (3,) float64
        The capture sun (unit, toward the sun, world frame).
    receivers, normals : mapping of str to (H, W, 3) float64
        Per view, the receiver points (metres, :func:`receiver_points`) and unit proxy normals
        (:func:`receiver_normals`), world frame.
    reflectance : mapping of str to (H, W, 3) float32
        ``R``, after the in-shadow fix with ``config.dropped="light"``.
    visibility : mapping of str to (H, W) float32
        The capture ``v_sun``, after the fix with ``config.dropped="light"`` (1 on the dropped clusters):
        ``render(self.sun, visibility=self.visibility)`` reproduces every view's
        ``reflectance * shading``.
    unexplained : mapping of str to (H, W) bool
        Per view, the pixels the proxy does not explain (``config.consistency``: their ray misses
        the proxy, or their colour disagrees with what the other views see at their receiver
        point); they keep :attr:`visibility` at every sun. Empty with ``consistency=None``.
    rescued : mapping of str to (H, W) bool
        Per view that has any, the pixels of the clusters the paper's rule drops and
        ``config.lost_occluders`` keeps, where :meth:`render` mixes the two (``OccupancyConfig.belief``;
        :meth:`layers` and :meth:`visibility_at` give the moved shadow alone); empty with belief 1.
    casters : mapping of str to Caster
        Per view, after the votes of every view (``method="multiview"``) and before merging
        (``dropped``: the pixels of the dropped clusters, ``config.dropped``).
    caster : Caster
        The union of the views' casters (:func:`merge_casters`).
    shadow_casters : mapping of str to ShadowCaster
        The Embree structure that shades each view: its own caster's (``casters="own"``) or
        one over :attr:`caster` shared by all views (``casters="merged"``).
    excluded_primitives : (K,) int64
        Proxy primitives that complete no shadow, contradicted by lit pixels
        (:func:`contradicted_primitives`; empty with ``method="paper"``).
    timings : mapping of str to float
        Seconds spent building: ``receivers`` (camera rays, depths, normals), ``casters`` (all
        views' :func:`build_caster`), ``votes`` (every view's lit pixels against every caster and
        the proxy), ``shadow_caster`` (merging and the BVHs), ``consistency`` (which other views'
        pixels see each receiver point, and the pixels the proxy does not explain,
        :attr:`unexplained`), ``fusion`` (the averaging of ``config.fusion``), ``new_sun_setup`` (what every
        new sun reuses: the completion lookups and the shading terms), with :attr:`rescued` ``rescued``
        (the terms of the paper's image at those pixels) and, with a ``client``,
        ``scatter`` (shipping those to the workers, which build their Embree structures).

    Raises
    ------
    TypeError
        If ``decomposition``, ``scene``, ``config``, ``tracer`` or ``client`` has the wrong type.
    ValueError
        If the decomposition's views are not the scene's (the message names ``decomposition``),
        ``tracer`` is not built over ``scene.proxy``, a view's camera sees no proxy, or the
        capture sun is at or below the horizon.
    """

    def __init__(self, decomposition: Decomposition, scene: Scene, *, config: RelightConfig | None = None,
                 tracer: Tracer | None = None, batch: int = DEFAULT_BATCH, client: Any = None,
                 threads: int = 2) -> None:
        # One BLAS thread while building (the same numbers: OpenBLAS splits the rows of each product among its
        # threads): the building's BLAS products are (N, 3) x (3, 3) (Camera.world_to_camera), and the second
        # OpenBLAS thread spinning after each took a core from these threads and Embree's ("Speed").
        with threadpool_limits(limits=1, user_api="blas"):
            self._build(decomposition, scene, config=config, tracer=tracer, batch=batch, client=client,
                        threads=threads)

    @property
    def config(self) -> RelightConfig:
        """The :class:`RelightConfig` the relighter was built with (read-only: the casters and every view's per-sun
        inputs hold it; an option changed afterwards would reach some steps and not others)."""
        return self._config

    def _build(self, decomposition: Decomposition, scene: Scene, *, config: RelightConfig | None, tracer: Tracer | None,
               batch: int, client: Any, threads: int) -> None:
        decomposition, scene = _check_decomposition(decomposition, scene)
        config = config_or_default(config, RelightConfig)
        client = _as_client(client)
        self._threads = as_count(threads, "threads", least=1)
        if tracer is None:
            tracer = Tracer(scene.proxy)
        tracer = _check_tracer(tracer)
        if tracer.proxy is not scene.proxy:
            raise ValueError("tracer must be built over scene.proxy")
        lighting = decomposition.lighting
        up = scene.up
        capture = _check_sun(lighting.sun.direction, up)
        self.decomposition, self.scene, self._config, self.tracer = decomposition, scene, config, tracer
        self.stems = scene.stems
        self.up, self.sun = up, capture
        self.sun_radiance = lighting.sun_radiance
        # L_sun in each view's own units (its exposure gain, mvintrinsic.exposure), float32 (3,)
        self._radiance = {stem: (lighting.sun_radiance * lighting.gain(stem)).astype(np.float32)
                          for stem in decomposition.layers}
        self._batch = batch
        timings = {"receivers": 0.0, "casters": 0.0, "votes": 0.0, "shadow_caster": 0.0, "consistency": 0.0}
        self._vertex_normals, receivers, normals, hits, cosine, known, links, nearest = _view_geometry(
            decomposition, scene, config, tracer, batch, capture, timings, run=self._per_view)
        reflectance, visibility, casters, lit_points, rescued = {}, {}, {}, {}, {}
        start = time.perf_counter()
        occupancy, rule = None, config  # with lost_occluders (beyond the paper) its cluster rule, min_hits;
        if config.lost_occluders is not None and len(scene.views) >= config.lost_occluders.min_views:  # else inert
            occupancy = photo_occupancy(scene.views, {s: hits[s].t.reshape(known[s].shape) for s in self.stems},
                                        known, nearest, config=config.lost_occluders)
            rule = replace(config, min_proxy_hits=max(config.min_proxy_hits, config.lost_occluders.min_hits))
        # lost_occluders' belief < 1: the pixels kept only thanks to its distances or as supported parts are the
        # expected image over the two hypotheses (their shadow is real, or a mislabelling), the parts' new shadows too.
        self._belief = config.lost_occluders.belief if occupancy is not None else 1.0
        timings["consistency"] += time.perf_counter() - start
        start = time.perf_counter()

        def view_caster(index: int) -> tuple:  # one view's caster and layers (views at once: self._threads)
            view = scene.views[index]
            stem, camera, hit = view.stem, view.camera, hits[view.stem].hit.reshape(view.shape)
            layers = decomposition.layers[stem]
            labels = layers.shadow_labels
            shadow = shadow_pixels(labels, layers.visibility, tau_s=config.tau_s)
            # caster_pixels="labels" (beyond the paper): lift the labelled shadow alone; the pixels
            # with v_sun < tau_s outside its kept clusters are dropped (relit as config.dropped says).
            lifted = shadow if config.caster_pixels == "paper" else shadow_pixels(labels, None)
            lit = hit & ~shadow & (labels == SHADOW_LABELS["lit"])
            missed = np.zeros(view.shape, dtype=bool)  # shadow pixels whose sun ray misses the proxy
            distance = None if occupancy is None else occupancy.sun_ray_distance(index, receivers[stem], asked=missed)
            caster = build_caster(camera, lifted, receivers[stem], capture, tracer, lit=lit, up=up,
                                  config=rule, batch=batch, occluder_distance=distance)
            if config.caster_pixels == "labels":
                caster = replace(caster, dropped=shadow & ~caster.shadow)
            r, v = layers.reflectance, layers.visibility
            if config.dropped == "light" and caster.dropped.any():
                r, v = _into_light(layers, r, v, caster.dropped)
            saved = None
            if self._belief < 1:  # kept, and dropped by the paper's rule; and the supported parts
                saved = caster.shadow & ~kept_clusters(lifted, lifted & ~missed, config.min_cluster,
                                                       config.min_proxy_hits)[0] | caster.parts
            return (receivers[stem][lit], caster, _read_only(np.array(r, dtype=np.float32)),
                    _read_only(np.array(v, dtype=np.float32)), saved)

        for stem, (points, caster, r, v, saved) in self._per_view(view_caster, range(len(scene.views))).items():
            lit_points[stem], casters[stem], reflectance[stem], visibility[stem] = points, caster, r, v
            if saved is not None:
                rescued[stem] = saved
        timings["casters"] += time.perf_counter() - start

        start = time.perf_counter()
        excluded = np.zeros(0, dtype=np.int64)
        #: Proxy hits nearer than this (metres) complete no shadow (RelightConfig.completion_distance),
        #: and the share of lit points the proxy shaded within 0.6 m at capture when it was "auto".
        self.completion_distance, self.self_shading = 0.0, None
        if config.method == "multiview":
            # Every view's lit pixels vote against every view's caster and against the proxy.
            casters.update(self._per_view(lambda stem: _revote(
                casters[stem], lit_points[stem], [lit_points[s] for s in self.stems if s != stem], capture, config,
                batch)))
            # One cast of the lit points' capture-sun rays: the proxy primitives they contradict, and
            # how near the proxy shades them (completion_distance="auto").
            first_t, first_primitive = capture_first_hits(tracer, [lit_points[s] for s in self.stems], capture,
                                                          config=config, batch=batch)
            excluded = _contradicted(first_primitive, config.epsilon)
            self.completion_distance, self.self_shading = _completion_distance(config, first_t)
        timings["votes"] = time.perf_counter() - start

        start = time.perf_counter()
        self.caster = merge_casters([casters[s] for s in self.stems])
        shared = ShadowCaster(self.caster) if config.casters == "merged" else None
        self.shadow_casters = MappingProxyType({s: ShadowCaster(casters[s]) if shared is None else shared
                                                for s in self.stems})
        timings["shadow_caster"] = time.perf_counter() - start
        self.excluded_primitives = _read_only(excluded)
        self.receivers = MappingProxyType(receivers)
        self.normals = MappingProxyType(normals)
        self.reflectance = MappingProxyType(reflectance)
        self.visibility = MappingProxyType(visibility)
        self.casters = MappingProxyType(casters)
        self._hits, self._known = hits, known
        start = time.perf_counter()
        unexplained = (_unexplained_pixels(scene.views, nearest, hits, known, config.consistency)
                       if config.consistency is not None else {})
        self.unexplained = MappingProxyType({s: _read_only(m) for s, m in unexplained.items()})
        timings["consistency"] += time.perf_counter() - start
        start = time.perf_counter()
        self._fusion = None
        if config.fusion is not None:
            explained = {s: hits[s].hit.reshape(known[s].shape) & known[s] for s in self.stems}
            for s, flagged in unexplained.items():
                explained[s] = explained[s] & ~flagged
            self._fusion = _fusion_matrices(scene.views, links, explained, visibility, config.fusion,
                                            run=self._per_view)
        timings["fusion"] = time.perf_counter() - start
        # The sun-independent inputs of every new sun, once (module docstring, "Speed").
        start = time.perf_counter()
        self._turbidity = lighting.sky.turbidity if lighting.sky is not None else config.turbidity
        self._new_sun = self._per_view(lambda s: self._prepare_new_sun(s, cosine[s], excluded, rescued.get(s)))
        timings["new_sun_setup"] = time.perf_counter() - start
        # RelightConfig.anchor (beyond the paper): the capture v_sun minus the caster's own v' at the capture sun.
        self._anchor: dict[str, tuple[np.ndarray, np.ndarray]] = {}
        if config.anchor is not None:
            start = time.perf_counter()
            at_capture = self._moved(capture)
            self._anchor = {s: _anchor_offsets(visibility[s], at_capture[s], config.anchor) for s in self.stems}
            timings["anchor"] = time.perf_counter() - start
        # The sun irradiance of the receivers at capture, the denominator of S_ind's scale.
        self._sun_irradiance = sum(float((cosine[s] * visibility[s])[known[s]].sum()) for s in self.stems)
        self._sky_grid: np.ndarray | None = None
        if config.sky == "model":
            self._sky_grid = _sky_irradiance_grid(capture, self._turbidity, up)
        self._tasks: _ViewTasks | None = None
        self._remote: dict[str, Any] = {}
        if client is not None:  # each view's inputs of a new sun on its worker, once
            start = time.perf_counter()
            self._tasks = _ViewTasks(client, self.stems)
            self._remote = {"tracer": self._tasks.broadcast(_Rebuilt(Tracer, scene.proxy, value=tracer)),
                            "new_sun": self._tasks.scatter(self._new_sun)}
            if config.casters == "merged":
                merged = _Rebuilt(ShadowCaster, self.caster, value=self.shadow_casters[self.stems[0]])
                shared = self._tasks.broadcast(merged)
                self._remote["casters"] = {s: shared for s in self.stems}
            else:
                self._remote["casters"] = self._tasks.scatter(
                    {s: _Rebuilt(ShadowCaster, casters[s], value=self.shadow_casters[s]) for s in self.stems})
            # the workers build their Embree structures now, not at the first sun
            builds = {s: (self._remote["casters"][s], self._remote["tracer"]) for s in self.stems}
            self._tasks.gather(self._tasks.submit("relight-build", _build_task, builds))
            timings["scatter"] = time.perf_counter() - start
        start = time.perf_counter()  # lost_occluders' belief < 1 (beyond the paper): the paper's image there
        self.rescued = MappingProxyType({s: _read_only(m) for s, m in rescued.items() if m.any()})
        self._paper = {s: self._paper_pixels(s, m, cosine[s]) for s, m in self.rescued.items()}
        self._rescued_pixels = {s: np.flatnonzero(m) for s, m in self.rescued.items()}
        if rescued:
            timings["rescued"] = time.perf_counter() - start
        self.timings = MappingProxyType(timings)

    # -- shadows -------------------------------------------------------------------------------
    def visibility_at(self, sun: object) -> dict[str, np.ndarray]:
        """The new shadow layer of every view: the caster's ``v'`` (Sec. 8, "Moving Shadows").

        :meth:`ShadowCaster.sun_visibility` of the view's caster (:attr:`shadow_casters`) from
        the view's receiver points, completed by the proxy's shadow (this relighter's tracer;
        with ``method="multiview"`` without :attr:`excluded_primitives` and hits nearer than
        ``config.completion_distance``) and blurred by ``config.blur``; the pixels the proxy does
        not explain (:attr:`unexplained`) keep their capture :attr:`visibility`; then, with
        ``config.fusion``, every pixel's value is averaged with the other views' that see its
        receiver point (module docstring, "One shadow in every view"); then, with ``config.anchor``,
        the capture's anchor is added (:attr:`RelightConfig.anchor`).

        Parameters
        ----------
        sun : (3,) array_like, Sun or (azimuth_deg, elevation_deg)
            The new sun (:func:`as_sun_direction`).

        Returns
        -------
        dict of str to (H, W) float32
            ``v'`` in [0, 1] per view, in scene order.
        """
        return self._anchored(self._moved(as_sun_direction(sun, up=self.up)))

    def _moved(self, direction: np.ndarray) -> dict[str, np.ndarray]:
        """The caster's ``v'`` of every view at the unit sun ``direction``, fused (:meth:`visibility_at` before the
        anchor)."""
        out = self._per_view(lambda s: self._new_sun[s].visibility(direction, self.shadow_casters[s], self.tracer))
        return out if self._fusion is None else _fuse(self._fusion, out, run=self._per_view)

    def _anchored(self, visibility: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """``clip(v' + a, 0, 1)`` in place with each view's anchor ``a`` (:attr:`RelightConfig.anchor`)."""
        for s, (index, offset) in self._anchor.items():
            flat = visibility[s].reshape(-1)
            flat[index] = np.clip(flat[index] + offset, 0.0, 1.0)
        return visibility

    def _per_view(self, task: Callable[[Any], Any], items: Iterable[Any] | None = None) -> dict[str, Any]:
        """``{stem: task(item)}`` in scene order, on the constructor's ``threads``; ``items`` one per view in
        the scene's order (default: the stems)."""
        items = list(self.stems if items is None else items)
        if self._threads == 1 or len(self.stems) == 1:
            return dict(zip(self.stems, map(task, items), strict=True))
        with ThreadPoolExecutor(max_workers=min(self._threads, len(self.stems))) as pool:
            return dict(zip(self.stems, pool.map(task, items), strict=True))

    def proxy_visibility(self, sun: object) -> dict[str, np.ndarray]:
        """The proxy's own shadow at a new sun, as Step 1 computes it (paper Sec. 4; Fig. 11, right).

        The proxy sun visibility ``~v`` of every vertex (:func:`mvintrinsic.raytrace.sun_visibility`:
        attached shadow, then a shadow ray offset ``config.ray_offset`` along the normal), carried
        to the pixels as :func:`mvintrinsic.pixels.pixel_quantities` does (barycentric
        interpolation at the pixel ray's hit; misses take the nearest hit's). The baseline the
        caster improves on.

        Parameters
        ----------
        sun : (3,) array_like, Sun or (azimuth_deg, elevation_deg)

        Returns
        -------
        dict of str to (H, W) float32
        """
        direction = as_sun_direction(sun, up=self.up)
        proxy = self.tracer.proxy
        vertex = proxy_vertex_visibility(proxy.vertices, self._vertex_normals, direction, self.tracer,
                                         ray_offset=self.config.ray_offset, batch=self._batch)
        out = {}
        for view in self.scene.views:  # the camera rays cast again: the relighter keeps only their hit and t
            hits = self.tracer.intersect(view.camera.center, view.camera.pixel_rays(), batch=self._batch)
            values = self.tracer.interpolate(vertex[:, None], hits).reshape(*view.shape, 1)
            values = nearest_fill(values, hits.hit.reshape(view.shape))[..., 0]
            out[view.stem] = np.clip(values, 0.0, 1.0).astype(np.float32)
        return out

    def _check_visibility(self, visibility: object) -> dict[str, np.ndarray]:
        if not isinstance(visibility, Mapping):
            raise TypeError(f"visibility must be a mapping of view stem to (H, W) array, got {describe(visibility)}")
        missing = [s for s in self.stems if s not in visibility]
        if missing:
            raise ValueError(f"visibility: no visibility for views {missing}")
        out = {}
        for view in self.scene.views:
            v = as_array(visibility[view.stem], f"visibility[{view.stem!r}]", shape=view.shape, dtype=np.float32)
            if v.size and (v.min() < 0 or v.max() > 1):
                raise ValueError(f"visibility[{view.stem!r}] must lie in [0, 1], got range [{v.min()}, {v.max()}]")
            out[view.stem] = v
        return out

    # -- shading -------------------------------------------------------------------------------
    def layers(self, sun: object, *, visibility: Mapping[str, np.ndarray] | None = None) -> dict[str, IntrinsicLayers]:
        """The relit layers of every view (paper Sec. 8, "Moving Shadows and Adjusting Shading").

        Parameters
        ----------
        sun : (3,) array_like, Sun or (azimuth_deg, elevation_deg)
            The new sun (:func:`as_sun_direction`); above the horizon.
        visibility : mapping of str to (H, W) array_like, optional
            ``v'`` per view in [0, 1] instead of the caster's (:meth:`visibility_at`): e.g.
            :attr:`visibility` (the identity check) or :meth:`proxy_visibility`.

        Returns
        -------
        dict of str to IntrinsicLayers
            Per view in scene order: ``reflectance`` :attr:`reflectance`, ``sun_shading``
            ``S_sun'``, ``sky_shading`` ``S_sky'``, ``indirect_shading`` ``S_ind'``,
            ``visibility`` ``v'``, ``shadow_labels`` 255 where ``v' >= 0.5``, else 0, and 128
            where the layers hold no estimate.

        Raises
        ------
        ValueError
            If ``sun`` is at or below the horizon (the message names ``sun``) or ``visibility``
            lacks a view or has the wrong shape or range.
        """
        out = {}
        for stem, (v_new, cosine, sky, indirect) in self._relit(sun, visibility)[0].items():
            layers = self.decomposition.layers[stem]
            s_sun = self._new_sun[stem].sun_shading(cosine)
            labels = np.where(v_new >= 0.5, SHADOW_LABELS["lit"], SHADOW_LABELS["shadow"]).astype(np.uint8)
            labels[~self._known[stem]] = SHADOW_LABELS["undecided"]
            out[stem] = IntrinsicLayers(
                stem,
                reflectance=self.reflectance[stem],
                sun_shading=s_sun,
                sky_shading=(layers.sky_shading * sky).astype(np.float32),
                indirect_shading=(layers.indirect_shading * np.float32(indirect)).astype(np.float32),
                visibility=v_new,
                shadow_labels=labels,
            )
        return out

    def _paper_pixels(self, stem: str, rescued: np.ndarray, cosine: np.ndarray) -> _PaperPixels:
        """The paper's hypothesis at a view's :attr:`rescued` pixels: the cluster dropped as ``config.dropped``
        says, ``v'`` 1 there (capture ``v`` where :attr:`unexplained` or ``"static"``)."""
        layers, config = self.decomposition.layers[stem], self.config
        r, v = layers.reflectance, layers.visibility
        if config.dropped == "light":
            r, v = _into_light(layers, r, v, rescued)
        base, floor = _sun_terms(layers.sun_shading[rescued].astype(np.float64),
                                 self._radiance[stem].astype(np.float64), cosine[rescued], v[rescued])
        keep = self.unexplained[stem][rescued] if stem in self.unexplained else np.zeros(int(rescued.sum()), bool)
        normals = self.normals[stem][rescued]
        return _PaperPixels(r[rescued], base, floor, normals.astype(np.float32),
                            layers.sky_shading[rescued], layers.indirect_shading[rescued], self._radiance[stem],
                            np.where(keep | (config.dropped == "static"), v[rescued], 1.0).astype(np.float32),
                            _SphereLookup(normals, NORMAL_GRID_HEIGHT, self.up) if config.sky == "model" else None)

    def _prepare_new_sun(self, stem: str, cosine: np.ndarray, excluded: np.ndarray,
                         rescued: np.ndarray | None = None) -> _NewSun:
        """The sun-independent inputs of a new sun of one view, float32, once (module docstring).

        ``S_sun' = max(S_sun - L_sun max(0, n.d) + L_sun max(0, n.d'), min(S_sun, 0))`` where the
        pixel saw the sun (``v_sun > 0``), else ``L_sun max(0, n.d')``: the first two terms and
        the floor do not depend on the new sun ``d'``.
        """
        config = self.config
        layers = self.decomposition.layers[stem]
        base, floor = _sun_terms(layers.sun_shading.astype(np.float64), self._radiance[stem].astype(np.float64),
                                 cosine, self.visibility[stem])
        unknown = ~self._known[stem][..., None]
        image = self.scene.view(stem).image
        fill = np.where(unknown, np.nan_to_num(image, nan=0.0, posinf=0.0, neginf=0.0), 0.0).astype(np.float32)
        sky_pixels = None
        if config.sky_pixels != "input":  # no estimate, valid, the ray misses the proxy above the horizon
            rays = self.scene.view(stem).camera.pixel_rays()
            index = np.flatnonzero(unknown.ravel() & self.scene.view(stem).mask.ravel() & ~self._hits[stem].hit
                                   & (rays @ self.up > 0))
            sky_pixels = (_SkyPixels(index, rays[index], self.sun, how=config.sky_pixels, turbidity=self._turbidity,
                                     up=self.up) if len(index) else None)
        excluded = excluded if config.method == "multiview" else None
        blocked = self.shadow_casters[stem].completion_blocked(self.tracer, excluded)
        full = None  # the rescued pixels' own moved shadow is that of every sheet (their hypothesis)
        if self._belief < 1 and self.shadow_casters[stem]._mixed:  # and under the paper's hypothesis
            blocked = (blocked, self.shadow_casters[stem].completion_blocked(self.tracer, excluded, certain=True))
            full = None if rescued is None or not rescued.any() else rescued.ravel()
        return _NewSun(
            receivers=self.receivers[stem].reshape(-1, 3),  # a view, no copy
            shape=layers.shape, blocked=blocked,
            min_distance=self.completion_distance,
            config=config, batch=self._batch, normals=self.normals[stem].astype(np.float32), base=base,
            floor=floor, fill=fill, reflectance=self.reflectance[stem],
            fill_reflectance=np.where(unknown, np.float32(0.0), self.reflectance[stem]),  # so the fill adds to 0
            sky_shading=layers.sky_shading, indirect_shading=layers.indirect_shading,
            radiance=self._radiance[stem], known=self._known[stem],
            sky_lookup=(_SphereLookup(self.normals[stem], NORMAL_GRID_HEIGHT, self.up)
                        if config.sky == "model" else None),
            unexplained=self.unexplained.get(stem), capture=self.visibility[stem],
            static=(self.casters[stem].dropped if config.dropped == "static" and self.casters[stem].dropped.any()
                    else None), sky_pixels=sky_pixels, belief=self._belief, full=full)

    def _environment(self, direction: np.ndarray) -> tuple[tuple[str, np.ndarray], float | None]:
        """The environment's change at a new sun: ``(how, table)`` for :meth:`_NewSun.sky_factor`,
        and the factor of ``S_ind`` (None with ``sky="model"``: it needs every view's ``v'``,
        :meth:`_indirect_factor`)."""
        if self.config.sky == "paper":
            gain, indirect_factor = paper_environment_factors(self.sun, direction, up=self.up)
            return ("paper", gain), float(indirect_factor)
        return ("model", _grid_ratio(_sky_irradiance_grid(direction, self._turbidity, self.up), self._sky_grid)), None

    def _indirect_factor(self, irradiance: float) -> float:
        """``sky="model"``: S_ind follows the sun irradiance of the receivers, the mean of
        ``max(0, n.d') v'`` over that of ``max(0, n.d) v`` (over every view's pixels with an estimate)."""
        return float(irradiance / self._sun_irradiance if self._sun_irradiance > 0 else 1.0)

    def _relit(self, sun: object, visibility: Mapping[str, np.ndarray] | None
               ) -> tuple[dict[str, tuple[np.ndarray, np.ndarray, np.ndarray, float]], tuple[str, np.ndarray], float]:
        """Per view ``(v', max(0, n . d'), S_sky' / S_sky, S_ind' / S_ind)``, the core of :meth:`layers` and
        :meth:`render`: (H, W) float32 twice; sky factor (3,) float32 (``sky="paper"``) or (H, W, 3) (``"model"``);
        scalar. And the environment's change (:meth:`_environment`) and ``S_ind' / S_ind``."""
        direction = as_sun_direction(sun, up=self.up)
        new_vis = self.visibility_at(direction) if visibility is None else self._check_visibility(visibility)
        d32 = direction.astype(np.float32)
        new_cosine = self._per_view(lambda s: self._new_sun[s].cosine(d32))
        environment, indirect_factor = self._environment(direction)
        if indirect_factor is None:
            irradiance = self._per_view(lambda s: self._new_sun[s].irradiance(new_cosine[s], new_vis[s]))
            indirect_factor = self._indirect_factor(sum(irradiance[s] for s in self.stems))
        return self._per_view(lambda s: (new_vis[s], new_cosine[s], self._new_sun[s].sky_factor(environment),
                                         indirect_factor)), environment, indirect_factor

    def render(self, sun: object, *, visibility: Mapping[str, np.ndarray] | None = None,
               fill: str = "input") -> dict[str, np.ndarray]:
        """Relit images of every view: ``R (v' S_sun' + S_sky' + S_ind')`` (Eq. 1 at the new sun).

        With a ``client`` (:class:`Relighter`), one task per view on the cluster (two with
        ``sky="model"``, whose ``S_ind'`` needs every view's ``v'``); the images are identical.

        Parameters
        ----------
        sun : (3,) array_like, Sun or (azimuth_deg, elevation_deg)
            The new sun (:func:`as_sun_direction`); above the horizon.
        visibility : mapping of str to (H, W) array_like, optional
            See :meth:`layers`. Given, the :attr:`rescued` pixels are not mixed.
        fill : {"input", "zero"}, optional
            What the pixels without an estimate (the layers hold 0 there: the sky, invalid pixels,
            pixels the decomposition took for sky) show: the view's input image (its non-finite
            values as 0), its sky pixels recoloured (:attr:`RelightConfig.sky_pixels`), or 0.

        Returns
        -------
        dict of str to (H, W, 3) float32
            Linear RGB in the images' units, per view in scene order. At the capture sun with
            ``visibility=self.visibility`` it is ``reflectance * shading`` of the decomposition
            wherever the layers hold an estimate (to float32 rounding).
        """
        if fill not in ("input", "zero"):
            raise ValueError(f"fill must be 'input' or 'zero', got {fill!r}")
        direction = as_sun_direction(sun, up=self.up)
        d32 = direction.astype(np.float32)
        blend = bool(self._paper) and visibility is None  # the rescued pixels mix the paper's image
        if self._tasks is not None:
            images, environment, indirect_factor = self._render_on_cluster(direction, visibility, fill)
            if not blend:
                return images
            return blend_rescued(images, {s: paper(d32, environment, indirect_factor)
                                          for s, paper in self._paper.items()},
                                 self.rescued, self.config.lost_occluders.belief)
        relit, environment, indirect_factor = self._relit(direction, visibility)

        def image(s: str) -> np.ndarray:
            out = self._new_sun[s].image(*relit[s], fill, direction)
            if blend and s in self._paper:
                _blend_into(out, self._rescued_pixels[s], self._paper[s](d32, environment, indirect_factor),
                            self.config.lost_occluders.belief)
            return out

        return self._per_view(image)

    def _render_on_cluster(self, sun: object, visibility: Mapping[str, np.ndarray] | None, fill: str
                           ) -> tuple[dict[str, np.ndarray], tuple[str, np.ndarray], float]:
        """:meth:`render` as one task per view on the client's cluster (the same per-view steps as :meth:`_relit`);
        with the environment's change and ``S_ind' / S_ind``."""
        tasks, remote = self._tasks, self._remote
        direction = as_sun_direction(sun, up=self.up)
        shadow_sun = as_sun_direction(direction, up=self.up)  # as visibility_at receives it in _relit
        given = None if visibility is None else tasks.scatter(self._check_visibility(visibility))
        args = {s: (remote["new_sun"][s], remote["casters"][s], remote["tracer"], direction, shadow_sun,
                    None if given is None else given[s]) for s in self.stems}
        if visibility is None and (self._fusion is not None or self._anchor):  # every view's v' first, then here
            terms = tasks.gather(tasks.submit("relight-shadows", _new_sun_terms, args))
            moved = {s: terms[s][0] for s in self.stems}
            given = tasks.scatter(self._anchored(moved if self._fusion is None else _fuse(self._fusion, moved)))
            args = {s: (*args[s][:-1], given[s]) for s in self.stems}
        environment, indirect_factor = self._environment(direction)
        if indirect_factor is not None:
            futures = tasks.submit("relight", _render_view, args, environment=environment,
                                   indirect_factor=indirect_factor, fill=fill)
        else:  # S_ind' needs the irradiance of every view at the new sun first
            terms = tasks.submit("relight-shadows", _new_sun_terms, args)
            irradiance = tasks.gather(tasks.submit("relight-irradiance", _irradiance_task,
                                                   {s: (remote["new_sun"][s], terms[s]) for s in self.stems}))
            indirect_factor = self._indirect_factor(sum(irradiance[s] for s in self.stems))
            futures = tasks.submit("relight", _image_task, {s: (remote["new_sun"][s], terms[s]) for s in self.stems},
                                   environment=environment, indirect_factor=indirect_factor, fill=fill,
                                   direction=direction)
        return tasks.gather(futures), environment, indirect_factor

    def __repr__(self) -> str:
        return f"Relighter({len(self.stems)} views, sky={self.config.sky!r}, {self.caster!r})"


def relight(decomposition: Decomposition, scene: Scene, *, sun: object,
            config: RelightConfig | None = None, client: Any = None) -> dict[str, np.ndarray]:
    """Relight every view of a scene under a new sun (paper Sec. 8): ``Relighter(...).render(sun)``.

    Parameters
    ----------
    decomposition : Decomposition
        The layers of every view of ``scene`` (:func:`mvintrinsic.decompose`).
    scene : Scene
    sun : (3,) array_like, Sun or (azimuth_deg, elevation_deg)
        The new sun (:func:`as_sun_direction`), above the horizon.
    config : RelightConfig, optional
    client : distributed.Client, optional
        Render the views as one task per view on a dask cluster (:class:`Relighter`); the images
        are identical.

    Returns
    -------
    dict of str to (H, W, 3) float32
        Relit linear RGB per view, in scene order.

    Raises
    ------
    ValueError
        If ``sun`` is at or below the horizon (the message names ``sun``) or the decomposition's
        views are not the scene's (the message names ``decomposition``).
    """
    direction = as_sun_direction(sun, up=scene.up if isinstance(scene, Scene) else (0.0, 0.0, 1.0))
    return Relighter(decomposition, scene, config=config, client=client).render(direction)
