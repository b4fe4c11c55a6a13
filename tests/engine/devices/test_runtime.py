"""engine/devices/runtime.py and engine/transport/bridge.py: a robot runtime and a twin over zenoh."""

import math
import re
import signal
import socket
import subprocess
import sys
import time
from collections import Counter

import numpy as np
import pytest

from isac_twin.bus.msgs import Header, Odometry, Pose, Twist
from isac_twin.bus.twin_msgs import Fingerprint
from isac_twin.devices.runtime import (
    PoseEstimator,
    RobotRuntime,
    box_room_scan_source,
    load_robot_config,
    robot_config_from_dict,
)
from isac_twin.errors import RobotConfigError
from isac_twin.utils.geometry import yaw_to_quaternion


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait(pred, timeout=5.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.02)
    return pred()


ROBOT_TOML = """\
[robot]
name = "robot1"
model = "burger"
initial_pose = [{x}, {y}, {yaw}]
emulated = true

[emulation]
room = [{w}, {d}]

[network]
listen = ["tcp/127.0.0.1:{port}"]

[control]
rate_hz = 20.0
cmd_timeout_s = 0.5
"""


def test_robot_toml_parses_and_rejects_bad_values(tmp_path):
    p = tmp_path / "robot.toml"
    p.write_text(ROBOT_TOML.format(x=1, y=2, yaw=0.5, w=6, d=4, port=7447))
    cfg = load_robot_config(p)
    assert (cfg.name, cfg.model, cfg.emulated) == ("robot1", "burger", True)
    assert cfg.initial_pose == (1.0, 2.0, 0.5) and cfg.room == (6.0, 4.0)
    assert cfg.network.listen == ["tcp/127.0.0.1:7447"] and cfg.network.multicast is False
    for doc, match in (({"robot": {"model": "tank"}}, "model"),
                       ({"robot": {"initial_pose": [1, 2]}}, "initial_pose"),
                       ({"network": {"listen": ["127.0.0.1"]}}, "listen"),
                       ({"network": {"mode": "mesh"}}, "mode"),
                       ({"control": {"rate_hz": 0}}, "rate_hz"),
                       ({"robot": {"colour": "red"}}, "unknown key 'colour'"),
                       ({"robot": {"frame_prefix": "yes"}}, "frame_prefix"),
                       ({"lidar": {}}, r"unknown section \[lidar\]"),
                       # issue 21: these ended in tracebacks
                       ({"network": {"domain_id": "abc"}}, r"\[network\] domain_id = 'abc': expected an integer 0\.\.232"),
                       ({"drivers": {"rplidar_baudrate": "fast"}},
                        r"\[drivers\] rplidar_baudrate = 'fast': expected one of 115200, 256000"),
                       ({"network": {"listen": ["tcp/127.0.0.1:99999"]}}, r"listen.*port 99999.*0\.\.65535"),
                       ({"robot": {"initial_pose": [math.nan, 0, 0]}}, r"initial_pose = \[nan, 0, 0\].*finite"),
                       ({"robot": {"emulated": "yes"}}, r"\[robot\] emulated = 'yes': expected true or false"),
                       ({"drivers": {"opencr": 5}}, r"\[drivers\] opencr = 5: expected a port path"),
                       ({"drivers": {"oakd": 1.5}}, r"\[drivers\] oakd = 1\.5: expected true, false or"),
                       ({"emulation": {"lidar_rate_hz": 1}}, r"lidar_rate_hz = 1: expected 2\.\.20 Hz")):
        with pytest.raises(RobotConfigError, match=match):
            robot_config_from_dict(doc, "r.toml")
    bad = tmp_path / "latin1.toml"
    bad.write_bytes('[robot]\nname = "roböt"\n'.encode("latin-1"))
    with pytest.raises(RobotConfigError, match=r"latin1\.toml: not UTF-8 \(byte 0xf6 at offset 19\)"):
        load_robot_config(bad)


