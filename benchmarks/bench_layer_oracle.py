"""Which layer limits Step 3's reflectance: the decomposition with parts replaced by the ground truth.

    python benchmarks/bench_layer_oracle.py [--data DIR] --scene NAME [--scene NAME ...]
                                            [--out benchmarks/results/layer_oracle.json]

For each scene (``DIR/NAME``, rendered by ``mvintrinsic synth``; ``demo`` is the embedded demo)
the decomposition up to Step 3 (``Config(steps=3)``, the scene's MVS-like proxy) is scored by
``mvintrinsic.evaluation.evaluate`` (reflectance and shading LMSE, mean over views), then again
with the reflectance recomputed by Eq. 2, ``R = I / (v S_sun k_sun + S_env')``, after replacing:

* ``true_env``: ``S_env`` by ``gt/env_shading`` (where it is defined);
* ``global_k``: ``S_env`` times ``env_scale_k``, the per-channel median over the views of true / estimated
  ``S_env`` (a level correction, what a global refinement could do);
* ``true_env_balanced``: the true ``S_env`` and ``S_sun`` times the same ``k``, so that the
  sun-to-sky balance of Step 2 is kept;
* ``true_v``: ``v_sun`` by the binary ``gt/sun_visibility``;
* ``true_v_env_balanced``: both.

Also the signed median relative error of ``S_env`` in the umbra
(:func:`mvintrinsic.evaluation.env_shading_error`) and issue 16's cross-view reflectance spread
(:func:`mvintrinsic.correspondence.cross_view_reflectance_spread` over the proxy's vertices) of
Step 3's reflectance and, as the floor the sampling sets, of the ground-truth reflectance. This measures how far issue 16's targets
(reflectance LMSE 30% lower) can be reached by correcting ``S_env`` alone, as the paper's Step 4
does. Run with the package importable.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import sys
import tempfile
from pathlib import Path

import numpy as np

import mvintrinsic
from mvintrinsic import Config, decompose
from mvintrinsic.correspondence import cross_view_reflectance_spread
from mvintrinsic.env_shading import step1
from mvintrinsic.evaluation import env_shading_error, evaluate, read_ground_truth
from mvintrinsic.image_model import total_shading
from mvintrinsic.io import load_scene, save_decomposition, write_json
from mvintrinsic.pipeline import carry_to_pixels
from mvintrinsic.raytrace import Tracer

ROOT = Path(__file__).resolve().parents[2]


def _score(folder: Path, scene, result) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        save_decomposition(result, Path(tmp) / "result", scene=scene)
        mean = evaluate(folder, Path(tmp) / "result")["mean"]
    return {"lmse_reflectance": mean["lmse_reflectance"], "lmse_shading": mean["lmse_shading"]}


def _replaced(result, images: dict, env: dict, sun_scale, visibility: dict | None):
    layers = {}
    for stem, layer in result.layers.items():
        old = layer.sky_shading.astype(np.float64) + layer.indirect_shading
        scale = np.where(old > 0, env[stem] / np.where(old > 0, old, 1.0), 1.0)
        v = layer.visibility if visibility is None else visibility[stem]
        sun, sky, indirect = layer.sun_shading * sun_scale, layer.sky_shading * scale, layer.indirect_shading * scale
        total = total_shading(sky, indirect, v, sun)  # Eq. 17
        known = (layer.reflectance > 0).any(axis=-1, keepdims=True) & (total > 0)
        reflectance = np.where(known, images[stem] / np.where(known, total, 1.0), layer.reflectance)  # Eq. 2
        layers[stem] = dataclasses.replace(
            layer, reflectance=reflectance.astype(np.float32), visibility=np.asarray(v, np.float32),
            sun_shading=sun.astype(np.float32), sky_shading=sky.astype(np.float32),
            indirect_shading=indirect.astype(np.float32))
    return dataclasses.replace(result, layers=layers)


def oracle_scene(folder: Path) -> dict:
    scene = load_scene(folder)
    tracer = Tracer(scene.proxy)
    result = decompose(scene, config=Config(steps=3), tracer=tracer)
    # The same Step 1 as decompose's (seeded): the proxy depth of every pixel, for the spread.
    quantities = carry_to_pixels(scene, step1(scene, tracer=tracer, rng=Config().seed), tracer)
    truth = read_ground_truth(folder, views=list(scene.stems))
    images = {v.stem: v.image.astype(np.float64) for v in scene.views}
    estimate = {s: layer.sky_shading.astype(np.float64) + layer.indirect_shading for s, layer in result.layers.items()}
    true_env = {s: truth[s].env_shading.astype(np.float64) for s in estimate}
    usable = {s: (estimate[s] > 0).all(axis=-1) & np.isfinite(true_env[s]).all(axis=-1)
              & (true_env[s] > 1e-4).all(axis=-1) & ~truth[s].sky_mask for s in estimate}
    k = np.median(np.concatenate([(true_env[s] / np.where(usable[s][..., None], estimate[s], 1.0))[usable[s]]
                                  for s in estimate]), axis=0)
    env = {s: np.where(usable[s][..., None], true_env[s], estimate[s]) for s in estimate}
    env_k = {s: np.where(usable[s][..., None], true_env[s], estimate[s] * k) for s in estimate}
    true_v = {s: truth[s].sun_visibility.astype(np.float32) for s in estimate}
    variants = {
        "step3": result,
        "true_env": _replaced(result, images, env, 1.0, None),
        "global_k": _replaced(result, images, {s: estimate[s] * k for s in estimate}, 1.0, None),
        "true_env_balanced": _replaced(result, images, env_k, k, None),
        "true_v": _replaced(result, images, estimate, 1.0, true_v),
        "true_v_env_balanced": _replaced(result, images, env_k, k, true_v),
    }
    vertices = np.asarray(scene.proxy.vertices)
    spread = {}
    for label, values in (("step3", {s: layer.reflectance for s, layer in result.layers.items()}),
                          ("truth", {s: truth[s].reflectance for s in estimate})):
        measured = cross_view_reflectance_spread(scene.views, quantities, values, vertices)
        spread[label] = {"median": measured.median, "p90": measured.p90, "points": measured.points}
        print(f"{folder.name:14s} spread {label:6s} median {np.round(measured.median, 3)} "
              f"p90 {np.round(measured.p90, 3)}", flush=True)
    out = {"reflectance_spread": spread, "env_scale_k": k.tolist(),
           "env_umbra_signed_median_rel_error": env_shading_error(folder, estimate, region="umbra")[
               "median_signed_rel_error"]}
    for name, variant in variants.items():
        out[name] = _score(folder, scene, variant)
        print(f"{folder.name:14s} {name:20s} LMSE R {out[name]['lmse_reflectance']:.4f} "
              f"S {out[name]['lmse_shading']:.4f}", flush=True)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=ROOT / "data", help="folder of the rendered scenes")
    parser.add_argument("--scene", action="append", required=True, help="DATA/NAME, or 'demo' (repeatable)")
    parser.add_argument("--out", type=Path, default=None, help="JSON report")
    args = parser.parse_args(argv)
    from mvintrinsic.cli import demo_scene_path

    report = {"benchmark": "layer_oracle", "version": mvintrinsic.__version__, "cores": os.cpu_count(),
              "python": platform.python_version(), "scenes": {}}
    for name in args.scene:
        folder = demo_scene_path() if name == "demo" else args.data / name
        report["scenes"][name] = oracle_scene(folder)
    if args.out:
        write_json(args.out, report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
