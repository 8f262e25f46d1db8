"""Over-segmentation of a view into small regions of uniform colour (paper Sec. 6.1).

Step 3 labels shadows on a graph of *clusters* rather than pixels: "we apply mean-shift clustering
[Comaniciu and Meer 2002] in (L,a,b,x,y) space to segment the image into small regions where we can
safely assume uniform reflectance and visibility [...] We use bandwidth parameters of 5 in space and
1 in color and a minimum region area of 50 pixels, which results in around 6000 clusters for an
image of size 1000x700 pixels." This module gives that segmentation, and a faster superpixel method
(SLIC) behind the same interface.

Colour space
------------
The input is linear, scene-referred RGB (``docs/conventions.md``; HDR, values may exceed 1). It is
made perceptual first: divided by the ``white_percentile`` (99.9th by default) percentile of the
Rec. 709 luminance of the valid pixels, clipped to [0, 1] (negative values to 0), sRGB-encoded (IEC
61966-2-1) and converted to CIELAB (D65, OpenCV ``COLOR_RGB2Lab`` on float input: ``L*`` in
[0, 100]). Colour distances and ``color_bandwidth`` are therefore in CIE76 ``Delta E*ab`` units.

Mean shift (``method="mean_shift"``)
------------------------------------
The steps of Comaniciu and Meer's segmentation [1]_ (Sec. 5 there), as EDISON implements them:

1. *Filtering* (mode seeking): OpenCV's ``pyrMeanShiftFiltering`` moves every pixel's joint
   (x, y, L, a, b) point uphill with a flat kernel, a ``(2 h_s + 1)^2`` spatial window and a colour
   ball of radius ``h_r``, until it moves by less than 1 or after ``max_iterations`` steps
   (``maxLevel=0``: no pyramid), and gives each pixel the colour of its mode. OpenCV needs 8-bit
   channels, so CIELAB is quantised with one scale ``k`` for all three channels (distances stay
   Euclidean in ``Delta E``): ``k = min(2.55, 255 / largest channel range of the image)`` codes per
   ``Delta E`` (2.55 is OpenCV's own ``L*`` scale; about 2.5 on the courtyard views, i.e. a
   quantisation step of 0.4 ``Delta E``), and OpenCV gets ``sp = h_s``, ``sr = k * h_r``.
2. *Delineation*: 4-connected pixels whose filtered colours lie within ``fusion_tolerance * h_r``
   of each other belong to one region (EDISON, the reference implementation of [1]_, joins modes
   closer than ``h_r / 2``: the default 0.5). Modes of one basin of attraction differ by the
   filter's stopping tolerance, so exact equality would not do.
3. *Pruning*: every region smaller than ``min_region`` pixels joins the touching region of closest
   mean filtered colour, all at once (each picks its nearest neighbour and the picks are joined by
   connected components, as EDISON's ``Prune`` does with union-find), repeated until no small
   region is left. Every segment is 4-connected. A connected component of valid pixels smaller
   than ``min_region`` (an island in the mask) has no neighbour to join and stays a small segment.

Colour bandwidth: the paper's "1" and ours
------------------------------------------
The paper gives no unit for "1 in color". Read in EDISON's units (CIE L*u*v*, ``L*`` in [0, 100],
the same scale as CIELAB), ``h_r = 1 Delta E`` is below the pixel noise of the views (the median
``Delta E`` between horizontal neighbours is 3.8 on the courtyard view 0; the filter then moves the
median pixel by 0.25 ``Delta E``, less than the quantisation), so the regions come from the pruning
alone. Measured on the courtyard view 0 cut to 1000x700 (rows 25-724), 5 px and 50 px fixed:

============  ========  ===================  ==================  ========================
``h_r``       segments  mean non-sky area    visibility error    reflectance deviation
============  ========  ===================  ==================  ========================
1             4443      114 px               0.0342              0.107
2             4362      116 px               0.0341              0.107
**3**         **4226**  **120 px**           **0.0329**          **0.108**
4             3983      127 px               0.0332              0.111
6             1484      342 px               0.0335              0.135
8             655       776 px               0.0475              0.175
============  ========  ===================  ==================  ========================

(visibility error: fraction of non-sky pixels whose true sun visibility disagrees with their
segment's majority, the floor of any cluster-level shadow labelling; reflectance deviation: mean
``|R - segment mean|_1 / |segment mean|_1`` of the true reflectance; ``bench_segmentation.py``.)
The count sits on a plateau for ``h_r`` from 1 to 4 ``Delta E`` and collapses above, where whole
walls become one segment; the visibility error barely moves up to 6 (it does at 8). We default to
``h_r = 3 Delta E``: on the plateau, and large enough for the filter to do work (it brings the
median neighbour difference from 3.8 to 2.6 ``Delta E``); ``color_bandwidth=1.0`` is the literal
reading (same purity, 5% more segments). The paper's "around 6000 clusters for 1000x700" is a mean
of 117 px per cluster; ours is 120 px per cluster on the non-sky pixels, and the sky (28% of the
crop) is one to a few segments, hence about 4200 segments in all rather than 6000.

Measured (``python benchmarks/bench_segmentation.py --out benchmarks/results/segmentation.json``,
2 cores shared with other jobs, load average 3.3): on the six 1000x750 courtyard views the mean
shift gives 4377-4448 segments (mean 4410) in 1.07 s per view (1.01-1.33 s; an earlier run at load
4.2 took 1.63 s; the filtering and delineation take about two thirds, the pruning the rest), and
4226 segments on the 1000x700 crop (3975 on the view resized to 1000x700).

SLIC (``method="slic"``)
------------------------
:func:`skimage.segmentation.slic` [2]_ (k-means in (L, a, b, x, y) from a regular grid of seeds) on
the same CIELAB image, with ``n_segments = valid pixels / slic_mean_area``, ``slic_compactness`` in
``Delta E`` per grid step (10, SLIC's usual CIELAB value) and ``slic_iterations``, split into
4-connected pieces and pruned like the mean shift. It spends as many superpixels on the sky as
anywhere: with ``slic_mean_area = 100`` px it gives 6307-6363 segments per 1000x750 view (mean
6337) but 4251 on non-sky pixels, as many as the mean shift, in 0.89 s per view (0.66-1.08 s; 5901
segments on the 1000x700 crop, 6168 resized). skimage's k-means alone takes about 0.7 s, so SLIC is
only about 20% faster than the mean shift here. Its segments straddle true shadow boundaries more
often (visibility error 0.048 against 0.028 for the mean shift, mean of the six views; reflectance
deviation 0.135 against 0.106).

Both methods are deterministic: no randomness is involved.

The segmentation feeds the paper's shadow labelling [3]_.

References
----------
.. [1] D. Comaniciu and P. Meer, "Mean shift: a robust approach toward feature space analysis",
   IEEE TPAMI 24(5), 603-619, 2002.
.. [2] R. Achanta et al., "SLIC superpixels compared to state-of-the-art superpixel methods",
   IEEE TPAMI 34(11), 2274-2282, 2012.
.. [3] S. Duchene et al., "Multi-view intrinsic images of outdoors scenes with an application to
   relighting", ACM TOG 34(5), 2015, Sec. 6.1.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import cv2
import numpy as np
from scipy import ndimage, sparse
from scipy.sparse import csgraph

from ._validation import as_array, config_or_default, describe, is_real
from .image_model import LUMINANCE_WEIGHTS

__all__ = [
    "SEGMENTATION_METHODS",
    "Segmentation",
    "SegmentationConfig",
    "boundary_band",
    "boundary_mask",
    "merge_small_regions",
    "perceptual_lab",
    "region_adjacency",
    "segment",
]

#: Valid values of :attr:`SegmentationConfig.method`.
SEGMENTATION_METHODS = ("mean_shift", "slic")

#: :data:`~mvintrinsic.image_model.LUMINANCE_WEIGHTS` in the float32 of the images.
_LUMINANCE_WEIGHTS = LUMINANCE_WEIGHTS.astype(np.float32)

#: Largest 8-bit codes per CIELAB unit given to OpenCV's mean-shift filter (OpenCV's own L* scale).
MAX_CODES_PER_DELTA_E = 2.55


@dataclass(frozen=True)
class SegmentationConfig:
    """Options of the over-segmentation (paper Sec. 6.1); defaults are the paper's where it gives one.

    Parameters
    ----------
    method : {"mean_shift", "slic"}
        Mean-shift clustering in (L, a, b, x, y) (the paper) or SLIC superpixels (faster).
    spatial_bandwidth : int
        Mean-shift spatial bandwidth ``h_s``, pixels (paper: 5): the filter window is
        ``(2 h_s + 1)^2`` pixels.
    color_bandwidth : float
        Mean-shift range bandwidth ``h_r``, CIE76 ``Delta E*ab`` of the perceptual image (paper:
        "1", in unstated units). 3 lies on the plateau (1 to 4) where the count matches the paper's
        cluster density and gives the purest segments on the courtyard; see the module docstring
        for the measurement and the scaling to OpenCV's 8-bit channels.
    min_region : int
        Smallest segment area, pixels (paper: 50); smaller regions are merged into their most
        similar neighbour. Both methods.
    fusion_tolerance : float
        Neighbouring pixels whose filtered colours differ by less than
        ``fusion_tolerance * color_bandwidth`` form one region (mean shift; in (0, 2]; EDISON: 0.5).
    max_iterations : int
        Largest number of mean-shift steps per pixel (OpenCV's default: 5).
    white_percentile : float
        Percentile of the valid pixels' luminance mapped to white before sRGB encoding, in
        (0, 100]; brighter pixels are clipped.
    slic_mean_area : float
        Mean SLIC superpixel area, pixels: ``n_segments = valid pixels / slic_mean_area``. 100 gives
        as many non-sky segments as the mean shift on the courtyard views.
    slic_compactness : float
        SLIC's weight of space against colour: a spatial distance of one grid step counts as
        ``slic_compactness`` ``Delta E``; higher gives squarer superpixels.
    slic_iterations : int
        SLIC's number of k-means iterations.
    """

    method: str = "mean_shift"
    spatial_bandwidth: int = 5
    color_bandwidth: float = 3.0
    min_region: int = 50
    fusion_tolerance: float = 0.5
    max_iterations: int = 5
    white_percentile: float = 99.9
    slic_mean_area: float = 100.0
    slic_compactness: float = 10.0
    slic_iterations: int = 10

    def __post_init__(self) -> None:
        if self.method not in SEGMENTATION_METHODS:
            raise ValueError(f"method must be one of {list(SEGMENTATION_METHODS)}, got {self.method!r}")
        for name, least in (("spatial_bandwidth", 1), ("min_region", 1), ("max_iterations", 1),
                            ("slic_iterations", 1)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
                raise ValueError(f"{name} must be an integer >= {least}, got {value!r}")
        for name in ("color_bandwidth", "slic_compactness"):
            value = getattr(self, name)
            if not is_real(value) or not 0 < value < np.inf:
                raise ValueError(f"{name} must be a positive finite number, got {value!r}")
        if not is_real(self.slic_mean_area) or not 1 <= self.slic_mean_area < np.inf:
            raise ValueError(f"slic_mean_area must be a finite number >= 1 pixel, got {self.slic_mean_area!r}")
        if not is_real(self.fusion_tolerance) or not 0 < self.fusion_tolerance <= 2:
            raise ValueError(f"fusion_tolerance must lie in (0, 2], got {self.fusion_tolerance!r}")
        if not is_real(self.white_percentile) or not 0 < self.white_percentile <= 100:
            raise ValueError(f"white_percentile must lie in (0, 100], got {self.white_percentile!r}")


@dataclass(frozen=True, eq=False)
class Segmentation:
    """A partition of a view's valid pixels into segments.

    Parameters
    ----------
    labels : (H, W) int32
        Segment of each pixel, ``0 .. n_segments - 1`` (numbered in raster order of first
        appearance); ``-1`` on invalid pixels. Read-only.
    n_segments : int
        Number of segments.
    method : str
        The method that produced it (one of :data:`SEGMENTATION_METHODS`).

    Notes
    -----
    Neighbourhoods are 4-connected throughout (:attr:`adjacency`, :attr:`boundaries`); segments
    produced by :func:`segment` are 4-connected.
    """

    labels: np.ndarray
    n_segments: int
    method: str

    def __post_init__(self) -> None:
        labels = self.labels
        if not isinstance(labels, np.ndarray) or labels.ndim != 2 or labels.dtype != np.int32:
            raise TypeError(f"labels must be an (H, W) int32 array, got {describe(labels)}")
        n = self.n_segments
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
            raise ValueError(f"n_segments must be an integer >= 0, got {n!r}")
        if labels.size and (labels.min() < -1 or labels.max() >= n):
            raise ValueError(f"labels must lie in [-1, {n - 1}], got [{labels.min()}, {labels.max()}]")
        if n and not np.bincount(labels[labels >= 0], minlength=n).all():
            raise ValueError(f"labels must use every segment 0 .. {n - 1}; some are empty")
        if labels.flags.writeable:  # keep a private, read-only copy: the caller's array is not frozen
            labels = labels.copy()
            labels.flags.writeable = False
            object.__setattr__(self, "labels", labels)
        object.__setattr__(self, "n_segments", int(n))

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)``."""
        return self.labels.shape

    @property
    def valid(self) -> np.ndarray:
        """(H, W) bool: pixels that belong to a segment."""
        return self.labels >= 0

    @cached_property
    def sizes(self) -> np.ndarray:
        """(n_segments,) int64: pixels per segment."""
        return np.bincount(self.labels[self.labels >= 0], minlength=self.n_segments)

    @cached_property
    def _contacts(self) -> tuple[np.ndarray, np.ndarray]:
        return region_adjacency(self.labels, self.n_segments)

    @property
    def adjacency(self) -> np.ndarray:
        """(E, 2) int32: pairs ``(i, j)``, ``i < j``, of segments with 4-neighbouring pixels, sorted."""
        return self._contacts[0]

    @property
    def contact_lengths(self) -> np.ndarray:
        """(E,) int64: number of 4-neighbour pixel pairs across each pair of :attr:`adjacency`."""
        return self._contacts[1]

    @cached_property
    def boundaries(self) -> np.ndarray:
        """(H, W) bool: valid pixels with a 4-neighbour in another segment or invalid (see :func:`boundary_mask`)."""
        return boundary_mask(self.labels)

    def band(self, width: int) -> np.ndarray:
        """(H, W) bool: valid pixels within ``width`` pixels of a segment boundary (:func:`boundary_band`)."""
        return boundary_band(self.labels, width)

    def means(self, values: np.ndarray, *, where: np.ndarray | None = None) -> np.ndarray:
        """Mean of ``values`` over each segment.

        Parameters
        ----------
        values : (H, W) or (H, W, C) array_like
            Per-pixel values.
        where : (H, W) bool, optional
            Only these pixels count (e.g. ``~seg.band(3)``).

        Returns
        -------
        (n_segments,) or (n_segments, C) float64
            NaN for a segment without a counted pixel.
        """
        values = np.asarray(values, dtype=np.float64)
        if values.shape[:2] != self.shape or values.ndim not in (2, 3):
            raise ValueError(f"values must have shape {self.shape} or {self.shape + ('C',)}, got {values.shape}")
        keep = self.valid if where is None else self.valid & _as_mask(where, "where", self.shape)
        labels = self.labels[keep]
        flat = values[keep].reshape(len(labels), 1 if values.ndim == 2 else values.shape[2])
        counts = np.bincount(labels, minlength=self.n_segments).astype(np.float64)
        sums = np.stack([np.bincount(labels, flat[:, c], minlength=self.n_segments) for c in range(flat.shape[1])], 1)
        with np.errstate(invalid="ignore", divide="ignore"):
            means = sums / counts[:, None]
        return means[:, 0] if values.ndim == 2 else means

    def __repr__(self) -> str:
        h, w = self.shape
        return f"Segmentation({self.method!r}, {w}x{h}, {self.n_segments} segments)"


def boundary_mask(labels: np.ndarray) -> np.ndarray:
    """Valid pixels that touch another segment.

    Parameters
    ----------
    labels : (H, W) int
        Segment labels, negative on invalid pixels.

    Returns
    -------
    (H, W) bool
        Pixels with ``labels >= 0`` whose 4-neighbour (inside the image) has a different label,
        invalid neighbours included; both sides of a segment border are marked. The image border
        is not a segment boundary.
    """
    labels = _as_labels(labels, "labels")
    h_diff = labels[:, 1:] != labels[:, :-1]
    v_diff = labels[1:] != labels[:-1]
    out = np.zeros(labels.shape, dtype=bool)
    out[:, 1:] |= h_diff
    out[:, :-1] |= h_diff
    out[1:] |= v_diff
    out[:-1] |= v_diff
    return out & (labels >= 0)


def boundary_band(labels: np.ndarray, width: int) -> np.ndarray:
    """Valid pixels within ``width`` pixels of a segment boundary.

    The paper computes a cluster's ``R(0)`` and ``R(1)`` "except for points in a 3-pixel wide
    boundary around each cluster" (Sec. 6.1): ``~boundary_band(labels, 3)`` keeps the others.

    Parameters
    ----------
    labels : (H, W) int
        Segment labels, negative on invalid pixels.
    width : int
        Band width, pixels (>= 0). 1 gives :func:`boundary_mask`; ``width`` gives the ``width``
        pixel rows of each segment nearest to a straight border.

    Returns
    -------
    (H, W) bool
        Valid pixels whose Euclidean distance to the nearest boundary pixel of
        :func:`boundary_mask` is below ``width``.
    """
    labels = _as_labels(labels, "labels")
    if isinstance(width, bool) or not isinstance(width, (int, np.integer)) or width < 0:
        raise ValueError(f"width must be an integer >= 0 pixels, got {width!r}")
    edges = boundary_mask(labels)
    if width == 0 or not edges.any():
        return np.zeros(labels.shape, dtype=bool)
    if width == 1:
        return edges
    distance = ndimage.distance_transform_edt(~edges)
    return (distance < width) & (labels >= 0)


def region_adjacency(labels: np.ndarray, n_segments: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Pairs of segments that touch (4-connectivity) and the length of their shared border.

    Parameters
    ----------
    labels : (H, W) int
        Segment labels ``0 .. n - 1``, negative on invalid pixels (which touch nothing).
    n_segments : int, optional
        Number of segments (default: ``labels.max() + 1``).

    Returns
    -------
    pairs : (E, 2) int32
        ``(i, j)`` with ``i < j``, sorted lexicographically.
    lengths : (E,) int64
        4-neighbour pixel pairs across each border.
    """
    labels = _as_labels(labels, "labels")
    n = int(labels.max()) + 1 if n_segments is None else int(n_segments)
    first, second = _neighbour_pairs(labels)
    return _unique_pairs(first, second, max(n, 1))


def merge_small_regions(
    labels: np.ndarray,
    colors: np.ndarray,
    min_region: int,
) -> np.ndarray:
    """Merge every region smaller than ``min_region`` into its most similar touching region.

    All small regions are handled at once: each picks the 4-adjacent region whose mean colour is
    nearest (Euclidean; ties to the lower label) and the picks are joined as a graph (connected
    components), so chains of small regions join the region at their end. This repeats until no
    small region has a neighbour. Regions stay 4-connected.

    Parameters
    ----------
    labels : (H, W) int
        Region labels ``0 .. n - 1`` (any order), negative on invalid pixels.
    colors : (H, W, C) float
        Per-pixel colour the region means are taken of.
    min_region : int
        Smallest region area, pixels.

    Returns
    -------
    (H, W) int32
        Labels ``0 .. m - 1`` in raster order of first appearance, ``-1`` on invalid pixels.
    """
    labels = _as_labels(labels, "labels")
    colors = np.asarray(colors, dtype=np.float64)
    if colors.shape[:2] != labels.shape or colors.ndim != 3:
        raise ValueError(f"colors must have shape {labels.shape + ('C',)}, got {colors.shape}")
    if isinstance(min_region, bool) or not isinstance(min_region, (int, np.integer)) or min_region < 1:
        raise ValueError(f"min_region must be an integer >= 1, got {min_region!r}")
    valid = labels >= 0
    if not valid.any():
        return np.full(labels.shape, -1, dtype=np.int32)
    current = _relabel(labels)
    flat = current[valid]
    n = int(flat.max()) + 1
    sizes = np.bincount(flat, minlength=n).astype(np.float64)
    pixels = colors[valid]
    sums = np.stack([np.bincount(flat, pixels[:, c], minlength=n) for c in range(pixels.shape[1])], axis=1)
    pairs, _ = _unique_pairs(*_neighbour_pairs(current), n)

    while True:
        small = sizes < min_region
        if not small.any() or len(pairs) == 0:
            break
        means = sums / sizes[:, None]
        # Both directions of every edge, kept where the source is small.
        src = np.concatenate([pairs[:, 0], pairs[:, 1]])
        dst = np.concatenate([pairs[:, 1], pairs[:, 0]])
        keep = small[src]
        if not keep.any():
            break
        src, dst = src[keep], dst[keep]
        difference = means[src] - means[dst]
        distance = np.einsum("ij,ij->i", difference, difference)
        # Nearest neighbour of each small region (ties: the lowest label), without a sort.
        nearest = np.full(n, np.inf)
        np.minimum.at(nearest, src, distance)
        best = distance == nearest[src]
        target = np.full(n, n, dtype=np.int64)
        np.minimum.at(target, src[best], dst[best])
        src = np.flatnonzero(target < n)
        dst = target[src]
        graph = sparse.coo_matrix((np.ones(len(src), dtype=np.int8), (src, dst)), shape=(n, n))
        n_new, mapping = csgraph.connected_components(graph, directed=False)
        sizes = np.bincount(mapping, sizes, minlength=n_new)
        sums = np.stack([np.bincount(mapping, sums[:, c], minlength=n_new) for c in range(sums.shape[1])], axis=1)
        current = np.where(valid, mapping[np.maximum(current, 0)], -1)
        pairs = mapping[pairs]
        pairs = pairs[pairs[:, 0] != pairs[:, 1]]
        pairs, _ = _unique_pairs(pairs[:, 0], pairs[:, 1], n_new)
        n = n_new
    return _relabel(current)


def perceptual_lab(image: np.ndarray, *, mask: np.ndarray | None = None, white_percentile: float = 99.9) -> np.ndarray:
    """CIELAB of a linear, scene-referred image after exposure normalisation and sRGB encoding.

    Parameters
    ----------
    image : (H, W, 3) float
        Linear RGB, Rec. 709 primaries, any positive scale; finite on valid pixels.
    mask : (H, W) bool, optional
        Valid pixels (default: all); only they set the white level.
    white_percentile : float
        Percentile, in (0, 100], of the valid pixels' Rec. 709 luminance that maps to sRGB white.

    Returns
    -------
    (H, W, 3) float32
        ``L*`` in [0, 100], ``a*``, ``b*`` (D65). Values above the white level are clipped to
        white, negative ones to black; invalid pixels are black.
    """
    image = as_array(image, "image", shape=(None, None, 3), dtype=np.float32, finite=False)
    valid = np.ones(image.shape[:2], dtype=bool) if mask is None else _as_mask(mask, "mask", image.shape[:2])
    if not is_real(white_percentile) or not 0 < white_percentile <= 100:
        raise ValueError(f"white_percentile must lie in (0, 100], got {white_percentile!r}")
    bad = valid & ~np.isfinite(image).all(axis=2)
    if bad.any():
        raise ValueError(f"image must be finite on valid pixels, got {int(bad.sum())} NaN/Inf pixels (mask them out)")
    return _perceptual_lab(image, valid, white_percentile)


def _perceptual_lab(rgb: np.ndarray, valid: np.ndarray, white_percentile: float) -> np.ndarray:
    rgb = np.where(valid[..., None], rgb, np.float32(0.0))
    luminance = rgb[valid] @ _LUMINANCE_WEIGHTS
    white = float(np.percentile(luminance, white_percentile)) if luminance.size else 0.0
    if not white > 0:  # a (mostly) black image: fall back to its brightest value
        white = float(rgb.max()) if rgb.max() > 0 else 1.0
    x = np.clip(rgb / np.float32(white), 0.0, 1.0)
    # sRGB encoding (IEC 61966-2-1).
    encoded = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4, dtype=np.float32) - 0.055)
    return cv2.cvtColor(np.ascontiguousarray(encoded, dtype=np.float32), cv2.COLOR_RGB2Lab)


def segment(
    image: np.ndarray,
    *,
    mask: np.ndarray | None = None,
    config: SegmentationConfig | None = None,
) -> Segmentation:
    """Segment a view into small regions of uniform colour (paper Sec. 6.1).

    Parameters
    ----------
    image : (H, W, 3) float
        Linear, scene-referred RGB (``docs/conventions.md``); values may exceed 1. Must be finite
        on valid pixels; negative values are clipped to 0.
    mask : (H, W) bool, optional
        Valid pixels (default: all). Invalid pixels get label -1 and neither join nor separate
        segments (their colour is replaced by the nearest valid pixel's before filtering).
    config : SegmentationConfig, optional
        Method and parameters (default: the paper's mean shift).

    Returns
    -------
    Segmentation
        Every valid pixel labelled ``0 .. n - 1``; no segment is smaller than
        ``config.min_region`` unless it is a whole connected component of the mask.

    Raises
    ------
    ValueError
        If ``image`` or ``mask`` has the wrong shape, or ``image`` is not finite on valid pixels.
    TypeError
        If ``config`` is not a :class:`SegmentationConfig` or an input is not numeric.
    """
    config = config_or_default(config, SegmentationConfig)
    image = as_array(image, "image", shape=(None, None, 3), dtype=np.float32, finite=False)
    shape = image.shape[:2]
    if 0 in shape:
        raise ValueError(f"image must have at least one pixel, got shape {image.shape}")
    valid = np.ones(shape, dtype=bool) if mask is None else _as_mask(mask, "mask", shape)
    bad = valid & ~np.isfinite(image).all(axis=2)
    if bad.any():
        raise ValueError(f"image must be finite on valid pixels, got {int(bad.sum())} NaN/Inf pixels (mask them out)")
    if not valid.any():
        return Segmentation(np.full(shape, -1, dtype=np.int32), 0, config.method)

    lab = _perceptual_lab(image, valid, config.white_percentile)
    if not valid.all():
        # Invalid pixels take their nearest valid pixel's colour, so they neither attract the
        # filter toward an arbitrary colour nor create edges.
        _, (rows, cols) = ndimage.distance_transform_edt(~valid, return_indices=True)
        lab = lab[rows, cols]
    if config.method == "mean_shift":
        labels, colors = _mean_shift_regions(lab, valid, config)
    else:
        labels, colors = _slic_regions(lab, valid, config)
    labels = merge_small_regions(labels, colors, config.min_region)
    return Segmentation(labels, int(labels.max()) + 1, config.method)


def _mean_shift_regions(
    lab: np.ndarray, valid: np.ndarray, config: SegmentationConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Mean-shift filtering and delineation: (H, W) region labels and the filtered CIELAB."""
    low = lab.reshape(-1, 3)[valid.ravel()].min(axis=0)
    high = lab.reshape(-1, 3)[valid.ravel()].max(axis=0)
    # One scale for the three channels keeps the colour ball round in Delta E.
    scale = min(MAX_CODES_PER_DELTA_E, 255.0 / max(float((high - low).max()), 1e-6))
    codes = np.clip(np.rint((lab - low) * scale), 0, 255).astype(np.uint8)
    criteria = (cv2.TERM_CRITERIA_MAX_ITER + cv2.TERM_CRITERIA_EPS, config.max_iterations, 1)
    filtered = cv2.pyrMeanShiftFiltering(codes, config.spatial_bandwidth, scale * config.color_bandwidth,
                                         maxLevel=0, termcrit=criteria)
    filtered = filtered.astype(np.float32) / np.float32(scale) + low  # back to CIELAB
    tolerance = config.fusion_tolerance * config.color_bandwidth
    h, w = valid.shape
    index = np.arange(h * w).reshape(h, w)
    join_h = valid[:, 1:] & valid[:, :-1] & (np.linalg.norm(filtered[:, 1:] - filtered[:, :-1], axis=2) < tolerance)
    join_v = valid[1:] & valid[:-1] & (np.linalg.norm(filtered[1:] - filtered[:-1], axis=2) < tolerance)
    rows = np.concatenate([index[:, 1:][join_h], index[1:][join_v]])
    cols = np.concatenate([index[:, :-1][join_h], index[:-1][join_v]])
    graph = sparse.coo_matrix((np.ones(len(rows), dtype=np.int8), (rows, cols)), shape=(h * w, h * w))
    _, components = csgraph.connected_components(graph, directed=False)
    labels = np.where(valid, components.reshape(h, w), -1)
    return labels, filtered


def _slic_regions(lab: np.ndarray, valid: np.ndarray, config: SegmentationConfig) -> tuple[np.ndarray, np.ndarray]:
    """SLIC superpixels of the CIELAB image: (H, W) labels and the CIELAB image."""
    from skimage.segmentation import slic

    n_segments = max(1, round(int(valid.sum()) / config.slic_mean_area))
    # slic rescales the image by its value range (all channels) before clustering: dividing the
    # compactness by the same range keeps it in Delta E units.
    values = lab[valid]
    value_range = max(float(values.max() - values.min()), 1e-6)
    labels = slic(lab, n_segments=n_segments, compactness=config.slic_compactness / value_range,
                  max_num_iter=config.slic_iterations, sigma=0, convert2lab=False, enforce_connectivity=True,
                  start_label=1, mask=None if valid.all() else valid, channel_axis=-1)
    labels = np.where(valid, labels, -1)
    # SLIC's connectivity enforcement is 8-connected; split to 4-connected pieces before pruning.
    return _split_four_connected(labels), lab


def _split_four_connected(labels: np.ndarray) -> np.ndarray:
    """Give each 4-connected piece of every region its own label."""
    h, w = labels.shape
    index = np.arange(h * w).reshape(h, w)
    join_h = (labels[:, 1:] == labels[:, :-1]) & (labels[:, 1:] >= 0)
    join_v = (labels[1:] == labels[:-1]) & (labels[1:] >= 0)
    rows = np.concatenate([index[:, 1:][join_h], index[1:][join_v]])
    cols = np.concatenate([index[:, :-1][join_h], index[:-1][join_v]])
    graph = sparse.coo_matrix((np.ones(len(rows), dtype=np.int8), (rows, cols)), shape=(h * w, h * w))
    _, components = csgraph.connected_components(graph, directed=False)
    return np.where(labels >= 0, components.reshape(h, w), -1)


def _neighbour_pairs(labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Labels on both sides of every 4-neighbour pixel pair of two different valid segments."""
    pairs = []
    for a, b in ((labels[:, 1:], labels[:, :-1]), (labels[1:], labels[:-1])):
        cross = (a != b) & (a >= 0) & (b >= 0)
        pairs.append((a[cross], b[cross]))
    return np.concatenate([pairs[0][0], pairs[1][0]]), np.concatenate([pairs[0][1], pairs[1][1]])


def _unique_pairs(first: np.ndarray, second: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Sorted unique ``(min, max)`` pairs and their multiplicities."""
    low = np.minimum(first, second).astype(np.int64)
    high = np.maximum(first, second).astype(np.int64)
    keys, counts = np.unique(low * n + high, return_counts=True)
    pairs = np.stack([keys // n, keys % n], axis=1).astype(np.int32)
    return pairs, counts.astype(np.int64)


def _relabel(labels: np.ndarray) -> np.ndarray:
    """Labels ``0 .. m - 1`` in raster order of first appearance; negative labels become -1."""
    flat = labels.ravel()
    valid = flat >= 0
    out = np.full(flat.shape, -1, dtype=np.int32)
    if valid.any():
        values, first, inverse = np.unique(flat[valid], return_index=True, return_inverse=True)
        rank = np.empty(len(values), dtype=np.int32)
        rank[np.argsort(first, kind="stable")] = np.arange(len(values), dtype=np.int32)
        out[valid] = rank[inverse]
    return out.reshape(labels.shape)


def _as_labels(labels: object, name: str) -> np.ndarray:
    array = np.asarray(labels)
    if array.ndim != 2 or array.dtype.kind not in "iu":
        raise ValueError(f"{name} must be an (H, W) integer array, got {describe(labels)}")
    return array


def _as_mask(mask: object, name: str, shape: tuple[int, int]) -> np.ndarray:
    array = np.asarray(mask)
    if array.dtype != bool:
        raise TypeError(f"{name} must be a boolean array, got {describe(mask)}")
    if array.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got shape {array.shape}")
    return array
