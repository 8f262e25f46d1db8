"""Peak memory (and seconds) of ``load_scene`` + ``decompose`` on 12 MP photos, per ``max_size``.

    python benchmarks/bench_memory.py [--scene ../data/street_s0] [--size 4000x3000] [--views 2]
                                      [--format jpg|exr] [--max-size 2048 full ...]
                                      [--timeout 1800] [--rss-limit 16]
                                      [--out benchmarks/results/memory_12mp.json]
    python benchmarks/bench_memory.py --smoke

The scene: the first ``--views`` views of a rendered scene (default ``../data/street_s0``,
480x360 EXR), each upsampled to ``--size`` (default 4000x3000, 12 MP; ``cv2.resize``, bilinear)
with its COLMAP camera scaled to match (:meth:`mvintrinsic.camera.Camera.scaled`), written into a
temporary scene folder with the source's ``proxy.ply`` and ``scene.json``. Images are written as
8-bit sRGB JPEG (quality 95; the real-capture case) or, with ``--format exr``, as linear half EXR.
Two views by default: one 12 MP view plus the partner the multi-view stages need.

For each ``--max-size`` (a longer side in pixels, or ``full``) a fresh Python process runs
``mvintrinsic.io.load_scene(folder, max_size=M)`` then ``mvintrinsic.pipeline.decompose(scene)``
(default ``Config``), so each peak is clean. Measured per run:

* ``peak_rss_gb``: the process's peak resident set (VmHWM), the figure the 4 GB budget is about;
  ``baseline_rss_gb``: its resident set after the imports, before loading;
* per stage (``load``, ``tracer``, ``step1``, ``pixels``, ``sun_pairs``, ``shadow_labels``,
  ``segmentation``, ``shadow_mrf``, ``matting``, ``step4``; ``other`` is the time between them):
  the peak resident set inside the stage, the resident set on entry, seconds and calls. The stages
  are timed by wrapping the functions ``decompose`` calls through ``mvintrinsic.pipeline``'s
  namespace (in the child process only), and the peak is exact: the kernel's high-water mark is
  reset at each stage boundary (``/proc/self/clear_refs``, Linux >= 4.0; where that is refused a
  thread samples VmRSS every 50 ms instead);
* ``wall_s``, ``load_s``, ``decompose_s`` and ``decompose``'s own ``timings`` (seconds per stage,
  summed over the views);
* ``status``: ``ok``, ``timeout`` (over ``--timeout`` seconds), ``rss_limit`` (over ``--rss-limit``
  GB, or the machine's available memory under 1 GB: the child is killed before the OOM killer picks
  a victim), or ``error``. A killed run keeps its peak so far (the parent samples the child's
  VmRSS / VmHWM every 50 ms, the child reports each finished stage) and the stage it was in.

``--smoke`` (CI, under a minute): 320x240 views, ``max_size`` 160 and full, no JSON unless
``--out`` is given. Without ``--smoke`` the report goes to ``benchmarks/results/memory_12mp.json``
unless ``--out`` says otherwise. Caveat: upsampled renders are smoother than real photos; the
resident set of the per-pixel stages scales with the pixel count, not the content, but the
segmentation's cluster count does depend on it.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
DEFAULT_SCENE = ROOT / "data" / "street_s0"
DEFAULT_OUT = Path(__file__).resolve().parent / "results" / "memory_12mp.json"
BUDGET_GB = 4.0
GB = 1024**3
# Functions decompose calls through mvintrinsic.pipeline's namespace, and the stage each one is.
STAGES = (("Tracer", "tracer"), ("step1", "step1"), ("carry_to_pixels", "pixels"), ("calibrate", "sun_pairs"),
          ("label_shadows_multiview", "shadow_labels"), ("segment", "segmentation"), ("label_shadows", "shadow_mrf"),
          ("intrinsic_layers", "matting"), ("step4", "step4"))


# ---------------------------------------------------------------------------------------------
# /proc readings
# ---------------------------------------------------------------------------------------------
def _status(pid: int | str = "self") -> dict[str, int]:
    """VmRSS and VmHWM of a process in bytes ({} once it is gone)."""
    out = {}
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith(("VmRSS:", "VmHWM:")):
                    key, value = line.split(":", 1)
                    out[key] = int(value.split()[0]) * 1024
    except OSError:
        pass
    return out


def _available() -> int | None:
    """The machine's MemAvailable in bytes."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


