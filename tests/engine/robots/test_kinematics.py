"""Differential-drive model f (eq. 5): closed-form arcs, limits, wheels, noise, seeds."""

import math
from dataclasses import replace

import numpy as np
import pytest

from isac_twin.bus.msgs import Twist
from isac_twin.errors import SpeedLimitError
from isac_twin.robots.kinematics import (
    MAX_WHEEL_RATE,
    ROBOT_SPECS,
    DiffDriveRobot,
    PoseObservation,
    ProcessNoise,
    arc_step,
    make_twist,
    robot_spec,
)


def moving(model, pose, v, w, **kw):
    """A robot already at (v, w), so acceleration limits play no role."""
    r = DiffDriveRobot(model, pose, **kw)
    r.state.v, r.state.w = v, w
    return r


@pytest.mark.parametrize("model", ["burger", "waffle"])
@pytest.mark.parametrize("v,w", [(0.2, 0.4), (0.1, -0.8), (-0.1, 0.3)])
def test_constant_twist_follows_the_closed_form_circle(model, v, w):
    spec = robot_spec(model)
    v, w = min(v, spec.max_linear), max(min(w, spec.max_angular), -spec.max_angular)
    x0, y0, th0 = 1.0, 2.0, 0.7
    r = moving(model, (x0, y0, th0), v, w)
    dt, n = 0.05, 173
    for _ in range(n):
        r.step((v, w), dt)
    t = n * dt
    R = v / w
    cx, cy = x0 - R * math.sin(th0), y0 + R * math.cos(th0)
    th = th0 + w * t
    want = (cx + R * math.sin(th), cy - R * math.cos(th))
    assert r.state.x == pytest.approx(want[0], abs=1e-9)
    assert r.state.y == pytest.approx(want[1], abs=1e-9)
    assert math.remainder(r.state.yaw - th, 2 * math.pi) == pytest.approx(0, abs=1e-9)
    # one big step lands on the same arc: integration is exact, not Euler
    r2 = moving(model, (x0, y0, th0), v, w)
    r2.step((v, w), t)
    assert np.allclose(r2.state.pose, r.state.pose, atol=1e-9)


def test_straight_line_and_tiny_rotation_are_continuous():
    x, y, th = arc_step(0, 0, 0.3, 0.2, 0.0, 2.0)
    assert (x, y) == pytest.approx((0.4 * math.cos(0.3), 0.4 * math.sin(0.3)), abs=1e-12)
    a = arc_step(0, 0, 0.3, 0.2, 1e-10, 2.0)
    b = arc_step(0, 0, 0.3, 0.2, 1e-6, 2.0)
    assert np.allclose(a, (x, y, th), atol=1e-9) and np.allclose(b, a, atol=1e-6)


def test_acceleration_limit_ramps_the_speed_and_integrates_exactly():
    r = DiffDriveRobot("burger", (0, 0, 0))
    spec = r.spec
    r.step((0.2, 0.0), 0.02)
    assert r.state.v == pytest.approx(spec.max_linear_accel * 0.02)
    r.step((0.2, 0.0), 1.0)  # reaches 0.2 m/s at t = 0.08 s
    assert r.state.v == pytest.approx(0.2)
    # distance = ramp v^2 / (2 a) + cruise
    a, t_ramp = spec.max_linear_accel, 0.2 / spec.max_linear_accel
    assert r.state.x == pytest.approx(0.5 * a * t_ramp ** 2 + 0.2 * (1.02 - t_ramp), abs=1e-12)
    assert r.state.accel[0] == pytest.approx((0.2 - 0.05) / 1.0)


def test_commands_above_the_limits_are_clamped_like_the_firmware():
    for model, spec in ROBOT_SPECS.items():
        r = DiffDriveRobot(model, (0, 0, 0))
        for _ in range(100):
            r.step((5.0, 0.0), 0.05)
        assert r.state.v == pytest.approx(spec.max_linear)
        r = DiffDriveRobot(model, (0, 0, 0))
        for _ in range(100):
            r.step(make_twist(0.0, -10.0), 0.05)
        assert r.state.w == pytest.approx(-spec.max_angular)
    # full speed and full turn together exceed a wheel: the wheel clamp lowers the twist
    r = DiffDriveRobot("burger", (0, 0, 0))
    for _ in range(100):
        r.step((0.211, 2.63), 0.05)
    assert np.max(np.abs(r.state.wheel_vel)) == pytest.approx(MAX_WHEEL_RATE)
    assert r.state.v < 0.211


