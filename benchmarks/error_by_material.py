"""Where a decomposition's errors are: shadow-label errors per material, LMSE in and outside foliage.

::

    python benchmarks/error_by_material.py SCENE RESULT [--out errors.json]
    python benchmarks/error_by_material.py SCENE --smooth-oracle SIGMA [--out errors.json]

``SCENE`` must carry the exact geometry with per-face materials (``gt/mesh.ply`` and
``gt/mesh_faces.npz``, as ``mvintrinsic synth`` and ``../shared/datasets/dev_courtyard`` write them);
``RESULT`` is a result folder of that scene (``mvintrinsic decompose``, or
``benchmarks/baselines/run_retinex.py`` for the baseline). Each pixel takes the material of the
exact mesh's face its camera ray hits first. Scored pixels are those ``evaluate`` scores
(``GroundTruth.valid`` and finite layers).

* **Shadow labels**, pooled over the views: per material, the GT-shadowed pixels labelled lit (FN)
  as a share of all GT-shadowed pixels, and the GT-lit pixels labelled shadow (FP) as a share of
  all GT-lit pixels. The pooled BER is half the sum of the two columns' totals, so each row is
  that material's share of the BER. Undecided labels are left out, as in ``evaluate``.
* **LMSE** (Grosse et al. 2009, ``mvintrinsic.metrics.lmse``, mean over views) of reflectance and
  shading over all scored pixels, outside the foliage (faces labelled ``foliage``, dilated by
  2 px) and inside it: tree crowns at these resolutions hold per-leaf shading that no proxy
  resolves.

``--smooth-oracle SIGMA`` scores, instead of a result folder, the best a method with smooth
environment shading can do: the exact sun term ``gt/sun_shading`` plus ``gt/env_shading`` blurred
by a Gaussian of SIGMA pixels (normalised within the scored pixels), reflectance = image / shading.

Nothing is written unless ``--out`` is given. Run with the package importable.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy import ndimage

import mvintrinsic  # noqa: F401  (loads libusb before open3d)
from mvintrinsic import metrics
from mvintrinsic.evaluation import read_ground_truth
from mvintrinsic.io import ResultFolderError, SceneError, load_decomposition, load_scene, read_proxy, write_json
from mvintrinsic.raytrace import Tracer
from mvintrinsic.results import SHADOW_LABELS, IntrinsicLayers

REGIONS = ("all", "outside_foliage", "foliage")


def material_maps(scene_folder: Path, scene) -> tuple[dict, dict, list[str], list[str]]:
    """Per view, the (H, W) material and label indices of the first exact-mesh face hit (-1 on a miss).

    Returns ``(materials, labels, material_names, label_names)``, the first two keyed by view stem.
    """
    faces_file = scene_folder / "gt" / "mesh_faces.npz"
    if not faces_file.is_file():
        raise FileNotFoundError(f"{faces_file}: per-face materials are needed (written by `mvintrinsic synth`)")
    faces = np.load(faces_file)
    tracer = Tracer(read_proxy(scene_folder / "gt" / "mesh.ply"))
    materials, labels = {}, {}
    for view in scene.views:
        hit = tracer.intersect(view.camera.center, view.camera.pixel_rays())
        face = np.maximum(hit.triangle, 0)
        materials[view.stem] = np.where(hit.hit, faces["material"][face], -1).reshape(view.camera.shape)
        labels[view.stem] = np.where(hit.hit, faces["label"][face], -1).reshape(view.camera.shape)
    return materials, labels, [str(m) for m in faces["material_names"]], [str(n) for n in faces["label_names"]]


def smooth_oracle(scene, truth: dict, sigma: float) -> dict[str, IntrinsicLayers]:
    """Layers from the exact sun term and the exact environment shading blurred by ``sigma`` px."""
    layers = {}
    for view in scene.views:
        gt = truth[view.stem]
        inside = gt.valid & np.isfinite(gt.env_shading).all(axis=2)
        weight = ndimage.gaussian_filter(inside.astype(float), sigma)
        env = np.stack([ndimage.gaussian_filter(np.where(inside, gt.env_shading[..., c], 0.0), sigma)
                        for c in range(3)], axis=2) / np.maximum(weight, 1e-9)[..., None]
        env = np.where(inside[..., None], env, 0.0)
        sun = np.where(inside[..., None], gt.sun_shading, 0.0)  # includes the visibility already
        total = sun + env
        ok = inside & (total > 0).all(axis=2)
        reflectance = np.where(ok[..., None], np.asarray(view.image, float) / np.where(ok[..., None], total, 1.0), 0.0)
        labels = np.where(gt.sun_visibility, SHADOW_LABELS["lit"], SHADOW_LABELS["shadow"])
        layers[view.stem] = IntrinsicLayers(
            stem=view.stem, reflectance=reflectance.astype(np.float32), sun_shading=sun.astype(np.float32),
            sky_shading=env.astype(np.float32), indirect_shading=np.zeros_like(env, dtype=np.float32),
            visibility=np.ones(inside.shape, dtype=np.float32),
            shadow_labels=np.where(ok, labels, SHADOW_LABELS["undecided"]).astype(np.uint8))
    return layers


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene", type=Path)
    parser.add_argument("result", type=Path, nargs="?", help="result folder")
    parser.add_argument("--smooth-oracle", type=float, metavar="SIGMA",
                        help="score the exact layers with env shading blurred by SIGMA px instead of RESULT")
    parser.add_argument("--out", type=Path, default=None, help="write the figures as JSON")
    args = parser.parse_args(argv)
    if (args.result is None) == (args.smooth_oracle is None):
        parser.error("give either RESULT or --smooth-oracle SIGMA")
    if args.smooth_oracle is not None and not args.smooth_oracle > 0:
        parser.error(f"--smooth-oracle must be a positive number of pixels, got {args.smooth_oracle}")
    try:
        return run(args)
    except (FileNotFoundError, SceneError, ResultFolderError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


def run(args: argparse.Namespace) -> int:
    """Score and print (and write with ``--out``); see the module docstring."""
    if args.result is not None:
        all_layers = load_decomposition(args.result).layers
        scene = load_scene(args.scene, views=sorted(all_layers))
        truth = read_ground_truth(args.scene, views=sorted(all_layers))
    else:
        scene = load_scene(args.scene)
        truth = read_ground_truth(args.scene)
        all_layers = smooth_oracle(scene, truth, args.smooth_oracle)
    materials, face_labels, names, label_names = material_maps(args.scene, scene)
    foliage_label = label_names.index("foliage") if "foliage" in label_names else None
    counts = np.zeros((len(names), 2), dtype=np.int64)  # (FN, FP) per material
    n_shadow = n_lit = 0
    missed = np.zeros(2, dtype=np.int64)  # (FN, FP) on pixels whose ray misses the exact mesh
    lmse = {r: {"reflectance": [], "shading": []} for r in REGIONS}
    for stem, layers in all_layers.items():
        gt = truth[stem]
        scored = gt.valid & np.isfinite(layers.reflectance).all(axis=2) & np.isfinite(layers.shading).all(axis=2)
        material = materials[stem]
        decided = scored & (layers.shadow_labels != SHADOW_LABELS["undecided"])
        true_shadow = ~gt.sun_visibility & decided
        true_lit = gt.sun_visibility & decided
        said_shadow = layers.shadow_labels == SHADOW_LABELS["shadow"]
        n_shadow += int(true_shadow.sum())
        n_lit += int(true_lit.sum())
        for i in range(len(names)):
            here = material == i
            counts[i] += [np.sum(here & true_shadow & ~said_shadow), np.sum(here & true_lit & said_shadow)]
        nowhere = material < 0
        missed += [np.sum(nowhere & true_shadow & ~said_shadow), np.sum(nowhere & true_lit & said_shadow)]
        foliage = np.zeros(material.shape, dtype=bool)
        if foliage_label is not None:
            foliage = ndimage.binary_dilation(face_labels[stem] == foliage_label, iterations=2)
        for region, mask in zip(REGIONS, (scored, scored & ~foliage, scored & foliage), strict=True):
            if mask.sum() < 400:  # too few pixels for 20 x 20 windows
                continue
            lmse[region]["reflectance"].append(metrics.lmse(layers.reflectance, gt.reflectance, mask=mask))
            lmse[region]["shading"].append(metrics.lmse(layers.shading, gt.shading, mask=mask))
    per_material = {names[i]: {"fn_share": counts[i, 0] / max(n_shadow, 1), "fp_share": counts[i, 1] / max(n_lit, 1)}
                    for i in range(len(names)) if counts[i].any()}
    if missed.any():
        per_material["(no exact-mesh hit)"] = {"fn_share": missed[0] / max(n_shadow, 1),
                                               "fp_share": missed[1] / max(n_lit, 1)}
    fnr = (counts[:, 0].sum() + missed[0]) / max(n_shadow, 1)
    fpr = (counts[:, 1].sum() + missed[1]) / max(n_lit, 1)
    report = {
        "scene": str(args.scene), "views": len(all_layers),
        "result": str(args.result) if args.result is not None else f"smooth oracle, sigma {args.smooth_oracle} px",
        "pooled_ber": 0.5 * (fnr + fpr), "fnr": fnr, "fpr": fpr, "per_material": per_material,
        "lmse": {r: {k: (float(np.mean(v)) if v else None) for k, v in d.items()} for r, d in lmse.items()},
    }
    print(f"pooled BER {report['pooled_ber']:.3f} (FNR {fnr:.3f}, FPR {fpr:.3f}); per material, share of "
          "GT shadow labelled lit (FN) and of GT lit labelled shadow (FP):")
    for name, row in sorted(per_material.items(), key=lambda kv: -(kv[1]["fn_share"] + kv[1]["fp_share"])):
        print(f"  {name:14s} FN {row['fn_share']:.3f}  FP {row['fp_share']:.3f}")
    for region, row in report["lmse"].items():
        text = "  ".join(f"LMSE_{k[0].upper()} {'-' if v is None else format(v, '.4f')}" for k, v in row.items())
        print(f"{region:16s} {text}")
    if args.out is not None:
        write_json(args.out, report)
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
