"""The robot runtime: what runs on the robot's own computer (``isac-twin robot robot.toml``).

Pipeline on the robot::

    OpenCR (serial) --odom/imu/battery--+                     +--> zenoh: /<name>/odom, imu,
    RPLIDAR (serial) --scan-------------+--> bus (zenoh) -----+    battery_state, scan,
    OAK-D (optional) --images-----------+        |                 pose_estimate
                                                 v
                  PoseEstimator: map pose = initial pose (+) wheel odometry,
                                 nudged by the twin's fingerprint fixes
                                                 |
    zenoh: /<name>/cmd_vel, /<name>/path, ------>+--> Controller (rate_hz): local path
           /<name>/fingerprint                        following (pure pursuit on the estimate),
                                                      else the twin's cmd_vel while fresh,
                                                      else stop --> OpenCR cmd_vel

The robot keeps running on its own when the network is gone: a path it was
given is followed to the end on its own estimate; a bare ``cmd_vel`` stream
from the twin times out after ``cmd_timeout_s`` and the robot stops (the
OpenCR firmware would also zero it after 500 ms).

``robot.toml``::

    [robot]
    name = "robot1"            # topic namespace; must match the twin's device name
    model = "burger"           # burger | waffle
    initial_pose = [1.0, 1.0, 0.0]   # x m, y m, yaw rad in the twin's map frame
    emulated = false           # true: pty emulators fed by a simulated robot
    frame_prefix = false       # true: frames "<name>/odom", ... (several robots, one domain)

    [drivers]                  # real devices (ignored when emulated = true)
    opencr = "/dev/ttyACM0"    # path or pyserial URL
    rplidar = "/dev/ttyUSB0"
    rplidar_baudrate = 115200
    oakd = false               # true, or a device MxId string (emulated: generated frames replayed)

    [emulation]                # used when emulated = true
    room = [6.0, 4.0]          # rectangle [0, W] x [0, D] m the emulated LiDAR sees
    lidar_rate_hz = 5.5

    [network]                  # zenoh (see isac_twin.transport.zenoh_transport)
    mode = "peer"
    listen = ["tcp/127.0.0.1:7448"]
    connect = []
    domain_id = 0
    distro = "jazzy"

    [control]
    rate_hz = 20.0
    cmd_timeout_s = 0.5
    lookahead = 0.25           # m, pure pursuit

    [estimation]
    fingerprint_gain = 0.3     # share of a fingerprint fix's error corrected at once
"""

from __future__ import annotations

import logging
import math
import threading
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..bus import frames
from ..bus.bus import Bus
from ..bus.msgs import (
    BatteryState,
    DiagnosticArray,
    DiagnosticStatus,
    Header,
    Imu,
    LaserScan,
    Odometry,
    Pose,
    PoseStamped,
    TFMessage,
    Twist,
)
from ..bus.twin_msgs import Fingerprint, PathCommand
from ..contract import schema
from ..errors import RobotConfigError
from ..robots.control import controller_from_spec
from ..robots.kinematics import robot_spec
from ..transport.clock import ClockResponder
from ..transport.zenoh_transport import ZenohConfig, ZenohTransport
from ..utils.geometry import quaternion_to_yaw, wrap_angle, yaw_to_quaternion

log = logging.getLogger(__name__)

#: ROS' global diagnostics topic; each robot's statuses are named ``<robot>: <component>``.
DIAGNOSTICS_TOPIC = "/diagnostics"


@dataclass
class RobotConfig:
    """A parsed ``robot.toml`` (see the module docstring for the file format)."""

    name: str = "robot1"
    model: str = schema.DEFAULT_ROBOT_MODEL
    initial_pose: tuple[float, float, float] = (0.0, 0.0, 0.0)  #: x m, y m, yaw rad (map)
    emulated: bool = False
    frame_prefix: bool = False  #: frames "<name>/odom", ... (isac_twin.bus.frames)
    opencr: str = "/dev/ttyACM0"
    rplidar: str | None = "/dev/ttyUSB0"
    rplidar_baudrate: int = 115200
    oakd: bool | str = False
    room: tuple[float, float] = (6.0, 4.0)  #: m, emulated LiDAR's rectangle
    lidar_rate_hz: float = 5.5
    network: ZenohConfig = field(default_factory=ZenohConfig)
    rate_hz: float = 20.0
    cmd_timeout_s: float = 0.5
    lookahead: float = 0.25
    fingerprint_gain: float = 0.3


