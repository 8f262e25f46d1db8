"""Speed against accuracy: every preset of ``Config.preset`` on rendered scenes (issue 17's chart).

    python benchmarks/bench_pareto.py --data DIR --scene NAME [--scene NAME ...] [--preset P ...]
                                      [--out benchmarks/results/pareto.json] [--figure benchmarks/results/pareto.png]
    python benchmarks/bench_pareto.py --scaling --data DIR --scene NAME [--out ...]
    python benchmarks/bench_pareto.py --end-to-end PRESET --data DIR --scene NAME [--out ...]
    python benchmarks/bench_pareto.py --plot-only benchmarks/results/pareto.json [--figure PNG]
    python benchmarks/bench_pareto.py --smoke

Per scene (``DIR/NAME`` rendered by ``mvintrinsic synth``; ``demo`` the embedded demo) and preset
(:data:`mvintrinsic.pipeline.PRESETS`): seconds per view, total and per stage (the stages of
``Decomposition.timings``, Step 1's parts summed), reflectance and shading LMSE and shadow BER
(:func:`mvintrinsic.evaluation.evaluate`) and, where the scene has relit renders
(``gt/relit/<tag>``), the relit PSNR of the full pipeline (``benchmarks/bench_relight.py``'s
metric, default ``RelightConfig``, mean over tags; the relighter's build and render seconds are
not in the decomposition's). The colour Retinex baseline (``benchmarks/baselines``) is run on the
same scenes as a reference point. The figure plots seconds per view against each accuracy figure
(mean over the scenes), marks the Pareto front (no preset both faster and more accurate) and
draws the seconds per stage as stacked bars.

``--scaling`` measures how the cost grows with the default preset: seconds per view at working
scales 0.25, 0.5, 0.75 and 1 of the first scene's first four views (pixels per view) and for its
first 2, 4, 8, ... views at working scale 0.5, with the log-log slope fitted to each. ``--end-to-end PRESET`` times
``mvintrinsic decompose --preset PRESET`` on the first scene in a fresh process (loading and writing
included) and records its peak resident memory. ``--smoke`` runs "fast" and "balanced" on the demo.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from _figures import require_matplotlib

import mvintrinsic
from mvintrinsic import decompose
from mvintrinsic.evaluation import evaluate
from mvintrinsic.io import load_scene, save_decomposition, write_json
from mvintrinsic.pipeline import PRESETS, Config
from mvintrinsic.raytrace import Tracer

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE / "baselines"))

#: stages of the stacked bars: timing keys that start with the name (``step1.*`` summed)
STAGES = ("downscale", "depth_maps", "exposure", "step1", "pixels", "sun_pairs", "shadow_labels", "segmentation",
          "shadow_mrf", "matting", "layers", "step4", "upsample")


def stage_seconds(timings: dict, views: int) -> dict:
    """Seconds per view of each of :data:`STAGES` (the top-level keys; ``step1`` sums its parts)."""
    out = {}
    for stage in STAGES:
        if stage == "step1":
            value = sum(v for k, v in timings.items() if k.startswith("step1."))
        else:
            value = timings.get(stage, 0.0)
        if value:
            out[stage] = value / views
    return out


def relit_psnr(folder: Path, scene, result) -> float | None:
    """Mean relit PSNR of ``result`` over the scene's relit tags (None without relit renders)."""
    from bench_relight import mean_psnr, relit_tags

    from mvintrinsic.evaluation import read_ground_truth
    from mvintrinsic.relight import Relighter

    tags = relit_tags(folder, scene.stems)
    if not tags:
        return None
    truth = read_ground_truth(folder, views=list(scene.stems))
    sky = {s: truth[s].sky_mask for s in scene.stems}
    relighter = Relighter(result, scene)
    return float(np.mean([mean_psnr(relighter.render(direction), images, sky)["mean"]
                          for direction, images, _ in tags.values()]))


