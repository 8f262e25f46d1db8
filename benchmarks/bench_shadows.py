"""Shadow labels of the multi-view method against the paper's, on every scene with ground truth.

    python benchmarks/bench_shadows.py [--smoke] [--data DIR] [--make] [--scene NAME ...]
                                       [--out benchmarks/results/shadows.json]
                                       [--figure docs/images/shadows.png]

For each scene, the whole pipeline (``mvintrinsic.decompose``, Steps 1-3, the scene's own MVS-like
proxy) runs twice with the same Steps 1-2 (seeded, so identical): once with the paper's labelling
(``ShadowConfig(method="paper")``, Sec. 6.1 per view and cluster) and once with the multi-view
pixel labelling (the default, ``mvintrinsic.multiview_shadows``). Reported per method, mean over
views as ``mvintrinsic.evaluation.evaluate`` scores them:

* ``ber``: balanced error rate of the shadow labels against ``gt/sun_visibility`` (non-sky pixels
  with a true albedo above 0.01); ``precision`` and ``recall`` of the shadow class, pooled over
  the views;
* ``agreement``: of the proxy vertices seen by two or more views (depth test against each view's
  proxy depth, and the view's colour within 0.2 log-RGB of the point's median colour: views whose
  photo shows something the proxy lacks do not count), the share with one label in all of them
  (``mvintrinsic.correspondence.cross_view_agreement``); ``agreement_truth`` is the same measure
  on the true labels, the ceiling set by pixel quantisation and proxy error;
* ``lmse_reflectance``, ``lmse_shading``: Grosse et al.'s LMSE of Step 3's layers (``steps=3``: the
  labelling's own; Step 4 is measured by ``bench_step4.py``);
* ``consensus_passes``: the multi-view labels alone (no matting) with 0-3 passes of the
  cross-view consensus: BER and agreement;
* ``--agreement`` alone: the agreement of the true, paper and multi-view labels as above
  (``all``) and away from the true shadow edges (``interior``: no pixel within one pixel of an
  edge of ``gt/sun_visibility`` is read; :func:`agreement_scene`);
* ``seconds_per_view``: the labelling's stages (multi-view: ``shadow_labels.*``; paper:
  ``segmentation`` and ``shadow_mrf``), ``segmentation`` and ``matting``.

Scenes: the embedded demo (240x180), ``../shared/datasets/dev_courtyard`` (320x240) and the
scenes below under ``--data`` (default ``../data`` beside the checkout), rendered by
``mvintrinsic synth`` (``--make`` renders the missing ones; about 15 minutes each at 480x360 with
three relit suns, 20 with the five of today's default, and half an hour at 1000x750 on 2 cores)::

    mvintrinsic synth courtyard DATA/courtyard_s1 --views 8 --size 480x360 --seed 1
    mvintrinsic synth street DATA/street_s0 --views 8 --size 480x360 --seed 0
    mvintrinsic synth street DATA/street_s2 --views 8 --size 480x360 --seed 2
    mvintrinsic synth courtyard DATA/demo_480 --views 6 --size 480x360 --seed 0 --sun=-120,35 \\
        --degrade voxel_size=0.08
    mvintrinsic synth courtyard DATA/courtyard_1000 --views 6 --size 1000x750 --seed 2 --relit none
    mvintrinsic synth street DATA/street_1000 --views 8 --size 1000x750 --seed 2 --relit none
    mvintrinsic synth street DATA/street_sky --views 8 --size 480x360 --seed 1 --sky simulated

(64 samples per pixel, each scene with its own MVS-like proxy; ``demo_480`` is the embedded demo's
scene at twice its resolution, ``street_1000`` is ``street_s2``'s recipe and seed at 1000x750: the
same street with shadow edges sampled about twice as finely, where the true labels' own agreement
is no longer held below 95% by pixel quantisation; ``street_sky`` is lit by the simulated clear sky
of ``mvintrinsic.synth.atmosphere``, not the analytic sky family Step 1 fits). ``--smoke`` runs the demo
only (CI-sized: under a minute). Run with the package importable.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
from _figures import require_matplotlib
from scipy import ndimage

import mvintrinsic
from mvintrinsic import Config, decompose
from mvintrinsic.correspondence import cross_view_agreement
from mvintrinsic.env_shading import step1
from mvintrinsic.evaluation import evaluate, read_ground_truth
from mvintrinsic.io import load_scene, save_decomposition, write_json
from mvintrinsic.metrics import balanced_error_rate
from mvintrinsic.multiview_shadows import MultiViewShadowConfig, label_shadows_multiview
from mvintrinsic.pipeline import carry_to_pixels
from mvintrinsic.raytrace import Tracer
from mvintrinsic.results import SHADOW_LABELS
from mvintrinsic.shadow_mrf import ShadowConfig

ROOT = Path(__file__).resolve().parents[2]
#: name: (recipe, views, size, seed, extra synth arguments)
SYNTH = {
    "courtyard_s1": ("courtyard", 8, "480x360", 1, []),
    "street_s0": ("street", 8, "480x360", 0, []),
    "street_s2": ("street", 8, "480x360", 2, []),
    "demo_480": ("courtyard", 6, "480x360", 0, ["--sun=-120,35", "--degrade", "voxel_size=0.08"]),
    "courtyard_1000": ("courtyard", 6, "1000x750", 2, ["--relit", "none"]),
    "street_1000": ("street", 8, "1000x750", 2, ["--relit", "none"]),
    "street_sky": ("street", 8, "480x360", 1, ["--sky", "simulated"]),
}
METHODS = ("paper", "multiview")
#: At most this many proxy vertices are tested for cross-view agreement (every k-th).
AGREEMENT_POINTS = 300_000
#: Consensus passes compared (``consensus_passes`` in the report).
CONSENSUS_PASSES = (0, 1, 2, 3)


def scenes(data: Path, make: bool) -> dict[str, Path]:
    from mvintrinsic.cli import demo_scene_path
    from mvintrinsic.cli import main as cli

    out = {"demo": demo_scene_path(), "dev_courtyard": ROOT / "shared" / "datasets" / "dev_courtyard"}
    for name, (recipe, views, size, seed, extra) in SYNTH.items():
        folder = data / name
        if not (folder / "scene.json").is_file() and make:
            cli(["synth", recipe, str(folder), "--views", str(views), "--size", size, "--seed", str(seed), *extra])
        out[name] = folder
    found = {k: v for k, v in out.items() if (v / "scene.json").is_file()}
    for name in sorted(set(out) - set(found)):
        print(f"skipping {name}: {out[name]} not found (render it with --make)", file=sys.stderr)
    return found


def precision_recall(truth: dict, labels: dict) -> tuple[float | None, float | None]:
    """Pooled precision and recall of the shadow class over the scored, decided pixels."""
    tp = fp = fn = 0
    for stem, gt in truth.items():
        label = labels[stem]
        scored = gt.valid & (label != SHADOW_LABELS["undecided"])
        predicted = (label == SHADOW_LABELS["shadow"]) & scored
        actual = ~gt.sun_visibility & scored
        tp += int((predicted & actual).sum())
        fp += int((predicted & ~actual).sum())
        fn += int((~predicted & actual).sum())
    precision = tp / (tp + fp) if tp + fp else None
    recall = tp / (tp + fn) if tp + fn else None
    return precision, recall


def run_scene(folder: Path, multiview: MultiViewShadowConfig) -> dict:
    scene = load_scene(folder)
    truth = read_ground_truth(folder, views=[v.stem for v in scene.views])
    h, w = scene.views[0].shape
    entry: dict = {"size": f"{w}x{h}", "views": len(scene.views)}
    # The quantities the agreement is measured with (Steps 1 as decompose runs it: same seed).
    tracer = Tracer(scene.proxy)
    quantities = carry_to_pixels(scene, step1(scene, tracer=tracer, rng=Config().seed), tracer)
    points = scene.proxy.vertices[:: max(1, len(scene.proxy.vertices) // AGREEMENT_POINTS)]
    true_labels = {s: np.where(gt.sun_visibility, SHADOW_LABELS["lit"], SHADOW_LABELS["shadow"]).astype(np.uint8)
                   for s, gt in truth.items()}
    entry["agreement_truth"] = cross_view_agreement(scene.views, quantities, true_labels, points).fraction
    figure = {"image": scene.views[0].image, "truth": truth[scene.views[0].stem].sun_visibility}
    for method in METHODS:
        config = Config(shadow=ShadowConfig(method=method), multiview=multiview, steps=3)
        start = time.perf_counter()
        result = decompose(scene, config=config)
        sun_radiance = result.lighting.sun_radiance  # Step 2's, the same for both methods
        seconds = time.perf_counter() - start
        with tempfile.TemporaryDirectory() as tmp:
            save_decomposition(result, Path(tmp) / "result", scene=scene)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # single-class views are reported, not warned
                mean = evaluate(folder, Path(tmp) / "result")["mean"]
        labels = {s: layers.shadow_labels for s, layers in result.layers.items()}
        precision, recall = precision_recall(truth, labels)
        agreement = cross_view_agreement(scene.views, quantities, labels, points)
        stages = {k: v / len(scene.views) for k, v in result.timings.items()
                  if k in ("segmentation", "shadow_mrf", "matting") or k.startswith("shadow_labels")}
        labelling = stages.get("shadow_labels", stages.get("segmentation", 0.0) + stages.get("shadow_mrf", 0.0))
        entry[method] = {
            "ber": mean["ber"], "precision": precision, "recall": recall,
            "agreement": agreement.fraction, "agreement_points": agreement.points,
            "lmse_reflectance": mean["lmse_reflectance"], "lmse_shading": mean["lmse_shading"],
            "labelling_seconds_per_view": labelling, "seconds_per_view": stages,
            "decompose_seconds": seconds,
        }
        figure[method] = labels[scene.views[0].stem] == SHADOW_LABELS["shadow"]
        e = entry[method]
        print(f"{folder.name:15s} {method:9s} BER {e['ber']:.3f} (P {precision:.2f} R {recall:.2f}) "
              f"agreement {e['agreement']:.3f} (truth {entry['agreement_truth']:.3f}) "
              f"LMSE R {e['lmse_reflectance']:.4f} S {e['lmse_shading']:.4f} "
              f"labelling {labelling:.2f} s/view", flush=True)
    entry["ber_ratio"] = entry["multiview"]["ber"] / entry["paper"]["ber"]
    entry["consensus_passes"] = consensus_study(scene, quantities, sun_radiance, truth, points, multiview)
    return entry, figure


def consensus_study(scene, quantities, sun_radiance, truth, points, multiview: MultiViewShadowConfig) -> dict:
    """The multi-view labels with 0-3 consensus passes: mean per-view BER and cross-view agreement.

    Same inputs as the decomposition's (Steps 1-2 with the same seed), labels only, so it isolates
    the pass; the BER is :func:`mvintrinsic.metrics.balanced_error_rate` on the decided non-sky
    pixels, as :func:`~mvintrinsic.evaluation.evaluate` scores it.
    """
    out = {}
    corr = None
    for passes in CONSENSUS_PASSES:
        config = dataclasses.replace(multiview, consensus_passes=passes)
        shared = label_shadows_multiview(scene.views, quantities, sun_radiance, config=config, up=scene.up,
                                         correspondences=corr)
        corr = shared.correspondences
        labels = {s: shared[s].labels for s in truth}
        bers = []
        for stem, gt in truth.items():
            decided = gt.valid & (labels[stem] != SHADOW_LABELS["undecided"])
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                bers.append(balanced_error_rate(labels[stem] == SHADOW_LABELS["shadow"], ~gt.sun_visibility,
                                                mask=decided))
        agreement = cross_view_agreement(scene.views, quantities, labels, points).fraction
        out[str(passes)] = {"ber": float(np.nanmean(bers)), "agreement": agreement,
                            "consensus_seconds_per_view": shared.timings["consensus"] / len(scene.views)}
        print(f"    consensus passes {passes}: BER {out[str(passes)]['ber']:.3f} agreement {agreement:.3f}", flush=True)
    return out


def save_figure(panels: dict[str, dict], path: Path) -> None:
    """One row per scene: image, true shadow, paper labels, multi-view labels (shadow dark)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(panels), 4, figsize=(12, 2.4 * len(panels)), squeeze=False)
    for row, (name, p) in zip(axes, panels.items(), strict=True):
        image = np.clip(p["image"] / max(np.percentile(p["image"], 99), 1e-6), 0, 1) ** (1 / 2.2)
        for ax, (title, data) in zip(row, (("image", image), ("true sun visibility", p["truth"]),
                                           ("paper (Sec. 6.1)", ~p["paper"]), ("multi-view", ~p["multiview"])),
                                     strict=True):
            ax.imshow(data, cmap=None if data.ndim == 3 else "gray", vmin=0, vmax=1, interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_title(f"{name}: {title}" if title == "image" else title, fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def away_from_edges(labels: dict, true_lit: dict) -> dict:
    """``labels`` (codes per view) with every pixel within one pixel of a true shadow edge made undecided.

    ``true_lit`` holds each view's true sun visibility as (H, W) bool; undecided pixels (128) are
    not read by :func:`~mvintrinsic.correspondence.cross_view_agreement`.
    """
    return {stem: np.where(true_edge(true_lit[stem]), SHADOW_LABELS["undecided"], codes).astype(np.uint8)
            for stem, codes in labels.items()}


def true_edge(true_lit: np.ndarray) -> np.ndarray:
    """(H, W) bool: the pixels within one pixel (3x3) of an edge of the true sun visibility ``true_lit`` ((H, W) bool)."""
    lit = np.asarray(true_lit, dtype=bool)
    square = np.ones((3, 3), dtype=bool)
    return ndimage.binary_dilation(lit, square) & ndimage.binary_dilation(~lit, square)


def agreement_scene(folder: Path, multiview: MultiViewShadowConfig) -> dict:
    """Cross-view agreement of the true, paper and multi-view labels, everywhere and away from true edges.

    ``all``: the measure of :func:`run_scene`; ``interior``: the same with the pixels within one
    pixel of a true shadow edge (``gt/sun_visibility``, 3x3) not read in any labelling. Where a
    point's pixels straddle an edge the views read it on different sides at their own sampling,
    so even the true labels disagree there; away from the edges they agree.
    """
    scene = load_scene(folder)
    truth = read_ground_truth(folder, views=[v.stem for v in scene.views])
    tracer = Tracer(scene.proxy)
    quantities = carry_to_pixels(scene, step1(scene, tracer=tracer, rng=Config().seed), tracer)
    points = scene.proxy.vertices[:: max(1, len(scene.proxy.vertices) // AGREEMENT_POINTS)]
    true_lit = {s: gt.sun_visibility for s, gt in truth.items()}
    labellings = {"truth": {s: np.where(lit, SHADOW_LABELS["lit"], SHADOW_LABELS["shadow"]).astype(np.uint8)
                            for s, lit in true_lit.items()}}
    for method in METHODS:
        result = decompose(scene, config=Config(shadow=ShadowConfig(method=method), multiview=multiview, steps=3),
                           tracer=tracer)
        labellings[method] = {s: layers.shadow_labels for s, layers in result.layers.items()}
    out = {}
    for name, labels in labellings.items():
        everywhere = cross_view_agreement(scene.views, quantities, labels, points)
        interior = cross_view_agreement(scene.views, quantities, away_from_edges(labels, true_lit), points)
        out[name] = {"all": everywhere.fraction, "all_points": everywhere.points,
                     "interior": interior.fraction, "interior_points": interior.points}
    print(f"{folder.name:15s} agreement all / away from true edges: " + "  ".join(
        f"{k} {v['all']:.3f} / {v['interior']:.3f} (points {v['all_points']} / {v['interior_points']})"
        for k, v in out.items()), flush=True)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--smoke", action="store_true", help="the demo only")
    parser.add_argument("--data", type=Path, default=ROOT / "data", help="folder of the rendered scenes")
    parser.add_argument("--make", action="store_true", help="render missing scenes (needs Mitsuba)")
    parser.add_argument("--scene", action="append", default=None, help="only these scenes (names)")
    parser.add_argument("--agreement", action="store_true",
                        help="only the cross-view agreement, everywhere and away from true shadow edges")
    parser.add_argument("--edge-reference", type=int, default=None,
                        help="MultiViewShadowConfig.edge_reference for the multi-view labelling (default: its default)")
    parser.add_argument("--out", type=Path, default=None, help="JSON report")
    parser.add_argument("--figure", type=Path, default=None, help="PNG: image, truth, both labellings per scene")
    args = parser.parse_args(argv)
    require_matplotlib(parser, args, "figure")
    multiview = MultiViewShadowConfig()
    if args.edge_reference is not None:
        multiview = dataclasses.replace(multiview, edge_reference=args.edge_reference)
    if args.smoke:
        from mvintrinsic.cli import demo_scene_path

        chosen = {"demo": demo_scene_path()}
    else:
        chosen = scenes(args.data, args.make)
    if args.scene:
        chosen = {k: v for k, v in chosen.items() if k in args.scene}
    report = {"benchmark": "shadows", "version": mvintrinsic.__version__, "cores": os.cpu_count(),
              "python": platform.python_version(), "config": Config(multiview=multiview).to_dict(), "scenes": {}}
    if args.agreement:
        report["agreement"] = {name: agreement_scene(folder, multiview) for name, folder in chosen.items()}
        if args.out:
            write_json(args.out, report)
        return 0
    panels = {}
    for name, folder in chosen.items():
        report["scenes"][name], panels[name] = run_scene(folder, multiview)
    rows = report["scenes"].values()
    summary = {}
    for method in METHODS:
        bers = [r[method]["ber"] for r in rows]
        summary[method] = {"ber_mean": float(np.mean(bers)), "ber_max": float(np.max(bers)),
                           "agreement_min": float(np.min([r[method]["agreement"] for r in rows]))}
    summary["ber_ratio_max"] = float(np.max([r["ber_ratio"] for r in rows]))
    report["summary"] = summary
    print(f"mean BER: paper {summary['paper']['ber_mean']:.3f}, multi-view {summary['multiview']['ber_mean']:.3f}; "
          f"max {summary['paper']['ber_max']:.3f}, {summary['multiview']['ber_max']:.3f}; "
          f"largest multi-view / paper ratio {summary['ber_ratio_max']:.2f}")
    if args.out:
        write_json(args.out, report)
    if args.figure:
        save_figure(panels, args.figure)
    return 0


if __name__ == "__main__":
    sys.exit(main())
