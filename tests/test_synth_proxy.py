"""MVS proxy simulator: a box with a known answer, quality budgets on dev_courtyard, one test per knob.

The knob tests run on five of the ten dev_courtyard cameras downscaled to 160x120 with 8 cm voxels
(about the pixel footprint at the facade) and compare against the same setting with only the knob
changed, so each asserts what that knob does rather than absolute numbers.
"""

from __future__ import annotations

import dataclasses
from functools import cache

import numpy as np
import pytest
from conftest import look_at

import mvintrinsic  # noqa: F401  (loads libusb before open3d)
from mvintrinsic import Camera, Proxy
from mvintrinsic.synth.proxy import (
    ProxyConfig,
    distance_to_mesh,
    foliage_retention,
    label_retention,
    simulate_mvs_proxy,
)
from mvintrinsic.synth.types import LABELS

# -- tolerances (named once) --------------------------------------------------------------------
WITHIN_10CM_MIN = 0.80  # default proxy: fraction of vertices within 10 cm of the GT mesh
RETENTION_RADIUS = 0.10  # m, for every retention figure
FOLIAGE_RETENTION_MAX = 0.5  # default proxy has lost most foliage...
KEPT_RETENTION_MIN = 0.8  # ...but kept the ground and the solid surfaces
NOISE_FREE_WITHIN_2VOX_MIN = 0.95  # no noise, no holes: vertices within 2 voxel sizes of the GT
KNOB_GAIN = 0.3  # retention gained when a class is no longer dropped
FAST = dict(voxel_size=0.08)  # knob tests: voxels about the size of a 160x120 pixel at the facade
GROUND, SOLID, FOLIAGE, THIN = range(4)


# -- the exact case: a box on the ground seen by four cameras -----------------------------------
BOX_HEIGHT = 1.5  # m, a round number, like the z = 0 ground (see GRID_OFFSET in synth.proxy)
BOX_VOXEL = 0.05


def box_scene(model: str = "PINHOLE"):
    """Ground square (20 m) and a 2 x 2 x BOX_HEIGHT m box; four cameras on the diagonals."""
    g = 10.0
    vertices = [(-g, -g, 0), (g, -g, 0), (g, g, 0), (-g, g, 0)]
    triangles = [(0, 1, 2), (0, 2, 3)]
    h = BOX_HEIGHT
    corners = [(x, y, z) for z in (0.0, h) for y in (-1.0, 1.0) for x in (-1.0, 1.0)]
    vertices += corners
    # Box faces, counter-clockwise from outside (indices into corners, offset by 4).
    quads = [(4, 5, 7, 6), (0, 1, 5, 4), (1, 3, 7, 5), (3, 2, 6, 7), (2, 0, 4, 6)]
    for a, b, c, d in quads:
        triangles += [(a + 4, b + 4, c + 4), (a + 4, c + 4, d + 4)]
    labels = np.array([GROUND, GROUND] + [SOLID] * 10)
    w, hh = 160, 120
    f = 0.9 * w
    params = {"PINHOLE": [f, f, w / 2, hh / 2], "OPENCV": [f, f, w / 2, hh / 2, -0.05, 0.01, 0.002, -0.001]}[model]
    cameras = []
    for angle in np.radians([45.0, 135.0, 225.0, 315.0]):
        center = np.array([6.0 * np.cos(angle), 6.0 * np.sin(angle), 4.0])
        rotation, translation = look_at(center, np.array([0.0, 0.0, 0.5]))
        cameras.append(Camera(model, w, hh, params, rotation, translation))
    return np.array(vertices, float), np.array(triangles), labels, cameras


EXACT = ProxyConfig(depth_noise=0.0, hole_rate=0.0, voxel_size=BOX_VOXEL)


