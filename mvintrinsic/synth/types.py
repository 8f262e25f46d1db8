"""Data types of the synthetic-scene generator (edge layer: never imported by the core).

A recipe (:mod:`mvintrinsic.synth.recipes`) builds a :class:`SynthScene`: triangle meshes with
texture coordinates, their materials (procedural albedo textures) and a camera path. The renderer
(:mod:`mvintrinsic.synth.render`) turns it into images and ground-truth layers; the MVS simulator
(:mod:`mvintrinsic.synth.proxy`) turns its geometry into an imperfect proxy.

World frame: right-handed, metres, **Z up** (as Mitsuba's ``sunsky`` emitter expects).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

import numpy as np

from ..scene import Proxy
from ._geometry import area_weighted_normals

__all__ = ["LABELS", "Material", "SynthMesh", "SynthScene", "ViewPath"]

#: Per-face geometry classes, in the order of ``gt/mesh_faces.npz["label_names"]``.
#: "foliage" and "thin" are what multi-view stereo mostly loses (see synth.proxy).
LABELS = ("ground", "solid", "foliage", "thin")


@dataclass(frozen=True, eq=False)
class Material:
    """A diffuse (optionally mildly glossy) material with a procedural albedo texture.

    Parameters
    ----------
    name : str
        Unique material name.
    albedo : (Ht, Wt, 3) float32
        Linear RGB diffuse albedo in [0, 1], tiled with ``repeat`` wrapping; row 0 is v = 1
        (top of the texture image), as image files store it.
    roughness : float, optional
        ``None`` for a purely diffuse (Lambertian) material; otherwise the GGX roughness
        ``alpha`` of a rough-plastic coating (mild gloss for stress tests).
    two_sided : bool, optional
        Shade both faces the same (thin leaves, signs).
    """

    name: str
    albedo: np.ndarray
    roughness: float | None = None
    two_sided: bool = False


@dataclass(frozen=True, eq=False)
class SynthMesh:
    """One triangle mesh of a synthetic scene.

    Parameters
    ----------
    name : str
        Unique name (also the PLY file name when rendering).
    vertices : (N, 3) float64
        World positions, metres, Z up.
    triangles : (M, 3) int64
        Vertex indices, counter-clockwise seen from the front (outside).
    uvs : (N, 2) float32
        Texture coordinates, in texture tiles (values beyond [0, 1] repeat the texture).
    material : str
        Key of :attr:`SynthScene.materials`.
    label : str
        Geometry class, one of :data:`LABELS`.
    """

    name: str
    vertices: np.ndarray
    triangles: np.ndarray
    uvs: np.ndarray
    material: str
    label: str


@dataclass(frozen=True, eq=False)
class ViewPath:
    """Where the recipe wants its cameras: a straight, horizontal, wide-baseline path.

    Parameters
    ----------
    center : (3,) float64
        Middle of the path (camera centres), metres.
    direction : (3,) float64
        Unit horizontal direction along which the cameras are spaced.
    target : (3,) float64
        Point every camera looks at.
    """

    center: np.ndarray
    direction: np.ndarray
    target: np.ndarray


@dataclass(frozen=True, eq=False)
class SynthScene:
    """A procedural outdoor scene.

    Parameters
    ----------
    recipe : str
        Recipe name.
    seed : int
        Seed it was built with (same seed, same scene).
    meshes : tuple of SynthMesh
        All geometry.
    materials : mapping of str to Material
        Materials by name.
    path : ViewPath
        Default camera path.
    markers : mapping of str to (3,) float64
        Named 3D points useful for tests (e.g. ``"pole_base"``, ``"pole_top"``).
    """

    recipe: str
    seed: int
    meshes: tuple[SynthMesh, ...]
    materials: Mapping[str, Material]
    path: ViewPath
    markers: Mapping[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "meshes", tuple(self.meshes))
        object.__setattr__(self, "materials", MappingProxyType(dict(self.materials)))
        object.__setattr__(self, "markers", MappingProxyType(dict(self.markers)))
        names = [m.name for m in self.meshes]
        if len(set(names)) != len(names):
            raise ValueError("meshes: names must be unique")
        for m in self.meshes:
            if m.material not in self.materials:
                raise ValueError(f"mesh {m.name!r} uses unknown material {m.material!r}")
            if m.label not in LABELS:
                raise ValueError(f"mesh {m.name!r}: label must be one of {LABELS}, got {m.label!r}")

    def merged(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """All meshes as one: vertices (N, 3), triangles (M, 3), per-face label index and
        per-face material index (into ``sorted(materials)``), both (M,) int32."""
        names = sorted(self.materials)
        vertices, triangles, labels, materials, offset = [], [], [], [], 0
        for m in self.meshes:
            vertices.append(m.vertices)
            triangles.append(m.triangles + offset)
            labels.append(np.full(len(m.triangles), LABELS.index(m.label), np.int32))
            materials.append(np.full(len(m.triangles), names.index(m.material), np.int32))
            offset += len(m.vertices)
        return np.concatenate(vertices), np.concatenate(triangles), np.concatenate(labels), np.concatenate(materials)

    def exact_proxy(self) -> Proxy:
        """The exact geometry as a mesh :class:`~mvintrinsic.scene.Proxy` (area-weighted vertex
        normals; a vertex used only by zero-area faces gets +Z)."""
        vertices, triangles, _, _ = self.merged()
        return Proxy(vertices, area_weighted_normals(vertices, triangles), triangles)
