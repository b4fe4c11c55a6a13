"""Input validation shared by the PHY modules (private).

Every check raises :class:`ValueError` whose message names the offending
argument, so a caller deep inside the twin sees *what* was wrong, not just
that a numpy broadcast failed.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np


def real_array(name: str, value, *, ndim: int | None = None,
               shape: Sequence[int | None] | None = None,
               nonnegative: bool = False) -> np.ndarray:
    """Return ``value`` as a finite float64 array or raise ``ValueError``."""
    arr = np.asarray(value)
    if np.iscomplexobj(arr):
        raise ValueError(f"{name} must be real, got a complex array")
    try:
        arr = arr.astype(np.float64, copy=False)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be numeric: {exc}") from None
    _check_shape(name, arr, ndim, shape)
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or infinite values")
    if nonnegative and np.any(arr < 0):
        raise ValueError(f"{name} must be non-negative, got min {arr.min():g}")
    return arr


def complex_array(name: str, value, *, ndim: int | None = None,
                  shape: Sequence[int | None] | None = None,
                  dtype=np.complex128) -> np.ndarray:
    """Return ``value`` as a finite complex array or raise ``ValueError``."""
    arr = np.asarray(value)
    try:
        arr = arr.astype(dtype, copy=False)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be numeric: {exc}") from None
    _check_shape(name, arr, ndim, shape)
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or infinite values")
    return arr


def _check_shape(name: str, arr: np.ndarray, ndim: int | None,
                 shape: Sequence[int | None] | None) -> None:
    if ndim is not None and arr.ndim != ndim:
        raise ValueError(f"{name} must have {ndim} dimension(s), "
                         f"got shape {arr.shape}")
    if shape is not None:
        if arr.ndim != len(shape) or any(
                s is not None and s != a for s, a in zip(shape, arr.shape)):
            want = "[" + ", ".join("*" if s is None else str(s)
                                    for s in shape) + "]"
            raise ValueError(f"{name} must have shape {want}, "
                             f"got {list(arr.shape)}")


def positive_int(name: str, value) -> int:
    """Return ``value`` as a positive ``int`` or raise ``ValueError``."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"{name} must be an integer, got {value!r}")
    if value < 1:
        raise ValueError(f"{name} must be >= 1, got {value}")
    return int(value)


def positive_float(name: str, value, *, allow_zero: bool = False) -> float:
    """Return ``value`` as a finite positive ``float`` or raise."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if not np.isfinite(v):
        raise ValueError(f"{name} must be finite, got {value!r}")
    if v < 0 or (v == 0 and not allow_zero):
        raise ValueError(f"{name} must be {'>= 0' if allow_zero else '> 0'}"
                         f", got {value!r}")
    return v


def same_length(**arrays: np.ndarray) -> int:
    """Check that all 1-D arrays have equal length; return it."""
    lengths = {k: np.shape(v)[0] for k, v in arrays.items()}
    if len(set(lengths.values())) > 1:
        desc = ", ".join(f"{k}: {n}" for k, n in lengths.items())
        raise ValueError(f"per-path inputs must have the same length L ({desc})")
    return next(iter(lengths.values()))
