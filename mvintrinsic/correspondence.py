"""Pixels of different views that see the same surface point, through the proxy.

A surface point has one reflectance and one sun visibility, whichever photo sees it. This module
finds, for every pixel of every view, the pixel of each other view that sees the same proxy point,
and whether the two photos agree there:

1. the pixel's centre ray meets the proxy at ``X = C_i + t d`` (``t`` from
   :attr:`~mvintrinsic.pixels.PixelQuantities.depth`);
2. ``X`` is projected into view ``j``; the pixel it falls in *sees* ``X`` when its own proxy depth
   equals ``|X - C_j|`` within ``depth_tolerance`` (relative): nothing of the proxy lies in front;
3. the correspondence is *consistent* when the two photos' colours agree: the Euclidean norm of the
   difference of the log RGB of the two pixels (images Gaussian-blurred by ``blur`` pixels against
   resampling and render noise) is below ``photo_tolerance``. A Lambertian point looks the same
   from every view under one sun, so a disagreement means that one of the photos sees something
   the proxy lacks in front of the point (foliage, a pole) or that the surface is not diffuse
   there; such pairs carry no evidence about the point.

Pixels whose ray misses the proxy (sky, or geometry the proxy lost: ``filled``) have no
correspondence. Everything is per pixel centre (nearest pixel, no interpolation).

:func:`fuse_views` averages a per-pixel quantity over a pixel and its consistent correspondences;
:func:`cross_view_agreement` measures how often the views give one surface point the same label;
:func:`cross_view_reflectance_spread` how far apart their reflectances of it are.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType

import numpy as np
from scipy import ndimage

from ._validation import describe, is_real
from .pixels import PixelQuantities
from .results import SHADOW_LABELS
from .scene import View

__all__ = ["Agreement", "Correspondences", "ReflectanceSpread", "consensus", "cross_view_agreement",
           "cross_view_reflectance_spread", "cross_view_value_agreement", "find_correspondences", "fuse_views", "log_image", "surface_points"]


@dataclass(frozen=True, eq=False)
class Correspondences:
    """Pixel-to-pixel correspondences between every ordered pair of views.

    Parameters
    ----------
    stems : tuple of str
        The views, sorted by stem (the order of every pooled computation, so that results do not
        depend on the order in which the views were given).
    shapes : mapping of str to (int, int)
        ``(H, W)`` of each view.
    index : mapping of (str, str) to (H_i * W_i,) int64
        For the pair ``(i, j)``: per pixel of view ``i`` (row-major), the flat index of the pixel of
        view ``j`` that sees the same proxy point, or -1.
    consistent : mapping of (str, str) to (H_i * W_i,) bool
        Where the two pixels' colours agree (module docstring); False where ``index`` is -1.
    depth_tolerance, photo_tolerance : float
        The tolerances used.
    """

    stems: tuple[str, ...]
    shapes: Mapping[str, tuple[int, int]]
    index: Mapping[tuple[str, str], np.ndarray]
    consistent: Mapping[tuple[str, str], np.ndarray]
    depth_tolerance: float
    photo_tolerance: float

    def pairs(self, stem: str) -> list[str]:
        """The other views of ``stem``, in stem order."""
        if stem not in self.shapes:
            raise KeyError(f"no view {stem!r}; views are {list(self.stems)}")
        return [other for other in self.stems if other != stem]

    def seen_by(self, stem: str) -> np.ndarray:
        """``(H, W)`` int: number of other views that see each pixel's proxy point."""
        return self._count(stem, {other: self.index[stem, other] >= 0 for other in self.pairs(stem)})

    def agreeing(self, stem: str) -> np.ndarray:
        """``(H, W)`` int: number of other views whose correspondence is consistent."""
        return self._count(stem, {other: self.consistent[stem, other] for other in self.pairs(stem)})

    def _count(self, stem: str, flags: Mapping[str, np.ndarray]) -> np.ndarray:
        total = np.zeros(int(np.prod(self.shapes[stem])), dtype=np.int64)
        for flag in flags.values():
            total += flag
        return total.reshape(self.shapes[stem])

    def __repr__(self) -> str:
        return f"Correspondences({len(self.stems)} views, depth_tolerance={self.depth_tolerance}, " \
               f"photo_tolerance={self.photo_tolerance})"


