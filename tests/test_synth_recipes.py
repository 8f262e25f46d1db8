"""Synthetic scene recipes and procedural textures: structure, determinism, geometry, visibility.

Fast (no rendering): the scenes are checked through their meshes, an Embree ray cast of the top
image row and the projection of marker points into cameras along the recipe's path.
"""

from __future__ import annotations

import numpy as np
import pytest

import mvintrinsic  # noqa: F401  (loads libusb before open3d)
from mvintrinsic import Camera, Proxy
from mvintrinsic.raytrace import Tracer
from mvintrinsic.synth import textures as tex
from mvintrinsic.synth._geometry import box, frustum, leaf_cluster, sphere
from mvintrinsic.synth.recipes import RECIPES, build_scene
from mvintrinsic.synth.types import LABELS, SynthScene

# Budgets and tolerances, in one place.
MAX_TRIANGLES = 250_000  # per scene (rendering speed)
MAX_TEXTURE_BYTES = 6_000_000  # all albedo textures of a scene, float32
TEXTURE_SIDE = (128, 512)  # pixels per side of every texture
MIN_LEAVES, MAX_LEAVES = 2_000, 20_000  # leaf quads per tree ("several thousand")
MIN_RELATIVE_GRADIENT = 0.005  # median |I(x+1) - I(x)| / mean I: reflectance varies within surfaces
MIN_UNIQUE_VALUES = 1_000  # not piecewise constant
SKY_FRACTION = 0.6  # of the top image row that must see the sky, per camera
N_VIEWS, SPACING = 8, 1.0  # cameras along the path, metres apart
HFOV_DEG, IMAGE_SIZE = 60.0, (64, 48)  # test cameras (4:3)
VISIBLE_VIEWS = 6  # of N_VIEWS in which each main element must project inside the image
WELD_DECIMALS = 6  # vertices closer than 1e-6 m are the same point
CLEARANCE = 0.3  # m between free-standing objects (tree, statue, car, ...) and the buildings

MARKERS = {"pole_base", "pole_top", "facade_corner", "facade_center", "tree_base", "crown_center", "tree_top"}
MAIN_ELEMENTS = {
    "courtyard": ("pole_base", "pole_top", "facade_center", "crown_center", "fence_center", "statue_top"),
    "street": ("pole_base", "pole_top", "facade_center", "facade_b_center", "crown_center", "pergola_center"),
}


@pytest.fixture(scope="module", params=sorted(RECIPES))
def scene(request) -> SynthScene:
    return build_scene(request.param, seed=0)


