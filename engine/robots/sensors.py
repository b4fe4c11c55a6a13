"""Simulated robot sensors: the observation side ``g`` (paper, eq. 6).

Every sensor has its own rate and its own seeded ``numpy.random.Generator``
and turns the true :class:`~isac_twin.robots.kinematics.KinematicState` into a ROS
message (:mod:`isac_twin.bus.msgs`). The common call is::

    msg = sensor.poll(t, state)   # a message when the sensor is due at t, else None

so a twin running at its own step can host a 5.5 Hz LiDAR beside a 20 Hz IMU.
Setting every noise parameter to 0 makes a sensor exact (tests rely on it).

=================  ==================  ==========================================
sensor             message             noise / error model
=================  ==================  ==========================================
WheelEncoders      JointState          tick quantisation (0.001533981 rad), tick
                                       jitter, slip random walk per wheel turn,
                                       velocity in DYNAMIXEL units (0.229 rpm)
WheelOdometry      Odometry            integrates encoder ticks with miscalibrated
                                       wheel radii / separation -> drifts
Imu                Imu                 white noise + bias random walk (gyro, accel);
                                       accel is specific force (gravity included)
Lidar2D            LaserScan           relative + absolute range noise, dropout,
                                       incidence-dependent quality; ray cast into
                                       the scene in one Mitsuba call
DepthCamera        Image (16UC1, mm)   off by default; ray-cast depth image
=================  ==================  ==========================================

The ray casts see the scene's geometry and the other robots' bodies (boxes of
the model's size, :class:`Body`); never the casting robot's own body, nor the
radar's sensing-target cuboids, which Sionna keeps in the same Mitsuba scene
(:func:`cast_rays`). Not modelled: the LiDAR takes the whole scan from the
pose at the scan time (no motion skew); no RGB camera image (only depth).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ..bus.msgs import Header, Image, Imu, JointState, LaserScan, Odometry, Pose, Twist
from ..utils.geometry import euler_to_quaternion, wrap_angle
from .kinematics import GRAVITY, TICK_RAD, KinematicState, RobotSpec, robot_spec

log = logging.getLogger(__name__)

#: DYNAMIXEL velocity unit: 0.229 rpm in rad/s.
DXL_VELOCITY_UNIT = 0.229 * 2 * math.pi / 60.0


class Sensor:
    """Base: a rate, a seeded generator, and :meth:`poll`.

    Args:
        rate_hz: output rate, Hz (> 0).
        seed: seed of this sensor's generator (or pass ``rng``).
        frame_id: ``header.frame_id`` of its messages.
    """

    msg_type: type = object
    topic: str = ""  #: topic name relative to the robot's namespace

    def __init__(self, rate_hz: float, *, seed: int | None = 0,
                 rng: np.random.Generator | None = None, frame_id: str = ""):
        if not (math.isfinite(rate_hz) and rate_hz > 0):
            raise ValueError(f"{type(self).__name__}: rate_hz must be > 0, got {rate_hz!r}")
        self.rate_hz = float(rate_hz)
        self.period = 1.0 / self.rate_hz
        self.rng = rng if rng is not None else np.random.default_rng(seed)
        self.frame_id = frame_id
        self._next_t: float | None = None
        self.last_t: float | None = None

    def due(self, t: float) -> bool:
        """Whether a sample is due at time ``t`` (s)."""
        return self._next_t is None or t >= self._next_t - 1e-9

    def poll(self, t: float, state: KinematicState, **measure_kw):
        """The sensor's message at time ``t`` (s) if it is due, else ``None``
        (``measure_kw``: passed to :meth:`measure`, e.g. a scan's ``hits``)."""
        if not self.due(t):
            return None
        msg = self.measure(t, state, **measure_kw)
        self._advance(t)
        return msg

    def _advance(self, t: float) -> None:
        """Schedule the next sample after one taken (or skipped) at ``t``."""
        self._next_t = (t if self._next_t is None else self._next_t) + self.period
        if self._next_t <= t:  # fell behind (twin step > period): resynchronise
            self._next_t = t + self.period
        self.last_t = t

    def skip(self, t: float, state: KinematicState) -> bool:
        """Let a due sample pass unrendered: the schedule and the noise stream
        advance exactly as :meth:`poll` would advance them (:meth:`discard`), so
        every later sample equals the one an always-polled sensor gives. For a
        sample nobody receives (issue #19: a ray-cast scan costs ~2 ms).

        Returns:
            Whether a sample was due (and passed).
        """
        if not self.due(t):
            return False
        self.discard(t, state)
        self._advance(t)
        return True

    def measure(self, t: float, state: KinematicState):
        """Take a sample now, regardless of the rate. Subclasses implement it."""
        raise NotImplementedError

    def discard(self, t: float, state: KinematicState) -> None:
        """What :meth:`measure` does to the sensor's state (random draws, filters)
        without forming the message; the default measures and drops it.
        Subclasses with a costly measurement override it."""
        self.measure(t, state)


# --------------------------------------------------------------------------- wheels


class WheelEncoders(Sensor):
    """The two DYNAMIXEL encoders, as the OpenCR reports them.

    The true wheel angles come from the state; the measurement adds a slip
    random walk (``slip_std`` rad per sqrt(rad) of wheel rotation), quantises
    to ticks of :data:`TICK_RAD` and jitters by one tick with probability
    ``tick_jitter``. Velocities are quantised to DYNAMIXEL units (0.229 rpm).

    Attributes (after a sample):
        ticks: ``[2]`` int64, left/right ``present_position`` (ticks).
        velocity_units: ``[2]`` int64, left/right ``present_velocity`` (0.229 rpm units).

    Message: :class:`~isac_twin.bus.msgs.JointState` with names ``wheel_left_joint``,
    ``wheel_right_joint``, positions in rad (``ticks * TICK_RAD``), velocities in rad/s.
    """

    msg_type = JointState
    topic = "joint_states"

    def __init__(self, rate_hz: float = 20.0, *, tick: float = TICK_RAD,
                 slip_std: float = 0.002, tick_jitter: float = 0.05, seed: int | None = 0,
                 rng=None):
        super().__init__(rate_hz, seed=seed, rng=rng, frame_id="base_link")
        self.tick = float(tick)
        self.slip_std = float(slip_std)
        self.tick_jitter = float(tick_jitter)
        self._slip = np.zeros(2)
        self._last_true: np.ndarray | None = None
        self.ticks = np.zeros(2, np.int64)
        self.velocity_units = np.zeros(2, np.int64)

    def measure(self, t: float, state: KinematicState) -> JointState:
        true = state.wheel_pos
        if self._last_true is not None and self.slip_std > 0:
            turned = np.abs(true - self._last_true)
            self._slip += self.slip_std * np.sqrt(turned) * self.rng.standard_normal(2)
        self._last_true = true.copy()
        ticks = np.round((true + self._slip) / self.tick).astype(np.int64)
        if self.tick_jitter > 0:
            jump = self.rng.random(2) < self.tick_jitter
            ticks += jump * self.rng.choice(np.array([-1, 1]), 2)
        self.ticks = ticks
        self.velocity_units = np.round(state.wheel_vel / DXL_VELOCITY_UNIT).astype(np.int64)
        return JointState(header=Header(stamp=t, frame_id=self.frame_id),
                          name=["wheel_left_joint", "wheel_right_joint"],
                          position=ticks * self.tick,
                          velocity=self.velocity_units * DXL_VELOCITY_UNIT,
                          effort=np.zeros(2))


class WheelOdometry:
    """Dead reckoning from encoder readings, like ``turtlebot3_node``'s odometry.

    The robot's real wheels differ from the nominal numbers the odometry uses:
    ``radius_scale`` ``[2]`` (left, right) and ``separation_scale`` are the
    ratios *assumed / true*; unless given, they are drawn once from
    ``N(1, radius_error_std)`` and ``N(1, separation_error_std)``, a fixed
    miscalibration per robot and seed. With the encoders' tick noise and slip
    this makes the odometry drift as a real one does (heading error grows
    with distance turned, position error with distance travelled).

    Integration per reading (the TurtleBot3 node's formula):
    ``ds = (r_l dphi_l + r_r dphi_r) / 2``, ``dth = (r_r dphi_r - r_l dphi_l) / L``,
    ``x += ds cos(th + dth / 2)``, ``y += ds sin(th + dth / 2)``, ``th += dth``.

    The ``odom`` frame coincides with the world at ``initial_pose`` ``[x, y, yaw]``.
    """

    msg_type = Odometry
    topic = "odom"

    def __init__(self, spec: RobotSpec | str = "burger", *, initial_pose=(0.0, 0.0, 0.0),
                 radius_scale: Sequence[float] | None = None,
                 separation_scale: float | None = None, radius_error_std: float = 0.003,
                 separation_error_std: float = 0.01, seed: int | None = 0, rng=None):
        self.spec = robot_spec(spec) if isinstance(spec, str) else spec
        rng = rng if rng is not None else np.random.default_rng(seed)
        if radius_scale is None:
            radius_scale = 1.0 + radius_error_std * rng.standard_normal(2)
        if separation_scale is None:
            separation_scale = 1.0 + separation_error_std * rng.standard_normal()
        self.radius = self.spec.wheel_radius * np.asarray(radius_scale, float)  # [2] l, r
        self.separation = self.spec.wheel_separation * float(separation_scale)
        self.pose = np.array(initial_pose, float)  # x, y, yaw
        #: frame ids (REP-105; the OpenCR driver's and turtlebot3_node's convention)
        self.odom_frame, self.base_frame = "odom", "base_footprint"
        self.v = self.w = 0.0
        self._last: np.ndarray | None = None
        self._last_t: float | None = None

    def update(self, joints: JointState) -> Odometry:
        """Integrate one encoder reading; returns the odometry at its stamp."""
        pos = np.asarray(joints.position, float)
        t = joints.header.stamp
        if self._last is not None:
            d = (pos - self._last) * self.radius
            ds = 0.5 * (d[0] + d[1])
            dth = (d[1] - d[0]) / self.separation
            th = self.pose[2]
            self.pose += [ds * math.cos(th + dth / 2), ds * math.sin(th + dth / 2), dth]
            self.pose[2] = float(wrap_angle(self.pose[2]))
            dt = t - self._last_t
            if dt > 0:
                self.v, self.w = ds / dt, dth / dt
        self._last, self._last_t = pos.copy(), t
        return self.message(t)

    def message(self, t: float) -> Odometry:
        cov = np.diag([1e-3, 1e-3, 1e6, 1e6, 1e6, 1e-2])  # planar: z/roll/pitch unknown
        return Odometry(
            header=Header(stamp=t, frame_id=self.odom_frame), child_frame_id=self.base_frame,
            pose=Pose(position=np.array([self.pose[0], self.pose[1], 0.0]),
                      orientation=euler_to_quaternion(0.0, 0.0, self.pose[2])),
            pose_covariance=cov,
            twist=Twist(linear=np.array([self.v, 0.0, 0.0]), angular=np.array([0, 0, self.w])),
            twist_covariance=cov.copy())


# --------------------------------------------------------------------------- IMU


@dataclass(frozen=True)
class ImuNoise:
    """Continuous-time IMU noise parameters (defaults: a consumer MEMS such as
    the ICM-20648 on the OpenCR, order-of-magnitude datasheet values).

    Attributes:
        gyro_noise: white noise density, rad/s/sqrt(Hz).
        gyro_bias_rw: bias random walk, rad/s^2/sqrt(Hz).
        gyro_bias0: std of the initial bias, rad/s.
        accel_noise: m/s^2/sqrt(Hz); accel_bias_rw: m/s^3/sqrt(Hz); accel_bias0: m/s^2.
    """

    gyro_noise: float = 2.6e-4
    gyro_bias_rw: float = 2e-5
    gyro_bias0: float = 2e-3
    accel_noise: float = 2.3e-3
    accel_bias_rw: float = 1e-4
    accel_bias0: float = 0.02

    @classmethod
    def off(cls) -> ImuNoise:
        return cls(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


class ImuSensor(Sensor):
    """Gyroscope + accelerometer at ``imu_link``.

    Gyro: ``w_m = w + b_g + n``; accelerometer: the specific force
    ``f = a_body - R^T g_world`` (so a level robot at rest reads ``+9.81`` on
    z, like a real IMU), plus bias and noise. Biases follow random walks
    advanced by the time between samples; white noise per sample has std
    ``density * sqrt(rate)``. The acceleration at the IMU includes the
    centripetal lever-arm term ``-w^2 r_xy`` of its mount offset (the
    ``dw/dt`` lever term is neglected). The orientation is roll/pitch from
    the truth and yaw integrated from the measured gyro (it drifts, as a
    6-axis filter without magnetometer does).
    """

    msg_type = Imu
    topic = "imu"

    def __init__(self, spec: RobotSpec | str = "burger", rate_hz: float = 20.0, *,
                 noise: ImuNoise | None = None, seed: int | None = 0, rng=None,
                 gravity: float = GRAVITY):
        super().__init__(rate_hz, seed=seed, rng=rng, frame_id="imu_link")
        self.spec = robot_spec(spec) if isinstance(spec, str) else spec
        self.noise = noise or ImuNoise()
        self.gravity = gravity
        n = self.noise
        self.gyro_bias = n.gyro_bias0 * self.rng.standard_normal(3)
        self.accel_bias = n.accel_bias0 * self.rng.standard_normal(3)
        self._yaw: float | None = None
        self._t_prev: float | None = None

    def measure(self, t: float, state: KinematicState) -> Imu:
        n = self.noise
        dt = 0.0 if self._t_prev is None else max(t - self._t_prev, 0.0)
        self._t_prev = t
        if dt > 0:
            self.gyro_bias += n.gyro_bias_rw * math.sqrt(dt) * self.rng.standard_normal(3)
            self.accel_bias += n.accel_bias_rw * math.sqrt(dt) * self.rng.standard_normal(3)
        sq = math.sqrt(self.rate_hz)
        omega = np.array([0.0, 0.0, state.w])
        gyro = omega + self.gyro_bias + n.gyro_noise * sq * self.rng.standard_normal(3)
        R = state.rotation()
        r = np.asarray(self.spec.imu_mount, float)
        a_body = state.accel + np.array([-state.w ** 2 * r[0], -state.w ** 2 * r[1], 0.0])
        f = a_body - R.T @ np.array([0.0, 0.0, -self.gravity])
        acc = f + self.accel_bias + n.accel_noise * sq * self.rng.standard_normal(3)
        if self._yaw is None:
            self._yaw = state.yaw
        else:
            self._yaw = float(wrap_angle(self._yaw + gyro[2] * dt))
        gv = (n.gyro_noise * sq) ** 2
        av = (n.accel_noise * sq) ** 2
        return Imu(header=Header(stamp=t, frame_id=self.frame_id),
                   orientation=euler_to_quaternion(state.pose[3], state.pose[4], self._yaw),
                   orientation_covariance=np.diag([1e-4, 1e-4, 1e-2]),
                   angular_velocity=gyro, angular_velocity_covariance=np.eye(3) * gv,
                   linear_acceleration=acc, linear_acceleration_covariance=np.eye(3) * av)


# --------------------------------------------------------------------------- ray casting


def _mi_scene(scene):
    """The Mitsuba scene of a TwinScene, a sionna Scene or a Mitsuba scene."""
    if hasattr(scene, "sionna"):
        scene = scene.sionna
    if hasattr(scene, "mi_scene"):
        scene = scene.mi_scene
    return scene


def _target_shape_ids(scene) -> np.ndarray:
    """Registry ids ``[T]`` (uint32, as ``reinterpret_array(UInt32, ShapePtr)``
    gives them) of the radar's sensing-target cuboids in the scene: Sionna puts
    them into the Mitsuba scene as shapes, but they are the radar's proxies of
    robots and objects, not geometry a LiDAR or camera sees."""
    import drjit as dr
    import mitsuba as mi

    sc = scene.sionna if hasattr(scene, "sionna") else scene
    targets = getattr(sc, "sensing_targets", None) or {}
    ids = [int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(t.mi_mesh))[0])
           for t in targets.values()]
    return np.array(ids, np.uint32)