def test_box_on_ground_is_reconstructed_where_it_is():
    vertices, triangles, labels, cameras = box_scene()
    proxy = simulate_mvs_proxy(vertices, triangles, labels, cameras, config=EXACT, rng=0)
    v, n = proxy.vertices, proxy.normals
    top = (np.abs(v[:, 0]) < 0.8) & (np.abs(v[:, 1]) < 0.8) & (v[:, 2] > 0.75)
    ground = (np.max(np.abs(v[:, :2]), axis=1) > 1.5) & (v[:, 2] < 0.75)
    # The top is complete and single: marching cubes puts one vertex on every vertical voxel edge
    # that crosses it, so the top vertices form a full grid with one voxel spacing.
    xs, ys = (np.unique(np.round(v[top, i], 6)) for i in (0, 1))
    assert top.sum() == len(xs) * len(ys)
    for coords in (xs, ys):
        np.testing.assert_allclose(np.diff(coords), BOX_VOXEL, atol=1e-5)
        assert coords[-1] - coords[0] > 1.5
    np.testing.assert_allclose(v[top, 2], BOX_HEIGHT, atol=BOX_VOXEL)
    np.testing.assert_allclose(v[ground, 2], 0.0, atol=BOX_VOXEL)
    # Normals face the cameras: up on the top and on the ground.
    assert np.all(n[top, 2] > 0.9) and np.mean(n[ground, 2] > 0.9) > 0.99
    assert distance_to_mesh(v, vertices, triangles).max() < BOX_VOXEL


def test_distorted_cameras_fuse_their_undistorted_pinhole_twins():
    """Depth is rendered for the pinhole twin (same K, no distortion): the proxy is the same."""
    vertices, triangles, labels, pinhole = box_scene("PINHOLE")
    distorted = box_scene("OPENCV")[3]
    assert distorted[0].is_distorted
    a = simulate_mvs_proxy(vertices, triangles, labels, pinhole, config=EXACT, rng=3)
    b = simulate_mvs_proxy(vertices, triangles, labels, distorted, config=EXACT, rng=3)
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.triangles, b.triangles)


def test_inputs_are_not_mutated_and_progress_is_optional(capsys):
    vertices, triangles, labels, cameras = box_scene()
    before = (vertices.copy(), triangles.copy(), labels.copy())
    simulate_mvs_proxy(vertices, triangles, labels, cameras, config=EXACT, rng=0, progress=True)
    for x, y in zip(before, (vertices, triangles, labels), strict=True):
        np.testing.assert_array_equal(x, y)
    assert "MVS proxy" in capsys.readouterr().err


def test_distance_to_mesh_on_a_plane():
    vertices, triangles = box_scene()[:2]
    points = np.array([[3.0, 4.0, 0.25], [5.0, -5.0, -0.5], [0.0, 0.0, BOX_HEIGHT + 0.125], [3.0, 0.0, 0.0]])
    np.testing.assert_allclose(distance_to_mesh(points, vertices, triangles), [0.25, 0.5, 0.125, 0.0], atol=1e-6)
    assert distance_to_mesh(np.zeros((0, 3)), vertices, triangles).shape == (0,)


def test_retention_of_the_ground_truth_itself_is_complete():
    vertices, triangles, labels, cameras = box_scene()
    exact = Proxy(vertices, np.tile([0.0, 0.0, 1.0], (len(vertices), 1)), triangles)
    retained = label_retention(exact, vertices, triangles, labels, cameras)
    assert retained["ground"] == 1.0 and retained["solid"] == 1.0
    assert np.isnan(retained["foliage"]) and np.isnan(retained["thin"])  # no such faces
    assert np.isnan(foliage_retention(exact, vertices, triangles, labels))
    all_foliage = np.full_like(labels, FOLIAGE)
    assert foliage_retention(exact, vertices, triangles, all_foliage) == 1.0
    # Nothing near the samples: nothing retained.
    far = Proxy(vertices + [0.0, 0.0, 50.0], exact.normals, triangles)
    assert foliage_retention(far, vertices, triangles, all_foliage) == 0.0


# -- dev_courtyard ------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def courtyard(dev_courtyard):
    """(vertices, triangles, labels, cameras sorted by name) of the shared dataset."""
    from mvintrinsic.io import read_colmap, read_proxy

    mesh = read_proxy(dev_courtyard / "gt" / "mesh.ply")
    faces = np.load(dev_courtyard / "gt" / "mesh_faces.npz")
    assert list(faces["label_names"]) == list(LABELS)
    cameras = read_colmap(dev_courtyard / "sparse")
    return mesh.vertices, mesh.triangles, faces["label"], [cameras[name] for name in sorted(cameras)]


@pytest.fixture(scope="module")
def fast(courtyard):
    """proxy(rng=0, **config changes) on 5 cameras at 160x120, memoised for the module."""
    vertices, triangles, labels, cameras = courtyard
    small = [cameras[i].scaled(160, 120) for i in (0, 2, 4, 6, 8)]

    @cache
    def run(**changes):
        config = ProxyConfig(**{**FAST, **changes})
        return simulate_mvs_proxy(vertices, triangles, labels, small, config=config, rng=0)

    def retention(proxy):
        return label_retention(proxy, vertices, triangles, labels, small, radius=RETENTION_RADIUS)

    run.retention = retention
    run.cameras = small
    return run


