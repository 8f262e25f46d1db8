"""Simulated multi-view-stereo proxy of a synthetic ground-truth scene.

The paper's input geometry is an automatic multi-view-stereo (MVS) reconstruction, "quite high
overall with some residual noise for buildings, but often very approximate for structures such as
vegetation", with "difficulty reconstructing silhouettes and fine structures" (Duchêne et al.
2015, Sec. 3; Fig. 19 shows it becoming increasingly incomplete with fewer views). To test the
decomposition under those conditions, :func:`simulate_mvs_proxy` turns the exact mesh of a
synthetic scene into a proxy with the same kinds of defects, by rendering one depth map per camera,
degrading it the way MVS depth maps are degraded and fusing the maps with a truncated signed
distance function (TSDF), the usual way depth maps become a mesh (Curless and Levoy 1996).

Failure modes simulated (one :class:`ProxyConfig` knob each):

* **Depth noise** (``depth_noise``, ``noise_correlation``): photo-consistency matching localises
  depth to a fraction of the disparity, so the error grows with depth; modelled as multiplicative
  Gaussian noise on the z-depth, spatially correlated over a few pixels because stereo matches
  windows, not single pixels.
* **Holes** (``hole_rate``, ``hole_size``): textureless, specular or occluded patches get no
  depth; modelled as random blobs (a smoothed white-noise field, thresholded) removed from each
  depth map independently, so other views may fill them.
* **Foliage and thin structures** (``foliage_loss``, ``thin_loss``, ``clump_size``): leaves
  move, self-occlude and are sub-pixel, poles and fences are a few pixels wide; MVS loses most of
  them and keeps isolated clumps. The decision is made *per face and in world space* (a smooth
  random field over the face centroids, thresholded so that the requested fraction of the
  class's area is dropped), so every view loses the same leaves: dropping pixels per view would
  let the other views fill them in again.
* **Grazing angles** (``grazing_angle_deg``): matching windows are foreshortened beyond
  recognition when the surface is seen edge-on; such pixels are dropped.
* **Silhouettes** (``edge_erosion``): windows straddling a depth discontinuity mix foreground and
  background, so MVS erodes or fattens silhouettes; ground and solid pixels next to a
  discontinuity are dropped (foliage and thin structures are all silhouette; their loss is set
  by their own knobs).
* **Triangulation needs two views** (``min_views``): a surface seen by a single camera cannot be
  triangulated; TSDF voxels observed by fewer views are not meshed.
* **Resolution** (``voxel_size``, ``depth_scale``): MVS meshes are coarse; the TSDF voxel size
  sets the resolution and ``depth_scale`` the resolution of the depth maps.
* **Floating fragments** (``min_component_area``): MVS cleanup (and TSDF fusion of noisy depth)
  leaves small disconnected pieces; components smaller than this area are removed, as MVS
  pipelines do when they trim their meshes.

Depth maps are rendered for the *undistorted pinhole twin* of each camera (same ``K``, pose and
size, no distortion), as MVS does after undistorting the photos; the fusion then uses ``K``.

Fusion details, each there to keep simulation artefacts out of the proxy so that only the
failure modes above remain: the TSDF truncation follows the depth noise (``truncation=None``);
each depth map is resampled :data:`SUPERSAMPLE` times finer with inverse depth interpolated
between smooth neighbours, because open3d reads one depth pixel per voxel and pixels larger than
voxels otherwise leave terraces; the voxel grid is offset by :data:`GRID_OFFSET` voxels so that
planes at round coordinates do not fall on voxel centres; and vertices and triangles are put in
a canonical order, so a seed gives the same arrays whatever the thread scheduling.

The paper's input geometry [1]_; the fusion is Curless and Levoy's [2]_.

References
----------
.. [1] S. Duchêne, C. Riant, G. Chaurasia, J. Lopez-Moreno, P.-Y. Laffont, S. Popov, A. Bousseau
   and G. Drettakis, "Multi-View Intrinsic Images of Outdoors Scenes with an Application to
   Relighting", ACM Transactions on Graphics 34(5), 2015.
.. [2] B. Curless and M. Levoy, "A Volumetric Method for Building Complex Models from Range
   Images", SIGGRAPH 1996.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from .._validation import config_or_default, describe
from ..camera import Camera
from ..raytrace import triangle_scene
from ..scene import Proxy
from .types import LABELS

__all__ = ["ProxyConfig", "distance_to_mesh", "foliage_retention", "label_retention", "simulate_mvs_proxy"]

#: Relative error of the depth of a 4-neighbour predicted by a pixel's tangent plane above which
#: the two pixels straddle a depth discontinuity (silhouette).
EDGE_JUMP = 0.05
#: TSDF block side, in voxels (open3d VoxelBlockGrid ``block_resolution``).
BLOCK_RESOLUTION = 8
#: Initial capacity of the TSDF block hash map (open3d grows it when needed).
BLOCK_COUNT = 10_000
#: Offset of the TSDF grid, in voxels along each axis. Open3d puts voxel centres at integer
#: multiples of the voxel size; a plane through them (the z = 0 ground, a wall at x = 8 m) has a
#: TSDF of exactly zero there, so its sign, and the meshed surface, turn to noise. An offset that
#: is no simple fraction keeps planes at round coordinates between voxel layers.
GRID_OFFSET = 0.382
#: Smallest automatic TSDF truncation, voxels (enough for marching cubes on exact depth).
MIN_TRUNCATION = 3.0
#: Automatic truncation: this many standard deviations of the depth noise at the median depth.
TRUNCATION_SIGMAS = 3.0
#: Depth maps are resampled this many times finer before fusion (see ``_supersample``).
SUPERSAMPLE = 4
#: Number of random plane waves summed to draw the world-space dropout field.
FIELD_WAVES = 64


@dataclass(frozen=True)
class ProxyConfig:
    """Degradations applied to the exact mesh, with defaults that mimic multi-view stereo.

    Parameters
    ----------
    depth_noise : float
        Standard deviation of multiplicative Gaussian noise on the z-depth (0.01 = 1 %):
        stereo matching localises depth to a fraction of the disparity, so errors grow with depth.
    noise_correlation : float
        Standard deviation, depth-map pixels, of the Gaussian that smooths the white noise
        before it scales the depth (4; 0 makes it independent per pixel): stereo matches whole
        windows (COLMAP's PatchMatch default radius is 5 px), so neighbouring depths err
        together and surfaces come out wavy rather than crumpled.
    hole_rate : float
        Fraction in [0, 1) of each depth map's valid pixels removed as random blobs
        (0.07): textureless, specular and occluded patches get no depth.
    hole_size : float
        Standard deviation, depth-map pixels, of the Gaussian that smooths the white noise
        thresholded into holes (6): holes are blobs, not salt noise.
    foliage_loss : float
        Fraction in [0, 1] of the foliage area dropped (0.9): MVS loses most vegetation.
    thin_loss : float
        Fraction in [0, 1] of the thin-structure area (poles, fences, beams) dropped (0.9).
    clump_size : float
        Correlation length, metres, of the world-space random field that decides which foliage
        and thin faces survive (0.5): what remains of a tree is a few clumps, not scattered leaves.
    grazing_angle_deg : float
        Pixels whose ray meets the surface more than this many degrees from its normal are
        dropped (85): matching fails on strongly foreshortened surfaces. From eye height
        (1.6 m) the ground is kept to about 18 m. 90 disables it.
    edge_erosion : int
        Ground and solid pixels within this many pixels of a depth discontinuity (where neither
        neighbour's tangent plane predicts the other's depth to :data:`EDGE_JUMP`, or where one
        ray misses) are dropped (1): matching windows straddling a silhouette are unreliable.
        Foliage and thin pixels are spared (their loss is ``foliage_loss`` and ``thin_loss``):
        a leaf or a pole a few pixels wide is all silhouette.
    voxel_size : float
        TSDF voxel side, metres (0.04): sets the resolution of the proxy mesh.
    truncation : float or None
        TSDF truncation distance in voxels. None (default) picks
        ``max(MIN_TRUNCATION, TRUNCATION_SIGMAS * depth_noise * median depth / voxel_size)``:
        noisy samples average only within the band, so it must hold a few standard deviations
        of the depth noise (1 % is 16 cm at 16 m) or the fused surface crumples, while a wider
        band fattens edges (voxels behind one view's surface are another view's free space).
    min_views : int
        A voxel is meshed only if at least this many depth maps observed it (2): a point seen
        by one camera cannot be triangulated.
    min_component_area : float
        Connected components of the fused mesh with less area than this, square metres, are
        removed (0.05, a 22 cm square): MVS pipelines trim small floating fragments.
    n_views : int or None
        Number of cameras whose depth maps are fused, chosen evenly spaced in the given order
        (None: all of them): fewer photos, sparser reconstruction (paper Fig. 19).
    depth_scale : float
        Resolution of the simulated depth maps relative to the camera images (1.0): MVS often
        computes depth at a reduced resolution.
    max_depth : float
        Depths beyond this many metres are discarded (50): far surfaces are not reconstructed.
    """

    depth_noise: float = 0.01
    noise_correlation: float = 4.0
    hole_rate: float = 0.07
    hole_size: float = 6.0
    foliage_loss: float = 0.9
    thin_loss: float = 0.9
    clump_size: float = 0.5
    grazing_angle_deg: float = 85.0
    edge_erosion: int = 1
    voxel_size: float = 0.04
    truncation: float | None = None
    min_views: int = 2
    min_component_area: float = 0.05
    n_views: int | None = None
    depth_scale: float = 1.0
    max_depth: float = 50.0

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name in ("n_views", "truncation") and value is None:
                continue
            if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
                raise TypeError(f"{f.name} must be a number, got {describe(value)}")
            if not math.isfinite(value):
                raise ValueError(f"{f.name} must be finite, got {value!r}")
        checks = {
            "depth_noise": (self.depth_noise >= 0, "must be >= 0"),
            "hole_rate": (0 <= self.hole_rate < 1, "must be in [0, 1)"),
            "noise_correlation": (self.noise_correlation >= 0, "must be >= 0 (pixels)"),
            "hole_size": (self.hole_size > 0, "must be positive (pixels)"),
            "foliage_loss": (0 <= self.foliage_loss <= 1, "must be in [0, 1]"),
            "thin_loss": (0 <= self.thin_loss <= 1, "must be in [0, 1]"),
            "clump_size": (self.clump_size > 0, "must be positive"),
            "grazing_angle_deg": (0 < self.grazing_angle_deg <= 90, "must be in (0, 90] degrees"),
            "edge_erosion": (
                self.edge_erosion >= 0 and float(self.edge_erosion).is_integer(),
                "must be an integer >= 0",
            ),
            "voxel_size": (self.voxel_size > 0, "must be positive (metres)"),
            "truncation": (self.truncation is None or self.truncation >= 1, "must be None or at least 1 voxel"),
            "min_views": (self.min_views >= 1 and float(self.min_views).is_integer(), "must be an integer >= 1"),
            "min_component_area": (self.min_component_area >= 0, "must be >= 0 (square metres)"),
            "n_views": (
                self.n_views is None or (self.n_views >= 1 and float(self.n_views).is_integer()),
                "must be None or an integer >= 1",
            ),
            "depth_scale": (0 < self.depth_scale <= 4, "must be in (0, 4]"),
            "max_depth": (self.max_depth > 0, "must be positive (metres)"),
        }
        for name, (ok, message) in checks.items():
            if not ok:
                raise ValueError(f"{name} {message}, got {getattr(self, name)!r}")


# -- input checks -------------------------------------------------------------------------------


def _check_mesh(vertices: object, triangles: object) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) float64 vertices and (M, 3) int64 triangles, validated."""
    v = np.asarray(vertices)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) < 3:
        raise ValueError(f"vertices must have shape (N, 3) with N >= 3, got {describe(v)}")
    if v.dtype.kind not in "fiu":
        raise TypeError(f"vertices must be a float array, got {describe(v)}")
    v = v.astype(np.float64)
    if not np.isfinite(v).all():
        raise ValueError(f"vertices must be finite, got {int((~np.isfinite(v)).sum())} NaN/Inf values")
    t = np.asarray(triangles)
    if t.ndim != 2 or t.shape[1] != 3 or len(t) == 0:
        raise ValueError(f"triangles must have shape (M, 3) with M >= 1, got {describe(t)}")
    if t.dtype.kind not in "iu":
        raise TypeError(f"triangles must be an integer array, got {describe(t)}")
    t = t.astype(np.int64)
    if t.min() < 0 or t.max() >= len(v):
        raise ValueError(f"triangles index vertices outside [0, {len(v)}), got range [{t.min()}, {t.max()}]")
    return v, t


