r"""Link layer of the PHY: beamforming, power allocation, eqs. 1-2, rates.

Signal model per resource element (RE) ``(k, n)`` (paper, eqs. 1-2)::

    x_q[k, n] = alpha_q[k, n] * W_q[k, n] @ (sqrt(p_q[k, n]) * d_q[k, n])   [Nt]
    y_v[k, n] = sum_q H_vq[k, n] @ x_q[k, n] + z[k, n],  z ~ CN(0, sigma^2 I) [Nr]

Eq. 1 is written for one stream; here ``W`` has ``S`` unit-norm columns and
``p``, ``d`` carry one entry per stream (S = 1 is the paper's form).
Symbols have ``E|d|^2 = 1``; the budget is ``sum_{(k,n) in R_q} ||x||^2 <= P_q``
(in expectation, and exactly for unit-modulus symbols and orthonormal ``W``).

Power units: ``p`` is the power of one RE in W, and ``sigma^2 = k_B T delta_f F``
is the noise power in one subcarrier (:func:`isac_twin.phy.units.thermal_noise_power`),
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

from ._checks import complex_array, positive_float, real_array
from .ofdm import ResourceGrid

__all__ = [
    "MRTPrecoder", "SVDPrecoder", "EqualPower", "WaterFilling", "water_filling",
    "transmit", "receive", "transmit_power", "Interferer", "LinkRate",
    "AchievableRate", "channel_gains", "svd_streams", "rate_per_re",
    "wideband_streams", "water_level", "water_levels",
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
        k, n, nr, nt = h.shape
        w, _, _ = svd_streams(h.reshape(k * n, nr, nt), 1, dtype=np.complex128)
        return w.reshape(k, n, nt, 1)


class SVDPrecoder:
    """Multi-stream SVD (eigen) precoder.

    Args:
        num_streams: S, at most min(Nr, Nt).
        mode: ``"per_re"`` (right singular vectors of every ``H[k, n]``) or
            ``"wideband"`` (eigenvectors of ``mean_{R} H^H H``, one precoder
            for all REs of the mask).

        method: ``"auto"`` (closed-form per-RE SVD when ``min(Nr, Nt) <= 2``,
            see :func:`svd_streams`) or ``"numpy"`` (``np.linalg.svd`` always,
            the reference). Both give orthonormal right singular vectors; columns
            are unique only up to a phase.

    Call: ``(H [K, N, Nr, Nt], mask [K, N] | None) -> W [K, N, Nt, S]``
    (unit-norm, orthonormal columns).
    """

    def __init__(self, num_streams: int, mode: str = "per_re", method: str = "auto") -> None:
        if isinstance(num_streams, bool) or not isinstance(num_streams, (int, np.integer)) \
                or num_streams < 1:
            raise ValueError(f"num_streams must be an integer >= 1, got {num_streams!r}")
        if mode not in ("per_re", "wideband"):
            raise ValueError(f"mode must be 'per_re' or 'wideband', got {mode!r}")
        if method not in ("auto", "numpy"):
            raise ValueError(f"method must be 'auto' or 'numpy', got {method!r}")
        self.num_streams = int(num_streams)
        self.mode = mode
        self.method = method

    def __call__(self, h, mask=None) -> np.ndarray:
        h = _check_h("H", h)
        k, n, nr, nt = h.shape
        s = self.num_streams
        if s > min(nr, nt):
            raise ValueError(f"num_streams={s} exceeds min(Nr, Nt)={min(nr, nt)}")
        m = _check_mask(mask, (k, n))
        if self.mode == "per_re":
            if self.method == "auto" and min(nr, nt) <= 2:
                w, _, _ = svd_streams(h.reshape(k * n, nr, nt), s, dtype=np.complex128)
                return w.reshape(k, n, nt, s)
            _, _, vh = np.linalg.svd(h, full_matrices=False)
            return np.conj(vh[:, :, :s, :]).swapaxes(-1, -2)
        hm = h[m]  # [R, Nr, Nt]
        if hm.shape[0] == 0:
            raise ValueError("mask selects no resource element")
        w = wideband_streams(hm, s)
        return np.broadcast_to(w, (k, n, nt, s)).copy()


def wideband_streams(h, num_streams: int, weights=None) -> np.ndarray:
    """The wideband (eigen) precoder: the ``S`` principal eigenvectors of the mean
    channel covariance ``sum_r w_r H_r^H H_r / sum_r w_r`` over a resource set.

    Args:
        h: channels of the set's REs ``[R, Nr, Nt]`` complex.
        num_streams: S.
        weights: how often each RE counts ``[R]`` (None: once each).

    Returns:
        ``W [Nt, S]``, orthonormal columns, strongest first.
    """
    hd = np.asarray(h, dtype=np.complex128)
    if weights is None:
        cov = np.einsum("rij,rik->jk", np.conj(hd), hd) / hd.shape[0]
    else:
        wts = np.asarray(weights, dtype=float)
        hw = hd * np.sqrt(wts)[:, None, None]
        cov = np.einsum("rij,rik->jk", np.conj(hw), hw) / wts.sum()
    _, vec = np.linalg.eigh(cov)
    return vec[:, ::-1][:, :num_streams]


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
    # Floor levels 1/SNR_i, sorted; water level if the m best entries are active;
    # the rounding residue is removed so the budget is never exceeded.
    out[active] = water_level(g[active], p_tot, n0)
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
        method: ``"auto"`` (closed-form 2 x 2 log-det / MMSE SINR on the mask's
            REs when Nr <= 2, see :func:`rate_per_re`) or ``"numpy"``
            (``slogdet`` / ``solve`` on every RE, the reference).
    """

    def __init__(self, grid: ResourceGrid, noise_power: float, method: str = "auto") -> None:
        if not isinstance(grid, ResourceGrid):
            raise ValueError("grid must be a ResourceGrid")
        if method not in ("auto", "numpy"):
            raise ValueError(f"method must be 'auto' or 'numpy', got {method!r}")
        self.grid = grid
        self.noise_power = positive_float("noise_power", noise_power)
        self.method = method

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
        if self.method == "auto" and nr <= 2:
            fis = []
            for i, itf in enumerate(interferers):
                fi, _ = self._effective(f"interferers[{i}]", itf.h, itf.w, itf.p, itf.mask)
                if fi.shape[2] != nr:
                    raise ValueError(f"interferers[{i}].h has Nr={fi.shape[2]}, link has {nr}")
                fis.append(fi[m])
            se_m, sinr_m = rate_per_re(f[m], fis, self.noise_power)
            se = np.zeros((k, n))
            sinr = np.zeros((k, n, s))
            se[m], sinr[m] = se_m, sinr_m
            bits = float(se_m.sum())
            return LinkRate(rate_bps=bits / self.grid.step_duration_s, bits_per_step=bits,
                            spectral_efficiency=se, sinr=sinr)
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


