"""Step 3a (paper Sec. 6.1): cluster reflectances, the potentials of Eqs. 8-16 and the graph cut of Eq. 7.

The synthetic views are walls tiled with four materials and made with the forward model (Eq. 1),
``I = R (S_sky + S_ind + v L_sun cos)``, from known shading and a cast shadow over the left half, so
``R(0)`` of a shadowed tile and ``R(1)`` of a lit one are exactly the tile's albedo.
"""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np
import pytest

from mvintrinsic.pixels import PixelQuantities
from mvintrinsic.results import SHADOW_LABELS
from mvintrinsic.segmentation import segment
from mvintrinsic.shadow_mrf import (
    EDGE_KINDS,
    UNARY_RULES,
    ShadowConfig,
    ShadowLabels,
    ShadowMRF,
    build_mrf,
    chi2_distance,
    cluster_reflectances,
    graph_cut,
    label_shadows,
    mrf_energy,
)

TILE = 10
H, W, EDGE = 60, 120, 60  # cast shadow on columns < EDGE (a tile border: no penumbra inside a tile)
L_SUN = np.array([1.0, 0.9, 0.75])
SKY = np.array([0.22, 0.23, 0.27])
INDIRECT = np.array([0.08, 0.07, 0.05])
COSINE = 0.7
MATERIALS = np.array([[0.60, 0.50, 0.40], [0.30, 0.35, 0.50], [0.20, 0.50, 0.25], [0.70, 0.70, 0.65]])
PAINT = np.array([0.25, 0.06, 0.05])  # a dark red found nowhere else, unlike any shadowed material
ENERGY_TOLERANCE = 1e-9


def tiles(h=H, w=W):
    """(h, w, 3) albedo: a 10-px tiling of the four materials, neighbours always different."""
    rows, cols = np.indices((h, w)) // TILE
    return MATERIALS[(rows + 2 * cols) % 4]


def make_view(*, albedo=None, visibility=None, proxy_visibility=None, noise=0.005, seed=0, filled=None, sky=None):
    """Image and PixelQuantities of a wall lit by ``L_SUN`` at ``COSINE``.

    ``visibility`` is the true sun visibility used to render (default: shadow on columns < EDGE);
    ``proxy_visibility`` the ``~v`` the quantities carry (default: the true one).
    """
    albedo = tiles() if albedo is None else albedo
    h, w = albedo.shape[:2]
    if visibility is None:
        visibility = np.broadcast_to((np.arange(w) >= EDGE).astype(float), (h, w))
    proxy_visibility = visibility if proxy_visibility is None else proxy_visibility
    image = albedo * (SKY + INDIRECT + visibility[..., None] * L_SUN * COSINE)      # Eq. 1
    if noise:
        image = image * (1 + noise * np.random.default_rng(seed).standard_normal(image.shape))
    sky_mask = np.zeros((h, w), bool) if sky is None else sky
    valid = ~sky_mask
    quantities = PixelQuantities(
        stem="wall",
        sky=np.where(valid[..., None], SKY, 0.0).astype(np.float32),
        indirect=np.where(valid[..., None], INDIRECT, 0.0).astype(np.float32),
        visibility=np.asarray(proxy_visibility, np.float32),
        cosine=np.where(valid, COSINE, 0.0).astype(np.float32),
        normals=np.broadcast_to([0.0, -1.0, 0.0], (h, w, 3)).astype(np.float32),
        depth=np.full((h, w), 10.0, np.float32),
        sky_mask=sky_mask,
        filled=np.zeros((h, w), bool) if filled is None else filled,
        valid=valid,
    )
    return image.astype(np.float32), quantities


def run(image, quantities, config=None, sun=L_SUN):
    seg = segment(image, mask=quantities.valid)
    return seg, label_shadows(image, quantities, seg, sun, config=config)


