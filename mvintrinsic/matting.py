"""Step 3, per pixel: soft sun visibility by matting and image-guided shading layers (paper Sec. 6.2).

The shadow labelling of Sec. 6.1 is binary and per cluster. Sec. 6.2 turns it into the per-pixel
layers of the image model (Eqs. 1, 17):

1. **Soft visibility** (:func:`sun_visibility_matting`). "We apply Laplacian matting [Levin et al.
   2008] to recover continuous variations of visibility in the boundaries between clusters. These
   correspond to penumbra regions at the frontier of shadow and light clusters, effectively
   providing a tri-map from the binary shadow mask." The trimap: a shadow (lit) pixel at most
   ``trimap_radius`` from a lit (shadow) pixel is unknown, the other shadow pixels are
   ``v_sun = 0`` and the other lit pixels ``v_sun = 1``; but a region thinner than the band keeps
   its centre line (the ridge of the distance to the other label) as known, since a thin shadow
   whose pixels were all unknown would only touch known lit pixels and be matted away (a matte
   whose known values are all 1 is 1). "We also propagate visibility in the boundary regions
   between clusters": when the clusters are given, pixels within ``visibility_cluster_width`` of
   any cluster boundary are unknown as well, so that the matte can follow fine shadow structures
   that the cluster labels missed but that stay connected to a labelled shadow (paper Sec. 9.9,
   Fig. 21). Undecided valid pixels (label 128) are unknown too. The unknowns solve Levin's
   closed-form system with the known pixels as Dirichlet values, clipped to [0, 1].
2. **Shading propagation** (:func:`propagate`). "We also apply Laplacian matting guided by the
   input image to propagate the shading values S_sky, S_ind and S_sun [...]. We use all 3D points
   except those in the boundaries between clusters as constraints." Our 3D points are the pixels
   the proxy covers (``PixelQuantities.valid & ~filled``: the per-pixel Step-1 values there come
   from the proxy, elsewhere they are nearest-neighbour copies); those within
   ``cluster_boundary_width`` of a cluster boundary are dropped (3 px, the boundary of Sec. 6.1).
   The propagation solves, per channel,

   .. math::

      \\min_x \\; x^T L x + \\delta \\sum_{i \\notin K} (x_i - p_i)^2
      \\quad \\text{subject to } x_k = s_k, \\; k \\in K

   ``L`` the matting Laplacian of the image, ``K`` the constraint pixels with values ``s``, and a
   weak pull (``delta = prior_weight``) toward the value ``p`` of the nearest constraint, which
   only matters where no constraint is reachable (it makes every system positive definite). The
   constraints are hard by default, the ``lambda -> infinity`` limit of Levin et al.'s soft term
   ``lambda sum_K (x_k - s_k)^2`` (their ``lambda = 100`` already reproduces the constraints to
   about 1%); a finite ``constraint_weight`` gives the soft form, at the cost of solving for every
   pixel instead of the unconstrained ones. ``S_sun = L_sun max(0, cos)`` (Eq. 3) is propagated as
   its cosine: ``L_sun`` is one constant per channel and the propagation is linear, so this is the
   same as propagating ``S_sun`` itself, at a third of the cost.
3. **Shadow-boundary band**. "Propagating them using the input image as guidance sometimes
   produces artifacts along shadow boundaries. We reduce these artifacts by excluding a small band
   along shadow boundaries from the propagation, which we subsequently fill with a color
   diffusion." Our reading: the pixels closer than ``shadow_band_radius`` to a shadow/lit label
   transition are neither constraints nor unknowns of the matting system (every matting window
   that touches the band is dropped, so the image's shadow edge cannot imprint on the smooth
   layers), and are then filled by diffusing the propagated shading values ("colors" of the RGB
   shading layers) inward from the band's border: the harmonic interpolation of the 4-neighbour
   graph Laplacian, ``Delta x = 0`` in the band with the propagated values around it as Dirichlet
   conditions. The diffusion is not image-guided, since image guidance is what caused the
   artifacts. (The paper does not give the band's width, nor whether "color diffusion" is guided;
   both are our choices.)
4. **Step 1's level in the shadows** (beyond the paper, ``MattingConfig.shadow_level``, off by
   default; :func:`restore_shadow_level`). The band diffusion and the cluster-boundary
   propagation raise ``S_sky + S_ind`` in the shadows; with the option the shadow-labelled pixels'
   propagated values are rescaled to Step 1's local level, keeping their pixel-to-pixel variation
   (``docs/step4.md``, "The umbra's ``S_env`` and Step 3's propagation").
5. **Reflectance** (:func:`intrinsic_layers`): ``R = I / S_tot`` with
   ``S_tot = S_sky + S_ind + v_sun S_sun`` (Eq. 17).

The Laplacian, its systems and solvers, the guide image and the options are in :mod:`.laplacian`.

The method is the paper's [1]_ (Sec. 6.2); the Laplacian is Levin et al.'s [2]_.

References
----------
.. [1] S. Duchêne et al., "Multi-View Intrinsic Images of Outdoors Scenes with an Application to
   Relighting", ACM Transactions on Graphics 34(5), 2015, Sec. 6.2.
.. [2] A. Levin, D. Lischinski and Y. Weiss, "A Closed-Form Solution to Natural Image Matting",
   IEEE TPAMI 30(2), 2008.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from ._validation import as_array, config_or_default, describe
from .laplacian import (
    SOLVERS,
    MattingConfig,
    SolveReport,
    _check_flags,
    _check_image,
    _check_mask,
    _GuidedLaplacian,
    _ordered,
    _propagate,
    _solve,
    _system,
    guide_image,
)
from .pixels import PixelQuantities, layers_from_shading, masked_gaussian_mean, nearest_fill
from .results import SHADOW_LABELS, IntrinsicLayers
from .scene import View
from .segmentation import boundary_band

__all__ = [
    "SOLVERS",
    "MattingConfig",
    "MattingResult",
    "SolveReport",
    "guide_image",
    "intrinsic_layers",
    "intrinsic_layers_result",
    "propagate",
    "restore_shadow_level",
    "shadow_transitions",
    "sun_visibility_matting",
]

logger = logging.getLogger(__name__)

_SHADOW, _UNDECIDED, _LIT = SHADOW_LABELS["shadow"], SHADOW_LABELS["undecided"], SHADOW_LABELS["lit"]


# --------------------------------------------------------------------------------------------
# Input checks
# --------------------------------------------------------------------------------------------


def _check_labels(labels: object, shape: tuple[int, int]) -> np.ndarray:
    array = np.asarray(labels)
    if array.dtype != np.uint8:
        raise TypeError(f"labels must be a uint8 array (0 shadow, 128 undecided, 255 lit), got {describe(labels)}")
    if array.shape != shape:
        raise ValueError(f"labels must have shape {shape}, got shape {array.shape}")
    bad = (array != _SHADOW) & (array != _UNDECIDED) & (array != _LIT)
    if bad.any():
        raise ValueError(f"labels may only hold 0, 128 or 255, got {np.unique(array[bad])[:5].tolist()}")
    return array


def _check_clusters(clusters: object, shape: tuple[int, int]) -> np.ndarray | None:
    if clusters is None:
        return None
    array = np.asarray(clusters)
    if array.ndim != 2 or array.dtype.kind not in "iu":
        raise TypeError(f"clusters must be an (H, W) integer array, got {describe(clusters)}")
    if array.shape != shape:
        raise ValueError(f"clusters must have shape {shape}, got shape {array.shape}")
    return array.astype(np.int64)


# --------------------------------------------------------------------------------------------
# Masks
# --------------------------------------------------------------------------------------------

def shadow_transitions(labels: np.ndarray, *, mask: np.ndarray | None = None) -> np.ndarray:
    """Pixels on a shadow/lit label transition.

    Parameters
    ----------
    labels : (H, W) uint8
        0 shadow, 255 lit, 128 undecided (:data:`mvintrinsic.results.SHADOW_LABELS`).
    mask : (H, W) bool, optional
        Pixels that count (default: all).

    Returns
    -------
    (H, W) bool
        Pixels in ``mask`` labelled 0 (255) with a 4-neighbour in ``mask`` labelled 255 (0); both
        sides of a transition are marked.
    """
    if np.ndim(labels) != 2:
        raise ValueError(f"labels must have shape (H, W), got shape {np.shape(labels)}")
    labels = _check_labels(labels, np.shape(labels))
    valid = np.ones(labels.shape, dtype=bool) if mask is None else _check_flags(mask, "mask", labels.shape)
    shadow = valid & (labels == _SHADOW)
    lit = valid & (labels == _LIT)
    out = np.zeros(labels.shape, dtype=bool)
    for first, second in (((slice(None), slice(1, None)), (slice(None), slice(None, -1))),
                          ((slice(1, None), slice(None)), (slice(None, -1), slice(None)))):
        cross = (shadow[first] & lit[second]) | (lit[first] & shadow[second])
        out[first] |= cross
        out[second] |= cross
    return out


def _near(seed: np.ndarray, radius: int) -> np.ndarray:
    """Pixels whose Euclidean distance to a ``seed`` pixel is below ``radius`` (``seed`` for 1)."""
    if radius == 0 or not seed.any():
        return np.zeros(seed.shape, dtype=bool)
    if radius == 1:
        return seed.copy()
    return ndimage.distance_transform_edt(~seed) < radius


def _trimap_unknown(labels: np.ndarray, mask: np.ndarray, radius: int) -> np.ndarray:
    """Valid pixels within ``radius`` of the other label, or undecided, minus the thin regions' cores.

    A shadow (lit) pixel is unknown when the nearest lit (shadow) pixel is at most ``radius`` away,
    unless it is a ridge of that distance within its region (no neighbour of the same label lies
    farther from the other label): a region thinner than the band keeps its centre line as a known
    value, so that thin shadows (a fence's, a window lintel's) are not erased by a trimap that only
    knows the other label around them.
    """
    unknown = mask & (labels == _UNDECIDED)
    for label, other in ((_SHADOW, _LIT), (_LIT, _SHADOW)):
        region = mask & (labels == label)
        opposite = mask & (labels == other)
        if not region.any() or not opposite.any():
            continue
        distance = ndimage.distance_transform_edt(~opposite)
        inner = np.where(region, distance, 0.0)
        ridge = region & (distance >= ndimage.maximum_filter(inner, size=3))
        unknown |= region & (distance <= radius) & ~ridge
    return unknown


def _matte(laplacian: _GuidedLaplacian, stencil: np.ndarray, labels: np.ndarray, mask: np.ndarray,
           clusters: np.ndarray | None, config: MattingConfig, what: str) -> tuple[np.ndarray, SolveReport | None]:
    """Closed-form matte of ``v_sun`` (float64, 0 outside ``mask``) from the label trimap.

    ``stencil`` is the Laplacian over the windows inside ``mask``.
    """
    unknown = _trimap_unknown(labels, mask, config.trimap_radius)
    if clusters is not None and config.visibility_cluster_width > 0:
        unknown |= boundary_band(np.where(mask, clusters, -1), config.visibility_cluster_width)
    known = mask & ~unknown
    visibility = np.where(mask & (labels == _LIT), 1.0, 0.0)
    if not unknown.any():
        return visibility, None
    if not known.any():
        logger.warning("%s: no labelled pixel outside the trimap band; keeping the labels", what)
        return np.where(mask & (labels == _UNDECIDED), 0.5, visibility), None
    fallback = nearest_fill(visibility, known).ravel()
    pixels = _ordered(np.flatnonzero(unknown), laplacian)
    # Levin et al. with the known pixels as Dirichlet values (as pymatting's estimate_alpha_cf):
    # (L_UU + delta I) v_U = -L_UK v_K + delta p_U; the weak pull toward p keeps L_UU definite.
    matrix, rhs = _system(laplacian, stencil, pixels, np.full(len(pixels), config.prior_weight),
                          known=known.ravel(), values=visibility.reshape(-1, 1))
    rhs += config.prior_weight * fallback[pixels, None]
    solution, report = _solve(matrix, rhs, fallback[pixels, None], config, what, ordered=True)
    visibility.ravel()[pixels] = np.clip(solution[:, 0], 0.0, 1.0)
    return visibility, report


# --------------------------------------------------------------------------------------------
# Public functions
# --------------------------------------------------------------------------------------------

def sun_visibility_matting(
    image: np.ndarray,
    labels: np.ndarray,
    *,
    mask: np.ndarray | None = None,
    clusters: np.ndarray | None = None,
    config: MattingConfig | None = None,
) -> np.ndarray:
    """Soft sun visibility from binary shadow labels by closed-form matting (Sec. 6.2; Levin et al. 2008).

    The trimap (module docstring): valid pixels at most ``config.trimap_radius`` from the other
    label (except the centre line of thinner regions), within ``config.visibility_cluster_width``
    of a cluster boundary (if ``clusters`` is given) or labelled undecided are unknown; the other
    shadow pixels are 0 and lit pixels 1. The unknowns minimise Levin et al.'s quadratic form of
    the guide image (:func:`guide_image`) over the windows inside ``mask``:

    .. math::

       \\min_{v_U} \\; v^T L v + \\delta \\sum_{i \\in U} (v_i - p_i)^2
       \\quad \\text{with } v_K \\text{ fixed by the labels}

    (``delta = config.prior_weight``, ``p`` the nearest known value.)

    Parameters
    ----------
    image : (H, W, 3) float
        Linear, scene-referred RGB; finite on ``mask``.
    labels : (H, W) uint8
        0 shadow, 255 lit, 128 undecided (:data:`mvintrinsic.results.SHADOW_LABELS`).
    mask : (H, W) bool, optional
        Pixels with an estimate (default: all); the others (sky, invalid) take part in no matting
        window and hold 0.
    clusters : (H, W) int, optional
        Cluster labels of the segmentation (negative on invalid pixels), for the propagation of
        visibility in cluster boundaries.
    config : MattingConfig, optional

    Returns
    -------
    (H, W) float32
        ``v_sun`` in [0, 1]; 0 outside ``mask``. A connected part of the unknowns that reaches no
        labelled pixel takes the nearest labelled pixel's value.

    Raises
    ------
    ValueError, TypeError
        Naming the argument: wrong shapes or dtypes, labels other than 0/128/255, an image that is
        not finite on the mask.
    """
    config = config_or_default(config, MattingConfig)
    image = _check_image(image)
    shape = image.shape[:2]
    valid = _check_mask(mask, shape, image)
    labels = _check_labels(labels, shape)
    clusters = _check_clusters(clusters, shape)
    if not valid.any():
        return np.zeros(shape, dtype=np.float32)
    laplacian = _GuidedLaplacian(guide_image(image, mask=valid, white_percentile=config.white_percentile), config)
    stencil = laplacian.stencils(valid)[0]
    visibility, _ = _matte(laplacian, stencil, labels, valid, clusters, config, "sun visibility matting")
    return visibility.astype(np.float32)


def propagate(
    image: np.ndarray,
    values: np.ndarray,
    known: np.ndarray,
    *,
    mask: np.ndarray | None = None,
    band: np.ndarray | None = None,
    config: MattingConfig | None = None,
) -> np.ndarray:
    """Image-guided propagation of values from constraint pixels (Sec. 6.2, after Levin et al. 2008).

    Every channel solves, over the pixels of ``mask & ~band``,

    .. math::

       \\min_x \\; x^T L x + \\delta \\sum_{i \\notin K} (x_i - p_i)^2
       \\quad \\text{subject to } x_k = s_k, \\; k \\in K

    with ``L`` the matting Laplacian of the guide image (:func:`guide_image`) over the windows
    inside that set, ``K = known``, ``s = values``, ``delta = config.prior_weight`` and ``p`` the
    nearest constraint's value (with a finite ``config.constraint_weight`` the constraint becomes
    the soft term ``lambda sum_K (x_k - s_k)^2``). Then the ``band`` pixels are filled by
    diffusing those values (harmonic interpolation over 4-neighbours, not image-guided): the
    paper's "small band along shadow boundaries [excluded] from the propagation, which we
    subsequently fill with a color diffusion".

    Parameters
    ----------
    image : (H, W, 3) float
        Linear, scene-referred RGB (the guide); finite on ``mask``.
    values : (H, W, C) or (H, W) float
        Values to propagate; only those at ``known`` pixels are read (they must be finite).
    known : (H, W) bool
        Constraint pixels.
    mask : (H, W) bool, optional
        Pixels to estimate (default: all); the others take part in no matting window.
    band : (H, W) bool, optional
        Pixels left out of the image-guided propagation and filled by diffusion (default: none);
        their ``known`` flags are ignored.
    config : MattingConfig, optional

    Returns
    -------
    (H, W, C) or (H, W) float64
        Like ``values``; pixels outside ``mask`` keep their input values.

    Raises
    ------
    ValueError
        Naming the argument: wrong shapes, non-finite constraint values, or no ``known`` pixel in
        ``mask & ~band`` (while ``mask`` is not empty).
    """
    config = config_or_default(config, MattingConfig)
    image = _check_image(image)
    shape = image.shape[:2]
    valid = _check_mask(mask, shape, image)
    array = np.asarray(values, dtype=np.float64)
    squeeze = array.ndim == 2
    if squeeze:
        array = array[..., None]
    if array.ndim != 3 or array.shape[:2] != shape or array.shape[2] == 0:
        raise ValueError(f"values must have shape {shape} or {(*shape, 'C')}, got shape {np.shape(values)}")
    known = _check_flags(known, "known", shape)
    band = np.zeros(shape, dtype=bool) if band is None else _check_flags(band, "band", shape)
    constraint = known & valid & ~band
    if not np.isfinite(array[constraint]).all():
        raise ValueError("values must be finite on the known pixels")
    if not valid.any():
        return array[..., 0].copy() if squeeze else array.copy()
    if not constraint.any():
        raise ValueError("known must hold at least one pixel inside mask and outside band")
    laplacian = _GuidedLaplacian(guide_image(image, mask=valid, white_percentile=config.white_percentile), config)
    band = band & valid
    stencil = laplacian.stencils(valid & ~band)[0]
    out, _ = _propagate(laplacian, stencil, array, constraint, valid, band, config, "propagation")
    return out[..., 0] if squeeze else out


@dataclass(frozen=True)
class MattingResult:
    """The layers of a view from :func:`intrinsic_layers_result`, with how their systems were solved.

    Parameters
    ----------
    layers : IntrinsicLayers
        As :func:`intrinsic_layers` returns them.
    solves : tuple of SolveReport
        One per linear system, in order: the visibility matte, the shading propagation and the
        band diffusion (those that had unknowns).
    timings : mapping of str to float
        Seconds of ``laplacian`` (the guide and its two stencils), ``visibility`` and
        ``propagation`` (diffusion included).
    """

    layers: IntrinsicLayers
    solves: tuple[SolveReport, ...] = ()
    timings: Mapping[str, float] = dataclasses.field(default_factory=dict)

    @property
    def converged(self) -> bool:
        """Every system reached ``rtol``."""
        return all(report.converged for report in self.solves)


def intrinsic_layers(
    view: View,
    quantities: PixelQuantities,
    labels: np.ndarray,
    sun_radiance: np.ndarray,
    *,
    clusters: np.ndarray | None = None,
    config: MattingConfig | None = None,
) -> IntrinsicLayers:
    """The intrinsic layers of a view from its shadow labels (paper Sec. 6.2, Eq. 17).

    1. ``v_sun``: closed-form matte in the trimap band (and the cluster boundaries), the labels
       elsewhere (:func:`sun_visibility_matting`);
    2. ``S_sky``, ``S_ind`` and ``cos omega_sun`` propagated from the proxy pixels away from
       cluster boundaries and shadow boundaries, guided by the image; the shadow-boundary band
       filled by diffusion (:func:`propagate`); one guide image for both steps;
    3. ``S_sun = L_sun max(0, cos)`` (Eq. 3), ``S_tot = S_sky + S_ind + v_sun S_sun`` (Eq. 17) and
       ``R = I / S_tot``. Propagated shading is clipped at 0 (the matting Laplacian can overshoot)
       and the cosine to [0, 1]. As in ``pipeline.step2_layers``, where ``S_tot`` is below
       ``config.shading_floor`` times the view's median, ``S_ind`` is raised to reach it, so ``R``
       stays finite and ``R * S_tot`` reproduces the image.

    :func:`intrinsic_layers_result` returns the same layers with a report of every linear solve.

    Parameters
    ----------
    view : View
        The view (its linear RGB image).
    quantities : PixelQuantities
        The view's per-pixel Step-1 quantities; ``quantities.valid`` are the pixels with layers.
    labels : (H, W) uint8
        Binary shadow labels of the view: 0 shadow, 255 lit, 128 undecided (Sec. 6.1).
    sun_radiance : (3,) array_like
        ``L_sun``, shading units, non-negative.
    clusters : (H, W) int, optional
        Cluster labels of the segmentation the shadow labels were computed on (negative on
        invalid pixels). Without them no pixel is excluded for lying on a cluster boundary and
        visibility is matted only around shadow transitions.
    config : MattingConfig, optional

    Returns
    -------
    IntrinsicLayers
        ``shadow_labels`` are ``labels`` (128 outside ``quantities.valid``); sky and invalid pixels
        hold 0 in every layer.

    Raises
    ------
    ValueError, TypeError
        Naming the argument, for inputs of the wrong shape, dtype or range.
    """
    return intrinsic_layers_result(view, quantities, labels, sun_radiance, clusters=clusters, config=config).layers


def restore_shadow_level(quantities: PixelQuantities, labels: np.ndarray, sky: np.ndarray, indirect: np.ndarray,
                         *, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Propagated ``S_sky`` and ``S_ind`` brought back to Step 1's level in the shadows (beyond the paper).

    Over the shadow-labelled pixels the proxy covers (``valid & ~filled``), the ratio of the
    Gaussian-weighted means (:func:`~mvintrinsic.pixels.masked_gaussian_mean`, standard deviation
    ``sigma`` pixels) of Step 1's ``S_sky + S_ind`` and of the propagated one multiplies both
    terms of every shadow-labelled pixel: the level is Step 1's, the pixel-to-pixel variation the
    propagation's. Where no such pixel is near, the factor is 1.

    Why: the propagation (paper Sec. 6.2) fills the shadow band from both sides and the cluster
    boundaries from the image, and raises ``S_env`` in the shadows (on the demo's exact mesh,
    Step 1 is within 9% in the umbra, the propagated values 32-75% above in green and blue);
    Step 1's own values have the right level but scatter from pixel to pixel (``docs/step4.md``).

    Parameters
    ----------
    quantities : PixelQuantities
        The view's Step-1 quantities.
    labels : (H, W) uint8
        Shadow labels (:data:`~mvintrinsic.results.SHADOW_LABELS`).
    sky, indirect : (H, W, 3) array_like
        The propagated ``S_sky`` and ``S_ind``, shading units.
    sigma : float
        Gaussian standard deviation, pixels (> 0).

    Returns
    -------
    sky, indirect : (H, W, 3) float64
        The two terms, changed on the shadow-labelled valid pixels only.
    """
    sky = np.asarray(sky, dtype=np.float64)
    indirect = np.asarray(indirect, dtype=np.float64)
    shadow = np.asarray(labels) == _SHADOW
    support = shadow & np.asarray(quantities.valid) & ~np.asarray(quantities.filled)
    if not support.any():
        return sky, indirect
    step1 = np.asarray(quantities.sky, dtype=np.float64) + quantities.indirect
    # Both means over the same pixels: one filtering of the six channels.
    means = masked_gaussian_mean(np.concatenate([step1, sky + indirect], axis=-1), support, sigma)
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = means[..., :3] / means[..., 3:]
    ratio = np.where(np.isfinite(ratio) & (ratio > 0), ratio, 1.0)
    factor = np.where((shadow & np.asarray(quantities.valid))[..., None], ratio, 1.0)
    return sky * factor, indirect * factor


