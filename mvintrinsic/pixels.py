"""Step-1 quantities carried from the proxy vertices to the pixels of a view.

Step 1 estimates ``S_sky``, ``S_ind`` and the proxy sun visibility ``~v`` at the vertices of the
proxy (paper Sec. 4). Steps 2 and later work in image space, so every view needs them per pixel.
This module does the simple, documented transfer used until Step 3's image-guided propagation
(paper Sec. 6.2) takes over:

* a pixel whose centre ray hits the proxy takes the barycentric interpolation of the hit
  triangle's vertex values (one primary ray per pixel, Embree);
* a valid pixel whose ray misses the proxy, whose direction is sky in the environment map and
  whose colour is close to the sky's there (the fitted sky model's or the environment map's
  radiance; :attr:`~mvintrinsic.env_shading.Step1Config.sky_colour_tolerance`) is sky: it carries no
  shading;
* a valid pixel whose ray misses the proxy but does not see the sky (geometry the proxy lost,
  typically foliage) takes the values of the nearest covered pixel (Euclidean distance in the
  image), flagged in :attr:`PixelQuantities.filled`.

The sun cosine is recomputed per pixel from the interpolated, renormalised vertex normal, so it is
``max(0, n . w_sun)`` of a smooth normal rather than an interpolated clamp.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from .env_shading import Step1Result
from .image_model import clamped_cosine, sun_shading, total_shading
from .raytrace import Tracer
from .results import SHADOW_LABELS, IntrinsicLayers
from .scene import View

#: Total shading below this fraction of the view's median is raised to it in ``S_ind`` so that
#: ``R = I / S_tot`` stays finite (a pixel the proxy says receives no light at all).
SHADING_FLOOR = 1e-3

__all__ = ["SHADING_FLOOR", "PixelQuantities", "floored_shading", "layers_from_shading", "masked_box_mean",
           "masked_gaussian_mean", "nearest_fill", "pixel_quantities"]


@dataclass(frozen=True, eq=False)
class PixelQuantities:
    """Step-1 quantities of one view, per pixel (``H x W`` of the view's image).

    Parameters
    ----------
    stem : str
        View name.
    sky, indirect : (H, W, 3) float32
        ``S_sky`` and ``S_ind`` in shading units; 0 on sky and invalid pixels.
    visibility : (H, W) float32
        Proxy sun visibility ``~v`` in [0, 1] (fractional where a pixel's triangle straddles a
        shadow edge); 1 on sky and invalid pixels.
    cosine : (H, W) float32
        ``max(0, cos omega_sun)`` with the interpolated vertex normal; 0 on sky and invalid pixels.
    normals : (H, W, 3) float32
        Unit world-frame normal (interpolated vertex normals); 0 on sky and invalid pixels.
    depth : (H, W) float32
        Distance (metres) along the pixel's centre ray to the proxy; ``inf`` where it misses.
    sky_mask : (H, W) bool
        Valid pixels that see the sky (ray misses the proxy toward a sky texel).
    filled : (H, W) bool
        Valid, non-sky pixels the proxy does not cover; their values come from the nearest covered
        pixel.
    valid : (H, W) bool
        Pixels with an estimate: the view's valid pixels minus the sky.
    """

    stem: str
    sky: np.ndarray
    indirect: np.ndarray
    visibility: np.ndarray
    cosine: np.ndarray
    normals: np.ndarray
    depth: np.ndarray
    sky_mask: np.ndarray
    filled: np.ndarray
    valid: np.ndarray

    @property
    def env(self) -> np.ndarray:
        """``S_env = S_sky + S_ind`` (Eq. 3), (H, W, 3) float32."""
        return self.sky + self.indirect

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)``."""
        return self.visibility.shape

    def __repr__(self) -> str:
        h, w = self.shape
        return (f"PixelQuantities({self.stem!r}, {w}x{h}, valid={int(self.valid.sum())}, "
                f"sky={int(self.sky_mask.sum())}, filled={int(self.filled.sum())})")


def pixel_quantities(view: View, step1_result: Step1Result, tracer: Tracer, *, sun_direction: np.ndarray) -> PixelQuantities:
    """Carry Step 1's per-vertex ``S_sky``, ``S_ind``, ``~v`` and normals into a view.

    Parameters
    ----------
    view : View
        The view (its camera and valid-pixel mask are used; its pixels are not).
    step1_result : Step1Result
        Per-vertex quantities of the proxy ``tracer`` was built on.
    tracer : Tracer
        Ray caster over the same proxy.
    sun_direction : (3,) array_like
        Unit world vector toward the sun.

    Returns
    -------
    PixelQuantities

    Raises
    ------
    ValueError
        If ``step1_result`` does not describe ``tracer``'s proxy.
    """
    n_vertices = len(tracer.proxy.vertices)
    if len(step1_result.shading.visibility) != n_vertices:
        raise ValueError(f"step1_result has {len(step1_result.shading.visibility)} points but the tracer's proxy has "
                         f"{n_vertices} vertices")
    camera = view.camera
    h, w = camera.shape
    rays = camera.pixel_rays()
    hits = tracer.intersect(camera.center, rays)
    shading = step1_result.shading
    # One interpolation for all per-vertex quantities: S_sky (3), S_ind (3), ~v (1), normal (3).
    stacked = np.concatenate([shading.sky, shading.indirect, shading.visibility[:, None], step1_result.normals], axis=1)
    values = tracer.interpolate(stacked, hits).reshape(h, w, 10)
    covered = hits.hit.reshape(h, w)
    depth = hits.t.reshape(h, w).astype(np.float32)

    uncovered = view.mask & ~covered
    sky_mask = np.zeros((h, w), dtype=bool)
    if uncovered.any():
        directions = rays.reshape(h, w, 3)[uncovered]
        sky = step1_result.environment.is_sky(directions)
        tolerance = step1_result.config.sky_colour_tolerance
        if tolerance is not None and sky.any():
            sky[sky] = _looks_like_sky(np.asarray(view.image)[uncovered][sky], directions[sky], step1_result, tolerance)
        sky_mask[uncovered] = sky
    filled = uncovered & ~sky_mask
    valid = view.mask & ~sky_mask
    if filled.any():
        if not covered.any():
            raise ValueError(f"view {view.stem!r}: no pixel sees the proxy, nothing to carry into the view")
        values[filled] = nearest_fill(values, covered)[filled]

    values[~valid] = 0.0
    normals = values[..., 7:10]
    length = np.linalg.norm(normals, axis=-1, keepdims=True)
    normals = np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)
    cosine = clamped_cosine(normals, sun_direction)  # max(0, cos w_sun) of Eq. 1; normals are 0 off valid
    visibility = np.where(valid, np.clip(values[..., 6], 0.0, 1.0), 1.0)
    return PixelQuantities(
        stem=view.stem,
        sky=values[..., 0:3].astype(np.float32),
        indirect=values[..., 3:6].astype(np.float32),
        visibility=visibility.astype(np.float32),
        cosine=cosine.astype(np.float32),
        normals=normals.astype(np.float32),
        depth=depth,
        sky_mask=sky_mask,
        filled=filled,
        valid=valid,
    )


