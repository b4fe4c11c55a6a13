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

import logging
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from ..bus import frames
from ..bus.bus import Bus
from ..bus.msgs import Clock, Csi, Header, TFMessage
from ..errors import ConfigError, PathError
from ..phy.network import NetworkPHY
from ..raytrace import make_tracer
from ..robots import KinematicState, SensorOptions, build_robots, cast_scans
from ..robots.control import controller_from_spec
from ..scene.room import ROBOT_BODY_HEIGHT_M, path_obstruction
from ..scene.twin_scene import TwinScene, load_scene
from ..utils.geometry import DevicePose, antenna_pose, quaternion_to_yaw
from ..utils.threads import one_blas_thread
from . import pacing
from .commands import apply_command, validate_command
from .edits import EditResult, SceneEditor
from .pacing import RunStats, StageClock
from .state import Command, Edit, LinkState, RobotState, StepResult

log = logging.getLogger(__name__)

#: ``estimator(twin, result) -> None``: fills ``result.robots[name].estimate``.
Estimator = Callable[["Twin", StepResult], None]
#: ``source(t, dt) -> KinematicState``: a robot's state at time ``t`` s after a step
#: of ``dt`` s, from outside the twin (:meth:`Twin.set_state_source`).
StateSource = Callable[[float, float], KinematicState]


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
        #: validates, queues and applies live edits (:mod:`.edits`)
        self.editor = SceneEditor(self)
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
        """Check an edit completely against the twin as it is now (the one validation
        of edits: :meth:`.edits.SceneEditor.validate`).

        Raises:
            ValueError: naming the edit (op and target) and the field at fault.
        """
        self.editor.validate(edit)

    def apply_edit(self, edit: Edit, *, on_result: EditResult | None = None) -> None:
        """Validate an edit (:meth:`validate_edit`, against the room as the edits
        already queued leave it) and queue it; it is applied before the next step
        (the next trace sees it). A bad edit raises here and queues nothing; the
        edits already queued are untouched.

        Args:
            on_result: ``on_result(edit, error)`` once it is applied (``error`` None)
                or failed when applied (the reason; the other edits still apply).
        """
        self.editor.queue(edit, on_result)

    def _apply_pending(self) -> None:
        """Apply the queued edits now (:meth:`.edits.SceneEditor.apply_pending`)."""
        self.editor.apply_pending()

    def register_database(self, name: str, scene_hash: str) -> None:
        """Track a database (grid, fingerprints) built for a scene state and the
        current access-point poses, so edits can flag it stale."""
        self.databases[name] = (scene_hash, dict(self.ap_poses))

    def stale_databases(self) -> list[str]:
        """Databases built for another room (content hash) or other AP poses."""
        now = self.scene.content_hash()
        return [n for n, (h, aps) in self.databases.items() if h != now or aps != self.ap_poses]

    # ------------------------------------------------------------------ commands

    def validate_command(self, cmd: Command) -> None:
        """Check a command completely (op, every argument) against the twin as it is
        now (:func:`.commands.validate_command`).

        Raises:
            ValueError: naming the command and the argument at fault.
        """
        validate_command(self, cmd)

    def command(self, cmd: Command) -> None:
        """Validate (:meth:`validate_command`) and apply a command: ``run``, ``pause``,
        ``step`` (these set :attr:`running` and :attr:`pending_steps`), ``reset``,
        ``set_path``, ``set_goal``, ``teleop`` (:func:`.commands.apply_command`).

        Raises:
            ValueError: a bad command; nothing was changed.
        """
        apply_command(self, cmd)

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
        clock = StageClock()
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
        self.stats.add_step(clock)
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
        """Run ``steps`` steps, as fast as possible or paced at ``rate_hz`` in real time,
        calling ``on_step(result)`` before yielding each :class:`StepResult`
        (:func:`.pacing.run`: overruns counted in :attr:`stats` by cause; the first
        paced step is the run's start-up)."""
        yield from pacing.run(self, steps, rate_hz=rate_hz, on_step=on_step)
