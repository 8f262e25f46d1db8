r"""Colour Retinex baseline of Grosse, Johnson, Adelson and Freeman (ICCV 2009).

R. Grosse, M. K. Johnson, E. H. Adelson, W. T. Freeman, "Ground truth dataset and baseline
evaluations for intrinsic image algorithms", ICCV 2009 (the MIT intrinsic images paper), their
"color Retinex" baseline. This is an independent implementation (numpy / scipy.sparse) of the method as the
paper and its public reference code describe it:

1. Work on log images. Each pixel is floored at ``floor`` times the 99th percentile of the grey
   image over the mask, so that black pixels have a finite logarithm.
2. For every pair of 4-neighbours ``p -> q`` that both lie in the mask, take the gradient of the
   log colour image, :math:`d_c = \log I_c(q) - \log I_c(p)` for ``c`` in R, G, B, and split it
   into its grey part :math:`\bar d = \frac13 \sum_c d_c` (the gradient of the log of the
   geometric-mean brightness) and its chromatic part :math:`d_c - \bar d` (the gradient of the log
   chromaticity, RGB over their geometric mean; zero for a change of grey shading).
3. The gradient is a *reflectance* change if :math:`|\bar d| > t_{gray}` **or**
   :math:`\| d - \bar d \|_2 > t_{color}`; otherwise it is attributed to *shading*.
4. The grey log shading :math:`s` is the least-squares integral of the gradients of the log grey
   image (:math:`\log \frac13 \sum_c I_c`) at the shading edges, zero at the reflectance edges:
   :math:`\min_s \sum_{p \to q} (s_q - s_p - g_{pq})^2` over the edges inside the mask (a Poisson
   equation with Neumann boundary on the mask, :func:`poisson_integrate`).
5. The shading is grey, :math:`S = e^{s}` in all three channels, and the reflectance is
   :math:`R = I / S` per channel, so that ``R * S`` reproduces the (non-negative) image exactly.

**Scale.** The gradients fix :math:`s` only up to one additive constant per 4-connected component
of the mask. :func:`color_retinex` fixes it in two steps: within each component, the geometric mean
of the grey reflectance ``I_grey / S`` is made equal (to 1); then one global factor makes the 99th
percentile over the mask of the per-pixel maximum channel of ``R`` equal to 1 (the brightest
surfaces are white, the usual Retinex "white patch" normalisation; about 1 % of the masked pixels
then have a reflectance channel slightly above 1, which is kept so that ``R * S`` stays the image).
The LMSE of Grosse et al. rescales the estimate in every window, so it does not depend on this
choice.

**Thresholds.** Grosse et al. choose ``(t_gray, t_color)`` by hold-one-out cross-validation on
their data set, over a 5 x 5 grid ``10 ** linspace(-1.5, 0, 5)`` for each (:data:`THRESHOLD_GRID`).
The defaults here, ``t_gray = 1`` and ``t_color = 10 ** -1.5 ~ 0.032``
(:data:`DEFAULT_GRAY_THRESHOLD`, :data:`DEFAULT_COLOR_THRESHOLD`), are the point of that grid with
the lowest mean LMSE score ``(LMSE_R + LMSE_S) / 2`` over the six views of mvintrinsic's embedded
demo scene (the training scene; ``../shared/datasets/dev_courtyard`` was held out). The score varies
little over the grid (0.154 to 0.173 on the demo, 0.142 to 0.148 on dev_courtyard) and extending
the grid beyond its corner (``t_gray`` up to infinity, ``t_color`` down to 0.01) gained less than
0.001. In words: nearly every chromatic change, including the sun / sky colour change at shadow
boundaries, is taken as reflectance, and only very large pure-brightness steps (a factor of
``e ~ 2.7`` between neighbours) are. The thresholds are in log units, so they do not depend on the
exposure of the image.

Speed: the Poisson equation is solved by conjugate gradients preconditioned with the exact
Neumann-Laplacian solve of the full rectangle (a DCT), which converged in about ten iterations
in our tests for masks that cover most of the image; a 1000 x 750 image takes about a second.
"""

from __future__ import annotations

import warnings

import numpy as np
import scipy.fft
import scipy.ndimage
import scipy.sparse as sp
import scipy.sparse.linalg as spla

