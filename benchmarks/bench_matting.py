"""Matting (paper Sec. 6.2) before and after the direct solver: seconds per view, accuracy, first-use cost.

    python benchmarks/bench_matting.py [--smoke] [--out benchmarks/results/matting.json] [--repeats 3]
                                       [--scene NAME ...] [--large SCENE] [--large-views 3] [--no-before]
                                       [--memory WxH|none] [--solvers] [--large-only]

*Before* is ``mvintrinsic/matting.py`` as of commit ``7d03579`` (pymatting's closed-form Laplacian,
conjugate gradients preconditioned by pymatting's incomplete Cholesky factor, a numba kernel of
ours), read from git and loaded beside the current module; it needs git, ``pymatting`` and
``numba`` (``pip install pymatting numba``) and is left out without them (or with ``--no-before``).
*After* is the current module (``MattingConfig()``: the direct solver).

- Accuracy and seconds per view at the scenes' size: the demo and the 480x360 scenes of ``../data``
  that exist (courtyard_s1, street_s0, demo_480, street_s2, street_sky; ``--scene NAME`` picks
  others). Each scene is decomposed (default ``Config``, Steps 1-4) once with each matting and scored
  against its ground truth (``mvintrinsic.evaluation.evaluate``: reflectance and shading LMSE,
  shadow BER, means over the views). The matting inputs of every view are kept, and both mattings
  are timed on them, interleaved, ``--repeats`` times: the median per view, then the median over
  the views. The largest differences between the two mattings' layers are reported too.
- Seconds per view at 1000x750: ``--large SCENE`` (default ``../data/courtyard_1000`` when it
  exists), else the first ``--large-views`` views of the first 480x360 scene upsampled to 1000x750
  (bilinear images, scaled cameras) and decomposed to Step 3 for their matting inputs.
- First use: a fresh interpreter imports the matting and solves a 40x60 case. Before: with an empty
  ``NUMBA_CACHE_DIR`` (numba compiles pymatting's kernels and ours, as after ``pip install``), then
  again with that cache (loaded).
- Peak memory (``--memory WxH``, default 1400x1050, the default largest size of real photos): one
  matting of the first 1000x750 view's inputs upsampled to that size, in a fresh process each.
- ``--solvers``: the matte and propagation systems of the first 1000x750 view solved by others
  (SuperLU in its own orderings, conjugate gradients preconditioned by an incomplete LU or by
  pyamg's smoothed aggregation if installed, the former incomplete Cholesky): seconds and error.

``--smoke``: the demo only, after only, one repeat (under a minute). ``--large-only``: first use
and the 1000x750 part only. Run with the package
importable (installed, or ``PYTHONPATH`` pointing at the checkout). The machine's load average is
recorded: the timings are only comparable within one run.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import json
import os
import pickle
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import scipy

import mvintrinsic
import mvintrinsic.matting as after
import mvintrinsic.pipeline as pipeline
from mvintrinsic import Config, decompose
from mvintrinsic.cli import demo_scene_path
from mvintrinsic.evaluation import evaluate
from mvintrinsic.io import load_scene, save_decomposition, write_json
from mvintrinsic.scene import View

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "data"
#: The last commit of the former matting (pymatting's Laplacian and incomplete Cholesky, numba).
BEFORE_COMMIT = "7d03579"
SCENES_480 = ("courtyard_s1", "street_s0", "demo_480", "street_s2", "street_sky")
LARGE = (1000, 750)
SCORES = ("lmse_reflectance", "lmse_shading", "ber")

FIRST_USE = r"""
import json, sys, time
began = time.perf_counter()
import numpy as np
{load}
imported = time.perf_counter()
rng = np.random.default_rng(0)
image = rng.random((40, 60, 3))
labels = np.where(np.arange(60) < 30, 0, 255).astype(np.uint8)[None].repeat(40, 0)
known = np.zeros((40, 60), bool)
known[::5, ::5] = True
module.sun_visibility_matting(image, labels)
module.propagate(image, rng.random((40, 60, 7)), known)
done = time.perf_counter()
print(json.dumps({{"import_seconds": imported - began, "first_call_seconds": done - imported,
                  "total_seconds": done - began}}))
