"""Antenna elements of ``twin.toml`` (patterns ``iso``, ``dipole``,
``hw_dipole``, ``tr38901``; polarizations ``V``, ``H``, ``VH``, ``cross``)
applied to traced paths, as Sionna RT applies them.

The tracer records per path the 2 x 2 field transfer matrix ``T``
(``LinkPaths.pol``, world spherical bases; :mod:`isac_twin.raytrace.polarization`)
and ``a``, the coefficient of isotropic V elements in the devices'
orientations. An element of pattern ``g`` and polarization slant ``zeta``
radiates, in its local frame, ``(C_theta, C_phi) = g(theta', phi') (cos zeta,
sin zeta)`` (Sionna's default polarization model ``tr38901_2``; V: ``zeta = 0``,
H: ``pi/2``, VH: two ports ``0, pi/2``, cross: two ports ``-pi/4, +pi/4``),
evaluated at the direction in the array's frame ``R^T k``. Every port pair
``(m, n)`` of a link then has the coefficient (paper eq. 4's ``a_l`` per port)

    a_mn = (Q_r c_r,m)^T T (Q_t c_t,n)

with ``Q`` the local -> world rotation of the spherical basis
(:func:`~isac_twin.raytrace.polarization.local_to_world`). For V at both ends
this reduces to ``g_tx g_rx a`` (``T`` not needed, so V links also work with
backends that carry no ``pol``, e.g. grids). Patterns are evaluated at the
array centre, like Sionna's synthetic arrays; a dual-polarized array has two
ports per element, port ``p * rows * cols + e`` (Sionna's order: all elements
of the first polarization, then the second). ``tests/engine/raytrace/test_antenna_patterns.py``
checks the eq.-4 channel against Sionna's ``Paths.cfr`` traced with the same
arrays.

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

from ..contract import schema as shared
from ..phy.arrays import r_hat, sionna_rotation
from ..scene.config import MODELLED_POLARIZATIONS
from ..utils.geometry import sionna_orientation, wrap_angle
from .polarization import local_to_world

__all__ = ["PATTERNS", "MODELLED_POLARIZATIONS", "SLANTS", "AntennaPatterns", "apply_elements",
           "element_fields", "field_pattern", "num_ports", "pattern_gains", "port_coefficients"]

#: polarization -> slant angles of its ports [rad] (``addon/contract/schema.py``, Sionna's
#: ``polarization_registry``).
SLANTS: dict[str, tuple[float, ...]] = {
    k: tuple(float(np.deg2rad(z)) for z in v) for k, v in shared.POLARIZATION_SLANTS_DEG.items()}



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
    phi = wrap_angle(phi)
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
    k_loc = k @ sionna_rotation(orientation)  # R^T k, row-vector form
    th = np.arctan2(np.hypot(k_loc[:, 0], k_loc[:, 1]), k_loc[:, 2])
    ph = np.arctan2(k_loc[:, 1], k_loc[:, 0])
    return field_pattern(name)(th, ph)


def num_ports(polarization: str) -> int:
    """Ports per element of ``polarization`` (1 or 2)."""
    if polarization not in SLANTS:
        raise ValueError(f"polarization: expected one of {', '.join(SLANTS)}, "
                         f"got {polarization!r}")
    return len(SLANTS[polarization])


def element_fields(name: str, polarization: str, theta, phi) -> np.ndarray:
    """Local field patterns ``(C_theta, C_phi)`` ``[L, P, 2]`` (real) of the ``P``
    ports of an element of pattern ``name`` and ``polarization`` at local angles
    ``theta, phi [L]`` rad (polarization model ``tr38901_2``)."""
    num_ports(polarization)
    g = field_pattern(name)(np.asarray(theta, float), np.asarray(phi, float))
    z = np.asarray(SLANTS[polarization])
    # exact zeros for V/H (cos(pi/2) is 6e-17 in float64)
    c = np.round(np.stack([np.cos(z), np.sin(z)], -1), 15)
    return g[:, None, None] * c[None]


def _world_fields(name, polarization, theta, phi, orientation) -> np.ndarray:
    """Port fields ``[L, P, 2]`` in the world spherical basis at world
    directions ``(theta, phi) [L]`` of an array with Sionna ``orientation``."""
    th, ph, q = local_to_world(r_hat(theta, phi).reshape(-1, 3), sionna_rotation(orientation))
    return np.einsum("lij,lpj->lpi", q, element_fields(name, polarization, th, ph))


def port_coefficients(lp, tx: tuple[str, str], rx: tuple[str, str]) -> np.ndarray:
    """Path coefficients ``[L, Pr, Pt]`` of every receive/transmit port pair of
    link ``lp`` (a :class:`~isac_twin.raytrace.base.LinkPaths`) for elements
    ``tx = (pattern, polarization)`` and ``rx`` likewise (see the module doc).

    Raises:
        ValueError: an H, VH or cross end on a link without ``pol``.
    """
    if tx[1] == "V" and rx[1] == "V":
        g = (pattern_gains(tx[0], lp.theta_t, lp.phi_t, sionna_orientation(lp.tx_orientation))
             * pattern_gains(rx[0], lp.theta_r, lp.phi_r, sionna_orientation(lp.rx_orientation)))
        return (np.asarray(lp.a) * g)[:, None, None]
    if lp.pol is None:
        raise ValueError(f"link {lp.tx}->{lp.rx}: polarization {tx[1]!r}/{rx[1]!r} needs the "
                         "paths' transfer matrices, which this tracer backend does not "
                         "provide (a path grid carries V only: use tracer.backend = \"sionna\")")
    if lp.num_paths == 0:
        return np.zeros((0, num_ports(rx[1]), num_ports(tx[1])), complex)
    ft = _world_fields(*tx, lp.theta_t, lp.phi_t, sionna_orientation(lp.tx_orientation))
    fr = _world_fields(*rx, lp.theta_r, lp.phi_r, sionna_orientation(lp.rx_orientation))
    return np.einsum("lri,lij,ltj->lrt", fr, lp.pol, ft)


class AntennaPatterns:
    """Callable: traced ``{(tx, rx): LinkPaths}`` (iso V coefficients in ``a``,
    transfer matrices in ``pol``) -> the same links with each device's elements
    applied (see the module doc).

    Links whose two ends are iso V are returned unchanged (the same object).
    Otherwise ``a`` becomes the coefficient of the first port pair ``[L]``,
    ``extra["a_ports"]`` holds every port pair ``[L, Pr, Pt]`` (what the eq.-4
    channel uses), ``extra["a_iso"]`` the iso V coefficients.

    Args:
        patterns: device name -> pattern name (e.g. from a config: :meth:`from_config`).
        polarizations: device name -> polarization (default ``"V"``).
    """

    def __init__(self, patterns: dict[str, str],
                 polarizations: dict[str, str] | None = None) -> None:
        for name, p in patterns.items():
            field_pattern(p)
        self.patterns = dict(patterns)
        self.polarizations = dict(polarizations or {})
        for pol in self.polarizations.values():
            num_ports(pol)

    @classmethod
    def from_config(cls, config) -> AntennaPatterns:
        """Elements of every device of a :class:`~isac_twin.scene.config.TwinConfig`."""
        return cls({d.name: d.array.pattern for d in config.devices},
                   {d.name: d.array.polarization for d in config.devices})

    def element(self, name: str) -> tuple[str, str]:
        """``(pattern, polarization)`` of device ``name`` (default iso V)."""
        return self.patterns.get(name, "iso"), self.polarizations.get(name, "V")

    @property
    def active(self) -> bool:
        """Whether any device has a non-isotropic pattern or is not V."""
        return (any(p != "iso" for p in self.patterns.values())
                or any(p != "V" for p in self.polarizations.values()))

    def apply(self, lp):
        """One :class:`~isac_twin.raytrace.base.LinkPaths` with its elements applied
        (unchanged when already applied, i.e. ``extra`` has ``a_ports``)."""
        if "a_ports" in lp.extra:
            return lp
        et, er = self.element(lp.tx), self.element(lp.rx)
        if et == ("iso", "V") and er == ("iso", "V"):
            return lp
        ports = port_coefficients(lp, et, er)
        extra = dict(lp.extra, a_iso=lp.a, a_ports=ports)
        return dataclasses.replace(lp, a=ports[:, 0, 0].copy(), extra=extra)

    def __call__(self, link_paths: dict) -> dict:
        if not self.active:
            return link_paths
        return {k: self.apply(v) for k, v in link_paths.items()}


#: :class:`AntennaPatterns` of the configs seen (by identity; a config is immutable).
_BY_CONFIG: dict[int, tuple[object, AntennaPatterns]] = {}


def apply_elements(config, link_paths: dict) -> dict:
    """Traced ``{(tx, rx): LinkPaths}`` with the element patterns and polarizations of
    ``config``'s devices applied: the one place they are applied. Every tracer backend
    returns its links through this (``SionnaTracer``, ``GridTracer``), as Sionna's
    ``Paths.a`` includes the arrays' antenna patterns; the PHY takes the result as is.

    Args:
        config: the :class:`~isac_twin.scene.config.TwinConfig` naming the devices.
        link_paths: iso-V traced links (already applied links pass unchanged).
    """
    hit = _BY_CONFIG.get(id(config))
    if hit is None or hit[0] is not config:
        if len(_BY_CONFIG) > 64:
            _BY_CONFIG.clear()
        hit = (config, AntennaPatterns.from_config(config))
        _BY_CONFIG[id(config)] = hit
    return hit[1](link_paths)

