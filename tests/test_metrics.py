"""Tests for mvintrinsic.metrics.

Expected values are derived independently of the implementation: by hand
(tiny cases, arithmetic in the comments), by closed-form formulas, or with
a deliberately naive loop (`_reference_lmse`) that follows the reference
code of Grosse et al. (2009) with the normaliser fix of Bell et al. (2014).
"""

import math

import numpy as np
import pytest
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from mvintrinsic.metrics import (
    balanced_error_floor,
    balanced_error_rate,
    lmse,
    lmse_score,
    psnr,
    si_mse,
    ssim,
)

# --- tolerances (all in one place) -----------------------------------------
#: results that are exact up to floating-point rounding
EXACT = 1e-12
#: vectorised LMSE vs. the naive loop (different summation order only)
REF_RTOL = 1e-12
#: PSNR of a known noise level, in dB
PSNR_ABS = 1e-9


# --- helpers ----------------------------------------------------------------


def _reference_lmse(estimate, truth, mask, window, step):
    """Naive LMSE: Grosse's local_error loop with Bell's normaliser fix.

    Per channel, then averaged over channels.
    """
    est = np.asarray(estimate, dtype=float)
    tru = np.asarray(truth, dtype=float)
    if est.ndim == 2:
        est, tru = est[:, :, None], tru[:, :, None]
    m = mask.astype(float)
    H, W, C = est.shape
    values = []
    for c in range(C):
        ssq = total = 0.0
        for i in range(0, H - window + 1, step):
            for j in range(0, W - window + 1, step):
                e = est[i : i + window, j : j + window, c]
                t = tru[i : i + window, j : j + window, c]
                mm = m[i : i + window, j : j + window]
                see = np.sum(mm * e**2)
                alpha = np.sum(mm * t * e) / see if see > 1e-5 else 0.0
                ssq += np.sum(mm * (t - alpha * e) ** 2)
                total += np.sum(mm * t**2)  # inside the loop: Bell's fix
        values.append(ssq / total)
    return float(np.mean(values))


def _halves():
    """2x4 truth: left two columns 0, right two columns 1."""
    truth = np.zeros((2, 4))
    truth[:, 2:] = 1.0
    return truth


@pytest.fixture
def rng():
    return np.random.default_rng(20150901)


# --- LMSE -------------------------------------------------------------------


@pytest.mark.parametrize("shape", [(45, 37), (45, 37, 3)])
@pytest.mark.parametrize("use_mask", [False, True])
@pytest.mark.parametrize("scale", [1.0, 0.3, 7.0])
def test_lmse_scaled_perfect_estimate_is_zero(rng, shape, use_mask, scale):
    truth = 0.05 + rng.random(shape)
    mask = rng.random(shape[:2]) > 0.3 if use_mask else None
    value = lmse(scale * truth, truth, mask=mask)
    assert value == pytest.approx(0.0, abs=EXACT)


def test_lmse_tiny_hand_computed():
    # truth (2x4) = [[0 0 1 1], [0 0 1 1]], estimate = all ones,
    # window=2, step=1 -> windows at columns j = 0, 1, 2 (one row).
    #   j=0: t = 0 everywhere -> alpha = 0/4 = 0, ssq = 0, sum t^2 = 0
    #   j=1: t = [0 1; 0 1]  -> alpha = 2/4 = 0.5, residuals +-0.5,
    #        ssq = 4 * 0.25 = 1, sum t^2 = 2
    #   j=2: t = 1 everywhere -> alpha = 1, ssq = 0, sum t^2 = 4
    # LMSE = (0 + 1 + 0) / (0 + 2 + 4) = 1/6.
    # (Grosse's original code added only the last window of each row to the
    #  normaliser, giving 1/4; Bell's fix gives 1/6.)
    value = lmse(np.ones((2, 4)), _halves(), window=2, step=1)
    assert value == pytest.approx(1.0 / 6.0, rel=EXACT)


