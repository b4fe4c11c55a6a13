"""Geolocation of radar detections: bistatic range ellipse x angle of arrival."""

from __future__ import annotations

import numpy as np
import scipy.optimize

from ..phy.arrays import r_hat

__all__ = ["locate"]


def locate(path_length_m: float, azimuth_rad: float, zenith_rad: float, tx, rx,
           height_m: float | None = None) -> np.ndarray | None:
    """Target position ``[3]`` [m] from a bistatic range sum and the arrival
    direction at the receiver; None if inconsistent.

    With ``height_m`` (targets on a known plane, e.g. robots on the floor)
    only the azimuth is used: the point ``P = rx + rho [cos az, sin az, 0]``
    at ``z = height_m`` with ``|P - tx| + |P - rx| = d`` (1-D root in
    ``rho``). Without it, the full direction ``u``:
    ``r = (d^2 - |b|^2) / (2 (d + u . b))`` with ``b = rx - tx``,
    ``P = rx + r u`` (monostatic: ``r = d / 2``).
    """
    tx, rx = np.asarray(tx, float), np.asarray(rx, float)
    d = float(path_length_m)
    if not np.isfinite(d) or not np.isfinite(azimuth_rad):
        return None
    base = float(np.linalg.norm(rx - tx))
    if d <= base:
        return None
    if height_m is None:
        u = r_hat(zenith_rad, azimuth_rad)
        b = rx - tx
        r = (d * d - base * base) / (2.0 * (d + u @ b))
        return rx + r * u if r > 0 else None
    dz = float(height_m) - rx[2]
    c = np.array([np.cos(azimuth_rad), np.sin(azimuth_rad)])

    def f(rho):
        p = np.array([rx[0] + rho * c[0], rx[1] + rho * c[1], height_m])
        return np.hypot(rho, dz) + np.linalg.norm(p - tx) - d

    hi = d
    # Along the plane the range sum first falls then rises: up to two roots
    # (in and out of the ellipsoid). Keep the one whose elevation seen from
    # the receiver matches the measured zenith best.
    lo_rho = scipy.optimize.minimize_scalar(f, bounds=(0.0, hi), method="bounded").x
    if f(lo_rho) > 0 or f(hi) < 0:
        return None
    roots = [scipy.optimize.brentq(f, lo_rho, hi, xtol=1e-6)]
    if f(0.0) > 0:
        roots.append(scipy.optimize.brentq(f, 0.0, lo_rho, xtol=1e-6))
    if len(roots) > 1 and np.isfinite(zenith_rad):
        ze = [np.arctan2(r, dz) for r in roots]  # zenith of (rho, dz) seen from rx
        rho = roots[int(np.argmin([abs(z - zenith_rad) for z in ze]))]
    else:
        rho = roots[0]
    return np.array([rx[0] + rho * c[0], rx[1] + rho * c[1], float(height_m)])
