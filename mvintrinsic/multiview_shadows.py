"""Step 3a beyond the paper: one shadow labelling for all views, at pixel resolution.

The paper labels each view alone, per mean-shift cluster (Sec. 6.1, :mod:`mvintrinsic.shadow_mrf`).
Measured on the project's scenes that labelling cannot get below the segmentation's floor and
stops at a balanced error of 0.15-0.34 even with exact shading (``docs/step3.md``). This module
labels every pixel of every view in one procedure that keeps the paper's principle -- *prefer the
explanation with fewer reflectances* (Sec. 3.3) -- and adds what the paper leaves out: the other
views, the colour of a shadow, and physically possible albedos.

Notation, per pixel (all RGB, shading units): the image ``I``, Step 1's environment shading
``S_env = S_sky + S_ind`` and the unshadowed sun term ``S_sun = L_sun max(0, cos w_sun)`` (Eq. 3);
``a = log I`` and the two reflectance hypotheses of Eq. 2, ``r_0 = a - log S_env`` (in shadow) and
``r_1 = a - log(S_env + S_sun)`` (lit); their difference ``lambda = log(1 + S_sun / S_env)`` is
the log *shadow ratio*: a shadow darkens a surface by ``lambda``, more in red than in blue under a
warm sun and a blue sky.

Per view, a score ``s(p)`` (> 0 favours lit) sums four terms:

1. **Edge evidence** (the paper's ``D_01`` / ``D_10`` of Eq. 6 on pixel pairs): for each pixel
   ``p`` and partners ``q`` at a few distances (``edge_radii``) in ``edge_directions`` directions,
   the jump ``a_p - a_q`` is compared with three explanations: ``+lambda`` (``p`` lit, ``q`` in
   shadow), ``-lambda`` (the reverse) and ``0`` (same light), each at cost
   ``|jump - explanation|^2 / (2 edge_sigma^2)``, and with a different material at the constant
   ``edge_material_cost``. The best pair's margin of "``p`` lit" over the best alternative is the
   lit vote, likewise the shadow vote; the term is ``edge_weight (lit - shadow)``. Partners at
   several distances let a jump across a penumbra be compared whole.
2. **Palette evidence** ("fewer reflectances", Secs. 3.3 and 6.1): the reflectances of the current
   labelling (``r_1`` on lit pixels, ``r_0`` in shadow), pooled over all views, form a histogram
   of log reflectance (:class:`ReflectancePalette`: log luminance and two log chromaticities). A
   pixel's most probable visibility is the ``v`` in [0, 1] whose reflectance
   ``a - log(S_env + v S_sun)`` the palette finds most common (:func:`palette_visibility`); it
   votes lit when that ``v`` is at least 1/2, with the confidence ``min(cap, log p_max - median_v
   log p)``. Searching ``v`` on the whole segment rather than comparing ``r_0`` with ``r_1`` puts
   the decision at half visibility: a pixel under a dappled shadow that still gets some sun is
   decided by whether it gets more or less than half of it.
3. **Albedo bound**: a diffuse albedo cannot exceed ``albedo_max`` (1). A pixel whose ``r_0``
   exceeds it in some channel cannot be in shadow; the term is
   ``albedo_weight (max_c(r_0 - log albedo_max)_+ - max_c(r_1 - log albedo_max)_+)``.
4. **Proxy prior** (Step 1's ``~v``): ``prior_lit (2 ~v - 1)`` where ``~v >= 1/2``,
   ``prior_shadow (2 ~v - 1)`` below. Asymmetric: an MVS proxy loses casters (foliage, poles) far
   more often than it invents them, so its shadows are trusted more than its light. Beyond that
   (``clear_rays``, not in the paper): where the photographs see the sun ray's path free, no lost
   caster stands on it, and the proxy's light gets ``clear_rays.prior`` instead of ``prior_lit``
   (:func:`mvintrinsic.photo_occupancy.clear_sun_rays`; with ``sun_direction`` only).

**All views at once.** Before each labelling the scores are averaged over every pixel and the
pixels of the other views that see the same proxy point and agree with it in colour
(:func:`mvintrinsic.correspondence.fuse_views`), so a shadow that is clear in some views decides
the others; the palette is pooled over all views.

**Pixel resolution.** Each view's labels minimise ``sum_p c_p(x_p) + sum_{p~q} w_pq [x_p != x_q]``
exactly by one s-t minimum cut (:func:`grid_cut`; PyMaxflow), with the unary costs ``c_p(lit) =
max(-s, 0)``, ``c_p(shadow) = max(s, 0)`` and contrast-sensitive Potts weights on the
8-neighbourhood ``w_pq = smoothness exp(-|a_p - a_q|^2 / (2 contrast^2)) / |p - q|``: labels change
along image edges, at any pixel, not along cluster boundaries.

**Iterations.** The first labelling uses terms 1, 3 and 4; each of the ``iterations`` rounds
rebuilds the palette from the last labels and labels again (an EM-like alternation between the
reflectance histogram and the visibility), stopping early when no label changes.

**Consensus.** Fused scores still leave views that disagree along a shadow's edge, where one
view's pixel straddles it and another's does not. A last majority vote over each pixel and its
consistent correspondences (:func:`~mvintrinsic.correspondence.consensus`, ``consensus_passes``)
settles those.

Everything pooled over views runs in stem order, so the labels do not depend on the order in which
the views are given. The per-pixel most probable visibility of the last palette is returned too
(:attr:`PixelShadowLabels.visibility`).

Measured on nine scenes (``benchmarks/bench_shadows.py``; figures and the choices not kept in
``docs/step3.md``): balanced error 0.073-0.150 against the paper's 0.192-0.340.

Sources: the paper's labelling [1]_, Boykov and Jolly's Potts weights [2]_, their max-flow [3]_.

References
----------
.. [1] S. Duchêne et al., "Multi-View Intrinsic Images of Outdoors Scenes with an Application to
   Relighting", ACM Transactions on Graphics 34(5), 2015, Secs. 3.3, 6.1.
.. [2] Y. Boykov and M.-P. Jolly, "Interactive graph cuts for optimal boundary & region
   segmentation of objects in N-D images", ICCV 2001 (contrast-sensitive Potts weights).
.. [3] Y. Boykov and V. Kolmogorov, "An experimental comparison of min-cut/max-flow algorithms for
   energy minimization in vision", IEEE TPAMI 26(9), 2004.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType

import numpy as np
from scipy import ndimage

from ._validation import as_array, as_unit_vector, config_or_default, describe, is_real
from .correspondence import Correspondences, _check_views, consensus, find_correspondences, fuse_views, log_image
from .photo_occupancy import ClearRaysConfig, clear_sun_rays
from .pixels import PixelQuantities
from .results import SHADOW_LABELS
from .scene import View

__all__ = [
    "LOG_CHROMA",
    "MultiViewShadowConfig",
    "MultiViewShadowLabels",
    "PixelShadowLabels",
    "ReflectancePalette",
    "albedo_term",
    "build_palette",
    "consensus",
    "edge_offsets",
    "edge_scale",
    "edge_votes",
    "grid_cut",
    "potts_weights",
    "label_shadows_multiview",
    "palette_visibility",
    "proxy_prior",
    "visibility_curve_bins",
]

logger = logging.getLogger(__name__)

#: Valid values of :attr:`MultiViewShadowConfig.palette_groups`.
PALETTE_GROUPS = ("orientation", "none")

#: Normals whose cosine with ``up`` exceeds this count as facing up (``palette_groups="orientation"``).
ORIENTATION_COS = 0.7

#: Log densities within this of the best count as tied in :func:`palette_visibility`.
TIE_TOLERANCE = 1e-9

#: Rows map log RGB to (log luminance, log R/G, log B/G): the palette's axes.
LOG_CHROMA = np.array([[1 / 3, 1 / 3, 1 / 3], [1.0, -1.0, 0.0], [0.0, -1.0, 1.0]])


@dataclass(frozen=True)
class MultiViewShadowConfig:
    """Options of :func:`label_shadows_multiview` (the module docstring defines every term).

    The defaults were chosen on the project's synthetic and shared scenes (240x180 to 1000x750),
    each value kept only where it helped on all of them (``benchmarks/bench_shadows.py``,
    ``docs/step3.md``).

    Parameters
    ----------
    iterations : int
        Palette rounds after the first labelling (>= 0); 3: the labels stop changing by then.
    palette_bins : (3,) float
        Histogram bin widths of log luminance, log R/G and log B/G. Luminance bins are wider than
        chromaticity bins: Step 1's ``S_env`` errs by tens of percent in brightness, far less in
        colour.
    palette_smoothing : float
        Gaussian smoothing of the histogram, in bins.
    visibility_levels : int
        Number of visibilities ``v`` in [0, 1] searched per pixel (>= 2).
    palette_weight, palette_cap : float
        Weight of the palette vote and the largest confidence (log-density gain) it can carry.
    edge_weight, edge_sigma, edge_material_cost : float
        Weight of the edge votes, the tolerance (log units) of a jump explained by light, and the
        cost of explaining it by a material change instead.
    edge_radii : tuple of int
        Partner distances (pixels) of the edge evidence (scaled up for large views with
        ``edge_reference``).
    edge_reference : int
        Longer image side (pixels) that ``edge_radii`` are meant for; a view whose longer side is
        ``k = round(side / edge_reference)`` times as long (``k >= 2``) uses ``k`` times the radii
        (:func:`edge_scale`); 0 (the default) never scales. Off by default, by measurement
        (``benchmarks/bench_shadows.py --edge-reference 480``, with the proxy's own normals, before
        Step 1 smoothed them): on the 1000x750 street (``street_1000``) the doubled radii lower
        the BER from 0.179 to 0.148, but raise the reflectance LMSE from 0.0563 to 0.0705 and lower the agreement from 0.953 to 0.949; the
        1000x750 courtyard is unchanged (BER 0.083, LMSE 0.1188). Scaling smaller views down is
        not offered: halving the radii raised the 240x180 demo's BER from 0.164 to 0.197.
    edge_directions : int
        Partner directions per distance.
    albedo_max, albedo_weight : float
        Largest plausible diffuse albedo and the weight of the bound.
    prior_lit, prior_shadow : float
        Weights of the proxy visibility where it says lit and where it says shadow.
    smoothness, contrast : float
        Potts weight and its contrast scale (log units) of the graph cut.
    view_weight : float
        Weight of each other view's score in the fusion (0: every view alone).
    depth_tolerance, photo_tolerance : float
        Tolerances of the cross-view correspondences
        (:func:`mvintrinsic.correspondence.find_correspondences`).
    palette_groups : {"orientation", "none"}
        ``"orientation"``: one palette for surfaces facing up (normal . ``up`` > 0.7: ground,
        roofs) and one for the rest (walls), as the two see different skies and Step 1's
        ``S_env`` errs differently on them; ``"none"``: one palette for all.
    edge_blur : float
        Standard deviation (pixels) of the Gaussian blur of ``a`` before the edge votes (0: none);
        it keeps sensor noise out of the jumps without moving edges.
    consensus_passes : int
        Passes of the cross-view consensus after the last labelling (>= 0): every pixel with
        consistent correspondences takes the label most of them and itself carry (its own on a
        tie), all views at once. Fusing the scores leaves views that disagree near a shadow's edge,
        where a pixel straddles it; the consensus makes the views agree there.
    clear_rays : ClearRaysConfig or None
        The lit prior where the photographs see the sun ray free (term 4;
        :class:`~mvintrinsic.photo_occupancy.ClearRaysConfig`); None: ``prior_lit`` everywhere (the
        labelling before it). Used when :func:`label_shadows_multiview` is given the sun's direction.
    """

    iterations: int = 3
    palette_bins: tuple[float, float, float] = (0.15, 0.05, 0.05)
    palette_smoothing: float = 1.0
    visibility_levels: int = 11
    palette_weight: float = 0.6
    palette_cap: float = 3.0
    edge_weight: float = 0.25
    edge_sigma: float = 0.15
    edge_material_cost: float = 2.0
    edge_radii: tuple[int, ...] = (2, 4, 7, 11)
    edge_reference: int = 0
    edge_directions: int = 16
    albedo_max: float = 1.0
    albedo_weight: float = 1.0
    prior_lit: float = 0.05
    prior_shadow: float = 0.2
    smoothness: float = 1.0
    contrast: float = 0.3
    view_weight: float = 1.0
    depth_tolerance: float = 0.03
    photo_tolerance: float = 0.25
    palette_groups: str = "orientation"
    edge_blur: float = 0.7
    consensus_passes: int = 1
    clear_rays: ClearRaysConfig | None = ClearRaysConfig()

    def __post_init__(self) -> None:
        for name, least in (("iterations", 0), ("consensus_passes", 0), ("visibility_levels", 2),
                            ("edge_directions", 1), ("edge_reference", 0)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
                raise ValueError(f"{name} must be an integer >= {least}, got {value!r}")
        bins = tuple(self.palette_bins)
        if len(bins) != 3 or not all(is_real(b) and 0 < b < np.inf for b in bins):
            raise ValueError(f"palette_bins must be three positive numbers, got {self.palette_bins!r}")
        object.__setattr__(self, "palette_bins", tuple(float(b) for b in bins))
        radii = tuple(self.edge_radii)
        if not all(isinstance(r, (int, np.integer)) and not isinstance(r, bool) and r >= 1 for r in radii):
            raise ValueError(f"edge_radii must be integers >= 1, got {self.edge_radii!r}")
        object.__setattr__(self, "edge_radii", tuple(int(r) for r in radii))
        for name in ("palette_smoothing", "palette_weight", "palette_cap", "edge_weight", "edge_material_cost",
                     "albedo_weight", "prior_lit", "prior_shadow", "smoothness", "view_weight"):
            value = getattr(self, name)
            if not is_real(value) or not 0 <= value < np.inf:
                raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
        for name in ("edge_sigma", "albedo_max", "contrast", "depth_tolerance", "photo_tolerance"):
            value = getattr(self, name)
            if not is_real(value) or not 0 < value < np.inf:
                raise ValueError(f"{name} must be a positive finite number, got {value!r}")
        if not is_real(self.edge_blur) or not 0 <= self.edge_blur < np.inf:
            raise ValueError(f"edge_blur must be a finite number >= 0, got {self.edge_blur!r}")
        if self.clear_rays is not None and not isinstance(self.clear_rays, ClearRaysConfig):
            raise TypeError(f"clear_rays must be a ClearRaysConfig or None, got {describe(self.clear_rays)}")
        if self.palette_groups not in PALETTE_GROUPS:
            raise ValueError(f"palette_groups must be one of {list(PALETTE_GROUPS)}, got {self.palette_groups!r}")


# ---------------------------------------------------------------------------------------------
# the palette ("fewer reflectances")
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class ReflectancePalette:
    """A smoothed, normalised histogram of log reflectances (:data:`LOG_CHROMA` axes).

    Parameters
    ----------
    bins : (3,) float64
        Bin widths along log luminance, log R/G and log B/G.
    origin : (3,) int64
        Index of the histogram's first bin along each axis (bin ``k`` spans
        ``[k, k + 1) * bins``).
    density : (A, B, C) float64
        Probability of each bin (sums to 1; all zeros for an empty palette).
    """

    bins: np.ndarray
    origin: np.ndarray
    density: np.ndarray

    def log_density(self, log_reflectance: np.ndarray, *, floor: float = 1e-7) -> np.ndarray:
        """``log(p + floor)`` of each log-RGB reflectance ``(N, 3)``; ``log(floor)`` outside the histogram."""
        r = np.asarray(log_reflectance, dtype=np.float64).reshape(-1, 3)
        return self.log_density_of_bins(np.floor((r @ LOG_CHROMA.T) / self.bins), floor=floor)

    def log_density_of_bins(self, bins: np.ndarray, *, floor: float = 1e-7) -> np.ndarray:
        """``log(p + floor)`` of bin indices ``(..., 3)`` (as :func:`visibility_curve_bins` gives them)."""
        # A table padded with one cell of log(floor) on every side: an index clipped into the padded
        # range reads log(floor) when it falls outside the histogram, with no test per axis.
        table = np.pad(np.log(self.density + floor), 1, constant_values=np.log(floor))
        shape = table.shape
        bins = np.asarray(bins)
        if not np.issubdtype(bins.dtype, np.integer):
            bins = bins.astype(np.int64)
        flat = np.zeros(bins.shape[:-1], dtype=np.int64)
        for axis in range(3):
            index = np.clip(bins[..., axis] - (self.origin[axis] - 1), 0, shape[axis] - 1)
            flat *= shape[axis]
            flat += index
        return table.ravel()[flat]

    def __repr__(self) -> str:
        return f"ReflectancePalette({'x'.join(map(str, self.density.shape))} bins of {self.bins.tolist()})"


def build_palette(log_reflectance: np.ndarray, weights: np.ndarray | None = None, *,
                  bins: Sequence[float] = (0.15, 0.05, 0.05), smoothing: float = 1.0) -> ReflectancePalette:
    """Histogram of log reflectances, Gaussian-smoothed and normalised.

    Parameters
    ----------
    log_reflectance : (N, 3) array_like
        Natural logarithms of RGB reflectances (finite).
    weights : (N,) array_like, optional
        Non-negative weight per sample (default 1).
    bins : (3,) float, optional
        Bin widths along log luminance, log R/G, log B/G.
    smoothing : float, optional
        Gaussian sigma in bins (0: none).

    Returns
    -------
    ReflectancePalette
        The bins span the samples' 0.1-99.9 percentiles plus a margin of 3 sigma; samples outside
        are left out.
    """
    samples = as_array(log_reflectance, "log_reflectance", shape=(None, 3), dtype=np.float64)
    w = np.ones(len(samples)) if weights is None else as_array(weights, "weights", shape=(len(samples),),
                                                                dtype=np.float64)
    if (w < 0).any():
        raise ValueError("weights must be non-negative")
    width = np.asarray(bins, dtype=np.float64)
    if width.shape != (3,) or not (width > 0).all():
        raise ValueError(f"bins must be three positive widths, got {bins!r}")
    margin = int(np.ceil(3 * smoothing)) + 1
    if len(samples) == 0 or w.sum() <= 0:
        return ReflectancePalette(bins=width, origin=np.zeros(3, np.int64), density=np.zeros((1, 1, 1)))
    index = np.floor((samples @ LOG_CHROMA.T) / width).astype(np.int64)
    low = np.floor(np.percentile(index, 0.1, axis=0)).astype(np.int64) - margin
    high = np.ceil(np.percentile(index, 99.9, axis=0)).astype(np.int64) + margin + 1
    inside = np.all((index >= low) & (index < high), axis=1)
    histogram = np.zeros(tuple(high - low))
    k = index[inside] - low
    np.add.at(histogram, (k[:, 0], k[:, 1], k[:, 2]), w[inside])
    if smoothing > 0:
        histogram = ndimage.gaussian_filter(histogram, smoothing, mode="constant")
    total = histogram.sum()
    density = histogram / total if total > 0 else histogram
    for array in (width, low, density):
        array.flags.writeable = False
    return ReflectancePalette(bins=width, origin=low, density=density)


def palette_visibility(log_image: np.ndarray, env: np.ndarray, sun: np.ndarray, palette: ReflectancePalette, *,
                       levels: int = 11) -> tuple[np.ndarray, np.ndarray]:
    """Most probable sun visibility of each pixel under a reflectance palette.

    For ``v`` on ``levels`` evenly spaced values in [0, 1], the reflectance the pixel would have
    (Eq. 2 with ``v_sun = v``) is ``a - log(S_env + v S_sun)``; the ``v`` whose reflectance is most
    common in the palette is returned, with the gain of its log density over the median over ``v``.

    Parameters
    ----------
    log_image : (N, 3) array_like
        ``a = log I``.
    env, sun : (N, 3) array_like
        ``S_env`` (> 0) and ``S_sun`` (>= 0), shading units.
    palette : ReflectancePalette
    levels : int, optional

    Returns
    -------
    visibility : (N,) float64
        In [0, 1]: the best ``v``, or the mean of the ``v`` that tie for best (their reflectances
        fall in one bin).
    gain : (N,) float64
        ``max_v log p - median_v log p`` (>= 0): how much the best ``v`` stands out.
    """
    curve = visibility_curve_bins(log_image, env, sun, bins=palette.bins, levels=levels)
    return _curve_visibility(curve, palette)


def visibility_curve_bins(log_image: np.ndarray, env: np.ndarray, sun: np.ndarray, *, bins: Sequence[float],
                          levels: int = 11) -> np.ndarray:
    """Palette bins of ``a - log(S_env + v S_sun)`` for ``levels`` visibilities ``v`` in [0, 1].

    The part of :func:`palette_visibility` that does not depend on the palette, computed once per
    view and reused in every palette round. Returns ``(N, levels, 3)`` bin indices (bin ``k`` spans
    ``[k, k + 1) * bins`` along each :data:`LOG_CHROMA` axis): int16 when every index fits (log
    values within 32767 bin widths of 0, which photographs are by far), else int32.
    """
    a = np.asarray(log_image, dtype=np.float64).reshape(-1, 3)
    e = np.asarray(env, dtype=np.float64).reshape(-1, 3)
    s = np.asarray(sun, dtype=np.float64).reshape(-1, 3)
    width = np.asarray(bins, dtype=np.float64)
    projected = a @ LOG_CHROMA.T
    out = np.empty((len(a), int(levels), 3), dtype=np.int32)
    for i, v in enumerate(np.linspace(0.0, 1.0, int(levels))):
        out[:, i] = np.floor((projected - np.log(e + v * s) @ LOG_CHROMA.T) / width)
    if len(out) and np.abs(out).max() < np.iinfo(np.int16).max:  # half the memory (the common case)
        return out.astype(np.int16)
    return out


def _curve_visibility(curve: np.ndarray, palette: ReflectancePalette, *, floor: float = 1e-7
                      ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`palette_visibility` from precomputed :func:`visibility_curve_bins`."""
    levels = curve.shape[1]
    logp = palette.log_density_of_bins(curve, floor=floor)
    top = logp.max(axis=1)
    gain = top - np.median(logp, axis=1)
    # Levels whose reflectances share the best bin tie; take their mean, not the first (which would
    # bias every pixel toward shadow by up to a bin's width).
    tied = logp >= top[:, None] - TIE_TOLERANCE
    grid = np.linspace(0.0, 1.0, levels)
    return (tied @ grid) / tied.sum(axis=1), gain