def test_ground_truth_files_agree(courtyard):
    vertices, triangles, labels, cameras = courtyard
    assert len(triangles) == len(labels) == 29388
    assert len(cameras) == 10 and all(c.shape == (240, 320) for c in cameras)
    # The face order matches the labels: every ground face lies in the plane z = 0.
    assert np.abs(vertices[triangles[labels == GROUND]][..., 2]).max() < 1e-6


def test_default_proxy_is_close_and_lost_most_foliage(courtyard):
    vertices, triangles, labels, cameras = courtyard
    proxy = simulate_mvs_proxy(vertices, triangles, labels, cameras, rng=0)
    within = np.mean(distance_to_mesh(proxy.vertices, vertices, triangles) <= 0.10)
    assert within >= WITHIN_10CM_MIN
    retained = label_retention(proxy, vertices, triangles, labels, cameras, radius=RETENTION_RADIUS)
    assert retained["foliage"] < FOLIAGE_RETENTION_MAX
    assert retained["solid"] > KEPT_RETENTION_MIN and retained["ground"] > KEPT_RETENTION_MIN
    assert foliage_retention(proxy, vertices, triangles, labels, radius=RETENTION_RADIUS) < FOLIAGE_RETENTION_MAX


def test_same_seed_same_proxy_other_seed_other_proxy(courtyard, fast):
    vertices, triangles, labels, _ = courtyard
    config = ProxyConfig(**FAST)
    again = simulate_mvs_proxy(vertices, triangles, labels, fast.cameras, config=config, rng=np.random.default_rng(0))
    np.testing.assert_array_equal(again.vertices, fast().vertices)
    np.testing.assert_array_equal(again.triangles, fast().triangles)
    other = simulate_mvs_proxy(vertices, triangles, labels, fast.cameras, config=config, rng=1)
    assert other.vertices.shape != again.vertices.shape or not np.array_equal(other.vertices, again.vertices)


def test_without_noise_and_holes_vertices_lie_on_the_surface(courtyard, fast):
    vertices, triangles = courtyard[:2]
    proxy = fast(depth_noise=0.0, hole_rate=0.0, voxel_size=0.04)
    distance = distance_to_mesh(proxy.vertices, vertices, triangles)
    assert np.mean(distance <= 2 * 0.04) >= NOISE_FREE_WITHIN_2VOX_MIN


def test_more_depth_noise_moves_the_surface_farther(courtyard, fast):
    vertices, triangles = courtyard[:2]
    medians = [
        np.median(distance_to_mesh(fast(depth_noise=noise).vertices, vertices, triangles))
        for noise in (0.0, 0.01, 0.03)
    ]
    assert medians[0] < medians[1] < medians[2]


@pytest.mark.parametrize(("knob", "label"), [("foliage_loss", "foliage"), ("thin_loss", "thin")])
def test_loss_knobs_drop_their_class_only(fast, knob, label):
    default, kept = fast.retention(fast()), fast.retention(fast(**{knob: 0.0}))
    assert kept[label] > default[label] + KNOB_GAIN
    assert kept["solid"] == pytest.approx(default["solid"], abs=0.02)
    assert kept["ground"] == pytest.approx(default["ground"], abs=0.02)


def test_fewer_views_reconstruct_less(fast):
    few, all_five = fast(n_views=3), fast()
    assert len(few.vertices) < len(all_five.vertices)
    assert fast.retention(few)["solid"] < fast.retention(all_five)["solid"]


def test_larger_voxels_give_fewer_vertices(fast):
    assert len(fast(voxel_size=0.16).vertices) < 0.5 * len(fast().vertices)


def test_holes_remove_coverage(fast):
    assert fast.retention(fast(hole_rate=0.5))["solid"] < fast.retention(fast(hole_rate=0.0))["solid"] - 0.1


def test_grazing_angle_drops_the_far_ground(fast):
    assert fast.retention(fast(grazing_angle_deg=70.0))["ground"] < 0.5 * fast.retention(fast())["ground"]


def test_views_needed_to_triangulate(fast):
    assert len(fast(min_views=1).vertices) > len(fast().vertices)


