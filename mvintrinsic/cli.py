"""Command-line interface: ``mvintrinsic <command> ...``.

Commands
--------
demo
    Decompose the embedded demo scene (rendered by ``synth``, shipped with the package): print
    its summary, L_sun and timings, write the result folder, a side-by-side PNG per view
    (estimate above, ground truth below), ground-truth previews, and the scores against gt/.
decompose SCENE OUT
    Decompose a scene folder (Steps 1-4; ``--steps 3`` stops before Step 4) and write the result
    folder of ``docs/formats.md``. ``--scheduler ADDRESS`` runs the per-view work on a dask
    cluster (``docs/distributed.md``).
info SCENE
    Load a scene folder (``docs/formats.md``), validate it and print a summary: views, cameras,
    image statistics, proxy, sun, and which ground-truth layers are present. ``--json`` prints
    the same summary as JSON.
synth RECIPE OUT
    Render a synthetic scene folder with ground truth (needs Mitsuba 3: the ``render`` extra).

Errors in the input are reported on one line naming the file or field, with exit status 2.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ._version import __version__
from .io import DEFAULT_MAX_SIZE, ResultFolderError, SceneError, demo_scene_path, load_scene
from .pipeline import PRESETS
from .scene import Scene
from .skymodel import SkyFitError
from .sun_calibration import SunCalibrationError
from .sun_position import azimuth_elevation

__all__ = ["main", "scene_summary"]

GT_LAYERS = ("reflectance", "shading", "sun_visibility", "sky_mask", "sun_shading", "env_shading")


def scene_summary(scene: Scene) -> dict[str, Any]:
    """JSON-ready summary of a loaded scene.

    Returns
    -------
    dict
        Keys ``folder``, ``views`` (count), ``image_sizes``, ``camera_models``, ``valid_fraction``,
        ``radiance`` (median and 99th percentile of valid pixels, linear), ``proxy`` (kind, counts,
        bounds in metres), ``sun`` (direction, azimuth counter-clockwise from the world reference
        axis and elevation, degrees), ``up`` and ``ground_truth`` (layers found under ``gt/``).
    """
    valid = np.concatenate([v.image[v.mask].ravel() for v in scene.views])
    azimuth, elevation = azimuth_elevation(scene.sun.direction, up=scene.up)
    proxy = scene.proxy
    gt: dict[str, Any] = {}
    if scene.source is not None and (scene.source / "gt").is_dir():
        root = scene.source / "gt"
        gt = {name: len(list((root / name).glob("*"))) for name in GT_LAYERS if (root / name).is_dir()}
        if (root / "relit").is_dir():
            gt["relit"] = sorted(p.name for p in (root / "relit").iterdir() if p.is_dir())
        gt["mesh"] = (root / "mesh.ply").is_file()
        gt["lighting"] = (root / "lighting.json").is_file()
    return {
        "folder": None if scene.source is None else str(scene.source),
        "views": len(scene.views),
        "image_sizes": dict(Counter(f"{v.shape[1]}x{v.shape[0]}" for v in scene.views)),
        "camera_models": dict(Counter(v.camera.model for v in scene.views)),
        "valid_fraction": float(np.mean([v.mask.mean() for v in scene.views])),
        "radiance": {
            "median": float(np.median(valid)) if valid.size else None,
            "p99": float(np.percentile(valid, 99)) if valid.size else None,
        },
        "proxy": {
            "kind": "mesh" if proxy.is_mesh else "point cloud",
            "vertices": int(len(proxy.vertices)),
            "triangles": int(len(proxy.triangles)) if proxy.is_mesh else 0,
            "bounds_m": proxy.bounds.round(3).tolist(),
        },
        "sun": {
            "direction": scene.sun.direction.round(6).tolist(),
            "azimuth_deg": round(azimuth, 3),
            "elevation_deg": round(elevation, 3),
        },
        "up": scene.up.tolist(),
        "ground_truth": gt,
    }


def _format_summary(s: dict[str, Any]) -> str:
    proxy, sun = s["proxy"], s["sun"]
    lines = [
        f"scene        {s['folder']}",
        f"views        {s['views']}  ({', '.join(f'{n} x {k}' for k, n in s['image_sizes'].items())})",
        f"cameras      {', '.join(f'{n} x {k}' for k, n in s['camera_models'].items())}",
        f"valid pixels {s['valid_fraction']:.1%}",
        f"radiance     median {s['radiance']['median']:.4g}, 99th percentile {s['radiance']['p99']:.4g} (linear)",
        f"proxy        {proxy['kind']}: {proxy['vertices']} vertices"
        + (f", {proxy['triangles']} triangles" if proxy["kind"] == "mesh" else ""),
        f"             bounds {proxy['bounds_m'][0]} .. {proxy['bounds_m'][1]} m",
        f"sun          {sun['direction']}  azimuth {sun['azimuth_deg']:.2f} deg, elevation {sun['elevation_deg']:.2f} deg",
        f"up           {s['up']}",
    ]
    gt = s["ground_truth"]
    if gt:
        layers = [f"{k} ({v})" for k, v in gt.items() if isinstance(v, int) and not isinstance(v, bool)]
        extras = [k for k in ("mesh", "lighting") if gt.get(k)]
        lines.append(f"ground truth {', '.join(layers + extras)}")
        if gt.get("relit"):
            lines.append(f"relit        {', '.join(gt['relit'])}")
    else:
        lines.append("ground truth none")
    return "\n".join(lines)


def _cmd_info(args: argparse.Namespace) -> int:
    scene = load_scene(args.scene, max_size=args.max_size, progress=not args.json and sys.stderr.isatty())
    summary = scene_summary(scene)
    print(json.dumps(summary, indent=1) if args.json else _format_summary(summary))
    return 0


MAX_SIZE_HELP = (f"downscale larger photos to this longer side in pixels (default {DEFAULT_MAX_SIZE}: a 12 MP "
                 "photo then decomposes within 4 GB); 'full' for full resolution")


def _tolerance_or_none(text: str) -> float | None:
    """A positive number, or ``none``."""
    if text.strip().lower() == "none":
        return None
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive number or 'none', got {text!r}") from None
    if not (np.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"expected a positive number or 'none', got {text!r}")
    return value


def _max_size(text: str) -> int | None:
    """``--max-size``: an integer (checked by load_scene, which names max_size) or 'full'."""
    if text.strip().lower() == "full":
        return None
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number of pixels or 'full', got {text!r}") from None


def _print_decomposition(result, scene: Scene) -> None:
    sun = result.lighting.sun_radiance
    sky = result.lighting.sky
    config = result.config_dict()
    steps = config.get("steps")
    if steps is not None:
        step4 = f"; Step 4: {config.get('env_refine', {}).get('method')}" if steps == 4 else ""
        print(f"steps        1-{steps} of the paper{step4} (docs/step4.md)")
    print(f"L_sun        {np.round(sun, 4).tolist()} (shading units)")
    if sky is not None:
        print(f"sky          {sky.model}, turbidity {sky.turbidity:.2f}, scale {np.round(sky.scale, 4).tolist()}")
    for name, choice in result.lighting.model.items():
        print(f"{'model ' + name:12s} {choice.choice}: {choice.evidence}")
    if result.lighting.horizon_evidence == "up":
        print("horizon      from the scene's up vector: the proxy has no clear ground plane")
    gains = result.lighting.exposure
    if gains is not None and gains.applied:
        stops = np.log2(gains.estimated.mean(axis=1))
        print(f"exposure     per-view gains compensated, {stops.min():+.2f} to {stops.max():+.2f} stops "
              "(lighting.json 'exposure')")
    step1 = sum(v for k, v in result.timings.items() if k.startswith("step1."))
    others = ", ".join(f"{k} {v:.2f}" for k, v in result.timings.items() if not k.startswith("step1."))
    print(f"seconds      step1 {step1:.2f}, {others} ({len(scene.views)} views)")


#: The demo's relit sequence: this many suns, the capture azimuth +- this many degrees.
DEMO_FRAMES, DEMO_SWEEP = 9, 30.0


def _cmd_demo(args: argparse.Namespace) -> int:
    from .io import check_result_folder, save_decomposition
    from .pipeline import decompose
    from .preview import write_decomposition_previews, write_scene_previews

    folder = demo_scene_path()
    out = args.out.resolve()
    if folder.resolve() in (out, *out.parents):
        raise ValueError(f"--out {out}: refusing to write inside the demo scene")
    check_result_folder(out / "result", scene=folder, overwrite=args.overwrite)  # before any work
    scene = load_scene(folder)
    print(_format_summary(scene_summary(scene)))
    result = decompose(scene, progress=sys.stderr.isatty())
    _print_decomposition(result, scene)
    save_decomposition(result, out / "result", scene=scene, overwrite=args.overwrite)
    compared = write_decomposition_previews(scene, result, out / "compare")
    written = write_scene_previews(folder, out / "ground_truth")
    from .evaluation import evaluate

    scores = evaluate(folder, out / "result")["mean"]
    print(f"result       {out / 'result'}/ (FORMAT.md result folder)")
    print(f"compare      {len(compared)} side-by-side PNGs in {out / 'compare'}/ (input, reflectance, shading, "
          f"visibility, shadow labels; estimate above, ground truth below)")
    print(f"previews     {len(written)} ground-truth PNGs in {out / 'ground_truth'}/")
    print(f"scores       LMSE reflectance {scores['lmse_reflectance']:.4f}, shading {scores['lmse_shading']:.4f}, "
          f"shadow BER {scores['ber']:.3f} (mean over views, vs gt/)")
    from .relight import Relighter

    azimuth, elevation = azimuth_elevation(result.lighting.sun.direction, up=scene.up)
    azimuths = azimuth + np.linspace(-DEMO_SWEEP, DEMO_SWEEP, DEMO_FRAMES)
    whites = {v.stem: float(np.percentile(v.image[np.isfinite(v.image)], 99)) for v in scene.views}
    _write_relit_sequence(Relighter(result, scene), out / "relit", azimuths, elevation, whites,
                          quiet=not sys.stderr.isatty())
    print(f"relit        {DEMO_FRAMES} suns from azimuth {azimuths[0]:.0f} to {azimuths[-1]:.0f} degrees: PNG frames "
          f"and one animated GIF per view in {out / 'relit'}/ (paper Sec. 8)")
    return 0


def _merged(base: dict, changes: dict) -> dict:
    """``base`` with ``changes`` written over it, nested mappings merged key by key."""
    out = dict(base)
    for key, value in changes.items():
        out[key] = _merged(base[key], value) if isinstance(value, dict) and isinstance(base.get(key), dict) else value
    return out


def _read_config(path: Path | None, preset: str | None = None):
    from .pipeline import Config

    base = Config() if preset is None else Config.preset(preset)
    if path is None:
        return base
    try:
        text = path.read_bytes()
    except OSError as exc:
        raise ValueError(f"--config {path}: cannot read ({exc.strerror})") from None
    try:
        if path.suffix.lower() == ".toml":
            import tomllib

            data = tomllib.loads(text.decode())
        else:
            data = json.loads(text)
    except (ValueError, UnicodeDecodeError) as exc:
        raise ValueError(f"--config {path}: not valid {'TOML' if path.suffix.lower() == '.toml' else 'JSON'} ({exc})") from None
    try:
        return Config.from_dict(data if preset is None else _merged(base.to_dict(), data))
    except ValueError as exc:
        raise ValueError(f"--config {path}: {exc}") from None


#: Seconds ``--scheduler`` waits for the dask scheduler to answer by default.
SCHEDULER_TIMEOUT = 10.0


@contextlib.contextmanager
def _scheduler(address: str | None, timeout: float):
    """A ``distributed.Client`` connected to ``address`` for the duration (None without an address).

    Errors are ``ValueError`` naming ``--scheduler`` (one line, exit status 2): dask.distributed
    not installed, a malformed address, or no scheduler answering within ``timeout`` seconds.
    """
    if address is None:
        yield None
        return
    if not timeout > 0:
        raise ValueError(f"--scheduler-timeout must be a positive number of seconds, got {timeout!r}")
    try:
        from distributed import Client
    except ImportError:
        raise ValueError("--scheduler needs dask.distributed, which is not installed: "
                         "pip install 'mvintrinsic[distributed]' (or pip install 'dask[distributed]')") from None
    try:
        client = Client(address, timeout=timeout, set_as_default=False)
    except (OSError, ValueError, TypeError) as exc:  # TimeoutError is an OSError
        reason = " ".join(str(exc).split()) or type(exc).__name__
        raise ValueError(f"--scheduler {address}: cannot connect to a dask scheduler ({reason})") from None
    with client:
        yield client


def _cmd_decompose(args: argparse.Namespace) -> int:
    from dataclasses import replace

    from .io import check_result_folder, save_decomposition
    from .pipeline import decompose

    check_result_folder(args.out, scene=args.scene, overwrite=args.overwrite)  # before any work
    config = _read_config(args.config, args.preset)
    if args.allow_missing_sun:
        config = replace(config, allow_missing_sun=True)
    if args.steps is not None:
        config = replace(config, steps=args.steps)
    with _scheduler(args.scheduler, args.scheduler_timeout) as client:  # before loading: a bad address fails fast
        scene = load_scene(args.scene, max_size=args.max_size, views=args.views or None, progress=not args.quiet)
        result = decompose(scene, config=config, progress=not args.quiet, client=client)
    folder = save_decomposition(result, args.out, scene=scene, overwrite=args.overwrite)
    if not args.quiet:
        _print_decomposition(result, scene)
    print(f"wrote {folder}: {len(result.layers)} views")
    return 0


def _cmd_complete_proxy(args: argparse.Namespace) -> int:
    import os
    import shutil
    import tempfile

    from .io import write_proxy
    from .result_folder import _PARTIAL, _swap_in
    from .stereo import StereoConfig, complete_proxy

    source, out = args.scene.resolve(), args.out.resolve()
    if out == source or source in out.parents:
        raise ValueError(f"out: {args.out} must lie outside the scene folder {args.scene} (the scene is never written)")
    if out.exists() and (not out.is_dir() or (any(out.iterdir()) and not args.overwrite)):
        raise FileExistsError(f"out: {args.out} exists and is not empty (--overwrite replaces it)")
    scene = load_scene(args.scene, max_size=args.max_size, progress=not args.quiet)
    chosen = {"colour_tolerance": args.colour_tolerance} if hasattr(args, "colour_tolerance") else {}
    config = StereoConfig(max_width=args.max_width, **chosen)
    proxy, _ = complete_proxy(scene, config=config, progress=None if args.quiet else print)
    # The new scene folder is written beside OUT and swapped in whole (result_folder._swap_in): a
    # failure at any instant leaves OUT as it was.
    out.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.{_PARTIAL}-{os.getpid()}-", dir=out.parent))
    try:
        for item in source.iterdir():
            if item.name != "proxy.ply" and not item.name.startswith("."):
                (shutil.copytree if item.is_dir() else shutil.copy2)(item, staging / item.name)
        write_proxy(staging / "proxy.ply", proxy)
        _swap_in(staging, out)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    added = len(proxy.triangles) - len(scene.proxy.triangles)
    print(f"wrote {args.out}: the scene with its proxy completed ({added} triangles added to {len(scene.proxy.triangles)})")
    return 0


def _cmd_relight(args: argparse.Namespace) -> int:
    from .io import check_result_folder, load_decomposition, write_image
    from .preview import tonemap
    from .relight import Relighter, as_sun_direction
    from .result_folder import _prepare_result_folder
    from .sun_position import azimuth_elevation

    by_time = args.time is not None
    if sum((args.azimuth is not None, args.sequence is not None, by_time)) != 1:
        raise ValueError("give one of --azimuth A, --sequence START END STEPS (azimuths in degrees) "
                         "or --time DATETIME --lat LAT --lon LON")
    if by_time and (args.lat is None or args.lon is None):
        raise ValueError("--time needs --lat and --lon (degrees, north and east positive)")
    if not by_time and (args.lat is not None or args.lon is not None or args.north is not None):
        raise ValueError("--lat, --lon and --north go with --time only")
    if not by_time and args.elevation is None:
        raise ValueError("--elevation is required with --azimuth and --sequence")
    if by_time and args.elevation is not None:
        raise ValueError("--elevation goes with --azimuth or --sequence; --time gives the sun's position itself")
    if args.sequence is not None and (args.sequence[2] < 2 or args.sequence[2] != int(args.sequence[2])):
        raise ValueError(f"--sequence STEPS must be an integer >= 2, got {args.sequence[2]:g}")
    check_result_folder(args.out, scene=args.scene, overwrite=args.overwrite)  # before any work
    scene = load_scene(args.scene, progress=not args.quiet)
    if by_time:
        sun = _sun_at_time(args, scene)
        as_sun_direction(sun, up=scene.up)  # a sun below the horizon is refused before anything is written
        args.azimuth, args.elevation = azimuth_elevation(sun, up=scene.up)
    azimuths = [args.azimuth] if args.azimuth is not None else np.linspace(*args.sequence[:2], int(args.sequence[2]))
    for azimuth in (azimuths[0], azimuths[-1]):  # a bad sun is refused before anything is read or written
        as_sun_direction((float(azimuth), args.elevation), up=scene.up)
    with _scheduler(args.scheduler, args.scheduler_timeout) as client:
        decomposition = load_decomposition(args.result)
        out = _prepare_result_folder(args.out, overwrite=args.overwrite, scene=scene)
        relighter = Relighter(decomposition, scene, client=client)
        whites = {v.stem: float(np.percentile(v.image[np.isfinite(v.image)], 99)) for v in scene.views}
        if args.azimuth is not None:
            images = relighter.render((args.azimuth, args.elevation))
            for stem, image in images.items():
                write_image(out / f"{stem}.exr", image)
                write_image(out / f"{stem}.png", tonemap(image, white=whites[stem]), dtype="uint8")
            print(f"wrote {out}: {len(images)} views relit at azimuth {args.azimuth:g}, elevation {args.elevation:g}")
            return 0
        _write_relit_sequence(relighter, out, azimuths, args.elevation, whites, quiet=args.quiet)
    print(f"wrote {out}: {len(azimuths)} frames per view (azimuth {azimuths[0]:g} to {azimuths[-1]:g}, "
          f"elevation {args.elevation:g}), one animated GIF per view")
    return 0


def _sun_at_time(args: argparse.Namespace, scene) -> np.ndarray:
    """The direction toward the sun at ``--time`` and ``--lat``/``--lon`` (NREL SPA through pvlib).

    North is ``--north`` or, when the scene's ``scene.json`` gives its sun as ``sun_time``, that
    entry's ``north``; the scene's own frame says nothing about geography otherwise.
    """
    import datetime as dt

    from .io import read_scene_json
    from .sun_position import sun_from_time

    try:
        when = dt.datetime.fromisoformat(args.time)
    except ValueError:
        raise ValueError(f"--time must be an ISO 8601 date and time, e.g. 2024-06-21T15:30+02:00, got {args.time!r}") from None
    if when.tzinfo is None:
        raise ValueError(f"--time must carry its UTC offset, e.g. 2024-06-21T15:30+02:00, got {args.time!r}")
    north = args.north
    if north is None:
        settings = read_scene_json(args.scene / "scene.json")
        if settings["sun_form"] != "sun_time":
            raise ValueError(f"--north X,Y,Z is needed: {args.scene / 'scene.json'} does not say where north is "
                             "(it gives no sun_time)")
        north = settings["sun_time"]["north"]
    return sun_from_time(when, args.lat, args.lon, north=np.asarray(north, dtype=np.float64), up=scene.up).direction


def _parse_vector(text: str) -> tuple[float, float, float]:
    try:
        x, y, z = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--north must be X,Y,Z (a world direction), got {text!r}") from None
    return x, y, z


def _write_relit_sequence(relighter, out: Path, azimuths, elevation: float, whites: dict[str, float], *,
                          quiet: bool) -> None:
    """PNG frames ``out/frames/<stem>/frame_###.png`` and an animated ``out/<stem>.gif`` per view."""
    from PIL import Image
    from tqdm.auto import tqdm

    from .io import _atomic_write, write_image
    from .preview import tonemap

    frames: dict[str, list[np.ndarray]] = {stem: [] for stem in whites}
    for k, azimuth in enumerate(tqdm(azimuths, desc="relight", unit="sun", disable=quiet)):
        for stem, image in relighter.render((float(azimuth), elevation)).items():
            frame = tonemap(image, white=whites[stem])
            write_image(out / "frames" / stem / f"frame_{k:03d}.png", frame, dtype="uint8")
            frames[stem].append(frame)
    for stem, sequence in frames.items():
        pictures = [Image.fromarray(f) for f in sequence]
        _atomic_write(out / f"{stem}.gif", lambda tmp, pictures=pictures: pictures[0].save(
            tmp, format="GIF", save_all=True, append_images=pictures[1:], duration=100, loop=0))


