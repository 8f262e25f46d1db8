"""Step 4 (paper Sec. 7) against Step 3 and the colour Retinex baseline: issue 16's measures.

    python benchmarks/bench_step4.py [--data DIR] --scene NAME [--scene NAME ...]
                                     [--proxy {own,exact,stereo,stereo-no-colour-test}] [--out benchmarks/results/step4.json]
                                     [--timing SCENE]
    python benchmarks/bench_step4.py --smoke

For each scene (``DIR/NAME`` rendered by ``mvintrinsic synth``; ``demo`` is the embedded demo,
``dev_courtyard`` the shared dataset) with its MVS-like proxy: Steps 1-3 once (``Config(steps=3)``),
then Step 4 on Step 3's layers with each method of :mod:`mvintrinsic.env_refine` (``multiview``,
the default, and ``paper``), and the colour Retinex baseline (``benchmarks/baselines``). Per
variant, mean over views:

* reflectance and shading LMSE (:func:`mvintrinsic.evaluation.evaluate`);
* ``S_env`` against ``gt/env_shading`` in the umbra: median relative error and signed median, per
  channel (:func:`mvintrinsic.evaluation.env_shading_error`, ``region="umbra"``);
* the cross-view reflectance spread (median and 90th percentile of ``|R_view / R_median - 1|`` per
  channel over the proxy's vertices seen by two or more views,
  :func:`mvintrinsic.correspondence.cross_view_reflectance_spread`), and the ground truth's own;
* ``L_sun`` over the truth per channel: Step 2's, and Eq. 5 recomputed with the variant's ``S_env``
  (:func:`mvintrinsic.pipeline.calibrate` on the pixel quantities with ``S_sky`` and ``S_ind``
  replaced by the layers');
* Step 4's seconds per view (correspondences found here; ``decompose`` reuses the labelling's);
* the same measures for Steps 1-4 with the lost occluders carved after Step 3 and Steps 2-3 run
  again on every scene (``Config(occluders=OccluderConfig(when="always"))``,
  :mod:`mvintrinsic.occluders`; variant ``occluders``), with its own ``L_sun`` over the truth, the
  share of the labelled shadow the proxy leaves in the sun (on which ``when="auto"``, the
  default, decides) and its seconds per view for the whole decomposition
  (``step3_seconds_per_view``: Steps 1-3 without it).

Every other variant runs without the carving (``Config(occluders=None)``): the default
configuration is the ``occluders`` variant where the share is at least
``OccluderConfig.min_unexplained`` and ``step4_multiview`` elsewhere.

``--proxy exact`` runs every variant with the scene's exact mesh as the proxy instead of its
MVS-like one (``proxy_clean.ply`` subdivided as the Step-1 benchmarks do,
``bench_step1_accuracy.clean_proxy``; issue 16 asks for ``L_sun`` with the clean and the MVS
proxies): what the method reaches when the proxy holds the scene. ``--proxy stereo`` runs them
with the scene's proxy completed by PatchMatch stereo from its photographs
(:func:`mvintrinsic.stereo.complete_proxy`, no ground truth involved; ``stereo-no-colour-test``:
without its colour test, ``StereoConfig(colour_tolerance=None)``).

``--timing SCENE`` decomposes SCENE (e.g. ``DIR/courtyard_1000``, 1000x750) with the default
configuration and reports Step 4's seconds per view from ``decompose``'s timings. ``--smoke``
runs the demo only (CI). Run with the package importable.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import mvintrinsic
from mvintrinsic import Config, decompose
from mvintrinsic.correspondence import cross_view_reflectance_spread
from mvintrinsic.env_refine import EnvRefineConfig
from mvintrinsic.env_shading import step1
from mvintrinsic.evaluation import (
    env_shading_error,
    evaluate,
    read_ground_truth,
    read_ground_truth_lighting,
    umbra_mask,
)
from mvintrinsic.io import load_scene, save_decomposition, write_json
from mvintrinsic.occluders import OccluderConfig
from mvintrinsic.pipeline import calibrate, carry_to_pixels, step4
from mvintrinsic.raytrace import Tracer
from mvintrinsic.sun_calibration import SunCalibrationError

sys.path.insert(0, str(Path(__file__).resolve().parent / "baselines"))
from run_retinex import retinex_decomposition  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
METHODS = ("multiview", "paper")


def _score(folder: Path, scene, result) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        save_decomposition(result, Path(tmp) / "result", scene=scene)
        mean = evaluate(folder, Path(tmp) / "result")["mean"]
    return {"lmse_reflectance": mean["lmse_reflectance"], "lmse_shading": mean["lmse_shading"]}


def _spread(scene, quantities, reflectance: dict) -> dict:
    measured = cross_view_reflectance_spread(scene.views, quantities, reflectance, np.asarray(scene.proxy.vertices))
    return {"median": measured.median, "p90": measured.p90, "points": measured.points}


def _env(folder: Path, layers: dict, umbra) -> dict:
    estimate = {s: layer.sky_shading.astype(np.float64) + layer.indirect_shading for s, layer in layers.items()}
    error = env_shading_error(folder, estimate, region="umbra", umbra=umbra)
    return {"median_rel_error": error["median_rel_error"], "median_signed_rel_error": error["median_signed_rel_error"]}


def _lsun_ratio(scene, quantities, layers: dict, truth: np.ndarray) -> list[float] | None:
    """Eq. 5 (Step 2's pairs and median) with S_sky and S_ind taken from the layers."""
    fed = {s: dataclasses.replace(q, sky=layers[s].sky_shading, indirect=layers[s].indirect_shading)
           for s, q in quantities.items()}
    try:
        radiance = calibrate(scene, fed).sun_radiance
    except SunCalibrationError:  # no pair survives: reported as None
        return None
    return (np.asarray(radiance) / truth).tolist()


def bench_scene(folder: Path, *, proxy: str = "own") -> dict:
    scene = load_scene(folder)
    if proxy == "exact":  # the exact mesh in place of the MVS-like proxy
        from bench_step1_accuracy import clean_proxy

        scene = dataclasses.replace(scene, proxy=clean_proxy(folder, scene))
    elif proxy in ("stereo", "stereo-no-colour-test"):  # the proxy completed from the photographs
        from mvintrinsic.stereo import StereoConfig, complete_proxy

        config = StereoConfig(colour_tolerance=None) if proxy == "stereo-no-colour-test" else StereoConfig()
        scene = dataclasses.replace(scene, proxy=complete_proxy(scene, config=config)[0])
    n = len(scene.views)
    tracer = Tracer(scene.proxy)
    start = time.perf_counter()
    base = decompose(scene, config=Config(steps=3, occluders=None), tracer=tracer)
    base_seconds = (time.perf_counter() - start) / n
    # The same seeded Step 1 as decompose's: the per-pixel quantities Step 4 and the spread need.
    quantities = carry_to_pixels(scene, step1(scene, tracer=tracer, rng=Config().seed), tracer)
    truth = read_ground_truth(folder, views=list(scene.stems))
    true_sun = np.asarray(read_ground_truth_lighting(folder).sun_radiance, dtype=np.float64)
    umbra = umbra_mask(folder, views=list(scene.stems))
    out = {"views": n, "size": "x".join(map(str, scene.views[0].shape[::-1])), "proxy": proxy,
           "lsun_ratio_step2": (np.asarray(base.lighting.sun_radiance) / true_sun).tolist(),
           "spread_truth": _spread(scene, quantities, {s: truth[s].reflectance for s in scene.stems})}
    variants = {"step3": (base, None)}
    for method in METHODS:
        start = time.perf_counter()
        refined = step4(scene, quantities, base.layers, config=Config(env_refine=EnvRefineConfig(method=method)))
        seconds = (time.perf_counter() - start) / n
        variants[f"step4_{method}"] = (dataclasses.replace(base, layers=dict(refined.layers)), seconds)
    start = time.perf_counter()
    variants["occluders"] = (decompose(scene, config=Config(occluders=OccluderConfig(when="always")), tracer=tracer),
                             (time.perf_counter() - start) / n)
    out["step3_seconds_per_view"] = base_seconds
    for name, (result, seconds) in variants.items():
        entry = _score(folder, scene, result)
        entry["env_umbra"] = _env(folder, result.layers, umbra)
        entry["spread"] = _spread(scene, quantities, {s: layer.reflectance for s, layer in result.layers.items()})
        entry["lsun_ratio_eq5"] = _lsun_ratio(scene, quantities, result.layers, true_sun)
        if seconds is not None:
            entry["seconds_per_view"] = seconds
        if name == "occluders":
            entry["lsun_ratio"] = (np.asarray(result.lighting.sun_radiance) / true_sun).tolist()
            entry["occluders"] = result.diagnostics.get("occluders")
            entry["unexplained_share"] = result.lighting.model["occluders"].measures["unexplained_share"]
        out[name] = entry
        print(f"{folder.name:14s} {name:16s} LMSE R {entry['lmse_reflectance']:.4f} S {entry['lmse_shading']:.4f}  "
              f"umbra S_env {np.round(entry['env_umbra']['median_signed_rel_error'], 3)}  "
              f"spread {np.round(entry['spread']['median'], 3)}  "
              f"L_sun/true {np.round(entry['lsun_ratio_eq5'], 3) if entry['lsun_ratio_eq5'] else None}", flush=True)
    out["retinex"] = _score(folder, scene, retinex_decomposition(scene))
    print(f"{folder.name:14s} {'retinex':16s} LMSE R {out['retinex']['lmse_reflectance']:.4f} "
          f"S {out['retinex']['lmse_shading']:.4f}  truth spread {np.round(out['spread_truth']['median'], 3)}  "
          f"Step-2 L_sun/true {np.round(out['lsun_ratio_step2'], 3)}", flush=True)
    return out


def timing(folder: Path) -> dict:
    scene = load_scene(folder)
    result = decompose(scene)
    n = len(scene.views)
    parts = {k: v / n for k, v in result.timings.items() if k.startswith("step4")}
    size = "x".join(map(str, scene.views[0].shape[::-1]))
    print(f"{folder.name}: {size}, {n} views, Step 4 seconds per view: " +
          ", ".join(f"{k} {v:.2f}" for k, v in parts.items()), flush=True)
    return {"scene": folder.name, "size": size, "views": n, "seconds_per_view": parts}


def scene_folder(name: str, data: Path) -> Path:
    """The folder of ``--scene NAME``: ``demo`` is the embedded demo, ``dev_courtyard`` the shared
    dataset unless ``data`` holds one, anything else ``data / NAME``."""
    from mvintrinsic.cli import demo_scene_path

    if name == "demo":
        return demo_scene_path()
    if name == "dev_courtyard" and not (data / name).is_dir():
        return ROOT / "shared" / "datasets" / "dev_courtyard"
    return data / name


def scene_folders(parser: argparse.ArgumentParser, names: list[str], data: Path) -> dict[str, Path]:
    """:func:`scene_folder` of every ``--scene NAME``, each checked before any is run (a parser
    error naming the one without ``scene.json``)."""
    folders = {name: scene_folder(name, data) for name in names}
    for name, folder in folders.items():
        if not (folder / "scene.json").is_file():
            parser.error(f"--scene {name}: no scene.json in {folder}")
    return folders


def scene_study_parser(description: str) -> argparse.ArgumentParser:
    """The parser of a per-scene study: ``--data`` (default: ``data`` beside the repository), ``--scene``
    (repeatable), ``--smoke`` (the demo only) and ``--out``; :func:`chosen_scene_folders` reads it."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--data", type=Path, default=ROOT / "data", help="folder of the rendered scenes")
    parser.add_argument("--scene", action="append", default=[], help="DATA/NAME, 'demo' or 'dev_courtyard' (repeatable)")
    parser.add_argument("--smoke", action="store_true", help="the demo only")
    parser.add_argument("--out", type=Path, help="JSON report (nothing is written without it)")
    return parser


def chosen_scene_folders(parser: argparse.ArgumentParser, args: argparse.Namespace) -> dict[str, Path]:
    """The folders of ``--scene`` (or of the demo with ``--smoke``), each checked (:func:`scene_folders`)."""
    names = ["demo"] if args.smoke else args.scene
    if not names:
        parser.error("give --scene or --smoke")
    return scene_folders(parser, names, args.data)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=ROOT / "data", help="folder of the rendered scenes")
    parser.add_argument("--scene", action="append", default=[], help="DATA/NAME, 'demo' or 'dev_courtyard' (repeatable)")
    parser.add_argument("--smoke", action="store_true", help="the demo only")
    parser.add_argument("--timing", type=Path, default=None, help="scene folder for Step 4's seconds per view")
    parser.add_argument("--proxy", choices=("own", "exact", "stereo", "stereo-no-colour-test"), default="own",
                        help="the scene's MVS-like proxy (default), its exact mesh, or the proxy completed by stereo "
                             "(with or without StereoConfig's colour test)")
    parser.add_argument("--out", type=Path, default=None, help="JSON report")
    args = parser.parse_args(argv)
    names = ["demo"] if args.smoke else args.scene
    if not names and args.timing is None:
        parser.error("give --scene, --smoke or --timing")
    report = {"benchmark": "step4", "version": mvintrinsic.__version__, "cores": os.cpu_count(),
              "python": platform.python_version(), "config": Config().env_refine.__dict__,
              "occluders": OccluderConfig().__dict__, "proxy": args.proxy, "scenes": {}}
    folders = scene_folders(parser, names, args.data)
    if args.proxy == "exact":
        for name, folder in folders.items():
            if not (folder / "proxy_clean.ply").is_file():
                parser.error(f"--proxy exact: --scene {name} has no proxy_clean.ply in {folder}")
    for name, folder in folders.items():
        report["scenes"][name] = bench_scene(folder, proxy=args.proxy)
    if args.timing is not None:
        report["timing"] = timing(args.timing)
    if args.out:
        write_json(args.out, report)
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
