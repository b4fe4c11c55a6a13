"""The topic bus: typed topics, delivery order, registry, errors, threads, transports."""

import threading

import numpy as np
import pytest

from isac_twin.bus.bus import Bus, Transport, resolve_type
from isac_twin.bus.msgs import Imu, LaserScan, Odometry, Twist
from isac_twin.errors import BusError


def test_publish_subscribe_in_order_callback_and_queue():
    bus = Bus()
    pub, a, b = bus.node("pub"), bus.node("a"), bus.node("b")
    pub.advertise("/odom", Odometry)
    got = []
    a.subscribe("/odom", Odometry, lambda m: got.append(m.header.stamp))
    q = b.subscribe("/odom", "nav_msgs/msg/Odometry")
    for k in range(5):
        m = Odometry()
        m.header.stamp = float(k)
        pub.publish("/odom", m)
        assert got[-1] == k  # synchronous: delivered before publish returns
    assert got == [0, 1, 2, 3, 4]
    assert [m.header.stamp for m in q.drain()] == [0, 1, 2, 3, 4]
    assert q.take() is None and len(q) == 0


def test_bounded_queue_drops_oldest_and_counts():
    bus = Bus()
    p, s = bus.node("p"), bus.node("s")
    p.advertise("/cmd", Twist)
    sub = s.subscribe("/cmd", Twist, queue_size=2)
    for k in range(5):
        p.publish("/cmd", Twist(linear=np.array([k, 0.0, 0.0])))
    assert [m.linear[0] for m in sub.drain()] == [3, 4]
    assert sub.dropped == 3 and sub.received == 5


def test_wrong_type_and_unknown_type_are_refused():
    bus = Bus()
    n = bus.node("n")
    n.advertise("/scan", LaserScan)
    with pytest.raises(BusError, match=r"topic '/scan' carries sensor_msgs/msg/LaserScan, "
                                       r"node 'n' published a isac_twin\.bus\.msgs\.Imu"):
        n.publish("/scan", Imu())
    with pytest.raises(BusError, match="unknown message type 'sensor_msgs/msg/PointCloud2'"):
        n.advertise("/cloud", "sensor_msgs/msg/PointCloud2")
    with pytest.raises(BusError, match="not a message type"):
        n.advertise("/x", dict)
    with pytest.raises(BusError, match=r"carries sensor_msgs/msg/LaserScan; node 'm' "
                                       r"subscribes it as sensor_msgs/msg/Imu"):
        bus.node("m").subscribe("/scan", Imu)
    with pytest.raises(BusError, match="without advertising"):
        n.publish("/other", Imu())
    with pytest.raises(BusError, match="already exists"):
        bus.node("n")
    with pytest.raises(BusError, match="unknown topic"):
        bus.topic_type("/nope")
    assert resolve_type("sensor_msgs/msg/Imu") is Imu


def test_registry_lists_nodes_topics_types_and_counts():
    bus = Bus()
    sim, ui, rec = bus.node("sim"), bus.node("ui"), bus.node("recorder")
    sim.advertise("/r1/scan", LaserScan)
    sim.advertise("/r1/odom", Odometry)
    ui.subscribe("/r1/scan", LaserScan, lambda m: None)
    rec.subscribe("/r1/scan", LaserScan)
    rec.subscribe("/r1/odom", Odometry)
    ui.advertise("/r1/cmd_vel", Twist)
    sim.publish("/r1/scan", LaserScan())
    reg = bus.registry()
    scan = reg.topic("/r1/scan")
    assert scan.type_name == "sensor_msgs/msg/LaserScan"
    assert scan.publishers == ("sim",) and scan.subscribers == ("ui", "recorder")
    assert scan.messages == 1
    assert reg.topic("/r1/cmd_vel").subscribers == ()
    assert [n.name for n in reg.nodes] == ["recorder", "sim", "ui"]
    sim_info = next(n for n in reg.nodes if n.name == "sim")
    assert sim_info.publishes == ("/r1/odom", "/r1/scan")
    table = reg.table()
    assert "/r1/scan" in table and "sensor_msgs/msg/LaserScan" in table
    assert "ui, recorder" in table and "3 nodes" in table
    bus.remove_node("recorder")
    assert bus.registry().topic("/r1/scan").subscribers == ("ui",)


def test_publish_from_threads_keeps_per_publisher_order_and_loses_nothing():
    bus = Bus()
    sub = bus.node("sub").subscribe("/t", Twist)
    seen = []
    bus.node("cb").subscribe("/t", Twist, lambda m: seen.append(m))
    nodes = [bus.node(f"p{i}") for i in range(4)]
    for n in nodes:
        n.advertise("/t", Twist)

    def run(i, n):
        for k in range(500):
            n.publish("/t", Twist(linear=np.array([i, k, 0.0])))

    th = [threading.Thread(target=run, args=(i, n)) for i, n in enumerate(nodes)]
    for t in th:
        t.start()
    for t in th:
        t.join()
    msgs = sub.drain()
    assert len(msgs) == 2000 and len(seen) == 2000
    assert [id(m) for m in msgs] == [id(m) for m in seen]  # one global order for all
    for i in range(4):
        ks = [m.linear[1] for m in msgs if m.linear[0] == i]
        assert ks == list(range(500))


class LoopbackTransport:
    """Two of these share a list of peers: what a zenoh transport would do over the wire."""

    def __init__(self, net):
        self.net, self.subs, self.advertised = net, {}, {}
        net.append(self)

    def advertise(self, topic, type_name):
        self.advertised[topic] = type_name

    def publish(self, topic, type_name, msg):
        if self not in self.net:  # closed
            return
        for peer in self.net:
            if peer is not self and topic in peer.subs:
                peer.subs[topic](topic, msg)

    def subscribe(self, topic, type_name, deliver):
        self.subs[topic] = deliver

    def close(self):
        self.net.remove(self)


def test_transport_protocol_bridges_two_buses():
    net = []
    ta, tb = LoopbackTransport(net), LoopbackTransport(net)
    assert isinstance(ta, Transport)
    a, b = Bus(transport=ta), Bus(transport=tb)
    robot = a.node("robot")
    robot.advertise("/r/odom", Odometry)
    local = a.node("local").subscribe("/r/odom", Odometry)
    remote = b.node("viewer").subscribe("/r/odom", Odometry)
    robot.publish("/r/odom", Odometry())
    assert len(local.drain()) == 1  # no echo back into bus a
    assert len(remote.drain()) == 1
    assert ta.advertised == {"/r/odom": "nav_msgs/msg/Odometry"}
    ta.close()
    robot.publish("/r/odom", Odometry())
    assert len(remote.drain()) == 0


def test_has_subscribers_tells_a_publisher_whether_anyone_receives():
    """Issue 19: the twin builds its CSI only for a consumer. A topic has
    subscribers while a local node subscribes to it (callback or queued, until the
    node is removed); a bus with a transport always may (remote peers)."""
    bus = Bus()
    pub = bus.node("pub")
    pub.advertise("/r/scan", LaserScan)
    assert not bus.has_subscribers("/r/scan") and not bus.has_subscribers("/never")
    bus.node("viewer").subscribe("/r/scan", LaserScan)
    assert bus.has_subscribers("/r/scan")
    bus.remove_node("viewer")
    assert not bus.has_subscribers("/r/scan")
    seen = []
    bus.node("cb").subscribe("/r/scan", LaserScan, seen.append)
    assert bus.has_subscribers("/r/scan")
    assert Bus(transport=LoopbackTransport([])).has_subscribers("/r/scan")