def _check_labels(face_labels: object, n_faces: int) -> np.ndarray:
    labels = np.asarray(face_labels)
    if labels.shape != (n_faces,):
        raise ValueError(f"face_labels must have shape ({n_faces},), one per triangle, got shape {labels.shape}")
    if labels.dtype.kind not in "iu":
        raise TypeError(f"face_labels must be an integer array (indices into {LABELS}), got {describe(labels)}")
    if labels.min() < 0 or labels.max() >= len(LABELS):
        raise ValueError(
            f"face_labels must be indices in [0, {len(LABELS)}) into {LABELS}, got range [{labels.min()}, {labels.max()}]"
        )
    return labels.astype(np.int64)


def _check_cameras(cameras: object) -> list[Camera]:
    if isinstance(cameras, Mapping):
        raise TypeError("cameras must be a sequence of Camera; for read_colmap's dict pass list(cameras.values())")
    if isinstance(cameras, Camera) or not isinstance(cameras, Sequence):
        raise TypeError(f"cameras must be a sequence of Camera, got {describe(cameras)}")
    cameras = list(cameras)
    if not cameras:
        raise ValueError("cameras must hold at least one Camera, got none")
    for i, camera in enumerate(cameras):
        if not isinstance(camera, Camera):
            raise TypeError(f"cameras[{i}] must be a Camera, got {describe(camera)}")
    return cameras




