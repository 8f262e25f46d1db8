"""Timing of the foundation: scene loading, ray generation, proxy ray casting, metrics.

asv-style classes (``setup`` + ``time_*``) that also run stand-alone::

    python benchmarks/bench_foundation.py [SCENE] [--quick] [--out benchmarks/results/foundation.json]

SCENE defaults to ../shared/datasets/dev_courtyard. ``--quick`` (a CI smoke mode) repeats each
measurement once. Results are written as JSON: best-of-N wall-clock seconds per benchmark plus the
machine's core count.
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

import numpy as np

import mvintrinsic as mvi
from mvintrinsic import metrics
from mvintrinsic.raytrace import Tracer

DEFAULT_SCENE = Path(__file__).resolve().parents[2] / "shared" / "datasets" / "dev_courtyard"


class SceneIO:
    def setup(self, scene=DEFAULT_SCENE):
        self.path = Path(scene)

    def time_load_scene(self):
        mvi.load_scene(self.path)


class RayCasting:
    def setup(self, scene=DEFAULT_SCENE):
        self.scene = mvi.load_scene(scene)
        self.tracer = Tracer(self.scene.proxy)
        self.camera = self.scene.views[0].camera
        self.rays = self.camera.pixel_rays()

    def time_build_tracer(self):
        Tracer(self.scene.proxy)

    def time_pixel_rays(self):
        self.camera.pixel_rays()

    def time_primary_rays_one_view(self):
        self.tracer.intersect(self.camera.center, self.rays)

    def time_shadow_rays_one_view(self):
        hits = self.tracer.intersect(self.camera.center, self.rays)
        ok = hits.hit
        self.tracer.occluded(hits.points[ok] + 1e-3 * hits.normals[ok], np.tile(self.scene.sun.direction, (ok.sum(), 1)))


class Metrics:
    def setup(self, scene=None):
        rng = np.random.default_rng(0)
        self.truth = rng.uniform(0.01, 1, (360, 480, 3))
        self.estimate = self.truth * rng.uniform(0.8, 1.2, self.truth.shape)
        self.mask = rng.uniform(size=(360, 480)) > 0.1

    def time_lmse_480x360(self):
        metrics.lmse(self.estimate, self.truth, mask=self.mask)

    def time_ssim_480x360(self):
        metrics.ssim(self.estimate, self.truth, mask=self.mask)


def run(scene: Path, repeat: int) -> dict:
    results = {}
    for cls in (SceneIO, RayCasting, Metrics):
        bench = cls()
        bench.setup(scene)
        for name in sorted(n for n in dir(bench) if n.startswith("time_")):
            best = np.inf
            for _ in range(repeat):
                start = time.perf_counter()
                getattr(bench, name)()
                best = min(best, time.perf_counter() - start)
            results[f"{cls.__name__}.{name}"] = best
            print(f"{cls.__name__}.{name:32s} {best * 1e3:9.2f} ms")
    return results


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene", nargs="?", type=Path, default=DEFAULT_SCENE)
    parser.add_argument("--quick", action="store_true", help="one repetition (smoke test)")
    parser.add_argument("--out", type=Path, default=None, help="JSON output file")
    args = parser.parse_args()
    timings = run(args.scene, 1 if args.quick else 5)
    report = {
        "benchmark": "foundation",
        "scene": str(args.scene),
        "version": mvi.__version__,
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "seconds_best": timings,
    }
    if args.out is not None:
        from mvintrinsic.io import write_json

        write_json(args.out, report)
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