def test_lmse_tiny_hand_computed_masked():
    # Same as above with column 3 masked out:
    #   j=0: t = 0 -> ssq 0, total 0
    #   j=1: columns 1, 2 unchanged -> ssq 1, total 2
    #   j=2: only column 2 counts (t = 1, e = 1) -> alpha = 2/2 = 1,
    #        ssq 0, total 2
    # LMSE = 1 / (2 + 2) = 1/4.
    mask = np.ones((2, 4), dtype=bool)
    mask[:, 3] = False
    value = lmse(np.ones((2, 4)), _halves(), mask=mask, window=2, step=1)
    assert value == pytest.approx(0.25, rel=EXACT)


def test_lmse_tiny_hand_computed_colour():
    # Channel 0: the 1/6 case.  Channel 1: truth x5 (LMSE is invariant to
    # the scale of the truth: ssq and total both scale by 25) -> 1/6.
    # Channel 2: constant truth -> alpha fits exactly in every window -> 0.
    # Mean over channels = (1/6 + 1/6 + 0) / 3 = 1/9.
    truth = np.stack([_halves(), 5.0 * _halves(), np.full((2, 4), 0.7)], -1)
    value = lmse(np.ones((2, 4, 3)), truth, window=2, step=1)
    assert value == pytest.approx(1.0 / 9.0, rel=EXACT)


def test_lmse_step_larger_than_window_skips_pixels():
    # window=1, step=2 on the 2x4 halves image: windows are the single
    # pixels at (0,0) and (0,2); a single pixel is always fitted exactly
    # (alpha = t/e), except where t=0 which contributes nothing -> 0.
    # With an estimate that is 0 at (0,2): alpha=0 there, ssq = 1, total = 1.
    est = np.ones((2, 4))
    est[0, 2] = 0.0
    value = lmse(est, _halves(), window=1, step=2)
    assert value == pytest.approx(1.0, rel=EXACT)
    # Changing pixels never covered by a window (column 1, row 1) has no
    # effect.
    est2 = est.copy()
    est2[1, :] = 123.0
    est2[:, 1] = -5.0
    assert lmse(est2, _halves(), window=1, step=2) == pytest.approx(1.0, rel=EXACT)


def test_lmse_constant_estimate_closed_form_gradient():
    # Truth t(y, x) = 1 + b x on a 40x40 image, estimate constant c.
    # In a window the least-squares alpha is mean(t)/c, so the residual is
    # t - mean(t) and the window's ssq is n * var(t) with n = 20*20.  Along x
    # the window holds 20 equally spaced values with spacing b, so
    # var = b^2 (20^2 - 1) / 12, the same in every window; along y, t is
    # constant.  The window's sum t^2 = n (mean^2 + var), with
    # mean = 1 + b (j + 9.5) for a window starting at column j.
    # Windows start at rows/columns 0, 10, 20, hence
    #   LMSE = 9 var / sum_{i,j} (mean_j^2 + var) = 3 var / sum_j (mean_j^2 + var).
    b = 0.05
    x = np.arange(40, dtype=float)
    truth = np.tile(1.0 + b * x, (40, 1))
    var = b**2 * (20**2 - 1) / 12.0
    means = [1.0 + b * (j + 9.5) for j in (0, 10, 20)]
    expected = 9 * var / (3 * sum(mu**2 + var for mu in means))
    value = lmse(np.full((40, 40), 0.5), truth)
    assert value == pytest.approx(expected, rel=EXACT)
    # Colour: the same gradient in every channel scaled differently gives
    # the same value (per-channel alpha, mean over channels).
    truth3 = np.stack([truth, 3.0 * truth, 0.2 * truth], -1)
    value3 = lmse(np.full((40, 40, 3), 0.5), truth3)
    assert value3 == pytest.approx(expected, rel=EXACT)


