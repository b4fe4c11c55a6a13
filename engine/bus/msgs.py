"""ROS 2-shaped message types for the topic bus, the devices and recording.

Field names and units follow the ROS 2 definitions (``sensor_msgs``,
``nav_msgs``, ``geometry_msgs``) so that a message converts one-to-one to
CDR for a ROS 2 peer or an MCAP file. Arrays are numpy; times are float
seconds here (``Header.stamp``) and split into ``sec``/``nanosec`` only at
the serialization edge.

Every type has ``ROS_TYPE`` (e.g. ``"sensor_msgs/msg/LaserScan"``);
:data:`MESSAGE_TYPES` maps those names to the classes.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


def _zeros(n: int):
    return field(default_factory=lambda: np.zeros(n))


def _cov(n: int):
    return field(default_factory=lambda: np.zeros((n, n)))


@dataclass
class Header:
    stamp: float = 0.0  #: s since the epoch of the source's clock
    frame_id: str = ""


@dataclass
class Vector3:
    ROS_TYPE = "geometry_msgs/msg/Vector3"
    x: float = 0.0
    y: float = 0.0
    z: float = 0.0


@dataclass
class Pose:
    """Position (m) and orientation quaternion ``[x, y, z, w]``."""

    ROS_TYPE = "geometry_msgs/msg/Pose"
    position: np.ndarray = _zeros(3)
    orientation: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 0.0, 1.0]))


@dataclass
class PoseStamped:
    ROS_TYPE = "geometry_msgs/msg/PoseStamped"
    header: Header = field(default_factory=Header)
    pose: Pose = field(default_factory=Pose)


@dataclass
class Twist:
    """Linear (m/s) and angular (rad/s) velocity ``[3]`` each."""

    ROS_TYPE = "geometry_msgs/msg/Twist"
    linear: np.ndarray = _zeros(3)
    angular: np.ndarray = _zeros(3)


@dataclass
class Odometry:
    ROS_TYPE = "nav_msgs/msg/Odometry"
    header: Header = field(default_factory=lambda: Header(frame_id="odom"))
    child_frame_id: str = "base_footprint"
    pose: Pose = field(default_factory=Pose)
    pose_covariance: np.ndarray = _cov(6)
    twist: Twist = field(default_factory=Twist)
    twist_covariance: np.ndarray = _cov(6)


@dataclass
class Imu:
    """Orientation quaternion, angular velocity (rad/s), linear acceleration (m/s^2)."""

    ROS_TYPE = "sensor_msgs/msg/Imu"
    header: Header = field(default_factory=lambda: Header(frame_id="imu_link"))
    orientation: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 0.0, 1.0]))
    orientation_covariance: np.ndarray = _cov(3)
    angular_velocity: np.ndarray = _zeros(3)
    angular_velocity_covariance: np.ndarray = _cov(3)
    linear_acceleration: np.ndarray = _zeros(3)
    linear_acceleration_covariance: np.ndarray = _cov(3)


@dataclass
class LaserScan:
    """A planar scan: ``ranges [M]`` m (inf = no return), ``intensities [M]``."""

    ROS_TYPE = "sensor_msgs/msg/LaserScan"
    header: Header = field(default_factory=lambda: Header(frame_id="base_scan"))
    angle_min: float = 0.0
    angle_max: float = 0.0
    angle_increment: float = 0.0
    time_increment: float = 0.0
    scan_time: float = 0.0
    range_min: float = 0.0
    range_max: float = 0.0
    ranges: np.ndarray = _zeros(0)
    intensities: np.ndarray = _zeros(0)


@dataclass
class Image:
    """``data`` is ``[height, width, channels]`` uint8 (or ``[h, w]`` uint16 depth)."""

    ROS_TYPE = "sensor_msgs/msg/Image"
    header: Header = field(default_factory=lambda: Header(frame_id="camera"))
    height: int = 0
    width: int = 0
    encoding: str = "rgb8"
    data: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 3), np.uint8))


@dataclass
class BatteryState:
    ROS_TYPE = "sensor_msgs/msg/BatteryState"
    header: Header = field(default_factory=Header)
    voltage: float = 0.0  #: V


MESSAGE_TYPES: dict[str, type] = {
    cls.ROS_TYPE: cls
    for cls in (Vector3, Pose, PoseStamped, Twist, Odometry, Imu, LaserScan, Image, BatteryState)
}


@dataclass
class JointState:
    """Joint positions (rad), velocities (rad/s), efforts; e.g. the two wheels."""

    ROS_TYPE = "sensor_msgs/msg/JointState"
    header: Header = field(default_factory=Header)
    name: list = field(default_factory=list)
    position: np.ndarray = _zeros(0)
    velocity: np.ndarray = _zeros(0)
    effort: np.ndarray = _zeros(0)


MESSAGE_TYPES[JointState.ROS_TYPE] = JointState


@dataclass
class DiagnosticStatus:
    """One component's health (``diagnostic_msgs/DiagnosticStatus``): ``level``
    :attr:`OK` 0, :attr:`WARN` 1, :attr:`ERROR` 2, :attr:`STALE` 3; ``values``
    a list of ``(key, value)`` string pairs."""

    ROS_TYPE = "diagnostic_msgs/msg/DiagnosticStatus"
    OK, WARN, ERROR, STALE = 0, 1, 2, 3
    level: int = 0
    name: str = ""
    message: str = ""
    hardware_id: str = ""
    values: list = field(default_factory=list)


@dataclass
class DiagnosticArray:
    """``diagnostic_msgs/DiagnosticArray``: the statuses of one publisher's components."""

    ROS_TYPE = "diagnostic_msgs/msg/DiagnosticArray"
    header: Header = field(default_factory=Header)
    status: list = field(default_factory=list)  #: [DiagnosticStatus]


