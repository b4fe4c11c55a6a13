"""MIMO-OFDM physical layer of the twin (paper, section III-A, eqs. 1-4).

Pure numpy/scipy: nothing here imports Sionna or Mitsuba. Modules, one
concept each: :mod:`~engine.phy.ofdm` (grid, resource sets),
:mod:`~engine.phy.arrays` (planar arrays, steering vectors),
:mod:`~engine.phy.channel` (eq. 4), :mod:`~engine.phy.link` (eqs. 1-2,
precoding, power allocation, rates), :mod:`~engine.phy.estimation`
(pilots, LS estimation, multipath delay profiles),
:mod:`~engine.phy.directions` (joint delay-direction estimation at an AP),
:mod:`~engine.phy.network` (:class:`NetworkPHY`: every link of a step, with
interference -- the twin's stage 3), :mod:`~engine.phy.units` (dBm/W, kTB).

Array axes used throughout: ``K`` OFDM symbols, ``N`` subcarriers,
``Nr``/``Nt`` receive/transmit antennas, ``S`` streams, ``L`` paths;
a channel is ``[K, N, Nr, Nt]``.
"""

from engine.phy.arrays import PlanarArray
from engine.phy.channel import OFDMChannel, baseband_gains, cfr_at, cfr_from_antenna_gains
from engine.phy.directions import DelayDirectionEstimator, DelayDirectionProfile
from engine.phy.estimation import (LSChannelEstimator, MdpEstimator,
                                   MultipathDelayProfile, PilotPattern, ideal_mdp)
from engine.phy.link import (AchievableRate, EqualPower, Interferer, LinkRate,
                             MRTPrecoder, SVDPrecoder, WaterFilling, receive,
                             transmit, water_filling, water_level, wideband_streams)
from engine.phy.network import LinkSignal, NetworkPHY
from engine.phy.ofdm import ResourceGrid, ResourceSet
from engine.phy.units import dbm_to_watt, thermal_noise_power, watt_to_dbm

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
