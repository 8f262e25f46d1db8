"""Reading scene folders and writing result folders (the edge of the package: files <-> objects).

The layouts are the public contract of ``docs/formats.md``:

* :func:`load_scene` reads ``images/``, ``sparse/`` (COLMAP text or binary, through pycolmap),
  ``proxy.ply`` (through open3d) and ``scene.json`` into a validated
  :class:`~mvintrinsic.scene.Scene`.
* :func:`save_decomposition` / :func:`load_decomposition` write and read a result folder.
  A result folder is written whole beside its place and swapped in (all or nothing), never inside
  a scene folder, and a non-empty folder that mvintrinsic did not create is only written into
  when ``overwrite=True``; :func:`check_result_folder` refuses a bad output before any work.
* :func:`read_image` / :func:`write_image` read and write single images through OpenImageIO
  (:mod:`.files`); the result folders are :mod:`.result_folder`'s, the errors :mod:`.errors`'; all
  are exported here too.

Every malformed input raises :class:`SceneError` (a :class:`ValueError`) whose message starts with
the offending file (and field) and says what is wrong.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import json
import math
import os
import tempfile
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ._libusb import ensure_libusb
from .camera import CAMERA_MODELS, Camera
from .errors import ResultFolderError, SceneError
from .files import (
    _atomic_write,
    _srgb_lut,
    exif_orient,
    read_image,
    read_image_for_size,
    write_image,
    write_json,
)
from .raytrace import Tracer
from .resolution import resize_image
from .result_folder import RESULT_MARKER, check_result_folder, load_decomposition, save_decomposition
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
#: Sun keys of scene.json; exactly one must be present.
SUN_FORMS = ("sun_direction", "sun_clicks", "sun_time")


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
