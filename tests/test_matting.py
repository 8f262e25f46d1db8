"""Per-pixel layers (paper Sec. 6.2): soft visibility by matting, image-guided shading propagation.

Known answers: a penumbra rendered with the image model (Eq. 1) and a linear visibility ramp is a
linear blend of the lit and shadowed colours, the case where closed-form matting recovers the
blend; a linear field is reproduced from sparse constraints on a uniform image, and a step
between two colours does not leak across their edge. Invariants: ``R * S_tot == I`` (Eq. 17),
finite layers, zeros and label 128 off the valid pixels. The Laplacian is checked against Levin
et al.'s Eq. 12 summed window by window, the nested-dissection order against SuperLU's own
ordering, both solvers on a system with a known solution and against each other, and the solve
reports (converged or not) that the layers come with.
"""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse import linalg as spla

from mvintrinsic.camera import Camera
from mvintrinsic.laplacian import _dissection_order, _GuidedLaplacian, _ordered, _solve, _system
from mvintrinsic.matting import (
    MattingConfig,
    MattingResult,
    SolveReport,
    guide_image,
    intrinsic_layers,
    intrinsic_layers_result,
    propagate,
    restore_shadow_level,
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
    "solver": 1e-6,       # a solve against the known solution
    "laplacian": 1e-12,   # the stencil Laplacian against Levin et al.'s Eq. 12 term by term (relative)
    "rank1": 1e-5,        # leak across a noiseless two-colour edge at epsilon = 1e-8 (rank-1 windows)
    "solvers": 1e-4,      # layers of solver="direct" against solver="cg" (relative)
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
    ("shading_floor", 1.0), ("white_percentile", 0.0), ("white_percentile", 101.0), ("solver", "ichol"),
    ("shadow_level", 0.0), ("shadow_level", -1.0), ("shadow_level", np.inf),
])
def test_config_validation_names_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        MattingConfig(**{field: value})


def test_config_defaults_and_json_round_trip():
    config = MattingConfig()
    assert config.epsilon == 1e-6 and config.window_radius == 1  # Levin et al.'s window, a larger epsilon
    assert config.constraint_weight is None  # hard constraints
    assert config.solver == "direct"
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


