"""Image model (Eqs. 1, 2, 3, 5, 17): exact round trips, clamping, NaN safety, broadcasting."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from mvintrinsic import image_model as im

EXACT = 1e-12


@pytest.fixture
def layers():
    rng = np.random.default_rng(0)
    shape = (7, 5)
    return {
        "R": rng.uniform(0.05, 0.9, (*shape, 3)),
        "sky": rng.uniform(0.05, 0.3, (*shape, 3)),
        "ind": rng.uniform(0.0, 0.2, (*shape, 3)),
        "v": rng.uniform(0, 1, shape),
        "L": np.array([1.2, 1.0, 0.8]),
        "cos": rng.uniform(-0.5, 1, shape),
    }


def test_forward_model_and_reflectance_round_trip(layers):
    s = layers
    sun = im.sun_shading(s["L"], s["cos"])
    assert np.all(sun[s["cos"] < 0] == 0)  # max(0, cos): attached shadow gets no sun
    image = im.render(s["R"], s["sky"], s["ind"], s["v"], sun)
    # Eq. (1) written out by hand.
    expected = s["R"] * (s["v"][..., None] * s["L"] * np.maximum(s["cos"], 0)[..., None] + s["sky"] + s["ind"])
    np.testing.assert_allclose(image, expected, rtol=EXACT)
    # Eq. (2) with the true visibility recovers R; with a wrong one it does not.
    np.testing.assert_allclose(im.reflectance(image, s["sky"], s["ind"], s["v"], sun), s["R"], rtol=1e-12)
    lit = im.reflectance(image, s["sky"], s["ind"], np.ones_like(s["v"]), sun)
    facing = s["cos"] > 0.1
    assert np.all(lit[facing] < s["R"][facing] + 1e-15)
    # Eq. (17)
    np.testing.assert_allclose(im.total_shading(s["sky"], s["ind"], s["v"], sun),
                               s["sky"] + s["ind"] + s["v"][..., None] * sun, rtol=EXACT)


def test_sun_radiance_from_a_pair(layers):
    """Eq. (5) returns L_sun for a shadow/lit pair of the same reflectance."""
    s = layers
    R = s["R"][0, 0]
    env1, env2 = s["sky"][0, 0] + s["ind"][0, 0], s["sky"][1, 1] + s["ind"][1, 1]
    cos1, cos2 = 0.3, 0.8
    i1 = R * env1  # in shadow
    i2 = R * (s["L"] * cos2 + env2)  # lit
    L = im.sun_radiance_from_pair(i1, i2, env1, env2, 0.0, 1.0, cos1, cos2)
    np.testing.assert_allclose(L, s["L"], rtol=1e-12)
    # Swapping the roles gives the same answer.
    np.testing.assert_allclose(im.sun_radiance_from_pair(i2, i1, env2, env1, 1.0, 0.0, cos2, cos1), s["L"], rtol=1e-12)
    # Vectorised over pairs.
    many = im.sun_radiance_from_pair(np.tile(i1, (4, 1)), np.tile(i2, (4, 1)), env1, env2, np.zeros(4), np.ones(4),
                                     np.full(4, cos1), np.full(4, cos2))
    np.testing.assert_allclose(many, np.tile(s["L"], (4, 1)), rtol=1e-12)


def test_degenerate_inputs_give_nan_without_warnings(layers):
    s = layers
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        zero = np.zeros(3)
        assert np.isnan(im.reflectance(np.ones(3), zero, zero, 0.0, zero)).all()
        # Both points in shadow: Eq. (5) is undefined.
        assert np.isnan(im.sun_radiance_from_pair(np.ones(3), np.ones(3), zero + 0.1, zero + 0.2, 0, 0, 1, 1)).all()
        # NaN and inf inputs propagate, never crash.
        bad = np.array([np.nan, np.inf, -np.inf])
        out = im.reflectance(bad, s["sky"][0, 0], s["ind"][0, 0], 1.0, np.ones(3))
        assert out.shape == (3,) and np.isnan(out[0])


def test_clamped_cosine_and_validation():
    normals = np.array([[0, 0, 1.0], [0, 0, -1.0], [1.0, 0, 0]])
    np.testing.assert_allclose(im.clamped_cosine(normals, np.array([0.6, 0, 0.8])), [0.8, 0.0, 0.6])
    with pytest.raises(ValueError, match="sun_direction"):
        im.clamped_cosine(normals, [0, 1])
    with pytest.raises(ValueError, match="image"):
        im.reflectance(np.ones((4, 2)), np.ones(3), np.ones(3), 1.0, np.ones(3))