def score(folder: Path, scene, result, work: Path) -> dict:
    out = work / "result"
    save_decomposition(result, out, scene=scene, overwrite=True)
    mean = evaluate(folder, out)["mean"]
    return {key: mean[key] for key in ("lmse_reflectance", "lmse_shading", "ber")}


def bench_scene(folder: Path, presets: list[str], work: Path, *, max_views: int | None = None) -> dict:
    from run_retinex import retinex_decomposition

    scene = load_scene(folder)
    if max_views is not None:
        scene = dataclasses.replace(scene, views=scene.views[:max_views])
    views = len(scene.views)
    h, w = scene.views[0].shape
    entry = {"size": f"{w}x{h}", "views": views, "presets": {}}
    for name in presets:
        tracer = Tracer(scene.proxy)  # built anew: its seconds count, as in a user's first call
        start = time.perf_counter()
        result = decompose(scene, config=Config.preset(name), tracer=tracer)
        seconds = time.perf_counter() - start
        row = {"seconds_per_view": seconds / views, "stages": stage_seconds(dict(result.timings), views),
               **score(folder, scene, result, work),
               "model": {k: v.choice for k, v in result.lighting.model.items()}}
        row["relit_psnr"] = relit_psnr(folder, scene, result)
        entry["presets"][name] = row
        print(f"{folder.name:16s} {name:9s} {row['seconds_per_view']:6.2f} s/view  LMSE R {row['lmse_reflectance']:.4f} "
              f"S {row['lmse_shading']:.4f}  BER {row['ber']:.4f}  relit "
              f"{'-' if row['relit_psnr'] is None else format(row['relit_psnr'], '.2f')}", flush=True)
    start = time.perf_counter()
    retinex = retinex_decomposition(scene)
    seconds = time.perf_counter() - start
    entry["retinex"] = {"seconds_per_view": seconds / views, **score(folder, scene, retinex, work)}
    print(f"{folder.name:16s} {'retinex':9s} {seconds / views:6.2f} s/view  LMSE R {entry['retinex']['lmse_reflectance']:.4f} "
          f"S {entry['retinex']['lmse_shading']:.4f}", flush=True)
    return entry


def loglog_slope(x: list[float], y: list[float]) -> float:
    """Least-squares slope of ``log y`` against ``log x``."""
    return float(np.polyfit(np.log(x), np.log(y), 1)[0])


def bench_scaling(folder: Path, *, views: int = 4, views_scale: float = 0.5) -> dict:
    """Seconds per view of the default preset against pixels per view and against the number of views.

    The pixel sweep decomposes the first ``views`` views at working scales 0.25, 0.5, 0.75 and 1;
    the view sweep decomposes the first 2, 4, 8, ... views at working scale ``views_scale`` (the
    work per view is the same at every count, so the scale only shortens the run).
    """
    from mvintrinsic.resolution import downscale_scene

    scene = load_scene(folder)
    out: dict = {"pixels": [], "views": [], "pixel_sweep_views": min(views, len(scene.views)),
                 "view_sweep_scale": views_scale}
    first = dataclasses.replace(scene, views=scene.views[:views])
    for scale in (0.25, 0.5, 0.75, 1.0):
        small = downscale_scene(first, scale) if scale != 1.0 else first
        start = time.perf_counter()
        decompose(small)
        seconds = (time.perf_counter() - start) / len(small.views)
        h, w = small.views[0].shape
        out["pixels"].append({"scale": scale, "pixels_per_view": h * w, "seconds_per_view": seconds})
        print(f"{folder.name} scale {scale}: {w}x{h} {seconds:.2f} s/view", flush=True)
    n = len(scene.views)
    small = downscale_scene(scene, views_scale)
    for count in sorted({k for k in (2, 4, 8, 16, n) if k <= n}):
        subset = dataclasses.replace(small, views=small.views[:count])
        start = time.perf_counter()
        decompose(subset)
        seconds = time.perf_counter() - start
        out["views"].append({"views": count, "seconds": seconds, "seconds_per_view": seconds / count})
        print(f"{folder.name} {count} views at scale {views_scale}: {seconds:.1f} s", flush=True)
    out["slope_seconds_per_view_vs_pixels"] = loglog_slope([p["pixels_per_view"] for p in out["pixels"]],
                                                           [p["seconds_per_view"] for p in out["pixels"]])
    out["slope_seconds_vs_views"] = loglog_slope([p["views"] for p in out["views"]], [p["seconds"] for p in out["views"]])
    print(f"log-log slopes: seconds per view against pixels {out['slope_seconds_per_view_vs_pixels']:.2f}, "
          f"seconds against views {out['slope_seconds_vs_views']:.2f}", flush=True)
    return out


