"""Relighting geometry: shadow receivers, a 2.5D shadow caster and moving cast shadows (Sec. 8).

The proxy's own shadows do not match the shadow boundaries of the photographs (paper Fig. 4b), so
the paper relights with a *caster* built from the shadows of the image itself (Duchêne et al.
2015, Sec. 8, "Creating Shadow Receiver and Caster Geometry" and "Moving Shadows"). This module
builds that geometry and computes the new shadow layer for any sun; the shading adjustment of
Sec. 8 is not here.

**Receiver** (:func:`receiver_depth`, :func:`receiver_points`). Every pixel gets the distance along
its camera ray to the proxy; pixels whose ray misses take the value of the nearest pixel that hits.

**Shadow pixels** (:func:`shadow_pixels`). A pixel is in shadow when Step 3 labels it shadow or
when its visibility ``v_sun < tau_s`` (``tau_s = 0.8``): the propagated ``v_sun`` keeps fine
shadow details the binary labelling loses.

**Caster** (:func:`build_caster`). From the receiver point ``P_p`` of each shadow pixel a ray
toward the sun ``d`` is traced against the proxy; its first hit at distance ``t_p`` is where the
occluder is. Shadow pixels are grouped into 8-connected clusters; a cluster smaller than
``min_cluster`` pixels (100) or in which fewer than ``min_proxy_hits`` (30%) of the rays hit the
proxy is a mislabelling and is dropped. In the kept clusters a pixel whose ray missed takes the
``t`` of the nearest kept pixel whose ray hit. The kept pixels are triangulated in image space and
lifted toward the sun, ``C = P + t d``: a 2.5D sheet whose shadow at the capture sun is the
shadow of the image (up to pixels along depth edges). Last, a ray toward the sun is cast from the
receiver point of every lit pixel against the caster; a triangle first hit by more than
``epsilon`` (3) of them contradicts the image (a lit pixel it would shade) and is removed. As
every quad re-projects onto its own pixel's footprint at the capture sun, only triangles that an
inconsistent receiver places over several lit pixels reach that count.

**Moving shadows** (:class:`ShadowCaster`). For a new sun, a ray from every receiver point toward
it is tested against the caster (Embree, via open3d, the structure built once per caster). Where
the caster has no coverage the proxy's shadow completes it, and a Gaussian blur of ``blur``
pixels softens the result and fills the cracks between disconnected triangles. The casters of
several views can be merged into one (:func:`merge_casters`) that shades every view.

Deviations from the paper, with their reasons
---------------------------------------------
* **Receiver by ray casting.** The paper gives each pixel "the depth value of the closest projected
  3D point"; here the pixel ray is intersected with the proxy through the project's
  :class:`~mvintrinsic.raytrace.Tracer` (triangles of a mesh, surfels of a point cloud), which is
  the same depth without holes between projected points, and misses are filled as the paper fills
  caster distances (nearest valid pixel, ``scipy.ndimage.distance_transform_edt``).
* **One quad per pixel footprint.** "We triangulate the shadow pixels in image space" is read as
  a mesh over the kept pixels' *footprints*: each kept pixel is the quad (two triangles) between
  its four pixel corners. A corner lies on the camera ray through that pixel corner, at a
  receiver distance ``s_c``, and is lifted by a caster distance ``t_c``; both average, over the
  kept pixels touching the corner that lie on the same surface as the pixel, each one's linear
  extrapolation to the corner (its value plus its image gradient times the half-pixel offset).
  Two kept pixels are on the same surface when their receiver distances differ by at most
  :data:`SURFACE_JUMP` (5%) and their caster distances by at most :data:`CASTER_JUMP` (25%, or 8
  pixel footprints). On a smooth surface every touching pixel extrapolates to the same corner, so
  neighbouring quads share their corners (the sheet is closed and moves as one when the sun
  moves), and the corners on the outline of a shadow sit on the receiver rather than half a pixel
  inside it; across a jump the quads separate instead of stretching. Why not the plain reading
  (one vertex per shadow pixel centre, two triangles per 2x2 block of shadow pixels): it puts
  every outline pixel of the shadow on the mesh's edge, where the pixel's own ray grazes a vertex
  and hits or misses at float32 rounding, and stretches triangles across every depth edge.
  Measured on ``tests/test_relight.py``'s box-on-a-plane scene (96x72, exact proxy and exact
  shadow mask, 11 pairs of camera and sun, elevations 30-65 degrees), the mean IoU of the caster's
  shadow with the exact shadow, at the capture sun and after a 15-degree azimuth change, is
  0.93 and 0.87 with one vertex per pixel centre, 0.92 and 0.89 with footprint corners averaged
  without extrapolation, 0.97 and 0.65 with unshared per-pixel quads, and 0.97 and 0.93 with this
  construction. The two thresholds were chosen on those cases; they are module constants, not
  paper parameters. Four vertices are stored per kept pixel (shared corners are equal bit for bit,
  not merged).
* **Cluster filtering before filling.** The paper does not say in which order it filters clusters
  and fills missed distances; here clusters are filtered first, so a kept pixel never borrows the
  distance of a dropped (mislabelled) cluster. A cluster with no proxy hit at all is always
  dropped (it cannot be lifted), whatever ``min_proxy_hits``.
* **Ray offset.** Rays start ``ray_offset`` metres (0.02, about a TSDF voxel, as in Step 1) along
  the sun direction from the receiver points, against self-intersection with the proxy; the
  caster distances are measured from the receiver point itself.
* **Which lit pixels vote.** By default every pixel outside the shadow mask casts an ``epsilon``
  ray (pixels of dropped clusters do not: they were shadow in the input). The caller may pass its
  own ``lit`` mask, e.g. only pixels the proxy covers and Step 3 labels lit (pixels whose ray
  misses the proxy, such as the sky, have filled receivers floating in the air).
* **Proxy completion, "no coverage".** The paper completes "the missing shadow in these areas using
  the shadow of the proxy geometry" without defining the areas. Here the caster records which
  proxy primitives (triangles; surfel points of a point cloud) the rays of its kept pixels hit:
  the occluders whose shadows the image shows and the caster stands for. For a new sun, a pixel
  whose shadow ray's first proxy hit is a primitive *not* in that set is occluded by geometry whose
  shadow the image never showed (it fell outside the frame, or on a part of the scene no view
  covers), and takes the proxy's shadow; elsewhere the caster decides. A plain OR of the two
  shadows would bring back the inaccurate proxy shadow boundaries the caster exists to replace.
* **Attached shadow.** When normals are given, a receiver point facing away from the new sun
  (``n . d <= 0``) has visibility 0, as the proxy visibility of Step 1
  (:func:`mvintrinsic.raytrace.sun_visibility`).

References
----------
.. [1] S. Duchêne, C. Riant, G. Chaurasia, J. Lopez-Moreno, P.-Y. Laffont, S. Popov, A. Bousseau
   and G. Drettakis, "Multi-View Intrinsic Images of Outdoors Scenes with an Application to
   Relighting", ACM Transactions on Graphics 34(5), 2015, Sec. 8.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from ._libusb import ensure_libusb
from ._validation import as_array, as_unit_vector, describe, is_real
from .camera import Camera
from .raytrace import DEFAULT_BATCH, Tracer
from .results import SHADOW_LABELS

__all__ = [
    "Caster",
    "RelightConfig",
    "ShadowCaster",
    "build_caster",
    "merge_casters",
    "receiver_depth",
    "receiver_points",
    "shadow_pixels",
]

#: 8-connectivity of the shadow clusters.
_EIGHT = np.ones((3, 3), dtype=bool)

#: ``primitive_ids`` of a ray that hits nothing (open3d's ``RaycastingScene.INVALID_ID``).
_INVALID_ID = np.iinfo(np.uint32).max


@dataclass(frozen=True)
class RelightConfig:
    """Options of the relighting geometry (paper Sec. 8), the paper's values as defaults.

    Parameters
    ----------
    tau_s : float
        A pixel with ``v_sun < tau_s`` counts as shadow besides the shadow labels; in [0, 1].
        0.8: "We used tau_s = 0.8 for all our results."
    epsilon : int
        A caster triangle first hit by more than ``epsilon`` sun rays from lit pixels is removed;
        >= 0. 3: "We used epsilon = 3 for all our results."
    min_cluster : int
        Shadow clusters (8-connected) of fewer pixels are dropped; >= 1. 100: "less than 100
        pixels".
    min_proxy_hits : float
        Shadow clusters in which a smaller share of the pixels' sun rays hit the proxy are
        dropped; in [0, 1]. 0.3: "less than 30% of the pixels yield an intersection".
    blur : float
        Standard deviation, pixels, of the Gaussian blur of the new shadow layer (0: none); >= 0.
        The paper applies "a small Gaussian blur" without a value; 1 pixel softens the edge to
        about the width of a photographed penumbra at these resolutions and closes one-pixel
        cracks.
    ray_offset : float
        Metres a sun ray starts from its receiver point along the sun direction, against
        self-intersection; >= 0. Not in the paper; 0.02 as Step 1's ``ray_offset`` (about a TSDF
        voxel).
    """

    tau_s: float = 0.8
    epsilon: int = 3
    min_cluster: int = 100
    min_proxy_hits: float = 0.3
    blur: float = 1.0
    ray_offset: float = 0.02

    def __post_init__(self) -> None:
        for name, least in (("epsilon", 0), ("min_cluster", 1)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
                raise ValueError(f"{name} must be an integer >= {least}, got {value!r}")
            object.__setattr__(self, name, int(value))
        for name in ("tau_s", "min_proxy_hits"):
            value = getattr(self, name)
            if not is_real(value) or not 0.0 <= value <= 1.0:
                raise ValueError(f"{name} must be a number in [0, 1], got {value!r}")
            object.__setattr__(self, name, float(value))
        for name in ("blur", "ray_offset"):
            value = getattr(self, name)
            if not is_real(value) or not 0.0 <= value < np.inf:
                raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
            object.__setattr__(self, name, float(value))


@dataclass(frozen=True, eq=False)
class Caster:
    """A shadow-caster mesh in the world frame (paper Sec. 8, Fig. 9 right).

    Parameters
    ----------
    vertices : (N, 3) float64
        World-frame vertex positions, metres.
    triangles : (M, 3) int32
        Vertex indices of the triangles (orientation is meaningless: rays hit both sides).
    proxy_primitives : (K,) int64
        Sorted indices of the proxy primitives (:attr:`RayHits.triangle
        <mvintrinsic.raytrace.RayHits>`: mesh triangles, or surfel points of a point cloud) hit by
        the sun rays of the kept shadow pixels: the occluders the caster stands for. Proxy
        completion (:meth:`ShadowCaster.sun_visibility`) applies to the others.
    shadow : (H, W) bool or None
        The shadow pixels the caster was built from (kept clusters); ``None`` for a merged caster.
    dropped : (H, W) bool or None
        Shadow pixels of the dropped clusters (too small, or too few proxy hits): mislabellings the
        paper brings back into light; ``None`` for a merged caster.
    n_clusters : int
        Number of 8-connected shadow clusters in the input mask.
    n_small : int
        Clusters dropped for having fewer than ``min_cluster`` pixels.
    n_unsupported : int
        Clusters of at least ``min_cluster`` pixels dropped for a share of proxy hits below
        ``min_proxy_hits`` (or no hit at all).
    n_removed : int
        Triangles removed for being first hit by more than ``epsilon`` rays from lit pixels.

    Notes
    -----
    Instances are immutable; arrays are read-only.
    """

    vertices: np.ndarray
    triangles: np.ndarray
    proxy_primitives: np.ndarray
    shadow: np.ndarray | None
    dropped: np.ndarray | None
    n_clusters: int
    n_small: int
    n_unsupported: int
    n_removed: int

    def __post_init__(self) -> None:
        vertices = as_array(self.vertices, "vertices", shape=(None, 3), dtype=np.float64)
        triangles = as_array(self.triangles, "triangles", shape=(None, 3), dtype=np.int32)
        if len(triangles) and (triangles.min() < 0 or triangles.max() >= len(vertices)):
            raise ValueError(f"triangles index vertices outside [0, {len(vertices)})")
        primitives = as_array(self.proxy_primitives, "proxy_primitives", shape=(None,), dtype=np.int64)
        object.__setattr__(self, "vertices", vertices)
        object.__setattr__(self, "triangles", triangles)
        object.__setattr__(self, "proxy_primitives", primitives)
        if (self.shadow is None) != (self.dropped is None):
            raise ValueError("shadow and dropped must both be masks or both be None")
        if self.shadow is not None:
            shadow = as_array(self.shadow, "shadow", shape=(None, None), dtype=bool)
            dropped = as_array(self.dropped, "dropped", shape=shadow.shape, dtype=bool)
            object.__setattr__(self, "shadow", shadow)
            object.__setattr__(self, "dropped", dropped)
        for name in ("n_clusters", "n_small", "n_unsupported", "n_removed"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
                raise ValueError(f"{name} must be an integer >= 0, got {value!r}")
            object.__setattr__(self, name, int(value))

    def __repr__(self) -> str:
        return (
            f"Caster({len(self.vertices)} vertices, {len(self.triangles)} triangles, "
            f"clusters {self.n_clusters} (dropped {self.n_small} small, {self.n_unsupported} unsupported), "
            f"{self.n_removed} triangles removed)"
        )


# ---------------------------------------------------------------------------------------------
# argument checks
# ---------------------------------------------------------------------------------------------
def _check_config(config: object) -> RelightConfig:
    if config is None:
        return RelightConfig()
    if not isinstance(config, RelightConfig):
        raise TypeError(f"config must be a RelightConfig, got {describe(config)}")
    return config


def _check_camera(camera: object) -> Camera:
    if not isinstance(camera, Camera):
        raise TypeError(f"camera must be a Camera, got {describe(camera)}")
    return camera


def _check_tracer(tracer: object, name: str = "tracer") -> Tracer:
    if not isinstance(tracer, Tracer):
        raise TypeError(f"{name} must be a Tracer, got {describe(tracer)}")
    return tracer


def _check_sun(sun_direction: object, up: object) -> np.ndarray:
    """``sun_direction`` as a unit vector, refused when at or below the horizon of ``up``."""
    sun = as_unit_vector(sun_direction, "sun_direction")
    up = as_unit_vector(up, "up")
    if float(sun @ up) <= 0.0:
        elevation = np.degrees(np.arcsin(np.clip(sun @ up, -1.0, 1.0)))
        raise ValueError(
            f"sun_direction must be above the horizon (sun_direction . up > 0), got elevation "
            f"{elevation:.2f} degrees (sun_direction {np.round(sun, 4).tolist()}, up {up.tolist()})"
        )
    return sun


def _image_array(value: object, name: str, shape: tuple[int, ...] | None, dtype: type, *,
                 trailing: tuple[int, ...] = (), finite: bool = True) -> np.ndarray:
    """``value`` as a read-only array of ``shape + trailing`` (``shape`` None: any (H, W))."""
    expected = (*(shape if shape is not None else (None, None)), *trailing)
    return as_array(value, name, shape=expected, dtype=dtype, finite=finite)


def _to_scene(vertices: np.ndarray, triangles: np.ndarray):
    """An open3d RaycastingScene over a non-empty triangle mesh, its BVH built."""
    ensure_libusb()
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.ascontiguousarray(vertices, dtype=np.float32)),
        o3d.core.Tensor(np.ascontiguousarray(triangles, dtype=np.uint32)),
    )
    scene.test_occlusions(o3d.core.Tensor(np.zeros((1, 6), dtype=np.float32)))  # build the BVH now
    return scene


def _rays(origins: np.ndarray, direction: np.ndarray):
    import open3d as o3d

    rays = np.empty((len(origins), 6), dtype=np.float32)
    rays[:, :3] = origins
    rays[:, 3:] = direction
    return o3d.core.Tensor(rays)


# ---------------------------------------------------------------------------------------------
# receiver
# ---------------------------------------------------------------------------------------------
def receiver_depth(camera: Camera, tracer: Tracer) -> tuple[np.ndarray, np.ndarray]:
    """Distance to the proxy along every pixel ray, misses filled from the nearest hit (Sec. 8).

    Parameters
    ----------
    camera : Camera
        The view; rays through the pixel centres (:meth:`Camera.pixel_rays`).
    tracer : Tracer
        Ray caster over the proxy.

    Returns
    -------
    depth : (H, W) float64
        Distance, metres, from the camera centre along the unit pixel ray to the first proxy hit.
        A pixel whose ray misses the proxy takes the distance of the nearest (Euclidean, in
        pixels) pixel that hits.
    hit : (H, W) bool
        Where the pixel's own ray hits the proxy.

    Raises
    ------
    ValueError
        If no pixel ray hits the proxy.
    """
    camera = _check_camera(camera)
    tracer = _check_tracer(tracer)
    t = tracer.intersect(camera.center, camera.pixel_rays()).t.reshape(camera.shape)
    hit = np.isfinite(t)
    if not hit.any():
        raise ValueError(f"tracer: no pixel ray of camera {camera!r} hits the proxy")
    depth = t
    if not hit.all():
        rows, cols = ndimage.distance_transform_edt(~hit, return_distances=False, return_indices=True)
        depth = t[rows, cols]
    return depth, hit


def receiver_points(camera: Camera, depth: np.ndarray) -> np.ndarray:
    """World points of the pixels at the given ray distances.

    Parameters
    ----------
    camera : Camera
    depth : (H, W) array_like
        Finite distances, metres, along the unit pixel rays (:func:`receiver_depth`).

    Returns
    -------
    (H, W, 3) float64
        ``camera.center + depth * ray``, world frame, metres.
    """
    camera = _check_camera(camera)
    depth = _image_array(depth, "depth", camera.shape, np.float64)
    rays = camera.pixel_rays().reshape(*camera.shape, 3)
    return camera.center + depth[..., None] * rays


# ---------------------------------------------------------------------------------------------
# shadow pixels
# ---------------------------------------------------------------------------------------------
def shadow_pixels(labels: np.ndarray, v_sun: np.ndarray | None, *, tau_s: float = RelightConfig.tau_s) -> np.ndarray:
    """Pixels in shadow for the caster: labelled shadow, or ``v_sun < tau_s`` (Sec. 8).

    Parameters
    ----------
    labels : (H, W) uint8 array_like
        Step-3 shadow labels, codes of :data:`mvintrinsic.results.SHADOW_LABELS`.
    v_sun : (H, W) float array_like or None
        Sun visibility in [0, 1]; NaN (no estimate) never counts as shadow. ``None``: labels only.
    tau_s : float, optional
        Visibility threshold in [0, 1].

    Returns
    -------
    (H, W) bool
        ``(labels == shadow) | (v_sun < tau_s)``, and never where ``labels == undecided``.
    """
    labels = _image_array(labels, "labels", None, np.int64)
    codes = list(SHADOW_LABELS.values())
    bad = ~np.isin(labels, codes)
    if bad.any():
        raise ValueError(f"labels may only hold {codes}, got {np.unique(labels[bad])[:5].tolist()}")
    if not is_real(tau_s) or not 0.0 <= tau_s <= 1.0:
        raise ValueError(f"tau_s must be a number in [0, 1], got {tau_s!r}")
    shadow = labels == SHADOW_LABELS["shadow"]
    if v_sun is not None:
        v = _image_array(v_sun, "v_sun", labels.shape, np.float64, finite=False)
        with np.errstate(invalid="ignore"):
            shadow |= v < tau_s  # NaN < tau_s is False
    return shadow & (labels != SHADOW_LABELS["undecided"])


# ---------------------------------------------------------------------------------------------
# caster
# ---------------------------------------------------------------------------------------------
#: Neighbouring kept pixels share caster corners only when their receiver distances differ by at
#: most this fraction of the larger (a depth edge splits the caster). Chosen on the test scene
#: (module docstring): 0.02 splits oblique surfaces, 0.1 is no better than 0.05.
SURFACE_JUMP = 0.05

#: ... and when their caster distances differ by at most this fraction of the larger, or by at most
#: this many pixel footprints (metres per pixel at the receiver; the absolute term keeps caster
#: distances near 0, at the foot of an occluder, together). Chosen on the test scene.
CASTER_JUMP = (0.25, 8.0)

#: Corners of a pixel as offsets (column, row) from its centre, in the order of its quad.
_CORNERS = ((-0.5, -0.5), (0.5, -0.5), (0.5, 0.5), (-0.5, 0.5))


def _continuous(a_s, a_t, b_s, b_t, footprint):
    """Whether two kept pixels (receiver distances ``s``, caster distances ``t``) are one surface."""
    rel_t, px_t = CASTER_JUMP
    return (np.abs(a_s - b_s) <= SURFACE_JUMP * np.maximum(a_s, b_s)) & (
        np.abs(a_t - b_t) <= np.maximum(rel_t * np.maximum(a_t, b_t), px_t * footprint)
    )


def _gradients(values: np.ndarray, similar_x: np.ndarray, similar_y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Derivatives of ``values`` (H, W) along columns and rows, per pixel, within one surface.

    ``similar_x[i, j]`` says pixels ``(i, j)`` and ``(i, j + 1)`` are on one surface (shape
    (H, W - 1)), ``similar_y`` likewise for ``(i, j)`` and ``(i + 1, j)`` ((H - 1, W)). Central
    differences where both neighbours are similar, one-sided where one is, 0 where none is.
    """
    out = []
    for axis, similar in ((1, similar_x), (0, similar_y)):
        diff = np.diff(values, axis=axis)
        diff = np.where(similar, diff, 0.0)
        pad_before = [(0, 0), (0, 0)]
        pad_after = [(0, 0), (0, 0)]
        pad_before[axis] = (1, 0)
        pad_after[axis] = (0, 1)
        forward, backward = np.pad(diff, pad_after), np.pad(diff, pad_before)
        n_forward, n_backward = np.pad(similar, pad_after), np.pad(similar, pad_before)
        count = n_forward.astype(np.int64) + n_backward
        out.append((forward + backward) / np.maximum(count, 1))
    return out[0], out[1]


