"""Step 2: the sun radiance ``L_sun`` from light/shadow pairs of equal reflectance (paper Sec. 5).

Per view (:func:`find_sun_pairs`, independent across views):

1. K-means (K = 4) on the luminance of the valid pixels;
2. a cluster is *shadow* when it holds a larger share of pixels inside the proxy shadow
   ``~v < 1/2`` than the image as a whole (the paper: "its ratio [of points inside to points
   outside the proxy shadow] is lower than the average ratio in the image"; read literally the
   comparison is reversed, since shadow clusters are the ones rich in proxy-shadow pixels, so we
   compare the in-to-out ratios the other way round, which is the paper's intent);
3. confident shadow = shadow clusters ∩ proxy shadow; confident lit = the other clusters ∩ proxy
   light;
4. the boundary of the confident shadow is sampled every ``boundary_step`` pixels along its
   contours; at each sample a walk of up to ``walk`` pixels goes each way along the normal of the
   boundary, and picks the brightest lit and the darkest shadowed pixel whose chromaticities are
   within ``chroma_tolerance`` (pixel values averaged over a ``smoothing`` box within each region
   first: a deviation, against noise, see :class:`SunConfig`);
5. a sample is rejected when no such pixel pair exists, when the segment between the two picked
   pixels crosses a depth or normal discontinuity (Canny edges of the proxy's depth and normal maps
   in the view), or when Eq. 5 has no positive, finite solution (the paper rejects a walk that
   crosses a discontinuity anywhere; testing only the stretch between the picked pixels is a
   deviation: beyond them a discontinuity cannot make the pair straddle two surfaces);
6. each surviving pair gives ``L_sun`` by Eq. 5 with the per-pixel ``S_sky``, ``S_ind`` and
   ``cos omega_sun`` (``v = 1`` at the lit pixel, ``v = 0`` at the shadowed one).

:func:`calibrate_sun` takes the per-channel median over the pairs of all views.
"""

from __future__ import annotations

import logging
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType

import cv2
import numpy as np
from scipy import ndimage

from ._validation import is_real
from .image_model import luminance, sun_radiance_from_pair
from .pixels import PixelQuantities, masked_box_mean, nearest_fill
from .scene import View

__all__ = [
    "SunContrast",
    "direct_sun_evidence",
    "REJECTION_RULES",
    "SunCalibration",
    "SunCalibrationError",
    "SunConfig",
    "SunPairs",
    "calibrate_sun",
    "chromaticity",
    "discontinuity_edges",
    "find_sun_pairs",
    "luminance_kmeans",
    "shadow_regions",
]

logger = logging.getLogger(__name__)

#: Why a boundary sample gave no pair, in the order the rules are applied.
REJECTION_RULES = ("no_candidates", "no_similar_chromaticity", "discontinuity", "degenerate", "low_contrast")



class SunCalibrationError(RuntimeError):
    """No light/shadow pair survived: the sun radiance cannot be calibrated from the images."""


