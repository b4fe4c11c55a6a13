"""Paths and controllers: queries, tracking bounds, goal reaching, bad input."""

import math

import numpy as np
import pytest

from isac_twin import PathError
from isac_twin.errors import SpeedLimitError
from isac_twin.robots.control import (
    CirclePath,
    FigureEightPath,
    GoalReacher,
    PolylinePath,
    PurePursuit,
)
from isac_twin.robots.kinematics import DiffDriveRobot, ProcessNoise

ROOM = ((0.0, 0.0), (8.0, 6.0))  # the bundled lab's floor
DT = 0.05  # 20 Hz, the OpenCR control period


def track(path, model, pose, laps, noise=None, seed=0, **kw):
    r = DiffDriveRobot(model, pose, noise=noise, seed=seed)
    c = PurePursuit(path, model, bounds=ROOM, **kw)
    errs, speeds = [], []
    for _ in range(int(laps * path.length / c.speed / DT * 1.3) + 400):
        if c.travelled >= laps * path.length:
            break
        u = c(r.state)
        speeds.append(u.linear[0])
        r.step(u, DT)
        errs.append(c.error)
    return np.array(errs), np.array(speeds), c, r


# ---------------------------------------------------------------- path queries


def test_circle_geometry_and_projection():
    p = CirclePath((4, 3), 1.5, "ccw")
    assert p.length == pytest.approx(3 * math.pi)
    assert p.point(0.0) == pytest.approx([5.5, 3.0])
    assert p.tangent(0.0) == pytest.approx([0.0, 1.0])
    assert p.point(p.length / 4) == pytest.approx([4.0, 4.5])
    inside = p.project((5.0, 3.0))
    assert inside.error == pytest.approx(0.5) and inside.s == pytest.approx(0.0)  # left of ccw
    cw = CirclePath((4, 3), 1.5, "cw")
    assert cw.project((5.0, 3.0)).error == pytest.approx(-0.5)
    assert cw.project((4.0, 1.0)).s == pytest.approx(cw.length / 4)
    assert p.curvature(1.0) == pytest.approx(1 / 1.5) and cw.curvature(1.0) == pytest.approx(-1 / 1.5)


def test_polyline_arc_length_and_closest_point():
    p = PolylinePath([(0, 0), (2, 0), (2, 1)])
    assert p.length == pytest.approx(3.0)
    assert p.point(2.5) == pytest.approx([2.0, 0.5])
    pr = p.project((1.0, 0.3))
    assert pr.s == pytest.approx(1.0) and pr.error == pytest.approx(0.3)
    pr = p.project((2.4, 0.7))
    assert pr.s == pytest.approx(2.7) and pr.error == pytest.approx(-0.4)
    loop = PolylinePath([(0, 0), (1, 0), (1, 1), (0, 1)], closed=True)
    assert loop.length == pytest.approx(4.0) and loop.point(4.5) == pytest.approx([0.5, 0.0])


def test_figure_eight_shape():
    f = FigureEightPath((4, 3), 4.0)
    lo, hi = f.bounds()
    assert lo == pytest.approx([2.0, 2.0], abs=1e-3) and hi == pytest.approx([6.0, 4.0], abs=1e-3)
    assert f.point(0.0) == pytest.approx([4.0, 3.0])
    # the two lobes turn opposite ways
    k = f.curvature(np.linspace(0, f.length, 400, endpoint=False))
    assert k.max() > 0.2 and k.min() < -0.2
    # windowed projection stays on the branch at the crossing
    s_other = f.length / 2
    pr = f.project((4.0, 3.0), hint=s_other, window=0.5)
    assert abs(pr.s - s_other) < 0.1


# ---------------------------------------------------------------- tracking


def test_circle_tracking_bound_noise_free():
    """Bundled lab path: circle (4, 3), r 1.5 m. Start 0.2 m outside, 17 deg off."""
    p = CirclePath((4, 3), 1.5)
    for model in ("burger", "waffle"):
        errs, speeds, c, _ = track(p, model, (5.7, 3.0, math.pi / 2 + 0.3), laps=3)
        first_lap = int(p.length / c.speed / DT)
        e = errs[first_lap:]
        assert np.abs(errs[:5]).max() > 0.15  # it did start off the path
        # measured ~1e-14 m: pure pursuit's arc is the circle itself in steady state
        assert np.abs(e).max() < 1e-3, model
        assert speeds.max() <= c.spec.max_linear + 1e-12


