"""Sionna RT backend: one ``PathSolver`` call traces every tx/rx pair.

:class:`SionnaTracer` puts every device that appears in a requested link into
the Sionna scene once (as a ``Transmitter`` and/or a ``Receiver`` with a
single isotropic, vertically polarized element at the array centre,
``synthetic_array=True``), moves them on later calls instead of recreating
them, runs one solver call and picks the links out of the
``[num_rx, num_tx, num_paths]`` tensors.

Truncation. Sionna's candidate generator stores at most
``max_num_paths_per_src`` candidates per source and drops the rest without a
word (``sb_candidate_generator.py``: the per-source counter is incremented
for every candidate, but only those below the cap are stored;
``sb_deterministic.py`` enforces the same budget). Nothing in the returned
``Paths`` tells. :class:`SolverCore` therefore wraps the solver's candidate
generator and counts the stored candidates per source
(``paths_buffer.source_indices[:paths_counter]``) before the image method
runs: a source that stored exactly the cap may have lost candidates, and the
trace is reported as truncated. Callers then retry with a larger cap (or fewer
receivers) or raise :class:`~engine.raytrace.base.TruncationError`.

Speed (see ``bench/bench_retrace.py``). :class:`SolverCore` runs the stages of
``PathSolver.__call__`` itself (Sionna 2.2: candidate generator, image
method, field calculator) and differs from it in two ways that do not change
the result (bit-identical in deterministic mode; ``legacy=True`` runs the
original code path for comparison):

- it reads the flat ``PathsBuffer`` into numpy (:func:`_buffer_to_numpy`)
  instead of building Sionna's ``Paths``, whose scatter kernels bake the path
  count as a literal: every call with a new path count compiled three LLVM
  kernels (~5 ms each) and ran ~25 extra kernels;
- it allocates a candidate buffer sized from the candidates actually seen
  (at least :data:`MIN_BUFFER_PER_SRC` per source, re-run with a larger one
  if it overflows) rather than ``max_num_paths_per_src`` (10**6 per source by
  default: ~800 MB of memset per call), while pinning the specular-chain hash
  table to the size Sionna would use for the requested cap, so the candidates
  are the same.

Mitsuba variant: Sionna selects it on import (CUDA when available, else
LLVM); nothing here forces one.
"""

from __future__ import annotations

import logging
import threading
import types
from collections.abc import Iterable, Mapping
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

from engine.config import TracerConfig
from engine.raytrace.base import (DevicePose, Link, LinkPaths, TruncationError,
                                  empty_link, resolve_links, sionna_orientation,
                                  validate_poses)

log = logging.getLogger(__name__)

#: A truncated trace is retried with the cap doubled at most this many times.
MAX_CAP_DOUBLINGS = 6

#: Smallest candidate buffer per source that :class:`SolverCore` allocates
#: (see "Buffer size" in :class:`SolverCore`).
MIN_BUFFER_PER_SRC = 4096

_TABLE_LOCK = threading.Lock()


@contextmanager
def _spec_table_size(size: int):
    """Pin the size of Sionna's specular-chain hash table (per source).

    Sionna sizes it ``max(max_num_paths_per_src, MIN_SPEC_COUNT_SIZE)``, read
    from the class attribute ``SBCandidateGenerator.MIN_SPEC_COUNT_SIZE`` (both
    generators). Raising that attribute for the duration of a call decouples
    the table from the candidate buffer.
    """
    from sionna.rt.path_solvers.sb_candidate_generator import SBCandidateGenerator

    with _TABLE_LOCK:
        old = SBCandidateGenerator.MIN_SPEC_COUNT_SIZE
        SBCandidateGenerator.MIN_SPEC_COUNT_SIZE = int(size)
        try:
            yield
        finally:
            SBCandidateGenerator.MIN_SPEC_COUNT_SIZE = old


def _spec_table_default(cap: int) -> int:
    from sionna.rt.path_solvers.sb_candidate_generator import SBCandidateGenerator

    return max(int(cap), int(SBCandidateGenerator.MIN_SPEC_COUNT_SIZE))


