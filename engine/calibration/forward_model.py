"""The forward model: the twin's channel power at parameter values, with gradients.

:class:`ForwardModel` writes parameter values into the scene and traces each
link's channel power per snapshot, antenna pair and subcarrier; with gradients,
:meth:`ForwardModel.evaluate` gives the mismatch (:mod:`.problem`) and its
derivative with respect to every parameter.

Gradients come from Sionna RT through Dr.Jit's automatic differentiation on
the LLVM backend: the material parameters are Dr.Jit variables of Sionna's
``RadioMaterial`` (its ITU frequency callback is switched off so the fitted
value sticks), the object offsets move the mesh vertices through Mitsuba's
scene parameters, and ``PathSolver``'s stages (``loop_mode="evaluated"``, the
mode Sionna documents as differentiable) plus a frequency response summed as
``Paths.cfr`` sums it propagate both to the channel. Paths are re-traced at
every evaluation with a fixed seed (their candidates: :mod:`.candidates`), so
the mismatch is a deterministic function of the parameters.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from ..errors import CalibrationError
from .candidates import Candidates, path_solver
from .problem import MATERIAL_KINDS, POSE_KINDS, POWER_FLOOR, Measurements, Parameter, power_db


@dataclass(frozen=True)
class SolverSettings:
    """Path solver settings of the calibration's traces.

    Attributes:
        max_depth: interactions per path.
        samples_per_src: rays shot per transmitter.
        seed: the ray sampler's seed (fixed: the mismatch must be deterministic).
        refraction: trace transmission through objects.
        chains: the model's candidates are the chains of the transmitters (every
            chain of ``samples_per_src`` branching rays, enumerated when the
            calibrator refreshes them, each tried to every receiver by the image
            method), as the twin's chain tracer finds paths
            (:mod:`isac_twin.raytrace.chains`); False: Sionna's candidate generator at
            every trace (its sampled candidates, as ``PathSolver``'s).
    """

    max_depth: int = 2
    samples_per_src: int = 20000
    seed: int = 1
    refraction: bool = True
    chains: bool = False

    @classmethod
    def from_tracer(cls, tracer) -> SolverSettings:
        """The settings of a scene's ``[tracer]`` (:class:`isac_twin.scene.config.TracerConfig`), so
        the model sees the paths the twin's tracer sees.

        Raises:
            CalibrationError: diffuse reflection or diffraction is on (not modelled).
        """
        if tracer.diffuse_reflection or tracer.diffraction or not tracer.los:
            raise CalibrationError("calibrate: the scene's [tracer] has diffuse reflection, "
                                   "diffraction or no line of sight; the calibration models "
                                   "line of sight, specular reflection and refraction only")
        return cls(max_depth=tracer.max_depth, samples_per_src=tracer.samples_per_src,
                   seed=tracer.seed, refraction=tracer.refraction, chains=tracer.uses_chains)



@dataclass(frozen=True)
class _LinkGroup:
    """One link of a :class:`ForwardModel`: its transmitter (``src``: Dr.Jit position,
    orientation, array element offsets) and its snapshots' receivers (``tgt``), ``n``
    snapshots, the antennas at either end, the arrays' patterns, the measured power
    (dB, float64 ``[N * Nr * Nt * K]``), the link's weight in the mismatch (its
    share of all snapshots) and the measurements' noise variance added to the model's
    power (float64 ``[N * Nr * Nt * K]``, or None)."""

    src: tuple
    tgt: tuple
    n: int
    n_tx_ant: int
    n_rx_ant: int
    patterns: tuple
    meas_db: object
    weight: float
    noise: object = None



def _materials(sc, params: list[Parameter]) -> dict[str, list]:
    """Per material target of ``params``: every Sionna radio material of ``sc`` whose ITU
    type or name matches, its ITU frequency callback switched off (the fitted value
    sticks)."""
    out: dict[str, list] = {}
    for p in params:
        if p.kind in MATERIAL_KINDS and p.target not in out:
            mats = [m for m in sc.radio_materials.values()
                    if getattr(m, "itu_type", None) == p.target or m.name == p.target]
            if not mats:
                have = sorted({getattr(m, "itu_type", m.name)
                               for m in sc.radio_materials.values()})
                raise CalibrationError(f"calibrate: parameter {p.name}: no radio material "
                                       f"{p.target!r} in the scene (have: {', '.join(have)})")
            for m in mats:
                m.frequency_update_callback = None  # keep the fitted value
            out[p.target] = mats
    return out


def _objects(sc, params: list[Parameter]) -> dict[str, tuple]:
    """Per object target of ``params``: ``(vertex key of Mitsuba's scene parameters,
    original vertices [V, 3] m, bounding-box centre [3] m, the vertices about the centre
    as Dr.Jit arrays (x, y, z))``."""
    import drjit as dr
    import mitsuba as mi

    out: dict[str, tuple] = {}
    params_mi = sc.mi_scene_params
    for p in params:
        if p.kind in POSE_KINDS and p.target not in out:
            obj = sc.objects.get(p.target)
            if obj is None:
                raise CalibrationError(f"calibrate: parameter {p.name}: no object "
                                       f"{p.target!r} (objects: {', '.join(sc.objects)})")
            key = obj.mi_mesh.id() + ".vertex_positions"
            v = np.array(params_mi[key].numpy(), dtype=np.float64).reshape(-1, 3)
            centre = 0.5 * (v.min(axis=0) + v.max(axis=0))
            # the vertices about the centre as Dr.Jit arrays made once: arrays made
            # afresh from NumPy at every evaluation landed at other alignments, and
            # Dr.Jit compiled the vertex kernel anew for each (2 x 80 ms per
            # evaluation on the lab, of 0.62 s)
            rel = [mi.Float(v[:, 0] - centre[0]), mi.Float(v[:, 1] - centre[1]),
                   mi.Float(v[:, 2])]
            dr.eval(rel)
            out[p.target] = (key, v, centre, rel)
    return out


def _link_groups(sc, links: list[Measurements]) -> list[_LinkGroup]:
    """Replace ``sc``'s devices by one transmitter per link and one receiver per snapshot
    (arrays of isotropic V elements); the scene's arrays become the first link's
    (Sionna's own traces, :meth:`ForwardModel.visibility`)."""
    import drjit as dr
    import mitsuba as mi
    import sionna.rt as rt

    def array(spec):
        rows, cols, dv, dh = spec
        return rt.PlanarArray(num_rows=int(rows), num_cols=int(cols),
                              vertical_spacing=float(dv), horizontal_spacing=float(dh),
                              pattern="iso", polarization="V")

    for name in [n for n in list(sc.transmitters) + list(sc.receivers)]:
        sc.remove(name)
    # one transmitter per link, one receiver per snapshot; each link is traced on its
    # own (a trace of every transmitter to every receiver would trace pairs that were
    # not measured)
    groups = []
    n_all = sum(len(m.rx_positions) for m in links)
    for j, m in enumerate(links):
        tx = rt.Transmitter(f"calib_tx{j}", position=mi.Point3f(*map(float, m.tx_position)),
                            orientation=mi.Point3f(*map(float, m.tx_orientation)))
        rxs = [rt.Receiver(f"calib_rx{j}_{i:04d}", position=mi.Point3f(*map(float, pos)),
                           orientation=mi.Point3f(*map(float, ori)))
               for i, (pos, ori) in enumerate(zip(m.rx_positions, m.rx_orientations))]
        sc.add(tx)
        for r in rxs:
            sc.add(r)
        tx_arr, rx_arr = array(m.tx_array), array(m.rx_array)
        src = sc._endpoints([tx], tx_arr, True, True)[:3]
        tgt = sc._endpoints(rxs, rx_arr, True, True)[:3]
        dr.make_opaque(*src, *tgt)
        groups.append(_LinkGroup(
            src=src, tgt=tgt, n=len(rxs), n_tx_ant=int(m.tx_array[0]) * int(m.tx_array[1]),
            n_rx_ant=int(m.rx_array[0]) * int(m.rx_array[1]),
            patterns=(tx_arr.antenna_pattern.patterns, rx_arr.antenna_pattern.patterns),
            # Sionna's cfr order [N, Nr, (tx=1), Nt, (time=1), K]
            meas_db=mi.Float64(power_db(m.csi.transpose(0, 2, 3, 1)).reshape(-1)),
            weight=len(rxs) / n_all,
            noise=None if m.noise_power is None else mi.Float64(np.repeat(
                m.noise_power, m.csi[0].size))))
    # the scene's arrays: those of the first link (Sionna's own traces, visibility)
    sc.tx_array, sc.rx_array = array(links[0].tx_array), array(links[0].rx_array)
    return groups


class ForwardModel:
    """The channel power of ``scene`` at parameter values, per link, and the mismatch
    to the measured one with its gradient.

    The model owns ``scene`` (a freshly loaded :class:`~isac_twin.scene.twin_scene.TwinScene`):
    it adds its own transmitter and receivers, replaces the scene's arrays by one
    isotropic element and switches the fitted materials' ITU frequency callback off.
    Object offsets are written straight into Mitsuba's vertex buffers, which the
    ``TwinScene``'s edit bookkeeping (``object_poses``, ``content_hash``) does not
    see.

    Args:
        scene: the twin's scene (``isac_twin.scene.twin_scene.load_scene``).
        links: the measurements, one :class:`~isac_twin.calibration.problem.Measurements`
            per link (:func:`~isac_twin.calibration.problem.as_links`).
        params: the parameters (:func:`~isac_twin.calibration.problem.check_parameters`).
        settings: :class:`SolverSettings`.

    Raises:
        CalibrationError: unknown material/object, a parameter whose scene value is
            outside its bounds.
    """

    def __init__(self, scene, links: list[Measurements], params: list[Parameter],
                 settings: SolverSettings):
        import drjit as dr
        import mitsuba as mi

        self._dr, self._mi = dr, mi
        self.params, self.links, self.settings = list(params), list(links), settings
        self.sc = sc = scene.sionna
        self.evaluations = 0
        #: Wall time of each gradient evaluation / of each evaluation without, s.
        self.step_seconds: list[float] = []
        self.forward_seconds: list[float] = []
        self._materials = _materials(sc, self.params)
        self._objects = _objects(sc, self.params)
        #: ``[P]`` the parameters' values in the scene as loaded (0 for pose offsets).
        self.initial = np.array([self._current(p) for p in self.params])
        for p, v in zip(self.params, self.initial):
            lo, hi = p.limits
            if not lo <= v <= hi:
                raise CalibrationError(f"calibrate: parameter {p.name} starts at {v:g}, "
                                       f"outside its bounds [{lo:g}, {hi:g}]")
        self._groups = _link_groups(sc, self.links)
        self.solver, deterministic = path_solver(settings, max(g.n for g in self._groups))
        #: The candidates of the traces (:class:`~isac_twin.calibration.candidates.Candidates`).
        self.candidates = Candidates(sc, settings, self.solver, deterministic,
                                     len(self._groups))
        self._visibility = None  # (values, result) of the last visibility()
        self._freqs = mi.Float(self.links[0].subcarrier_offsets_hz)

    def _current(self, p: Parameter) -> float:
        if p.kind == "permittivity":
            return float(self._materials[p.target][0].relative_permittivity.numpy()[0])
        if p.kind == "conductivity":
            return float(self._materials[p.target][0].conductivity.numpy()[0])
        return 0.0  # pose offsets start at the loaded pose

    def object_radius(self, name: str) -> float:
        """The horizontal distance from object ``name``'s bounding-box centre to its
        farthest vertex, m (as loaded)."""
        _, v, c, _ = self._objects[name]
        return float(np.hypot(v[:, 0] - c[0], v[:, 1] - c[1]).max())

    def refresh_chains(self) -> None:
        """New candidates at the next trace (:meth:`Candidates.refresh
        <isac_twin.calibration.candidates.Candidates.refresh>`)."""
        self.candidates.refresh()

    def apply(self, values: np.ndarray, grad: bool) -> list:
        """Write ``values`` into the scene; return the Dr.Jit variables, one per parameter."""
        dr, mi = self._dr, self._mi
        vars_ = []
        for v in values:
            x = dr.opaque(mi.Float, float(v))  # a literal would recompile every kernel
            if grad:
                dr.enable_grad(x)
            vars_.append(x)
        offsets: dict[str, dict] = {}
        for p, x in zip(self.params, vars_):
            if p.kind == "permittivity":
                for m in self._materials[p.target]:
                    m.relative_permittivity = x
            elif p.kind == "conductivity":
                for m in self._materials[p.target]:
                    m.conductivity = x
            else:
                offsets.setdefault(p.target, {})[p.kind] = x
        if offsets:
            params_mi = self.sc.mi_scene_params
            for obj, off in offsets.items():
                key, _, c, (rx, ry, z) = self._objects[obj]
                dx, dy = off.get("x", mi.Float(0.0)), off.get("y", mi.Float(0.0))
                yaw = off.get("yaw", mi.Float(0.0))
                cs, sn = dr.cos(yaw), dr.sin(yaw)
                cx, cy = float(c[0]), float(c[1])  # a NumPy scalar on the left drops AD
                pts = mi.Point3f(cx + cs * rx - sn * ry + dx, cy + sn * rx + cs * ry + dy, z)
                params_mi[key] = dr.ravel(pts)
            params_mi.update()
            self.sc.scene_geometry_updated()
        return vars_

    def trace_db(self) -> list:
        """Model channel power in dB per link: Dr.Jit float64 arrays ``[N * Nr * Nt * K]``
        (the link's snapshots, antennas and subcarriers), each link traced on its own.

        Sionna's ``PathSolver`` stages (candidate generator, image method, field
        calculator) on a candidate buffer of *fixed* size, and the frequency
        response summed here instead of in Sionna's ``Paths``: the generator finds
        a different number of candidates whenever an object moves, and Sionna's
        kernels bake that number in (as ``Paths`` does the paths per link), so an
        evaluation at new poses recompiled ~12 kernels (13-16 s of LLVM on the
        lab, against ~1 s of work). The candidates are padded to
        :attr:`Candidates.buffer_sizes
        <isac_twin.calibration.candidates.Candidates.buffer_sizes>` (grown by half when a
        trace finds more); the padding is weighted out of the sum. The channel equals
        ``Paths.cfr`` of ``PathSolver`` with ``synthetic_array=True``
        (``tests/engine/calibration/test_forward_model.py``).
        """
        return self.candidates.each_link(self._groups, self._link_cfr_db)

    def _link_cfr_db(self, grp, buf, used):
        """Image method and field calculator on a link's candidates ``buf`` (``used``
        marks those that count: not padding, not a hidden line of sight), and
        its power in dB per snapshot, antenna pair and subcarrier (``[N * Nr * Nt * K]``,
        Dr.Jit float64)."""
        from sionna.rt.utils import map_angle_to_canonical_range

        from ..raytrace.solver_core import image_and_field

        dr, mi = self._dr, self._mi
        s, sc, solver = self.settings, self.sc, self.solver
        (src, src_o, rel_tx), (tgt, tgt_o, rel_rx) = grp.src, grp.tgt
        buf = image_and_field(solver, buf, sc.mi_scene, sc.wavelength, src, tgt,
                              samples_per_src=s.samples_per_src, src_o=src_o, tgt_o=tgt_o,
                              patterns=grp.patterns)
        size = dr.width(buf.valid)
        # H[t, r, s, k] = sum_p a_p exp(j 2pi/lambda (d_r . k_rx,p + d_s . k_tx,p))
        #                 exp(-j 2pi f_k tau_p), over the valid, unpadded p of target t
        n_rx, n_tx, k = grp.n_rx_ant, grp.n_tx_ant, len(self.links[0].subcarrier_offsets_hz)
        # (Paths.cir: the carrier's phase exp(-j 2pi f_c tau) first, as Sionna does)
        w = dr.select(buf.valid & used, mi.Float(1.0), mi.Float(0.0))
        a, tau, t = buf.a[0][0], buf.tau, buf.target_indices
        sn_c, cs_c = dr.sincos(map_angle_to_canonical_range(-2.0 * math.pi * sc.frequency * tau))
        a_re = (dr.real(a) * cs_c - dr.imag(a) * sn_c) * w
        a_im = (dr.real(a) * sn_c + dr.imag(a) * cs_c) * w
        k_tx, k_rx = buf.k_tx, buf.k_rx
        per = n_rx * n_tx * k
        j = dr.arange(mi.UInt, size * per)
        p, rem = j // per, j % per
        r, q = rem // (n_tx * k), rem % (n_tx * k)
        st, kk = q // k, q % k
        tp = dr.gather(mi.UInt, t, p)
        d_rx = dr.gather(mi.Point3f, rel_rx, tp * n_rx + r)
        d_tx = dr.gather(mi.Point3f, rel_tx, st)
        phase = (2.0 * math.pi / sc.wavelength) * (
            dr.dot(d_rx, dr.gather(mi.Vector3f, k_rx, p))
            + dr.dot(d_tx, dr.gather(mi.Vector3f, k_tx, p))) \
            - 2.0 * math.pi * dr.gather(mi.Float, self._freqs, kk) * dr.gather(mi.Float, tau, p)
        sn, cs = dr.sincos(phase)
        are, aim = dr.gather(mi.Float, a_re, p), dr.gather(mi.Float, a_im, p)
        out = tp * per + rem
        # summed in float64: the LLVM backend's atomic adds land in thread order, so a
        # float32 sum differed between calls at the same values (lab: 4 losses of 6
        # within 7e-7, gradients 0.3 % apart), which steered the line search apart
        h_re = dr.zeros(mi.Float64, grp.n * per)
        h_im = dr.zeros(mi.Float64, grp.n * per)
        dr.scatter_add(h_re, mi.Float64(are * cs - aim * sn), out)
        dr.scatter_add(h_im, mi.Float64(are * sn + aim * cs), out)
        pw = h_re * h_re + h_im * h_im
        if grp.noise is not None:  # what a noisy estimate's power is on average
            pw = pw + grp.noise
        return 10.0 * dr.log(pw + POWER_FLOOR) / math.log(10.0)


    def trace(self):
        """Sionna's own ``PathSolver`` on the scene as it is (synthetic arrays)."""
        s = self.settings
        return self.solver(self.sc, max_depth=s.max_depth, samples_per_src=s.samples_per_src,
                            synthetic_array=True, los=True, specular_reflection=True,
                            diffuse_reflection=False, refraction=s.refraction,
                            diffraction=False, seed=s.seed)

    # ------------------------------------------------------------------ API

    def visibility(self, values=None) -> dict[str, dict]:
        """How much of the measured channel each parameter's target touches, from one
        trace (no gradients) at ``values`` (physical units, ``[P]``; default the
        scene's values).

        A path touches a material when one of its interactions (reflection or
        refraction) is on an object of that material, and an object when one is on
        that object. Its power is ``|a|^2`` summed over the antenna pairs.

        Returns:
            ``target -> {"paths": [N] paths touching it per snapshot, "power_share":
            [N] their share of the snapshot's total path power (0..1),
            "strongest_db": [N] the strongest such path relative to the snapshot's
            strongest path, dB (-inf without one)}``, one entry per material or
            object named by a parameter.
        """
        dr = self._dr
        values = np.array(self.initial if values is None else values, float).reshape(-1)
        # the same values twice (calibrate_run: the objects' paths and the materials'
        # observability at the fit): one trace
        if self._visibility is not None and np.array_equal(self._visibility[0], values):
            return self._visibility[1]
        self.apply(values, False)
        paths = self.trace()
        objs = np.asarray(paths.objects.numpy())  # [D, N, T, P] (synthetic array)
        a_re, a_im = (np.asarray(dr.detach(t).numpy()) for t in paths.a)
        pw = (a_re ** 2 + a_im ** 2).sum(axis=(1, 3))  # [N, Nr, T, Nt, P] -> [N, T, P]
        valid = np.asarray(paths.valid.numpy()).reshape(pw.shape)
        # every link's transmitter was traced to every snapshot: keep the measured pairs
        # (the scene's arrays are the first link's: the same gain on every path of a pair)
        snap = np.arange(pw.shape[0])
        link = np.concatenate([np.full(g.n, j) for j, g in enumerate(self._groups)])
        pw, valid = pw[snap, link], valid[snap, link]  # [N, P]
        pw = np.where(valid, pw, 0.0)
        objs = objs.reshape(objs.shape[0], len(snap), len(self._groups), -1)[:, snap, link]
        total = pw.sum(axis=1)
        top = pw.max(axis=1)
        ids: dict[str, set[int]] = {}
        for p in self.params:
            if p.target in ids:
                continue
            if p.kind in MATERIAL_KINDS:
                mats = {id(m) for m in self._materials[p.target]}
                ids[p.target] = {int(o.object_id) for o in self.sc.objects.values()
                                 if id(o.radio_material) in mats}
            else:
                ids[p.target] = {int(self.sc.objects[p.target].object_id)}
        out = {}
        for target, oids in ids.items():
            hit = np.isin(objs, list(oids)).any(axis=0) & valid  # [N, P]
            share = np.where(total > 0, (pw * hit).sum(axis=1) / np.where(total > 0, total, 1),
                             0.0)
            strongest = np.where(hit, pw, 0.0).max(axis=1)
            with np.errstate(divide="ignore"):
                rel = np.where(strongest > 0, 10 * np.log10(strongest / np.where(top > 0, top, 1)),
                               -np.inf)
            out[target] = {"paths": hit.sum(axis=1).astype(int), "power_share": share,
                           "strongest_db": rel}
        self._visibility = (values, out)
        return out

    def evaluate(self, values, grad: bool = True) -> tuple[float, np.ndarray, np.ndarray]:
        """Mismatch at ``values`` (physical units, ``[P]``).

        Returns:
            ``(mismatch dB^2, gradient [P] in dB^2 per unit, model power per link
            [N, K, Nr, Nt] dB)``.
        """
        dr = self._dr
        t0 = time.perf_counter()
        values = np.asarray(values, float).reshape(-1)
        vars_ = self.apply(values, grad)
        models_db = self.trace_db()
        loss = None
        for grp, model_db in zip(self._groups, models_db):
            diff = model_db - grp.meas_db
            # each snapshot counts the same (one link: weight 1, the mean itself)
            term = grp.weight * dr.mean(diff * diff)
            loss = term if loss is None else loss + term
        g = np.zeros(len(values))
        if grad:
            dr.eval(loss)  # the forward pass on every thread
            # The backward pass on one thread: it accumulates the gradients with
            # float32 atomic adds, which on two threads land in timing order, so
            # the gradient at the same values differed in its last bits between
            # calls; L-BFGS-B amplified that into different fits of the same lap
            # (the tables' permittivity 3.1 %, 6.0 % and 20.6 % off in three runs).
            threads = dr.thread_count()
            dr.set_thread_count(1)
            try:
                # at some bounds (conductivity 0) Sionna's graph no longer depends
                # on a parameter: its gradient is then 0, not an error
                dr.backward(loss, flags=dr.ADFlag.Default | dr.ADFlag.AllowNoGrad)
                g = np.array([float(dr.grad(x)[0]) for x in vars_])
            finally:
                dr.set_thread_count(threads)
        k = len(self._freqs)
        models = [np.array(dr.detach(m).numpy(), float)
                  .reshape(grp.n, grp.n_rx_ant, grp.n_tx_ant, k).transpose(0, 3, 1, 2)
                  for grp, m in zip(self._groups, models_db)]
        out = float(loss[0]), g, models
        if grad:  # leave the scene at values, detached from the graph (a BVH rebuild)
            self.apply(values, False)
        self.evaluations += 1
        (self.step_seconds if grad else self.forward_seconds).append(time.perf_counter() - t0)
        return out