def _reset_hwm() -> bool:
    """Reset this process's VmHWM to its current VmRSS; False where the kernel refuses."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


# ---------------------------------------------------------------------------------------------
# the child: one load + decompose, measured per stage
# ---------------------------------------------------------------------------------------------
class _Meter:
    """Peak resident set per stage. Exact through VmHWM resets, else sampled every 50 ms."""

    def __init__(self, progress: Path) -> None:
        self.progress = progress
        self.stages: dict[str, dict] = {}
        self.current: str | None = None
        self.info: dict = {}
        self.peak = _status().get("VmHWM", 0)  # the imports' peak, before the first reset
        self.exact = _reset_hwm()
        self._sampled = 0
        if not self.exact:
            threading.Thread(target=self._sample, daemon=True).start()
        self._open("other")

    def _sample(self) -> None:
        while True:
            self._sampled = max(self._sampled, _status().get("VmRSS", 0))
            time.sleep(0.05)

    def _window_peak(self) -> int:
        """Peak since the last boundary, and start a new window."""
        now = _status()
        if self.exact:
            peak = now.get("VmHWM", 0)
            _reset_hwm()
        else:
            peak = max(self._sampled, now.get("VmRSS", 0))
            self._sampled = 0
        self.peak = max(self.peak, peak)
        return peak

    def _open(self, name: str) -> None:
        self.current, self._start, self._entered_at = name, time.perf_counter(), time.time()
        entry = self.stages.setdefault(name, {"peak_rss": 0, "rss_on_entry": None, "seconds": 0.0, "calls": 0})
        rss = _status().get("VmRSS", 0)
        entry["rss_on_entry"] = rss if entry["rss_on_entry"] is None else max(entry["rss_on_entry"], rss)

    def _close(self) -> None:
        entry = self.stages[self.current]
        entry["peak_rss"] = max(entry["peak_rss"], self._window_peak())
        entry["seconds"] += time.perf_counter() - self._start
        entry["calls"] += 1

    def enter(self, name: str) -> None:
        self._close()
        self._open(name)
        self.dump()

    def leave(self) -> None:
        self._close()
        self._open("other")
        self.dump()

    def finish(self) -> None:
        self._close()
        self.current = None

    def report(self) -> dict:
        return {**self.info, "exact": self.exact, "peak_rss": self.peak, "current": self.current,
                "entered_at": self._entered_at, "stages": self.stages}

    def dump(self) -> None:
        tmp = self.progress.with_suffix(".tmp")
        tmp.write_text(json.dumps(self.report()))
        os.replace(tmp, self.progress)


def _instrument(meter: _Meter) -> None:
    """Wrap the stage functions in mvintrinsic.pipeline's namespace (this process only)."""
    import functools

    import mvintrinsic.pipeline as pipeline

    depth = [0]

    def wrap(function, stage):
        @functools.wraps(function)
        def wrapped(*args, **kwargs):
            depth[0] += 1
            if depth[0] == 1:
                meter.enter(stage)
            try:
                return function(*args, **kwargs)
            finally:
                if depth[0] == 1:
                    meter.leave()
                depth[0] -= 1
        return wrapped

    for attr, stage in STAGES:
        setattr(pipeline, attr, wrap(getattr(pipeline, attr), stage))