def _rt():
    import engine._llvm

    engine._llvm.configure_llvm()
    import sionna.rt as rt

    return rt


class _CountingGenerator:
    """Wraps a Sionna candidate generator; records stored candidates per source."""

    def __init__(self, inner):
        self.inner = inner
        self.counts: np.ndarray | None = None
        self.cap: int | None = None

    def __call__(self, **kw):
        import drjit as dr

        paths = self.inner(**kw)
        paths.schedule()
        dr.eval()
        n = int(dr.minimum(dr.max(paths.paths_counter), paths.buffer_size)[0]) \
            if paths.buffer_size else 0
        num_src = dr.width(kw["src_positions"])
        # Transfer only the stored candidates, not the whole buffer.
        idx = dr.gather(type(paths.source_indices), paths.source_indices,
                        dr.arange(type(paths.source_indices), n)) if n else None
        src = np.asarray(idx.numpy(), dtype=np.int64) if n else np.zeros(0, np.int64)
        self.counts = np.bincount(src, minlength=num_src)
        self.cap = int(kw["max_num_paths_per_src"])
        return paths

    @property
    def truncated(self) -> bool:
        """Whether a source stored as many candidates as the cap allows."""
        return bool(self.counts is not None and self.counts.size
                    and self.counts.max() >= self.cap)


@dataclass
class RawPaths:
    """Numpy copy of a Sionna ``Paths`` (synthetic arrays, single-element devices).

    Attributes (``R`` receivers, ``T`` transmitters, ``P`` max paths, ``D`` depth):
        valid: ``[R, T, P]`` bool.
        a: ``[R, T, P]`` complex128 passband coefficients.
        tau, doppler, theta_t, phi_t, theta_r, phi_r: ``[R, T, P]`` float64.
        interactions: ``[R, T, P, D]`` int32.
        vertices: ``[R, T, P, D, 3]`` float32.
        candidates_per_source: ``[T]`` candidates the generator stored.
        cap: the ``max_num_paths_per_src`` used.
    """

    valid: np.ndarray
    a: np.ndarray
    tau: np.ndarray
    doppler: np.ndarray
    theta_t: np.ndarray
    phi_t: np.ndarray
    theta_r: np.ndarray
    phi_r: np.ndarray
    interactions: np.ndarray
    vertices: np.ndarray
    candidates_per_source: np.ndarray
    cap: int

    @property
    def truncated(self) -> bool:
        return bool(self.candidates_per_source.size
                    and self.candidates_per_source.max() >= self.cap)

    def link(self, r: int, t: int) -> dict[str, np.ndarray]:
        """Valid paths of receiver ``r`` / transmitter ``t``, sorted by delay."""
        m = self.valid[r, t]
        tau = self.tau[r, t][m]
        order = np.lexsort((-np.abs(self.a[r, t][m]), tau))
        out = {k: getattr(self, k)[r, t][m][order]
               for k in ("a", "tau", "doppler", "theta_t", "phi_t", "theta_r", "phi_r",
                         "interactions", "vertices")}
        return out

    @classmethod
    def empty(cls, num_rx: int, num_tx: int, depth: int, counts: np.ndarray,
              cap: int) -> "RawPaths":
        """No path for any pair (``P = 0``)."""
        z = np.zeros((num_rx, num_tx, 0))
        return cls(valid=z.astype(bool), a=z.astype(complex), tau=z, doppler=z, theta_t=z,
                   phi_t=z, theta_r=z, phi_r=z,
                   interactions=np.zeros((num_rx, num_tx, 0, depth), np.int32),
                   vertices=np.zeros((num_rx, num_tx, 0, depth, 3), np.float32),
                   candidates_per_source=counts, cap=cap)


def _points(v, n: int, cls):
    """``[n, 3]`` numpy (None: zeros) -> Mitsuba ``Point3f``/``Vector3f``.

    The components are copied into Dr.Jit's own (64-byte aligned) memory:
    kernels that read numpy's memory directly record its alignment in their
    IR, so a differently aligned array compiled the same kernel again (seen on
    about one live retrace in five)."""
    import drjit as dr
    import mitsuba as mi

    v = np.zeros((n, 3), np.float32) if v is None else np.asarray(v, np.float32).reshape(n, 3)
    comps = [dr.copy(mi.Float(np.ascontiguousarray(v[:, i]))) for i in range(3)]
    dr.eval(*comps)
    return cls(*comps)


