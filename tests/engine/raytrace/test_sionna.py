"""engine/raytrace/sionna.py: SionnaTracer against analytic references."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from isac_twin import device_poses, load_scene
from isac_twin.errors import TruncationError
from isac_twin.raytrace.base import INTERACTION_SPECULAR, SPEED_OF_LIGHT, DevicePose
from isac_twin.raytrace.conformance import check_tracer
from isac_twin.raytrace.sionna import SionnaTracer
from isac_twin.scene.synthetic import furnished_room, reflector_scene

C = SPEED_OF_LIGHT


@pytest.mark.slow
def test_conformance(room_scene):
    rep = check_tracer(SionnaTracer(room_scene.config.tracer), room_scene)
    assert rep.passed, str(rep)


def test_los_only_delay_and_friis(tmp_path):
    scene = load_scene(furnished_room(tmp_path, tracer={"max_depth": 0}))
    res = SionnaTracer(scene.config.tracer)(scene, device_poses(scene.config))
    lam = C / scene.config.scene.frequency_hz
    for lp in res.values():
        assert lp.num_paths == 1 and lp.is_los[0]
        d = np.linalg.norm(lp.rx_position - lp.tx_position)
        assert lp.tau[0] == pytest.approx(d / C, rel=1e-6)
        assert abs(lp.a[0]) ** 2 == pytest.approx((lam / (4 * math.pi * d)) ** 2, rel=1e-4)


def test_metal_reflector_image_source(tmp_path):
    scene = load_scene(reflector_scene(tmp_path))
    lp = SionnaTracer(scene.config.tracer)(scene, device_poses(scene.config))[("TX", "RX")]
    refl = np.flatnonzero((lp.interactions[:, 0] == INTERACTION_SPECULAR)
                          & (np.abs(lp.vertices[:, 0, 2]) < 1e-4))
    assert refl.size == 1
    i = refl[0]
    image = np.array([0.0, 0.0, -1.0])  # tx mirrored in z = 0
    d = np.linalg.norm(np.array([2.0, 0.0, 1.5]) - image)
    assert lp.tau[i] == pytest.approx(d / C, rel=1e-6)
    np.testing.assert_allclose(lp.vertices[i, 0], [0.8, 0.0, 0.0], atol=1e-4)
    lam = C / scene.config.scene.frequency_hz
    # metal: |Gamma| <= 1, close to 1
    ratio = abs(lp.a[i]) ** 2 / (lam / (4 * math.pi * d)) ** 2
    assert 0.8 < ratio <= 1.0 + 1e-4
    assert lp.is_los.sum() == 1


@pytest.mark.slow
def test_truncation_detected_and_grown(room_scene):
    """Direct shoot-and-bounce (chain reuse enumerates its chains uncapped)."""
    tiny = replace(room_scene.config.tracer, max_num_paths_per_src=5, method="sbr")
    poses = device_poses(room_scene.config)
    with pytest.raises(TruncationError, match="max_num_paths_per_src"):
        SionnaTracer(tiny, on_truncation="raise")(room_scene, poses)
    grown = SionnaTracer(tiny)(room_scene, poses)
    full = SionnaTracer(replace(room_scene.config.tracer, method="sbr"))(room_scene, poses)
    for lk in full:
        assert grown[lk].num_paths == full[lk].num_paths
        np.testing.assert_allclose(grown[lk].tau, full[lk].tau, rtol=1e-6)


def test_devices_moved_not_recreated_and_doppler(room_scene):
    tr = SionnaTracer(room_scene.config.tracer)
    poses = device_poses(room_scene.config)
    tr(room_scene, poses)
    rx_obj = room_scene.sionna.receivers["rx:robot1"]
    v = np.array([0.6, -0.3, 0.0])
    moved = dict(poses, robot1=DevicePose((2.3, 1.4, 0.25), velocity=tuple(v)))
    res = tr(room_scene, moved)
    assert room_scene.sionna.receivers["rx:robot1"] is rx_obj
    lam = C / room_scene.config.scene.frequency_hz
    for lp in res.values():
        np.testing.assert_allclose(lp.rx_position, (2.3, 1.4, 0.25))
        st = np.sin(lp.theta_r)
        r_r = np.stack([st * np.cos(lp.phi_r), st * np.sin(lp.phi_r), np.cos(lp.theta_r)], 1)
        np.testing.assert_allclose(lp.doppler, r_r @ v / lam, rtol=1e-4, atol=1e-3)


def test_bad_pose_names_device(room_scene):
    tr = SionnaTracer(room_scene.config.tracer)
    poses = device_poses(room_scene.config)
    with pytest.raises(ValueError, match="'robot1'.*not finite"):
        tr(room_scene, dict(poses, robot1=DevicePose((math.nan, 1.0, 0.25))))
    with pytest.raises(ValueError, match="'AP2'.*outside the scene"):
        tr(room_scene, dict(poses, AP2=DevicePose((3.5, 2.5, 9.0))))
    with pytest.raises(ValueError, match="on_truncation"):
        SionnaTracer(room_scene.config.tracer, on_truncation="ignore")
