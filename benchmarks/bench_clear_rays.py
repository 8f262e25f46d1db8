"""Step 3's lit prior where the photographs see the sun ray free, on and off (``MultiViewShadowConfig.clear_rays``).

::

    python benchmarks/bench_clear_rays.py [--data DIR] --scene NAME [--scene NAME ...] [--out FILE [--merge]]
    python benchmarks/bench_clear_rays.py --smoke

For each scene (``DIR/NAME`` rendered by ``mvintrinsic synth``; ``demo`` is the embedded demo,
``dev_courtyard`` the shared dataset), with its MVS-like proxy, the whole pipeline
(:func:`mvintrinsic.decompose`, Steps 1-4, default configuration) twice: with the default
``clear_rays`` (``on``) and with ``clear_rays=None`` (``off``: the proxy's light weighted
``prior_lit`` everywhere, the labelling before it). Per variant:

* the shadow labels against ``gt/sun_visibility`` (lit at 0.5 or more), over the decided pixels:
  the balanced error as :func:`mvintrinsic.evaluation.evaluate` scores it (mean over views) and,
  pooled over the views, the false-positive rate (truly lit labelled shadow), the false-negative
  rate, precision and recall of the shadow class;
* reflectance and shading LMSE of the decomposition (:func:`~mvintrinsic.evaluation.evaluate`);
* where the scene has relit renders (``gt/relit/<tag>``), the relit PSNR above the input's (row
  (e) minus row (a) of ``benchmarks/bench_relight.py``) per tag, with
  :class:`~mvintrinsic.relight.RelightConfig` without ``lost_occluders`` (``relight``; the default
  until 2026-11-29) and with ``lost_occluders=OccupancyConfig()`` (``relight_lost_occluders``);
* the labelling's seconds (``shadow_labels``; ``shadow_labels.clear_rays`` the clear-ray test) per
  view.

``--smoke``: the demo only. Nothing is written unless ``--out`` is given; with ``--merge`` the scenes
are added to (or replace theirs in) an existing ``--out`` written by this benchmark.
"""

from __future__ import annotations

import dataclasses
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

import mvintrinsic
from mvintrinsic import Config, decompose
from mvintrinsic.evaluation import evaluate, read_ground_truth
from mvintrinsic.io import load_scene, save_decomposition, write_json
from mvintrinsic.photo_occupancy import OccupancyConfig
from mvintrinsic.raytrace import Tracer
from mvintrinsic.relight import RelightConfig, Relighter
from mvintrinsic.results import SHADOW_LABELS

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_relight import mean_psnr, relit_tags  # noqa: E402
from bench_step4 import chosen_scene_folders, scene_study_parser  # noqa: E402

VARIANTS = ("off", "on")


def variant_config(name: str) -> Config:
    """The default :class:`~mvintrinsic.Config` (``"on"``) or the same with ``multiview.clear_rays=None`` (``"off"``)."""
    config = Config()
    if name == "off":
        return dataclasses.replace(config, multiview=dataclasses.replace(config.multiview, clear_rays=None))
    if name != "on":
        raise ValueError(f"variant must be one of {VARIANTS}, got {name!r}")
    return config


def label_scores(labels: dict, truth: dict) -> dict:
    """Pooled over the views: false-positive and false-negative rates, precision and recall of the shadow
    class; ``labels``: stem -> (H, W) uint8 codes, ``truth``: stem -> ViewGroundTruth."""
    counts = np.zeros(4)  # true shadow labelled shadow, true shadow labelled lit, lit labelled shadow, lit labelled lit
    for stem, code in labels.items():
        lit = np.asarray(truth[stem].sun_visibility, dtype=np.float64) >= 0.5
        decided = code != SHADOW_LABELS["undecided"]
        shadow = code == SHADOW_LABELS["shadow"]
        counts += [(decided & ~lit & shadow).sum(), (decided & ~lit & ~shadow).sum(),
                   (decided & lit & shadow).sum(), (decided & lit & ~shadow).sum()]
    tp, fn, fp, tn = counts
    return {"fpr": float(fp / max(fp + tn, 1)), "fnr": float(fn / max(tp + fn, 1)),
            "precision": float(tp / max(tp + fp, 1)), "recall": float(tp / max(tp + fn, 1))}


#: The relighters (dropped "light": the default of the committed runs, so that --merge mixes like with like).
RELIGHT_CONFIGS = {"relight": RelightConfig(lost_occluders=None, dropped="light"),
                   "relight_lost_occluders": RelightConfig(lost_occluders=OccupancyConfig(), dropped="light")}


def run_scene(folder: Path) -> dict:
    """Both variants of one scene (module docstring)."""
    scene = load_scene(folder)
    tracer = Tracer(scene.proxy)
    truth = read_ground_truth(folder, views=list(scene.stems))
    tags = relit_tags(folder, scene.stems)
    sky = {s: truth[s].sky_mask for s in scene.stems}
    inputs = {v.stem: v.image for v in scene.views}
    base = {tag: mean_psnr(inputs, images, sky)["mean"] for tag, (_, images, _) in tags.items()}
    out = {"size": list(scene.views[0].shape[::-1]), "views": len(scene.views)}
    for name in VARIANTS:
        result = decompose(scene, config=variant_config(name), tracer=tracer)
        with tempfile.TemporaryDirectory() as tmp:
            save_decomposition(result, Path(tmp) / "result", scene=scene)
            mean = evaluate(folder, Path(tmp) / "result")["mean"]
        entry = {"ber": mean["ber"], "lmse_reflectance": mean["lmse_reflectance"], "lmse_shading": mean["lmse_shading"],
                 **label_scores({s: layer.shadow_labels for s, layer in result.layers.items()}, truth),
                 "seconds_per_view": {key: result.timings[key] / len(scene.views)
                                      for key in ("shadow_labels", "shadow_labels.clear_rays") if key in result.timings}}
        for row, config in RELIGHT_CONFIGS.items():
            if tags:
                relighter = Relighter(result, scene, config=config, tracer=tracer)
                entry[row] = {tag: mean_psnr(relighter.render(direction), images, sky)["mean"] - base[tag]
                              for tag, (direction, images, _) in tags.items()}
        out[name] = entry
        print(f"{folder.name} {name}: BER {entry['ber']:.4f} FPR {entry['fpr']:.4f} FNR {entry['fnr']:.4f} "
              f"LMSE R {entry['lmse_reflectance']:.4f} S {entry['lmse_shading']:.4f} "
              + " ".join(f"{row} {tag} {v:+.2f}" for row in RELIGHT_CONFIGS for tag, v in entry.get(row, {}).items()),
              flush=True)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = scene_study_parser(__doc__.splitlines()[0])
    parser.add_argument("--merge", action="store_true", help="add the scenes to an existing --out")
    args = parser.parse_args(argv)
    folders = chosen_scene_folders(parser, args)
    if args.merge and (args.out is None or not args.out.is_file()):
        parser.error("--merge needs an existing --out")
    scenes = json.loads(args.out.read_text())["scenes"] if args.merge else {}
    scenes.update({name: run_scene(folder) for name, folder in folders.items()})
    if args.out is not None:
        write_json(args.out, {"benchmark": "bench_clear_rays", "version": mvintrinsic.__version__,
                              "config": dataclasses.asdict(Config().multiview.clear_rays),
                              "relight_configs": {k: dataclasses.asdict(c) for k, c in RELIGHT_CONFIGS.items()},
                              "scenes": scenes})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