@dataclass(frozen=True)
class SunConfig:
    """Options of the sun calibration (paper Sec. 5); defaults are the paper's where it gives one.

    Parameters
    ----------
    n_clusters : int
        K of the luminance K-means (paper: 4).
    walk : int
        Pixels walked each way from a boundary sample (paper: 30).
    boundary_step : int
        Spacing, in contour pixels, of the boundary samples (the paper samples "regularly").
    chroma_tolerance : float
        Largest Euclidean distance between the ``(r, g)`` chromaticities of a lit and a shadowed
        pixel for them to count as the same reflectance. Shadowed pixels are lit by the bluer sky,
        so the tolerance must span that shift; the default was chosen on the demo scene (see
        ``docs/step2.md``).
    depth_edge : float
        Canny high threshold on the gradient of the log proxy depth (a relative depth step: 0.01
        catches the 20-30 cm recess of a door seen from 10-20 m); the low threshold is half of it.
    normal_edge : float
        Canny high threshold on the gradient of the proxy normal map (a step in the unit normal);
        the low threshold is half of it.
    normal_sigma : float
        Standard deviation (pixels) of the Gaussian that smooths the normal map before its edge
        detection (Canny's first step); the depth map is not smoothed. Interpolated normals of
        an MVS proxy are noisy: on the MVS demo this kept 88 pairs instead of 7 (78% true
        instead of 57%); smoothing the depth map as well let pairs cross the door recess
        (``docs/step2.md``).
    pick : {"extreme", "median"}
        Which of the similar-chromaticity candidates of a walk form the pair: the brightest lit
        and darkest shadowed (the paper, away from the penumbra) or the median-luminance ones
        (less biased on textured materials; ``docs/step2.md`` compares them).
    min_cosine : float
        Lit pixels with ``cos omega_sun`` below this are not used (Eq. 5 divides by it).
    min_pair_contrast : float or None
        Beyond the paper: a pair is kept only when the contrast its own estimate implies, ``1 +
        L_sun cos omega_lit / S_env,shadow`` (luminances), is at least this, i.e. when its lit
        pixel gets from the sun at least ``min_pair_contrast - 1`` times the environment light of
        its shadowed pixel. A "shadowed" pixel that is a dark material in the sun gives an
        estimate near 0, which the ``degenerate`` rule (``L_sun <= 0``, a contrast of 1) keeps.
        ``None``: that rule alone, as in the paper. Measured (``docs/step2.md``): on the two streets under trees 52-55% of the
        pairs' shadowed pixels are lit, 421 and 179 of their pairs fall below 1.5, and ``L_sun``
        goes from 0.51/0.56/0.81 and 0.40/0.37/0.43 of the truth to 0.91/0.99/1.33 and
        0.71/0.66/0.77; at most 17 pairs fall on five other scenes. 2.0 overshoots (1.43/1.54/2.08).
    smoothing : int
        Side (pixels) of the box over which pixel values are averaged, within the confident
        shadow and lit regions separately, before the brightest/darkest choice and Eq. 5; 1 uses
        raw pixels as the paper does. Picking the extreme of 30 noisy pixels biases ``L_sun`` up
        (the darkest shadow pixel is darkest partly by noise); see ``docs/step2.md``.
    direct_sun : {"auto", "always"}
        Whether the scene has direct sun at all (beyond the paper, which assumes it): ``"auto"``
        decides from the images (:func:`direct_sun_evidence`) and from the pairs (none surviving
        means no direct sun), and without direct sun the layers are ``R = I / S_env``;
        ``"always"`` is the paper (no pair: :class:`SunCalibrationError` unless missing sun is
        allowed).
    sun_contrast : float
        ``"auto"``: direct sun is absent when the upper quartile of the contrast across the
        proxy's shadow edges (:func:`direct_sun_evidence`, ``1 + E_sun / E_env`` where the proxy's
        edge is right) is below this: not even a quarter of the edge samples show the sun bringing
        as much irradiance as the environment. Measured (``docs/presets.md``): 0.92-1.89 on two
        overcast renders (working scales 1 to 0.35), 2.8-5.0 on five sunny scenes but 1.4-1.9 on
        three others at 1000x750 (hence :attr:`sun_warmth`), where the
        median, pulled to 1 by the proxy's misplaced edges, fell to 1.06-1.43 on three.
    sun_warmth : float
        ``"auto"``: direct sun is present, whatever the contrast, when the median warmth of the
        edge samples (:attr:`SunContrast.warmth`, ``log(rho_R / rho_B)``) is at least this: an
        overcast scene needs both figures below their thresholds. Measured: 0.03 on an overcast
        render, 0.12-0.28 on eight sunny scenes (three of them with a contrast of 1.4-1.9 at
        1000x750, which the contrast alone called overcast).
    contrast_samples : int
        Fewest shadow-edge samples for the contrast to decide; with fewer (no proxy shadow in
        view) the pairs decide alone.
    min_shadow_share, min_shadow_edge : float
        ``"auto"`` with direct sun: the views hold no cast shadow when the proxy's cast shadow
        covers less than ``min_shadow_share`` of the sunward pixels and its edges in view are
        shorter than ``min_shadow_edge`` view sizes (``sqrt(H W)``) per view
        (:func:`mvintrinsic.model_choice.choose_cast_shadows`); then every pixel is lit. Measured on
        a street rendered without occluders: 0.74% and 0.10; on nine sunny scenes 2.3-17.7% and
        0.32-14 (the demo the least: 2.3%, and 0.32 at 240x180, 1.29 at 480x360).
    """

    n_clusters: int = 4
    walk: int = 30
    boundary_step: int = 4
    chroma_tolerance: float = 0.04
    depth_edge: float = 0.01
    normal_edge: float = 0.3
    min_cosine: float = 0.1
    min_pair_contrast: float | None = 1.5
    smoothing: int = 5
    normal_sigma: float = 3.0
    pick: str = "extreme"
    direct_sun: str = "auto"
    sun_contrast: float = 2.0
    sun_warmth: float = 0.07
    contrast_samples: int = 500
    min_shadow_share: float = 0.012
    min_shadow_edge: float = 0.35

    def __post_init__(self) -> None:
        for name, least in (("n_clusters", 2), ("walk", 1), ("boundary_step", 1), ("smoothing", 1)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < least:
                raise ValueError(f"{name} must be an integer >= {least}, got {value!r}")
        for name in ("chroma_tolerance", "depth_edge", "normal_edge"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)!r}")
        if self.direct_sun not in ("auto", "always"):
            raise ValueError(f"direct_sun must be 'auto' or 'always', got {self.direct_sun!r}")
        if not self.sun_contrast >= 1.0:
            raise ValueError(f"sun_contrast must be >= 1, got {self.sun_contrast!r}")
        for name in ("min_shadow_share", "min_shadow_edge"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)!r}")
        if not self.sun_warmth > 0:
            raise ValueError(f"sun_warmth must be positive, got {self.sun_warmth!r}")
        if isinstance(self.contrast_samples, bool) or not isinstance(self.contrast_samples, int) or \
                self.contrast_samples < 1:
            raise ValueError(f"contrast_samples must be a positive integer, got {self.contrast_samples!r}")
        if self.pick not in ("extreme", "median"):
            raise ValueError(f"pick must be 'extreme' or 'median', got {self.pick!r}")
        if not self.normal_sigma >= 0:
            raise ValueError(f"normal_sigma must be >= 0 pixels, got {self.normal_sigma!r}")
        if not 0 <= self.min_cosine < 1:
            raise ValueError(f"min_cosine must lie in [0, 1), got {self.min_cosine!r}")
        if self.min_pair_contrast is not None and not (is_real(self.min_pair_contrast) and self.min_pair_contrast >= 1):
            raise ValueError(f"min_pair_contrast must be None or a number >= 1, got {self.min_pair_contrast!r}")


