"""Typed ``[[sensing]]`` tables -> :class:`SensingLinkSpec` list.

The tables are parsed and validated once, by :mod:`isac_twin.scene.config`, into
:class:`isac_twin.scene.config.SensingConfig` (``TwinConfig.sensing``); this module only
adds what the radar needs from the devices (the receive array and its
orientation). Keys of one table::

    [[sensing]]
    tx = "AP2"                 # transmitting device
    rx = "AP1"                 # receiving device (= tx: monostatic)
    rho = 0.25                 # sensing share of the REs (subcarrier comb); or:
    # subcarriers = [0, 1024]  # explicit half-open ranges (like devices)
    # symbols = [0, 14]
    power_dbm = 20.0           # default: the tx device's power_dbm
    noise_figure_db = 7.0      # default: [noise].noise_figure_db
    estimate_angles = true
    target_height_m = 0.096    # geolocate on this plane (false: full 3-D)
    every = 1                  # run the radar every this many twin steps
    range_method = "first_arrival"   # or "nls" (OFDMRadar)
"""

from __future__ import annotations

from ..phy.arrays import PlanarArray
from ..scene.config import SENSING_KEYS, SensingConfig, TwinConfig
from .link import SensingLinkSpec

__all__ = ["parse_sensing", "link_spec", "SENSING_KEYS"]


def link_spec(config: TwinConfig, s: SensingConfig) -> SensingLinkSpec:
    """The radar's :class:`SensingLinkSpec` of one typed ``[[sensing]]`` table."""
    rx = config.device(s.rx)
    a = rx.array
    return SensingLinkSpec(
        tx=s.tx, rx=s.rx,
        rx_array=PlanarArray(a.rows, a.cols, a.vertical_spacing, a.horizontal_spacing),
        rx_orientation=tuple(rx.orientation), power_dbm=s.power_dbm, rho=s.rho,
        subcarriers=s.subcarriers, symbols=s.symbols, noise_figure_db=s.noise_figure_db,
        estimate_angles=s.estimate_angles, target_height_m=s.target_height_m,
        every=s.every, range_method=s.range_method)


def parse_sensing(config: TwinConfig) -> list[SensingLinkSpec]:
    """The sensing links of a config (empty when there is no ``[[sensing]]``)."""
    return [link_spec(config, s) for s in config.sensing]
