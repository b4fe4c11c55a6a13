"""MCAP recording and replay of bus topics (the ``ros2 bag`` format).

Files are MCAP with profile ``ros2``: one schema per message type (encoding
``ros2msg``, the full ``.msg`` text with dependencies, ``isac_twin_msgs``
included), channels with message encoding ``cdr``, payloads CDR with the
encapsulation header. Foxglove, ``ros2 bag`` (rosbag2_storage_mcap) and
``mcap_ros2.reader`` read them.

Crash safety: the writer is chunked (``chunk_size`` bytes, default 64 KiB)
and the file is flushed after every completed chunk, so a process killed at
any point leaves a file whose complete chunks are readable:
:func:`read_messages` streams the file and stops cleanly at the first
truncated record (no footer or summary needed).

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

import logging
import math
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from mcap.stream_reader import StreamReader
from mcap.records import Channel, Message, Metadata, Schema
from mcap.writer import CompressionType, Writer

from engine.bus import Bus
from engine.msgs import MESSAGE_TYPES, PoseStamped, quaternion_to_yaw
from engine.transport import cdr
from engine.transport.twin_msgs import link_metrics_msg, link_paths_msg

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
        compression: ``"none"`` (default), ``"zstd"`` or ``"lz4"``.
        clock_ns: the log-time clock, ns (default wall clock).
        metadata: written as an MCAP metadata record named ``isac_twin``.
    """

    def __init__(self, path: str | Path, *, chunk_size: int = 64 * 1024,
                 compression: str = "none", clock_ns: Callable[[], int] = time.time_ns,
                 metadata: dict | None = None):
        if compression not in _COMPRESSION:
            raise ValueError(f"compression: expected one of {sorted(_COMPRESSION)}, "
                             f"got {compression!r}")
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
        """Record ``msg`` (an engine.msgs / isac_twin_msgs dataclass) on ``topic``."""
        type_name = msg.ROS_TYPE
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
                    topic, "cdr", sid, {"offered_qos_profiles": ""})
                self._seq[topic] = 0
            self._seq[topic] += 1
            self._writer.add_message(ch, lt, data, int(publish_time_ns), self._seq[topic])
            self.messages += 1
            self._file.flush()  # no-op unless a chunk was just written

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
        """The engine dataclass (``engine.msgs`` / ``isac_twin_msgs``)."""
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
                chunk_size: int = 64 * 1024, compression: str = "none",
                metadata: dict | None = None, bridge=None,
                on_step: Callable | None = None) -> McapRecorder:
    """Run ``twin`` for ``steps`` steps and record every topic of its bus plus, per
    step, one ``isac_twin_msgs/LinkMetrics`` per link on ``/twin/link_metrics`` and
    one ``isac_twin_msgs/LinkPaths`` per traced link on ``/twin/paths``.

    Log times are the twin's simulated time (ns) so a replay keeps its pace.

    Args:
        rate_hz: pace the steps in real time (default as fast as possible).
        bridge: a :class:`~engine.transport.bridge.TwinBridge` to step through
            (real robots mirrored; their ``/<robot>/real/*`` topics are recorded too).
    Returns:
        the closed recorder (``.messages`` counts what was written).
    """
    now = {"ns": int(round(twin.time_s * 1e9))}
    meta = {"kind": "twin", "dt": twin.dt, "seed": getattr(twin, "seed", 0),
            "scene": str(getattr(getattr(twin, "config", None), "folder", "") or "")}
    meta.update(metadata or {})
    rec = McapRecorder(out, chunk_size=chunk_size, compression=compression,
                       clock_ns=lambda: now["ns"], metadata=meta)
    period = 1.0 / rate_hz if rate_hz else 0.0
    try:
        bus = None
        next_t = time.perf_counter()
        for _ in range(steps):
            if twin.bus is not bus:  # reset() replaces the bus
                bus = twin.bus
                rec.attach(bus)
            now["ns"] = int(round((twin.time_s + twin.dt) * 1e9))
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
        yaw = math.atan2(math.sin(yaw), math.cos(yaw))
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
    (:meth:`engine.twin.Twin.set_state_source`): each replayed robot is placed at
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
        from engine.robots.kinematics import KinematicState

        def state_at(t: float, dt: float) -> KinematicState:
            pose, v, w = traj.at(t)
            return KinematicState(pose=pose, v=v, w=w, t=t)

        return state_at

    def detach(self) -> None:
        """Return the replayed robots to simulation."""
        for r in self.trajectories:
            self.twin.set_state_source(r, None)