@dataclass(frozen=True, eq=False)
class SunPairs:
    """Light/shadow pairs of one view and the ``L_sun`` each gives (Eq. 5).

    Parameters
    ----------
    stem : str
        View name.
    lit, shadow : (P, 2) int64
        ``(row, col)`` of the lit and of the shadowed pixel of each pair.
    estimates : (P, 3) float64
        ``L_sun`` from each pair by Eq. 5, shading units.
    n_samples : int
        Boundary samples tried.
    rejected : mapping of str to int
        Samples rejected by each rule of :data:`REJECTION_RULES`.
    """

    stem: str
    lit: np.ndarray
    shadow: np.ndarray
    estimates: np.ndarray
    n_samples: int
    rejected: Mapping[str, int]

    def __len__(self) -> int:
        return len(self.estimates)

    def __repr__(self) -> str:
        return f"SunPairs({self.stem!r}, {len(self)} pairs of {self.n_samples} samples, rejected={dict(self.rejected)})"


@dataclass(frozen=True, eq=False)
class SunCalibration:
    """The calibrated sun radiance and the evidence behind it.

    Parameters
    ----------
    sun_radiance : (3,) float64
        ``L_sun``: per-channel median of the pair estimates (shading units). Zeros when
        ``fallback``.
    spread : (3,) float64
        Per-channel median absolute deviation of the pair estimates, scaled by 1.4826 (a robust
        standard deviation); NaN with fewer than two pairs.
    quartiles : (2, 3) float64
        25th and 75th percentiles of the pair estimates per channel.
    pairs : tuple of SunPairs
        The pairs of every view.
    rejected : mapping of str to int
        Samples rejected by each rule, summed over views.
    fallback : bool
        True when no pair survived and ``allow_missing`` took the fallback (``L_sun = 0``).
    """

    sun_radiance: np.ndarray
    spread: np.ndarray
    quartiles: np.ndarray
    pairs: tuple[SunPairs, ...]
    rejected: Mapping[str, int]
    fallback: bool = False

    @property
    def n_pairs(self) -> int:
        """Pairs over all views."""
        return sum(len(p) for p in self.pairs)

    @property
    def estimates(self) -> np.ndarray:
        """All pair estimates, (P, 3)."""
        return np.concatenate([p.estimates for p in self.pairs]) if self.pairs else np.zeros((0, 3))

    def __repr__(self) -> str:
        return (f"SunCalibration(L_sun={np.round(self.sun_radiance, 4).tolist()}, pairs={self.n_pairs}, "
                f"fallback={self.fallback})")


def chromaticity(image: np.ndarray) -> np.ndarray:
    """``(r, g) = (R, G) / (R + G + B)`` of linear RGB ``(..., 3)`` -> ``(..., 2)``; 1/3 on black."""
    image = np.asarray(image, dtype=np.float64)
    total = image.sum(axis=-1, keepdims=True)
    return np.divide(image[..., :2], total, out=np.full(image.shape[:-1] + (2,), 1.0 / 3.0), where=total > 0)


