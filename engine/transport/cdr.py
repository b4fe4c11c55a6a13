"""CDR codec: :mod:`isac_twin.bus.msgs` dataclasses <-> ROS 2 messages, through rosbags.

The wire form is what ``rmw_zenoh`` and ``ros2 bag`` carry: XCDR1 little
endian with the 4-byte encapsulation header ``00 01 00 00``. The typestore is
rosbags' ROS 2 Jazzy store plus the :mod:`isac_twin.bus.twin_msgs` types
(registered from their ``.msg`` text).

Conversions at this edge (and only here):

* ``Header.stamp`` float s -> ``builtin_interfaces/Time`` ``sec``/``nanosec``
  (round to the nearest ns; float64 s keeps ~0.2 us at today's epoch);
* covariance matrices ``[n, n]`` <-> flattened ``float64[n*n]`` row-major;
* positions ``[3]`` <-> ``geometry_msgs/Point``, quaternions ``[x, y, z, w]`` <->
  ``geometry_msgs/Quaternion``, vectors ``[3]`` <-> ``geometry_msgs/Vector3``;
* ``Image.data`` ``[h, w(, c)]`` <-> ``uint8[]`` with ``step``; the dtype and
  channel count come back from ``encoding`` (``rgb8``/``bgr8`` 3, ``rgba8``/
  ``bgra8`` 4, ``mono8`` 1 x uint8, ``mono16``/``16UC1`` uint16, ``32FC1`` float32);
* ``BatteryState`` fields the dataclass lacks are sent as ROS' "unknown" (NaN).

Example::

    data = encode(LaserScan(...))            # bytes, CDR
    scan = decode(data, "sensor_msgs/msg/LaserScan")
"""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from ..bus import msgs as m
from ..bus import twin_msgs as tm
from . import sensing_cdr

#: XCDR1 little-endian encapsulation header (what rmw_zenoh and ros2 bag carry).
CDR_HEADER = b"\x00\x01\x00\x00"


@functools.lru_cache(maxsize=None)
def typestore():
    """The rosbags typestore (ROS 2 Jazzy + ``isac_twin_msgs``)."""
    ts = get_typestore(Stores.ROS2_JAZZY)
    types: dict = {}
    for name, text in {**tm.MSG_DEFINITIONS, **sensing_cdr.MSG_DEFINITIONS}.items():
        types.update(get_types_from_msg(text, name))
    ts.register(types)
    return ts


def dds_type_name(type_name: str) -> str:
    """The DDS/rmw type name: ``sensor_msgs/msg/LaserScan`` -> ``sensor_msgs::msg::dds_::LaserScan_``."""
    pkg, kind, name = type_name.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


@functools.lru_cache(maxsize=None)
def type_hash(type_name: str) -> str:
    """REP-2011 type hash ``RIHS01_<sha256 hex>`` (what Jazzy's rmw_zenoh puts in key expressions)."""
    return typestore().hash_rihs01(type_name)


@functools.lru_cache(maxsize=None)
def msgdef(type_name: str) -> str:
    """The ``ros2msg`` schema text of a type with all its dependencies (MCAP schema data)."""
    text, _ = typestore().generate_msgdef(type_name, ros_version=2)
    return text


# ------------------------------------------------------------------ time

def stamp_to_ros(t: float):
    """Float seconds -> ``builtin_interfaces/msg/Time`` (nearest ns)."""
    T = typestore().types["builtin_interfaces/msg/Time"]
    ns = int(round(float(t) * 1e9)) if math.isfinite(t) else 0
    sec, nsec = divmod(ns, 1_000_000_000)
    return T(sec=int(sec), nanosec=int(nsec))


def stamp_from_ros(t) -> float:
    return t.sec + t.nanosec * 1e-9


def stamp_ns(t: float) -> int:
    """Float seconds -> integer nanoseconds (nearest)."""
    return int(round(float(t) * 1e9))


def _header(h: m.Header):
    T = typestore().types["std_msgs/msg/Header"]
    return T(stamp=stamp_to_ros(h.stamp), frame_id=h.frame_id)


def _header_from(h) -> m.Header:
    return m.Header(stamp=stamp_from_ros(h.stamp), frame_id=h.frame_id)


def _t(name: str):
    return typestore().types[name]


