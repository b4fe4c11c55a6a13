"""MIMO-OFDM physical layer of the twin (paper, section III-A, eqs. 1-4).

Pure numpy/scipy: nothing here imports Sionna or Mitsuba. Modules, one
concept each: :mod:`~isac_twin.phy.ofdm` (grid, resource sets),
:mod:`~isac_twin.phy.arrays` (planar arrays, steering vectors),
:mod:`~isac_twin.phy.channel` (eq. 4), :mod:`~isac_twin.phy.link` (eqs. 1-2,
precoding, power allocation, rates), :mod:`~isac_twin.phy.estimation`
(pilots, LS estimation, multipath delay profiles),
:mod:`~isac_twin.phy.directions` (joint delay-direction estimation at an AP),
:mod:`~isac_twin.phy.network` (:class:`NetworkPHY`: every link of a step, with
interference -- the twin's stage 3), :mod:`~isac_twin.phy.units` (dBm/W, kTB).

Array axes used throughout: ``K`` OFDM symbols, ``N`` subcarriers,
``Nr``/``Nt`` receive/transmit antennas, ``S`` streams, ``L`` paths;
a channel is ``[K, N, Nr, Nt]``.
"""

from .arrays import PlanarArray
from .channel import OFDMChannel, baseband_gains, cfr_at, cfr_from_antenna_gains
from .directions import DelayDirectionEstimator, DelayDirectionProfile
from .estimation import (
                                   LSChannelEstimator,
                                   MdpEstimator,
                                   MultipathDelayProfile,
                                   PilotPattern,
                                   ideal_mdp,
)
from .link import (
                                   AchievableRate,
                                   EqualPower,
                                   Interferer,
                                   LinkRate,
                                   MRTPrecoder,
                                   SVDPrecoder,
                                   WaterFilling,
                                   receive,
                                   transmit,
                                   water_filling,
                                   water_level,
                                   wideband_streams,
)
from .network import LinkSignal, NetworkPHY
from .ofdm import ResourceGrid, ResourceSet
from .units import dbm_to_watt, thermal_noise_power, watt_to_dbm

__all__ = [
    "ResourceGrid", "ResourceSet",
    "PlanarArray",
    "OFDMChannel", "baseband_gains", "cfr_at", "cfr_from_antenna_gains",
    "MRTPrecoder", "SVDPrecoder", "EqualPower", "WaterFilling",
    "water_filling", "water_level", "wideband_streams",
    "NetworkPHY", "LinkSignal",
    "transmit", "receive", "Interferer", "LinkRate", "AchievableRate",
    "PilotPattern", "LSChannelEstimator", "MultipathDelayProfile",
    "ideal_mdp", "MdpEstimator", "DelayDirectionEstimator", "DelayDirectionProfile",
    "dbm_to_watt", "watt_to_dbm", "thermal_noise_power",
]
