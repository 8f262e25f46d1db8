"""Reading scene folders and writing result folders (the edge of the package: files <-> objects).

The layouts are the public contract of ``docs/formats.md``:

* :func:`load_scene` reads ``images/``, ``sparse/`` (COLMAP text or binary, through pycolmap),
  ``proxy.ply`` (through open3d) and ``scene.json`` into a validated
  :class:`~mvintrinsic.scene.Scene`.
* :func:`save_decomposition` / :func:`load_decomposition` write and read a result folder.
  A result folder is written whole beside its place and swapped in (all or nothing), never inside
  a scene folder, and a non-empty folder that mvintrinsic did not create is only written into
  when ``overwrite=True``; :func:`check_result_folder` refuses a bad output before any work.
* :func:`read_image` / :func:`write_image` read and write single images through OpenImageIO.

Every malformed input raises :class:`SceneError` (a :class:`ValueError`) whose message starts with
the offending file (and field) and says what is wrong.
"""

from __future__ import annotations

import contextlib
import ctypes
import datetime as _dt
import errno
import functools
import json
import math
import os
import shutil
import tempfile
import warnings
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ._libusb import ensure_libusb
from .camera import CAMERA_MODELS, Camera
from .raytrace import Tracer
from .resolution import resize_image
from .results import Decomposition, IntrinsicLayers, Lighting, ModelChoice, SkyParameters, ViewGains
from .scene import Proxy, Scene, Sun, View, valid_pixels
from .sun_position import sun_from_clicks, sun_from_time

__all__ = [
    "RESULT_MARKER",
    "DEFAULT_MAX_SIZE",
    "IMAGE_EXTENSIONS",
    "ResultFolderError",
    "SceneError",
    "check_result_folder",
    "demo_scene_path",
    "load_decomposition",
    "load_scene",
    "read_colmap",
    "exif_orient",
    "read_image",
    "read_image_for_size",
    "read_proxy",
    "read_scene_json",
    "save_decomposition",
    "write_colmap_text",
    "write_image",
    "write_json",
    "write_proxy",
]


def demo_scene_path() -> Path:
    """Folder of the embedded demo scene (package data ``mvintrinsic/data/demo``).

    A complete scene folder (``docs/formats.md``) of 6 views at 240x180 with its ground truth and
    relit renders, so that ``load_scene(demo_scene_path())`` works after a plain ``pip install``.
    """
    from importlib.resources import files

    return Path(str(files("mvintrinsic") / "data" / "demo"))

#: Default longer side (pixels) to which :func:`load_scene` downscales larger photos: one 12 MP
#: view then decomposes within 4 GB (benchmarks/results/memory_12mp.json, docs/real_capture.md).
DEFAULT_MAX_SIZE = 1400

#: Image file extensions load_scene accepts (case-insensitive).
IMAGE_EXTENSIONS = (".exr", ".tif", ".tiff", ".png", ".jpg", ".jpeg")
#: File that marks a folder as created by :func:`save_decomposition`.
RESULT_MARKER = ".mvintrinsic-result"
#: Sun keys of scene.json; exactly one must be present.
SUN_FORMS = ("sun_direction", "sun_clicks", "sun_time")


class SceneError(ValueError):
    """A scene folder or one of its files is missing or malformed.

    Attributes
    ----------
    path : pathlib.Path
        The offending file or folder.
    """

    def __init__(self, path: os.PathLike | str, message: str) -> None:
        self.path = Path(path)
        super().__init__(f"{self.path}: {message}")


class ResultFolderError(ValueError):
    """A result folder cannot be written where asked (inside a scene, or a foreign folder)."""


# ---------------------------------------------------------------------------------------------
# images
# ---------------------------------------------------------------------------------------------
def import_colour():
    """Import colour-science without its warning about the optional matplotlib.

    colour-science warns on import when its plotting dependency is absent; mvintrinsic only uses
    its transfer functions.
    """
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*Matplotlib.*related API features are not available")
        import colour
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


def write_proxy(path: os.PathLike | str, proxy: Proxy) -> Path:
    """Write a proxy as a binary little-endian PLY, atomically.

    Vertices and normals are stored as float32 (8 µm resolution 100 m from the origin, far
    finer than any multi-view-stereo proxy), faces as ``uchar``-counted ``int`` lists; a point
    cloud has no face element.
    """
    path = Path(path)
    n = len(proxy.vertices)
    header = [
        "ply", "format binary_little_endian 1.0", "comment written by mvintrinsic", f"element vertex {n}",
        *(f"property float {c}" for c in ("x", "y", "z", "nx", "ny", "nz")),
    ]
    vertex_data = np.concatenate([proxy.vertices, proxy.normals], axis=1).astype("<f4").tobytes()
    face_data = b""
    if proxy.is_mesh:
        header += [f"element face {len(proxy.triangles)}", "property list uchar int vertex_indices"]
        faces = np.empty(len(proxy.triangles), dtype=[("n", "u1"), ("i", "<i4", (3,))])
        faces["n"], faces["i"] = 3, proxy.triangles
        face_data = faces.tobytes()
    blob = ("\n".join([*header, "end_header"]) + "\n").encode("ascii") + vertex_data + face_data
    _atomic_write(path, lambda tmp: tmp.write_bytes(blob))
    return path


