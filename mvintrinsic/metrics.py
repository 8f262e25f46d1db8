"""Error metrics for intrinsic image decompositions and shadow masks.

All functions are pure: they take NumPy arrays, never modify them, and
return a Python ``float``.  Images are ``(H, W)`` or ``(H, W, C)`` real
arrays (typically linear RGB, ``C = 3``); masks are ``(H, W)`` boolean
arrays in which ``True`` marks a pixel that counts.  Values outside the
mask never influence any result (they may be NaN or infinite); non-finite
values *inside* the mask raise :class:`ValueError`.

Metrics
-------
lmse
    Local, scale-invariant mean squared error of Grosse et al. [1]_, with
    the normalisation of Bell et al. [2]_.
lmse_score
    Grosse et al.'s decomposition score, the mean of the LMSE of the
    reflectance and of the shading [1]_.
si_mse
    Global scale-invariant mean squared error (Grosse et al. [1]_, Eq. 7),
    normalised by the energy of the ground truth.
balanced_error_rate
    Balanced error rate of a binary shadow mask, as used to evaluate
    shadow detectors (e.g. Vicente et al. [3]_).
psnr
    Peak signal-to-noise ratio over the masked pixels [4]_.
ssim
    Structural similarity index of Wang et al. [5]_ averaged over the
    masked pixels.

These are the measures used to compare decompositions of outdoor scenes
such as those of Duchêne et al. [6]_ against ground truth.

References
----------
.. [1] R. Grosse, M. K. Johnson, E. H. Adelson and W. T. Freeman,
   "Ground truth dataset and baseline evaluations for intrinsic image
   algorithms", in *Proceedings of the IEEE International Conference on
   Computer Vision (ICCV)*, pp. 2335-2342, 2009.
.. [2] S. Bell, K. Bala and N. Snavely, "Intrinsic Images in the Wild",
   *ACM Transactions on Graphics (Proc. SIGGRAPH)*, 33(4), article 159,
   2014.
.. [3] T. F. Y. Vicente, L. Hou, C.-P. Yu, M. Hoai and D. Samaras,
   "Large-scale training of shadow detectors with noisily-annotated
   shadow examples", in *Proceedings of the European Conference on
   Computer Vision (ECCV)*, pp. 816-832, 2016.
.. [4] Q. Huynh-Thu and M. Ghanbari, "Scope of validity of PSNR in
   image/video quality assessment", *Electronics Letters*, 44(13),
   pp. 800-801, 2008.
.. [5] Z. Wang, A. C. Bovik, H. R. Sheikh and E. P. Simoncelli, "Image
   quality assessment: from error visibility to structural similarity",
   *IEEE Transactions on Image Processing*, 13(4), pp. 600-612, 2004.
.. [6] S. Duchêne, C. Riant, G. Chaurasia, J. Lopez-Moreno, P.-Y. Laffont,
   S. Popov, A. Bousseau and G. Drettakis, "Multi-View Intrinsic Images of
   Outdoors Scenes with an Application to Relighting", *ACM Transactions
   on Graphics*, 34(5), article 164, 2015.
"""

import operator
import warnings

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from skimage.metrics import structural_similarity

__all__ = [
    "lmse",
    "lmse_score",
    "si_mse",
    "balanced_error_rate",
    "balanced_error_floor",
    "psnr",
    "ssim",
]

#: Threshold on ``sum(mask * estimate**2)`` below which a window's scale
#: ``alpha`` is set to 0, exactly as in the reference LMSE code of
#: Grosse et al. (2009) and Bell et al. (2014).
_LMSE_ALPHA_THRESHOLD = 1e-5

#: Number of residual values materialised at once by `lmse` (memory bound).
_LMSE_CHUNK_ELEMENTS = 1 << 20

#: Side of the (uniform) SSIM window used by scikit-image by default.
_SSIM_WIN_SIZE = 7


# ---------------------------------------------------------------------------
# Input validation
# ---------------------------------------------------------------------------


def _as_image(array, name):
    """Return `array` as a float64 ``(H, W, C)`` array (a view or a copy).

    Raises TypeError for non-real dtypes and ValueError for bad shapes.
    The returned array is never written to by this module.
    """
    arr = np.asarray(array)
    if arr.dtype == np.bool_ or not (np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.floating)):
        raise TypeError(
            f"`{name}` must be a real-valued (integer or floating-point) "
            f"array of shape (H, W) or (H, W, C); got dtype {arr.dtype}"
        )
    if arr.ndim not in (2, 3):
        raise ValueError(f"`{name}` must have shape (H, W) or (H, W, C); got shape {arr.shape}")
    if 0 in arr.shape:
        raise ValueError(f"`{name}` must be non-empty with shape (H, W) or (H, W, C); got shape {arr.shape}")
    arr = arr.astype(np.float64, copy=False)
    if arr.ndim == 2:
        arr = arr[:, :, np.newaxis]
    return arr


