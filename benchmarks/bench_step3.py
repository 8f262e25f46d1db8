"""Step 3 against Step 2 and the colour Retinex baseline, and Step 3's seconds per view.

    python benchmarks/bench_step3.py [--smoke] [--out benchmarks/results/step3.json]
                                     [--history benchmarks/results/accuracy_history/step3.json]
                                     [--timing SCENE] [--scene NAME ...]

For each scene of ``bench_step1_accuracy.py`` (the demo, ``../shared/datasets/dev_courtyard`` and,
when rendered, courtyard seed 1 and street seed 0), with the scene's own MVS-like proxy, the
Step-2 decomposition (``Config(steps=2)``), the Step-3 decomposition (default) and the colour
Retinex baseline (``benchmarks/baselines``) are scored by ``mvintrinsic.evaluation.evaluate``
(LMSE of reflectance and shading, BER of the shadow labels), mean over views. ``--timing SCENE``
decomposes SCENE at its full size (1000x750 for ``../data/courtyard_1000``) and reports the
seconds per view of segmentation, shadow MRF and matting. ``--smoke`` runs the demo only.
``--scene NAME`` (repeatable) adds ``../data/NAME`` (e.g. street_s2, demo_480 and street_sky, issue
16's scenes).
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

from bench_step1_accuracy import ROOT, scenes

import mvintrinsic
from mvintrinsic import Config, decompose
from mvintrinsic.evaluation import evaluate
from mvintrinsic.io import load_scene, save_decomposition, write_json

sys.path.insert(0, str(Path(__file__).resolve().parent / "baselines"))
from run_retinex import retinex_decomposition  # noqa: E402

SCORES = ("lmse_reflectance", "lmse_shading", "lmse_score", "ber")


def score(folder: Path, scene, result) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        save_decomposition(result, Path(tmp) / "result", scene=scene)
        mean = evaluate(folder, Path(tmp) / "result")["mean"]
    return {k: mean[k] for k in SCORES}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--smoke", action="store_true", help="the demo scene only")
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--history", type=Path, default=None, help="accuracy-history point (Step-3 scores)")
    parser.add_argument("--timing", type=Path, default=None, help="scene folder for the seconds per view")
    parser.add_argument("--scene", action="append", default=[], help="also ../data/NAME (repeatable)")
    args = parser.parse_args()
    report = {"benchmark": "step3", "version": mvintrinsic.__version__, "cores": os.cpu_count(),
              "python": platform.python_version(), "config": Config().to_dict(), "scenes": {}}
    chosen = scenes(False)
    if args.smoke:
        chosen = {"demo": chosen["demo"]}
    for name in args.scene:
        folder = ROOT / "data" / name
        if not (folder / "scene.json").is_file():
            parser.error(f"--scene {name}: no scene.json in {folder}")
        chosen[name] = folder
    for name, folder in chosen.items():
        scene = load_scene(folder)
        entry = {}
        for label in ("step2", "step3", "retinex"):
            start = time.perf_counter()
            if label == "retinex":
                result = retinex_decomposition(scene)
            else:
                result = decompose(scene, config=Config(steps=2 if label == "step2" else 3))
            entry[label] = score(folder, scene, result) | {"seconds": time.perf_counter() - start}
        report["scenes"][name] = entry
        print(f"{name:14s} " + "  ".join(
            f"{label}: LMSE_R {e['lmse_reflectance']:.4f} LMSE_S {e['lmse_shading']:.4f} "
            f"BER {'-' if e['ber'] is None else format(e['ber'], '.3f')}" for label, e in entry.items()), flush=True)
    if args.timing is not None:
        scene = load_scene(args.timing)
        h, w = scene.views[0].shape
        start = time.perf_counter()
        result = decompose(scene)
        total = time.perf_counter() - start
        n = len(scene.views)
        per_view = {k: result.timings[k] / n for k in ("pixels", "sun_pairs", "segmentation", "shadow_mrf", "matting")}
        step1 = sum(v for k, v in result.timings.items() if k.startswith("step1."))
        report["timing"] = {"scene": str(args.timing), "size": f"{w}x{h}", "views": n, "total_seconds": total,
                            "step1_seconds": step1, "seconds_per_view": per_view,
                            "step3_seconds_per_view": sum(per_view[k] for k in ("segmentation", "shadow_mrf", "matting"))}
        print(f"{w}x{h}, {n} views: step1 {step1:.1f} s; per view " +
              ", ".join(f"{k} {v:.2f} s" for k, v in per_view.items()) +
              f"; Step 3 {report['timing']['step3_seconds_per_view']:.1f} s per view; total {total:.1f} s")
    if args.out is not None:
        write_json(args.out, report)
        print(f"wrote {args.out}")
    if args.history is not None:
        write_json(args.history, {"stage": "step3", "version": mvintrinsic.__version__,
                                  "proxy": "mvs (scene's proxy.ply)",
                                  "scenes": {n: e["step3"] for n, e in report["scenes"].items()}})
        print(f"wrote {args.history}")


if __name__ == "__main__":
    main()
