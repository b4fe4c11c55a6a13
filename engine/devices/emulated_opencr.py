"""An emulated TurtleBot3 OpenCR board: DYNAMIXEL Protocol 2.0 on a pty.

The server side of Protocol 2.0 (ROBOTIS e-Manual): packets
``FF FF FD 00 | ID | LEN (LE) | INST | params | CRC16 (LE)``, CRC-16 with
polynomial 0x8005 (init 0) over the *stuffed* packet, ``FF FF FD`` in the
body sent as ``FF FF FD FD``; status packets carry INST 0x55 and an error
byte. The board answers as the TurtleBot3 firmware's packet handler,
ROBOTIS' Dynamixel2Arduino ``Slave`` (``src/utility/slave.cpp``), does: only
PING, READ and WRITE addressed to its ID get a status; broadcast packets,
SYNC_READ, BULK_READ and any other instruction get none (counted in
``stats.ignored``), as do READ/WRITE with too few parameters; a packet with a
bad CRC never parses and gets no reply (``stats.bad_requests``).

Behind the control table sits a robot: ``step(v, w, dt)`` (m/s, rad/s, s)
returns ``(left_pos, right_pos, left_vel, right_vel, gyro[3], accel[3],
quat[4])`` with wheel angles in rad, wheel rates in rad/s, gyro in rad/s,
acceleration in m/s^2 (gravity included, as an IMU measures it) and the
orientation quaternion ``[x, y, z, w]``. :class:`DiffDriveRobot` is the
default; the twin's kinematics can be plugged in instead.

Firmware behaviour kept: cmd_vel stays in the table as written and is
limited to the model's speeds when it drives the wheels; it is zeroed when
neither the heartbeat nor cmd_vel changed for ``watchdog_s`` (0.5 s). Not
verified against the firmware: the data-access error (7) for writes to
read-only addresses.
"""

from __future__ import annotations

import logging
import math
import struct
from typing import Callable

import numpy as np

from ..bus.msgs import BatteryState, Imu, Odometry
from ..utils.geometry import wrap_angle, yaw_to_quaternion
from . import opencr as oc
from .emulated import EmulatedSerialDevice

log = logging.getLogger(__name__)

StepFn = Callable[[float, float, float], tuple]

INST_PING = 0x01
INST_READ = 0x02
INST_WRITE = 0x03
INST_STATUS = 0x55
INST_SYNC_READ = 0x82
INST_BULK_READ = 0x92
BROADCAST_ID = 0xFE

ERR_RESULT_FAIL = 0x01
ERR_INSTRUCTION = 0x02
ERR_CRC = 0x03
ERR_DATA_LENGTH = 0x05
ERR_ACCESS = 0x07

TABLE_SIZE = 256
#: (start, end) address ranges the host may write.
WRITABLE = ((oc.Addr.HEARTBEAT, 24), (50, 51), (59, 60), (oc.Addr.MOTOR_TORQUE_ENABLE, 182))
GRAVITY = 9.80665  #: m/s^2


def _crc_table() -> list[int]:
    table = []
    for i in range(256):
        crc = i << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x8005) if crc & 0x8000 else (crc << 1)
        table.append(crc & 0xFFFF)
    return table


_CRC_TABLE = _crc_table()


def crc16(data: bytes | bytearray) -> int:
    """CRC-16 of Protocol 2.0 (polynomial 0x8005, init 0, no reflection)."""
    crc = 0
    for b in data:
        crc = ((crc << 8) ^ _CRC_TABLE[((crc >> 8) ^ b) & 0xFF]) & 0xFFFF
    return crc


def stuff(prefix: bytes, body: bytes) -> bytes:
    """Insert 0xFD after every ``FF FF FD`` in ``body`` (``prefix`` = the bytes
    before it, whose tail counts for the pattern)."""
    out = bytearray()
    hist = bytearray(prefix[-2:])
    for b in body:
        out.append(b)
        if b == 0xFD and hist[-2:] == b"\xff\xff":
            out.append(0xFD)
        hist.append(b)
        del hist[:-2]
    return bytes(out)


def unstuff(prefix: bytes, body: bytes) -> bytes:
    """Remove the 0xFD inserted by :func:`stuff`."""
    out = bytearray()
    seq = bytearray(prefix[-2:]) + body
    off = len(seq) - len(body)
    i = 0
    while i < len(body):
        b = body[i]
        out.append(b)
        j = off + i
        if b == 0xFD and j >= 2 and seq[j - 2] == 0xFF and seq[j - 1] == 0xFF and i + 1 < len(body) and body[i + 1] == 0xFD:
            i += 2
            continue
        i += 1
    return bytes(out)


