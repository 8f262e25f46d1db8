"""Scoring result folders against ground truth: the ground truth scores perfectly, damage scores worse."""

from __future__ import annotations

import dataclasses
import importlib.util
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from mvintrinsic import Decomposition
from mvintrinsic import io as mio
from mvintrinsic.evaluation import (
    METRIC_KEYS,
    PSNR_MAX_DB,
    GroundTruth,
    evaluate,
    ground_truth_decomposition,
    read_ground_truth,
    read_ground_truth_lighting,
)

# Tolerances, in one place.
EXACT = 1e-10  # LMSE / si-MSE of the ground truth scored against itself (exactly 0 in float64 up to rounding)
RECON_PSNR_MIN_DB = 50.0  # image vs gt R * S: float16 EXRs, measured 81.2-81.6 dB on dev_courtyard
FLOAT16_ENV_ATOL = 5e-3  # gt/env_shading vs gt/shading - gt/sun_shading (float16 rounding, measured <= 3.2e-3)
VIEWS = ("view_000", "view_005")  # a subset keeps the file fast


@pytest.fixture(scope="module")
def gt_decomposition(dev_courtyard) -> Decomposition:
    return ground_truth_decomposition(dev_courtyard, views=list(VIEWS))


@pytest.fixture(scope="module")
def gt_result(gt_decomposition, tmp_path_factory) -> Path:
    """The ground truth of two views written as a result folder."""
    return mio.save_decomposition(gt_decomposition, tmp_path_factory.mktemp("gt") / "result")


@pytest.fixture(scope="module")
def truth(dev_courtyard) -> dict[str, GroundTruth]:
    return read_ground_truth(dev_courtyard, views=list(VIEWS))


def save_changed(decomposition: Decomposition, folder: Path, stem: str, **changes) -> Path:
    """Write ``decomposition`` with some layers of one view replaced."""
    layers = dict(decomposition.layers)
    layers[stem] = dataclasses.replace(layers[stem], **changes)
    return mio.save_decomposition(dataclasses.replace(decomposition, layers=layers), folder)


# -- reading the ground truth ----------------------------------------------------------------------
def test_read_ground_truth(dev_courtyard, truth):
    gt = truth["view_000"]
    assert gt.shape == (240, 320)
    assert gt.sun_visibility.dtype == bool and gt.sky_mask.dtype == bool
    assert gt.sky_mask.any() and not gt.sky_mask.all()
    assert gt.sun_shading is not None and gt.env_shading is not None
    # The files agree with their definitions up to float16 storage.
    rgb, _ = mio.read_image(dev_courtyard / "images" / "view_000.exr")
    known = gt.valid
    np.testing.assert_allclose((gt.reflectance * gt.shading)[known], rgb[known], rtol=1e-3, atol=1e-4)
    assert np.all(gt.sun_shading[~gt.sun_visibility & ~gt.sky_mask] == 0)  # gt/sun_shading includes v_sun
    assert sorted(read_ground_truth(dev_courtyard)) == [f"view_{i:03d}" for i in range(10)]


def test_read_ground_truth_lighting(dev_courtyard):
    lighting = read_ground_truth_lighting(dev_courtyard)
    data = json.loads((dev_courtyard / "gt" / "lighting.json").read_text())
    np.testing.assert_allclose(lighting.sun_radiance, data["sun_radiance"])
    scene = mio.read_scene_json(dev_courtyard / "scene.json")
    np.testing.assert_allclose(lighting.sun.direction, scene["sun_direction"], atol=1e-12)


def test_ground_truth_decomposition_layers(gt_decomposition, truth):
    for stem, gt in truth.items():
        layers = gt_decomposition.layers[stem]
        known = ~gt.sky_mask
        # S_tot is the true shading exactly; the environment term is gt/env_shading up to float16.
        np.testing.assert_array_equal(layers.shading[known], gt.shading[known])
        np.testing.assert_allclose(layers.env_shading[known], gt.env_shading[known], atol=FLOAT16_ENV_ATOL)
        np.testing.assert_array_equal(layers.reflectance[known], gt.reflectance[known])
        np.testing.assert_array_equal(layers.visibility, (gt.sun_visibility & known).astype(np.float32))
        assert np.all(layers.shadow_labels[gt.sky_mask] == 128)
        np.testing.assert_array_equal(layers.shadow_labels[known] == 255, gt.sun_visibility[known])
        assert np.all(layers.reflectance[gt.sky_mask] == 0) and np.all(layers.shading[gt.sky_mask] == 0)
        assert np.all(layers.indirect_shading == 0)