def _vec3(v):
    v = np.asarray(v, float)
    return _t("geometry_msgs/msg/Vector3")(x=float(v[0]), y=float(v[1]), z=float(v[2]))


def _point(v):
    v = np.asarray(v, float)
    return _t("geometry_msgs/msg/Point")(x=float(v[0]), y=float(v[1]), z=float(v[2]))


def _quat(q):
    q = np.asarray(q, float)
    return _t("geometry_msgs/msg/Quaternion")(x=float(q[0]), y=float(q[1]), z=float(q[2]),
                                              w=float(q[3]))


def _arr3(o) -> np.ndarray:
    return np.array([o.x, o.y, o.z], float)


def _arr4(o) -> np.ndarray:
    return np.array([o.x, o.y, o.z, o.w], float)


def _f64(a) -> np.ndarray:
    return np.ascontiguousarray(np.asarray(a, np.float64).ravel())


def _f32(a) -> np.ndarray:
    return np.ascontiguousarray(np.asarray(a, np.float32).ravel())


def _pose(p: m.Pose):
    return _t("geometry_msgs/msg/Pose")(position=_point(p.position), orientation=_quat(p.orientation))


def _pose_from(p) -> m.Pose:
    return m.Pose(position=_arr3(p.position), orientation=_arr4(p.orientation))


def _twist(t: m.Twist):
    return _t("geometry_msgs/msg/Twist")(linear=_vec3(t.linear), angular=_vec3(t.angular))


def _twist_from(t) -> m.Twist:
    return m.Twist(linear=_arr3(t.linear), angular=_arr3(t.angular))


_IMAGE_LAYOUT = {"rgb8": (np.uint8, 3), "bgr8": (np.uint8, 3), "rgba8": (np.uint8, 4),
                 "bgra8": (np.uint8, 4), "mono8": (np.uint8, 1), "8UC1": (np.uint8, 1),
                 "mono16": (np.uint16, 1), "16UC1": (np.uint16, 1), "32FC1": (np.float32, 1)}


def _transform(t: m.TransformStamped):
    return _t("geometry_msgs/msg/TransformStamped")(
        header=_header(t.header), child_frame_id=t.child_frame_id,
        transform=_t("geometry_msgs/msg/Transform")(translation=_vec3(t.translation),
                                                    rotation=_quat(t.rotation)))


def _transform_from(o) -> m.TransformStamped:
    return m.TransformStamped(header=_header_from(o.header), child_frame_id=o.child_frame_id,
                              translation=_arr3(o.transform.translation),
                              rotation=_arr4(o.transform.rotation))


# ------------------------------------------------------------------ to ROS