def test_propagation_does_not_leak_across_a_noiseless_edge_at_tiny_epsilon():
    """Windows on a two-colour edge have a rank-1 covariance; the LDL^T whitening stays accurate.

    pymatting's cofactor inverse leaked 0.07 across this edge at epsilon = 1e-8 (and divided by zero
    at 1e-9); the leak is now of the order of epsilon.
    """
    image = np.empty((H, W, 3), dtype=np.float32)
    image[:, :24] = [0.7, 0.2, 0.1]
    image[:, 24:] = [0.1, 0.3, 0.8]
    values = np.where(np.arange(W) < 24, 0.0, 1.0)[None, :].repeat(H, axis=0)
    known = np.zeros((H, W), dtype=bool)
    known[H // 2, [3, 44]] = True
    for epsilon in (1e-8, 1e-10):
        out = propagate(image, values, known, config=MattingConfig(epsilon=epsilon))
        assert np.abs(out - values).max() < TOL["rank1"]


# --------------------------------------------------------------------------------------------
# The Laplacian and the solvers
# --------------------------------------------------------------------------------------------

def levin_laplacian(image: np.ndarray, epsilon: float, radius: int, keep: np.ndarray) -> np.ndarray:
    """Levin et al.'s Eq. 12 summed window by window (dense, ``np.linalg.inv``): the reference."""
    h, w, _ = image.shape
    size = 2 * radius + 1
    area = size * size
    out = np.zeros((h * w, h * w))
    index = np.arange(h * w).reshape(h, w)
    for y in range(h - size + 1):
        for x in range(w - size + 1):
            if not keep[y:y + size, x:x + size].all():
                continue
            colours = image[y:y + size, x:x + size].reshape(area, 3)
            centred = colours - colours.mean(axis=0)
            inverse = np.linalg.inv(centred.T @ centred / area + epsilon / area * np.eye(3))
            block = np.eye(area) - (1.0 + centred @ inverse @ centred.T) / area
            pixels = index[y:y + size, x:x + size].ravel()
            out[np.ix_(pixels, pixels)] += block
    return out


@pytest.mark.parametrize("radius", [1, 2])
def test_laplacian_and_restricted_system_match_levins_definition(radius):
    rng = np.random.default_rng(radius)
    h, w = 11, 14
    image = rng.random((h, w, 3))
    keep = rng.random((h, w)) > 0.1
    config = MattingConfig(window_radius=radius)
    reference = levin_laplacian(image, config.epsilon, radius, keep)
    laplacian = _GuidedLaplacian(image, config)
    stencil, everything = laplacian.stencils(keep, np.ones((h, w), dtype=bool))
    every = np.arange(h * w)
    matrix, _ = _system(laplacian, stencil, every, np.zeros(h * w))
    scale = np.abs(reference).max()
    np.testing.assert_allclose(matrix.toarray(), reference, atol=TOL["laplacian"] * scale)
    full, _ = _system(laplacian, everything, every, np.zeros(h * w))
    np.testing.assert_allclose(full.toarray(), levin_laplacian(image, config.epsilon, radius, np.ones((h, w), bool)),
                               atol=TOL["laplacian"] * scale)
    # Rows of the unknowns, in elimination order, with the Dirichlet term of the known pixels.
    unknown = keep & (rng.random((h, w)) > 0.5)
    known = keep & ~unknown
    values = rng.random((h * w, 2))
    pixels = _ordered(np.flatnonzero(unknown), laplacian)
    assert sorted(pixels) == list(np.flatnonzero(unknown))
    diagonal = rng.random(len(pixels))
    matrix, rhs = _system(laplacian, stencil, pixels, diagonal, known=known.ravel(), values=values)
    given = np.flatnonzero(known)
    np.testing.assert_allclose(matrix.toarray(), reference[np.ix_(pixels, pixels)] + np.diag(diagonal),
                               atol=TOL["laplacian"] * scale)
    np.testing.assert_allclose(rhs, -reference[np.ix_(pixels, given)] @ values[given], atol=TOL["laplacian"] * scale)


def test_dissection_order_reduces_fill_below_minimum_degree():
    h, w = 40, 60
    image = np.random.default_rng(3).random((h, w, 3))
    laplacian = _GuidedLaplacian(image, MattingConfig())
    stencil = laplacian.stencils(np.ones((h, w), dtype=bool))[0]
    every = np.arange(h * w)

    def fill(order: np.ndarray, spec: str) -> int:
        matrix, _ = _system(laplacian, stencil, order, np.full(len(order), 1e-5))
        factor = spla.splu(matrix, permc_spec=spec, diag_pivot_thresh=0.0, options={"SymmetricMode": True})
        return factor.L.nnz + factor.U.nnz

    order = _ordered(every, laplacian)
    assert np.array_equal(np.sort(order), every)
    dissected = fill(order, "NATURAL")
    assert dissected < 0.6 * fill(every, "NATURAL")  # row-major: a band of 2 rows, filled
    assert dissected < fill(every, "MMD_AT_PLUS_A")  # SuperLU's minimum degree (measured: 302 792 < 315 804)


def test_dissection_order_keeps_parts_that_share_no_window_apart():
    """Two blocks 3 columns apart (no 3x3 window holds pixels of both): each is eliminated in one run."""
    mask = np.zeros((12, 20), dtype=bool)
    mask[:, :8] = True
    mask[:, 11:] = True
    pixels = np.flatnonzero(mask)
    order = pixels[_dissection_order(pixels, 20, 2, leaf=4)]
    left = (order % 20) < 8
    assert np.count_nonzero(np.diff(left.astype(int))) == 1


def spd_system(n: int = 300, seed: int = 0) -> sp.csc_matrix:
    rng = np.random.default_rng(seed)
    lower = sp.random(n, n, density=0.02, random_state=rng, format="csr")
    return (lower @ lower.T + sp.eye(n) * 2.0).tocsc()


@pytest.mark.parametrize("solver", ["direct", "cg"])
def test_solvers_on_a_system_with_known_solution(solver):
    matrix = spd_system()
    n = matrix.shape[0]
    solution = np.random.default_rng(2).standard_normal((n, 2))
    config = MattingConfig(rtol=1e-10, solver=solver)
    found, report = _solve(matrix, matrix @ solution, np.zeros((n, 2)), config, "test")
    np.testing.assert_allclose(found, solution, atol=TOL["solver"])
    assert isinstance(report, SolveReport) and report.solver == solver and report.what == "test"
    assert report.converged and report.residual <= 1e-10
    assert (report.unknowns, report.channels) == (n, 2) and report.seconds >= 0
    assert report.n_iter >= (1 if solver == "cg" else 0)
    assert json.loads(json.dumps(report.to_dict()))["converged"] is True


def test_solver_that_runs_out_of_iterations_reports_and_returns_the_last_iterate(caplog):
    matrix = spd_system()
    rhs = np.ones((matrix.shape[0], 1))
    config = MattingConfig(rtol=1e-14, max_iter=1, ichol_threshold=0.5, solver="cg")
    with caplog.at_level("WARNING", logger="mvintrinsic.matting"):
        found, report = _solve(matrix, rhs, np.zeros_like(rhs), config, "tiny system")
    assert np.isfinite(found).all()
    residual = np.linalg.norm(matrix @ found - rhs) / np.linalg.norm(rhs)
    assert residual < 1  # one step made progress
    assert not report.converged and report.n_iter == 1
    assert report.residual == pytest.approx(residual)
    assert any("tiny system" in r.getMessage() and "1 conjugate-gradient iterations" in r.getMessage()
               for r in caplog.records)


def test_matting_compiles_nothing_and_leaves_the_process_alone():
    """No JIT (numba, pymatting) on first use, and no process-wide state changed (sys.stdout)."""
    code = (
        "import sys, json, numpy as np\n"
        "stdout = sys.stdout\n"
        "from mvintrinsic.matting import propagate, sun_visibility_matting\n"
        "rng = np.random.default_rng(0)\n"
        "image = rng.random((20, 30, 3))\n"
        "known = np.zeros((20, 30), bool); known[::4, ::4] = True\n"
        "propagate(image, rng.random((20, 30)), known)\n"
        "labels = np.where(np.arange(30) < 15, 0, 255).astype(np.uint8)[None].repeat(20, 0)\n"
        "sun_visibility_matting(image, labels)\n"
        "print(json.dumps({'stdout': sys.stdout is stdout, "
        "'jit': sorted({m.split('.')[0] for m in sys.modules} & {'numba', 'llvmlite', 'pymatting'})}))\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120)
    assert json.loads(done.stdout.strip().splitlines()[-1]) == {"stdout": True, "jit": []}


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


def test_intrinsic_layers_result_reports_every_solve():
    view, quantities, labels, clusters = synthetic_view()
    config = MattingConfig(trimap_radius=9)
    result = intrinsic_layers_result(view, quantities, labels, SUN, clusters=clusters, config=config)
    assert isinstance(result, MattingResult) and result.converged
    plain = intrinsic_layers(view, quantities, labels, SUN, clusters=clusters, config=config)
    np.testing.assert_array_equal(result.layers.reflectance, plain.reflectance)
    np.testing.assert_array_equal(result.layers.visibility, plain.visibility)
    whats = [report.what for report in result.solves]
    assert whats == ["sun visibility matting 'v'", "shading propagation 'v'", "shading propagation 'v' (band diffusion)"]
    channels = [report.channels for report in result.solves]
    assert channels == [1, 7, 7]  # v_sun; S_sky, S_ind and the cosine together
    for report in result.solves:
        assert report.solver == "direct" and report.converged and report.residual <= config.rtol
        assert 0 < report.unknowns < H * W
    # The visibility unknowns are the trimap band and cluster boundaries on the valid pixels.
    assert result.solves[0].unknowns <= quantities.valid.sum()
    assert set(result.timings) == {"laplacian", "visibility", "propagation"}


def test_one_or_two_threads_give_the_same_layers():
    """MattingConfig.threads: the matte and the propagation solved concurrently or in turn."""
    view, quantities, labels, clusters = synthetic_view()
    results = [intrinsic_layers_result(view, quantities, labels, SUN, clusters=clusters,
                                       config=MattingConfig(trimap_radius=9, threads=threads)) for threads in (1, 2)]
    for name in ("reflectance", "sky_shading", "indirect_shading", "sun_shading", "visibility"):
        np.testing.assert_array_equal(getattr(results[0].layers, name), getattr(results[1].layers, name))
    assert [r.what for r in results[0].solves] == [r.what for r in results[1].solves]
    with pytest.raises(ValueError, match="threads"):
        MattingConfig(threads=0)


def test_direct_and_conjugate_gradient_solvers_agree_on_the_layers():
    view, quantities, labels, clusters = synthetic_view()
    layers = {solver: intrinsic_layers(view, quantities, labels, SUN, clusters=clusters,
                                       config=MattingConfig(trimap_radius=9, solver=solver))
              for solver in ("direct", "cg")}
    valid = quantities.valid
    for name in ("reflectance", "sky_shading", "indirect_shading", "sun_shading", "visibility"):
        a, b = getattr(layers["direct"], name)[valid], getattr(layers["cg"], name)[valid]
        assert np.abs(a - b).max() <= TOL["solvers"] * np.abs(a).max(), name


def test_solve_failure_is_reported_not_only_logged(caplog):
    """A cg solve stopped early by max_iter shows in the layers' report, with its residual."""
    view, quantities, labels, clusters = synthetic_view()
    config = MattingConfig(trimap_radius=9, solver="cg", max_iter=1, rtol=1e-12, ichol_threshold=0.5)
    with caplog.at_level("WARNING", logger="mvintrinsic.matting"):
        result = intrinsic_layers_result(view, quantities, labels, SUN, clusters=clusters, config=config)
    assert not result.converged
    failed = [report for report in result.solves if not report.converged]
    assert failed and all(report.n_iter == 1 and report.residual > 1e-12 for report in failed)
    assert len([r for r in caplog.records if "without reaching rtol" in r.getMessage()]) == len(failed)
    assert np.isfinite(result.layers.reflectance).all()


# --------------------------------------------------------------------------------------------
# Step 1's level in the shadows (beyond the paper, MattingConfig.shadow_level)
# --------------------------------------------------------------------------------------------

def test_restore_shadow_level_keeps_the_propagated_variation_at_step1s_level():
    view, quantities, labels, _ = synthetic_view()
    shadow = (labels == 0) & quantities.valid
    assert shadow.sum() > 50 and ((labels == 255) & quantities.valid).sum() > 50
    # Step 1: S_env half as high in the shadow as in the light.
    step1_sky = np.where(shadow[..., None], 0.5 * SKY, SKY) * quantities.valid[..., None]
    quantities = dataclasses.replace(quantities, sky=step1_sky.astype(np.float32))
    # A propagation that raised the shadow's level to 0.8 of the light's, with a texture of its own.
    texture = 1.0 + 0.1 * np.sin(np.arange(W) / 2.0)[None, :, None]
    propagated = np.where(shadow[..., None], 0.8 * SKY * texture, SKY) * quantities.valid[..., None]
    indirect = np.broadcast_to(INDIRECT, (H, W, 3)) * quantities.valid[..., None]
    sky, ind = restore_shadow_level(quantities, labels, propagated, indirect, sigma=8.0)
    # Outside the shadow nothing changes.
    np.testing.assert_array_equal(sky[~shadow], propagated[~shadow])
    np.testing.assert_array_equal(ind[~shadow], indirect[~shadow])
    # Inside it the level is Step 1's: the mean of S_env over the shadow within 1% of Step 1's.
    support = shadow & ~quantities.filled
    step1_env = (step1_sky + quantities.indirect)[support].mean(axis=0)
    restored = (sky + ind)[support].mean(axis=0)
    before = (propagated + indirect)[support].mean(axis=0)
    assert np.all(np.abs(restored / step1_env - 1) < 0.01), restored / step1_env
    assert np.all(before / step1_env - 1 > 0.3)
    # The pixel-to-pixel variation is the propagation's: both terms scaled by one smooth factor.
    factor = sky[support] / propagated[support]
    np.testing.assert_allclose(factor, ind[support] / indirect[support], rtol=1e-12)
    row = 20  # a shadowed row: the texture's relative variation survives
    cols = support[row]
    assert cols.sum() > 10
    kept = sky[row, cols, 0] / propagated[row, cols, 0]
    assert np.ptp(kept) / kept.mean() < 0.04  # a fifth of the texture's 20% at most: the texture is kept


def test_shadow_level_leaves_exact_layers_exact():
    # On the exact image-model scene Step 1's S_env is the truth and the propagation keeps it,
    # so restoring its level changes nothing.
    view, quantities, labels, clusters = synthetic_view()
    config = MattingConfig(trimap_radius=9)
    plain = intrinsic_layers(view, quantities, labels, SUN, clusters=clusters, config=config)
    levelled = intrinsic_layers(view, quantities, labels, SUN, clusters=clusters,
                                config=dataclasses.replace(config, shadow_level=5.0))
    for name in ("reflectance", "sky_shading", "indirect_shading", "sun_shading", "visibility"):
        np.testing.assert_allclose(getattr(levelled, name), getattr(plain, name), rtol=1e-5, atol=1e-7, err_msg=name)
    valid = quantities.valid
    image = np.asarray(view.image)[valid]
    assert (np.abs(levelled.reconstruct()[valid] - image) / np.abs(image)).max() < TOL["invariant"]


def test_restore_shadow_level_without_shadow_is_the_identity():
    view, quantities, labels, _ = synthetic_view()
    lit = np.where(quantities.valid, 255, 128).astype(np.uint8)
    sky = np.asarray(quantities.sky, dtype=np.float64) * 1.3
    ind = np.asarray(quantities.indirect, dtype=np.float64)
    out_sky, out_ind = restore_shadow_level(quantities, lit, sky, ind, sigma=2.0)
    np.testing.assert_array_equal(out_sky, sky)
    np.testing.assert_array_equal(out_ind, ind)
