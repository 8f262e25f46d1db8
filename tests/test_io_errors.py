"""Malformed scene folders: every case raises the right error naming the offending file or field.

Each test builds a valid scene (``scene_dir`` / ``make_scene`` from conftest), breaks exactly one
thing and loads it with :func:`mvintrinsic.io.load_scene`. Errors of the folder are
:class:`~mvintrinsic.io.SceneError` (a ValueError) whose message names the file or field and whose
``path`` is the offending file; bad Python arguments are plain ValueError/TypeError naming the
argument. A few positive tests check the two indirect sun forms (clicks, time and place).

``test_fault_table`` is the CLI contract of docs/formats.md ("Errors"): each hostile input is run
through the real ``mvintrinsic`` command and must end with exit status 2, one error line naming the
culprit, the inputs byte-identical and nothing written.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
import shutil
import struct
import subprocess
import sys
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pytest
from conftest import make_scene

from mvintrinsic import io as mio
from mvintrinsic.io import SceneError, load_scene, read_image, write_image

# --- constants and tolerances (all in one place) --------------------------------------------
#: size of the images written by make_scene (width, height)
WIDTH, HEIGHT = 64, 48
#: the two views of the default scene
VIEW0, VIEW1 = "view_000.exr", "view_001.exr"
#: pixels (row, column) poisoned in the invalid-pixel tests
BAD_PIXELS = ((0, 0), (5, 7), (20, 33), (47, 63), (30, 1))
#: distance the proxy is moved to put it behind both cameras (they look toward +y from y ~ -8 m)
FAR_BEHIND = (0.0, -1000.0, 0.0)
#: 3D points for the positive sun-click test: a ground point in front of the box, a point on the
#: box top (ground top face at z = 0, box top at z = 2, cameras at z = 2.5 looking from y ~ -8)
SHADOW_3D = np.array([0.5, -3.0, 0.0])
CASTER_3D = np.array([0.0, -0.5, 2.0])
#: sun direction recovered from the clicks vs. normalize(caster - shadow) (float32 ray casting)
CLICK_TOL = 1e-3
#: sun_time positive case: noon UTC at the June solstice on the equator, north = +y
SOLSTICE_NOON = "2026-06-21T12:00:00+00:00"
#: expected solar elevation there: 90 - declination (23.44 degrees), with a generous tolerance
#: (equation of time, refraction and the exact declination move it by a fraction of a degree)
SOLSTICE_ELEVATION_DEG = 90.0 - 23.44
ELEVATION_TOL_DEG = 1.0
#: the sun is near the meridian at 12:00 UTC at longitude 0 (solar noon ~12:02 UTC)
AZIMUTH_TOL_DEG = 5.0


# --- helpers that break a scene ---------------------------------------------------------------
def _write_scene_json(scene: Path, settings: dict) -> None:
    """Replace scene.json (json.dumps writes NaN/Infinity, which json.loads accepts)."""
    (scene / "scene.json").write_text(json.dumps(settings))


def _set_camera_model(scene: Path, model: str, params: list[float]) -> None:
    """Give camera 1 of sparse/cameras.txt another model and parameter list."""
    file = scene / "sparse" / "cameras.txt"
    lines = file.read_text().splitlines()
    for i, line in enumerate(lines):
        fields = line.split()
        if fields and fields[0] == "1":
            lines[i] = " ".join([fields[0], model, fields[2], fields[3], *(f"{p:.12g}" for p in params)])
    file.write_text("\n".join(lines) + "\n")


def _write_ply_points(path: Path, points: np.ndarray, normals: np.ndarray | None = None) -> None:
    """ASCII PLY point cloud (optionally with normals)."""
    props = ["x", "y", "z"] + (["nx", "ny", "nz"] if normals is not None else [])
    header = ["ply", "format ascii 1.0", f"element vertex {len(points)}"]
    header += [f"property float {p}" for p in props] + ["end_header"]
    rows = points if normals is None else np.hstack([points, normals])
    body = [" ".join(f"{v:.6f}" for v in row) for row in rows]
    path.write_text("\n".join(header + body) + "\n")


def _poison(scene: Path, kind: str) -> None:
    """Put NaN / +Inf / negative values into BAD_PIXELS of view_000.exr (one channel each)."""
    file = scene / "images" / VIEW0
    image, _ = read_image(file)
    value, channel = {"nan": (np.nan, 0), "inf": (np.inf, 2), "negative": (-0.25, 1)}[kind]
    for row, col in BAD_PIXELS:
        image[row, col, channel] = value
    write_image(file, image)


def _view(scene, stem: str):
    return next(v for v in scene.views if v.stem == stem)


def _click_for(camera, point: np.ndarray) -> list[float]:
    """Pixel index (column, row) whose ray goes through ``point``: rays pass through (u+.5, v+.5)."""
    pixels, depth = camera.project(point[None])
    assert depth[0] > 0 and camera.in_image(pixels)[0]
    return (pixels[0] - 0.5).tolist()


# --- missing parts ------------------------------------------------------------------------------
def test_missing_scene_folder(tmp_path):
    missing = tmp_path / "no_such_scene"
    with pytest.raises(SceneError, match=r"no_such_scene: scene folder not found") as exc:
        load_scene(missing)
    assert exc.value.path == missing


@pytest.mark.parametrize("part", ["images", "sparse", "proxy.ply", "scene.json"])
def test_missing_part(scene_dir, part):
    target = scene_dir / part
    if target.is_dir():
        shutil.rmtree(target)
    else:
        target.unlink()
    with pytest.raises(SceneError, match=rf"{re.escape(part)}: missing") as exc:
        load_scene(scene_dir)
    assert exc.value.path == target


def test_image_listed_in_model_but_absent(scene_dir):
    (scene_dir / "images" / VIEW1).unlink()
    with pytest.raises(SceneError, match=r"view_001\.exr: .*absent from images/") as exc:
        load_scene(scene_dir)
    assert exc.value.path == scene_dir / "images" / VIEW1


# --- images -------------------------------------------------------------------------------------
def test_image_size_not_matching_camera(scene_dir):
    write_image(scene_dir / "images" / VIEW1, np.full((HEIGHT // 2, WIDTH // 2, 3), 0.5, np.float32))
    with pytest.raises(SceneError, match=rf"view_001\.exr: .*{WIDTH // 2}x{HEIGHT // 2}.*{WIDTH}x{HEIGHT}") as exc:
        load_scene(scene_dir)
    assert exc.value.path == scene_dir / "images" / VIEW1


def test_unreadable_image(scene_dir):
    file = scene_dir / "images" / VIEW0
    file.write_bytes(np.random.default_rng(1).bytes(4096))
    with pytest.raises(SceneError, match=r"view_000\.exr: unreadable") as exc:
        load_scene(scene_dir)
    assert exc.value.path == file


@pytest.mark.parametrize("ext", [".exr", ".png"])
def test_truncated_image(tmp_path, ext):
    scene = make_scene(tmp_path / "scene", ext=ext)
    file = scene / "images" / f"view_000{ext}"
    data = file.read_bytes()
    file.write_bytes(data[: len(data) // 2])
    with pytest.raises(SceneError, match=rf"view_000\{ext}: .*truncated") as exc:
        load_scene(scene)
    assert exc.value.path == file


@pytest.mark.parametrize(
    ("kind", "words"), [("nan", "NaN"), ("inf", "infinite"), ("negative", "negative")]
)
def test_invalid_pixels_raise_by_default(scene_dir, kind, words):
    _poison(scene_dir, kind)
    with pytest.raises(SceneError, match=rf"view_000\.exr: .*{words}.*on_invalid='mask'") as exc:
        load_scene(scene_dir)
    assert exc.value.path == scene_dir / "images" / VIEW0


@pytest.mark.parametrize("kind", ["nan", "inf", "negative"])
def test_invalid_pixels_masked_on_request(scene_dir, kind):
    _poison(scene_dir, kind)
    scene = load_scene(scene_dir, on_invalid="mask")
    mask = _view(scene, "view_000").mask
    rows, cols = np.array(BAD_PIXELS).T
    assert int((~mask).sum()) == len(BAD_PIXELS)
    assert not mask[rows, cols].any()
    assert _view(scene, "view_001").mask.all()


# --- proxy --------------------------------------------------------------------------------------
def test_empty_proxy(scene_dir):
    file = scene_dir / "proxy.ply"
    file.write_text("ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\n"
                    "property float z\nend_header\n")
    with pytest.raises(SceneError, match=r"proxy\.ply: .*empty") as exc:
        load_scene(scene_dir)
    assert exc.value.path == file


def test_degenerate_proxy_collinear_points(scene_dir):
    file = scene_dir / "proxy.ply"
    x = np.linspace(-2.0, 2.0, 20)
    points = np.stack([x, np.full_like(x, -3.0), np.zeros_like(x)], axis=1)
    _write_ply_points(file, points, np.tile([0.0, 0.0, 1.0], (len(x), 1)))
    with pytest.raises(SceneError, match=r"proxy\.ply: .*degenerate.*line") as exc:
        load_scene(scene_dir)
    assert exc.value.path == file


def test_proxy_in_front_of_no_camera(scene_dir):
    import open3d as o3d

    file = scene_dir / "proxy.ply"
    mesh = o3d.io.read_triangle_mesh(str(file)).translate(FAR_BEHIND)
    o3d.io.write_triangle_mesh(str(file), mesh)
    with pytest.raises(SceneError, match=r"proxy\.ply: .*in front of no camera") as exc:
        load_scene(scene_dir)
    assert exc.value.path == file


# --- scene.json: sun forms ---------------------------------------------------------------------
def test_zero_sun_vector(scene_dir):
    _write_scene_json(scene_dir, {"up": [0, 0, 1], "sun_direction": [0, 0, 0]})
    with pytest.raises(SceneError, match=r"scene\.json: sun_direction .*non-zero") as exc:
        load_scene(scene_dir)
    assert exc.value.path == scene_dir / "scene.json"


@pytest.mark.parametrize("bad", [math.nan, math.inf, "north"], ids=["nan", "inf", "string"])
def test_non_finite_sun_vector(scene_dir, bad):
    _write_scene_json(scene_dir, {"up": [0, 0, 1], "sun_direction": [0.3, bad, 0.8]})
    with pytest.raises(SceneError, match=r"scene\.json: sun_direction must be") as exc:
        load_scene(scene_dir)
    assert exc.value.path == scene_dir / "scene.json"


def test_two_sun_forms(scene_dir):
    settings = {
        "sun_direction": [0.4, -0.3, 0.8],
        "sun_time": {"datetime": SOLSTICE_NOON, "latitude": 0.0, "longitude": 0.0, "north": [0, 1, 0]},
    }
    _write_scene_json(scene_dir, settings)
    with pytest.raises(SceneError, match=r"scene\.json: .*exactly one.*sun_direction.*sun_time") as exc:
        load_scene(scene_dir)
    assert exc.value.path == scene_dir / "scene.json"


def test_no_sun_form(scene_dir):
    _write_scene_json(scene_dir, {"up": [0, 0, 1]})
    with pytest.raises(SceneError, match=r"scene\.json: .*exactly one.*found none") as exc:
        load_scene(scene_dir)
    assert exc.value.path == scene_dir / "scene.json"


@pytest.mark.parametrize("click", [[WIDTH, 10], [-1, 10], [10, HEIGHT]], ids=["right", "left", "below"])
def test_sun_click_outside_image(scene_dir, click):
    clicks = {"view": "view_000", "shadow_px": click, "caster_px": [32, 20]}
    _write_scene_json(scene_dir, {"up": [0, 0, 1], "sun_clicks": clicks})
    with pytest.raises(SceneError, match=r"scene\.json: sun_clicks[.: ]+shadow_px .*outside") as exc:
        load_scene(scene_dir)
    assert exc.value.path == scene_dir / "scene.json"


def test_sun_click_ray_misses_proxy(scene_dir):
    scene = load_scene(scene_dir)
    camera, proxy_top = _view(scene, "view_000").camera, scene.proxy.bounds[1, 2]
    sky = [WIDTH // 2, 0]
    # The ray through the top-middle pixel rises from above the highest proxy point: it must miss.
    ray = camera.pixel_rays(np.array([sky], float) + 0.5)[0]
    assert camera.center[2] > proxy_top and ray[2] > 0
    caster = _click_for(camera, CASTER_3D)
    _write_scene_json(scene_dir, {"sun_clicks": {"view": "view_000", "shadow_px": sky, "caster_px": caster}})
    with pytest.raises(SceneError, match=r"scene\.json: sun_clicks[.: ]+shadow_px .*misses the proxy") as exc:
        load_scene(scene_dir)
    assert exc.value.path == scene_dir / "scene.json"


def test_sun_clicks_unknown_view(scene_dir):
    clicks = {"view": "view_999", "shadow_px": [10, 40], "caster_px": [32, 20]}
    _write_scene_json(scene_dir, {"sun_clicks": clicks})
    with pytest.raises(SceneError, match=r"scene\.json: sun_clicks\.view: .*'view_999'") as exc:
        load_scene(scene_dir)
    assert exc.value.path == scene_dir / "scene.json"


def test_sun_below_horizon(scene_dir):
    _write_scene_json(scene_dir, {"up": [0, 0, 1], "sun_direction": [0.4, -0.3, -0.2]})
    with pytest.raises(SceneError, match=r"scene\.json: sun: .*below the horizon") as exc:
        load_scene(scene_dir)
    assert exc.value.path == scene_dir / "scene.json"


def test_sun_time_naive_datetime(scene_dir):
    when = {"datetime": "2026-06-21T12:00:00", "latitude": 0.0, "longitude": 0.0, "north": [0, 1, 0]}
    _write_scene_json(scene_dir, {"sun_time": when})
    with pytest.raises(SceneError, match=r"scene\.json: sun_time\.datetime .*UTC offset") as exc:
        load_scene(scene_dir)
    assert exc.value.path == scene_dir / "scene.json"


def test_sun_time_missing_north(scene_dir):
    _write_scene_json(scene_dir, {"sun_time": {"datetime": SOLSTICE_NOON, "latitude": 0.0, "longitude": 0.0}})
    with pytest.raises(SceneError, match=r"scene\.json: sun_time\.north is missing") as exc:
        load_scene(scene_dir)
    assert exc.value.path == scene_dir / "scene.json"


def test_malformed_scene_json(scene_dir):
    (scene_dir / "scene.json").write_text('{"up": [0, 0, 1], "sun_direction": [0.4, -0.3, 0.8]')
    with pytest.raises(SceneError, match=r"scene\.json: not valid JSON") as exc:
        load_scene(scene_dir)
    assert exc.value.path == scene_dir / "scene.json"


# --- COLMAP camera models -----------------------------------------------------------------------
def test_unknown_camera_model(scene_dir):
    _set_camera_model(scene_dir, "FANCY_LENS", [57.6, 57.6, 32.0, 24.0])
    file = scene_dir / "sparse" / "cameras.txt"
    with pytest.raises(SceneError, match=r"cameras\.txt: .*unknown or unsupported camera model 'FANCY_LENS'") as exc:
        load_scene(scene_dir)
    assert exc.value.path == file


# OPENCV_FISHEYE: fx, fy, cx, cy, k1, k2, k3, k4 (COLMAP knows it, mvintrinsic does not support it).
FISHEYE_PARAMS = [57.6, 57.6, 32.0, 24.0, 0.01, 0.0, 0.0, 0.0]
#: A COLMAP model without a focal plane: the one kind mvintrinsic refuses (camera.CAMERA_MODELS).
SPHERICAL_PARAMS = [64.0, 48.0]


def test_colmap_fisheye_model_is_read(scene_dir):
    """Every perspective COLMAP model is supported through pycolmap (issue 19), a fisheye included."""
    _set_camera_model(scene_dir, "OPENCV_FISHEYE", FISHEYE_PARAMS)
    scene = load_scene(scene_dir)
    camera = next(v.camera for v in scene.views if v.camera.model == "OPENCV_FISHEYE")
    assert camera.is_distorted and camera.params.tolist() == FISHEYE_PARAMS


def test_colmap_model_not_supported_text(scene_dir):
    _set_camera_model(scene_dir, "EQUIRECTANGULAR", SPHERICAL_PARAMS)
    file = scene_dir / "sparse" / "cameras.txt"
    with pytest.raises(SceneError, match=r"cameras\.txt: .*unsupported camera model 'EQUIRECTANGULAR'") as exc:
        load_scene(scene_dir)
    assert exc.value.path == file


def test_colmap_model_not_supported_binary(scene_dir):
    import pycolmap

    sparse = scene_dir / "sparse"
    _set_camera_model(scene_dir, "EQUIRECTANGULAR", SPHERICAL_PARAMS)
    pycolmap.Reconstruction(str(sparse)).write_binary(str(sparse))
    for name in ("cameras", "images", "points3D"):
        (sparse / f"{name}.txt").unlink()
    with pytest.raises(SceneError, match=r"cameras\.bin: .*unsupported camera model 'EQUIRECTANGULAR'") as exc:
        load_scene(scene_dir)
    assert exc.value.path == sparse / "cameras.bin"


# --- bad Python arguments -------------------------------------------------------------------------
def test_unknown_view_argument(scene_dir):
    with pytest.raises(ValueError, match=r"^views: .*'nope'"):
        load_scene(scene_dir, views=["nope"])


def test_views_argument_single_string(scene_dir):
    with pytest.raises(TypeError, match=r"views"):
        load_scene(scene_dir, views="view_000")


@pytest.mark.parametrize("bad", [0, -3, 2.5, True])
def test_bad_max_size(scene_dir, bad):
    with pytest.raises(ValueError, match=r"^max_size must be a positive integer"):
        load_scene(scene_dir, max_size=bad)


def test_bad_on_invalid(scene_dir):
    with pytest.raises(ValueError, match=r"^on_invalid must be"):
        load_scene(scene_dir, on_invalid="ignore")


# --- positive: the indirect sun forms ---------------------------------------------------------
def test_sun_clicks_recover_direction(scene_dir):
    camera = _view(load_scene(scene_dir), "view_000").camera
    shadow, caster = _click_for(camera, SHADOW_3D), _click_for(camera, CASTER_3D)
    clicks = {"view": "view_000", "shadow_px": shadow, "caster_px": caster}
    _write_scene_json(scene_dir, {"up": [0, 0, 1], "sun_clicks": clicks})
    sun = load_scene(scene_dir).sun
    expected = (CASTER_3D - SHADOW_3D) / np.linalg.norm(CASTER_3D - SHADOW_3D)
    np.testing.assert_allclose(sun.direction, expected, atol=CLICK_TOL)


def test_sun_time_solstice_noon_on_equator(scene_dir):
    when = {"datetime": SOLSTICE_NOON, "latitude": 0.0, "longitude": 0.0, "north": [0, 1, 0]}
    _write_scene_json(scene_dir, {"up": [0, 0, 1], "sun_time": when})
    d = load_scene(scene_dir).sun.direction
    elevation = math.degrees(math.asin(d[2]))
    azimuth_from_north = math.degrees(math.atan2(d[0], d[1]))  # east = north x up = +x
    assert elevation > 60.0
    assert elevation == pytest.approx(SOLSTICE_ELEVATION_DEG, abs=ELEVATION_TOL_DEG)
    assert d[1] > 0  # the June sun stands north of the equator
    assert abs(azimuth_from_north) < AZIMUTH_TOL_DEG


# --- the fault table (issue 18): hostile inputs end as one clear line, exit 2, nothing written ---
# Each case runs the real CLI (``python -m mvintrinsic.cli``) in a fresh tmp_path holding a copy of
# a small scene (``make_scene``: two 64x48 views) and, for ``relight``, of a result decomposed from
# it; most cases fail while loading, before any computation. The contract is docs/formats.md,
# "Errors": exit status 2, stderr exactly one line ``mvintrinsic CMD: error: ...`` naming the
# culprit, every input file byte-identical, and nothing written (no OUT, no ``.OUT.partial-*``).


def _ascii_proxy(scene: Path, *, extra_face=None, vertex_count=None, nan_vertex=False) -> None:
    """Rewrite proxy.ply as ASCII, optionally with one more face, a lying vertex count or a NaN vertex."""
    proxy = mio.read_proxy(scene / "proxy.ply")
    faces = proxy.triangles if extra_face is None else np.vstack([proxy.triangles, [extra_face]])
    vertices = proxy.vertices.copy()
    if nan_vertex:
        vertices[0, 0] = np.nan
    count = len(vertices) if vertex_count is None else vertex_count
    header = ["ply", "format ascii 1.0", f"element vertex {count}", "property float x", "property float y",
              "property float z", f"element face {len(faces)}", "property list uchar int vertex_indices", "end_header"]
    body = [" ".join(f"{x:.6f}" for x in v) for v in vertices] + [f"3 {a} {b} {c}" for a, b, c in faces]
    (scene / "proxy.ply").write_text("\n".join(header + body) + "\n")


def _edit_pose_line(scene: Path, edit) -> None:
    """Apply ``edit(fields) -> fields`` to the first pose line of sparse/images.txt."""
    file = scene / "sparse" / "images.txt"
    lines = file.read_text().splitlines()
    first = next(i for i, line in enumerate(lines) if line and not line.startswith("#"))
    lines[first] = " ".join(edit(lines[first].split()))
    file.write_text("\n".join(lines) + "\n")


def _duplicate_first_image(scene: Path) -> None:
    file = scene / "sparse" / "images.txt"
    lines = file.read_text().splitlines()
    first = next(i for i, line in enumerate(lines) if line and not line.startswith("#"))
    fields = lines[first].split()
    fields[0] = "99"
    file.write_text("\n".join([*lines, " ".join(fields), ""]) + "\n")


def _blacken(scene: Path, names=(VIEW0,)) -> None:
    for name in names:
        image, _ = read_image(scene / "images" / name)
        write_image(scene / "images" / name, np.zeros_like(image))


def _greyen(scene: Path) -> None:
    for name in (VIEW0, VIEW1):
        image, _ = read_image(scene / "images" / name)
        write_image(scene / "images" / name, np.full_like(image, 0.5))


DECOMPOSE = ("decompose", "{scene}", "{out}", "--quiet")
RELIGHT = ("relight", "{scene}", "{result}", "{out}", "--azimuth", "30", "--elevation", "40", "--quiet")


class Fault(NamedTuple):
    """A hostile input: ``damage(scene)`` breaks the copy, then the CLI runs ``argv``.

    ``culprit`` and ``message`` must both appear in the error line; ``{scene}``, ``{out}``,
    ``{result}`` and ``{tmp}`` in them and in ``argv`` stand for the paths of the case.
    """

    damage: Callable[[Path], None]
    culprit: str
    message: str
    argv: tuple[str, ...] = DECOMPOSE
    ext: str = ".exr"


def _nothing(scene: Path) -> None:
    """The scene stays valid: the fault is in the arguments or the output."""


def _remove(relative: str) -> Callable[[Path], None]:
    def damage(scene: Path) -> None:
        target = scene / relative
        shutil.rmtree(target) if target.is_dir() else target.unlink()
    return damage


def _truncate(relative: str, keep_bytes: int | None = None) -> Callable[[Path], None]:
    """Cut a file (to half its size by default) as an interrupted write would leave it."""
    def damage(scene: Path) -> None:
        file = scene / relative
        data = file.read_bytes()
        file.write_bytes(data[: len(data) // 2 if keep_bytes is None else keep_bytes])
    return damage


def _scene_json(settings: dict | str) -> Callable[[Path], None]:
    def damage(scene: Path) -> None:
        text = settings if isinstance(settings, str) else json.dumps(settings)  # NaN written as NaN
        (scene / "scene.json").write_text(text)
    return damage


def _edit_camera_line(scene: Path, edit) -> None:
    """Apply ``edit(fields) -> fields`` to the line of camera 1 in sparse/cameras.txt."""
    file = scene / "sparse" / "cameras.txt"
    lines = file.read_text().splitlines()
    lines = [" ".join(edit(line.split())) if line.split()[:1] == ["1"] else line for line in lines]
    file.write_text("\n".join(lines) + "\n")


def _five_channel_image(scene: Path) -> None:
    """view_000.exr rewritten with 5 channels (write_image refuses to write that)."""
    import OpenImageIO as oiio

    file = scene / "images" / VIEW0
    out = oiio.ImageOutput.create(str(file))
    assert out.open(str(file), oiio.ImageSpec(WIDTH, HEIGHT, 5, "float"))
    assert out.write_image(np.full((HEIGHT, WIDTH, 5), 0.5, np.float32)) and out.close()


def _proxy_behind_cameras(scene: Path) -> None:
    import open3d as o3d

    file = scene / "proxy.ply"
    o3d.io.write_triangle_mesh(str(file), o3d.io.read_triangle_mesh(str(file)).translate(FAR_BEHIND))


def _huge_png(scene: Path) -> None:
    """view_000.png rewritten as a 74-byte PNG whose header claims 40000x40000 RGB pixels (4.8 GB)."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    header = struct.pack(">IIBBBBB", 40_000, 40_000, 8, 2, 0, 0, 0)
    png = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(bytes(1000))) + chunk(b"IEND", b"")
    (scene / "images" / "view_000.png").write_bytes(png)


