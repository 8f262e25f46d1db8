"""Over-segmentation (paper Sec. 6.1): seconds per view, segment counts and ground-truth purity.

    python benchmarks/bench_segmentation.py [--scene ../data/courtyard_1000] [--views N] [--no-sweep]
                                            [--out benchmarks/results/segmentation.json]

For both methods of :func:`mvintrinsic.segmentation.segment` (the paper's mean shift and SLIC), on
every view of the scene (1000x750 for ``courtyard_1000``):

* seconds per view (wall clock, one run, after a warm-up on a small image);
* the number of segments, the smallest segment, the segments whose pixels are mostly not sky and
  their mean area (the paper reports "around 6000 clusters for an image of size 1000x700");
* when the scene has ``gt/``: ``visibility_error``, the fraction of non-sky pixels whose true sun
  visibility disagrees with the majority of their segment (the error of the best possible
  cluster-level shadow labelling: the graph cut of Sec. 6.1 cannot do better), and
  ``reflectance_deviation``, the mean over non-sky pixels of ``|R - mean_segment(R)|_1 / |mean|_1``
  (how far the segments are from uniform reflectance; texture inside a material counts too).

The first view is also cut to 1000x700 (rows 25-724, a crop) and resized to 1000x700 (area
averaging) to compare with the paper's count. Unless ``--no-sweep``, the mean shift is repeated on
the crop for several colour bandwidths, and SLIC for several compactness values, to document the
choice of defaults (``mvintrinsic/segmentation.py``).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import time
from pathlib import Path

import cv2
import numpy as np

import mvintrinsic
from mvintrinsic.io import load_scene, read_image, write_json
from mvintrinsic.segmentation import SEGMENTATION_METHODS, Segmentation, SegmentationConfig, segment

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_SCENE = ROOT.parent / "data" / "courtyard_1000"
BANDWIDTHS = (1.0, 2.0, 3.0, 4.0, 6.0, 8.0)
COMPACTNESS = (3.0, 10.0, 30.0)
CROP_ROWS = (25, 725)


def ground_truth(folder: Path, stem: str) -> dict | None:
    """True sun visibility, reflectance and sky mask of a view, or None without ``gt/``."""
    gt = folder / "gt"
    paths = {"visibility": gt / "sun_visibility" / f"{stem}.png", "reflectance": gt / "reflectance" / f"{stem}.exr",
             "sky": gt / "sky_mask" / f"{stem}.png"}
    if not all(p.is_file() for p in paths.values()):
        return None
    return {
        "visibility": read_image(paths["visibility"])[0][..., 0] > 0.5,
        "reflectance": read_image(paths["reflectance"])[0].astype(np.float64),
        "sky": read_image(paths["sky"])[0][..., 0] > 0.5,
    }


def scores(seg: Segmentation, truth: dict | None) -> dict:
    """Counts, and the purity of the segments against the ground truth."""
    out = {"n_segments": seg.n_segments, "smallest": int(seg.sizes.min()) if seg.n_segments else 0,
           "median_area": float(np.median(seg.sizes)) if seg.n_segments else 0.0}
    if truth is None:
        return out
    sky = truth["sky"]
    keep = seg.valid & ~sky
    labels = seg.labels[keep]
    total = np.bincount(labels, minlength=seg.n_segments)
    lit = np.bincount(labels, truth["visibility"][keep], minlength=seg.n_segments)
    minority = np.minimum(lit, total - lit)
    mean = seg.means(truth["reflectance"], where=~sky)
    reflectance = truth["reflectance"][keep]
    deviation = np.abs(reflectance - mean[labels]).sum(axis=1) / np.maximum(mean[labels].sum(axis=1), 1e-6)
    ground = total * 2 > seg.sizes  # segments mostly made of non-sky pixels
    out.update({
        "segments_non_sky": int(ground.sum()),
        "mean_area_non_sky": float(keep.sum() / max(int(ground.sum()), 1)),
        "visibility_error": float(minority.sum() / max(int(keep.sum()), 1)),
        "reflectance_deviation": float(deviation.mean()),
    })
    return out


def timed(image: np.ndarray, mask: np.ndarray | None, config: SegmentationConfig, truth: dict | None) -> dict:
    start = time.perf_counter()
    seg = segment(image, mask=mask, config=config)
    seconds = time.perf_counter() - start
    return {"seconds": seconds, **scores(seg, truth)}


def crop_truth(truth: dict | None, rows: tuple[int, int]) -> dict | None:
    return None if truth is None else {k: v[rows[0]:rows[1]] for k, v in truth.items()}


def resize_truth(truth: dict | None, size: tuple[int, int]) -> dict | None:
    if truth is None:
        return None
    out = {k: cv2.resize(v.astype(np.uint8), size, interpolation=cv2.INTER_NEAREST) > 0
           for k, v in truth.items() if v.ndim == 2}
    out["reflectance"] = cv2.resize(truth["reflectance"], size, interpolation=cv2.INTER_AREA)
    return out


def summary(rows: list[dict]) -> dict:
    keys = [k for k in rows[0] if isinstance(rows[0][k], (int, float))]
    counts = [r["n_segments"] for r in rows]
    return {k: float(np.mean([r[k] for r in rows])) for k in keys} | {
        "min_segments": int(min(counts)), "max_segments": int(max(counts)),
        "min_seconds": float(min(r["seconds"] for r in rows)), "max_seconds": float(max(r["seconds"] for r in rows))}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", type=Path, default=DEFAULT_SCENE, help="scene folder (default: %(default)s)")
    parser.add_argument("--views", type=int, default=None, help="only the first N views")
    parser.add_argument("--no-sweep", action="store_true", help="skip the bandwidth and compactness sweeps")
    parser.add_argument("--out", type=Path, default=None, help="write the results as JSON here")
    args = parser.parse_args(argv)

    scene = load_scene(args.scene)
    views = scene.views[: args.views] if args.views else scene.views
    configs = {m: SegmentationConfig(method=m) for m in SEGMENTATION_METHODS}
    # Warm-up: imports, OpenCV and skimage first-call costs stay out of the timings.
    for config in configs.values():
        segment(np.random.default_rng(0).uniform(size=(64, 64, 3)), config=config)

    report = {
        "scene": str(args.scene), "mvintrinsic": mvintrinsic.__version__, "python": platform.python_version(),
        "opencv": cv2.__version__, "cpus": os.cpu_count(), "load_average_at_start": list(os.getloadavg()),
        "command": "python benchmarks/bench_segmentation.py" + (" --no-sweep" if args.no_sweep else ""),
        "configs": {m: dataclasses.asdict(c) for m, c in configs.items()},
        "views": {}, "summary": {}, "1000x700": {}, "sweep": {},
    }
    truths = {v.stem: ground_truth(args.scene, v.stem) for v in views}
    for method, config in configs.items():
        rows = {}
        for view in views:
            rows[view.stem] = timed(view.image, view.mask, config, truths[view.stem])
        report["views"][method] = rows
        report["summary"][method] = summary(list(rows.values()))

    first = views[0]
    h, w = first.shape
    cut = first.image[CROP_ROWS[0]:CROP_ROWS[1]]
    cut_mask = first.mask[CROP_ROWS[0]:CROP_ROWS[1]]
    resized = cv2.resize(first.image, (1000, 700), interpolation=cv2.INTER_AREA)
    resized_mask = cv2.resize(first.mask.astype(np.uint8), (1000, 700), interpolation=cv2.INTER_NEAREST) > 0
    for method, config in configs.items():
        report["1000x700"][method] = {
            "crop": timed(cut, cut_mask, config, crop_truth(truths[first.stem], CROP_ROWS)),
            "resize": timed(resized, resized_mask, config, resize_truth(truths[first.stem], (1000, 700))),
        }

    if not args.no_sweep:
        truth = crop_truth(truths[first.stem], CROP_ROWS)
        report["sweep"]["mean_shift_color_bandwidth"] = {
            str(b): timed(cut, cut_mask, SegmentationConfig(color_bandwidth=b), truth) for b in BANDWIDTHS}
        report["sweep"]["slic_compactness"] = {
            str(c): timed(cut, cut_mask, SegmentationConfig(method="slic", slic_compactness=c), truth)
            for c in COMPACTNESS}

    print(f"{len(views)} views of {w}x{h} from {args.scene} ({os.cpu_count()} cpus, "
          f"load {report['load_average_at_start'][0]:.2f})")
    header = f"{'':28s}{'seconds':>9s}{'segments':>10s}{'non-sky':>9s}{'area':>7s}{'vis.err':>9s}{'refl.dev':>9s}"
    print(header)

    def line(name: str, row: dict) -> None:
        print(f"{name:28s}{row['seconds']:9.2f}{row['n_segments']:10.0f}{row.get('segments_non_sky', np.nan):9.0f}"
              f"{row.get('mean_area_non_sky', np.nan):7.0f}{row.get('visibility_error', np.nan):9.4f}"
              f"{row.get('reflectance_deviation', np.nan):9.4f}")

    for method in configs:
        for stem, row in report["views"][method].items():
            line(f"{method} {stem}", row)
        line(f"{method} mean per view", report["summary"][method])
        for kind, row in report["1000x700"][method].items():
            line(f"{method} 1000x700 {kind}", row)
    for name, rows in report["sweep"].items():
        for value, row in rows.items():
            line(f"{name} {value}", row)
    if args.out:
        write_json(args.out, report)
        print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
