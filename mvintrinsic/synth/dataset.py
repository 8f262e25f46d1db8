"""Write a complete synthetic scene folder with ground truth (``docs/formats.md``).

:func:`synthesize` builds a recipe, places cameras along its path, renders every view with
Mitsuba (:mod:`mvintrinsic.synth.render`), simulates an imperfect multi-view-stereo proxy
(:mod:`mvintrinsic.synth.proxy`) and writes:

* ``images/<stem>.exr`` (linear, half float), ``sparse/`` (COLMAP text), ``scene.json``,
  ``proxy.ply`` (MVS-like) and ``proxy_clean.ply`` (the exact geometry);
* ``gt/reflectance`` (albedo AOV), ``gt/shading`` (image / reflectance), ``gt/sun_shading``
  (direct-sun render / reflectance), ``gt/env_shading`` (shading - sun_shading),
  ``gt/sun_visibility`` and ``gt/sky_mask`` (pixel-centre rays against the exact mesh),
  ``gt/lighting.json`` (``sun_radiance`` from a white plate facing the sun), ``gt/mesh.ply`` and
  ``gt/mesh_faces.npz`` (per-face label and material), ``gt/relit/<tag>/`` (same cameras, moved
  sun), ``gt/scene_info.json`` (recipe, seed, sun angles, markers, proxy quality, timings).

Shading is undefined where the albedo is 0 (sky) and unreliable at silhouette pixels that mix
surfaces, or a surface and the sky (the albedo AOV and the radiance are averaged differently).
"""

from __future__ import annotations

import math
import re
import shutil
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from ..camera import Camera
from ..io import write_colmap_text, write_image, write_json, write_proxy
from ..raytrace import Tracer, sun_visibility
from .proxy import ProxyConfig, distance_to_mesh, foliage_retention, label_retention, simulate_mvs_proxy
from .recipes import RECIPES, build_scene
from .render import MitsubaScene, RenderConfig, sun_radiance, sun_vector
from .types import LABELS, SynthScene, ViewPath

__all__ = ["SynthConfig", "cameras_along_path", "gt_layers", "parse_relit_tag", "synthesize"]

#: Default relit tags: sun azimuth +-15 and +-30 degrees, elevation +10 degrees (the suns
#: ``benchmarks/bench_relight.py`` scores relighting at).
DEFAULT_RELIT = ("az+15", "az-15", "az+30", "az-30", "el+10")
#: Offset along the normal of shadow-ray origins, metres.
SHADOW_RAY_OFFSET = 1e-3
_TAG = re.compile(r"^(az|el)([+-]\d+(?:\.\d+)?)$")


@dataclass(frozen=True)
class SynthConfig:
    """What :func:`synthesize` renders.

    Parameters
    ----------
    n_views : int
        Number of views along the recipe's path.
    width, height : int
        Image size, pixels.
    hfov_deg : float
        Horizontal field of view, degrees.
    spacing : float
        Distance between consecutive camera centres, metres (wide baseline, about 1 m).
    sun_azimuth_deg, sun_elevation_deg : float, optional
        Sun position (azimuth counter-clockwise from +X, elevation above the horizon). ``None``
        draws them from the seed: elevation uniform in [30, 55] degrees, azimuth 20-50 degrees to
        either side of the direction from the scene toward the cameras. This oblique front light
        lights the facades facing the cameras and throws the shadows of the tree, the pole and the
        statue sideways onto them, in view (a sun straight behind the cameras hides each shadow
        behind its caster; a side or back light leaves the facades in attached shadow).
    relit : tuple of str
        Tags of the relit renders, e.g. ``("az+15", "el+10")``.
    gloss : bool
        Mild glossiness on a few materials (stress tests).
    occluders : bool
        False renders the recipe without its occluders: ground and plain box buildings only, so
        that a sun in front of the facades casts no shadow in view (the no-cast-shadow scene of
        ``docs/stability.md``; :func:`~mvintrinsic.synth.recipes.build_scene`).
    seed : int
        Seed of the recipe, the sun draw, the sampler and the proxy simulation.
    render : RenderConfig
        Samples, path depth, sky turbidity, sun on/off (overcast).
    proxy : ProxyConfig
        Degradations of the simulated MVS proxy.
    """

    n_views: int = 8
    width: int = 320
    height: int = 240
    hfov_deg: float = 60.0
    spacing: float = 1.0
    sun_azimuth_deg: float | None = None
    sun_elevation_deg: float | None = None
    relit: tuple[str, ...] = DEFAULT_RELIT
    gloss: bool = False
    occluders: bool = True
    seed: int = 0
    render: RenderConfig = field(default_factory=RenderConfig)
    proxy: ProxyConfig = field(default_factory=ProxyConfig)

    def __post_init__(self) -> None:
        for name in ("n_views", "width", "height"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"{name} must be a positive integer, got {value!r}")
        if not 1.0 < self.hfov_deg < 170.0:
            raise ValueError(f"hfov_deg must be in (1, 170) degrees, got {self.hfov_deg!r}")
        if not self.spacing > 0:
            raise ValueError(f"spacing must be positive, got {self.spacing!r}")
        if self.sun_elevation_deg is not None and not 0 < self.sun_elevation_deg < 90:
            raise ValueError(f"sun_elevation_deg must be in (0, 90), got {self.sun_elevation_deg!r}")
        for tag in self.relit:
            parse_relit_tag(tag)


