"""The closed-form matting Laplacian [2]_ of a view, its sparse systems and their solvers (paper Sec. 6.2).

The numerical core of :mod:`.matting` (Step 3's per-pixel layers [1]_): the guide image, the
Laplacian as a stencil, the systems of the matte, the propagation and the band diffusion, their
nested-dissection order and sparse LU (or conjugate-gradient) solves with residual reports, and
the options of the whole matting stage (:class:`MattingConfig`).

Guide image
-----------
The views are linear, scene-referred HDR RGB (``docs/conventions.md``). Both the matte and the
propagation use the image scaled by one positive number: divided by the ``white_percentile``
(99.9th by default) percentile of the valid pixels' largest channel, negative values set to 0,
clipped at 1 and not gamma-encoded. Linear RGB is where the penumbra obeys the compositing
equation of matting: with ``R``, ``S_env`` and ``S_sun`` locally constant, Eq. 1 reads
``I = R S_env + v_sun R S_sun``, i.e. ``I = alpha F + (1 - alpha) B`` with ``alpha = v_sun``,
``B = R S_env`` (the shadowed colour) and ``F = R (S_env + S_sun)`` (the lit colour). The
closed-form matte is invariant to a global scale of the image except through ``epsilon``, which
assumes a [0, 1] image, hence the normalisation; the clip (the brightest 0.1% of the pixels,
highlights) keeps every window's colour variance below 1 (see ``epsilon`` in
:class:`MattingConfig`). Pixels
outside the valid mask (sky, invalid) take part in no matting window: every window that touches
one is dropped from the Laplacian, so the sky neither pulls nor separates the image's values.

Solver
------
The closed-form Laplacian (Levin et al.'s Eq. 12, 3x3 windows) is built in NumPy as a stencil:
one image per coupling offset, the upper half of the 5x5 neighbourhood (13 images; ``L`` is
symmetric). Each window's regularised colour covariance is factored as ``L D L^T`` in closed form,
so that every entry is ``delta_ij - (1 + g_i . g_j) / |w|`` with whitened colours ``g``; this stays
accurate on the rank-1 windows of a two-colour edge, where a cofactor inverse cancels. One pass
over the windows builds the view's two stencils: over the valid pixels (the visibility matte) and
over the valid pixels outside the shadow-boundary band (the propagation). A system gathers the
rows of its unknowns from its stencil, the known pixels' Dirichlet term on the right-hand side,
with the unknowns in a nested-dissection order computed from their image coordinates
(:func:`_dissection_order`: separators of 2 rows or columns, cut where the unknowns are fewest),
and is solved by one sparse LU factorisation (SciPy's SuperLU, without pivoting: the systems are
symmetric positive definite) shared by its channels: 1 for ``v_sun``, 7 for ``S_sky``, ``S_ind``
and the cosine. The band diffusion is solved the same way (4-neighbour separators of 1 pixel).
Every solve's residual is checked against ``rtol`` and reported (:class:`SolveReport`,
:func:`intrinsic_layers_result`). ``MattingConfig(solver="cg")`` selects conjugate gradients
preconditioned by an incomplete LU instead (slower; for memory).

Measured (``benchmarks/bench_matting.py``, ``docs/matting.md``; 2 cores shared with other jobs,
medians of interleaved repeats) against the former solver, conjugate gradients preconditioned by
pymatting's [3]_ incomplete Cholesky factor: 1.4-1.6x faster at 480x360, 2.1-4.4x at 1000x750
(views upsampled from 480x360 and 320x240), 40% less peak memory at 1400x1050; the scores against
ground truth unchanged to the fourth digit (the direct solve is exact where conjugate gradients
stopped at ``rtol``, up to 1.4% of a layer's range apart). Nothing is compiled at first use: the
former pymatting and numba kernels took 38-74 s to compile on the first call after
``pip install``. The module changes no process-wide state.

References
----------
.. [1] S. Duchêne et al., "Multi-View Intrinsic Images of Outdoors Scenes with an Application to
   Relighting", ACM Transactions on Graphics 34(5), 2015, Sec. 6.2.
.. [2] A. Levin, D. Lischinski and Y. Weiss, "A Closed-Form Solution to Natural Image Matting",
   IEEE TPAMI 30(2), 2008.
.. [3] T. Germer, T. Uelwer, S. Conrad and S. Harmeling, "PyMatting: A Python Library for Alpha
   Matting", Journal of Open Source Software 5(54), 2020.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy import ndimage
from scipy.sparse import linalg as spla

from ._validation import as_array, describe, is_real
from .pixels import SHADING_FLOOR, nearest_fill

__all__ = ["SOLVERS", "MattingConfig", "SolveReport", "guide_image"]

logger = logging.getLogger(__name__)


#: The solvers of :class:`MattingConfig` ``solver`` (see there and the module docstring).
SOLVERS = ("direct", "cg")


@dataclass(frozen=True)
class MattingConfig:
    """Options of the per-pixel layers (paper Sec. 6.2); the paper gives none of these values.

    Distances are in pixels of the working image (they do not scale with the image size).

    Parameters
    ----------
    trimap_radius : int
        A shadow (lit) pixel at most this far (Euclidean) from a lit (shadow) pixel is unknown in
        the visibility matte, a band about ``2 * trimap_radius`` wide, except the centre line of
        regions thinner than that. 3 covers the penumbra of an occluder 10 m from its shadow at
        1000x750 (the sun's 0.53 deg spans 9 cm there, 5 px at the courtyard's 1.7 cm per pixel);
        5 erased thin shadows (fence, window lintels) at 480x360 before the centre-line rule.
    visibility_cluster_width : int
        Pixels within this of a cluster boundary are unknown in the visibility matte too ("we also
        propagate visibility in the boundary regions between clusters"); 0 disables it. 1 marks the
        boundary pixels themselves (both sides, :func:`mvintrinsic.segmentation.boundary_band`).
        Used only when the clusters are given.
    cluster_boundary_width : int
        Proxy pixels within this of a cluster boundary are not constraints of the shading
        propagation ("all 3D points except those in the boundaries between clusters"); 3 is the
        paper's "3-pixel wide boundary around each cluster" of Sec. 6.1, as
        :func:`mvintrinsic.segmentation.boundary_band` reads it. On the courtyard views (labels from
        the true visibility) it lowers the mean relative reflectance error from 0.46 to 0.34 at
        1000x750 (median 0.23 to 0.20) against 1 (the boundary pixels only), at about twice the
        propagation time (three quarters of the pixels are then unconstrained). Used only when the clusters
        are given.
    shadow_band_radius : int
        Pixels within this of a shadow/lit label transition are left out of the shading
        propagation and filled by diffusion ("a small band along shadow boundaries"); 0 disables
        it. 3 gives a band about 6 px wide, which holds the penumbra at 1000x750.
    shadow_level : float or None
        Beyond the paper (``None``, the default, is the paper's propagation): the Gaussian
        standard deviation, in pixels, over which the propagated ``S_sky`` and ``S_ind`` of the
        shadow-labelled pixels are brought back to Step 1's level
        (:func:`~mvintrinsic.matting.restore_shadow_level`).
        The propagation fills the band and the cluster boundaries with values that follow the
        image but raise ``S_env`` in the shadows (the band is diffused from both sides, the lit
        side's ``S_env`` is higher); Step 1's own values have the right level but scatter from
        pixel to pixel. With 5 on the seven test scenes (``docs/step4.md``, "The umbra's ``S_env``
        and Step 3's propagation"): the reflectance LMSE falls on all seven (2-11%), the
        shading LMSE moves by -4% to +1%, the umbra's blue error falls on six of them. Not the
        default: the shading LMSE rises on five scenes, the umbra's red and green on two, and
        the relit images lose 0.00-0.05 dB (three scenes, 12 suns). With an accurate proxy it
        matters more: on the exact meshes of demo_480 and courtyard_s1 the paper's propagation
        leaves the umbra's blue 51-57% off, the option 13-17%; the reflectance LMSE falls 4-19%
        on three exact meshes (``docs/step4.md``, "The umbra line against the proxy").
    epsilon : float
        Regularisation of the window colour covariance in the matting Laplacian, for images in
        [0, 1]. Levin et al. and pymatting use ``1e-7``; we use ``1e-6``, chosen when the Laplacian
        was pymatting's: its cofactor inverse of the 3x3 covariance cancels catastrophically when
        a window holds exactly two colours (rank 1) and ``epsilon`` is tiny (a noiseless two-colour
        edge leaked 0.32 across at ``1e-7``, 0.002 at ``1e-6``), and on the courtyard views (noisy
        renders) both values gave the same layers to 0.001 in ``v_sun`` error. The ``L D L^T``
        whitening used now is accurate down to ``1e-10`` (tested); the default is kept so that the
        layers do not change.
    window_radius : int
        Matting windows are ``(2 r + 1)^2`` pixels (Levin et al. and pymatting: 1).
    constraint_weight : float or None
        ``lambda`` of a soft constraint term ``lambda sum_K (x_k - s_k)^2`` in the propagation, or
        None (default) for hard constraints, its ``lambda -> infinity`` limit: fewer unknowns, and
        the Step-1 values at the proxy pixels are kept exactly.
    prior_weight : float
        ``delta``, the weight of the pull toward the nearest constraint's value, on every unknown;
        small enough to leave reachable pixels alone (a change of order ``delta`` near constraints),
        large enough to make every system positive definite.
    white_percentile : float
        Percentile of the valid pixels' largest channel that the guide image maps to 1, in
        (0, 100]; brighter values are clipped (highlights).
    solver : str
        How the linear systems are solved (:data:`SOLVERS`): ``"direct"`` (default), a sparse LU
        factorisation (SciPy's SuperLU) of each system in a nested-dissection order of its pixels,
        shared by the system's channels; ``"cg"``, conjugate gradients preconditioned by an
        incomplete LU of the same system (less memory, more time). Measured on 1000x750 views
        (``benchmarks/bench_matting.py``, ``docs/matting.md``), the direct solve makes the matting
        2.1-4.4x faster than the former default, conjugate gradients with pymatting's incomplete
        Cholesky factor (1.4-1.6x at 480x360), and exact where those stopped at ``rtol`` (up to
        1.4% of a shading layer's range apart); ``"cg"`` took 2.2 s where ``"direct"`` took 0.9 s.
    threads : int
        Threads of one view's matting: with 2 (default) the visibility matte and the shading
        propagation, independent systems, are factorised at the same time (SuperLU releases the
        GIL); 1 solves them one after the other (e.g. when views already run in parallel). Not
        in the paper. On a 1000x750 view of timing_1000 with the paper's segmentation (363k and
        426k unknowns): ``docs/presets.md``.
    rtol : float
        Accepted relative residual ``||A x - b|| / ||b||`` of every system and channel. A direct
        solve above it is refined (:data:`REFINEMENT_STEPS`); conjugate gradients stop once below
        it. Against a direct solve of a 480x360 shading system, conjugate gradients stopped at
        ``1e-6`` left a largest error of 0.6% of the layer's range (0.14% at the 99th percentile);
        ``1e-5`` left 28% (1%). A system that misses it keeps its last iterate, with a logged
        warning and ``converged=False`` in its :class:`SolveReport`.
    max_iter : int
        Largest number of conjugate-gradient iterations per channel (``solver="cg"``).
    ichol_threshold : float
        Drop tolerance of the incomplete factorisation that preconditions ``solver="cg"``
        (SciPy's ``spilu``, an incomplete LU of the symmetric system; entries below this
        fraction of their column are dropped). The name is that of the former incomplete
        Cholesky (pymatting's, whose default 1e-4 it keeps), so that saved configurations load.
    shading_floor : float
        Total shading below this fraction of the view's median is raised to it through ``S_ind``,
        so that ``R = I / S_tot`` stays finite (as ``pipeline.step2_layers``: ``1e-3``).
    """

    trimap_radius: int = 3
    visibility_cluster_width: int = 1
    cluster_boundary_width: int = 3
    shadow_band_radius: int = 3
    shadow_level: float | None = None
    epsilon: float = 1e-6
    window_radius: int = 1
    constraint_weight: float | None = None
    prior_weight: float = 1e-5
    white_percentile: float = 99.9
    rtol: float = 1e-6
    max_iter: int = 2000
    ichol_threshold: float = 1e-4
    shading_floor: float = SHADING_FLOOR
    solver: str = "direct"
    threads: int = 2

    def __post_init__(self) -> None:
        for name, least in (("trimap_radius", 1), ("visibility_cluster_width", 0), ("cluster_boundary_width", 0),
                            ("shadow_band_radius", 0), ("window_radius", 1), ("max_iter", 1), ("threads", 1)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
                raise ValueError(f"{name} must be an integer >= {least}, got {value!r}")
        for name in ("epsilon", "constraint_weight", "shadow_level", "prior_weight", "rtol", "ichol_threshold",
                     "shading_floor"):
            value = getattr(self, name)
            if name in ("constraint_weight", "shadow_level") and value is None:
                continue
            if not is_real(value) or not 0 < value < np.inf:
                raise ValueError(f"{name} must be a positive finite number, got {value!r}")
        if not is_real(self.white_percentile) or not 0 < self.white_percentile <= 100:
            raise ValueError(f"white_percentile must lie in (0, 100], got {self.white_percentile!r}")
        if not self.rtol < 1:
            raise ValueError(f"rtol must be below 1, got {self.rtol!r}")
        if not self.shading_floor < 1:
            raise ValueError(f"shading_floor must be below 1, got {self.shading_floor!r}")
        if self.solver not in SOLVERS:
            raise ValueError(f"solver must be one of {list(SOLVERS)}, got {self.solver!r}")


def _check_image(image: object) -> np.ndarray:
    array = as_array(image, "image", shape=(None, None, 3), dtype=np.float64, finite=False)
    if 0 in array.shape:
        raise ValueError(f"image must have at least one pixel, got shape {array.shape}")
    return array


def _check_flags(flags: object, name: str, shape: tuple[int, int]) -> np.ndarray:
    array = np.asarray(flags)
    if array.dtype != bool:
        raise TypeError(f"{name} must be a boolean array, got {describe(flags)}")
    if array.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got shape {array.shape}")
    return array


def _check_mask(mask: object, shape: tuple[int, int], image: np.ndarray) -> np.ndarray:
    valid = np.ones(shape, dtype=bool) if mask is None else _check_flags(mask, "mask", shape)
    bad = valid & ~np.isfinite(image).all(axis=2)
    if bad.any():
        raise ValueError(f"image must be finite on the mask, got {int(bad.sum())} NaN/Inf pixels (mask them out)")
    return valid


# --------------------------------------------------------------------------------------------
# The matting Laplacian and the solvers
# --------------------------------------------------------------------------------------------

def guide_image(image: np.ndarray, *, mask: np.ndarray | None = None, white_percentile: float = 99.9) -> np.ndarray:
    """The image that guides the matting: linear RGB scaled to a white of 1 (module docstring).

    Parameters
    ----------
    image : (H, W, 3) float
        Linear, scene-referred RGB; must be finite on ``mask``.
    mask : (H, W) bool, optional
        Valid pixels (default: all).
    white_percentile : float, optional
        Percentile of the valid pixels' largest channel mapped to 1, in (0, 100].

    Returns
    -------
    (H, W, 3) float64, C-contiguous
        ``clip(image / white, 0, 1)`` on ``mask``, 0 elsewhere. ``white`` is 1 when the
        percentile is not positive (a black image).
    """
    image = _check_image(image)
    valid = _check_mask(mask, image.shape[:2], image)
    if not is_real(white_percentile) or not 0 < white_percentile <= 100:
        raise ValueError(f"white_percentile must lie in (0, 100], got {white_percentile!r}")
    rgb = np.where(valid[..., None], np.maximum(image, 0.0), 0.0)  # finite on the mask (checked above)
    white = float(np.percentile(rgb[valid].max(axis=-1), white_percentile)) if valid.any() else 0.0
    return np.ascontiguousarray(np.minimum(rgb / (white if white > 0 else 1.0), 1.0), dtype=np.float64)


# The matting Laplacian of Levin et al. (their Eq. 12) over windows of (2 r + 1)^2 pixels:
#
#   L_ij = sum_{k | i, j in w_k} ( delta_ij - (1 + (I_i - mu_k)^T (Sigma_k + eps / |w_k| I_3)^-1 (I_j - mu_k)) / |w_k| )
#
# with mu_k and Sigma_k the mean and covariance of the guide's colours in window w_k. Writing the
# regularised covariance as L D L^T (the 3x3 LDL^T factorisation, in closed form), the quadratic
# term is g_i . g_j with the whitened colours g = D^-1/2 L^-1 (I - mu_k): each window adds, for
# every pair (a, b) of its pixels, -(1 + g_a . g_b) / |w| (plus 1 on the diagonal). Pixels that
# share a window are at most 2 r apart in both axes, so L is a (4 r + 1)^2-point stencil, stored
# as one image per coupling offset ``(dy, dx)`` (the upper half: L is symmetric).


def _window_pixels(radius: int) -> list[tuple[int, int]]:
    """Offsets ``(dy, dx)`` of a window's pixels from its top-left pixel, row-major."""
    size = 2 * radius + 1
    return [(dy, dx) for dy in range(size) for dx in range(size)]


def _couplings(radius: int) -> list[tuple[int, int]]:
    """The coupling offsets ``(dy, dx)`` stored by the stencil: the upper half of ``[-2r, 2r]^2``, row-major."""
    reach = 2 * radius
    return [(dy, dx) for dy in range(reach + 1) for dx in range(-reach, reach + 1) if dy > 0 or dx >= 0]


def _whitened_colours(guide: np.ndarray, epsilon: float, radius: int) -> list[np.ndarray]:
    """``g`` of every window pixel: one ``(3, H - 2r, W - 2r)`` array per window pixel (row-major).

    ``guide`` is ``(3, H, W)``; entry ``[:, y, x]`` of array ``a`` belongs to the window whose
    top-left pixel is ``(y, x)``. The covariance is centred per window (as pymatting's kernel) and
    factored as ``L D L^T``, which stays accurate where the covariance has rank 1 or 2 (a window of
    two colours); inverting it by cofactors, as pymatting does, lost the matte across such edges at
    ``epsilon = 1e-7`` (:class:`MattingConfig`).
    """
    _, h, w = guide.shape
    area = (2 * radius + 1) ** 2
    hh, ww = h - 2 * radius, w - 2 * radius
    pixels = [guide[:, dy:dy + hh, dx:dx + ww] for dy, dx in _window_pixels(radius)]
    mean = np.zeros((3, hh, ww))
    for colours in pixels:
        mean += colours
    mean /= area
    centred = [colours - mean for colours in pixels]

    def covariance(i: int, j: int) -> np.ndarray:
        total = np.zeros((hh, ww))
        for colours in centred:
            total += colours[i] * colours[j]
        return total / area

    regular = epsilon / area  # Sigma_k + eps / |w| I_3 (Levin et al., Eq. 12)
    a00, a01, a02 = covariance(0, 0) + regular, covariance(0, 1), covariance(0, 2)
    a11, a12, a22 = covariance(1, 1) + regular, covariance(1, 2), covariance(2, 2) + regular
    l10, l20 = a01 / a00, a02 / a00
    d1 = a11 - l10 * a01
    l21 = (a12 - l20 * a01) / d1
    d2 = a22 - l20 * a02 - l21 * l21 * d1
    s0, s1, s2 = 1.0 / np.sqrt(a00), 1.0 / np.sqrt(d1), 1.0 / np.sqrt(d2)
    for c in centred:  # in place: c <- D^-1/2 L^-1 c
        y1 = c[1] - l10 * c[0]
        c[2] -= l20 * c[0] + l21 * y1
        c[2] *= s2
        np.multiply(y1, s1, out=c[1])
        c[0] *= s0
    return centred


class _GuidedLaplacian:
    """The closed-form matting Laplacian of one guide image (Levin et al. 2008, Eq. 12; module references), as a stencil.

    ``stencils(keep, ...)`` sums the windows lying wholly inside ``keep`` only: a pixel outside
    ``keep`` takes part in no window, so it neither pulls nor separates the others.
    """

    #: Window rows per band of :meth:`stencils`: cache-sized (at 1000x750, 0.32 s for two stencils
    #: against 0.62-1.28 s for whole images).
    TILE = 16

    def __init__(self, guide: np.ndarray, config: MattingConfig) -> None:
        h, w = guide.shape[:2]
        self.shape = (h, w)
        self.radius = int(config.window_radius)
        self.couplings = _couplings(self.radius)
        self._slot = {offset: k for k, offset in enumerate(self.couplings)}
        self._guide = np.ascontiguousarray(np.moveaxis(guide, -1, 0), dtype=np.float64)
        self._epsilon = float(config.epsilon)

    def stencils(self, *keeps: np.ndarray) -> list[np.ndarray]:
        """The Laplacian over the windows inside each of ``keeps``, sharing the work of the windows.

        Each is ``(K, H, W)`` float64: ``[k, y, x]`` is ``L[(y, x), (y, x) + couplings[k]]`` (0 off
        the image).
        """
        h, w = self.shape
        r = self.radius
        outs = [np.zeros((len(self.couplings), h, w)) for _ in keeps]
        hh, ww = h - 2 * r, w - 2 * r
        if hh <= 0 or ww <= 0 or not any(keep.any() for keep in keeps):
            return outs  # no whole window fits in the image or in the kept pixels
        area = (2 * r + 1) ** 2
        weights = [ndimage.minimum_filter(keep.astype(np.uint8), size=2 * r + 1, mode="constant", cval=0)
                   [r:h - r, r:w - r].astype(np.float64) for keep in keeps]  # windows by their top-left pixel
        offsets = _window_pixels(r)
        for top in range(0, hh, self.TILE):  # bands of window rows, small enough to stay in cache
            bottom = min(top + self.TILE, hh)
            whitened = _whitened_colours(self._guide[:, top:bottom + 2 * r], self._epsilon, r)
            for g in whitened:
                g *= 1.0 / np.sqrt(area)  # g_a . g_b now carries the 1 / |w| of Eq. 12
            tiles = [weight[top:bottom] for weight in weights]
            value = np.empty((bottom - top, ww))
            weighted = np.empty_like(value)
            for a, (ay, ax) in enumerate(offsets):
                for b in range(a, len(offsets)):
                    by, bx = offsets[b]
                    np.einsum("cij,cij->ij", whitened[a], whitened[b], out=value)
                    value += 1.0 / area  # (1 + g_a . g_b) / |w|
                    if a == b:
                        value -= 1.0  # delta_ij
                    dy, dx = by - ay, bx - ax
                    if (dy, dx) in self._slot:  # stored at pixel a
                        slot, rows, cols = self._slot[dy, dx], slice(top + ay, bottom + ay), slice(ax, ax + ww)
                    else:  # stored at pixel b, coupling a - b
                        slot, rows, cols = self._slot[-dy, -dx], slice(top + by, bottom + by), slice(bx, bx + ww)
                    for out, weight in zip(outs, tiles, strict=True):
                        np.multiply(value, weight, out=weighted)
                        out[slot, rows, cols] -= weighted
        return outs


def _system(laplacian: _GuidedLaplacian, stencil: np.ndarray, pixels: np.ndarray, diagonal: np.ndarray,
            known: np.ndarray | None = None, values: np.ndarray | None = None) -> tuple[sp.csc_matrix, np.ndarray]:
    """``L_PP + diag(diagonal)`` over ``pixels`` (flat, in that order) and ``-L_PK values_K``.

    ``known`` ``(H W,)`` bool marks the pixels whose ``values`` ``(H W, C)`` are given (none of
    ``pixels``). The matrix is symmetric, so its CSR arrays are also its CSC arrays (SuperLU's
    input). Couplings that vanish (windows outside the kept set, pixels off the image) are dropped.
    """
    h, w = laplacian.shape
    n = h * w
    m = len(pixels)
    flat = stencil.reshape(len(laplacian.couplings), n)
    position = np.full(n, -1, dtype=np.int32)  # row of each unknown pixel
    position[pixels] = np.arange(m, dtype=np.int32)
    given = np.zeros(0, dtype=np.int64) if known is None else np.flatnonzero(known)
    rank = np.full(n, -1, dtype=np.int32)  # column of each known pixel in L_PK
    rank[given] = np.arange(len(given), dtype=np.int32)
    reach = 2 * laplacian.radius
    neighbours = [(dy, dx) for dy in range(-reach, reach + 1) for dx in range(-reach, reach + 1)]
    data = np.empty((len(neighbours), m))
    columns = np.empty((len(neighbours), m), dtype=np.int32)
    known_columns = np.empty((len(neighbours), m), dtype=np.int32)
    for s, (dy, dx) in enumerate(neighbours):
        # A neighbour off the image has no window in common with the pixel: its stencil value is 0
        # (one wrapped to another row in the flat index too) and the entry is dropped below.
        neighbour = pixels + (dy * w + dx)
        beyond = (neighbour < 0) | (neighbour >= n)
        neighbour[beyond] = pixels[beyond]
        if (dy, dx) in laplacian._slot:
            data[s] = flat[laplacian._slot[dy, dx], pixels]
        else:
            data[s] = flat[laplacian._slot[-dy, -dx], neighbour]
        data[s, beyond] = 0.0
        columns[s] = position[neighbour]
        known_columns[s] = rank[neighbour]
    centre = neighbours.index((0, 0))
    data[centre] += diagonal
    columns[centre] = np.arange(m)
    nonzero = data != 0
    nonzero[centre] = True
    data, columns, known_columns, nonzero = data.T, columns.T, known_columns.T, nonzero.T  # row-major entries

    def compact(index: np.ndarray, size: int, kind: type) -> sp.spmatrix:
        keep = nonzero & (index >= 0)
        indptr = np.concatenate([[0], np.cumsum(keep.sum(axis=1))])
        return kind((data[keep], index[keep], indptr), shape=(m, size))

    matrix = compact(columns, m, sp.csc_matrix)  # symmetric: the CSR arrays are the CSC arrays
    matrix.sort_indices()
    channels = 0 if values is None else values.shape[1]
    rhs = np.zeros((m, channels))
    if len(given):
        rhs -= compact(known_columns, len(given), sp.csr_matrix) @ values[given]
    return matrix, rhs


def _dissection_order(pixels: np.ndarray, width: int, reach: int, *, leaf: int = 32) -> np.ndarray:
    """A nested-dissection elimination order of image pixels (George 1973) from their coordinates.

    Two pixels are coupled when both coordinates differ by at most ``reach``. A set of more than
    ``leaf`` pixels is split by ``reach`` consecutive rows (or columns), its separator: the cut
    through an empty stretch (no separator at all) leaving the most pixels on its smaller side if
    there is one, else the cut with the fewest separator pixels among those leaving at least a fifth
    of the set on each side (if any), with ties to the most balanced. Each half is ordered the same
    way, first, and the separator last, so that eliminating a half never fills the other; smaller
    sets keep their row-major order. All the sets of one level of the recursion are split at once.

    Parameters
    ----------
    pixels : (n,) int
        Flat indices (row-major) of the pixels in an image ``width`` pixels wide.
    width, reach : int

    Returns
    -------
    (n,) int64
        A permutation: eliminate ``pixels[order]`` in sequence.
    """
    pixels = np.asarray(pixels, dtype=np.int64)
    n = len(pixels)
    coordinates = np.divmod(pixels, width)  # rows, columns
    # Each pixel's path down the recursion as base-3 digits (0 first half, 1 second half, 2 the
    # separator, eliminated after both): sorting the paths, then the flat indices, is the order.
    path = np.zeros(n, dtype=np.int64)
    digits = np.zeros(n, dtype=np.int64)
    active = np.arange(n)  # pixels of the sets still to split, and their set
    group = np.zeros(n, dtype=np.int64)
    worst = np.iinfo(np.int64).max
    for _ in range(39):  # 3**39 < 2**63
        large = np.bincount(group)[group] > leaf
        active, group = active[large], group[large]
        if not len(active):
            break
        present = np.bincount(group) > 0
        group = (np.cumsum(present) - 1)[group]  # sets numbered 0..k-1
        k = int(present.sum())
        sizes = np.bincount(group, minlength=k)
        best = np.full(k, worst)
        best_axis, best_cut, lows = np.zeros(k, dtype=np.int64), np.zeros(k, dtype=np.int64), []
        for axis in (0, 1):
            coordinate = coordinates[axis][active]
            low, high = np.full(k, worst), np.full(k, -1)
            np.minimum.at(low, group, coordinate)
            np.maximum.at(high, group, coordinate)
            lows.append(low)
            span = high - low + 1
            start = np.cumsum(span) - span  # each set's stretch of the concatenated histograms
            below = np.concatenate([[0], np.cumsum(np.bincount(start[group] + coordinate - low[group],
                                                               minlength=int(span.sum())))])
            count = np.maximum(span - reach - 1, 0)  # cuts j: rows low+j .. low+j+reach-1 separate
            owner = np.repeat(np.arange(k), count)
            if not len(owner):
                continue
            j = np.arange(len(owner)) - np.repeat(np.cumsum(count) - count, count) + 1
            before = below[start[owner] + j] - below[start[owner]]
            separator = below[start[owner] + j + reach] - below[start[owner] + j]
            m = sizes[owner]
            smaller = np.minimum(before, m - before - separator)
            usable = smaller > 0
            rank = np.where(separator == 0, 0, np.where(5 * smaller >= m, 1, 2))  # free, balanced, other
            score = np.where(usable, (rank * (n + 1) + separator) * (n + 1) + (m - smaller), worst)
            lowest = np.full(k, worst)
            np.minimum.at(lowest, owner, score)
            hit = np.flatnonzero((score == lowest[owner]) & (score < best[owner]))
            hit = hit[np.unique(owner[hit], return_index=True)[1]]  # the first best cut of each set
            best[owner[hit]], best_axis[owner[hit]], best_cut[owner[hit]] = score[hit], axis, j[hit]
        split = (best < worst)[group]  # a set without a usable cut stays whole
        active, group = active[split], group[split]
        if not len(active):
            break
        axis = best_axis[group]
        relative = np.where(axis == 0, coordinates[0][active] - lows[0][group],
                            coordinates[1][active] - lows[1][group])
        cut = best_cut[group]
        part = np.where(relative < cut, 0, np.where(relative < cut + reach, 2, 1))
        path[active] = 3 * path[active] + part
        digits[active] += 1
        halves = part != 2
        active, group = active[halves], 2 * group[halves] + part[halves]
    if n:
        path *= 3 ** (digits.max() - digits)
    return np.lexsort((pixels, path))


# --------------------------------------------------------------------------------------------
# Solvers
# --------------------------------------------------------------------------------------------

#: Steps of iterative refinement a direct solve may take to bring its residual below ``rtol``.
REFINEMENT_STEPS = 3

#: Fill allowed to SciPy's incomplete LU (``spilu``'s ``fill_factor``) preconditioning ``solver="cg"``.
ILU_FILL = 10.0


@dataclass(frozen=True)
class SolveReport:
    """How one linear system of the matting was solved.

    Parameters
    ----------
    what : str
        The system, e.g. ``"sun visibility matting 'view_000'"``.
    solver : str
        ``"direct"`` (sparse LU), ``"cg"`` (preconditioned conjugate gradients), or ``"none"``
        (no unknown).
    unknowns : int
        Size of the system.
    channels : int
        Right-hand sides solved with the same matrix.
    converged : bool
        Every channel's relative residual ``||A x - b|| / ||b||`` is at most ``rtol``.
    n_iter : int
        Conjugate-gradient iterations (the largest over the channels), or refinement steps of a
        direct solve (0 when the first solution was accurate enough).
    residual : float
        Largest relative residual over the channels (0 for a zero right-hand side).
    seconds : float
        Wall-clock time of the solve (factorisation included).
    """

    what: str
    solver: str
    unknowns: int
    channels: int
    converged: bool
    n_iter: int
    residual: float
    seconds: float

    def to_dict(self) -> dict:
        """JSON-ready dictionary of the fields."""
        return dataclasses.asdict(self)


def _relative_residual(matrix: sp.spmatrix, x: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """``||rhs - matrix x|| / ||rhs||`` per column (0 where ``rhs`` is 0 and so is the residual)."""
    residual = np.linalg.norm(rhs - matrix @ x, axis=0)
    norm = np.linalg.norm(rhs, axis=0)
    return np.divide(residual, norm, out=np.where(residual > 0, np.inf, 0.0), where=norm > 0)


def _lu(matrix: sp.csc_matrix, *, ordered: bool, drop_tol: float | None = None):
    """SuperLU factor of a symmetric positive definite ``matrix``; incomplete with ``drop_tol``.

    No pivoting (``diag_pivot_thresh=0``, symmetric mode): a positive definite matrix needs none.
    The complete factor eliminates in the given order when ``ordered`` (nested dissection, see
    :func:`_dissection_order`), else in SuperLU's minimum degree order of ``A^T + A``; the
    incomplete one always in the latter (a nested-dissection order made a poorer preconditioner:
    53 iterations instead of 7 on a 1000x750 shading system).
    """
    options = {"diag_pivot_thresh": 0.0, "options": {"SymmetricMode": True}}
    if drop_tol is None:
        return spla.splu(matrix, permc_spec="NATURAL" if ordered else "MMD_AT_PLUS_A", **options)
    return spla.spilu(matrix, drop_tol=drop_tol, fill_factor=ILU_FILL, permc_spec="MMD_AT_PLUS_A", **options)


def _solve(matrix: sp.csc_matrix, rhs: np.ndarray, start: np.ndarray, config: MattingConfig, what: str, *,
           ordered: bool = False) -> tuple[np.ndarray, SolveReport]:
    """Solve the symmetric positive definite system ``matrix @ X = rhs`` (``(n, m)``).

    ``config.solver == "direct"``: one sparse LU factorisation (SuperLU, no pivoting) serves the
    ``m`` columns; its residual is checked against ``config.rtol`` and, above it, refined
    (:data:`REFINEMENT_STEPS`). ``"cg"``: conjugate gradients from ``start``, preconditioned by
    SciPy's incomplete LU (drop tolerance ``config.ichol_threshold``), the ``m`` columns in
    lockstep; each column stops once its residual norm is below ``config.rtol`` times its
    right-hand side's. A direct factorisation that fails (out of memory, or a pivot of exactly 0)
    falls back to ``"cg"``. A solve that misses ``rtol`` keeps its last iterate, logs a warning and
    says so in the report (``converged`` False).

    ``ordered`` says that the unknowns are already in a fill-reducing order
    (:func:`_dissection_order`); otherwise SuperLU orders them (minimum degree).
    """
    began = time.perf_counter()
    n, channels = rhs.shape
    if n == 0:
        return np.zeros((0, channels)), SolveReport(what, "none", 0, channels, True, 0, 0.0, 0.0)
    solver = config.solver
    x = steps = None
    if solver == "direct":
        try:
            factor = _lu(matrix, ordered=ordered)
        except (RuntimeError, MemoryError) as error:  # a zero pivot, or a factor too large
            logger.warning("%s: direct solve failed (%s); using conjugate gradients", what, error)
            solver = "cg"
        else:
            x = factor.solve(rhs)
            residual = _relative_residual(matrix, x, rhs)
            steps = 0
            while residual.max() > config.rtol and steps < REFINEMENT_STEPS:
                x += factor.solve(rhs - matrix @ x)
                residual = _relative_residual(matrix, x, rhs)
                steps += 1
    if solver == "cg":
        x, steps = _conjugate_gradients(matrix, rhs, start, config)
        residual = _relative_residual(matrix, x, rhs)
    converged = bool(residual.max() <= config.rtol)
    if not converged:
        limit = (f"{REFINEMENT_STEPS} refinement steps" if solver == "direct"
                 else f"{config.max_iter} conjugate-gradient iterations")
        logger.warning("%s: the %s solve stopped after %s without reaching rtol=%g on %d of %d channels "
                       "(largest relative residual %.3g); using the last iterate", what, solver, limit,
                       config.rtol, int((residual > config.rtol).sum()), channels, float(residual.max()))
    report = SolveReport(what, solver, int(n), int(channels), converged, int(steps), float(residual.max()),
                         time.perf_counter() - began)
    logger.debug("%s", report)
    return x, report


def _conjugate_gradients(matrix: sp.csc_matrix, rhs: np.ndarray, start: np.ndarray,
                         config: MattingConfig) -> tuple[np.ndarray, int]:
    """Block of independent preconditioned conjugate-gradient runs (Hestenes and Stiefel) in lockstep.

    Each iteration makes one sparse product and one application of the incomplete factor for all
    columns. Returns the iterate and the number of iterations of the slowest column.
    """
    try:
        factor = _lu(matrix, ordered=False, drop_tol=config.ichol_threshold)
        precondition = factor.solve
    except (RuntimeError, MemoryError) as error:
        logger.warning("incomplete LU failed (%s); conjugate gradients preconditioned by the diagonal", error)
        inverse = 1.0 / matrix.diagonal()[:, None]

        def precondition(residual: np.ndarray) -> np.ndarray:
            return inverse * residual

    x = np.array(start, dtype=np.float64, order="C")
    residual = rhs - matrix @ x
    target = config.rtol * np.linalg.norm(rhs, axis=0)
    active = np.linalg.norm(residual, axis=0) > target
    iterations = np.zeros(rhs.shape[1], dtype=np.int64)
    if active.any():
        z = precondition(residual)
        direction = z.copy()
        rz = np.einsum("ij,ij->j", residual, z)
        for _ in range(config.max_iter):
            product = matrix @ direction
            curvature = np.einsum("ij,ij->j", direction, product)
            step = np.divide(rz, curvature, out=np.zeros_like(rz), where=active & (curvature > 0))
            x += step * direction
            residual -= step * product
            iterations += active
            active &= np.linalg.norm(residual, axis=0) > target
            if not active.any():
                break
            z = precondition(residual)
            rz_next = np.einsum("ij,ij->j", residual, z)
            beta = np.divide(rz_next, rz, out=np.zeros_like(rz), where=active & (rz != 0))
            rz = rz_next
            direction = z + beta * direction
    return x, int(iterations.max())


def _diffuse(values: np.ndarray, band: np.ndarray, mask: np.ndarray, fallback: np.ndarray,
             config: MattingConfig, what: str) -> tuple[np.ndarray, SolveReport | None]:
    """Fill ``band`` by harmonic interpolation (4-neighbour graph Laplacian over ``mask``).

    Solves ``(D - W + delta I) x = W x_border + delta fallback`` on the band pixels, where ``W``
    links 4-neighbours both in ``mask`` and ``x_border`` are the values of the non-band neighbours.
    """
    out = values.copy()
    if not band.any():
        return out, None
    h, w = band.shape
    flat_band = band.ravel()
    pixels = np.flatnonzero(flat_band)
    pixels = pixels[_dissection_order(pixels, w, 1)]  # 4-neighbours: coupled within 1 px
    n = len(pixels)
    index = np.full(h * w, -1, dtype=np.int64)
    index[pixels] = np.arange(n)
    flat_values = values.reshape(h * w, -1)
    flat_mask = mask.ravel()
    pixel = np.arange(h * w).reshape(h, w)
    rows, cols, degree = [], [], np.zeros(n)
    start = fallback.reshape(h * w, -1)[pixels].astype(np.float64)
    rhs = config.prior_weight * start
    for a, b in ((pixel[:, :-1], pixel[:, 1:]), (pixel[:-1], pixel[1:])):
        a, b = a.ravel(), b.ravel()
        linked = flat_mask[a] & flat_mask[b] & (flat_band[a] | flat_band[b])
        a, b = a[linked], b[linked]
        for p, q in ((a, b), (b, a)):
            inner = flat_band[p]
            p, q = p[inner], q[inner]
            np.add.at(degree, index[p], 1.0)
            both = flat_band[q]
            rows.append(index[p[both]])
            cols.append(index[q[both]])
            np.add.at(rhs, index[p[~both]], flat_values[q[~both]])
    rows = np.concatenate(rows)
    cols = np.concatenate(cols)
    matrix = sp.csc_matrix((np.full(len(rows), -1.0), (rows, cols)), shape=(n, n))
    matrix = (matrix + sp.diags(degree + config.prior_weight, format="csc")).tocsc()
    solution, report = _solve(matrix, rhs, start, config, f"{what} (band diffusion)", ordered=True)
    out.reshape(h * w, -1)[pixels] = solution
    return out, report


def _ordered(pixels: np.ndarray, laplacian: _GuidedLaplacian) -> np.ndarray:
    """``pixels`` (flat) in the nested-dissection order of the Laplacian's coupling reach."""
    return pixels[_dissection_order(pixels, laplacian.shape[1], 2 * laplacian.radius)]


def _propagate(laplacian: _GuidedLaplacian, stencil: np.ndarray, values: np.ndarray, known: np.ndarray,
               mask: np.ndarray, band: np.ndarray, config: MattingConfig, what: str,
               start: np.ndarray | None = None) -> tuple[np.ndarray, list[SolveReport]]:
    """Image-guided propagation over ``mask & ~band``, then diffusion into ``band`` (module docstring).

    ``stencil`` is the Laplacian over the windows inside ``mask & ~band``.
    """
    h, w, channels = values.shape
    out = np.array(values, dtype=np.float64)
    known = known & mask & ~band
    if not known.any():
        raise ValueError(f"{what}: no constraint pixel inside the mask and outside the band")
    fallback = nearest_fill(np.where(known[..., None], out, 0.0), known).reshape(h * w, channels)
    free = mask & ~band
    flat = out.reshape(h * w, channels)
    guess = fallback if start is None else np.asarray(start, dtype=np.float64).reshape(h * w, channels)
    reports = []
    if config.constraint_weight is None:
        # Hard constraints (lambda -> infinity): (L_UU + delta I) x_U = -L_UK s_K + delta p_U.
        pixels = _ordered(np.flatnonzero(free & ~known), laplacian)
        if len(pixels):
            matrix, rhs = _system(laplacian, stencil, pixels, np.full(len(pixels), config.prior_weight),
                                  known=known.ravel(), values=flat)
            rhs += config.prior_weight * fallback[pixels]
            flat[pixels], report = _solve(matrix, rhs, guess[pixels], config, what, ordered=True)
            reports.append(report)
    else:
        # (L + lambda D_K + delta I) x = lambda D_K s + delta p over every pixel of mask & ~band.
        pixels = _ordered(np.flatnonzero(free), laplacian)
        constrained = known.ravel()[pixels]
        weight = np.where(constrained, config.constraint_weight, 0.0) + config.prior_weight
        matrix, _ = _system(laplacian, stencil, pixels, weight)
        rhs = (config.constraint_weight * np.where(constrained[:, None], flat[pixels], 0.0)
               + config.prior_weight * fallback[pixels])
        flat[pixels], report = _solve(matrix, rhs, np.where(constrained[:, None], flat[pixels], guess[pixels]),
                                      config, what, ordered=True)
        reports.append(report)
    out, report = _diffuse(out, band & mask, mask, fallback.reshape(h, w, channels), config, what)
    return out, reports + ([] if report is None else [report])
