"""Sensing links: which REs carry sensing symbols, the echo channel, y = H x + z.

A sensing link ``tx -> rx`` (bistatic) or ``tx -> tx`` (monostatic,
full-duplex) transmits known unit-modulus (QPSK) sensing symbols on a share
``rho`` of the step's resource elements -- a uniform comb over subcarriers
(every ``round(1/rho)``-th subcarrier, all symbols), the rest carries data.
The transmitter radiates from one element (port 0 of its array, i.e. an
omnidirectional sensing beam); the receiver samples all its elements.

Power: the transmitter's ``P`` is spread uniformly over all ``K N`` REs of
the grid (same power spectral density for sensing and data), so one RE
carries ``P / (K N)`` [W]; noise per RE and antenna is ``k_B T delta_f F``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import SensingError
from ..phy.arrays import PlanarArray
from ..phy.channel import OFDMChannel, baseband_gains
from ..phy.ofdm import ResourceGrid, ResourceSet
from ..phy.units import dbm_to_watt, thermal_noise_power
from ..raytrace.base import LinkPaths
from ..utils.geometry import sionna_orientation

__all__ = ["SensingLinkSpec", "sensing_resource_set", "echo_channel", "SensingReceiver"]


def sensing_resource_set(grid: ResourceGrid, rho: float = 1.0, *, name: str = "sensing",
                         subcarriers=None, symbols=None) -> ResourceSet:
    """Sensing REs: explicit ``subcarriers``/``symbols`` (see ``ResourceSet``),
    else a comb of every ``round(1/rho)``-th subcarrier over all symbols.

    Raises:
        SensingError: ``rho`` not in (0, 1] or REs outside the grid (names the link).
    """
    try:
        if subcarriers is None:
            if not (0 < float(rho) <= 1):
                raise SensingError(f"sensing link {name!r}: sensing share rho must be in "
                                   f"(0, 1], got {rho!r}")
            step = max(1, int(round(1.0 / float(rho))))
            subcarriers = range(0, grid.num_subcarriers, step)
        return ResourceSet(grid, subcarriers, symbols, name=name)
    except SensingError:
        raise
    except ValueError as exc:
        raise SensingError(f"sensing link {name!r}: sensing resources: {exc}") from exc


@dataclass
class SensingLinkSpec:
    """One sensing link.

    Attributes:
        tx: transmitting device; rx: receiving device (== tx: monostatic).
        rx_array: receive array (angles need >= 2 elements).
        rx_orientation: receive array ``[roll, pitch, yaw]`` [rad] (twin.toml order).
        power_dbm: transmit power over the whole grid [dBm].
        rho: sensing share of the REs (comb), unless ``subcarriers`` is given.
        subcarriers, symbols: explicit sensing REs (``ResourceSet`` specs).
        noise_figure_db: receiver noise figure [dB].
        estimate_angles: estimate the angle of arrival.
        target_height_m: geolocate on the plane ``z = target_height_m``
            (robots drive on the floor; None: use the full 3-D direction).
        every: sense every this many twin steps (1: every step).
        range_method: :class:`~isac_twin.sensing.radar.OFDMRadar` range method
            (``radar_kw`` of the estimator overrides it).
    """

    tx: str
    rx: str
    rx_array: PlanarArray = field(default_factory=lambda: PlanarArray(1, 1))
    rx_orientation: tuple = (0.0, 0.0, 0.0)
    power_dbm: float = 20.0
    rho: float = 1.0
    subcarriers: object = None
    symbols: object = None
    noise_figure_db: float = 7.0
    estimate_angles: bool = True
    target_height_m: float | None = 0.096
    every: int = 1
    range_method: str = "nls"

    @property
    def name(self) -> str:
        """``"tx->rx"``."""
        return f"{self.tx}->{self.rx}"

    @property
    def monostatic(self) -> bool:
        return self.tx == self.rx


def echo_channel(paths: LinkPaths, grid: ResourceGrid, rx_array: PlanarArray,
                 dtype=np.complex64) -> np.ndarray:
    """Eq.-4 channel ``[K, N, Nr]`` of ``paths`` from transmit port 0 (one
    isotropic element at the tx array centre) to every receive element."""
    ch = OFDMChannel(grid, rx_array, PlanarArray(1, 1), dtype=dtype)
    if paths.num_paths == 0:
        return np.zeros(grid.shape + (rx_array.num_ant,), dtype=dtype)
    b = baseband_gains(paths.a, paths.tau, paths.frequency_hz)
    h = ch(b, paths.tau, paths.doppler, paths.theta_r, paths.phi_r, paths.theta_t,
           paths.phi_t, rx_orientation=sionna_orientation(paths.rx_orientation))
    return h[..., 0]


class SensingReceiver:
    """Known sensing symbols and the received samples ``y = H x + z`` of one link.

    Args:
        spec: the :class:`SensingLinkSpec`.
        grid: the step's OFDM grid.
        seed: seed of the sensing symbols and the noise.
    """

    def __init__(self, spec: SensingLinkSpec, grid: ResourceGrid, seed: int = 0) -> None:
        self.spec = spec
        self.grid = grid
        self.resource_set = sensing_resource_set(grid, spec.rho, name=spec.name,
                                                 subcarriers=spec.subcarriers,
                                                 symbols=spec.symbols)
        self.rng = np.random.default_rng(seed)
        rs = self.resource_set
        self.re_power_w = dbm_to_watt(spec.power_dbm) / (grid.num_symbols * grid.num_subcarriers)
        self.noise_w = thermal_noise_power(grid.subcarrier_spacing_hz,
                                           noise_figure_db=spec.noise_figure_db)
        q = self.rng.integers(0, 4, (rs.symbol_indices.size, rs.subcarrier_indices.size))
        self.symbols = np.sqrt(self.re_power_w) * np.exp(1j * (np.pi / 4 + np.pi / 2 * q))

    def receive(self, h: np.ndarray) -> np.ndarray:
        """``y [Ks, Ns, Nr]`` on the sensing REs from the full-grid channel
        ``h [K, N, Nr]`` (noise ``CN(0, noise_w)`` per RE and antenna)."""
        rs = self.resource_set
        hs = h[np.ix_(rs.symbol_indices, rs.subcarrier_indices)]
        z = np.sqrt(self.noise_w / 2) * (self.rng.standard_normal(hs.shape)
                                         + 1j * self.rng.standard_normal(hs.shape))
        return hs * self.symbols[..., None] + z
