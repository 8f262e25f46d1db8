"""Image files and atomic writes (the edge: files <-> arrays).

:func:`read_image` / :func:`write_image` read and write single images through OpenImageIO
(linear float, or sRGB-encoded 8/16-bit with the EXIF orientation applied on request);
:func:`write_json` and every writer of the package go through one atomic write (a temporary
file beside the target, renamed over it), so a reader never sees half a file. A malformed
image raises :class:`~mvintrinsic.errors.SceneError` naming the file.
"""

from __future__ import annotations

import contextlib
import functools
import json
import os
import sys
import tempfile
import warnings
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from .errors import SceneError

__all__ = ["exif_orient", "import_colour", "read_image", "read_image_for_size", "write_image", "write_json"]


# ---------------------------------------------------------------------------------------------
# images
# ---------------------------------------------------------------------------------------------
def import_colour():
    """Import colour-science without its warning about the optional matplotlib, and without its stubs.

    colour-science warns on import when its plotting dependency is absent; mvintrinsic only uses
    its transfer functions. It also puts ``unittest.mock.MagicMock`` objects into ``sys.modules``
    under ``matplotlib``, ``matplotlib.pyplot``, ``cycler``, ``mpl_toolkits`` and their kin, so that
    a later ``import matplotlib`` anywhere in the process succeeds and every plot silently draws
    nothing (``fig, ax = plt.subplots()`` then fails far from the cause). Those entries are put
    back as they were before the import: ``import matplotlib`` raises ``ImportError`` again where
    matplotlib is absent. colour's own plotting module keeps its references; mvintrinsic never
    calls it.
    """
    if "colour" in sys.modules:  # imported already: its stand-ins were dealt with then, or are the importer's
        import colour  # (another thread's import in progress: this waits for it)

        return colour
    before = dict(sys.modules)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*Matplotlib.*related API features are not available")
        import colour
    for name, module in list(sys.modules.items()):
        if type(module).__module__ == "unittest.mock" and before.get(name) is not module:
            if name in before:
                sys.modules[name] = before[name]
            else:
                sys.modules.pop(name, None)  # another thread's call may have put it back already
    return colour


@functools.lru_cache(maxsize=2)
def _srgb_lut(levels: int) -> np.ndarray:
    """Linear value of every code of an sRGB-encoded integer image, (levels,) float32."""
    colour = import_colour()
    code = np.arange(levels, dtype=np.float64) / (levels - 1)
    lut = np.asarray(colour.cctf_decoding(code, function="sRGB"), dtype=np.float32)
    lut.flags.writeable = False
    return lut


def _first_line(message: str) -> str:
    """The first non-empty line of a library's error message (one-line errors, docs/formats.md)."""
    return next((line.strip() for line in message.splitlines() if line.strip()), "")


_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _check_png(path: Path) -> None:
    """Refuse a PNG cut before its IEND chunk, before libpng reads it (it prints on stderr).

    Walks the chunk headers (length, type) without reading their data.
    """
    size = path.stat().st_size
    with open(path, "rb") as handle:
        if handle.read(8) != _PNG_SIGNATURE:
            return  # not a PNG: OpenImageIO names what it is
        offset = 8
        while True:
            header = handle.read(8)
            if len(header) < 8:
                raise SceneError(path, f"truncated PNG: the file ends at byte {size} before its IEND chunk")
            length, kind = int.from_bytes(header[:4], "big"), header[4:]
            offset += 12 + length
            if offset > size:
                raise SceneError(path, f"truncated PNG: its {kind.decode('latin-1')!r} chunk needs {offset} bytes, "
                                 f"the file holds {size}")
            if kind == b"IEND":
                return
            handle.seek(offset)


def _read_stored(path: Path, missing: str) -> tuple[np.ndarray, int]:
    """Pixels of an image file as stored: (H, W, C) uint8, uint16 or float32 (any other type is
    read as float32), and the file's EXIF orientation (1-8, 1 when absent or invalid). Raises
    SceneError naming the file when it is missing, unreadable or cut."""
    import OpenImageIO as oiio

    if not path.is_file():
        raise SceneError(path, missing)
    if path.suffix.lower() == ".png":
        _check_png(path)
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise SceneError(path, f"unreadable image ({_first_line(oiio.geterror()) or 'unknown format'})")
    try:
        spec = inp.spec()
        fmt = {oiio.UINT8: "uint8", oiio.UINT16: "uint16"}.get(spec.format.basetype, "float")
        data = inp.read_image(0, 0, 0, spec.nchannels, fmt)
        if data is None or inp.has_error:
            raise SceneError(path, f"unreadable or truncated image ({_first_line(inp.geterror())})")
        orientation = spec.get_int_attribute("Orientation", 1)
    finally:
        inp.close()
    return np.asarray(data).reshape(spec.height, spec.width, spec.nchannels), (orientation if 1 <= orientation <= 8 else 1)


def exif_orient(image: np.ndarray, orientation: int) -> np.ndarray:
    """The image as displayed: stored pixels ``(H, W, ...)`` turned by an EXIF orientation 1-8.

    Orientations 5-8 swap the axes (a photo taken in portrait). The result is a view of
    ``image`` (no copy).
    """
    if orientation not in range(1, 9):
        raise ValueError(f"orientation must be an EXIF orientation 1-8, got {orientation!r}")
    swap = (1, 0, *range(2, image.ndim))
    return {
        1: lambda a: a,
        2: lambda a: a[:, ::-1],
        3: lambda a: a[::-1, ::-1],
        4: lambda a: a[::-1],
        5: lambda a: a.transpose(swap),
        6: lambda a: a[::-1].transpose(swap),
        7: lambda a: a[::-1, ::-1].transpose(swap),
        8: lambda a: a[:, ::-1].transpose(swap),
    }[orientation](image)