def build_packet(dxl_id: int, inst: int, params: bytes) -> bytes:
    """A complete (stuffed, CRC'd) Protocol 2.0 packet."""
    head = bytes((0xFF, 0xFF, 0xFD, 0x00, dxl_id))
    body = stuff(head + b"\0\0", bytes((inst,)) + params)
    length = len(body) + 2
    pkt = head + struct.pack("<H", length) + body
    return pkt + struct.pack("<H", crc16(pkt))


class DiffDriveRobot:
    """Default ``step(v, w, dt)``: an ideal differential drive on flat ground.

    Args:
        model: ``"burger"`` or ``"waffle"`` (wheel separation and speed limits).
    Attributes:
        x, y, yaw: pose in the odom frame (m, m, rad).
    """

    def __init__(self, model: str = "burger") -> None:
        self.wheel_radius = oc.WHEEL_RADIUS
        self.separation = oc.WHEEL_SEPARATION[model]
        self.max_linear = oc.MAX_LINEAR[model]
        self.max_angular = oc.MAX_ANGULAR[model]
        self.x = self.y = self.yaw = 0.0
        self.left_pos = self.right_pos = 0.0
        self._v = 0.0

    def __call__(self, v: float, w: float, dt: float) -> tuple:
        v = float(np.clip(v, -self.max_linear, self.max_linear))
        w = float(np.clip(w, -self.max_angular, self.max_angular))
        wl = (v - w * self.separation / 2) / self.wheel_radius
        wr = (v + w * self.separation / 2) / self.wheel_radius
        self.left_pos += wl * dt
        self.right_pos += wr * dt
        mid = self.yaw + w * dt / 2
        self.x += v * dt * math.cos(mid)
        self.y += v * dt * math.sin(mid)
        self.yaw = wrap_angle(self.yaw + w * dt)
        ax = (v - self._v) / dt if dt > 0 else 0.0
        self._v = v
        return (self.left_pos, self.right_pos, wl, wr, np.array([0.0, 0.0, w]),
                np.array([ax, v * w, GRAVITY]), yaw_to_quaternion(self.yaw))


