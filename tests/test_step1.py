"""Step 1 (paper Sec. 4): hemisphere sampling, analytic shading cases, exact shadow footprints,
vertex radiance, rasterisation, and the end-to-end accuracy on the demo scene."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mvintrinsic import Camera, Proxy, Scene, View
from mvintrinsic.env_shading import (
    Step1Config,
    environment_shading,
    fill_unseen,
    ray_radiance,
    step1,
    vertex_radiance,
)
from mvintrinsic.environment import EnvironmentMap
from mvintrinsic.raytrace import (
    Tracer,
    cosine_hemisphere,
    interpolate_points,
    morton_order,
    rasterize,
    smooth_normals,
    subdivide,
    sun_visibility,
    vertex_normals,
    voxel_subsample,
)

MC_RAYS = 4096  # rays per point in the analytic Monte Carlo tests
MC_TOL = 0.02  # relative; stratified sampling with 4096 rays is well inside this
CLEAN_PROXY_ENV_ERROR_MAX = 0.25  # issue 4: median relative S_env error in GT shadow, clean proxy
CLEAN_PROXY_BER_MAX = 0.12  # ~v vs gt/sun_visibility with the exact geometry (measured 0.09 at 20 cm edges)


def mesh_proxy(vertices, triangles):
    vertices = np.asarray(vertices, float)
    triangles = np.asarray(triangles)
    a, b, c = (vertices[triangles[:, i]] for i in range(3))
    face = np.cross(b - a, c - a)
    normals = np.zeros_like(vertices)
    for i in range(3):
        np.add.at(normals, triangles[:, i], face)
    return Proxy(vertices, normals / np.linalg.norm(normals, axis=1, keepdims=True), triangles)


def quad(corners):
    return np.asarray(corners, float), np.array([[0, 1, 2], [0, 2, 3]])


def merge(*parts):
    vertices, triangles, offset = [], [], 0
    for v, t in parts:
        vertices.append(v)
        triangles.append(t + offset)
        offset += len(v)
    return np.concatenate(vertices), np.concatenate(triangles)


def ground(size=100.0):
    return quad([[-size, -size, 0], [size, -size, 0], [size, size, 0], [-size, size, 0]])


def uniform_sky(radiance, height=32):
    rgb = np.broadcast_to(np.asarray(radiance, np.float32), (height, 2 * height, 3))
    up = np.array([0.0, 0.0, 1.0])
    sky = np.zeros((height, 2 * height), bool)
    sky[: height // 2] = True
    return EnvironmentMap(radiance=np.ascontiguousarray(rgb), sky=sky, observed=np.ones_like(sky), up=up,
                          horizon_normal=up)


# -- sampling ------------------------------------------------------------------------------------
@pytest.mark.parametrize("n_rays", [64, 50])
def test_cosine_hemisphere_is_cosine_distributed(n_rays):
    rng = np.random.default_rng(0)
    normals = rng.normal(size=(300, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    d = cosine_hemisphere(normals, n_rays, rng=1)
    assert d.shape == (300, n_rays, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=2), 1.0, atol=1e-12)
    cos = np.einsum("pj,prj->pr", normals, d)
    assert cos.min() >= 0
    # Under pdf cos/pi: E[cos] = 2/3 and E[cos^2] = 1/2.
    assert cos.mean() == pytest.approx(2 / 3, abs=0.003)
    assert (cos**2).mean() == pytest.approx(1 / 2, abs=0.003)


def test_morton_order_and_voxel_subsample():
    rng = np.random.default_rng(0)
    points = rng.uniform(0, 10, (5000, 3))
    order = morton_order(points)
    assert sorted(order.tolist()) == list(range(5000))
    # consecutive points in Morton order are much closer than random pairs
    step = np.linalg.norm(np.diff(points[order], axis=0), axis=1)
    assert np.median(step) < 0.3 * np.median(np.linalg.norm(np.diff(points, axis=0), axis=1))
    idx = voxel_subsample(points, 1.0)
    cells = np.floor(points / 1.0)
    assert len(idx) == len(np.unique(cells, axis=0))
    assert len(np.unique(cells[idx], axis=0)) == len(idx)


# -- analytic shading ----------------------------------------------------------------------------
def test_open_plane_under_uniform_sky_gets_exactly_its_radiance():
    """Units: an unoccluded horizontal plane under a uniform sky of radiance L has S_sky = L."""
    tracer = Tracer(mesh_proxy(*ground()))
    L = np.array([0.3, 0.5, 0.9])
    points = np.array([[0.0, 0.0, 0.0], [3.0, -2.0, 0.0]])
    normals = np.tile([0.0, 0.0, 1.0], (2, 1))
    sky, ind = environment_shading(points, normals, tracer, uniform_sky(L), np.zeros((4, 3)), n_rays=256, rng=0)
    np.testing.assert_allclose(sky, np.tile(L, (2, 1)), rtol=1e-6)  # every ray sees sky: no MC error
    np.testing.assert_array_equal(ind, 0)


@pytest.mark.parametrize("attenuation", [True, False])
def test_point_at_the_foot_of_a_wall(attenuation):
    """A tall, long wall blocks half the (cosine-weighted) hemisphere of a ground point at its foot.

    S_sky = L / 2. The wall, of radiance W, gives S_ind = W / 2 without attenuation and
    W * E[cos_wall ; wall side] = W * 2 / (3 pi) with the paper's attenuation factor.
    """
    wall = quad([[0.01, -500, -1], [0.01, 500, -1], [0.01, 500, 200], [0.01, -500, 200]])
    tracer = Tracer(mesh_proxy(*merge(wall)))
    L, W = np.array([0.2, 0.4, 0.8]), np.array([0.6, 0.5, 0.4])
    radiance = np.tile(W, (4, 1))
    points, normals = np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]])
    sky, ind = environment_shading(points, normals, tracer, uniform_sky(L), radiance, n_rays=MC_RAYS,
                                   ray_offset=0.0, attenuation=attenuation, rng=0)
    np.testing.assert_allclose(sky[0], L / 2, rtol=MC_TOL)
    expected = W * (2 / (3 * math.pi) if attenuation else 0.5)
    np.testing.assert_allclose(ind[0], expected, rtol=MC_TOL)


def test_attenuation_only_on_unseen_radiance():
    """``attenuation="unseen"`` scales only the radiance no view saw.

    The wall at the foot of the point is split at y = 0 into two quads that share no vertex:
    the y < 0 half is seen (radiance W), the y > 0 half unseen (NaN, filled with W from its
    nearest seen vertex). Each half takes half of the wall's rays, so S_ind = W / 4 (seen,
    unattenuated) + W / (3 pi) (unseen, attenuated); with every vertex seen it is W / 2, the
    value without attenuation.
    """
    left = quad([[0.01, -500, -1], [0.01, 0, -1], [0.01, 0, 200], [0.01, -500, 200]])
    right = quad([[0.01, 0, -1], [0.01, 500, -1], [0.01, 500, 200], [0.01, 0, 200]])
    tracer = Tracer(mesh_proxy(*merge(left, right)))
    L, W = np.array([0.2, 0.4, 0.8]), np.array([0.6, 0.5, 0.4])
    radiance = np.tile(W, (8, 1))
    points, normals = np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]])
    kwargs = dict(n_rays=MC_RAYS, ray_offset=0.0, attenuation="unseen", rng=0)
    _, ind = environment_shading(points, normals, tracer, uniform_sky(L), radiance, **kwargs)
    np.testing.assert_allclose(ind[0], W / 2, rtol=MC_TOL)
    radiance[4:] = np.nan
    _, ind = environment_shading(points, normals, tracer, uniform_sky(L), radiance, **kwargs)
    np.testing.assert_allclose(ind[0], W / 4 + W / (3 * math.pi), rtol=MC_TOL)


def test_ray_radiance_is_what_environment_shading_averages():
    """Per ray, ``ray_radiance`` brings the sky colour L or the wall's W (times the factor); the
    mean over the rays ``environment_shading`` casts (same seed, one point) is its result."""
    left = quad([[0.01, -500, -1], [0.01, 0, -1], [0.01, 0, 200], [0.01, -500, 200]])
    right = quad([[0.01, 0, -1], [0.01, 500, -1], [0.01, 500, 200], [0.01, 0, 200]])
    tracer = Tracer(mesh_proxy(*merge(left, right)))
    L, W = np.array([0.2, 0.4, 0.8]), np.array([0.6, 0.5, 0.4])
    radiance = np.tile(W, (8, 1))
    radiance[4:] = np.nan
    unseen = (~np.isfinite(radiance).all(axis=1)).astype(np.float64)[:, None]
    filled = fill_unseen(radiance, tracer.proxy.vertices)
    np.testing.assert_array_equal(filled, np.tile(W, (8, 1)))
    points, normals = np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]])
    directions = cosine_hemisphere(normals, MC_RAYS, rng=np.random.default_rng(0)).reshape(-1, 3)
    hits = tracer.intersect(np.zeros((MC_RAYS, 3)), directions)
    assert 0.3 < hits.hit.mean() < 0.7
    for mode in ("all", "unseen", "none"):
        sky, ind = ray_radiance(tracer, hits, directions, uniform_sky(L), filled, unseen, attenuation=mode)
        np.testing.assert_allclose(sky[~hits.hit], np.tile(L, (int((~hits.hit).sum()), 1)), rtol=1e-6)
        assert not sky[hits.hit].any() and not ind[~hits.hit].any()
        if mode == "none":
            np.testing.assert_allclose(ind[hits.hit], np.tile(W, (int(hits.hit.sum()), 1)), rtol=1e-12)
        mean_sky, mean_ind = environment_shading(points, normals, tracer, uniform_sky(L), radiance, n_rays=MC_RAYS,
                                                 ray_offset=0.0, attenuation=mode, rng=0)
        np.testing.assert_allclose(mean_sky[0], sky.mean(axis=0), rtol=1e-6)
        np.testing.assert_allclose(mean_ind[0], ind.mean(axis=0), rtol=1e-6)


def test_attenuation_modes_are_validated():
    assert Step1Config(indirect_attenuation=True).indirect_attenuation == "all"
    assert Step1Config(indirect_attenuation=False).indirect_attenuation == "none"
    assert Step1Config().indirect_attenuation == "all"  # the paper's
    with pytest.raises(ValueError, match="indirect_attenuation must be one of"):
        Step1Config(indirect_attenuation="some")


def test_box_on_plane_casts_the_exact_shadow_footprint():
    """~v on a grid of ground points equals the analytic shadow of a box (slab test)."""
    lo, hi = np.array([-1.0, -1.0, 0.0]), np.array([1.0, 1.0, 2.0])
    corners = np.array([[x, y, z] for z in (lo[2], hi[2]) for y in (lo[1], hi[1]) for x in (lo[0], hi[0])])
    faces = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    box = (corners, np.array([t for a, b, c, d in faces for t in ((a, b, c), (a, c, d))]))
    tracer = Tracer(mesh_proxy(*merge(ground(20.0), box)))
    sun = np.array([0.5, -0.3, 0.6])
    sun /= np.linalg.norm(sun)
    xs = np.linspace(-8, 8, 161)
    grid = np.stack(np.meshgrid(xs, xs), -1).reshape(-1, 2)
    points = np.column_stack([grid, np.zeros(len(grid))])
    outside = ~np.all((points[:, :2] >= lo[:2]) & (points[:, :2] <= hi[:2]), axis=1)
    points = points[outside]
    normals = np.tile([0.0, 0.0, 1.0], (len(points), 1))
    v = sun_visibility(points, normals, sun, tracer, ray_offset=1e-4)
    # slab test of the ray p + t sun against the box
    with np.errstate(divide="ignore"):
        t1, t2 = (lo - points) / sun, (hi - points) / sun
    t_near, t_far = np.minimum(t1, t2).max(axis=1), np.maximum(t1, t2).min(axis=1)
    shadow = (t_far >= max(t_near.min(), 0)) & (t_far >= t_near) & (t_far > 0)
    # ignore points within 1 cm of the shadow boundary (float32 ray casting)
    margin = np.minimum(np.abs(t_far - t_near), 1.0) > 0.01
    assert shadow.sum() > 100
    np.testing.assert_array_equal(v[margin] == 0, shadow[margin])
    # attached shadow: a face turned away from the sun is never lit
    assert sun_visibility(np.array([[0.0, 0.0, 5.0]]), np.array([[0.0, 0.0, -1.0]]), sun, tracer).tolist() == [0.0]


def test_interpolation_respects_creases():
    # Ground points (normal +z) and wall points (normal +x) side by side: a ground target takes
    # only ground values even where wall sources are as close.
    src = np.array([[0.1, 0, 0], [0.3, 0, 0], [0, 0, 0.1], [0, 0, 0.3]], float)
    src_n = np.array([[0, 0, 1], [0, 0, 1], [1, 0, 0], [1, 0, 0]], float)
    values = np.array([[1.0], [1.0], [5.0], [5.0]])
    out = interpolate_points(src, src_n, values, np.array([[0.05, 0, 0.05]]), np.array([[0, 0, 1.0]]), neighbors=4)
    assert out[0, 0] == pytest.approx(1.0)


# -- gathering and rasterising -------------------------------------------------------------------
def looking_down(center, size=40):
    f = size / (2 * math.tan(math.radians(30)))
    rotation = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
    return Camera("PINHOLE", size, size, [f, f, size / 2, size / 2], rotation, -rotation @ np.asarray(center, float))


def test_vertex_radiance_is_the_median_of_the_views_that_see_it():
    xs = np.linspace(-2, 2, 9)
    grid = np.stack(np.meshgrid(xs, xs), -1).reshape(-1, 2)
    vertices = np.column_stack([grid, np.zeros(len(grid))])
    tri = []
    for i in range(8):
        for j in range(8):
            a = i * 9 + j
            tri += [(a, a + 1, a + 10), (a, a + 10, a + 9)]
    proxy = mesh_proxy(vertices, np.array(tri))
    tracer = Tracer(proxy)
    colours = [0.2, 0.21, 0.9]  # the third view is an outlier; the median ignores it
    views = [View(f"v{k}", np.full((40, 40, 3), c, np.float32), looking_down([0.1 * k, 0, 5])) for k, c in enumerate(colours)]
    radiance, count = vertex_radiance(views, tracer)
    seen = count == 3
    assert seen.sum() > 20
    np.testing.assert_allclose(radiance[seen], 0.21, rtol=1e-6)
    # Occlusion: a vertex under an opaque roof is not seen.
    roof = quad([[-0.3, -0.3, 1.0], [0.3, -0.3, 1.0], [0.3, 0.3, 1.0], [-0.3, 0.3, 1.0]])
    occluded = Tracer(mesh_proxy(*merge((vertices, np.array(tri)), roof)))
    radiance2, count2 = vertex_radiance(views, occluded)
    centre = np.flatnonzero(np.all(np.abs(vertices) < 1e-9, axis=1))[0]
    assert count2[centre] == 0 and np.isnan(radiance2[centre]).all()


def test_rasterize_interpolates_linearly():
    proxy = mesh_proxy(*ground(10.0))
    tracer = Tracer(proxy)
    camera = looking_down([0.0, 0.0, 4.0])
    image = rasterize(proxy.vertices[:, :2], camera, tracer)  # x, y of each vertex
    hits = tracer.intersect(camera.center, camera.pixel_rays())
    np.testing.assert_allclose(image.reshape(-1, 2), hits.points[:, :2], atol=1e-5)


# -- end to end ----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def demo_clean():
    """The demo scene with its exact geometry (proxy_clean.ply) subdivided as the proxy."""
    from mvintrinsic.cli import demo_scene_path
    from mvintrinsic.io import load_scene, read_proxy

    folder = demo_scene_path()
    scene = load_scene(folder)
    centers = np.array([v.camera.center for v in scene.views])
    proxy = subdivide(read_proxy(folder / "proxy_clean.ply"), max_edge=0.3, center=centers.mean(axis=0), radius=25.0)
    return folder, Scene(scene.views, proxy, scene.sun, scene.up)


def env_error_in_gt_shadow(folder, scene, result):
    """Median relative error per channel of S_sky + S_ind against gt/env_shading, GT-shadowed pixels."""
    from mvintrinsic.evaluation import env_shading_error

    tracer = Tracer(scene.proxy)
    estimates = {v.stem: rasterize(result.shading.env, v.camera, tracer) for v in scene.views}
    return np.asarray(env_shading_error(folder, estimates, region="shadow")["median_rel_error"])


def test_step1_on_the_demo_scene_with_a_clean_proxy(demo_clean):
    folder, scene = demo_clean
    result = step1(scene, config=Step1Config(), rng=0)
    n = len(scene.proxy.vertices)
    assert result.radiance.shape == (n, 3) and result.shading.sky.shape == (n, 3)
    assert result.sky_model.converged and 1.7 <= result.sky_model.turbidity <= 10
    assert abs(result.horizon.plane[2]) > 0.99 and abs(result.horizon.plane[3]) < 0.05  # the ground z = 0
    assert set(result.timings) >= {"environment", "vertex_radiance", "environment_shading", "sun_visibility"}
    np.testing.assert_array_equal(result.normals, vertex_normals(scene.proxy, Step1Config().normal_smoothing,
                                                                 Step1Config().planes))
    error = env_error_in_gt_shadow(folder, scene, result)
    assert np.all(error <= CLEAN_PROXY_ENV_ERROR_MAX), error
    # ~v against the ground truth, all views
    from mvintrinsic.evaluation import visibility_error

    tracer = Tracer(scene.proxy)
    visibility = {v.stem: rasterize(result.shading.visibility, v.camera, tracer) for v in scene.views}
    assert visibility_error(folder, visibility)["ber"] < CLEAN_PROXY_BER_MAX


# -- normal smoothing ----------------------------------------------------------------------------
def grid_mesh(n=41, spacing=0.05, z=0.0, x0=0.0):
    """An n x n vertex grid in the plane z (spacing metres), two triangles per cell."""
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    vertices = np.stack([x0 + i.ravel() * spacing, j.ravel() * spacing, np.full(n * n, z)], axis=1)
    k = (i[:-1, :-1] * n + j[:-1, :-1]).ravel()
    triangles = np.concatenate([np.stack([k, k + n, k + 1], 1), np.stack([k + 1, k + n, k + n + 1], 1)])
    return vertices, triangles


def noisy_normals(n_vertices, degrees, rng):
    tilt = np.radians(degrees) * np.abs(rng.normal(size=n_vertices))
    phi = rng.uniform(0, 2 * np.pi, n_vertices)
    return np.stack([np.sin(tilt) * np.cos(phi), np.sin(tilt) * np.sin(phi), np.cos(tilt)], axis=1)


def test_smoothing_recovers_a_noisy_planes_normal_and_its_grazing_sun_cosine():
    # An MVS-like facade: normals tilted by |N(0, 30 degrees)| (median 20), the sun grazing it (cos 0.26).
    rng = np.random.default_rng(0)
    vertices, triangles = grid_mesh()
    proxy = Proxy(vertices, noisy_normals(len(vertices), 30.0, rng), triangles)
    smoothed = smooth_normals(proxy, 0.4)
    np.testing.assert_allclose(np.linalg.norm(smoothed, axis=1), 1.0, atol=1e-12)
    inner = (np.abs(vertices[:, :2] - 1.0) < 0.5).all(axis=1)  # a metre away from the borders
    before = np.degrees(np.arccos(np.clip(proxy.normals[inner, 2], -1, 1)))
    after = np.degrees(np.arccos(np.clip(smoothed[inner, 2], -1, 1)))
    assert np.median(before) > 15 and np.median(after) < 2.0, (np.median(before), np.median(after))
    sun = np.array([np.sin(np.radians(75)), 0.0, np.cos(np.radians(75))])
    error = np.abs(np.maximum(smoothed[inner] @ sun, 0) - sun[2])
    noisy_error = np.abs(np.maximum(proxy.normals[inner] @ sun, 0) - sun[2])
    assert np.median(error) < 0.02 and np.median(noisy_error) > 0.1, (np.median(error), np.median(noisy_error))


def test_smoothing_keeps_exact_planes_and_unconnected_surfaces_apart():
    # Two parallel grids 10 cm apart, facing opposite ways: averaging in space would cancel them.
    a, ta = grid_mesh(n=11)
    b, tb = grid_mesh(n=11, z=0.1)
    vertices, triangles = merge((a, ta), (b, tb))
    normals = np.concatenate([np.tile([0.0, 0.0, 1.0], (len(a), 1)), np.tile([0.0, 0.0, -1.0], (len(b), 1))])
    proxy = Proxy(vertices, normals, triangles)
    np.testing.assert_allclose(smooth_normals(proxy, 0.3), normals, atol=1e-12)


def test_smoothing_a_coarse_mesh_or_a_point_cloud_changes_nothing():
    vertices, triangles = grid_mesh(n=5, spacing=2.0)
    rng = np.random.default_rng(1)
    proxy = Proxy(vertices, noisy_normals(len(vertices), 20.0, rng), triangles)
    np.testing.assert_array_equal(smooth_normals(proxy, 0.4), proxy.normals)  # edges of 2 m >> 0.4 m
    cloud = Proxy(vertices, proxy.normals)
    np.testing.assert_array_equal(smooth_normals(cloud, 0.4), proxy.normals)


def test_normal_smoothing_is_validated():
    vertices, triangles = grid_mesh(n=3)
    proxy = Proxy(vertices, np.tile([0.0, 0.0, 1.0], (len(vertices), 1)), triangles)
    for bad in (0.0, -1.0, np.inf, "0.4", True):
        with pytest.raises(ValueError, match="sigma"):
            smooth_normals(proxy, bad)
    for bad in (-0.1, np.nan, "x"):
        with pytest.raises(ValueError, match="normal_smoothing"):
            Step1Config(normal_smoothing=bad)
    assert Step1Config(normal_smoothing=0).normal_smoothing == 0


def test_subdivide_keeps_the_surface_and_bounds_edges():
    corners = np.array([[x, y, z] for z in (0.0, 2.0) for y in (-1.0, 1.0) for x in (-1.0, 1.0)])
    faces = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    box = mesh_proxy(corners, np.array([t for a, b, c, d in faces for t in ((a, b, c), (a, c, d))]))
    fine = subdivide(box, max_edge=0.3)
    np.testing.assert_array_equal(fine.vertices[: len(box.vertices)], box.vertices)
    v, t = fine.vertices, fine.triangles
    edges = np.concatenate([np.linalg.norm(v[t[:, i]] - v[t[:, (i + 1) % 3]], axis=1) for i in range(3)])
    assert edges.max() <= 0.3 and len(t) == 12 * 4**4
    rng = np.random.default_rng(0)
    d = rng.normal(size=(500, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    a, b = Tracer(box).intersect([0.1, 0.2, 1.0], d), Tracer(fine).intersect([0.1, 0.2, 1.0], d)
    np.testing.assert_allclose(a.t, b.t, atol=1e-5)
    # only near the centre
    local = subdivide(box, max_edge=0.3, center=[0.0, 0.0, 0.0], radius=1.2)
    assert len(box.triangles) < len(local.triangles) < len(fine.triangles)
    with pytest.raises(ValueError, match="point cloud"):
        subdivide(Proxy(box.vertices, box.normals), max_edge=0.3)


def test_subdivide_reaches_a_huge_triangle_whose_centroid_is_far():
    """A ground triangle 600 m wide passing under the centre is refined there (not only near its centroid)."""
    big = mesh_proxy([[-20.0, -20.0, 0.0], [600.0, -20.0, 0.0], [-20.0, 600.0, 0.0]], np.array([[0, 1, 2]]))
    assert np.linalg.norm(big.vertices.mean(axis=0)) > 150  # the centroid is far outside the 5 m ball
    fine = subdivide(big, max_edge=0.5, center=[0.0, 0.0, 0.0], radius=5.0)
    v, t = fine.vertices, fine.triangles
    centroids = v[t].mean(axis=1)
    near = np.linalg.norm(centroids, axis=1) < 5.0
    edges = np.max([np.linalg.norm(v[t[:, i]] - v[t[:, (i + 1) % 3]], axis=1) for i in range(3)], axis=0)
    assert near.sum() > 100 and edges[near].max() <= 0.5
    assert len(t) < 20000  # far parts stay coarse


def test_convergence_test_spends_rays_only_where_the_shading_varies():
    """Step1Config.ray_tolerance: a point that sees only a uniform sky converges in one round (every
    ray brings the same radiance); a point at the foot of a wall gets more rounds, and is then closer
    to the analytic S_sky = L / 2 than one round of the same first size."""
    c, s = math.cos(0.5), math.sin(0.5)  # a wall turned off the sampler's strata boundaries
    corners = np.array([[0.01, -500, -1], [0.01, 500, -1], [0.01, 500, 200], [0.01, -500, 200]])
    wall = quad(corners @ np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]]))
    tracer = Tracer(mesh_proxy(*merge(wall)))
    L = np.array([0.2, 0.4, 0.8])
    points = np.array([[0.0, 0.0, 0.0], [-c, -s, 0.0]])  # at the wall's foot; facing away from it
    normals = np.array([[0.0, 0.0, 1.0], [-c, -s, 0.0]])
    kwargs = dict(ray_offset=0.0, attenuation="none", n_rays=16)
    one = [environment_shading(points, normals, tracer, uniform_sky(L), np.zeros((4, 3)), rng=seed, **kwargs)[0]
           for seed in range(8)]
    many = [environment_shading(points, normals, tracer, uniform_sky(L), np.zeros((4, 3)), rng=seed,
                                tolerance=0.01, max_rays=336, return_counts=True, **kwargs) for seed in range(8)]
    counts = np.array([m[2] for m in many])
    assert (counts[:, 1] == 16).all() and (counts[:, 0] == 336).all()  # 16 + 64 + 256 at the wall
    error_one = np.abs(np.array([s[0] for s in one]) / (L / 2) - 1).mean()
    error_many = np.abs(np.array([m[0][0] for m in many]) / (L / 2) - 1).mean()
    assert error_many < 0.5 * error_one
    # Without a tolerance the count is fixed and the result is the one-round result.
    fixed = environment_shading(points, normals, tracer, uniform_sky(L), np.zeros((4, 3)), rng=0,
                                return_counts=True, **kwargs)
    np.testing.assert_array_equal(fixed[0], one[0]) and np.testing.assert_array_equal(fixed[2], 16)
    with pytest.raises(ValueError, match="tolerance"):
        environment_shading(points, normals, tracer, uniform_sky(L), np.zeros((4, 3)), tolerance=0.0)
    with pytest.raises(ValueError, match="max_rays"):
        Step1Config(ray_tolerance=0.05, max_rays=8)
