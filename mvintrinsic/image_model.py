"""The image formation model of Duchêne et al. 2015 (Sec. 3.1), the bottom layer of every stage.

.. math::

   I = R \\, (v_{sun} L_{sun} \\max(0, \\cos\\omega_{sun}) + S_{sky} + S_{ind})    \\qquad (1)

   R(v_{sun}) = \\frac{I}{S_{ind} + S_{sky} + v_{sun} L_{sun} \\max(0, \\cos\\omega_{sun})}   \\qquad (2)

   I = R \\, (v_{sun} S_{sun} + S_{env}), \\quad S_{sun} = L_{sun} \\max(0, \\cos\\omega_{sun}),
   \\quad S_{env} = S_{sky} + S_{ind}    \\qquad (3)

   S_{tot} = S_{sky} + S_{ind} + v_{sun} S_{sun}    \\qquad (17)

and the sun radiance from a lit/shadow pair of equal reflectance (Eq. 5). All values are RGB except
the cosine and the visibility; "for all cosines we take max(0, cos)" (Sec. 3.1). Units: R is the
diffuse albedo in [0, 1]; shading is irradiance / pi in the image's units (``docs/conventions.md``).

Every function is vectorised over leading axes: RGB quantities have shape ``(..., 3)``, per-point
scalars (visibility, cosine) shape ``(...)`` and broadcast against them. Functions are NaN-safe:
where a denominator vanishes the result is NaN (never a warning or an infinity), so callers mask
with ``numpy.isfinite``.

References
----------
S. Duchêne et al., "Multi-View Intrinsic Images of Outdoors Scenes with an Application to
Relighting", ACM Transactions on Graphics 34(5), 2015. Eq. (1) follows Laffont et al. 2013.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "DENOMINATOR_EPS",
    "LUMINANCE_WEIGHTS",
    "clamped_cosine",
    "luminance",
    "reflectance",
    "render",
    "sun_radiance_from_pair",
    "sun_shading",
    "total_shading",
]

#: Denominators whose magnitude is at or below this are treated as zero (result NaN).
DENOMINATOR_EPS = 1e-12

#: Rec. 709 / sRGB luminance weights of linear RGB (the colour space of ``docs/conventions.md``).
LUMINANCE_WEIGHTS = np.array([0.2126, 0.7152, 0.0722])


def luminance(image: np.ndarray) -> np.ndarray:
    """Rec. 709 luminance of linear RGB ``(..., 3)`` -> ``(...)`` float64."""
    return np.asarray(image, dtype=np.float64) @ LUMINANCE_WEIGHTS


def _rgb(value: object, name: str) -> np.ndarray:
    array = np.asarray(value, dtype=np.float64)
    if array.ndim == 0 or array.shape[-1] != 3:
        raise ValueError(f"{name} must have shape (..., 3) (RGB last), got shape {array.shape}")
    return array


def _scalar_per_point(value: object) -> np.ndarray:
    """Per-point scalar -> (..., 1) so that it broadcasts against (..., 3) RGB arrays."""
    return np.asarray(value, dtype=np.float64)[..., None]


def _divide(numerator: np.ndarray, denominator: np.ndarray) -> np.ndarray:
    numerator, denominator = np.broadcast_arrays(numerator, denominator)
    out = np.full(numerator.shape, np.nan)
    ok = np.abs(denominator) > DENOMINATOR_EPS
    np.divide(numerator, denominator, out=out, where=ok)
    return out


def clamped_cosine(normals: np.ndarray, sun_direction: np.ndarray) -> np.ndarray:
    """``max(0, cos(omega_sun))`` (Sec. 3.1) for unit normals ``(..., 3)``; returns ``(...)``.

    ``sun_direction`` is the unit ``(3,)`` vector toward the sun, in the normals' frame.
    """
    normals = _rgb(normals, "normals")
    sun = np.asarray(sun_direction, dtype=np.float64)
    if sun.shape != (3,):
        raise ValueError(f"sun_direction must have shape (3,), got shape {sun.shape}")
    return np.maximum(normals @ sun, 0.0)


def sun_shading(sun_radiance: np.ndarray, cosine: np.ndarray) -> np.ndarray:
    """``S_sun = L_sun max(0, cos omega_sun)`` (Eq. 3).

    Parameters
    ----------
    sun_radiance : (3,) or (..., 3) array_like
        ``L_sun`` in shading units.
    cosine : (...) array_like
        ``cos(omega_sun)``; negative values are clamped to 0 (attached shadow).

    Returns
    -------
    (..., 3) float64
    """
    return _rgb(sun_radiance, "sun_radiance") * np.maximum(_scalar_per_point(cosine), 0.0)


def total_shading(sky: np.ndarray, indirect: np.ndarray, visibility: np.ndarray, sun: np.ndarray) -> np.ndarray:
    """``S_tot = S_sky + S_ind + v_sun S_sun`` (Eq. 17), ``(..., 3)``.

    Parameters
    ----------
    sky, indirect, sun : (..., 3) array_like
        ``S_sky``, ``S_ind`` and ``S_sun`` (the latter before visibility).
    visibility : (...) array_like
        ``v_sun`` in [0, 1].
    """
    return _rgb(sky, "sky") + _rgb(indirect, "indirect") + _scalar_per_point(visibility) * _rgb(sun, "sun")


def render(reflectance_: np.ndarray, sky: np.ndarray, indirect: np.ndarray, visibility: np.ndarray,
           sun: np.ndarray) -> np.ndarray:
    """The forward model ``I = R (v_sun S_sun + S_sky + S_ind)`` (Eqs. 1 and 3), ``(..., 3)``."""
    return _rgb(reflectance_, "reflectance") * total_shading(sky, indirect, visibility, sun)


def reflectance(image: np.ndarray, sky: np.ndarray, indirect: np.ndarray, visibility: np.ndarray,
                sun: np.ndarray) -> np.ndarray:
    """``R(v_sun) = I / (S_ind + S_sky + v_sun S_sun)`` (Eq. 2), ``(..., 3)``.

    ``visibility`` may be a hypothesis (0 or 1) rather than an estimate, as in the shadow
    labelling of Sec. 6.1. NaN where the total shading vanishes.
    """
    return _divide(_rgb(image, "image"), total_shading(sky, indirect, visibility, sun))


def sun_radiance_from_pair(
    image_1: np.ndarray,
    image_2: np.ndarray,
    env_1: np.ndarray,
    env_2: np.ndarray,
    visibility_1: np.ndarray,
    visibility_2: np.ndarray,
    cosine_1: np.ndarray,
    cosine_2: np.ndarray,
) -> np.ndarray:
    """Sun radiance from two points of equal reflectance and different visibility (Eq. 5).

    .. math::

       L_{sun} = \\frac{I_1 (S_{sky,2} + S_{ind,2}) - I_2 (S_{sky,1} + S_{ind,1})}
                      {I_2 v_{sun,1} \\cos\\omega_1 - I_1 v_{sun,2} \\cos\\omega_2}

    Parameters
    ----------
    image_1, image_2 : (..., 3) array_like
        Observed radiance of the two points.
    env_1, env_2 : (..., 3) array_like
        Their environment shading ``S_sky + S_ind``.
    visibility_1, visibility_2 : (...) array_like
        Their sun visibility.
    cosine_1, cosine_2 : (...) array_like
        ``cos(omega_sun)`` at each (clamped to ``max(0, cos)``).

    Returns
    -------
    (..., 3) float64
        ``L_sun`` per channel; NaN where the denominator vanishes (e.g. both points in shadow).
    """
    i1, i2 = _rgb(image_1, "image_1"), _rgb(image_2, "image_2")
    e1, e2 = _rgb(env_1, "env_1"), _rgb(env_2, "env_2")
    c1 = np.maximum(_scalar_per_point(cosine_1), 0.0) * _scalar_per_point(visibility_1)
    c2 = np.maximum(_scalar_per_point(cosine_2), 0.0) * _scalar_per_point(visibility_2)
    return _divide(i1 * e2 - i2 * e1, i2 * c1 - i1 * c2)
