"""The decomposition pipeline: the paper's steps composed, and their configuration.

``decompose(scene)`` runs what is implemented so far: Step 1 (Sec. 4: environment map, sky model,
``S_sky``, ``S_ind`` and ``~v`` at the proxy vertices), Step 2 (Sec. 5: ``L_sun`` from
light/shadow pairs) and Step 3 (Sec. 6): shadow labels, then per view the per-pixel layers by
matting (Eq. 17); Step 4 (Sec. 7, :mod:`mvintrinsic.env_refine`): by default one reflectance per
surface point across the views (beyond the paper), or the paper's ``S_env`` offsets. The labels
come by default from all views at once at pixel resolution (:mod:`mvintrinsic.multiview_shadows`,
beyond the paper); ``Config(shadow=ShadowConfig(method="paper"))`` runs the paper's per-view
labelling instead (a colour segmentation and the MRF of Eq. 7, :mod:`mvintrinsic.shadow_mrf`).
``Config(steps=3)`` stops before Step 4, ``Config(steps=2)`` after Step 2 with
``R = I / (S_env + ~v S_sun)`` (Eq. 2 with the proxy visibility). Every stage is also a public
function, so a pipeline can be composed by hand::

    from mvintrinsic import env_shading, pipeline, raytrace
    tracer = raytrace.Tracer(scene.proxy)
    s1 = env_shading.step1(scene, tracer=tracer)
    quantities = pipeline.carry_to_pixels(scene, s1, tracer)
    calibration = pipeline.calibrate(scene, quantities)
    layers = {v.stem: pipeline.step2_layers(v, quantities[v.stem], calibration.sun_radiance) for v in scene.views}
    step3 = pipeline.step3(scene, quantities, calibration.sun_radiance)        # all views
    step4 = pipeline.step4(scene, quantities, {stem: v.layers for stem, v in step3[0].items()})
    paper = pipeline.step3_view(scene.views[0], quantities[scene.views[0].stem], calibration.sun_radiance,
                                config=Config(shadow=ShadowConfig(method="paper")))

Per-view work (``pixel_quantities``, ``find_sun_pairs``, ``step2_layers``, ``step3_view``, the
matting) depends only on the view and shared results (Step 1, ``L_sun``, the multi-view labels),
so it can be fanned out over processes: ``decompose(scene, client=client)`` with a
``dask.distributed.Client`` runs Step 2's pair search, Step 3's per-view segmentation, MRF and
matting (:func:`step3_view`) and the paper's Step 4 offsets as one task per view on its cluster,
with identical results (``docs/distributed.md``).
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ._cluster import _as_client, _ViewTasks
from ._validation import config_or_default
from .correspondence import Correspondences
from .env_refine import EnvRefineConfig, Step4Result, refine, refine_environment
from .env_shading import Step1Config, Step1Result, step1
from .exposure import ExposureConfig, compensate, estimate_view_gains, restore_units
from .laplacian import SolveReport
from .matting import MattingConfig, intrinsic_layers_result
from .model_choice import (
    choose_cast_shadows,
    choose_direct_sun,
    choose_occluders,
    choose_step4,
    sky_choice,
)
from .multiview_shadows import MultiViewShadowConfig, MultiViewShadowLabels, PixelShadowLabels, label_shadows_multiview
from .occluders import OccluderConfig, carve_occluders, occluded_step1, seen_occluders, smooth_occluder_reflectance
from .photo_occupancy import ClearRaysConfig, OccupancyConfig
from .pixels import PixelQuantities, layers_from_shading, pixel_quantities
from .planes import PlaneConfig
from .raytrace import Tracer, depth_map
from .resolution import downscale_scene, upsample_layers
from .results import SHADOW_LABELS, Decomposition, IntrinsicLayers, Lighting, ModelChoice
from .scene import Scene, View
from .segmentation import Segmentation, SegmentationConfig, segment
from .shadow_mrf import ShadowConfig, ShadowLabels, label_shadows
from .skymodel import SkyConfig
from .sun_calibration import SunCalibration, SunConfig, SunPairs, calibrate_sun, find_sun_pairs

__all__ = ["PRESETS", "Config", "Step3View", "calibrate", "carry_to_pixels", "choose_direct_sun", "decompose",
           "environment_layers", "choose_cast_shadows", "label_layers", "sky_choice", "step2_layers", "step3", "step3_view", "step4"]

logger = logging.getLogger(__name__)

@dataclass(frozen=True)
class Config:
    """Configuration of the whole pipeline: one dataclass per stage, the paper's values as defaults.

    Parameters
    ----------
    exposure : ExposureConfig
        Per-view exposure and white-balance gains, estimated from the proxy points the views
        share and compensated before Step 1 when they differ from 1 (beyond the paper,
        :mod:`mvintrinsic.exposure`).
    step1 : Step1Config
        Environment map, sky model and ray-traced shading (Sec. 4).
    sun : SunConfig
        Sun calibration (Sec. 5).
    segmentation : SegmentationConfig
        Colour over-segmentation of each view (Sec. 6.1).
    shadow : ShadowConfig
        Which shadow labelling Step 3 runs (``method``) and the paper's MRF (Sec. 6.1, Eqs. 6-16).
    multiview : MultiViewShadowConfig
        The multi-view, pixel-level labelling (``shadow.method="multiview"``, the default).
    matting : MattingConfig or None
        Per-pixel visibility and shading (Sec. 6.2). None skips the matting (beyond the paper,
        for speed): ``v_sun`` is the shadow labels (1 lit, 0 shadow, the proxy's ``~v`` where
        undecided) softened by a Gaussian of :data:`LABEL_SOFTNESS` pixels, and the environment
        shading is Step 1's per pixel (Eq. 17 as in Step 2).
    env_refine : EnvRefineConfig
        Step 4 (Sec. 7): the multi-view reflectance fusion (default) or the paper's ``S_env``
        offsets (:mod:`mvintrinsic.env_refine`).
    occluders : OccluderConfig or None
        Beyond the paper (:mod:`mvintrinsic.occluders`): after Step 3, when the proxy cannot cast
        most of the labelled shadow (``OccluderConfig.when``, recorded in ``lighting.json``
        "model"), carve the occluders it lost (tree crowns, poles) from the shadows and the
        photos, integrate ``S_sky`` and ``S_ind`` again with them, and run Steps 2 and 3 again;
        after Step 4, the shadowed pixels that see an occluder take a smooth reflectance
        (``OccluderConfig.reflectance_smoothing``).
        On the four synthetic scenes whose proxy lost their trees it brought the umbra's ``S_env``
        from +36..+91% of the truth to -16..+36% and ``L_sun`` toward the truth, and lowered both
        LMSEs at 480x360; it about triples the time of Steps 1-3 there (``docs/step4.md``). None:
        off (the ``"paper"`` and ``"fast"`` presets).
    scale : float
        Working resolution, in (0, 1]: the views are area-averaged to ``scale`` times their size
        (but not below :data:`MIN_WORKING_SIDE` pixels on their longer side), decomposed, and the
        layers carried back to full size (beyond the paper,
        :mod:`mvintrinsic.resolution`: bilinear shading, ``v_sun`` guided by the photo, then
        ``R = I / S`` at full size). 1 (default) decomposes at full size.
    max_side : int or None
        Working resolution as a size: the views are decomposed with their longer side at most this
        many pixels (the smaller of this and ``scale``; never below :data:`MIN_WORKING_SIDE`), so
        that the cost per view is bounded whatever the photos' size. None (default): ``scale``
        alone.
    steps : {2, 3, 4}
        Last step run: 2 gives the Step-2 layers (proxy visibility), 3 the Step-3 layers, 4
        (default) the Step-4 layers.
    allow_missing_sun : bool
        With ``SunConfig(direct_sun="always")`` (the paper; the default ``"auto"`` decides that a
        scene without pairs has no direct sun, :func:`choose_direct_sun`), when no light/shadow
        pair survives: False raises
        :class:`~mvintrinsic.sun_calibration.SunCalibrationError`; True uses ``L_sun = 0`` (all
        light treated as environment light; see :func:`~mvintrinsic.sun_calibration.calibrate_sun`).
    seed : int
        Seeds every random choice (RANSAC, hemisphere sampling).
    """

    step1: Step1Config = field(default_factory=Step1Config)
    exposure: ExposureConfig = field(default_factory=ExposureConfig)
    sun: SunConfig = field(default_factory=SunConfig)
    segmentation: SegmentationConfig = field(default_factory=SegmentationConfig)
    shadow: ShadowConfig = field(default_factory=ShadowConfig)
    multiview: MultiViewShadowConfig = field(default_factory=MultiViewShadowConfig)
    matting: MattingConfig | None = field(default_factory=MattingConfig)
    env_refine: EnvRefineConfig = field(default_factory=EnvRefineConfig)
    occluders: OccluderConfig | None = field(default_factory=OccluderConfig)
    scale: float = 1.0
    max_side: int | None = None
    steps: int = 4
    allow_missing_sun: bool = False
    seed: int = 0

    def __post_init__(self) -> None:
        if not isinstance(self.step1, Step1Config):
            raise TypeError(f"step1 must be a Step1Config, got {type(self.step1).__name__}")
        for name, kind in (("exposure", ExposureConfig), ("sun", SunConfig), ("segmentation", SegmentationConfig),
                           ("shadow", ShadowConfig),
                           ("multiview", MultiViewShadowConfig), ("matting", MattingConfig),
                           ("env_refine", EnvRefineConfig), ("occluders", OccluderConfig)):
            if name in ("matting", "occluders") and getattr(self, name) is None:
                continue
            if not isinstance(getattr(self, name), kind):
                raise TypeError(f"{name} must be a {kind.__name__}, got {type(getattr(self, name)).__name__}")
        if isinstance(self.scale, bool) or not isinstance(self.scale, (int, float)) or not 0.0 < self.scale <= 1.0:
            raise ValueError(f"scale must be a number in (0, 1], got {self.scale!r}")
        if self.max_side is not None and (isinstance(self.max_side, bool) or not isinstance(self.max_side, int)
                                          or self.max_side < 1):
            raise ValueError(f"max_side must be a positive integer (pixels) or None, got {self.max_side!r}")
        if self.steps not in (2, 3, 4) or isinstance(self.steps, bool):
            raise ValueError(f"steps must be 2, 3 or 4, got {self.steps!r}")
        if not isinstance(self.allow_missing_sun, bool):
            raise TypeError(f"allow_missing_sun must be a bool, got {self.allow_missing_sun!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int):
            raise TypeError(f"seed must be an int, got {self.seed!r}")

    @classmethod
    def preset(cls, name: str) -> Config:
        """A named trade of speed against accuracy (:data:`PRESETS`; ``docs/presets.md`` charts them).

        Parameters
        ----------
        name : {"fast", "balanced", "paper", "best"}
            * ``"fast"``: a quick look. The views decomposed with their longer side at
              :data:`FAST_SIDE` pixels (:mod:`mvintrinsic.resolution`), 16 Step-1 rays on a
              0.2 m grid, normals smoothed over 0.2 m, one labelling pass, no occluder carving, no
              matting (``v_sun`` from the labels, :func:`label_layers`). Measured on 6 views of
              timing_1000 (1000x750, ``docs/presets.md``, before the occluder carving existed):
              2.3 s per view, reflectance LMSE 0.059 (with the matting 3.5 s and 0.049).
            * ``"balanced"``: the defaults with the longer side at :data:`BALANCED_SIDE` pixels:
              16 views at 1000x750 in 158 s end to end and 3.2 GB (``docs/presets.md``, before the
              occluder carving, which adds a second pass of Steps 2-3 where it runs); photos of at
              most that size are decomposed as by ``Config()``.
            * ``"paper"``: the paper's method as published (Duchêne et al. 2015): the per-view
              colour segmentation and MRF of Sec. 6.1, matting (Sec. 6.2), Step 4's ``S_env``
              offsets (Sec. 7), the proxy's own normals, the Preetham sky, direct sun assumed,
              no exposure compensation, no sky colour test and no occluder carving.
            * ``"best"``: the defaults with four times the Step-1 rays (256, a 16 x 16 stratified
              grid: 1.05% median Monte Carlo error against 2.6% with 64; 128 rays, not a square,
              are stratified in one dimension only and gave 2.7%, ``docs/presets.md``) and two
              consensus passes of the labelling.

        Returns
        -------
        Config

        Raises
        ------
        ValueError
            If ``name`` is not one of :data:`PRESETS`.
        """
        if name not in PRESETS:
            raise ValueError(f"preset must be one of {sorted(PRESETS)}, got {name!r}")
        base = cls()
        if name == "balanced":
            return dataclasses.replace(base, max_side=BALANCED_SIDE)
        if name == "fast":
            return dataclasses.replace(
                base, max_side=FAST_SIDE, matting=None, occluders=None,
                step1=dataclasses.replace(base.step1, n_rays=16, subsample=0.2, normal_smoothing=0.2),
                multiview=dataclasses.replace(base.multiview, iterations=1))
        if name == "paper":
            return dataclasses.replace(
                base, exposure=ExposureConfig(method="none"), shadow=ShadowConfig(method="paper"), occluders=None,
                env_refine=EnvRefineConfig(method="paper"),
                sun=dataclasses.replace(base.sun, direct_sun="always", min_pair_contrast=None),
                step1=dataclasses.replace(base.step1, normal_smoothing=0.0, planes=None, sky_colour_tolerance=None,
                                          sky=dataclasses.replace(base.step1.sky, model="preetham")))
        return dataclasses.replace(  # "best"
            base, step1=dataclasses.replace(base.step1, n_rays=256),
            multiview=dataclasses.replace(base.multiview, consensus_passes=2))

    def to_dict(self) -> dict[str, Any]:
        """JSON-compatible nested mapping (the ``config`` key of ``lighting.json``)."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> Config:
        """Build from a (possibly partial) nested mapping, e.g. a parsed JSON or TOML file.

        Missing keys keep their defaults; an unknown key raises ``ValueError`` naming it.
        """
        return _from_dict(cls, data, "config")


