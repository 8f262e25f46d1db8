"""Over-segmentation (paper Sec. 6.1): mean shift and SLIC behind one interface.

Piecewise-constant images with known regions must be recovered exactly; the invariants (labels
0..n-1, no segment under ``min_region``, 4-connected segments, masked pixels -1) hold on textured
input; the neighbourhood helpers are checked on hand-made label maps.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy import ndimage

from mvintrinsic.segmentation import (
    SEGMENTATION_METHODS,
    Segmentation,
    SegmentationConfig,
    boundary_band,
    boundary_mask,
    merge_small_regions,
    perceptual_lab,
    region_adjacency,
    segment,
)

H, W = 60, 80
#: Linear RGB of the four rectangles (top-left, top-right, bottom-left, bottom-right).
COLORS = np.array([[0.6, 0.2, 0.1], [0.1, 0.5, 0.2], [0.15, 0.2, 0.7], [0.7, 0.7, 0.6]])
#: Relative (multiplicative) noise of the "mild noise" images: an rms of 1.3-1.9 Delta E about each
#: rectangle's CIELAB mean, below the default 3 Delta E colour bandwidth (at 3% noise, 2-2.9 Delta E,
#: the bright rectangle can split into two pieces larger than min_region, as mean shift should).
NOISE = 0.02
#: A SLIC configuration with one superpixel per rectangle.
SLIC_4 = SegmentationConfig(method="slic", slic_mean_area=H * W / 4)
CONFIGS = {"mean_shift": SegmentationConfig(), "slic": SLIC_4}


def rectangles() -> np.ndarray:
    """(H, W) int: index of the rectangle of each pixel (2 x 2 layout)."""
    truth = np.zeros((H, W), dtype=np.int64)
    truth[: H // 2, W // 2:] = 1
    truth[H // 2:, : W // 2] = 2
    truth[H // 2:, W // 2:] = 3
    return truth


def rectangle_image(*, noise: float = NOISE, seed: int = 0, scale: float = 1.0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    image = COLORS[rectangles()] * (1.0 + noise * rng.standard_normal((H, W, 3)))
    return (scale * image).astype(np.float32)


def textured_image(seed: int = 1) -> np.ndarray:
    """Smooth random colour field plus pixel noise: many regions of varied size."""
    rng = np.random.default_rng(seed)
    field = ndimage.gaussian_filter(rng.uniform(size=(H, W, 3)), sigma=(4, 4, 0))
    field = (field - field.min()) / (field.max() - field.min())
    return (0.05 + 0.8 * field * (1 + 0.05 * rng.standard_normal((H, W, 3)))).astype(np.float32)


def contingency(labels: np.ndarray, truth: np.ndarray) -> np.ndarray:
    valid = labels >= 0
    table = np.zeros((labels.max() + 1, truth.max() + 1), dtype=np.int64)
    np.add.at(table, (labels[valid], truth[valid]), 1)
    return table


def assert_partition_matches(labels: np.ndarray, truth: np.ndarray) -> None:
    """Labels equal ``truth`` up to a permutation of the label values."""
    table = contingency(labels, truth)
    assert table.shape[0] == table.shape[1]
    assert ((table > 0).sum(axis=0) == 1).all() and ((table > 0).sum(axis=1) == 1).all()


def assert_invariants(seg: Segmentation, min_region: int) -> None:
    labels = seg.labels
    assert labels.dtype == np.int32 and not labels.flags.writeable
    assert np.array_equal(np.unique(labels[labels >= 0]), np.arange(seg.n_segments))
    assert seg.sizes.min() >= min_region
    assert seg.sizes.sum() == (labels >= 0).sum()
    for k in range(seg.n_segments):  # every segment is one 4-connected piece
        assert ndimage.label(labels == k)[1] == 1


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("method", SEGMENTATION_METHODS)
def test_rectangles_with_mild_noise_are_recovered(method, seed):
    seg = segment(rectangle_image(seed=seed), config=CONFIGS[method])
    assert seg.n_segments == 4 and seg.method == method
    assert_partition_matches(seg.labels, rectangles())
    assert seg.sizes.tolist() == [H * W // 4] * 4


def test_paper_defaults():
    config = SegmentationConfig()
    assert (config.method, config.spatial_bandwidth, config.min_region) == ("mean_shift", 5, 50)


@pytest.mark.parametrize("method", SEGMENTATION_METHODS)
def test_textured_image_invariants(method):
    config = SegmentationConfig(method=method, min_region=30)
    seg = segment(textured_image(), config=config)
    assert 5 < seg.n_segments <= H * W // 30
    assert_invariants(seg, 30)


def test_mean_shift_splits_a_cast_shadow_on_one_material():
    # One material, its left third in shadow (lit by the bluer sky only): no segment straddles.
    rng = np.random.default_rng(3)
    shading = np.where(np.arange(W) < W // 3, 0.25, 1.0)[None, :, None] * np.array([0.9, 0.95, 1.1])
    image = (COLORS[0] * shading * (1 + NOISE * rng.standard_normal((H, W, 3)))).astype(np.float32)
    seg = segment(image)
    shadow = np.broadcast_to(np.arange(W) < W // 3, (H, W)).astype(np.int64)
    assert seg.n_segments == 2
    assert_partition_matches(seg.labels, shadow)


@pytest.mark.parametrize("method", SEGMENTATION_METHODS)
def test_deterministic(method):
    image = textured_image(seed=5)
    config = SegmentationConfig(method=method)
    assert np.array_equal(segment(image, config=config).labels, segment(image, config=config).labels)


@pytest.mark.parametrize("method", SEGMENTATION_METHODS)
def test_exposure_scale_does_not_matter(method):
    # The white level follows the image (a power of two keeps the float arithmetic exact): HDR
    # values above 1 segment like the same image exposed lower.
    image = textured_image(seed=2)
    config = SegmentationConfig(method=method)
    reference = segment(image, config=config)
    brighter = segment(image * np.float32(16.0), config=config)
    assert brighter.labels.max() > 0
    assert np.array_equal(reference.labels, brighter.labels)


def test_labels_are_in_raster_order():
    seg = segment(rectangle_image())
    assert seg.labels[0, 0] == 0 and seg.labels[0, -1] == 1 and seg.labels[-1, 0] == 2 and seg.labels[-1, -1] == 3


@pytest.mark.parametrize("method", SEGMENTATION_METHODS)
def test_mask_pixels_get_minus_one_and_do_not_matter(method):
    image = rectangle_image()
    mask = np.ones((H, W), dtype=bool)
    mask[10:20, 5:70] = False  # a band across the two top rectangles
    corrupted = image.copy()
    corrupted[~mask] = np.nan  # invalid pixels may hold anything
    seg = segment(corrupted, mask=mask, config=CONFIGS[method])
    assert (seg.labels[~mask] == -1).all() and (seg.labels[mask] >= 0).all()
    assert seg.n_segments == 4
    assert_partition_matches(seg.labels, rectangles())
    assert seg.sizes.sum() == mask.sum()


def test_mask_island_smaller_than_min_region_stays_alone():
    mask = np.zeros((H, W), dtype=bool)
    mask[:, :50] = True
    mask[5:10, 60:65] = True  # a 25-pixel island: no neighbour to merge into
    seg = segment(rectangle_image(), mask=mask)
    island = np.unique(seg.labels[5:10, 60:65])
    assert len(island) == 1 and seg.sizes[island[0]] == 25
    assert (seg.sizes >= 50).sum() == seg.n_segments - 1


def test_empty_mask_gives_no_segment():
    seg = segment(rectangle_image(), mask=np.zeros((H, W), dtype=bool))
    assert seg.n_segments == 0 and (seg.labels == -1).all() and seg.sizes.shape == (0,)
    assert seg.adjacency.shape == (0, 2) and not seg.boundaries.any()


@pytest.mark.parametrize("method", SEGMENTATION_METHODS)
@pytest.mark.parametrize("shape", [(1, 1), (3, 4), (7, 9)])
def test_images_smaller_than_min_region_are_one_segment(method, shape):
    image = np.random.default_rng(0).uniform(size=(*shape, 3))
    seg = segment(image, config=SegmentationConfig(method=method))
    assert seg.n_segments == 1 and (seg.labels == 0).all()


@pytest.mark.parametrize("value", [0.0, 1.0, 1e6])
def test_constant_image_is_one_segment(value):
    seg = segment(np.full((H, W, 3), value, dtype=np.float32))
    assert seg.n_segments == 1


def test_adjacency_of_the_four_rectangles():
    seg = segment(rectangle_image())
    # 4-connectivity: the diagonal rectangles (0, 3) and (1, 2) do not touch.
    assert seg.adjacency.tolist() == [[0, 1], [0, 2], [1, 3], [2, 3]]
    assert seg.adjacency.dtype == np.int32
    assert seg.contact_lengths.tolist() == [H // 2, W // 2, W // 2, H // 2]


def test_region_adjacency_on_a_known_layout():
    labels = np.array([
        [0, 0, 1, 1],
        [0, 0, 1, 1],
        [2, 3, 3, 1],
        [2, -1, 3, 4],
    ])
    pairs, lengths = region_adjacency(labels)
    # 0-1: 2 horizontal contacts; 0-2: 1 (col 0); 0-3: 1 (col 1); 1-3: 2 (row 1 col 2, row 2 col 2|3);
    # 1-4: 1 (col 3); 2-3: 1 (row 2); 3-4: 1 (row 3); nothing touches the invalid pixel.
    assert pairs.tolist() == [[0, 1], [0, 2], [0, 3], [1, 3], [1, 4], [2, 3], [3, 4]]
    assert lengths.tolist() == [2, 1, 1, 2, 1, 1, 1]


def test_boundary_mask_and_band_on_a_vertical_edge():
    labels = np.zeros((10, 20), dtype=np.int32)
    labels[:, 10:] = 1
    seg = Segmentation(labels, 2, "mean_shift")
    edge_columns = np.flatnonzero(seg.boundaries.any(axis=0))
    assert edge_columns.tolist() == [9, 10] and seg.boundaries[:, [9, 10]].all()
    for width in (1, 2, 3):
        band = seg.band(width)
        assert np.flatnonzero(band.any(axis=0)).tolist() == list(range(10 - width, 10 + width))
        assert band[:, 10 - width:10 + width].all()
    assert np.array_equal(boundary_band(labels, 1), seg.boundaries)
    assert not boundary_band(labels, 0).any()
    assert not boundary_band(np.zeros((5, 5), dtype=np.int32), 3).any()  # one segment: no boundary


def test_boundary_next_to_invalid_pixels():
    labels = np.zeros((5, 5), dtype=np.int32)
    labels[2, 2] = -1
    edges = boundary_mask(labels)
    assert not edges[2, 2]  # invalid pixels are never boundary pixels
    assert edges.sum() == 4 and edges[[1, 3, 2, 2], [2, 2, 1, 3]].all()
    assert boundary_band(labels, 2)[2, 0] and not boundary_band(labels, 2)[0, 0]


def test_merge_small_regions_joins_the_most_similar_neighbour():
    labels = np.zeros((10, 10), dtype=np.int64)
    labels[:, 5:] = 1
    labels[4:6, 4:6] = 2  # 4 pixels straddling the border
    colors = np.zeros((10, 10, 1))
    colors[labels == 1] = 10.0
    colors[labels == 2] = 8.0  # nearer to region 1
    out = merge_small_regions(labels, colors, 10)
    assert out.max() == 1
    assert np.array_equal(out == out[0, 9], (labels == 1) | (labels == 2))


def test_merge_small_regions_follows_chains_of_small_regions():
    # Columns: big region 0 (colour 0), small regions 1 and 2 (colours 7 and 9), big region 3 (10).
    labels = np.repeat(np.array([[0] * 8 + [1, 2] + [3] * 8]), 5, axis=0)
    colors = np.choose(labels, [0.0, 7.0, 9.0, 10.0])[..., None]
    out = merge_small_regions(labels, colors, 20)
    # 1 picks 2 (distance 2 < 7), 2 picks 3 (1 < 2): both join region 3.
    assert np.array_equal(out, np.repeat(np.array([[0] * 8 + [1] * 10]), 5, axis=0))


def test_merge_small_regions_keeps_invalid_pixels():
    labels = np.arange(16).reshape(4, 4) % 2
    labels[0, 0] = -1
    out = merge_small_regions(labels, np.zeros((4, 4, 3)), 1)
    assert out[0, 0] == -1 and out.dtype == np.int32
    assert (out[labels >= 0] >= 0).all()


def test_segment_means_with_and_without_a_band():
    labels = np.zeros((4, 6), dtype=np.int32)
    labels[:, 3:] = 1
    seg = Segmentation(labels, 2, "slic")
    values = np.tile(np.arange(6.0), (4, 1))
    assert seg.means(values).tolist() == [1.0, 4.0]
    assert seg.means(values, where=~seg.band(1)).tolist() == [0.5, 4.5]
    rgb = np.stack([values, 2 * values, np.zeros_like(values)], axis=2)
    assert seg.means(rgb).tolist() == [[1.0, 2.0, 0.0], [4.0, 8.0, 0.0]]
    assert np.isnan(seg.means(values, where=np.zeros((4, 6), dtype=bool))).all()


def test_segmentation_is_frozen_and_copies_its_labels():
    labels = np.zeros((3, 3), dtype=np.int32)
    seg = Segmentation(labels, 1, "mean_shift")
    assert labels.flags.writeable  # the caller's array is not frozen
    labels[0, 0] = 5
    assert seg.labels[0, 0] == 0
    with pytest.raises(dataclasses.FrozenInstanceError):
        seg.n_segments = 2
    assert repr(seg) == "Segmentation('mean_shift', 3x3, 1 segments)"


def test_perceptual_lab_maps_the_white_percentile_to_white():
    image = np.full((4, 4, 3), 0.25, dtype=np.float32)
    image[0, 0] = 100.0  # a highlight above the 50th percentile is clipped
    lab = perceptual_lab(image, white_percentile=50.0)
    assert lab.shape == (4, 4, 3) and lab.dtype == np.float32
    np.testing.assert_allclose(lab[1, 1], [100.0, 0.0, 0.0], atol=0.01)
    np.testing.assert_allclose(lab[0, 0], [100.0, 0.0, 0.0], atol=0.01)
    # 18% grey (linear, relative to white) is L* = 116 * 0.18 ** (1 / 3) - 16 = 49.5.
    grey = np.ones((2, 2, 3), dtype=np.float32)
    grey[0] = 0.18
    np.testing.assert_allclose(perceptual_lab(grey, white_percentile=100.0)[0, 0, 0], 49.5, atol=0.1)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"image": np.zeros((H, W))}, "image must have shape"),
        ({"image": np.zeros((H, W, 4))}, "image must have shape"),
        ({"image": "not an image"}, "image must be convertible"),
        ({"image": np.zeros((0, 5, 3))}, "image must have at least one pixel"),
        ({"mask": np.ones((H, W + 1), dtype=bool)}, "mask must have shape"),
        ({"mask": np.ones((H, W))}, "mask must be a boolean array"),
        ({"config": {"method": "slic"}}, "config must be a SegmentationConfig"),
    ],
)
def test_segment_bad_input_names_the_argument(kwargs, message):
    args = {"image": rectangle_image()} | kwargs
    image = args.pop("image")
    with pytest.raises((ValueError, TypeError), match=message):
        segment(image, **args)


def test_segment_rejects_nan_on_valid_pixels():
    image = rectangle_image()
    image[3, 4] = np.inf
    with pytest.raises(ValueError, match="image must be finite on valid pixels, got 1"):
        segment(image)


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("method", "watershed"),
        ("spatial_bandwidth", 0),
        ("spatial_bandwidth", 2.5),
        ("color_bandwidth", 0.0),
        ("color_bandwidth", np.inf),
        ("min_region", 0),
        ("min_region", True),
        ("fusion_tolerance", 3.0),
        ("max_iterations", 0),
        ("white_percentile", 0.0),
        ("white_percentile", 101.0),
        ("slic_mean_area", 0.5),
        ("slic_compactness", -1.0),
        ("slic_iterations", 0),
    ],
)
def test_config_errors_name_the_field(field, value):
    with pytest.raises(ValueError, match=f"^{field} must"):
        SegmentationConfig(**{field: value})


def test_config_method_error_lists_the_methods():
    with pytest.raises(ValueError, match=r"\['mean_shift', 'slic'\]"):
        SegmentationConfig(method="quickshift")


def test_helpers_bad_input_names_the_argument():
    labels = np.zeros((4, 4), dtype=np.int32)
    with pytest.raises(ValueError, match="width must be"):
        boundary_band(labels, -1)
    with pytest.raises(ValueError, match="labels must be an"):
        boundary_mask(np.zeros((4, 4, 2), dtype=np.int32))
    with pytest.raises(ValueError, match="labels must be an"):
        region_adjacency(np.zeros((4, 4)))
    with pytest.raises(ValueError, match="colors must have shape"):
        merge_small_regions(labels, np.zeros((4, 5, 3)), 2)
    with pytest.raises(ValueError, match="min_region must be"):
        merge_small_regions(labels, np.zeros((4, 4, 3)), 0)
    with pytest.raises(ValueError, match="white_percentile must"):
        perceptual_lab(np.zeros((2, 2, 3)), white_percentile=0)
    with pytest.raises(TypeError, match="labels must be an"):
        Segmentation(labels.astype(np.int64), 1, "slic")
    with pytest.raises(ValueError, match="labels must lie in"):
        Segmentation(labels, 0, "slic")
    with pytest.raises(ValueError, match="labels must use every segment"):
        Segmentation(labels, 2, "slic")
    with pytest.raises(ValueError, match="values must have shape"):
        Segmentation(labels, 1, "slic").means(np.zeros((3, 4)))
