"""Shared fixtures: a tiny but complete scene folder written from scratch, and the shared dataset."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import mvintrinsic  # noqa: F401  (loads libusb before open3d)

SHARED = Path(__file__).resolve().parents[2] / "shared"
DEV_COURTYARD = SHARED / "datasets" / "dev_courtyard"


def look_at(center: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """World-to-camera (R, t) of a camera at ``center`` looking at ``target`` (x right, y down)."""
    forward = np.asarray(target, float) - center
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    rotation = np.stack([right, down, forward])
    return rotation, -rotation @ center


def ground_and_box_mesh():
    """A 10 m ground square (subdivided) and a 2 m box standing on it: (vertices, triangles)."""
    import open3d as o3d

    ground = o3d.geometry.TriangleMesh.create_box(10.0, 10.0, 0.01).translate((-5.0, -5.0, -0.01))
    box = o3d.geometry.TriangleMesh.create_box(2.0, 2.0, 2.0).translate((-1.0, -1.0, 0.0))
    mesh = (ground + box).subdivide_midpoint(2)
    mesh.compute_vertex_normals()
    return mesh


def make_scene(
    root: Path,
    *,
    n_views: int = 2,
    size: tuple[int, int] = (64, 48),
    ext: str = ".exr",
    model: str = "PINHOLE",
    sun: dict | None = None,
    seed: int = 0,
) -> Path:
    """Write a complete, valid scene folder under ``root`` and return its path."""
    import open3d as o3d

    from mvintrinsic.camera import Camera
    from mvintrinsic.io import write_colmap_text, write_image

    rng = np.random.default_rng(seed)
    root.mkdir(parents=True, exist_ok=True)
    w, h = size
    f = 0.9 * w
    params = {
        "PINHOLE": [f, f, w / 2, h / 2],
        "SIMPLE_PINHOLE": [f, w / 2, h / 2],
        "SIMPLE_RADIAL": [f, w / 2, h / 2, 0.01],
        "RADIAL": [f, w / 2, h / 2, 0.01, -0.002],
        "OPENCV": [f, f * 1.01, w / 2, h / 2, 0.01, -0.002, 0.001, -0.001],
    }[model]
    cameras = {}
    for i in range(n_views):
        angle = -np.pi / 2 + 0.25 * (i - (n_views - 1) / 2)
        center = np.array([8.0 * np.cos(angle), 8.0 * np.sin(angle), 2.5])
        rotation, translation = look_at(center, np.array([0.0, 0.0, 0.5]))
        name = f"view_{i:03d}{ext}"
        cameras[name] = Camera(model, w, h, params, rotation, translation)
        image = rng.uniform(0.05, 0.9, size=(h, w, 3)).astype(np.float32)
        if ext == ".exr":
            write_image(root / "images" / name, image)
        else:
            write_image(root / "images" / name, np.round(image * 255), dtype="uint8")
    write_colmap_text(root / "sparse", cameras)
    o3d.io.write_triangle_mesh(str(root / "proxy.ply"), ground_and_box_mesh())
    settings = {"up": [0, 0, 1]}
    settings.update(sun if sun is not None else {"sun_direction": [0.4, -0.3, 0.8]})
    (root / "scene.json").write_text(json.dumps(settings))
    return root


@pytest.fixture
def scene_dir(tmp_path: Path) -> Path:
    """A valid two-view scene folder (64x48 EXR images, ground + box mesh proxy)."""
    return make_scene(tmp_path / "scene")


@pytest.fixture(scope="session")
def dev_courtyard() -> Path:
    """The shared dataset made by another tool; skips with a message when ../shared is absent."""
    if not (DEV_COURTYARD / "scene.json").is_file():
        pytest.skip(f"shared dataset not found at {DEV_COURTYARD} (needs ../shared beside the checkout)")
    return DEV_COURTYARD
