"""engine/transport/record.py: MCAP recording (ros2 profile, CDR), crash recovery, replay."""

import os
import signal
import subprocess
import sys
import textwrap
import time
from collections import Counter

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader
from mcap_ros2.decoder import DecoderFactory

from isac_twin import LinkPaths, LinkState, RobotState, StepResult
from isac_twin.bus.bus import Bus
from isac_twin.bus.msgs import Header, LaserScan, Twist
from isac_twin.bus.twin_msgs import Fingerprint
from isac_twin.robots.agent import RobotAgent, SensorOptions
from isac_twin.robots.control import CirclePath, PurePursuit
from isac_twin.transport.record import (
    LINKS_TOPIC,
    PATHS_TOPIC,
    CsiRecording,
    McapRecorder,
    TrajectoryReplay,
    read_messages,
    read_metadata,
    record_twin,
    recover,
    replay_to_bus,
)


class _Decoded:
    def __init__(self, schema, channel, message, ros_msg):
        self.schema, self.channel, self.ros_msg = schema, channel, ros_msg
        self.log_time_ns, self.publish_time_ns = message.log_time, message.publish_time


def _decoded(path, topics=None):
    """Every message decoded by mcap's reader with the mcap_ros2 decoder."""
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        return [_Decoded(*x) for x in reader.iter_decoded_messages(topics=topics)]


class FakeTwin:
    """The twin's interface as record_twin / TrajectoryReplay use it, without a scene:
    real RobotAgents on a bus, one synthetic link traced from each robot's pose."""

    def __init__(self, dt=0.05, circle=True):
        self.dt, self.time_s, self.step_index, self.seed = dt, 0.0, 0, 0
        self.bus = Bus()
        opts = SensorOptions(lidar=False, noise=False)
        self.agents = {"robot1": RobotAgent("robot1", "burger", (2.0, 1.0, 0, 0, 0, np.pi / 2),
                                            self.bus, None, options=opts)}
        if circle:
            self.agents["robot1"].drive(PurePursuit(CirclePath((1.5, 1.0), 0.5), "burger"))
        self.state_sources = {}

    def set_state_source(self, robot, source):  # as Twin.set_state_source
        if source is None:
            self.state_sources.pop(robot, None)
        else:
            self.state_sources[robot] = source

    def step(self):
        t = self.time_s + self.dt
        for n, a in self.agents.items():
            if n in self.state_sources:
                a.place(self.state_sources[n](t, self.dt), t)
                continue
            ctl, a.controller = a.controller, None
            a.step(t, self.dt)
            a.controller = ctl
        res = StepResult(step=self.step_index, time_s=t)
        for n, a in self.agents.items():
            st = a.state
            res.robots[n] = RobotState(n, st.pose.copy(), np.array([st.v, st.w]))
            d = float(np.linalg.norm(st.position - np.array([0.0, 0.0, 2.0])))
            lp = LinkPaths("AP1", n, np.array([0.0, 0.0, 2.0]), st.position, np.zeros(3),
                           np.zeros(3), 3.5e9, np.array([1e-3 / d + 0j]), np.array([d / 3e8]),
                           np.zeros(1), np.zeros(1), np.zeros(1), np.zeros(1), np.zeros(1),
                           np.zeros((1, 0, 3)), np.zeros((1, 0), np.int32))
            res.links[("AP1", n)] = LinkState("AP1", n, lp, snr_db=20.0, rate_bps=1e8)
        for n, a in self.agents.items():
            if a.controller is not None and n not in self.state_sources:
                a._ctl_node.publish(a.topics["cmd_vel"], a.controller(a.state))
        self.step_index += 1
        self.time_s = t
        return res


