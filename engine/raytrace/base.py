"""The tracer interface: per-link path records, device poses, the Tracer protocol.

Every ray-tracing backend (Sionna RT, a precomputed grid, an importer of
another tracer's output) turns a scene and the devices' poses into one
:class:`LinkPaths` per link. Everything downstream (the PHY's eq.-4 channel
synthesis, the live view, fingerprint databases) reads only this record.

Conventions (Sionna RT's, so that Sionna's own ``Paths.cfr`` is the reference):

* ``a`` is the *passband* complex path coefficient of single isotropic,
  vertically polarized elements at the two array centres (Sionna's
  ``Paths.a``); the baseband gain of eq. 4 is ``b = a * exp(-j 2 pi f_c tau)``
  (``isac_twin.phy.channel.baseband_gains``).
* ``pol`` (when the backend provides it) is the path's 2 x 2 complex field
  transfer matrix between the world spherical bases (theta-hat, phi-hat) at
  departure (columns) and arrival (rows), from which any element's
  coefficient follows (:mod:`isac_twin.raytrace.polarization`); ``a`` is the
  V-V coefficient of it in the devices' orientations.
* ``tau`` is the absolute propagation delay in s (not normalized).
* Zenith ``theta`` from +z in ``[0, pi]``, azimuth ``phi`` from +x towards +y in
  ``(-pi, pi]``; departure angles point away from the transmitter, arrival
  angles point from the receiver towards where the wave comes from.
* ``doppler`` in Hz, including the devices' velocities.
* Device orientation is ``[roll, pitch, yaw]`` rad as in ``twin.toml``; Sionna
  and ``isac_twin.phy.arrays`` take ``[yaw, pitch, roll]`` (use
  :func:`sionna_orientation`).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from ..scene.config import LinkConfig, TwinConfig
from ..utils.geometry import DevicePose, antenna_pose, sionna_orientation  # noqa: F401 (re-exported)

#: Speed of light in vacuum, m/s (Sionna's value).
SPEED_OF_LIGHT = 299_792_458.0

#: Sionna's ``InteractionType`` codes (``sionna.rt.constants``), repeated here so
#: that reading paths never needs Sionna.
INTERACTION_NONE = 0
INTERACTION_SPECULAR = 1
INTERACTION_DIFFUSE = 2
INTERACTION_REFRACTION = 4
INTERACTION_DIFFRACTION = 8

Link = tuple[str, str]  #: ``(tx name, rx name)``


@dataclass(frozen=True, eq=False)
class LinkPaths:
    """The propagation paths of one link (``L`` paths, up to ``D`` interactions each).

    Paths are sorted by delay (the LOS path, when present, comes first).

    Attributes:
        tx, rx: device names.
        tx_position, rx_position: array centres ``[3]``, m.
        tx_orientation, rx_orientation: ``[roll, pitch, yaw]`` ``[3]``, rad.
        frequency_hz: carrier frequency the paths were traced at, Hz.
        a: passband complex path coefficients ``[L]`` (linear amplitude), complex128.
        tau: delays ``[L]``, s, float64.
        doppler: Doppler shifts ``[L]``, Hz, float64.
        theta_t, phi_t: departure zenith / azimuth ``[L]``, rad.
        theta_r, phi_r: arrival zenith / azimuth ``[L]``, rad.
        vertices: interaction points ``[L, D, 3]``, m (0 where ``interactions`` is NONE).
        interactions: Sionna ``InteractionType`` codes ``[L, D]``, int32, NONE (0) padding.
        pol: transfer matrices ``[L, 2, 2]`` complex128 (rows: arrival
            theta/phi, columns: departure theta/phi, world bases), or None when
            the backend does not provide them (then only V elements can be
            modelled).
    """

    tx: str
    rx: str
    tx_position: np.ndarray
    rx_position: np.ndarray
    tx_orientation: np.ndarray
    rx_orientation: np.ndarray
    frequency_hz: float
    a: np.ndarray
    tau: np.ndarray
    doppler: np.ndarray
    theta_t: np.ndarray
    phi_t: np.ndarray
    theta_r: np.ndarray
    phi_r: np.ndarray
    vertices: np.ndarray
    interactions: np.ndarray
    pol: np.ndarray | None = field(default=None, repr=False)
    extra: dict = field(default_factory=dict, repr=False)

    @property
    def num_paths(self) -> int:
        """L."""
        return int(self.tau.shape[0])

    @property
    def depth(self) -> int:
        """D, the interaction slots per path."""
        return int(self.interactions.shape[1])

    @property
    def num_interactions(self) -> np.ndarray:
        """Interactions per path ``[L]`` (0 for LOS)."""
        return np.count_nonzero(self.interactions != INTERACTION_NONE, axis=1)

    @property
    def is_los(self) -> np.ndarray:
        """LOS flags ``[L]`` (no interaction)."""
        return self.num_interactions == 0

    @property
    def los_delay(self) -> float | None:
        """Delay of the LOS path, s, or None when blocked."""
        idx = np.flatnonzero(self.is_los)
        return float(self.tau[idx[0]]) if idx.size else None

    @property
    def power(self) -> np.ndarray:
        """Path powers ``|a|^2`` ``[L]`` (linear)."""
        return np.abs(self.a) ** 2

    @property
    def distance(self) -> float:
        """Straight-line distance between the array centres, m."""
        return float(np.linalg.norm(np.asarray(self.rx_position) - self.tx_position))

    def reversed(self) -> "LinkPaths":
        """The reciprocal link ``rx -> tx``: same delays and gains (reciprocity),
        swapped angles, vertices in reverse order, transposed ``pol``."""
        # Reverse the populated interaction slots of each path, keep NONE padding last.
        n = self.num_interactions
        idx = np.tile(np.arange(self.depth), (self.num_paths, 1))
        rev = np.where(idx < n[:, None], n[:, None] - 1 - idx, idx)
        return LinkPaths(
            tx=self.rx, rx=self.tx, tx_position=self.rx_position, rx_position=self.tx_position,
            tx_orientation=self.rx_orientation, rx_orientation=self.tx_orientation,
            frequency_hz=self.frequency_hz, a=self.a, tau=self.tau, doppler=self.doppler,
            theta_t=self.theta_r, phi_t=self.phi_r, theta_r=self.theta_t, phi_r=self.phi_t,
            vertices=np.take_along_axis(self.vertices, rev[:, :, None], axis=1),
            interactions=np.take_along_axis(self.interactions, rev, axis=1),
            pol=None if self.pol is None else np.swapaxes(self.pol, -1, -2),
            extra=dict(self.extra))

    def summary(self) -> dict:
        """JSON-friendly summary: path count, LOS delay (s), strongest path power (dB)."""
        p = self.power
        return {
            "tx": self.tx, "rx": self.rx, "num_paths": self.num_paths,
            "los": self.los_delay is not None, "los_delay_s": self.los_delay,
            "distance_m": self.distance,
            "strongest_path_gain_db": float(10 * np.log10(p.max())) if p.size else None,
            "total_gain_db": float(10 * np.log10(p.sum())) if p.size else None,
        }


@runtime_checkable
class Tracer(Protocol):
    """A ray-tracing backend.

    ``tracer(scene, poses, links=None)`` returns one :class:`LinkPaths` per link:
    the scene config's links when ``links`` is None, else the given
    ``(tx, rx)`` pairs (any two distinct devices; roles are not enforced so
    that reciprocity can be checked). ``poses`` maps every device named in the
    links to its :class:`DevicePose`. Invalid poses raise ``ValueError`` naming
    the device (see :func:`validate_poses`).
    """

    def __call__(self, scene, poses: Mapping[str, DevicePose],
                 links: Iterable[Link] | None = None) -> dict[Link, LinkPaths]: ...


# --------------------------------------------------------------------------- helpers


def device_poses(config: TwinConfig) -> dict[str, DevicePose]:
    """Initial array-centre poses of all devices from the config (velocity 0).

    Access points: ``position`` is the array centre. Robots: ``position`` is
    ``base_link`` and the array centre is :func:`isac_twin.utils.geometry.antenna_pose` of it.
    """
    out = {}
    for d in config.devices:
        if d.kind == "robot":
            out[d.name] = antenna_pose((*d.position, *d.orientation), d.antenna_offset)
        else:
            out[d.name] = DevicePose(position=tuple(d.position), orientation=tuple(d.orientation))
    return out


def resolve_links(config: TwinConfig, links: Iterable[Link] | None) -> list[Link]:
    """The requested links as ``(tx, rx)`` tuples (default: the config's links).

    Raises:
        ValueError: unknown device, a self-link, or no links at all.
    """
    if links is None:
        out = [(lk.tx, lk.rx) for lk in config.links]
    else:
        out = [(lk.tx, lk.rx) if isinstance(lk, LinkConfig) else (str(lk[0]), str(lk[1]))
               for lk in links]
    names = {d.name for d in config.devices}
    for tx, rx in out:
        for n in (tx, rx):
            if n not in names:
                raise ValueError(f"link {tx}->{rx}: unknown device {n!r} "
                                 f"(devices: {', '.join(sorted(names))})")
        if tx == rx:
            raise ValueError(f"link {tx}->{rx}: a link needs two distinct devices")
    if not out:
        raise ValueError(f"{config.path}: no links to trace (add [[links]] or pass links=)")
    return list(dict.fromkeys(out))


def validate_poses(scene, poses: Mapping[str, DevicePose], names: Iterable[str]) -> None:
    """Check the poses of ``names``: present, finite, and inside the scene.

    Raises:
        ValueError: naming the device and what is wrong.
    """
    for n in names:
        if n not in poses:
            raise ValueError(f"device {n!r}: no pose given (poses for: "
                             f"{', '.join(sorted(poses)) or 'none'})")
        p = poses[n]
        if not isinstance(p, DevicePose):
            raise ValueError(f"device {n!r}: expected a DevicePose, got {type(p).__name__}")
        for k in ("position", "orientation", "velocity"):
            v = np.asarray(getattr(p, k), float)
            if not np.all(np.isfinite(v)):
                raise ValueError(f"device {n!r}: {k} {list(v)} is not finite")
        if not scene.contains(p.position):
            lo, hi = scene.bounds_min, scene.bounds_max
            raise ValueError(
                f"device {n!r}: position {[round(x, 4) for x in p.position]} m lies outside "
                f"the scene (x {lo[0]:.2f}..{hi[0]:.2f}, y {lo[1]:.2f}..{hi[1]:.2f}, "
                f"z {lo[2]:.2f}..{hi[2]:.2f} m)")


def empty_link(tx: str, rx: str, tx_pose: DevicePose, rx_pose: DevicePose,
               frequency_hz: float, depth: int) -> LinkPaths:
    """A link without any path (blocked or out of range)."""
    z = np.zeros(0)
    return LinkPaths(tx=tx, rx=rx, tx_position=np.asarray(tx_pose.position),
                     rx_position=np.asarray(rx_pose.position),
                     tx_orientation=np.asarray(tx_pose.orientation),
                     rx_orientation=np.asarray(rx_pose.orientation),
                     frequency_hz=float(frequency_hz), a=z.astype(complex), tau=z, doppler=z,
                     theta_t=z, phi_t=z, theta_r=z, phi_r=z,
                     vertices=np.zeros((0, depth, 3)),
                     interactions=np.zeros((0, depth), np.int32),
                     pol=np.zeros((0, 2, 2), complex))