def test_lmse_constant_estimate_window_variance_formula(rng):
    # General constant estimate: LMSE = sum_w n var_w / sum_w sum t^2, with
    # var_w the population variance of the truth in window w -- evaluated
    # here with np.var over explicitly listed windows, not with the
    # alpha-fitting formula.
    truth = np.where(rng.random((40, 40)) > 0.5, 2.0, 0.5)
    n = 20 * 20
    num = den = 0.0
    for i in (0, 10, 20):
        for j in (0, 10, 20):
            win = truth[i : i + 20, j : j + 20]
            num += n * np.var(win)
            den += np.sum(win**2)
    value = lmse(np.full((40, 40), 1.3), truth)
    assert value == pytest.approx(num / den, rel=EXACT)


@pytest.mark.parametrize("seed", [0, 1, 2, 3, 4])
def test_lmse_matches_reference_loop(seed):
    rng = np.random.default_rng(seed)
    H, W = rng.integers(20, 70, size=2)
    window = int(rng.integers(1, min(H, W) + 1))
    step = int(rng.integers(1, 15))
    shape = (H, W, 3) if seed % 2 else (H, W)
    truth = rng.random(shape)
    estimate = truth * (0.5 + rng.random(shape)) + 0.1 * rng.random(shape)
    # some dark windows exercise the alpha = 0 branch
    estimate[: H // 4, : W // 4] *= 1e-5
    mask = rng.random((H, W)) > rng.uniform(0.1, 0.7)
    expected = _reference_lmse(estimate, truth, mask, window, step)
    value = lmse(estimate, truth, mask=mask, window=window, step=step)
    assert value == pytest.approx(expected, rel=REF_RTOL)
    expected_full = _reference_lmse(estimate, truth, np.ones((H, W), bool), window, step)
    assert lmse(estimate, truth, window=window, step=step) == pytest.approx(expected_full, rel=REF_RTOL)


def test_lmse_zero_estimate_is_one_and_bounded(rng):
    truth = rng.random((50, 60, 3))
    assert lmse(np.zeros_like(truth), truth) == pytest.approx(1.0, rel=EXACT)
    # Bell's normalisation bounds LMSE by 1 for any estimate.
    for _ in range(5):
        est = rng.normal(size=truth.shape)
        assert 0.0 <= lmse(est, truth) <= 1.0


def test_lmse_score_hand_computed():
    # Reflectance perfect up to scale (LMSE 0), shading the 1/6 case:
    # score = 0.5 * 0 + 0.5 * 1/6 = 1/12.
    true_r = np.stack([_halves() + 0.5] * 3, -1)
    value = lmse_score(2.0 * true_r, np.ones((2, 4)), true_r, _halves(), window=2, step=1)
    assert value == pytest.approx(1.0 / 12.0, rel=EXACT)


def test_lmse_score_is_mean_of_lmse(rng):
    r, tr = rng.random((30, 40, 3)), rng.random((30, 40, 3))
    s, ts = rng.random((30, 40)), rng.random((30, 40))
    mask = rng.random((30, 40)) > 0.4
    expected = 0.5 * _reference_lmse(r, tr, mask, 20, 10) + 0.5 * _reference_lmse(s, ts, mask, 20, 10)
    assert lmse_score(r, s, tr, ts, mask=mask) == pytest.approx(expected, rel=REF_RTOL)


# --- si_mse -----------------------------------------------------------------


@pytest.mark.parametrize("shape", [(20, 30), (20, 30, 3)])
def test_si_mse_perfect_multiple_and_zero(rng, shape):
    truth = rng.random(shape)
    mask = rng.random(shape[:2]) > 0.5
    assert si_mse(truth, truth) == pytest.approx(0.0, abs=EXACT)
    assert si_mse(0.3 * truth, truth, mask=mask) == pytest.approx(0.0, abs=EXACT)
    assert si_mse(7.0 * truth, truth) == pytest.approx(0.0, abs=EXACT)
    assert si_mse(np.zeros(shape), truth, mask=mask) == pytest.approx(1.0, rel=EXACT)


def test_si_mse_hand_computed():
    # truth = [1, 2, 3, 4] (as a 2x2 image), estimate = 1 everywhere.
    # alpha = sum(t e) / sum(e^2) = 10 / 4 = 2.5; residuals -1.5 -0.5 0.5 1.5,
    # ssq = 2.25 + 0.25 + 0.25 + 2.25 = 5; sum t^2 = 30 -> 5/30 = 1/6.
    truth = np.array([[1.0, 2.0], [3.0, 4.0]])
    assert si_mse(np.ones((2, 2)), truth) == pytest.approx(1.0 / 6.0, rel=EXACT)
    # Colour: channel 0 as above (1/6), channel 1 perfect (0) -> mean 1/12.
    truth3 = np.stack([truth, truth], -1)
    est3 = np.stack([np.ones((2, 2)), 2.0 * truth], -1)
    assert si_mse(est3, truth3) == pytest.approx(1.0 / 12.0, rel=EXACT)


# --- balanced error rate ----------------------------------------------------


def test_ber_reference_predictions(rng):
    true = rng.random((30, 40)) > 0.6
    assert balanced_error_rate(np.zeros_like(true), true) == pytest.approx(0.5, abs=EXACT)
    assert balanced_error_rate(np.ones_like(true), true) == pytest.approx(0.5, abs=EXACT)
    assert balanced_error_rate(true.copy(), true) == 0.0
    assert balanced_error_rate(~true, true) == 1.0


def test_ber_hand_computed():
    # 2x5 truth with 4 shadow pixels (first row, columns 0-3) and 6 lit.
    # Prediction: 3 of the 4 shadow pixels (TP=3, FN=1) and 2 lit pixels
    # wrongly in shadow (FP=2, TN=4).
    # BER = 1 - (3/4 + 4/6) / 2 = 1 - 17/24 = 7/24.
    true = np.zeros((2, 5), dtype=bool)
    true[0, :4] = True
    pred = np.zeros((2, 5), dtype=bool)
    pred[0, :3] = True
    pred[1, :2] = True
    assert balanced_error_rate(pred, true) == pytest.approx(7.0 / 24.0, rel=EXACT)
    # Masking out the missed shadow pixel (0,3) and one false positive
    # (1,0): TP=3, FN=0, FP=1, TN=4 -> BER = 1 - (1 + 4/5)/2 = 0.1.
    mask = np.ones((2, 5), dtype=bool)
    mask[0, 3] = False
    mask[1, 0] = False
    assert balanced_error_rate(pred, true, mask=mask) == pytest.approx(0.1, rel=EXACT)


def test_ber_floor_equals_the_best_of_every_region_labelling(rng):
    # Brute force over all 2^7 labellings of 7 regions, each pixel taking its region's label.
    regions = rng.integers(0, 7, size=(12, 15))
    true = rng.random((12, 15)) > 0.7  # unbalanced: about 30% shadow
    mask = rng.random((12, 15)) > 0.1
    best = min(
        balanced_error_rate(np.isin(regions, [r for r in range(7) if bits >> r & 1]), true, mask=mask)
        for bits in range(2**7)
    )
    assert balanced_error_floor(regions, true, mask=mask) == pytest.approx(best, rel=EXACT)


def test_ber_floor_hand_computed_and_below_the_majority_vote():
    # Region 0: 2 shadow + 3 lit pixels, region 1: 0 shadow + 5 lit. P = 2, N = 8.
    # Majority vote calls both lit: BER = (1 + 0) / 2 = 0.5. Calling region 0 shadow costs
    # l_0 / N = 3/8 instead of s_0 / P = 1: floor = 3/16.
    regions = np.array([[0, 0, 0, 0, 0], [1, 1, 1, 1, 1]])
    true = np.zeros((2, 5), dtype=bool)
    true[0, :2] = True
    assert balanced_error_floor(regions, true) == pytest.approx(3.0 / 16.0, rel=EXACT)
    assert balanced_error_rate(np.zeros_like(true), true) == pytest.approx(0.5, rel=EXACT)
    # Regions that are each one class: the floor is 0.
    assert balanced_error_floor(true.astype(int), true) == 0.0


def test_ber_floor_rejects_bad_input():
    true = np.zeros((2, 3), dtype=bool)
    true[0, 0] = True
    with pytest.raises(TypeError, match="regions"):
        balanced_error_floor(np.zeros((2, 3)), true)
    with pytest.raises(ValueError, match="non-negative"):
        balanced_error_floor(-np.ones((2, 3), dtype=int), true)
    with pytest.raises(ValueError, match="both shadow and lit"):
        balanced_error_floor(np.zeros((2, 3), dtype=int), np.zeros((2, 3), dtype=bool))
    with pytest.raises(ValueError, match="shape"):
        balanced_error_floor(np.zeros((3, 3), dtype=int), true)


def test_ber_single_class_warns_and_uses_present_class():
    true = np.zeros((2, 5), dtype=bool)  # no shadow at all
    pred = np.zeros((2, 5), dtype=bool)
    pred[0, :2] = True  # FP=2, TN=8 -> lit-class error 0.2
    with pytest.warns(RuntimeWarning, match="no shadow pixel"):
        value = balanced_error_rate(pred, true)
    assert value == pytest.approx(0.2, rel=EXACT)
    with pytest.warns(RuntimeWarning, match="no lit pixel"):
        value = balanced_error_rate(pred, ~true)  # all shadow, FN=8 of 10
    assert value == pytest.approx(0.8, rel=EXACT)


# --- PSNR -------------------------------------------------------------------


@pytest.mark.parametrize("sigma", [0.1, 0.01, 0.003])
@pytest.mark.parametrize("shape", [(40, 50), (40, 50, 3)])
def test_psnr_known_noise(rng, sigma, shape):
    truth = rng.random(shape)
    signs = rng.choice([-1.0, 1.0], size=shape)
    estimate = truth + sigma * signs  # (e - t)^2 == sigma^2 everywhere
    expected = -20.0 * math.log10(sigma)
    assert psnr(estimate, truth, data_range=1.0) == pytest.approx(expected, abs=PSNR_ABS)
    assert peak_signal_noise_ratio(truth, estimate, data_range=1.0) == pytest.approx(expected, abs=PSNR_ABS)
    # Huge noise outside the mask must not matter.
    mask = rng.random(shape[:2]) > 0.5
    noisy = np.where(mask if len(shape) == 2 else mask[..., None], estimate, truth + 1e3 * signs)
    assert psnr(noisy, truth, mask=mask, data_range=1.0) == pytest.approx(expected, abs=PSNR_ABS)


def test_psnr_default_data_range_and_perfect():
    # truth in mask spans [2, 6] -> data_range 4; error 0.4 everywhere ->
    # PSNR = 10 log10(16 / 0.16) = 20 dB.  Values outside the mask (100)
    # must not enter the data range.
    truth = np.array([[2.0, 3.0, 6.0, 100.0], [4.0, 5.0, 2.5, 100.0]])
    mask = np.ones((2, 4), dtype=bool)
    mask[:, 3] = False
    assert psnr(truth + 0.4, truth, mask=mask) == pytest.approx(20.0, abs=PSNR_ABS)
    assert psnr(truth, truth) == np.inf


# --- SSIM -------------------------------------------------------------------


@pytest.mark.parametrize("shape", [(32, 40), (32, 40, 3)])
def test_ssim_identical_is_one(rng, shape):
    truth = rng.random(shape)
    assert ssim(truth, truth) == pytest.approx(1.0, abs=EXACT)
    mask = rng.random(shape[:2]) > 0.5
    assert ssim(truth, truth, mask=mask) == pytest.approx(1.0, abs=EXACT)


def test_ssim_without_mask_equals_skimage(rng):
    truth = rng.random((32, 40, 3))
    est = truth + 0.2 * rng.random((32, 40, 3))
    dr = float(truth.max() - truth.min())
    expected = structural_similarity(est, truth, data_range=dr, channel_axis=-1)
    assert ssim(est, truth) == pytest.approx(expected, rel=EXACT)


def test_ssim_mask_restricts_averaging(rng):
    # Left half identical, right half independent noise.  Without a mask
    # the score is far below 1.  With the mask on the left half, every
    # averaged pixel sees, in its 7x7 window, either identical values or
    # masked-out pixels (set to 0 in both images) -> exactly 1.
    truth = rng.random((40, 40))
    est = truth.copy()
    est[:, 20:] = rng.random((40, 20))
    left = np.zeros((40, 40), dtype=bool)
    left[:, :20] = True
    full = ssim(est, truth, data_range=1.0)
    assert full < 0.8
    assert ssim(est, truth, mask=left, data_range=1.0) == pytest.approx(1.0, abs=EXACT)
    # The right half alone scores lower than the whole image.
    assert ssim(est, truth, mask=~left, data_range=1.0) < full - 0.2


# --- out-of-mask values, NaN and inf ------------------------------------------


def _all_metrics(est, truth, mask):
    return {
        "lmse": lmse(est, truth, mask=mask),
        "lmse_small": lmse(est, truth, mask=mask, window=5, step=3),
        "lmse_score": lmse_score(est, est[..., 0], truth, truth[..., 0], mask=mask),
        "si_mse": si_mse(est, truth, mask=mask),
        "psnr": psnr(est, truth, mask=mask),
        "ssim": ssim(est, truth, mask=mask),
    }


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf, 1e300])
@pytest.mark.parametrize("where", ["estimate", "truth", "both"])
def test_values_outside_mask_do_not_matter(rng, bad, where):
    truth = 0.1 + rng.random((40, 48, 3))
    est = truth * rng.uniform(0.5, 1.5, size=truth.shape)
    mask = rng.random((40, 48)) > 0.3
    reference = _all_metrics(est, truth, mask)
    est2, truth2 = est.copy(), truth.copy()
    if where in ("estimate", "both"):
        est2[~mask] = bad
    if where in ("truth", "both"):
        truth2[~mask] = bad
    with np.errstate(all="raise"):  # no invalid/overflow operation on them
        result = _all_metrics(est2, truth2, mask)
    for name, value in reference.items():
        assert result[name] == pytest.approx(value, rel=EXACT), name