"""
MEMORY = r"""
import json, pickle, sys
import cv2, dataclasses, numpy as np
from mvintrinsic.scene import View
{load}
view, quantities, labels, radiance, clusters, config = pickle.load(open({inputs!r}, "rb"))
width, height = {size}

def resize(a, nearest):
    kind = np.asarray(a).dtype
    a = np.asarray(a, dtype=np.int32 if nearest else np.float32)
    out = cv2.resize(a, (width, height), interpolation=cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR)
    return out.astype(kind)

view = View(view.stem, resize(np.where(view.mask[..., None], view.image, 0.0), False),
            view.camera.scaled(width, height), resize(view.mask, True))
fields = {{}}
for field in dataclasses.fields(quantities):
    value = getattr(quantities, field.name)
    if isinstance(value, np.ndarray) and value.shape[:2] == labels.shape:
        fields[field.name] = resize(value, value.dtype == bool or not np.isfinite(value).all())
quantities = dataclasses.replace(quantities, **fields)
labels, clusters = resize(labels, True), resize(clusters, True)
if hasattr(module, "_block_substitution"):  # compile the former kernels first: their memory is not the matting's
    module.propagate(np.random.default_rng(0).random((8, 8, 3)), np.zeros((8, 8)), np.eye(8, dtype=bool))
    module._block_substitution()
config = module.MattingConfig(**{{k: v for k, v in dataclasses.asdict(config).items()
                                 if k in {{f.name for f in dataclasses.fields(module.MattingConfig)}}}})

def status(key):
    return next(int(line.split()[1]) for line in open("/proc/self/status") if line.startswith(key)) / 1024

open("/proc/self/clear_refs", "w").write("5")  # reset the peak resident set size
start = status("VmRSS:")
module.intrinsic_layers(view, quantities, labels, radiance, clusters=clusters, config=config)
print(json.dumps({{"rss_before_mb": start, "peak_rss_mb": status("VmHWM:"), "peak_increase_mb": status("VmHWM:") - start}}))
"""
LOAD_AFTER = "import mvintrinsic.matting as module"
LOAD_BEFORE = """import importlib.util
spec = importlib.util.spec_from_file_location("mvintrinsic._matting_before", {path!r})
module = importlib.util.module_from_spec(spec)
sys.modules[spec.name] = module
spec.loader.exec_module(module)"""


# --------------------------------------------------------------------------------------------
# The two mattings
# --------------------------------------------------------------------------------------------

def load_before(folder: Path):
    """The former matting module from git, or None (with the reason) when it cannot run here."""
    for needed in ("pymatting", "numba"):
        if importlib.util.find_spec(needed) is None:
            return None, f"{needed} is not installed"
    try:
        source = subprocess.run(["git", "show", f"{BEFORE_COMMIT}:mvintrinsic/matting.py"], cwd=REPO,
                                capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError) as error:
        return None, f"git show {BEFORE_COMMIT}: {error}"
    path = folder / "matting_before.py"
    path.write_text(source)
    spec = importlib.util.spec_from_file_location("mvintrinsic._matting_before", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module, str(path)


def before_config(module, config: after.MattingConfig):
    """The former module's MattingConfig with the same values (its fields are a subset of ours)."""
    names = {f.name for f in dataclasses.fields(module.MattingConfig)}
    return module.MattingConfig(**{k: v for k, v in dataclasses.asdict(config).items() if k in names})


