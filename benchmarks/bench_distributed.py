"""Wall time of ``decompose`` and of relighting, serial against a dask.distributed cluster (issue 17 item 6).

    python benchmarks/bench_distributed.py --scene DIR [--views N] [--repeats 3] [--workers 2] [--threads 1]
                                           [--suns 5] [--out benchmarks/results/distributed.json]
    python benchmarks/bench_distributed.py --upsample DIR --size 1000x750 [...]
    python benchmarks/bench_distributed.py --smoke

``--upsample DIR --size WxH`` times a scratch scene: DIR's views resampled in memory to WxH
(bilinear images, nearest masks, ``Camera.scaled``): only for timing, its layers mean nothing.

Every sample runs in a fresh process (importing a copy of the package taken at the start, so that
edits to the tree during a long run do not mix code versions), so that its peak RSS is that mode's
driver memory:
``serial`` decomposes in it; ``cluster`` starts a ``LocalCluster(n_workers, threads_per_worker,
processes=True)`` in it and decomposes with ``client=``. Both first warm up on two demo views
(imports, numba's cached kernels; the cluster's workers too), which is not timed. The samples
alternate between the modes (A/B in one run, so that the machine's background load is shared), the
mode that goes first alternating too. Reported: the median wall seconds of ``decompose`` per mode
and every sample, the stage seconds of each sample, the driver's peak RSS and each worker's RSS
before and peak after, whether the layers are identical across all samples (SHA-1 of every layer
array), and, in the cluster samples (``--suns``), the seconds per new sun of ``Relighter.render``
here and on the cluster (interleaved, same process) and the relighter's build seconds.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import os
import platform
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
RESULT_PREFIX = "RESULT "


def _mib(kib: float) -> float:
    return round(kib / 1024.0, 1)


def upsampled(scene, width: int, height: int):
    """``scene`` with every view resampled to ``width x height`` (a scratch scene for timing only)."""
    import cv2

    from mvintrinsic import Scene, View

    views = []
    for view in scene.views:
        clean = np.where(view.mask[..., None], view.image, 0.0).astype(np.float32)
        image = cv2.resize(clean, (width, height), interpolation=cv2.INTER_LINEAR)
        mask = cv2.resize(view.mask.astype(np.uint8), (width, height), interpolation=cv2.INTER_NEAREST).astype(bool)
        views.append(View(view.stem, image, view.camera.scaled(width, height), mask))
    return Scene(views, scene.proxy, scene.sun, scene.up)


def load(args):
    from mvintrinsic import Scene, load_scene
    from mvintrinsic.cli import demo_scene_path

    folder = demo_scene_path() if args.smoke else Path(args.scene or args.upsample)
    scene = load_scene(folder, max_size=None)
    if args.upsample:
        scene = upsampled(scene, *args.size)
    if args.views:
        scene = Scene(scene.views[:args.views], scene.proxy, scene.sun, scene.up)
    return scene, folder


def layers_digest(result) -> str:
    digest = hashlib.sha1()
    for stem in sorted(result.layers):
        layers = result.layers[stem]
        for field in dataclasses.fields(layers):
            value = getattr(layers, field.name)
            if isinstance(value, np.ndarray):
                digest.update(f"{stem}.{field.name}{value.dtype}{value.shape}".encode())
                digest.update(np.ascontiguousarray(value).tobytes())
    digest.update(np.asarray(result.lighting.sun_radiance).tobytes())
    return digest.hexdigest()


def _worker_memory():
    """Run on each worker: (RSS now, peak RSS) in KiB."""
    import psutil

    return psutil.Process().memory_info().rss / 1024.0, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss


def warm_up(client) -> float:
    """Decompose two demo views with few rays (imports, numba caches; the workers too). Seconds."""
    from mvintrinsic import Config, Scene, decompose, load_scene
    from mvintrinsic.cli import demo_scene_path
    from mvintrinsic.env_shading import Step1Config

    demo = load_scene(demo_scene_path())
    start = time.perf_counter()
    decompose(Scene(demo.views[:2], demo.proxy, demo.sun, demo.up), config=Config(step1=Step1Config(n_rays=8)),
              client=client)
    return time.perf_counter() - start


def relight_ab(result, scene, client, suns: int) -> dict:
    """Seconds per new sun of ``Relighter.render`` here and on the cluster, interleaved; identical images?"""
    from mvintrinsic.relight import Relighter
    from mvintrinsic.sun_position import azimuth_elevation

    start = time.perf_counter()
    here = Relighter(result, scene)
    build_here = time.perf_counter() - start
    start = time.perf_counter()
    there = Relighter(result, scene, client=client)
    build_there = time.perf_counter() - start
    azimuth, elevation = azimuth_elevation(result.lighting.sun.direction, up=scene.up)
    seconds = {"serial": [], "cluster": []}
    identical = True
    for k, offset in enumerate(np.linspace(-30.0, 30.0, suns)):
        sun = (float(azimuth + offset), float(elevation))
        images = {}
        for mode in (("serial", "cluster") if k % 2 == 0 else ("cluster", "serial")):
            relighter = here if mode == "serial" else there
            start = time.perf_counter()
            images[mode] = relighter.render(sun)
            seconds[mode].append(time.perf_counter() - start)
        identical &= all(np.array_equal(images["serial"][s], images["cluster"][s]) for s in images["serial"])
    return {"build_seconds": {"serial": build_here, "cluster": build_there},
            "cluster_build_parts": dict(there.timings),
            "render_seconds": seconds,
            "render_median": {m: statistics.median(v) for m, v in seconds.items()},
            "identical": bool(identical)}


def child(args) -> dict:
    """One sample in this process: ``args.child`` is "serial" or "cluster"."""
    from mvintrinsic import decompose

    scene, _ = load(args)
    out = {"mode": args.child}
    client = cluster = None
    try:
        if args.child == "cluster":
            from distributed import Client, LocalCluster

            start = time.perf_counter()
            cluster = LocalCluster(n_workers=args.workers, threads_per_worker=args.threads, processes=True,
                                   dashboard_address=None)
            client = Client(cluster, set_as_default=False)
            out["cluster_start_seconds"] = time.perf_counter() - start
        out["warm_up_seconds"] = warm_up(client)
        if client is not None:
            out["worker_rss_before_mib"] = {w: _mib(m[0]) for w, m in client.run(_worker_memory).items()}
        start = time.perf_counter()
        result = decompose(scene, client=client)
        out["seconds"] = time.perf_counter() - start
        out["timings"] = {k: round(v, 3) for k, v in result.timings.items()}
        out["digest"] = layers_digest(result)
        out["driver_peak_rss_mib"] = _mib(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)
        if client is not None:
            out["worker_peak_rss_mib"] = {w: _mib(m[1]) for w, m in client.run(_worker_memory).items()}
            if args.suns:
                out["relight"] = relight_ab(result, scene, client, args.suns)
    finally:
        if client is not None:
            client.close()
        if cluster is not None:
            cluster.close()
    return out


def run_sample(mode: str, argv: list[str], snapshot: Path | None) -> dict:
    cmd = [sys.executable, str(Path(__file__).resolve()), *argv, "--child", mode]
    env = dict(os.environ)
    if snapshot is not None:  # the child and its cluster's workers import the snapshot
        env["PYTHONPATH"] = os.pathsep.join([str(snapshot), *filter(None, [env.get("PYTHONPATH")])])
    run = subprocess.run(cmd, capture_output=True, text=True, env=env)
    lines = [line for line in run.stdout.splitlines() if line.startswith(RESULT_PREFIX)]
    if run.returncode != 0 or not lines:
        raise RuntimeError(f"{mode} sample failed ({run.returncode}):\n{run.stderr[-4000:]}")
    return json.loads(lines[-1][len(RESULT_PREFIX):])


def _parse_size(text: str) -> tuple[int, int]:
    """``--size WxH`` as ``(W, H)`` pixels, each at least 2 (an argparse ``type``: a bad value is a usage error)."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be WxH, got {text!r}") from None
    if min(w, h) < 2:
        raise argparse.ArgumentTypeError(f"must be WxH with W and H at least 2, got {text!r}")
    return w, h


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default=None, help="scene folder to time")
    parser.add_argument("--upsample", default=None, help="scene folder whose views are resampled to --size")
    parser.add_argument("--size", type=_parse_size, default=(1000, 750), help="WxH for --upsample (default 1000x750)")
    parser.add_argument("--views", type=int, default=None, help="first N views only")
    parser.add_argument("--repeats", type=int, default=3, help="samples per mode (default 3)")
    parser.add_argument("--workers", type=int, default=2, help="LocalCluster workers (default 2)")
    parser.add_argument("--threads", type=int, default=1, help="threads per worker (default 1)")
    parser.add_argument("--suns", type=int, default=5, help="new suns rendered per cluster sample (0: none)")
    parser.add_argument("--smoke", action="store_true", help="the demo, one sample per mode, two suns (< 2 min)")
    parser.add_argument("--out", type=Path, default=None,
                        help="JSON report (default benchmarks/results/distributed.json; none with --smoke)")
    parser.add_argument("--no-snapshot", action="store_true",
                        help="run the tree's package as it is (default: a copy taken at the start)")
    parser.add_argument("--child", choices=("serial", "cluster"), default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.smoke:
        args.repeats, args.suns = 1, min(args.suns, 2)
    elif bool(args.scene) == bool(args.upsample):
        parser.error("give one of --scene, --upsample or --smoke")
    if args.child:
        print(RESULT_PREFIX + json.dumps(child(args)), flush=True)
        return 0

    import mvintrinsic

    forwarded = ["--suns", str(args.suns), "--workers", str(args.workers), "--threads", str(args.threads)]
    if args.smoke:
        forwarded.append("--smoke")
    else:
        forwarded += ["--scene", args.scene] if args.scene else ["--upsample", args.upsample,
                                                                  "--size", "x".join(map(str, args.size))]
    if args.views:
        forwarded += ["--views", str(args.views)]
    scene, folder = load(args)
    samples = []
    with tempfile.TemporaryDirectory() as tmp:
        snapshot = None
        if not args.no_snapshot:  # one version of the code for every sample, whatever is edited meanwhile
            snapshot = Path(tmp)
            shutil.copytree(Path(mvintrinsic.__file__).parent, snapshot / "mvintrinsic",
                            ignore=shutil.ignore_patterns("__pycache__"))
        for k in range(args.repeats):
            for mode in (("serial", "cluster") if k % 2 == 0 else ("cluster", "serial")):
                sample = run_sample(mode, forwarded, snapshot)
                print(f"{mode:8s} {sample['seconds']:8.1f} s  driver peak {sample['driver_peak_rss_mib']:.0f} MiB"
                      + (f"  workers peak {sorted(sample['worker_peak_rss_mib'].values())} MiB"
                         if mode == "cluster" else ""), flush=True)
                samples.append(sample)
    by_mode = {m: [s for s in samples if s["mode"] == m] for m in ("serial", "cluster")}
    medians = {m: statistics.median(s["seconds"] for s in v) for m, v in by_mode.items()}
    h, w = scene.views[0].shape
    report = {
        "benchmark": "distributed", "version": mvintrinsic.__version__, "cores": os.cpu_count(),
        "python": platform.python_version(), "load_average_at_start": list(os.getloadavg()),
        "scene": {"folder": str(folder), "upsampled_to": None if not args.upsample else f"{w}x{h}",
                  "views": len(scene.views), "size": f"{w}x{h}"},
        "cluster": {"n_workers": args.workers, "threads_per_worker": args.threads, "processes": True},
        "command": " ".join([Path(sys.executable).name, "benchmarks/bench_distributed.py", *(argv or sys.argv[1:])]),
        "decompose_seconds_median": medians,
        "speedup": medians["serial"] / medians["cluster"],
        "identical_layers": len({s["digest"] for s in samples}) == 1,
        "code": "snapshot of the package at the start" if not args.no_snapshot else "the tree as it was at each sample",
        "samples": samples,
    }
    relit = [s["relight"] for s in by_mode["cluster"] if "relight" in s]
    if relit:
        report["relight_render_seconds_median"] = {
            m: statistics.median(x for r in relit for x in r["render_seconds"][m]) for m in ("serial", "cluster")}
        report["relight_identical"] = all(r["identical"] for r in relit)
    print(f"decompose median: serial {medians['serial']:.1f} s, cluster {medians['cluster']:.1f} s "
          f"(x{report['speedup']:.2f}); identical layers: {report['identical_layers']}")
    if relit:
        rm = report["relight_render_seconds_median"]
        print(f"relight render per sun: serial {rm['serial']:.3f} s, cluster {rm['cluster']:.3f} s; "
              f"identical: {report['relight_identical']}")
    out = args.out if args.out is not None else (None if args.smoke else HERE / "results" / "distributed.json")
    if out is not None:
        from mvintrinsic.io import write_json

        write_json(out, report)
        print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
