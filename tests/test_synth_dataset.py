"""Synthetic datasets end to end: tiny renders written as a scene folder, checked layer by layer."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("mitsuba", reason="Mitsuba 3 is not installed (pip install 'mvintrinsic[render]')")

from mvintrinsic import load_scene  # noqa: E402
from mvintrinsic.evaluation import evaluate, ground_truth_decomposition  # noqa: E402
from mvintrinsic.io import read_image, read_proxy, save_decomposition  # noqa: E402
from mvintrinsic.raytrace import Tracer  # noqa: E402
from mvintrinsic.synth.dataset import SynthConfig, cameras_along_path, synthesize, with_overrides  # noqa: E402
from mvintrinsic.synth.proxy import ProxyConfig, distance_to_mesh, foliage_retention, simulate_mvs_proxy  # noqa: E402
from mvintrinsic.synth.recipes import RECIPES, build_scene  # noqa: E402
from mvintrinsic.synth.render import RenderConfig  # noqa: E402

PRODUCT_TOL = 0.01  # image == reflectance * shading (issue 3), where reflectance > 0.05
SUM_TOL = 0.02  # sun_shading + env_shading == shading (issue 3)
SHADOW_CONTRAST_MIN = 2.0  # GT-shadowed pixels of one material are > 2x darker than lit ones
PROXY_WITHIN_10CM_MIN = 0.80  # default proxy: fraction of vertices within 10 cm of the GT mesh
FOLIAGE_RETENTION_MAX = 0.5  # default proxy has lost most foliage

TINY = SynthConfig(n_views=2, width=128, height=96, relit=("az+15",),
                   render=RenderConfig(spp=16, sun_spp=16, max_depth=4),
                   proxy=ProxyConfig(voxel_size=0.08))


@pytest.fixture(scope="module", params=sorted(RECIPES))
def tiny(request, tmp_path_factory):
    out = tmp_path_factory.mktemp(request.param) / "scene"
    info = synthesize(request.param, out, config=TINY, progress=False)
    return out, info


def layer(folder, name, stem):
    ext = "png" if name in ("sun_visibility", "sky_mask") else "exr"
    return read_image(folder / "gt" / name / f"{stem}.{ext}")[0]


def test_scene_folder_loads_and_is_complete(tiny):
    out, info = tiny
    scene = load_scene(out)
    assert scene.stems == ("view_000", "view_001")
    assert scene.views[0].shape == (96, 128)
    np.testing.assert_allclose(scene.sun.direction, info["sun_direction"], atol=1e-12)
    assert 30.0 <= info["sun_elevation_deg"] <= 55.0
    for name in ("reflectance", "shading", "sun_shading", "env_shading", "sun_visibility", "sky_mask"):
        assert (out / "gt" / name).is_dir()
    assert (out / "gt" / "relit" / "az+15" / "images" / "view_000.exr").is_file()
    assert (out / "proxy_clean.ply").is_file() and (out / "gt" / "mesh.ply").is_file()
    assert not (out / ".render-cache").exists()


def test_image_is_reflectance_times_shading(tiny):
    out, _ = tiny
    for stem in ("view_000", "view_001"):
        image = read_image(out / "images" / f"{stem}.exr")[0]
        reflectance, shading = layer(out, "reflectance", stem), layer(out, "shading", stem)
        ok = reflectance > 0.05
        assert ok.mean() > 0.3
        product = reflectance * shading
        assert np.all(np.abs(product[ok] - image[ok]) <= PRODUCT_TOL * np.abs(image[ok]) + 1e-6)


def test_sun_plus_environment_is_the_shading(tiny):
    out, _ = tiny
    for stem in ("view_000", "view_001"):
        shading = layer(out, "shading", stem)
        total = layer(out, "sun_shading", stem) + layer(out, "env_shading", stem)
        ok = layer(out, "reflectance", stem) > 0.05
        assert np.all(np.abs(total[ok] - shading[ok]) <= SUM_TOL * np.abs(shading[ok]) + 1e-6)


def test_shadowed_pixels_of_one_material_are_much_darker(tiny):
    """On the material with the most cast shadow in view, shadowed pixels are > 2x darker.

    Only surfaces facing the sun (cos > 0.2) count, so the shadow is a cast one. Masks are eroded
    by one pixel: visibility is decided at the pixel centre while the image averages the whole
    pixel, so boundary pixels mix light and shadow.
    """
    from scipy.ndimage import binary_erosion

    out, info = tiny
    scene = load_scene(out)
    faces = np.load(out / "gt" / "mesh_faces.npz")
    tracer = Tracer(read_proxy(out / "gt" / "mesh.ply"))  # triangle order = mesh_faces.npz order
    lit_values, shadow_values = {}, {}
    for view in scene.views:
        hits = tracer.intersect(view.camera.center, view.camera.pixel_rays())
        facing = (hits.hit & (hits.normals @ np.asarray(info["sun_direction"]) > 0.2)).reshape(view.shape)
        material = np.where(hits.hit, faces["material"][np.maximum(hits.triangle, 0)], -1).reshape(view.shape)
        lit = layer(out, "sun_visibility", view.stem)[..., 0] > 0.5
        luminance = view.image.mean(axis=2)
        for m in np.unique(material[facing]):
            here = facing & (material == m)
            lit_values.setdefault(m, []).append(luminance[binary_erosion(here & lit)])
            shadow_values.setdefault(m, []).append(luminance[binary_erosion(here & ~lit)])
    shadowed = {m: np.concatenate(v) for m, v in shadow_values.items()}
    m = max(shadowed, key=lambda k: len(shadowed[k]))
    assert len(shadowed[m]) >= 20, "no material has cast-shadow pixels in view"
    ratio = np.median(np.concatenate(lit_values[m])) / np.median(shadowed[m])
    assert ratio > SHADOW_CONTRAST_MIN, (faces["material_names"][m], ratio)


def test_relit_sun_moves_the_shadows(tiny):
    out, _ = tiny
    before = layer(out, "sun_visibility", "view_000")
    after = read_image(out / "gt" / "relit" / "az+15" / "sun_visibility" / "view_000.png")[0]
    assert 0 < np.mean(before != after) < 0.5
    image = read_image(out / "images" / "view_000.exr")[0]
    relit = read_image(out / "gt" / "relit" / "az+15" / "images" / "view_000.exr")[0]
    assert not np.allclose(image, relit, rtol=0.05)


def test_ground_truth_scores_itself_perfectly(tiny, tmp_path):
    out, _ = tiny
    result = save_decomposition(ground_truth_decomposition(out), tmp_path / "gt-result")
    scores = evaluate(out, result)
    assert scores["mean"]["lmse_score"] < 1e-10
    assert scores["mean"]["ber"] == 0.0


def test_default_proxy_is_close_and_loses_foliage():
    """The default MVS simulation on the default camera path of each recipe (no rendering)."""
    for recipe in sorted(RECIPES):
        scene = build_scene(recipe, seed=0)
        cameras = cameras_along_path(scene.path, n_views=8, width=320, height=240)
        vertices, triangles, labels, _ = scene.merged()
        proxy = simulate_mvs_proxy(vertices, triangles, labels, cameras, config=ProxyConfig(), rng=0)
        within = np.mean(distance_to_mesh(proxy.vertices, vertices, triangles) <= 0.10)
        assert within >= PROXY_WITHIN_10CM_MIN, recipe
        assert foliage_retention(proxy, vertices, triangles, labels) < FOLIAGE_RETENTION_MAX, recipe


def test_config_validation_and_overrides():
    # The suns bench_relight scores relighting at (issue 15).
    assert SynthConfig().relit == ("az+15", "az-15", "az+30", "az-30", "el+10")
    with pytest.raises(ValueError, match="relit tag"):
        SynthConfig(relit=("sideways",))
    with pytest.raises(ValueError, match="n_views"):
        SynthConfig(n_views=0)
    with pytest.raises(ValueError, match="recipe"):
        synthesize("nope", "/nonexistent/never-written", config=TINY)
    config = with_overrides(TINY, proxy_voxel_size=0.1, render_spp=4, n_views=3)
    assert (config.proxy.voxel_size, config.render.spp, config.n_views) == (0.1, 4, 3)


def test_cli_synth(tmp_path, capsys):
    from mvintrinsic.cli import main

    out = tmp_path / "cli"
    args = ["synth", "courtyard", str(out), "--views", "2", "--size", "48x36", "--spp", "2", "--relit", "none",
            "--degrade", "voxel_size=0.1", "--degrade", "depth_noise=0.02", "--sun=-100,40", "--quiet"]
    assert main(args) == 0
    printed = capsys.readouterr().out
    assert "seconds per render" in printed and "azimuth -100.0" in printed
    assert load_scene(out).views[0].shape == (36, 48)
    assert main(args) == 2  # OUT is not empty now
    assert "overwrite" in capsys.readouterr().err
    assert main(["synth", "courtyard", str(tmp_path / "x"), "--degrade", "wobble=3"]) == 2
    assert "unknown knob 'wobble'" in capsys.readouterr().err
