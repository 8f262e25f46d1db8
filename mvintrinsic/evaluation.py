"""Scoring a result folder against the ground truth of a scene (the edge: reads files, uses metrics).

A synthetic scene folder may hold a ``gt/`` folder (``docs/formats.md``, "Ground truth"):
per-view reflectance, shading, sun visibility, sky mask, optionally the split of the shading into
the direct sun term and the rest, and ``gt/lighting.json``. This module

* reads it into :class:`GroundTruth` objects (:func:`read_ground_truth`) and a
  :class:`~mvintrinsic.results.Lighting` (:func:`read_ground_truth_lighting`);
* expresses it as a result (:func:`ground_truth_decomposition`), so that the scoring can be
  checked end to end: the ground truth written as a result folder and scored must get LMSE 0 and
  BER 0;
* scores a result folder written by :func:`mvintrinsic.io.save_decomposition` (:func:`evaluate`)
  with the measures of :mod:`mvintrinsic.metrics`: the LMSE of Grosse et al. [1]_ (with the
  normalisation of Bell et al. [2]_) of reflectance and shading and their mean (Grosse's score),
  the global scale-invariant MSE, the balanced error rate of the shadow labels, and PSNR / SSIM of
  the reconstruction ``R * S`` against the photo and of the shading against the true shading.

These are the measures with which Duchêne et al. [3]_ compare decompositions of outdoor scenes.
Everything returned by :func:`evaluate` is JSON-ready (Python ``float``/``int``/``str``/``None``,
no NumPy scalars, no infinities).

References
----------
.. [1] R. Grosse, M. K. Johnson, E. H. Adelson and W. T. Freeman, "Ground truth dataset and
   baseline evaluations for intrinsic image algorithms", in *Proc. ICCV*, pp. 2335-2342, 2009.
.. [2] S. Bell, K. Bala and N. Snavely, "Intrinsic Images in the Wild", *ACM Transactions on
   Graphics (Proc. SIGGRAPH)*, 33(4), article 159, 2014.
.. [3] S. Duchêne, C. Riant, G. Chaurasia, J. Lopez-Moreno, P.-Y. Laffont, S. Popov, A. Bousseau
   and G. Drettakis, "Multi-View Intrinsic Images of Outdoors Scenes with an Application to
   Relighting", *ACM Transactions on Graphics*, 34(5), article 164, 2015.
"""

from __future__ import annotations

import glob
import json
import math
import os
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from . import metrics
from ._validation import as_array, describe
from ._version import __version__
from .io import IMAGE_EXTENSIONS, SceneError, load_decomposition, read_image, read_image_for_size, read_scene_json
from .pixels import masked_box_mean
from .results import SHADOW_LABELS, Decomposition, IntrinsicLayers, Lighting
from .scene import Sun, valid_pixels
from .sun_position import sun_from_time

__all__ = [
    "DATA_RANGE_PERCENTILE",
    "METRIC_KEYS",
    "PSNR_MAX_DB",
    "REFLECTANCE_MIN",
    "SUN_APERTURE_DEG",
    "GroundTruth",
    "evaluate",
    "ground_truth_decomposition",
    "read_ground_truth",
    "read_ground_truth_lighting",
    "umbra_mask",
]

#: Pixels whose true reflectance is at or below this value in any channel are not scored: the true
#: shading there (``image / reflectance``) is undefined or dominated by noise. The renderer writes 0
#: where the reflectance is 0, and anti-aliased silhouette pixels against the sky get an albedo AOV
#: of a few 1e-4 with the sky's radiance in the image: one such pixel (true shading 328, 300 times
#: its neighbours') set the demo's view_005 shading LMSE to 0.63 for any estimate at the former
#: threshold 1e-4. 0.01 excludes 0.24% (demo) and 0.22% (dev_courtyard) of the pixels with a
#: non-zero albedo.
REFLECTANCE_MIN = 0.01
#: PSNR ``data_range`` is this percentile of the reference over the scored pixels (all channels):
#: HDR photos have no natural peak value, and the maximum is set by a few specular or sun-lit
#: pixels, so a robust high percentile is used instead.
DATA_RANGE_PERCENTILE = 99.0
#: PSNR is reported clipped to this value. An exact match has an infinite PSNR, which JSON cannot
#: hold; float32 rounding alone stays below ~150 dB, so the clip only ever catches exact matches.
PSNR_MAX_DB = 200.0
#: Per-view scores averaged into ``"mean"`` by :func:`evaluate`.
METRIC_KEYS = (
    "lmse_reflectance",
    "lmse_shading",
    "lmse_score",
    "si_mse_reflectance",
    "si_mse_shading",
    "ber",
    "ber_excluded_fraction",
    "reconstruction_psnr",
    "reconstruction_ssim",
    "shading_psnr",
    "shading_ssim",
)

#: Per-view ground-truth layers: (folder under gt/, file extension, required).
_GT_LAYERS = (
    ("reflectance", ".exr", True),
    ("shading", ".exr", True),
    ("sun_visibility", ".png", True),
    ("sky_mask", ".png", True),
    ("sun_shading", ".exr", False),
    ("env_shading", ".exr", False),
)