# --------------------------------------------------------------------------------------
# Exact small-matrix fast paths (vectorised over resource elements).
#
# For a link with Nr <= 2 (or Nt <= 2) receive/transmit antennas, the per-RE SVD,
# log-det and MMSE SINR reduce to closed forms on 2 x 2 Hermitian matrices, evaluated
# for all REs at once with elementwise numpy (no per-matrix LAPACK calls):
#
# * SVD: the Gram ``G = H H^H`` (Nr x Nr, float64 accumulation) has the closed-form
#   eigen-decomposition ``lambda_1,2 = (a+d)/2 +- sqrt(((a-d)/2)^2 + |b|^2)``; its
#   eigenvectors are the left singular vectors U, ``sigma = sqrt(lambda)`` and the
#   right singular vectors are ``W = H^H U Sigma^-1`` (orthonormal; the effective
#   channel is ``H W = U Sigma`` exactly). When Nt <= 2 < Nr the Gram ``H^H H`` gives
#   W directly.
# * Rates: ``log2 det(C + F F^H) - log2 det(C)`` and the per-stream MMSE SINR
#   ``f_s^H (C + sum_{j != s} f_j f_j^H)^-1 f_s`` with 2 x 2 closed-form determinants
#   and adjugates (the same quantity as the reference ``g / (1 - g)`` form, without
#   its cancellation at high SINR).
#
# Precision (documented error bounds, checked by tests/engine/phy/test_link_fast.py):
# all Gram, eigenvalue, determinant and SINR arithmetic is float64. The absolute error
# of lambda_2 is ~1e-16 * lambda_1, so a stream's per-RE rate error is
# ~1e-16 * SNR_1 / ln 2 bit -- negligible for any SNR below ~1e10 (rates match the
# LAPACK reference to ~1e-12 relative in the tests). W from the Gram has a direction
# error ~eps / r with r = sigma_2 / sigma_1: REs with r < 1e-6 (incl. rank-deficient
# channels) therefore go to LAPACK, so complex128 W is accurate to ~1e-10 (when more
# than 512 REs of a call are that ill-conditioned, e.g. a single-path channel, the
# weak column is completed orthogonally in closed form instead: it carries <= 1e-12
# of the gain, so rates are unaffected). Zero channels get W = [e_0, e_1].
# W may be formed in complex64 when H is complex64 (``H^H U`` in single precision,
# error ~6e-8 / r); REs with r < 0.05 are then recomputed in complex128, so complex64
# W is accurate to ~1e-6 (complex128 W is recomputed for them too, normalised by the
# actual column norms). Rates never use W for the link's own stream gains (they
# use ``U Sigma`` from the float64 eigen-decomposition), so complex64 W only enters
# through cross-channel interference (relative power error ~1e-6).
# Singular vectors are, as with LAPACK, unique only up to a phase per column (and
# any orthonormal completion for a zero singular value); rates do not depend on it.

