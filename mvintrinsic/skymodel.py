"""The sky model fitted to the environment map (paper Sec. 4, Eq. 4): Perez, Preetham, or a constant sky.

The sky model of Perez et al. (1993) [2]_, with the turbidity-dependent coefficients of Preetham
et al. (1999) [3]_, is fitted to the visible sky of the environment map by minimising Eq. (4)
over the turbidity ``t`` and a per-channel scale ``k``: simplex search over ``t``, linear least
squares for ``k`` (:func:`fit_sky`), as Lalonde et al. do from single images [4]_. Beyond the
paper, :func:`select_sky_model` chooses among a constant sky, Preetham's and a free Perez sky by
the error on sky texels held out from the fit (``docs/step1.md``). The XYZ to linear-RGB matrix
is sRGB's [5]_. The paper's Step 1 [1]_ uses the model to fill the sky no photograph shows
(:mod:`.environment`).

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
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from types import MappingProxyType
from typing import Any

import numpy as np
import scipy.optimize
import scipy.sparse
import scipy.sparse.linalg

from ._validation import as_array, as_unit_vector, config_or_default, describe, is_real
from .envmap import (
    _Z_UP,
    _unit_rows,
    envmap_directions,
    horizontal_frame,
)
from .results import SkyParameters

__all__ = [
    "SKY_MODELS",
    "SkyConfig",
    "SkyFitError",
    "SkyModel",
    "fit_sky",
    "preetham_perez_coefficients",
    "preetham_relative_rgb",
    "preetham_zenith_chromaticity",
    "select_sky_model",
    "sky_fit_outliers",
]


# ------------------------------------------------------------------------------------------------
# Configuration
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SkyConfig:
    """Parameters of the environment-map and sky-model stage (paper Sec. 4).

    Parameters
    ----------
    envmap_height : int
        ``He``, rows of the equirectangular map (width ``2 He``). 64 rows are 2.8° texels: the
        paper gives no resolution, and sky and indirect light are low-frequency (paper Sec. 4,
        "Given the low frequency nature of these quantities").
    initial_turbidity : float
        Start of the simplex search: 3.5, "the turbidity of a clear sky" (paper Sec. 4, after
        Preetham et al. 1999).
    turbidity_bounds : (float, float)
        Turbidity range in which Preetham et al. fitted their coefficients (1.7 to 10, Appendix
        A.2); the fit never leaves it.
    max_iter : int
        Nelder-Mead iterations; a 1-D simplex converges in 20-40, 200 is a safe cap.
    xatol : float
        Nelder-Mead tolerance on the turbidity (dimensionless): 1e-3, far below the 0.2 accuracy
        needed.
    fatol : float
        Nelder-Mead tolerance on the objective, which is normalised by ``sum w |A|^2`` (so 1.0 is
        the error of ``k = 0``): 1e-12.
    min_texels : int
        Fewest sky texels :func:`fit_sky` accepts: two unknowns per channel need far more than a
        handful of samples; 20 texels is ~0.1% of a 64-row hemisphere.
    weight_by_solid_angle : bool
        :func:`estimate_environment` weights each texel of Eq. (4) by its solid angle, so the sum
        over "pixels of the environment map" approximates an integral over the sky and does not
        depend on the map's parameterisation (an equirectangular map has ``1 / sin θ`` times more
        texels per steradian near the zenith).
    sky_blue_min : float
        Lowest blue chromaticity ``b / (r + g + b)`` of a sky texel. Neutral greys, white clouds
        and sunlit stone sit at 1/3, foliage at 0.15-0.25, warm plaster and brick at 0.2-0.3. 0.34
        keeps, in solid angle, >= 90% of Preetham clear skies with ``t <= 3`` and the sun above
        30°, and 80-95% with ``t = 4`` (the whitish rows near the horizon and the sun are lost,
        they stay observed non-sky texels).
    sky_luminance_min : float
        Lowest luminance of a sky texel relative to the reference luminance (below); the
        darkest part of a Preetham sky with ``t >= 2.5`` is > 0.3 of its own 90th percentile, so
        0.1 keeps all of it and rejects dark objects (shadowed foliage, dark facades).
    sky_luminance_percentile : float
        The reference luminance is this percentile of the known texels above the horizon (the
        "bright texels" of the upper hemisphere, robust to a few saturated ones): 90.
    outlier_ratio : float or None
        Robust refit of :func:`estimate_environment`: sky texels whose colour differs from the
        first fit by more than this fraction of the model (``|A - k f| > ratio |k f|``) are
        re-labelled non-sky and the fit is repeated once; ``None`` disables it. Measured on
        Mitsuba's Hosek-Wilkie sky (t = 3, sun at 40°, tests/test_skymodel.py): 0.5 flags only
        2% of a clean clear sky (up to 17% for t = 2 with a low sun, where Preetham cannot reach
        Hosek-Wilkie's deep blue; those texels keep their observed radiance), and with bluish
        distant hills at 0.35x the sky radiance that pass the colour detector it lowers the
        relative RMSE of the fitted sky over the true sky from 0.153 to 0.137. 0.75 and above
        no longer catch such hills.
    horizon_angle_tol_deg : float
        A RANSAC plane is "horizontal" when its normal is within 15° of ``up``.
    horizon_inlier_distance : float
        RANSAC inlier distance, metres (5 cm: noise of a multi-view-stereo ground).
    horizon_iterations : int
        Near-horizontal candidate planes scored by RANSAC (drawn among up to 50 times as many
        random triples).
    horizon_max_points : int
        Candidates are scored on a random subset of at most this many vertices (the final plane
        is refitted on every inlier).
    horizon_min_contrast : float
        The plane must be a real surface, not a slice through walls: its point density within
        ``horizon_inlier_distance`` must be at least this many times the density in the slabs
        from 1 to 4 inlier distances on either side. A slice through walls scores ~1.
    horizon : {"auto", "plane", "up"}
        What places the horizon. ``"plane"``: the paper's main horizontal plane of the proxy
        (RANSAC), an error when the proxy has none. ``"up"``: the scene's ``up`` vector, through
        the proxy's lowest points (:func:`horizon_from_up`); the cameras and the sky only need
        its normal, and real multi-view-stereo meshes often lack a dense ground (a facade, a
        roof cap). ``"auto"`` (default): the plane when RANSAC finds one, else ``"up"``; the
        evidence used is recorded in the result (``horizon_evidence`` of ``lighting.json``).
    model : {"auto", "preetham", "perez", "constant"}
        The sky family fitted by Eq. (4) (:data:`SKY_MODELS`). ``"preetham"`` is the paper's;
        ``"auto"`` (default, beyond the paper) picks the family with the lowest error on sky
        texels held out from the fit (:func:`select_sky_model`), preferring the simpler one
        within ``model_margin``; its evidence is kept in :attr:`SkyModel.evidence` and
        ``lighting.json`` "model". Against ``"preetham"`` on seven scenes (``docs/presets.md``,
        the whole pipeline): the free Perez sky was chosen on five, and brought the umbra's
        ``S_env`` closer to the truth on all five (street_sky, the simulated sky: +14/+2/+11% to
        +6/-5/+2%); reflectance LMSE -0.3% to -1.8% on three, +0.6% on street_sky and +3.8% on
        dev_courtyard (320x240).
    model_folds : int
        Contiguous sectors of azimuth the sky texels are split into for the held-out errors.
    model_margin : float
        A simpler family whose held-out error is within this fraction of the best is chosen.
    """

    envmap_height: int = 64
    initial_turbidity: float = 3.5
    turbidity_bounds: tuple[float, float] = (1.7, 10.0)
    max_iter: int = 200
    xatol: float = 1e-3
    fatol: float = 1e-12
    min_texels: int = 20
    weight_by_solid_angle: bool = True
    sky_blue_min: float = 0.34
    sky_luminance_min: float = 0.1
    sky_luminance_percentile: float = 90.0
    outlier_ratio: float | None = 0.5
    horizon_angle_tol_deg: float = 15.0
    horizon_inlier_distance: float = 0.05
    horizon_iterations: int = 500
    horizon_max_points: int = 20_000
    horizon_min_contrast: float = 3.0
    horizon: str = "auto"
    model: str = "auto"
    model_folds: int = 5
    model_margin: float = 0.05

    def __post_init__(self) -> None:
        if self.horizon not in ("auto", "plane", "up"):
            raise ValueError(f"horizon must be 'auto', 'plane' or 'up', got {self.horizon!r}")
        if self.model != "auto" and self.model not in SKY_MODELS:
            raise ValueError(f"model must be 'auto' or one of {SKY_MODELS}, got {self.model!r}")
        if not (is_real(self.model_margin) and 0.0 <= self.model_margin < math.inf):
            raise ValueError(f"model_margin must be a non-negative number, got {self.model_margin!r}")
        if isinstance(self.model_folds, bool) or not isinstance(self.model_folds, (int, np.integer)) or \
                self.model_folds < 2:
            raise ValueError(f"model_folds must be an integer >= 2, got {self.model_folds!r}")
        for name in ("envmap_height", "max_iter", "min_texels", "horizon_iterations", "horizon_max_points"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise ValueError(f"{name} must be a positive integer, got {describe(value)}")
            object.__setattr__(self, name, int(value))
        if self.envmap_height < 2:
            raise ValueError(f"envmap_height must be at least 2, got {self.envmap_height}")
        if self.min_texels < 2:
            raise ValueError(f"min_texels must be at least 2, got {self.min_texels}")
        try:
            lo, hi = (float(b) for b in self.turbidity_bounds)
        except (TypeError, ValueError) as exc:
            raise TypeError(f"turbidity_bounds must be two numbers, got {describe(self.turbidity_bounds)}") from exc
        if not (0.0 < lo < hi < math.inf):
            raise ValueError(f"turbidity_bounds must satisfy 0 < low < high < inf, got {(lo, hi)}")
        object.__setattr__(self, "turbidity_bounds", (lo, hi))
        if not (lo <= float(self.initial_turbidity) <= hi):
            raise ValueError(
                f"initial_turbidity must lie in turbidity_bounds {(lo, hi)}, got {self.initial_turbidity!r}"
            )
        positive = (
            "initial_turbidity",
            "xatol",
            "fatol",
            "sky_luminance_min",
            "horizon_inlier_distance",
            "horizon_min_contrast",
        )
        for name in positive:
            value = float(getattr(self, name))
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive finite number, got {getattr(self, name)!r}")
            object.__setattr__(self, name, value)
        if not (0.0 < float(self.sky_blue_min) < 1.0):
            raise ValueError(f"sky_blue_min must be in (0, 1), got {self.sky_blue_min!r}")
        if not (0.0 <= float(self.sky_luminance_percentile) <= 100.0):
            raise ValueError(f"sky_luminance_percentile must be in [0, 100], got {self.sky_luminance_percentile!r}")
        if self.outlier_ratio is not None and not (math.isfinite(self.outlier_ratio) and self.outlier_ratio > 0):
            raise ValueError(f"outlier_ratio must be a positive number or None, got {self.outlier_ratio!r}")
        if not (0.0 < float(self.horizon_angle_tol_deg) < 90.0):
            raise ValueError(f"horizon_angle_tol_deg must be in (0, 90), got {self.horizon_angle_tol_deg!r}")


class SkyFitError(RuntimeError):
    """The sky model cannot be fitted (too few sky texels, or no signal in them)."""




# ------------------------------------------------------------------------------------------------
# Preetham et al. (1999) sky model
# ------------------------------------------------------------------------------------------------
#: Preetham et al. 1999, Appendix A.2: Perez coefficients (A, B, C, D, E) as ``slope * T + offset``
#: for the luminance Y and the chromaticities x and y. Shape (3 quantities, 5 coefficients, 2).
_PEREZ_TABLE = np.array(
    [
        # Y
        [[0.1787, -1.4630], [-0.3554, 0.4275], [-0.0227, 5.3251], [0.1206, -2.5771], [-0.0670, 0.3703]],
        # x
        [[-0.0193, -0.2592], [-0.0665, 0.0008], [-0.0004, 0.2125], [-0.0641, -0.8989], [-0.0033, 0.0452]],
        # y
        [[-0.0167, -0.2608], [-0.0950, 0.0092], [-0.0079, 0.2102], [-0.0441, -1.6537], [-0.0109, 0.0529]],
    ]
)

#: Preetham et al. 1999, Appendix A.2: zenith chromaticity
#: ``x_z = [T^2, T, 1] @ M_x @ [θs^3, θs^2, θs, 1]`` (same for y), θs in radians.
_ZENITH_X = np.array(
    [
        [0.00166, -0.00375, 0.00209, 0.0],
        [-0.02903, 0.06377, -0.03202, 0.00394],
        [0.11693, -0.21196, 0.06052, 0.25886],
    ]
)
_ZENITH_Y = np.array(
    [
        [0.00275, -0.00610, 0.00317, 0.0],
        [-0.04214, 0.08970, -0.04153, 0.00516],
        [0.15346, -0.26756, 0.06670, 0.26688],
    ]
)

#: CIE XYZ -> linear sRGB / Rec.709 (D65), IEC 61966-2-1.
_XYZ_TO_RGB = np.array(
    [
        [3.2406, -1.5372, -0.4986],
        [-0.9689, 1.8758, 0.0415],
        [0.0557, -0.2040, 1.0570],
    ]
)

#: Lowest cos θ used in the Perez formula (θ <= 89.43°); see :func:`preetham_relative_rgb`.
_COS_THETA_MIN = 0.01


def _check_turbidity(turbidity: object) -> float:
    try:
        t = float(turbidity)  # type: ignore[arg-type]
    except (TypeError, ValueError) as exc:
        raise TypeError(f"turbidity must be a number, got {describe(turbidity)}") from exc
    if not (math.isfinite(t) and t > 0):
        raise ValueError(f"turbidity must be a positive finite number, got {turbidity!r}")
    return t


def preetham_perez_coefficients(turbidity: float) -> np.ndarray:
    """Perez distribution coefficients of Preetham et al. (1999), Appendix A.2.

    Parameters
    ----------
    turbidity : float
        Atmospheric turbidity ``T`` (the table was fitted for 1.7 <= T <= 10).

    Returns
    -------
    (3, 5) float64
        Rows Y, x, y; columns A, B, C, D, E. E.g. ``A_Y = 0.1787 T - 1.4630``.
    """
    t = _check_turbidity(turbidity)
    return _PEREZ_TABLE[..., 0] * t + _PEREZ_TABLE[..., 1]


def preetham_zenith_chromaticity(turbidity: float, sun_zenith: float) -> np.ndarray:
    """CIE xy chromaticity of the zenith, Preetham et al. (1999), Appendix A.2.

    Parameters
    ----------
    turbidity : float
        Atmospheric turbidity ``T``.
    sun_zenith : float
        Angle ``θs`` between the sun and the zenith, radians, in ``[0, π/2]``.

    Returns
    -------
    (2,) float64
        ``(x_z, y_z)``.
    """
    t = _check_turbidity(turbidity)
    ts = float(sun_zenith)
    if not (0.0 <= ts <= math.pi / 2 + 1e-9):
        raise ValueError(f"sun_zenith must be in [0, pi/2] radians, got {sun_zenith!r}")
    tv, sv = np.array([t * t, t, 1.0]), np.array([ts**3, ts**2, ts, 1.0])
    return np.array([tv @ _ZENITH_X @ sv, tv @ _ZENITH_Y @ sv])


def _perez(coeffs: np.ndarray, cos_theta: np.ndarray, gamma: np.ndarray) -> np.ndarray:
    """Perez et al. (1993) distribution ``F(θ, γ) = (1 + A e^{B / cos θ})(1 + C e^{D γ} + E cos² γ)``."""
    a, b, c, d, e = coeffs
    return (1.0 + a * np.exp(b / cos_theta)) * (1.0 + c * np.exp(d * gamma) + e * np.cos(gamma) ** 2)


def _preetham(directions: np.ndarray, sun: np.ndarray, turbidity: float, up: np.ndarray,
              luminance_coefficients: np.ndarray | None = None) -> np.ndarray:
    """Unchecked core of :func:`preetham_relative_rgb` (unit inputs).

    ``luminance_coefficients`` (5,) replace Preetham's ``A..E`` of the luminance ``Y`` (the free
    Perez sky of :class:`SkyModel`, ``model="perez"``); the chromaticities stay Preetham's.
    """
    height = directions @ up
    below = height < 0
    if below.any():  # mirror into the upper hemisphere, where the model is defined
        directions = directions - 2.0 * np.minimum(height, 0.0)[:, None] * up
    cos_theta = np.maximum(np.abs(height), _COS_THETA_MIN)
    gamma = np.arccos(np.clip(directions @ sun, -1.0, 1.0))
    theta_s = math.acos(min(1.0, max(0.0, float(sun @ up))))
    coeffs = preetham_perez_coefficients(turbidity)
    if luminance_coefficients is not None:
        coeffs = np.concatenate([np.asarray(luminance_coefficients, dtype=np.float64)[None], coeffs[1:]])
    x_z, y_z = preetham_zenith_chromaticity(turbidity, theta_s)
    one, ts = np.ones(1), np.array([theta_s])
    # Preetham et al. 1999, Eq. (3) relative to the zenith: Q = Q_z F(θ, γ) / F(0, θs), Q in {Y, x, y}
    big_y = _perez(coeffs[0], cos_theta, gamma) / _perez(coeffs[0], one, ts)
    x = x_z * _perez(coeffs[1], cos_theta, gamma) / _perez(coeffs[1], one, ts)
    y = y_z * _perez(coeffs[2], cos_theta, gamma) / _perez(coeffs[2], one, ts)
    xyz = np.stack([x * big_y / y, big_y, (1.0 - x - y) * big_y / y], axis=1)  # xyY -> XYZ
    return xyz @ _XYZ_TO_RGB.T


def preetham_relative_rgb(
    directions: object,
    *,
    sun_direction: object,
    turbidity: float,
    up: object = _Z_UP,
) -> np.ndarray:
    """Sky colour relative to the zenith, ``f(θ, γ, t)`` of Eq. (4).

    The Perez et al. (1993) distribution ``F(θ, γ) = (1 + A e^{B/cos θ})(1 + C e^{Dγ} + E cos²γ)``
    with the turbidity-dependent coefficients of Preetham et al. (1999) gives the luminance and
    both chromaticities relative to the zenith:

    .. math::

        Y = \\frac{F_Y(θ, γ)}{F_Y(0, θ_s)}, \\quad
        x = x_z \\frac{F_x(θ, γ)}{F_x(0, θ_s)}, \\quad
        y = y_z \\frac{F_y(θ, γ)}{F_y(0, θ_s)}

    with Preetham's zenith chromaticity ``(x_z, y_z)``; ``xyY`` is converted to XYZ and to
    linear Rec.709 / sRGB RGB. The zenith therefore has luminance 1 and colour
    ``RGB(x_z, y_z, Y = 1)``; the absolute zenith luminance is left to the per-channel scale
    ``k`` of Eq. (4).

    Parameters
    ----------
    directions : (N, 3) array_like
        World view directions (normalised here).
    sun_direction : (3,) array_like
        Unit vector toward the sun, world frame; must be above the horizon (``· up > 0``).
    turbidity : float
        Atmospheric turbidity ``t`` (the coefficients were fitted for 1.7 <= t <= 10).
    up : (3,) array_like, optional
        Zenith direction, default +Z. ``θ`` is the angle to ``up``, ``γ`` the angle to the sun.

    Returns
    -------
    (N, 3) float64
        Linear RGB, relative to the zenith luminance.

    Notes
    -----
    ``cos θ`` is clamped to >= 0.01 (θ <= 89.43°). In the valid turbidity range every ``B`` is
    negative, so ``e^{B / cos θ}`` tends smoothly to 0 at the horizon, but ``1 / cos θ`` itself
    diverges there; the clamp avoids the division by zero. The model is undefined below the
    horizon: a direction there gets the value of its mirror image about the horizontal plane
    (continuous across the horizon, finite everywhere).
    """
    d = _unit_rows(directions, "directions")
    up = as_unit_vector(up, "up")
    sun = as_unit_vector(sun_direction, "sun_direction")
    if sun @ up <= 0:
        raise ValueError(f"sun_direction {sun.tolist()} must be above the horizon (sun_direction · up > 0)")
    return _preetham(d, sun, _check_turbidity(turbidity), up)


# ------------------------------------------------------------------------------------------------
# Sky model fit, Eq. (4)
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class SkyModel:
    """The fitted sky: ``L(p) = k ⊙ f(θ_p, γ_p, t)`` (paper Eq. 4).

    Parameters
    ----------
    turbidity : float
        Atmospheric turbidity ``t`` (Preetham et al. 1999).
    scale : (3,) float64
        ``k``: per-channel scale from :func:`preetham_relative_rgb` (zenith luminance 1) to image
        radiance, image units.
    residual : float
        RMS of ``k f − A`` over the fitted texels and channels (weighted as in the fit), image
        units.
    converged : bool
        Whether the simplex search met its tolerances within ``max_iter``.
    n_iter : int
        Nelder-Mead iterations.
    sun_direction : (3,) float64
        Unit vector toward the sun, world frame.
    up : (3,) float64
        Zenith, world frame.
    n_texels : int
        Number of texels fitted.
    model : {"preetham", "perez", "constant"}
        The sky family (:data:`SKY_MODELS`): ``"preetham"``, the paper's Perez distribution with
        Preetham's turbidity-dependent coefficients; ``"perez"``, the five Perez coefficients of
        the luminance fitted freely (``coefficients``), the chromaticities Preetham's at
        ``turbidity``; ``"constant"``, the same radiance ``k`` in every direction (``f = 1``).
    coefficients : (5,) float64, optional
        ``A..E`` of the luminance distribution, ``model="perez"`` only.
    evidence : mapping, optional
        How the model was chosen (:func:`select_sky_model`): the held-out errors of the
        candidates, the folds and texels; empty when the model was given.
    """

    turbidity: float
    scale: np.ndarray
    residual: float
    converged: bool
    n_iter: int
    sun_direction: np.ndarray
    up: np.ndarray
    n_texels: int
    model: str = "preetham"
    coefficients: np.ndarray | None = None
    evidence: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "turbidity", _check_turbidity(self.turbidity))
        scale = as_array(self.scale, "scale", shape=(3,), dtype=np.float64)
        if (scale < 0).any():
            raise ValueError(f"scale must be non-negative, got {scale.tolist()}")
        object.__setattr__(self, "scale", scale)
        residual = float(self.residual)
        if not (math.isfinite(residual) and residual >= 0):
            raise ValueError(f"residual must be a non-negative number, got {self.residual!r}")
        object.__setattr__(self, "residual", residual)
        object.__setattr__(self, "converged", bool(self.converged))
        object.__setattr__(self, "n_iter", int(self.n_iter))
        object.__setattr__(self, "n_texels", int(self.n_texels))
        up = as_unit_vector(self.up, "up")
        sun = as_unit_vector(self.sun_direction, "sun_direction")
        if sun @ up <= 0:
            raise ValueError(f"sun_direction {sun.tolist()} must be above the horizon (sun_direction · up > 0)")
        object.__setattr__(self, "up", up)
        object.__setattr__(self, "sun_direction", sun)
        if self.model not in SKY_MODELS:
            raise ValueError(f"model must be one of {SKY_MODELS}, got {self.model!r}")
        if (self.model == "perez") != (self.coefficients is not None):
            raise ValueError("coefficients must be given for model 'perez' and only for it")
        if self.coefficients is not None:
            object.__setattr__(self, "coefficients", as_array(self.coefficients, "coefficients", shape=(5,),
                                                              dtype=np.float64))
        if not isinstance(self.evidence, Mapping):
            raise TypeError(f"evidence must be a mapping, got {describe(self.evidence)}")
        object.__setattr__(self, "evidence", MappingProxyType(dict(self.evidence)))

    def relative(self, directions: np.ndarray) -> np.ndarray:
        """``f`` of Eq. (4) toward unit world directions ``(N, 3)``, before the scale ``k``, (N, 3)."""
        if self.model == "constant":
            return np.ones((len(directions), 3))
        return _preetham(directions, self.sun_direction, self.turbidity, self.up, self.coefficients)

    def radiance(self, directions: object) -> np.ndarray:
        """Sky radiance ``k ⊙ f`` toward world directions ``(N, 3)``: ``(N, 3)`` float64, image units.

        Clipped at 0 (the model is positive in its valid range; the clip only guards extreme
        turbidities). Below the horizon the value of the mirrored direction is returned (see
        :func:`preetham_relative_rgb`).
        """
        d = _unit_rows(directions, "directions")
        return np.maximum(self.scale * self.relative(d), 0.0)

    def to_parameters(self) -> SkyParameters:
        """The JSON summary (:class:`mvintrinsic.results.SkyParameters`)."""
        return SkyParameters(model=self.model, turbidity=self.turbidity, scale=self.scale, residual=self.residual,
                             coefficients=self.coefficients)

    def __repr__(self) -> str:
        return (
            f"SkyModel({self.model}, turbidity={self.turbidity:.3f}, scale={np.round(self.scale, 5).tolist()}, "
            f"residual={self.residual:.4g}, converged={self.converged}, n_iter={self.n_iter}, n_texels={self.n_texels})"
        )



def _best_scale(f: np.ndarray, a: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Closed-form ``k_c = Σ w f_c A_c / Σ w f_c²`` (normal equation of Eq. 4 for fixed t), (3,)."""
    num = (w[:, None] * f * a).sum(axis=0)
    den = (w[:, None] * f * f).sum(axis=0)
    return np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)