# ---------------------------------------------------------------------------------------------
# edge evidence, albedo bound, proxy prior
# ---------------------------------------------------------------------------------------------
def edge_scale(shape: tuple[int, int], reference: int) -> int:
    """Factor of the edge radii for a view of ``shape`` (H, W): ``round(max(H, W) / reference)``, at
    least 1 (:attr:`MultiViewShadowConfig.edge_reference`; ``reference`` 0 gives 1)."""
    if reference <= 0:
        return 1
    return max(1, int(round(max(shape) / reference)))


def edge_offsets(radii: Sequence[int] = (2, 4, 7, 11), directions: int = 16) -> list[tuple[int, int]]:
    """Partner offsets ``(dy, dx)``: ``directions`` evenly spaced directions at each radius, rounded
    to pixels, duplicates and ``(0, 0)`` removed, sorted. Symmetric: ``(-dy, -dx)`` is in the list
    whenever ``(dy, dx)`` is when ``directions`` is even."""
    out = set()
    for r in radii:
        for k in range(int(directions)):
            angle = 2 * np.pi * k / directions
            out.add((int(round(r * np.sin(angle))), int(round(r * np.cos(angle)))))
    out.discard((0, 0))
    return sorted(out)


def _overlap(h: int, w: int, dy: int, dx: int) -> tuple[tuple[slice, slice], tuple[slice, slice]]:
    """Slices of the pixels ``p`` whose partner ``p + (dy, dx)`` is inside the image, and of the partners."""
    p = (slice(max(0, -dy), h - max(0, dy)), slice(max(0, -dx), w - max(0, dx)))
    q = (slice(max(0, dy), h + min(0, dy)), slice(max(0, dx), w + min(0, dx)))
    return p, q