# -- the ground truth scores perfectly ------------------------------------------------------------
def test_ground_truth_scores_perfectly(dev_courtyard, gt_result):
    scores = evaluate(dev_courtyard, gt_result)
    assert list(scores["views"]) == list(VIEWS)
    for values in [*scores["views"].values(), scores["mean"]]:
        for key in ("lmse_reflectance", "lmse_shading", "lmse_score", "si_mse_reflectance", "si_mse_shading"):
            assert 0 <= values[key] < EXACT, key
        assert values["ber"] == 0.0 and values["ber_excluded_fraction"] == 0.0
        assert values["reconstruction_psnr"] > RECON_PSNR_MIN_DB
        assert values["reconstruction_ssim"] > 0.9999
        assert values["shading_psnr"] == PSNR_MAX_DB and values["shading_ssim"] == pytest.approx(1.0)
    view = scores["views"]["view_000"]
    assert view["ber_single_class"] is False and 0 < view["true_shadow_fraction"] < 1
    assert view["shading_scale"] == pytest.approx([1.0, 1.0, 1.0])
    assert 0.5 < view["scored_fraction"] < 1  # the sky is excluded
    assert scores["lighting"]["sun_direction_error_deg"] == pytest.approx(0.0, abs=1e-6)
    assert scores["settings"]["window"] == 20 and scores["settings"]["step"] == 10
    # JSON-ready: plain Python types, no NaN or infinity.
    assert json.loads(json.dumps(scores, allow_nan=False)) == scores
    assert all(type(view[k]) is float for k in METRIC_KEYS)


def test_missing_view_is_scored_on_the_views_it_has(dev_courtyard, gt_decomposition, tmp_path):
    one = dataclasses.replace(gt_decomposition, layers={"view_005": gt_decomposition.layers["view_005"]})
    scores = evaluate(dev_courtyard, mio.save_decomposition(one, tmp_path / "one"))
    assert list(scores["views"]) == ["view_005"]
    assert "view_000" in scores["views_without_result"] and len(scores["views_without_result"]) == 9
    assert scores["mean"] == {k: scores["views"]["view_005"][k] for k in METRIC_KEYS}


def test_views_argument_selects_and_validates(dev_courtyard, gt_result):
    scores = evaluate(dev_courtyard, gt_result, views=["view_005"], window=10, step=5)
    assert list(scores["views"]) == ["view_005"] and scores["settings"]["window"] == 10
    with pytest.raises(ValueError, match="view_003"):
        evaluate(dev_courtyard, gt_result, views=["view_003"])  # has gt, not in the result


# -- damage scores worse --------------------------------------------------------------------------
def test_smooth_reflectance_field_scores_worse(dev_courtyard, gt_decomposition, tmp_path):
    layers = gt_decomposition.layers["view_000"]
    h, w = layers.shape
    y, x = np.mgrid[0:h, 0:w] / max(h, w)
    field = (1.0 + 0.5 * np.sin(2 * np.pi * x) * np.cos(np.pi * y)).astype(np.float32)[..., None]
    # R * field and S / field: the same image, a different (wrong) decomposition.
    result = save_changed(
        gt_decomposition,
        tmp_path / "field",
        "view_000",
        reflectance=layers.reflectance * field,
        sun_shading=layers.sun_shading / field,
        sky_shading=layers.sky_shading / field,
    )
    view = evaluate(dev_courtyard, result, views=["view_000"])["views"]["view_000"]
    for key in ("lmse_reflectance", "lmse_shading", "lmse_score", "si_mse_reflectance", "si_mse_shading"):
        assert view[key] > 1e-4, key
    # LMSE fits a scale per 20 px window, so a smooth field costs it far less than the global si-MSE.
    assert view["lmse_reflectance"] < 0.5 * view["si_mse_reflectance"]
    assert view["shading_psnr"] < 40 and view["shading_ssim"] < 1
    assert view["reconstruction_psnr"] > RECON_PSNR_MIN_DB  # the image is still explained
    assert view["ber"] == 0.0


def test_all_lit_labels_give_ber_one_half(dev_courtyard, gt_decomposition, tmp_path):
    labels = gt_decomposition.layers["view_000"].shadow_labels
    all_lit = np.where(labels == 128, 128, 255).astype(np.uint8)
    result = save_changed(gt_decomposition, tmp_path / "lit", "view_000", shadow_labels=all_lit)
    view = evaluate(dev_courtyard, result, views=["view_000"])["views"]["view_000"]
    assert view["ber"] == 0.5  # both classes present: 1 - (0 / P + N / N) / 2
    assert view["lmse_score"] < EXACT  # the layers are untouched