def test_pose_estimator_composes_odometry_and_fixes():
    est = PoseEstimator((1.0, 2.0, math.pi / 2), gain=0.5)
    est.on_odom(Odometry(header=Header(stamp=1.0), pose=Pose(
        position=np.array([1.0, 0.0, 0.0]), orientation=yaw_to_quaternion(0.0)),
        twist=Twist(linear=np.array([0.1, 0, 0]))))
    np.testing.assert_allclose(est.pose(), [1.0, 3.0, math.pi / 2], atol=1e-12)
    est.on_fix([1.2, 3.0], confidence=1.0)
    np.testing.assert_allclose(est.pose()[:2], [1.1, 3.0], atol=1e-12)
    assert tuple(est.velocity) == (0.1, 0.0)


def test_box_room_scan_source():
    src = box_room_scan_source(lambda: (1.0, 1.0, 0.0), (4.0, 3.0))
    r = src(np.array([0.0, math.pi / 2, math.pi, -math.pi / 2]))
    np.testing.assert_allclose(r, [3.0, 2.0, 1.0, 1.0])


@pytest.mark.slow
def test_runtime_in_process_follows_paths_and_times_out_cmd_vel():
    """Emulated devices -> drivers -> estimate -> control, with topics on a zenoh peer."""
    from isac_twin.bus.bus import Bus
    from isac_twin.transport.zenoh_transport import ZenohConfig, ZenohTransport

    port = _free_port()
    cfg = robot_config_from_dict({"robot": {"emulated": True, "initial_pose": [2.0, 2.0, 0.0],
                                            "frame_prefix": True},
                                  "network": {"listen": [f"tcp/127.0.0.1:{port}"]}})
    twin_side = ZenohTransport(ZenohConfig(connect=[f"tcp/127.0.0.1:{port}"]))
    rt = RobotRuntime(cfg).start()
    try:
        assert twin_side.wait_for_peers(1, 5.0)
        node = Bus(transport=twin_side).node("twin")
        est = node.subscribe("/robot1/pose_estimate", "geometry_msgs/msg/PoseStamped",
                             queue_size=1)
        scans = node.subscribe("/robot1/scan", "sensor_msgs/msg/LaserScan")
        tfs = node.subscribe("/tf", "tf2_msgs/msg/TFMessage")
        static = node.subscribe("/tf_static", "tf2_msgs/msg/TFMessage")  # joins late: latched
        odoms = node.subscribe("/robot1/odom", "nav_msgs/msg/Odometry")
        node.advertise("/robot1/cmd_vel", Twist)
        node.advertise("/robot1/fingerprint", Fingerprint)
        assert _wait(lambda: len(scans) > 0 and len(est) > 0, 5.0)
        scan = scans.drain()[-1]
        # REP-105 frames with the robot prefix, the same convention as the twin (isac_twin.bus.frames)
        assert scan.header.frame_id == "robot1/base_scan"
        assert _wait(lambda: len(tfs) > 0 and len(static) > 0 and len(odoms) > 0, 5.0)
        tf = tfs.drain()[-1].transforms
        assert [(t.header.frame_id, t.child_frame_id) for t in tf] == [
            ("map", "robot1/odom"), ("robot1/odom", "robot1/base_footprint")]
        np.testing.assert_allclose(tf[0].translation[:2], [2.0, 2.0], atol=1e-9)  # initial pose
        assert {t.child_frame_id for t in static.drain()[0].transforms} == {
            "robot1/base_link", "robot1/base_scan", "robot1/imu_link"}
        o = odoms.drain()[-1]
        assert (o.header.frame_id, o.child_frame_id) == ("robot1/odom", "robot1/base_footprint")
        assert len(scan.ranges) > 100 and np.nanmin(scan.ranges) == pytest.approx(2.0, abs=0.1)
        # twin teleop: the robot drives while commands are fresh, then stops by itself
        for _ in range(10):
            node.publish("/robot1/cmd_vel", Twist(linear=np.array([0.2, 0, 0])))
            time.sleep(0.05)
        assert rt.stats.mode == "teleop" and rt.sim.state.v > 0.1
        assert _wait(lambda: rt.stats.mode == "stopped" and abs(rt.sim.state.v) < 1e-3, 2.0)
        x_stop = rt.estimator.pose()[0]
        assert x_stop > 2.05
        # a fingerprint fix pulls the estimate
        node.publish("/robot1/fingerprint", Fingerprint(estimate=np.array([x_stop + 0.5, 2.0, 0]),
                                                        confidence=1.0))
        assert _wait(lambda: rt.stats.fingerprints_received == 1, 2.0)
        assert rt.estimator.pose()[0] == pytest.approx(x_stop + 0.15, abs=0.02)
    finally:
        rt.stop()
        twin_side.close()
    assert not rt.opencr.running and rt.emulators == []


