"""The colour Retinex baseline (benchmarks/baselines/retinex.py, Grosse et al. 2009) and its runner."""

from __future__ import annotations

import numpy as np
import pytest
import retinex  # benchmarks/baselines, on the path through pyproject's [tool.pytest.ini_options] pythonpath
from retinex import color_retinex, poisson_integrate, reflectance_edges

H, W = 60, 80

#: (rows, columns, RGB albedo) of the patches, painted in order over a grey background.
PATCHES = (
    ((slice(0, H), slice(0, W)), (0.6, 0.6, 0.6)),
    ((slice(8, 30), slice(6, 36)), (0.8, 0.2, 0.1)),  # red
    ((slice(34, 55), slice(10, 40)), (0.1, 0.3, 0.7)),  # blue
    ((slice(10, 50), slice(48, 70)), (0.15, 0.15, 0.15)),  # grey, 4x darker than the background
    ((slice(20, 30), slice(52, 62)), (0.2, 0.6, 0.2)),  # green, inside the dark grey patch
)


def synthetic(shading_kind: str = "ramp") -> tuple[np.ndarray, np.ndarray, np.ndarray, list[np.ndarray]]:
    """Piecewise-constant reflectance times a smooth grey shading: (image, reflectance, shading, patch masks)."""
    reflectance = np.zeros((H, W, 3))
    labels = np.zeros((H, W), int)
    for k, (where, colour) in enumerate(PATCHES):
        reflectance[where] = colour
        labels[where] = k
    y, x = np.mgrid[0:H, 0:W]
    if shading_kind == "ramp":
        shading = 0.2 + 0.8 * x / (W - 1) + 0.3 * y / (H - 1)  # log step per pixel <= 0.02
    else:
        shading = 1.0 + 0.5 * np.sin(2 * np.pi * x / W) * np.cos(np.pi * y / H)
    return reflectance * shading[..., None], reflectance, shading, [labels == k for k in range(len(PATCHES))]


def relative_std(values: np.ndarray) -> float:
    return float(np.std(values) / np.mean(values))


@pytest.mark.parametrize("shading_kind", ["ramp", "wave"])
def test_piecewise_constant_reflectance_times_smooth_shading(shading_kind):
    image, true_r, true_s, patches = synthetic(shading_kind)
    r, s = color_retinex(image)
    assert r.shape == s.shape == (H, W, 3) and r.dtype == s.dtype == np.float32
    # The shading is grey and the decomposition reproduces the image.
    np.testing.assert_array_equal(s[..., 0], s[..., 1])
    np.testing.assert_array_equal(s[..., 0], s[..., 2])
    np.testing.assert_allclose(r * s, image, rtol=1e-5, atol=1e-7)
    # Reflectance: constant inside every patch and equal to the truth up to one global scale, to
    # about 1.5 %: Retinex sets the shading gradient to 0 across every reflectance edge, so the true
    # shading step there (up to 0.05 in log here) is lost and spread by the least squares.
    image_spread = max(relative_std(image[..., c][p]) for p in patches for c in range(3))
    spread = max(relative_std(r[..., c][p]) for p in patches for c in range(3))
    assert image_spread > 0.25
    assert spread < 0.03
    assert relative_std((r / true_r).ravel()) < 0.03
    # Shading: the true smooth shading up to a global scale, no patch edge (grey log steps of 0.6 to 1.4
    # in the image) leaks into it.
    assert relative_std(s[..., 0] / true_s) < 0.03
    assert np.abs(np.diff(np.log(s[..., 0]), axis=1)).max() < 0.06
    assert np.abs(np.diff(np.log(s[..., 0]), axis=0)).max() < 0.06


def test_flat_image_gives_constant_reflectance_and_shading():
    image = np.broadcast_to(np.array([0.3, 0.5, 0.2]), (H, W, 3))
    r, s = color_retinex(image)
    assert np.ptp(r.reshape(-1, 3), axis=0).max() < 1e-6
    assert np.ptp(s) < 1e-6
    # Scale convention: the 99th percentile of the maximum channel of the reflectance is 1.
    np.testing.assert_allclose(r[0, 0], [0.6, 1.0, 0.4], rtol=1e-5)
    np.testing.assert_allclose(s[0, 0], [0.5, 0.5, 0.5], rtol=1e-5)


def test_scale_convention_and_mask():
    image, _, _, _ = synthetic()
    mask = np.ones((H, W), bool)
    mask[:, 40:44] = False  # splits the image into two components
    mask[5, 5] = False
    image = image.copy()
    image[5, 5] = np.nan  # non-finite pixels must be outside the mask
    r, s = color_retinex(image, mask=mask)
    assert not r[~mask].any() and not s[~mask].any()
    assert np.isfinite(r).all() and np.isfinite(s).all() and (s[mask] > 0).all()
    np.testing.assert_allclose(r[mask] * s[mask], image[mask], rtol=1e-5, atol=1e-7)
    assert np.percentile(r.max(axis=2)[mask], 99) == pytest.approx(1.0, rel=1e-6)


