"""engine/sensing: OFDM radar processing on synthetic point targets (no tracing)."""

import numpy as np
import pytest

from isac_twin.bus.bus import Bus, resolve_type
from isac_twin.errors import SensingError
from isac_twin.phy import OFDMChannel, PlanarArray, ResourceGrid, ResourceSet
from isac_twin.phy.units import SPEED_OF_LIGHT
from isac_twin.sensing import (
    BackgroundSubtractor,
    Detections,
    KalmanTracker,
    OFDMRadar,
    SensingLinkSpec,
    SensingReceiver,
    ca_cfar,
    locate,
    sensing_resource_set,
)

# A 60 GHz frame whose Doppler resolves a moving point target:
# B = 256 x 120 kHz = 30.7 MHz (monostatic range bin 4.88 m, path-length bin 9.76 m),
# 128 symbols of 8.92 us -> Doppler bin 876 Hz (monostatic velocity bin 2.19 m/s).
FC = 60e9
LAM = SPEED_OF_LIGHT / FC
GRID = ResourceGrid(256, 120e3, 128, 18)
R_TRUE, V_TRUE = 7.3, 5.0  # monostatic range (m), radial velocity (m/s, > 0 approaching)
AZ, ZE = np.deg2rad(20.0), np.deg2rad(100.0)

#: refined-estimate tolerances, all SNRs below (per-RE, per-antenna SNR)
TOL_RANGE_M = 0.05
TOL_VEL_MPS = 0.05
TOL_ANGLE_DEG = 0.5


def _frame(snr_db, array, seed=0, grid=GRID, r=R_TRUE, v=V_TRUE):
    """Received sensing REs of one monostatic point target + known symbols."""
    d = 2 * r
    nu = 2 * v / LAM
    ch = OFDMChannel(grid, array, PlanarArray(1, 1), dtype=np.complex128)
    h = ch(np.array([1.0]), np.array([d / SPEED_OF_LIGHT]), np.array([nu]),
           np.array([ZE]), np.array([AZ]), np.array([ZE]), np.array([AZ]))[..., 0]
    rng = np.random.default_rng(seed)
    x = np.exp(1j * np.pi / 2 * rng.integers(0, 4, grid.shape))
    n0 = 10 ** (-snr_db / 10)
    z = np.sqrt(n0 / 2) * (rng.standard_normal(h.shape) + 1j * rng.standard_normal(h.shape))
    return h * x[..., None] + z, x, d, nu


@pytest.mark.parametrize("snr_db", [-20.0, -10.0, 10.0])
def test_point_target_bins_and_refinement(snr_db):
    arr = PlanarArray(2, 4)
    radar = OFDMRadar(ResourceSet(GRID, name="AP1->AP1"), FC, rx_array=arr, max_detections=1)
    y, x, d, nu = _frame(snr_db, arr, seed=int(snr_db) + 100)
    dets, rd = radar(y, x)
    assert len(dets) == 1
    det = dets[0]
    # Coarse cell: the right range and Doppler bins.
    res_d = radar.max_unambiguous_path_m / rd.path_length_m.size
    res_nu = rd.doppler_hz[1] - rd.doppler_hz[0]
    assert det.range_bin == int(round(d / res_d))
    assert det.doppler_bin == int(round(nu / res_nu))
    # Refined: within the stated tolerances.
    assert abs(det.path_length_m / 2 - R_TRUE) < TOL_RANGE_M
    assert abs(-det.range_rate_mps / 2 - V_TRUE) < TOL_VEL_MPS
    assert abs(np.rad2deg(det.azimuth_rad - AZ)) < TOL_ANGLE_DEG
    assert abs(np.rad2deg(det.zenith_rad - ZE)) < TOL_ANGLE_DEG


