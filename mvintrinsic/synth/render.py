"""Physically based rendering of synthetic scenes with Mitsuba 3 (optional extra ``render``).

For each view this renders, like Sec. 9.3 of Duchêne et al. 2015:

* the **image** with a unidirectional path tracer under Mitsuba's ``sunsky`` emitter (Hosek-Wilkie
  sky + sun disc), together with the diffuse **albedo** AOV from the same samples (``aov``
  integrator wrapping ``path``): ``gt/reflectance``;
* the **direct sun** image (sun only, sky off, ``direct`` integrator, so penumbrae from the
  sun's disc are included): divided by the albedo it gives ``gt/sun_shading``
  ``= v_sun L_sun max(0, cos)``;
* the **sun radiance** ``L_sun`` in shading units, from a white diffuse square facing the sun lit
  by the sun alone (:func:`sun_radiance`).

``RenderConfig(sky="simulated")`` replaces the ``sunsky`` emitter by a sky that no analytic sky
model reproduces: the environment map of a numerical clear-sky simulation
(:mod:`mvintrinsic.synth.atmosphere`: Rayleigh and Mie single and multiple scattering in a
layered atmosphere) through Mitsuba's ``envmap`` emitter, and the sun as a ``directional``
emitter (a point sun: its shadows have no penumbra) of the simulation's transmitted irradiance.

Only the ``scalar_rgb`` variant is used (the ``llvm_*`` variants crash on the project's machines).
Meshes are handed to Mitsuba as PLY files: its ``aov`` integrator ran ~10x slower on meshes built
in memory. Mitsuba's ``sunsky`` is Z-up as it is; ``sun_direction`` is the world vector toward the
sun, with no ``to_world``.
"""

from __future__ import annotations

import functools
import math
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .._validation import is_real
from ..camera import Camera
from .types import SynthScene

__all__ = [
    "MitsubaScene",
    "RenderConfig",
    "Renders",
    "SKIES",
    "SIMULATED_SKY_SCALE",
    "import_mitsuba",
    "simulated_sky",
    "sky_radiance",
    "sun_radiance",
    "sun_vector",
    "write_ply_with_uvs",
]

#: Solar disc aperture (full angle, degrees) used by Mitsuba's sunsky by default.
SUN_APERTURE_DEG = 0.5358

#: The skies of :attr:`RenderConfig.sky`.
SKIES = ("hosek-wilkie", "simulated")

#: Exposure of the simulated sky (:func:`mvintrinsic.synth.atmosphere.clear_sky`'s ``scale``): its
#: physical units times this give the sun radiance of Mitsuba's ``sunsky`` for the same sun
#: (0.0082, measured at 45 degrees of elevation; the atmosphere module's docstring), so both skies
#: light a scene at about the same exposure.
SIMULATED_SKY_SCALE = 0.0082

#: Columns of the simulated sky's environment map (rows: half of it).
SIMULATED_SKY_WIDTH = 512


@functools.lru_cache(maxsize=16)
def _simulated_sky(sun_direction: tuple[float, float, float], aerosol_scale: float, ground_albedo: float):
    from .atmosphere import AtmosphereConfig, clear_sky

    config = AtmosphereConfig(aerosol_scale=aerosol_scale, ground_albedo=ground_albedo)
    return clear_sky(np.asarray(sun_direction), width=SIMULATED_SKY_WIDTH, config=config, scale=SIMULATED_SKY_SCALE)


def simulated_sky(sun_direction: Sequence[float], config: RenderConfig):
    """The :class:`~mvintrinsic.synth.atmosphere.ClearSky` a ``sky="simulated"`` render uses (cached)."""
    d = np.asarray(sun_direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    return _simulated_sky(tuple(float(v) for v in d), float(config.aerosol_scale), float(config.ground_albedo))


def sun_vector(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """Unit vector toward the sun, Z up, azimuth counter-clockwise from +X, (3,) float64.

    This is the ``sun_direction`` Mitsuba's ``sunsky`` takes as it is (no ``to_world``).
    """
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    return np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])


def import_mitsuba():
    """Import Mitsuba 3 and select the ``scalar_rgb`` variant.

    Raises
    ------
    ImportError
        With the install command when Mitsuba is absent (``pip install "mvintrinsic[render]"``).
    """
    try:
        import mitsuba as mi
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError(
            "rendering synthetic scenes needs Mitsuba 3 >= 3.7: pip install 'mvintrinsic[render]'"
        ) from exc
    if mi.variant() != "scalar_rgb":
        mi.set_variant("scalar_rgb")
    return mi


