"""What a robot measures from one step's links: MDPs, CSI amplitudes, PDPs.

Two measurement modes (``docs/casestudy.md``):

* ``"tracer"`` (the paper's mode, on purpose a stress test of the twin): the
  MDP is the tracer's path lengths ``c * tau`` and powers, strongest first;
  CSI and PDP features are synthesized from all traced paths.
* ``"pilots"`` (realistic): the eq.-4 channel of the link
  (:meth:`isac_twin.phy.network.NetworkPHY.channel`) carries comb pilots
  (:class:`~isac_twin.phy.estimation.PilotPattern`, one port per AP antenna,
  stride ``max(min_stride, ports)``) received with white Gaussian noise at a
  given SNR; :class:`~isac_twin.phy.estimation.LSChannelEstimator` estimates the
  CSI; the MDP comes from :class:`~isac_twin.phy.estimation.MdpEstimator`
  (TLS-ESPRIT + least squares) on the raw LS values at each port's pilot
  comb, averaged over the 14 symbols, with every (port, receive antenna) as a
  snapshot. The APs' pilots are assumed orthogonal to each other. At APs
  with more than one antenna, :class:`~isac_twin.phy.directions.DelayDirectionEstimator`
  also estimates each path's departure direction from the same combs
  (feature ``"dirs"``, :attr:`Observation.paths`; in tracer mode the traced
  ``theta_t, phi_t``).

SNR in pilot mode is the mean pilot SNR per resource element and receive
antenna: ``mean |H|^2 |x|^2 / sigma^2`` over the link's antenna pairs.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..phy.arrays import PlanarArray, r_hat, sionna_rotation
from ..phy.channel import baseband_gains, cfr_at
from ..phy.directions import DelayDirectionEstimator, DelayDirectionProfile
from ..phy.estimation import LSChannelEstimator, MdpEstimator, PilotPattern, ideal_mdp
from ..phy.ofdm import ResourceGrid, ResourceSet
from ..raytrace.base import SPEED_OF_LIGHT
from ..utils.geometry import sionna_orientation

#: Decimation of the subcarriers used as kNN features (1024 / 64 = 16 subcarriers).
KNN_SUBCARRIER_STEP = 64
#: PDP sampling: path-length bins, m.
PDP_BINS_M = np.arange(0.0, 40.0, 0.5)
#: Floor of the dB features, relative to nothing (absolute |.|^2 in dB).
FEATURE_FLOOR_DB = -160.0


@dataclass
class FeatureSpec:
    """Shared settings of the features (database and measurements must agree).

    Attributes:
        grid: the OFDM grid (N subcarriers, delta_f).
        frequency_hz: carrier, Hz.
        arrays: device name -> :class:`PlanarArray`.
        knn_subcarriers: subcarrier indices of the kNN features ``[S]``.
        pdp_bins_m: path-length bins of the PDP ``[B]``, m.
        orientations: device name -> array orientation ``[yaw, pitch, roll]``
            rad (Sionna order; missing: ``(0, 0, 0)``).
    """

    grid: ResourceGrid
    frequency_hz: float
    arrays: dict
    knn_subcarriers: np.ndarray
    pdp_bins_m: np.ndarray = field(default_factory=lambda: PDP_BINS_M.copy())
    orientations: dict = field(default_factory=dict)

    @classmethod
    def from_config(cls, config, knn_step: int = KNN_SUBCARRIER_STEP) -> FeatureSpec:
        o = config.ofdm
        grid = ResourceGrid(o.num_subcarriers, o.subcarrier_spacing_hz, o.num_symbols,
                            o.cyclic_prefix_samples)
        arrays = {d.name: PlanarArray(d.array.rows, d.array.cols, d.array.vertical_spacing,
                                      d.array.horizontal_spacing) for d in config.devices}
        sc = np.arange(knn_step // 2, o.num_subcarriers, knn_step)
        orient = {d.name: sionna_orientation(d.orientation) for d in config.devices}
        return cls(grid, config.scene.frequency_hz, arrays, sc, orientations=orient)

    @property
    def knn_frequencies(self) -> np.ndarray:
        """Centred offsets of the kNN subcarriers ``[S]``, Hz."""
        return self.grid.subcarrier_frequencies[self.knn_subcarriers]


@dataclass
class Observation:
    """One measurement of all APs at one position.

    Attributes:
        lengths: ``[A, J]`` measured path lengths, m, strongest first (NaN pad).
        powers: ``[A, J]`` their powers (linear, 0 pad).
        csi_db: per AP ``[S, Nt]``: ``10 log10`` of ``|H|^2`` averaged over the
            receive antennas at the kNN subcarriers.
        pdp_db: ``[A, B]`` power-delay profile in dB at :attr:`FeatureSpec.pdp_bins_m`.
        paths: per AP a :class:`~isac_twin.phy.directions.DelayDirectionProfile`
            (path lengths, departure directions at the AP, powers) for APs
            with more than one antenna, ``None`` for single-antenna APs; empty
            when directions were not measured.
    """

    lengths: np.ndarray
    powers: np.ndarray
    csi_db: list
    pdp_db: np.ndarray
    paths: list = field(default_factory=list)


# --------------------------------------------------------------------------- features


def csi_from_paths(a, tau, frequency_hz: float, freqs_hz, rx_array: PlanarArray,
                   tx_array: PlanarArray, *, theta_r, phi_r, theta_t, phi_t,
                   rx_orientation=(0.0, 0.0, 0.0), tx_orientation=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Eq.-4 CSI of one link at selected subcarriers (one symbol, no Doppler):
    :func:`isac_twin.phy.channel.cfr_at` of the passband gains ``a``.

    Args:
        a, tau: ``[L]`` passband path gains and delays (s).
        frequency_hz: carrier, Hz.
        freqs_hz: ``[S]`` centred subcarrier offsets, Hz.
        theta_r, phi_r, theta_t, phi_t: ``[L]`` angles, rad (keyword-only: the
            order of the stored database columns differs from eq. 4's).
        rx_orientation, tx_orientation: ``[yaw, pitch, roll]`` rad (Sionna order).

    Returns:
        ``[S, Nr, Nt]`` complex128.
    """
    b = baseband_gains(np.asarray(a, complex), np.asarray(tau, float), frequency_hz)
    return cfr_at(b, tau, theta_r, phi_r, theta_t, phi_t, freqs_hz, rx_array, tx_array,
                  rx_orientation, tx_orientation)