@dataclass(frozen=True)
class Body:
    """A box that occludes the scene sensors: a robot's body.

    Robots are not shapes of the Mitsuba scene (they move every step), so the
    LiDAR and depth cameras of the other robots see them through this box,
    intersected analytically (:func:`body_hits`).

    Attributes:
        centre: box centre ``[3]``, world frame, m.
        yaw: heading of the box's x axis, rad.
        size: ``(length, width, height)``, m.
    """

    centre: tuple[float, float, float]
    yaw: float
    size: tuple[float, float, float]


def body_hits(origins: np.ndarray, directions: np.ndarray, bodies: Sequence[Body],
              owner: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """First hit of each ray on the boxes ``bodies`` (slab test in each box's frame).

    Args:
        origins: ``[N, 3]`` or ``[3]``, m; directions: ``[N, 3]`` unit vectors.
        owner: ``[N]`` index into ``bodies`` of the box each ray ignores (its own
            robot's), -1 for none.

    Returns:
        ``t [N]`` distance to the first box entered (m, ``inf`` if none; a ray
        starting inside a box does not hit it) and ``cos_inc [N]`` |cos| of the
        incidence angle on the face entered.
    """
    d = np.asarray(directions, np.float64)
    n = d.shape[0]
    o = np.broadcast_to(np.asarray(origins, np.float64), (n, 3))
    best = np.full(n, np.inf)
    cos_best = np.zeros(n)
    for k, b in enumerate(bodies):
        c, s = math.cos(b.yaw), math.sin(b.yaw)
        R = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])  # world -> box
        ol = (o - np.asarray(b.centre, float)) @ R.T
        dl = d @ R.T
        half = 0.5 * np.asarray(b.size, float)
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (-half - ol) / dl
            t2 = (half - ol) / dl
        lo = np.where(np.isnan(t1), -np.inf, np.minimum(t1, t2))  # [N, 3]
        hi = np.where(np.isnan(t1), np.inf, np.maximum(t1, t2))
        # a ray parallel to a slab misses unless it runs between its faces
        par = dl == 0
        inside = np.abs(ol) <= half
        lo = np.where(par, np.where(inside, -np.inf, np.inf), lo)
        hi = np.where(par, np.where(inside, np.inf, -np.inf), hi)
        axis = np.argmax(lo, axis=1)
        t_in, t_out = lo.max(axis=1), hi.min(axis=1)
        hit = (t_in > 0) & (t_in <= t_out) & (t_in < best)
        if owner is not None:
            hit &= np.asarray(owner) != k
        best = np.where(hit, t_in, best)
        cos_best = np.where(hit, np.abs(dl[np.arange(n), axis]), cos_best)
    return best, cos_best