def _put(file: Path, text: str = "mine\n") -> None:
    file.parent.mkdir(parents=True, exist_ok=True)
    file.write_text(text)


EMPTY_MESH = ("ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\nproperty float z\n"
              "element face 0\nproperty list uchar int vertex_indices\nend_header\n")
SUN = [0.4, -0.3, 0.8]
CLICKS = {"view": "view_000", "shadow_px": [WIDTH, 10], "caster_px": [32, 20]}
SUN_TIME = {"datetime": SOLSTICE_NOON, "latitude": 200.0, "longitude": 0.0, "north": [0, 1, 0]}
PROXY, SCENE_JSON = "{scene}/proxy.ply", "{scene}/scene.json"
CAMERAS_TXT, IMAGES_TXT = "{scene}/sparse/cameras.txt", "{scene}/sparse/images.txt"
IMAGE0, IMAGE1, PNG0 = f"{{scene}}/images/{VIEW0}", f"{{scene}}/images/{VIEW1}", "{scene}/images/view_000.png"

FAULTS = {
    # proxy.ply: corrupt, hostile sizes, cut by an interrupted write, wrong geometry
    "face index beyond the vertices": Fault(lambda s: _ascii_proxy(s, extra_face=[0, 1, 10**9]), PROXY,
                                            "corrupt face indices"),
    "negative face index": Fault(lambda s: _ascii_proxy(s, extra_face=[0, 1, -5]), PROXY, "corrupt face indices"),
    "PLY header claims billions of vertices": Fault(lambda s: _ascii_proxy(s, vertex_count=4_000_000_000), PROXY,
                                                    "header claims 4000000000"),
    "PLY cut inside its header": Fault(_truncate("proxy.ply", keep_bytes=60), PROXY, "malformed PLY header"),
    "binary PLY cut in its body": Fault(_truncate("proxy.ply"), PROXY, "truncated or corrupt"),
    "proxy.ply of 0 bytes": Fault(_truncate("proxy.ply", keep_bytes=0), PROXY, "empty"),
    "text file named proxy.ply": Fault(lambda s: (s / "proxy.ply").write_text("solid mesh\n"), PROXY,
                                       "not a PLY file"),
    "empty mesh (0 vertices, 0 faces)": Fault(lambda s: (s / "proxy.ply").write_text(EMPTY_MESH), PROXY, "empty"),
    "NaN proxy vertex": Fault(lambda s: _ascii_proxy(s, nan_vertex=True), PROXY, "finite"),
    "proxy behind every camera": Fault(_proxy_behind_cameras, PROXY, "in front of no camera"),
    # sparse/images.txt
    "zero quaternion": Fault(lambda s: _edit_pose_line(s, lambda f: [f[0], "0", "0", "0", "0", *f[5:]]), IMAGES_TXT,
                             "zero quaternion"),
    "NaN translation": Fault(lambda s: _edit_pose_line(s, lambda f: [*f[:5], "nan", *f[6:]]), IMAGES_TXT,
                             "non-finite pose"),
    "pose that is not numbers": Fault(lambda s: _edit_pose_line(s, lambda f: [f[0], "x", *f[2:]]), IMAGES_TXT,
                                      "must be numbers"),
    "image listed twice": Fault(_duplicate_first_image, IMAGES_TXT, "given twice"),
    "image of a missing camera": Fault(lambda s: _edit_pose_line(s, lambda f: [*f[:8], "77", *f[9:]]), IMAGES_TXT,
                                       "77"),
    # sparse/cameras.txt
    "unknown camera model": Fault(lambda s: _set_camera_model(s, "FANCY_LENS", [57.6, 57.6, 32.0, 24.0]), CAMERAS_TXT,
                                  "unknown or unsupported camera model 'FANCY_LENS'"),
    "camera with a parameter missing": Fault(lambda s: _set_camera_model(s, "PINHOLE", [57.6, 57.6, 32.0]),
                                             CAMERAS_TXT, "param"),
    "NaN camera parameter": Fault(lambda s: _edit_camera_line(s, lambda f: [*f[:4], "nan", *f[5:]]), CAMERAS_TXT,
                                  "finite"),
    "camera of width 0": Fault(lambda s: _edit_camera_line(s, lambda f: [f[0], f[1], "0", *f[3:]]),
                               "{scene}/sparse: image 'view_000.exr'", "width must be a positive integer"),
    # images/
    "all-black view": Fault(_blacken, IMAGE0, "no valid pixel above 0"),
    "every view black": Fault(lambda s: _blacken(s, (VIEW0, VIEW1)), IMAGE0, "no valid pixel above 0"),
    "grey images (no sky to fit)": Fault(_greyen, "views", "too few sky texels"),
    "image size not its camera's": Fault(
        lambda s: write_image(s / "images" / VIEW1, np.full((HEIGHT // 2, WIDTH // 2, 3), 0.5, np.float32)),
        IMAGE1, f"{WIDTH // 2}x{HEIGHT // 2} pixels but its COLMAP camera is {WIDTH}x{HEIGHT}"),
    "truncated EXR": Fault(_truncate(f"images/{VIEW0}"), IMAGE0, "truncated"),
    "truncated PNG": Fault(_truncate("images/view_000.png"), PNG0, "truncated", ext=".png"),
    "PNG header claims 40000x40000 pixels": Fault(_huge_png, PNG0, "unreadable image", ext=".png"),
    "image with 5 channels": Fault(_five_channel_image, IMAGE0, "5 channels"),
    "text file named .png": Fault(lambda s: (s / "images" / "view_000.png").write_text("not a picture\n"), PNG0,
                                  "unreadable image", ext=".png"),
    # missing parts
    "scene folder absent": Fault(_remove(""), "{scene}", "scene folder not found"),
    "images/ missing": Fault(_remove("images"), "{scene}/images", "missing"),
    "sparse/ missing": Fault(_remove("sparse"), "{scene}/sparse", "missing"),
    "proxy.ply missing": Fault(_remove("proxy.ply"), PROXY, "missing"),
    "scene.json missing": Fault(_remove("scene.json"), SCENE_JSON, "missing"),
    # scene.json: not JSON, wrong types, wrong values
    "scene.json not JSON": Fault(_scene_json('{"sun_direction": [0.4, -0.3, 0.8]'), SCENE_JSON, "not valid JSON"),
    "scene.json a list": Fault(_scene_json([SUN]), SCENE_JSON, "must hold a JSON object"),
    "up not a 3-vector": Fault(_scene_json({"up": [0, 1], "sun_direction": SUN}), SCENE_JSON,
                               "up must be a list of 3 numbers"),
    "up zero": Fault(_scene_json({"up": [0, 0, 0], "sun_direction": SUN}), SCENE_JSON, "up must be a non-zero vector"),
    "sun_direction NaN": Fault(_scene_json({"sun_direction": [0.4, math.nan, 0.8]}), SCENE_JSON,
                               "sun_direction must be finite"),
    "sun below the horizon": Fault(_scene_json({"sun_direction": [0.4, -0.3, -0.2]}), SCENE_JSON, "below the horizon"),
    "sun given two ways": Fault(_scene_json({"sun_direction": SUN, "sun_clicks": CLICKS}), SCENE_JSON,
                                "exactly one way"),
    "sun under an unknown key": Fault(_scene_json({"sun": SUN}), SCENE_JSON, "found none"),
    "sun_clicks not an object": Fault(_scene_json({"sun_clicks": [3, 4]}), SCENE_JSON, "sun_clicks must be an object"),
    "sun click outside the image": Fault(_scene_json({"sun_clicks": CLICKS}), SCENE_JSON,
                                         "sun_clicks.shadow_px [64.0, 10.0] lies outside"),
    "sun_time latitude 200": Fault(_scene_json({"sun_time": SUN_TIME}), SCENE_JSON, "sun_time.latitude"),
    # OUT: unwritable, inside the scene, foreign; a previous result survives a failed run
    "OUT is a file": Fault(lambda s: _put(s.parent / "out"), "{out}", "is not a folder"),
    "OUT under a file": Fault(lambda s: _put(s.parent / "file"), "{tmp}/file exists", "is not a folder",
                              argv=("decompose", "{scene}", "{tmp}/file/out", "--quiet")),
    "OUT inside the scene": Fault(_nothing, "{scene}/out", "inside the scene folder",
                                  argv=("decompose", "{scene}", "{scene}/out", "--quiet")),
    "OUT a foreign non-empty folder": Fault(lambda s: _put(s.parent / "out" / "notes.txt"), "{out}",
                                            "not written by mvintrinsic"),
    "OUT a previous result, scene broken": Fault(_truncate(f"images/{VIEW0}"), IMAGE0, "truncated",
                                                 argv=("decompose", "{scene}", "{result}", "--quiet")),
    # arguments (the messages name the load_scene argument)
    "--views names an unknown view": Fault(_nothing, "views: no view named 'nope'", "view_000",
                                           argv=(*DECOMPOSE, "--views", "nope")),
    "--max-size 0": Fault(_nothing, "max_size", "got 0", argv=(*DECOMPOSE, "--max-size", "0")),
    "--max-size negative": Fault(_nothing, "max_size", "got -5", argv=(*DECOMPOSE, "--max-size=-5")),
    "--config not JSON": Fault(lambda s: _put(s.parent / "config.json", "{"), "--config {tmp}/config.json",
                               "not valid JSON", argv=(*DECOMPOSE, "--config", "{tmp}/config.json")),
    # relight: bad arguments, a RESULT absent or left incomplete by an interrupted write
    "relight --elevation below 0": Fault(_nothing, "elevation -10", "above the horizon",
                                         argv=(*RELIGHT[:-3], "--elevation=-10", "--quiet")),
    "relight --sequence of 1 step": Fault(_nothing, "--sequence STEPS", ">= 2",
                                          argv=(*RELIGHT[:4], "--sequence", "0", "90", "1", "--elevation", "40")),
    "relight RESULT absent": Fault(_nothing, "{tmp}/no_such_result/lighting.json", "not found",
                                   argv=(*RELIGHT[:2], "{tmp}/no_such_result", *RELIGHT[3:])),
    "relight RESULT without a layer": Fault(_remove("../result/views/view_000/reflectance.exr"),
                                            "{result}/views/view_000/reflectance.exr", "not found", argv=RELIGHT),
    "relight RESULT without lighting.json": Fault(_remove("../result/lighting.json"), "{result}/lighting.json",
                                                  "not found", argv=RELIGHT),
    "relight RESULT with a cut layer": Fault(_truncate("../result/views/view_001/sky_shading.exr"),
                                             "{result}/views/view_001/sky_shading.exr", "lighting.json says",
                                             argv=RELIGHT),
}

FAULT_CASES = list(FAULTS)


@pytest.fixture(scope="module")
def fault_scenes(tmp_path_factory) -> dict[str, Path]:
    """The valid scenes the cases copy and break: one with EXR images, one with PNG images."""
    root = tmp_path_factory.mktemp("fault_scenes")
    return {ext: make_scene(root / ext[1:], ext=ext) for ext in (".exr", ".png")}


@pytest.fixture(scope="module")
def fault_result(fault_scenes, tmp_path_factory) -> Path:
    """A result folder decomposed from the EXR scene by the CLI (its random images show no shadow)."""
    out = tmp_path_factory.mktemp("fault_result") / "result"
    run = subprocess.run([sys.executable, "-m", "mvintrinsic.cli", "decompose", str(fault_scenes[".exr"]), str(out),
                          "--quiet", "--allow-missing-sun"], capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-2000:]
    return out


def _tree(root: Path) -> dict[str, str]:
    """sha256 of every file and a mark for every folder under ``root`` (hidden ones included)."""
    tree = {}
    for folder, dirs, files in os.walk(root):
        here = Path(folder)
        for name in dirs:
            tree[(here / name).relative_to(root).as_posix()] = "folder"
        for name in files:
            tree[(here / name).relative_to(root).as_posix()] = hashlib.sha256((here / name).read_bytes()).hexdigest()
    return tree


@pytest.mark.parametrize("fault", FAULT_CASES)
def test_fault_table(tmp_path, fault, fault_scenes, request):
    """Each hostile input: exit 2, one line naming the culprit, the inputs byte-identical, no output."""
    case = FAULTS[fault]
    tmp = tmp_path.resolve()
    places = {"tmp": tmp, "scene": tmp / "scene", "out": tmp / "out", "result": tmp / "result"}
    shutil.copytree(fault_scenes[case.ext], places["scene"])
    if "{result}" in " ".join(case.argv):
        shutil.copytree(request.getfixturevalue("fault_result"), places["result"])
    case.damage(places["scene"])
    argv = [arg.format(**places) for arg in case.argv]
    before = _tree(tmp)

    run = subprocess.run([sys.executable, "-m", "mvintrinsic.cli", *argv], capture_output=True, text=True,
                         timeout=600, cwd=tmp)
    assert run.returncode == 2, run.stderr[-2000:]
    assert "Traceback" not in run.stderr, run.stderr[-2000:]
    lines = run.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"mvintrinsic {argv[0]}: error: "), run.stderr[-2000:]
    assert case.culprit.format(**places) in lines[0] and case.message in lines[0], lines[0]
    after = _tree(tmp)
    inputs = [path for path in before if path.split("/")[0] in ("scene", "result")]
    assert {p: after.get(p) for p in inputs} == {p: before[p] for p in inputs}, "an input was modified"
    assert not [path for path in after if ".partial-" in path], "a partial result was left"
    assert after == before, "something was written"
