r"""Pilots, least-squares channel estimation and multipath delay profiles.

* :class:`PilotPattern`: comb (pilot subcarriers on every allocated symbol)
  or block (all/strided subcarriers on strided symbols) pilots inside a
  resource set, with ``P`` antenna ports kept orthogonal by frequency
  division (port ``p`` uses allocated subcarriers ``j`` with
  ``j % stride == p``).
* :class:`LSChannelEstimator`: ``H_hat = y / x`` on pilot REs, then linear
  interpolation over subcarriers and symbols (edges held constant) to every RE
  of the resource set. Error at pilots is ``sigma^2 / |x|^2``.
* Multipath delay profile (MDP, fingerprint of MCA localization): path
  lengths ``d = c tau`` [m] with powers, sorted by decreasing power.
  :func:`ideal_mdp` takes the tracer's delays; :class:`MdpEstimator`
  estimates them from CSI with TLS-ESPRIT over subcarriers (frequency
  smoothing + forward-backward averaging, model order by MDL/AIC with a cap),
  because one IFFT bin is ``c / (N delta_f)`` = 3.75 m at 80 MHz.

Frequency model used by the estimator (same as :mod:`isac_twin.phy.channel`):
``h[n] = sum_l c_l exp(-j 2 pi f_n tau_l)``, ``f_n`` centred subcarrier
offsets, so adjacent subcarriers rotate by ``z_l = exp(-j 2 pi delta_f tau_l)``;
delays are unambiguous in ``[0, 1/delta_f)`` (3837 m at 78.125 kHz).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ._checks import complex_array, positive_float, positive_int, real_array
from .ofdm import ResourceSet
from .units import SPEED_OF_LIGHT

__all__ = ["PilotPattern", "LSChannelEstimator", "MultipathDelayProfile",
           "ideal_mdp", "MdpEstimator", "noise_power_from_delay_tail"]


@dataclass(frozen=True, eq=False)
class PilotPattern:
    """Pilot positions and values inside one transmitter's resource set.

    Args:
        resource_set: Where the transmitter may place pilots.
        kind: ``"comb"`` (pilot subcarriers every ``subcarrier_stride`` on all
            allocated symbols) or ``"block"`` (pilot symbols every
            ``symbol_stride`` allocated symbols, all subcarriers of the set
            shared by the ports).
        num_ports: P orthogonal pilot ports (transmit antennas or streams).
        subcarrier_stride: Comb spacing in allocated subcarriers; must be
            >= num_ports. Ignored for ``"block"`` (stride = num_ports there).
        symbol_stride: Block spacing in allocated symbols (``"block"`` only).
        pilot_power: |x|^2 of every pilot RE [W].
        seed: Seed of the unit-modulus QPSK pilot sequence.
    """

    resource_set: ResourceSet
    kind: str = "comb"
    num_ports: int = 1
    subcarrier_stride: int = 4
    symbol_stride: int = 7
    pilot_power: float = 1.0
    seed: int = 0
    _pos: list = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if self.kind not in ("comb", "block"):
            raise ValueError(f"pilot kind must be 'comb' or 'block', got {self.kind!r}")
        positive_int("num_ports", self.num_ports)
        positive_int("subcarrier_stride", self.subcarrier_stride)
        positive_int("symbol_stride", self.symbol_stride)
        positive_float("pilot_power", self.pilot_power)
        sc = self.resource_set.subcarrier_indices
        sy = self.resource_set.symbol_indices
        stride = self.subcarrier_stride if self.kind == "comb" else self.num_ports
        if self.kind == "comb" and self.subcarrier_stride < self.num_ports:
            raise ValueError(f"subcarrier_stride ({self.subcarrier_stride}) must be "
                             f">= num_ports ({self.num_ports}) for orthogonal ports")
        pos = []
        for port in range(self.num_ports):
            scp = sc[port::stride]
            syp = sy if self.kind == "comb" else sy[::self.symbol_stride]
            if scp.size == 0:
                raise ValueError(f"resource set {self.resource_set.name!r} is too "
                                 f"narrow for pilot port {port}")
            pos.append((syp, scp))
        object.__setattr__(self, "_pos", pos)

    def positions(self, port: int) -> tuple[np.ndarray, np.ndarray]:
        """Pilot ``(symbol_indices, subcarrier_indices)`` of ``port``; the
        port's pilot REs are their Cartesian product."""
        return self._pos[port]

    @property
    def mask(self) -> np.ndarray:
        """Pilot masks ``[P, K, N]`` (bool)."""
        k, n = self.resource_set.grid.shape
        m = np.zeros((self.num_ports, k, n), dtype=bool)
        for p, (sy, sc) in enumerate(self._pos):
            m[p][np.ix_(sy, sc)] = True
        return m

    @property
    def symbols(self) -> np.ndarray:
        """Pilot values ``[P, K, N]`` complex128: QPSK with ``|x|^2 =
        pilot_power`` on the port's pilot REs, zero elsewhere."""
        rng = np.random.default_rng(self.seed)
        k, n = self.resource_set.grid.shape
        qpsk = np.exp(1j * (np.pi / 4 + np.pi / 2 * rng.integers(0, 4, (self.num_ports, k, n))))
        return qpsk * np.sqrt(self.pilot_power) * self.mask


