"""Slamtec RPLIDAR (A1/A2) driver over pyserial, publishing ``LaserScan``.

Protocol (Slamtec rplidar_sdk ``sl_lidar_cmd.h`` / ``rplidar_cmd.h``,
``sl_lidar_protocol.h``; see ``reference/devices.md``):

* request ``A5 cmd`` or ``A5 cmd len payload xor``; response descriptor
  ``A5 5A`` + u32 LE (30-bit size, 2-bit send mode) + type byte;
* standard scan (``SCAN 0x20``, answer type 0x81): 5-byte nodes
  ``[S | !S<<1 | quality<<2] [check=1 | angle_q6<<1 : u16] [distance_q2 : u16]``;
* legacy express scan (``EXPRESS_SCAN 0x82``, answer type 0x82): 84-byte
  capsules ``[0xA<<4 | chk&0xF] [0x5<<4 | chk>>4] [start_angle_q6 | S<<15 : u16]``
  then 16 cabins of 5 bytes ``[dist1_q2 | dtheta1>>4 : u16] [dist2 ... : u16]
  [dtheta1&0xF | (dtheta2&0xF)<<4]``; ``chk`` is the XOR of bytes 2..83. A
  capsule's 32 nodes are placed between its start angle and the *next*
  capsule's; the arithmetic below is the SDK's ``_capsuleToNormal`` in the same
  fixed point.

Validation (nothing is published that was not measured). A standard node
passes the protocol's checks (``S != !S``, ``C = 1``, angle < 360 deg) *and*
continues the rotation from the nodes before and after it
(:class:`NodeStreamParser`); an express capsule passes its sync nibbles and
checksum and advances plausibly from the previous one. A turn runs between
start flags (a flag far from 0 deg is garbage) and never spans more than
360 deg; each node is published in its own slot at the angle it was measured
at, lost nodes as NaN, "no return" as +inf (REP-117); a turn with too few
nodes, or a node count the scan mode cannot make, is dropped
(:class:`ScanAssembler`). :class:`LidarStats` counts what was dropped.

Angles. The RPLIDAR reports angles in degrees **clockwise** seen from above
(0 deg = the device's forward mark). ROS (REP-103) angles are radians
**counter-clockwise** about +Z. :func:`device_to_ros_angle` maps one to the
other: ``theta_ros = angle_offset - radians(theta_dev)`` wrapped to [0, 2 pi).
``angle_offset`` (rad) is where the device's 0 deg points in the laser frame;
0 here, pi in ``rplidar_ros`` (its laser frame faces the cable side).

Motor. An A1 spins its motor while DTR is *cleared*; an A2/A3 takes
``SET_MOTOR_PWM 0xF0`` (u16 0..1023). The driver sends both (devices that
do not support 0xF0 parse and ignore it). Ports are opened with
``serial.serial_for_url`` so ``pty://`` URLs (emulators, tests) record DTR.
"""

from __future__ import annotations

import logging
import math
import struct
import time
from dataclasses import dataclass
from typing import Iterator, NamedTuple

import numpy as np
import serial

from ..bus.msgs import Header, LaserScan
from ..errors import DeviceError, DeviceTimeout
from ..utils.geometry import wrap_angle
from . import ptyserial  # noqa: F401  (registers the pty:// URL handler)
from .base import DeviceDriver, DriverStats, Publish

log = logging.getLogger(__name__)

SYNC_BYTE = 0xA5
SYNC_BYTE2 = 0x5A
CMDFLAG_HAS_PAYLOAD = 0x80

CMD_STOP = 0x25
CMD_SCAN = 0x20
CMD_FORCE_SCAN = 0x21
CMD_RESET = 0x40
CMD_GET_INFO = 0x50
CMD_GET_HEALTH = 0x52
CMD_GET_SAMPLERATE = 0x59
CMD_EXPRESS_SCAN = 0x82
CMD_GET_LIDAR_CONF = 0x84
CMD_SET_MOTOR_PWM = 0xF0

ANS_TYPE_DEVINFO = 0x04
ANS_TYPE_DEVHEALTH = 0x06
ANS_TYPE_SAMPLERATE = 0x15
ANS_TYPE_MEASUREMENT = 0x81
ANS_TYPE_MEASUREMENT_CAPSULED = 0x82
ANS_TYPE_GET_LIDAR_CONF = 0x20

# GET_LIDAR_CONF (0x84, firmware >= 1.24) configuration types (sl_lidar_cmd.h)
CONF_SCAN_MODE_COUNT = 0x70
CONF_SCAN_MODE_US_PER_SAMPLE = 0x71
CONF_SCAN_MODE_MAX_DISTANCE = 0x74
CONF_SCAN_MODE_ANS_TYPE = 0x75
CONF_SCAN_MODE_TYPICAL = 0x7C
CONF_SCAN_MODE_NAME = 0x7F

SEND_MODE_SINGLE = 0
SEND_MODE_MULTIPLE = 1

NODE_SIZE = 5
CAPSULE_SIZE = 84
CABINS_PER_CAPSULE = 16
NODES_PER_CAPSULE = 32
EXP_SYNC_1 = 0xA
EXP_SYNC_2 = 0x5

STATUS_OK, STATUS_WARNING, STATUS_ERROR = 0, 1, 2
MAX_MOTOR_PWM = 1023
DEFAULT_MOTOR_PWM = 660


# --------------------------------------------------------------------------- framing
def build_request(cmd: int, payload: bytes | None = None) -> bytes:
    """``A5 cmd`` or ``A5 cmd len payload xor`` (xor of all preceding bytes)."""
    if payload is None:
        return bytes((SYNC_BYTE, cmd))
    body = bytes((SYNC_BYTE, cmd, len(payload))) + payload
    chk = 0
    for b in body:
        chk ^= b
    return body + bytes((chk,))


