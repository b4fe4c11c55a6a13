"""The twin: Algorithm 1 of the paper, the only place that wires the layers together.

Each :meth:`Twin.step`:

1. agent states ``s_t = f(s_{t-1}, u_{t-1}) + noise``      (robots/)
2. re-trace all Tx/Rx pairs -> path parameters            (raytrace/)
3. MIMO-OFDM channels, precoding, power, rates (eqs. 1-4) (phy/)
4. measurements and observations ``o_t = g(s_t, m_t)``     (robots/sensors, phy/)
5. state estimates (pluggable estimators, e.g. fingerprint localization)
6. next controls ``u_t``                                   (robots/control)

Sensors (stage 4) are sampled inside each robot agent right after its
motion update; the agent's controller publishes ``u_t`` on ``cmd_vel`` after
the estimators have run (stage 6). Edits and commands received between steps
are applied before the next step starts.
"""

from __future__ import annotations

import gc
import hashlib
import logging
import shutil
import tempfile
import time
import weakref
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..bus import frames
from ..bus.bus import Bus
from ..bus.msgs import Clock, Csi, Header, TFMessage, quaternion_to_yaw
from ..contract import wire
from ..errors import ConfigError, MeshError, PathError
from ..phy.network import NetworkPHY
from ..raytrace import make_tracer
from ..robots import SensorOptions, build_robots, cast_scans
from ..robots.control import controller_from_spec
from ..scene.meshes import confine, parse_ply, read_ply
from ..scene.room import ROBOT_BODY_HEIGHT_M, path_obstruction
from ..scene.twin_scene import BOUNDS_TOLERANCE_M, TwinScene, load_scene
from ..utils.geometry import DevicePose, antenna_pose
from ..utils.threads import one_blas_thread
from .state import Command, Edit, LinkState, RobotState, StepResult

log = logging.getLogger(__name__)

#: The timed stages of :meth:`Twin.step`: agents (motion, sensors, their topics,
#: ``/tf``), trace, phy, publish (the step's result and the CSI for its
#: subscribers, e.g. a recorder), sense (``[[sensing]]`` radar), estimate, control.
STAGES = ("agents", "trace", "phy", "publish", "sense", "estimate", "control")

#: Largest mesh an ``add`` edit may name, bytes.
MAX_EDIT_MESH_BYTES = 32 * 1024 * 1024
#: Most single steps one ``step`` command may request.
MAX_STEP_COUNT = 100_000

#: ``estimator(twin, result) -> None``: fills ``result.robots[name].estimate``.
Estimator = Callable[["Twin", StepResult], None]


@dataclass
class RunStats:
    """What a paced run measured.

    Attributes:
        steps: steps run.
        wall_s: wall time, s.
        overruns: steps that took longer than the period (paced runs only).
        stage_s: total wall time per stage, s.
        overrun_stages: overruns per cause: the step's longest stage (one of
            :data:`STAGES`), or ``"caller"`` when the code that consumed the step
            between two steps (e.g. printing, recording) took longer than any stage.
        overrun_ms: total time by which paced steps missed their deadline, ms.
        stage_cpu_s: total CPU time of the stepping thread per stage, s (next to
            ``stage_s``: on a shared machine a stage whose wall time far exceeds
            its CPU time waited for a core; Dr.Jit's kernel threads and BLAS
            threads are not counted, so for ``trace`` it is the Python side).
        startup_s: the start-up of a paced run, s: the twin's first step
            (chain enumeration, kernel recording and compilation; with a radar
            also its first frame and the second step, see :meth:`Twin.run`),
            which the schedule starts after and which is no overrun.
    """

    steps: int = 0
    wall_s: float = 0.0
    overruns: int = 0
    stage_s: dict[str, float] = field(default_factory=lambda: {s: 0.0 for s in STAGES})
    overrun_stages: dict[str, int] = field(default_factory=dict)
    overrun_ms: float = 0.0
    stage_cpu_s: dict[str, float] = field(default_factory=lambda: {s: 0.0 for s in STAGES})
    startup_s: float = 0.0

    def overrun_summary(self) -> str:
        """``"N overruns"`` with their causes, e.g. ``"2 overruns (trace 2; 3.1 ms late)"``,
        and the start-up's time when a paced run had one."""
        start = f" after a {self.startup_s:.2f} s start-up" if self.startup_s else ""
        if not self.overruns:
            return f"0 overruns{start}"
        causes = ", ".join(f"{k} {v}" for k, v in sorted(self.overrun_stages.items(),
                                                         key=lambda kv: -kv[1]))
        return (f"{self.overruns} overruns ({causes}; {self.overrun_ms:.1f} ms late in "
                f"total){start}")

    def table(self) -> str:
        """A per-stage timing breakdown (mean wall ms per step, share, and the
        stepping thread's CPU ms per step)."""
        n = max(self.steps, 1)
        total = sum(self.stage_s.values()) or 1e-12
        lines = [f"{self.steps} steps in {self.wall_s:.2f} s "
                 f"({self.steps / max(self.wall_s, 1e-12):.1f} steps/s), {self.overrun_summary()}",
                 f"  {'stage':<10} {'ms/step':>9} {'share':>6} {'cpu ms':>8}"]
        for s in STAGES:
            lines.append(f"  {s:<10} {1e3 * self.stage_s[s] / n:9.2f} "
                         f"{100 * self.stage_s[s] / total:5.1f}% "
                         f"{1e3 * self.stage_cpu_s.get(s, 0.0) / n:8.2f}")
        return "\n".join(lines)