def _as_mask(mask, shape_hw, name="mask", reference="estimate"):
    """Validate `mask` against the spatial shape `shape_hw`.

    ``None`` becomes an all-True mask.  The mask must be boolean, of shape
    ``shape_hw`` and contain at least one True pixel.
    """
    if mask is None:
        return np.ones(shape_hw, dtype=bool)
    m = np.asarray(mask)
    if m.dtype != np.bool_:
        raise TypeError(
            f"`{name}` must be a boolean array of shape {shape_hw} "
            f"(True = pixel counts); got dtype {m.dtype}. "
            f"Convert explicitly, e.g. `{name}.astype(bool)`."
        )
    if m.shape != tuple(shape_hw):
        raise ValueError(
            f"`{name}` must have shape (H, W) = {tuple(shape_hw)} to match `{reference}`; got shape {m.shape}"
        )
    if not m.any():
        raise ValueError(f"`{name}` selects no pixel (all False, shape {m.shape}); at least one pixel must be True")
    return m


def _check_same_shape(a, b, name_a, name_b):
    if a.shape != b.shape:
        raise ValueError(
            f"`{name_a}` and `{name_b}` must have the same shape; "
            f"got {name_a}.shape={a.shape} and {name_b}.shape={b.shape}"
        )


def _check_finite_in_mask(arr, mask, name):
    """Raise ValueError if `arr` (H, W, C) is non-finite where `mask`."""
    finite = np.isfinite(arr)
    if finite.all():
        return
    bad = ~finite & mask[:, :, np.newaxis]
    if bad.any():
        n_bad = int(bad.any(axis=2).sum())
        raise ValueError(
            f"`{name}` contains non-finite values (NaN or inf) at {n_bad} "
            "pixel(s) inside the mask; only pixels outside the mask may be "
            "non-finite"
        )


def _validated_pair(estimate, truth, mask, est_name, truth_name):
    """Validate an (estimate, truth, mask) triple.

    Returns ``(e, t, m)`` where `e` and `t` are float64 ``(H, W, C)``
    arrays with every pixel outside the mask set to 0 (new arrays, the
    inputs are untouched) and `m` is the ``(H, W)`` boolean mask.  Also
    returns whether the input was 2-D.
    """
    e_raw = np.asarray(estimate)
    t_raw = np.asarray(truth)
    e = _as_image(e_raw, est_name)
    t = _as_image(t_raw, truth_name)
    _check_same_shape(e_raw, t_raw, est_name, truth_name)
    m = _as_mask(mask, e.shape[:2], reference=est_name)
    _check_finite_in_mask(e, m, est_name)
    _check_finite_in_mask(t, m, truth_name)
    # Zero the masked-out pixels into new arrays stored channel-first
    # (C, H, W) -- the layout the LMSE reductions want -- and return
    # (H, W, C) views of them.
    m_cf = m[np.newaxis]
    e_cf = np.zeros((e.shape[2],) + e.shape[:2])
    t_cf = np.zeros_like(e_cf)
    np.copyto(e_cf, e.transpose(2, 0, 1), where=m_cf)
    np.copyto(t_cf, t.transpose(2, 0, 1), where=m_cf)
    return e_cf.transpose(1, 2, 0), t_cf.transpose(1, 2, 0), m, e_raw.ndim == 2


def _positive_int(value, name):
    if isinstance(value, (bool, np.bool_)):
        raise TypeError(f"`{name}` must be an integer >= 1; got {value!r}")
    try:
        ivalue = operator.index(value)
    except TypeError:
        raise TypeError(f"`{name}` must be an integer >= 1; got {value!r} of type {type(value).__name__}") from None
    if ivalue < 1:
        raise ValueError(f"`{name}` must be an integer >= 1; got {ivalue}")
    return ivalue


def _data_range(data_range, t, m, truth_name):
    """Return a validated data range (float > 0)."""
    if data_range is not None:
        try:
            dr = float(data_range)
        except (TypeError, ValueError):
            raise TypeError(f"`data_range` must be a positive finite number or None; got {data_range!r}") from None
        if not np.isfinite(dr) or dr <= 0:
            raise ValueError(f"`data_range` must be a positive finite number or None; got {data_range!r}")
        return dr
    vals = t[m]  # (n_masked, C)
    dr = float(vals.max() - vals.min())
    if dr <= 0:
        raise ValueError(
            f"cannot infer `data_range`: `{truth_name}` is constant "
            f"({float(vals.max())!r}) inside the mask; pass `data_range` "
            "explicitly"
        )
    return dr


