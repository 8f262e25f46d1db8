"""Relighting (paper Sec. 8) against path-traced renders of the same scene under moved suns.

    python benchmarks/bench_relight.py [--smoke] [--data DIR --scene NAME ...] [--timing | --stride | --softness | --bounds | --receivers
                                       | --proxy-loss | --error-split | --occluder-distance | --sky-pixels
                                       | --lost-occluders | --sun-radiance | --true-labels | --agreement]
                                       [--relight-config JSON] [--decompose-config JSON] [--no-caster-study]
                                       [--out benchmarks/results/relight.json]
                                       [--figure docs/images/relight.png]

Scenes: the embedded demo (240x180, 6 views, relit tags ``az+15`` and ``el+10``) by default and
with ``--smoke``; ``--scene NAME`` (repeatable) scores ``DIR/NAME`` instead (``--data``, default
``../data`` beside the checkout), any scene folder rendered by ``mvintrinsic synth`` with relit
tags. For every relit tag ``gt/relit/<tag>`` (``docs/formats.md``) the relit views are scored by
:func:`relit_psnr` against the path-traced render ``gt/relit/<tag>/images/<stem>.exr``:

(a) ``input``: the input image unchanged (what not relighting scores);
(b) ``gt_proxy``: the ground-truth layers (:func:`mvintrinsic.evaluation.ground_truth_decomposition`)
    relit with the proxy's own shadow at the new sun, as Step 1 computes it
    (:meth:`~mvintrinsic.relight.Relighter.proxy_visibility`);
(c) ``gt_mesh``: the ground-truth layers with the exact mesh's shadow (``gt/mesh.ply`` as the
    caster, receivers on the mesh, its normals for the attached shadow, no blur, a ray from every
    pixel): the relighting
    model's bound, all its error is the shading adjustment's; ``gt_mesh_blurred`` is the same with
    the relighter's blur (``RelightConfig.blur``), what the blur costs;
(d) ``gt_caster``: the ground-truth layers with our caster built from the ground-truth shadow
    labels (:class:`~mvintrinsic.relight.Relighter` with its defaults: the paper's parameters,
    every view's votes, each view's own caster, proxy completion, the dropped clusters' shadow
    kept in the shadow layer);
(e) ``pipeline``: the full pipeline, ``mvintrinsic.decompose(scene)`` then the Relighter.

Rows (b) and (c) keep the true layers and are given their shadow layer (``dropped="none"``: the
handling of the dropped clusters belongs to the caster). Every row is computed for both environment adjustments (``sky="paper"`` and
``"model"``, :class:`~mvintrinsic.relight.RelightConfig`). Also reported:

* ``capture_psnr``: rows (d) and (e) at the capture sun against the input image (what the caster
  loses before the sun moves);
* ``agreement``: the cross-view consistency of the relit shadow state: the share of proxy vertices
  seen by two or more views whose relit shadow state (:func:`shadow_layer` ``>= 0.5``) is the same in all of them
  (:func:`mvintrinsic.correspondence.cross_view_agreement`, Step 1's pixel quantities as Step 3
  uses them); ``truth`` is the same measure on ``gt/relit/<tag>/sun_visibility``;
  ``agreement_interior`` the same without reading the pixels within one pixel of a true relit
  shadow edge, where even the true labels disagree (``bench_shadows.py --agreement``);
* ``caster_study``: rows (d) and (e) under other :class:`~mvintrinsic.relight.RelightConfig`
  options, one changed at a time from the default: the merged caster, the paper's checks
  (``method="paper"``, own and merged casters), no completion distance, ``min_proxy_hits`` 0
  (keep every cluster of >= 100 pixels), ``min_cluster`` 20, the paper's cluster rule alone
  (``support_radius=0``, without the supported parts), no blur, the dropped clusters
  brought into light (``dropped="light"``, the paper) or moved like every pixel (``"none"``), with the pixels the proxy does not explain relit like the
  others (``consistency=None``, the paper), each view's new shadow alone (``fusion=None``, the
  paper) and fused over every view that sees a point (``fusion="all"``), and each
  :attr:`~mvintrinsic.relight.RelightConfig.anchor` (None, the paper; ``"shadow"``; ``"both"``), and the receivers'
  normals not snapped to the proxy's planes (``planes=None``; the decomposition's layers keep theirs); per row also the
  ``agreement_interior`` at each relit sun;
* ``mesh_visibility_iou``: row (c)'s shadow (``< 0.5``) against ``gt/relit/<tag>/sun_visibility``
  over the non-sky pixels, without and with the blur (a check of the bound);
* ``seconds_per_view``: building the relighter (receivers, casters, merged caster and BVH) and
  rendering one sun, per view; ``decompose_seconds``.

``--relight-config '{"support_radius": 10}'`` (a JSON object of
:class:`~mvintrinsic.relight.RelightConfig` keywords) changes every relighter the run builds, rows
and studies alike, from the package's defaults (the report's ``config`` records the result): how a
run with an option is reproduced. A keyword a row or study sets itself (e.g. ``--timing``'s
``lost_occluders``, a ``caster_study`` variant's option) wins over the override.

``--decompose-config '{"step1": {"planes": null}}'`` (a JSON object of :class:`mvintrinsic.Config` keys, nested
as :meth:`~mvintrinsic.Config.from_dict` reads them) changes every decomposition the run makes (row (e) and the
studies' pipelines; the report's ``decompose_config`` records it); ``--no-caster-study`` skips the caster study
of a main run (most of its time) where only the rows are wanted.

``--agreement`` only asks what the cross-view agreement measures and where rows (d) and (e) lose it
(:func:`agreement_scene`; ``agreement_summary``: per row the lowest value and the scene-suns at 0.95 or more): the
binary measure away from the true edges beside its soft counterpart (the views' ``v'`` within 0.5 of each other,
:func:`~mvintrinsic.correspondence.cross_view_value_agreement`), for the truth, the exact mesh's shadow at suns turned
by 0.5-2 degrees (one 3D shadow, not the truth's), rows (d) and (e), row (d) on the exact receivers, and the views'
caster sheets alone.

``--sky-pixels`` only compares the colours :attr:`~mvintrinsic.relight.RelightConfig.sky_pixels` gives
the sky pixels, by :func:`sky_psnr` (:func:`sky_pixels_scene`).

``--stride`` only compares ``RelightConfig.ray_stride`` 2 and 3 with 1 (every pixel): the share of
the sharp shadow state that changes, the relit PSNR change and the time of the new visibility
(:func:`stride_scene`).

``--softness`` only compares ways of softening row (d)'s new shadow (:func:`softness_scene`):
the paper's 1 px Gaussian blur (the default), none, a penumbra from the sun's angular size and
the occluder distance, and a blend with the capture visibility (shadows that persist).

``--bounds`` only relights the ground-truth and the pipeline's layers with ideal shadow layers
(:func:`bounds_scene`): the exact mesh's, the path tracer's and the best possible one
(:func:`best_visibility`, the per-pixel least-squares visibility against the truth): how much of
row (e)'s distance to row (c) a better caster could close, and how much is the layers'.

``--receivers`` only relights the ground-truth layers with the exact mesh as the occluder but
the rays shot from the proxy's receiver points (:func:`receivers_scene`): what no caster built on
this proxy's receivers can exceed, i.e. how much of row (d)'s distance to row (c) is the caster's.

``--proxy-loss`` only scores rows (a), (c), (d) and (e) again on better proxies than the scene's
(:func:`proxy_variant`: less foliage and thin-structure loss, a fusion of exact depth maps, the
exact mesh and its part the views see): what the caster needs of the proxy. ``--proxy-variant``
picks some of them and ``--update`` merges them into an existing ``--out``.

``--error-split`` only splits row (d)'s squared error beyond row (c)'s by the true shadow state
at the capture and the new sun and ours at the new sun (:func:`error_split_scene`): which shadows
the caster misses or adds. ``--occluder-distance`` splits it by how far the exact mesh's occluder
is along the capture and the new sun (:func:`occluder_distance_scene`): near occluders (ledges,
recesses) or far ones (crowns, posts).

``--lost-occluders`` only scores rows (a), (c), (d) and (e) with and without
:attr:`~mvintrinsic.relight.RelightConfig.lost_occluders` (the shadow rays that miss the proxy
take the distance at which the photographs see what the proxy lost, :mod:`mvintrinsic.photo_occupancy`),
with the seconds per view of building the relighter and the share of shadow pixels dropped
(:func:`lost_occluders_scene`; ``lost_occluders_summary``: the means at +-15 degrees; the key ``off``
was ``default`` in the runs before 2026-11-27). The option
runs with its defaults (``OccupancyConfig.belief`` 0.5 since 2026-11-27: the rescued clusters' pixels
mix the moved shadow and the paper's image; ``results/relight_lost_occluders_belief1.json`` is the
run before, the moved shadow alone).

``--sun-radiance`` only relights the pipeline's layers with its ``L_sun`` replaced by the truth, by
the truth's level (luminance) alone and by its colour alone, the reflectance made again
(:func:`sun_radiance_scene`, an oracle; ``sun_radiance_summary``: the means at +-15 degrees): what a
better ``L_sun`` (issue 16) would give the relit images.

``--true-labels`` only decomposes again with the true shadow labels in place of Step 3's
multi-view labelling and relights by the default relighter, with ``lost_occluders`` and with the
caster from the labels alone (``RelightConfig.caster_pixels``), beside the same relighters on the
pipeline's own layers (:func:`true_labels_scene`, an oracle; ``true_labels_summary``: the means at
+-15 degrees): what better labels would give the relit images, and what the caster needs of them.

``--timing`` only times the relighter built on the ground-truth layers (``--timed-occluders``: ``none``,
``lost_occluders=None``, by default; ``occupancy``, ``OccupancyConfig()``, also chosen by ``--lost-occluders``;
``default``, the relighter's default ``OccupancyConfig(silhouette=1)``; build per view by stage,
and each new sun per view) for scenes with or without relit renders, e.g. the 1000x750 speed
scene: ``python benchmarks/bench_relight.py --timing --scene courtyard_1000``; ``--size 1000x750``
times a smaller scene's views and layers resampled to that size (:func:`upscaled`).

Run with the package importable; the demo takes about 30 s on 2 cores (9 s of it decomposing).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import json
import os
import platform
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from _figures import require_matplotlib
from bench_distributed import _parse_size, upsampled
from bench_shadows import away_from_edges, true_edge
from scipy import ndimage

import mvintrinsic
from mvintrinsic import Config, decompose, image_model
from mvintrinsic.correspondence import cross_view_agreement, cross_view_value_agreement
from mvintrinsic.env_shading import step1
from mvintrinsic.evaluation import ground_truth_decomposition, read_ground_truth
from mvintrinsic.io import load_scene, read_image, read_proxy, read_scene_json, write_json
from mvintrinsic.metrics import psnr
from mvintrinsic.photo_occupancy import OccupancyConfig
from mvintrinsic.pipeline import carry_to_pixels
from mvintrinsic.planes import PlaneConfig
from mvintrinsic.raytrace import Tracer
from mvintrinsic.relight import (
    SKY_ADJUSTMENTS,
    SKY_PIXEL_MODES,
    Caster,
    RelightConfig,
    Relighter,
    ShadowCaster,
    as_sun_direction,
    receiver_depth,
    receiver_points,
)
from mvintrinsic.results import SHADOW_LABELS
from mvintrinsic.shadow_caster import AUTO_COMPLETION_DISTANCE
from mvintrinsic.sun_position import azimuth_elevation

ROOT = Path(__file__).resolve().parents[2]
#: Percentile of the relit truth (non-sky pixels, all channels) at which both images are clipped
#: and which is the PSNR's data range: HDR renders have no natural peak, and a few sun-lit
#: specular pixels set the maximum.
CLIP_PERCENTILE = 99.5
#: At most this many proxy vertices are tested for cross-view agreement (every k-th).
AGREEMENT_POINTS = 300_000
#: The relit suns shown in the figure (all of a scene's when it has none of them).
FIGURE_TAGS = ("az+15", "az-15")
ROWS = ("input", "gt_proxy", "gt_mesh", "gt_mesh_blurred", "gt_caster", "pipeline")
#: The rows of ``--bounds`` (:func:`bounds_scene`).
BOUND_ROWS = ("input", "gt_mesh", "gt_caster", "pipeline", "gt_truth", "gt_best", "pipeline_mesh", "pipeline_truth",
              "pipeline_best")

#: ``--relight-config``: keyword overrides of every :class:`~mvintrinsic.relight.RelightConfig` this
#: benchmark builds (its rows' and its studies' alike), e.g. ``{"support_radius": 10}``; empty: the
#: package's defaults. The report's ``config`` records the resulting configuration.
CONFIG_OVERRIDES: dict = {}


#: ``--decompose-config``: a (partial) nested :class:`mvintrinsic.Config` mapping for every decomposition this
#: benchmark makes (row (e) and the studies' pipelines), e.g. ``{"step1": {"planes": null}}``; empty: the package's
#: defaults. The report's ``decompose_config`` records it.
DECOMPOSE_OVERRIDES: dict = {}
#: ``--no-caster-study``: skip :func:`caster_study` (most of a main run's time).
SKIP_CASTER_STUDY = [False]


def pipeline_config() -> Config:
    """The decomposition's :class:`mvintrinsic.Config`: the defaults under :data:`DECOMPOSE_OVERRIDES`."""
    return Config.from_dict(DECOMPOSE_OVERRIDES)


