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
from .env_refine import Step4Result  # noqa: E402
from .env_shading import Step1Result, step1  # noqa: E402
from .io import demo_scene_path, load_decomposition, load_scene, save_decomposition  # noqa: E402
from .multiview_shadows import PixelShadowLabels  # noqa: E402
from .occluders import (  # noqa: E402
    OccluderConfig,
    Occluders,
    carve_occluders,
    occluded_step1,
    seen_occluders,
    smooth_occluder_reflectance,
)
from .photo_occupancy import OccupancyConfig  # noqa: E402
from .pipeline import (  # noqa: E402
    Config,
    Step3View,
    calibrate,
    carry_to_pixels,
    decompose,
    label_layers,
    step2_layers,
    step3,
    step4,
)
from .pixels import PixelQuantities  # noqa: E402
from .planes import PlaneConfig  # noqa: E402
from .raytrace import Tracer  # noqa: E402

# ``relight`` (the function) stays in its module: a package attribute of that name would hide the
# module ``mvintrinsic.relight`` from ``import mvintrinsic.relight as ...``.
from .relight import RelightConfig, Relighter  # noqa: E402
from .results import Decomposition, IntrinsicLayers, Lighting, SkyParameters  # noqa: E402
from .scene import Proxy, Scene, Sun, View  # noqa: E402
from .sun_calibration import SunCalibration  # noqa: E402

__all__ = [
    "CAMERA_MODELS",
    "Camera",
    "Config",
    "Decomposition",
    "IntrinsicLayers",
    "Lighting",
    "OccluderConfig",
    "OccupancyConfig",
    "Occluders",
    "PixelQuantities",
    "PixelShadowLabels",
    "PlaneConfig",
    "Proxy",
    "RelightConfig",
    "Relighter",
    "Scene",
    "SkyParameters",
    "Step1Result",
    "Step3View",
    "Step4Result",
    "Sun",
    "SunCalibration",
    "Tracer",
    "View",
    "__version__",
    "calibrate",
    "carry_to_pixels",
    "carve_occluders",
    "decompose",
    "demo_scene_path",
    "label_layers",
    "load_decomposition",
    "load_scene",
    "occluded_step1",
    "save_decomposition",
    "seen_occluders",
    "smooth_occluder_reflectance",
    "step1",
    "step2_layers",
    "step3",
    "step4",
]
