"""Result types that the pipeline stages fill: per-view intrinsic layers and the decomposition.

The layers follow the paper's image model (Duchêne et al. 2015, Eqs. 1 and 3)

.. math::

   I = R \\, (v_{sun} S_{sun} + S_{sky} + S_{ind}), \\qquad S_{sun} = L_{sun} \\max(0, \\cos\\omega_{sun})

with shading in the image's own units (irradiance / pi) so that ``reflectance * shading``
reproduces the image. Their file layout is the result folder of ``docs/formats.md``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import numpy as np

from ._validation import as_array, as_unit_vector, describe
from ._version import __version__
from .scene import Sun

__all__ = ["SHADOW_LABELS", "Decomposition", "IntrinsicLayers", "Lighting", "ModelChoice", "SkyParameters", "ViewGains"]

#: 8-bit codes of ``IntrinsicLayers.shadow_labels``.
SHADOW_LABELS: dict[str, int] = {"shadow": 0, "undecided": 128, "lit": 255}


def _rgb_image(value: object, name: str, shape: tuple[int, int]) -> np.ndarray:
    return as_array(value, name, shape=(*shape, 3), dtype=np.float32)


@dataclass(frozen=True, eq=False)
class IntrinsicLayers:
    """The decomposition of one view.

    Parameters
    ----------
    stem : str
        View name.
    reflectance : (H, W, 3) float32
        Diffuse albedo ``R`` in [0, 1] (linear RGB).
    sun_shading : (H, W, 3) float32
        ``S_sun = L_sun * max(0, cos w_sun)`` before visibility (Eq. 3), shading units.
    sky_shading : (H, W, 3) float32
        ``S_sky``: sky radiance integrated over the hemisphere of the normal (Eq. 1).
    indirect_shading : (H, W, 3) float32
        ``S_ind``: light from the rest of the scene, integrated over the hemisphere (Eq. 1).
    visibility : (H, W) float32
        Sun visibility ``v_sun`` in [0, 1] (fractional in penumbra).
    shadow_labels : (H, W) uint8
        Binary shadow labelling: 0 shadow, 255 lit, 128 undecided / penumbra / sky
        (:data:`SHADOW_LABELS`).

    Notes
    -----
    All arrays must be finite; pixels without an estimate (sky, invalid) hold 0 and label 128.
    """

    stem: str
    reflectance: np.ndarray
    sun_shading: np.ndarray
    sky_shading: np.ndarray
    indirect_shading: np.ndarray
    visibility: np.ndarray
    shadow_labels: np.ndarray

    def __post_init__(self) -> None:
        if not isinstance(self.stem, str) or not self.stem:
            raise ValueError(f"stem must be a non-empty string, got {describe(self.stem)}")
        reflectance = as_array(self.reflectance, "reflectance", shape=(None, None, 3), dtype=np.float32)
        shape = reflectance.shape[:2]
        object.__setattr__(self, "reflectance", reflectance)
        for name in ("sun_shading", "sky_shading", "indirect_shading"):
            object.__setattr__(self, name, _rgb_image(getattr(self, name), name, shape))
        visibility = as_array(self.visibility, "visibility", shape=shape, dtype=np.float32)
        if visibility.size and (visibility.min() < 0 or visibility.max() > 1):
            raise ValueError(f"visibility must lie in [0, 1], got range [{visibility.min()}, {visibility.max()}]")
        labels = np.asarray(self.shadow_labels)
        if labels.dtype != np.uint8:
            raise TypeError(f"shadow_labels must be uint8, got dtype {labels.dtype}")
        labels = as_array(labels, "shadow_labels", shape=shape, dtype=np.uint8)
        bad = ~np.isin(labels, list(SHADOW_LABELS.values()))
        if bad.any():
            raise ValueError(f"shadow_labels may only hold 0, 128 or 255, got {np.unique(labels[bad])[:5].tolist()}")
        object.__setattr__(self, "visibility", visibility)
        object.__setattr__(self, "shadow_labels", labels)

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)``."""
        return self.reflectance.shape[:2]

    @property
    def env_shading(self) -> np.ndarray:
        """``S_env = S_sky + S_ind`` (Eq. 3), (H, W, 3) float32."""
        return self.sky_shading + self.indirect_shading

    @property
    def shading(self) -> np.ndarray:
        """Total shading ``S_tot = v_sun S_sun + S_sky + S_ind`` (Eqs. 1, 3), (H, W, 3) float32."""
        return self.visibility[..., None] * self.sun_shading + self.env_shading

    def reconstruct(self) -> np.ndarray:
        """``R * S_tot``: the image the layers explain (Eq. 1), (H, W, 3) float32."""
        return self.reflectance * self.shading

    def __repr__(self) -> str:
        h, w = self.shape
        return f"IntrinsicLayers({self.stem!r}, {w}x{h})"