def write_colmap_text(folder: os.PathLike | str, cameras: dict[str, Camera]) -> Path:
    """Write a COLMAP text model (one camera per image, no 3D points), atomically per file.

    Parameters
    ----------
    folder : path-like
        The ``sparse/`` folder to write ``cameras.txt``, ``images.txt`` and ``points3D.txt`` into.
    cameras : dict of str to Camera
        Posed camera of each image, keyed by image name (e.g. ``"view_000.exr"``), in order.
    """
    from scipy.spatial.transform import Rotation

    folder = Path(folder)
    cam_lines = ["# Camera list with one line of data per camera:", "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]"]
    img_lines = [
        "# Image list with two lines of data per image:",
        "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
        "#   POINTS2D[] as (X, Y, POINT3D_ID)",
    ]
    for i, (name, cam) in enumerate(cameras.items(), start=1):
        cam_lines.append(f"{i} {cam.model} {cam.width} {cam.height} " + " ".join(f"{p:.17g}" for p in cam.params))
        x, y, z, w = Rotation.from_matrix(cam.rotation).as_quat()
        qt = (w, x, y, z, *cam.translation)
        img_lines += [f"{i} " + " ".join(f"{v:.17g}" for v in qt) + f" {i} {name}", ""]
    write_text = {"cameras.txt": cam_lines, "images.txt": img_lines, "points3D.txt": ["# 3D point list (empty)"]}
    for file, lines in write_text.items():
        text = "\n".join(lines) + "\n"
        _atomic_write(folder / file, lambda tmp, text=text: tmp.write_text(text))
    return folder


# ---------------------------------------------------------------------------------------------
# COLMAP model
# ---------------------------------------------------------------------------------------------
def read_colmap(sparse: os.PathLike | str) -> dict[str, Camera]:
    """Read a COLMAP model (text or binary) with pycolmap.

    Parameters
    ----------
    sparse : path-like
        Folder holding ``cameras``, ``images`` and ``points3D`` as ``.txt`` or ``.bin``.
        A missing points3D file is treated as empty.

    Returns
    -------
    dict of str to Camera
        Posed camera of every registered image, keyed by the image name in the model.

    Raises
    ------
    SceneError
        If the folder or a model file is missing or malformed, or a camera model is not one of
        :data:`~mvintrinsic.camera.CAMERA_MODELS`.
    """
    import pycolmap

    sparse = Path(sparse)
    if not sparse.is_dir():
        raise SceneError(sparse, "COLMAP model folder not found")
    for ext in (".bin", ".txt"):
        if (sparse / f"cameras{ext}").is_file() and (sparse / f"images{ext}").is_file():
            break
    else:
        raise SceneError(sparse, "no COLMAP model: need cameras.txt + images.txt or cameras.bin + images.bin")
    cameras_file = sparse / f"cameras{ext}"
    if ext == ".txt":
        camera_ids = _check_camera_models_txt(cameras_file)
        _check_images_txt(sparse / "images.txt", camera_ids)
    with contextlib.ExitStack() as stack:
        folder = sparse
        if not (sparse / f"points3D{ext}").is_file():
            folder = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="mvintrinsic-sparse-")))
            for name in ("cameras", "images"):
                (folder / f"{name}{ext}").symlink_to((sparse / f"{name}{ext}").resolve())
            if ext == ".txt":
                (folder / "points3D.txt").write_text("")
            else:
                (folder / "points3D.bin").write_bytes(np.uint64(0).tobytes())
        try:
            reconstruction = pycolmap.Reconstruction(str(folder))
        except Exception as exc:  # pycolmap raises plain RuntimeError/ValueError on bad files
            raise SceneError(sparse, f"malformed COLMAP model ({str(exc).strip().splitlines()[-1][:200]})") from exc
    cameras: dict[str, Camera] = {}
    for image in reconstruction.images.values():
        cam = reconstruction.cameras[image.camera_id]
        model = cam.model.name
        if model not in CAMERA_MODELS:
            raise SceneError(
                cameras_file,
                f"camera {image.camera_id}: unknown or unsupported camera model {model!r} "
                f"(supported: {', '.join(CAMERA_MODELS)})",
            )
        pose = image.cam_from_world() if callable(image.cam_from_world) else image.cam_from_world
        try:
            cameras[image.name] = Camera(
                model, cam.width, cam.height, np.array(cam.params), pose.rotation.matrix(), np.array(pose.translation)
            )
        except ValueError as exc:
            raise SceneError(sparse, f"image {image.name!r}: invalid camera ({exc})") from exc
    if not cameras:
        raise SceneError(sparse / f"images{ext}", "the COLMAP model has no registered images")
    return cameras


def _check_images_txt(path: Path, camera_ids: set[str] | None = None) -> None:
    """Refuse what pycolmap would silently accept in an images.txt: a zero or non-finite pose, or an
    image given twice (the same IMAGE_ID or NAME on two pose lines); and, naming the line, what it
    would refuse vaguely: a CAMERA_ID not in ``camera_ids`` (those of cameras.txt)."""
    lines = [(number, line) for number, line in enumerate(path.read_text().splitlines(), start=1)
             if not line.lstrip().startswith("#")]
    ids: dict[str, int] = {}
    names: dict[str, int] = {}
    pose_line = True
    for number, line in lines:
        if not pose_line:  # the POINTS2D line after every pose line (may be empty)
            pose_line = True
            continue
        fields = line.split()
        if not fields:
            continue  # blank lines between images
        pose_line = False
        if len(fields) < 10:
            raise SceneError(path, f"line {number}: expected 'IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME', "
                             f"got {line.strip()!r}")
        try:
            pose = np.array([float(v) for v in fields[1:8]])
        except ValueError:
            raise SceneError(path, f"line {number}: the pose QW QX QY QZ TX TY TZ must be numbers, got "
                             f"{' '.join(fields[1:8])!r}") from None
        if not np.isfinite(pose).all():
            raise SceneError(path, f"line {number} (image {fields[9]!r}): non-finite pose {fields[1:8]}")
        if np.linalg.norm(pose[:4]) < 1e-6:
            raise SceneError(path, f"line {number} (image {fields[9]!r}): zero quaternion QW QX QY QZ, "
                             "not a rotation")
        if camera_ids is not None and fields[8] not in camera_ids:
            raise SceneError(path, f"line {number} (image {fields[9]!r}): CAMERA_ID {fields[8]} is not in cameras.txt "
                             f"(its cameras: {', '.join(sorted(camera_ids, key=lambda c: (len(c), c)))})")
        for key, seen, what in ((fields[0], ids, "IMAGE_ID"), (fields[9], names, "NAME")):
            if key in seen:
                raise SceneError(path, f"line {number}: {what} {key!r} given twice (also on line {seen[key]})")
            seen[key] = number