def _check_views(views: Sequence[View], quantities: Mapping[str, PixelQuantities]) -> list[View]:
    if isinstance(views, View) or not isinstance(views, Sequence) or not views:
        raise TypeError(f"views must be a non-empty sequence of View, got {describe(views)}")
    stems = set()
    for view in views:
        if not isinstance(view, View):
            raise TypeError(f"views must hold View objects, got {describe(view)}")
        if view.stem in stems:
            raise ValueError(f"views: stem {view.stem!r} appears twice")
        stems.add(view.stem)
        q = quantities.get(view.stem) if isinstance(quantities, Mapping) else None
        if not isinstance(q, PixelQuantities):
            raise ValueError(f"quantities: no PixelQuantities for view {view.stem!r}")
        if q.shape != view.shape:
            raise ValueError(f"quantities[{view.stem!r}] is {q.shape}, its view {view.shape}")
    return sorted(views, key=lambda v: v.stem)


def _positive(value: object, name: str) -> float:
    if not is_real(value) or not 0 < float(value) < np.inf:
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    return float(value)


def log_image(view: View, valid: np.ndarray, *, blur: float = 0.0) -> np.ndarray:
    """``log`` of the view's linear RGB, optionally Gaussian-blurred, floored at 1e-3 of its median.

    Parameters
    ----------
    view : View
    valid : (H, W) bool
        Pixels whose median sets the floor (and whose values are kept); others are set to the floor.
    blur : float, optional
        Gaussian sigma in pixels applied to the linear image first (0: none).

    Returns
    -------
    (H, W, 3) float64
    """
    image = np.where(valid[..., None], np.asarray(view.image, dtype=np.float64), 0.0)
    if blur > 0:
        image = ndimage.gaussian_filter(image, (blur, blur, 0))
    median = float(np.median(image[valid])) if valid.any() else 1.0
    floor = 1e-3 * max(median, 1e-12)
    return np.log(np.maximum(image, floor))


def surface_points(view: View, quantities: PixelQuantities) -> np.ndarray:
    """``(H, W, 3)`` world points where each pixel's centre ray meets the proxy (NaN where it misses)."""
    rays = view.camera.pixel_rays().reshape(*view.shape, 3)
    depth = np.where(np.isfinite(quantities.depth), quantities.depth, np.nan).astype(np.float64)
    return view.camera.center + rays * depth[..., None]


def _sees(view: View, quantities: PixelQuantities, points: np.ndarray, depth_tolerance: float
          ) -> tuple[np.ndarray, np.ndarray]:
    """Which of ``points (N, 3)`` the view sees (depth test); their flat pixel indices there."""
    return seen_pixels(view.camera, quantities.depth, quantities.valid & ~quantities.filled, points, depth_tolerance)


def seen_pixels(camera, depth: np.ndarray, usable: np.ndarray, points: np.ndarray, depth_tolerance: float
                ) -> tuple[np.ndarray, np.ndarray]:
    """Which of ``points (N, 3)`` a camera sees, and their flat pixel indices there (-1 where not).

    A point is seen when it projects in front of the camera into the image, on a ``usable``
    ((H, W) bool) pixel whose proxy ``depth`` ((H, W), metres along the ray; ``inf`` where the ray
    misses) is within ``depth_tolerance`` of the point's distance (relative to that distance):
    nothing of the proxy lies in front of it.
    """
    pixels, z = camera.project(points)
    inside = camera.in_image(pixels) & (z > 0)
    k = np.flatnonzero(inside)
    col = pixels[k, 0].astype(np.int64)
    row = pixels[k, 1].astype(np.int64)
    distance = np.linalg.norm(points[k] - camera.center, axis=1)
    seen = usable[row, col] & (np.abs(depth[row, col] - distance) < depth_tolerance * distance)
    flat = np.full(len(points), -1, dtype=np.int64)
    flat[k[seen]] = row[seen] * depth.shape[1] + col[seen]
    return flat >= 0, flat


