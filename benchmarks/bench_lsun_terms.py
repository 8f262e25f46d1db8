"""Which term of Eq. 5 makes Step 2's ``L_sun`` wrong, with the scene's own MVS-like proxy (issue 16).

    python benchmarks/bench_lsun_terms.py [--data DIR] --scene NAME [--scene NAME ...] [--occluders] [--out FILE]

For each scene (``DIR/NAME``; ``demo`` is the embedded demo, ``dev_courtyard`` the shared dataset),
Step 2's light/shadow pairs are found as ``decompose`` finds them
(:func:`mvintrinsic.sun_calibration.find_sun_pairs` on Step 1's pixel quantities), and ``L_sun``
is recomputed by Eq. 5 (:func:`mvintrinsic.image_model.sun_radiance_from_pair`, per-channel
median over the pairs of all views, over the true ``L_sun``) with the terms swapped for the truth
one at a time:

* ``ours``: Step 1's ``S_env`` and sun cosine, lit visibility 1, shadowed 0 (Step 2 as it is);
* ``true_env``: ``gt/env_shading`` at both pixels;
* ``true_cosine``: the lit pixel's true ``cos`` (``gt/sun_shading / L_sun``, mean over RGB);
* ``true_env_cosine``: both;
* ``true_env_cosine_visibility``: both, and the shadowed pixel's true sun term
  (``gt/sun_shading / L_sun`` there: the partial sun a "shadowed" pixel receives);
* ``step3_labels``: ours, on the pairs whose lit pixel Step 3 (default labelling, no occluder
  carving) gives ``v_sun > 0.9`` and whose shadowed pixel ``v_sun < 0.1``.

With ``--occluders``, on the scenes where the default configuration carves the occluders the proxy
lost (:func:`mvintrinsic.model_choice.choose_occluders`), the same rows for the pipeline's second
pass: Step 1's shading integrated again with the carved voxels
(:func:`mvintrinsic.occluders.carve_occluders`, :func:`~mvintrinsic.occluders.occluded_step1`, from
the first pass's Step 3), the pairs found again on it, and ``step3_labels`` with the default
configuration's labels. Scenes where it does not carve are reported as the first pass.

And the pairs' quality against the truth: the share whose lit pixel is truly lit and whose shadowed
pixel truly shadowed (``gt/sun_visibility``), and the median of ``|R_lit / R_shadow - 1|`` (the
reflectances Eq. 5 assumes equal), before and after the label filter. Rows needing
``gt/sun_shading`` are None on scenes without it. Run with the package importable.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
from pathlib import Path

import numpy as np
from bench_step4 import ROOT, scene_folders

import mvintrinsic
from mvintrinsic import Config, decompose
from mvintrinsic.env_shading import step1
from mvintrinsic.evaluation import read_ground_truth, read_ground_truth_lighting
from mvintrinsic.image_model import sun_radiance_from_pair
from mvintrinsic.io import load_scene, write_json
from mvintrinsic.model_choice import choose_occluders
from mvintrinsic.occluders import OccluderConfig, carve_occluders, occluded_step1
from mvintrinsic.pipeline import carry_to_pixels
from mvintrinsic.raytrace import Tracer
from mvintrinsic.sun_calibration import find_sun_pairs

ROWS = ("ours", "true_env", "true_cosine", "true_env_cosine", "true_env_cosine_visibility", "step3_labels")


def _median_ratio(values: list[np.ndarray], truth: np.ndarray) -> list[float] | None:
    values = [v for v in values if v is not None and len(v)]
    if not values:
        return None
    return (np.nanmedian(np.concatenate(values), axis=0) / truth).round(4).tolist()  # NaN: no true sun term there


def _quality(lit_v, shadow_v, ratio) -> dict:
    return {"pairs": int(len(ratio)), "lit_truly_lit": float((lit_v > 0.5).mean()) if len(ratio) else None,
            "shadow_truly_shadowed": float((shadow_v < 0.5).mean()) if len(ratio) else None,
            "median_reflectance_mismatch": float(np.median(ratio)) if len(ratio) else None}


def bench_scene(folder: Path, *, occluders: bool = False) -> dict:
    scene = load_scene(folder)
    tracer = Tracer(scene.proxy)
    seed = Config().seed
    first = step1(scene, tracer=tracer, rng=seed)
    quantities = carry_to_pixels(scene, first, tracer)
    labelled = decompose(scene, tracer=tracer, config=Config(steps=3, occluders=None))
    carved = None
    if occluders:  # the second pass of the default configuration, where it carves
        carved = choose_occluders(quantities, labelled.layers, OccluderConfig()).choice == "carve"
        if carved:
            voxels = carve_occluders(scene.views, quantities, labelled.layers, first.radiance, tracer,
                                     scene.sun.direction, config=OccluderConfig())
            quantities = carry_to_pixels(scene, occluded_step1(first, tracer, voxels, rng=seed), tracer)
            labelled = decompose(scene, tracer=tracer, config=Config(steps=3))
    truth = read_ground_truth(folder, views=list(scene.stems))
    true_sun = np.asarray(read_ground_truth_lighting(folder).sun_radiance, dtype=np.float64)
    rows: dict[str, list] = {name: [] for name in ROWS}
    lit_v, shadow_v, mismatch, agreed = [], [], [], []
    for view in scene.views:
        pairs = find_sun_pairs(view, quantities[view.stem])
        if not len(pairs):
            continue
        q, gt, layer = quantities[view.stem], truth[view.stem], labelled.layers[view.stem]
        (lr, lc), (sr, sc) = pairs.lit.T, pairs.shadow.T
        i1, i2 = view.image[lr, lc].astype(np.float64), view.image[sr, sc].astype(np.float64)
        env1, env2 = q.env[lr, lc].astype(np.float64), q.env[sr, sc].astype(np.float64)
        true1, true2 = gt.env_shading[lr, lc].astype(np.float64), gt.env_shading[sr, sc].astype(np.float64)
        cos1 = q.cosine[lr, lc].astype(np.float64)
        one, zero = np.ones(len(i1)), np.zeros(len(i1))

        def eq5(e1, e2, c1, v2=zero, c2=zero, i1=i1, i2=i2, one=one):
            return sun_radiance_from_pair(i1, i2, e1, e2, one, v2, c1, c2)

        ours = eq5(env1, env2, cos1)
        rows["ours"].append(ours)
        rows["true_env"].append(eq5(true1, true2, cos1))
        if gt.sun_shading is not None:
            tcos1 = (gt.sun_shading[lr, lc].astype(np.float64) / true_sun).mean(axis=-1)
            tsun2 = (gt.sun_shading[sr, sc].astype(np.float64) / true_sun).mean(axis=-1)
            rows["true_cosine"].append(eq5(env1, env2, tcos1))
            rows["true_env_cosine"].append(eq5(true1, true2, tcos1))
            rows["true_env_cosine_visibility"].append(eq5(true1, true2, tcos1, one, tsun2))
        agree = (layer.visibility[lr, lc] > 0.9) & (layer.visibility[sr, sc] < 0.1)
        rows["step3_labels"].append(ours[agree])
        lit_v.append(gt.sun_visibility[lr, lc])
        shadow_v.append(gt.sun_visibility[sr, sc])
        r1, r2 = gt.reflectance[lr, lc].astype(np.float64), gt.reflectance[sr, sc].astype(np.float64)
        mismatch.append(np.abs(r1 / np.maximum(r2, 1e-4) - 1.0).mean(axis=-1))
        agreed.append(agree)
    lit_v, shadow_v = np.concatenate(lit_v), np.concatenate(shadow_v)
    mismatch, agreed = np.concatenate(mismatch), np.concatenate(agreed)
    out = {"views": len(scene.views), "size": "x".join(map(str, scene.views[0].shape[::-1])), "carved": carved,
           "lsun_over_truth": {name: _median_ratio(rows[name], true_sun) for name in ROWS},
           "pairs": _quality(lit_v, shadow_v, mismatch),
           "pairs_step3_labels": _quality(lit_v[agreed], shadow_v[agreed], mismatch[agreed])}
    print(f"{folder.name}: " + "  ".join(f"{k} {v}" for k, v in out["lsun_over_truth"].items()), flush=True)
    print(f"{folder.name}: pairs {out['pairs']}  with Step 3's labels {out['pairs_step3_labels']}", flush=True)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=ROOT / "data", help="folder of the rendered scenes")
    parser.add_argument("--scene", action="append", default=[], help="DATA/NAME, 'demo' or 'dev_courtyard'")
    parser.add_argument("--occluders", action="store_true",
                        help="the second pass where the default configuration carves the lost occluders")
    parser.add_argument("--out", type=Path, default=None, help="JSON report")
    args = parser.parse_args(argv)
    if not args.scene:
        parser.error("give --scene")

    report = {"benchmark": "lsun_terms", "version": mvintrinsic.__version__, "cores": os.cpu_count(),
              "python": platform.python_version(), "occluders": args.occluders, "scenes": {}}
    for name, folder in scene_folders(parser, args.scene, args.data).items():
        report["scenes"][name] = bench_scene(folder, occluders=args.occluders)
    if args.out:
        write_json(args.out, report)
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