#: The names :meth:`Config.preset` knows, from the fastest to the most work.
PRESETS = ("fast", "balanced", "paper", "best")
#: Longer side (pixels) of the working views of the "fast" and "balanced" presets.
FAST_SIDE = 400
BALANCED_SIDE = 640

_NESTED = {"step1": Step1Config, "exposure": ExposureConfig, "sun": SunConfig, "sky": SkyConfig,
           "segmentation": SegmentationConfig,
           "shadow": ShadowConfig, "multiview": MultiViewShadowConfig, "matting": MattingConfig,
           "env_refine": EnvRefineConfig, "occluders": OccluderConfig, "clear_rays": ClearRaysConfig,
           "occupancy": OccupancyConfig, "planes": PlaneConfig}


def _from_dict(kind: type, data: Mapping[str, Any], where: str) -> Any:
    if not isinstance(data, Mapping):
        raise ValueError(f"{where} must be a mapping, got {type(data).__name__}")
    names = {f.name for f in dataclasses.fields(kind)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ValueError(f"{where}: unknown key(s) {unknown}; known keys are {sorted(names)}")
    values = {}
    for key, value in data.items():
        nested = _NESTED.get(key)
        if nested is not None and isinstance(value, Mapping):
            value = _from_dict(nested, value, f"{where}.{key}")
        elif isinstance(value, list):
            value = tuple(value)
        values[key] = value
    try:
        return kind(**values)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{where}: {exc}") from None


def carry_to_pixels(scene: Scene, step1_result: Step1Result, tracer: Tracer, *, progress: bool = False
                    ) -> dict[str, PixelQuantities]:
    """Step-1 quantities of every view, per pixel (:func:`mvintrinsic.pixels.pixel_quantities`)."""
    from tqdm.auto import tqdm

    return {view.stem: pixel_quantities(view, step1_result, tracer, sun_direction=scene.sun.direction)
            for view in tqdm(scene.views, desc="pixels", unit="view", disable=not progress)}


def calibrate(scene: Scene, quantities: Mapping[str, PixelQuantities], *, config: Config | None = None,
              progress: bool = False) -> SunCalibration:
    """Step 2 (Sec. 5): light/shadow pairs in every view, then ``L_sun`` (per-channel median)."""

    config = config or Config()
    return calibrate_sun(_sun_pairs(scene, quantities, config=config, progress=progress),
                         allow_missing=config.allow_missing_sun)


def step2_layers(view: View, quantities: PixelQuantities, sun_radiance: np.ndarray) -> IntrinsicLayers:
    """The Step-2 intrinsic layers of a view: ``R = I / (S_sky + S_ind + ~v S_sun)`` (Eqs. 2, 17).

    ``v_sun`` is the proxy visibility ``~v`` carried to the pixels; the shadow labels threshold it
    at 1/2. Sky and invalid pixels hold zeros and label 128. Where the total shading is below
    :data:`~mvintrinsic.pixels.SHADING_FLOOR` times the view's median, ``S_ind`` is raised so that
    it reaches that floor (:func:`~mvintrinsic.pixels.layers_from_shading`).

    Parameters
    ----------
    view : View
    quantities : PixelQuantities
        The view's per-pixel Step-1 quantities.
    sun_radiance : (3,) array_like
        ``L_sun``, shading units.

    Returns
    -------
    IntrinsicLayers
    """
    if view.stem != quantities.stem or view.camera.shape != quantities.shape:
        raise ValueError(f"quantities ({quantities.stem!r}) do not belong to view {view.stem!r}")
    valid = quantities.valid
    labels = np.where(quantities.visibility >= 0.5, SHADOW_LABELS["lit"], SHADOW_LABELS["shadow"]).astype(np.uint8)
    return layers_from_shading(view, valid, quantities.sky, quantities.indirect, quantities.visibility,  # Eqs. 2, 17
                               quantities.cosine, sun_radiance, labels)


@dataclass(frozen=True, eq=False)
class Step3View:
    """Step 3 of one view: its shadow labels and per-pixel layers, and the seconds spent.

    Parameters
    ----------
    segmentation : Segmentation or None
        The view's colour clusters (the paper's labelling works on them; the matting uses their
        boundaries with either labelling); None when neither needs them (multi-view labels
        without matting).
    shadow : ShadowLabels or PixelShadowLabels
        The paper's per-cluster labels, or the view's share of the multi-view labels.
    layers : IntrinsicLayers
    timings : mapping of str to float
        ``segmentation``, ``shadow_mrf`` (paper only; the multi-view labelling is shared by all
        views, see :func:`step3`) and ``matting`` (or ``layers`` without matting) seconds.
    solves : tuple of SolveReport
        How each linear system of the matting was solved (converged, iterations, residual;
        :class:`~mvintrinsic.laplacian.SolveReport`); empty without matting.
    """

    segmentation: Segmentation | None
    shadow: ShadowLabels | PixelShadowLabels
    layers: IntrinsicLayers
    timings: Mapping[str, float]
    solves: tuple[SolveReport, ...] = ()


def step3_view(view: View, quantities: PixelQuantities, sun_radiance: np.ndarray, *,
               config: Config | None = None, labels: PixelShadowLabels | None = None) -> Step3View:
    """Step 3 (Sec. 6) on one view: shadow labels, matting and layers.

    With ``config.shadow.method == "paper"``: the paper's segmentation and shadow MRF on this view
    alone, then matting. With ``"multiview"``: the segmentation and matting with the view's share
    of the multi-view labels, which must be given (:func:`step3` computes them for all views).

    Parameters
    ----------
    view : View
    quantities : PixelQuantities
        The view's per-pixel Step-1 quantities (:func:`carry_to_pixels`).
    sun_radiance : (3,) array_like
        ``L_sun`` from Step 2.
    config : Config, optional
    labels : PixelShadowLabels, optional
        The view's multi-view labels (method ``"multiview"`` only).

    Returns
    -------
    Step3View
    """
    config = config or Config()
    multiview = config.shadow.method == "multiview"
    if multiview and (not isinstance(labels, PixelShadowLabels) or labels.stem != view.stem):
        raise ValueError(f"labels: the multi-view labelling needs the PixelShadowLabels of view {view.stem!r} "
                         f"(pipeline.step3 computes them for all views), got {labels!r}")
    if not multiview and labels is not None:
        raise ValueError("labels are only taken with config.shadow.method == 'multiview'")
    timings = {}
    # The segmentation serves the matting under both labellings: its cluster boundaries are kept
    # out of the shading constraints and matted for visibility (Sec. 6.2). Without them the demo's
    # reflectance LMSE rose from 0.070 to 0.104 with the multi-view labels, 0.122 with the true ones.
    seg = None
    if config.matting is not None or not multiview:
        start = time.perf_counter()
        seg = segment(view.image, mask=quantities.valid, config=config.segmentation)
        timings["segmentation"] = time.perf_counter() - start
    if multiview:
        shadow = labels
    else:
        start = time.perf_counter()
        shadow = label_shadows(view.image, quantities, seg, sun_radiance, config=config.shadow)
        timings["shadow_mrf"] = time.perf_counter() - start
    start = time.perf_counter()
    solves: tuple[SolveReport, ...] = ()
    if config.matting is None:
        layers = label_layers(view, quantities, shadow.labels, sun_radiance)
        timings["layers"] = time.perf_counter() - start
    else:
        matted = intrinsic_layers_result(view, quantities, shadow.labels, sun_radiance, clusters=seg.labels,
                                         config=config.matting)
        layers, solves = matted.layers, matted.solves
        timings["matting"] = time.perf_counter() - start
    return Step3View(segmentation=seg, shadow=shadow, layers=layers, timings=timings, solves=solves)


#: Standard deviation (pixels) of the Gaussian that softens the shadow labels into ``v_sun`` when
#: the matting is skipped (``Config(matting=None)``): about a penumbra's width at the test scenes'
#: resolution, so that a label edge is not a one-pixel step in the reflectance.
LABEL_SOFTNESS = 0.7


def label_layers(view: View, quantities: PixelQuantities, labels: np.ndarray, sun_radiance: np.ndarray
                 ) -> IntrinsicLayers:
    """The layers of a view straight from its shadow labels, without matting (``Config(matting=None)``).

    ``v_sun`` is 1 on lit, 0 on shadow and the proxy's ``~v`` on undecided pixels, softened by a
    Gaussian of :data:`LABEL_SOFTNESS` pixels (normalised over the valid pixels); ``S_sky`` and
    ``S_ind`` are Step 1's per pixel; then Eqs. 2, 3 and 17 as in :func:`step2_layers`.

    Parameters
    ----------
    view : View
    quantities : PixelQuantities
        The view's per-pixel Step-1 quantities.
    labels : (H, W) uint8
        0 shadow, 255 lit, 128 undecided.
    sun_radiance : (3,) array_like
        ``L_sun``.

    Returns
    -------
    IntrinsicLayers
    """
    from scipy import ndimage

    if view.stem != quantities.stem or view.camera.shape != quantities.shape or labels.shape != view.shape:
        raise ValueError(f"quantities and labels must belong to view {view.stem!r}")
    valid = quantities.valid
    hard = np.where(labels == SHADOW_LABELS["lit"], 1.0,
                    np.where(labels == SHADOW_LABELS["shadow"], 0.0, quantities.visibility))
    weight = ndimage.gaussian_filter(valid.astype(np.float64), LABEL_SOFTNESS, mode="nearest")
    soft = ndimage.gaussian_filter(np.where(valid, hard, 0.0), LABEL_SOFTNESS, mode="nearest")
    visibility = np.clip(np.divide(soft, weight, out=hard.astype(np.float64), where=weight > 1e-6), 0.0, 1.0)
    return layers_from_shading(view, valid, quantities.sky, quantities.indirect, visibility,  # Eqs. 2, 3, 17
                               quantities.cosine, sun_radiance, labels)


def step3(scene: Scene, quantities: Mapping[str, PixelQuantities], sun_radiance: np.ndarray, *,
          config: Config | None = None, progress: bool = False) -> tuple[dict[str, Step3View], dict[str, float]]:
    """Step 3 (Sec. 6) on every view: shadow labels, then per view matting and layers.

    With ``config.shadow.method == "multiview"`` (default) the labels of all views come from one
    :func:`~mvintrinsic.multiview_shadows.label_shadows_multiview`; with ``"paper"`` each view is
    labelled alone (:func:`step3_view`).

    Parameters
    ----------
    scene : Scene
    quantities : mapping of str to PixelQuantities
        Per view (:func:`carry_to_pixels`).
    sun_radiance : (3,) array_like
        ``L_sun`` from Step 2.
    config : Config, optional
    progress : bool, optional

    Returns
    -------
    views : dict of str to Step3View
    timings : dict of str to float
        Seconds summed over views: ``shadow_labels`` and its parts ``shadow_labels.<part>``
        (multi-view) or ``shadow_mrf`` (paper), ``segmentation`` and ``matting``.
    """
    views, timings, _ = _step3(scene, quantities, sun_radiance, config=config, progress=progress)
    return views, timings


def _step3(scene: Scene, quantities: Mapping[str, PixelQuantities], sun_radiance: np.ndarray, *,
           config: Config | None, progress: bool
           ) -> tuple[dict[str, Step3View], dict[str, float], MultiViewShadowLabels | None]:
    """:func:`step3`, and the multi-view labelling (None with the paper's) for Step 4 to reuse."""
    from tqdm.auto import tqdm

    config = config or Config()
    timings: dict[str, float] = {}
    shared = _multiview_labels(scene, quantities, sun_radiance, config=config, timings=timings, progress=progress)
    views = {}
    for view in tqdm(scene.views, desc="step 3", unit="view", disable=not progress):
        result = step3_view(view, quantities[view.stem], sun_radiance, config=config,
                            labels=None if shared is None else shared[view.stem])
        views[view.stem] = result
        for name, seconds in result.timings.items():
            timings[name] = timings.get(name, 0.0) + seconds
    return views, timings, shared


def _multiview_labels(scene: Scene, quantities: Mapping[str, PixelQuantities], sun_radiance: np.ndarray, *,
                      config: Config, timings: dict[str, float], progress: bool) -> MultiViewShadowLabels | None:
    """The labels of all views at once (``shadow.method == "multiview"``; None with ``"paper"``),
    timed into ``timings``."""
    if config.shadow.method != "multiview":
        return None
    start = time.perf_counter()
    shared = label_shadows_multiview(scene.views, quantities, sun_radiance, config=config.multiview,
                                     up=scene.up, sun_direction=scene.sun.direction, progress=progress)
    timings["shadow_labels"] = time.perf_counter() - start
    timings.update({f"shadow_labels.{k}": v for k, v in shared.timings.items()})
    return shared


def _step3_task(inputs: tuple[View, PixelQuantities], labels: PixelShadowLabels | None, *, sun_radiance: np.ndarray,
                config: Config) -> tuple[IntrinsicLayers, dict[str, float], list[dict]]:
    """A task: :func:`step3_view` of one view, its layers, timings and solve reports only (the rest stays on the worker)."""
    view, quantities = inputs
    result = step3_view(view, quantities, sun_radiance, config=config, labels=labels)
    return result.layers, dict(result.timings), [report.to_dict() for report in result.solves]


def _sun_pairs_task(inputs: tuple[View, PixelQuantities], *, config: SunConfig) -> SunPairs:
    """A task: :func:`~mvintrinsic.sun_calibration.find_sun_pairs` of one view."""
    view, quantities = inputs
    return find_sun_pairs(view, quantities, config=config)


def _offsets_task(inputs: tuple[View, PixelQuantities], step3_result: tuple[IntrinsicLayers, dict[str, float], list], *,
                  config: EnvRefineConfig) -> IntrinsicLayers:
    """A task: the paper's Step 4 on one view (:func:`~mvintrinsic.env_refine.refine_environment`), its layers."""
    return refine_environment(inputs[0].image, step3_result[0], config=config).layers


def _step3_layers(scene: Scene, quantities: Mapping[str, PixelQuantities], sun_radiance: np.ndarray, *,
                  config: Config, progress: bool, tasks: _ViewTasks | None, inputs: Mapping[str, Any] | None
                  ) -> tuple[dict[str, IntrinsicLayers], dict[str, float], MultiViewShadowLabels | None,
                             dict[str, Any], dict[str, list[dict]]]:
    """Step 3 for :func:`decompose`: the layers, timings (as :func:`step3`'s), the multi-view labelling,
    on a cluster (``tasks``) the per-view task futures (for Step 4 to start from in place), and each
    view's matting solve reports (JSON-ready)."""
    from tqdm.auto import tqdm

    timings: dict[str, float] = {}
    shared = _multiview_labels(scene, quantities, sun_radiance, config=config, timings=timings, progress=progress)
    if tasks is None:
        results = {}
        for view in tqdm(scene.views, desc="step 3", unit="view", disable=not progress):
            results[view.stem] = _step3_task((view, quantities[view.stem]), None if shared is None else shared[view.stem],
                                             sun_radiance=sun_radiance, config=config)
        futures: dict[str, Any] = {}
    else:
        start = time.perf_counter()
        labels = ({s: None for s in scene.stems} if shared is None
                  else tasks.scatter({s: shared[s] for s in scene.stems}))  # each to its view's worker
        timings["scatter"] = time.perf_counter() - start
        start = time.perf_counter()
        futures = tasks.submit("step3", _step3_task, {s: (inputs[s], labels[s]) for s in scene.stems},
                               sun_radiance=np.asarray(sun_radiance), config=config)
        results = tasks.gather(futures, desc="step 3", progress=progress)
        timings["cluster.step3"] = time.perf_counter() - start
    layers, solves = {}, {}
    for stem in scene.stems:
        layers[stem], view_timings, solves[stem] = results[stem]
        for name, seconds in view_timings.items():
            timings[name] = timings.get(name, 0.0) + seconds
    return layers, timings, shared, futures, solves


def step4(scene: Scene, quantities: Mapping[str, PixelQuantities], layers: Mapping[str, IntrinsicLayers], *,
          correspondences: Correspondences | None = None, config: Config | None = None) -> Step4Result:
    """Step 4 (Sec. 7) on every view: :func:`mvintrinsic.env_refine.refine` with ``config.env_refine``.

    Parameters
    ----------
    scene : Scene
    quantities : mapping of str to PixelQuantities
        Per view (:func:`carry_to_pixels`).
    layers : mapping of str to IntrinsicLayers
        Step 3's layers per view (``{stem: v.layers for stem, v in step3(...)[0].items()}``).
    correspondences : Correspondences, optional
        Those of the multi-view labelling, when at hand; found from ``quantities`` otherwise.
    config : Config, optional

    Returns
    -------
    Step4Result
    """
    config = config or Config()
    return refine(scene.views, layers, quantities=quantities, correspondences=correspondences,
                  config=config.env_refine)


#: Longer side (pixels) below which ``Config.scale`` does not shrink the views: Step 2 walks 30 px
#: from each boundary and the labels' edge radii reach 11 px, so much smaller working images lose
#: the shadows (the demo's 240x180 views at scale 1/2 gave no light/shadow pair at all).
MIN_WORKING_SIDE = 400


def working_scale(scene: Scene, scale: float, max_side: int | None = None) -> float:
    """The scale the views are decomposed at: ``scale``, or less so that the longest side is at most
    ``max_side`` pixels, but never smaller than :data:`MIN_WORKING_SIDE` allows."""
    longest = max(max(v.shape) for v in scene.views)
    wanted = float(scale) if max_side is None else min(float(scale), max_side / longest)
    return min(1.0, max(wanted, min(1.0, MIN_WORKING_SIDE / longest)))


def _sun_pairs(scene: Scene, quantities: Mapping[str, PixelQuantities], *, config: Config, progress: bool,
               tasks: _ViewTasks | None = None, inputs: Mapping[str, Any] | None = None) -> list[SunPairs]:
    """Every view's light/shadow pairs, in scene order: here, or one task per view on a cluster (``tasks``)."""
    from tqdm.auto import tqdm

    if tasks is None:
        return [find_sun_pairs(view, quantities[view.stem], config=config.sun)
                for view in tqdm(scene.views, desc="sun pairs", unit="view", disable=not progress)]
    futures = tasks.submit("sun-pairs", _sun_pairs_task, {s: (inputs[s],) for s in scene.stems}, config=config.sun)
    pairs = tasks.gather(futures, desc="sun pairs", progress=progress)
    return [pairs[s] for s in scene.stems]


def environment_layers(view: View, quantities: PixelQuantities, sun_radiance: np.ndarray | None = None
                       ) -> IntrinsicLayers:
    """The layers of a view without a cast shadow: every valid pixel lit, ``v_sun = 1``.

    Without direct sun (``sun_radiance`` None or 0) ``R = I / S_env`` (Eq. 2 with ``L_sun = 0``);
    with direct sun but no cast shadow in view, ``R = I / (S_env + L_sun cos)``. ``S_sky`` and
    ``S_ind`` are Step 1's per pixel, floored as everywhere
    (:func:`~mvintrinsic.pixels.layers_from_shading`).
    """
    labels = np.full(view.shape, SHADOW_LABELS["lit"], np.uint8)
    radiance = np.zeros(3) if sun_radiance is None else np.asarray(sun_radiance, dtype=np.float64)
    return layers_from_shading(view, quantities.valid, quantities.sky, quantities.indirect,
                               np.ones(view.shape), quantities.cosine, radiance, labels)


def _steps_2_3(scene: Scene, quantities: Mapping[str, PixelQuantities], *, config: Config, progress: bool,
               tasks: _ViewTasks | None, inputs: Any, timings: dict[str, float]) -> tuple:
    """Steps 2 and 3 of :func:`decompose` on the given pixel quantities (seconds into ``timings``)."""
    logger.info("step 2: sun calibration over %d views", len(scene.views))
    start = time.perf_counter()
    model: dict[str, ModelChoice] = {}
    if config.sun.direct_sun == "always":  # calibrate(), its pairs found on the cluster
        pairs = _sun_pairs(scene, quantities, config=config, progress=progress, tasks=tasks, inputs=inputs)
        sun_radiance = calibrate_sun(pairs, allow_missing=config.allow_missing_sun).sun_radiance
    else:
        pairs = _sun_pairs(scene, quantities, config=config, progress=progress, tasks=tasks, inputs=inputs)
        model["sun"] = choose_direct_sun(scene, quantities, pairs, config=config.sun)
        sun_radiance = np.zeros(3)
        if model["sun"].choice == "direct sun":
            sun_radiance = calibrate_sun(pairs).sun_radiance
        elif model["sun"].choice == "unknown":  # sunny, but Sec. 5 found no pair: fail as the paper does
            sun_radiance = calibrate_sun(pairs, allow_missing=config.allow_missing_sun).sun_radiance
    timings["sun_pairs"] = time.perf_counter() - start

    if "sun" in model and model["sun"].choice == "direct sun":
        model["shadows"] = choose_cast_shadows(scene, quantities, model["sun"].measures["edge_samples"],
                                               config=config.sun)
    no_sun = "sun" in model and model["sun"].choice == "no direct sun"
    no_cast = "shadows" in model and model["shadows"].choice == "no cast shadow"
    shared = step3_futures = None
    solves: dict[str, list[dict]] = {}
    if no_sun or (no_cast and config.steps > 2):  # Step 2 keeps the proxy's shadows
        # Every pixel lit: R = I / S_env without direct sun (Eq. 2 with L_sun = 0), or
        # R = I / (S_env + L_sun cos) without a cast shadow; nothing to label, no S_env to refine.
        start = time.perf_counter()
        layers = {view.stem: environment_layers(view, quantities[view.stem], sun_radiance) for view in scene.views}
        timings["layers"] = time.perf_counter() - start
    elif config.steps == 2:
        start = time.perf_counter()
        layers = {view.stem: step2_layers(view, quantities[view.stem], sun_radiance) for view in scene.views}
        timings["layers"] = time.perf_counter() - start
    else:
        logger.info("step 3 (%s labelling) over %d views", config.shadow.method, len(scene.views))
        layers, step3_timings, shared, step3_futures, solves = _step3_layers(
            scene, quantities, sun_radiance, config=config, progress=progress, tasks=tasks, inputs=inputs)
        if "scatter" in step3_timings:  # the labels' shipping adds to the inputs'
            timings["scatter"] = timings.get("scatter", 0.0) + step3_timings.pop("scatter")
        timings.update(step3_timings)
    return sun_radiance, model, no_sun, no_cast, layers, shared, step3_futures, solves


def decompose(scene: Scene, *, config: Config | None = None, tracer: Tracer | None = None,
              progress: bool = False, client: Any = None) -> Decomposition:
    """Decompose every view of a scene into reflectance and shading layers (Steps 1-4).

    Parameters
    ----------
    scene : Scene
        Views, proxy, sun and up (:func:`mvintrinsic.io.load_scene`).
    config : Config, optional
        Defaults to ``Config()``, the paper's parameters.
    tracer : Tracer, optional
        A tracer already built over ``scene.proxy``.
    progress : bool, optional
        tqdm progress bars over the long stages and the views.
    client : distributed.Client, optional
        A dask.distributed client (``docs/distributed.md``): the per-view work runs as one task
        per view on its cluster: Step 2's light/shadow pair search
        (:func:`~mvintrinsic.sun_calibration.find_sun_pairs`), Step 3's segmentation, shadow MRF
        and matting (:func:`step3_view`) and, with ``env_refine.method="paper"``, Step 4's
        offsets. Each view (its image and Step-1 pixel quantities, and later its labels) is
        shipped once to one worker, where its tasks run. Everything that needs all views at once
        stays here: Step 1 and the pixel quantities (ray casting over the proxy's Embree
        structure, which cannot be pickled), the choice of a direct sun and ``L_sun``, the
        multi-view shadow labelling, Step 4's multi-view fusion, and the upsampling of
        ``config.scale``. The layers and lighting are identical to those without a client (no
        per-view step draws random numbers). None (default): everything runs in this process
        and dask is not imported.

    Returns
    -------
    Decomposition
        Per-view :class:`~mvintrinsic.results.IntrinsicLayers`, the :class:`Lighting` (sun
        radiance, fitted sky, horizon plane, environment map), seconds per stage summed over the
        views (``downscale`` and ``upsample`` with ``config.scale < 1``, ``depth_maps`` (cast once
        for the gains and Step 1), ``exposure``,
        ``step1.<sub-stage>``, ``pixels``, ``sun_pairs``, then the Step-3 stages of
        :func:`step3`, or ``layers`` with ``steps=2``; ``occluders.carve``, ``occluders.shading`` and ``occluders.<stage>`` of the second
        pass of Steps 2-3 where the occluders are carved; ``step4`` and its parts ``step4.<part>``;
        ``occluders.reflectance`` (after Step 4: the reflectance of the shadowed pixels that see an occluder);
        with a ``client``, ``scatter``: shipping the views' inputs to the workers, and
        ``cluster.step3``: the wall seconds of Step 3's tasks, whose stages (``segmentation``,
        ``matting``, ...) are the workers' seconds summed over the views) and ``config.to_dict()``.

    Raises
    ------
    TypeError
        If ``scene``, ``config`` or ``client`` has the wrong type.
    ValueError
        If the ``client``'s cluster has no worker.
    SunCalibrationError
        With ``config.sun.direct_sun == "always"``: no light/shadow pair survived and
        ``config.allow_missing_sun`` is False.
    """
    if not isinstance(scene, Scene):
        raise TypeError(f"scene must be a Scene, got {type(scene).__name__}")
    config = config_or_default(config, Config)
    client = _as_client(client)
    tasks = None if client is None else _ViewTasks(client, scene.stems)  # fails now on a cluster without workers
    timings: dict[str, float] = {}

    tracer = tracer if tracer is not None else Tracer(scene.proxy)
    full = scene  # the photos' size; the working scene below when the working scale is below 1
    scale = working_scale(scene, config.scale, config.max_side)
    if scale < 1.0:
        start = time.perf_counter()
        scene = downscale_scene(scene, scale)
        timings["downscale"] = time.perf_counter() - start
    start = time.perf_counter()
    depths = [depth_map(v.camera, tracer) for v in scene.views]  # cast once: the gains and Step 1
    timings["depth_maps"] = time.perf_counter() - start
    start = time.perf_counter()
    gains = estimate_view_gains(scene.views, tracer, config=config.exposure, depths=depths, rng=config.seed)
    if gains.applied:
        logger.info("exposure: compensating per-view gains (%s)", gains.reason)
        if scale < 1.0:
            full = compensate(full, gains)
        scene = compensate(scene, gains)
    timings["exposure"] = time.perf_counter() - start

    logger.info("step 1: environment map, sky model, S_sky, S_ind, ~v on %d proxy vertices", len(scene.proxy.vertices))
    s1 = step1(scene, config=config.step1, tracer=tracer, depths=depths, rng=config.seed, progress=progress)
    timings.update({f"step1.{k}": v for k, v in s1.timings.items()})

    start = time.perf_counter()
    quantities = carry_to_pixels(scene, s1, tracer, progress=progress)
    timings["pixels"] = time.perf_counter() - start
    inputs = None
    if tasks is not None:  # each view's image and quantities to its worker, once
        start = time.perf_counter()
        inputs = tasks.scatter({v.stem: (v, quantities[v.stem]) for v in scene.views})
        timings["scatter"] = time.perf_counter() - start

    sun_radiance, model, no_sun, no_cast, layers, shared, step3_futures, solves = _steps_2_3(
        scene, quantities, config=config, progress=progress, tasks=tasks, inputs=inputs, timings=timings)

    occluders = None
    if config.occluders is not None and config.steps > 2 and not (no_sun or no_cast):
        # Beyond the paper (mvintrinsic.occluders): the occluders the proxy lost, carved from Step 3's
        # shadows and the photos, added to Step 1's hemisphere rays; then Steps 2 and 3 again.
        choice = choose_occluders(quantities, layers, config.occluders)
        if choice.choice == "carve":
            logger.info("occluders: carving what the proxy lost (%s), then Steps 2 and 3 again", choice.evidence)
            start = time.perf_counter()
            occluders = carve_occluders(scene.views, quantities, layers, s1.radiance, tracer, scene.sun.direction,
                                        config=config.occluders)
            timings["occluders.carve"] = time.perf_counter() - start
        if occluders is not None and len(occluders):
            start = time.perf_counter()
            s1 = occluded_step1(s1, tracer, occluders, rng=config.seed, progress=progress)
            quantities = carry_to_pixels(scene, s1, tracer, progress=progress)
            timings["occluders.shading"] = time.perf_counter() - start
            if tasks is not None:  # the new quantities to the workers
                start = time.perf_counter()
                inputs = tasks.scatter({v.stem: (v, quantities[v.stem]) for v in scene.views})
                timings["scatter"] += time.perf_counter() - start
            again: dict[str, float] = {}
            sun_radiance, model, no_sun, no_cast, layers, shared, step3_futures, solves = _steps_2_3(
                scene, quantities, config=config, progress=progress, tasks=tasks, inputs=inputs, timings=again)
            for key in ("scatter", "cluster.step3"):  # shipping and cluster wall time: both passes summed
                if key in again:
                    timings[key] = timings.get(key, 0.0) + again.pop(key)
            timings.update({f"occluders.{k}": v for k, v in again.items()})
        model["occluders"] = choice

    if config.steps == 4:
        # Without cast-shadow boundaries the S_env offsets are skipped and the multi-view fusion,
        # which needs none, runs alone (overcast render: reflectance LMSE 0.0403 -> 0.0339,
        # docs/stability.md).
        choice = choose_step4(layers, config.env_refine, quantities, views=len(scene.views))
        if no_sun or no_cast:
            choice = ModelChoice(choice.choice, ("no direct sun" if no_sun else "no cast shadow in view")
                                 + ", so no shadow boundary: " + choice.evidence, choice.measures)
        model["step4"] = choice
        if choice.choice in ("run", "fusion only"):
            logger.info("step 4 (%s) over %d views", config.env_refine.method, len(scene.views))
            start = time.perf_counter()
            if tasks is not None and step3_futures is not None and config.env_refine.method == "paper":
                # per view, from Step 3 in place
                futures = tasks.submit("step4", _offsets_task, {s: (inputs[s], step3_futures[s]) for s in scene.stems},
                                       config=config.env_refine)
                layers = tasks.gather(futures, desc="step 4", progress=progress)
                step4_timings = {"offsets": time.perf_counter() - start}
            else:
                refined = step4(scene, quantities, layers, config=config,
                                correspondences=None if shared is None else shared.correspondences)
                layers, step4_timings = dict(refined.layers), refined.timings
            timings["step4"] = time.perf_counter() - start
            timings.update({f"step4.{k}": v for k, v in step4_timings.items()})

    smoothed = None
    if occluders is not None and len(occluders) and config.occluders.reflectance_smoothing is not None:
        # Beyond the paper: the shadowed pixels that see a carved occluder take a smooth reflectance
        # (mvintrinsic.occluders.smooth_occluder_reflectance; docs/step4.md).
        start = time.perf_counter()
        seen = seen_occluders(scene.views, quantities, occluders)
        before = layers
        layers = {stem: smooth_occluder_reflectance(layer, seen[stem],
                                                    sigma=config.occluders.reflectance_smoothing * max(layer.shape))
                  for stem, layer in layers.items()}
        smoothed = float(np.mean([(layers[s].reflectance != before[s].reflectance).any(axis=-1).mean()
                                  for s in layers]))
        timings["occluders.reflectance"] = time.perf_counter() - start

    if scale < 1.0:  # the layers at the photos' size
        start = time.perf_counter()
        layers = {view.stem: upsample_layers(view, layers[view.stem]) for view in full.views}
        timings["upsample"] = time.perf_counter() - start
    if gains.applied:  # the shading back in each photo's units, so that R * S reproduces it
        layers = {stem: restore_units(layer, gains.of(stem)) for stem, layer in layers.items()}
    sky = s1.sky_model
    if sky.evidence.get("chosen_by") is not None:  # SkyConfig(model="auto"): the family and why
        model["sky"] = sky_choice(sky)
    lighting = Lighting(
        sun=scene.sun, sun_radiance=sun_radiance, up=scene.up,
        sky=sky.to_parameters(),
        horizon_plane=s1.horizon.plane, envmap=s1.environment.radiance, exposure=gains,
        horizon_evidence=s1.horizon.evidence, model=model,
    )
    diagnostics: dict[str, Any] = {"matting": solves} if any(solves.values()) else {}  # a missed rtol was logged
    if occluders is not None:
        diagnostics["occluders"] = {"voxels": len(occluders), "voxel": occluders.size, "rays": dict(occluders.counts)}
        if smoothed is not None:
            diagnostics["occluders"]["smoothed_share"] = smoothed  # of the pixels, mean over views
    return Decomposition(layers=layers, lighting=lighting, timings=timings, config=config, diagnostics=diagnostics)
