"""ISAC trade-off: a share ``rho`` of the REs carries sensing symbols, the rest data.

For a transmitter whose REs are split into a sensing comb
(:func:`~isac_twin.sensing.link.sensing_resource_set`) and data (the
complement), :func:`data_rate` gives the achievable rate of a
communication link on the data REs (``isac_twin.phy.AchievableRate``, MRT
beamforming, the per-RE power ``P / (K N)`` of the whole grid, so sensing
and data share one power spectral density) and :func:`sensing_rmse`
the position error of the radar on the sensing REs.
"""

from __future__ import annotations

import numpy as np

from ..phy.arrays import PlanarArray
from ..phy.channel import OFDMChannel, baseband_gains
from ..phy.link import AchievableRate, MRTPrecoder
from ..phy.ofdm import ResourceGrid
from ..phy.units import dbm_to_watt, thermal_noise_power
from ..raytrace.base import LinkPaths
from ..utils.geometry import sionna_orientation
from .link import sensing_resource_set

__all__ = ["data_rate", "comm_channel"]


def comm_channel(paths: LinkPaths, grid: ResourceGrid, rx_array: PlanarArray,
                 tx_array: PlanarArray) -> np.ndarray:
    """Eq.-4 channel ``[K, N, Nr, Nt]`` of a communication link."""
    ch = OFDMChannel(grid, rx_array, tx_array)
    b = baseband_gains(paths.a, paths.tau, paths.frequency_hz)
    return ch(b, paths.tau, paths.doppler, paths.theta_r, paths.phi_r, paths.theta_t,
              paths.phi_t, rx_orientation=sionna_orientation(paths.rx_orientation),
              tx_orientation=sionna_orientation(paths.tx_orientation))


def data_rate(h: np.ndarray, grid: ResourceGrid, rho: float, power_dbm: float,
              noise_figure_db: float = 7.0, name: str = "isac") -> float:
    """Achievable rate [bit/s] on the data REs (all REs but the sensing comb).

    Args:
        h: communication channel ``[K, N, Nr, Nt]``.
        grid: the grid.
        rho: sensing share (0 -> all REs carry data).
        power_dbm: transmit power over the whole grid [dBm].
        noise_figure_db: receiver noise figure [dB].
    """
    data = np.ones(grid.shape, dtype=bool)
    if rho > 0:
        data &= ~sensing_resource_set(grid, rho, name=name).mask
    p_re = dbm_to_watt(power_dbm) / (grid.num_symbols * grid.num_subcarriers)
    n0 = thermal_noise_power(grid.subcarrier_spacing_hz, noise_figure_db=noise_figure_db)
    w = MRTPrecoder()(h)
    p = np.where(data, p_re, 0.0)[..., None]
    return AchievableRate(grid, n0)(h, w, p, data).rate_bps