@dataclass(frozen=True)
class RenderConfig:
    """Rendering options.

    Parameters
    ----------
    spp : int
        Samples per pixel of the path-traced image (and its albedo AOV).
    max_depth : int
        Longest light path (``path`` integrator); 6 captures interreflections in a courtyard.
    sun_spp : int
        Samples per pixel of the direct-sun image (converges much faster: one light, no bounce).
    turbidity : float
        Atmospheric turbidity of the Hosek-Wilkie sky (3 = clear).
    ground_albedo : float
        Ground albedo parameter of the sky model.
    sun : bool
        Sun on; ``False`` renders an overcast-like sky-only scene (``sun_scale = 0``).
    seed : int
        Sampler seed (renders are deterministic per seed).
    sky : {"hosek-wilkie", "simulated"}
        The sky (:data:`SKIES`): Mitsuba's analytic ``sunsky`` (``turbidity``), or the numerical
        clear-sky simulation of :mod:`mvintrinsic.synth.atmosphere` (``aerosol_scale``, the
        ground albedo ``ground_albedo``), exposed by :data:`SIMULATED_SKY_SCALE`.
    aerosol_scale : float
        ``sky="simulated"``: multiplier of the atmosphere's aerosol density
        (:attr:`~mvintrinsic.synth.atmosphere.AtmosphereConfig.aerosol_scale`); > 0. 20 gives an
        aerosol optical depth of about 0.11 at 550 nm, a clear day, and a zenith-to-sun radiance
        ratio near ``sunsky``'s at turbidity 3 (0.092 against 0.108 in green, sun at 45 degrees).
    """

    spp: int = 64
    max_depth: int = 6
    sun_spp: int = 32
    turbidity: float = 3.0
    ground_albedo: float = 0.3
    sun: bool = True
    seed: int = 0
    sky: str = "hosek-wilkie"
    aerosol_scale: float = 20.0

    def __post_init__(self) -> None:
        if self.sky not in SKIES:
            raise ValueError(f"sky must be one of {', '.join(map(repr, SKIES))}, got {self.sky!r}")
        if not is_real(self.aerosol_scale) or not 0 < self.aerosol_scale < math.inf:
            raise ValueError(f"aerosol_scale must be a finite number > 0, got {self.aerosol_scale!r}")


@dataclass(frozen=True, eq=False)
class Renders:
    """The rendered layers of one view, all ``(H, W, 3)`` float32 linear RGB.

    ``image`` is the path-traced radiance, ``albedo`` the diffuse reflectance AOV and
    ``sun_direct`` the radiance due to direct sunlight alone; ``seconds`` maps each pass to its
    wall-clock time.
    """

    image: np.ndarray
    albedo: np.ndarray | None
    sun_direct: np.ndarray | None
    seconds: dict