def child(folder: Path, max_size: int | None, out: Path) -> int:
    """Run in the fresh process: load, decompose, write the measurements to ``out``."""
    import numpy as np  # noqa: F401  (the imports belong to the baseline, not to a stage)

    import mvintrinsic.pipeline as pipeline
    from mvintrinsic.io import load_scene

    baseline = _status().get("VmRSS", 0)
    meter = _Meter(out.with_suffix(".progress.json"))
    _instrument(meter)
    start = time.perf_counter()
    meter.enter("load")
    scene = load_scene(folder, max_size=max_size)
    shape = scene.views[0].shape
    meter.info.update(baseline_rss=baseline, loaded_size=f"{shape[1]}x{shape[0]}", views=len(scene.views))
    meter.leave()
    load_s = time.perf_counter() - start
    result = pipeline.decompose(scene)
    wall = time.perf_counter() - start
    meter.finish()
    report = meter.report()
    report.update(status="ok", wall_s=wall, load_s=load_s, decompose_s=wall - load_s, timings=dict(result.timings))
    out.write_text(json.dumps(report))
    return 0


# ---------------------------------------------------------------------------------------------
# the parent: build the scene, one watched child per max_size
# ---------------------------------------------------------------------------------------------
def _srgb_encode(linear):
    import numpy as np

    x = np.clip(linear, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def build_scene(source: Path, dest: Path, width: int, height: int, views: int, fmt: str) -> dict:
    """Upsample the first ``views`` views of ``source`` into the scene folder ``dest``."""
    import shutil

    import cv2
    import numpy as np

    from mvintrinsic.io import read_colmap, read_image, write_colmap_text, write_image

    cameras = read_colmap(source / "sparse")
    names = sorted(cameras)[:views]
    (dest / "images").mkdir(parents=True)
    shutil.copy(source / "proxy.ply", dest / "proxy.ply")
    shutil.copy(source / "scene.json", dest / "scene.json")
    scaled, saturated = {}, 0
    for name in names:
        image, _ = read_image(source / "images" / name)
        big = cv2.resize(image, (width, height), interpolation=cv2.INTER_LINEAR)
        stem = Path(name).with_suffix("").as_posix()
        if fmt == "jpg":
            saturated += int((big >= 1.0).any(axis=2).sum())
            codes = np.round(_srgb_encode(big) * 255).astype(np.uint8)
            file = f"{stem}.jpg"
            if not cv2.imwrite(str(dest / "images" / file), codes[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 95]):
                raise OSError(f"cannot write {dest / 'images' / file}")
        else:
            file = f"{stem}.exr"
            write_image(dest / "images" / file, big, dtype="half")
        scaled[file] = cameras[name].scaled(width, height)
    write_colmap_text(dest / "sparse", scaled)
    return {"views": names, "saturated_pixels": saturated,
            "image_bytes": sum(p.stat().st_size for p in (dest / "images").iterdir())}


def _read_json(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def run_one(folder: Path, max_size: int | None, timeout: float, rss_limit: float, work: Path) -> dict:
    """One load + decompose in a watched child process."""
    tag = "full" if max_size is None else str(max_size)
    out = work / f"run_{tag}.json"
    progress = out.with_suffix(".progress.json")
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", str(folder),
           "--child-max-size", tag, "--child-out", str(out)]
    stderr_path = work / f"run_{tag}.stderr"
    start = time.perf_counter()
    with open(stderr_path, "w") as stderr:
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=stderr)
    samples: list[tuple[float, int]] = []  # (time.time(), VmRSS or VmHWM) of the child
    status, rusage_kb, code = None, 0, None
    while True:
        pid, wait_status, usage = os.wait4(proc.pid, os.WNOHANG)
        if pid:
            code = os.waitstatus_to_exitcode(wait_status)
            rusage_kb = usage.ru_maxrss
            proc.returncode = code  # reaped here: keep Popen from waiting again
            break
        now = _status(proc.pid)
        samples.append((time.time(), max(now.get("VmRSS", 0), now.get("VmHWM", 0))))
        available = _available()
        if time.perf_counter() - start > timeout:
            status = "timeout"
        elif now.get("VmRSS", 0) > rss_limit * GB or (available is not None and available < GB):
            status = "rss_limit"
        if status is not None:
            os.kill(proc.pid, signal.SIGKILL)
            _, wait_status, usage = os.wait4(proc.pid, 0)
            code, rusage_kb = os.waitstatus_to_exitcode(wait_status), usage.ru_maxrss
            proc.returncode = code
            break
        time.sleep(0.05)
    wall = time.perf_counter() - start
    sampled = max((rss for _, rss in samples), default=0)
    report = _read_json(out) if status is None and code == 0 else None
    if report is None:
        report = _read_json(progress) or {"stages": {}, "peak_rss": 0, "current": None}
        report["status"] = status or "error"
        report["wall_s"] = wall
        if status is None:
            report["error"] = stderr_path.read_text()[-2000:]
        stage = report["stages"].get(report.get("current"))
        if stage is not None:  # the stage the child died in: its peak as the parent saw it
            since = report.get("entered_at", 0.0)
            stage["peak_rss"] = max(stage["peak_rss"], max((r for t, r in samples if t >= since), default=0))
            stage["seconds"] += time.time() - since
            stage["killed"] = True
    report["max_size"] = max_size
    report["exit_code"] = code
    report["process_wall_s"] = wall
    report["parent_sampled_peak_rss"] = sampled
    # VmHWM resets (clear_refs) also reset what ru_maxrss reports, so it is the last window's peak only.
    report["ru_maxrss"] = rusage_kb * 1024
    report["peak_rss"] = max(report.get("peak_rss", 0), sampled)
    return report


