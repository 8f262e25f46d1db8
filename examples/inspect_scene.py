"""Load a scene, cast every pixel ray of one view into the proxy, and show what the proxy covers.

    python examples/inspect_scene.py SCENE [--view STEM] [--out coverage.png]

Writes a figure with the image (tonemapped), the proxy depth along each pixel ray and the pixels
the proxy misses (sky, and geometry the reconstruction lost). Needs matplotlib
(``pip install -e ".[plot]"``).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import mvintrinsic as mvi
from mvintrinsic.raytrace import Tracer


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene", type=Path)
    parser.add_argument("--view", default=None, help="view stem (default: the first)")
    parser.add_argument("--out", type=Path, default=Path("coverage.png"))
    args = parser.parse_args()

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    scene = mvi.load_scene(args.scene)
    view = scene.view(args.view) if args.view else scene.views[0]
    camera = view.camera
    hits = Tracer(scene.proxy).intersect(camera.center, camera.pixel_rays())
    depth = np.where(hits.hit, hits.t, np.nan).reshape(camera.shape)

    image = view.image / max(np.percentile(view.image[view.mask], 99), 1e-6)
    srgb = np.where(image <= 0.0031308, 12.92 * image, 1.055 * np.clip(image, 0, None) ** (1 / 2.4) - 0.055)
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6), constrained_layout=True)
    axes[0].imshow(np.clip(srgb, 0, 1))
    axes[0].set_title(f"{view.stem} (tonemapped)")
    im = axes[1].imshow(depth, cmap="viridis")
    fig.colorbar(im, ax=axes[1], label="proxy depth along the ray (m)")
    axes[1].set_title("proxy hit distance")
    axes[2].imshow(~hits.hit.reshape(camera.shape), cmap="gray")
    axes[2].set_title(f"missed by the proxy: {1 - hits.hit.mean():.1%}")
    for ax in axes:
        ax.set_axis_off()
    fig.savefig(args.out, dpi=110)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