class MattingHook:
    """Replaces the pipeline's matting during a decomposition: records inputs, runs a matting.

    ``pipeline.intrinsic_layers`` and, if the pipeline uses it, ``pipeline.intrinsic_layers_result``.
    """

    def __init__(self, module=None, *, skip: bool = False) -> None:
        self.module, self.skip, self.inputs = module, skip, {}

    def __call__(self, view, quantities, labels, sun_radiance, *, clusters=None, config=None):
        self.inputs[view.stem] = (view, quantities, labels, np.asarray(sun_radiance), clusters, config)
        if self.skip:  # inputs only: the layers straight from the labels
            return pipeline.label_layers(view, quantities, labels, sun_radiance)
        if self.module is None:
            return after.intrinsic_layers(view, quantities, labels, sun_radiance, clusters=clusters, config=config)
        return self.module.intrinsic_layers(view, quantities, labels, sun_radiance, clusters=clusters,
                                            config=before_config(self.module, config or after.MattingConfig()))

    def result(self, *args, **kwargs):
        return after.MattingResult(self(*args, **kwargs))

    def decompose(self, scene, config: Config):
        names = {"intrinsic_layers": self, "intrinsic_layers_result": self.result}
        originals = {name: getattr(pipeline, name) for name in names if hasattr(pipeline, name)}
        for name in originals:
            setattr(pipeline, name, names[name])
        try:
            result = decompose(scene, config=config)
        finally:
            for name, original in originals.items():
                setattr(pipeline, name, original)
        if not self.inputs and config.matting is not None and "matting" in result.timings:
            raise RuntimeError("the pipeline's matting went round the hook: update MattingHook")
        return result


# --------------------------------------------------------------------------------------------
# Measurements
# --------------------------------------------------------------------------------------------

def score(folder: Path, scene, result) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        save_decomposition(result, Path(tmp) / "result", scene=scene)
        scores = evaluate(folder, Path(tmp) / "result")
    return {"mean": {k: scores["mean"][k] for k in SCORES},
            "views": {stem: {k: v[k] for k in SCORES} for stem, v in scores["views"].items()}}


def layer_differences(a, b, valid: np.ndarray) -> dict:
    """Largest and 99th-percentile differences between two IntrinsicLayers (relative to ``a``'s range)."""
    out = {}
    for name in ("reflectance", "sky_shading", "indirect_shading", "sun_shading", "visibility"):
        x, y = np.asarray(getattr(a, name), float)[valid], np.asarray(getattr(b, name), float)[valid]
        scale = max(float(np.abs(x).max()), 1e-12)
        difference = np.abs(x - y) / scale
        out[name] = {"max": float(difference.max()), "p99": float(np.percentile(difference, 99))}
    return out


def time_mattings(inputs: dict, modules: dict, repeats: int) -> dict:
    """Median seconds per view of each matting on the recorded inputs, interleaved; solve reports."""
    seconds = {name: {stem: [] for stem in inputs} for name in modules}
    layers, reports = {}, {}
    names = list(modules)
    for repeat in range(repeats):
        for stem, (view, quantities, labels, radiance, clusters, config) in inputs.items():
            for name in (names if repeat % 2 == 0 else names[::-1]):
                module = modules[name]
                began = time.perf_counter()
                if module is after:
                    result = after.intrinsic_layers_result(view, quantities, labels, radiance, clusters=clusters,
                                                           config=config)
                    layers[name, stem] = result.layers
                    reports[stem] = [r.to_dict() for r in result.solves]
                else:
                    layers[name, stem] = module.intrinsic_layers(view, quantities, labels, radiance, clusters=clusters,
                                                                 config=before_config(module, config))
                seconds[name][stem].append(time.perf_counter() - began)
    out = {"repeats": repeats, "views": len(inputs), "size": "x".join(map(str, next(iter(inputs.values()))[0].shape[::-1])),
           "seconds_per_view": {name: float(np.median([np.median(s) for s in per.values()]))
                                for name, per in seconds.items()},
           "seconds_by_view": {name: {stem: float(np.median(s)) for stem, s in per.items()}
                               for name, per in seconds.items()},
           "after_solves": reports}
    if "before" in modules:
        out["speedup"] = out["seconds_per_view"]["before"] / out["seconds_per_view"]["after"]
        out["layer_differences"] = {stem: layer_differences(layers["before", stem], layers["after", stem],
                                                            inputs[stem][1].valid) for stem in inputs}
    return out


