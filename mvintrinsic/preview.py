"""Previews: tonemapped 8-bit PNGs of linear images, ground-truth layers and decompositions (edge layer)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .files import import_colour, read_image, write_image
from .results import Decomposition, IntrinsicLayers
from .scene import Scene

__all__ = ["side_by_side", "tonemap", "write_decomposition_previews", "write_scene_previews"]


def tonemap(image: np.ndarray, *, white: float | None = None, percentile: float = 99.0) -> np.ndarray:
    """Linear RGB to displayable 8-bit sRGB.

    Parameters
    ----------
    image : (H, W, 3) or (H, W) float array
        Linear values (non-finite values are shown black).
    white : float, optional
        Linear value mapped to white. Default: the ``percentile`` of the finite values.
    percentile : float, optional
        Percentile used when ``white`` is not given.

    Returns
    -------
    (H, W, 3) or (H, W) uint8
        sRGB-encoded (IEC 61966-2-1, colour-science) after scaling by ``1 / white`` and clipping.
    """
    image = np.asarray(image, dtype=np.float64)
    finite = np.isfinite(image)
    if white is None:
        white = float(np.percentile(image[finite], percentile)) if finite.any() else 1.0
    scaled = np.clip(np.where(finite, image, 0.0) / max(white, 1e-12), 0.0, 1.0)
    encoded = import_colour().cctf_encoding(scaled, function="sRGB")
    return np.round(np.asarray(encoded) * 255).astype(np.uint8)


def write_scene_previews(scene_folder: os.PathLike | str, out: os.PathLike | str) -> list[Path]:
    """Write PNG previews of a scene's images and of its ground-truth layers.

    Images and shading layers share one exposure per view (the 99th percentile of the image),
    so a shadow looks as dark in ``sun_shading`` as in the photo; reflectance is shown with
    white = 1. Binary masks are copied as they are.

    Returns
    -------
    list of pathlib.Path
        The files written, under ``out/<layer>/<stem>.png``.
    """
    scene_folder, out = Path(scene_folder), Path(out)
    written = []
    for file in sorted((scene_folder / "images").iterdir()):
        stem = file.stem
        image, _ = read_image(file)
        white = float(np.percentile(image, 99))
        layers = {"image": (image, white)}
        gt = scene_folder / "gt"
        shading_white = None
        if (gt / "shading" / f"{stem}.exr").is_file():
            shading, _ = read_image(gt / "shading" / f"{stem}.exr")
            shading_white = float(np.percentile(shading, 99))
            layers["shading"] = (shading, shading_white)
        for name, exposure in (("reflectance", 1.0), ("sun_shading", shading_white), ("env_shading", shading_white)):
            path = gt / name / f"{stem}.exr"
            if path.is_file():
                layers[name] = (read_image(path)[0], exposure)
        for name, (values, exposure) in layers.items():
            written.append(write_image(out / name / f"{stem}.png", tonemap(values, white=exposure), dtype="uint8"))
        for name in ("sun_visibility", "sky_mask"):
            path = gt / name / f"{stem}.png"
            if path.is_file():
                mask = read_image(path)[0][..., 0] > 0.5
                written.append(write_image(out / name / f"{stem}.png", np.where(mask, 255, 0), dtype="uint8"))
    return written


def _caption(tile: np.ndarray, text: str) -> np.ndarray:
    """Write ``text`` in the top-left corner of an 8-bit RGB tile (white on a dark band)."""
    import cv2

    tile = np.ascontiguousarray(tile)
    scale = max(0.35, tile.shape[0] / 500)
    height = int(22 * scale) + 4
    tile[:height] = (tile[:height] * 0.4).astype(np.uint8)
    cv2.putText(tile, text, (4, height - 6), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1, cv2.LINE_AA)
    return tile


def side_by_side(image: np.ndarray, layers: IntrinsicLayers, *, truth: dict[str, np.ndarray] | None = None
                 ) -> np.ndarray:
    """One preview of a view's decomposition: input | reflectance | shading | sun visibility | labels.

    The image is shown at its 99th percentile, both shading rows at the 99th percentile of the
    ground-truth shading (of the estimate without ground truth), reflectance with white = 1,
    visibility and the shadow labels (0 shadow, 128 undecided, 255 lit) in grey. With ``truth`` (keys ``reflectance``, ``shading``,
    ``sun_visibility``; linear arrays) a second row shows the ground truth the same way.

    Returns
    -------
    (H or 2H, 5W, 3) uint8
    """
    image = np.asarray(image, dtype=np.float64)
    white = float(np.percentile(image[np.isfinite(image)], 99)) if np.isfinite(image).any() else 1.0
    reference = layers.shading if truth is None else np.asarray(truth["shading"])
    shading_white = float(np.percentile(reference[np.isfinite(reference)], 99)) if reference.size else 1.0

    def grey(values):
        return np.repeat(np.clip(np.round(values), 0, 255).astype(np.uint8)[..., None], 3, axis=2)

    def row(reflectance, shading, visibility, labels, label):
        return np.concatenate([
            _caption(tonemap(image, white=white), "input" if label == "estimate" else "ground truth"),
            _caption(tonemap(reflectance, white=1.0), f"reflectance ({label})"),
            _caption(tonemap(shading, white=shading_white), f"shading ({label})"),
            _caption(grey(np.clip(visibility, 0, 1) * 255), f"sun visibility ({label})"),
            _caption(grey(labels), f"shadow labels ({label})"),
        ], axis=1)

    rows = [row(layers.reflectance, layers.shading, layers.visibility, layers.shadow_labels, "estimate")]
    if truth is not None:
        binary = np.where(np.asarray(truth["sun_visibility"]) > 0.5, 255.0, 0.0)
        rows.append(row(truth["reflectance"], truth["shading"], truth["sun_visibility"], binary, "truth"))
    return np.concatenate(rows, axis=0)


def write_decomposition_previews(scene: Scene, result: Decomposition, out: os.PathLike | str) -> list[Path]:
    """Write :func:`side_by_side` PNGs of every view to ``out/<stem>.png``.

    When the scene folder has ground truth (``gt/reflectance``, ``gt/shading``,
    ``gt/sun_visibility``) for a view, its preview gets the ground-truth row.
    """
    out = Path(out)
    written = []
    gt = None if scene.source is None else Path(scene.source) / "gt"
    for view in scene.views:
        if view.stem not in result.layers:
            continue
        truth = None
        if gt is not None and all((gt / n / f"{view.stem}.{e}").is_file() for n, e in
                                  (("reflectance", "exr"), ("shading", "exr"), ("sun_visibility", "png"))):
            truth = {n: read_image(gt / n / f"{view.stem}.exr")[0] for n in ("reflectance", "shading")}
            truth["sun_visibility"] = read_image(gt / "sun_visibility" / f"{view.stem}.png")[0][..., 0]
            if truth["reflectance"].shape[:2] != view.shape:
                truth = None
        tile = side_by_side(view.image, result.layers[view.stem], truth=truth)
        written.append(write_image(out / f"{view.stem}.png", tile, dtype="uint8"))
    return written
