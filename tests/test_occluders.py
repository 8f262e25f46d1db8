"""The occluders the proxy lost, carved from shadows and photos (mvintrinsic.occluders).

Exact case: a ground plane is the proxy; a slab floating above it (a tree crown the MVS lost) is
missing from it but casts its shadow and is seen by four cameras. Then the demo scene, where the
proxy lost the tree: the umbra's ``S_env`` and ``L_sun`` move toward the truth.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from conftest import look_at

from mvintrinsic import Proxy
from mvintrinsic.camera import Camera
from mvintrinsic.model_choice import choose_occluders
from mvintrinsic.occluders import (
    OccluderConfig,
    Occluders,
    carve_occluders,
    seen_occluders,
    smooth_occluder_reflectance,
    unexplained_shadow_share,
)
from mvintrinsic.pixels import PixelQuantities
from mvintrinsic.raytrace import Tracer
from mvintrinsic.results import SHADOW_LABELS, IntrinsicLayers
from mvintrinsic.scene import View

W, H = 128, 96
SLAB_LOW, SLAB_HIGH = np.array([-0.8, -0.8, 2.5]), np.array([0.8, 0.8, 3.1])
SUN = np.array([np.cos(np.radians(50)) * np.cos(np.radians(150)), np.cos(np.radians(50)) * np.sin(np.radians(150)),
                np.sin(np.radians(50))])
LIT, DARK, SLAB, SKY = 0.5, 0.15, 0.05, np.array([0.5, 0.6, 0.9])
SHADOW_IOU_DEFAULT = 0.7  # the voxels' shadow on the ground against the slab's, 0.5 m voxels (the default;
# measured 0.74)
SHADOW_IOU = 0.75  # the same with 0.25 m voxels (measured 0.80:
# whole voxels over the slab's edges widen it by about half a voxel; the slab's shadow is inside it)
SHADOW_IOU_FINE = 0.85  # the same with 0.1 m voxels (measured 0.91)
RECALL = 0.95  # share of the slab's shadow the voxels' shadow covers (measured 1.0, 1.0 and 0.997)
INSIDE = 0.8  # share of the voxels within one voxel of the slab (measured 1.0, 0.95 and 0.87)
SEEN_IOU = 0.7  # the pixels that see a voxel against those that see the slab, 0.5 m voxels (measured 0.73
# in every view: whole voxels over the slab widen its outline)


def _mesh(low, high, subdivisions=0):
    import open3d as o3d

    box = o3d.geometry.TriangleMesh.create_box(*(high - low)).translate(low)
    return box.subdivide_midpoint(subdivisions) if subdivisions else box


def _proxy(mesh) -> Proxy:
    mesh.compute_vertex_normals()
    return Proxy(np.asarray(mesh.vertices), np.asarray(mesh.vertex_normals), np.asarray(mesh.triangles))


def _ground():
    return _mesh(np.array([-6.0, -6.0, -0.01]), np.array([6.0, 6.0, 0.0]), subdivisions=5)


@pytest.fixture(scope="module")
def world():
    """The proxy (ground only), its tracer, the exact tracer (ground and slab) and four views."""
    proxy_tracer = Tracer(_proxy(_ground()))
    exact = Tracer(_proxy(_ground() + _mesh(SLAB_LOW, SLAB_HIGH)))
    vertices = proxy_tracer.proxy.vertices
    in_shadow = exact.occluded(vertices + [0, 0, 1e-3], np.broadcast_to(SUN, vertices.shape))
    radiance = np.where(in_shadow[:, None], DARK, LIT) * np.ones((1, 3))
    views, quantities, layers = [], {}, {}
    for k, (x, y) in enumerate([(6.0, 5.0), (-6.0, 5.0), (6.0, -5.0), (-6.0, -5.0)]):
        rotation, translation = look_at(np.array([x, y, 2.0]), np.array([0.0, 0.0, 1.2]))
        camera = Camera("PINHOLE", W, H, [0.7 * W, 0.7 * W, W / 2, H / 2], rotation, translation)
        stem = f"v{k}"
        rays = camera.pixel_rays()
        seen = proxy_tracer.intersect(camera.center, rays)
        truth = exact.intersect(camera.center, rays)
        on_slab = (truth.hit & (truth.points[:, 2] > 1.0)).reshape(H, W)
        ground = seen.hit.reshape(H, W) & ~on_slab
        points = seen.points.reshape(H, W, 3)
        shadow = ground & exact.occluded(points.reshape(-1, 3) + [0, 0, 1e-3],
                                         np.broadcast_to(SUN, (H * W, 3))).reshape(H, W)
        sky = ~seen.hit.reshape(H, W) & ~on_slab
        image = np.where(sky[..., None], SKY, np.where(on_slab[..., None], SLAB, np.where(shadow, DARK, LIT)[..., None]))
        valid = ~sky
        zeros = np.zeros((H, W, 3), np.float32)
        quantities[stem] = PixelQuantities(
            stem=stem, sky=zeros, indirect=zeros, visibility=np.ones((H, W), np.float32),
            cosine=np.where(seen.hit.reshape(H, W), SUN[2], 0.0).astype(np.float32),
            normals=np.where(seen.hit.reshape(H, W, 1), [0.0, 0.0, 1.0], 0.0).astype(np.float32),
            depth=np.where(seen.hit, seen.t, np.inf).reshape(H, W).astype(np.float32),
            sky_mask=sky, filled=valid & ~seen.hit.reshape(H, W), valid=valid)
        labels = np.where(shadow, SHADOW_LABELS["shadow"], np.where(ground, SHADOW_LABELS["lit"],
                                                                    SHADOW_LABELS["undecided"])).astype(np.uint8)
        layers[stem] = IntrinsicLayers(stem, reflectance=zeros, sun_shading=zeros, sky_shading=zeros,
                                       indirect_shading=zeros, visibility=(ground & ~shadow).astype(np.float32),
                                       shadow_labels=labels)
        views.append(View(stem, image.astype(np.float32), camera))
    return proxy_tracer, exact, radiance, views, quantities, layers


def _shadow_of(occluders: Occluders, points: np.ndarray) -> np.ndarray:
    vertices, triangles = occluders.mesh()
    tracer = Tracer(Proxy(vertices, np.tile([0.0, 0.0, 1.0], (len(vertices), 1)), triangles))
    return tracer.occluded(points + [0, 0, 1e-3], np.broadcast_to(SUN, points.shape))


@pytest.mark.parametrize(("voxel", "min_iou"), [(0.5, SHADOW_IOU_DEFAULT), (0.25, SHADOW_IOU), (0.1, SHADOW_IOU_FINE)])
def test_the_lost_slab_is_carved_where_it_stands(world, voxel, min_iou):
    proxy_tracer, exact, radiance, views, quantities, layers = world
    occluders = carve_occluders(views, quantities, layers, radiance, proxy_tracer, SUN,
                                config=OccluderConfig(voxel=voxel))
    assert len(occluders) > 0
    size = occluders.size
    inside = ((occluders.centres >= SLAB_LOW - size) & (occluders.centres <= SLAB_HIGH + size)).all(axis=1)
    assert inside.mean() >= INSIDE
    # the voxels shade the ground as the slab does
    grid = np.stack(np.meshgrid(np.linspace(-4, 4, 81), np.linspace(-4, 4, 81)), -1).reshape(-1, 2)
    points = np.column_stack([grid, np.zeros(len(grid))])
    truth = exact.occluded(points + [0, 0, 1e-3], np.broadcast_to(SUN, points.shape))
    ours = _shadow_of(occluders, points)
    assert (truth & ours).sum() / (truth | ours).sum() >= min_iou
    assert (truth & ours).sum() / truth.sum() >= RECALL
    assert occluders.counts["shadow"] > 0 and occluders.counts["free"] > 0
    assert not occluders.centres.flags.writeable
    assert occluders.radiance.shape == (len(occluders), 3) and not occluders.radiance.any()  # "zero"


def test_observed_radiance_is_the_slabs_colour(world):
    proxy_tracer, _, radiance, views, quantities, layers = world
    occluders = carve_occluders(views, quantities, layers, radiance, proxy_tracer, SUN,
                                config=OccluderConfig(radiance="observed"))
    np.testing.assert_allclose(np.median(occluders.radiance, axis=0), SLAB, rtol=1e-5)


def test_no_shadow_no_occluder(world):
    proxy_tracer, _, radiance, views, quantities, layers = world
    lit = {s: IntrinsicLayers(s, reflectance=layer.reflectance, sun_shading=layer.sun_shading,
                              sky_shading=layer.sky_shading, indirect_shading=layer.indirect_shading,
                              visibility=np.ones(layer.shape, np.float32),
                              shadow_labels=np.where(layer.shadow_labels == 0, 255, layer.shadow_labels).astype(np.uint8))
           for s, layer in layers.items()}
    assert len(carve_occluders(views, quantities, lit, radiance, proxy_tracer, SUN)) == 0


def test_carving_is_chosen_where_the_proxy_cannot_cast_the_shadow(world):
    _, _, _, _, quantities, layers = world
    assert unexplained_shadow_share(quantities, layers) == 1.0  # the proxy is the ground alone
    assert choose_occluders(quantities, layers, OccluderConfig()).choice == "carve"
    # a proxy that casts the labelled shadows: ~v = 0 there
    cast = {s: replace(q, visibility=np.where(layers[s].shadow_labels == SHADOW_LABELS["shadow"], 0.0,
                                              q.visibility).astype(np.float32)) for s, q in quantities.items()}
    assert unexplained_shadow_share(cast, layers) == 0.0
    choice = choose_occluders(cast, layers, OccluderConfig())
    assert choice.choice == "skip" and choice.measures["unexplained_share"] == 0.0
    assert choose_occluders(cast, layers, OccluderConfig(when="always")).choice == "carve"


def test_mesh_is_closed_cubes():
    occluders = Occluders(centres=np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]]), size=0.5, radiance=np.zeros((2, 3)))
    vertices, triangles = occluders.mesh()
    assert vertices.shape == (16, 3) and triangles.shape == (24, 3)
    np.testing.assert_allclose(vertices[:8].min(axis=0), [-0.25, -0.25, -0.25])
    np.testing.assert_allclose(vertices[8:].max(axis=0), [2.25, 0.25, 0.25])
    edges = np.sort(np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert (counts == 2).all()  # every edge shared by two triangles: closed


def test_the_pixels_that_see_the_slab_are_found(world):
    proxy_tracer, exact, radiance, views, quantities, layers = world
    occluders = carve_occluders(views, quantities, layers, radiance, proxy_tracer, SUN)
    seen = seen_occluders(views, quantities, occluders)
    for view in views:
        truth = exact.intersect(view.camera.center, view.camera.pixel_rays())
        on_slab = (truth.hit & (truth.points[:, 2] > 1.0)).reshape(H, W)
        ours = seen[view.stem]
        assert ours.shape == (H, W) and ours.dtype == bool
        assert (ours & on_slab).sum() / (ours | on_slab).sum() >= SEEN_IOU
    empty = Occluders(centres=np.zeros((0, 3)), size=0.5, radiance=np.zeros((0, 3)))
    assert not any(m.any() for m in seen_occluders(views, quantities, empty).values())
    with pytest.raises(ValueError, match="quantities"):
        seen_occluders(views, {}, occluders)


def test_shadowed_pixels_that_see_an_occluder_get_a_smooth_reflectance():
    """A leafy crown: one green material under shading that varies from leaf to leaf."""
    rng = np.random.default_rng(0)
    h, w = 40, 60
    seen = np.zeros((h, w), bool)
    seen[5:35, 10:50] = True
    labels = np.full((h, w), SHADOW_LABELS["lit"], np.uint8)
    labels[:, :30] = SHADOW_LABELS["shadow"]
    green = np.array([0.1, 0.3, 0.05], np.float32)
    leaf_shading = rng.uniform(0.2, 1.0, (h, w, 1)).astype(np.float32)
    # the model's layers: the leaf-to-leaf shading wrongly in the reflectance, flat shading
    reflectance = np.broadcast_to(green, (h, w, 3)) * leaf_shading
    flat = np.full((h, w, 3), 0.5, np.float32)
    layers = IntrinsicLayers("v", reflectance=reflectance.astype(np.float32), sun_shading=flat,
                             sky_shading=0.3 * flat, indirect_shading=0.1 * flat,
                             visibility=(labels == SHADOW_LABELS["lit"]).astype(np.float32), shadow_labels=labels)
    out = smooth_occluder_reflectance(layers, seen, sigma=5.0)
    region = seen & (labels == SHADOW_LABELS["shadow"])
    # the image is kept (Eq. 1), the labels and v_sun too
    np.testing.assert_allclose(out.reconstruct(), layers.reconstruct(), rtol=1e-5)
    np.testing.assert_array_equal(out.shadow_labels, labels)
    np.testing.assert_array_equal(out.visibility, layers.visibility)
    # outside the region nothing moves
    np.testing.assert_array_equal(out.reflectance[~region], layers.reflectance[~region])
    np.testing.assert_array_equal(out.sky_shading[~region], layers.sky_shading[~region])
    # inside, the reflectance is the material's colour up to a smooth factor: its chromaticity is
    # green's, and its pixel-to-pixel variation falls by more than 5x
    chroma = out.reflectance[region] / out.reflectance[region].sum(axis=1, keepdims=True)
    np.testing.assert_allclose(chroma, np.broadcast_to(green / green.sum(), chroma.shape), rtol=1e-4)
    before = np.std(np.log(layers.reflectance[region][:, 1]))
    after = np.std(np.log(out.reflectance[region][:, 1]))
    assert after < before / 20  # measured 34x lower
    # no pixel in the region: the layers themselves
    assert smooth_occluder_reflectance(layers, np.zeros((h, w), bool), sigma=5.0) is layers


@pytest.mark.parametrize(("kwargs", "match"), [({"seen": np.ones((3, 3), bool)}, "seen"),
                                               ({"seen": np.ones((40, 60))}, "seen"),
                                               ({"sigma": 0.0}, "sigma"), ({"sigma": np.nan}, "sigma")])
def test_smoothing_errors_name_the_argument(kwargs, match):
    zeros = np.zeros((40, 60, 3), np.float32)
    layers = IntrinsicLayers("v", reflectance=zeros, sun_shading=zeros, sky_shading=zeros, indirect_shading=zeros,
                             visibility=np.zeros((40, 60), np.float32),
                             shadow_labels=np.zeros((40, 60), np.uint8))
    arguments = {"seen": np.zeros((40, 60), bool), "sigma": 2.0, **kwargs}
    with pytest.raises(ValueError, match=match):
        smooth_occluder_reflectance(layers, arguments.pop("seen"), **arguments)
    with pytest.raises(TypeError, match="layers"):
        smooth_occluder_reflectance(zeros, np.zeros((40, 60), bool), sigma=2.0)


def test_mismatched_inputs_name_the_argument(world):
    proxy_tracer, _, radiance, views, quantities, layers = world
    with pytest.raises(ValueError, match="quantities and layers"):
        carve_occluders(views, {}, layers, radiance, proxy_tracer, SUN)


@pytest.mark.parametrize(("field", "value"), [("voxel", 0.0), ("voxel", np.inf), ("shadow_share", 1.0),
                                              ("camera_share", 0.0), ("min_shadow_rays", 0), ("radiance", "mean"),
                                              ("margin", -1.0), ("max_voxels", 2.5),
                                              ("when", "never"), ("min_unexplained", 1.5),
                                              ("reflectance_smoothing", 0.0), ("reflectance_smoothing", 1.0)])
def test_config_errors_name_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        OccluderConfig(**{field: value})


def test_grid_counts_each_ray_once_per_voxel_it_crosses():
    """The batched count against a plain reference: every sample of every ray, whole length."""
    from mvintrinsic.occluders import _Grid

    grid = _Grid(np.array([-1.0, -2.0, 0.0]), np.array([3.0, 2.0, 1.5]), 0.25, 10**6)
    gen = np.random.default_rng(0)
    origins = gen.uniform([-1.5, -2.5, -0.5], [3.5, 2.5, 2.0], (500, 3))  # some outside the grid
    directions = gen.normal(size=(500, 3))
    directions[:50, 2] = 0.0  # parallel to a face
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    end = gen.uniform(0.5, 8.0, 500)
    end[:100] = np.inf
    got = grid.count(origins, directions, 0.1, end, chunk=64)
    expected = np.zeros(grid.size)
    step = 0.5 * grid.voxel
    for o, d, e in zip(origins, directions, end, strict=True):
        t = 0.1 + (np.arange(int(grid._span / step) + 1) + 0.5) * step
        ijk = np.floor((o + t[t < e, None] * d - grid.low) / grid.voxel).astype(int)
        ijk = ijk[((ijk >= 0) & (ijk < grid.dims)).all(axis=1)]
        flat = np.ravel_multi_index(ijk.T, grid.dims)
        keep = np.ones(len(flat), bool)
        keep[1:] = flat[1:] != flat[:-1]
        np.add.at(expected, flat[keep], 1.0)
    np.testing.assert_array_equal(got, expected)
    assert expected.sum() > 1000
