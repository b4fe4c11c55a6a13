"""The MIMO-OFDM signals of a whole network graph in one step (paper, eqs. 1-4).

For every link ``q -> v`` of the configuration: the eq.-4 channel from the
traced paths with each device's own array, a precoder and a power
allocation that keep ``sum |x|^2 <= P_q`` over the transmitter's resource set
``R_q``, and the achievable rate with every *other* transmitter heard by
``v`` on shared resource elements treated as interference (eq. 2).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from engine.phy.arrays import PlanarArray
from engine.phy.channel import OFDMChannel, baseband_gains
from engine.phy.link import (AchievableRate, EqualPower, Interferer, SVDPrecoder,
                             WaterFilling, channel_gains)
from engine.phy.ofdm import ResourceGrid, ResourceSet
from engine.phy.units import dbm_to_watt, thermal_noise_power

__all__ = ["LinkSignal", "NetworkPHY"]


@dataclass(frozen=True)
class LinkSignal:
    """One link's PHY state in a step.

    Attributes:
        tx, rx: device names.
        h: channel ``[K, N, Nr, Nt]`` (complex64).
        w: precoder ``[K, N, Nt, S]``.
        p: power per RE and stream ``[K, N, S]``, W.
        mask: the transmitter's allocation ``[K, N]``.
        rate_bps: achievable rate, bit/s (interference treated as noise).
        snr_db: mean SNR over the allocation before precoding,
            ``P_q/|R_q| * ||H||_F^2 / (Nr sigma^2)``, dB.
        sinr_db: mean post-MMSE SINR over the allocation and streams, dB.
    """

    tx: str
    rx: str
    h: np.ndarray
    w: np.ndarray
    p: np.ndarray
    mask: np.ndarray
    rate_bps: float
    snr_db: float
    sinr_db: float


def _array(cfg) -> PlanarArray:
    if cfg.polarization != "V" or cfg.pattern != "iso":
        # The tracer works at array centres with iso V elements; other patterns and
        # dual polarization need per-element gains this PHY does not model yet.
        raise ValueError(f"array pattern {cfg.pattern!r}/polarization {cfg.polarization!r}: "
                         "the PHY models iso V elements only")
    return PlanarArray(cfg.rows, cfg.cols, cfg.vertical_spacing, cfg.horizontal_spacing)


class NetworkPHY:
    """Callable: traced paths of all links -> :class:`LinkSignal` per link.

    Args:
        config: :class:`~engine.config.TwinConfig`.
        power_allocation: ``"waterfilling"`` (default) or ``"equal"``.
        precoding: ``"svd"`` (per resource element) or ``"svd_wideband"``.
    """

    def __init__(self, config, *, power_allocation: str = "waterfilling",
                 precoding: str = "svd") -> None:
        if power_allocation not in ("waterfilling", "equal"):
            raise ValueError(f"power_allocation: expected 'waterfilling' or 'equal', "
                             f"got {power_allocation!r}")
        if precoding not in ("svd", "svd_wideband"):
            raise ValueError(f"precoding: expected 'svd' or 'svd_wideband', got {precoding!r}")
        o = config.ofdm
        self.config = config
        self.grid = ResourceGrid(o.num_subcarriers, o.subcarrier_spacing_hz, o.num_symbols,
                                 o.cyclic_prefix_samples)
        self.noise_power = thermal_noise_power(o.subcarrier_spacing_hz,
                                               config.noise.temperature_k,
                                               config.noise.noise_figure_db)
        self.power_allocation = power_allocation
        self.precoding = "per_re" if precoding == "svd" else "wideband"
        self.devices = {d.name: d for d in config.devices}
        self.arrays = {d.name: _array(d.array) for d in config.devices}
        self.masks = {d.name: ResourceSet(self.grid, d.subcarriers, d.symbols, name=d.name).mask
                      for d in config.devices if d.is_tx}
        self.rate = AchievableRate(self.grid, self.noise_power)

    def channel(self, paths) -> np.ndarray:
        """Eq. 4 for one :class:`~engine.raytrace.base.LinkPaths` -> ``[K, N, Nr, Nt]``."""
        from engine.raytrace.base import sionna_orientation

        syn = OFDMChannel(self.grid, self.arrays[paths.rx], self.arrays[paths.tx])
        b = baseband_gains(paths.a, paths.tau, paths.frequency_hz)
        return syn(b, paths.tau, paths.doppler, paths.theta_r, paths.phi_r, paths.theta_t,
                   paths.phi_t, rx_orientation=sionna_orientation(paths.rx_orientation),
                   tx_orientation=sionna_orientation(paths.tx_orientation))

    def __call__(self, link_paths: dict) -> dict[tuple[str, str], LinkSignal]:
        """Args: ``{(tx, rx): LinkPaths}``. Returns ``{(tx, rx): LinkSignal}``."""
        h = {lk: self.channel(lp) for lk, lp in link_paths.items()}
        tx_side = {}
        for (tx, rx), hl in h.items():
            mask = self.masks[tx]
            total = float(dbm_to_watt(self.devices[tx].power_dbm))
            s = min(hl.shape[2], hl.shape[3])
            w = SVDPrecoder(s, self.precoding)(hl, mask)
            if self.power_allocation == "waterfilling":
                p = WaterFilling(total, self.noise_power)(channel_gains(hl, w), mask)
            else:
                p = EqualPower(total)(mask, s)
            tx_side[(tx, rx)] = (w, p, mask, total)
        out = {}
        for (tx, rx), hl in h.items():
            w, p, mask, total = tx_side[(tx, rx)]
            # Every other transmitter with a traced channel to this receiver interferes
            # on the REs it shares (its own precoder, aimed at its own receiver).
            interferers = []
            for (tx2, rx2), (w2, p2, m2, _) in tx_side.items():
                if tx2 == tx or (tx2, rx) not in h or not (m2 & mask).any():
                    continue
                interferers.append(Interferer(h[(tx2, rx)], w2, p2, m2))
            r = self.rate(hl, w, p, mask, interferers)
            nr = hl.shape[2]
            per_re = total / mask.sum()
            gain = np.mean(np.sum(np.abs(hl[mask]) ** 2, axis=(1, 2))) / nr
            snr = per_re * gain / self.noise_power
            sinr = r.sinr[mask]
            sinr = sinr[np.isfinite(sinr) & (sinr > 0)]
            out[(tx, rx)] = LinkSignal(
                tx=tx, rx=rx, h=hl, w=w, p=p, mask=mask, rate_bps=r.rate_bps,
                snr_db=float(10 * np.log10(snr)) if snr > 0 else float("-inf"),
                sinr_db=float(10 * np.log10(sinr.mean())) if sinr.size else float("-inf"))
        return out
