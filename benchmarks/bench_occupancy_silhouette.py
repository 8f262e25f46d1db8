"""The relighter's ``lost_occluders`` with and without the proxy-silhouette band (``OccupancyConfig.silhouette``).

::

    python benchmarks/bench_occupancy_silhouette.py [--data DIR] --scene NAME [--scene NAME ...] [--out FILE]
    python benchmarks/bench_occupancy_silhouette.py --smoke

For each scene (``DIR/NAME`` rendered by ``mvintrinsic synth`` with relit renders under
``gt/relit/<tag>``; ``demo`` is the embedded demo, ``dev_courtyard`` the shared dataset), with its
MVS-like proxy, the whole pipeline (:func:`mvintrinsic.decompose`, default configuration) once, then
the relit PSNR above the input's (row (e) minus row (a) of ``benchmarks/bench_relight.py``) per tag
with three relighters:

* ``default``: :class:`~mvintrinsic.relight.RelightConfig` with ``lost_occluders=None`` (the
  relighter's default until 2026-11-29, when this study made the option its default);
* ``silhouette_0``: ``lost_occluders=OccupancyConfig()`` (``silhouette=0``, ``OccupancyConfig``'s
  default: every unexplained pixel is occupancy evidence);
* ``silhouette_1``: ``lost_occluders=OccupancyConfig(silhouette=1)`` (a band of 1 pixel; the
  relighter's default since 2026-11-29, ``mvintrinsic.caster.LOST_OCCLUDERS``).

and the rescued pixels (:attr:`~mvintrinsic.relight.Relighter.rescued`) per row as a share of the
pixels, and the cross-view agreement of the relit image's shadow layer away from the true relit
edges (``agreement_interior``, as row (e)'s in ``benchmarks/bench_relight.py``; added 2026-11-29).
``--smoke``: the demo only. Nothing is written unless ``--out`` is given.

All three with ``support_radius=0``: the study was made, and its JSON written, before the supported parts of the
shadow clusters (``RelightConfig.support_radius``, 2026-11-29), which add pixels to ``rescued``.
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import mvintrinsic
from mvintrinsic import Config, decompose
from mvintrinsic.env_shading import step1
from mvintrinsic.evaluation import read_ground_truth
from mvintrinsic.io import load_scene, write_json
from mvintrinsic.photo_occupancy import OccupancyConfig
from mvintrinsic.pipeline import carry_to_pixels
from mvintrinsic.raytrace import Tracer
from mvintrinsic.relight import RelightConfig, Relighter

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_relight import AGREEMENT_POINTS, mean_psnr, relit_agreement, relit_tags, shadow_layer  # noqa: E402
from bench_step4 import chosen_scene_folders, scene_study_parser  # noqa: E402

# Pinned to the relighter of the committed runs (support_radius 0, dropped "light": the defaults then).
ROWS = {"default": RelightConfig(lost_occluders=None, support_radius=0, dropped="light"),
        "silhouette_0": RelightConfig(lost_occluders=OccupancyConfig(), support_radius=0, dropped="light"),
        "silhouette_1": RelightConfig(lost_occluders=OccupancyConfig(silhouette=1), support_radius=0, dropped="light")}


def run_scene(folder: Path) -> dict:
    """The three rows of one scene (module docstring)."""
    scene = load_scene(folder)
    tags = relit_tags(folder, scene.stems)
    if not tags:
        raise SystemExit(f"{folder}: no relit renders under gt/relit")
    tracer = Tracer(scene.proxy)
    truth = read_ground_truth(folder, views=list(scene.stems))
    sky = {s: truth[s].sky_mask for s in scene.stems}
    inputs = {v.stem: v.image for v in scene.views}
    base = {tag: mean_psnr(inputs, images, sky)["mean"] for tag, (_, images, _) in tags.items()}
    result = decompose(scene, tracer=tracer)
    quantities = carry_to_pixels(scene, step1(scene, tracer=tracer, rng=Config().seed), tracer)
    points = scene.proxy.vertices[:: max(1, len(scene.proxy.vertices) // AGREEMENT_POINTS)]

    pixels = sum(v.mask.size for v in scene.views)
    out = {"size": list(scene.views[0].shape[::-1]), "views": len(scene.views)}
    for row, config in ROWS.items():
        relighter = Relighter(result, scene, config=config, tracer=tracer)
        out[row] = {"relit_minus_input": {tag: mean_psnr(relighter.render(direction), images, sky)["mean"] - base[tag]
                                          for tag, (direction, images, _) in tags.items()},
                    "rescued_share": sum(int(m.sum()) for m in relighter.rescued.values()) / pixels,
                    "agreement_interior": {tag: relit_agreement(scene, quantities, points, shadow_layer(
                        relighter, relighter.visibility_at(direction)), vis) for tag, (direction, _, vis) in tags.items()}}
        print(f"{folder.name} {row}: " + " ".join(f"{tag} {v:+.2f}" for tag, v in out[row]["relit_minus_input"].items())
              + f" rescued {out[row]['rescued_share']:.4f} agreement "
              + " ".join(f"{v:.3f}" for v in out[row]["agreement_interior"].values()), flush=True)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = scene_study_parser(__doc__.splitlines()[0])
    args = parser.parse_args(argv)
    scenes = {name: run_scene(folder) for name, folder in chosen_scene_folders(parser, args).items()}
    if args.out is not None:
        write_json(args.out, {"benchmark": "bench_occupancy_silhouette", "version": mvintrinsic.__version__,
                              "psnr": "relit PSNR minus the input's, dB (docs/metrics.md)",
                              "relight_configs": {name: dataclasses.asdict(config) for name, config in ROWS.items()},
                              "scenes": scenes})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