def test_small_components_are_removed(fast):
    """Every connected component left has at least min_component_area of surface."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    proxy = fast(min_component_area=1.0)
    v, t = proxy.vertices, proxy.triangles
    graph = coo_matrix((np.ones(2 * len(t)), (np.r_[t[:, 0], t[:, 1]], np.r_[t[:, 1], t[:, 2]])), shape=(len(v),) * 2)
    component = connected_components(graph, directed=False)[1][t[:, 0]]
    area = 0.5 * np.linalg.norm(np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]]), axis=1)
    assert np.bincount(component, weights=area).min() >= 1.0
    assert len(v) < len(fast().vertices)


def test_max_depth_drops_the_far_facade(fast):
    """The facade is about 16 m from the cameras."""
    assert fast.retention(fast(max_depth=10.0))["solid"] < 0.5 * fast.retention(fast())["solid"]


def test_lower_depth_resolution_reconstructs_less(fast):
    assert fast.retention(fast(depth_scale=0.5))["solid"] < fast.retention(fast())["solid"]


# -- bad input ----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("changes", "name"),
    [
        (dict(voxel_size=0.0), "voxel_size"),
        (dict(voxel_size=-0.04), "voxel_size"),
        (dict(depth_noise=-0.01), "depth_noise"),
        (dict(hole_rate=1.0), "hole_rate"),
        (dict(foliage_loss=1.5), "foliage_loss"),
        (dict(thin_loss=-0.1), "thin_loss"),
        (dict(n_views=0), "n_views"),
        (dict(depth_scale=0.0), "depth_scale"),
        (dict(max_depth=0.0), "max_depth"),
        (dict(grazing_angle_deg=95.0), "grazing_angle_deg"),
        (dict(min_views=0), "min_views"),
        (dict(truncation=0.5), "truncation"),
        (dict(voxel_size=float("nan")), "voxel_size"),
    ],
)
def test_bad_config_names_the_field(changes, name):
    with pytest.raises(ValueError, match=name):
        dataclasses.replace(ProxyConfig(), **changes)


def test_bad_inputs_name_the_argument():
    vertices, triangles, labels, cameras = box_scene()
    call = simulate_mvs_proxy
    with pytest.raises(ValueError, match="vertices"):
        call(vertices[:, :2], triangles, labels, cameras)
    with pytest.raises(ValueError, match="vertices"):
        call(np.where(vertices == 0, np.nan, vertices), triangles, labels, cameras)
    with pytest.raises(ValueError, match="triangles"):
        call(vertices, triangles + len(vertices), labels, cameras)
    with pytest.raises(ValueError, match="triangles"):
        call(vertices, triangles[:, :2], labels, cameras)
    with pytest.raises(ValueError, match="face_labels"):
        call(vertices, triangles, labels[:-1], cameras)
    with pytest.raises(ValueError, match="face_labels"):
        call(vertices, triangles, np.full_like(labels, len(LABELS)), cameras)
    with pytest.raises(ValueError, match="cameras"):
        call(vertices, triangles, labels, [])
    with pytest.raises(TypeError, match="cameras"):
        call(vertices, triangles, labels, {"a": cameras[0]})
    with pytest.raises(TypeError, match=r"cameras\[1\]"):
        call(vertices, triangles, labels, [cameras[0], "view"])
    with pytest.raises(TypeError, match="config"):
        call(vertices, triangles, labels, cameras, config={"voxel_size": 0.04})
    with pytest.raises(TypeError, match="rng"):
        call(vertices, triangles, labels, cameras, rng="seed")
    with pytest.raises(ValueError, match="points"):
        distance_to_mesh(np.zeros((4, 2)), vertices, triangles)
    proxy = Proxy(vertices, np.tile([0.0, 0.0, 1.0], (len(vertices), 1)), triangles)
    with pytest.raises(ValueError, match="radius"):
        label_retention(proxy, vertices, triangles, labels, cameras, radius=0.0)
    with pytest.raises(ValueError, match="stride"):
        label_retention(proxy, vertices, triangles, labels, cameras, stride=0)
    with pytest.raises(ValueError, match="n_samples"):
        foliage_retention(proxy, vertices, triangles, labels, n_samples=0)
    with pytest.raises(TypeError, match="proxy"):
        foliage_retention(vertices, vertices, triangles, labels)


def test_nothing_reconstructed_is_an_error():
    """A single view cannot be triangulated (min_views=2)."""
    vertices, triangles, labels, cameras = box_scene()
    with pytest.raises(ValueError, match="nothing was reconstructed"):
        simulate_mvs_proxy(vertices, triangles, labels, cameras[:1], config=EXACT)