def test_validate_names_the_limit():
    r = DiffDriveRobot("burger", (0, 0, 0), name="tb1")
    with pytest.raises(SpeedLimitError, match=r"0\.3 m/s exceeds the burger limit of 0\.211"):
        r.step((0.3, 0.0), 0.05, validate=True)
    with pytest.raises(SpeedLimitError, match=r"angular velocity 3 rad/s .* 2\.63"):
        r.step((0.0, 3.0), 0.05, validate=True)
    with pytest.raises(SpeedLimitError, match="per-wheel limit"):
        r.step((0.2, 2.5), 0.05, validate=True)
    w = DiffDriveRobot("waffle", (0, 0, 0))
    with pytest.raises(SpeedLimitError, match=r"waffle limit of 1\.85 rad/s"):
        w.step(make_twist(0.0, 2.0), 0.05, validate=True)
    r.step((0.2, 0.5), 0.05, validate=True)  # within limits: fine


def test_bad_input():
    with pytest.raises(ValueError, match="unknown robot model 'turtle'"):
        DiffDriveRobot("turtle")
    r = DiffDriveRobot("burger")
    with pytest.raises(ValueError, match="dt must be"):
        r.step((0.1, 0), 0.0)
    with pytest.raises(ValueError, match="finite"):
        r.step((float("nan"), 0), 0.1)
    with pytest.raises(TypeError, match="Twist or"):
        r.step("fast", 0.1)
    with pytest.raises(ValueError, match="pose"):
        DiffDriveRobot("burger", (0, 0))


def test_wheels_count_what_the_body_did():
    spec = robot_spec("waffle")
    r = moving("waffle", (0, 0, 0), 0.2, 0.0)
    for _ in range(50):
        r.step((0.2, 0.0), 0.1)
    assert np.allclose(r.state.wheel_pos, 1.0 / spec.wheel_radius)  # 1 m each wheel
    assert np.allclose(r.state.wheel_vel, 0.2 / spec.wheel_radius)
    r = moving("waffle", (0, 0, 0), 0.0, 1.0)
    r.step((0.0, 1.0), math.pi)  # half a turn in place
    arc = math.pi * spec.wheel_separation / 2
    assert r.state.wheel_pos == pytest.approx([-arc / spec.wheel_radius, arc / spec.wheel_radius])
    v, w = spec.body_twist(*spec.wheel_rates(0.13, -0.7))
    assert (v, w) == pytest.approx((0.13, -0.7))


def test_twist_and_tuple_commands_agree():
    a, b = DiffDriveRobot("burger"), DiffDriveRobot("burger")
    for _ in range(20):
        a.step((0.1, 0.2), 0.05)
        b.step(Twist(linear=np.array([0.1, 0, 0]), angular=np.array([0, 0, 0.2])), 0.05)
    assert np.array_equal(a.state.pose, b.state.pose)


def run(seed, steps=200):
    r = DiffDriveRobot("burger", (1, 1, 0), noise=ProcessNoise(0.01, 0.02, 0.001, 0.001),
                       seed=seed)
    return np.array([r.step((0.2, 0.3), 0.05).vector() for _ in range(steps)])


def test_process_noise_is_deterministic_per_seed():
    a, b, c = run(7), run(7), run(8)
    assert np.array_equal(a, b)
    assert not np.allclose(a, c)
    clean = DiffDriveRobot("burger", (1, 1, 0))
    ref = np.array([clean.step((0.2, 0.3), 0.05).vector() for _ in range(200)])
    dev = np.hypot(*(a[-1, :2] - ref[-1, :2]))
    assert 1e-4 < dev < 0.2  # noise moves the robot, but only by random-walk amounts


def test_noise_free_robot_at_rest_stays_put():
    r = DiffDriveRobot("burger", (1, 2, 0.5), noise=ProcessNoise(0.01, 0.02), seed=1)
    for _ in range(20):
        r.step((0, 0), 0.1)
    assert np.allclose(r.state.pose[[0, 1, 5]], (1, 2, 0.5))  # speed-scaled noise


def test_observation_model_g():
    r = DiffDriveRobot("burger", (1, 2, 0.5))
    g = PoseObservation(0.05, 0.01)
    obs = np.array([g(r.state, np.random.default_rng(s)) for s in range(400)])
    assert obs.mean(axis=0) == pytest.approx([1, 2, 0.5], abs=0.01)
    assert obs[:, 0].std() == pytest.approx(0.05, rel=0.15)


def test_antenna_follows_the_pose():
    r = DiffDriveRobot("burger", (1.0, 2.0, 0.0, 0.0, 0.0, math.pi / 2))
    assert r.antenna_position((0.1, 0.0, 0.25)) == pytest.approx([1.0, 2.1, 0.25])


def test_custom_accel_limit():
    spec = replace(robot_spec("burger"), max_linear_accel=0.5)
    r = DiffDriveRobot(spec)
    r.step((0.2, 0), 0.1)
    assert r.state.v == pytest.approx(0.05)