def build_descriptor(size: int, send_mode: int, data_type: int) -> bytes:
    """7-byte response descriptor ``A5 5A`` + u32 (size | mode<<30) + type."""
    return bytes((SYNC_BYTE, SYNC_BYTE2)) + struct.pack("<IB", (size & 0x3FFFFFFF) | (send_mode << 30), data_type)


class Descriptor(NamedTuple):
    size: int  #: bytes per answer (per node/capsule in multiple mode)
    send_mode: int  #: 0 single answer, 1 multiple (stream)
    data_type: int


def parse_descriptor(raw: bytes) -> Descriptor:
    """Decode 7 descriptor bytes (raises ``DeviceError`` naming the bad byte)."""
    if len(raw) != 7 or raw[0] != SYNC_BYTE or raw[1] != SYNC_BYTE2:
        raise DeviceError(f"bad response descriptor {raw.hex(' ')} (expected A5 5A ...)")
    v, t = struct.unpack("<IB", raw[2:7])
    return Descriptor(v & 0x3FFFFFFF, v >> 30, t)


@dataclass(frozen=True)
class DeviceInfo:
    """GET_INFO answer: model id (e.g. 0x18 = A1M8), firmware (major, minor),
    hardware revision, 16-byte serial number."""

    model: int
    firmware: tuple[int, int]
    hardware: int
    serial_number: bytes

    def to_bytes(self) -> bytes:
        sn = self.serial_number.ljust(16, b"\0")[:16]
        return bytes((self.model, self.firmware[1], self.firmware[0], self.hardware)) + sn

    @classmethod
    def from_bytes(cls, raw: bytes) -> "DeviceInfo":
        if len(raw) != 20:
            raise DeviceError(f"GET_INFO answer is {len(raw)} bytes, expected 20")
        return cls(raw[0], (raw[2], raw[1]), raw[3], bytes(raw[4:20]))

    @property
    def serial_hex(self) -> str:
        return self.serial_number.hex().upper()


@dataclass(frozen=True)
class DeviceHealth:
    """GET_HEALTH answer: status 0 good / 1 warning / 2 error, u16 error code."""

    status: int
    error_code: int

    def to_bytes(self) -> bytes:
        return struct.pack("<BH", self.status, self.error_code)

    @classmethod
    def from_bytes(cls, raw: bytes) -> "DeviceHealth":
        if len(raw) != 3:
            raise DeviceError(f"GET_HEALTH answer is {len(raw)} bytes, expected 3")
        s, e = struct.unpack("<BH", raw)
        return cls(s, e)


class ScanNode(NamedTuple):
    """One measurement: device angle (deg, clockwise), distance (mm, 0 = no
    return), quality (0..63), start = first node of a new 360 deg scan."""

    angle_deg: float
    distance_mm: float
    quality: int
    start: bool


# --------------------------------------------------------------------------- nodes
def encode_node(angle_deg: float, distance_mm: float, quality: int, start: bool) -> bytes:
    """5-byte standard scan node (angle q6, distance q2, check bit set)."""
    q6 = int(round(angle_deg * 64.0)) % (360 * 64)
    d_q2 = min(int(round(distance_mm * 4.0)), 0xFFFF)
    b0 = (1 if start else 2) | ((quality & 0x3F) << 2)
    return struct.pack("<BHH", b0, (q6 << 1) | 1, d_q2)


def node_angle_q6(raw: bytes | bytearray | memoryview, offset: int = 0) -> int | None:
    """The per-node checks of the protocol: ``S != !S`` (byte 0 bits 0/1), check
    bit ``C = 1`` (byte 1 bit 0) and an angle below 360 deg. Returns the angle
    (q6, 1/64 deg) of a node that passes, ``None`` otherwise. Quality (6 bits)
    and distance (16 bits) have no invalid values, so they cannot be checked."""
    b0, b1, b2 = raw[offset], raw[offset + 1], raw[offset + 2]
    if not ((b0 ^ (b0 >> 1)) & 1) or not (b1 & 1):
        return None
    q6 = (b1 | (b2 << 8)) >> 1
    return q6 if q6 < 360 * 64 else None


def node_is_valid(raw: bytes | bytearray | memoryview, offset: int = 0) -> bool:
    """The SDK's checks on a 5-byte node: S != !S, check bit = 1; plus angle < 360 deg."""
    return node_angle_q6(raw, offset) is not None


def decode_node(raw: bytes | bytearray | memoryview, offset: int = 0) -> ScanNode:
    """Decode a node already checked with :func:`node_is_valid`."""
    b0, a, d = struct.unpack_from("<BHH", raw, offset)
    return ScanNode((a >> 1) / 64.0, d / 4.0, b0 >> 2, bool(b0 & 1))


# --------------------------------------------------------------------------- capsules
def encode_capsule(start_angle_deg: float, distances_mm, new_scan: bool = False,
                   offsets_q3=None) -> bytes:
    """84-byte legacy express capsule.

    Args:
        start_angle_deg: device angle (deg, clockwise) of the capsule's first node.
        distances_mm: ``[32]`` distances (mm, 0 = no return; 14 bits, 1 mm steps).
        new_scan: the S bit (set on the first capsule after EXPRESS_SCAN).
        offsets_q3: ``[32]`` 6-bit angle compensations (1/8 deg), subtracted
            from the node angle by the decoder; default 0.
    """
    d = [min(int(round(x)), 0x3FFF) for x in distances_mm]
    if len(d) != NODES_PER_CAPSULE:
        raise ValueError(f"a capsule holds {NODES_PER_CAPSULE} distances, got {len(d)}")
    off = [0] * NODES_PER_CAPSULE if offsets_q3 is None else [int(o) & 0x3F for o in offsets_q3]
    q6 = int(round(start_angle_deg * 64.0)) % (360 * 64)
    body = bytearray(struct.pack("<H", q6 | (0x8000 if new_scan else 0)))
    for c in range(CABINS_PER_CAPSULE):
        d1, d2 = d[2 * c], d[2 * c + 1]
        o1, o2 = off[2 * c], off[2 * c + 1]
        body += struct.pack("<HHB", (d1 << 2) | (o1 >> 4), (d2 << 2) | (o2 >> 4), (o1 & 0xF) | ((o2 & 0xF) << 4))
    chk = 0
    for b in body:
        chk ^= b
    return bytes(((EXP_SYNC_1 << 4) | (chk & 0xF), (EXP_SYNC_2 << 4) | (chk >> 4))) + bytes(body)


