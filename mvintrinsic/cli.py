"""Command-line interface: ``mvintrinsic <command> ...``.

Commands
--------
info SCENE
    Load a scene folder (``docs/formats.md``), validate it and print a summary: views, cameras,
    image statistics, proxy, sun, and which ground-truth layers are present. ``--json`` prints
    the same summary as JSON.

Errors in the input are reported on one line naming the file or field, with exit status 2.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ._version import __version__
from .io import ResultFolderError, SceneError, load_scene
from .scene import Scene
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
    info.add_argument("--max-size", type=int, default=None, help="downscale images to this longer side")
    info.add_argument("--json", action="store_true", help="print the summary as JSON")
    info.set_defaults(run=_cmd_info)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``mvintrinsic`` console script; returns the exit status."""
    args = build_parser().parse_args(argv)
    try:
        return args.run(args)
    except (SceneError, ResultFolderError, ValueError) as exc:
        print(f"mvintrinsic {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
