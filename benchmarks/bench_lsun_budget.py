"""Where the error of ``L_sun`` comes from, with the clean proxy (Step 1's ``S_env`` or Step 2's pairs).

    python benchmarks/bench_lsun_budget.py [--smoke] [--points N] [--spp N] [--out FILE]

For each scene of ``bench_step1_accuracy.scenes`` (the demo, ``../shared/datasets/dev_courtyard`` and
the synthetic courtyard seed 1 and street seed 0 when rendered), with the clean proxy (the exact
mesh subdivided to 20 cm) and the default configuration:

1. **Eq. 5 with parts of** ``S_env`` **replaced by the truth**, on the Step-2 pairs of the paper's
   pick (brightest lit, darkest shadowed) and of ``SunConfig(pick="median")``. ``S_env`` splits
   into the sky texels the Preetham model filled (no view saw them) and the rest; each part is
   ours or the truth, a 2 x 2 table. The true sky is Mitsuba's ``sunsky`` (the renderer's),
   traced over the proxy like ours; the true ``S_env`` is ``gt/env_shading``.
2. **Ray by ray, against the path tracer** (synthetic scenes whose ``gt/scene_info.json`` names
   the recipe, so the Mitsuba scene can be rebuilt): at the 3D points of the pairs' shadowed
   pixels, Step 1's cosine-weighted hemisphere rays are cast against the proxy as Step 1 casts
   them, and Mitsuba's path tracer (the integrator that rendered the images, ``--spp`` samples a
   ray) gives the radiance each ray truly brings. Our contribution of each ray (the environment
   map where it misses the proxy, the gathered vertex radiance times the attenuation factor where
   it hits) is compared with the truth, split by what the ray met: observed sky texels,
   model-filled sky texels, other texels, proxy vertices some view sees, vertices no view sees.

Both parts need Mitsuba (the ``render`` extra); without it only the rows that need no true sky
are written. ``--smoke``: the demo only, 40 points, 4 samples a ray.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from bench_step1_accuracy import clean_proxy, hosek_sky, scenes

import mvintrinsic
from mvintrinsic import Scene
from mvintrinsic.env_shading import environment_shading, fill_unseen, ray_radiance, step1
from mvintrinsic.envmap import direction_to_texel, envmap_directions
from mvintrinsic.evaluation import read_ground_truth, read_ground_truth_lighting
from mvintrinsic.image_model import sun_radiance_from_pair
from mvintrinsic.io import load_scene, write_json
from mvintrinsic.pipeline import Config, calibrate, carry_to_pixels
from mvintrinsic.raytrace import Tracer, cosine_hemisphere, interpolate_points, voxel_subsample

#: Hemisphere rays per point in part 2 (Step 1's default count).
RAYS = 64


def _traced_sky(scene: Scene, tracer: Tracer, result, radiance: np.ndarray, where: np.ndarray, config: Config):
    """``S_sky`` per vertex from the map texels ``where`` holding ``radiance``, traced as Step 1 traces."""
    points, normals = scene.proxy.vertices, scene.proxy.normals
    traced = voxel_subsample(points, config.step1.subsample)
    env = replace(result.environment, radiance=np.where(where[..., None], radiance, 0).astype(np.float32), sky=where)
    sky, _ = environment_shading(points[traced], normals[traced], tracer, env, np.zeros((len(points), 3)),
                                 n_rays=config.step1.n_rays, ray_offset=config.step1.ray_offset, rng=1)
    return interpolate_points(points[traced], normals[traced], sky, points, normals,
                              neighbors=config.step1.interpolation_neighbors)


def _as_pixels(scene: Scene, tracer: Tracer, result, values: np.ndarray) -> dict:
    shading = replace(result.shading, sky=values.astype(np.float32), indirect=np.zeros_like(result.shading.indirect))
    return {k: q.sky for k, q in carry_to_pixels(scene, replace(result, shading=shading), tracer).items()}


def _at(pairs, maps: dict, side: str) -> np.ndarray:
    """Values of per-view ``maps`` at the ``side`` ("lit" or "shadow") pixel of every pair, (P, C)."""
    return np.concatenate([maps[p.stem][getattr(p, side)[:, 0], getattr(p, side)[:, 1]] for p in pairs]
                          ).astype(np.float64)


def _eq5_error(image: dict, cosine: np.ndarray, truth: np.ndarray, env: dict) -> list:
    """Relative error of the per-channel median over the pairs of Eq. (5), given each pair's
    ``image`` and ``env`` (``S_env``) by side ("lit", "shadow") and the lit pixel's ``cosine``."""
    estimates = sun_radiance_from_pair(image["lit"], image["shadow"], env["lit"], env["shadow"],
                                       np.ones(len(cosine)), np.zeros(len(cosine)), cosine, np.zeros(len(cosine)))
    return np.round((np.median(estimates, axis=0) - truth) / truth, 4).tolist()