def _cast(scene, origin: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ray distance t (inf on a miss), primitive id (-1 on a miss) and unit face normals."""
    import open3d as o3d

    rays = np.empty((len(directions), 6), dtype=np.float32)
    rays[:, :3] = origin
    rays[:, 3:] = directions
    answer = scene.cast_rays(o3d.core.Tensor(rays))
    t = answer["t_hit"].numpy().astype(np.float64)
    prim = answer["primitive_ids"].numpy().astype(np.int64)
    hit = np.isfinite(t)
    prim[~hit] = -1
    normals = answer["primitive_normals"].numpy().astype(np.float64)
    return t, prim, normals


# -- degradations -------------------------------------------------------------------------------


def _pinhole_twin(camera: Camera, scale: float) -> Camera:
    """The undistorted pinhole camera with the same K and pose, resampled by ``scale``."""
    (fx, fy), (cx, cy) = camera.focal, camera.principal_point
    twin = Camera("PINHOLE", camera.width, camera.height, [fx, fy, cx, cy], camera.rotation, camera.translation)
    if scale != 1.0:
        twin = twin.scaled(max(1, round(camera.width * scale)), max(1, round(camera.height * scale)))
    return twin


def _surviving_faces(
    centroids: np.ndarray, areas: np.ndarray, labels: np.ndarray, config: ProxyConfig, rng: np.random.Generator
) -> np.ndarray:
    """(M,) bool: faces kept after foliage and thin-structure loss.

    For each lossy class a smooth Gaussian random field ``f`` of correlation length
    ``clump_size`` is drawn as a sum of random plane waves (random Fourier features of a Gaussian
    kernel), evaluated at the face centroids, and the faces with the lowest ``f`` are dropped
    until the requested fraction of the class's area is gone.
    """
    keep = np.ones(len(labels), dtype=bool)
    for name, loss in (("foliage", config.foliage_loss), ("thin", config.thin_loss)):
        # Draw the field even when unused so that one knob does not shift another's randomness.
        freqs = rng.normal(size=(FIELD_WAVES, 3)) / config.clump_size
        phases = rng.uniform(0.0, 2.0 * np.pi, FIELD_WAVES)
        idx = np.flatnonzero(labels == LABELS.index(name))
        if loss == 0 or len(idx) == 0:
            continue
        if loss == 1:
            keep[idx] = False
            continue
        field = np.cos(centroids[idx] @ freqs.T + phases).sum(axis=1)
        order = np.argsort(field, kind="stable")
        cumulative = np.cumsum(areas[idx][order])
        n_drop = int(np.searchsorted(cumulative, loss * cumulative[-1], side="left")) + 1
        keep[idx[order[:n_drop]]] = False
    return keep


def _discontinuities(t: np.ndarray, directions: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels next to a depth discontinuity or to a miss (both sides of it).

    ``t`` (H, W) is the ray distance (inf on a miss), ``directions`` and ``normals`` (H, W, 3)
    the unit rays and face normals. Neighbours ``p``, ``q`` are continuous when the plane of
    either one predicts the other's distance to :data:`EDGE_JUMP` (relative): the plane of ``p``
    meets ray ``q`` at ``t_p (n_p . d_p) / (n_p . d_q)``. Comparing raw depths instead would
    flag every surface seen at a grazing angle, whose depth changes fast from pixel to pixel.
    """
    finite = np.isfinite(t)
    tt = np.where(finite, t, 1.0)
    nn = np.where(finite[..., None], normals, 0.0)
    edge = np.zeros(t.shape, dtype=bool)
    for axis in (0, 1):
        p = (slice(None, -1), slice(None)) if axis == 0 else (slice(None), slice(None, -1))
        q = (slice(1, None), slice(None)) if axis == 0 else (slice(None), slice(1, None))

        def error(a, b):
            """Relative error of the distance of b predicted by the plane of a."""
            cos_a = np.einsum("...k,...k->...", nn[a], directions[a])
            cos_b = np.einsum("...k,...k->...", nn[a], directions[b])
            with np.errstate(divide="ignore", invalid="ignore"):
                predicted = tt[a] * cos_a / cos_b
            return np.where(np.isfinite(predicted), np.abs(tt[b] - predicted) / tt[b], np.inf)

        jump = finite[p] != finite[q]
        both = finite[p] & finite[q]
        jump |= both & (np.minimum(error(p, q), error(q, p)) > EDGE_JUMP)
        edge[p] |= jump
        edge[q] |= jump
    return edge


def _hole_mask(valid: np.ndarray, config: ProxyConfig, rng: np.random.Generator) -> np.ndarray:
    """(H, W) bool: random blobs covering ``hole_rate`` of the valid pixels."""
    noise = rng.standard_normal(valid.shape)
    if config.hole_rate == 0 or not valid.any():
        return np.zeros(valid.shape, dtype=bool)
    field = ndimage.gaussian_filter(noise, sigma=config.hole_size, mode="wrap")
    threshold = np.quantile(field[valid], 1.0 - config.hole_rate)
    return field > threshold


def _simulated_depth(
    scene,
    twin: Camera,
    keep_face: np.ndarray,
    lossy_face: np.ndarray,
    config: ProxyConfig,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray]:
    """Degraded z-depth map of one view and where it is smooth.

    ``keep_face`` (M,) bool says which faces survived the foliage and thin-structure loss,
    ``lossy_face`` (M,) bool which faces are foliage or thin. Returns the depth, (H, W) float32
    metres, 0 where there is none, and (H, W) bool, False next to a depth discontinuity.
    """
    directions = twin.pixel_rays()
    t, prim, normals = _cast(scene, twin.center, directions)
    h, w = twin.shape
    z = (t * (directions @ twin.forward)).reshape(h, w)  # ray distance -> camera-frame z
    # Grazing angle between ray and face normal (normals need not face the camera).
    cos_incidence = np.abs(np.einsum("ij,ij->i", normals, directions)).reshape(h, w)
    valid = np.isfinite(z) & (z <= config.max_depth)
    valid &= cos_incidence >= math.cos(math.radians(config.grazing_angle_deg)) - 1e-12
    face = np.maximum(prim, 0).reshape(h, w)
    valid &= keep_face[face]
    # Silhouette erosion spares foliage and thin pixels: a leaf or a pole is all silhouette at
    # this resolution, and their loss is already what foliage_loss and thin_loss set.
    edge = _discontinuities(t.reshape(h, w), directions.reshape(h, w, 3), normals.reshape(h, w, 3))
    if config.edge_erosion > 0:
        eroded = (
            ndimage.binary_dilation(edge, iterations=int(config.edge_erosion) - 1) if config.edge_erosion > 1 else edge
        )
        valid &= ~(eroded & ~lossy_face[face])
    # Draws happen in a fixed order and size, whatever the masks: one seed, one proxy.
    valid &= ~_hole_mask(valid, config, rng)
    noise = rng.standard_normal((h, w))
    if config.noise_correlation > 0:
        noise = ndimage.gaussian_filter(noise, sigma=config.noise_correlation, mode="wrap")
        noise /= max(float(noise.std()), 1e-12)  # unit variance: depth_noise stays the per-pixel sigma
    depth = np.where(valid, z * (1.0 + config.depth_noise * noise), 0.0)
    return np.maximum(depth, 0.0).astype(np.float32), ~edge


# -- fusion -------------------------------------------------------------------------------------


def _supersample(depth: np.ndarray, smooth: np.ndarray, factor: int) -> np.ndarray:
    """The depth map ``factor`` times finer, (H f, W f) float32 metres (0: no depth).

    Open3d's TSDF integration reads, for every voxel, the one depth pixel it projects into; when
    pixels are larger than voxels the fused surface comes out terraced, in steps one pixel wide.
    Resampling the map finer, with inverse depth interpolated bilinearly (exact for planes, whose
    1/z is affine in the image), makes that lookup an interpolation. Where one of the four source
    pixels has no depth or is next to a discontinuity (``smooth`` False), the nearest pixel is
    copied instead, so no surface is invented across silhouettes or holes.
    """
    if factor == 1:
        return depth

    def taps(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        centre = (np.arange(n * factor) + 0.5) / factor - 0.5  # fine pixel centres, source index units
        lower = np.floor(centre)
        frac = centre - lower
        i0 = np.clip(lower.astype(np.int64), 0, n - 1)
        return i0, np.minimum(i0 + 1, n - 1), frac

    h, w = depth.shape
    (j0, j1, fy), (i0, i1, fx) = taps(h), taps(w)
    usable = (depth > 0) & smooth
    inverse = np.where(depth > 0, 1.0 / np.where(depth > 0, depth, 1.0), 0.0)
    total = np.zeros((h * factor, w * factor))
    ok = np.ones((h * factor, w * factor), dtype=bool)
    for rows, cols, weight in (
        (j0, i0, np.outer(1 - fy, 1 - fx)),
        (j0, i1, np.outer(1 - fy, fx)),
        (j1, i0, np.outer(fy, 1 - fx)),
        (j1, i1, np.outer(fy, fx)),
    ):
        total += weight * inverse[np.ix_(rows, cols)]
        ok &= usable[np.ix_(rows, cols)]
    nearest = depth[np.ix_(np.arange(h * factor) // factor, np.arange(w * factor) // factor)]
    return np.where(ok, 1.0 / np.where(ok, total, 1.0), nearest).astype(np.float32)


def _fuse(
    depths: list[tuple[Camera, np.ndarray, np.ndarray]], config: ProxyConfig, progress_bar
) -> tuple[np.ndarray, ...]:
    """TSDF-fuse z-depth maps; returns mesh vertices, TSDF-gradient normals and triangles.

    The grid frame is the world shifted by ``GRID_OFFSET`` voxels: ``x_grid = x_world + shift``.
    """
    import open3d as o3d

    shift = np.full(3, GRID_OFFSET * config.voxel_size)
    truncation = config.truncation
    if truncation is None:
        measured = np.concatenate([depth[depth > 0] for _, depth, _ in depths])
        typical = float(np.median(measured)) if len(measured) else 0.0
        truncation = max(MIN_TRUNCATION, TRUNCATION_SIGMAS * config.depth_noise * typical / config.voxel_size)

    o3c = o3d.core
    device = o3c.Device("CPU:0")
    grid = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight"),
        attr_dtypes=(o3c.float32, o3c.float32),
        attr_channels=((1,), (1,)),
        voxel_size=float(config.voxel_size),
        block_resolution=BLOCK_RESOLUTION,
        block_count=BLOCK_COUNT,
        device=device,
    )
    for twin, depth, smooth in depths:
        if (depth > 0).any():
            fine = _supersample(depth, smooth, SUPERSAMPLE)
            image = o3d.t.geometry.Image(o3c.Tensor(fine[:, :, None]))
            # Continuous pixel coordinates scale with the image: K of the finer map.
            intrinsic = o3c.Tensor(np.diag([SUPERSAMPLE, SUPERSAMPLE, 1.0]) @ twin.K, o3c.float64)
            extrinsic = np.eye(4)
            # x_cam = R x_world + t = R x_grid + (t - R shift)
            extrinsic[:3, :3], extrinsic[:3, 3] = twin.rotation, twin.translation - twin.rotation @ shift
            extrinsic = o3c.Tensor(extrinsic, o3c.float64)
            # Allocate the blocks around every measured point. (The depth-image overload of
            # compute_unique_block_coordinates samples every 4th pixel only, which leaves
            # holes when pixels are larger than blocks.)
            rows, cols = np.nonzero(depth > 0)
            z = depth[rows, cols].astype(np.float64)
            (fx, fy), (cx, cy) = twin.focal, twin.principal_point
            cam = np.stack([(cols + 0.5 - cx) / fx * z, (rows + 0.5 - cy) / fy * z, z], axis=1)
            points = (cam - twin.translation) @ twin.rotation + shift  # R.T @ (x_cam - t), row-wise
            cloud = o3d.t.geometry.PointCloud(o3c.Tensor(points.astype(np.float32)))
            blocks = grid.compute_unique_block_coordinates(cloud, trunc_voxel_multiplier=float(truncation))
            grid.integrate(
                blocks,
                image,
                intrinsic,
                extrinsic,
                depth_scale=1.0,
                depth_max=float(config.max_depth),
                trunc_voxel_multiplier=float(truncation),
            )
        progress_bar.update(1)
    empty = np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    threshold = float(config.min_views) - 0.5  # weights count the maps that updated a voxel
    if grid.hashmap().size() == 0 or grid.attribute("weight").max().item() < threshold:
        return empty
    try:
        mesh = grid.extract_triangle_mesh(weight_threshold=threshold)
    except RuntimeError as exc:  # open3d 0.20 fails this way when no cube has a surface
        if "shape {0}" in str(exc):
            return empty
        raise
    if "positions" not in mesh.vertex or mesh.vertex.positions.shape[0] == 0 or "indices" not in mesh.triangle:
        return empty
    vertices = mesh.vertex.positions.numpy().astype(np.float64) - shift
    normals = mesh.vertex.normals.numpy().astype(np.float64)
    triangles = mesh.triangle.indices.numpy().astype(np.int64)
    return vertices, normals, triangles


def _clean_mesh(
    vertices: np.ndarray, gradient_normals: np.ndarray, triangles: np.ndarray, min_area: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Drop degenerate triangles and small components; area-weighted normals facing the cameras.

    The TSDF gradient points from inside (behind the observed surface) to the observed free
    space, i.e. toward the cameras that saw the surface; the triangle normals are flipped to
    agree with it.
    """
    a, b, c = (vertices[triangles[:, i]] for i in range(3))
    cross = np.cross(b - a, c - a)
    double_area = np.linalg.norm(cross, axis=1)
    good = double_area > 1e-12
    triangles, cross, double_area = triangles[good], cross[good], double_area[good]
    if len(triangles) == 0:
        return vertices[:0], vertices[:0], triangles
    # Connected components over the vertex graph of the triangles.
    n = len(vertices)
    rows = np.concatenate([triangles[:, 0], triangles[:, 1]])
    cols = np.concatenate([triangles[:, 1], triangles[:, 2]])
    graph = coo_matrix((np.ones(len(rows), dtype=np.int8), (rows, cols)), shape=(n, n))
    _, component = connected_components(graph, directed=False)
    face_component = component[triangles[:, 0]]
    area = np.bincount(face_component, weights=0.5 * double_area, minlength=component.max() + 1)
    kept = area[face_component] >= min_area
    triangles, cross = triangles[kept], cross[kept]
    # Keep the vertices the remaining triangles use, in a canonical order: marching cubes numbers
    # vertices in thread-completion order, so without sorting one seed could give permutations.
    used = np.unique(triangles)
    used = used[np.lexsort(vertices[used].T[::-1])]
    remap = np.full(n, -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    triangles = remap[triangles]
    vertices, gradient_normals = vertices[used], gradient_normals[used]
    # Triangles: smallest index first (a rotation keeps the winding), then sorted.
    first = np.argmin(triangles, axis=1)
    triangles = np.take_along_axis(triangles, (first[:, None] + np.arange(3)) % 3, axis=1)
    order = np.lexsort(triangles.T[::-1])
    triangles, cross = triangles[order], cross[order]
    # Area-weighted vertex normals (|cross| is twice the triangle's area).
    corners = triangles.reshape(-1)
    normals = np.stack(
        [np.bincount(corners, weights=np.repeat(cross[:, k], 3), minlength=len(vertices)) for k in range(3)], axis=1
    )
    length = np.linalg.norm(normals, axis=1)
    grad_length = np.linalg.norm(gradient_normals, axis=1)
    normals = np.where(length[:, None] > 0, normals / np.maximum(length, 1e-300)[:, None], 0.0)
    gradient = np.where(grad_length[:, None] > 0, gradient_normals / np.maximum(grad_length, 1e-300)[:, None], 0.0)
    # Wind the triangles like the TSDF gradient (marching cubes is consistent, so one global test).
    if np.einsum("ij,ij->", normals, gradient) < 0:
        triangles = triangles[:, [0, 2, 1]]  # reversed winding, smallest index still first
        normals = -normals
    flip = np.einsum("ij,ij->i", normals, gradient) < 0
    normals[flip] *= -1.0
    missing = length == 0
    normals[missing] = gradient[missing]
    still = np.linalg.norm(normals, axis=1) == 0
    normals[still] = (0.0, 0.0, 1.0)  # isolated sliver vertex with no usable direction
    return vertices, normals, triangles


# -- public API ---------------------------------------------------------------------------------


def simulate_mvs_proxy(
    vertices: np.ndarray,
    triangles: np.ndarray,
    face_labels: np.ndarray,
    cameras: Sequence[Camera],
    *,
    config: ProxyConfig | None = None,
    rng: np.random.Generator | int | None = None,
    progress: bool = False,
) -> Proxy:
    """Reconstruct an imperfect, MVS-like proxy mesh from an exact mesh and cameras.

    Per camera, the pixel-centre rays of its undistorted pinhole twin (scaled by
    ``config.depth_scale``) are cast against the exact mesh; the z-depth map is degraded (faces
    of lost foliage and thin structures, grazing angles, silhouettes, random holes, then
    multiplicative noise; see the module docstring) and fused into a TSDF
    (open3d ``VoxelBlockGrid``); the zero level set is meshed by marching cubes, voxels seen by
    fewer than ``config.min_views`` maps and components smaller than
    ``config.min_component_area`` are dropped, and vertex normals are oriented toward the
    cameras that observed the surface.

    Parameters
    ----------
    vertices : (N, 3) float64
        Exact mesh vertices, world frame, metres.
    triangles : (M, 3) int
        Vertex indices of the exact mesh.
    face_labels : (M,) int
        Geometry class of each triangle, an index into :data:`~mvintrinsic.synth.types.LABELS`
        (``ground``, ``solid``, ``foliage``, ``thin``).
    cameras : sequence of Camera
        Posed cameras (any COLMAP model, see ``docs/conventions.md``); ``config.n_views`` of
        them, evenly spaced in this order, are used.
    config : ProxyConfig, optional
        Degradations and fusion parameters; ``ProxyConfig()`` by default.
    rng : numpy.random.Generator or int or None, optional
        Source of randomness; the same seed gives the same proxy.
    progress : bool, optional
        Show a progress bar over the views (tqdm).

    Returns
    -------
    Proxy
        Triangle mesh: ``vertices`` (P, 3) float64 metres, unit ``normals`` (P, 3) facing the
        cameras, ``triangles`` (Q, 3) int64.

    Raises
    ------
    ValueError
        If an argument has the wrong shape or range (naming it), or if nothing could be
        reconstructed (every depth was dropped or fewer than ``min_views`` views overlap).
    TypeError
        If an argument has the wrong type.
    """
    from tqdm import tqdm

    vertices, triangles = _check_mesh(vertices, triangles)
    labels = _check_labels(face_labels, len(triangles))
    cameras = _check_cameras(cameras)
    config = config_or_default(config, ProxyConfig)
    if isinstance(rng, bool) or not (rng is None or isinstance(rng, (int, np.integer, np.random.Generator))):
        raise TypeError(f"rng must be a numpy Generator, an int seed or None, got {describe(rng)}")
    rng = np.random.default_rng(rng)

    if config.n_views is not None and config.n_views < len(cameras):
        chosen = np.unique(np.round(np.linspace(0, len(cameras) - 1, int(config.n_views))).astype(int))
        cameras = [cameras[i] for i in chosen]

    a, b, c = (vertices[triangles[:, i]] for i in range(3))
    areas = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    keep_face = _surviving_faces((a + b + c) / 3.0, areas, labels, config, rng)
    lossy_face = np.isin(labels, [LABELS.index("foliage"), LABELS.index("thin")])
    scene = triangle_scene(vertices, triangles)

    with tqdm(total=2 * len(cameras), desc="MVS proxy", unit="view", disable=not progress) as bar:
        depths = []
        for camera in cameras:
            twin = _pinhole_twin(camera, config.depth_scale)
            depths.append((twin, *_simulated_depth(scene, twin, keep_face, lossy_face, config, rng)))
            bar.update(1)
        fused = _fuse(depths, config, bar)
    out_vertices, out_normals, out_triangles = _clean_mesh(*fused, config.min_component_area)
    if len(out_triangles) == 0:
        raise ValueError(
            "cameras: nothing was reconstructed; no surface is seen by "
            f"{config.min_views} or more of the {len(cameras)} depth maps after the degradations"
        )
    return Proxy(out_vertices, out_normals, out_triangles)


def distance_to_mesh(points: np.ndarray, vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Unsigned distance from points to a triangle mesh.

    Parameters
    ----------
    points : (P, 3) array_like
        Query points, world frame, metres.
    vertices : (N, 3) array_like
        Mesh vertices, metres.
    triangles : (M, 3) int
        Vertex indices.

    Returns
    -------
    (P,) float64
        Distance to the closest point of the mesh, metres (computed in float32 by Embree's
        closest-point query through open3d, so accurate to about 1e-7 of the scene's extent).
    """
    vertices, triangles = _check_mesh(vertices, triangles)
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (P, 3), got {describe(points)}")
    if len(points) == 0:
        return np.zeros(0)
    import open3d as o3d

    scene = triangle_scene(vertices, triangles)
    query = o3d.core.Tensor(np.ascontiguousarray(points, dtype=np.float32))
    return scene.compute_distance(query).numpy().astype(np.float64)


def _retained(proxy: Proxy, points: np.ndarray, radius: float) -> np.ndarray:
    """(P,) bool: whether the proxy surface (its vertices for a point cloud) is within radius."""
    if len(points) == 0:
        return np.zeros(0, dtype=bool)
    if proxy.is_mesh:
        return distance_to_mesh(points, proxy.vertices, proxy.triangles) <= radius
    return np.isfinite(cKDTree(proxy.vertices).query(points, k=1, distance_upper_bound=radius)[0])


def foliage_retention(
    proxy: Proxy,
    vertices: np.ndarray,
    triangles: np.ndarray,
    face_labels: np.ndarray,
    *,
    radius: float = 0.1,
    n_samples: int = 20_000,
    rng: np.random.Generator | int | None = 0,
) -> float:
    """Fraction of the ground-truth foliage surface that the proxy retains.

    ``n_samples`` points are drawn uniformly over the area of the faces labelled ``"foliage"``;
    a point counts as retained when the proxy surface (its triangles; its vertices for a point
    cloud) passes within ``radius`` of it. Foliage no camera saw counts as lost, so this is a
    lower bound of what MVS kept of the foliage the photos show; :func:`label_retention`
    measures that, per class, from the cameras.

    Parameters
    ----------
    proxy : Proxy
        The reconstructed geometry, mesh or point cloud.
    vertices : (N, 3) array_like
        Exact mesh vertices, world frame, metres.
    triangles : (M, 3) int
        Exact mesh triangles.
    face_labels : (M,) int
        Class of each exact triangle, indices into :data:`~mvintrinsic.synth.types.LABELS`.
    radius : float, optional
        Distance, metres, within which the proxy retains a sample.
    n_samples : int, optional
        Number of points sampled on the foliage.
    rng : numpy.random.Generator or int or None, optional
        Source of the sample positions (seeded by default, so the figure is reproducible).

    Returns
    -------
    float
        Retained fraction in [0, 1]; NaN when the mesh has no foliage.
    """
    if not isinstance(proxy, Proxy):
        raise TypeError(f"proxy must be a Proxy, got {describe(proxy)}")
    vertices, triangles = _check_mesh(vertices, triangles)
    labels = _check_labels(face_labels, len(triangles))
    if not radius > 0:
        raise ValueError(f"radius must be positive (metres), got {radius!r}")
    if isinstance(n_samples, bool) or not isinstance(n_samples, (int, np.integer)) or n_samples < 1:
        raise ValueError(f"n_samples must be an integer >= 1, got {describe(n_samples)}")
    rng = np.random.default_rng(rng)
    foliage = triangles[labels == LABELS.index("foliage")]
    a, b, c = (vertices[foliage[:, i]] for i in range(3))
    areas = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    if len(foliage) == 0 or areas.sum() <= 0:
        return float("nan")
    face = rng.choice(len(foliage), size=int(n_samples), p=areas / areas.sum())
    # Uniform barycentrics: (1 - sqrt(u), sqrt(u) (1 - v), sqrt(u) v).
    su, v = np.sqrt(rng.uniform(size=n_samples)), rng.uniform(size=n_samples)
    points = (1.0 - su)[:, None] * a[face] + (su * (1.0 - v))[:, None] * b[face] + (su * v)[:, None] * c[face]
    return float(_retained(proxy, points, radius).mean())


def label_retention(
    proxy: Proxy,
    vertices: np.ndarray,
    triangles: np.ndarray,
    face_labels: np.ndarray,
    cameras: Sequence[Camera],
    *,
    radius: float = 0.1,
    stride: int = 2,
    max_depth: float | None = None,
) -> dict[str, float]:
    """Fraction of the ground-truth surface of each class that the proxy retains.

    The ground-truth surface is sampled where the photos see it: the rays through every
    ``stride``-th pixel centre of every camera are cast against the exact mesh; a sample counts
    as retained when the proxy surface (its triangles; its vertices for a point cloud) passes
    within ``radius`` of it. This weighs surfaces by how many pixels show them, which is what the
    decomposition cares about, and ignores surfaces no camera sees (the back of a wall, the
    far ground).

    Parameters
    ----------
    proxy : Proxy
        The reconstructed geometry, mesh or point cloud.
    vertices : (N, 3) array_like
        Exact mesh vertices, metres.
    triangles : (M, 3) int
        Exact mesh triangles.
    face_labels : (M,) int
        Class of each exact triangle, indices into :data:`~mvintrinsic.synth.types.LABELS`.
    cameras : sequence of Camera
        Cameras whose pixels sample the surface.
    radius : float, optional
        Distance, metres, within which the proxy retains a sample.
    stride : int, optional
        Sample every ``stride``-th pixel in each image direction.
    max_depth : float, optional
        Ignore samples farther than this (metres) from the camera along the ray; all by default.

    Returns
    -------
    dict of str to float
        For every name in ``LABELS``: the retained fraction in [0, 1], NaN when no sampled pixel
        sees that class.

    Examples
    --------
    ``label_retention(proxy, v, t, labels, cams)["foliage"] < 0.5`` says that most foliage
    seen in the photos was lost.
    """
    if not isinstance(proxy, Proxy):
        raise TypeError(f"proxy must be a Proxy, got {describe(proxy)}")
    vertices, triangles = _check_mesh(vertices, triangles)
    labels = _check_labels(face_labels, len(triangles))
    cameras = _check_cameras(cameras)
    if not radius > 0:
        raise ValueError(f"radius must be positive (metres), got {radius!r}")
    if isinstance(stride, bool) or not isinstance(stride, (int, np.integer)) or stride < 1:
        raise ValueError(f"stride must be an integer >= 1, got {describe(stride)}")
    if max_depth is not None and not max_depth > 0:
        raise ValueError(f"max_depth must be positive (metres) or None, got {max_depth!r}")

    scene = triangle_scene(vertices, triangles)
    points, point_labels = [], []
    for camera in cameras:
        pixels = camera.pixel_centers()[::stride, ::stride].reshape(-1, 2)
        directions = camera.pixel_rays(pixels)
        t, prim, _ = _cast(scene, camera.center, directions)
        ok = prim >= 0
        if max_depth is not None:
            ok &= t <= max_depth
        points.append(camera.center + t[ok, None] * directions[ok])
        point_labels.append(labels[prim[ok]])
    points, point_labels = np.concatenate(points), np.concatenate(point_labels)
    retained = _retained(proxy, points, radius)
    out = {}
    for i, name in enumerate(LABELS):
        mine = point_labels == i
        out[name] = float(retained[mine].mean()) if mine.any() else float("nan")
    return out
