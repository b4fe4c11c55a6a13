"""engine/transport/cdr.py: every bus message type round-trips through ROS 2 CDR."""

import math

import numpy as np
import pytest

from isac_twin.bus import msgs as m
from isac_twin.bus import twin_msgs as tm
from isac_twin.bus.msgs import MESSAGE_TYPES
from isac_twin.transport import cdr

STAMP = 1_763_000_000.123456789


def _sample(type_name: str):
    """A message of each type with non-default values in every field."""
    rng = np.random.default_rng(1)
    h = m.Header(stamp=STAMP, frame_id="f")
    q = np.array([0.0, 0.0, math.sin(0.3), math.cos(0.3)])
    cov6 = rng.normal(size=(6, 6))
    cov3 = rng.normal(size=(3, 3))
    return {
        "geometry_msgs/msg/Vector3": m.Vector3(1.0, -2.0, 3.5),
        "geometry_msgs/msg/Pose": m.Pose(np.array([1.0, 2.0, 3.0]), q),
        "geometry_msgs/msg/PoseStamped": m.PoseStamped(h, m.Pose(np.array([1.0, 2, 3]), q)),
        "geometry_msgs/msg/Twist": m.Twist(np.array([0.2, 0, 0]), np.array([0, 0, -0.5])),
        "nav_msgs/msg/Odometry": m.Odometry(h, "base_link", m.Pose(np.array([1.0, 2, 0]), q),
                                            cov6, m.Twist(np.array([0.1, 0, 0]),
                                                          np.array([0, 0, 0.2])), cov6.T),
        "sensor_msgs/msg/Imu": m.Imu(h, q, cov3, np.array([0.1, 0.2, 0.3]), cov3 * 2,
                                     np.array([0.0, 0.1, 9.81]), cov3 * 3),
        "sensor_msgs/msg/LaserScan": m.LaserScan(h, -math.pi, math.pi, 0.0175, 1e-4, 0.18,
                                                 0.12, 12.0,
                                                 np.array([1.0, np.inf, 2.5, 0.5]),
                                                 np.array([10.0, 0.0, 47.0, 3.0])),
        "sensor_msgs/msg/Image": m.Image(h, 2, 3, "rgb8",
                                         rng.integers(0, 255, (2, 3, 3)).astype(np.uint8)),
        "sensor_msgs/msg/BatteryState": m.BatteryState(h, 12.1),
        "sensor_msgs/msg/JointState": m.JointState(h, ["wheel_left_joint", "wheel_right_joint"],
                                                   np.array([1.5, -2.0]), np.array([0.1, 0.2]),
                                                   np.array([0.0, 0.3])),
        "isac_twin_msgs/msg/LinkMetrics": tm.LinkMetrics(h, "AP1", "robot1", 23.5, 1.2e8, 7,
                                                         True, -61.2, 6.1e7),
        "isac_twin_msgs/msg/LinkPaths": tm.LinkPathsMsg(
            h, "AP1", "robot1", 3.5e9, np.array([0.1, 2.0, 2.0]), np.array([4.0, 2.0, 0.25]),
            rng.normal(size=3) + 1j * rng.normal(size=3), np.array([1e-8, 2e-8, 3e-8]),
            np.array([0.0, 1.0, -1.0]), rng.random(3), rng.random(3), rng.random(3),
            rng.random(3), rng.random((3, 2, 3)), np.array([[0, 0], [1, 0], [1, 2]], np.int32)),
        "isac_twin_msgs/msg/Fingerprint": tm.Fingerprint(h, "robot1", "AP1", 2.5e-9,
                                                         rng.random(16), np.array([1.0, 2, 0.25]),
                                                         0.8),
        "isac_twin_msgs/msg/Csi": tm.Csi(h, "AP1", "robot1",
                                         (rng.normal(size=(2, 4, 2, 1))
                                          + 1j * rng.normal(size=(2, 4, 2, 1))).astype(np.complex64)),
        "isac_twin_msgs/msg/PathCommand": tm.PathCommand.from_spec(
            {"kind": "polyline", "waypoints": [[1, 1], [2, 1], [2, 2]], "closed": True,
             "speed": 0.15}, STAMP),
        "isac_twin_msgs/msg/ClockPing": tm.ClockPing("twin", "robot1", 7, 10, 20, 30),
        "isac_twin_msgs/msg/Detections": _detections(h, rng),
        "geometry_msgs/msg/TransformStamped": m.TransformStamped(h, "c", np.array([1.0, 2, 3]), q),
        "tf2_msgs/msg/TFMessage": m.TFMessage([m.TransformStamped(h, "c", np.array([1.0, 2, 3]),
                                                                  q)] * 2),
        "rosgraph_msgs/msg/Clock": m.Clock(STAMP),
        "diagnostic_msgs/msg/DiagnosticArray": m.DiagnosticArray(h, [
            m.DiagnosticStatus(m.DiagnosticStatus.ERROR, "RPLidar", "never connected: no such file",
                               "pty:///tmp/ttyUSB0", [("connects", "0"), ("frames_bad", "12")]),
            m.DiagnosticStatus(m.DiagnosticStatus.OK, "runtime", "up", "robot1", [])]),
    }[type_name]