def parse_relit_tag(tag: str) -> tuple[str, float]:
    """``"az+15"`` -> ``("az", 15.0)``; raises ValueError naming the tag when malformed."""
    match = _TAG.match(tag)
    if match is None:
        raise ValueError(f"relit tag {tag!r} must look like 'az+15', 'az-30' or 'el+10'")
    return match.group(1), float(match.group(2))


def _sun_angles(scene: SynthScene, config: SynthConfig) -> tuple[float, float]:
    rng = np.random.default_rng([config.seed, 7])
    toward_cameras = scene.path.center - scene.path.target
    facing = math.degrees(math.atan2(toward_cameras[1], toward_cameras[0]))
    offset = rng.uniform(20.0, 50.0) * rng.choice([-1.0, 1.0])
    azimuth = config.sun_azimuth_deg if config.sun_azimuth_deg is not None else facing + offset
    elevation = config.sun_elevation_deg if config.sun_elevation_deg is not None else rng.uniform(30.0, 55.0)
    return (azimuth + 180.0) % 360.0 - 180.0, elevation


def cameras_along_path(path: ViewPath, *, n_views: int, width: int, height: int, hfov_deg: float = 60.0,
                       spacing: float = 1.0) -> list[Camera]:
    """Pinhole cameras spaced ``spacing`` metres apart along the path, all looking at its target.

    Returns
    -------
    list of Camera
        PINHOLE, square pixels, principal point at the image centre; COLMAP pose convention.
    """
    focal = width / (2.0 * math.tan(math.radians(hfov_deg) / 2.0))
    offsets = (np.arange(n_views) - (n_views - 1) / 2.0) * spacing
    cameras = []
    for offset in offsets:
        center = path.center + offset * path.direction
        forward = path.target - center
        forward = forward / np.linalg.norm(forward)
        right = np.cross(forward, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        down = np.cross(forward, right)
        rotation = np.stack([right, down, forward])
        cameras.append(Camera("PINHOLE", width, height, [focal, focal, width / 2.0, height / 2.0],
                              rotation, -rotation @ center))
    return cameras


def gt_layers(image: np.ndarray, albedo: np.ndarray, sun_direct: np.ndarray) -> dict[str, np.ndarray]:
    """Shading layers from the renders: ``shading = image / albedo``, ``sun_shading =
    sun_direct / albedo``, ``env_shading = shading - sun_shading``; 0 where the albedo is 0."""
    ok = albedo > 1e-6
    safe = np.where(ok, albedo, 1.0)
    shading = np.where(ok, image / safe, 0.0).astype(np.float32)
    sun_shading = np.where(ok, sun_direct / safe, 0.0).astype(np.float32)
    return {"shading": shading, "sun_shading": sun_shading, "env_shading": shading - sun_shading}


def _visibility_and_sky(tracer: Tracer, camera: Camera, sun: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-centre rays: sky where they miss; lit where the hit faces the sun unoccluded."""
    hits = tracer.intersect(camera.center, camera.pixel_rays())
    lit = np.zeros(len(hits.hit), dtype=bool)
    idx = np.flatnonzero(hits.hit)
    lit[idx] = sun_visibility(hits.points[idx], hits.normals[idx], sun, tracer, ray_offset=SHADOW_RAY_OFFSET) > 0
    return lit.reshape(camera.shape), ~hits.hit.reshape(camera.shape)


def _png(mask: np.ndarray) -> np.ndarray:
    return np.where(mask, 255, 0).astype(np.uint8)


def _prepare(out: Path, overwrite: bool) -> None:
    if out.exists() and any(out.iterdir()):
        if not overwrite:
            raise FileExistsError(f"{out}: not empty; pass overwrite=True (--overwrite) to replace it")
        shutil.rmtree(out)
    out.mkdir(parents=True, exist_ok=True)


def synthesize(recipe: str, out: str | Path, *, config: SynthConfig | None = None, overwrite: bool = False,
               progress: bool = True, workdir: str | Path | None = None) -> dict:
    """Render a synthetic scene folder with ground truth.

    Parameters
    ----------
    recipe : str
        One of :data:`mvintrinsic.synth.recipes.RECIPES`.
    out : path-like
        Output scene folder; must be absent or empty unless ``overwrite``.
    config : SynthConfig, optional
        Views, size, samples, sun, relit tags, proxy degradations, seed.
    overwrite : bool, optional
        Replace a non-empty ``out``.
    progress : bool, optional
        Progress bar over renders with seconds per render.
    workdir : path-like, optional
        Where the Mitsuba PLY files go (default: ``out/.render-cache``, removed at the end).

    Returns
    -------
    dict
        The content of ``gt/scene_info.json`` (sun, timings, proxy quality, ...).
    """
    from tqdm.auto import tqdm

    config = config or SynthConfig()
    if recipe not in RECIPES:
        raise ValueError(f"recipe must be one of {sorted(RECIPES)}, got {recipe!r}")
    out = Path(out)
    _prepare(out, overwrite)
    started = time.perf_counter()
    scene = build_scene(recipe, seed=config.seed, gloss=config.gloss, occluders=config.occluders)
    cameras = cameras_along_path(scene.path, n_views=config.n_views, width=config.width, height=config.height,
                                 hfov_deg=config.hfov_deg, spacing=config.spacing)
    azimuth, elevation = _sun_angles(scene, config)
    sun = sun_vector(azimuth, elevation)
    names = {f"view_{i:03d}.exr": cam for i, cam in enumerate(cameras)}
    stems = [n[:-4] for n in names]

    vertices, triangles, labels, materials = scene.merged()
    exact = scene.exact_proxy()
    tracer = Tracer(exact)
    render_dir = Path(workdir) if workdir is not None else out / ".render-cache"
    mitsuba = MitsubaScene(scene, render_dir)
    timings: dict[str, list[float]] = {"image": [], "sun_direct": [], "relit": []}
    relit = [(tag, *parse_relit_tag(tag)) for tag in config.relit]
    n_renders = len(cameras) * (2 + len(relit)) if config.render.sun else len(cameras) * (1 + len(relit))
    bar = tqdm(total=n_renders, desc=f"render {recipe}", unit="render", disable=not progress)
    try:
        for (name, camera), stem in zip(names.items(), stems, strict=True):
            renders = mitsuba.render(camera, sun, config.render)
            for key, seconds in renders.seconds.items():
                timings[key].append(seconds)
                bar.update(1)
            bar.set_postfix_str(f"{renders.seconds['image']:.1f} s/image")
            layers = gt_layers(renders.image, renders.albedo, renders.sun_direct)
            lit, sky = _visibility_and_sky(tracer, camera, sun)
            write_image(out / "images" / name, renders.image, dtype="half")
            write_image(out / "gt" / "reflectance" / f"{stem}.exr", renders.albedo, dtype="half")
            for layer, values in layers.items():
                write_image(out / "gt" / layer / f"{stem}.exr", values, dtype="half")
            write_image(out / "gt" / "sun_visibility" / f"{stem}.png", _png(lit & ~sky), dtype="uint8")
            write_image(out / "gt" / "sky_mask" / f"{stem}.png", _png(sky), dtype="uint8")
            for tag, what, delta in relit:
                moved = sun_vector(azimuth + delta, elevation) if what == "az" else sun_vector(azimuth, elevation + delta)
                relit_render = mitsuba.render(camera, moved, config.render, with_albedo=False, with_sun_direct=False)
                timings["relit"].append(relit_render.seconds["image"])
                bar.update(1)
                folder = out / "gt" / "relit" / tag
                write_image(folder / "images" / name, relit_render.image, dtype="half")
                moved_lit, _ = _visibility_and_sky(tracer, camera, moved)
                write_image(folder / "sun_visibility" / f"{stem}.png", _png(moved_lit & ~sky), dtype="uint8")
    finally:
        bar.close()
        if workdir is None:
            shutil.rmtree(render_dir, ignore_errors=True)

    for tag, what, delta in relit:
        moved = sun_vector(azimuth + delta, elevation) if what == "az" else sun_vector(azimuth, elevation + delta)
        write_json(out / "gt" / "relit" / tag / "scene.json", {"up": [0.0, 0.0, 1.0], "sun_direction": moved.tolist()})

    start = time.perf_counter()
    proxy = simulate_mvs_proxy(vertices, triangles, labels, cameras, config=config.proxy, rng=config.seed,
                               progress=progress)
    proxy_seconds = time.perf_counter() - start
    write_proxy(out / "proxy.ply", proxy)
    write_proxy(out / "proxy_clean.ply", exact)
    write_proxy(out / "gt" / "mesh.ply", exact)
    _save_npz(out / "gt" / "mesh_faces.npz", label=labels, material=materials,
              label_names=np.array(LABELS), material_names=np.array(sorted(scene.materials)))
    write_colmap_text(out / "sparse", names)
    radiance = sun_radiance(sun, config.render)
    write_json(out / "gt" / "lighting.json", {
        "sun_radiance": radiance.tolist(),
        "sun_direction": sun.tolist(),
        "units": "shading units: radiance of a white diffuse surface facing the sun, direct sun only",
    })
    write_json(out / "scene.json", {"up": [0.0, 0.0, 1.0], "sun_direction": sun.tolist()})

    distances = distance_to_mesh(proxy.vertices, vertices, triangles)
    quality = {
        "vertices": int(len(proxy.vertices)),
        "triangles": int(len(proxy.triangles)) if proxy.is_mesh else 0,
        "within_10cm": float(np.mean(distances <= 0.10)),
        "median_distance_m": float(np.median(distances)),
        # share of the whole foliage surface with a proxy vertex within 10 cm (None: no foliage)
        "foliage_retention": _finite_or_none(foliage_retention(proxy, vertices, triangles, labels)),
        # the same per label, over the surface the cameras see (pixel samples; None: label not seen)
        "retention_seen": {k: _finite_or_none(v)
                           for k, v in label_retention(proxy, vertices, triangles, labels, cameras).items()},
        "seconds": proxy_seconds,
    }
    info = {
        "recipe": recipe,
        "seed": config.seed,
        "views": config.n_views,
        "width": config.width,
        "height": config.height,
        "hfov_deg": config.hfov_deg,
        "sun_azimuth_deg": azimuth,
        "sun_elevation_deg": elevation,
        "sun_direction": sun.tolist(),
        "up": [0.0, 0.0, 1.0],
        "azimuth_convention": "counter-clockwise from +x, Z up",
        "units": "m",
        "sky": _sky_info(config.render),
        "config": _jsonable(asdict(config)),
        "markers": {k: np.asarray(v).tolist() for k, v in scene.markers.items()},
        "proxy": quality,
        "seconds_per_render": {k: (float(np.mean(v)) if v else None) for k, v in timings.items()},
        "seconds_total": time.perf_counter() - started,
    }
    write_json(out / "gt" / "scene_info.json", info)
    return info


def _sky_info(render: RenderConfig) -> dict:
    """What lit the scene, for ``gt/scene_info.json``."""
    if render.sky == "simulated":
        from .render import SIMULATED_SKY_SCALE, SIMULATED_SKY_WIDTH

        return {"model": "simulated clear sky: Rayleigh and Mie, single and multiple scattering "
                         "(mvintrinsic.synth.atmosphere)",
                "aerosol_scale": render.aerosol_scale, "ground_albedo": render.ground_albedo,
                "exposure": SIMULATED_SKY_SCALE, "envmap_width": SIMULATED_SKY_WIDTH,
                "renderer": "mitsuba scalar_rgb envmap + directional sun", "sun": render.sun}
    return {"model": "hosek-wilkie", "turbidity": render.turbidity, "renderer": "mitsuba scalar_rgb sunsky",
            "sun": render.sun}


def _save_npz(path: Path, **arrays) -> None:
    from ..io import _atomic_write

    def write(tmp: Path) -> None:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **arrays)

    _atomic_write(path, write)


def _finite_or_none(value: float) -> float | None:
    """``float(value)``, or None for NaN (JSON holds no NaN: a scene without foliage, say)."""
    return float(value) if math.isfinite(value) else None


def _jsonable(value):
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


def with_overrides(config: SynthConfig, **changes) -> SynthConfig:
    """``dataclasses.replace`` that also accepts ``proxy_*`` / ``render_*`` keys for the nested configs."""
    proxy = {k[6:]: v for k, v in changes.items() if k.startswith("proxy_")}
    render = {k[7:]: v for k, v in changes.items() if k.startswith("render_")}
    top = {k: v for k, v in changes.items() if not k.startswith(("proxy_", "render_"))}
    return replace(config, proxy=replace(config.proxy, **proxy), render=replace(config.render, **render), **top)
