"""Per-view exposure and white balance, recovered from the proxy points that several photos see.

The paper takes all photographs "under the same sun", with one exposure: its single ``L_sun``
(Eq. 5) and its per-vertex median radiance (Sec. 4) assume that a surface point has the same pixel
value in every view. Real captures break this: automatic exposure and white balance vary by more
than a stop between photos. This module (beyond the paper) models each view ``k`` by a gain per
channel,

.. math::

    I_k(\\mathbf{x}) = g_k \\, L(\\mathbf{x}),

with ``L(x)`` the radiance of surface point ``x`` in reference units (Lambertian: the same from
every view). Taking logarithms, ``log I_k(x) = log g_k + log L(x)``: a two-way layout whose
unknowns are one offset per view and one per point. It is solved per channel by alternating
medians (Tukey's median polish), robust to the samples that break the model (occlusions the
proxy misses, specular highlights, proxy errors at silhouettes). The scale is free; it is fixed
by a geometric mean of 1 over the views, so that the layers keep the units of the average photo.

:func:`estimate_view_gains` returns the gains and their evidence (:class:`ViewGains`);
:func:`compensate` divides the images by them before the decomposition and
:func:`restore_units` multiplies a view's shading layers back, so that ``R * S`` reproduces each
photograph in its own units.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ._validation import config_or_default, is_real
from .env_shading import vertex_observations
from .raytrace import Tracer
from .results import IntrinsicLayers, ViewGains
from .scene import Scene, View

__all__ = ["ExposureConfig", "ViewGains", "compensate", "estimate_view_gains", "restore_units"]

_METHODS = ("auto", "always", "none")


@dataclass(frozen=True)
class ExposureConfig:
    """Options of the per-view gain estimation (not in the paper).

    Parameters
    ----------
    method : {"auto", "always", "none"}
        ``"auto"`` estimates the gains and compensates them when some view's gain differs from 1
        by more than ``min_correction`` (a capture with one exposure is left as it is);
        ``"always"`` compensates whatever the estimate; ``"none"`` estimates nothing (the paper).
    min_correction : float
        Relative gain difference below which ``"auto"`` leaves the images alone: 0.02, below the
        spread of the estimate on renders with one exposure (0.2-0.6 %, docs/real_capture.md) times
        a safety factor, and below what changes the decomposition measurably.
    depth_tolerance : float
        Occlusion test of the vertex samples, relative depth (as Step 1's
        :attr:`~mvintrinsic.env_shading.Step1Config.depth_tolerance`).
    min_relative_value : float
        Samples darker than this fraction of their view's median sample (per channel) are left
        out: their relative noise and JPEG quantisation are large, and the log amplifies them.
    max_points : int
        Proxy points used in the fit at most (a seeded random subset of those seen twice); the
        gains of the test scenes move by less than 0.1% between 50,000 and 200,000 points.
    iterations : int
        Median-polish sweeps at most; it stops earlier when no gain moves by 1e-6 in log.
    """

    method: str = "auto"
    min_correction: float = 0.02
    depth_tolerance: float = 0.02
    min_relative_value: float = 0.02
    max_points: int = 50_000
    iterations: int = 50

    def __post_init__(self) -> None:
        if self.method not in _METHODS:
            raise ValueError(f"method must be one of {_METHODS}, got {self.method!r}")
        for name in ("min_correction", "depth_tolerance", "min_relative_value"):
            value = getattr(self, name)
            if not is_real(value) or not (0.0 <= value < 1.0):
                raise ValueError(f"{name} must be a number in [0, 1), got {value!r}")
        for name in ("max_points", "iterations"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be a positive integer, got {value!r}")


def _nanmedian_first_axis(a: np.ndarray) -> np.ndarray:
    """``np.nanmedian(a, axis=0)`` for a short first axis, by one sort (10x faster here)."""
    ordered = np.sort(a, axis=0)  # NaN last
    n = np.isfinite(a).sum(axis=0)
    lo = np.take_along_axis(ordered, np.maximum(n - 1, 0)[None] // 2, axis=0)[0]
    hi = np.take_along_axis(ordered, (n // 2)[None], axis=0)[0]
    return np.where(n > 0, 0.5 * (lo + hi), np.nan)


def _median_polish(logs: np.ndarray, iterations: int) -> tuple[np.ndarray, np.ndarray]:
    """View effects of ``logs (V, M, C)`` (NaN = missing) by alternating medians.

    Returns (V, C) log gains (mean 0 over the views with data) and (V, C) robust residual spread
    (NaN for a view without data).
    """
    rows = np.isfinite(logs).any(axis=(1, 2))
    g = np.zeros((logs.shape[0], logs.shape[2]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # views without data: all-NaN medians
        for _ in range(iterations):
            point = _nanmedian_first_axis(logs - g[:, None])  # log L(x), (M, C)
            new = np.nanmedian(logs - point[None], axis=1)  # (V, C)
            new[~rows] = 0.0
            new[rows] -= new[rows].mean(axis=0)
            moved = float(np.abs(new - g).max())
            g = new
            if moved < 1e-6:
                break
        residual = logs - g[:, None] - _nanmedian_first_axis(logs - g[:, None])[None]
        spread = 1.4826 * np.nanmedian(np.abs(residual), axis=1)
    return g, spread


def estimate_view_gains(
    views: Sequence[View],
    tracer: Tracer,
    *,
    config: ExposureConfig | None = None,
    depths: Sequence[np.ndarray] | None = None,
    rng: np.random.Generator | int | None = None,
) -> ViewGains:
    """Exposure and white-balance gain of every view from the proxy points they share.

    Parameters
    ----------
    views : sequence of View
        The photographs (linear RGB, each in its own units).
    tracer : Tracer
        Built over the scene's proxy.
    config : ExposureConfig, optional
    depths : sequence of (H, W) arrays, optional
        Proxy depth maps of the views (:func:`~mvintrinsic.raytrace.depth_map`), if already cast.
    rng : numpy.random.Generator or int or None, optional
        Seeds the subset of points used when more than ``config.max_points`` are shared.

    Returns
    -------
    ViewGains
        ``estimated`` per view and channel (geometric mean 1 over the views that share points),
        ``applied`` by the rule of ``config.method``, the number of shared points and the
        residual spread per view. A view that shares no point with another keeps gain 1 (with a
        warning): nothing relates its units to the others'.

    Notes
    -----
    The samples are those of Step 1's vertex radiance (:func:`~mvintrinsic.env_shading.vertex_observations`):
    vertex projections that pass the occlusion test and fall on valid (unsaturated) pixels.
    """
    config = config_or_default(config, ExposureConfig)
    views = list(views)
    stems = tuple(v.stem for v in views)
    if config.method == "none":
        return ViewGains.identity(stems, "method='none': not estimated")
    if len(views) < 2:
        return ViewGains.identity(stems, "a single view: no gain to relate")
    samples = vertex_observations(views, tracer, depth_tolerance=config.depth_tolerance, depths=depths)
    with np.errstate(invalid="ignore", divide="ignore"):
        floor = np.nanmedian(np.where(samples > 0, samples, np.nan), axis=1) * config.min_relative_value  # (V, 3)
        usable = np.isfinite(samples).all(axis=2) & (samples > np.nan_to_num(floor, nan=np.inf)[:, None, :]).all(axis=2)
    seen = usable.sum(axis=0)
    points = np.flatnonzero(seen >= 2)
    gen = np.random.default_rng(rng)
    if len(points) > config.max_points:
        points = np.sort(gen.choice(points, config.max_points, replace=False))
    shared = usable[:, points].sum(axis=1).astype(np.int64)
    if len(points) == 0:
        warnings.warn("no proxy point is seen by two views: the per-view gains cannot be estimated (kept at 1)",
                      RuntimeWarning, stacklevel=2)
        return ViewGains.identity(stems, "no proxy point seen by two views")
    logs = np.where(usable[:, points, None], np.log(np.where(usable[:, points, None], samples[:, points], 1.0)), np.nan)
    log_gains, residual = _median_polish(logs, config.iterations)
    lonely = [s for s, n in zip(stems, shared, strict=True) if n == 0]
    if lonely:
        warnings.warn(f"views {lonely} share no proxy point with another view: their gains are kept at 1",
                      RuntimeWarning, stacklevel=2)
    estimated = np.exp(log_gains)
    largest = float(np.abs(estimated - 1.0).max())
    if config.method == "always":
        applied, reason = True, "method='always'"
    elif largest > config.min_correction:
        applied, reason = True, f"a gain differs from 1 by {100 * largest:.1f}% (> {100 * config.min_correction:g}%)"
    else:
        applied, reason = False, (f"every gain within {100 * config.min_correction:g}% of 1 (largest "
                                  f"{100 * largest:.2f}%): one exposure, images left as they are")
    return ViewGains(stems, estimated, applied, shared, residual, reason)


def compensate(scene: Scene, gains: ViewGains) -> Scene:
    """The scene with every image divided by its view's gain (reference units).

    Parameters
    ----------
    scene : Scene
    gains : ViewGains
        For the scene's views (by stem). Gains not applied (``gains.applied`` False) leave the
        scene as it is.

    Returns
    -------
    Scene
        A new scene (the input is not modified); masks, cameras, proxy and sun unchanged.
    """
    if not isinstance(gains, ViewGains):
        raise TypeError(f"gains must be ViewGains, got {type(gains).__name__}")
    missing = [v.stem for v in scene.views if v.stem not in gains.stems]
    if missing:
        raise ValueError(f"gains: no gain for views {missing}")
    if not gains.applied:
        return scene
    views = []
    for view in scene.views:
        g = gains.of(view.stem).astype(np.float32)
        views.append(View(view.stem, view.image / g, view.camera, view.mask))
    return Scene(tuple(views), scene.proxy, scene.sun, up=scene.up, source=scene.source)


def restore_units(layers: IntrinsicLayers, gain: object) -> IntrinsicLayers:
    """A view's layers computed on the compensated image, with the shading in the photo's units.

    ``S_sun``, ``S_sky`` and ``S_ind`` are multiplied by ``gain`` (3,) per channel; reflectance,
    visibility and labels are unchanged, so ``R * S`` reproduces the photograph.
    """
    g = np.asarray(gain, dtype=np.float32)
    if g.shape != (3,) or not np.isfinite(g).all() or (g <= 0).any():
        raise ValueError(f"gain must be 3 positive finite numbers, got {g.tolist()}")
    if np.all(g == 1.0):
        return layers
    return IntrinsicLayers(
        layers.stem, reflectance=layers.reflectance, sun_shading=layers.sun_shading * g,
        sky_shading=layers.sky_shading * g, indirect_shading=layers.indirect_shading * g,
        visibility=layers.visibility, shadow_labels=layers.shadow_labels,
    )