class EmulatedOpenCR(EmulatedSerialDevice):
    """OpenCR on a pty.

    Args:
        step: robot model ``step(v, w, dt)`` (see module doc); default :class:`DiffDriveRobot`.
        model: ``"burger"`` or ``"waffle"`` (model_information 1/2, limits).
        dxl_id: 200.
        battery_voltage: V.
        motors_connected: False makes device_status -1 and the wheels stay still.
        watchdog_s: s without heartbeat/cmd_vel change before cmd_vel is zeroed.
        physics_dt: s, largest step handed to ``step``.
        link_path: stable port path (default: temp dir).
    """

    name = "ACM"

    def __init__(self, step: StepFn | None = None, *, model: str = "burger", dxl_id: int = oc.DEFAULT_ID,
                 battery_voltage: float = 12.1, motors_connected: bool = True, firmware_version: int = 1,
                 watchdog_s: float = 0.5, physics_dt: float = 0.01, link_path: str | None = None) -> None:
        super().__init__(link_path, tick_s=0.005)
        self.model = model
        self.robot = step if step is not None else DiffDriveRobot(model)
        self.dxl_id = dxl_id
        self.battery_voltage = battery_voltage
        self.motors_connected = motors_connected
        self.firmware_version = firmware_version
        self.watchdog_s = watchdog_s
        self.physics_dt = physics_dt
        self.watchdog_trips = 0
        self._faults: list[str] = []
        self.table = bytearray(TABLE_SIZE)
        self.on_plug()

    # -- table helpers ----------------------------------------------------------------
    def _put(self, addr: int, fmt: str, *values) -> None:
        struct.pack_into("<" + fmt, self.table, addr, *values)

    def _get(self, addr: int, fmt: str):
        return struct.unpack_from("<" + fmt, self.table, addr)

    @property
    def cmd_vel(self) -> tuple[float, float]:
        """(linear x m/s, angular z rad/s) currently commanded."""
        c = self._get(oc.Addr.CMD_VELOCITY, "6i")
        return c[0] / 100.0, c[5] / 100.0

    def on_plug(self) -> None:
        """Power-on: fresh table, robot state kept (the robot did not teleport)."""
        self.table[:] = bytes(TABLE_SIZE)
        self._put(oc.Addr.MODEL_NUMBER, "H", oc.MODEL_NUMBER)
        self._put(oc.Addr.MODEL_INFORMATION, "I", oc.MODEL_INFORMATION[self.model])
        self._put(oc.Addr.FIRMWARE_VERSION, "B", self.firmware_version)
        self._put(oc.Addr.ID, "B", self.dxl_id)
        self._put(oc.Addr.BAUD_RATE, "B", 3)  # 1 Mbps
        self._put(oc.Addr.DEVICE_STATUS, "b", 0 if self.motors_connected else -1)
        self._put(oc.Addr.MOTOR_TORQUE_ENABLE, "B", 1)
        self._put(oc.Addr.IMU_ORIENTATION, "4f", 1.0, 0.0, 0.0, 0.0)
        self._rx = bytearray()
        self._boot: float | None = None
        self._t_phys: float | None = None
        self._last_alive = 0.0
        self._wheel_offset: tuple[float, float] | None = None

    def inject_fault(self, kind: str) -> None:
        """Applies to the next status packet: ``garbage`` (random bytes before it),
        ``corrupt`` (CRC wrong), ``truncate`` (cut in half)."""
        if kind not in ("garbage", "corrupt", "truncate"):
            raise ValueError(f"emulated OpenCR: unknown fault kind {kind!r}")
        with self._lock:
            self._faults.append(kind)

    # -- truth ------------------------------------------------------------------------------
    def check_message(self, topic: str, msg: object) -> str:
        """What is wrong with a message a driver published from this board (``""``
        if nothing), for the conformance checker: every number finite, the
        battery voltage the one this board reports (V, 0.01 V steps), the IMU
        orientation a unit quaternion."""
        if isinstance(msg, BatteryState):
            if not abs(msg.voltage - self.battery_voltage) <= 0.006:
                return f"battery {msg.voltage!r} V, the board reports {self.battery_voltage:.2f} V"
            return ""
        if isinstance(msg, Imu):
            vals = np.concatenate([msg.orientation, msg.angular_velocity, msg.linear_acceleration])
            if not np.all(np.isfinite(vals)):
                return f"non-finite IMU values {vals}"
            if abs(float(np.linalg.norm(msg.orientation)) - 1.0) > 1e-3:
                return f"IMU orientation {msg.orientation} is not a unit quaternion"
            return ""
        if isinstance(msg, Odometry):
            vals = np.concatenate([msg.pose.position, msg.pose.orientation, msg.twist.linear, msg.twist.angular])
            return "" if np.all(np.isfinite(vals)) else f"non-finite odometry {vals}"
        return f"unexpected message {type(msg).__name__}"

    # -- physics ---------------------------------------------------------------------------
    def _advance(self, now: float) -> None:
        if self._boot is None:
            self._boot = now
            self._t_phys = now
            self._last_alive = now
        if now - self._last_alive > self.watchdog_s and any(self._get(oc.Addr.CMD_VELOCITY, "6i")):
            self._put(oc.Addr.CMD_VELOCITY, "6i", 0, 0, 0, 0, 0, 0)
            self.watchdog_trips += 1
            log.info("emulated OpenCR: no heartbeat/cmd_vel change for %.2f s, cmd_vel zeroed", now - self._last_alive)
        v, w = self.cmd_vel
        lim_v = getattr(self.robot, "max_linear", oc.MAX_LINEAR[self.model])
        lim_w = getattr(self.robot, "max_angular", oc.MAX_ANGULAR[self.model])
        v, w = max(-lim_v, min(lim_v, v)), max(-lim_w, min(lim_w, w))
        if not self.motors_connected or not self.table[oc.Addr.MOTOR_TORQUE_ENABLE]:
            v = w = 0.0
        state = None
        while self._t_phys < now - 1e-9:
            dt = min(self.physics_dt, now - self._t_phys)
            state = self.robot(v, w, dt)
            self._t_phys += dt
        ms = int((now - self._boot) * 1000)
        self._put(oc.Addr.MILLIS, "II", ms & 0xFFFFFFFF, int((now - self._boot) * 1e6) & 0xFFFFFFFF)
        self._put(oc.Addr.BATTERY_VOLTAGE, "ii", int(round(self.battery_voltage * 100)),
                  int(round(100 * 100 * min(1.0, max(0.0, (self.battery_voltage - 10.5) / (12.6 - 10.5))))))
        if state is None:
            return
        lp, rp_, lv, rv, gyro, acc, quat = state
        if self._wheel_offset is None:  # encoders count from power-on
            self._wheel_offset = (lp, rp_)
        lp -= self._wheel_offset[0]
        rp_ -= self._wheel_offset[1]
        self._put(oc.Addr.IMU_ANGULAR_VELOCITY, "3f", *map(float, gyro))
        self._put(oc.Addr.IMU_LINEAR_ACCELERATION, "3f", *map(float, acc))
        x, y, z, w_ = map(float, quat)
        self._put(oc.Addr.IMU_ORIENTATION, "4f", w_, x, y, z)
        self._put(oc.Addr.PRESENT_VELOCITY, "2i", oc.rad_s_to_velocity_units(lv), oc.rad_s_to_velocity_units(rv))

        def ticks(rad: float) -> int:
            t = int(round(rad / oc.TICK_TO_RAD))
            return (t + 2**31) % 2**32 - 2**31

        self._put(oc.Addr.PRESENT_POSITION, "2i", ticks(lp), ticks(rp_))

    def on_tick(self, now: float) -> None:
        self._advance(now)

    # -- protocol ------------------------------------------------------------------------------
    def on_bytes(self, data: bytes, now: float) -> None:
        buf = self._rx
        buf += data
        while True:
            i = buf.find(b"\xff\xff\xfd\x00")
            if i < 0:
                keep = min(len(buf), 3)
                del buf[: len(buf) - keep]
                return
            if i:
                del buf[:i]
            if len(buf) < 7:
                return
            length = struct.unpack_from("<H", buf, 5)[0]
            total = 7 + length
            if length < 3 or total > 1024:
                self.stats.bad_requests += 1
                del buf[:4]
                continue
            if len(buf) < total:
                return
            pkt = bytes(buf[:total])
            del buf[:total]
            dxl_id = pkt[4]
            if crc16(pkt[:-2]) != struct.unpack_from("<H", pkt, total - 2)[0]:
                self.stats.bad_requests += 1  # never parses in the slave library: no reply
                continue
            body = unstuff(pkt[:7], pkt[7:-2])
            self._advance(now)
            self._handle(dxl_id, body[0], body[1:], now)

    def _reply(self, error: int, params: bytes) -> None:
        pkt = build_packet(self.dxl_id, INST_STATUS, bytes((error,)) + params)
        while self._faults:
            fault = self._faults.pop(0)
            if fault == "garbage":
                pkt = bytes(self._rng.randrange(256) for _ in range(23)) + pkt
            elif fault == "corrupt":
                pkt = pkt[:-1] + bytes((pkt[-1] ^ 0xFF,))
            elif fault == "truncate":
                pkt = pkt[: len(pkt) // 2]
        self.send(pkt)

    def _read(self, addr: int, length: int) -> tuple[int, bytes]:
        if length < 1 or addr + length > TABLE_SIZE:
            return ERR_ACCESS, b""
        return 0, bytes(self.table[addr: addr + length])

    def _handle(self, dxl_id: int, inst: int, params: bytes, now: float) -> None:
        """As Dynamixel2Arduino's ``Slave::processInst``: PING, READ and WRITE to
        this ID only; broadcast and every other instruction get no status."""
        if dxl_id != self.dxl_id:
            if dxl_id == BROADCAST_ID:
                self.stats.ignored += 1
            return
        self.stats.requests += 1
        if inst == INST_PING:
            self._reply(0, struct.pack("<HB", oc.MODEL_NUMBER, self.firmware_version))
        elif inst == INST_READ:
            if len(params) != 4:  # WRONG_PACKET: no status
                self.stats.ignored += 1
                return
            addr, length = struct.unpack("<HH", params)
            self._reply(*self._read(addr, length))
        elif inst == INST_WRITE:
            if len(params) <= 2:  # WRONG_PACKET: no status
                self.stats.ignored += 1
                return
            addr = struct.unpack_from("<H", params)[0]
            self._reply(self._write(addr, params[2:], now), b"")
        else:
            self.stats.ignored += 1

    def _write(self, addr: int, data: bytes, now: float) -> int:
        end = addr + len(data)
        if not any(lo <= addr and end <= hi for lo, hi in WRITABLE):
            return ERR_ACCESS
        hb_before = self.table[oc.Addr.HEARTBEAT]
        self.table[addr:end] = data
        touches_cmd = addr < oc.Addr.CMD_VELOCITY + oc.CMD_VEL_LEN and end > oc.Addr.CMD_VELOCITY
        if touches_cmd:  # kept as written; limited when applied (_advance)
            self._last_alive = now
        if addr <= oc.Addr.HEARTBEAT < end and self.table[oc.Addr.HEARTBEAT] != hb_before:
            self._last_alive = now
        return 0


__all__ = ["EmulatedOpenCR", "DiffDriveRobot", "crc16", "build_packet", "stuff", "unstuff", "StepFn"]
