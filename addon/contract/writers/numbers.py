# SPDX-License-Identifier: Apache-2.0
"""Deterministic, short number formatting for the exported text files.

Blender stores float properties and coordinates as 32-bit floats, so
``2.4e9`` comes back as a float32. We print the shortest decimal that maps to
the same float32, which gives ``0.2`` rather than ``0.20000000298023224``.
"""

from __future__ import annotations

import math
import struct


def to_f32(x: float) -> float:
    """Round a Python float to the nearest float32 value."""
    return struct.unpack("<f", struct.pack("<f", x))[0]


def fmt_float(x: float) -> str:
    """Shortest decimal text for ``x`` that round-trips through float32; always has '.' or 'e'.

    Raises:
        ValueError: ``x`` is NaN or infinite.
    """
    x = float(x)
    if not math.isfinite(x):
        raise ValueError(f"cannot write non-finite number {x!r}")
    if x == 0.0:
        return "0.0"  # also turns -0.0 into 0.0
    target = to_f32(x)
    for digits in range(1, 10):
        text = f"{target:.{digits}g}"
        if to_f32(float(text)) == target:
            return repr(float(text))
    return repr(target)


def clean(x: float, eps: float = 1e-7) -> float:
    """``x`` with float32 noise below ``eps`` (e.g. 1e-8 rad) and -0.0 mapped to 0.0."""
    return 0.0 if abs(x) < eps else float(x)
