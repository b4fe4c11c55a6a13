"""TurtleBot3 OpenCR driver (DYNAMIXEL Protocol 2.0 through ``dynamixel_sdk``).

Does what the ROBOTIS ``turtlebot3_node`` does (``control_table.hpp``,
``turtlebot3.cpp``): ping ID 200 (model number 0x5000), read the control
table block at address 10, 172 bytes, every 50 ms (20 Hz), write the
heartbeat every 100 ms, write cmd_vel as one 24-byte WRITE at address 150
(int32 ``linear.x * 100``, four zeros, int32 ``angular.z * 100``, truncated
toward zero like the node's ``static_cast<int32_t>``). From each block it
publishes ``Odometry`` (integrated from wheel tick deltas, differential
drive), ``Imu`` and ``BatteryState``.

The framing (CRC-16/0x8005, byte stuffing, status packets) is the official
SDK's; only the port is opened with ``serial.serial_for_url`` so that
``pty://`` URLs work.
"""

from __future__ import annotations

import logging
import math
import struct
import threading
import time
from dataclasses import dataclass, field

import numpy as np
import serial
from dynamixel_sdk import COMM_RX_CORRUPT, COMM_RX_TIMEOUT, COMM_SUCCESS, PacketHandler, PortHandler

from ..bus.msgs import BatteryState, Header, Imu, Odometry, Pose, Twist
from ..contract import schema
from ..errors import DeviceError, DeviceTimeout
from ..utils.geometry import wrap_angle, yaw_to_quaternion
from . import ptyserial  # noqa: F401  (registers the pty:// URL handler)
from .base import DeviceDriver, Publish

log = logging.getLogger(__name__)

PROTOCOL_VERSION = 2.0
DEFAULT_ID = 200
DEFAULT_BAUDRATE = 1_000_000
MODEL_NUMBER = 0x5000
MODEL_INFORMATION = {"burger": 1, "waffle": 2}


class Addr:
    """Control-table addresses (bytes) of the OpenCR TurtleBot3 firmware."""

    MODEL_NUMBER = 0  # u16
    MODEL_INFORMATION = 2  # u32
    FIRMWARE_VERSION = 6  # u8
    ID = 7
    BAUD_RATE = 8
    MILLIS = 10  # u32 ms
    MICROS = 14  # u32 us
    DEVICE_STATUS = 18  # int8, -1 = motors not connected
    HEARTBEAT = 19  # u8
    BATTERY_VOLTAGE = 42  # int32, V * 100
    BATTERY_PERCENTAGE = 46  # int32, % * 100
    IMU_ANGULAR_VELOCITY = 60  # 3 x float32 rad/s (x, y, z)
    IMU_LINEAR_ACCELERATION = 72  # 3 x float32 m/s^2
    IMU_MAGNETIC = 84  # 3 x float32
    IMU_ORIENTATION = 96  # 4 x float32 (w, x, y, z)
    PRESENT_CURRENT = 120  # 2 x int32 (left, right)
    PRESENT_VELOCITY = 128  # 2 x int32, 0.229 rpm
    PRESENT_POSITION = 136  # 2 x int32, ticks
    MOTOR_TORQUE_ENABLE = 149  # u8
    CMD_VELOCITY = 150  # 6 x int32: linear x y z, angular x y z (m/s, rad/s) * 100
    PROFILE_ACCELERATION = 174  # 2 x int32


BLOCK_ADDR = 10
BLOCK_LEN = 172
CMD_VEL_LEN = 24
TICK_TO_RAD = 0.001533981  #: rad per encoder tick (2 pi / 4096)
RPM_PER_UNIT = 0.229  #: rev/min per present_velocity unit
# the robots' bodies and firmware limits are the shared schema's (addon/contract/schema.py)
WHEEL_RADIUS = schema.ROBOT_MODELS["burger"].wheel_radius  #: m (both models)
WHEEL_SEPARATION = {m: b.wheel_separation for m, b in schema.ROBOT_MODELS.items()}  #: m
MAX_LINEAR = {m: b.max_linear for m, b in schema.ROBOT_MODELS.items()}  #: m/s (firmware)
MAX_ANGULAR = {m: b.max_angular for m, b in schema.ROBOT_MODELS.items()}  #: rad/s (firmware)


