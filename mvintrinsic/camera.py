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
* **Models** (parameter order as in COLMAP's ``cameras.txt``):

  ================  ==================================
  SIMPLE_PINHOLE    f, cx, cy
  PINHOLE           fx, fy, cx, cy
  SIMPLE_RADIAL     f, cx, cy, k
  RADIAL            f, cx, cy, k1, k2
  OPENCV            fx, fy, cx, cy, k1, k2, p1, p2
  ================  ==================================

  All five are special cases of OPENCV: with normalised coordinates ``(x, y) = (X/Z, Y/Z)`` and
  ``r^2 = x^2 + y^2`` the distorted coordinates are

  .. math::

     x_d = x (1 + k_1 r^2 + k_2 r^4) + 2 p_1 x y + p_2 (r^2 + 2 x^2)

     y_d = y (1 + k_1 r^2 + k_2 r^4) + 2 p_2 x y + p_1 (r^2 + 2 y^2)

  and the pixel is ``(fx x_d + cx, fy y_d + cy)`` (COLMAP ``OpenCVCameraModel``).

Undistortion inverts the distortion with Newton's method (COLMAP's ``IterativeUndistortion`` uses
the same fixed point with a numerical Jacobian; here the Jacobian is analytic and the iteration is
vectorised). See ``docs/conventions.md``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from ._validation import as_array, describe

__all__ = ["CAMERA_MODELS", "Camera"]

#: Supported COLMAP camera models and the names of their parameters, in COLMAP's order.
CAMERA_MODELS: dict[str, tuple[str, ...]] = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
}


def _distort(xy: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Apply OPENCV distortion to normalised coordinates ``xy`` of shape (N, 2)."""
    k1, k2, p1, p2 = dist
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    radial = 1.0 + k1 * r2 + k2 * r2 * r2
    xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * radial + 2.0 * p2 * x * y + p1 * (r2 + 2.0 * y * y)
    return np.stack([xd, yd], axis=1)


def _undistort(xy_d: np.ndarray, dist: np.ndarray, *, max_iter: int = 50, tol: float = 1e-14) -> np.ndarray:
    """Invert :func:`_distort` by Newton's method, vectorised over the (N, 2) points."""
    k1, k2, p1, p2 = dist
    xy = xy_d.copy()
    active = np.ones(len(xy), dtype=bool)
    for _ in range(max_iter):
        if not active.any():
            break
        x, y = xy[active, 0], xy[active, 1]
        residual = _distort(xy[active], dist) - xy_d[active]
        r2 = x * x + y * y
        radial = 1.0 + k1 * r2 + k2 * r2 * r2
        # d(radial)/dx = 2x (k1 + 2 k2 r^2), same in y.
        dr = 2.0 * (k1 + 2.0 * k2 * r2)
        j11 = radial + x * x * dr + 2.0 * p1 * y + 6.0 * p2 * x
        j12 = x * y * dr + 2.0 * p1 * x + 2.0 * p2 * y
        j21 = x * y * dr + 2.0 * p2 * y + 2.0 * p1 * x
        j22 = radial + y * y * dr + 2.0 * p2 * x + 6.0 * p1 * y
        det = j11 * j22 - j12 * j21
        det = np.where(np.abs(det) < 1e-300, 1e-300, det)
        step_x = (j22 * residual[:, 0] - j12 * residual[:, 1]) / det
        step_y = (-j21 * residual[:, 0] + j11 * residual[:, 1]) / det
        xy[active, 0] -= step_x
        xy[active, 1] -= step_y
        done = np.hypot(step_x, step_y) < tol * (1.0 + np.hypot(x, y))
        idx = np.flatnonzero(active)
        active[idx[done]] = False
    return xy


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
    _dist: np.ndarray = field(init=False, repr=False)

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
        fx, fy = self.focal
        if not (fx > 0 and fy > 0):
            raise ValueError(f"params: focal lengths must be positive, got {params.tolist()}")
        dist = np.zeros(4)
        values = dict(zip(CAMERA_MODELS[self.model], params, strict=True))
        if self.model == "SIMPLE_RADIAL":
            dist[0] = values["k"]
        elif self.model in ("RADIAL", "OPENCV"):
            dist[0], dist[1] = values["k1"], values["k2"]
            dist[2], dist[3] = values.get("p1", 0.0), values.get("p2", 0.0)
        dist.flags.writeable = False
        object.__setattr__(self, "_dist", dist)

    # -- intrinsics -----------------------------------------------------------------------------
    @property
    def focal(self) -> tuple[float, float]:
        """``(fx, fy)`` in pixels."""
        p = self.params
        if self.model in ("PINHOLE", "OPENCV"):
            return float(p[0]), float(p[1])
        return float(p[0]), float(p[0])

    @property
    def principal_point(self) -> tuple[float, float]:
        """``(cx, cy)`` in pixels (continuous coordinates, top-left corner at the origin)."""
        i = 2 if self.model in ("PINHOLE", "OPENCV") else 1
        return float(self.params[i]), float(self.params[i + 1])

    @property
    def distortion(self) -> np.ndarray:
        """``(k1, k2, p1, p2)``: the model's distortion written in OPENCV form, (4,) float64."""
        return self._dist

    @property
    def is_distorted(self) -> bool:
        """Whether the lens model has any non-zero distortion coefficient."""
        return bool(np.any(self._dist != 0.0))

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
        return points @ self.rotation.T + self.translation

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
        """Map undistorted normalised coordinates ``(N, 2)`` to distorted pixels ``(N, 2)``."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        if self.is_distorted:
            xy = _distort(xy, self._dist)
        (fx, fy), (cx, cy) = self.focal, self.principal_point
        return np.stack([fx * xy[:, 0] + cx, fy * xy[:, 1] + cy], axis=1)

    def pixels_to_normalized(self, pixels: np.ndarray) -> np.ndarray:
        """Map distorted pixels ``(N, 2)`` to undistorted normalised coordinates ``(N, 2)``.

        The inverse of :meth:`normalized_to_pixels` (Newton iterations for distorted models).
        """
        pixels = np.asarray(pixels, dtype=np.float64)
        if pixels.ndim != 2 or pixels.shape[1] != 2:
            raise ValueError(f"pixels must have shape (N, 2), got shape {pixels.shape}")
        (fx, fy), (cx, cy) = self.focal, self.principal_point
        xy = np.stack([(pixels[:, 0] - cx) / fx, (pixels[:, 1] - cy) / fy], axis=1)
        if self.is_distorted:
            xy = _undistort(xy, self._dist)
        return xy

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
        a single-focal model cannot represent the result, so SIMPLE_PINHOLE becomes PINHOLE and
        SIMPLE_RADIAL / RADIAL become OPENCV with the same distortion: the mapping is exact.
        """
        sx, sy = width / self.width, height / self.height
        (fx, fy), (cx, cy) = self.focal, self.principal_point
        k1, k2, p1, p2 = self._dist
        same = abs(sx - sy) < 1e-12
        if self.model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL") and same:
            params = np.array([fx * sx, cx * sx, cy * sy, *self.params[3:]])
            model = self.model
        elif self.model in ("PINHOLE", "SIMPLE_PINHOLE"):
            model, params = "PINHOLE", np.array([fx * sx, fy * sy, cx * sx, cy * sy])
        else:
            model, params = "OPENCV", np.array([fx * sx, fy * sy, cx * sx, cy * sy, k1, k2, p1, p2])
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
