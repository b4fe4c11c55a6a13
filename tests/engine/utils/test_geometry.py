"""engine/utils/geometry.py: the one antenna-pose function, against hand-computed geometry."""

import math

import numpy as np
import pytest

from isac_twin.utils.geometry import (
    DevicePose,
    antenna_pose,
    planar_pose,
    rotation_matrix,
    sionna_orientation,
)


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
