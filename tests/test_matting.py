"""Per-pixel layers (paper Sec. 6.2): soft visibility by matting, image-guided shading propagation.

Known answers: a penumbra rendered with the image model (Eq. 1) and a linear visibility ramp is a
linear blend of the lit and shadowed colours, the case where closed-form matting recovers the
blend; a linear field is reproduced from sparse constraints on a uniform image, and a step
between two colours does not leak across their edge. Invariants: ``R * S_tot == I`` (Eq. 17),
finite layers, zeros and label 128 off the valid pixels. The solver is checked on a system with a
known solution.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import scipy.sparse as sp

from mvintrinsic.camera import Camera
from mvintrinsic.matting import (
    MattingConfig,
    _preconditioner,
    _solve,
    guide_image,
    intrinsic_layers,
    propagate,
    shadow_transitions,
    sun_visibility_matting,
)
from mvintrinsic.pixels import PixelQuantities
from mvintrinsic.results import IntrinsicLayers
from mvintrinsic.scene import View

#: Tolerances, in one place.
TOL = {
    "ramp": 0.03,         # |v_sun - true ramp| in the penumbra (closed-form matte of an exact blend)
    "plateau": 1e-3,      # v_sun away from the penumbra (0 in shadow, 1 in light)
    "field": 1e-4,        # relative error of a linear field rebuilt from sparse constraints
    "soft": 1e-2,         # the same with Levin et al.'s soft constraints (lambda = 100): about 1 / lambda
    "leak": 0.02,         # value leaking across a strong colour edge
    "diffusion": 1e-3,    # harmonic fill of a band, relative to the field
    "invariant": 1e-4,    # relative |R * S_tot - I| on valid pixels (the acceptance criterion)
    "solver": 1e-6,       # conjugate gradients against a direct solve
}

H, W = 24, 48
SKY = np.array([0.30, 0.35, 0.45])     # S_sky, bluish (shading units)
INDIRECT = np.array([0.05, 0.05, 0.04])
SUN = np.array([1.00, 0.90, 0.75])     # L_sun
COSINE = 0.8
ALBEDO = np.array([0.6, 0.45, 0.3])
#: The penumbra: v_sun rises linearly from 0 at column RAMP[0] to 1 at column RAMP[1].
RAMP = (18.0, 30.0)
#: Relative pixel noise of the synthetic views (renders and photographs are never noiseless).
NOISE = 0.005


def true_visibility(h: int = H, w: int = W) -> np.ndarray:
    columns = np.arange(w, dtype=float)
    ramp = np.clip((columns - RAMP[0]) / (RAMP[1] - RAMP[0]), 0.0, 1.0)
    return np.broadcast_to(ramp, (h, w)).copy()


def penumbra_image(h: int = H, w: int = W, *, noise: float = NOISE, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Image of Eq. 1 with a soft shadow edge (uniform albedo, mild pixel noise), and its true visibility.

    Under the ramp the image is exactly ``v F + (1 - v) B`` with ``F`` the lit and ``B`` the
    shadowed colour, the compositing equation that closed-form matting inverts.
    """
    visibility = true_visibility(h, w)
    shading = SKY + INDIRECT + visibility[..., None] * SUN * COSINE
    rng = np.random.default_rng(seed)
    image = ALBEDO * shading * (1.0 + noise * rng.standard_normal((h, w, 3)))
    return image.astype(np.float32), visibility


def binary_labels(visibility: np.ndarray) -> np.ndarray:
    return np.where(visibility >= 0.5, 255, 0).astype(np.uint8)


# --------------------------------------------------------------------------------------------
# Configuration and input checks
# --------------------------------------------------------------------------------------------

