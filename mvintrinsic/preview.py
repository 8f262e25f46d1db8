"""Previews: tonemapped 8-bit PNGs of linear images and ground-truth layers (edge layer)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .io import import_colour, read_image, write_image

__all__ = ["tonemap", "write_scene_previews"]


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
