"""An emulated Slamtec RPLIDAR serving the real serial protocol on a pty.

Ranges come from ``scan_source(angles) -> ranges``: ``angles`` ``[M]`` in
rad, ROS convention (counter-clockwise in the laser frame, see
:func:`isac_twin.devices.rplidar.device_to_ros_angle`), ``ranges`` ``[M]`` in m
(``inf``/``nan``/``<= 0`` = no return). The twin's ray-cast LiDAR plugs in
here (:func:`laser_scan_source` adapts anything returning a ``LaserScan``);
the default is a 4 m x 3 m room centred on the sensor.

What it implements: GET_INFO, GET_HEALTH, GET_SAMPLERATE, GET_LIDAR_CONF
(scan mode count, typical mode, and per mode the name, us per sample, max
distance and answer type, as Slamtec's SDK and ``rplidar_ros`` ask on
firmware >= 1.24), SCAN/FORCE_SCAN (5-byte nodes), EXPRESS_SCAN (legacy
84-byte capsules), STOP, RESET (with the boot banner a real unit prints),
SET_MOTOR_PWM (A2/A3) and DTR motor control (A1, through ``pty://`` URLs).
The default sample times are an A1's on firmware 1.29: 508 us standard,
254 us express. Unlike a real A1 (5 scan modes: also Boost, Sensitivity and
Stability in ultra capsules, typical Sensitivity) it reports only the two
modes it can stream, typical Express; a configuration type it does not
know is answered with the type and no payload (unverified on hardware). Any other request, with or without
payload, is parsed (checksum and all) and ignored, as the firmware does.
A new request while scanning stops the stream first (real units need STOP;
clients send it anyway).

Timing: the head turns at ``scan_rate_hz``; nodes are emitted as the
sample clock produces them (``sample_rate_hz`` standard,
``express_sample_rate_hz`` express), paced in real time times ``time_scale``.
"""

from __future__ import annotations

import logging
import math
import struct
from typing import Callable

import numpy as np

from ..bus.msgs import LaserScan
from . import rplidar as rp
from .emulated import EmulatedSerialDevice

log = logging.getLogger(__name__)

ScanSource = Callable[[np.ndarray], np.ndarray]


def room_scan_source(width: float = 4.0, depth: float = 3.0) -> ScanSource:
    """Ranges (m) from the centre of a ``width`` (x) by ``depth`` (y) m rectangle."""

    def source(angles: np.ndarray) -> np.ndarray:
        c, s = np.cos(angles), np.sin(angles)
        with np.errstate(divide="ignore"):
            tx = np.where(np.abs(c) > 1e-12, (width / 2) / np.abs(c), np.inf)
            ty = np.where(np.abs(s) > 1e-12, (depth / 2) / np.abs(s), np.inf)
        return np.minimum(tx, ty)

    return source


def laser_scan_source(get_scan: Callable[[], LaserScan]) -> ScanSource:
    """Adapt a simulated LiDAR to a scan source: each query takes the latest
    ``LaserScan`` from ``get_scan()`` (e.g. the twin's ray-cast ``Lidar2D``) and
    returns, for every angle, the range of the nearest ray (m, ``inf`` = none)."""

    def source(angles: np.ndarray) -> np.ndarray:
        scan = get_scan()
        n = len(scan.ranges)
        if n == 0 or scan.angle_increment == 0:
            return np.full(np.shape(angles), np.inf)
        k = np.rint((np.asarray(angles) - scan.angle_min) / scan.angle_increment).astype(int)
        full_turn = abs(n * scan.angle_increment - 2 * np.pi) < 1.5 * abs(scan.angle_increment)
        if full_turn:
            k %= n
        inside = (k >= 0) & (k < n)
        out = np.full(np.shape(angles), np.inf)
        out[inside] = np.asarray(scan.ranges, dtype=float)[k[inside]]
        return out

    return source