def _check_camera_models_txt(path: Path) -> set[str]:
    """Name what pycolmap would reject with a vaguer message in a cameras.txt: an unknown model, a
    parameter count that is not the model's, a parameter that is not a finite number. Returns the
    CAMERA_IDs."""
    import pycolmap

    known = {m for m in dir(pycolmap.CameraModelId) if m.isupper()}
    ids = set()
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        fields = line.split()
        if not fields or fields[0].startswith("#"):
            continue
        if len(fields) < 4:
            raise SceneError(path, f"line {number}: expected 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS...', got {line!r}")
        camera, model = fields[0], fields[1]
        if model not in known or model not in CAMERA_MODELS:
            raise SceneError(
                path,
                f"line {number}: unknown or unsupported camera model {model!r} (supported: {', '.join(CAMERA_MODELS)})",
            )
        names = CAMERA_MODELS[model]
        if len(fields) - 4 != len(names):
            raise SceneError(path, f"line {number} (camera {camera}): a {model} camera has {len(names)} params "
                             f"({', '.join(names)}), got {len(fields) - 4}")
        try:
            values = [float(v) for v in fields[2:]]
        except ValueError:
            raise SceneError(path, f"line {number} (camera {camera}): WIDTH HEIGHT and params must be numbers, got "
                             f"{' '.join(fields[2:])!r}") from None
        bad = [name for name, v in zip(("WIDTH", "HEIGHT", *names), values, strict=True) if not math.isfinite(v)]
        if bad:
            raise SceneError(path, f"line {number} (camera {camera}): {', '.join(bad)} must be finite numbers, got "
                             f"{' '.join(fields[2:])!r}")
        ids.add(camera)
    return ids


# ---------------------------------------------------------------------------------------------
# proxy
# ---------------------------------------------------------------------------------------------
def read_proxy(path: os.PathLike | str, *, camera_centers: np.ndarray | None = None, knn: int = 30) -> Proxy:
    """Read the reconstructed geometry with open3d.

    Parameters
    ----------
    path : path-like
        A PLY (or any format open3d reads) triangle mesh or point cloud.
    camera_centers : (C, 3) array_like, optional
        World-frame camera centres. Estimated point-cloud normals are flipped toward the nearest
        centre (they face the side that was photographed).
    knn : int, optional
        Neighbours used to estimate point-cloud normals when the file has none.

    Returns
    -------
    Proxy
        Meshes keep their triangles (unreferenced vertices dropped); vertex normals come from the
        file or, when absent, from the triangles. 8-bit vertex colours are sRGB-decoded to linear.

    Raises
    ------
    SceneError
        If the file is missing, unreadable, empty or degenerate.
    """
    ensure_libusb()
    import open3d as o3d

    path = Path(path)
    if not path.is_file():
        raise SceneError(path, "proxy file not found")
    if path.suffix.lower() == ".ply":
        _check_ply_header(path)
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        mesh = o3d.io.read_triangle_mesh(str(path), enable_post_processing=False)
        cloud = None
        if len(mesh.triangles) == 0:
            cloud = o3d.io.read_point_cloud(str(path))
    if cloud is None:
        # open3d crashes the process on a face index outside the vertex list: check first.
        faces, n_vertices = np.asarray(mesh.triangles), len(mesh.vertices)
        wrong = (faces < 0) | (faces >= n_vertices)
        if wrong.any():
            face = int(np.flatnonzero(wrong.any(axis=1))[0])
            raise SceneError(path, f"face {face} refers to vertex {int(faces[face][wrong[face]][0])}, but the file has "
                             f"{n_vertices} vertices ({int(wrong.any(axis=1).sum())} such faces): corrupt face indices")
        mesh.remove_unreferenced_vertices()
        if not mesh.has_vertex_normals():
            mesh.compute_vertex_normals()
        vertices, triangles = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
        _check_finite_vertices(vertices, path)
        normals = np.asarray(mesh.vertex_normals)
        colors = np.asarray(mesh.vertex_colors) if mesh.has_vertex_colors() else None
    else:
        triangles = None
        vertices = np.asarray(cloud.points)
        if len(vertices) == 0:
            raise SceneError(path, "the proxy is empty (no vertices could be read)")
        _check_finite_vertices(vertices, path)
        if not cloud.has_normals() and len(vertices) >= 3:
            cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=min(knn, len(vertices))))
            normals = np.asarray(cloud.normals).copy()
            if camera_centers is not None:
                normals = _orient_toward(vertices, normals, np.asarray(camera_centers, dtype=np.float64))
        else:
            normals = np.asarray(cloud.normals)
        colors = np.asarray(cloud.colors) if cloud.has_colors() else None
    if len(vertices) == 0:
        raise SceneError(path, "the proxy is empty (no vertices could be read)")
    normals = _repair_normals(vertices, normals, path)
    if colors is not None and len(colors):
        colors = _srgb_lut(256)[np.clip(np.round(colors * 255), 0, 255).astype(np.uint8)]
    else:
        colors = None
    try:
        return Proxy(vertices, normals, triangles, colors)
    except ValueError as exc:
        raise SceneError(path, str(exc)) from exc


#: Bytes of the PLY scalar types.
_PLY_SIZES = {"char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2, "int16": 2, "uint16": 2,
              "int": 4, "uint": 4, "int32": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8}