MESSAGE_TYPES[DiagnosticArray.ROS_TYPE] = DiagnosticArray


@dataclass
class Csi:
    """The CSI a robot's radio receives on one link (Algorithm 1, stage 3).

    ``h`` is ``[K, N, Nr, Nt]`` complex (symbols, subcarriers, rx ports, tx ports).
    """

    ROS_TYPE = "isac_twin_msgs/msg/Csi"
    header: Header = field(default_factory=Header)
    tx: str = ""
    rx: str = ""
    h: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 0, 0), np.complex64))


MESSAGE_TYPES[Csi.ROS_TYPE] = Csi


@dataclass
class TransformStamped:
    """``header.frame_id`` -> ``child_frame_id``: translation (m) ``[3]`` and rotation
    quaternion ``[x, y, z, w]`` of the child frame in the parent frame."""

    ROS_TYPE = "geometry_msgs/msg/TransformStamped"
    header: Header = field(default_factory=Header)
    child_frame_id: str = ""
    translation: np.ndarray = _zeros(3)
    rotation: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 0.0, 1.0]))


@dataclass
class TFMessage:
    """A batch of transforms (``/tf``, ``/tf_static``)."""

    ROS_TYPE = "tf2_msgs/msg/TFMessage"
    transforms: list[TransformStamped] = field(default_factory=list)


@dataclass
class Clock:
    """``/clock``: the current (simulated) time, s."""

    ROS_TYPE = "rosgraph_msgs/msg/Clock"
    clock: float = 0.0


for _cls in (TransformStamped, TFMessage, Clock):
    MESSAGE_TYPES[_cls.ROS_TYPE] = _cls


def shift_stamps(msg, offset_s: float):
    """A copy of ``msg`` with every ``Header.stamp`` (nested ones and those in lists, e.g.
    a TFMessage's transforms) and ``Clock.clock`` moved by ``offset_s`` s; other fields
    are shared, not copied. Used at the recording/network edge to put the twin's
    simulated time on a wall-clock epoch."""
    import dataclasses

    if isinstance(msg, Header):
        return dataclasses.replace(msg, stamp=msg.stamp + offset_s)
    if isinstance(msg, Clock):
        return Clock(msg.clock + offset_s)
    if not dataclasses.is_dataclass(msg) or isinstance(msg, type):
        return msg
    changes = {}
    for f in dataclasses.fields(msg):
        v = getattr(msg, f.name)
        if isinstance(v, Header) or dataclasses.is_dataclass(v):
            changes[f.name] = shift_stamps(v, offset_s)
        elif isinstance(v, list) and v and dataclasses.is_dataclass(v[0]):
            changes[f.name] = [shift_stamps(x, offset_s) for x in v]
    return dataclasses.replace(msg, **changes) if changes else msg