@dataclass(frozen=True)
class ModelChoice:
    """One choice of the model made from the data, and its evidence (``lighting.json`` "model").

    Parameters
    ----------
    choice : str
        What was chosen, e.g. ``"direct sun"`` / ``"no direct sun"`` or ``"run"`` / ``"fusion only"`` /
        ``"skipped"``.
    evidence : str
        Why, in one sentence with the figures.
    measures : mapping of str to float, int, bool or None
        The figures the choice was made on (JSON-ready).
    """

    choice: str
    evidence: str
    measures: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for name in ("choice", "evidence"):
            if not isinstance(getattr(self, name), str):
                raise TypeError(f"{name} must be a str, got {describe(getattr(self, name))}")
        if not isinstance(self.measures, Mapping):
            raise TypeError(f"measures must be a mapping, got {describe(self.measures)}")
        object.__setattr__(self, "measures", MappingProxyType(dict(self.measures)))

    def to_dict(self) -> dict[str, Any]:
        """``{"choice", "evidence", "measures"}``."""
        return {"choice": self.choice, "evidence": self.evidence, "measures": dict(self.measures)}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> ModelChoice:
        """Inverse of :meth:`to_dict`."""
        return cls(data["choice"], data["evidence"], data.get("measures", {}))


@dataclass(frozen=True, eq=False)
class ViewGains:
    """Per-view exposure and white-balance gains of the photographs (:mod:`mvintrinsic.exposure`).

    A view's pixel value at a surface point is ``gain * L`` per channel, with ``L`` the point's
    radiance in the scene's reference units (the geometric mean of the views' gains is 1 per
    channel). The decomposition divides each image by its gain, and multiplies its shading
    layers back by it, so that one ``L_sun`` and one reflectance serve all views while
    ``reflectance * shading`` still reproduces each photograph.

    Parameters
    ----------
    stems : tuple of str
        The views, in scene order.
    estimated : (V, 3) float64
        Estimated gains, positive, geometric mean 1 per channel over the views that share points.
    applied : bool
        Whether the decomposition compensated the images by ``estimated`` (else by 1).
    shared : (V,) int64
        Proxy points each view shares with at least one other view (the evidence of its gain).
    residual : (V, 3) float64
        Robust spread (1.4826 times the median absolute deviation) of the log residuals of each
        view's samples after the fit: how far the photos disagree beyond a gain (noise, JPEG,
        proxy errors, non-Lambertian surfaces).
    reason : str
        Why the gains were or were not applied.
    """

    stems: tuple[str, ...]
    estimated: np.ndarray
    applied: bool
    shared: np.ndarray
    residual: np.ndarray
    reason: str = ""

    def __post_init__(self) -> None:
        stems = tuple(self.stems)
        if not stems or not all(isinstance(s, str) and s for s in stems) or len(set(stems)) != len(stems):
            raise ValueError(f"stems must be distinct non-empty strings, got {stems!r}")
        n = len(stems)
        estimated = as_array(self.estimated, "estimated", shape=(n, 3), dtype=np.float64)
        if (estimated <= 0).any():
            raise ValueError("estimated gains must be positive")
        shared = as_array(self.shared, "shared", shape=(n,), dtype=np.int64)
        residual = as_array(self.residual, "residual", shape=(n, 3), dtype=np.float64, finite=False)
        if not isinstance(self.applied, bool):
            raise TypeError(f"applied must be a bool, got {describe(self.applied)}")
        for name, array in (("estimated", estimated), ("shared", shared), ("residual", residual)):
            array = np.array(array)
            array.flags.writeable = False
            object.__setattr__(self, name, array)
        object.__setattr__(self, "stems", stems)
        object.__setattr__(self, "reason", str(self.reason))

    @property
    def gains(self) -> np.ndarray:
        """The gains the decomposition used: ``estimated`` if applied, else ones; (V, 3) float64."""
        return self.estimated.copy() if self.applied else np.ones((len(self.stems), 3))

    def of(self, stem: str) -> np.ndarray:
        """The gain used for view ``stem``, (3,) float64."""
        if stem not in self.stems:
            raise KeyError(f"no view named {stem!r}; views are {list(self.stems)}")
        return self.gains[self.stems.index(stem)]

    @classmethod
    def identity(cls, stems: tuple[str, ...], reason: str = "not estimated") -> ViewGains:
        """Gains of 1 for every view, not applied."""
        n = len(tuple(stems))
        return cls(tuple(stems), np.ones((n, 3)), False, np.zeros(n, np.int64), np.full((n, 3), np.nan), reason)

    def to_dict(self) -> dict[str, Any]:
        """The ``exposure`` entry of ``lighting.json``."""
        return {
            "applied": self.applied,
            "reason": self.reason,
            "gains": {s: g.tolist() for s, g in zip(self.stems, self.gains, strict=True)},
            "estimated": {s: g.tolist() for s, g in zip(self.stems, self.estimated, strict=True)},
            "shared_points": {s: int(c) for s, c in zip(self.stems, self.shared, strict=True)},
            "residual": {s: [None if not np.isfinite(x) else float(x) for x in r]
                         for s, r in zip(self.stems, self.residual, strict=True)},
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> ViewGains:
        """Inverse of :meth:`to_dict`."""
        stems = tuple(data["estimated"])
        residual = [[np.nan if x is None else x for x in data["residual"][s]] for s in stems]
        return cls(stems, [data["estimated"][s] for s in stems], bool(data["applied"]),
                   [data["shared_points"][s] for s in stems], residual, data.get("reason", ""))

    def __repr__(self) -> str:
        spread = float(np.abs(np.log(self.estimated)).max()) if len(self.stems) else 0.0
        return f"ViewGains({len(self.stems)} views, applied={self.applied}, max |log gain| {spread:.3f})"


@dataclass(frozen=True, eq=False)
class SkyParameters:
    """Summary of the fitted sky model (paper Eq. 4), as written to ``lighting.json``.

    Parameters
    ----------
    model : str
        Sky model name: ``"preetham"``, ``"perez"`` or ``"constant"``
        (:data:`mvintrinsic.skymodel.SKY_MODELS`).
    turbidity : float
        Atmospheric turbidity ``t`` (> 0) of the Preetham coefficients (``"perez"``: of its
        chromaticities and of the fit its coefficients started from).
    scale : (3,) float64
        Per-channel scale ``k`` from the sky model's relative luminance to image radiance.
    residual : float
        Fit residual (RMS over the known sky pixels, image units).
    coefficients : (5,) float64, optional
        The Perez coefficients ``A..E`` of the luminance, model ``"perez"`` only.
    """

    model: str
    turbidity: float
    scale: np.ndarray
    residual: float
    coefficients: np.ndarray | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.model, str) or not self.model:
            raise ValueError(f"model must be a non-empty string, got {describe(self.model)}")
        if not (np.isfinite(self.turbidity) and self.turbidity > 0):
            raise ValueError(f"turbidity must be a positive number, got {self.turbidity!r}")
        if not (np.isfinite(self.residual) and self.residual >= 0):
            raise ValueError(f"residual must be a non-negative number, got {self.residual!r}")
        object.__setattr__(self, "turbidity", float(self.turbidity))
        object.__setattr__(self, "residual", float(self.residual))
        object.__setattr__(self, "scale", as_array(self.scale, "scale", shape=(3,), dtype=np.float64))
        if self.coefficients is not None:
            object.__setattr__(self, "coefficients",
                               as_array(self.coefficients, "coefficients", shape=(5,), dtype=np.float64))

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dictionary (``lighting.json["sky"]``)."""
        out = {"model": self.model, "turbidity": self.turbidity, "scale": self.scale.tolist(), "residual": self.residual}
        if self.coefficients is not None:
            out["coefficients"] = self.coefficients.tolist()
        return out

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> SkyParameters:
        """Inverse of :meth:`to_dict`."""
        return cls(data["model"], data["turbidity"], data["scale"], data["residual"], data.get("coefficients"))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, SkyParameters):
            return NotImplemented
        return self.to_dict() == other.to_dict()

    __hash__ = None  # type: ignore[assignment]


@dataclass(frozen=True, eq=False)
class Lighting:
    """The scene's estimated lighting, shared by all views.

    Parameters
    ----------
    sun : Sun
        Sun direction (unit, toward the sun, world frame).
    sun_radiance : (3,) float64
        ``L_sun`` in shading units: a white diffuse surface facing the sun has
        ``S_sun = sun_radiance`` (Eq. 1), RGB, non-negative.
    up : (3,) float64
        Unit world up vector.
    sky : SkyParameters, optional
        The fitted sky model (Eq. 4).
    horizon_plane : (4,) float64, optional
        ``[a, b, c, d]`` with ``a x + b y + c z + d = 0`` the main horizontal plane of the proxy,
        ``(a, b, c)`` unit.
    envmap : (He, 2 He, 3) float32, optional
        Completed environment map, equirectangular as in ``docs/conventions.md``.
    horizon_evidence : str, optional
        What placed the horizon: ``"proxy plane"`` (the paper's main horizontal plane of the
        proxy) or ``"up"`` (the scene's up vector, when the proxy has no clear ground plane).
    exposure : ViewGains, optional
        Per-view exposure and white-balance gains; the layers of view ``k`` are in that view's
        units, ``S_sun = gain_k * sun_radiance * max(0, cos w_sun)``. None: every gain 1.
    model : mapping of str to ModelChoice, optional
        The choices of the model made from the data and their evidence (beyond the paper):
        ``"sun"`` (direct sun or none, :func:`mvintrinsic.sun_calibration.direct_sun_evidence`),
        ``"step4"`` (``"run"``; ``"fusion only"`` without cast-shadow boundaries, the ``S_env``
        offsets skipped and the multi-view reflectance fusion kept; ``"skipped"``), ``"sky"``
        (the sky family by its held-out error).
    """

    sun: Sun
    sun_radiance: np.ndarray
    up: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    sky: SkyParameters | None = None
    horizon_plane: np.ndarray | None = None
    envmap: np.ndarray | None = None
    horizon_evidence: str | None = None
    exposure: ViewGains | None = None
    model: Mapping[str, ModelChoice] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not isinstance(self.sun, Sun):
            raise TypeError(f"sun must be a Sun, got {describe(self.sun)}")
        radiance = as_array(self.sun_radiance, "sun_radiance", shape=(3,), dtype=np.float64)
        if (radiance < 0).any():
            raise ValueError(f"sun_radiance must be non-negative, got {radiance.tolist()}")
        object.__setattr__(self, "sun_radiance", radiance)
        object.__setattr__(self, "up", as_unit_vector(self.up, "up"))
        if self.sky is not None and not isinstance(self.sky, SkyParameters):
            raise TypeError(f"sky must be SkyParameters or None, got {describe(self.sky)}")
        if self.horizon_plane is not None:
            plane = as_array(self.horizon_plane, "horizon_plane", shape=(4,), dtype=np.float64)
            if abs(np.linalg.norm(plane[:3]) - 1.0) > 1e-6:
                raise ValueError(f"horizon_plane normal (a, b, c) must be unit length, got {plane.tolist()}")
            object.__setattr__(self, "horizon_plane", plane)
        if self.envmap is not None:
            envmap = as_array(self.envmap, "envmap", shape=(None, None, 3), dtype=np.float32)
            if envmap.shape[1] != 2 * envmap.shape[0]:
                raise ValueError(f"envmap must have shape (He, 2*He, 3), got shape {envmap.shape}")
            object.__setattr__(self, "envmap", envmap)
        if self.horizon_evidence is not None and self.horizon_evidence not in ("proxy plane", "up"):
            raise ValueError(f"horizon_evidence must be 'proxy plane', 'up' or None, got {self.horizon_evidence!r}")
        if self.exposure is not None and not isinstance(self.exposure, ViewGains):
            raise TypeError(f"exposure must be ViewGains or None, got {describe(self.exposure)}")
        if not isinstance(self.model, Mapping) or not all(isinstance(v, ModelChoice) for v in self.model.values()):
            raise TypeError(f"model must be a mapping of str to ModelChoice, got {describe(self.model)}")
        object.__setattr__(self, "model", MappingProxyType(dict(self.model)))

    def gain(self, stem: str) -> np.ndarray:
        """Exposure gain of view ``stem`` (ones without :attr:`exposure`), (3,) float64."""
        return np.ones(3) if self.exposure is None else self.exposure.of(stem)

    def to_dict(self) -> dict[str, Any]:
        """The lighting keys of ``lighting.json`` (the envmap is written separately)."""
        return {
            "sun_direction": self.sun.direction.tolist(),
            "sun_angular_radius": self.sun.angular_radius,
            "sun_radiance": self.sun_radiance.tolist(),
            "sky": None if self.sky is None else self.sky.to_dict(),
            "up": self.up.tolist(),
            "horizon_plane": None if self.horizon_plane is None else self.horizon_plane.tolist(),
            "horizon_evidence": self.horizon_evidence,
            "exposure": None if self.exposure is None else self.exposure.to_dict(),
            "model": {name: choice.to_dict() for name, choice in self.model.items()},
        }


def _frozen_mapping(value: object, name: str) -> MappingProxyType:
    if not isinstance(value, Mapping):
        raise TypeError(f"{name} must be a mapping, got {describe(value)}")
    return MappingProxyType(dict(value))


@dataclass(frozen=True, eq=False)
class Decomposition:
    """The result of decomposing a scene: layers of every view plus the shared lighting.

    Parameters
    ----------
    layers : mapping of str to IntrinsicLayers
        Layers by view stem (keys equal each value's ``stem``); stored read-only.
    lighting : Lighting
        Shared lighting estimate.
    timings : mapping of str to float, optional
        Wall-clock seconds spent in each stage, by stage name.
    config : Config or mapping, optional
        The configuration used: the :class:`mvintrinsic.Config` of :func:`mvintrinsic.decompose`
        (and of a result folder it wrote, read back), or a JSON-compatible mapping for results made
        otherwise (a baseline's settings, or a result folder whose configuration this version
        cannot read).
    version : str, optional
        mvintrinsic version that produced the result.
    diagnostics : mapping, optional
        How the numerical solves went, JSON-compatible: ``{"matting": {stem: [report, ...]}}`` with
        one report per linear system of the view's matting (``what``, ``solver``, ``unknowns``,
        ``channels``, ``converged``, ``n_iter``, ``residual``, ``seconds``;
        :class:`mvintrinsic.laplacian.SolveReport`). Empty when nothing was solved (no matting).
        ``{"occluders": {"voxels", "voxel", "rays", "smoothed_share"}}`` where the occluders the
        proxy lost were carved (:mod:`mvintrinsic.occluders`): their number, edge (m), the rays
        used, and the share of the pixels whose reflectance was smoothed (mean over the views).
    """

    layers: Mapping[str, IntrinsicLayers]
    lighting: Lighting
    timings: Mapping[str, float] = field(default_factory=dict)
    config: Any = field(default_factory=dict)
    version: str = ""
    diagnostics: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        layers = _frozen_mapping(self.layers, "layers")
        for stem, layer in layers.items():
            if not isinstance(layer, IntrinsicLayers):
                raise TypeError(f"layers[{stem!r}] must be IntrinsicLayers, got {describe(layer)}")
            if layer.stem != stem:
                raise ValueError(f"layers[{stem!r}] holds the layers of view {layer.stem!r}")
        if not isinstance(self.lighting, Lighting):
            raise TypeError(f"lighting must be Lighting, got {describe(self.lighting)}")
        timings = _frozen_mapping(self.timings, "timings")
        for stage, seconds in timings.items():
            if not (isinstance(seconds, (int, float)) and np.isfinite(seconds) and seconds >= 0):
                raise ValueError(f"timings[{stage!r}] must be a non-negative number of seconds, got {seconds!r}")
        object.__setattr__(self, "layers", layers)
        object.__setattr__(self, "timings", timings)
        if isinstance(self.config, Mapping):
            object.__setattr__(self, "config", _frozen_mapping(self.config, "config"))
        elif not callable(getattr(self.config, "to_dict", None)):  # a Config (defined above this layer)
            raise TypeError(f"config must be a Config or a mapping, got {describe(self.config)}")
        object.__setattr__(self, "diagnostics", _frozen_mapping(self.diagnostics, "diagnostics"))
        if not self.version:
            object.__setattr__(self, "version", __version__)

    def config_dict(self) -> dict[str, Any]:
        """:attr:`config` as a JSON-compatible mapping (a Config's ``to_dict()``, or the mapping itself)."""
        return dict(self.config) if isinstance(self.config, Mapping) else self.config.to_dict()

    @property
    def stems(self) -> tuple[str, ...]:
        """View names in order."""
        return tuple(self.layers)

    def __repr__(self) -> str:
        return f"Decomposition({len(self.layers)} views, stages={list(self.timings)}, version={self.version!r})"