def _looks_like_sky(colours: np.ndarray, directions: np.ndarray, step1_result: Step1Result,
                    tolerance: float) -> np.ndarray:
    """Whether pixel ``colours (N, 3)`` are within ``tolerance`` (log-RGB norm) of the fitted sky
    model's or the environment map's radiance in ``directions (N, 3)``: ``(N,)`` bool."""
    log_colour = np.log(np.maximum(np.asarray(colours, dtype=np.float64), 1e-6))
    close = np.zeros(len(colours), dtype=bool)
    for reference in (step1_result.sky_model.radiance(directions), step1_result.environment.lookup(directions)):
        log_reference = np.log(np.maximum(np.asarray(reference, dtype=np.float64), 1e-6))
        close |= np.linalg.norm(log_colour - log_reference, axis=1) < tolerance
    return close


def nearest_fill(values: np.ndarray, known: np.ndarray) -> np.ndarray:
    """``values (H, W, ...)`` of the nearest ``known`` pixel, everywhere (Euclidean distance in
    the image); a copy. ``known (H, W)`` bool must hold at least one pixel."""
    if known.all():
        return values.copy()
    _, (rows, cols) = ndimage.distance_transform_edt(~known, return_indices=True)
    return values[rows, cols]


def masked_box_mean(values: np.ndarray, mask: np.ndarray, window: int) -> np.ndarray:
    """Mean of ``values`` over the ``mask`` pixels of each ``window x window`` neighbourhood.

    Parameters
    ----------
    values : (H, W, C) array_like
    mask : (H, W) bool
        Pixels that count; a window with none of them gives 0.
    window : int
        Side in pixels; 1 or less returns ``values`` unchanged.

    Returns
    -------
    (H, W, C) float64
    """
    values = np.asarray(values, dtype=np.float64)
    if window <= 1:
        return values
    weights = ndimage.uniform_filter(mask.astype(np.float64), size=window, mode="constant")
    total = ndimage.uniform_filter(np.where(mask[..., None], values, 0.0), size=(window, window, 1), mode="constant")
    return total / np.maximum(weights, 1e-12)[..., None]