def test_cluster_reflectances_are_the_albedo_under_the_right_hypothesis():
    image, q = make_view(noise=0.0)
    seg = segment(image, mask=q.valid)
    assert seg.n_segments == (H // TILE) * (W // TILE)
    r0, r1, samples, small = cluster_reflectances(image, q, seg, L_SUN)
    albedo = seg.means(tiles())
    lit = seg.means(np.broadcast_to(np.arange(W) >= EDGE, (H, W)).astype(float)) > 0.5
    np.testing.assert_allclose(r0[~lit], albedo[~lit], rtol=1e-5)   # Eq. 2, v = 0 in shadow
    np.testing.assert_allclose(r1[lit], albedo[lit], rtol=1e-5)     # Eq. 2, v = 1 in light
    ratio = (SKY + INDIRECT + L_SUN * COSINE) / (SKY + INDIRECT)
    np.testing.assert_allclose(r0[lit], albedo[lit] * ratio, rtol=1e-5)
    # 10x10 tiles minus the 3-px band keep their 4x4 interior (corner tiles keep more: the image
    # border is no boundary).
    assert samples.min() == 16 and not small.any()


def test_medians_ignore_the_boundary_band_and_pixels_without_proxy_samples():
    image, q = make_view(noise=0.0)
    seg = segment(image, mask=q.valid)
    band = seg.band(3)
    spoiled = image.copy()
    spoiled[band] *= 5.0  # outliers in the band only: the paper's reason to leave it out
    filled = np.zeros((H, W), bool)
    filled[:, :TILE] = True  # the first tile column has no proxy samples at all
    spoiled[filled] *= 3.0
    q = dataclasses.replace(q, filled=filled)
    r0, _, samples, _ = cluster_reflectances(spoiled, q, seg, L_SUN)
    clean, _, _, _ = cluster_reflectances(image, q, seg, L_SUN)
    first_column = np.unique(seg.labels[:, :TILE])
    assert np.isnan(r0[first_column]).all() and (samples[first_column] == 0).all()
    rest = np.setdiff1d(np.arange(seg.n_segments), first_column)
    np.testing.assert_allclose(r0[rest], clean[rest], rtol=1e-6)
    result = label_shadows(image, q, seg, L_SUN)
    assert (result.unary_rule[first_column] == UNARY_RULES.index("no_samples")).all()
    assert not (result.mrf.edge_kind[np.isin(result.mrf.edges, first_column).any(axis=1)] == 0).any()


def test_a_small_cluster_falls_back_to_all_its_pixels():
    image, q = make_view(noise=0.0)
    seg = segment(image, mask=q.valid)
    _, _, samples, small = cluster_reflectances(image, q, seg, L_SUN, config=ShadowConfig(min_interior=17))
    # Tiles on the image border keep more than 16 interior pixels; the inner ones fall back.
    border = np.unique(np.concatenate([seg.labels[0], seg.labels[-1], seg.labels[:, 0], seg.labels[:, -1]]))
    inner = np.setdiff1d(np.arange(seg.n_segments), border)
    np.testing.assert_array_equal(np.flatnonzero(small), inner)
    assert (samples[inner] == TILE * TILE).all()


@pytest.mark.parametrize("distance", ["euclidean", "log"])
def test_a_cast_shadow_the_proxy_misses_is_found(distance):
    """Same materials on both sides of a cast shadow: D_01 = 0 across it decides every tile (Eqs. 8-11)."""
    image, q = make_view(proxy_visibility=np.ones((H, W)))  # ~v says all lit: no shadow in the proxy
    seg, result = run(image, q, ShadowConfig(distance=distance))
    truth = np.broadcast_to(np.arange(W) >= EDGE, (H, W))
    np.testing.assert_array_equal(result.labels == SHADOW_LABELS["lit"], truth)
    np.testing.assert_array_equal(result.labels == SHADOW_LABELS["shadow"], ~truth)
    lit = seg.means(truth.astype(float)) > 0.5
    assert (result.unary_rule[~lit] == UNARY_RULES.index("shadow")).all()
    assert (result.unary_rule[lit] == UNARY_RULES.index("lit")).all()
    np.testing.assert_array_equal(result.mrf.unary[~lit], [[0.0, 1.0]] * int((~lit).sum()))  # Eq. 10 as costs
    assert result.energy == pytest.approx(result.mrf.energy(lit.astype(np.uint8)))
    assert not result.undetermined.any()  # Eq. 7 alone decides: the proxy's tie-break plays no part


def test_the_tie_break_does_not_override_the_energy():
    """A proxy that is wrong everywhere cannot flip decided clusters: the prior weighs < 0.2 in all."""
    image, q = make_view(proxy_visibility=np.broadcast_to(np.arange(W) < EDGE, (H, W)).astype(float))
    seg, result = run(image, q)
    truth = np.broadcast_to(np.arange(W) >= EDGE, (H, W))
    np.testing.assert_array_equal(result.labels == SHADOW_LABELS["lit"], truth)
    assert result.prior.sum() == pytest.approx(ShadowConfig().tie_break_weight)
    for tie_break in ("lit", "shadow"):
        _, other = run(image, q, ShadowConfig(tie_break=tie_break))
        assert result.energy == pytest.approx(other.energy, abs=ENERGY_TOLERANCE)
        np.testing.assert_array_equal(other.labels, result.labels)


def painted_view(**kwargs):
    """Cast shadow on the left; a dark red painted patch of 2 x 2 tiles (two shades) in the lit half."""
    albedo = tiles().copy()
    patch = np.zeros((H, W), bool)
    patch[20:40, 80:100] = True
    shade = np.where((np.indices((H, W)) // TILE).sum(axis=0) % 2 == 0, 1.0, 0.85)
    albedo[patch] = PAINT * shade[patch][:, None]
    image, q = make_view(albedo=albedo, **kwargs)
    return image, q, patch


def test_a_painted_dark_patch_without_proxy_shadow_stays_lit():
    """No shadowed material matches the paint, so nothing ties it to the shadow: Eq. 7 leaves it
    open (equal unaries, its reflectance partners are its own tiles, its neighbours' colours differ)
    and the tie-break toward the proxy, which sees no shadow there, keeps it lit."""
    image, q, patch = painted_view()
    seg, result = run(image, q)
    truth = np.broadcast_to(np.arange(W) >= EDGE, (H, W))
    np.testing.assert_array_equal(result.labels == SHADOW_LABELS["lit"], truth)
    painted = np.unique(seg.labels[patch])
    assert len(painted) == 4
    assert (result.unary_rule[painted] == UNARY_RULES.index("equal")).all()
    np.testing.assert_array_equal(np.flatnonzero(result.undetermined), painted)
    np.testing.assert_array_equal(result.undetermined_pixels(seg), patch)
    # Labelling the paint shadow costs the same (Eq. 7 does not decide), and so does the
    # tie-break toward shadow, which does label it shadow.
    flipped = result.cluster_labels.copy()
    flipped[painted] = 0
    assert result.mrf.energy(flipped) == pytest.approx(result.energy, abs=ENERGY_TOLERANCE)
    _, darkest = run(image, q, ShadowConfig(tie_break="shadow"))
    assert (darkest.labels[patch] == SHADOW_LABELS["shadow"]).all()
    assert darkest.energy == pytest.approx(result.energy, abs=ENERGY_TOLERANCE)


def test_the_graph_cut_beats_all_lit_and_random_labellings():
    image, q, _ = painted_view(noise=0.02, seed=4)
    seg, result = run(image, q)
    energy = result.mrf.energy
    assert result.energy == pytest.approx(energy(result.cluster_labels))
    assert result.energy < energy(np.ones(seg.n_segments, np.uint8))
    assert result.energy < energy(np.zeros(seg.n_segments, np.uint8))
    rng = np.random.default_rng(0)
    for _ in range(50):
        assert result.energy <= energy(rng.integers(0, 2, seg.n_segments)) + ENERGY_TOLERANCE
    # and every single-cluster flip of the solution
    for s in range(seg.n_segments):
        flipped = result.cluster_labels.copy()
        flipped[s] ^= 1
        assert result.energy <= energy(flipped) + ENERGY_TOLERANCE


def brute_force(mrf):
    best = np.inf
    for labels in itertools.product((0, 1), repeat=mrf.n_clusters):
        best = min(best, mrf.energy(np.array(labels)))
    return best


def test_graph_cut_equals_brute_force_on_a_twelve_cluster_view():
    albedo = tiles(30, 40)  # 3 x 4 tiles: 12 clusters
    visibility = np.broadcast_to((np.arange(40) >= 20).astype(float), (30, 40))
    image, q = make_view(albedo=albedo, visibility=visibility, proxy_visibility=np.ones((30, 40)), noise=0.0)
    seg, result = run(image, q, ShadowConfig(k=2))
    assert seg.n_segments == 12 and len(result.mrf.edges) > 12
    assert result.energy == pytest.approx(brute_force(result.mrf), abs=ENERGY_TOLERANCE)


@pytest.mark.parametrize("seed", range(5))
def test_graph_cut_equals_brute_force_on_random_submodular_energies(seed):
    rng = np.random.default_rng(seed)
    n = 10
    edges = np.array([(s, t) for s in range(n) for t in range(s + 1, n) if rng.random() < 0.4])
    # Random tables made submodular: theta(0,1) + theta(1,0) >= theta(0,0) + theta(1,1).
    pairwise = rng.uniform(-1, 1, (len(edges), 4))
    excess = pairwise[:, 0] + pairwise[:, 3] - pairwise[:, 1] - pairwise[:, 2]
    pairwise[:, 1] += np.maximum(excess, 0) + rng.uniform(0, 0.5, len(edges))
    mrf = ShadowMRF(unary=rng.uniform(-1, 2, (n, 2)), edges=edges, pairwise=pairwise,
                    edge_kind=np.zeros(len(edges), np.int8))
    labels, value = graph_cut(mrf)
    assert mrf.energy(labels) == pytest.approx(value, abs=1e-9)
    assert value == pytest.approx(brute_force(mrf), abs=1e-9)


def test_a_non_submodular_term_is_refused():
    mrf = ShadowMRF(unary=np.zeros((2, 2)), edges=[[0, 1]], pairwise=[[1.0, 0.0, 0.0, 1.0]], edge_kind=[0])
    assert mrf.n_nonsubmodular == 1
    with pytest.raises(ValueError, match="not submodular"):
        graph_cut(mrf)


def test_pairwise_terms_follow_eqs_14_to_16():
    config = ShadowConfig()
    r = np.array([[0.5, 0.4, 0.3], [0.5, 0.4, 0.3], [0.1, 0.6, 0.2], [0.1, 0.6, 0.2]])
    adjacency = np.array([[0, 2], [1, 3], [2, 3]])
    mrf, rule, _ = build_mrf(r, r * 3, np.zeros((4, 2)), adjacency, np.array([0.01, 0.5, 0.04]), radius=1.0,
                             config=dataclasses.replace(config, k=1))
    kinds = [EDGE_KINDS[i] for i in mrf.edge_kind]
    tables = {(tuple(e), kind): tuple(p) for e, kind, p in zip(mrf.edges.tolist(), kinds, mrf.pairwise, strict=True)}
    assert tables[((0, 1), "reflectance")] == (0.0, 1.0, 1.0, 0.0)          # Eq. 14
    assert tables[((2, 3), "reflectance")] == (0.0, 1.0, 1.0, 0.0)
    assert tables[((0, 2), "similar_colours")] == (0.2, 0.8, 0.8, 0.2)      # Eq. 15
    assert tables[((2, 3), "similar_colours")] == (0.2, 0.8, 0.8, 0.2)
    assert tables[((1, 3), "different_colours")] == (0.5, 0.5, 0.5, 0.5)    # Eq. 16
    assert mrf.n_nonsubmodular == 0
    # R(1) = 3 R(0) everywhere: no cluster pair explains a shadow/light pair better than the other.
    assert (rule == UNARY_RULES.index("equal")).all() and (mrf.unary == 0.5).all()   # Eq. 13


def test_local_search_decides_when_the_global_partners_do_not():
    """Eq. 12: an ambiguous global hypothesis, made confident by the local partners."""
    a = np.array([0.5, 0.4, 0.3])
    norm = np.linalg.norm(a)
    # Cluster 0 in shadow (R(0) = a, R(1) = a / 3); cluster 1 next to it, lit, a near match
    # (D_01 = 0.1 |a|); cluster 2 far away, a darker material in shadow that fakes the light
    # hypothesis (D_10 = |a / 3 - a / 2| = |a| / 6).
    r0 = np.array([a, 3.3 * a, a / 2])
    r1 = np.array([a / 3, 1.1 * a, a / 6])
    centroids = np.array([[0.0, 0.0], [0.0, 10.0], [0.0, 500.0]])
    config = ShadowConfig(k=1, distance="euclidean")
    h0, h1 = 0.1 * norm, norm / 6                                   # Eqs. 8-9
    assert config.tau_1 < h0 / (h0 + h1) < 1 - config.tau_1        # neither Eq. 10 nor Eq. 11
    h0_local, h1_local = 0.1 * norm, np.linalg.norm(a / 3 - 3.3 * a)
    assert (h0 + h0_local) / (h0 + h1 + h0_local + h1_local) < config.tau_1   # Eq. 12
    no_edges = (np.zeros((0, 2)), np.zeros(0))
    mrf, rule, _ = build_mrf(r0, r1, centroids, *no_edges, radius=0.0, config=config)
    assert UNARY_RULES[rule[0]] == "equal" and (mrf.unary[0] == config.l_eq).all()   # Eq. 13
    mrf, rule, _ = build_mrf(r0, r1, centroids, *no_edges, radius=50.0, config=config)
    assert UNARY_RULES[rule[0]] == "local_shadow"
    np.testing.assert_array_equal(mrf.unary[0], [config.l_0, config.l_1])


def test_chi2_distance_bounds():
    p = np.zeros((3, 4))
    p[:, 0] = 1
    q = np.zeros((3, 4))
    q[:, 3] = 1
    assert chi2_distance(p, p) == 0.0
    assert chi2_distance(p, q) == pytest.approx(1.0)
    half = np.full((3, 4), 0.25)
    assert 0 < chi2_distance(p, half) < 1


def test_sky_and_invalid_pixels_are_undecided():
    sky = np.zeros((H, W), bool)
    sky[:10] = True
    image, q = make_view(sky=sky)
    _, result = run(image, q)
    assert (result.labels[sky] == SHADOW_LABELS["undecided"]).all()
    assert set(np.unique(result.labels[~sky])) <= {SHADOW_LABELS["shadow"], SHADOW_LABELS["lit"]}
    assert isinstance(result, ShadowLabels) and "ShadowLabels('wall'" in repr(result)
    assert set(result.timings) == {"reflectance", "unary", "pairwise", "graph_cut", "labels"}
    assert result.counts["lit_clusters"] + result.counts["shadow_clusters"] == result.n_clusters
    assert sum(result.counts[name] for name in UNARY_RULES) == result.n_clusters
    assert sum(result.counts[f"{kind}_edges"] for kind in EDGE_KINDS) == len(result.mrf.edges)
    assert not result.labels.flags.writeable


def test_mrf_energy_checks_its_labels():
    mrf = ShadowMRF(unary=np.zeros((3, 2)), edges=np.zeros((0, 2)), pairwise=np.zeros((0, 4)),
                    edge_kind=np.zeros(0))
    assert mrf_energy(mrf, np.array([True, False, True])) == 0.0
    with pytest.raises(ValueError, match="labels must have shape"):
        mrf.energy(np.zeros(2))
    with pytest.raises(ValueError, match="only 0"):
        mrf.energy(np.array([0, 2, 1]))
    with pytest.raises(ValueError, match="edges must join two different clusters"):
        ShadowMRF(unary=np.zeros((3, 2)), edges=[[0, 3]], pairwise=np.zeros((1, 4)), edge_kind=[0])


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("k", 0, "k must be an integer >= 1"),
        ("k", 2.0, "k must be an integer"),
        ("tau_1", 0.5, "tau_1 must lie in"),
        ("tau_1", 0.0, "tau_1 must lie in"),
        ("tau_c", 0.0, "tau_c must lie in"),
        ("l_0", 2.0, "l_0 must be <= l_1"),
        ("l_np", 0.9, "l_np must be <= l_p"),
        ("l_eq", float("nan"), "l_eq must be a finite number"),
        ("histogram_bins", 1, "histogram_bins must be an integer >= 2"),
        ("boundary_band", -1, "boundary_band must be an integer >= 0"),
        ("min_interior", 0, "min_interior must be an integer >= 1"),
        ("local_radius", -0.1, "local_radius must be"),
        ("tie_break", "none", "tie_break must be one of"),
        ("tie_break_weight", 0.0, "tie_break_weight must be a positive"),
        ("distance", "manhattan", "distance must be one of"),
    ],
)
def test_config_validation_names_the_field(field, value, message):
    with pytest.raises(ValueError, match=message):
        ShadowConfig(**{field: value})


def test_label_shadows_validates_its_arguments():
    image, q = make_view()
    seg = segment(image, mask=q.valid)
    with pytest.raises(ValueError, match="image must have shape"):
        label_shadows(image[:-1], q, seg, L_SUN)
    with pytest.raises(ValueError, match="sun_radiance must be non-negative"):
        label_shadows(image, q, seg, -L_SUN)
    with pytest.raises(ValueError, match="sun_radiance must have shape"):
        label_shadows(image, q, seg, L_SUN[:2])
    with pytest.raises(TypeError, match="config must be a ShadowConfig"):
        label_shadows(image, q, seg, L_SUN, config={"k": 3})
    with pytest.raises(TypeError, match="segmentation must be a Segmentation"):
        label_shadows(image, q, seg.labels, L_SUN)
    small = segment(image[:30], mask=q.valid[:30])
    with pytest.raises(ValueError, match="segmentation must have shape"):
        label_shadows(image, q, small, L_SUN)


def test_defaults_are_the_papers():
    config = ShadowConfig()
    assert (config.tau_1, config.l_1, config.l_0, config.l_p, config.l_np, config.l_eq, config.tau_c,
            config.boundary_band) == (0.1, 1.0, 0.0, 0.8, 0.2, 0.5, 0.05, 3)


def test_a_view_without_valid_pixels_gives_an_empty_labelling():
    sky = np.ones((H, W), bool)
    image, q = make_view(sky=sky)
    image[sky] = np.nan  # never read
    seg, result = run(image, q)
    assert seg.n_segments == 0 and result.n_clusters == 0 and result.energy == 0.0
    assert (result.labels == SHADOW_LABELS["undecided"]).all()
