"""Where a calibration trace's candidate paths come from.

Sionna's ``PathSolver`` runs in stages: a candidate generator (which chains of
interactions a path may take), then the image method and the field calculator on
those candidates. The forward model (:mod:`.forward_model`) runs the last two
itself; :class:`Candidates` gives it, per link, either

* Sionna's candidate generator at every trace (its sampled candidates, as
  ``PathSolver``'s; deterministic: the same candidates at the same geometry), or
  the candidates of the round's first trace kept (:attr:`Candidates.freeze`), or
* with ``SolverSettings.chains``, the transmitter's chains (every chain of
  ``samples_per_src`` branching rays, enumerated when :meth:`Candidates.refresh`
  asked for it, each tried to every receiver by the image method), as the twin's
  chain tracer finds paths (:mod:`isac_twin.raytrace.chains`),

padded to a buffer of fixed size per link (:attr:`Candidates.buffer_sizes`):
Sionna's kernels bake the number of candidates in, and a number that changes with
every move recompiled them (13-16 s of LLVM per evaluation on the lab).
"""

from __future__ import annotations

import logging

import numpy as np

log = logging.getLogger(__name__)

#: ``max_num_paths_per_src`` of the candidate generator (Sionna's default).
MAX_CANDIDATES = 1_000_000

#: Sionna's deterministic candidate generator (``PathSolver(deterministic=True)``) keeps,
#: per chain of planes, the ray of the lowest index instead of whichever thread wins a
#: race on its hash table, so it runs on every thread and gives the same candidates on
#: every call (lab, 2 cores: 0.14 s, against 0.33 s for the default generator, which had
#: to run on one thread to be repeatable). Its memory grows with depth x rays x snapshots
#: (one 64-bit hash per lane); above this many lanes the default generator runs instead,
#: on one thread.
DETERMINISTIC_LANES = 1 << 26

#: With ``SolverSettings.chains``: a receiver is given the chains that mirror geometry
#: allows (:class:`~isac_twin.raytrace.source_chains.MirrorFilter`) with this margin, m,
#: around each reflecting plane's triangles: the objects move between enumerations
#: (the calibration's offsets are a few cm), and a chain the filter drops is never
#: traced. Lab: about 1/7 of the (chain, receiver) pairs at 1 mm.
CHAIN_FILTER_MARGIN = 0.1

def path_solver(settings, snapshots: int):
    """Sionna's ``PathSolver`` of a calibration whose links have at most ``snapshots``
    receivers: ``(solver, deterministic)``, ``deterministic`` whether its candidate
    generator is Sionna's deterministic one (see :data:`DETERMINISTIC_LANES`); its loops
    are evaluated (symbolic loops do not backpropagate)."""
    import sionna.rt as rt

    lanes = settings.max_depth * settings.samples_per_src * snapshots
    deterministic = lanes <= DETERMINISTIC_LANES
    if not deterministic:
        log.info("calibrate: %d x %d rays x %d snapshots is more than the deterministic "
                 "candidate generator's %d lanes; the default generator runs on one "
                 "thread", settings.max_depth, settings.samples_per_src, snapshots,
                 DETERMINISTIC_LANES)
    solver = rt.PathSolver(deterministic=deterministic)
    solver.loop_mode = "evaluated"  # symbolic loops do not backpropagate
    return solver, deterministic