def capsule_checksum_ok(raw: bytes | bytearray | memoryview, offset: int = 0) -> bool:
    """Sync nibbles 0xA/0x5 and XOR of bytes 2..83 equal to the split checksum."""
    b0, b1 = raw[offset], raw[offset + 1]
    if (b0 >> 4) != EXP_SYNC_1 or (b1 >> 4) != EXP_SYNC_2:
        return False
    chk = 0
    for b in raw[offset + 2: offset + CAPSULE_SIZE]:
        chk ^= b
    return chk == ((b0 & 0xF) | ((b1 & 0xF) << 4))


class CapsuleDecoder:
    """Turns consecutive capsules into nodes (needs the next capsule's start angle).

    Args:
        max_capsule_step_deg: largest plausible advance (deg) of the start angle
            from one capsule to the next; a pair outside ``(0, max]`` is not
            decoded (its nodes would be spread over the wrong arc) and counted
            in ``rejected``.
    """

    def __init__(self, max_capsule_step_deg: float = 60.0) -> None:
        self.max_capsule_step_q8 = int(max_capsule_step_deg * 256)
        self.rejected = 0
        self._prev: bytes | None = None

    def reset(self) -> None:
        self._prev = None

    def feed(self, capsule: bytes) -> list[ScanNode]:
        """Nodes of the *previous* capsule, placed up to this one's start angle."""
        start_sync = struct.unpack_from("<H", capsule, 2)[0]
        nodes: list[ScanNode] = []
        if start_sync & 0x8000:  # S: first capsule of a stream -> nothing to pair with
            self._prev = None
        prev = self._prev
        if prev is not None:
            cur_q8 = (start_sync & 0x7FFF) << 2
            prev_q8 = (struct.unpack_from("<H", prev, 2)[0] & 0x7FFF) << 2
            diff_q8 = cur_q8 - prev_q8
            if prev_q8 > cur_q8:
                diff_q8 += 360 << 8
            if not 0 < diff_q8 <= self.max_capsule_step_q8:
                self.rejected += 1  # a capsule went missing or one is garbage: do not stretch
                prev = None
        if prev is not None:
            inc_q16 = diff_q8 << 3
            cur_q16 = prev_q8 << 8
            for c in range(CABINS_PER_CAPSULE):
                da1, da2, oq = struct.unpack_from("<HHB", prev, 4 + 5 * c)
                for dist_angle, off_q3 in ((da1, (oq & 0xF) | ((da1 & 0x3) << 4)),
                                           (da2, (oq >> 4) | ((da2 & 0x3) << 4))):
                    dist_q2 = dist_angle & 0xFFFC
                    angle_q6 = (cur_q16 - (off_q3 << 13)) >> 10
                    sync = ((cur_q16 + inc_q16) % (360 << 16)) < inc_q16
                    cur_q16 += inc_q16
                    angle_q6 %= 360 << 6
                    nodes.append(ScanNode(angle_q6 / 64.0, dist_q2 / 4.0, 0x2F if dist_q2 else 0, sync))
        self._prev = bytes(capsule)
        return nodes


# --------------------------------------------------------------------------- stream parsing
@dataclass
class LidarStats(DriverStats):
    """:class:`DriverStats` plus what the RPLIDAR driver did with each node and turn."""

    nodes_bad: int = 0  #: nodes that failed a check (bits, angle, continuity, misplaced start flag)
    nodes_unpublished: int = 0  #: valid nodes in no published scan (partial or dropped turn, duplicate slot)
    scans_published: int = 0  #: turns published as ``LaserScan``
    scans_dropped: int = 0  #: turns dropped for covering less than ``min_coverage`` of 360 deg
    beams_missing: int = 0  #: NaN beams published (nodes lost on the line, REP-117)