def db(x) -> np.ndarray:
    """``10 log10`` with a floor at :data:`FEATURE_FLOOR_DB`."""
    return np.maximum(10 * np.log10(np.maximum(np.asarray(x, float), 1e-300)), FEATURE_FLOOR_DB)


def pdp_from_paths(lengths, powers, bins_m, grid: ResourceGrid) -> np.ndarray:
    """PDP of paths as the receiver's band sees it: ``sum_l p_l |D_N(d - d_l)|^2``.

    ``D_N`` is the normalised Dirichlet kernel of N subcarriers at delta_f
    (resolution ``c / (N delta_f)`` = 3.75 m at 80 MHz).

    Args:
        lengths, powers: ``[..., L]`` (NaN lengths are ignored).
        bins_m: ``[B]`` m.

    Returns:
        ``[..., B]`` linear power.
    """
    lengths = np.asarray(lengths, float)
    p = np.where(np.isfinite(lengths), np.asarray(powers, float), 0.0)
    d = np.where(np.isfinite(lengths), lengths, 0.0)
    n, df = grid.num_subcarriers, grid.subcarrier_spacing_hz
    x = (np.asarray(bins_m)[None, :] - d[..., :, None]) / SPEED_OF_LIGHT * df  # [..., L, B]
    num = np.sin(np.pi * n * x)
    den = n * np.sin(np.pi * x)
    with np.errstate(invalid="ignore", divide="ignore"):
        k = np.where(np.abs(den) < 1e-12, 1.0, num / den) ** 2
    return np.einsum("...l,...lb->...b", p, k)


def pdp_from_csi(h, bins_m, grid: ResourceGrid) -> np.ndarray:
    """PDP from CSI ``[N, M]`` (all subcarriers, M antenna pairs): mean over
    pairs of ``|(1/N) sum_n H[n] exp(+j 2 pi f_n d / c)|^2`` -> ``[B]``."""
    f = grid.subcarrier_frequencies
    e = np.exp(2j * np.pi * np.outer(np.asarray(bins_m) / SPEED_OF_LIGHT, f)) / len(f)  # [B, N]
    return np.mean(np.abs(e @ h) ** 2, axis=1)


# --------------------------------------------------------------------------- observations