@pytest.mark.parametrize(("field", "value"), [
    ("trimap_radius", 0), ("trimap_radius", 2.5), ("visibility_cluster_width", -1), ("cluster_boundary_width", True),
    ("shadow_band_radius", -2), ("window_radius", 0), ("max_iter", 0), ("epsilon", 0.0), ("epsilon", np.inf),
    ("constraint_weight", -1.0), ("prior_weight", 0.0), ("rtol", 1.0), ("ichol_threshold", np.nan),
    ("shading_floor", 1.0), ("white_percentile", 0.0), ("white_percentile", 101.0),
])
def test_config_validation_names_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        MattingConfig(**{field: value})


def test_config_defaults_and_json_round_trip():
    config = MattingConfig()
    assert config.epsilon == 1e-6 and config.window_radius == 1  # Levin et al.'s window, a larger epsilon
    assert config.constraint_weight is None  # hard constraints
    assert MattingConfig(**dataclasses.asdict(config)) == config


def test_bad_inputs_name_the_argument():
    image, visibility = penumbra_image()
    labels = binary_labels(visibility)
    with pytest.raises(TypeError, match="labels"):
        sun_visibility_matting(image, labels.astype(np.int32))
    with pytest.raises(ValueError, match="labels may only hold"):
        sun_visibility_matting(image, np.full((H, W), 7, dtype=np.uint8))
    with pytest.raises(ValueError, match="mask"):
        sun_visibility_matting(image, labels, mask=np.ones((H, W + 1), dtype=bool))
    with pytest.raises(TypeError, match="config"):
        sun_visibility_matting(image, labels, config={"trimap_radius": 3})
    with pytest.raises(ValueError, match="clusters"):
        sun_visibility_matting(image, labels, clusters=np.zeros((H, 3), dtype=np.int32))
    nan_image = image.copy()
    nan_image[3, 4] = np.nan
    with pytest.raises(ValueError, match="image must be finite on the mask"):
        sun_visibility_matting(nan_image, labels)
    values = np.ones((H, W))
    known = np.zeros((H, W), dtype=bool)
    with pytest.raises(ValueError, match="known must hold"):
        propagate(image, values, known)
    known[5, 5] = True
    values[5, 5] = np.nan
    with pytest.raises(ValueError, match="values must be finite on the known"):
        propagate(image, values, known)
    with pytest.raises(ValueError, match="values must have shape"):
        propagate(image, np.ones((H, 3)), known)


def test_non_finite_pixels_outside_the_mask_are_ignored():
    image, visibility = penumbra_image()
    mask = np.ones((H, W), dtype=bool)
    mask[:4] = False
    image[:4] = np.nan
    matte = sun_visibility_matting(image, binary_labels(visibility), mask=mask)
    assert np.isfinite(matte).all() and (matte[:4] == 0).all()
    assert guide_image(image, mask=mask)[:4].max() == 0


# --------------------------------------------------------------------------------------------
# Visibility matting
# --------------------------------------------------------------------------------------------

def test_shadow_transitions_marks_both_sides():
    labels = np.full((3, 6), 255, dtype=np.uint8)
    labels[:, :2] = 0
    labels[:, 4:] = 128
    marked = shadow_transitions(labels)
    assert marked[:, 1:3].all() and marked.sum() == 6  # undecided pixels make no transition


def test_matting_recovers_a_soft_shadow_ramp():
    image, truth = penumbra_image()
    config = MattingConfig(trimap_radius=9)  # the band (columns 15-32) holds the whole ramp
    matte = sun_visibility_matting(image, binary_labels(truth), config=config)
    assert matte.dtype == np.float32 and matte.shape == (H, W)
    penumbra = (truth > 0) & (truth < 1)
    assert np.abs(matte - truth)[penumbra].max() < TOL["ramp"]
    assert np.abs(matte - truth).max() < TOL["ramp"]
    assert (matte[:, :10] < TOL["plateau"]).all() and (matte[:, -10:] > 1 - TOL["plateau"]).all()
    # Monotone across the edge, as the true ramp.
    assert (np.diff(matte.mean(axis=0)) > -TOL["plateau"]).all()


