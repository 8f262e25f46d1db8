"""Stability of the decomposition, one factor at a time from a good scene: issue 17, item 3.

    python benchmarks/bench_stability.py [--data DIR] [--base NAME] [--reference NAME]
                                         [--overcast NAME] [--noshadow NAME] [--factor F ...]
                                         [--out benchmarks/results/stability.json]
                                         [--plot benchmarks/results/stability.png]
    python benchmarks/bench_stability.py --smoke
    python benchmarks/bench_stability.py --plot-only benchmarks/results/stability.json

The base is ``DIR/stability_base`` (16 views of the street recipe, seed 0, MVS-like proxy, exact
sun, linear EXR photos with one exposure). Each factor changes one thing, the rest stays at the
base setting; every variant is an in-memory :class:`mvintrinsic.Scene` (``dataclasses.replace``
of the loaded scene), seeded:

* ``proxy``: ``clean`` (``proxy_clean.ply``, the exact mesh, subdivided to 20 cm edges), ``mvs`` (``proxy.ply``, the base),
  ``decimated`` (the MVS proxy decimated 10x by open3d's quadric decimation), ``missing`` (half
  of the MVS proxy's area removed as connected patches: the faces whose centroid lies within
  :data:`HOLE_RADIUS` of random, area-weighted face centroids, until half the area is gone);
* ``views``: 16 (base), 8, 4, 2 views, spread along the path (indices ``round(linspace(0, 15, n))``),
  the 16-view proxy kept;
* ``sun_error``: the sun direction rotated by 0, 2, 5, 10 degrees about the horizontal axis
  perpendicular to it (its elevation changes; the sign is seeded);
* ``noise``: Gaussian noise of standard deviation ``sqrt(a + b I)`` (read noise plus a shot-noise
  term), 1, 3 and 10% of the view's median per channel at the median level (half from each term),
  clipped at 0;
* ``exposure``: per-view gains ``2^e_k w_k`` with ``e_k`` uniform in [-s, s] stops and ``log w_k``
  uniform in [-0.15 s, 0.15 s] per channel (``mvintrinsic.synth.capture``'s model), geometric mean
  1, on the linear photos, for s = 0.25, 0.5 and 1 stop;
* ``scene``: ``sunny`` (``DIR/street_s0``: the same street, sun and 8 cameras as the two others,
  the reference for them), ``overcast`` (``DIR/stability_overcast``, rendered with the sun off)
  and ``noshadow`` (``DIR/stability_noshadow``: the street without occluders,
  ``SynthConfig(occluders=False)``, sun on; the photos hold no cast shadow).

Every point runs in its own subprocess (a crash is recorded with its return code or signal and
the sweep goes on), first with the default ``Config()``. A documented mvintrinsic error
(:data:`DOCUMENTED_ERRORS`) is recorded; after a
:class:`~mvintrinsic.sun_calibration.SunCalibrationError` the point is run again with
``Config(allow_missing_sun=True)``, the documented fallback (``L_sun = 0``), and flagged. Any
other exception is a failure. Per point:

* ``lmse_reflectance``, ``lmse_shading``, ``ber`` (:func:`mvintrinsic.evaluation.evaluate`, mean
  over the views; the BER of the overcast scene scores labels against where the sun *would* fall);
* ``lsun_rel_error``: ``L_sun`` estimate / truth - 1 per channel (None where the truth is 0, the
  overcast scene: ``lsun_over_reference`` divides by the sunny reference's truth instead);
* ``seconds``, ``seconds_per_view`` and ``timings`` (the decomposition's seconds per stage);
* ``nonfinite``: layers or lighting arrays holding NaN or inf (must be empty);
* ``warnings`` raised during the decomposition, ``lighting`` flags (``horizon_evidence``, the
  exposure gains and why they were or were not applied, the sky fit), and for ``exposure`` the
  estimated gains against the applied ones;
* ``retinex``: the colour Retinex baseline (``benchmarks/baselines``) on the same photos, where
  they differ from the base's (``proxy`` and ``sun_error`` points share the base's).

``--smoke`` runs the embedded demo: its base, a 5-degree sun error and 3% noise (CI, < 2 min).
Results are written after every point, atomically; ``--plot`` draws one panel per factor.
``--update --factor F --out REPORT`` reruns the base and factor F only and replaces those points in
REPORT (after a change that can only move them).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import platform
import signal
import subprocess
import sys
import tempfile
import time
import traceback
import warnings
from pathlib import Path

import numpy as np
from _figures import require_matplotlib

ROOT = Path(__file__).resolve().parents[2]
HERE = Path(__file__).resolve()

#: Seed of every random change (sign of the sun error, noise, gains, removed patches).
SEED = 0
#: Radius of the spheres whose faces are removed from the proxy (``missing``), metres.
HOLE_RADIUS = 1.5
#: Fraction of the proxy's area removed (``missing``).
MISSING_FRACTION = 0.5
#: Decimation factor of the ``decimated`` proxy (triangles / this).
DECIMATION = 10
#: White-balance range per stop of exposure range (``exposure``): 0.15 at 1 stop, as
#: ``mvintrinsic.synth.capture.imitate_capture``'s defaults.
WB_PER_STOP = 0.15
#: Seconds after which a point's subprocess is killed and recorded as a timeout.
TIMEOUT = 3 * 3600

#: Factor levels; the base setting of each is the first entry that equals BASE's.
LEVELS = {
    "proxy": ["clean", "mvs", "decimated", "missing"],
    "views": [16, 8, 4, 2],
    "sun_error": [0.0, 2.0, 5.0, 10.0],
    "noise": [0.0, 0.01, 0.03, 0.10],
    "exposure": [0.0, 0.25, 0.5, 1.0],
    "scene": ["sunny", "overcast", "noshadow"],
}
#: The base setting (``views`` None: all the base scene's views).
BASE = {"scene": "base", "proxy": "mvs", "views": None, "sun_error": 0.0, "noise": 0.0, "exposure": 0.0}
SMOKE_LEVELS = {"sun_error": [0.0, 5.0], "noise": [0.0, 0.03]}
#: mvintrinsic's documented errors (decompose's Raises, the loaders' SceneError, the sky fit's).
DOCUMENTED_ERRORS = ("SunCalibrationError", "NoGroundPlaneError", "SkyFitError", "SceneError")


# -------------------------------------------------------------------------------------------------
# variants (in-memory scenes)
# -------------------------------------------------------------------------------------------------
def _rng(*key: int) -> np.random.Generator:
    return np.random.default_rng([SEED, *key])


def spread_indices(n_total: int, n: int) -> list[int]:
    """``n`` view indices spread evenly over ``range(n_total)`` (the first and the last included)."""
    return sorted({int(i) for i in np.round(np.linspace(0, n_total - 1, n))})


def _mesh_proxy(proxy, vertices: np.ndarray, triangles: np.ndarray, normals: np.ndarray):
    """A Proxy of ``vertices``/``triangles`` with ``normals`` oriented like ``proxy``'s nearest vertex's."""
    from scipy.spatial import cKDTree

    from mvintrinsic import Proxy

    _, nearest = cKDTree(proxy.vertices).query(vertices)
    reference = proxy.normals[nearest]
    length = np.linalg.norm(normals, axis=1)
    bad = ~np.isfinite(length) | (length < 1e-9)
    normals = np.where(bad[:, None], reference, normals / np.where(bad, 1.0, length)[:, None])
    flip = np.einsum("ij,ij->i", normals, reference) < 0
    normals[flip] *= -1.0
    return Proxy(vertices, normals, triangles), {"flipped_normals": float(flip.mean()),
                                                  "replaced_normals": float(bad.mean())}


def decimated_proxy(proxy, factor: int = DECIMATION):
    """The mesh ``proxy`` decimated to ``1/factor`` of its triangles (open3d quadric decimation)."""
    import open3d as o3d

    # open3d refuses read-only arrays: copies
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(np.array(proxy.vertices)),
                                     o3d.utility.Vector3iVector(np.array(proxy.triangles, dtype=np.int32)))
    mesh = mesh.simplify_quadric_decimation(target_number_of_triangles=max(4, len(proxy.triangles) // factor))
    mesh.remove_degenerate_triangles()
    mesh.remove_unreferenced_vertices()
    mesh.compute_vertex_normals()
    out, info = _mesh_proxy(proxy, np.asarray(mesh.vertices), np.asarray(mesh.triangles),
                            np.asarray(mesh.vertex_normals).copy())
    info.update(triangles_before=int(len(proxy.triangles)), triangles=int(len(out.triangles)))
    return out, info


def _areas_centroids(vertices: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    a, b, c = (vertices[triangles[:, i]] for i in range(3))
    return 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1), (a + b + c) / 3.0


def holed_proxy(proxy, *, fraction: float = MISSING_FRACTION, radius: float = HOLE_RADIUS, rng=None):
    """``proxy`` with ``fraction`` of its area removed as patches: the faces within ``radius`` of
    random face centroids (drawn by area among the faces left), until ``fraction`` is gone."""
    from mvintrinsic import Proxy

    rng = np.random.default_rng(rng)
    area, centroid = _areas_centroids(proxy.vertices, proxy.triangles)
    removed = np.zeros(len(area), dtype=bool)
    total, patches = area.sum(), 0
    while area[removed].sum() < fraction * total:
        alive = np.flatnonzero(~removed)
        centre = centroid[rng.choice(alive, p=area[alive] / area[alive].sum())]
        removed |= np.linalg.norm(centroid - centre, axis=1) < radius
        patches += 1
    kept = proxy.triangles[~removed]
    used = np.unique(kept)
    index = np.full(len(proxy.vertices), -1, dtype=np.int64)
    index[used] = np.arange(len(used))
    out = Proxy(proxy.vertices[used], proxy.normals[used], index[kept])
    return out, {"removed_area_fraction": float(area[removed].sum() / total), "patches": patches,
                 "triangles_before": int(len(proxy.triangles)), "triangles": int(len(kept))}


def rotated_sun(sun, up: np.ndarray, degrees: float, rng=None):
    """``sun`` turned by ``degrees`` about the horizontal axis perpendicular to it (sign from ``rng``)."""
    from mvintrinsic import Sun

    rng = np.random.default_rng(rng)
    d = np.asarray(sun.direction, dtype=np.float64)
    axis = np.cross(up, d)
    axis /= np.linalg.norm(axis)
    angle = math.radians(degrees) * rng.choice([-1.0, 1.0])
    turned = d * math.cos(angle) + np.cross(axis, d) * math.sin(angle)  # Rodrigues, axis perpendicular to d
    return Sun(turned, angular_radius=sun.angular_radius)


def noisy_view(view, level: float, rng=None):
    """``view`` with noise of standard deviation ``level`` times its median (per channel) at the median."""
    rng = np.random.default_rng(rng)
    image = view.image.astype(np.float64)
    median = np.maximum(np.median(image[view.mask], axis=0), 1e-12)
    variance = (level * median) ** 2 * (0.5 + 0.5 * np.maximum(image, 0.0) / median)  # read + shot noise
    out = np.maximum(image + np.sqrt(variance) * rng.standard_normal(image.shape), 0.0)
    out = np.where(view.mask[..., None], out, view.image).astype(np.float32)
    return dataclasses.replace(view, image=out, mask=view.mask)


def view_gains(n: int, stops: float, rng=None) -> np.ndarray:
    """(n, 3) gains ``2^e w``: ``e`` uniform in [-stops, stops], ``log w`` in +-WB_PER_STOP*stops, geometric mean 1."""
    rng = np.random.default_rng(rng)
    log_gain = (rng.uniform(-stops, stops, n)[:, None] * math.log(2.0)
                + rng.uniform(-WB_PER_STOP * stops, WB_PER_STOP * stops, (n, 3)))
    return np.exp(log_gain - log_gain.mean(axis=0))


# -------------------------------------------------------------------------------------------------
# one point (run in a subprocess)
# -------------------------------------------------------------------------------------------------
def _nonfinite(result) -> list[str]:
    bad = []
    for stem, layer in result.layers.items():
        for name in ("reflectance", "sun_shading", "sky_shading", "indirect_shading", "visibility"):
            if not np.isfinite(getattr(layer, name)).all():
                bad.append(f"{stem}.{name}")
    lighting = result.lighting
    for name in ("sun_radiance", "envmap", "horizon_plane"):
        value = getattr(lighting, name)
        if value is not None and not np.isfinite(value).all():
            bad.append(f"lighting.{name}")
    return bad


def _error(exc: BaseException) -> dict:
    kind = type(exc).__name__
    return {"type": kind, "module": type(exc).__module__, "message": str(exc)[:2000],
            "documented": kind in DOCUMENTED_ERRORS and type(exc).__module__.startswith("mvintrinsic"),
            "traceback": traceback.format_exc()[-4000:]}


def _jsonable(value):
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, (np.floating, float)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.bool_):
        return bool(value)
    return value


def _score(folder: Path, scene, result, work: Path) -> dict:
    from mvintrinsic.evaluation import evaluate
    from mvintrinsic.io import save_decomposition

    out = work / f"result_{time.perf_counter_ns()}"
    save_decomposition(result, out, scene=scene)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        report = evaluate(folder, out, views=list(scene.stems))
    mean = report["mean"]
    single = sum(bool(v.get("ber_single_class")) for v in report["views"].values())
    return {"lmse_reflectance": mean["lmse_reflectance"], "lmse_shading": mean["lmse_shading"],
            "ber": mean["ber"], "ber_single_class_views": single,
            "evaluation_warnings": sorted({str(w.message) for w in caught})}


def _lighting_flags(result) -> dict:
    lighting = result.lighting
    flags = {"horizon_evidence": lighting.horizon_evidence,
             "sky": None if lighting.sky is None else lighting.sky.to_dict()}
    gains = lighting.exposure
    if gains is not None:
        flags["exposure"] = {"applied": gains.applied, "reason": gains.reason,
                             "max_abs_log_gain": float(np.abs(np.log(gains.estimated)).max())}
    # the model chosen from the data, as lighting.json records it
    flags["model"] = {name: {"choice": c.choice, "evidence": c.evidence} for name, c in lighting.model.items()}
    return flags


def build_variant(spec: dict, folders: dict) -> tuple:
    """The point's scene (in memory), its scene folder and what was changed."""
    from mvintrinsic import load_scene

    folder = folders[spec["scene"]]
    stems = None
    if spec["views"] is not None:
        scene = load_scene(folder)
        stems = [scene.stems[i] for i in spread_indices(len(scene.stems), spec["views"])]
    scene = load_scene(folder, views=stems)
    info: dict = {"views": list(scene.stems)}
    if spec["proxy"] == "clean":  # the exact mesh, subdivided as the Step-1 benchmarks do (vertex quantities)
        from bench_step1_accuracy import clean_proxy

        scene = dataclasses.replace(scene, proxy=clean_proxy(folder, scene))
    elif spec["proxy"] == "decimated":
        proxy, info["proxy"] = decimated_proxy(scene.proxy)
        scene = dataclasses.replace(scene, proxy=proxy)
    elif spec["proxy"] == "missing":
        proxy, info["proxy"] = holed_proxy(scene.proxy, rng=_rng(1))
        scene = dataclasses.replace(scene, proxy=proxy)
    if spec["sun_error"]:
        sun = rotated_sun(scene.sun, scene.up, spec["sun_error"], rng=_rng(2))
        angle = math.degrees(math.acos(np.clip(sun.direction @ scene.sun.direction, -1.0, 1.0)))
        info["sun"] = {"direction": sun.direction.tolist(), "angle_deg": angle,
                       "elevation_change_deg": math.degrees(sun.elevation(scene.up) - scene.sun.elevation(scene.up))}
        scene = dataclasses.replace(scene, sun=sun)
    if spec["noise"]:
        views = tuple(noisy_view(v, spec["noise"], rng=_rng(3, k)) for k, v in enumerate(scene.views))
        scene = dataclasses.replace(scene, views=views)
    if spec["exposure"]:
        gains = view_gains(len(scene.views), spec["exposure"], rng=_rng(4))
        views = tuple(dataclasses.replace(v, image=(v.image * g.astype(np.float32)).astype(np.float32), mask=v.mask)
                      for v, g in zip(scene.views, gains, strict=True))
        scene = dataclasses.replace(scene, views=views)
        info["applied_gains"] = gains.tolist()
    info["proxy_size"] = {"vertices": int(len(scene.proxy.vertices)),
                          "triangles": int(len(scene.proxy.triangles)) if scene.proxy.is_mesh else 0}
    return scene, folder, info


