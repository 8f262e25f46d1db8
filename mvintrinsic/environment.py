"""The environment map of Step 1 (paper Sec. 4): horizon, projected photographs, sky detection, completion.

Step 1 of Duchêne et al. (2015) synthesises an environment map that holds the light coming from
the sky and from everything the proxy does not reconstruct:

1. every valid pixel whose camera ray misses the proxy is projected into an equirectangular map
   (:func:`partial_environment_map`) -- "We project all pixels of the input pictures that are not
   covered by the reconstructed geometry into this map";
2. the horizon is "the main horizontal plane of the proxy" (:func:`horizon_plane`);
3. "a simple color-based sky detector" tells sky from distant objects above the horizon
   (:func:`detect_sky`);
4. the sky model of Perez et al. (1993), with the turbidity-dependent coefficients of Preetham et
   al. (1999), is fitted to the visible sky by minimising Eq. (4) over the turbidity ``t`` and a
   per-channel scale ``k`` -- simplex search over ``t``, linear least squares for ``k``
   (:func:`~mvintrinsic.skymodel.fit_sky`), as Lalonde et al. (2009, 2011) do from single images;
5. the missing sky is filled with the model and the holes below the horizon by diffusion
   (:func:`complete_environment_map`, :func:`fill_by_diffusion`).

:func:`estimate_environment` chains the five steps.

The sky model itself and its fit are in :mod:`.skymodel`; the map's parameterisation in :mod:`.envmap`.

Sources: the paper [1]_; the Perez sky [2]_ in Preetham's parameterisation [3]_ (:mod:`.skymodel`),
fitted as Lalonde et al. do [4]_; linear RGB with sRGB primaries [5]_.

References
----------
.. [1] S. Duchêne, C. Riant, G. Chaurasia, J. Lopez-Moreno, P.-Y. Laffont, S. Popov, A. Bousseau,
   G. Drettakis, "Multi-View Intrinsic Images of Outdoors Scenes with an Application to
   Relighting", ACM Transactions on Graphics 34(5), 2015. Sec. 4 and Eq. (4).
.. [2] R. Perez, R. Seals, J. Michalsky, "All-weather model for sky luminance distribution --
   Preliminary configuration and validation", Solar Energy 50(3), 235-245, 1993.
.. [3] A. J. Preetham, P. Shirley, B. Smits, "A Practical Analytic Model for Daylight",
   Proc. SIGGRAPH 99, 91-100, 1999. Appendix A.2: distribution coefficients and zenith values.
.. [4] J.-F. Lalonde, S. G. Narasimhan, A. A. Efros, "What do the sun and the sky tell us about
   the camera?", IJCV 88(1), 2010 (ICCV 2009); J.-F. Lalonde, A. A. Efros, S. G. Narasimhan,
   "Estimating the Natural Illumination Conditions from a Single Outdoor Image", IJCV 98(2), 2012
   (2011 preprint).
.. [5] IEC 61966-2-1:1999, sRGB: the XYZ -> linear RGB matrix of the Rec.709 primaries, D65.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import scipy.optimize
import scipy.sparse
import scipy.sparse.linalg

from ._validation import as_array, as_unit_vector, config_or_default, describe
from .envmap import (
    _Z_UP,
    _check_height,
    direction_to_texel,
    envmap_directions,
    texel_solid_angles,
)
from .image_model import luminance
from .scene import View
from .skymodel import SkyConfig, SkyModel, fit_sky, select_sky_model, sky_fit_outliers

__all__ = [
    "EnvironmentMap",
    "HorizonPlane",
    "NoGroundPlaneError",
    "PartialEnvironmentMap",
    "complete_environment_map",
    "detect_sky",
    "estimate_environment",
    "fill_by_diffusion",
    "find_horizon",
    "horizon_from_up",
    "horizon_plane",
    "partial_environment_map",
]

class NoGroundPlaneError(ValueError):
    """The proxy has no near-horizontal plane to serve as the horizon (:func:`horizon_plane`)."""




# ------------------------------------------------------------------------------------------------
# Horizon: the main horizontal plane of the proxy
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class HorizonPlane:
    """The main horizontal plane of the proxy (paper Sec. 4).

    Parameters
    ----------
    plane : (4,) float64
        ``[a, b, c, d]`` with ``(a, b, c)`` the unit normal on the ``up`` side: a point ``x`` is
        at signed height ``n · x + d`` metres above the plane.
    inlier_fraction : float
        Fraction of the vertices within ``horizon_inlier_distance`` of the plane.
    n_inliers : int
        Their number.
    evidence : {"proxy plane", "up"}
        What placed it: RANSAC on the proxy (:func:`horizon_plane`) or the scene's up vector
        (:func:`horizon_from_up`).
    reason : str
        Why ``"up"`` was used (the RANSAC failure), empty otherwise.
    """

    plane: np.ndarray
    inlier_fraction: float
    n_inliers: int
    evidence: str = "proxy plane"
    reason: str = ""

    def __post_init__(self) -> None:
        plane = np.array(as_array(self.plane, "plane", shape=(4,), dtype=np.float64))
        norm = float(np.linalg.norm(plane[:3]))
        if abs(norm - 1.0) > 1e-6:
            raise ValueError(f"plane: the normal (a, b, c) must be a unit vector, got length {norm}")
        plane.flags.writeable = False
        object.__setattr__(self, "plane", plane)
        object.__setattr__(self, "inlier_fraction", float(self.inlier_fraction))
        object.__setattr__(self, "n_inliers", int(self.n_inliers))
        if self.evidence not in ("proxy plane", "up"):
            raise ValueError(f"evidence must be 'proxy plane' or 'up', got {self.evidence!r}")

    @property
    def normal(self) -> np.ndarray:
        """Unit normal of the plane on the ``up`` side, (3,) float64, world frame."""
        return self.plane[:3].copy()

    def height_of(self, points: object) -> np.ndarray:
        """Signed height of world points ``(N, 3)`` above the plane, ``(N,)`` metres."""
        p = as_array(points, "points", shape=(None, 3), dtype=np.float64)
        return p @ self.plane[:3] + self.plane[3]


def _plane_through(points: np.ndarray, up: np.ndarray) -> np.ndarray:
    """Least-squares plane ``[n, d]`` of ``points`` (SVD of the centred points), ``n · up >= 0``."""
    centroid = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - centroid, full_matrices=False)
    normal = vt[-1]
    if normal @ up < 0:
        normal = -normal
    return np.concatenate([normal, [-normal @ centroid]])


def horizon_plane(
    vertices: object,
    *,
    up: object = _Z_UP,
    config: SkyConfig | None = None,
    rng: np.random.Generator | int | None = None,
) -> HorizonPlane:
    """Find "the main horizontal plane of the proxy" (paper Sec. 4) by RANSAC.

    Random vertex triples give candidate planes; those whose normal is within
    ``config.horizon_angle_tol_deg`` of ``up`` are scored by their number of vertices within
    ``config.horizon_inlier_distance`` (on a random subset of at most
    ``config.horizon_max_points`` vertices). The best one is refitted twice by least squares
    (SVD) on all its inliers.

    Parameters
    ----------
    vertices : (N, 3) array_like
        Proxy vertices, world frame, metres.
    up : (3,) array_like, optional
        World up vector, default +Z.
    config : SkyConfig, optional
        Uses the ``horizon_*`` fields.
    rng : numpy.random.Generator or int or None, optional
        Randomness of the RANSAC samples; a seed makes the result reproducible.

    Returns
    -------
    HorizonPlane

    Raises
    ------
    ValueError
        If ``vertices`` holds fewer than 3 finite points.
    NoGroundPlaneError
        (a ValueError) If no near-horizontal plane exists: no candidate within the angle tolerance, or the best one is not denser than its
        surroundings by ``config.horizon_min_contrast`` (e.g. a horizontal slice through walls).
    """
    config = config_or_default(config, SkyConfig)
    points = as_array(vertices, "vertices", shape=(None, 3), dtype=np.float64)
    if len(points) < 3:
        raise ValueError(f"vertices must hold at least 3 points, got {len(points)}")
    up = as_unit_vector(up, "up")
    rng = np.random.default_rng(rng)
    delta = config.horizon_inlier_distance
    cos_tol = math.cos(math.radians(config.horizon_angle_tol_deg))

    scoring = points
    if len(points) > config.horizon_max_points:
        scoring = points[rng.choice(len(points), config.horizon_max_points, replace=False)]
    n_draw = 50 * config.horizon_iterations
    triples = scoring[rng.integers(0, len(scoring), size=(n_draw, 3))]
    normals = np.cross(triples[:, 1] - triples[:, 0], triples[:, 2] - triples[:, 0])
    lengths = np.linalg.norm(normals, axis=1)
    good = lengths > 1e-12
    normals, anchors, lengths = normals[good], triples[good, 0], lengths[good]
    normals /= lengths[:, None]
    normals *= np.sign(normals @ up)[:, None]
    horizontal = normals @ up >= cos_tol
    normals, anchors = (
        normals[horizontal][: config.horizon_iterations],
        anchors[horizontal][: config.horizon_iterations],
    )
    if len(normals) == 0:
        raise NoGroundPlaneError(
            f"vertices: no near-horizontal plane (normal within {config.horizon_angle_tol_deg}° of up "
            f"{up.tolist()}) among {n_draw} random vertex triples; the proxy has no horizon plane"
        )
    offsets = -np.einsum("ij,ij->i", normals, anchors)
    best, best_count = 0, -1
    for start in range(0, len(normals), 64):  # (64, M) distance blocks
        dist = np.abs(scoring @ normals[start : start + 64].T + offsets[start : start + 64])
        counts = (dist <= delta).sum(axis=0)
        i = int(np.argmax(counts))
        if counts[i] > best_count:
            best, best_count = start + i, int(counts[i])
    plane = np.concatenate([normals[best], [offsets[best]]])
    for _ in range(2):  # least-squares refit on all inliers
        inliers = np.abs(points @ plane[:3] + plane[3]) <= delta
        if inliers.sum() < 3:
            break
        plane = _plane_through(points[inliers], up)
    height = points @ plane[:3] + plane[3]
    n_in = int((np.abs(height) <= delta).sum())
    n_near = int(((np.abs(height) > delta) & (np.abs(height) <= 4.0 * delta)).sum())
    # density in the 2δ inlier slab over density in the two 3δ slabs around it (6δ in all)
    contrast = math.inf if n_near == 0 else 3.0 * n_in / n_near
    tilt = math.degrees(math.acos(min(1.0, float(plane[:3] @ up))))
    if n_in < 3 or tilt > config.horizon_angle_tol_deg or contrast < config.horizon_min_contrast:
        raise NoGroundPlaneError(
            f"vertices: no near-horizontal plane found: the best candidate (tilt {tilt:.1f}° from up, "
            f"{n_in} inliers within {delta} m) is only {contrast:.2f} times denser than its surroundings "
            f"(need {config.horizon_min_contrast}); the proxy has no ground plane"
        )
    return HorizonPlane(plane=plane, inlier_fraction=n_in / len(points), n_inliers=n_in)


def horizon_from_up(
    vertices: object,
    *,
    up: object = _Z_UP,
    camera_centers: object | None = None,
    camera_ups: object | None = None,
    config: SkyConfig | None = None,
    reason: str = "",
) -> HorizonPlane:
    """The horizon plane from the scene's up vector, for a proxy without a clear ground.

    The normal is ``up``; the plane passes through the 1st percentile of the proxy's heights
    along ``up``, or 1.6 m (eye height) below the lowest camera if that is lower. Only the normal
    matters to Step 1 (the sky lies above the horizon, :func:`estimate_environment`); the offset
    is a best guess of the ground level, reported in the result.

    Parameters
    ----------
    vertices : (N, 3) array_like
        Proxy vertices, world frame, metres.
    up : (3,) array_like, optional
        World up vector, default +Z.
    camera_centers : (M, 3) array_like, optional
        Camera centres, world frame.
    camera_ups : (M, 3) array_like, optional
        The cameras' up axes in the world frame (``-y`` of the camera, the top of the photo).
        Photos are taken roughly upright, so their mean should lie near ``up``; the angle is
        added to :attr:`HorizonPlane.reason`, and a warning is given above 60 degrees (``up`` in
        scene.json is then probably wrong: the sky would be looked for in the wrong place).
    config : SkyConfig, optional
        ``horizon_inlier_distance`` counts the vertices near the plane.
    reason : str, optional
        Why the proxy's plane was not used; kept in :attr:`HorizonPlane.reason`.

    Returns
    -------
    HorizonPlane
        With ``evidence="up"``.
    """
    config = config_or_default(config, SkyConfig)
    points = as_array(vertices, "vertices", shape=(None, 3), dtype=np.float64)
    if len(points) < 1:
        raise ValueError("vertices must hold at least 1 point")
    up = as_unit_vector(up, "up")
    heights = points @ up
    ground = float(np.percentile(heights, 1.0))
    if camera_centers is not None:
        centers = as_array(camera_centers, "camera_centers", shape=(None, 3), dtype=np.float64)
        if len(centers):
            ground = min(ground, float((centers @ up).min()) - 1.6)
    plane = np.concatenate([up, [-ground]])
    n_in = int((np.abs(heights - ground) <= config.horizon_inlier_distance).sum())
    if camera_ups is not None:
        ups = as_array(camera_ups, "camera_ups", shape=(None, 3), dtype=np.float64)
        mean = ups.sum(axis=0)
        if len(ups) and np.linalg.norm(mean) > 0:
            angle = math.degrees(math.acos(float(np.clip(mean @ up / np.linalg.norm(mean), -1.0, 1.0))))
            reason = f"{reason}; the cameras' mean up axis is {angle:.0f}° from up".lstrip("; ")
            if angle > 60.0:
                warnings.warn(f"up {up.tolist()} is {angle:.0f}° from the cameras' mean up axis: the horizon and "
                              "the sky detector rely on it (check 'up' in scene.json)", UserWarning, stacklevel=2)
    return HorizonPlane(plane=plane, inlier_fraction=n_in / len(points), n_inliers=n_in, evidence="up",
                        reason=reason)


def find_horizon(
    vertices: object,
    *,
    up: object = _Z_UP,
    camera_centers: object | None = None,
    camera_ups: object | None = None,
    config: SkyConfig | None = None,
    rng: np.random.Generator | int | None = None,
) -> HorizonPlane:
    """The horizon by the rule of ``config.horizon``: the proxy's plane, the up vector, or the
    first that works (``"auto"``). See :func:`horizon_plane` and :func:`horizon_from_up`."""
    config = config_or_default(config, SkyConfig)
    if config.horizon == "up":
        return horizon_from_up(vertices, up=up, camera_centers=camera_centers, camera_ups=camera_ups, config=config,
                               reason="SkyConfig.horizon='up'")
    try:
        return horizon_plane(vertices, up=up, config=config, rng=rng)
    except NoGroundPlaneError as exc:
        if config.horizon == "plane":
            raise
        return horizon_from_up(vertices, up=up, camera_centers=camera_centers, camera_ups=camera_ups, config=config,
                               reason=str(exc))


# ------------------------------------------------------------------------------------------------
# Partial environment map
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class PartialEnvironmentMap:
    """The environment map seen by the photographs, before completion (paper Fig. 3, left).

    Parameters
    ----------
    radiance : (He, 2 He, 3) float32
        Linear RGB radiance in image units, NaN where no view saw the direction.
    count : (He, 2 He) int64
        Number of views that contributed to each texel (0 where unknown).
    up : (3,) float64
        World up vector of the map's parameterisation.
    """

    radiance: np.ndarray
    count: np.ndarray
    up: np.ndarray = field(default_factory=lambda: np.array(_Z_UP))

    def __post_init__(self) -> None:
        radiance = as_array(self.radiance, "radiance", shape=(None, None, 3), dtype=np.float32, finite=False)
        he, w = radiance.shape[:2]
        if he < 2 or w != 2 * he:
            raise ValueError(f"radiance must have shape (He, 2 He, 3) with He >= 2, got shape {radiance.shape}")
        count = as_array(self.count, "count", shape=(he, w), dtype=np.int64)
        known = np.isfinite(radiance).all(axis=2)
        if np.isinf(radiance).any():
            raise ValueError("radiance must be finite where known (NaN marks unknown texels), got infinite values")
        if np.any(known != (count > 0)) or (count < 0).any():
            raise ValueError("count must be positive exactly where radiance is known (not NaN)")
        if (radiance[known] < 0).any():
            raise ValueError("radiance must be non-negative where known")
        object.__setattr__(self, "radiance", radiance)
        object.__setattr__(self, "count", count)
        object.__setattr__(self, "up", as_unit_vector(self.up, "up"))

    @property
    def height(self) -> int:
        """``He``."""
        return self.radiance.shape[0]

    @property
    def known(self) -> np.ndarray:
        """Texels seen by at least one view, (He, 2 He) bool."""
        return self.count > 0


def partial_environment_map(
    views: Sequence[View],
    uncovered: Sequence[object],
    *,
    height: int,
    up: object = _Z_UP,
) -> PartialEnvironmentMap:
    """Project the pixels not covered by the proxy into an environment map (paper Sec. 4).

    "We project all pixels of the input pictures that are not covered by the reconstructed
    geometry into this map." Each selected pixel is splatted along its camera ray
    (:meth:`Camera.pixel_rays`, through the pixel centre) into the texel containing the ray's
    direction; each view averages its pixels per texel, and the views are combined by a
    per-texel, per-channel median of their means (robust to a view with a moving object or a
    different exposure).

    Parameters
    ----------
    views : sequence of View
        The photographs (linear RGB, image units).
    uncovered : sequence of (H, W) bool
        One mask per view: pixels whose ray misses the proxy (computed by the caller). Only
        pixels that are also valid (``View.mask``) are used.
    height : int
        ``He`` of the map.
    up : (3,) array_like, optional
        World up vector, default +Z.

    Returns
    -------
    PartialEnvironmentMap
        NaN where no view saw the direction.
    """
    height = _check_height(height)
    up = as_unit_vector(up, "up")
    if isinstance(views, View) or not isinstance(views, Sequence):
        raise TypeError(f"views must be a sequence of View, got {describe(views)}")
    if isinstance(uncovered, np.ndarray) or not isinstance(uncovered, Sequence):
        raise TypeError(f"uncovered must be a sequence of (H, W) bool arrays (one per view), got {describe(uncovered)}")
    if len(views) != len(uncovered):
        raise ValueError(f"uncovered must hold one mask per view: {len(views)} views, {len(uncovered)} masks")
    if len(views) == 0:
        raise ValueError("views must hold at least one View, got none")
    width = 2 * height
    n_tex = height * width
    means = np.full((len(views), n_tex, 3), np.nan)
    for i, (view, mask) in enumerate(zip(views, uncovered, strict=True)):
        if not isinstance(view, View):
            raise TypeError(f"views[{i}] must be a View, got {describe(view)}")
        mask = as_array(mask, f"uncovered[{i}]", shape=view.shape, dtype=bool)
        rows, cols = np.nonzero(mask & view.mask)
        if len(rows) == 0:
            continue
        sums = np.zeros((n_tex, 3))
        hits = np.zeros(n_tex)
        for start in range(0, len(rows), 1 << 20):
            r, c = rows[start : start + (1 << 20)], cols[start : start + (1 << 20)]
            pixels = np.stack([c + 0.5, r + 0.5], axis=1)
            tv, tu = direction_to_texel(view.camera.pixel_rays(pixels), height, up=up)
            texel = tv * width + tu
            colours = view.image[r, c].astype(np.float64)
            hits += np.bincount(texel, minlength=n_tex)
            for ch in range(3):
                sums[:, ch] += np.bincount(texel, weights=colours[:, ch], minlength=n_tex)
        seen = hits > 0
        means[i, seen] = sums[seen] / hits[seen, None]
    count = np.isfinite(means[..., 0]).sum(axis=0)
    radiance = np.full((n_tex, 3), np.nan)
    known = count > 0
    radiance[known] = np.nanmedian(means[:, known], axis=0)
    return PartialEnvironmentMap(
        radiance=radiance.reshape(height, width, 3).astype(np.float32),
        count=count.reshape(height, width),
        up=up,
    )


# ------------------------------------------------------------------------------------------------
# Sky detection
# ------------------------------------------------------------------------------------------------
def detect_sky(
    partial: PartialEnvironmentMap, *, horizon_normal: object, config: SkyConfig | None = None
) -> np.ndarray:
    """Colour-based sky detector (paper Sec. 4: "a simple color-based sky detector").

    Among the known texels above the horizon (``direction · horizon_normal > 0``), a texel is
    sky when it is

    * **bluish**: blue chromaticity ``b / (r + g + b) >= config.sky_blue_min`` (0.34, just above
      neutral 1/3) -- green foliage, warm plaster or brick and neutral grey or white objects
      fail;
    * **bright**: Rec.709 luminance ``>= config.sky_luminance_min`` (0.1) times the
      ``config.sky_luminance_percentile`` (90th) percentile of the luminance of all known texels
      above the horizon -- dark objects, including bluish ones in shadow, fail.

    Parameters
    ----------
    partial : PartialEnvironmentMap
    horizon_normal : (3,) array_like
        Normal of the horizon plane (:attr:`HorizonPlane.normal`), world frame, ``up`` side.
    config : SkyConfig, optional

    Returns
    -------
    (He, 2 He) bool
        True on detected sky texels; always False below the horizon and on unknown texels.
    """
    if not isinstance(partial, PartialEnvironmentMap):
        raise TypeError(f"partial must be a PartialEnvironmentMap, got {describe(partial)}")
    config = config_or_default(config, SkyConfig)
    normal = as_unit_vector(horizon_normal, "horizon_normal")
    directions = envmap_directions(partial.height, up=partial.up)
    candidates = partial.known & (directions @ normal > 0)
    sky = np.zeros(candidates.shape, dtype=bool)
    if not candidates.any():
        return sky
    rgb = partial.radiance[candidates].astype(np.float64)
    total = rgb.sum(axis=1)
    brightness = luminance(rgb)
    reference = float(np.percentile(brightness, config.sky_luminance_percentile))
    with np.errstate(divide="ignore", invalid="ignore"):
        blue = np.where(total > 0, rgb[:, 2] / total, 0.0)
    is_sky = (blue >= config.sky_blue_min) & (brightness >= config.sky_luminance_min * reference) & (brightness > 0)
    sky[candidates] = is_sky
    return sky




# ------------------------------------------------------------------------------------------------
# Completion
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class EnvironmentMap:
    """The completed environment map (paper Fig. 3, right).

    Parameters
    ----------
    radiance : (He, 2 He, 3) float32
        Linear RGB radiance, image units; complete, finite and non-negative.
    sky : (He, 2 He) bool
        Texels whose radiance is sky (detected sky and model-filled texels); rays toward them
        contribute to ``S_sky``, toward the other texels to ``S_ind`` (paper Sec. 4).
    observed : (He, 2 He) bool
        Texels seen in the photographs (the others were filled).
    up : (3,) float64
        World up vector of the parameterisation.
    horizon_normal : (3,) float64
        Normal of the horizon plane, world frame.
    """

    radiance: np.ndarray
    sky: np.ndarray
    observed: np.ndarray
    up: np.ndarray = field(default_factory=lambda: np.array(_Z_UP))
    horizon_normal: np.ndarray = field(default_factory=lambda: np.array(_Z_UP))

    def __post_init__(self) -> None:
        radiance = as_array(self.radiance, "radiance", shape=(None, None, 3), dtype=np.float32)
        he, w = radiance.shape[:2]
        if he < 2 or w != 2 * he:
            raise ValueError(f"radiance must have shape (He, 2 He, 3) with He >= 2, got shape {radiance.shape}")
        if (radiance < 0).any():
            raise ValueError("radiance must be non-negative")
        object.__setattr__(self, "radiance", radiance)
        object.__setattr__(self, "sky", as_array(self.sky, "sky", shape=(he, w), dtype=bool))
        object.__setattr__(self, "observed", as_array(self.observed, "observed", shape=(he, w), dtype=bool))
        object.__setattr__(self, "up", as_unit_vector(self.up, "up"))
        object.__setattr__(self, "horizon_normal", as_unit_vector(self.horizon_normal, "horizon_normal"))

    @property
    def height(self) -> int:
        """``He``."""
        return self.radiance.shape[0]

    def lookup(self, directions: object) -> np.ndarray:
        """Radiance toward world directions ``(N, 3)`` (nearest texel): ``(N, 3)`` float32."""
        rows, cols = direction_to_texel(directions, self.height, up=self.up)
        return self.radiance[rows, cols]

    def is_sky(self, directions: object) -> np.ndarray:
        """Whether world directions ``(N, 3)`` see the sky (nearest texel): ``(N,)`` bool."""
        rows, cols = direction_to_texel(directions, self.height, up=self.up)
        return self.sky[rows, cols]


def fill_by_diffusion(image: object, *, wrap: bool = True) -> np.ndarray:
    """Fill NaN holes with the harmonic interpolation of the known texels.

    Solves the discrete Laplace equation ``Σ_{j ~ i} (u_i − u_j) = 0`` at every hole ``i``,
    the known texels being Dirichlet boundary values, on the 4-neighbour texel graph. With
    ``wrap`` the image is an equirectangular sphere: columns wrap around (the ``u = 0`` and
    ``u = W − 1`` texels are neighbours) and the texels of the first and last rows are linked
    across the pole to the texel half a turn away. Each channel is solved with one sparse LU
    factorisation (:mod:`scipy.sparse`). The graph is connected, so one known texel suffices for
    a unique solution; the result is a convex combination of known values (maximum principle).

    Parameters
    ----------
    image : (He, W) or (He, W, C) float array
        Values with NaN at the holes (a texel is a hole when any channel is NaN).
    wrap : bool, optional
        Treat the image as an equirectangular map (default) rather than a flat rectangle.

    Returns
    -------
    ndarray
        Same shape and dtype, every hole filled; known texels unchanged.

    Raises
    ------
    ValueError
        If the image holds infinite values or no known texel.
    """
    array = np.asarray(image)
    if array.dtype.kind != "f":
        raise TypeError(f"image must be a floating-point array with NaN holes, got {describe(image)}")
    if array.ndim not in (2, 3) or array.shape[0] < 1 or array.shape[1] < 1:
        raise ValueError(f"image must have shape (He, W) or (He, W, C), got shape {array.shape}")
    if np.isinf(array).any():
        raise ValueError("image must not hold infinite values (NaN marks the holes)")
    values = array.reshape(array.shape[0], array.shape[1], -1).astype(np.float64)
    rows, cols = values.shape[:2]
    holes = np.isnan(values).any(axis=2)
    out = values.copy()
    if not holes.any():
        return out.reshape(array.shape).astype(array.dtype)
    if holes.all():
        raise ValueError("image has no known texel to diffuse from")
    index = np.arange(rows * cols).reshape(rows, cols)
    pairs = [np.stack([index[:-1].ravel(), index[1:].ravel()], axis=1)]  # vertical neighbours
    if wrap and cols > 1:
        pairs.append(np.stack([index.ravel(), np.roll(index, -1, axis=1).ravel()], axis=1))
        if cols % 2 == 0 and cols > 2:  # across the poles: (0, u) ~ (0, u + W/2), same for the last row
            half = cols // 2
            for r in {0, rows - 1}:
                pairs.append(np.stack([index[r, :half], index[r, half:]], axis=1))
    else:
        pairs.append(np.stack([index[:, :-1].ravel(), index[:, 1:].ravel()], axis=1))
    edges = np.unique(np.sort(np.concatenate(pairs), axis=1), axis=0)
    edges = edges[edges[:, 0] != edges[:, 1]]
    n = rows * cols
    adjacency = scipy.sparse.coo_matrix(
        (np.ones(2 * len(edges)), (np.r_[edges[:, 0], edges[:, 1]], np.r_[edges[:, 1], edges[:, 0]])), shape=(n, n)
    ).tocsr()
    degree = np.asarray(adjacency.sum(axis=1)).ravel()
    flat_holes = holes.ravel()
    unknown, known = np.flatnonzero(flat_holes), np.flatnonzero(~flat_holes)
    # Laplace at the holes: (D - A)_UU x_U = A_UK x_K
    system = (scipy.sparse.diags(degree[unknown]) - adjacency[unknown][:, unknown]).tocsc()
    coupling = adjacency[unknown][:, known]
    solve = scipy.sparse.linalg.factorized(system)
    flat = out.reshape(n, -1)
    for ch in range(flat.shape[1]):
        flat[unknown, ch] = solve(coupling @ flat[known, ch])
    return flat.reshape(array.shape).astype(array.dtype)


def complete_environment_map(
    partial: PartialEnvironmentMap,
    sky_mask: object,
    sky_model: SkyModel,
    *,
    horizon_normal: object,
) -> EnvironmentMap:
    """Complete the partial map: sky model above the horizon, diffusion below (paper Sec. 4).

    * Observed texels keep their value.
    * Unknown texels above the horizon (``direction · horizon_normal > 0``) take the fitted sky,
      "we estimate the missing sky pixels by fitting the parametric sky model".
    * Unknown texels below the horizon are filled by :func:`fill_by_diffusion` from the observed
      texels that are not sky (distant ground and objects), "We fill holes below the horizon line
      by diffusing color from nearby pixels". Sky texels, observed or modelled, are not sources:
      the bright, whitish sky near the horizon would otherwise flood the whole unobserved lower
      hemisphere (on the demo scene it doubled ``S_ind`` of shadowed walls, whose downward rays
      leave the proxy where the cameras never saw the ground). Only when no non-sky texel is
      observed do the texels above the horizon diffuse down.

    Parameters
    ----------
    partial : PartialEnvironmentMap
    sky_mask : (He, 2 He) bool
        Observed texels that are sky (:func:`detect_sky`); must be known in ``partial``.
    sky_model : SkyModel
        The fitted sky (:func:`fit_sky`).
    horizon_normal : (3,) array_like
        Normal of the horizon plane, world frame, ``up`` side.

    Returns
    -------
    EnvironmentMap
        ``sky`` = detected sky | model-filled texels; ``observed`` = known texels of ``partial``.
    """
    if not isinstance(partial, PartialEnvironmentMap):
        raise TypeError(f"partial must be a PartialEnvironmentMap, got {describe(partial)}")
    if not isinstance(sky_model, SkyModel):
        raise TypeError(f"sky_model must be a SkyModel, got {describe(sky_model)}")
    he = partial.height
    mask = as_array(sky_mask, "sky_mask", shape=(he, 2 * he), dtype=bool)
    known = partial.known
    if (mask & ~known).any():
        raise ValueError(f"sky_mask marks {int((mask & ~known).sum())} texels that partial does not know")
    normal = as_unit_vector(horizon_normal, "horizon_normal")
    directions = envmap_directions(he, up=partial.up)
    above = directions @ normal > 0
    radiance = partial.radiance.astype(np.float64)
    model_filled = above & ~known
    if model_filled.any():
        radiance[model_filled] = sky_model.radiance(directions[model_filled])
    below_unknown = ~above & ~known
    if below_unknown.any():
        sources = known & ~mask
        if not sources.any():
            sources = above | known
        seeds = np.where(sources[..., None], radiance, np.nan)
        radiance[below_unknown] = fill_by_diffusion(seeds, wrap=True)[below_unknown]
    remaining = np.isnan(radiance)
    if remaining.any():  # unknown texels above the horizon cannot remain; this is a safeguard
        radiance = fill_by_diffusion(radiance, wrap=True)
    return EnvironmentMap(
        radiance=np.maximum(radiance, 0.0).astype(np.float32),
        sky=mask | model_filled,
        observed=known,
        up=partial.up,
        horizon_normal=normal,
    )


def estimate_environment(
    views: Sequence[View],
    uncovered: Sequence[object],
    *,
    sun_direction: object,
    horizon_normal: object,
    up: object = _Z_UP,
    config: SkyConfig | None = None,
) -> tuple[EnvironmentMap, SkyModel]:
    """The whole of paper Sec. 4: partial map, sky detection, Eq. (4) fit, completion.

    1. :func:`partial_environment_map` of the uncovered valid pixels;
    2. :func:`detect_sky` above the horizon;
    3. :func:`fit_sky` on the detected sky texels (weights: texel solid angles when
       ``config.weight_by_solid_angle``), of the family ``config.model`` (Preetham's with
       ``"auto"``);
    4. with ``config.outlier_ratio``, the sky texels the fit does not explain
       (:func:`sky_fit_outliers`) are re-labelled non-sky and the fit is repeated once (kept
       only if at least ``config.min_texels`` texels remain);
    5. with ``config.model == "auto"``, the family chosen on the remaining texels by
       :func:`select_sky_model`;
    6. :func:`complete_environment_map`.

    Parameters
    ----------
    views : sequence of View
    uncovered : sequence of (H, W) bool
        Per view, the pixels whose ray misses the proxy.
    sun_direction : (3,) array_like
        Unit vector toward the sun, world frame.
    horizon_normal : (3,) array_like
        Normal of the horizon plane (:func:`horizon_plane`), world frame.
    up : (3,) array_like, optional
        World up vector, default +Z.
    config : SkyConfig, optional

    Returns
    -------
    environment : EnvironmentMap
    sky : SkyModel

    Raises
    ------
    SkyFitError
        If too few sky texels are visible.
    """
    config = config_or_default(config, SkyConfig)
    partial = partial_environment_map(views, uncovered, height=config.envmap_height, up=up)
    sky = detect_sky(partial, horizon_normal=horizon_normal, config=config)
    directions = envmap_directions(partial.height, up=partial.up)
    weights_map = texel_solid_angles(partial.height) if config.weight_by_solid_angle else np.ones(sky.shape)

    family = "preetham" if config.model == "auto" else config.model

    def fit(mask: np.ndarray, chooser=fit_sky, **kwargs) -> SkyModel:
        return chooser(
            directions[mask],
            partial.radiance[mask],
            sun_direction=sun_direction,
            up=partial.up,
            config=config,
            weights=weights_map[mask],
            **kwargs,
        )

    model = fit(sky, model=family)
    if config.outlier_ratio is not None:
        outliers = sky_fit_outliers(model, directions[sky], partial.radiance[sky], config=config)
        if outliers.any() and (~outliers).sum() >= config.min_texels:
            flat = sky.ravel().copy()
            flat[np.flatnonzero(flat)[outliers]] = False
            sky = flat.reshape(sky.shape)
            model = fit(sky, model=family)
    if config.model == "auto":
        model = fit(sky, chooser=select_sky_model)
    return complete_environment_map(partial, sky, model, horizon_normal=horizon_normal), model
