"""Everything that touches Sionna RT's internals (Sionna 2.2, ``path_solvers/``).

The stages of ``PathSolver.__call__`` run one by one (candidate generator,
image method, field calculator), the candidate counter that detects
truncation, the size of the specular-chain hash table, ``PathsBuffer``
reads and writes (chain reuse builds buffers of cached chains and gathers
(chain, target) pairs from them) and Sionna's line-of-sight test. Nothing
above this module names a private Sionna attribute; a Sionna upgrade is
checked here (and by ``tests/engine/raytrace/``).

Truncation. Sionna's candidate generator stores at most
``max_num_paths_per_src`` candidates per source and drops the rest without a
word (``sb_candidate_generator.py``: the per-source counter is incremented
for every candidate, but only those below the cap are stored;
``sb_deterministic.py`` enforces the same budget). Nothing in the returned
``Paths`` tells. :class:`SolverCore` therefore wraps the solver's candidate
generator and counts the stored candidates per source
(``paths_buffer.source_indices[:paths_counter]``) before the image method
runs: a source that stored exactly the cap may have lost candidates, and the
trace is reported as truncated (:func:`isac_twin.raytrace.raw.grow_cap` decides
what happens then).

Speed (see ``bench/bench_retrace.py``). :class:`SolverCore` differs from
``PathSolver.__call__`` in two ways that do not change the result
(bit-identical in deterministic mode; ``legacy=True`` runs the original code
path for comparison):

- it reads the flat ``PathsBuffer`` into numpy (:func:`buffer_to_numpy`)
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

import threading
import types
from contextlib import contextmanager

import numpy as np

from ..scene.config import TracerConfig
from .polarization import v_world
from .raw import RawPaths, to_points

__all__ = ["MIN_BUFFER_PER_SRC", "SolverCore", "arrays_to_raw", "basis_patterns",
           "buffer_arrays", "buffer_columns", "buffer_to_numpy", "chain_arrays",
           "image_and_field",
           "load_sionna_rt", "paths_to_numpy", "pinned_spec_table", "spec_table_default"]

#: Smallest candidate buffer per source that :class:`SolverCore` allocates
#: (see "Buffer size" in :class:`SolverCore`).
MIN_BUFFER_PER_SRC = 4096

_TABLE_LOCK = threading.Lock()


@contextmanager
def pinned_spec_table(size: int):
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


def spec_table_default(cap: int) -> int:
    from sionna.rt.path_solvers.sb_candidate_generator import SBCandidateGenerator

    return max(int(cap), int(SBCandidateGenerator.MIN_SPEC_COUNT_SIZE))


def load_sionna_rt():
    """``sionna.rt``, imported after Dr.Jit was pointed at an LLVM library."""
    from ..utils import llvm

    llvm.configure_llvm()
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


def _orient(v, n: int) -> np.ndarray:
    """Orientations (None, numpy or a Mitsuba ``Point3f``) -> ``[n, 3]`` float64."""
    if v is None:
        return np.zeros((n, 3))
    if hasattr(v, "x") and hasattr(v.x, "numpy"):
        return np.stack([np.asarray(c.numpy(), np.float64) for c in (v.x, v.y, v.z)], -1)
    return np.asarray(v, np.float64).reshape(n, 3)


def _with_v(pol, tht, pht, thr, phr, src_i, tgt_i, src_o, tgt_o) -> np.ndarray:
    """Iso V coefficients ``[n]`` of paths with transfer matrices ``pol [n, 2, 2]``
    between devices of orientations ``src_o [S, 3]`` / ``tgt_o [T, 3]``."""
    from ..phy.arrays import r_hat

    if not (np.any(src_o) or np.any(tgt_o)):
        return pol[:, 0, 0].copy()
    qt = v_world(r_hat(tht, pht), src_o, src_i)
    qr = v_world(r_hat(thr, phr), tgt_o, tgt_i)
    return np.einsum("li,lij,lj->l", qr, pol, qt)


def paths_to_numpy(paths, num_rx: int, num_tx: int, depth: int,
                    counts: np.ndarray, cap: int, src_o=None, tgt_o=None) -> RawPaths:
    """Sionna ``Paths`` traced with :func:`basis_patterns` at both ends (two
    ports each, orientation zero) -> :class:`RawPaths` (``a`` for iso V
    elements in the orientations ``src_o [T, 3]`` / ``tgt_o [R, 3]``)."""
    tau = np.asarray(paths.tau.numpy(), np.float64).reshape(num_rx, num_tx, -1)
    p = tau.shape[-1]
    d = max(1, depth)
    if p == 0:
        return RawPaths.empty(num_rx, num_tx, d, counts, cap)
    ar, ai = paths.a
    a = (np.asarray(ar.numpy(), np.float64) + 1j * np.asarray(ai.numpy(), np.float64))
    pol = np.moveaxis(a.reshape(num_rx, 2, num_tx, 2, p), (1, 3), (3, 4))  # [R, T, P, 2, 2]
    f = lambda x: np.asarray(x.numpy(), np.float64).reshape(num_rx, num_tx, p)  # noqa: E731
    inter = np.asarray(paths.interactions.numpy()).reshape(-1, num_rx, num_tx, p)
    vert = np.asarray(paths.vertices.numpy(), np.float32).reshape(-1, num_rx, num_tx, p, 3)
    inter = np.moveaxis(inter, 0, -1).astype(np.int32)
    vert = np.array(np.moveaxis(vert, 0, -2), copy=True)
    vert[inter == 0] = 0.0  # Sionna leaves stale coordinates in unused slots
    ang = {k: f(getattr(paths, k)) for k in ("theta_t", "phi_t", "theta_r", "phi_r")}
    r, t, _ = np.meshgrid(np.arange(num_rx), np.arange(num_tx), np.arange(p), indexing="ij")
    v = _with_v(pol.reshape(-1, 2, 2), *(ang[k].ravel() for k in ("theta_t", "phi_t",
                                                                  "theta_r", "phi_r")),
                t.ravel(), r.ravel(), _orient(src_o, num_tx), _orient(tgt_o, num_rx))
    return RawPaths(
        valid=np.asarray(paths.valid.numpy(), bool).reshape(num_rx, num_tx, p),
        a=v.reshape(num_rx, num_tx, p), pol=pol, tau=tau, doppler=f(paths.doppler),
        interactions=inter, vertices=vert,
        candidates_per_source=counts, cap=cap, **ang)


def buffer_arrays(buf, src_vel, tgt_vel, wavelength) -> list:
    """Per-path quantities of a field-calculated ``PathsBuffer``, as Dr.Jit arrays
    (not evaluated): ``src_i, tgt_i, tau, doppler, theta_t, phi_t, theta_r,
    phi_r [n]``, ``types, vx, vy, vz [n * D]`` (flat, depth-minor) and the real
    and imaginary parts of ``a[i][j]`` ``[n]`` (i, j = 0, 1; real first).

    Angles and Doppler as in Sionna's ``Paths._build_from_buffer`` and
    ``Paths._finalize_doppler_shift_compute``."""
    import drjit as dr
    import mitsuba as mi
    from sionna.rt.utils import theta_phi_from_unit_vec

    src_i, tgt_i = buf.source_indices, buf.target_indices
    k_tx, k_rx = buf.k_tx, buf.k_rx
    theta_t, phi_t = theta_phi_from_unit_vec(k_tx)
    theta_r, phi_r = theta_phi_from_unit_vec(k_rx)
    v_tx = dr.gather(mi.Vector3f, src_vel, src_i)
    v_rx = dr.gather(mi.Vector3f, tgt_vel, tgt_i)
    doppler = buf.doppler + dr.dot(k_tx, v_tx) / wavelength - dr.dot(-k_rx, v_rx) / wavelength
    comps = [buf.a[i][j] for i in range(2) for j in range(2)]
    parts = [f(c) for c in comps for f in (dr.real, dr.imag)]
    return [src_i, tgt_i, buf.tau, doppler, theta_t, phi_t, theta_r, phi_r,
            buf.interaction_types.array, buf.vertices_x.array, buf.vertices_y.array,
            buf.vertices_z.array, *parts]


def arrays_to_raw(cols: list[np.ndarray], num_rx: int, num_tx: int, depth: int,
                  counts: np.ndarray, cap: int, src_o=None, tgt_o=None,
                  keep: np.ndarray | None = None) -> RawPaths:
    """:func:`buffer_arrays` read into numpy -> :class:`RawPaths` ``[R, T, P]``.

    ``keep [n]``: the paths to keep (default all); within a link, paths keep
    their buffer order. Invalid slots are zero. ``pol`` is the transfer matrix
    (the buffer holds the coefficients of :func:`basis_patterns` at both ends
    at orientation zero); ``a`` is the iso V coefficient in the devices'
    orientations ``src_o [T, 3]`` / ``tgt_o [R, 3]`` (Sionna ``[yaw, pitch,
    roll]``, default 0), see :mod:`isac_twin.raytrace.polarization`.
    """
    d = max(1, depth)
    (src_i, tgt_i, tau, dop, tht, pht, thr, phr, inter, vx, vy, vz, *parts) = cols
    inter = np.asarray(inter).reshape(-1, d)
    vert = np.stack([vx, vy, vz], -1).reshape(-1, d, 3)
    parts = np.stack(parts, -1)
    if keep is not None:
        (src_i, tgt_i, tau, dop, tht, pht, thr, phr, inter, vert, parts) = (
            x[keep] for x in (src_i, tgt_i, tau, dop, tht, pht, thr, phr, inter, vert, parts))
    n = len(src_i)
    if n == 0:
        return RawPaths.empty(num_rx, num_tx, d, counts, cap)
    pol = (parts[:, 0::2].astype(np.float64)
           + 1j * parts[:, 1::2].astype(np.float64)).reshape(n, 2, 2)
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

    inter = inter.astype(np.int32)
    vert = vert.astype(np.float32)
    vert[inter == 0] = 0.0  # Sionna leaves stale coordinates in unused slots
    f64 = np.float64
    v = _with_v(pol, tht, pht, thr, phr, t, r, _orient(src_o, num_tx), _orient(tgt_o, num_rx))
    return RawPaths(
        valid=place(np.ones(n, bool), bool),
        a=place(v, np.complex128), pol=place(pol, np.complex128),
        tau=place(tau, f64), doppler=place(dop, f64),
        theta_t=place(tht, f64), phi_t=place(pht, f64),
        theta_r=place(thr, f64), phi_r=place(phr, f64),
        interactions=place(inter, np.int32), vertices=place(vert, np.float32),
        candidates_per_source=counts, cap=cap)


def buffer_to_numpy(buf, src_vel, tgt_vel, wavelength, num_rx: int, num_tx: int,
                     depth: int, counts: np.ndarray, cap: int, src_o=None,
                     tgt_o=None) -> RawPaths:
    """Flat ``PathsBuffer`` (after ``discard_invalid``) -> :class:`RawPaths`.

    Equivalent to building Sionna's ``Paths`` (synthetic single-element arrays)
    and reading its tensors, without it: ``Paths`` scatters into
    ``[depth, rx, tx, max_num_paths]`` tensors whose kernels bake the path
    count as a literal (an LLVM compile, ~5 ms each, three per call whenever the
    count changes) and costs a few ms of Python tracing. Here the per-path
    quantities (:func:`buffer_arrays`) are evaluated in one ``dr.eval`` and
    arranged by :func:`arrays_to_raw`.
    """
    import drjit as dr

    d = max(1, depth)
    n = int(buf.buffer_size) if buf.tau is not None else 0
    if n == 0:
        return RawPaths.empty(num_rx, num_tx, d, counts, cap)
    out = buffer_arrays(buf, src_vel, tgt_vel, wavelength)
    dr.eval(*out)
    return arrays_to_raw([x.numpy() for x in out], num_rx, num_tx, depth, counts, cap,
                         src_o, tgt_o)


def image_and_field(solver, buf, mi_scene, wavelength, src, tgt, *, samples_per_src: int,
                    diffraction: bool = False, patterns=None, src_o=None, tgt_o=None):
    """Sionna's image method and field calculator (the last two stages of
    ``PathSolver.__call__``, Sionna 2.2) on candidates ``buf`` -> the buffer.

    ``patterns``: ``(tx, rx)`` antenna pattern lists (default
    :func:`basis_patterns` at both ends); ``src_o`` / ``tgt_o``: orientations
    (``mi.Point3f``, default zero). The one place these stages are called
    (chain reuse, the direct trace, the legacy path, calibration)."""
    import drjit as dr
    import mitsuba as mi

    if patterns is None:
        basis = basis_patterns()
        patterns = (basis, basis)
    buf.detach_geometry()
    buf = solver._image_method(scene=mi_scene, paths=buf, src_positions=src,
                               tgt_positions=tgt, diffraction=diffraction,
                               diffraction_lit_region=True)
    return solver._field_calculator(
        wavelength=wavelength, paths=buf, samples_per_src=samples_per_src,
        diffraction=diffraction, src_positions=src, tgt_positions=tgt,
        src_orientations=dr.zeros(mi.Point3f, dr.width(src)) if src_o is None else src_o,
        tgt_orientations=dr.zeros(mi.Point3f, dr.width(tgt)) if tgt_o is None else tgt_o,
        src_antenna_patterns=patterns[0], tgt_antenna_patterns=patterns[1])


def basis_patterns() -> list:
    """Two isotropic element patterns for Sionna's field calculator: the unit
    vectors ``(C_theta, C_phi) = (1, 0)`` and ``(0, 1)`` of the local
    spherical basis (exactly; Sionna's ``"VH"`` computes ``cos(pi/2)`` in
    float32). Traced at orientation zero at both ends, the coefficients
    ``a[i][j]`` are the path's transfer matrix (:mod:`isac_twin.raytrace.polarization`)."""
    import drjit as dr
    import mitsuba as mi

    def unit(i: int):
        def f(theta, phi):
            n = dr.shape(theta)[0]
            one, zero = dr.ones(mi.Float, n), dr.zeros(mi.Float, n)
            return (mi.Complex2f(one if i == 0 else zero, 0),
                    mi.Complex2f(zero if i == 0 else one, 0))
        return f

    return [unit(0), unit(1)]


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
        rt = load_sionna_rt()
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
        self._basis = None

    @property
    def basis_array(self):
        """Sionna ``PlanarArray(1, 1, "iso", "VH")`` whose two patterns are
        :func:`basis_patterns` (what every trace uses at both ends)."""
        if self._basis is None:
            arr = load_sionna_rt().PlanarArray(num_rows=1, num_cols=1, vertical_spacing=0.5,
                                               horizontal_spacing=0.5, pattern="iso",
                                               polarization="VH")
            arr.antenna_pattern.patterns = basis_patterns()
            self._basis = arr
        return self._basis

    def solver_kwargs(self, cap: int) -> dict:
        c = self.config
        return dict(max_depth=c.max_depth, max_num_paths_per_src=int(cap),
                    samples_per_src=c.samples_per_src, los=c.los,
                    specular_reflection=c.specular_reflection,
                    diffuse_reflection=c.diffuse_reflection, refraction=c.refraction,
                    diffraction=c.diffraction, seed=c.seed)

    def _trace(self, mi_scene, wavelength, src, tgt, src_o, tgt_o, v_tx, v_rx,
               cap: int) -> RawPaths:
        """The stages of ``PathSolver.__call__`` (Sionna 2.2), then
        :func:`_buffer_to_numpy` instead of building ``Paths``.

        ``cap`` is the ``max_num_paths_per_src`` the result is equivalent to; the
        buffer actually allocated is smaller (see the class doc)."""
        import drjit as dr

        dr.make_opaque(src, tgt)
        table = self.spec_table_size or spec_table_default(cap)
        buf_cap = min(int(cap), max(MIN_BUFFER_PER_SRC,
                                    1 << int(4 * max(1, self.candidates_seen) - 1).bit_length()))
        while True:
            with pinned_spec_table(table):
                raw = self._trace_once(mi_scene, wavelength, src, tgt, src_o, tgt_o, v_tx, v_rx,
                                       cap, buf_cap)
            self.candidates_seen = max(self.candidates_seen, int(raw.candidates_per_source.max(
                initial=0)))
            if buf_cap >= cap or raw.candidates_per_source.max(initial=0) < buf_cap:
                return raw
            # The reduced buffer overflowed: not a truncation of the requested
            # cap; re-run with a larger buffer (same hash table -> same result).
            self.buffer_regrows += 1
            buf_cap = min(int(cap), 8 * buf_cap)

    def _trace_once(self, mi_scene, wavelength, src, tgt, src_o, tgt_o, v_tx, v_rx,
                    cap: int, buf_cap: int) -> RawPaths:
        buf = self.generate(mi_scene, src, tgt, buf_cap)
        # (the counting wrapper has scheduled and evaluated the buffer)
        return self.evaluate(buf, mi_scene, wavelength, src, tgt, src_o, tgt_o, v_tx, v_rx,
                             self._counter.counts, cap)

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
                 counts: np.ndarray, cap: int, depth: int | None = None) -> RawPaths:
        """Image method and field calculator on candidates -> :class:`RawPaths`.

        ``buf``: candidates whose ``valid`` flag is False (valid entries, e.g.
        line-of-sight paths, skip the image method); ``depth``: the buffer's
        max depth (default the configured one). The field calculator runs
        with :func:`basis_patterns` at orientation zero at both ends (the
        transfer matrix ``pol``); the orientations ``src_o`` / ``tgt_o`` (Sionna
        ``[yaw, pitch, roll]``) only enter ``a`` (iso V elements), computed
        from ``pol`` in numpy.
        """
        import drjit as dr

        pattern = self.basis_array.antenna_pattern.patterns
        buf = image_and_field(self.solver, buf, mi_scene, wavelength, src, tgt,
                              samples_per_src=self.config.samples_per_src,
                              diffraction=self.config.diffraction, patterns=(pattern, pattern))
        buf.discard_invalid()
        return buffer_to_numpy(buf, v_tx, v_rx, wavelength, dr.width(tgt), dr.width(src),
                                self.config.max_depth if depth is None else depth,
                                counts, cap, _orient(src_o, dr.width(src)),
                                _orient(tgt_o, dr.width(tgt)))

    def solve_scene(self, sionna_scene, cap: int, source_orientations=None,
                    target_orientations=None) -> RawPaths:
        """Trace the Sionna scene's own transmitters and receivers.

        The scene's arrays must be :attr:`basis_array` and its devices at
        orientation zero (the transfer matrix is in the world basis); the
        devices' orientations ``[T|R, 3]`` (Sionna ``[yaw, pitch, roll]``) are
        given here and enter only ``a``."""
        nt, nr = len(sionna_scene.transmitters), len(sionna_scene.receivers)
        if self.legacy:
            paths = self.solver(sionna_scene, synthetic_array=True,
                                **self.solver_kwargs(cap))
            return paths_to_numpy(paths, nr, nt, self.config.max_depth,
                                   self._counter.counts, cap, source_orientations,
                                   target_orientations)
        sionna_scene.all_set(radio_map=False)
        src, _, _, v_tx = sionna_scene.sources(True, True)
        tgt, _, _, v_rx = sionna_scene.targets(True, True)
        return self._trace(sionna_scene.mi_scene, sionna_scene.wavelength, src, tgt,
                           _orient(source_orientations, nt), _orient(target_orientations, nr),
                           v_tx, v_rx, cap)

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

        arr = to_points
        sources = np.asarray(sources, np.float32).reshape(-1, 3)
        targets = np.asarray(targets, np.float32).reshape(-1, 3)
        ns, nt = len(sources), len(targets)
        src, tgt = arr(sources, ns, mi.Point3f), arr(targets, nt, mi.Point3f)
        src_o = arr(source_orientations, ns, mi.Point3f)
        tgt_o = arr(target_orientations, nt, mi.Point3f)
        v_tx = arr(source_velocities, ns, mi.Vector3f)
        v_rx = arr(target_velocities, nt, mi.Vector3f)
        if not self.legacy:
            return self._trace(sionna_scene.mi_scene, sionna_scene.wavelength, src, tgt,
                               src_o, tgt_o, v_tx, v_rx, cap)
        return self._solve_endpoints_legacy(sionna_scene, src, tgt, src_o, tgt_o, v_tx, v_rx,
                                            cap)

    def _solve_endpoints_legacy(self, sionna_scene, src, tgt, src_o, tgt_o, v_tx, v_rx,
                                cap: int) -> RawPaths:
        import drjit as dr
        import mitsuba as mi
        from sionna.rt.path_solvers.paths import Paths

        ns, nt = dr.width(src), dr.width(tgt)
        rel_tx, rel_rx = dr.zeros(mi.Point3f, ns), dr.zeros(mi.Point3f, nt)
        pattern = self.basis_array.antenna_pattern.patterns
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
        buf = image_and_field(s, buf, sionna_scene.mi_scene, sionna_scene.wavelength, src, tgt,
                              samples_per_src=kw["samples_per_src"],
                              diffraction=kw["diffraction"], patterns=(pattern, pattern))
        buf.discard_invalid()
        # Paths only reads these attributes of the scene.
        stand_in = types.SimpleNamespace(
            tx_array=self.basis_array, rx_array=self.basis_array, transmitters=range(ns),
            receivers=range(nt), wavelength=sionna_scene.wavelength,
            frequency=sionna_scene.frequency)
        paths = Paths(stand_in, src, tgt, v_tx, v_rx, True, buf, rel_tx, rel_rx)
        return paths_to_numpy(paths, nt, ns, self.config.max_depth,
                               self._counter.counts, cap, _orient(src_o, ns),
                               _orient(tgt_o, nt))

    def evaluate_chains(self, mi_scene, chains: dict, chain_idx, target_idx, src, tgt,
                        v_tx, v_rx, wavelength, los: bool, pad=None) -> list:
        """Image method and field calculator on (chain, target) pairs.

        Args:
            mi_scene: the Mitsuba scene.
            chains: :func:`chain_arrays` (the chains and at least one empty chain).
            chain_idx, target_idx: ``mi.UInt [M]`` the pairs (chain ``M_i`` to
                target ``target_idx_i``).
            src, tgt: ``mi.Point3f`` ``[S]`` / ``[T]`` m; v_tx, v_rx: their
                velocities, ``mi.Vector3f`` m/s.
            wavelength: m (the scene's ``mi.Float``).
            los: also test the ``S x T`` line-of-sight paths (Sionna's LoS test,
                written into fixed slots after the pairs, source-major, so the
                call has no data-dependent size).
            pad: ``mi.UInt [M]`` (optional), non-zero for pairs that only pad
                the call to a fixed size: the image method skips them and
                ``keep`` drops them.

        Returns:
            ``[keep, *arrays]``: ``keep`` ``mi.Bool [M (+ S T)]`` marks the
            entries that are paths; ``arrays`` are :func:`buffer_arrays` of all
            entries. Nothing here reads data back to the host, so the call can
            be frozen (``drjit.freeze``; :class:`~isac_twin.raytrace.chains.ChainTracer`
            does for live traces). Same paths, in the same order, as
            Sionna's candidate buffer after its LoS test and ``discard_invalid``.
        """
        b, unused = chain_candidates(mi_scene, chains, chain_idx, target_idx, src, tgt,
                                     self.config.max_depth, los, pad)
        pattern = self.basis_array.antenna_pattern.patterns
        b = image_and_field(self.solver, b, mi_scene, wavelength, src, tgt,
                            samples_per_src=self.config.samples_per_src,
                            diffraction=self.config.diffraction, patterns=(pattern, pattern))
        return [b.valid & ~unused, *buffer_arrays(b, v_tx, v_rx, wavelength)]


