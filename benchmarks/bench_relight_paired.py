"""The new sun's time against another checkout's per-sun shadow code, renders alternating in one process.

    python benchmarks/bench_relight_paired.py --reference DIR [--data DIR --scene NAME ...] [--size 1000x750]
                                              [--pairs 30] [--out benchmarks/results/relight_paired.json]

This virtual machine's speed drifts by 10-50% over minutes (``docs/relight.md``, "Speed"), more than a change of
10% in the code; two runs of the timing command (``bench_relight.py --timing``), one per commit, cannot tell such a
change from the drift. Here one :class:`~mvintrinsic.relight.Relighter` per scene (the ground-truth layers
resampled to ``--size``, the working tree's build) renders a new sun with this checkout's per-sun shadow code and
then with the reference checkout's (``DIR/mvintrinsic/shadow_caster.py``: ``ShadowCaster._visibility``,
``_strided`` and ``_fuse``, compiled in this module's namespace), the order swapped every pair and the azimuth
moved by one degree, so both see the same machine state. Reported per scene: seconds per view and sun of each
(mean, median), the median of the pairs' ratios (new over reference), the share of pairs where the new code was
faster, and whether every pair's images were identical to the bit. The reference must share the rest of the code
(the relighter's build and shading) with this checkout: the comparison is of those three functions alone.
"""

from __future__ import annotations

import argparse
import ast
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_relight  # noqa: E402  (the resampling of the timing command)
from bench_distributed import _parse_size  # noqa: E402

import mvintrinsic.relight as relight_module  # noqa: E402
import mvintrinsic.shadow_caster as shadow_caster  # noqa: E402
from mvintrinsic.evaluation import ground_truth_decomposition  # noqa: E402
from mvintrinsic.io import load_scene, write_json  # noqa: E402
from mvintrinsic.sun_position import azimuth_elevation  # noqa: E402

FUNCTIONS = ("_strided", "_fuse")
METHOD = "_visibility"


def reference_code(folder: Path) -> dict:
    """``_strided``, ``_fuse`` and ``ShadowCaster._visibility`` of ``folder/mvintrinsic/shadow_caster.py``, compiled
    in one copy of this checkout's module namespace (so the reference's ``_visibility`` calls the reference's
    ``_strided``; their other names resolve to this checkout's)."""
    path = folder / "mvintrinsic" / "shadow_caster.py"
    if not path.is_file():
        raise FileNotFoundError(f"--reference: no mvintrinsic/shadow_caster.py in {folder}")
    namespace = dict(vars(shadow_caster))
    found = {}
    for node in ast.parse(path.read_text(), str(path)).body:
        nodes = [node] if isinstance(node, ast.FunctionDef) and node.name in FUNCTIONS else []
        if isinstance(node, ast.ClassDef) and node.name == "ShadowCaster":
            nodes = [f for f in node.body if isinstance(f, ast.FunctionDef) and f.name == METHOD]
        for f in nodes:
            exec(compile(ast.Module([f], []), str(path), "exec"), namespace)  # noqa: S102 (a checkout's own code)
            found[f.name] = namespace[f.name]
    missing = set(FUNCTIONS + (METHOD,)) - set(found)
    if missing:
        raise ValueError(f"--reference: {path} has no {sorted(missing)}")
    return found


def use(code: dict) -> None:
    """Install ``code`` (:func:`reference_code`'s keys) as the per-sun shadow code."""
    shadow_caster._strided = code["_strided"]
    shadow_caster._fuse = relight_module._fuse = code["_fuse"]
    shadow_caster.ShadowCaster._visibility = code[METHOD]


def pair_scene(folder: Path, reference: dict, size: tuple[int, int], pairs: int) -> dict:
    """Alternating renders of one scene (module docstring); seconds per view and sun."""
    scene = load_scene(folder)
    truth = ground_truth_decomposition(folder, views=list(scene.stems))
    scene, truth = bench_relight.upscaled(scene, truth, size)
    current = {"_strided": shadow_caster._strided, "_fuse": shadow_caster._fuse,
               METHOD: shadow_caster.ShadowCaster._visibility}
    try:
        relighter = relight_module.Relighter(truth, scene)
        azimuth, elevation = azimuth_elevation(relighter.sun, up=scene.up)
        relighter.render((azimuth + 3.0, elevation))  # warm: the first render pays for fresh memory
        times = {"new": [], "reference": []}
        identical = True
        for k in range(pairs):
            sun = (azimuth + 5.0 + k % 21, elevation)
            images = {}
            order = (("new", current), ("reference", reference)) if k % 2 == 0 else \
                (("reference", reference), ("new", current))
            for name, code in order:
                use(code)
                start = time.perf_counter()
                images[name] = relighter.render(sun)
                times[name].append((time.perf_counter() - start) / len(relighter.stems))
            identical &= all(np.array_equal(images["new"][s], images["reference"][s]) for s in images["new"])
    finally:
        use(current)
    new, ref = np.array(times["new"]), np.array(times["reference"])
    return {
        "size": list(size), "views": len(relighter.stems), "pairs": pairs,
        "new_mean": float(new.mean()), "new_median": float(np.median(new)),
        "reference_mean": float(ref.mean()), "reference_median": float(np.median(ref)),
        "ratio_median": float(np.median(new / ref)), "new_faster_share": float(np.mean(new < ref)),
        "identical_images": bool(identical),
        "seconds_per_view_and_sun": {"new": new.tolist(), "reference": ref.tolist()},
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reference", type=Path, required=True, help="another checkout of the project")
    parser.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[1].parent / "data")
    parser.add_argument("--scene", action="append", default=None, help="scene folder name under --data")
    parser.add_argument("--size", type=_parse_size, default=(1000, 750),
                        help="WxH the views are resampled to (default 1000x750)")
    parser.add_argument("--pairs", type=int, default=30)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    if args.pairs < 1:
        parser.error(f"--pairs must be at least 1, got {args.pairs}")
    reference = reference_code(args.reference)
    out = {"benchmark": "relight_paired", "reference": str(args.reference), "scenes": {}}
    for name in args.scene or ["demo_480r", "courtyard_s1r", "street_s0r"]:
        folder = args.data / name
        if not folder.is_dir():
            parser.error(f"--scene {name}: no folder {folder}")
        row = pair_scene(folder, reference, args.size, args.pairs)
        out["scenes"][name] = row
        print(f"{name}: new {row['new_median'] * 1e3:.1f} ms, reference {row['reference_median'] * 1e3:.1f} ms per view "
              f"and sun (medians); new/reference {row['ratio_median']:.3f}, new faster in "
              f"{row['new_faster_share']:.0%} of {args.pairs} pairs; identical images: {row['identical_images']}",
              flush=True)
    if args.out is not None:
        write_json(args.out, out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
