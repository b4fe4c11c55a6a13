"""engine/utils/geometry.py: the one geometry convention (rotation, quaternions, angle
wrap) against scipy.spatial.transform.Rotation and hand-checked cases, and the one
antenna-pose function against hand-computed geometry."""

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from isac_twin.utils.geometry import (
    DevicePose,
    antenna_pose,
    euler_to_quaternion,
    planar_pose,
    quaternion_to_yaw,
    rotation_matrix,
    sionna_orientation,
    wrap_angle,
    yaw_to_quaternion,
)

#: random ZYX angles [N, 3] (roll, pitch, yaw), rad; pitch inside (-pi/2, pi/2)
RPY = np.column_stack([np.random.default_rng(7).uniform(-math.pi, math.pi, 50),
                       np.random.default_rng(8).uniform(-1.5, 1.5, 50),
                       np.random.default_rng(9).uniform(-math.pi, math.pi, 50)])


def test_offset_rotates_with_yaw_and_velocity_adds_the_lever_arm():
    # base at (1, 2, 0) facing +y, antenna 0.1 m ahead and 0.25 m up, driving 0.5 m/s
    # while turning at 2 rad/s: the antenna is at (1, 2.1, 0.25) and moves
    # 0.5 m/s along +y plus w x lever = 2 ez x (0, 0.1, 0.25) = (-0.2, 0, 0).
    p = antenna_pose(planar_pose(1.0, 2.0, math.pi / 2), (0.1, 0.0, 0.25), v=0.5, w=2.0)
    np.testing.assert_allclose(p.position, (1.0, 2.1, 0.25), atol=1e-12)
    np.testing.assert_allclose(p.orientation, (0.0, 0.0, math.pi / 2))
    np.testing.assert_allclose(p.velocity, (-0.2, 0.5, 0.0), atol=1e-12)


def test_full_rotation_uses_roll_and_pitch():
    # roll 90 deg turns the body's +z offset into world -y (REP-103, ZYX).
    p = antenna_pose((0, 0, 0, math.pi / 2, 0, 0), (0.0, 0.0, 1.0))
    np.testing.assert_allclose(p.position, (0.0, -1.0, 0.0), atol=1e-12)
    # pitch 90 deg turns body +x into world -z
    np.testing.assert_allclose(rotation_matrix(0, math.pi / 2, 0) @ [1, 0, 0], [0, 0, -1],
                               atol=1e-12)


def test_sionna_order_and_bad_input():
    assert sionna_orientation((0.1, 0.2, 0.3)) == (0.3, 0.2, 0.1)
    with pytest.raises(ValueError, match=r"pose: expected \[x, y, z, roll, pitch, yaw\]"):
        antenna_pose((1.0, 2.0, 0.3))
    with pytest.raises(ValueError, match="DevicePose.velocity: expected 3 numbers"):
        DevicePose((0, 0, 0), velocity=(1, 2))


def test_rotation_is_rep103_zyx_as_scipy_computes_it():
    """``rotation_matrix(roll, pitch, yaw)`` = Rz(yaw) Ry(pitch) Rx(roll): scipy's
    intrinsic ``"ZYX"`` with angles ``[yaw, pitch, roll]``, and the hand composition."""
    for r, p, y in RPY:
        ref = Rotation.from_euler("ZYX", [y, p, r]).as_matrix()
        np.testing.assert_allclose(rotation_matrix(r, p, y), ref, atol=1e-12)
    r, p, y = 1.1, -0.7, 0.3
    rz = np.array([[np.cos(y), -np.sin(y), 0], [np.sin(y), np.cos(y), 0], [0, 0, 1]])
    ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    rx = np.array([[1, 0, 0], [0, np.cos(r), -np.sin(r)], [0, np.sin(r), np.cos(r)]])
    np.testing.assert_allclose(rotation_matrix(r, p, y), rz @ ry @ rx, atol=1e-12)
    # Sionna's order is the reversal, and reversing twice is the identity
    assert sionna_orientation(sionna_orientation((r, p, y))) == (r, p, y)


def test_quaternions_are_ros_xyzw_as_scipy_computes_them():
    """``[x, y, z, w]`` (scipy's ``as_quat`` order, scalar last), equal up to the sign
    of a quaternion; the yaw of any unit quaternion is its ZYX Euler yaw."""
    for r, p, y in RPY:
        q = euler_to_quaternion(r, p, y)
        ref = Rotation.from_euler("ZYX", [y, p, r]).as_quat()
        np.testing.assert_allclose(q * np.sign(q @ ref), ref, atol=1e-12)
        np.testing.assert_allclose(Rotation.from_quat(q).as_matrix(), rotation_matrix(r, p, y),
                                   atol=1e-12)
        yq = yaw_to_quaternion(y)
        np.testing.assert_allclose(yq, Rotation.from_euler("z", y).as_quat(), atol=1e-15)
        assert yq[0] == yq[1] == 0.0  # exact zeros: no roll or pitch leaks into /tf
        assert quaternion_to_yaw(yq) == pytest.approx(y, abs=1e-12)
        assert quaternion_to_yaw(q) == pytest.approx(y, abs=1e-12)
        general = Rotation.from_quat(np.random.default_rng(int(1e3 * (r + 4))).normal(size=4))
        assert quaternion_to_yaw(general.as_quat()) == pytest.approx(
            general.as_euler("ZYX")[0], abs=1e-9)
    assert isinstance(quaternion_to_yaw([0.0, 0.0, 0.0, 1.0]), float)


def test_wrap_angle_is_half_open_at_pi():
    """Hand-checked: the range is [-pi, pi), so +pi and -pi both map to -pi; whole
    turns vanish; angles inside the range come back within an ulp of pi."""
    assert wrap_angle(math.pi) == -math.pi
    assert wrap_angle(-math.pi) == -math.pi
    assert wrap_angle(3 * math.pi) == -math.pi
    assert wrap_angle(0.0) == 0.0
    assert wrap_angle(2 * math.pi) == pytest.approx(0.0, abs=1e-15)
    assert wrap_angle(-2 * math.pi) == pytest.approx(0.0, abs=1e-15)
    assert wrap_angle(1.5 * math.pi) == pytest.approx(-0.5 * math.pi, abs=1e-15)
    assert wrap_angle(-1.5 * math.pi) == pytest.approx(0.5 * math.pi, abs=1e-15)
    assert wrap_angle(7.0) == pytest.approx(7.0 - 2 * math.pi, abs=1e-15)
    assert wrap_angle(-7.0) == pytest.approx(2 * math.pi - 7.0, abs=1e-15)
    assert wrap_angle(0.3) == pytest.approx(0.3, abs=4.5e-16)
    assert type(wrap_angle(1)) is float and type(wrap_angle(np.float64(4.0))) is float
    a = np.linspace(-20, 20, 4002).reshape(2, -1)
    w = wrap_angle(a)
    assert w.shape == a.shape and np.all(w >= -math.pi) and np.all(w < math.pi)
    # the same angle: an independent wrap through the unit circle
    np.testing.assert_allclose(np.exp(1j * w), np.exp(1j * a), atol=1e-13)
