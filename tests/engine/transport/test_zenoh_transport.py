"""engine/transport/zenoh_transport.py: two buses bridged over zenoh on loopback."""

import time

import numpy as np
import pytest

from isac_twin.bus.bus import Bus, Transport
from isac_twin.bus.msgs import LaserScan, Twist
from isac_twin.transport.clock import ClockProbe, ClockResponder
from isac_twin.transport.zenoh_transport import ZenohConfig, ZenohTransport


def _wait(pred, timeout=5.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.01)
    return pred()


@pytest.fixture
def pair(port):
    a = ZenohTransport(ZenohConfig(listen=[f"tcp/127.0.0.1:{port}"]), name="a")
    b = ZenohTransport(ZenohConfig(connect=[f"tcp/127.0.0.1:{port}"]), name="b")
    assert b.wait_for_peers(1, 5.0)
    yield a, b
    a.close()
    b.close()


def test_is_a_bus_transport(pair):
    assert isinstance(pair[0], Transport)
    assert pair[0].config.multicast is False


def test_messages_cross_in_order_without_echo(pair):
    a, b = pair
    pub_bus, sub_bus = Bus(transport=a), Bus(transport=b)
    pub = pub_bus.node("robot")
    pub.advertise("/robot1/scan", LaserScan)
    local = pub.subscribe("/robot1/scan", LaserScan)  # same process: the bus delivers it once
    remote = sub_bus.node("twin").subscribe("/robot1/scan", LaserScan)
    time.sleep(0.3)  # let the subscriber's declaration reach the publisher
    for i in range(20):
        pub.publish("/robot1/scan", LaserScan(ranges=np.full(360, float(i)),
                                              angle_increment=0.0175))
    assert _wait(lambda: len(remote) >= 20)
    got = remote.drain()
    assert [s.ranges[0] for s in got] == list(range(20))
    assert got[0].ranges.shape == (360,)
    assert len(local.drain()) == 20  # no echo from the transport
    st = b.stats["/robot1/scan"]
    assert st.received == 20 and st.decode_errors == 0 and st.lost == 0
    assert 0 < time.time_ns() - st.last_source_ns < 5e9


def test_partition_and_heal(pair):
    a, b = pair
    pub = Bus(transport=a).node("robot")
    pub.advertise("/robot1/cmd_vel", Twist)
    sub = Bus(transport=b).node("twin").subscribe("/robot1/cmd_vel", Twist)
    time.sleep(0.3)
    pub.publish("/robot1/cmd_vel", Twist(linear=np.array([1.0, 0, 0])))
    assert _wait(lambda: len(sub) == 1)
    b.partition()
    assert not b.connected
    pub.publish("/robot1/cmd_vel", Twist(linear=np.array([2.0, 0, 0])))  # lost
    time.sleep(0.1)
    b.heal()
    assert b.wait_for_peers(1, 5.0)
    time.sleep(0.3)
    pub.publish("/robot1/cmd_vel", Twist(linear=np.array([3.0, 0, 0])))
    assert _wait(lambda: len(sub) == 2)
    assert [t.linear[0] for t in sub.drain()] == [1.0, 3.0]
    assert b.stats["/robot1/cmd_vel"].lost == 1  # the sequence-number gap is seen


def test_clock_offset_estimate(pair):
    a, b = pair
    skew_ns = 2_500_000_000  # the robot's clock runs 2.5 s ahead
    ClockResponder(Bus(transport=a), "robot1", clock_ns=lambda: time.time_ns() + skew_ns)
    probe = ClockProbe(Bus(transport=b), "twin")
    time.sleep(0.3)
    for _ in range(5):
        probe.ping()
        time.sleep(0.02)
    assert _wait(lambda: probe.offset_s("robot1") is not None)
    # exact whatever the load: the four-timestamp estimate is off by at most half the
    # round trip of the sample it comes from (the one with the smallest round trip)
    off, rtt = probe.offset_s("robot1"), probe.rtt_s("robot1")
    assert 0 < rtt < 5.0
    assert abs(off - 2.5) <= rtt / 2 + 1e-6
    assert probe.to_local("robot1", 102.5) == pytest.approx(102.5 - off, abs=1e-9)
    assert probe.offset_s("nobody") is None


def test_tf_static_is_latched_for_a_late_joiner(port):
    """/tf_static is TRANSIENT_LOCAL: published before the subscriber exists, still delivered
    (zenoh-ext advanced publisher cache + advanced subscriber history, as rmw_zenoh)."""
    from isac_twin.bus.msgs import Header, TFMessage, TransformStamped

    a = ZenohTransport(ZenohConfig(listen=[f"tcp/127.0.0.1:{port}"]), name="a")
    b = None
    try:
        tf = TFMessage([TransformStamped(Header(1.5, "robot1/base_link"), "robot1/base_scan",
                                         np.array([-0.032, 0.0, 0.172]))])
        robot = Bus(transport=a).node("robot")
        robot.advertise("/tf_static", TFMessage)
        robot.advertise("/robot1/cmd_vel", Twist)
        robot.publish("/tf_static", tf)
        robot.publish("/robot1/cmd_vel", Twist())  # volatile: not for late joiners
        time.sleep(0.2)
        b = ZenohTransport(ZenohConfig(connect=[f"tcp/127.0.0.1:{port}"]), name="b")
        bus = Bus(transport=b)
        late = bus.node("late")
        got = late.subscribe("/tf_static", TFMessage)
        vol = late.subscribe("/robot1/cmd_vel", Twist)
        deadline = time.monotonic() + 5
        msgs = []
        while not msgs and time.monotonic() < deadline:
            msgs = got.drain()
            time.sleep(0.02)
        assert len(msgs) == 1
        t = msgs[0].transforms[0]
        assert (t.header.frame_id, t.child_frame_id) == ("robot1/base_link", "robot1/base_scan")
        np.testing.assert_allclose(t.translation, [-0.032, 0.0, 0.172])
        assert vol.drain() == []
    finally:
        a.close()
        if b is not None:
            b.close()