def run_point(spec: dict, folders: dict, *, retinex: bool, reference_truth: list | None) -> dict:
    """Decompose one variant (default config, then the documented fallback if needed) and score it."""
    import faulthandler

    faulthandler.enable()
    from mvintrinsic import Config, decompose
    from mvintrinsic.evaluation import read_ground_truth_lighting

    out: dict = {"spec": spec}
    scene, folder, out["variant"] = build_variant(spec, folders)
    attempts = []
    result = None
    for config in (Config(), Config(allow_missing_sun=True)):
        attempt = {"config": "default" if not config.allow_missing_sun else "allow_missing_sun=True"}
        start = time.perf_counter()
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                result = decompose(scene, config=config)
                attempt["outcome"] = "ok"
            except Exception as exc:  # recorded: documented errors and failures alike
                attempt["outcome"] = "error"
                attempt["error"] = _error(exc)
        attempt["seconds"] = time.perf_counter() - start
        attempt["warnings"] = [f"{w.category.__name__}: {w.message}" for w in caught]
        attempts.append(attempt)
        if result is not None or attempt["error"]["type"] != "SunCalibrationError":
            break
    out["attempts"] = attempts
    last = attempts[-1]
    out["outcome"] = ("ok" if len(attempts) == 1 else "fallback") if result is not None else (
        "documented_error" if last["error"]["documented"] else "failure")
    n = len(scene.views)
    with tempfile.TemporaryDirectory() as tmp:
        if result is not None:
            out["nonfinite"] = _nonfinite(result)
            out["seconds"] = last["seconds"]
            out["seconds_per_view"] = last["seconds"] / n
            out["timings"] = dict(result.timings)
            out["lighting"] = _lighting_flags(result)
            out.update(_score(folder, scene, result, Path(tmp)))
            truth = np.asarray(read_ground_truth_lighting(folder).sun_radiance, dtype=np.float64)
            estimate = np.asarray(result.lighting.sun_radiance, dtype=np.float64)
            out["lsun"] = estimate.tolist()
            out["lsun_truth"] = truth.tolist()
            out["lsun_rel_error"] = (estimate / truth - 1.0).tolist() if (truth > 0).all() else None
            if reference_truth is not None:
                out["lsun_over_reference"] = (estimate / np.asarray(reference_truth)).tolist()
            if spec["exposure"] and result.lighting.exposure is not None:
                applied = np.asarray(out["variant"]["applied_gains"])
                error = np.abs(result.lighting.exposure.gains / applied - 1.0)
                out["gain_error"] = {"max": float(error.max()), "mean": float(error.mean()),
                                     "estimated": result.lighting.exposure.estimated.tolist()}
        if retinex:
            sys.path.insert(0, str(HERE.parent / "baselines"))
            from run_retinex import retinex_decomposition

            start = time.perf_counter()
            baseline = retinex_decomposition(scene)
            seconds = time.perf_counter() - start
            scores = _score(folder, scene, baseline, Path(tmp))
            out["retinex"] = {"lmse_reflectance": scores["lmse_reflectance"], "lmse_shading": scores["lmse_shading"],
                              "seconds_per_view": seconds / n}
    return _jsonable(out)