class NodeStreamParser:
    """Byte stream of a running scan -> nodes that passed every check.

    ``mode`` is ``"standard"`` (5-byte nodes) or ``"express"`` (84-byte capsules).

    Standard nodes carry only three check bits (``S``, ``!S``, ``C``), so 1 in
    8 random 5-byte windows passes them, and windows straddling two real nodes
    pass in long, smoothly changing runs (a window starting at a node's second
    byte always claims ``S = 1`` and reads part of the distance as its angle).
    A node is therefore accepted only when it also continues the rotation as
    the head turns it: its start flag is set only within ``start_window_deg``
    of 0 deg, and its angle steps ahead of the node before it *and* to the node
    after it by 1 q6 .. ``max_angle_step_deg``, within ``step_tolerance`` of
    the head's current step (learned from accepted nodes, forgotten after 1 kB
    without sync so a changed motor speed is re-learned). Out of sync (at start
    and after a bad node) three such nodes in a row with equal steps are
    needed before the first is accepted; until then the parser slides one byte
    at a time. A good node whose successor is bad is dropped with it.

    Express capsules are checked by their sync nibbles and XOR checksum (as
    the SDK does) and by the advance of their start angle
    (:class:`CapsuleDecoder`).

    Counters (``stats``): ``frames_bad`` once per loss of sync (and per bad
    capsule), ``nodes_bad`` per rejected node window, ``bytes_dropped`` per
    skipped byte, ``frames_ok`` per accepted node/capsule.
    """

    def __init__(self, mode: str, stats: DriverStats, max_angle_step_deg: float = 5.0,
                 max_capsule_step_deg: float = 60.0, start_window_deg: float = 10.0,
                 step_tolerance: float = 0.2) -> None:
        if mode not in ("standard", "express"):
            raise ValueError(f"scan mode must be 'standard' or 'express', got {mode!r}")
        self.mode = mode
        self.stats = stats
        self.max_step_q6 = int(round(max_angle_step_deg * 64))
        self.start_window_q6 = int(round(start_window_deg * 64))
        self.step_tolerance = step_tolerance
        self._buf = bytearray()
        self._synced = True
        self._prev_q6: int | None = None  #: angle of the last accepted node; None = out of sync
        self._ref_step: float | None = None  #: q6, the head's step between neighbouring nodes
        self._unsynced_bytes = 0
        self._decoder = CapsuleDecoder(max_capsule_step_deg)

    def feed(self, data: bytes) -> list[ScanNode]:
        self._buf += data
        return self._parse_standard() if self.mode == "standard" else self._parse_express()

    def _bad_node(self) -> None:
        if isinstance(self.stats, LidarStats):
            self.stats.nodes_bad += 1

    def _drop(self, n: int = 1) -> None:
        if self._synced:  # count each loss of sync once as a bad frame
            self.stats.frames_bad += 1
            self._synced = False
        del self._buf[:n]
        self.stats.bytes_dropped += n

    def _node(self, buf: bytearray, i: int) -> int | None:
        """Angle (q6) of the node at ``i`` if it passes the protocol's checks and
        its start flag, if set, is near 0 deg; else ``None``."""
        a = node_angle_q6(buf, i)
        if a is not None and buf[i] & 1 and self.start_window_q6 < a < 360 * 64 - self.start_window_q6:
            return None
        return a

    def _step(self, a_q6: int | None, b_q6: int | None) -> int | None:
        """Step (q6) from ``a`` to ``b`` if the head can make it, else ``None``."""
        if a_q6 is None or b_q6 is None:
            return None
        d = (b_q6 - a_q6) % (360 * 64)
        if not 0 < d <= self.max_step_q6:
            return None
        ref = self._ref_step
        if ref is not None and abs(d - ref) > max(4.0, self.step_tolerance * ref):
            return None
        return d

    def _alike(self, s1: int, s2: int) -> bool:
        return abs(s1 - s2) <= max(4.0, self.step_tolerance * max(s1, s2))

    def _learn(self, step: int) -> None:
        self._ref_step = float(step) if self._ref_step is None else 0.9 * self._ref_step + 0.1 * step

    def _parse_standard(self) -> list[ScanNode]:
        out: list[ScanNode] = []
        buf = self._buf
        i = 0
        n = len(buf)
        dropped = 0
        while True:
            if self._prev_q6 is not None:  # in sync: this node and the next must continue the turn
                if n - i < 2 * NODE_SIZE:
                    break
                a = self._node(buf, i)
                s1 = self._step(self._prev_q6, a)
                s2 = self._step(a, self._node(buf, i + NODE_SIZE)) if s1 is not None else None
                if s2 is not None:
                    out.append(decode_node(buf, i))
                    self._prev_q6 = a
                    self._learn(s1)
                    i += NODE_SIZE
                    self.stats.frames_ok += 1
                    continue
                self._bad_node()
                self.stats.frames_bad += 1
                self._synced = False
                self._prev_q6 = None
                self._unsynced_bytes = 0
                i += 1
                dropped += 1
                continue
            if n - i < 3 * NODE_SIZE:  # out of sync: three nodes in a row that continue each other
                break
            a0 = self._node(buf, i)
            a1 = self._node(buf, i + NODE_SIZE) if a0 is not None else None
            s1 = self._step(a0, a1)
            s2 = self._step(a1, self._node(buf, i + 2 * NODE_SIZE)) if s1 is not None else None
            if s2 is not None and self._alike(s1, s2):
                out.append(decode_node(buf, i))
                self._prev_q6 = a0
                self._learn(s1)
                self._synced = True
                i += NODE_SIZE
                self.stats.frames_ok += 1
                continue
            if self._synced:  # first byte of a loss of sync (e.g. right after start)
                self.stats.frames_bad += 1
                self._synced = False
            self._unsynced_bytes += 1
            if self._unsynced_bytes > 1024:  # the head may have changed speed: learn its step anew
                self._ref_step = None
                self._unsynced_bytes = 0
            i += 1
            dropped += 1
        self.stats.bytes_dropped += dropped
        del buf[:i]
        return out

    def _parse_express(self) -> list[ScanNode]:
        out: list[ScanNode] = []
        buf = self._buf
        while len(buf) >= 2:
            if (buf[0] >> 4) != EXP_SYNC_1 or (buf[1] >> 4) != EXP_SYNC_2:
                self._decoder.reset()
                self._drop(1)
                continue
            if len(buf) < CAPSULE_SIZE:
                break
            if not capsule_checksum_ok(buf):
                # a framed capsule that fails its checksum is always a bad frame;
                # the bytes skipped after it belong to the same loss of sync
                log.debug("express capsule checksum mismatch: %s...", bytes(buf[:8]).hex(" "))
                self._decoder.reset()
                self.stats.frames_bad += 1
                self._synced = False
                self._drop(1)
                continue
            capsule = bytes(buf[:CAPSULE_SIZE])
            del buf[:CAPSULE_SIZE]
            self._synced = True
            self.stats.frames_ok += 1
            rejected = self._decoder.rejected
            out.extend(self._decoder.feed(capsule))
            if self._decoder.rejected > rejected:
                self.stats.frames_bad += 1
                self._bad_node()
        return out


# --------------------------------------------------------------------------- angles / scans
def device_to_ros_angle(angle_deg, angle_offset: float = 0.0):
    """Device angle (deg, clockwise) -> ROS angle (rad, counter-clockwise) in [0, 2 pi)."""
    return np.mod(angle_offset - np.radians(angle_deg), 2 * np.pi)