def test_thin_shadows_survive_the_trimap():
    """A 2-px shadow line in light keeps its centre as known: the matte does not erase it."""
    visibility = np.ones((H, W))
    visibility[10:12] = 0.0
    albedo = ALBEDO * np.ones((H, W, 1))
    image = (albedo * (SKY + INDIRECT + visibility[..., None] * SUN * COSINE)).astype(np.float32)
    matte = sun_visibility_matting(image, binary_labels(visibility))
    assert matte[10:12].max() < TOL["plateau"] and matte[:6].min() > 1 - TOL["plateau"]


def test_visibility_is_propagated_in_cluster_boundaries():
    """A shadow the labels missed, on a cluster boundary next to a labelled shadow, is matted in."""
    image, truth = penumbra_image()
    labels = binary_labels(truth)
    clusters = np.zeros((H, W), dtype=np.int32)
    clusters[:, 24:] = 1  # the boundary falls inside the penumbra
    far = MattingConfig(trimap_radius=1, visibility_cluster_width=0)
    near = MattingConfig(trimap_radius=1, visibility_cluster_width=4)
    without = sun_visibility_matting(image, labels, clusters=clusters, config=far)
    with_band = sun_visibility_matting(image, labels, clusters=clusters, config=near)
    columns = slice(21, 27)
    assert np.abs(with_band - truth)[:, columns].mean() < np.abs(without - truth)[:, columns].mean()


def test_undecided_pixels_are_matted_and_unreachable_ones_take_the_nearest_label():
    image, truth = penumbra_image()
    labels = binary_labels(truth)
    labels[:, 17:31] = 128  # the penumbra, undecided
    mask = np.ones((H, W), dtype=bool)
    mask[:, 40] = False  # cuts the right edge off: columns 41-47 reach no label but lit ones
    labels[:, 41:] = 128
    matte = sun_visibility_matting(image, labels, mask=mask, config=MattingConfig(trimap_radius=1))
    assert np.isfinite(matte).all() and matte.min() >= 0 and matte.max() <= 1
    assert np.abs(matte - truth)[:, 17:31].max() < TOL["ramp"]
    assert (matte[:, 41:] > 1 - TOL["plateau"]).all()  # the nearest labelled pixels are lit


# --------------------------------------------------------------------------------------------
# Propagation
# --------------------------------------------------------------------------------------------

def linear_field(h: int = H, w: int = W) -> np.ndarray:
    rows, cols = np.mgrid[0:h, 0:w]
    return np.stack([1.0 + 0.5 * cols / w + 0.3 * rows / h, 2.0 - 0.4 * rows / h], axis=-1)


def sparse_grid(step: int, h: int = H, w: int = W) -> np.ndarray:
    """Every ``step``-th pixel, and a 2-px frame.

    The frame: the matting Laplacian only has windows wholly inside the image, so a pixel less
    than 2 px from the border is not balanced by windows on both sides and a linear field is not
    its minimiser there; with the frame known, it is everywhere.
    """
    known = np.zeros((h, w), dtype=bool)
    known[::step, ::step] = True
    known[:2] = known[-2:] = True
    known[:, :2] = known[:, -2:] = True
    return known


def test_propagation_rebuilds_a_smooth_field_on_a_uniform_image():
    image = np.full((H, W, 3), 0.4, dtype=np.float32)
    field = linear_field()
    known = sparse_grid(5)
    assert known.mean() < 0.3
    out = propagate(image, np.where(known[..., None], field, np.nan), known)
    assert out.shape == field.shape and out.dtype == np.float64
    assert np.abs(out - field).max() / np.abs(field).max() < TOL["field"]
    np.testing.assert_allclose(out[known], field[known])  # hard constraints
    single = propagate(image, np.where(known, field[..., 0], 0.0), known)  # (H, W) in, (H, W) out
    np.testing.assert_allclose(single, out[..., 0], atol=1e-9)
    # Soft constraints (Levin et al.'s lambda = 100) agree to about 1 / lambda.
    soft = propagate(image, np.where(known[..., None], field, 0.0), known, config=MattingConfig(constraint_weight=100.0))
    assert np.abs(soft - field).max() / np.abs(field).max() < TOL["soft"]


