"""Seconds per render of the synthetic-scene generator, and the quality of its MVS-like proxy.

    python benchmarks/bench_render.py [--size 480x360] [--spp 128] [--views 2] [--quick]
                                      [--out benchmarks/results/render.json]

Renders each recipe with ``mvintrinsic.synth.synthesize`` (no relit renders) into a temporary
folder and records the mean seconds per pass (path-traced image + albedo AOV, direct sun), the
total time and the proxy statistics from ``gt/scene_info.json``. ``--quick`` is a CI smoke mode
(64x48, 4 spp, one view).
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
from pathlib import Path

import mvintrinsic
from mvintrinsic.io import write_json
from mvintrinsic.synth.dataset import SynthConfig, synthesize
from mvintrinsic.synth.recipes import RECIPES
from mvintrinsic.synth.render import RenderConfig


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="480x360")
    parser.add_argument("--spp", type=int, default=128)
    parser.add_argument("--views", type=int, default=2)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args()
    width, height = (int(v) for v in args.size.split("x"))
    spp, views = args.spp, args.views
    if args.quick:
        width, height, spp, views = 64, 48, 4, 1
    report = {"benchmark": "render", "version": mvintrinsic.__version__, "cores": os.cpu_count(),
              "python": platform.python_version(), "width": width, "height": height, "spp": spp, "recipes": {}}
    for recipe in sorted(RECIPES):
        config = SynthConfig(n_views=views, width=width, height=height, relit=(), render=RenderConfig(spp=spp))
        with tempfile.TemporaryDirectory() as tmp:
            info = synthesize(recipe, Path(tmp) / "scene", config=config, progress=False)
        report["recipes"][recipe] = {
            "seconds_per_render": info["seconds_per_render"],
            "seconds_total": info["seconds_total"],
            "proxy": info["proxy"],
            "sun_azimuth_deg": info["sun_azimuth_deg"],
            "sun_elevation_deg": info["sun_elevation_deg"],
        }
        per = info["seconds_per_render"]
        print(f"{recipe:10s} {width}x{height} {spp} spp: image {per['image']:.1f} s, sun {per['sun_direct']:.1f} s "
              f"per render; proxy {info['proxy']['within_10cm']:.1%} within 10 cm, "
              f"foliage retention {info['proxy']['foliage_retention']:.1%}")
    if args.out is not None:
        write_json(args.out, report)
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
