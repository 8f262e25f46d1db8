"""Result folders: checked before any work, written whole and swapped in, read back (``docs/formats.md``).

A result folder is written whole beside its place and swapped in (all or nothing), never inside
a scene folder, and a non-empty folder that mvintrinsic did not create is only written into
when ``overwrite=True``; :func:`check_result_folder` refuses a bad output before any work.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import functools
import json
import os
import shutil
import tempfile
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from .errors import ResultFolderError, SceneError
from .files import _atomic_write, _read_stored, _umask, write_image, write_json
from .results import Decomposition, IntrinsicLayers, Lighting, ModelChoice, SkyParameters, ViewGains
from .scene import Scene, Sun

__all__ = ["RESULT_MARKER", "check_result_folder", "load_decomposition", "save_decomposition"]

#: File that marks a folder as created by :func:`save_decomposition`.
RESULT_MARKER = ".mvintrinsic-result"


# ---------------------------------------------------------------------------------------------
# result folder
# ---------------------------------------------------------------------------------------------
def _is_scene_folder(folder: Path) -> bool:
    return (folder / "scene.json").is_file() and (folder / "sparse").is_dir()


def _nearest_existing(folder: Path) -> Path:
    for candidate in (folder, *folder.parents):
        if candidate.exists():
            return candidate
    return Path(folder.anchor)


def _is_foreign(folder: Path) -> bool:
    """A non-empty folder that mvintrinsic did not write (no :data:`RESULT_MARKER`)."""
    return folder.is_dir() and any(folder.iterdir()) and not (folder / RESULT_MARKER).is_file()


def _write_marker(folder: Path) -> None:
    _atomic_write(folder / RESULT_MARKER, lambda tmp: tmp.write_text("written by mvintrinsic\n"))


def check_result_folder(
    folder: os.PathLike | str,
    *,
    scene: Scene | os.PathLike | str | None = None,
    overwrite: bool = False,
) -> Path:
    """Refuse an output folder that :func:`save_decomposition` could not or must not write.

    Call it before a long computation (the CLI does) so that a bad ``OUT`` costs nothing; it
    writes nothing.

    Parameters
    ----------
    folder : path-like
        The intended result folder.
    scene : Scene or path-like, optional
        The input scene (or its folder): the result may not be it or lie inside it.
    overwrite : bool, optional
        Accept a non-empty folder that mvintrinsic did not write (:data:`RESULT_MARKER` absent).

    Returns
    -------
    pathlib.Path
        ``folder``, resolved.

    Raises
    ------
    ResultFolderError
        If ``folder`` is a file, is or lies inside the scene folder (or any folder that looks
        like a scene folder: ``scene.json`` and ``sparse/``), is a non-empty folder that
        mvintrinsic did not write and ``overwrite`` is false, or cannot be written (the message
        names the folder and the reason).
    """
    folder = Path(folder).resolve()
    scene_dir = scene.source if isinstance(scene, Scene) else (None if scene is None else Path(scene))
    if scene_dir is not None:
        scene_dir = Path(scene_dir).resolve()
        if folder == scene_dir or scene_dir in folder.parents:
            raise ResultFolderError(f"{folder}: refusing to write a result inside the scene folder {scene_dir}")
    for candidate in (folder, *folder.parents):
        if _is_scene_folder(candidate):
            raise ResultFolderError(f"{folder}: refusing to write a result inside the scene folder {candidate}")
    existing = _nearest_existing(folder)
    if not existing.is_dir():
        raise ResultFolderError(f"{folder}: {existing} exists and is not a folder")
    if _is_foreign(folder) and not overwrite:
        raise ResultFolderError(
            f"{folder}: is not empty and was not written by mvintrinsic; choose another folder or pass "
            "overwrite=True (--overwrite) to write into it"
        )
    # The result is written beside the folder and swapped in, or (a foreign folder) into it.
    for where in {_nearest_existing(folder.parent), existing}:
        if not os.access(where, os.W_OK | os.X_OK):
            raise ResultFolderError(f"{folder}: cannot write there ({where} is not writable)")
    return folder


def _prepare_result_folder(folder: Path, *, overwrite: bool, scene: Scene | os.PathLike | str | None) -> Path:
    """:func:`check_result_folder`, then create the folder and its marker (for in-place writers)."""
    folder = check_result_folder(folder, scene=scene, overwrite=overwrite)
    folder.mkdir(parents=True, exist_ok=True)
    if not (folder / RESULT_MARKER).is_file():
        _write_marker(folder)
    return folder


#: Prefix of the sibling folders a result is written into before it is swapped in.
_PARTIAL = "partial"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):  # another user's process, or no such pid number
        pass
    return True


def _remove_stale_partials(folder: Path) -> None:
    """Delete sibling work folders (``.NAME.partial-PID-*``) left by writers that were killed."""
    for sibling in folder.parent.glob(f".{folder.name}.{_PARTIAL}-*"):
        pid = sibling.name[len(f".{folder.name}.{_PARTIAL}-"):].split("-", 1)[0]
        if sibling.is_dir() and pid.isdigit() and not _alive(int(pid)):
            shutil.rmtree(sibling, ignore_errors=True)


@functools.cache
def _renameat2():
    """glibc's ``renameat2`` (Linux >= 3.15, glibc >= 2.28), or None."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        function = libc.renameat2
    except (OSError, AttributeError):
        return None
    function.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    function.restype = ctypes.c_int
    return function