def test_propagation_does_not_leak_across_a_colour_edge():
    image = np.empty((H, W, 3), dtype=np.float32)
    image[:, :24] = [0.7, 0.2, 0.1]
    image[:, 24:] = [0.1, 0.3, 0.8]
    values = np.where(np.arange(W) < 24, 0.0, 1.0)[None, :].repeat(H, axis=0)
    known = np.zeros((H, W), dtype=bool)
    known[H // 2, [3, 44]] = True  # one constraint per side, far from the edge
    out = propagate(image, values, known)
    assert np.abs(out - values).max() < TOL["leak"]
    # The same constraints on a uniform image spread smoothly across the middle.
    smooth = propagate(np.full_like(image, 0.4), values, known)
    assert 0.2 < smooth[H // 2, 24] < 0.8


def test_band_is_filled_by_diffusion_not_by_the_image():
    """The band straddles a sharp shadow edge; its values come from the smooth field around it."""
    image, _ = penumbra_image()
    image[:, 24:] *= 3.0  # a sharp edge in the middle of the band
    field = linear_field()
    band = np.zeros((H, W), dtype=bool)
    band[2:-2, 20:28] = True  # surrounded by known pixels (a harmonic fill with Neumann borders bends)
    known = ~band
    out = propagate(image, field, known, band=band)
    # A linear field is harmonic for the 4-neighbour Laplacian: the fill is exact.
    assert np.abs(out - field)[band].max() / np.abs(field).max() < TOL["diffusion"]
    np.testing.assert_allclose(out[known], field[known])


def spd_system(n: int = 300, seed: int = 0) -> sp.csr_matrix:
    rng = np.random.default_rng(seed)
    lower = sp.random(n, n, density=0.02, random_state=rng, format="csr")
    return (lower @ lower.T + sp.eye(n) * 2.0).tocsr()


def test_block_substitution_applies_the_cholesky_inverse():
    """With nothing discarded the incomplete factorisation is complete: M^-1 b = A^-1 b, all columns at once."""
    matrix = spd_system()
    rhs = np.random.default_rng(1).standard_normal((matrix.shape[0], 3))
    apply = _preconditioner(matrix, MattingConfig(ichol_threshold=1e-300))
    # The smallest shift (1e-4) perturbs M by 1e-4 I against eigenvalues >= 2.
    np.testing.assert_allclose(apply(rhs), np.linalg.solve(matrix.toarray(), rhs), rtol=1e-3, atol=1e-4)


def test_solver_on_a_system_with_known_solution():
    matrix = spd_system()
    n = matrix.shape[0]
    solution = np.random.default_rng(2).standard_normal((n, 2))
    found = _solve(matrix, matrix @ solution, np.zeros((n, 2)), MattingConfig(rtol=1e-10), "test")
    np.testing.assert_allclose(found, solution, atol=TOL["solver"])


# --------------------------------------------------------------------------------------------
# Intrinsic layers
# --------------------------------------------------------------------------------------------

def synthetic_view() -> tuple[View, PixelQuantities, np.ndarray, np.ndarray]:
    """A view of Eq. 1 with a penumbra, a sky strip on top and uncovered ("filled") pixels."""
    image, truth = penumbra_image()
    sky = np.zeros((H, W), dtype=bool)
    sky[:3] = True
    filled = np.zeros((H, W), dtype=bool)
    filled[15:20, 5:12] = True
    valid = ~sky
    image[sky] = [5.0, 6.0, 8.0]  # bright sky: must not drive the matte
    camera = Camera("PINHOLE", W, H, [W, W, W / 2, H / 2], np.eye(3), np.zeros(3))
    view = View("v", image, camera)
    zero = ~valid[..., None]
    quantities = PixelQuantities(
        stem="v",
        sky=np.where(zero, 0.0, SKY * np.ones((H, W, 1))).astype(np.float32),
        indirect=np.where(zero, 0.0, INDIRECT * np.ones((H, W, 1))).astype(np.float32),
        visibility=np.where(valid, truth > 0.5, 1.0).astype(np.float32),
        cosine=np.where(valid, COSINE, 0.0).astype(np.float32),
        normals=np.where(zero, 0.0, np.array([0.0, 0.0, 1.0])).astype(np.float32),
        depth=np.where(valid, 10.0, np.inf).astype(np.float32),
        sky_mask=sky, filled=filled, valid=valid,
    )
    labels = np.where(valid, binary_labels(truth), 128).astype(np.uint8)
    clusters = np.where(valid, (np.arange(W) // 8)[None, :] + 10 * (np.arange(H) // 8)[:, None], -1).astype(np.int32)
    return view, quantities, labels, clusters


def test_intrinsic_layers_reproduce_the_image():
    view, quantities, labels, clusters = synthetic_view()
    config = MattingConfig(trimap_radius=9)
    layers = intrinsic_layers(view, quantities, labels, SUN, clusters=clusters, config=config)
    assert isinstance(layers, IntrinsicLayers) and layers.stem == "v"
    valid = quantities.valid
    for name in ("reflectance", "sun_shading", "sky_shading", "indirect_shading", "visibility"):
        layer = getattr(layers, name)
        assert np.isfinite(layer).all(), name
        assert (layer[~valid] == 0).all(), name
    assert (layers.shadow_labels[~valid] == 128).all()
    np.testing.assert_array_equal(layers.shadow_labels[valid], labels[valid])
    image = np.asarray(view.image)[valid]
    relative = np.abs(layers.reconstruct()[valid] - image) / np.abs(image)
    assert relative.max() < TOL["invariant"]
    # On this exact image-model scene the layers are the truth: constant shading, the ramp.
    np.testing.assert_allclose(layers.sky_shading[valid], np.broadcast_to(SKY, (valid.sum(), 3)), rtol=1e-4)
    np.testing.assert_allclose(layers.sun_shading[valid], np.broadcast_to(SUN * COSINE, (valid.sum(), 3)), rtol=1e-4)
    assert np.abs(layers.visibility - true_visibility())[valid].max() < TOL["ramp"]


def test_intrinsic_layers_floor_tiny_shading_and_check_inputs():
    view, quantities, labels, _ = synthetic_view()
    dark = dataclasses.replace(quantities, sky=np.zeros_like(quantities.sky),
                               indirect=np.zeros_like(quantities.indirect))
    layers = intrinsic_layers(view, dark, labels, SUN)  # shadowed pixels have S_tot = 0
    valid = quantities.valid
    image = np.asarray(view.image)[valid]
    assert np.isfinite(layers.reflectance).all()
    assert np.abs(layers.reconstruct()[valid] - image).max() / np.abs(image).max() < TOL["invariant"]
    with pytest.raises(ValueError, match="sun_radiance"):
        intrinsic_layers(view, quantities, labels, -SUN)
    with pytest.raises(ValueError, match="labels must have shape"):
        intrinsic_layers(view, quantities, labels[:, :-1], SUN)
    with pytest.raises(ValueError, match="do not belong"):
        intrinsic_layers(view, dataclasses.replace(quantities, stem="w"), labels, SUN)


def test_solver_that_runs_out_of_iterations_logs_and_returns_the_last_iterate(caplog):
    matrix = spd_system()
    rhs = np.ones((matrix.shape[0], 1))
    config = MattingConfig(rtol=1e-14, max_iter=1, ichol_threshold=0.5)
    with caplog.at_level("WARNING", logger="mvintrinsic.matting"):
        found = _solve(matrix, rhs, np.zeros_like(rhs), config, "tiny system")
    assert np.isfinite(found).all()
    assert np.linalg.norm(matrix @ found - rhs) < np.linalg.norm(rhs)  # one step made progress
    assert any("tiny system" in r.getMessage() and "after 1 iterations" in r.getMessage() for r in caplog.records)
