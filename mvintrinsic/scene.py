"""The input data model: views, the geometric proxy, the sun and the scene that holds them.

These frozen dataclasses are what :func:`mvintrinsic.io.load_scene` returns and what every stage
of the pipeline reads. They validate themselves on construction, hold read-only arrays and are
never mutated; functions return new objects. Frames and units are those of
``docs/conventions.md``: world frame right-handed in metres, images linear scene-referred RGB
(Rec.709 primaries) of shape ``(H, W, 3)`` float32 with row 0 at the top.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ._validation import as_array, as_unit_vector, describe
from .camera import Camera

__all__ = ["SUN_ANGULAR_RADIUS", "Proxy", "Scene", "Sun", "View", "valid_pixels"]

#: Mean angular radius of the solar disc seen from the Earth, radians (0.2666 degrees).
SUN_ANGULAR_RADIUS = math.radians(0.5332 / 2)


def valid_pixels(image: np.ndarray, *, saturation: float | None = None) -> np.ndarray:
    """Mask of the pixels whose value can be trusted.

    Parameters
    ----------
    image : (H, W, 3) float array
        Linear RGB.
    saturation : float, optional
        Linear value at which the sensor clipped (1.0 for images decoded from 8- or 16-bit
        files). A pixel with any channel at or above it is excluded. ``None`` (float images such
        as EXR): no saturation test.

    Returns
    -------
    (H, W) bool
        True where all three channels are finite, non-negative and below ``saturation``.
    """
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"image must have shape (H, W, 3), got shape {image.shape}")
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(image).all(axis=2) & (image >= 0).all(axis=2)
        if saturation is not None:
            ok &= (image < saturation).all(axis=2)
    return ok


@dataclass(frozen=True, eq=False)
class View:
    """One photograph with its camera.

    Parameters
    ----------
    stem : str
        Name of the view: the image file name without extension (``images/<stem>.<ext>``).
    image : (H, W, 3) float32
        Linear scene-referred RGB, row 0 at the top. Pixels outside ``mask`` may hold anything,
        including NaN.
    camera : Camera
        Calibration and pose; ``(camera.height, camera.width) == (H, W)``.
    mask : (H, W) bool, optional
        Valid pixels: finite, non-negative, not saturated. Defaults to
        ``valid_pixels(image)`` (no saturation test). Must exclude every non-finite pixel.
    """

    stem: str
    image: np.ndarray
    camera: Camera
    mask: np.ndarray | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.stem, str) or not self.stem:
            raise ValueError(f"stem must be a non-empty string, got {describe(self.stem)}")
        if not isinstance(self.camera, Camera):
            raise TypeError(f"camera must be a Camera, got {describe(self.camera)}")
        h, w = self.camera.shape
        image = as_array(self.image, "image", shape=(None, None, 3), dtype=np.float32, finite=False)
        if image.shape[:2] != (h, w):
            raise ValueError(
                f"image of view {self.stem!r} is {image.shape[1]}x{image.shape[0]} pixels but its camera is {w}x{h}"
            )
        if self.mask is None:
            mask = valid_pixels(image)
            mask.flags.writeable = False
        else:
            mask = as_array(self.mask, "mask", shape=(h, w), dtype=bool)
            if not np.isfinite(image[mask]).all():
                raise ValueError(f"mask of view {self.stem!r} must exclude the non-finite pixels of image")
        object.__setattr__(self, "image", image)
        object.__setattr__(self, "mask", mask)

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)``."""
        return self.camera.shape

    def __repr__(self) -> str:
        return f"View({self.stem!r}, {self.shape[1]}x{self.shape[0]}, valid={self.mask.mean():.1%})"


