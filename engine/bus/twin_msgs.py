"""``isac_twin_msgs``: the twin-specific message types, as ROS 2 ``.msg`` definitions.

Paths, link metrics, fingerprints (multipath delay profiles, MDP), CSI, path
commands and clock pings have no standard ROS 2 message. They are defined
here twice, in one place:

* as ``.msg`` text (:data:`MSG_DEFINITIONS`), registered into the rosbags
  typestore by :mod:`isac_twin.transport.cdr` so they serialize to CDR and so MCAP
  files carry their definitions (Foxglove / ``ros2 bag`` decode them; a ROS 2
  workspace can build a real ``isac_twin_msgs`` package from the same text);
* as :mod:`isac_twin.bus.msgs`-style dataclasses with ``ROS_TYPE``, added to
  :data:`isac_twin.bus.msgs.MESSAGE_TYPES` on import so they travel on the topic bus.

Units: SI (m, s, Hz, rad), powers/gains in dB where named ``*_db``; stamps are
float seconds in the dataclasses and ``builtin_interfaces/Time`` on the wire.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .msgs import MESSAGE_TYPES, Csi, Header

PACKAGE = "isac_twin_msgs"

#: ``isac_twin_msgs/msg/<Name>`` -> ``.msg`` text.
MSG_DEFINITIONS: dict[str, str] = {
    "isac_twin_msgs/msg/LinkMetrics": """\
# One radio link at the end of a twin step.
std_msgs/Header header
string tx
string rx
float64 snr_db          # mean received SNR over the resource set, dB
float64 rate_bps        # achievable rate, bit/s
uint32 num_paths
bool los
float64 total_gain_db   # 10 log10(sum |a|^2), dB (-inf when no path)
float64 mcs_rate_bps    # rate through the [link_adaptation] MCS table, bit/s
""",
    "isac_twin_msgs/msg/LinkPaths": """\
# The traced propagation paths of one link: L paths, D interaction slots each.
std_msgs/Header header
string tx
string rx
float64 frequency_hz
float64[3] tx_position   # m
float64[3] rx_position   # m
float64[] a_real         # [L] complex path coefficient, real part
float64[] a_imag         # [L] imaginary part
float64[] tau            # [L] delay, s
float64[] doppler        # [L] Hz
float64[] theta_t        # [L] departure zenith, rad
float64[] phi_t          # [L] departure azimuth, rad
float64[] theta_r        # [L] arrival zenith, rad
float64[] phi_r          # [L] arrival azimuth, rad
uint32 depth             # D
float64[] vertices       # [L * D * 3] row-major, m
int32[] interactions     # [L * D] Sionna InteractionType codes (0 = none)
""",
    "isac_twin_msgs/msg/Fingerprint": """\
# A radio fingerprint (multipath delay profile) and the position estimate made from it.
std_msgs/Header header
string robot
string source                 # transmitter (AP) the profile was measured from
float64 delay_resolution_s    # width of one MDP bin, s
float64[] mdp                 # [B] power per delay bin, linear
geometry_msgs/Point estimate  # localization estimate in the map frame, m
float64 confidence            # 0..1 (0 = no estimate)
""",
    "isac_twin_msgs/msg/Csi": """\
# Channel state information H[k, n, r, t] of one link, row-major.
std_msgs/Header header
string tx
string rx
uint32 num_symbols       # K
uint32 num_subcarriers   # N
uint32 num_rx            # Nr
uint32 num_tx            # Nt
float32[] real           # [K * N * Nr * Nt]
float32[] imag
""",
    "isac_twin_msgs/msg/PathCommand": """\
# A path for a robot to follow (the twin's path spec, see isac_twin.robots.control.controller_from_spec).
std_msgs/Header header
string kind              # circle | polyline | figure_eight | goal | stop
float64[] waypoints      # polyline: [x0, y0, x1, y1, ...] m; goal: [x, y]
bool closed
float64[2] centre        # circle / figure_eight, m
float64 radius           # circle, m
float64 size             # figure_eight, m
string direction         # circle: ccw | cw
float64 speed            # m/s, 0 = the controller's default
""",
    "isac_twin_msgs/msg/ClockPing": """\