__all__ = [
    "DEFAULT_COLOR_THRESHOLD",
    "DEFAULT_FLOOR",
    "DEFAULT_GRAY_THRESHOLD",
    "THRESHOLD_GRID",
    "color_retinex",
    "poisson_integrate",
    "reflectance_edges",
]

#: Threshold values Grosse et al. cross-validate over, for both thresholds (log units).
THRESHOLD_GRID: tuple[float, ...] = tuple(float(t) for t in np.logspace(-1.5, 0.0, 5))
#: Default ``gray_threshold`` (``10 ** 0``, the top of :data:`THRESHOLD_GRID`), chosen on the demo scene.
DEFAULT_GRAY_THRESHOLD: float = THRESHOLD_GRID[4]
#: Default ``color_threshold`` (``10 ** -1.5``, the bottom of :data:`THRESHOLD_GRID`), chosen on the demo scene.
DEFAULT_COLOR_THRESHOLD: float = THRESHOLD_GRID[0]
#: Default ``floor``: pixels are floored at this fraction of the 99th percentile of the grey image.
DEFAULT_FLOOR: float = 1e-3

#: Weight of the ``eps * ||s||^2`` term that makes the Poisson system positive definite; the
#: per-component constant it leaves is reset afterwards, so it has no other effect.
_EPS = 1e-8


def _check_threshold(value: float, name: str) -> float:
    value = float(value)
    if not value >= 0:  # also rejects NaN
        raise ValueError(f"{name} must be a number >= 0 (inf disables its test), got {value!r}")
    return value


def reflectance_edges(
    log_rgb: np.ndarray, *, gray_threshold: float, color_threshold: float
) -> tuple[np.ndarray, np.ndarray]:
    """Classify the gradients of a log colour image as reflectance (True) or shading (False) changes.

    Parameters
    ----------
    log_rgb : (H, W, 3) array_like of float
        Logarithm of a linear RGB image (finite).
    gray_threshold : float
        Threshold on the absolute grey log gradient (mean of the three channel log gradients).
    color_threshold : float
        Threshold on the Euclidean norm of the chromatic part of the log gradient (the channel log
        gradients minus their mean).

    Returns
    -------
    along_x : (H, W - 1) ndarray of bool
        True where the step from ``[i, j]`` to ``[i, j + 1]`` is a reflectance change.
    along_y : (H - 1, W) ndarray of bool
        True where the step from ``[i, j]`` to ``[i + 1, j]`` is a reflectance change.
    """
    log_rgb = np.asarray(log_rgb, dtype=np.float64)
    if log_rgb.ndim != 3 or log_rgb.shape[2] != 3:
        raise ValueError(f"log_rgb must have shape (H, W, 3), got {log_rgb.shape}")
    gray_threshold = _check_threshold(gray_threshold, "gray_threshold")
    color_threshold = _check_threshold(color_threshold, "color_threshold")
    out = []
    for axis in (1, 0):
        d = np.diff(log_rgb, axis=axis)
        gray = d.mean(axis=2)
        chroma = np.linalg.norm(d - gray[..., None], axis=2)
        out.append((np.abs(gray) > gray_threshold) | (chroma > color_threshold))
    return out[0], out[1]