def bench_end_to_end(folder: Path, preset: str, work: Path) -> dict:
    """Wall seconds and peak memory of ``mvintrinsic decompose SCENE OUT --preset P`` in a fresh process.

    Loading, the decomposition and writing the result folder are all counted; the peak is the
    child's maximum resident set (``getrusage(RUSAGE_CHILDREN).ru_maxrss``, the figure
    ``/usr/bin/time -v`` reports).
    """
    import resource
    import subprocess

    cmd = [sys.executable, "-m", "mvintrinsic", "decompose", str(folder), str(work / "result"), "--preset", preset]
    start = time.perf_counter()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - start
    peak_gb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 2**20  # kB on Linux
    import json

    views = len(json.loads((work / "result" / "lighting.json").read_text())["views"])  # the decomposed views
    row = {"preset": preset, "views": views, "wall_s": wall, "peak_rss_gb": peak_gb,
           "command": f"mvintrinsic decompose {folder.name} OUT --preset {preset}"}
    print(f"{folder.name}: mvintrinsic decompose --preset {preset}, {views} views: {wall:.1f} s end to end, "
          f"peak {peak_gb:.2f} GB", flush=True)
    return row


def pareto_front(points: list[tuple[float, float]]) -> list[int]:
    """Indices of the points no other point beats on both coordinates (both smaller is better)."""
    front = []
    for i, (x, y) in enumerate(points):
        if not any((a <= x and b <= y) and (a < x or b < y) for j, (a, b) in enumerate(points) if j != i):
            front.append(i)
    return front


