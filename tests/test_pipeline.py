"""The Steps 1-3 pipeline: configuration, per-pixel quantities, decompose(), and the decompose CLI."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest

from mvintrinsic import Config, Scene, View, decompose, load_decomposition, load_scene, model_choice, pipeline
from mvintrinsic.cli import demo_scene_path, main
from mvintrinsic.env_refine import EnvRefineConfig
from mvintrinsic.env_shading import Step1Config, step1
from mvintrinsic.pipeline import carry_to_pixels
from mvintrinsic.raytrace import Tracer, depth_map
from mvintrinsic.sun_calibration import SunCalibrationError, SunConfig

RECONSTRUCTION_TOL = 1e-4  # issue 5: reflectance * shading == image on valid pixels


@pytest.fixture(scope="module")
def demo_scene():
    return load_scene(demo_scene_path())


@pytest.fixture(scope="module")
def demo_result(demo_scene):
    return decompose(demo_scene)


@pytest.fixture(scope="module")
def plain_result(demo_scene):
    """Without the occluder carving (which runs Steps 2-3 again on the demo and moves L_sun)."""
    return decompose(demo_scene, config=Config(occluders=None))


def test_config_round_trips_and_reads_partial_mappings():
    config = Config()
    assert Config.from_dict(json.loads(json.dumps(config.to_dict()))) == config
    partial = Config.from_dict({"sun": {"walk": 20}, "step1": {"n_rays": 32, "sky": {"envmap_height": 32}}})
    assert partial.sun == replace(SunConfig(), walk=20)
    assert partial.step1.n_rays == 32 and partial.step1.sky.envmap_height == 32
    assert partial.step1.subsample == Step1Config().subsample


@pytest.mark.parametrize("data, match", [
    ({"sunn": {}}, r"config: unknown key\(s\) \['sunn'\]"),
    ({"sun": {"walkk": 3}}, r"config\.sun: unknown key\(s\) \['walkk'\]"),
    ({"sun": {"walk": 0}}, r"config\.sun: walk must be"),
    ({"sun": 3}, r"config: sun must be a SunConfig"),
])
def test_config_errors_name_the_key(data, match):
    with pytest.raises(ValueError, match=match):
        Config.from_dict(data)


def test_decompose_reproduces_every_image(demo_scene, demo_result):
    assert demo_result.stems == tuple(v.stem for v in demo_scene.views)
    for view in demo_scene.views:
        layers = demo_result.layers[view.stem]
        for name in ("reflectance", "sun_shading", "sky_shading", "indirect_shading", "visibility"):
            assert np.isfinite(getattr(layers, name)).all(), name
        estimated = layers.shadow_labels != 128
        assert estimated.mean() > 0.5
        difference = np.abs(layers.reconstruct()[estimated] - view.image[estimated])
        assert difference.max() <= RECONSTRUCTION_TOL * max(1.0, float(view.image[estimated].max()))
        assert (layers.reflectance[~estimated] == 0).all()


def test_decompose_records_lighting_timings_and_config(demo_result):
    lighting = demo_result.lighting
    assert (lighting.sun_radiance > 0).all()
    assert lighting.sky.model in ("constant", "preetham", "perez") and lighting.envmap is not None
    for stage in ("step1.environment_shading", "step1.vertex_radiance", "pixels", "sun_pairs", "shadow_labels",
                  "shadow_labels.evidence", "shadow_labels.correspondences", "shadow_labels.palette",
                  "shadow_labels.graph_cut", "segmentation", "matting"):
        assert stage in demo_result.timings
    assert "shadow_mrf" not in demo_result.timings
    assert demo_result.config == Config()  # the Config itself (issue 19), not a mapping


def test_the_papers_labelling_stays_selectable(demo_scene, demo_result, plain_result):
    config = Config.from_dict({"shadow": {"method": "paper"}, "occluders": None})
    assert config.shadow.method == "paper" and Config().shadow.method == "multiview"
    paper = decompose(demo_scene, config=config)
    assert "shadow_mrf" in paper.timings and "shadow_labels" not in paper.timings
    np.testing.assert_array_equal(paper.lighting.sun_radiance, plain_result.lighting.sun_radiance)
    stem = demo_scene.views[0].stem
    assert not np.array_equal(paper.layers[stem].shadow_labels, demo_result.layers[stem].shadow_labels)
    with pytest.raises(ValueError, match="method must be one of"):
        Config.from_dict({"shadow": {"method": "best"}})
    partial = Config.from_dict({"multiview": {"iterations": 1, "palette_bins": [0.2, 0.05, 0.05]}})
    assert partial.multiview.iterations == 1 and partial.multiview.palette_bins == (0.2, 0.05, 0.05)


def test_step3_view_needs_the_multiview_labels(demo_scene):
    from mvintrinsic.pipeline import step3_view

    tracer = Tracer(demo_scene.proxy)
    view = demo_scene.views[0]
    quantities = carry_to_pixels(demo_scene, step1(demo_scene, tracer=tracer, rng=0), tracer)
    with pytest.raises(ValueError, match="labels: the multi-view labelling needs"):
        step3_view(view, quantities[view.stem], np.ones(3))


def test_steps_2_stops_after_the_sun_calibration(demo_scene, demo_result, plain_result):
    step2 = decompose(demo_scene, config=Config(steps=2))
    assert "layers" in step2.timings and "matting" not in step2.timings
    assert "occluders" not in step2.lighting.model  # the carving needs Step 3's labels
    np.testing.assert_array_equal(step2.lighting.sun_radiance, plain_result.lighting.sun_radiance)
    view = demo_scene.views[0]
    # Step 2 labels are the proxy visibility thresholded; Step 3 relabels
    assert not np.array_equal(step2.layers[view.stem].shadow_labels, demo_result.layers[view.stem].shadow_labels)
    with pytest.raises(ValueError, match="steps must be 2, 3 or 4"):
        Config(steps=5)



def test_step_4_runs_by_default_and_steps_3_stops_before_it(demo_scene, demo_result):
    step3_result = decompose(demo_scene, config=Config(steps=3))
    assert "step4" in demo_result.timings and "step4.fusion" in demo_result.timings
    assert not any(k.startswith("step4") for k in step3_result.timings)
    changed = 0
    for view in demo_scene.views:
        four, three = demo_result.layers[view.stem], step3_result.layers[view.stem]
        # Step 4 keeps the labels and v_sun, and Eq. 1: R * S_tot reproduces the image.
        np.testing.assert_array_equal(four.shadow_labels, three.shadow_labels)
        np.testing.assert_array_equal(four.visibility, three.visibility)
        np.testing.assert_allclose(four.reconstruct(), three.reconstruct(), rtol=1e-4, atol=1e-6)
        changed += int((four.reflectance != three.reflectance).any())
    assert changed == len(demo_scene.views)
    paper = decompose(demo_scene, config=Config(env_refine=EnvRefineConfig(method="paper")))
    assert "step4.offsets" in paper.timings

def test_pixel_quantities_split_sky_covered_and_filled(demo_scene):
    tracer = Tracer(demo_scene.proxy)
    s1 = step1(demo_scene, tracer=tracer, rng=0)
    quantities = carry_to_pixels(demo_scene, s1, tracer)
    for view in demo_scene.views:
        q = quantities[view.stem]
        covered = np.isfinite(q.depth)
        assert not (q.sky_mask & covered).any() and not (q.filled & covered).any()
        np.testing.assert_array_equal(q.valid, view.mask & ~q.sky_mask)
        assert q.sky_mask.mean() > 0.05  # the demo's views all show sky
        assert np.isfinite(q.sky).all() and (q.sky[q.valid] > 0).any()
        cos = np.einsum("hwc,c->hw", q.normals, demo_scene.sun.direction)
        np.testing.assert_allclose(q.cosine[q.valid], np.maximum(cos[q.valid], 0), atol=1e-6)



def test_a_surface_against_the_sky_that_the_proxy_lost_is_not_sky(demo_scene):
    # Pixels whose rays miss the proxy toward the sky but whose colour is not the sky's (a tree
    # crown the MVS proxy lost) are surfaces ("filled"), not sky (Step1Config.sky_colour_tolerance).
    from mvintrinsic.pixels import pixel_quantities

    tracer = Tracer(demo_scene.proxy)
    s1 = step1(demo_scene, tracer=tracer, rng=0)
    view = demo_scene.views[0]
    before = pixel_quantities(view, s1, tracer, sun_direction=demo_scene.sun.direction)
    rows, cols = np.nonzero(before.sky_mask)
    painted = np.zeros(view.shape, dtype=bool)
    painted[rows[:300], cols[:300]] = True
    image = view.image.copy()
    image[painted] = (0.03, 0.06, 0.015)  # dark foliage green
    crown = replace(view, image=image)
    after = pixel_quantities(crown, s1, tracer, sun_direction=demo_scene.sun.direction)
    assert after.filled[painted].all() and after.valid[painted].all() and not after.sky_mask[painted].any()
    np.testing.assert_array_equal(after.sky_mask[~painted], before.sky_mask[~painted])
    assert before.sky_mask.sum() - after.sky_mask.sum() == painted.sum()
    # The direction alone (the behaviour before the colour test) keeps them sky.
    direction_only = replace(s1, config=Step1Config(sky_colour_tolerance=None))
    old = pixel_quantities(crown, direction_only, tracer, sun_direction=demo_scene.sun.direction)
    assert old.sky_mask[painted].all()
    with pytest.raises(ValueError, match="sky_colour_tolerance"):
        Step1Config(sky_colour_tolerance=0.0)

def flat_scene(scene: Scene) -> Scene:
    """The scene with every pixel that sees the proxy set to one grey: no shadow edge anywhere."""
    tracer = Tracer(scene.proxy)
    views = []
    for v in scene.views:
        covered = np.isfinite(depth_map(v.camera, tracer))
        image = np.where(covered[..., None], np.float32(0.2), v.image).astype(np.float32)
        views.append(View(v.stem, image, v.camera, v.mask))
    return Scene(views, scene.proxy, scene.sun, scene.up)


def test_no_shadow_boundary_records_no_direct_sun_or_fails_loudly(demo_scene):
    scene = flat_scene(demo_scene)
    # The default decides from the data: no pair and no contrast across the proxy's shadow edges.
    result = decompose(scene)
    sun = result.lighting.model["sun"]
    assert sun.choice == "no direct sun" and sun.measures["pairs"] == 0
    assert sun.measures["contrast"] < 1.5  # one grey: no contrast beyond what S_env explains
    # no shadow boundary: nothing for the S_env refinement, but the reflectance is fused across views
    assert result.lighting.model["step4"].choice == "fusion only" and "step4.fusion" in result.timings
    assert (result.lighting.sun_radiance == 0).all()
    for view in scene.views:
        layers = result.layers[view.stem]
        assert np.isfinite(layers.reflectance).all() and np.isfinite(layers.shading).all()
        valid = layers.shadow_labels != 128
        assert (layers.shadow_labels[valid] == 255).all() and (layers.sun_shading == 0).all()
        np.testing.assert_allclose(layers.reconstruct()[valid], view.image[valid], rtol=1e-4, atol=1e-6)
    # The paper's Step 4 (S_env offsets at shadow boundaries) is skipped outright.
    offsets = decompose(scene, config=Config(env_refine=EnvRefineConfig(method="paper")))
    assert offsets.lighting.model["step4"].choice == "skipped" and "step4" not in offsets.timings
    # The paper's assumption (direct sun always) fails loudly, or falls back when asked.
    paper = Config(sun=SunConfig(direct_sun="always"))
    with pytest.raises(SunCalibrationError, match="allow_missing_sun=True"):
        decompose(scene, config=paper)
    with pytest.warns(RuntimeWarning, match="L_sun = 0"):
        result = decompose(scene, config=replace(paper, allow_missing_sun=True))
    assert (result.lighting.sun_radiance == 0).all() and "sun" not in result.lighting.model


def test_sunny_demo_records_direct_sun_and_step4(demo_result):
    model = demo_result.lighting.model
    assert model["sun"].choice == "direct sun"
    assert model["sun"].measures["contrast"] > 2.0 and model["sun"].measures["pairs"] > 10
    assert model["sun"].measures["warmth"] > Config().sun.sun_warmth  # the sun is warmer than the sky light
    assert model["step4"].choice == "run" and model["step4"].measures["boundary_pixels"] > 100
    sky = model["sky"]  # the family by its held-out error, recorded with it
    assert sky.choice == demo_result.lighting.sky.model and sky.measures["chosen_by"] == "held-out error"
    errors = sky.measures["held_out_error"]
    assert set(errors) == {"constant", "preetham", "perez"} and errors[sky.choice] <= min(errors.values()) * 1.05


def test_presets_are_configs_and_unknown_names_are_refused():
    balanced = Config.preset("balanced")
    assert balanced.max_side == pipeline.BALANCED_SIDE and replace(balanced, max_side=None) == Config()
    fast, paper = Config.preset("fast"), Config.preset("paper")
    assert fast.max_side == pipeline.FAST_SIDE and fast.step1.n_rays < Config().step1.n_rays and fast.matting is None
    assert paper.shadow.method == "paper" and paper.env_refine.method == "paper"
    assert paper.exposure.method == "none" and paper.step1.normal_smoothing == 0.0
    assert paper.step1.sky.model == "preetham" and paper.sun.direct_sun == "always" and paper.max_side is None
    assert Config.preset("best").step1.n_rays > Config().step1.n_rays
    assert Config.from_dict(fast.to_dict()) == fast
    with pytest.raises(ValueError, match="preset must be one of"):
        Config.preset("fastest")
    with pytest.raises(ValueError, match="scale"):
        Config(scale=0.0)
    with pytest.raises(ValueError, match="scale"):
        Config(scale=1.5)
    with pytest.raises(ValueError, match="max_side"):
        Config(max_side=0)


def test_working_scale_and_no_matting_keep_layers_consistent(demo_scene, monkeypatch):
    scene = Scene(demo_scene.views[:2], demo_scene.proxy, demo_scene.sun, demo_scene.up)
    assert pipeline.working_scale(scene, 0.5) == 1.0  # 240x180 views stay whole (MIN_WORKING_SIDE)
    assert pipeline.working_scale(scene, 1.0, 640) == 1.0  # smaller than max_side: whole
    big = Scene(tuple(View(v.stem, np.zeros((750, 1000, 3), np.float32), v.camera.scaled(1000, 750))
                      for v in scene.views), scene.proxy, scene.sun, scene.up)
    assert pipeline.working_scale(big, 1.0, 640) == 0.64 and pipeline.working_scale(big, 0.5, 640) == 0.5
    assert pipeline.working_scale(big, 1.0, 100) == 0.4  # MIN_WORKING_SIDE / 1000
    monkeypatch.setattr(pipeline, "MIN_WORKING_SIDE", 100)
    assert pipeline.working_scale(scene, 0.5) == 0.5
    for config in (Config(scale=0.5, steps=3), Config(matting=None, steps=3)):
        result = decompose(scene, config=config)
        for view in scene.views:
            layers = result.layers[view.stem]
            assert layers.shape == view.shape
            valid = layers.shadow_labels != 128
            assert valid.mean() > 0.5
            for name in ("reflectance", "sun_shading", "sky_shading", "indirect_shading", "visibility"):
                assert np.isfinite(getattr(layers, name)).all(), name
            np.testing.assert_allclose(layers.reconstruct()[valid], view.image[valid], rtol=1e-3, atol=1e-5)
        assert ("upsample" in result.timings) == (config.scale < 1)
        if config.matting is None:
            assert "matting" not in result.timings


def test_cli_decompose_writes_a_result_folder(tmp_path):
    config = tmp_path / "config.json"
    config.write_text(json.dumps({"sun": {"walk": 25}}))
    out = tmp_path / "result"
    code = main(["decompose", str(demo_scene_path()), str(out), "--views", "view_004", "view_005",
                 "--config", str(config), "--quiet"])
    assert code == 0
    result = load_decomposition(out)
    assert result.stems == ("view_004", "view_005")
    assert result.layers["view_004"].shape == (180, 240)
    assert isinstance(result.config, Config) and result.config.sun.walk == 25  # read back as a Config
    saved = json.loads((out / "lighting.json").read_text())
    assert saved["sun_radiance"] == pytest.approx(result.lighting.sun_radiance.tolist())


def test_cli_decompose_max_size_and_missing_sun(tmp_path, capsys):
    out = tmp_path / "small"
    args = ["decompose", str(demo_scene_path()), str(out), "--views", "view_001", "--max-size", "160", "--quiet"]
    # At 160 px this one view has no surviving light/shadow pair, but its proxy's shadow edges show
    # sun: not taken for an overcast scene, the paper's assumption fails loudly.
    assert main(args) == 2
    assert "allow_missing_sun=True" in capsys.readouterr().err and not out.exists()
    with pytest.warns(RuntimeWarning, match="L_sun = 0"):
        assert main([*args, "--allow-missing-sun"]) == 0
    result = load_decomposition(out)
    assert result.layers["view_001"].shape == (120, 160)
    assert (result.lighting.sun_radiance == 0).all()
    sun = result.lighting.model["sun"]
    assert sun.choice == "unknown" and sun.measures["pairs"] == 0 and sun.measures["contrast"] > 2.0


def test_cli_refuses_a_bad_output_before_any_work(tmp_path, capsys, monkeypatch):
    """Issue 18: OUT that is a file, inside the scene or a foreign folder is refused before decomposing."""
    import mvintrinsic.pipeline

    def never(*args, **kwargs):
        raise AssertionError("decomposed before checking OUT")

    monkeypatch.setattr(mvintrinsic.pipeline, "decompose", never)
    a_file = tmp_path / "out.txt"
    a_file.write_text("x")
    foreign = tmp_path / "notes"
    foreign.mkdir()
    (foreign / "thesis.tex").write_text("precious")
    demo = demo_scene_path()
    for out, message in ((a_file, "is not a folder"), (demo / "result", "inside the scene folder"),
                         (foreign, "not written by mvintrinsic")):
        assert main(["decompose", str(demo), str(out), "--quiet"]) == 2
        err = capsys.readouterr().err
        assert str(out.resolve()) in err and message in err
        assert main(["relight", str(demo), str(tmp_path), str(out), "--azimuth", "0", "--elevation", "30"]) == 2
        assert message in capsys.readouterr().err
    assert main(["demo", "--out", str(a_file)]) == 2
    assert "is not a folder" in capsys.readouterr().err
    assert a_file.read_text() == "x" and [p.name for p in foreign.iterdir()] == ["thesis.tex"]
    assert not (demo / "result").exists()


def test_cli_ctrl_c_is_a_short_message(tmp_path, capsys, monkeypatch):
    import mvintrinsic.pipeline

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(mvintrinsic.pipeline, "decompose", interrupted)
    assert main(["decompose", str(demo_scene_path()), str(tmp_path / "out"), "--quiet"]) == 130
    err = capsys.readouterr().err
    assert err.strip() == "mvintrinsic decompose: interrupted" and not (tmp_path / "out").exists()


@pytest.mark.parametrize("content, suffix, message", [
    ("{not json", ".json", "not valid JSON"),
    ("sun = {walkk = 3}", ".toml", r"unknown key\(s\) \['walkk'\]"),
])
def test_cli_decompose_names_a_bad_config_file(tmp_path, capsys, content, suffix, message):
    config = tmp_path / f"config{suffix}"
    config.write_text(content)
    code = main(["decompose", str(demo_scene_path()), str(tmp_path / "out"), "--config", str(config), "--quiet"])
    assert code == 2
    err = capsys.readouterr().err
    assert str(config) in err
    assert re.search(message, err)
    assert not (tmp_path / "out").exists()


def test_cli_decompose_on_dev_courtyard(dev_courtyard, tmp_path):
    """Issue 5: ``mvintrinsic decompose`` on data we did not write; R * S == I on valid pixels."""
    out = tmp_path / "dev"
    run = subprocess.run([sys.executable, "-m", "mvintrinsic.cli", "decompose", str(dev_courtyard), str(out), "--quiet"],
                         capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    result = load_decomposition(out)
    scene = load_scene(dev_courtyard)
    assert result.stems == tuple(v.stem for v in scene.views)
    for view in scene.views:
        layers = result.layers[view.stem]
        estimated = (layers.shadow_labels != 128) & view.mask
        assert estimated.mean() > 0.5
        difference = np.abs(layers.reconstruct()[estimated] - view.image[estimated])
        assert difference.max() <= RECONSTRUCTION_TOL * max(1.0, float(view.image[estimated].max()))


def test_step4_choice_counts_cast_shadow_boundaries_only():
    from types import SimpleNamespace

    labels = np.full((40, 60), 255, np.uint8)
    labels[:, 30:] = 0  # a vertical shadow boundary, 40 boundary pixels
    cosine = np.full((40, 60), 0.7)
    layers = {"a": SimpleNamespace(shadow_labels=labels)}
    cast = model_choice.choose_step4(layers, EnvRefineConfig(), {"a": SimpleNamespace(cosine=cosine)}, views=2)
    assert cast.choice == "run" and cast.measures["boundary_pixels"] == 40 and cast.measures["attached_pixels"] == 0
    # the shadow side turned away from the sun: a crease (attached shadow), not a cast shadow
    turned = np.where(np.arange(60) >= 30, 0.05, 0.7)[None, :].repeat(40, axis=0)
    crease = model_choice.choose_step4(layers, EnvRefineConfig(), {"a": SimpleNamespace(cosine=turned)}, views=2)
    assert crease.choice == "fusion only" and crease.measures["boundary_pixels"] == 0
    assert crease.measures["attached_pixels"] == 40
    paper = model_choice.choose_step4(layers, EnvRefineConfig(method="paper"), {"a": SimpleNamespace(cosine=turned)},
                                   views=2)
    assert paper.choice == "skipped"
    single = model_choice.choose_step4(layers, EnvRefineConfig(), {"a": SimpleNamespace(cosine=turned)}, views=1)
    assert single.choice == "skipped"


def test_cast_shadow_choice_from_the_proxys_shadow_edges(demo_scene):
    from types import SimpleNamespace

    views = demo_scene.views[:2]
    scene = Scene(views, demo_scene.proxy, demo_scene.sun, demo_scene.up)
    size = sum(np.sqrt(v.shape[0] * v.shape[1]) for v in views)
    few, many = int(0.1 * model_choice.EDGE_BAND * size), int(1.3 * model_choice.EDGE_BAND * size)  # edge samples
    shape = views[0].shape

    def quantities(shadowed: float):
        visibility = np.ones(shape)
        visibility[: int(round(shadowed * shape[0]))] = 0.0  # the top rows in the proxy's cast shadow
        q = SimpleNamespace(valid=np.ones(shape, bool), sky_mask=np.zeros(shape, bool), cosine=np.full(shape, 0.8),
                            visibility=visibility)
        return {v.stem: q for v in views}

    none = model_choice.choose_cast_shadows(scene, quantities(0.005), few)
    assert none.choice == "no cast shadow" and none.measures["shadow_edge"] == pytest.approx(0.1, abs=1e-2)
    assert none.measures["shadow_share"] == pytest.approx(1 / 180, abs=1e-9)  # one row of 180
    # either figure alone keeps the shadows: a large shadow with short edges, or long edges
    assert model_choice.choose_cast_shadows(scene, quantities(0.2), few).choice == "cast shadows"
    assert model_choice.choose_cast_shadows(scene, quantities(0.005), many).choice == "cast shadows"
    with pytest.raises(ValueError, match="min_shadow_edge"):
        SunConfig(min_shadow_edge=-1.0)


def test_no_cast_shadow_lights_every_pixel_and_keeps_the_sun(demo_scene):
    scene = Scene(demo_scene.views[:3], demo_scene.proxy, demo_scene.sun, demo_scene.up)
    # thresholds above the demo's figures (2.3% shadow share, 0.32 view sizes of edge per view)
    result = decompose(scene, config=Config(sun=SunConfig(min_shadow_share=0.5, min_shadow_edge=100.0)))
    model = result.lighting.model
    assert model["sun"].choice == "direct sun" and model["shadows"].choice == "no cast shadow"
    assert model["step4"].choice == "fusion only" and (result.lighting.sun_radiance > 0).all()
    for view in scene.views:
        layers = result.layers[view.stem]
        valid = layers.shadow_labels != 128
        assert (layers.shadow_labels[valid] == 255).all() and (layers.visibility[valid] == 1).all()
        assert np.isfinite(layers.reflectance).all() and layers.sun_shading[valid].max() > 0
        np.testing.assert_allclose(layers.reconstruct()[valid], view.image[valid], rtol=1e-4, atol=1e-6)
    assert "shadow_labels" not in result.timings and "matting" not in result.timings


def test_warmth_is_blind_to_white_balance_and_says_sun_on_the_demo(demo_scene):
    from mvintrinsic.sun_calibration import direct_sun_evidence

    scene = Scene(demo_scene.views[:2], demo_scene.proxy, demo_scene.sun, demo_scene.up)
    tracer = Tracer(scene.proxy)
    quantities = carry_to_pixels(scene, step1(scene, tracer=tracer, rng=0), tracer)
    before = direct_sun_evidence(scene.views, quantities)
    gains = np.array([1.6, 1.0, 0.55], np.float32)  # a strong warm white balance
    balanced = [View(v.stem, v.image * gains, v.camera, v.mask) for v in scene.views]
    after = direct_sun_evidence(balanced, quantities)
    assert before.samples == after.samples > 300
    assert after.warmth == pytest.approx(before.warmth, abs=1e-5)
    assert after.contrast == pytest.approx(before.contrast, rel=0.05)  # luminance weights move it a little
    assert before.warmth > SunConfig().sun_warmth


def test_solver_diagnostics_are_in_the_result_and_its_folder(tmp_path):
    """Issue 19: how every matting system was solved is returned, not only logged, and saved."""
    from mvintrinsic import save_decomposition
    from mvintrinsic.io import demo_scene_path

    scene = load_scene(demo_scene_path())
    result = decompose(scene)
    reports = result.diagnostics["matting"]
    assert set(reports) == set(scene.stems)
    rtol = Config().matting.rtol
    for stem, view_reports in reports.items():
        assert [r["what"].split(" '")[0] for r in view_reports][:1] == ["sun visibility matting"], stem
        for report in view_reports:
            assert report["converged"] and 0.0 <= report["residual"] <= rtol, (stem, report)
            assert report["solver"] in ("direct", "cg", "none") and report["unknowns"] >= 0
    save_decomposition(result, tmp_path / "result")
    assert load_decomposition(tmp_path / "result").diagnostics == result.diagnostics


def test_result_config_round_trips_as_a_config_or_stays_a_mapping(tmp_path, demo_result):
    from mvintrinsic import save_decomposition

    save_decomposition(demo_result, tmp_path / "ours")
    assert load_decomposition(tmp_path / "ours").config == demo_result.config == Config()
    lighting = tmp_path / "ours" / "lighting.json"
    data = json.loads(lighting.read_text())
    data["config"]["steps"] = 7  # Config's key, a value this version refuses
    lighting.write_text(json.dumps(data))
    with pytest.warns(UserWarning, match="kept as a mapping"):
        kept = load_decomposition(tmp_path / "ours").config
    assert kept["steps"] == 7


# Issue 16, beyond the paper: the occluders the proxy lost (the demo's tree crown), carved after Step 3
# by default (the proxy leaves 87% of the demo's labelled shadow in the sun). Measured on the demo
# (docs/step4.md), without -> with: umbra S_env signed error +38/+54/+91% -> +10/+17/+36%, L_sun over
# the truth 1.40/1.40/1.61 -> 1.12/1.14/1.29, reflectance LMSE 0.0392 -> 0.0393.
OCCLUDED_UMBRA_MAX = 0.45  # largest |signed median relative error| of the umbra's S_env over R, G, B
OCCLUDED_LSUN_MAX = 1.35  # largest L_sun / truth over R, G, B


def test_occluders_bring_the_umbra_and_lsun_toward_the_truth(demo_scene, demo_result, plain_result, tmp_path):
    from mvintrinsic.evaluation import env_shading_error, evaluate, read_ground_truth_lighting, umbra_mask
    from mvintrinsic.io import save_decomposition
    from mvintrinsic.occluders import OccluderConfig

    folder = demo_scene_path()
    occluded, plain = demo_result, plain_result
    assert occluded.diagnostics["occluders"]["voxels"] > 0 and "occluders.carve" in occluded.timings
    choice = occluded.lighting.model["occluders"]
    assert choice.choice == "carve" and choice.measures["unexplained_share"] > OccluderConfig().min_unexplained
    assert "occluders" not in plain.lighting.model and "occluders" not in plain.diagnostics
    umbra = umbra_mask(folder)
    true_sun = np.asarray(read_ground_truth_lighting(folder).sun_radiance)
    scores = {}
    for name, result in (("default", plain), ("occluders", occluded)):
        env = {s: layer.sky_shading.astype(np.float64) + layer.indirect_shading for s, layer in result.layers.items()}
        error = np.abs(env_shading_error(folder, env, region="umbra", umbra=umbra)["median_signed_rel_error"])
        save_decomposition(result, tmp_path / name, scene=demo_scene)
        mean = evaluate(folder, tmp_path / name)["mean"]
        lmse = np.array([mean["lmse_reflectance"], mean["lmse_shading"]])
        scores[name] = (error, np.asarray(result.lighting.sun_radiance) / true_sun, lmse)
    (error0, lsun0, lmse0), (error1, lsun1, lmse1) = scores["default"], scores["occluders"]
    assert (error1 < error0).all() and error1.max() < OCCLUDED_UMBRA_MAX
    assert (np.abs(lsun1 - 1) < np.abs(lsun0 - 1)).all() and lsun1.max() < OCCLUDED_LSUN_MAX
    # both LMSEs lower (measured 0.0392 -> 0.0370 and 0.1535 -> 0.1508: the carving alone raised the
    # shading's to 0.1575, the smooth reflectance where shadowed pixels see an occluder lowers it)
    assert (lmse1 < lmse0).all()
    assert 0 < occluded.diagnostics["occluders"]["smoothed_share"] < 0.1
    assert load_decomposition(tmp_path / "occluders").config.occluders == OccluderConfig()