def luminance_kmeans(values: np.ndarray, k: int, *, iterations: int = 100) -> tuple[np.ndarray, np.ndarray]:
    """One-dimensional K-means (Lloyd) with centres started at the ``(2i + 1) / 2k`` quantiles.

    Deterministic, so the calibration needs no seed.

    Parameters
    ----------
    values : (N,) array_like
    k : int

    Returns
    -------
    labels : (N,) int64
        Cluster of each value, clusters sorted by increasing centre.
    centres : (k,) float64
    """
    values = np.asarray(values, dtype=np.float64).ravel()
    if values.size == 0:
        raise ValueError("luminance_kmeans needs at least one value")
    centres = np.quantile(values, (2 * np.arange(k) + 1) / (2 * k))
    for _ in range(iterations):
        bounds = (centres[1:] + centres[:-1]) / 2
        labels = np.searchsorted(bounds, values)
        sums = np.bincount(labels, weights=values, minlength=k)
        counts = np.bincount(labels, minlength=k)
        new = np.where(counts > 0, sums / np.maximum(counts, 1), centres)
        if np.allclose(new, centres, rtol=0, atol=1e-12 * max(1.0, np.abs(values).max())):
            break
        centres = np.sort(new)
    bounds = (centres[1:] + centres[:-1]) / 2
    return np.searchsorted(bounds, values), centres