def chain_candidates(mi_scene, chains: dict, chain_idx, target_idx, src, tgt, max_depth: int,
                     los: bool, pad=None) -> tuple:
    """The candidate buffer of (chain, target) pairs, for :func:`image_and_field`.

    Arguments as :meth:`SolverCore.evaluate_chains` (``max_depth``: the solver's).

    Returns:
        ``(buffer, unused)``: Sionna's ``PathsBuffer`` of the pairs (then the ``S x T``
        line-of-sight slots), none valid yet but the slots to skip; ``unused``
        ``mi.Bool`` marks those slots (hidden line of sight, padding), which are no
        paths whatever the image method says.
    """
    import drjit as dr
    import mitsuba as mi
    from sionna.rt.constants import MIN_SEGMENT_LENGTH
    from sionna.rt.path_solvers.sample_data import SampleData
    from sionna.rt.utils import spawn_ray_to

    ns, nt = dr.width(src), dr.width(tgt)
    m = ns * nt if los else 0
    npairs = dr.width(chain_idx)
    n = npairs + m
    idx = chain_idx
    if m:  # LoS slots start as empty chains
        empty = dr.width(chains["_src_indices"]) - 1
        idx = dr.concat([chain_idx, dr.full(mi.UInt, empty, m)]) if npairs else \
            dr.full(mi.UInt, empty, m)
    b = _chain_buffer(chains, max_depth).gather(idx)
    b._tgt_indices = dr.concat([target_idx, dr.zeros(mi.UInt, m)]) if (m and npairs) else \
        (target_idx if npairs else dr.zeros(mi.UInt, m))
    b._valid = dr.full(mi.Bool, False, n)
    b._paths_counter = mi.UInt(n)
    # Sizes as evaluated values, not literals: a kernel that bakes a size
    # compiles again for every other size (grids call with varying counts;
    # a stage scattering into these must not be split across kernels).
    dr.make_opaque(b._valid, b._paths_counter, b._tgt_indices)
    unused = dr.full(mi.Bool, False, n)
    if m:
        off = dr.opaque(mi.UInt, npairs)
        # sb_deterministic._los (Sionna 2.2) without its compaction: lane
        # (s, t) -> entry npairs + s T + t.
        sd = SampleData(ns, nt, 0, diffraction=False)
        o, t = dr.repeat(src, nt), dr.tile(tgt, ns)
        visible = dr.norm(t - o) > MIN_SEGMENT_LENGTH
        rays = spawn_ray_to(o, t)
        visible &= ~mi_scene.ray_test(rays, active=visible)
        lane = dr.arange(mi.UInt, m)
        b.add_paths(mi.UInt(0), off + lane, sd, visible,
                    dr.tile(dr.arange(mi.UInt, nt), ns), rays.d, -rays.d, visible)
        # Hidden LoS slots are no candidates: marked valid, the image
        # method skips them, and ``keep`` drops them.
        i = dr.arange(mi.UInt, n)
        in_los = i >= off
        seen = dr.gather(mi.Bool, visible, dr.select(in_los, i - off, 0), in_los)
        unused = in_los & ~seen
        b._valid = b._valid | unused
    if pad is not None:
        padded = pad != 0
        if m:
            padded = dr.concat([padded, dr.zeros(mi.Bool, m)])
        b._valid = b._valid | padded
        unused = unused | padded
    return b, unused