def eq5_table(folder: Path, info: dict, scene: Scene, tracer: Tracer, result, quantities, config: Config,
              pairs_by_pick: dict) -> dict:
    """Part 1: relative ``L_sun`` error of Eq. 5 with each part of ``S_env`` ours or true."""
    truth = read_ground_truth_lighting(folder).sun_radiance
    gt = read_ground_truth(folder)
    env = result.environment
    he = env.height
    turbidity = float(info.get("sky", {}).get("turbidity", 3.0))
    true_sky = hosek_sky(scene.sun.direction, turbidity, envmap_directions(he, up=scene.up).reshape(-1, 3))
    filled = env.sky & ~env.observed
    if true_sky is not None:
        ours_filled = _as_pixels(scene, tracer, result, _traced_sky(scene, tracer, result, env.radiance, filled, config))
        true_filled = _as_pixels(scene, tracer, result, _traced_sky(
            scene, tracer, result, true_sky.reshape(he, 2 * he, 3), filled, config))
    images = {v.stem: v.image for v in scene.views}
    cosines = {k: q.cosine for k, q in quantities.items()}
    ours_env = {k: q.env for k, q in quantities.items()}
    true_env = {k: g.env_shading for k, g in gt.items()}
    sides = ("lit", "shadow")
    out = {}
    for pick, pairs in pairs_by_pick.items():
        image = {s: _at(pairs, images, s) for s in sides}
        cosine = _at(pairs, cosines, "lit").reshape(len(image["lit"]), -1)[:, 0]
        ours = {s: _at(pairs, ours_env, s) for s in sides}
        true = {s: _at(pairs, true_env, s) for s in sides}
        rows = {"pairs": len(cosine), "ours": _eq5_error(image, cosine, truth, ours),
                "true": _eq5_error(image, cosine, truth, true)}
        if true_sky is not None:  # our minus the true sky of the model-filled texels, at each pixel
            delta = {s: _at(pairs, ours_filled, s) - _at(pairs, true_filled, s) for s in sides}
            rows["ours_with_true_filled_sky"] = _eq5_error(image, cosine, truth,
                                                           {s: ours[s] - delta[s] for s in sides})
            rows["true_with_our_filled_sky"] = _eq5_error(image, cosine, truth,
                                                          {s: true[s] + delta[s] for s in sides})
        out[pick] = rows
    return out