def test_angle_search_equals_the_library_steering_vectors():
    """The angle search's own steering vectors (iso array: rotated positions once
    per search) give bit for bit the result of PlanarArray's, which a unit
    element pattern routes through (``a * 1`` is exact)."""
    ori = (0.3, 0.0, 0.0)
    iso = PlanarArray(2, 4)
    unit = PlanarArray(2, 4, pattern=lambda th, ph: np.ones_like(th))
    y, x, _, _ = _frame(10.0, iso)
    out = []
    for arr in (iso, unit):
        radar = OFDMRadar(ResourceSet(GRID, name="AP1->AP1"), FC, rx_array=arr,
                          rx_orientation=ori, max_detections=2)
        out.append(radar(y, x)[0])
    assert len(out[0]) == len(out[1]) > 0
    for a, b in zip(*out):
        assert (a.azimuth_rad, a.zenith_rad) == (b.azimuth_rad, b.zenith_rad)


@pytest.mark.slow
def test_full_32_element_array_and_first_arrival():
    arr = PlanarArray(4, 8)
    radar = OFDMRadar(ResourceSet(GRID, name="AP1->AP1"), FC, rx_array=arr,
                      range_method="first_arrival")
    y, x, d, nu = _frame(0.0, arr)
    dets, _ = radar(y, x)
    assert dets and abs(dets[0].path_length_m - d) < 2 * TOL_RANGE_M
    assert abs(dets[0].doppler_hz - nu) < 10.0


def test_noise_only_gives_no_detection():
    arr = PlanarArray(1, 2)
    radar = OFDMRadar(ResourceSet(GRID, name="a->b"), FC, rx_array=arr, pfa=1e-6)
    rng = np.random.default_rng(3)
    y = (rng.standard_normal((128, 256, 2)) + 1j * rng.standard_normal((128, 256, 2)))
    dets, _ = radar(y, np.ones(GRID.shape))
    assert len(dets) <= 1


def test_ca_cfar_detects_spike():
    p = np.random.default_rng(0).exponential(1.0, (32, 64))
    p[10, 20] = 1e4
    hits, noise = ca_cfar(p, pfa=1e-6)
    assert hits[10, 20] and hits.sum() <= 2
    assert 0.5 < np.median(noise) < 1.5


def test_comb_sensing_resources_and_receiver_snr():
    g = ResourceGrid(1024, 78125.0, 14, 72)
    rs = sensing_resource_set(g, 0.25, name="AP2->AP1")
    assert rs.subcarrier_indices.size == 256 and rs.symbol_indices.size == 14
    spec = SensingLinkSpec("AP2", "AP1", rx_array=PlanarArray(1, 1), rho=0.25,
                           estimate_angles=False)
    rx = SensingReceiver(spec, g, seed=1)
    y = rx.receive(np.zeros(g.shape + (1,), complex))
    assert y.shape == (14, 256, 1)
    assert np.var(y) == pytest.approx(rx.noise_w, rel=0.1)
    assert np.allclose(np.abs(rx.symbols) ** 2, rx.re_power_w)


def test_errors_name_the_link():
    g = ResourceGrid(64, 78125.0, 14)
    with pytest.raises(SensingError, match="AP2->AP1.*angles requested"):
        OFDMRadar(ResourceSet(g, name="AP2->AP1"), 2.4e9, rx_array=PlanarArray(1, 1))
    with pytest.raises(SensingError, match="AP1->AP2.*outside the grid"):
        sensing_resource_set(g, name="AP1->AP2", subcarriers=(0, 80))
    with pytest.raises(SensingError, match="AP1->AP2.*rho"):
        sensing_resource_set(g, 1.5, name="AP1->AP2")
    with pytest.raises(SensingError, match="AP1->AP2.*equally spaced"):
        OFDMRadar(ResourceSet(g, [0, 1, 5], name="AP1->AP2"), 2.4e9, estimate_angles=False)
    spec = SensingLinkSpec("AP1", "AP2", symbols=(10, 20))
    with pytest.raises(SensingError, match="AP1->AP2"):
        SensingReceiver(spec, g)
    radar = OFDMRadar(ResourceSet(g, name="AP1->AP2"), 2.4e9, estimate_angles=False)
    with pytest.raises(SensingError, match="AP1->AP2.*zero"):
        radar.channel_estimate(np.ones((14, 64, 1)), np.zeros((14, 64)))