class _StageClock:
    """Wall time and the calling thread's CPU time of consecutive stages, s:
    :meth:`mark` closes the stage that began at the previous mark (or at creation)."""

    __slots__ = ("wall", "cpu", "_t", "_c")

    def __init__(self) -> None:
        self.wall: dict[str, float] = {}
        self.cpu: dict[str, float] = {}
        self._t, self._c = time.perf_counter(), time.thread_time()

    def mark(self, stage: str) -> None:
        t, c = time.perf_counter(), time.thread_time()
        self.wall[stage], self.cpu[stage] = t - self._t, c - self._c
        self._t, self._c = t, c


class Twin:
    """A digital twin of one scene folder, stepped by Algorithm 1.

    Args:
        scene: the loaded :class:`~isac_twin.scene.twin_scene.TwinScene`.
        seed: one seed for every random stream (robots, sensors, noise).
        dt: simulated time per step, s.
        sensors: which simulated sensors the robots carry.
        tracer: a ray-tracing backend (default: the config's ``[tracer]``).
        phy: compute channels and rates each step (stage 3).
        estimators: stage-5 callables, run in order.
        sensing: run the config's ``[[sensing]]`` radar links (stage "sense",
            before the estimators; see :meth:`_build_sensing`).
        sync_sensing: compute each radar frame on the stepping thread, within its
            step (``result.sensing`` of the sensed step). Default: on a worker
            thread while the next steps run, delivered a fixed number of steps
            later (:class:`~isac_twin.sensing.worker.SensingWorker`; the same frames,
            stamped with the step they sensed).
        sensing_process: compute the radar frames in a child process instead of
            a thread (:class:`~isac_twin.sensing.process.SensingProcess`: the same
            frames on the same steps; the twin's steps no longer wait behind a
            frame for the interpreter or Dr.Jit's threads, which a paced run
            needs). Not with ``sync_sensing``.
        asset_dirs: folders an ``add`` edit may name a mesh in by absolute path
            (besides the scene folder, where paths are relative).
        localize: run the config's ``[localization]`` (a
            :class:`~isac_twin.localization.estimator.TwinLocalizer` appended to
            the estimators; it fills ``robots[r].estimate`` every step).

    Hooks (the supported way to change how a twin steps; never replace a method
    of a live twin or agent):

    * :meth:`set_state_source` -- a robot's state comes from outside (a
      recording, a real robot) instead of its simulated motion model (stage 1).
    * :attr:`trace_schedule` -- ``schedule(step_index) -> bool``: trace the
      links on this step (stage 2); on other steps the step has no links, no
      signals and no CSI. ``None`` (default) traces every step.
    * :attr:`estimators` -- stage-5 observers ``est(twin, result)``, run in order.
    * CSI consumers -- ``/<robot>/csi`` (:class:`~isac_twin.bus.msgs.Csi`, the channel
      on every symbol) is built and published only while something subscribes
      to it on :attr:`bus` (the recorder, a bridge sharing it, the live view, an
      estimator that needs pilots: :meth:`isac_twin.bus.bus.Bus.has_subscribers`); the
      PHY keeps one channel per symbol group and
      :attr:`~isac_twin.phy.network.LinkSignal.h` expands it only when read.
    * Scan consumers -- the ray-cast sensors (``/<robot>/scan``,
      ``/<robot>/camera/depth``) are rendered only while something subscribes to
      their topic; a skipped scan advances the sensor's schedule and noise stream
      as if taken, so a subscriber gets the same scans whenever it arrives
      (:class:`~isac_twin.robots.agent.RobotAgent` ``render_unheard``).
    """

    def __init__(self, scene: TwinScene, *, seed: int = 0, dt: float = 0.05,
                 sensors: SensorOptions | None = None, tracer=None, phy: bool = True,
                 estimators: list[Estimator] | None = None, sensing: bool = True,
                 asset_dirs: list[str | Path] | tuple = (),
                 localize: bool = True, sync_sensing: bool = False,
                 sensing_process: bool = False) -> None:
        if not dt > 0:
            raise ValueError(f"dt: expected a positive step in s, got {dt}")
        if sync_sensing and sensing_process:
            raise ValueError("sync_sensing and sensing_process: choose one (the radar "
                             "frames on the stepping thread or in a child process)")
        self.scene = scene
        self.config = scene.config
        self.seed, self.dt = int(seed), float(dt)
        self.sensor_options = sensors
        self.tracer = tracer if tracer is not None else make_tracer(self.config)
        self.phy = NetworkPHY(self.config) if phy else None
        self.estimators: list[Estimator] = list(estimators or [])
        #: the ``[localization]`` estimator (a TwinLocalizer, last of the
        #: estimators), or None without that table or with ``localize=False``
        self.localizer = None
        self.sensing_enabled = bool(sensing) and bool(self.config.sensing)
        self.sync_sensing = bool(sync_sensing)
        self.sensing_process = bool(sensing_process)
        #: the ``[[sensing]]`` radar (a RadarEstimator), rebuilt by reset(); None without
        self.radar = None
        #: the radar's worker thread (a SensingWorker) or process (a
        #: SensingProcess); None without a radar or with ``sync_sensing``
        self.sensing_worker = None
        #: ``schedule(step_index) -> bool``: trace on this step (None: every step)
        self.trace_schedule: Callable[[int], bool] | None = None
        #: robot name -> ``source(t, dt) -> KinematicState`` replacing its motion model
        self.state_sources: dict[str, StateSource] = {}
        #: keep stepping (a driver such as the live server reads it; ``run``/``pause``)
        self.running = True
        #: steps requested by ``step`` commands and not yet taken (``pause`` clears them)
        self.pending_steps = 0
        self.asset_dirs = [Path(d) for d in asset_dirs]
        self._upload_dir: Path | None = None
        self._pending_edits: list[Edit] = []
        #: access points' array poses ``(position, orientation)``, movable by edits
        self.ap_poses = {d.name: (tuple(d.position), tuple(d.orientation))
                         for d in self.config.devices if d.kind != "robot"}
        #: name -> (scene content hash, access-point poses) a database was built for
        self.databases: dict[str, tuple[str, dict]] = {}
        grid = getattr(self.tracer, "grid", None)
        if grid is not None:
            self.register_database(str(grid.path or "grid tracer"), grid.meta["scene_hash"])
        self._controllers: dict[str, object] = {}
        self._build_agents()
        for i, d in enumerate(self.config.devices):
            if d.kind == "robot" and d.path is not None:  # checked in free space at load
                try:
                    self.set_path(d.name, d.path, check_free_space=False)
                except ValueError as exc:  # e.g. a path leaving the room: the file's fault
                    raise ConfigError(f"{self.config.path}: devices[{i}] ({d.name}).path: "
                                      f"{exc}") from None
        if localize and self.config.localization is not None:
            self._build_localizer()

    @classmethod
    def from_scene(cls, path: str | Path, **kw) -> Twin:
        """Load a scene folder (or ``twin.toml``) and build its twin."""
        return cls(load_scene(path), **kw)

    # ------------------------------------------------------------------ setup

    def _build_agents(self) -> None:
        self.bus = Bus()
        self.agents = build_robots(self.config, self.bus, self.scene, seed=self.seed,
                                   options=self.sensor_options, render_unheard=False)
        for name, agent in self.agents.items():
            # The robot's radio is a sensor too: the CSI of every link it receives.
            agent.topics["csi"] = f"/{name}/csi"
            agent.node.advertise(agent.topics["csi"], Csi)
        # REP-105 frames and the simulated clock (isac_twin.bus.frames)
        self._tf_node = self.bus.node("twin_tf")
        for topic, typ in (("/tf", TFMessage), ("/tf_static", TFMessage), ("/clock", Clock)):
            self._tf_node.advertise(topic, typ)
        for name, ctl in self._controllers.items():
            if hasattr(ctl, "reset"):
                ctl.reset()
            self.agents[name].drive(ctl)
        self._build_sensing()
        self.step_index = 0
        self.time_s = 0.0
        self.stats = RunStats()
        self.last: StepResult | None = None

    def _build_sensing(self) -> None:
        """One :class:`~isac_twin.sensing.estimator.RadarEstimator` for every
        ``[[sensing]]`` table (fresh tracker after a reset); its detections
        topic is advertised on the new bus at once."""
        old = self.sensing_worker
        if old is not None and not self.sensing_process:  # a reset: the old frame is dropped
            old.close()
            self.sensing_worker = old = None
        if not self.sensing_enabled:
            return
        from ..sensing.config import parse_sensing
        from ..sensing.estimator import RadarEstimator
        from ..sensing.process import SensingProcess
        from ..sensing.worker import SensingWorker

        self.radar = RadarEstimator(parse_sensing(self.config), seed=self.seed)
        self.radar.attach(self.bus)
        if self.sync_sensing:
            return
        latency = min(max(int(s.every), 1) for s in self.radar.links)
        if not self.sensing_process:
            self.sensing_worker = SensingWorker(self.radar, latency)
        elif old is not None:  # a reset: the child drops its frame and starts a new radar
            old.reset(self.radar.links, self.seed)
        else:
            self.sensing_worker = SensingProcess(self.scene, self.radar.links, self.seed,
                                                 latency)

    def _build_localizer(self) -> None:
        """The ``[localization]`` estimator, appended to :attr:`estimators` once
        (its fingerprint database is loaded or built now)."""
        from ..localization.estimator import TwinLocalizer

        self.localizer = TwinLocalizer.for_twin(self)
        self.estimators.append(self.localizer)

    def reset(self) -> None:
        """Back to the initial state (same seed: the same run again). Room edits and
        moved access points stay; robots return to their start. The hooks (state
        sources, trace schedule, estimators) stay attached."""
        self._build_agents()

    def set_controller(self, robot: str, controller) -> None:
        """Drive ``robot`` with ``controller(state) -> Twist`` from the next step on."""
        if robot not in self.agents:
            raise KeyError(f"no robot named {robot!r} (robots: {', '.join(self.agents)})")
        self._controllers[robot] = controller
        self.agents[robot].drive(controller)

    def set_state_source(self, robot: str, source: StateSource | None) -> None:
        """Take ``robot``'s state from ``source(t, dt) -> KinematicState`` each step
        (t: the step's end time, s; dt: step, s) instead of simulating its motion;
        ``None`` returns it to simulation. A sourced robot is placed, not driven:
        its controller does not run and it publishes ground truth and scene
        sensors only (:meth:`isac_twin.robots.RobotAgent.place`).
        """
        if robot not in self.agents:
            raise KeyError(f"no robot named {robot!r} (robots: {', '.join(self.agents)})")
        if source is None:
            self.state_sources.pop(robot, None)
        else:
            self.state_sources[robot] = source

    def set_path(self, robot: str, spec: dict, *, check_free_space: bool = True) -> None:
        """Follow a path given as a spec dict, e.g. ``{"kind": "circle", "centre": [4, 3],
        "radius": 1.5}``; the path must lie inside the room and in free space (not
        through a wall or furniture as the room is now: :mod:`isac_twin.scene.room`).

        Raises:
            KeyError: unknown robot. PathError: the path leaves the room or free space,
                or the robot cannot follow it.
        """
        agent = self.agents.get(robot)
        if agent is None:
            raise KeyError(f"no robot named {robot!r} (robots: {', '.join(self.agents)})")
        bounds = (self.scene.bounds_min[:2], self.scene.bounds_max[:2])
        ctl = controller_from_spec(spec, agent.spec, bounds=bounds)
        st = agent.state
        msg = None if not check_free_space else path_obstruction(
            self.scene, spec, (st.x, st.y),
            self.config.device(robot).position[2] + ROBOT_BODY_HEIGHT_M)
        if msg is not None:
            raise PathError(f"set_path({robot}): {msg}")
        self.set_controller(robot, ctl)

    # ------------------------------------------------------------------ edits

    def validate_edit(self, edit: Edit) -> None:
        """Check an edit completely against the twin as it is now.

        The one validation of edits: :meth:`apply_edit` calls it before queuing,
        so the live server (which queues through ``apply_edit``) answers a bad
        edit at once and the twin never meets it in a step.

        Raises:
            ValueError: naming the edit (op and target) and the field at fault.
        """
        what = f"edit {edit.op} {edit.target!r}"
        if edit.op not in wire.EDIT_OPS:
            raise ValueError(f"{what}: op: expected one of {', '.join(wire.EDIT_OPS)}")
        objects = self.scene.objects
        devices = set(self.ap_poses) | set(self.agents)

        def triple(field, value, margin=None):
            try:
                v = np.asarray(value, dtype=np.float64).reshape(-1)
            except (TypeError, ValueError):
                v = np.zeros(0)
            if v.shape != (3,) or not np.isfinite(v).all():
                raise ValueError(f"{what}: {field}: expected 3 finite numbers, got {value!r}")
            if margin is None:
                return
            lo = np.asarray(self.scene.bounds_min, float) - margin
            hi = np.asarray(self.scene.bounds_max, float) + margin
            if not (np.all(v >= lo) and np.all(v <= hi)):
                where = ("the room's extent" if margin == 0 else
                         f"the room's extent grown by {margin:.3g} m")
                raise ValueError(f"{what}: {field}: {v.tolist()} lies outside {where} "
                                 f"{np.round(lo, 3).tolist()}..{np.round(hi, 3).tolist()} m")

        def material(required):
            if edit.material is None and not required:
                return
            if edit.thickness is not None and not (np.isfinite(edit.thickness)
                                                   and edit.thickness > 0):
                raise ValueError(f"{what}: thickness: expected a finite value > 0 m, "
                                 f"got {edit.thickness!r}")
            # an ITU material defined at the carrier or a custom one of the scene
            self.scene.check_material(edit.material, edit.thickness, what)

        if edit.op == "add":
            if edit.target in objects or edit.target in devices:
                raise ValueError(f"{what}: target: an object or device of that name exists")
            if bool(edit.mesh_file) == (edit.mesh_data is not None):
                raise ValueError(f"{what}: mesh_file/mesh_data: give exactly one for add")
            material(required=True)
            if edit.mesh_data is None:
                self._check_mesh(what, edit.mesh_file)
            elif len(edit.mesh_data) > MAX_EDIT_MESH_BYTES:
                raise ValueError(f"{what}: mesh_data: {len(edit.mesh_data)} bytes exceeds "
                                 f"the limit of {MAX_EDIT_MESH_BYTES}")
            else:
                try:
                    parse_ply(edit.mesh_data, f"mesh_data of {edit.target!r}")
                except MeshError as exc:
                    raise ValueError(f"{what}: {exc}") from None
            return
        if edit.op == "move":
            if edit.target not in objects and edit.target not in devices:
                raise ValueError(f"{what}: target: no object or device of that name")
            if edit.position is None and edit.orientation is None:
                raise ValueError(f"{what}: position/orientation: give at least one")
            if edit.position is not None:
                # Devices stay in the room. An object may move out (a wall moved
                # outwards grows the room), by at most the room's diagonal.
                diag = float(np.linalg.norm(np.subtract(self.scene.bounds_max,
                                                        self.scene.bounds_min)))
                triple("position", edit.position,
                       margin=BOUNDS_TOLERANCE_M if edit.target in devices else diag)
            if edit.orientation is not None:
                triple("orientation", edit.orientation)
            return
        if edit.target not in objects:
            raise ValueError(f"{what}: target: no object of that name")
        if edit.op == "material":
            material(required=True)

    def _check_mesh(self, what: str, mesh_file: str) -> None:
        """An ``add`` edit's mesh: a readable PLY inside the scene folder (relative path)
        or an asset folder (absolute), a regular file of at most
        :data:`MAX_EDIT_MESH_BYTES`. One message whatever the reason, so an edit
        reveals nothing about the host's files (the reason is logged)."""
        try:
            path = confine(mesh_file, self.config.scene.file.parent, roots=self.asset_dirs)
            read_ply(path, MAX_EDIT_MESH_BYTES)
        except MeshError as exc:
            log.info("%s: mesh_file refused: %s", what, exc)
            raise ValueError(
                f"{what}: mesh_file: expected a PLY file inside the scene folder (a relative "
                f"path) or an asset folder, at most {MAX_EDIT_MESH_BYTES} bytes") from None

    def apply_edit(self, edit: Edit) -> None:
        """Validate an edit (:meth:`validate_edit`) and queue it; it is applied before
        the next step (the next trace sees it). A bad edit raises here and queues
        nothing; the edits already queued are untouched."""
        self.validate_edit(edit)
        self._pending_edits.append(edit)

    def _apply_pending(self) -> None:
        edits, self._pending_edits = self._pending_edits, []
        if edits and self.sensing_worker is not None and self.sensing_worker.shares_scene:
            self.sensing_worker.wait()  # the radar frame out traces this scene
        for e in edits:
            try:
                self._apply_one(e)
            except (KeyError, ValueError, OSError) as exc:
                # Validated when queued, but an earlier edit of the same batch can
                # invalidate a later one (remove, then move): skip only that one.
                log.error("edit %s %r not applied: %s", e.op, e.target, exc)
        if edits:
            for name in self.stale_databases():
                log.warning("database %s was built before this edit of the room and is "
                            "stale: rebuild it (e.g. `isac-twin grid`)", name)

    def _apply_one(self, e: Edit) -> None:
        if e.op == "move" and e.target in self.ap_poses:
            self._move_access_point(e)
        elif e.op == "move" and e.target in self.agents:
            self._teleport_robot(e)
        elif e.op == "move":
            self.scene.move_object(e.target, e.position, e.orientation)
        elif e.op == "material":
            self.scene.set_material(e.target, e.material, e.thickness)
        elif e.op == "remove":
            self.scene.remove_object(e.target)
        elif e.op == "add":
            if e.mesh_data is not None:
                path = self._store_mesh(e.mesh_data)
            else:
                path = confine(e.mesh_file, self.config.scene.file.parent,
                               roots=self.asset_dirs)
            self.scene.add_object(e.target, path, e.material, e.thickness)
        log.info("applied edit %s %s; scene hash now %s", e.op, e.target,
                 self.scene.content_hash()[:12])

    def _store_mesh(self, data: bytes) -> Path:
        """Write a mesh sent as bytes to the twin's own folder (private, removed with
        the twin); the file is named by its SHA-256."""
        if self._upload_dir is None:
            self._upload_dir = Path(tempfile.mkdtemp(prefix="isac-twin-meshes-"))
            weakref.finalize(self, shutil.rmtree, self._upload_dir, True)
        path = self._upload_dir / f"{hashlib.sha256(data).hexdigest()}.ply"
        path.write_bytes(data)
        return path

    def _move_access_point(self, e: Edit) -> None:
        pos, ori = self.ap_poses[e.target]
        new_pos = tuple(map(float, e.position)) if e.position is not None else pos
        new_ori = tuple(map(float, e.orientation)) if e.orientation is not None else ori
        if not (np.isfinite(new_pos).all() and np.isfinite(new_ori).all()):
            raise ValueError(f"move {e.target!r}: position/orientation must be finite")
        if not self.scene.contains(new_pos):
            raise ValueError(f"move {e.target!r}: {list(new_pos)} lies outside the room")
        self.ap_poses[e.target] = (new_pos, new_ori)

    def _teleport_robot(self, e: Edit) -> None:
        robot = self.agents[e.target].robot
        pose = robot.state.pose.copy()
        if e.position is not None:
            pose[:3] = e.position
        if e.orientation is not None:
            pose[3:6] = e.orientation
        if not np.isfinite(pose).all() or not self.scene.contains(pose[:3]):
            raise ValueError(f"move {e.target!r}: pose {pose.tolist()} is not finite or "
                             "lies outside the room")
        robot.reset(pose, t=robot.state.t)

    def register_database(self, name: str, scene_hash: str) -> None:
        """Track a database (grid, fingerprints) built for a scene state and the
        current access-point poses, so edits can flag it stale."""
        self.databases[name] = (scene_hash, dict(self.ap_poses))

    def stale_databases(self) -> list[str]:
        """Databases built for another room (content hash) or other AP poses."""
        now = self.scene.content_hash()
        return [n for n, (h, aps) in self.databases.items() if h != now or aps != self.ap_poses]

    def validate_command(self, cmd: Command) -> None:
        """Check a command completely (op, every argument) against the twin as it is now.

        Raises:
            ValueError: naming the command and the argument at fault.
        """
        what = f"command {cmd.op}"
        if cmd.op not in wire.COMMAND_OPS:
            raise ValueError(f"{what}: unknown op {cmd.op!r} (expected one of "
                             f"{', '.join(wire.COMMAND_OPS)})")
        a = cmd.args if isinstance(cmd.args, dict) else None
        if a is None:
            raise ValueError(f"{what}: args: expected an object")

        def robot():
            name = a.get("robot")
            if name not in self.agents:
                raise ValueError(f"{what}: robot: expected one of {', '.join(self.agents)}, "
                                 f"got {name!r}")

        def number(key, lo, hi, default=None):
            v = a.get(key, default)
            if type(v) not in (int, float) or not (np.isfinite(v) and lo <= v <= hi):
                raise ValueError(f"{what}: {key}: expected a number in {lo:g}..{hi:g}, "
                                 f"got {v!r}")

        if cmd.op in ("run", "pause", "reset"):
            return
        if cmd.op == "step":
            n = a.get("count", 1)
            if type(n) is not int or not 1 <= n <= MAX_STEP_COUNT:
                raise ValueError(f"{what}: count: expected an integer in 1..{MAX_STEP_COUNT}, "
                                 f"got {n!r}")
        elif cmd.op == "set_path":
            robot()
            if not isinstance(a.get("path"), dict):
                raise ValueError(f"{what}: path: expected an object such as "
                                 '{"kind": "circle", "centre": [x, y], "radius": r}')
        elif cmd.op == "set_goal":
            robot()
            g = a.get("goal")
            lo, hi = self.scene.bounds_min, self.scene.bounds_max
            if not (isinstance(g, list) and len(g) == 2
                    and all(type(x) in (int, float) and np.isfinite(x) for x in g)
                    and lo[0] <= g[0] <= hi[0] and lo[1] <= g[1] <= hi[1]):
                raise ValueError(f"{what}: goal: expected [x, y] inside the room, got {g!r}")
        elif cmd.op == "teleop":
            robot()
            number("linear", -10.0, 10.0)
            number("angular", -20.0, 20.0)
        else:  # an op wire.COMMAND_OPS offers must be checked above
            raise AssertionError(f"{what}: wire.COMMAND_OPS has an op Twin does not handle")

    def command(self, cmd: Command) -> None:
        """Validate (:meth:`validate_command`) and apply a command; the one dispatch of
        every command op.

        * ``run`` / ``pause``: set :attr:`running` (``pause`` also drops
          :attr:`pending_steps`);
        * ``step`` (``count``, default 1): pause and request ``count`` single steps
          (:attr:`pending_steps`; each :meth:`step` takes one);
        * ``reset``: :meth:`reset`;
        * ``set_path`` (``robot``, ``path``), ``set_goal`` (``robot``, ``goal [x, y]``),
          ``teleop`` (``robot``, ``linear`` m/s, ``angular`` rad/s).

        Raises:
            ValueError: a bad command; nothing was changed.
        """
        self.validate_command(cmd)
        a = cmd.args
        if cmd.op == "run":
            self.running = True
        elif cmd.op == "pause":
            self.running = False
            self.pending_steps = 0
        elif cmd.op == "step":
            self.running = False
            self.pending_steps += int(a.get("count", 1))
        elif cmd.op == "reset":
            self.reset()
        elif cmd.op == "set_path":
            self.set_path(a["robot"], a["path"])
        elif cmd.op == "set_goal":
            self.set_path(a["robot"], {"kind": "goal", "goal": a["goal"]})
        elif cmd.op == "teleop":
            from ..bus.msgs import Twist

            tw = Twist(linear=np.array([float(a["linear"]), 0, 0]),
                       angular=np.array([0, 0, float(a["angular"])]))
            self.set_controller(a["robot"], lambda _state, tw=tw: tw)

    # ------------------------------------------------------------------ step

    def device_poses(self) -> dict[str, DevicePose]:
        """Array-centre poses of every device now: APs from their (editable) poses,
        robots from their state through :func:`isac_twin.utils.geometry.antenna_pose`."""
        poses = {}
        for d in self.config.devices:
            agent = self.agents.get(d.name)
            if agent is None:
                poses[d.name] = DevicePose(*self.ap_poses[d.name])
                continue
            st = agent.state
            poses[d.name] = antenna_pose(st.pose, d.antenna_offset, st.v, st.w)
        return poses

    def step(self) -> StepResult:
        """Run one step of Algorithm 1 and return what it produced (takes one of the
        :attr:`pending_steps`, if any). BLAS runs on one thread
        (:func:`~isac_twin.utils.threads.one_blas_thread`: the PHY's matrices are small)."""
        one_blas_thread()
        self.pending_steps = max(0, self.pending_steps - 1)
        self._apply_pending()
        clock = _StageClock()
        t_next = self.time_s + self.dt
        for name, agent in self.agents.items():
            source = self.state_sources.get(name)
            if source is None:
                agent.advance(self.dt)
            else:
                agent.set_state(source(t_next, self.dt))
        # every robot's due LiDAR / depth scans in one ray cast, then each robot
        # publishes its sensors (robot by robot, as RobotAgent.step would)
        hits = cast_scans(self.agents.values(), t_next)
        for name, agent in self.agents.items():
            agent.sense(t_next, placed=name in self.state_sources, hits=hits.get(name))
        self._publish_frames(t_next)
        clock.mark("agents")
        if self.trace_schedule is None or self.trace_schedule(self.step_index):
            paths = self.tracer(self.scene, self.device_poses())
        else:
            paths = {}
        clock.mark("trace")
        signals = self.phy(paths) if self.phy is not None else {}
        clock.mark("phy")

        result = StepResult(step=self.step_index, time_s=t_next,
                            scene_hash=self.scene.content_hash())
        for name, agent in self.agents.items():
            st = agent.state
            odo = agent.last.get("odom")
            odom = None
            if odo is not None:
                odom = np.array([odo.pose.position[0], odo.pose.position[1],
                                 quaternion_to_yaw(odo.pose.orientation)])
            result.robots[name] = RobotState(name=name, pose=st.pose.copy(),
                                             velocity=np.array([st.v, st.w]), odometry=odom)
        for lk, lp in paths.items():
            sig = signals.get(lk)
            result.links[lk] = LinkState(tx=lk[0], rx=lk[1], paths=lp,
                                         snr_db=sig.snr_db if sig else float("nan"),
                                         rate_bps=sig.rate_bps if sig else float("nan"),
                                         mcs_rate_bps=sig.mcs_rate_bps if sig else float("nan"),
                                         mcs=sig.mcs if sig else ())
        result.signals = signals
        for (tx, rx), sig in signals.items():
            agent = self.agents.get(rx)
            # The CSI message expands h over the symbols (a copy of K / G times
            # the step's channel): only for a consumer (see the class doc).
            if agent is not None and self.bus.has_subscribers(agent.topics["csi"]):
                agent.node.publish(agent.topics["csi"], Csi(
                    header=Header(stamp=t_next, frame_id=rx), tx=tx, rx=rx, h=sig.h))
        clock.mark("publish")
        if self.radar is not None:
            self._sense(result)
        clock.mark("sense")
        for est in self.estimators:
            est(self, result)
        clock.mark("estimate")
        for name, agent in self.agents.items():
            if name not in self.state_sources:
                agent.control()
        clock.mark("control")
        result.timings_s = clock.wall
        for k, v in clock.wall.items():
            self.stats.stage_s[k] = self.stats.stage_s.get(k, 0.0) + v
        for k, v in clock.cpu.items():
            self.stats.stage_cpu_s[k] = self.stats.stage_cpu_s.get(k, 0.0) + v
        self.stats.steps += 1
        self.step_index += 1
        self.time_s = t_next
        self.last = result
        return result

    def _sense(self, result: StepResult) -> None:
        """Stage "sense": the radar frame of this step, synchronously or through
        :attr:`sensing_worker` (deliver the frame out when its step has come or a
        new frame is due, then prepare and submit this step's frame, if due)."""
        w = self.sensing_worker
        if w is None:
            self.radar(self, result)
            return
        result.sensing = None
        if w.due(result.step) or (w.pending and self.radar.frame_due()):
            result.sensing = self.flush_sensing()
        job = self.radar.prepare(self, result)
        if job is not None:
            w.submit(job, result.step)

    def close(self) -> None:
        """Stop the radar's worker thread or process (dropping a frame still out;
        call :meth:`flush_sensing` first to keep it). Idempotent. A twin with a
        worker thread may step again afterwards (a frame then starts a new
        thread); with ``sensing_process`` its radar's state ended with the child,
        and the next frame raises."""
        if self.sensing_worker is not None:
            self.sensing_worker.close()

    def flush_sensing(self):
        """Wait for the radar frame computed off the stepping thread (if any),
        publish it (stamped with the step it sensed) and return its
        :class:`~isac_twin.sensing.estimator.SensingStep`; None when no frame is out.
        A run that ends with a frame out calls this to keep it (``record_twin`` does)."""
        w = self.sensing_worker
        out = w.collect() if w is not None else None
        if out is not None:
            self.radar.deliver(self, out)
        return out

    def _publish_frames(self, t: float) -> None:
        """``/clock``, every robot's ``/tf`` (map -> odom -> base_footprint) and, on the
        first step after a (re)build, ``/tf_static`` (the sensor mounts), stamped ``t`` s."""
        node = self._tf_node
        node.publish("/clock", Clock(t))
        dyn = []
        for agent in self.agents.values():
            st = agent.state
            odo = agent.odometry.pose if "odom" in agent.topics else None
            dyn += frames.dynamic_tf(t, agent.frames, (st.x, st.y, st.yaw), odo)
        if dyn:
            node.publish("/tf", TFMessage(dyn))
        if self.step_index == 0 and self.agents:
            static = []
            for agent in self.agents.values():
                static += frames.static_tf(t, agent.frames, agent.spec,
                                           camera=agent.camera is not None)
            node.publish("/tf_static", TFMessage(static))

    def run(self, steps: int, *, rate_hz: float | None = None,
            on_step: Callable[[StepResult], None] | None = None) -> Iterator[StepResult]:
        """Run ``steps`` steps, as fast as possible or paced at ``rate_hz`` in real time.

        A paced step that takes longer than its period is an *overrun*: it is
        counted in :attr:`stats` with its cause (the step's longest stage, or
        ``"caller"`` when the consumer of the previous result took longer; see
        :attr:`RunStats.overrun_stages`) and logged, and the schedule restarts
        from now (no burst of catch-up steps).

        Paced with the radar in a child process (``sensing_process``), the twin's
        own Dr.Jit runs on one thread for the run (restored after it): its
        kernels are small, and the idle thread of a two-thread pool spins
        between them, taking the CPU the radar's process needs (the lab with 4
        robots: 20.1 ms wall and 40.1 ms CPU per step on two threads, 22.9 and
        22.8 ms on one).

        Paced, the twin's first step is its start-up (the tracer enumerates its
        chains and Dr.Jit records and compiles its kernels: ~1.2 s for the lab
        with 4 robots): the schedule starts when it ends
        (:attr:`RunStats.startup_s`). With a radar, the start-up also waits for
        its first frame (Sionna compiles the radar's solvers) and takes the
        second step too: the first frame put the robots' targets into the
        scene, so that step's trace enumerates its chains again (~1.5 s on the
        lab with 4 robots). Then the objects alive are moved out of
        Python's cyclic garbage collector (``gc.freeze``: they are kept for the
        process's life), so that its full collections, which walked them all
        (~30 ms on the lab, an overrun at 20 Hz), stay short.
        """
        if steps < 0:
            raise ValueError(f"steps: expected >= 0, got {steps}")
        if rate_hz is not None and not rate_hz > 0:
            raise ValueError(f"rate_hz: expected a positive rate, got {rate_hz}")
        period = 1.0 / rate_hz if rate_hz else 0.0
        jit_threads = None
        if period and self.sensing_process and self.radar is not None:
            import drjit as dr

            jit_threads = dr.thread_count()
            dr.set_thread_count(1)
        try:
            yield from self._run(steps, period, rate_hz, on_step)
        finally:
            if jit_threads is not None:
                dr.set_thread_count(jit_threads)

    def _run(self, steps: int, period: float, rate_hz, on_step) -> Iterator[StepResult]:
        start = time.perf_counter()
        deadline = start + period
        for _ in range(steps):
            startup = bool(period) and self.step_index < (2 if self.radar is not None else 1)
            res = self.step()
            t_done = time.perf_counter()
            if on_step is not None:
                on_step(res)
            yield res
            if startup:
                if self.sensing_worker is not None:
                    self.sensing_worker.wait()
                now = time.perf_counter()
                self.stats.startup_s = now - start
                gc.collect()
                gc.freeze()
                deadline = time.perf_counter() + period
                log.info("start-up (step %d) took %.2f s; pacing at %.1f Hz after it",
                         res.step, now - start, rate_hz)
            elif period:
                now = time.perf_counter()
                if now > deadline:
                    costs = dict(res.timings_s)
                    costs["caller"] = now - t_done
                    cause = max(costs, key=costs.get)
                    st = self.stats
                    st.overruns += 1
                    st.overrun_stages[cause] = st.overrun_stages.get(cause, 0) + 1
                    st.overrun_ms += 1e3 * (now - deadline)
                    log.warning("step %d overran its %.1f ms period by %.1f ms (%s %.1f ms)",
                                res.step, 1e3 * period, 1e3 * (now - deadline), cause,
                                1e3 * costs[cause])
                    deadline = now + period
                else:
                    time.sleep(deadline - now)
                    deadline += period
        self.stats.wall_s += time.perf_counter() - start