def load_robot_config(path: str | Path) -> RobotConfig:
    """Read and validate a ``robot.toml``.

    Raises:
        RobotConfigError: unreadable file, unknown section/key or a bad value.
    """
    path = Path(path)
    try:
        raw = path.read_bytes()
        doc = tomllib.loads(raw.decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise RobotConfigError(f"{path}: not UTF-8 (byte 0x{raw[exc.start]:02x} at offset {exc.start})") from None
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise RobotConfigError(f"{path}: {exc}") from None
    return robot_config_from_dict(doc, str(path))


#: Serial rates of the RPLIDAR family (Slamtec: A1/A2M8, A2M7/A2M12/A3/S1, C1, S2/S3).
RPLIDAR_BAUDRATES = (115200, 256000, 460800, 1000000)

_KEYS = {"robot": {"name", "model", "initial_pose", "emulated", "frame_prefix"},
         "drivers": {"opencr", "rplidar", "rplidar_baudrate", "oakd"},
         "emulation": {"room", "lidar_rate_hz"},
         "network": {"mode", "listen", "connect", "domain_id", "distro", "multicast"},
         "control": {"rate_hz", "cmd_timeout_s", "lookahead"},
         "estimation": {"fingerprint_gain"}}


def robot_config_from_dict(doc: dict, where: str = "robot.toml") -> RobotConfig:
    """A :class:`RobotConfig` from the parsed TOML document ``doc``."""
    for sec, body in doc.items():
        if sec not in _KEYS or not isinstance(body, dict):
            raise RobotConfigError(f"{where}: unknown section [{sec}] "
                                   f"(expected {', '.join(_KEYS)})")
        for k in body:
            if k not in _KEYS[sec]:
                raise RobotConfigError(f"{where}: [{sec}] unknown key {k!r} "
                                       f"(expected {', '.join(sorted(_KEYS[sec]))})")
    r, d, e = doc.get("robot", {}), doc.get("drivers", {}), doc.get("emulation", {})
    n, c, s = doc.get("network", {}), doc.get("control", {}), doc.get("estimation", {})

    def num(sec, body, key, default, lo=None):
        v = body.get(key, default)
        if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v) \
                or (lo is not None and v <= lo):
            raise RobotConfigError(f"{where}: [{sec}] {key} = {v!r}: expected a number"
                                   + (f" > {lo}" if lo is not None else ""))
        return float(v)

    name = r.get("name", "robot1")
    if not isinstance(name, str) or not name or "/" in name:
        raise RobotConfigError(f"{where}: [robot] name = {name!r}: expected a non-empty name "
                               "without '/'")
    model = r.get("model", schema.DEFAULT_ROBOT_MODEL)
    if model not in schema.ROBOT_MODELS:
        raise RobotConfigError(f"{where}: [robot] model = {model!r}: expected "
                               f"{' or '.join(schema.ROBOT_MODELS)}")
    pose = r.get("initial_pose", [0.0, 0.0, 0.0])
    if not (isinstance(pose, list) and len(pose) == 3
            and all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in pose)):
        raise RobotConfigError(f"{where}: [robot] initial_pose = {pose!r}: expected [x, y, yaw], finite numbers")
    emulated = r.get("emulated", False)
    if not isinstance(emulated, bool):
        raise RobotConfigError(f"{where}: [robot] emulated = {emulated!r}: expected true or false")
    opencr = d.get("opencr", "/dev/ttyACM0")
    if not isinstance(opencr, str) or not opencr:
        raise RobotConfigError(f"{where}: [drivers] opencr = {opencr!r}: expected a port path or pyserial URL")
    rplidar = d.get("rplidar", "/dev/ttyUSB0")
    if not isinstance(rplidar, str):
        raise RobotConfigError(f"{where}: [drivers] rplidar = {rplidar!r}: expected a port path or pyserial URL "
                               "(\"\" for none)")
    baud = d.get("rplidar_baudrate", 115200)
    if baud not in RPLIDAR_BAUDRATES or isinstance(baud, bool):
        raise RobotConfigError(f"{where}: [drivers] rplidar_baudrate = {baud!r}: expected one of "
                               f"{', '.join(map(str, RPLIDAR_BAUDRATES))} (A1/A2M8, A2M7/A3, C1, S2/S3)")
    oakd = d.get("oakd", False)
    if not isinstance(oakd, (bool, str)):
        raise RobotConfigError(f"{where}: [drivers] oakd = {oakd!r}: expected true, false or a device MxId")
    prefix = r.get("frame_prefix", False)
    if not isinstance(prefix, bool):
        raise RobotConfigError(f"{where}: [robot] frame_prefix = {prefix!r}: expected true or "
                               "false")
    room = e.get("room", [6.0, 4.0])
    if not (isinstance(room, list) and len(room) == 2 and all(
            isinstance(x, (int, float)) and x > 0 for x in room)):
        raise RobotConfigError(f"{where}: [emulation] room = {room!r}: expected [W, D] m > 0")
    for key in ("listen", "connect"):
        eps = n.get(key, [])
        if not (isinstance(eps, list) and all(isinstance(x, str) and "/" in x for x in eps)):
            raise RobotConfigError(f"{where}: [network] {key} = {eps!r}: expected a list of "
                                   "endpoints like \"tcp/127.0.0.1:7448\"")
        for ep in eps:
            port = ep.rsplit(":", 1)[-1] if ":" in ep.split("/", 1)[1] else ""
            if port and not (port.isdigit() and 0 <= int(port) <= 65535):
                raise RobotConfigError(f"{where}: [network] {key}: {ep!r} has port {port}: expected 0..65535")
    domain_id = n.get("domain_id", 0)
    if not isinstance(domain_id, int) or isinstance(domain_id, bool) or not 0 <= domain_id <= 232:
        raise RobotConfigError(f"{where}: [network] domain_id = {domain_id!r}: expected an integer 0..232 "
                               "(ROS_DOMAIN_ID)")
    multicast = n.get("multicast", False)
    if not isinstance(multicast, bool):
        raise RobotConfigError(f"{where}: [network] multicast = {multicast!r}: expected true or false")
    net = ZenohConfig(mode=n.get("mode", "peer"), listen=list(n.get("listen", [])),
                      connect=list(n.get("connect", [])), multicast=multicast,
                      domain_id=domain_id, distro=n.get("distro", "jazzy"))
    if net.mode not in ("peer", "client", "router"):
        raise RobotConfigError(f"{where}: [network] mode = {net.mode!r}: expected peer, client "
                               "or router")
    if net.distro not in ("jazzy", "humble"):
        raise RobotConfigError(f"{where}: [network] distro = {net.distro!r}: expected jazzy or "
                               "humble")
    from .rplidar import MAX_ROTATION_HZ, MIN_ROTATION_HZ  # the devices extra (pyserial)

    lidar_hz = num("emulation", e, "lidar_rate_hz", 5.5, 0)
    if not MIN_ROTATION_HZ <= lidar_hz <= MAX_ROTATION_HZ:  # the driver drops turns outside it
        raise RobotConfigError(f"{where}: [emulation] lidar_rate_hz = {lidar_hz:g}: expected "
                               f"{MIN_ROTATION_HZ:g}..{MAX_ROTATION_HZ:g} Hz (an RPLIDAR head's rotation)")
    gain = num("estimation", s, "fingerprint_gain", 0.3)
    if not 0 <= gain <= 1:
        raise RobotConfigError(f"{where}: [estimation] fingerprint_gain = {gain}: expected 0..1")
    return RobotConfig(
        name=name, model=model, initial_pose=tuple(float(x) for x in pose),
        emulated=emulated, frame_prefix=prefix, opencr=opencr, rplidar=rplidar or None,
        rplidar_baudrate=int(baud), oakd=oakd,
        room=(float(room[0]), float(room[1])),
        lidar_rate_hz=lidar_hz, network=net,
        rate_hz=num("control", c, "rate_hz", 20.0, 0),
        cmd_timeout_s=num("control", c, "cmd_timeout_s", 0.5, 0),
        lookahead=num("control", c, "lookahead", 0.25, 0), fingerprint_gain=gain)


