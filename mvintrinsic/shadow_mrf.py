"""Step 3a: binary shadow labelling of the clusters of a view by graph cut (paper Sec. 6.1).

The proxy visibility ``~v`` of Step 1 is coarse. Step 3 finds the sun visibility that makes most
points share a similar reflectance: every cluster ``s`` of a colour over-segmentation
(:func:`mvintrinsic.segmentation.segment`) gets a label ``x_s`` (1 lit, 0 shadow) minimising

.. math::

   E(\\mathcal X) = \\sum_{s \\in V} \\phi_s(x_s) + \\sum_{(s,t) \\in \\mathcal E} \\phi_{s,t}(x_s, x_t)
   \\qquad (7)

Per view (:func:`label_shadows`, independent of the other views):

1. *Reflectance hypotheses* (Eq. 2): ``R_s(0) = I / (S_sky + S_ind)`` and
   ``R_s(1) = I / (S_sky + S_ind + L_sun max(0, cos w_sun))``, per RGB channel the median over the
   pixels of cluster ``s`` that carry proxy samples (valid, not :attr:`~PixelQuantities.filled`)
   and lie outside the ``boundary_band``-pixel band along the cluster boundary (Sec. 6.1: "except
   for points in a 3-pixel wide boundary"). A cluster with fewer than ``min_interior`` such
   interior pixels uses all its sampled pixels, band included (a deviation: the paper would leave
   a small cluster without samples). A cluster without any sampled pixel has no ``R``: it gets
   the equal unary (Eq. 13) and no reflectance edge, and "the propagation is solely governed by the
   chi^2 distance to neighboring regions" (Sec. 6.1).
2. *Distances* (Eq. 6): ``D_ij(s, t) = |R_s(i) - R_t(j)|``. The paper names no norm; by default
   (``distance="log"``) it is the Euclidean norm of the difference of the logarithms of the RGB
   reflectances (a ratio), ``distance="euclidean"`` gives the norm of the RGB difference. The
   absolute difference is small between any two dark values: the dark ``R_s(1)`` of a shadowed
   cluster then finds close ``R_t(0)`` among the many dark clusters, ``H_1`` is small and Eq. 10
   almost never fires (dev_courtyard, Step-1 shading, ``k = 1``: Eq. 10 for 2% of the truly
   shadowed clusters, Eq. 11 for 35% of the lit ones; 5% and 4% with the log distance, which
   treats both hypotheses alike).
3. *Unary terms* (Eqs. 8-13): ``H_0`` sums the ``k`` smallest ``D_01(s, .)`` over the other
   clusters, ``H_1`` the ``k`` smallest ``D_10(s, .)`` (k-d tree queries: 70-100 times faster than
   an ``n x n`` distance matrix at ``n`` = 4400-6000); ``H_0 / (H_0 + H_1) < tau_1`` prefers shadow
   (Eq. 10), ``H_1 / (H_0 + H_1) < tau_1`` light (Eq. 11). Otherwise ``H'_0`` and ``H'_1`` are the
   same sums over the clusters whose centroid lies within ``local_radius`` (a fraction of the
   image diagonal) of ``s``'s, and ``(H_1 + H'_1) / (H_0 + H_1 + H'_0 + H'_1) < tau_1`` (Eq. 12)
   prefers light, its ``H_0`` twin shadow; else both labels cost ``l_eq`` (Eq. 13).
4. *Pairwise terms*: each cluster is joined to the ``k`` other clusters of smallest
   ``min(D_00, D_11)`` ("the k clusters with smallest D_00 or D_11"; a pair chosen from both
   sides is one edge) with the strong same-label potential of Eq. 14, and to its 4-adjacent
   clusters with Eq. 15 when the chi^2 distance ``d_c`` of their CIELAB histograms is below
   ``tau_c``, Eq. 16 otherwise. A pair that is both keeps both terms (``E`` is a multiset).
5. *Graph cut*: Eq. 7 is minimised exactly by one s-t minimum cut (PyMaxflow, the Boykov-Kolmogorov
   algorithm of the paper's solver [2]_).

Potentials as costs
-------------------
Eq. 7 is an ``argmin``, so every potential is a cost. The text says what each potential must
encourage, and the values are assigned so that they do: the encouraged configuration costs
``l_0 = 0`` (strongly, Eqs. 10, 11, 14) or ``l_np = 0.2`` (moderately, Eq. 15), the discouraged one
``l_1 = 1`` or ``l_p = 0.8``, and ``l_eq = 0.5`` when neither is (Eqs. 13, 16):

==========================  ====================  ==================
potential                   encouraged            discouraged
==========================  ====================  ==================
Eq. 10 (shadow preferred)   ``x_s = 0``: l_0      ``x_s = 1``: l_1
Eq. 11 (light preferred)    ``x_s = 1``: l_0      ``x_s = 0``: l_1
Eq. 14 (same reflectance)   ``x_s = x_t``: l_0    ``x_s != x_t``: l_1
Eq. 15 (same colours)       ``x_s = x_t``: l_np   ``x_s != x_t``: l_p
==========================  ====================  ==================

As printed, Eqs. 10, 11 and 14 give ``l_1`` to the encouraged configuration and Eq. 15 gives the
smaller ``l_np`` to it: no single reading (costs or scores, ``x = 1`` lit or shadow) makes all
four agree with the text, so the text is followed. Read literally as costs, Eq. 14 would push
clusters of equal reflectance *apart* and be non-submodular on every such edge.

Graph representability
----------------------
A pairwise table ``theta`` on binary labels is representable by an s-t cut iff it is submodular,
``theta(0,0) + theta(1,1) <= theta(0,1) + theta(1,0)`` (Kolmogorov and Zabih 2004 [3]_). Eq. 14:
``2 l_0 <= 2 l_1``; Eq. 15: ``2 l_np <= 2 l_p``; Eq. 16: ``2 l_eq = 2 l_eq``. :class:`ShadowConfig`
requires ``l_0 <= l_1`` and ``l_np <= l_p``, so every pairwise term is submodular, no term is
truncated or reparametrised, and the cut is the exact global minimum of Eq. 7 (+ the tie-break
below). Each table is split as
``theta(x_s, x_t) = A + (C - A) x_s + (D - C) x_t + (B + C - A - D) (1 - x_s) x_t`` with
``A, B, C, D = theta(0,0), theta(0,1), theta(1,0), theta(1,1)``: the linear parts go to the
terminal edges, the last one is an edge ``s -> t`` of capacity ``B + C - A - D >= 0``.

Tie-break (a deviation)
-----------------------
Eq. 7 often has many minimisers: a region with no unary decision, joined to the rest only by Eq. 16
edges (constants, which join nothing), costs the same lit or in shadow. Which minimiser a max-flow
returns is then an accident of its search trees (the Boykov-Kolmogorov code leaves such nodes on
the source side: shadow). The choice is made explicit by adding to the cut (not to Eq. 7) a unary
prior of total weight ``tie_break_weight``, spread over the clusters in proportion to their areas:
toward the cluster's median proxy visibility ``~v`` (``tie_break="proxy"``: ``w_s |x_s - ~v_s|``),
toward light or toward shadow. With the paper's potentials every energy difference between two
labellings is an integer combination of ``l_1 - l_0 = 1`` and ``l_p - l_np = 0.6``, hence a
multiple of 0.2; a prior of total weight 0.1 < 0.2 cannot outweigh any such difference, so the cut
still minimises Eq. 7 exactly and only chooses among its minimisers. The minimisers of a submodular
energy form a lattice; the "lit" and "shadow" priors give its two extreme elements (the most and
the fewest lit clusters), and the clusters on which these differ, whose label Eq. 7 leaves open,
are :attr:`ShadowLabels.undetermined`.

Measured
--------
Balanced error of the labels, their floor and speed on five scenes: ``docs/notes/shadow_mrf.md``
(``benchmarks/bench_shadow_mrf.py``, ``benchmarks/results/shadow_mrf.json``).

The labelling is the paper's [1]_, with the cluster histograms of Chaurasia et al. [4]_.

References
----------
.. [1] S. Duchêne et al., "Multi-View Intrinsic Images of Outdoors Scenes with an Application to
   Relighting", ACM Transactions on Graphics 34(5), 2015, Sec. 6.1.
.. [2] Y. Boykov and V. Kolmogorov, "An experimental comparison of min-cut/max-flow algorithms for
   energy minimization in vision", IEEE TPAMI 26(9), 2004.
.. [3] V. Kolmogorov and R. Zabih, "What energy functions can be minimized via graph cuts?",
   IEEE TPAMI 26(2), 2004.
.. [4] G. Chaurasia et al., "Depth synthesis and local warps for plausible image-based
   navigation", ACM Transactions on Graphics 32(3), 2013 (chi^2 distance of Lab histograms).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType

import numpy as np
from scipy.spatial import cKDTree

from ._validation import as_array, config_or_default, describe, is_real
from .image_model import reflectance, sun_shading
from .pixels import PixelQuantities
from .results import SHADOW_LABELS
from .segmentation import Segmentation, perceptual_lab

__all__ = [
    "DISTANCES",
    "METHODS",
    "EDGE_KINDS",
    "TIE_BREAKS",
    "UNARY_RULES",
    "ShadowConfig",
    "ShadowLabels",
    "ShadowMRF",
    "build_mrf",
    "chi2_distance",
    "cluster_reflectances",
    "graph_cut",
    "label_shadows",
    "lab_histograms",
    "mrf_energy",
]

logger = logging.getLogger(__name__)

#: Cluster labels ``x_s`` (the sun visibility hypothesis ``v``).
SHADOW, LIT = 0, 1

#: How each cluster's unary term was set, indexed by :attr:`ShadowLabels.unary_rule`.
UNARY_RULES = ("shadow", "lit", "local_shadow", "local_lit", "equal", "no_samples")

#: Kinds of pairwise terms, indexed by :attr:`ShadowMRF.edge_kind`.
EDGE_KINDS = ("reflectance", "similar_colours", "different_colours")


#: Valid values of :attr:`ShadowConfig.distance`.
DISTANCES = ("log", "euclidean")

#: Valid values of :attr:`ShadowConfig.tie_break`.
TIE_BREAKS = ("proxy", "lit", "shadow")

#: Valid values of :attr:`ShadowConfig.method`: the labelling Step 3 runs.
METHODS = ("multiview", "paper")

#: Reflectances below this are raised to it before the logarithm of ``distance="log"``.
LOG_FLOOR = 1e-3


@dataclass(frozen=True)
class ShadowConfig:
    """Options of the shadow labelling (paper Sec. 6.1); defaults are the paper's where it gives one.

    Parameters
    ----------
    method : {"multiview", "paper"}
        Which labelling the pipeline's Step 3 runs. ``"paper"``: this module, Sec. 6.1 per view and
        per cluster, with the parameters below. ``"multiview"`` (default): all views at once at
        pixel resolution (:mod:`mvintrinsic.multiview_shadows`, configured by
        ``Config.multiview``), which measured 0.33-0.54 of the paper's balanced error on the seven
        scenes of ``benchmarks/bench_shadows.py``; the parameters below are then unused.
    k : int
        Number of best partners: the clusters summed in ``H_0``, ``H_1`` (Eqs. 8-9), ``H'_0``,
        ``H'_1`` (Eq. 12), and the reflectance edges per cluster (Eq. 14). The paper names ``k``
        but gives no value. 1 gave the lowest shadow error on the three courtyard-like scenes
        measured (``benchmarks/bench_shadow_mrf.py``): with more partners than a material has
        clusters under one light, the strong Eq. 14 edges reach across shadow boundaries.
    tau_1 : float
        Confidence threshold of the unary decisions, in (0, 1/2) (paper: 0.1, "a 90% confidence
        level").
    local_radius : float
        Radius of the neighbourhood of the local search (Eq. 12), as a fraction of the image
        diagonal, between cluster centroids. The paper gives no size; 0.05 (about 60 pixels on its
        1000x700 images) did as well as or better than 0.1 on the scenes measured.
    l_1, l_0 : float
        Costs of the strongly discouraged and encouraged configurations (paper: 1 and 0);
        ``l_0 <= l_1``.
    l_p, l_np : float
        Costs of the moderately discouraged and encouraged configurations of Eq. 15 (paper: 0.8
        and 0.2, "preferred" / "non-preferred"); ``l_np <= l_p``.
    l_eq : float
        Cost of every configuration when neither is encouraged (Eqs. 13, 16; paper: 0.5).
    tau_c : float
        Two adjacent clusters have similar colours when the chi^2 distance of their CIELAB
        histograms is below ``tau_c`` (paper: 0.05).
    histogram_bins : int
        Bins per CIELAB channel of the cluster histograms (the paper follows Chaurasia et al. 2013
        and gives no count), spanning the 0.5-99.5 percentiles of the view's valid pixels. With 8,
        12-16% of the adjacent cluster pairs under one light pass ``tau_c`` on the demo and
        dev_courtyard scenes and none across a true shadow boundary; with 20, 3%; with 4, 31-52%
        but also 1% of the pairs across a boundary.
    boundary_band : int
        Width (pixels) of the band along each cluster boundary whose pixels are left out of
        ``R(0)``, ``R(1)`` (paper: 3).
    min_interior : int
        A cluster with fewer interior (outside the band) sampled pixels takes its medians over all
        its sampled pixels (a small cluster can be all band).
    tie_break : {"proxy", "lit", "shadow"}
        Which minimiser of Eq. 7 to return when it has several (a deviation, see the module
        docstring): the one closest to the proxy visibility ``~v``, the one with the most lit or
        the most shadowed clusters.
    tie_break_weight : float
        Total weight of the tie-break prior, > 0. Keep it below the smallest non-zero energy
        difference between labellings (0.2 with the paper's potentials) so that it never changes
        the energy of the solution.
    distance : {"log", "euclidean"}
        The norm of Eq. 6 (the paper's ``|.|``; see the module docstring).
    """

    method: str = "multiview"
    k: int = 1
    tau_1: float = 0.1
    local_radius: float = 0.05
    l_1: float = 1.0
    l_0: float = 0.0
    l_p: float = 0.8
    l_np: float = 0.2
    l_eq: float = 0.5
    tau_c: float = 0.05
    histogram_bins: int = 8
    boundary_band: int = 3
    min_interior: int = 5
    tie_break: str = "proxy"
    tie_break_weight: float = 0.1
    distance: str = "log"

    def __post_init__(self) -> None:
        for name, least in (("k", 1), ("histogram_bins", 2), ("boundary_band", 0), ("min_interior", 1)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
                raise ValueError(f"{name} must be an integer >= {least}, got {value!r}")
        for name in ("l_1", "l_0", "l_p", "l_np", "l_eq"):
            value = getattr(self, name)
            if not is_real(value) or not np.isfinite(value):
                raise ValueError(f"{name} must be a finite number, got {value!r}")
        if not self.l_0 <= self.l_1:
            raise ValueError(f"l_0 must be <= l_1 (Eq. 14 must stay submodular), got l_0={self.l_0!r}, "
                             f"l_1={self.l_1!r}")
        if not self.l_np <= self.l_p:
            raise ValueError(f"l_np must be <= l_p (Eq. 15 must stay submodular), got l_np={self.l_np!r}, "
                             f"l_p={self.l_p!r}")
        if self.method not in METHODS:
            raise ValueError(f"method must be one of {list(METHODS)}, got {self.method!r}")
        if self.distance not in DISTANCES:
            raise ValueError(f"distance must be one of {list(DISTANCES)}, got {self.distance!r}")
        if not is_real(self.tau_1) or not 0 < self.tau_1 < 0.5:
            raise ValueError(f"tau_1 must lie in (0, 0.5), got {self.tau_1!r}")
        if not is_real(self.tau_c) or not 0 < self.tau_c <= 1:
            raise ValueError(f"tau_c must lie in (0, 1], got {self.tau_c!r}")
        if not is_real(self.local_radius) or not 0 <= self.local_radius < np.inf:
            raise ValueError(f"local_radius must be a finite number >= 0, got {self.local_radius!r}")
        if self.tie_break not in TIE_BREAKS:
            raise ValueError(f"tie_break must be one of {list(TIE_BREAKS)}, got {self.tie_break!r}")
        if not is_real(self.tie_break_weight) or not 0 < self.tie_break_weight < np.inf:
            raise ValueError(f"tie_break_weight must be a positive finite number, got {self.tie_break_weight!r}")


@dataclass(frozen=True, eq=False)
class ShadowMRF:
    """The terms of Eq. 7 on the cluster graph of one view.

    Parameters
    ----------
    unary : (n, 2) float64
        ``phi_s(0)``, ``phi_s(1)`` (costs of shadow and light) per cluster.
    edges : (E, 2) int64
        Clusters ``(s, t)`` of each pairwise term (``s < t`` from :func:`build_mrf`). A pair may carry two terms (a
        reflectance edge and an adjacency edge): the energy sums them.
    pairwise : (E, 4) float64
        ``phi_st(0, 0)``, ``phi_st(0, 1)``, ``phi_st(1, 0)``, ``phi_st(1, 1)`` per edge.
    edge_kind : (E,) int8
        Index into :data:`EDGE_KINDS`.
    """

    unary: np.ndarray
    edges: np.ndarray
    pairwise: np.ndarray
    edge_kind: np.ndarray

    def __post_init__(self) -> None:
        unary = as_array(self.unary, "unary", shape=(None, 2), dtype=np.float64)
        edges = as_array(self.edges, "edges", shape=(None, 2), dtype=np.int64)
        pairwise = as_array(self.pairwise, "pairwise", shape=(len(edges), 4), dtype=np.float64)
        kind = as_array(self.edge_kind, "edge_kind", shape=(len(edges),), dtype=np.int8)
        if len(edges) and (edges.min() < 0 or edges.max() >= len(unary) or (edges[:, 0] == edges[:, 1]).any()):
            raise ValueError(f"edges must join two different clusters in [0, {len(unary) - 1}]")
        for name, value in (("unary", unary), ("edges", edges), ("pairwise", pairwise), ("edge_kind", kind)):
            object.__setattr__(self, name, value)

    @property
    def n_clusters(self) -> int:
        """Number of nodes ``n``."""
        return len(self.unary)

    @property
    def n_nonsubmodular(self) -> int:
        """Pairwise tables with ``theta(0,0) + theta(1,1) > theta(0,1) + theta(1,0)`` (0 from :func:`build_mrf`)."""
        p = self.pairwise
        return int((p[:, 0] + p[:, 3] > p[:, 1] + p[:, 2] + 1e-12).sum())

    def energy(self, labels: np.ndarray) -> float:
        """Eq. 7 for a labelling ``(n,)`` of 0 (shadow) / 1 (lit); see :func:`mrf_energy`."""
        return mrf_energy(self, labels)

    def __repr__(self) -> str:
        return f"ShadowMRF({self.n_clusters} clusters, {len(self.edges)} pairwise terms)"


def mrf_energy(mrf: ShadowMRF, labels: np.ndarray) -> float:
    """Energy of Eq. 7 for any labelling.

    Parameters
    ----------
    mrf : ShadowMRF
    labels : (n,) array_like of {0, 1} or bool
        ``x_s`` per cluster, 1 lit.

    Returns
    -------
    float
        ``sum_s phi_s(x_s) + sum_(s,t) phi_st(x_s, x_t)``.
    """
    x = np.asarray(labels)
    if x.shape != (mrf.n_clusters,):
        raise ValueError(f"labels must have shape ({mrf.n_clusters},), got shape {x.shape}")
    if x.dtype != bool and not np.isin(x, (0, 1)).all():
        raise ValueError("labels must hold only 0 (shadow) and 1 (lit)")
    x = x.astype(np.int64)
    unary = mrf.unary[np.arange(len(x)), x].sum()
    if not len(mrf.edges):
        return float(unary)
    index = 2 * x[mrf.edges[:, 0]] + x[mrf.edges[:, 1]]
    return float(unary + mrf.pairwise[np.arange(len(index)), index].sum())


def graph_cut(mrf: ShadowMRF, *, prior: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """Exact minimum of Eq. 7 (plus an optional unary ``prior``) by one s-t minimum cut.

    Parameters
    ----------
    mrf : ShadowMRF
        Every pairwise table must be submodular (see the module docstring).
    prior : (n, 2) array_like, optional
        Extra unary costs of shadow and light added to the cut only.

    Returns
    -------
    labels : (n,) uint8
        1 lit, 0 shadow.
    value : float
        Minimum of Eq. 7 + prior.

    Raises
    ------
    ValueError
        If a pairwise table is not submodular.
    """
    import maxflow

    if mrf.n_nonsubmodular:
        raise ValueError(f"{mrf.n_nonsubmodular} pairwise terms are not submodular: the graph cut cannot represent "
                         f"them")
    n = mrf.n_clusters
    if n == 0:
        return np.zeros(0, dtype=np.uint8), 0.0
    cost = mrf.unary.copy()
    if prior is not None:
        cost = cost + as_array(prior, "prior", shape=(n, 2), dtype=np.float64)
    constant = 0.0
    s, t = mrf.edges[:, 0], mrf.edges[:, 1]
    a, b, c, d = mrf.pairwise.T
    # theta(x_s, x_t) = A + (C - A) x_s + (D - C) x_t + (B + C - A - D) (1 - x_s) x_t.
    constant += float(a.sum())
    np.add.at(cost[:, 1], s, c - a)
    np.add.at(cost[:, 1], t, d - c)
    cross = b + c - a - d
    # Terminal edges: a node in the sink segment (x = 1) cuts its source edge and pays cost[:, 1].
    low = cost.min(axis=1)
    constant += float(low.sum())
    graph = maxflow.Graph[float](n, max(len(s), 1))
    nodes = graph.add_nodes(n)
    graph.add_grid_tedges(nodes, cost[:, 1] - low, cost[:, 0] - low)
    keep = cross > 0
    if keep.any():
        # Edge s -> t is cut when s is on the source side (x_s = 0) and t on the sink side (x_t = 1).
        graph.add_edges(s[keep], t[keep], cross[keep], np.zeros(int(keep.sum())))
    flow = graph.maxflow()
    labels = graph.get_grid_segments(nodes).astype(np.uint8)
    return labels, float(flow) + constant


@dataclass(frozen=True, eq=False)
class ShadowLabels:
    """Shadow labels of one view and the evidence behind them (paper Sec. 6.1).

    Parameters
    ----------
    stem : str
        View name.
    cluster_labels : (n,) uint8
        ``x_s`` per cluster of the segmentation: 1 lit, 0 shadow.
    labels : (H, W) uint8
        Per pixel, :data:`mvintrinsic.results.SHADOW_LABELS`: 0 shadow, 255 lit, 128 on pixels that
        are invalid, sky, or outside the segmentation.
    energy : float
        Eq. 7 at ``cluster_labels`` (without the tie-break prior): its minimum.
    mrf : ShadowMRF
        The unary and pairwise terms; ``mrf.energy(x)`` evaluates Eq. 7 for any labelling.
    prior : (n, 2) float64
        The tie-break costs of shadow and light added to the cut.
    undetermined : (n,) bool
        Clusters whose label differs between minimisers of Eq. 7 (set by the tie-break alone).
    reflectance_shadow, reflectance_lit : (n, 3) float64
        ``R_s(0)`` and ``R_s(1)`` (Eq. 2 with ``v = 0`` and ``v = 1``), medians; NaN for a cluster
        without samples.
    samples : (n,) int64
        Pixels each cluster's medians were taken over.
    unary_rule : (n,) int8
        Index into :data:`UNARY_RULES`: how each unary term was set.
    counts : mapping of str to int
        Clusters per unary rule (:data:`UNARY_RULES`), terms per edge kind (``<kind>_edges``),
        ``small_clusters`` (medians over the band), ``lit_clusters``, ``shadow_clusters`` and
        ``undetermined_clusters``.
    timings : mapping of str to float
        Seconds per part: ``reflectance``, ``unary``, ``pairwise``, ``graph_cut``, ``labels``.
    """

    stem: str
    cluster_labels: np.ndarray
    labels: np.ndarray
    energy: float
    mrf: ShadowMRF
    prior: np.ndarray
    undetermined: np.ndarray
    reflectance_shadow: np.ndarray
    reflectance_lit: np.ndarray
    samples: np.ndarray
    unary_rule: np.ndarray
    counts: Mapping[str, int]
    timings: Mapping[str, float]

    @property
    def n_clusters(self) -> int:
        """Number of clusters ``n``."""
        return len(self.cluster_labels)

    @property
    def shadow(self) -> np.ndarray:
        """(H, W) bool: pixels labelled shadow."""
        return self.labels == SHADOW_LABELS["shadow"]

    def undetermined_pixels(self, segmentation: Segmentation) -> np.ndarray:
        """(H, W) bool: labelled pixels of the :attr:`undetermined` clusters of ``segmentation``."""
        if segmentation.n_segments != self.n_clusters or segmentation.shape != self.labels.shape:
            raise ValueError(f"segmentation must be the one labelled ({self.n_clusters} clusters, {self.labels.shape}), "
                             f"got {segmentation!r}")
        inside = segmentation.valid & (self.labels != SHADOW_LABELS["undecided"])
        out = np.zeros(self.labels.shape, dtype=bool)
        out[inside] = self.undetermined[segmentation.labels[inside]]
        return out

    def __repr__(self) -> str:
        return (f"ShadowLabels({self.stem!r}, {self.n_clusters} clusters, {self.counts['shadow_clusters']} in shadow, "
                f"energy={self.energy:.2f})")


def cluster_reflectances(
    image: np.ndarray,
    quantities: PixelQuantities,
    segmentation: Segmentation,
    sun_radiance: np.ndarray,
    *,
    config: ShadowConfig | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per-cluster ``R(0)`` and ``R(1)``: Eq. 2 with ``v = 0`` and ``v = 1``, medians per channel.

    Parameters
    ----------
    image : (H, W, 3) array_like
        Linear RGB of the view.
    quantities : PixelQuantities
        ``S_sky``, ``S_ind``, ``cos w_sun`` and the sampled pixels (``valid & ~filled``).
    segmentation : Segmentation
        The clusters.
    sun_radiance : (3,) array_like
        ``L_sun``, shading units.
    config : ShadowConfig, optional
        ``boundary_band`` and ``min_interior`` are used.

    Returns
    -------
    r0, r1 : (n, 3) float64
        Medians of ``R(0)`` and ``R(1)``; NaN rows for clusters without a sampled pixel.
    samples : (n,) int64
        Pixels per cluster the medians were taken over.
    small : (n,) bool
        Clusters whose medians include their boundary band (fewer than ``min_interior`` interior
        pixels).
    """
    config = config or ShadowConfig()
    n = segmentation.n_segments
    labels = segmentation.labels
    image = np.asarray(image, dtype=np.float64)
    if image.shape != (*quantities.shape, 3) or segmentation.shape != quantities.shape:
        raise ValueError(f"image {image.shape} and segmentation {segmentation.shape} must match the quantities "
                         f"{quantities.shape}")
    sampled = (labels >= 0) & quantities.valid & ~quantities.filled & np.isfinite(image).all(axis=2)
    rows, cols = np.nonzero(sampled)
    sun = sun_shading(np.asarray(sun_radiance, dtype=np.float64), quantities.cosine[rows, cols])  # Eq. 3
    sky = quantities.sky[rows, cols]
    indirect = quantities.indirect[rows, cols]
    pixels = image[rows, cols]
    r0 = reflectance(pixels, sky, indirect, np.zeros(len(rows)), sun)                           # Eq. 2, v = 0
    r1 = reflectance(pixels, sky, indirect, np.ones(len(rows)), sun)                            # Eq. 2, v = 1
    finite = np.isfinite(r0).all(axis=1) & np.isfinite(r1).all(axis=1)
    rows, cols, r0, r1 = rows[finite], cols[finite], r0[finite], r1[finite]
    cluster = labels[rows, cols].astype(np.int64)
    interior = ~segmentation.band(config.boundary_band)[rows, cols]  # width 0: no band
    n_interior = np.bincount(cluster[interior], minlength=n)
    small = n_interior < config.min_interior
    use = interior | small[cluster]
    cluster, r0, r1 = cluster[use], r0[use], r1[use]
    samples = np.bincount(cluster, minlength=n)
    small &= samples > 0
    return _group_median(cluster, r0, n), _group_median(cluster, r1, n), samples, small


def _group_median(groups: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """Per-group, per-column median of ``values`` (N, C) with group ids in ``[0, n)``; NaN if empty."""
    out = np.full((n, values.shape[1]), np.nan)
    counts = np.bincount(groups, minlength=n)
    present = np.flatnonzero(counts)
    if not len(present):
        return out
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])[present]
    c = counts[present]
    for channel in range(values.shape[1]):
        column = values[:, channel]
        # One sort on (group, value): the value mapped into [0, 1/2) and added to the group id.
        low, high = column.min(), column.max()
        key = groups + 0.5 * (column - low) / max(high - low, np.finfo(np.float64).tiny)
        ordered = column[np.argsort(key)]
        out[present, channel] = 0.5 * (ordered[starts + (c - 1) // 2] + ordered[starts + c // 2])
    return out


def lab_histograms(image: np.ndarray, segmentation: Segmentation, *, bins: int = 20) -> np.ndarray:
    """Normalised per-channel CIELAB histograms of every cluster.

    Parameters
    ----------
    image : (H, W, 3) array_like
        Linear RGB; made perceptual by :func:`mvintrinsic.segmentation.perceptual_lab` with its
        default white point (the segmentation's default too).
    segmentation : Segmentation
    bins : int
        Bins per channel over the 0.5-99.5 percentiles of the valid pixels (values outside go to
        the end bins).

    Returns
    -------
    (n, 3, bins) float64
        Each channel's histogram sums to 1 (0 for an empty cluster).
    """
    n = segmentation.n_segments
    out = np.zeros((n, 3, bins))
    valid = segmentation.valid
    if not valid.any():
        return out
    lab = perceptual_lab(np.asarray(image, dtype=np.float32), mask=valid)[valid].astype(np.float64)
    cluster = segmentation.labels[valid].astype(np.int64)
    low, high = np.percentile(lab, [0.5, 99.5], axis=0)
    width = np.maximum(high - low, 1e-6) / bins
    index = np.clip(((lab - low) / width).astype(np.int64), 0, bins - 1)
    for channel in range(3):
        out[:, channel] = np.bincount(cluster * bins + index[:, channel], minlength=n * bins).reshape(n, bins)
    total = out.sum(axis=2, keepdims=True)
    return np.divide(out, total, out=np.zeros_like(out), where=total > 0)


def chi2_distance(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """chi^2 histogram distance ``1/2 sum (p - q)^2 / (p + q)``, mean over channels, in [0, 1].

    Parameters
    ----------
    first, second : (..., C, B) array_like
        Histograms normalised to 1 per channel.

    Returns
    -------
    (...) float64
    """
    p = np.asarray(first, dtype=np.float64)
    q = np.asarray(second, dtype=np.float64)
    total = p + q
    terms = np.divide((p - q) ** 2, total, out=np.zeros(np.broadcast_shapes(p.shape, q.shape)), where=total > 0)
    return 0.5 * terms.sum(axis=-1).mean(axis=-1)


def _nearest_others(tree: cKDTree, queries: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``k`` nearest tree points to each query, the query's own index excluded.

    Query ``i`` is tree point ``i`` (both are indexed alike). Returns distances and indices (m, k).
    """
    m = len(queries)
    distance, index = tree.query(queries, k=k + 1)
    distance = distance.reshape(m, k + 1)
    index = index.reshape(m, k + 1)
    distance = np.where(index == np.arange(m)[:, None], np.inf, distance)
    order = np.argsort(distance, axis=1, kind="stable")[:, :k]
    return np.take_along_axis(distance, order, axis=1), np.take_along_axis(index, order, axis=1)


def _local_sums(pairs: np.ndarray, distance: np.ndarray, k: int, n: int) -> np.ndarray:
    """Per source cluster, the sum of the ``k`` smallest ``distance`` over its ``pairs`` (P, 2)."""
    if not len(pairs):
        return np.zeros(n)
    # One sort on (source, distance): the distance mapped into [0, 1/2) and added to the source id.
    key = pairs[:, 0] + 0.5 * distance / max(float(distance.max()), np.finfo(np.float64).tiny)
    order = np.argsort(key)
    source = pairs[order, 0]
    first = np.searchsorted(source, source, side="left")
    rank = np.arange(len(source)) - first
    keep = rank < k
    return np.bincount(source[keep], weights=distance[order][keep], minlength=n)


def _unary_terms(r0: np.ndarray, r1: np.ndarray, centroids: np.ndarray, radius: float,
                 config: ShadowConfig) -> tuple[np.ndarray, np.ndarray]:
    """Unary costs (n, 2) and the rule of each (Eqs. 8-13)."""
    n = len(r0)
    rule = np.full(n, UNARY_RULES.index("no_samples"), dtype=np.int8)
    unary = np.full((n, 2), config.l_eq)                                   # Eq. 13 unless decided
    have = np.flatnonzero(np.isfinite(r0).all(axis=1))
    rule[have] = UNARY_RULES.index("equal")
    m = len(have)
    if m < 2:
        return unary, rule
    k = min(config.k, m - 1)
    a0, a1 = r0[have], r1[have]
    d01, _ = _nearest_others(cKDTree(a1), a0, k)  # D_01(s, t) = |R_s(0) - R_t(1)|   (Eq. 6)
    d10, _ = _nearest_others(cKDTree(a0), a1, k)  # D_10(s, t) = |R_s(1) - R_t(0)|
    h0 = d01.sum(axis=1)                           # Eq. 8
    h1 = d10.sum(axis=1)                           # Eq. 9
    total = h0 + h1
    with np.errstate(invalid="ignore", divide="ignore"):
        shadow = h0 / total < config.tau_1
        lit = h1 / total < config.tau_1
    rest = np.flatnonzero(~shadow & ~lit)  # includes H_0 = H_1 = 0 (two perfect partners)
    local_shadow = np.zeros(m, dtype=bool)
    local_lit = np.zeros(m, dtype=bool)
    if len(rest) and radius > 0:
        # H'_0, H'_1: the same sums over the clusters whose centroid is within `radius` (Eq. 12).
        near = cKDTree(centroids[have[rest]]).sparse_distance_matrix(cKDTree(centroids[have]), radius,
                                                                    output_type="ndarray")
        s, t = rest[near["i"].astype(np.int64)], near["j"].astype(np.int64)
        s, t = s[s != t], t[s != t]
        pairs = np.stack([s, t], axis=1)
        h0_local = _local_sums(pairs, np.linalg.norm(a0[s] - a1[t], axis=1), k, m)
        h1_local = _local_sums(pairs, np.linalg.norm(a1[s] - a0[t], axis=1), k, m)
        both = (h0 + h1 + h0_local + h1_local)[rest]
        with np.errstate(invalid="ignore", divide="ignore"):
            local_lit[rest] = (h1 + h1_local)[rest] / both < config.tau_1      # Eq. 12
            local_shadow[rest] = (h0 + h0_local)[rest] / both < config.tau_1  # Eq. 12 for H_0
    for mask, name, label in ((shadow, "shadow", SHADOW), (lit, "lit", LIT), (local_shadow, "local_shadow", SHADOW),
                              (local_lit, "local_lit", LIT)):
        index = have[mask]
        rule[index] = UNARY_RULES.index(name)
        unary[index, label] = config.l_0                                   # Eqs. 10, 11 (and 12)
        unary[index, 1 - label] = config.l_1
    return unary, rule


def _reflectance_edges(r0: np.ndarray, r1: np.ndarray, k: int) -> np.ndarray:
    """Pairs ``(s, t)``, ``s < t``, joining each cluster to its ``k`` nearest in ``min(D_00, D_11)``."""
    have = np.flatnonzero(np.isfinite(r0).all(axis=1))
    m = len(have)
    if m < 2:
        return np.zeros((0, 2), dtype=np.int64)
    k = min(k, m - 1)
    a0, a1 = r0[have], r1[have]
    # The k smallest of min(D_00, D_11) are among the k nearest in D_00 or in D_11.
    _, near0 = _nearest_others(cKDTree(a0), a0, k)
    _, near1 = _nearest_others(cKDTree(a1), a1, k)
    candidates = np.sort(np.concatenate([near0, near1], axis=1), axis=1)
    source = np.arange(m)[:, None]
    distance = np.minimum(np.linalg.norm(a0[source] - a0[candidates], axis=2),   # D_00
                          np.linalg.norm(a1[source] - a1[candidates], axis=2))   # D_11
    duplicate = np.zeros(candidates.shape, dtype=bool)
    duplicate[:, 1:] = candidates[:, 1:] == candidates[:, :-1]
    distance[duplicate] = np.inf
    best = np.take_along_axis(candidates, np.argsort(distance, axis=1, kind="stable")[:, :k], axis=1)
    s = np.repeat(np.arange(m), k)
    t = best.ravel()
    pairs = np.stack([have[np.minimum(s, t)], have[np.maximum(s, t)]], axis=1)
    return np.unique(pairs, axis=0)


def build_mrf(
    r0: np.ndarray,
    r1: np.ndarray,
    centroids: np.ndarray,
    adjacency: np.ndarray,
    colour_distance: np.ndarray,
    *,
    radius: float,
    config: ShadowConfig | None = None,
) -> tuple[ShadowMRF, np.ndarray, dict[str, float]]:
    """The unary and pairwise terms of Eq. 7 from per-cluster quantities.

    Parameters
    ----------
    r0, r1 : (n, 3) array_like
        ``R(0)`` and ``R(1)`` per cluster; NaN rows for clusters without samples.
    centroids : (n, 2) array_like
        Cluster centroids, pixels.
    adjacency : (A, 2) array_like of int
        Pairs of touching clusters.
    colour_distance : (A,) array_like
        chi^2 distance of their colour histograms.
    radius : float
        Local-search radius, pixels (Eq. 12).
    config : ShadowConfig, optional

    Returns
    -------
    mrf : ShadowMRF
    unary_rule : (n,) int8
        Index into :data:`UNARY_RULES`.
    timings : dict
        Seconds for ``unary`` and ``pairwise``.
    """
    config = config or ShadowConfig()
    r0 = np.asarray(r0, dtype=np.float64)
    r1 = np.asarray(r1, dtype=np.float64)
    n = len(r0)
    if r0.shape != (n, 3) or r1.shape != (n, 3):
        raise ValueError(f"r0 and r1 must have shape (n, 3), got {r0.shape} and {r1.shape}")
    if config.distance == "log":
        with np.errstate(invalid="ignore"):
            r0, r1 = np.log(np.maximum(r0, LOG_FLOOR)), np.log(np.maximum(r1, LOG_FLOOR))
    centroids = as_array(centroids, "centroids", shape=(n, 2), dtype=np.float64)
    adjacency = as_array(adjacency, "adjacency", shape=(None, 2), dtype=np.int64)
    colour_distance = as_array(colour_distance, "colour_distance", shape=(len(adjacency),), dtype=np.float64)
    start = time.perf_counter()
    unary, rule = _unary_terms(r0, r1, centroids, radius, config)
    middle = time.perf_counter()
    reflectance_pairs = _reflectance_edges(r0, r1, config.k)
    strong = np.array([config.l_0, config.l_1, config.l_1, config.l_0])         # Eq. 14
    similar = np.array([config.l_np, config.l_p, config.l_p, config.l_np])      # Eq. 15
    equal = np.full(4, config.l_eq)                                             # Eq. 16
    is_similar = colour_distance < config.tau_c
    edges = np.concatenate([reflectance_pairs, np.sort(adjacency, axis=1)])
    pairwise = np.concatenate([np.broadcast_to(strong, (len(reflectance_pairs), 4)),
                               np.where(is_similar[:, None], similar, equal)])
    kind = np.concatenate([np.zeros(len(reflectance_pairs), np.int8), np.where(is_similar, 1, 2).astype(np.int8)])
    mrf = ShadowMRF(unary=unary, edges=edges, pairwise=pairwise, edge_kind=kind)
    end = time.perf_counter()
    return mrf, rule, {"unary": middle - start, "pairwise": end - middle}


def label_shadows(
    image: np.ndarray,
    quantities: PixelQuantities,
    segmentation: Segmentation,
    sun_radiance: np.ndarray,
    *,
    config: ShadowConfig | None = None,
) -> ShadowLabels:
    """Label the clusters of one view as lit or in shadow (paper Sec. 6.1, Eqs. 6-16).

    Parameters
    ----------
    image : (H, W, 3) array_like
        The view's linear RGB image (finite on the segmented pixels).
    quantities : PixelQuantities
        The view's per-pixel Step-1 quantities (:func:`mvintrinsic.pixels.pixel_quantities`).
    segmentation : Segmentation
        Clusters of the view (:func:`mvintrinsic.segmentation.segment`, typically with
        ``mask=quantities.valid``).
    sun_radiance : (3,) array_like
        ``L_sun`` from Step 2, shading units.
    config : ShadowConfig, optional
        Defaults to the paper's parameters.

    Returns
    -------
    ShadowLabels

    Raises
    ------
    ValueError
        If the shapes of ``image``, ``quantities`` and ``segmentation`` disagree or ``sun_radiance``
        is not a finite, non-negative RGB triple.
    TypeError
        If an argument has the wrong type.
    """
    config = config_or_default(config, ShadowConfig)
    if not isinstance(quantities, PixelQuantities):
        raise TypeError(f"quantities must be PixelQuantities, got {describe(quantities)}")
    if not isinstance(segmentation, Segmentation):
        raise TypeError(f"segmentation must be a Segmentation, got {describe(segmentation)}")
    shape = quantities.shape
    image = as_array(image, "image", shape=(*shape, 3), dtype=np.float64, finite=False)
    if segmentation.shape != shape:
        raise ValueError(f"segmentation must have shape {shape} (the quantities'), got {segmentation.shape}")
    sun_radiance = as_array(sun_radiance, "sun_radiance", shape=(3,), dtype=np.float64)
    if (sun_radiance < 0).any():
        raise ValueError(f"sun_radiance must be non-negative, got {sun_radiance.tolist()}")
    n = segmentation.n_segments
    timings: dict[str, float] = {}

    start = time.perf_counter()
    r0, r1, samples, small = cluster_reflectances(image, quantities, segmentation, sun_radiance, config=config)
    timings["reflectance"] = time.perf_counter() - start

    start = time.perf_counter()
    rows, cols = np.indices(shape)
    centroids = segmentation.means(np.stack([rows, cols], axis=2))  # no cluster is empty
    histograms = lab_histograms(image, segmentation, bins=config.histogram_bins)
    adjacency = segmentation.adjacency.astype(np.int64)
    colour = chi2_distance(histograms[adjacency[:, 0]], histograms[adjacency[:, 1]])
    radius = config.local_radius * float(np.hypot(*shape))
    colour_seconds = time.perf_counter() - start
    mrf, rule, parts = build_mrf(r0, r1, centroids, adjacency, colour, radius=radius, config=config)
    timings["unary"] = parts["unary"]
    timings["pairwise"] = parts["pairwise"] + colour_seconds

    start = time.perf_counter()
    # Tie-break among the minimisers of Eq. 7 (module docstring): priors of total weight
    # tie_break_weight, spread by area. "lit"/"shadow" give the extreme minimisers.
    weight = config.tie_break_weight * segmentation.sizes / max(int(segmentation.sizes.sum()), 1)
    zero = np.zeros(n)
    most_lit, _ = graph_cut(mrf, prior=np.stack([weight, zero], axis=1))
    most_shadow, _ = graph_cut(mrf, prior=np.stack([zero, weight], axis=1))
    undetermined = most_lit != most_shadow
    if config.tie_break == "lit":
        prior, cluster_labels = np.stack([weight, zero], axis=1), most_lit
    elif config.tie_break == "shadow":
        prior, cluster_labels = np.stack([zero, weight], axis=1), most_shadow
    else:
        proxy = _proxy_visibility(quantities, segmentation)
        prior = np.stack([weight * proxy, weight * (1.0 - proxy)], axis=1)
        cluster_labels, _ = graph_cut(mrf, prior=prior)
    energy = mrf.energy(cluster_labels)
    timings["graph_cut"] = time.perf_counter() - start

    start = time.perf_counter()
    labels = np.full(shape, SHADOW_LABELS["undecided"], dtype=np.uint8)
    inside = segmentation.valid & quantities.valid
    codes = np.where(cluster_labels == LIT, SHADOW_LABELS["lit"], SHADOW_LABELS["shadow"]).astype(np.uint8)
    labels[inside] = codes[segmentation.labels[inside]]
    timings["labels"] = time.perf_counter() - start

    counts = {name: int((rule == i).sum()) for i, name in enumerate(UNARY_RULES)}
    counts.update({f"{name}_edges": int((mrf.edge_kind == i).sum()) for i, name in enumerate(EDGE_KINDS)})
    counts.update(small_clusters=int(small.sum()), lit_clusters=int((cluster_labels == LIT).sum()),
                  shadow_clusters=int((cluster_labels == SHADOW).sum()), undetermined_clusters=int(undetermined.sum()))
    logger.info("%s: %d clusters, unary %s, energy %.2f, %d in shadow", quantities.stem, n,
                {name: counts[name] for name in UNARY_RULES}, energy, counts["shadow_clusters"])
    for array in (r0, r1, samples, rule, prior, undetermined, cluster_labels, labels):
        array.flags.writeable = False
    return ShadowLabels(
        stem=quantities.stem, cluster_labels=cluster_labels, labels=labels, energy=energy, mrf=mrf, prior=prior,
        undetermined=undetermined,
        reflectance_shadow=r0, reflectance_lit=r1, samples=samples, unary_rule=rule,
        counts=MappingProxyType(counts), timings=MappingProxyType(timings),
    )


def _proxy_visibility(quantities: PixelQuantities, segmentation: Segmentation) -> np.ndarray:
    """Median proxy visibility ``~v`` of each cluster over its valid pixels (1 where it has none)."""
    inside = segmentation.valid & quantities.valid
    median = _group_median(segmentation.labels[inside].astype(np.int64),
                           quantities.visibility[inside].astype(np.float64)[:, None], segmentation.n_segments)[:, 0]
    return np.where(np.isfinite(median), median, 1.0)