def save_figure(report: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    scenes = report["scenes"]
    presets = [p for p in PRESETS if all(p in s["presets"] for s in scenes.values())]
    metrics = [("lmse_reflectance", "reflectance LMSE", False), ("ber", "shadow BER", False),
               ("relit_psnr", "relit PSNR (dB)", True)]
    metrics = [m for m in metrics if all(s["presets"][p].get(m[0]) is not None for s in scenes.values() for p in presets)]
    fig, axes = plt.subplots(1, len(metrics) + 1, figsize=(4.2 * (len(metrics) + 1), 3.8))
    seconds = [np.mean([s["presets"][p]["seconds_per_view"] for s in scenes.values()]) for p in presets]
    for ax, (key, label, higher) in zip(axes, metrics, strict=False):
        values = [np.mean([s["presets"][p][key] for s in scenes.values()]) for p in presets]
        front = pareto_front([(t, -v if higher else v) for t, v in zip(seconds, values, strict=True)])
        for i, p in enumerate(presets):
            ax.scatter(seconds[i], values[i], s=60, marker="o" if i in front else "x", color=f"C{i}", label=p)
            ax.annotate(p, (seconds[i], values[i]), textcoords="offset points", xytext=(5, 4), fontsize=8)
        order = sorted(front, key=lambda i: seconds[i])
        ax.plot([seconds[i] for i in order], [values[i] for i in order], "k--", lw=0.8, label="Pareto front")
        if key in ("lmse_reflectance",):
            rx = np.mean([s["retinex"]["seconds_per_view"] for s in scenes.values()])
            ry = np.mean([s["retinex"][key] for s in scenes.values()])
            ax.scatter(rx, ry, marker="s", color="grey", label="colour Retinex")
        ax.set_xscale("log")
        ax.xaxis.set_major_locator(matplotlib.ticker.FixedLocator([0.2, 0.5, 1, 2, 5, 10, 20, 50]))
        ax.xaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%g"))
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.set_xlabel("seconds per view")
        ax.set_ylabel(label + " (mean over scenes)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    ax = axes[-1]
    bottom = np.zeros(len(presets))
    for k, stage in enumerate(STAGES):
        heights = np.array([np.mean([s["presets"][p]["stages"].get(stage, 0.0) for s in scenes.values()])
                            for p in presets])
        if heights.any():
            ax.bar(presets, heights, bottom=bottom, label=stage, color=plt.cm.tab20(k))
            bottom += heights
    ax.set_ylabel("seconds per view, by stage")
    ax.legend(fontsize=6, ncol=2)
    size = next(iter(scenes.values()))["size"]
    fig.suptitle(f"mvintrinsic presets, {len(scenes)} scenes at {size}, {report['cores']} cores")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path("data"), help="folder of the rendered scenes")
    parser.add_argument("--scene", action="append", default=[], help="DATA/NAME or 'demo' (repeatable)")
    parser.add_argument("--preset", action="append", choices=PRESETS, default=None, help="default: all")
    parser.add_argument("--smoke", action="store_true", help="'fast' and 'balanced' on the demo")
    parser.add_argument("--scaling", action="store_true", help="cost against pixels and views (first scene)")
    parser.add_argument("--end-to-end", choices=PRESETS, default=None,
                        help="wall time and peak memory of the CLI with this preset (first scene)")
    parser.add_argument("--views", type=int, default=None, help="only the first N views of each scene")
    parser.add_argument("--out", type=Path, default=None, help="JSON report")
    parser.add_argument("--figure", type=Path, default=None, help="PNG chart")
    parser.add_argument("--plot-only", type=Path, default=None, help="draw --figure from this JSON report and exit")
    args = parser.parse_args(argv)
    require_matplotlib(parser, args, "figure", "plot_only")
    if args.plot_only:
        import json

        save_figure(json.loads(args.plot_only.read_text()), args.figure or args.plot_only.with_suffix(".png"))
        return 0
    from mvintrinsic.cli import demo_scene_path

    names = ["demo"] if args.smoke else args.scene
    if not names:
        parser.error("give --scene or --smoke")
    presets = ["fast", "balanced"] if args.smoke else (args.preset or list(PRESETS))
    report = {"benchmark": "pareto" if not args.scaling else "scaling", "version": mvintrinsic.__version__,
              "cores": os.cpu_count(), "python": platform.python_version(), "scenes": {}}
    folders = {}
    for name in names:
        folder = demo_scene_path() if name == "demo" else args.data / name
        if not (folder / "scene.json").is_file():
            parser.error(f"--scene {name}: no scene.json in {folder}")
        folders[name] = folder
    if args.end_to_end:
        report["benchmark"] = "end_to_end"
        name = names[0]
        with tempfile.TemporaryDirectory() as tmp:
            report["scenes"][name] = bench_end_to_end(folders[name], args.end_to_end, Path(tmp))
    elif args.scaling:
        name = names[0]
        report["scenes"][name] = bench_scaling(folders[name])
    else:
        for name, folder in folders.items():
            with tempfile.TemporaryDirectory() as tmp:
                report["scenes"][name] = bench_scene(folder, presets, Path(tmp), max_views=args.views)
    if args.out:
        write_json(args.out, report)
        print(f"wrote {args.out}")
    if args.figure and not (args.scaling or args.end_to_end):
        save_figure(report, args.figure)
        print(f"wrote {args.figure}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