def masked_gaussian_mean(values: np.ndarray, mask: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian-weighted mean of ``values`` over the ``mask`` pixels (normalised convolution).

    :func:`masked_box_mean` with a Gaussian of standard deviation ``sigma`` pixels for the box.

    Parameters
    ----------
    values : (H, W, C) array_like
    mask : (H, W) bool
        Pixels that count; far from all of them the result is 0.
    sigma : float
        Standard deviation in pixels, > 0.

    Returns
    -------
    (H, W, C) float64
    """
    values = np.asarray(values, dtype=np.float64)
    weights = ndimage.gaussian_filter(mask.astype(np.float64), sigma, mode="constant")
    total = ndimage.gaussian_filter(np.where(mask[..., None], values, 0.0), (sigma, sigma, 0), mode="constant")
    return total / np.maximum(weights, 1e-12)[..., None]


def floored_shading(sky: np.ndarray, indirect: np.ndarray, visibility: np.ndarray, sun: np.ndarray,
                    valid: np.ndarray, *, floor: float = SHADING_FLOOR) -> tuple[np.ndarray, np.ndarray]:
    """``S_tot = S_sky + S_ind + v_sun S_sun`` (Eq. 17), ``S_ind`` raised where ``S_tot`` is too low.

    Where ``S_tot`` is below ``floor`` times its median over ``valid``, ``S_ind`` is raised by the
    difference, so that ``R = I / S_tot`` stays finite and ``R * S_tot`` reproduces the image.

    Parameters
    ----------
    sky, indirect, sun : (H, W, 3) array_like
        ``S_sky``, ``S_ind`` and the unshadowed ``S_sun``, shading units.
    visibility : (H, W) array_like
        ``v_sun`` in [0, 1].
    valid : (H, W) bool
        Pixels with an estimate: the median is taken over them and only they are raised.
    floor : float, optional

    Returns
    -------
    indirect, total : (H, W, 3) float64
        The raised ``S_ind`` and ``S_tot``.
    """
    sky = np.asarray(sky, dtype=np.float64)
    indirect = np.asarray(indirect, dtype=np.float64)
    visibility = np.asarray(visibility, dtype=np.float64)
    total = total_shading(sky, indirect, visibility, sun)
    if valid.any():
        lowest = floor * float(np.median(total[valid]))
        indirect = indirect + np.where(valid[..., None], np.maximum(lowest - total, 0.0), 0.0)
        total = total_shading(sky, indirect, visibility, sun)
    return indirect, total


def layers_from_shading(view: View, valid: np.ndarray, sky: np.ndarray, indirect: np.ndarray,
                        visibility: np.ndarray, cosine: np.ndarray, sun_radiance: np.ndarray, labels: np.ndarray,
                        *, floor: float = SHADING_FLOOR) -> IntrinsicLayers:
    """Intrinsic layers of a view from its per-pixel shading terms: ``R = I / S_tot`` (Eqs. 3, 17).

    ``S_sun = L_sun max(0, cos)`` (Eq. 3), ``S_tot = S_sky + S_ind + v_sun S_sun`` (Eq. 17). Where
    ``S_tot`` is below ``floor`` times the view's median over ``valid``, ``S_ind`` is raised to reach
    it, so ``R`` stays finite and ``R * S_tot`` reproduces the image. Pixels outside ``valid`` hold
    zeros and label 128.

    Parameters
    ----------
    view : View
    valid : (H, W) bool
        Pixels with an estimate.
    sky, indirect : (H, W, 3) array_like
        ``S_sky``, ``S_ind``, shading units.
    visibility, cosine : (H, W) array_like
        ``v_sun`` in [0, 1] and ``max(0, cos omega_sun)``.
    sun_radiance : (3,) array_like
        ``L_sun``.
    labels : (H, W) uint8
        Shadow labels (0 shadow, 255 lit, 128 undecided) on the valid pixels.
    floor : float, optional

    Returns
    -------
    IntrinsicLayers
    """
    image = np.where(valid[..., None], np.asarray(view.image, dtype=np.float64), 0.0)
    sky = np.asarray(sky, dtype=np.float64)
    indirect = np.asarray(indirect, dtype=np.float64)
    visibility = np.asarray(visibility, dtype=np.float64)
    sun = sun_shading(sun_radiance, cosine)                                              # Eq. 3
    indirect, total = floored_shading(sky, indirect, visibility, sun, valid, floor=floor)  # Eq. 17
    reflectance = np.divide(image, total, out=np.zeros_like(image), where=valid[..., None] & (total > 0))  # Eq. 2
    zero = ~valid[..., None]
    return IntrinsicLayers(
        stem=view.stem,
        reflectance=reflectance.astype(np.float32),
        sun_shading=np.where(zero, 0.0, sun).astype(np.float32),
        sky_shading=np.where(zero, 0.0, sky).astype(np.float32),
        indirect_shading=np.where(zero, 0.0, indirect).astype(np.float32),
        visibility=np.where(valid, visibility, 0.0).astype(np.float32),
        shadow_labels=np.where(valid, labels, SHADOW_LABELS["undecided"]).astype(np.uint8),
    )
