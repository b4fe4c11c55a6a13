"""engine/raytrace/base.py: poses, links, LinkPaths helpers (no tracing)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from isac_twin import LinkPaths, device_poses, load_config, load_scene
from isac_twin.raytrace.base import DevicePose, resolve_links, sionna_orientation, validate_poses
from isac_twin.scene.synthetic import ROBOT_EXTRA, SyntheticDevice, furnished_room


def test_device_poses_rotate_antenna_offset_by_yaw(tmp_path):
    extra = dict(ROBOT_EXTRA, antenna_offset=[0.1, 0.0, 0.25])
    dev = SyntheticDevice("robot2", "robot", "rx", (2.0, 1.0, 0.0),
                          orientation=(0.0, 0.0, math.pi / 2), extra=extra)
    cfg = load_config(furnished_room(tmp_path, extra_devices=[dev]))
    poses = device_poses(cfg)
    np.testing.assert_allclose(poses["robot2"].position, (2.0, 1.1, 0.25), atol=1e-12)
    np.testing.assert_allclose(poses["robot2"].orientation, (0, 0, math.pi / 2))
    np.testing.assert_allclose(poses["AP1"].position, (0.5, 0.5, 2.5))
    assert poses["robot1"].velocity == (0.0, 0.0, 0.0)


def test_device_pose_shape_checked():
    with pytest.raises(ValueError, match="position"):
        DevicePose(position=(1.0, 2.0))


def test_validate_poses_names_device(tmp_path):
    scene = load_scene(furnished_room(tmp_path), load_sionna=False)
    poses = device_poses(scene.config)
    validate_poses(scene, poses, ["AP1", "robot1"])
    bad = dict(poses, robot1=DevicePose((math.nan, 1.0, 0.25)))
    with pytest.raises(ValueError, match="'robot1'.*not finite"):
        validate_poses(scene, bad, ["robot1"])
    bad = dict(poses, robot1=DevicePose((1.0, 1.0, 0.25), velocity=(math.inf, 0, 0)))
    with pytest.raises(ValueError, match="'robot1': velocity"):
        validate_poses(scene, bad, ["robot1"])
    bad = dict(poses, AP1=DevicePose((50.0, 1.0, 2.0)))
    with pytest.raises(ValueError, match="'AP1'.*outside the scene"):
        validate_poses(scene, bad, ["AP1"])
    with pytest.raises(ValueError, match="'AP2': no pose"):
        validate_poses(scene, {"AP1": poses["AP1"]}, ["AP2"])


def test_resolve_links(tmp_path):
    cfg = load_config(furnished_room(tmp_path))
    assert resolve_links(cfg, None) == [("AP1", "robot1"), ("AP2", "robot1")]
    assert resolve_links(cfg, [("robot1", "AP1")]) == [("robot1", "AP1")]
    with pytest.raises(ValueError, match="unknown device 'nope'"):
        resolve_links(cfg, [("AP1", "nope")])
    with pytest.raises(ValueError, match="two distinct"):
        resolve_links(cfg, [("AP1", "AP1")])


def test_sionna_orientation_reverses():
    assert sionna_orientation((0.1, 0.2, 0.3)) == (0.3, 0.2, 0.1)


def test_reversed_swaps_ends_and_vertex_order():
    z = np.zeros(2)
    lp = LinkPaths(tx="a", rx="b", tx_position=np.zeros(3), rx_position=np.ones(3),
                   tx_orientation=np.zeros(3), rx_orientation=np.zeros(3), frequency_hz=1e9,
                   a=np.array([1 + 1j, 0.5]), tau=np.array([1e-9, 2e-9]), doppler=z,
                   theta_t=np.array([0.1, 0.2]), phi_t=np.array([0.3, 0.4]),
                   theta_r=np.array([1.1, 1.2]), phi_r=np.array([1.3, 1.4]),
                   vertices=np.array([[[0, 0, 0], [0, 0, 0]], [[1, 1, 1], [2, 2, 2]]], float),
                   interactions=np.array([[0, 0], [1, 4]], np.int32))
    r = lp.reversed()
    assert (r.tx, r.rx) == ("b", "a")
    np.testing.assert_array_equal(r.theta_t, lp.theta_r)
    np.testing.assert_array_equal(r.interactions, [[0, 0], [4, 1]])
    np.testing.assert_array_equal(r.vertices[1], [[2, 2, 2], [1, 1, 1]])
    assert lp.los_delay == 1e-9 and r.los_delay == 1e-9
    s = lp.summary()
    assert s["num_paths"] == 2 and s["los"] and math.isclose(s["distance_m"], math.sqrt(3))