# -- helpers -------------------------------------------------------------------------------------
def face_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    a, b, c = (vertices[triangles[:, i]] for i in range(3))
    n = np.cross(b - a, c - a)
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def welded(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Triangles re-indexed so that coincident vertices share one index."""
    _, inverse = np.unique(np.round(vertices, WELD_DECIMALS), axis=0, return_inverse=True)
    return inverse.reshape(-1)[triangles]


def is_closed_and_oriented(vertices: np.ndarray, triangles: np.ndarray) -> bool:
    """Every directed edge occurs once and its reverse once: a watertight, consistently oriented
    surface (no holes, no T-junctions, no flipped triangle)."""
    t = welded(vertices, triangles)
    edges = np.concatenate([t[:, [0, 1]], t[:, [1, 2]], t[:, [2, 0]]])
    n = t.max() + 1
    codes = edges[:, 0] * n + edges[:, 1]
    reverse = edges[:, 1] * n + edges[:, 0]
    _, counts = np.unique(codes, return_counts=True)
    return bool((counts == 1).all() and np.array_equal(np.sort(codes), np.sort(reverse)))


def signed_volume(vertices: np.ndarray, triangles: np.ndarray) -> float:
    a, b, c = (vertices[triangles[:, i]] for i in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def look_at_camera(center: np.ndarray, target: np.ndarray) -> Camera:
    """A pinhole camera at ``center`` looking at ``target`` (x right, y down, Z up world)."""
    forward = (target - center) / np.linalg.norm(target - center)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    rotation = np.stack([right, down, forward])
    w, h = IMAGE_SIZE
    f = 0.5 * w / np.tan(np.deg2rad(HFOV_DEG) / 2)
    return Camera("PINHOLE", w, h, [f, f, w / 2, h / 2], rotation, -rotation @ center)


def path_cameras(s: SynthScene) -> list[Camera]:
    offsets = (np.arange(N_VIEWS) - (N_VIEWS - 1) / 2) * SPACING
    return [look_at_camera(s.path.center + o * s.path.direction, s.path.target) for o in offsets]


def tracer_for(s: SynthScene) -> Tracer:
    vertices, triangles, _, _ = s.merged()
    normals = np.zeros_like(vertices)
    np.add.at(normals, triangles.ravel(), np.repeat(face_normals(vertices, triangles), 3, axis=0))
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    normals = np.where(length > 1e-12, normals / np.maximum(length, 1e-12), [0.0, 0.0, 1.0])
    return Tracer(Proxy(vertices, normals, triangles))


def mesh(s: SynthScene, name: str):
    return next(m for m in s.meshes if m.name == name)


# -- structure -----------------------------------------------------------------------------------
def test_scene_structure(scene):
    assert isinstance(scene, SynthScene) and scene.recipe in RECIPES and scene.seed == 0
    for m in scene.meshes:
        assert m.vertices.dtype == np.float64 and m.vertices.shape[1] == 3, m.name
        assert m.triangles.dtype == np.int64 and m.triangles.shape[1] == 3, m.name
        assert m.uvs.dtype == np.float32 and m.uvs.shape == (len(m.vertices), 2), m.name
        assert np.isfinite(m.vertices).all() and np.isfinite(m.uvs).all(), m.name
        assert m.triangles.min() >= 0 and m.triangles.max() < len(m.vertices), m.name
        assert all(a.flags.c_contiguous for a in (m.vertices, m.triangles, m.uvs)), m.name
        assert np.unique(m.triangles).size == len(m.vertices), f"{m.name}: unused vertices"
        a, b, c = (m.vertices[m.triangles[:, i]] for i in range(3))
        assert np.linalg.norm(np.cross(b - a, c - a), axis=1).min() > 1e-8, f"{m.name}: degenerate triangle"


def test_labels_budget_and_textures(scene):
    assert {m.label for m in scene.meshes} == set(LABELS)
    _, triangles, labels, _ = scene.merged()
    assert len(triangles) <= MAX_TRIANGLES
    assert set(np.unique(labels)) == set(range(len(LABELS)))
    assert sum(m.albedo.nbytes for m in scene.materials.values()) <= MAX_TEXTURE_BYTES
    for mat in scene.materials.values():
        h, w, c = mat.albedo.shape
        assert c == 3 and TEXTURE_SIDE[0] <= min(h, w) and max(h, w) <= TEXTURE_SIDE[1], mat.name
        assert mat.albedo.dtype == np.float32
        assert tex.ALBEDO_MIN <= mat.albedo.min() and mat.albedo.max() <= tex.ALBEDO_MAX, mat.name
        assert mat.roughness is None, f"{mat.name}: diffuse by default"
    # Leaves are foliage on a two-sided material; the lamp pole is thin.
    leaves = mesh(scene, "tree_leaves")
    assert leaves.label == "foliage" and scene.materials[leaves.material].two_sided
    assert MIN_LEAVES <= len(leaves.triangles) // 2 <= MAX_LEAVES
    assert mesh(scene, "lamp_pole").label == "thin"


def test_ground_faces_up(scene):
    for m in scene.meshes:
        if m.label == "ground":
            assert face_normals(m.vertices, m.triangles)[:, 2].min() > 0.999, m.name
            assert np.abs(m.vertices[:, 2]).max() < 1e-9, m.name
    # The ground reaches far beyond the square: no hard edge of the world in view.
    far = np.concatenate([m.vertices for m in scene.meshes if m.label == "ground"])
    assert np.linalg.norm(far[:, :2], axis=1).max() > 300.0


def test_markers(scene):
    assert MARKERS <= set(scene.markers)
    for name, point in scene.markers.items():
        assert point.shape == (3,) and point.dtype == np.float64 and np.isfinite(point).all(), name
    base, top = scene.markers["pole_base"], scene.markers["pole_top"]
    np.testing.assert_allclose(top[:2], base[:2])
    assert base[2] == 0.0 and 3.5 <= top[2] - base[2] <= 4.5
    # The markers lie on the axis of the 8 cm shaft, which runs from below the ground to the top.
    pole = mesh(scene, "lamp_pole").vertices
    shaft = pole[np.abs(np.linalg.norm(pole[:, :2] - base[:2], axis=1) - 0.04) < 1e-9]
    assert shaft[:, 2].min() <= base[2] and shaft[:, 2].max() == pytest.approx(top[2])


# -- determinism and validation ------------------------------------------------------------------
@pytest.mark.parametrize("recipe", sorted(RECIPES))
def test_deterministic_per_seed(recipe):
    a, b, c = build_scene(recipe, seed=3), build_scene(recipe, seed=3), build_scene(recipe, seed=4)
    assert [m.name for m in a.meshes] == [m.name for m in b.meshes] == [m.name for m in c.meshes]
    for ma, mb in zip(a.meshes, b.meshes, strict=True):
        np.testing.assert_array_equal(ma.vertices, mb.vertices)
        np.testing.assert_array_equal(ma.triangles, mb.triangles)
        np.testing.assert_array_equal(ma.uvs, mb.uvs)
    for name in a.materials:
        np.testing.assert_array_equal(a.materials[name].albedo, b.materials[name].albedo)
    assert not np.array_equal(mesh(a, "tree_leaves").vertices, mesh(c, "tree_leaves").vertices)
    assert not np.array_equal(a.materials["leaves"].albedo, c.materials["leaves"].albedo)
    assert not np.array_equal(a.markers["pole_base"], c.markers["pole_base"])


@pytest.mark.parametrize("recipe", sorted(RECIPES))
def test_gloss_changes_only_roughness(recipe):
    matte, glossy = build_scene(recipe), build_scene(recipe, gloss=True)
    rough = {n: m.roughness for n, m in glossy.materials.items() if m.roughness is not None}
    assert 2 <= len(rough) < len(glossy.materials) and all(0.0 < r < 1.0 for r in rough.values())
    assert "glass" in rough and "leaves" not in rough
    for name in matte.materials:
        np.testing.assert_array_equal(matte.materials[name].albedo, glossy.materials[name].albedo)


def test_build_scene_validates_arguments():
    with pytest.raises(ValueError, match="courtyard.*street"):
        build_scene("nope")
    with pytest.raises(ValueError, match="seed"):
        build_scene("courtyard", seed=-1)
    with pytest.raises(TypeError, match="seed"):
        build_scene("courtyard", seed="1")
    with pytest.raises(TypeError, match="gloss"):
        build_scene("courtyard", gloss="yes")


# -- geometry ------------------------------------------------------------------------------------
def test_geometry_helpers_are_closed_and_outward():
    solids = {
        "box": (box((0.0, 1.0, 2.0), (2.0, 2.5, 3.0)), 2.0 * 1.5 * 1.0),
        "cylinder": (frustum((1.0, 0.0, 0.0), (1.0, 0.0, 2.0), 0.5, 0.5, segments=64), np.pi * 0.25 * 2.0),
        "cone": (frustum((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), 0.3, 0.0, segments=64), np.pi * 0.09 * np.sqrt(3) / 3),
        "sphere": (sphere((0.0, 0.0, 1.0), 0.7, rings=48, segments=96), 4.0 / 3.0 * np.pi * 0.7**3),
    }
    for name, (part, volume) in solids.items():
        assert is_closed_and_oriented(part.vertices, part.triangles), name
        # Positive signed volume = normals point outward; polygonal approximations lose a little.
        assert signed_volume(part.vertices, part.triangles) == pytest.approx(volume, rel=0.01), name


def test_leaf_cluster_stays_in_its_blob():
    part = leaf_cluster(np.random.default_rng(0), (1.0, 2.0, 4.0), 1.2, 500)
    assert part.vertices.shape == (2000, 3) and part.triangles.shape == (1000, 3)
    centres = part.vertices.reshape(-1, 4, 3).mean(axis=1)
    assert np.linalg.norm(centres - [1.0, 2.0, 4.0], axis=1).max() <= 1.2 + 1e-9


def test_buildings_are_closed_boxes_with_outward_faces(scene):
    for wall in (m for m in scene.meshes if m.name.endswith("_wall")):
        prefix = wall.name[: -len("wall")]
        parts = [wall] + [mesh(scene, prefix + k) for k in ("reveals", "windows", "door")]
        vertices = np.concatenate([p.vertices for p in parts])
        offsets = np.cumsum([0] + [len(p.vertices) for p in parts[:-1]])
        triangles = np.concatenate([p.triangles + o for p, o in zip(parts, offsets, strict=True)])
        assert is_closed_and_oriented(vertices, triangles), wall.name
        assert signed_volume(vertices, triangles) > 0, wall.name
        # The box's own faces (recesses excluded) face away from its centre.
        centre = 0.5 * (wall.vertices.min(axis=0) + wall.vertices.max(axis=0))
        face_centres = wall.vertices[wall.triangles].mean(axis=1)
        outward = np.einsum("ij,ij->i", face_normals(wall.vertices, wall.triangles), face_centres - centre)
        assert (outward > 0).all(), wall.name
        # Windows are recessed: their panes lie behind the wall's front face.
        assert len(mesh(scene, prefix + "windows").triangles) >= 8


def test_closed_solids(scene):
    for name in ("tree_trunk", "statue_plinth", "lamp_pole", "fence", "car_wheels", "bollards"):
        if any(m.name == name for m in scene.meshes):
            m = mesh(scene, name)
            assert signed_volume(m.vertices, m.triangles) > 0, name


@pytest.mark.parametrize("recipe", sorted(RECIPES))
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_free_standing_objects_keep_clear_of_the_buildings(recipe, seed):
    import open3d as o3d

    s = build_scene(recipe, seed=seed)
    buildings = o3d.t.geometry.RaycastingScene()
    for m in s.meshes:
        if m.name.startswith(("facade", "plaque", "shop_sign")):
            buildings.add_triangles(
                o3d.core.Tensor(m.vertices.astype(np.float32)), o3d.core.Tensor(m.triangles.astype(np.uint32))
            )
    for m in s.meshes:
        if m.label != "ground" and not m.name.startswith(("facade", "plaque", "shop_sign")):
            distance = buildings.compute_distance(o3d.core.Tensor(m.vertices.astype(np.float32))).numpy()
            assert distance.min() > CLEARANCE, f"{m.name} within {distance.min():.2f} m of a building"


# -- what the cameras see ------------------------------------------------------------------------
def test_path_is_horizontal_and_at_eye_height(scene):
    path = scene.path
    assert np.linalg.norm(path.direction) == pytest.approx(1.0) and path.direction[2] == 0.0
    assert 1.6 <= path.center[2] <= 2.0


def test_cameras_see_sky_in_the_top_row(scene):
    tracer = tracer_for(scene)
    for cam in path_cameras(scene):
        top_row = np.stack([np.arange(cam.width) + 0.5, np.full(cam.width, 0.5)], axis=1)
        hits = tracer.intersect(cam.center, cam.pixel_rays(top_row))
        assert 1.0 - hits.hit.mean() >= SKY_FRACTION, f"camera at {cam.center}"
        # ... and the ground in the bottom row.
        bottom_row = top_row + [0.0, cam.height - 1.0]
        assert tracer.intersect(cam.center, cam.pixel_rays(bottom_row)).hit.all()


def test_main_elements_are_in_view(scene):
    cams = path_cameras(scene)
    for name in MAIN_ELEMENTS[scene.recipe]:
        point = scene.markers[name][None]
        visible = 0
        for cam in cams:
            pixels, depth = cam.project(point)
            visible += int(depth[0] > 0 and cam.in_image(pixels)[0])
        assert visible >= VISIBLE_VIEWS, f"{name} in view {visible}/{len(cams)} times"


# -- textures ------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", sorted(tex.TEXTURES))
def test_texture_range_variation_and_determinism(name):
    fn = tex.TEXTURES[name]
    image = fn(7)
    assert image.dtype == np.float32 and image.ndim == 3 and image.shape[2] == 3
    assert TEXTURE_SIDE[0] <= min(image.shape[:2]) and max(image.shape[:2]) <= TEXTURE_SIDE[1]
    assert tex.ALBEDO_MIN <= image.min() and image.max() <= tex.ALBEDO_MAX
    # Reflectance varies within surfaces: fine-scale variation everywhere, many distinct values.
    lum = image.mean(axis=2)
    assert np.median(np.abs(np.diff(lum, axis=1))) / lum.mean() > MIN_RELATIVE_GRADIENT
    assert np.median(np.abs(np.diff(lum, axis=0))) / lum.mean() > MIN_RELATIVE_GRADIENT
    assert np.unique(image).size > MIN_UNIQUE_VALUES
    np.testing.assert_array_equal(image, fn(np.random.default_rng(7)))
    assert not np.array_equal(image, fn(8))


def test_brick_varies_within_each_brick():
    image = tex.brick(0, shape=(240, 256), courses=12, columns=4).mean(axis=2)
    # The middle of one brick (course 0, first brick: rows 0-20, columns 0-64), joints excluded.
    inner = image[4:16, 8:56]
    assert inner.std() / inner.mean() > 0.03
    # Per-brick jitter: the mean colour differs between bricks.
    means = [image[4 + 20 * r : 16 + 20 * r, 8:56].mean() for r in range(0, 12, 2)]
    assert np.std(means) / np.mean(means) > 0.05


def test_textures_tile_seamlessly():
    image = tex.paving(0).mean(axis=2)
    # Across the wrap-around seam the step is like any step inside the texture.
    inside = np.abs(np.diff(image, axis=1)).mean()
    assert np.abs(image[:, 0] - image[:, -1]).mean() < 2.0 * inside


def test_sign_has_lettering():
    blank = tex.sign(0, text=" . ")
    lettered = tex.sign(0, text="PLACE DES ARTS")
    ink = lettered.mean(axis=2) > 0.5
    assert ink.mean() > 2.0 * (blank.mean(axis=2) > 0.5).mean()
    with pytest.raises(ValueError, match="text"):
        tex.sign(0, text="")


def test_texture_arguments_are_validated():
    with pytest.raises(ValueError, match="shape"):
        tex.brick(0, shape=(4, 4))
    with pytest.raises(TypeError, match="rng"):
        tex.grass("seed")
    with pytest.raises(ValueError, match="color"):
        tex.plaster(0, color=(2.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="courses"):
        tex.brick(0, courses=3)