def observe_tracer(links: list, spec: FeatureSpec, num_paths: int = 9) -> Observation:
    """Paper's mode: features straight from the traced paths of each AP's link.

    Args:
        links: per AP (database order) the :class:`~isac_twin.raytrace.base.LinkPaths`.
        num_paths: strongest paths in the MDP (J).
    """
    A = len(links)
    lengths = np.full((A, num_paths), np.nan)
    powers = np.zeros((A, num_paths))
    csi, pdp, paths = [], [], []
    for i, lp in enumerate(links):
        m = ideal_mdp(lp.tau, lp.a, max_paths=num_paths)
        lengths[i, :len(m)], powers[i, :len(m)] = m.distances_m, m.powers
        paths.append(traced_directions(lp, num_paths) if spec.arrays[lp.tx].num_ant > 1
                     else None)
        h = csi_from_paths(lp.a, lp.tau, lp.frequency_hz, spec.knn_frequencies,
                           spec.arrays[lp.rx], spec.arrays[lp.tx], theta_r=lp.theta_r,
                           phi_r=lp.phi_r, theta_t=lp.theta_t, phi_t=lp.phi_t,
                           rx_orientation=sionna_orientation(lp.rx_orientation),
                           tx_orientation=sionna_orientation(lp.tx_orientation))
        csi.append(db(np.mean(np.abs(h) ** 2, axis=1)))
        pdp.append(db(pdp_from_paths(SPEED_OF_LIGHT * lp.tau, np.abs(lp.a) ** 2,
                                     spec.pdp_bins_m, spec.grid)))
    return Observation(lengths, powers, csi, np.array(pdp), paths)