# ---------------------------------------------------------------- estimation

class PoseEstimator:
    """The robot's map-frame pose: ``initial pose (+) wheel odometry`` with fingerprint fixes.

    The odometry (frame ``odom``, starting at 0) is composed with the
    ``map -> odom`` transform, which starts at the initial pose. A fingerprint
    fix ``(x, y)`` with confidence ``c`` shifts that transform's translation by
    ``gain * c * (fix - estimate)``: a complementary filter where odometry
    carries the high frequencies and the twin's radio fixes remove the drift.

    Args:
        initial_pose: ``(x m, y m, yaw rad)`` in the map frame.
        gain: 0..1, share of a fix's error corrected at once.
    """

    def __init__(self, initial_pose=(0.0, 0.0, 0.0), gain: float = 0.3):
        self.origin = np.array(initial_pose, float)  # map -> odom: x, y, yaw
        self.gain = gain
        self.odom = np.zeros(3)
        self.velocity = np.zeros(2)  #: (v m/s, w rad/s)
        self.stamp = 0.0
        self.fixes = 0
        self._lock = threading.Lock()

    def on_odom(self, msg: Odometry) -> None:
        with self._lock:
            self.odom = np.array([msg.pose.position[0], msg.pose.position[1],
                                  quaternion_to_yaw(msg.pose.orientation)])
            self.velocity = np.array([msg.twist.linear[0], msg.twist.angular[2]])
            self.stamp = msg.header.stamp

    def on_fix(self, xy, confidence: float = 1.0) -> None:
        """Blend in a position fix ``[x, y]`` (m, map frame)."""
        with self._lock:
            err = np.asarray(xy, float)[:2] - self._pose()[:2]
            self.origin[:2] += self.gain * float(np.clip(confidence, 0, 1)) * err
            self.fixes += 1

    def _pose(self) -> np.ndarray:
        ox, oy, oyaw = self.origin
        x, y, yaw = self.odom
        c, s = math.cos(oyaw), math.sin(oyaw)
        return np.array([ox + c * x - s * y, oy + s * x + c * y,
                         wrap_angle(oyaw + yaw)])

    def pose(self) -> np.ndarray:
        """``[x m, y m, yaw rad]`` in the map frame."""
        with self._lock:
            return self._pose()