def find_correspondences(
    views: Sequence[View],
    quantities: Mapping[str, PixelQuantities],
    *,
    depth_tolerance: float = 0.03,
    photo_tolerance: float = 0.25,
    blur: float = 1.0,
) -> Correspondences:
    """Correspondences between every ordered pair of views (module docstring).

    Parameters
    ----------
    views : sequence of View
    quantities : mapping of str to PixelQuantities
        Per-pixel Step-1 quantities of each view (their ``depth``, ``valid`` and ``filled``).
    depth_tolerance : float, optional
        Relative depth agreement of the depth test (0.03: 3 cm at 1 m, 30 cm at 10 m; MVS proxies
        are a few centimetres off and a pixel spans 1-2 cm at 10 m at 1000 px).
    photo_tolerance : float, optional
        Largest norm of the log-RGB difference of a consistent pair (0.25: about 14% per channel;
        the render noise of a 64-spp view after the blur is 3-5%).
    blur : float, optional
        Gaussian sigma (pixels) of the images compared.

    Returns
    -------
    Correspondences

    Raises
    ------
    ValueError, TypeError
        For an empty or duplicated set of views, missing quantities or non-positive tolerances.
    """
    ordered = _check_views(views, quantities)
    depth_tolerance = _positive(depth_tolerance, "depth_tolerance")
    photo_tolerance = _positive(photo_tolerance, "photo_tolerance")
    if not is_real(blur) or not 0 <= blur < np.inf:
        raise ValueError(f"blur must be a finite number >= 0, got {blur!r}")
    logs = {v.stem: log_image(v, quantities[v.stem].valid, blur=blur).reshape(-1, 3) for v in ordered}
    index: dict[tuple[str, str], np.ndarray] = {}
    consistent: dict[tuple[str, str], np.ndarray] = {}
    for view in ordered:
        q = quantities[view.stem]
        points = surface_points(view, q).reshape(-1, 3)
        usable = (q.valid & ~q.filled & np.isfinite(q.depth)).ravel()
        rows = np.flatnonzero(usable)
        for other in ordered:
            if other is view:
                continue
            seen, flat = _sees(other, quantities[other.stem], points[rows], depth_tolerance)
            pair = np.full(len(points), -1, dtype=np.int64)
            pair[rows[seen]] = flat[seen]
            agree = np.zeros(len(points), dtype=bool)
            src = rows[seen]
            difference = logs[view.stem][src] - logs[other.stem][flat[seen]]
            agree[src] = np.linalg.norm(difference, axis=1) < photo_tolerance
            for array in (pair, agree):
                array.flags.writeable = False
            index[view.stem, other.stem] = pair
            consistent[view.stem, other.stem] = agree
    return Correspondences(
        stems=tuple(v.stem for v in ordered),
        shapes=MappingProxyType({v.stem: v.shape for v in ordered}),
        index=MappingProxyType(index), consistent=MappingProxyType(consistent),
        depth_tolerance=depth_tolerance, photo_tolerance=photo_tolerance)


def fuse_views(values: Mapping[str, np.ndarray], correspondences: Correspondences, *,
               weight: float = 1.0) -> dict[str, np.ndarray]:
    """Average a per-pixel quantity over each pixel and its consistent correspondences.

    ``out_i(p) = (v_i(p) + w sum_j v_j(c_ij(p))) / (1 + w n(p))`` over the views ``j`` whose
    correspondence ``c_ij(p)`` is consistent, ``n(p)`` their number. Views are summed in stem order,
    so the result does not depend on the order of ``values``.

    Parameters
    ----------
    values : mapping of str to (H, W) or (H, W, C) array_like
        One array per view of ``correspondences`` (finite where it is read).
    correspondences : Correspondences
    weight : float, optional
        Weight ``w`` of each other view relative to the pixel's own (>= 0; 0 returns copies).

    Returns
    -------
    dict of str to float64 arrays of the input shapes
    """
    if not isinstance(correspondences, Correspondences):
        raise TypeError(f"correspondences must be Correspondences, got {describe(correspondences)}")
    if not is_real(weight) or not 0 <= weight < np.inf:
        raise ValueError(f"weight must be a finite number >= 0, got {weight!r}")
    missing = [s for s in correspondences.stems if s not in values]
    if missing:
        raise ValueError(f"values: no array for views {missing}")
    flat = {}
    for stem in correspondences.stems:
        array = np.asarray(values[stem], dtype=np.float64)
        if array.shape[:2] != tuple(correspondences.shapes[stem]):
            raise ValueError(f"values[{stem!r}] has shape {array.shape}, the view is {correspondences.shapes[stem]}")
        flat[stem] = array.reshape(array.shape[0] * array.shape[1], -1)
    out = {}
    for stem in correspondences.stems:
        total = flat[stem].copy()
        count = np.ones(len(total))
        if weight > 0:
            for other in correspondences.pairs(stem):
                k = np.flatnonzero(correspondences.consistent[stem, other])
                total[k] += weight * flat[other][correspondences.index[stem, other][k]]
                count[k] += weight
        out[stem] = (total / count[:, None]).reshape(np.shape(values[stem]))
    return out