def buffer_columns(buf) -> list[np.ndarray]:
    """The stored candidates of a generator ``PathsBuffer`` (after ``shrink``) as
    numpy: ``src, tgt, valid [n]``, ``types, shapes, prims, probs, vx, vy, vz
    [n * D]`` (flat, depth-minor), ``kx, ky, kz [n]``."""
    import drjit as dr

    cols = [buf.source_indices, buf.target_indices, buf.valid,
            buf.interaction_types.array, buf.shapes.array, buf.primitives.array,
            buf.probs.array, buf.vertices_x.array, buf.vertices_y.array,
            buf.vertices_z.array, *buf.k_tx]
    dr.eval(*cols)
    return [np.asarray(c.numpy()) for c in cols]


def chain_arrays(cols: dict[str, np.ndarray], max_depth: int) -> dict:
    """Chains ``cols`` (``src [C]``, ``types, shapes, prims, probs, vx, vy, vz
    [C, D]``, ``k_tx [C, 3]``) as the Dr.Jit arrays of a ``PathsBuffer`` (keys:
    its attribute names), followed by empty chains (no interaction) up to a
    power of two (at least 1024 entries, at least one empty). The size rarely
    changes as a store grows (Dr.Jit recompiles kernels that gather from the
    chains when it does); :meth:`SolverCore.evaluate_chains` reads them."""
    import drjit as dr
    import mitsuba as mi
    from sionna.rt.constants import INVALID_PRIMITIVE, INVALID_SHAPE, InteractionType

    n = max(1024, 1 << len(cols["src"]).bit_length())
    empty = {"src": 0, "types": int(InteractionType.NONE), "shapes": INVALID_SHAPE,
             "prims": INVALID_PRIMITIVE, "probs": 0.0, "vx": 0.0, "vy": 0.0,
             "vz": 0.0, "k_tx": 0.0}
    col = {k: np.concatenate([v, np.full((n - len(v),) + v.shape[1:], empty[k], v.dtype)])
           for k, v in cols.items()}
    out = {"_src_indices": mi.UInt(col["src"]),
           "_interaction_types": mi.UInt(col["types"].ravel()),
           "_shapes": mi.UInt(col["shapes"].ravel()),
           "_primitives": mi.UInt(col["prims"].ravel()),
           "_probs": mi.Float(col["probs"].ravel()),
           "_vertices_x": mi.Float(col["vx"].ravel()),
           "_vertices_y": mi.Float(col["vy"].ravel()),
           "_vertices_z": mi.Float(col["vz"].ravel()),
           **{f"_k_tx_{c}": mi.Float(np.ascontiguousarray(col["k_tx"][:, i]))
              for i, c in enumerate("xyz")}}
    dr.eval(*out.values())
    return out


def _chain_buffer(chains: dict, max_depth: int):
    """A ``PathsBuffer`` of :func:`chain_arrays` ``chains``, none valid."""
    import drjit as dr
    import mitsuba as mi
    from sionna.rt.path_solvers.paths_buffer import PathsBuffer

    n = dr.width(chains["_src_indices"])
    d = max(1, int(max_depth))
    b = PathsBuffer(n, int(max_depth), False)
    b._src_indices = chains["_src_indices"]
    for k in ("_interaction_types", "_shapes", "_primitives"):
        setattr(b, k, mi.TensorXu(chains[k], shape=(n, d)))
    for k in ("_probs", "_vertices_x", "_vertices_y", "_vertices_z"):
        setattr(b, k, mi.TensorXf(chains[k], shape=(n, d)))
    b._k_tx_x, b._k_tx_y, b._k_tx_z = (chains[f"_k_tx_{c}"] for c in "xyz")
    b._paths_counter = mi.UInt(n)
    return b


