"""Sionna RT backend: one solver call traces every tx/rx pair.

:class:`SionnaTracer` puts every device that appears in a requested link into
the Sionna scene once (as a ``Transmitter`` and/or a ``Receiver`` with a
single element at the array centre with the two isotropic basis patterns
of :func:`~isac_twin.raytrace.solver_core.basis_patterns`, ``synthetic_array=True``:
every path's 2 x 2 transfer matrix), moves them on later calls instead of recreating
them, and traces through :class:`~isac_twin.raytrace.solver_core.SolverCore`
(Sionna's own stages; truncation detected and retried by
:func:`~isac_twin.raytrace.raw.grow_cap`) or, by default, through chain reuse
(:mod:`isac_twin.raytrace.chains`).
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Mapping

import numpy as np

from ..scene.config import TracerConfig
from .antenna_patterns import apply_elements
from .base import DevicePose, Link, LinkPaths, resolve_links, sionna_orientation, validate_poses
from .chains import ChainTracer
from .raw import RawPaths, grow_cap, link_paths
from .solver_core import SolverCore, load_sionna_rt

__all__ = ["MAX_CAP_DOUBLINGS", "SionnaTracer"]

log = logging.getLogger(__name__)

#: A truncated trace is retried with the cap doubled at most this many times.
MAX_CAP_DOUBLINGS = 6

class SionnaTracer:
    """Tracer backend on Sionna RT's ``PathSolver`` (see :class:`~isac_twin.raytrace.base.Tracer`).

    Args:
        config: ``[tracer]`` settings. ``deterministic=True`` selects Sionna's
            deterministic candidate generator (same seed -> same paths);
            ``seed`` seeds the ray sampler.
        on_truncation: ``"grow"`` (default) retries a truncated trace with the
            cap doubled (up to ``2**MAX_CAP_DOUBLINGS`` times the configured cap)
            and logs a warning; ``"raise"`` raises
            :class:`~isac_twin.raytrace.base.TruncationError` at once.

    With ``config.uses_chains`` (the default) calls go through chain reuse
    (:class:`~isac_twin.raytrace.chains.ChainTracer`): uplinks to access points
    are traced as downlinks and reversed, and a call whose sources moved
    since the previous one is traced directly (:attr:`direct_calls`).

    Call:
        ``tracer(scene, poses, links=None) -> {(tx, rx): LinkPaths}``.
    """

    def __init__(self, config: TracerConfig | None = None, *, on_truncation: str = "grow",
                 legacy: bool = False):
        if on_truncation not in ("grow", "raise"):
            raise ValueError(f"on_truncation: expected 'grow' or 'raise', got {on_truncation!r}")
        self.config = config or TracerConfig()
        self.on_truncation = on_truncation
        self.core = SolverCore(self.config, legacy=legacy)
        #: Chain reuse (``tracer.method``; see :mod:`isac_twin.raytrace.chains`),
        #: None when tracing directly.
        self.chains = None
        if self.config.uses_chains and not legacy:
            # Each receiver gets the chains mirror geometry allows (about a
            # seventh of them in the lab), the evaluation is frozen, and the
            # varying pair counts are padded to a few sizes (chains.pad_pairs),
            # each recorded once.
            self.chains = ChainTracer(self.core, freeze=True)
        #: Where each source of chain reuse was at its last call (name -> [3] m).
        self._source_positions: dict[str, np.ndarray] = {}
        #: Calls traced by shoot-and-bounce (all of them without chain reuse;
        #: with it, calls whose transmitters had moved).
        self.direct_calls = 0
        self._tx: dict[str, object] = {}
        self._rx: dict[str, object] = {}
        self.last_raw: RawPaths | None = None

    # Sionna names: a txrx device may be both a transmitter and a receiver.
    @staticmethod
    def _tx_name(n: str) -> str:
        return f"tx:{n}"

    @staticmethod
    def _rx_name(n: str) -> str:
        return f"rx:{n}"

    def _sync_devices(self, sc, tx_names: list[str], rx_names: list[str],
                      poses: Mapping[str, DevicePose]) -> None:
        rt = load_sionna_rt()
        if sc.tx_array is not self.core.basis_array:
            sc.tx_array = self.core.basis_array
        if sc.rx_array is not self.core.basis_array:
            sc.rx_array = self.core.basis_array
        want_tx = [self._tx_name(n) for n in tx_names]
        want_rx = [self._rx_name(n) for n in rx_names]
        have_tx, have_rx = list(sc.transmitters), list(sc.receivers)
        same = (have_tx == want_tx and have_rx == want_rx
                and all(sc.transmitters[self._tx_name(n)] is self._tx.get(n) for n in tx_names)
                and all(sc.receivers[self._rx_name(n)] is self._rx.get(n) for n in rx_names))
        if not same:
            for n in have_tx + have_rx:
                sc.remove(n)
            for n in tx_names:
                if n not in self._tx:
                    self._tx[n] = rt.Transmitter(self._tx_name(n), position=poses[n].position)
            for n in rx_names:
                if n not in self._rx:
                    self._rx[n] = rt.Receiver(self._rx_name(n), position=poses[n].position)
            sc.add([self._tx[n] for n in tx_names] + [self._rx[n] for n in rx_names])
        for n, dev in [(n, self._tx[n]) for n in tx_names] + [(n, self._rx[n]) for n in rx_names]:
            p = poses[n]
            dev.position = p.position
            # orientation stays zero: the trace is in world bases, the
            # devices' orientations enter only ``a`` (SolverCore)
            dev.velocity = p.velocity

    def __call__(self, scene, poses: Mapping[str, DevicePose],
                 links: Iterable[Link] | None = None) -> dict[Link, LinkPaths]:
        links = resolve_links(scene.config, links)
        tx_names = list(dict.fromkeys(t for t, _ in links))
        rx_names = list(dict.fromkeys(r for _, r in links))
        validate_poses(scene, poses, dict.fromkeys(tx_names + rx_names))
        sc = scene.sionna
        self._sync_devices(sc, tx_names, rx_names, poses)
        raw = None
        src_names, tgt_names, flipped = tx_names, rx_names, set()
        if self.chains is not None:
            # Reciprocity: an uplink (robot -> access point) is traced as the
            # downlink and reversed, so that the sources, whose chains are
            # enumerated once, stay the static access points.
            kinds = {d.name: d.kind for d in scene.config.devices}
            flipped = {(tx, rx) for tx, rx in links
                       if kinds.get(rx) == "access_point" and kinds.get(tx) != "access_point"}
            oriented = [(rx, tx) if (tx, rx) in flipped else (tx, rx) for tx, rx in links]
            c_src = list(dict.fromkeys(t for t, _ in oriented))
            c_tgt = list(dict.fromkeys(r for _, r in oriented))
            sources = np.array([poses[n].position for n in c_src], float)
            # A source that stands elsewhere than at its last call has moved; a
            # call with another subset of the sources (e.g. one reversed link)
            # has not.
            moved = any(n in self._source_positions
                        and not np.array_equal(self._source_positions[n], q)
                        for n, q in zip(c_src, sources))
            self._source_positions.update(zip(c_src, sources))
            if moved:  # the enumerated chains belong to the source positions
                flipped = set()
            else:
                raw = self.chains.trace(
                    sc, sources, [poses[n].position for n in c_tgt],
                    source_orientations=[sionna_orientation(poses[n].orientation)
                                         for n in c_src],
                    source_velocities=[poses[n].velocity for n in c_src],
                    target_orientations=[sionna_orientation(poses[n].orientation)
                                         for n in c_tgt],
                    target_velocities=[poses[n].velocity for n in c_tgt],
                    context=(id(scene), scene.revision))
                src_names, tgt_names = c_src, c_tgt
        if raw is None:
            self.direct_calls += 1

            def trace(cap: int) -> RawPaths:
                if self.core.legacy:
                    return self.core.solve_scene(
                        sc, cap, [sionna_orientation(poses[n].orientation) for n in tx_names],
                        [sionna_orientation(poses[n].orientation) for n in rx_names])
                return self.core.solve_endpoints(
                    sc, [poses[n].position for n in tx_names],
                    [poses[n].position for n in rx_names], cap,
                    source_orientations=[sionna_orientation(poses[n].orientation)
                                         for n in tx_names],
                    source_velocities=[poses[n].velocity for n in tx_names],
                    target_orientations=[sionna_orientation(poses[n].orientation)
                                         for n in rx_names],
                    target_velocities=[poses[n].velocity for n in rx_names])

            cap = self.config.max_num_paths_per_src
            raw, _ = grow_cap(trace, cap, cap << MAX_CAP_DOUBLINGS,
                              what=f"links {links}", raise_at_once=self.on_truncation == "raise")
        self.last_raw = raw
        f = scene.config.scene.frequency_hz
        out: dict[Link, LinkPaths] = {}
        for tx, rx in links:
            src, tgt = (rx, tx) if (tx, rx) in flipped else (tx, rx)
            lp = link_paths(raw, tgt_names.index(tgt), src_names.index(src), src, tgt,
                            poses[src], poses[tgt], f)
            out[(tx, rx)] = lp.reversed() if (tx, rx) in flipped else lp
        return apply_elements(scene.config, out)