def intrinsic_layers_result(
    view: View,
    quantities: PixelQuantities,
    labels: np.ndarray,
    sun_radiance: np.ndarray,
    *,
    clusters: np.ndarray | None = None,
    config: MattingConfig | None = None,
) -> MattingResult:
    """:func:`intrinsic_layers`, with the report of each linear solve and the seconds per part.

    A solve that misses ``config.rtol`` is logged as a warning and recorded in its
    :class:`SolveReport` (``converged`` False, ``residual``, ``n_iter``); the layers keep its last
    iterate, as :func:`intrinsic_layers` does.

    Parameters and errors as :func:`intrinsic_layers`.

    Returns
    -------
    MattingResult
    """
    config = config_or_default(config, MattingConfig)
    if not isinstance(view, View):
        raise TypeError(f"view must be a View, got {describe(view)}")
    if not isinstance(quantities, PixelQuantities):
        raise TypeError(f"quantities must be PixelQuantities, got {describe(quantities)}")
    if view.stem != quantities.stem or view.camera.shape != quantities.shape:
        raise ValueError(f"quantities ({quantities.stem!r}) do not belong to view {view.stem!r}")
    shape = quantities.shape
    labels = _check_labels(labels, shape)
    clusters = _check_clusters(clusters, shape)
    radiance = as_array(sun_radiance, "sun_radiance", shape=(3,), dtype=np.float64)
    if (radiance < 0).any():
        raise ValueError(f"sun_radiance must be non-negative, got {radiance.tolist()}")
    valid = np.asarray(quantities.valid, dtype=bool)
    image = np.where(valid[..., None], np.asarray(view.image, dtype=np.float64), 0.0)
    sky = np.where(valid[..., None], quantities.sky, 0.0).astype(np.float64)
    indirect = np.where(valid[..., None], quantities.indirect, 0.0).astype(np.float64)
    cosine = np.where(valid, quantities.cosine, 0.0).astype(np.float64)
    visibility = np.zeros(shape)
    reports: list[SolveReport] = []
    timings: dict[str, float] = {}
    if valid.any():
        began = time.perf_counter()
        laplacian = _GuidedLaplacian(guide_image(image, mask=valid, white_percentile=config.white_percentile), config)
        band = valid & _near(shadow_transitions(labels, mask=valid), config.shadow_band_radius)
        whole, outside_band = laplacian.stencils(valid, valid & ~band)
        timings["laplacian"] = time.perf_counter() - began
        constraints = valid & ~quantities.filled & ~band
        if clusters is not None:
            constraints &= ~boundary_band(np.where(valid, clusters, -1), config.cluster_boundary_width)
        stacked = np.concatenate([sky, indirect, cosine[..., None]], axis=2)

        def matte() -> tuple[np.ndarray, list[SolveReport], float]:
            began = time.perf_counter()
            result, report = _matte(laplacian, whole, labels, valid, clusters, config,
                                    f"sun visibility matting {view.stem!r}")
            return result, [] if report is None else [report], time.perf_counter() - began

        def shading() -> tuple[np.ndarray, list[SolveReport], float]:
            began = time.perf_counter()
            if not constraints.any():
                logger.warning("view %r: no proxy pixel left as a constraint; shading layers are the Step-1 values",
                               view.stem)
                return stacked, [], time.perf_counter() - began
            result, propagated = _propagate(laplacian, outside_band, stacked, constraints, valid, band, config,
                                            f"shading propagation {view.stem!r}", start=stacked)
            return result, list(propagated), time.perf_counter() - began

        # The two systems are independent and SuperLU releases the GIL: with two threads both
        # factorisations run at once (1.9x on two cores for two equal factorisations).
        if config.threads > 1:
            with ThreadPoolExecutor(max_workers=2) as pool:
                matted, propagated = pool.submit(matte), pool.submit(shading)
                (visibility, matte_reports, timings["visibility"]), (stacked, shading_reports,
                                                                      timings["propagation"]) = (
                    matted.result(), propagated.result())
        else:
            visibility, matte_reports, timings["visibility"] = matte()
            stacked, shading_reports, timings["propagation"] = shading()
        del whole, outside_band
        reports += matte_reports + shading_reports
        sky = np.maximum(stacked[..., 0:3], 0.0)
        indirect = np.maximum(stacked[..., 3:6], 0.0)
        cosine = np.clip(stacked[..., 6], 0.0, 1.0)
        if config.shadow_level is not None:  # beyond the paper: Step 1's level in the shadows
            sky, indirect = restore_shadow_level(quantities, labels, sky, indirect, sigma=config.shadow_level)
        logger.info("view %r: Laplacian %.2f s, visibility matte %.2f s, shading propagation %.2f s", view.stem,
                    timings["laplacian"], timings["visibility"], timings["propagation"])
    layers = layers_from_shading(view, valid, sky, indirect, visibility, cosine, radiance, labels,  # Eqs. 3, 17
                                 floor=config.shading_floor)
    return MattingResult(layers, tuple(reports), timings)