def test_flipped_region_ber_by_hand(dev_courtyard, gt_decomposition, truth, tmp_path):
    gt = truth["view_000"]
    labels = gt_decomposition.layers["view_000"].shadow_labels.copy()
    region = np.zeros(gt.shape, bool)
    region[60:200, 40:220] = True
    flip = region & (labels != 128)
    labels[flip] = 255 - labels[flip]
    result = save_changed(gt_decomposition, tmp_path / "flip", "view_000", shadow_labels=labels)
    view = evaluate(dev_courtyard, result, views=["view_000"])["views"]["view_000"]
    scored, shadow = gt.valid, ~gt.sun_visibility
    false_lit = (region & shadow & scored).sum()  # true shadow labelled lit
    false_shadow = (region & ~shadow & scored).sum()  # true lit labelled shadow
    expected = 0.5 * (false_lit / (shadow & scored).sum() + false_shadow / (~shadow & scored).sum())
    assert 0.05 < expected < 0.95
    assert view["ber"] == pytest.approx(expected, rel=1e-12)


def test_undecided_labels_are_left_out_of_the_ber(dev_courtyard, gt_decomposition, truth, tmp_path):
    gt = truth["view_000"]
    labels = gt_decomposition.layers["view_000"].shadow_labels.copy()
    labels[100:150, :] = 128
    result = save_changed(gt_decomposition, tmp_path / "undecided", "view_000", shadow_labels=labels)
    view = evaluate(dev_courtyard, result, views=["view_000"])["views"]["view_000"]
    region = np.zeros(gt.shape, bool)
    region[100:150, :] = True
    assert view["ber"] == 0.0
    assert view["ber_excluded_fraction"] == pytest.approx((region & gt.valid).sum() / gt.valid.sum(), rel=1e-12)


# -- errors ---------------------------------------------------------------------------------------
def test_scene_without_gt(scene_dir, gt_result):
    with pytest.raises(mio.SceneError, match=r"gt"):
        evaluate(scene_dir, gt_result)
    with pytest.raises(mio.SceneError, match=r"gt"):
        read_ground_truth(scene_dir)


def test_result_without_lighting_json(dev_courtyard, gt_result, tmp_path):
    broken = tmp_path / "broken"
    shutil.copytree(gt_result, broken)
    (broken / "lighting.json").unlink()
    with pytest.raises(mio.SceneError, match=r"lighting\.json"):
        evaluate(dev_courtyard, broken)


def test_missing_gt_layer_is_named(dev_courtyard, tmp_path):
    (tmp_path / "gt" / "reflectance").mkdir(parents=True)
    shutil.copy(dev_courtyard / "gt" / "reflectance" / "view_000.exr", tmp_path / "gt" / "reflectance")
    with pytest.raises(mio.SceneError, match=r"gt/shading/view_000\.exr"):
        read_ground_truth(tmp_path)
    with pytest.raises(mio.SceneError, match=r"gt/lighting\.json"):
        read_ground_truth_lighting(tmp_path)


