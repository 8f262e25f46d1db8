"""Selections of the PatchMatch-completed proxy, judged by relighting (``mvintrinsic.stereo``).

PatchMatch runs once per scene (:func:`mvintrinsic.stereo.complete_proxy`, its defaults); every
selection of ``--tolerance`` then builds a completed proxy from the same depth maps
(:func:`mvintrinsic.stereo.proxy_from_depths` with ``StereoConfig(colour_tolerance=...)``; ``none``:
no colour test, the selection before the test was added; 0.15 is the default), and the scene is relit at each of its relit suns with
the relighter's defaults:

* ``input``: the photographs unchanged, row (a) of ``bench_relight.py``;
* ``own_proxy_gt_caster`` / ``gt_caster``: the true layers relit on the scene's own proxy / on the
  completed one, row (d);
* ``own_proxy_pipeline`` / ``pipeline_own_layers``: the layers decomposed on the scene's own proxy,
  relit on it / on the completed one;
* ``pipeline`` (with ``--decompose``): decomposed and relit on the completed proxy, row (e).

PSNR as in ``bench_relight.py`` (``docs/metrics.md``). Also per selection: the triangles added and
the share of the true foliage and thin structures the photos show that the proxy retains.

Usage::

    python benchmarks/bench_stereo.py --data DATA --scene courtyard_s1r --tolerance none --tolerance 0.15 \\
        --decompose --out benchmarks/results/stereo_colour.json
    python benchmarks/bench_stereo.py --smoke        # CI: a tiny ray-cast scene, seconds
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import pickle
import sys
import time
from pathlib import Path

import numpy as np
from bench_relight import _relit_scene, mean_psnr  # benchmarks/ is the script's folder

import mvintrinsic
from mvintrinsic.evaluation import ground_truth_decomposition
from mvintrinsic.io import read_proxy, write_json
from mvintrinsic.pipeline import decompose
from mvintrinsic.raytrace import Tracer
from mvintrinsic.relight import Relighter
from mvintrinsic.stereo import StereoConfig, complete_proxy, proxy_from_depths

#: The suns of the issue's +-15 degree targets.
TARGET_SUNS = ("az+15", "az-15")


def _tolerance(text: str) -> float | None:
    return None if text == "none" else float(text)


def _label(tolerance: float | None) -> str:
    return "none" if tolerance is None else f"colour {tolerance:g}"


def stereo_scene(folder: Path, tolerances: list[float | None], *, decomposed: bool, cache: Path | None) -> dict:
    """Every selection of one scene (module docstring)."""
    from mvintrinsic.synth.proxy import label_retention

    scene, tags, sky = _relit_scene(folder, "bench_stereo")
    truth = ground_truth_decomposition(folder, views=list(scene.stems))
    exact = read_proxy(folder / "gt" / "mesh.ply")
    labels = np.load(folder / "gt" / "mesh_faces.npz")["label"]
    cameras = [v.camera for v in scene.views]
    tracer = Tracer(scene.proxy)
    cached = None if cache is None else cache / f"{folder.name}_depths.pkl"
    start = time.perf_counter()
    if cached is not None and cached.exists():
        maps = pickle.loads(cached.read_bytes())
    else:
        maps = complete_proxy(scene, tracer=tracer, progress=print)[1]
        if cached is not None:  # written whole or not at all: an interrupted run leaves no partial cache
            cached.parent.mkdir(parents=True, exist_ok=True)
            partial = cached.with_suffix(".partial")
            partial.write_bytes(pickle.dumps(maps))
            partial.replace(cached)
    out = {"patchmatch_seconds": time.perf_counter() - start, "selections": {}}
    own_layers = decompose(scene, tracer=tracer)
    own_gt = Relighter(truth, scene, tracer=tracer)
    own_pipe = Relighter(own_layers, scene, tracer=tracer)
    out["own_proxy"] = {tag: {"input": mean_psnr({v.stem: v.image for v in scene.views}, images, sky)["mean"],
                              "own_proxy_gt_caster": mean_psnr(own_gt.render(np.asarray(d, float)), images, sky)["mean"],
                              "own_proxy_pipeline": mean_psnr(own_pipe.render(np.asarray(d, float)), images, sky)["mean"]}
                        for tag, (d, images, _) in tags.items()}
    for tolerance in tolerances:
        proxy = proxy_from_depths(scene, maps, config=StereoConfig(colour_tolerance=tolerance), tracer=tracer)
        moved = dataclasses.replace(scene, proxy=proxy)
        moved_tracer = Tracer(proxy)
        retained = label_retention(proxy, exact.vertices, exact.triangles, labels, cameras)
        rows = {"gt_caster": Relighter(truth, moved, tracer=moved_tracer),
                "pipeline_own_layers": Relighter(own_layers, moved, tracer=moved_tracer)}
        if decomposed:
            rows["pipeline"] = Relighter(decompose(moved, tracer=moved_tracer), moved, tracer=moved_tracer)
        entry = {"triangles_added": int(len(proxy.triangles) - len(scene.proxy.triangles)),
                 "retention": {k: float(retained[k]) if np.isfinite(retained[k]) else None for k in ("foliage", "thin")},
                 "psnr": {}}
        for tag, (direction, images, _) in tags.items():
            sun = np.asarray(direction, dtype=np.float64)
            entry["psnr"][tag] = {row: mean_psnr(r.render(sun), images, sky)["mean"] for row, r in rows.items()}
            print(f"{folder.name} {_label(tolerance)} {tag}: "
                  + " ".join(f"{k} {v:.2f}" for k, v in {**out["own_proxy"][tag], **entry["psnr"][tag]}.items()),
                  flush=True)
        out["selections"][_label(tolerance)] = entry
    return out


def summary(scenes: dict) -> dict:
    """Per selection, means over the scenes at +-15 degrees: row (d), (e) - (a), and the worst (e) - (a)."""
    out = {}
    labels = {label for s in scenes.values() for label in s["selections"]}
    for label in sorted(labels):
        d, e_own, e, e_gain = [], [], [], []
        for s in scenes.values():
            sel = s["selections"].get(label)
            if sel is None:
                continue
            for tag in TARGET_SUNS:
                if tag not in sel["psnr"]:
                    continue
                row, base = sel["psnr"][tag], s["own_proxy"][tag]
                d.append(row["gt_caster"] - base["own_proxy_gt_caster"])
                e_own.append(row["pipeline_own_layers"] - base["input"])
                if "pipeline" in row:
                    e.append(row["pipeline"] - base["input"])
                    e_gain.append(row["pipeline"] - base["own_proxy_pipeline"])
        out[label] = {"scene_suns": len(d), "gt_caster_gain_mean": float(np.mean(d)),
                      "gt_caster_gain_min": float(np.min(d)),
                      "own_layers_minus_input_mean": float(np.mean(e_own)),
                      "own_layers_minus_input_min": float(np.min(e_own))}
        if e:
            out[label].update({"pipeline_minus_input_mean": float(np.mean(e)),
                               "pipeline_minus_input_min": float(np.min(e)),
                               "pipeline_gain_over_own_proxy_mean": float(np.mean(e_gain)),
                               "pipeline_gain_over_own_proxy_min": float(np.min(e_gain))})
    return out


def smoke() -> int:
    """CI's quick check: two selections of a ray-cast box scene differ only by the colour test."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from test_stereo import make_box_scene  # the tests' textured box the proxy lost

    scene = make_box_scene()[0]
    coloured, maps = complete_proxy(scene)  # the default selection: the colour test at 0.15
    plain = proxy_from_depths(scene, maps, config=StereoConfig(colour_tolerance=None))
    added = len(plain.triangles) - len(scene.proxy.triangles)
    kept = len(coloured.triangles) - len(scene.proxy.triangles)
    print(f"smoke: {added} triangles added without the colour test, {kept} with it (0.15)")
    return 0 if 0 < kept <= added else 1


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, help="folder holding the scenes")
    parser.add_argument("--scene", action="append", default=[], help="scene folder name (repeatable)")
    parser.add_argument("--tolerance", action="append", type=_tolerance, default=[],
                        help="colour tolerance of a selection, or 'none' (repeatable; default: none and 0.15, the default)")
    parser.add_argument("--decompose", action="store_true", help="also decompose on every completed proxy (row (e))")
    parser.add_argument("--cache", type=Path, help="folder to keep the PatchMatch depth maps in between runs")
    parser.add_argument("--out", type=Path, help="JSON to write (merged with its scenes if it exists)")
    parser.add_argument("--smoke", action="store_true", help="a seconds-long check for CI")
    args = parser.parse_args(argv)
    if args.smoke:
        return smoke()
    if args.data is None or not args.scene:
        parser.error("--data and at least one --scene are needed (or --smoke)")
    tolerances = args.tolerance or [None, 0.15]
    scenes = {}
    if args.out is not None and args.out.exists():
        scenes = json.loads(args.out.read_text()).get("scenes", {})
    for name in args.scene:
        folder = args.data / name
        if not folder.is_dir():
            parser.error(f"--scene: no folder {folder}")
        scenes[name] = stereo_scene(folder, tolerances, decomposed=args.decompose, cache=args.cache)
        if args.out is not None:
            report = {"benchmark": "stereo_selection", "version": mvintrinsic.__version__, "cores": os.cpu_count(),
                      "psnr": "as bench_relight.py: linear RGB, non-sky pixels, clipped at the truth's 99.5th percentile",
                      "scenes": scenes, "summary": summary(scenes)}
            write_json(args.out, report)
    print(json.dumps(summary(scenes), indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
