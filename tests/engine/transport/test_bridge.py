"""engine/transport/bridge.py: fusion of real robot data into a twin (in one process)."""

import math
import time

import numpy as np
import pytest

from isac_twin.bus.bus import Bus
from isac_twin.bus.msgs import Header, Odometry, Pose, PoseStamped, Twist
from isac_twin.robots.agent import RobotAgent, SensorOptions
from isac_twin.transport.bridge import FusionConfig, TwinBridge, _extrapolate
from isac_twin.transport.zenoh_transport import ZenohConfig, ZenohTransport
from isac_twin.utils.geometry import yaw_to_quaternion


class MiniTwin:
    """One robot agent on a bus, stepped without a scene."""

    def __init__(self, pose=(1.0, 2.0, 0, 0, 0, math.pi / 2)):
        self.bus = Bus()
        self.agents = {"robot1": RobotAgent("robot1", "burger", pose, self.bus, None,
                                            options=SensorOptions(lidar=False, noise=False))}
        self.t = 0.0

    def step(self):
        self.t += 0.05
        for a in self.agents.values():
            a.step(self.t, 0.05)
        return type("R", (), {"robots": {}})()


def _wait(pred, timeout=5.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline and not pred():
        time.sleep(0.01)
    return pred()


@pytest.fixture
def link(port):
    robot = ZenohTransport(ZenohConfig(listen=[f"tcp/127.0.0.1:{port}"]), name="robot")
    twin_t = ZenohTransport(ZenohConfig(connect=[f"tcp/127.0.0.1:{port}"]), name="twin")
    assert twin_t.wait_for_peers(1, 5.0)
    node = Bus(transport=robot).node("robot1")
    yield node, twin_t
    robot.close()


def test_odom_source_composes_with_initial_pose_and_blends(link):
    node, twin_t = link
    twin = MiniTwin()
    bridge = TwinBridge(twin, twin_t, fusion=FusionConfig(gain=0.5, stale_s=0.5,
                                                          source="odom"), clock_period_s=0)
    try:
        node.advertise("/robot1/odom", Odometry)
        time.sleep(0.3)
        now = time.time()
        node.publish("/robot1/odom", Odometry(header=Header(stamp=now), pose=Pose(
            position=np.array([0.5, 0.0, 0.0]), orientation=yaw_to_quaternion(0.0))))
        assert _wait(lambda: bridge.mirrors["robot1"].received == 1)
        bridge.sync()  # first sample: applied in full
        pose = twin.agents["robot1"].state.pose
        np.testing.assert_allclose(pose[[0, 1]], [1.0, 2.5], atol=1e-3)
        assert pose[5] == pytest.approx(math.pi / 2)
        node.publish("/robot1/odom", Odometry(header=Header(stamp=time.time()), pose=Pose(
            position=np.array([0.7, 0.0, 0.0]), orientation=yaw_to_quaternion(0.0))))
        assert _wait(lambda: bridge.mirrors["robot1"].received == 2)
        bridge.sync()  # within stale_s: half of the error
        assert twin.agents["robot1"].state.pose[1] == pytest.approx(2.6, abs=1e-3)
        # the real data is also on the twin's bus, beside the synthetic topics
        got = twin.bus.node("viewer").subscribe("/robot1/real/odom", Odometry)
        node.publish("/robot1/odom", Odometry(header=Header(stamp=time.time())))
        assert _wait(lambda: bridge.mirrors["robot1"].received == 3)
        bridge.sync()
        assert len(got) == 1
        st = bridge.status()["robot1"]
        assert st["connected"] and st["corrections"] == 3 and st["catchups"] == 1
    finally:
        bridge.close()


def test_pose_estimate_source_and_cmd_vel_forwarding(link):
    node, twin_t = link
    twin = MiniTwin()
    bridge = TwinBridge(twin, twin_t, fusion=FusionConfig(gain=1.0), clock_period_s=0)
    try:
        cmds = node.subscribe("/robot1/cmd_vel", Twist)
        node.advertise("/robot1/pose_estimate", PoseStamped)
        twin.agents["robot1"].drive(lambda st: Twist(linear=np.array([0.1, 0, 0])))
        time.sleep(0.3)
        node.publish("/robot1/pose_estimate", PoseStamped(
            header=Header(stamp=time.time() - 0.2, frame_id="map"),
            pose=Pose(position=np.array([3.0, 1.0, 0.0]), orientation=yaw_to_quaternion(0.0))))
        odom = Odometry(header=Header(stamp=time.time()), twist=Twist(linear=np.array([0.5, 0, 0])))
        node.advertise("/robot1/odom", Odometry)
        node.publish("/robot1/odom", odom)  # the velocity used to extrapolate
        assert _wait(lambda: bridge.mirrors["robot1"].received == 1
                     and bridge.mirrors["robot1"].velocity[0] == 0.5)
        bridge.step()
        x = twin.agents["robot1"].state.pose[0]
        assert 3.0 + 0.5 * 0.15 < x < 3.0 + 0.5 * 0.5 + 0.02  # latency compensated
        assert _wait(lambda: len(cmds) >= 1)
        assert cmds.drain()[0].linear[0] == pytest.approx(0.1)
    finally:
        bridge.close()


def test_extrapolate_arc():
    np.testing.assert_allclose(_extrapolate(np.array([0.0, 0, 0]), np.array([1.0, 0]), 0.5),
                               [0.5, 0, 0])
    end = _extrapolate(np.array([0.0, 0, 0]), np.array([math.pi / 2, math.pi / 2]), 1.0)
    np.testing.assert_allclose(end, [1.0, 1.0, math.pi / 2], atol=1e-12)
