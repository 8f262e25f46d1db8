"""Step 2 (sun calibration) and the first full decomposition: accuracy and seconds per stage.

    python benchmarks/bench_step2.py [--make] [--smoke] [--out benchmarks/results/step2.json]
                                     [--history benchmarks/results/accuracy_history/step2.json]
                                     [--timing SCENE]

For each scene (the embedded demo, ``../shared/datasets/dev_courtyard`` and, with ``--make``, the
synthetic courtyard seed 1 and street seed 0 of ``bench_step1_accuracy.py``) and for both proxies
(the scene's MVS-like ``proxy.ply`` and the clean proxy: the exact mesh subdivided to 20 cm):

* ``L_sun`` against ``gt/lighting.json`` (relative error per channel), the number of pairs, the
  samples each rule rejected, the robust spread;
* the fraction of pairs that truly straddle a ground-truth shadow boundary on one material: the lit
  pixel is lit and the shadowed pixel shadowed in ``gt/sun_visibility``, and the exact mesh shows
  the same material at both (``gt/mesh_faces.npz``);
* the Step-2 decomposition scored by ``mvintrinsic.evaluation.evaluate`` (LMSE of reflectance and
  shading, BER of the shadow labels, reconstruction PSNR), mean over views;
* each of these again with Step 1's indirect attenuation only on unseen vertices' radiance
  (``Step1Config(indirect_attenuation="unseen")``, entries ``*_unseen_attenuation``).

``--history`` writes the MVS-proxy scores (the default input) as one point of the accuracy
history. ``--timing SCENE`` decomposes SCENE at a longer side of 480 and of 1000 pixels and
reports seconds per stage and per view. ``--smoke`` runs the demo scene only.
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from bench_step1_accuracy import CLEAN_MAX_EDGE, CLEAN_RADIUS, scenes

import mvintrinsic
from mvintrinsic import Scene
from mvintrinsic.env_shading import step1
from mvintrinsic.evaluation import evaluate, read_ground_truth_lighting
from mvintrinsic.io import load_scene, read_image, read_proxy, save_decomposition, write_json
from mvintrinsic.pipeline import Config, calibrate, carry_to_pixels, decompose, step2_layers
from mvintrinsic.raytrace import Tracer, subdivide
from mvintrinsic.results import Decomposition, Lighting

SCORES = ("lmse_reflectance", "lmse_shading", "lmse_score", "si_mse_reflectance", "si_mse_shading", "ber",
          "reconstruction_psnr")


def true_pair_fraction(folder: Path, scene: Scene, calibration) -> float | None:
    """Fraction of pairs whose lit/shadowed pixels are lit/shadowed in the GT and on one material."""
    faces = folder / "gt" / "mesh_faces.npz"
    if not faces.is_file():
        return None
    material = np.load(faces)["material"]
    exact = Tracer(read_proxy(folder / "gt" / "mesh.ply"))
    views = {v.stem: v for v in scene.views}
    good = total = 0
    for pairs in calibration.pairs:
        if not len(pairs):
            continue
        view = views[pairs.stem]
        lit = read_image(folder / "gt" / "sun_visibility" / f"{view.stem}.png")[0][..., 0] > 0.5
        hits = exact.intersect(view.camera.center, view.camera.pixel_rays())
        mat = np.where(hits.hit, material[np.maximum(hits.triangle, 0)], -1).reshape(view.camera.shape)
        a, b = pairs.lit, pairs.shadow
        ok = lit[a[:, 0], a[:, 1]] & ~lit[b[:, 0], b[:, 1]] & (mat[a[:, 0], a[:, 1]] == mat[b[:, 0], b[:, 1]])
        ok &= mat[a[:, 0], a[:, 1]] >= 0
        good += int(ok.sum())
        total += len(ok)
    return good / total if total else None


def run(folder: Path, scene: Scene, config: Config) -> dict:
    start = time.perf_counter()
    tracer = Tracer(scene.proxy)
    s1 = step1(scene, config=config.step1, tracer=tracer, rng=config.seed)
    quantities = carry_to_pixels(scene, s1, tracer)
    calibration = calibrate(scene, quantities, config=config)
    layers = {v.stem: step2_layers(v, quantities[v.stem], calibration.sun_radiance) for v in scene.views}
    seconds = time.perf_counter() - start
    truth = read_ground_truth_lighting(folder).sun_radiance
    result = Decomposition(layers=layers, lighting=Lighting(sun=scene.sun, sun_radiance=calibration.sun_radiance,
                                                            up=scene.up), config=config.to_dict())
    with tempfile.TemporaryDirectory() as tmp:
        save_decomposition(result, Path(tmp) / "result", scene=scene)
        scores = evaluate(folder, Path(tmp) / "result")
    return {
        "vertices": int(len(scene.proxy.vertices)),
        "seconds": seconds,
        "sun_radiance": calibration.sun_radiance.tolist(),
        "sun_radiance_truth": truth.tolist(),
        "sun_radiance_rel_error": ((calibration.sun_radiance - truth) / truth).tolist(),
        "spread": calibration.spread.tolist(),
        "pairs": calibration.n_pairs,
        "samples": int(sum(p.n_samples for p in calibration.pairs)),
        "rejected": dict(calibration.rejected),
        "true_pair_fraction": true_pair_fraction(folder, scene, calibration),
        "scores": {k: scores["mean"][k] for k in SCORES},
    }


def timing(folder: Path, config: Config) -> dict:
    out = {}
    for size in (480, 1000):
        scene = load_scene(folder, max_size=size)
        h, w = scene.views[0].shape
        start = time.perf_counter()
        result = decompose(scene, config=config)
        total = time.perf_counter() - start
        n = len(scene.views)
        step1_seconds = sum(v for k, v in result.timings.items() if k.startswith("step1."))
        per_view = {k: v / n for k, v in result.timings.items() if not k.startswith("step1.")}
        out[f"{w}x{h}"] = {"views": n, "proxy_vertices": int(len(scene.proxy.vertices)), "total_seconds": total,
                           "step1_seconds": step1_seconds, "step1": dict(result.timings),
                           "seconds_per_view": per_view, "step1_seconds_per_view": step1_seconds / n}
        print(f"{w}x{h}: {n} views, step1 {step1_seconds:.1f} s ({step1_seconds / n:.2f} s/view), per view "
              + ", ".join(f"{k} {v:.3f} s" for k, v in per_view.items()) + f"; total {total:.1f} s")
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--make", action="store_true", help="render the synthetic scenes that are absent")
    parser.add_argument("--smoke", action="store_true", help="the demo scene only")
    parser.add_argument("--out", type=Path, default=None, help="JSON report")
    parser.add_argument("--history", type=Path, default=None, help="accuracy-history point (MVS-proxy scores)")
    parser.add_argument("--timing", type=Path, default=None, help="scene folder for the per-stage timings")
    args = parser.parse_args()
    config = Config(steps=2)  # the Step-2 decomposition (decompose runs Step 3 by default)
    report = {"benchmark": "step2", "version": mvintrinsic.__version__, "cores": os.cpu_count(),
              "python": platform.python_version(), "config": config.to_dict(), "scenes": {}}
    chosen = scenes(args.make)
    if args.smoke:
        chosen = {"demo": chosen["demo"]}
    for name, folder in chosen.items():
        base = load_scene(folder)
        centers = np.array([v.camera.center for v in base.views])
        proxies = {"mvs": base.proxy}
        if not args.smoke:
            proxies["clean"] = subdivide(read_proxy(folder / "proxy_clean.ply"), max_edge=CLEAN_MAX_EDGE,
                                         center=centers.mean(axis=0), radius=CLEAN_RADIUS)
        entry = {}
        # the paper's attenuation factor (default) and, as a variant, only on unseen vertices' radiance
        unseen = replace(config, step1=replace(config.step1, indirect_attenuation="unseen"))
        runs = [(key, proxy, config) for key, proxy in proxies.items()]
        runs += [(f"{key}_unseen_attenuation", proxy, unseen) for key, proxy in proxies.items()]
        for proxy_name, proxy, run_config in runs:
            e = entry[proxy_name] = run(folder, Scene(base.views, proxy, base.sun, base.up), run_config)
            frac = e["true_pair_fraction"]
            print(f"{name:14s} {proxy_name:24s} L_sun {np.round(e['sun_radiance'], 3)} truth "
                  f"{np.round(e['sun_radiance_truth'], 3)} rel {np.round(e['sun_radiance_rel_error'], 3)}  "
                  f"pairs {e['pairs']}/{e['samples']} true {'-' if frac is None else f'{frac:.2f}'}  "
                  f"LMSE_R {e['scores']['lmse_reflectance']:.4f} LMSE_S {e['scores']['lmse_shading']:.4f} "
                  f"BER {e['scores']['ber']:.3f}  {e['seconds']:.1f} s", flush=True)
        report["scenes"][name] = entry
    if args.timing is not None:
        report["timing"] = {"scene": str(args.timing), **timing(args.timing, config)}
    if args.out is not None:
        write_json(args.out, report)
        print(f"wrote {args.out}")
    if args.history is not None:
        history = {"stage": "step2", "version": mvintrinsic.__version__, "proxy": "mvs (scene's proxy.ply)",
                   "scenes": {n: e["mvs"]["scores"] | {"sun_radiance_rel_error": e["mvs"]["sun_radiance_rel_error"]}
                              for n, e in report["scenes"].items()}}
        write_json(args.history, history)
        print(f"wrote {args.history}")


if __name__ == "__main__":
    main()
