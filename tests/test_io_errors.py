"""Malformed scene folders: every case raises the right error naming the offending file or field.

Each test builds a valid scene (``scene_dir`` / ``make_scene`` from conftest), breaks exactly one
thing and loads it with :func:`mvintrinsic.io.load_scene`. Errors of the folder are
:class:`~mvintrinsic.io.SceneError` (a ValueError) whose message names the file or field and whose
``path`` is the offending file; bad Python arguments are plain ValueError/TypeError naming the
argument. A few positive tests check the two indirect sun forms (clicks, time and place).
"""

from __future__ import annotations

import json
import math
import re
import shutil
from pathlib import Path

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


def test_colmap_model_not_supported_text(scene_dir):
    _set_camera_model(scene_dir, "OPENCV_FISHEYE", FISHEYE_PARAMS)
    file = scene_dir / "sparse" / "cameras.txt"
    with pytest.raises(SceneError, match=r"cameras\.txt: .*unsupported camera model 'OPENCV_FISHEYE'") as exc:
        load_scene(scene_dir)
    assert exc.value.path == file


def test_colmap_model_not_supported_binary(scene_dir):
    import pycolmap

    sparse = scene_dir / "sparse"
    _set_camera_model(scene_dir, "OPENCV_FISHEYE", FISHEYE_PARAMS)
    pycolmap.Reconstruction(str(sparse)).write_binary(str(sparse))
    for name in ("cameras", "images", "points3D"):
        (sparse / f"{name}.txt").unlink()
    with pytest.raises(SceneError, match=r"cameras\.bin: .*unsupported camera model 'OPENCV_FISHEYE'") as exc:
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
def _ascii_proxy(scene: Path, *, extra_face=None, vertex_count=None) -> None:
    """Rewrite proxy.ply as ASCII, optionally with one more face or a lying vertex count."""
    proxy = mio.read_proxy(scene / "proxy.ply")
    faces = proxy.triangles if extra_face is None else np.vstack([proxy.triangles, [extra_face]])
    count = len(proxy.vertices) if vertex_count is None else vertex_count
    header = ["ply", "format ascii 1.0", f"element vertex {count}", "property float x", "property float y",
              "property float z", f"element face {len(faces)}", "property list uchar int vertex_indices", "end_header"]
    body = [" ".join(f"{x:.6f}" for x in v) for v in proxy.vertices] + [f"3 {a} {b} {c}" for a, b, c in faces]
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


FAULTS = {
    "face index beyond the vertices": (lambda s: _ascii_proxy(s, extra_face=[0, 1, 10**9]), "proxy.ply",
                                       "corrupt face indices"),
    "negative face index": (lambda s: _ascii_proxy(s, extra_face=[0, 1, -5]), "proxy.ply", "corrupt face indices"),
    "PLY header claims billions of vertices": (lambda s: _ascii_proxy(s, vertex_count=4_000_000_000), "proxy.ply",
                                               "header claims 4000000000"),
    "PLY cut inside its header": (lambda s: (s / "proxy.ply").write_bytes((s / "proxy.ply").read_bytes()[:60]),
                                  "proxy.ply", "malformed PLY header"),
    "zero quaternion": (lambda s: _edit_pose_line(s, lambda f: [f[0], "0", "0", "0", "0", *f[5:]]), "images.txt",
                        "zero quaternion"),
    "NaN translation": (lambda s: _edit_pose_line(s, lambda f: [*f[:5], "nan", *f[6:]]), "images.txt",
                        "non-finite pose"),
    "pose that is not numbers": (lambda s: _edit_pose_line(s, lambda f: [f[0], "x", *f[2:]]), "images.txt",
                                 "must be numbers"),
    "image listed twice": (_duplicate_first_image, "images.txt", "given twice"),
    "all-black view": (_blacken, VIEW0, "no valid pixel above 0"),
    "every view black": (lambda s: _blacken(s, (VIEW0, VIEW1)), VIEW0, "no valid pixel above 0"),
    "grey images (no sky to fit)": (_greyen, "", "too few sky texels"),
}


@pytest.mark.parametrize("fault", list(FAULTS))
def test_fault_table(tmp_path, fault):
    """Each hostile scene: exit 2, one line naming the culprit, scene byte-identical, no output."""
    import hashlib
    import subprocess
    import sys

    scene = make_scene(tmp_path / "scene")
    damage, culprit, message = FAULTS[fault]
    damage(scene)

    def digest() -> str:
        h = hashlib.sha256()
        for p in sorted(scene.rglob("*")):
            if p.is_file():
                h.update(p.relative_to(scene).as_posix().encode() + p.read_bytes())
        return h.hexdigest()

    before = digest()
    out = tmp_path / "out"
    run = subprocess.run([sys.executable, "-m", "mvintrinsic.cli", "decompose", str(scene), str(out), "--quiet"],
                         capture_output=True, text=True, timeout=600)
    lines = [line for line in run.stderr.splitlines() if line.startswith("mvintrinsic decompose: error:")]
    assert run.returncode == 2, run.stderr[-2000:]
    assert "Traceback" not in run.stderr and len(lines) == 1
    assert culprit in lines[0] and message in lines[0]
    assert digest() == before
    assert not out.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["scene"]
