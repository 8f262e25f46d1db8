"""Run the colour Retinex baseline (Grosse et al. 2009) on every view of a scene and write a result folder.

::

    python benchmarks/baselines/run_retinex.py SCENE OUT [--views V ...] [--max-size N]
                                               [--gray-threshold T] [--color-threshold T] [--overwrite]

Each view is decomposed on its own (:func:`retinex.color_retinex` on the view's valid pixels) and
the result is written with ``mvintrinsic.io.save_decomposition``, so that
``benchmarks/evaluate.py SCENE OUT`` scores it like any mvintrinsic result.

Mapping onto mvintrinsic's layers (``mvintrinsic.results.IntrinsicLayers``): Retinex estimates one
grey shading and no sun / sky split, so

* ``reflectance`` = the Retinex reflectance, ``indirect_shading`` = the Retinex (grey) shading, so
  that ``layers.shading`` (``v S_sun + S_sky + S_ind``) is the Retinex shading;
* ``sun_shading`` and ``sky_shading`` are zero, ``visibility`` is zero and every ``shadow_labels``
  pixel is 128 ("undecided": Retinex makes no shadow decision, so BER is not scored);
* pixels outside a view's valid mask hold 0 in every layer;
* the lighting has the scene's sun direction and up vector (inputs, not estimates) and a zero
  sun radiance.

Run with the package importable (installed, or ``PYTHONPATH`` pointing at the checkout). Errors in
the input are reported on one line, with exit status 2.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from retinex import DEFAULT_COLOR_THRESHOLD, DEFAULT_FLOOR, DEFAULT_GRAY_THRESHOLD, color_retinex

from mvintrinsic.io import ResultFolderError, SceneError, load_scene, save_decomposition
from mvintrinsic.results import SHADOW_LABELS, Decomposition, IntrinsicLayers, Lighting
from mvintrinsic.scene import Scene


def retinex_decomposition(
    scene: Scene,
    *,
    gray_threshold: float = DEFAULT_GRAY_THRESHOLD,
    color_threshold: float = DEFAULT_COLOR_THRESHOLD,
    floor: float = DEFAULT_FLOOR,
    max_size: int | None = None,
    verbose: bool = False,
) -> Decomposition:
    """Colour Retinex on every view of ``scene``, as a :class:`~mvintrinsic.results.Decomposition`.

    Parameters
    ----------
    scene : mvintrinsic.Scene
        Loaded scene; each view is decomposed over its valid mask.
    gray_threshold, color_threshold, floor : float, optional
        Passed to :func:`retinex.color_retinex`.
    max_size : int, optional
        Only recorded in the config (the scene is already loaded at its size).
    verbose : bool, optional
        Print the seconds spent on each view.

    Returns
    -------
    Decomposition
        Layers as described in the module docstring; ``timings["retinex"]`` is the total wall-clock
        time of the per-view decompositions.
    """
    layers = {}
    total = 0.0
    for view in scene.views:
        start = time.perf_counter()
        reflectance, shading = color_retinex(
            view.image, mask=view.mask, gray_threshold=gray_threshold, color_threshold=color_threshold, floor=floor
        )
        seconds = time.perf_counter() - start
        total += seconds
        if verbose:
            h, w = view.image.shape[:2]
            print(f"{view.stem}: {w}x{h}, {seconds:.3f} s")
        zeros3 = np.zeros_like(shading)
        h, w = shading.shape[:2]
        layers[view.stem] = IntrinsicLayers(
            view.stem,
            reflectance=reflectance,
            sun_shading=zeros3,
            sky_shading=zeros3,
            indirect_shading=shading,
            visibility=np.zeros((h, w), np.float32),
            shadow_labels=np.full((h, w), SHADOW_LABELS["undecided"], np.uint8),
        )
    lighting = Lighting(sun=scene.sun, sun_radiance=np.zeros(3), up=scene.up)
    config = {
        "method": "color_retinex (Grosse et al. 2009), benchmarks/baselines/retinex.py",
        "gray_threshold": float(gray_threshold),
        "color_threshold": float(color_threshold),
        "floor": float(floor),
        "max_size": max_size,
    }
    return Decomposition(layers=layers, lighting=lighting, timings={"retinex": total}, config=config)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("scene", type=Path, help="scene folder")
    parser.add_argument("out", type=Path, help="result folder to write (not inside the scene)")
    parser.add_argument("--views", nargs="+", metavar="STEM", help="decompose only these views")
    parser.add_argument("--max-size", type=int, metavar="N", help="downscale images to a longer side of N pixels")
    parser.add_argument(
        "--gray-threshold", type=float, default=DEFAULT_GRAY_THRESHOLD,
        help=f"grey log-gradient threshold (default {DEFAULT_GRAY_THRESHOLD:.4g})",
    )
    parser.add_argument(
        "--color-threshold", type=float, default=DEFAULT_COLOR_THRESHOLD,
        help=f"log-chromaticity gradient threshold (default {DEFAULT_COLOR_THRESHOLD:.4g})",
    )
    parser.add_argument(
        "--floor", type=float, default=DEFAULT_FLOOR,
        help=f"log floor, fraction of the 99th-percentile grey value (default {DEFAULT_FLOOR:g})",
    )
    parser.add_argument("--overwrite", action="store_true", help="allow writing into a non-empty foreign folder")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        scene = load_scene(args.scene, max_size=args.max_size, views=args.views)
        result = retinex_decomposition(
            scene,
            gray_threshold=args.gray_threshold,
            color_threshold=args.color_threshold,
            floor=args.floor,
            max_size=args.max_size,
            verbose=True,
        )
        folder = save_decomposition(result, args.out, scene=scene, overwrite=args.overwrite)
    except (SceneError, ResultFolderError, ValueError) as exc:
        print(f"run_retinex: error: {exc}", file=sys.stderr)
        return 2
    n = len(result.layers)
    print(f"{n} views, {result.timings['retinex']:.3f} s ({result.timings['retinex'] / n:.3f} s per view)")
    print(f"result written to {folder}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
