"""engine/transport/keyexpr.py: rmw_zenoh key expressions and attachments."""

import pytest

from isac_twin.transport.keyexpr import Attachment, parse_topic_key, topic_key


def test_topic_key_matches_rmw_zenoh_format():
    k = topic_key("/robot1/cmd_vel", "geometry_msgs/msg/Twist")
    assert k == ("0/robot1/cmd_vel/geometry_msgs::msg::dds_::Twist_/"
                 "RIHS01_9c45bf16fe0983d80e3cfe750d6835843d265a9a6c46bd2e609fcddde6fb8d2a")
    assert topic_key("/chatter", "std_msgs/msg/String", domain_id=7, distro="humble") == \
        "7/chatter/std_msgs::msg::dds_::String_/TypeHashNotSupported"
    assert topic_key("/scan", "sensor_msgs/msg/LaserScan", any_hash=True).endswith("LaserScan_/*")


def test_parse_topic_key_inverts_topic_key():
    k = topic_key("/robot1/camera/depth", "sensor_msgs/msg/Image", domain_id=3)
    dom, topic, typ, h = parse_topic_key(k)
    assert (dom, topic, typ) == (3, "/robot1/camera/depth", "sensor_msgs/msg/Image")
    assert h.startswith("RIHS01_")
    with pytest.raises(ValueError):
        topic_key("//", "std_msgs/msg/String")


def test_attachment_is_what_zenoh_ext_deserializes():
    """rmw_zenoh's AttachmentData is zenoh-ext serialized (int64, int64, uint8[16] as a
    sequence: a LEB128 length byte then the bytes), 33 bytes in all (rmw_zenoh
    docs/design.md, "Publishers"). zenoh-ext's own deserializer is the reference."""
    from zenoh.ext import Int64, z_deserialize, z_serialize

    gid = bytes(range(0xA0, 0xB0))
    a = Attachment(42, 1_763_000_000_000_000_123, gid)
    raw = a.to_bytes()
    assert len(raw) == 33
    assert raw[16] == 16  # the GID length byte
    import zenoh
    seq, ts, g = z_deserialize(tuple[Int64, Int64, bytes], zenoh.ZBytes(raw))
    assert (int(seq), int(ts), g) == (42, 1_763_000_000_000_000_123, gid)
    # and what zenoh-ext writes, we read
    ref = z_serialize((Int64(7), Int64(-5), gid)).to_bytes()
    assert Attachment.from_bytes(ref) == Attachment(7, -5, gid)
    assert ref == Attachment(7, -5, gid).to_bytes()


def test_attachment_refuses_malformed_bytes_with_the_offending_byte():
    good = Attachment(1, 2, bytes(16)).to_bytes()
    with pytest.raises(ValueError, match="33 bytes"):
        Attachment.from_bytes(good[:32])  # the old 32-byte layout without the length byte
    with pytest.raises(ValueError, match="byte 16"):
        Attachment.from_bytes(good[:16] + b"\x0f" + good[17:])
    with pytest.raises(ValueError):
        Attachment.from_bytes(b"\0" * 10)
    with pytest.raises(ValueError, match="16 bytes"):
        Attachment(1, 2, bytes(15)).to_bytes()