def test_inputs_are_not_modified(rng):
    truth = rng.random((30, 30, 3))
    est = rng.random((30, 30, 3))
    est[0, 0] = np.nan
    mask = np.ones((30, 30), dtype=bool)
    mask[0, 0] = False
    arrays = [truth, est, mask]
    copies = [a.copy() for a in arrays]
    for a in arrays:
        a.flags.writeable = False  # any in-place write would raise
    _all_metrics(est, truth, mask)
    pred = truth[..., 0] > 0.5
    pred.flags.writeable = False
    balanced_error_rate(pred, pred, mask=mask)
    for a, c in zip(arrays, copies, strict=True):
        np.testing.assert_array_equal(a, c)


# --- errors -----------------------------------------------------------------

IMAGE_METRICS = [lmse, si_mse, psnr, ssim]


@pytest.mark.parametrize("metric", IMAGE_METRICS)
def test_error_shape_mismatch(metric):
    with pytest.raises(ValueError, match=r"`estimate` and `truth`.*\(30, 30, 3\).*\(30, 30\)"):
        metric(np.ones((30, 30, 3)), np.ones((30, 30)))


@pytest.mark.parametrize("metric", IMAGE_METRICS)
def test_error_mask_shape(metric):
    with pytest.raises(ValueError, match=r"`mask`.*\(30, 30\).*\(30, 31\)"):
        metric(np.ones((30, 30)), np.ones((30, 30)), mask=np.ones((30, 31), bool))


