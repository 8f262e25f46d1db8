"""Relighting's shadow geometry (paper Sec. 8): shadow pixels, the 2.5D caster and the views' votes.

The proxy's own shadows do not match the shadow boundaries of the photographs (paper Fig. 4b), so
the paper relights with a *caster* built from the shadows of the image itself [1]_ ("Creating
Shadow Receiver and Caster Geometry"). This module builds it per view; :mod:`.shadow_caster`
casts the new sun's shadows with it and :mod:`.relight` relights the views.

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

Deviations from the paper, with their reasons
---------------------------------------------
* **One quad per pixel footprint.** "We triangulate the shadow pixels in image space" is read as a mesh over the kept
  pixels' *footprints*: each kept pixel is the quad (two triangles) between its four pixel corners. A corner lies on
  the camera ray through it, at a receiver distance ``s_c``, lifted by a caster distance ``t_c``; both average, over
  the kept pixels touching the corner on the same surface as the pixel, each one's linear extrapolation to the corner.
  Two kept pixels are on the same surface when their receiver distances differ by at most :data:`SURFACE_JUMP` (5%)
  and their caster distances by at most :data:`CASTER_JUMP` (25%, or 8 pixel footprints). Neighbouring quads so share
  their corners (the sheet moves as one when the sun moves), the outline's corners sit on the receiver, and across a
  jump the quads separate instead of stretching. The plain reading (a vertex per shadow pixel centre) puts every
  outline pixel on the mesh's edge, where its own ray hits or misses at float32 rounding. On
  ``tests/test_relight.py``'s box-on-a-plane scene (96x72, exact proxy and shadow, 11 pairs of camera and sun,
  elevations 30-65 degrees), the mean IoU with the exact shadow at the capture sun and after 15 degrees of azimuth is
  0.93 and 0.87 with a vertex per pixel centre, 0.92 and 0.89 with corners averaged without extrapolation, 0.97 and
  0.65 with unshared quads, 0.97 and 0.93 with this construction (its two thresholds, module constants, chosen there).
* **Cluster filtering before filling**: no kept pixel borrows a dropped cluster's distance; a
  cluster with no proxy hit is always dropped.
* **Occluders the proxy lost** (by default, :attr:`RelightConfig.lost_occluders`, :mod:`.photo_occupancy`).
* **Supported parts of the dropped clusters** (by default, :attr:`RelightConfig.support_radius`,
  :mod:`.shadow_clusters`): their triangles are :attr:`Caster.uncertain`.
* **Ray offset.** Rays start ``ray_offset`` metres (0.02, a TSDF voxel, as Step 1) toward the sun from the receiver
  points, against self-intersection; the caster distances are measured from the receiver point itself.
* **Which lit pixels vote.** By default every pixel outside the shadow mask casts an ``epsilon`` ray; the caller may
  pass its own ``lit`` mask (a pixel whose ray misses the proxy has a filled receiver floating in the air).

Votes of every view (``method="multiview"``, beyond the paper)
---------------------------------------------------------------
A receiver point lit in *any* photograph is lit; the paper lets only the caster's own view say so.
Two uses of that evidence, both measured with ``benchmarks/bench_relight.py`` on four 480x360
scenes with MVS-like proxies (``docs/relight.md`` gives every figure):

* **Every view votes against every caster.** Each view's caster is tested again with the
  capture-sun rays of the lit pixels of all views (:func:`remove_contradicted`): triangles the
  own view's few rays could not condemn reach ``epsilon`` with several views.
* **The proxy completion is voted on too** (:func:`contradicted_primitives`): a proxy triangle
  first hit by more than ``epsilon`` lit rays of the views at the capture sun completes no shadow
  later (reconstruction noise, wrongly filled holes, light-letting foliage remnants). Hits nearer
  than ``completion_distance`` (0.6 m) along the new sun ray complete nothing: a noisy proxy
  shades itself there when the sun turns, while the true short-range shadows are the caster's;
  an exact proxy does not, and ``completion_distance="auto"`` (default) measures which
  (:func:`~mvintrinsic.shadow_caster.choose_completion_distance`).
* **Each view keeps its own caster** (``casters="own"``, as the paper): the union of all views'
  measured 0.6-3.1 dB lower with the true layers on courtyard_s1 (other views' sheets, lifted
  from receivers misplaced under lost foliage, shade the view's lit pixels): an option.

References
----------
.. [1] S. Duchêne, C. Riant, G. Chaurasia, J. Lopez-Moreno, P.-Y. Laffont, S. Popov, A. Bousseau
   and G. Drettakis, "Multi-View Intrinsic Images of Outdoors Scenes with an Application to
   Relighting", ACM Transactions on Graphics 34(5), 2015, Sec. 8.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from ._validation import as_array, as_unit_vector, config_or_default, describe, is_real
from .camera import Camera
from .photo_occupancy import OccupancyConfig
from .pixels import nearest_fill
from .planes import PlaneConfig
from .raytrace import DEFAULT_BATCH, Tracer, _ray_array, triangle_scene
from .shadow_clusters import TAU_S, kept_clusters, shadow_pixels, supported_parts

__all__ = ["capture_first_hits", "CASTER_JUMP", "CASTER_MODES", "ANCHOR_MODES", "CASTER_PIXEL_MODES", "DROPPED_MODES", "LOST_OCCLUDERS", "RELIGHT_METHODS", "SKY_ADJUSTMENTS", "SKY_PIXEL_MODES", "SURFACE_JUMP", "Caster", "RelightConfig", "build_caster", "contradicted_primitives", "kept_clusters", "merge_casters", "remove_contradicted", "shadow_pixels"]

#: ``primitive_ids`` of a ray that hits nothing (open3d's ``RaycastingScene.INVALID_ID``).
_INVALID_ID = np.iinfo(np.uint32).max

#: The environment adjustments of :attr:`RelightConfig.sky` (module docstring, "Adjusting shading").
SKY_ADJUSTMENTS = ("model", "paper")

#: The caster checks of :attr:`RelightConfig.method` (module docstring, "Votes of every view").
RELIGHT_METHODS = ("multiview", "paper")

#: Which caster shades a view, :attr:`RelightConfig.casters`.
CASTER_MODES = ("own", "merged")

#: Which other views' new visibility a pixel's is averaged with, :attr:`RelightConfig.fusion` (or None).
FUSION_MODES = ("capture", "all")
#: How the pixels of dropped shadow clusters are relit (:attr:`RelightConfig.dropped`).
DROPPED_MODES = ("light", "static", "none")
#: How the sky pixels change colour, :attr:`RelightConfig.sky_pixels`.
SKY_PIXEL_MODES = ("paper", "model", "input")
#: Which shadow pixels the caster is built from, :attr:`RelightConfig.caster_pixels`.
CASTER_PIXEL_MODES = ("paper", "labels")
#: How the capture ``v_sun`` anchors the new shadow layer, :attr:`RelightConfig.anchor` (or None).
ANCHOR_MODES = ("shadow", "both")
#: The default of :attr:`RelightConfig.lost_occluders`: :class:`OccupancyConfig` with the proxy's 1 px silhouette
#: band out of the evidence (``docs/relight.md``, "Occluders the proxy lost").
LOST_OCCLUDERS = OccupancyConfig(silhouette=1)


@dataclass(frozen=True)
class RelightConfig:
    """Options of the relighting geometry (paper Sec. 8), the paper's values as defaults where it gives one.

    Parameters
    ----------
    tau_s : float
        A pixel with ``v_sun < tau_s`` counts as shadow besides the shadow labels; in [0, 1]. 0.8: "We used tau_s =
        0.8 for all our results."
    caster_pixels : {"paper", "labels"}
        The shadow pixels the caster is built from (:data:`CASTER_PIXEL_MODES`). ``"paper"`` (default, Sec. 8): the
        labelled shadow or ``v_sun < tau_s``. ``"labels"`` (beyond the paper, for labels better than Step 3's): the
        labelled shadow alone; the pixels with ``v_sun < tau_s`` outside its kept clusters are dropped
        (:attr:`Caster.dropped`, relit as ``dropped`` says). With the true labels in Steps 3-4 and ``lost_occluders``,
        (e) - (a) at +-15 degrees 2.51 -> 3.01 dB (``bench_relight.py --true-labels``; the matting's soft ``v_sun``
        below 0.8 joins true shadows into clusters the rules drop whole); with Step 3's labels -0.31 to +0.09 dB, so
        not the default (``docs/relight.md``, "Perfect shadow labels").
    epsilon : int
        A caster triangle first hit by more than ``epsilon`` sun rays from lit pixels is removed; >= 0. 3: "We used
        epsilon = 3 for all our results."
    min_cluster : int
        Shadow clusters (8-connected) of fewer pixels are dropped; >= 1. 100: "less than 100 pixels".
    min_proxy_hits : float
        Shadow clusters in which a smaller share of the pixels' sun rays hit the proxy are dropped; in [0, 1]. 0.3:
        "less than 30% of the pixels yield an intersection".
    blur : float
        Standard deviation, pixels, of the Gaussian blur of the new shadow layer (0: none); >= 0. The paper applies "a
        small Gaussian blur" without a value; 1 pixel softens the edge to about the width of a photographed penumbra
        at these resolutions and closes one-pixel cracks. A per-pixel penumbra from the sun's angular size and the
        occluder distance instead scored 0.08-1.07 dB lower, and added in quadrature to the 1 px within 0.01 dB of it
        (``benchmarks/bench_relight.py --softness``, four 480x360 scenes, 20 suns).
    ray_offset : float
        Metres a sun ray starts from its receiver point along the sun direction, against self-intersection; >= 0. Not
        in the paper; 0.02 as Step 1's ``ray_offset`` (about a TSDF voxel).
    normal_smoothing : float
        Standard deviation (metres) of the smoothing of the proxy's vertex normals that give the receivers' ``max(0,
        cos w_sun)`` and the proxy's sun visibility at the new sun (:func:`mvintrinsic.raytrace.smooth_normals`); >=
        0, 0: the proxy's own normals. Not in the paper; 0.4 as Step 1's
        :attr:`~mvintrinsic.env_shading.Step1Config.normal_smoothing`, so that the relit ``S_sun`` uses the normals
        the decomposition used.
    planes : PlaneConfig or None
        The receivers' smoothed normals snapped to the proxy's dominant planes (:mod:`mvintrinsic.planes`), as
        :attr:`~mvintrinsic.env_shading.Step1Config.planes` (the same default, so that the relit ``S_sun`` uses the
        normals the decomposition used); None: the smoothed normals. Not in the paper.
    sky : {"model", "paper"}
        How the environment shading follows the sun (:data:`SKY_ADJUSTMENTS`, module docstring, "Adjusting shading").
        ``"paper"``: our reading of the paper's adjustment, a red shift of ``S_sky`` and ``S_ind`` scaled like the
        horizontal sun irradiance (:func:`paper_environment_factors`). ``"model"``: ``S_sky`` scaled per pixel normal
        by the fitted sky model's irradiance at the new sun over the old one (:func:`sky_irradiance_ratio`), ``S_ind``
        by the change of the sun irradiance on the receivers. Default ``"paper"``: neither wins on every scene
        (``docs/relight.md``).
    sky_pixels : {"paper", "model", "input"}
        How the pixels without an estimate that look at the sky (their ray misses the proxy above the horizon) change
        colour (:data:`SKY_PIXEL_MODES`, :func:`sky_pixel_factors`): the paper's red shift near the horizon (default:
        never below ``"input"`` on seven scenes, 0.6 to 1.5 dB above it at a higher sun), the fitted sky's radiance
        ratio, or the input's.
    turbidity : float
        Turbidity of the sky model used by ``sky="model"`` when the decomposition carries no fitted sky
        (``decomposition.lighting.sky is None``, e.g. a ground truth); > 0. 3.5, Step 1's starting value
        (:class:`~mvintrinsic.skymodel.SkyConfig`), "the turbidity of a clear sky". Only the shape of the sky matters:
        its scale cancels in the ratio.
    dropped : {"light", "static", "none"}
        How the pixels of dropped shadow clusters (too small or unsupported by the proxy, :func:`build_caster`: their
        occluder is unknown) are relit (:data:`DROPPED_MODES`). ``"light"`` (the paper, "We adjust the reflectance of
        such pixels to bring them in light using the v_sun layer"): their ``v_sun`` becomes 1 and their reflectance
        ``I / (S_sun + S_sky + S_ind)``, so the captured shadow stays in the reflectance and the shadow layer calls
        them lit (:class:`Relighter`). ``"static"`` (default, beyond the paper): their shadow stays in the shadow
        layer: at every sun their ``v'`` is their capture ``v_sun`` times the caster's, and their reflectance is the
        layers' (every view's shadow layer then shows the shadow its image shows; against ``"light"`` a higher relit
        PSNR on every scene's mean and a higher cross-view agreement, docs/relight.md). ``"none"``: the layers as they are,
        these pixels moved by the caster like every other (their shadow leaves: for layers whose shadow layer is given
        at every sun, as the benchmark's rows with the true shadows).
    method : {"multiview", "paper"}
        How the views' evidence is used (:data:`RELIGHT_METHODS`, module docstring, "Votes of every view").
        ``"paper"``: each view's caster is checked against that view's lit pixels only, and the proxy completes every
        shadow it casts on primitives the caster does not stand for. ``"multiview"`` (default, beyond the paper): the
        lit pixels of *every* view vote against every caster triangle and against every proxy triangle (a proxy
        triangle first hit by more than ``epsilon`` of their capture-sun rays casts no completion shadow), and the
        completion ignores proxy hits nearer than ``completion_distance``. Chosen by measurement
        (``benchmarks/bench_relight.py``, module docstring).
    casters : {"own", "merged"}
        ``"own"`` (default): every view is shaded by its own caster, as in the paper (its votes still come from every
        view with ``method="multiview"``). ``"merged"``: one caster, the union of all the views'
        (:func:`merge_casters`), shades every view. Chosen by measurement: other views' caster pieces shade lit pixels
        of a view (module docstring).
    completion_distance : float or "auto"
        ``method="multiview"``: proxy hits nearer than this many metres along the new sun ray complete no shadow; >=
        0. Self-shadowing by the proxy's own reconstruction noise sits there, while the short-range shadows the image
        shows (recesses, ledges) are already in the caster. ``"auto"`` (default, beyond the paper):
        :data:`~mvintrinsic.shadow_caster.AUTO_COMPLETION_DISTANCE` (0.6; 0.3, 0.6 and 1.0 measured, module
        docstring) when the proxy shades itself (:func:`~mvintrinsic.shadow_caster.proxy_self_shading`: at least
        :data:`~mvintrinsic.shadow_caster.SELF_SHADING_SHARE` of the lit pixels' sun rays hit the proxy within that
        distance at the capture sun), else 0: an exact proxy keeps its near shadows
        (:func:`~mvintrinsic.shadow_caster.choose_completion_distance`).
    ray_stride : int
        The new sun's shadow rays are cast from every ``ray_stride``-th pixel along both image axes, then from every
        pixel of the cells whose four sampled corners disagree (a shadow edge crosses them) and of their neighbour
        cells; a cell far from any such cell takes its corners' state. 1 casts from every pixel; >= 1. Not in the
        paper: the ray budget is spent only where the visibility varies, which halves the shadow time of a new sun at
        1000x750, while a shadow thinner than ``ray_stride`` pixels that touches no sampled pixel, far from any other
        edge, is lost (module docstring, "Speed": 2 changes the relit PSNR by -0.006 to +0.025 dB against 1).
    consistency : float or None
        A pixel the proxy does not explain keeps its capture ``v_sun`` at every new sun: its colour is at least
        ``consistency`` (median over the channels of ``|log I - log I_o|``, both in the decomposition's common
        exposure) from what each of the other views that see its receiver point (occlusion-tested) sees there,
        ``I_o``, or its ray misses the proxy. There the receiver point is not the surface the photograph shows (a
        crown in front of the facade the proxy kept), so the receiver's new shadow says nothing about the pixel. > 0;
        None: every pixel takes the moved shadow (the paper). Not in the paper; 0.3 as
        :attr:`~mvintrinsic.occluders.OccluderConfig.consistency`, not tuned. Chosen by measurement (module docstring
        of :mod:`mvintrinsic.relight`, "Pixels the proxy does not explain").
    fusion : {"capture", "all"} or None
        The new ``v'`` of a pixel is the mean of its own and of the other views' ``v'`` at the pixels that see its
        receiver point (depth-tested, as for ``consistency``), over the pixels the proxy explains on both sides (not
        flagged by ``consistency``; with ``consistency=None``, every pixel whose ray hits the proxy), weight 1 each:
        ``"capture"`` (default) only the views whose capture state there (``v_sun >= 0.5``) is the pixel's own, so
        that each view's reflectance, which its own label made, meets the shadow state it was made for; ``"all"``
        every such view (the relit shadow state agrees more across views, the relit images are further from the truth
        where the views' labels disagree); None: each view alone (the paper). Not in the paper (module docstring of
        :mod:`mvintrinsic.relight`, "One shadow in every view").
    lost_occluders : OccupancyConfig or None
        A shadow pixel another view confirms whose sun ray misses the proxy takes the distance at which the
        photographs see what the proxy lacks along it (a hit for the cluster rules, then at least ``min_hits``;
        :mod:`mvintrinsic.photo_occupancy`; beyond the paper; inert with fewer views than ``min_views``). Default
        ``OccupancyConfig(silhouette=1)`` (:data:`LOST_OCCLUDERS`): row (e) - (a) at +-15 degrees 2.42 dB on the five
        480x360 scenes (2.07 without), above the option off at all 22 of their scene-suns and on the 240x180 demo
        (where ``silhouette`` 0 loses 1.4 dB), -0.19 to +0.04 on dev_courtyard (``docs/relight.md``, "Occluders the
        proxy lost"). None: the paper.
    support_radius : int
        Pixels; a part of a shadow cluster the paper's rule drops is lifted when, within this radius, the share of
        its pixels whose rays find an occluder reaches the rule's (:func:`~mvintrinsic.shadow_clusters.supported_parts`:
        Step 3's labels join true shadows with unsupported ones into clusters the rule drops whole); >= 0, 0: the
        paper's rule alone. With ``lost_occluders``, the parts and their sheets are the expected image over
        the shadow and the paper's dropping (``belief``). Beyond the paper; 10 by default since 2026-12-07: with the
        other defaults of that day, row (e) - (a) at +-15 degrees 2.74 -> 3.07 dB and row (d) - (c) -2.81 -> -2.61
        (five 480x360 scenes; row (e) -0.10..+1.70 dB over 22 scene-suns, street_s2 -0.10..+0.04), each new sun
        0.081-0.099 s per view at 1000x750 against 0.059-0.072 with 0 (runs alone on the machine; slower machine
        states of earlier sessions up to 0.110 s; ``docs/relight.md``, "Supported parts of the shadow clusters").
    anchor : {"shadow", "both"} or None
        How the capture ``v_sun`` anchors the new shadow layer (:data:`ANCHOR_MODES`; beyond the paper). The caster's
        own shadow at the capture sun, ``C(d)``, is not the photograph's (a shadow it cannot cast, an edge a pixel off,
        the blur); ``v' = clip(C(d') + a, 0, 1)`` with the anchor ``a = v_sun - C(d)`` (``"both"``: at the capture sun
        ``v'`` is ``v_sun``, and only the caster's *change* moves a shadow) or ``a = min(0, v_sun - C(d))``
        (``"shadow"``: a captured shadow the caster does not cast stays, as a dropped cluster's does with
        ``dropped="static"``; where the caster shades more than the photograph, it is trusted). None: ``v' = C(d')``
        (the paper).
        Default ``"shadow"`` by measurement against None, with the other defaults (Step 1 and the relighter on the
        proxy's planes), on five 480x360 scenes and dev_courtyard (26 scene-suns; ``docs/relight.md``, "The anchor"):
        the full pipeline's row (e) of ``benchmarks/bench_relight.py`` +0.01 to +0.28 dB at 22, -0.01 to -0.11 at four
        (street_sky az-15, az-30, el+10; street_s2 az-30), every scene's mean up but street_sky's (-0.002); the true
        layers' row (d) +0.01 to +0.60 at 24, street_sky az-15 and az-30 -0.19 and -0.23. ``"both"`` keeps a caster
        edge a pixel off at every sun.
    """

    tau_s: float = TAU_S
    caster_pixels: str = "paper"
    epsilon: int = 3
    min_cluster: int = 100
    min_proxy_hits: float = 0.3
    blur: float = 1.0
    ray_offset: float = 0.02
    normal_smoothing: float = 0.4
    planes: PlaneConfig | None = field(default_factory=PlaneConfig)
    sky: str = "paper"
    sky_pixels: str = "paper"
    turbidity: float = 3.5
    dropped: str = "static"
    method: str = "multiview"
    casters: str = "own"
    completion_distance: float | str = "auto"
    ray_stride: int = 2
    consistency: float | None = 0.3
    fusion: str | None = "capture"
    lost_occluders: OccupancyConfig | None = LOST_OCCLUDERS
    support_radius: int = 10
    anchor: str | None = "shadow"

    def __post_init__(self) -> None:
        for name, allowed in (("method", RELIGHT_METHODS), ("casters", CASTER_MODES), ("fusion", FUSION_MODES),
                              ("dropped", DROPPED_MODES), ("sky_pixels", SKY_PIXEL_MODES),
                              ("caster_pixels", CASTER_PIXEL_MODES), ("anchor", ANCHOR_MODES)):
            value = getattr(self, name)
            if name in ("fusion", "anchor") and value is None:
                continue
            if not isinstance(value, str) or value not in allowed:
                raise ValueError(f"{name} must be one of {', '.join(map(repr, allowed))}, got {value!r}")
        if not isinstance(self.sky, str) or self.sky not in SKY_ADJUSTMENTS:
            raise ValueError(f"sky must be one of {', '.join(map(repr, SKY_ADJUSTMENTS))}, got {self.sky!r}")
        if not is_real(self.turbidity) or not 0.0 < self.turbidity < np.inf:
            raise ValueError(f"turbidity must be a finite number > 0, got {self.turbidity!r}")
        object.__setattr__(self, "turbidity", float(self.turbidity))
        for name, least in (("epsilon", 0), ("min_cluster", 1), ("ray_stride", 1), ("support_radius", 0)):
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
            if name == "completion_distance" and isinstance(value, str) and value == "auto":
                continue
            if not is_real(value) or not 0.0 <= value < np.inf:
                raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
            object.__setattr__(self, name, float(value))
        if self.consistency is not None:
            if not is_real(self.consistency) or not 0.0 < self.consistency < np.inf:
                raise ValueError(f"consistency must be a finite number > 0 or None, got {self.consistency!r}")
            object.__setattr__(self, "consistency", float(self.consistency))
        if not isinstance(self.planes, (PlaneConfig, type(None))):
            raise TypeError(f"planes must be a PlaneConfig or None, got {describe(self.planes)}")
        if not isinstance(self.lost_occluders, (OccupancyConfig, type(None))):
            raise TypeError(f"lost_occluders must be an OccupancyConfig or None, got {describe(self.lost_occluders)}")


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
        paper brings back into light (and, in a :class:`~mvintrinsic.relight.Relighter` with
        ``caster_pixels="labels"``, the ``v_sun < tau_s`` pixels it did not lift); ``None`` for a merged caster.
    n_clusters : int
        Number of 8-connected shadow clusters in the input mask.
    n_small : int
        Clusters dropped for having fewer than ``min_cluster`` pixels.
    n_unsupported : int
        Clusters of at least ``min_cluster`` pixels dropped for a share of proxy hits below
        ``min_proxy_hits`` (or no hit at all).
    n_removed : int
        Triangles removed for being first hit by more than ``epsilon`` rays from lit pixels.
    uncertain : (M,) bool or None
        Triangles lifted from :attr:`parts`: their new shadows may be mixed with those of the caster without them
        (``belief``, :meth:`~mvintrinsic.shadow_caster.ShadowCaster.sun_visibility`). None: none.
    uncertain_primitives : (J,) int64 or None
        The :attr:`proxy_primitives` only the rays of :attr:`parts` hit: without the parts they complete shadows
        (:meth:`~mvintrinsic.shadow_caster.ShadowCaster.completion_blocked`). None: none.
    parts : (H, W) bool or None
        The kept pixels outside the clusters the cluster rule keeps whole, the supported parts
        (:attr:`RelightConfig.support_radius`, :func:`~mvintrinsic.shadow_clusters.supported_parts`); None for a
        merged caster.

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
    uncertain: np.ndarray | None = None
    uncertain_primitives: np.ndarray | None = None
    parts: np.ndarray | None = None

    def __post_init__(self) -> None:
        vertices = as_array(self.vertices, "vertices", shape=(None, 3), dtype=np.float64)
        triangles = as_array(self.triangles, "triangles", shape=(None, 3), dtype=np.int32)
        for name, shape, dtype in (("uncertain", (len(triangles),), bool), ("uncertain_primitives", (None,), np.int64)):
            if getattr(self, name) is not None:
                object.__setattr__(self, name, as_array(getattr(self, name), name, shape=shape, dtype=dtype))
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
        if self.parts is not None:
            if self.shadow is None:
                raise ValueError("parts needs the shadow mask")
            object.__setattr__(self, "parts", as_array(self.parts, "parts", shape=self.shadow.shape, dtype=bool))
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


# ---------------------------------------------------------------------------------------------
# receiver
# ---------------------------------------------------------------------------------------------
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
    occluder_distance: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
) -> Caster:
    """Build the shadow caster of one view from its shadow pixels (paper Sec. 8, Fig. 9).

    Steps (module docstring): sun rays from the shadow pixels' receiver points against the proxy;
    the clusters :func:`kept_clusters` keeps; missed distances filled from the nearest kept pixel
    that hit; a quad over every kept pixel's footprint, lifted toward the sun; triangles first hit
    by more than ``config.epsilon`` sun rays from lit pixels removed.

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
    occluder_distance : callable, optional
        ``f(miss, sun) -> (H, W)`` metres to an occluder the proxy lacks for the shadow pixels
        ``miss`` whose rays miss it, ``inf`` if unknown (:attr:`RelightConfig.lost_occluders`).

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
    if occluder_distance is not None:  # beyond the paper: occluders the photographs show
        miss = shadow & ~np.isfinite(t)
        t = np.where(miss, occluder_distance(miss, sun), t)
    hit = np.isfinite(t)

    kept, *counts = kept_clusters(shadow, hit, config.min_cluster, config.min_proxy_hits)  # n_clusters, small, unsupported
    clusters = kept.copy()
    kept |= supported_parts(shadow, hit, config.min_cluster, config.min_proxy_hits, config.support_radius)
    dropped = shadow & ~kept
    primitives = np.unique(hits.triangle[kept[rows, cols] & hits.hit])

    if not kept.any():
        return Caster(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int32), primitives, kept, dropped, *counts, 0,
                      parts=np.zeros_like(kept))

    # Missed rays take the distance of the nearest kept pixel whose ray hit.
    valid = kept & hit
    lift = np.where(kept, nearest_fill(t, valid), 0.0)

    # Receiver distance from the camera centre (along the pixel ray for receiver_points' points).
    ray_distance = np.linalg.norm(receiver - camera.center, axis=-1)
    vertices, triangles = _footprint_mesh(camera, kept, ray_distance, lift, sun)
    # The supported parts' triangles (per kept pixel in np.nonzero order, _footprint_mesh's two halves) and the
    # proxy primitives only their rays hit are uncertain.
    parts = kept & ~clusters
    uncertain = np.tile(parts[kept], 2)
    uncertain_primitives = np.setdiff1d(hits.triangle[parts[rows, cols] & hits.hit],
                                        hits.triangle[clusters[rows, cols] & hits.hit]).astype(np.int64)

    # Triangles first hit by more than epsilon sun rays from lit pixels contradict the image.
    caster = Caster(vertices, triangles, primitives, kept, dropped, *counts, 0, uncertain, uncertain_primitives, parts)
    return remove_contradicted(caster, [receiver[lit]], sun, config=config, batch=batch)


