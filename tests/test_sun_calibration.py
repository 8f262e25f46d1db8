"""Step 2 (paper Sec. 5): luminance clusters, light/shadow pairs, Eq. 5 and the median of all pairs.

The synthetic views are made with the forward model (Eq. 1) from known S_sky, S_ind, cos and a
straight cast-shadow edge, so the pairs' L_sun is known exactly.
"""

from __future__ import annotations

import numpy as np
import pytest

from mvintrinsic import Camera, View
from mvintrinsic.pixels import PixelQuantities
from mvintrinsic.sun_calibration import (
    REJECTION_RULES,
    SunCalibrationError,
    SunConfig,
    SunPairs,
    calibrate_sun,
    chromaticity,
    discontinuity_edges,
    find_sun_pairs,
    luminance_kmeans,
    shadow_regions,
)

H, W, EDGE = 60, 80, 40  # shadow on columns < EDGE
L_SUN = np.array([1.0, 0.9, 0.75])
SKY = np.array([0.22, 0.23, 0.27])
INDIRECT = np.array([0.08, 0.07, 0.05])
COSINE = 0.7


def make_view(reflectance_left, reflectance_right=None, *, noise=0.0, depth_step=0.0, seed=0, sunlit=False):
    """A view of a wall: left half in cast shadow (2-px linear penumbra), right half lit.

    ``sunlit``: the image has no shadow at all (the proxy's quantities still put the left half in it).
    """
    reflectance_right = reflectance_left if reflectance_right is None else reflectance_right
    cols = np.arange(W)
    visibility = np.clip((cols - EDGE + 1.5) / 3.0, 0.0, 1.0)[None, :].repeat(H, axis=0)
    reflectance = np.where((cols < EDGE)[None, :, None], np.asarray(reflectance_left), np.asarray(reflectance_right))
    reflectance = np.broadcast_to(reflectance, (H, W, 3))
    shading = SKY + INDIRECT + (1.0 if sunlit else visibility[..., None]) * L_SUN * COSINE
    image = reflectance * shading
    if noise:
        image = image * (1 + noise * np.random.default_rng(seed).standard_normal(image.shape))
    depth = np.full((H, W), 10.0) * np.where(cols < EDGE, 1.0, 1.0 + depth_step)[None, :]
    quantities = PixelQuantities(
        stem="wall",
        sky=np.broadcast_to(SKY, (H, W, 3)).astype(np.float32),
        indirect=np.broadcast_to(INDIRECT, (H, W, 3)).astype(np.float32),
        visibility=visibility.astype(np.float32),
        cosine=np.full((H, W), COSINE, np.float32),
        normals=np.broadcast_to([0.0, -1.0, 0.0], (H, W, 3)).astype(np.float32),
        depth=depth.astype(np.float32),
        sky_mask=np.zeros((H, W), bool),
        filled=np.zeros((H, W), bool),
        valid=np.ones((H, W), bool),
    )
    camera = Camera("PINHOLE", W, H, [60.0, 60.0, W / 2, H / 2], np.eye(3), np.zeros(3))
    return View("wall", image.astype(np.float32), camera), quantities


def test_luminance_kmeans_finds_four_groups_deterministically():
    rng = np.random.default_rng(1)
    means = np.array([0.05, 0.3, 0.6, 1.2])
    values = np.concatenate([m + 0.01 * rng.standard_normal(500) for m in means])
    labels, centres = luminance_kmeans(values, 4)
    np.testing.assert_allclose(centres, means, atol=0.003)
    np.testing.assert_array_equal(labels, np.repeat(np.arange(4), 500))
    labels2, centres2 = luminance_kmeans(values, 4)
    np.testing.assert_array_equal(centres, centres2)


def test_shadow_regions_keep_the_dark_side_inside_the_proxy_shadow():
    view, q = make_view([0.5, 0.45, 0.4])
    shadow, lit, clusters = shadow_regions(view.image, q)
    assert shadow[:, : EDGE - 2].all() and not shadow[:, EDGE + 2:].any()
    assert lit[:, EDGE + 2:].all() and not lit[:, : EDGE - 2].any()
    assert clusters[:, : EDGE - 2].all()


def test_pairs_of_one_material_give_the_exact_sun_radiance():
    view, q = make_view([0.5, 0.45, 0.4])
    pairs = find_sun_pairs(view, q)
    assert len(pairs) >= 10
    assert (pairs.lit[:, 1] > EDGE).all() and (pairs.shadow[:, 1] < EDGE - 1).all()
    np.testing.assert_allclose(pairs.estimates, np.broadcast_to(L_SUN, pairs.estimates.shape), rtol=1e-5)
    calibration = calibrate_sun([pairs])
    np.testing.assert_allclose(calibration.sun_radiance, L_SUN, rtol=1e-5)
    assert calibration.n_pairs == len(pairs) and not calibration.fallback
    assert sum(pairs.rejected.values()) + len(pairs) == pairs.n_samples


def test_ties_go_to_the_nearest_pixels_beyond_the_penumbra():
    view, q = make_view([0.5, 0.45, 0.4])  # uniform material: every walk pixel beyond the penumbra ties
    pairs = find_sun_pairs(view, q)
    # the smoothed values tie up to rounding; the nearest pixels past the 5x5 window's reach win
    assert (pairs.lit[:, 1] <= EDGE + 5).all() and (pairs.lit[:, 1] > EDGE).all()
    assert (pairs.shadow[:, 1] >= EDGE - 6).all() and (pairs.shadow[:, 1] < EDGE - 1).all()
    smoothed = SunConfig(smoothing=5)
    tol = [find_sun_pairs(View(view.stem, view.image * np.float32(f), view.camera), q, config=smoothed).lit
           for f in (1.0, 3.0)]
    np.testing.assert_array_equal(tol[0], tol[1])  # a global scale (rounding differs) picks the same pixels