def _interp_axis(values: np.ndarray, known: np.ndarray, target: np.ndarray,
                 axis: int) -> np.ndarray:
    """Linear interpolation of ``values`` (sampled at sorted ``known``) onto
    ``target`` along ``axis``; constant outside ``[known[0], known[-1]]``."""
    if known.size == 1:
        return np.repeat(np.take(values, [0], axis=axis), target.size, axis=axis)
    idx = np.clip(np.searchsorted(known, target, side="right") - 1, 0, known.size - 2)
    x0, x1 = known[idx], known[idx + 1]
    wgt = np.clip((target - x0) / (x1 - x0), 0.0, 1.0)
    shape = [1] * values.ndim
    shape[axis] = target.size
    wgt = wgt.reshape(shape)
    return np.take(values, idx, axis=axis) * (1 - wgt) + np.take(values, idx + 1, axis=axis) * wgt


class LSChannelEstimator:
    """Least-squares channel estimator with linear interpolation.

    Args:
        pattern: The transmitter's pilot pattern.

    Call: ``y [K, N, Nr]`` (received grid containing the pilots) ->
    ``H_hat [K, N, Nr, P]``: estimate of the channel seen by each pilot port
    on every RE of the resource set (zero outside it).
    """

    def __init__(self, pattern: PilotPattern) -> None:
        if not isinstance(pattern, PilotPattern):
            raise ValueError("pattern must be a PilotPattern")
        self.pattern = pattern
        self._x = pattern.symbols

    def __call__(self, y) -> np.ndarray:
        y = complex_array("y", y, ndim=3)
        rs = self.pattern.resource_set
        k, n = rs.grid.shape
        if y.shape[:2] != (k, n):
            raise ValueError(f"y must have shape [K, N, Nr] = [{k}, {n}, *], got {list(y.shape)}")
        nr = y.shape[2]
        out = np.zeros((k, n, nr, self.pattern.num_ports), dtype=np.complex128)
        sy_all, sc_all = rs.symbol_indices, rs.subcarrier_indices
        for port in range(self.pattern.num_ports):  # few ports; all else vectorised
            sy, sc = self.pattern.positions(port)
            ls = y[np.ix_(sy, sc)] / self._x[port][np.ix_(sy, sc)][..., None]  # [Ks, Ns, Nr]
            full = _interp_axis(ls, sc, sc_all, axis=1)
            full = _interp_axis(full, sy, sy_all, axis=0)
            out[np.ix_(sy_all, sc_all, np.arange(nr), [port])] = full[..., None]
        return out