#: how far past a skipped target's surface a ray is cast on, m
_SKIP_EPS = 1e-4


def _intersect(m, org, d: np.ndarray, n: int):
    """One Mitsuba ``ray_intersect`` of ``n`` rays: numpy ``t``, ``valid``, the
    unnormalised hit normal ``[3, N]`` and the hit shape's registry id."""
    import drjit as dr
    import mitsuba as mi

    ray = mi.Ray3f(o=org, d=mi.Vector3f(mi.Float(d[:, 0].copy()), mi.Float(d[:, 1].copy()),
                                        mi.Float(d[:, 2].copy())))
    si = m.ray_intersect(ray)
    valid_mi = si.is_valid()
    shape = dr.reinterpret_array(mi.UInt32, si.shape)
    dr.eval(si.t, si.n, valid_mi, shape)  # one kernel for all outputs
    valid = np.array(valid_mi, bool).reshape(-1)
    if valid.shape != (n,):
        valid = np.broadcast_to(valid, (n,)).copy()
    t = np.where(valid, np.array(si.t, np.float64).reshape(-1), np.inf)
    nrm = np.array(si.n, np.float64)
    if nrm.shape != (3, n):  # drjit returns Vector3f as [3, N]
        nrm = nrm.reshape(3, -1) if nrm.size == 3 * n else np.zeros((3, n))
    ids = np.array(shape, np.uint32).reshape(-1)
    if ids.shape != (n,):
        ids = np.broadcast_to(ids, (n,)).copy()
    return t, valid, nrm, ids


