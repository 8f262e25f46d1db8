"""Relighting: shadow receivers, a 2.5D shadow caster, moving cast shadows and relit shading (Sec. 8).

The proxy's own shadows do not match the shadow boundaries of the photographs (paper Fig. 4b), so
the paper relights with a *caster* built from the shadows of the image itself (Duchêne et al.
2015, Sec. 8, "Creating Shadow Receiver and Caster Geometry" and "Moving Shadows and Adjusting
Shading"). This module builds that geometry, computes the new shadow layer for any sun, and
relights the views (:class:`Relighter`, :func:`relight`).

**Receiver** (:func:`receiver_depth`, :func:`receiver_points`). Every pixel gets the distance along
its camera ray to the proxy; pixels whose ray misses take the value of the nearest pixel that hits.

**Shadow pixels** (:func:`shadow_pixels`). A pixel is in shadow when Step 3 labels it shadow or
when its visibility ``v_sun < tau_s`` (``tau_s = 0.8``): the propagated ``v_sun`` keeps fine
shadow details the binary labelling loses.

**Caster** (:func:`build_caster`). From the receiver point ``P_p`` of each shadow pixel a ray
toward the sun ``d`` is traced against the proxy; its first hit at distance ``t_p`` is where the
occluder is. Shadow pixels are grouped into 8-connected clusters; a cluster smaller than
``min_cluster`` pixels (100) or in which fewer than ``min_proxy_hits`` (30%) of the rays hit the
proxy is a mislabelling and is dropped. In the kept clusters a pixel whose ray missed takes the
``t`` of the nearest kept pixel whose ray hit. The kept pixels are triangulated in image space and
lifted toward the sun, ``C = P + t d``: a 2.5D sheet whose shadow at the capture sun is the
shadow of the image (up to pixels along depth edges). Last, a ray toward the sun is cast from the
receiver point of every lit pixel against the caster; a triangle first hit by more than
``epsilon`` (3) of them contradicts the image (a lit pixel it would shade) and is removed. As
every quad re-projects onto its own pixel's footprint at the capture sun, only triangles that an
inconsistent receiver places over several lit pixels reach that count.

**Moving shadows** (:class:`ShadowCaster`). For a new sun, a ray from every receiver point toward
it is tested against the caster (Embree, via open3d, the structure built once per caster). Where
the caster has no coverage the proxy's shadow completes it, and a Gaussian blur of ``blur``
pixels softens the result and fills the cracks between disconnected triangles. The casters of
several views can be merged into one (:func:`merge_casters`) that shades every view. With
``method="multiview"`` (the default) the lit pixels of every view vote against every caster and
against the proxy's completion (below, "Votes of every view").

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

* in-shadow reflectance fix: the pixels of dropped shadow clusters (too small or unsupported by
  the proxy, :func:`build_caster`) are mislabellings the paper brings "in light using the v_sun
  layer": their ``v_sun`` becomes 1 and their reflectance ``R (v_sun S_sun + S_env) / (S_sun +
  S_env)``, i.e. ``I / (S_sun + S_sky + S_ind)`` (Eq. 2 with ``v_sun = 1``); the image is
  unchanged at the capture sun.

At the capture sun with the (fixed) visibility of the layers every factor is 1 and every
correction 0: the relit image is ``R S_tot``, the decomposition's reconstruction, exactly
(``tests/test_relight.py``).

Deviations from the paper, with their reasons
---------------------------------------------
* **Receiver by ray casting.** The paper gives each pixel "the depth value of the closest projected
  3D point"; here the pixel ray is intersected with the proxy through the project's
  :class:`~mvintrinsic.raytrace.Tracer` (triangles of a mesh, surfels of a point cloud), which is
  the same depth without holes between projected points, and misses are filled as the paper fills
  caster distances (nearest valid pixel, ``scipy.ndimage.distance_transform_edt``).
* **One quad per pixel footprint.** "We triangulate the shadow pixels in image space" is read as
  a mesh over the kept pixels' *footprints*: each kept pixel is the quad (two triangles) between
  its four pixel corners. A corner lies on the camera ray through that pixel corner, at a
  receiver distance ``s_c``, and is lifted by a caster distance ``t_c``; both average, over the
  kept pixels touching the corner that lie on the same surface as the pixel, each one's linear
  extrapolation to the corner (its value plus its image gradient times the half-pixel offset).
  Two kept pixels are on the same surface when their receiver distances differ by at most
  :data:`SURFACE_JUMP` (5%) and their caster distances by at most :data:`CASTER_JUMP` (25%, or 8
  pixel footprints). On a smooth surface every touching pixel extrapolates to the same corner, so
  neighbouring quads share their corners (the sheet is closed and moves as one when the sun
  moves), and the corners on the outline of a shadow sit on the receiver rather than half a pixel
  inside it; across a jump the quads separate instead of stretching. Why not the plain reading
  (one vertex per shadow pixel centre, two triangles per 2x2 block of shadow pixels): it puts
  every outline pixel of the shadow on the mesh's edge, where the pixel's own ray grazes a vertex
  and hits or misses at float32 rounding, and stretches triangles across every depth edge.
  Measured on ``tests/test_relight.py``'s box-on-a-plane scene (96x72, exact proxy and exact
  shadow mask, 11 pairs of camera and sun, elevations 30-65 degrees), the mean IoU of the caster's
  shadow with the exact shadow, at the capture sun and after a 15-degree azimuth change, is
  0.93 and 0.87 with one vertex per pixel centre, 0.92 and 0.89 with footprint corners averaged
  without extrapolation, 0.97 and 0.65 with unshared per-pixel quads, and 0.97 and 0.93 with this
  construction. The two thresholds were chosen on those cases; they are module constants, not
  paper parameters. Four vertices are stored per kept pixel (shared corners are equal bit for bit,
  not merged).
* **Cluster filtering before filling.** The paper does not say in which order it filters clusters
  and fills missed distances; here clusters are filtered first, so a kept pixel never borrows the
  distance of a dropped (mislabelled) cluster. A cluster with no proxy hit at all is always
  dropped (it cannot be lifted), whatever ``min_proxy_hits``.
* **Ray offset.** Rays start ``ray_offset`` metres (0.02, about a TSDF voxel, as in Step 1) along
  the sun direction from the receiver points, against self-intersection with the proxy; the
  caster distances are measured from the receiver point itself.
* **Which lit pixels vote.** By default every pixel outside the shadow mask casts an ``epsilon``
  ray (pixels of dropped clusters do not: they were shadow in the input). The caller may pass its
  own ``lit`` mask, e.g. only pixels the proxy covers and Step 3 labels lit (pixels whose ray
  misses the proxy, such as the sky, have filled receivers floating in the air).
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

Votes of every view (``method="multiview"``, beyond the paper)
---------------------------------------------------------------
A receiver point lit in *any* photograph is lit; the paper lets only the caster's own view say so.
Two uses of that evidence, both measured with ``benchmarks/bench_relight.py`` on four 480x360
scenes with MVS-like proxies (``docs/relight.md`` gives every figure):

* **Every view votes against every caster.** After :func:`build_caster`, each view's caster is
  tested again with the capture-sun rays of the lit pixels of all views
  (:func:`remove_contradicted`): triangles the own view's few rays could not condemn (a single
  pixel footprint is hit by one or two rays of its own view) reach ``epsilon`` with several views.
* **The proxy completion is voted on too.** The paper's epsilon test applied to the proxy
  (:func:`contradicted_primitives`): a proxy triangle first hit by more than ``epsilon`` lit rays
  of the views at the capture sun completes no shadow later. These are the proxy's
  reconstruction noise (bumps of a wall shading the wall), wrongly filled holes and light-letting
  foliage remnants. And hits nearer than ``completion_distance`` (0.6 m) along the new sun ray
  complete nothing: a noisy proxy shades itself there when the sun turns, while the true
  short-range shadows the image shows are the caster's. On courtyard_s1 with the true layers and
  the paper's checks, the completion put 3.8% of the non-sky pixels into false shadow at the
  capture sun (the caster itself 1.8%, while 3.0% were missed). Relit PSNR with the true layers
  at azimuth +15 degrees on courtyard_s1: 20.28 dB with the paper's checks, 21.15 with every
  view's votes but no completion distance, 23.19 with both (the input unchanged: 21.32).
* **Each view keeps its own caster** (``casters="own"``, as the paper): a merged caster (the
  union of all views') measured 0.6-3.1 dB lower with the true layers on courtyard_s1 (other
  views' sheets, lifted from receivers the proxy places wrongly under lost foliage, shade the
  view's lit pixels), so the merge is an option, not the default.

Speed (beyond the paper)
------------------------
Building costs one pass per view; every new sun then costs, per view, the shadow rays and a few
array passes. At 1000x750 (courtyard_1000, 6 views, a 484k-triangle proxy, 2 cores) a new sun
took 0.30 s per view with one caster ray and one proxy ray per pixel; now 0.086 s:

* **Rays only where the visibility varies** (:attr:`RelightConfig.ray_stride`): both queries run
  on a grid of every second pixel, then on every pixel of the grid cells whose corners disagree
  and of their neighbours (0.39 of the pixels at 1000x750). Against every pixel
  (``bench_relight.py --stride``, ``benchmarks/results/relight_stride.json``), the sharp shadow
  state of 0.02-0.10% of the pixels changes at 480x360 (four scenes, five suns each) and
  0.04-0.05% at 1000x750 (four suns), isolated pixels the blur mostly absorbs (0-0.003% of the
  pixels cross 0.5 after it), and the relit PSNR by -0.010 to +0.007 dB; stride 3 changed 0.05-0.13% and
  -0.019 to +0.001 dB for 15% less time, so 2 is the default. The exact meshes' own shadows,
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

Ordering the rays in 8x8 or 16x16 tiles instead of rows changed the Embree time by under 6%, and
rendering the views in two threads by 5% (Embree already uses both cores): neither is done.

Relit shading: deviations and readings, with their reasons. Numbers are PSNR (dB) against the
demo's path-traced relit renders (sun azimuth +15 degrees / elevation +10 degrees), as
``benchmarks/bench_relight.py`` scores them (linear RGB, non-sky pixels, clipped at the truth's
99.5th percentile):

* **The sun term keeps the layers' own S_sun.** The paper adjusts "the sun shading intensity
  according to a cosine factor with respect to elevation and the horizontal plane", one factor
  for the image; the per-pixel ``L_sun max(0, n . d')`` with the proxy's normals is its natural
  refinement, but the layers' ``S_sun`` is not ``L_sun max(0, n . d)`` of the proxy (Step 3
  propagates it guided by the image; the ground truth holds the true normals'), so that term
  alone would not give the image back at the capture sun. Adding only the *change* of the
  proxy's term keeps the identity exact and the layers' detail. With the true layers and the
  true relit visibility: 27.02 / 26.10 with the change, 22.59 / 20.72 with
  ``L_sun max(0, n . d')`` alone, 24.58 / 23.44 with the ratio ``S_sun max(0, n . d') / max(0,
  n . d)``; the full pipeline 23.55 / 22.75, 20.36 / 19.18 and 22.24 / 21.40.
* **The environment "paper" is our reading**: the paper gives no formula (see above and
  :func:`paper_environment_factors`). ``L_sun`` keeps its colour and intensity, as in the paper
  (Sec. 9.4: the relit shadows "have the same color as the shadow in the input image because they
  are computed from an estimate of the same sun color and sky model"); on the demo the renderer's
  sun is brighter at a higher elevation and the lit pixels at +10 degrees come out 4.6% darker
  than the truth (median).
* **Default "paper" by measurement**: on the demo it scores higher than ``"model"`` in every row:
  the full pipeline 23.55 / 22.75 against 23.45 / 22.18, the true layers with the true shadow
  27.03 / 26.08 against 26.83 / 25.90. With the true layers, in the pixels in shadow in both
  renders, the median ratio of the new to the old ``S_env`` (RGB) is 1.07 / 1.05 / 1.05 and
  0.97 / 1.03 / 1.10 with ``"model"``, 1 / 1 / 1 and 0.99 / 1.00 / 1.03 with ``"paper"``, and
  1.08 / 1.07 / 1.07 and 0.97 / 1.00 / 1.06 in the truth: ``"model"`` follows the azimuth change
  (those pixels score 27.14 against 26.88) but overshoots the blue shift of the higher sun
  (26.25 against 26.48), and loses on the pixels lit in both (29.74 against 30.16, 27.38 against
  27.58).
* **Sky irradiance ratio, not re-integration**: ``"model"`` scales the layers' ``S_sky``, which
  holds the occlusion Step 1 traced, by the ratio of *unoccluded* sky irradiances: it assumes the
  occluded share of the sky changes in proportion. Re-integrating with Step 1's hemisphere rays
  would need Step 1's per-vertex radiance and environment map, which a decomposition does not
  carry. The scale ``k`` of Eq. (4) cancels; the absolute zenith luminance of Preetham et al.
  (Appendix A.2), which the relative model leaves to ``k``, does not, and is applied.
* **Pixels without an estimate** (the layers hold 0: sky, invalid pixels, pixels the
  decomposition took for sky) show the input image in :meth:`Relighter.render` (``fill``); the
  paper's recolouring of the sky near the horizon is not done.
* **On the demo the paper's caster keeps no cluster**: the demo's proxy lost 90% of the foliage
  and of the thin structures, so the sun rays of the tree's and the fence's shadows miss it and
  every large cluster has fewer than 30% proxy hits (the largest 26.5%), and the others are under
  100 pixels: all are dropped and brought into light, and the relit shadows are the proxy's
  completion only. Keeping them (``min_proxy_hits=0``) lowers the scores (the true layers 21.31 /
  20.56 against 24.11 / 23.16), mostly through the merging (23.46 / 22.34 with each view's own
  caster): the other views' sheets shade a view's lit pixels, 2520 of them in view_000 at the
  capture sun, and about half of the triangles responsible come from pixels whose receiver lies
  more than 10% off the surface they show (foliage and thin structures the proxy lacks). Each
  triangle is a pixel footprint, hit by a few of the view's lit rays at most, so the
  ``epsilon`` rule does not catch them (applied to the merged caster with every view's lit
  pixels, it removes 300 of 41676 triangles).

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

import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from types import MappingProxyType
from typing import Any

import numpy as np
from scipy import ndimage

from ._cluster import _as_client, _Rebuilt, _ViewTasks
from ._validation import as_array, as_unit_vector, config_or_default, describe, is_real
from .camera import Camera
from .image_model import LUMINANCE_WEIGHTS
from .pixels import nearest_fill
from .raytrace import DEFAULT_BATCH, Tracer, triangle_scene, vertex_normals
from .raytrace import sun_visibility as proxy_vertex_visibility
from .results import SHADOW_LABELS, Decomposition, IntrinsicLayers
from .scene import Scene, Sun
from .skymodel import envmap_directions, horizontal_frame, preetham_relative_rgb, texel_solid_angles

__all__ = [
    "NORMAL_GRID_HEIGHT",
    "RGB_WAVELENGTHS_UM",
    "CASTER_MODES",
    "RELIGHT_METHODS",
    "SKY_ADJUSTMENTS",
    "SKY_GRID_HEIGHT",
    "SKY_RATIO_FLOOR",
    "Caster",
    "RelightConfig",
    "Relighter",
    "ShadowCaster",
    "as_sun_direction",
    "build_caster",
    "contradicted_primitives",
    "merge_casters",
    "paper_environment_factors",
    "receiver_depth",
    "receiver_normals",
    "receiver_points",
    "relight",
    "remove_contradicted",
    "shadow_pixels",
    "sky_irradiance_ratio",
]

#: 8-connectivity of the shadow clusters.
_EIGHT = np.ones((3, 3), dtype=bool)

#: ``primitive_ids`` of a ray that hits nothing (open3d's ``RaycastingScene.INVALID_ID``).
_INVALID_ID = np.iinfo(np.uint32).max

#: The environment adjustments of :attr:`RelightConfig.sky` (module docstring, "Adjusting shading").
SKY_ADJUSTMENTS = ("model", "paper")

#: The caster checks of :attr:`RelightConfig.method` (module docstring, "Votes of every view").
RELIGHT_METHODS = ("multiview", "paper")

#: Which caster shades a view, :attr:`RelightConfig.casters`.
CASTER_MODES = ("own", "merged")


@dataclass(frozen=True)
class RelightConfig:
    """Options of the relighting geometry (paper Sec. 8), the paper's values as defaults.

    Parameters
    ----------
    tau_s : float
        A pixel with ``v_sun < tau_s`` counts as shadow besides the shadow labels; in [0, 1].
        0.8: "We used tau_s = 0.8 for all our results."
    epsilon : int
        A caster triangle first hit by more than ``epsilon`` sun rays from lit pixels is removed;
        >= 0. 3: "We used epsilon = 3 for all our results."
    min_cluster : int
        Shadow clusters (8-connected) of fewer pixels are dropped; >= 1. 100: "less than 100
        pixels".
    min_proxy_hits : float
        Shadow clusters in which a smaller share of the pixels' sun rays hit the proxy are
        dropped; in [0, 1]. 0.3: "less than 30% of the pixels yield an intersection".
    blur : float
        Standard deviation, pixels, of the Gaussian blur of the new shadow layer (0: none); >= 0.
        The paper applies "a small Gaussian blur" without a value; 1 pixel softens the edge to
        about the width of a photographed penumbra at these resolutions and closes one-pixel
        cracks. A per-pixel penumbra from the sun's angular size and the occluder distance
        instead scored 0.08-1.07 dB lower, and added in quadrature to the 1 px within 0.01 dB of
        it (``benchmarks/bench_relight.py --softness``, four 480x360 scenes, 20 suns).
    ray_offset : float
        Metres a sun ray starts from its receiver point along the sun direction, against
        self-intersection; >= 0. Not in the paper; 0.02 as Step 1's ``ray_offset`` (about a TSDF
        voxel).
    normal_smoothing : float
        Standard deviation (metres) of the smoothing of the proxy's vertex normals that give the
        receivers' ``max(0, cos w_sun)`` and the proxy's sun visibility at the new sun
        (:func:`mvintrinsic.raytrace.smooth_normals`); >= 0, 0: the proxy's own normals. Not in
        the paper; 0.4 as Step 1's :attr:`~mvintrinsic.env_shading.Step1Config.normal_smoothing`,
        so that the relit ``S_sun`` uses the normals the decomposition used.
    sky : {"model", "paper"}
        How the environment shading follows the sun (:data:`SKY_ADJUSTMENTS`, module docstring,
        "Adjusting shading"). ``"paper"``: our reading of the paper's adjustment, a red shift of
        ``S_sky`` and ``S_ind`` scaled like the horizontal sun irradiance
        (:func:`paper_environment_factors`). ``"model"``: ``S_sky`` scaled per pixel normal by
        the fitted sky model's irradiance at the new sun over the old one
        (:func:`sky_irradiance_ratio`), ``S_ind`` by the change of the sun irradiance on the
        receivers. Default ``"paper"``, chosen by measurement: on the demo's path-traced relit
        renders it scores higher in every row of ``benchmarks/bench_relight.py`` (by 0.1 to 0.6
        dB; module docstring).
    turbidity : float
        Turbidity of the sky model used by ``sky="model"`` when the decomposition carries no
        fitted sky (``decomposition.lighting.sky is None``, e.g. a ground truth); > 0. 3.5,
        Step 1's starting value (:class:`~mvintrinsic.skymodel.SkyConfig`), "the turbidity of a
        clear sky". Only the shape of the sky matters: its scale cancels in the ratio.
    light_dropped : bool
        Bring the pixels of dropped shadow clusters into light, as the paper does ("We adjust the
        reflectance of such pixels to bring them in light using the v_sun layer"): their
        ``v_sun`` becomes 1 and their reflectance ``I / (S_sun + S_sky + S_ind)``
        (:class:`Relighter`). False keeps the layers as they are.
    method : {"multiview", "paper"}
        How the views' evidence is used (:data:`RELIGHT_METHODS`, module docstring, "Votes of
        every view"). ``"paper"``: each view's caster is checked against that view's lit pixels
        only, and the proxy completes every shadow it casts on primitives the caster does not
        stand for. ``"multiview"`` (default, beyond the paper): the lit pixels of *every* view
        vote against every caster triangle and against every proxy triangle (a proxy triangle
        first hit by more than ``epsilon`` of their capture-sun rays casts no completion
        shadow), and the completion ignores proxy hits nearer than ``completion_distance``.
        Chosen by measurement (``benchmarks/bench_relight.py``, module docstring).
    casters : {"own", "merged"}
        ``"own"`` (default): every view is shaded by its own caster, as in the paper (its votes
        still come from every view with ``method="multiview"``). ``"merged"``: one caster, the
        union of all the views' (:func:`merge_casters`), shades every view. Chosen by
        measurement: other views' caster pieces shade lit pixels of a view (module docstring).
    completion_distance : float
        ``method="multiview"``: proxy hits nearer than this many metres along the new sun ray
        complete no shadow; >= 0. Self-shadowing by the proxy's own reconstruction noise sits
        there, while the short-range shadows the image shows (recesses, ledges) are already in
        the caster. 0.6 (module docstring: 0.3, 0.6 and 1.0 measured).
    ray_stride : int
        The new sun's shadow rays are cast from every ``ray_stride``-th pixel along both image
        axes, then from every pixel of the cells whose four sampled corners disagree (a shadow
        edge crosses them) and of their neighbour cells; a cell far from any such cell takes
        its corners' state. 1 casts from every pixel; >= 1. Not in the paper: the ray budget is
        spent only where the visibility varies, which halves the shadow time of a new sun at
        1000x750, while a shadow thinner than ``ray_stride`` pixels that touches no sampled
        pixel, far from any other edge, is lost (module docstring, "Speed": 2 changes the relit
        PSNR by -0.010 to +0.007 dB against 1).
    """

    tau_s: float = 0.8
    epsilon: int = 3
    min_cluster: int = 100
    min_proxy_hits: float = 0.3
    blur: float = 1.0
    ray_offset: float = 0.02
    normal_smoothing: float = 0.4
    sky: str = "paper"
    turbidity: float = 3.5
    light_dropped: bool = True
    method: str = "multiview"
    casters: str = "own"
    completion_distance: float = 0.6
    ray_stride: int = 2

    def __post_init__(self) -> None:
        for name, allowed in (("method", RELIGHT_METHODS), ("casters", CASTER_MODES)):
            value = getattr(self, name)
            if not isinstance(value, str) or value not in allowed:
                raise ValueError(f"{name} must be one of {', '.join(map(repr, allowed))}, got {value!r}")
        if not isinstance(self.sky, str) or self.sky not in SKY_ADJUSTMENTS:
            raise ValueError(f"sky must be one of {', '.join(map(repr, SKY_ADJUSTMENTS))}, got {self.sky!r}")
        if not is_real(self.turbidity) or not 0.0 < self.turbidity < np.inf:
            raise ValueError(f"turbidity must be a finite number > 0, got {self.turbidity!r}")
        object.__setattr__(self, "turbidity", float(self.turbidity))
        if not isinstance(self.light_dropped, (bool, np.bool_)):
            raise ValueError(f"light_dropped must be a bool, got {describe(self.light_dropped)}")
        object.__setattr__(self, "light_dropped", bool(self.light_dropped))
        for name, least in (("epsilon", 0), ("min_cluster", 1), ("ray_stride", 1)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
                raise ValueError(f"{name} must be an integer >= {least}, got {value!r}")
            object.__setattr__(self, name, int(value))
        for name in ("tau_s", "min_proxy_hits"):
            value = getattr(self, name)
            if not is_real(value) or not 0.0 <= value <= 1.0:
                raise ValueError(f"{name} must be a number in [0, 1], got {value!r}")
            object.__setattr__(self, name, float(value))
        for name in ("blur", "ray_offset", "completion_distance", "normal_smoothing"):
            value = getattr(self, name)
            if not is_real(value) or not 0.0 <= value < np.inf:
                raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
            object.__setattr__(self, name, float(value))


@dataclass(frozen=True, eq=False)
class Caster:
    """A shadow-caster mesh in the world frame (paper Sec. 8, Fig. 9 right).

    Parameters
    ----------
    vertices : (N, 3) float64
        World-frame vertex positions, metres.
    triangles : (M, 3) int32
        Vertex indices of the triangles (orientation is meaningless: rays hit both sides).
    proxy_primitives : (K,) int64
        Sorted indices of the proxy primitives (:attr:`RayHits.triangle
        <mvintrinsic.raytrace.RayHits>`: mesh triangles, or surfel points of a point cloud) hit by
        the sun rays of the kept shadow pixels: the occluders the caster stands for. Proxy
        completion (:meth:`ShadowCaster.sun_visibility`) applies to the others.
    shadow : (H, W) bool or None
        The shadow pixels the caster was built from (kept clusters); ``None`` for a merged caster.
    dropped : (H, W) bool or None
        Shadow pixels of the dropped clusters (too small, or too few proxy hits): mislabellings the
        paper brings back into light; ``None`` for a merged caster.
    n_clusters : int
        Number of 8-connected shadow clusters in the input mask.
    n_small : int
        Clusters dropped for having fewer than ``min_cluster`` pixels.
    n_unsupported : int
        Clusters of at least ``min_cluster`` pixels dropped for a share of proxy hits below
        ``min_proxy_hits`` (or no hit at all).
    n_removed : int
        Triangles removed for being first hit by more than ``epsilon`` rays from lit pixels.

    Notes
    -----
    Instances are immutable; arrays are read-only.
    """

    vertices: np.ndarray
    triangles: np.ndarray
    proxy_primitives: np.ndarray
    shadow: np.ndarray | None
    dropped: np.ndarray | None
    n_clusters: int
    n_small: int
    n_unsupported: int
    n_removed: int

    def __post_init__(self) -> None:
        vertices = as_array(self.vertices, "vertices", shape=(None, 3), dtype=np.float64)
        triangles = as_array(self.triangles, "triangles", shape=(None, 3), dtype=np.int32)
        if len(triangles) and (triangles.min() < 0 or triangles.max() >= len(vertices)):
            raise ValueError(f"triangles index vertices outside [0, {len(vertices)})")
        primitives = as_array(self.proxy_primitives, "proxy_primitives", shape=(None,), dtype=np.int64)
        object.__setattr__(self, "vertices", vertices)
        object.__setattr__(self, "triangles", triangles)
        object.__setattr__(self, "proxy_primitives", primitives)
        if (self.shadow is None) != (self.dropped is None):
            raise ValueError("shadow and dropped must both be masks or both be None")
        if self.shadow is not None:
            shadow = as_array(self.shadow, "shadow", shape=(None, None), dtype=bool)
            dropped = as_array(self.dropped, "dropped", shape=shadow.shape, dtype=bool)
            object.__setattr__(self, "shadow", shadow)
            object.__setattr__(self, "dropped", dropped)
        for name in ("n_clusters", "n_small", "n_unsupported", "n_removed"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
                raise ValueError(f"{name} must be an integer >= 0, got {value!r}")
            object.__setattr__(self, name, int(value))

    def __repr__(self) -> str:
        return (
            f"Caster({len(self.vertices)} vertices, {len(self.triangles)} triangles, "
            f"clusters {self.n_clusters} (dropped {self.n_small} small, {self.n_unsupported} unsupported), "
            f"{self.n_removed} triangles removed)"
        )


# ---------------------------------------------------------------------------------------------
# argument checks
# ---------------------------------------------------------------------------------------------

def _check_camera(camera: object) -> Camera:
    if not isinstance(camera, Camera):
        raise TypeError(f"camera must be a Camera, got {describe(camera)}")
    return camera


def _check_tracer(tracer: object, name: str = "tracer") -> Tracer:
    if not isinstance(tracer, Tracer):
        raise TypeError(f"{name} must be a Tracer, got {describe(tracer)}")
    return tracer


def _check_sun(sun_direction: object, up: object) -> np.ndarray:
    """``sun_direction`` as a unit vector, refused when at or below the horizon of ``up``."""
    sun = as_unit_vector(sun_direction, "sun_direction")
    up = as_unit_vector(up, "up")
    if float(sun @ up) <= 0.0:
        elevation = np.degrees(np.arcsin(np.clip(sun @ up, -1.0, 1.0)))
        raise ValueError(
            f"sun_direction must be above the horizon (sun_direction . up > 0), got elevation "
            f"{elevation:.2f} degrees (sun_direction {np.round(sun, 4).tolist()}, up {up.tolist()})"
        )
    return sun


def _image_array(value: object, name: str, shape: tuple[int, ...] | None, dtype: type, *,
                 trailing: tuple[int, ...] = (), finite: bool = True) -> np.ndarray:
    """``value`` as a read-only array of ``shape + trailing`` (``shape`` None: any (H, W))."""
    expected = (*(shape if shape is not None else (None, None)), *trailing)
    return as_array(value, name, shape=expected, dtype=dtype, finite=finite)


def _check_rays(origins: object, sun_direction: object) -> tuple[np.ndarray, np.ndarray]:
    """``origins`` as (N, 3) float64 and ``sun_direction`` as a unit vector, each error naming its argument."""
    return (as_array(origins, "origins", shape=(None, 3), dtype=np.float64),
            as_unit_vector(sun_direction, "sun_direction"))


def _rays(origins: np.ndarray, direction: np.ndarray):
    import open3d as o3d

    rays = np.empty((len(origins), 6), dtype=np.float32)
    rays[:, :3] = origins
    rays[:, 3:] = direction
    return o3d.core.Tensor(rays)


# ---------------------------------------------------------------------------------------------
# receiver
# ---------------------------------------------------------------------------------------------
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
def shadow_pixels(labels: np.ndarray, v_sun: np.ndarray | None, *, tau_s: float = RelightConfig.tau_s) -> np.ndarray:
    """Pixels in shadow for the caster: labelled shadow, or ``v_sun < tau_s`` (Sec. 8).

    Parameters
    ----------
    labels : (H, W) uint8 array_like
        Step-3 shadow labels, codes of :data:`mvintrinsic.results.SHADOW_LABELS`.
    v_sun : (H, W) float array_like or None
        Sun visibility in [0, 1]; NaN (no estimate) never counts as shadow. ``None``: labels only.
    tau_s : float, optional
        Visibility threshold in [0, 1].

    Returns
    -------
    (H, W) bool
        ``(labels == shadow) | (v_sun < tau_s)``, and never where ``labels == undecided``.
    """
    labels = _image_array(labels, "labels", None, np.int64)
    codes = list(SHADOW_LABELS.values())
    bad = ~np.isin(labels, codes)
    if bad.any():
        raise ValueError(f"labels may only hold {codes}, got {np.unique(labels[bad])[:5].tolist()}")
    if not is_real(tau_s) or not 0.0 <= tau_s <= 1.0:
        raise ValueError(f"tau_s must be a number in [0, 1], got {tau_s!r}")
    shadow = labels == SHADOW_LABELS["shadow"]
    if v_sun is not None:
        v = _image_array(v_sun, "v_sun", labels.shape, np.float64, finite=False)
        with np.errstate(invalid="ignore"):
            shadow |= v < tau_s  # NaN < tau_s is False
    return shadow & (labels != SHADOW_LABELS["undecided"])


# ---------------------------------------------------------------------------------------------
# caster
# ---------------------------------------------------------------------------------------------
#: Neighbouring kept pixels share caster corners only when their receiver distances differ by at
#: most this fraction of the larger (a depth edge splits the caster). Chosen on the test scene
#: (module docstring): 0.02 splits oblique surfaces, 0.1 is no better than 0.05.
SURFACE_JUMP = 0.05

#: ... and when their caster distances differ by at most this fraction of the larger, or by at most
#: this many pixel footprints (metres per pixel at the receiver; the absolute term keeps caster
#: distances near 0, at the foot of an occluder, together). Chosen on the test scene.
CASTER_JUMP = (0.25, 8.0)

#: Corners of a pixel as offsets (column, row) from its centre, in the order of its quad.
_CORNERS = ((-0.5, -0.5), (0.5, -0.5), (0.5, 0.5), (-0.5, 0.5))


def _continuous(a_s, a_t, b_s, b_t, footprint):
    """Whether two kept pixels (receiver distances ``s``, caster distances ``t``) are one surface."""
    rel_t, px_t = CASTER_JUMP
    return (np.abs(a_s - b_s) <= SURFACE_JUMP * np.maximum(a_s, b_s)) & (
        np.abs(a_t - b_t) <= np.maximum(rel_t * np.maximum(a_t, b_t), px_t * footprint)
    )


def _gradients(values: np.ndarray, similar_x: np.ndarray, similar_y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Derivatives of ``values`` (H, W) along columns and rows, per pixel, within one surface.

    ``similar_x[i, j]`` says pixels ``(i, j)`` and ``(i, j + 1)`` are on one surface (shape
    (H, W - 1)), ``similar_y`` likewise for ``(i, j)`` and ``(i + 1, j)`` ((H - 1, W)). Central
    differences where both neighbours are similar, one-sided where one is, 0 where none is.
    """
    out = []
    for axis, similar in ((1, similar_x), (0, similar_y)):
        diff = np.diff(values, axis=axis)
        diff = np.where(similar, diff, 0.0)
        pad_before = [(0, 0), (0, 0)]
        pad_after = [(0, 0), (0, 0)]
        pad_before[axis] = (1, 0)
        pad_after[axis] = (0, 1)
        forward, backward = np.pad(diff, pad_after), np.pad(diff, pad_before)
        n_forward, n_backward = np.pad(similar, pad_after), np.pad(similar, pad_before)
        count = n_forward.astype(np.int64) + n_backward
        out.append((forward + backward) / np.maximum(count, 1))
    return out[0], out[1]


def _footprint_mesh(camera: Camera, kept: np.ndarray, s: np.ndarray, t: np.ndarray,
                    sun: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A quad over every kept pixel's footprint, lifted toward the sun (module docstring).

    ``s`` (H, W) are the receiver distances along the pixel rays, ``t`` (H, W) the caster
    distances (meaningful on ``kept``). A corner of a kept pixel lies on the camera ray through
    that pixel corner at distance ``s_c`` and is lifted by ``t_c`` along ``sun``, where ``s_c`` and
    ``t_c`` average, over the kept pixels touching the corner that are continuous with the pixel
    (:func:`_continuous`), each one's linear extrapolation to the corner (value plus gradient times
    the half-pixel offset). On a plane every touching pixel extrapolates to the same corner, so
    neighbouring quads share their corners (the sheet is closed) and the boundary corners of a
    shadow sit on the surface rather than half a pixel inward; across a jump in ``s`` or ``t`` the
    quads separate instead of stretching. Returns ``(4K, 3)`` float64 vertices (four per kept
    pixel, equal where shared) and ``(2K, 3)`` int32 triangles.
    """
    h, w = kept.shape
    footprint = s / min(camera.focal)  # metres per pixel at the receiver
    t = np.where(kept, t, 0.0)
    similar_x = kept[:, 1:] & kept[:, :-1] & _continuous(s[:, 1:], t[:, 1:], s[:, :-1], t[:, :-1], footprint[:, 1:])
    similar_y = kept[1:] & kept[:-1] & _continuous(s[1:], t[1:], s[:-1], t[:-1], footprint[1:])
    gs_x, gs_y = _gradients(s, similar_x, similar_y)
    gt_x, gt_y = _gradients(t, similar_x, similar_y)
    i, j = np.nonzero(kept)
    n = len(i)
    s_p, t_p, f_p = s[i, j], t[i, j], footprint[i, j]
    corner_s = np.empty((n, 4))
    corner_t = np.empty((n, 4))
    corner_row = np.empty((n, 4), dtype=np.int64)
    corner_col = np.empty((n, 4), dtype=np.int64)
    for k, (ox, oy) in enumerate(_CORNERS):
        # The corner at continuous pixel coordinates (j + 0.5 + ox, i + 0.5 + oy) is touched by the
        # 2x2 block of pixels whose centres are half a pixel from it; sum over the block in a fixed
        # order so that every pixel sharing the corner computes it bit for bit alike.
        total_s, total_t, count = np.zeros(n), np.zeros(n), np.zeros(n)
        for dy in (-0.5, 0.5):
            for dx in (-0.5, 0.5):
                qi, qj = i + round(oy + dy), j + round(ox + dx)  # the block pixel's centre is (dx, dy) off the corner
                inside = (qi >= 0) & (qi < h) & (qj >= 0) & (qj < w)
                ci, cj = np.clip(qi, 0, h - 1), np.clip(qj, 0, w - 1)
                ok = inside & kept[ci, cj] & _continuous(s_p, t_p, s[ci, cj], t[ci, cj], f_p)
                # Linear extrapolation from the block pixel's centre to the corner, (-dx, -dy) away.
                total_s += np.where(ok, s[ci, cj] - dx * gs_x[ci, cj] - dy * gs_y[ci, cj], 0.0)
                total_t += np.where(ok, t[ci, cj] - dx * gt_x[ci, cj] - dy * gt_y[ci, cj], 0.0)
                count += ok
        corner_s[:, k] = total_s / count  # the pixel itself is always in its own block
        corner_t[:, k] = total_t / count
        corner_row[:, k], corner_col[:, k] = i + round(oy + 0.5), j + round(ox + 0.5)
    # One ray per distinct pixel corner (corner (r, c) is at continuous pixel coordinates (c, r)).
    flat = corner_row * (w + 1) + corner_col
    distinct, inverse = np.unique(flat, return_inverse=True)
    uv = np.stack([distinct % (w + 1), distinct // (w + 1)], axis=1).astype(np.float64)
    rays = camera.pixel_rays(uv)[inverse.reshape(n, 4)]
    vertices = camera.center + corner_s[..., None] * rays + corner_t[..., None] * sun
    base = 4 * np.arange(n)[:, None]
    triangles = np.concatenate([base + [0, 1, 2], base + [0, 2, 3]])
    return vertices.reshape(-1, 3), triangles.astype(np.int32)


def build_caster(
    camera: Camera,
    shadow: np.ndarray,
    receiver: np.ndarray,
    sun_direction: np.ndarray,
    tracer: Tracer,
    *,
    lit: np.ndarray | None = None,
    up: np.ndarray = (0.0, 0.0, 1.0),
    config: RelightConfig | None = None,
    batch: int = DEFAULT_BATCH,
) -> Caster:
    """Build the shadow caster of one view from its shadow pixels (paper Sec. 8, Fig. 9).

    Steps (module docstring): sun rays from the shadow pixels' receiver points against the proxy;
    8-connected clusters dropped when smaller than ``config.min_cluster`` pixels or with a share
    of proxy hits below ``config.min_proxy_hits``; missed distances filled from the nearest kept
    pixel that hit; a quad of two triangles over every kept pixel's footprint, lifted toward the
    sun; triangles first hit by more than ``config.epsilon`` sun rays from lit pixels removed.

    Parameters
    ----------
    camera : Camera
        The view (its pixel rays place the footprint corners).
    shadow : (H, W) bool array_like
        Shadow pixels (:func:`shadow_pixels`).
    receiver : (H, W, 3) array_like
        Finite receiver points of every pixel, world frame, metres (:func:`receiver_points`).
    sun_direction : (3,) array_like
        Direction toward the sun at capture time, world frame (normalised here); above the
        horizon of ``up``.
    tracer : Tracer
        Ray caster over the proxy.
    lit : (H, W) bool array_like, optional
        Pixels in light whose sun rays vote against caster triangles. Default: ``~shadow``.
    up : (3,) array_like, optional
        World up vector.
    config : RelightConfig, optional
    batch : int, optional
        Rays per Embree call.

    Returns
    -------
    Caster
        Empty (no vertex, no triangle) when no cluster is kept.

    Raises
    ------
    ValueError
        If an array has the wrong shape, ``receiver`` is not finite or the sun is at or below the
        horizon (the message names ``sun_direction``).
    """
    camera = _check_camera(camera)
    tracer = _check_tracer(tracer)
    config = config_or_default(config, RelightConfig)
    sun = _check_sun(sun_direction, up)
    shape = camera.shape
    shadow = _image_array(shadow, "shadow", shape, bool)
    receiver = _image_array(receiver, "receiver", shape, np.float64, trailing=(3,))
    lit = ~shadow if lit is None else _image_array(lit, "lit", shape, bool)
    offset = config.ray_offset

    # Sun rays from the shadow pixels against the proxy: the occluder distance t_p.
    rows, cols = np.nonzero(shadow)
    hits = tracer.intersect(receiver[rows, cols], np.broadcast_to(sun, (len(rows), 3)), t_min=offset, batch=batch)
    t = np.full(shape, np.inf)
    t[rows, cols] = hits.t
    hit = np.isfinite(t)

    # 8-connected clusters; drop the small ones and those the proxy does not explain.
    clusters, n_clusters = ndimage.label(shadow, structure=_EIGHT)
    size = np.bincount(clusters.ravel(), minlength=n_clusters + 1)
    n_hits = np.bincount(clusters.ravel(), weights=hit.ravel(), minlength=n_clusters + 1)
    share = n_hits / np.maximum(size, 1)
    small = size < config.min_cluster
    unsupported = ~small & ((share < config.min_proxy_hits) | (n_hits == 0))
    keep = ~(small | unsupported)
    keep[0] = small[0] = unsupported[0] = False  # label 0 is the background
    kept = keep[clusters]
    dropped = shadow & ~kept
    primitives = np.unique(hits.triangle[kept[rows, cols] & hits.hit])

    if not kept.any():
        return Caster(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int32), primitives, kept, dropped,
                      n_clusters, int(small[1:].sum()), int(unsupported[1:].sum()), 0)

    # Missed rays take the distance of the nearest kept pixel whose ray hit.
    valid = kept & hit
    lift = np.where(kept, nearest_fill(t, valid), 0.0)

    # Receiver distance from the camera centre (along the pixel ray for receiver_points' points).
    ray_distance = np.linalg.norm(receiver - camera.center, axis=-1)
    vertices, triangles = _footprint_mesh(camera, kept, ray_distance, lift, sun)

    # Triangles first hit by more than epsilon sun rays from lit pixels contradict the image.
    caster = Caster(vertices, triangles, primitives, kept, dropped, n_clusters, int(small[1:].sum()),
                    int(unsupported[1:].sum()), 0)
    return remove_contradicted(caster, [receiver[lit]], sun, config=config, batch=batch)


def _first_hit_counts(vertices: np.ndarray, triangles: np.ndarray, points: Sequence[np.ndarray],
                      sun: np.ndarray, offset: float, batch: int) -> np.ndarray:
    """How many rays ``p + offset d + s d`` (``p`` in every array of ``points``) first hit each triangle."""
    counts = np.zeros(len(triangles), dtype=np.int64)
    if not len(triangles):
        return counts
    scene = triangle_scene(vertices, triangles)
    for array in points:
        for start in range(0, len(array), batch):
            origins = array[start:start + batch] + offset * sun
            ids = scene.cast_rays(_rays(origins, sun))["primitive_ids"].numpy()
            ids = ids[ids != _INVALID_ID].astype(np.int64)
            counts += np.bincount(ids, minlength=len(triangles))
    return counts


def remove_contradicted(caster: Caster, lit_points: Sequence[np.ndarray], sun_direction: np.ndarray, *,
                        config: RelightConfig | None = None, batch: int = DEFAULT_BATCH) -> Caster:
    """Remove the caster triangles that shade lit pixels at the capture sun (paper Sec. 8, epsilon).

    "If a triangle of the caster mesh is intersected by more than epsilon such rays, it is
    removed." A ray toward the sun is cast from every lit point (offset ``config.ray_offset``);
    a triangle *first* hit by more than ``config.epsilon`` of them is removed.

    Parameters
    ----------
    caster : Caster
    lit_points : sequence of (N_i, 3) array_like
        Receiver points of lit pixels, world frame, metres: one view's (the paper) or every
        view's (``method="multiview"``: a receiver point lit in any photo votes).
    sun_direction : (3,) array_like
        Unit direction toward the capture sun, world frame.
    config : RelightConfig, optional
    batch : int, optional

    Returns
    -------
    Caster
        The same caster without those triangles (unused vertices dropped), ``n_removed``
        increased by their number.
    """
    if not isinstance(caster, Caster):
        raise TypeError(f"caster must be a Caster, got {describe(caster)}")
    config = config_or_default(config, RelightConfig)
    sun = as_unit_vector(sun_direction, "sun_direction")
    points = [as_array(p, f"lit_points[{i}]", shape=(None, 3), dtype=np.float64) for i, p in enumerate(lit_points)]
    counts = _first_hit_counts(caster.vertices, caster.triangles, points, sun, config.ray_offset, batch)
    bad = counts > config.epsilon
    if not bad.any():
        return caster
    triangles = caster.triangles[~bad]
    used, triangles = np.unique(triangles, return_inverse=True)
    return replace(caster, vertices=caster.vertices[used], triangles=triangles.reshape(-1, 3).astype(np.int32),
                   n_removed=caster.n_removed + int(bad.sum()))


def contradicted_primitives(tracer: Tracer, lit_points: Sequence[np.ndarray], sun_direction: np.ndarray, *,
                            config: RelightConfig | None = None, batch: int = DEFAULT_BATCH) -> np.ndarray:
    """Proxy primitives whose capture-sun shadow the photographs contradict (beyond the paper).

    The paper's epsilon test applied to the proxy itself: a ray toward the capture sun from the
    receiver point of every lit pixel of every view is traced against the proxy, and a primitive
    first hit by more than ``config.epsilon`` of them would shade pixels the images show in
    light: it is reconstruction noise (bumps of a noisy wall shading the wall itself), a hole
    wrongly filled, or geometry that lets the light through (sparse foliage). Such primitives
    complete no shadow at a new sun (:meth:`ShadowCaster.sun_visibility`).

    Parameters
    ----------
    tracer : Tracer
        Ray caster over the proxy.
    lit_points : sequence of (N_i, 3) array_like
        Receiver points of lit pixels (one array per view), world frame, metres.
    sun_direction : (3,) array_like
        Unit direction toward the capture sun, world frame.
    config : RelightConfig, optional
    batch : int, optional

    Returns
    -------
    (K,) int64
        Sorted indices of the contradicted primitives.
    """
    tracer = _check_tracer(tracer)
    config = config_or_default(config, RelightConfig)
    sun = as_unit_vector(sun_direction, "sun_direction")
    ids = [np.zeros(0, dtype=np.int64)]
    for i, p in enumerate(lit_points):
        p = as_array(p, f"lit_points[{i}]", shape=(None, 3), dtype=np.float64)
        if not len(p):
            continue
        _, primitive = tracer.first_primitive(p, sun, t_min=config.ray_offset, batch=batch)
        ids.append(primitive[primitive >= 0])
    return np.flatnonzero(np.bincount(np.concatenate(ids)) > config.epsilon).astype(np.int64)


def _revote(caster: Caster, own: np.ndarray, others: list[np.ndarray], sun: np.ndarray, config: RelightConfig,
            batch: int) -> Caster:
    """The epsilon test of a view's caster with the lit points of every view (``method="multiview"``).

    :func:`build_caster` already removed the triangles its own view's lit pixels contradict; the
    count is redone with every view's lit points, the own view's included, so that a triangle
    hit by a few rays from each of several views reaches ``epsilon`` too.
    """
    if not len(caster.triangles) or not any(len(p) for p in others):
        return caster
    return remove_contradicted(caster, [own, *others], sun, config=config, batch=batch)


def merge_casters(casters: Sequence[Caster]) -> Caster:
    """One caster for all views: the union of the meshes (paper Sec. 8).

    Parameters
    ----------
    casters : sequence of Caster
        Casters built against the same proxy (their ``proxy_primitives`` index it).

    Returns
    -------
    Caster
        Concatenated vertices and (re-indexed) triangles, the union of ``proxy_primitives``,
        summed counts; ``shadow`` and ``dropped`` are ``None`` (they belong to single views).
    """
    if isinstance(casters, Caster) or not isinstance(casters, Sequence):
        raise TypeError(f"casters must be a sequence of Caster, got {describe(casters)}")
    for i, caster in enumerate(casters):
        if not isinstance(caster, Caster):
            raise TypeError(f"casters[{i}] must be a Caster, got {describe(caster)}")
    if not casters:
        raise ValueError("casters must hold at least one Caster, got none")
    starts = np.cumsum([0] + [len(c.vertices) for c in casters[:-1]])
    vertices = np.concatenate([c.vertices for c in casters])
    triangles = np.concatenate([c.triangles.astype(np.int64) + s for c, s in zip(casters, starts, strict=True)])
    if len(vertices) > np.iinfo(np.int32).max:
        raise ValueError(f"casters: the merged mesh has {len(vertices)} vertices, more than int32 indices can hold")
    primitives = np.unique(np.concatenate([c.proxy_primitives for c in casters]))
    return Caster(vertices, triangles.astype(np.int32), primitives, None, None,
                  sum(c.n_clusters for c in casters), sum(c.n_small for c in casters),
                  sum(c.n_unsupported for c in casters), sum(c.n_removed for c in casters))


# ---------------------------------------------------------------------------------------------
# moving shadows
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
    # cell below and right of its nearest grid row and column above and left.
    mixed = ((corners[:-1, :-1] != corners[1:, :-1]) | (corners[:-1, :-1] != corners[:-1, 1:])
             | (corners[:-1, :-1] != corners[1:, 1:]))
    mixed = ndimage.binary_dilation(mixed, structure=np.ones((3, 3), dtype=bool))
    row = np.minimum(np.searchsorted(ys, np.arange(h), side="right") - 1, len(ys) - 2)
    col = np.minimum(np.searchsorted(xs, np.arange(w), side="right") - 1, len(xs) - 2)
    out = corners[row[:, None], col[None, :]].copy()  # the top-left corner's state
    out[np.ix_(ys, xs)] = corners
    refine = mixed[row[:, None], col[None, :]]
    refine[np.ix_(ys, xs)] = False  # the corners are known
    index = np.flatnonzero(refine)
    out = out.ravel()
    if len(index):
        out[index] = shaded(index)
    return out


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

    def occluded(self, origins: np.ndarray, sun_direction: np.ndarray, *, batch: int = DEFAULT_BATCH) -> np.ndarray:
        """Whether the caster blocks each ray ``origins + s d``, ``s > 0``; (N,) bool.

        Parameters
        ----------
        origins : (N, 3) array_like
            World-frame ray origins, metres (already offset off the receiver).
        sun_direction : (3,) array_like
            Unit direction toward the sun, world frame.
        """
        return self._occluded(*_check_rays(origins, sun_direction), batch=batch)

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
        origins, sun = _check_rays(origins, sun_direction)
        return self._query(origins, sun, np.inf, np.float32, lambda rays: self._scene.cast_rays(rays)["t_hit"], batch)

    def _occluded(self, origins: np.ndarray, sun: np.ndarray, *, batch: int) -> np.ndarray:
        """:meth:`occluded` on checked inputs (the per-sun hot path: no copy, no finiteness scan)."""
        return self._query(origins, sun, False, bool, lambda rays: self._scene.test_occlusions(rays), batch)

    def _query(self, origins: np.ndarray, sun: np.ndarray, empty, dtype, query, batch: int) -> np.ndarray:
        """``query`` (an Embree call on a ray tensor) over ``origins`` in batches; ``empty`` without a caster."""
        out = np.full(len(origins), empty, dtype=dtype)
        if self._scene is None:
            return out
        for start in range(0, len(origins), batch):
            sl = slice(start, start + batch)
            out[sl] = query(_rays(origins[sl], sun)).numpy()
        return out

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
        facing = None
        if normals is not None:
            n = _image_array(normals, "normals", shape, np.float64, trailing=(3,), finite=False).reshape(-1, 3)
            with np.errstate(invalid="ignore"):
                facing = ~((n @ sun) <= 0.0)  # NaN <= 0 is False: no normal, no attached shadow
        return self._visibility(points.reshape(-1, 3), shape, sun, proxy_tracer=proxy_tracer, blocked=blocked,
                                min_distance=float(min_distance) if proxy_tracer is not None else 0.0,
                                facing=facing, config=config, batch=batch)

    def completion_blocked(self, proxy_tracer: Tracer, excluded: np.ndarray | None = None) -> np.ndarray:
        """Per proxy primitive, whether a first hit on it completes no shadow; (P + 1,) bool.

        True for the primitives the caster stands for (:attr:`Caster.proxy_primitives`), for
        ``excluded`` ones, and in the last entry, which a miss (primitive -1) reads. A lookup
        built once per view and sun-independent, so each new sun costs one gather.
        """
        n = proxy_tracer.n_primitives
        blocked = np.zeros(n + 1, dtype=bool)
        for ids in (self.caster.proxy_primitives, () if excluded is None else excluded):
            ids = np.asarray(ids, dtype=np.int64)
            blocked[ids[(ids >= 0) & (ids < n)]] = True  # other ids name no primitive: no hit reads them
        blocked[-1] = True
        return blocked

    def _visibility(self, points: np.ndarray, shape: tuple[int, int], sun: np.ndarray, *,
                    proxy_tracer: Tracer | None, blocked: np.ndarray | None, min_distance: float,
                    facing: np.ndarray | None, config: RelightConfig, batch: int) -> np.ndarray:
        """:meth:`sun_visibility` on checked inputs: ``points`` (H*W, 3) float64, ``sun`` unit."""
        offset = config.ray_offset * sun

        def shaded(index: np.ndarray) -> np.ndarray:
            # Offset toward the sun in float64, then float32 as Embree takes them.
            origins = (points[index] + offset).astype(np.float32)
            shade = self._occluded(origins, sun, batch=batch)
            if proxy_tracer is not None:
                # Only rays the caster let through can change: the proxy's rays go to those alone.
                # A proxy hit completes the shadow unless the caster stands for its primitive, a
                # lit pixel contradicted it or it lies nearer than ``min_distance`` (``blocked``).
                open_rays = np.flatnonzero(~shade)
                t, primitive = proxy_tracer.first_primitive(origins[open_rays], sun, batch=batch)
                # t counts from the offset origin.
                shade[open_rays] = ~blocked[primitive] & (t + np.float32(config.ray_offset) >= min_distance)
            if facing is not None:
                shade |= ~facing[index]
            return shade

        shade = _strided(shaded, shape, config.ray_stride)
        visibility = (~shade).reshape(shape).astype(np.float32)
        if config.blur > 0:
            visibility = ndimage.gaussian_filter(visibility, sigma=config.blur, mode="nearest")
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
                raise ValueError(f"sun: the elevation must be at most 90 degrees, got {value[1]!r}")
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


def receiver_normals(camera: Camera, tracer: Tracer, *, normal_smoothing: float = 0.0) -> np.ndarray:
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
    return _pixel_normals(tracer, hits, camera.shape, vertex_normals(tracer.proxy, normal_smoothing))


# ---------------------------------------------------------------------------------------------
# environment shading at the new sun
# ---------------------------------------------------------------------------------------------
#: Rows of the full-sphere grid of sky directions over which the sky irradiance is summed (its
#: upper half: 32 x 128 texels of 2.8 degrees, SkyConfig's envmap resolution).
SKY_GRID_HEIGHT = 64

#: Rows of the full-sphere grid of normals on which the sky irradiance is tabulated (5.6 degrees);
#: a pixel's value is the bilinear interpolation of the table at its normal. The irradiance is a
#: cosine-smoothed function of the normal: against the exact sum at each of 2000 random normals,
#: the interpolated ratio is within 0.12% for 99% of them and 1.1% at worst (normals grazing the
#: horizon), for sun moves of 10 to 30 degrees and turbidities 2 and 3.5.
NORMAL_GRID_HEIGHT = 32


def _zenith_luminance(turbidity: float, sun_zenith: float) -> float:
    """Absolute zenith luminance of the Preetham sky, kcd/m^2 (Preetham et al. 1999, Appendix A.2).

    ``Y_z = (4.0453 T - 4.9710) tan(chi) - 0.2155 T + 2.4192``, ``chi = (4/9 - T/120)(pi - 2 theta_s)``.
    """
    chi = (4.0 / 9.0 - turbidity / 120.0) * (math.pi - 2.0 * sun_zenith)
    return (4.0453 * turbidity - 4.9710) * math.tan(chi) - 0.2155 * turbidity + 2.4192


def _sky_irradiance_grid(sun: np.ndarray, turbidity: float, up: np.ndarray) -> np.ndarray:
    """Preetham sky irradiance / pi on the normal grid, ``(Hn, 2 Hn, 3)`` float64 (relative units).

    ``E(n) = (1 / pi) sum_k Y_z f(w_k) max(0, n . w_k) Omega_k`` over the texels ``w_k`` above the
    horizon, ``f`` the sky's colour relative to its zenith (:func:`preetham_relative_rgb`) and
    ``Y_z`` the absolute zenith luminance (:func:`_zenith_luminance`), which the relative model
    leaves to the fitted scale ``k`` of Eq. (4): ``k`` fixes ``Y_z`` at the capture sun, and ``k Y_z(d')
    / Y_z(d)`` is the sky at the new one.
    """
    half = SKY_GRID_HEIGHT // 2
    directions = envmap_directions(SKY_GRID_HEIGHT, up=up)[:half].reshape(-1, 3)
    omega = texel_solid_angles(SKY_GRID_HEIGHT)[:half].reshape(-1)
    sun_zenith = math.acos(max(-1.0, min(1.0, float(sun @ up))))
    relative = preetham_relative_rgb(directions, sun_direction=sun, turbidity=turbidity, up=up)
    weighted = np.maximum(relative, 0.0) * (_zenith_luminance(turbidity, sun_zenith) * omega / math.pi)[:, None]
    normals = envmap_directions(NORMAL_GRID_HEIGHT, up=up).reshape(-1, 3)
    cosine = np.maximum(normals.astype(np.float32) @ directions.T.astype(np.float32), 0.0)
    return (cosine.astype(np.float64) @ weighted).reshape(NORMAL_GRID_HEIGHT, 2 * NORMAL_GRID_HEIGHT, 3)


#: Normals whose sky irradiance at the capture sun is below this fraction of the largest (normals
#: that see at most a sliver of sky at the horizon, whose S_sky is about 0) keep their S_sky: a
#: ratio of two near-zero sums is noise.
SKY_RATIO_FLOOR = 1e-3


def _grid_ratio(new: np.ndarray, old: np.ndarray) -> np.ndarray:
    """``new / old`` per texel and channel, 1 where ``old`` is below :data:`SKY_RATIO_FLOOR` of its max."""
    floor = SKY_RATIO_FLOOR * float(old.max()) if old.size else 0.0
    return np.divide(new, old, out=np.ones_like(new), where=old > floor)


class _SphereLookup:
    """Bilinear interpolation of an equirectangular full-sphere table at fixed directions.

    The table's texel ``(v, u)`` is at polar angle ``pi (v + 0.5) / He`` from ``up`` and azimuth
    ``2 pi (u + 0.5) / (2 He)`` (:func:`~mvintrinsic.skymodel.envmap_directions`); columns wrap,
    rows clamp at the poles. Indices and weights are computed once.
    """

    def __init__(self, directions: np.ndarray, height: int, up: np.ndarray) -> None:
        d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
        width = 2 * height
        local = d @ horizontal_frame(up).T
        theta = np.arccos(np.clip(local[:, 2], -1.0, 1.0))
        phi = np.mod(np.arctan2(local[:, 1], local[:, 0]), 2.0 * math.pi)
        v = theta * height / math.pi - 0.5
        u = phi * width / (2.0 * math.pi) - 0.5
        v0, u0 = np.floor(v), np.floor(u)
        fv, fu = v - v0, u - u0
        r0 = np.clip(v0, 0, height - 1).astype(np.int64)
        r1 = np.clip(v0 + 1, 0, height - 1).astype(np.int64)
        c0 = np.mod(u0, width).astype(np.int64)
        c1 = np.mod(u0 + 1, width).astype(np.int64)
        self.index = np.stack([r0 * width + c0, r0 * width + c1, r1 * width + c0, r1 * width + c1], axis=1)
        self.weight = np.stack([(1 - fv) * (1 - fu), (1 - fv) * fu, fv * (1 - fu), fv * fu], axis=1)
        self.shape = np.shape(directions)[:-1]

    def __call__(self, table: np.ndarray) -> np.ndarray:
        flat = table.reshape(-1, table.shape[-1])
        out = np.einsum("nk,nkc->nc", self.weight, flat[self.index])
        return out.reshape(*self.shape, table.shape[-1])


def sky_irradiance_ratio(normals: np.ndarray, old_sun: np.ndarray, new_sun: np.ndarray, *, turbidity: float,
                         up: np.ndarray = (0.0, 0.0, 1.0)) -> np.ndarray:
    """Sky irradiance of the Preetham model at a new sun over the old one, per normal (``sky="model"``).

    .. math::

        \\rho(n) = \\frac{E_{sky}(n; d')}{E_{sky}(n; d)}, \\qquad
        E_{sky}(n; d) = \\frac{1}{\\pi} \\int_{\\Omega_{sky}} L_{sky}(\\omega; d) \\max(0, n \\cdot \\omega)
        \\, d\\omega

    with ``L_sky`` the Preetham sky of Eq. (4) at turbidity ``t`` including its absolute zenith
    luminance (Preetham et al. 1999, Appendix A.2), integrated over the directions above the
    horizon (a :data:`SKY_GRID_HEIGHT`-row grid), unoccluded. The scale ``k`` of Eq. (4) cancels.
    The ratio is tabulated on a :data:`NORMAL_GRID_HEIGHT`-row grid of normals and interpolated.

    Parameters
    ----------
    normals : (..., 3) array_like
        Unit normals, world frame.
    old_sun, new_sun : (3,) array_like
        Unit vectors toward the capture sun and the new sun, world frame, above the horizon.
    turbidity : float
        Turbidity ``t`` of the fitted sky (:attr:`mvintrinsic.results.SkyParameters.turbidity`).
    up : (3,) array_like, optional
        World up vector (the sky's zenith).

    Returns
    -------
    (..., 3) float64
        Per-channel ratio (1 for normals that see no sky, :data:`SKY_RATIO_FLOOR`); exactly 1
        when ``new_sun == old_sun``, up to the interpolation's rounding.
    """
    up = as_unit_vector(up, "up")
    old = _check_sun(old_sun, up)
    new = _check_sun(new_sun, up)
    if not is_real(turbidity) or not 0.0 < turbidity < np.inf:
        raise ValueError(f"turbidity must be a finite number > 0, got {turbidity!r}")
    normals = np.asarray(normals, dtype=np.float64)
    if normals.ndim < 1 or normals.shape[-1] != 3:
        raise ValueError(f"normals must have shape (..., 3), got shape {normals.shape}")
    turbidity = float(turbidity)
    ratio = _grid_ratio(_sky_irradiance_grid(new, turbidity, up), _sky_irradiance_grid(old, turbidity, up))
    return _SphereLookup(normals, NORMAL_GRID_HEIGHT, up)(ratio)


#: Dominant wavelengths of the Rec.709 / sRGB primaries (R, G, B), micrometres: where the paper's
#: red shift (:func:`paper_environment_factors`) reads the Rayleigh optical depth.
RGB_WAVELENGTHS_UM = np.array([0.611, 0.549, 0.464])


def _rayleigh_optical_depth(wavelength_um: np.ndarray) -> np.ndarray:
    """Rayleigh optical depth of the whole atmosphere at sea level (Hansen & Travis 1974)."""
    lam = np.asarray(wavelength_um, dtype=np.float64)
    return 0.008569 * lam**-4 * (1.0 + 0.0113 * lam**-2 + 0.00013 * lam**-4)


def _air_mass(elevation: float) -> float:
    """Relative optical air mass at a solar elevation (radians), Kasten & Young (1989)."""
    degrees = math.degrees(elevation)
    return 1.0 / (math.sin(elevation) + 0.50572 * (degrees + 6.07995) ** -1.6364)


def paper_environment_factors(old_sun: np.ndarray, new_sun: np.ndarray, *,
                              up: np.ndarray = (0.0, 0.0, 1.0)) -> tuple[np.ndarray, float]:
    """Our reading of the paper's environment adjustment (``sky="paper"``, Sec. 8).

    The paper "render[s] an approximate effect of illumination changes by adjusting the sun
    shading intensity according to a cosine factor with respect to elevation and the horizontal
    plane, and shifting S_sky towards red in the morning and afternoon. We also diminish S_ind
    with a similar amount". It gives no formula; this is our reading, tied to the change of the
    sun's elevation from ``el`` to ``el'``:

    * the "cosine factor with respect to [...] the horizontal plane" is the cosine between the
      sun and the horizontal plane's normal, ``sin(el)``; ``S_ind``, light the sun brought to
      the scene, is scaled by its change ``f = sin(el') / sin(el)`` (the "similar amount");
    * the red shift of ``S_sky`` is the change of colour of the light through the atmosphere's
      Rayleigh scattering: with the optical depth ``tau_c`` at each primary's dominant wavelength
      (:data:`RGB_WAVELENGTHS_UM`, Hansen & Travis 1974) and the air mass ``m(el)`` (Kasten &
      Young 1989), ``t_c = exp(-tau_c (m(el') - m(el)))``, normalised to unit luminance (a shift
      of colour, not of brightness): ``g = t / (0.2126 t_R + 0.7152 t_G + 0.0722 t_B)``. A lower
      sun gives ``g_R > g_G > g_B``; 35 to 25 degrees gives ``g = (1.02, 1.00, 0.94)``.

    Parameters
    ----------
    old_sun, new_sun : (3,) array_like
        Unit vectors toward the capture sun and the new sun, world frame, above the horizon.
    up : (3,) array_like, optional
        World up vector.

    Returns
    -------
    sky_gain : (3,) float64
        ``g``, multiplies ``S_sky`` (RGB).
    indirect_factor : float
        ``f``, multiplies ``S_ind``.
    """
    up = as_unit_vector(up, "up")
    old = _check_sun(old_sun, up)
    new = _check_sun(new_sun, up)
    old_el, new_el = math.asin(min(1.0, float(old @ up))), math.asin(min(1.0, float(new @ up)))
    factor = math.sin(new_el) / math.sin(old_el)
    transmittance = np.exp(-_rayleigh_optical_depth(RGB_WAVELENGTHS_UM) * (_air_mass(new_el) - _air_mass(old_el)))
    return transmittance / float(LUMINANCE_WEIGHTS @ transmittance), factor


# ---------------------------------------------------------------------------------------------
# relighting
# ---------------------------------------------------------------------------------------------
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


def _read_only(array: np.ndarray) -> np.ndarray:
    array.flags.writeable = False
    return array


class _NewSun:
    """One view's sun-independent inputs of a new sun, and the per-view steps of one (:class:`Relighter`).

    Built once per view; :meth:`Relighter.render` runs these steps here, or ships this object once
    to a dask worker and runs them there (:func:`_render_view`): the same code either way, so the
    images are identical. It holds no Embree structure (those cannot be pickled): the caster's and
    the proxy's are passed in.

    Parameters
    ----------
    receivers : (H*W, 3) float64
        Receiver points, world frame, metres (:func:`receiver_points`).
    shape : (int, int)
        ``(H, W)``.
    blocked : (P + 1,) bool
        :meth:`ShadowCaster.completion_blocked` of the view's caster.
    min_distance : float
        Proxy hits nearer than this (metres) complete no shadow.
    config : RelightConfig
    batch : int
        Rays per Embree call.
    normals : (H, W, 3) float32
        Unit receiver normals, world frame.
    base, floor : (H, W, 3) float32
        ``S_sun' = max(base + L_sun max(0, n.d'), floor)`` (:meth:`Relighter._prepare_new_sun`).
    fill : (H, W, 3) float32
        The input image where the layers hold no estimate, 0 elsewhere.
    reflectance, fill_reflectance : (H, W, 3) float32
        ``R`` after the in-shadow fix; the same with 0 where the layers hold no estimate.
    sky_shading, indirect_shading : (H, W, 3) float32
        The layers' ``S_sky`` and ``S_ind``.
    radiance : (3,) float32
        ``L_sun`` in the view's units.
    known : (H, W) bool
        Pixels where the layers hold an estimate.
    sky_lookup : _SphereLookup or None
        ``sky="model"``: the sky irradiance table at each pixel's normal.
    """

    def __init__(self, *, receivers: np.ndarray, shape: tuple[int, int], blocked: np.ndarray, min_distance: float,
                 config: RelightConfig, batch: int, normals: np.ndarray, base: np.ndarray, floor: np.ndarray,
                 fill: np.ndarray, reflectance: np.ndarray, fill_reflectance: np.ndarray, sky_shading: np.ndarray,
                 indirect_shading: np.ndarray, radiance: np.ndarray, known: np.ndarray,
                 sky_lookup: _SphereLookup | None) -> None:
        self.receivers, self.shape, self.blocked, self.min_distance = receivers, shape, blocked, min_distance
        self.config, self.batch = config, batch
        self.normals, self.base, self.floor, self.fill = normals, base, floor, fill
        self.reflectance, self.fill_reflectance = reflectance, fill_reflectance
        self.sky_shading, self.indirect_shading = sky_shading, indirect_shading
        self.radiance, self.known, self.sky_lookup = radiance, known, sky_lookup

    def visibility(self, direction: np.ndarray, shadow_caster: ShadowCaster, tracer: Tracer) -> np.ndarray:
        """``v'`` (H, W) float32 at the unit sun ``direction`` (:meth:`Relighter.visibility_at`)."""
        return shadow_caster._visibility(self.receivers, self.shape, direction, proxy_tracer=tracer,
                                         blocked=self.blocked, min_distance=self.min_distance, facing=None,
                                         config=self.config, batch=self.batch)

    def cosine(self, direction: np.ndarray) -> np.ndarray:
        """``max(0, n . d')`` (H, W) float32 for the float32 unit sun ``direction``."""
        cosine = self.normals @ direction
        return np.maximum(cosine, np.float32(0.0), out=cosine)

    def irradiance(self, cosine: np.ndarray, visibility: np.ndarray) -> float:
        """``sum max(0, n . d') v'`` over the pixels with an estimate (``sky="model"``'s ``S_ind``)."""
        return float((cosine.astype(np.float64) * visibility)[self.known].sum())

    def sky_factor(self, environment: tuple[str, np.ndarray]) -> np.ndarray:
        """``S_sky' / S_sky``: the (3,) float32 gain (``"paper"``) or the sky-model ratio at each normal (H, W, 3)."""
        how, table = environment
        return table.astype(np.float32) if how == "paper" else self.sky_lookup(table)

    def sun_shading(self, cosine: np.ndarray) -> np.ndarray:
        """``S_sun'`` (H, W, 3) float32 from ``max(0, n . d')``."""
        s_sun = cosine[..., None] * self.radiance
        s_sun += self.base
        return np.maximum(s_sun, self.floor, out=s_sun)

    def image(self, visibility: np.ndarray, sun_shading: np.ndarray, sky: np.ndarray, indirect: float,
              fill: str) -> np.ndarray:
        """``R (v' S_sun' + S_sky' + S_ind')`` (H, W, 3) float32; ``sun_shading`` is overwritten."""
        image = sun_shading
        image *= visibility[..., None]
        image += self.sky_shading * sky
        image += self.indirect_shading * np.float32(indirect)
        if fill == "input":  # the reflectance of the pixels without an estimate is 0 there
            image *= self.fill_reflectance
            image += self.fill
        else:
            image *= self.reflectance
        return image


def _build_task(caster: _Rebuilt, tracer: _Rebuilt) -> None:
    """A task: build the caster's and the proxy's Embree structures on this worker (once each)."""
    caster.get()
    tracer.get()


def _new_sun_terms(new_sun: _NewSun, caster: _Rebuilt, tracer: _Rebuilt, direction: np.ndarray,
                   shadow_sun: np.ndarray, visibility: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """A task: one view's ``(v', max(0, n . d'))`` at a new sun (``visibility`` given: that ``v'``)."""
    if visibility is None:
        visibility = new_sun.visibility(shadow_sun, caster.get(), tracer.get())
    return visibility, new_sun.cosine(direction.astype(np.float32))


def _irradiance_task(new_sun: _NewSun, terms: tuple[np.ndarray, np.ndarray]) -> float:
    """A task: :meth:`_NewSun.irradiance` of one view's :func:`_new_sun_terms`."""
    visibility, cosine = terms
    return new_sun.irradiance(cosine, visibility)


def _image_task(new_sun: _NewSun, terms: tuple[np.ndarray, np.ndarray], *, environment: tuple[str, np.ndarray],
                indirect_factor: float, fill: str) -> np.ndarray:
    """A task: one view's relit image from its :func:`_new_sun_terms`."""
    visibility, cosine = terms
    return new_sun.image(visibility, new_sun.sun_shading(cosine), new_sun.sky_factor(environment),
                         indirect_factor, fill)


def _render_view(new_sun: _NewSun, caster: _Rebuilt, tracer: _Rebuilt, direction: np.ndarray,
                 shadow_sun: np.ndarray, visibility: np.ndarray | None, *, environment: tuple[str, np.ndarray],
                 indirect_factor: float, fill: str) -> np.ndarray:
    """A task: one view's relit image at a new sun (``sky="paper"``: no cross-view term)."""
    terms = _new_sun_terms(new_sun, caster, tracer, direction, shadow_sun, visibility)
    return _image_task(new_sun, terms, environment=environment, indirect_factor=indirect_factor, fill=fill)


class Relighter:
    """Relight every view of a decomposition under new suns (paper Sec. 8).

    Built once per decomposition: per view the receiver points and normals, the shadow pixels and
    the caster (:func:`build_caster` at the capture sun, lit pixels voting), the in-shadow
    reflectance fix of the dropped clusters; then one caster merged over all views
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
    client : distributed.Client, optional
        A dask.distributed client: :meth:`render` then runs one task per view on its cluster
        (``docs/distributed.md``). Building stays here (the casters need every view's votes); at
        the end each view's inputs of a new sun (receivers, completion lookup, shading terms and
        caster, about 120 bytes per pixel, 180 with ``sky="model"``) are shipped once to one
        worker, the proxy once to every worker, and each worker builds its own Embree structures
        over them (they cannot be pickled):
        the proxy's tracer is ``Tracer(scene.proxy)`` there, so a ``tracer`` built with other
        surfel parameters (point clouds) would not be matched. The images are identical to
        those rendered here. None (default): everything runs in this process; dask is not
        imported.

    Attributes
    ----------
    stems : tuple of str
        The views, in the scene's order.
    sun : (3,) float64
        The capture sun (unit, toward the sun, world frame).
    receivers, normals : mapping of str to (H, W, 3) float64
        Per view, the receiver points (metres, :func:`receiver_points`) and unit proxy normals
        (:func:`receiver_normals`), world frame.
    reflectance : mapping of str to (H, W, 3) float32
        ``R`` after the in-shadow fix (``config.light_dropped``).
    visibility : mapping of str to (H, W) float32
        The capture ``v_sun`` after the fix (1 on the dropped clusters):
        ``render(self.sun, visibility=self.visibility)`` reproduces every view's
        ``reflectance * shading``.
    casters : mapping of str to Caster
        Per view, after the votes of every view (``method="multiview"``) and before merging
        (``dropped`` holds the pixels brought into light).
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
        the proxy), ``shadow_caster`` (merging and the BVHs), ``new_sun_setup`` (what every new
        sun reuses: the completion lookups and the shading terms) and, with a ``client``,
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
                 tracer: Tracer | None = None, batch: int = DEFAULT_BATCH, client: Any = None) -> None:
        decomposition, scene = _check_decomposition(decomposition, scene)
        config = config_or_default(config, RelightConfig)
        client = _as_client(client)
        if tracer is None:
            tracer = Tracer(scene.proxy)
        tracer = _check_tracer(tracer)
        if tracer.proxy is not scene.proxy:
            raise ValueError("tracer must be built over scene.proxy")
        lighting = decomposition.lighting
        up = scene.up
        capture = _check_sun(lighting.sun.direction, up)
        self.decomposition, self.scene, self.config, self.tracer = decomposition, scene, config, tracer
        self.stems = scene.stems
        self.up, self.sun = up, capture
        self.sun_radiance = lighting.sun_radiance
        # L_sun in each view's own units (its exposure gain, mvintrinsic.exposure), float32 (3,)
        self._radiance = {stem: (lighting.sun_radiance * lighting.gain(stem)).astype(np.float32)
                          for stem in decomposition.layers}
        self._batch = batch
        timings = {"receivers": 0.0, "casters": 0.0, "votes": 0.0, "shadow_caster": 0.0}
        receivers, normals, hits, known, cosine = {}, {}, {}, {}, {}
        start = time.perf_counter()
        self._vertex_normals = vertex_normals(tracer.proxy, config.normal_smoothing)
        timings["receivers"] += time.perf_counter() - start
        reflectance, visibility, casters, lit_points = {}, {}, {}, {}
        for view in scene.views:
            stem, camera = view.stem, view.camera
            start = time.perf_counter()
            ray_hits, t, hit = _cast_pixels(camera, tracer, batch, name=f"scene (view {stem!r})")
            receivers[stem] = _read_only(receiver_points(camera, t))
            normals[stem] = _read_only(_pixel_normals(tracer, ray_hits, camera.shape, self._vertex_normals))
            hits[stem] = ray_hits
            cosine[stem] = np.maximum(normals[stem] @ capture, 0.0)  # max(0, cos w_sun), Eq. (1)
            timings["receivers"] += time.perf_counter() - start

            start = time.perf_counter()
            layers = decomposition.layers[stem]
            labels = layers.shadow_labels
            shadow = shadow_pixels(labels, layers.visibility, tau_s=config.tau_s)
            lit = hit & ~shadow & (labels == SHADOW_LABELS["lit"])
            lit_points[stem] = receivers[stem][lit]
            casters[stem] = build_caster(camera, shadow, receivers[stem], capture, tracer, lit=lit, up=up,
                                         config=config, batch=batch)
            timings["casters"] += time.perf_counter() - start

            shading = layers.shading.astype(np.float64)
            known[stem] = _read_only((layers.reflectance > 0).any(axis=-1) | (shading > 0).any(axis=-1))
            r, v = layers.reflectance, layers.visibility
            dropped = casters[stem].dropped
            if config.light_dropped and dropped.any():
                # Sec. 8: "We adjust the reflectance of such pixels to bring them in light using the
                # v_sun layer": v_sun = 1 and R = I / (S_sun + S_sky + S_ind), I = R S_tot (Eq. 2).
                in_light = layers.sun_shading.astype(np.float64) + layers.env_shading
                ok = dropped[..., None] & (in_light > 0)
                r = np.where(ok, r * shading / np.where(ok, in_light, 1.0), r).astype(np.float32)
                v = np.where(dropped, np.float32(1.0), v)
            reflectance[stem] = _read_only(np.array(r, dtype=np.float32))
            visibility[stem] = _read_only(np.array(v, dtype=np.float32))

        start = time.perf_counter()
        excluded = np.zeros(0, dtype=np.int64)
        if config.method == "multiview":
            # Every view's lit pixels vote against every view's caster and against the proxy.
            for stem in self.stems:
                others = [lit_points[s] for s in self.stems if s != stem]
                casters[stem] = _revote(casters[stem], lit_points[stem], others, capture, config, batch)
            excluded = contradicted_primitives(tracer, [lit_points[s] for s in self.stems], capture,
                                               config=config, batch=batch)
        timings["votes"] = time.perf_counter() - start

        start = time.perf_counter()
        self.caster = merge_casters([casters[s] for s in self.stems])
        if config.casters == "merged":
            shared = ShadowCaster(self.caster)
            self.shadow_casters = MappingProxyType({s: shared for s in self.stems})
        else:
            self.shadow_casters = MappingProxyType({s: ShadowCaster(casters[s]) for s in self.stems})
        timings["shadow_caster"] = time.perf_counter() - start
        self.excluded_primitives = _read_only(excluded)
        self.receivers = MappingProxyType(receivers)
        self.normals = MappingProxyType(normals)
        self.reflectance = MappingProxyType(reflectance)
        self.visibility = MappingProxyType(visibility)
        self.casters = MappingProxyType(casters)
        self._hits, self._known = hits, known
        # The sun-independent inputs of every new sun, once (module docstring, "Speed").
        start = time.perf_counter()
        self._new_sun = {s: self._prepare_new_sun(s, cosine[s], excluded) for s in self.stems}
        timings["new_sun_setup"] = time.perf_counter() - start
        # The sun irradiance of the receivers at capture, the denominator of S_ind's scale.
        self._sun_irradiance = sum(float((cosine[s] * visibility[s])[known[s]].sum()) for s in self.stems)
        self._turbidity = lighting.sky.turbidity if lighting.sky is not None else config.turbidity
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
        self.timings = MappingProxyType(timings)

    # -- shadows -------------------------------------------------------------------------------
    def visibility_at(self, sun: object) -> dict[str, np.ndarray]:
        """The new shadow layer of every view: the caster's ``v'`` (Sec. 8, "Moving Shadows").

        :meth:`ShadowCaster.sun_visibility` of the view's caster (:attr:`shadow_casters`) from
        the view's receiver points, completed by the proxy's shadow (this relighter's tracer;
        with ``method="multiview"`` without :attr:`excluded_primitives` and hits nearer than
        ``config.completion_distance``) and blurred by ``config.blur``.

        Parameters
        ----------
        sun : (3,) array_like, Sun or (azimuth_deg, elevation_deg)
            The new sun (:func:`as_sun_direction`).

        Returns
        -------
        dict of str to (H, W) float32
            ``v'`` in [0, 1] per view, in scene order.
        """
        direction = as_sun_direction(sun, up=self.up)
        return {s: self._new_sun[s].visibility(direction, self.shadow_casters[s], self.tracer) for s in self.stems}

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
        for view in self.scene.views:
            hits = self._hits[view.stem]
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
        for stem, (v_new, s_sun, sky, indirect) in self._relit(sun, visibility).items():
            layers = self.decomposition.layers[stem]
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

    def _prepare_new_sun(self, stem: str, cosine: np.ndarray, excluded: np.ndarray) -> _NewSun:
        """The sun-independent inputs of a new sun of one view, float32, once (module docstring).

        ``S_sun' = max(S_sun - L_sun max(0, n.d) + L_sun max(0, n.d'), min(S_sun, 0))`` where the
        pixel saw the sun (``v_sun > 0``), else ``L_sun max(0, n.d')``: the first two terms and
        the floor do not depend on the new sun ``d'``.
        """
        config = self.config
        radiance = self._radiance[stem].astype(np.float64)
        layers = self.decomposition.layers[stem]
        s_sun = layers.sun_shading.astype(np.float64)
        saw_sun = (self.visibility[stem] > 0)[..., None]
        # In full shadow base 0 and floor -inf leave L_sun max(0, n.d') alone.
        base = np.where(saw_sun, s_sun - radiance * cosine[..., None], 0.0).astype(np.float32)
        floor = np.where(saw_sun, np.minimum(s_sun, 0.0), -np.inf).astype(np.float32)
        unknown = ~self._known[stem][..., None]
        image = self.scene.view(stem).image
        fill = np.where(unknown, np.nan_to_num(image, nan=0.0, posinf=0.0, neginf=0.0), 0.0).astype(np.float32)
        blocked = self.shadow_casters[stem].completion_blocked(
            self.tracer, excluded if config.method == "multiview" else None)
        return _NewSun(
            receivers=self.receivers[stem].reshape(-1, 3),  # a view, no copy
            shape=layers.shape, blocked=blocked,
            min_distance=config.completion_distance if config.method == "multiview" else 0.0,
            config=config, batch=self._batch, normals=self.normals[stem].astype(np.float32), base=base,
            floor=floor, fill=fill, reflectance=self.reflectance[stem],
            fill_reflectance=np.where(unknown, np.float32(0.0), self.reflectance[stem]),  # so the fill adds to 0
            sky_shading=layers.sky_shading, indirect_shading=layers.indirect_shading,
            radiance=self._radiance[stem], known=self._known[stem],
            sky_lookup=(_SphereLookup(self.normals[stem], NORMAL_GRID_HEIGHT, self.up)
                        if config.sky == "model" else None))

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
               ) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray, float]]:
        """Per view ``(v', S_sun', S_sky' / S_sky, S_ind' / S_ind)``: the core of :meth:`layers`.

        ``S_sun'`` (H, W, 3) float32; the sky factor (3,) float32 (``sky="paper"``) or (H, W, 3)
        float64 (``"model"``); the indirect factor a scalar.
        """
        direction = as_sun_direction(sun, up=self.up)
        new_vis = self.visibility_at(direction) if visibility is None else self._check_visibility(visibility)
        d32 = direction.astype(np.float32)
        new_cosine = {s: self._new_sun[s].cosine(d32) for s in self.stems}
        environment, indirect_factor = self._environment(direction)
        if indirect_factor is None:
            indirect_factor = self._indirect_factor(
                sum(self._new_sun[s].irradiance(new_cosine[s], new_vis[s]) for s in self.stems))
        return {s: (new_vis[s], self._new_sun[s].sun_shading(new_cosine[s]), self._new_sun[s].sky_factor(environment),
                    indirect_factor)
                for s in self.stems}

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
            See :meth:`layers`.
        fill : {"input", "zero"}, optional
            What the pixels without an estimate (the layers hold 0 there: the sky, invalid pixels,
            pixels the decomposition took for sky) show: the view's input image (its non-finite
            values as 0), or 0. The paper recolours the sky near the horizon; that is not done
            here.

        Returns
        -------
        dict of str to (H, W, 3) float32
            Linear RGB in the images' units, per view in scene order. At the capture sun with
            ``visibility=self.visibility`` it is ``reflectance * shading`` of the decomposition
            wherever the layers hold an estimate (to float32 rounding).
        """
        if fill not in ("input", "zero"):
            raise ValueError(f"fill must be 'input' or 'zero', got {fill!r}")
        if self._tasks is not None:
            return self._render_on_cluster(sun, visibility, fill)
        return {s: self._new_sun[s].image(v_new, s_sun, sky, indirect, fill)
                for s, (v_new, s_sun, sky, indirect) in self._relit(sun, visibility).items()}

    def _render_on_cluster(self, sun: object, visibility: Mapping[str, np.ndarray] | None, fill: str
                           ) -> dict[str, np.ndarray]:
        """:meth:`render` as one task per view on the client's cluster (the same per-view steps as :meth:`_relit`)."""
        tasks, remote = self._tasks, self._remote
        direction = as_sun_direction(sun, up=self.up)
        shadow_sun = as_sun_direction(direction, up=self.up)  # as visibility_at receives it in _relit
        given = None if visibility is None else tasks.scatter(self._check_visibility(visibility))
        args = {s: (remote["new_sun"][s], remote["casters"][s], remote["tracer"], direction, shadow_sun,
                    None if given is None else given[s]) for s in self.stems}
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
                                   environment=environment, indirect_factor=indirect_factor, fill=fill)
        return tasks.gather(futures)

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
