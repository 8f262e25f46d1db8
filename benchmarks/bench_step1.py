"""Step 1 speed against accuracy: hemisphere rays per point and point subsampling.

    python benchmarks/bench_step1.py [SCENE] [--make] [--quick] [--out benchmarks/results/step1.json]

SCENE defaults to a 16-view courtyard with a ~1M-vertex MVS-like proxy, rendered on demand with
``--make`` (``mvintrinsic synth courtyard SCENE --views 16 --size 320x240 --spp 64 --relit none
--degrade voxel_size=0.02 --sun=-120,35``; about 4 minutes on 2 cores).

Measured:

* the shared part of Step 1 (tracer build, environment map and sky fit, vertex radiance);
* Embree throughput of the hemisphere rays, with points in Morton order and in random order;
* ``S_env = S_sky + S_ind`` at every proxy vertex for each (rays per point, subsample voxel)
  setting: wall-clock time, and the error against a 256-rays-per-point reference on a fixed
  random set of vertices (median and 90th percentile of the per-channel relative error);
* for the chosen default, the error against the ground truth ``gt/env_shading`` in GT-shadowed
  pixels (median relative error per channel, ``mvintrinsic.evaluation.env_shading_error``).

Writes JSON and a time-versus-error chart (PNG, needs matplotlib) next to ``--out``.
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

import numpy as np

import mvintrinsic
from mvintrinsic.env_shading import Step1Config, environment_shading, vertex_radiance
from mvintrinsic.environment import estimate_environment, horizon_plane
from mvintrinsic.io import load_scene, write_json
from mvintrinsic.raytrace import Tracer, depth_map, interpolate_points, rasterize, voxel_subsample

DEFAULT_SCENE = Path(__file__).resolve().parents[2] / "data" / "courtyard16"
REFERENCE_RAYS = 256
REFERENCE_POINTS = 20_000


def make_scene(folder: Path) -> None:
    from mvintrinsic.synth.dataset import SynthConfig, synthesize, with_overrides

    config = with_overrides(SynthConfig(n_views=16, width=320, height=240, relit=(), sun_azimuth_deg=-120.0,
                                        sun_elevation_deg=35.0), proxy_voxel_size=0.02, render_spp=64)
    synthesize("courtyard", folder, config=config, progress=True)


def env_error_in_gt_shadow(folder: Path, scene, tracer: Tracer, env: np.ndarray) -> list[float]:
    from mvintrinsic.evaluation import env_shading_error

    estimates = {v.stem: rasterize(env, v.camera, tracer) for v in scene.views}
    return env_shading_error(folder, estimates, region="shadow")["median_rel_error"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene", nargs="?", type=Path, default=DEFAULT_SCENE)
    parser.add_argument("--make", action="store_true", help="render the default scene if it is absent")
    parser.add_argument("--quick", action="store_true", help="smoke mode: few settings, few points")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    if not (args.scene / "scene.json").is_file():
        if not args.make:
            raise SystemExit(f"{args.scene}: no scene; pass --make to render it")
        make_scene(args.scene)

    report: dict = {"benchmark": "step1", "version": mvintrinsic.__version__, "cores": os.cpu_count(),
                    "python": platform.python_version(), "scene": str(args.scene)}
    t0 = time.perf_counter()
    scene = load_scene(args.scene)
    report["load_seconds"] = time.perf_counter() - t0
    proxy = scene.proxy
    report["vertices"], report["triangles"] = len(proxy.vertices), len(proxy.triangles)
    report["views"] = len(scene.views)
    config = Step1Config()
    timings = {}
    t0 = time.perf_counter()
    tracer = Tracer(proxy)
    timings["tracer"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    horizon = horizon_plane(proxy.vertices, up=scene.up, config=config.sky, rng=0)
    timings["horizon"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    depths = [depth_map(v.camera, tracer) for v in scene.views]
    uncovered = [np.isinf(d) & v.mask for d, v in zip(depths, scene.views, strict=True)]
    environment, sky_model = estimate_environment(scene.views, uncovered, sun_direction=scene.sun.direction,
                                                  horizon_normal=horizon.plane[:3], up=scene.up, config=config.sky)
    timings["environment"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    radiance, _ = vertex_radiance(scene.views, tracer, depths=depths)
    timings["vertex_radiance"] = time.perf_counter() - t0
    report["shared_seconds"] = timings
    report["sky_model"] = {"turbidity": sky_model.turbidity, "scale": sky_model.scale.tolist(),
                           "residual": sky_model.residual, "n_iter": sky_model.n_iter}

    points, normals = proxy.vertices, proxy.normals
    rng = np.random.default_rng(0)
    probe = rng.choice(len(points), size=min(REFERENCE_POINTS if not args.quick else 2000, len(points)),
                       replace=False)

    def shade(idx, n_rays, seed=1):
        sky, ind = environment_shading(points[idx], normals[idx], tracer, environment, radiance, n_rays=n_rays,
                                       ray_offset=config.ray_offset, rng=seed)
        return sky + ind

    t0 = time.perf_counter()
    reference = shade(probe, REFERENCE_RAYS, seed=99)
    report["reference"] = {"rays": REFERENCE_RAYS, "points": len(probe), "seconds": time.perf_counter() - t0}

    # Throughput, coherent (Morton) against incoherent (shuffled) ray batches.
    sample = rng.choice(len(points), size=min(50_000, len(points)), replace=False)
    from mvintrinsic.raytrace import cosine_hemisphere

    d = cosine_hemisphere(normals[sample], 64, rng=0).reshape(-1, 3)
    o = np.repeat(points[sample] + config.ray_offset * normals[sample], 64, axis=0)
    from mvintrinsic.raytrace import morton_order

    order = np.repeat(morton_order(points[sample]) * 64, 64) + np.tile(np.arange(64), len(sample))
    shuffled = rng.permutation(len(d))
    throughput = {}
    for name, perm in (("morton", order), ("shuffled", shuffled)):
        t0 = time.perf_counter()
        tracer.intersect(o[perm], d[perm])
        throughput[name] = len(d) / (time.perf_counter() - t0) / 1e6
    report["mrays_per_second"] = throughput

    settings = [(16, None), (32, None), (64, None), (32, 0.05), (64, 0.05), (64, 0.1), (128, 0.1), (64, 0.2)]
    if args.quick:
        settings = [(16, 0.2), (32, 0.2)]
    runs = []
    for n_rays, voxel in settings:
        t0 = time.perf_counter()
        traced = np.arange(len(points)) if voxel is None else voxel_subsample(points, voxel)
        env = shade(traced, n_rays)
        if voxel is not None:
            env = interpolate_points(points[traced], normals[traced], env, points, normals,
                                     neighbors=config.interpolation_neighbors)
        seconds = time.perf_counter() - t0
        rel = np.abs(env[probe] - reference) / np.maximum(reference, 1e-6)
        run = {"rays": n_rays, "subsample_m": voxel, "points_traced": int(len(traced)), "seconds": seconds,
               "median_rel_error": np.median(rel, axis=0).tolist(), "p90_rel_error": np.percentile(rel, 90, axis=0).tolist()}
        if not args.quick and (n_rays, voxel) == (config.n_rays, config.subsample):
            run["gt_shadow_median_rel_error"] = env_error_in_gt_shadow(args.scene, scene, tracer, env)
        runs.append(run)
        print(f"{n_rays:4d} rays, subsample {voxel!s:>5}: {len(traced):8d} points, {seconds:6.1f} s, "
              f"median rel. error vs {REFERENCE_RAYS}-ray reference {np.median(rel):.3f}")
    report["runs"] = runs
    report["default"] = {"rays": config.n_rays, "subsample_m": config.subsample}
    if args.out is not None:
        write_json(args.out, report)
        print(f"wrote {args.out}")
        try:
            import matplotlib

            matplotlib.use("Agg")
            import matplotlib.pyplot as plt
        except ImportError:
            return
        fig, ax = plt.subplots(figsize=(6, 4), constrained_layout=True)
        for run in runs:
            err = float(np.max(run["median_rel_error"])) * 100
            ax.scatter(run["seconds"], err, color="C0" if run["subsample_m"] is None else "C1")
            ax.annotate(f"{run['rays']} r, {run['subsample_m'] or 'all'}", (run["seconds"], err), fontsize=7,
                        xytext=(3, 3), textcoords="offset points")
        ax.axhline(5, color="grey", lw=0.8, ls="--")
        ax.axvline(30, color="grey", lw=0.8, ls="--")
        ax.set_xlabel(f"seconds for S_sky + S_ind at {len(points):,} vertices (2 cores)")
        ax.set_ylabel(f"median relative error vs {REFERENCE_RAYS}-ray reference (%)")
        ax.set_title("Step 1: speed against accuracy (blue: every vertex, orange: subsampled)")
        fig.savefig(args.out.with_suffix(".png"), dpi=120)


if __name__ == "__main__":
    main()