def _points(p: np.ndarray):
    import mitsuba as mi

    p = np.ascontiguousarray(p, np.float32)
    return mi.Point3f(mi.Float(p[:, 0].copy()), mi.Float(p[:, 1].copy()),
                      mi.Float(p[:, 2].copy()))


def cast_rays(scene, origins: np.ndarray, directions: np.ndarray, *,
              bodies: Sequence[Body] = (), owner: np.ndarray | None = None
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cast ``N`` rays into the scene's geometry and the robots' ``bodies``.

    The radar's sensing-target cuboids in the Sionna scene are not geometry a
    sensor sees (one encloses each robot's own LiDAR): a ray that hits one is
    cast on from just past it (:data:`_SKIP_EPS`), so it returns what the scene
    without targets returns. The robots are seen through ``bodies`` instead.

    Args:
        scene: a :class:`~isac_twin.scene.twin_scene.TwinScene`, ``sionna.rt.Scene`` or
            Mitsuba scene.
        origins: ``[N, 3]`` or ``[3]`` (shared), m.
        directions: ``[N, 3]`` unit vectors.
        bodies: boxes that occlude (:class:`Body`, e.g. the other robots).
        owner: ``[N]`` index into ``bodies`` of the box a ray ignores (the body
            of the robot that casts it), -1 for none.

    Returns:
        ``t [N]`` distance to the first hit (m, ``inf`` if none), ``valid [N]``
        bool, ``cos_inc [N]`` |cos| of the incidence angle on the hit surface.
    """
    import drjit as dr
    import mitsuba as mi

    m = _mi_scene(scene)
    d = np.ascontiguousarray(directions, np.float32)
    n = d.shape[0]
    o = np.asarray(origins, np.float32)
    if o.ndim == 1:
        # one shared origin; opaque, so a new pose does not bake new literals into
        # the kernel and force a recompile (that costs ~20 ms per scan)
        org = mi.Point3f(*(dr.opaque(mi.Float, float(c)) for c in o))
    else:
        org = _points(o)
    t, valid, nrm, ids = _intersect(m, org, d, n)
    skip = _target_shape_ids(scene)
    if skip.size:
        o64 = np.broadcast_to(np.asarray(origins, np.float64), (n, 3))
        d64 = d.astype(np.float64)
        # a ray crosses each convex cuboid at most twice
        for _ in range(2 * skip.size + 1):
            again = np.flatnonzero(valid & np.isin(ids, skip))
            if again.size == 0:
                break
            base = t[again] + _SKIP_EPS
            t2, v2, n2, i2 = _intersect(m, _points(o64[again] + d64[again] * base[:, None]),
                                        d[again], again.size)
            t[again], valid[again], ids[again] = base + t2, v2, i2
            nrm[:, again] = n2
        else:
            lost = valid & np.isin(ids, skip)
            valid &= ~lost
            t[lost] = np.inf
    cos_inc = np.abs(np.einsum("in,ni->n", nrm, d.astype(np.float64)))
    cos_inc = np.where(valid, cos_inc, 0.0)
    if bodies:
        tb, cb = body_hits(origins, d, bodies, owner)
        closer = tb < t
        t = np.where(closer, tb, t)
        valid = valid | closer
        cos_inc = np.where(closer, cb, cos_inc)
    return t, valid, cos_inc


class Lidar2D(Sensor):
    """A planar 360-degree laser scanner (RPLIDAR A1/A2-like) at ``base_scan``.

    All beams are cast from the scan pose in one vectorised Mitsuba
    ``ray_intersect``. Beams are at ``angle_min + i * angle_increment`` in the
    ``base_scan`` frame (x forward, counter-clockwise), ``angle_min = -pi``.

    Range model: a hit at distance ``d`` reads ``d + N(0, (rel d + abs)^2)``;
    no hit, a hit beyond ``range_max``, below ``range_min`` or lost to
    ``dropout`` reads ``inf`` with quality 0 (the RPLIDAR reports distance 0,
    which drivers publish as inf). Quality (``intensities``, 0..63 as the
    RPLIDAR's 6-bit quality) falls with incidence angle and distance:
    ``round(clip(63 sqrt(cos_inc) (1 - 0.5 d / range_max), 0, 63))``; beams at
    grazing incidence (``cos_inc < min_cos_incidence``) are lost.

    Args:
        scene: :class:`~isac_twin.scene.twin_scene.TwinScene` (or sionna/Mitsuba scene); the
            Mitsuba scene is first used at the first scan, so a scene loaded
            with ``load_sionna=False`` is fine until then.
        spec: robot model (for the mount).
        mount: ``base_scan`` origin in base_link ``[3]``, m (default: the model's URDF).
        rate_hz: scan rate, Hz (RPLIDAR A1 default 5.5).
        range_noise_rel, range_noise_abs: range noise std = rel * d + abs (m).
        dropout: probability that a valid return is lost.
    """

    msg_type = LaserScan
    topic = "scan"

    def __init__(self, scene, spec: RobotSpec | str = "burger", *, mount=None,
                 num_beams: int = 360, range_min: float = 0.15, range_max: float = 12.0,
                 rate_hz: float = 5.5, range_noise_rel: float = 0.005,
                 range_noise_abs: float = 0.002, dropout: float = 0.0,
                 min_cos_incidence: float = 0.05, seed: int | None = 0, rng=None):
        super().__init__(rate_hz, seed=seed, rng=rng, frame_id="base_scan")
        self.scene = scene
        self.spec = robot_spec(spec) if isinstance(spec, str) else spec
        self.mount = np.asarray(self.spec.lidar_mount if mount is None else mount, float)
        if int(num_beams) < 1:
            raise ValueError(f"Lidar2D: num_beams must be >= 1, got {num_beams}")
        if not 0 < range_min < range_max:
            raise ValueError(f"Lidar2D: need 0 < range_min < range_max, got {range_min}, "
                             f"{range_max}")
        self.num_beams = int(num_beams)
        self.range_min, self.range_max = float(range_min), float(range_max)
        self.range_noise_rel, self.range_noise_abs = range_noise_rel, range_noise_abs
        self.dropout, self.min_cos_incidence = dropout, min_cos_incidence
        self.angle_min = -math.pi
        self.angle_increment = 2 * math.pi / self.num_beams
        self.angles = self.angle_min + self.angle_increment * np.arange(self.num_beams)
        self._dirs_local = np.stack([np.cos(self.angles), np.sin(self.angles),
                                     np.zeros(self.num_beams)], axis=1)  # [M, 3]

    def rays(self, state: KinematicState) -> tuple[np.ndarray, np.ndarray]:
        """World origin ``[3]`` and beam directions ``[M, 3]`` for ``state``."""
        R = state.rotation()
        return state.pose[:3] + R @ self.mount, self._dirs_local @ R.T

    def discard(self, t: float, state: KinematicState) -> None:
        """The random draws of :meth:`measure` (dropout, then range noise: a fixed
        count per scan whatever the hits), without the ray cast."""
        if self.dropout > 0:
            self.rng.random(self.num_beams)
        if self.range_noise_rel > 0 or self.range_noise_abs > 0:
            self.rng.standard_normal(self.num_beams)

    def measure(self, t: float, state: KinematicState, hits=None) -> LaserScan:
        """The scan at ``state``; ``hits``: its beams' :func:`cast_rays` result when
        already cast (e.g. with other robots' beams in one call), else cast here."""
        d, valid, cos_inc = hits if hits is not None else cast_rays(self.scene, *self.rays(state))
        ok = valid & (d >= self.range_min) & (d <= self.range_max) \
            & (cos_inc >= self.min_cos_incidence)
        if self.dropout > 0:
            ok &= self.rng.random(self.num_beams) >= self.dropout
        r = d.copy()
        if self.range_noise_rel > 0 or self.range_noise_abs > 0:
            sd = self.range_noise_rel * np.where(ok, d, 0.0) + self.range_noise_abs
            r = r + sd * self.rng.standard_normal(self.num_beams)
        r = np.where(ok, r, np.inf)
        q = np.round(np.clip(63 * np.sqrt(cos_inc) * (1 - 0.5 * np.where(ok, d, 0) /
                                                      self.range_max), 0, 63))
        q = np.where(ok, q, 0.0)
        return LaserScan(header=Header(stamp=t, frame_id=self.frame_id),
                         angle_min=self.angle_min,
                         angle_max=self.angle_min + (self.num_beams - 1) * self.angle_increment,
                         angle_increment=self.angle_increment,
                         time_increment=self.period / self.num_beams, scan_time=self.period,
                         range_min=self.range_min, range_max=self.range_max,
                         ranges=r, intensities=q)


class DepthCamera(Sensor):
    """A small pinhole depth camera (OAK-D stereo-depth-like), off by default.

    When ``enabled``, each sample ray-casts a ``height x width`` image in one
    Mitsuba call and returns a ``16UC1`` :class:`~isac_twin.bus.msgs.Image` of depth
    along the optical axis in millimetres (0 = no return / beyond
    ``range_max``), as the OAK-D publishes depth. Disabled, :meth:`poll`
    returns ``None`` and costs nothing. No RGB image is rendered.

    The camera looks along base_link x from ``mount`` (default: the model's
    camera mount), ``hfov`` rad horizontal field of view, square pixels.
    """

    msg_type = Image
    topic = "camera/depth"

    def __init__(self, scene, spec: RobotSpec | str = "burger", *, enabled: bool = False,
                 width: int = 80, height: int = 60, hfov: float = math.radians(72.0),
                 range_max: float = 10.0, depth_noise_rel: float = 0.01, rate_hz: float = 5.0,
                 mount=None, seed: int | None = 0, rng=None):
        super().__init__(rate_hz, seed=seed, rng=rng, frame_id="camera_depth_optical_frame")
        self.scene = scene
        self.spec = robot_spec(spec) if isinstance(spec, str) else spec
        self.enabled = bool(enabled)
        self.width, self.height = int(width), int(height)
        self.hfov, self.range_max, self.depth_noise_rel = hfov, range_max, depth_noise_rel
        self.mount = np.asarray(self.spec.camera_mount if mount is None else mount, float)
        f = (self.width / 2) / math.tan(hfov / 2)  # focal length, px
        u = (np.arange(self.width) + 0.5 - self.width / 2) / f
        v = (np.arange(self.height) + 0.5 - self.height / 2) / f
        uu, vv = np.meshgrid(u, v)  # [H, W]; image x right = -y body, image y down = -z body
        d = np.stack([np.ones_like(uu), -uu, -vv], axis=-1).reshape(-1, 3)
        self._z_body = 1.0 / np.linalg.norm(d, axis=1)  # cos of the angle to the optical axis
        self._dirs_local = d * self._z_body[:, None]

    def poll(self, t: float, state: KinematicState, **measure_kw):
        if not self.enabled:
            return None
        return super().poll(t, state, **measure_kw)

    def skip(self, t: float, state: KinematicState) -> bool:
        return self.enabled and super().skip(t, state)

    def discard(self, t: float, state: KinematicState) -> None:
        """The random draws of :meth:`measure` (depth noise, one per pixel),
        without the ray cast."""
        if self.depth_noise_rel > 0:
            self.rng.standard_normal(self.height * self.width)

    def rays(self, state: KinematicState) -> tuple[np.ndarray, np.ndarray]:
        """World origin ``[3]`` and pixel ray directions ``[H * W, 3]`` for ``state``."""
        R = state.rotation()
        return state.pose[:3] + R @ self.mount, self._dirs_local @ R.T

    def measure(self, t: float, state: KinematicState, hits=None) -> Image:
        """The depth image at ``state``; ``hits``: its rays' :func:`cast_rays`
        result when already cast, else cast here."""
        dist, valid, _ = hits if hits is not None else cast_rays(self.scene, *self.rays(state))
        depth = dist * self._z_body
        if self.depth_noise_rel > 0:
            depth = depth * (1 + self.depth_noise_rel * self.rng.standard_normal(depth.shape))
        ok = valid & (depth <= self.range_max)
        mm = np.where(ok, np.round(depth * 1000.0), 0).astype(np.uint16)
        return Image(header=Header(stamp=t, frame_id=self.frame_id), height=self.height,
                     width=self.width, encoding="16UC1",
                     data=mm.reshape(self.height, self.width))


__all__ = ["Sensor", "WheelEncoders", "WheelOdometry", "ImuNoise", "ImuSensor", "Lidar2D",
           "DepthCamera", "Body", "body_hits", "cast_rays", "DXL_VELOCITY_UNIT"]