def test_recording_reads_back_with_mcap_ros2(tmp_path):
    out = tmp_path / "bus.mcap"
    bus = Bus()
    node = bus.node("robot")
    node.advertise("/robot1/scan", LaserScan)
    node.advertise("/robot1/cmd_vel", Twist)
    rec = McapRecorder(out, metadata={"note": "unit"})
    rec.attach(bus)
    for i in range(10):
        node.publish("/robot1/scan", LaserScan(header=Header(stamp=100.0 + i, frame_id="laser"),
                                               ranges=np.full(8, i + 0.5)))
        node.publish("/robot1/cmd_vel", Twist(linear=np.array([0.01 * i, 0, 0])))
    node.advertise("/robot1/fingerprint", Fingerprint)  # a topic that appears later
    rec.refresh()
    node.publish("/robot1/fingerprint", Fingerprint(robot="robot1", estimate=np.ones(3)))
    rec.close()
    decoded = _decoded(out)
    assert Counter(m.channel.topic for m in decoded) == {
        "/robot1/scan": 10, "/robot1/cmd_vel": 10, "/robot1/fingerprint": 1}
    scans = [m for m in decoded if m.channel.topic == "/robot1/scan"]
    assert scans[3].schema.name == "sensor_msgs/msg/LaserScan"
    assert scans[3].schema.encoding == "ros2msg" and scans[3].channel.message_encoding == "cdr"
    assert list(scans[3].ros_msg.ranges) == [3.5] * 8
    assert scans[3].ros_msg.header.stamp.sec == 103
    assert scans[3].publish_time_ns == 103_000_000_000
    fp = [m for m in decoded if m.channel.topic == "/robot1/fingerprint"][0]
    assert fp.ros_msg.estimate.x == 1.0
    assert read_metadata(out)["note"] == "unit"
    # our own reader gives the engine dataclasses back
    ours = [r.decode() for r in read_messages(out, ["/robot1/cmd_vel"])]
    assert [t.linear[0] for t in ours] == pytest.approx([0.01 * i for i in range(10)])


def test_record_twin_links_paths_and_replay(tmp_path):
    out = tmp_path / "twin.mcap"
    twin = FakeTwin()
    rec = record_twin(twin, 40, out, metadata={"scene": "fake"})
    topics = Counter(m.topic for m in read_messages(out))
    assert topics[LINKS_TOPIC] == 40 and topics[PATHS_TOPIC] == 40
    assert topics["/robot1/ground_truth"] == 40 and topics["/robot1/cmd_vel"] == 40
    assert rec.messages == sum(topics.values())
    msgs = _decoded(out, [PATHS_TOPIC])
    assert msgs[0].log_time_ns == 50_000_000  # the twin's simulated time
    assert msgs[-1].ros_msg.tau[0] > 0
    truth = [g.decode() for g in read_messages(out, ["/robot1/ground_truth"])]

    # replay on a bus, 20x faster than recorded (2 s recorded -> ~0.1 s)
    bus = Bus()
    got = bus.node("viewer").subscribe("/robot1/ground_truth", "geometry_msgs/msg/PoseStamped")
    t0 = time.perf_counter()
    n = replay_to_bus(out, bus, speed=20.0)
    assert n == sum(topics.values()) and len(got) == 40
    # paced: never faster than the recording at 20x (a lower bound holds under any load)
    span_s = (msgs[-1].log_time_ns - msgs[0].log_time_ns) * 1e-9
    assert time.perf_counter() - t0 >= span_s / 20.0

    # a fresh twin (robot elsewhere, no controller) re-traces along the recorded trajectory
    twin2 = FakeTwin(circle=False)
    twin2.agents["robot1"].robot.reset((0.5, 0.5, 0.0))
    rp = TrajectoryReplay(twin2, out)
    assert rp.steps == 40
    for k in range(40):
        res = twin2.step()
        np.testing.assert_allclose(res.robots["robot1"].pose[:2], truth[k].pose.position[:2],
                                   atol=1e-9)
    d_rec = [m.decode().tau[0] for m in read_messages(out, [PATHS_TOPIC])]
    assert res.links[("AP1", "robot1")].paths.tau[0] == pytest.approx(d_rec[-1])
    rp.detach()
    assert not twin2.state_sources


_CHILD = textwrap.dedent("""
    import sys, time
    import numpy as np
    from isac_twin.bus.msgs import Header, LaserScan
    from isac_twin.transport.record import McapRecorder
    rec = McapRecorder(sys.argv[1], chunk_size=16 * 1024)
    for i in range(int(sys.argv[2])):
        rec.write("/scan", LaserScan(header=Header(stamp=float(i)), ranges=np.full(90, float(i))),
                  log_time_ns=i)
    print("written", rec.messages, flush=True)
    time.sleep(60)   # killed here, never closes the file
""")