def first_use(before_path: str | None) -> dict:
    """Seconds of a fresh interpreter's import and first solve, after and (cold, then cached) before."""
    def run(load: str, env: dict | None = None) -> dict:
        began = time.perf_counter()
        done = subprocess.run([sys.executable, "-c", FIRST_USE.format(load=load)], capture_output=True, text=True,
                              check=True, env=env)
        figures = json.loads(done.stdout.strip().splitlines()[-1])
        return figures | {"process_seconds": time.perf_counter() - began}

    out = {"after": run(LOAD_AFTER)}
    if before_path is not None:
        with tempfile.TemporaryDirectory() as cache:
            env = dict(os.environ, NUMBA_CACHE_DIR=cache)
            out["before_cold"] = run(LOAD_BEFORE.format(path=before_path), env)
            out["before_cached"] = run(LOAD_BEFORE.format(path=before_path), env)
    return out


def solver_alternatives(inputs: tuple, before, max_iter: int = 500) -> dict:
    """Seconds and error of other solvers on the matte and propagation systems of one view.

    The error is against our solution, in units of its largest value. The others: SuperLU in its
    own orderings, conjugate gradients preconditioned by SciPy's incomplete LU or by pyamg's
    smoothed aggregation (if installed), and the former solver (pymatting's incomplete Cholesky,
    on the unknowns in the former row-major order).
    """
    view, quantities, labels, radiance, clusters, config = inputs
    systems, orders = [], []
    solve, ordered = after._solve, after._ordered

    def spy_solve(matrix, rhs, start, config, what, *, ordered=False):
        systems.append((matrix, rhs, np.array(start), what))
        return solve(matrix, rhs, start, config, what, ordered=ordered)

    def spy_order(pixels, laplacian):
        orders.append(ordered(pixels, laplacian))
        return orders[-1]

    after._solve, after._ordered = spy_solve, spy_order
    try:
        after.intrinsic_layers(view, quantities, labels, radiance, clusters=clusters, config=config)
    finally:
        after._solve, after._ordered = solve, ordered
    out = {}
    for index, (matrix, rhs, start, what) in enumerate(systems[:2]):  # the matte and the propagation
        back = np.argsort(orders[index]) if index < len(orders) else None
        out[what] = {"unknowns": int(matrix.shape[0]), "channels": int(rhs.shape[1]),
                     "solvers": _alternatives(matrix, rhs, start, what, config, back, before, max_iter)}
    return out


def _alternatives(matrix, rhs, start, what, config, back, before, max_iter) -> dict:
    from scipy.sparse import linalg as spla

    symmetric = {"diag_pivot_thresh": 0.0, "options": {"SymmetricMode": True}}

    def ours():
        return after._lu(matrix, ordered=True).solve(rhs), {}

    def superlu(spec):
        return spla.splu(matrix, permc_spec=spec, **symmetric).solve(rhs), {}

    def incomplete_lu():
        x, report = after._solve(matrix, rhs, start, dataclasses.replace(config, solver="cg", max_iter=max_iter), what)
        return x, {"n_iter": report.n_iter, "converged": report.converged}

    def amg():  # the first channel only (a V-cycle per channel and iteration: slow)
        import pyamg

        cycle = pyamg.smoothed_aggregation_solver(matrix.tocsr()).aspreconditioner()
        counter = []
        x, _ = spla.cg(matrix, rhs[:, 0], x0=start[:, 0], rtol=config.rtol, maxiter=max_iter, M=cycle,
                       callback=counter.append)
        return x[:, None], {"n_iter": len(counter), "channels_solved": 1}

    def former():
        permuted = matrix[back][:, back].tocsr()
        x = np.empty_like(rhs)
        x[back] = before._solve(permuted, rhs[back], start[back], before_config(before, config), what)
        return x, {}

    runs = {"superlu_nested_dissection (ours)": ours, "superlu_mmd_at_plus_a": lambda: superlu("MMD_AT_PLUS_A"),
            "superlu_colamd": lambda: superlu("COLAMD"), "cg_incomplete_lu": incomplete_lu}
    if importlib.util.find_spec("pyamg") is not None:
        runs["cg_pyamg_smoothed_aggregation"] = amg
    if before is not None and back is not None:
        runs["before: cg_pymatting_ichol"] = former
    rows, solutions = {}, {}
    for name, run in runs.items():
        began = time.perf_counter()
        try:
            solutions[name], note = run()
        except Exception as error:  # noqa: BLE001 - a benchmark reports what failed
            rows[name] = {"error": f"{type(error).__name__}: {error}"}
            continue
        rows[name] = {"seconds": time.perf_counter() - began} | note
    reference = solutions["superlu_nested_dissection (ours)"]
    scale = max(float(np.abs(reference).max()), 1e-12)
    for name, x in solutions.items():
        rows[name]["max_error"] = float(np.abs(x - reference[:, :x.shape[1]]).max() / scale)
    return rows