def ros_to_device_angle(angle_rad, angle_offset: float = 0.0):
    """ROS angle (rad, counter-clockwise) -> device angle (deg, clockwise) in [0, 360)."""
    return np.mod(np.degrees(angle_offset - np.asarray(angle_rad)), 360.0)


#: Rotation rates (Hz) an RPLIDAR head turns at in service (A1 nominal 5.5, A2/A3 up to 15),
#: with margin; outside them a "turn" is not a turn of a working head.
MIN_ROTATION_HZ, MAX_ROTATION_HZ = 2.0, 20.0


def nodes_per_turn_range(us_per_sample: float, min_hz: float = MIN_ROTATION_HZ,
                         max_hz: float = MAX_ROTATION_HZ) -> tuple[float, float]:
    """(fewest, most) nodes one turn can hold at ``us_per_sample`` (GET_SAMPLERATE)
    for a head turning at ``min_hz .. max_hz``."""
    per_s = 1e6 / us_per_sample
    return per_s / max_hz, per_s / min_hz


class ScanAssembler:
    """Collects validated nodes into 360 deg turns and converts them to ``LaserScan``.

    A turn starts at a start-flagged node and ends at the next one, or where
    the angle wraps past the turn's first node (the start node was lost);
    it never spans more than 360 deg. A start flag on a node more than
    ``start_window_deg`` from 0 deg is garbage that passed the check bits:
    the node is dropped (``stats.nodes_bad``). Nodes before the first start
    flag are not published.

    Every beam is published at the angle it was measured at, on a grid:

    * ``angle_bins = None``: the grid is the device's own sample step (the
      turn's median node spacing refined over the turn), one full turn of
      ``round(360 / step)`` beams starting at the turn's first node; each node
      goes to its nearest grid slot (error <= half a step), so a lost node
      leaves its slot empty instead of closing up the turn;
    * ``angle_bins = N``: N fixed bins from ROS angle 0, nearest return per bin.

    REP-117: a slot with a node whose distance is 0 (measured, no return) is
    ``+inf``; a slot no node reached (lost on the line) is ``NaN``. A turn
    whose nodes cover less than ``min_coverage`` of the device's turn is
    dropped (``stats.scans_dropped``), not published; so is one whose node
    count per full turn (360 deg / step) lies outside ``nodes_per_turn``
    (see :func:`nodes_per_turn_range`; ``None`` = not checked).

    The per-node grid assumes the nodes of a turn are evenly spaced, as in
    standard scans and in express scans without angle compensation; with
    compensated express nodes two nodes may share a slot (the one nearer its
    centre is kept, the other counted in ``nodes_unpublished``); use
    ``angle_bins`` there.
    """

    def __init__(self, *, frame_id: str = "base_scan", angle_offset: float = 0.0,
                 angle_bins: int | None = None, range_min: float = 0.15, range_max: float = 12.0,
                 start_window_deg: float = 10.0, min_coverage: float = 0.5,
                 nodes_per_turn: tuple[float, float] | None = None, stats: LidarStats | None = None) -> None:
        if not 0.0 < min_coverage <= 1.0:
            raise ValueError(f"min_coverage must be in (0, 1], got {min_coverage!r}")
        self.frame_id = frame_id
        self.angle_offset = angle_offset
        self.angle_bins = angle_bins
        self.range_min = range_min
        self.range_max = range_max
        self.start_window_deg = start_window_deg
        self.min_coverage = min_coverage
        self.nodes_per_turn = nodes_per_turn
        self.stats = stats if stats is not None else LidarStats()
        self._nodes: list[ScanNode] = []
        self._rel: list[float] = []
        self._a0 = 0.0
        self._half = False
        self._started = False
        self._t_start: float | None = None
        self._last_scan_time = 0.0

    def reset(self) -> None:
        self.stats.nodes_unpublished += len(self._nodes)
        self._nodes, self._rel = [], []
        self._started = False
        self._half = False
        self._t_start = None

    def _count(self, name: str, n: int = 1) -> None:
        setattr(self.stats, name, getattr(self.stats, name) + n)

    def _begin(self, node: ScanNode, stamp: float) -> None:
        self._nodes, self._rel = [node], [0.0]
        self._a0 = node.angle_deg
        self._half = False
        self._started = True
        self._t_start = stamp

    def add(self, nodes: list[ScanNode], stamp: float) -> list[LaserScan]:
        """Add nodes received at ``stamp`` (s); returns the turns they completed."""
        scans: list[LaserScan] = []
        for node in nodes:
            if node.start:
                a = node.angle_deg % 360.0
                if min(a, 360.0 - a) > self.start_window_deg:
                    self._count("nodes_bad")
                    self.stats.frames_bad += 1
                    continue
                scans += self._close(stamp)
                self._begin(node, stamp)
                continue
            if not self._started:
                self._count("nodes_unpublished")
                continue
            rel = (node.angle_deg - self._a0) % 360.0
            if self._half and rel < 90.0:  # wrapped past the start: its start node was lost
                scans += self._close(stamp)
                self._begin(node, stamp)
                continue
            if rel > 270.0 and not self._half:
                rel -= 360.0  # a little behind the first node (angle compensation)
            elif 90.0 <= rel <= 270.0:
                self._half = True
            self._nodes.append(node)
            self._rel.append(rel)
        return scans

    def _close(self, stamp: float) -> list[LaserScan]:
        """Turn the collected turn into a scan (or drop it); start nothing."""
        nodes, rel = self._nodes, np.asarray(self._rel, dtype=float)
        self._nodes, self._rel = [], []
        if not self._started or not nodes:
            return []
        scan_time = max(0.0, stamp - self._t_start) if self._t_start is not None else 0.0
        step = _sample_step_deg(rel)
        why = None
        if step is None or len(nodes) / (360.0 / step) < self.min_coverage:
            why = f"covers < {100 * self.min_coverage:.0f} % of a turn"
        elif self.nodes_per_turn is not None and not (
                self.nodes_per_turn[0] <= 360.0 / step <= self.nodes_per_turn[1]):
            why = (f"{360.0 / step:.0f} nodes per turn, the scan mode makes "
                   f"{self.nodes_per_turn[0]:.0f}..{self.nodes_per_turn[1]:.0f}")
        if why is not None:
            self._count("scans_dropped")
            self._count("nodes_unpublished", len(nodes))
            log.debug("turn of %d nodes dropped (%s)", len(nodes), why)
            return []
        self._last_scan_time = scan_time
        scan = self.to_laser_scan(nodes, self._t_start if self._t_start is not None else stamp, scan_time,
                                  rel=rel, step_deg=step)
        self._count("scans_published")
        return [scan]

    def to_laser_scan(self, nodes: list[ScanNode], stamp: float, scan_time: float, *,
                      rel: np.ndarray | None = None, step_deg: float | None = None) -> LaserScan:
        """One turn of nodes -> ``LaserScan`` (ranges m, intensities = quality).

        Args:
            nodes: the turn's nodes in arrival order.
            stamp: s, time of the turn's first node.
            scan_time: s, duration of the turn.
            rel: ``[len(nodes)]`` device angles (deg) relative to the first
                node, unwrapped; default from the nodes.
            step_deg: the device's sample step; default estimated from ``rel``.

        Beams are ordered by increasing ROS angle (the reverse of measurement
        order, as ``rplidar_ros`` publishes); ``time_increment`` is
        ``scan_time / len(ranges)``. Per-node grid: ``angle_min`` in
        [-pi, pi), the turn spans ``angle_max - angle_min < 2 pi``.
        """
        if rel is None:
            rel = np.mod(np.array([nd.angle_deg for nd in nodes]) - nodes[0].angle_deg, 360.0)
        step = step_deg if step_deg is not None else _sample_step_deg(rel)
        dist = np.array([nd.distance_mm for nd in nodes], dtype=float) / 1000.0
        qual = np.array([nd.quality for nd in nodes], dtype=float)
        valid = dist > 0
        if self.angle_bins is None:
            if step is None:
                raise ValueError("cannot place fewer than 2 nodes on a grid")
            base = float(rel.min())
            fslot = (rel - base) / step
            slot = np.rint(fslot).astype(int)
            n = max(int(round(360.0 / step)), int(slot.max()) + 1)
            # one node per slot: the one nearest the slot's centre
            order = np.lexsort((np.abs(fslot - slot), slot))
            first = np.ones(len(order), bool)
            first[1:] = slot[order][1:] != slot[order][:-1]
            keep = order[first]
            self._count("nodes_unpublished", len(nodes) - len(keep))
            # ROS angle decreases with device angle: index j = n - 1 - slot
            idx = n - 1 - slot[keep]
            inc = math.radians(step)
            a0 = wrap_angle(self.angle_offset
                            - math.radians(nodes[0].angle_deg + base + (n - 1) * step))
            ranges = np.full(n, np.nan)
            inten = np.zeros(n)
            ranges[idx] = np.where(valid[keep], dist[keep], np.inf)
            inten[idx] = np.where(valid[keep], qual[keep], 0.0)
            a1 = a0 + (n - 1) * inc
        else:
            n = self.angle_bins
            inc = 2 * math.pi / n
            a0, a1 = 0.0, (n - 1) * inc
            ang = device_to_ros_angle(np.array([nd.angle_deg for nd in nodes]), self.angle_offset)
            idx = np.rint(ang / inc).astype(int) % n
            ranges = np.full(n, np.nan)
            inten = np.zeros(n)
            ranges[idx[~valid]] = np.inf  # measured without a return ...
            for k in np.argsort(-np.where(valid, dist, np.inf)):  # ... unless a return: nearest written last
                if valid[k]:
                    ranges[idx[k]] = dist[k]
                    inten[idx[k]] = qual[k]
        self._count("beams_missing", int(np.isnan(ranges).sum()))
        return LaserScan(
            header=Header(stamp=stamp, frame_id=self.frame_id),
            angle_min=a0, angle_max=a1, angle_increment=inc,
            time_increment=scan_time / n if n else 0.0, scan_time=scan_time,
            range_min=self.range_min, range_max=self.range_max,
            ranges=ranges, intensities=inten,
        )