@pytest.mark.parametrize("metric", IMAGE_METRICS)
def test_error_all_false_mask(metric):
    with pytest.raises(ValueError, match="`mask`.*all False"):
        metric(np.ones((30, 30)), np.ones((30, 30)), mask=np.zeros((30, 30), bool))


@pytest.mark.parametrize("metric", IMAGE_METRICS)
def test_error_non_bool_mask(metric):
    with pytest.raises(TypeError, match="`mask` must be a boolean"):
        metric(np.ones((30, 30)), np.ones((30, 30)), mask=np.ones((30, 30), np.uint8))


@pytest.mark.parametrize("metric", IMAGE_METRICS)
@pytest.mark.parametrize("bad", [np.nan, np.inf])
@pytest.mark.parametrize("name", ["estimate", "truth"])
def test_error_non_finite_inside_mask(rng, metric, bad, name):
    images = {"estimate": rng.random((30, 30, 3)), "truth": rng.random((30, 30, 3))}
    images[name][4, 5, 1] = bad
    with pytest.raises(ValueError, match=f"`{name}` contains non-finite.*1 pixel"):
        metric(images["estimate"], images["truth"])


@pytest.mark.parametrize("metric", IMAGE_METRICS)
def test_error_bad_dimensions_and_dtype(metric):
    with pytest.raises(ValueError, match=r"`estimate`.*\(H, W\).*\(2, 30, 30, 3\)"):
        metric(np.ones((2, 30, 30, 3)), np.ones((2, 30, 30, 3)))
    with pytest.raises(TypeError, match="`truth` must be a real-valued"):
        metric(np.ones((30, 30)), np.ones((30, 30), dtype=complex))


