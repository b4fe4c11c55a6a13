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

Attachment (rmw_zenoh on Jazzy and later, ``AttachmentData::serialize_to_zbytes``:
zenoh-ext serialization of ``int64, int64, std::array<uint8_t, 16>``), 33 bytes::

    offset  0  int64 LE   sequence number (per publisher, from 1)
    offset  8  int64 LE   source timestamp, ns since the Unix epoch (publisher's clock)
    offset 16  uint8      GID length, LEB128 (always 16 = 0x10)
    offset 17  16 bytes   publisher GID

``zenoh.ext.z_deserialize(tuple[Int64, Int64, bytes], ...)`` reads it (the
tests check against that independent decoder). rmw_zenoh's subscriber parses
the attachment of every sample without recovery, so anything else is refused.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from .cdr import dds_type_name, type_hash

HUMBLE_HASH = "TypeHashNotSupported"
#: bytes of a GID (RMW_GID_STORAGE_SIZE on Jazzy) and of a whole attachment
GID_SIZE = 16
ATTACHMENT_SIZE = 8 + 8 + 1 + GID_SIZE


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
        """The 33-byte zenoh-ext serialization (see the module docstring)."""
        if len(self.source_gid) != GID_SIZE:
            raise ValueError(f"rmw_zenoh attachment: source_gid must be {GID_SIZE} bytes, "
                             f"got {len(self.source_gid)}")
        return struct.pack("<qqB", self.sequence_number, self.source_timestamp_ns, GID_SIZE) \
            + bytes(self.source_gid)

    @classmethod
    def from_bytes(cls, data: bytes) -> Attachment:
        """Parse the 33-byte attachment; ``ValueError`` naming the offending byte otherwise."""
        data = bytes(data)
        if len(data) != ATTACHMENT_SIZE:
            raise ValueError(f"rmw_zenoh attachment: expected {ATTACHMENT_SIZE} bytes "
                             f"(int64 seq, int64 stamp, GID length byte, 16-byte GID), "
                             f"got {len(data)}")
        if data[16] != GID_SIZE:
            raise ValueError(f"rmw_zenoh attachment: byte 16 (GID length) is {data[16]}, "
                             f"expected {GID_SIZE}")
        seq, ts = struct.unpack_from("<qq", data)
        return cls(seq, ts, data[17:])
