"""A synthetic scene that imitates a real capture, made from a rendered one.

Real photo sets differ from the rendered scenes in ways that break a method tuned on renders:
every photo has its own automatic exposure and white balance, the files are 8-bit sRGB JPEGs
(quantised, compressed, clipped), some are stored in portrait with an EXIF orientation tag, and
the multi-view-stereo mesh of a facade has no dense ground but a false cap that closes it at the
roof line. :func:`imitate_capture` turns a scene folder written by
:func:`mvintrinsic.synth.dataset.synthesize` into such a capture, keeping its ground truth
consistent:

* per view ``k`` a gain ``g_k = 2^e_k * w_k`` with ``e_k`` uniform in ``[-exposure_stops,
  exposure_stops]`` and ``log w_k`` uniform in ``[-white_balance, white_balance]`` per channel,
  normalised to a geometric mean of 1 over the views (the scale an estimate can recover), and
  one global scale ``k_0`` for the whole set that maps the 99.5th percentile of the pixel values
  to 0.9 (the set's auto exposure);
* images ``k_0 g_k I_k`` clipped to [0, 1], sRGB-encoded, written as JPEG at ``jpeg_quality``;
  the view ``portrait_view`` is stored turned by 90 degrees with EXIF orientation 6, its COLMAP
  camera as displayed (so the loader must honour the tag);
* the proxy without its ground (faces whose three vertices lie within ``ground_band`` of the
  ground plane) and with a false cap: over each cluster of roof-line vertices, a fan of
  triangles over their convex hull widened by ``cap_overhang`` and raised by ``cap_rise``;
* ground truth in the photos' units: shading, sun shading, environment shading and the relit
  renders of view ``k`` multiplied by ``k_0 g_k``; ``sun_radiance`` by ``k_0``; reflectance,
  visibility and masks unchanged. ``gt/capture.json`` records the gains, ``k_0`` and the edits.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
from scipy import ndimage
from scipy.spatial import ConvexHull, QhullError

from ..environment import horizon_plane
from ..io import read_colmap, read_image, read_proxy, write_colmap_text, write_image, write_json, write_proxy
from ..preview import tonemap
from ..scene import Proxy
from ._geometry import area_weighted_normals

__all__ = ["imitate_capture"]

_SCALED = ("shading", "sun_shading", "env_shading")


def _cap(vertices: np.ndarray, up: np.ndarray, ground: float, *, overhang: float, rise: float,
         cell: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """A false roof cap: fans over the clusters of vertices near the top of the proxy.

    Returns cap vertices (M, 3) and triangles (T, 3) indexing them.
    """
    frame_x = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    frame_x /= np.linalg.norm(frame_x)
    frame_y = np.cross(up, frame_x)
    height = vertices @ up - ground
    top = height >= 0.8 * float(np.percentile(height, 99.5))
    xy = np.stack([vertices @ frame_x, vertices @ frame_y], axis=1)[top]
    if len(xy) < 3:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    lo = xy.min(axis=0) - 3 * cell  # a margin of 3 cells, so that the closing does not erode the borders
    cells = np.floor((xy - lo) / cell).astype(np.int64)
    grid = np.zeros(cells.max(axis=0) + 4, dtype=bool)
    grid[cells[:, 0], cells[:, 1]] = True
    grid = ndimage.binary_closing(grid, structure=np.ones((3, 3)), iterations=2)
    labels, n = ndimage.label(grid, structure=np.ones((3, 3)))
    point_label = labels[cells[:, 0], cells[:, 1]]
    verts, tris = [], []
    for label in range(1, n + 1):
        pts = xy[point_label == label]
        if len(pts) < 10:
            continue
        try:
            hull = pts[ConvexHull(pts).vertices]
        except QhullError:
            continue
        centre = hull.mean(axis=0)
        radial = hull - centre
        radial *= (1.0 + overhang / np.maximum(np.linalg.norm(radial, axis=1, keepdims=True), 1e-9))
        ring = centre + radial
        level = ground + float(height[top][point_label == label].max())
        base = sum(len(v) for v in verts)
        ring3 = ring[:, :1] * frame_x + ring[:, 1:] * frame_y + level * up
        apex = centre[0] * frame_x + centre[1] * frame_y + (level + rise) * up
        verts.append(np.vstack([apex[None], ring3]))
        k = len(ring)
        tris.append(np.stack([np.full(k, base), base + 1 + np.arange(k), base + 1 + (np.arange(k) + 1) % k], axis=1))
    if not verts:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    return np.vstack(verts), np.vstack(tris).astype(np.int64)


def _edit_proxy(proxy: Proxy, up: np.ndarray, *, ground_band: float | None, cap: bool, overhang: float, rise: float,
                rng: np.random.Generator) -> tuple[Proxy, dict]:
    """The proxy without its ground and with a false cap, and what was done."""
    if not proxy.is_mesh:
        raise ValueError("source proxy.ply must be a triangle mesh")
    plane = horizon_plane(proxy.vertices, up=up, rng=rng)
    ground = -float(plane.plane[3])
    vertices, triangles = proxy.vertices, proxy.triangles
    info: dict = {"ground_height": ground}
    if ground_band is not None:
        near = np.abs(plane.height_of(vertices)) <= ground_band
        keep = ~near[triangles].all(axis=1)
        info["ground_faces_removed"] = int((~keep).sum())
        triangles = triangles[keep]
        used = np.zeros(len(vertices), bool)
        used[triangles] = True
        remap = np.cumsum(used) - 1
        vertices, triangles = vertices[used], remap[triangles]
    cap_faces = 0
    if cap:
        cap_v, cap_t = _cap(vertices, up, ground, overhang=overhang, rise=rise)
        cap_faces = len(cap_t)
        triangles = np.vstack([triangles, cap_t + len(vertices)])
        vertices = np.vstack([vertices, cap_v])
    info["cap_faces_added"] = cap_faces
    normals = area_weighted_normals(vertices, triangles)
    return Proxy(vertices, normals, triangles), info


def imitate_capture(
    source: str | Path,
    out: str | Path,
    *,
    seed: int = 0,
    exposure_stops: float = 1.0,
    white_balance: float = 0.15,
    jpeg_quality: int = 85,
    portrait_view: int | None = 0,
    ground_band: float | None = 0.25,
    false_cap: bool = True,
    cap_overhang: float = 0.5,
    cap_rise: float = 0.5,
    overwrite: bool = False,
) -> dict:
    """Write an imitation of a real capture of the scene folder ``source`` (module docstring).

    Parameters
    ----------
    source : path-like
        A synthetic scene folder with ground truth (``docs/formats.md``), images linear.
    out : path-like
        The new scene folder; must not exist or be empty unless ``overwrite``.
    seed : int, optional
        Seeds the gains.
    exposure_stops : float, optional
        Per-view exposure spread, stops (1: the photos differ by up to two stops).
    white_balance : float, optional
        Per-view, per-channel white-balance spread, natural log units.
    jpeg_quality : int, optional
        JPEG quality, 1-100.
    portrait_view : int or None, optional
        Index (in name order) of the view stored turned by 90 degrees with EXIF orientation 6;
        None for none.
    ground_band : float or None, optional
        Faces within this distance of the ground plane (metres) are removed; None keeps them.
    false_cap : bool, optional
        Add the false roof cap.
    cap_overhang, cap_rise : float, optional
        How far the cap reaches beyond the roof-line vertices and how high its apex rises, metres.
    overwrite : bool, optional
        Replace a non-empty ``out``.

    Returns
    -------
    dict
        What ``gt/capture.json`` records: ``gains`` per view (geometric mean 1), ``global_scale``,
        ``jpeg_quality``, ``portrait_view`` and the proxy edits.
    """
    src, dst = Path(source), Path(out)
    if not (src / "gt" / "lighting.json").is_file():
        raise FileNotFoundError(f"{src}: not a synthetic scene folder with ground truth (no gt/lighting.json)")
    if not (1 <= int(jpeg_quality) <= 100):
        raise ValueError(f"jpeg_quality must be in 1-100, got {jpeg_quality!r}")
    if dst.resolve() == src.resolve():
        raise ValueError("out must differ from source")
    if dst.exists() and any(dst.iterdir()):
        if not overwrite:
            raise FileExistsError(f"{dst}: not empty; pass overwrite=True to replace it")
        shutil.rmtree(dst)
    gen = np.random.default_rng(seed)
    cameras = read_colmap(src / "sparse")
    names = sorted(cameras)
    stems = [Path(n).with_suffix("").as_posix() for n in names]
    settings = json.loads((src / "scene.json").read_text())
    up = np.asarray(settings.get("up", [0.0, 0.0, 1.0]), dtype=np.float64)
    up /= np.linalg.norm(up)

    log_gain = (gen.uniform(-exposure_stops, exposure_stops, len(names))[:, None] * np.log(2.0)
                + gen.uniform(-white_balance, white_balance, (len(names), 3)))
    log_gain -= log_gain.mean(axis=0)
    gains = np.exp(log_gain)
    images = [read_image(src / "images" / n)[0] for n in names]
    values = np.concatenate([(im * g.astype(np.float32)).reshape(-1, 3) for im, g in zip(images, gains, strict=True)])
    values = values[np.isfinite(values).all(axis=1)]
    scale = 0.9 / float(np.percentile(values, 99.5))

    (dst / "images").mkdir(parents=True)
    new_cameras = {}
    for k, (name, stem, image) in enumerate(zip(names, stems, images, strict=True)):
        codes = tonemap(image * np.float32(scale) * gains[k].astype(np.float32), white=1.0)  # 8-bit sRGB
        orientation = 1
        if portrait_view is not None and k == portrait_view:
            codes, orientation = np.ascontiguousarray(np.rot90(codes, 1)), 6  # stored turned; displays upright
        file = f"{stem}.jpg"
        write_image(dst / "images" / file, codes, dtype="uint8",
                    attributes={"Compression": f"jpeg:{int(jpeg_quality)}", "Orientation": orientation})
        new_cameras[file] = cameras[name]
    write_colmap_text(dst / "sparse", new_cameras)
    write_json(dst / "scene.json", settings)

    centers = np.stack([c.center for c in cameras.values()])
    proxy = read_proxy(src / "proxy.ply", camera_centers=centers)
    edited, edits = _edit_proxy(proxy, up, ground_band=ground_band, cap=false_cap, overhang=cap_overhang,
                                rise=cap_rise, rng=gen)
    write_proxy(dst / "proxy.ply", edited)

    gt_src, gt_dst = src / "gt", dst / "gt"
    shutil.copytree(gt_src, gt_dst, ignore=shutil.ignore_patterns(*_SCALED, "relit", "lighting.json"))
    for kind in _SCALED:
        (gt_dst / kind).mkdir(exist_ok=True)
        for k, stem in enumerate(stems):
            file = gt_src / kind / f"{stem}.exr"
            if file.is_file():
                gained = read_image(file)[0] * np.float32(scale) * gains[k].astype(np.float32)
                write_image(gt_dst / kind / f"{stem}.exr", gained)
    relit = gt_src / "relit"
    if relit.is_dir():
        for tag in sorted(p.name for p in relit.iterdir() if p.is_dir()):
            (gt_dst / "relit" / tag / "images").mkdir(parents=True)
            shutil.copy2(relit / tag / "scene.json", gt_dst / "relit" / tag / "scene.json")
            for k, stem in enumerate(stems):
                file = relit / tag / "images" / f"{stem}.exr"
                if file.is_file():
                    write_image(gt_dst / "relit" / tag / "images" / f"{stem}.exr",
                                read_image(file)[0] * np.float32(scale) * gains[k].astype(np.float32))
    lighting = json.loads((gt_src / "lighting.json").read_text())
    lighting["sun_radiance"] = (np.asarray(lighting["sun_radiance"]) * scale).tolist()
    write_json(gt_dst / "lighting.json", lighting)
    record = {
        "source": str(src.resolve()),
        "gains": {stem: g.tolist() for stem, g in zip(stems, gains, strict=True)},
        "global_scale": scale,
        "jpeg_quality": int(jpeg_quality),
        "portrait_view": None if portrait_view is None else stems[portrait_view],
        "exposure_stops": exposure_stops,
        "white_balance": white_balance,
        "seed": seed,
        "proxy": edits,
    }
    write_json(gt_dst / "capture.json", record)
    return record

