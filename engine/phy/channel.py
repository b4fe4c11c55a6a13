r"""MIMO-OFDM channel synthesis from path parameters (paper, eq. 4).

.. math::

    H[k, n] = \sum_l b_l \, e^{j 2\pi (k \nu_l T_s - f_n \tau_l)}
              \, a_{rx}(\theta_l) \, a_{tx}(\psi_l)^T

with ``f_n = n * delta_f`` the centred subcarrier offset (the paper's
``n * delta_f`` with n counted from the band centre).

Sionna correspondence (``Paths.cfr`` with ``synthetic_array=True``,
``frequencies = subcarrier_frequencies(N, delta_f)``,
``sampling_frequency = 1/T_s``, ``num_time_steps = K``,
``normalize_delays=False``)::

    H_sionna[rx, :, tx, :, k, n]  ==  H[k, n, :, :]      (transpose (2, 3, 0, 1))

provided that

* ``b_l = a_l * exp(-j 2 pi f_c tau_l)`` where ``a_l`` is Sionna's passband
  path coefficient ``Paths.a`` (already including antenna patterns at the
  array centres) -- see :func:`baseband_gains`;
* ``tau_l`` is the absolute delay ``Paths.tau`` [s] (no normalisation),
  ``nu_l`` is ``Paths.doppler`` [Hz];
* ``(theta_l, phi_l)`` arrival = ``(theta_r, phi_r)``, departure =
  ``(theta_t, phi_t)``, arrays built with the same rows/cols/spacings and the
  devices' ``orientation`` (``[yaw, pitch, roll]``), pattern ``"iso"``;
* phases: frequency term ``exp(-j 2 pi f_n tau)``, Doppler term
  ``exp(+j 2 pi nu t_k)`` with ``t_k = k / sampling_frequency = k T_s``,
  array term ``exp(+j 2 pi p . r_hat / lambda)`` for both ends -- the
  same signs Sionna uses in ``cir``/``cfr``/``_apply_synthetic_array``.

Precision: phases are computed in float64 and the result is complex64 by
default (Sionna itself works in float32); pass ``dtype=np.complex128`` for
reference computations.
"""

from __future__ import annotations

import numpy as np

from ._checks import complex_array, real_array, same_length
from .arrays import PlanarArray
from .ofdm import ResourceGrid

__all__ = ["OFDMChannel", "baseband_gains", "cfr_at", "cfr_from_antenna_gains",
           "port_pair_gains", "synthesize_many"]


def port_pair_gains(b: np.ndarray, a_rx: np.ndarray, a_tx: np.ndarray) -> np.ndarray:
    """Per-path gains of every receive/transmit antenna pair ``[L, Nr, Nt]``.

    Args:
        b: baseband gains ``[L]`` (single-polarized ends) or ``[L, Pr, Pt]`` per
            polarization port pair (``isac_twin.raytrace.antenna_patterns``).
        a_rx, a_tx: steering vectors ``[L, Er]`` / ``[L, Et]`` of the elements.

    Returns:
        ``[L, Pr * Er, Pt * Et]`` with antenna ``p * E + e`` (port ``p`` of
        element ``e``, Sionna's order for dual-polarized arrays).
    """
    if b.ndim == 1:
        return b[:, None, None] * a_rx[:, :, None] * a_tx[:, None, :]
    num_paths, pr, pt = b.shape
    g = (b[:, :, None, :, None] * a_rx[:, None, :, None, None]
         * a_tx[:, None, None, None, :])
    return g.reshape(num_paths, pr * a_rx.shape[1], pt * a_tx.shape[1])


def baseband_gains(a, tau, carrier_frequency_hz: float) -> np.ndarray:
    """Baseband-equivalent path gains ``b = a * exp(-j 2 pi f_c tau)``.

    Args:
        a: Passband path coefficients ``[L]`` or ``[L, ...]`` (Sionna ``Paths.a``).
        tau: Path delays ``[L]`` [s] (broadcast against ``a`` along axis 0).
        carrier_frequency_hz: Carrier frequency f_c [Hz].

    Returns:
        complex128 array with the shape of ``a``.
    """
    a = complex_array("a", a)
    tau = real_array("tau", tau, ndim=1)
    if a.shape[:1] != tau.shape:
        raise ValueError(f"a has {a.shape[0] if a.ndim else 0} paths on axis 0 "
                         f"but tau has {tau.shape[0]}")
    # Reduce f_c * tau modulo 1 in float64 before the exponential for accuracy.
    cycles = np.mod(float(carrier_frequency_hz) * tau, 1.0)
    ph = np.exp(-2j * np.pi * cycles)
    return a * ph.reshape((-1,) + (1,) * (a.ndim - 1))


