"""Step 1 accuracy on several scenes, with the MVS-like proxy and with a clean proxy.

    python benchmarks/bench_step1_accuracy.py [--make] [--out benchmarks/results/step1_accuracy.json]
    python benchmarks/bench_step1_accuracy.py --seeds 4 --out benchmarks/results/step1_seeds.json

Scenes: the embedded demo, ``../shared/datasets/dev_courtyard`` (made by another tool) and two
synthetic scenes rendered on demand with ``--make`` under ``../data/`` (courtyard seed 1 and
street seed 0, 8 views 240x180, 128 spp, sun drawn from the seed). For each scene and proxy:

* ``S_env = S_sky + S_ind`` against ``gt/env_shading`` in GT-shadowed pixels (median relative
  error per channel, both sides averaged over 5x5 masked windows against render noise,
  ``mvintrinsic.evaluation.env_shading_error``) and its signed median (bias); the same in the
  umbra only (``env_umbra``: no part of the sun's disc reaches the pixel,
  ``mvintrinsic.evaluation.umbra_mask``), where the two ground-truth conventions for partial sun
  agree (``docs/step1.md``);
* the proxy sun visibility ``~v`` against ``gt/sun_visibility`` (balanced error rate);
* the fitted sky against Mitsuba's Hosek-Wilkie sky (the renderer's, turbidity from
  ``gt/scene_info.json``) over the sky texels the views saw, and over the whole upper hemisphere
  (relative RMSE, solid-angle weighted; texels within 5 degrees of the sun excluded);
* the same ``S_env`` error with the true Hosek-Wilkie sky put into the environment map, which
  separates the sky model's share of the error from the rest;
* the indirect attenuation factor (``Step1Config.indirect_attenuation``) on every hit (the paper,
  entries ``mvs`` and ``clean``), only on unseen vertices' radiance (``*_unseen_attenuation``),
  and, with the clean proxy, nowhere (``clean_no_attenuation``).

With ``--seeds N`` it runs only the clean proxy, with the paper's attenuation and with
``"unseen"``, for ray seeds ``0 .. N-1``, and reports the ``S_env`` errors per seed: how much of a
difference between settings or from the issue's 25% is Monte Carlo noise.

The clean proxy is the scene's ``proxy_clean.ply`` (the exact mesh) subdivided to 20 cm edges
within 30 m of the cameras (``mvintrinsic.raytrace.subdivide``): its triangles are metres wide
and Step 1 carries its quantities on vertices.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import platform
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

import mvintrinsic
from mvintrinsic import Scene
from mvintrinsic.env_shading import Step1Config, environment_shading, step1
from mvintrinsic.environment import EnvironmentMap
from mvintrinsic.envmap import envmap_directions, texel_solid_angles
from mvintrinsic.evaluation import env_shading_error, umbra_mask, visibility_error
from mvintrinsic.io import load_scene, read_proxy, write_json
from mvintrinsic.raytrace import Tracer, interpolate_points, rasterize, subdivide, voxel_subsample

ROOT = Path(__file__).resolve().parents[2]
SYNTH = {"courtyard_s1": ("courtyard", 1), "street_s0": ("street", 0)}
CLEAN_MAX_EDGE = 0.2  # m
CLEAN_RADIUS = 30.0  # m around the cameras' centroid


def scenes(make: bool) -> dict[str, Path]:
    from mvintrinsic.cli import demo_scene_path

    out = {"demo": demo_scene_path(), "dev_courtyard": ROOT / "shared" / "datasets" / "dev_courtyard"}
    for name, (recipe, seed) in SYNTH.items():
        folder = ROOT / "data" / name
        if not (folder / "scene.json").is_file():
            if not make:
                continue
            from mvintrinsic.synth.dataset import SynthConfig, synthesize
            from mvintrinsic.synth.render import RenderConfig

            synthesize(recipe, folder, config=SynthConfig(n_views=8, width=240, height=180, relit=(), seed=seed,
                                                          render=RenderConfig(spp=128)), progress=True)
        out[name] = folder
    return {k: v for k, v in out.items() if (v / "scene.json").is_file()}


def hosek_sky(sun: np.ndarray, turbidity: float, directions: np.ndarray) -> np.ndarray | None:
    from mvintrinsic.synth.render import sky_radiance

    try:
        return sky_radiance(sun, directions, turbidity=turbidity)
    except ImportError:  # Mitsuba absent: no true sky to compare with
        return None


def relative_rmse(a: np.ndarray, b: np.ndarray, w: np.ndarray) -> float:
    return float(np.sqrt((w[:, None] * (a - b) ** 2).sum() / (w[:, None] * b**2).sum()))


@functools.cache
def umbra_of(folder: Path) -> dict:
    return umbra_mask(folder)


def env_errors(folder: Path, scene: Scene, result, tracer: Tracer, *, lit: bool = False) -> dict:
    """``S_env`` of a Step-1 result rasterised into the views, scored in GT shadow, in the umbra (and lit)."""
    env = {v.stem: rasterize(result.shading.env, v.camera, tracer) for v in scene.views}
    out = {"env_shadow": env_shading_error(folder, env, region="shadow"),
           "env_umbra": env_shading_error(folder, env, region="umbra", umbra=umbra_of(folder))}
    if lit:
        out["env_lit"] = env_shading_error(folder, env, region="lit")
    return out


def clean_proxy(folder: Path, base: Scene):
    centers = np.array([v.camera.center for v in base.views])
    return subdivide(read_proxy(folder / "proxy_clean.ply"), max_edge=CLEAN_MAX_EDGE, center=centers.mean(axis=0),
                     radius=CLEAN_RADIUS)


def seed_study(folder: Path, base: Scene, config: Step1Config, seeds: int) -> dict:
    """``S_env`` errors (GT shadow and umbra) with the clean proxy for ray seeds ``0 .. seeds - 1``."""
    proxy = clean_proxy(folder, base)
    scene, tracer = Scene(base.views, proxy, base.sun, base.up), Tracer(proxy)
    out = {}
    for attenuation in ("all", "unseen"):
        rows = []
        for seed in range(seeds):
            result = step1(scene, config=replace(config, indirect_attenuation=attenuation), tracer=tracer, rng=seed)
            errors = env_errors(folder, scene, result, tracer)
            rows.append({"seed": seed} | {k: e["median_rel_error"] for k, e in errors.items()})
            print(f"{folder.name:14s} clean {attenuation:7s} seed {seed}  S_env shadow err "
                  f"{np.round(rows[-1]['env_shadow'], 3)} umbra {np.round(rows[-1]['env_umbra'], 3)}", flush=True)
        worst = {k: np.max([r[k] for r in rows], axis=0).tolist() for k in ("env_shadow", "env_umbra")}
        out[attenuation] = {"runs": rows, "worst": worst}
    return out


def evaluate(folder: Path, scene: Scene, config: Step1Config) -> dict:
    start = time.perf_counter()
    result = step1(scene, config=config, rng=0)
    seconds = time.perf_counter() - start
    tracer = Tracer(scene.proxy)
    vis = {v.stem: rasterize(result.shading.visibility, v.camera, tracer) for v in scene.views}
    out = {
        "vertices": int(len(scene.proxy.vertices)),
        "seconds": seconds,
        "timings": dict(result.timings),
        "turbidity": result.sky_model.turbidity,
        "sky_texels": result.sky_model.n_texels,
        **env_errors(folder, scene, result, tracer, lit=True),
        "visibility": visibility_error(folder, vis),
    }
    info_file = folder / "gt" / "scene_info.json"
    info = json.loads(info_file.read_text()) if info_file.is_file() else {}
    turbidity = info.get("sky", {}).get("turbidity")
    he = result.environment.radiance.shape[0]
    d = envmap_directions(he, up=scene.up).reshape(-1, 3)
    true = hosek_sky(scene.sun.direction, turbidity, d) if turbidity is not None else None
    if true is not None:
        w = texel_solid_angles(he).reshape(-1)
        model = result.sky_model.radiance(d)
        above = d @ scene.up > 0
        near_sun = d @ scene.sun.direction > np.cos(np.radians(5.0))
        seen = result.environment.observed.reshape(-1) & result.environment.sky.reshape(-1) & ~near_sun
        hemi = above & ~near_sun
        out["sky_rel_rmse_seen"] = relative_rmse(model[seen], true[seen], w[seen])
        out["sky_rel_rmse_hemisphere"] = relative_rmse(model[hemi], true[hemi], w[hemi])
        # the same S_env with the true sky in the map: the sky model's share of the error
        halo = d @ scene.sun.direction > np.cos(np.radians(3.0))
        ring = (d @ scene.sun.direction > np.cos(np.radians(6.0))) & ~halo
        true[halo] = np.median(true[ring], axis=0)
        radiance = result.environment.radiance.reshape(-1, 3).copy()
        radiance[above] = true[above]
        exact_sky = EnvironmentMap(radiance=radiance.reshape(he, 2 * he, 3).astype(np.float32),
                                   sky=above.reshape(he, 2 * he), observed=result.environment.observed,
                                   up=result.environment.up, horizon_normal=result.environment.horizon_normal)
        points, normals = scene.proxy.vertices, scene.proxy.normals
        traced = voxel_subsample(points, config.subsample)
        sky, ind = environment_shading(points[traced], normals[traced], tracer, exact_sky, result.radiance,
                                       n_rays=config.n_rays, ray_offset=config.ray_offset,
                                       attenuation=config.indirect_attenuation, rng=0)
        both = interpolate_points(points[traced], normals[traced], sky + ind, points, normals,
                                  neighbors=config.interpolation_neighbors)
        env_true_sky = {v.stem: rasterize(both, v.camera, tracer) for v in scene.views}
        out["env_shadow_true_sky"] = env_shading_error(folder, env_true_sky, region="shadow")
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--make", action="store_true", help="render the synthetic scenes that are absent")
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--seeds", type=int, default=None, metavar="N",
                        help="only the clean proxy, for ray seeds 0 .. N-1 (Monte Carlo spread of S_env's error)")
    args = parser.parse_args()
    config = Step1Config()
    report = {"benchmark": "step1_accuracy", "version": mvintrinsic.__version__, "cores": os.cpu_count(),
              "python": platform.python_version(), "config": {"n_rays": config.n_rays, "subsample": config.subsample,
                                                               "ray_offset": config.ray_offset}, "scenes": {}}
    if args.seeds is not None:
        if args.seeds < 1:
            parser.error(f"--seeds must be at least 1, got {args.seeds}")
        report["benchmark"] = "step1_seeds"
        for name, folder in scenes(args.make).items():
            report["scenes"][name] = seed_study(folder, load_scene(folder), config, args.seeds)
        if args.out is not None:
            write_json(args.out, report)
            print(f"wrote {args.out}")
        return
    for name, folder in scenes(args.make).items():
        base = load_scene(folder)
        clean = clean_proxy(folder, base)
        entry = {}
        # (entry key, proxy, indirect attenuation): the paper's factor on every hit is the default
        runs = (("mvs", base.proxy, "all"), ("clean", clean, "all"), ("mvs_unseen_attenuation", base.proxy, "unseen"),
                ("clean_unseen_attenuation", clean, "unseen"), ("clean_no_attenuation", clean, "none"))
        for key, proxy, attenuation in runs:
            entry[key] = e = evaluate(folder, Scene(base.views, proxy, base.sun, base.up),
                                      replace(config, indirect_attenuation=attenuation))
            print(f"{name:14s} {key:24s} {e['vertices']:8d} v  S_env shadow err "
                  f"{np.round(e['env_shadow']['median_rel_error'], 3)} signed "
                  f"{np.round(e['env_shadow']['median_signed_rel_error'], 3)} umbra "
                  f"{np.round(e['env_umbra']['median_rel_error'], 3)} (true sky "
                  f"{np.round(e.get('env_shadow_true_sky', {}).get('median_rel_error', [np.nan] * 3), 3)})  "
                  f"BER {e['visibility']['ber']:.3f}  sky rmse seen {e.get('sky_rel_rmse_seen', np.nan):.3f} "
                  f"hemi {e.get('sky_rel_rmse_hemisphere', np.nan):.3f}  {e['seconds']:.1f} s", flush=True)
        report["scenes"][name] = entry
    if args.out is not None:
        write_json(args.out, report)
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