# ---------------------------------------------------------------- control

def box_room_scan_source(get_pose, room=(6.0, 4.0)):
    """A LiDAR scan source for the emulated RPLIDAR: ranges (m) from the robot's
    pose ``get_pose() -> (x, y, yaw)`` to the walls of the rectangle ``[0, W] x [0, D]``."""
    W, D = room

    def source(angles: np.ndarray) -> np.ndarray:
        x, y, yaw = get_pose()
        a = np.asarray(angles, float) + yaw
        c, s = np.cos(a), np.sin(a)
        with np.errstate(divide="ignore", invalid="ignore"):
            tx = np.where(c > 1e-12, (W - x) / c, np.where(c < -1e-12, -x / c, np.inf))
            ty = np.where(s > 1e-12, (D - y) / s, np.where(s < -1e-12, -y / s, np.inf))
        r = np.minimum(tx, ty)
        return np.where(r > 0, r, np.inf)

    return source


@dataclass
class RuntimeStats:
    """Counters of a running :class:`RobotRuntime`."""

    cmd_vel_received: int = 0
    paths_received: int = 0
    fingerprints_received: int = 0
    control_ticks: int = 0
    commands_sent: int = 0
    mode: str = "idle"  #: idle | path | teleop (twin cmd_vel) | stopped