def ray_table(info: dict, scene: Scene, tracer: Tracer, result, config: Config, pairs: list, *,
              points: int, spp: int) -> dict | None:
    """Part 2: our per-ray contributions to ``S_env`` at the pairs' shadowed points against Mitsuba."""
    if "recipe" not in info:
        return None  # made by another tool: the Mitsuba scene cannot be rebuilt
    try:
        from mvintrinsic.synth.recipes import build_scene
        from mvintrinsic.synth.render import MitsubaScene, RenderConfig, import_mitsuba
        import_mitsuba()
    except ImportError:
        return None
    views = {v.stem: v for v in scene.views}
    origins, normals = [], []
    for p in pairs:
        camera = views[p.stem].camera
        rays = camera.pixel_rays(p.shadow[:, ::-1] + 0.5)
        hits = tracer.intersect(camera.center, rays)
        origins.append(hits.points[hits.hit])
        normals.append(hits.normals[hits.hit])
    origins, normals = np.concatenate(origins), np.concatenate(normals)
    rng = np.random.default_rng(0)
    if len(origins) > points:
        keep = rng.choice(len(origins), points, replace=False)
        origins, normals = origins[keep], normals[keep]
    directions = cosine_hemisphere(normals, RAYS, rng=1).reshape(-1, 3)
    starts = np.repeat(origins + config.step1.ray_offset * normals, RAYS, axis=0)
    hits = tracer.intersect(starts, directions)
    radiance = np.asarray(result.radiance, dtype=np.float64)
    unseen = (~np.isfinite(radiance).all(axis=1)).astype(np.float64)[:, None]
    filled = fill_unseen(radiance, scene.proxy.vertices)
    env = result.environment
    mode = config.step1.indirect_attenuation
    ours = np.add(*ray_radiance(tracer, hits, directions, env, filled, unseen, attenuation=mode))  # sky + indirect
    unattenuated = np.add(*ray_radiance(tracer, hits, directions, env, filled, unseen, attenuation="none"))
    unseen_share = tracer.interpolate(unseen, hits)[:, 0]
    miss = ~hits.hit
    rows_t, cols_t = direction_to_texel(directions, env.height, up=env.up)
    kind = np.full(len(directions), "proxy, unseen vertices", dtype=object)
    kind[hits.hit & (unseen_share <= 0.5)] = "proxy, seen vertices"
    kind[miss & env.sky[rows_t, cols_t] & env.observed[rows_t, cols_t]] = "sky, observed texels"
    kind[miss & env.sky[rows_t, cols_t] & ~env.observed[rows_t, cols_t]] = "sky, model-filled texels"
    kind[miss & ~env.sky[rows_t, cols_t]] = "other texels"

    render = RenderConfig(**info["config"]["render"])  # the renderer's settings of this scene
    synth = build_scene(info["recipe"], seed=info["seed"], gloss=info["config"].get("gloss", False))
    with tempfile.TemporaryDirectory() as work:  # the PLY files Mitsuba loads the meshes from
        mitsuba = MitsubaScene(synth, work)
        mi = mitsuba.mi
        mscene = mi.load_dict({"type": "scene", "integrator": {"type": "path", "max_depth": render.max_depth},
                               "emitter": mitsuba._emitter(np.array(info["sun_direction"]), render, sun=True,
                                                           sky=True),
                               **mitsuba.shapes})
    integrator = mscene.integrator()
    sampler = mi.load_dict({"type": "independent", "sample_count": spp})
    sampler.seed(0, 1)
    true = np.zeros((len(directions), 3))
    start = time.perf_counter()
    for i in range(len(directions)):
        ray = mi.Ray3f(mi.Point3f(*starts[i]), mi.Vector3f(*directions[i]))
        total = np.zeros(3)
        for _ in range(spp):
            value, _, _ = integrator.sample(mscene, sampler, ray)
            sampler.advance()
            total += (value[0], value[1], value[2])
        true[i] = total / spp
    seconds = time.perf_counter() - start
    n = len(directions)  # each ray's share of a point's S_env is 1 / RAYS; sums over points then / points
    table = {}
    for name in ("sky, observed texels", "sky, model-filled texels", "other texels", "proxy, seen vertices",
                 "proxy, unseen vertices", "all"):
        sel = np.ones(n, bool) if name == "all" else kind == name
        table[name] = {"ray_share": round(float(sel.mean()), 4),
                       "ours": np.round(ours[sel].sum(axis=0) / n, 5).tolist(),
                       "ours_unattenuated": np.round(unattenuated[sel].sum(axis=0) / n, 5).tolist(),
                       "true": np.round(true[sel].sum(axis=0) / n, 5).tolist()}
    total_true = true.sum(axis=0)
    return {"points": len(origins), "rays_per_point": RAYS, "spp": spp, "attenuation": mode,
            "mitsuba_seconds": round(seconds, 1), "components": table,
            "ours_over_true": np.round(ours.sum(axis=0) / total_true, 3).tolist()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--smoke", action="store_true", help="demo only, few points and samples")
    parser.add_argument("--points", type=int, default=400, help="shadowed points of part 2 per scene")
    parser.add_argument("--spp", type=int, default=16, help="path-tracer samples per ray in part 2")
    parser.add_argument("--out", type=Path, default=None, help="JSON report")
    args = parser.parse_args()
    chosen = scenes(False)
    if args.smoke:
        chosen, args.points, args.spp = {"demo": chosen["demo"]}, 40, 4
    config = Config()
    report = {"benchmark": "lsun_budget", "version": mvintrinsic.__version__, "cores": os.cpu_count(),
              "python": platform.python_version(), "proxy": "clean", "scenes": {}}
    for name, folder in chosen.items():
        base = load_scene(folder)
        proxy = clean_proxy(folder, base)
        scene, tracer = Scene(base.views, proxy, base.sun, base.up), Tracer(proxy)
        result = step1(scene, config=config.step1, tracer=tracer, rng=0)
        quantities = carry_to_pixels(scene, result, tracer)
        info = json.loads((folder / "gt" / "scene_info.json").read_text())
        pairs_by_pick = {pick: [p for p in calibrate(scene, quantities, config=replace(
            config, sun=replace(config.sun, pick=pick))).pairs if len(p)] for pick in ("extreme", "median")}
        entry = {"eq5": eq5_table(folder, info, scene, tracer, result, quantities, config, pairs_by_pick)}
        for pick, rows in entry["eq5"].items():
            print(f"{name:14s} pick {pick:8s} {rows['pairs']:4d} pairs  L_sun rel. error: "
                  + "  ".join(f"{k} {np.round(v, 2).tolist()}" for k, v in rows.items() if k != "pairs"), flush=True)
        rays = ray_table(info, scene, tracer, result, config, pairs_by_pick[config.sun.pick], points=args.points,
                         spp=args.spp)
        if rays is not None:
            entry["rays"] = rays
            for k, row in rays["components"].items():
                print(f"{name:14s}   {k:26s} rays {row['ray_share']:.3f}  ours {row['ours']}  "
                      f"unattenuated {row['ours_unattenuated']}  true {row['true']}", flush=True)
            print(f"{name:14s}   S_env ours / true {rays['ours_over_true']} ({rays['points']} points, "
                  f"{rays['mitsuba_seconds']} s of path tracing)", flush=True)
        report["scenes"][name] = entry
    if args.out is not None:
        write_json(args.out, report)
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