def _exchange(a: Path, b: Path) -> bool:
    """Swap two paths in one atomic step (``RENAME_EXCHANGE``); False where the system cannot."""
    function = _renameat2()
    if function is None:
        return False
    at_fdcwd, rename_exchange = -100, 2
    if function(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), rename_exchange) == 0:
        return True
    error = ctypes.get_errno()
    if error in (errno.EINVAL, errno.ENOSYS, errno.EOPNOTSUPP):
        return False
    raise OSError(error, os.strerror(error), str(b))


def _swap_in(work: Path, folder: Path) -> None:
    """Put the complete folder ``work`` at ``folder``; a crash at any instant leaves a complete one.

    An absent or empty ``folder`` is replaced by a rename. An existing result is exchanged with
    ``work`` in one atomic step where the system offers it (Linux ``renameat2``), then deleted;
    elsewhere it is renamed aside first, so that a crash between the two renames leaves it, whole,
    as ``.NAME.partial-PID-*`` beside an absent ``folder``.
    """
    if folder.is_dir() and not any(folder.iterdir()):
        folder.rmdir()
    if not folder.exists():
        os.rename(work, folder)
        return
    if not _exchange(work, folder):
        aside = Path(tempfile.mkdtemp(prefix=f".{folder.name}.{_PARTIAL}-{os.getpid()}-old-", dir=folder.parent))
        os.rename(folder, aside / "result")
        os.rename(work, folder)
        work = aside
    shutil.rmtree(work, ignore_errors=True)  # now the old result


def _result_files(result: Decomposition) -> dict[str, tuple[np.ndarray, str]]:
    """Relative path -> (array, :func:`write_image` dtype) of every layer file of a result folder."""
    files = {}
    if result.lighting.envmap is not None:
        files["envmap.exr"] = (result.lighting.envmap, "float")
    for stem, layers in result.layers.items():
        for name in ("reflectance", "shading", "sun_shading", "sky_shading", "indirect_shading", "visibility"):
            files[f"views/{stem}/{name}.exr"] = (getattr(layers, name), "float")
        files[f"views/{stem}/shadow_labels.png"] = (layers.shadow_labels, "uint8")
    return files


