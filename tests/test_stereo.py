"""PatchMatch stereo and the completed proxy (mvintrinsic.stereo) on exact, textured scenes.

The views are ray-cast images of a mesh whose colour is a fixed function of the world position
(a Lambertian texture: every view sees a point with the same colour), so the true depth of every
pixel is known.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import ground_and_box_mesh, look_at

from mvintrinsic.camera import Camera
from mvintrinsic.raytrace import Tracer
from mvintrinsic.scene import Proxy, Scene, Sun, View
from mvintrinsic.stereo import StereoConfig, complete_proxy, depth_surface, patchmatch, source_views

W, H = 160, 120


def texture(points: np.ndarray) -> np.ndarray:
    """Linear RGB of world points (N, 3): a sum of sines at several scales, no two places alike."""
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    g = (3.5 + np.sin(7.1 * x + 3.3 * y) + np.sin(11.3 * y - 5.9 * z + 1.0) + np.sin(17.7 * z + 13.1 * x - 2.0)
         + 0.5 * np.sin(29.0 * x - 23.0 * y + 19.0 * z)) / 7.0  # in [0, 1]
    return np.stack([0.1 + 0.6 * g, 0.1 + 0.5 * g, 0.1 + 0.4 * g], axis=1).astype(np.float32)


def render(tracer: Tracer, camera: Camera, sky: float = 0.8) -> tuple[np.ndarray, np.ndarray]:
    """The textured image and the true depth along the optical axis (inf for the sky), (H, W)."""
    rays = camera.pixel_rays()
    hits = tracer.intersect(camera.center, rays)
    image = np.full((camera.height * camera.width, 3), sky, np.float32)
    points = camera.center + rays * hits.t[:, None]
    image[hits.hit] = texture(points[hits.hit])
    return image.reshape(camera.height, camera.width, 3), (hits.t * (rays @ camera.forward)).reshape(camera.shape)


def mesh_proxy(mesh) -> Proxy:
    return Proxy(np.asarray(mesh.vertices), np.asarray(mesh.vertex_normals), np.asarray(mesh.triangles))


@pytest.fixture(scope="module")
def box_scene():
    return make_box_scene()


def make_box_scene():
    """Five views of the box on the ground; the proxy holds the ground only (it lost the box).

    Returns the scene, the views' true depth maps and a tracer of the exact mesh.
    """
    import open3d as o3d

    exact = Tracer(mesh_proxy(ground_and_box_mesh()))
    ground = o3d.geometry.TriangleMesh.create_box(10.0, 10.0, 0.01).translate((-5.0, -5.0, -0.01)).subdivide_midpoint(2)
    ground.compute_vertex_normals()
    views, depths = [], []
    for k, angle in enumerate(np.radians([-110, -100, -90, -80, -70])):
        center = np.array([7.0 * np.cos(angle), 7.0 * np.sin(angle), 3.5])
        rotation, translation = look_at(center, np.array([0.0, 0.0, 0.8]))
        camera = Camera("PINHOLE", W, H, [0.9 * W, 0.9 * W, W / 2, H / 2], rotation, translation)
        image, depth = render(exact, camera)
        views.append(View(f"view_{k}", image, camera))
        depths.append(depth)
    scene = Scene(views=tuple(views), proxy=mesh_proxy(ground), sun=Sun(np.array([0.4, -0.3, 0.8])))
    return scene, depths, exact


def test_config_errors_name_the_field():
    for field, value in [("window", 0), ("stride", 1.5), ("colour_sigma", -1.0), ("max_cost", np.nan),
                         ("in_front", 1.0), ("agreeing_views", -1), ("iterations", True),
                         ("colour_tolerance", 0.0), ("colour_tolerance", "0.15")]:
        with pytest.raises(ValueError, match=field):
            StereoConfig(**{field: value})
    with pytest.raises(ValueError, match="best_views"):
        StereoConfig(source_views=2, best_views=3)


def test_source_views_nearest_in_direction(box_scene):
    scene, _, _ = box_scene
    cameras = [v.camera for v in scene.views]
    assert set(source_views(cameras, 2, 2)) == {1, 3}  # symmetric: either first
    assert source_views(cameras, 0, 3) == (1, 2, 3)


def test_patchmatch_recovers_the_depth_of_textured_surfaces(box_scene):
    scene, depths, _ = box_scene
    cameras = [v.camera for v in scene.views]
    from mvintrinsic.stereo import _pinhole

    greys = [_pinhole(v, 640)[1] for v in scene.views]
    true = depths[2]
    finite = np.isfinite(true)
    result = patchmatch(cameras, greys, 2, depth_range=(2.0, 20.0), config=StereoConfig())
    with np.errstate(invalid="ignore"):
        error = np.abs(result.depth - true) / true
    inner = finite.copy()
    inner[:6], inner[-6:], inner[:, :6], inner[:, -6:] = False, False, False, False  # windows leave the image
    # Measured: 94% of the surface pixels within 2% of the true depth (87% within 1%), without the
    # proxy's prior; the misses sit along the box's occluding edges and its top.
    assert np.mean(error[inner] < 0.02) > 0.9
    assert result.depth.shape == (H, W) and result.normal.shape == (H, W, 3) and set(result.sources) == {0, 1, 3, 4}
    # The normals of the ground, in the world frame: up.
    ground = inner & (np.abs(result.points()[..., 2]) < 0.02)
    assert np.median(result.normal[ground] @ np.array([0.0, 0.0, 1.0])) > 0.98


def test_complete_proxy_adds_the_lost_box(box_scene):
    scene, depths, exact = box_scene
    proxy, maps = complete_proxy(scene)
    n = len(scene.proxy.vertices)
    assert np.array_equal(proxy.vertices[:n], scene.proxy.vertices)
    assert np.array_equal(proxy.triangles[: len(scene.proxy.triangles)], scene.proxy.triangles)
    added = proxy.vertices[n:]
    # The added points lie on the box (the ground is in the proxy already): within 3 cm of its faces.
    inside = np.abs(added[:, :2]).max(axis=1) <= 1.03
    on_box = inside & (added[:, 2] <= 2.03) & (added[:, 2] >= 0.0)
    dist = np.minimum(1.0 - np.abs(added[:, :2]).max(axis=1), 2.0 - added[:, 2])
    assert on_box.mean() > 0.95 and np.median(np.abs(dist[on_box])) < 0.03
    # And they cover most of the box each view sees: measured 72-84% of its pixels within 2% of
    # the true depth (the outer views, with sources on one side only, 72-73%; the misses lie along
    # the box's edges and on its grazing top).
    tracer = Tracer(proxy)
    for view, true in zip(scene.views, depths, strict=True):
        rays = view.camera.pixel_rays()
        points = view.camera.center + rays * (true.ravel() / (rays @ view.camera.forward))[:, None]
        box = (np.abs(points[:, :2]).max(axis=1) < 1.001) & (points[:, 2] > 0.01)
        found = tracer.intersect(view.camera.center, rays).t * (rays @ view.camera.forward)
        assert np.mean(np.abs(found[box] - true.ravel()[box]) < 0.02 * true.ravel()[box]) > 0.7
    assert all(m.depth.shape == (H, W) for m in maps)


def test_selection_again_from_the_depth_maps_and_the_colour_test(box_scene):
    import dataclasses

    from mvintrinsic.stereo import _colour_seen, proxy_from_depths

    scene, _, _ = box_scene
    proxy, maps = complete_proxy(scene)
    again = proxy_from_depths(scene, maps)
    assert np.array_equal(again.vertices, proxy.vertices) and np.array_equal(again.triangles, proxy.triangles)
    n = len(scene.proxy.triangles)
    plain = proxy_from_depths(scene, maps, config=StereoConfig(colour_tolerance=None))
    # The box's Lambertian texture looks the same from every view: measured 15365 of 15538 added
    # triangles kept with the default colour test (0.15; 12205 at 0.05).
    assert 0.95 * (len(plain.triangles) - n) < len(proxy.triangles) - n < len(plain.triangles) - n
    # NCC ignores a view's gain, the colour test does not: view 2 twice as bright (0.69 in log
    # radiance) sees its points' colours in no other view (measured 87 of 19200 pixels, against 18419).
    keep = np.isfinite(maps[2].depth)
    views = list(scene.views)
    views[2] = dataclasses.replace(views[2], image=views[2].image * 2.0)
    brighter = dataclasses.replace(scene, views=tuple(views))
    assert _colour_seen(scene, maps[2], 2, keep, 0.15).mean() > 0.9
    assert _colour_seen(brighter, maps[2], 2, keep, 0.15).mean() < 0.01
    with pytest.raises(ValueError, match="depths"):
        proxy_from_depths(scene, maps[:-1])


def test_depth_surface_splits_at_depth_jumps():
    camera = Camera("PINHOLE", 4, 3, [3.0, 3.0, 2.0, 1.5], np.eye(3), np.zeros(3))
    from mvintrinsic.stereo import DepthMap

    depth = np.array([[1.0, 1.0, 2.0, 2.0]] * 3)
    dm = DepthMap(camera, depth, np.zeros((3, 4, 3)), np.zeros((3, 4), np.float32), ())
    vertices, triangles = depth_surface(dm, np.ones((3, 4), bool))
    assert len(vertices) == 12 and len(triangles) == 8  # the middle column of quads spans the jump
    np.testing.assert_allclose(vertices[:, 2], depth.ravel())


def test_complete_proxy_refuses_point_clouds_and_too_few_views(box_scene):
    scene, _, _ = box_scene
    cloud = Proxy(scene.proxy.vertices, scene.proxy.normals)
    with pytest.raises(ValueError, match="point cloud"):
        complete_proxy(Scene(views=scene.views, proxy=cloud, sun=scene.sun))
    with pytest.raises(ValueError, match="views"):
        complete_proxy(Scene(views=scene.views[:2], proxy=scene.proxy, sun=scene.sun), config=StereoConfig(best_views=2))


def test_cli_complete_proxy_writes_a_new_scene_and_leaves_the_input(tmp_path, capsys):
    import hashlib

    from conftest import make_scene

    from mvintrinsic.cli import main
    from mvintrinsic.io import load_scene, read_proxy

    scene_dir = make_scene(tmp_path / "scene", n_views=3)

    def digest(folder):
        return {p.relative_to(folder): hashlib.sha256(p.read_bytes()).hexdigest() for p in folder.rglob("*") if p.is_file()}

    before = digest(scene_dir)
    out = tmp_path / "completed"
    assert main(["complete-proxy", str(scene_dir), str(out), "--quiet"]) == 0
    assert digest(scene_dir) == before
    assert {p for p in digest(out)} == {p for p in before}  # the same files, proxy.ply rewritten
    original, completed = read_proxy(scene_dir / "proxy.ply"), read_proxy(out / "proxy.ply")
    n = len(original.vertices)
    np.testing.assert_allclose(completed.vertices[:n], original.vertices, atol=1e-5)
    assert len(load_scene(out).views) == 3
    assert "triangles added" in capsys.readouterr().out
    # A non-empty OUT, or one inside the scene, is refused naming the argument; nothing is written.
    assert main(["complete-proxy", str(scene_dir), str(out), "--quiet"]) == 2
    assert "out:" in capsys.readouterr().err
    assert main(["complete-proxy", str(scene_dir), str(scene_dir / "inner"), "--quiet"]) == 2
    assert "out:" in capsys.readouterr().err and not (scene_dir / "inner").exists()
    # The colour test: off with 'none', a bad value refused naming the option.
    assert main(["complete-proxy", str(scene_dir), str(tmp_path / "plain"), "--quiet", "--colour-tolerance", "none"]) == 0
    assert len(read_proxy(tmp_path / "plain" / "proxy.ply").triangles) >= len(completed.triangles)
    with pytest.raises(SystemExit):
        main(["complete-proxy", str(scene_dir), str(tmp_path / "bad"), "--colour-tolerance", "0"])
    assert "--colour-tolerance" in capsys.readouterr().err and not (tmp_path / "bad").exists()
    assert digest(scene_dir) == before


def test_distorted_views_are_matched_on_their_pinhole_twins():
    from mvintrinsic.stereo import _pinhole

    rotation, translation = look_at(np.array([0.0, -6.0, 2.0]), np.array([0.0, 0.0, 0.5]))
    camera = Camera("OPENCV", W, H, [0.9 * W, 0.9 * W, W / 2, H / 2, -0.25, 0.05, 0.001, -0.001], rotation, translation)
    yy, xx = np.mgrid[0:H, 0:W]
    lum = (0.3 + 0.1 * np.sin(xx / 4.0) + 0.1 * np.cos(yy / 3.0)).astype(np.float32)
    view = View("v", np.repeat(lum[..., None], 3, axis=2), camera)
    twin, grey = _pinhole(view, 640)
    assert twin.model == "PINHOLE" and not twin.is_distorted and grey.shape == (H, W)
    np.testing.assert_allclose(twin.K, camera.K)
    # A world point lands where each camera says: the twin's grey there is the view's (the same
    # normalisation: square root of luminance over its 99th percentile).
    rng = np.random.default_rng(0)
    points = np.column_stack([rng.uniform(-1.5, 1.5, 200), rng.uniform(-0.5, 0.5, 200), rng.uniform(0.0, 1.5, 200)])
    (u0, v0), (u1, v1) = (c.project(points)[0].T for c in (camera, twin))
    inside = (u0 > 2) & (u0 < W - 3) & (v0 > 2) & (v0 < H - 3) & (u1 > 2) & (u1 < W - 3) & (v1 > 2) & (v1 < H - 3)
    source = np.sqrt(lum) / np.percentile(np.sqrt(lum), 99)
    import cv2

    def sample(image, u, v):
        return cv2.remap(image.astype(np.float32), (u - 0.5).astype(np.float32)[None], (v - 0.5).astype(np.float32)[None],
                         cv2.INTER_LINEAR)[0]

    assert inside.sum() > 100
    # Measured: within 0.007 everywhere; the view's own grey, not resampled, misses by up to 0.027
    # (15% of the points beyond 0.01).
    np.testing.assert_allclose(sample(grey, u1[inside], v1[inside]), sample(source, u0[inside], v0[inside]), atol=0.01)