def _twin_for(scene_dir):
    """A real Twin of the bundled scene without ray tracing, PHY or LiDAR (fast steps)."""
    from isac_twin import Twin, load_scene
    from isac_twin.robots import SensorOptions

    def oracle(twin, result):  # a stand-in localization estimator: fingerprints = truth
        for r in result.robots.values():
            r.estimate = r.pose[:3].copy()

    return Twin(load_scene(scene_dir, load_sionna=False), tracer=lambda scene, poses: {},
                phy=False, sensors=SensorOptions(lidar=False), estimators=[oracle],
                sensing=False)  # the lab's radar would trace with Sionna


@pytest.mark.slow
def test_twin_and_robot_runtime_in_two_processes(tmp_path):
    """The robot runtime (emulated devices) in a subprocess, the twin here; zenoh on
    loopback both ways; a partition; the recording of it decodes with mcap_ros2."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    from isac_twin import bundled_scene_dir
    from isac_twin.transport.bridge import FusionConfig, TwinBridge
    from isac_twin.transport.record import McapRecorder, read_messages
    from isac_twin.transport.zenoh_transport import ZenohConfig, ZenohTransport

    twin = _twin_for(bundled_scene_dir())
    x0, y0, yaw0 = (float(v) for v in twin.agents["robot1"].state.pose[[0, 1, 5]])
    port = _free_port()
    hi = twin.scene.bounds_max
    toml = tmp_path / "robot.toml"
    toml.write_text(ROBOT_TOML.format(x=x0, y=y0, yaw=yaw0, w=float(hi[0]), d=float(hi[1]),
                                      port=port))
    proc = subprocess.Popen([sys.executable, "-m", "isac_twin.cli", "robot", str(toml),
                             "--duration", "60"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    bridge = None
    try:
        line = proc.stdout.readline()
        assert "robot1 (burger, emulated) up" in line, line + proc.stderr.read()
        bridge = TwinBridge(twin, ZenohTransport(ZenohConfig(connect=[f"tcp/127.0.0.1:{port}"])),
                            fusion=FusionConfig(gain=0.8, stale_s=1.0), clock_period_s=0.2)
        assert bridge.transport.wait_for_peers(1, 10.0)
        rec = McapRecorder(tmp_path / "live.mcap")
        rec.attach(twin.bus)
        spec = {"kind": "circle", "centre": [x0, y0 + 0.4], "radius": 0.4}
        twin.set_path("robot1", spec)  # the twin's controller -> cmd_vel -> robot

        def run(seconds):
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                bridge.step()
                time.sleep(0.04)

        time.sleep(0.3)
        bridge.send_path("robot1", spec)  # the robot follows it on its own
        run(2.0)
        deadline = time.monotonic() + 6.0  # slack for a loaded machine
        while time.monotonic() < deadline and not (
                bridge.mirrors["robot1"].received > 10 and bridge.mirrors["robot1"].scans >= 3
                and bridge.status()["robot1"]["connected"]):
            run(0.2)
        st = bridge.status()["robot1"]
        assert st["connected"] and st["received"] > 10 and st["scans"] >= 3, (
            st, dict(bridge.transport.stats))
        assert st["corrections"] > 5 and st["catchups"] >= 1
        assert st["clock_offset_s"] == pytest.approx(0.0, abs=0.05)  # same host clock
        real = np.array(st["estimate"])
        assert math.dist(real[:2], (x0, y0)) > 0.05  # the real robot moves
        _wait(lambda: bridge.mirrors["robot1"].fresh, 2.0)
        bridge.sync()  # the twin follows it (gain 0.8 per step, latency compensated)
        real = bridge.mirrors["robot1"].estimate
        assert math.dist(twin.agents["robot1"].state.pose[:2], real[:2]) < 0.15

        # partition: the twin runs on its own, the robot keeps following its path
        bridge.transport.partition()
        before = np.array(bridge.mirrors["robot1"].estimate)
        run(1.5)
        assert not bridge.status()["robot1"]["connected"]
        bridge.transport.heal()
        assert bridge.transport.wait_for_peers(1, 10.0)
        catchups = bridge.mirrors["robot1"].catchups
        deadline = time.monotonic() + 10.0
        while bridge.mirrors["robot1"].catchups == catchups and time.monotonic() < deadline:
            bridge.step()
            time.sleep(0.02)
        assert bridge.mirrors["robot1"].catchups > catchups, (
            bridge.status(), bridge.transport.peers(), dict(bridge.transport.stats))
        after = np.array(bridge.mirrors["robot1"].estimate)
        assert math.dist(after[:2], before[:2]) > 0.1  # it drove on during the partition
        # caught up: the twin sits at the robot's estimate (extrapolated over its latency)
        assert math.dist(twin.agents["robot1"].state.pose[:2], after[:2]) < 0.1
        run(0.5)
        rec.close()
        # the robot's /diagnostics reached the twin, which recorded them
        diag = bridge.status()["robot1"]["diagnostics"]
        assert diag["runtime"][0] == 0 and diag["OpenCR"] == (0, "connected"), diag
        assert "/diagnostics" in {m.topic for m in read_messages(tmp_path / "live.mcap")}
    finally:
        if bridge is not None:
            bridge.close()
        proc.send_signal(signal.SIGTERM)
        try:
            out, err = proc.communicate(timeout=15)
        except subprocess.TimeoutExpired:
            proc.kill()
            out, err = proc.communicate()
    assert proc.returncode == 0, err
    stats = dict(re.findall(r"(\w+)=(\d+)", out))
    assert int(stats["paths_received"]) == 1
    assert int(stats["cmd_vel_received"]) > 20  # the twin's controller reached the robot
    assert int(stats["fingerprints_received"]) > 20

    with open(tmp_path / "live.mcap", "rb") as f:
        decoded = list(make_reader(f, decoder_factories=[DecoderFactory()])
                       .iter_decoded_messages())
    topics = Counter(ch.topic for _, ch, _, _ in decoded)
    assert topics["/robot1/real/scan"] >= 5 and topics["/robot1/real/pose_estimate"] > 20
    assert topics["/robot1/ground_truth"] > 20 and topics["/robot1/cmd_vel"] > 20
    scan = next(m for _, ch, _, m in decoded if ch.topic == "/robot1/real/scan")
    assert len(scan.ranges) > 100


def test_runtime_says_which_device_never_connected(tmp_path, caplog):
    """Serial ports that do not exist: the runtime keeps running, and at stop
    a WARNING and the per-device summary say that neither device ever connected."""
    import logging

    cfg = robot_config_from_dict({"drivers": {"opencr": str(tmp_path / "ttyACM7"), "rplidar": str(tmp_path / "ttyUSB7")},
                                  "network": {"listen": [f"tcp/127.0.0.1:{_free_port()}"]}})
    from isac_twin.bus.msgs import DiagnosticArray, DiagnosticStatus

    with caplog.at_level(logging.WARNING):
        rt = RobotRuntime(cfg, diagnostics_period_s=0.1)
        diags = rt.bus.node("probe").subscribe("/diagnostics", DiagnosticArray)
        rt.start()
        try:
            time.sleep(0.4)
        finally:
            rt.stop()
    # /diagnostics: one array per period with the runtime and every device, said as it is
    last = diags.drain()[-1]
    by_name = {st.name: st for st in last.status}
    assert set(by_name) == {"robot1: runtime", "robot1: OpenCR", "robot1: RPLIDAR"}
    assert by_name["robot1: OpenCR"].level == by_name["robot1: RPLIDAR"].level == DiagnosticStatus.WARN
    assert "connecting" in by_name["robot1: RPLIDAR"].message  # 0.4 s < connect_warn_s
    assert by_name["robot1: runtime"].level == DiagnosticStatus.WARN
    assert "not connected: OpenCR, RPLIDAR" in by_name["robot1: runtime"].message
    lines = rt.device_summaries()
    assert [ln.split(":")[0] for ln in lines] == ["OpenCR", "RPLIDAR"]
    assert all("NEVER connected" in ln and "No such file" in ln for ln in lines), lines
    warned = [r.getMessage() for r in caplog.records if "NEVER connected" in r.getMessage()]
    assert len(warned) == 2, warned
