"""Echo and clutter paths of sensing links, traced with Sionna RT.

Targets. Every robot (and any scene object tagged as a target) is put into
the Sionna scene as a ``sionna.rt.rcs.ConstantRCSSensingTarget``: a cuboid
the size of the body (TurtleBot3 Burger 0.14 x 0.18 x 0.19 m by default)
with one scattering point of constant radar cross-section ``sigma`` [m^2]
at its centre. The cuboid is moved to the robot's pose and given its
velocity every step, so the echo's Doppler follows the robot.

Echo paths come from Sionna's ``RCSSolver`` (tx -> ... -> scattering point
-> ... -> rx; both legs may reflect off the room up to ``max_depth - 1``
times). Every path it returns touches a target by construction, and
``Paths.objects`` at the ``SENSING`` interaction gives the target index, so
echoes are attributed to targets exactly (``EchoPaths.target``).

Clutter paths (the static room: direct tx -> rx coupling, walls,
furniture) come from Sionna's ``PathSolver``, for which sensing targets are
absorbers: no clutter path touches a target. Clutter is cached and only
re-traced when the scene is edited (``TwinScene.revision``) -- the
shadowing of clutter by a moving robot is therefore not modelled.

Monostatic links (tx == rx) trace the echo with a receiver co-located with
the transmitter (the RCS solver pairs both legs at the scattering point, so
no dummy node is needed for the echo). The clutter of a monostatic node
needs a distinct receiver point: a dummy receiver displaced by
``monostatic_offset_m`` (paper sec. III-A) is used, and the direct
tx -> dummy coupling (self-interference) is removed, i.e. assumed cancelled
by the full-duplex front end.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from ..contract import schema
from ..raytrace.base import LinkPaths, empty_link
from ..raytrace.solver_core import load_sionna_rt
from ..utils.geometry import DevicePose, sionna_orientation

log = logging.getLogger(__name__)

__all__ = ["TargetSpec", "EchoPaths", "SensingTracer", "BURGER_SIZE"]

#: TurtleBot3 Burger footprint and height (length, width, height) [m] (addon/contract/schema.py).
BURGER_SIZE = schema.ROBOT_MODELS["burger"].size

SENSING_INTERACTION = 16


@dataclass
class TargetSpec:
    """A sensing target.

    Attributes:
        name: target name (a robot's device name or a scene object's name).
        size: cuboid ``(length, width, height)`` [m].
        sigma: radar cross-section [m^2] of its scattering point.
        position: centre ``[3]`` [m].
        yaw: heading [rad].
        velocity: ``[3]`` [m/s].
    """

    name: str
    size: tuple = BURGER_SIZE
    sigma: float = 0.5
    position: np.ndarray = field(default_factory=lambda: np.zeros(3))
    yaw: float = 0.0
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))


@dataclass
class EchoPaths:
    """Paths of one sensing link in one step.

    Attributes:
        echo: paths that touch a target (``LinkPaths``).
        target: ``[L_echo]`` name of the target each echo path scatters on.
        clutter: paths that touch no target (static room).
    """

    echo: LinkPaths
    target: list
    clutter: LinkPaths



def _to_numpy_paths(paths, num_rx: int, num_tx: int, depth: int):
    """Numpy copy of a Sionna ``Paths`` (synthetic array), incl. object ids."""
    tau = np.asarray(paths.tau.numpy(), np.float64).reshape(num_rx, num_tx, -1)
    p = tau.shape[-1]
    out = {"tau": tau}
    if p == 0:
        return out, 0
    ar, ai = paths.a
    out["a"] = (np.asarray(ar.numpy(), np.float64)
                + 1j * np.asarray(ai.numpy(), np.float64)).reshape(num_rx, num_tx, p)
    for k in ("doppler", "theta_t", "phi_t", "theta_r", "phi_r"):
        out[k] = np.asarray(getattr(paths, k).numpy(), np.float64).reshape(num_rx, num_tx, p)
    out["valid"] = np.asarray(paths.valid.numpy(), bool).reshape(num_rx, num_tx, p)
    inter = np.asarray(paths.interactions.numpy()).reshape(-1, num_rx, num_tx, p)
    objs = np.asarray(paths.objects.numpy()).reshape(-1, num_rx, num_tx, p)
    vert = np.asarray(paths.vertices.numpy(), np.float64).reshape(-1, num_rx, num_tx, p, 3)
    out["interactions"] = np.moveaxis(inter, 0, -1).astype(np.int32)
    out["objects"] = np.moveaxis(objs, 0, -1).astype(np.int64)
    v = np.array(np.moveaxis(vert, 0, -2))
    v[out["interactions"] == 0] = 0.0
    out["vertices"] = v
    return out, p


def _link_paths(raw, r, t, tx, rx, pt: DevicePose, pr: DevicePose, f, depth, keep=None):
    if "valid" not in raw:
        return empty_link(tx, rx, pt, pr, f, depth), np.zeros((0, depth), np.int64)
    m = raw["valid"][r, t].copy()
    if keep is not None:
        m &= keep
    order = np.argsort(raw["tau"][r, t][m], kind="stable")
    g = {k: raw[k][r, t][m][order] for k in ("a", "tau", "doppler", "theta_t", "phi_t",
                                              "theta_r", "phi_r", "interactions", "vertices",
                                              "objects")}
    if g["tau"].size == 0:
        return (empty_link(tx, rx, pt, pr, f, raw["interactions"].shape[-1]),
                np.zeros((0, raw["interactions"].shape[-1]), np.int64))
    lp = LinkPaths(tx=tx, rx=rx, tx_position=np.asarray(pt.position),
                   rx_position=np.asarray(pr.position),
                   tx_orientation=np.asarray(pt.orientation),
                   rx_orientation=np.asarray(pr.orientation), frequency_hz=f,
                   **{k: g[k] for k in ("a", "tau", "doppler", "theta_t", "phi_t", "theta_r",
                                        "phi_r", "interactions", "vertices")})
    return lp, g["objects"]


class SensingTracer:
    """Traces echo (RCS solver) and clutter (path solver) paths of sensing links.

    Args:
        scene: the :class:`~isac_twin.scene.twin_scene.TwinScene` (its Sionna scene is shared
            with the twin's tracer; devices are re-synced on every call).
        max_depth: echo paths: total interactions incl. the scattering event
            (1 = direct tx -> target -> rx only); clutter: reflections.
        samples: rays per scattering point / per source.
        seed: solver seed (fixed, with Sionna's deterministic candidate
            generators -> the same paths on every call, whatever else runs).
        monostatic_offset_m: displacement of the dummy clutter receiver of a
            monostatic link [m].
    """

    def __init__(self, scene, *, max_depth: int = 2, clutter_depth: int = 3,
                 samples: int = 20000, seed: int = 1,
                 monostatic_offset_m: float = 0.1) -> None:
        self.scene = scene
        self.max_depth = int(max_depth)
        self.clutter_depth = int(clutter_depth)
        self.samples = int(samples)
        self.seed = int(seed)
        self.mono_offset = float(monostatic_offset_m)
        self._targets: dict[str, object] = {}
        self._specs: dict[str, TargetSpec] = {}
        self._clutter_cache: dict = {}
        rt = load_sionna_rt()
        from sionna.rt.rcs import RCSSolver

        # Sionna's deterministic candidate generators: with the default ones the
        # order in which rays record their paths (atomic counters) follows the
        # thread schedule, and the paths' gains changed at float32 level when the
        # twin's tracer ran at the same time (the sensing worker); same cost.
        self._rcs = RCSSolver(deterministic=True)
        self._ps = rt.PathSolver(deterministic=True)
        self._iso = rt.PlanarArray(num_rows=1, num_cols=1, pattern="iso", polarization="V")

    # ------------------------------------------------------------------ targets

    @property
    def targets(self) -> dict[str, TargetSpec]:
        """name -> current :class:`TargetSpec`."""
        return dict(self._specs)

    def set_target(self, spec: TargetSpec) -> None:
        """Add a target to the Sionna scene or update its pose/velocity."""
        import mitsuba as mi
        from sionna.rt.rcs import ConstantRCSSensingTarget

        sc = self.scene.sionna
        st = self._targets.get(spec.name)
        if st is None:  # another tracer on this scene may have added it already
            st = sc.sensing_targets.get(f"target:{spec.name}")
            if st is not None:
                st.sigma = float(spec.sigma)
                self._targets[spec.name] = st
        if st is None:
            length, width, height = (float(v) for v in spec.size)
            st = ConstantRCSSensingTarget(name=f"target:{spec.name}", sigma=float(spec.sigma),
                                          length=length, width=width, height=height,
                                          position=[float(v) for v in spec.position])
            sc.add(st)
            self._targets[spec.name] = st
        st.position = mi.Point3f(*(float(v) for v in spec.position))
        st.orientation = mi.Point3f(float(spec.yaw), 0.0, 0.0)
        st.velocity = mi.Vector3f(*(float(v) for v in spec.velocity))
        self._specs[spec.name] = spec

    def remove_target(self, name: str) -> None:
        """Take a target out of the scene."""
        st = self._targets.pop(name, None)
        if st is not None:
            self.scene.sionna.edit(remove=[st.name])
        self._specs.pop(name, None)

    # ------------------------------------------------------------------ trace

    def _devices_view(self, txs: Mapping[str, DevicePose], rxs: Mapping[str, DevicePose]):
        """A view of the twin's Sionna scene with this tracer's own devices.

        The view is a :class:`sionna.rt.Scene` sharing everything of the twin's
        scene (Mitsuba scene, objects, radio materials, sensing targets) except
        the transmitters, receivers and arrays, which it holds itself: the
        sensing solvers read those from the scene they are given, and the
        twin's tracer sets the scene's arrays to its own. So tracing the sensing
        links never writes to the twin's scene, and it may run on another
        thread while the twin's tracer runs (:class:`~isac_twin.sensing.worker.SensingWorker`).
        """
        rt = load_sionna_rt()
        sc = self.scene.sionna
        view = object.__new__(type(sc))
        view.__dict__.update(sc.__dict__)
        view._transmitters, view._receivers = {}, {}
        view._tx_array = view._rx_array = self._iso
        view._preview_widget = None
        devs = [rt.Transmitter(f"stx:{n}", position=list(p.position),
                               orientation=list(sionna_orientation(p.orientation)),
                               velocity=list(p.velocity)) for n, p in txs.items()]
        devs += [rt.Receiver(f"srx:{n}", position=list(p.position),
                             orientation=list(sionna_orientation(p.orientation)),
                             velocity=list(p.velocity)) for n, p in rxs.items()]
        view.add(devs)
        return view

    def __call__(self, poses: Mapping[str, DevicePose],
                 links: list[tuple[str, str]]) -> dict[tuple[str, str], EchoPaths]:
        """Trace the echo and clutter paths of ``links`` (``(tx, rx)``; tx == rx
        is monostatic). ``poses`` gives every device's array centre."""
        for tx, rx in links:
            for n in (tx, rx):
                if n not in poses:
                    raise ValueError(f"sensing link {tx}->{rx}: no pose for device {n!r}")
        f = float(self.scene.config.scene.frequency_hz)
        txs = {t: poses[t] for t, _ in links}
        rxs = {r: poses[r] for _, r in links}
        tx_names, rx_names = list(txs), list(rxs)
        out: dict = {}
        echo_raw = None
        if self._targets:
            view = self._devices_view(txs, rxs)
            paths = self._rcs(view, max_depth=self.max_depth,
                              samples_per_sp=self.samples, buffer_size_per_sp=self.samples,
                              seed=self.seed)
            echo_raw, _ = _to_numpy_paths(paths, len(rx_names), len(tx_names), self.max_depth)
        clutter = self._clutter(poses, links, f)
        names = [n[len("target:"):] for n in self.scene.sionna.sensing_targets]
        for tx, rx in links:
            pt, pr = poses[tx], poses[rx]
            if echo_raw is None:
                echo = empty_link(tx, rx, pt, pr, f, self.max_depth)
                tgt = []
            else:
                echo, objs = _link_paths(echo_raw, rx_names.index(rx), tx_names.index(tx),
                                         tx, rx, pt, pr, f, self.max_depth)
                slot = np.argmax(echo.interactions == SENSING_INTERACTION, axis=1)
                idx = objs[np.arange(echo.num_paths), slot] if echo.num_paths else []
                tgt = [names[int(i)] if 0 <= int(i) < len(names) else "?" for i in idx]
            out[(tx, rx)] = EchoPaths(echo=echo, target=tgt, clutter=clutter[(tx, rx)])
        return out

    def _clutter(self, poses, links, f) -> dict:
        """Static clutter paths per link (cached per scene revision and poses)."""
        out = {}
        todo = []
        for tx, rx in links:
            pt, pr = poses[tx], poses[rx]
            key = (tx, rx, self.scene.revision, pt.position, pr.position, pt.orientation)
            hit = self._clutter_cache.get((tx, rx))
            if hit is not None and hit[0] == key:
                out[(tx, rx)] = hit[1]
            else:
                todo.append((tx, rx, key))
        if not todo:
            return out
        txs, rxs = {}, {}
        for tx, rx, _ in todo:
            txs[tx] = poses[tx]
            pr = poses[rx]
            if tx == rx:
                pos = np.asarray(pr.position) + np.array([0.0, 0.0, -self.mono_offset])
                pr = DevicePose(tuple(pos), pr.orientation, pr.velocity)
            rxs[rx + ("#dummy" if tx == rx else "")] = pr
        view = self._devices_view(txs, rxs)
        paths = self._ps(view, max_depth=self.clutter_depth,
                         max_num_paths_per_src=max(self.samples, 100000),
                         samples_per_src=max(self.samples, 100000), synthetic_array=True,
                         seed=self.seed)
        raw, _ = _to_numpy_paths(paths, len(rxs), len(txs), self.clutter_depth)
        tx_names, rx_names = list(txs), list(rxs)
        for tx, rx, key in todo:
            rname = rx + ("#dummy" if tx == rx else "")
            keep = None
            if tx == rx and "valid" in raw:
                # drop the direct tx -> dummy coupling (self-interference, cancelled)
                keep = np.any(raw["interactions"][rx_names.index(rname), tx_names.index(tx)] != 0,
                              axis=-1)
            lp, _ = _link_paths(raw, rx_names.index(rname), tx_names.index(tx), tx, rx,
                                poses[tx], poses[rx], f, self.clutter_depth, keep=keep)
            self._clutter_cache[(tx, rx)] = (key, lp)
            out[(tx, rx)] = lp
        log.debug("traced clutter of %d sensing link(s)", len(todo))
        return out