def test_recording_killed_mid_run_is_readable_up_to_its_last_chunk(tmp_path):
    out = tmp_path / "killed.mcap"
    n = 500  # ~ 440 bytes each -> ~ 13 full chunks of 16 KiB, the last one unwritten
    proc = subprocess.Popen([sys.executable, "-c", _CHILD, str(out), str(n)],
                            stdout=subprocess.PIPE, text=True, cwd=os.getcwd())
    try:
        line = proc.stdout.readline()
        assert line.split() == ["written", str(n)]
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
    assert proc.returncode == -signal.SIGKILL
    data = out.read_bytes()
    assert not data.endswith(b"\x89MCAP0\r\n") or len(data) < 16  # no footer magic at the end

    got = [m.decode() for m in read_messages(out)]
    per_chunk = (16 * 1024) // 440 + 2
    assert n - per_chunk <= len(got) < n  # only the open chunk is lost
    assert [s.header.stamp for s in got] == [float(i) for i in range(len(got))]

    # the same with mcap's own stream reader + the mcap_ros2 decoder, record by record
    decode = None
    seen = 0
    with open(out, "rb") as f:
        try:
            for rec in StreamReader(f).records:
                if isinstance(rec, Schema):
                    schema = rec
                elif isinstance(rec, Channel):
                    decode = DecoderFactory().decoder_for(rec.message_encoding, schema)
                elif isinstance(rec, Message):
                    msg = decode(rec.data)
                    assert msg.ranges[0] == seen
                    seen += 1
        except Exception:  # the truncated tail
            pass
    assert seen == len(got)

    # indexed readers need the summary the killed writer never wrote ...
    with pytest.raises(Exception):
        with open(out, "rb") as f:
            list(make_reader(f).iter_messages())
    # ... which recover() (and `isac-twin recover`) rewrites, losing nothing readable
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    from isac_twin.cli import main

    assert main(["recover", str(out)]) == 0
    fixed = tmp_path / "killed.recovered.mcap"
    assert out.read_bytes() == data  # the original is untouched
    with open(fixed, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        assert reader.get_summary().statistics.message_count == len(got)
        stamps = [m.header.stamp.sec for _, _, _, m in reader.iter_decoded_messages()]
    assert stamps == list(range(len(got)))
    with AnyReader([fixed], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as ar:
        msgs = [ar.deserialize(raw, c.msgtype) for c, _, raw in ar.messages()]
    assert [m.ranges[0] for m in msgs] == [float(i) for i in range(len(got))]
    assert main(["recover", str(tmp_path / "nope.mcap")]) == 2
    (tmp_path / "text.mcap").write_text("not an mcap")
    with pytest.raises(ValueError, match="not an MCAP file"):
        recover(tmp_path / "text.mcap")

    # cut inside a chunk: everything before that chunk still comes back
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) - 5000])
    got_cut = list(read_messages(cut))
    assert 0 < len(got_cut) < len(got)
    with pytest.raises(Exception):
        list(read_messages(cut, recover=False))


def test_channels_offer_qos_profiles_that_rosbags_parses(tmp_path):
    """rosbag2's offered_qos_profiles in each channel, read back by rosbags (an independent
    rosbag2 implementation): /tf_static latched (transient local), scans best effort."""
    from rosbags.highlevel import AnyReader
    from rosbags.interfaces import QosDurability, QosReliability

    from isac_twin.bus.msgs import TFMessage, TransformStamped

    out = tmp_path / "qos.mcap"
    with McapRecorder(out) as rec:
        rec.write("/tf_static", TFMessage([TransformStamped(Header(1.0, "base_link"),
                                                            "base_scan")]))
        rec.write("/robot1/scan", LaserScan(header=Header(1.0, "base_scan")))
        rec.write("/robot1/cmd_vel", Twist())
    with AnyReader([out]) as ar:
        qos = {c.topic: c.ext.offered_qos_profiles[0] for c in ar.connections}
    assert qos["/tf_static"].durability == QosDurability.TRANSIENT_LOCAL
    assert qos["/tf_static"].depth == 1
    assert qos["/robot1/scan"].reliability == QosReliability.BEST_EFFORT
    assert qos["/robot1/cmd_vel"].reliability == QosReliability.RELIABLE
    with open(out, "rb") as f:
        assert make_reader(f).get_header().profile == "ros2"
    with open(out, "rb") as f:
        summary = make_reader(f).get_summary()
    assert {ci.compression for ci in summary.chunk_indexes} == {"zstd"}  # the default


