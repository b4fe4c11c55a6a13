"""The twin's side of the network: mirror real robots into a :class:`~isac_twin.twin.twin.Twin`.

:class:`TwinBridge` attaches to a twin without changing ``twin.py``. It owns
a second bus whose transport is the network (zenoh) and, per real robot
``<name>`` (a robot device of the twin with the same name):

* **receives** ``/<name>/pose_estimate``, ``/<name>/odom`` and ``/<name>/scan``
  from the robot runtime (:mod:`isac_twin.devices.runtime`), re-publishes them on the
  twin's bus as ``/<name>/real/pose_estimate``, ``/<name>/real/odom`` and
  ``/<name>/real/scan`` (beside the twin's synthetic ``/<name>/odom``,
  ``/<name>/scan``; recorders and the live view see both), and the robots'
  ``/diagnostics`` as they are (their statuses are named ``<name>: ...``;
  :meth:`TwinBridge.status` lists the newest per robot);
* **sends** the twin's control ``/<name>/cmd_vel`` (what the twin's controller
  for that robot publishes, when ``send_cmd_vel``), path commands
  (:meth:`TwinBridge.send_path`) and fingerprints (the step's localization
  estimate, :meth:`TwinBridge.publish_step`);
* **shares** (``share``) the twin's own topics with the network, so a stock ROS 2
  node on rmw_zenoh sees the twin: ``share="all"`` or a list of topics (``/tf``,
  ``/tf_static``, ``/clock``, ``/robot2/scan``, ...), renamed ``share_prefix +
  topic`` (``/twin/robot1/scan``; ``""`` keeps the names, refused for a topic the
  bridge itself exchanges with a real robot) and, with ``share_stamps="wall"``,
  stamped on the wall clock (the twin's t = 0 is the bridge's creation time).

Fusion (stage 1 of Algorithm 1, before each step, :meth:`TwinBridge.sync`):
the twin's simulated pose of a mirrored robot is corrected towards the real
robot's published estimate::

    est_local  = estimate stamped at t_r on the robot's clock, moved to the twin's
                 clock with the ClockProbe offset, then extrapolated to now with the
                 robot's odometry twist (v, w) over the age (capped at max_extrapolation_s)
    pose_twin <- pose_twin + gain * (est_local - pose_twin)     (x, y; yaw on the circle)

with ``gain = 1`` (snap) for the first sample and for the first sample after a
gap longer than ``stale_s`` (the twin *catches up* after a partition), and
``FusionConfig.gain`` (default 0.5) otherwise. While no fresh data arrives the
twin runs the robot on its own motion model (synthetic source only) and
:meth:`TwinBridge.status` reports it stale.

Use::

    bridge = TwinBridge(twin, ZenohTransport(ZenohConfig(connect=["tcp/127.0.0.1:7448"])))
    for _ in range(n):
        result = bridge.step()       # sync(); twin.step(); publish_step(result)
    bridge.close()
"""

from __future__ import annotations

import logging
import math
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from ..bus.bus import Bus
from ..bus.msgs import (
    DiagnosticArray,
    Header,
    LaserScan,
    Odometry,
    PoseStamped,
    Twist,
    shift_stamps,
)
from ..bus.twin_msgs import Fingerprint, PathCommand
from ..utils.geometry import quaternion_to_yaw, wrap_angle
from .clock import ClockProbe

log = logging.getLogger(__name__)


@dataclass
class FusionConfig:
    """How real robot estimates correct the twin's simulated robots.

    Attributes:
        gain: 0..1 share of the error corrected per step (1 = the real robot's estimate
            replaces the twin's pose; 0 = mirror only, no correction).
        stale_s: s without an estimate before a robot counts as disconnected; the next
            sample after such a gap is applied with gain 1 (catch-up).
        max_extrapolation_s: cap of the latency compensation, s.
        source: ``"pose_estimate"`` (the isac-twin robot runtime's map-frame estimate) or
            ``"odom"`` (a plain ROS 2 robot, e.g. ``turtlebot3_node`` under rmw_zenoh: its
            ``/<name>/odom`` composed with the robot's initial pose in the twin).
    """

    gain: float = 0.5
    stale_s: float = 1.0
    max_extrapolation_s: float = 0.5
    source: str = "pose_estimate"


