"""Mitsuba rendering of synthetic scenes: sun orientation, determinism, the sun radiance."""

from __future__ import annotations

import math

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba", reason="Mitsuba 3 is not installed (pip install 'mvintrinsic[render]')")

from mvintrinsic.camera import Camera  # noqa: E402
from mvintrinsic.raytrace import Tracer  # noqa: E402
from mvintrinsic.synth.render import MitsubaScene, RenderConfig, sun_radiance, sun_vector  # noqa: E402
from mvintrinsic.synth.types import Material, SynthMesh, SynthScene, ViewPath  # noqa: E402

POLE_HEIGHT = 3.0  # m
POLE_HALF_WIDTH = 0.15  # m
TOP_VIEW_PX = 256  # ground pixels of the top view are 6.8 cm wide
ANGLE_TOL_DEG = 2.0  # shadow azimuth vs the sun's opposite azimuth
LENGTH_TOL = 0.1  # m, 1.5 ground pixels


def box(name, lo, hi, material, label):
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    corners = np.array([[x, y, z] for z in (lo[2], hi[2]) for y in (lo[1], hi[1]) for x in (lo[0], hi[0])])
    quads = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    triangles = np.array([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))])
    return SynthMesh(name, corners, triangles, np.zeros((8, 2), np.float32), material, label)


def pole_scene() -> SynthScene:
    grey = Material("grey", np.full((1, 1, 3), 0.5, np.float32))
    ground = SynthMesh(
        "ground",
        np.array([[-10.0, -10.0, 0.0], [10.0, -10.0, 0.0], [10.0, 10.0, 0.0], [-10.0, 10.0, 0.0]]),
        np.array([[0, 1, 2], [0, 2, 3]]),
        np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32),
        "grey",
        "ground",
    )
    w = POLE_HALF_WIDTH
    pole = box("pole", [-w, -w, 0.0], [w, w, POLE_HEIGHT], "grey", "thin")
    path = ViewPath(np.array([0.0, -10.0, 2.0]), np.array([1.0, 0.0, 0.0]), np.zeros(3))
    return SynthScene("pole", 0, (ground, pole), {"grey": grey}, path)


def top_camera(size=TOP_VIEW_PX, height=15.0):
    f = size / (2 * math.tan(math.radians(30)))
    rotation = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])  # x right, y down (= -Y), looking down
    return Camera("PINHOLE", size, size, [f, f, size / 2, size / 2], rotation, -rotation @ [0.0, 0.0, height])


@pytest.fixture(scope="module")
def pole(tmp_path_factory):
    scene = pole_scene()
    return scene, MitsubaScene(scene, tmp_path_factory.mktemp("pole"))


@pytest.mark.parametrize(("azimuth", "elevation"), [(30.0, 40.0), (-120.0, 55.0)])
def test_pole_shadow_points_away_from_the_sun(pole, azimuth, elevation):
    scene, mitsuba = pole
    camera = top_camera()
    sun = sun_vector(azimuth, elevation)
    renders = mitsuba.render(camera, sun, RenderConfig(spp=4, sun_spp=16), with_albedo=False)
    hits = Tracer(scene.exact_proxy()).intersect(camera.center, camera.pixel_rays())
    ground = hits.hit & (np.abs(hits.points[:, 2]) < 1e-3)
    direct = renders.sun_direct.reshape(-1, 3).mean(axis=1)
    shadow = ground & (direct < 0.5 * np.median(direct[ground]))
    points = hits.points[shadow, :2]
    assert len(points) > 20
    mean = points.mean(axis=0)
    away = -sun[:2] / np.linalg.norm(sun[:2])
    angle = math.degrees(math.acos(np.clip(mean @ away / np.linalg.norm(mean), -1, 1)))
    assert angle < ANGLE_TOL_DEG
    # The shadow ends where the top face projects: height / tan(elevation) beyond the top
    # face's farthest corner along the shadow.
    length = np.max(points @ away)
    expected = POLE_HEIGHT / math.tan(math.radians(elevation)) + POLE_HALF_WIDTH * np.abs(away).sum()
    assert length == pytest.approx(expected, abs=LENGTH_TOL)


