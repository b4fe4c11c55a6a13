"""The MIMO-OFDM signals of a whole network graph in one step (paper, eqs. 1-4).

For every link ``q -> v`` of the configuration: the eq.-4 channel from the
traced paths with each device's own array, a precoder and a power
allocation that keep ``sum |x|^2 <= P_q`` over the transmitter's resource set
``R_q``, and the achievable rate with every *other* transmitter heard by
``v`` on shared resource elements treated as interference (eq. 2).

Three implementations give the same result (tests/engine/phy/test_network_fast.py,
tests/engine/phy/test_network_batched.py):

* ``method="batched"`` (default): the ``fast`` closed forms with all links of
  a step together (issue #19): one channel-synthesis pass over every link's
  paths (:meth:`NetworkPHY.channels`: one delay-phase table, one Doppler
  Taylor order, one steering-vector evaluation per device over all its links'
  paths), the rotated element positions of a device kept while its
  orientation does not change (static access points: once), and the per-RE
  precoding and rates of all links of one transmitter with the same array
  shapes stacked along the RE axis into one call each; water-filling (one
  row per link: own budget, :func:`~isac_twin.phy.link.water_levels`) and MCS
  (:meth:`~isac_twin.phy.mcs.McsRate.many`) take the stack in one call too.
  Rates equal the per-link ``fast`` ones (equal to ~1e-15 on the lab; tested
  to 1e-6 relative).
* ``method="fast"``: per link (the per-link reference of ``batched``), the channel is synthesised once, the
  per-RE SVD precoder comes from the closed-form 2 x 2 Gram eigen-decomposition
  (:func:`~isac_twin.phy.link.svd_streams`, exact; LAPACK when ``min(Nr, Nt) > 2``),
  its eigenmode gains feed water-filling directly, and the effective channels
  ``H W sqrt(P) = U Sigma sqrt(P)`` are computed once and reused for the link's
  own rate *and* as interference at the same receiver
  (:func:`~isac_twin.phy.link.rate_per_re`, closed-form 2 x 2 log-det / SINR). Only
  the REs of each transmitter's allocation are processed.
* ``method="reference"``: the straightforward composition of
  :class:`~isac_twin.phy.link.SVDPrecoder`, :class:`~isac_twin.phy.link.WaterFilling`
  and :class:`~isac_twin.phy.link.AchievableRate` with ``np.linalg`` on every RE.

Time-invariant steps (``time_invariant_tol``, fast path only): the symbols are
grouped by the pattern of all transmitters' allocations (one group for
full-grid allocations). If every path's Doppler phase drift from its group's
mean symbol time, ``2 pi |nu| max_k |t_k - t_mean|`` (:meth:`max_doppler_phase`),
is at most the tolerance (default 1e-3 rad), the channel is evaluated once per
group at ``t_mean`` and every per-RE quantity is computed once per (group,
subcarrier), weighted by the number of symbols it stands for (water-filling
included, so the budget is exact). The channel error is then at most
``tol * sum_l |b_l|`` per entry (relative ``<= tol`` for a single path), and as
the group's symbol times are symmetric about ``t_mean`` in the mean, the
first-order term of the rate error cancels in the sum over symbols: the bit
count errs by ``O(tol^2)`` relative (measured <~ 1e-7 at tol = 1e-3, see
tests/engine/phy/test_network_fast.py). A robot at 0.22 m/s at 2.4 GHz
(nu <= 1.8 Hz) with K = 14 symbols of 13.7 us gives ~1e-3 rad for one group.
``time_invariant_tol=0`` disables it. In this mode ``LinkSignal.h``/``w``/``p``
repeat the group values over the symbols (read-only broadcast views for one
group), expanded only when read (``h_by_group``/``w_by_group``/``p_by_group``
hold one value per group).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from ..contract import schema
from ..utils.threads import one_blas_thread
from .arrays import PlanarArray, r_hat
from .channel import OFDMChannel, baseband_gains, port_pair_gains, synthesize_many
from .link import (
    AchievableRate,
    EqualPower,
    Interferer,
    SVDPrecoder,
    WaterFilling,
    channel_gains,
    rate_per_re,
    svd_streams,
    water_levels,
    wideband_streams,
)
from .mcs import McsRate
from .ofdm import ResourceGrid, ResourceSet
from .units import dbm_to_watt, thermal_noise_power

__all__ = ["LinkSignal", "METHODS", "NetworkPHY"]

#: ``NetworkPHY(method=...)``: ``batched`` (default: all links of a step in one
#: stacked pass), ``fast`` (the same closed forms, one link at a time: the
#: per-link reference of ``batched``), ``reference`` (np.linalg on every RE).
METHODS = ("batched", "fast", "reference")


@dataclass(frozen=True)
class LinkSignal:
    """One link's PHY state in a step.

    The per-RE arrays (``h``, ``w``, ``p`` and their per-group forms) are
    computed or expanded on first read, not every step (issue #19): the rates
    need each link's channel only on its transmitter's resource elements and
    the precoder only where it interferes elsewhere, so the channel on the other
    symbols (the CSI message's), the precoder and the expansion over the symbols
    (a copy of ``K / G`` times the data: 42 % of the PHY time of 4 robots for
    w and p, 13-28 % for h) are left to whoever reads them. The values are
    those of the step whenever they are read.

    Attributes:
        tx, rx: device names.
        mask: the transmitter's allocation ``[K, N]``.
        rate_bps: achievable rate, bit/s (interference treated as noise).
        snr_db: mean SNR over the allocation before precoding,
            ``P_q/|R_q| * ||H||_F^2 / (Nr sigma^2)``, dB.
        sinr_db: mean post-MMSE SINR over the allocation and streams, dB.
        time_invariant: the step was computed with the time-invariant shortcut
            (``h``/``w``/``p`` then hold one value per symbol group, at the group's
            mean time; use ``NetworkPHY.channel(paths)`` or
            ``time_invariant_tol=0`` for the exact per-symbol channel, e.g. for
            Doppler sensing).
        mcs_rate_bps: the rate a modem reaches: per stream one MCS of the
            config's ``[link_adaptation]`` table over the allocation, with the
            transmitter EVM floor (:class:`~isac_twin.phy.mcs.McsRate`), bit/s.
        mcs: ``[S]`` table index per stream (-1: below the lowest entry).
        group: ``[K]`` symbol -> group index, or None (one group per symbol).
        per_re: ``per_re(name) -> array`` for ``name`` in ``"h"``, ``"w"``,
            ``"p"``: the per-group arrays, computed when called (read them
            through the attributes below, which call it once).
    """

    tx: str
    rx: str
    mask: np.ndarray
    rate_bps: float
    snr_db: float
    sinr_db: float
    time_invariant: bool = False
    mcs_rate_bps: float = float("nan")
    mcs: tuple = ()
    group: np.ndarray | None = None
    per_re: Callable[[str], np.ndarray] | None = field(default=None, repr=False,
                                                        compare=False)

    @cached_property
    def h_by_group(self) -> np.ndarray:
        """Channel ``[G, N, Nr, Nt]`` (complex64) per symbol group (``G = K``
        unless the step is time-invariant)."""
        return self.per_re("h")

    @cached_property
    def w_by_group(self) -> np.ndarray:
        """Precoder ``[G, N, Nt, S]`` per symbol group."""
        return self.per_re("w")

    @cached_property
    def p_by_group(self) -> np.ndarray:
        """Power per RE and stream ``[G, N, S]``, W."""
        return self.per_re("p")

    @cached_property
    def h(self) -> np.ndarray:
        """Channel ``[K, N, Nr, Nt]`` (complex64) on every symbol (eq. 4; with the
        time-invariant shortcut each symbol holds its group's channel, at the
        group's mean time)."""
        return self.h_by_group if self.group is None else _expand(self.h_by_group, self.group)

    @cached_property
    def w(self) -> np.ndarray:
        """Precoder ``[K, N, Nt, S]`` (fast paths: complex64 and zero off the
        transmitter's allocation, where it is not used)."""
        return self.w_by_group if self.group is None else _expand(self.w_by_group, self.group)

    @cached_property
    def p(self) -> np.ndarray:
        """Power per RE and stream ``[K, N, S]``, W."""
        return self.p_by_group if self.group is None else _expand(self.p_by_group, self.group)


class _PerRE:
    """``LinkSignal.per_re``: one zero-argument function per array name."""

    __slots__ = ("fns",)

    def __init__(self, **fns: Callable[[], np.ndarray]):
        self.fns = fns

    def __call__(self, name: str) -> np.ndarray:
        fn = self.fns.get(name)
        if fn is None:
            raise KeyError(f"per_re: expected one of {', '.join(self.fns)}, got {name!r}")
        one_blas_thread()  # (in case it is read in a process that never stepped)
        return fn()


class _Once:
    """A value computed by ``fn()`` on the first call, then kept (shared by the
    links of one stacked bucket)."""

    __slots__ = ("fn", "value")

    def __init__(self, fn: Callable[[], object]):
        self.fn, self.value = fn, None

    def __call__(self):
        if self.fn is not None:
            self.value, self.fn = self.fn(), None
        return self.value


#: polarizations the PHY models (every one the scene-folder vocabulary names)
MODELLED_POLARIZATIONS = tuple(schema.POLARIZATIONS)


def _array(cfg) -> PlanarArray:
    if cfg.polarization not in MODELLED_POLARIZATIONS:
        # isac_twin.scene.config refuses these at load; a hand-built config gets the same line.
        raise ValueError(f"array polarization {cfg.polarization!r} is not modelled "
                         f"(modelled: {', '.join(MODELLED_POLARIZATIONS)})")
    # The element pattern and polarization are in the path coefficients, applied by
    # the tracer at the array centre (isac_twin.raytrace.antenna_patterns, one
    # coefficient per port pair), as in Sionna's synthetic arrays; the steering
    # vectors carry the geometry only (each element's ports share its position).
    return PlanarArray(cfg.rows, cfg.cols, cfg.vertical_spacing, cfg.horizontal_spacing)


def _gains(lp) -> np.ndarray:
    """Baseband gains of a link: ``[L]``, or ``[L, Pr, Pt]`` per port pair."""
    return baseband_gains(lp.extra.get("a_ports", lp.a), lp.tau, lp.frequency_hz)


class NetworkPHY:
    """Callable: traced paths of all links -> :class:`LinkSignal` per link.

    Args:
        config: :class:`~isac_twin.scene.config.TwinConfig`.
        power_allocation: ``"waterfilling"`` (default) or ``"equal"``.
        precoding: ``"svd"`` (per resource element) or ``"svd_wideband"``.
        method: one of :data:`METHODS` (see the module doc).
        time_invariant_tol: Doppler phase tolerance [rad] below which a step is
            treated as time-invariant (fast path only; 0 disables).
    """

    def __init__(self, config, *, power_allocation: str = "waterfilling",
                 precoding: str = "svd", method: str = "batched",
                 time_invariant_tol: float = 1e-3) -> None:
        if method not in METHODS:
            raise ValueError(f"method: expected one of {', '.join(METHODS)}, got {method!r}")
        if not time_invariant_tol >= 0:
            raise ValueError(f"time_invariant_tol: expected >= 0 rad, got {time_invariant_tol}")
        self.method = method
        self.time_invariant_tol = float(time_invariant_tol)
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
        #: devices whose element is not iso V: their links must come with port
        #: coefficients (``extra["a_ports"]``), as the config's tracer returns them
        self._elements = {d.name: (d.array.pattern, d.array.polarization)
                          for d in config.devices
                          if (d.array.pattern, d.array.polarization) != ("iso", "V")}
        self.masks = {d.name: ResourceSet(self.grid, d.subcarriers, d.symbols, name=d.name).mask
                      for d in config.devices if d.is_tx}
        self.rate = AchievableRate(self.grid, self.noise_power, method="numpy")
        la = config.link_adaptation
        self.mcs = McsRate(la.table, la.evm_db)
        self._cache: dict = {}

    def channel(self, paths, times=None) -> np.ndarray:
        """Eq. 4 for one :class:`~isac_twin.raytrace.base.LinkPaths` -> ``[K, N, Nr, Nt]``
        (``[T, N, Nr, Nt]`` at explicit symbol ``times`` [s])."""
        from ..utils.geometry import sionna_orientation

        syn = OFDMChannel(self.grid, self.arrays[paths.rx], self.arrays[paths.tx])
        b = _gains(self._checked(paths))
        return syn(b, paths.tau, paths.doppler, paths.theta_r, paths.phi_r, paths.theta_t,
                   paths.phi_t, rx_orientation=sionna_orientation(paths.rx_orientation),
                   tx_orientation=sionna_orientation(paths.tx_orientation), times=times)

    def __call__(self, link_paths: dict) -> dict[tuple[str, str], LinkSignal]:
        """Args: ``{(tx, rx): LinkPaths}`` as the config's tracer returns them (the
        devices' element patterns applied). Returns ``{(tx, rx): LinkSignal}``."""
        for lp in link_paths.values():
            self._checked(lp)
        one_blas_thread()  # small matrices (isac_twin.utils.threads)
        if self.method == "reference":
            return self._reference(link_paths)
        return self._fast(link_paths, batched=self.method == "batched")

    def _checked(self, lp):
        """``lp`` itself, once it is known to carry its devices' elements.

        Raises:
            ValueError: a link of a device with a non-iso-V element traced without
                its elements (a backend other than ``make_tracer(config)``'s).
        """
        if lp.num_paths and "a_ports" not in lp.extra:
            odd = [n for n in (lp.tx, lp.rx) if n in self._elements]
            if odd:
                raise ValueError(
                    f"link {lp.tx}->{lp.rx}: {', '.join(odd)} has element "
                    f"{'/'.join(self._elements[odd[0]])}, but the paths carry iso-V "
                    f"coefficients only: trace with isac_twin.make_tracer(config), which "
                    f"applies the elements (isac_twin.raytrace.antenna_patterns)")
        return lp

    def _steering(self, name: str, theta, phi, orientation) -> np.ndarray:
        """Steering vectors ``[L, Nant]`` of device ``name``'s array; the rotated
        element positions are kept per device while its orientation does not
        change (static access points: computed once)."""
        arr = self.arrays[name]
        key = tuple(float(x) for x in orientation)
        hit = self._cache.get(("pos", name))
        if hit is None or hit[0] != key:
            hit = (key, arr.positions(key))
            self._cache[("pos", name)] = hit
        k = r_hat(np.asarray(theta, np.float64), np.asarray(phi, np.float64))
        return np.exp(1j * (2.0 * np.pi * (k @ hit[1].T)))

    def _all_pair_gains(self, link_paths: dict) -> dict:
        """Every link's path gains times both steering vectors (eq. 4 without the
        time-frequency kernel) -> ``{(tx, rx): (gains [L, Nr * Nt] complex128, Nr,
        Nt)}``; one steering-vector evaluation per (device, orientation) over all
        its links' paths and one baseband conversion over all links (issue #19:
        per link, the calls cost more in Python than in arithmetic)."""
        from ..utils.geometry import sionna_orientation

        lps = {lk: self._checked(lp) for lk, lp in link_paths.items()}
        ends: dict = {}  # (device, orientation) -> [(link, side, theta, phi)]
        for lk, lp in lps.items():
            for side, dev, th, ph, ori in (("r", lp.rx, lp.theta_r, lp.phi_r, lp.rx_orientation),
                                           ("t", lp.tx, lp.theta_t, lp.phi_t, lp.tx_orientation)):
                ends.setdefault((dev, sionna_orientation(ori)), []).append((lk, side, th, ph))
        steer = {}
        for (dev, ori), items in ends.items():
            a = self._steering(dev, np.concatenate([np.asarray(it[2], np.float64) for it in items]),
                               np.concatenate([np.asarray(it[3], np.float64) for it in items]), ori)
            start = 0
            for lk, side, th, _ in items:
                steer[(lk, side)] = a[start:start + len(th)]
                start += len(th)
        same = {}  # (carrier, gain shape) -> links: their baseband gains in one call
        for lk, lp in lps.items():
            a = lp.extra.get("a_ports", lp.a)
            same.setdefault((lp.frequency_hz, np.shape(a)[1:]), []).append(lk)
        bs = {}
        for (fc, _), lks in same.items():
            a = [np.asarray(lps[lk].extra.get("a_ports", lps[lk].a)) for lk in lks]
            b = baseband_gains(np.concatenate(a), np.concatenate(
                [np.asarray(lps[lk].tau, np.float64) for lk in lks]), fc)
            start = 0
            for lk, al in zip(lks, a):
                bs[lk] = b[start:start + al.shape[0]]
                start += al.shape[0]
        out = {}
        for lk in lps:
            g = port_pair_gains(bs[lk], steer[(lk, "r")], steer[(lk, "t")])
            nr, nt = g.shape[1:]
            out[lk] = (g.reshape(g.shape[0], nr * nt), nr, nt)
        return out

    def channels(self, link_paths: dict, times=None, rows: dict | None = None) -> dict:
        """Eq. 4 for every link in one pass (:func:`~isac_twin.phy.channel.synthesize_many`):
        ``{(tx, rx): LinkPaths}`` -> ``{(tx, rx): [K|T, N, Nr, Nt]}`` complex64;
        equal to :meth:`channel` per link. ``rows``: ``{(tx, rx): indices [R]}``
        of the symbols (or ``times``) to compute per link -> ``[R, N, Nr, Nt]``."""
        return self._channels(link_paths, times, rows)[0]

    def _channels(self, link_paths: dict, times, rows: dict | None):
        """:meth:`channels` and, per link, ``rest(rows) -> [R, N, Nr, Nt]`` that
        computes other rows later exactly as this pass would have (same gains,
        same Taylor bound; a row's value does not depend on the others)."""
        gs = self._all_pair_gains(link_paths)
        lps = list(link_paths.values())
        nu = max((float(np.max(np.abs(lp.doppler))) for lp in lps if len(lp.doppler)),
                 default=0.0)
        hs = synthesize_many(self.grid, [g for g, _, _ in gs.values()], [lp.tau for lp in lps],
                             [lp.doppler for lp in lps], times=times, max_doppler=nu,
                             rows=None if rows is None else [rows[lk] for lk in link_paths])
        n_ = self.grid.num_subcarriers

        def rest(lk):
            g, nr, nt = gs[lk]
            lp = link_paths[lk]
            return lambda r: synthesize_many(self.grid, [g], [lp.tau], [lp.doppler],
                                             times=times, rows=[r], max_doppler=nu
                                             )[0].reshape(len(r), n_, nr, nt)

        return ({lk: hl.reshape(hl.shape[0], n_, nr, nt)
                 for lk, hl, (_, nr, nt) in zip(link_paths, hs, gs.values())},
                {lk: rest(lk) for lk in link_paths})

    def _groups(self, txs: tuple):
        """Symbols grouped by the pattern of all transmitters' masks (cached):
        ``(group [K], masks {tx: [G, N]}, weights [G], mean times [G], span)`` with
        ``span = max_g max_{k in g} |t_k - mean_g|`` [s]."""
        key = ("groups",) + txs
        if key not in self._cache:
            t = self.grid.symbol_times
            n_ = self.grid.num_subcarriers
            sig = np.concatenate([self.masks[tx] for tx in txs], axis=1)  # [K, ntx * N]
            uniq, group, counts = np.unique(sig, axis=0, return_inverse=True,
                                            return_counts=True)
            group = np.asarray(group).reshape(-1)
            times = np.bincount(group, weights=t) / counts
            span = float(np.max(np.abs(t - times[group])))
            masks = {tx: uniq[:, i * n_:(i + 1) * n_] for i, tx in enumerate(txs)}
            self._cache[key] = (group, masks, counts.astype(float), times, span)
        return self._cache[key]

    def _layout(self, txs: tuple, invariant: bool, batched: bool) -> dict:
        """What the allocations fix for a step of transmitters ``txs`` (cached:
        masks and powers come from the config): ``masks {tx: [G, N]}``, ``g`` (G),
        ``every`` (``arange(G)``), ``rows {tx: [R]}`` (the symbols or groups a
        transmitter's channels are needed on: its own, when batched), ``overlap
        {(a, b): bool}`` and per transmitter ``tx {tx: (full, idx, idx_c, wts,
        total W, count)}``: whether it has the whole grid, its flat REs on the
        grid and on its rows (None when full), the symbols each RE stands for
        (time-invariant steps), its power budget and its RE count."""
        key = ("layout", txs, invariant, batched)
        hit = self._cache.get(key)
        if hit is not None:
            return hit
        k_, n_ = self.grid.shape
        if invariant:
            _, masks, weights_g, _, _ = self._groups(txs)
        else:
            masks, weights_g = {tx: self.masks[tx] for tx in txs}, None
        g_ = next(iter(masks.values())).shape[0] if masks else k_
        every = np.arange(g_)
        rows = {tx: (np.flatnonzero(masks[tx].any(axis=1)) if batched else every)
                for tx in txs}
        per_tx = {}
        for tx in txs:
            mask = masks[tx]
            full = bool(mask.all())
            idx = None if full else np.flatnonzero(mask)  # REs on the grid [G * N]
            idx_c = None if full else np.flatnonzero(mask[rows[tx]])  # REs of h's rows
            wts = None
            if invariant:
                wts = np.repeat(weights_g, n_) if full else weights_g[idx // n_]
            for arr in (idx, idx_c, wts):  # shared by every step: read-only
                if arr is not None:
                    arr.flags.writeable = False
            per_tx[tx] = (full, idx, idx_c, wts, float(dbm_to_watt(self.devices[tx].power_dbm)),
                          int(self.masks[tx].sum()))
        lay = dict(masks=masks, g=g_, every=every, rows=rows, tx=per_tx,
                   overlap={(a, b): bool((masks[a] & masks[b]).any()) for a in txs for b in txs})
        self._cache[key] = lay
        return lay

    def max_doppler_phase(self, link_paths: dict) -> float:
        """Largest Doppler phase drift within a symbol group,
        ``2 pi max|nu| max_k |t_k - t_mean(group of k)|`` [rad] (with one group,
        e.g. full-grid allocations, ``t_mean`` is the mid-step time)."""
        nu = max((float(np.max(np.abs(lp.doppler))) for lp in link_paths.values()
                  if len(lp.doppler)), default=0.0)
        span = self._groups(tuple(sorted({tx for tx, _ in link_paths})))[4]
        return 2 * np.pi * nu * span

    def _fast(self, link_paths: dict, batched: bool = False) -> dict[tuple[str, str], LinkSignal]:
        """The closed-form PHY. ``batched``: channels from one synthesis pass
        (:meth:`channels`) on only the symbols (groups) each transmitter uses,
        and the per-RE precoding / rate of all links of one transmitter with the
        same array shapes (and, for the rate, the same interferers' stream
        counts) stacked along the RE axis into one call each, water-filling
        (a row per link: each has its own budget) and MCS included. Otherwise one
        link at a time on every symbol (the per-link reference). Either way the
        precoders are formed only where they interfere at another receiver, and
        what the rates do not need (the channel on other symbols, the precoders,
        the per-symbol expansion) when a :class:`LinkSignal` attribute is read."""
        k_, n_ = self.grid.shape
        txs = tuple(sorted({tx for tx, _ in link_paths}))
        invariant = (self.time_invariant_tol > 0 and k_ > 1 and bool(txs)
                     and self.max_doppler_phase(link_paths) <= self.time_invariant_tol)
        if invariant:
            # One channel per symbol group, at the group's mean time (so the
            # first-order Doppler error cancels within the group); every per-RE
            # quantity is computed once per (group, subcarrier), weighted by the
            # number of symbols in the group.
            group, _, _, times, _ = self._groups(txs)
        else:
            times = group = None
        lay = self._layout(txs, invariant, batched)
        masks, g_, every, rows, overlap = (lay["masks"], lay["g"], lay["every"], lay["rows"],
                                           lay["overlap"])
        if batched:
            h, rest = self._channels(link_paths, times, {lk: rows[lk[0]] for lk in link_paths})
        else:
            h = {lk: self.channel(lp, times) for lk, lp in link_paths.items()}
            rest = {}

        def gather(hl, idx, full):
            """Channels at the flat (row, subcarrier) REs ``idx`` -> [R, Nr, Nt]."""
            t_, _, nr, nt = hl.shape
            flat = hl.reshape(t_ * n_, nr, nt)
            return flat if full else flat[idx]

        # Precoders are formed where a link interferes at another receiver (its
        # precoder aims at its own); elsewhere only on request.
        need_w = {(tx2, rx2) for (tx, rx) in h for (tx2, rx2) in h
                  if tx2 != tx and rx2 != rx and (tx2, rx) in h and overlap[(tx, tx2)]}

        # Transmit side: precoder, powers and effective channels, stacked per
        # (tx, Nr, Nt) bucket when batched (one bucket per link otherwise).
        buckets: dict = {}
        for lk, hl in h.items():
            key = (lk[0], hl.shape[2], hl.shape[3]) if batched else lk
            buckets.setdefault(key, []).append(lk)
        side = {}
        for lks in buckets.values():
            tx = lks[0][0]
            full, idx, idx_c, wts, total, count = lay["tx"][tx]
            hms = [gather(h[lk], idx_c, full) for lk in lks]
            hm = hms[0] if len(hms) == 1 else np.concatenate(hms)
            r_ = hms[0].shape[0]
            nr, nt = hm.shape[1], hm.shape[2]
            s = min(nr, nt)
            if self.precoding == "per_re":
                w, lam, f1 = svd_streams(hm, s, precoders=any(lk in need_w for lk in lks))
                if w is None:  # the same call with precoders, on request
                    w = _Once(lambda hm=hm, s=s: svd_streams(hm, s)[0])
            else:
                hd = np.asarray(hm, dtype=np.complex128)
                w0s = [wideband_streams(hd[b * r_:(b + 1) * r_], s, wts)
                       for b in range(len(lks))]
                w = np.concatenate([np.broadcast_to(w0, (r_, nt, s)) for w0 in w0s])
                f1 = hd @ w
                lam = np.sum(np.abs(f1) ** 2, axis=1)
            if self.power_allocation == "waterfilling":
                # each link its own budget: one row per link, in one sort
                pw = None if wts is None else np.broadcast_to(wts[:, None], (r_, s)).reshape(-1)
                p = water_levels(lam.reshape(len(lks), r_ * s), total, self.noise_power,
                                 pw).reshape(lam.shape)
            else:
                p = np.full(lam.shape, total / (count * s))
            f = f1 * np.sqrt(p)[:, None, :]
            # ||H||_F^2 per RE (for the SNR): the sum of all eigenmode gains.
            gain_re = lam.sum(axis=1) if self.precoding == "per_re" else \
                np.sum(np.abs(np.asarray(hm, dtype=np.complex128).reshape(hm.shape[0], -1))
                       ** 2, axis=1)
            for b, lk in enumerate(lks):
                seg = slice(b * r_, (b + 1) * r_)
                w_of = (lambda w=w, seg=seg: w()[seg]) if isinstance(w, _Once) else \
                    (lambda w=w, seg=seg: w[seg])
                side[lk] = dict(idx=idx, idx_c=idx_c, full=full, w=w_of, p=p[seg], f=f[seg],
                                wts=wts, total=total, count=count, gain=gain_re[seg])

        def on_grid(arr, d):
            """Per-RE values of a link -> [G * N, ...] (zeros off its REs)."""
            if d["full"]:
                return arr
            out = np.zeros((g_ * n_,) + arr.shape[1:], dtype=arr.dtype)
            out[d["idx"]] = arr
            return out

        # Receive side: every other transmitter heard on shared REs interferes.
        interf = {}
        for (tx, rx) in h:
            d = side[(tx, rx)]
            lst = []
            for (tx2, rx2), d2 in side.items():
                if tx2 == tx or (tx2, rx) not in h or not overlap[(tx, tx2)]:
                    continue
                if rx2 == rx:
                    fi = d2["f"]  # the same effective channel, computed once
                else:
                    hc = gather(h[(tx2, rx)], d2["idx_c"], d2["full"])
                    fi = np.matmul(np.asarray(hc, dtype=np.complex128),
                                   np.asarray(d2["w"](), dtype=np.complex128)) \
                        * np.sqrt(d2["p"])[:, None, :]
                fi = on_grid(fi, d2)
                lst.append(fi if d["full"] else fi[d["idx"]])
            interf[(tx, rx)] = lst
        rate_buckets: dict = {}
        for lk in h:
            f = side[lk]["f"]
            key = ((lk[0], f.shape[1:], tuple(fi.shape[1:] for fi in interf[lk]))
                   if batched else lk)
            rate_buckets.setdefault(key, []).append(lk)
        # Per rate bucket (one link unless batched): rates, MCS, SNR and mean SINR
        # of all its links in one pass each.
        scalars = {}
        for lks in rate_buckets.values():
            d0 = side[lks[0]]
            r_, nr = d0["f"].shape[:2]
            cat = (lambda xs: xs[0]) if len(lks) == 1 else np.concatenate
            its = [cat([interf[lk][i] for lk in lks]) for i in range(len(interf[lks[0]]))]
            se, sinr = rate_per_re(cat([side[lk]["f"] for lk in lks]), its, self.noise_power)
            b_ = len(lks)
            se, sinr = se.reshape(b_, r_), sinr.reshape(b_, r_, -1)
            gain = np.stack([side[lk]["gain"] for lk in lks])  # [B, R]
            wts = d0["wts"]
            mcs_bits, mcs = self.mcs.many(sinr, np.stack([side[lk]["p"] for lk in lks]), wts)
            ok = np.isfinite(sinr) & (sinr > 0)
            wok = ok if wts is None else wts[None, :, None] * ok
            if wts is None:
                bits, gain = se.sum(axis=1), gain.mean(axis=1) / nr
            else:
                bits, gain = se @ wts, (gain @ wts) / wts.sum() / nr
            n_ok = wok.sum(axis=(1, 2))
            sinr_mean = np.where(n_ok > 0, np.sum(wok * np.where(ok, sinr, 0.0), axis=(1, 2))
                                 / np.where(n_ok > 0, n_ok, 1.0), 0.0)
            for i, lk in enumerate(lks):
                scalars[lk] = (float(bits[i]), float(mcs_bits[i]), mcs[i], float(gain[i]),
                               float(sinr_mean[i]))

        def grid_of(arr, d):
            """Per-RE values of a link -> [G, N, ...] (zeros off its REs)."""
            a = on_grid(np.asarray(arr), d)
            return a.reshape((g_, n_) + a.shape[1:])

        def channel_on_every_row(hl, r, more):
            """The link's channel on all G rows (``hl`` holds rows ``r``)."""
            if len(r) == g_:
                return hl
            out = np.empty((g_,) + hl.shape[1:], dtype=hl.dtype)
            out[r] = hl
            miss = np.setdiff1d(every, r)
            out[miss] = more(miss)
            return out

        out = {}
        for (tx, rx), hl in h.items():
            d = side[(tx, rx)]
            bits, mcs_bits, mcs, gain, sinr_mean = scalars[(tx, rx)]
            snr = d["total"] / d["count"] * gain / self.noise_power

            arrays = _PerRE(
                h=lambda hl=hl, r=rows[tx], lk=(tx, rx): channel_on_every_row(
                    hl, r, rest.get(lk)),
                w=lambda d=d: grid_of(d["w"](), d),
                p=lambda d=d: grid_of(d["p"], d))
            out[(tx, rx)] = LinkSignal(
                tx=tx, rx=rx, mask=self.masks[tx], per_re=arrays,
                group=group if invariant else None,
                rate_bps=bits / self.grid.step_duration_s,
                snr_db=float(10 * np.log10(snr)) if snr > 0 else float("-inf"),
                sinr_db=float(10 * np.log10(sinr_mean)) if sinr_mean > 0 else float("-inf"),
                time_invariant=invariant,
                mcs_rate_bps=mcs_bits / self.grid.step_duration_s,
                mcs=tuple(int(i) for i in mcs))
        return out

    def _reference(self, link_paths: dict) -> dict[tuple[str, str], LinkSignal]:
        h = {lk: self.channel(lp) for lk, lp in link_paths.items()}
        tx_side = {}
        for (tx, rx), hl in h.items():
            mask = self.masks[tx]
            total = float(dbm_to_watt(self.devices[tx].power_dbm))
            s = min(hl.shape[2], hl.shape[3])
            w = SVDPrecoder(s, self.precoding, method="numpy")(hl, mask)
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
            mcs_bits, mcs = self.mcs(r.sinr[mask], p[mask])
            sinr = r.sinr[mask]
            sinr = sinr[np.isfinite(sinr) & (sinr > 0)]
            out[(tx, rx)] = LinkSignal(
                tx=tx, rx=rx, mask=mask,
                per_re=_PerRE(h=lambda hl=hl: hl, w=lambda w=w: w, p=lambda p=p: p),
                rate_bps=r.rate_bps,
                snr_db=float(10 * np.log10(snr)) if snr > 0 else float("-inf"),
                sinr_db=float(10 * np.log10(sinr.mean())) if sinr.size else float("-inf"),
                mcs_rate_bps=mcs_bits / self.grid.step_duration_s,
                mcs=tuple(int(i) for i in mcs))
        return out


def _expand(a: np.ndarray, group: np.ndarray) -> np.ndarray:
    """``a [G, ...]`` -> ``[K, ...]`` with ``out[k] = a[group[k]]`` (a read-only
    broadcast view when G == 1)."""
    if a.shape[0] == 1:
        return np.broadcast_to(a, (group.shape[0],) + a.shape[1:])
    return a[group]