def test_error_lmse_window_and_step():
    img = np.ones((30, 30))
    with pytest.raises(ValueError, match="`window` must be an integer >= 1; got 0"):
        lmse(img, img, window=0)
    with pytest.raises(ValueError, match="`step` must be an integer >= 1; got -1"):
        lmse(img, img, step=-1)
    with pytest.raises(TypeError, match="`window` must be an integer"):
        lmse(img, img, window=2.5)
    with pytest.raises(TypeError, match="`step` must be an integer"):
        lmse(img, img, step=True)
    with pytest.raises(ValueError, match=r"`window` \(31\).*\(30, 30\)"):
        lmse(img, img, window=31)


def test_error_lmse_undefined_zero_truth():
    # truth nonzero only in a margin that no window covers (columns 40-44
    # with window 20, step 10 on a width of 45) -> 0/0.
    truth = np.zeros((20, 45))
    truth[:, 40:] = 1.0
    with pytest.raises(ValueError, match="LMSE is undefined.*`truth`"):
        lmse(np.ones((20, 45)), truth)
    with pytest.raises(ValueError, match="si_mse is undefined"):
        si_mse(np.ones((20, 45)), np.zeros((20, 45)))


def test_error_lmse_score_names_argument():
    good = np.ones((30, 30))
    with pytest.raises(ValueError, match="`shading` and `true_shading`"):
        lmse_score(good, good, good, np.ones((30, 31)))
    bad = good.copy()
    bad[0, 0] = np.nan
    with pytest.raises(ValueError, match="`true_reflectance` contains non-finite"):
        lmse_score(good, good, bad, good)