def _first_hit_counts(vertices: np.ndarray, triangles: np.ndarray, points: Sequence[np.ndarray],
                      sun: np.ndarray, offset: float, batch: int) -> np.ndarray:
    """How many rays ``p + offset d + s d`` (``p`` in every array of ``points``) first hit each triangle."""
    import open3d as o3d

    counts = np.zeros(len(triangles), dtype=np.int64)
    if not len(triangles):
        return counts
    scene = triangle_scene(vertices, triangles)
    for array in points:
        for start in range(0, len(array), batch):
            origins = array[start:start + batch] + offset * sun
            ids = scene.cast_rays(o3d.core.Tensor.from_numpy(_ray_array(origins, sun)))["primitive_ids"].numpy()
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
                   n_removed=caster.n_removed + int(bad.sum()),
                   uncertain=None if caster.uncertain is None else caster.uncertain[~bad])


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
    config = config_or_default(config, RelightConfig)
    _, primitive = capture_first_hits(tracer, lit_points, sun_direction, config=config, batch=batch)
    return _contradicted(primitive, config.epsilon)


def capture_first_hits(tracer: Tracer, lit_points: Sequence[np.ndarray], sun_direction: np.ndarray, *,
                       config: RelightConfig | None = None, batch: int = DEFAULT_BATCH
                       ) -> tuple[np.ndarray, np.ndarray]:
    """The first proxy hit of every lit point's ray toward the sun: what the proxy says of the lit pixels.

    Rays start ``config.ray_offset`` toward the sun. One cast serves both uses of it:
    :func:`contradicted_primitives` (the primitives hit) and :func:`proxy_self_shading` (how near).

    Returns
    -------
    t : (N,) float32
        Distance from the point to the hit, metres; ``inf`` on a miss. ``N`` is the number of
        points over all arrays, in order.
    primitive : (N,) int64
        The primitive hit; -1 on a miss.
    """
    tracer = _check_tracer(tracer)
    config = config_or_default(config, RelightConfig)
    sun = as_unit_vector(sun_direction, "sun_direction")
    t, ids = [np.zeros(0, dtype=np.float32)], [np.zeros(0, dtype=np.int64)]
    for i, p in enumerate(lit_points):
        p = as_array(p, f"lit_points[{i}]", shape=(None, 3), dtype=np.float64)
        if len(p):
            distance, primitive = tracer.first_primitive(p, sun, t_min=config.ray_offset, batch=batch)
            t.append(distance)
            ids.append(primitive)
    return np.concatenate(t), np.concatenate(ids)