def _parse_size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--size must look like 320x240, got {text!r}") from None
    return w, h


def _parse_sun(text: str) -> tuple[float, float]:
    try:
        az, el = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--sun must be AZIMUTH,ELEVATION in degrees, got {text!r}") from None
    return az, el


def _parse_knob(text: str, current: object) -> object:
    """A --degrade value typed like the knob's default (None for 'none')."""
    if text.lower() == "none":
        return None
    if isinstance(current, bool):
        return text.lower() in ("1", "true", "yes")
    if isinstance(current, int):
        return int(text)
    return float(text)


def _cmd_synth(args: argparse.Namespace) -> int:
    from dataclasses import fields

    from .synth.dataset import DEFAULT_RELIT, SynthConfig, synthesize, with_overrides

    if args.relit is None:
        relit = DEFAULT_RELIT
    else:
        relit = tuple(t for t in args.relit.split(",") if t) if args.relit != "none" else ()
    config = SynthConfig(n_views=args.views, width=args.size[0], height=args.size[1], seed=args.seed,
                         gloss=args.gloss, hfov_deg=args.hfov, relit=relit, occluders=not args.no_occluders)
    if args.sun is not None:
        config = with_overrides(config, sun_azimuth_deg=args.sun[0], sun_elevation_deg=args.sun[1])
    changes = {"render_spp": args.spp, "render_sun": not args.overcast, "render_turbidity": args.turbidity,
               "render_sky": args.sky, "render_aerosol_scale": args.aerosol}
    proxy_fields = {f.name: f.type for f in fields(config.proxy)}
    for item in args.degrade:
        key, _, value = item.partition("=")
        if key not in proxy_fields:
            raise ValueError(f"--degrade {item!r}: unknown knob {key!r}; knobs are {sorted(proxy_fields)}")
        changes[f"proxy_{key}"] = _parse_knob(value, getattr(config.proxy, key))
    config = with_overrides(config, **changes)
    info = synthesize(args.recipe, args.out, config=config, overwrite=args.overwrite, progress=not args.quiet)
    per = info["seconds_per_render"]
    print(f"wrote {args.out}: {info['views']} views {info['width']}x{info['height']}, "
          f"sun azimuth {info['sun_azimuth_deg']:.1f} deg, elevation {info['sun_elevation_deg']:.1f} deg")
    print("seconds per render: " + ", ".join(f"{k} {v:.1f}" for k, v in per.items() if v is not None)
          + f"; total {info['seconds_total']:.0f} s")
    q = info["proxy"]
    foliage = "no foliage" if q["foliage_retention"] is None else f"foliage retention {q['foliage_retention']:.1%}"
    print(f"proxy: {q['vertices']} vertices, {q['within_10cm']:.1%} within 10 cm of the exact mesh, {foliage}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``mvintrinsic`` command."""
    parser = argparse.ArgumentParser(
        prog="mvintrinsic",
        description="Multi-view intrinsic images of outdoor scenes and relighting (Duchene et al. 2015).",
    )
    parser.add_argument("--version", action="version", version=f"mvintrinsic {__version__}")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    info = commands.add_parser("info", help="validate a scene folder and summarise it")
    info.add_argument("scene", type=Path, help="scene folder (images/, sparse/, proxy.ply, scene.json)")
    info.add_argument("--max-size", type=_max_size, default=DEFAULT_MAX_SIZE, help=MAX_SIZE_HELP)
    info.add_argument("--json", action="store_true", help="print the summary as JSON")
    info.set_defaults(run=_cmd_info)

    demo = commands.add_parser("demo", help="decompose the embedded demo scene and score it against its ground truth")
    demo.add_argument("--out", type=Path, default=Path("mvintrinsic-demo"),
                      help="output folder: result/, compare/ and ground_truth/ (default mvintrinsic-demo)")
    demo.add_argument("--overwrite", action="store_true", help="write into an existing non-empty OUT/result")
    demo.set_defaults(run=_cmd_demo)

    dec = commands.add_parser("decompose", help="decompose a scene folder into a result folder")
    dec.add_argument("scene", type=Path, help="scene folder (images/, sparse/, proxy.ply, scene.json)")
    dec.add_argument("out", type=Path, help="result folder to write (absent, empty, or a previous result)")
    dec.add_argument("--config", type=Path, default=None,
                     help="JSON or TOML file with (part of) the configuration, e.g. {\"sun\": {\"walk\": 20}}")
    dec.add_argument("--preset", choices=PRESETS, default=None,
                     help="speed against accuracy (Config.preset, docs/presets.md); --config changes apply on top")
    dec.add_argument("--max-size", type=_max_size, default=DEFAULT_MAX_SIZE, help=MAX_SIZE_HELP)
    dec.add_argument("--views", nargs="+", default=None, metavar="STEM", help="decompose only these views")
    dec.add_argument("--steps", type=int, choices=(2, 3, 4), default=None,
                     help="last step of the paper to run (default 4; overrides --config)")
    dec.add_argument("--allow-missing-sun", action="store_true",
                     help="if no light/shadow pair is found, use L_sun = 0 instead of failing")
    dec.add_argument("--overwrite", action="store_true", help="write into an existing non-empty OUT")
    dec.add_argument("--quiet", action="store_true", help="no progress bars or summary")
    dec.add_argument("--scheduler", default=None, metavar="ADDRESS",
                     help="run the per-view work (Steps 2-4) as one task per view on the dask cluster whose "
                          "scheduler is at ADDRESS, e.g. tcp://10.0.0.5:8786 (needs dask.distributed; "
                          "docs/distributed.md)")
    dec.add_argument("--scheduler-timeout", type=float, default=SCHEDULER_TIMEOUT, metavar="SECONDS",
                     help=f"seconds to wait for the scheduler to answer (default {SCHEDULER_TIMEOUT:g})")
    dec.set_defaults(run=_cmd_decompose)

    synth = commands.add_parser("synth", help="render a synthetic scene with ground truth (needs mitsuba)")
    synth.add_argument("recipe", help="scene recipe (courtyard, street)")
    synth.add_argument("out", type=Path, help="output scene folder (absent or empty)")
    synth.add_argument("--views", type=int, default=8, help="number of views (default 8)")
    synth.add_argument("--size", type=_parse_size, default=(320, 240), help="WIDTHxHEIGHT (default 320x240)")
    synth.add_argument("--spp", type=int, default=64, help="samples per pixel (default 64)")
    synth.add_argument("--seed", type=int, default=0, help="seed of the recipe, sun, sampler and proxy")
    synth.add_argument("--sun", type=_parse_sun, default=None, help="AZIMUTH,ELEVATION in degrees, e.g. --sun=-30,40 (default: drawn from the seed)")
    synth.add_argument("--hfov", type=float, default=60.0, help="horizontal field of view, degrees")
    synth.add_argument("--relit", default=None,
                       help="comma-separated relit tags like az+15,el+10, or 'none' "
                            "(default az+15,az-15,az+30,az-30,el+10: synth.dataset.DEFAULT_RELIT)")
    synth.add_argument("--degrade", action="append", default=[], metavar="KNOB=VALUE",
                       help="proxy degradation, e.g. depth_noise=0.02 (repeatable)")
    synth.add_argument("--turbidity", type=float, default=3.0, help="sky turbidity (default 3; --sky hosek-wilkie)")
    synth.add_argument("--sky", choices=("hosek-wilkie", "simulated"), default="hosek-wilkie",
                       help="Mitsuba's analytic sunsky (default) or a numerical clear-sky simulation "
                            "(Rayleigh and Mie, single and multiple scattering: synth.atmosphere)")
    synth.add_argument("--aerosol", type=float, default=20.0,
                       help="--sky simulated: aerosol density multiplier (default 20: optical depth ~0.11)")
    synth.add_argument("--overcast", action="store_true", help="sun off (sky only)")
    synth.add_argument("--gloss", action="store_true", help="mildly glossy materials (stress test)")
    synth.add_argument("--no-occluders", action="store_true",
                       help="ground and plain box buildings only: no cast shadow in view for a sun in front "
                            "of the facades (synth.recipes.build_scene(occluders=False))")
    synth.add_argument("--overwrite", action="store_true", help="replace a non-empty OUT")
    synth.add_argument("--quiet", action="store_true", help="no progress bar")
    synth.set_defaults(run=_cmd_synth)

    comp = commands.add_parser("complete-proxy",
                               help="copy a scene folder with its proxy completed by PatchMatch stereo (beyond the paper)")
    comp.add_argument("scene", type=Path, help="scene folder (images/, sparse/, proxy.ply, scene.json); not written")
    comp.add_argument("out", type=Path, help="new scene folder: the scene's files and the completed proxy.ply")
    comp.add_argument("--max-size", type=_max_size, default=DEFAULT_MAX_SIZE, help=MAX_SIZE_HELP)
    comp.add_argument("--max-width", type=int, default=640,
                      help="views wider than this are matched at this width (default 640; StereoConfig.max_width)")
    comp.add_argument("--colour-tolerance", type=_tolerance_or_none, default=argparse.SUPPRESS,
                      help="a completed pixel's colour must be seen by another view within this log radiance, "
                           "or 'none' (default 0.15; StereoConfig.colour_tolerance)")
    comp.add_argument("--overwrite", action="store_true", help="replace a non-empty OUT")
    comp.add_argument("--quiet", action="store_true", help="no progress")
    comp.set_defaults(run=_cmd_complete_proxy)

    rel = commands.add_parser("relight", help="relight a decomposed scene under a new sun (paper Sec. 8)")
    rel.add_argument("scene", type=Path, help="scene folder the result was decomposed from")
    rel.add_argument("result", type=Path, help="result folder written by `mvintrinsic decompose`")
    rel.add_argument("out", type=Path, help="output folder (absent, empty, or a previous output)")
    rel.add_argument("--azimuth", type=float, default=None,
                     help="sun azimuth in degrees, in the scene's horizontal frame (docs/conventions.md)")
    rel.add_argument("--elevation", type=float, default=None,
                     help="sun elevation in degrees (> 0); with --azimuth or --sequence")
    rel.add_argument("--sequence", type=float, nargs=3, default=None, metavar=("START", "END", "STEPS"),
                     help="a sequence of STEPS suns from azimuth START to END: PNG frames and a GIF per view")
    rel.add_argument("--time", default=None, metavar="DATETIME",
                     help="the sun at this ISO 8601 date and time with UTC offset, e.g. 2024-06-21T15:30+02:00 "
                          "(with --lat, --lon; solar position by NREL SPA, pvlib)")
    rel.add_argument("--lat", type=float, default=None, help="latitude in degrees, north positive (with --time)")
    rel.add_argument("--lon", type=float, default=None, help="longitude in degrees, east positive (with --time)")
    rel.add_argument("--north", type=_parse_vector, default=None, metavar="X,Y,Z",
                     help="world direction of geographic north (with --time; default: scene.json's sun_time.north)")
    rel.add_argument("--overwrite", action="store_true", help="write into an existing non-empty OUT")
    rel.add_argument("--quiet", action="store_true", help="no progress bars")
    rel.add_argument("--scheduler", default=None, metavar="ADDRESS",
                     help="render each new sun as one task per view on the dask cluster whose "
                          "scheduler is at ADDRESS, e.g. tcp://10.0.0.5:8786 (needs dask.distributed; "
                          "docs/distributed.md)")
    rel.add_argument("--scheduler-timeout", type=float, default=SCHEDULER_TIMEOUT, metavar="SECONDS",
                     help=f"seconds to wait for the scheduler to answer (default {SCHEDULER_TIMEOUT:g})")
    rel.set_defaults(run=_cmd_relight)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``mvintrinsic`` console script; returns the exit status."""
    args = build_parser().parse_args(argv)
    try:
        return args.run(args)
    except (SceneError, ResultFolderError, SunCalibrationError, SkyFitError, ValueError, FileExistsError,
            ImportError) as exc:
        print(f"mvintrinsic {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # a result being written is left as it was (io.save_decomposition)
        print(f"mvintrinsic {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