def to_ros(msg: Any):
    """The rosbags message object for an :mod:`isac_twin.bus.msgs` / ``twin_msgs`` dataclass."""
    R = _t(msg.ROS_TYPE)
    if isinstance(msg, m.Vector3):
        return R(x=float(msg.x), y=float(msg.y), z=float(msg.z))
    if isinstance(msg, m.Pose):
        return _pose(msg)
    if isinstance(msg, m.PoseStamped):
        return R(header=_header(msg.header), pose=_pose(msg.pose))
    if isinstance(msg, m.Twist):
        return _twist(msg)
    if isinstance(msg, m.Odometry):
        return R(header=_header(msg.header), child_frame_id=msg.child_frame_id,
                 pose=_t("geometry_msgs/msg/PoseWithCovariance")(
                     pose=_pose(msg.pose), covariance=_f64(msg.pose_covariance)),
                 twist=_t("geometry_msgs/msg/TwistWithCovariance")(
                     twist=_twist(msg.twist), covariance=_f64(msg.twist_covariance)))
    if isinstance(msg, m.Imu):
        return R(header=_header(msg.header), orientation=_quat(msg.orientation),
                 orientation_covariance=_f64(msg.orientation_covariance),
                 angular_velocity=_vec3(msg.angular_velocity),
                 angular_velocity_covariance=_f64(msg.angular_velocity_covariance),
                 linear_acceleration=_vec3(msg.linear_acceleration),
                 linear_acceleration_covariance=_f64(msg.linear_acceleration_covariance))
    if isinstance(msg, m.LaserScan):
        return R(header=_header(msg.header), angle_min=float(msg.angle_min),
                 angle_max=float(msg.angle_max), angle_increment=float(msg.angle_increment),
                 time_increment=float(msg.time_increment), scan_time=float(msg.scan_time),
                 range_min=float(msg.range_min), range_max=float(msg.range_max),
                 ranges=_f32(msg.ranges), intensities=_f32(msg.intensities))
    if isinstance(msg, m.Image):
        data = np.ascontiguousarray(msg.data)
        h, w = (int(msg.height), int(msg.width))
        step = (data.nbytes // h) if h else 0
        return R(header=_header(msg.header), height=h, width=w, encoding=msg.encoding,
                 is_bigendian=0, step=step,
                 data=np.frombuffer(data.astype(data.dtype.newbyteorder("<"), copy=False)
                                    .tobytes(), np.uint8))
    if isinstance(msg, m.BatteryState):
        nan = float("nan")
        return R(header=_header(msg.header), voltage=float(msg.voltage), temperature=nan,
                 current=nan, charge=nan, capacity=nan, design_capacity=nan, percentage=nan,
                 power_supply_status=0, power_supply_health=0, power_supply_technology=0,
                 present=True, cell_voltage=np.zeros(0, np.float32),
                 cell_temperature=np.zeros(0, np.float32), location="", serial_number="")
    if isinstance(msg, m.JointState):
        return R(header=_header(msg.header), name=[str(n) for n in msg.name],
                 position=_f64(msg.position), velocity=_f64(msg.velocity),
                 effort=_f64(msg.effort))
    if isinstance(msg, m.TransformStamped):
        return _transform(msg)
    if isinstance(msg, m.TFMessage):
        return R(transforms=[_transform(t) for t in msg.transforms])
    if isinstance(msg, m.Clock):
        return R(clock=stamp_to_ros(msg.clock))
    if isinstance(msg, m.DiagnosticArray):
        S, KV = _t("diagnostic_msgs/msg/DiagnosticStatus"), _t("diagnostic_msgs/msg/KeyValue")
        return R(header=_header(msg.header), status=[
            S(level=int(st.level), name=str(st.name), message=str(st.message), hardware_id=str(st.hardware_id),
              values=[KV(key=str(k), value=str(v)) for k, v in st.values]) for st in msg.status])
    if isinstance(msg, tm.LinkMetrics):
        return R(header=_header(msg.header), tx=msg.tx, rx=msg.rx, snr_db=float(msg.snr_db),
                 rate_bps=float(msg.rate_bps), num_paths=int(msg.num_paths), los=bool(msg.los),
                 total_gain_db=float(msg.total_gain_db),
                 mcs_rate_bps=float(msg.mcs_rate_bps))
    if isinstance(msg, tm.LinkPathsMsg):
        a = np.asarray(msg.a, complex).ravel()
        v = np.asarray(msg.vertices, float)
        depth = int(v.shape[1]) if v.ndim == 3 else 0
        return R(header=_header(msg.header), tx=msg.tx, rx=msg.rx,
                 frequency_hz=float(msg.frequency_hz), tx_position=_f64(msg.tx_position),
                 rx_position=_f64(msg.rx_position), a_real=_f64(a.real), a_imag=_f64(a.imag),
                 tau=_f64(msg.tau), doppler=_f64(msg.doppler), theta_t=_f64(msg.theta_t),
                 phi_t=_f64(msg.phi_t), theta_r=_f64(msg.theta_r), phi_r=_f64(msg.phi_r),
                 depth=depth, vertices=_f64(v),
                 interactions=np.ascontiguousarray(np.asarray(msg.interactions, np.int32).ravel()))
    if isinstance(msg, tm.Fingerprint):
        return R(header=_header(msg.header), robot=msg.robot, source=msg.source,
                 delay_resolution_s=float(msg.delay_resolution_s), mdp=_f64(msg.mdp),
                 estimate=_point(msg.estimate), confidence=float(msg.confidence))
    if isinstance(msg, tm.Csi):
        h = np.asarray(msg.h)
        shape = h.shape if h.ndim == 4 else (0, 0, 0, 0)
        return R(header=_header(msg.header), tx=msg.tx, rx=msg.rx, num_symbols=shape[0],
                 num_subcarriers=shape[1], num_rx=shape[2], num_tx=shape[3],
                 real=_f32(h.real), imag=_f32(h.imag))
    if isinstance(msg, tm.PathCommand):
        return R(header=_header(msg.header), kind=msg.kind, waypoints=_f64(msg.waypoints),
                 closed=bool(msg.closed), centre=_f64(msg.centre), radius=float(msg.radius),
                 size=float(msg.size), direction=msg.direction, speed=float(msg.speed))
    if isinstance(msg, tm.ClockPing):
        return R(origin=msg.origin, responder=msg.responder, seq=int(msg.seq),
                 t0_ns=int(msg.t0_ns), t1_ns=int(msg.t1_ns), t2_ns=int(msg.t2_ns))
    obj = sensing_cdr.to_ros(msg, R, _header)
    if obj is not None:
        return obj
    raise TypeError(f"no CDR conversion for {type(msg).__name__}")


# ------------------------------------------------------------------ from ROS

def from_ros(obj: Any, type_name: str):
    """The dataclass for a rosbags message object of ROS type ``type_name``."""
    t = type_name
    if t == "geometry_msgs/msg/Vector3":
        return m.Vector3(obj.x, obj.y, obj.z)
    if t == "geometry_msgs/msg/Pose":
        return _pose_from(obj)
    if t == "geometry_msgs/msg/PoseStamped":
        return m.PoseStamped(header=_header_from(obj.header), pose=_pose_from(obj.pose))
    if t == "geometry_msgs/msg/Twist":
        return _twist_from(obj)
    if t == "nav_msgs/msg/Odometry":
        return m.Odometry(header=_header_from(obj.header), child_frame_id=obj.child_frame_id,
                          pose=_pose_from(obj.pose.pose),
                          pose_covariance=np.asarray(obj.pose.covariance, float).reshape(6, 6),
                          twist=_twist_from(obj.twist.twist),
                          twist_covariance=np.asarray(obj.twist.covariance, float).reshape(6, 6))
    if t == "sensor_msgs/msg/Imu":
        return m.Imu(header=_header_from(obj.header), orientation=_arr4(obj.orientation),
                     orientation_covariance=np.asarray(obj.orientation_covariance, float).reshape(3, 3),
                     angular_velocity=_arr3(obj.angular_velocity),
                     angular_velocity_covariance=np.asarray(obj.angular_velocity_covariance,
                                                            float).reshape(3, 3),
                     linear_acceleration=_arr3(obj.linear_acceleration),
                     linear_acceleration_covariance=np.asarray(obj.linear_acceleration_covariance,
                                                               float).reshape(3, 3))
    if t == "sensor_msgs/msg/LaserScan":
        return m.LaserScan(header=_header_from(obj.header), angle_min=float(obj.angle_min),
                           angle_max=float(obj.angle_max),
                           angle_increment=float(obj.angle_increment),
                           time_increment=float(obj.time_increment),
                           scan_time=float(obj.scan_time), range_min=float(obj.range_min),
                           range_max=float(obj.range_max),
                           ranges=np.asarray(obj.ranges, np.float32).astype(float),
                           intensities=np.asarray(obj.intensities, np.float32).astype(float))
    if t == "sensor_msgs/msg/Image":
        dtype, ch = _IMAGE_LAYOUT.get(obj.encoding, (np.uint8, None))
        dt = np.dtype(dtype).newbyteorder(">" if obj.is_bigendian else "<")
        raw = np.asarray(obj.data, np.uint8)
        h, w = int(obj.height), int(obj.width)
        if ch is None:
            ch = (int(obj.step) // max(w, 1)) if h else 1
        rows = raw.reshape(h, int(obj.step)) if h else raw.reshape(0, 0)
        px = rows[:, :w * ch * dt.itemsize].copy().view(dt).astype(dtype)
        data = px.reshape(h, w, ch) if ch > 1 else px.reshape(h, w)
        return m.Image(header=_header_from(obj.header), height=h, width=w,
                       encoding=obj.encoding, data=data)
    if t == "sensor_msgs/msg/BatteryState":
        return m.BatteryState(header=_header_from(obj.header), voltage=float(obj.voltage))
    if t == "sensor_msgs/msg/JointState":
        return m.JointState(header=_header_from(obj.header), name=list(obj.name),
                            position=np.asarray(obj.position, float),
                            velocity=np.asarray(obj.velocity, float),
                            effort=np.asarray(obj.effort, float))
    if t == "geometry_msgs/msg/TransformStamped":
        return _transform_from(obj)
    if t == "tf2_msgs/msg/TFMessage":
        return m.TFMessage(transforms=[_transform_from(x) for x in obj.transforms])
    if t == "rosgraph_msgs/msg/Clock":
        return m.Clock(clock=stamp_from_ros(obj.clock))
    if t == m.DiagnosticArray.ROS_TYPE:
        return m.DiagnosticArray(header=_header_from(obj.header), status=[
            m.DiagnosticStatus(int(st.level), st.name, st.message, st.hardware_id,
                               [(kv.key, kv.value) for kv in st.values]) for st in obj.status])
    if t == tm.LinkMetrics.ROS_TYPE:
        return tm.LinkMetrics(header=_header_from(obj.header), tx=obj.tx, rx=obj.rx,
                              snr_db=float(obj.snr_db), rate_bps=float(obj.rate_bps),
                              num_paths=int(obj.num_paths), los=bool(obj.los),
                              total_gain_db=float(obj.total_gain_db),
                              mcs_rate_bps=float(obj.mcs_rate_bps))
    if t == tm.LinkPathsMsg.ROS_TYPE:
        L, D = len(obj.tau), int(obj.depth)
        return tm.LinkPathsMsg(header=_header_from(obj.header), tx=obj.tx, rx=obj.rx,
                               frequency_hz=float(obj.frequency_hz),
                               tx_position=np.asarray(obj.tx_position, float),
                               rx_position=np.asarray(obj.rx_position, float),
                               a=np.asarray(obj.a_real, float) + 1j * np.asarray(obj.a_imag, float),
                               tau=np.asarray(obj.tau, float),
                               doppler=np.asarray(obj.doppler, float),
                               theta_t=np.asarray(obj.theta_t, float),
                               phi_t=np.asarray(obj.phi_t, float),
                               theta_r=np.asarray(obj.theta_r, float),
                               phi_r=np.asarray(obj.phi_r, float),
                               vertices=np.asarray(obj.vertices, float).reshape(L, D, 3),
                               interactions=np.asarray(obj.interactions, np.int32).reshape(L, D))
    if t == tm.Fingerprint.ROS_TYPE:
        return tm.Fingerprint(header=_header_from(obj.header), robot=obj.robot, source=obj.source,
                              delay_resolution_s=float(obj.delay_resolution_s),
                              mdp=np.asarray(obj.mdp, float), estimate=_arr3(obj.estimate),
                              confidence=float(obj.confidence))
    if t == tm.Csi.ROS_TYPE:
        shape = (obj.num_symbols, obj.num_subcarriers, obj.num_rx, obj.num_tx)
        h = (np.asarray(obj.real, np.float32) + 1j * np.asarray(obj.imag, np.float32))
        return tm.Csi(header=_header_from(obj.header), tx=obj.tx, rx=obj.rx,
                      h=h.astype(np.complex64).reshape(shape))
    if t == tm.PathCommand.ROS_TYPE:
        return tm.PathCommand(header=_header_from(obj.header), kind=obj.kind,
                              waypoints=np.asarray(obj.waypoints, float).reshape(-1, 2),
                              closed=bool(obj.closed), centre=np.asarray(obj.centre, float),
                              radius=float(obj.radius), size=float(obj.size),
                              direction=obj.direction, speed=float(obj.speed))
    if t == tm.ClockPing.ROS_TYPE:
        return tm.ClockPing(origin=obj.origin, responder=obj.responder, seq=int(obj.seq),
                            t0_ns=int(obj.t0_ns), t1_ns=int(obj.t1_ns), t2_ns=int(obj.t2_ns))
    out = sensing_cdr.from_ros(obj, t, _header_from)
    if out is not None:
        return out
    raise TypeError(f"no conversion from ROS type {type_name!r}")


def encode(msg: Any) -> bytes:
    """CDR bytes (with the 4-byte encapsulation header) of a message dataclass."""
    return bytes(typestore().serialize_cdr(to_ros(msg), msg.ROS_TYPE))


def decode(data: bytes | memoryview, type_name: str):
    """The dataclass from CDR bytes of ROS type ``type_name``.

    Raises:
        ValueError: not a little/big-endian XCDR1 payload, or malformed.
    """
    data = bytes(data)
    if len(data) < 4 or data[0] != 0 or data[1] not in (0, 1):
        raise ValueError(f"{type_name}: not a CDR payload (header {data[:4].hex()})")
    return from_ros(typestore().deserialize_cdr(data, type_name), type_name)