def _contradicted(primitive: np.ndarray, epsilon: int) -> np.ndarray:
    """The primitives first hit more than ``epsilon`` times, sorted (K,) int64."""
    return np.flatnonzero(np.bincount(primitive[primitive >= 0]) > epsilon).astype(np.int64)


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
    uncertain = unsure = None
    if any(c.uncertain is not None for c in casters):
        uncertain = np.concatenate([np.zeros(len(c.triangles), bool) if c.uncertain is None else c.uncertain
                                    for c in casters])
        # A primitive some caster stands for with certain pixels is certain in the merged one.
        own = [np.zeros(0, np.int64) if c.uncertain_primitives is None else c.uncertain_primitives for c in casters]
        sure = [np.setdiff1d(c.proxy_primitives, u) for c, u in zip(casters, own, strict=True)]
        unsure = np.setdiff1d(np.concatenate(own), np.concatenate(sure))
    return Caster(vertices, triangles.astype(np.int32), primitives, None, None,
                  sum(c.n_clusters for c in casters), sum(c.n_small for c in casters),
                  sum(c.n_unsupported for c in casters), sum(c.n_removed for c in casters), uncertain, unsure)


# ---------------------------------------------------------------------------------------------
# moving shadows
# ---------------------------------------------------------------------------------------------