# -------------------------------------------------------------------------------------------------
# the sweep
# -------------------------------------------------------------------------------------------------
def sweep_points(levels: dict) -> list[dict]:
    """(factor, level, spec) of every point; the base setting is run once, under factor ``base``."""
    points = [{"factor": "base", "level": "base", "spec": dict(BASE)}]
    for factor, values in levels.items():
        for value in values:
            spec = dict(BASE)
            if factor == "scene":
                spec.update(scene=value, views=None)
            elif factor == "views":
                spec["views"] = value
            else:
                spec[factor] = value
            if spec == BASE or (factor == "views" and value == 16):
                continue  # the base point
            points.append({"factor": factor, "level": value, "spec": spec})
    return points


def _signal_name(rc: int) -> str | None:
    if rc >= 0:
        return None
    try:
        return signal.Signals(-rc).name
    except ValueError:
        return f"signal {-rc}"


def run_in_subprocess(point: dict, folders: dict, *, retinex: bool, reference_truth, timeout: float) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        result_file = Path(tmp) / "point.json"
        job = {"spec": point["spec"], "folders": {k: str(v) for k, v in folders.items()}, "retinex": retinex,
               "reference_truth": reference_truth, "out": str(result_file)}
        start = time.perf_counter()
        try:
            proc = subprocess.run([sys.executable, str(HERE), "--_point", json.dumps(job)], capture_output=True,
                                  text=True, timeout=timeout)
            rc, stderr = proc.returncode, proc.stderr
        except subprocess.TimeoutExpired as exc:
            rc, stderr = None, (exc.stderr or b"").decode(errors="replace") if isinstance(exc.stderr, bytes) else (
                exc.stderr or "")
        wall = time.perf_counter() - start
        entry = {"factor": point["factor"], "level": point["level"], "rc": rc, "signal": None if rc is None else
                 _signal_name(rc), "wall_seconds": wall}
        if result_file.is_file():
            entry.update(json.loads(result_file.read_text()))
        else:
            entry.update(spec=point["spec"], outcome="timeout" if rc is None else "crash",
                         stderr_tail=stderr[-4000:])
    return entry