#: complex64 W columns with sigma_2 < _REFINE * sigma_1 are recomputed in complex128.
_REFINE = 0.05
#: REs with sigma_2 < _LAPACK * sigma_1 (incl. rank-deficient) go to np.linalg.svd
#: (up to _LAPACK_MAX_REs of them; beyond, a closed-form orthogonal completion).
_LAPACK = 1e-6
_LAPACK_MAX_REs = 512


def _eigh2(a, d, b):
    """Closed-form eigen-decomposition of Hermitian PSD ``[[a, b], [conj(b), d]]``.

    Args: ``a, d`` float64 ``[R]``, ``b`` complex128 ``[R]``.
    Returns: ``lam [R, 2]`` (descending, >= 0) and ``u [R, 2, 2]`` complex128 with
    orthonormal eigenvector columns.
    """
    half = 0.5 * (a - d)
    mid = 0.5 * (a + d)
    r = np.hypot(half, np.abs(b))
    lam = np.stack([mid + r, np.maximum(mid - r, 0.0)], axis=-1)
    pos = half >= 0
    # Eigenvector of lambda_1 from whichever row of (G - lambda_1 I) is better
    # conditioned: |x| >= r >= |b| in both branches, so no cancellation.
    x = np.where(pos, r + half, b)
    y = np.where(pos, np.conj(b), r - half)
    nrm = np.sqrt(np.abs(x) ** 2 + np.abs(y) ** 2)
    flat = nrm == 0  # G = a I: any basis
    nrm = np.where(flat, 1.0, nrm)
    x = np.where(flat, 1.0, x / nrm)
    y = np.where(flat, 0.0, y / nrm)
    u = np.empty(a.shape + (2, 2), dtype=np.complex128)
    u[..., 0, 0], u[..., 1, 0] = x, y
    u[..., 0, 1], u[..., 1, 1] = -np.conj(y), np.conj(x)
    return lam, u