# ---------------------------------------------------------------------------------------------
# ground truth
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class GroundTruth:
    """The ground truth of one view (``gt/`` of a scene folder, ``docs/formats.md``).

    Parameters
    ----------
    stem : str
        View name.
    reflectance : (H, W, 3) float32
        Diffuse albedo, linear RGB.
    shading : (H, W, 3) float32
        ``image / reflectance`` per channel, shading units (0 where the reflectance is 0).
    sun_visibility : (H, W) bool
        True where the pixel is lit by the sun, False in cast or attached shadow.
    sky_mask : (H, W) bool
        True where the pixel sees the sky.
    sun_shading : (H, W, 3) float32, optional
        Direct sun term ``v_sun * L_sun * max(0, cos w_sun)`` (it *includes* the visibility).
    env_shading : (H, W, 3) float32, optional
        The rest, ``shading - sun_shading``: sky and all indirect light, not split.

    Notes
    -----
    Arrays are stored as read-only copies. Non-finite values are kept (they are excluded when
    scoring); shapes must agree.
    """

    stem: str
    reflectance: np.ndarray
    shading: np.ndarray
    sun_visibility: np.ndarray
    sky_mask: np.ndarray
    sun_shading: np.ndarray | None = None
    env_shading: np.ndarray | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.stem, str) or not self.stem:
            raise ValueError(f"stem must be a non-empty string, got {describe(self.stem)}")
        reflectance = as_array(self.reflectance, "reflectance", shape=(None, None, 3), dtype=np.float32, finite=False)
        h, w = reflectance.shape[:2]
        object.__setattr__(self, "reflectance", reflectance)
        for name in ("shading", "sun_shading", "env_shading"):
            value = getattr(self, name)
            if value is not None or name == "shading":
                value = as_array(value, name, shape=(h, w, 3), dtype=np.float32, finite=False)
                object.__setattr__(self, name, value)
        for name in ("sun_visibility", "sky_mask"):
            value = np.asarray(getattr(self, name))
            if value.dtype != np.bool_:
                raise TypeError(f"{name} must be a boolean array, got {describe(value)}")
            object.__setattr__(self, name, as_array(value, name, shape=(h, w), dtype=np.bool_))

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)``."""
        return self.reflectance.shape[:2]

    @property
    def valid(self) -> np.ndarray:
        """(H, W) bool: pixels where the ground truth can be scored.

        Not sky, all layers finite, and the true reflectance above :data:`REFLECTANCE_MIN` in every
        channel (below it the true shading is undefined).
        """
        ok = ~self.sky_mask & np.isfinite(self.reflectance).all(axis=2) & np.isfinite(self.shading).all(axis=2)
        with np.errstate(invalid="ignore"):
            ok &= (self.reflectance > REFLECTANCE_MIN).all(axis=2)
        return ok

    def __repr__(self) -> str:
        h, w = self.shape
        return f"GroundTruth({self.stem!r}, {w}x{h})"


def _gt_stems(gt: Path) -> list[str]:
    """Stems of the views with a ground-truth reflectance, sorted (``gt/reflectance/**.exr``)."""
    folder = gt / "reflectance"
    if not folder.is_dir():
        raise SceneError(folder, "missing: the ground truth needs gt/reflectance/<stem>.exr for every view")
    stems = sorted(p.relative_to(folder).with_suffix("").as_posix() for p in folder.rglob("*.exr") if p.is_file())
    if not stems:
        raise SceneError(folder, "holds no .exr file: no view has ground truth")
    return stems


def _gt_folder(scene_folder: os.PathLike | str) -> Path:
    root = Path(scene_folder)
    if not root.is_dir():
        raise SceneError(root, "scene folder not found")
    gt = root / "gt"
    if not gt.is_dir():
        raise SceneError(gt, "no ground truth: the scene folder has no gt/ folder (docs/formats.md)")
    return gt


def _read_layer(path: Path, *, binary: bool) -> np.ndarray:
    image, _ = read_image(path)  # raises SceneError naming the file when missing or unreadable
    if binary:
        # 8-bit masks hold 0 / 255; read_image decodes them to linear 0 / 1.
        return image[..., 0] > 0.5
    return image


def read_ground_truth(scene_folder: os.PathLike | str, *, views: Sequence[str] | None = None) -> dict[str, GroundTruth]:
    """Read the per-view ground truth of a scene folder.

    Parameters
    ----------
    scene_folder : path-like
        Scene folder holding ``gt/`` (``docs/formats.md``).
    views : sequence of str, optional
        Stems of the views to read, in this order. Default: every view with a
        ``gt/reflectance/<stem>.exr``, sorted.

    Returns
    -------
    dict of str to GroundTruth
        By stem. ``sun_shading`` / ``env_shading`` are None when their files are absent.

    Raises
    ------
    SceneError
        Naming the folder or file: no ``gt/`` folder, a required layer (reflectance, shading,
        sun_visibility, sky_mask) missing or unreadable for a view, or layers of different sizes.
    """
    gt = _gt_folder(scene_folder)
    if views is None:
        stems = _gt_stems(gt)
    else:
        if isinstance(views, str):
            raise TypeError("views must be a sequence of stems, not a single string")
        stems = list(views)
    out: dict[str, GroundTruth] = {}
    for stem in stems:
        layers: dict[str, np.ndarray | None] = {}
        shape = None
        for name, ext, required in _GT_LAYERS:
            path = gt / name / f"{stem}{ext}"
            if not path.is_file():
                if required:
                    raise SceneError(path, f"ground-truth {name} of view {stem!r} not found")
                layers[name] = None
                continue
            layer = _read_layer(path, binary=ext == ".png")
            if shape is None:
                shape = layer.shape[:2]
            elif layer.shape[:2] != shape:
                raise SceneError(
                    path, f"is {layer.shape[1]}x{layer.shape[0]} pixels, other layers are {shape[1]}x{shape[0]}"
                )
            layers[name] = layer
        out[stem] = GroundTruth(stem, **layers)
    return out


def _gt_sun(root: Path) -> tuple[Sun | None, np.ndarray]:
    """The true sun (or None when the scene gives it only by clicks) and the up vector.

    ``gt/lighting.json["sun_direction"]`` wins when present; otherwise ``scene.json``'s
    ``sun_direction`` or ``sun_time``. Clicks are an estimate, not a ground truth.
    """
    settings = read_scene_json(root / "scene.json")
    up = settings["up"]
    file = root / "gt" / "lighting.json"
    if file.is_file():
        data = _read_json(file)
        if "sun_direction" in data:
            try:
                return Sun(data["sun_direction"]), up
            except (TypeError, ValueError) as exc:
                raise SceneError(file, f"sun_direction: {exc}") from exc
    form = settings["sun_form"]
    if form == "sun_direction":
        return Sun(settings[form]), up
    if form == "sun_time":
        value = settings[form]
        sun = sun_from_time(
            value["datetime"],
            value["latitude"],
            value["longitude"],
            north=value["north"],
            up=up,
            altitude=value["altitude"],
        )
        return sun, up
    return None, up


def _read_json(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise SceneError(path, f"not valid JSON ({exc})") from None
    if not isinstance(data, dict):
        raise SceneError(path, f"must hold a JSON object, got {type(data).__name__}")
    return data


def read_ground_truth_lighting(scene_folder: os.PathLike | str) -> Lighting:
    """Read the true lighting: ``gt/lighting.json`` and the sun direction.

    Parameters
    ----------
    scene_folder : path-like
        Scene folder holding ``scene.json`` and ``gt/lighting.json``.

    Returns
    -------
    Lighting
        ``sun_radiance`` (3,) from ``gt/lighting.json`` (``L_sun`` in shading units); the sun
        direction (unit, toward the sun, world frame) from ``gt/lighting.json["sun_direction"]``
        when present, else from ``scene.json`` (``sun_direction`` or ``sun_time``); ``up`` from
        ``scene.json``. No sky model, horizon plane or environment map.

    Raises
    ------
    SceneError
        Naming the file: no ``gt/``, ``gt/lighting.json`` missing or malformed (no valid
        ``sun_radiance``), ``scene.json`` malformed, or the sun given only by clicks (no true
        direction).
    """
    root = Path(scene_folder)
    gt = _gt_folder(root)
    file = gt / "lighting.json"
    if not file.is_file():
        raise SceneError(file, "ground-truth lighting not found")
    data = _read_json(file)
    if "sun_radiance" not in data:
        raise SceneError(file, "sun_radiance is missing")
    sun, up = _gt_sun(root)
    if sun is None:
        raise SceneError(
            root / "scene.json",
            "the sun is given by clicks, which is no ground truth; add sun_direction to gt/lighting.json",
        )
    try:
        return Lighting(sun, data["sun_radiance"], up=up)
    except (TypeError, ValueError) as exc:
        raise SceneError(file, f"sun_radiance: {exc}") from exc


def ground_truth_decomposition(scene_folder: os.PathLike | str, *, views: Sequence[str] | None = None) -> Decomposition:
    """The ground truth of a scene expressed as a result (a :class:`Decomposition`).

    Scoring it with :func:`evaluate` must give LMSE 0, si-MSE 0 and BER 0: the self-check of the
    evaluation.

    Parameters
    ----------
    scene_folder : path-like
        Scene folder holding ``scene.json`` and ``gt/``.
    views : sequence of str, optional
        Stems to include; default every view of the ground truth.

    Returns
    -------
    Decomposition
        Per view (:class:`~mvintrinsic.results.IntrinsicLayers`):

        * ``reflectance`` = true reflectance;
        * ``visibility`` = true sun visibility (0 or 1);
        * ``sun_shading`` (``S_sun``, *without* visibility) = ``gt/sun_shading`` where lit.
          In shadow the true ``S_sun = L_sun max(0, cos)`` is not recorded (``gt/sun_shading``
          holds ``v_sun S_sun = 0`` there, and the normals are not in ``gt/``), so it is set to 0;
          with visibility 0 this does not change ``S_tot``;
        * ``sky_shading`` = ``gt/shading - visibility * sun_shading``, i.e. ``gt/env_shading``:
          the ground truth does not split sky and indirect light, so all of it goes to the sky
          term. It is recomputed from ``gt/shading`` rather than read from ``gt/env_shading``
          because the files are stored as float16 and ``sun_shading + env_shading`` differs from
          ``shading`` by the rounding (up to ~3e-3 on dev_courtyard); this way ``S_tot`` equals
          ``gt/shading`` exactly (in float32). Without ``gt/sun_shading`` the whole shading is
          put in the sky term;
        * ``indirect_shading`` = 0;
        * ``shadow_labels`` = 255 lit, 0 shadow, 128 on sky.

        Sky pixels and pixels with a non-finite true layer get 0 in every layer and label 128.
        ``lighting`` comes from :func:`read_ground_truth_lighting`; ``config`` records the source.

    Raises
    ------
    SceneError
        As :func:`read_ground_truth` and :func:`read_ground_truth_lighting`.
    """
    root = Path(scene_folder)
    truth = read_ground_truth(root, views=views)
    lighting = read_ground_truth_lighting(root)
    layers = {}
    for stem, gt in truth.items():
        known = ~gt.sky_mask & np.isfinite(gt.reflectance).all(axis=2) & np.isfinite(gt.shading).all(axis=2)
        lit = gt.sun_visibility & known
        if gt.sun_shading is not None:
            known &= np.isfinite(gt.sun_shading).all(axis=2)
            lit &= known
            sun = np.where(lit[..., None], gt.sun_shading, np.float32(0.0))
        else:
            sun = np.zeros_like(gt.shading)
        visibility = lit.astype(np.float32)
        env = np.where(known[..., None], gt.shading - visibility[..., None] * sun, np.float32(0.0))
        labels = np.where(lit, SHADOW_LABELS["lit"], SHADOW_LABELS["shadow"]).astype(np.uint8)
        labels[~known] = SHADOW_LABELS["undecided"]
        layers[stem] = IntrinsicLayers(
            stem,
            reflectance=np.where(known[..., None], gt.reflectance, np.float32(0.0)),
            sun_shading=sun,
            sky_shading=env,
            indirect_shading=np.zeros_like(env),
            visibility=visibility,
            shadow_labels=labels,
        )
    config = {"source": "ground truth", "scene": str(root.resolve())}
    return Decomposition(layers, lighting, config=config)


# ---------------------------------------------------------------------------------------------
# scoring
# ---------------------------------------------------------------------------------------------
def _input_image(root: Path, stem: str, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, Path]:
    """The photo of a view (``images/<stem>.<ext>``) and its valid-pixel mask; ``shape`` (H, W)
    is the size the scene expects (:func:`~mvintrinsic.io.read_image_for_size`)."""
    target = root / "images" / stem
    found = [
        p
        for p in target.parent.glob(glob.escape(target.name) + ".*")
        if p.suffix.lower() in IMAGE_EXTENSIONS and p.with_suffix("").name == target.name
    ]
    if not found:
        raise SceneError(target, f"no input image for view {stem!r} (images/{stem}.<ext>, ext in {IMAGE_EXTENSIONS})")
    if len(found) > 1:
        raise SceneError(target, f"several input images for view {stem!r}: {sorted(p.name for p in found)}")
    image, saturation = read_image_for_size(found[0], width=shape[1], height=shape[0])
    return image, valid_pixels(image, saturation=saturation), found[0]


def _capped_psnr(estimate: np.ndarray, truth: np.ndarray, mask: np.ndarray, data_range: float) -> float:
    return float(min(metrics.psnr(estimate, truth, mask=mask, data_range=data_range), PSNR_MAX_DB))


def _percentile_range(reference: np.ndarray, mask: np.ndarray) -> float | None:
    """:data:`DATA_RANGE_PERCENTILE` of ``reference`` over the masked pixels, or None if not > 0."""
    value = float(np.percentile(reference[mask], DATA_RANGE_PERCENTILE))
    return value if value > 0 else None


def _channel_scale(estimate: np.ndarray, truth: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Least-squares scale per channel, ``k_c = sum m t e / sum m e^2`` (0 for a zero estimate)."""
    e = estimate[mask].astype(np.float64)
    t = truth[mask].astype(np.float64)
    num, den = (t * e).sum(axis=0), (e * e).sum(axis=0)
    return np.divide(num, den, out=np.zeros_like(num), where=den > 0)


def _score_view(
    gt: GroundTruth, layers: IntrinsicLayers, image: np.ndarray, image_valid: np.ndarray, *, window: int, step: int
) -> dict[str, Any]:
    """All scores of one view (see :func:`evaluate`)."""
    reflectance, shading = layers.reflectance, layers.shading
    mask = gt.valid & np.isfinite(reflectance).all(axis=2) & np.isfinite(shading).all(axis=2)
    n = int(mask.sum())
    scores: dict[str, Any] = dict.fromkeys(METRIC_KEYS)
    scores.update(
        pixels=n,
        scored_fraction=n / mask.size,
        true_shadow_fraction=None,
        ber_single_class=None,
        reconstruction_data_range=None,
        shading_scale=None,
    )
    if n == 0:
        return scores

    # Grosse et al.'s LMSE and score; global scale-invariant MSE (per channel scale).
    lmse_r = metrics.lmse(reflectance, gt.reflectance, mask=mask, window=window, step=step)
    lmse_s = metrics.lmse(shading, gt.shading, mask=mask, window=window, step=step)
    scores.update(
        lmse_reflectance=lmse_r,
        lmse_shading=lmse_s,
        lmse_score=0.5 * (lmse_r + lmse_s),  # = metrics.lmse_score, without computing both twice
        si_mse_reflectance=metrics.si_mse(reflectance, gt.reflectance, mask=mask),
        si_mse_shading=metrics.si_mse(shading, gt.shading, mask=mask),
    )

    # Shadow labels: shadow (0) is the positive class; undecided (128) is left out of the BER.
    labels = layers.shadow_labels
    decided = mask & (labels != SHADOW_LABELS["undecided"])
    scores["ber_excluded_fraction"] = 1.0 - int(decided.sum()) / n
    if decided.any():
        true_shadow = ~gt.sun_visibility
        n_shadow = int((true_shadow & decided).sum())
        single = n_shadow in (0, int(decided.sum()))
        with warnings.catch_warnings():
            if single:  # reported through ber_single_class instead of a warning per view
                warnings.filterwarnings("ignore", message="balanced_error_rate", category=RuntimeWarning)
            scores["ber"] = metrics.balanced_error_rate(labels == SHADOW_LABELS["shadow"], true_shadow, mask=decided)
        scores["ber_single_class"] = single
        scores["true_shadow_fraction"] = n_shadow / int(decided.sum())

    # Reconstruction R * S_tot against the photo, where the photo is valid.
    recon_mask = mask & image_valid
    if recon_mask.any():
        data_range = _percentile_range(image, recon_mask)
        scores["reconstruction_data_range"] = data_range
        if data_range is not None:
            recon = layers.reconstruct()
            scores["reconstruction_psnr"] = _capped_psnr(recon, image, recon_mask, data_range)
            scores["reconstruction_ssim"] = metrics.ssim(recon, image, mask=recon_mask, data_range=data_range)

    # Shading against the true shading after a least-squares global scale per channel.
    scale = _channel_scale(shading, gt.shading, mask)
    scores["shading_scale"] = [float(k) for k in scale]
    data_range = _percentile_range(gt.shading, mask)
    if data_range is not None:
        scaled = (shading * scale).astype(np.float32)
        scores["shading_psnr"] = _capped_psnr(scaled, gt.shading, mask, data_range)
        scores["shading_ssim"] = metrics.ssim(scaled, gt.shading, mask=mask, data_range=data_range)
    return {k: (float(v) if isinstance(v, (float, np.floating)) else v) for k, v in scores.items()}


def _mean(per_view: dict[str, dict[str, Any]]) -> dict[str, float | None]:
    out: dict[str, float | None] = {}
    for key in METRIC_KEYS:
        values = [s[key] for s in per_view.values() if s[key] is not None]
        out[key] = float(np.mean(values)) if values else None
    return out


def evaluate(
    scene_folder: os.PathLike | str,
    result_folder: os.PathLike | str,
    *,
    views: Sequence[str] | None = None,
    window: int = 20,
    step: int = 10,
) -> dict[str, Any]:
    r"""Score a result folder against the ground truth of a scene.

    Parameters
    ----------
    scene_folder : path-like
        Scene folder with ``images/``, ``scene.json`` and ``gt/`` (``docs/formats.md``).
    result_folder : path-like
        Result folder written by :func:`mvintrinsic.io.save_decomposition`, read with
        :func:`mvintrinsic.io.load_decomposition` (``shading`` is ``S_tot`` derived from the layers).
    views : sequence of str, optional
        Stems to score, in this order; each must be in the result and have ground truth.
        Default: every view of the result that has ground truth, in the result's order.
    window, step : int, optional
        LMSE window side and stride in pixels; Grosse et al.'s 20 and 10 by default.

    Returns
    -------
    dict
        JSON-ready::

            {"scene", "result": str (resolved paths),
             "mvintrinsic_version", "result_version": str,
             "settings": {"window", "step", "reflectance_min", "data_range_percentile",
                          "psnr_max_db"},
             "views": {stem: scores}, "mean": {key: mean over views of METRIC_KEYS},
             "views_without_result": [gt stems the result lacks],
             "views_without_gt": [result stems with no ground truth],
             "lighting": {"sun_direction_error_deg": float or None}}

        ``scores`` of a view (None where undefined, e.g. no scored pixel):

        * ``pixels``, ``scored_fraction``: scored pixels, count and fraction of the image;
        * ``lmse_reflectance``, ``lmse_shading`` (:func:`~mvintrinsic.metrics.lmse`) and
          ``lmse_score`` :math:`= \frac12(\mathrm{LMSE}_R + \mathrm{LMSE}_S)`, Grosse's score;
        * ``si_mse_reflectance``, ``si_mse_shading`` (:func:`~mvintrinsic.metrics.si_mse`);
        * ``ber``: balanced error rate of ``shadow_labels == 0`` against the true shadow
          ``sun_visibility == 0`` over the scored pixels not labelled 128 (undecided);
          ``ber_excluded_fraction``: fraction of scored pixels labelled 128;
          ``true_shadow_fraction``; ``ber_single_class``: True when the true shadow mask holds one
          class only (the BER is then the error rate of that class, see the metric);
        * ``reconstruction_psnr``, ``reconstruction_ssim``: ``reflectance * shading`` against the
          photo over the scored pixels where the photo is valid (finite, non-negative, not
          saturated); ``reconstruction_data_range`` is the 99th percentile of the photo there;
        * ``shading_psnr``, ``shading_ssim``: the shading times a least-squares scale per channel
          (``shading_scale``, :math:`k_c = \sum m t e / \sum m e^2`) against the true shading,
          ``data_range`` the 99th percentile of the true shading.

    Raises
    ------
    SceneError
        Naming the file: no ``gt/``, a missing or malformed ground-truth layer or result file
        (e.g. ``lighting.json``), no input image for a view, or result layers whose size differs
        from the ground truth.
    ValueError
        If a requested view is not in the result or has no ground truth, no view of the result has
        ground truth, or ``window`` / ``step`` are invalid for the images.

    Notes
    -----
    **Scored pixels.** All metrics use the same mask: not sky (``gt/sky_mask``), every true and
    estimated layer finite, and the true reflectance above :data:`REFLECTANCE_MIN` in every
    channel (the true shading ``image / reflectance`` is undefined where it is 0).

    **PSNR.** HDR images have no peak value, so ``data_range`` is the
    :data:`DATA_RANGE_PERCENTILE` (99th) percentile of the reference (photo, or true shading) over
    the scored pixels and channels; pixels above it are not clipped. An exact match is reported as
    :data:`PSNR_MAX_DB` instead of infinity. SSIM uses the same ``data_range``.

    **Global scale of the shading.** A decomposition is defined up to a scale per channel
    (``R k``, ``S / k`` explain the same image), which LMSE and si-MSE ignore; PSNR and SSIM of the
    shading are made comparable by the same per-channel least-squares scale. The reconstruction
    ``R S`` has no such ambiguity and is scored as it is.

    **Means** are unweighted over the scored views, skipping undefined (None) values.
    """
    root, folder = Path(scene_folder), Path(result_folder)
    gt_stems = _gt_stems(_gt_folder(root))
    result = load_decomposition(folder)
    if views is None:
        stems = [s for s in result.stems if s in set(gt_stems)]
        if not stems:
            raise ValueError(
                f"result_folder: no view of {folder} has ground truth in {root / 'gt'} "
                f"(result views {list(result.stems)}, ground-truth views {gt_stems})"
            )
    else:
        if isinstance(views, str):
            raise TypeError("views must be a sequence of stems, not a single string")
        stems = list(views)
        for stem in stems:
            if stem not in result.layers:
                raise ValueError(f"views: {stem!r} is not in the result {folder}; its views are {list(result.stems)}")
            if stem not in gt_stems:
                raise ValueError(f"views: {stem!r} has no ground truth in {root / 'gt'}; those are {gt_stems}")
    truth = read_ground_truth(root, views=stems)

    per_view: dict[str, dict[str, Any]] = {}
    for stem in stems:
        gt, layers = truth[stem], result.layers[stem]
        if layers.shape != gt.shape:
            raise SceneError(
                folder / "views" / stem,
                f"result layers are {layers.shape[1]}x{layers.shape[0]} pixels, the ground truth "
                f"{gt.shape[1]}x{gt.shape[0]}",
            )
        image, image_valid, image_path = _input_image(root, stem, gt.shape)
        if image.shape[:2] != gt.shape:
            raise SceneError(
                image_path, f"is {image.shape[1]}x{image.shape[0]} pixels, the ground truth {gt.shape[1]}x{gt.shape[0]}"
            )
        per_view[stem] = _score_view(gt, layers, image, image_valid, window=window, step=step)

    true_sun, _ = _gt_sun(root)
    sun_error = None
    if true_sun is not None:
        cosine = float(np.clip(true_sun.direction @ result.lighting.sun.direction, -1.0, 1.0))
        sun_error = math.degrees(math.acos(cosine))
    return {
        "scene": str(root.resolve()),
        "result": str(folder.resolve()),
        "mvintrinsic_version": __version__,
        "result_version": str(result.version),
        "settings": {
            "window": int(window),
            "step": int(step),
            "reflectance_min": REFLECTANCE_MIN,
            "data_range_percentile": DATA_RANGE_PERCENTILE,
            "psnr_max_db": PSNR_MAX_DB,
        },
        "views": per_view,
        "mean": _mean(per_view),
        "views_without_result": [s for s in gt_stems if s not in result.layers],
        "views_without_gt": [s for s in result.stems if s not in set(gt_stems)],
        "lighting": {"sun_direction_error_deg": sun_error},
    }


# ---------------------------------------------------------------------------------------------
# intermediate quantities (Step 1): environment shading and proxy sun visibility
# ---------------------------------------------------------------------------------------------
#: Side (pixels) of the window over which :func:`env_shading_error` averages both sides. The
#: ground-truth ``env_shading`` of a 64-spp render is noisy: two renders with different seeds
#: differ by 19-26% per pixel (median, GT-shadowed pixels of the demo scene) and by 6-8% after
#: this 5 x 5 masked averaging, which makes the error measure the estimate, not the render noise.
ENV_SMOOTHING_WINDOW = 5
#: Ground-truth env shading below this is treated as undefined (relative errors explode).
ENV_MIN = 1e-4


#: Full angle (degrees) of the sun's disc for :func:`umbra_mask`: Mitsuba's ``sunsky`` default,
#: which the synthetic scenes are rendered with (the real sun subtends about 0.53 degrees).
SUN_APERTURE_DEG = 0.5358


def umbra_mask(
    scene_folder: os.PathLike | str,
    *,
    views: Sequence[str] | None = None,
    samples: int = 16,
    aperture_deg: float = SUN_APERTURE_DEG,
    seed: int = 0,
) -> dict[str, np.ndarray]:
    """Pixels that no part of the sun's disc reaches (the umbra), from the exact mesh.

    ``gt/sun_visibility`` is the pixel-centre ray toward the sun's centre. Where sunlight
    reaches a "shadowed" pixel in part (a penumbra, gaps between leaves smaller than a pixel),
    ground-truth generators split the shading differently: a render of the sun alone puts that
    light in ``gt/sun_shading``, an analytic ``L_sun cos(w) v`` with the binary visibility
    leaves it in ``gt/env_shading`` (``docs/step1.md``). In the umbra both agree.

    Per pixel, ``samples`` rays through jittered positions in the pixel hit ``gt/mesh.ply``; from
    each hit a shadow ray toward a jittered point of the sun's disc (uniform over the disc of
    full angle ``aperture_deg``) is cast. A pixel is umbra when its ray hits the mesh every time
    and every shadow ray is blocked or starts on a surface facing away from the sun.

    Parameters
    ----------
    scene_folder : path-like
        Scene with ``gt/mesh.ply``, cameras and a ground-truth sun (``gt/lighting.json`` or
        ``scene.json``).
    views : sequence of str, optional
        Stems; default every view of the scene.
    samples : int
        Rays per pixel.
    aperture_deg : float
        Full angle of the sun's disc, degrees.
    seed : int
        Seed of the jitter.

    Returns
    -------
    dict of str to (H, W) bool
        By stem.

    Raises
    ------
    SceneError
        ``gt/mesh.ply`` missing, or no ground-truth sun direction (only clicks).
    """
    from .envmap import horizontal_frame
    from .io import load_scene, read_proxy
    from .raytrace import Tracer

    if isinstance(samples, bool) or not isinstance(samples, int) or samples < 1:
        raise ValueError(f"samples must be a positive integer, got {samples!r}")
    if not 0 <= aperture_deg < 10:
        raise ValueError(f"aperture_deg must be in [0, 10) degrees, got {aperture_deg!r}")
    root = Path(scene_folder)
    mesh_file = _gt_folder(root) / "mesh.ply"
    if not mesh_file.is_file():
        raise SceneError(mesh_file, "missing: the umbra needs the exact mesh")
    sun, _ = _gt_sun(root)
    if sun is None:
        raise SceneError(root / "scene.json", "gives the sun by clicks only: the umbra needs its true direction")
    scene = load_scene(root, views=views)
    tracer = Tracer(read_proxy(mesh_file))
    centre = sun.direction
    frame = horizontal_frame(centre)  # any orthonormal pair across the sun's direction
    t1, t2 = frame[1], -frame[0]
    radius = math.tan(math.radians(aperture_deg) / 2.0)
    gen = np.random.default_rng(seed)
    out = {}
    for view in scene.views:
        camera = view.camera
        lit_any = np.zeros(camera.height * camera.width, dtype=bool)
        rows, cols = np.mgrid[0:camera.height, 0:camera.width]
        for _ in range(samples):
            jitter = gen.random((rows.size, 2))
            pixels = np.stack([cols.ravel() + jitter[:, 0], rows.ravel() + jitter[:, 1]], axis=1)
            rays = camera.pixel_rays(pixels)
            hits = tracer.intersect(camera.center, rays)
            lit_any |= ~hits.hit  # a sample on the sky: not umbra
            idx = np.flatnonzero(hits.hit)
            normals = hits.normals[idx]  # facing the camera (Tracer.intersect)
            r = radius * np.sqrt(gen.random(len(idx)))
            a = 2.0 * np.pi * gen.random(len(idx))
            toward = centre + r[:, None] * (np.cos(a)[:, None] * t1 + np.sin(a)[:, None] * t2)
            toward /= np.linalg.norm(toward, axis=1, keepdims=True)
            facing = np.einsum("ij,ij->i", normals, toward) > 0
            f = np.flatnonzero(facing)
            origins = hits.points[idx[f]] + 1e-3 * normals[f]
            lit_any[idx[f]] |= ~tracer.occluded(origins, toward[f])
        out[view.stem] = ~lit_any.reshape(camera.height, camera.width)
    return out


def env_shading_error(
    scene_folder: os.PathLike | str,
    estimates: Mapping[str, np.ndarray],
    *,
    region: str = "shadow",
    window: int = ENV_SMOOTHING_WINDOW,
    umbra: Mapping[str, np.ndarray] | None = None,
) -> dict[str, Any]:
    """Relative error of per-pixel environment shading ``S_sky + S_ind`` against ``gt/env_shading``.

    Parameters
    ----------
    scene_folder : path-like
        Scene with ``gt/env_shading``, ``gt/sun_visibility``, ``gt/sky_mask`` and
        ``gt/reflectance``.
    estimates : mapping of str to (H, W, 3) array
        Estimated ``S_env`` per view stem (NaN where there is no estimate, e.g. off the proxy).
    region : {"shadow", "umbra", "lit", "all"}
        Pixels compared: GT-shadowed (``gt/sun_visibility == 0``: there the shading is ``S_env``
        alone), GT-shadowed and in the umbra (:func:`umbra_mask`: no part of the sun's disc
        reaches them, so the ground-truth convention for partial sun does not matter), lit, or
        all; always excluding sky, pixels with GT reflectance below :data:`REFLECTANCE_MIN`, GT
        ``S_env`` below :data:`ENV_MIN` and pixels without estimate.
    window : int
        Both sides are averaged over the region's pixels in ``window x window`` neighbourhoods
        before comparing (:data:`ENV_SMOOTHING_WINDOW`: the render noise); 1 compares raw pixels.
    umbra : mapping of str to (H, W) bool, optional
        :func:`umbra_mask` of the views, for ``region="umbra"``; computed when not given.

    Returns
    -------
    dict
        ``median_rel_error`` and ``p90_rel_error`` (per channel, over all pixels of all views),
        ``median_signed_rel_error`` (bias), ``pixels`` and ``per_view`` medians.
    """
    if region not in ("shadow", "umbra", "lit", "all"):
        raise ValueError(f"region must be 'shadow', 'umbra', 'lit' or 'all', got {region!r}")
    gt = read_ground_truth(scene_folder, views=list(estimates))
    if region == "umbra" and umbra is None:
        umbra = umbra_mask(scene_folder, views=list(estimates))
    errors, per_view = [], {}
    for stem, estimate in estimates.items():
        truth = gt[stem]
        if truth.env_shading is None:
            raise SceneError(_gt_folder(scene_folder) / "env_shading", "missing: env_shading is needed")
        estimate = np.asarray(estimate, dtype=np.float64)
        if estimate.shape != truth.env_shading.shape:
            raise ValueError(f"estimates[{stem!r}] must have shape {truth.env_shading.shape}, got {estimate.shape}")
        env = truth.env_shading.astype(np.float64)
        ok = truth.valid & np.isfinite(estimate).all(axis=2) & (env > ENV_MIN).all(axis=2)
        if region == "shadow":
            ok &= ~truth.sun_visibility
        elif region == "umbra":
            if stem not in umbra or np.shape(umbra[stem]) != ok.shape:
                raise ValueError(f"umbra must hold an {ok.shape} mask for view {stem!r}")
            ok &= ~truth.sun_visibility & np.asarray(umbra[stem], dtype=bool)
        elif region == "lit":
            ok &= truth.sun_visibility
        if not ok.any():
            continue
        a, b = masked_box_mean(estimate, ok, window), masked_box_mean(env, ok, window)
        rel = (a[ok] - b[ok]) / b[ok]
        errors.append(rel)
        per_view[stem] = np.median(np.abs(rel), axis=0).tolist()
    if not errors:
        raise ValueError(f"no {region} pixel with an estimate in any view")
    rel = np.concatenate(errors)
    return {
        "region": region,
        "window": window,
        "pixels": int(len(rel)),
        "median_rel_error": np.median(np.abs(rel), axis=0).tolist(),
        "p90_rel_error": np.percentile(np.abs(rel), 90, axis=0).tolist(),
        "median_signed_rel_error": np.median(rel, axis=0).tolist(),
        "per_view": per_view,
    }


def visibility_error(scene_folder: os.PathLike | str, estimates: Mapping[str, np.ndarray]) -> dict[str, Any]:
    """Balanced error rate of an estimated sun visibility against ``gt/sun_visibility``.

    ``estimates`` maps view stems to ``(H, W)`` visibility in [0, 1] (NaN: no estimate); values
    below 0.5 count as shadow. Sky and pixels without estimate are excluded. Returns the BER over
    all views (pooled confusion counts), per view, and the fraction of non-sky pixels scored.
    """
    gt = read_ground_truth(scene_folder, views=list(estimates))
    pred_all, true_all, per_view, scored = [], [], {}, []
    for stem, estimate in estimates.items():
        truth = gt[stem]
        estimate = np.asarray(estimate, dtype=np.float64)
        ok = ~truth.sky_mask & np.isfinite(estimate)
        pred, true = estimate[ok] < 0.5, ~truth.sun_visibility[ok]
        pred_all.append(pred)
        true_all.append(true)
        scored.append(ok.sum() / max((~truth.sky_mask).sum(), 1))
        if true.any() and (~true).any():
            per_view[stem] = metrics.balanced_error_rate(estimate < 0.5, ~truth.sun_visibility, mask=ok)
    pred, true = np.concatenate(pred_all), np.concatenate(true_all)
    ber = 1.0 - 0.5 * (np.mean(pred[true]) + np.mean(~pred[~true]))
    return {"ber": float(ber), "per_view": per_view, "scored_fraction": float(np.mean(scored))}