def _fmt(value, spec: str = ".4f") -> str:
    return "-" if value is None else format(value, spec)


def summary_line(entry: dict) -> str:
    lsun = entry.get("lsun_rel_error")
    lsun_text = "-" if lsun is None else "/".join(f"{x:+.2f}" for x in lsun)
    ret = entry.get("retinex") or {}
    return (f"{entry['factor']:9s} {str(entry['level']):9s} {entry['outcome']:16s} "
            f"LMSE R {_fmt(entry.get('lmse_reflectance'))} S {_fmt(entry.get('lmse_shading'))} "
            f"BER {_fmt(entry.get('ber'), '.3f')} L_sun {lsun_text}  "
            f"{_fmt(entry.get('seconds_per_view'), '.1f')} s/view  nonfinite {len(entry.get('nonfinite') or [])}  "
            f"retinex R {_fmt(ret.get('lmse_reflectance'))}")


#: Stages of the decomposition's timings, summed (dotted sub-stages of a timed stage are left out).
STAGES = {"gains": ("depth_maps", "exposure"), "step1": ("step1.",), "step2": ("pixels", "sun_pairs"),
          "step3": ("shadow_labels", "shadow_mrf", "segmentation", "matting", "layers"), "step4": ("step4",)}


def stage_seconds(timings: dict) -> dict:
    """Seconds per stage group (:data:`STAGES`) from a decomposition's ``timings``."""
    out = {}
    for group, keys in STAGES.items():
        out[group] = sum(v for k, v in timings.items()
                         if (k in keys) or any(key.endswith(".") and k.startswith(key) for key in keys))
    return out


