"""mvintrinsic: multi-view intrinsic images of outdoor scenes, and relighting.

A reference implementation of Duchêne, Riant, Chaurasia, Lopez-Moreno, Laffont, Popov, Bousseau
and Drettakis, "Multi-View Intrinsic Images of Outdoors Scenes with an Application to
Relighting", ACM Transactions on Graphics 34(5), 2015.

The package is layered: the data model (:mod:`~mvintrinsic.camera`, :mod:`~mvintrinsic.scene`,
:mod:`~mvintrinsic.results`) at the bottom, pure computational stages above it
(:mod:`~mvintrinsic.raytrace`, :mod:`~mvintrinsic.sun_calibration`, ...) composed by
:func:`~mvintrinsic.decompose` (:mod:`~mvintrinsic.pipeline`), and the edge
(:mod:`~mvintrinsic.io`, :mod:`~mvintrinsic.metrics`, :mod:`~mvintrinsic.cli`) that touches files
and users. See ``docs/`` for conventions and file formats.
"""

from ._libusb import ensure_libusb as _ensure_libusb

_ensure_libusb()  # before anything imports open3d; see mvintrinsic/_libusb.py

from ._version import __version__  # noqa: E402
from .camera import CAMERA_MODELS, Camera  # noqa: E402
from .io import load_decomposition, load_scene, save_decomposition  # noqa: E402
from .pipeline import Config, decompose  # noqa: E402
from .results import Decomposition, IntrinsicLayers, Lighting, SkyParameters  # noqa: E402
from .scene import Proxy, Scene, Sun, View  # noqa: E402

__all__ = [
    "CAMERA_MODELS",
    "Camera",
    "Config",
    "Decomposition",
    "IntrinsicLayers",
    "Lighting",
    "Proxy",
    "Scene",
    "SkyParameters",
    "Sun",
    "View",
    "__version__",
    "decompose",
    "load_decomposition",
    "load_scene",
    "save_decomposition",
]