def _paths_to_numpy(paths, num_rx: int, num_tx: int, depth: int,
                    counts: np.ndarray, cap: int) -> RawPaths:
    tau = np.asarray(paths.tau.numpy(), np.float64).reshape(num_rx, num_tx, -1)
    p = tau.shape[-1]
    d = max(1, depth)
    if p == 0:
        return RawPaths.empty(num_rx, num_tx, d, counts, cap)
    ar, ai = paths.a
    a = (np.asarray(ar.numpy(), np.float64) + 1j * np.asarray(ai.numpy(), np.float64))
    f = lambda x: np.asarray(x.numpy(), np.float64).reshape(num_rx, num_tx, p)  # noqa: E731
    inter = np.asarray(paths.interactions.numpy()).reshape(-1, num_rx, num_tx, p)
    vert = np.asarray(paths.vertices.numpy(), np.float32).reshape(-1, num_rx, num_tx, p, 3)
    inter = np.moveaxis(inter, 0, -1).astype(np.int32)
    vert = np.array(np.moveaxis(vert, 0, -2), copy=True)
    vert[inter == 0] = 0.0  # Sionna leaves stale coordinates in unused slots
    return RawPaths(
        valid=np.asarray(paths.valid.numpy(), bool).reshape(num_rx, num_tx, p),
        a=a.reshape(num_rx, num_tx, p), tau=tau, doppler=f(paths.doppler),
        theta_t=f(paths.theta_t), phi_t=f(paths.phi_t),
        theta_r=f(paths.theta_r), phi_r=f(paths.phi_r),
        interactions=inter, vertices=vert,
        candidates_per_source=counts, cap=cap)


def _buffer_to_numpy(buf, src_vel, tgt_vel, wavelength, num_rx: int, num_tx: int,
                     depth: int, counts: np.ndarray, cap: int) -> RawPaths:
    """Flat ``PathsBuffer`` (after ``discard_invalid``) -> :class:`RawPaths`.

    Equivalent to building Sionna's ``Paths`` (synthetic single-element arrays)
    and reading its tensors, without it: ``Paths`` scatters into
    ``[depth, rx, tx, max_num_paths]`` tensors whose kernels bake the path
    count as a literal (an LLVM compile, ~5 ms each, three per call whenever the
    count changes) and costs a few ms of Python tracing. Here the per-path
    quantities (angles and Doppler as in ``Paths._build_from_buffer``) are
    evaluated in one ``dr.eval`` and arranged into ``[R, T, P]`` with numpy;
    within a link, paths keep their buffer order. Invalid slots are zero.
    """
    import drjit as dr
    import mitsuba as mi

    from sionna.rt.utils import theta_phi_from_unit_vec

    d = max(1, depth)
    n = int(buf.buffer_size) if buf.tau is not None else 0
    if n == 0:
        return RawPaths.empty(num_rx, num_tx, d, counts, cap)
    src_i, tgt_i = buf.source_indices, buf.target_indices
    k_tx, k_rx = buf.k_tx, buf.k_rx
    theta_t, phi_t = theta_phi_from_unit_vec(k_tx)
    theta_r, phi_r = theta_phi_from_unit_vec(k_rx)
    # Paths._finalize_doppler_shift_compute
    v_tx = dr.gather(mi.Vector3f, src_vel, src_i)
    v_rx = dr.gather(mi.Vector3f, tgt_vel, tgt_i)
    doppler = buf.doppler + dr.dot(k_tx, v_tx) / wavelength - dr.dot(-k_rx, v_rx) / wavelength
    a = buf.a[0][0]
    out = [src_i, tgt_i, dr.real(a), dr.imag(a), buf.tau, doppler, theta_t, phi_t,
           theta_r, phi_r, buf.interaction_types.array, buf.vertices_x.array,
           buf.vertices_y.array, buf.vertices_z.array]
    dr.eval(*out)
    (src_i, tgt_i, ar, ai, tau, dop, tht, pht, thr, phr, inter, vx, vy, vz) = \
        [x.numpy() for x in out]
    pair = tgt_i.astype(np.int64) * num_tx + src_i.astype(np.int64)
    order = np.argsort(pair, kind="stable")
    per_pair = np.bincount(pair, minlength=num_rx * num_tx)
    p = int(per_pair.max())
    start = np.concatenate([[0], np.cumsum(per_pair)[:-1]])
    slot = np.empty(n, np.int64)
    slot[order] = np.arange(n) - start[pair[order]]
    r, t = tgt_i.astype(np.int64), src_i.astype(np.int64)

    def place(v, dtype):
        o = np.zeros((num_rx, num_tx, p) + v.shape[1:], dtype)
        o[r, t, slot] = v
        return o

    inter = inter.reshape(n, d).astype(np.int32)
    vert = np.stack([vx, vy, vz], -1).reshape(n, d, 3).astype(np.float32)
    vert[inter == 0] = 0.0  # Sionna leaves stale coordinates in unused slots
    f64 = np.float64
    return RawPaths(
        valid=place(np.ones(n, bool), bool),
        a=place(ar.astype(f64) + 1j * ai.astype(f64), np.complex128),
        tau=place(tau, f64), doppler=place(dop, f64),
        theta_t=place(tht, f64), phi_t=place(pht, f64),
        theta_r=place(thr, f64), phi_r=place(phr, f64),
        interactions=place(inter, np.int32), vertices=place(vert, np.float32),
        candidates_per_source=counts, cap=cap)


