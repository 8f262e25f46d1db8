"""The errors of the package's edge: bad scene input and refused result folders (``docs/formats.md``)."""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["ResultFolderError", "SceneError"]


class SceneError(ValueError):
    """A scene folder or one of its files is missing or malformed.

    Attributes
    ----------
    path : pathlib.Path
        The offending file or folder.
    """

    def __init__(self, path: os.PathLike | str, message: str) -> None:
        self.path = Path(path)
        super().__init__(f"{self.path}: {message}")


class ResultFolderError(ValueError):
    """A result folder cannot be written where asked (inside a scene, or a foreign folder)."""
