"""Multi-view, pixel-level shadow labelling (mvintrinsic.multiview_shadows) and cross-view correspondences.

The scenes are a textured ground plane seen by several cameras, rendered with the forward model
(Eq. 1), ``I = R (S_env + v L_sun cos)``, from known shading. The proxy is the plane alone: its
``~v`` says lit everywhere, as an MVS proxy that lost the caster would.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from conftest import look_at

from mvintrinsic.camera import Camera
from mvintrinsic.correspondence import (
    Correspondences,
    cross_view_agreement,
    cross_view_reflectance_spread,
    cross_view_value_agreement,
    find_correspondences,
    fuse_views,
)
from mvintrinsic.multiview_shadows import (
    LOG_CHROMA,
    MultiViewShadowConfig,
    albedo_term,
    build_palette,
    consensus,
    edge_offsets,
    edge_scale,
    edge_votes,
    grid_cut,
    label_shadows_multiview,
    palette_visibility,
    potts_weights,
    proxy_prior,
)
from mvintrinsic.photo_occupancy import ClearRaysConfig
from mvintrinsic.pixels import PixelQuantities
from mvintrinsic.results import SHADOW_LABELS
from mvintrinsic.scene import View

L_SUN = np.array([1.0, 0.9, 0.75])
S_ENV = np.array([0.30, 0.35, 0.45])      # a blue sky and little indirect light
COSINE = 0.8                              # the sun's elevation above the plane: cos = sin(elevation)
LIGHT = np.array([0.60, 0.50, 0.40])      # plaster-like
DARK = np.array([0.12, 0.10, 0.08])       # the same hue five times darker
UP = np.array([0.0, 0.0, 1.0])


def albedo_at(x, y, *, patch=None, patch_colour=DARK):
    """Plane albedo: LIGHT with a mild deterministic texture; ``patch`` = (x0, x1, y0, y1) painted."""
    texture = 1.0 + 0.04 * np.sin(7.0 * x) * np.cos(5.0 * y)
    albedo = LIGHT * texture[..., None]
    if patch is not None:
        x0, x1, y0, y1 = patch
        inside = (x >= x0) & (x < x1) & (y >= y0) & (y < y1)
        albedo = np.where(inside[..., None], patch_colour * texture[..., None], albedo)
    return albedo


def plane_view(stem, center, target, *, size=(96, 72), focal=90.0, shadow_x=None, patch=None,
               patch_colour=DARK, noise=0.004, seed=0):
    """A view of the ground plane z = 0 and its PixelQuantities; the sun is blocked where x < shadow_x."""
    w, h = size
    rotation, translation = look_at(np.asarray(center, float), np.asarray(target, float), up=(0.0, 1.0, 0.0))
    camera = Camera("PINHOLE", w, h, [focal, focal, w / 2, h / 2], rotation, translation)
    rays = camera.pixel_rays().reshape(h, w, 3)
    t = -camera.center[2] / rays[..., 2]
    points = camera.center + rays * t[..., None]
    x, y = points[..., 0], points[..., 1]
    albedo = albedo_at(x, y, patch=patch, patch_colour=patch_colour)
    visibility = np.ones((h, w)) if shadow_x is None else (x >= shadow_x).astype(float)
    shading = S_ENV + visibility[..., None] * L_SUN * COSINE
    rng = np.random.default_rng(seed)
    image = (albedo * shading * (1 + noise * rng.standard_normal((h, w, 3)))).astype(np.float32)
    ones = np.ones((h, w), dtype=bool)
    q = PixelQuantities(
        stem=stem, sky=np.broadcast_to(S_ENV, (h, w, 3)).astype(np.float32), indirect=np.zeros((h, w, 3), np.float32),
        visibility=np.ones((h, w), np.float32), cosine=np.full((h, w), COSINE, np.float32),
        normals=np.broadcast_to(UP, (h, w, 3)).astype(np.float32), depth=t.astype(np.float32),
        sky_mask=~ones, filled=~ones, valid=ones)
    return View(stem=stem, image=image, camera=camera), q, visibility >= 0.5


def overview(stem, dx, **kw):
    return plane_view(stem, (dx, -0.5, 5.0), (0.0, 0.0, 0.0), **kw)


@pytest.fixture(scope="module")
def straddling_patch():
    """A dark patch straddling a cast shadow's edge (x = 0): three views see the edge cross both
    materials; the fourth sees only the shadowed part of the patch."""
    patch = (-1.5, 1.5, -1.2, 1.2)
    views, quantities, truth = [], {}, {}
    for i, dx in enumerate((-1.0, 0.0, 1.0)):
        view, q, lit = overview(f"view_{i}", dx, shadow_x=0.0, patch=patch, seed=i)
        views.append(view)
        quantities[view.stem], truth[view.stem] = q, lit
    view, q, lit = plane_view("view_3", (-0.8, 0.0, 3.0), (-0.8, 0.0, 0.0), size=(48, 36), focal=120.0,
                              shadow_x=0.0, patch=patch, seed=3)
    views.append(view)
    quantities[view.stem], truth[view.stem] = q, lit
    return views, quantities, truth


def test_the_fourth_view_alone_cannot_tell(straddling_patch):
    views, quantities, truth = straddling_patch
    assert not truth["view_3"].any()  # it sees shadow only, on the dark patch only
    alone = label_shadows_multiview(views[3:], quantities, L_SUN)
    assert alone["view_3"].shadow.mean() < 0.5


def test_a_shadow_clear_in_three_views_decides_the_fourth(straddling_patch):
    views, quantities, truth = straddling_patch
    result = label_shadows_multiview(views, quantities, L_SUN)
    assert result["view_3"].shadow.mean() > 0.95
    for stem in ("view_0", "view_1", "view_2"):
        wrong = (result[stem].shadow == truth[stem]).mean()
        assert wrong < 0.03, stem
    assert result.correspondences is not None


def test_a_dark_painted_patch_without_shadow_stays_lit():
    # A grey darkening (same factor in every channel), not the colour shift of a shadow.
    patch, grey = (-0.8, 0.8, -0.6, 0.6), 0.25 * LIGHT
    views, quantities = [], {}
    for i, dx in enumerate((-1.0, 0.0, 1.0)):
        view, q, _ = overview(f"view_{i}", dx, patch=patch, patch_colour=grey, seed=i)
        views.append(view)
        quantities[view.stem] = q
    result = label_shadows_multiview(views, quantities, L_SUN)
    for stem in quantities:
        assert result[stem].shadow.mean() < 0.01, stem


def test_the_order_of_the_views_changes_no_label(straddling_patch):
    views, quantities, _ = straddling_patch
    first = label_shadows_multiview(views, quantities, L_SUN)
    shuffled = label_shadows_multiview([views[2], views[0], views[3], views[1]], quantities, L_SUN)
    assert list(first.views) == list(shuffled.views) == sorted(quantities)
    for stem in quantities:
        np.testing.assert_array_equal(first[stem].labels, shuffled[stem].labels)
        np.testing.assert_array_equal(first[stem].score, shuffled[stem].score)


def test_a_single_view_still_works():
    view, q, lit = overview("only", 0.0, shadow_x=0.0)
    result = label_shadows_multiview([view], {"only": q}, L_SUN)
    assert result.correspondences is None
    labels = result["only"]
    assert labels.labels.dtype == np.uint8 and set(np.unique(labels.labels)) <= {0, 255}
    assert (labels.shadow == lit).mean() < 0.03
    finite = np.isfinite(labels.visibility)
    assert finite.all() and ((labels.visibility >= 0) & (labels.visibility <= 1)).all()


def test_no_sun_labels_everything_lit():
    view, q, _ = overview("only", 0.0, shadow_x=0.0)
    result = label_shadows_multiview([view], {"only": q}, np.zeros(3))
    assert (result["only"].labels == SHADOW_LABELS["lit"]).all() and result.palette is None


def test_invalid_pixels_are_undecided():
    view, q, _ = overview("only", 0.0, shadow_x=0.0)
    valid = q.valid.copy()
    valid[:10] = False
    q = dataclasses.replace(q, valid=valid)
    labels = label_shadows_multiview([view], {"only": q}, L_SUN)["only"]
    assert (labels.labels[:10] == SHADOW_LABELS["undecided"]).all()
    assert np.isnan(labels.visibility[:10]).all() and (labels.score[:10] == 0).all()


@pytest.mark.parametrize(("kwargs", "match"), [
    ({"iterations": -1}, "iterations"),
    ({"visibility_levels": 1}, "visibility_levels"),
    ({"palette_bins": (0.1, 0.0, 0.1)}, "palette_bins"),
    ({"edge_radii": (0, 2)}, "edge_radii"),
    ({"edge_reference": -1}, "edge_reference"),
    ({"prior_shadow": -0.1}, "prior_shadow"),
    ({"contrast": 0.0}, "contrast"),
    ({"palette_groups": "material"}, "palette_groups"),
    ({"edge_blur": float("nan")}, "edge_blur"),
])
def test_config_is_validated(kwargs, match):
    with pytest.raises(ValueError, match=match):
        MultiViewShadowConfig(**kwargs)


def test_bad_arguments_are_named():
    view, q, _ = overview("only", 0.0)
    with pytest.raises(TypeError, match="views"):
        label_shadows_multiview(view, {"only": q}, L_SUN)
    with pytest.raises(ValueError, match="quantities"):
        label_shadows_multiview([view], {}, L_SUN)
    with pytest.raises(ValueError, match="sun_radiance"):
        label_shadows_multiview([view], {"only": q}, [1.0, -1.0, 1.0])
    with pytest.raises(ValueError, match="sun_radiance"):
        label_shadows_multiview([view], {"only": q}, [1.0, np.nan, 1.0])
    with pytest.raises(ValueError, match="twice"):
        label_shadows_multiview([view, view], {"only": q}, L_SUN)


# -- the pieces ------------------------------------------------------------------------------------
def test_palette_peaks_at_its_samples_and_normalises():
    rng = np.random.default_rng(0)
    samples = np.log(LIGHT) + 0.01 * rng.standard_normal((500, 3))
    palette = build_palette(samples, bins=(0.15, 0.05, 0.05), smoothing=1.0)
    assert palette.density.sum() == pytest.approx(1.0)
    near, far = palette.log_density(np.log([LIGHT, DARK]))
    assert near > far + 5
    assert palette.log_density(np.log([[50.0, 1e-5, 3.0]]))[0] == pytest.approx(np.log(1e-7))
    empty = build_palette(np.zeros((0, 3)))
    assert empty.density.sum() == 0


def test_palette_visibility_recovers_partial_sun():
    palette = build_palette(np.log(np.tile(LIGHT, (50, 1))), smoothing=0.5)
    v = np.array([0.0, 0.3, 0.5, 1.0])
    image = LIGHT * (S_ENV + v[:, None] * L_SUN * COSINE)
    found, gain = palette_visibility(np.log(image), np.tile(S_ENV, (4, 1)), np.tile(L_SUN * COSINE, (4, 1)), palette,
                                     levels=11)
    np.testing.assert_allclose(found, v, atol=0.051)
    assert (gain > 1).all()


def test_edge_votes_point_the_bright_side_to_the_light():
    h, w = 20, 40
    lit = np.broadcast_to(np.arange(w) >= 20, (h, w))
    image = LIGHT * (S_ENV + lit[..., None] * L_SUN * COSINE)
    ratio = np.broadcast_to(np.log1p(L_SUN * COSINE / S_ENV), (h, w, 3))
    lit_vote, shadow_vote = edge_votes(np.log(image), ratio, np.ones((h, w), bool))
    near = slice(14, 26)
    assert (lit_vote[:, 20:26] > 1).all() and (shadow_vote[:, 14:20] > 1).all()
    assert (lit_vote[:, 14:20] == 0).all() and (shadow_vote[:, 20:26] == 0).all()
    assert (lit_vote[:, :5] == 0).all() and (shadow_vote[:, -5:] == 0).all()  # out of reach of the edge
    assert near.start < near.stop


def test_edge_radii_scale_with_the_longer_image_side_only_upward():
    assert edge_scale((360, 480), 480) == 1 and edge_scale((180, 240), 480) == 1  # never below the radii
    assert edge_scale((750, 1000), 480) == 2 and edge_scale((1064, 1416), 480) == 3
    assert edge_scale((750, 1000), 0) == 1  # 0: never scaled


def test_edge_offsets_are_symmetric_and_unique():
    offsets = edge_offsets((2, 4), 16)
    assert len(offsets) == len(set(offsets)) and (0, 0) not in offsets
    assert all((-dy, -dx) in offsets for dy, dx in offsets)


def test_grid_cut_follows_the_image_edge_through_noisy_evidence():
    h, w = 30, 30
    truth = np.broadcast_to(np.arange(w) >= 12, (h, w))
    guide = np.where(truth[..., None], 0.0, -1.5) * np.ones(3)
    rng = np.random.default_rng(1)
    score = np.where(truth, 0.3, -0.3) + 0.6 * rng.standard_normal((h, w))
    valid = np.ones((h, w), bool)
    raw = (score > 0) == truth
    lit = grid_cut(np.maximum(score, 0), np.maximum(-score, 0), guide, valid, smoothness=2.0, contrast=0.3)
    assert raw.mean() < 0.8 and (lit == truth).mean() > 0.99
    valid[0] = False
    assert grid_cut(np.maximum(score, 0), np.maximum(-score, 0), guide, valid)[0].all()


def test_albedo_term_and_proxy_prior():
    r1 = np.log([[0.5, 0.4, 0.3], [0.1, 0.1, 0.1]])
    r0 = np.log([[2.0, 1.6, 0.9], [0.4, 0.3, 0.2]])
    np.testing.assert_allclose(albedo_term(r0, r1), [np.log(2.0), 0.0])
    np.testing.assert_allclose(proxy_prior([1.0, 0.75, 0.5, 0.25, 0.0], lit=0.1, shadow=0.4),
                               [0.1, 0.05, 0.0, -0.2, -0.4])


def test_log_chroma_axes():
    grey = np.log([0.3, 0.3, 0.3]) @ LOG_CHROMA.T
    assert grey[1] == pytest.approx(0.0) and grey[2] == pytest.approx(0.0)


# -- correspondences -------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def two_views():
    a, qa, _ = overview("a", -0.5, shadow_x=0.0)
    b, qb, _ = overview("b", 0.5, shadow_x=0.0)
    return [a, b], {"a": qa, "b": qb}


def test_correspondences_match_the_projection_of_the_plane(two_views):
    views, quantities = two_views
    corr = find_correspondences(views, quantities)
    assert isinstance(corr, Correspondences) and corr.stems == ("a", "b")
    index = corr.index["a", "b"]
    found = np.flatnonzero(index >= 0)
    assert len(found) > 0.5 * index.size
    # The pixel of b must contain the projection of a's surface point.
    a, b = views
    h, w = a.shape
    rays = a.camera.pixel_rays()[found]
    t = quantities["a"].depth.ravel()[found]
    pixels, _ = b.camera.project(a.camera.center + rays * t[:, None])
    expected = pixels[:, 1].astype(int) * b.shape[1] + pixels[:, 0].astype(int)
    np.testing.assert_array_equal(index[found], expected)
    assert corr.consistent["a", "b"][found].mean() > 0.99
    assert corr.seen_by("a").max() == 1 and corr.agreeing("b").shape == b.shape


def test_a_photo_that_disagrees_is_not_consistent(two_views):
    views, quantities = two_views
    altered = View(stem="b", image=views[1].image * np.float32(2.0), camera=views[1].camera)
    corr = find_correspondences([views[0], altered], quantities)
    assert not corr.consistent["a", "b"].any() and (corr.index["a", "b"] >= 0).any()


def test_fuse_views_averages_consistent_correspondences(two_views):
    views, quantities = two_views
    corr = find_correspondences(views, quantities)
    values = {"a": np.zeros(views[0].shape), "b": np.ones(views[1].shape)}
    fused = fuse_views(values, corr)
    matched = corr.consistent["a", "b"].reshape(views[0].shape)
    np.testing.assert_allclose(fused["a"][matched], 0.5)
    np.testing.assert_allclose(fused["a"][~matched], 0.0)
    np.testing.assert_allclose(fuse_views(values, corr, weight=0.0)["b"], 1.0)
    with pytest.raises(ValueError, match="weight"):
        fuse_views(values, corr, weight=-1.0)


def test_cross_view_agreement(two_views):
    views, quantities = two_views
    points = np.stack(np.meshgrid(np.linspace(-1, 1, 30), np.linspace(-1, 1, 30), [0.0]), -1).reshape(-1, 3)
    lit = {s: np.broadcast_to(True, v.shape) for s, v in zip(quantities, views, strict=True)}
    same = cross_view_agreement(views, quantities, lit, points)
    assert same.fraction == 1.0 and same.points > 0.8 * len(points)
    codes = {"a": np.full(views[0].shape, SHADOW_LABELS["lit"], np.uint8),
             "b": np.full(views[1].shape, SHADOW_LABELS["shadow"], np.uint8)}
    assert cross_view_agreement(views, quantities, codes, points).fraction == 0.0
    codes["b"] = np.full(views[1].shape, SHADOW_LABELS["undecided"], np.uint8)  # undecided is not read
    assert cross_view_agreement(views, quantities, codes, points).fraction is None


def test_cross_view_value_agreement(two_views):
    views, quantities = two_views
    points = np.stack(np.meshgrid(np.linspace(-1, 1, 30), np.linspace(-1, 1, 30), [0.0]), -1).reshape(-1, 3)
    a, b = views[0].shape, views[1].shape
    # 0.45 against 0.55: the binary measure's states differ (0.5 threshold), the values by 0.1
    soft = {"a": np.full(a, 0.45), "b": np.full(b, 0.55)}
    assert cross_view_value_agreement(views, quantities, soft, points).fraction == 1.0
    assert cross_view_agreement(views, quantities, {k: v >= 0.5 for k, v in soft.items()}, points).fraction == 0.0
    # 0.55 against 0.95: the same state, 0.4 apart: agreeing at 0.5, not at 0.3
    soft = {"a": np.full(a, 0.55), "b": np.full(b, 0.95)}
    assert cross_view_value_agreement(views, quantities, soft, points).fraction == 1.0
    assert cross_view_value_agreement(views, quantities, soft, points, tolerance=0.3).fraction == 0.0
    # binary layers give the binary measure's fraction, half the points one way
    left = np.zeros(a)
    left[:, : a[1] // 2] = 1.0
    binary = {"a": left, "b": np.ones(b)}
    expected = cross_view_agreement(views, quantities, {k: v >= 0.5 for k, v in binary.items()}, points)
    got = cross_view_value_agreement(views, quantities, binary, points)
    assert 0.0 < got.fraction < 1.0 and got.fraction == expected.fraction and got.points == expected.points
    # NaN is not read: nothing is seen twice
    assert cross_view_value_agreement(views, quantities, {"a": left, "b": np.full(b, np.nan)}, points).fraction is None
    with pytest.raises(ValueError, match="tolerance"):
        cross_view_value_agreement(views, quantities, binary, points, tolerance=0.0)
    with pytest.raises(ValueError, match="values"):
        cross_view_value_agreement(views, quantities, {"a": left}, points)



def test_cross_view_reflectance_spread(two_views):
    views, quantities = two_views
    points = np.stack(np.meshgrid(np.linspace(-1, 1, 30), np.linspace(-1, 1, 30), [0.0]), -1).reshape(-1, 3)
    one = {v.stem: np.full((*v.shape, 3), 0.4) for v in views}
    same = cross_view_reflectance_spread(views, quantities, one, points)
    assert same.median == (0.0, 0.0, 0.0) and same.points > 0.8 * len(points)
    # b reads 1.2 times a in the red channel: the two-view median is their mean, 1.1 * 0.4, so each
    # reading is 0.1 / 1.1 from it; green and blue agree.
    apart = dict(one, b=one["b"] * np.array([1.2, 1.0, 1.0]))
    spread = cross_view_reflectance_spread(views, quantities, apart, points)
    np.testing.assert_allclose(spread.median, [0.1 / 1.1, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(spread.p90, [0.1 / 1.1, 0.0, 0.0], atol=1e-12)
    # A view without reflectance there (zeros: sky, no estimate) is not read: no point is seen twice.
    none = dict(one, b=np.zeros_like(one["b"]))
    empty = cross_view_reflectance_spread(views, quantities, none, points)
    assert empty.median is None and empty.points == 0
    with pytest.raises(ValueError, match="reflectance"):
        cross_view_reflectance_spread(views, quantities, {"a": one["a"]}, points)
    with pytest.raises(ValueError, match="points"):
        cross_view_reflectance_spread(views, quantities, one, points[:, :2])

def test_consensus_takes_the_majority_of_consistent_views():
    # Three 1x4 views that see the same four points in the same pixels; view "b" alone calls the
    # second pixel shadow, and "c" cannot see (no consistent partner for) the last one.
    stems = ("a", "b", "c")
    same = np.arange(4)
    index, consistent = {}, {}
    for i in stems:
        for j in stems:
            if i != j:
                index[i, j] = same.copy()
                consistent[i, j] = np.array([True, True, True, "c" not in (i, j)])
    corr = Correspondences(stems=stems, shapes={s: (1, 4) for s in stems}, index=index, consistent=consistent,
                           depth_tolerance=0.03, photo_tolerance=0.25)
    lit = {"a": np.array([[True, True, False, True]]),
           "b": np.array([[True, False, False, False]]),
           "c": np.array([[True, True, False, True]])}
    out = consensus(lit, corr)
    np.testing.assert_array_equal(out["b"][0, :3], [True, True, False])   # outvoted two to one
    assert out["a"][0, 3] and not out["b"][0, 3]                           # a tie keeps each its own
    shuffled = consensus({s: lit[s] for s in reversed(stems)}, corr)
    assert all(np.array_equal(out[s], shuffled[s]) for s in stems)
    # An invalid pixel neither votes nor changes.
    valid = {s: np.ones((1, 4), bool) for s in stems}
    valid["a"][0, 1] = valid["c"][0, 1] = False
    held = consensus(lit, corr, valid)
    assert not held["b"][0, 1] and held["a"][0, 1]


def _edge_votes_by_definition(a, lam, valid, *, sigma=0.15, material_cost=2.0, offsets=None):
    """Term 1 of the module docstring pair by pair, in float64: what edge_votes computes faster."""
    h, w = valid.shape
    lit, shadow = np.zeros((h, w)), np.zeros((h, w))
    scale = 1.0 / (2 * sigma * sigma)
    for y in range(h):
        for x in range(w):
            for dy, dx in offsets:
                if not (0 <= y + dy < h and 0 <= x + dx < w) or not (valid[y, x] and valid[y + dy, x + dx]):
                    continue
                jump, ratio = a[y, x] - a[y + dy, x + dx], 0.5 * (lam[y, x] + lam[y + dy, x + dx])
                c_lit, c_shadow, c_same = (scale * np.sum((jump - ratio) ** 2), scale * np.sum((jump + ratio) ** 2),
                                           scale * np.sum(jump ** 2))
                lit[y, x] = max(lit[y, x], min(c_shadow, c_same, material_cost) - c_lit)
                shadow[y, x] = max(shadow[y, x], min(c_lit, c_same, material_cost) - c_shadow)
    return lit, shadow


@pytest.mark.parametrize("offsets", [edge_offsets((1, 2), 8), [(0, 1), (1, 1), (2, -1)]])  # mirrored; one-sided
def test_edge_votes_score_each_pair_as_defined(offsets):
    """The vectorised votes (float32, each mirrored pair scored once) equal the definition."""
    rng = np.random.default_rng(3)
    a = np.log(rng.uniform(0.05, 1.0, (9, 11, 3)))
    lam = rng.uniform(0.2, 2.0, (9, 11, 3))
    valid = rng.random((9, 11)) > 0.2
    fast = edge_votes(a, lam, valid, offsets=offsets)
    slow = _edge_votes_by_definition(a, lam, valid, offsets=offsets)
    for f, r in zip(fast, slow, strict=True):
        np.testing.assert_allclose(f, r, atol=2e-5)


def test_grid_cut_with_precomputed_potts_weights_is_the_same_cut():
    rng = np.random.default_rng(4)
    guide = np.log(rng.uniform(0.1, 1.0, (30, 40, 3)))
    valid = rng.random((30, 40)) > 0.1
    score = rng.normal(size=(30, 40))
    cost_shadow, cost_lit = np.maximum(score, 0), np.maximum(-score, 0)
    weights = potts_weights(guide, valid, smoothness=1.0, contrast=0.3)
    assert len(weights) == 4 and all(w.shape == (30, 40) and (w[~valid] == 0).all() for w in weights)
    np.testing.assert_array_equal(grid_cut(cost_shadow, cost_lit, guide, valid, weights=weights),
                                  grid_cut(cost_shadow, cost_lit, guide, valid))


def _sun_at_cosine() -> np.ndarray:
    """Unit vector toward the sun whose cosine with the plane's normal is COSINE (azimuth 30 degrees)."""
    horizontal = np.sqrt(1.0 - COSINE**2)
    return np.array([horizontal * np.cos(np.radians(30.0)), horizontal * np.sin(np.radians(30.0)), COSINE])


