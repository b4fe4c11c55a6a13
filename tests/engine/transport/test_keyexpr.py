"""engine/transport/keyexpr.py: rmw_zenoh key expressions and attachments."""

import pytest

from engine.transport.keyexpr import Attachment, parse_topic_key, topic_key


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


def test_attachment_round_trip_and_length_prefixed_gid():
    a = Attachment(42, 1_763_000_000_000_000_123, bytes(range(16)))
    raw = a.to_bytes()
    assert len(raw) == 32
    assert Attachment.from_bytes(raw) == a
    assert Attachment.from_bytes(raw[:16] + b"\x10" + raw[16:]) == a
    with pytest.raises(ValueError):
        Attachment.from_bytes(b"\0" * 10)
