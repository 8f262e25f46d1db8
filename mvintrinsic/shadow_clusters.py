"""Which shadow pixels the relighting caster lifts: shadow pixels, the paper's cluster rule and its local form (Sec. 8).

**Shadow pixels** (:func:`shadow_pixels`): Step 3's shadow labels, or ``v_sun < tau_s`` (0.8).

"Finally, we discard shadow clusters of less than 100 pixels and clusters where less than 30% of the pixels
yield an intersection" with the proxy [1]_ (:func:`kept_clusters`): a cluster whose sun rays find no occluder is
a mislabelling, and its shadow cannot be lifted. The rule judges each 8-connected cluster as a whole.

**Supported parts** (:func:`supported_parts`, beyond the paper, :attr:`RelightConfig.support_radius
<mvintrinsic.caster.RelightConfig>`). Step 3's labels join shadows that are apart in the truth into one
cluster: a ledge's shadow whose rays hit the proxy touches a crown's, whose rays miss it, and both touch dark
materials labelled shadow. The whole is then judged by its mean: on the 480x360 demo the pipeline's largest
cluster holds 18-22k pixels per view (68-72% truly shadowed) with 16-18% of its rays finding an occluder, and is
dropped, with the supported parts the true labels keep as clusters of their own (hit shares 0.5-0.66). A part is
kept when, within ``radius`` pixels, the kept share of the cluster's pixels whose rays find an occluder is at
least the rule's share, and the part, 8-connected, has the rule's size and share. The relighter treats these
parts as it treats the clusters kept thanks to :attr:`~mvintrinsic.caster.RelightConfig.lost_occluders`: the
expected image over the two hypotheses (a shadow, or a mislabelling the paper drops;
:attr:`OccupancyConfig.belief <mvintrinsic.photo_occupancy.OccupancyConfig>`).

References
----------
.. [1] S. Duchêne et al., "Multi-View Intrinsic Images of Outdoors Scenes with an Application to Relighting",
   ACM Transactions on Graphics 34(5), 2015, Sec. 8.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from ._validation import as_array, is_real
from .results import SHADOW_LABELS

__all__ = ["TAU_S", "kept_clusters", "shadow_pixels", "supported_parts"]

#: 8-connectivity of the shadow clusters.
_EIGHT = np.ones((3, 3), dtype=bool)

#: The paper's visibility threshold of the shadow pixels: "We used tau_s = 0.8 for all our results."
TAU_S = 0.8


def shadow_pixels(labels: np.ndarray, v_sun: np.ndarray | None, *, tau_s: float = TAU_S) -> np.ndarray:
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
    labels = as_array(labels, "labels", shape=(None, None), dtype=np.int64)
    codes = list(SHADOW_LABELS.values())
    bad = ~np.isin(labels, codes)
    if bad.any():
        raise ValueError(f"labels may only hold {codes}, got {np.unique(labels[bad])[:5].tolist()}")
    if not is_real(tau_s) or not 0.0 <= tau_s <= 1.0:
        raise ValueError(f"tau_s must be a number in [0, 1], got {tau_s!r}")
    shadow = labels == SHADOW_LABELS["shadow"]
    if v_sun is not None:
        v = as_array(v_sun, "v_sun", shape=labels.shape, dtype=np.float64, finite=False)
        with np.errstate(invalid="ignore"):
            shadow |= v < tau_s  # NaN < tau_s is False
    return shadow & (labels != SHADOW_LABELS["undecided"])


def kept_clusters(shadow: np.ndarray, hit: np.ndarray, min_cluster: int, min_share: float
                  ) -> tuple[np.ndarray, int, int, int]:
    """The paper's cluster rule (Sec. 8).

    Parameters
    ----------
    shadow, hit : (H, W) bool ndarray
        The shadow pixels, and those whose sun ray found an occluder.
    min_cluster : int
        Least pixels of a kept cluster (the paper's 100).
    min_share : float
        Least share of ``hit`` in a kept cluster (the paper's 0.3); a cluster without a hit is never kept.

    Returns
    -------
    kept : (H, W) bool ndarray
        The pixels of the 8-connected clusters of ``shadow`` that the rule keeps.
    n_clusters, n_small, n_unsupported : int
        The clusters, those dropped as small and those dropped for too few hits.
    """
    clusters, n_clusters = ndimage.label(shadow, structure=_EIGHT)
    size = np.bincount(clusters.ravel(), minlength=n_clusters + 1)
    n_hits = np.bincount(clusters.ravel(), weights=hit.ravel(), minlength=n_clusters + 1)
    small = size < min_cluster
    unsupported = ~small & ((n_hits / np.maximum(size, 1) < min_share) | (n_hits == 0))
    small[0] = unsupported[0] = False  # label 0 is the background
    keep = ~(small | unsupported) & (np.arange(n_clusters + 1) > 0)
    return keep[clusters], n_clusters, int(small.sum()), int(unsupported.sum())


def supported_parts(shadow: np.ndarray, hit: np.ndarray, min_cluster: int, min_share: float, radius: int
                    ) -> np.ndarray:
    """The parts of the shadow clusters whose neighbourhood's rays find occluders (module docstring).

    Parameters
    ----------
    shadow, hit : (H, W) bool ndarray
        As :func:`kept_clusters`.
    min_cluster : int
        Least pixels of a kept part.
    min_share : float
        Least share of ``hit`` among the shadow pixels of a pixel's ``(2 radius + 1)``-pixel square window, and in
        a kept part.
    radius : int
        Half-width of the window, pixels; 0: no part (the paper's rule alone).

    Returns
    -------
    (H, W) bool ndarray
        The supported parts; pixels of ``shadow`` only. The caller adds the clusters :func:`kept_clusters` keeps.
    """
    if radius <= 0 or not shadow.any():
        return np.zeros(shadow.shape, dtype=bool)
    size = 2 * radius + 1
    hits = ndimage.uniform_filter((hit & shadow).astype(np.float32), size, mode="constant")
    pixels = ndimage.uniform_filter(shadow.astype(np.float32), size, mode="constant")
    # The window means share the factor 1 / size^2: compare the hits with the share of the shadow pixels.
    local = shadow & (hits > 0) & (hits >= min_share * pixels - 1e-6)
    return kept_clusters(local, hit, min_cluster, min_share)[0]
