"""Working resolution: decompose at a fraction of the photos' size, deliver layers at full size.

Beyond the paper. Most of the pipeline's cost grows with the pixel count (the depth maps, the
per-pixel Step-1 quantities, the shadow labels, the segmentation and the matting), while what it
estimates per pixel is smooth except at shadow and material edges: ``S_sky``, ``S_ind`` and the
unshadowed ``S_sun`` vary with the proxy's normals and occlusion, ``v_sun`` only at shadow edges.
:func:`downscale_scene` gives the scene at ``scale`` (area-averaged images, exact cameras);
:func:`upsample_layers` carries the layers computed on it back to each full-size photo:

1. the shading terms ``S_sky``, ``S_ind``, ``S_sun`` and ``v_sun`` by bilinear interpolation
   normalised by the valid pixels (so invalid pixels do not bleed in);
2. ``v_sun`` then follows the full-size photo's edges: a guided filter [1]_ of the bilinear
   ``v_sun`` with the photo's log luminance as guide, radius ``1 / scale`` pixels. A shadow edge is
   an edge of the photo, so the guide restores the sharpness the low resolution lost;
3. ``R = I / S_tot`` at full size with the same floor on ``S_tot`` as every other stage
   (Eq. 2 and 17, :func:`mvintrinsic.pixels.floored_shading`), so ``R * S`` reproduces each photo
   exactly and the reflectance keeps the photo's full detail.

The shadow labels are taken from the upsampled ``v_sun`` (lit at 1/2 and above).

References
----------
.. [1] K. He, J. Sun, X. Tang. Guided Image Filtering. IEEE TPAMI 35(6), 2013.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .pixels import SHADING_FLOOR, floored_shading
from .results import SHADOW_LABELS, IntrinsicLayers
from .scene import Scene, View

__all__ = ["downscale_scene", "downscale_view", "resize_image", "upsample_layers"]

#: Regularisation of the guided filter (:func:`upsample_layers`) on a log-luminance guide:
#: edges weaker than about ``sqrt(eps)`` in log units (a 10% step) are smoothed over.
GUIDE_EPSILON = 0.01


def _check_scale(scale: object) -> float:
    if isinstance(scale, bool) or not isinstance(scale, (int, float)) or not 0.0 < float(scale) <= 1.0:
        raise ValueError(f"scale must be a number in (0, 1], got {scale!r}")
    return float(scale)


def resize_image(image: np.ndarray, mask: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Area-average ``image`` to ``width x height``; a result pixel is valid only if all its sources were.

    Parameters
    ----------
    image : (H, W, C) or (H, W) array_like
    mask : (H, W) bool
        Valid source pixels; the others are left out of the averages.
    width, height : int
        The new size in pixels.

    Returns
    -------
    image : (height, width[, C]) float32
    mask : (height, width) bool
    """
    import cv2

    mask = np.asarray(mask, dtype=bool)
    image = np.asarray(image)
    weight = mask if image.ndim == 2 else mask[..., None]
    clean = np.where(weight, image, 0.0).astype(np.float32)
    small = cv2.resize(clean, (int(width), int(height)), interpolation=cv2.INTER_AREA)
    coverage = cv2.resize(mask.astype(np.float32), (int(width), int(height)), interpolation=cv2.INTER_AREA)
    return small, coverage > 1.0 - 1e-4


def _scaled_size(shape: tuple[int, int], scale: float) -> tuple[int, int]:
    h, w = shape
    return max(1, round(w * scale)), max(1, round(h * scale))


def downscale_view(view: View, scale: float) -> View:
    """``view`` at ``scale`` times its size: area-averaged image and mask, the camera rescaled.

    Parameters
    ----------
    view : View
    scale : float
        In (0, 1]; 1 returns ``view`` itself.

    Returns
    -------
    View
    """
    scale = _check_scale(scale)
    if scale == 1.0:
        return view
    width, height = _scaled_size(view.shape, scale)
    image, mask = resize_image(view.image, view.mask, width, height)
    return View(view.stem, image, view.camera.scaled(width, height), mask)


def downscale_scene(scene: Scene, scale: float) -> Scene:
    """Every view of ``scene`` at ``scale`` times its size (:func:`downscale_view`); the rest unchanged."""
    scale = _check_scale(scale)
    if scale == 1.0:
        return scene
    return dataclasses.replace(scene, views=tuple(downscale_view(v, scale) for v in scene.views))