def _check_finite_vertices(vertices: np.ndarray, path: Path) -> None:
    """Refuse NaN or infinite vertex coordinates, naming the first."""
    bad = ~np.isfinite(vertices).all(axis=1)
    if bad.any():
        raise SceneError(path, f"{int(bad.sum())} vertices have NaN or infinite coordinates (the first: vertex "
                         f"{int(np.flatnonzero(bad)[0])}); every coordinate must be finite")


def _check_ply_header(path: Path) -> None:
    """Refuse a PLY whose header is malformed or claims more elements than the file can hold.

    Read before open3d allocates anything: each element needs at least its scalar properties'
    bytes (binary) or two characters per property (ASCII), and a list at least its count.
    """
    with open(path, "rb") as handle:
        head = handle.read(65536)
    if not head:
        raise SceneError(path, "empty file (0 bytes): not a PLY mesh or point cloud")
    if not head.startswith(b"ply"):
        raise SceneError(path, f"not a PLY file (it starts with {head[:16]!r}, not 'ply')")
    end = head.find(b"end_header")
    if end < 0:
        raise SceneError(path, "malformed PLY header (no 'end_header' in the first 64 kB)")
    body = path.stat().st_size - (head.find(b"\n", end) + 1)
    binary, needed, element = False, 0, None
    for raw in head[:end].decode("ascii", errors="replace").splitlines():
        fields = raw.split()
        if not fields:
            continue
        if fields[0] == "format" and len(fields) > 1:
            binary = fields[1].startswith("binary")
        elif fields[0] == "element":
            if len(fields) != 3 or not fields[2].isdigit():
                raise SceneError(path, f"malformed PLY header line {raw.strip()!r}")
            element = (fields[1], int(fields[2]))
        elif fields[0] == "property" and element is not None and len(fields) >= 2:
            # A list needs at least its count; ASCII at least a digit and a separator per value.
            scalar = fields[2] if fields[1] == "list" and len(fields) > 2 else fields[1]
            needed += element[1] * (_PLY_SIZES.get(scalar, 1) if binary else 2)
            if needed > body + 1:  # + 1: an ASCII body may lack its last newline
                raise SceneError(path, f"the header claims {element[1]} {element[0]} elements, which need at least "
                                 f"{needed} bytes, but the file holds {body} after its header (truncated or "
                                 "corrupt)")