@dataclass(frozen=True)
class MultipathDelayProfile:
    """MDP of a link: path lengths and powers, strongest first.

    Attributes:
        distances_m: Path lengths ``d = c tau`` ``[L]`` [m].
        powers: Path powers ``[L]`` (|gain|^2, linear; units of the input).
    """

    distances_m: np.ndarray
    powers: np.ndarray

    @property
    def delays_s(self) -> np.ndarray:
        """Delays ``[L]`` [s]."""
        return self.distances_m / SPEED_OF_LIGHT

    def __len__(self) -> int:
        return int(self.distances_m.size)


def _sorted_mdp(dist: np.ndarray, power: np.ndarray, max_paths: int | None,
                min_relative_power_db: float | None) -> MultipathDelayProfile:
    order = np.argsort(-power, kind="stable")
    dist, power = dist[order], power[order]
    if min_relative_power_db is not None and power.size:
        keep = power >= power[0] * 10 ** (-abs(min_relative_power_db) / 10)
        dist, power = dist[keep], power[keep]
    if max_paths is not None:
        dist, power = dist[:max_paths], power[:max_paths]
    return MultipathDelayProfile(dist, power)


def ideal_mdp(tau, b, max_paths: int | None = None,
              min_relative_power_db: float | None = None) -> MultipathDelayProfile:
    """MDP straight from the tracer.

    Args:
        tau: Path delays ``[L]`` [s].
        b: Path gains ``[L]`` (complex or real amplitude), or ``[L, ...]``
            per antenna pair (powers are averaged over the trailing axes).
        max_paths: Keep at most this many strongest paths.
        min_relative_power_db: Drop paths weaker than the strongest by more
            than this many dB.
    """
    tau = real_array("tau", tau, ndim=1, nonnegative=True)
    b = complex_array("b", b)
    if b.shape[:1] != tau.shape:
        raise ValueError(f"b must have L={tau.size} entries on axis 0, got {list(b.shape)}")
    power = np.mean(np.abs(b.reshape(tau.size, -1)) ** 2, axis=1) if tau.size else np.zeros(0)
    return _sorted_mdp(SPEED_OF_LIGHT * tau, power, max_paths, min_relative_power_db)


#: :func:`noise_power_from_delay_tail`: delays further than this from the strongest
#: tap are taken to carry no path (indoor: 60 m of excess path; the lab's longest
#: depth-3 path is ~30 m)
MAX_EXCESS_DELAY_S = 200e-9


