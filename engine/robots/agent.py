"""A robot on the bus: motion model + sensors + topics, one per ``robot`` device.

:class:`RobotAgent` is what the twin loop holds per robot. Each step::

    agent.step(t, dt)        # 1. s_t = f(s_{t-1}, u_{t-1}); 4. sensors -> topics

The command ``u_{t-1}`` is the last :class:`~isac_twin.bus.msgs.Twist` received on
``/<name>/cmd_vel`` (from a controller, a teleop node or a real robot's
bridge); :meth:`RobotAgent.drive` attaches a controller that publishes there
from the agent's own controller node each step (step 6 of Algorithm 1).

Topics of robot ``<name>`` (frames in brackets):

=========================  ==============================  ======================
topic                      type                            publisher
=========================  ==============================  ======================
/<name>/cmd_vel            geometry_msgs/msg/Twist         controller (subscribed)
/<name>/ground_truth       geometry_msgs/msg/PoseStamped   robot [map]
/<name>/joint_states       sensor_msgs/msg/JointState      robot [base_link]
/<name>/odom               nav_msgs/msg/Odometry           robot [odom -> base_footprint]
/<name>/imu                sensor_msgs/msg/Imu             robot [imu_link]
/<name>/scan               sensor_msgs/msg/LaserScan       robot [base_scan]
/<name>/camera/depth       sensor_msgs/msg/Image           robot, when enabled
=========================  ==============================  ======================

Frame ids follow :mod:`isac_twin.bus.frames` (``<name>/`` prefixed when the twin has
several robots); the twin publishes their ``/tf`` and ``/tf_static``.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..bus.bus import Bus
from ..bus.frames import RobotFrames, robot_prefix
from ..bus.msgs import Header, Pose, PoseStamped, Twist
from .kinematics import DiffDriveRobot, ProcessNoise, robot_spec
from .sensors import (
    Body,
    DepthCamera,
    ImuNoise,
    ImuSensor,
    Lidar2D,
    WheelEncoders,
    WheelOdometry,
    cast_rays,
)

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SensorOptions:
    """Which sensors a robot carries and whether they are noisy.

    Attributes:
        lidar, imu, odometry: enable each.
        camera: the depth camera (off by default: it costs a ray cast per pixel).
        noise: ``False`` makes every sensor exact (and the process noise zero).
        process_noise: the motion model's noise when ``noise`` is on.
    """

    lidar: bool = True
    imu: bool = True
    odometry: bool = True
    camera: bool = False
    noise: bool = True
    process_noise: ProcessNoise = ProcessNoise(xy_std=0.002, yaw_std=0.005)


class RobotAgent:
    """One robot: :class:`DiffDriveRobot`, its sensors, and its bus node.

    Args:
        name: device name (also the topic namespace).
        model: ``"burger"`` or ``"waffle"``.
        pose: initial ``[x, y, z, roll, pitch, yaw]`` (m, rad).
        bus: the :class:`~isac_twin.bus.bus.Bus` to publish on.
        scene: the :class:`~isac_twin.scene.twin_scene.TwinScene` (LiDAR/camera ray casting);
            ``None`` disables them.
        seed: one seed; the robot and each sensor derive their own streams from it.
        options: :class:`SensorOptions`.
        frame_prefix: prefix of its frame ids (``"robot1/"``; see :mod:`isac_twin.bus.frames`).
        render_unheard: ray cast the scene sensors (LiDAR, depth camera) even when
            nobody subscribes to their topic. ``False`` (the twin's choice, issue
            #19): a due scan nobody receives (:meth:`isac_twin.bus.bus.Bus.has_subscribers`)
            is skipped (:meth:`~isac_twin.robots.sensors.Sensor.skip`: schedule and
            noise stream advance as if sampled, so a subscriber arriving later gets
            the very scans an always-rendering agent publishes) and is neither
            published nor in :attr:`last`.
    """

    #: topic keys of the sensors that ray cast into the scene (see ``render_unheard``)
    SCENE_SENSORS = ("scan", "camera/depth")

    def __init__(self, name: str, model: str, pose, bus: Bus, scene=None, *, seed: int = 0,
                 options: SensorOptions | None = None, frame_prefix: str = "",
                 render_unheard: bool = True):
        self.name = name
        self.render_unheard = bool(render_unheard)
        self.frames = RobotFrames(frame_prefix)
        self.spec = robot_spec(model)
        opt = options or SensorOptions()
        self.options = opt
        seeds = np.random.SeedSequence([seed, _name_key(name)]).spawn(6)
        rng = [np.random.default_rng(s) for s in seeds]
        noisy = opt.noise
        self.robot = DiffDriveRobot(self.spec, pose, name=name, rng=rng[0],
                                    noise=opt.process_noise if noisy else ProcessNoise())
        st = self.robot.state
        self.encoders = WheelEncoders(rng=rng[1], **({} if noisy else
                                                     {"slip_std": 0.0, "tick_jitter": 0.0}))
        self.odometry = WheelOdometry(self.spec, initial_pose=(st.x, st.y, st.yaw), rng=rng[2],
                                      **({} if noisy else {"radius_scale": (1.0, 1.0),
                                                           "separation_scale": 1.0}))
        self.imu = ImuSensor(self.spec, rng=rng[3], noise=None if noisy else ImuNoise.off()) \
            if opt.imu else None
        self.lidar = None
        if opt.lidar and scene is not None:
            kw = {} if noisy else {"range_noise_rel": 0.0, "range_noise_abs": 0.0}
            self.lidar = Lidar2D(scene, self.spec, rng=rng[4], **kw)
        self.camera = None
        if opt.camera and scene is not None:
            self.camera = DepthCamera(scene, self.spec, enabled=True, rng=rng[5],
                                      **({} if noisy else {"depth_noise_rel": 0.0}))

        fr = self.frames
        self.encoders.frame_id = fr.base_link
        self.odometry.odom_frame, self.odometry.base_frame = fr.odom, fr.base_footprint
        for sensor, frame in ((self.imu, fr.imu_link), (self.lidar, fr.base_scan),
                              (self.camera, fr.camera_optical)):
            if sensor is not None:
                sensor.frame_id = frame

        self.bus = bus
        self.node = bus.node(name)
        ns = f"/{name}"
        self.topics = {"cmd_vel": f"{ns}/cmd_vel", "ground_truth": f"{ns}/ground_truth",
                       "joint_states": f"{ns}/joint_states"}
        self.node.advertise(self.topics["ground_truth"], PoseStamped)
        self.node.advertise(self.topics["joint_states"], self.encoders.msg_type)
        for key, sensor in (("odom", self.odometry if opt.odometry else None),
                            ("imu", self.imu), ("scan", self.lidar),
                            ("camera/depth", self.camera)):
            if sensor is not None:
                self.topics[key] = f"{ns}/{sensor.topic}"
                self.node.advertise(self.topics[key], sensor.msg_type)
        self._cmd = self.node.subscribe(self.topics["cmd_vel"], Twist, queue_size=None)
        self.command = Twist()
        self.controller: Callable | None = None
        self._ctl_node = None
        self.last: dict[str, object] = {}  #: last message per topic key

    def drive(self, controller: Callable) -> None:
        """Attach ``controller(state) -> Twist``; it publishes on ``cmd_vel`` each step
        from node ``<name>/controller``."""
        if self._ctl_node is None:
            self._ctl_node = self.bus.node(f"{self.name}/controller")
            self._ctl_node.advertise(self.topics["cmd_vel"], Twist)
        self.controller = controller

    @property
    def state(self):
        return self.robot.state

    def step(self, t: float, dt: float, *, control: bool = True) -> dict[str, object]:
        """Advance to time ``t`` (s) by ``dt`` (s) and publish what is due.

        Order: take the newest ``cmd_vel`` (``u_{t-1}``), apply ``f``, sample the
        due sensors and publish them, then let the controller (if any) publish
        the next command from the new state (:meth:`advance`, :meth:`sense`,
        :meth:`control`).

        Args:
            control: run the controller at the end; the twin passes False and
                runs it itself after its estimators (Algorithm 1, stage 6).

        Returns:
            ``topic key -> message`` of what was published this step.
        """
        self.advance(dt)
        out = self.sense(t)
        if control:
            self.control()
        return out

    def advance(self, dt: float) -> None:
        """Take the newest ``cmd_vel`` (``u_{t-1}``) and apply ``f`` over ``dt`` s."""
        for msg in self._cmd.drain():
            self.command = msg
        self.robot.step(self.command, dt)

    def place(self, state, t: float) -> dict[str, object]:
        """Put the robot at ``state`` (a :class:`~isac_twin.robots.kinematics.KinematicState`
        from an outside source, e.g. a recording) at time ``t`` s and publish what a
        placed robot can measure: ``ground_truth`` and the scene sensors (LiDAR, depth
        camera). Wheel encoders, odometry and IMU are not simulated for a placed robot.

        Returns:
            ``topic key -> message`` of what was published.
        """
        self.set_state(state)
        return self.sense(t, placed=True)

    def body(self) -> Body:
        """The robot's body now, as the other robots' scene sensors see it: a box of
        the model's ``body_size`` on the floor under base_link, turned by its yaw."""
        st = self.robot.state
        size = self.spec.body_size
        return Body(centre=(float(st.pose[0]), float(st.pose[1]),
                            float(st.pose[2]) + 0.5 * size[2]),
                    yaw=float(st.yaw), size=tuple(size))

    def set_state(self, state) -> None:
        """Put the robot at ``state`` without publishing (see :meth:`place`)."""
        self.robot.state = state

    def scans_due(self, t: float) -> list[tuple[str, object]]:
        """``(topic key, sensor)`` of the scene sensors :meth:`sense` will ray cast
        at ``t`` s: due, and subscribed to unless ``render_unheard``."""
        out = []
        for key, sensor in (("scan", self.lidar), ("camera/depth", self.camera)):
            if (sensor is not None and key in self.topics and self._renders(key)
                    and getattr(sensor, "enabled", True) and sensor.due(t)):
                out.append((key, sensor))
        return out

    def _renders(self, key: str) -> bool:
        return (self.render_unheard or key not in self.SCENE_SENSORS
                or self.bus.has_subscribers(self.topics[key]))

    def sense(self, t: float, *, placed: bool = False,
              hits: dict | None = None) -> dict[str, object]:
        """Sample and publish what is due at ``t`` s from the current state:
        ``ground_truth``, the wheel encoders / odometry and the IMU (not when
        ``placed``), and the scene sensors.

        Args:
            placed: the state came from outside (:meth:`place`).
            hits: ``{topic key: cast_rays result}`` of scene sensors already cast
                (:func:`cast_scans`, several robots in one call); the others are
                cast here.

        Returns:
            ``topic key -> message`` of what was published.
        """
        st = self.robot.state
        out: dict[str, object] = {
            "ground_truth": PoseStamped(header=Header(stamp=t, frame_id="map"),
                                        pose=Pose(position=st.position,
                                                  orientation=st.quaternion()))}
        sensors = (("scan", self.lidar), ("camera/depth", self.camera))
        if not placed:
            js = self.encoders.poll(t, st)
            if js is not None:
                out["joint_states"] = js
                if "odom" in self.topics:
                    out["odom"] = self.odometry.update(js)
            sensors = (("imu", self.imu),) + sensors
        hits = hits or {}
        for key, sensor in sensors:
            if sensor is not None and key in self.topics:
                if not self._renders(key):
                    sensor.skip(t, st)
                    continue
                m = sensor.poll(t, st) if key not in hits else sensor.poll(t, st, hits=hits[key])
                if m is not None:
                    out[key] = m
        for key, msg in out.items():
            self.node.publish(self.topics[key], msg)
        self.last.update(out)
        return out

    def control(self) -> None:
        """Publish the controller's next command from the current state (if driven)."""
        if self.controller is not None:
            self._ctl_node.publish(self.topics["cmd_vel"], self.controller(self.robot.state))


class OpenCRStep:
    """The twin's robot as the ``step(v, w, dt)`` an emulated OpenCR board drives.

    :class:`isac_twin.devices.emulated_opencr.EmulatedOpenCR` takes a callable
    ``step(v, w, dt) -> (left_pos, right_pos, left_vel, right_vel, gyro[3],
    accel[3], quat[4])`` (rad, rad/s, rad/s, m/s^2 with gravity, ``[x, y, z, w]``);
    this adapter runs :meth:`DiffDriveRobot.step` (same firmware clamping,
    acceleration limits and process noise as the twin) and reads the IMU
    through an :class:`~isac_twin.robots.sensors.ImuSensor` (noise-free if none given)::

        board = EmulatedOpenCR(step=OpenCRStep(DiffDriveRobot("burger")), model="burger")

    Args:
        robot: the robot to move.
        imu: the IMU model (default: exact, ``ImuNoise.off()``).
    """

    def __init__(self, robot: DiffDriveRobot, imu: ImuSensor | None = None):
        self.robot = robot
        self.imu = imu or ImuSensor(robot.spec, noise=ImuNoise.off())

    def __call__(self, v: float, w: float, dt: float) -> tuple:
        st = self.robot.step((v, w), dt) if dt > 0 else self.robot.state
        m = self.imu.measure(st.t, st)
        return (float(st.wheel_pos[0]), float(st.wheel_pos[1]), float(st.wheel_vel[0]),
                float(st.wheel_vel[1]), m.angular_velocity, m.linear_acceleration,
                st.quaternion())


def _name_key(name: str) -> int:
    # stable across runs (unlike hash()): robots with one seed get distinct streams
    return int.from_bytes(name.encode()[:8].ljust(8, b"\0"), "little")


def cast_scans(agents, t: float, *, occluders=None) -> dict[str, dict[str, tuple]]:
    """The scene-sensor scans of several robots due at ``t`` s, cast in one
    Mitsuba call (issue #19: a call costs ~2 ms whatever its 360 beams; every
    ray's hit is computed alone, so each robot gets what its own call gives).
    Each robot's rays see the bodies of the ``occluders`` but its own
    (:meth:`RobotAgent.body`).

    Args:
        agents: the :class:`RobotAgent` s whose due scans to cast, after their
            motion update.
        occluders: the robots whose bodies the rays see (default ``agents``).

    Returns:
        ``{robot: {topic key: (t [M], valid [M], cos_inc [M])}}`` for
        :meth:`RobotAgent.sense` ``hits``; empty when no scan is due.
    """
    agents = list(agents)
    occluders = agents if occluders is None else list(occluders)
    jobs = []
    for a in agents:
        for key, sensor in a.scans_due(t):
            origin, dirs = sensor.rays(a.state)
            jobs.append((a, key, sensor.scene, origin, dirs))
    scenes = {id(j[2]) for j in jobs}
    if not jobs or len(scenes) != 1:
        return {}
    bodies = [o.body() for o in occluders]
    index = {id(o): i for i, o in enumerate(occluders)}
    origins = np.concatenate([np.broadcast_to(np.asarray(o, float), d.shape)
                              for *_, o, d in jobs])
    owner = np.concatenate([np.full(d.shape[0], index.get(id(a), -1)) for a, *_, d in jobs])
    d_all, valid, cos_inc = cast_rays(jobs[0][2], origins, np.concatenate([j[4] for j in jobs]),
                                      bodies=bodies, owner=owner)
    out: dict[str, dict[str, tuple]] = {}
    start = 0
    for a, key, _, _, dirs in jobs:
        seg = slice(start, start + dirs.shape[0])
        out.setdefault(a.name, {})[key] = (d_all[seg], valid[seg], cos_inc[seg])
        start = seg.stop
    return out


def build_robots(config, bus: Bus, scene=None, *, seed: int = 0,
                 options: SensorOptions | None = None,
                 render_unheard: bool = True) -> dict[str, RobotAgent]:
    """A :class:`RobotAgent` for each ``robot`` device of a twin config.

    Args:
        config: :class:`~isac_twin.scene.config.TwinConfig`.
        bus: where the agents' nodes register.
        scene: :class:`~isac_twin.scene.twin_scene.TwinScene` for LiDAR/camera, or ``None``.
        render_unheard: see :class:`RobotAgent`.
    """
    agents = {}
    robots = [d for d in config.devices if d.kind == "robot"]
    for d in robots:
        pose = (*d.position, *d.orientation)
        agents[d.name] = RobotAgent(d.name, d.model or "burger", pose, bus, scene, seed=seed,
                                    options=options,
                                    frame_prefix=robot_prefix(d.name, len(robots)),
                                    render_unheard=render_unheard)
        log.info("robot %s (%s) at %s", d.name, d.model, d.position)
    return agents