def _edge_lists(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Compressed pixel index and the (start, end) indices of the x and y edges inside ``mask``."""
    h, w = mask.shape
    index = np.full((h, w), -1, dtype=np.int64)
    index[mask] = np.arange(int(mask.sum()))
    in_x = mask[:, :-1] & mask[:, 1:]
    in_y = mask[:-1, :] & mask[1:, :]
    start = np.concatenate([index[:, :-1][in_x], index[:-1, :][in_y]])
    end = np.concatenate([index[:, 1:][in_x], index[1:, :][in_y]])
    return index, in_x, in_y, start, end


def poisson_integrate(
    grad_x: np.ndarray, grad_y: np.ndarray, mask: np.ndarray, *, rtol: float = 1e-7, maxiter: int = 2000
) -> np.ndarray:
    """Least-squares integration of a gradient field inside a mask.

    Solves :math:`\\min_s \\sum_{p \\to q} (s_q - s_p - g_{pq})^2` over the pairs of horizontal and
    vertical neighbours ``p -> q`` that both lie in ``mask`` (the Poisson equation
    :math:`\\Delta s = \\operatorname{div} g` with Neumann boundary conditions on the mask).

    Parameters
    ----------
    grad_x : (H, W - 1) array_like of float
        Target ``s[i, j + 1] - s[i, j]``.
    grad_y : (H - 1, W) array_like of float
        Target ``s[i + 1, j] - s[i, j]``.
    mask : (H, W) array_like of bool
        Pixels to solve for. Gradients touching a pixel outside the mask are ignored.
    rtol : float, optional
        Relative residual tolerance of the conjugate gradients.
    maxiter : int, optional
        Iteration limit of the conjugate gradients (a ``RuntimeWarning`` is issued if reached).

    Returns
    -------
    (H, W) ndarray of float64
        The integral, with zero mean over each 4-connected component of ``mask`` (the gradients
        fix it only up to one constant per component); 0 outside the mask.

    Notes
    -----
    Conjugate gradients on the normal equations :math:`(D^T D + \\epsilon I) s = D^T g`
    (:math:`\\epsilon = 10^{-8}`), preconditioned by the exact inverse of the Neumann Laplacian of
    the full rectangle, computed with a type-II DCT. Where the mask covers the whole image the
    preconditioner is the exact solution (one iteration).
    """
    mask = np.asarray(mask, dtype=bool)
    if mask.ndim != 2:
        raise ValueError(f"mask must be 2-D, got shape {mask.shape}")
    h, w = mask.shape
    grad_x = np.asarray(grad_x, dtype=np.float64)
    grad_y = np.asarray(grad_y, dtype=np.float64)
    if grad_x.shape != (h, w - 1) or grad_y.shape != (h - 1, w):
        raise ValueError(
            f"grad_x must have shape {(h, w - 1)} and grad_y {(h - 1, w)}, got {grad_x.shape} and {grad_y.shape}"
        )
    out = np.zeros((h, w))
    n = int(mask.sum())
    if n == 0:
        return out
    _, in_x, in_y, start, end = _edge_lists(mask)
    g = np.concatenate([grad_x[in_x], grad_y[in_y]])
    if not np.isfinite(g).all():
        raise ValueError("the gradients must be finite inside the mask")
    m = g.size
    rows = np.arange(m)
    d = sp.csr_matrix(
        (np.concatenate([-np.ones(m), np.ones(m)]), (np.concatenate([rows, rows]), np.concatenate([start, end]))),
        shape=(m, n),
    )
    a = (d.T @ d + _EPS * sp.identity(n, format="csr")).tocsr()
    rhs = d.T @ g
    if m and np.any(rhs):
        # Eigenvalues of the Neumann Laplacian of the full H x W grid (DCT-II basis); the constant
        # mode gets 1 instead of ~0: the preconditioner only has to be positive definite.
        lam = (2.0 - 2.0 * np.cos(np.pi * np.arange(h) / h))[:, None] + (2.0 - 2.0 * np.cos(np.pi * np.arange(w) / w))
        lam[0, 0] = 1.0
        full = np.zeros((h, w))

        def precondition(r: np.ndarray) -> np.ndarray:
            full[mask] = r
            return scipy.fft.idctn(scipy.fft.dctn(full, norm="ortho") / lam, norm="ortho")[mask]

        solution, info = spla.cg(
            a, rhs, rtol=rtol, maxiter=maxiter, M=spla.LinearOperator((n, n), precondition, dtype=np.float64)
        )
        if info > 0:
            warnings.warn(
                f"poisson_integrate: conjugate gradients stopped after {maxiter} iterations without reaching "
                f"rtol={rtol}",
                RuntimeWarning,
                stacklevel=2,
            )
        out[mask] = solution
    labels, count = scipy.ndimage.label(mask)
    if count:
        sums = np.bincount(labels[mask], weights=out[mask], minlength=count + 1)
        sizes = np.bincount(labels[mask], minlength=count + 1)
        out[mask] -= (sums / np.maximum(sizes, 1))[labels[mask]]
    return out


def color_retinex(
    image: np.ndarray,
    *,
    mask: np.ndarray | None = None,
    gray_threshold: float = DEFAULT_GRAY_THRESHOLD,
    color_threshold: float = DEFAULT_COLOR_THRESHOLD,
    floor: float = DEFAULT_FLOOR,
) -> tuple[np.ndarray, np.ndarray]:
    """Decompose a linear RGB image into reflectance and grey shading (colour Retinex, Grosse et al. 2009).

    Parameters
    ----------
    image : (H, W, 3) array_like of float
        Linear RGB image (any exposure: the thresholds act on log gradients). Negative values are
        treated as 0.
    mask : (H, W) array_like of bool, optional
        Pixels to decompose. Non-finite pixels are always excluded. Default: every finite pixel.
    gray_threshold : float, optional
        A log gradient whose grey part (mean over the channels) exceeds this in absolute value is a
        reflectance change. Default :data:`DEFAULT_GRAY_THRESHOLD` (``1.0``).
    color_threshold : float, optional
        A log gradient whose chromatic part (the channel log gradients minus their mean; Euclidean
        norm) exceeds this is a reflectance change. Default :data:`DEFAULT_COLOR_THRESHOLD`
        (``10 ** -1.5 ~ 0.0316``).
    floor : float, optional
        Pixels are floored at ``floor`` times the 99th percentile of the grey image over the mask
        before taking logarithms (for the gradients only; ``R * S`` reproduces the unfloored image).
        Default :data:`DEFAULT_FLOOR`.

    Returns
    -------
    reflectance : (H, W, 3) ndarray of float32
        ``image / shading``; 0 outside the mask.
    shading : (H, W, 3) ndarray of float32
        Grey shading (the three channels are equal), positive in the mask; 0 outside.

    Raises
    ------
    ValueError
        If ``image`` is not (H, W, 3), ``mask`` has another shape or selects no finite pixel, a
        threshold is negative or NaN (``inf`` is allowed: it disables that test), or ``floor`` is not
        a finite positive number.

    Notes
    -----
    The shading is defined by the gradients only up to a factor per 4-connected component of the
    mask. Within each component the geometric mean of the grey reflectance is set to 1; then one
    global factor makes the 99th percentile over the mask of ``reflectance.max(axis=2)`` equal to 1
    (the shading absorbs the inverse factors). See the module docstring for the whole method.
    """
    rgb = np.asarray(image, dtype=np.float64)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"image must have shape (H, W, 3), got {rgb.shape}")
    h, w = rgb.shape[:2]
    valid = np.isfinite(rgb).all(axis=2)
    if mask is not None:
        mask = np.asarray(mask)
        if mask.shape != (h, w):
            raise ValueError(f"mask must have shape {(h, w)}, got {mask.shape}")
        valid &= mask.astype(bool)
    if not valid.any():
        raise ValueError("the mask selects no finite pixel")
    gray_threshold = _check_threshold(gray_threshold, "gray_threshold")
    color_threshold = _check_threshold(color_threshold, "color_threshold")
    floor = float(floor)
    if not (np.isfinite(floor) and floor > 0):
        raise ValueError(f"floor must be a finite number > 0, got {floor!r}")

    rgb = np.where(valid[..., None], np.maximum(rgb, 0.0), 0.0)
    gray = rgb.mean(axis=2)
    reference = float(np.percentile(gray[valid], 99))
    lowest = floor * (reference if reference > 0 else 1.0)
    log_rgb = np.log(np.maximum(rgb, lowest))
    log_gray = np.log(np.maximum(gray, lowest))

    along_x, along_y = reflectance_edges(log_rgb, gray_threshold=gray_threshold, color_threshold=color_threshold)
    grad_x = np.where(along_x, 0.0, np.diff(log_gray, axis=1))
    grad_y = np.where(along_y, 0.0, np.diff(log_gray, axis=0))
    log_shading = poisson_integrate(grad_x, grad_y, valid)

    # One constant per component: geometric mean of the grey reflectance = 1.
    labels, count = scipy.ndimage.label(valid)
    offset = np.bincount(labels[valid], weights=(log_gray - log_shading)[valid], minlength=count + 1)
    offset /= np.maximum(np.bincount(labels[valid], minlength=count + 1), 1)
    log_shading[valid] += offset[labels[valid]]

    shading = np.where(valid, np.exp(log_shading), 0.0)
    reflectance = np.divide(rgb, shading[..., None], out=np.zeros_like(rgb), where=valid[..., None])
    white = float(np.percentile(reflectance.max(axis=2)[valid], 99))
    if white > 0:
        reflectance /= white
        shading *= white
    shading3 = np.repeat(shading[..., None], 3, axis=2)
    return reflectance.astype(np.float32), shading3.astype(np.float32)