def noise_power_from_delay_tail(h, subcarrier_offsets_hz, *,
                                max_excess_delay_s: float = MAX_EXCESS_DELAY_S) -> float:
    """Noise variance of a channel estimate from its delay-domain tail.

    A real receiver's trick (channel sounders threshold their delay profiles the
    same way): over ``K`` evenly spaced subcarriers the channel is a few paths
    within ``max_excess_delay_s`` of each other, so after a Hann-windowed inverse
    DFT the taps further than that (circularly) from the strongest tap of the
    delay profile hold noise only. Their mean power over the window's energy is
    the noise variance per subcarrier sample. What leaks from the paths (the
    window's sidelobes fall 18 dB per octave) sets the floor of a noise-free
    channel (~-80 dB of its power with a path 16 taps away).

    Args:
        h: ``[..., K]`` complex CSI (any leading axes: antenna pairs, snapshots;
            they share the delay profile's peak and average the estimate).
        subcarrier_offsets_hz: ``[K]`` evenly spaced subcarrier frequencies, Hz.
        max_excess_delay_s: delays around the peak holding paths, s.

    Returns:
        The noise variance per complex sample, ``E|n|^2``, in the units of ``|h|^2``.

    Raises:
        ValueError: uneven subcarriers, or too few for a tail (the inverse DFT's
            period ``1/spacing`` must exceed ``2 * max_excess_delay_s`` by two taps).
    """
    f = real_array("subcarrier_offsets_hz", subcarrier_offsets_hz, ndim=1)
    h = complex_array("h", h)
    k = f.size
    if h.ndim < 1 or h.shape[-1] != k:
        raise ValueError(f"h must be [..., K={k}] (the subcarriers last), got {list(h.shape)}")
    df = np.diff(f)
    if k < 8 or not np.allclose(df, df[0], rtol=1e-6, atol=0.0) or df[0] <= 0:
        raise ValueError(f"noise_power_from_delay_tail: needs >= 8 evenly spaced, increasing "
                         f"subcarriers, got {k} with spacings {np.unique(df)[:4]} Hz")
    tap_s = 1.0 / (k * df[0])
    guard = int(np.ceil(max_excess_delay_s / tap_s))
    if k - 2 * guard - 1 < 2:
        raise ValueError(f"noise_power_from_delay_tail: {k} subcarriers {df[0]:g} Hz apart "
                         f"resolve {tap_s * 1e9:.3g} ns over {1e9 / df[0]:.4g} ns, no tail "
                         f"beyond +-{max_excess_delay_s * 1e9:g} ns of the peak")
    w = np.hanning(k + 2)[1:-1]  # no zero ends: every subcarrier counts
    taps = np.fft.ifft(h.reshape(-1, k) * w, axis=-1) * k  # sum_k w_k h_k e^{+j...}
    profile = np.mean(np.abs(taps) ** 2, axis=0)
    peak = int(np.argmax(profile))
    dist = np.abs((np.arange(k) - peak + k // 2) % k - k // 2)  # circular tap distance
    tail = dist > guard
    return float(np.mean(profile[tail]) / np.sum(w ** 2))


#: smoothing windows up to this size get a full ``eigh`` of their covariance
#: (faster than the randomised subspace iteration there: 43 vs 381 us at 16,
#: 0.54 vs 0.73 ms at 64 on the lab machine)
_DIRECT_EIGH_MAX = 96

#: residual energy, relative to the CSI's, below which a fit is exact in float64
#: (eps^2 ~ 5e-32 per sample; a margin for the refinement's own rounding)
_RSS_FLOOR = 1e-24


def _vp_refine(h, fc, d, *, max_nfev: int, xtol: float = 1e-8, ftol: float = 1e-8) -> np.ndarray:
    """Path lengths minimising the variable-projection residual
    ``||(I - E E^+) h||_F^2``, ``E[n, l] = exp(-j 2 pi fc_n d_l)``, by
    Levenberg-Marquardt with Kaufman's Jacobian (MINPACK's ``lmder`` stopping
    rules: relative cost change or step below ``ftol`` / ``xtol``).

    Everything is formed from ``[k, k]`` and ``[k, S]`` products (no
    ``[N S, k]`` Jacobian, no per-evaluation least-squares solver): with
    ``G = E^H E``, ``c = G^-1 E^H h``, ``r = h - E c`` and ``D = dE/dd``,
    ``J^T J = Re(D^H P D * conj(c c^H))`` (``P = I - E G^-1 E^H``) and
    ``J^T r = -Re(sum_s conj(c) * (D^H r))``.

    Args:
        h: ``[N, S]`` complex samples (unit RMS is best).
        fc: ``[N]`` sample frequencies over the speed of light [cycles / m].
        d: ``[k]`` starting path lengths [m].
        max_nfev: cost evaluations allowed.

    Returns:
        ``[k]`` refined path lengths [m] (the start if no step lowered the cost).
    """
    w = -2j * np.pi * np.asarray(fc, float)  # [N]
    d = np.asarray(d, float).copy()

    def evaluate(x):
        e = np.exp(np.outer(w, x))  # [N, k]
        eh = e.conj().T
        try:
            gi = np.linalg.inv(eh @ e)  # G^-1
        except np.linalg.LinAlgError:
            return None
        c = gi @ (eh @ h)  # [k, S]
        r = h - e @ c
        cost = float(np.vdot(r, r).real)
        return (e, eh, gi, c, r, cost) if np.isfinite(cost) else None

    cur = evaluate(d)
    if cur is None:
        return d
    nfev, lam = 1, 1e-3
    while nfev < max_nfev:
        e, eh, gi, c, r, cost = cur
        de = w[:, None] * e  # dE/dd  [N, k]
        dh = de.conj().T
        a = dh @ de - (dh @ e) @ gi @ (eh @ de)  # D^H P D
        jtj = np.real(a * np.conj(c @ c.conj().T))
        grad = -np.real(np.sum(np.conj(c) * (dh @ r), axis=1))
        scale = np.maximum(np.diag(jtj), 1e-12 * max(float(np.max(np.diag(jtj))), 1e-300))
        moved = False
        while nfev < max_nfev:
            try:
                step = -np.linalg.solve(jtj + lam * np.diag(scale), grad)
            except np.linalg.LinAlgError:
                step = None
            trial = None
            if step is not None and np.all(np.isfinite(step)):
                trial = evaluate(d + step)
                nfev += 1
            if trial is not None and trial[5] < cost:
                d, cur, moved = d + step, trial, True
                lam = max(lam * 0.1, 1e-12)
                break
            lam *= 10.0
            if lam > 1e12:
                break
        if not moved:
            break
        if (cost - cur[5] <= ftol * cost
                or np.max(np.abs(step)) <= xtol * (np.max(np.abs(d)) + xtol)):
            break
    return d


class MdpEstimator:
    """Super-resolution MDP estimator: TLS-ESPRIT over subcarriers, refined
    by non-linear least squares, model order by an information criterion.

    Steps: (1) frequency-smoothed, forward-backward averaged covariance of
    length-``subband`` windows of the CSI (decorrelates coherent paths);
    (2) its ``max_paths`` leading eigenvectors; (3) for every order
    ``k = 1..max_paths``: TLS-ESPRIT delays, then a Levenberg-Marquardt fit
    of the delays (amplitudes projected out) to all N subcarriers (approaches the
    Cramer-Rao bound that ESPRIT alone misses for close paths); (4) the order
    minimising the data-domain criterion ``2 N S ln(RSS_k / (N S)) +
    penalty(k)`` (``"mdl"``: ``k (1 + 2S) ln(2 N S)``; ``"aic"``:
    ``2 k (1 + 2S)``), or a fixed ``int`` order.

    Robustness (an order is a candidate only if its fit is physical; an
    order that is not counts as non-improving):

    * refinement is bounded: a delay the least-squares fit moves by more
      than one resolution cell ``c / (N delta_f)`` from its ESPRIT start is
      an escape, and the order keeps its unrefined ESPRIT fit;
    * near-coincident roots (two lengths closer than ``min_separation``
      resolution cells whose amplitudes cancel: ``|c_i + c_j|^2`` below a
      tenth of ``|c_i|^2 + |c_j|^2``) are merged, i.e. that order is refused
      and the lower order, which holds the merged component, stands;
    * a component whose fitted power exceeds ``max_power_ratio`` times the
      measured mean power ``mean |csi|^2`` is refused: it only exists by
      cancelling another one (the degenerate pairs of the issue, +40 dB);
    * ``dynamic_range_db``: an order whose weakest component is more than
      this many dB below its strongest is refused, so the order stops
      growing with SNR once the criterion starts fitting the weak diffuse
      tail (which no fingerprint holds).

    Args:
        subcarrier_spacing_hz: delta_f [Hz] of the CSI samples.
        max_paths: Cap on the model order (paths returned), e.g. 9.
        order: ``"mdl"``, ``"aic"`` or a fixed ``int`` order.
        subband: Smoothing window length M [subcarriers]; default ``N // 2``
            (largest aperture). Smaller is faster and less accurate.
        forward_backward: Forward-backward averaging of the covariance.
        refine: Run the least-squares refinement (step 3) at every order
            (``True``), only on the order the criterion chose from the
            ESPRIT fits (``"final"``: about 6x faster, for per-fix budgets),
            or never (``False``).
        max_distance_m: Drop estimates beyond this path length (aliases).
        min_separation: Near-coincidence threshold [resolution cells
            ``c / (N delta_f)``]; 0.1 = 37.5 cm at 80 MHz.
        max_power_ratio: Largest plausible component power relative to the
            measured mean power ``mean |csi|^2``.
        dynamic_range_db: Largest power spread of the components [dB];
            ``None`` switches the rule off.

    Call: ``csi [N]`` or ``[N, S]`` (S snapshots: antennas and/or symbols
    flattened on axis 1; paths share delays, not amplitudes), optional
    ``frequencies_hz [N]`` (uniform spacing delta_f; default centred
    ``(n - N//2) delta_f``) -> :class:`MultipathDelayProfile`, strongest
    first. Powers are the fitted ``|c_l|^2`` averaged over snapshots, in the
    units of ``|csi|^2``.
    """

    def __init__(self, subcarrier_spacing_hz: float, max_paths: int = 9,
                 order: str | int = "mdl", subband: int | None = None,
                 forward_backward: bool = True, refine: bool | str = True,
                 max_distance_m: float | None = None, min_separation: float = 0.1,
                 max_power_ratio: float = 4.0,
                 dynamic_range_db: float | None = 25.0) -> None:
        self.df = positive_float("subcarrier_spacing_hz", subcarrier_spacing_hz)
        self.max_paths = positive_int("max_paths", max_paths)
        if not (order in ("mdl", "aic") or (isinstance(order, (int, np.integer))
                                              and not isinstance(order, bool) and order >= 1)):
            raise ValueError(f"order must be 'mdl', 'aic' or an int >= 1, got {order!r}")
        self.order = order
        self.subband = None if subband is None else positive_int("subband", subband)
        self.forward_backward = bool(forward_backward)
        if refine not in (True, False, "final"):
            raise ValueError(f"refine must be True, False or 'final', got {refine!r}")
        self.refine = refine
        self.max_distance_m = (None if max_distance_m is None
                               else positive_float("max_distance_m", max_distance_m))
        if not (np.isfinite(min_separation) and 0 <= min_separation < 1):
            raise ValueError(f"min_separation must be in [0, 1) resolution cells, "
                             f"got {min_separation!r}")
        self.min_separation = float(min_separation)
        self.max_power_ratio = positive_float("max_power_ratio", max_power_ratio)
        self.dynamic_range_db = (None if dynamic_range_db is None
                                 else positive_float("dynamic_range_db", dynamic_range_db))

    def _signal_subspace(self, h: np.ndarray, kmax: int) -> np.ndarray:
        """Leading ``kmax`` eigenvectors ``[M, kmax]`` (strongest first) of
        the smoothed covariance of ``h [N, S]``."""
        n = h.shape[0]
        msub = self.subband or n // 2
        msub = max(min(msub, n - 1), 2 * kmax + 1)  # TLS-ESPRIT needs M - 1 >= 2k
        win = np.lib.stride_tricks.sliding_window_view(h, msub, axis=0)  # [J, S, M]
        # Many snapshots (e.g. 2 x 32 antennas) already decorrelate the paths:
        # thin the windows so the covariance costs O(M^2 * 2048), not O(M^2 J S).
        step = int(np.ceil(win.shape[0] * win.shape[1] / 2048))
        win = win[::step]
        # Contiguous copy: BLAS on the strided view is ~10x slower.
        x = np.ascontiguousarray(win.reshape(-1, msub).T)  # [M, J*S]
        cov = x @ np.conj(x.T) / x.shape[1]
        if self.forward_backward:
            cov = 0.5 * (cov + np.conj(cov[::-1, ::-1]))
        if msub <= _DIRECT_EIGH_MAX:  # small: all eigenvectors, exact and cheaper
            val, vec = np.linalg.eigh(cov)
            return vec[:, np.argsort(-val)[:kmax]]
        # Randomised subspace iteration for the few leading eigenvectors:
        # LAPACK's subset drivers and ARPACK are slow on the clustered noise
        # eigenvalues of this matrix; the signal/noise gap makes this converge
        # in a few iterations. Fixed seed -> deterministic.
        p = min(kmax + 10, msub)
        q = np.random.default_rng(0).standard_normal((msub, p)).astype(cov.dtype)
        for _ in range(8):
            q, _ = np.linalg.qr(cov @ q)
        val, small = np.linalg.eigh(np.conj(q.T) @ cov @ q)
        vec = q @ small
        return vec[:, np.argsort(-val)[:kmax]]

    def _esprit(self, es: np.ndarray) -> np.ndarray:
        """TLS-ESPRIT delays ``[k]`` [s] from a signal subspace ``[M, k]``."""
        k = es.shape[1]
        e12 = np.concatenate([es[:-1], es[1:]], axis=1)
        _, _, vh = np.linalg.svd(e12, full_matrices=False)
        v = np.conj(vh.T)
        psi = -v[:k, k:] @ np.linalg.inv(v[k:, k:])
        z = np.linalg.eigvals(psi)
        # Adjacent subcarriers rotate by exp(-j 2 pi delta_f tau).
        return np.mod(-np.angle(z) / (2 * np.pi * self.df), 1.0 / self.df)

    def _circular_m(self, dtau: np.ndarray) -> np.ndarray:
        """``|dtau|`` as path length [m], modulo the alias period ``c / delta_f``."""
        period = 1.0 / self.df
        return SPEED_OF_LIGHT * np.abs((dtau + period / 2) % period - period / 2)

    def _plausible(self, tau: np.ndarray, amp: np.ndarray, cell: float) -> bool:
        """Whether a fit of the unit-RMS CSI is physical (see the class doc)."""
        power = np.mean(np.abs(amp) ** 2, axis=1)
        if power.max() > self.max_power_ratio:  # mean |h|^2 is 1 at unit RMS
            return False
        if (self.dynamic_range_db is not None
                and power.min() < power.max() * 10 ** (-self.dynamic_range_db / 10)):
            return False
        if tau.size > 1 and self.min_separation > 0:
            gap = self._circular_m(tau[:, None] - tau[None, :])
            gap[np.diag_indices(tau.size)] = np.inf
            for i, j in zip(*np.nonzero(np.triu(gap < self.min_separation * cell))):
                # Near-coincident roots that cancel (the pair's sum holds less than
                # a tenth of their separate powers) are one component split in two.
                joint = np.mean(np.abs(amp[i] + amp[j]) ** 2)
                if joint < 0.1 * (power[i] + power[j]):
                    return False
        return True

    @staticmethod
    def _fit_amplitudes(h, f, tau):
        steer = np.exp(-2j * np.pi * np.outer(f, tau))  # [N, k]
        amp, *_ = np.linalg.lstsq(steer, h, rcond=None)  # [k, S]
        rss = float(np.sum(np.abs(h - steer @ amp) ** 2))
        return amp, rss

    def _refine(self, h, f, tau, h_fit):
        """Levenberg-Marquardt on the path lengths [m] by variable projection
        (:func:`_vp_refine`): amplitudes are eliminated by least squares, so the
        problem has k unknowns whatever the number of snapshots S. The fit
        runs on ``h_fit`` (``h`` compressed to its dominant column space);
        the returned amplitudes and RSS are for the full ``h``."""
        d = _vp_refine(h_fit, f / SPEED_OF_LIGHT, SPEED_OF_LIGHT * tau,
                       max_nfev=30 * (tau.size + 1))
        tau = np.mod(d / SPEED_OF_LIGHT, 1.0 / self.df)
        amp, rss = self._fit_amplitudes(h, f, tau)
        return tau, amp, rss

    def __call__(self, csi, frequencies_hz=None) -> MultipathDelayProfile:
        h = complex_array("csi", csi)
        if h.ndim == 1:
            h = h[:, None]
        if h.ndim != 2:
            raise ValueError(f"csi must have shape [N] or [N, S], got {list(np.shape(csi))}")
        n, s = h.shape
        if n < 4:
            raise ValueError(f"csi needs at least 4 subcarriers, got {n}")
        if frequencies_hz is None:
            f = (np.arange(n) - n // 2) * self.df
        else:
            f = real_array("frequencies_hz", frequencies_hz, shape=(n,))
            if not np.allclose(np.diff(f), self.df, rtol=1e-6, atol=0):
                raise ValueError("frequencies_hz must be uniformly spaced by "
                                 f"subcarrier_spacing_hz={self.df}")
        if not np.any(h):
            return MultipathDelayProfile(np.zeros(0), np.zeros(0))
        # Work at unit RMS: physical CSI (~1e-5) would mis-scale the LM steps.
        scale = float(np.sqrt(np.mean(np.abs(h) ** 2)))
        h = h / scale
        kmax = min(self.max_paths, n // 2 - 1)
        orders = [min(int(self.order), kmax)] if not isinstance(self.order, str) \
            else range(1, kmax + 1)
        es = self._signal_subspace(h, max(orders))
        # Snapshot compression for the refinement: the dominant column space
        # of h keeps every path's contribution; RSS is re-evaluated on all of h.
        h_fit = h
        if s > kmax + 1:
            u, sv, _ = np.linalg.svd(h, full_matrices=False)
            h_fit = u[:, :kmax + 1] * sv[:kmax + 1]
        best = None
        worse = 0
        cell = SPEED_OF_LIGHT / (n * self.df)  # resolution [m]
        for k in orders:  # <= max_paths small fits; stop after 2 non-improving orders
            if worse >= 2:
                break
            tau = self._esprit(es[:, :k])
            amp, rss = self._fit_amplitudes(h, f, tau)
            if self.refine is True:
                tau_r, amp_r, rss_r = self._refine(h, f, tau, h_fit)
                if np.all(self._circular_m(tau_r - tau) <= cell) and rss_r <= rss:
                    tau, amp, rss = tau_r, amp_r, rss_r
            if best is not None and not self._plausible(tau, amp, cell):
                worse += 1
                continue
            rss = max(rss, 1e-300)
            free = k * (1 + 2 * s)
            pen = free * np.log(2 * n * s) if self.order != "aic" else 2.0 * free
            crit = 2 * n * s * np.log(rss / (n * s)) + pen
            if best is None or crit < best[0]:
                best = (crit, tau, amp)
                worse = 0
            else:
                worse += 1
            # An order whose fit already leaves only float64 rounding (the CSI is at
            # unit RMS, energy n*s) explains everything: any higher order only fits
            # rounding noise, which the criterion, on log(rss), would still reward.
            if rss <= _RSS_FLOOR * n * s:
                break
        _, tau, amp = best
        if self.refine == "final":
            _, rss0 = self._fit_amplitudes(h, f, tau)
            tau_r, amp_r, rss_r = self._refine(h, f, tau, h_fit)
            if (np.all(self._circular_m(tau_r - tau) <= cell) and rss_r <= rss0
                    and self._plausible(tau_r, amp_r, cell)):
                tau, amp = tau_r, amp_r
        power = np.mean(np.abs(amp) ** 2, axis=1) * scale ** 2
        dist = SPEED_OF_LIGHT * tau
        if self.max_distance_m is not None:
            keep = dist <= self.max_distance_m
            dist, power = dist[keep], power[keep]
        return _sorted_mdp(dist, power, self.max_paths, None)