def test_locate_bistatic_and_monostatic():
    tx, rx = np.array([4.0, 0.05, 2.0]), np.array([0.05, 3.0, 2.0])
    for t in ([5.5, 3.0, 0.1], [2.6, 2.46, 0.1], [3.1, 1.8, 0.1], [4.0, 4.5, 0.1]):
        t = np.array(t)
        d = np.linalg.norm(t - tx) + np.linalg.norm(t - rx)
        u = (t - rx) / np.linalg.norm(t - rx)
        az, ze = np.arctan2(u[1], u[0]), np.arccos(u[2])
        assert np.allclose(locate(d, az, ze, tx, rx, height_m=0.1), t, atol=1e-4)
        assert np.allclose(locate(d, az, ze, tx, rx), t, atol=1e-6)
    t = np.array([2.0, 1.0, 1.0])
    u = (t - tx) / np.linalg.norm(t - tx)
    mono = locate(2 * np.linalg.norm(t - tx), np.arctan2(u[1], u[0]), np.arccos(u[2]),
                  tx, tx + 1e-9)
    assert np.allclose(mono, t, atol=1e-6)


def test_background_subtraction():
    rng = np.random.default_rng(0)
    static = rng.standard_normal((14, 16, 2)) + 1j * rng.standard_normal((14, 16, 2))
    bg = BackgroundSubtractor("ema", beta=0.2, name="x")
    assert np.allclose(bg(static), 0)
    assert np.allclose(bg(static), 0)
    ref = BackgroundSubtractor("reference", name="x")
    with pytest.raises(SensingError, match="set_reference"):
        ref(static)
    ref.set_reference(static)
    assert np.allclose(ref(static + 1), 1)
    with pytest.raises(SensingError, match="'x'"):
        BackgroundSubtractor("median", name="x")


def test_tracker_follows_constant_velocity_target_and_drops_clutter():
    rng = np.random.default_rng(1)
    trk = KalmanTracker(meas_std_m=0.1)
    truth = []
    errs = []
    for k in range(40):
        p = np.array([1.0 + 0.2 * 0.5 * k, 2.0 + 0.1 * 0.5 * k])
        truth.append(p)
        meas = [p + 0.1 * rng.standard_normal(2)]
        if k % 7 == 0:  # a lone false alarm now and then
            meas.append(rng.uniform(0, 8, 2))
        conf = trk.update(np.array(meas), 0.5)
        if k >= 5:
            assert len(conf) == 1
            errs.append(np.linalg.norm(conf[0].position - p))
    assert np.sqrt(np.mean(np.square(errs))) < 0.1
    assert np.allclose(trk.confirmed[0].velocity, [0.2, 0.1], atol=0.1)


def test_detections_message_on_the_bus():
    from isac_twin.bus.sensing_msgs import register

    register()
    assert resolve_type("isac_twin_msgs/msg/Detections") is Detections
    bus = Bus()
    sub = bus.node("viewer").subscribe("/sensing/detections", Detections)
    pub = bus.node("radar")
    pub.advertise("/sensing/detections", Detections)
    pub.publish("/sensing/detections", Detections(link="AP2->AP1",
                                                 path_length=np.array([9.6])))
    msg = sub.take()
    assert msg.link == "AP2->AP1" and msg.path_length[0] == 9.6


def test_os_cfar_resists_masking_by_a_neighbour():
    from isac_twin.sensing.radar import os_cfar

    p = np.random.default_rng(0).exponential(1.0, (16, 256))
    p[8, 100] = 3e4
    p[8, 112] = 1.2e3  # inside the first one's training cells
    hits_ca, _ = ca_cfar(p, guard=(1, 2), train=(2, 16), pfa=1e-6)
    hits_os, _ = os_cfar(p, guard=(1, 2), train=(2, 16), pfa=1e-6)
    assert hits_os[8, 100] and hits_os[8, 112]
    assert not hits_ca[8, 112]
    assert hits_os.sum() <= 4