def test_a_shadow_coloured_patch_is_lit_where_the_photos_see_the_sun_ray_free():
    # The patch's albedo is the plaster's in shadow: its ratio to the plaster, channel by channel, is the
    # shadow ratio, so every test on the image reads it as plaster in shadow (window glass in a painted
    # frame is such a case). Nothing stands above the plane, and every view sees its sun rays' paths
    # free: with the sun's direction, the proxy's "lit" is trusted at ClearRaysConfig.prior. Here the
    # image evidence for a shadow is unambiguous (no texture, 0.4% noise), and the default prior (0.3)
    # leaves it (on the scenes it tips the balanced cases: docs/step3.md); a prior of 3 shows the term.
    patch = (-0.8, 0.8, -0.6, 0.6)
    colour = LIGHT * S_ENV / (S_ENV + L_SUN * COSINE)
    views, quantities = [], {}
    for i, (dx, dy) in enumerate(((-1.0, -0.5), (0.0, -0.8), (1.0, -0.5), (0.0, 0.6))):
        view, q, _ = plane_view(f"view_{i}", (dx, dy, 5.0), (0.0, 0.0, 0.0), patch=patch, patch_colour=colour, seed=i)
        views.append(view)
        quantities[view.stem] = q
    config = MultiViewShadowConfig(clear_rays=ClearRaysConfig(distance=3.0, prior=3.0))
    before = label_shadows_multiview(views, quantities, L_SUN, config=config)
    default = label_shadows_multiview(views, quantities, L_SUN, sun_direction=_sun_at_cosine(),
                                      config=MultiViewShadowConfig(clear_rays=ClearRaysConfig(distance=3.0)))
    after = label_shadows_multiview(views, quantities, L_SUN, config=config, sun_direction=_sun_at_cosine())
    assert after.timings["clear_rays"] > 0 and before.timings["clear_rays"] == 0
    for view in views:
        q = quantities[view.stem]
        rays = view.camera.pixel_rays().reshape(*view.shape, 3)
        points = view.camera.center + rays * q.depth[..., None]
        inside = ((points[..., 0] >= patch[0]) & (points[..., 0] < patch[1])
                  & (points[..., 1] >= patch[2]) & (points[..., 1] < patch[3]))
        # Measured: the patch is labelled shadow on all its pixels without the sun's direction and with
        # the default prior, on none with the prior of 3; the plaster stays lit.
        assert before[view.stem].shadow[inside].mean() > 0.9, view.stem
        assert default[view.stem].shadow[inside].mean() > 0.9, view.stem
        assert after[view.stem].shadow[inside].mean() < 0.05, view.stem
        assert after[view.stem].shadow[~inside].mean() < 0.01, view.stem
    # clear_rays=None: the labelling before it, with or without the sun's direction.
    off = dataclasses.replace(config, clear_rays=None)
    unchanged = label_shadows_multiview(views, quantities, L_SUN, config=off, sun_direction=_sun_at_cosine())
    for view in views:
        np.testing.assert_array_equal(unchanged[view.stem].labels, before[view.stem].labels)
    with pytest.raises(TypeError, match="clear_rays"):
        MultiViewShadowConfig(clear_rays=0.3)