def test_stamp_epoch_time_chunks_and_compact_csi(tmp_path):
    """Stamps moved onto a wall-clock epoch (nested TF headers and /clock too); a chunk
    spans at most max_chunk_s of log time; CSI decimated 1/14 symbols, 1/16 subcarriers."""
    from isac_twin.bus.msgs import Clock, Csi, TFMessage, TransformStamped

    epoch = 1_763_000_000.0
    out = tmp_path / "epoch.mcap"
    h = (np.arange(14 * 1024 * 2 * 4).reshape(14, 1024, 2, 4) * (1 + 1j)).astype(np.complex64)
    with McapRecorder(out, stamp_offset_s=epoch, max_chunk_s=1.0,
                      transforms={Csi.ROS_TYPE: CsiRecording()}) as rec:
        for i in range(50):  # 5 s of log time at 10 Hz
            t = 0.1 * i
            lt = int((epoch + t) * 1e9)
            rec.write("/clock", Clock(t), log_time_ns=lt)
            rec.write("/tf", TFMessage([TransformStamped(Header(t, "map"), "odom")]),
                      log_time_ns=lt)
            if i == 0:
                rec.write("/robot1/csi", Csi(Header(t, "robot1/base_link"), "AP1", "robot1", h),
                          log_time_ns=lt)
    got = {m.topic: [] for m in read_messages(out)}
    for m in read_messages(out):
        got[m.topic].append(m.decode())
    assert got["/clock"][3].clock == pytest.approx(epoch + 0.3, abs=1e-6)
    assert got["/tf"][3].transforms[0].header.stamp == pytest.approx(epoch + 0.3, abs=1e-6)
    csi = got["/robot1/csi"][0]
    assert csi.h.shape == (1, 64, 2, 4)
    np.testing.assert_array_equal(csi.h, h[::14, ::16])
    assert csi.header.stamp == pytest.approx(epoch, abs=1e-6)
    with open(out, "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    assert 5 <= len(chunks) <= 6
    assert max(c.message_end_time - c.message_start_time for c in chunks) < 1e9
    with pytest.raises(ValueError, match="subcarrier_step"):
        CsiRecording(subcarrier_step=0)
    with pytest.raises(ValueError, match="stamp_offset_s"):
        McapRecorder(tmp_path / "x.mcap", stamp_offset_s=float("nan"))


def test_diagnostics_are_recorded_and_read_back(tmp_path):
    """/diagnostics (issue 21) goes to MCAP like every other topic: mcap_ros2 decodes
    it with ROS' own definition, our reader gives the dataclasses back."""
    from isac_twin.bus.msgs import DiagnosticArray, DiagnosticStatus

    out = tmp_path / "diag.mcap"
    bus = Bus()
    node = bus.node("robot1")
    node.advertise("/diagnostics", DiagnosticArray)
    rec = McapRecorder(out)
    rec.attach(bus)
    msg = DiagnosticArray(Header(stamp=5.0), [DiagnosticStatus(DiagnosticStatus.ERROR, "robot1: RPLIDAR",
                                                               "never connected: no such file", "/dev/ttyUSB0",
                                                               [("connects", "0")])])
    node.publish("/diagnostics", msg)
    rec.close()
    decoded = _decoded(out)
    assert decoded[0].schema.name == "diagnostic_msgs/msg/DiagnosticArray"
    st = decoded[0].ros_msg.status[0]
    assert (st.level, st.name, st.values[0].key, st.values[0].value) == (2, "robot1: RPLIDAR", "connects", "0")
    assert [r.decode() for r in read_messages(out)] == [msg]


def test_csi_noise_at_an_snr(tmp_path):
    """CsiRecording(snr_db=...) adds white Gaussian noise whose measured power ratio is
    the SNR asked for; the same seed gives the same noise; bad values are refused."""
    from isac_twin.bus.msgs import Csi

    rng = np.random.default_rng(5)
    h = (rng.standard_normal((14, 1024, 2, 4)) + 1j * rng.standard_normal((14, 1024, 2, 4))
         ).astype(np.complex64) * 1e-4
    msg = Csi(Header(0.0, "robot1/base_link"), "AP1", "robot1", h)
    rec = CsiRecording(snr_db=20.0, seed=3)
    a = np.asarray(rec(msg).h)
    clean = h[::14, ::16]
    assert a.shape == clean.shape and a.dtype == np.complex64
    snr = 10 * np.log10(np.mean(np.abs(clean) ** 2) / np.mean(np.abs(a - clean) ** 2))
    assert snr == pytest.approx(20.0, abs=0.5)  # 512 complex samples
    b = np.asarray(CsiRecording(snr_db=20.0, seed=3)(msg).h)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(np.asarray(rec(msg).h), a)  # a new draw per message
    full = np.asarray(CsiRecording.full(snr_db=10.0)(msg).h)
    assert full.shape == h.shape and not np.array_equal(full, h)
    assert "noise at 20 dB SNR (seed 3)" in rec.describe()
    with pytest.raises(ValueError, match="snr_db: expected a finite number"):
        CsiRecording(snr_db=float("nan"))