def _seen_pixels(ordered: Sequence[View], quantities: Mapping[str, PixelQuantities], points: object,
                 depth_tolerance: object, photo_tolerance: object, blur: object) -> np.ndarray:
    """``(M, N)`` flat pixel index of each point in each view that sees it, else -1.

    A view sees a point when the point projects into the image, passes the depth test against the
    view's proxy depth (``depth_tolerance``, relative) and the view's colour there is within
    ``photo_tolerance`` (log-RGB norm, images blurred by ``blur``) of the median colour over the views
    that pass the depth test (:func:`cross_view_agreement`).
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {points.shape}")
    depth_tolerance = _positive(depth_tolerance, "depth_tolerance")
    photo_tolerance = _positive(photo_tolerance, "photo_tolerance")
    if not is_real(blur) or not 0 <= blur < np.inf:
        raise ValueError(f"blur must be a finite number >= 0, got {blur!r}")
    flat = np.full((len(ordered), len(points)), -1, dtype=np.int64)
    colour = np.full((len(ordered), len(points), 3), np.nan)
    for i, view in enumerate(ordered):
        q = quantities[view.stem]
        seen, index = _sees(view, q, points, depth_tolerance)
        flat[i, seen] = index[seen]
        colour[i, seen] = log_image(view, q.valid, blur=blur).reshape(-1, 3)[index[seen]]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN columns: points nobody sees
        median = np.nanmedian(colour, axis=0)
    close = np.linalg.norm(colour - median, axis=2) < photo_tolerance  # NaN colour (unseen) compares False
    return np.where(close, flat, -1)


@dataclass(frozen=True)
class Agreement:
    """How often the views give one surface point the same binary label.

    Parameters
    ----------
    fraction : float or None
        Share of the points seen by two or more views whose label is the same in all of them
        (None when no point is seen twice).
    points : int
        Points seen by two or more views.
    points_tested : int
        Points projected.
    """

    fraction: float | None
    points: int
    points_tested: int


def cross_view_agreement(
    views: Sequence[View],
    quantities: Mapping[str, PixelQuantities],
    labels: Mapping[str, np.ndarray],
    points: np.ndarray,
    *,
    depth_tolerance: float = 0.02,
    photo_tolerance: float = 0.2,
    blur: float = 1.0,
) -> Agreement:
    """Share of surface points that get one label in every view that sees them.

    A point counts as seen by a view when it projects into the image, passes the depth test against
    the view's proxy depth (``depth_tolerance``, relative) and the view's colour there is within
    ``photo_tolerance`` (log-RGB norm) of the median colour over the views that pass the depth test:
    a view whose photo shows something else at the point (an occluder the proxy lacks, a
    reflection) does not see it. The label read is the one of the pixel the point projects into.

    Parameters
    ----------
    views : sequence of View
    quantities : mapping of str to PixelQuantities
    labels : mapping of str to (H, W) array_like
        Per view, bool (True lit) or the codes of :data:`~mvintrinsic.results.SHADOW_LABELS`
        (0 shadow, 255 lit; 128, undecided, is not read). Pixels outside
        ``quantities[stem].valid`` are never read.
    points : (N, 3) array_like
        World points to test, e.g. the proxy's vertices.
    depth_tolerance, photo_tolerance : float, optional
    blur : float, optional
        Gaussian sigma (pixels) of the images whose colours are compared.

    Returns
    -------
    Agreement
    """
    ordered = _check_views(views, quantities)
    _check_layers(ordered, labels, "labels")
    values = {}
    for view in ordered:
        label = np.asarray(labels[view.stem])
        if label.dtype == bool:
            values[view.stem] = label.astype(np.float64)
        else:
            values[view.stem] = np.select([label == SHADOW_LABELS["lit"], label == SHADOW_LABELS["shadow"]],
                                          [1.0, 0.0], np.nan)
    # On values 0 and 1 "within less than 1 of each other" is "the same label".
    return _value_agreement(ordered, quantities, values, points, 1.0, depth_tolerance, photo_tolerance, blur)


def cross_view_value_agreement(
    views: Sequence[View],
    quantities: Mapping[str, PixelQuantities],
    values: Mapping[str, np.ndarray],
    points: np.ndarray,
    *,
    tolerance: float = 0.5,
    depth_tolerance: float = 0.02,
    photo_tolerance: float = 0.2,
    blur: float = 1.0,
) -> Agreement:
    """Share of surface points whose soft value (a sun visibility) differs by less than ``tolerance`` over the views.

    The soft counterpart of :func:`cross_view_agreement`, for layers in [0, 1] such as a relit
    shadow layer ``v'``: a point agrees when the largest minus the smallest of the values the views
    give it is below ``tolerance``. On binary layers (values 0 and 1) and any ``tolerance`` in
    (0, 1] it is :func:`cross_view_agreement`'s fraction. Where a shadow is soft (a penumbra, a
    blur, a crown's dapples averaged) the binary measure's threshold at 0.5 counts two views that
    give a point 0.45 and 0.55 as disagreeing and two that give it 0.55 and 0.95 as agreeing; this
    one counts what the images show: how different the shadow is.

    Parameters
    ----------
    views : sequence of View
    quantities : mapping of str to PixelQuantities
    values : mapping of str to (H, W) array_like
        Per view, values in [0, 1]; NaN pixels are not read (as the undecided label 128 in
        :func:`cross_view_agreement`). Pixels outside ``quantities[stem].valid`` are never read.
    points : (N, 3) array_like
        World points to test, e.g. the proxy's vertices.
    tolerance : float, optional
        In (0, 1]; 0.5 (default): the views differ by less than half the shadow's depth.
    depth_tolerance, photo_tolerance, blur : float, optional
        As :func:`cross_view_agreement`.

    Returns
    -------
    Agreement
        ``fraction`` over the points seen by two or more views with a value read in each.
    """
    if not is_real(tolerance) or not 0.0 < tolerance <= 1.0:
        raise ValueError(f"tolerance must be a number in (0, 1], got {tolerance!r}")
    ordered = _check_views(views, quantities)
    _check_layers(ordered, values, "values")
    return _value_agreement(ordered, quantities, values, points, float(tolerance), depth_tolerance, photo_tolerance,
                            blur)


def _check_layers(ordered: Sequence[View], layers: Mapping[str, np.ndarray], name: str) -> None:
    """ValueError naming ``name`` unless ``layers`` holds an (H, W) array for every view."""
    for view in ordered:
        if view.stem not in layers:
            raise ValueError(f"{name}: no layer for view {view.stem!r}")
        if np.shape(layers[view.stem]) != view.shape:
            raise ValueError(f"{name}[{view.stem!r}] has shape {np.shape(layers[view.stem])}, the view is {view.shape}")


def _value_agreement(ordered: Sequence[View], quantities: Mapping[str, PixelQuantities],
                     values: Mapping[str, np.ndarray], points: object, tolerance: float, depth_tolerance: object,
                     photo_tolerance: object, blur: object) -> Agreement:
    """:func:`cross_view_value_agreement` on checked views and layers (NaN: not read)."""
    flat = _seen_pixels(ordered, quantities, points, depth_tolerance, photo_tolerance, blur)
    read = np.full(flat.shape, np.nan)
    for i, view in enumerate(ordered):
        seen = flat[i] >= 0
        read[i, seen] = np.asarray(values[view.stem], dtype=np.float64).ravel()[flat[i, seen]]
    twice = np.isfinite(read).sum(axis=0) >= 2
    if not twice.any():
        return Agreement(fraction=None, points=0, points_tested=flat.shape[1])
    read = read[:, twice]
    spread = np.nanmax(read, axis=0) - np.nanmin(read, axis=0)  # every column holds two readings or more
    return Agreement(fraction=float(np.mean(spread < tolerance)), points=int(twice.sum()),
                     points_tested=flat.shape[1])


@dataclass(frozen=True)
class ReflectanceSpread:
    """How much the views disagree on the reflectance of one surface point.

    Parameters
    ----------
    median : (3,) tuple of float or None
        Per channel (R, G, B), the median over the (point, view) readings of
        ``|R_view / R_median - 1|``, where ``R_median`` is the point's median reflectance over the
        views that see it; points seen by two or more views only. None when no point is seen twice.
    p90 : (3,) tuple of float or None
        The same readings' 90th percentile.
    points : int
        Points seen by two or more views (with a positive reflectance in each).
    points_tested : int
        Points projected.
    """

    median: tuple[float, float, float] | None
    p90: tuple[float, float, float] | None
    points: int
    points_tested: int


def cross_view_reflectance_spread(
    views: Sequence[View],
    quantities: Mapping[str, PixelQuantities],
    reflectance: Mapping[str, np.ndarray],
    points: np.ndarray,
    *,
    depth_tolerance: float = 0.02,
    photo_tolerance: float = 0.2,
    blur: float = 1.0,
) -> ReflectanceSpread:
    """Spread of a surface point's reflectance over the views that see it (issue 16's measure).

    A surface point has one reflectance whichever photo sees it; the decomposition of each photo
    gives its own. Views see a point as in :func:`cross_view_agreement` (depth test, colour close to
    the views' median). Readings with a zero or non-finite reflectance in some channel (sky, no
    estimate) are left out.

    Parameters
    ----------
    views : sequence of View
    quantities : mapping of str to PixelQuantities
    reflectance : mapping of str to (H, W, 3) array_like
        Per view, the estimated reflectance.
    points : (N, 3) array_like
        World points to test, e.g. the proxy's vertices.
    depth_tolerance, photo_tolerance, blur : float, optional
        As :func:`cross_view_agreement`.

    Returns
    -------
    ReflectanceSpread
    """
    ordered = _check_views(views, quantities)
    for view in ordered:
        if view.stem not in reflectance:
            raise ValueError(f"reflectance: no array for view {view.stem!r}")
        if np.shape(reflectance[view.stem]) != (*view.shape, 3):
            raise ValueError(f"reflectance[{view.stem!r}] has shape {np.shape(reflectance[view.stem])}, "
                             f"expected {(*view.shape, 3)}")
    flat = _seen_pixels(ordered, quantities, points, depth_tolerance, photo_tolerance, blur)
    read = np.full((*flat.shape, 3), np.nan)
    for i, view in enumerate(ordered):
        values = np.asarray(reflectance[view.stem], dtype=np.float64).reshape(-1, 3)
        seen = flat[i] >= 0
        value = values[flat[i, seen]]
        usable = (np.isfinite(value) & (value > 0)).all(axis=1)
        read[i, np.flatnonzero(seen)[usable]] = value[usable]
    twice = np.isfinite(read[..., 0]).sum(axis=0) >= 2
    read = read[:, twice]
    if not twice.any():
        return ReflectanceSpread(median=None, p90=None, points=0, points_tested=flat.shape[1])
    median = np.nanmedian(read, axis=0)  # every column holds two readings or more
    deviation = np.abs(read / median - 1.0)
    deviation = deviation[np.isfinite(deviation[..., 0])]
    return ReflectanceSpread(median=tuple(float(x) for x in np.median(deviation, axis=0)),
                             p90=tuple(float(x) for x in np.percentile(deviation, 90, axis=0)),
                             points=int(twice.sum()), points_tested=flat.shape[1])


def consensus(lit: Mapping[str, np.ndarray], correspondences: Correspondences,
              valid: Mapping[str, np.ndarray] | None = None) -> dict[str, np.ndarray]:
    """One pass of the cross-view majority vote on binary labels.

    Every pixel with consistent correspondences (:attr:`Correspondences.consistent`) takes the
    label carried by most of them and itself, keeping its own on a tie; all views are updated at
    once from the same input, so the result does not depend on the order of the views.

    Parameters
    ----------
    lit : mapping of str to (H, W) bool
        Labels per view (True: lit).
    correspondences : Correspondences
    valid : mapping of str to (H, W) bool, optional
        Pixels whose labels count; an invalid pixel neither votes nor changes.

    Returns
    -------
    dict of str to (H, W) bool
    """
    if not isinstance(correspondences, Correspondences):
        raise TypeError(f"correspondences must be Correspondences, got {describe(correspondences)}")
    out = {}
    for stem in correspondences.stems:
        own = np.asarray(lit[stem], dtype=bool).ravel()
        ok = np.ones(own.shape, bool) if valid is None else np.asarray(valid[stem], dtype=bool).ravel()
        votes = np.where(own, 1, -1) * ok
        for other in correspondences.pairs(stem):
            k = np.flatnonzero(correspondences.consistent[stem, other] & ok)
            j = correspondences.index[stem, other][k]
            partner_ok = np.ones(len(j), bool) if valid is None else np.asarray(valid[other], bool).ravel()[j]
            votes[k] += np.where(np.asarray(lit[other], dtype=bool).ravel()[j], 1, -1) * partner_ok
        new = np.where(votes > 0, True, np.where(votes < 0, False, own))
        out[stem] = np.where(ok, new, own).reshape(np.shape(lit[stem]))
    return out