def read_image(path: os.PathLike | str, *, orient: bool = False) -> tuple[np.ndarray, float | None]:
    """Read an image file as linear RGB.

    Parameters
    ----------
    path : path-like
        EXR, TIFF, PNG or JPEG file.
    orient : bool, optional
        Turn the pixels by the file's EXIF orientation (as image viewers show it). Default: the
        pixels as stored, the convention of COLMAP, which ignores the tag.

    Returns
    -------
    image : (H, W, 3) float32
        Linear RGB. 8-bit files are sRGB-decoded (colour-science's sRGB EOTF); 16-bit integer and
        float files are taken as linear (16-bit scaled to [0, 1]). Grey images are replicated to
        three channels, an alpha channel is dropped.
    saturation : float or None
        The linear value at which an integer file clips (1.0), or None for float files.

    Raises
    ------
    SceneError
        If the file is missing, unreadable, truncated or has an unsupported channel count.
    """
    image, saturation, orientation = _read_linear(Path(path))
    return (np.ascontiguousarray(exif_orient(image, orientation)) if orient else image), saturation


def _read_linear(path: Path) -> tuple[np.ndarray, float | None, int]:
    """:func:`read_image`'s pixels as stored, its saturation, and the file's EXIF orientation."""
    data, orientation = _read_stored(path, "image file not found")
    channels = data.shape[2]
    if channels not in (1, 2, 3, 4):
        raise SceneError(path, f"unsupported image with {channels} channels (need 1-4)")
    integer = data.dtype in (np.uint8, np.uint16)
    if data.dtype == np.uint8:
        data = _srgb_lut(256)[data]
    elif data.dtype == np.uint16:
        data = data.astype(np.float32) / np.float32(65535.0)
    data = data.astype(np.float32, copy=False)
    if channels <= 2:
        data = np.repeat(data[..., :1], 3, axis=2)
    else:
        data = data[..., :3]
    return np.ascontiguousarray(data), (1.0 if integer else None), orientation


def read_image_for_size(path: os.PathLike | str, *, width: int, height: int) -> tuple[np.ndarray, float | None]:
    """:func:`read_image` as the scene's camera expects it: the pixels as stored (COLMAP's
    convention, which ignores the EXIF orientation), unless only the orientation makes them
    ``width`` x ``height`` (a model made from the photos as displayed)."""
    image, saturation, orientation = _read_linear(Path(path))
    h, w = image.shape[:2]
    if (w, h) == (height, width) and w != h and orientation >= 5:  # only 5-8 turn by 90 degrees
        return np.ascontiguousarray(exif_orient(image, orientation)), saturation
    return image, saturation


def _umask() -> int:
    """The process's file-creation mask (read by setting and restoring it)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _atomic_write(path: Path, write: Callable[[Path], None]) -> None:
    """Write through ``write(tmp)`` to a temporary sibling of ``path``, then rename it over ``path``.

    The temporary file keeps ``path``'s extension (OpenImageIO chooses the format from it) and is
    removed when anything, including KeyboardInterrupt, interrupts the write; the file gets the
    permissions the user's umask gives new files.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}", dir=path.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        write(tmp)
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp's 0600 would hide results from the user's group
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise


def write_image(path: os.PathLike | str, image: np.ndarray, *, dtype: str = "float",
                attributes: Mapping[str, int | float | str] | None = None) -> Path:
    """Write an image atomically with OpenImageIO (format from the extension).

    Parameters
    ----------
    path : path-like
        Destination; ``.exr`` for linear float data, ``.png`` for 8-bit codes.
    image : (H, W) or (H, W, C) array
        Pixel values, written as they are (no colour encoding).
    dtype : {"float", "half", "uint8", "uint16"}, optional
        Storage type in the file.
    attributes : mapping, optional
        OpenImageIO metadata for the file, e.g. ``{"Compression": "jpeg:85", "Orientation": 6}``
        (EXR files are zip-compressed unless it says otherwise).

    Returns
    -------
    pathlib.Path
    """
    import OpenImageIO as oiio

    if dtype not in ("float", "half", "uint8", "uint16"):
        raise ValueError(f"dtype must be one of 'float', 'half', 'uint8', 'uint16', got {dtype!r}")
    array = np.asarray(image)
    if array.ndim == 2:
        array = array[..., None]
    if array.ndim != 3 or array.shape[2] not in (1, 3, 4):
        raise ValueError(f"image must have shape (H, W), (H, W, 1), (H, W, 3) or (H, W, 4), got shape {np.shape(image)}")
    np_dtype = {"float": np.float32, "half": np.float16, "uint8": np.uint8, "uint16": np.uint16}[dtype]
    array = np.ascontiguousarray(array.astype(np_dtype, copy=False))
    path = Path(path)

    def write(tmp: Path) -> None:
        out = oiio.ImageOutput.create(str(tmp))
        if out is None:
            raise OSError(f"{path}: cannot create an image writer ({oiio.geterror().strip()})")
        spec = oiio.ImageSpec(array.shape[1], array.shape[0], array.shape[2], dtype)
        if path.suffix.lower() == ".exr":
            spec.attribute("compression", "zip")
        for name, value in (attributes or {}).items():
            spec.attribute(name, value)
        ok = out.open(str(tmp), spec) and out.write_image(array)
        ok = out.close() and ok
        if not ok:
            raise OSError(f"{path}: writing failed ({out.geterror().strip()})")

    _atomic_write(path, write)
    return path


def write_json(path: os.PathLike | str, data: Any) -> Path:
    """Write ``data`` as indented JSON, atomically."""
    path = Path(path)
    text = json.dumps(data, indent=1, allow_nan=False) + "\n"
    _atomic_write(path, lambda tmp: tmp.write_text(text))
    return path