def test_error_psnr_ssim_data_range():
    img = np.ones((30, 30))
    with pytest.raises(ValueError, match="`data_range` must be a positive"):
        psnr(img, 2 * img, data_range=0.0)
    with pytest.raises(ValueError, match="`data_range` must be a positive"):
        ssim(img, 2 * img, data_range=np.nan)
    with pytest.raises(ValueError, match="cannot infer `data_range`"):
        psnr(2 * img, img)
    with pytest.raises(ValueError, match="at least 7x7"):
        ssim(np.ones((6, 30)), np.ones((6, 30)), data_range=1.0)
    border = np.zeros((30, 30), dtype=bool)
    border[:3, :] = True
    with pytest.raises(ValueError, match="`mask` selects only pixels within 3"):
        ssim(img, img, mask=border, data_range=1.0)


def test_error_ber_inputs():
    a = np.zeros((4, 5), dtype=bool)
    with pytest.raises(TypeError, match="`predicted_shadow` must be a boolean"):
        balanced_error_rate(a.astype(float), a)
    with pytest.raises(ValueError, match=r"`predicted_shadow` and `true_shadow`.*\(4, 5\).*\(4, 6\)"):
        balanced_error_rate(a, np.zeros((4, 6), dtype=bool))
    with pytest.raises(ValueError, match="`mask`.*all False"):
        balanced_error_rate(a, a, mask=np.zeros((4, 5), dtype=bool))
