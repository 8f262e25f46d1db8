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
4. **Reflectance** (:func:`intrinsic_layers`): ``R = I / S_tot`` with
   ``S_tot = S_sky + S_ind + v_sun S_sun`` (Eq. 17).

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
highlights) keeps every window's colour variance below 1, where pymatting's closed-form inverse of
the 3x3 window covariance stays accurate (see ``epsilon`` in :class:`MattingConfig`). Pixels
outside the valid mask (sky, invalid) take part in no matting window: every window that touches
one is dropped from the Laplacian, so the sky neither pulls nor separates the image's values.

Solver
------
pymatting's [3]_ closed-form Laplacian (``cf_laplacian``, Levin's 3x3 windows) is built once per
view over the whole image; the Laplacian restricted to windows inside a pixel set is the full one
minus the windows that touch the set's complement (pymatting builds exactly those when asked with
``is_known``), so no window is computed in a second code path. Each system is solved by
preconditioned conjugate gradients with pymatting's thresholded incomplete Cholesky factorisation,
built once per system and shared by its channels (3 + 3 + 1 for the shading layers): the channels
run in lockstep, so that every iteration makes one sparse product and one pass of triangular
substitution (a small numba kernel, :func:`_cholesky_solve_block`) for all of them, 3x faster than
SciPy's ``cg`` one channel at a time with pymatting's one-vector substitution. The band diffusion
is a small sparse direct solve (SuperLU, all channels at once).

Measured on the six courtyard views (2 cores shared with another job, load average 2-2.5; labels
from the true visibility, mean-shift clusters): 2.5 s per view at 480x360 (1.6-3.3 s) and 15.6 s
per view at 1000x750 (12.2-20.7 s: Laplacian 0.4 s, visibility matte 1.2-1.7 s over 300 000
unknowns, shading propagation 10-19 s over 400 000 unknowns, of which the incomplete Cholesky
factorisation takes 4.6-5.3 s and 15-30 iterations the rest).

pymatting compiles its numba kernels when it is first imported (38 s on 2 cores, every kernel of
the package, plus 1 s for ours) and caches them next to the sources (``__pycache__``; numba falls
back to ``NUMBA_CACHE_DIR`` or a user cache when that is read-only); later imports load the
caches (0.5 s). pymatting is imported lazily, on the first matting call.

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

import contextlib
import io
import logging
import os
import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy import ndimage
from scipy.sparse import linalg as spla

from ._validation import as_array, config_or_default, describe, is_real
from .pixels import SHADING_FLOOR, PixelQuantities, layers_from_shading, nearest_fill
from .results import SHADOW_LABELS, IntrinsicLayers
from .scene import View
from .segmentation import boundary_band

__all__ = [
    "MattingConfig",
    "guide_image",
    "intrinsic_layers",
    "propagate",
    "shadow_transitions",
    "sun_visibility_matting",
]

logger = logging.getLogger(__name__)