class SolverCore:
    """A Sionna ``PathSolver`` with truncation detection (callable helpers).

    Args:
        config: the ``[tracer]`` settings (depth, samples, cap, mechanisms, seed,
            ``deterministic``).
        deterministic: override ``config.deterministic``.
        legacy: run ``PathSolver.__call__`` / build Sionna's ``Paths`` (the
            original, slower code path; for benchmarks and cross-checks).
        spec_table_size: entries per source of Sionna's specular-chain hash
            table (None: Sionna's ``max(cap, 1e6)``). Grids use a larger one.

    Buffer size: the candidate buffer is ``max(MIN_BUFFER_PER_SRC, 4 x the
    largest per-source count seen so far)`` (power of two, at most ``cap``);
    a call that fills it is re-run with 8 x the buffer (``buffer_regrows``),
    so the result equals a trace with ``max_num_paths_per_src=cap``.
    Truncation at ``cap`` itself is reported as before.
    """

    def __init__(self, config: TracerConfig, *, deterministic: bool | None = None,
                 legacy: bool = False, spec_table_size: int | None = None):
        rt = _rt()
        self.config = config
        #: Specular-chain hash table entries per source (None: Sionna's own
        #: choice, ``max(cap, 1e6)``). Larger tables lose fewer candidates to
        #: collisions when many receivers share a call.
        self.spec_table_size = spec_table_size
        #: Largest per-source candidate count seen so far (sizes the buffer).
        self.candidates_seen = 0
        #: Calls re-run because the reduced buffer overflowed.
        self.buffer_regrows = 0
        self.deterministic = config.deterministic if deterministic is None else deterministic
        #: True: run ``PathSolver.__call__`` and read Sionna's ``Paths`` (the
        #: pre-optimization code path, kept for benchmarks and cross-checks).
        self.legacy = bool(legacy)
        self.solver = rt.PathSolver(deterministic=self.deterministic)
        self._counter = _CountingGenerator(self.solver._candidate_generator)
        # The one hook into Sionna internals: count candidates per source.
        self.solver._candidate_generator = self._counter
        self._iso = None

    @property
    def iso_array(self):
        """Sionna ``PlanarArray(1, 1, "iso", "V")``."""
        if self._iso is None:
            self._iso = _rt().PlanarArray(num_rows=1, num_cols=1, vertical_spacing=0.5,
                                          horizontal_spacing=0.5, pattern="iso",
                                          polarization="V")
        return self._iso

    def solver_kwargs(self, cap: int) -> dict:
        c = self.config
        return dict(max_depth=c.max_depth, max_num_paths_per_src=int(cap),
                    samples_per_src=c.samples_per_src, los=c.los,
                    specular_reflection=c.specular_reflection,
                    diffuse_reflection=c.diffuse_reflection, refraction=c.refraction,
                    diffraction=c.diffraction, seed=c.seed)

    def _trace(self, mi_scene, wavelength, src, tgt, src_o, tgt_o, v_tx, v_rx,
               src_patterns, tgt_patterns, cap: int) -> RawPaths:
        """The stages of ``PathSolver.__call__`` (Sionna 2.2), then
        :func:`_buffer_to_numpy` instead of building ``Paths``.

        ``cap`` is the ``max_num_paths_per_src`` the result is equivalent to; the
        buffer actually allocated is smaller (see the class doc)."""
        import drjit as dr

        dr.make_opaque(src, tgt, src_o, tgt_o)
        table = self.spec_table_size or _spec_table_default(cap)
        buf_cap = min(int(cap), max(MIN_BUFFER_PER_SRC,
                                    1 << int(4 * max(1, self.candidates_seen) - 1).bit_length()))
        while True:
            with _spec_table_size(table):
                raw = self._trace_once(mi_scene, wavelength, src, tgt, src_o, tgt_o, v_tx, v_rx,
                                       src_patterns, tgt_patterns, cap, buf_cap)
            self.candidates_seen = max(self.candidates_seen, int(raw.candidates_per_source.max(
                initial=0)))
            if buf_cap >= cap or raw.candidates_per_source.max(initial=0) < buf_cap:
                return raw
            # The reduced buffer overflowed: not a truncation of the requested
            # cap; re-run with a larger buffer (same hash table -> same result).
            self.buffer_regrows += 1
            buf_cap = min(int(cap), 8 * buf_cap)

    def _trace_once(self, mi_scene, wavelength, src, tgt, src_o, tgt_o, v_tx, v_rx,
                    src_patterns, tgt_patterns, cap: int, buf_cap: int) -> RawPaths:
        buf = self.generate(mi_scene, src, tgt, buf_cap)
        # (the counting wrapper has scheduled and evaluated the buffer)
        return self.evaluate(buf, mi_scene, wavelength, src, tgt, src_o, tgt_o, v_tx, v_rx,
                             src_patterns, tgt_patterns, self._counter.counts, cap)

    def generate(self, mi_scene, src, tgt, buf_cap: int, *, max_depth: int | None = None,
                 los: bool | None = None):
        """Sionna's candidate generator (shoot-and-bounce) -> shrunk ``PathsBuffer``.

        Candidates per source are counted (:attr:`last_counts`, truncation).
        ``max_depth=0`` runs only the line-of-sight test; ``los=False`` skips it.
        """
        kw = self.solver_kwargs(buf_cap)
        buf = self.solver._candidate_generator(
            mi_scene=mi_scene, src_positions=src, tgt_positions=tgt,
            samples_per_src=kw["samples_per_src"],
            max_num_paths_per_src=kw["max_num_paths_per_src"],
            max_depth=kw["max_depth"] if max_depth is None else int(max_depth),
            los=kw["los"] if los is None else bool(los),
            specular_reflection=kw["specular_reflection"],
            diffuse_reflection=kw["diffuse_reflection"], refraction=kw["refraction"],
            diffraction=kw["diffraction"], edge_diffraction=False, seed=kw["seed"])
        buf.shrink()
        return buf

    @property
    def candidate_generator(self):
        """Sionna's candidate generator (unwrapped)."""
        return self._counter.inner

    @property
    def last_counts(self) -> np.ndarray:
        """Candidates per source that the last :meth:`generate` stored ``[S]``."""
        return self._counter.counts

    def evaluate(self, buf, mi_scene, wavelength, src, tgt, src_o, tgt_o, v_tx, v_rx,
                 src_patterns, tgt_patterns, counts: np.ndarray, cap: int,
                 depth: int | None = None) -> RawPaths:
        """Image method and field calculator on candidates -> :class:`RawPaths`.

        ``buf``: candidates whose ``valid`` flag is False (valid entries, e.g.
        line-of-sight paths, skip the image method); ``depth``: the buffer's
        max depth (default the configured one).
        """
        import drjit as dr

        kw = self.solver_kwargs(cap)
        s = self.solver
        buf.detach_geometry()
        buf = s._image_method(scene=mi_scene, paths=buf, src_positions=src,
                              tgt_positions=tgt, diffraction=kw["diffraction"],
                              diffraction_lit_region=True)
        buf = s._field_calculator(
            wavelength=wavelength, paths=buf, samples_per_src=kw["samples_per_src"],
            diffraction=kw["diffraction"], src_positions=src, tgt_positions=tgt,
            src_orientations=src_o, tgt_orientations=tgt_o,
            src_antenna_patterns=src_patterns, tgt_antenna_patterns=tgt_patterns)
        buf.discard_invalid()
        return _buffer_to_numpy(buf, v_tx, v_rx, wavelength, dr.width(tgt), dr.width(src),
                                self.config.max_depth if depth is None else depth,
                                counts, cap)

    def solve_scene(self, sionna_scene, cap: int) -> RawPaths:
        """Trace the Sionna scene's own transmitters and receivers."""
        if self.legacy:
            paths = self.solver(sionna_scene, synthetic_array=True,
                                **self.solver_kwargs(cap))
            return _paths_to_numpy(paths, len(sionna_scene.receivers),
                                   len(sionna_scene.transmitters), self.config.max_depth,
                                   self._counter.counts, cap)
        sionna_scene.all_set(radio_map=False)
        src, src_o, _, v_tx = sionna_scene.sources(True, True)
        tgt, tgt_o, _, v_rx = sionna_scene.targets(True, True)
        return self._trace(sionna_scene.mi_scene, sionna_scene.wavelength, src, tgt, src_o,
                           tgt_o, v_tx, v_rx, sionna_scene.tx_array.antenna_pattern.patterns,
                           sionna_scene.rx_array.antenna_pattern.patterns, cap)

    def solve_endpoints(self, sionna_scene, sources: np.ndarray, targets: np.ndarray,
                        cap: int, source_orientations: np.ndarray | None = None,
                        source_velocities: np.ndarray | None = None,
                        target_orientations: np.ndarray | None = None,
                        target_velocities: np.ndarray | None = None) -> RawPaths:
        """Trace single-element endpoints given as arrays.

        Used for grids (thousands of ``Receiver`` objects would cost a Python
        loop of scatters in ``Scene._endpoints``) and by :class:`SionnaTracer`:
        the positions go to the solver stages as evaluated arrays, never as
        literals (``Scene._endpoints`` scatters each device's position as a
        literal into a kernel, so every new pose compiled a new kernel).

        Args:
            sionna_scene: the ``sionna.rt.Scene`` (geometry and materials only).
            sources: ``[S, 3]`` m.
            targets: ``[T, 3]`` m.
            cap: ``max_num_paths_per_src``.
            source_orientations, target_orientations: ``[S|T, 3]`` Sionna
                ``[yaw, pitch, roll]`` rad (default 0).
            source_velocities, target_velocities: ``[S|T, 3]`` m/s (default 0).
        """
        import mitsuba as mi

        arr = _points
        sources = np.asarray(sources, np.float32).reshape(-1, 3)
        targets = np.asarray(targets, np.float32).reshape(-1, 3)
        ns, nt = len(sources), len(targets)
        src, tgt = arr(sources, ns, mi.Point3f), arr(targets, nt, mi.Point3f)
        src_o = arr(source_orientations, ns, mi.Point3f)
        tgt_o = arr(target_orientations, nt, mi.Point3f)
        v_tx = arr(source_velocities, ns, mi.Vector3f)
        v_rx = arr(target_velocities, nt, mi.Vector3f)
        if not self.legacy:
            pattern = self.iso_array.antenna_pattern.patterns
            return self._trace(sionna_scene.mi_scene, sionna_scene.wavelength, src, tgt,
                               src_o, tgt_o, v_tx, v_rx, pattern, pattern, cap)
        return self._solve_endpoints_legacy(sionna_scene, src, tgt, src_o, tgt_o, v_tx, v_rx,
                                            cap)

    def _solve_endpoints_legacy(self, sionna_scene, src, tgt, src_o, tgt_o, v_tx, v_rx,
                                cap: int) -> RawPaths:
        import drjit as dr
        import mitsuba as mi

        from sionna.rt.path_solvers.paths import Paths

        ns, nt = dr.width(src), dr.width(tgt)
        rel_tx, rel_rx = dr.zeros(mi.Point3f, ns), dr.zeros(mi.Point3f, nt)
        pattern = self.iso_array.antenna_pattern.patterns
        dr.make_opaque(src, tgt, src_o, tgt_o)
        kw = self.solver_kwargs(cap)
        s = self.solver
        buf = s._candidate_generator(
            mi_scene=sionna_scene.mi_scene, src_positions=src, tgt_positions=tgt,
            samples_per_src=kw["samples_per_src"], max_num_paths_per_src=kw["max_num_paths_per_src"],
            max_depth=kw["max_depth"], los=kw["los"],
            specular_reflection=kw["specular_reflection"],
            diffuse_reflection=kw["diffuse_reflection"], refraction=kw["refraction"],
            diffraction=kw["diffraction"], edge_diffraction=False, seed=kw["seed"])
        buf.schedule()
        dr.eval()
        buf.shrink()
        buf.detach_geometry()
        buf = s._image_method(scene=sionna_scene.mi_scene, paths=buf, src_positions=src,
                              tgt_positions=tgt, diffraction=kw["diffraction"],
                              diffraction_lit_region=True)
        buf = s._field_calculator(
            wavelength=sionna_scene.wavelength, paths=buf,
            samples_per_src=kw["samples_per_src"], diffraction=kw["diffraction"],
            src_positions=src, tgt_positions=tgt, src_orientations=src_o,
            tgt_orientations=tgt_o, src_antenna_patterns=pattern,
            tgt_antenna_patterns=pattern)
        buf.discard_invalid()
        # Paths only reads these attributes of the scene.
        stand_in = types.SimpleNamespace(
            tx_array=self.iso_array, rx_array=self.iso_array, transmitters=range(ns),
            receivers=range(nt), wavelength=sionna_scene.wavelength,
            frequency=sionna_scene.frequency)
        paths = Paths(stand_in, src, tgt, v_tx, v_rx, True, buf, rel_tx, rel_rx)
        return _paths_to_numpy(paths, nt, ns, self.config.max_depth,
                               self._counter.counts, cap)


