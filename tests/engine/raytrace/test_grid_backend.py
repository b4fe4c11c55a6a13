"""engine/raytrace/grid_backend.py: GridTracer serves a grid like a tracer."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from isac_twin import device_poses, load_scene
from isac_twin.raytrace.base import SPEED_OF_LIGHT, DevicePose
from isac_twin.raytrace.conformance import check_tracer
from isac_twin.raytrace.grid_backend import GridTracer
from isac_twin.scene.synthetic import furnished_room


def test_conformance(room_grid, room_scene):
    rep = check_tracer(GridTracer(room_grid), room_scene)
    assert rep.passed, str(rep)


def test_nearest_point_and_doppler(room_grid, room_scene):
    g = room_grid
    poses = device_poses(room_scene.config)
    i = int(np.flatnonzero(g.free)[10])
    target = g.points[i] + np.array([0.05, -0.04, 0.0])
    v = np.array([0.5, 0.2, 0.0])
    poses["robot1"] = DevicePose(tuple(target), velocity=tuple(v))
    lp = GridTracer(g)(room_scene, poses)[("AP1", "robot1")]
    assert lp.extra["grid_index"] == i
    assert lp.extra["snap_distance_m"] == pytest.approx(np.hypot(0.05, 0.04))
    np.testing.assert_allclose(lp.rx_position, g.points[i])
    d = g.paths(i, 0)
    np.testing.assert_array_equal(lp.tau, d["tau"])
    lam = SPEED_OF_LIGHT / g.meta["frequency_hz"]
    st = np.sin(lp.theta_r)
    r_r = np.stack([st * np.cos(lp.phi_r), st * np.sin(lp.phi_r), np.cos(lp.theta_r)], 1)
    np.testing.assert_allclose(lp.doppler, r_r @ v / lam)
    up = GridTracer(g)(room_scene, poses, [("robot1", "AP1")])[("robot1", "AP1")]
    np.testing.assert_array_equal(up.tau, lp.tau)
    np.testing.assert_array_equal(up.theta_t, lp.theta_r)


def test_errors_name_device(room_grid, room_scene):
    tr = GridTracer(room_grid)
    poses = device_poses(room_scene.config)
    rob = poses["robot1"]
    cases = [
        ("'robot1'.*height", replace(rob, position=(2.0, 1.5, 1.0)), "robot1"),
        ("'robot1'.*not in free space", replace(rob, position=(3.3, 0.5, 0.25)), "robot1"),
        ("'robot1'.*outside the stored grid", replace(rob, position=(4.12, 1.5, 0.25)),
         "robot1"),
        ("'AP1'.*transmitter moved", replace(poses["AP1"], position=(0.6, 0.5, 2.5)), "AP1"),
        ("'robot1'.*upright", replace(rob, orientation=(0.2, 0.0, 0.0)), "robot1"),
    ]
    for pattern, pose, name in cases:
        with pytest.raises(ValueError, match=pattern):
            tr(room_scene, dict(poses, **{name: pose}))


def test_other_scene_refused(room_grid, tmp_path):
    other = load_scene(furnished_room(tmp_path, size=(4.0, 3.0, 2.8)), load_sionna=False)
    with pytest.raises(ValueError, match="another scene"):
        GridTracer(room_grid)(other, device_poses(other.config))