def test_median_pick_is_exact_on_one_material_too():
    view, q = make_view([0.5, 0.45, 0.4])
    pairs = find_sun_pairs(view, q, config=SunConfig(pick="median"))
    assert len(pairs) >= 10
    np.testing.assert_allclose(pairs.estimates, np.broadcast_to(L_SUN, pairs.estimates.shape), rtol=1e-5)


def test_smoothing_removes_the_bias_of_picking_noisy_extremes():
    view, q = make_view([0.5, 0.45, 0.4], noise=0.05, seed=3)
    raw = calibrate_sun([find_sun_pairs(view, q, config=SunConfig(smoothing=1))]).sun_radiance
    smooth = calibrate_sun([find_sun_pairs(view, q)]).sun_radiance
    raw_error = np.abs(raw / L_SUN - 1)
    smooth_error = np.abs(smooth / L_SUN - 1)
    assert (smooth_error < 0.05).all(), smooth_error
    assert (raw > L_SUN).all(), "the darkest noisy shadow pixel biases Eq. 5 upward"
    assert (smooth_error < raw_error).all(), (smooth_error, raw_error)


def test_different_chromaticities_across_the_edge_give_no_pair():
    view, q = make_view([0.2, 0.5, 0.2], [0.6, 0.3, 0.2])
    gap = np.linalg.norm(chromaticity(np.asarray(view.image)[0, 0]) - chromaticity(np.asarray(view.image)[0, -1]))
    assert gap > SunConfig().chroma_tolerance
    pairs = find_sun_pairs(view, q)
    assert len(pairs) == 0
    assert pairs.rejected["no_similar_chromaticity"] == pairs.n_samples > 0


def test_a_sunlit_darker_material_is_no_pair_unless_the_paper_is_asked():
    # The proxy says shadow on the left, but the left is in the sun, 20% darker than the right: the
    # pair's contrast (1.25) is the material's, and Eq. 5 turns it into a sun of a fraction of the truth.
    right = np.array([0.5, 0.45, 0.4])
    view, q = make_view(0.8 * right, right, sunlit=True)
    paper = find_sun_pairs(view, q, config=SunConfig(min_pair_contrast=None))
    assert len(paper) >= 10 and paper.rejected["low_contrast"] == 0
    assert (calibrate_sun([paper]).sun_radiance < 0.25 * L_SUN).all()
    ours = find_sun_pairs(view, q)
    assert len(ours) == 0 and ours.rejected["low_contrast"] == len(paper)
    assert sum(ours.rejected.values()) == ours.n_samples
    # a true shadow of the same contrast range keeps every pair: its contrast is 1 + L cos / S_env ~ 3
    view, q = make_view(right)
    assert find_sun_pairs(view, q).rejected["low_contrast"] == 0


def test_a_depth_discontinuity_on_the_walk_rejects_the_sample():
    view, q = make_view([0.5, 0.45, 0.4], depth_step=0.05)
    edges = discontinuity_edges(q)
    assert edges[5:-5, EDGE - 1:EDGE + 1].any(axis=1).all()
    pairs = find_sun_pairs(view, q)
    assert len(pairs) == 0 and pairs.rejected["discontinuity"] == pairs.n_samples > 0


def test_no_pair_raises_unless_allowed():
    view, q = make_view([0.2, 0.5, 0.2], [0.6, 0.3, 0.2])
    pairs = [find_sun_pairs(view, q)]
    with pytest.raises(SunCalibrationError, match="no light/shadow pair"):
        calibrate_sun(pairs)
    with pytest.warns(RuntimeWarning, match="L_sun = 0"):
        fallback = calibrate_sun(pairs, allow_missing=True)
    assert fallback.fallback and (fallback.sun_radiance == 0).all()
    assert set(fallback.rejected) == set(REJECTION_RULES)


def test_median_is_per_channel_over_all_views():
    def pairs(stem, values):
        values = np.asarray(values, float)
        n = len(values)
        return SunPairs(stem, np.zeros((n, 2), int), np.zeros((n, 2), int), values, n, dict.fromkeys(REJECTION_RULES, 0))

    a = pairs("a", [[1, 5, 9], [2, 6, 7]])
    b = pairs("b", [[3, 4, 8]])
    result = calibrate_sun([a, b])
    np.testing.assert_array_equal(result.sun_radiance, [2, 5, 8])
    assert result.n_pairs == 3


@pytest.mark.parametrize("bad", [{"n_clusters": 1}, {"walk": 0}, {"chroma_tolerance": 0}, {"min_cosine": 1.0},
                                 {"smoothing": 0}, {"boundary_step": 2.5}, {"pick": "max"}, {"normal_sigma": -1.0},
                                 {"min_pair_contrast": 0.5}, {"min_pair_contrast": "high"}])
def test_config_validation_names_the_field(bad):
    with pytest.raises(ValueError, match=next(iter(bad))):
        SunConfig(**bad)


def test_quantities_of_another_view_are_refused():
    view, q = make_view([0.5, 0.45, 0.4])
    other = View("other", view.image, view.camera)
    with pytest.raises(ValueError, match="do not belong"):
        find_sun_pairs(other, q)
