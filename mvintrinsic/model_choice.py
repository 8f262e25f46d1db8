"""Model selection from the data (beyond the paper): what each scene needs of the image model.

The paper assumes a clear sky with direct sun and cast shadows in every scene, and runs every step.
Here the pipeline (:func:`mvintrinsic.decompose`) asks the data first, and records each answer with
its evidence in ``lighting.json`` (:class:`~mvintrinsic.results.ModelChoice`, ``docs/presets.md``):

* :func:`choose_direct_sun`: direct sun, or an overcast sky (``L_sun = 0``, no shadow labels);
* :func:`choose_cast_shadows`: cast shadows in view, or none (every pixel lit, Step 3 skipped);
* :func:`sky_choice`: the sky family Step 1 kept (constant, Preetham or Perez) by held-out error;
* :func:`choose_step4`: Step 4 run, reduced to the multi-view fusion, or skipped, from the labels'
  cast-shadow boundaries.

The thresholds are :class:`~mvintrinsic.sun_calibration.SunConfig` and
:class:`~mvintrinsic.env_refine.EnvRefineConfig` fields; their measurements are in
``docs/stability.md`` and ``docs/presets.md``.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping

import numpy as np

from ._validation import config_or_default
from .env_refine import EnvRefineConfig
from .occluders import OccluderConfig, unexplained_shadow_share
from .pixels import PixelQuantities
from .results import SHADOW_LABELS, IntrinsicLayers, ModelChoice
from .scene import Scene
from .skymodel import SkyModel
from .sun_calibration import SunConfig, SunPairs, direct_sun_evidence

__all__ = ["ATTACHED_COSINE", "EDGE_BAND", "MIN_CONTRAST_SAMPLES", "choose_cast_shadows", "choose_direct_sun", "choose_occluders",
           "choose_step4", "sky_choice"]

logger = logging.getLogger(__name__)


#: Fewest shadow-edge samples whose contrast can overrule "no pair means no direct sun"
#: (:func:`choose_direct_sun`): the demo's views at 160x120 give 65 samples at contrast 3.7.
MIN_CONTRAST_SAMPLES = 30


def choose_direct_sun(scene: Scene, quantities: Mapping[str, PixelQuantities], pairs: list[SunPairs], *,
                      config: SunConfig | None = None) -> ModelChoice:
    """Whether the scene has direct sun (beyond the paper; ``SunConfig(direct_sun="auto")``).

    No direct sun when no light/shadow pair survived (Sec. 5), or when, over at least
    ``config.contrast_samples`` samples across the proxy's shadow edges
    (:func:`~mvintrinsic.sun_calibration.direct_sun_evidence`), both the contrast (upper quartile)
    is below ``config.sun_contrast`` and the warmth (median ``log(rho_R / rho_B)``) is below
    ``config.sun_warmth`` (an overcast sky).

    Parameters
    ----------
    scene : Scene
    quantities : mapping of str to PixelQuantities
        Per view (:func:`carry_to_pixels`).
    pairs : list of SunPairs
        Every view's light/shadow pairs (:func:`~mvintrinsic.sun_calibration.find_sun_pairs`).
    config : SunConfig, optional

    When no pair survived but the contrast is at least ``config.sun_contrast`` over at least
    :data:`MIN_CONTRAST_SAMPLES` samples, the images show sun that Sec. 5 could not calibrate (e.g.
    views too small for its 30 px walk): the choice is ``"unknown"`` and :func:`decompose` fails
    as the paper's assumption does (:class:`~mvintrinsic.sun_calibration.SunCalibrationError`, or
    ``L_sun = 0`` with a warning when ``Config.allow_missing_sun``), rather than calling a sunny
    scene overcast.

    Returns
    -------
    ModelChoice
        ``choice`` ``"direct sun"``, ``"no direct sun"`` or ``"unknown"``; ``measures``: ``pairs``,
        ``boundary_samples`` (of Sec. 5), ``contrast``, ``contrast_quartiles``, ``warmth``, ``edge_samples``.
    """
    config = config_or_default(config, SunConfig)
    contrast = direct_sun_evidence(scene.views, quantities)
    n_pairs = int(sum(len(p.estimates) for p in pairs))
    samples = int(sum(p.n_samples for p in pairs))
    measures = {"pairs": n_pairs, "boundary_samples": samples,
                "contrast": None if not np.isfinite(contrast.contrast) else contrast.contrast,
                "contrast_quartiles": [float(x) if np.isfinite(x) else None for x in contrast.quartiles],
                "warmth": None if not np.isfinite(contrast.warmth) else contrast.warmth,
                "edge_samples": contrast.samples}
    figures = (f"contrast across the proxy's shadow edges {contrast.contrast:.2f} (upper quartile of "
               f"{contrast.samples} samples; threshold {config.sun_contrast:g}), warmth {contrast.warmth:+.3f} "
               f"(median log(rho_R / rho_B); threshold {config.sun_warmth:g}); {n_pairs} light/shadow pairs")
    warm = np.isfinite(contrast.warmth) and contrast.warmth >= config.sun_warmth
    if n_pairs == 0 and contrast.samples >= MIN_CONTRAST_SAMPLES and contrast.contrast >= config.sun_contrast:
        choice, evidence = "unknown", (f"no light/shadow pair survived ({samples} boundary samples) although the "
                                       f"images show direct sun: {figures}")
    elif n_pairs == 0:
        choice, evidence = "no direct sun", f"no light/shadow pair survived ({samples} boundary samples); {figures}"
    elif contrast.samples >= config.contrast_samples and contrast.contrast < config.sun_contrast and not warm:
        choice, evidence = "no direct sun", f"overcast: {figures}"
    else:
        choice, evidence = "direct sun", figures
    if choice == "no direct sun":
        logger.info("no direct sun: %s", evidence)
    return ModelChoice(choice, evidence, measures)


#: Width of the band of :func:`~mvintrinsic.sun_calibration.direct_sun_evidence`'s samples, pixels
#: (shadow pixels 2 to 8 px from the lit region): samples / width is the length of the proxy's
#: cast-shadow edges in pixels.
EDGE_BAND = 6


def choose_cast_shadows(scene: Scene, quantities: Mapping[str, PixelQuantities], edge_samples: int, *,
                        config: SunConfig | None = None) -> ModelChoice:
    """Whether the views hold cast shadows at all (beyond the paper).

    Two figures of the proxy's cast shadows in view, both needed to call a scene shadowless:
    the share of the sunward pixels (proxy sun cosine at least 0.2) in the proxy's cast shadow
    (``~v <= 0.1``), below ``config.min_shadow_share``, and the length of its cast-shadow edges
    (``edge_samples``, the samples of :func:`~mvintrinsic.sun_calibration.direct_sun_evidence`,
    divided by their band's width :data:`EDGE_BAND`) per view, in units of the
    view's size ``sqrt(H W)``, below ``config.min_shadow_edge``. Then the photos hold no cast
    shadow worth labelling: every pixel is lit (``v_sun = 1``), Step 3's labels and matting are
    skipped, and so are Step 4's ``S_env`` offsets.

    Returns
    -------
    ModelChoice
        ``"cast shadows"`` or ``"no cast shadow"``; ``measures``: ``shadow_share``,
        ``shadow_edge`` (view sizes of edge per view), ``edge_samples``.
    """
    config = config_or_default(config, SunConfig)
    samples = int(edge_samples)
    size = float(sum(np.sqrt(v.shape[0] * v.shape[1]) for v in scene.views))
    length = samples / EDGE_BAND / max(size, 1.0)
    sunward = cast = 0
    for view in scene.views:
        q = quantities[view.stem]
        facing = np.asarray(q.valid) & ~np.asarray(q.sky_mask) & (np.asarray(q.cosine) >= ATTACHED_COSINE)
        sunward += int(facing.sum())
        cast += int((facing & (np.asarray(q.visibility) <= 0.1)).sum())
    share = cast / max(sunward, 1)
    measures = {"shadow_share": share, "shadow_edge": length, "edge_samples": samples}
    evidence = (f"the proxy's cast shadow covers {share:.2%} of the sunward pixels (threshold "
                f"{config.min_shadow_share:.1%}), its edges {length:.2f} view sizes per view ({samples} edge samples; "
                f"threshold {config.min_shadow_edge:g})")
    none = share < config.min_shadow_share and length < config.min_shadow_edge
    return ModelChoice("no cast shadow" if none else "cast shadows", evidence, measures)


def sky_choice(sky: SkyModel) -> ModelChoice:
    """The sky family chosen by :func:`~mvintrinsic.skymodel.select_sky_model` as a :class:`ModelChoice`."""
    evidence = dict(sky.evidence)
    errors = evidence.get("held_out_error")
    if errors:
        text = (f"error on sky texels held out from the fit ({evidence['folds']} azimuth sectors of "
                f"{evidence['texels']} texels): " + ", ".join(f"{k} {v:.4f}" for k, v in errors.items())
                + f"; the simplest within {evidence['margin']:.0%} of the best")
    else:
        text = f"{evidence.get('texels')} sky texels: too few for held-out sectors, the paper's Preetham sky"
    return ModelChoice(sky.model, text, evidence)


#: Sun cosine (the proxy's, per pixel) below which a shadow pixel at a label boundary is taken for
#: an attached shadow (the surface turned away from the sun; a crease, not a cast-shadow edge), as
#: the lit side of :func:`~mvintrinsic.sun_calibration.direct_sun_evidence`'s samples.
ATTACHED_COSINE = 0.2


def choose_step4(layers: Mapping[str, IntrinsicLayers], config: EnvRefineConfig,
                  quantities: Mapping[str, PixelQuantities], *, views: int) -> ModelChoice:
    """Step 4 runs where the labels hold cast-shadow boundaries (``config.min_boundary_share``).

    A boundary pixel is a shadow pixel with a lit 4-neighbour; those whose proxy sun cosine is below :data:`ATTACHED_COSINE` (attached shadows: creases between faces
    turned to and away from the sun) do not count. Without cast-shadow boundaries the paper's
    ``S_env`` offsets have nothing to work on: ``"skipped"``; the ``"multiview"`` method's
    reflectance fusion needs no boundary and still runs with two views or more:
    ``"fusion only"``.
    """
    boundary = attached = valid = 0
    for stem, layer in layers.items():
        labels = layer.shadow_labels
        shadow, lit = labels == SHADOW_LABELS["shadow"], labels == SHADOW_LABELS["lit"]
        edge = np.zeros_like(shadow)
        edge[1:] |= shadow[1:] & lit[:-1]
        edge[:-1] |= shadow[:-1] & lit[1:]
        edge[:, 1:] |= shadow[:, 1:] & lit[:, :-1]
        edge[:, :-1] |= shadow[:, :-1] & lit[:, 1:]
        turned = edge & (np.asarray(quantities[stem].cosine) < ATTACHED_COSINE)
        attached += int(turned.sum())
        edge &= ~turned
        boundary += int(edge.sum())
        valid += int((shadow | lit).sum())
    share = boundary / max(valid, 1)
    measures = {"boundary_pixels": boundary, "attached_pixels": attached, "labelled_pixels": valid,
                "boundary_share": share}
    evidence = (f"{boundary} cast-shadow boundary pixels, {share:.2e} of the labelled pixels "
                f"(threshold {config.min_boundary_share:g}; {attached} more at attached shadows, not counted)")
    if share >= config.min_boundary_share and boundary > 0:
        return ModelChoice("run", evidence, measures)
    if config.method == "multiview" and views > 1:
        return ModelChoice("fusion only", evidence + ": no S_env to refine at a boundary; the reflectance "
                           "fused across the views", measures)
    return ModelChoice("skipped", evidence, measures)


def choose_occluders(quantities: Mapping[str, PixelQuantities], layers: Mapping[str, IntrinsicLayers],
                     config: OccluderConfig) -> ModelChoice:
    """Carve the occluders the proxy lost when it cannot cast most of the labelled shadow.

    ``"carve"`` when ``config.when == "always"``, or when the share of Step 3's shadow pixels the
    proxy leaves in the sun (:func:`~mvintrinsic.occluders.unexplained_shadow_share`) is at least
    ``config.min_unexplained``; ``"skip"`` otherwise (and without shadow pixels).
    """
    share = unexplained_shadow_share(quantities, layers, config=config)
    measures = {"unexplained_share": share, "min_unexplained": config.min_unexplained, "when": config.when}
    if share is None:
        return ModelChoice("skip", "no pixel is labelled shadow", measures)
    evidence = (f"the proxy leaves {share:.0%} of the labelled shadow pixels in the sun "
                f"(threshold {config.min_unexplained:.0%})")
    if config.when == "always":
        return ModelChoice("carve", evidence + "; carving always (when='always')", measures)
    if share >= config.min_unexplained:
        return ModelChoice("carve", evidence + ": it lost most occluders", measures)
    return ModelChoice("skip", evidence + ": it holds most occluders", measures)