class RobotRuntime:
    """Drivers, estimation and control of one robot, with its topics on zenoh.

    Topics (``<ns>`` = ``/<name>``)::

        published   <ns>/odom (nav_msgs/Odometry, frame odom), <ns>/imu, <ns>/battery_state,
                    <ns>/scan (sensor_msgs/LaserScan), <ns>/pose_estimate
                    (geometry_msgs/PoseStamped, frame map), /isac/clock/pong,
                    /diagnostics (diagnostic_msgs/DiagnosticArray: runtime and every device,
                    connected or not, every ``diagnostics_period_s``)
        subscribed  <ns>/cmd_vel (geometry_msgs/Twist), <ns>/path (isac_twin_msgs/PathCommand),
                    <ns>/fingerprint (isac_twin_msgs/Fingerprint), /isac/clock/ping

    Args:
        config: :class:`RobotConfig`.
        transport: a transport to use instead of a new :class:`ZenohTransport`.
        diagnostics_period_s: s between ``/diagnostics`` messages.
    """

    def __init__(self, config: RobotConfig, *, transport=None, diagnostics_period_s: float = 1.0):
        self.config = cfg = config
        self.diagnostics_period_s = diagnostics_period_s
        self.transport = transport if transport is not None else ZenohTransport(
            cfg.network, name=cfg.name)
        self.bus = Bus(transport=self.transport)
        ns = f"/{cfg.name}"
        self.topics = {k: f"{ns}/{k}" for k in ("odom", "imu", "battery_state", "scan",
                                                 "pose_estimate", "cmd_vel", "path",
                                                 "fingerprint")}
        self.node = self.bus.node(cfg.name)
        for key, typ in (("odom", Odometry), ("imu", Imu), ("battery_state", BatteryState),
                         ("scan", LaserScan), ("pose_estimate", PoseStamped)):
            self.node.advertise(self.topics[key], typ)
        #: REP-105 frame ids (isac_twin.bus.frames, the twin's convention)
        self.frames = frames.RobotFrames(f"{cfg.name}/" if cfg.frame_prefix else "")
        self.node.advertise("/tf", TFMessage)
        self.node.advertise("/tf_static", TFMessage)
        self.node.advertise(DIAGNOSTICS_TOPIC, DiagnosticArray)
        self.estimator = PoseEstimator(cfg.initial_pose, cfg.fingerprint_gain)
        self.stats = RuntimeStats()
        self._lock = threading.Lock()
        self._twin_cmd: tuple[float, float] | None = None
        self._twin_cmd_t = -math.inf
        self._controller = None
        self.node.subscribe(self.topics["odom"], Odometry, self._on_odom)
        self.node.subscribe(self.topics["cmd_vel"], Twist, self._on_cmd_vel)
        self.node.subscribe(self.topics["path"], PathCommand, self._on_path)
        self.node.subscribe(self.topics["fingerprint"], Fingerprint, self._on_fingerprint)
        self.clock = ClockResponder(self.bus, cfg.name)
        self.emulators: list = []
        self.sim = None
        self.opencr = None
        self.lidar = None
        self.oakd = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # ------------------------------------------------------------ lifecycle
    def start(self) -> RobotRuntime:
        """Start emulators (if emulated), drivers and the control loop; returns at once."""
        from .opencr import OpenCR
        from .rplidar import RPLidar

        cfg = self.config
        opencr_url, lidar_url = cfg.opencr, cfg.rplidar
        if cfg.emulated:
            from ..robots.agent import OpenCRStep
            from ..robots.kinematics import DiffDriveRobot
            from .emulated_opencr import EmulatedOpenCR
            from .emulated_rplidar import EmulatedRPLidar

            self.sim = DiffDriveRobot(cfg.model, pose=cfg.initial_pose, name=cfg.name)
            board = EmulatedOpenCR(step=OpenCRStep(self.sim), model=cfg.model).start()
            sim = self.sim
            lidar = EmulatedRPLidar(box_room_scan_source(
                lambda: (sim.state.x, sim.state.y, sim.state.yaw), cfg.room),
                scan_rate_hz=cfg.lidar_rate_hz).start()
            self.emulators = [board, lidar]
            opencr_url, lidar_url = board.url, lidar.url
            log.info("%s: emulated OpenCR at %s, RPLIDAR at %s", cfg.name, board.path, lidar.path)
        publish = self.node.publish
        fr = self.frames
        self.node.publish("/tf_static", TFMessage(frames.static_tf(
            time.time(), fr, robot_spec(cfg.model))))
        self.opencr = OpenCR(opencr_url, publish, model=cfg.model,
                             topics={k: self.topics[k] for k in ("odom", "imu", "battery_state")},
                             odom_frame=fr.odom, base_frame=fr.base_footprint,
                             imu_frame=fr.imu_link,
                             diagnostics_topic=None).start()  # the runtime publishes all diagnostics
        if lidar_url:
            self.lidar = RPLidar(lidar_url, publish, baudrate=cfg.rplidar_baudrate,
                                 topic=self.topics["scan"], frame_id=fr.base_scan,
                                 diagnostics_topic=None).start()
        if cfg.oakd:
            try:
                from .oakd import OakD, ReplaySource, generated_frames

                # emulated: generated frames through the driver's device path (needs depthai)
                replay = ReplaySource(generated_frames(), fps=15.0) if cfg.emulated else None
                self.oakd = OakD(cfg.oakd if isinstance(cfg.oakd, str) else "", self._publish_any,
                                 topics={"color": f"/{cfg.name}/camera/color/image_raw",
                                         "depth": f"/{cfg.name}/camera/depth/image_raw",
                                         "imu": f"/{cfg.name}/camera/imu"},
                                 diagnostics_topic=None, replay=replay).start()
            except Exception as exc:  # noqa: BLE001 - the camera is optional
                log.warning("%s: OAK-D unavailable (%s); running without it", cfg.name, exc)
        self._stop.clear()
        self._thread = threading.Thread(target=self._control_loop, name=f"{cfg.name}-control",
                                        daemon=True)
        self._thread.start()
        return self

    def _publish_any(self, topic: str, msg) -> None:
        if topic not in self.node.advertised:
            self.node.advertise(topic, type(msg))
        self.node.publish(topic, msg)

    def stop(self) -> None:
        """Stop the robot (zero command), the control loop, drivers, emulators, the session.

        :attr:`stop_stage` names the step it is in (a caller that bounds the
        shutdown reports where it stalled)."""
        self._stop.set()
        self.stop_stage = "control loop"
        if self._thread is not None:
            self._thread.join(2.0)
            self._thread = None
        if self.opencr is not None:
            try:
                self.opencr.set_cmd_vel(0.0, 0.0)
                time.sleep(0.06)
            except Exception:  # noqa: BLE001
                pass
        for d in (self.oakd, self.lidar, self.opencr):
            if d is not None:
                self.stop_stage = f"driver {type(d).__name__}"
                d.stop()
                if not d.ever_connected:
                    log.warning("%s: %s", self.config.name, d.summary())
        for e in reversed(self.emulators):
            self.stop_stage = f"emulator {type(e).__name__}"
            e.stop()
        self.emulators = []
        self.stop_stage = "zenoh transport close"
        self.transport.close()
        self.stop_stage = "done"

    def drivers(self) -> list[tuple[str, object]]:
        """(name, driver) of every device driver running."""
        return [(n, d) for n, d in (("OpenCR", self.opencr), ("RPLIDAR", self.lidar), ("OAK-D", self.oakd))
                if d is not None]

    def diagnostics(self) -> DiagnosticArray:
        """``/diagnostics`` now: one status per device (see
        :meth:`isac_twin.devices.base.DeviceDriver.diagnostic_status`) and the
        runtime's own, as bad as its worst device, naming those not connected."""
        name = self.config.name
        devs = []
        for dev_name, d in self.drivers():
            st = d.diagnostic_status()
            st.name = f"{name}: {dev_name}"
            devs.append(st)
        missing = [st.name.split(": ", 1)[1] for st in devs if st.level != DiagnosticStatus.OK
                   and not st.message.startswith("connected")]
        level = max([st.level for st in devs], default=DiagnosticStatus.OK)
        msg = f"mode {self.stats.mode}; " + (f"not connected: {', '.join(missing)}" if missing
                                            else f"all {len(devs)} devices connected")
        values = [(k, str(v)) for k, v in vars(self.stats).items()]
        own = DiagnosticStatus(level, f"{name}: runtime", msg, name, values)
        return DiagnosticArray(Header(stamp=time.time(), frame_id=""), [own, *devs])

    def device_summaries(self) -> list[str]:
        """One line per device driver: whether it ever connected, frames, messages."""
        return [f"{name}: {d.summary()}" for name, d in self.drivers()]

    def __enter__(self) -> RobotRuntime:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    #: Longest the main thread sleeps in :meth:`run` between looks at its signals, s.
    RUN_POLL_S = 0.2

    def run(self, duration: float | None = None, stop: threading.Event | None = None) -> None:
        """Block until ``duration`` s passed or ``stop`` is set (the runtime keeps running).

        Waits in slices of :attr:`RUN_POLL_S`: CPython runs signal handlers only in
        the main thread, and a process-directed SIGTERM that the kernel hands to
        another thread (one of zenoh's, a driver's) does not interrupt the main
        thread's lock wait, so one long ``Event.wait`` left the handler (and the
        stop it sets) pending until the whole duration ran out.
        """
        stop = stop or self._stop
        end = None if duration is None else time.monotonic() + duration
        while not stop.is_set():
            left = self.RUN_POLL_S if end is None else min(self.RUN_POLL_S, end - time.monotonic())
            if left <= 0:
                return
            stop.wait(left)

    # ------------------------------------------------------------ callbacks
    def _on_odom(self, msg: Odometry) -> None:
        self.estimator.on_odom(msg)
        x, y, yaw = self.estimator.pose()
        self.node.publish(self.topics["pose_estimate"], PoseStamped(
            header=Header(stamp=msg.header.stamp, frame_id=frames.MAP),
            pose=Pose(position=np.array([x, y, 0.0]), orientation=yaw_to_quaternion(yaw))))
        odom = (msg.pose.position[0], msg.pose.position[1],
                quaternion_to_yaw(msg.pose.orientation))
        self.node.publish("/tf", TFMessage(frames.dynamic_tf(
            msg.header.stamp, self.frames, (x, y, yaw), odom)))

    def _on_cmd_vel(self, msg: Twist) -> None:
        with self._lock:
            self._twin_cmd = (float(msg.linear[0]), float(msg.angular[2]))
            self._twin_cmd_t = time.monotonic()
            self.stats.cmd_vel_received += 1

    def _on_path(self, msg: PathCommand) -> None:
        spec = msg.to_spec()
        try:
            ctl = controller_from_spec(spec, self.config.model, lookahead=self.config.lookahead) \
                if spec else None
        except (ValueError, KeyError) as exc:
            log.warning("%s: rejected path %s: %s", self.config.name, spec, exc)
            return
        with self._lock:
            self._controller = ctl
            self.stats.paths_received += 1
        log.info("%s: following %s", self.config.name, spec or "nothing (stop)")

    def _on_fingerprint(self, msg: Fingerprint) -> None:
        self.stats.fingerprints_received += 1
        if msg.confidence > 0:
            self.estimator.on_fix(msg.estimate[:2], msg.confidence)

    # ------------------------------------------------------------ control
    def command(self) -> tuple[float, float]:
        """The command now (v m/s, w rad/s): path > fresh twin cmd_vel > stop."""
        from ..robots.kinematics import KinematicState

        with self._lock:
            ctl, cmd, age = self._controller, self._twin_cmd, time.monotonic() - self._twin_cmd_t
        if ctl is not None:
            x, y, yaw = self.estimator.pose()
            v, w = self.estimator.velocity
            st = KinematicState(pose=np.array([x, y, 0.0, 0.0, 0.0, yaw]), v=float(v), w=float(w))
            self.stats.mode = "path"
            return tuple(float(u) for u in ctl.command(st))
        if cmd is not None and age <= self.config.cmd_timeout_s:
            self.stats.mode = "teleop"
            return cmd
        self.stats.mode = "stopped" if cmd is not None else "idle"
        return 0.0, 0.0

    def _control_loop(self) -> None:
        period = 1.0 / self.config.rate_hz
        last = None
        next_t = time.monotonic()
        next_diag = next_t
        while not self._stop.is_set():
            if time.monotonic() >= next_diag:
                next_diag = time.monotonic() + self.diagnostics_period_s
                try:
                    self.node.publish(DIAGNOSTICS_TOPIC, self.diagnostics())
                except Exception:  # noqa: BLE001 - diagnostics must not stop the robot
                    log.exception("%s: publishing diagnostics failed", self.config.name)
            try:
                v, w = self.command()
                self.stats.control_ticks += 1
                if (v, w) != last or self.stats.control_ticks % 5 == 0:
                    self.opencr.set_cmd_vel(v, w)
                    self.stats.commands_sent += 1
                    last = (v, w)
            except Exception:  # noqa: BLE001 - the loop must survive a bad tick
                log.exception("%s: control tick failed", self.config.name)
            next_t += period
            self._stop.wait(max(0.0, next_t - time.monotonic()))
            if time.monotonic() - next_t > period:
                next_t = time.monotonic()
