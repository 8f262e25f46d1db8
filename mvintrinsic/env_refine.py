"""Step 4 (paper Sec. 7): refining the layers after Step 3 (the reflectance across views, or S_env).

After Step 3 the reflectance ``R = I / (v_sun S_sun + S_env)`` (Eq. 2) can still be wrong near
the shadow boundaries: ``S_env = S_sky + S_ind`` and ``L_sun`` come from the incomplete proxy (paper
Fig. 7a), and the matted ``v_sun`` of the penumbra has high-frequency errors (Sec. 7, last
paragraph). The paper's Step 4 corrects both; its details are in a supplemental that is not
available, so the details below are ours. :func:`refine` runs one of two methods
(:class:`EnvRefineConfig` ``method``):

``"multiview"`` (default; beyond the paper)
    A surface point has one reflectance whichever photo sees it (:mod:`mvintrinsic.correspondence`).
    Each view's log reflectance is averaged with that of the pixels of the other views that see
    the same proxy point with a consistent colour, each other view weighted ``fusion_weight``
    against the pixel's own (:func:`fuse_reflectance`, :func:`~mvintrinsic.correspondence.fuse_views`),
    and the shading takes the rest, ``S_tot = I / R`` (Eq. 1 keeps holding): every shading term of
    the pixel is multiplied by the same factor. A view's own errors -- a label or matte that went
    wrong in this photo only, its noise -- are outvoted by the others; errors that every view shares
    (``S_env``'s level, the proxy's cosine) are not touched. The labels and ``v_sun`` are kept.
``"paper"``
    Sec. 7's refinement of ``S_env``, one view at a time (:func:`refine_environment`):

    1. **Pairs** (:func:`boundary_pairs`). Umbra shadow pixels (shadow label, ``v_sun <= umbra``)
       within ``band`` pixels of the lit umbra (lit label, ``v_sun >= 1 - umbra``) are paired with
       their nearest lit umbra pixel, and lit pixels within ``band`` of the shadow umbra with their
       nearest shadow pixel (``scipy.ndimage.distance_transform_edt``). A pair is kept when both
       pixels lie on one surface (their ``S_env`` luminances and their ``S_sun`` luminances differ
       by at most ``surface_tolerance`` relative: a normal or sky-exposure jump changes them), their
       reflectances have one chromaticity (``chroma_tolerance``, rg chromaticity of ``I / S`` on each
       side) and the lit pixel is brighter than the shadowed one by at least ``min_contrast``
       relative in every channel (the offset below is ill-conditioned otherwise). Pixel values are
       averaged over a ``smoothing`` box within their own side first, against noise.
    2. **Offsets** (Fig. 8). With the same offset ``x`` added to ``S_env`` on both sides, equal
       reflectance ``I_s / (S_env,s + x) = I_l / (S_sun,l + S_env,l + x)`` gives, per channel,

       .. math::

          x = \\frac{I_s (S_{sun,l} + S_{env,l}) - I_l S_{env,s}}{I_l - I_s},

       clipped so that ``S_env + x`` stays within ``[1 / max_change, max_change]`` times ``S_env``
       on both pixels.
    3. **Propagation** ("smoothly propagate the offsets to all pixels while preserving the
       variations of S_env", :func:`propagate_offsets`). ``S_env^n = S_env + x`` with ``x`` the
       minimiser of

       .. math::

          \\sum_{k} (x_{p_k} - x_k)^2 + \\lambda \\sum_{p \\sim q} w_{pq} (x_p - x_q)^2 + \\mu \\sum_p x_p^2

       over a grid ``coarse`` times coarser than the image, with 4-neighbour weights
       ``w_pq = exp(-(log S_env,p - log S_env,q)^2 / edge_scale^2)`` (the offset may jump where
       ``S_env`` itself jumps, at a change of orientation) and a weak pull ``mu`` toward no change
       where no pair constrains; bilinear upsampling to the image. ``S_sky`` and ``S_ind`` are scaled
       alike by ``S_env^n / S_env``.

    The paper's penumbra ``v_sun`` correction is not part of this method (its details are not
    published); ``"multiview"`` is our version of it. A per-view estimator of the partial sun
    (``v_sun`` fitted against the local reflectance of the shadowed neighbours) was measured and
    not kept: within one view it cannot tell partial sun from a too low ``S_env``, and it raised
    the reflectance LMSE on two of four scenes (``docs/step4.md``).

Why ``"multiview"`` is the default (``docs/step4.md``, ``benchmarks/bench_step4.py``): on the
six scenes of issue 16 (MVS-like proxies, 320x240 and 480x360) the fusion lowered both the
reflectance and the shading LMSE on every scene (reflectance by 10-15%) and the cross-view spread
of the reflectance from 5-8% to 2-4%, while the paper's offsets raised the reflectance LMSE on
every scene tried. The offsets' pairs are impure: measured against the ground truth, only 27-47% of
the kept pairs have reflectances within 10% of each other and 16-41% of their shadow-side pixels
are lit (dark materials labelled shadow, e.g. window glass). Neither method fixes ``S_env``'s level
error in the umbra (Step 1), which pairs cannot see: a common factor on ``S_env`` and ``L_sun``
leaves every pair's equation unchanged.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from scipy import ndimage, sparse
from scipy.sparse.linalg import spsolve

from ._validation import config_or_default, describe, is_real
from .correspondence import Correspondences, find_correspondences, fuse_views
from .image_model import luminance
from .pixels import SHADING_FLOOR, PixelQuantities, floored_shading, masked_box_mean
from .results import SHADOW_LABELS, IntrinsicLayers
from .scene import View

__all__ = ["METHODS", "EnvRefineConfig", "EnvRefinement", "OffsetPairs", "Step4Result", "boundary_pairs",
           "fuse_reflectance", "propagate_offsets", "refine", "refine_environment", "relayer",
           "with_reflectance"]

METHODS = ("multiview", "paper")


@dataclass(frozen=True)
class EnvRefineConfig:
    """Options of Step 4 (paper Sec. 7; its details are a supplemental we do not have: ours).

    Parameters
    ----------
    method : {"multiview", "paper"}
        ``"multiview"`` (default): the multi-view fusion of the reflectance; ``"paper"``: Sec. 7's
        ``S_env`` offsets (module docstring).
    fusion_weight : float
        ``"multiview"``: weight of each other view's log reflectance relative to the pixel's own
        (:func:`~mvintrinsic.correspondence.fuse_views`); >= 0 (0: no change). 0.25, measured
        against 0.5, 1 and 2 (``docs/step4.md``): the reflectance LMSE is within 1% of the best of
        them and the shading LMSE falls on every scene (at 0.5 and above it rose on street_s0 and
        street_s2).
    band : int
        ``"paper"``: a pixel pairs with the nearest pixel of the other side within this distance
        (pixels); >= 1. 6 spans the matted penumbra of Step 3 at 480x360 to 1000x750.
    umbra : float
        ``"paper"``: ``v_sun <= umbra`` is full shadow, ``>= 1 - umbra`` full light; in [0, 0.5).
    surface_tolerance : float
        ``"paper"``: largest relative difference of the two pixels' ``S_env`` luminances and of their
        ``S_sun`` luminances (one surface); >= 0.
    chroma_tolerance : float
        ``"paper"``: largest L1 distance of the rg chromaticities of the two sides' reflectances; >= 0.
    min_contrast : float
        ``"paper"``: smallest ``(I_l - I_s) / I_l`` in every channel; in (0, 1).
    max_change : float
        ``"paper"``: ``S_env + x`` stays within ``[S_env / max_change, S_env max_change]``; >= 1.
    smoothing : int
        ``"paper"``: box side, pixels, over which a pair's values are averaged within their own side.
    smoothness : float
        ``"paper"``: ``lambda``, weight of the smoothness term; > 0.
    edge_scale : float
        ``"paper"``: scale of the ``log S_env`` jumps that cut the smoothness; > 0.
    prior : float
        ``"paper"``: ``mu``, pull toward no change; > 0.
    coarse : int
        ``"paper"``: the offsets are solved on a grid this many times coarser than the image; >= 1.
    shading_floor : float
        As :class:`~mvintrinsic.matting.MattingConfig` ``shading_floor``: where the refined total
        shading falls below this fraction of the view's median, ``S_ind`` is raised to reach it
        (:func:`relayer`); in (0, 1).
    min_boundary_share : float
        The pipeline runs Step 4 only when the Step-3 labels hold cast-shadow boundary pixels
        (shadow pixels with a lit 4-neighbour, the proxy's sun cosine at least 0.2: not an
        attached shadow) on at least this share of the valid pixels of all views (beyond the
        paper: without a shadow boundary the ``S_env`` offsets have nothing to correct; the
        ``"multiview"`` fusion, which needs none, still runs: "fusion only"; recorded in
        ``lighting.json`` "model"). 5e-4 is 86 pixels of a 480x360 view; one shadow edge across
        a view is several hundred.
    """

    method: str = "multiview"
    fusion_weight: float = 0.25
    band: int = 6
    umbra: float = 0.05
    surface_tolerance: float = 0.15
    chroma_tolerance: float = 0.04
    min_contrast: float = 0.2
    max_change: float = 2.0
    smoothing: int = 3
    smoothness: float = 10.0
    edge_scale: float = 0.1
    prior: float = 1e-3
    coarse: int = 4
    shading_floor: float = SHADING_FLOOR
    min_boundary_share: float = 5e-4

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {self.method!r}")
        for name, least in (("band", 1), ("smoothing", 1), ("coarse", 1)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
                raise ValueError(f"{name} must be an integer >= {least}, got {value!r}")
            object.__setattr__(self, name, int(value))
        checks = {"fusion_weight": lambda v: v >= 0.0, "umbra": lambda v: 0.0 <= v < 0.5,
                  "surface_tolerance": lambda v: v >= 0.0, "chroma_tolerance": lambda v: v >= 0.0,
                  "min_contrast": lambda v: 0.0 < v < 1.0, "max_change": lambda v: v >= 1.0,
                  "smoothness": lambda v: v > 0.0, "edge_scale": lambda v: v > 0.0, "prior": lambda v: v > 0.0,
                  "shading_floor": lambda v: 0.0 < v < 1.0, "min_boundary_share": lambda v: 0.0 <= v < 1.0}
        for name, ok in checks.items():
            value = getattr(self, name)
            if not is_real(value) or not np.isfinite(value) or not ok(float(value)):
                raise ValueError(f"{name} is out of range, got {value!r} (EnvRefineConfig docstring)")
            object.__setattr__(self, name, float(value))


@dataclass(frozen=True)
class OffsetPairs:
    """Same-reflectance light/shadow pixel pairs across the shadow boundaries of one view.

    Parameters
    ----------
    shadow, lit : (K, 2) int64
        ``(row, col)`` of the shadowed and the lit pixel of each pair.
    offset : (K, 3) float64
        ``x``, the offset of ``S_env`` (shading units, per channel) that makes the pair's two
        reflectances equal (module docstring, step 2).
    """

    shadow: np.ndarray
    lit: np.ndarray
    offset: np.ndarray

    def __len__(self) -> int:
        return len(self.offset)


@dataclass(frozen=True)
class EnvRefinement:
    """The result of Step 4 for one view.

    Parameters
    ----------
    layers : IntrinsicLayers
        The refined layers: ``S_sky`` and ``S_ind`` scaled to ``S_env^n``, the reflectance by Eq. 2.
    offset : (H, W, 3) float32
        The propagated ``x`` (``S_env^n = S_env + x``), shading units.
    pairs : OffsetPairs
        The pairs that constrained it.
    """

    layers: IntrinsicLayers
    offset: np.ndarray
    pairs: OffsetPairs



def _check_inputs(image: object, layers: object) -> tuple[np.ndarray, IntrinsicLayers]:
    if not isinstance(layers, IntrinsicLayers):
        raise TypeError(f"layers must be an IntrinsicLayers, got {type(layers).__name__}")
    image = np.asarray(image, dtype=np.float64)
    if image.shape != (*layers.shape, 3):
        raise ValueError(f"image must have shape {(*layers.shape, 3)} (the layers'), got {image.shape}")
    if not np.isfinite(image).all():
        raise ValueError("image must be finite")
    return image, layers


def boundary_pairs(image: np.ndarray, layers: IntrinsicLayers, *, config: EnvRefineConfig | None = None
                   ) -> OffsetPairs:
    """Same-reflectance light/shadow pairs across the shadow boundaries and their offsets (Sec. 7).

    Parameters
    ----------
    image : (H, W, 3) array_like
        The view's linear image ``I``.
    layers : IntrinsicLayers
        Step 3's layers of the view (labels, ``v_sun``, ``S_sun``, ``S_sky``, ``S_ind``).
    config : EnvRefineConfig, optional

    Returns
    -------
    OffsetPairs
        Module docstring, steps 1-2.
    """
    config = config_or_default(config, EnvRefineConfig)
    image, layers = _check_inputs(image, layers)
    v = layers.visibility
    env = layers.sky_shading.astype(np.float64) + layers.indirect_shading
    sun = layers.sun_shading.astype(np.float64)
    valid = (env > 0).all(axis=-1) & (image > 0).all(axis=-1)
    shadow = valid & (layers.shadow_labels == SHADOW_LABELS["shadow"]) & (v <= config.umbra)
    lit = valid & (layers.shadow_labels == SHADOW_LABELS["lit"]) & (v >= 1.0 - config.umbra) & (sun > 0).all(axis=-1)
    empty = OffsetPairs(np.zeros((0, 2), np.int64), np.zeros((0, 2), np.int64), np.zeros((0, 3)))
    if not shadow.any() or not lit.any():
        return empty
    size = config.smoothing
    smooth = {name: (masked_box_mean(image, mask, size), masked_box_mean(env, mask, size),
                     masked_box_mean(sun, mask, size)) for name, mask in (("shadow", shadow), ("lit", lit))}
    pairs_s, pairs_l = [], []
    for near, far in ((shadow, lit), (lit, shadow)):
        distance, (rows, cols) = ndimage.distance_transform_edt(~far, return_indices=True)
        i, j = np.nonzero(near & (distance <= config.band))
        k, m = rows[i, j], cols[i, j]
        if near is shadow:
            pairs_s.append(np.stack([i, j], 1))
            pairs_l.append(np.stack([k, m], 1))
        else:
            pairs_s.append(np.stack([k, m], 1))
            pairs_l.append(np.stack([i, j], 1))
    s = np.concatenate(pairs_s)
    ell = np.concatenate(pairs_l)
    i_s, e_s, u_s = (a[s[:, 0], s[:, 1]] for a in smooth["shadow"])
    i_l, e_l, u_l = (a[ell[:, 0], ell[:, 1]] for a in smooth["lit"])

    def relative(a, b):
        la, lb = luminance(a), luminance(b)
        return np.abs(la - lb) / np.maximum(np.maximum(la, lb), 1e-12)

    def rg(x):
        return x[:, :2] / np.maximum(x.sum(axis=1, keepdims=True), 1e-12)

    total_l = u_l + e_l
    same_surface = (relative(e_s, e_l) <= config.surface_tolerance) & (relative(u_s, u_l) <= config.surface_tolerance)
    same_material = np.abs(rg(i_s / e_s) - rg(i_l / total_l)).sum(axis=1) <= config.chroma_tolerance
    contrast = ((i_l - i_s) >= config.min_contrast * i_l).all(axis=1)
    keep = same_surface & same_material & contrast
    s, ell = s[keep], ell[keep]
    i_s, e_s, i_l, e_l, total_l = i_s[keep], e_s[keep], i_l[keep], e_l[keep], total_l[keep]
    # Fig. 8: I_s / (S_env,s + x) = I_l / (S_sun,l + S_env,l + x), per channel.
    x = (i_s * total_l - i_l * e_s) / (i_l - i_s)
    low = np.maximum(e_s, e_l) * (1.0 / config.max_change - 1.0)  # S_env + x >= S_env / max_change on both
    high = np.minimum(e_s, e_l) * (config.max_change - 1.0)
    x = np.clip(x, low, high)
    return OffsetPairs(s.astype(np.int64), ell.astype(np.int64), x)


def _coarse_mean(values: np.ndarray, weights: np.ndarray, factor: int) -> tuple[np.ndarray, np.ndarray]:
    """Block sums of ``weights`` and weighted block means of ``values`` (H, W, C) over factor x factor blocks."""
    h, w = weights.shape
    hc, wc = -(-h // factor), -(-w // factor)
    pad = ((0, hc * factor - h), (0, wc * factor - w))
    wt = np.pad(weights, pad).reshape(hc, factor, wc, factor).sum(axis=(1, 3))
    val = np.pad(values * weights[..., None], (*pad, (0, 0))).reshape(hc, factor, wc, factor, -1).sum(axis=(1, 3))
    return val / np.maximum(wt, 1e-12)[..., None], wt


def propagate_offsets(pairs: OffsetPairs, env: np.ndarray, *, config: EnvRefineConfig | None = None) -> np.ndarray:
    """Spread the pairs' offsets smoothly over the view (module docstring, step 3).

    Parameters
    ----------
    pairs : OffsetPairs
    env : (H, W, 3) array_like
        ``S_env = S_sky + S_ind`` of the view, shading units (its jumps cut the smoothness).
    config : EnvRefineConfig, optional

    Returns
    -------
    (H, W, 3) float64
        The offset ``x`` of every pixel (0 everywhere when there is no pair).
    """
    config = config_or_default(config, EnvRefineConfig)
    env = np.asarray(env, dtype=np.float64)
    h, w = env.shape[:2]
    if not len(pairs):
        return np.zeros((h, w, 3))
    data = np.zeros((h, w, 3))
    count = np.zeros((h, w))
    for where in (pairs.shadow, pairs.lit):
        np.add.at(data, (where[:, 0], where[:, 1]), pairs.offset)
        np.add.at(count, (where[:, 0], where[:, 1]), 1.0)
    data /= np.maximum(count, 1.0)[..., None]
    f = config.coarse
    target, weight = _coarse_mean(data, count, f)
    log_env, _ = _coarse_mean(np.log(np.maximum(luminance(env), 1e-12))[..., None], np.ones((h, w)), f)
    log_env = log_env[..., 0]
    hc, wc = weight.shape
    n = hc * wc
    index = np.arange(n).reshape(hc, wc)
    rows, cols, vals = [], [], []
    for a, b, da, db in ((index[:, 1:], index[:, :-1], log_env[:, 1:], log_env[:, :-1]),
                         (index[1:], index[:-1], log_env[1:], log_env[:-1])):
        wt = config.smoothness * np.exp(-((da - db) / config.edge_scale) ** 2)
        a, b, wt = a.ravel(), b.ravel(), wt.ravel()
        rows += [a, b, a, b]
        cols += [a, b, b, a]
        vals += [wt, wt, -wt, -wt]
    laplacian = sparse.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n))
    # Each coarse cell's data weight: the number of pair pixels in it (a cell mean of them).
    system = (laplacian + sparse.diags(weight.ravel() + config.prior)).tocsc()
    solution = spsolve(system, (weight[..., None] * target).reshape(n, 3))
    coarse = np.asarray(solution).reshape(hc, wc, 3)
    # Bilinear upsampling: pixel centres to coarse-cell centres.
    y = (np.arange(h) + 0.5) / f - 0.5
    x = (np.arange(w) + 0.5) / f - 0.5
    yy, xx = np.meshgrid(np.clip(y, 0, hc - 1), np.clip(x, 0, wc - 1), indexing="ij")
    return np.stack([ndimage.map_coordinates(coarse[..., c], [yy, xx], order=1, mode="nearest") for c in range(3)],
                    axis=-1)


def relayer(image: np.ndarray, layers: IntrinsicLayers, *, visibility: np.ndarray | None = None,
            env_scale: np.ndarray | None = None, floor: float = SHADING_FLOOR) -> IntrinsicLayers:
    """The layers with a new ``v_sun`` and/or ``S_env``, the reflectance recomputed by Eq. 2.

    ``S_tot = v_sun S_sun + S_sky + S_ind`` (Eq. 17) with ``S_sky`` and ``S_ind`` both multiplied by
    ``env_scale``; where ``S_tot`` falls below ``floor`` times its median over the layers' pixels,
    ``S_ind`` is raised to reach it (:func:`~mvintrinsic.pixels.floored_shading`), so that
    ``R * S_tot`` reproduces the image. Pixels without layers (all-zero reflectance: sky, off the
    proxy) keep zeros. Labels and ``S_sun`` are kept.

    Parameters
    ----------
    image : (H, W, 3) array_like
        The view's linear image ``I``.
    layers : IntrinsicLayers
    visibility : (H, W) array_like, optional
        New ``v_sun``, clipped to [0, 1]; the layers' own when not given.
    env_scale : (H, W, 3) or (H, W) array_like, optional
        Factor on ``S_env``; 1 when not given.
    floor : float, optional

    Returns
    -------
    IntrinsicLayers
    """
    image, layers = _check_inputs(image, layers)
    known = (layers.reflectance > 0).any(axis=-1)
    v = layers.visibility.astype(np.float64) if visibility is None else np.clip(
        np.asarray(visibility, dtype=np.float64), 0.0, 1.0)
    if v.shape != layers.shape:
        raise ValueError(f"visibility must have shape {layers.shape}, got {v.shape}")
    scale = np.ones((*layers.shape, 1)) if env_scale is None else np.asarray(env_scale, dtype=np.float64)
    if scale.ndim == 2:
        scale = scale[..., None]
    if scale.shape[:2] != layers.shape or not np.isfinite(scale).all() or (scale < 0).any():
        raise ValueError(f"env_scale must be finite, non-negative, of shape {layers.shape} (+ channels)")
    sky = layers.sky_shading * scale
    indirect, total = floored_shading(sky, layers.indirect_shading * scale, v, layers.sun_shading, known,
                                      floor=floor)                                        # Eq. 17
    reflectance = np.divide(image, total, out=np.zeros_like(image), where=known[..., None] & (total > 0))  # Eq. 2
    zero = ~known[..., None]
    return dataclasses.replace(
        layers, reflectance=reflectance.astype(np.float32),
        visibility=np.where(known, v, layers.visibility).astype(np.float32),
        sky_shading=np.where(zero, layers.sky_shading, sky).astype(np.float32),
        indirect_shading=np.where(zero, layers.indirect_shading, indirect).astype(np.float32))


def refine_environment(image: np.ndarray, layers: IntrinsicLayers, *, config: EnvRefineConfig | None = None
                       ) -> EnvRefinement:
    """The paper's Step 4 on one view: ``S_env`` offsets that make the reflectance continuous (Sec. 7).

    Parameters
    ----------
    image : (H, W, 3) array_like
        The view's linear image ``I``.
    layers : IntrinsicLayers
        Step 3's layers of the view.
    config : EnvRefineConfig, optional
        Its ``"paper"`` options are used whatever its ``method``.

    Returns
    -------
    EnvRefinement
        The refined layers (module docstring, ``"paper"``), the offset and the pairs.

    Raises
    ------
    TypeError, ValueError
        If ``layers`` is not an IntrinsicLayers, ``image`` does not have its shape or is not finite,
        or ``config`` is not an EnvRefineConfig.
    """
    config = config_or_default(config, EnvRefineConfig)
    image, layers = _check_inputs(image, layers)
    pairs = boundary_pairs(image, layers, config=config)
    env = layers.sky_shading.astype(np.float64) + layers.indirect_shading
    offset = propagate_offsets(pairs, env, config=config)
    refined = np.clip(env + offset, env / config.max_change, env * config.max_change)
    scale = np.where(env > 0, refined / np.where(env > 0, env, 1.0), 1.0)
    out = relayer(image, layers, env_scale=scale, floor=config.shading_floor)
    return EnvRefinement(out, (refined - env).astype(np.float32), pairs)


def fuse_reflectance(layers: Mapping[str, IntrinsicLayers], correspondences: Correspondences, *,
                     weight: float = 0.25) -> dict[str, np.ndarray]:
    """Each view's reflectance averaged, in log, with the other views' at the same surface point.

    :func:`~mvintrinsic.correspondence.fuse_views` of ``log R`` over the consistent correspondences
    (a point has one reflectance whichever photo sees it). Pixels without reflectance (zero: sky,
    off the proxy) are neither changed nor read: a correspondence that lands on one is not used.
    Views are summed in stem order, so the result does not depend on the order of ``layers``.

    Parameters
    ----------
    layers : mapping of str to IntrinsicLayers
        One per view of ``correspondences``.
    correspondences : Correspondences
    weight : float, optional
        Weight of each other view relative to the pixel's own (>= 0).

    Returns
    -------
    dict of str to (H, W, 3) float64
        The fused reflectance (0 where the view has none).
    """
    for stem, layer in layers.items():
        if not isinstance(layer, IntrinsicLayers):
            raise TypeError(f"layers[{stem!r}] must be IntrinsicLayers, got {describe(layer)}")
    if not is_real(weight) or not 0 <= weight < np.inf:
        raise ValueError(f"weight must be a finite number >= 0, got {weight!r}")
    known = {stem: (layer.reflectance > 0).all(axis=-1, keepdims=True) for stem, layer in layers.items()}
    # Channels 0-2: k log R, channel 3: k, with k = 1 where the view has a reflectance, 0 elsewhere
    # (log 1 = 0), so that partners without one add nothing; their ratio is the mean over the rest.
    values = {stem: np.concatenate([np.log(np.where(known[stem], layer.reflectance, 1.0)), known[stem]], axis=-1)
              for stem, layer in layers.items()}
    out = {}
    for stem, fused in fuse_views(values, correspondences, weight=weight).items():
        mean_log = np.divide(fused[..., :3], fused[..., 3:], out=np.zeros_like(fused[..., :3]), where=known[stem])
        out[stem] = np.where(known[stem], np.exp(mean_log), 0.0)
    return out


def with_reflectance(layers: IntrinsicLayers, reflectance: np.ndarray) -> IntrinsicLayers:
    """The layers with a new reflectance, the shading taking the rest: ``S_tot = R_old S_tot_old / R``.

    Every shading term (``v_sun S_sun``, ``S_sky``, ``S_ind``) of a pixel is multiplied by the same
    per-channel factor ``R_old / R``, so ``R * S_tot`` still reproduces the image (Eq. 1) and the terms
    keep their proportions. Pixels where either reflectance is zero keep their layers.

    Parameters
    ----------
    layers : IntrinsicLayers
    reflectance : (H, W, 3) array_like
        The new reflectance, >= 0.

    Returns
    -------
    IntrinsicLayers
    """
    if not isinstance(layers, IntrinsicLayers):
        raise TypeError(f"layers must be an IntrinsicLayers, got {describe(layers)}")
    new = np.asarray(reflectance, dtype=np.float64)
    if new.shape != (*layers.shape, 3) or not np.isfinite(new).all() or (new < 0).any():
        raise ValueError(f"reflectance must be finite, non-negative, of shape {(*layers.shape, 3)}")
    old = layers.reflectance.astype(np.float64)
    both = ((old > 0) & (new > 0)).all(axis=-1, keepdims=True)
    factor = np.where(both, old / np.where(both, new, 1.0), 1.0)
    return dataclasses.replace(
        layers, reflectance=np.where(both, new, old).astype(np.float32),
        sun_shading=(layers.sun_shading * factor).astype(np.float32),
        sky_shading=(layers.sky_shading * factor).astype(np.float32),
        indirect_shading=(layers.indirect_shading * factor).astype(np.float32))


@dataclass(frozen=True, eq=False)
class Step4Result:
    """Step 4 of every view.

    Parameters
    ----------
    layers : mapping of str to IntrinsicLayers
        The refined layers per view stem.
    offsets : mapping of str to (H, W, 3) float32, or None
        ``"paper"``: the propagated ``S_env`` offset of each view (shading units); None otherwise.
    pairs : mapping of str to int
        ``"paper"``: the number of light/shadow pairs per view; empty otherwise.
    timings : mapping of str to float
        Seconds: ``correspondences`` (when found here) and ``fusion`` (``"multiview"``) or ``offsets``
        (``"paper"``).
    """

    layers: Mapping[str, IntrinsicLayers]
    offsets: Mapping[str, np.ndarray] | None
    pairs: Mapping[str, int]
    timings: Mapping[str, float]


def refine(views: Sequence[View], layers: Mapping[str, IntrinsicLayers], *,
           quantities: Mapping[str, PixelQuantities] | None = None,
           correspondences: Correspondences | None = None,
           config: EnvRefineConfig | None = None) -> Step4Result:
    """Step 4 (Sec. 7) on every view (module docstring).

    Parameters
    ----------
    views : sequence of View
    layers : mapping of str to IntrinsicLayers
        Step 3's layers per view stem.
    quantities : mapping of str to PixelQuantities, optional
        The views' per-pixel Step-1 quantities; ``"multiview"`` needs them to find the
        correspondences when ``correspondences`` is not given.
    correspondences : Correspondences, optional
        Cross-view correspondences already found (e.g.
        :attr:`~mvintrinsic.multiview_shadows.MultiViewShadowLabels.correspondences`).
    config : EnvRefineConfig, optional

    Returns
    -------
    Step4Result

    Raises
    ------
    ValueError, TypeError
        Naming the argument: a view without layers, layers of the wrong shape, ``"multiview"``
        without ``quantities`` or ``correspondences``.
    """
    config = config_or_default(config, EnvRefineConfig)
    views = list(views)
    if not views:
        raise ValueError("views must not be empty")
    for view in views:
        if not isinstance(view, View):
            raise TypeError(f"views must hold View objects, got {describe(view)}")
        if view.stem not in layers:
            raise ValueError(f"layers: no layers for view {view.stem!r}")
        if not isinstance(layers[view.stem], IntrinsicLayers) or layers[view.stem].shape != view.shape:
            raise ValueError(f"layers[{view.stem!r}] must be IntrinsicLayers of shape {view.shape}")
    timings: dict[str, float] = {}
    if config.method == "paper":
        start = time.perf_counter()
        results = {v.stem: refine_environment(v.image, layers[v.stem], config=config) for v in views}
        timings["offsets"] = time.perf_counter() - start
        return Step4Result(layers={s: r.layers for s, r in results.items()},
                           offsets={s: r.offset for s, r in results.items()},
                           pairs={s: len(r.pairs) for s, r in results.items()}, timings=timings)
    if len(views) == 1:
        return Step4Result(layers={views[0].stem: layers[views[0].stem]}, offsets=None, pairs={}, timings=timings)
    if correspondences is None:
        if quantities is None:
            raise ValueError("quantities: the 'multiview' method needs the views' PixelQuantities "
                             "(or correspondences)")
        start = time.perf_counter()
        correspondences = find_correspondences(views, quantities)
        timings["correspondences"] = time.perf_counter() - start
    elif not isinstance(correspondences, Correspondences):
        raise TypeError(f"correspondences must be Correspondences, got {describe(correspondences)}")
    start = time.perf_counter()
    fused = fuse_reflectance({v.stem: layers[v.stem] for v in views}, correspondences, weight=config.fusion_weight)
    out = {v.stem: with_reflectance(layers[v.stem], fused[v.stem]) for v in views}
    timings["fusion"] = time.perf_counter() - start
    return Step4Result(layers=out, offsets=None, pairs={}, timings=timings)