#: The sky families of :class:`SkyModel`, from the fewest parameters to the most.
SKY_MODELS = ("constant", "preetham", "perez")

#: Weight of the prior that keeps the free Perez coefficients near Preetham's at the fitted
#: turbidity (``model="perez"``): added to the normalised objective as this times the mean squared
#: coefficient change over ``|c_Preetham| + 0.1``. Where the views see sky, the data moves the
#: coefficients (an objective change of 1e-2 is 1% of the sky's energy); near the sun, which no
#: view sees, the prior keeps Preetham's circumsolar shape instead of an unconstrained one.
#: Measured against Mitsuba's sky (solid-angle-weighted model / truth within 5-30 and 30-60
#: degrees of the sun, R/G/B; scratch, docs/presets.md): courtyard_s1 Preetham 1.05/1.20/1.31 and
#: 1.30/1.23/1.18, free Perez with 1e-3 1.17/1.35/1.49 and 1.28/1.25/1.22, with 1e-2 1.10/1.27/1.39
#: and 1.21/1.18/1.15; the demo Preetham 1.22/1.32/1.40 and 1.42/1.30/1.23, 1e-3 1.14/1.23/1.32 and
#: 1.25/1.16/1.12, 1e-2 1.11/1.20/1.28 and 1.23/1.14/1.09.
PEREZ_PRIOR = 1e-2