def test_renders_are_deterministic_per_seed(pole):
    _, mitsuba = pole
    camera, sun = top_camera(size=32), sun_vector(10.0, 45.0)
    a = mitsuba.render(camera, sun, RenderConfig(spp=4, sun_spp=4, seed=3))
    b = mitsuba.render(camera, sun, RenderConfig(spp=4, sun_spp=4, seed=3))
    c = mitsuba.render(camera, sun, RenderConfig(spp=4, sun_spp=4, seed=4))
    np.testing.assert_array_equal(a.image, b.image)
    np.testing.assert_array_equal(a.sun_direct, b.sun_direct)
    assert not np.array_equal(a.image, c.image)
    # Albedo AOV of the grey material is exact away from silhouettes.
    assert np.median(a.albedo) == pytest.approx(0.5, abs=1e-6)


def test_sun_radiance_is_the_shading_of_a_plate_facing_the_sun(pole):
    """L_sun = radiance of an albedo-1 plate facing the sun; a grey ground shows 0.5 L_sun cos."""
    scene, mitsuba = pole
    sun = sun_vector(0.0, 40.0)
    radiance = sun_radiance(sun, RenderConfig())
    assert np.all(radiance > 0) and radiance[0] > radiance[2]  # a warm sun at 40 degrees
    camera = top_camera(size=32)
    renders = mitsuba.render(camera, sun, RenderConfig(spp=4, sun_spp=64), with_albedo=False)
    lit_ground = renders.sun_direct[2:8, 2:8].reshape(-1, 3)  # a corner far from the pole
    expected = 0.5 * radiance * math.sin(math.radians(40.0))
    np.testing.assert_allclose(lit_ground.mean(axis=0), expected, rtol=0.02)
    assert sun_radiance(sun, RenderConfig(sun=False)).tolist() == [0.0, 0.0, 0.0]


def sky_camera(size=24, elevation_deg=55.0):
    """A camera 1.5 m above the ground looking along +X, tilted up to ``elevation_deg``: sky only."""
    e = math.radians(elevation_deg)
    forward = np.array([math.cos(e), 0.0, math.sin(e)])
    right = np.array([0.0, -1.0, 0.0])
    rotation = np.stack([right, np.cross(forward, right), forward])  # rows: camera x, y (down), z in the world
    f = size / (2 * math.tan(math.radians(10)))
    return Camera("PINHOLE", size, size, [f, f, size / 2, size / 2], rotation, -rotation @ [0.0, -5.0, 1.5])


def test_simulated_sky_renders_its_own_environment_map(pole):
    """Issue 16: the new sky's rendered radiance matches its own environment map on sky pixels."""
    from mvintrinsic.synth.render import simulated_sky

    _, mitsuba = pole
    config = RenderConfig(spp=4, sun_spp=4, sky="simulated")
    sun = sun_vector(-60.0, 35.0)
    camera = sky_camera()
    renders = mitsuba.render(camera, sun, config, with_albedo=False)
    sky = simulated_sky(sun, config)
    rows, cols = sky.texel_of_direction(camera.pixel_rays())
    expected = np.asarray(sky.radiance)[rows, cols].reshape(renders.image.shape)
    # Smooth sky: nearest texel against Mitsuba's bilinear lookup over a 20-degree field.
    np.testing.assert_allclose(renders.image.reshape(-1, 3).mean(axis=0), expected.reshape(-1, 3).mean(axis=0),
                               rtol=0.02)
    np.testing.assert_allclose(renders.image, expected, rtol=0.05)
    assert np.abs(renders.sun_direct).max() == 0.0  # the sun is a directional light: no disc seen


def test_simulated_sun_radiance_is_the_shading_of_a_plate_facing_the_sun(pole):
    scene, mitsuba = pole
    sun = sun_vector(0.0, 40.0)
    config = RenderConfig(spp=4, sun_spp=16, sky="simulated")
    radiance = sun_radiance(sun, config)
    assert np.all(radiance > 0) and radiance[0] > radiance[2]  # a warm sun at 40 degrees
    renders = mitsuba.render(top_camera(size=32), sun, config, with_albedo=False)
    lit_ground = renders.sun_direct[2:8, 2:8].reshape(-1, 3)
    np.testing.assert_allclose(lit_ground.mean(axis=0), 0.5 * radiance * math.sin(math.radians(40.0)), rtol=0.02)
    # The simulated sky is exposed like Mitsuba's sunsky: the two suns within 30% per channel.
    np.testing.assert_allclose(radiance, sun_radiance(sun, RenderConfig()), rtol=0.3)


@pytest.mark.parametrize(("changes", "name"), [({"sky": "overcast"}, "sky"), ({"aerosol_scale": 0.0}, "aerosol_scale"),
                                               ({"aerosol_scale": math.inf}, "aerosol_scale")])
def test_render_config_names_the_bad_field(changes, name):
    with pytest.raises(ValueError, match=name):
        RenderConfig(**changes)
