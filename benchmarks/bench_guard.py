"""The accuracy guard's figures and their noise margins, on the embedded demo (issue 19).

    python benchmarks/bench_guard.py [--seeds 5] [--out benchmarks/results/accuracy_guard.json]

``tests/test_accuracy_guard.py`` decomposes the embedded demo scene (``mvintrinsic demo``'s, 240x180,
6 views, with ground truth and relit renders) with the default :class:`~mvintrinsic.Config` and fails
when a figure is worse than the one committed here by more than its margin. This benchmark
measures both:

* the figures: mean over views of the reflectance LMSE, the shading LMSE and the shadow BER
  (:func:`mvintrinsic.evaluation.evaluate`), and the relit PSNR of the full pipeline at each of the
  demo's relit suns (``gt/relit/<tag>``, :func:`bench_relight.relit_psnr`, mean over views), with
  the default configuration (``seed=0``);
* the noise: the same figures with ``Config(seed=k)`` for ``k = 0 .. seeds - 1``. The seed draws
  Step 1's rays and sample points, the exposure's pairs and every other random choice of the
  method, so its spread is how far a figure moves under a change that does not change the method.
  The margin of a figure is three standard deviations of its values over the seeds (sample
  standard deviation), and never less than the largest distance of a seed's value from the
  default's: a change of the code that moves a figure by more is more than another draw of the
  random samples.

Run with the package importable; about 25 s per seed on 2 cores.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from bench_relight import mean_psnr, relit_tags

import mvintrinsic
from mvintrinsic import Config, decompose, load_scene, save_decomposition
from mvintrinsic.cli import demo_scene_path
from mvintrinsic.evaluation import evaluate, read_ground_truth
from mvintrinsic.io import write_json
from mvintrinsic.relight import Relighter

#: The figures guarded: the key of :func:`mvintrinsic.evaluation.evaluate`'s mean, and whether larger is better.
DECOMPOSITION_FIGURES = {"lmse_reflectance": False, "lmse_shading": False, "ber": False}
#: Standard deviations of the seed-to-seed spread in a margin.
SIGMAS = 3.0


def measure(folder: Path, seed: int) -> dict[str, float]:
    """The guarded figures of the decomposition of ``folder`` with ``Config(seed=seed)``."""
    scene = load_scene(folder)
    result = decompose(scene, config=Config(seed=seed))
    with tempfile.TemporaryDirectory() as tmp:
        save_decomposition(result, Path(tmp) / "result")
        scores = evaluate(folder, Path(tmp) / "result")["mean"]
    figures = {key: float(scores[key]) for key in DECOMPOSITION_FIGURES}
    sky = {s: t.sky_mask for s, t in read_ground_truth(folder, views=list(scene.stems)).items()}
    relighter = Relighter(result, scene)
    for tag, (direction, images, _) in relit_tags(folder, scene.stems).items():
        figures[f"relit_psnr_{tag}"] = mean_psnr(relighter.render(direction), images, sky)["mean"]
    return figures


def margins(runs: list[dict[str, float]]) -> dict[str, float]:
    """Per figure: max(SIGMAS x sample std over the runs, largest |run - runs[0]|)."""
    out = {}
    for key in runs[0]:
        values = np.array([r[key] for r in runs])
        out[key] = float(max(SIGMAS * values.std(ddof=1), np.abs(values - values[0]).max()))
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=5, help="seeds 0 .. N-1 (N >= 2; 0 is the default)")
    parser.add_argument("--out", type=Path, default=None, help="JSON report")
    args = parser.parse_args(argv)
    if args.seeds < 2:
        parser.error("--seeds must be at least 2 (a spread needs two runs)")
    folder = demo_scene_path()
    runs, seconds = [], []
    for seed in range(args.seeds):
        start = time.perf_counter()
        runs.append(measure(folder, seed))
        seconds.append(time.perf_counter() - start)
        print(f"seed {seed}: " + " ".join(f"{k} {v:.4f}" for k, v in runs[-1].items()) + f" ({seconds[-1]:.1f} s)",
              flush=True)
    margin = margins(runs)
    report = {"benchmark": "accuracy_guard", "version": mvintrinsic.__version__, "cores": os.cpu_count(),
              "python": platform.python_version(), "scene": "embedded demo",
              "figures": runs[0], "margins": margin, "sigmas": SIGMAS,
              "larger_is_better": {k: k.startswith("relit_psnr") for k in runs[0]},
              "seeds": {str(i): r for i, r in enumerate(runs)}, "seconds_per_seed": float(np.mean(seconds))}
    for key, value in runs[0].items():
        print(f"{key}: {value:.4f} +- {margin[key]:.4f}")
    if args.out:
        write_json(args.out, report)
    return 0


if __name__ == "__main__":
    sys.exit(main())