def _flags(entry: dict) -> str:
    """Short notes: the fallback, the gains, a horizon from 'up', the decomposition's warnings."""
    notes = []
    if entry.get("outcome") == "fallback":
        notes.append("default: " + entry["attempts"][0]["error"]["type"] + ", then allow_missing_sun (L_sun = 0)")
    elif entry.get("outcome") not in ("ok", None):
        error = (entry.get("attempts") or [{}])[-1].get("error") or {}
        notes.append(f"{entry['outcome']}: {error.get('type', entry.get('signal') or '')}")
    lighting = entry.get("lighting") or {}
    if (lighting.get("exposure") or {}).get("applied"):
        notes.append(f"gains applied (max err {entry.get('gain_error', {}).get('max', float('nan')):.1%})")
    if lighting.get("horizon_evidence") not in (None, "proxy plane"):
        notes.append(f"horizon from {lighting['horizon_evidence']}")
    warned = {w.split(":")[0] + ": " + w.split(":", 1)[1].strip()[:60]
              for a in entry.get("attempts", []) if a.get("outcome") == "ok" for w in a.get("warnings", [])}
    notes += sorted(warned)
    if entry.get("nonfinite"):
        notes.append(f"NaN/inf in {len(entry['nonfinite'])} arrays")
    return "; ".join(notes)


