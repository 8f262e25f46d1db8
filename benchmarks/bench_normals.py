"""The receivers' normals against the exact mesh's: smoothed (Step 1) and snapped to the proxy's planes.

    python benchmarks/bench_normals.py [--smoke] [--data DIR --scene NAME ...]
                                       [--out benchmarks/results/normals.json]

Every shading term reads the receiver's normal (Eq. 3's ``S_sun``, Step 2's cosines, the relit
cosine of Sec. 8), and Step 1 and the relighter take the proxy's vertex normals smoothed over
``Step1Config.normal_smoothing`` (0.4 m) and, by default, snapped to the proxy's dominant planes
(``Step1Config.planes``, :mod:`mvintrinsic.planes`). For each scene and view this benchmark casts
every pixel's centre ray at the proxy and at the exact mesh (``gt/mesh.ply``) and compares, over
the pixels the proxy *explains* (both rays hit, depths within :data:`DEPTH_TOLERANCE` relative),
the angle between the proxy's interpolated normal (:func:`mvintrinsic.relight.receiver_normals`)
and the mesh's geometric normal (turned to face the camera, as the proxy's are):

* ``raw``: the proxy's own vertex normals;
* ``smoothed``: smoothed by 0.4 m (``planes=None``, the paper's reading of Step 1 plus the smoothing);
* ``planes``: smoothed and snapped (:class:`~mvintrinsic.planes.PlaneConfig`, the default).

Reported per scene (pooled over its views): the median angle (degrees), the share above 10
degrees, the mean absolute error of ``max(0, n . d)`` at the capture sun (the cosine every
``S_sun`` carries), the share of pixels explained, the planes found and the seconds the
snapping took. ``--smoke`` runs the embedded demo only (seconds).

Scenes: the embedded demo by default, or ``DIR/NAME`` per ``--scene`` (any scene folder with
``gt/mesh.ply``; the scenes of ``bench_shadows.py``'s docstring).
"""

from __future__ import annotations

import argparse
import os
import platform
import time
from pathlib import Path

import numpy as np

import mvintrinsic
from mvintrinsic.cli import demo_scene_path
from mvintrinsic.io import load_scene, read_proxy, write_json
from mvintrinsic.planes import PlaneConfig, detect_planes, planar_normals
from mvintrinsic.raytrace import Tracer, smooth_normals
from mvintrinsic.shadow_caster import _cast_pixels, _pixel_normals

ROOT = Path(__file__).resolve().parents[1]
#: A pixel is explained when its proxy depth is within this share of the exact mesh's.
DEPTH_TOLERANCE = 0.05
#: Step 1's and the relighter's smoothing (metres).
SMOOTHING = 0.4


def _angles(estimate: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Degrees between unit normals (N, 3)."""
    return np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", estimate, truth), -1.0, 1.0)))


def normals_scene(folder: Path) -> dict:
    """The normal errors of one scene (module docstring).

    The vertex normals of each variant are computed once per scene, and each view's pixel rays are cast once
    per mesh; the pixel normals are interpolated as :func:`mvintrinsic.relight.receiver_normals` does
    (the same helpers), so the figures are those of the relighter's receivers.
    """
    scene = load_scene(folder)
    mesh_tracer = Tracer(read_proxy(folder / "gt" / "mesh.ply"))
    tracer = Tracer(scene.proxy)
    start = time.perf_counter()
    smoothed = smooth_normals(scene.proxy, SMOOTHING)
    seconds_smoothing = time.perf_counter() - start
    start = time.perf_counter()
    config = PlaneConfig()
    planes = detect_planes(scene.proxy.vertices, smoothed, config=config)
    snapped = planar_normals(scene.proxy.vertices, smoothed, planes, config=config)[0]
    seconds_planes = time.perf_counter() - start
    # raw: normal_smoothing 0; smoothed: Step 1's smoothing (planes=None); planes: smoothed and snapped (default).
    variants = {"raw": scene.proxy.normals, "smoothed": smoothed, "planes": snapped}
    pooled: dict[str, list] = {name: [] for name in variants}
    cosines: dict[str, list] = {name: [] for name in variants}
    explained_share = []
    sun = scene.sun.direction
    for view in scene.views:
        camera = view.camera
        hits, depth, hit = _cast_pixels(camera, tracer)
        mesh_hits, true_depth, true_hit = _cast_pixels(camera, mesh_tracer, name="gt/mesh.ply")
        truth = mesh_hits.normals.reshape(*view.shape, 3).astype(np.float64)
        rays = camera.pixel_rays().reshape(*view.shape, 3)
        truth = np.where((np.einsum("hwc,hwc->hw", truth, rays) > 0)[..., None], -truth, truth)  # toward the camera
        explained = hit & true_hit & (np.abs(depth - true_depth) <= DEPTH_TOLERANCE * true_depth)
        explained_share.append(float(explained.mean()))
        true_cos = np.maximum(0.0, truth[explained] @ sun)
        for name, at_vertices in variants.items():
            normals = _pixel_normals(tracer, hits, view.shape, at_vertices)[explained]
            pooled[name].append(_angles(normals, truth[explained]))
            cosines[name].append(np.abs(np.maximum(0.0, normals @ sun) - true_cos))
    out: dict = {"views": len(scene.views), "size": f"{scene.views[0].shape[1]}x{scene.views[0].shape[0]}",
                 "explained_share": float(np.mean(explained_share)), "planes_found": len(planes),
                 "seconds": {"smoothing": seconds_smoothing, "detect_planes": seconds_planes}}
    for name in variants:
        angles, cos_error = np.concatenate(pooled[name]), np.concatenate(cosines[name])
        out[name] = {"median_deg": float(np.median(angles)), "p90_deg": float(np.percentile(angles, 90)),
                     "share_above_10_deg": float((angles > 10.0).mean()),
                     "cosine_mean_abs_error": float(cos_error.mean())}
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--smoke", action="store_true", help="the embedded demo only (the default)")
    parser.add_argument("--data", type=Path, default=ROOT.parent / "data", help="folder of the rendered scenes")
    parser.add_argument("--scene", action="append", default=None, help="score DATA/NAME (repeatable)")
    parser.add_argument("--out", type=Path, default=None, help="JSON report")
    args = parser.parse_args(argv)
    if args.smoke or not args.scene:
        folders = {"demo": demo_scene_path()}
    else:
        folders = {name: args.data / name for name in args.scene}
        missing = [str(f) for f in folders.values() if not (f / "gt" / "mesh.ply").is_file()]
        if missing:
            raise SystemExit(f"--scene: no gt/mesh.ply in {', '.join(missing)}")
    report = {"benchmark": "normals", "version": mvintrinsic.__version__, "cores": os.cpu_count(),
              "python": platform.python_version(), "depth_tolerance": DEPTH_TOLERANCE, "smoothing_m": SMOOTHING,
              "scenes": {}}
    for name, folder in folders.items():
        report["scenes"][name] = entry = normals_scene(folder)
        print(f"{name}: explained {entry['explained_share']:.2f}, {entry['planes_found']} planes; " + "; ".join(
            f"{v} median {entry[v]['median_deg']:.1f} deg, >10 deg {entry[v]['share_above_10_deg']:.2f}, "
            f"|cos err| {entry[v]['cosine_mean_abs_error']:.3f}" for v in ("raw", "smoothed", "planes")), flush=True)
    if args.out:
        write_json(args.out, report)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