def test_circle_tracking_bound_with_process_noise():
    """Slip-like process noise 0.01 m/sqrt(s), 0.02 rad/sqrt(s): measured max 2.9 cm,
    RMS 0.94 cm after the first lap (burger, seed 0)."""
    p = CirclePath((4, 3), 1.5)
    errs, _, c, _ = track(p, "burger", (5.7, 3.0, math.pi / 2 + 0.3), laps=3,
                          noise=ProcessNoise(0.01, 0.02), seed=0)
    e = errs[int(p.length / c.speed / DT):]
    assert np.abs(e).max() < 0.05
    assert np.sqrt(np.mean(e ** 2)) < 0.015


def test_figure_eight_tracking():
    f = FigureEightPath((4, 3), 4.0)
    errs, _, c, r = track(f, "burger", (4.0, 3.0, math.atan2(1, 1)), laps=2)
    assert c.travelled >= 2 * f.length
    assert np.abs(errs[100:]).max() < 0.03  # measured ~1.3 cm at the lobes' tight ends


def test_open_polyline_stops_at_the_end():
    p = PolylinePath([(1, 1), (4, 1), (4, 4)])
    r = DiffDriveRobot("waffle", (1, 1, 0))
    c = PurePursuit(p, "waffle", bounds=ROOM, lookahead=0.3)
    for _ in range(1200):
        r.step(c(r.state), DT)
        if c.done:
            break
    assert c.done
    for _ in range(20):
        r.step(c(r.state), DT)
    assert np.hypot(r.state.x - 4, r.state.y - 4) < 0.05
    assert abs(r.state.v) < 1e-9


@pytest.mark.parametrize("goal", [(2.0, 5.0), (6.0, 1.0, -math.pi / 2), (3.0, 3.0, math.pi)])
def test_goal_reacher(goal):
    r = DiffDriveRobot("burger", (4, 3, 0))
    c = GoalReacher(goal, "burger", bounds=ROOM)
    for _ in range(2000):
        u = c(r.state)
        r.step(u, DT)
        if c.done:
            break
    assert c.done
    assert np.hypot(r.state.x - goal[0], r.state.y - goal[1]) < 0.04
    if len(goal) == 3:
        assert abs(math.remainder(r.state.yaw - goal[2], 2 * math.pi)) < 0.05


# ---------------------------------------------------------------- bad input


def test_path_leaving_the_room_is_refused():
    with pytest.raises(PathError, match=r"leaves the room.*y .* not inside 0\.000\.\.6\.000"):
        PurePursuit(CirclePath((4, 3), 3.5), "burger", bounds=ROOM)
    with pytest.raises(PathError, match="polyline of 2 waypoints leaves the room"):
        PurePursuit(PolylinePath([(1, 1), (9, 1)]), "burger", bounds=ROOM)
    # the footprint counts: 0.05 m from the wall is too close for a burger (0.113 m)
    with pytest.raises(PathError, match="clearance"):
        PurePursuit(CirclePath((4, 3), 2.95), "burger", bounds=ROOM)
    with pytest.raises(PathError, match="goal .* outside the room"):
        GoalReacher((7.95, 3), "waffle", bounds=ROOM)


def test_unreachable_radius_names_the_limit():
    with pytest.raises(PathError, match=r"unreachable for a burger at 0\.211 m/s.*minimum "
                                        r"turning radius 0\.080 m.*speed <= 0\.131"):
        PurePursuit(CirclePath((4, 3), 0.05), "burger")
    PurePursuit(CirclePath((4, 3), 0.05), "burger", speed=0.13)  # slower is fine
    with pytest.raises(SpeedLimitError, match=r"0\.3 m/s exceeds the waffle limit of 0\.266"):
        PurePursuit(CirclePath((4, 3), 1.5), "waffle", speed=0.3)


@pytest.mark.parametrize("make,msg", [
    (lambda: PolylinePath([]), "at least 2 waypoints, got 0"),
    (lambda: PolylinePath([(1, 1)]), "at least 2 waypoints, got 1"),
    (lambda: PolylinePath([(1, 1), (float("nan"), 2)]), r"waypoint 1 is not finite"),
    (lambda: PolylinePath([(1, 1), (1, 1), (2, 2)]), "waypoints 0 and 1 coincide"),
    (lambda: CirclePath((4, 3), -1.0), "circle radius: expected a positive"),
    (lambda: CirclePath((4, float("nan")), 1.0), "circle centre"),
    (lambda: CirclePath((4, 3), 1.0, "sideways"), "circle direction"),
    (lambda: FigureEightPath((4, 3), 0.0), "figure-eight size"),
    (lambda: GoalReacher((float("inf"), 1.0)), "goal"),
])
def test_malformed_paths(make, msg):
    with pytest.raises(PathError, match=msg):
        make()
