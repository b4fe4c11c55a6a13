"""What a stock ROS 2 node on rmw_zenoh sees of a twin shared by TwinBridge (loopback).

The "ROS 2 node" here is a bare zenoh session plus independent decoders: rosbags'
Jazzy typestore for the CDR payloads, zenoh-ext's deserializer for the attachment,
and the liveliness key format of rmw_zenoh's design document. No engine code decodes.
"""

import time

import pytest
import zenoh
from rosbags.typesys import Stores, get_typestore
from zenoh.ext import Int64, z_deserialize

from isac_twin import Twin
from isac_twin.scene.synthetic import ROBOT_EXTRA, SyntheticDevice, box_room
from isac_twin.transport.bridge import TwinBridge
from isac_twin.transport.zenoh_transport import ZenohConfig, ZenohTransport

pytestmark = pytest.mark.slow


def _wait(pred, timeout=8.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and not pred():
        time.sleep(0.02)
    return pred()


def test_stock_ros2_node_sees_and_decodes_the_shared_twin(tmp_path, port):
    devs = [SyntheticDevice("AP1", "access_point", "tx", (1.0, 1.0, 2.0)),
            SyntheticDevice("robot1", "robot", "rx", (2.0, 2.0, 0.0), extra=dict(ROBOT_EXTRA))]
    twin = Twin.from_scene(box_room(tmp_path / "room", devices=devs, links=[("AP1", "robot1")]),
                           phy=False, sensing=False)
    twin.trace_schedule = lambda i: False
    twin.set_path("robot1", {"kind": "circle", "centre": [2.5, 2.0], "radius": 0.5})
    transport = ZenohTransport(ZenohConfig(listen=[f"tcp/127.0.0.1:{port}"]), name="isac_twin")
    t_created = time.time()  # the bridge's epoch (the twin's t = 0) is taken after this
    bridge = TwinBridge(twin, transport, robots=[], clock_period_s=0,
                        share=["/tf", "/tf_static", "/robot1/odom"], share_prefix="")
    c = zenoh.Config()
    c.insert_json5("connect/endpoints", f'["tcp/127.0.0.1:{port}"]')
    c.insert_json5("scouting/multicast/enabled", "false")
    ros = zenoh.open(c)
    try:
        ts = get_typestore(Stores.ROS2_JAZZY)
        got = []
        ros.declare_subscriber("0/tf/tf2_msgs::msg::dds_::TFMessage_/*", got.append)
        odo = []
        ros.declare_subscriber("0/robot1/odom/nav_msgs::msg::dds_::Odometry_/*", odo.append)
        assert transport.wait_for_peers(1, 5.0)
        time.sleep(0.5)
        for _ in range(5):
            bridge.step()
        assert _wait(lambda: len(got) >= 5 and len(odo) >= 1)
        s = got[-1]
        tf = ts.deserialize_cdr(s.payload.to_bytes(), "tf2_msgs/msg/TFMessage")
        assert [t.child_frame_id for t in tf.transforms] == ["odom", "base_footprint"]
        assert tf.transforms[0].header.frame_id == "map"
        # wall-clock stamps: the bridge's epoch plus the twin's simulated time
        latest = time.time() + twin.time_s
        assert int(t_created) <= tf.transforms[0].header.stamp.sec <= latest
        seq, stamp, gid = z_deserialize(tuple[Int64, Int64, bytes], s.attachment)
        assert int(seq) == len(got) and len(gid) == 16
        assert t_created <= int(stamp) / 1e9 <= latest
        o = ts.deserialize_cdr(odo[-1].payload.to_bytes(), "nav_msgs/msg/Odometry")
        assert (o.header.frame_id, o.child_frame_id) == ("odom", "base_footprint")
        # a late joiner gets the latched /tf_static (TRANSIENT_LOCAL on both sides)
        from zenoh.ext import HistoryConfig, declare_advanced_subscriber
        static = []
        declare_advanced_subscriber(ros, "0/tf_static/tf2_msgs::msg::dds_::TFMessage_/*",
                                    static.append,
                                    history=HistoryConfig(detect_late_publishers=True))
        assert _wait(lambda: len(static) == 1)
        st = ts.deserialize_cdr(static[0].payload.to_bytes(), "tf2_msgs/msg/TFMessage")
        assert {t.child_frame_id for t in st.transforms} == {"base_link", "base_scan",
                                                            "imu_link"}
        # `ros2 node list` / `ros2 topic list` material: the graph tokens
        keys = {str(r.ok.key_expr) for r in ros.liveliness().get("@ros2_lv/0/**", timeout=2.0)
                if r.ok}
        zid = transport.zid()
        assert f"@ros2_lv/0/{zid}/0/0/NN/%/%/isac_twin" in keys
        topics = {k.split("/")[9] for k in keys if f"/{zid}/" in k and "/MP/" in k}
        assert {"%tf", "%tf_static", "%robot1%odom"} <= topics
        with pytest.raises(ValueError, match="share_stamps"):
            TwinBridge(twin, transport, robots=[], clock_period_s=0, share_stamps="later")
    finally:
        ros.close()
        bridge.close()


def test_share_refuses_a_name_the_real_robot_uses(tmp_path):
    from tests.engine.transport.test_bridge import MiniTwin

    t = ZenohTransport(ZenohConfig())
    try:
        with pytest.raises(ValueError, match="share_prefix"):
            TwinBridge(MiniTwin(), t, clock_period_s=0, share=["/robot1/odom"], share_prefix="")
        with pytest.raises(ValueError, match="share:"):
            TwinBridge(MiniTwin(), t, clock_period_s=0, share="everything")
    finally:
        t.close()