def _footprint_mesh(camera: Camera, kept: np.ndarray, s: np.ndarray, t: np.ndarray,
                    sun: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A quad over every kept pixel's footprint, lifted toward the sun (module docstring).

    ``s`` (H, W) are the receiver distances along the pixel rays, ``t`` (H, W) the caster
    distances (meaningful on ``kept``). A corner of a kept pixel lies on the camera ray through
    that pixel corner at distance ``s_c`` and is lifted by ``t_c`` along ``sun``, where ``s_c`` and
    ``t_c`` average, over the kept pixels touching the corner that are continuous with the pixel
    (:func:`_continuous`), each one's linear extrapolation to the corner (value plus gradient times
    the half-pixel offset). On a plane every touching pixel extrapolates to the same corner, so
    neighbouring quads share their corners (the sheet is closed) and the boundary corners of a
    shadow sit on the surface rather than half a pixel inward; across a jump in ``s`` or ``t`` the
    quads separate instead of stretching. Returns ``(4K, 3)`` float64 vertices (four per kept
    pixel, equal where shared) and ``(2K, 3)`` int32 triangles.
    """
    h, w = kept.shape
    footprint = s / min(camera.focal)  # metres per pixel at the receiver
    t = np.where(kept, t, 0.0)
    similar_x = kept[:, 1:] & kept[:, :-1] & _continuous(s[:, 1:], t[:, 1:], s[:, :-1], t[:, :-1], footprint[:, 1:])
    similar_y = kept[1:] & kept[:-1] & _continuous(s[1:], t[1:], s[:-1], t[:-1], footprint[1:])
    gs_x, gs_y = _gradients(s, similar_x, similar_y)
    gt_x, gt_y = _gradients(t, similar_x, similar_y)
    i, j = np.nonzero(kept)
    n = len(i)
    s_p, t_p, f_p = s[i, j], t[i, j], footprint[i, j]
    corner_s = np.empty((n, 4))
    corner_t = np.empty((n, 4))
    corner_row = np.empty((n, 4), dtype=np.int64)
    corner_col = np.empty((n, 4), dtype=np.int64)
    for k, (ox, oy) in enumerate(_CORNERS):
        # The corner at continuous pixel coordinates (j + 0.5 + ox, i + 0.5 + oy) is touched by the
        # 2x2 block of pixels whose centres are half a pixel from it; sum over the block in a fixed
        # order so that every pixel sharing the corner computes it bit for bit alike.
        total_s, total_t, count = np.zeros(n), np.zeros(n), np.zeros(n)
        for dy in (-0.5, 0.5):
            for dx in (-0.5, 0.5):
                qi, qj = i + round(oy + dy), j + round(ox + dx)  # the block pixel's centre is (dx, dy) off the corner
                inside = (qi >= 0) & (qi < h) & (qj >= 0) & (qj < w)
                ci, cj = np.clip(qi, 0, h - 1), np.clip(qj, 0, w - 1)
                ok = inside & kept[ci, cj] & _continuous(s_p, t_p, s[ci, cj], t[ci, cj], f_p)
                # Linear extrapolation from the block pixel's centre to the corner, (-dx, -dy) away.
                total_s += np.where(ok, s[ci, cj] - dx * gs_x[ci, cj] - dy * gs_y[ci, cj], 0.0)
                total_t += np.where(ok, t[ci, cj] - dx * gt_x[ci, cj] - dy * gt_y[ci, cj], 0.0)
                count += ok
        corner_s[:, k] = total_s / count  # the pixel itself is always in its own block
        corner_t[:, k] = total_t / count
        corner_row[:, k], corner_col[:, k] = i + round(oy + 0.5), j + round(ox + 0.5)
    # One ray per distinct pixel corner (corner (r, c) is at continuous pixel coordinates (c, r)).
    flat = corner_row * (w + 1) + corner_col
    distinct, inverse = np.unique(flat, return_inverse=True)
    uv = np.stack([distinct % (w + 1), distinct // (w + 1)], axis=1).astype(np.float64)
    rays = camera.pixel_rays(uv)[inverse.reshape(n, 4)]
    vertices = camera.center + corner_s[..., None] * rays + corner_t[..., None] * sun
    base = 4 * np.arange(n)[:, None]
    triangles = np.concatenate([base + [0, 1, 2], base + [0, 2, 3]])
    return vertices.reshape(-1, 3), triangles.astype(np.int32)


def build_caster(
    camera: Camera,
    shadow: np.ndarray,
    receiver: np.ndarray,
    sun_direction: np.ndarray,
    tracer: Tracer,
    *,
    lit: np.ndarray | None = None,
    up: np.ndarray = (0.0, 0.0, 1.0),
    config: RelightConfig | None = None,
    batch: int = DEFAULT_BATCH,
) -> Caster:
    """Build the shadow caster of one view from its shadow pixels (paper Sec. 8, Fig. 9).

    Steps (module docstring): sun rays from the shadow pixels' receiver points against the proxy;
    8-connected clusters dropped when smaller than ``config.min_cluster`` pixels or with a share
    of proxy hits below ``config.min_proxy_hits``; missed distances filled from the nearest kept
    pixel that hit; a quad of two triangles over every kept pixel's footprint, lifted toward the
    sun; triangles first hit by more than ``config.epsilon`` sun rays from lit pixels removed.

    Parameters
    ----------
    camera : Camera
        The view (its pixel rays place the footprint corners).
    shadow : (H, W) bool array_like
        Shadow pixels (:func:`shadow_pixels`).
    receiver : (H, W, 3) array_like
        Finite receiver points of every pixel, world frame, metres (:func:`receiver_points`).
    sun_direction : (3,) array_like
        Direction toward the sun at capture time, world frame (normalised here); above the
        horizon of ``up``.
    tracer : Tracer
        Ray caster over the proxy.
    lit : (H, W) bool array_like, optional
        Pixels in light whose sun rays vote against caster triangles. Default: ``~shadow``.
    up : (3,) array_like, optional
        World up vector.
    config : RelightConfig, optional
    batch : int, optional
        Rays per Embree call.

    Returns
    -------
    Caster
        Empty (no vertex, no triangle) when no cluster is kept.

    Raises
    ------
    ValueError
        If an array has the wrong shape, ``receiver`` is not finite or the sun is at or below the
        horizon (the message names ``sun_direction``).
    """
    camera = _check_camera(camera)
    tracer = _check_tracer(tracer)
    config = _check_config(config)
    sun = _check_sun(sun_direction, up)
    shape = camera.shape
    shadow = _image_array(shadow, "shadow", shape, bool)
    receiver = _image_array(receiver, "receiver", shape, np.float64, trailing=(3,))
    lit = ~shadow if lit is None else _image_array(lit, "lit", shape, bool)
    offset = config.ray_offset

    # Sun rays from the shadow pixels against the proxy: the occluder distance t_p.
    rows, cols = np.nonzero(shadow)
    hits = tracer.intersect(receiver[rows, cols], np.broadcast_to(sun, (len(rows), 3)), t_min=offset, batch=batch)
    t = np.full(shape, np.inf)
    t[rows, cols] = hits.t
    hit = np.isfinite(t)

    # 8-connected clusters; drop the small ones and those the proxy does not explain.
    clusters, n_clusters = ndimage.label(shadow, structure=_EIGHT)
    size = np.bincount(clusters.ravel(), minlength=n_clusters + 1)
    n_hits = np.bincount(clusters.ravel(), weights=hit.ravel(), minlength=n_clusters + 1)
    share = n_hits / np.maximum(size, 1)
    small = size < config.min_cluster
    unsupported = ~small & ((share < config.min_proxy_hits) | (n_hits == 0))
    keep = ~(small | unsupported)
    keep[0] = small[0] = unsupported[0] = False  # label 0 is the background
    kept = keep[clusters]
    dropped = shadow & ~kept
    primitives = np.unique(hits.triangle[kept[rows, cols] & hits.hit])

    if not kept.any():
        return Caster(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int32), primitives, kept, dropped,
                      n_clusters, int(small[1:].sum()), int(unsupported[1:].sum()), 0)

    # Missed rays take the distance of the nearest kept pixel whose ray hit.
    valid = kept & hit
    lift = t
    if not valid[kept].all():
        near_r, near_c = ndimage.distance_transform_edt(~valid, return_distances=False, return_indices=True)
        lift = np.where(valid, t, t[near_r, near_c])
    lift = np.where(kept, lift, 0.0)

    # Receiver distance from the camera centre (along the pixel ray for receiver_points' points).
    ray_distance = np.linalg.norm(receiver - camera.center, axis=-1)
    vertices, triangles = _footprint_mesh(camera, kept, ray_distance, lift, sun)

    # Triangles first hit by more than epsilon sun rays from lit pixels contradict the image.
    counts = np.zeros(len(triangles), dtype=np.int64)
    lit_points = receiver[lit]
    if len(lit_points):
        scene = _to_scene(vertices, triangles)
        for start in range(0, len(lit_points), batch):
            origins = lit_points[start:start + batch] + offset * sun
            ids = scene.cast_rays(_rays(origins, sun))["primitive_ids"].numpy()
            ids = ids[ids != _INVALID_ID].astype(np.int64)
            counts += np.bincount(ids, minlength=len(triangles))
    bad = counts > config.epsilon
    if bad.any():
        triangles = triangles[~bad]
        used, triangles = np.unique(triangles, return_inverse=True)
        vertices = vertices[used]
        triangles = triangles.reshape(-1, 3).astype(np.int32)
    return Caster(vertices, triangles, primitives, kept, dropped, n_clusters, int(small[1:].sum()),
                  int(unsupported[1:].sum()), int(bad.sum()))


def merge_casters(casters: Sequence[Caster]) -> Caster:
    """One caster for all views: the union of the meshes (paper Sec. 8).

    Parameters
    ----------
    casters : sequence of Caster
        Casters built against the same proxy (their ``proxy_primitives`` index it).

    Returns
    -------
    Caster
        Concatenated vertices and (re-indexed) triangles, the union of ``proxy_primitives``,
        summed counts; ``shadow`` and ``dropped`` are ``None`` (they belong to single views).
    """
    if isinstance(casters, Caster) or not isinstance(casters, Sequence):
        raise TypeError(f"casters must be a sequence of Caster, got {describe(casters)}")
    for i, caster in enumerate(casters):
        if not isinstance(caster, Caster):
            raise TypeError(f"casters[{i}] must be a Caster, got {describe(caster)}")
    if not casters:
        raise ValueError("casters must hold at least one Caster, got none")
    starts = np.cumsum([0] + [len(c.vertices) for c in casters[:-1]])
    vertices = np.concatenate([c.vertices for c in casters])
    triangles = np.concatenate([c.triangles.astype(np.int64) + s for c, s in zip(casters, starts, strict=True)])
    if len(vertices) > np.iinfo(np.int32).max:
        raise ValueError(f"casters: the merged mesh has {len(vertices)} vertices, more than int32 indices can hold")
    primitives = np.unique(np.concatenate([c.proxy_primitives for c in casters]))
    return Caster(vertices, triangles.astype(np.int32), primitives, None, None,
                  sum(c.n_clusters for c in casters), sum(c.n_small for c in casters),
                  sum(c.n_unsupported for c in casters), sum(c.n_removed for c in casters))


# ---------------------------------------------------------------------------------------------
# moving shadows
# ---------------------------------------------------------------------------------------------
class ShadowCaster:
    """Embree structure over a :class:`Caster`, built once and queried for many suns (Sec. 8).

    Parameters
    ----------
    caster : Caster
        The caster of one view or of all views (:func:`merge_casters`).
    """

    def __init__(self, caster: Caster) -> None:
        if not isinstance(caster, Caster):
            raise TypeError(f"caster must be a Caster, got {describe(caster)}")
        self.caster = caster
        self._scene = _to_scene(caster.vertices, caster.triangles) if len(caster.triangles) else None

    def occluded(self, origins: np.ndarray, sun_direction: np.ndarray, *, batch: int = DEFAULT_BATCH) -> np.ndarray:
        """Whether the caster blocks each ray ``origins + s d``, ``s > 0``; (N,) bool.

        Parameters
        ----------
        origins : (N, 3) array_like
            World-frame ray origins, metres (already offset off the receiver).
        sun_direction : (3,) array_like
            Unit direction toward the sun, world frame.
        """
        origins = as_array(origins, "origins", shape=(None, 3), dtype=np.float64)
        sun = as_unit_vector(sun_direction, "sun_direction")
        out = np.zeros(len(origins), dtype=bool)
        if self._scene is None:
            return out
        for start in range(0, len(origins), batch):
            sl = slice(start, start + batch)
            out[sl] = self._scene.test_occlusions(_rays(origins[sl], sun)).numpy().astype(bool)
        return out

    def sun_visibility(
        self,
        receiver_points: np.ndarray,
        normals: np.ndarray | None,
        sun_direction: np.ndarray,
        *,
        proxy_tracer: Tracer | None = None,
        up: np.ndarray = (0.0, 0.0, 1.0),
        config: RelightConfig | None = None,
        batch: int = DEFAULT_BATCH,
    ) -> np.ndarray:
        """The new shadow layer: sun visibility of every pixel for a new sun (paper Sec. 8).

        A ray from each receiver point (offset ``config.ray_offset`` toward the sun) is tested
        against the caster; with ``proxy_tracer``, a pixel whose first proxy hit is a primitive
        the caster does not stand for (:attr:`Caster.proxy_primitives`) is in the proxy's shadow
        ("We complete the missing shadow in these areas using the shadow of the proxy
        geometry"); with ``normals``, points facing away from the sun are in attached shadow.
        The binary visibility is then blurred with a Gaussian of ``config.blur`` pixels.

        Parameters
        ----------
        receiver_points : (H, W, 3) array_like
            Finite receiver points, world frame, metres (:func:`receiver_points`).
        normals : (H, W, 3) array_like or None
            Unit surface normals, world frame; NaN rows (no normal) skip the attached-shadow test.
            ``None``: no attached-shadow test.
        sun_direction : (3,) array_like
            Direction toward the new sun, world frame (normalised here); above the horizon.
        proxy_tracer : Tracer, optional
            Ray caster over the proxy the caster was built against, for the completion.
        up : (3,) array_like, optional
            World up vector.
        config : RelightConfig, optional
            ``ray_offset`` and ``blur`` are used.
        batch : int, optional
            Rays per Embree call.

        Returns
        -------
        (H, W) float32
            Sun visibility in [0, 1]: 1 lit, 0 in the new cast (or attached) shadow.

        Raises
        ------
        ValueError
            If the sun is at or below the horizon (the message names ``sun_direction``) or an
            array has the wrong shape.
        """
        config = _check_config(config)
        sun = _check_sun(sun_direction, up)
        points = _image_array(receiver_points, "receiver_points", None, np.float64, trailing=(3,))
        shape = points.shape[:2]
        flat = points.reshape(-1, 3)
        origins = flat + config.ray_offset * sun
        shade = self.occluded(origins, sun, batch=batch)
        if proxy_tracer is not None:
            proxy_tracer = _check_tracer(proxy_tracer, "proxy_tracer")
            hits = proxy_tracer.intersect(flat, np.broadcast_to(sun, flat.shape), t_min=config.ray_offset, batch=batch)
            uncovered = hits.hit & ~np.isin(hits.triangle, self.caster.proxy_primitives)
            shade |= uncovered
        if normals is not None:
            n = _image_array(normals, "normals", shape, np.float64, trailing=(3,), finite=False).reshape(-1, 3)
            with np.errstate(invalid="ignore"):
                shade |= (n @ sun) <= 0.0  # NaN <= 0 is False: no normal, no attached shadow
        visibility = (~shade).reshape(shape).astype(np.float32)
        if config.blur > 0:
            visibility = ndimage.gaussian_filter(visibility, sigma=config.blur, mode="nearest")
        return np.clip(visibility, 0.0, 1.0).astype(np.float32)

    def __repr__(self) -> str:
        return f"ShadowCaster({self.caster!r})"
