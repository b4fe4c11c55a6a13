"""engine/bus/frames.py + the twin's /tf, /tf_static and /clock (REP-105).

The tf tree is checked the way RViz would use it: chain the published transforms
(4x4 matrices built here from the quaternions) from ``map`` to each robot's
``base_footprint`` and compare with the robot's ``/ground_truth`` topic; the
``odom -> base_footprint`` link must equal the ``/odom`` message.
"""

import math

import numpy as np
import pytest

from isac_twin import Twin
from isac_twin.bus.frames import dynamic_tf, planar_compose, planar_inverse, robot_prefix
from isac_twin.scene.synthetic import ROBOT_EXTRA, SyntheticDevice, box_room


def _matrix(t):
    x, y, z, w = t.rotation
    R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                  [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                  [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = R, t.translation
    return M


def _chain(tfs, parent, child):
    """parent -> child as a 4x4 matrix by walking child's parents up to ``parent``."""
    by_child = {t.child_frame_id: t for t in tfs}
    M, f = np.eye(4), child
    while f != parent:
        if f not in by_child:
            raise AssertionError(f"frame {f!r} has no parent in the tree (looking for {parent})")
        t = by_child[f]
        M = _matrix(t) @ M
        f = t.header.frame_id
    return M


def test_planar_algebra():
    a, b = np.array([1.0, 2.0, 0.7]), np.array([-0.3, 0.5, -1.2])
    np.testing.assert_allclose(planar_compose(a, planar_inverse(a)), 0, atol=1e-12)
    ab = planar_compose(a, b)
    c, s = math.cos(0.7), math.sin(0.7)
    np.testing.assert_allclose(ab, [1 - 0.3 * c - 0.5 * s, 2 - 0.3 * s + 0.5 * c, -0.5])
    tf = dynamic_tf(3.0, type("F", (), {"odom": "o", "base_footprint": "b"})(), a, b)
    np.testing.assert_allclose((_chain(tf, "map", "b"))[:2, 3], a[:2], atol=1e-12)
    assert robot_prefix("r2", 2) == "r2/" and robot_prefix("r2", 1) == ""


def _scene(tmp_path, n):
    devs = [SyntheticDevice("AP1", "access_point", "tx", (1.0, 1.0, 2.0))]
    devs += [SyntheticDevice(f"robot{i + 1}", "robot", "rx", (2.0 + i, 2.0, 0.0),
                             orientation=(0.0, 0.0, 0.3 * i), extra=dict(ROBOT_EXTRA))
             for i in range(n)]
    return box_room(tmp_path / f"room{n}", devices=devs,
                    links=[("AP1", f"robot{i + 1}") for i in range(n)])


@pytest.mark.slow
@pytest.mark.parametrize("n", [1, 2])
def test_twin_tf_tree_matches_ground_truth_and_odometry(tmp_path, n):
    tw = Twin.from_scene(_scene(tmp_path, n), seed=1, phy=False, sensing=False)
    tw.trace_schedule = lambda i: False  # frames only: no radio needed
    for i in range(n):
        tw.set_path(f"robot{i + 1}", {"kind": "circle", "centre": [2.5 + i, 2.0],
                                      "radius": 0.5})
    probe = tw.bus.node("probe")
    subs = {t: probe.subscribe(t, typ) for t, typ in
            (("/tf", "tf2_msgs/msg/TFMessage"), ("/tf_static", "tf2_msgs/msg/TFMessage"),
             ("/clock", "rosgraph_msgs/msg/Clock"))}
    gts = {i: probe.subscribe(f"/robot{i + 1}/ground_truth", "geometry_msgs/msg/PoseStamped")
           for i in range(n)}
    odos = {i: probe.subscribe(f"/robot{i + 1}/odom", "nav_msgs/msg/Odometry") for i in range(n)}
    scans = {i: probe.subscribe(f"/robot{i + 1}/scan", "sensor_msgs/msg/LaserScan")
             for i in range(n)}
    for _ in range(30):
        res = tw.step()
    static = [t for m in subs["/tf_static"].drain() for t in m.transforms]
    tf_msgs = subs["/tf"].drain()
    assert len(tf_msgs) == 30
    clocks = subs["/clock"].drain()
    assert clocks[-1].clock == pytest.approx(res.time_s)
    last = tf_msgs[-1].transforms
    assert all(t.header.stamp == pytest.approx(res.time_s) for t in last)
    for i in range(n):
        p = f"robot{i + 1}/" if n > 1 else ""
        gt = gts[i].drain()[-1]
        M = _chain(last + static, "map", f"{p}base_footprint")
        np.testing.assert_allclose(M[:2, 3], gt.pose.position[:2], atol=1e-9)
        yaw = math.atan2(M[1, 0], M[0, 0])
        q = gt.pose.orientation
        assert yaw == pytest.approx(math.atan2(2 * (q[3] * q[2]), 1 - 2 * q[2] ** 2), abs=1e-9)
        odo = odos[i].drain()[-1]
        assert (odo.header.frame_id, odo.child_frame_id) == (f"{p}odom", f"{p}base_footprint")
        O = _chain(last, f"{p}odom", f"{p}base_footprint")
        np.testing.assert_allclose(O[:2, 3], odo.pose.position[:2], atol=1e-9)
        scan = scans[i].drain()[-1]
        assert scan.header.frame_id == f"{p}base_scan"
        S = _chain(last + static, "map", scan.header.frame_id)
        np.testing.assert_allclose(S[2, 3], 0.010 + 0.172, atol=1e-9)  # burger URDF
    # exactly one static batch, with every robot's mounts
    assert len({t.child_frame_id for t in static}) == len(static) == 3 * n