def save_decomposition(
    result: Decomposition,
    folder: os.PathLike | str,
    *,
    overwrite: bool = False,
    scene: Scene | os.PathLike | str | None = None,
) -> Path:
    """Write a decomposition as a result folder (``docs/formats.md``), all or nothing.

    Parameters
    ----------
    result : Decomposition
        What to write.
    folder : path-like
        Destination folder, created if needed (:func:`check_result_folder` says which are
        refused).
    overwrite : bool, optional
        Allow writing into an existing non-empty folder that mvintrinsic did not create; its
        other files are kept. Folders mvintrinsic created (they hold :data:`RESULT_MARKER`) are
        replaced whole without it.
    scene : Scene or path-like, optional
        The input scene (or its folder): writing inside it is refused. Folders that look like a
        scene folder (``scene.json`` + ``sparse/``), or lie inside one, are refused in any case.

    Returns
    -------
    pathlib.Path
        The result folder.

    Raises
    ------
    ResultFolderError
        If ``folder`` may not or cannot be written (:func:`check_result_folder`).

    Notes
    -----
    An absent, empty or mvintrinsic-written ``folder`` is written as a hidden sibling
    (``.NAME.partial-PID-*``) and swapped in when complete (:func:`os.rename`; over an existing
    result, Linux's atomic ``renameat2`` exchange): a crash or ``kill -9`` at any instant leaves
    either the complete old result or the complete new one, and a later write removes the
    sibling a killed writer left. A result of fewer views replaces a larger one whole (no stale
    view folder). Into a foreign folder (``overwrite=True``) the files are written in place,
    ``lighting.json`` removed first and written last. ``lighting.json`` lists every layer file
    with its size, and :func:`load_decomposition` refuses a folder that does not match it. Every
    file is written atomically with the user's umask; EXR files are 32-bit float (lossless round
    trip).
    """
    if not isinstance(result, Decomposition):
        raise TypeError(f"result must be a Decomposition, got {type(result).__name__}")
    folder = check_result_folder(folder, scene=scene, overwrite=overwrite)
    if _is_foreign(folder):  # overwrite=True: written in place, its other files kept
        _write_marker(folder)
        with contextlib.suppress(FileNotFoundError):
            (folder / "lighting.json").unlink()  # incomplete until it is written again, last
        _write_result(result, folder)
        return folder
    folder.parent.mkdir(parents=True, exist_ok=True)
    _remove_stale_partials(folder)
    work = Path(tempfile.mkdtemp(prefix=f".{folder.name}.{_PARTIAL}-{os.getpid()}-", dir=folder.parent))
    try:
        os.chmod(work, 0o777 & ~_umask())
        _write_marker(work)
        _write_result(result, work)
        _swap_in(work, folder)
    except BaseException:
        shutil.rmtree(work, ignore_errors=True)
        raise
    return folder


def _write_result(result: Decomposition, folder: Path) -> None:
    """Every layer file, then ``lighting.json`` with the manifest of their sizes."""
    sizes = {}
    for relative, (array, dtype) in _result_files(result).items():
        sizes[relative] = write_image(folder / relative, array, dtype=dtype).stat().st_size
    lighting = result.lighting.to_dict()
    lighting.update(
        views=list(result.stems), timings=dict(result.timings), version=result.version,
        config=result.config_dict(),
        diagnostics=dict(result.diagnostics), files=sizes,
    )
    write_json(folder / "lighting.json", lighting)


def _read_raw(path: Path, channels: int) -> np.ndarray:
    """A result layer as stored (float32, or uint8 for PNG labels), ``(H, W)`` for one channel."""
    data, _ = _read_stored(path, "result file not found")
    if data.shape[2] != channels:
        raise SceneError(path, f"expected {channels} channels, found {data.shape[2]}")
    return data[..., 0] if channels == 1 else data


