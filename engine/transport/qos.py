"""ROS 2 QoS profiles: the one definition the zenoh transport and the MCAP recorder share.

A :class:`QosProfile` is written in two places:

* rmw_zenoh liveliness tokens, in rmw_zenoh's compact form
  (``qos_to_keyexpr`` in ``rmw_zenoh_cpp/src/detail/liveliness_utils.cpp``)::

      <reliability>:<durability>:<history>,<depth>:<deadline s>,<ns>:<lifespan s>,<ns>:<liveliness>,<lease s>,<ns>

  each field empty when it equals rmw_zenoh's default (RELIABLE, VOLATILE,
  KEEP_LAST, depth 42, infinite deadline/lifespan/lease, AUTOMATIC), numbers
  otherwise (the ``rmw_qos_*_policy_e`` values: RELIABLE 1, BEST_EFFORT 2;
  TRANSIENT_LOCAL 1, VOLATILE 2; KEEP_LAST 1, KEEP_ALL 2). A talker with depth 7
  is ``::,7:,:,:,,``;
* MCAP channel metadata ``offered_qos_profiles``: the YAML list rosbag2 writes
  (``history``, ``depth``, ``reliability``, ``durability``, ``deadline``,
  ``lifespan``, ``liveliness``, ``liveliness_lease_duration``,
  ``avoid_ros_namespace_conventions``), enums as numbers.

:func:`qos_for` gives the twin's profile of a topic from REP-2003/rclcpp conventions:
sensor streams (scan, imu, images) best-effort depth 5 (``SensorDataQoS``),
``/tf_static`` transient-local depth 1 (latched), ``/tf`` depth 100, ``/clock``
best-effort depth 1 (``ClockQoS``), everything else reliable depth 10; the tf
topics keep their QoS under a namespace (``/twin/tf_static``).
"""

from __future__ import annotations

from dataclasses import dataclass

#: rmw's enum values (rmw/types.h)
RELIABILITY = {"reliable": 1, "best_effort": 2}
DURABILITY = {"transient_local": 1, "volatile": 2}
HISTORY = {"keep_last": 1, "keep_all": 2}
LIVELINESS_AUTOMATIC = 1
#: RMW_DURATION_INFINITE as (sec, nsec)
INFINITE = (9223372036, 854775807)


@dataclass(frozen=True)
class QosProfile:
    """A ROS 2 QoS profile (the policies rmw_zenoh acts on).

    Attributes:
        reliability: ``"reliable"`` or ``"best_effort"``.
        durability: ``"volatile"`` or ``"transient_local"`` (late joiners get the last
            ``depth`` samples).
        history: ``"keep_last"`` or ``"keep_all"``.
        depth: samples kept (KEEP_LAST), >= 1.
    """

    reliability: str = "reliable"
    durability: str = "volatile"
    history: str = "keep_last"
    depth: int = 10

    def __post_init__(self):
        for name, table in (("reliability", RELIABILITY), ("durability", DURABILITY),
                            ("history", HISTORY)):
            if getattr(self, name) not in table:
                raise ValueError(f"QoS {name}: expected one of {sorted(table)}, "
                                 f"got {getattr(self, name)!r}")
        if not isinstance(self.depth, int) or self.depth < 1:
            raise ValueError(f"QoS depth: expected an integer >= 1, got {self.depth!r}")

    @property
    def transient_local(self) -> bool:
        return self.durability == "transient_local"

    def to_keyexpr(self) -> str:
        """rmw_zenoh's compact QoS chunk of a liveliness token (defaults left empty)."""
        rel = "" if self.reliability == "reliable" else str(RELIABILITY[self.reliability])
        dur = "" if self.durability == "volatile" else str(DURABILITY[self.durability])
        his = "" if self.history == "keep_last" else str(HISTORY[self.history])
        depth = "" if self.depth == 42 else str(self.depth)
        return f"{rel}:{dur}:{his},{depth}:,:,:,,"

    @classmethod
    def from_keyexpr(cls, text: str) -> QosProfile:
        """Parse rmw_zenoh's compact QoS chunk (deadline/lifespan/liveliness are ignored)."""
        parts = text.split(":")
        if len(parts) < 6 or len(parts[2].split(",")) < 2:
            raise ValueError(f"rmw_zenoh QoS chunk: expected "
                             f"'rel:dur:hist,depth:dl_s,dl_ns:ls_s,ls_ns:lv,lv_s,lv_ns', "
                             f"got {text!r}")
        inv = {v: k for k, v in RELIABILITY.items()}, {v: k for k, v in DURABILITY.items()}, \
            {v: k for k, v in HISTORY.items()}
        hist, depth = parts[2].split(",")[:2]
        try:
            return cls(reliability=inv[0][int(parts[0])] if parts[0] else "reliable",
                       durability=inv[1][int(parts[1])] if parts[1] else "volatile",
                       history=inv[2][int(hist)] if hist else "keep_last",
                       depth=int(depth) if depth else 42)
        except (KeyError, ValueError):
            raise ValueError(f"rmw_zenoh QoS chunk: unknown policy value in {text!r}") from None

    def to_rosbag2_yaml(self) -> str:
        """One profile of rosbag2's ``offered_qos_profiles`` YAML (a list item)."""
        inf = f"\n    sec: {INFINITE[0]}\n    nsec: {INFINITE[1]}"
        return (f"- history: {HISTORY[self.history]}\n  depth: {self.depth}\n"
                f"  reliability: {RELIABILITY[self.reliability]}\n"
                f"  durability: {DURABILITY[self.durability]}\n"
                f"  deadline:{inf}\n  lifespan:{inf}\n"
                f"  liveliness: {LIVELINESS_AUTOMATIC}\n  liveliness_lease_duration:{inf}\n"
                f"  avoid_ros_namespace_conventions: false")


SENSOR_DATA = QosProfile("best_effort", "volatile", "keep_last", 5)
LATCHED = QosProfile("reliable", "transient_local", "keep_last", 1)
DEFAULT = QosProfile()

_SENSOR_LEAVES = {"scan", "imu", "image_raw", "image", "depth", "points", "csi"}


def qos_for(topic: str) -> QosProfile:
    """The twin's QoS of ``topic`` (a ROS name) by convention (see the module docstring)."""
    parts = topic.strip("/").split("/")
    if parts[-1] == "tf_static":  # also a namespaced one (/twin/tf_static)
        return LATCHED
    if parts[-1] == "tf":
        return QosProfile(depth=100)
    if parts[-1] == "clock" and len(parts) <= 2:
        return QosProfile("best_effort", "volatile", "keep_last", 1)
    if parts[-1] in _SENSOR_LEAVES or (len(parts) > 1 and parts[-2] in ("camera", "depth")):
        return SENSOR_DATA
    return DEFAULT


def rosbag2_qos_yaml(profiles: list[QosProfile]) -> str:
    """rosbag2's ``offered_qos_profiles`` value for a channel (empty list: ``""``)."""
    return "\n".join(p.to_rosbag2_yaml() for p in profiles)
