"""Antenna element patterns of ``twin.toml`` (``iso``, ``dipole``, ``hw_dipole``,
``tr38901``) applied to traced paths, as Sionna RT applies them.

The tracer traces every device with one isotropic, vertically polarized
element at its array centre (``LinkPaths.a``). A V-polarized element with
pattern ``g`` radiates the iso V field scaled by the real amplitude
``g(theta', phi')`` evaluated in the array's local frame (Sionna's
``v_*_pattern`` functions return ``C_theta = g``, ``C_phi = 0``; both TR 38.901
polarization models give slant angle 0 -> no phi component). The local ->
world polarization rotation is linear, so for any orientation

    a_pattern = g_tx(R_tx^T k_t) * g_rx(R_rx^T k_r) * a_iso

exactly, where ``k_t`` is the departure and ``k_r`` the arrival direction
(``r_hat(theta, phi)``). Patterns are evaluated at the array centre, like
Sionna's synthetic arrays (``tests/engine/phy/test_patterns.py`` checks the
eq.-4 channel against Sionna's ``Paths.cfr`` traced with the same arrays).

H, VH and cross polarization need the path's full 2 x 2 polarimetric transfer
matrix, which the V-only trace does not carry: ``engine.config`` refuses them
at load (:data:`MODELLED_POLARIZATIONS`).

Formulas (Sionna RT 2.2 ``antenna_pattern.py``):

* ``iso``: ``g = 1``
* ``dipole`` (short dipole): ``g = sqrt(1.5) |sin theta|``
* ``hw_dipole``: ``g = sqrt(1.643) |cos(pi/2 cos theta) / sin theta|`` (0 at the poles)
* ``tr38901`` (3GPP TR 38.901 Table 7.3-1): ``A_v = -min(12 ((theta - pi/2) /
  65 deg)^2, 30)``, ``A_h = -min(12 (phi / 65 deg)^2, 30)``,
  ``A = -min(-(A_v + A_h), 30) + 8`` dBi, ``g = sqrt(10^(A/10))``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np

from engine.config import MODELLED_POLARIZATIONS
from engine.phy.arrays import r_hat, rotation_matrix
from engine.raytrace.base import sionna_orientation

__all__ = ["PATTERNS", "MODELLED_POLARIZATIONS", "field_pattern", "pattern_gains",
           "AntennaPatterns"]



def _iso(theta, phi):
    return np.ones_like(theta)


def _dipole(theta, phi):
    return np.sqrt(1.5) * np.abs(np.sin(theta))


def _hw_dipole(theta, phi):
    s = np.sin(theta)
    small = np.isclose(s, 0.0, atol=1e-5)
    inv = np.where(small, 0.0, 1.0 / np.where(small, 1.0, s))
    return np.abs(np.sqrt(1.643) * np.cos(np.pi / 2 * np.cos(theta)) * inv)


def _tr38901(theta, phi):
    phi = np.mod(phi + np.pi, 2 * np.pi) - np.pi
    t3 = np.deg2rad(65.0)
    a_v = -np.minimum(12.0 * ((theta - np.pi / 2) / t3) ** 2, 30.0)
    a_h = -np.minimum(12.0 * (phi / t3) ** 2, 30.0)
    a_db = -np.minimum(-(a_v + a_h), 30.0) + 8.0
    return np.sqrt(10.0 ** (a_db / 10.0))


#: pattern name -> ``g(theta_local [L], phi_local [L]) -> [L]`` field amplitude.
PATTERNS: dict[str, Callable[[np.ndarray, np.ndarray], np.ndarray]] = {
    "iso": _iso, "dipole": _dipole, "hw_dipole": _hw_dipole, "tr38901": _tr38901}


def field_pattern(name: str) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """The V-polarized field amplitude of pattern ``name`` (a :data:`PATTERNS` key)."""
    if name not in PATTERNS:
        raise ValueError(f"pattern: expected one of {', '.join(PATTERNS)}, got {name!r}")
    return PATTERNS[name]


def pattern_gains(name: str, theta, phi, orientation) -> np.ndarray:
    """Field amplitude ``[L]`` of pattern ``name`` towards world directions
    ``(theta [L], phi [L])`` [rad] of an array with ``orientation = [yaw, pitch,
    roll]`` [rad] (Sionna order)."""
    k = r_hat(theta, phi).reshape(-1, 3)
    k_loc = k @ rotation_matrix(orientation)  # R^T k, row-vector form
    th = np.arctan2(np.hypot(k_loc[:, 0], k_loc[:, 1]), k_loc[:, 2])
    ph = np.arctan2(k_loc[:, 1], k_loc[:, 0])
    return field_pattern(name)(th, ph)


class AntennaPatterns:
    """Callable: iso-traced ``{(tx, rx): LinkPaths}`` -> the same links with each
    device's element pattern in ``a`` (see the module doc).

    Links whose two ends are ``iso`` are returned unchanged (the same object).
    A patterned link keeps the isotropic coefficients in ``extra["a_iso"]`` and
    the applied factor ``g_tx g_rx`` in ``extra["pattern_gain"]`` (``[L]``).

    Args:
        patterns: device name -> pattern name (e.g. from a config: :meth:`from_config`).
    """

    def __init__(self, patterns: dict[str, str]) -> None:
        for name, p in patterns.items():
            field_pattern(p)
        self.patterns = dict(patterns)

    @classmethod
    def from_config(cls, config) -> AntennaPatterns:
        """Patterns of every device of a :class:`~engine.config.TwinConfig`."""
        return cls({d.name: d.array.pattern for d in config.devices})

    @property
    def active(self) -> bool:
        """Whether any device has a non-isotropic pattern."""
        return any(p != "iso" for p in self.patterns.values())

    def apply(self, lp):
        """One :class:`~engine.raytrace.base.LinkPaths` with its patterns applied
        (unchanged when already applied, i.e. ``extra`` has ``pattern_gain``)."""
        if "pattern_gain" in lp.extra:
            return lp
        pt = self.patterns.get(lp.tx, "iso")
        pr = self.patterns.get(lp.rx, "iso")
        if pt == "iso" and pr == "iso":
            return lp
        g = (pattern_gains(pt, lp.theta_t, lp.phi_t, sionna_orientation(lp.tx_orientation))
             * pattern_gains(pr, lp.theta_r, lp.phi_r, sionna_orientation(lp.rx_orientation)))
        extra = dict(lp.extra, a_iso=lp.a, pattern_gain=g)
        return dataclasses.replace(lp, a=np.asarray(lp.a) * g, extra=extra)

    def __call__(self, link_paths: dict) -> dict:
        if not self.active:
            return link_paths
        return {k: self.apply(v) for k, v in link_paths.items()}