def _parse_decompose_overrides(text: str | None) -> dict:
    """``--decompose-config``'s JSON object, checked by :meth:`mvintrinsic.Config.from_dict` before any scene is read."""
    if not text:
        return {}
    try:
        options = json.loads(text)
        Config.from_dict(options)
    except ValueError as error:  # JSONDecodeError is a ValueError
        raise SystemExit(f"--decompose-config: {error}") from None
    return options


def relight_config(**options) -> RelightConfig:
    """:class:`~mvintrinsic.relight.RelightConfig` with ``options`` over :data:`CONFIG_OVERRIDES`."""
    return RelightConfig(**{**CONFIG_OVERRIDES, **options})


def _parse_overrides(text: str | None) -> dict:
    """``--relight-config``'s JSON object -> RelightConfig keywords (``lost_occluders``, ``planes``: an object of
    :class:`~mvintrinsic.photo_occupancy.OccupancyConfig` or :class:`~mvintrinsic.planes.PlaneConfig` keywords, or
    null)."""
    if not text:
        return {}
    try:
        options = json.loads(text)
    except json.JSONDecodeError as error:
        raise SystemExit(f"--relight-config: not JSON ({error})") from None
    fields = {f.name for f in dataclasses.fields(RelightConfig)}
    if not isinstance(options, dict) or set(options) - fields:
        raise SystemExit(f"--relight-config: expected an object of RelightConfig fields ({', '.join(sorted(fields))}), "
                         f"got {text!r}")
    try:
        if isinstance(options.get("lost_occluders"), dict):
            options["lost_occluders"] = OccupancyConfig(**options["lost_occluders"])
        if isinstance(options.get("planes"), dict):
            options["planes"] = PlaneConfig(**options["planes"])
        RelightConfig(**options)  # validated here, before any scene is read
    except (TypeError, ValueError) as error:
        raise SystemExit(f"--relight-config: {error}") from None
    return options