def write_ply_with_uvs(path: Path, vertices: np.ndarray, triangles: np.ndarray, uvs: np.ndarray) -> None:
    """Binary little-endian PLY with ``x y z u v`` per vertex (Mitsuba's ``ply`` loader reads UVs).

    ``v`` is written as ``1 - v``: :class:`~mvintrinsic.synth.types.Material` textures store
    row 0 at v = 1 (as image files do) while Mitsuba's bitmap puts v = 0 at row 0.
    """
    vertices = np.ascontiguousarray(vertices, dtype=np.float32)
    uvs = np.array(uvs, dtype=np.float32)
    uvs[:, 1] = 1.0 - uvs[:, 1]
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(vertices)}\n"
        "property float x\nproperty float y\nproperty float z\nproperty float u\nproperty float v\n"
        f"element face {len(triangles)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    vertex_data = np.concatenate([vertices, uvs], axis=1).astype("<f4").tobytes()
    faces = np.empty(len(triangles), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    faces["n"] = 3
    faces["i"] = triangles
    with open(path, "wb") as fh:
        fh.write(header.encode("ascii"))
        fh.write(vertex_data)
        fh.write(faces.tobytes())


def _sensor(mi, camera: Camera, spp: int, seed: int) -> dict:
    if camera.model not in ("PINHOLE", "SIMPLE_PINHOLE"):
        raise ValueError(f"camera: synthetic views must be pinhole, got {camera.model}")
    (fx, fy), (cx, cy) = camera.focal, camera.principal_point
    if abs(fx - fy) > 1e-9 * fx:
        raise ValueError("camera: synthetic views need square pixels (fx == fy)")
    w, h = camera.width, camera.height
    center, forward, down = camera.center, camera.rotation[2], camera.rotation[1]
    transform = mi.ScalarTransform4f().look_at(
        origin=center.tolist(), target=(center + forward).tolist(), up=(-down).tolist()
    )
    return {
        "type": "perspective",
        "fov": float(np.degrees(2.0 * np.arctan(w / (2.0 * fx)))),
        "fov_axis": "x",
        # Offsets of the principal point from the film centre, in units of the film size.
        "principal_point_offset_x": float((cx - w / 2.0) / w),
        "principal_point_offset_y": float((cy - h / 2.0) / h),
        "to_world": transform,
        "film": {"type": "hdrfilm", "width": w, "height": h, "rfilter": {"type": "box"}, "pixel_format": "rgb"},
        "sampler": {"type": "independent", "sample_count": int(spp), "seed": int(seed)},
    }


def _bsdf(mi, material) -> dict:
    texture = {"type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(material.albedo, dtype=np.float32)),
               "raw": True, "filter_type": "bilinear", "wrap_mode": "repeat"}
    if material.roughness is None:
        bsdf = {"type": "diffuse", "reflectance": texture}
    else:
        bsdf = {"type": "roughplastic", "diffuse_reflectance": texture, "alpha": float(material.roughness),
                "distribution": "ggx", "int_ior": 1.5}
    return {"type": "twosided", "bsdf": bsdf} if material.two_sided else bsdf


class MitsubaScene:
    """Mitsuba representation of a :class:`SynthScene`: meshes written once as PLY files.

    Parameters
    ----------
    scene : SynthScene
    workdir : path-like
        Folder for the PLY files (kept until the object is closed).
    """

    def __init__(self, scene: SynthScene, workdir: os.PathLike | str) -> None:
        self.mi = import_mitsuba()
        self.workdir = Path(workdir)
        self.workdir.mkdir(parents=True, exist_ok=True)
        self.shapes = {}
        self._envmaps = {}  # ClearSky -> Mitsuba emitter entries (sky="simulated")
        bsdfs = {name: _bsdf(self.mi, m) for name, m in scene.materials.items()}
        for mesh in scene.meshes:
            file = self.workdir / f"{mesh.name}.ply"
            write_ply_with_uvs(file, mesh.vertices, mesh.triangles, mesh.uvs)
            self.shapes[mesh.name] = {"type": "ply", "filename": str(file), "face_normals": True,
                                      "bsdf": bsdfs[mesh.material]}

    def _emitter(self, sun_direction: np.ndarray, config: RenderConfig, *, sun: bool, sky: bool) -> dict:
        """Scene-dict entries of the emitters (``sun`` and ``sky`` switch them on)."""
        if config.sky == "simulated":
            from .atmosphere import envmap_emitter

            sky_model = simulated_sky(sun_direction, config)
            if sky_model not in self._envmaps:  # its EXR is written once, not for every pass
                self._envmaps[sky_model] = envmap_emitter(sky_model, self.workdir)
            entries = self._envmaps[sky_model]
            return {k: v for k, v in entries.items() if (k == "sun" and sun and config.sun) or (k == "sky" and sky)}
        return {"emitter": {
            "type": "sunsky",
            "sun_direction": [float(v) for v in sun_direction],
            "turbidity": float(config.turbidity),
            "albedo": float(config.ground_albedo),
            "sun_scale": 1.0 if (sun and config.sun) else 0.0,
            "sky_scale": 1.0 if sky else 0.0,
        }}

    def render(self, camera: Camera, sun_direction: np.ndarray, config: RenderConfig, *,
               with_albedo: bool = True, with_sun_direct: bool = True) -> Renders:
        """Render one view (see the module docstring for the passes)."""
        mi = self.mi
        seconds = {}
        integrator = {"type": "path", "max_depth": int(config.max_depth)}
        if with_albedo:
            integrator = {"type": "aov", "aovs": "albedo:albedo", "integrator": integrator}
        scene = mi.load_dict({"type": "scene", "integrator": integrator,
                              "sensor": _sensor(mi, camera, config.spp, config.seed),
                              **self._emitter(sun_direction, config, sun=True, sky=True), **self.shapes})
        start = time.perf_counter()
        out = np.array(mi.render(scene), dtype=np.float32)
        seconds["image"] = time.perf_counter() - start
        image, albedo = out[..., :3], (out[..., 3:6] if with_albedo else None)
        sun_direct = None
        if with_sun_direct:
            if config.sun:
                scene = mi.load_dict({"type": "scene", "integrator": {"type": "direct"},
                                      "sensor": _sensor(mi, camera, config.sun_spp, config.seed + 1),
                                      **self._emitter(sun_direction, config, sun=True, sky=False),
                                      **self.shapes})
                start = time.perf_counter()
                sun_direct = np.array(mi.render(scene), dtype=np.float32)[..., :3]
                seconds["sun_direct"] = time.perf_counter() - start
            else:
                sun_direct = np.zeros_like(image)
        return Renders(np.ascontiguousarray(image), None if albedo is None else np.ascontiguousarray(albedo),
                       sun_direct, seconds)


def sun_radiance(sun_direction: Sequence[float], config: RenderConfig, *, size: int = 16) -> np.ndarray:
    """``L_sun`` in shading units: radiance of a white diffuse square facing the sun, sun only.

    A Lambertian surface of albedo 1 facing the sun reflects ``E_sun / pi``, which is exactly the
    shading ``S_sun = L_sun * max(0, cos)`` at ``cos = 1`` (shading = image / reflectance).

    Returns
    -------
    (3,) float64
        RGB sun radiance; zeros when the sun is off.
    """
    if not config.sun:
        return np.zeros(3)
    if config.sky == "simulated":  # the directional emitter's irradiance is pi times this
        return np.array(simulated_sky(sun_direction, config).sun_radiance, dtype=np.float64)
    mi = import_mitsuba()
    d = np.asarray(sun_direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    up = [0, 0, 1] if abs(d[2]) < 0.99 else [1, 0, 0]
    # A 2 m x 2 m rectangle (local normal +Z) turned so that its normal is the sun direction.
    plate_to_world = mi.ScalarTransform4f().look_at(origin=[0, 0, 0], target=d.tolist(), up=up)
    camera_at = 5.0 * d
    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "direct"},
        "plate": {"type": "rectangle", "to_world": plate_to_world,
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [1.0, 1.0, 1.0]}}},
        "sensor": {"type": "perspective", "fov": 5.0,
                   "to_world": mi.ScalarTransform4f().look_at(origin=camera_at.tolist(), target=[0, 0, 0], up=up),
                   "film": {"type": "hdrfilm", "width": size, "height": size, "rfilter": {"type": "box"},
                            "pixel_format": "rgb"},
                   "sampler": {"type": "independent", "sample_count": 256, "seed": int(config.seed)}},
        "emitter": {"type": "sunsky", "sun_direction": d.tolist(), "turbidity": float(config.turbidity),
                    "albedo": float(config.ground_albedo), "sun_scale": 1.0, "sky_scale": 0.0},
    })
    image = np.array(mi.render(scene), dtype=np.float64)[..., :3]
    return image.reshape(-1, 3).mean(axis=0)


def sky_radiance(sun_direction, directions: np.ndarray, *, turbidity: float = 3.0,
                 ground_albedo: float = 0.3) -> np.ndarray:
    """Radiance of Mitsuba's ``sunsky`` emitter (Hosek-Wilkie sky and the sun's disc) toward
    world ``directions (N, 3)``, Z up; 0 below the horizon. (N, 3) float64.

    This is the sky the synthetic scenes are rendered under, for checking a fitted sky model.
    """
    import drjit as dr

    mi = import_mitsuba()
    emitter = mi.load_dict({"type": "sunsky", "sun_direction": [float(v) for v in sun_direction],
                            "turbidity": float(turbidity), "albedo": float(ground_albedo)})
    si = dr.zeros(mi.SurfaceInteraction3f)
    directions = np.asarray(directions, dtype=np.float64)
    out = np.zeros((len(directions), 3))
    for i, d in enumerate(directions):
        if d[2] > 0:
            si.wi = mi.Vector3f(*(-d))  # wi points away from the emitter: radiance arriving along -d
            out[i] = np.array(emitter.eval(si))
    return out
