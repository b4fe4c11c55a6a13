"""Agent state and the differential-drive motion model ``f`` (paper, eq. 5).

A TurtleBot3 is a differential-drive robot: two driven wheels of radius ``r``
on an axle of length ``L`` (the wheel separation) and a passive caster. Its
body twist ``(v, w)`` (m/s, rad/s) and wheel rates ``(phi_l, phi_r)`` (rad/s)
are related by::

    phi_l = (v - w L / 2) / r        v = r (phi_r + phi_l) / 2
    phi_r = (v + w L / 2) / r        w = r (phi_r - phi_l) / L

Frames follow REP-103/105: the pose is that of ``base_link`` (x forward, y
left, z up) in the world/``map`` frame (Z up); yaw is counter-clockwise
about Z. The robot moves on the floor plane, so ``z``, roll and pitch are
carried in the state (the paper's ``[x, y, z, alpha, beta, gamma]``) but only
changed by process noise if one asks for it.

Limits (source: ROBOTIS ``turtlebot3_node`` / OpenCR firmware):

* body speed: Burger 0.211 m/s, 2.63 rad/s; Waffle 0.266 m/s, 1.85 rad/s
  (:mod:`reference/devices.md`);
* per wheel: the OpenCR motor driver clamps each DYNAMIXEL goal velocity to
  337 units x 0.229 rpm = 77.2 rpm = 8.08 rad/s (0.267 m/s at the rim) --
  ``LIMIT_X_MAX_VELOCITY`` in ``turtlebot3_motor_driver.cpp``;
* acceleration: the firmware drives the motors in velocity mode without an
  acceleration profile, so no hard number exists on the robot itself. We use
  the values of the TurtleBot3 Nav2 parameter files (``acc_lim_x: 2.5``,
  ``acc_lim_theta: 3.2``; the same in the velocity smoother's
  ``max_accel``), which is what a TurtleBot3 under ROS 2 navigation actually
  sees. **Assumption**, documented here and adjustable per :class:`RobotSpec`.

Integration over a step ``dt`` is exact for constant velocities (a straight
segment when ``w == 0``, a circular arc otherwise). When the acceleration
limit makes the velocity ramp, the step is split at the instants where
``v`` and ``w`` reach their targets; each piece is integrated as an exact arc
with the piece's mean velocities (second-order accurate, and exact once the
robot is at its commanded speed).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from ..bus.msgs import Twist
from ..contract import schema
from ..errors import SpeedLimitError
from ..utils.geometry import euler_to_quaternion, rotation_matrix, wrap_angle

log = logging.getLogger(__name__)

#: Encoder resolution of the TurtleBot3's DYNAMIXEL X-series motors, rad/tick (2 pi / 4096).
TICK_RAD = 0.001533981
#: OpenCR per-wheel velocity clamp: 337 DYNAMIXEL units x 0.229 rpm, in rad/s.
MAX_WHEEL_RATE = 337 * 0.229 * 2 * math.pi / 60.0
#: Standard gravity, m/s^2.
GRAVITY = 9.80665


@dataclass(frozen=True)
class RobotSpec:
    """Physical parameters of one robot model.

    Attributes:
        model: ``"burger"`` or ``"waffle"``.
        wheel_radius: m.
        wheel_separation: distance between the wheels' contact points, m.
        max_linear: firmware limit on ``|v|``, m/s.
        max_angular: firmware limit on ``|w|``, rad/s.
        max_linear_accel: ``|dv/dt|`` limit, m/s^2 (assumption, see module doc).
        max_angular_accel: ``|dw/dt|`` limit, rad/s^2 (assumption, see module doc).
        max_wheel_rate: per-wheel clamp, rad/s.
        footprint_radius: radius of a circle enclosing the base, m (room checks).
        lidar_mount: ``base_scan`` origin in ``base_link`` ``[3]``, m (TurtleBot3 URDF).
        imu_mount: ``imu_link`` origin in ``base_link`` ``[3]``, m (TurtleBot3 URDF).
        camera_mount: camera origin in ``base_link`` ``[3]``, m.
        body_size: overall ``(length, width, height)`` of the base, m, a box centred
            on base_link in x/y from the floor up (what other robots' LiDAR and
            depth cameras see of it; the radar's target cuboid is the same box).
    """

    model: str
    wheel_radius: float
    wheel_separation: float
    max_linear: float
    max_angular: float
    max_linear_accel: float = 2.5
    max_angular_accel: float = 3.2
    max_wheel_rate: float = MAX_WHEEL_RATE
    footprint_radius: float = 0.11
    lidar_mount: tuple[float, float, float] = (-0.032, 0.0, 0.172)
    imu_mount: tuple[float, float, float] = (-0.032, 0.0, 0.068)
    camera_mount: tuple[float, float, float] = (0.07, 0.0, 0.15)
    body_size: tuple[float, float, float] = schema.ROBOT_MODELS["burger"].size

    @property
    def min_turn_radius_at_max_speed(self) -> float:
        """Smallest radius (m) the robot can follow at ``max_linear``: ``v / w_max``."""
        return self.max_linear / self.max_angular

    def wheel_rates(self, v: float, w: float) -> tuple[float, float]:
        """Left and right wheel rates (rad/s) for body twist ``v`` (m/s), ``w`` (rad/s)."""
        half = 0.5 * w * self.wheel_separation
        return (v - half) / self.wheel_radius, (v + half) / self.wheel_radius

    def body_twist(self, phi_l: float, phi_r: float) -> tuple[float, float]:
        """Body twist ``(v m/s, w rad/s)`` for wheel rates ``phi_l``, ``phi_r`` (rad/s)."""
        r = self.wheel_radius
        return r * (phi_r + phi_l) / 2.0, r * (phi_r - phi_l) / self.wheel_separation


def _spec(model: str, **mounts) -> RobotSpec:
    """A model's spec: the body (wheels, footprint, firmware limits) is the shared
    schema's (``addon/contract/schema.py``), the sensor mounts are the engine's."""
    body = schema.ROBOT_MODELS[model]
    return RobotSpec(model, body.wheel_radius, body.wheel_separation, body.max_linear,
                     body.max_angular, footprint_radius=body.footprint_radius,
                     body_size=tuple(body.size), **mounts)


#: The two TurtleBot3 models (dimensions from ROBOTIS' URDFs and e-Manual).
ROBOT_SPECS: dict[str, RobotSpec] = {
    "burger": _spec("burger", lidar_mount=(-0.032, 0.0, 0.172), imu_mount=(-0.032, 0.0, 0.068),
                    camera_mount=(0.04, 0.0, 0.20)),
    "waffle": _spec("waffle", lidar_mount=(-0.064, 0.0, 0.122), imu_mount=(-0.032, 0.0, 0.068),
                    camera_mount=(0.064, -0.065, 0.094)),
}


def robot_spec(model: str) -> RobotSpec:
    """The :class:`RobotSpec` of ``model`` (``"burger"`` or ``"waffle"``)."""
    try:
        return ROBOT_SPECS[model]
    except KeyError:
        raise ValueError(f"unknown robot model {model!r} (known: {', '.join(ROBOT_SPECS)})") \
            from None


def arc_step(x: float, y: float, yaw: float, v: float, w: float, dt: float
             ) -> tuple[float, float, float]:
    """Exact planar motion for a constant twist over ``dt`` (s).

    A straight segment when ``w`` is (numerically) zero, else a circular arc of
    radius ``v / w``. Returns the new ``(x, y, yaw)`` (m, m, rad; yaw unwrapped).
    """
    th = w * dt
    if abs(th) < 1e-9:
        # second-order series of the arc: avoids 0/0 and is exact to O(th^3)
        c = v * dt * (1.0 - th * th / 6.0)
        s = v * dt * th / 2.0
    else:
        c = v / w * math.sin(th)
        s = v / w * (1.0 - math.cos(th))
    cy, sy = math.cos(yaw), math.sin(yaw)
    return x + c * cy - s * sy, y + c * sy + s * cy, yaw + th


@dataclass
class KinematicState:
    """State ``s_t`` of one agent.

    Attributes:
        pose: ``[x, y, z, roll, pitch, yaw]`` of ``base_link`` in the world (m, rad).
        v: linear velocity along base_link x, m/s.
        w: angular velocity about z, rad/s.
        wheel_pos: left/right wheel angles ``[2]``, rad (unwrapped, as the encoders count).
        wheel_vel: left/right wheel rates ``[2]``, rad/s.
        accel: body-frame linear acceleration ``[3]`` over the last step, m/s^2
            (tangential ``dv/dt``, centripetal ``v w``, 0), what an IMU feels
            besides gravity.
        t: time, s.
    """

    pose: np.ndarray = field(default_factory=lambda: np.zeros(6))
    v: float = 0.0
    w: float = 0.0
    wheel_pos: np.ndarray = field(default_factory=lambda: np.zeros(2))
    wheel_vel: np.ndarray = field(default_factory=lambda: np.zeros(2))
    accel: np.ndarray = field(default_factory=lambda: np.zeros(3))
    t: float = 0.0

    @property
    def x(self) -> float:
        return float(self.pose[0])

    @property
    def y(self) -> float:
        return float(self.pose[1])

    @property
    def yaw(self) -> float:
        return float(self.pose[5])

    @property
    def position(self) -> np.ndarray:
        """``[3]`` m."""
        return self.pose[:3].copy()

    def rotation(self) -> np.ndarray:
        """``[3, 3]`` base_link -> world."""
        return rotation_matrix(*self.pose[3:6])

    def quaternion(self) -> np.ndarray:
        """Orientation ``[x, y, z, w]``."""
        return euler_to_quaternion(*self.pose[3:6])

    def to_world(self, p_body) -> np.ndarray:
        """Point ``[3]`` in base_link -> world ``[3]`` (m)."""
        return self.pose[:3] + self.rotation() @ np.asarray(p_body, float)

    def vector(self) -> np.ndarray:
        """``[8]``: ``[x, y, z, roll, pitch, yaw, v, w]``."""
        return np.concatenate([self.pose, [self.v, self.w]])

    def copy(self) -> KinematicState:
        return replace(self, pose=self.pose.copy(), wheel_pos=self.wheel_pos.copy(),
                       wheel_vel=self.wheel_vel.copy(), accel=self.accel.copy())


@dataclass(frozen=True)
class ProcessNoise:
    """Gaussian process noise ``eps_s`` of eq. 5, as random walks per sqrt(second).

    The noise is added to the pose after the deterministic step; the wheels do
    not see it, so it acts like wheel slip / floor unevenness and makes wheel
    odometry drift from the truth. All zero by default (a deterministic twin).

    Attributes:
        xy_std: m / sqrt(s), along the robot's own x and y.
        yaw_std: rad / sqrt(s).
        z_std, rp_std: m / sqrt(s) and rad / sqrt(s) for z and roll/pitch.
        speed_scaled: scale the xy/yaw noise by ``|v| / max_linear`` and
            ``|w| / max_angular`` so a robot at rest does not wander.
    """

    xy_std: float = 0.0
    yaw_std: float = 0.0
    z_std: float = 0.0
    rp_std: float = 0.0
    speed_scaled: bool = True

    @property
    def enabled(self) -> bool:
        return any(s > 0 for s in (self.xy_std, self.yaw_std, self.z_std, self.rp_std))


def as_command(u) -> tuple[float, float]:
    """``(v, w)`` from a :class:`~isac_twin.bus.msgs.Twist` or a 2-sequence (m/s, rad/s)."""
    if isinstance(u, Twist):
        v, w = float(u.linear[0]), float(u.angular[2])
    else:
        try:
            v, w = (float(c) for c in u)
        except (TypeError, ValueError):
            raise TypeError(f"a command is a Twist or (v, w), got {u!r}") from None
    if not (math.isfinite(v) and math.isfinite(w)):
        raise ValueError(f"command must be finite, got v={v}, w={w}")
    return v, w


def make_twist(v: float, w: float) -> Twist:
    """A :class:`~isac_twin.bus.msgs.Twist` with ``linear.x = v``, ``angular.z = w``."""
    return Twist(linear=np.array([v, 0.0, 0.0]), angular=np.array([0.0, 0.0, w]))


class DiffDriveRobot:
    """One TurtleBot3: the motion model ``f`` of eq. 5 with its state.

    Call :meth:`step` once per twin step with the last command ``u_{t-1}``::

        robot = DiffDriveRobot("burger", pose=(4.0, 1.5, 0.0, 0, 0, np.pi / 2), seed=1)
        state = robot.step((0.2, 0.1), dt=0.05)

    Args:
        spec: a :class:`RobotSpec` or a model name.
        pose: initial ``[x, y, z, roll, pitch, yaw]`` (m, rad); a 3-vector
            ``[x, y, yaw]`` is accepted too.
        noise: process noise (default: none).
        seed: seed of the robot's own ``numpy.random.Generator`` (or pass ``rng``).
        name: for messages and logs.
    """

    def __init__(self, spec: RobotSpec | str = "burger", pose: Sequence[float] = (0, 0, 0),
                 *, noise: ProcessNoise | None = None, seed: int | None = 0,
                 rng: np.random.Generator | None = None, name: str = "robot"):
        self.spec = robot_spec(spec) if isinstance(spec, str) else spec
        p = np.asarray(pose, float)
        if p.shape == (3,):
            p = np.array([p[0], p[1], 0.0, 0.0, 0.0, p[2]])
        if p.shape != (6,) or not np.all(np.isfinite(p)):
            raise ValueError(f"{name}: pose must be 6 (or 3) finite numbers, got {pose!r}")
        self.name = name
        self.noise = noise or ProcessNoise()
        self.rng = rng if rng is not None else np.random.default_rng(seed)
        self.state = KinematicState(pose=p)
        self.command = (0.0, 0.0)  #: last clamped command (v, w)

    # ------------------------------------------------------------------ limits
    def clamp(self, v: float, w: float, *, validate: bool = False) -> tuple[float, float]:
        """Apply the firmware limits to a command ``(v, w)``.

        Like the OpenCR firmware: clamp ``|v|`` and ``|w|`` to the model's limits,
        then each wheel's rate to :data:`MAX_WHEEL_RATE` (which, for a combined
        ``v`` and ``w``, lowers the resulting twist).

        Args:
            validate: raise :class:`SpeedLimitError` instead of clamping.
        """
        s = self.spec
        if validate:
            if abs(v) > s.max_linear + 1e-12:
                raise SpeedLimitError(f"{self.name}: linear velocity {v:.4g} m/s exceeds the "
                                      f"{s.model} limit of {s.max_linear} m/s")
            if abs(w) > s.max_angular + 1e-12:
                raise SpeedLimitError(f"{self.name}: angular velocity {w:.4g} rad/s exceeds "
                                      f"the {s.model} limit of {s.max_angular} rad/s")
            pl, pr = s.wheel_rates(v, w)
            if max(abs(pl), abs(pr)) > s.max_wheel_rate + 1e-9:
                raise SpeedLimitError(
                    f"{self.name}: v={v:.4g} m/s with w={w:.4g} rad/s needs a wheel rate of "
                    f"{max(abs(pl), abs(pr)):.4g} rad/s, above the {s.model} per-wheel limit "
                    f"of {s.max_wheel_rate:.4g} rad/s")
        v = min(max(v, -s.max_linear), s.max_linear)
        w = min(max(w, -s.max_angular), s.max_angular)
        pl, pr = s.wheel_rates(v, w)
        m = s.max_wheel_rate
        pl, pr = min(max(pl, -m), m), min(max(pr, -m), m)
        return s.body_twist(pl, pr)

    # ------------------------------------------------------------------ step
    def step(self, u, dt: float, *, validate: bool = False) -> KinematicState:
        """Advance the state by ``dt`` s under command ``u`` (eq. 5).

        Args:
            u: a :class:`~isac_twin.bus.msgs.Twist` or ``(v m/s, w rad/s)``; values above
                the limits are clamped like the firmware does.
            dt: step, s (> 0).
            validate: raise :class:`SpeedLimitError` for a command above a limit.

        Returns:
            The new :class:`KinematicState` (also ``self.state``).
        """
        if not (dt > 0 and math.isfinite(dt)):
            raise ValueError(f"{self.name}: dt must be a positive finite number of s, got {dt}")
        v_cmd, w_cmd = self.clamp(*as_command(u), validate=validate)
        self.command = (v_cmd, w_cmd)
        s, st = self.spec, self.state
        v0, w0 = st.v, st.w
        # acceleration limits: the velocity ramps toward the command
        tv = abs(v_cmd - v0) / s.max_linear_accel
        tw = abs(w_cmd - w0) / s.max_angular_accel

        def vel(t: float) -> tuple[float, float]:
            fv = 1.0 if tv <= t else t / tv
            fw = 1.0 if tw <= t else t / tw
            return v0 + (v_cmd - v0) * fv, w0 + (w_cmd - w0) * fw

        knots = sorted({0.0, dt, *(k for k in (tv, tw) if 0.0 < k < dt)})
        x, y, yaw = st.pose[0], st.pose[1], st.pose[5]
        for a, b in zip(knots[:-1], knots[1:]):
            va, wa = vel(a)
            vb, wb = vel(b)
            x, y, yaw = arc_step(x, y, yaw, 0.5 * (va + vb), 0.5 * (wa + wb), b - a)
        v1, w1 = vel(dt)
        # wheels: velocities are piecewise linear, so the mean rate is exact
        vm = sum(0.5 * (vel(a)[0] + vel(b)[0]) * (b - a) for a, b in zip(knots[:-1], knots[1:]))
        wm = sum(0.5 * (vel(a)[1] + vel(b)[1]) * (b - a) for a, b in zip(knots[:-1], knots[1:]))
        # wheel_rates is linear, so applied to (distance, angle) it gives the wheel angle increments
        dl, dr = s.wheel_rates(vm, wm)

        pose = st.pose.copy()
        pose[0], pose[1], pose[5] = x, y, yaw
        n = self.noise
        if n.enabled:
            sq = math.sqrt(dt)
            kv = min(abs(v1) / s.max_linear, 1.0) if n.speed_scaled else 1.0
            kw = min(max(abs(w1) / s.max_angular, kv), 1.0) if n.speed_scaled else 1.0
            e = self.rng.standard_normal(6)
            dx, dy = n.xy_std * sq * kv * e[0], n.xy_std * sq * kv * e[1]
            c, sn = math.cos(yaw), math.sin(yaw)
            pose[0] += c * dx - sn * dy
            pose[1] += sn * dx + c * dy
            pose[5] += n.yaw_std * sq * kw * e[2]
            pose[2] += n.z_std * sq * e[3]
            pose[3] += n.rp_std * sq * e[4]
            pose[4] += n.rp_std * sq * e[5]
        pose[5] = float(wrap_angle(pose[5]))

        accel = np.array([(v1 - v0) / dt, v1 * w1, 0.0])
        self.state = KinematicState(pose=pose, v=v1, w=w1,
                                wheel_pos=st.wheel_pos + np.array([dl, dr]),
                                wheel_vel=np.array(s.wheel_rates(v1, w1)),
                                accel=accel, t=st.t + dt)
        return self.state

    __call__ = step

    # ------------------------------------------------------------------ helpers
    def reset(self, pose: Sequence[float], t: float = 0.0) -> None:
        """Put the robot at rest at ``pose`` (6 or 3 numbers) at time ``t`` (s)."""
        p = np.asarray(pose, float)
        if p.shape == (3,):
            p = np.array([p[0], p[1], 0.0, 0.0, 0.0, p[2]])
        self.state = KinematicState(pose=p, t=t)

    def antenna_position(self, offset: Sequence[float]) -> np.ndarray:
        """World position ``[3]`` (m) of a point at ``offset`` in base_link (e.g. the antenna)."""
        return self.state.to_world(offset)


@dataclass(frozen=True)
class PoseObservation:
    """A simple observation model ``g`` (eq. 6): the pose with Gaussian noise.

    Stands in for any absolute position fix (e.g. a localization estimate);
    the richer observations are in :mod:`isac_twin.robots.sensors`.

    Attributes:
        xy_std: m; yaw_std: rad.
    """

    xy_std: float = 0.0
    yaw_std: float = 0.0

    def __call__(self, state: KinematicState, rng: np.random.Generator) -> np.ndarray:
        """``[3]``: observed ``[x, y, yaw]`` (m, m, rad)."""
        e = rng.standard_normal(3) * np.array([self.xy_std, self.xy_std, self.yaw_std])
        return np.array([state.x + e[0], state.y + e[1], float(wrap_angle(state.yaw + e[2]))])
