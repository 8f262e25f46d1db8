"""Sun direction from the user's input: two clicks on a photo, or a date, time and place.

* :func:`sun_from_clicks` is the paper's manual step (Duchêne et al. 2015, Sec. 3.2): the user
  clicks a point in a cast shadow and the point that casts it; both are lifted to 3D by casting
  the pixel rays into the proxy and the sun lies along ``caster - shadow``.
* :func:`sun_from_time` computes the solar position with pvlib's implementation of the NREL
  Solar Position Algorithm (Reda & Andreas 2004) and expresses it in the world frame given the
  world directions of up and geographic north.
"""

from __future__ import annotations

import datetime as _dt
import math

import numpy as np

from ._validation import as_array, as_unit_vector, describe
from .camera import Camera
from .envmap import horizontal_frame
from .raytrace import Tracer
from .scene import Sun

__all__ = ["azimuth_elevation", "horizontal_frame", "sun_from_clicks", "sun_from_time"]


def azimuth_elevation(direction: np.ndarray, *, up: np.ndarray, reference: np.ndarray | None = None) -> tuple[float, float]:
    """Azimuth and elevation of a world direction, degrees.

    Azimuth is measured counter-clockwise seen from above from the horizontal projection of
    ``reference`` (see :func:`horizontal_frame`), in (-180, 180]; elevation is the angle above the
    plane normal to ``up``.
    """
    frame = horizontal_frame(up, reference)
    d = frame @ as_unit_vector(direction, "direction")
    return math.degrees(math.atan2(d[1], d[0])), math.degrees(math.asin(float(np.clip(d[2], -1.0, 1.0))))


def sun_from_clicks(
    camera: Camera,
    shadow_px: tuple[float, float],
    caster_px: tuple[float, float],
    tracer: Tracer,
) -> Sun:
    """Sun direction from a shadow pixel and the pixel of the point casting it (paper Sec. 3.2).

    Parameters
    ----------
    camera : Camera
        Camera of the clicked view.
    shadow_px, caster_px : (2,) array_like
        Pixel indices ``(column, row)`` as an image viewer shows them (0-based, may be
        fractional); the rays go through ``(u + 0.5, v + 0.5)`` in COLMAP's continuous
        coordinates, i.e. through the pixel centre for integer clicks.
    tracer : Tracer
        Ray caster over the proxy.

    Returns
    -------
    Sun
        Direction ``normalize(X_caster - X_shadow)``.

    Raises
    ------
    ValueError
        Naming ``shadow_px`` or ``caster_px`` when a click lies outside the image or its ray
        misses the proxy, or when both clicks land on the same 3D point.
    """
    points = []
    for name, px in (("shadow_px", shadow_px), ("caster_px", caster_px)):
        uv = as_array(px, name, shape=(2,), dtype=np.float64)
        if not (0 <= uv[0] < camera.width and 0 <= uv[1] < camera.height):
            raise ValueError(
                f"{name} {uv.tolist()} lies outside the {camera.width}x{camera.height} image "
                f"(columns 0..{camera.width - 1}, rows 0..{camera.height - 1})"
            )
        ray = camera.pixel_rays((uv + 0.5)[None])
        hits = tracer.intersect(camera.center, ray)
        if not hits.hit[0]:
            raise ValueError(f"{name} {uv.tolist()}: the ray through this pixel misses the proxy")
        points.append(hits.points[0])
    shadow, caster = points
    if np.linalg.norm(caster - shadow) < 1e-9:
        raise ValueError("shadow_px and caster_px land on the same 3D point of the proxy")
    return Sun(caster - shadow)


def sun_from_time(
    when: _dt.datetime,
    latitude: float,
    longitude: float,
    *,
    north: np.ndarray,
    up: np.ndarray,
    altitude: float = 0.0,
) -> Sun:
    """Sun direction at a date, time and place (NREL SPA through pvlib).

    Parameters
    ----------
    when : datetime.datetime
        Time of capture; must be timezone-aware (an ISO 8601 string with an offset, e.g.
        ``2026-06-21T14:30:00+02:00``, parsed with :meth:`datetime.datetime.fromisoformat`).
    latitude, longitude : float
        Degrees, north and east positive.
    north : (3,) array_like
        World direction of geographic north; only its horizontal part is used.
    up : (3,) array_like
        World up vector.
    altitude : float, optional
        Metres above sea level.

    Returns
    -------
    Sun
        Direction from the *apparent* (refraction-corrected) elevation and the azimuth (east of
        north). With ``east = north x up``:
        ``d = cos(el) (cos(az) north + sin(az) east) + sin(el) up``.
    """
    import pandas as pd
    import pvlib

    if not isinstance(when, _dt.datetime):
        raise TypeError(f"when must be a datetime.datetime, got {describe(when)}")
    if when.tzinfo is None or when.utcoffset() is None:
        raise ValueError(f"when must be timezone-aware (give a UTC offset), got {when.isoformat()}")
    if not (-90.0 <= latitude <= 90.0):
        raise ValueError(f"latitude must be in [-90, 90] degrees, got {latitude!r}")
    if not (-180.0 <= longitude <= 180.0):
        raise ValueError(f"longitude must be in [-180, 180] degrees, got {longitude!r}")
    frame = horizontal_frame(up, north)
    north_h, up_v = frame[0], frame[2]
    east = np.cross(north_h, up_v)
    position = pvlib.solarposition.get_solarposition(
        pd.DatetimeIndex([pd.Timestamp(when)]), latitude, longitude, altitude=altitude
    )
    elevation = math.radians(float(position["apparent_elevation"].iloc[0]))
    azimuth = math.radians(float(position["azimuth"].iloc[0]))
    direction = math.cos(elevation) * (math.cos(azimuth) * north_h + math.sin(azimuth) * east) + math.sin(elevation) * up_v
    return Sun(direction)