# NTP-style clock probe: origin stamps t0, responder stamps t1 (receive) and t2 (send).
string origin
string responder
uint32 seq
int64 t0_ns
int64 t1_ns
int64 t2_ns
""",
}


def _f(n: int = 0):
    return field(default_factory=lambda: np.zeros(n))


@dataclass
class LinkMetrics:
    ROS_TYPE = "isac_twin_msgs/msg/LinkMetrics"
    header: Header = field(default_factory=lambda: Header(frame_id="map"))
    tx: str = ""
    rx: str = ""
    snr_db: float = float("nan")
    rate_bps: float = float("nan")
    num_paths: int = 0
    los: bool = False
    total_gain_db: float = float("-inf")
    mcs_rate_bps: float = float("nan")


@dataclass
class LinkPathsMsg:
    """:class:`isac_twin.raytrace.base.LinkPaths` on the wire (see :func:`link_paths_msg`)."""

    ROS_TYPE = "isac_twin_msgs/msg/LinkPaths"
    header: Header = field(default_factory=lambda: Header(frame_id="map"))
    tx: str = ""
    rx: str = ""
    frequency_hz: float = 0.0
    tx_position: np.ndarray = _f(3)
    rx_position: np.ndarray = _f(3)
    a: np.ndarray = field(default_factory=lambda: np.zeros(0, complex))  #: [L] complex
    tau: np.ndarray = _f()
    doppler: np.ndarray = _f()
    theta_t: np.ndarray = _f()
    phi_t: np.ndarray = _f()
    theta_r: np.ndarray = _f()
    phi_r: np.ndarray = _f()
    vertices: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 3)))  #: [L, D, 3] m
    interactions: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), np.int32))  #: [L, D]


@dataclass
class Fingerprint:
    ROS_TYPE = "isac_twin_msgs/msg/Fingerprint"
    header: Header = field(default_factory=lambda: Header(frame_id="map"))
    robot: str = ""
    source: str = ""
    delay_resolution_s: float = 0.0
    mdp: np.ndarray = _f()
    estimate: np.ndarray = _f(3)  #: [3] m, map frame
    confidence: float = 0.0


@dataclass
class PathCommand:
    ROS_TYPE = "isac_twin_msgs/msg/PathCommand"
    header: Header = field(default_factory=lambda: Header(frame_id="map"))
    kind: str = "stop"
    waypoints: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))  #: [P, 2] m
    closed: bool = False
    centre: np.ndarray = _f(2)
    radius: float = 0.0
    size: float = 0.0
    direction: str = "ccw"
    speed: float = 0.0  #: m/s, 0 = default

    @classmethod
    def from_spec(cls, spec: dict, stamp: float = 0.0) -> PathCommand:
        """From a twin path spec dict (``{"kind": "circle", "centre": [x, y], ...}``)."""
        kind = spec.get("kind", "stop")
        pts = spec.get("waypoints") if kind == "polyline" else (
            [spec["goal"]] if kind == "goal" else [])
        return cls(header=Header(stamp=stamp, frame_id="map"), kind=kind,
                   waypoints=np.asarray(pts, float).reshape(-1, 2),
                   closed=bool(spec.get("closed", False)),
                   centre=np.asarray(spec.get("centre", (0.0, 0.0)), float),
                   radius=float(spec.get("radius", 0.0)), size=float(spec.get("size", 0.0)),
                   direction=str(spec.get("direction", "ccw")),
                   speed=float(spec.get("speed") or 0.0))

    def to_spec(self) -> dict | None:
        """The path spec dict for :func:`isac_twin.robots.control.controller_from_spec` (None for ``stop``)."""
        k = self.kind
        spec: dict = {"kind": k}
        if k == "stop":
            return None
        if k == "circle":
            spec.update(centre=list(map(float, self.centre)), radius=self.radius,
                        direction=self.direction)
        elif k == "polyline":
            spec.update(waypoints=self.waypoints.tolist(), closed=self.closed)
        elif k == "figure_eight":
            spec.update(centre=list(map(float, self.centre)), size=self.size)
        elif k == "goal":
            spec.update(goal=list(map(float, self.waypoints[0])))
        if self.speed > 0:
            spec["speed"] = self.speed
        return spec


@dataclass
class ClockPing:
    ROS_TYPE = "isac_twin_msgs/msg/ClockPing"
    origin: str = ""
    responder: str = ""
    seq: int = 0
    t0_ns: int = 0
    t1_ns: int = 0
    t2_ns: int = 0


TWIN_MESSAGE_TYPES: dict[str, type] = {
    c.ROS_TYPE: c for c in (LinkMetrics, LinkPathsMsg, Fingerprint, Csi, PathCommand, ClockPing)}
MESSAGE_TYPES.update(TWIN_MESSAGE_TYPES)


def link_paths_msg(lp, stamp: float = 0.0) -> LinkPathsMsg:
    """A :class:`LinkPathsMsg` from an :class:`isac_twin.raytrace.base.LinkPaths`."""
    return LinkPathsMsg(header=Header(stamp=stamp, frame_id="map"), tx=lp.tx, rx=lp.rx,
                        frequency_hz=float(lp.frequency_hz),
                        tx_position=np.asarray(lp.tx_position, float),
                        rx_position=np.asarray(lp.rx_position, float),
                        a=np.asarray(lp.a, complex), tau=np.asarray(lp.tau, float),
                        doppler=np.asarray(lp.doppler, float),
                        theta_t=np.asarray(lp.theta_t, float), phi_t=np.asarray(lp.phi_t, float),
                        theta_r=np.asarray(lp.theta_r, float), phi_r=np.asarray(lp.phi_r, float),
                        vertices=np.asarray(lp.vertices, float),
                        interactions=np.asarray(lp.interactions, np.int32))


def link_metrics_msg(ls, stamp: float = 0.0) -> LinkMetrics:
    """A :class:`LinkMetrics` from an :class:`isac_twin.twin.state.LinkState`."""
    n, los, total = 0, False, float("-inf")
    if ls.paths is not None:
        n = ls.paths.num_paths
        p = float(np.sum(np.abs(np.asarray(ls.paths.a)) ** 2))
        total = 10 * np.log10(p) if p > 0 else float("-inf")
        inter = np.asarray(ls.paths.interactions)
        los = bool(n and inter.ndim == 2 and not np.any(inter[0]))
    return LinkMetrics(header=Header(stamp=stamp, frame_id="map"), tx=ls.tx, rx=ls.rx,
                       snr_db=float(ls.snr_db), rate_bps=float(ls.rate_bps), num_paths=n,
                       los=los, total_gain_db=float(total),
                       mcs_rate_bps=float(getattr(ls, "mcs_rate_bps", float("nan"))))