def _gb(value: float | None) -> float | None:
    return None if value is None else round(value / GB, 3)


def _tidy(report: dict) -> dict:
    """Bytes to GB (three decimals), seconds to three decimals."""
    out = dict(report)
    out.pop("entered_at", None)
    for key in ("peak_rss", "baseline_rss", "parent_sampled_peak_rss", "ru_maxrss"):
        if key in out:
            out[key + "_gb"] = _gb(out.pop(key))
    out["stages"] = {name: {"peak_rss_gb": _gb(s["peak_rss"]), "rss_on_entry_gb": _gb(s["rss_on_entry"]),
                            "seconds": round(s["seconds"], 3), "calls": s["calls"],
                            **({"killed": True} if s.get("killed") else {})}
                     for name, s in report.get("stages", {}).items()}
    if out["stages"]:
        out["dominant_stage"] = max(out["stages"], key=lambda n: out["stages"][n]["peak_rss_gb"] or 0)
    if "timings" in out:
        out["timings"] = {k: round(v, 3) for k, v in out["timings"].items()}
    out["within_budget"] = out["status"] == "ok" and out["peak_rss_gb"] <= BUDGET_GB
    return out


def _print_tables(runs: list[dict]) -> None:
    print(f"\n{'max_size':>8s} {'loaded':>10s} {'status':>9s} {'peak GB':>8s} {'load GB':>8s} {'base GB':>8s} "
          f"{'wall s':>8s} {'load s':>7s}  dominant")
    for r in runs:
        load = r["stages"].get("load", {}).get("peak_rss_gb")
        print(f"{r['max_size'] or 'full':>8} {r.get('loaded_size', '?'):>10s} {r['status']:>9s} "
              f"{r['peak_rss_gb']:8.2f} {load if load is not None else float('nan'):8.2f} "
              f"{r.get('baseline_rss_gb') or float('nan'):8.2f} {r['wall_s']:8.1f} {r.get('load_s', float('nan')):7.1f}"
              f"  {r.get('dominant_stage', '?')}" + (f" (killed in {r.get('current')})" if r["status"] != "ok" else ""))
    names = []
    for r in runs:
        names += [n for n in r["stages"] if n not in names]
    print("\nper stage: peak RSS GB / seconds (calls)")
    print(f"{'stage':>14s} " + " ".join(f"{str(r['max_size'] or 'full'):>21s}" for r in runs))
    for name in names:
        cells = []
        for r in runs:
            s = r["stages"].get(name)
            cells.append(f"{'-':>21s}" if s is None else
                         f"{s['peak_rss_gb']:6.2f} / {s['seconds']:7.1f} ({s['calls']})".rjust(21))
        print(f"{name:>14s} " + " ".join(cells))


