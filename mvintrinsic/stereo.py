"""Per-view PatchMatch stereo, and a proxy completed with the surfaces it lost (beyond the paper).

An MVS proxy loses thin, porous and single-view geometry: tree crowns, ledges, railings. The
relighter's caster (:mod:`~mvintrinsic.caster`) lifts every shadow pixel toward the sun by its
distance to the proxy, so a crown the proxy lost casts a shadow whose distance comes from the
nearest surface it kept, and moves wrongly at every new sun. Given the exact depth of the pixels
whose proxy depth lies more than 5% behind the truth, row (d) of ``bench_relight`` rose by +0.4 to
+2.1 dB (an oracle, ``docs/relight.md``). :func:`complete_proxy` recovers part of that from the
photographs alone:

1. **Depth and normal per pixel** (:func:`patchmatch`), as in Gipuma (Galliani et al. 2015) and
   COLMAP (Schoenberger et al. 2016): every pixel carries a slanted plane, scored by the
   bilateral-weighted normalised cross-correlation (Yoon and Kweon 2006) of a window warped by the
   plane's homography into each source view, averaged over the best ``best_views`` of them (a
   per-pixel view selection that survives occlusion). The planes start random, with the proxy's
   plane offered to every pixel, and improve by red-black propagation from eight neighbours and
   random refinement at shrinking ranges.
2. **Kept pixels**: the cost is at most ``max_cost``, the window is textured, at least
   ``agreeing_views`` source views' depth maps hold the same point (within ``depth_tolerance``),
   the depth lies more than ``in_front`` in front of the proxy's (or the proxy has none there),
   one source view sees the pixel's colour at its point within ``colour_tolerance`` in log
   radiance (NCC ignores gain and offset, so a window straddling a picket fence and the wall
   behind it can match at a depth neither lies at; its colours do not), and the kept region has
   at least ``min_region`` pixels. :func:`proxy_from_depths` is this step alone, to select again
   from the same depth maps.
3. **Surfaces**: the kept pixels of every view triangulated in image space (neighbours within 3%
   in depth) and appended to the proxy.

A plane sweep (fronto-parallel planes, square windows, winner-take-all) was tried first: its kept
pixels were where the proxy had lost geometry, but 13% of them lay more than 10% in front of the
truth (foreground fattening), and row (d) moved by -0.31 to +0.28 dB.

Measured on five 480x360 scenes (``docs/relight.md``, "The proxy completed by PatchMatch stereo";
``benchmarks/results/relight_stereo.json`` without the colour test, ``stereo_colour.json`` with it):
at +-15 degrees row (d) rises by 0.35 dB on average (-0.08 to +0.84), and the full pipeline
decomposed and relit on the completed proxy gains +0.42 to +0.74 dB on the streets but loses up
to 0.33 dB on courtyard_s1 (0.74 without the colour test); so the completion is an option, not a
default stage. About 30 s per 480x360 view on 2 cores.

The images are resampled to their cameras' distortion-free pinhole twins and to at most
``max_width`` pixels across before matching (depth maps for casters need not be finer). No I/O.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from ._validation import describe
from .camera import Camera
from .raytrace import Tracer, depth_map
from .scene import Proxy, Scene, View

__all__ = ["DepthMap", "StereoConfig", "complete_proxy", "depth_surface", "patchmatch", "proxy_from_depths", "source_views"]

_LUMINANCE = np.array([0.2126, 0.7152, 0.0722], np.float32)
# Eight propagation neighbours of the red-black scheme: each has the other colour.
_NEIGHBOURS = ((0, 1), (0, -1), (1, 0), (-1, 0), (0, 5), (0, -5), (5, 0), (-5, 0))
_CHUNK = 8000  # pixels scored at once (memory: about 50 floats per pixel, sample and view)
_INVALID = 2.0  # cost of a view that cannot score the window (outside, behind, flat)
_OUT_OF_RANGE = 3.0  # cost of a plane whose depth at the pixel leaves the depth range


@dataclass(frozen=True)
class StereoConfig:
    """Options of :func:`patchmatch` and :func:`complete_proxy` (not in the paper).

    Parameters
    ----------
    window : int
        Half-size of the matching window, pixels (a ``2 * window + 1`` square).
    stride : int
        Spacing of the window's samples, pixels (Gipuma's sparse window: 25 samples by default).
    colour_sigma : float
        Scale of the bilateral weight ``exp(-|g(q) - g(p)| / colour_sigma)``, on the square root of
        luminance normalised by its 99th percentile. 0.04 kept 91% of the kept pixels within 10% of
        the true depth on dev_courtyard, against 82% with 0.1 (the window straddles crown edges).
    source_views : int
        Views matched against each view: the nearest in viewing direction.
    best_views : int
        The cost is the mean over the best this many source views.
    iterations : int
        Red-black propagation and refinement sweeps.
    min_texture : float
        Windows whose weighted variance of the normalised square-root luminance is below this
        cannot score (the sky: median 2e-5; the scene's 10th percentile: 2e-3, dev_courtyard).
    max_cost : float
        Largest ``1 - NCC`` of a kept pixel.
    agreeing_views : int
        Source views whose own depth maps must hold a kept pixel's point.
    depth_tolerance : float
        Relative depth difference within which another view's depth map holds the point.
    in_front : float
        A kept pixel lies more than this fraction of the proxy's depth in front of it.
    min_region : int
        Smallest connected region of kept pixels, pixels.
    max_width : int
        Views wider than this are matched at this width (same aspect).
    seed : int
        Seed of the random planes.
    colour_tolerance : float or None
        If given, a kept pixel's colour must also be seen at its point by at least one source view
        within this difference of log radiance (largest over the channels); None: no colour test.
        0.15 against None on five 480x360 scenes (``benchmarks/bench_stereo.py``): the pipeline
        decomposed and relit on the completed proxy gains +0.26 dB over the own proxy at +-15
        degrees on average, worst -0.33 (None: +0.25, worst -0.74); 0.05 removes the worst loss
        and most of the gains (+0.12, worst -0.07).
    """

    window: int = 4
    stride: int = 2
    colour_sigma: float = 0.04
    source_views: int = 5
    best_views: int = 2
    iterations: int = 5
    min_texture: float = 2e-4
    max_cost: float = 0.5
    agreeing_views: int = 1
    depth_tolerance: float = 0.01
    in_front: float = 0.05
    min_region: int = 10
    max_width: int = 640
    seed: int = 0
    colour_tolerance: float | None = 0.15

    def __post_init__(self) -> None:
        for name in ("window", "stride", "source_views", "best_views", "iterations", "max_width"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise ValueError(f"{name} must be a positive integer, got {describe(value)}")
        for name in ("agreeing_views", "min_region", "seed"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
                raise ValueError(f"{name} must be a non-negative integer, got {describe(value)}")
        for name in ("colour_sigma", "min_texture", "max_cost", "depth_tolerance"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and np.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, got {describe(value)}")
        tol = self.colour_tolerance
        if tol is not None and not (isinstance(tol, (int, float)) and not isinstance(tol, bool)
                                    and np.isfinite(tol) and tol > 0):
            raise ValueError(f"colour_tolerance must be a positive number or None, got {describe(tol)}")
        if not (isinstance(self.in_front, (int, float)) and 0 <= self.in_front < 1):
            raise ValueError(f"in_front must be in [0, 1), got {describe(self.in_front)}")
        if self.best_views > self.source_views:
            raise ValueError(f"best_views ({self.best_views}) must not exceed source_views ({self.source_views})")


@dataclass(frozen=True)
class DepthMap:
    """One view's PatchMatch result, on the pixel grid of ``camera``.

    Parameters
    ----------
    camera : Camera
        The distortion-free pinhole camera the maps are in (the view's camera's twin, possibly
        scaled to ``StereoConfig.max_width``).
    depth : (H, W) float64
        Depth along the optical axis (camera z), metres; NaN where no plane has a depth in range.
    normal : (H, W, 3) float64
        Unit normals in the world frame, facing the camera.
    cost : (H, W) float32
        ``1 - NCC`` averaged over the best source views, in [0, 2]; 2 or more: no view could score.
    sources : tuple of int
        Indices of the source views matched.
    """

    camera: Camera
    depth: np.ndarray
    normal: np.ndarray
    cost: np.ndarray
    sources: tuple[int, ...]

    def points(self) -> np.ndarray:
        """World points of every pixel, (H, W, 3) metres (NaN where the depth is)."""
        rays = self.camera.pixel_rays().reshape(*self.depth.shape, 3)
        along = self.depth / (rays @ self.camera.forward)
        return self.camera.center + rays * along[..., None]


def _pinhole(view: View, max_width: int) -> tuple[Camera, np.ndarray]:
    """The view's distortion-free pinhole twin at most ``max_width`` wide, and its grey image.

    Grey: square root of the luminance over its 99th percentile (invalid pixels 0).
    """
    cam = view.camera
    scale = min(1.0, max_width / cam.width)
    w, h = max(1, round(cam.width * scale)), max(1, round(cam.height * scale))
    image = np.where(view.mask[..., None], np.nan_to_num(view.image, nan=0.0), 0.0).astype(np.float32)
    grey = np.sqrt(np.maximum(image @ _LUMINANCE, 0.0))
    (fx, fy), (cx, cy) = cam.focal, cam.principal_point
    sx, sy = w / cam.width, h / cam.height
    pin = Camera("PINHOLE", w, h, np.array([fx * sx, fy * sy, cx * sx, cy * sy]), cam.rotation, cam.translation)
    if cam.is_distorted or (w, h) != (cam.width, cam.height):
        xy = pin.pixels_to_normalized(pin.pixel_centers().reshape(-1, 2))
        src = cam.normalized_to_pixels(xy) - 0.5
        mx = src[:, 0].reshape(h, w).astype(np.float32)
        my = src[:, 1].reshape(h, w).astype(np.float32)
        if scale < 1:  # anti-alias before sampling
            grey = cv2.GaussianBlur(grey, (0, 0), 0.5 / scale)
        grey = cv2.remap(grey, np.nan_to_num(mx, nan=-1), np.nan_to_num(my, nan=-1), cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return pin, (grey / max(float(np.percentile(grey, 99)), 1e-12)).astype(np.float32)


def source_views(cameras: Sequence[Camera], index: int, count: int) -> tuple[int, ...]:
    """The ``count`` views nearest view ``index`` in viewing direction (smallest angle between the
    optical axes; ties by distance between the centres)."""
    ref = cameras[index]
    keys = []
    for k, cam in enumerate(cameras):
        if k != index:
            angle = float(np.arccos(np.clip(ref.forward @ cam.forward, -1.0, 1.0)))
            keys.append((angle, float(np.linalg.norm(ref.center - cam.center)), k))
    return tuple(k for _, _, k in sorted(keys)[:count])


class _Matcher:
    """Scores slanted planes of one reference view against its source views (camera frame)."""

    def __init__(self, ref: Camera, grey: np.ndarray, sources: Sequence[tuple[Camera, np.ndarray]],
                 depth_range: tuple[float, float], config: StereoConfig, rng: np.random.Generator) -> None:
        self.h, self.w = h, w = ref.height, ref.width
        self.zmin, self.zmax = depth_range
        self.config, self.rng = config, rng
        self.k_inv = np.linalg.inv(ref.K)
        offsets = np.arange(-config.window, config.window + 1, config.stride)
        dy, dx = np.meshgrid(offsets, offsets, indexing="ij")
        self.dx, self.dy = dx.ravel().astype(np.float64), dy.ravel().astype(np.float64)
        yy, xx = np.mgrid[0:h, 0:w]
        self.px, self.py = xx.ravel(), yy.ravel()
        qx = self.px[:, None] + dx.ravel()[None]
        qy = self.py[:, None] + dy.ravel()[None]
        inside = (qx >= 0) & (qx < w) & (qy >= 0) & (qy < h)
        samples = grey[np.clip(qy, 0, h - 1), np.clip(qx, 0, w - 1)]
        self.a = samples.astype(np.float32)
        self.weight = (np.exp(-np.abs(samples - grey.ravel()[:, None]) / config.colour_sigma) * inside).astype(np.float32)
        self.weight_sum = self.weight.sum(axis=1)
        pixels = np.stack([self.px + 0.5, self.py + 0.5, np.ones(h * w)], axis=1)
        self.ray = pixels @ self.k_inv.T  # (H*W, 3), z = 1, camera frame
        self.sources = []
        for cam, image in sources:
            rotation = cam.rotation @ ref.rotation.T
            shift = cam.translation - rotation @ ref.translation
            # Homography of the plane n.X = c: K_s (R + t n^T / c) K_r^-1 = A + b m^T, m = K_r^-T n / c.
            self.sources.append((cam.K @ rotation @ self.k_inv, cam.K @ shift, image, cam.width, cam.height))

    def depth(self, idx: np.ndarray, normal: np.ndarray, offset: np.ndarray) -> np.ndarray:
        with np.errstate(divide="ignore", invalid="ignore"):
            return offset / np.einsum("ij,ij->i", normal, self.ray[idx])

    def cost(self, idx: np.ndarray, normal: np.ndarray, offset: np.ndarray) -> np.ndarray:
        """Cost ``1 - NCC`` over the best source views of the planes ``normal . X = offset`` at
        pixels ``idx``, (M,) float32."""
        out = np.empty(len(idx), np.float32)
        for s in range(0, len(idx), _CHUNK):
            part = slice(s, s + _CHUNK)
            out[part] = self._cost(idx[part], normal[part], offset[part])
        return out

    def _cost(self, idx: np.ndarray, normal: np.ndarray, offset: np.ndarray) -> np.ndarray:
        z = self.depth(idx, normal, offset)
        bad = ~np.isfinite(z) | (z < self.zmin) | (z > self.zmax)
        m = (normal @ self.k_inv) / np.where(bad, 1.0, offset)[:, None]
        p = np.stack([self.px[idx] + 0.5, self.py[idx] + 0.5, np.ones(len(idx))], axis=1)
        mq = np.einsum("ij,ij->i", m, p)[:, None] + m[:, :1] * self.dx + m[:, 1:2] * self.dy
        a, weight = self.a[idx], self.weight[idx]
        enough = 0.6 * self.weight_sum[idx]
        costs = np.empty((len(idx), len(self.sources)), np.float32)
        for k, (A, b, image, w, h) in enumerate(self.sources):
            ap = p @ A.T
            x, y, z3 = (ap[:, r:r + 1] + A[r, 0] * self.dx + A[r, 1] * self.dy + b[r] * mq for r in range(3))
            with np.errstate(divide="ignore", invalid="ignore"):
                u, v = x / z3 - 0.5, y / z3 - 0.5
                valid = (z3 > 0) & (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
            u = np.where(valid, u, -10.0).astype(np.float32)
            v = np.where(valid, v, -10.0).astype(np.float32)
            bb = cv2.remap(image, u, v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
            wv = weight * valid
            sw = wv.sum(axis=1) + 1e-12
            da = a - ((wv * a).sum(axis=1) / sw)[:, None]
            db = bb - ((wv * bb).sum(axis=1) / sw)[:, None]
            va, vb = (wv * da * da).sum(axis=1), (wv * db * db).sum(axis=1)
            cost = 1.0 - (wv * da * db).sum(axis=1) / np.sqrt(va * vb + 1e-10)
            floor = self.config.min_texture * sw
            cost[(sw < enough) | (va < floor) | (vb < 1e-6 * sw)] = _INVALID
            costs[:, k] = cost
        costs.sort(axis=1)
        out = costs[:, : self.config.best_views].mean(axis=1)
        out[bad] = _OUT_OF_RANGE
        return out

    def random_planes(self, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        z = 1.0 / self.rng.uniform(1.0 / self.zmax, 1.0 / self.zmin, len(idx))
        normal = self.rng.normal(size=(len(idx), 3))
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        normal *= -np.sign(np.einsum("ij,ij->i", normal, self.ray[idx]))[:, None]
        return normal, np.einsum("ij,ij->i", normal, self.ray[idx] * z[:, None])

    def perturbed(self, idx, normal, z, depth_range, normal_spread):
        z = np.clip(z * (1.0 + self.rng.uniform(-1.0, 1.0, len(idx)) * depth_range), self.zmin, self.zmax)
        if normal_spread > 0:
            step = self.rng.normal(size=(len(idx), 3))
            step /= np.linalg.norm(step, axis=1, keepdims=True)
            moved = normal + normal_spread * step
            moved /= np.linalg.norm(moved, axis=1, keepdims=True)
            facing = np.einsum("ij,ij->i", moved, self.ray[idx]) < 0
            normal = np.where(facing[:, None], moved, normal)
        return normal, np.einsum("ij,ij->i", normal, self.ray[idx] * z[:, None])


def _proxy_planes(camera: Camera, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Planes (camera frame) of a depth map: normals from its central differences, (H*W, 3) and
    (H*W,) offsets; NaN offsets where the depth is not finite."""
    h, w = z.shape
    yy, xx = np.mgrid[0:h, 0:w]
    rays = np.stack([xx + 0.5, yy + 0.5, np.ones((h, w))], axis=-1) @ np.linalg.inv(camera.K).T
    with np.errstate(invalid="ignore"):
        points = rays * z[..., None]
        gx, gy = np.zeros_like(points), np.zeros_like(points)
        gx[:, 1:-1] = points[:, 2:] - points[:, :-2]
        gy[1:-1] = points[2:] - points[:-2]
        normal = np.cross(gy, gx)
        length = np.linalg.norm(normal, axis=-1, keepdims=True)
        normal = normal / np.where(length > 0, length, 1.0)
        normal *= -np.sign(np.einsum("ijk,ijk->ij", normal, rays))[..., None]
    fallback = ~(np.isfinite(normal).all(axis=-1) & (np.linalg.norm(normal, axis=-1) > 0.5))
    normal[fallback] = -rays[fallback] / np.linalg.norm(rays[fallback], axis=-1, keepdims=True)
    offset = np.einsum("ijk,ijk->ij", normal, np.nan_to_num(points, nan=0.0, posinf=0.0))
    offset[~np.isfinite(z)] = np.nan
    return normal.reshape(-1, 3), offset.ravel()


def patchmatch(cameras: Sequence[Camera], greys: Sequence[np.ndarray], index: int, *,
               depth_range: tuple[float, float], sources: Sequence[int] | None = None,
               prior_depth: np.ndarray | None = None, config: StereoConfig = StereoConfig()) -> DepthMap:
    """Depth and normal of every pixel of one view by PatchMatch stereo (module docstring, step 1).

    Parameters
    ----------
    cameras : sequence of Camera
        Distortion-free pinhole cameras of all views (``PINHOLE``/``SIMPLE_PINHOLE``).
    greys : sequence of (H_k, W_k) float32
        Grey images on those cameras' grids (:func:`complete_proxy` uses the square root of
        luminance over its 99th percentile).
    index : int
        The reference view.
    depth_range : (float, float)
        Smallest and largest depth along the optical axis, metres.
    sources : sequence of int, optional
        Source views; default :func:`source_views` with ``config.source_views``.
    prior_depth : (H, W) float64, optional
        A depth map (camera z, metres; non-finite where none) whose planes every pixel is offered
        at the start: the proxy's.
    config : StereoConfig

    Returns
    -------
    DepthMap
    """
    ref = cameras[index]
    if ref.is_distorted:
        raise ValueError(f"cameras[{index}] is distorted ({ref.model}): give the pinhole twin")
    zmin, zmax = (float(v) for v in depth_range)
    if not (0 < zmin < zmax and np.isfinite(zmax)):
        raise ValueError(f"depth_range must be 0 < near < far < inf, got {depth_range!r}")
    sources = tuple(source_views(cameras, index, config.source_views) if sources is None else sources)
    if len(sources) < config.best_views:
        raise ValueError(f"sources: {len(sources)} views for best_views={config.best_views}")
    rng = np.random.default_rng([config.seed, index])
    match = _Matcher(ref, greys[index], [(cameras[k], greys[k]) for k in sources], (zmin, zmax), config, rng)
    h, w = ref.height, ref.width
    every = np.arange(h * w)
    normal, offset = match.random_planes(every)
    cost = match.cost(every, normal, offset)
    if prior_depth is not None:
        n0, c0 = _proxy_planes(ref, np.asarray(prior_depth, dtype=np.float64))
        have = every[np.isfinite(c0)]
        trial = match.cost(have, n0[have], c0[have])
        better = trial < cost[have]
        take = have[better]
        normal[take], offset[take], cost[take] = n0[take], c0[take], trial[better]
    colour = (match.px + match.py) % 2
    for it in range(config.iterations):
        scale = 0.5 ** it  # refinement ranges shrink by half per sweep
        kinds = [*_NEIGHBOURS, (0.1 * scale, 0.0), (0.0, 0.5 * scale), (0.1 * scale, 0.5 * scale)]
        if it < 3:
            kinds.append("random")
        for c in (0, 1):
            idx = every[colour == c]
            y, x = match.py[idx], match.px[idx]
            for kind in kinds:
                if kind == "random":
                    n, o = match.random_planes(idx)
                elif isinstance(kind[0], int):  # propagation: a neighbour's plane
                    nb = np.clip(y + kind[0], 0, h - 1) * w + np.clip(x + kind[1], 0, w - 1)
                    n, o = normal[nb], offset[nb]
                else:  # refinement: depth and/or normal perturbed
                    z = match.depth(idx, normal[idx], offset[idx])
                    n, o = match.perturbed(idx, normal[idx], z, *kind)
                trial = match.cost(idx, n, o)
                better = trial < cost[idx]
                take = idx[better]
                normal[take], offset[take], cost[take] = n[better], o[better], trial[better]
    depth = match.depth(every, normal, offset).reshape(h, w)
    depth[~((depth >= zmin) & (depth <= zmax))] = np.nan
    return DepthMap(camera=ref, depth=depth, normal=(normal @ ref.rotation).reshape(h, w, 3),
                    cost=cost.reshape(h, w), sources=sources)


def _agreeing(maps: Sequence[DepthMap], index: int, tolerance: float) -> np.ndarray:
    """How many of view ``index``'s source views' depth maps hold its pixels' points, (H, W) int."""
    own = maps[index]
    h, w = own.depth.shape
    points = own.points().reshape(-1, 3)
    count = np.zeros(h * w, np.int32)
    for k in own.sources:
        other = maps[k]
        cam = other.camera
        uv, z = cam.project(points)
        u, v = np.floor(uv[:, 0]), np.floor(uv[:, 1])
        with np.errstate(invalid="ignore"):
            inside = (z > 0) & cam.in_image(uv)
        seen = np.full(h * w, np.nan)
        seen[inside] = other.depth[v[inside].astype(int), u[inside].astype(int)]
        with np.errstate(invalid="ignore"):
            count += np.abs(seen - z) < tolerance * z
    return count.reshape(h, w)


def depth_surface(depth: DepthMap, keep: np.ndarray, *, max_ratio: float = 1.03) -> tuple[np.ndarray, np.ndarray]:
    """Triangulate the kept pixels of a depth map in image space (module docstring, step 3).

    Two triangles per 2x2 block of kept pixels whose depths lie within ``max_ratio`` of each other.

    Returns
    -------
    vertices : (N, 3) float64
        World points, metres.
    triangles : (T, 3) int64
        Indices into ``vertices``.
    """
    z = depth.depth
    keep = np.asarray(keep, dtype=bool) & np.isfinite(z)
    index = np.full(z.shape, -1, np.int64)
    index[keep] = np.arange(int(keep.sum()))
    vertices = depth.points()[keep]
    a, b, c, d = index[:-1, :-1], index[:-1, 1:], index[1:, :-1], index[1:, 1:]
    za, zb, zc, zd = z[:-1, :-1], z[:-1, 1:], z[1:, :-1], z[1:, 1:]
    triangles = []
    for (p, q, r), (zp, zq, zr) in (((a, c, b), (za, zc, zb)), ((b, c, d), (zb, zc, zd))):
        ok = (p >= 0) & (q >= 0) & (r >= 0)
        with np.errstate(invalid="ignore"):
            ok &= np.fmax(np.fmax(zp, zq), zr) <= max_ratio * np.fmin(np.fmin(zp, zq), zr)
        triangles.append(np.stack([p[ok], q[ok], r[ok]], axis=1))
    return vertices, np.concatenate(triangles).astype(np.int64)


def _with_surfaces(proxy: Proxy, parts: Sequence[tuple[np.ndarray, np.ndarray, View]]) -> Proxy:
    """The proxy mesh plus triangulated parts (vertices, triangles, the view they come from), their
    vertex normals from the triangles, turned toward that view's camera; their colours (if the proxy
    has colours) the view's pixels they project to."""
    vertices, normals, triangles = [proxy.vertices], [proxy.normals], [proxy.triangles]
    colors = None if proxy.colors is None else [proxy.colors]
    offset = len(proxy.vertices)
    for verts, tris, view in parts:
        center = view.camera.center
        if len(tris) == 0:
            continue
        used = np.unique(tris)
        remap = np.full(len(verts), -1, np.int64)
        remap[used] = np.arange(len(used))
        verts, tris = verts[used], remap[tris]
        face = np.cross(verts[tris[:, 1]] - verts[tris[:, 0]], verts[tris[:, 2]] - verts[tris[:, 0]])
        n = np.zeros_like(verts)
        for k in range(3):
            np.add.at(n, tris[:, k], face)
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
        n *= np.where(np.einsum("ij,ij->i", n, center - verts) < 0, -1.0, 1.0)[:, None]
        vertices.append(verts)
        normals.append(n)
        triangles.append(tris + offset)
        if colors is not None:
            uv, _ = view.camera.project(verts)
            i = np.clip(np.floor(uv[:, 0]).astype(int), 0, view.camera.width - 1)
            j = np.clip(np.floor(uv[:, 1]).astype(int), 0, view.camera.height - 1)
            colors.append(np.nan_to_num(view.image[j, i], nan=0.0).astype(np.float32))
        offset += len(verts)
    return Proxy(vertices=np.concatenate(vertices), normals=np.concatenate(normals),
                 triangles=np.concatenate(triangles),
                 colors=None if colors is None else np.concatenate(colors))


def complete_proxy(scene: Scene, *, config: StereoConfig = StereoConfig(), tracer: Tracer | None = None,
                   progress: Callable[[str], None] | None = None) -> tuple[Proxy, tuple[DepthMap, ...]]:
    """The scene's proxy with the surfaces the photographs show in front of it (module docstring).

    Parameters
    ----------
    scene : Scene
        Views and a triangle-mesh proxy.
    config : StereoConfig, optional
    tracer : Tracer, optional
        A tracer of ``scene.proxy`` (built if not given).
    progress : callable, optional
        Called with a line of text after each view.

    Returns
    -------
    proxy : Proxy
        ``scene.proxy`` with the kept pixels' surfaces appended (the same vertices first, in order).
    depths : tuple of DepthMap
        Every view's PatchMatch result.

    Raises
    ------
    ValueError
        If the proxy is a point cloud, or the scene has fewer views than ``config.best_views + 1``.
    """
    if scene.proxy.triangles is None:
        raise ValueError("scene: complete_proxy needs a triangle-mesh proxy, got a point cloud")
    if len(scene.views) < config.best_views + 1:
        raise ValueError(f"scene: {len(scene.views)} views, need at least best_views + 1 = {config.best_views + 1}")
    tracer = Tracer(scene.proxy) if tracer is None else tracer
    cameras, greys = zip(*(_pinhole(view, config.max_width) for view in scene.views), strict=True)
    # The proxy's depth along each optical axis (camera z), inf where it has none.
    proxy_depth = [_axis_depth(cam, tracer) for cam in cameras]
    maps = []
    for k in range(len(cameras)):
        start = time.perf_counter()
        finite = proxy_depth[k][np.isfinite(proxy_depth[k])]
        if finite.size == 0:
            raise ValueError(f"scene: the proxy is not in view {scene.views[k].stem!r}")
        near, far = 0.3 * float(np.percentile(finite, 1)), 1.3 * float(np.percentile(finite, 99))
        maps.append(patchmatch(cameras, greys, k, depth_range=(near, far), prior_depth=proxy_depth[k], config=config))
        if progress is not None:
            progress(f"stereo: view {scene.views[k].stem} in {time.perf_counter() - start:.1f} s")
    return proxy_from_depths(scene, maps, config=config, tracer=tracer, proxy_depth=proxy_depth), tuple(maps)


def _axis_depth(camera: Camera, tracer: Tracer) -> np.ndarray:
    """The proxy's depth along the camera's optical axis (camera z) per pixel, (H, W); inf where it has none."""
    return depth_map(camera, tracer) * (camera.pixel_rays() @ camera.forward).reshape(camera.shape)


def _colour_seen(scene: Scene, depth: DepthMap, index: int, keep: np.ndarray, tolerance: float) -> np.ndarray:
    """Which kept pixels' colours a source view sees at their points within ``tolerance`` (log radiance).

    The colours are read at the nearest pixel of the views' own (possibly distorted) cameras.
    """
    points = depth.points()[keep]

    def log_colour(view: View) -> np.ndarray:
        uv, z = view.camera.project(points)
        with np.errstate(invalid="ignore"):
            inside = (z > 0) & view.camera.in_image(uv)
        out = np.full((len(points), 3), np.nan)
        i, j = np.floor(uv[inside, 0]).astype(int), np.floor(uv[inside, 1]).astype(int)
        seen = view.mask[j, i]
        rgb = np.where(seen[:, None], view.image[j, i], np.nan)
        with np.errstate(invalid="ignore", divide="ignore"):
            out[inside] = np.log(np.maximum(rgb, 1e-4))
        return out

    own = log_colour(scene.views[index])
    ok = np.zeros(len(points), bool)
    for k in depth.sources:
        with np.errstate(invalid="ignore"):
            ok |= np.abs(log_colour(scene.views[k]) - own).max(axis=1) < tolerance
    out = np.zeros(keep.shape, bool)
    out[keep] = ok
    return out


def proxy_from_depths(scene: Scene, depths: Sequence[DepthMap], *, config: StereoConfig = StereoConfig(),
                      tracer: Tracer | None = None, proxy_depth: Sequence[np.ndarray] | None = None) -> Proxy:
    """The scene's proxy completed with the kept pixels of its views' depth maps (module docstring, 2-3).

    The selection half of :func:`complete_proxy`: call it again with another ``config`` to try other
    selections of the same (costly) PatchMatch results.

    Parameters
    ----------
    scene : Scene
        The scene the depth maps were computed for (one per view, in order).
    depths : sequence of DepthMap
        :func:`complete_proxy`'s second result.
    config : StereoConfig, optional
        Its selection fields (``max_cost``, ``agreeing_views``, ``depth_tolerance``, ``in_front``,
        ``min_region``, ``colour_tolerance``) apply.
    tracer : Tracer, optional
        A tracer of ``scene.proxy`` (built if not given).
    proxy_depth : sequence of (H, W) arrays, optional
        The proxy's depth along each depth map's optical axis (computed if not given).

    Returns
    -------
    Proxy
        ``scene.proxy`` with the kept pixels' surfaces appended.

    Raises
    ------
    ValueError
        If ``depths`` does not hold one depth map per view.
    """
    if len(depths) != len(scene.views):
        raise ValueError(f"depths: {len(depths)} depth maps for {len(scene.views)} views")
    if proxy_depth is None:
        tracer = Tracer(scene.proxy) if tracer is None else tracer
        proxy_depth = [_axis_depth(dm.camera, tracer) for dm in depths]
    parts = []
    for k, dm in enumerate(depths):
        zp = proxy_depth[k]
        with np.errstate(invalid="ignore"):
            keep = np.isfinite(dm.depth) & (dm.cost <= config.max_cost) & (
                ~np.isfinite(zp) | (dm.depth < (1.0 - config.in_front) * zp))
        keep &= _agreeing(depths, k, config.depth_tolerance) >= config.agreeing_views
        if config.colour_tolerance is not None:
            keep &= _colour_seen(scene, dm, k, keep, config.colour_tolerance)
        if config.min_region > 1:
            _, label, stats, _ = cv2.connectedComponentsWithStats(keep.astype(np.uint8), connectivity=8)
            keep &= stats[label, cv2.CC_STAT_AREA] >= config.min_region
        parts.append((*depth_surface(dm, keep), scene.views[k]))
    return _with_surfaces(scene.proxy, parts)
