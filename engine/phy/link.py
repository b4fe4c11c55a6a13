r"""Link layer of the PHY: beamforming, power allocation, eqs. 1-2, rates.

Signal model per resource element (RE) ``(k, n)`` (paper, eqs. 1-2)::

    x_q[k, n] = alpha_q[k, n] * W_q[k, n] @ (sqrt(p_q[k, n]) * d_q[k, n])   [Nt]
    y_v[k, n] = sum_q H_vq[k, n] @ x_q[k, n] + z[k, n],  z ~ CN(0, sigma^2 I) [Nr]

Eq. 1 is written for one stream; here ``W`` has ``S`` unit-norm columns and
``p``, ``d`` carry one entry per stream (S = 1 is the paper's form).
Symbols have ``E|d|^2 = 1``; the budget is ``sum_{(k,n) in R_q} ||x||^2 <= P_q``
(in expectation, and exactly for unit-modulus symbols and orthonormal ``W``).

Power units: ``p`` is the power of one RE in W, and ``sigma^2 = k_B T delta_f F``
is the noise power in one subcarrier (:func:`engine.phy.units.thermal_noise_power`),
so ``p |h|^2 / sigma^2`` is the per-RE SNR. With the total power P_q spread
uniformly over R_q, per-RE power is ``P_q / |R_q|``.

Rate normalisation (documented choice): a link's achievable rate per twin step
is ``sum over its REs of log2 det(I + C^-1 H W P W^H H^H)`` [bit], divided by
the step duration ``K * T_s`` (T_s includes the cyclic prefix) -> bit/s. So a
full-grid SISO AWGN link gives ``N * log2(1 + SNR) / T_s``.

Given weights: any ``W [K, N, Nt, S]`` may be passed to :func:`transmit` and
:class:`AchievableRate`; the budget then reads ``sum p ||w_s||^2 <= P_q``, so
give it unit-norm columns (the precoders here always do).

Beamforming choices (documented): :class:`MRTPrecoder` maximises received
power ``||H w||`` (principal right singular vector; ``h^H / ||h||`` for one
receive antenna). :class:`SVDPrecoder` takes the S strongest right singular
vectors either per RE (``mode="per_re"``, the default: eigen-beamforming on
each subcarrier/symbol) or from the channel covariance averaged over the
resource set (``mode="wideband"``: one precoder for the whole allocation).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from engine.phy._checks import complex_array, positive_float, real_array
from engine.phy.ofdm import ResourceGrid

__all__ = [
    "MRTPrecoder", "SVDPrecoder", "EqualPower", "WaterFilling", "water_filling",
    "transmit", "receive", "transmit_power", "Interferer", "LinkRate",
    "AchievableRate", "channel_gains",
]


def _check_h(name: str, h) -> np.ndarray:
    h = complex_array(name, h)
    if h.ndim != 4:
        raise ValueError(f"{name} must have shape [K, N, Nr, Nt], got {list(h.shape)}")
    return h


def _check_mask(mask, shape: tuple[int, int], name: str = "mask") -> np.ndarray:
    if mask is None:
        return np.ones(shape, dtype=bool)
    m = np.asarray(mask)
    if m.shape != shape:
        raise ValueError(f"{name} must have shape {list(shape)} (K, N), got {list(m.shape)}")
    if m.dtype != bool:
        if not np.all(np.isin(m, (0, 1))):
            raise ValueError(f"{name} must be boolean/0-1")
        m = m.astype(bool)
    return m


class MRTPrecoder:
    """Single-stream maximum-ratio (eigen) beamformer.

    Call: ``H [K, N, Nr, Nt] -> W [K, N, Nt, 1]`` with unit-norm columns,
    chosen per RE to maximise ``||H w||^2``.
    """

    def __call__(self, h) -> np.ndarray:
        h = _check_h("H", h)
        if h.shape[2] == 1:
            w = np.conj(h[:, :, 0, :])
            norm = np.linalg.norm(w, axis=-1, keepdims=True)
            w = np.where(norm > 0, w / np.where(norm > 0, norm, 1), 1 / np.sqrt(h.shape[3]))
            return w[..., None]
        _, _, vh = np.linalg.svd(h, full_matrices=False)
        return np.conj(vh[:, :, :1, :]).swapaxes(-1, -2)


class SVDPrecoder:
    """Multi-stream SVD (eigen) precoder.

    Args:
        num_streams: S, at most min(Nr, Nt).
        mode: ``"per_re"`` (right singular vectors of every ``H[k, n]``) or
            ``"wideband"`` (eigenvectors of ``mean_{R} H^H H``, one precoder
            for all REs of the mask).

    Call: ``(H [K, N, Nr, Nt], mask [K, N] | None) -> W [K, N, Nt, S]``
    (unit-norm, orthonormal columns).
    """

    def __init__(self, num_streams: int, mode: str = "per_re") -> None:
        if isinstance(num_streams, bool) or not isinstance(num_streams, (int, np.integer)) \
                or num_streams < 1:
            raise ValueError(f"num_streams must be an integer >= 1, got {num_streams!r}")
        if mode not in ("per_re", "wideband"):
            raise ValueError(f"mode must be 'per_re' or 'wideband', got {mode!r}")
        self.num_streams = int(num_streams)
        self.mode = mode

    def __call__(self, h, mask=None) -> np.ndarray:
        h = _check_h("H", h)
        k, n, nr, nt = h.shape
        s = self.num_streams
        if s > min(nr, nt):
            raise ValueError(f"num_streams={s} exceeds min(Nr, Nt)={min(nr, nt)}")
        m = _check_mask(mask, (k, n))
        if self.mode == "per_re":
            _, _, vh = np.linalg.svd(h, full_matrices=False)
            return np.conj(vh[:, :, :s, :]).swapaxes(-1, -2)
        hm = h[m]  # [R, Nr, Nt]
        if hm.shape[0] == 0:
            raise ValueError("mask selects no resource element")
        cov = np.einsum("rij,rik->jk", np.conj(hm), hm) / hm.shape[0]
        _, vec = np.linalg.eigh(cov)
        w = vec[:, ::-1][:, :s]
        return np.broadcast_to(w, (k, n, nt, s)).copy()


def channel_gains(h, w) -> np.ndarray:
    """Per-stream effective gains ``||H w_s||^2`` ``[K, N, S]`` (inputs as in
    :func:`transmit`); the input to power allocation."""
    h = _check_h("H", h)
    w = complex_array("W", w, ndim=4)
    if w.shape[:3] != (h.shape[0], h.shape[1], h.shape[3]):
        raise ValueError(f"W must have shape [K, N, Nt, S] matching H {list(h.shape)}, "
                         f"got {list(w.shape)}")
    return np.sum(np.abs(h @ w) ** 2, axis=-2)


def water_filling(gains, total_power: float, noise_power: float = 1.0,
                  mask=None) -> np.ndarray:
    """Water-filling power allocation over all entries of ``gains``.

    Maximises ``sum log2(1 + p_i g_i / noise_power)`` s.t. ``sum p_i = P``,
    ``p_i >= 0``; exact (sort-based, no iterations).

    Args:
        gains: Channel gains ``g_i >= 0`` (any shape, e.g. ``[K, N, S]``).
        total_power: P [W] to distribute (the budget P_q).
        noise_power: sigma^2 [W].
        mask: Optional boolean array broadcastable to ``gains``; entries
            outside get zero power.

    Returns:
        Powers ``p`` [W], same shape as ``gains``; ``sum(p) == P`` unless all
        gains are zero (then all zero).
    """
    g = real_array("gains", gains, nonnegative=True)
    p_tot = positive_float("total_power", total_power, allow_zero=True)
    n0 = positive_float("noise_power", noise_power)
    active = g > 0
    if mask is not None:
        active &= np.broadcast_to(np.asarray(mask, dtype=bool), g.shape)
    out = np.zeros(g.shape)
    if p_tot == 0 or not active.any():
        return out
    inv = n0 / g[active]  # floor levels 1/SNR_i
    order = np.sort(inv)
    m = np.arange(1, order.size + 1)
    levels = (p_tot + np.cumsum(order)) / m  # water level if m best entries active
    n_on = int(np.max(np.nonzero(levels > order)[0])) + 1
    mu = levels[n_on - 1]
    out[active] = np.maximum(mu - inv, 0.0)
    # Remove the rounding residue so the budget is never exceeded.
    out *= min(1.0, p_tot / out.sum())
    return out


class WaterFilling:
    """Callable water-filling across streams and REs of a resource set.

    Args:
        total_power: P_q [W].
        noise_power: sigma^2 per RE [W].

    Call: ``(gains [K, N, S], mask [K, N]) -> p [K, N, S]`` [W].
    """

    def __init__(self, total_power: float, noise_power: float) -> None:
        self.total_power = positive_float("total_power", total_power, allow_zero=True)
        self.noise_power = positive_float("noise_power", noise_power)

    def __call__(self, gains, mask=None) -> np.ndarray:
        g = real_array("gains", gains, ndim=3)
        m = _check_mask(mask, g.shape[:2])
        return water_filling(g, self.total_power, self.noise_power, m[:, :, None])


class EqualPower:
    """Equal power over the REs and streams of a resource set.

    Args:
        total_power: P_q [W].

    Call: ``(mask [K, N], num_streams S) -> p [K, N, S]`` with
    ``P_q / (|R_q| S)`` on every allocated RE and stream.
    """

    def __init__(self, total_power: float) -> None:
        self.total_power = positive_float("total_power", total_power, allow_zero=True)

    def __call__(self, mask, num_streams: int = 1) -> np.ndarray:
        m = np.asarray(mask, dtype=bool)
        if m.ndim != 2:
            raise ValueError(f"mask must have shape [K, N], got {list(m.shape)}")
        if num_streams < 1:
            raise ValueError(f"num_streams must be >= 1, got {num_streams}")
        count = int(m.sum()) * num_streams
        if count == 0:
            raise ValueError("mask selects no resource element")
        p = np.zeros(m.shape + (num_streams,))
        p[m] = self.total_power / count
        return p


def transmit(alpha, p, w, d) -> np.ndarray:
    """Eq. 1: ``x[k, n] = alpha[k, n] * W[k, n] @ (sqrt(p[k, n]) * d[k, n])``.

    Args:
        alpha: Allocation mask ``[K, N]`` (bool or 0/1).
        p: Powers ``[K, N, S]`` [W], non-negative.
        w: Beamformers ``[K, N, Nt, S]``.
        d: Symbols ``[K, N, S]`` with ``E|d|^2 = 1``.

    Returns:
        Transmit signal ``x [K, N, Nt]`` complex128.
    """
    p = real_array("p", p, ndim=3, nonnegative=True)
    k, n, s = p.shape
    a = _check_mask(alpha, (k, n), "alpha")
    w = complex_array("w", w, ndim=4)
    if w.shape[:2] != (k, n) or w.shape[3] != s:
        raise ValueError(f"w must have shape [K, N, Nt, S] = [{k}, {n}, *, {s}], "
                         f"got {list(w.shape)}")
    d = complex_array("d", d, shape=(k, n, s))
    x = np.einsum("knts,kns->knt", w, np.sqrt(p) * d)
    return x * a[:, :, None]


def transmit_power(x, mask=None) -> float:
    """Total transmit power ``sum_{(k,n) in mask} ||x[k, n]||^2`` [W]."""
    x = complex_array("x", x, ndim=3)
    m = _check_mask(mask, x.shape[:2])
    return float(np.sum(np.abs(x[m]) ** 2))


def receive(channels: Sequence, signals: Sequence, noise_power: float,
            rng: np.random.Generator | None = None) -> np.ndarray:
    """Eq. 2: ``y[k, n] = sum_q H_q[k, n] @ x_q[k, n] + z[k, n]``.

    Args:
        channels: Per transmitter ``H_q [K, N, Nr, Nt_q]``.
        signals: Per transmitter ``x_q [K, N, Nt_q]`` (from :func:`transmit`).
        noise_power: sigma^2 per RE and receive antenna [W]; 0 = noiseless.
        rng: numpy Generator for the noise.

    Returns:
        ``y [K, N, Nr]`` complex128.
    """
    if len(channels) != len(signals) or not channels:
        raise ValueError(f"channels ({len(channels)}) and signals ({len(signals)}) "
                         "must be non-empty and of equal length")
    n0 = positive_float("noise_power", noise_power, allow_zero=True)
    y = None
    for q, (h, x) in enumerate(zip(channels, signals)):
        h = _check_h(f"channels[{q}]", h)
        x = complex_array(f"signals[{q}]", x, ndim=3)
        if x.shape != (h.shape[0], h.shape[1], h.shape[3]):
            raise ValueError(f"signals[{q}] shape {list(x.shape)} does not match "
                             f"channels[{q}] {list(h.shape)} ([K, N, Nt])")
        yq = np.einsum("knrt,knt->knr", h, x)
        if y is not None and yq.shape != y.shape:
            raise ValueError(f"channels[{q}] has shape {list(h.shape)}, inconsistent "
                             "with channels[0] (K, N, Nr must agree)")
        y = yq if y is None else y + yq
    if n0 > 0:
        rng = rng or np.random.default_rng()
        y = y + np.sqrt(n0 / 2) * (rng.standard_normal(y.shape)
                                   + 1j * rng.standard_normal(y.shape))
    return y


@dataclass(frozen=True)
class Interferer:
    """Another transmitter heard by the receiver on (some of) the same REs.

    Attributes:
        h: Cross channel ``[K, N, Nr, Nt_i]`` to the victim receiver.
        w: Its beamformers ``[K, N, Nt_i, S_i]``.
        p: Its powers ``[K, N, S_i]`` [W].
        mask: Its allocation ``[K, N]``.
    """

    h: np.ndarray
    w: np.ndarray
    p: np.ndarray
    mask: np.ndarray


@dataclass(frozen=True)
class LinkRate:
    """Achievable rate of one link in one twin step.

    Attributes:
        rate_bps: Rate [bit/s] = ``bits_per_step / (K T_s)``.
        bits_per_step: Sum over the link's REs of the per-RE rate [bit].
        spectral_efficiency: Per-RE rate ``[K, N]`` [bit/RE], zero off the mask.
        sinr: Per-RE, per-stream post-MMSE SINR ``[K, N, S]`` (linear).
    """

    rate_bps: float
    bits_per_step: float
    spectral_efficiency: np.ndarray
    sinr: np.ndarray


class AchievableRate:
    """Achievable rate with Gaussian signalling and interference treated as
    noise (log-det with the interference-plus-noise covariance).

    Per RE: ``C = sigma^2 I + sum_i alpha_i H_i W_i P_i W_i^H H_i^H`` and
    ``r = log2 det(I + C^-1 H W P W^H H^H)`` [bit].

    Args:
        grid: OFDM grid (for ``K T_s``).
        noise_power: sigma^2 per RE and receive antenna [W].
    """

    def __init__(self, grid: ResourceGrid, noise_power: float) -> None:
        if not isinstance(grid, ResourceGrid):
            raise ValueError("grid must be a ResourceGrid")
        self.grid = grid
        self.noise_power = positive_float("noise_power", noise_power)

    def _effective(self, name, h, w, p, mask):
        h = _check_h(f"{name}.h", h)
        k, n, nr, nt = h.shape
        if (k, n) != self.grid.shape:
            raise ValueError(f"{name}.h grid dims {[k, n]} != grid {list(self.grid.shape)}")
        w = complex_array(f"{name}.w", w, ndim=4)
        if w.shape[:3] != (k, n, nt):
            raise ValueError(f"{name}.w must have shape [K, N, Nt, S] = [{k}, {n}, {nt}, *], "
                             f"got {list(w.shape)}")
        p = real_array(f"{name}.p", p, shape=(k, n, w.shape[3]), nonnegative=True)
        m = _check_mask(mask, (k, n), f"{name}.mask")
        f = (h @ w) * np.sqrt(p)[:, :, None, :]  # [K, N, Nr, S]
        return f * m[:, :, None, None], m

    def __call__(self, h, w, p, mask, interferers: Sequence[Interferer] = ()) -> LinkRate:
        """Args: ``h [K, N, Nr, Nt]``, ``w [K, N, Nt, S]``, ``p [K, N, S]``,
        ``mask [K, N]`` of the desired link; ``interferers`` as
        :class:`Interferer`. Returns :class:`LinkRate`."""
        f, m = self._effective("link", h, w, p, mask)
        k, n, nr, s = f.shape
        cov = np.broadcast_to(self.noise_power * np.eye(nr), (k, n, nr, nr)).astype(complex)
        for i, itf in enumerate(interferers):
            fi, _ = self._effective(f"interferers[{i}]", itf.h, itf.w, itf.p, itf.mask)
            if fi.shape[2] != nr:
                raise ValueError(f"interferers[{i}].h has Nr={fi.shape[2]}, link has {nr}")
            cov = cov + fi @ np.conj(fi).swapaxes(-1, -2)
        sig = f @ np.conj(f).swapaxes(-1, -2)
        _, ld_tot = np.linalg.slogdet(cov + sig)
        _, ld_in = np.linalg.slogdet(cov)
        se = np.maximum((ld_tot - ld_in) / np.log(2.0), 0.0) * m
        # Per-stream MMSE SINR: f_s^H (C + sum_{j!=s} f_j f_j^H)^-1 f_s.
        cinv_f = np.linalg.solve(cov + sig, f)  # (C+FF^H)^-1 F
        g = np.real(np.einsum("knrs,knrs->kns", np.conj(f), cinv_f))
        sinr = np.where(g < 1, g / np.maximum(1 - g, 1e-300), np.inf) * m[:, :, None]
        bits = float(se.sum())
        return LinkRate(rate_bps=bits / self.grid.step_duration_s, bits_per_step=bits,
                        spectral_efficiency=se, sinr=sinr)