@dataclass
class MirrorState:
    """What the bridge knows of one real robot.

    Attributes:
        estimate: last ``[x, y, yaw]`` (m, rad, map frame), or None.
        stamp_local: its stamp on the twin's clock, s.
        velocity: ``(v m/s, w rad/s)`` from the robot's last odometry.
        received: estimates received. corrections: steps a correction was applied.
        catchups: corrections applied with gain 1 after a gap.
        last_receive: local monotonic time of the last estimate, s.
    """

    estimate: np.ndarray | None = None
    stamp_local: float = 0.0
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(2))
    received: int = 0
    scans: int = 0
    corrections: int = 0
    catchups: int = 0
    last_receive: float = -math.inf
    last_applied: float = -math.inf
    fresh: bool = False


class TwinBridge:
    """Mirror real robots into a twin over a network transport.

    Args:
        twin: an :class:`isac_twin.twin.twin.Twin` (or anything with ``agents``, ``bus``, ``step``).
        transport: the network transport (e.g. :class:`ZenohTransport`); the bridge owns it.
        robots: names of the twin's robots that have a real counterpart (default all).
        fusion: :class:`FusionConfig`.
        send_cmd_vel: forward the twin's ``cmd_vel`` of each robot to the real robot.
        clock_period_s: s between clock pings (0 disables the probe).
        share: the twin's topics to publish on the network: ``"all"``, a list, or None.
        share_prefix: prepended to shared topic names (``"/twin"``; ``""`` keeps them).
        share_stamps: ``"wall"`` (stamps + the wall-clock time of the twin's t = 0)
            or ``"sim"`` (simulated seconds, with ``/clock`` for ``use_sim_time`` nodes).
    """

    def __init__(self, twin, transport, *, robots: list[str] | None = None,
                 fusion: FusionConfig | None = None, send_cmd_vel: bool = True,
                 clock_period_s: float = 0.5, name: str = "twin",
                 share: str | list[str] | None = None, share_prefix: str = "/twin",
                 share_stamps: str = "wall"):
        self.twin = twin
        self.transport = transport
        self.fusion = fusion or FusionConfig()
        self.send_cmd_vel = send_cmd_vel
        self.robots = list(robots if robots is not None else twin.agents)
        for r in self.robots:
            if r not in twin.agents:
                raise KeyError(f"no robot named {r!r} in the twin (robots: {', '.join(twin.agents)})")
        if share is not None and share != "all" and not isinstance(share, (list, tuple)):
            raise ValueError(f"share: expected 'all', a list of topics or None, got {share!r}")
        if share_stamps not in ("wall", "sim"):
            raise ValueError(f"share_stamps: expected 'wall' or 'sim', got {share_stamps!r}")
        if share_prefix and (not share_prefix.startswith("/") or share_prefix.endswith("/")):
            raise ValueError(f"share_prefix: expected '' or '/name', got {share_prefix!r}")
        self.share, self.share_prefix = share, share_prefix
        #: added to shared stamps, s (the wall-clock time of the twin's t = 0)
        self.share_offset_s = (time.time() - float(getattr(twin, "time_s", 0.0))
                               if share_stamps == "wall" else 0.0)
        self._own_net = {f"/{r}/{k}" for r in self.robots
                         for k in ("cmd_vel", "path", "fingerprint", "pose_estimate", "odom",
                                   "scan")}
        if isinstance(share, (list, tuple)):
            for t in share:
                self._check_share(t)
        self.net = Bus(transport=transport)
        self.node = self.net.node(f"{name}/bridge")
        self.mirrors: dict[str, MirrorState] = {r: MirrorState() for r in self.robots}
        if self.fusion.source not in ("pose_estimate", "odom"):
            raise ValueError(f"fusion source: expected pose_estimate or odom, "
                             f"got {self.fusion.source!r}")
        #: map -> odom of each robot for ``source = "odom"``: its initial pose in the twin
        self.odom_origin = {r: twin.agents[r].state.pose[[0, 1, 5]].astype(float).copy()
                            for r in self.robots}
        self._lock = threading.Lock()
        self._inbox: list[tuple[str, str, object]] = []
        for r in self.robots:
            ns = f"/{r}"
            self.node.advertise(f"{ns}/cmd_vel", Twist)
            self.node.advertise(f"{ns}/path", PathCommand)
            self.node.advertise(f"{ns}/fingerprint", Fingerprint)
            self.node.subscribe(f"{ns}/pose_estimate", PoseStamped,
                                lambda m, r=r: self._on_net(r, "pose_estimate", m))
            self.node.subscribe(f"{ns}/odom", Odometry, lambda m, r=r: self._on_net(r, "odom", m))
            self.node.subscribe(f"{ns}/scan", LaserScan, lambda m, r=r: self._on_net(r, "scan", m))
        self.diagnostics: dict[str, tuple[int, str]] = {}  #: status name -> (level, message), newest
        self.node.subscribe("/diagnostics", DiagnosticArray, self._on_diagnostics)
        self.clock = ClockProbe(self.net, name, period_s=clock_period_s or 1.0)
        if clock_period_s:
            self.clock.start()
        self._shared: set[str] = set()
        self._twin_bus = None
        self._attach_twin_bus()

    # ------------------------------------------------------------ twin bus
    def _attach_twin_bus(self) -> None:
        """(Re)create the bridge's nodes on the twin's bus (twin.reset() replaces the bus)."""
        bus = self.twin.bus
        if bus is self._twin_bus:
            return
        self._twin_bus = bus
        self._tnode = bus.node("bridge")
        self._tnode.advertise("/diagnostics", DiagnosticArray)
        for r in self.robots:
            ns = f"/{r}"
            self._tnode.advertise(f"{ns}/real/pose_estimate", PoseStamped)
            self._tnode.advertise(f"{ns}/real/odom", Odometry)
            self._tnode.advertise(f"{ns}/real/scan", LaserScan)
            if self.send_cmd_vel:
                self._tnode.subscribe(f"{ns}/cmd_vel", Twist,
                                      lambda m, r=r: self._forward_cmd(r, m))
        self._shared = set()
        self.refresh_shared()

    def _check_share(self, topic: str) -> bool:
        """Whether ``topic`` may be shared; ValueError for a name clash with a real robot."""
        if "/real/" in topic:
            return False  # the real robots' own data, re-published on the twin's bus
        if self.share_prefix + topic in self._own_net:
            raise ValueError(f"share: {topic!r} would be published as "
                             f"{self.share_prefix + topic!r}, which the bridge exchanges with "
                             f"the real robot; use share_prefix (e.g. '/twin')")
        return True

    def refresh_shared(self) -> None:
        """Start sharing topics of the twin's bus that appeared since the last call
        (called on every :meth:`sync` and :meth:`publish_step`)."""
        if self.share is None:
            return
        for t in self._twin_bus.registry().topics:
            if t.name in self._shared:
                continue
            if self.share != "all" and t.name not in self.share:
                continue
            self._shared.add(t.name)
            if self.share == "all":
                try:
                    if not self._check_share(t.name):
                        continue
                except ValueError:
                    log.info("not sharing %s: it is exchanged with the real robot", t.name)
                    continue
            elif not self._check_share(t.name):
                continue
            out = self.share_prefix + t.name
            self.node.advertise(out, t.type_name)
            self._tnode.subscribe(t.name, t.type_name, lambda m, out=out: self._share_out(out, m))

    def _share_out(self, topic: str, msg) -> None:
        if self.share_offset_s:
            msg = shift_stamps(msg, self.share_offset_s)
        self.node.publish(topic, msg)

    def _forward_cmd(self, robot: str, msg: Twist) -> None:
        self.node.publish(f"/{robot}/cmd_vel", msg)

    # ------------------------------------------------------------ network in
    def _on_net(self, robot: str, kind: str, msg) -> None:
        st = self.mirrors[robot]
        now = time.monotonic()
        with self._lock:
            if kind == self.fusion.source:
                p = msg.pose  # Odometry.pose and PoseStamped.pose are both a Pose
                est = np.array([p.position[0], p.position[1], quaternion_to_yaw(p.orientation)])
                if kind == "odom":
                    est = _compose(self.odom_origin[robot], est)
                st.estimate = est
                st.stamp_local = self.clock.to_local(robot, msg.header.stamp)
                st.received += 1
                st.last_receive = now
                st.fresh = True
            if kind == "odom":
                st.velocity = np.array([msg.twist.linear[0], msg.twist.angular[2]])
            elif kind == "scan":
                st.scans += 1
            self._inbox.append((robot, kind, msg))

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        with self._lock:
            for st in msg.status:
                self.diagnostics[st.name] = (int(st.level), st.message)
            self._inbox.append(("", "diagnostics", msg))

    # ------------------------------------------------------------ per step
    def sync(self) -> None:
        """Before a twin step: re-publish received real data on the twin's bus and fuse
        the newest real estimates into the twin's robot poses (see the module doc)."""
        self._attach_twin_bus()
        self.refresh_shared()
        with self._lock:
            inbox, self._inbox = self._inbox, []
        for robot, kind, msg in inbox:
            self._tnode.publish("/diagnostics" if kind == "diagnostics" else f"/{robot}/real/{kind}", msg)
        now_wall, now = time.time(), time.monotonic()
        for robot in self.robots:
            st = self.mirrors[robot]
            with self._lock:
                if not st.fresh or st.estimate is None:
                    continue
                est, stamp, vel = st.estimate.copy(), st.stamp_local, st.velocity.copy()
                st.fresh = False
                gap = now - st.last_applied
                st.last_applied = now
            age = float(np.clip(now_wall - stamp, 0.0, self.fusion.max_extrapolation_s))
            est = _extrapolate(est, vel, age)
            catchup = gap > self.fusion.stale_s
            gain = 1.0 if catchup else self.fusion.gain
            self._correct(robot, est, gain)
            st.corrections += 1
            if catchup:
                st.catchups += 1
                log.info("%s: real estimate applied in full (first or after %.1f s gap)",
                         robot, gap if math.isfinite(gap) else 0.0)

    def _correct(self, robot: str, est: np.ndarray, gain: float) -> None:
        if gain <= 0:
            return
        state = self.twin.agents[robot].robot.state
        pose = state.pose
        pose[0] += gain * (est[0] - pose[0])
        pose[1] += gain * (est[1] - pose[1])
        dyaw = wrap_angle(est[2] - pose[5])
        pose[5] = wrap_angle(pose[5] + gain * dyaw)

    def publish_step(self, result) -> None:
        """After a twin step: send each mirrored robot the step's localization estimate
        as a :class:`Fingerprint` (when the twin's estimators produced one)."""
        self.refresh_shared()
        for robot in self.robots:
            rs = result.robots.get(robot)
            if rs is None or rs.estimate is None:
                continue
            self.node.publish(f"/{robot}/fingerprint", Fingerprint(
                header=Header(stamp=time.time(), frame_id="map"), robot=robot,
                estimate=np.asarray(rs.estimate, float)[:3], confidence=1.0))

    def step(self):
        """``sync()``, ``twin.step()``, ``publish_step()``; returns the StepResult."""
        self.sync()
        result = self.twin.step()
        self.publish_step(result)
        return result

    def send_path(self, robot: str, spec: dict | None) -> None:
        """Send a path (twin path spec dict, None = stop) for the real robot to follow itself."""
        msg = PathCommand.from_spec(spec or {"kind": "stop"}, stamp=time.time())
        self.node.publish(f"/{robot}/path", msg)

    def status(self) -> dict[str, dict]:
        """Per robot: connected (fresh within ``stale_s``), counters, clock offset (s),
        ``diagnostics``: component -> (level, message) from its newest ``/diagnostics``."""
        now = time.monotonic()
        out = {}
        for r, st in self.mirrors.items():
            out[r] = {"connected": now - st.last_receive <= self.fusion.stale_s,
                      "received": st.received, "scans": st.scans,
                      "corrections": st.corrections, "catchups": st.catchups,
                      "clock_offset_s": self.clock.offset_s(r),
                      "estimate": None if st.estimate is None else st.estimate.tolist(),
                      "diagnostics": {k.split(": ", 1)[1]: v for k, v in self.diagnostics.items()
                                      if k.startswith(f"{r}: ")}}
        return out

    def close(self) -> None:
        """Stop the clock probe and close the transport."""
        self.clock.stop()
        self.transport.close()

    def __enter__(self) -> TwinBridge:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _compose(origin: np.ndarray, local: np.ndarray) -> np.ndarray:
    """``origin (+) local`` for planar poses ``[x, y, yaw]``."""
    ox, oy, oyaw = origin
    x, y, yaw = local
    c, s = math.cos(oyaw), math.sin(oyaw)
    return np.array([ox + c * x - s * y, oy + s * x + c * y,
                     wrap_angle(oyaw + yaw)])


def _extrapolate(est: np.ndarray, vel: np.ndarray, dt: float) -> np.ndarray:
    """Pose ``[x, y, yaw]`` moved by a constant twist ``(v, w)`` for ``dt`` s (arc)."""
    x, y, yaw = est
    v, w = vel
    if dt <= 0:
        return est
    if abs(w) < 1e-9:
        return np.array([x + v * dt * math.cos(yaw), y + v * dt * math.sin(yaw), yaw])
    yaw2 = yaw + w * dt
    r = v / w
    return np.array([x + r * (math.sin(yaw2) - math.sin(yaw)),
                     y - r * (math.cos(yaw2) - math.cos(yaw)),
                     wrap_angle(yaw2)])
