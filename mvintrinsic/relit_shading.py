"""Relit environment shading (paper Sec. 8, "Adjusting Shading"): how S_sky and S_ind follow the sun.

The paper adjusts the environment shading for the new sun [1]_. Two readings, selected by
:attr:`~mvintrinsic.caster.RelightConfig.sky` and applied by
:class:`~mvintrinsic.relight.Relighter`: the paper's (a Rayleigh-transmittance tint of ``S_sky``
and ``S_ind`` scaled by the sine of the elevation, :func:`paper_environment_factors`, with the
optical depth of [3]_ and the air mass of [4]_) and the fitted Preetham sky re-evaluated at the
new sun (:func:`sky_irradiance_ratio`, [2]_). Their measurements are in :mod:`.relight`'s
docstring and ``docs/relight.md``.

References
----------
.. [1] S. Duchêne, C. Riant, G. Chaurasia, J. Lopez-Moreno, P.-Y. Laffont, S. Popov, A. Bousseau
   and G. Drettakis, "Multi-View Intrinsic Images of Outdoors Scenes with an Application to
   Relighting", ACM Transactions on Graphics 34(5), 2015, Sec. 8.
.. [2] A. J. Preetham, P. Shirley and B. Smits, "A Practical Analytic Model for Daylight", Proc.
   SIGGRAPH 99, 91-100, 1999. Appendix A.2: the absolute zenith luminance.
.. [3] J. E. Hansen and L. D. Travis, "Light scattering in planetary atmospheres", Space Science
   Reviews 16, 527-610, 1974: the Rayleigh optical depth at sea level,
   ``0.008569 lambda^-4 (1 + 0.0113 lambda^-2 + 0.00013 lambda^-4)``, lambda in micrometres.
.. [4] F. Kasten and A. T. Young, "Revised optical air mass tables and approximation formula",
   Applied Optics 28(22), 4735-4738, 1989.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING

import cv2
import numpy as np

from ._validation import as_unit_vector, is_real
from .caster import _check_sun
from .envmap import envmap_directions, horizontal_frame, texel_solid_angles
from .image_model import LUMINANCE_WEIGHTS
from .skymodel import preetham_relative_rgb

if TYPE_CHECKING:
    from ._cluster import _Rebuilt
    from .caster import RelightConfig
    from .raytrace import Tracer
    from .results import IntrinsicLayers
    from .shadow_caster import ShadowCaster

__all__ = ["NORMAL_GRID_HEIGHT", "RGB_WAVELENGTHS_UM", "SKY_GRID_HEIGHT", "SKY_RATIO_FLOOR", "paper_environment_factors", "sky_irradiance_ratio",
           "sky_pixel_factors"]

# ---------------------------------------------------------------------------------------------
# environment shading at the new sun
# ---------------------------------------------------------------------------------------------
#: Rows of the full-sphere grid of sky directions over which the sky irradiance is summed (its
#: upper half: 32 x 128 texels of 2.8 degrees, SkyConfig's envmap resolution).
SKY_GRID_HEIGHT = 64

#: Rows of the full-sphere grid of normals on which the sky irradiance is tabulated (5.6 degrees);
#: a pixel's value is the bilinear interpolation of the table at its normal. The irradiance is a
#: cosine-smoothed function of the normal: against the exact sum at each of 2000 random normals,
#: the interpolated ratio is within 0.12% for 99% of them and 1.1% at worst (normals grazing the
#: horizon), for sun moves of 10 to 30 degrees and turbidities 2 and 3.5.
NORMAL_GRID_HEIGHT = 32


def _zenith_luminance(turbidity: float, sun_zenith: float) -> float:
    """Absolute zenith luminance of the Preetham sky, kcd/m^2 (Preetham et al. 1999, Appendix A.2).

    ``Y_z = (4.0453 T - 4.9710) tan(chi) - 0.2155 T + 2.4192``, ``chi = (4/9 - T/120)(pi - 2 theta_s)``.
    """
    chi = (4.0 / 9.0 - turbidity / 120.0) * (math.pi - 2.0 * sun_zenith)
    return (4.0453 * turbidity - 4.9710) * math.tan(chi) - 0.2155 * turbidity + 2.4192


def _sky_irradiance_grid(sun: np.ndarray, turbidity: float, up: np.ndarray) -> np.ndarray:
    """Preetham sky irradiance / pi on the normal grid, ``(Hn, 2 Hn, 3)`` float64 (relative units).

    ``E(n) = (1 / pi) sum_k Y_z f(w_k) max(0, n . w_k) Omega_k`` over the texels ``w_k`` above the
    horizon, ``f`` the sky's colour relative to its zenith (:func:`preetham_relative_rgb`) and
    ``Y_z`` the absolute zenith luminance (:func:`_zenith_luminance`), which the relative model
    leaves to the fitted scale ``k`` of Eq. (4): ``k`` fixes ``Y_z`` at the capture sun, and ``k Y_z(d')
    / Y_z(d)`` is the sky at the new one.
    """
    half = SKY_GRID_HEIGHT // 2
    directions = envmap_directions(SKY_GRID_HEIGHT, up=up)[:half].reshape(-1, 3)
    omega = texel_solid_angles(SKY_GRID_HEIGHT)[:half].reshape(-1)
    sun_zenith = math.acos(max(-1.0, min(1.0, float(sun @ up))))
    relative = preetham_relative_rgb(directions, sun_direction=sun, turbidity=turbidity, up=up)
    weighted = np.maximum(relative, 0.0) * (_zenith_luminance(turbidity, sun_zenith) * omega / math.pi)[:, None]
    normals = envmap_directions(NORMAL_GRID_HEIGHT, up=up).reshape(-1, 3)
    cosine = np.maximum(normals.astype(np.float32) @ directions.T.astype(np.float32), 0.0)
    return (cosine.astype(np.float64) @ weighted).reshape(NORMAL_GRID_HEIGHT, 2 * NORMAL_GRID_HEIGHT, 3)


#: Rows of the bands in which :meth:`_NewSun.image` composes a relit image (32-128 time alike at 1000x750:
#: 8.8-9.3 ms per view against 25 ms for whole-image passes, one core).
COMPOSE_ROWS = 64

#: Normals whose sky irradiance at the capture sun is below this fraction of the largest (normals
#: that see at most a sliver of sky at the horizon, whose S_sky is about 0) keep their S_sky: a
#: ratio of two near-zero sums is noise.
SKY_RATIO_FLOOR = 1e-3


def _grid_ratio(new: np.ndarray, old: np.ndarray) -> np.ndarray:
    """``new / old`` per texel and channel, 1 where ``old`` is below :data:`SKY_RATIO_FLOOR` of its max."""
    floor = SKY_RATIO_FLOOR * float(old.max()) if old.size else 0.0
    return np.divide(new, old, out=np.ones_like(new), where=old > floor)


class _SphereLookup:
    """Bilinear interpolation of an equirectangular full-sphere table at fixed directions.

    The table's texel ``(v, u)`` is at polar angle ``pi (v + 0.5) / He`` from ``up`` and azimuth
    ``2 pi (u + 0.5) / (2 He)`` (:func:`~mvintrinsic.envmap.envmap_directions`); columns wrap,
    rows clamp at the poles. Indices and weights are computed once.
    """

    def __init__(self, directions: np.ndarray, height: int, up: np.ndarray) -> None:
        d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
        width = 2 * height
        local = d @ horizontal_frame(up).T
        theta = np.arccos(np.clip(local[:, 2], -1.0, 1.0))
        phi = np.mod(np.arctan2(local[:, 1], local[:, 0]), 2.0 * math.pi)
        v = theta * height / math.pi - 0.5
        u = phi * width / (2.0 * math.pi) - 0.5
        v0, u0 = np.floor(v), np.floor(u)
        fv, fu = v - v0, u - u0
        r0 = np.clip(v0, 0, height - 1).astype(np.int64)
        r1 = np.clip(v0 + 1, 0, height - 1).astype(np.int64)
        c0 = np.mod(u0, width).astype(np.int64)
        c1 = np.mod(u0 + 1, width).astype(np.int64)
        self.index = np.stack([r0 * width + c0, r0 * width + c1, r1 * width + c0, r1 * width + c1], axis=1)
        self.weight = np.stack([(1 - fv) * (1 - fu), (1 - fv) * fu, fv * (1 - fu), fv * fu], axis=1)
        self.shape = np.shape(directions)[:-1]

    def __call__(self, table: np.ndarray) -> np.ndarray:
        flat = table.reshape(-1, table.shape[-1])
        out = np.einsum("nk,nkc->nc", self.weight, flat[self.index])
        return out.reshape(*self.shape, table.shape[-1])


def sky_irradiance_ratio(normals: np.ndarray, old_sun: np.ndarray, new_sun: np.ndarray, *, turbidity: float,
                         up: np.ndarray = (0.0, 0.0, 1.0)) -> np.ndarray:
    """Sky irradiance of the Preetham model at a new sun over the old one, per normal (``sky="model"``).

    .. math::

        \\rho(n) = \\frac{E_{sky}(n; d')}{E_{sky}(n; d)}, \\qquad
        E_{sky}(n; d) = \\frac{1}{\\pi} \\int_{\\Omega_{sky}} L_{sky}(\\omega; d) \\max(0, n \\cdot \\omega)
        \\, d\\omega

    with ``L_sky`` the Preetham sky of Eq. (4) at turbidity ``t`` including its absolute zenith
    luminance (Preetham et al. 1999, Appendix A.2), integrated over the directions above the
    horizon (a :data:`SKY_GRID_HEIGHT`-row grid), unoccluded. The scale ``k`` of Eq. (4) cancels.
    The ratio is tabulated on a :data:`NORMAL_GRID_HEIGHT`-row grid of normals and interpolated.

    Parameters
    ----------
    normals : (..., 3) array_like
        Unit normals, world frame.
    old_sun, new_sun : (3,) array_like
        Unit vectors toward the capture sun and the new sun, world frame, above the horizon.
    turbidity : float
        Turbidity ``t`` of the fitted sky (:attr:`mvintrinsic.results.SkyParameters.turbidity`).
    up : (3,) array_like, optional
        World up vector (the sky's zenith).

    Returns
    -------
    (..., 3) float64
        Per-channel ratio (1 for normals that see no sky, :data:`SKY_RATIO_FLOOR`); exactly 1
        when ``new_sun == old_sun``, up to the interpolation's rounding.
    """
    up = as_unit_vector(up, "up")
    old = _check_sun(old_sun, up)
    new = _check_sun(new_sun, up)
    if not is_real(turbidity) or not 0.0 < turbidity < np.inf:
        raise ValueError(f"turbidity must be a finite number > 0, got {turbidity!r}")
    normals = np.asarray(normals, dtype=np.float64)
    if normals.ndim < 1 or normals.shape[-1] != 3:
        raise ValueError(f"normals must have shape (..., 3), got shape {normals.shape}")
    turbidity = float(turbidity)
    ratio = _grid_ratio(_sky_irradiance_grid(new, turbidity, up), _sky_irradiance_grid(old, turbidity, up))
    return _SphereLookup(normals, NORMAL_GRID_HEIGHT, up)(ratio)


#: Dominant wavelengths of the Rec.709 / sRGB primaries (R, G, B), micrometres: where the paper's
#: red shift (:func:`paper_environment_factors`) reads the Rayleigh optical depth.
RGB_WAVELENGTHS_UM = np.array([0.611, 0.549, 0.464])


def _rayleigh_optical_depth(wavelength_um: np.ndarray) -> np.ndarray:
    """Rayleigh optical depth of the whole atmosphere at sea level (Hansen & Travis 1974)."""
    lam = np.asarray(wavelength_um, dtype=np.float64)
    return 0.008569 * lam**-4 * (1.0 + 0.0113 * lam**-2 + 0.00013 * lam**-4)


def _air_mass(elevation: float) -> float:
    """Relative optical air mass at a solar elevation (radians), Kasten & Young (1989)."""
    degrees = math.degrees(elevation)
    return 1.0 / (math.sin(elevation) + 0.50572 * (degrees + 6.07995) ** -1.6364)


def paper_environment_factors(old_sun: np.ndarray, new_sun: np.ndarray, *,
                              up: np.ndarray = (0.0, 0.0, 1.0)) -> tuple[np.ndarray, float]:
    """Our reading of the paper's environment adjustment (``sky="paper"``, Sec. 8).

    The paper "render[s] an approximate effect of illumination changes by adjusting the sun
    shading intensity according to a cosine factor with respect to elevation and the horizontal
    plane, and shifting S_sky towards red in the morning and afternoon. We also diminish S_ind
    with a similar amount". It gives no formula; this is our reading, tied to the change of the
    sun's elevation from ``el`` to ``el'``:

    * the "cosine factor with respect to [...] the horizontal plane" is the cosine between the
      sun and the horizontal plane's normal, ``sin(el)``; ``S_ind``, light the sun brought to
      the scene, is scaled by its change ``f = sin(el') / sin(el)`` (the "similar amount");
    * the red shift of ``S_sky`` is the change of colour of the light through the atmosphere's
      Rayleigh scattering: with the optical depth ``tau_c`` at each primary's dominant wavelength
      (:data:`RGB_WAVELENGTHS_UM`, Hansen & Travis 1974) and the air mass ``m(el)`` (Kasten &
      Young 1989), ``t_c = exp(-tau_c (m(el') - m(el)))``, normalised to unit luminance (a shift
      of colour, not of brightness): ``g = t / (0.2126 t_R + 0.7152 t_G + 0.0722 t_B)``. A lower
      sun gives ``g_R > g_G > g_B``; 35 to 25 degrees gives ``g = (1.02, 1.00, 0.94)``.

    Parameters
    ----------
    old_sun, new_sun : (3,) array_like
        Unit vectors toward the capture sun and the new sun, world frame, above the horizon.
    up : (3,) array_like, optional
        World up vector.

    Returns
    -------
    sky_gain : (3,) float64
        ``g``, multiplies ``S_sky`` (RGB).
    indirect_factor : float
        ``f``, multiplies ``S_ind``.
    """
    up = as_unit_vector(up, "up")
    old = _check_sun(old_sun, up)
    new = _check_sun(new_sun, up)
    old_el, new_el = math.asin(min(1.0, float(old @ up))), math.asin(min(1.0, float(new @ up)))
    factor = math.sin(new_el) / math.sin(old_el)
    transmittance = np.exp(-_rayleigh_optical_depth(RGB_WAVELENGTHS_UM) * (_air_mass(new_el) - _air_mass(old_el)))
    return transmittance / float(LUMINANCE_WEIGHTS @ transmittance), factor


def sky_pixel_factors(directions: np.ndarray, old_sun: np.ndarray, new_sun: np.ndarray, *, how: str,
                      turbidity: float = 3.5, up: np.ndarray = (0.0, 0.0, 1.0)) -> np.ndarray:
    """The change of colour of the sky pixels at a new sun (Sec. 8: "we detect sky pixels and change
    their color near the horizon"; :attr:`~mvintrinsic.caster.RelightConfig.sky_pixels`).

    * ``how="paper"``: our reading (the paper gives no formula): the red shift ``g`` of
      :func:`paper_environment_factors`, strongest at the horizon and gone at the zenith:
      ``g ** (1 - sin(alt))``, ``alt`` the altitude of the pixel's direction. 1 for a move in
      azimuth alone;
    * ``how="model"``: the fitted Preetham sky's radiance in the pixel's direction at the new sun
      over that at the old one (Eq. 4 with the absolute zenith luminance, as
      :func:`sky_irradiance_ratio`).

    Parameters
    ----------
    directions : (N, 3) array_like
        Unit view directions of the sky pixels, world frame (toward the sky).
    old_sun, new_sun : (3,) array_like
        Unit vectors toward the capture sun and the new sun, world frame, above the horizon.
    how : {"paper", "model"}
    turbidity : float, optional
        Turbidity of the sky model (``how="model"``).
    up : (3,) array_like, optional
        World up vector.

    Returns
    -------
    (N, 3) float32
        Per-channel factors of the pixels' radiance; exactly 1 when ``new_sun == old_sun``.
    """
    return _SkyPixels(None, directions, old_sun, how=how, turbidity=turbidity, up=up).factors(new_sun)


class _SkyPixels:
    """The sky pixels of one view (flat ``index``, view ``directions``) and what of
    :func:`sky_pixel_factors` does not depend on the new sun, computed once."""

    def __init__(self, index: np.ndarray | None, directions: np.ndarray, old_sun: np.ndarray, *, how: str,
                 turbidity: float, up: np.ndarray) -> None:
        if how not in ("paper", "model"):
            raise ValueError(f"how must be 'paper' or 'model', got {how!r}")
        self.up = as_unit_vector(up, "up")
        self.old, self.index, self.how, self.turbidity = _check_sun(old_sun, self.up), index, how, turbidity
        directions = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
        self._count = len(directions)
        if how == "paper":
            self.weight = 1.0 - np.clip(directions @ self.up, 0.0, 1.0)
        else:  # below the horizon: the horizon's colour
            above = directions - np.minimum(directions @ self.up, 0.0)[:, None] * self.up
            self.directions = above / np.maximum(np.linalg.norm(above, axis=1, keepdims=True), 1e-12)
            self.radiance = self._radiance(self.old)

    def _radiance(self, sun: np.ndarray) -> np.ndarray:
        zenith = _zenith_luminance(self.turbidity, math.acos(max(-1.0, min(1.0, float(sun @ self.up)))))
        relative = preetham_relative_rgb(self.directions, sun_direction=sun, turbidity=self.turbidity, up=self.up)
        return np.maximum(relative, 1e-6) * zenith

    def factors(self, new_sun: np.ndarray) -> np.ndarray:
        """(N, 3) float32 factors at ``new_sun`` (:func:`sky_pixel_factors`)."""
        factors = self._changed(new_sun)
        return np.ones((self._count, 3), np.float32) if factors is None else factors

    def _changed(self, new_sun: np.ndarray) -> np.ndarray | None:
        """:meth:`factors`, or None when every factor is 1 in float32 (``"paper"`` with the elevation unchanged:
        ``g ** w`` lies between 1 and ``g``, which rounds to 1; ``"model"`` at the capture sun)."""
        new = _check_sun(new_sun, self.up)
        if self.how == "paper":
            gain, _ = paper_environment_factors(self.old, new, up=self.up)
            if np.all(gain.astype(np.float32) == 1.0):
                return None
            return (gain[None, :] ** self.weight[:, None]).astype(np.float32)
        if np.array_equal(self.old, new):
            return None
        return (self._radiance(new) / self.radiance).astype(np.float32)

    def recolour(self, image: np.ndarray, new_sun: np.ndarray) -> None:
        """Multiply the sky pixels of ``image`` ((H, W, 3) float32, in place) by their factors (nothing to do where
        every one is 1)."""
        factors = self._changed(new_sun)
        if factors is None:
            return
        image.reshape(-1, 3)[self.index] *= factors


# ---------------------------------------------------------------------------------------------
# relighting
# ---------------------------------------------------------------------------------------------


def _sun_terms(s_sun: np.ndarray, radiance: np.ndarray, cosine: np.ndarray, visibility: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """``S_sun' = max(base + L_sun max(0, n.d'), floor)``: ``base`` and ``floor``, float32 like ``s_sun`` (..., 3)
    (:class:`~mvintrinsic.relight.Relighter`); in full shadow (``visibility`` 0) 0 and -inf leave ``L_sun max(0, n.d')``."""
    saw_sun = (visibility > 0)[..., None]
    base = np.where(saw_sun, s_sun - radiance * cosine[..., None], 0.0).astype(np.float32)
    return base, np.where(saw_sun, np.minimum(s_sun, 0.0), -np.inf).astype(np.float32)


def _into_light(layers: IntrinsicLayers, r: np.ndarray, v: np.ndarray, pixels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sec. 8: "We adjust the reflectance of such pixels to bring them in light using the v_sun layer":
    at ``pixels`` (H, W) bool v_sun = 1 and R = I / (S_sun + S_sky + S_ind), I = R S_tot (Eq. 2); float32."""
    in_light = layers.sun_shading.astype(np.float64) + layers.env_shading
    ok = pixels[..., None] & (in_light > 0)
    r = np.where(ok, r * layers.shading.astype(np.float64) / np.where(ok, in_light, 1.0), r).astype(np.float32)
    return r, np.where(pixels, np.float32(1.0), v).astype(np.float32)


def _relit_sun_shading(cosine: np.ndarray, radiance: np.ndarray, base: np.ndarray, floor: np.ndarray) -> np.ndarray:
    """``S_sun' = max(base + L_sun max(0, n.d'), floor)``, float32 (..., 3), from ``max(0, n.d')`` (...) and the
    terms of :func:`_sun_terms`."""
    s_sun = cosine[..., None] * radiance
    s_sun += base
    return np.maximum(s_sun, floor, out=s_sun)


def _sky_factor(environment: tuple[str, np.ndarray], lookup: Callable[[np.ndarray], np.ndarray] | None) -> np.ndarray:
    """``S_sky' / S_sky``: the (3,) float32 gain of ``("paper", gain)``, or ``lookup(table)`` of ``("model", table)``
    (the sky-model ratio at each normal)."""
    how, table = environment
    return table.astype(np.float32) if how == "paper" else lookup(table)


class _PaperPixels:
    """The paper's image at one view's rescued pixels (:attr:`OccupancyConfig.belief <mvintrinsic.photo_occupancy.OccupancyConfig>`): ``R (v' S_sun' + S_sky' +
    S_ind')`` with the cluster dropped (its reflectance and capture visibility as
    :attr:`RelightConfig.dropped <mvintrinsic.caster.RelightConfig>` leaves them) and ``v'`` 1, or the given
    ``visibility``: no other caster or proxy shadow is cast there. Against the paper's whole relighter (the
    first form, rendering every pixel again): every relit PSNR within 0.004 dB, five scenes, 22 scene-suns,
    both rows (``docs/relight.md``).

    Parameters
    ----------
    reflectance, base, floor, sky_shading, indirect_shading : (N, 3) float32
        At the rescued pixels, in row-major order: ``R``, ``S_sun' = max(base + L_sun max(0, n.d'), floor)``, ``S_sky``, ``S_ind``.
    normals : (N, 3) float32
        Unit receiver normals, world frame.
    radiance : (3,) float32
        ``L_sun`` in the view's units.
    visibility : (N,) float32
        ``v'`` at every sun.
    sky_lookup : callable or None
        ``sky="model"``: the sky irradiance table at the normals.
    """

    def __init__(self, reflectance: np.ndarray, base: np.ndarray, floor: np.ndarray,
                 normals: np.ndarray, sky_shading: np.ndarray, indirect_shading: np.ndarray, radiance: np.ndarray,
                 visibility: np.ndarray, sky_lookup: Callable[[np.ndarray], np.ndarray] | None) -> None:
        self.reflectance, self.base, self.floor = reflectance, base, floor
        self.normals, self.sky_shading, self.indirect_shading = normals, sky_shading, indirect_shading
        self.radiance, self.visibility, self.sky_lookup = radiance, visibility, sky_lookup

    def __call__(self, direction: np.ndarray, environment: tuple[str, np.ndarray], indirect: float) -> np.ndarray:
        """(N, 3) float32 at the float32 unit sun ``direction``; ``environment`` ``("paper", (3,) gain)`` or
        ``("model", table)`` and ``indirect`` ``S_ind' / S_ind``, as the relighter's."""
        image = _relit_sun_shading(np.maximum(self.normals @ direction, np.float32(0.0)), self.radiance, self.base,
                                   self.floor)
        image *= self.visibility[:, None]
        image += self.sky_shading * _sky_factor(environment, self.sky_lookup)
        image += self.indirect_shading * np.float32(indirect)
        return (image * self.reflectance).astype(np.float32)


class _NewSun:
    """One view's sun-independent inputs of a new sun, and the per-view steps of one (:class:`~mvintrinsic.relight.Relighter`).

    Built once per view; :meth:`~mvintrinsic.relight.Relighter.render` runs these steps here, or ships this object once
    to a dask worker and runs them there (:func:`_render_view`): the same code either way, so the
    images are identical. It holds no Embree structure (those cannot be pickled): the caster's and
    the proxy's are passed in.

    Parameters
    ----------
    receivers : (H*W, 3) float64
        Receiver points, world frame, metres (:func:`~mvintrinsic.shadow_caster.receiver_points`).
    shape : (int, int)
        ``(H, W)``.
    blocked : (P + 1,) bool, or a pair of them
        :meth:`ShadowCaster.completion_blocked` of the view's caster; with ``belief < 1`` and uncertain sheets,
        the pair (all, ``certain=True``).
    min_distance : float
        Proxy hits nearer than this (metres) complete no shadow.
    config : RelightConfig
    batch : int
        Rays per Embree call.
    normals : (H, W, 3) float32
        Unit receiver normals, world frame.
    base, floor : (H, W, 3) float32
        ``S_sun' = max(base + L_sun max(0, n.d'), floor)`` (:meth:`~mvintrinsic.relight.Relighter._prepare_new_sun`).
    fill : (H, W, 3) float32
        The input image where the layers hold no estimate, 0 elsewhere.
    reflectance, fill_reflectance : (H, W, 3) float32
        ``R`` after the in-shadow fix; the same with 0 where the layers hold no estimate.
    sky_shading, indirect_shading : (H, W, 3) float32
        The layers' ``S_sky`` and ``S_ind``.
    radiance : (3,) float32
        ``L_sun`` in the view's units.
    known : (H, W) bool
        Pixels where the layers hold an estimate.
    sky_lookup : _SphereLookup or None
        ``sky="model"``: the sky irradiance table at each pixel's normal.
    unexplained : (H, W) bool or None
        Pixels that keep ``capture`` at every sun (:attr:`~mvintrinsic.relight.Relighter.unexplained`); None: none.
    capture : (H, W) float32 or None
        The capture ``v_sun`` after the in-shadow fix (:attr:`~mvintrinsic.relight.Relighter.visibility`).
    static : (H, W) bool or None
        Pixels whose ``v'`` is ``capture`` times the caster's (``dropped="static"``); None: none.
    belief : float
        :meth:`ShadowCaster.sun_visibility`'s ``belief`` (the caster's uncertain sheets).
    full : (H*W,) bool or None
        Pixels whose ``v'`` is that of every sheet, not the mixture (the rescued pixels: the relighter mixes
        their images, :func:`~mvintrinsic.photo_occupancy.blend_rescued`).
    """

    def __init__(self, *, receivers: np.ndarray, shape: tuple[int, int], blocked: np.ndarray, min_distance: float,
                 config: RelightConfig, batch: int, normals: np.ndarray, base: np.ndarray, floor: np.ndarray,
                 fill: np.ndarray, reflectance: np.ndarray, fill_reflectance: np.ndarray, sky_shading: np.ndarray,
                 indirect_shading: np.ndarray, radiance: np.ndarray, known: np.ndarray,
                 sky_lookup: _SphereLookup | None, unexplained: np.ndarray | None = None,
                 capture: np.ndarray | None = None, static: np.ndarray | None = None,
                 sky_pixels: _SkyPixels | None = None, belief: float = 1.0, full: np.ndarray | None = None) -> None:
        if (static is not None or unexplained is not None) and capture is None:
            raise ValueError("capture is needed with static or unexplained pixels")
        self.sky_pixels = sky_pixels
        self.belief, self.full = belief, full
        self.receivers, self.shape, self.blocked, self.min_distance = receivers, shape, blocked, min_distance
        self.config, self.batch = config, batch
        self.normals, self.radiance, self.known, self.sky_lookup = normals, radiance, known, sky_lookup
        # Channel planes (3, H, W) of what every new sun's image reads (:meth:`image`): long inner loops in
        # cache-sized bands of rows instead of (H, W, 3) passes broadcast over 3 channels, 2.7x faster at 1000x750.
        self._planes = {name: _planar(array) for name, array in (
            ("base", base), ("floor", floor), ("sky", sky_shading), ("indirect", indirect_shading),
            ("reflectance", fill_reflectance), ("fill", fill))}
        # fill="zero" multiplies by the reflectance itself; it equals fill_reflectance unless a pixel without an
        # estimate has a reflectance other than 0 (the layers hold 0 there).
        differs = not np.array_equal(np.asarray(reflectance), np.asarray(fill_reflectance))
        self._zero_reflectance = _planar(reflectance) if differs else None
        # Each new sun touches these pixels alone: their flat indices and capture v_sun, gathered once.
        self._static = None if static is None else _gathered(static, capture)
        self._unexplained = None if unexplained is None else _gathered(unexplained, capture)

    def visibility(self, direction: np.ndarray, shadow_caster: ShadowCaster, tracer: Tracer) -> np.ndarray:
        """``v'`` (H, W) float32 at the unit sun ``direction`` (:meth:`~mvintrinsic.relight.Relighter.visibility_at`)."""
        visibility = shadow_caster._visibility(self.receivers, self.shape, direction, proxy_tracer=tracer,
                                               blocked=self.blocked, min_distance=self.min_distance, facing=None,
                                               config=self.config, batch=self.batch, belief=self.belief,
                                               full=self.full)
        visibility = np.ascontiguousarray(visibility)  # (already is: then the flat view writes into it)
        flat = visibility.reshape(-1)
        if self._static is not None:  # the shadow of a dropped cluster stays (RelightConfig.dropped)
            index, capture = self._static
            flat[index] *= capture
        if self._unexplained is not None:
            index, capture = self._unexplained
            flat[index] = capture
        return visibility

    def cosine(self, direction: np.ndarray) -> np.ndarray:
        """``max(0, n . d')`` (H, W) float32 for the float32 unit sun ``direction``."""
        cosine = self.normals @ direction
        return np.maximum(cosine, np.float32(0.0), out=cosine)

    def irradiance(self, cosine: np.ndarray, visibility: np.ndarray) -> float:
        """``sum max(0, n . d') v'`` over the pixels with an estimate (``sky="model"``'s ``S_ind``)."""
        return float((cosine.astype(np.float64) * visibility)[self.known].sum())

    def sky_factor(self, environment: tuple[str, np.ndarray]) -> np.ndarray:
        """``S_sky' / S_sky``: the (3,) float32 gain (``"paper"``) or the sky-model ratio at each normal (H, W, 3)."""
        return _sky_factor(environment, self.sky_lookup)

    def _sun_plane(self, out: np.ndarray, cosine: np.ndarray, channel: int, rows: slice) -> np.ndarray:
        """``S_sun'`` of one channel on ``rows`` into ``out`` ((n, W) float32) from ``max(0, n . d')`` ((H, W)):
        the operations of :func:`_relit_sun_shading`, in its order."""
        np.multiply(cosine[rows], self.radiance[channel], out=out)
        out += self._planes["base"][channel, rows]
        return np.maximum(out, self._planes["floor"][channel, rows], out=out)

    def sun_shading(self, cosine: np.ndarray) -> np.ndarray:
        """``S_sun'`` (H, W, 3) float32 from ``max(0, n . d')``."""
        planes = np.empty((3, *self.shape), np.float32)
        for c in range(3):
            self._sun_plane(planes[c], cosine, c, slice(None))
        return _interleaved(planes)

    def image(self, visibility: np.ndarray, cosine: np.ndarray, sky: np.ndarray, indirect: float,
              fill: str, direction: np.ndarray | None = None) -> np.ndarray:
        """``R (v' S_sun' + S_sky' + S_ind')`` (H, W, 3) float32 from ``v'`` and ``max(0, n . d')`` ((H, W)
        float32), ``S_sky' / S_sky`` (:meth:`sky_factor`) and ``S_ind' / S_ind``; with ``fill="input"`` the
        pixels without an estimate show the input, its sky pixels recoloured for the sun ``direction``
        (:attr:`RelightConfig.sky_pixels`).

        The operations of :func:`_relit_sun_shading` and Eq. (1), in their order (so the same float32
        values), on one band of :data:`COMPOSE_ROWS` rows and one channel plane at a time, the bands
        interleaved into the image by OpenCV.
        """
        planes = self._planes
        reflectance = planes["reflectance"] if fill == "input" or self._zero_reflectance is None \
            else self._zero_reflectance
        h, w = self.shape
        image = np.empty((h, w, 3), np.float32)
        per_pixel = np.ndim(sky) == 3  # sky="model": a factor per pixel, else (3,)
        sky = np.asarray(sky) if per_pixel else np.asarray(sky, np.float32)  # the products as before, in its dtype
        indirect = np.float32(indirect)
        rows = min(COMPOSE_ROWS, h)
        band = np.empty((3, rows, w), np.float32)
        term = np.empty((rows, w), np.float32)
        for top in range(0, h, rows):
            bottom = min(h, top + rows)
            n = bottom - top
            t = term[:n]
            for c in range(3):
                out = self._sun_plane(band[c, :n], cosine, c, slice(top, bottom))
                out *= visibility[top:bottom]  # v' S_sun' + S_sky' + S_ind', Eq. (1)
                np.multiply(planes["sky"][c, top:bottom], sky[top:bottom, :, c] if per_pixel else sky[c], out=t)
                out += t
                np.multiply(planes["indirect"][c, top:bottom], indirect, out=t)
                out += t
                out *= reflectance[c, top:bottom]  # 0 where the layers hold no estimate, so the fill adds to 0
                if fill == "input":
                    out += planes["fill"][c, top:bottom]
            merged = cv2.merge([band[0, :n], band[1, :n], band[2, :n]], dst=image[top:bottom])
            if not np.shares_memory(merged, image):  # OpenCV wrote elsewhere (it should not)
                image[top:bottom] = merged
        if fill == "input" and self.sky_pixels is not None and direction is not None:
            self.sky_pixels.recolour(image, direction)
        return image