def _repair_normals(vertices: np.ndarray, normals: np.ndarray, path: Path) -> np.ndarray:
    """Unit normals; a zero or non-finite one (a vertex of degenerate triangles only, a bad
    file entry) takes the normal of the nearest vertex that has a valid one."""
    from scipy.spatial import cKDTree

    if len(normals) != len(vertices):
        raise SceneError(path, f"{len(normals)} normals for {len(vertices)} vertices")
    normals = np.array(normals, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        lengths = np.linalg.norm(normals, axis=1)
        good = np.isfinite(lengths) & (lengths > 1e-12)
    if not good.any():
        raise SceneError(path, "the proxy is degenerate: no vertex has a valid normal")
    normals[good] /= lengths[good, None]
    if not good.all():
        _, nearest = cKDTree(vertices[good]).query(vertices[~good])
        normals[~good] = normals[good][nearest]
    return normals


def _orient_toward(points: np.ndarray, normals: np.ndarray, centers: np.ndarray) -> np.ndarray:
    from scipy.spatial import cKDTree

    _, nearest = cKDTree(centers).query(points)
    flip = np.einsum("ij,ij->i", normals, centers[nearest] - points) < 0
    normals[flip] *= -1
    return normals


def _check_proxy_visible(proxy: Proxy, cameras: Iterable[Camera], path: Path) -> None:
    """Raise unless some proxy point lies in front of some camera and inside its image."""
    step = max(1, len(proxy.vertices) // 200_000)
    points = proxy.vertices[::step]
    for camera in cameras:
        pixels, depth = camera.project(points)
        if np.any((depth > 0) & camera.in_image(pixels)):
            return
    raise SceneError(path, "the proxy lies in front of no camera: no vertex projects into any image (wrong frame?)")


# ---------------------------------------------------------------------------------------------
# scene.json
# ---------------------------------------------------------------------------------------------
def _vector(value: Any, path: Path, field: str) -> np.ndarray:
    try:
        vector = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise SceneError(path, f"{field} must be a list of 3 numbers, got {value!r}") from None
    if vector.shape != (3,):
        raise SceneError(path, f"{field} must be a list of 3 numbers, got {value!r}")
    if not np.isfinite(vector).all():
        raise SceneError(path, f"{field} must be finite, got {value!r}")
    if np.linalg.norm(vector) < 1e-12:
        raise SceneError(path, f"{field} must be a non-zero vector, got {value!r}")
    return vector / np.linalg.norm(vector)


def _pixel(value: Any, path: Path, field: str) -> np.ndarray:
    try:
        pixel = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        pixel = None
    if pixel is None or pixel.shape != (2,) or not np.isfinite(pixel).all():
        raise SceneError(path, f"{field} must be a pixel [column, row], got {value!r}")
    return pixel


def read_scene_json(path: os.PathLike | str) -> dict[str, Any]:
    """Read and validate ``scene.json`` (frame and sun, see ``docs/formats.md``).

    Returns
    -------
    dict
        ``{"up": (3,) unit float64, "sun_form": name, name: validated value}`` where ``name`` is the
        single sun form given (``sun_direction`` as a unit vector, ``sun_clicks`` with float pixels,
        ``sun_time`` with a timezone-aware :class:`datetime.datetime` under ``"datetime"``).

    Raises
    ------
    SceneError
        Naming the field: unreadable JSON, zero or non-finite vectors, no sun form or several,
        missing or malformed sub-fields.
    """
    path = Path(path)
    if not path.is_file():
        raise SceneError(path, "scene.json not found")
    try:
        data = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise SceneError(path, f"not valid JSON ({exc})") from None
    if not isinstance(data, dict):
        raise SceneError(path, f"must hold a JSON object, got {type(data).__name__}")
    out: dict[str, Any] = {"up": _vector(data.get("up", [0.0, 0.0, 1.0]), path, "up")}
    forms = [key for key in SUN_FORMS if key in data]
    if len(forms) != 1:
        found = f"found {forms}" if forms else "found none"
        raise SceneError(path, f"give the sun in exactly one way ({', '.join(SUN_FORMS)}); {found}")
    form = forms[0]
    out["sun_form"] = form
    value = data[form]
    if form == "sun_direction":
        out[form] = _vector(value, path, "sun_direction")
    elif form == "sun_clicks":
        if not isinstance(value, dict):
            raise SceneError(path, f"sun_clicks must be an object with view, shadow_px, caster_px, got {value!r}")
        for key in ("view", "shadow_px", "caster_px"):
            if key not in value:
                raise SceneError(path, f"sun_clicks.{key} is missing")
        if not isinstance(value["view"], str):
            raise SceneError(path, f"sun_clicks.view must be a view stem (string), got {value['view']!r}")
        out[form] = {
            "view": value["view"],
            "shadow_px": _pixel(value["shadow_px"], path, "sun_clicks.shadow_px"),
            "caster_px": _pixel(value["caster_px"], path, "sun_clicks.caster_px"),
        }
    else:
        if not isinstance(value, dict):
            raise SceneError(path, f"sun_time must be an object with datetime, latitude, longitude, north, got {value!r}")
        for key in ("datetime", "latitude", "longitude", "north"):
            if key not in value:
                raise SceneError(path, f"sun_time.{key} is missing")
        try:
            when = _dt.datetime.fromisoformat(str(value["datetime"]))
        except ValueError:
            raise SceneError(path, f"sun_time.datetime must be ISO 8601, got {value['datetime']!r}") from None
        if when.tzinfo is None:
            raise SceneError(path, f"sun_time.datetime needs a UTC offset (e.g. +02:00), got {value['datetime']!r}")
        numbers = {}
        for key, bound in (("latitude", 90.0), ("longitude", 180.0), ("altitude", math.inf)):
            raw = value.get(key, 0.0)
            if isinstance(raw, bool) or not isinstance(raw, (int, float)) or not math.isfinite(raw) or abs(raw) > bound:
                raise SceneError(path, f"sun_time.{key} must be a number in [-{bound}, {bound}], got {raw!r}")
            numbers[key] = float(raw)
        out[form] = {"datetime": when, **numbers, "north": _vector(value["north"], path, "sun_time.north")}
    return out


# ---------------------------------------------------------------------------------------------
# the scene
# ---------------------------------------------------------------------------------------------
def load_scene(
    path: os.PathLike | str,
    *,
    max_size: int | None = DEFAULT_MAX_SIZE,
    views: Sequence[str] | None = None,
    on_invalid: str = "raise",
    progress: bool = False,
) -> Scene:
    """Load a scene folder (``docs/formats.md``).

    Parameters
    ----------
    path : path-like
        Scene folder with ``images/``, ``sparse/``, ``proxy.ply`` and ``scene.json``.
    max_size : int or None, optional
        Downscale images (area averaging) so that their longer side is at most ``max_size`` pixels;
        cameras are scaled to match (:meth:`Camera.scaled`). Default :data:`DEFAULT_MAX_SIZE`
        (1400): larger photos are downscaled, so that a 12 MP view stays within 4 GB (the matting
        and the multi-view labelling hold several arrays per pixel). ``None``: full resolution. Sun clicks refer to full-size pixels.
    views : sequence of str, optional
        Stems (or image names) of the views to load, in the order given. Default: all registered
        images, sorted by name.
    on_invalid : {"raise", "mask"}, optional
        What to do with NaN, infinite or negative pixels: raise a :class:`SceneError` naming the
        image, or exclude them from the view's valid mask.
    progress : bool, optional
        Show a progress bar over images (tqdm).

    Returns
    -------
    Scene
        With ``source`` set to the folder. Each view's mask excludes saturated pixels of integer
        images (any channel at the maximum code) and, with ``on_invalid="mask"``, invalid pixels.
        Pixels are taken as stored in the file, COLMAP's convention (it ignores the EXIF
        orientation); a photo whose stored size is its camera's size turned by 90 degrees is
        turned by its EXIF orientation instead (a model made from the photos as displayed).

    Raises
    ------
    SceneError
        Naming the file or field: missing folder or part, image listed in the model but absent,
        image size not matching its camera, unreadable image, invalid pixels, empty or degenerate
        proxy, proxy in front of no camera, malformed scene.json, clicks outside the image or
        missing the proxy, sun below the horizon, unknown camera model.
    """
    from tqdm.auto import tqdm

    if on_invalid not in ("raise", "mask"):
        raise ValueError(f"on_invalid must be 'raise' or 'mask', got {on_invalid!r}")
    if max_size is not None and (isinstance(max_size, bool) or not isinstance(max_size, int) or max_size < 1):
        raise ValueError(f"max_size must be a positive integer or None, got {max_size!r}")
    root = Path(path)
    if not root.is_dir():
        raise SceneError(root, "scene folder not found")
    for part, is_dir in (("images", True), ("sparse", True), ("proxy.ply", False), ("scene.json", False)):
        p = root / part
        if not (p.is_dir() if is_dir else p.is_file()):
            raise SceneError(p, "missing: a scene folder needs images/, sparse/, proxy.ply and scene.json")
    settings = read_scene_json(root / "scene.json")
    cameras = read_colmap(root / "sparse")
    by_stem = {Path(name).with_suffix("").as_posix(): name for name in cameras}
    if views is None:
        names = sorted(cameras)
    else:
        if isinstance(views, str):
            raise TypeError("views must be a sequence of stems, not a single string")
        names = []
        for wanted in views:
            name = wanted if wanted in cameras else by_stem.get(wanted)
            if name is None:
                raise ValueError(f"views: no view named {wanted!r} in the model; views are {sorted(by_stem)}")
            names.append(name)
    proxy = read_proxy(root / "proxy.ply", camera_centers=np.stack([c.center for c in cameras.values()]))
    _check_proxy_visible(proxy, cameras.values(), root / "proxy.ply")

    loaded = []
    for name in tqdm(names, desc="images", unit="img", disable=not progress):
        file = root / "images" / name
        if not file.is_file():
            raise SceneError(file, f"image {name!r} is listed in the COLMAP model but absent from images/")
        if file.suffix.lower() not in IMAGE_EXTENSIONS:
            raise SceneError(file, f"unsupported image type {file.suffix!r} (supported: {', '.join(IMAGE_EXTENSIONS)})")
        camera = cameras[name]
        image, saturation = read_image_for_size(file, width=camera.width, height=camera.height)
        h, w = image.shape[:2]
        if (w, h) != (camera.width, camera.height):
            raise SceneError(file, f"image is {w}x{h} pixels but its COLMAP camera is {camera.width}x{camera.height}")
        with np.errstate(invalid="ignore"):
            finite = np.isfinite(image).all(axis=2)
            negative = finite & (image < 0).any(axis=2)
        if on_invalid == "raise" and (not finite.all() or negative.any()):
            raise SceneError(
                file,
                f"{int((~finite).sum())} pixels are NaN or infinite and {int(negative.sum())} are negative "
                "(pass on_invalid='mask' to exclude them instead)",
            )
        mask = valid_pixels(image, saturation=saturation)
        if not (mask & (image > 0).any(axis=2)).any():
            raise SceneError(file, "the image holds no valid pixel above 0 (all black, saturated or invalid): it would "
                             "give zero layers and bias L_sun; fix it or leave it out (load_scene(views=...), --views)")
        if max_size is not None and max(w, h) > max_size:
            scale = max_size / max(w, h)
            nw, nh = max(1, round(w * scale)), max(1, round(h * scale))
            image, mask = resize_image(image, mask, nw, nh)
            camera = camera.scaled(nw, nh)
        loaded.append(View(Path(name).with_suffix("").as_posix(), image, camera, mask))

    sun = _scene_sun(settings, root, cameras, by_stem, proxy)
    try:
        return Scene(tuple(loaded), proxy, sun, up=settings["up"], source=root.resolve())
    except ValueError as exc:
        raise SceneError(root / "scene.json", str(exc)) from exc


def _scene_sun(settings: dict, root: Path, cameras: dict[str, Camera], by_stem: dict[str, str], proxy: Proxy) -> Sun:
    form, value, file = settings["sun_form"], settings[settings["sun_form"]], root / "scene.json"
    if form == "sun_direction":
        return Sun(value)
    if form == "sun_time":
        return sun_from_time(
            value["datetime"], value["latitude"], value["longitude"], north=value["north"], up=settings["up"],
            altitude=value["altitude"],
        )
    name = value["view"] if value["view"] in cameras else by_stem.get(value["view"])
    if name is None:
        raise SceneError(file, f"sun_clicks.view: no view named {value['view']!r}; views are {sorted(by_stem)}")
    try:
        return sun_from_clicks(cameras[name], value["shadow_px"], value["caster_px"], Tracer(proxy))
    except ValueError as exc:
        raise SceneError(file, f"sun_clicks.{exc}") from exc


# ---------------------------------------------------------------------------------------------
# result folder
# ---------------------------------------------------------------------------------------------
def _is_scene_folder(folder: Path) -> bool:
    return (folder / "scene.json").is_file() and (folder / "sparse").is_dir()


def _umask() -> int:
    """The process's file-creation mask (read by setting and restoring it)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _nearest_existing(folder: Path) -> Path:
    for candidate in (folder, *folder.parents):
        if candidate.exists():
            return candidate
    return Path(folder.anchor)


def _is_foreign(folder: Path) -> bool:
    """A non-empty folder that mvintrinsic did not write (no :data:`RESULT_MARKER`)."""
    return folder.is_dir() and any(folder.iterdir()) and not (folder / RESULT_MARKER).is_file()


def _write_marker(folder: Path) -> None:
    _atomic_write(folder / RESULT_MARKER, lambda tmp: tmp.write_text("written by mvintrinsic\n"))


def check_result_folder(
    folder: os.PathLike | str,
    *,
    scene: Scene | os.PathLike | str | None = None,
    overwrite: bool = False,
) -> Path:
    """Refuse an output folder that :func:`save_decomposition` could not or must not write.

    Call it before a long computation (the CLI does) so that a bad ``OUT`` costs nothing; it
    writes nothing.

    Parameters
    ----------
    folder : path-like
        The intended result folder.
    scene : Scene or path-like, optional
        The input scene (or its folder): the result may not be it or lie inside it.
    overwrite : bool, optional
        Accept a non-empty folder that mvintrinsic did not write (:data:`RESULT_MARKER` absent).

    Returns
    -------
    pathlib.Path
        ``folder``, resolved.

    Raises
    ------
    ResultFolderError
        If ``folder`` is a file, is or lies inside the scene folder (or any folder that looks
        like a scene folder: ``scene.json`` and ``sparse/``), is a non-empty folder that
        mvintrinsic did not write and ``overwrite`` is false, or cannot be written (the message
        names the folder and the reason).
    """
    folder = Path(folder).resolve()
    scene_dir = scene.source if isinstance(scene, Scene) else (None if scene is None else Path(scene))
    if scene_dir is not None:
        scene_dir = Path(scene_dir).resolve()
        if folder == scene_dir or scene_dir in folder.parents:
            raise ResultFolderError(f"{folder}: refusing to write a result inside the scene folder {scene_dir}")
    for candidate in (folder, *folder.parents):
        if _is_scene_folder(candidate):
            raise ResultFolderError(f"{folder}: refusing to write a result inside the scene folder {candidate}")
    existing = _nearest_existing(folder)
    if not existing.is_dir():
        raise ResultFolderError(f"{folder}: {existing} exists and is not a folder")
    if _is_foreign(folder) and not overwrite:
        raise ResultFolderError(
            f"{folder}: is not empty and was not written by mvintrinsic; choose another folder or pass "
            "overwrite=True (--overwrite) to write into it"
        )
    # The result is written beside the folder and swapped in, or (a foreign folder) into it.
    for where in {_nearest_existing(folder.parent), existing}:
        if not os.access(where, os.W_OK | os.X_OK):
            raise ResultFolderError(f"{folder}: cannot write there ({where} is not writable)")
    return folder


def _prepare_result_folder(folder: Path, *, overwrite: bool, scene: Scene | os.PathLike | str | None) -> Path:
    """:func:`check_result_folder`, then create the folder and its marker (for in-place writers)."""
    folder = check_result_folder(folder, scene=scene, overwrite=overwrite)
    folder.mkdir(parents=True, exist_ok=True)
    if not (folder / RESULT_MARKER).is_file():
        _write_marker(folder)
    return folder


#: Prefix of the sibling folders a result is written into before it is swapped in.
_PARTIAL = "partial"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):  # another user's process, or no such pid number
        pass
    return True


def _remove_stale_partials(folder: Path) -> None:
    """Delete sibling work folders (``.NAME.partial-PID-*``) left by writers that were killed."""
    for sibling in folder.parent.glob(f".{folder.name}.{_PARTIAL}-*"):
        pid = sibling.name[len(f".{folder.name}.{_PARTIAL}-"):].split("-", 1)[0]
        if sibling.is_dir() and pid.isdigit() and not _alive(int(pid)):
            shutil.rmtree(sibling, ignore_errors=True)


@functools.cache
def _renameat2():
    """glibc's ``renameat2`` (Linux >= 3.15, glibc >= 2.28), or None."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        function = libc.renameat2
    except (OSError, AttributeError):
        return None
    function.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    function.restype = ctypes.c_int
    return function


def _exchange(a: Path, b: Path) -> bool:
    """Swap two paths in one atomic step (``RENAME_EXCHANGE``); False where the system cannot."""
    function = _renameat2()
    if function is None:
        return False
    at_fdcwd, rename_exchange = -100, 2
    if function(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), rename_exchange) == 0:
        return True
    error = ctypes.get_errno()
    if error in (errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP):
        return False
    raise OSError(error, os.strerror(error), str(b))


def _swap_in(work: Path, folder: Path) -> None:
    """Put the complete folder ``work`` at ``folder``; a crash at any instant leaves a complete one.

    An absent or empty ``folder`` is replaced by a rename. An existing result is exchanged with
    ``work`` in one atomic step where the system offers it (Linux ``renameat2``), then deleted;
    elsewhere it is renamed aside first, so that a crash between the two renames leaves it, whole,
    as ``.NAME.partial-PID-*`` beside an absent ``folder``.
    """
    if folder.is_dir() and not any(folder.iterdir()):
        folder.rmdir()
    if not folder.exists():
        os.rename(work, folder)
        return
    if not _exchange(work, folder):
        aside = Path(tempfile.mkdtemp(prefix=f".{folder.name}.{_PARTIAL}-{os.getpid()}-old-", dir=folder.parent))
        os.rename(folder, aside / "result")
        os.rename(work, folder)
        work = aside
    shutil.rmtree(work, ignore_errors=True)  # now the old result


def _result_files(result: Decomposition) -> dict[str, tuple[np.ndarray, str]]:
    """Relative path -> (array, :func:`write_image` dtype) of every layer file of a result folder."""
    files = {}
    if result.lighting.envmap is not None:
        files["envmap.exr"] = (result.lighting.envmap, "float")
    for stem, layers in result.layers.items():
        for name in ("reflectance", "shading", "sun_shading", "sky_shading", "indirect_shading", "visibility"):
            files[f"views/{stem}/{name}.exr"] = (getattr(layers, name), "float")
        files[f"views/{stem}/shadow_labels.png"] = (layers.shadow_labels, "uint8")
    return files


def save_decomposition(
    result: Decomposition,
    folder: os.PathLike | str,
    *,
    overwrite: bool = False,
    scene: Scene | os.PathLike | str | None = None,
) -> Path:
    """Write a decomposition as a result folder (``docs/formats.md``), all or nothing.

    Parameters
    ----------
    result : Decomposition
        What to write.
    folder : path-like
        Destination folder, created if needed (:func:`check_result_folder` says which are
        refused).
    overwrite : bool, optional
        Allow writing into an existing non-empty folder that mvintrinsic did not create; its
        other files are kept. Folders mvintrinsic created (they hold :data:`RESULT_MARKER`) are
        replaced whole without it.
    scene : Scene or path-like, optional
        The input scene (or its folder): writing inside it is refused. Folders that look like a
        scene folder (``scene.json`` + ``sparse/``), or lie inside one, are refused in any case.

    Returns
    -------
    pathlib.Path
        The result folder.

    Raises
    ------
    ResultFolderError
        If ``folder`` may not or cannot be written (:func:`check_result_folder`).

    Notes
    -----
    An absent, empty or mvintrinsic-written ``folder`` is written as a hidden sibling
    (``.NAME.partial-PID-*``) and swapped in when complete (:func:`os.rename`; over an existing
    result, Linux's atomic ``renameat2`` exchange): a crash or ``kill -9`` at any instant leaves
    either the complete old result or the complete new one, and a later write removes the
    sibling a killed writer left. A result of fewer views replaces a larger one whole (no stale
    view folder). Into a foreign folder (``overwrite=True``) the files are written in place,
    ``lighting.json`` removed first and written last. ``lighting.json`` lists every layer file
    with its size, and :func:`load_decomposition` refuses a folder that does not match it. Every
    file is written atomically with the user's umask; EXR files are 32-bit float (lossless round
    trip).
    """
    if not isinstance(result, Decomposition):
        raise TypeError(f"result must be a Decomposition, got {type(result).__name__}")
    folder = check_result_folder(folder, scene=scene, overwrite=overwrite)
    if _is_foreign(folder):  # overwrite=True: written in place, its other files kept
        _write_marker(folder)
        with contextlib.suppress(FileNotFoundError):
            (folder / "lighting.json").unlink()  # incomplete until it is written again, last
        _write_result(result, folder)
        return folder
    folder.parent.mkdir(parents=True, exist_ok=True)
    _remove_stale_partials(folder)
    work = Path(tempfile.mkdtemp(prefix=f".{folder.name}.{_PARTIAL}-{os.getpid()}-", dir=folder.parent))
    try:
        os.chmod(work, 0o777 & ~_umask())
        _write_marker(work)
        _write_result(result, work)
        _swap_in(work, folder)
    except BaseException:
        shutil.rmtree(work, ignore_errors=True)
        raise
    return folder


def _write_result(result: Decomposition, folder: Path) -> None:
    """Every layer file, then ``lighting.json`` with the manifest of their sizes."""
    sizes = {}
    for relative, (array, dtype) in _result_files(result).items():
        sizes[relative] = write_image(folder / relative, array, dtype=dtype).stat().st_size
    lighting = result.lighting.to_dict()
    lighting.update(
        views=list(result.stems), timings=dict(result.timings), version=result.version, config=dict(result.config),
        files=sizes,
    )
    write_json(folder / "lighting.json", lighting)


def _read_raw(path: Path, channels: int) -> np.ndarray:
    """A result layer as stored (float32, or uint8 for PNG labels), ``(H, W)`` for one channel."""
    data, _ = _read_stored(path, "result file not found")
    if data.shape[2] != channels:
        raise SceneError(path, f"expected {channels} channels, found {data.shape[2]}")
    return data[..., 0] if channels == 1 else data


def _check_complete(folder: Path, data: dict) -> None:
    """Refuse a result folder that does not match its ``lighting.json`` (a mixed or partial write)."""
    file = folder / "lighting.json"
    views = data.get("views", [])
    if not isinstance(views, list) or not all(isinstance(v, str) for v in views):
        raise SceneError(file, "malformed lighting.json ('views' must be a list of view names)")
    if (folder / "views").is_dir():
        stale = sorted(p.name for p in (folder / "views").iterdir() if p.is_dir() and p.name not in views)
        if stale:
            raise SceneError(folder / "views" / stale[0], f"view folder not listed in lighting.json ({len(stale)} "
                             "such): the result folder mixes two writes; write the result again")
    sizes = data.get("files")
    if sizes is None:  # written before the manifest existed
        return
    if not isinstance(sizes, dict):
        raise SceneError(file, "malformed lighting.json ('files' must map file names to sizes)")
    for relative, size in sizes.items():
        path = folder / relative
        if not path.is_file():
            raise SceneError(path, "result file not found (incomplete result folder); write the result again")
        if path.stat().st_size != size:
            raise SceneError(path, f"{path.stat().st_size} bytes where lighting.json says {size}: the result "
                             "folder mixes two writes; write the result again")


def load_decomposition(folder: os.PathLike | str) -> Decomposition:
    """Read a result folder written by :func:`save_decomposition`.

    ``shading.exr`` is not read back: it is derived from the other layers.

    Raises
    ------
    SceneError
        If ``lighting.json`` or a layer file is missing or malformed, or the folder does not match
        ``lighting.json`` (a file of another size than it lists, a view folder it does not list):
        the traces of an interrupted or mixed write.
    """
    folder = Path(folder)
    file = folder / "lighting.json"
    if not file.is_file():
        raise SceneError(file, "lighting.json not found (not a complete result folder)")
    try:
        data = json.loads(file.read_text())
        sky = None if data.get("sky") is None else SkyParameters.from_dict(data["sky"])
        envmap = _read_raw(folder / "envmap.exr", 3) if (folder / "envmap.exr").is_file() else None
        lighting = Lighting(
            Sun(data["sun_direction"], data.get("sun_angular_radius", Sun(data["sun_direction"]).angular_radius)),
            data["sun_radiance"],
            up=data["up"],
            sky=sky,
            horizon_plane=data.get("horizon_plane"),
            envmap=envmap,
            horizon_evidence=data.get("horizon_evidence"),
            exposure=None if data.get("exposure") is None else ViewGains.from_dict(data["exposure"]),
            model={name: ModelChoice.from_dict(value) for name, value in (data.get("model") or {}).items()},
        )
    except (KeyError, TypeError, ValueError) as exc:
        if isinstance(exc, SceneError):
            raise
        raise SceneError(file, f"malformed lighting.json ({exc!r})") from exc
    _check_complete(folder, data)
    layers = {}
    for stem in data.get("views", []):
        out = folder / "views" / stem
        layers[stem] = IntrinsicLayers(
            stem,
            reflectance=_read_raw(out / "reflectance.exr", 3),
            sun_shading=_read_raw(out / "sun_shading.exr", 3),
            sky_shading=_read_raw(out / "sky_shading.exr", 3),
            indirect_shading=_read_raw(out / "indirect_shading.exr", 3),
            visibility=_read_raw(out / "visibility.exr", 1),
            shadow_labels=_read_raw(out / "shadow_labels.png", 1),
        )
    return Decomposition(
        layers, lighting, timings=data.get("timings", {}), config=data.get("config", {}), version=data.get("version", "")
    )
