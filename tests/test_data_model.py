"""View, Proxy, Sun, Scene and the result types: validation, immutability, derived quantities."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mvintrinsic import Camera, Decomposition, IntrinsicLayers, Lighting, Proxy, Scene, SkyParameters, Sun, View
from mvintrinsic.scene import SUN_ANGULAR_RADIUS, valid_pixels


def camera(w=8, h=6):
    return Camera("PINHOLE", w, h, [5.0, 5.0, w / 2, h / 2], np.eye(3), [0.0, 0.0, 5.0])


def plane_proxy():
    xy = np.stack(np.meshgrid(np.linspace(-1, 1, 5), np.linspace(-1, 1, 5)), -1).reshape(-1, 2)
    vertices = np.column_stack([xy, np.zeros(len(xy))])
    normals = np.tile([0.0, 0.0, 1.0], (len(xy), 1))
    return Proxy(vertices, normals)


def layers(stem="a", h=6, w=8, seed=0):
    rng = np.random.default_rng(seed)
    return IntrinsicLayers(
        stem,
        reflectance=rng.uniform(0, 1, (h, w, 3)),
        sun_shading=rng.uniform(0, 2, (h, w, 3)),
        sky_shading=rng.uniform(0, 1, (h, w, 3)),
        indirect_shading=rng.uniform(0, 1, (h, w, 3)),
        visibility=rng.uniform(0, 1, (h, w)),
        shadow_labels=rng.choice(np.array([0, 128, 255], dtype=np.uint8), (h, w)),
    )


# -- View ----------------------------------------------------------------------------------------
def test_valid_pixels_excludes_saturated_nonfinite_negative():
    image = np.full((2, 3, 3), 0.5, dtype=np.float32)
    image[0, 0, 1] = 1.0  # saturated for an integer file
    image[0, 1, 2] = np.nan
    image[0, 2, 0] = -0.1
    image[1, 0] = np.inf
    assert valid_pixels(image, saturation=1.0).tolist() == [[False, False, False], [False, True, True]]
    assert valid_pixels(image).tolist() == [[True, False, False], [False, True, True]]


def test_view_default_mask_and_size_check():
    image = np.ones((6, 8, 3), dtype=np.float32)
    image[2, 3] = np.nan
    view = View("v", image, camera())
    assert view.mask.sum() == 47 and not view.mask[2, 3]
    assert view.image.dtype == np.float32 and not view.image.flags.writeable
    with pytest.raises(ValueError, match="8x6"):
        View("v", np.ones((5, 8, 3)), camera())
    with pytest.raises(ValueError, match="mask"):
        View("v", image, camera(), mask=np.ones((6, 8), bool))  # keeps the NaN pixel
    with pytest.raises(ValueError, match="stem"):
        View("", image, camera())


# -- Proxy ---------------------------------------------------------------------------------------
def test_proxy_validation():
    p = plane_proxy()
    assert not p.is_mesh and p.bounds.tolist() == [[-1, -1, 0], [1, 1, 0]]
    with pytest.raises(ValueError, match="vertices"):
        Proxy(np.zeros((0, 3)), np.zeros((0, 3)))
    line = np.column_stack([np.arange(5.0), 2 * np.arange(5.0), np.zeros(5)])
    with pytest.raises(ValueError, match="line"):
        Proxy(line, np.tile([0.0, 0.0, 1.0], (5, 1)))
    with pytest.raises(ValueError, match="normals"):
        Proxy(p.vertices, 2 * p.normals)
    with pytest.raises(ValueError, match="triangles"):
        Proxy(p.vertices, p.normals, triangles=[[0, 1, 99]])
    with pytest.raises(ValueError, match="zero area"):
        Proxy(p.vertices, p.normals, triangles=[[0, 1, 1], [2, 2, 2]])


# -- Sun and Scene -------------------------------------------------------------------------------
def test_sun_normalises_and_rejects_zero():
    sun = Sun([0.0, 3.0, 4.0])
    np.testing.assert_allclose(sun.direction, [0, 0.6, 0.8])
    assert sun.angular_radius == SUN_ANGULAR_RADIUS
    assert math.degrees(sun.elevation([0, 0, 1])) == pytest.approx(math.degrees(math.asin(0.8)))
    for bad in ([0, 0, 0], [np.nan, 0, 1], [np.inf, 0, 1], [1, 2]):
        with pytest.raises(ValueError, match="direction"):
            Sun(bad)


def test_scene_checks_sun_above_horizon_and_unique_stems():
    view = View("v", np.ones((6, 8, 3)), camera())
    scene = Scene([view], plane_proxy(), Sun([0, 0.5, 1]))
    assert scene.views == (view,) and scene.view("v") is view and scene.stems == ("v",)
    with pytest.raises(KeyError, match="'v'"):
        scene.view("w")
    with pytest.raises(ValueError, match="below the horizon"):
        Scene([view], plane_proxy(), Sun([0, 0.5, -1]))
    # The horizon follows `up`: the same sun is fine when up is -Z... and not when up is +Z.
    Scene([view], plane_proxy(), Sun([0, 0.5, -1]), up=[0, 0, -1])
    with pytest.raises(ValueError, match="unique"):
        Scene([view, view], plane_proxy(), Sun([0, 0, 1]))
    with pytest.raises(ValueError, match="at least one"):
        Scene([], plane_proxy(), Sun([0, 0, 1]))


# -- results -------------------------------------------------------------------------------------
def test_intrinsic_layers_image_model():
    lay = layers()
    # Eq. (1): S_tot = v_sun S_sun + S_sky + S_ind and the reconstruction R * S_tot.
    expected = lay.visibility[..., None] * lay.sun_shading + lay.sky_shading + lay.indirect_shading
    np.testing.assert_allclose(lay.shading, expected, rtol=1e-6)
    np.testing.assert_allclose(lay.reconstruct(), lay.reflectance * expected, rtol=1e-6)
    np.testing.assert_allclose(lay.env_shading, lay.sky_shading + lay.indirect_shading, rtol=1e-6)


def test_intrinsic_layers_validation():
    good = layers()
    kwargs = {f: getattr(good, f) for f in ("reflectance", "sun_shading", "sky_shading", "indirect_shading",
                                            "visibility", "shadow_labels")}
    with pytest.raises(ValueError, match="visibility"):
        IntrinsicLayers("a", **{**kwargs, "visibility": kwargs["visibility"] + 1.5})
    with pytest.raises(ValueError, match="shadow_labels"):
        IntrinsicLayers("a", **{**kwargs, "shadow_labels": np.full((6, 8), 7, np.uint8)})
    with pytest.raises(ValueError, match="sky_shading"):
        IntrinsicLayers("a", **{**kwargs, "sky_shading": np.ones((6, 7, 3))})
    with pytest.raises(ValueError, match="reflectance"):
        IntrinsicLayers("a", **{**kwargs, "reflectance": np.full((6, 8, 3), np.nan)})


def test_decomposition_is_read_only_and_consistent():
    lighting = Lighting(Sun([0, 0, 1]), [1.0, 0.9, 0.8], sky=SkyParameters("perez", 3.5, [1, 1, 1], 0.01))
    result = Decomposition({"a": layers("a")}, lighting, timings={"step1": 1.5})
    assert result.stems == ("a",) and result.version
    with pytest.raises(TypeError):
        result.layers["b"] = layers("b")  # type: ignore[index]
    with pytest.raises(ValueError, match="layers\\['x'\\]"):
        Decomposition({"x": layers("a")}, lighting)
    with pytest.raises(ValueError, match="timings"):
        Decomposition({}, lighting, timings={"step1": -1.0})
    with pytest.raises(ValueError, match="sun_radiance"):
        Lighting(Sun([0, 0, 1]), [-1.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="envmap"):
        Lighting(Sun([0, 0, 1]), [1.0, 1.0, 1.0], envmap=np.zeros((4, 4, 3)))
