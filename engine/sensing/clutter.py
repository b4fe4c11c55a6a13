"""Background (static clutter) subtraction on channel estimates.

A real radar does not know which paths touch a target: it removes what
does not change. Two estimators of the background ``B [Ks, Ns, Nr]``:

* ``"ema"``: exponentially averaged channel estimate over steps,
  ``B <- (1 - beta) B + beta H_hat`` (initialised with the first frame);
  a target moving by a fraction of a wavelength per step decorrelates from
  the average and survives, static clutter is removed. Time constant
  ``~ 1 / beta`` steps.
* ``"reference"``: a fixed empty-room channel (e.g. measured/calibrated
  before the robots enter; in the twin: the clutter-only channel).

``"none"`` disables subtraction.
"""

from __future__ import annotations

import numpy as np

from ..errors import SensingError

__all__ = ["BackgroundSubtractor"]


class BackgroundSubtractor:
    """Stateful background subtraction for one sensing link.

    Args:
        mode: ``"ema"``, ``"reference"`` or ``"none"``.
        beta: EMA update weight in (0, 1] (``"ema"``).
        name: link name for errors.
    """

    def __init__(self, mode: str = "ema", beta: float = 0.1, name: str = "sensing") -> None:
        if mode not in ("ema", "reference", "none"):
            raise SensingError(f"sensing link {name!r}: background mode must be 'ema', "
                               f"'reference' or 'none', got {mode!r}")
        if not 0 < float(beta) <= 1:
            raise SensingError(f"sensing link {name!r}: beta must be in (0, 1], got {beta!r}")
        self.mode, self.beta, self.name = mode, float(beta), name
        self.background: np.ndarray | None = None

    def set_reference(self, h_ref: np.ndarray) -> None:
        """Fix the empty-room channel ``[Ks, Ns, Nr]`` (mode ``"reference"``)."""
        self.background = np.asarray(h_ref, dtype=np.complex128)

    def __call__(self, h: np.ndarray) -> np.ndarray:
        """Subtract the background from ``h [Ks, Ns, Nr]`` (then update it)."""
        h = np.asarray(h, dtype=np.complex128)
        if self.mode == "none":
            return h
        if self.background is None:
            if self.mode == "reference":
                raise SensingError(f"sensing link {self.name!r}: background mode "
                                   "'reference' needs set_reference() first")
            self.background = h.copy()
            return h - self.background
        if self.background.shape != h.shape:
            raise SensingError(f"sensing link {self.name!r}: background shape "
                               f"{list(self.background.shape)} != frame {list(h.shape)}")
        out = h - self.background
        if self.mode == "ema":
            self.background = (1 - self.beta) * self.background + self.beta * h
        return out
