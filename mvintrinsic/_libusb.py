"""Make ``libusb-1.0.so.0`` loadable for open3d on systems that lack it (private).

The Linux wheels of open3d link ``libusb-1.0.so.0`` (for its RealSense support) even though
mvintrinsic never touches USB devices; a bare Debian or a slim container has no such library and
``import open3d`` fails with ``ImportError: libusb-1.0.so.0: cannot open shared object file``.
When the system provides the library nothing happens. Otherwise the copy shipped by the
``libusb-package`` wheel (a runtime dependency on Linux) is loaded with ``RTLD_GLOBAL`` before
open3d is first imported, so the dynamic linker resolves open3d's dependency to it.
:mod:`mvintrinsic` calls :func:`ensure_libusb` on import, so ``import mvintrinsic, open3d`` works
after a plain ``pip install``.
"""

from __future__ import annotations

import ctypes
import sys

__all__ = ["ensure_libusb"]

_SONAME = "libusb-1.0.so.0"
_loaded: str | None = None


def ensure_libusb() -> str | None:
    """Load a libusb for open3d when the system has none.

    Returns
    -------
    str or None
        Path of the bundled library that was loaded, or ``None`` when nothing was needed (the
        system library is present, the platform is not Linux, or ``libusb-package`` is absent,
        in which case importing open3d will report the missing library itself).
    """
    global _loaded
    if _loaded is not None or not sys.platform.startswith("linux"):
        return _loaded
    try:
        ctypes.CDLL(_SONAME)  # the system's own copy, found by the dynamic linker
        return None
    except OSError:
        pass
    try:
        import libusb_package
    except ImportError:
        return None
    path = libusb_package.get_library_path()
    if path is None:
        return None
    ctypes.CDLL(str(path), mode=ctypes.RTLD_GLOBAL)
    _loaded = str(path)
    return _loaded