def velocity_units_to_rad_s(units) -> np.ndarray:
    """present_velocity units (0.229 rpm) -> rad/s."""
    return np.asarray(units, dtype=float) * RPM_PER_UNIT * 2 * math.pi / 60.0


def rad_s_to_velocity_units(rad_s: float) -> int:
    """rad/s -> present_velocity units (0.229 rpm), rounded."""
    return int(round(rad_s * 60.0 / (2 * math.pi) / RPM_PER_UNIT))


def encode_cmd_vel(linear_x: float, angular_z: float) -> bytes:
    """24 bytes for address 150, as ``turtlebot3_node`` builds them."""
    return struct.pack("<6i", int(linear_x * 100), 0, 0, 0, 0, int(angular_z * 100))


@dataclass
class OpenCRState:
    """One decoded control-table block (address 10..181)."""

    millis: int  #: ms since boot
    device_status: int  #: 0 ok, -1 motors not connected
    heartbeat: int
    battery_voltage: float  #: V
    battery_percentage: float  #: %
    angular_velocity: np.ndarray  #: [3] rad/s
    linear_acceleration: np.ndarray  #: [3] m/s^2
    magnetic_field: np.ndarray  #: [3] (firmware units)
    orientation: np.ndarray  #: [4] quaternion x, y, z, w
    current: np.ndarray  #: [2] left, right (firmware units)
    wheel_velocity: np.ndarray  #: [2] left, right rad/s
    wheel_ticks: np.ndarray  #: [2] left, right int ticks
    torque_enabled: bool
    cmd_vel: tuple[float, float]  #: (linear x m/s, angular z rad/s) as stored

    @classmethod
    def from_block(cls, block: bytes) -> "OpenCRState":
        """Decode the 172-byte block read at address 10."""
        if len(block) != BLOCK_LEN:
            raise DeviceError(f"control-table block is {len(block)} bytes, expected {BLOCK_LEN}")

        def at(addr: int) -> int:
            return addr - BLOCK_ADDR

        millis = struct.unpack_from("<I", block, at(Addr.MILLIS))[0]
        status = struct.unpack_from("<b", block, at(Addr.DEVICE_STATUS))[0]
        volt, pct = struct.unpack_from("<ii", block, at(Addr.BATTERY_VOLTAGE))
        gyro = np.array(struct.unpack_from("<3f", block, at(Addr.IMU_ANGULAR_VELOCITY)))
        acc = np.array(struct.unpack_from("<3f", block, at(Addr.IMU_LINEAR_ACCELERATION)))
        mag = np.array(struct.unpack_from("<3f", block, at(Addr.IMU_MAGNETIC)))
        w, x, y, z = struct.unpack_from("<4f", block, at(Addr.IMU_ORIENTATION))
        cur = np.array(struct.unpack_from("<2i", block, at(Addr.PRESENT_CURRENT)), dtype=float)
        vel = velocity_units_to_rad_s(struct.unpack_from("<2i", block, at(Addr.PRESENT_VELOCITY)))
        ticks = np.array(struct.unpack_from("<2i", block, at(Addr.PRESENT_POSITION)), dtype=np.int64)
        cmd = struct.unpack_from("<6i", block, at(Addr.CMD_VELOCITY))
        return cls(millis, status, block[at(Addr.HEARTBEAT)], volt / 100.0, pct / 100.0, gyro, acc, mag,
                   np.array([x, y, z, w]), cur, vel, ticks, bool(block[at(Addr.MOTOR_TORQUE_ENABLE)]),
                   (cmd[0] / 100.0, cmd[5] / 100.0))


