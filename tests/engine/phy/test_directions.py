"""Tests for isac_twin.phy.directions: joint delay-direction estimation at an AP.

The CSI is synthesised with the eq.-4 channel (:func:`isac_twin.phy.channel.cfr_at`)
at each port's comb subcarriers, as the PHY's comb pilots place them."""

import numpy as np
import pytest

from isac_twin.phy.arrays import PlanarArray, r_hat
from isac_twin.phy.channel import cfr_at
from isac_twin.phy.directions import DelayDirectionEstimator
from isac_twin.phy.estimation import MdpEstimator
from isac_twin.phy.units import SPEED_OF_LIGHT as C

DF = 78125.0
N = 1024
STRIDE = 32
AP = PlanarArray(4, 8)
ROBOT = PlanarArray(1, 2)
F = (np.arange(N) - N // 2) * DF


def _comb_csi(d, theta_t, phi_t, b, ap_orientation=(0.0, 0.0, 0.0), snr_db=None, seed=0):
    """LS-like comb CSI [M, Nr, P] and port offsets [P] Hz of paths with lengths
    ``d`` m and departure angles (rad, world frame) at a 4x8 AP."""
    rng = np.random.default_rng(seed)
    n_path = len(d)
    h = cfr_at(np.asarray(b, complex), np.asarray(d) / C, rng.uniform(0.5, 2.5, n_path),
               rng.uniform(-np.pi, np.pi, n_path), theta_t, phi_t, F, ROBOT, AP,
               tx_orientation=ap_orientation)  # [N, Nr, Nt]
    m = N // STRIDE
    csi = np.stack([h[p::STRIDE][:m, :, p] for p in range(AP.num_ant)], axis=2)
    if snr_db is not None:
        n0 = np.mean(np.abs(csi) ** 2) / 10 ** (snr_db / 10)
        csi = csi + np.sqrt(n0 / 2) * (rng.standard_normal(csi.shape)
                                       + 1j * rng.standard_normal(csi.shape))
    return csi, np.arange(AP.num_ant) * DF


def _match(est, d, k):
    """Per true path: length error (m) and angle error (rad) of the nearest estimate
    in (length, direction)."""
    out = []
    for di, ki in zip(d, k):
        cost = np.abs(est.distances_m - di) + np.linalg.norm(est.directions - ki, axis=1)
        j = np.argmin(cost)
        out.append((abs(est.distances_m[j] - di),
                    np.arccos(np.clip(est.directions[j] @ ki, -1, 1))))
    return np.array(out)


PATHS = dict(d=[3.4, 6.9, 9.7, 14.2], theta_t=[1.75, 1.45, 1.9, 1.2],
             phi_t=[0.1, -0.6, 0.5, 0.9], b=[1.0, 0.6j, -0.5, 0.4 * np.exp(1j)])


@pytest.mark.parametrize("yaw", [0.0, np.pi / 2])
def test_noise_free_paths_come_back_exactly(yaw):
    """Lengths, world-frame departure directions and powers of 4 paths, the AP
    facing +x (yaw 0, like AP1) or +y (yaw pi/2, like AP2)."""
    p = dict(PATHS)
    p["phi_t"] = np.asarray(p["phi_t"]) + yaw  # the same paths in the AP's frame
    csi, off = _comb_csi(ap_orientation=(yaw, 0.0, 0.0), **p)
    est = DelayDirectionEstimator(AP, STRIDE * DF, orientation=(yaw, 0.0, 0.0))(csi, off)
    k = r_hat(p["theta_t"], p["phi_t"])
    err = _match(est, p["d"], k)
    assert len(est) == 4
    assert err[:, 0].max() < 1e-3
    assert np.degrees(err[:, 1].max()) < 0.05
    np.testing.assert_allclose(np.sort(est.powers), np.sort(np.abs(p["b"]) ** 2), rtol=1e-3)
    assert est.powers[0] == pytest.approx(1.0, rel=1e-3)  # strongest first
    np.testing.assert_allclose(np.linalg.norm(est.directions, axis=1), 1.0)
    np.testing.assert_allclose(est.zenith_rad[0], 1.75, atol=1e-3)
    np.testing.assert_allclose(est.azimuth_rad[0], 0.1 + yaw, atol=1e-3)


def test_equal_lengths_different_directions_are_resolved():
    """Two paths 10 cm apart in length (1/37 of the 3.75 m delay cell), 40 deg apart
    in azimuth: delay-only estimation sees one component, the joint estimator
    two, each in its direction."""
    d = [5.0, 5.1, 11.0]
    th = [1.6, 1.5, 1.4]
    ph = [-0.35, 0.35, 0.0]
    b = [1.0, 0.8j, 0.5]
    csi, off = _comb_csi(d, th, ph, b, snr_db=25.0, seed=3)
    delay_only = MdpEstimator(STRIDE * DF)(csi.reshape(csi.shape[0], -1),
                                           frequencies_hz=np.arange(csi.shape[0]) * STRIDE * DF)
    assert np.sum(np.abs(delay_only.distances_m - 5.05) < 1.0) == 1
    est = DelayDirectionEstimator(AP, STRIDE * DF)(csi, off)
    err = _match(est, d, r_hat(th, ph))
    assert np.degrees(err[:, 1].max()) < 3.0, np.degrees(err[:, 1])
    assert err[:, 0].max() < 0.2


def test_noisy_directions_within_a_degree_at_20db():
    errs = []
    for seed in range(3):
        csi, off = _comb_csi(snr_db=20.0, seed=seed, **PATHS)
        est = DelayDirectionEstimator(AP, STRIDE * DF)(csi, off)
        errs.append(_match(est, PATHS["d"], r_hat(PATHS["theta_t"], PATHS["phi_t"])))
    errs = np.concatenate(errs)
    assert errs[:, 0].max() < 0.05
    assert np.degrees(errs[:, 1].max()) < 1.0, np.degrees(errs[:, 1])


def test_bad_inputs_are_refused():
    with pytest.raises(ValueError, match="single antenna"):
        DelayDirectionEstimator(PlanarArray(1, 1), STRIDE * DF)
    with pytest.raises(ValueError, match="split_fraction"):
        DelayDirectionEstimator(AP, STRIDE * DF, split_fraction=1.5)
    est = DelayDirectionEstimator(AP, STRIDE * DF)
    with pytest.raises(ValueError, match="P = 32 ports"):
        est(np.ones((32, 2, 8)), np.zeros(8))
    with pytest.raises(ValueError, match="port_offsets_hz must have shape"):
        est(np.ones((32, 2, 32)), np.zeros(4))
    assert len(est(np.zeros((32, 2, 32)), np.zeros(32))) == 0


def test_a_single_row_array_resolves_azimuth_only():
    """A 1 x 8 array sees only the direction cosine along its row (local y):
    that one comes back; the unresolved one is reported as 0."""
    ula = PlanarArray(1, 8)
    d, th, ph = [4.0, 9.0], [np.pi / 2, np.pi / 2], [0.3, -0.5]  # horizontal paths
    h = cfr_at(np.array([1.0, 0.5j]), np.asarray(d) / C, [1.0, 2.0], [0.0, 1.0], th, ph, F,
               ROBOT, ula)
    csi = np.stack([h[p::STRIDE][:N // STRIDE, :, p] for p in range(8)], axis=2)
    est = DelayDirectionEstimator(ula, STRIDE * DF)(csi, np.arange(8) * DF)
    k = r_hat(th, ph)
    for di, ki in zip(d, k):
        j = np.argmin(np.abs(est.distances_m - di))
        assert abs(est.distances_m[j] - di) < 1e-3
        assert est.directions[j, 1] == pytest.approx(ki[1], abs=1e-4)  # u = sin(phi)
        assert est.directions[j, 2] == pytest.approx(0.0, abs=1e-12)
