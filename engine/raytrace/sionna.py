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

Mitsuba variant: Sionna selects it on import (CUDA when available, else
LLVM); nothing here forces one.
"""

from __future__ import annotations

import logging
import types
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import numpy as np

from engine.config import TracerConfig
from engine.raytrace.base import (DevicePose, Link, LinkPaths, TruncationError,
                                  empty_link, resolve_links, sionna_orientation,
                                  validate_poses)

log = logging.getLogger(__name__)

#: A truncated trace is retried with the cap doubled at most this many times.
MAX_CAP_DOUBLINGS = 6


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
        src = np.asarray(paths.source_indices.numpy()[:n], dtype=np.int64)
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


def _paths_to_numpy(paths, num_rx: int, num_tx: int, depth: int,
                    counts: np.ndarray, cap: int) -> RawPaths:
    tau = np.asarray(paths.tau.numpy(), np.float64).reshape(num_rx, num_tx, -1)
    p = tau.shape[-1]
    d = max(1, depth)
    if p == 0:
        z = np.zeros((num_rx, num_tx, 0))
        return RawPaths(valid=z.astype(bool), a=z.astype(complex), tau=z, doppler=z,
                        theta_t=z, phi_t=z, theta_r=z, phi_r=z,
                        interactions=np.zeros((num_rx, num_tx, 0, d), np.int32),
                        vertices=np.zeros((num_rx, num_tx, 0, d, 3), np.float32),
                        candidates_per_source=counts, cap=cap)
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


class SolverCore:
    """A Sionna ``PathSolver`` with truncation detection (callable helpers).

    Args:
        config: the ``[tracer]`` settings (depth, samples, cap, mechanisms, seed,
            ``deterministic``).
        deterministic: override ``config.deterministic``.
    """

    def __init__(self, config: TracerConfig, *, deterministic: bool | None = None):
        rt = _rt()
        self.config = config
        self.deterministic = config.deterministic if deterministic is None else deterministic
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

    def solve_scene(self, sionna_scene, cap: int) -> RawPaths:
        """Trace the Sionna scene's own transmitters and receivers."""
        paths = self.solver(sionna_scene, synthetic_array=True, **self.solver_kwargs(cap))
        return _paths_to_numpy(paths, len(sionna_scene.receivers),
                               len(sionna_scene.transmitters), self.config.max_depth,
                               self._counter.counts, cap)

    def solve_endpoints(self, sionna_scene, sources: np.ndarray, targets: np.ndarray,
                        cap: int, source_orientations: np.ndarray | None = None) -> RawPaths:
        """Trace static single-element endpoints given as arrays.

        Used for grids: thousands of ``Receiver`` objects would cost a Python
        loop of scatters in ``Scene._endpoints``; here the positions go to the
        solver stages directly (the same stages ``PathSolver.__call__`` runs).

        Args:
            sionna_scene: the ``sionna.rt.Scene`` (geometry and materials only).
            sources: ``[S, 3]`` m (velocity 0).
            targets: ``[T, 3]`` m (orientation 0, velocity 0).
            cap: ``max_num_paths_per_src``.
            source_orientations: ``[S, 3]`` Sionna ``[yaw, pitch, roll]`` rad (default 0).
        """
        import drjit as dr
        import mitsuba as mi

        from sionna.rt.path_solvers.paths import Paths

        sources = np.asarray(sources, np.float32).reshape(-1, 3)
        targets = np.asarray(targets, np.float32).reshape(-1, 3)
        ns, nt = len(sources), len(targets)
        src = mi.Point3f(*(mi.Float(sources[:, i]) for i in range(3)))
        tgt = mi.Point3f(*(mi.Float(targets[:, i]) for i in range(3)))
        so = (np.zeros((ns, 3), np.float32) if source_orientations is None
              else np.asarray(source_orientations, np.float32).reshape(ns, 3))
        src_o = mi.Point3f(*(mi.Float(so[:, i]) for i in range(3)))
        tgt_o = dr.zeros(mi.Point3f, nt)
        rel_tx, rel_rx = dr.zeros(mi.Point3f, ns), dr.zeros(mi.Point3f, nt)
        v_tx, v_rx = dr.zeros(mi.Vector3f, ns), dr.zeros(mi.Vector3f, nt)
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

    Call:
        ``tracer(scene, poses, links=None) -> {(tx, rx): LinkPaths}``.
    """

    def __init__(self, config: TracerConfig | None = None, *, on_truncation: str = "grow"):
        if on_truncation not in ("grow", "raise"):
            raise ValueError(f"on_truncation: expected 'grow' or 'raise', got {on_truncation!r}")
        self.config = config or TracerConfig()
        self.on_truncation = on_truncation
        self.core = SolverCore(self.config)
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
        for attempt in range(MAX_CAP_DOUBLINGS + 1):
            raw = self.core.solve_scene(sc, cap)
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
            t, r = tx_names.index(tx), rx_names.index(rx)
            pt, pr = poses[tx], poses[rx]
            d = raw.link(r, t)
            if d["tau"].size == 0:
                out[(tx, rx)] = empty_link(tx, rx, pt, pr, f, raw.interactions.shape[-1])
                continue
            out[(tx, rx)] = LinkPaths(
                tx=tx, rx=rx, tx_position=np.asarray(pt.position),
                rx_position=np.asarray(pr.position),
                tx_orientation=np.asarray(pt.orientation),
                rx_orientation=np.asarray(pr.orientation), frequency_hz=f,
                vertices=d["vertices"].astype(np.float64),
                **{k: d[k] for k in ("a", "tau", "doppler", "theta_t", "phi_t", "theta_r",
                                     "phi_r", "interactions")})
        return out
