"""rmw_zenoh-compatible key expressions and sample attachments.

Data key expression of a topic (what ``rmw_zenoh_cpp`` publishes on)::

    <domain_id>/<topic without its leading '/'>/<DDS type name>/<type hash>
    0/robot1/scan/sensor_msgs::msg::dds_::LaserScan_/RIHS01_64c19139...

* ``<DDS type name>``: ``pkg::msg::dds_::Name_`` (the rosidl DDS mangling rmw_zenoh keeps);
* ``<type hash>``: REP-2011 ``RIHS01_<sha256>`` on Jazzy and later (rosbags computes
  the same hash from the message definitions); Humble's rmw_zenoh puts the literal
  ``TypeHashNotSupported`` there.

Subscriptions use ``*`` for the hash chunk, so a peer of another distro (other
hash) is still received; a hash that differs from ours is logged once.

Attachment (rmw_zenoh >= 0.2 on Jazzy, zenoh-ext serialization): ``int64``
sequence number, ``int64`` source timestamp (ns since the Unix epoch, the
publisher's clock), 16-byte source GID -- 32 bytes little endian. Readers here
also accept the GID with a 1-byte length prefix (33 bytes).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from engine.transport.cdr import dds_type_name, type_hash

HUMBLE_HASH = "TypeHashNotSupported"


def topic_key(topic: str, type_name: str, *, domain_id: int = 0, distro: str = "jazzy",
              any_hash: bool = False) -> str:
    """The data key expression of ``topic`` (a ROS name, ``/ns/name``) with ``type_name``.

    Args:
        domain_id: ROS_DOMAIN_ID.
        distro: ``"jazzy"`` (RIHS01 hash) or ``"humble"`` (``TypeHashNotSupported``).
        any_hash: ``*`` instead of the hash (for subscribers).
    """
    name = topic.strip("/")
    if not name or "//" in name:
        raise ValueError(f"invalid ROS topic name {topic!r}")
    if any_hash:
        h = "*"
    elif distro == "humble":
        h = HUMBLE_HASH
    else:
        h = type_hash(type_name)
    return f"{int(domain_id)}/{name}/{dds_type_name(type_name)}/{h}"


def parse_topic_key(key: str) -> tuple[int, str, str, str]:
    """``(domain_id, "/topic", "pkg/msg/Type", hash)`` of a data key expression."""
    parts = str(key).split("/")
    if len(parts) < 4:
        raise ValueError(f"not an rmw_zenoh topic key expression: {key!r}")
    dds, h = parts[-2], parts[-1]
    try:
        pkg, kind, dds_, name = dds.split("::")
    except ValueError:
        raise ValueError(f"not a DDS type name in {key!r}: {dds!r}") from None
    return int(parts[0]), "/" + "/".join(parts[1:-2]), f"{pkg}/{kind}/{name.rstrip('_')}", h


@dataclass(frozen=True)
class Attachment:
    """What rmw_zenoh attaches to each sample.

    Attributes:
        sequence_number: per-publisher counter, from 1.
        source_timestamp_ns: publisher's wall clock at publication, ns since the epoch.
        source_gid: 16 bytes identifying the publisher.
    """

    sequence_number: int
    source_timestamp_ns: int
    source_gid: bytes

    def to_bytes(self) -> bytes:
        return struct.pack("<qq", self.sequence_number, self.source_timestamp_ns) \
            + self.source_gid[:16].ljust(16, b"\0")

    @classmethod
    def from_bytes(cls, data: bytes) -> Attachment:
        if len(data) == 33 and data[16] == 16:
            data = data[:16] + data[17:]
        if len(data) != 32:
            raise ValueError(f"rmw_zenoh attachment: expected 32 bytes, got {len(data)}")
        seq, ts = struct.unpack_from("<qq", data)
        return cls(seq, ts, bytes(data[16:32]))