def _sample_step_deg(rel: np.ndarray) -> float | None:
    """The device's angular sample step (deg) from one turn's node angles.

    The median spacing of neighbouring nodes, refined over the whole turn:
    each spacing counts as ``round(spacing / step)`` steps (gaps from lost
    nodes count as several) and the step is their mean, three times, so q6
    rounding (steps alternate 63/64 q6) does not accumulate along the turn. ``None`` with fewer than 2 distinct angles.
    """
    d = np.diff(np.sort(np.asarray(rel, dtype=float)))
    d = d[d > 1e-9]
    if d.size == 0:
        return None
    step = float(np.median(d))
    for _ in range(3):  # a gap of ~100 steps is miscounted by one with the median alone
        k = np.rint(d / step)
        step = float(d[k > 0].sum() / k[k > 0].sum())
    return step


# --------------------------------------------------------------------------- driver
class RPLidar(DeviceDriver):
    """RPLIDAR driver: a synchronous client plus a read-loop thread publishing scans.

    Synchronous use (no thread)::

        lidar = RPLidar("/dev/ttyUSB0"); lidar.open()
        lidar.get_info(); lidar.get_health(); lidar.set_motor(True)
        lidar.start_scan("express"); scans = list(lidar.iter_scans(3, timeout=5))
        lidar.stop_scan(); lidar.close()

    Threaded use: ``RPLidar(url, publish).start()`` publishes ``LaserScan`` on
    ``topic`` for every full turn, reconnecting with backoff when the device
    disappears; :meth:`stop` ends the thread (``stop_scan`` is the protocol's
    STOP command).

    Args:
        url: port path or pyserial URL.
        publish: ``publish(topic, msg)``.
        baudrate: 115200 (A1, A2M8) or 256000 (A2M7/A3...).
        scan_mode: ``"standard"`` (SCAN 0x20) or ``"express"`` (EXPRESS_SCAN 0x82, legacy capsules).
        motor_pwm: PWM sent with SET_MOTOR_PWM (0..1023).
        topic, frame_id, angle_offset, angle_bins, range_min, range_max, min_coverage: see
            :class:`ScanAssembler`.
        max_angle_step_deg: largest angle step between neighbouring standard nodes
            (see :class:`NodeStreamParser`); 5 deg covers an A1/A2 at up to 15 Hz.
        timeout: s to wait for a command's answer.
    """

    MESSAGE_TYPES = {"scan": LaserScan}

    def __init__(self, url: str, publish: Publish | None = None, *, baudrate: int = 115200,
                 scan_mode: str = "standard", motor_pwm: int = DEFAULT_MOTOR_PWM, topic: str = "scan",
                 frame_id: str = "base_scan", angle_offset: float = 0.0, angle_bins: int | None = None,
                 range_min: float = 0.15, range_max: float = 12.0, max_angle_step_deg: float = 5.0,
                 min_coverage: float = 0.5, timeout: float = 1.0, stale_timeout: float = 1.0,
                 backoff_initial: float = 0.05, backoff_max: float = 2.0, connect_warn_s: float = 3.0,
                 diagnostics_topic: str | None = "diagnostics", diagnostics_period_s: float = 1.0) -> None:
        super().__init__(url, publish, stale_timeout=stale_timeout, backoff_initial=backoff_initial,
                         backoff_max=backoff_max, connect_warn_s=connect_warn_s,
                         diagnostics_topic=diagnostics_topic, diagnostics_period_s=diagnostics_period_s)
        if scan_mode not in ("standard", "express"):
            raise ValueError(f"scan_mode must be 'standard' or 'express', got {scan_mode!r}")
        self.baudrate = baudrate
        self.scan_mode = scan_mode
        self.motor_pwm = motor_pwm
        self.topic = topic
        self.timeout = timeout
        self.MESSAGE_TYPES = {topic: LaserScan}
        self.stats: LidarStats = LidarStats()
        self.max_angle_step_deg = max_angle_step_deg
        self.assembler = ScanAssembler(frame_id=frame_id, angle_offset=angle_offset, angle_bins=angle_bins,
                                       range_min=range_min, range_max=range_max, min_coverage=min_coverage,
                                       stats=self.stats)
        self.info: DeviceInfo | None = None
        self.health: DeviceHealth | None = None
        self._ser: serial.SerialBase | None = None
        self._parser: NodeStreamParser | None = None
        self._rx = bytearray()

    # -- port ------------------------------------------------------------------
    def open(self) -> None:
        """Open the port (8N1, ``baudrate``) with ``serial.serial_for_url``."""
        self.close()
        self._ser = serial.serial_for_url(self.url, baudrate=self.baudrate, timeout=0.01, write_timeout=1.0)
        self._rx.clear()

    def close(self) -> None:
        if self._ser is not None:
            try:
                self._ser.close()
            except Exception:  # noqa: BLE001
                pass
            self._ser = None
        self._parser = None

    @property
    def port(self) -> serial.SerialBase:
        if self._ser is None:
            raise DeviceError(f"{self.url}: port is not open")
        return self._ser

    def _send(self, cmd: int, payload: bytes | None = None) -> None:
        self.port.write(build_request(cmd, payload))
        self.port.flush()

    def _read_exact(self, n: int, deadline: float) -> bytes:
        while len(self._rx) < n:
            if time.monotonic() > deadline:
                raise DeviceTimeout(f"{self.url}: timed out waiting for {n} bytes (got {len(self._rx)})")
            chunk = self.port.read(max(1, n - len(self._rx)))
            self._rx += chunk
        out = bytes(self._rx[:n])
        del self._rx[:n]
        return out

    def _read_descriptor(self, expected_type: int, deadline: float) -> Descriptor:
        """Find ``A5 5A ... type`` in the input, skipping (and counting) anything else
        (old scan data, the boot banner after RESET)."""
        while True:
            while len(self._rx) < 7:
                if time.monotonic() > deadline:
                    raise DeviceTimeout(f"{self.url}: no response descriptor of type 0x{expected_type:02X}")
                self._rx += self.port.read(64)
            i = self._rx.find(bytes((SYNC_BYTE, SYNC_BYTE2)))
            if i < 0:
                keep = 1 if self._rx[-1] == SYNC_BYTE else 0
                self.stats.bytes_dropped += len(self._rx) - keep
                del self._rx[: len(self._rx) - keep]
                continue
            if i:
                self.stats.bytes_dropped += i
                del self._rx[:i]
            if len(self._rx) < 7:
                continue
            desc = parse_descriptor(bytes(self._rx[:7]))
            if desc.data_type != expected_type:
                self.stats.bytes_dropped += 2
                del self._rx[:2]
                continue
            del self._rx[:7]
            return desc

    def _request(self, cmd: int, answer_type: int, payload: bytes | None = None) -> bytes:
        self.port.reset_input_buffer()
        self._rx.clear()
        self._send(cmd, payload)
        deadline = time.monotonic() + self.timeout
        desc = self._read_descriptor(answer_type, deadline)
        return self._read_exact(desc.size, deadline)

    # -- commands --------------------------------------------------------------
    def get_info(self) -> DeviceInfo:
        """GET_INFO 0x50: model, firmware, hardware, serial number."""
        self.info = DeviceInfo.from_bytes(self._request(CMD_GET_INFO, ANS_TYPE_DEVINFO))
        return self.info

    def get_health(self) -> DeviceHealth:
        """GET_HEALTH 0x52: status (0 good, 1 warning, 2 error) and error code."""
        self.health = DeviceHealth.from_bytes(self._request(CMD_GET_HEALTH, ANS_TYPE_DEVHEALTH))
        return self.health

    def get_samplerate(self) -> tuple[int, int]:
        """GET_SAMPLERATE 0x59: (standard, express) µs per sample."""
        raw = self._request(CMD_GET_SAMPLERATE, ANS_TYPE_SAMPLERATE)
        return struct.unpack("<HH", raw)

    def stop_scan(self) -> None:
        """STOP 0x25: leave scanning; the device sends nothing back."""
        self._send(CMD_STOP)
        time.sleep(0.005)
        self.port.reset_input_buffer()
        self._rx.clear()
        self._parser = None

    def reset(self) -> None:
        """RESET 0x40: reboot the core; its boot banner is discarded."""
        self._send(CMD_RESET)
        time.sleep(0.05)
        self.port.reset_input_buffer()
        self._rx.clear()
        self._parser = None

    def set_motor_pwm(self, pwm: int) -> None:
        """SET_MOTOR_PWM 0xF0 with a u16 duty (0..1023); A1s ignore it."""
        if not 0 <= pwm <= MAX_MOTOR_PWM:
            raise ValueError(f"motor PWM must be 0..{MAX_MOTOR_PWM}, got {pwm}")
        self._send(CMD_SET_MOTOR_PWM, struct.pack("<H", pwm))

    def set_motor(self, on: bool) -> None:
        """Spin (``on``) or stop the motor: DTR cleared/set (A1) and SET_MOTOR_PWM (A2/A3)."""
        self.port.dtr = not on
        self.set_motor_pwm(self.motor_pwm if on else 0)

    def start_scan(self, mode: str | None = None) -> None:
        """Start SCAN (``"standard"``) or EXPRESS_SCAN (``"express"``, legacy capsules)."""
        mode = mode or self.scan_mode
        self.port.reset_input_buffer()
        self._rx.clear()
        deadline = time.monotonic() + self.timeout
        if mode == "standard":
            self._send(CMD_SCAN)
            desc = self._read_descriptor(ANS_TYPE_MEASUREMENT, deadline)
            want = NODE_SIZE
        elif mode == "express":
            self._send(CMD_EXPRESS_SCAN, bytes(5))  # working mode 0, flags 0, param 0
            desc = self._read_descriptor(ANS_TYPE_MEASUREMENT_CAPSULED, deadline)
            want = CAPSULE_SIZE
        else:
            raise ValueError(f"scan mode must be 'standard' or 'express', got {mode!r}")
        if desc.size != want or desc.send_mode != SEND_MODE_MULTIPLE:
            raise DeviceError(f"{self.url}: scan descriptor says {desc.size}-byte answers, "
                              f"send mode {desc.send_mode}; expected {want} bytes, mode 1")
        self._parser = NodeStreamParser(mode, self.stats, self.max_angle_step_deg)
        self.assembler.reset()
        leftover = bytes(self._rx)
        self._rx.clear()
        if leftover:
            self._parser.feed(leftover)

    def read_nodes(self, timeout: float = 0.05) -> list[ScanNode]:
        """Nodes that arrived within ``timeout`` s (empty list if none)."""
        if self._parser is None:
            raise DeviceError(f"{self.url}: not scanning (call start_scan first)")
        deadline = time.monotonic() + timeout
        nodes: list[ScanNode] = []
        while True:
            n = self.port.in_waiting
            data = self.port.read(n if n else 1)
            if data:
                nodes += self._parser.feed(data)
            if nodes or time.monotonic() > deadline:
                return nodes

    def iter_scans(self, max_scans: int, timeout: float) -> Iterator[LaserScan]:
        """Yield up to ``max_scans`` full turns; stops after ``timeout`` s overall."""
        deadline = time.monotonic() + timeout
        got = 0
        while got < max_scans and time.monotonic() < deadline:
            for scan in self.assembler.add(self.read_nodes(0.05), time.time()):
                got += 1
                yield scan
                if got >= max_scans:
                    return

    # -- read loop ---------------------------------------------------------------
    def _connect(self) -> None:
        self.open()
        self.stop_scan()
        health = self.get_health()
        if health.status == STATUS_ERROR:
            self.reset()
            raise DeviceError(f"{self.url}: health status 2 (error code 0x{health.error_code:04X}); reset sent")
        if health.status == STATUS_WARNING:
            log.warning("%s: health warning, error code 0x%04X", self.url, health.error_code)
        info = self.get_info()
        log.info("%s: RPLIDAR model 0x%02X fw %d.%02d hw %d s/n %s", self.url, info.model, *info.firmware,
                 info.hardware, info.serial_hex)
        try:  # GET_SAMPLERATE (firmware >= 1.17): bounds the node count of a turn
            standard_us, express_us = self.get_samplerate()
            us = standard_us if self.scan_mode == "standard" else express_us
            if us > 0:
                self.assembler.nodes_per_turn = nodes_per_turn_range(float(us))
        except DeviceTimeout:
            log.info("%s: no GET_SAMPLERATE answer; node counts per turn are not checked", self.url)
        self.set_motor(True)
        self.start_scan(self.scan_mode)

    def _disconnect(self) -> None:
        if self._ser is not None and self._ser.is_open:
            try:
                self._send(CMD_STOP)
                self._ser.dtr = True
            except Exception:  # noqa: BLE001 - port may already be gone
                pass
        self.close()

    def _poll(self) -> None:
        nodes = self.read_nodes(0.05)
        if nodes:
            self._mark_valid()
            for scan in self.assembler.add(nodes, time.time()):
                self._publish(self.topic, scan)
