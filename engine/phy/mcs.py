"""Link adaptation: the rate a modem reaches, through a modulation-and-coding table.

Beside the Shannon (log-det) rate, each stream of a link gets one MCS for the
whole allocation, as a real scheduler would pick it:

1. per RE ``r`` and stream ``s``, the post-MMSE SINR capped by the transmitter's
   EVM floor: ``1/sinr_eff = 1/sinr + 10^(EVM_dB / 10)`` (an EVM of -35 dB caps
   every stream at 35 dB);
2. the stream's effective SINR over its REs (those with power), the
   mutual-information (capacity) average
   ``sinr_s = 2^(mean_r log2(1 + sinr_eff[r, s])) - 1`` (weights: REs stood for);
3. the highest table entry whose SNR threshold is ``<= sinr_s``; the stream then
   carries ``efficiency`` bit on each of its REs (none below the lowest entry).

Tables (:data:`TABLES`):

* ``"he"``: IEEE 802.11ax HE MCS 0-11 (BPSK 1/2 ... 1024-QAM 5/6; efficiency =
  bits per subcarrier symbol x code rate). SNR thresholds from the minimum
  receiver sensitivities of IEEE Std 802.11ax-2021 Table 27-51 (20 MHz:
  -82, -79, -77, -74, -70, -66, -65, -64, -59, -57, -54, -52 dBm), converted with
  the standard's own assumptions (noise figure 10 dB, implementation margin
  5 dB): ``SNR_min = S + 174 - 10 log10(20e6) - 15`` dB (MCS 0: 4.0 dB ...
  MCS 11: 34.0 dB).
* ``"nr_cqi2"``: 5G NR CQI table 2 (3GPP TS 38.214 Table 5.2.2.1-3, CQI 1-15:
  QPSK 78/1024 ... 256-QAM 948/1024; efficiency as tabulated there). 3GPP
  publishes no SNR thresholds for CQIs; they come from the attenuated Shannon
  bound of 3GPP TR 36.942 Annex A.2 (downlink ``alpha = 0.6``):
  ``SNR_min = 2^(efficiency / 0.6) - 1``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["McsTable", "TABLES", "McsRate"]


@dataclass(frozen=True)
class McsTable:
    """One MCS table.

    Attributes:
        name: table key (``twin.toml`` ``[link_adaptation] table``).
        labels: ``[M]`` entry names (e.g. ``"MCS7 64QAM 5/6"``).
        efficiency: ``[M]`` bit per RE and stream, increasing.
        snr_db: ``[M]`` minimum SINR of each entry, dB, increasing.
    """

    name: str
    labels: tuple[str, ...]
    efficiency: np.ndarray
    snr_db: np.ndarray

    def select(self, sinr_db: np.ndarray) -> np.ndarray:
        """Index of the highest entry with ``snr_db <= sinr_db`` (-1: none). Shape as input."""
        return np.searchsorted(self.snr_db, np.asarray(sinr_db, float), side="right") - 1


def _he() -> McsTable:
    mods = [("BPSK", 1, 1 / 2), ("QPSK", 2, 1 / 2), ("QPSK", 2, 3 / 4), ("16QAM", 4, 1 / 2),
            ("16QAM", 4, 3 / 4), ("64QAM", 6, 2 / 3), ("64QAM", 6, 3 / 4), ("64QAM", 6, 5 / 6),
            ("256QAM", 8, 3 / 4), ("256QAM", 8, 5 / 6), ("1024QAM", 10, 3 / 4),
            ("1024QAM", 10, 5 / 6)]
    sens_dbm = np.array([-82, -79, -77, -74, -70, -66, -65, -64, -59, -57, -54, -52], float)
    snr = sens_dbm + 174.0 - 10 * np.log10(20e6) - 15.0
    codes = ("1/2", "1/2", "3/4", "1/2", "3/4", "2/3", "3/4", "5/6", "3/4", "5/6", "3/4", "5/6")
    labels = tuple(f"MCS{i} {m} {c}" for i, ((m, _, _), c) in enumerate(zip(mods, codes)))
    return McsTable("he", labels, np.array([b * r for _, b, r in mods]), snr)


def _nr_cqi2() -> McsTable:
    rows = [("QPSK", 2, 78), ("QPSK", 2, 193), ("QPSK", 2, 449), ("16QAM", 4, 378),
            ("16QAM", 4, 490), ("16QAM", 4, 616), ("64QAM", 6, 466), ("64QAM", 6, 567),
            ("64QAM", 6, 666), ("64QAM", 6, 772), ("64QAM", 6, 873), ("256QAM", 8, 711),
            ("256QAM", 8, 797), ("256QAM", 8, 885), ("256QAM", 8, 948)]
    eff = np.array([q * r / 1024 for _, q, r in rows])
    snr = 10 * np.log10(2 ** (eff / 0.6) - 1)
    labels = tuple(f"CQI{i + 1} {m} {r}/1024" for i, (m, _, r) in enumerate(rows))
    return McsTable("nr_cqi2", labels, eff, snr)


#: ``[link_adaptation] table`` -> :class:`McsTable`.
TABLES: dict[str, McsTable] = {"he": _he(), "nr_cqi2": _nr_cqi2()}


class McsRate:
    """Callable: per-RE stream SINRs -> bits a modem carries (see the module doc).

    Args:
        table: a :data:`TABLES` key.
        evm_db: transmitter EVM floor, dB (< 0).
    """

    def __init__(self, table: str = "he", evm_db: float = -35.0) -> None:
        if table not in TABLES:
            raise ValueError(f"link_adaptation.table: expected one of {', '.join(TABLES)}, "
                             f"got {table!r}")
        if not evm_db < 0:
            raise ValueError(f"link_adaptation.evm_db: expected a negative dB value, got {evm_db}")
        self.table = TABLES[table]
        self.evm = 10.0 ** (float(evm_db) / 10.0)

    def __call__(self, sinr: np.ndarray, power: np.ndarray,
                 weights: np.ndarray | None = None) -> tuple[float, np.ndarray]:
        """Bits over the allocation and the chosen entry per stream.

        Args:
            sinr: ``[R, S]`` post-MMSE SINR per RE and stream, linear.
            power: ``[R, S]`` power per RE and stream (a stream uses the REs with
                power > 0), W.
            weights: ``[R]`` REs each row stands for (default 1).

        Returns:
            ``(bits, mcs [S])``: bits carried per step (all streams), and the
            table index per stream (-1: the stream carries nothing).
        """
        bits, idx = self.many(np.asarray(sinr, float)[None], np.asarray(power)[None], weights)
        return float(bits[0]), idx[0]

    def many(self, sinr: np.ndarray, power: np.ndarray,
             weights: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`__call__` for ``B`` links with the same shapes at once (issue #19).

        Args:
            sinr, power: ``[B, R, S]``. weights: ``[R]`` (shared) or None.

        Returns:
            ``(bits [B], mcs [B, S])``.
        """
        sinr = np.asarray(sinr, float)
        b_, r_, s_ = sinr.shape
        w = np.ones(r_) if weights is None else np.asarray(weights, float)
        on = (np.asarray(power) > 0) & np.isfinite(sinr) & (sinr > 0)
        eff = np.where(on, 1.0 / (1.0 / np.where(on, sinr, 1.0) + self.evm), 0.0)
        ww = w[None, :, None] * on
        n_re = ww.sum(axis=1)  # [B, S]
        mi = np.einsum("brs,brs->bs", ww, np.log2(1.0 + eff))
        with np.errstate(divide="ignore", invalid="ignore"):
            sinr_s = np.where(n_re > 0, 2.0 ** (mi / np.maximum(n_re, 1e-300)) - 1.0, 0.0)
            idx = np.where(n_re > 0, self.table.select(10 * np.log10(sinr_s)), -1)
        bits = np.sum(np.where(idx >= 0, self.table.efficiency[np.maximum(idx, 0)], 0.0)
                      * n_re, axis=1)
        return bits, idx