# -- the command-line script ----------------------------------------------------------------------
def _load_benchmark(name: str):
    """Import ``benchmarks/<name>.py`` as a module (the folder is not a package)."""
    path = Path(__file__).resolve().parents[1] / "benchmarks" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(f"benchmarks_{name}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_cli_gt_as_result(dev_courtyard, tmp_path, capsys):
    script = _load_benchmark("evaluate")
    out = tmp_path / "scores.json"
    argv = [str(dev_courtyard), "--gt-as-result", str(tmp_path / "gt"), "--views", "view_005", "--out", str(out)]
    assert script.main(argv) == 0
    table = capsys.readouterr().out
    assert "view_005" in table and "mean" in table
    scores = json.loads(out.read_text())
    assert scores["mean"]["lmse_score"] < EXACT and scores["mean"]["ber"] == 0.0
    assert (tmp_path / "gt" / "lighting.json").is_file() and not (tmp_path / "gt" / "scores.json").exists()
    assert script.main([str(dev_courtyard), str(tmp_path / "missing")]) == 2
    assert "lighting.json" in capsys.readouterr().err


def test_env_shading_and_visibility_errors_on_known_estimates():
    """Ground truth scores 0; a uniform 10% excess scores exactly 0.1; all-lit visibility 0.5."""
    from mvintrinsic.cli import demo_scene_path
    from mvintrinsic.evaluation import env_shading_error, read_ground_truth, visibility_error

    folder = demo_scene_path()
    gt = read_ground_truth(folder, views=["view_000", "view_001"])
    exact = {s: g.env_shading for s, g in gt.items()}
    assert env_shading_error(folder, exact)["median_rel_error"] == [0.0, 0.0, 0.0]
    scaled = env_shading_error(folder, {s: 1.1 * e for s, e in exact.items()}, region="all")
    np.testing.assert_allclose(scaled["median_rel_error"], 0.1, rtol=1e-5)
    np.testing.assert_allclose(scaled["median_signed_rel_error"], 0.1, rtol=1e-5)
    visibility = {s: g.sun_visibility.astype(float) for s, g in gt.items()}
    assert visibility_error(folder, visibility)["ber"] == 0.0
    assert visibility_error(folder, {s: np.ones(v.shape) for s, v in visibility.items()})["ber"] == 0.5
    with pytest.raises(ValueError, match="region"):
        env_shading_error(folder, exact, region="dusk")


def test_umbra_is_the_shadow_no_part_of_the_sun_reaches():
    """The umbra lies inside the GT shadow and is smaller than it where shadows are dappled or
    soft; where the sun is a point (aperture 0) and rays go through pixel centres only its
    difference from the shadow is the pixel-centre jitter; the S_env error there is scored."""
    from mvintrinsic.cli import demo_scene_path
    from mvintrinsic.evaluation import env_shading_error, read_ground_truth, umbra_mask

    folder = demo_scene_path()
    stems = ["view_000"]
    gt = read_ground_truth(folder, views=stems)["view_000"]
    shadow = ~gt.sun_visibility & gt.valid  # not the sky
    umbra = umbra_mask(folder, views=stems)["view_000"]
    assert umbra.shape == shadow.shape and umbra.dtype == bool
    assert (umbra & shadow).sum() >= 0.99 * umbra.sum()  # inside the shadow (up to the pixel jitter)
    assert 0.1 * shadow.sum() < umbra.sum() < 0.9 * shadow.sum()  # the tree's dappled shadow is no umbra
    point_sun = umbra_mask(folder, views=stems, samples=1, aperture_deg=0.0)["view_000"]
    assert (point_sun & ~umbra).sum() > 0.2 * umbra.sum()  # one ray per pixel finds more "umbra"
    assert umbra_mask(folder, views=stems, seed=3)["view_000"].sum() == pytest.approx(umbra.sum(), rel=0.05)
    truth = gt.env_shading
    scored = env_shading_error(folder, {"view_000": 1.2 * truth}, region="umbra")
    np.testing.assert_allclose(scored["median_rel_error"], 0.2, rtol=1e-5)
    assert scored["pixels"] <= env_shading_error(folder, {"view_000": truth}, region="shadow")["pixels"]
    with pytest.raises(ValueError, match="samples"):
        umbra_mask(folder, views=stems, samples=0)


def test_error_by_material_splits_the_ber_by_material(dev_courtyard, gt_decomposition, truth, tmp_path, capsys):
    """Ground truth: no label error, LMSE 0; all lit: every GT shadow pixel is a miss, shared by material."""
    script = _load_benchmark("error_by_material")
    out = tmp_path / "gt.json"
    gt_folder = mio.save_decomposition(gt_decomposition, tmp_path / "gt")
    assert script.main([str(dev_courtyard), str(gt_folder), "--out", str(out)]) == 0
    exact = json.loads(out.read_text())
    assert exact["pooled_ber"] == 0.0 and exact["fnr"] == 0.0 and exact["fpr"] == 0.0
    assert exact["lmse"]["all"]["reflectance"] < EXACT and exact["lmse"]["outside_foliage"]["shading"] < EXACT

    stem = VIEWS[0]
    lit = np.full(truth[stem].sun_visibility.shape, 255, dtype=np.uint8)
    all_lit = save_changed(gt_decomposition, tmp_path / "lit", stem, shadow_labels=lit)
    assert script.main([str(dev_courtyard), str(all_lit), "--out", str(out)]) == 0
    report = json.loads(out.read_text())
    # one view of two lost all its shadows: FNR = its share of the GT shadow, FPR 0
    shadow = {s: int((~truth[s].sun_visibility & truth[s].valid).sum()) for s in VIEWS}
    assert report["fpr"] == 0.0
    assert report["fnr"] == pytest.approx(shadow[stem] / sum(shadow.values()), rel=1e-6)
    assert sum(row["fn_share"] for row in report["per_material"].values()) == pytest.approx(report["fnr"], rel=1e-9)
    assert report["pooled_ber"] == pytest.approx(report["fnr"] / 2)
    assert "paving" in report["per_material"]  # named by the dataset's material table
    capsys.readouterr()
    assert script.main([str(dev_courtyard), str(tmp_path / "missing")]) == 2
    assert "missing" in capsys.readouterr().err
