"""Calibrated cameras in COLMAP's conventions.

A :class:`Camera` is one COLMAP camera (intrinsics and lens distortion) together with the pose of
the image taken with it. Everything follows COLMAP exactly, so a model written by COLMAP (or read
by pycolmap) projects here to the same pixels:

* **Pose**: world-to-camera rotation ``R`` and translation ``t``: ``x_cam = R @ x_world + t``.
  The camera centre in the world frame is ``-R.T @ t``.
* **Camera axes**: x to the right, y down, z forward (the viewing direction).
* **Pixel coordinates** are continuous, ``(u, v)`` = (column, row), with the *top-left corner* of
  the image at ``(0, 0)``: the centre of the pixel in column ``i``, row ``j`` is at
  ``(i + 0.5, j + 0.5)`` (COLMAP's convention).
* **Models**: every perspective camera model of COLMAP (:data:`CAMERA_MODELS`: the pinhole and
  OpenCV families, the division, FOV and unified (EUCM) models and the fisheye models), with the
  parameters in the order of COLMAP's ``cameras.txt``. Projection and unprojection are COLMAP's own
  code, through pycolmap (``Camera.img_from_cam`` / ``cam_from_img``; the iterative undistortion
  of distorted models included), so that no lens model is written twice; the equirectangular
  model, which has no focal plane, is not supported.

See ``docs/conventions.md``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
import pycolmap

from ._validation import as_array, describe

__all__ = ["CAMERA_MODELS", "Camera"]

#: COLMAP models without a focal plane (not supported).
_NOT_PERSPECTIVE = ("EQUIRECTANGULAR", "INVALID")


def _model_parameters() -> dict[str, tuple[str, ...]]:
    names = sorted(m for m in pycolmap.CameraModelId.__members__ if m not in _NOT_PERSPECTIVE)
    out = {}
    for name in names:
        camera = pycolmap.Camera.create_from_model_name(1, name, 1.0, 1, 1)
        out[name] = tuple(p.strip() for p in camera.params_info.split(","))
    return out


#: Supported COLMAP camera models and the names of their parameters, in COLMAP's order (every
#: perspective model of the installed COLMAP, read from pycolmap).
CAMERA_MODELS: dict[str, tuple[str, ...]] = _model_parameters()

#: Single-focal models and their two-focal twins: a view resampled with different horizontal and
#: vertical scales needs ``fx != fy`` (:meth:`Camera.scaled`), the extra parameters padded with 0.
_TWO_FOCAL = {"SIMPLE_PINHOLE": "PINHOLE", "SIMPLE_RADIAL": "OPENCV", "RADIAL": "OPENCV",
              "SIMPLE_RADIAL_FISHEYE": "OPENCV_FISHEYE", "RADIAL_FISHEYE": "OPENCV_FISHEYE",
              "SIMPLE_DIVISION": "DIVISION", "SIMPLE_FISHEYE": "FISHEYE"}


@dataclass(frozen=True, eq=False)
class Camera:
    """A calibrated, posed camera (one image of a COLMAP model).

    Parameters
    ----------
    model : str
        COLMAP camera model name, one of :data:`CAMERA_MODELS`.
    width, height : int
        Image size in pixels.
    params : (P,) float64
        Intrinsic parameters in COLMAP's order for ``model`` (focal lengths and principal point in
        pixels; distortion coefficients dimensionless).
    rotation : (3, 3) float64
        World-to-camera rotation ``R`` (proper rotation, ``det = +1``).
    translation : (3,) float64
        World-to-camera translation ``t`` in metres: ``x_cam = R @ x_world + t``.

    Notes
    -----
    Pixel coordinates are continuous ``(u, v)`` = (column, row) with the top-left image corner at
    ``(0, 0)`` and pixel centres at integer + 0.5, as in COLMAP.
    Instances are immutable; arrays are read-only copies of the inputs.
    """

    model: str
    width: int
    height: int
    params: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray
    _colmap: pycolmap.Camera = field(init=False, repr=False)
    _pinhole: bool = field(init=False, repr=False, default=False)  # not is_distorted: K alone projects

    #: Tolerance on ``R.T @ R - I`` accepted for the rotation.
    ROTATION_TOL: ClassVar[float] = 1e-6

    def __post_init__(self) -> None:
        if not isinstance(self.model, str) or self.model not in CAMERA_MODELS:
            raise ValueError(
                f"model must be one of {sorted(CAMERA_MODELS)}, got {describe(self.model)}"
            )
        for name in ("width", "height"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise ValueError(f"{name} must be a positive integer, got {describe(value)}")
            object.__setattr__(self, name, int(value))
        n_params = len(CAMERA_MODELS[self.model])
        params = as_array(self.params, "params", shape=(n_params,), dtype=np.float64)
        rotation = as_array(self.rotation, "rotation", shape=(3, 3), dtype=np.float64)
        translation = as_array(self.translation, "translation", shape=(3,), dtype=np.float64)
        if np.abs(rotation.T @ rotation - np.eye(3)).max() > self.ROTATION_TOL or np.linalg.det(rotation) < 0:
            raise ValueError("rotation must be a proper rotation matrix (R.T @ R = I, det R = +1)")
        object.__setattr__(self, "params", params)
        object.__setattr__(self, "rotation", rotation)
        object.__setattr__(self, "translation", translation)
        colmap = pycolmap.Camera(model=self.model, width=self.width, height=self.height, params=params.tolist())
        object.__setattr__(self, "_colmap", colmap)
        fx, fy = self.focal
        if not (fx > 0 and fy > 0):
            raise ValueError(f"params: focal lengths must be positive, got {params.tolist()}")
        object.__setattr__(self, "_pinhole", not self.is_distorted)

    # -- intrinsics -----------------------------------------------------------------------------
    @property
    def focal(self) -> tuple[float, float]:
        """``(fx, fy)`` in pixels."""
        return float(self._colmap.focal_length_x), float(self._colmap.focal_length_y)

    @property
    def principal_point(self) -> tuple[float, float]:
        """``(cx, cy)`` in pixels (continuous coordinates, top-left corner at the origin)."""
        return float(self._colmap.principal_point_x), float(self._colmap.principal_point_y)

    @property
    def distortion(self) -> np.ndarray:
        """The model's distortion parameters (those after the focal lengths and principal point), (P,)."""
        return self.params[list(self._colmap.extra_params_idxs())]

    @property
    def is_distorted(self) -> bool:
        """Whether pixels differ from the pinhole projection ``K (x, y, 1)`` with the same ``K``.

        Tested on a grid of normalised coordinates over the image (10^-9 px): the fisheye models
        are distorted even with zero coefficients, the OpenCV family only with non-zero ones.
        """
        (fx, fy), (cx, cy) = self.focal, self.principal_point
        u, v = np.meshgrid(np.linspace(0.0, self.width, 5), np.linspace(0.0, self.height, 5))
        xy = np.column_stack([(u.ravel() - cx) / fx, (v.ravel() - cy) / fy])
        pinhole = np.column_stack([fx * xy[:, 0] + cx, fy * xy[:, 1] + cy])
        return bool(np.nanmax(np.abs(self.normalized_to_pixels(xy) - pinhole)) > 1e-9)

    @property
    def K(self) -> np.ndarray:
        """Calibration matrix, (3, 3) float64, mapping normalised to pixel coordinates."""
        (fx, fy), (cx, cy) = self.focal, self.principal_point
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])

    @property
    def shape(self) -> tuple[int, int]:
        """Image shape ``(height, width)`` as numpy orders it."""
        return self.height, self.width

    # -- extrinsics -----------------------------------------------------------------------------
    @property
    def center(self) -> np.ndarray:
        """Camera centre in the world frame, (3,) float64, metres: ``-R.T @ t``."""
        return -self.rotation.T @ self.translation

    @property
    def forward(self) -> np.ndarray:
        """Viewing direction (camera +z) in the world frame, unit (3,) float64."""
        return self.rotation[2].copy()

    def world_to_camera(self, points: np.ndarray) -> np.ndarray:
        """Transform world points ``(N, 3)`` (metres) to the camera frame ``(N, 3)``."""
        points = np.asarray(points, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 3:
            raise ValueError(f"points must have shape (N, 3), got shape {points.shape}")
        return np.dot(points, np.ascontiguousarray(self.rotation.T)) + self.translation  # BLAS: 3x faster than @ here

    # -- projection -----------------------------------------------------------------------------
    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project world points to pixels, applying lens distortion.

        Parameters
        ----------
        points : (N, 3) array_like
            World-frame points, metres.

        Returns
        -------
        pixels : (N, 2) float64
            Continuous pixel coordinates ``(u, v)`` (COLMAP convention); NaN for points with
            ``depth <= 0``. Points outside the image are not clipped (see :meth:`in_image`).
        depth : (N,) float64
            Camera-frame z in metres (positive in front of the camera).
        """
        cam = self.world_to_camera(points)
        depth = cam[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            xy = cam[:, :2] / depth[:, None]
        xy[depth <= 0] = np.nan
        return self.normalized_to_pixels(xy), depth

    def normalized_to_pixels(self, xy: np.ndarray) -> np.ndarray:
        """Map undistorted normalised coordinates ``(N, 2)`` to distorted pixels ``(N, 2)``.

        COLMAP's ``img_from_cam`` (pycolmap); NaN rows stay NaN. Without distortion
        (:attr:`is_distorted` false) ``K (x, y, 1)`` directly, the same numbers 5-10x faster.
        """
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        if self._pinhole:
            (fx, fy), (cx, cy) = self.focal, self.principal_point
            return np.column_stack([fx * xy[:, 0] + cx, fy * xy[:, 1] + cy])
        out = np.full((len(xy), 2), np.nan)
        ok = np.isfinite(xy).all(axis=1)
        if ok.any():
            out[ok] = self._colmap.img_from_cam(np.column_stack([xy[ok], np.ones(int(ok.sum()))]))
        return out

    def pixels_to_normalized(self, pixels: np.ndarray) -> np.ndarray:
        """Map distorted pixels ``(N, 2)`` to undistorted normalised coordinates ``(N, 2)``.

        The inverse of :meth:`normalized_to_pixels`: COLMAP's ``cam_from_img`` (pycolmap), with its
        iterative undistortion for distorted models; NaN where it has no solution. Without
        distortion ``K^-1 (u, v, 1)`` directly (the same numbers).
        """
        pixels = np.asarray(pixels, dtype=np.float64)
        if pixels.ndim != 2 or pixels.shape[1] != 2:
            raise ValueError(f"pixels must have shape (N, 2), got shape {pixels.shape}")
        if self._pinhole:  # the same numbers as COLMAP's, without its per-call cost
            (fx, fy), (cx, cy) = self.focal, self.principal_point
            return np.column_stack([(pixels[:, 0] - cx) / fx, (pixels[:, 1] - cy) / fy])
        out = np.full((len(pixels), 2), np.nan)
        ok = np.isfinite(pixels).all(axis=1)
        if ok.any():
            out[ok] = self._colmap.cam_from_img(np.ascontiguousarray(pixels[ok]))
        return out

    def undistort_pixels(self, pixels: np.ndarray) -> np.ndarray:
        """Where pixels ``(N, 2)`` of this camera land in its distortion-free pinhole twin.

        The twin keeps the focal lengths and principal point (:attr:`K`) and drops distortion.
        """
        xy = self.pixels_to_normalized(pixels)
        (fx, fy), (cx, cy) = self.focal, self.principal_point
        return np.stack([fx * xy[:, 0] + cx, fy * xy[:, 1] + cy], axis=1)

    def pixel_centers(self) -> np.ndarray:
        """All pixel centres, ``(H, W, 2)`` float64, ``[j, i] = (i + 0.5, j + 0.5)``."""
        u = np.arange(self.width) + 0.5
        v = np.arange(self.height) + 0.5
        uu, vv = np.meshgrid(u, v)
        return np.stack([uu, vv], axis=-1)

    def pixel_rays(self, pixels: np.ndarray | None = None) -> np.ndarray:
        """World-frame unit directions of the rays through pixels.

        Parameters
        ----------
        pixels : (N, 2) array_like, optional
            Continuous pixel coordinates. Default: every pixel centre in row-major order, i.e.
            ``pixel_centers().reshape(-1, 2)``, so the result reshapes to ``(H, W, 3)``.

        Returns
        -------
        (N, 3) float64
            Unit ray directions in the world frame; every ray starts at :attr:`center`.
        """
        if pixels is None:
            pixels = self.pixel_centers().reshape(-1, 2)
        xy = self.pixels_to_normalized(pixels)
        d_cam = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
        d_cam /= np.linalg.norm(d_cam, axis=1, keepdims=True)
        return d_cam @ self.rotation  # R.T @ d for each row

    def in_image(self, pixels: np.ndarray) -> np.ndarray:
        """Whether continuous pixel coordinates ``(N, 2)`` fall inside the image, (N,) bool."""
        pixels = np.asarray(pixels, dtype=np.float64)
        with np.errstate(invalid="ignore"):
            return (
                (pixels[:, 0] >= 0) & (pixels[:, 0] < self.width) & (pixels[:, 1] >= 0) & (pixels[:, 1] < self.height)
            )

    # -- derived cameras ------------------------------------------------------------------------
    def scaled(self, width: int, height: int) -> Camera:
        """The same camera for the image resampled to ``width x height`` pixels.

        Continuous pixel coordinates scale by ``sx = width / self.width`` and
        ``sy = height / self.height`` (the image corner stays at the origin). When ``sx != sy``
        a single-focal model cannot represent the result, so it becomes its two-focal twin with the
        same distortion (SIMPLE_PINHOLE -> PINHOLE, SIMPLE_RADIAL / RADIAL -> OPENCV, the radial
        fisheyes -> OPENCV_FISHEYE, SIMPLE_DIVISION -> DIVISION, SIMPLE_FISHEYE -> FISHEYE). Every
        model distorts normalised coordinates and then applies ``(fx x + cx, fy y + cy)``, so
        scaling the focal lengths and principal point is exact.
        """
        sx, sy = width / self.width, height / self.height
        model, params = self.model, self.params.copy()
        if abs(sx - sy) >= 1e-12 and model in _TWO_FOCAL:
            twin = _TWO_FOCAL[model]
            (fx, fy), (cx, cy) = self.focal, self.principal_point
            extra = np.zeros(len(CAMERA_MODELS[twin]) - 4)
            extra[: len(self.distortion)] = self.distortion
            model, params = twin, np.array([fx, fy, cx, cy, *extra])
        probe = pycolmap.Camera(model=model, width=self.width, height=self.height, params=params.tolist())
        focal = list(probe.focal_length_idxs())
        principal = list(probe.principal_point_idxs())
        if len(focal) == 1:
            params[focal] *= sx  # sx == sy here
        else:
            params[focal[0]] *= sx
            params[focal[1]] *= sy
        params[principal[0]] *= sx
        params[principal[1]] *= sy
        return Camera(model, int(width), int(height), params, self.rotation, self.translation)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Camera):
            return NotImplemented
        return (
            self.model == other.model
            and self.width == other.width
            and self.height == other.height
            and np.array_equal(self.params, other.params)
            and np.array_equal(self.rotation, other.rotation)
            and np.array_equal(self.translation, other.translation)
        )

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        c = np.array2string(self.center, precision=3)
        return f"Camera({self.model}, {self.width}x{self.height}, params={self.params.tolist()}, center={c})"