# ---------------------------------------------------------------------------
# LMSE
# ---------------------------------------------------------------------------


def _lmse_validated(e, t, window, step, est_name, truth_name):
    """LMSE of validated, mask-zeroed ``(H, W, C)`` arrays.

    Out-of-mask pixels are 0 in both `e` and `t`, so the mask factor of
    every sum is implicit.
    """
    H, W, C = e.shape
    if window > H or window > W:
        raise ValueError(
            f"`window` ({window}) must not exceed the image size; `{est_name}` has spatial shape (H, W) = ({H}, {W})"
        )
    # Channel-first contiguous arrays (no copy when they come from
    # _validated_pair) make the window rows contiguous, which makes the
    # reductions below several times faster.
    e_cf = np.ascontiguousarray(e.transpose(2, 0, 1))
    t_cf = np.ascontiguousarray(t.transpose(2, 0, 1))
    # Views of shape (C, nI, nJ, window, window); windows start at
    # 0, step, 2*step, ... while start + window <= size.
    e_win = sliding_window_view(e_cf, (window, window), axis=(1, 2))[:, ::step, ::step]
    t_win = sliding_window_view(t_cf, (window, window), axis=(1, 2))[:, ::step, ::step]
    s_ee = np.einsum("cijxy,cijxy->cij", e_win, e_win)
    s_te = np.einsum("cijxy,cijxy->cij", t_win, e_win)
    s_tt = np.einsum("cijxy,cijxy->cij", t_win, t_win)

    use = s_ee > _LMSE_ALPHA_THRESHOLD
    alpha = np.zeros_like(s_ee)
    np.divide(s_te, s_ee, out=alpha, where=use)
    # Residual formed explicitly (not as s_tt - s_te**2 / s_ee) to avoid
    # cancellation: a perfect estimate then gives 0 up to rounding.  It is
    # materialised a few rows of windows at a time to bound memory (the
    # windows overlap, so all of them together are (window/step)^2 times
    # the image).
    n_i = e_win.shape[1]
    rows = max(1, _LMSE_CHUNK_ELEMENTS // e_win[0, :1].size)
    ssq = np.zeros(C)
    for c in range(C):
        for i0 in range(0, n_i, rows):
            sl = slice(i0, i0 + rows)
            resid = e_win[c, sl] * alpha[c, sl, :, np.newaxis, np.newaxis]
            np.subtract(t_win[c, sl], resid, out=resid)
            ssq[c] += np.einsum("ijxy,ijxy->", resid, resid)
    total = s_tt.sum(axis=(1, 2))  # (C,)

    if np.any(total <= 0):
        bad = [int(c) for c in np.flatnonzero(total <= 0)]
        raise ValueError(
            f"LMSE is undefined: `{truth_name}` has zero energy "
            f"(sum(mask * {truth_name}**2) == 0) inside every window for "
            f"channel(s) {bad}; windows are {window}x{window} with step "
            f"{step} on an image of spatial shape ({H}, {W})"
        )
    return float(np.mean(ssq / total))


def lmse(estimate, truth, *, mask=None, window=20, step=10):
    r"""Local mean squared error (LMSE) of Grosse et al. (2009).

    The image is covered by ``window x window`` windows whose top-left
    corners are at rows and columns ``0, step, 2*step, ...`` as long as the
    window fits entirely inside the image.  Inside each window the estimate
    is rescaled by the least-squares factor that best fits the ground
    truth; the rescaled squared errors and the squared ground truth are
    both summed over all windows and their ratio is returned.

    Parameters
    ----------
    estimate : (H, W) or (H, W, C) array_like of float
        Estimated image (e.g. reflectance or shading), linear values.
    truth : (H, W) or (H, W, C) array_like of float
        Ground-truth image; same shape as `estimate`.
    mask : (H, W) array_like of bool, optional
        True where a pixel counts.  ``None`` (default) uses every pixel.
        Must contain at least one True pixel.
    window : int, optional
        Side of the square windows, in pixels, ``1 <= window <= min(H, W)``.
        Default 20, as in Grosse et al.
    step : int, optional
        Stride between window origins, in pixels, ``>= 1``.  Default 10
        (half the window), as in Grosse et al.

    Returns
    -------
    float
        The LMSE, ``>= 0``.  0 means the estimate equals the truth up to a
        positive or negative scale factor in every window.  With Bell et
        al.'s normalisation the value is at most 1 (a zero estimate scores
        exactly 1).

    Raises
    ------
    TypeError
        If an image is not real-valued, `mask` is not boolean, or `window`
        / `step` are not integers.
    ValueError
        If the shapes of `estimate`, `truth` and `mask` disagree, `mask`
        is all False, an image is non-finite inside the mask, `window` or
        `step` is < 1, `window` exceeds the image, or the masked truth has
        zero energy in every window (LMSE undefined, 0/0).

    Notes
    -----
    For each window :math:`w` and channel :math:`c`, with :math:`m` the
    mask, :math:`e` the estimate and :math:`t` the truth,

    .. math::

        \alpha_w = \frac{\sum_{p \in w} m_p t_p e_p}{\sum_{p \in w} m_p e_p^2},
        \qquad
        \mathrm{LMSE}_c = \frac{\sum_w \sum_{p \in w} m_p (t_p - \alpha_w e_p)^2}
                               {\sum_w \sum_{p \in w} m_p t_p^2},

    and :math:`\alpha_w = 0` whenever
    :math:`\sum_{p \in w} m_p e_p^2 \le 10^{-5}` (the absolute threshold
    of the reference code; it only matters for nearly black estimates, but
    it means that scale invariance holds for windows whose estimate energy
    exceeds :math:`10^{-5}`).  Pixels covered by several windows count
    several times; pixels covered by no window (right/bottom margins when
    ``(size - window) % step != 0``) are ignored.

    **Colour.**  Each channel is treated independently, with its own
    :math:`\alpha_w` per window, and the result is the mean of the
    per-channel LMSE values, :math:`\frac{1}{C}\sum_c \mathrm{LMSE}_c`.
    A grey image is the case :math:`C = 1`.

    **Normalisation (Bell et al. 2014).**  The public Python code of
    Grosse et al. (``intrinsic.py``, ``local_error``) accumulates the
    denominator ``total += np.sum(mask_curr * correct_curr**2)`` one
    indentation level too far out -- in the loop over window rows instead
    of the loop over windows -- so that only the last window of each row
    of windows enters the normaliser.  The denominator is then too small
    and scores above 1 become possible.  Bell et al.'s release
    (``bell2014/lmse.py`` in https://github.com/seanbell/intrinsic) moves
    this line into the inner loop, with the comment that the outdented
    version "allows for scores greater than 1 (which should not be
    possible)" and that the difference is negligible on the MIT images but
    can be significant on larger images.  This function implements the
    corrected form: numerator and denominator are summed over exactly the
    same windows.  Bell et al. kept everything else unchanged (windows of
    ``window_size`` with shift ``window_size // 2``, the :math:`10^{-5}`
    threshold on :math:`\alpha`, mask applied to every sum).

    The window loop is vectorised with
    :func:`numpy.lib.stride_tricks.sliding_window_view`; the squared
    residual is formed explicitly (not as
    :math:`\sum t^2 - (\sum te)^2/\sum e^2`) so a perfect estimate gives 0
    up to rounding.

    References
    ----------
    .. [1] R. Grosse, M. K. Johnson, E. H. Adelson and W. T. Freeman,
       "Ground truth dataset and baseline evaluations for intrinsic image
       algorithms", in *Proceedings of the IEEE International Conference
       on Computer Vision (ICCV)*, pp. 2335-2342, 2009.
       Code: http://people.csail.mit.edu/rgrosse/intrinsic/
    .. [2] S. Bell, K. Bala and N. Snavely, "Intrinsic Images in the Wild",
       *ACM Transactions on Graphics (Proc. SIGGRAPH)*, 33(4), article 159,
       2014.  Code: https://github.com/seanbell/intrinsic

    Examples
    --------
    >>> import numpy as np
    >>> truth = np.zeros((2, 4)); truth[:, 2:] = 1.0
    >>> float(lmse(np.ones((2, 4)), truth, window=2, step=1))  # 1 / 6
    0.16666666666666666
    """
    window = _positive_int(window, "window")
    step = _positive_int(step, "step")
    e, t, _, _ = _validated_pair(estimate, truth, mask, "estimate", "truth")
    return _lmse_validated(e, t, window, step, "estimate", "truth")


def lmse_score(reflectance, shading, true_reflectance, true_shading, *, mask=None, window=20, step=10):
    r"""Grosse et al.'s decomposition score: mean LMSE of reflectance and shading.

    Parameters
    ----------
    reflectance : (H, W) or (H, W, C) array_like of float
        Estimated reflectance.
    shading : (H, W) or (H, W, C) array_like of float
        Estimated shading (may be grey while the reflectance is colour).
    true_reflectance : array_like of float
        Ground-truth reflectance, same shape as `reflectance`.
    true_shading : array_like of float
        Ground-truth shading, same shape as `shading`.
    mask : (H, W) array_like of bool, optional
        Pixels that count, applied to both components.  ``None`` uses all
        pixels.
    window, step : int, optional
        Window side and stride, see :func:`lmse`.

    Returns
    -------
    float
        :math:`\tfrac12\,\mathrm{LMSE}(R, R^*) + \tfrac12\,\mathrm{LMSE}(S, S^*)`.

    Raises
    ------
    TypeError, ValueError
        As :func:`lmse`, with the message naming the offending argument of
        this function.

    Notes
    -----
    .. math::

        \mathrm{score} = \tfrac12\,\mathrm{LMSE}(R, R^*)
                       + \tfrac12\,\mathrm{LMSE}(S, S^*)

    This is ``score_image`` of the reference code (Grosse et al. 2009,
    with Bell et al.'s 2014 normalisation, see :func:`lmse`).

    References
    ----------
    .. [1] R. Grosse, M. K. Johnson, E. H. Adelson and W. T. Freeman,
       "Ground truth dataset and baseline evaluations for intrinsic image
       algorithms", in *Proceedings of the IEEE International Conference
       on Computer Vision (ICCV)*, pp. 2335-2342, 2009.
    .. [2] S. Bell, K. Bala and N. Snavely, "Intrinsic Images in the Wild",
       *ACM Transactions on Graphics (Proc. SIGGRAPH)*, 33(4), article 159,
       2014.
    """
    window = _positive_int(window, "window")
    step = _positive_int(step, "step")
    er, tr, _, _ = _validated_pair(reflectance, true_reflectance, mask, "reflectance", "true_reflectance")
    es, ts, _, _ = _validated_pair(shading, true_shading, mask, "shading", "true_shading")
    l_r = _lmse_validated(er, tr, window, step, "reflectance", "true_reflectance")
    l_s = _lmse_validated(es, ts, window, step, "shading", "true_shading")
    return 0.5 * l_r + 0.5 * l_s


# ---------------------------------------------------------------------------
# Global scale-invariant MSE
# ---------------------------------------------------------------------------


def si_mse(estimate, truth, *, mask=None):
    r"""Scale-invariant mean squared error, normalised by the truth's energy.

    Parameters
    ----------
    estimate : (H, W) or (H, W, C) array_like of float
        Estimated image.
    truth : (H, W) or (H, W, C) array_like of float
        Ground-truth image, same shape as `estimate`.
    mask : (H, W) array_like of bool, optional
        Pixels that count; ``None`` uses all pixels.

    Returns
    -------
    float
        Value in ``[0, 1]``: 0 for an estimate equal to the truth up to a
        global scale factor per channel, 1 for a zero estimate.

    Raises
    ------
    TypeError
        If an image is not real-valued or `mask` is not boolean.
    ValueError
        If shapes disagree, `mask` is all False, an image is non-finite
        inside the mask, or a channel of `truth` is zero on every masked
        pixel (the normalised error is then 0/0).

    Notes
    -----
    Grosse et al. (2009, Eq. 7) define the scale-invariant MSE as the
    squared error after rescaling the estimate by the best single factor.
    Here, per channel :math:`c`,

    .. math::

        \alpha_c = \frac{\sum_p m_p t_p e_p}{\sum_p m_p e_p^2}, \qquad
        \mathrm{siMSE} = \frac{1}{C} \sum_c
            \frac{\sum_p m_p (t_p - \alpha_c e_p)^2}{\sum_p m_p t_p^2},

    with :math:`\alpha_c = 0` when :math:`\sum_p m_p e_p^2 = 0`.  As in
    :func:`lmse`, each colour channel gets its own factor and the result is
    the mean over channels.  Dividing by the masked energy of the truth
    (rather than by the pixel count) makes the value dimensionless,
    independent of the image's overall intensity and directly comparable
    with :func:`lmse`, which is the same quantity computed on local windows;
    a zero (or orthogonal) estimate scores 1.

    References
    ----------
    .. [1] R. Grosse, M. K. Johnson, E. H. Adelson and W. T. Freeman,
       "Ground truth dataset and baseline evaluations for intrinsic image
       algorithms", in *Proceedings of the IEEE International Conference
       on Computer Vision (ICCV)*, pp. 2335-2342, 2009.
    """
    e, t, _, _ = _validated_pair(estimate, truth, mask, "estimate", "truth")
    s_ee = np.einsum("hwc,hwc->c", e, e)
    s_te = np.einsum("hwc,hwc->c", t, e)
    s_tt = np.einsum("hwc,hwc->c", t, t)
    if np.any(s_tt <= 0):
        bad = [int(c) for c in np.flatnonzero(s_tt <= 0)]
        raise ValueError(f"si_mse is undefined: `truth` is zero on every masked pixel for channel(s) {bad}")
    alpha = np.zeros_like(s_ee)
    np.divide(s_te, s_ee, out=alpha, where=s_ee > 0)
    resid = t - alpha * e
    ssq = np.einsum("hwc,hwc->c", resid, resid)
    return float(np.mean(ssq / s_tt))


# ---------------------------------------------------------------------------
# Shadow masks
# ---------------------------------------------------------------------------


def _as_bool_map(array, name):
    arr = np.asarray(array)
    if arr.dtype != np.bool_:
        raise TypeError(f"`{name}` must be a boolean array of shape (H, W) (True = in shadow); got dtype {arr.dtype}")
    if arr.ndim != 2:
        raise ValueError(f"`{name}` must have shape (H, W); got shape {arr.shape}")
    if 0 in arr.shape:
        raise ValueError(f"`{name}` must be non-empty; got shape {arr.shape}")
    return arr


def balanced_error_rate(predicted_shadow, true_shadow, *, mask=None):
    r"""Balanced error rate (BER) of a binary shadow mask.

    Shadow is the positive class.

    Parameters
    ----------
    predicted_shadow : (H, W) array_like of bool
        Predicted shadow mask, True = in shadow.
    true_shadow : (H, W) array_like of bool
        Ground-truth shadow mask, True = in shadow.
    mask : (H, W) array_like of bool, optional
        Pixels that count; ``None`` uses all pixels.

    Returns
    -------
    float
        BER in ``[0, 1]``: 0 for a perfect prediction, 0.5 for a constant
        prediction (all lit or all shadow) when both classes are present,
        1 for the inverted prediction.

    Raises
    ------
    TypeError
        If an input is not boolean.
    ValueError
        If shapes disagree or `mask` is all False.

    Warns
    -----
    RuntimeWarning
        If, inside the mask, the ground truth contains only one class.

    Notes
    -----
    With TP, FN, TN, FP counted over the masked pixels,

    .. math::

        \mathrm{BER} = 1 - \frac12\left(\frac{TP}{TP + FN}
                                       + \frac{TN}{TN + FP}\right).

    If a class is absent from the masked ground truth its rate is
    undefined (0/0): that term is omitted, the result is the error rate of
    the present class alone (``FP / (TN + FP)`` if there is no shadow,
    ``FN / (TP + FN)`` if everything is in shadow) and a
    :class:`RuntimeWarning` is emitted, because such a value is not
    comparable with a two-class BER.

    References
    ----------
    .. [1] T. F. Y. Vicente, L. Hou, C.-P. Yu, M. Hoai and D. Samaras,
       "Large-scale training of shadow detectors with noisily-annotated
       shadow examples", in *Proceedings of the European Conference on
       Computer Vision (ECCV)*, pp. 816-832, 2016.
    """
    pred = _as_bool_map(predicted_shadow, "predicted_shadow")
    true = _as_bool_map(true_shadow, "true_shadow")
    _check_same_shape(pred, true, "predicted_shadow", "true_shadow")
    m = _as_mask(mask, pred.shape, reference="predicted_shadow")

    pos = true & m
    neg = ~true & m
    n_pos = int(pos.sum())
    n_neg = int(neg.sum())
    tp = int((pred & pos).sum())
    tn = int((~pred & neg).sum())

    if n_pos > 0 and n_neg > 0:
        return 1.0 - 0.5 * (tp / n_pos + tn / n_neg)
    if n_pos > 0:
        warnings.warn(
            "balanced_error_rate: `true_shadow` has no lit pixel inside the "
            "mask; returning the error rate of the shadow class only "
            "(FN / (TP + FN))",
            RuntimeWarning,
            stacklevel=2,
        )
        return 1.0 - tp / n_pos
    warnings.warn(
        "balanced_error_rate: `true_shadow` has no shadow pixel inside the "
        "mask; returning the error rate of the lit class only "
        "(FP / (TN + FP))",
        RuntimeWarning,
        stacklevel=2,
    )
    return 1.0 - tn / n_neg


def balanced_error_floor(regions, true_shadow, *, mask=None):
    r"""Smallest balanced error rate of any labelling that gives each region one label.

    A labelling that calls every pixel of a region shadow or lit (a clustering followed by a
    per-cluster classifier, as the shadow MRF of :mod:`mvintrinsic.shadow_mrf`) cannot score a
    lower :func:`balanced_error_rate` than this, whatever its classifier.

    Parameters
    ----------
    regions : (H, W) array_like of int
        Region index of every pixel; must be non-negative where ``mask`` is True (pixels
        outside it may carry any value, e.g. -1).
    true_shadow : (H, W) array_like of bool
        Ground-truth shadow mask, True = in shadow.
    mask : (H, W) array_like of bool, optional
        Pixels that count; ``None`` uses all pixels.

    Returns
    -------
    float
        The floor in ``[0, 0.5]``.

    Raises
    ------
    TypeError
        If ``true_shadow`` is not boolean or ``regions`` not integer.
    ValueError
        If shapes disagree, a region index inside the mask is negative, or the masked ground truth lacks a class
        (the BER then has no two-class meaning).

    Notes
    -----
    With ``P`` shadowed and ``N`` lit pixels in the mask, and ``s_c``, ``l_c`` those of region
    ``c``, a region labelled lit adds ``s_c / P`` to the miss rate and one labelled shadow adds
    ``l_c / N`` to the false-alarm rate. The BER is half their sum, so the regions are independent
    and the best labelling takes the cheaper label for each:

    .. math::

        \mathrm{BER}_{\min} = \frac12 \sum_c \min\left(\frac{s_c}{P}, \frac{l_c}{N}\right).

    It is lower than the BER of the per-region majority vote when the classes are unbalanced (a
    region that is 40% shadow is best called shadow when shadow is rarer than 40%).
    """
    true = _as_bool_map(true_shadow, "true_shadow")
    labels = np.asarray(regions)
    if not np.issubdtype(labels.dtype, np.integer):
        raise TypeError(f"`regions` must be an integer array of shape (H, W); got dtype {labels.dtype}")
    _check_same_shape(labels, true, "regions", "true_shadow")
    m = _as_mask(mask, true.shape, reference="true_shadow")
    labels, true = labels[m], true[m]
    if labels.size and labels.min() < 0:
        raise ValueError("`regions` must be non-negative inside the mask")
    n_shadow, n_lit = int(true.sum()), int((~true).sum())
    if n_shadow == 0 or n_lit == 0:
        raise ValueError("balanced_error_floor: the masked ground truth must hold both shadow and lit pixels")
    shadow = np.bincount(labels, weights=true.astype(np.float64))
    lit = np.bincount(labels, weights=(~true).astype(np.float64))
    return float(0.5 * np.minimum(shadow / n_shadow, lit / n_lit).sum())


# ---------------------------------------------------------------------------
# PSNR and SSIM
# ---------------------------------------------------------------------------


def psnr(estimate, truth, *, mask=None, data_range=None):
    r"""Peak signal-to-noise ratio over the masked pixels, in decibels.

    Parameters
    ----------
    estimate : (H, W) or (H, W, C) array_like of float
        Estimated image.
    truth : (H, W) or (H, W, C) array_like of float
        Ground-truth image, same shape as `estimate`.
    mask : (H, W) array_like of bool, optional
        Pixels that count; ``None`` uses all pixels.
    data_range : float, optional
        Peak-to-peak range of the signal.  Default: ``max - min`` of
        `truth` over the masked pixels and all channels.

    Returns
    -------
    float
        PSNR in dB; ``numpy.inf`` when the masked MSE is exactly 0.

    Raises
    ------
    TypeError
        If an image is not real-valued, `mask` is not boolean, or
        `data_range` is not a number.
    ValueError
        If shapes disagree, `mask` is all False, an image is non-finite
        inside the mask, `data_range` is not positive and finite, or it
        must be inferred but `truth` is constant inside the mask (and the
        MSE is not 0).

    Notes
    -----
    .. math::

        \mathrm{PSNR} = 10 \log_{10} \frac{\mathrm{data\_range}^2}{\mathrm{MSE}},
        \qquad
        \mathrm{MSE} = \frac{1}{C \sum_p m_p} \sum_p \sum_c m_p (e_{pc} - t_{pc})^2 .

    With ``mask=None`` and an explicit `data_range` this equals
    :func:`skimage.metrics.peak_signal_noise_ratio`.  No scale is fitted:
    PSNR is not scale-invariant.

    References
    ----------
    .. [1] Q. Huynh-Thu and M. Ghanbari, "Scope of validity of PSNR in
       image/video quality assessment", *Electronics Letters*, 44(13),
       pp. 800-801, 2008.
    """
    e, t, m, _ = _validated_pair(estimate, truth, mask, "estimate", "truth")
    diff = e[m] - t[m]  # (n_masked, C)
    mse = float(np.mean(diff * diff))
    if mse == 0.0:
        if data_range is not None:
            _data_range(data_range, t, m, "truth")  # still validate it
        return float(np.inf)
    dr = _data_range(data_range, t, m, "truth")
    return float(10.0 * np.log10(dr * dr / mse))


def ssim(estimate, truth, *, mask=None, data_range=None):
    r"""Structural similarity (SSIM) averaged over the masked pixels.

    Parameters
    ----------
    estimate : (H, W) or (H, W, C) array_like of float
        Estimated image, ``H, W >= 7``.
    truth : (H, W) or (H, W, C) array_like of float
        Ground-truth image, same shape as `estimate`.
    mask : (H, W) array_like of bool, optional
        Pixels over which the SSIM map is averaged; ``None`` uses all
        pixels (except the 3-pixel image border, see Notes).
    data_range : float, optional
        Peak-to-peak range of the signal, sets the SSIM stabilising
        constants.  Default: ``max - min`` of `truth` over the masked
        pixels and all channels.

    Returns
    -------
    float
        Mean SSIM, at most 1 (1 for identical images).

    Raises
    ------
    TypeError
        If an image is not real-valued, `mask` is not boolean, or
        `data_range` is not a number.
    ValueError
        If shapes disagree, an image is smaller than 7x7, `mask` is all
        False or selects only pixels of the 3-pixel image border, an image
        is non-finite inside the mask, `data_range` is not positive and
        finite, or it must be inferred but `truth` is constant inside the
        mask.

    Notes
    -----
    The SSIM map is :func:`skimage.metrics.structural_similarity` with its
    defaults (7x7 uniform window, :math:`K_1 = 0.01`, :math:`K_2 = 0.03`,
    sample covariance), computed per channel (``channel_axis=-1`` for
    colour) with ``full=True``:

    .. math::

        \mathrm{SSIM}_p = \frac{(2\mu_e\mu_t + C_1)(2\sigma_{et} + C_2)}
                               {(\mu_e^2 + \mu_t^2 + C_1)(\sigma_e^2 + \sigma_t^2 + C_2)},
        \qquad C_i = (K_i \cdot \mathrm{data\_range})^2,

    and the result is the mean of :math:`\mathrm{SSIM}_p` over all channels
    and over the masked pixels at least 3 pixels away from the image
    border.  The border strip is excluded as scikit-image does, because
    its windows are filled by reflection; hence with ``mask=None`` the
    result equals scikit-image's mean SSIM.

    The map itself is computed on the whole image, so a masked pixel
    within 3 pixels of the mask boundary has masked-out pixels in its
    window.  To make the result depend only on values inside the mask (and
    to tolerate NaN outside it), every masked-out pixel is set to 0 in
    *both* images before filtering; such neighbours therefore agree
    perfectly but still pull the local means and variances of border
    pixels towards 0.

    References
    ----------
    .. [1] Z. Wang, A. C. Bovik, H. R. Sheikh and E. P. Simoncelli, "Image
       quality assessment: from error visibility to structural
       similarity", *IEEE Transactions on Image Processing*, 13(4),
       pp. 600-612, 2004.
    """
    e, t, m, is_2d = _validated_pair(estimate, truth, mask, "estimate", "truth")
    H, W, _ = e.shape
    if H < _SSIM_WIN_SIZE or W < _SSIM_WIN_SIZE:
        raise ValueError(
            f"`estimate` must be at least {_SSIM_WIN_SIZE}x{_SSIM_WIN_SIZE} "
            f"pixels for SSIM; got spatial shape (H, W) = ({H}, {W})"
        )
    pad = (_SSIM_WIN_SIZE - 1) // 2
    interior = np.zeros((H, W), dtype=bool)
    interior[pad : H - pad, pad : W - pad] = True
    use = m & interior
    if not use.any():
        raise ValueError(
            f"`mask` selects only pixels within {pad} pixels of the image "
            "border, where the SSIM map is not evaluated; no pixel left to "
            "average"
        )
    dr = _data_range(data_range, t, m, "truth")
    if is_2d:
        _, smap = structural_similarity(e[:, :, 0], t[:, :, 0], data_range=dr, full=True, win_size=_SSIM_WIN_SIZE)
        smap = smap[:, :, np.newaxis]
    else:
        _, smap = structural_similarity(e, t, data_range=dr, full=True, channel_axis=-1, win_size=_SSIM_WIN_SIZE)
    return float(np.mean(smap[use]))