class EmulatedRPLidar(EmulatedSerialDevice):
    """RPLIDAR on a pty.

    Args:
        scan_source: ``f(angles [M] rad CCW) -> ranges [M] m``.
        model: GET_INFO model byte (0x18 = A1M8, 0x28 = A2M8).
        firmware: (major, minor).
        hardware: hardware revision byte.
        serial_number: 16 bytes.
        health: (status, error_code) returned by GET_HEALTH.
        scan_rate_hz: head rotation (A1 nominal 5.5 Hz).
        sample_rate_hz: standard-scan samples/s (A1: 1e6 / 508 us).
        express_sample_rate_hz: express-scan samples/s (A1: 1e6 / 254 us).
        max_distance_m: per-mode max distance reported by GET_LIDAR_CONF (A1 12 m).
        motor_control: ``"dtr"`` (A1: DTR low spins) or ``"pwm"`` (SET_MOTOR_PWM).
        require_motor: if True, scans carry no samples while the motor is off.
        angle_offset: rad, see :func:`isac_twin.devices.rplidar.device_to_ros_angle`.
        time_scale: >1 runs the sample clock faster than real time (benchmarks).
        link_path: stable port path (default: temp dir).
    """

    name = "USB"

    def __init__(self, scan_source: ScanSource | None = None, *, model: int = 0x18,
                 firmware: tuple[int, int] = (1, 29), hardware: int = 7,
                 serial_number: bytes = bytes.fromhex("8ba7ed1ee6e19dd3a4e39ef331554b33"),
                 health: tuple[int, int] = (rp.STATUS_OK, 0), scan_rate_hz: float = 5.5,
                 sample_rate_hz: float = 1e6 / 508, express_sample_rate_hz: float = 1e6 / 254,
                 max_distance_m: float = 12.0,
                 motor_control: str = "dtr", require_motor: bool = False, angle_offset: float = 0.0,
                 time_scale: float = 1.0, link_path: str | None = None) -> None:
        super().__init__(link_path)
        if motor_control not in ("dtr", "pwm"):
            raise ValueError(f"motor_control must be 'dtr' or 'pwm', got {motor_control!r}")
        self.scan_source = scan_source or room_scan_source()
        self.info = rp.DeviceInfo(model, firmware, hardware, serial_number)
        self.health = rp.DeviceHealth(*health)
        self.scan_rate_hz = scan_rate_hz
        self.sample_rate_hz = sample_rate_hz
        self.express_sample_rate_hz = express_sample_rate_hz
        self.max_distance_m = max_distance_m
        self.motor_control = motor_control
        self.require_motor = require_motor
        self.angle_offset = angle_offset
        self.time_scale = time_scale
        self.motor_pwm = 0
        self.dtr = True
        self.ignored_commands: list[int] = []
        self.nodes_sent = 0
        self.scans_started = 0
        self._pending_faults: list[str] = []
        self.on_plug()

    # -- state -------------------------------------------------------------------
    @property
    def motor_on(self) -> bool:
        return (not self.dtr) if self.motor_control == "dtr" else self.motor_pwm > 0

    def on_plug(self) -> None:
        self._rxbuf = bytearray()
        self._mode: str | None = None  # None, "standard", "express"
        self._t0 = 0.0
        self._sample_idx = 0
        self._first_capsule = True
        self._banner_at: float | None = None
        self.dtr = True
        self.motor_pwm = 0

    def on_modem(self, line: str, state: bool) -> None:
        if line == "DTR":
            self.dtr = state

    def inject_fault(self, kind: str) -> None:
        """``garbage`` (random bytes now), ``corrupt`` (next node/capsule fails its
        check), ``truncate`` (next node/capsule loses bytes)."""
        if kind in ("corrupt", "truncate"):
            with self._lock:
                self._pending_faults.append(kind)
        else:
            super().inject_fault(kind)

    # -- host requests -------------------------------------------------------------
    def on_bytes(self, data: bytes, now: float) -> None:
        buf = self._rxbuf
        buf += data
        while buf:
            if buf[0] != rp.SYNC_BYTE:
                del buf[0]
                self.stats.bad_requests += 1
                continue
            if len(buf) < 2:
                return
            cmd = buf[1]
            if cmd & rp.CMDFLAG_HAS_PAYLOAD:
                if len(buf) < 3 or len(buf) < 4 + buf[2]:
                    return
                size = buf[2]
                frame = bytes(buf[: 4 + size])
                chk = 0
                for b in frame[:-1]:
                    chk ^= b
                del buf[: 4 + size]
                if chk != frame[-1]:
                    log.debug("emulated RPLIDAR: request 0x%02X checksum 0x%02X != 0x%02X, ignored",
                              cmd, frame[-1], chk)
                    self.stats.bad_requests += 1
                    continue
                self._handle(cmd, frame[3:-1], now)
            else:
                del buf[:2]
                self._handle(cmd, b"", now)

    def _handle(self, cmd: int, payload: bytes, now: float) -> None:
        self.stats.requests += 1
        if cmd != rp.CMD_SET_MOTOR_PWM and self._mode is not None:
            self._mode = None  # any other request ends a running scan
            self._out.clear()  # ... and what was not yet on the wire
        if cmd == rp.CMD_STOP:
            return
        if cmd == rp.CMD_RESET:
            self._banner_at = now + 0.01
            return
        if cmd == rp.CMD_GET_INFO:
            self.send(rp.build_descriptor(20, rp.SEND_MODE_SINGLE, rp.ANS_TYPE_DEVINFO) + self.info.to_bytes())
        elif cmd == rp.CMD_GET_HEALTH:
            self.send(rp.build_descriptor(3, rp.SEND_MODE_SINGLE, rp.ANS_TYPE_DEVHEALTH) + self.health.to_bytes())
        elif cmd == rp.CMD_GET_SAMPLERATE:
            body = struct.pack("<HH", round(1e6 / self.sample_rate_hz), round(1e6 / self.express_sample_rate_hz))
            self.send(rp.build_descriptor(4, rp.SEND_MODE_SINGLE, rp.ANS_TYPE_SAMPLERATE) + body)
        elif cmd in (rp.CMD_SCAN, rp.CMD_FORCE_SCAN):
            self.send(rp.build_descriptor(rp.NODE_SIZE, rp.SEND_MODE_MULTIPLE, rp.ANS_TYPE_MEASUREMENT))
            self._begin("standard", now)
        elif cmd == rp.CMD_EXPRESS_SCAN:
            self.send(rp.build_descriptor(rp.CAPSULE_SIZE, rp.SEND_MODE_MULTIPLE, rp.ANS_TYPE_MEASUREMENT_CAPSULED))
            self._begin("express", now)
        elif cmd == rp.CMD_GET_LIDAR_CONF and len(payload) >= 4:
            body = self._lidar_conf(payload)
            self.send(rp.build_descriptor(len(body), rp.SEND_MODE_SINGLE, rp.ANS_TYPE_GET_LIDAR_CONF) + body)
        elif cmd == rp.CMD_SET_MOTOR_PWM and self.motor_control == "pwm" and len(payload) == 2:
            self.motor_pwm = min(struct.unpack("<H", payload)[0], rp.MAX_MOTOR_PWM)
        else:
            self.ignored_commands.append(cmd)

    def scan_modes(self) -> list[tuple[str, float, float, int]]:
        """(name, us per sample, max distance m, answer type) of each scan mode."""
        return [("Standard", 1e6 / self.sample_rate_hz, self.max_distance_m, rp.ANS_TYPE_MEASUREMENT),
                ("Express", 1e6 / self.express_sample_rate_hz, self.max_distance_m, rp.ANS_TYPE_MEASUREMENT_CAPSULED)]

    def _lidar_conf(self, payload: bytes) -> bytes:
        """GET_LIDAR_CONF answer: u32 type + value (sl_lidar_cmd.h; q8 = x 256)."""
        conf = struct.unpack_from("<I", payload)[0]
        modes = self.scan_modes()
        head = struct.pack("<I", conf)
        if conf == rp.CONF_SCAN_MODE_COUNT:
            return head + struct.pack("<H", len(modes))
        if conf == rp.CONF_SCAN_MODE_TYPICAL:
            return head + struct.pack("<H", 1)
        mode = struct.unpack_from("<H", payload, 4)[0] if len(payload) >= 6 else 0
        if mode >= len(modes):
            return head
        name, us, dist, ans = modes[mode]
        if conf == rp.CONF_SCAN_MODE_US_PER_SAMPLE:
            return head + struct.pack("<I", round(us * 256))
        if conf == rp.CONF_SCAN_MODE_MAX_DISTANCE:
            return head + struct.pack("<I", round(dist * 256))
        if conf == rp.CONF_SCAN_MODE_ANS_TYPE:
            return head + bytes((ans,))
        if conf == rp.CONF_SCAN_MODE_NAME:
            return head + name.encode("ascii") + b"\0"
        return head

    def _begin(self, mode: str, now: float) -> None:
        self._mode = mode
        self._t0 = now
        self._sample_idx = 0
        self._first_capsule = True
        self.scans_started += 1

    # -- streaming -------------------------------------------------------------------
    def on_tick(self, now: float) -> None:
        if self._banner_at is not None and now >= self._banner_at:
            self._banner_at = None
            fw = self.info.firmware
            self.send(f"RP LIDAR System.\r\nFirmware Ver {fw[0]}.{fw[1]:02d} - rc9, HW Ver {self.info.hardware}\r\n"
                      f"Model: {self.info.model:02X}\r\n".encode())
        if self._mode is None:
            return
        rate = self.sample_rate_hz if self._mode == "standard" else self.express_sample_rate_hz
        due = int((now - self._t0) * self.time_scale * rate)
        if self._mode == "standard":
            n = min(due - self._sample_idx, 4096)
            if n > 0:
                self._emit_nodes(n, rate)
        else:
            while due - self._sample_idx >= rp.NODES_PER_CAPSULE:
                self._emit_capsule(rate)

    def _samples(self, first: int, n: int, rate: float) -> tuple[np.ndarray, np.ndarray]:
        """Device angles (deg, clockwise) and distances (mm) of samples ``first..first+n``."""
        k = np.arange(first, first + n)
        dev_angle = np.mod(k * (360.0 * self.scan_rate_hz / rate), 360.0)
        if self.require_motor and not self.motor_on:
            return dev_angle, np.zeros(n)
        rng = np.asarray(self.scan_source(rp.device_to_ros_angle(dev_angle, self.angle_offset)), dtype=float)
        rng = np.where(np.isfinite(rng) & (rng > 0), rng, 0.0)
        return dev_angle, np.clip(rng * 1000.0, 0.0, 16383.0)

    def _take_fault(self) -> str | None:
        return self._pending_faults.pop(0) if self._pending_faults else None

    def _emit_nodes(self, n: int, rate: float) -> None:
        ang, dist = self._samples(self._sample_idx, n, rate)
        step = 360.0 * self.scan_rate_hz / rate
        out = bytearray()
        for a, d in zip(ang, dist):
            start = a < step - 1e-9  # the first sample of each turn
            node = rp.encode_node(a, d, 47 if d > 0 else 0, start)
            fault = self._take_fault()
            if fault == "corrupt":
                node = bytes((node[0] | 0x03,)) + node[1:]  # S and !S both set
            elif fault == "truncate":
                node = node[:2]
            out += node
        self._sample_idx += n
        self.nodes_sent += n
        self.send(bytes(out))

    def _emit_capsule(self, rate: float) -> None:
        ang, dist = self._samples(self._sample_idx, rp.NODES_PER_CAPSULE, rate)
        cap = rp.encode_capsule(float(ang[0]), dist, new_scan=self._first_capsule)
        self._first_capsule = False
        fault = self._take_fault()
        if fault == "corrupt":
            cap = cap[:10] + bytes((cap[10] ^ 0x5A,)) + cap[11:]
        elif fault == "truncate":
            cap = cap[:50]
        self._sample_idx += rp.NODES_PER_CAPSULE
        self.nodes_sent += rp.NODES_PER_CAPSULE
        self.send(cap)

    # -- truth ------------------------------------------------------------------------
    def check_message(self, topic: str, msg: object, angle_tol_deg: float = 0.2,
                      range_tol_m: float = 0.002) -> str:
        """What is wrong with a ``LaserScan`` a driver published from this device
        (``""`` if nothing), judged against ``scan_source`` (for the conformance
        checker; the source must not have changed since the scan was taken).

        Each finite beam at ``angle_min + i * angle_increment`` must lie between
        the smallest and largest true range within half a beam step plus
        ``angle_tol_deg`` of its angle (plus ``range_tol_m``); a ``+inf`` beam
        needs a "no return" there; NaN (missing, REP-117) is always allowed.
        Angles in the driver's frame are assumed to use this emulator's
        ``angle_offset``.
        """
        if not isinstance(msg, LaserScan):
            return f"expected a LaserScan, got {type(msg).__name__}"
        r = np.asarray(msg.ranges, dtype=float)
        if r.size == 0:
            return "empty scan"
        if not (math.isfinite(msg.angle_min) and math.isfinite(msg.angle_increment) and msg.angle_increment > 0):
            return f"angle_min {msg.angle_min!r}, angle_increment {msg.angle_increment!r}"
        if r.size * msg.angle_increment > 2 * math.pi + 1.5 * msg.angle_increment:
            return f"{r.size} beams of {math.degrees(msg.angle_increment):.3f} deg span more than one turn"
        if self.require_motor and not self.motor_on:
            return ""
        ang = msg.angle_min + np.arange(r.size) * msg.angle_increment
        half = msg.angle_increment / 2 + math.radians(angle_tol_deg)
        probe = ang[:, None] + np.linspace(-half, half, 9)[None, :]
        truth = np.asarray(self.scan_source(np.mod(probe, 2 * math.pi).ravel()), dtype=float).reshape(probe.shape)
        none = ~(np.isfinite(truth) & (truth > 0) & (truth * 1000.0 <= 16383.0))
        t = np.where(none, np.nan, truth)
        with np.errstate(all="ignore"):
            lo, hi = np.nanmin(t, axis=1), np.nanmax(t, axis=1)
        fin = np.isfinite(r)
        with np.errstate(invalid="ignore"):
            wrong = fin & ~((r >= lo - range_tol_m) & (r <= hi + range_tol_m))
        wrong_inf = np.isposinf(r) & ~none.any(axis=1)
        if np.isneginf(r).any():
            return f"{int(np.isneginf(r).sum())} beams -inf: this device never reports 'too close'"
        if wrong.any() or wrong_inf.any():
            k = int(np.flatnonzero(wrong | wrong_inf)[0])
            return (f"{int(wrong.sum())} beams with a range not measured at their angle, {int(wrong_inf.sum())} "
                    f"'no return' where there is one; e.g. beam {k} at {math.degrees(ang[k]) % 360:.2f} deg: "
                    f"{r[k]:.4f} m, true {lo[k]:.4f}..{hi[k]:.4f} m")
        return ""

    @property
    def nominal_nodes_per_s(self) -> float:
        return self.sample_rate_hz * self.time_scale

    @property
    def nominal_scans_per_s(self) -> float:
        return self.scan_rate_hz * self.time_scale


__all__ = ["EmulatedRPLidar", "room_scan_source", "laser_scan_source", "ScanSource"]