def peak_memory(inputs: tuple, size: tuple[int, int], before_path: str | None) -> dict:
    """Peak resident memory of one matting of ``inputs`` upsampled to ``size``, in a fresh process each."""
    out = {"size": f"{size[0]}x{size[1]}"}
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "inputs.pkl"
        with open(path, "wb") as file:
            pickle.dump(inputs, file)
        loads = {"after": LOAD_AFTER} | ({} if before_path is None else {"before": LOAD_BEFORE.format(path=before_path)})
        for label, load in loads.items():
            done = subprocess.run([sys.executable, "-c", MEMORY.format(load=load, inputs=str(path), size=size)],
                                  capture_output=True, text=True)
            if done.returncode:
                out[label] = {"error": done.stderr.strip().splitlines()[-1:]}
            else:
                out[label] = json.loads(done.stdout.strip().splitlines()[-1])
    return out


def upsampled(scene, width: int, height: int, n_views: int):
    """The first ``n_views`` views at ``width x height``: bilinear images, nearest masks, scaled cameras."""
    views = []
    for view in scene.views[:n_views]:
        image = cv2.resize(np.where(view.mask[..., None], view.image, 0.0).astype(np.float32), (width, height),
                           interpolation=cv2.INTER_LINEAR)
        mask = cv2.resize(view.mask.astype(np.uint8), (width, height), interpolation=cv2.INTER_NEAREST).astype(bool)
        views.append(View(view.stem, image, view.camera.scaled(width, height), mask))
    return dataclasses.replace(scene, views=tuple(views))


def scene_entry(name: str, folder: Path, modules: dict, repeats: int) -> dict:
    scene = load_scene(folder)
    entry = {"folder": str(folder), "size": "x".join(map(str, scene.views[0].shape[::-1])), "views": len(scene.views)}
    inputs = None
    for label, module in modules.items():
        hook = MattingHook(None if module is after else module)
        began = time.perf_counter()
        result = hook.decompose(scene, Config())
        entry[f"decompose_seconds_{label}"] = time.perf_counter() - began
        entry[label] = score(folder, scene, result)
        inputs = inputs or hook.inputs
    entry["timing"] = time_mattings(inputs, modules, repeats)
    return entry


def large_entry(folder: Path, n_views: int, modules: dict, repeats: int, *, alternatives: bool,
                memory: tuple[int, int] | None, before_path: str | None) -> dict:
    scene = load_scene(folder)
    source = "rendered"
    if scene.views[0].shape != LARGE[::-1]:
        scene, source = upsampled(scene, *LARGE, n_views), f"upsampled from {scene.views[0].shape[1]}x{scene.views[0].shape[0]}"
    hook = MattingHook(skip=True)
    config = Config(steps=3)
    hook.decompose(scene, config)
    if not hook.inputs:  # the upsampled views' model choice said no direct sun: force it (timing only)
        config = Config.from_dict({"steps": 3, "sun": {"direct_sun": "always"}})
        hook.decompose(scene, config)
    inputs = dict(list(hook.inputs.items())[:n_views])
    entry = {"folder": str(folder), "source": source, "views": len(inputs)} | time_mattings(inputs, modules, repeats)
    if alternatives:
        entry["solvers"] = solver_alternatives(next(iter(inputs.values())), modules.get("before"))
    if memory is not None:
        entry["memory"] = peak_memory(next(iter(inputs.values())), memory, before_path)
    return entry