def _planar(array: np.ndarray) -> np.ndarray:
    """(H, W, 3) -> its channel planes (3, H, W), float32, contiguous."""
    return np.ascontiguousarray(np.moveaxis(np.asarray(array, np.float32), -1, 0))


def _interleaved(planes: np.ndarray) -> np.ndarray:
    """(3, H, W) -> (H, W, 3) float32, contiguous."""
    return np.ascontiguousarray(np.moveaxis(planes, 0, -1))


def _gathered(mask: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The flat indices of ``mask`` (H, W) (int32: fewer than 2**31 pixels) and ``values`` (H, W) there."""
    index = np.flatnonzero(mask).astype(np.int32)
    return index, np.asarray(values).reshape(-1)[index]


def _build_task(caster: _Rebuilt, tracer: _Rebuilt) -> None:
    """A task: build the caster's and the proxy's Embree structures on this worker (once each)."""
    caster.get()
    tracer.get()


def _new_sun_terms(new_sun: _NewSun, caster: _Rebuilt, tracer: _Rebuilt, direction: np.ndarray,
                   shadow_sun: np.ndarray, visibility: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """A task: one view's ``(v', max(0, n . d'))`` at a new sun (``visibility`` given: that ``v'``)."""
    if visibility is None:
        visibility = new_sun.visibility(shadow_sun, caster.get(), tracer.get())
    return visibility, new_sun.cosine(direction.astype(np.float32))


def _irradiance_task(new_sun: _NewSun, terms: tuple[np.ndarray, np.ndarray]) -> float:
    """A task: :meth:`_NewSun.irradiance` of one view's :func:`_new_sun_terms`."""
    visibility, cosine = terms
    return new_sun.irradiance(cosine, visibility)


def _image_task(new_sun: _NewSun, terms: tuple[np.ndarray, np.ndarray], *, environment: tuple[str, np.ndarray],
                indirect_factor: float, fill: str, direction: np.ndarray) -> np.ndarray:
    """A task: one view's relit image from its :func:`_new_sun_terms`."""
    visibility, cosine = terms
    return new_sun.image(visibility, cosine, new_sun.sky_factor(environment), indirect_factor, fill, direction)


def _render_view(new_sun: _NewSun, caster: _Rebuilt, tracer: _Rebuilt, direction: np.ndarray,
                 shadow_sun: np.ndarray, visibility: np.ndarray | None, *, environment: tuple[str, np.ndarray],
                 indirect_factor: float, fill: str) -> np.ndarray:
    """A task: one view's relit image at a new sun (``sky="paper"``: no cross-view term)."""
    terms = _new_sun_terms(new_sun, caster, tracer, direction, shadow_sun, visibility)
    return _image_task(new_sun, terms, environment=environment, indirect_factor=indirect_factor, fill=fill,
                       direction=direction)