class SionnaTracer:
    """Tracer backend on Sionna RT's ``PathSolver`` (see :class:`~engine.raytrace.base.Tracer`).

    Args:
        config: ``[tracer]`` settings. ``deterministic=True`` selects Sionna's
            deterministic candidate generator (same seed -> same paths);
            ``seed`` seeds the ray sampler.
        on_truncation: ``"grow"`` (default) retries a truncated trace with the
            cap doubled (up to ``2**MAX_CAP_DOUBLINGS`` times the configured cap)
            and logs a warning; ``"raise"`` raises
            :class:`~engine.raytrace.base.TruncationError` at once.

    With ``config.uses_chains`` (the default) calls go through chain reuse
    (:class:`~engine.raytrace.chains.ChainTracer`): uplinks to access points
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
        #: Chain reuse (``tracer.method``; see :mod:`engine.raytrace.chains`),
        #: None when tracing directly.
        self.chains = None
        if self.config.uses_chains and not legacy:
            from engine.raytrace.chains import ChainTracer

            cap = self.config.max_num_paths_per_src
            self.chains = ChainTracer(self.core, self.config.probe_spacing,
                                      max_cap=cap if on_truncation == "raise"
                                      else cap << MAX_CAP_DOUBLINGS)
        self._last_sources: np.ndarray | None = None
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
        rt = _rt()
        if sc.tx_array is not self.core.iso_array:
            sc.tx_array = self.core.iso_array
        if sc.rx_array is not self.core.iso_array:
            sc.rx_array = self.core.iso_array
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
            dev.orientation = sionna_orientation(p.orientation)
            dev.velocity = p.velocity

    def __call__(self, scene, poses: Mapping[str, DevicePose],
                 links: Iterable[Link] | None = None) -> dict[Link, LinkPaths]:
        links = resolve_links(scene.config, links)
        tx_names = list(dict.fromkeys(t for t, _ in links))
        rx_names = list(dict.fromkeys(r for _, r in links))
        validate_poses(scene, poses, dict.fromkeys(tx_names + rx_names))
        sc = scene.sionna
        self._sync_devices(sc, tx_names, rx_names, poses)
        cap = self.config.max_num_paths_per_src
        raw = None
        src_names, tgt_names, flipped = tx_names, rx_names, set()
        if self.chains is not None:
            # Reciprocity: an uplink (robot -> access point) is traced as the
            # downlink and reversed, so that the sources, whose chains the
            # probes cache, stay the static access points.
            kinds = {d.name: d.kind for d in scene.config.devices}
            flipped = {(tx, rx) for tx, rx in links
                       if kinds.get(rx) == "access_point" and kinds.get(tx) != "access_point"}
            oriented = [(rx, tx) if (tx, rx) in flipped else (tx, rx) for tx, rx in links]
            c_src = list(dict.fromkeys(t for t, _ in oriented))
            c_tgt = list(dict.fromkeys(r for _, r in oriented))
            sources = np.array([poses[n].position for n in c_src], float)
            moved = self._last_sources is not None and (
                self._last_sources.shape != sources.shape
                or not np.array_equal(self._last_sources, sources))
            self._last_sources = sources
            if moved:  # the probes' chains belong to the source positions
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
            for attempt in range(MAX_CAP_DOUBLINGS + 1):
                if self.core.legacy:
                    raw = self.core.solve_scene(sc, cap)
                else:
                    raw = self.core.solve_endpoints(
                        sc, [poses[n].position for n in tx_names],
                        [poses[n].position for n in rx_names], cap,
                        source_orientations=[sionna_orientation(poses[n].orientation)
                                             for n in tx_names],
                        source_velocities=[poses[n].velocity for n in tx_names],
                        target_orientations=[sionna_orientation(poses[n].orientation)
                                             for n in rx_names],
                        target_velocities=[poses[n].velocity for n in rx_names])
                if not raw.truncated:
                    break
                msg = (f"Sionna stored the maximum of {cap} path candidates for a source "
                       f"(candidates per transmitter {dict(zip(tx_names, raw.candidates_per_source.tolist()))}); "
                       "paths would be dropped")
                if self.on_truncation == "raise" or attempt == MAX_CAP_DOUBLINGS:
                    raise TruncationError(msg + "; raise tracer.max_num_paths_per_src")
                log.warning("%s: retrying with max_num_paths_per_src=%d", msg, 2 * cap)
                cap *= 2
        self.last_raw = raw
        f = scene.config.scene.frequency_hz
        out: dict[Link, LinkPaths] = {}
        for tx, rx in links:
            src, tgt = (rx, tx) if (tx, rx) in flipped else (tx, rx)
            t, r = src_names.index(src), tgt_names.index(tgt)
            pt, pr = poses[src], poses[tgt]
            d = raw.link(r, t)
            if d["tau"].size == 0:
                out[(tx, rx)] = empty_link(tx, rx, poses[tx], poses[rx], f,
                                           raw.interactions.shape[-1])
                continue
            lp = LinkPaths(
                tx=src, rx=tgt, tx_position=np.asarray(pt.position),
                rx_position=np.asarray(pr.position),
                tx_orientation=np.asarray(pt.orientation),
                rx_orientation=np.asarray(pr.orientation), frequency_hz=f,
                vertices=d["vertices"].astype(np.float64),
                **{k: d[k] for k in ("a", "tau", "doppler", "theta_t", "phi_t", "theta_r",
                                     "phi_r", "interactions")})
            out[(tx, rx)] = lp.reversed() if (tx, rx) in flipped else lp
        return out