class Candidates:
    """The candidates of each link's traces, padded to a fixed size per link.

    Args:
        sc: the forward model's ``sionna.rt.Scene``.
        settings: :class:`~isac_twin.calibration.forward_model.SolverSettings`.
        solver, deterministic: :func:`path_solver`'s.
        links: number of links (transmitters).
    """

    def __init__(self, sc, settings, solver, deterministic: bool, links: int):
        import drjit as dr
        import mitsuba as mi

        self._dr, self._mi = dr, mi
        self.sc, self.settings, self.solver = sc, settings, solver
        #: True: Sionna's deterministic candidate generator on every thread; False: the
        #: default one on one thread (see :data:`DETERMINISTIC_LANES`).
        self.deterministic = deterministic
        #: Keep the candidate chains of the next trace for the following ones (the
        #: image method and field calculator still run at the current geometry and
        #: materials): the sampled candidates change with a sub-millimetre move
        #: (lab: +1.5 dB^2 for 0.9 mm of one rack, a path no ray found any more),
        #: which stalls the line search. A trust-box fit sets it per round.
        #: The kept chains' reflection points stay where the first trace found them,
        #: a second-order approximation (1 cm / 1 deg later: median 0.01 dB, at most a
        #: few tenths of a dB in a fade); reported values are traced afresh.
        self.freeze = False
        self._kept: list | None = None
        #: with ``settings.chains``: per link, its transmitter's chains and the
        #: (chain, receiver) pairs, enumerated at the first trace after
        #: :meth:`refresh` (fit rounds, polish, hop, result call it)
        self._chains: list = [None] * links
        #: chain enumerations so far (each: every link's transmitter)
        self.chain_refreshes = 0
        #: Candidate buffer entries of every evaluation, per link (0: sized by the first).
        self.buffer_sizes = [0] * links
        #: Evaluations that found more candidates than the buffer held (it grew:
        #: Dr.Jit recompiled the evaluation's kernels once).
        self.buffer_regrows = 0

    @property
    def buffer_size(self) -> int:
        """Candidate buffer entries of every evaluation, all links (0 before the first)."""
        return sum(self.buffer_sizes)

    def refresh(self) -> None:
        """New candidates at the next trace, at the geometry then: with
        ``settings.chains`` the transmitters' chains are enumerated again (the kept
        chains' reflection points stay where their rays found them: second order in a
        move), else the kept candidates of :attr:`freeze` are dropped."""
        self._chains = [None] * len(self._chains)
        self._kept = None

    def release(self) -> None:
        """Stop keeping candidates (:attr:`freeze` off) and drop those kept."""
        self.freeze, self._kept = False, None

    def each_link(self, groups, model) -> list:
        """``[model(group, candidates, used) for each link]``: each link's candidates
        (``used`` marks those that count: not padding, not a hidden line of sight)
        given to ``model`` as they are made, one link after the other."""
        frozen = self._kept if self.freeze else None
        out, kept = [], []
        for j, grp in enumerate(groups):
            buf, used, k = self._link(j, grp, None if frozen is None else frozen[j])
            out.append(model(grp, buf, used))
            kept.append(k)
        self._kept = kept if self.freeze else None
        return out

    def _grow(self, j: int, n: int) -> int:
        """Link ``j``'s buffer size for ``n`` candidates (grown by half when they no
        longer fit, counted in :attr:`buffer_regrows`)."""
        if n > self.buffer_sizes[j]:
            if self.buffer_sizes[j]:
                self.buffer_regrows += 1
            self.buffer_sizes[j] = max(1024, int(1.5 * n))
        return self.buffer_sizes[j]

    def _link(self, j: int, grp, buf) -> tuple:
        """Link ``j``'s candidates, padded: ``(candidates, used, kept)``; ``buf``: that
        link's kept candidates (None: trace new ones); ``kept``: what to keep of them
        (None with chains: they are kept until :meth:`refresh`)."""
        dr, mi = self._dr, self._mi
        s, sc, solver = self.settings, self.sc, self.solver
        (src, _, _), (tgt, _, _) = grp.src, grp.tgt
        if s.chains:
            from ..raytrace.solver_core import chain_candidates

            chains, ci, ti, pad = self._link_chains(j, grp)
            buf, unused = chain_candidates(sc.mi_scene, chains, ci, ti, src, tgt, s.max_depth,
                                           True, pad)
            return buf, ~unused, None
        if buf is None:
            # the default generator keeps one candidate per chain of planes, whichever
            # ray's triangle wins a race on its hash table; with two threads the kept
            # triangle (and so the float32 image of a coplanar face) varied between
            # calls (lab: 3 different mismatches of 6 calls at the same values), so it
            # runs on one thread; the deterministic one runs on every thread
            threads = dr.thread_count()
            if not self.deterministic:
                dr.set_thread_count(1)
            try:
                buf = solver._candidate_generator(
                    mi_scene=sc.mi_scene, src_positions=src, tgt_positions=tgt,
                    samples_per_src=s.samples_per_src, max_num_paths_per_src=MAX_CANDIDATES,
                    max_depth=s.max_depth, los=True, specular_reflection=True,
                    diffuse_reflection=False, refraction=s.refraction, diffraction=False,
                    edge_diffraction=False, seed=s.seed)
                buf.schedule()
                dr.eval()
            finally:
                dr.set_thread_count(threads)
            buf.shrink()
        kept = buf
        n = int(buf.buffer_size)
        size = self._grow(j, n)
        buf = buf.gather(mi.UInt(np.concatenate([np.arange(n), np.zeros(size - n, int)])
                                 .astype(np.uint32)))
        used = mi.Bool(np.arange(size) < n)
        dr.make_opaque(used)
        return buf, used, kept

    def _link_chains(self, j: int, grp) -> tuple:
        """Link ``j``'s chains (:func:`~isac_twin.raytrace.solver_core.chain_arrays`) and its
        (chain, receiver) pairs, padded to :attr:`buffer_sizes`: ``(chains, chain_idx,
        target_idx, pad)``, enumerated at the current geometry when refreshed."""
        from ..raytrace.chains import ChainStore
        from ..raytrace.planes import PlaneIndex
        from ..raytrace.solver_core import chain_arrays
        from ..raytrace.source_chains import MirrorFilter, shoot_chains

        if self._chains[j] is None:
            mi, s, sc = self._mi, self.settings, self.sc

            def points(p):
                return np.stack([np.asarray(c.numpy(), np.float64) for c in p], 1)

            src = points(grp.src[0])
            planes = PlaneIndex(sc.mi_scene)
            store = ChainStore(s.max_depth, planes)
            store.add_columns(shoot_chains(sc.mi_scene, planes, src, s.samples_per_src,
                                           s.max_depth, specular=True,
                                           refraction=s.refraction))
            per_target = MirrorFilter(planes, src, store.columns(),
                                      margin=CHAIN_FILTER_MARGIN)(points(grp.tgt[0]))
            n = sum(len(k) for k in per_target)
            size = self._grow(j, n)
            ci = np.zeros(size, np.uint32)
            ti = np.zeros(size, np.uint32)
            if n:
                ci[:n] = np.concatenate(per_target)
                ti[:n] = np.repeat(np.arange(len(per_target), dtype=np.uint32),
                                   [len(k) for k in per_target])
            pad = np.ones(size, np.uint32)
            pad[:n] = 0
            arrays = [mi.UInt(ci), mi.UInt(ti), mi.UInt(pad)]
            self._dr.make_opaque(*arrays)
            self._chains[j] = (chain_arrays(store.columns(), s.max_depth), *arrays)
            if j == 0:
                self.chain_refreshes += 1
        return self._chains[j]
