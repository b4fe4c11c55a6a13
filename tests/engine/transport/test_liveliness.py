"""engine/transport/liveliness.py + ZenohTransport's graph tokens, on a real zenoh session.

The expected key expressions are written out here from rmw_zenoh's docs/design.md
("Graph Cache"), not produced by our own code:

    @ros2_lv/<domain_id>/<session_id>/<node_id>/<node_id>/NN/<enclave>/<namespace>/<node_name>
    @ros2_lv/<domain_id>/<session_id>/<node_id>/<entity_id>/<MP|MS>/<enclave>/<namespace>/
        <node_name>/<mangled_qualified_name>/<type_name>/<type_hash>/<qos>

and its examples (talker publisher ``.../MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/
RIHS01_df66.../::,7:,:,:,,``).
"""

import time

import pytest
import zenoh

from isac_twin.bus.bus import Bus
from isac_twin.bus.msgs import LaserScan, Twist
from isac_twin.transport.liveliness import parse_token
from isac_twin.transport.qos import QosProfile
from isac_twin.transport.zenoh_transport import ZenohConfig, ZenohTransport

# published hashes (rosidl-generated, as other ROS 2 client libraries list them)
SCAN_HASH = "RIHS01_64c191398013af96509d518dac71d5164f9382553fce5c1f8cca5be7924bd828"
TWIST_HASH = "RIHS01_9c45bf16fe0983d80e3cfe750d6835843d265a9a6c46bd2e609fcddde6fb8d2a"
STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"


def plain_session(port: int) -> zenoh.Session:
    """A bare zenoh session (no engine code), as another ROS 2 process would open one."""
    c = zenoh.Config()
    c.insert_json5("mode", '"peer"')
    c.insert_json5("connect/endpoints", f'["tcp/127.0.0.1:{port}"]')
    c.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(c)


def liveliness_keys(session: zenoh.Session, domain: int = 0) -> set[str]:
    return {str(r.ok.key_expr) for r in session.liveliness().get(f"@ros2_lv/{domain}/**",
                                                                 timeout=2.0) if r.ok}


def wait_until(cond, timeout=5.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(0.02)
    return False


@pytest.fixture
def robot(port):
    t = ZenohTransport(ZenohConfig(listen=[f"tcp/127.0.0.1:{port}"]), name="robot1_node")
    yield t
    t.close()


def test_tokens_follow_rmw_zenoh_design_document(robot, port):
    bus = Bus(transport=robot)
    node = bus.node("robot1")
    node.advertise("/robot1/scan", LaserScan)
    node.subscribe("/robot1/cmd_vel", Twist, lambda m: None)
    other = plain_session(port)
    try:
        zid = str(robot.session.zid())
        expected = {
            f"@ros2_lv/0/{zid}/0/0/NN/%/%/robot1_node",
            # SensorDataQoS: BEST_EFFORT (2), depth 5; the rest rmw_zenoh's defaults
            f"@ros2_lv/0/{zid}/0/1/MP/%/%/robot1_node/%robot1%scan/"
            f"sensor_msgs::msg::dds_::LaserScan_/{SCAN_HASH}/2::,5:,:,:,,",
            f"@ros2_lv/0/{zid}/0/2/MS/%/%/robot1_node/%robot1%cmd_vel/"
            f"geometry_msgs::msg::dds_::Twist_/{TWIST_HASH}/::,10:,:,:,,",
        }
        assert wait_until(lambda: expected <= liveliness_keys(other))
        assert liveliness_keys(other) == expected
        assert robot.token_key("MP", "/robot1/scan") in expected
    finally:
        other.close()


def test_transport_sees_a_ros2_talker_and_its_departure(robot, port):
    """A token exactly as design.md's talker example (our own session id) appears in the
    graph as node /talker publishing /chatter, and goes when the process leaves."""
    other = plain_session(port)
    zid = str(other.zid())
    nn = other.liveliness().declare_token(f"@ros2_lv/0/{zid}/0/0/NN/%/%/talker")
    mp = other.liveliness().declare_token(
        f"@ros2_lv/0/{zid}/0/10/MP/%/%/talker/%chatter/std_msgs::msg::dds_::String_/"
        f"{STRING_HASH}/::,7:,:,:,,")
    # two tokens, two liveliness samples: wait for both (under load the second one
    # arrived after the first check)
    assert wait_until(lambda: "/talker" in robot.ros_nodes() and "/chatter" in robot.ros_topics())
    assert robot.ros_nodes() == ["/robot1_node", "/talker"]
    assert robot.ros_topics()["/chatter"] == {"std_msgs/msg/String"}
    pub = [e for e in robot.graph(remote_only=True) if e.kind == "MP"][0]
    assert pub.qos == QosProfile(depth=7) and pub.type_hash == STRING_HASH
    del nn, mp
    other.close()
    assert wait_until(lambda: robot.ros_nodes() == ["/robot1_node"])
    assert "/chatter" not in robot.ros_topics()


def test_namespace_domain_and_latched_qos_in_tokens(port):
    t = ZenohTransport(ZenohConfig(listen=[f"tcp/127.0.0.1:{port}"], domain_id=7,
                                   namespace="/lab"), name="twin")
    try:
        Bus(transport=t).node("twin").advertise("/tf_static", _tf_type())
        key = t.token_key("MP", "/tf_static")
        # TRANSIENT_LOCAL (1), depth 1
        assert key.startswith(f"@ros2_lv/7/{t.zid()}/0/1/MP/%/%lab/twin/%tf_static/"
                              "tf2_msgs::msg::dds_::TFMessage_/RIHS01_")
        assert key.endswith("/:1:,1:,:,:,,")
        assert t.ros_nodes() == ["/lab/twin"] or wait_until(lambda: t.ros_nodes() == ["/lab/twin"])
    finally:
        t.close()


def _tf_type():
    from isac_twin.bus.msgs import TFMessage
    return TFMessage


def test_bad_tokens_and_names_are_refused_with_the_chunk_named():
    with pytest.raises(ValueError, match="chunk 5"):
        parse_token("@ros2_lv/0/abc/0/0/XX/%/%/n")
    with pytest.raises(ValueError, match="13 chunks"):
        parse_token("@ros2_lv/0/abc/0/1/MP/%/%/n/%t")
    with pytest.raises(ValueError, match="QoS"):
        parse_token("@ros2_lv/0/abc/0/1/MP/%/%/n/%t/std_msgs::msg::dds_::String_/H/9:9")
    with pytest.raises(ValueError, match="node name"):
        ZenohTransport(ZenohConfig(), name="bad-name")
    with pytest.raises(ValueError, match="namespace"):
        ZenohTransport(ZenohConfig(namespace="lab"))
    with pytest.raises(ValueError, match="depth"):
        QosProfile(depth=0)