def _delay_phase(grid: ResourceGrid, tau: np.ndarray, dtype=np.complex128) -> np.ndarray:
    """``exp(-j 2 pi f_n tau_l)`` ``[N, L]`` in ``dtype``, to float64 rounding.

    Subcarriers are uniform, ``f_n = (n0 + n) delta_f``: with ``n = B a + c`` the
    phase factors into ``exp(..(n0 + B a)..) * exp(..c..)``, two small tables of
    ``~sqrt(N)`` rows per path and one complex multiply per entry, formed in
    complex128 and rounded once to ``dtype``. Each table is a running product of
    at most ``~sqrt(N)`` factors whose phases are reduced modulo one cycle in
    float64 before the exponential (3 exponentials per path instead of
    ``2 sqrt(N)``, the table's largest cost with many links, issue #19): the
    rounding of a step's phase grows ``~sqrt(N)``-fold along a table, not along
    the N subcarriers; measured <= 3e-14 from the direct ``exp`` for N = 1024
    (delays to 300 ns), far below complex64 rounding (6e-8).
    """
    tau = np.asarray(tau, np.float64)
    n = grid.num_subcarriers
    df = grid.subcarrier_spacing_hz
    n0 = float(grid.subcarrier_indices[0])
    blk = max(1, int(np.ceil(np.sqrt(n))))
    na = -(-n // blk)

    def powers(first_cycles, step_cycles, count):
        """``exp(-j 2 pi (first + k step))`` for k < count -> ``[count, L]``."""
        t = np.empty((count, tau.size), np.complex128)
        t[0] = np.exp(-2j * np.pi * np.mod(first_cycles, 1.0))
        t[1:] = np.exp(-2j * np.pi * np.mod(step_cycles, 1.0))
        return np.cumprod(t, axis=0, out=t)

    outer = powers(n0 * df * tau, blk * df * tau, na)  # [na, L]
    inner = powers(np.zeros_like(tau), df * tau, blk)  # [B, L]
    out = np.empty((na, blk, tau.size), dtype)
    np.multiply(outer[:, None, :], inner[None, :, :], out=out, casting="same_kind")
    return out.reshape(na * blk, -1)[:n]


#: Doppler phases are expanded in a Taylor series in time when the truncation
#: error ``x^(J+1) / (J+1)!`` (x = largest phase drift from the centre time) is below
#: this, far below complex64 rounding (6e-8); see :func:`_synthesize`.
_TAYLOR_TOL = 1e-10


def _taylor_order(x: float, max_order: int) -> int | None:
    """Smallest J with ``x^(J+1) / (J+1)! <= _TAYLOR_TOL`` (None if > max_order)."""
    term = x
    for j in range(max_order + 1):
        if term <= _TAYLOR_TOL:
            return j
        term = term * x / (j + 2)
    return None


def _synthesize(gains: np.ndarray, tau: np.ndarray, doppler: np.ndarray,
                grid: ResourceGrid, dtype, times=None, delay_phase=None,
                max_doppler: float | None = None, rows=None) -> np.ndarray:
    """Core of eq. 4: ``[L, M]`` antenna-pair gains -> ``[T, N, M]`` (``[R, N, M]``
    with ``rows``).

    The time-frequency kernel ``exp(j2pi(nu t_k - f_n tau))`` is separable, so the
    Doppler phase is folded into the (small) gains and one BLAS matmul with the
    ``[N, L]`` delay phases covers all symbols, without materialising the
    ``[T, N, L]`` kernel. Over a step the Doppler phase drifts by
    ``x = 2 pi |nu| max_k |t_k - t_c|`` (~1e-3 rad for walking speeds), so
    ``exp(j 2 pi nu t_k) = exp(j 2 pi nu t_c) sum_j (j 2 pi nu (t_k - t_c))^j / j!``
    truncated after J + 1 terms (error <= _TAYLOR_TOL relative per path, i.e.
    exact in complex64) needs only J + 1 << T "basis" channels, combined per symbol
    by a second small matmul; used when J + 1 <= T / 2, else all T directly.

    Args:
        times: Symbol times ``[T]`` [s] (default ``grid.symbol_times``, T = K).
        delay_phase: precomputed ``_delay_phase(grid, tau)`` ``[N, L]`` in ``dtype``
            (e.g. columns of one table over several links' paths).
        max_doppler: |nu| bound [Hz] that picks the Taylor order (default
            ``max |doppler|``; a larger bound only adds terms).
        rows: indices ``[R]`` into ``times``: only these symbols are computed
            (the method and the Taylor basis still follow all ``times``, so a
            symbol's value does not depend on which others are requested).
    """
    num_paths, m = gains.shape
    t = grid.symbol_times if times is None else np.asarray(times, dtype=np.float64)
    k_, n_ = t.shape[0], grid.num_subcarriers
    rows = np.arange(k_) if rows is None else np.asarray(rows, dtype=np.int64).reshape(-1)
    r_ = rows.shape[0]
    if num_paths == 0 or r_ == 0:
        return np.zeros((r_, n_, m), dtype=dtype)
    if delay_phase is None:
        delay_phase = _delay_phase(grid, tau, dtype)  # [N, L]
    t_c = 0.5 * (t.max() + t.min())
    half = 0.5 * float(t.max() - t.min())
    nu = float(np.max(np.abs(doppler))) if max_doppler is None else float(max_doppler)
    x = 2 * np.pi * nu * half
    order = _taylor_order(x, k_ // 2 - 1) if k_ >= 4 else None
    if order is None:
        doppler_phase = np.exp(2j * np.pi * np.mod(np.outer(t[rows], doppler), 1.0))  # [R, L]
        g_t = doppler_phase[:, :, None] * gains[None, :, :]  # [R, L, M]
        g_t = g_t.transpose(1, 0, 2).reshape(num_paths, r_ * m).astype(dtype)
        out = delay_phase @ g_t  # [N, R * M]
        return np.ascontiguousarray(out.reshape(n_, r_, m).transpose(1, 0, 2))
    j = np.arange(order + 1)
    centre = np.exp(2j * np.pi * np.mod(t_c * doppler, 1.0))  # [L]
    # coef[j, l] = (j 2 pi nu_l half)^j / j!  ;  basis[k, j] = ((t_k - t_c) / half)^j
    xl = 2j * np.pi * doppler * half
    fact = np.cumprod(np.concatenate([[1.0], np.arange(1, order + 1)]))
    coef = xl[None, :] ** j[:, None] / fact[:, None]  # [J+1, L]
    g_j = (coef[:, :, None] * (centre[:, None] * gains)[None]).transpose(1, 0, 2)
    g_j = g_j.reshape(num_paths, (order + 1) * m).astype(dtype)  # [L, (J+1) M]
    xb = (delay_phase @ g_j).reshape(n_, order + 1, m).transpose(1, 0, 2)  # [J+1, N, M]
    s = (t - t_c) / half if half > 0 else np.zeros_like(t)
    basis = (s[rows, None] ** j[None, :]).astype(dtype)  # [R, J+1]
    out = basis @ np.ascontiguousarray(xb).reshape(order + 1, n_ * m)  # [R, N * M]
    return out.reshape(r_, n_, m)


def synthesize_many(grid: ResourceGrid, gains, taus, dopplers, dtype=np.complex64,
                    times=None, rows=None, max_doppler: float | None = None
                    ) -> list[np.ndarray]:
    """Eq. 4 for several links in one pass (the batched network PHY, issue #19).

    One delay-phase table ``exp(-j 2 pi f_n tau)`` covers every link's paths and
    one Taylor order (from the largest Doppler shift of the batch) covers every
    link; each link then costs its own two small matmuls. Equal to one
    :func:`_synthesize` per link up to the Taylor remainder (<= 1e-10 relative
    per path, below complex64 rounding).

    Args:
        gains: per link ``[L_i, M_i]`` antenna-pair gains (complex).
        taus, dopplers: per link ``[L_i]`` delays [s] and Doppler shifts [Hz].
        times: symbol times ``[T]`` [s] (default the grid's K symbols).
        rows: per link the indices ``[R_i]`` into ``times`` to compute (None: all),
            e.g. only the symbols a transmitter uses; a symbol's value does not
            depend on which others are computed with it.
        max_doppler: |nu| bound [Hz] that picks the Taylor order (default the
            batch's largest; pass a batch's value to extend it later).

    Returns:
        per link ``[T, N, M_i]`` (``[R_i, N, M_i]`` with ``rows``) in ``dtype``.
    """
    gains, taus, dopplers = list(gains), list(taus), list(dopplers)
    if not gains:
        return []
    rows = [None] * len(gains) if rows is None else list(rows)
    tau_all = np.concatenate([np.asarray(t, np.float64) for t in taus])
    nu_all = np.concatenate([np.asarray(d, np.float64) for d in dopplers])
    table = _delay_phase(grid, tau_all, dtype) if tau_all.size else None
    nu = (float(np.max(np.abs(nu_all))) if nu_all.size else 0.0) if max_doppler is None \
        else float(max_doppler)
    out, start = [], 0
    for g, t, d, r in zip(gains, taus, dopplers, rows):
        n = len(t)
        dp = None if table is None else table[:, start:start + n]
        out.append(_synthesize(g, np.asarray(t, np.float64), np.asarray(d, np.float64),
                               grid, dtype, times, delay_phase=dp, max_doppler=nu, rows=r))
        start += n
    return out


def cfr_from_antenna_gains(gains, tau, doppler, grid: ResourceGrid,
                           dtype=np.complex64) -> np.ndarray:
    """Eq. 4 with per-path, per-antenna-pair gains that already contain the
    array phases (validation variant).

    Use it with Sionna paths traced with ``synthetic_array=True`` (gains
    ``a * exp(-j 2 pi f_c tau)`` per antenna pair, delays ``[L]``) or
    ``synthetic_array=False`` (every antenna pair has its own delays and
    Doppler shifts: pass them as ``[L, Nr, Nt]``; invalid paths must have
    zero gain, their delay is then irrelevant).

    Args:
        gains: Baseband gains ``[L, Nr, Nt]`` (complex).
        tau: Delays ``[L]`` or ``[L, Nr, Nt]`` [s].
        doppler: Doppler shifts, same shape as ``tau`` [Hz].
        grid: OFDM grid (K, N, delta_f, T_s).
        dtype: Output dtype (complex64 or complex128).

    Returns:
        Channel ``[K, N, Nr, Nt]``.
    """
    gains = complex_array("gains", gains, ndim=3)
    num_paths, nr, nt = gains.shape
    tau = real_array("tau", tau)
    doppler = real_array("doppler", doppler)
    if tau.shape not in ((num_paths,), gains.shape):
        raise ValueError(f"tau must have shape [L] or [L, Nr, Nt] = {list(gains.shape)}, "
                         f"got {list(tau.shape)}")
    if doppler.shape != tau.shape:
        raise ValueError(f"doppler must have the shape of tau {list(tau.shape)}, "
                         f"got {list(doppler.shape)}")
    k_, n_ = grid.shape
    if tau.ndim == 1:
        h = _synthesize(gains.reshape(num_paths, nr * nt), tau, doppler, grid, dtype)
        return h.reshape(k_, n_, nr, nt)
    # Per-pair delays: one small matmul per antenna pair (not per path).
    out = np.empty((k_, n_, nr * nt), dtype=dtype)
    g2, t2, d2 = (x.reshape(num_paths, nr * nt) for x in (gains, tau, doppler))
    for pair in range(nr * nt):
        out[:, :, pair] = _synthesize(g2[:, pair:pair + 1], t2[:, pair], d2[:, pair],
                                      grid, dtype)[:, :, 0]
    return out.reshape(k_, n_, nr, nt)


def cfr_at(b, tau, theta_r, phi_r, theta_t, phi_t, freqs_hz, rx_array: PlanarArray,
           tx_array: PlanarArray, rx_orientation=(0.0, 0.0, 0.0),
           tx_orientation=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Eq. 4 at one instant (``t = 0``, so no Doppler) at chosen subcarriers.

    The snapshot variant of :class:`OFDMChannel` (same arguments, same order) for
    features that need a few subcarriers of one symbol (e.g. fingerprint CSI).

    Args:
        b: baseband complex path gains ``[L]`` (see :func:`baseband_gains`), or
            ``[L, Pr, Pt]`` per polarization port pair (:func:`port_pair_gains`).
        tau: delays ``[L]`` [s].
        theta_r, phi_r: arrival zenith/azimuth ``[L]`` [rad].
        theta_t, phi_t: departure zenith/azimuth ``[L]`` [rad].
        freqs_hz: centred subcarrier offsets ``[S]`` [Hz].
        rx_orientation, tx_orientation: ``[yaw, pitch, roll]`` [rad].

    Returns:
        ``H [S, Nr, Nt]`` complex128 (``Nr = Pr * rows * cols``).
    """
    tau = np.asarray(tau, float)
    b = np.asarray(b, complex)
    pr, pt = b.shape[1:] if b.ndim == 3 else (1, 1)
    if tau.size == 0:
        return np.zeros((len(freqs_hz), pr * rx_array.num_ant, pt * tx_array.num_ant), complex)
    arx = rx_array.steering_vectors(np.asarray(theta_r, float), np.asarray(phi_r, float),
                                    rx_orientation)
    atx = tx_array.steering_vectors(np.asarray(theta_t, float), np.asarray(phi_t, float),
                                    tx_orientation)
    ph = np.exp(-2j * np.pi * np.mod(np.outer(freqs_hz, tau), 1.0))
    if b.ndim == 1:
        return np.einsum("sl,lr,lt->srt", ph * b, arx, atx, optimize=True)
    return np.einsum("sl,lrt->srt", ph, port_pair_gains(b, arx, atx), optimize=True)


class OFDMChannel:
    """Eq.-4 channel synthesiser for one link (callable).

    Args:
        grid: OFDM grid.
        rx_array: Receive array (Nr elements).
        tx_array: Transmit array (Nt elements).
        dtype: Output dtype, complex64 (default) or complex128.

    Call args:
        b: Baseband complex path gains ``[L]`` (see :func:`baseband_gains`), or
            ``[L, Pr, Pt]`` per polarization port pair of dual-polarized arrays
            (then ``Nr = Pr * rows * cols``, see :func:`port_pair_gains`).
        tau: Delays ``[L]`` [s].
        doppler: Doppler shifts ``[L]`` [Hz].
        theta_r, phi_r: Arrival zenith/azimuth ``[L]`` [rad].
        theta_t, phi_t: Departure zenith/azimuth ``[L]`` [rad].
        rx_orientation, tx_orientation: ``[yaw, pitch, roll]`` [rad].
        times: Optional symbol times ``[T]`` [s] to evaluate instead of the
            grid's ``k T_s`` (e.g. one mid-step time for a time-invariant step).

    Returns:
        ``H [K, N, Nr, Nt]`` (``[T, N, Nr, Nt]`` with ``times``);
        ``y[k, n] = H[k, n] @ x[k, n]``.
    """

    def __init__(self, grid: ResourceGrid, rx_array: PlanarArray,
                 tx_array: PlanarArray, dtype=np.complex64) -> None:
        if not isinstance(grid, ResourceGrid):
            raise ValueError("grid must be a ResourceGrid")
        if not isinstance(rx_array, PlanarArray) or not isinstance(tx_array, PlanarArray):
            raise ValueError("rx_array and tx_array must be PlanarArray instances")
        if np.dtype(dtype) not in (np.dtype(np.complex64), np.dtype(np.complex128)):
            raise ValueError(f"dtype must be complex64 or complex128, got {dtype}")
        self.grid = grid
        self.rx_array = rx_array
        self.tx_array = tx_array
        self.dtype = np.dtype(dtype)

    def __call__(self, b, tau, doppler, theta_r, phi_r, theta_t, phi_t,
                 rx_orientation=(0.0, 0.0, 0.0),
                 tx_orientation=(0.0, 0.0, 0.0), times=None) -> np.ndarray:
        b = complex_array("b", b)
        if b.ndim not in (1, 3):
            raise ValueError(f"b must have shape [L] or [L, Pr, Pt], got {list(b.shape)}")
        tau = real_array("tau", tau, ndim=1)
        doppler = real_array("doppler", doppler, ndim=1)
        angles = {n: real_array(n, v, ndim=1) for n, v in
                  (("theta_r", theta_r), ("phi_r", phi_r),
                   ("theta_t", theta_t), ("phi_t", phi_t))}
        same_length(b=b[:, 0, 0] if b.ndim == 3 else b, tau=tau, doppler=doppler, **angles)
        a_rx = self.rx_array.steering_vectors(angles["theta_r"], angles["phi_r"],
                                              rx_orientation)  # [L, Nr]
        a_tx = self.tx_array.steering_vectors(angles["theta_t"], angles["phi_t"],
                                              tx_orientation)  # [L, Nt]
        # Outer product per path: [L, Nr * Nt] (row-major matches [Nr, Nt]).
        pair = port_pair_gains(b, a_rx, a_tx)
        num_paths, nr, nt = pair.shape
        h = _synthesize(pair.reshape(num_paths, nr * nt), tau, doppler,
                        self.grid, self.dtype, times)
        return h.reshape(h.shape[0], self.grid.num_subcarriers, nr, nt)
