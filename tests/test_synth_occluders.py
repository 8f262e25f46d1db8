"""Recipes without occluders (``build_scene(..., occluders=False)``): a sunny scene with no cast shadow.

The stability study (``benchmarks/bench_stability.py``, ``docs/stability.md``) needs photos that
hold no cast shadow while the sun is on. These tests check the geometry (fast, ray cast against
the exact mesh) and one tiny render end to end.
"""

from __future__ import annotations

import numpy as np
import pytest

import mvintrinsic  # noqa: F401  (loads libusb before open3d)
from mvintrinsic.raytrace import Tracer, sun_visibility
from mvintrinsic.synth.dataset import SynthConfig, _sun_angles, cameras_along_path
from mvintrinsic.synth.recipes import RECIPES, build_scene
from mvintrinsic.synth.render import sun_vector
from mvintrinsic.synth.types import LABELS

N_VIEWS, IMAGE_SIZE = 8, (96, 72)  # cameras along the recipe's path, pixels
FRONT_SUNS = {"street": (-115.0, 50.0), "courtyard": (-90.0, 40.0)}  # azimuth, elevation in front of the facades
BUILDING_PARTS = {"street": {"facade_a_wall", "facade_b_wall"}, "courtyard": {"facade_wall"}}


def cast_shadow_fraction(scene, sun: np.ndarray) -> float:
    """Fraction of the pixels of ``N_VIEWS`` cameras on a surface facing ``sun`` but occluded."""
    tracer = Tracer(scene.exact_proxy())
    cast = total = 0
    for camera in cameras_along_path(scene.path, n_views=N_VIEWS, width=IMAGE_SIZE[0], height=IMAGE_SIZE[1]):
        hits = tracer.intersect(camera.center, camera.pixel_rays())
        idx = np.flatnonzero(hits.hit)
        lit = sun_visibility(hits.points[idx], hits.normals[idx], sun, tracer, ray_offset=1e-3) > 0
        facing = hits.normals[idx] @ sun > 0
        cast += int(np.sum(facing & ~lit))
        total += len(hits.hit)
    return cast / total


@pytest.mark.parametrize("recipe", sorted(RECIPES))
def test_only_ground_and_plain_buildings(recipe):
    full, plain = build_scene(recipe, seed=0), build_scene(recipe, seed=0, occluders=False)
    names = {m.name for m in plain.meshes}
    assert names == {m.name for m in full.meshes if m.label == "ground"} | BUILDING_PARTS[recipe]
    assert {m.label for m in plain.meshes} == {"ground", "solid"}
    assert LABELS.index("foliage") not in plain.merged()[2]
    # same path, textures and building markers as the full recipe
    np.testing.assert_array_equal(plain.path.target, full.path.target)
    for name, material in plain.materials.items():
        np.testing.assert_array_equal(material.albedo, full.materials[name].albedo)
    for name, point in plain.markers.items():
        np.testing.assert_array_equal(point, full.markers[name])
    for mesh in plain.meshes:  # each building a plain box: 6 faces, 2 triangles each
        assert mesh.label == "ground" or len(mesh.triangles) == 12, mesh.name


@pytest.mark.parametrize("recipe", sorted(RECIPES))
def test_sun_in_front_casts_no_shadow_in_view(recipe):
    sun = sun_vector(*FRONT_SUNS[recipe])
    assert cast_shadow_fraction(build_scene(recipe, seed=0, occluders=False), sun) == 0.0
    assert cast_shadow_fraction(build_scene(recipe, seed=0), sun) > 0.005  # the full recipe has shadows


def test_street_seed_sun_casts_no_shadow():
    """The street's seed-0 sun (that of the stability study's base scene) casts none without occluders."""
    plain = build_scene("street", seed=0, occluders=False)
    assert cast_shadow_fraction(plain, sun_vector(*_sun_angles(plain, SynthConfig(seed=0)))) == 0.0


def test_occluders_is_validated():
    with pytest.raises(TypeError, match="occluders must be a bool"):
        build_scene("street", occluders="no")


def test_tiny_render_without_occluders(tmp_path):
    """The gt sun visibility is lit wherever a surface faces the sun, and scene_info.json is valid
    JSON although no foliage exists (its retention is None)."""
    pytest.importorskip("mitsuba", reason="Mitsuba 3 is not installed (pip install 'mvintrinsic[render]')")
    from mvintrinsic.evaluation import read_ground_truth
    from mvintrinsic.synth.dataset import synthesize
    from mvintrinsic.synth.proxy import ProxyConfig
    from mvintrinsic.synth.render import RenderConfig

    config = SynthConfig(n_views=2, width=64, height=48, relit=(), occluders=False,
                         render=RenderConfig(spp=4, sun_spp=4, max_depth=2), proxy=ProxyConfig(voxel_size=0.1))
    info = synthesize("street", tmp_path / "scene", config=config, progress=False)
    assert info["config"]["occluders"] is False
    assert info["proxy"]["foliage_retention"] is None and info["proxy"]["retention_seen"]["foliage"] is None
    truth = read_ground_truth(tmp_path / "scene")["view_000"]
    assert truth.sky_mask.any() and np.array_equal(truth.sun_visibility, ~truth.sky_mask)