@dataclass
class DiffDriveOdometry:
    """Pose from wheel tick deltas (differential drive, midpoint integration).

    Args:
        wheel_radius: m.
        wheel_separation: m.
    """

    wheel_radius: float = WHEEL_RADIUS
    wheel_separation: float = WHEEL_SEPARATION["burger"]
    x: float = 0.0  #: m
    y: float = 0.0  #: m
    yaw: float = 0.0  #: rad
    _last_ticks: np.ndarray | None = field(default=None, repr=False)

    def reset(self) -> None:
        self.x = self.y = self.yaw = 0.0
        self._last_ticks = None

    def update(self, ticks: np.ndarray) -> tuple[float, float]:
        """Integrate new absolute ticks ``[left, right]``; returns (ds m, dyaw rad)."""
        ticks = np.asarray(ticks, dtype=np.int64)
        if self._last_ticks is None:
            self._last_ticks = ticks
            return 0.0, 0.0
        delta = ticks - self._last_ticks
        delta = (delta + 2**31) % 2**32 - 2**31  # int32 wrap-around
        self._last_ticks = ticks
        d_l, d_r = delta * TICK_TO_RAD * self.wheel_radius
        ds = (d_l + d_r) / 2.0
        dyaw = (d_r - d_l) / self.wheel_separation
        self.x += ds * math.cos(self.yaw + dyaw / 2.0)
        self.y += ds * math.sin(self.yaw + dyaw / 2.0)
        self.yaw = wrap_angle(self.yaw + dyaw)
        return ds, dyaw


#: Longest a single read of the port blocks, s. dynamixel_sdk waits for an answer by
#: calling ``readPort`` in a loop until its packet timeout (~34 ms); with the SDK's own
#: read timeout of 0 that loop spins and holds the GIL, starving every other thread of
#: the process (a streaming camera, an emulated board) and so delaying the very answer
#: it waits for. A read that blocks in ``select`` returns as soon as the bytes asked
#: for are in, so this bounds the loop's turns without delaying any answer.
READ_POLL_S = 0.01


class _UrlPortHandler(PortHandler):
    """The SDK's PortHandler, opening its port with ``serial.serial_for_url`` and a
    blocking read of at most :data:`READ_POLL_S` (the SDK's own port spins)."""

    def setupPort(self, cflag_baud):  # noqa: N802 (SDK name)
        if self.is_open:
            self.closePort()
        self.ser = serial.serial_for_url(self.port_name, baudrate=self.baudrate, bytesize=serial.EIGHTBITS,
                                         timeout=READ_POLL_S)
        self.is_open = True
        self.ser.reset_input_buffer()
        self.tx_time_per_byte = (1000.0 / self.baudrate) * 10.0
        return True