def markdown_table(report: dict) -> str:
    """The points as a Markdown table (docs/stability.md)."""
    rows = ["| factor | level | outcome | LMSE R | LMSE S | BER | L_sun / truth - 1 (R, G, B) | s / view "
            "(gains, 1, 2, 3, 4) | Retinex LMSE R, S | notes |",
            "|---|---|---|---|---|---|---|---|---|---|"]
    for e in report["points"]:
        lsun = e.get("lsun_rel_error")
        if lsun is not None:
            lsun_text = ", ".join(f"{x:+.2f}" for x in lsun)
        elif e.get("lsun_over_reference") is not None:
            lsun_text = "truth 0; " + ", ".join(f"{x:.2f}" for x in e["lsun_over_reference"]) + " of sunny"
        else:
            lsun_text = "-"
        n = len((e.get("variant") or {}).get("views", [])) or 1
        stages = stage_seconds(e.get("timings") or {})
        stage_text = (f"{_fmt(e.get('seconds_per_view'), '.1f')} (" +
                      ", ".join(f"{v / n:.1f}" for v in stages.values()) + ")") if e.get("timings") else "-"
        ret = e.get("retinex") or {}
        rows.append(f"| {e['factor']} | {e['level']} | {e['outcome']} | {_fmt(e.get('lmse_reflectance'))} | "
                    f"{_fmt(e.get('lmse_shading'))} | {_fmt(e.get('ber'), '.3f')} | {lsun_text} | {stage_text} | "
                    f"{_fmt(ret.get('lmse_reflectance'))}, {_fmt(ret.get('lmse_shading'))} | {_flags(e)} |")
    return "\n".join(rows)


def _platform() -> dict:
    import mvintrinsic

    package = Path(mvintrinsic.__file__).resolve().parent
    info = {"version": mvintrinsic.__version__, "package": str(package), "cores": os.cpu_count(),
            "python": platform.python_version(), "platform": platform.platform(), "machine": platform.machine()}
    try:
        commit = subprocess.run(["git", "-C", str(package), "rev-parse", "HEAD"], capture_output=True, text=True,
                                check=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(package), "status", "--porcelain", "--", "."], capture_output=True,
                               text=True, check=True).stdout.strip()
        info.update(commit=commit, package_modified=bool(dirty))
    except (OSError, subprocess.CalledProcessError):
        info.update(commit=None, package_modified=None)
    return info


def _write(path: Path | None, report: dict) -> None:
    if path is not None:
        from mvintrinsic.io import write_json

        write_json(path, _jsonable(report))


# -------------------------------------------------------------------------------------------------
# plot
# -------------------------------------------------------------------------------------------------
FACTOR_TITLES = {"proxy": "proxy", "views": "views", "sun_error": "sun direction error (deg)",
                 "noise": "image noise (% of median)", "exposure": "per-view exposure range (stops)",
                 "scene": "scene"}


