"""Small argument checks shared by the data model (private).

Every helper raises :class:`ValueError` or :class:`TypeError` whose message names the
argument, the expected shape or range and what was received, as the style guide asks.
"""

from __future__ import annotations

from typing import TypeVar

import numpy as np

T = TypeVar("T")

__all__ = ["as_array", "as_unit_vector", "config_or_default", "describe", "is_real"]


def describe(value: object) -> str:
    """Return a short description of ``value`` for error messages."""
    if isinstance(value, np.ndarray):
        return f"array of shape {value.shape} and dtype {value.dtype}"
    return f"{type(value).__name__} {value!r}"[:120]


def config_or_default(config: object, cls: type[T]) -> T:
    """``cls()`` (the paper's values) for ``None``, else ``config`` itself if it is a ``cls``.

    Raises
    ------
    TypeError
        If ``config`` is neither ``None`` nor a ``cls``; the message names ``config`` and ``cls``.
    """
    if config is None:
        return cls()
    if not isinstance(config, cls):
        article = "an" if cls.__name__[:1] in "AEIOU" else "a"
        raise TypeError(f"config must be {article} {cls.__name__}, got {describe(config)}")
    return config


def is_real(value: object) -> bool:
    """Whether ``value`` is a real scalar (Python or NumPy int or float), bools excluded."""
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)


def as_count(value: object, name: str, *, least: int) -> int:
    """``value`` as an ``int`` if it is a Python or NumPy integer (bools excluded) of at least ``least``.

    Raises
    ------
    ValueError
        Otherwise, naming ``name``: "``name`` must be an integer >= ``least``, got ``value``".
    """
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
        raise ValueError(f"{name} must be an integer >= {least}, got {value!r}")
    return int(value)


def as_array(
    value: object,
    name: str,
    *,
    shape: tuple[int | None, ...],
    dtype: type | np.dtype,
    finite: bool = True,
) -> np.ndarray:
    """Return ``value`` as a read-only array of ``dtype`` and ``shape``.

    Parameters
    ----------
    value : array_like
        The input.
    name : str
        Argument name used in error messages.
    shape : tuple of int or None
        Expected shape; ``None`` matches any length along that axis.
    dtype : numpy dtype
        Target dtype; the input is converted (a copy is made when needed).
    finite : bool, optional
        Reject NaN and infinite values.

    Returns
    -------
    ndarray
        A read-only array (the input is never mutated; a copy is taken when it was writeable).
    """
    try:
        array = np.array(value, dtype=dtype, copy=True)
    except (TypeError, ValueError) as exc:
        raise TypeError(f"{name} must be convertible to a {np.dtype(dtype)} array, got {describe(value)}") from exc
    expected = "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"
    if array.ndim != len(shape) or any(s is not None and s != a for s, a in zip(shape, array.shape, strict=False)):
        raise ValueError(f"{name} must have shape {expected}, got shape {array.shape}")
    if finite and array.dtype.kind == "f" and not np.isfinite(array).all():
        raise ValueError(f"{name} must be finite, got {int((~np.isfinite(array)).sum())} NaN/Inf values")
    array.flags.writeable = False
    return array


def as_unit_vector(value: object, name: str) -> np.ndarray:
    """Return ``value`` as a read-only unit ``(3,)`` float64 vector.

    Raises
    ------
    ValueError
        If the vector is not of shape (3,), not finite, or of (near) zero length.
    """
    vector = as_array(value, name, shape=(3,), dtype=np.float64)
    norm = float(np.linalg.norm(vector))
    if norm < 1e-12:
        raise ValueError(f"{name} must be a non-zero vector, got {vector.tolist()}")
    # A vector already of unit length (within float64 rounding) is kept bit for bit, so that a
    # direction written out and read back compares equal: dividing by a norm that rounds 1 ulp off
    # 1 would move it (seen with NumPy 2.4's norm).
    unit = vector.copy() if abs(norm - 1.0) <= 4 * np.finfo(np.float64).eps else vector / norm
    unit.flags.writeable = False
    return unit