def _check_fit_inputs(directions: object, radiance: object, sun_direction: object, up: object,
                      weights: object | None, config: SkyConfig
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
    """Validated ``(d, a, w, sun, up, energy)`` of the texels with a positive weight (:func:`fit_sky`)."""
    d = _unit_rows(directions, "directions")
    a = as_array(radiance, "radiance", shape=(len(d), 3), dtype=np.float64)
    if (a < 0).any():
        raise ValueError("radiance must be non-negative")
    if weights is None:
        w = np.ones(len(d))
    else:
        w = as_array(weights, "weights", shape=(len(d),), dtype=np.float64)
        if (w < 0).any():
            raise ValueError("weights must be non-negative")
    up = as_unit_vector(up, "up")
    sun = as_unit_vector(sun_direction, "sun_direction")
    if sun @ up <= 0:
        raise ValueError(f"sun_direction {sun.tolist()} must be above the horizon (sun_direction · up > 0)")
    used = w > 0
    n = int(used.sum())
    if n < config.min_texels:
        raise SkyFitError(f"too few sky texels to fit the sky model: {n} (need at least {config.min_texels}): the "
                          "views show too little bright sky above the horizon (sky-less, black or grey images?)")
    d, a, w = d[used], a[used], w[used]
    energy = float((w[:, None] * a * a).sum())
    if energy <= 0:
        raise SkyFitError(f"the {n} sky texels are all black; the sky model cannot be fitted")
    return d, a, w, sun, up, energy


def _model_residual(f: np.ndarray, k: np.ndarray, a: np.ndarray, w: np.ndarray) -> float:
    return math.sqrt(float((w[:, None] * (f * k - a) ** 2).sum()) / (3.0 * float(w.sum())))


def _fit_perez(preetham: SkyModel, d: np.ndarray, a: np.ndarray, w: np.ndarray, energy: float,
               config: SkyConfig) -> SkyModel:
    """The five luminance coefficients of the Perez distribution, from Preetham's at its turbidity."""
    start = preetham_perez_coefficients(preetham.turbidity)[0]
    spread = np.abs(start) + 0.1
    sun, up, t = preetham.sun_direction, preetham.up, preetham.turbidity
    check = envmap_directions(16, up=up).reshape(-1, 3)
    check = np.concatenate([check[check @ up > 0], sun[None]])  # the whole sky, the sun included

    def objective(c: np.ndarray) -> float:
        f = _preetham(d, sun, t, up, c)
        if not np.isfinite(f).all() or not (_preetham(check, sun, t, up, c)[:, 1] > 0).all():
            return 2.0 + float(np.sum(((c - start) / spread) ** 2))  # worse than k = 0 (error 1)
        k = _best_scale(f, a, w)
        err = float((w[:, None] * (f * k - a) ** 2).sum()) / energy
        return err + PEREZ_PRIOR * float(np.mean(((c - start) / spread) ** 2))

    result = scipy.optimize.minimize(objective, x0=start, method="Nelder-Mead",
                                     options={"maxiter": 200 * 5, "xatol": 1e-4, "fatol": config.fatol})
    c = result.x if objective(result.x) < objective(start) else start
    f = _preetham(d, sun, t, up, c)
    k = np.maximum(_best_scale(f, a, w), 0.0)
    return replace(preetham, model="perez", coefficients=c, scale=k, residual=_model_residual(f, k, a, w),
                   converged=bool(result.success), n_iter=preetham.n_iter + int(result.nit))


def fit_sky(
    directions: object,
    radiance: object,
    *,
    sun_direction: object,
    up: object = _Z_UP,
    config: SkyConfig | None = None,
    weights: object | None = None,
    model: str = "preetham",
) -> SkyModel:
    """Fit the Preetham sky (or another :data:`SKY_MODELS` family) to observed sky texels (paper Eq. 4).

    .. math::

        \\min_{t, \\mathbf{k}} \\; \\sum_{p \\in \\mathcal{P}} w_p
        \\left\\| \\mathbf{k} \\odot f(θ_p, γ_p, t) - \\mathbf{A}_p \\right\\|^2

    The paper prints Eq. (4) without the square; a least-squares objective is what its "solving
    a linear system" for ``k`` implies, and is used here. As in the paper, the turbidity is
    found by simplex search (Nelder-Mead, :func:`scipy.optimize.minimize`) started at
    ``config.initial_turbidity`` (3.5), and at every evaluation ``k`` is the closed-form linear
    least-squares solution per channel for the current ``t``. The objective is divided by
    ``Σ w |A|²`` so that the tolerance ``fatol`` is scale-free. The turbidity is kept in
    ``config.turbidity_bounds`` by evaluating the model at the clipped turbidity and adding the
    distance outside the bounds to the (normalised, <= 1) objective, so that any point outside
    is worse than the nearest bound; the returned turbidity is the clipped one.

    Parameters
    ----------
    directions : (N, 3) array_like
        World directions of the sky texels (normalised here).
    radiance : (N, 3) array_like
        Their observed linear RGB radiance ``A_p``, image units, finite and non-negative.
    sun_direction : (3,) array_like
        Unit vector toward the sun, world frame, above the horizon.
    up : (3,) array_like, optional
        Zenith, default +Z.
    config : SkyConfig, optional
    weights : (N,) array_like, optional
        Non-negative weight ``w_p`` of each texel (e.g. its solid angle); default 1.
    model : {"preetham", "perez", "constant"}, optional
        ``"preetham"`` (the paper, default) as above. ``"constant"``: ``f = 1``, ``k`` the
        weighted mean radiance (an overcast or barely seen sky). ``"perez"`` (beyond the paper):
        Preetham's fit, then the five Perez coefficients of the luminance freed (Nelder-Mead from
        Preetham's, with the weak prior :data:`PEREZ_PRIOR` toward them and a positive sky
        everywhere), the chromaticities kept.

    Returns
    -------
    SkyModel

    Raises
    ------
    SkyFitError
        If fewer than ``config.min_texels`` texels have a positive weight, or all their radiance
        is zero.
    """
    config = config_or_default(config, SkyConfig)
    if model not in SKY_MODELS:
        raise ValueError(f"model must be one of {SKY_MODELS}, got {model!r}")
    d, a, w, sun, up, energy = _check_fit_inputs(directions, radiance, sun_direction, up, weights, config)
    n = len(d)
    lo, hi = config.turbidity_bounds
    if model == "constant":
        f = np.ones_like(a)
        k = np.maximum(_best_scale(f, a, w), 0.0)
        return SkyModel(turbidity=config.initial_turbidity, scale=k, residual=_model_residual(f, k, a, w),
                        converged=True, n_iter=0, sun_direction=sun, up=up, n_texels=n, model="constant")

    def objective(x: np.ndarray) -> float:
        t = min(hi, max(lo, float(x[0])))
        f = _preetham(d, sun, t, up)
        k = _best_scale(f, a, w)
        err = float((w[:, None] * (f * k - a) ** 2).sum()) / energy
        return err + abs(float(x[0]) - t)  # bound penalty (see docstring)

    result = scipy.optimize.minimize(
        objective,
        x0=np.array([config.initial_turbidity]),
        method="Nelder-Mead",
        options={"maxiter": config.max_iter, "xatol": config.xatol, "fatol": config.fatol},
    )
    t = min(hi, max(lo, float(result.x[0])))
    f = _preetham(d, sun, t, up)
    k = np.maximum(_best_scale(f, a, w), 0.0)
    preetham = SkyModel(
        turbidity=t,
        scale=k,
        residual=_model_residual(f, k, a, w),
        converged=bool(result.success),
        n_iter=int(result.nit),
        sun_direction=sun,
        up=up,
        n_texels=n,
    )
    return preetham if model == "preetham" else _fit_perez(preetham, d, a, w, energy, config)


def _azimuth_folds(directions: np.ndarray, sun: np.ndarray, up: np.ndarray, folds: int) -> np.ndarray:
    """Fold of each direction: ``folds`` contiguous sectors of azimuth about ``up``, equal in count,
    starting at the sun's azimuth (so each held-out sector is an extrapolation in azimuth)."""
    frame = horizontal_frame(up, sun if abs(sun @ up) < 1 - 1e-9 else None)
    azimuth = np.arctan2(directions @ frame[1], directions @ frame[0]) % (2 * math.pi)
    ranks = np.argsort(np.argsort(azimuth, kind="stable"), kind="stable")
    return (ranks * folds) // len(directions)


def select_sky_model(
    directions: object,
    radiance: object,
    *,
    sun_direction: object,
    up: object = _Z_UP,
    config: SkyConfig | None = None,
    weights: object | None = None,
) -> SkyModel:
    """The sky family the texels support, by their error held out from the fit (beyond the paper).

    The texels are split into ``config.model_folds`` contiguous sectors of azimuth; each family of
    :data:`SKY_MODELS` is fitted (:func:`fit_sky`) on all sectors but one and scored on the one
    held out, ``Σ w |k f - A|²`` summed over the folds and divided by ``Σ w |A|²``. The family
    with the lowest held-out error wins, except that a simpler family within
    ``config.model_margin`` (relative) of it is preferred: the model is no bigger than the sky
    needs. The winner is refitted on every texel; its ``evidence`` holds the held-out errors.
    With fewer than ``config.min_texels`` texels in a training set the paper's Preetham sky is
    fitted without a choice (``evidence["chosen_by"] = "too few texels"``).

    Parameters
    ----------
    directions, radiance, sun_direction, up, config, weights
        As :func:`fit_sky`.

    Returns
    -------
    SkyModel
    """
    config = config_or_default(config, SkyConfig)
    d, a, w, sun, up, energy = _check_fit_inputs(directions, radiance, sun_direction, up, weights, config)
    folds = _azimuth_folds(d, sun, up, config.model_folds)
    smallest_training = min(int((folds != k).sum()) for k in range(config.model_folds))
    if smallest_training < config.min_texels:
        model = fit_sky(d, a, sun_direction=sun, up=up, config=config, weights=w)
        return replace(model, evidence={"chosen_by": "too few texels", "texels": len(d)})
    errors = {}
    for family in SKY_MODELS:
        sse = 0.0
        for k in range(config.model_folds):
            train, test = folds != k, folds == k
            fitted = fit_sky(d[train], a[train], sun_direction=sun, up=up, config=config, weights=w[train],
                             model=family)
            sse += float((w[test, None] * (fitted.radiance(d[test]) - a[test]) ** 2).sum())
        errors[family] = sse / energy
    best = min(errors.values())
    chosen = next(f for f in SKY_MODELS if errors[f] <= best * (1.0 + config.model_margin))
    model = fit_sky(d, a, sun_direction=sun, up=up, config=config, weights=w, model=chosen)
    return replace(model, evidence={"chosen_by": "held-out error", "held_out_error": errors,
                                    "folds": config.model_folds, "margin": config.model_margin, "texels": len(d)})


def sky_fit_outliers(
    model: SkyModel, directions: object, radiance: object, *, config: SkyConfig | None = None
) -> np.ndarray:
    """Texels that a fitted sky does not explain: ``|A − k f| > config.outlier_ratio · |k f|``.

    Used by :func:`estimate_environment` for its one robust refit: such texels are distant
    objects that passed the colour detector (or clouds), and are re-labelled non-sky.

    Parameters
    ----------
    model : SkyModel
    directions : (N, 3) array_like
        World directions.
    radiance : (N, 3) array_like
        Observed linear RGB, image units.
    config : SkyConfig, optional
        ``outlier_ratio``; ``None`` there means no texel is an outlier.

    Returns
    -------
    (N,) bool
        True on outliers (RGB Euclidean norms).
    """
    if not isinstance(model, SkyModel):
        raise TypeError(f"model must be a SkyModel, got {describe(model)}")
    config = config_or_default(config, SkyConfig)
    d = _unit_rows(directions, "directions")
    a = as_array(radiance, "radiance", shape=(len(d), 3), dtype=np.float64)
    if config.outlier_ratio is None:
        return np.zeros(len(d), dtype=bool)
    predicted = model.radiance(d)
    return np.linalg.norm(a - predicted, axis=1) > config.outlier_ratio * np.linalg.norm(predicted, axis=1)