def _detections(h, rng):
    from isac_twin.bus.sensing_msgs import Detections

    return Detections(h, "AP2->AP1", rng.random(2) + 3, rng.normal(size=2), rng.random(2),
                      np.array([np.nan, 1.2]), rng.random(2) * 20,
                      np.array([[1.0, 2.0, 0.1], [np.nan, np.nan, np.nan]]),
                      np.array([3, 9], np.int64), rng.random((2, 2)), rng.normal(size=(2, 2)))


def _assert_same(a, b, path="msg"):
    assert type(a) is type(b), path
    for k, va in vars(a).items():
        vb = getattr(b, k)
        where = f"{path}.{k}"
        if hasattr(va, "__dataclass_fields__"):
            _assert_same(va, vb, where)
        elif isinstance(va, np.ndarray):
            assert np.shape(vb) == va.shape, where
            tol = 1e-6 if va.dtype in (np.float32, np.complex64) else 1e-12
            np.testing.assert_allclose(np.asarray(vb), va, rtol=tol, atol=tol, err_msg=where)
        elif isinstance(va, list) and va and hasattr(va[0], "__dataclass_fields__"):
            assert len(vb) == len(va), where
            for i, (x, y) in enumerate(zip(va, vb)):
                _assert_same(x, y, f"{where}[{i}]")
        elif isinstance(va, float):
            assert vb == pytest.approx(va, rel=1e-6, abs=1e-6) or (math.isnan(va) and math.isnan(vb)), where
        else:
            assert vb == va, where


@pytest.mark.parametrize("type_name", sorted(MESSAGE_TYPES))
def test_round_trip_every_type(type_name):
    msg = _sample(type_name)
    data = cdr.encode(msg)
    assert data[:4] == cdr.CDR_HEADER
    back = cdr.decode(data, type_name)
    _assert_same(msg, back)
    assert cdr.encode(back) == data  # stable: a second round trip is byte-identical


def test_every_bus_type_has_a_sample():
    for t in MESSAGE_TYPES:
        assert _sample(t).ROS_TYPE == t


def test_stamp_split_and_covariance_flattening():
    ts = cdr.typestore()
    odom = _sample("nav_msgs/msg/Odometry")
    raw = ts.deserialize_cdr(cdr.encode(odom), "nav_msgs/msg/Odometry")
    assert raw.header.stamp.sec == 1_763_000_000
    assert abs(raw.header.stamp.nanosec - 123_456_789) <= 1000  # float64 s keeps ~0.2 us
    assert raw.pose.covariance.shape == (36,)
    np.testing.assert_array_equal(raw.pose.covariance, odom.pose_covariance.ravel())
    t = cdr.stamp_to_ros(2.9999999999)
    assert (t.sec, t.nanosec) == (3, 0)  # nanosecond rounding carries into seconds


def test_image_encodings_round_trip():
    depth = m.Image(m.Header(1.0, "cam"), 2, 3, "16UC1",
                    np.arange(6, dtype=np.uint16).reshape(2, 3) * 1000)
    back = cdr.decode(cdr.encode(depth), "sensor_msgs/msg/Image")
    assert back.data.dtype == np.uint16 and back.data.shape == (2, 3)
    np.testing.assert_array_equal(back.data, depth.data)
    raw = cdr.typestore().deserialize_cdr(cdr.encode(depth), "sensor_msgs/msg/Image")
    assert raw.step == 6 and raw.is_bigendian == 0


def test_decode_rejects_non_cdr():
    with pytest.raises(ValueError, match="not a CDR payload"):
        cdr.decode(b"\x07\x07\x00\x00abcd", "geometry_msgs/msg/Twist")


def test_type_hashes_match_ros2():
    # published REP-2011 hashes of Jazzy's std_msgs/String and geometry_msgs/Twist
    assert cdr.type_hash("std_msgs/msg/String") == (
        "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18")
    assert cdr.type_hash("geometry_msgs/msg/Twist") == (
        "RIHS01_9c45bf16fe0983d80e3cfe750d6835843d265a9a6c46bd2e609fcddde6fb8d2a")


def test_custom_message_definitions_are_self_contained():
    text = cdr.msgdef("isac_twin_msgs/msg/Fingerprint")
    assert text.startswith("std_msgs/Header header")
    assert "MSG: geometry_msgs/Point" in text and "MSG: builtin_interfaces/Time" in text


def test_path_command_spec_round_trip():
    for spec in ({"kind": "circle", "centre": [4.0, 3.0], "radius": 1.5, "direction": "cw"},
                 {"kind": "figure_eight", "centre": [1.0, 2.0], "size": 1.0},
                 {"kind": "goal", "goal": [1.0, 2.0], "speed": 0.1}):
        msg = cdr.decode(cdr.encode(tm.PathCommand.from_spec(spec)), tm.PathCommand.ROS_TYPE)
        assert msg.to_spec() == spec
    assert tm.PathCommand().to_spec() is None