_SHADOW, _UNDECIDED, _LIT = SHADOW_LABELS["shadow"], SHADOW_LABELS["undecided"], SHADOW_LABELS["lit"]


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
    epsilon : float
        Regularisation of the window colour covariance in the matting Laplacian, for images in
        [0, 1]. Levin et al. and pymatting use ``1e-7``; we use ``1e-6``: pymatting inverts the 3x3
        covariance by the cofactor formula, whose determinant cancels catastrophically when a
        window holds exactly two colours (rank 1) and ``epsilon`` is tiny (a noiseless two-colour
        edge leaked 0.32 across at ``1e-7``, 0.002 at ``1e-6``); on the courtyard views (noisy
        renders) both values give the same layers to 0.001 in ``v_sun`` error, and ``1e-6`` is
        20% faster (better conditioned).
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
    rtol : float
        Conjugate-gradient stopping rule: residual norm below ``rtol`` times the right-hand side's.
        Against a direct solve of a 480x360 shading system, ``1e-6`` leaves a largest error of 0.6%
        of the layer's range (0.14% at the 99th percentile); ``1e-5`` left 28% (1%).
    max_iter : int
        Largest number of conjugate-gradient iterations per channel (a warning is logged when it is
        reached and the last iterate is used).
    ichol_threshold : float
        Entries below this are dropped from the incomplete Cholesky preconditioner (pymatting's
        default 1e-4); larger is faster to factor but needs more iterations.
    shading_floor : float
        Total shading below this fraction of the view's median is raised to it through ``S_ind``,
        so that ``R = I / S_tot`` stays finite (as ``pipeline.step2_layers``: ``1e-3``).
    """

    trimap_radius: int = 3
    visibility_cluster_width: int = 1
    cluster_boundary_width: int = 3
    shadow_band_radius: int = 3
    epsilon: float = 1e-6
    window_radius: int = 1
    constraint_weight: float | None = None
    prior_weight: float = 1e-5
    white_percentile: float = 99.9
    rtol: float = 1e-6
    max_iter: int = 2000
    ichol_threshold: float = 1e-4
    shading_floor: float = SHADING_FLOOR

    def __post_init__(self) -> None:
        for name, least in (("trimap_radius", 1), ("visibility_cluster_width", 0), ("cluster_boundary_width", 0),
                            ("shadow_band_radius", 0), ("window_radius", 1), ("max_iter", 1)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
                raise ValueError(f"{name} must be an integer >= {least}, got {value!r}")
        for name in ("epsilon", "constraint_weight", "prior_weight", "rtol", "ichol_threshold", "shading_floor"):
            value = getattr(self, name)
            if name == "constraint_weight" and value is None:
                continue
            if not is_real(value) or not 0 < value < np.inf:
                raise ValueError(f"{name} must be a positive finite number, got {value!r}")
        if not is_real(self.white_percentile) or not 0 < self.white_percentile <= 100:
            raise ValueError(f"white_percentile must lie in (0, 100], got {self.white_percentile!r}")
        if not self.rtol < 1:
            raise ValueError(f"rtol must be below 1, got {self.rtol!r}")
        if not self.shading_floor < 1:
            raise ValueError(f"shading_floor must be below 1, got {self.shading_floor!r}")


# --------------------------------------------------------------------------------------------
# Input checks
# --------------------------------------------------------------------------------------------


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


def _import_numba():
    """Import numba with a threading layer that does not clash with open3d's bundled TBB.

    open3d loads its own libtbb (interface 12050); numba's default threading-layer probe then finds
    a TBB it refuses and emits a ``NumbaWarning`` on the first parallel kernel. Unless the user
    chose a layer (``NUMBA_THREADING_LAYER``), take the always-available ``workqueue`` layer.
    """
    import numba

    if numba.config.THREADING_LAYER == "default" and "NUMBA_THREADING_LAYER" not in os.environ:
        numba.config.THREADING_LAYER = "workqueue"
    return numba


class _GuidedLaplacian:
    """The closed-form matting Laplacian of one guide image, built once, restricted on demand.

    ``inside(keep)`` is the Laplacian of the windows lying wholly inside ``keep``: Levin's
    ``L = sum_w L_w`` over windows ``w``, where pymatting's ``is_known`` option builds the sum over
    the windows that touch the complement of a set; the difference of the two sums is the one we
    want. Entries of pixels outside ``keep`` vanish: every window through them touches ``~keep``.
    """

    def __init__(self, guide: np.ndarray, config: MattingConfig) -> None:
        _import_numba()
        from pymatting.laplacian.cf_laplacian import cf_laplacian  # lazy: numba compiles on first import

        self._cf = cf_laplacian
        self._guide = guide
        self._epsilon = float(config.epsilon)
        self._radius = int(config.window_radius)
        h, w = guide.shape[:2]
        self.shape = (h, w)
        self._full = self._build(None)
        # pymatting stores every pixel's (4r + 1)^2 neighbour slots, those outside the image as
        # explicit zeros in column 0; keep the in-image slots only (their columns are sorted).
        span = np.arange(-2 * self._radius, 2 * self._radius + 1)
        rows, cols = np.divmod(np.arange(h * w), w)
        in_rows = (0 <= rows[:, None] + span) & (rows[:, None] + span < h)
        in_cols = (0 <= cols[:, None] + span) & (cols[:, None] + span < w)
        self._slots = (in_rows[:, :, None] & in_cols[:, None, :]).ravel()
        counts = self._slots.reshape(h * w, -1).sum(axis=1)
        self._indptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        self._indices = self._full.indices[self._slots].astype(np.int64)

    def _build(self, is_known: np.ndarray | None) -> sp.csr_matrix:
        known = None if is_known is None else np.ascontiguousarray(is_known, dtype=np.bool_)
        return self._cf(self._guide, epsilon=self._epsilon, radius=self._radius, is_known=known)

    def inside(self, keep: np.ndarray) -> sp.csr_matrix:
        """``(H W, H W)`` CSR Laplacian of the windows wholly inside ``keep`` (pixels in row-major order)."""
        data = self._full.data
        if not keep.all():
            data = data - self._build(keep).data
        n = self.shape[0] * self.shape[1]
        return sp.csr_matrix((data[self._slots], self._indices, self._indptr), shape=(n, n))


#: Diagonal shifts tried, in order, by the incomplete Cholesky factorisation (pymatting's list
#: without its leading 0: the unshifted thresholded factorisation broke down on every shading system
#: of the courtyard views, and the failed attempt cost as much as a factorisation). The shift
#: changes the preconditioner only, never the system solved.
ICHOL_SHIFTS = (1e-4, 1e-3, 1e-2, 0.1, 0.5, 1.0, 10.0, 100.0, 1e3, 1e4, 1e5)


def _cholesky_solve_block(data: np.ndarray, indices: np.ndarray, indptr: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """``(L L^T)^-1 rhs`` for a lower-triangular CSC factor ``L`` and ``rhs`` of shape ``(n, m)``.

    pymatting's ``CholeskyDecomposition`` substitutes one vector at a time; here each factor entry
    is read once for all ``m`` columns (4.6x faster for the 7 shading channels at 1000x750).
    Compiled with numba on first use (:func:`_block_substitution`).
    """
    n, m = rhs.shape
    x = rhs.copy()
    for j in range(n):  # forward: L y = rhs (column-oriented)
        start = indptr[j]
        diagonal = data[start]
        for c in range(m):
            x[j, c] /= diagonal
        for k in range(start + 1, indptr[j + 1]):
            i = indices[k]
            value = data[k]
            for c in range(m):
                x[i, c] -= value * x[j, c]
    for i in range(n - 1, -1, -1):  # backward: L^T x = y (row i of L^T is column i of L)
        start = indptr[i]
        for k in range(start + 1, indptr[i + 1]):
            j = indices[k]
            value = data[k]
            for c in range(m):
                x[i, c] -= value * x[j, c]
        diagonal = data[start]
        for c in range(m):
            x[i, c] /= diagonal
    return x


_COMPILED: dict[str, object] = {}


def _block_substitution():
    """:func:`_cholesky_solve_block` compiled by numba (cached on disk, like pymatting's kernels)."""
    if "solve" not in _COMPILED:
        numba = _import_numba()
        _COMPILED["solve"] = numba.njit(cache=True, nogil=True)(_cholesky_solve_block)
    return _COMPILED["solve"]


def _preconditioner(matrix: sp.csr_matrix, config: MattingConfig):
    """``M^-1`` of pymatting's thresholded incomplete Cholesky factorisation ``M = L L^T`` of ``matrix``."""
    _import_numba()
    from pymatting.preconditioner.ichol import ichol

    # ichol prints a "PERFORMANCE WARNING" to stdout when it needs a larger shift; route it to the
    # log (the core never prints).
    with contextlib.redirect_stdout(io.StringIO()) as printed:
        factor = ichol(matrix.T.tocsc(), discard_threshold=config.ichol_threshold,  # symmetric: A^T = A
                       shifts=list(ICHOL_SHIFTS))
    if printed.getvalue().strip():
        logger.debug("pymatting ichol: %s", " ".join(printed.getvalue().split()))
    data, indices, indptr = factor.Ltuple
    logger.debug("ichol: %d unknowns, %d entries in A, %d in the factor", matrix.shape[0], matrix.nnz, len(data))
    solve = _block_substitution()

    def apply(residual: np.ndarray) -> np.ndarray:
        return solve(data, indices, indptr, np.ascontiguousarray(residual, dtype=np.float64))

    return apply


def _solve(matrix: sp.csr_matrix, rhs: np.ndarray, start: np.ndarray, config: MattingConfig, what: str) -> np.ndarray:
    """Solve the SPD system ``matrix @ X = rhs`` (``(n, m)``) by preconditioned conjugate gradients.

    The ``m`` columns are independent conjugate-gradient runs (Hestenes and Stiefel, with the
    incomplete Cholesky preconditioner ``M``) advanced in lockstep so that each iteration makes one
    sparse product and one triangular substitution for all columns; a column stops once its residual
    norm is below ``config.rtol`` times its right-hand side's. A column still above after
    ``config.max_iter`` iterations keeps its last iterate, with a logged warning.
    """
    began = time.perf_counter()
    precondition = _preconditioner(matrix, config)
    factored = time.perf_counter()
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
    if active.any():
        logger.warning("%s: conjugate gradients stopped after %d iterations without reaching rtol=%g on "
                       "%d of %d channels; using the last iterate", what, config.max_iter, config.rtol,
                       int(active.sum()), len(active))
    logger.debug("%s: %d unknowns, ichol %.2f s, cg %.2f s, iterations %s", what, matrix.shape[0],
                 factored - began, time.perf_counter() - factored, iterations.tolist())
    return x


def _diffuse(values: np.ndarray, band: np.ndarray, mask: np.ndarray, fallback: np.ndarray,
             config: MattingConfig) -> np.ndarray:
    """Fill ``band`` by harmonic interpolation (4-neighbour graph Laplacian over ``mask``).

    Solves ``(D - W + delta I) x = W x_border + delta fallback`` on the band pixels, where ``W``
    links 4-neighbours both in ``mask`` and ``x_border`` are the values of the non-band neighbours.
    """
    out = values.copy()
    if not band.any():
        return out
    h, w = band.shape
    index = np.full(h * w, -1, dtype=np.int64)
    flat_band = band.ravel()
    index[flat_band] = np.arange(int(flat_band.sum()))
    n = int(flat_band.sum())
    flat_values = values.reshape(h * w, -1)
    flat_mask = mask.ravel()
    pixel = np.arange(h * w).reshape(h, w)
    rows, cols, degree = [], [], np.zeros(n)
    rhs = config.prior_weight * fallback.reshape(h * w, -1)[flat_band].astype(np.float64)
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
    matrix = matrix + sp.diags(degree + config.prior_weight, format="csc")
    solution = spla.splu(matrix).solve(rhs)
    out.reshape(h * w, -1)[flat_band] = solution
    return out


def _propagate(laplacian: _GuidedLaplacian, values: np.ndarray, known: np.ndarray, mask: np.ndarray,
               band: np.ndarray, config: MattingConfig, what: str, start: np.ndarray | None = None) -> np.ndarray:
    """Image-guided propagation over ``mask & ~band``, then diffusion into ``band`` (module docstring)."""
    h, w, channels = values.shape
    out = np.array(values, dtype=np.float64)
    known = known & mask & ~band
    if not known.any():
        raise ValueError(f"{what}: no constraint pixel inside the mask and outside the band")
    fallback = nearest_fill(np.where(known[..., None], out, 0.0), known).reshape(h * w, channels)
    free = mask & ~band
    flat = out.reshape(h * w, channels)
    guess = fallback if start is None else np.asarray(start, dtype=np.float64).reshape(h * w, channels)
    lap = laplacian.inside(free)
    if config.constraint_weight is None:
        # Hard constraints (lambda -> infinity): L_UU x_U = -L_UK s_K (+ delta (p_U - x_U)).
        u, k = np.flatnonzero(free & ~known), np.flatnonzero(known)
        if len(u):
            rows = lap[u]
            matrix = (rows[:, u] + sp.diags(np.full(len(u), config.prior_weight), format="csr")).tocsr()
            rhs = -(rows[:, k] @ flat[k]) + config.prior_weight * fallback[u]
            flat[u] = _solve(matrix, rhs, guess[u], config, what)
    else:
        # (L + lambda D_K + delta I) x = lambda D_K s + delta p over every pixel of mask & ~band.
        pixels = np.flatnonzero(free)
        constrained = known.ravel()[pixels]
        weight = np.where(constrained, config.constraint_weight, 0.0) + config.prior_weight
        matrix = (lap[pixels][:, pixels] + sp.diags(weight, format="csr")).tocsr()
        rhs = (config.constraint_weight * np.where(constrained[:, None], flat[pixels], 0.0)
               + config.prior_weight * fallback[pixels])
        flat[pixels] = _solve(matrix, rhs, np.where(constrained[:, None], flat[pixels], guess[pixels]), config, what)
    return _diffuse(out, band & mask, mask, fallback.reshape(h, w, channels), config)


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


def _matte(laplacian: _GuidedLaplacian, labels: np.ndarray, mask: np.ndarray, clusters: np.ndarray | None,
           config: MattingConfig) -> np.ndarray:
    """Closed-form matte of ``v_sun`` (float64, 0 outside ``mask``) from the label trimap."""
    unknown = _trimap_unknown(labels, mask, config.trimap_radius)
    if clusters is not None and config.visibility_cluster_width > 0:
        unknown |= boundary_band(np.where(mask, clusters, -1), config.visibility_cluster_width)
    known = mask & ~unknown
    visibility = np.where(mask & (labels == _LIT), 1.0, 0.0)
    if not unknown.any():
        return visibility
    if not known.any():
        logger.warning("sun visibility matting: no labelled pixel outside the trimap band; keeping the labels")
        return np.where(mask & (labels == _UNDECIDED), 0.5, visibility)
    fallback = nearest_fill(visibility, known).ravel()
    u, k = np.flatnonzero(unknown), np.flatnonzero(known)
    rows = laplacian.inside(mask)[u]
    # Levin et al. with the known pixels as Dirichlet values (as pymatting's estimate_alpha_cf):
    # L_UU v_U = -L_UK v_K, plus the weak pull delta (p_U - v_U) that keeps L_UU definite.
    matrix = (rows[:, u] + sp.diags(np.full(len(u), config.prior_weight), format="csr")).tocsr()
    rhs = -(rows[:, k] @ visibility.ravel()[k]) + config.prior_weight * fallback[u]
    solution = _solve(matrix, rhs[:, None], fallback[u][:, None], config, "sun visibility matting")[:, 0]
    visibility.ravel()[u] = np.clip(solution, 0.0, 1.0)
    return visibility


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
    """Soft sun visibility from binary shadow labels by closed-form matting (Sec. 6.2, [2]_).

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
    return _matte(laplacian, labels, valid, clusters, config).astype(np.float32)


def propagate(
    image: np.ndarray,
    values: np.ndarray,
    known: np.ndarray,
    *,
    mask: np.ndarray | None = None,
    band: np.ndarray | None = None,
    config: MattingConfig | None = None,
) -> np.ndarray:
    """Image-guided propagation of values from constraint pixels (Sec. 6.2, after Levin et al. [2]_).

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
    out = _propagate(laplacian, array, constraint, valid, band & valid, config, "propagation")
    return out[..., 0] if squeeze else out


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
       filled by diffusion (:func:`propagate`); one Laplacian for both steps;
    3. ``S_sun = L_sun max(0, cos)`` (Eq. 3), ``S_tot = S_sky + S_ind + v_sun S_sun`` (Eq. 17) and
       ``R = I / S_tot``. Propagated shading is clipped at 0 (the matting Laplacian can overshoot)
       and the cosine to [0, 1]. As in ``pipeline.step2_layers``, where ``S_tot`` is below
       ``config.shading_floor`` times the view's median, ``S_ind`` is raised to reach it, so ``R``
       stays finite and ``R * S_tot`` reproduces the image.

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
    began = time.perf_counter()
    if valid.any():
        laplacian = _GuidedLaplacian(guide_image(image, mask=valid, white_percentile=config.white_percentile), config)
        built = time.perf_counter()
        visibility = _matte(laplacian, labels, valid, clusters, config)
        matted = time.perf_counter()
        band = valid & _near(shadow_transitions(labels, mask=valid), config.shadow_band_radius)
        constraints = valid & ~quantities.filled & ~band
        if clusters is not None:
            constraints &= ~boundary_band(np.where(valid, clusters, -1), config.cluster_boundary_width)
        stacked = np.concatenate([sky, indirect, cosine[..., None]], axis=2)
        if constraints.any():
            stacked = _propagate(laplacian, stacked, constraints, valid, band, config,
                                 f"shading propagation {view.stem!r}", start=stacked)
        else:
            logger.warning("view %r: no proxy pixel left as a constraint; shading layers are the Step-1 values",
                           view.stem)
        sky = np.maximum(stacked[..., 0:3], 0.0)
        indirect = np.maximum(stacked[..., 3:6], 0.0)
        cosine = np.clip(stacked[..., 6], 0.0, 1.0)
        logger.info("view %r: Laplacian %.2f s, visibility matte %.2f s, shading propagation %.2f s", view.stem,
                    built - began, matted - built, time.perf_counter() - matted)
    return layers_from_shading(view, valid, sky, indirect, visibility, cosine, radiance, labels,  # Eqs. 3, 17
                               floor=config.shading_floor)