def _max_size(value: str) -> int | None:
    if value.lower() in ("full", "none"):
        return None
    size = int(value)
    if size < 1:
        raise argparse.ArgumentTypeError("max size must be positive or 'full'")
    return size


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", type=Path, default=DEFAULT_SCENE, help="rendered scene folder to upsample")
    parser.add_argument("--size", default="4000x3000", help="WIDTHxHEIGHT of each built view")
    parser.add_argument("--views", type=int, default=2, help="views kept (the first ones by name)")
    parser.add_argument("--format", choices=("jpg", "exr"), default="jpg", help="8-bit sRGB JPEG or linear half EXR")
    parser.add_argument("--max-size", type=_max_size, nargs="+", default=None,
                        help="load_scene max_size values, 'full' for none (default: 2048 full)")
    parser.add_argument("--timeout", type=float, default=1800.0, help="seconds before a run is killed")
    parser.add_argument("--rss-limit", type=float, default=16.0, help="GB of resident set before a run is killed")
    parser.add_argument("--smoke", action="store_true", help="CI: 320x240 views, max_size 160 and full")
    parser.add_argument("--out", type=Path, default=None,
                        help="JSON report (default benchmarks/results/memory_12mp.json; none with --smoke)")
    parser.add_argument("--child", type=Path, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--child-max-size", type=_max_size, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--child-out", type=Path, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child is not None:
        return child(args.child, args.child_max_size, args.child_out)

    import mvintrinsic

    width, height = (int(v) for v in args.size.lower().split("x"))
    sizes = args.max_size or [2048, None]
    out = args.out
    if args.smoke:
        width, height, sizes = 320, 240, args.max_size or [160, None]
    elif out is None:
        out = DEFAULT_OUT
    sizes = sorted(set(sizes), key=lambda s: float("inf") if s is None else s)
    if args.views < 2:
        parser.error("--views: the multi-view stages need at least 2 views")
    if not (args.scene / "scene.json").is_file():
        parser.error(f"--scene: no scene.json in {args.scene}")
    report = {"benchmark": "memory_12mp", "version": mvintrinsic.__version__, "cores": os.cpu_count(),
              "python": platform.python_version(), "machine_memory_gb": _gb(os.sysconf("SC_PAGE_SIZE")
                                                                            * os.sysconf("SC_PHYS_PAGES")),
              "source": str(args.scene), "size": f"{width}x{height}", "megapixels": width * height / 1e6,
              "format": args.format, "budget_gb": BUDGET_GB, "timeout_s": args.timeout, "rss_limit_gb": args.rss_limit,
              "config": "default Config()", "runs": []}
    with tempfile.TemporaryDirectory(prefix="bench_memory_") as tmp:
        folder = Path(tmp) / "scene"
        start = time.perf_counter()
        built = build_scene(args.scene, folder, width, height, args.views, args.format)
        report["scene"] = {**built, "build_s": round(time.perf_counter() - start, 1)}
        print(f"built {args.views} views of {width}x{height} ({width * height / 1e6:.1f} MP, {args.format}) from "
              f"{args.scene.name} in {report['scene']['build_s']} s", flush=True)
        for max_size in sizes:
            run = _tidy(run_one(folder, max_size, args.timeout, args.rss_limit, Path(tmp)))
            report["runs"].append(run)
            print(f"max_size {max_size or 'full'}: {run['status']}, peak {run['peak_rss_gb']:.2f} GB, "
                  f"{run['wall_s']:.1f} s", flush=True)
    _print_tables(report["runs"])
    if out is not None:
        from mvintrinsic.io import write_json

        write_json(out, report)
        print(f"wrote {out}")
    return 0 if all(r["status"] == "ok" for r in report["runs"]) or not args.smoke else 1


if __name__ == "__main__":
    sys.exit(main())