def shadow_regions(image: np.ndarray, quantities: PixelQuantities, *, config: SunConfig | None = None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Confident shadow and lit regions of a view (paper Sec. 5, Fig. 4(b-d)).

    Parameters
    ----------
    image : (H, W, 3) array_like
        Linear RGB.
    quantities : PixelQuantities
        The view's Step-1 quantities (``~v`` and the valid pixels).
    config : SunConfig, optional

    Returns
    -------
    shadow, lit : (H, W) bool
        Confident shadow (shadow cluster and ``~v < 1/2``) and confident light (lit cluster and
        ``~v >= 1/2``), over the valid, proxy-covered pixels.
    cluster_shadow : (H, W) bool
        The luminance clusters classified as shadow (Fig. 4(c)).
    """
    config = config or SunConfig()
    usable = quantities.valid & ~quantities.filled
    cluster_shadow = np.zeros(quantities.shape, dtype=bool)
    if usable.sum() < config.n_clusters:
        return cluster_shadow, cluster_shadow.copy(), cluster_shadow.copy()
    labels, _ = luminance_kmeans(luminance(np.asarray(image)[usable]), config.n_clusters)
    proxy_shadow = quantities.visibility < 0.5
    in_shadow = proxy_shadow[usable]
    share = in_shadow.mean()
    shadow_clusters = [c for c in range(config.n_clusters)
                       if (labels == c).any() and in_shadow[labels == c].mean() > share]
    cluster_shadow[usable] = np.isin(labels, shadow_clusters)
    return cluster_shadow & proxy_shadow & usable, ~cluster_shadow & ~proxy_shadow & usable, cluster_shadow


def _canny(gradients: list[tuple[np.ndarray, np.ndarray]], high: float) -> np.ndarray:
    """Canny hysteresis (low = high / 2) on precomputed gradients, threshold in gradient units.

    With several channels each pixel takes the gradient of the channel where it is largest (as
    OpenCV's Canny does for colour images).
    """
    dx = np.stack([g[0] for g in gradients])
    dy = np.stack([g[1] for g in gradients])
    best = np.argmax(dx ** 2 + dy ** 2, axis=0)[None]
    dx = np.take_along_axis(dx, best, axis=0)[0]
    dy = np.take_along_axis(dy, best, axis=0)[0]
    scale = 1000.0 / high  # the high threshold maps to 1000 int16 units
    dx16 = np.clip(dx * scale, -32767, 32767).astype(np.int16)
    dy16 = np.clip(dy * scale, -32767, 32767).astype(np.int16)
    return cv2.Canny(dx16, dy16, 500.0, 1000.0, L2gradient=True) > 0


def discontinuity_edges(quantities: PixelQuantities, *, config: SunConfig | None = None) -> np.ndarray:
    """Depth and normal discontinuities of the proxy in a view (Canny), ``(H, W)`` bool.

    Depth edges are found on ``log(depth)`` (a relative step of ``config.depth_edge``), normal
    edges on the normal map (a step of ``config.normal_edge`` in the unit normal, summed over the
    three components, after a Gaussian of ``config.normal_sigma`` pixels). Pixels where the proxy
    coverage begins or ends are edges too.
    """
    config = config or SunConfig()
    covered = np.isfinite(quantities.depth)
    log_depth = np.log(np.maximum(quantities.depth.astype(np.float64), 1e-6))  # inf off the proxy
    if covered.any():
        log_depth = nearest_fill(log_depth, covered)
    else:
        log_depth = np.zeros(covered.shape)

    def sobel(channel: np.ndarray, sigma: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        # Optional Gaussian smoothing (Canny's first step, which OpenCV leaves to the caller), then
        # a 3x3 Sobel, whose response to a unit step is 4: divide so the gradient is the step per
        # pixel.
        if sigma > 0:
            channel = ndimage.gaussian_filter(channel, sigma)
        return (cv2.Sobel(channel, cv2.CV_64F, 1, 0, ksize=3) / 4.0,
                cv2.Sobel(channel, cv2.CV_64F, 0, 1, ksize=3) / 4.0)

    edges = _canny([sobel(log_depth)], config.depth_edge)
    normals = quantities.normals.astype(np.float64)
    edges |= _canny([sobel(normals[..., i], config.normal_sigma) for i in range(3)], config.normal_edge)
    edges |= covered ^ ndimage.binary_erosion(covered, border_value=1)
    return edges


def _boundary_samples(shadow: np.ndarray, lit: np.ndarray, step: int) -> tuple[np.ndarray, np.ndarray]:
    """Samples every ``step`` contour pixels of the shadow region where it meets lit pixels.

    Returns ``(row, col)`` ints (S, 2) and unit directions (S, 2) in ``(row, col)`` pointing from
    shadow to light (the negated gradient of the smoothed shadow mask).
    """
    contours, _ = cv2.findContours(shadow.astype(np.uint8), cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    if not contours:
        return np.zeros((0, 2), dtype=np.int64), np.zeros((0, 2))
    points = np.concatenate([c[::step, 0, ::-1] for c in contours]).astype(np.int64)  # (x, y) -> (row, col)
    near_lit = ndimage.binary_dilation(lit, iterations=2)
    points = points[near_lit[points[:, 0], points[:, 1]]]
    smooth = ndimage.gaussian_filter(shadow.astype(np.float64) - lit.astype(np.float64), 2.0)
    gr, gc = np.gradient(smooth)
    direction = -np.stack([gr[points[:, 0], points[:, 1]], gc[points[:, 0], points[:, 1]]], axis=1)
    length = np.linalg.norm(direction, axis=1)
    keep = length > 1e-6
    return points[keep], direction[keep] / length[keep, None]


def _region_mean(image: np.ndarray, regions: Sequence[np.ndarray], size: int) -> np.ndarray:
    """Box mean of ``image`` over ``size x size`` windows, each region averaged on its own pixels."""
    out = np.asarray(image, dtype=np.float64).copy()
    for region in regions:
        out[region] = masked_box_mean(image, region, size)[region]
    return out


#: Scores within this relative distance of a row's best count as tied (uniform textures give 5x5
#: means equal up to rounding).
TIE_TOLERANCE = 1e-9


def _pick(scores: np.ndarray, how: str) -> np.ndarray:
    """Per row, the index of the smallest finite score (``"extreme"``) or of the median one.

    Columns are walk steps ordered by distance from the boundary; among scores tied with the best
    (within :data:`TIE_TOLERANCE`) the nearest step wins, so the choice does not depend on
    rounding. (The farthest tied step was measured too: on the clean demo it lowered the share of
    true pairs from 55% to 43%, the walk reaching other materials more often.)
    """
    if how == "extreme":
        best = np.min(scores, axis=1, keepdims=True)
        tied = scores <= best + TIE_TOLERANCE * np.abs(np.where(np.isfinite(best), best, 0.0))
        return np.argmax(tied, axis=1)
    order = np.argsort(scores, axis=1, kind="stable")
    count = np.isfinite(scores).sum(axis=1)
    return order[np.arange(len(scores)), np.maximum(count - 1, 0) // 2]


def find_sun_pairs(view: View, quantities: PixelQuantities, *, config: SunConfig | None = None) -> SunPairs:
    """Light/shadow pairs of equal reflectance across the proxy shadow boundary of one view.

    Parameters
    ----------
    view : View
        Its image (linear RGB) is read; ``view.stem`` must match ``quantities.stem``.
    quantities : PixelQuantities
        The view's Step-1 quantities (:func:`mvintrinsic.pixels.pixel_quantities`).
    config : SunConfig, optional

    Returns
    -------
    SunPairs
        Possibly empty; ``rejected`` counts the samples each rule removed.
    """
    config = config or SunConfig()
    if view.stem != quantities.stem or view.camera.shape != quantities.shape:
        raise ValueError(f"quantities ({quantities.stem!r}, {quantities.shape}) do not belong to view "
                         f"{view.stem!r} ({view.camera.shape})")
    image = np.asarray(view.image, dtype=np.float64)
    h, w = quantities.shape
    shadow, lit, _ = shadow_regions(image, quantities, config=config)
    image = _region_mean(image, (shadow, lit), config.smoothing)
    rejected = dict.fromkeys(REJECTION_RULES, 0)
    empty = SunPairs(view.stem, np.zeros((0, 2), np.int64), np.zeros((0, 2), np.int64), np.zeros((0, 3)), 0,
                     MappingProxyType(rejected))
    if not shadow.any() or not lit.any():
        return empty
    points, direction = _boundary_samples(shadow, lit, config.boundary_step)
    n_samples = len(points)
    if n_samples == 0:
        return empty

    lit_ok = lit & (quantities.cosine >= config.min_cosine)
    # One line of pixels per sample, offsets -walk..walk along the boundary normal (S, 2 walk + 1):
    # the positive half is the walk toward the light, the negative half (read outward) the walk
    # into the shadow, and the stretch between the two picked pixels is tested for discontinuities.
    offsets = np.arange(-config.walk, config.walk + 1)
    line = np.rint(points[:, None, :] + offsets[None, :, None] * direction[:, None, :]).astype(np.int64)
    line_in = (line[..., 0] >= 0) & (line[..., 0] < h) & (line[..., 1] >= 0) & (line[..., 1] < w)
    line = np.where(line_in[..., None], line, 0)
    lit_rc, lit_in = line[:, config.walk + 1:], line_in[:, config.walk + 1:]
    sh_rc, sh_in = line[:, config.walk - 1::-1], line_in[:, config.walk - 1::-1]
    lit_cand = lit_in & lit_ok[lit_rc[..., 0], lit_rc[..., 1]]
    sh_cand = sh_in & shadow[sh_rc[..., 0], sh_rc[..., 1]]

    lum = luminance(image)
    lit_lum = np.where(lit_cand, lum[lit_rc[..., 0], lit_rc[..., 1]], -np.inf)
    sh_lum = np.where(sh_cand, lum[sh_rc[..., 0], sh_rc[..., 1]], np.inf)
    chroma = chromaticity(image)
    lit_chroma = chroma[lit_rc[..., 0], lit_rc[..., 1]]
    sh_chroma = chroma[sh_rc[..., 0], sh_rc[..., 1]]
    similar = np.linalg.norm(lit_chroma[:, :, None, :] - sh_chroma[:, None, :, :], axis=-1) <= config.chroma_tolerance
    similar &= lit_cand[:, :, None] & sh_cand[:, None, :]

    has_candidates = lit_cand.any(axis=1) & sh_cand.any(axis=1)
    rejected["no_candidates"] = int((~has_candidates).sum())
    has_pair = similar.any(axis=(1, 2))
    rejected["no_similar_chromaticity"] = int((has_candidates & ~has_pair).sum())
    keep = np.flatnonzero(has_pair)
    # Brightest lit pixel with a similar partner, then its darkest similar shadowed partner (the
    # paper), or the median ones (config.pick == "median").
    lit_score = np.where(similar[keep].any(axis=2), -lit_lum[keep], np.inf)
    i_lit = _pick(lit_score, config.pick)
    partners = similar[keep, i_lit]
    i_sh = _pick(np.where(partners, sh_lum[keep], np.inf), config.pick)

    # Reject when the segment from the shadowed to the lit pixel crosses a proxy discontinuity.
    edges = discontinuity_edges(quantities, config=config)
    seg = line[keep]
    within = (offsets[None, :] >= -(i_sh[:, None] + 1)) & (offsets[None, :] <= i_lit[:, None] + 1) & line_in[keep]
    crosses = (edges[seg[..., 0], seg[..., 1]] & within).any(axis=1)
    rejected["discontinuity"] = int(crosses.sum())
    keep, i_lit, i_sh = keep[~crosses], i_lit[~crosses], i_sh[~crosses]

    lit_px = lit_rc[keep, i_lit]
    sh_px = sh_rc[keep, i_sh]
    env = quantities.env.astype(np.float64)
    env_shadow, cos_lit = env[sh_px[:, 0], sh_px[:, 1]], quantities.cosine[lit_px[:, 0], lit_px[:, 1]]
    estimates = sun_radiance_from_pair(  # Eq. 5 with v = 1 at the lit pixel, 0 at the shadowed one
        image[lit_px[:, 0], lit_px[:, 1]], image[sh_px[:, 0], sh_px[:, 1]],
        env[lit_px[:, 0], lit_px[:, 1]], env_shadow,
        np.ones(len(keep)), np.zeros(len(keep)),
        cos_lit, quantities.cosine[sh_px[:, 0], sh_px[:, 1]],
    )
    good = np.isfinite(estimates).all(axis=1) & (estimates > 0).all(axis=1)
    rejected["degenerate"] = int((~good).sum())
    if config.min_pair_contrast is not None:  # beyond the paper: the pair must show the sun
        contrast = 1.0 + luminance(estimates) * cos_lit / np.maximum(luminance(env_shadow), 1e-12)
        low = good & (contrast < config.min_pair_contrast)
        rejected["low_contrast"] = int(low.sum())
        good &= ~low
    return SunPairs(
        stem=view.stem, lit=lit_px[good], shadow=sh_px[good], estimates=estimates[good], n_samples=n_samples,
        rejected=MappingProxyType(rejected),
    )


def calibrate_sun(pairs: Sequence[SunPairs], *, allow_missing: bool = False) -> SunCalibration:
    """``L_sun`` as the per-channel median of the pair estimates of all views (paper Sec. 5).

    Parameters
    ----------
    pairs : sequence of SunPairs
        The pairs of every view (:func:`find_sun_pairs`).
    allow_missing : bool, optional
        When no pair survived: False (default) raises :class:`SunCalibrationError`; True returns
        ``L_sun = 0`` with ``fallback=True`` and a warning, i.e. all light is treated as
        environment light (right for an overcast scene; for a sunny scene without usable shadow
        boundaries it makes the reflectance too bright in sunlit areas).

    Returns
    -------
    SunCalibration

    Raises
    ------
    SunCalibrationError
        No pair survived and ``allow_missing`` is False.
    """
    pairs = tuple(pairs)
    for p in pairs:
        if not isinstance(p, SunPairs):
            raise TypeError(f"pairs must hold SunPairs, got {type(p).__name__}")
    rejected = {rule: sum(p.rejected.get(rule, 0) for p in pairs) for rule in REJECTION_RULES}
    estimates = np.concatenate([p.estimates for p in pairs]) if pairs else np.zeros((0, 3))
    if len(estimates) == 0:
        samples = sum(p.n_samples for p in pairs)
        message = (f"no light/shadow pair survived in {len(pairs)} view(s) ({samples} boundary samples; rejected: "
                   f"{rejected}): the images show no usable cast-shadow boundary (overcast, no shadows, or a proxy "
                   f"whose shadows do not match the images)")
        if not allow_missing:
            raise SunCalibrationError(message + "; pass allow_missing_sun=True to treat all light as environment light")
        warnings.warn(message + "; falling back to L_sun = 0", RuntimeWarning, stacklevel=2)
        nan = np.full(3, np.nan)
        return SunCalibration(np.zeros(3), nan, np.full((2, 3), np.nan), pairs, MappingProxyType(rejected),
                              fallback=True)
    median = np.median(estimates, axis=0)
    spread = 1.4826 * np.median(np.abs(estimates - median), axis=0) if len(estimates) > 1 else np.full(3, np.nan)
    logger.info("L_sun = %s from %d pairs", np.round(median, 4).tolist(), len(estimates))
    return SunCalibration(median, spread, np.percentile(estimates, [25, 75], axis=0), pairs,
                          MappingProxyType(rejected))


# ---------------------------------------------------------------------------------------------
# is there direct sun at all? (beyond the paper)
# ---------------------------------------------------------------------------------------------
#: Pixels on each side of a proxy shadow edge that :func:`direct_sun_evidence` reads: the shadow
#: sample lies 2 to 8 px from the proxy's lit region (its edge is a few pixels off on an MVS proxy),
#: the lit sample 2 px beyond the nearest lit pixel.
EDGE_OFFSETS = (2, 8)


@dataclass(frozen=True)
class SunContrast:
    """The median light/shadow contrast across the proxy's cast-shadow edges (:func:`direct_sun_evidence`).

    Parameters
    ----------
    contrast : float
        Upper quartile over the samples of ``(I_lit / I_shadow) / (E_lit / E_shadow)``,
        ``E = S_sky + S_ind`` (Step 1): about 1 without direct sun, ``1 + E_sun / E_env`` of the lit
        pixel with it where the proxy's edge is the true one. The upper quartile, not the median:
        where an MVS proxy misplaces a shadow edge both samples lie on one side and give about 1,
        which pulled the median of sunny scenes down to 1.06-1.43. NaN without samples.
    quartiles : (3,) float64
        The 25th, 50th and 75th percentiles.
    samples : int
        Shadow-edge samples read, over all views.
    warmth : float
        Median over the samples of ``log(rho_R / rho_B)``, ``rho`` per channel: positive across
        true sun edges, because the sun is warmer than the sky light that ``E`` holds
        (``rho_c = 1 + L_sun,c cos / E_c``); about 0 without direct sun, where only reflectance
        changes colour the ratio, either way. A white balance (per-channel gains on the photo)
        cancels in each ratio. It survives an MVS proxy's misplaced edges better than
        ``contrast``: measured 0.03 on an overcast render, 0.12-0.28 on eight sunny scenes,
        among them three whose ``contrast`` was 1.4-1.9 at 1000x750 (``docs/presets.md``). NaN
        without samples.
    """

    contrast: float
    quartiles: np.ndarray
    samples: int
    warmth: float


def direct_sun_evidence(views: Sequence[View], quantities: Mapping[str, PixelQuantities]) -> SunContrast:
    """How much brighter the images are on the lit side of the proxy's shadow edges than Step 1 explains.

    Beyond the paper, which assumes direct sun. Per view, every valid pixel the proxy puts in the
    cast shadow (``~v <= 0.1``) between 2 and 8 px from its lit region (``~v >= 0.9``,
    ``cos omega_sun >= 0.2``) is paired with the lit pixel 2 px beyond the nearest one
    (:data:`EDGE_OFFSETS`). Under Eq. 1, with ``E = S_sky + S_ind`` from Step 1 and the same
    reflectance on both sides,

    .. math::

        \rho = \frac{I_{lit} / I_{shadow}}{E_{lit} / E_{shadow}} = 1 + \frac{L_{sun} \\cos\\omega_{sun}}{E_{lit}},

    so without direct sun ``rho`` is 1 whatever the reflectances (their changes across the edge
    spread it both ways), and with it the samples where the proxy's edge is right are well above 1. No pair is selected by brightness (the sun pairs of Sec. 5 are, which biases them up:
    on an overcast render their estimates implied ``rho`` about 3); reflectance changes across the
    edge only widen the spread.

    Parameters
    ----------
    views : sequence of View
    quantities : mapping of str to PixelQuantities
        Per view, Step 1's quantities at the pixels.

    Returns
    -------
    SunContrast
    """
    logs, warm = [], []
    near, far = EDGE_OFFSETS
    for view in views:
        q = quantities[view.stem]
        image = luminance(np.asarray(view.image, dtype=np.float64))
        env = luminance(np.asarray(q.sky, dtype=np.float64) + q.indirect)
        ok = q.valid & (image > 0) & (env > 0)
        lit = ok & (q.visibility >= 0.9) & (q.cosine >= 0.2)
        shadow = ok & (q.visibility <= 0.1)
        if not lit.any() or not shadow.any():
            continue
        distance, (rows, cols) = ndimage.distance_transform_edt(~lit, return_indices=True)
        ys, xs = np.nonzero(shadow & (distance >= near) & (distance <= far))
        ly, lx = rows[ys, xs], cols[ys, xs]
        dy, dx = ly - ys, lx - xs
        norm = np.maximum(np.hypot(dy, dx), 1e-9)
        ly = np.clip(np.round(ly + near * dy / norm).astype(int), 0, image.shape[0] - 1)
        lx = np.clip(np.round(lx + near * dx / norm).astype(int), 0, image.shape[1] - 1)
        good = lit[ly, lx]
        ys, xs, ly, lx = ys[good], xs[good], ly[good], lx[good]
        logs.append(np.log(image[ly, lx] / image[ys, xs]) - np.log(env[ly, lx] / env[ys, xs]))
        # the warmth: log rho in red and blue at the samples only (not whole-image copies)
        red_blue = [0, 2]
        rb = [np.asarray(view.image[y, x][:, red_blue], dtype=np.float64) for y, x in ((ly, lx), (ys, xs))]
        rb += [np.asarray(q.sky[y, x][:, red_blue], dtype=np.float64) + q.indirect[y, x][:, red_blue]
               for y, x in ((ly, lx), (ys, xs))]
        lit_i, shadow_i, lit_e, shadow_e = rb
        positive = np.logical_and.reduce([(a > 0).all(axis=1) for a in rb])
        log_rho = (np.log(lit_i[positive] / shadow_i[positive])
                   - np.log(lit_e[positive] / shadow_e[positive]))
        warm.append(log_rho[:, 0] - log_rho[:, 1])
    logs = np.concatenate(logs) if logs else np.zeros(0)
    if len(logs) == 0:
        return SunContrast(float("nan"), np.full(3, np.nan), 0, float("nan"))
    quartiles = np.exp(np.percentile(logs, [25, 50, 75]))
    warm = np.concatenate(warm)
    warmth = float(np.median(warm)) if len(warm) else float("nan")  # every sample non-positive in R or B
    return SunContrast(float(quartiles[2]), quartiles, len(logs), warmth)
