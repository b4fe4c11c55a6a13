"""MCAP recording and replay of bus topics (the ``ros2 bag`` format).

Files are MCAP with profile ``ros2``: one schema per message type (encoding
``ros2msg``, the full ``.msg`` text with dependencies, ``isac_twin_msgs``
included), channels with message encoding ``cdr``, payloads CDR with the
encapsulation header. Foxglove, ``ros2 bag`` (rosbag2_storage_mcap) and
``mcap_ros2.reader`` read them.

Channels carry rosbag2's ``offered_qos_profiles`` (the topic's
:func:`isac_twin.transport.qos.qos_for` profile, e.g. ``/tf_static`` transient-local),
so ``ros2 bag play`` re-offers them. Chunks are zstd-compressed by default.

Crash safety: the writer is chunked (``chunk_size`` bytes, default 64 KiB,
and at most ``max_chunk_s`` = 1 s of log time per chunk) and the file is
flushed after every completed chunk, so a process killed at any point leaves
a file whose complete chunks are readable: :func:`read_messages` streams the
file and stops cleanly at the first truncated record, and :func:`recover`
rewrites it as a finished MCAP (summary, footer) that indexed readers
(``mcap.reader.make_reader``, rosbags ``AnyReader``) open.

Times: ``log_time`` is the recorder's clock (wall clock ns by default; the
twin's simulated time for :func:`record_twin`), ``publish_time`` is the
message's ``header.stamp`` when it has one, else ``log_time``.

Replay:

* :func:`replay_to_bus` re-publishes a recording on a bus at the recorded pace
  (``speed`` x faster, or as fast as possible);
* :class:`TrajectoryReplay` drives a twin's robots along their recorded
  ``/<robot>/ground_truth`` poses, so each twin step re-traces the radio
  channel along the recorded trajectory (the live server can stream that twin:
  ``isac-twin replay run.mcap --serve``).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from mcap.records import Channel, Message, Metadata, Schema
from mcap.records import Header as McapHeader
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from ..bus.bus import Bus
from ..bus.msgs import MESSAGE_TYPES, Csi, PoseStamped, shift_stamps
from ..bus.twin_msgs import link_metrics_msg, link_paths_msg
from ..utils.geometry import quaternion_to_yaw, wrap_angle
from . import cdr
from .qos import qos_for, rosbag2_qos_yaml

log = logging.getLogger(__name__)

METADATA_NAME = "isac_twin"
LINKS_TOPIC = "/twin/link_metrics"
PATHS_TOPIC = "/twin/paths"
_COMPRESSION = {"none": CompressionType.NONE, "zstd": CompressionType.ZSTD,
                "lz4": CompressionType.LZ4}


class McapRecorder:
    """Write bus messages to an MCAP file (ros2 profile, CDR).

    Args:
        path: output ``.mcap``.
        chunk_size: bytes per chunk (smaller = less lost when killed, larger files).
        compression: ``"zstd"`` (default), ``"lz4"`` or ``"none"``.
        clock_ns: the log-time clock, ns (default wall clock).
        metadata: written as an MCAP metadata record named ``isac_twin``.
        max_chunk_s: close the open chunk once it spans this much log time (s), so a
            killed recording loses at most about that much; None: by size only.
        stamp_offset_s: added to every ``header.stamp`` (and ``/clock``) before writing,
            e.g. the wall-clock epoch of the twin's t = 0, so the recording lines up
            with real robots' logs; 0 keeps the stamps as published.
        transforms: ``{ROS type: f(msg) -> msg}`` applied before writing (e.g.
            :class:`CsiRecording` for ``isac_twin_msgs/msg/Csi``).
    """

    def __init__(self, path: str | Path, *, chunk_size: int = 64 * 1024,
                 compression: str = "zstd", clock_ns: Callable[[], int] = time.time_ns,
                 metadata: dict | None = None, max_chunk_s: float | None = 1.0,
                 stamp_offset_s: float = 0.0, transforms: dict[str, Callable] | None = None):
        if compression not in _COMPRESSION:
            raise ValueError(f"compression: expected one of {sorted(_COMPRESSION)}, "
                             f"got {compression!r}")
        if not (isinstance(stamp_offset_s, (int, float)) and math.isfinite(stamp_offset_s)):
            raise ValueError(f"stamp_offset_s: expected a finite number of s, "
                             f"got {stamp_offset_s!r}")
        if max_chunk_s is not None and not max_chunk_s > 0:
            raise ValueError(f"max_chunk_s: expected a positive duration in s or None, "
                             f"got {max_chunk_s!r}")
        self.stamp_offset_s = float(stamp_offset_s)
        self.transforms = dict(transforms or {})
        self.max_chunk_ns = None if max_chunk_s is None else int(max_chunk_s * 1e9)
        self._chunk_start_ns: int | None = None
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(self.path, "wb")
        self._writer = Writer(self._file, chunk_size=chunk_size,
                              compression=_COMPRESSION[compression])
        self._writer.start(profile="ros2", library="isac-twin")
        if metadata:
            self._writer.add_metadata(METADATA_NAME, {k: str(v) for k, v in metadata.items()})
        self._file.flush()
        self.clock_ns = clock_ns
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._seq: dict[str, int] = {}
        self._lock = threading.Lock()
        self._taps: list[tuple] = []
        self.messages = 0
        self.closed = False

    def write(self, topic: str, msg, *, log_time_ns: int | None = None,
              publish_time_ns: int | None = None) -> None:
        """Record ``msg`` (an isac_twin.bus.msgs / isac_twin_msgs dataclass) on ``topic``."""
        type_name = msg.ROS_TYPE
        f = self.transforms.get(type_name)
        if f is not None:
            msg = f(msg)
        if self.stamp_offset_s:
            msg = shift_stamps(msg, self.stamp_offset_s)
        data = cdr.encode(msg)
        lt = self.clock_ns() if log_time_ns is None else int(log_time_ns)
        if publish_time_ns is None:
            h = getattr(msg, "header", None)
            publish_time_ns = cdr.stamp_ns(h.stamp) if h is not None and h.stamp else lt
        with self._lock:
            if self.closed:
                return
            ch = self._channels.get(topic)
            if ch is None:
                sid = self._schemas.get(type_name)
                if sid is None:
                    sid = self._schemas[type_name] = self._writer.register_schema(
                        type_name, "ros2msg", cdr.msgdef(type_name).encode())
                ch = self._channels[topic] = self._writer.register_channel(
                    topic, "cdr", sid,
                    {"offered_qos_profiles": rosbag2_qos_yaml([qos_for(topic)])})
                self._seq[topic] = 0
            self._seq[topic] += 1
            if self._chunk_start_ns is None:
                self._chunk_start_ns = lt
            elif self.max_chunk_ns is not None and lt - self._chunk_start_ns >= self.max_chunk_ns:
                self._end_chunk()
                self._chunk_start_ns = lt
            self._writer.add_message(ch, lt, data, int(publish_time_ns), self._seq[topic])
            self.messages += 1
            self._file.flush()  # no-op unless a chunk was just written

    def _end_chunk(self) -> None:
        """Write the open chunk now (``Writer.flush`` finishes it and flushes the file)."""
        self._writer.flush()

    def attach(self, bus: Bus, topics: list[str] | None = None, *, prefix: str = "") -> None:
        """Record every topic of ``bus`` (or only ``topics``); :meth:`refresh` picks up
        topics registered later. ``prefix`` is prepended to the recorded topic names."""
        node = bus.node(f"recorder{len(self._taps) or ''}")
        self._taps.append((bus, node, set(), topics, prefix))
        self.refresh()

    def refresh(self) -> None:
        """Subscribe to topics that appeared on the attached buses since the last call."""
        for bus, node, seen, only, prefix in self._taps:
            for t in bus.registry().topics:
                if t.name in seen or (only is not None and t.name not in only):
                    continue
                seen.add(t.name)
                node.subscribe(t.name, t.type_name,
                               lambda m, name=prefix + t.name: self.write(name, m))

    def close(self) -> None:
        """Write the summary and footer (idempotent)."""
        with self._lock:
            if self.closed:
                return
            self.closed = True
            self._writer.finish()
            self._file.close()

    def __enter__(self) -> McapRecorder:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


@dataclass(frozen=True)
class CsiRecording:
    """How CSI (``isac_twin_msgs/Csi``, ``h[K, N, Nr, Nt]``) is recorded.

    The default keeps one OFDM symbol in 14 and one subcarrier in 16: within a
    14-symbol slot the channel changes only by Doppler (~1e-3 rad at walking speed)
    and the lab's 1024 subcarriers over-sample its delay spread; the lab's CSI
    goes from 3.78 MB to ~17 kB a message. The kept indices are
    ``k = 0, symbol_step, ...`` and ``n = 0, subcarrier_step, ...`` (recorded in the
    file's metadata); :meth:`full` records everything.

    Attributes:
        symbol_step, subcarrier_step: keep every ``step``-th symbol / subcarrier (>= 1).
        snr_db: add complex white Gaussian noise to each recorded message at this SNR,
            dB (noise power = the message's mean ``|h|^2`` / 10^(snr/10), i.i.d. over
            symbols, subcarriers and antenna pairs): a measured channel estimate instead
            of the twin's exact one. ``None`` (default): no noise.
        seed: seed of that noise.
    """

    symbol_step: int = 14
    subcarrier_step: int = 16
    snr_db: float | None = None
    seed: int = 0
    _rng: list = field(default_factory=list, compare=False, repr=False)

    def __post_init__(self):
        for name in ("symbol_step", "subcarrier_step"):
            v = getattr(self, name)
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise ValueError(f"CsiRecording.{name}: expected an integer >= 1, got {v!r}")
        if self.snr_db is not None and not (isinstance(self.snr_db, (int, float))
                                            and math.isfinite(self.snr_db)):
            raise ValueError(f"CsiRecording.snr_db: expected a finite number of dB or None, "
                             f"got {self.snr_db!r}")

    @classmethod
    def full(cls, **kw) -> CsiRecording:
        return cls(1, 1, **kw)

    def describe(self) -> str:
        out = f"symbols[::{self.symbol_step}], subcarriers[::{self.subcarrier_step}]"
        if self.snr_db is not None:
            out += f", noise at {self.snr_db:g} dB SNR (seed {self.seed})"
        return out

    def __call__(self, msg):
        h = np.asarray(msg.h)
        if h.ndim != 4 or (self.symbol_step == self.subcarrier_step == 1
                           and self.snr_db is None):
            return msg
        h = np.ascontiguousarray(h[::self.symbol_step, ::self.subcarrier_step])
        if self.snr_db is not None:
            if not self._rng:
                self._rng.append(np.random.default_rng(self.seed))
            rng = self._rng[0]
            sigma = math.sqrt(float(np.mean(np.abs(h) ** 2)) / 10 ** (self.snr_db / 10) / 2)
            h = (h + sigma * (rng.standard_normal(h.shape) + 1j * rng.standard_normal(h.shape))
                 ).astype(h.dtype if np.iscomplexobj(h) else np.complex128)
        return dataclasses.replace(msg, h=h)


# ------------------------------------------------------------------ recovery

def recover(path: str | Path, out: str | Path | None = None) -> tuple[Path, int]:
    """Rewrite a killed (unfinished) recording as a finished MCAP.

    Copies the header, schemas, channels, metadata and every message of the complete
    chunks of ``path`` into ``out`` (default ``<name>.recovered.mcap`` next to it) and
    writes the summary and footer, so indexed readers open it. ``path`` is not
    modified.

    Returns:
        ``(out, messages copied)``.
    Raises:
        ValueError: ``path`` is not an MCAP file (bad magic), naming it.
    """
    path = Path(path)
    out = Path(out) if out is not None else path.with_name(path.stem + ".recovered.mcap")
    if out.resolve() == path.resolve():
        raise ValueError(f"recover: the output must differ from the input ({path})")
    with open(path, "rb") as f:
        magic = f.read(8)
    if magic != b"\x89MCAP0\r\n":
        raise ValueError(f"{path}: not an MCAP file (first bytes {magic[:8]!r}, "
                         f"expected the MCAP magic 89 4d 43 41 50 30 0d 0a)")
    n = 0
    compression = CompressionType.ZSTD
    with open(path, "rb") as f, open(out, "wb") as g:
        w = Writer(g, compression=compression)
        started = False
        schema_ids: dict[int, int] = {}
        channel_ids: dict[int, int] = {}
        it = iter(StreamReader(f, skip_magic=False, emit_chunks=False).records)
        while True:
            try:
                rec = next(it)
            except StopIteration:
                break
            except Exception as exc:  # noqa: BLE001 - the truncated tail of a killed file
                log.info("%s: recovered %d messages; stopped at %s: %s", path, n,
                         type(exc).__name__, exc)
                break
            if isinstance(rec, McapHeader):
                w.start(profile=rec.profile, library=rec.library)
                started = True
            elif not started:
                continue
            elif isinstance(rec, Schema):
                schema_ids[rec.id] = w.register_schema(rec.name, rec.encoding, rec.data)
            elif isinstance(rec, Channel):
                channel_ids[rec.id] = w.register_channel(
                    rec.topic, rec.message_encoding, schema_ids.get(rec.schema_id, 0),
                    dict(rec.metadata))
            elif isinstance(rec, Metadata):
                w.add_metadata(rec.name, dict(rec.metadata))
            elif isinstance(rec, Message) and rec.channel_id in channel_ids:
                w.add_message(channel_ids[rec.channel_id], rec.log_time, rec.data,
                              rec.publish_time, rec.sequence)
                n += 1
        if not started:
            w.start(profile="ros2", library="isac-twin recover")
        w.finish()
    return out, n


# ------------------------------------------------------------------ reading

@dataclass
class RecordedMessage:
    """One message of a recording.

    Attributes:
        topic, type_name: channel topic and ROS type.
        log_time_ns, publish_time_ns: ns (see the module doc).
        data: CDR payload.
    """

    topic: str
    type_name: str
    log_time_ns: int
    publish_time_ns: int
    data: bytes

    def decode(self):
        """The engine dataclass (``isac_twin.bus.msgs`` / ``isac_twin_msgs``)."""
        return cdr.decode(self.data, self.type_name)


def read_messages(path: str | Path, topics: list[str] | None = None, *,
                  recover: bool = True) -> Iterator[RecordedMessage]:
    """Stream the messages of an MCAP file in file order.

    Args:
        topics: only these topics (default all).
        recover: stop quietly at a truncated or corrupt tail (a killed recording)
            instead of raising; what was read until then is returned.
    """
    schemas: dict[int, str] = {}
    channels: dict[int, tuple[str, str]] = {}
    with open(path, "rb") as f:
        reader = StreamReader(f, skip_magic=False, emit_chunks=False)
        it = iter(reader.records)
        n = 0
        while True:
            try:
                rec = next(it)
            except StopIteration:
                return
            except Exception as exc:  # noqa: BLE001 - truncated chunk, bad CRC, EOF
                if not recover:
                    raise
                log.info("%s: stopped at a damaged or truncated record after %d messages "
                         "(%s: %s)", path, n, type(exc).__name__, exc)
                return
            if isinstance(rec, Schema):
                schemas[rec.id] = rec.name
            elif isinstance(rec, Channel):
                channels[rec.id] = (rec.topic, schemas.get(rec.schema_id, ""))
            elif isinstance(rec, Message):
                topic, type_name = channels[rec.channel_id]
                if topics is None or topic in topics:
                    n += 1
                    yield RecordedMessage(topic, type_name, rec.log_time, rec.publish_time,
                                          bytes(rec.data))


def read_metadata(path: str | Path) -> dict[str, str]:
    """The ``isac_twin`` metadata record of a recording (empty if none)."""
    with open(path, "rb") as f:
        try:
            for rec in StreamReader(f, emit_chunks=False).records:
                if isinstance(rec, Metadata) and rec.name == METADATA_NAME:
                    return dict(rec.metadata)
                if isinstance(rec, Message):
                    break
        except Exception:  # noqa: BLE001
            pass
    return {}


# ------------------------------------------------------------------ twin recording

def record_twin(twin, steps: int, out: str | Path, *, rate_hz: float | None = None,
                chunk_size: int = 64 * 1024, compression: str = "zstd",
                metadata: dict | None = None, bridge=None,
                on_step: Callable | None = None, stamp_epoch_s: float = 0.0,
                csi: CsiRecording | None = None) -> McapRecorder:
    """Run ``twin`` for ``steps`` steps and record every topic of its bus plus, per
    step, one ``isac_twin_msgs/LinkMetrics`` per link on ``/twin/link_metrics`` and
    one ``isac_twin_msgs/LinkPaths`` per traced link on ``/twin/paths``.

    Log times are the twin's simulated time (ns) so a replay keeps its pace.

    Args:
        rate_hz: pace the steps in real time (default as fast as possible).
        stamp_epoch_s: the Unix time (s) of the twin's t = 0: stamps and log times
            become ``stamp_epoch_s + t`` (e.g. ``time.time()`` at the start, so the file
            lines up with real robots' logs); 0 keeps simulated seconds.
        csi: how ``/<robot>/csi`` is recorded (default :class:`CsiRecording`: compact).
        compression, chunk_size: see :class:`McapRecorder`.
        bridge: a :class:`~isac_twin.transport.bridge.TwinBridge` to step through
            (real robots mirrored; their ``/<robot>/real/*`` topics are recorded too).
    Returns:
        the closed recorder (``.messages`` counts what was written).
    """
    epoch = float(stamp_epoch_s)
    csi = csi if csi is not None else CsiRecording()
    now = {"ns": int(round((epoch + twin.time_s) * 1e9))}
    meta = {"kind": "twin", "dt": twin.dt, "seed": getattr(twin, "seed", 0),
            "scene": str(getattr(getattr(twin, "config", None), "folder", "") or ""),
            "stamp_epoch_s": repr(epoch), "csi": csi.describe()}
    meta.update(metadata or {})
    rec = McapRecorder(out, chunk_size=chunk_size, compression=compression,
                       clock_ns=lambda: now["ns"], metadata=meta, stamp_offset_s=epoch,
                       transforms={Csi.ROS_TYPE: csi})
    period = 1.0 / rate_hz if rate_hz else 0.0
    try:
        bus = None
        next_t = time.perf_counter()
        for _ in range(steps):
            if twin.bus is not bus:  # reset() replaces the bus
                bus = twin.bus
                rec.attach(bus)
            now["ns"] = int(round((epoch + twin.time_s + twin.dt) * 1e9))
            if bridge is not None:
                bridge.sync()
                rec.refresh()
            result = twin.step()
            rec.refresh()
            if bridge is not None:
                bridge.publish_step(result)
            t = result.time_s
            for ls in result.links.values():
                rec.write(LINKS_TOPIC, link_metrics_msg(ls, t))
                if ls.paths is not None:
                    rec.write(PATHS_TOPIC, link_paths_msg(ls.paths, t))
            if on_step is not None:
                on_step(result)
            if period:
                next_t += period
                time.sleep(max(0.0, next_t - time.perf_counter()))
        flush = getattr(twin, "flush_sensing", None)
        if flush is not None:  # a radar frame still out (Twin.sensing_worker): keep it
            flush()
    finally:
        rec.close()
    return rec


# ------------------------------------------------------------------ replay

def replay_to_bus(path: str | Path, bus: Bus, *, speed: float | None = 1.0,
                  topics: list[str] | None = None, node_name: str = "replay",
                  stop: threading.Event | None = None) -> int:
    """Re-publish a recording's messages on ``bus`` in recorded order.

    Args:
        speed: pace relative to the recorded log times (2 = twice as fast);
            ``None`` or 0 = as fast as possible.
        topics: only these topics.
        stop: set to end early.
    Returns:
        messages published.
    """
    node = bus.node(node_name)
    t0_rec = t0_wall = None
    n = 0
    for rm in read_messages(path, topics):
        if stop is not None and stop.is_set():
            break
        if rm.type_name not in MESSAGE_TYPES:
            continue
        if rm.topic not in node.advertised:
            node.advertise(rm.topic, rm.type_name)
        if speed:
            if t0_rec is None:
                t0_rec, t0_wall = rm.log_time_ns, time.perf_counter()
            due = t0_wall + (rm.log_time_ns - t0_rec) * 1e-9 / speed
            delay = due - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
        node.publish(rm.topic, rm.decode())
        n += 1
    return n


class Trajectory:
    """A robot's recorded poses: times ``[T]`` s and ``[T, 6]`` poses, interpolated."""

    def __init__(self, t: np.ndarray, poses: np.ndarray):
        order = np.argsort(t, kind="stable")
        self.t, self.poses = np.asarray(t, float)[order], np.asarray(poses, float)[order]
        self._yaw = np.unwrap(self.poses[:, 5])

    def __len__(self) -> int:
        return len(self.t)

    def at(self, t: float) -> tuple[np.ndarray, float, float]:
        """``(pose [6], v m/s, w rad/s)`` at time ``t`` s (clamped to the recorded span)."""
        x = np.interp(t, self.t, self.poses[:, 0])
        y = np.interp(t, self.t, self.poses[:, 1])
        z = np.interp(t, self.t, self.poses[:, 2])
        yaw = float(np.interp(t, self.t, self._yaw))
        v = w = 0.0
        if len(self.t) > 1:
            k = int(np.clip(np.searchsorted(self.t, t) , 1, len(self.t) - 1))
            dt = self.t[k] - self.t[k - 1]
            if dt > 0:
                dx, dy = self.poses[k, :2] - self.poses[k - 1, :2]
                v = float(math.hypot(dx, dy) / dt) * (1.0 if (
                    dx * math.cos(yaw) + dy * math.sin(yaw)) >= 0 else -1.0)
                w = float((self._yaw[k] - self._yaw[k - 1]) / dt)
        yaw = wrap_angle(yaw)
        return np.array([x, y, z, 0.0, 0.0, yaw]), v, w


def load_trajectories(path: str | Path) -> dict[str, Trajectory]:
    """``robot -> Trajectory`` from the ``/<robot>/ground_truth`` topics of a recording
    (times are the messages' header stamps, s)."""
    data: dict[str, tuple[list, list]] = {}
    for rm in read_messages(path):
        if rm.type_name != PoseStamped.ROS_TYPE or not rm.topic.endswith("/ground_truth"):
            continue
        robot = rm.topic.strip("/").split("/")[0]
        ps = rm.decode()
        q = ps.pose.orientation
        pose = [*ps.pose.position, 0.0, 0.0, quaternion_to_yaw(q)]
        ts, ps_ = data.setdefault(robot, ([], []))
        ts.append(ps.header.stamp)
        ps_.append(pose)
    return {r: Trajectory(np.array(t), np.array(p)) for r, (t, p) in data.items()}


class TrajectoryReplay:
    """Drive a twin's robots along recorded trajectories.

    Attaches to ``twin`` through its state-source hook
    (:meth:`isac_twin.twin.twin.Twin.set_state_source`): each replayed robot is placed at
    its recorded pose (and recorded speed) at ``t`` and publishes ``ground_truth``
    and its scene sensors (LiDAR, camera); its controller does not run. Then
    ``twin.step()`` re-traces all links along the recording. :meth:`detach`
    returns the robots to simulation.

    Args:
        twin: the twin (its robots must be named as in the recording).
        path: the recording.
    """

    def __init__(self, twin, path: str | Path):
        self.twin = twin
        self.trajectories = {r: tr for r, tr in load_trajectories(path).items()
                             if r in twin.agents}
        if not self.trajectories:
            raise ValueError(f"{path}: no /<robot>/ground_truth of the twin's robots "
                             f"({', '.join(twin.agents)}) in the recording")
        for r, traj in self.trajectories.items():
            twin.set_state_source(r, self.source(traj))

    @property
    def steps(self) -> int:
        """Recorded samples of the longest trajectory."""
        return max(len(t) for t in self.trajectories.values())

    @staticmethod
    def source(traj: Trajectory):
        """``source(t, dt) -> KinematicState`` along ``traj`` (a twin state source)."""
        from ..robots.kinematics import KinematicState

        def state_at(t: float, dt: float) -> KinematicState:
            pose, v, w = traj.at(t)
            return KinematicState(pose=pose, v=v, w=w, t=t)

        return state_at

    def detach(self) -> None:
        """Return the replayed robots to simulation."""
        for r in self.trajectories:
            self.twin.set_state_source(r, None)