def _check_complete(folder: Path, data: dict) -> None:
    """Refuse a result folder that does not match its ``lighting.json`` (a mixed or partial write)."""
    file = folder / "lighting.json"
    views = data.get("views", [])
    if not isinstance(views, list) or not all(isinstance(v, str) for v in views):
        raise SceneError(file, "malformed lighting.json ('views' must be a list of view names)")
    if (folder / "views").is_dir():
        stale = sorted(p.name for p in (folder / "views").iterdir() if p.is_dir() and p.name not in views)
        if stale:
            raise SceneError(folder / "views" / stale[0], f"view folder not listed in lighting.json ({len(stale)} "
                             "such): the result folder mixes two writes; write the result again")
    sizes = data.get("files")
    if sizes is None:  # written before the manifest existed
        return
    if not isinstance(sizes, dict):
        raise SceneError(file, "malformed lighting.json ('files' must map file names to sizes)")
    for relative, size in sizes.items():
        path = folder / relative
        if not path.is_file():
            raise SceneError(path, "result file not found (incomplete result folder); write the result again")
        if path.stat().st_size != size:
            raise SceneError(path, f"{path.stat().st_size} bytes where lighting.json says {size}: the result "
                             "folder mixes two writes; write the result again")


def _config(data: Any, folder: Path) -> Any:
    """The saved configuration as a :class:`~mvintrinsic.Config`, or as saved when it is not one.

    A mapping with keys :class:`~mvintrinsic.Config` does not have is another method's settings (a
    baseline's) and is kept as it is; one with Config's keys that this version cannot read (values
    of another version) is kept too, with a warning naming the folder.
    """
    import dataclasses

    from .pipeline import Config

    if not data:
        return {}
    if not isinstance(data, Mapping) or not set(data) <= {f.name for f in dataclasses.fields(Config)}:
        return data
    try:
        return Config.from_dict(data)
    except (TypeError, ValueError) as error:
        warnings.warn(f"{folder}: the configuration in lighting.json is kept as a mapping: {error}", stacklevel=3)
        return data


def load_decomposition(folder: os.PathLike | str) -> Decomposition:
    """Read a result folder written by :func:`save_decomposition`.

    ``shading.exr`` is not read back: it is derived from the other layers.

    Raises
    ------
    SceneError
        If ``lighting.json`` or a layer file is missing or malformed, or the folder does not match
        ``lighting.json`` (a file of another size than it lists, a view folder it does not list):
        the traces of an interrupted or mixed write.
    """
    folder = Path(folder)
    file = folder / "lighting.json"
    if not file.is_file():
        raise SceneError(file, "lighting.json not found (not a complete result folder)")
    try:
        data = json.loads(file.read_text())
        sky = None if data.get("sky") is None else SkyParameters.from_dict(data["sky"])
        envmap = _read_raw(folder / "envmap.exr", 3) if (folder / "envmap.exr").is_file() else None
        lighting = Lighting(
            Sun(data["sun_direction"], data.get("sun_angular_radius", Sun(data["sun_direction"]).angular_radius)),
            data["sun_radiance"],
            up=data["up"],
            sky=sky,
            horizon_plane=data.get("horizon_plane"),
            envmap=envmap,
            horizon_evidence=data.get("horizon_evidence"),
            exposure=None if data.get("exposure") is None else ViewGains.from_dict(data["exposure"]),
            model={name: ModelChoice.from_dict(value) for name, value in (data.get("model") or {}).items()},
        )
    except (KeyError, TypeError, ValueError) as exc:
        if isinstance(exc, SceneError):
            raise
        raise SceneError(file, f"malformed lighting.json ({exc!r})") from exc
    _check_complete(folder, data)
    layers = {}
    for stem in data.get("views", []):
        out = folder / "views" / stem
        layers[stem] = IntrinsicLayers(
            stem,
            reflectance=_read_raw(out / "reflectance.exr", 3),
            sun_shading=_read_raw(out / "sun_shading.exr", 3),
            sky_shading=_read_raw(out / "sky_shading.exr", 3),
            indirect_shading=_read_raw(out / "indirect_shading.exr", 3),
            visibility=_read_raw(out / "visibility.exr", 1),
            shadow_labels=_read_raw(out / "shadow_labels.png", 1),
        )
    return Decomposition(
        layers, lighting, timings=data.get("timings", {}), config=_config(data.get("config", {}), folder),
        version=data.get("version", ""),
        diagnostics=data.get("diagnostics", {}),
    )