def test_scale_is_exposure_invariant():
    image, _, _, _ = synthetic("wave")
    r1, s1 = color_retinex(image)
    r2, s2 = color_retinex(image * 37.0)
    np.testing.assert_allclose(r1, r2, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(s2, 37.0 * s1, rtol=1e-5)


def test_thresholds_decide_what_is_reflectance():
    image, _, _, _ = synthetic()
    # Nothing is a reflectance change: the shading is the grey image (up to scale).
    _, s = color_retinex(image, gray_threshold=np.inf, color_threshold=np.inf)
    assert relative_std(s[..., 0] / image.mean(axis=2)) < 1e-5
    # Everything is a reflectance change: the shading is constant, the reflectance is the image.
    r, s = color_retinex(image, gray_threshold=0.0, color_threshold=0.0)
    assert np.ptp(s) < 1e-6 * s.max()
    assert relative_std((r / image).ravel()) < 1e-5


def test_reflectance_edges():
    log_rgb = np.zeros((2, 4, 3))
    log_rgb[:, 1] = 0.5  # grey step of 0.5 between columns 0 and 1
    log_rgb[:, 2] = [0.5, 0.7, 0.3]  # chromatic step (norm sqrt(0.08) ~ 0.28), no grey change
    log_rgb[:, 3] = [0.55, 0.75, 0.35]  # small grey step 0.05
    along_x, along_y = reflectance_edges(log_rgb, gray_threshold=0.3, color_threshold=0.2)
    assert along_x.shape == (2, 3) and along_y.shape == (1, 4)
    np.testing.assert_array_equal(along_x, [[True, True, False]] * 2)
    assert not along_y.any()
    along_x, _ = reflectance_edges(log_rgb, gray_threshold=0.6, color_threshold=0.3)
    assert not along_x.any()


def test_poisson_integrate_recovers_a_field_per_component():
    rng = np.random.default_rng(3)
    y, x = np.mgrid[0:40, 0:50]
    field = np.sin(x / 7.0) + 0.02 * (y - 20) ** 2 / 10 + 0.1 * rng.standard_normal((40, 50))
    mask = rng.random((40, 50)) > 0.1
    mask[:, 24:26] = False  # two components
    out = poisson_integrate(np.diff(field, axis=1), np.diff(field, axis=0), mask)
    assert not out[~mask].any()
    import scipy.ndimage

    labels, count = scipy.ndimage.label(mask)
    assert count >= 2
    for k in range(1, count + 1):
        part = labels == k
        assert abs(out[part].mean()) < 1e-9  # zero mean per component
        np.testing.assert_allclose(out[part], field[part] - field[part].mean(), atol=1e-5)


def test_poisson_integrate_large_image_is_fast():
    import time

    h, w = 750, 1000
    y, x = np.mgrid[0:h, 0:w] / 100.0
    field = np.sin(x) * np.cos(y)
    mask = np.random.default_rng(0).random((h, w)) > 0.01
    start = time.perf_counter()
    out = poisson_integrate(np.diff(field, axis=1), np.diff(field, axis=0), mask)
    assert time.perf_counter() - start < 20.0  # about 1 s on the development machine
    error = (out - field)[mask]  # the 1 % holes leave one big component (and a few isolated pixels)
    assert np.abs(error - np.median(error)).max() < 1e-3  # field amplitude 1


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"image": np.ones((4, 4))}, "shape"),
        ({"image": np.ones((4, 4, 3)), "mask": np.ones((4, 5), bool)}, "mask"),
        ({"image": np.ones((4, 4, 3)), "mask": np.zeros((4, 4), bool)}, "no finite pixel"),
        ({"image": np.ones((4, 4, 3)), "gray_threshold": -1.0}, "gray_threshold"),
        ({"image": np.ones((4, 4, 3)), "color_threshold": np.nan}, "color_threshold"),
        ({"image": np.ones((4, 4, 3)), "floor": 0.0}, "floor"),
    ],
)
def test_color_retinex_rejects_bad_input(kwargs, message):
    image = kwargs.pop("image")
    with pytest.raises(ValueError, match=message):
        color_retinex(image, **kwargs)


def test_defaults_are_on_grosse_grid():
    assert retinex.DEFAULT_GRAY_THRESHOLD in retinex.THRESHOLD_GRID
    assert retinex.DEFAULT_COLOR_THRESHOLD in retinex.THRESHOLD_GRID


def test_run_retinex_writes_a_scorable_result(scene_dir, tmp_path, capsys):
    import run_retinex

    from mvintrinsic.io import load_decomposition, load_scene
    from mvintrinsic.results import SHADOW_LABELS

    out = tmp_path / "result"
    assert run_retinex.main([str(scene_dir), str(out)]) == 0
    assert "result written to" in capsys.readouterr().out
    result = load_decomposition(out)
    scene = load_scene(scene_dir)
    assert result.stems == tuple(v.stem for v in scene.views)
    assert set(result.timings) == {"retinex"}
    assert result.config["gray_threshold"] == retinex.DEFAULT_GRAY_THRESHOLD
    assert result.config["color_threshold"] == retinex.DEFAULT_COLOR_THRESHOLD
    np.testing.assert_allclose(result.lighting.sun.direction, scene.sun.direction)
    np.testing.assert_array_equal(result.lighting.sun_radiance, np.zeros(3))
    for view in scene.views:
        layers = result.layers[view.stem]
        assert not layers.sun_shading.any() and not layers.sky_shading.any() and not layers.visibility.any()
        assert (layers.shadow_labels == SHADOW_LABELS["undecided"]).all()
        np.testing.assert_array_equal(layers.shading, layers.indirect_shading)
        m = view.mask
        np.testing.assert_allclose(layers.reconstruct()[m], np.maximum(view.image[m], 0), rtol=1e-4, atol=1e-6)
    # Writing into the scene folder is refused (exit status 2, one-line error).
    assert run_retinex.main([str(scene_dir), str(scene_dir / "out")]) == 2
    assert "run_retinex: error:" in capsys.readouterr().err