@dataclass(frozen=True, eq=False)
class Proxy:
    """The reconstructed (imperfect) geometry of the scene, in the world frame.

    Parameters
    ----------
    vertices : (N, 3) float64
        Point positions, metres.
    normals : (N, 3) float64
        Unit outward normals (pointing to the side the cameras see).
    triangles : (M, 3) int64, optional
        Vertex indices of a triangle mesh; ``None`` for a point cloud.
    colors : (N, 3) float32, optional
        Linear RGB per vertex, if the reconstruction provides it.

    Raises
    ------
    ValueError
        If the proxy is empty or degenerate: fewer than 3 points, all points on a line, or a mesh
        whose triangles all have zero area.
    """

    vertices: np.ndarray
    normals: np.ndarray
    triangles: np.ndarray | None = None
    colors: np.ndarray | None = None

    def __post_init__(self) -> None:
        vertices = as_array(self.vertices, "vertices", shape=(None, 3), dtype=np.float64)
        n = len(vertices)
        if n < 3:
            raise ValueError(f"vertices: the proxy is empty or degenerate, it has {n} points (need at least 3)")
        normals = as_array(self.normals, "normals", shape=(n, 3), dtype=np.float64)
        lengths = np.linalg.norm(normals, axis=1)
        if np.abs(lengths - 1.0).max() > 1e-3:
            raise ValueError("normals must be unit vectors (one per vertex)")
        centred = vertices - vertices.mean(axis=0)
        singular = np.linalg.svd(centred[:: max(1, n // 100_000)], compute_uv=False)
        if singular[1] <= 1e-9 * max(singular[0], 1e-300):
            raise ValueError("vertices: the proxy is degenerate, all its points lie on a line or at one point")
        triangles = None
        if self.triangles is not None:
            triangles = as_array(self.triangles, "triangles", shape=(None, 3), dtype=np.int64)
            if len(triangles) == 0:
                triangles = None
            elif triangles.min() < 0 or triangles.max() >= n:
                raise ValueError(f"triangles index vertices outside [0, {n}), got range [{triangles.min()}, {triangles.max()}]")
            else:
                a, b, c = (vertices[triangles[:, i]] for i in range(3))
                if not np.any(np.linalg.norm(np.cross(b - a, c - a), axis=1) > 1e-12):
                    raise ValueError("triangles: the proxy mesh is degenerate, every triangle has zero area")
        colors = None
        if self.colors is not None:
            colors = as_array(self.colors, "colors", shape=(n, 3), dtype=np.float32)
        object.__setattr__(self, "vertices", vertices)
        object.__setattr__(self, "normals", normals)
        object.__setattr__(self, "triangles", triangles)
        object.__setattr__(self, "colors", colors)

    @property
    def is_mesh(self) -> bool:
        """True for a triangle mesh, False for a point cloud."""
        return self.triangles is not None

    @property
    def bounds(self) -> np.ndarray:
        """Axis-aligned bounding box ``[[xmin, ymin, zmin], [xmax, ymax, zmax]]``, metres."""
        return np.stack([self.vertices.min(axis=0), self.vertices.max(axis=0)])

    def __repr__(self) -> str:
        kind = f"mesh, {len(self.triangles)} triangles" if self.is_mesh else "point cloud"
        return f"Proxy({len(self.vertices)} vertices, {kind})"


@dataclass(frozen=True, eq=False)
class Sun:
    """The sun as seen from the scene.

    Parameters
    ----------
    direction : (3,) float64
        Unit vector **toward** the sun in the world frame. Any non-zero finite vector is accepted
        and normalised.
    angular_radius : float, optional
        Angular radius of the solar disc, radians. Defaults to :data:`SUN_ANGULAR_RADIUS`.
    """

    direction: np.ndarray
    angular_radius: float = SUN_ANGULAR_RADIUS

    def __post_init__(self) -> None:
        object.__setattr__(self, "direction", as_unit_vector(self.direction, "direction"))
        radius = float(self.angular_radius)
        if not (0.0 <= radius < math.pi / 4):
            raise ValueError(f"angular_radius must be in [0, pi/4) radians, got {self.angular_radius!r}")
        object.__setattr__(self, "angular_radius", radius)

    def elevation(self, up: np.ndarray) -> float:
        """Angle of the sun above the plane normal to ``up``, radians."""
        up = np.asarray(up, dtype=np.float64)
        return float(np.arcsin(np.clip(self.direction @ (up / np.linalg.norm(up)), -1.0, 1.0)))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Sun):
            return NotImplemented
        return bool(np.array_equal(self.direction, other.direction)) and self.angular_radius == other.angular_radius

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        return f"Sun(direction={np.round(self.direction, 4).tolist()}, angular_radius={self.angular_radius:.5f})"


@dataclass(frozen=True, eq=False)
class Scene:
    """Everything the decomposition needs: photos, proxy, sun and the up direction.

    Parameters
    ----------
    views : sequence of View
        At least one view; stems must be unique. Stored as a tuple.
    proxy : Proxy
        Reconstructed geometry in the same world frame as the cameras.
    sun : Sun
        Sun direction; it must be above the horizon (``sun.direction @ up > 0``).
    up : (3,) float64, optional
        Unit world up vector (default ``+Z``).
    source : pathlib.Path, optional
        Folder the scene was loaded from, if any (metadata; writers refuse to write inside it).
    """

    views: tuple[View, ...]
    proxy: Proxy
    sun: Sun
    up: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    source: Path | None = None

    def __post_init__(self) -> None:
        if isinstance(self.views, View) or not isinstance(self.views, Sequence):
            raise TypeError(f"views must be a sequence of View, got {describe(self.views)}")
        views = tuple(self.views)
        if not views:
            raise ValueError("views must hold at least one View, got none")
        for i, view in enumerate(views):
            if not isinstance(view, View):
                raise TypeError(f"views[{i}] must be a View, got {describe(view)}")
        stems = [v.stem for v in views]
        if len(set(stems)) != len(stems):
            dupes = sorted({s for s in stems if stems.count(s) > 1})
            raise ValueError(f"views: stems must be unique, repeated: {dupes}")
        if not isinstance(self.proxy, Proxy):
            raise TypeError(f"proxy must be a Proxy, got {describe(self.proxy)}")
        if not isinstance(self.sun, Sun):
            raise TypeError(f"sun must be a Sun, got {describe(self.sun)}")
        up = as_unit_vector(self.up, "up")
        elevation = self.sun.elevation(up)
        if elevation <= 0:
            raise ValueError(
                f"sun: the sun is {math.degrees(-elevation):.2f} degrees below the horizon "
                f"(direction {np.round(self.sun.direction, 4).tolist()}, up {up.tolist()})"
            )
        source = None if self.source is None else Path(self.source)
        object.__setattr__(self, "views", views)
        object.__setattr__(self, "up", up)
        object.__setattr__(self, "source", source)

    @property
    def stems(self) -> tuple[str, ...]:
        """View names in order."""
        return tuple(v.stem for v in self.views)

    def view(self, stem: str) -> View:
        """The view called ``stem``.

        Raises
        ------
        KeyError
            If no view has that stem; the message lists the available ones.
        """
        for v in self.views:
            if v.stem == stem:
                return v
        raise KeyError(f"no view named {stem!r}; views are {list(self.stems)}")

    def __repr__(self) -> str:
        return (
            f"Scene({len(self.views)} views, {self.proxy!r}, {self.sun!r}, up={self.up.tolist()}"
            + (f", source='{self.source}')" if self.source else ")")
        )
