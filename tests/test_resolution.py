"""Working resolution (mvintrinsic.resolution): downscaling views and carrying layers back."""

import numpy as np
import pytest

from mvintrinsic.camera import Camera
from mvintrinsic.resolution import downscale_view, resize_image, upsample_layers
from mvintrinsic.results import SHADOW_LABELS, IntrinsicLayers
from mvintrinsic.scene import View


def camera(width=64, height=48):
    return Camera("PINHOLE", width, height, np.array([50.0, 50.0, width / 2, height / 2]), np.eye(3), np.zeros(3))


def shadow_step_view():
    """A grey plane, a sharp shadow edge at column 29.5 (shadow left: 0.25 of the light)."""
    h, w = 48, 64
    image = np.full((h, w, 3), 0.4, np.float32)
    image[:, :30] *= 0.25
    return View("v", image, camera(w, h))


def test_resize_keeps_only_fully_valid_pixels():
    image = np.ones((4, 4, 3), np.float32)
    mask = np.ones((4, 4), bool)
    mask[0, 0] = False
    small, valid = resize_image(image, mask, 2, 2)
    assert small.shape == (2, 2, 3) and valid.tolist() == [[False, True], [True, True]]
    np.testing.assert_allclose(small[1, 1], 1.0)


def test_downscale_view_scales_the_camera_and_is_identity_at_one():
    view = shadow_step_view()
    assert downscale_view(view, 1.0) is view
    small = downscale_view(view, 0.5)
    assert small.shape == (24, 32) and small.camera.focal == (25.0, 25.0)
    with pytest.raises(ValueError, match="scale"):
        downscale_view(view, 0.0)


def test_upsampled_layers_reproduce_the_photo_and_follow_its_shadow_edge():
    view = shadow_step_view()
    small = downscale_view(view, 0.5)
    h, w = small.shape
    sun = np.zeros((h, w, 3), np.float32) + 0.3
    sky = np.zeros((h, w, 3), np.float32) + 0.1
    visibility = np.ones((h, w), np.float32)
    visibility[:, :15] = 0.0
    total = sky + visibility[..., None] * sun
    layers = IntrinsicLayers("v", small.image / total, sun, sky, np.zeros_like(sky), visibility,
                             np.where(visibility >= 0.5, 255, 0).astype(np.uint8))
    full = upsample_layers(view, layers)
    assert full.shape == view.shape
    np.testing.assert_allclose(full.reconstruct(), view.image, rtol=1e-5)
    # R is 1 everywhere: the guided v_sun, which follows the photo's edge, errs less than the bilinear one
    guided_error = ((full.reflectance - 1.0) ** 2).sum()
    bilinear_error = ((upsample_layers(view, layers, guided=False).reflectance - 1.0) ** 2).sum()
    assert guided_error < 0.7 * bilinear_error
    np.testing.assert_allclose(full.reflectance[:, :24], 1.0, atol=0.02)
    np.testing.assert_allclose(full.reflectance[:, 36:], 1.0, atol=0.02)
    assert (full.shadow_labels[:, :28] == SHADOW_LABELS["shadow"]).all()
    assert (full.shadow_labels[:, 32:] == SHADOW_LABELS["lit"]).all()