class OpenCR(DeviceDriver):
    """OpenCR driver: synchronous SDK calls plus a 20 Hz read loop publishing odom/IMU/battery.

    Args:
        url: port path (``/dev/ttyACM0``) or pyserial URL.
        publish: ``publish(topic, msg)``.
        model: ``"burger"`` or ``"waffle"`` (wheel separation).
        baudrate: 1 000 000.
        dxl_id: 200.
        read_rate_hz: control-table reads per second (the ROS node: 20).
        heartbeat_period: s between heartbeat writes (the ROS node: 0.1).
        topics: override of ``{"odom": ..., "imu": ..., "battery_state": ...}`` names.
    """

    MESSAGE_TYPES = {"odom": Odometry, "imu": Imu, "battery_state": BatteryState}

    def __init__(self, url: str, publish: Publish | None = None, *, model: str = "burger",
                 baudrate: int = DEFAULT_BAUDRATE, dxl_id: int = DEFAULT_ID, read_rate_hz: float = 20.0,
                 heartbeat_period: float = 0.1, odom_frame: str = "odom", base_frame: str = "base_footprint",
                 imu_frame: str = "imu_link", topics: dict[str, str] | None = None, stale_timeout: float = 1.0,
                 backoff_initial: float = 0.05, backoff_max: float = 2.0, connect_warn_s: float = 3.0,
                 diagnostics_topic: str | None = "diagnostics", diagnostics_period_s: float = 1.0) -> None:
        super().__init__(url, publish, stale_timeout=stale_timeout, backoff_initial=backoff_initial,
                         backoff_max=backoff_max, connect_warn_s=connect_warn_s,
                         diagnostics_topic=diagnostics_topic, diagnostics_period_s=diagnostics_period_s)
        if model not in WHEEL_SEPARATION:
            raise ValueError(f"model must be one of {sorted(WHEEL_SEPARATION)}, got {model!r}")
        self.model = model
        self.baudrate = baudrate
        self.dxl_id = dxl_id
        self.read_rate_hz = read_rate_hz
        self.heartbeat_period = heartbeat_period
        self.odom_frame, self.base_frame, self.imu_frame = odom_frame, base_frame, imu_frame
        names = {"odom": "odom", "imu": "imu", "battery_state": "battery_state"}
        names.update(topics or {})
        self.topics = names
        self.MESSAGE_TYPES = {names[k]: t for k, t in type(self).MESSAGE_TYPES.items()}
        self.odometry = DiffDriveOdometry(WHEEL_RADIUS, WHEEL_SEPARATION[model])
        self.state: OpenCRState | None = None
        self.model_number: int | None = None
        self._port: PortHandler | None = None
        self._packet = PacketHandler(PROTOCOL_VERSION)
        self._cmd_lock = threading.Lock()
        self._pending_cmd: tuple[float, float] | None = None
        self._wake = threading.Event()
        self._heartbeat = 0
        self._next_read = 0.0
        self._next_hb = 0.0

    # -- synchronous API -------------------------------------------------------------
    def open(self) -> None:
        """Open the port at ``baudrate``."""
        self.close()
        port = _UrlPortHandler(self.url)
        port.baudrate = self.baudrate
        if not port.openPort():
            raise DeviceError(f"{self.url}: cannot open at {self.baudrate} baud")
        self._port = port

    def close(self) -> None:
        if self._port is not None:
            try:
                self._port.closePort()
            except Exception:  # noqa: BLE001
                pass
            self._port = None

    @property
    def port(self) -> PortHandler:
        if self._port is None:
            raise DeviceError(f"{self.url}: port is not open")
        return self._port

    def _check(self, what: str, result: int, error: int) -> None:
        if result == COMM_SUCCESS and not error:
            return
        if result == COMM_RX_CORRUPT:
            self.stats.frames_bad += 1
        elif result == COMM_RX_TIMEOUT:
            self.stats.timeouts += 1
        if result != COMM_SUCCESS:
            raise (DeviceTimeout if result == COMM_RX_TIMEOUT else DeviceError)(
                f"{self.url}: {what} to ID {self.dxl_id}: {self._packet.getTxRxResult(result)}")
        raise DeviceError(f"{self.url}: {what} to ID {self.dxl_id}: {self._packet.getRxPacketError(error)}")

    def ping(self) -> int:
        """PING; returns the model number (0x5000 for an OpenCR)."""
        model, result, error = self._packet.ping(self.port, self.dxl_id)
        self._check("PING", result, error)
        self.stats.frames_ok += 1
        self.model_number = model
        return model

    def read_block(self) -> OpenCRState:
        """READ address 10, 172 bytes -> :class:`OpenCRState`."""
        data, result, error = self._packet.readTxRx(self.port, self.dxl_id, BLOCK_ADDR, BLOCK_LEN)
        self._check(f"READ {BLOCK_ADDR}+{BLOCK_LEN}", result, error)
        self.stats.frames_ok += 1
        self.state = OpenCRState.from_block(bytes(data))
        return self.state

    def write_cmd_vel(self, linear_x: float, angular_z: float) -> None:
        """WRITE 24 bytes at 150 (m/s and rad/s, x100 int32)."""
        result, error = self._packet.writeTxRx(self.port, self.dxl_id, Addr.CMD_VELOCITY, CMD_VEL_LEN,
                                               list(encode_cmd_vel(linear_x, angular_z)))
        self._check("WRITE cmd_velocity", result, error)

    def write_heartbeat(self) -> None:
        """WRITE the next heartbeat count (u8) at 19."""
        self._heartbeat = (self._heartbeat + 1) & 0xFF
        result, error = self._packet.write1ByteTxRx(self.port, self.dxl_id, Addr.HEARTBEAT, self._heartbeat)
        self._check("WRITE heartbeat", result, error)

    # -- thread-safe command input -------------------------------------------------------
    def set_cmd_vel(self, linear_x: float, angular_z: float) -> None:
        """Queue a velocity command (m/s, rad/s); the read loop writes it next."""
        with self._cmd_lock:
            self._pending_cmd = (float(linear_x), float(angular_z))
        self._wake.set()

    def on_cmd_vel(self, msg: Twist) -> None:
        """Bus callback for ``geometry_msgs/Twist``."""
        self.set_cmd_vel(float(msg.linear[0]), float(msg.angular[2]))

    # -- messages -------------------------------------------------------------------------
    def messages(self, st: OpenCRState, stamp: float) -> dict[str, object]:
        """Build (and integrate odometry for) the messages of one block."""
        self.odometry.update(st.wheel_ticks)
        r, sep = self.odometry.wheel_radius, self.odometry.wheel_separation
        wl, wr = st.wheel_velocity
        odom = Odometry(
            header=Header(stamp=stamp, frame_id=self.odom_frame), child_frame_id=self.base_frame,
            pose=Pose(position=np.array([self.odometry.x, self.odometry.y, 0.0]),
                      orientation=yaw_to_quaternion(self.odometry.yaw)),
            twist=Twist(linear=np.array([r * (wl + wr) / 2.0, 0.0, 0.0]),
                        angular=np.array([0.0, 0.0, r * (wr - wl) / sep])),
        )
        imu = Imu(header=Header(stamp=stamp, frame_id=self.imu_frame), orientation=st.orientation.copy(),
                  angular_velocity=st.angular_velocity.copy(), linear_acceleration=st.linear_acceleration.copy())
        battery = BatteryState(header=Header(stamp=stamp, frame_id=""), voltage=st.battery_voltage)
        return {self.topics["odom"]: odom, self.topics["imu"]: imu, self.topics["battery_state"]: battery}

    # -- read loop ---------------------------------------------------------------------------
    def _connect(self) -> None:
        self.open()
        model = self.ping()
        if model != MODEL_NUMBER:
            raise DeviceError(f"{self.url}: ID {self.dxl_id} has model number 0x{model:04X}, "
                              f"expected 0x{MODEL_NUMBER:04X} (OpenCR)")
        st = self.read_block()
        if st.device_status == -1:
            log.warning("%s: OpenCR reports device_status -1 (motors not connected)", self.url)
        self.odometry._last_ticks = None  # the board may have rebooted: re-reference ticks
        now = time.monotonic()
        self._next_read = now
        self._next_hb = now

    def _disconnect(self) -> None:
        self.close()

    def _poll(self) -> None:
        with self._cmd_lock:
            cmd, self._pending_cmd = self._pending_cmd, None
        try:
            if cmd is not None:
                self.write_cmd_vel(*cmd)
            now = time.monotonic()
            if now >= self._next_hb:
                self.write_heartbeat()
                self._next_hb = max(self._next_hb + self.heartbeat_period, now)
            now = time.monotonic()
            if now >= self._next_read:
                st = self.read_block()
                self._mark_valid()
                for topic, msg in self.messages(st, time.time()).items():
                    self._publish(topic, msg)
                self._next_read = max(self._next_read + 1.0 / self.read_rate_hz, now)
        except DeviceError as exc:
            # one bad or missing answer is not a lost device: the stale timer decides that
            self.stats.last_error = str(exc)
            log.debug("%s", exc)
            if cmd is not None:
                with self._cmd_lock:
                    if self._pending_cmd is None:
                        self._pending_cmd = cmd
        wait = min(self._next_read, self._next_hb) - time.monotonic()
        if wait > 0:
            self._wake.wait(wait)
            self._wake.clear()