def _bilinear(values: np.ndarray, valid: np.ndarray, width: int, height: int) -> np.ndarray:
    """Bilinear upsampling of ``values`` (h, w[, C]) normalised by the valid pixels' weight."""
    import cv2

    weight = valid.astype(np.float32)
    w = weight if values.ndim == 2 else weight[..., None]
    num = cv2.resize((np.nan_to_num(values) * w).astype(np.float32), (width, height), interpolation=cv2.INTER_LINEAR)
    den = cv2.resize(weight, (width, height), interpolation=cv2.INTER_LINEAR)
    if values.ndim == 3:
        den = den[..., None]
    return np.divide(num, den, out=np.zeros_like(num), where=den > 1e-6)


def _guided(guide: np.ndarray, source: np.ndarray, radius: int, eps: float) -> np.ndarray:
    """He et al.'s guided filter [1]_ with a grey guide (box means by ``cv2.boxFilter``)."""
    import cv2

    def mean(x: np.ndarray) -> np.ndarray:
        return cv2.boxFilter(x, -1, (2 * radius + 1, 2 * radius + 1), borderType=cv2.BORDER_REFLECT)

    mean_i, mean_p = mean(guide), mean(source)
    var_i = mean(guide * guide) - mean_i * mean_i
    cov_ip = mean(guide * source) - mean_i * mean_p
    a = cov_ip / (var_i + eps)
    b = mean_p - a * mean_i
    return mean(a) * guide + mean(b)


def upsample_layers(view: View, layers: IntrinsicLayers, *, guided: bool = True,
                    floor: float = SHADING_FLOOR) -> IntrinsicLayers:
    """Layers computed on a downscaled ``view`` (:func:`downscale_view`), at ``view``'s full size.

    Module docstring: the shading terms by valid-normalised bilinear interpolation, ``v_sun``
    guided by the photo's log luminance (``guided``), then ``R = I / S_tot`` (Eqs. 2, 17).

    Parameters
    ----------
    view : View
        The full-size view.
    layers : IntrinsicLayers
        The layers of the downscaled view (any size smaller than or equal to ``view``'s).
    guided : bool, optional
        Guided filtering of ``v_sun`` (True) or bilinear only.
    floor : float, optional
        ``S_tot`` floor, times its median (:func:`~mvintrinsic.pixels.floored_shading`).

    Returns
    -------
    IntrinsicLayers
        At ``view.shape``; its pixels are ``view.mask`` and covered by the small layers' valid
        pixels.
    """
    if not isinstance(view, View):
        raise TypeError(f"view must be a View, got {type(view).__name__}")
    if not isinstance(layers, IntrinsicLayers):
        raise TypeError(f"layers must be IntrinsicLayers, got {type(layers).__name__}")
    if layers.stem != view.stem:
        raise ValueError(f"layers are of view {layers.stem!r}, not {view.stem!r}")
    height, width = view.shape
    if layers.shape == (height, width):
        return layers
    small_valid = layers.shadow_labels != SHADOW_LABELS["undecided"]
    small_valid |= (layers.reflectance > 0).any(axis=-1)
    den = _bilinear(np.ones(layers.shape, np.float32), small_valid, width, height)
    covered = den > 0
    valid = view.mask & covered
    sky = _bilinear(layers.sky_shading, small_valid, width, height)
    indirect = _bilinear(layers.indirect_shading, small_valid, width, height)
    sun = _bilinear(layers.sun_shading, small_valid, width, height)
    visibility = _bilinear(layers.visibility, small_valid, width, height)
    if guided:
        luminance = np.asarray(view.image, dtype=np.float32) @ np.array([0.2126, 0.7152, 0.0722], np.float32)
        guide = np.log(np.maximum(luminance, 1e-4)).astype(np.float32)
        radius = max(1, round(width / layers.shape[1]))
        visibility = _guided(guide, visibility.astype(np.float32), radius, GUIDE_EPSILON)
    visibility = np.clip(visibility, 0.0, 1.0)
    indirect, total = floored_shading(sky, indirect, visibility, sun, valid, floor=floor)  # Eq. 17
    image = np.where(valid[..., None], np.asarray(view.image, dtype=np.float64), 0.0)
    reflectance = np.divide(image, total, out=np.zeros_like(image), where=valid[..., None] & (total > 0))  # Eq. 2
    labels = np.where(visibility >= 0.5, SHADOW_LABELS["lit"], SHADOW_LABELS["shadow"])
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