def load_average() -> list[float] | None:
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--smoke", action="store_true", help="the demo only, after only, one repeat")
    parser.add_argument("--out", type=Path, default=None,
                        help="JSON report (default benchmarks/results/matting.json, matting_smoke.json with --smoke)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--scene", action="append", default=[], help="../data/NAME instead of the default list")
    parser.add_argument("--large", type=Path, default=None, help="scene for the 1000x750 timing")
    parser.add_argument("--large-views", type=int, default=3)
    parser.add_argument("--no-before", action="store_true", help="time the current matting only")
    parser.add_argument("--large-only", action="store_true", help="first use and the 1000x750 timing only")
    parser.add_argument("--solvers", action="store_true",
                        help="also time other solvers on the systems of the first 1000x750 view")
    parser.add_argument("--memory", default="1400x1050", metavar="WxH",
                        help="peak memory of one matting of the first 1000x750 view upsampled to WxH "
                             "(default 1400x1050, the default largest size of real photos; 'none' skips it)")
    args = parser.parse_args()
    if args.memory == "none":
        args.memory = None
    out = args.out or REPO / "benchmarks" / "results" / ("matting_smoke.json" if args.smoke else "matting.json")
    repeats = 1 if args.smoke else args.repeats
    report = {"benchmark": "matting", "version": mvintrinsic.__version__, "cores": os.cpu_count(),
              "python": platform.python_version(), "numpy": np.__version__, "scipy": scipy.__version__,
              "load_average_start": load_average(), "before_commit": BEFORE_COMMIT,
              "config": dataclasses.asdict(after.MattingConfig()), "scenes": {}}
    with tempfile.TemporaryDirectory() as tmp:
        before, why = (None, "--smoke or --no-before") if args.smoke or args.no_before else load_before(Path(tmp))
        modules = {"after": after} if before is None else {"before": before, "after": after}
        report["before"] = why if before is None else f"git show {BEFORE_COMMIT}:mvintrinsic/matting.py"
        report["first_use"] = first_use(None if before is None else why)
        print("first use:", json.dumps(report["first_use"]), flush=True)
        names = [] if args.large_only else ["demo"] + ([] if args.smoke else (args.scene or list(SCENES_480)))
        for name in names:
            folder = demo_scene_path() if name == "demo" else DATA / name
            if not (folder / "scene.json").is_file() or not (folder / "gt").is_dir():
                report["scenes"][name] = "not rendered"
                continue
            entry = report["scenes"][name] = scene_entry(name, folder, modules, repeats)
            print(f"{name} ({entry['size']}): " + "; ".join(
                f"{label} {entry['timing']['seconds_per_view'][label]:.2f} s/view, LMSE_R "
                f"{entry[label]['mean']['lmse_reflectance']:.4f} LMSE_S {entry[label]['mean']['lmse_shading']:.4f} "
                f"BER {entry[label]['mean']['ber']:.4f}" for label in modules), flush=True)
        if not args.smoke:
            large = args.large or DATA / "courtyard_1000"
            if not (large / "scene.json").is_file():
                large = next((DATA / n for n in SCENES_480 if (DATA / n / "scene.json").is_file()), None)
            if large is not None:
                entry = report["large"] = large_entry(
                    large, args.large_views, modules, repeats, alternatives=args.solvers,
                    memory=None if args.memory is None else tuple(map(int, args.memory.split("x"))),
                    before_path=None if before is None else why)
                print(f"1000x750 ({entry['source']}, {entry['views']} views): " + "; ".join(
                    f"{label} {s:.2f} s/view" for label, s in entry["seconds_per_view"].items()), flush=True)
    report["load_average_end"] = load_average()
    write_json(out, report)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