def front_directions(directions, orientation=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Directions ``[..., 3]`` (world axes) folded into a planar array's front
    half-space: the local boresight component (local +x) made non-negative.

    A planar array's phases see only the local y and z components, so a path
    leaving backwards (e.g. off the wall a wall-mounted AP hangs on) looks
    like its mirror image in front; compare directions after this fold.
    """
    k = np.asarray(directions, float)
    rot = sionna_rotation(orientation)
    loc = k @ rot  # world -> local (R^T k as rows)
    loc[..., 0] = np.abs(loc[..., 0])
    return loc @ rot.T


def traced_directions(lp, num_paths: int = 9) -> DelayDirectionProfile:
    """The ``num_paths`` strongest traced paths of a link as a
    :class:`DelayDirectionProfile`: lengths ``c tau`` [m], departure directions
    ``r_hat(theta_t, phi_t)`` (world axes), powers ``|a|^2``."""
    power = np.abs(np.asarray(lp.a)) ** 2
    order = np.argsort(-power, kind="stable")[:num_paths]
    return DelayDirectionProfile(SPEED_OF_LIGHT * np.asarray(lp.tau)[order],
                                 r_hat(np.asarray(lp.theta_t)[order],
                                       np.asarray(lp.phi_t)[order]), power[order])


@dataclass
class PilotSettings:
    """Pilot-mode settings.

    Attributes:
        snr_db: mean pilot SNR per RE and receive antenna, dB.
        min_stride: smallest comb stride (subcarriers); the stride is
            ``max(min_stride, ports)`` so every port keeps its own comb.
        max_paths: MdpEstimator model-order cap (paths returned).
        seed: noise seed.
    """

    snr_db: float = 20.0
    min_stride: int = 8
    max_paths: int = 9
    seed: int = 0


#: Comb pilot patterns by (transmitter, grid, ports, stride, seed) ->
#: ``(PilotPattern, symbols [P, K, N], LSChannelEstimator, CombGather)``: drawing
#: the QPSK symbols of a 32-port grid costs tens of ms, and a pattern never changes.
_COMB_PILOTS: dict = {}


@dataclass(frozen=True)
class CombGather:
    """Where a comb pattern's pilots sit, flattened over its ports (made once
    per pattern, :func:`comb_pilots`): every pilot RE carries exactly one port
    (the combs are disjoint in frequency), so the received pilots are a gather
    of the channel, not a sum over ports.

    Attributes:
        symbols: ``[Ks]`` pilot symbol indices (shared by the ports of a comb).
        subcarriers: ``[Np]`` pilot subcarriers, port 0's comb first, then port 1's, ...
        ports: ``[Np]`` the port of each.
        bounds: ``[P + 1]`` port ``p``'s pilots are ``bounds[p]:bounds[p + 1]``.
        values: ``[Ks, Np]`` the pilot symbols there (read-only).
    """

    symbols: np.ndarray
    subcarriers: np.ndarray
    ports: np.ndarray
    bounds: np.ndarray
    values: np.ndarray

    @classmethod
    def of(cls, pattern: PilotPattern, x: np.ndarray) -> CombGather:
        pos = [pattern.positions(p) for p in range(pattern.num_ports)]
        sy = pos[0][0]
        if any(not np.array_equal(s, sy) for s, _ in pos):
            raise ValueError("CombGather: the ports of a comb pattern share their symbols")
        sc = np.concatenate([c for _, c in pos])
        port = np.concatenate([np.full(len(c), p) for p, (_, c) in enumerate(pos)])
        bounds = np.concatenate([[0], np.cumsum([len(c) for _, c in pos])])
        vals = x[port[None, :], sy[:, None], sc[None, :]]  # [Ks, Np]
        vals.setflags(write=False)
        return cls(sy, sc, port, bounds, vals)

    def received(self, h: np.ndarray, noise: np.ndarray) -> np.ndarray:
        """Received pilots ``h x + noise`` at the pilot REs ``[Ks, Np, Nr]``
        from the channel ``h [K, N, Nr, P]`` and the noise ``[K, N, Nr]``."""
        hp = np.moveaxis(h[:, self.subcarriers, :, self.ports], 0, 1)  # [K, Np, Nr]
        return hp[self.symbols] * self.values[..., None] + noise[np.ix_(self.symbols,
                                                                       self.subcarriers)]


def comb_pilots(grid, name: str, num_ports: int, stride: int, seed: int):
    """The comb :class:`~isac_twin.phy.estimation.PilotPattern` of transmitter ``name``
    (``num_ports`` ports, subcarrier ``stride``, QPSK ``seed``) on ``grid``, its
    symbols ``[P, K, N]`` (read-only), its :class:`LSChannelEstimator` and its
    :class:`CombGather`, made once and kept (a few patterns per twin)."""
    key = (name, grid.num_subcarriers, grid.subcarrier_spacing_hz, grid.num_symbols,
           grid.cyclic_prefix_samples, int(num_ports), int(stride), int(seed))
    hit = _COMB_PILOTS.get(key)
    if hit is None:
        if len(_COMB_PILOTS) >= 64:
            _COMB_PILOTS.clear()
        pat = PilotPattern(ResourceSet(grid, None, None, name=name), "comb",
                           num_ports=num_ports, subcarrier_stride=stride, seed=seed)
        ls = LSChannelEstimator(pat)
        x = pat.symbols
        x.setflags(write=False)
        hit = _COMB_PILOTS[key] = (pat, x, ls, CombGather.of(pat, x))
    return hit


def observe_pilots(links: list, channels: list, spec: FeatureSpec, settings: PilotSettings,
                   num_paths: int = 9, rng: np.random.Generator | None = None,
                   features=("mdp", "csi", "pdp", "dirs")) -> Observation:
    """Realistic mode: features estimated from noisy received pilots.

    Args:
        links: per AP the :class:`LinkPaths` (only ``tx``/``rx`` names are read).
        channels: per AP the channel ``[K, N, Nr, Nt]`` (``NetworkPHY.channel``).
        settings: :class:`PilotSettings`.
        num_paths: MDP entries kept (J).
        rng: noise generator (default from ``settings.seed``).
        features: which of ``"mdp"``, ``"csi"``, ``"pdp"``, ``"dirs"`` to
            estimate (the MDP's super-resolution is the costly one); the others
            stay NaN / empty. ``"dirs"``: joint delay-direction estimation
            (:class:`~isac_twin.phy.directions.DelayDirectionEstimator`) at every
            AP with more than one antenna, into :attr:`Observation.paths`.
            ``"mdp_fallback"``: the delay-only MDP only at the APs that get no
            direction estimate (single-antenna APs, or all when ``"dirs"`` is
            not asked for): what MCA-angles reads, without the MDP of a
            32-antenna AP it never uses.

    Without ``"csi"`` and ``"pdp"`` only the raw LS values at each port's comb
    are formed (the interpolated full-grid estimate is what those two read);
    both ways give the same comb values, so the MDP and directions do not
    depend on the feature set.
    """
    rng = rng if rng is not None else np.random.default_rng(settings.seed)
    grid = spec.grid
    A = len(links)
    lengths = np.full((A, num_paths), np.nan)
    powers = np.zeros((A, num_paths))
    csi, pdp, paths = [], [], []
    full = "csi" in features or "pdp" in features
    for i, (lp, h) in enumerate(zip(links, channels)):
        k_, n_, nr, nt = h.shape
        stride = max(settings.min_stride, nt)
        pat, x, ls_est, gather = comb_pilots(grid, lp.tx, nt, stride, settings.seed)
        sig = np.vdot(h, h).real / h.size  # mean |H|^2 (no square root per entry)
        sigma2 = sig * pat.pilot_power / 10 ** (settings.snr_db / 10) if sig > 0 else 1e-30
        noise = np.sqrt(sigma2 / 2) * (rng.standard_normal((k_, n_, nr))
                                       + 1j * rng.standard_normal((k_, n_, nr)))
        yp = gather.received(h, noise)  # [Ks, Np, Nr] at the pilot REs
        # LS at each port's comb, averaged over the 14 symbols (noise / K): [Ns, Nr] per port
        scs = [pat.positions(p)[1] for p in range(nt)]
        if full:  # the interpolated grid reads the pilot REs only: the rest is noise
            y = noise
            y[np.ix_(gather.symbols, gather.subcarriers)] = yp
            hmean = ls_est(y).mean(axis=0)  # [N, Nr, P]
            combs = [hmean[sc, :, p] for p, sc in enumerate(scs)]
        else:
            ls = (yp / gather.values[..., None]).mean(axis=0)  # [Np, Nr]
            combs = [ls[b0:b1] for b0, b1 in zip(gather.bounds[:-1], gather.bounds[1:])]
        csi.append(db(np.mean(np.abs(hmean[spec.knn_subcarriers]) ** 2, axis=1))
                   if "csi" in features else np.full((len(spec.knn_subcarriers), nt), np.nan))
        pdp.append(db(pdp_from_csi(hmean.reshape(n_, -1), spec.pdp_bins_m, grid))
                   if "pdp" in features else np.full(len(spec.pdp_bins_m), np.nan))
        dirs = "dirs" in features and nt > 1
        if "dirs" in features:
            paths.append(_pilot_directions(combs, scs, spec, lp, settings, stride)
                         if dirs else None)
        if not ("mdp" in features or ("mdp_fallback" in features and not dirs)):
            continue
        # MDP: raw LS at each port's comb, snapshots = (rx, port).
        ncomb = min(len(sc) for sc in scs)
        snap = np.concatenate([c[:ncomb] for c in combs], axis=1)  # [Nc, Nr*P]
        # ESPRIT needs 2k <= M - 1 (window M): widen the window for short combs.
        sub = min(ncomb - 2, max(ncomb // 2, 2 * settings.max_paths + 2))
        est = MdpEstimator(stride * grid.subcarrier_spacing_hz, max_paths=settings.max_paths,
                           subband=sub, refine="final",
                           max_distance_m=SPEED_OF_LIGHT / (stride * grid.subcarrier_spacing_hz)
                           * 0.9)
        mdp = est(snap)
        j = min(len(mdp), num_paths)
        lengths[i, :j], powers[i, :j] = mdp.distances_m[:j], mdp.powers[:j]
    return Observation(lengths, powers, csi, np.array(pdp), paths)


def _pilot_directions(combs: list, scs: list, spec: FeatureSpec, lp, settings: PilotSettings,
                      stride: int) -> DelayDirectionProfile:
    """Joint delay-direction estimate of one AP from its LS values at each
    port's comb (``combs[p] [Ns, Nr]`` at subcarriers ``scs[p]``)."""
    nt = len(combs)
    m = min(len(c) for c in scs)
    csi = np.stack([c[:m] for c in combs], axis=2)  # [M, Nr, P]
    df = spec.grid.subcarrier_spacing_hz
    off = np.array([(c[0] - scs[0][0]) * df for c in scs])
    est = DelayDirectionEstimator(spec.arrays[lp.tx], stride * df,
                                  orientation=sionna_orientation(lp.tx_orientation),
                                  max_paths=settings.max_paths,
                                  max_distance_m=SPEED_OF_LIGHT / (stride * df) * 0.9)
    return est(csi, off)
