"""Step 4 (mvintrinsic.env_refine): the paper's S_env offsets and the multi-view reflectance fusion.

The paper's method is tested on a planar 1-D shadow boundary built from Eq. 1; the fusion on the
textured ground plane seen by several cameras of ``test_multiview_shadows``.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from test_multiview_shadows import COSINE, L_SUN, S_ENV, overview

from mvintrinsic.correspondence import cross_view_reflectance_spread, find_correspondences
from mvintrinsic.env_refine import (
    EnvRefineConfig,
    boundary_pairs,
    fuse_reflectance,
    refine,
    refine_environment,
    relayer,
    with_reflectance,
)
from mvintrinsic.results import SHADOW_LABELS, IntrinsicLayers

H, W = 40, 80
ALBEDO = np.array([0.45, 0.40, 0.32])
SUN = np.array([2.4, 2.2, 1.9])     # S_sun = L_sun cos on the lit half
ENV = np.array([0.50, 0.56, 0.70])  # the true S_env


def boundary(env_shadow_scale=1.0, seed=0):
    """A plane of one albedo (mild texture), lit for x < W/2 and in shadow beyond; the layers carry
    the true S_sun and S_env, except S_env times ``env_shadow_scale`` on the shadowed half."""
    rng = np.random.default_rng(seed)
    x = np.arange(W)[None, :].repeat(H, 0)
    lit = x < W // 2
    texture = 1.0 + 0.03 * np.sin(0.7 * x)[..., None] * np.cos(0.5 * np.arange(H))[:, None, None]
    albedo = ALBEDO * texture
    image = albedo * (ENV + lit[..., None] * SUN) * (1 + 0.002 * rng.standard_normal((H, W, 3)))
    env = np.where(lit[..., None], ENV, ENV * env_shadow_scale) * np.ones((H, W, 3))
    visibility = lit.astype(np.float32)
    total = env + visibility[..., None] * SUN
    layers = IntrinsicLayers(
        stem="plane", reflectance=(image / total).astype(np.float32),
        sun_shading=np.broadcast_to(SUN, (H, W, 3)).astype(np.float32),
        sky_shading=(0.8 * env).astype(np.float32), indirect_shading=(0.2 * env).astype(np.float32),
        visibility=visibility,
        shadow_labels=np.where(lit, SHADOW_LABELS["lit"], SHADOW_LABELS["shadow"]).astype(np.uint8))
    return image.astype(np.float32), layers, albedo


def jump(reflectance):
    """Relative jump of the median reflectance across the boundary (columns W/2-4.. and ..W/2+3)."""
    left = np.median(reflectance[:, W // 2 - 4:W // 2], axis=(0, 1))
    right = np.median(reflectance[:, W // 2:W // 2 + 4], axis=(0, 1))
    return np.abs(right / left - 1.0)


# -- the paper's offsets (Sec. 7, Fig. 8) -----------------------------------------------------------
def test_a_wrongly_scaled_environment_gets_a_continuous_reflectance():
    image, layers, _ = boundary(env_shadow_scale=1.1)
    assert (jump(layers.reflectance) > 0.08).all()  # 1 / 1.1: the shadowed side 9% too dark
    out = refine_environment(image, layers, config=EnvRefineConfig(method="paper"))
    assert len(out.pairs) > 100
    assert (jump(out.layers.reflectance) < 0.01).all()
    np.testing.assert_allclose(out.layers.reconstruct(), image, rtol=1e-4)
    np.testing.assert_array_equal(out.layers.shadow_labels, layers.shadow_labels)


def test_an_exact_environment_is_kept_far_from_the_boundary():
    image, layers, _ = boundary(env_shadow_scale=1.0)
    out = refine_environment(image, layers, config=EnvRefineConfig(method="paper"))
    before = layers.sky_shading + layers.indirect_shading
    after = out.layers.sky_shading + out.layers.indirect_shading
    far = np.zeros((H, W), dtype=bool)
    far[:, :W // 2 - 12] = far[:, W // 2 + 12:] = True
    assert np.abs(after[far] / before[far] - 1.0).max() < 0.01
    assert (jump(out.layers.reflectance) < 0.01).all()


def test_pairs_need_both_sides():
    image, layers, _ = boundary()
    lit_only = relayer(image, layers, visibility=np.ones((H, W)))
    lit_only = dataclasses.replace(lit_only, shadow_labels=np.full((H, W), SHADOW_LABELS["lit"], np.uint8))
    assert len(boundary_pairs(image, lit_only)) == 0


def test_relayer_keeps_eq_1():
    image, layers, _ = boundary(env_shadow_scale=1.3)
    out = relayer(image, layers, env_scale=np.full((H, W), 0.9))
    np.testing.assert_allclose(out.reconstruct(), image, rtol=1e-4)
    np.testing.assert_allclose(out.sky_shading, 0.9 * layers.sky_shading, rtol=1e-6)
    with pytest.raises(ValueError, match="visibility"):
        relayer(image, layers, visibility=np.ones((3, 3)))
    with pytest.raises(ValueError, match="env_scale"):
        relayer(image, layers, env_scale=-np.ones((H, W)))


# -- the multi-view fusion ----------------------------------------------------------------------------
def plane_layers(view, quantity, error=None):
    """Exact layers of a ``test_multiview_shadows`` plane view (all lit); ``error`` (H, W) multiplies
    the reflectance there and divides the shading, as a matte gone wrong in this view only."""
    h, w = view.shape
    sun = np.broadcast_to(L_SUN * COSINE, (h, w, 3))
    env = np.broadcast_to(S_ENV, (h, w, 3))
    reflectance = view.image / (sun + env)
    factor = np.ones((h, w, 1)) if error is None else error[..., None]
    return IntrinsicLayers(
        stem=view.stem, reflectance=(reflectance * factor).astype(np.float32),
        sun_shading=(sun / factor).astype(np.float32), sky_shading=(env / factor).astype(np.float32),
        indirect_shading=np.zeros((h, w, 3), np.float32), visibility=np.ones((h, w), np.float32),
        shadow_labels=np.full((h, w), SHADOW_LABELS["lit"], np.uint8))


@pytest.fixture(scope="module")
def three_views():
    views, quantities = [], {}
    for i, dx in enumerate((-0.5, 0.0, 0.5)):
        view, q, _ = overview(f"view_{i}", dx, seed=i)
        views.append(view)
        quantities[view.stem] = q
    error = np.ones(views[1].shape)
    error[20:50, 30:70] = 1.3  # view_1's reflectance 30% too bright in a block
    layers = {v.stem: plane_layers(v, quantities[v.stem], error if v.stem == "view_1" else None) for v in views}
    return views, quantities, layers


def test_one_reflectance_per_point_outvotes_one_view(three_views):
    views, quantities, layers = three_views
    out = refine(views, layers, quantities=quantities)
    wrong = np.zeros(views[1].shape, dtype=bool)
    wrong[20:50, 30:70] = True
    truth = plane_layers(views[1], quantities["view_1"]).reflectance
    before = np.median(np.abs(layers["view_1"].reflectance[wrong] / truth[wrong] - 1))
    after = np.median(np.abs(out.layers["view_1"].reflectance[wrong] / truth[wrong] - 1))
    assert before == pytest.approx(0.3, abs=1e-3) and after < 0.2
    points = np.stack(np.meshgrid(np.linspace(-1, 1, 40), np.linspace(-1, 1, 40), [0.0]), -1).reshape(-1, 3)
    spread = [cross_view_reflectance_spread(views, quantities, {s: lay.reflectance for s, lay in ls.items()}, points)
              for ls in (layers, out.layers)]
    assert spread[1].p90[0] < 0.7 * spread[0].p90[0]
    for v in views:  # Eq. 1 still holds; labels and v_sun are kept
        np.testing.assert_allclose(out.layers[v.stem].reconstruct(), v.image, rtol=1e-4, atol=1e-7)
        np.testing.assert_array_equal(out.layers[v.stem].visibility, layers[v.stem].visibility)
        np.testing.assert_array_equal(out.layers[v.stem].shadow_labels, layers[v.stem].shadow_labels)
    assert set(out.timings) == {"correspondences", "fusion"} and out.offsets is None


def test_the_order_of_the_views_changes_nothing(three_views):
    views, quantities, layers = three_views
    forward = refine(views, layers, quantities=quantities)
    backward = refine(views[::-1], layers, quantities=quantities)
    for v in views:
        np.testing.assert_array_equal(forward.layers[v.stem].reflectance, backward.layers[v.stem].reflectance)


def test_a_single_view_is_unchanged_and_zero_weight_is_identity(three_views):
    views, quantities, layers = three_views
    alone = refine(views[:1], layers, quantities=quantities)
    assert alone.layers["view_0"] is layers["view_0"]
    corr = find_correspondences(views, quantities)
    same = fuse_reflectance(layers, corr, weight=0.0)
    for v in views:
        np.testing.assert_allclose(same[v.stem], layers[v.stem].reflectance, rtol=1e-6)


def test_with_reflectance_moves_the_rest_to_the_shading(three_views):
    views, quantities, layers = three_views
    lay = layers["view_0"]
    new = with_reflectance(lay, lay.reflectance * 0.5)
    np.testing.assert_allclose(new.reconstruct(), lay.reconstruct(), rtol=1e-5)
    np.testing.assert_allclose(new.sun_shading, 2 * lay.sun_shading, rtol=1e-6)
    with pytest.raises(ValueError, match="reflectance"):
        with_reflectance(lay, -lay.reflectance)


def test_bad_arguments_are_named(three_views):
    views, quantities, layers = three_views
    with pytest.raises(ValueError, match="layers"):
        refine(views, {"view_0": layers["view_0"]}, quantities=quantities)
    with pytest.raises(ValueError, match="quantities"):
        refine(views, layers)
    with pytest.raises(ValueError, match="views"):
        refine([], layers)
    with pytest.raises(TypeError, match="config"):
        refine(views, layers, quantities=quantities, config="paper")
    with pytest.raises(ValueError, match="method"):
        EnvRefineConfig(method="best")
    with pytest.raises(ValueError, match="fusion_weight"):
        EnvRefineConfig(fusion_weight=-1.0)
    with pytest.raises(ValueError, match="weight"):
        fuse_reflectance(layers, find_correspondences(views, quantities), weight=np.inf)