def _gram_rows2(h) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``G = h h^H`` of ``h [R, 2, M]`` as ``(a, d, b)`` (float64 accumulation).

    Products of two float32 numbers are exact in float64, so for complex64 ``h``
    the sums are formed from the float32 components widened to float64 once
    (one float64 copy of the real view: einsum's casting buffers made the five
    reductions ~1.8x slower, issue #19), without complex arithmetic.
    """
    h = np.asarray(h)
    if h.dtype != np.complex64:
        h = np.ascontiguousarray(h, dtype=np.complex128)
    elif not h.flags.c_contiguous:
        h = np.ascontiguousarray(h)
    v = h.view(h.real.dtype).astype(np.float64, copy=False)  # [R, 2, 2M]: re/im interleaved
    x0, y0, x1, y1 = v[:, 0, 0::2], v[:, 0, 1::2], v[:, 1, 0::2], v[:, 1, 1::2]
    a = np.einsum("ri,ri->r", v[:, 0], v[:, 0])
    d = np.einsum("ri,ri->r", v[:, 1], v[:, 1])
    re = np.einsum("ri,ri->r", v[:, 0], v[:, 1])
    im = np.einsum("ri,ri->r", y0, x1) - np.einsum("ri,ri->r", x0, y1)
    return a, d, re + 1j * im


def svd_streams(h, num_streams: int, dtype=None, *, precoders: bool = True):
    """Per-RE dominant right singular vectors, exactly (closed form when
    ``min(Nr, Nt) <= 2``, LAPACK otherwise).

    Args:
        h: Channels ``[R, Nr, Nt]`` (complex64 or complex128).
        num_streams: S <= min(Nr, Nt).
        dtype: dtype of the returned W (default: complex64 for complex64 ``h``,
            else complex128).
        precoders: False: ``w`` may be returned as None where it is extra work
            (``Nr == 2``: ``W = H^H U Sigma^-1``, ~1/3 of the call for 32 transmit
            antennas); ``lam`` and ``f`` are the same either way.

    Returns:
        ``(w [R, Nt, S], lam [R, S], f [R, Nr, S])``: orthonormal precoders,
        eigenmode gains ``lambda_s = sigma_s^2 = ||H w_s||^2`` (float64, descending)
        and effective channels ``f = H W`` (complex128; ``= U Sigma`` for Nr <= 2).
    """
    h = np.asarray(h)
    r, nr, nt = h.shape
    s = int(num_streams)
    if dtype is None:
        dtype = np.complex64 if h.dtype == np.complex64 else np.complex128
    if nr == 1:
        hd = np.ascontiguousarray(h[:, 0, :], dtype=np.complex128)
        lam = np.einsum("ri,ri->r", hd.view(np.float64), hd.view(np.float64))
        sig = np.sqrt(lam)
        zero = sig == 0
        w = np.where(zero[:, None], 1 / np.sqrt(nt), np.conj(hd) / np.where(zero, 1, sig)[:, None])
        f = sig.astype(np.complex128)[:, None, None]
        return w[:, :, None].astype(dtype, copy=False), lam[:, None], f
    if nr == 2:
        a, d, b = _gram_rows2(h)
        lam, u = _eigh2(a, d, b)
        lam, u = lam[:, :s], u[:, :, :s]
        sig = np.sqrt(lam)
        f = u * sig[:, None, :]
        if precoders:
            # W = H^H (U Sigma^-1): scale the small [R, 2, S] factor, not the product.
            us = u / np.where(sig > 0, sig, 1.0)[:, None, :]
            hc = np.conj(h).swapaxes(-1, -2)  # [R, Nt, 2]
            w = np.matmul(hc, us.astype(h.dtype)) if h.dtype == np.complex64 \
                else np.matmul(hc.astype(np.complex128, copy=False), us)
            w = w.astype(dtype, copy=False)
        else:
            w = None
        if s < 2:
            zero = sig[:, 0] == 0
            if zero.any() and w is not None:  # H = 0: any unit vector (LAPACK gives e_0)
                w[zero] = 0
                w[zero, 0, 0] = 1
            return w, lam, f
        # Weak second modes: W from the Gram has direction error ~eps / r for
        # r = sigma_2 / sigma_1 (eps of the arithmetic used) and sigma_2 a relative
        # error ~1e-16 / r^2. For r < _REFINE redo them in complex128, normalised by
        # the actual column norms and re-orthogonalised; for r < _LAPACK (incl. rank
        # deficiency) with LAPACK on just those REs.
        ratio = sig[:, 1] / np.where(sig[:, 0] > 0, sig[:, 0], 1.0)
        zero = sig[:, 0] == 0
        tiny = (ratio < _LAPACK) & ~zero
        weak = (ratio < _REFINE) & ~tiny & ~zero
        if w is None:  # only the tiny REs' gains change below
            weak = np.zeros_like(weak)
        elif zero.any():  # H = 0: lam = f = 0 already; W = [e_0, e_1] like LAPACK
            w[zero] = np.eye(nt, s, dtype=w.dtype)
        if weak.any():
            rows = np.nonzero(weak)[0]
            hb = np.conj(np.asarray(h[rows], dtype=np.complex128)).swapaxes(-1, -2)
            wb = np.matmul(hb, us[rows])  # [B, Nt, 2]
            w1 = wb[:, :, 0] / np.linalg.norm(wb[:, :, 0], axis=-1, keepdims=True)
            y = wb[:, :, 1] - np.sum(np.conj(w1) * wb[:, :, 1], axis=-1, keepdims=True) * w1
            y = y / np.linalg.norm(y, axis=-1, keepdims=True)
            w[rows] = np.stack([w1, y], axis=-1).astype(w.dtype)
        if tiny.any():
            rows = np.nonzero(tiny)[0]
            if rows.size <= _LAPACK_MAX_REs:
                ul, sl, vh = np.linalg.svd(np.asarray(h[rows], dtype=np.complex128),
                                           full_matrices=False)
                if w is not None:
                    w[rows] = np.conj(vh[:, :s, :]).swapaxes(-1, -2).astype(w.dtype)
                lam[rows] = sl[:, :s] ** 2
                f[rows] = ul[:, :, :s] * sl[:, None, :s]
            elif w is not None:
                # Many (near-)rank-1 REs (e.g. a single-path channel): w_1 from
                # H^H u_1 in complex128 (accurate), w_2 = H^H u_2 orthogonalised
                # against w_1 while it is above the rounding floor, else any unit
                # vector orthogonal to w_1. Stream 2 carries <= 1e-12 of the
                # RE's gain here, so rates are unaffected; its direction is
                # accurate to ~1e-16 / r (undefined at r = 0, as with LAPACK).
                hb = np.conj(np.asarray(h[rows], dtype=np.complex128)).swapaxes(-1, -2)
                wb = np.matmul(hb, u[rows])  # [B, Nt, 2] = H^H U
                w1 = wb[:, :, 0] / np.linalg.norm(wb[:, :, 0], axis=-1, keepdims=True)
                y = wb[:, :, 1] - np.sum(np.conj(w1) * wb[:, :, 1], axis=-1,
                                         keepdims=True) * w1
                ny = np.linalg.norm(y, axis=-1)
                ok = ny > 1e-12 * sig[rows, 0]
                j = np.argmin(np.abs(w1), axis=-1)
                e = np.zeros_like(w1)
                e[np.arange(rows.size), j] = 1.0
                e = e - np.sum(np.conj(w1) * e, axis=-1, keepdims=True) * w1
                e /= np.linalg.norm(e, axis=-1, keepdims=True)
                y = np.where(ok[:, None], y / np.where(ok, ny, 1.0)[:, None], e)
                w[rows] = np.stack([w1, y], axis=-1).astype(w.dtype)
        return w, lam, f
    if nt <= 2:
        # Gram H^H H (Nt x Nt): right singular vectors directly.
        if nt == 1:
            w = np.ones((r, 1, 1), dtype=np.complex128)
        else:
            a, d, b = _gram_rows2(np.swapaxes(h, -1, -2).conj())
            _, v = _eigh2(a, d, b)
            w = np.ascontiguousarray(v[:, :, :s])
        f = np.matmul(np.asarray(h, dtype=np.complex128), w)
        lam = np.einsum("rns,rns->rs", f.real, f.real) + np.einsum("rns,rns->rs", f.imag,
                                                                   f.imag)
        return w.astype(dtype, copy=False), lam, f
    uu, sv, vh = np.linalg.svd(np.asarray(h, dtype=np.complex128), full_matrices=False)
    w = np.conj(vh[:, :s, :]).swapaxes(-1, -2)
    return w.astype(dtype, copy=False), sv[:, :s] ** 2, uu[:, :, :s] * sv[:, None, :s]


def rate_per_re(f, interference, noise_power: float):
    """Per-RE log-det rate and MMSE SINR from effective channels (closed form for
    Nr <= 2, LAPACK otherwise).

    Args:
        f: Desired effective channels ``H W sqrt(P)`` ``[R, Nr, S]``.
        interference: Sequence of interferers' effective channels ``[R, Nr, S_i]``
            (zero where an interferer is silent).
        noise_power: sigma^2.

    Returns:
        ``(se [R] bit, sinr [R, S])`` -- ``se = max(log2 det(I + C^-1 F F^H), 0)``
        with ``C = sigma^2 I + sum_i F_i F_i^H`` and
        ``sinr_s = f_s^H (C + sum_{j != s} f_j f_j^H)^-1 f_s``.
    """
    f = np.asarray(f, dtype=np.complex128)
    r, nr, s = f.shape
    n0 = float(noise_power)
    if nr == 1:
        c = np.full(r, n0)
        for fi in interference:
            c = c + np.sum(np.abs(fi[:, 0, :]) ** 2, axis=-1)
        pw = np.abs(f[:, 0, :]) ** 2  # [R, S]
        tot = pw.sum(axis=-1)
        se = np.maximum(np.log2((c + tot) / c), 0.0)
        others = tot[:, None] - pw if s > 1 else 0.0
        return se, pw / (c[:, None] + others)
    if nr == 2:
        c00 = np.full(r, n0)
        c11 = np.full(r, n0)
        c01 = np.zeros(r, dtype=np.complex128)
        for fi in interference:
            fi = np.asarray(fi, dtype=np.complex128)
            c00 = c00 + np.sum(fi[:, 0].real ** 2 + fi[:, 0].imag ** 2, axis=-1)
            c11 = c11 + np.sum(fi[:, 1].real ** 2 + fi[:, 1].imag ** 2, axis=-1)
            c01 = c01 + np.sum(fi[:, 0] * np.conj(fi[:, 1]), axis=-1)
        f0, f1 = f[:, 0], f[:, 1]  # [R, S]
        p0 = f0.real ** 2 + f0.imag ** 2
        p1 = f1.real ** 2 + f1.imag ** 2
        x01 = f0 * np.conj(f1)
        t00 = c00 + p0.sum(axis=-1)
        t11 = c11 + p1.sum(axis=-1)
        t01 = c01 + x01.sum(axis=-1)
        det_c = c00 * c11 - (c01.real ** 2 + c01.imag ** 2)
        det_t = t00 * t11 - (t01.real ** 2 + t01.imag ** 2)
        se = np.maximum(np.log2(det_t / det_c), 0.0)
        # B_s = T - f_s f_s^H; sinr_s = f_s^H adj(B_s) f_s / det(B_s).
        b00 = t00[:, None] - p0
        b11 = t11[:, None] - p1
        b01 = t01[:, None] - x01
        det_b = b00 * b11 - (b01.real ** 2 + b01.imag ** 2)
        num = b11 * p0 + b00 * p1 - 2.0 * np.real(np.conj(f0) * b01 * f1)
        return se, np.maximum(num, 0.0) / det_b
    cov = np.broadcast_to(n0 * np.eye(nr), (r, nr, nr)).astype(complex)
    for fi in interference:
        cov = cov + fi @ np.conj(fi).swapaxes(-1, -2)
    tot = cov + f @ np.conj(f).swapaxes(-1, -2)
    _, ld_tot = np.linalg.slogdet(tot)
    _, ld_in = np.linalg.slogdet(cov)
    se = np.maximum((ld_tot - ld_in) / np.log(2.0), 0.0)
    g = np.real(np.einsum("rns,rns->rs", np.conj(f), np.linalg.solve(tot, f)))
    return se, np.where(g < 1, g / np.maximum(1 - g, 1e-300), np.inf)


def water_level(g, total_power: float, noise_power: float, weights=None) -> np.ndarray:
    """Water-filling powers for gains ``g [M] > 0`` whose entries count ``weights``
    times in the budget (``sum w_i p_i = P``); ``weights=None`` = all ones
    (one row of :func:`water_levels`)."""
    return water_levels(np.asarray(g, dtype=float)[None], total_power, noise_power,
                        weights)[0]


def water_levels(g, total_power, noise_power: float, weights=None) -> np.ndarray:
    """Water-filling of several independent budgets at once (issue #19: all links
    of one transmitter in one sort).

    Args:
        g: gains ``[B, M]`` >= 0; an entry <= 0 gets no power (so rows of
            different lengths can be padded with zeros).
        total_power: budget per row, W (scalar or ``[B]``).
        noise_power: sigma^2, W.
        weights: ``[M]`` times each entry counts in the budget
            (``sum_i w_i p_i = P``; None: all ones).

    Returns:
        Powers ``[B, M]``, W; a row without a positive gain (or budget) gets none.
    """
    g = np.asarray(g, dtype=float)
    b_, m_ = g.shape
    total = np.broadcast_to(np.asarray(total_power, dtype=float), (b_,))
    if weights is not None:
        weights = np.asarray(weights, dtype=float)
        if weights.size and np.all(weights == weights.flat[0]):
            # Uniform weights: plain water-filling with the budget per copy.
            return water_levels(g, total / weights.flat[0], noise_power)
    on = g > 0
    inv = np.full(g.shape, np.inf)
    np.divide(noise_power, g, out=inv, where=on)  # floor levels 1/SNR_i; off: inf
    if weights is None:
        inv_s = np.sort(inv, axis=1)
        levels = (total[:, None] + np.cumsum(inv_s, axis=1)) / np.arange(1, m_ + 1)
    else:
        order = np.argsort(inv, axis=1)
        inv_s = np.take_along_axis(inv, order, axis=1)
        w_s = weights[order]
        levels = (total[:, None] + np.cumsum(w_s * inv_s, axis=1)) / np.cumsum(w_s, axis=1)
    # The water level if the m best entries are on: the last m where it is
    # above the m-th floor (off entries sort last with an infinite floor).
    above = levels > inv_s
    has = above.any(axis=1) & (total > 0)
    n_on = m_ - np.argmax(above[:, ::-1], axis=1)
    level = np.where(has, levels[np.arange(b_), n_on - 1], 0.0)
    p = np.maximum(level[:, None] - inv, 0.0)  # inv = inf (off): 0
    spent = p.sum(axis=1) if weights is None else p @ weights
    # The rounding residue is removed so the budget is never exceeded.
    scale = np.minimum(1.0, total / np.where(spent > 0, spent, 1.0))
    return p * scale[:, None]