def relit_psnr(estimate: np.ndarray, truth: np.ndarray, sky_mask: np.ndarray) -> float:
    """PSNR of a relit image against the path-traced relit render, dB.

    Linear RGB over the non-sky pixels (``~sky_mask``, the ground truth's) where the truth is
    finite; both images are clipped to ``[0, c]`` with ``c`` the truth's
    :data:`CLIP_PERCENTILE` (99.5th) percentile over those pixels and channels, and ``c`` is the
    data range: ``10 log10(c^2 / MSE)``.

    Parameters
    ----------
    estimate, truth : (H, W, 3) array_like
        Linear RGB, the images' units.
    sky_mask : (H, W) bool
        True where the truth sees the sky (``gt/sky_mask``).
    """
    truth = np.asarray(truth, dtype=np.float64)
    estimate = np.nan_to_num(np.asarray(estimate, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    mask = ~np.asarray(sky_mask, dtype=bool) & np.isfinite(truth).all(axis=-1)
    top = float(np.percentile(truth[mask], CLIP_PERCENTILE))
    return psnr(np.clip(estimate, 0.0, top), np.clip(truth, 0.0, top), mask=mask, data_range=top)


def sky_psnr(estimate: np.ndarray, truth: np.ndarray, sky_mask: np.ndarray) -> float:
    """:func:`relit_psnr` over the sky pixels instead (``sky_mask``, the truth's), clipped at the
    truth's :data:`CLIP_PERCENTILE` percentile there (the sun's disc above it)."""
    return relit_psnr(estimate, truth, ~np.asarray(sky_mask, dtype=bool))


def sky_pixels_scene(folder: Path) -> dict:
    """``--sky-pixels``: the sky pixels' colour at each relit sun (:attr:`RelightConfig.sky_pixels`).

    The full pipeline's layers relit with each mode of :data:`SKY_PIXEL_MODES` (``"input"``: the
    input's sky unchanged); per relit tag the mean over views of :func:`sky_psnr` (the truth's sky
    pixels) and of :func:`relit_psnr` (the other pixels: unchanged, but for pixels the relighter takes
    for sky that the truth does not), and the share of the truth's sky pixels the relighter recolours.
    """
    scene, tags, sky_mask = _relit_scene(folder, "--sky-pixels")
    tracer = Tracer(scene.proxy)
    result = decompose(scene, tracer=tracer, config=pipeline_config())
    out: dict = {}
    for mode in SKY_PIXEL_MODES:
        relighter = Relighter(result, scene, config=relight_config(sky_pixels=mode), tracer=tracer)
        entry = out[mode] = {}
        for tag, (direction, images, _) in tags.items():
            rendered = relighter.render(direction)
            entry[tag] = {"sky": float(np.mean([sky_psnr(rendered[s], images[s], sky_mask[s]) for s in scene.stems])),
                          "non_sky": mean_psnr(rendered, images, sky_mask)["mean"]}
        if mode != "input":
            found = [np.isin(np.flatnonzero(sky_mask[s]), relighter._new_sun[s].sky_pixels.index).mean()
                     if relighter._new_sun[s].sky_pixels is not None else 0.0 for s in scene.stems]
            entry["truth_sky_recoloured"] = float(np.mean(found))
        print(f"{folder.name} sky_pixels={mode}: " + " ".join(
            f"{t} {v['sky']:.2f}/{v['non_sky']:.2f}" for t, v in entry.items() if isinstance(v, dict)), flush=True)
    return out


def mean_psnr(images: dict, truth: dict, sky: dict) -> dict:
    per_view = {s: relit_psnr(images[s], truth[s], sky[s]) for s in truth}
    return {"mean": float(np.mean(list(per_view.values()))), "per_view": per_view}


def relit_tags(folder: Path, stems) -> dict:
    """Per tag: the sun direction, the relit renders and the true relit visibility of every view."""
    out = {}
    root = folder / "gt" / "relit"
    found = sorted(p for p in root.iterdir() if (p / "scene.json").is_file()) if root.is_dir() else []
    for tag_dir in found:
        direction = np.asarray(read_scene_json(tag_dir / "scene.json")["sun_direction"])
        images = {s: read_image(tag_dir / "images" / f"{s}.exr")[0] for s in stems}
        visibility = {s: read_image(tag_dir / "sun_visibility" / f"{s}.png")[0][..., 0] > 0.5 for s in stems}
        out[tag_dir.name] = (direction, images, visibility)
    return out


def mesh_occluder(mesh) -> ShadowCaster:
    """A mesh (a :class:`~mvintrinsic.scene.Proxy` with triangles) as the occluder of every shadow ray, as it is."""
    return ShadowCaster(Caster(mesh.vertices, mesh.triangles.astype(np.int32), np.zeros(0, np.int64),
                               None, None, 0, 0, 0, 0))


def scene_folders(args) -> dict:
    """The scenes a benchmark scores: ``{"demo": the embedded demo}`` with ``--smoke`` or no ``--scene``,
    else ``{NAME: DATA/NAME}`` per ``--scene`` (``args.smoke``, ``args.scene``, ``args.data``)."""
    from mvintrinsic.cli import demo_scene_path

    if args.smoke or not args.scene:
        return {"demo": demo_scene_path()}
    return {name: args.data / name for name in args.scene}


class MeshShadow:
    """Shadows of the exact mesh (``gt/mesh.ply``) at its own receivers: row (c)."""

    def __init__(self, folder: Path, scene) -> None:
        mesh = read_proxy(folder / "gt" / "mesh.ply")
        self.tracer = tracer = Tracer(mesh)
        self.caster = mesh_occluder(mesh)
        self.points, self.normals = {}, {}
        for view in scene.views:
            depth, hit = receiver_depth(view.camera, tracer)
            self.points[view.stem] = receiver_points(view.camera, depth)
            normals = tracer.intersect(view.camera.center, view.camera.pixel_rays()).normals.reshape(*view.shape, 3)
            self.normals[view.stem] = np.where(hit[..., None], normals, np.nan)  # geometric, toward the camera

    def visibility(self, direction: np.ndarray, config: RelightConfig, *, caster: ShadowCaster | None = None) -> dict:
        """Every pixel's own ray (``ray_stride=1``): the bound is not sampled. ``caster``: another occluder
        than the exact mesh (:func:`mesh_occluder`), shot from the same receivers."""
        config = dataclasses.replace(config, ray_stride=1)
        caster = self.caster if caster is None else caster
        return {s: caster.sun_visibility(self.points[s], self.normals[s], direction, config=config)
                for s in self.points}

    def render(self, plain: Relighter, direction: np.ndarray, config: RelightConfig) -> dict:
        """Row (c): ``plain`` (the true layers, ``dropped="none"``) relit with the sharp exact shadow."""
        return plain.render(direction, visibility=self.visibility(direction, dataclasses.replace(config, blur=0.0)))


def caster_summary(relighter: Relighter) -> dict:
    merged = relighter.caster
    return {"triangles": len(merged.triangles), "clusters": merged.n_clusters, "dropped_small": merged.n_small,
            "dropped_unsupported": merged.n_unsupported, "triangles_removed": merged.n_removed,
            "pixels_kept": int(sum(c.shadow.sum() for c in relighter.casters.values())),
            "pixels_dropped": int(sum(c.dropped.sum() for c in relighter.casters.values()))}


def relit_agreement(scene, quantities, points: np.ndarray, visibility: dict, true_lit: dict | None = None) -> float:
    """Cross-view agreement of a relit shadow state (``visibility >= 0.5`` lit) at ``points``; with ``true_lit``
    the pixels within one pixel of a true shadow edge are not read (``agreement_interior``)."""
    labels = {s: np.asarray(v) >= 0.5 for s, v in visibility.items()}
    if true_lit is not None:
        labels = away_from_edges({s: np.where(lit, SHADOW_LABELS["lit"], SHADOW_LABELS["shadow"])
                                  for s, lit in labels.items()}, true_lit)
    return cross_view_agreement(scene.views, quantities, labels, points).fraction


def agreement_inputs(scene, tracer: Tracer, config: Config) -> tuple[dict, np.ndarray]:
    """What the agreement measures read: Step 1's pixel quantities (``config``'s Step 1, as Step 3 uses them) and the
    tested points (every k-th proxy vertex, at most :data:`AGREEMENT_POINTS`)."""
    quantities = carry_to_pixels(scene, step1(scene, config=config.step1, tracer=tracer, rng=config.seed), tracer)
    return quantities, scene.proxy.vertices[:: max(1, len(scene.proxy.vertices) // AGREEMENT_POINTS)]


def relit_value_agreement(scene, quantities, points: np.ndarray, visibility: dict, true_lit: dict) -> float:
    """The soft counterpart of :func:`relit_agreement` (``agreement_interior``): a point agrees when the largest minus
    the smallest ``visibility`` over the views that see it is below 0.5
    (:func:`~mvintrinsic.correspondence.cross_view_value_agreement`), the pixels within one pixel of a true shadow
    edge not read."""
    values = {s: np.where(true_edge(true_lit[s]), np.nan, np.asarray(v, np.float64)) for s, v in visibility.items()}
    return cross_view_value_agreement(scene.views, quantities, values, points).fraction


#: ``--agreement``: the azimuths (degrees) by which the exact mesh's control shadow is turned from each relit sun.
AGREEMENT_SHIFTS = (-2.0, -1.0, -0.5, 0.5, 1.0, 2.0)


def agreement_scene(folder: Path) -> dict:
    """What issue 15's cross-view agreement measures, and where rows (d) and (e) lose it (``--agreement``).

    Per relit tag, the binary measure away from the true edges (``agreement_interior``, :func:`relit_agreement`) and
    its soft counterpart (:func:`relit_value_agreement`: the views' ``v'`` within 0.5 of each other) of:

    * ``truth``: ``gt/relit/<tag>/sun_visibility``;
    * ``exact_az{d}``: a shadow that is one 3D field by construction but not the truth's: the exact mesh's (row (c)'s
      sharp shadow, exact receivers) at the sun turned by ``d`` degrees of azimuth (:data:`AGREEMENT_SHIFTS`), read
      against the tag's true edges: whether the measure asks for consistency or for the truth's edges;
    * ``gt_caster`` (d) and ``pipeline`` (e), as the main run;
    * ``gt_caster_exact_receivers``: row (d) with its receivers on the exact mesh (:func:`_exact_receivers`);
    * ``sheets_own`` / ``sheets_merged``: each view's own caster sheets alone, and the union of every view's
      (:attr:`~mvintrinsic.relight.Relighter.caster`), from row (d)'s receivers, a ray from every pixel, the 1 px
      blur: no completion, fusion or anchor (what the views' sheets agree on by themselves).
    """
    scene, tags, _ = _relit_scene(folder, "--agreement")
    tracer = Tracer(scene.proxy)
    decompose_config = pipeline_config()
    print(f"{folder.name}: decomposing {len(scene.stems)} views", flush=True)
    result = decompose(scene, tracer=tracer, config=decompose_config)
    truth = ground_truth_decomposition(folder, views=list(scene.stems))
    quantities, points = agreement_inputs(scene, tracer, decompose_config)
    config = relight_config()
    rows = {"gt_caster": Relighter(truth, scene, config=config, tracer=tracer),
            "pipeline": Relighter(result, scene, config=config, tracer=tracer)}
    mesh = MeshShadow(folder, scene)
    with _exact_receivers(scene, mesh):
        rows["gt_caster_exact_receivers"] = _exact_receivers_built(
            Relighter(truth, scene, config=config, tracer=tracer), mesh)
    ours = rows["gt_caster"]
    merged = ShadowCaster(ours.caster)
    every_pixel = dataclasses.replace(config, ray_stride=1)
    sharp = dataclasses.replace(config, blur=0.0)
    out = {}
    for tag, (direction, _, true_lit) in tags.items():
        direction = np.asarray(direction, dtype=np.float64)
        azimuth, elevation = azimuth_elevation(direction, up=scene.up)
        layers = {"truth": {s: true_lit[s].astype(np.float64) for s in scene.stems}}
        for shift in AGREEMENT_SHIFTS:
            turned = as_sun_direction((azimuth + shift, elevation), up=scene.up)
            layers[f"exact_az{shift:+g}"] = {s: np.nan_to_num(v, nan=1.0) for s, v in mesh.visibility(turned, sharp).items()}
        for name, relighter in rows.items():
            layers[name] = shadow_layer(relighter, relighter.visibility_at(direction))
        for name, caster in (("sheets_own", None), ("sheets_merged", merged)):
            layers[name] = {s: np.nan_to_num((caster or ours.shadow_casters[s]).sun_visibility(
                ours.receivers[s], ours.normals[s], direction, up=scene.up, config=every_pixel), nan=1.0)
                for s in scene.stems}
        out[tag] = {name: {"binary": relit_agreement(scene, quantities, points, layer, true_lit),
                           "soft": relit_value_agreement(scene, quantities, points, layer, true_lit)}
                    for name, layer in layers.items()}
        print(f"{folder.name} {tag}: " + " ".join(f"{k} {v['binary']:.3f}/{v['soft']:.3f}" for k, v in out[tag].items()),
              flush=True)
    return out


def agreement_summary(study: dict) -> dict:
    """Per row of :func:`agreement_scene` and measure: the lowest and highest value over the scene-suns and how many
    reach 0.95 (issue 15's target)."""
    rows: dict = {}
    for tags in study.values():
        for entry in tags.values():
            for row, measures in entry.items():
                for measure, value in measures.items():
                    rows.setdefault(row, {}).setdefault(measure, []).append(value)
    return {row: {measure: {"min": float(min(values)), "max": float(max(values)),
                            "at_least_0.95": int(sum(v >= 0.95 for v in values)), "scene_suns": len(values)}
                  for measure, values in measures.items()} for row, measures in rows.items()}


def shadow_layer(relighter: Relighter, visibility: dict) -> dict:
    """The relit image's shadow layer: ``visibility`` with, under ``dropped="light"`` (the paper), the
    dropped clusters' captured ``v_sun`` multiplied in, since there their shadow stays in the
    reflectance while their ``v'`` says lit (``RelightConfig.dropped``); unchanged otherwise."""
    if relighter.config.dropped != "light":
        return visibility
    return {s: np.where(relighter.casters[s].dropped, v * relighter.decomposition.layers[s].visibility, v)
            for s, v in visibility.items()}


def run_scene(folder: Path) -> tuple[dict, dict]:
    scene = load_scene(folder)
    stems = scene.stems
    truth = read_ground_truth(folder, views=list(stems))
    sky_mask = {s: truth[s].sky_mask for s in stems}
    tags = relit_tags(folder, stems)
    if not tags:
        raise SystemExit(f"{folder}: no gt/relit/<tag>/scene.json, nothing to score")
    h, w = scene.views[0].shape
    inputs = {v.stem: v.image for v in scene.views}
    entry: dict = {"size": f"{w}x{h}", "views": len(stems), "tags": {}}
    for tag, (direction, _, _) in tags.items():
        entry["tags"][tag] = {"sun_direction": direction.tolist(),
                              "azimuth_elevation_deg": list(azimuth_elevation(direction, up=scene.up))}
    entry["capture_sun_azimuth_elevation_deg"] = list(azimuth_elevation(scene.sun.direction, up=scene.up))

    tracer = Tracer(scene.proxy)
    print(f"{folder.name}: decomposing {len(stems)} views", flush=True)
    start = time.perf_counter()
    decompose_config = pipeline_config()
    result = decompose(scene, tracer=tracer, config=decompose_config)
    entry["decompose_seconds"] = time.perf_counter() - start
    ground_truth = ground_truth_decomposition(folder, views=list(stems))
    quantities, points = agreement_inputs(scene, tracer, decompose_config)
    mesh = MeshShadow(folder, scene)

    def agreement(visibility: dict, true_lit: dict | None = None) -> float:
        return relit_agreement(scene, quantities, points, visibility, true_lit)

    entry["psnr"], entry["capture_psnr"], entry["caster"] = {}, {}, {}
    entry["agreement"] = {tag: {"truth": agreement({s: vis[s] for s in stems})} for tag, (_, _, vis) in tags.items()}
    entry["agreement_interior"] = {tag: {"truth": agreement({s: vis[s] for s in stems}, vis)}
                                   for tag, (_, _, vis) in tags.items()}
    entry["mesh_visibility_iou"] = {}
    entry["seconds_per_view"] = {}
    figure = {"stem": stems[0], "input": inputs[stems[0]], "tags": {}}
    default = relight_config()
    for sky in SKY_ADJUSTMENTS:
        config = relight_config(sky=sky)
        plain = Relighter(ground_truth, scene, config=dataclasses.replace(config, dropped="none"), tracer=tracer)
        relighters = {}
        for name, decomposition in (("gt_caster", ground_truth), ("pipeline", result)):
            start = time.perf_counter()
            relighters[name] = Relighter(decomposition, scene, config=config, tracer=tracer)
            build = time.perf_counter() - start
            if sky == default.sky:
                entry["seconds_per_view"][name] = {"build": build / len(stems),
                                                   **{k: v / len(stems) for k, v in relighters[name].timings.items()}}
                entry["caster"][name] = caster_summary(relighters[name])
        entry["capture_psnr"][sky] = {name: mean_psnr(r.render(r.sun), inputs, sky_mask)["mean"]
                                      for name, r in relighters.items()}
        scores = {}
        for tag, (direction, images, vis) in tags.items():
            rows = {"input": mean_psnr(inputs, images, sky_mask)}
            proxy_vis = plain.proxy_visibility(direction)
            mesh_vis = mesh.visibility(direction, dataclasses.replace(config, blur=0.0))
            blurred_vis = mesh.visibility(direction, config)
            rows["gt_proxy"] = mean_psnr(plain.render(direction, visibility=proxy_vis), images, sky_mask)
            rows["gt_mesh"] = mean_psnr(plain.render(direction, visibility=mesh_vis), images, sky_mask)
            rows["gt_mesh_blurred"] = mean_psnr(plain.render(direction, visibility=blurred_vis), images, sky_mask)
            relit_vis = {"gt_proxy": proxy_vis, "gt_mesh": mesh_vis}
            for name, relighter in relighters.items():
                start = time.perf_counter()
                rendered = relighter.render(direction)  # not given v': the rescued pixels mixed (OccupancyConfig.belief)
                seconds = time.perf_counter() - start
                relit_vis[name] = relighter.visibility_at(direction)
                rows[name] = mean_psnr(rendered, images, sky_mask)
                if sky == default.sky:
                    entry["seconds_per_view"].setdefault(name, {}).setdefault("render_per_sun", []).append(
                        seconds / len(stems))
                    if name == "pipeline":
                        figure["tags"][tag] = {"ours": rendered[stems[0]], "truth": images[stems[0]]}
            scores[tag] = rows
            if sky == default.sky:
                for name in ("gt_proxy", "gt_mesh", "gt_caster", "pipeline"):
                    state = shadow_layer(relighters[name], relit_vis[name]) if name in relighters else relit_vis[name]
                    entry["agreement"][tag][name] = agreement(state)
                    entry["agreement_interior"][tag][name] = agreement(state, vis)
                entry["mesh_visibility_iou"][tag] = {}
                for label, visibility in (("sharp", mesh_vis), ("blurred", blurred_vis)):
                    ious = []
                    for s in stems:
                        scored = ~sky_mask[s]
                        ours, exact = (visibility[s] < 0.5) & scored, ~vis[s] & scored
                        ious.append((ours & exact).sum() / max((ours | exact).sum(), 1))
                    entry["mesh_visibility_iou"][tag][label] = float(np.mean(ious))
            print(f"  sky={sky:5s} {tag:6s} " + " ".join(f"{k} {v['mean']:.2f}" for k, v in rows.items()), flush=True)
        entry["psnr"][sky] = scores
        print(f"  sky={sky:5s} capture: " + " ".join(f"{k} {v:.2f}" for k, v in entry["capture_psnr"][sky].items()),
              flush=True)
    for name in ("gt_caster", "pipeline"):
        renders = entry["seconds_per_view"][name].pop("render_per_sun")
        entry["seconds_per_view"][name]["render_per_sun"] = float(np.mean(renders))
    entry["better_sky"] = {
        row: max(SKY_ADJUSTMENTS, key=lambda sky: np.mean([entry["psnr"][sky][t][row]["mean"] for t in tags]))
        for row in ROWS[1:]}
    if not SKIP_CASTER_STUDY[0]:
        entry["caster_study"] = caster_study(scene, tracer, ground_truth, result, tags, inputs, sky_mask, agreement)
    entry["agreement_points"] = len(points)
    return entry, figure


def caster_study(scene, tracer, ground_truth, result, tags, inputs, sky_mask, agreement) -> dict:
    """Rows (d) and (e) under other caster options (the default environment adjustment), and their
    cross-view agreement away from the true edges (``agreement(visibility, true_lit)``)."""
    out = {}
    default = relight_config()
    variants = {"default (multiview votes, own casters)": default,
                "multiview votes, merged caster": relight_config(casters="merged"),
                "paper (own view's votes, full completion, own casters)": relight_config(method="paper"),
                "paper, merged caster": relight_config(method="paper", casters="merged"),
                "default, completion_distance 0": relight_config(completion_distance=0.0),
                "default, min_proxy_hits 0": relight_config(min_proxy_hits=0.0),
                "default, min_cluster 20": relight_config(min_cluster=20),
                "default, the paper's cluster rule alone (support_radius 0)": relight_config(support_radius=0),
                "default, no blur": relight_config(blur=0.0),
                "default, dropped clusters brought into light (dropped light, the paper)": relight_config(dropped="light"),
                "default, dropped clusters moved like every pixel (dropped none)": relight_config(dropped="none"),
                "default, unexplained pixels moved too (consistency None)": relight_config(consistency=None),
                "default, each view alone (fusion None)": relight_config(fusion=None),
                "default, fused over every view (fusion all)": relight_config(fusion="all"),
                "default, no anchor (anchor None, the paper: v' = C(d'))": relight_config(anchor=None),
                "default, the captured shadow the caster does not cast kept (anchor shadow)": relight_config(anchor="shadow"),
                "default, the capture v_sun plus the caster's change (anchor both)": relight_config(anchor="both"),
                "default, the receivers' normals not snapped to the planes (planes None; the layers keep theirs)":
                    relight_config(planes=None)}
    for label, config in variants.items():
        out[label] = {}
        for name, decomposition in (("gt_caster", ground_truth), ("pipeline", result)):
            relighter = Relighter(decomposition, scene, config=config, tracer=tracer)
            row = {"triangles": len(relighter.caster.triangles), "agreement_interior": {}}
            suns = {"capture": (relighter.sun, inputs, None)} | {t: (d, im, vis) for t, (d, im, vis) in tags.items()}
            for tag, (direction, images, true_lit) in suns.items():
                visibility = relighter.visibility_at(direction)
                row[tag] = mean_psnr(relighter.render(direction), images, sky_mask)["mean"]
                if true_lit is not None:
                    row["agreement_interior"][tag] = agreement(shadow_layer(relighter, visibility), true_lit)
            out[label][name] = row
        scores = [f"{n} " + " ".join(f"{t} {v:.2f}" for t, v in r.items() if t not in ("triangles", "agreement_interior"))
                  for n, r in out[label].items()]
        print(f"  caster study: {label:48s} " + " ".join(scores), flush=True)
    return out


def upscaled(scene, decomposition, size: tuple[int, int]) -> tuple:
    """The scene's views and the decomposition's layers resampled to ``size`` (W, H) pixels.

    The views as :func:`bench_distributed.upsampled` resamples them; the shading layers
    bilinearly, the visibility and the labels by nearest neighbour; the proxy and the lighting
    stay. For timing the steps whose cost follows the pixel count at a resolution not rendered.
    """
    import cv2

    from mvintrinsic.results import Decomposition, IntrinsicLayers

    def resize(array, nearest=False):
        return cv2.resize(np.ascontiguousarray(array), size,
                          interpolation=cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR)

    layers = {s: IntrinsicLayers(s, reflectance=resize(x.reflectance), sun_shading=resize(x.sun_shading),
                                 sky_shading=resize(x.sky_shading), indirect_shading=resize(x.indirect_shading),
                                 visibility=resize(x.visibility, True), shadow_labels=resize(x.shadow_labels, True))
              for s, x in decomposition.layers.items()}
    return upsampled(scene, *size), Decomposition(layers, decomposition.lighting)


def time_scene(folder: Path, n_suns: int = 5, size: tuple[int, int] | None = None,
               config: RelightConfig | None = None) -> dict:
    """Seconds per view to build the relighter of the ground-truth layers and to relight one sun.

    For scenes without relit renders (e.g. the 1000x750 speed scene): the caster is built from the
    ground-truth labels and ``n_suns`` suns 5 to 25 degrees of azimuth from the capture are
    rendered (:meth:`~mvintrinsic.relight.Relighter.render`: new visibility and shading). With
    ``size`` (W, H) the views and layers are first resampled to it (:func:`upscaled`). ``config``:
    the relighter's (default ``RelightConfig()``; ``--timing``: as ``--timed-occluders`` says).
    """
    scene = load_scene(folder)
    stems = scene.stems
    tracer = Tracer(scene.proxy)
    ground_truth = ground_truth_decomposition(folder, views=list(stems))
    if size is not None:
        scene, ground_truth = upscaled(scene, ground_truth, size)
    start = time.perf_counter()
    relighter = Relighter(ground_truth, scene, tracer=tracer, config=config)
    build = time.perf_counter() - start
    azimuth, elevation = azimuth_elevation(scene.sun.direction, up=scene.up)
    suns = [(azimuth + delta, elevation) for delta in np.linspace(5.0, 25.0, n_suns)]
    relighter.render(suns[0])  # warm-up
    start = time.perf_counter()
    for sun in suns:
        relighter.render(sun)
    per_sun = (time.perf_counter() - start) / n_suns
    h, w = scene.views[0].shape
    out = {"size": f"{w}x{h}", "views": len(stems), "lost_occluders": relighter.config.lost_occluders is not None,
           "occupancy": (None if relighter.config.lost_occluders is None
                         else dataclasses.asdict(relighter.config.lost_occluders)), "proxy_triangles": len(scene.proxy.triangles),
           "build_per_view": build / len(stems), **{k: v / len(stems) for k, v in relighter.timings.items()},
           "render_per_sun_per_view": per_sun / len(stems), "suns": n_suns}
    print(f"{folder.name}: " + " ".join(f"{k} {v:.3f}" if isinstance(v, float) else f"{k} {v}" for k, v in out.items()),
          flush=True)
    return out


def stride_scene(folder: Path, strides: tuple[int, ...] = (2, 3)) -> dict:
    """What :attr:`~mvintrinsic.relight.RelightConfig.ray_stride` costs against casting every pixel.

    The relighter of the ground-truth layers (defaults), for every relit tag of the scene (or,
    without relit renders, suns 15 and 30 degrees of azimuth either side of the capture): the
    share of the non-blurred shadow state that differs from ``ray_stride=1``, the relit PSNR of
    each stride against the path-traced render, and seconds per view of the new visibility.
    One relighter is built per stride and blur (a built relighter's options are read-only: every
    view's per-sun inputs hold them).
    """
    scene = load_scene(folder)
    stems = scene.stems
    ground_truth = ground_truth_decomposition(folder, views=list(stems))
    tracer = Tracer(scene.proxy)
    tags = relit_tags(folder, stems)
    sky_mask = None
    if tags:
        truth = read_ground_truth(folder, views=list(stems))
        sky_mask = {s: truth[s].sky_mask for s in stems}
        suns = {tag: (direction, images) for tag, (direction, images, _) in tags.items()}
    else:
        azimuth, elevation = azimuth_elevation(scene.sun.direction, up=scene.up)
        suns = {f"az{d:+d}": (as_sun_direction((azimuth + d, elevation), up=scene.up), None) for d in (-30, -15, 15, 30)}
    rows: dict = {tag: {} for tag in suns}
    for stride in (1, *strides):
        sharp = Relighter(ground_truth, scene, tracer=tracer, config=relight_config(ray_stride=stride, blur=0.0))
        for tag, (direction, _) in suns.items():
            sharp.visibility_at(direction)  # warm-up of the first sun's caches
            start = time.perf_counter()
            shadow = sharp.visibility_at(direction)
            seconds = (time.perf_counter() - start) / len(stems)
            rows[tag][stride] = {"visibility_seconds_per_view": seconds, "shadow": {s: shadow[s] < 0.5 for s in stems}}
        del sharp
        if tags:
            relighter = Relighter(ground_truth, scene, tracer=tracer, config=relight_config(ray_stride=stride))
            for tag, (direction, images) in suns.items():
                rows[tag][stride]["psnr"] = mean_psnr(relighter.render(direction), images, sky_mask)["mean"]
            del relighter
    out = {}
    for tag, by_stride in rows.items():
        for stride in strides:
            row = by_stride[stride]
            row["changed_share"] = float(np.mean([np.mean(row["shadow"][s] != by_stride[1]["shadow"][s]) for s in stems]))
            if tags:
                row["psnr_change"] = row["psnr"] - by_stride[1]["psnr"]
        for row in by_stride.values():
            del row["shadow"]
        out[tag] = {str(k): v for k, v in by_stride.items()}
        print(f"{folder.name} {tag}: " + " ".join(
            f"stride {k} changed {v['changed_share']:.6f} " + (f"dPSNR {v['psnr_change']:+.4f} " if "psnr_change" in v else "")
            + f"{v['visibility_seconds_per_view'] * 1e3:.1f} ms (stride 1 {by_stride[1]['visibility_seconds_per_view'] * 1e3:.1f})"
            for k, v in by_stride.items() if k != 1), flush=True)
    return out


#: The share of the new shadow state kept from the caster in the ``persistence`` row of
#: :func:`softness_scene` (the rest is the capture visibility).
PERSISTENCE_WEIGHT = 0.7


def _relit_scene(folder: Path, what: str) -> tuple:
    """The scene, its relit tags (:func:`relit_tags`; ``what``, the mode, needs them) and the true sky masks."""
    scene = load_scene(folder)
    tags = relit_tags(folder, scene.stems)
    if not tags:
        raise ValueError(f"{folder}: {what} needs relit renders (gt/relit/<tag>)")
    truth = read_ground_truth(folder, views=list(scene.stems))
    return scene, tags, {s: truth[s].sky_mask for s in scene.stems}


def _variable_blur(image: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """``image`` (H, W) blurred by a Gaussian whose standard deviation ``sigma`` (H, W, pixels) varies.

    Linear interpolation between a stack of uniform blurs (0 to 12 px; wider is clipped).
    """
    levels = np.array([0.0, 0.5, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 8.0, 12.0])
    stack = np.stack([image if s == 0 else ndimage.gaussian_filter(image, s, mode="nearest") for s in levels])
    sigma = np.clip(sigma, levels[0], levels[-1])
    upper = np.clip(np.searchsorted(levels, sigma), 1, len(levels) - 1)
    weight = (sigma - levels[upper - 1]) / (levels[upper] - levels[upper - 1])
    rows, cols = np.indices(image.shape)
    return ((1 - weight) * stack[upper - 1, rows, cols] + weight * stack[upper, rows, cols]).astype(np.float32)


def softness_scene(folder: Path) -> dict:
    """How soft row (d)'s new shadow should be: relit PSNR of the ground-truth layers with our caster.

    Per relit tag, the sharp new visibility (``ray_stride=1``, no blur) softened by:

    * ``paper``: a Gaussian of ``RelightConfig.blur`` = 1 px (the default);
    * ``sharp``: nothing;
    * ``penumbra``: a Gaussian whose width is the penumbra of the sun's disc,
      ``t tan(angular_radius) / footprint`` pixels, ``t`` the distance along the new sun ray to
      the occluder (caster or proxy completion; lit pixels take the nearest shadow pixel's),
      ``footprint`` the pixel's size on the receiver (metres per pixel);
    * ``penumbra_and_paper``: both widths in quadrature;
    * ``persistence``: :data:`PERSISTENCE_WEIGHT` of the paper's row plus the rest of the capture
      visibility (blurred alike): at a small sun move most shadows stay, and where the caster's
      predicted change is uncertain the blend is the least-squares answer.
    """
    scene, tags, sky_mask = _relit_scene(folder, "--softness")
    stems = scene.stems
    ground_truth = ground_truth_decomposition(folder, views=list(stems))
    tracer = Tracer(scene.proxy)
    config = relight_config(ray_stride=1, blur=0.0)
    relighter = Relighter(ground_truth, scene, config=config, tracer=tracer)
    blur = relight_config().blur
    cameras = {view.stem: view.camera for view in scene.views}
    blocked = {s: relighter.shadow_casters[s].completion_blocked(tracer, relighter.excluded_primitives)
               for s in stems}
    capture = {s: ndimage.gaussian_filter(np.asarray(relighter.visibility[s], np.float32), blur, mode="nearest")
               for s in stems}
    out = {}
    for tag, (direction, images, _) in tags.items():
        sharp = relighter.visibility_at(direction)
        rows = {name: {} for name in ("paper", "sharp", "penumbra", "penumbra_and_paper", "persistence")}
        for s in stems:
            shape = sharp[s].shape
            origins = relighter.receivers[s].reshape(-1, 3) + config.ray_offset * direction
            t = relighter.shadow_casters[s].hit_distance(origins, direction).astype(np.float64)
            t_proxy, primitive = tracer.first_primitive(origins, direction)
            completes = ~blocked[s][primitive] & (t_proxy + config.ray_offset >= relighter.completion_distance)
            t = np.where(completes, np.minimum(t, t_proxy), t).reshape(shape)
            t = np.where(sharp[s] < 0.5, t, np.inf)
            known = np.isfinite(t)
            if known.any():
                nearest = ndimage.distance_transform_edt(~known, return_distances=False, return_indices=True)
                t = t[nearest[0], nearest[1]]
            else:
                t = np.zeros(shape)
            footprint = np.linalg.norm(relighter.receivers[s] - cameras[s].center, axis=-1) / min(cameras[s].focal)
            width = t * np.tan(scene.sun.angular_radius) / footprint
            paper = ndimage.gaussian_filter(sharp[s], blur, mode="nearest")
            rows["paper"][s] = paper
            rows["sharp"][s] = sharp[s]
            rows["penumbra"][s] = _variable_blur(sharp[s], width)
            rows["penumbra_and_paper"][s] = _variable_blur(sharp[s], np.hypot(width, blur))
            rows["persistence"][s] = PERSISTENCE_WEIGHT * paper + (1 - PERSISTENCE_WEIGHT) * capture[s]
        out[tag] = {name: mean_psnr(relighter.render(direction, visibility=v), images, sky_mask)["mean"]
                    for name, v in rows.items()}
        print(f"{folder.name} {tag}: " + " ".join(f"{k} {v:.2f}" for k, v in out[tag].items()), flush=True)
    return out


def lost_occluders_scene(folder: Path) -> dict:
    """Rows (a), (c), (d), (e) without (``lost_occluders=None``, the paper's rule) and with ``RelightConfig.lost_occluders``.

    Per option (``off``, ``lost_occluders``: ``OccupancyConfig()``; runs before 2026-11-27 call the option
    off ``default``) and row (``gt_caster`` (d), ``pipeline`` (e)): the
    relit PSNR per tag, the capture-sun PSNR against the input, the relighter's build seconds per
    view and the share of the views' pixels in dropped shadow clusters. ``input`` (a) and
    ``gt_mesh`` (c) per tag as in the main run.
    """
    scene, tags, sky_mask = _relit_scene(folder, "--lost-occluders")
    stems = scene.stems
    tracer = Tracer(scene.proxy)
    layers = {"gt_caster": ground_truth_decomposition(folder, views=list(stems)),
              "pipeline": decompose(scene, tracer=tracer, config=pipeline_config())}
    inputs = {v.stem: v.image for v in scene.views}
    mesh = MeshShadow(folder, scene)
    plain = Relighter(layers["gt_caster"], scene, config=relight_config(dropped="none"), tracer=tracer)
    out = {"input": {}, "gt_mesh": {}}
    for tag, (direction, images, _) in tags.items():
        out["input"][tag] = mean_psnr(inputs, images, sky_mask)["mean"]
        out["gt_mesh"][tag] = mean_psnr(mesh.render(plain, direction, relight_config()), images, sky_mask)["mean"]
    for option, config in (("off", relight_config(lost_occluders=None)), ("lost_occluders", relight_config(lost_occluders=OccupancyConfig()))):
        out[option] = {}
        for row, decomposition in layers.items():
            start = time.perf_counter()
            relighter = Relighter(decomposition, scene, config=config, tracer=tracer)
            build = (time.perf_counter() - start) / len(stems)
            entry = {"build_seconds_per_view": build, "timings_per_view": {k: v / len(stems) for k, v in relighter.timings.items()},
                     "dropped_share": float(np.mean([relighter.casters[s].dropped.mean() for s in stems])),
                     "capture": mean_psnr(relighter.render(relighter.sun), inputs, sky_mask)["mean"],
                     "psnr": {tag: mean_psnr(relighter.render(direction), truth, sky_mask)["mean"]
                              for tag, (direction, truth, _) in tags.items()}}
            out[option][row] = entry
            print(f"{folder.name} {option:14s} {row:9s} build {build:.2f} s/view dropped {entry['dropped_share']:.3f} "
                  + " ".join(f"{t} {v:.2f}" for t, v in entry["psnr"].items()), flush=True)
    return out


#: The rows of ``--sun-radiance`` (:func:`sun_radiance_scene`).
SUN_RADIANCE_ROWS = ("input", "gt_caster", "pipeline", "pipeline_true_sun", "pipeline_true_level", "pipeline_true_colour")


def with_sun_radiance(decomposition, images: dict, factor: np.ndarray):
    """``decomposition`` with ``L_sun`` multiplied by ``factor`` ``(3,)`` and the reflectance made again.

    ``S_sun`` (every view's layer and ``lighting.sun_radiance``) is scaled; the reflectance is
    ``I / (v_sun S_sun + S_sky + S_ind)`` (Eq. 2) again, so the layers still give the input at the capture
    sun; pixels whose total shading vanishes keep theirs. ``images``: the input image of every view. An
    oracle when ``factor`` is the truth over the estimate.
    """
    factor = np.asarray(factor, dtype=np.float64)
    layers = {}
    for stem, layer in decomposition.layers.items():
        sun = layer.sun_shading * factor.astype(layer.sun_shading.dtype)
        again = image_model.reflectance(images[stem], layer.sky_shading, layer.indirect_shading, layer.visibility, sun)
        reflectance = np.where(np.isfinite(again), again, layer.reflectance).astype(layer.reflectance.dtype)
        layers[stem] = dataclasses.replace(layer, sun_shading=sun, reflectance=reflectance)
    lighting = dataclasses.replace(decomposition.lighting,
                                   sun_radiance=np.asarray(decomposition.lighting.sun_radiance) * factor)
    return dataclasses.replace(decomposition, layers=layers, lighting=lighting)


def sun_radiance_scene(folder: Path) -> dict:
    """What the pipeline's ``L_sun`` costs the relit images (:data:`SUN_RADIANCE_ROWS`; an oracle study).

    Rows (a), (d) and (e) as in :func:`run_scene` (default :class:`~mvintrinsic.relight.RelightConfig`),
    then row (e) with the pipeline's ``L_sun`` replaced by :func:`with_sun_radiance`: by the truth
    (``pipeline_true_sun``), by its level only (the estimate times the ratio of the luminances,
    :func:`mvintrinsic.image_model.luminance`: ``pipeline_true_level``), and by its colour only (the truth scaled to the
    estimate's luminance: ``pipeline_true_colour``). Also the estimate and the truth.
    """
    scene, tags, sky_mask = _relit_scene(folder, "--sun-radiance")
    stems = scene.stems
    tracer = Tracer(scene.proxy)
    inputs = {v.stem: v.image for v in scene.views}
    truth_layers = ground_truth_decomposition(folder, views=list(stems))
    result = decompose(scene, tracer=tracer, config=pipeline_config())
    estimate = np.asarray(result.lighting.sun_radiance, dtype=np.float64)
    true_sun = np.asarray(truth_layers.lighting.sun_radiance, dtype=np.float64)
    level = image_model.luminance(true_sun) / image_model.luminance(estimate)
    factors = {"pipeline": np.ones(3), "pipeline_true_sun": true_sun / estimate,
               "pipeline_true_level": np.full(3, level), "pipeline_true_colour": true_sun / estimate / level}
    relighters = {"gt_caster": Relighter(truth_layers, scene, config=relight_config(), tracer=tracer)}
    for row, factor in factors.items():
        relighters[row] = Relighter(with_sun_radiance(result, inputs, factor), scene, config=relight_config(), tracer=tracer)
    out = {"sun_radiance": estimate.tolist(), "true_sun_radiance": true_sun.tolist(),
           "over_truth": (estimate / true_sun).tolist(), "psnr": {}}
    for tag, (direction, images, _) in tags.items():
        rows = {"input": mean_psnr(inputs, images, sky_mask)["mean"]}
        rows.update({row: mean_psnr(r.render(direction), images, sky_mask)["mean"] for row, r in relighters.items()})
        out["psnr"][tag] = rows
        print(f"{folder.name} {tag}: " + " ".join(f"{k} {v:.2f}" for k, v in rows.items()), flush=True)
    return out


def _minus_input_at_15(study: dict, rows: Sequence[str]) -> dict:
    """Per row of ``rows`` (after ``"input"``), the mean over the scenes' +-15 degree suns of the row minus (a);
    ``study``: scene -> ``{"psnr": {tag: {row: dB}}}``."""
    gains = {row: [entry["psnr"][tag][row] - entry["psnr"][tag]["input"] for entry in study.values()
                   for tag in ("az+15", "az-15") if tag in entry["psnr"]] for row in rows[1:]}
    return {row: {"minus_input_mean": float(np.mean(v)), "scene_suns": len(v)} for row, v in gains.items()}


def sun_radiance_summary(study: dict) -> dict:
    """:func:`_minus_input_at_15` of the rows :data:`SUN_RADIANCE_ROWS`."""
    return _minus_input_at_15(study, SUN_RADIANCE_ROWS)


#: The rows of ``--true-labels`` (:func:`true_labels_scene`): the layers (``pipeline``: Steps 1-4 as they
#: are; ``true_labels``: Steps 3-4 on the true labels; ``gt``: the true layers, row (d)) and the relighter
#: (none: the default; ``option``: ``lost_occluders``; ``labels_caster``: and ``caster_pixels="labels"``).
TRUE_LABEL_ROWS = ("input", "pipeline", "pipeline_option", "pipeline_option_labels_caster", "true_labels",
                   "true_labels_option", "true_labels_option_labels_caster", "gt_option")


@contextlib.contextmanager
def _true_shadow_labels(truth: dict):
    """Steps 3-4 of :func:`~mvintrinsic.decompose` on the true shadow labels (an oracle).

    Replaces, for the duration, the pipeline's multi-view labelling (``pipeline._multiview_labels``,
    private) by one that keeps its output but sets every decided pixel's label from
    ``gt/sun_visibility`` (lit at 0.5 or more) and its visibility to the truth's; the matting then
    solves ``v_sun`` for those labels and Step 4 fuses as usual. ``truth``: stem -> ViewGroundTruth.
    """
    from mvintrinsic import pipeline

    original = pipeline._multiview_labels

    def labelled(scene, quantities, sun_radiance, *, config, timings, progress):
        shared = original(scene, quantities, sun_radiance, config=config, timings=timings, progress=progress)
        views = {}
        for stem, found in shared.views.items():
            lit = np.asarray(truth[stem].sun_visibility, dtype=np.float64)
            if lit.shape != found.labels.shape:
                raise ValueError(f"{stem}: the labelling runs at {found.labels.shape}, gt/sun_visibility is {lit.shape}: "
                                 "--true-labels needs the views decomposed at their own size")
            decided = found.labels != SHADOW_LABELS["undecided"]
            labels = np.where(decided, np.where(lit >= 0.5, SHADOW_LABELS["lit"], SHADOW_LABELS["shadow"]), found.labels)
            views[stem] = dataclasses.replace(found, labels=labels.astype(np.uint8),
                                              visibility=np.where(decided, lit, np.nan).astype(np.float32))
        return dataclasses.replace(shared, views=views)

    pipeline._multiview_labels = labelled
    try:
        yield
    finally:
        pipeline._multiview_labels = original


def true_labels_scene(folder: Path) -> dict:
    """Row (e) with Steps 3-4 fed the true shadow labels (:data:`TRUE_LABEL_ROWS`; an oracle study).

    The multi-view labelling needs ``Config().shadow.method == "multiview"`` (the default); with the
    paper's per-view labelling the study refuses to run.
    """
    if Config().shadow.method != "multiview":
        raise ValueError("--true-labels replaces the multi-view labelling; the default config does not use it")
    scene, tags, sky_mask = _relit_scene(folder, "--true-labels")
    stems = scene.stems
    tracer = Tracer(scene.proxy)
    inputs = {v.stem: v.image for v in scene.views}
    truth = read_ground_truth(folder, views=list(stems))
    layers = {"pipeline": decompose(scene, tracer=tracer, config=pipeline_config())}
    with _true_shadow_labels(truth):
        layers["true_labels"] = decompose(scene, tracer=tracer, config=pipeline_config())
    layers["gt"] = ground_truth_decomposition(folder, views=list(stems))
    option = relight_config(lost_occluders=OccupancyConfig())
    configs = {"": relight_config(), "_option": option,
               "_option_labels_caster": dataclasses.replace(option, caster_pixels="labels")}
    relighters = {f"{name}{suffix}": Relighter(layers[name], scene, config=config, tracer=tracer)
                  for name in ("pipeline", "true_labels") for suffix, config in configs.items()}
    relighters["gt_option"] = Relighter(layers["gt"], scene, config=option, tracer=tracer)
    out = {"psnr": {}, "capture": {row: mean_psnr(r.render(r.sun), inputs, sky_mask)["mean"]
                                   for row, r in relighters.items()}}
    for tag, (direction, images, _) in tags.items():
        rows = {"input": mean_psnr(inputs, images, sky_mask)["mean"]}
        rows.update({row: mean_psnr(r.render(direction), images, sky_mask)["mean"] for row, r in relighters.items()})
        out["psnr"][tag] = {row: rows[row] for row in TRUE_LABEL_ROWS}
        print(f"{folder.name} {tag}: " + " ".join(f"{k} {v:.2f}" for k, v in out["psnr"][tag].items()), flush=True)
    return out


def true_labels_summary(study: dict) -> dict:
    """:func:`_minus_input_at_15` of the rows :data:`TRUE_LABEL_ROWS`."""
    return _minus_input_at_15(study, TRUE_LABEL_ROWS)


def lost_occluders_summary(study: dict) -> dict:
    """Means over the scenes' +-15 degree suns (the tags ``az+15``, ``az-15``) of (c) - (d) and (e) - (a)."""
    out = {}
    for option in ("off", "lost_occluders"):
        gaps, gains = [], []
        for entry in study.values():
            for tag in ("az+15", "az-15"):
                if tag in entry["input"]:
                    gaps.append(entry["gt_mesh"][tag] - entry[option]["gt_caster"]["psnr"][tag])
                    gains.append(entry[option]["pipeline"]["psnr"][tag] - entry["input"][tag])
        out[option] = {"c_minus_d_mean": float(np.mean(gaps)), "c_minus_d_max": float(np.max(gaps)),
                       "e_minus_a_mean": float(np.mean(gains)), "e_minus_a_min": float(np.min(gains)), "scene_suns": len(gaps)}
    return out


def best_visibility(relighter: Relighter, direction: np.ndarray, truth: dict, sky_mask: dict) -> dict:
    """Per view, the visibility in [0, 1] that brings the relit image nearest the path-traced one.

    The relit image is linear in the visibility, ``I'(v) = A + v (B - A)`` with ``A`` the render
    at ``v = 0`` and ``B`` at ``v = 1`` (:meth:`~mvintrinsic.relight.Relighter.render`), so per
    pixel the least-squares ``v`` against the truth (clipped as :func:`relit_psnr` clips it) over
    the three channels is ``<T - A, B - A> / |B - A|^2``, clipped to [0, 1]: no shadow layer,
    however it is computed, relights these layers closer to the truth (up to the metric's clip of
    the estimate).
    """
    zero = relighter.render(direction, visibility={s: np.zeros(sky_mask[s].shape, np.float32) for s in truth})
    one = relighter.render(direction, visibility={s: np.ones(sky_mask[s].shape, np.float32) for s in truth})
    out = {}
    for s, image in truth.items():
        image = np.asarray(image, dtype=np.float64)
        mask = ~sky_mask[s] & np.isfinite(image).all(axis=-1)
        target = np.clip(np.nan_to_num(image), 0.0, float(np.percentile(image[mask], CLIP_PERCENTILE)))
        base = zero[s].astype(np.float64)
        step = one[s].astype(np.float64) - base
        v = ((target - base) * step).sum(axis=-1) / np.maximum((step * step).sum(axis=-1), 1e-30)
        out[s] = np.clip(np.nan_to_num(v), 0.0, 1.0).astype(np.float32)
    return out


def bounds_scene(folder: Path) -> dict:
    """What the shadow layer can still give: the layers relit with ideal shadows (:data:`BOUND_ROWS`).

    The environment adjustment is the default (``RelightConfig.sky``); rows (a), (c), (d) and (e)
    as in :func:`run_scene`, then, for the ground-truth and the pipeline's layers (both with
    ``dropped="none"``, as row (c)):

    * ``*_mesh``: the exact mesh's shadow (row (c)'s visibility);
    * ``*_truth``: the path tracer's visibility at the new sun (``gt/relit/<tag>/sun_visibility``);
    * ``*_best``: :func:`best_visibility`, the bound of every shadow layer for these layers.
    """
    scene, tags, sky_mask = _relit_scene(folder, "--bounds")
    stems = scene.stems
    inputs = {v.stem: v.image for v in scene.views}
    tracer = Tracer(scene.proxy)
    print(f"{folder.name}: decomposing {len(stems)} views", flush=True)
    layers = {"gt": ground_truth_decomposition(folder, views=list(stems)), "pipeline": decompose(scene, tracer=tracer, config=pipeline_config())}
    config = relight_config()
    ours = {name: Relighter(d, scene, config=config, tracer=tracer) for name, d in layers.items()}
    plain = {name: Relighter(d, scene, config=dataclasses.replace(config, dropped="none"), tracer=tracer)
             for name, d in layers.items()}
    mesh = MeshShadow(folder, scene)
    out = {}
    for tag, (direction, images, vis) in tags.items():
        exact = mesh.visibility(direction, dataclasses.replace(config, blur=0.0))
        true_vis = {s: np.asarray(vis[s], np.float32) for s in stems}
        rows = {"input": inputs, "gt_caster": ours["gt"].render(direction), "pipeline": ours["pipeline"].render(direction)}
        for name, relighter in plain.items():  # gt_mesh is row (c)
            rows[f"{name}_mesh"] = relighter.render(direction, visibility=exact)
            rows[f"{name}_truth"] = relighter.render(direction, visibility=true_vis)
            rows[f"{name}_best"] = relighter.render(
                direction, visibility=best_visibility(relighter, direction, images, sky_mask))
        out[tag] = {name: mean_psnr(rows[name], images, sky_mask)["mean"] for name in BOUND_ROWS}
        print(f"{folder.name} {tag}: " + " ".join(f"{k} {v:.2f}" for k, v in out[tag].items()), flush=True)
    return out


RECEIVER_ROWS = ("input", "gt_mesh", "gt_caster", "gt_caster_exact_receivers", "exact_at_proxy", "exact_at_proxy_far",
                 "exact_at_proxy_far_and_caster")


@contextlib.contextmanager
def _exact_receivers(scene, mesh: MeshShadow):
    """Within the block, :class:`Relighter` places every pixel's receiver on the exact mesh (an oracle).

    ``receiver_points`` is swapped, where the relighter's view geometry looks it up
    (:mod:`mvintrinsic.shadow_caster`), for one returning the exact mesh's point of the view whose
    camera it is given (the proxy's where the exact mesh has none); the proxy still gives the normals,
    the caster distances and the completion. :func:`_exact_receivers_built` checks that a relighter
    built in the block took them. (From 2026-11-27, when the view geometry moved to
    :mod:`~mvintrinsic.shadow_caster`, until 2026-12-08 the swap was made in :mod:`mvintrinsic.relight`, where
    nothing read it: the oracle built the plain relighter. ``results/relight_receivers.json`` is of
    2026-11-25, before.)
    """
    import mvintrinsic.shadow_caster as module

    original = module.receiver_points
    by_center = [(v.camera.center, v.stem) for v in scene.views]

    def exact(camera, depth):
        points = original(camera, depth)
        stem = next(s for c, s in by_center if np.array_equal(c, camera.center))
        ok = np.isfinite(mesh.points[stem]).all(axis=-1)
        return np.where(ok[..., None], mesh.points[stem], points)

    module.receiver_points = exact
    try:
        yield
    finally:
        module.receiver_points = original


def _exact_receivers_built(relighter: Relighter, mesh: MeshShadow) -> Relighter:
    """``relighter``, after checking that its receivers are the exact mesh's wherever the mesh has a point
    (:func:`_exact_receivers`); RuntimeError if they are not."""
    for stem, exact in mesh.points.items():
        found = np.isfinite(exact).all(axis=-1)
        if not np.array_equal(relighter.receivers[stem][found], exact[found]):
            raise RuntimeError(f"view {stem!r}: the relighter built under _exact_receivers has the proxy's receivers")
    return relighter


#: The true shadow states of :func:`error_split`'s classes: at the capture sun, then at the new sun.
TRUE_TRANSITIONS = (("new shadow", True, False), ("stays shadow", False, False), ("stays lit", True, True),
                    ("leaves shadow", False, True))

#: Our states at the new sun, as :func:`error_split` codes them: shadow (visibility < 0.5), lit, and
#: a pixel of a dropped cluster, whose captured shadow stays where it was
#: (``RelightConfig.dropped``: in the shadow layer by default, in the reflectance with ``"light"``).
OURS_STATES = ("shadow", "lit", "dropped")


def error_by_class(estimate: dict, reference: dict, truth: dict, sky_mask: dict, classes: dict,
                   names: Sequence[str]) -> dict:
    """Where a relit image's squared error is, beyond a reference relighting's, by pixel class.

    Per view, both images are clipped as :func:`relit_psnr` clips them and their squared error
    against the truth (summed over the channels) is added up over the non-sky pixels of each
    class: ``classes`` (H, W) int per view stem, an index into ``names``; pixels of any other value
    are not scored.

    Returns
    -------
    dict
        Per class name: ``pixels`` (share of the scored pixels), ``estimate`` and ``reference`` (share
        of that image's summed squared error) and ``excess`` (share of the estimate's squared error
        above the reference's; they sum to 1 over the classes, None when the totals are equal); and
        ``totals``, both mean squared errors per channel.
    """
    sums = np.zeros((len(names), 3))
    total, count = np.zeros(2), 0
    for s, image in truth.items():
        image = np.asarray(image, dtype=np.float64)
        mask = ~np.asarray(sky_mask[s], dtype=bool) & np.isfinite(image).all(axis=-1)
        top = float(np.percentile(image[mask], CLIP_PERCENTILE))
        code = np.asarray(classes[s])
        mask &= (code >= 0) & (code < len(names))
        target = np.clip(np.nan_to_num(image), 0.0, top)
        errors = [((np.clip(np.nan_to_num(np.asarray(x[s], dtype=np.float64)), 0.0, top) - target) ** 2).sum(axis=-1)
                  for x in (estimate, reference)]
        for index in range(len(names)):
            chosen = mask & (code == index)
            sums[index] += (chosen.sum(), errors[0][chosen].sum(), errors[1][chosen].sum())
        total += (errors[0][mask].sum(), errors[1][mask].sum())
        count += int(mask.sum())
    excess = total[0] - total[1]
    out = {name: {"pixels": float(v[0] / count), "estimate": float(v[1] / total[0]),
                  "reference": float(v[2] / total[1]), "excess": float((v[1] - v[2]) / excess) if excess else None}
           for name, v in zip(names, sums, strict=True)}
    out["totals"] = {"estimate_mse": float(total[0] / count / 3), "reference_mse": float(total[1] / count / 3)}
    return out


def error_split(estimate: dict, reference: dict, truth: dict, sky_mask: dict, capture_lit: dict, new_lit: dict,
                ours: dict) -> dict:
    """:func:`error_by_class` by shadow state: the true transition (:data:`TRUE_TRANSITIONS`, from
    ``capture_lit`` and ``new_lit``, (H, W) bool per view stem) and our state (``ours``, (H, W) int per
    stem, an index into :data:`OURS_STATES`); the classes are named ``"<transition>, ours <state>"``."""
    names = [f"{t}, ours {o}" for t, *_ in TRUE_TRANSITIONS for o in OURS_STATES]
    classes = {}
    for s in truth:
        code = np.full(np.shape(ours[s]), -1, dtype=np.int64)
        for index, (_, capture, new) in enumerate(TRUE_TRANSITIONS):
            chosen = (capture_lit[s] == capture) & (new_lit[s] == new)
            code[chosen] = index * len(OURS_STATES) + np.asarray(ours[s])[chosen]
        classes[s] = code
    return error_by_class(estimate, reference, truth, sky_mask, classes, names)


def _bound_and_caster(folder: Path, what: str) -> tuple:
    """What rows (c) and (d) of a study need: the scene, its relit tags, the true sky masks (:func:`_relit_scene`),
    the ground-truth layers' default :class:`~mvintrinsic.relight.Relighter` (row (d)), the same layers with
    ``dropped="none"`` (row (c)'s relighter) and the exact mesh's shadows (:class:`MeshShadow`)."""
    scene, tags, sky_mask = _relit_scene(folder, what)
    ground_truth = ground_truth_decomposition(folder, views=list(scene.stems))
    tracer = Tracer(scene.proxy)
    config = relight_config()
    ours = Relighter(ground_truth, scene, config=config, tracer=tracer)
    plain = Relighter(ground_truth, scene, config=dataclasses.replace(config, dropped="none"), tracer=tracer)
    return scene, tags, sky_mask, ours, plain, MeshShadow(folder, scene)


def error_split_scene(folder: Path) -> dict:
    """Where row (d)'s error is beyond row (c)'s (:func:`error_split`), per relit tag.

    Row (d): the ground-truth layers relit by the default :class:`~mvintrinsic.relight.Relighter`
    (our caster from the true labels); row (c): the same layers with the exact mesh's shadow. The
    true states are ``gt/sun_visibility`` and ``gt/relit/<tag>/sun_visibility``; ours is the
    relit visibility, and ``dropped`` for the pixels of the dropped clusters (:data:`OURS_STATES`).
    """
    scene, tags, sky_mask, ours, plain, mesh = _bound_and_caster(folder, "--error-split")
    stems = scene.stems
    truth = read_ground_truth(folder, views=list(stems))
    capture_lit = {s: np.asarray(truth[s].sun_visibility, dtype=np.float64) >= 0.5 for s in stems}
    out = {}
    for tag, (direction, images, visibility) in tags.items():
        relit = ours.visibility_at(direction)
        state = {s: np.where(ours.casters[s].dropped, 2, (relit[s] >= 0.5).astype(np.int64)) for s in stems}
        out[tag] = error_split(ours.render(direction, visibility=relit), mesh.render(plain, direction, ours.config),
                               images, sky_mask, capture_lit, {s: np.asarray(visibility[s], bool) for s in stems},
                               state)
        print(f"{folder.name} {tag}: " + "; ".join(f"{name} {v['pixels']:.3f} px {v['excess']:+.2f}"
                                                   for name, v in out[tag].items()
                                                   if name != "totals" and abs(v["excess"] or 0) >= 0.02), flush=True)
    return out


#: Upper bounds (metres) of :func:`occluder_distance_scene`'s classes of the exact mesh's first occluder
#: along a sun ray from the exact receiver; a last class, ``lit``, for the rays that meet nothing.
OCCLUDER_DISTANCE_BOUNDS = (0.6, 2.0, 5.0)
OCCLUDER_DISTANCE_NAMES = ("< 0.6 m", "0.6-2 m", "2-5 m", ">= 5 m", "lit")


def occluder_distance_class(distance: np.ndarray) -> np.ndarray:
    """The index into :data:`OCCLUDER_DISTANCE_NAMES` of each first-occluder ``distance`` (metres, ``inf``
    for a ray that meets nothing, NaN for no receiver: -1, not scored); same shape, int64."""
    distance = np.asarray(distance, dtype=np.float64)
    code = np.searchsorted(np.asarray(OCCLUDER_DISTANCE_BOUNDS), distance, side="right").astype(np.int64)
    code[np.isinf(distance)] = len(OCCLUDER_DISTANCE_NAMES) - 1
    code[np.isnan(distance)] = -1
    return code


def exact_occluder_distance(mesh: MeshShadow, stem: str, direction: np.ndarray, offset: float) -> np.ndarray:
    """(H, W) metres from each exact receiver of view ``stem`` along ``direction`` to the exact mesh's first
    hit (the ray starting ``offset`` toward the sun, as every shadow ray): ``inf`` where it meets nothing, NaN
    at a non-finite receiver (:class:`MeshShadow` fills a pixel whose camera ray misses the mesh from the nearest
    hit; the sky is left out by the scoring's mask)."""
    points = mesh.points[stem].reshape(-1, 3)
    valid = np.isfinite(points).all(axis=1)
    distance = np.full(len(points), np.nan)
    t, _ = mesh.tracer.first_primitive(points[valid], direction, t_min=offset)
    distance[valid] = t
    return distance.reshape(mesh.points[stem].shape[:2])


def occluder_distance_scene(folder: Path) -> dict:
    """Where row (d)'s error is beyond row (c)'s (:func:`error_by_class`), by how far the exact mesh's
    occluder is along the capture sun and along the new sun from the pixel's exact receiver (classes
    ``"capture <a>, new <b>"`` of :data:`OCCLUDER_DISTANCE_NAMES`; ``lit``: nothing blocks the ray), per
    relit tag: which occluders' shadows the caster gets wrong (near ones, ledges and recesses the proxy
    smooths, or far ones, crowns and posts it loses). Row (d) is the default relighter's image as the main run
    scores it (:meth:`~mvintrinsic.relight.Relighter.render` without a given ``v'``), row (c) as in
    :func:`error_split_scene`.
    """
    scene, tags, sky_mask, ours, plain, mesh = _bound_and_caster(folder, "--occluder-distance")
    stems, offset = scene.stems, ours.config.ray_offset
    names = [f"capture {a}, new {b}" for a in OCCLUDER_DISTANCE_NAMES for b in OCCLUDER_DISTANCE_NAMES]
    n = len(OCCLUDER_DISTANCE_NAMES)
    capture = {s: occluder_distance_class(exact_occluder_distance(mesh, s, ours.sun, offset)) for s in stems}
    out = {}
    for tag, (direction, images, _) in tags.items():
        new = {s: occluder_distance_class(exact_occluder_distance(mesh, s, direction, offset)) for s in stems}
        classes = {s: np.where((capture[s] >= 0) & (new[s] >= 0), capture[s] * n + new[s], -1) for s in stems}
        out[tag] = error_by_class(ours.render(direction), mesh.render(plain, direction, ours.config), images,
                                  sky_mask, classes, names)
        print(f"{folder.name} {tag}: " + "; ".join(f"{name} {v['pixels']:.3f} px {v['excess']:+.2f}"
                                                   for name, v in out[tag].items()
                                                   if name != "totals" and abs(v["excess"] or 0) >= 0.05), flush=True)
    return out


#: :func:`occluder_distance_summary`'s groups: the true transition, then the occluder distance (metres; of the
#: new sun's occluder for a new shadow, of the capture's for a shadow that leaves).
OCCLUDER_DISTANCE_GROUPS = (("new shadow", "< 0.6 m"), ("new shadow", "0.6-2 m"), ("new shadow", ">= 2 m"),
                            ("shadow leaves", "< 0.6 m"), ("shadow leaves", "0.6-2 m"), ("shadow leaves", ">= 2 m"),
                            ("stays shadow", "any"), ("stays lit", "any"))
#: The classes of :data:`OCCLUDER_DISTANCE_NAMES` each group distance takes in.
_GROUP_DISTANCES = {"< 0.6 m": ("< 0.6 m",), "0.6-2 m": ("0.6-2 m",), ">= 2 m": ("2-5 m", ">= 5 m"),
                    "any": OCCLUDER_DISTANCE_NAMES[:-1]}


def occluder_distance_summary(study: dict) -> dict:
    """Per scene and tag of :func:`occluder_distance_scene`'s output, the share of row (d)'s excess squared
    error in each of :data:`OCCLUDER_DISTANCE_GROUPS` (``"<transition>, <distance>"``); the classes whose
    occluder moved from one distance class to another are counted as staying in shadow."""
    def classes(transition: str, distance: str) -> list[str]:
        within = _GROUP_DISTANCES[distance]
        if transition == "new shadow":
            return [f"capture lit, new {d}" for d in within]
        if transition == "shadow leaves":
            return [f"capture {d}, new lit" for d in within]
        if transition == "stays lit":
            return ["capture lit, new lit"]
        return [f"capture {a}, new {b}" for a in within for b in within]  # stays shadow, at any two distances

    return {scene: {tag: {f"{t}, {d}": float(sum(split[name]["excess"] or 0.0 for name in classes(t, d)))
                          for t, d in OCCLUDER_DISTANCE_GROUPS}
                    for tag, split in tags.items()}
            for scene, tags in study.items()}


def receivers_scene(folder: Path) -> dict:
    """Whether any caster can bring row (d) near row (c) from the proxy's receiver points.

    Row (d)'s shadow rays start at the proxy's point of every pixel (:attr:`Relighter.receivers`);
    row (c)'s at the exact mesh's. Here the occluder is made perfect, the exact mesh itself, and
    the rays still start at the proxy's receivers (offset ``RelightConfig.ray_offset`` toward the
    sun, the proxy's smoothed normals for the attached shadow, blurred as row (d)), on the
    ground-truth layers with ``dropped="none"`` as row (c):

    * ``exact_at_proxy``: every hit of the exact mesh shades;
    * ``exact_at_proxy_far``: hits nearer than ``AUTO_COMPLETION_DISTANCE`` (0.6 m) are ignored
      (the rule row (d)'s proxy completion uses: a receiver on a noisy proxy lies centimetres in
      front of or behind the true surface, which then shades it);
    * ``exact_at_proxy_far_and_caster``: that, or row (d)'s visibility where it is darker (our
      caster supplies the near shadows), relit with row (d)'s relighter;
    * ``gt_caster_exact_receivers``: row (d) with every receiver point on the exact mesh instead
      (:func:`_exact_receivers`; the caster is built from and shot from them, the proxy still
      gives its distances, the completion and the normals).

    Note that the ``exact_at_proxy*`` rows test a ray's *first* hit: a receiver a few centimetres
    inside the true surface first hits that surface from behind, so ``_far`` also loses every
    farther occluder of that ray; ``gt_caster_exact_receivers`` is the direct measure of what the
    receivers cost our caster.

    """
    scene, tags, sky_mask = _relit_scene(folder, "--receivers")
    stems = scene.stems
    inputs = {v.stem: v.image for v in scene.views}
    tracer = Tracer(scene.proxy)
    truth = ground_truth_decomposition(folder, views=list(stems))
    config = relight_config()
    ours = Relighter(truth, scene, config=config, tracer=tracer)
    plain = Relighter(truth, scene, config=dataclasses.replace(config, dropped="none"), tracer=tracer)
    mesh = MeshShadow(folder, scene)
    with _exact_receivers(scene, mesh):
        oracle = _exact_receivers_built(Relighter(truth, scene, config=config, tracer=tracer), mesh)
    every_pixel = dataclasses.replace(config, ray_stride=1)
    # The exact mesh as the proxy completion of an empty caster: the relighter's own rays, offset,
    # attached-shadow test, near-hit rule (``min_distance``) and blur, from the proxy's receivers.
    nothing = ShadowCaster(Caster(np.zeros((0, 3)), np.zeros((0, 3), np.int32), np.zeros(0, np.int64),
                                  None, None, 0, 0, 0, 0))

    def exact_from_proxy(sun: np.ndarray, min_distance: float) -> dict:
        return {s: nothing.sun_visibility(plain.receivers[s], plain.normals[s], sun, proxy_tracer=mesh.tracer,
                                          min_distance=min_distance, config=every_pixel) for s in stems}

    out = {}
    for tag, (direction, images, _) in tags.items():
        sun = np.asarray(direction, dtype=np.float64)
        everything = exact_from_proxy(sun, 0.0)
        far = exact_from_proxy(sun, AUTO_COMPLETION_DISTANCE)
        caster = ours.visibility_at(sun)
        rows = {"input": inputs,
                "gt_mesh": mesh.render(plain, sun, config),
                "gt_caster": ours.render(sun, visibility=caster),
                "gt_caster_exact_receivers": oracle.render(sun),
                "exact_at_proxy": plain.render(sun, visibility=everything),
                "exact_at_proxy_far": plain.render(sun, visibility=far),
                "exact_at_proxy_far_and_caster": ours.render(
                    sun, visibility={s: np.minimum(far[s], caster[s]) for s in stems})}
        out[tag] = {name: mean_psnr(rows[name], images, sky_mask)["mean"] for name in RECEIVER_ROWS}
        print(f"{folder.name} {tag}: " + " ".join(f"{k} {v:.2f}" for k, v in out[tag].items()), flush=True)
    return out


#: The proxies of ``--proxy-loss`` (:func:`proxy_loss_scene`), from the scene's own to the exact mesh.
PROXY_VARIANTS = ("loss 0.9", "loss 0.0", "fused exact depth", "exact seen by 2+", "exact seen by 1+", "exact",
                  "stereo", "stereo, no colour test")


def mesh_subset(proxy, keep: np.ndarray):
    """The triangles ``keep`` ((T,) bool) of a mesh proxy, its unused vertices dropped and the rest reindexed."""
    from mvintrinsic.scene import Proxy

    triangles = proxy.triangles[keep]
    used = np.unique(triangles)
    index = np.full(len(proxy.vertices), -1, dtype=np.int64)
    index[used] = np.arange(len(used))
    return Proxy(vertices=proxy.vertices[used], normals=proxy.normals[used], triangles=index[triangles])


def _seen_part(proxy, views, min_views: int):
    """The triangles of a mesh proxy that the centre rays of ``min_views`` or more views hit first."""
    tracer = Tracer(proxy)
    count = np.zeros(len(proxy.triangles), dtype=np.int64)
    for view in views:
        hits = tracer.intersect(view.camera.center, view.camera.pixel_rays())
        count[np.unique(hits.triangle[hits.hit])] += 1
    return mesh_subset(proxy, count >= min_views)


def proxy_variant(folder: Path, scene, name: str):
    """One proxy of :data:`PROXY_VARIANTS` for the scene rendered in ``folder``.

    * ``loss L``: the scene's MVS-like proxy simulated again
      (:func:`mvintrinsic.synth.proxy.simulate_mvs_proxy`, the scene's own ``ProxyConfig`` and
      seed from ``gt/scene_info.json``) with its foliage and thin-structure losses
      (``foliage_loss``, ``thin_loss``) set to ``L``, everything else unchanged; the scene's own
      ``proxy.ply`` where ``L`` is its own;
    * ``fused exact depth``: the same simulation without any degradation (no depth noise, holes,
      losses, grazing-angle or edge erosion): what the TSDF fusion itself (4 cm voxels, two
      views per voxel) keeps of the exact depth maps;
    * ``exact``: the exact mesh (``proxy_clean.ply`` subdivided as the Step-1 benchmarks do,
      ``bench_step1_accuracy.clean_proxy``); ``exact seen by K+``: its triangles that the pixel-centre rays of
      at least ``K`` views hit first (what the photographs show, at the precision of the mesh);
    * ``stereo``: the scene's own proxy completed by PatchMatch stereo from the photographs
      (:func:`mvintrinsic.stereo.complete_proxy`, its defaults): no ground truth involved;
      ``stereo, no colour test``: the same with ``StereoConfig(colour_tolerance=None)`` (the
      default before the colour test; ``benchmarks/results/relight_stereo.json``'s ``stereo``).
    """
    from bench_step1_accuracy import clean_proxy

    from mvintrinsic.synth.proxy import ProxyConfig, simulate_mvs_proxy

    if name.startswith("stereo"):  # from the photographs alone
        from mvintrinsic.stereo import StereoConfig, complete_proxy

        config = StereoConfig(colour_tolerance=None) if name == "stereo, no colour test" else StereoConfig()
        return complete_proxy(scene, config=config, progress=print)[0]
    settings = json.loads((folder / "gt" / "scene_info.json").read_text())["config"]
    own = ProxyConfig(**settings["proxy"])
    if name.startswith("exact"):
        exact = clean_proxy(folder, scene)
        return exact if name == "exact" else _seen_part(exact, scene.views, int(name.split()[-1].rstrip("+")))
    if name.startswith("loss "):
        loss = float(name.split()[1])
        if loss == own.foliage_loss == own.thin_loss:
            return scene.proxy  # the scene's own proxy.ply
        changes = {"foliage_loss": loss, "thin_loss": loss}
    elif name == "fused exact depth":
        changes = {"depth_noise": 0.0, "hole_rate": 0.0, "foliage_loss": 0.0, "thin_loss": 0.0,
                   "grazing_angle_deg": 90.0, "edge_erosion": 0}
    else:
        raise ValueError(f"unknown proxy variant {name!r}; choose from {PROXY_VARIANTS}")
    mesh = read_proxy(folder / "gt" / "mesh.ply")
    labels = np.load(folder / "gt" / "mesh_faces.npz")["label"]
    return simulate_mvs_proxy(mesh.vertices, mesh.triangles, labels, [v.camera for v in scene.views],
                              config=dataclasses.replace(own, **changes), rng=settings["seed"])


#: The proxies on which ``--proxy-loss`` also runs the full pipeline (row (e)): the scene's own and the exact mesh.
PIPELINE_VARIANTS = ("loss 0.9", "exact", "stereo", "stereo, no colour test")


def proxy_loss_scene(folder: Path, *, variants: Sequence[str] = PROXY_VARIANTS,
                     pipeline: Sequence[str] = PIPELINE_VARIANTS) -> dict:
    """Rows (a), (c), (d) and (e) on better proxies than the scene's: what the caster needs of the proxy.

    For every proxy of ``variants`` (:func:`proxy_variant`): (c) ``gt_mesh`` (the exact mesh's
    shadow; the proxy only gives the normals of the cosine, as in row (d)), (d) ``gt_caster``
    (the relighter's defaults) and, for the proxies named in ``pipeline``, (e) the full pipeline
    decomposed on that proxy (for ``stereo`` also ``pipeline_own_layers``: the layers decomposed on the
    scene's own proxy, relit with the completed one); and the share of the true foliage and thin surface seen in the photos that the proxy
    retains within 10 cm (:func:`mvintrinsic.synth.proxy.label_retention`).
    """
    from mvintrinsic.synth.proxy import label_retention

    scene, tags, sky_mask = _relit_scene(folder, "--proxy-loss")
    stems = scene.stems
    inputs = {v.stem: v.image for v in scene.views}
    exact = read_proxy(folder / "gt" / "mesh.ply")
    labels = np.load(folder / "gt" / "mesh_faces.npz")["label"]
    truth = ground_truth_decomposition(folder, views=list(stems))
    mesh = MeshShadow(folder, scene)
    config = relight_config()
    out = {}
    own_result = None  # the decomposition on the scene's own proxy, for the "stereo" variant's relight-only row
    for name in variants:
        proxy = proxy_variant(folder, scene, name)
        moved = dataclasses.replace(scene, proxy=proxy)
        tracer = Tracer(proxy)
        retained = label_retention(proxy, exact.vertices, exact.triangles, labels, [v.camera for v in scene.views])
        entry = {"triangles": int(len(proxy.triangles)) if proxy.triangles is not None else None,
                 "retention": {k: (float(retained[k]) if np.isfinite(retained[k]) else None)
                               for k in ("foliage", "thin")}, "psnr": {}}
        plain = Relighter(truth, moved, config=dataclasses.replace(config, dropped="none"), tracer=tracer)
        ours = Relighter(truth, moved, config=config, tracer=tracer)
        pipeline_relighter = None
        if name in pipeline:
            start = time.perf_counter()
            result = decompose(moved, tracer=tracer, config=pipeline_config())
            entry["decompose_seconds"] = time.perf_counter() - start
            pipeline_relighter = Relighter(result, moved, config=config, tracer=tracer)
            if proxy is scene.proxy:
                own_result = result
        own_layers_relighter = None
        if name.startswith("stereo"):  # the layers decomposed on the scene's own proxy, relit with the completed one
            if own_result is None:
                own_result = decompose(scene, config=pipeline_config())
            own_layers_relighter = Relighter(own_result, moved, config=config, tracer=tracer)
        for tag, (direction, images, _) in tags.items():
            sun = np.asarray(direction, dtype=np.float64)
            rows = {"input": inputs,
                    "gt_mesh": mesh.render(plain, sun, config),
                    "gt_caster": ours.render(sun)}
            if pipeline_relighter is not None:
                rows["pipeline"] = pipeline_relighter.render(sun)
            if own_layers_relighter is not None:
                rows["pipeline_own_layers"] = own_layers_relighter.render(sun)
            entry["psnr"][tag] = {row: mean_psnr(image, images, sky_mask)["mean"] for row, image in rows.items()}
            print(f"{folder.name} {name} {tag}: " + " ".join(f"{k} {v:.2f}" for k, v in entry["psnr"][tag].items()),
                  flush=True)
        out[name] = entry
    return out


def proxy_loss_summary(study: dict) -> dict:
    """Per proxy: mean over the scenes at +-15 degrees of (c) - (d) and (e) - (a), and the worst scene's (c) - (d)."""
    out = {}
    for name in PROXY_VARIANTS:
        gaps, gains = [], []
        for scene in study.values():
            if name not in scene:
                continue
            for tag in ("az+15", "az-15"):
                rows = scene[name]["psnr"].get(tag)
                if rows is None:
                    continue
                gaps.append(rows["gt_mesh"] - rows["gt_caster"])
                if "pipeline" in rows:
                    gains.append(rows["pipeline"] - rows["input"])
        if gaps:
            out[name] = {"mean_c_minus_d_at_15_deg": float(np.mean(gaps)), "max_c_minus_d_at_15_deg": float(max(gaps)),
                         "mean_e_minus_a_at_15_deg": float(np.mean(gains)) if gains else None}
    return out


def bounds_summary(bounds: dict, rows: tuple[str, ...] = BOUND_ROWS) -> dict:
    """Mean gain over row (a) at +-15 degrees of azimuth, and the scene-suns each row beats (a) on."""
    gains = {row: [] for row in rows[1:]}
    above = {row: 0 for row in rows[1:]}
    count = 0
    for tags in bounds.values():
        for tag, rows in tags.items():
            count += 1
            for row in gains:
                above[row] += rows[row] > rows["input"]
                if tag in ("az+15", "az-15"):
                    gains[row].append(rows[row] - rows["input"])
    return {"mean_gain_over_input_at_15_deg": {row: float(np.mean(g)) if g else None for row, g in gains.items()},
            "scene_suns_above_input": {row: f"{n}/{count}" for row, n in above.items()}}


def save_figure(panels: dict, path: Path) -> None:
    """Per scene and relit sun of :data:`FIGURE_TAGS`: input, ours (full pipeline), path-traced truth (view 0)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [(name, tag, p["input"], t) for name, p in panels.items() for tag, t in p["tags"].items()
            if tag in FIGURE_TAGS or not any(k in FIGURE_TAGS for k in p["tags"])]
    fig, axes = plt.subplots(len(rows), 3, figsize=(9, 2.3 * len(rows)), squeeze=False)
    for row, (name, tag, image, t) in zip(axes, rows, strict=True):
        scale = max(float(np.percentile(np.nan_to_num(t["truth"]), 99)), 1e-6)
        for ax, (title, data) in zip(row, (("input", image), (f"ours ({tag})", t["ours"]),
                                           (f"path-traced ({tag})", t["truth"])), strict=True):
            ax.imshow(np.clip(np.nan_to_num(data) / scale, 0, 1) ** (1 / 2.2), interpolation="nearest")
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_title(f"{name}: {title}" if title == "input" else title, fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    # JPEG (by the suffix) keeps a figure of many photographs small enough to commit.
    options = {"pil_kwargs": {"quality": 85}} if path.suffix.lower() in (".jpg", ".jpeg") else {}
    fig.savefig(path, dpi=90, **options)
    plt.close(fig)


def save_occluder_distance_figure(summary: dict, path: Path) -> None:
    """Stacked bars of :func:`occluder_distance_summary`: per scene and relit tag, the share of row (d)'s excess
    squared error in each group of :data:`OCCLUDER_DISTANCE_GROUPS` (negative shares below the axis)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    bars = [(f"{scene} {tag}", shares) for scene, tags in summary.items() for tag, shares in tags.items()]
    groups = [f"{t}, {d}" for t, d in OCCLUDER_DISTANCE_GROUPS]
    colours = plt.get_cmap("tab10").colors
    fig, ax = plt.subplots(figsize=(max(6.0, 0.45 * len(bars) + 2.5), 4.2))
    up, down = np.zeros(len(bars)), np.zeros(len(bars))
    for index, group in enumerate(groups):
        share = np.array([100.0 * b[group] for _, b in bars])
        base = np.where(share >= 0, up, down)
        ax.bar(np.arange(len(bars)), share, bottom=base, color=colours[index % len(colours)], label=group)
        up += np.maximum(share, 0.0)
        down += np.minimum(share, 0.0)
    ax.axhline(0.0, color="black", linewidth=0.6)
    ax.set_xticks(np.arange(len(bars)), [name for name, _ in bars], rotation=70, fontsize=7)
    ax.set_ylabel("share of row (d)'s excess squared error (%)")
    ax.set_title("Where row (d) loses to row (c), by the exact occluder's distance", fontsize=9)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)


#: ``--timed-occluders``: the ``RelightConfig.lost_occluders`` of the timed relighter.
TIMED_OCCLUDERS = {"none": None, "occupancy": OccupancyConfig(), "default": RelightConfig().lost_occluders}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--smoke", action="store_true", help="the embedded demo only (the default)")
    parser.add_argument("--data", type=Path, default=ROOT / "data", help="folder of the rendered scenes")
    parser.add_argument("--scene", action="append", default=None, help="score DATA/NAME (repeatable)")
    parser.add_argument("--timing", action="store_true",
                        help="only time the relighter on the ground-truth layers (scenes without relit renders)")
    parser.add_argument("--size", type=_parse_size, default=None,
                        help="with --timing: resample the views and layers to WxH first")
    parser.add_argument("--stride", action="store_true",
                        help="only compare RelightConfig.ray_stride 2 and 3 with 1 on the ground-truth layers")
    parser.add_argument("--softness", action="store_true",
                        help="only compare ways of softening the new shadow on the ground-truth layers")
    parser.add_argument("--bounds", action="store_true",
                        help="only the layers (true and pipeline) relit with ideal shadows: exact, true, best")
    parser.add_argument("--receivers", action="store_true",
                        help="only the exact mesh as the occluder, shot from the proxy's receivers (ground-truth layers)")
    parser.add_argument("--proxy-loss", action="store_true",
                        help="only rows (c), (d), (e) on proxies simulated with less foliage and thin-structure loss")
    parser.add_argument("--error-split", action="store_true",
                        help="only where row (d)'s squared error is beyond row (c)'s, by true and relit shadow state")
    parser.add_argument("--occluder-distance", action="store_true",
                        help="only where row (d)'s squared error is beyond row (c)'s, by the exact mesh's occluder "
                             "distance along the capture and the new sun")
    parser.add_argument("--lost-occluders", action="store_true",
                        help="only rows (a), (c)-(e) with and without RelightConfig.lost_occluders (lost_occluders_scene)")
    parser.add_argument("--sun-radiance", action="store_true",
                        help="only row (e) with the pipeline's L_sun replaced by the truth, its level or its colour")
    parser.add_argument("--true-labels", action="store_true",
                        help="only row (e) with Steps 3-4 fed the true shadow labels, three relighters (true_labels_scene)")
    parser.add_argument("--agreement", action="store_true",
                        help="only what the cross-view agreement measures, and where rows (d) and (e) lose it")
    parser.add_argument("--sky-pixels", action="store_true",
                        help="only compare RelightConfig.sky_pixels' modes on the sky pixels (sky_pixels_scene)")
    parser.add_argument("--timed-occluders", choices=TIMED_OCCLUDERS, default=None,
                        help="with --timing: RelightConfig.lost_occluders of the timed relighter: none (the paper; "
                             "default), occupancy (OccupancyConfig(), as --lost-occluders) or default (the relighter's "
                             "default, OccupancyConfig(silhouette=1))")
    parser.add_argument("--proxy-variant", action="append", default=None, choices=PROXY_VARIANTS,
                        help="with --proxy-loss: only this proxy (repeatable); default all")
    parser.add_argument("--update", action="store_true",
                        help="with --proxy-loss: merge into the report at --out instead of replacing it")
    parser.add_argument("--relight-config", default=None, metavar="JSON",
                        help='overrides of every RelightConfig the benchmark builds, e.g. \'{"support_radius": 10}\'')
    parser.add_argument("--decompose-config", default=None, metavar="JSON",
                        help='a partial Config for every decomposition the benchmark makes, e.g. \'{"step1": {"planes": null}}\'')
    parser.add_argument("--no-caster-study", action="store_true", help="main run: skip the caster study")
    parser.add_argument("--out", type=Path, default=None, help="JSON report")
    parser.add_argument("--figure", type=Path, default=None,
                        help="PNG or JPEG (by suffix): input, ours, truth per relit sun; with --occluder-distance, "
                             "stacked bars of its split")
    args = parser.parse_args(argv)
    require_matplotlib(parser, args, "figure")
    CONFIG_OVERRIDES.clear()
    CONFIG_OVERRIDES.update(_parse_overrides(args.relight_config))
    DECOMPOSE_OVERRIDES.clear()
    DECOMPOSE_OVERRIDES.update(_parse_decompose_overrides(args.decompose_config))
    SKIP_CASTER_STUDY[0] = args.no_caster_study
    chosen = scene_folders(args)
    report = {"benchmark": "relight", "version": mvintrinsic.__version__, "cores": os.cpu_count(),
              "python": platform.python_version(), "config": dataclasses.asdict(relight_config()),
              "decompose_config": DECOMPOSE_OVERRIDES,
              "psnr": f"linear RGB, non-sky pixels, both clipped to [0, truth's {CLIP_PERCENTILE}th percentile], "
                      "data range = that percentile", "scenes": {}}
    # The studies (one per flag): a scene folder -> its JSON entry, written under the report key.
    # --timing: the relighter without lost_occluders (relight_timing_resampled.json), with OccupancyConfig()
    # (--lost-occluders or --timed-occluders occupancy: relight_timing_lost_occluders.json), or the default relighter
    # (--timed-occluders default, silhouette 1: relight_timing_default.json).
    timed = relight_config(lost_occluders=TIMED_OCCLUDERS[args.timed_occluders or
                                                          ("occupancy" if args.lost_occluders else "none")])
    studies = (("timing", "timing", functools.partial(time_scene, size=args.size, config=timed)), ("stride", "ray_stride", stride_scene),
               ("softness", "softness", softness_scene), ("bounds", "bounds", bounds_scene),
               ("receivers", "receivers", receivers_scene), ("proxy_loss", "proxy_loss", proxy_loss_scene),
               ("error_split", "error_split", error_split_scene),
               ("occluder_distance", "occluder_distance", occluder_distance_scene),
               ("sky_pixels", "sky_pixels", sky_pixels_scene),
               ("lost_occluders", "lost_occluders", lost_occluders_scene), ("sun_radiance", "sun_radiance", sun_radiance_scene),
               ("true_labels", "true_labels", true_labels_scene), ("agreement", "agreement_study", agreement_scene))
    if args.proxy_variant:
        studies = tuple((f, k, functools.partial(proxy_loss_scene, variants=tuple(args.proxy_variant)))
                        if f == "proxy_loss" else (f, k, st) for f, k, st in studies)
    for flag, key, study in studies:
        if getattr(args, flag):
            if key == "timing":
                report["timed_config"] = dataclasses.asdict(timed)
            report[key] = {name: study(folder) for name, folder in chosen.items()}
            if key == "proxy_loss":
                if args.update and args.out and args.out.is_file():
                    merged = json.loads(args.out.read_text())[key]
                    for name, variants in report[key].items():
                        merged.setdefault(name, {}).update(variants)
                    report[key] = merged
                report["proxy_loss_summary"] = proxy_loss_summary(report[key])
            if key == "bounds":
                report["bounds_summary"] = bounds_summary(report["bounds"])
            if key == "receivers":
                report["receivers_summary"] = bounds_summary(report["receivers"], RECEIVER_ROWS)
            if key == "lost_occluders":
                report["lost_occluders_summary"] = lost_occluders_summary(report[key])
            if key == "sun_radiance":
                report["sun_radiance_summary"] = sun_radiance_summary(report[key])
            if key == "true_labels":
                report["true_labels_summary"] = true_labels_summary(report[key])
            if key == "agreement_study":
                report["agreement_summary"] = agreement_summary(report[key])
            if key == "occluder_distance":
                report["occluder_distance_summary"] = occluder_distance_summary(report[key])
                if args.figure:
                    save_occluder_distance_figure(report["occluder_distance_summary"], args.figure)
            if args.out:
                write_json(args.out, report)
            return 0
    panels = {}
    for name, folder in chosen.items():
        report["scenes"][name], panels[name] = run_scene(folder)
    if args.out:
        write_json(args.out, report)
    if args.figure:
        save_figure(panels, args.figure)
    return 0


if __name__ == "__main__":
    sys.exit(main())