def factor_series(report: dict, factor: str) -> list[dict]:
    """The points of ``factor`` in level order, with the base point at the base level."""
    entries = [e for e in report["points"] if e["factor"] == factor]
    base = next((e for e in report["points"] if e["factor"] == "base"), None)
    levels = report["levels"][factor]
    out = []
    for level in levels:
        match = [e for e in entries if e["level"] == level]
        if match:
            out.append(match[0])
        elif base is not None and factor != "scene":
            out.append({**base, "level": level})
    return out


def plot(report: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    factors = [f for f in report["levels"] if factor_series(report, f)]
    fig, axes = plt.subplots(2, len(factors), figsize=(3.3 * len(factors), 6.4), squeeze=False)
    for col, factor in enumerate(factors):
        series = factor_series(report, factor)
        labels = [str(e["level"]) if factor != "noise" else f"{100 * float(e['level']):g}" for e in series]
        x = np.arange(len(series))

        def values(key, series=series):
            return np.array([np.nan if e.get(key) is None else e[key] for e in series], dtype=float)

        def retinex(key, series=series):
            return np.array([np.nan if not e.get("retinex") else e["retinex"][key] for e in series], dtype=float)

        top, bottom = axes[0, col], axes[1, col]
        top.plot(x, values("lmse_reflectance"), "o-", color="C0", label="LMSE R")
        top.plot(x, values("lmse_shading"), "s-", color="C1", label="LMSE S")
        top.plot(x, retinex("lmse_reflectance"), "o--", color="C0", alpha=0.5, label="Retinex LMSE R")
        top.plot(x, retinex("lmse_shading"), "s--", color="C1", alpha=0.5, label="Retinex LMSE S")
        for i, e in enumerate(series):
            if e.get("outcome") not in ("ok", None):
                top.annotate(e["outcome"], (x[i], 0.0), textcoords="offset points", xytext=(0, 4), ha="center",
                             fontsize=7, color="C3", rotation=90)
        top.set_ylim(bottom=0)
        twin = top.twinx()
        twin.plot(x, values("seconds_per_view"), "^:", color="0.4", label="s / view")
        twin.set_ylim(bottom=0)
        if col == len(factors) - 1:
            twin.set_ylabel("seconds per view")
        top.set_title(FACTOR_TITLES.get(factor, factor), fontsize=9)
        # |L_sun / truth - 1|; where the truth is 0 (overcast): L_sun over the sunny reference's truth
        lsun = np.array([np.mean(np.abs(e["lsun_rel_error"])) if e.get("lsun_rel_error") else
                         np.mean(e["lsun_over_reference"]) if e.get("lsun_over_reference") else np.nan
                         for e in series])
        bottom.plot(x, values("ber"), "o-", color="C2", label="shadow BER")
        bottom.plot(x, lsun, "d-", color="C3", label="|L_sun rel. error| (mean RGB)")
        bottom.set_ylim(bottom=0)
        for ax in (top, bottom):
            ax.set_xticks(x, labels, fontsize=8)
            ax.grid(alpha=0.3)
        if col == 0:
            top.set_ylabel("LMSE")
            bottom.set_ylabel("BER, L_sun error")
            handles = top.get_legend_handles_labels()
            more = twin.get_legend_handles_labels()
            top.legend(handles[0] + more[0], handles[1] + more[1], fontsize=7, loc="upper left")
            bottom.legend(fontsize=7, loc="upper left")
    base = report.get("scenes", {}).get("base", "")
    fig.suptitle(f"Stability, one factor at a time from {Path(str(base)).name} (mvintrinsic "
                 f"{report['platform']['version']})", fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.NamedTemporaryFile(dir=path.parent, suffix=".png", delete=False) as tmp:
        fig.savefig(tmp.name, dpi=110)
    os.replace(tmp.name, path)
    plt.close(fig)


# -------------------------------------------------------------------------------------------------
def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=ROOT / "data", help="folder of the rendered scenes")
    parser.add_argument("--base", default="stability_base", help="DATA/NAME of the base scene")
    parser.add_argument("--reference", default="street_s0", help="DATA/NAME of the sunny reference (scene factor)")
    parser.add_argument("--overcast", default="stability_overcast", help="DATA/NAME of the overcast scene")
    parser.add_argument("--noshadow", default="stability_noshadow", help="DATA/NAME of the scene without cast shadow")
    parser.add_argument("--factor", action="append", choices=sorted(LEVELS), help="only these factors (repeatable)")
    parser.add_argument("--smoke", action="store_true", help="the embedded demo, three points (CI)")
    parser.add_argument("--timeout", type=float, default=TIMEOUT, help="seconds per point before it is killed")
    parser.add_argument("--out", type=Path, default=None, help="JSON report (written after every point)")
    parser.add_argument("--update", action="store_true",
                        help="rerun only the --factor points (and the base) and replace them in the --out report")
    parser.add_argument("--plot", type=Path, default=None, help="PNG of the curves")
    parser.add_argument("--plot-only", type=Path, default=None, help="draw --plot from this JSON report and exit")
    parser.add_argument("--_point", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    require_matplotlib(parser, args, "plot", "plot_only")

    if args._point:  # the child: one point
        job = json.loads(args._point)
        try:
            out = run_point(job["spec"], {k: Path(v) for k, v in job["folders"].items()}, retinex=job["retinex"],
                            reference_truth=job["reference_truth"])
        except Exception as exc:  # outside decompose (building the variant, scoring): a failure of the harness
            out = {"spec": job["spec"], "outcome": "harness_error", "error": _error(exc)}
        Path(job["out"]).write_text(json.dumps(out, allow_nan=False))
        return 0
    if args.plot_only:
        report = json.loads(args.plot_only.read_text())
        plot(report, args.plot or args.plot_only.with_suffix(".png"))
        print(markdown_table(report))
        return 0

    from mvintrinsic.cli import demo_scene_path
    from mvintrinsic.evaluation import read_ground_truth_lighting

    if args.smoke:
        folders = {"base": demo_scene_path()}
        levels = dict(SMOKE_LEVELS)
    else:
        folders = {"base": args.data / args.base, "sunny": args.data / args.reference,
                   "overcast": args.data / args.overcast, "noshadow": args.data / args.noshadow}
        levels = {f: LEVELS[f] for f in (args.factor or LEVELS)}
        if "scene" not in levels:
            folders = {"base": folders["base"]}
    for name, folder in folders.items():
        if not (folder / "scene.json").is_file():
            parser.error(f"{name} scene: no scene.json in {folder}")
    reference_truth = None
    if "sunny" in folders:
        reference_truth = read_ground_truth_lighting(folders["sunny"]).sun_radiance.tolist()

    report = {"benchmark": "stability", "platform": _platform(), "seed": SEED, "scenes": {k: str(v) for k, v in
              folders.items()}, "levels": levels, "base": BASE,
              "settings": {"hole_radius_m": HOLE_RADIUS, "missing_fraction": MISSING_FRACTION,
                           "decimation": DECIMATION, "wb_per_stop": WB_PER_STOP}, "points": []}
    previous = None
    if args.update:
        if not (args.out and args.out.is_file() and args.factor):
            parser.error("--update needs --out (an existing report) and --factor")
        previous = json.loads(args.out.read_text())
    # with --update the points are written beside the report until they replace its own
    live = args.out if previous is None else args.out.with_name(args.out.stem + ".update.json")
    started = time.perf_counter()
    for point in sweep_points(levels):
        # Retinex sees only the photos: the proxy and sun points share the base's.
        retinex = point["factor"] not in ("proxy", "sun_error")
        entry = run_in_subprocess(point, folders, retinex=retinex, reference_truth=reference_truth,
                                  timeout=args.timeout)
        if not retinex:
            base = report["points"][0]
            entry["retinex"] = base.get("retinex")
            entry["retinex_from"] = "base"
        report["points"].append(entry)
        report["seconds_total"] = time.perf_counter() - started
        print(summary_line(entry), flush=True)
        _write(live, report)
    if previous is not None:  # the other factors' points from the earlier run, in sweep order
        fresh = {(e["factor"], str(e["level"])): e for e in report["points"]}
        kept = [fresh.pop((e["factor"], str(e["level"])), e) if e["factor"] in levels or e["factor"] == "base" else e
                for e in previous["points"]]
        report = {**previous, "points": kept + list(fresh.values()), "platform": report["platform"],
                  "platform_of_the_other_points": previous.get("platform"),
                  "updated": {"factors": sorted(levels), "seconds": report["seconds_total"]}}
        live.unlink(missing_ok=True)
    failures = [e for e in report["points"]
                if e["outcome"] in ("failure", "crash", "timeout", "harness_error") or e.get("nonfinite")]
    report["failures"] = [f"{e['factor']}={e['level']}: {e['outcome']}" for e in failures]
    _write(args.out, report)
    if args.out:
        print(f"wrote {args.out}")
    if args.plot:
        plot(report, args.plot)
        print(f"wrote {args.plot}")
    print(markdown_table(report))
    print(f"{len(report['points'])} points in {report['seconds_total']:.0f} s; failures: {report['failures'] or 'none'}")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