def edge_votes(log_image: np.ndarray, shadow_ratio: np.ndarray, valid: np.ndarray, *, sigma: float = 0.15,
               material_cost: float = 2.0, offsets: Sequence[tuple[int, int]] | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
    """Lit and shadow votes of each pixel from the jumps to its partners (module docstring, term 1).

    Parameters
    ----------
    log_image : (H, W, 3) array_like
        ``a = log I``.
    shadow_ratio : (H, W, 3) array_like
        ``lambda = log(1 + S_sun / S_env)``.
    valid : (H, W) bool
        Pixels that take part (as ``p`` or as partner).
    sigma, material_cost : float, optional
    offsets : sequence of (int, int), optional
        Partner offsets; :func:`edge_offsets` by default.

    Returns
    -------
    lit, shadow : (H, W) float64
        Largest margin (>= 0, at most ``material_cost``) by which "``p`` lit, partner in shadow"
        (resp. the reverse) beats the other explanations of one jump; 0 off ``valid``.
    """
    a = np.asarray(log_image, dtype=np.float32)
    half = 0.5 * np.asarray(shadow_ratio, dtype=np.float32)
    valid = np.asarray(valid, dtype=bool)
    h, w = valid.shape
    if a.shape != (h, w, 3) or half.shape != (h, w, 3):
        raise ValueError(f"log_image and shadow_ratio must have shape {(h, w, 3)}, got {a.shape} and "
                         f"{np.shape(shadow_ratio)}")
    scale = np.float32(1.0 / (2.0 * sigma * sigma))
    cap = np.float32(material_cost)
    lit = np.zeros((h, w), np.float32)
    shadow = np.zeros((h, w), np.float32)
    offsets = [(int(dy), int(dx)) for dy, dx in (edge_offsets() if offsets is None else offsets)]
    listed = set(offsets)
    for dy, dx in offsets:
        mirrored = (-dy, -dx) in listed
        if mirrored and (dy, dx) < (-dy, -dx):
            continue  # the pair (p, p + d) is scored once, from the offset's mirror image
        ps, qs = _overlap(h, w, dy, dx)
        both = valid[ps] & valid[qs]
        jump = a[ps] - a[qs]
        ratio = half[ps] + half[qs]
        # With j the jump and r the ratio: |j - r|^2 (p lit, q shadow), |j + r|^2 (p shadow, q lit)
        # and |j|^2 (same light) differ by 4 j.r and 2 j.r +- r.r: three dot products per pair.
        jj = np.einsum("ijk,ijk->ij", jump, jump)
        jr = np.einsum("ijk,ijk->ij", jump, ratio)
        rr = np.einsum("ijk,ijk->ij", ratio, ratio)
        c_lit = scale * (jj - 2 * jr + rr)
        c_shadow = c_lit + 4 * scale * jr
        c_same = scale * jj
        lit_margin = np.where(both, np.minimum(np.minimum(c_shadow, c_same), cap) - c_lit, 0)
        shadow_margin = np.where(both, np.minimum(np.minimum(c_lit, c_same), cap) - c_shadow, 0)
        np.maximum(lit[ps], lit_margin, out=lit[ps])
        np.maximum(shadow[ps], shadow_margin, out=shadow[ps])
        if mirrored:  # the partner's votes of the same pair: its "lit" is p's "shadow" and back
            np.maximum(lit[qs], shadow_margin, out=lit[qs])
            np.maximum(shadow[qs], lit_margin, out=shadow[qs])
    return lit.astype(np.float64), shadow.astype(np.float64)


def albedo_term(r0: np.ndarray, r1: np.ndarray, *, albedo_max: float = 1.0) -> np.ndarray:
    """``max_c(r_0 - log albedo_max)_+ - max_c(r_1 - log albedo_max)_+`` (module docstring, term 3).

    Positive where the shadow hypothesis needs an albedo above ``albedo_max`` (favours lit).
    ``r0``, ``r1`` are ``(..., 3)`` log reflectances; returns ``(...)``.
    """
    bound = np.log(albedo_max)
    over0 = np.maximum(np.asarray(r0) - bound, 0.0).max(axis=-1)
    over1 = np.maximum(np.asarray(r1) - bound, 0.0).max(axis=-1)
    return over0 - over1


def proxy_prior(visibility: np.ndarray, *, lit: float = 0.05, shadow: float = 0.2) -> np.ndarray:
    """``lit (2 ~v - 1)`` where ``~v >= 1/2``, ``shadow (2 ~v - 1)`` below (module docstring, term 4)."""
    v = np.clip(np.asarray(visibility, dtype=np.float64), 0.0, 1.0)
    return np.where(v >= 0.5, lit, shadow) * (2.0 * v - 1.0)


# ---------------------------------------------------------------------------------------------
# the graph cut
# ---------------------------------------------------------------------------------------------
#: Neighbour offsets of the 8-connected grid, each pair once.
_NEIGHBOURS = ((0, 1), (1, 0), (1, 1), (1, -1))


def potts_weights(guide: np.ndarray, valid: np.ndarray, *, smoothness: float = 1.0, contrast: float = 0.3
                  ) -> tuple[np.ndarray, ...]:
    """The contrast-sensitive Potts weights of :func:`grid_cut`, one ``(H, W)`` float32 array per
    neighbour offset of ``_NEIGHBOURS`` (the weight of the edge from ``p`` to ``p + offset``, 0 where
    either end is off ``valid``). They depend on the view only: computed once, reused every round."""
    valid = np.asarray(valid, dtype=bool)
    h, w = valid.shape
    g = np.asarray(guide, dtype=np.float32)
    if g.ndim == 2:
        g = g[..., None]
    scale = np.float32(1.0 / (2.0 * contrast * contrast))
    out = []
    for dy, dx in _NEIGHBOURS:
        ps, qs = _overlap(h, w, dy, dx)
        weight = np.zeros((h, w), np.float32)
        diff = g[ps] - g[qs]
        keep = np.exp(-scale * np.einsum("ijk,ijk->ij", diff, diff))
        weight[ps] = np.where(valid[ps] & valid[qs], np.float32(smoothness / np.hypot(dy, dx)) * keep, 0)
        out.append(weight)
    return tuple(out)


def grid_cut(cost_shadow: np.ndarray, cost_lit: np.ndarray, guide: np.ndarray, valid: np.ndarray, *,
             smoothness: float = 1.0, contrast: float = 0.3, weights: tuple[np.ndarray, ...] | None = None
             ) -> np.ndarray:
    """Exact binary labelling of a pixel grid with contrast-sensitive Potts smoothing.

    Minimises ``sum_p c_p(x_p) + sum_{p~q} w_pq [x_p != x_q]`` over the 8-neighbourhood, with
    ``w_pq = smoothness exp(-|g_p - g_q|^2 / (2 contrast^2)) / |p - q|`` (``g`` the guide), by one
    s-t minimum cut (Boykov-Kolmogorov, PyMaxflow). Pixels off ``valid`` are cut loose (no unary,
    no edge) and returned lit.

    Parameters
    ----------
    cost_shadow, cost_lit : (H, W) array_like
        Non-negative unary costs of each label.
    guide : (H, W, C) array_like
        The image the Potts weights follow (here the log image).
    valid : (H, W) bool
    smoothness, contrast : float, optional
    weights : tuple of (H, W) arrays, optional
        The Potts weights already computed (:func:`potts_weights` of the same guide, valid,
        smoothness and contrast); ``guide``, ``smoothness`` and ``contrast`` are then not read.

    Returns
    -------
    (H, W) bool
        True lit.
    """
    import maxflow

    valid = np.asarray(valid, dtype=bool)
    h, w = valid.shape
    if weights is None:
        weights = potts_weights(guide, valid, smoothness=smoothness, contrast=contrast)
    graph = maxflow.Graph[float]()
    nodes = graph.add_grid_nodes((h, w))
    for (dy, dx), weight in zip(_NEIGHBOURS, weights, strict=True):
        structure = np.zeros((3, 3))
        structure[1 + dy, 1 + dx] = 1.0
        graph.add_grid_edges(nodes, weights=weight, structure=structure, symmetric=True)
    shadow_cost = np.where(valid, np.maximum(np.asarray(cost_shadow, dtype=np.float64), 0.0), 0.0)
    lit_cost = np.where(valid, np.maximum(np.asarray(cost_lit, dtype=np.float64), 0.0), 0.0)
    # A node on the sink side (label lit) cuts its source edge, whose capacity is then its cost.
    graph.add_grid_tedges(nodes, lit_cost, shadow_cost)
    graph.maxflow()
    return np.asarray(graph.get_grid_segments(nodes), dtype=bool) | ~valid


# ---------------------------------------------------------------------------------------------
# results and the whole procedure
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class PixelShadowLabels:
    """The multi-view labelling of one view.

    Parameters
    ----------
    stem : str
        View name.
    labels : (H, W) uint8
        :data:`~mvintrinsic.results.SHADOW_LABELS`: 0 shadow, 255 lit, 128 on pixels without an
        estimate (invalid, sky).
    visibility : (H, W) float32
        Most probable sun visibility under the last palette (:func:`palette_visibility`), in
        [0, 1]; NaN off the valid pixels (and everywhere when ``iterations`` is 0).
    score : (H, W) float32
        The fused score of the last labelling (> 0 favours lit); 0 off the valid pixels.
    """

    stem: str
    labels: np.ndarray
    visibility: np.ndarray
    score: np.ndarray

    @property
    def shadow(self) -> np.ndarray:
        """``(H, W)`` bool: labelled shadow."""
        return self.labels == SHADOW_LABELS["shadow"]

    def __repr__(self) -> str:
        decided = self.labels != SHADOW_LABELS["undecided"]
        share = float(self.shadow.sum() / max(int(decided.sum()), 1))
        return f"PixelShadowLabels({self.stem!r}, {self.labels.shape[1]}x{self.labels.shape[0]}, shadow {share:.1%})"


@dataclass(frozen=True, eq=False)
class MultiViewShadowLabels:
    """The shadow labels of all views, and how they were reached.

    Parameters
    ----------
    views : mapping of str to PixelShadowLabels
        Per view, in stem order.
    palette : ReflectancePalette or None
        The last palette of the surfaces not facing up (of all surfaces with
        ``palette_groups="none"``); None when ``iterations`` is 0 or there is no sun.
    correspondences : Correspondences or None
        The cross-view correspondences used (None for a single view or ``view_weight`` 0).
    changed : tuple of float
        Per palette round, the share of valid pixels whose label changed.
    timings : mapping of str to float
        Seconds summed over views: ``evidence``, ``correspondences``, ``palette``, ``fusion``,
        ``graph_cut``, ``consensus``.
    """

    views: Mapping[str, PixelShadowLabels]
    palette: ReflectancePalette | None
    correspondences: Correspondences | None
    changed: tuple[float, ...]
    timings: Mapping[str, float]

    def __getitem__(self, stem: str) -> PixelShadowLabels:
        return self.views[stem]

    def __repr__(self) -> str:
        return f"MultiViewShadowLabels({len(self.views)} views, rounds={len(self.changed)})"


def _check_sun(sun_radiance: object) -> np.ndarray:
    radiance = as_array(sun_radiance, "sun_radiance", shape=(3,), dtype=np.float64)
    if (radiance < 0).any():
        raise ValueError(f"sun_radiance must be non-negative, got {radiance.tolist()}")
    return radiance


@dataclass
class _Evidence:
    """Per-view arrays of the procedure (private, mutable while it runs)."""

    valid: np.ndarray
    a: np.ndarray
    r0: np.ndarray
    r1: np.ndarray
    base: np.ndarray
    curve: np.ndarray
    group: np.ndarray


def _evidence(view: View, q: PixelQuantities, radiance: np.ndarray, config: MultiViewShadowConfig,
              offsets: list[tuple[int, int]], up: np.ndarray) -> _Evidence:
    valid = np.asarray(q.valid, dtype=bool)
    a = log_image(view, valid)
    median = float(np.exp(np.median(a[valid]))) if valid.any() else 1.0
    env = np.maximum(np.asarray(q.env, dtype=np.float64), 1e-6 * median)
    sun = radiance * np.asarray(q.cosine, dtype=np.float64)[..., None]        # S_sun, Eq. 3
    ratio = np.log1p(sun / env)                                               # lambda
    r0 = a - np.log(env)                                                      # Eq. 2, v = 0
    r1 = r0 - ratio                                                           # Eq. 2, v = 1
    a_edges = log_image(view, valid, blur=config.edge_blur) if config.edge_blur > 0 else a
    lit_vote, shadow_vote = edge_votes(a_edges, ratio, valid, sigma=config.edge_sigma,
                                       material_cost=config.edge_material_cost, offsets=offsets)
    base = (config.edge_weight * (lit_vote - shadow_vote)
            + config.albedo_weight * albedo_term(r0, r1, albedo_max=config.albedo_max)
            + proxy_prior(q.visibility, lit=config.prior_lit, shadow=config.prior_shadow))
    curve = visibility_curve_bins(a[valid], env[valid], sun[valid], bins=config.palette_bins,
                                  levels=config.visibility_levels) if config.iterations else np.zeros((0, 0, 3), np.int32)
    if config.palette_groups == "orientation":
        group = (np.asarray(q.normals, dtype=np.float64)[valid] @ up > ORIENTATION_COS).astype(np.int64)
    else:
        group = np.zeros(int(valid.sum()), dtype=np.int64)
    return _Evidence(valid=valid, a=a, r0=r0, r1=r1, base=np.where(valid, base, 0.0), curve=curve, group=group)


def label_shadows_multiview(
    views: Sequence[View],
    quantities: Mapping[str, PixelQuantities],
    sun_radiance: np.ndarray,
    *,
    config: MultiViewShadowConfig | None = None,
    correspondences: Correspondences | None = None,
    up: np.ndarray = (0.0, 0.0, 1.0),
    sun_direction: np.ndarray | None = None,
    progress: bool = False,
) -> MultiViewShadowLabels:
    """Label every pixel of every view as lit or in shadow, all views at once (module docstring).

    Parameters
    ----------
    views : sequence of View
        The views, in any order (the result does not depend on it).
    quantities : mapping of str to PixelQuantities
        Per view, Step 1's quantities carried to its pixels
        (:func:`mvintrinsic.pixels.pixel_quantities`).
    sun_radiance : (3,) array_like
        ``L_sun`` from Step 2, shading units.
    config : MultiViewShadowConfig, optional
    correspondences : Correspondences, optional
        Reuse correspondences found before; found with the config's tolerances otherwise.
    sun_direction : (3,) array_like, optional
        Unit vector toward the sun, world frame: with it (and ``config.clear_rays``) the proxy's lit
        prior is ``clear_rays.prior`` where the photographs see the sun ray free (term 4).
    progress : bool, optional
        tqdm progress bar over the rounds.

    Returns
    -------
    MultiViewShadowLabels

    Raises
    ------
    ValueError, TypeError
        Naming the argument: no views, duplicated stems, missing or mis-shaped quantities, a
        negative or non-finite ``sun_radiance``, correspondences of other views.
    """
    from tqdm.auto import tqdm

    config = config_or_default(config, MultiViewShadowConfig)
    ordered = _check_views(views, quantities)
    radiance = _check_sun(sun_radiance)
    timings = dict.fromkeys(("evidence", "clear_rays", "correspondences", "palette", "fusion", "graph_cut",
                             "consensus"), 0.0)
    stems = [v.stem for v in ordered]

    if not (radiance > 0).any():
        # No direct sun: v_sun multiplies S_sun = 0, so every labelling explains the images alike.
        out = {}
        for view in ordered:
            valid = quantities[view.stem].valid
            labels = np.where(valid, SHADOW_LABELS["lit"], SHADOW_LABELS["undecided"]).astype(np.uint8)
            out[view.stem] = _freeze(view.stem, labels, np.full(view.shape, np.nan), np.zeros(view.shape))
        return MultiViewShadowLabels(views=MappingProxyType(out), palette=None, correspondences=None, changed=(),
                                     timings=MappingProxyType(timings))

    start = time.perf_counter()
    up = as_unit_vector(up, "up")
    evidence = {}
    for v in ordered:
        k = edge_scale(v.shape, config.edge_reference)
        offsets = edge_offsets(tuple(k * r for r in config.edge_radii), config.edge_directions)
        evidence[v.stem] = _evidence(v, quantities[v.stem], radiance, config, offsets, up)
    timings["evidence"] = time.perf_counter() - start
    if config.clear_rays is not None and sun_direction is not None:  # term 4 where the photos see the sun ray free
        start = time.perf_counter()
        clear = clear_sun_rays(ordered, quantities, as_unit_vector(sun_direction, "sun_direction"),
                               config=config.clear_rays)
        for stem, e in evidence.items():
            lit = np.clip(np.asarray(quantities[stem].visibility, dtype=np.float64), 0.0, 1.0) * 2.0 - 1.0
            e.base = e.base + (config.clear_rays.prior - config.prior_lit) * np.where(clear[stem], lit, 0.0)
        timings["clear_rays"] = time.perf_counter() - start

    use_views = len(ordered) > 1 and config.view_weight > 0
    if use_views and correspondences is None:
        start = time.perf_counter()
        correspondences = find_correspondences(ordered, quantities, depth_tolerance=config.depth_tolerance,
                                               photo_tolerance=config.photo_tolerance)
        timings["correspondences"] = time.perf_counter() - start
    elif correspondences is not None:
        if not isinstance(correspondences, Correspondences):
            raise TypeError(f"correspondences must be Correspondences, got {describe(correspondences)}")
        if tuple(correspondences.stems) != tuple(stems):
            raise ValueError(f"correspondences are for views {list(correspondences.stems)}, not {stems}")
    if not use_views:
        correspondences = None

    potts: dict[str, tuple[np.ndarray, ...]] = {}

    def label(scores: dict[str, np.ndarray]) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
        start = time.perf_counter()
        if correspondences is not None:
            scores = fuse_views(scores, correspondences, weight=config.view_weight)
        timings["fusion"] += time.perf_counter() - start
        start = time.perf_counter()
        lit = {}
        for stem in stems:
            e, s = evidence[stem], scores[stem]
            if stem not in potts:
                potts[stem] = potts_weights(e.a, e.valid, smoothness=config.smoothness, contrast=config.contrast)
            lit[stem] = grid_cut(np.maximum(s, 0.0), np.maximum(-s, 0.0), e.a, e.valid, weights=potts[stem])
        timings["graph_cut"] += time.perf_counter() - start
        return lit, scores

    lit, scores = label({s: evidence[s].base for s in stems})
    visibility = {s: np.full(evidence[s].valid.shape, np.nan) for s in stems}
    palette = None
    changed: list[float] = []
    n_valid = max(sum(int(evidence[s].valid.sum()) for s in stems), 1)
    for _ in tqdm(range(config.iterations), desc="shadow labels", unit="round", disable=not progress):
        start = time.perf_counter()
        samples = np.concatenate([np.where(lit[s][evidence[s].valid][:, None], evidence[s].r1[evidence[s].valid],
                                           evidence[s].r0[evidence[s].valid]) for s in stems])
        groups = np.concatenate([evidence[s].group for s in stems])
        palettes = {g: build_palette(samples[groups == g], bins=config.palette_bins,
                                     smoothing=config.palette_smoothing) for g in np.unique(groups)}
        palette = palettes[min(palettes)]
        new_scores = {}
        for stem in stems:
            e = evidence[stem]
            v = np.zeros(len(e.group))
            gain = np.zeros(len(e.group))
            for g, pal in palettes.items():
                k = e.group == g
                v[k], gain[k] = _curve_visibility(e.curve[k], pal)
            vote = np.zeros(e.valid.shape)
            vote[e.valid] = np.where(v >= 0.5, 1.0, -1.0) * np.minimum(gain, config.palette_cap)
            visibility[stem] = np.where(e.valid, 0.0, np.nan)
            visibility[stem][e.valid] = v
            new_scores[stem] = e.base + config.palette_weight * vote
        timings["palette"] += time.perf_counter() - start
        previous = lit
        lit, scores = label(new_scores)
        moved = sum(int((lit[s] != previous[s])[evidence[s].valid].sum()) for s in stems) / n_valid
        changed.append(moved)
        logger.info("shadow labels: palette round %d, %.3f%% of the pixels changed", len(changed), 100 * moved)
        if moved == 0:
            break

    if correspondences is not None:
        start = time.perf_counter()
        for _ in range(config.consensus_passes):
            lit = consensus(lit, correspondences, {s: evidence[s].valid for s in stems})
        timings["consensus"] = time.perf_counter() - start

    out = {}
    for view in ordered:
        e = evidence[view.stem]
        codes = np.where(lit[view.stem], SHADOW_LABELS["lit"], SHADOW_LABELS["shadow"])
        labels = np.where(e.valid, codes, SHADOW_LABELS["undecided"]).astype(np.uint8)
        out[view.stem] = _freeze(view.stem, labels, visibility[view.stem], np.where(e.valid, scores[view.stem], 0.0))
    return MultiViewShadowLabels(views=MappingProxyType(out), palette=palette, correspondences=correspondences,
                                 changed=tuple(changed), timings=MappingProxyType(timings))


def _freeze(stem: str, labels: np.ndarray, visibility: np.ndarray, score: np.ndarray) -> PixelShadowLabels:
    arrays = (labels.astype(np.uint8), visibility.astype(np.float32), score.astype(np.float32))
    for array in arrays:
        array.flags.writeable = False
    return PixelShadowLabels(stem=stem, labels=arrays[0], visibility=arrays[1], score=arrays[2])
