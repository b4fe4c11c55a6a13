"""Physical constants and unit conversions (dBm <-> W, dB <-> linear, kTB)."""

from __future__ import annotations

import numpy as np

from ._checks import positive_float

__all__ = ["SPEED_OF_LIGHT", "BOLTZMANN", "dbm_to_watt", "watt_to_dbm",
           "db_to_linear", "linear_to_db", "thermal_noise_power"]

SPEED_OF_LIGHT: float = 299_792_458.0
"""Speed of light in vacuum [m/s] (same value as ``sionna.rt.constants``)."""

BOLTZMANN: float = 1.380649e-23
"""Boltzmann constant k_B [J/K]."""


def dbm_to_watt(p_dbm):
    """Power in dBm -> W. Accepts scalars or arrays (any shape)."""
    p = np.asarray(p_dbm, dtype=np.float64)
    if np.any(np.isnan(p)):
        raise ValueError("p_dbm contains NaN")
    out = 10.0 ** ((p - 30.0) / 10.0)
    return float(out) if out.ndim == 0 else out


def watt_to_dbm(p_watt):
    """Power in W -> dBm (0 W -> -inf). Negative or NaN power is an error."""
    p = np.asarray(p_watt, dtype=np.float64)
    if np.any(np.isnan(p)) or np.any(p < 0):
        raise ValueError("p_watt must be non-negative and not NaN")
    with np.errstate(divide="ignore"):
        out = 10.0 * np.log10(p) + 30.0
    return float(out) if out.ndim == 0 else out


def db_to_linear(x_db):
    """Power ratio in dB -> linear."""
    out = 10.0 ** (np.asarray(x_db, dtype=np.float64) / 10.0)
    return float(out) if out.ndim == 0 else out


def linear_to_db(x):
    """Power ratio linear -> dB (0 -> -inf)."""
    x = np.asarray(x, dtype=np.float64)
    if np.any(x < 0):
        raise ValueError("a power ratio must be non-negative")
    with np.errstate(divide="ignore"):
        out = 10.0 * np.log10(x)
    return float(out) if out.ndim == 0 else out


def thermal_noise_power(bandwidth_hz: float, temperature_k: float = 290.0,
                        noise_figure_db: float = 0.0) -> float:
    """Receiver noise power sigma^2 = k_B * T * B * 10^(NF/10) [W].

    Args:
        bandwidth_hz: Noise bandwidth B [Hz]; per subcarrier use the
            subcarrier spacing Delta f.
        temperature_k: Noise temperature T [K].
        noise_figure_db: Receiver noise figure NF [dB].

    Returns:
        Noise power [W] (per complex sample of a B-wide channel).
    """
    b = positive_float("bandwidth_hz", bandwidth_hz)
    t = positive_float("temperature_k", temperature_k)
    nf = float(noise_figure_db)
    if not np.isfinite(nf):
        raise ValueError(f"noise_figure_db must be finite, got {noise_figure_db!r}")
    return BOLTZMANN * t * b * 10.0 ** (nf / 10.0)
