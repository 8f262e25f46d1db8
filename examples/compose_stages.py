"""Compose the decomposition by hand: run Step 1, look at it, swap in your own shadow labels, go on.

    python examples/compose_stages.py [SCENE] [--view STEM] [--out compose]

SCENE is any scene folder (``docs/formats.md``); the embedded demo by default. Every call below is
an exported name of ``mvintrinsic`` (``README.md``, "Use from Python"), the same stages
:func:`mvintrinsic.decompose` chains:

1. Step 1 (paper Sec. 4): sky and indirect shading and the proxy's sun visibility per proxy vertex,
   carried to the pixels;
2. Step 2 (Sec. 5): ``L_sun`` from light/shadow pairs;
3. Step 3 (Sec. 6): shadow labels and matting; here one view's labels are replaced by your own
   (this script uses the proxy's shadow, thresholded, as a stand-in for, e.g., a hand-painted mask)
   and its layers rebuilt from them;
4. Step 4 (Sec. 7): one reflectance per surface point across the views;
5. relighting (Sec. 8): the sun moved by +20 degrees of azimuth, the cast shadows with it.

It prints what each stage found and writes the chosen view's reflectance, shading and relit image
as PNG (sRGB, each scaled to its own 99th percentile) into ``--out``.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import mvintrinsic as mvi
from mvintrinsic.files import write_image
from mvintrinsic.sun_position import azimuth_elevation


def to_png(image: np.ndarray) -> np.ndarray:
    """Linear RGB to an sRGB-encodable [0, 1] image scaled to its own 99th percentile."""
    finite = np.nan_to_num(np.asarray(image, dtype=np.float64))
    top = max(float(np.percentile(finite, 99)), 1e-9)
    return np.clip(finite / top, 0.0, 1.0)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene", type=Path, nargs="?", default=None, help="scene folder (default: the demo)")
    parser.add_argument("--view", default=None, help="view whose labels are replaced (default: the first)")
    parser.add_argument("--out", type=Path, default=Path("compose"), help="output folder for the PNGs")
    args = parser.parse_args(argv)

    scene = mvi.load_scene(args.scene or mvi.demo_scene_path())
    view = scene.views[0] if args.view is None else next(v for v in scene.views if v.stem == args.view)
    tracer = mvi.Tracer(scene.proxy)

    s1 = mvi.step1(scene, tracer=tracer)
    quantities = mvi.carry_to_pixels(scene, s1, tracer)
    own = quantities[view.stem]
    print(f"Step 1: sky model {s1.sky_model.model!r}, {len(s1.normals)} proxy vertices; view {view.stem}: "
          f"{own.valid.mean():.0%} of the pixels on the proxy, {(own.visibility[own.valid] < 0.5).mean():.0%} "
          "of them in the proxy's shadow")

    calibration = mvi.calibrate(scene, quantities)
    sun_radiance = calibration.sun_radiance
    print(f"Step 2: L_sun = {np.round(sun_radiance, 3).tolist()} from {sum(len(p.estimates) for p in calibration.pairs)} "
          "light/shadow pairs")

    step3, _ = mvi.step3(scene, quantities, sun_radiance)
    layers = {stem: v.layers for stem, v in step3.items()}
    labels = np.where(own.visibility < 0.5, 0, 255).astype(np.uint8)  # your labels: 0 shadow, 255 lit, 128 unknown
    before = (layers[view.stem].shadow_labels == 0).mean()
    layers[view.stem] = mvi.label_layers(view, own, labels, sun_radiance)
    print(f"Step 3: view {view.stem}'s labels replaced ({before:.0%} -> {(labels == 0).mean():.0%} shadow)")

    step4 = mvi.step4(scene, quantities, layers)
    layers = step4.layers
    print(f"Step 4: the reflectance of every surface point fused across the {len(scene.views)} views "
          f"({step4.timings.get('total', sum(step4.timings.values())):.1f} s)")

    result = mvi.Decomposition(layers=layers, lighting=mvi.Lighting(sun=scene.sun, sun_radiance=sun_radiance,
                                                                   up=scene.up))
    azimuth, elevation = azimuth_elevation(scene.sun.direction, up=scene.up)
    relit = mvi.Relighter(result, scene).render((azimuth + 20.0, elevation))
    print(f"Relit: the sun from azimuth {azimuth:.1f} to {azimuth + 20.0:.1f} degrees at elevation {elevation:.1f}")

    args.out.mkdir(parents=True, exist_ok=True)
    chosen = layers[view.stem]
    for name, image in (("reflectance", chosen.reflectance), ("shading", chosen.shading), ("relit", relit[view.stem])):
        write_image(args.out / f"{view.stem}_{name}.png", to_png(image), dtype="uint8")
    print(f"wrote {args.out}/{view.stem}_{{reflectance,shading,relit}}.png")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
