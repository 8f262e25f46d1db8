"""Imitations of real captures against their clean scenes: issue 18's "real capture data" measures.

    python benchmarks/bench_capture.py [--data DIR] --scene NAME [--scene NAME ...]
                                       [--out benchmarks/results/real_capture.json]
    python benchmarks/bench_capture.py --smoke

For each scene (``DIR/NAME`` rendered by ``mvintrinsic synth``, ``demo`` the embedded demo), an
imitation of a real capture is made with :func:`mvintrinsic.synth.capture.imitate_capture` (per-view
exposure up to +-1 stop and white balance up to +-15% per channel, 8-bit sRGB JPEG at quality 85,
one view stored in portrait with EXIF orientation 6, the proxy's ground removed and a false roof
cap added; seed 0). Then, each with the default configuration:

* ``clean``: the scene as rendered (linear EXR, MVS-like proxy with its ground);
* ``capture``: the imitation (per-view gains estimated and compensated, horizon from ``up``);
* ``capture_no_gains``: the imitation with ``Config(exposure=ExposureConfig(method="none"))``,
  the paper's single exposure, to show what the compensation buys.

Per run: reflectance and shading LMSE, shadow BER, reconstruction PSNR
(:func:`mvintrinsic.evaluation.evaluate`), ``L_sun`` over the truth per channel, the horizon
evidence, the estimated gains against the applied ones (both normalised to a geometric mean of 1:
max and mean of ``|estimated / applied - 1|``; for ``capture_no_gains`` the gains are 1, so the
figure is how far the photos are from one exposure), and seconds. ``--smoke`` runs the demo only (CI).

``--ablation`` adds the imitation's changes one at a time, each with the default configuration:
``jpeg`` (8-bit sRGB JPEG only: no gains, no portrait view, ground kept, no cap), ``jpeg_no_ground``
(and the ground removed), ``jpeg_no_ground_cap`` (and the false cap); ``capture`` adds the gains
and the portrait view on top.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import mvintrinsic
from mvintrinsic import Config, decompose
from mvintrinsic.evaluation import evaluate, read_ground_truth_lighting
from mvintrinsic.exposure import ExposureConfig
from mvintrinsic.io import load_scene, save_decomposition, write_json
from mvintrinsic.synth.capture import imitate_capture

ROOT = Path(__file__).resolve().parents[2]


def run(folder: Path, work: Path, config: Config) -> dict:
    """Decompose ``folder`` with ``config`` and score it against its ground truth."""
    start = time.perf_counter()
    scene = load_scene(folder)
    result = decompose(scene, config=config)
    seconds = time.perf_counter() - start
    out = work / "result"
    save_decomposition(result, out, scene=scene, overwrite=True)
    mean = evaluate(folder, out)["mean"]
    truth = np.asarray(read_ground_truth_lighting(folder).sun_radiance, dtype=np.float64)
    entry = {key: mean[key] for key in ("lmse_reflectance", "lmse_shading", "ber", "reconstruction_psnr")}
    entry.update(lsun_ratio=(np.asarray(result.lighting.sun_radiance) / truth).tolist(),
                 horizon_evidence=result.lighting.horizon_evidence, seconds=seconds,
                 seconds_per_view=seconds / len(scene.views))
    gains = result.lighting.exposure
    if gains is not None:
        entry["exposure"] = {"applied": gains.applied, "reason": gains.reason}
        capture = folder / "gt" / "capture.json"
        if capture.is_file():
            applied = json.loads(capture.read_text())["gains"]
            truth_gains = np.array([applied[s] for s in gains.stems])
            error = np.abs(gains.estimated / truth_gains - 1.0)
            entry["exposure"].update(max_gain_error=float(error.max()), mean_gain_error=float(error.mean()),
                                     estimated=gains.estimated.tolist(), truth=truth_gains.tolist())
    return entry


#: the imitation's changes added one at a time (--ablation): imitate_capture arguments
ABLATION = {
    "jpeg": {"exposure_stops": 0.0, "white_balance": 0.0, "portrait_view": None, "ground_band": None,
             "false_cap": False},
    "jpeg_no_ground": {"exposure_stops": 0.0, "white_balance": 0.0, "portrait_view": None, "false_cap": False},
    "jpeg_no_ground_cap": {"exposure_stops": 0.0, "white_balance": 0.0, "portrait_view": None},
}


def bench_scene(folder: Path, work: Path, *, ablation: bool = False) -> dict:
    capture = work / f"{folder.name}_capture"
    record = imitate_capture(folder, capture, seed=0, overwrite=True)
    scene = load_scene(folder)
    out = {"views": len(scene.views), "size": "x".join(map(str, scene.views[0].shape[::-1])),
           "imitation": {k: record[k] for k in ("global_scale", "jpeg_quality", "portrait_view", "proxy")}}
    runs = {"clean": (folder, Config())}
    if ablation:
        for name, kwargs in ABLATION.items():
            imitate_capture(folder, work / name, seed=0, overwrite=True, **kwargs)
            runs[name] = (work / name, Config())
    runs.update(capture=(capture, Config()), capture_no_gains=(capture, Config(exposure=ExposureConfig(method="none"))))
    for name, (source, config) in runs.items():
        entry = run(source, work, config)
        out[name] = entry
        gains = entry.get("exposure", {})
        print(f"{folder.name:14s} {name:17s} LMSE R {entry['lmse_reflectance']:.4f} S {entry['lmse_shading']:.4f} "
              f"BER {entry['ber']:.3f}  L_sun/true {np.round(entry['lsun_ratio'], 3)}  "
              f"horizon {entry['horizon_evidence']}  gains {gains.get('applied')} "
              f"max err {gains.get('max_gain_error', float('nan')):.4f}  {entry['seconds']:.0f} s", flush=True)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=ROOT / "data", help="folder of the rendered scenes")
    parser.add_argument("--scene", action="append", default=[], help="DATA/NAME or 'demo' (repeatable)")
    parser.add_argument("--smoke", action="store_true", help="the demo only")
    parser.add_argument("--ablation", action="store_true", help="add the imitation's changes one at a time")
    parser.add_argument("--out", type=Path, default=None, help="JSON report")
    args = parser.parse_args(argv)
    from mvintrinsic.cli import demo_scene_path

    names = ["demo"] if args.smoke else args.scene
    if not names:
        parser.error("give --scene or --smoke")
    report = {"benchmark": "real_capture", "version": mvintrinsic.__version__, "cores": os.cpu_count(),
              "python": platform.python_version(), "scenes": {}}
    for name in names:
        folder = demo_scene_path() if name == "demo" else args.data / name
        if not (folder / "scene.json").is_file():
            parser.error(f"--scene {name}: no scene.json in {folder}")
        with tempfile.TemporaryDirectory() as tmp:
            report["scenes"][name] = bench_scene(folder, Path(tmp), ablation=args.ablation)
    if args.out:
        write_json(args.out, report)
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
