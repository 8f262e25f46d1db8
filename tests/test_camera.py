"""Camera model: agreement with COLMAP's own implementation (pycolmap), round trips, scaling."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest

from mvintrinsic.camera import CAMERA_MODELS, Camera

PIXEL_TOL = 1e-6  # px: projection agreement with pycolmap
NORMALIZED_TOL = 1e-9  # undistortion agreement and round trips, normalised units

PARAMS = {
    "SIMPLE_PINHOLE": [150.0, 80.0, 60.0],
    "PINHOLE": [150.0, 155.0, 81.0, 59.5],
    "SIMPLE_RADIAL": [150.0, 80.0, 60.0, -0.08],
    "RADIAL": [150.0, 80.0, 60.0, -0.1, 0.03],
    "OPENCV": [150.0, 152.0, 79.0, 61.0, -0.12, 0.04, 0.002, -0.0015],
    "FULL_OPENCV": [150.0, 152.0, 79.0, 61.0, -0.12, 0.04, 0.002, -0.0015, 0.001, 0.0005, 0.0, 0.0002],
    "OPENCV_FISHEYE": [150.0, 152.0, 79.0, 61.0, 0.05, -0.01, 0.002, -0.0005],
    "FOV": [150.0, 152.0, 79.0, 61.0, 0.6],
    "SIMPLE_RADIAL_FISHEYE": [150.0, 80.0, 60.0, 0.04],
    "RADIAL_FISHEYE": [150.0, 80.0, 60.0, 0.04, -0.01],
    "THIN_PRISM_FISHEYE": [150.0, 152.0, 79.0, 61.0, 0.05, -0.01, 0.001, -0.001, 0.0005, 0.0, 0.001, -0.001],
    "RAD_TAN_THIN_PRISM_FISHEYE": [150.0, 152.0, 79.0, 61.0, 0.05, -0.01, 0.002, 0.0, 0.0, 0.0, 0.001, -0.001,
                                   0.0005, 0.0, -0.0005, 0.0],
    "SIMPLE_DIVISION": [150.0, 80.0, 60.0, -0.05],
    "DIVISION": [150.0, 152.0, 79.0, 61.0, -0.05],
    "SIMPLE_FISHEYE": [150.0, 80.0, 60.0],
    "FISHEYE": [150.0, 152.0, 79.0, 61.0],
    "EUCM": [150.0, 152.0, 79.0, 61.0, 0.5, 1.0],
}


def random_pose(rng):
    from scipy.spatial.transform import Rotation

    return Rotation.random(random_state=rng.integers(1 << 31)).as_matrix(), rng.normal(size=3)


def make(model, rng):
    r, t = random_pose(rng)
    return Camera(model, 160, 120, PARAMS[model], r, t)


def colmap_camera(camera: Camera) -> pycolmap.Camera:
    cam = pycolmap.Camera.create_from_model_name(1, camera.model, 100.0, camera.width, camera.height)
    cam.params = camera.params.tolist()
    return cam


@pytest.mark.parametrize("model", list(CAMERA_MODELS))
def test_projection_matches_pycolmap(model):
    rng = np.random.default_rng(1)
    camera = make(model, rng)
    # Points in front of the camera spread over the image (normalised coords up to ~0.55).
    cam_points = np.column_stack([rng.uniform(-0.5, 0.5, 200), rng.uniform(-0.4, 0.4, 200), np.ones(200)])
    cam_points *= rng.uniform(1.0, 30.0, size=(200, 1))
    world = (cam_points - camera.translation) @ camera.rotation  # R.T (x - t)
    pixels, depth = camera.project(world)
    np.testing.assert_allclose(depth, cam_points[:, 2], rtol=1e-12)
    expected = colmap_camera(camera).img_from_cam(cam_points)
    np.testing.assert_allclose(pixels, expected, atol=PIXEL_TOL)


@pytest.mark.parametrize("model", list(CAMERA_MODELS))
def test_unprojection_matches_pycolmap_and_round_trips(model):
    rng = np.random.default_rng(2)
    camera = make(model, rng)
    pixels = rng.uniform([0, 0], [camera.width, camera.height], size=(300, 2))
    xy = camera.pixels_to_normalized(pixels)
    np.testing.assert_allclose(xy, colmap_camera(camera).cam_from_img(pixels), atol=1e-7)
    np.testing.assert_allclose(camera.normalized_to_pixels(xy), pixels, atol=NORMALIZED_TOL * 1e3)
    # pixel rays hit the points they came from: re-project a point along each ray
    rays = camera.pixel_rays(pixels)
    np.testing.assert_allclose(np.linalg.norm(rays, axis=1), 1.0, atol=1e-12)
    back, depth = camera.project(camera.center + 7.0 * rays)
    assert np.all(depth > 0)
    np.testing.assert_allclose(back, pixels, atol=1e-6)


@pytest.mark.parametrize("model, params", [("PINHOLE", [150.0, 140.0, 80.0, 60.0]), ("SIMPLE_PINHOLE", [150.0, 80.0, 60.0]),
                                           ("OPENCV", [150.0, 140.0, 80.0, 60.0, 0, 0, 0, 0])])
def test_undistorted_cameras_give_colmaps_numbers_exactly(model, params):
    """Without distortion the projection skips pycolmap (``K`` alone) and must not change a digit."""
    camera = Camera(model, 160, 120, params, *random_pose(np.random.default_rng(3)))
    assert not camera.is_distorted
    xy = np.random.default_rng(4).normal(size=(5000, 2))
    xy[::17] = np.nan
    colmap = colmap_camera(camera)
    expected = colmap.img_from_cam(np.column_stack([xy, np.ones(len(xy))]))[:, :2]
    np.testing.assert_array_equal(camera.normalized_to_pixels(xy), expected)
    pixels = np.random.default_rng(5).uniform(-50.0, 250.0, size=(5000, 2))
    np.testing.assert_array_equal(camera.pixels_to_normalized(pixels), colmap.cam_from_img(pixels)[:, :2])


def test_pixel_centres_follow_colmap_convention():
    camera = Camera("PINHOLE", 4, 3, [2.0, 2.0, 2.0, 1.5], np.eye(3), np.zeros(3))
    centres = camera.pixel_centers()
    assert centres.shape == (3, 4, 2)
    assert tuple(centres[0, 0]) == (0.5, 0.5)
    assert tuple(centres[2, 3]) == (3.5, 2.5)
    # The principal point at the image centre: the ray through it is the optical axis.
    np.testing.assert_allclose(camera.pixel_rays([[2.0, 1.5]]), [[0.0, 0.0, 1.0]], atol=1e-15)
    # Default rays are in row-major pixel order.
    np.testing.assert_allclose(camera.pixel_rays()[5], camera.pixel_rays(centres[1, 1][None])[0])


def test_center_and_forward():
    rng = np.random.default_rng(3)
    camera = make("PINHOLE", rng)
    np.testing.assert_allclose(camera.world_to_camera(camera.center[None]), [[0, 0, 0]], atol=1e-12)
    ahead = camera.world_to_camera((camera.center + 2.0 * camera.forward)[None])
    np.testing.assert_allclose(ahead, [[0, 0, 2.0]], atol=1e-12)


def test_points_behind_are_nan():
    camera = Camera("SIMPLE_PINHOLE", 10, 10, [5.0, 5.0, 5.0], np.eye(3), np.zeros(3))
    pixels, depth = camera.project(np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0]]))
    assert np.isnan(pixels[0]).all() and depth[0] == -1.0
    np.testing.assert_allclose(pixels[1], [5.0, 5.0])
    assert camera.in_image(pixels).tolist() == [False, True]


@pytest.mark.parametrize("model", list(CAMERA_MODELS))
@pytest.mark.parametrize("size", [(80, 60), (53, 41)])
def test_scaled_camera_maps_pixels_exactly(model, size):
    rng = np.random.default_rng(4)
    camera = make(model, rng)
    small = camera.scaled(*size)
    sx, sy = size[0] / camera.width, size[1] / camera.height
    points = camera.center + 10.0 * camera.pixel_rays(rng.uniform([0, 0], [160, 120], size=(50, 2)))
    big_px, _ = camera.project(points)
    small_px, _ = small.project(points)
    np.testing.assert_allclose(small_px, big_px * [sx, sy], atol=1e-9)
    assert (small.width, small.height) == size
    if sx == sy:
        assert small.model == camera.model
        assert pycolmap.Camera.create_from_model_name(1, small.model, 1.0, *size).params.size == small.params.size


def test_scaling_agrees_with_colmap_rescale():
    camera = make("SIMPLE_RADIAL", np.random.default_rng(5))
    reference = colmap_camera(camera)
    reference.rescale(80, 60)
    np.testing.assert_allclose(camera.scaled(80, 60).params, reference.params, rtol=1e-12)


def test_camera_is_frozen_and_copies_inputs():
    rotation = np.eye(3)
    camera = Camera("PINHOLE", 10, 10, [5.0, 5.0, 5.0, 5.0], rotation, np.zeros(3))
    rotation[0, 0] = 7.0
    assert camera.rotation[0, 0] == 1.0
    with pytest.raises(ValueError):
        camera.params[0] = 1.0
    with pytest.raises(AttributeError):
        camera.width = 3


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"model": "EQUIRECTANGULAR"}, "model"),
        ({"width": 0}, "width"),
        ({"params": [1.0, 2.0]}, "params"),
        ({"params": [np.nan, 5.0, 5.0, 5.0]}, "params"),
        ({"params": [-5.0, 5.0, 5.0, 5.0]}, "params"),
        ({"rotation": np.diag([1.0, 1.0, -1.0])}, "rotation"),
        ({"rotation": 2 * np.eye(3)}, "rotation"),
        ({"translation": [0.0, 1.0]}, "translation"),
    ],
)
def test_invalid_cameras_name_the_field(kwargs, field):
    args = {"model": "PINHOLE", "width": 10, "height": 10, "params": [5.0, 5.0, 5.0, 5.0],
            "rotation": np.eye(3), "translation": np.zeros(3)}
    args.update(kwargs)
    with pytest.raises(ValueError, match=field):
        Camera(**args)


def test_every_perspective_colmap_model_is_supported():
    """Issue 19: pycolmap's models, not a hand-written subset; the fisheyes are distorted even at zero."""
    assert set(CAMERA_MODELS) == set(PARAMS)
    assert Camera("FISHEYE", 160, 120, [150.0, 150.0, 80.0, 60.0], np.eye(3), np.zeros(3)).is_distorted
    assert not Camera("OPENCV", 160, 120, [150.0, 150.0, 80.0, 60.0, 0, 0, 0, 0], np.eye(3), np.zeros(3)).is_distorted
    assert Camera("OPENCV", 160, 120, PARAMS["OPENCV"], np.eye(3), np.zeros(3)).is_distorted
