"""Tests for isac_twin.phy.channel (eq. 4) against analytic cases and an
independent per-path re-implementation of Sionna's cir/cfr formulas."""

import numpy as np
import pytest

from isac_twin.phy.arrays import PlanarArray, r_hat
from isac_twin.phy.channel import OFDMChannel, baseband_gains, cfr_from_antenna_gains
from isac_twin.phy.ofdm import ResourceGrid
from isac_twin.phy.units import SPEED_OF_LIGHT

GRID = ResourceGrid(64, 78125.0, 4, cyclic_prefix_samples=8)


def _one_path(grid=GRID, tau=37e-9, nu=0.0, b=0.7 - 0.2j, rx=PlanarArray(1, 1),
              tx=PlanarArray(1, 1), dtype=np.complex128):
    ch = OFDMChannel(grid, rx, tx, dtype=dtype)
    return ch([b], [tau], [nu], [np.pi / 2], [0.0], [np.pi / 2], [0.0])


def test_single_path_delay_gives_linear_phase_ramp():
    tau = 123.4e-9
    h = _one_path(tau=tau)[0, :, 0, 0]
    f = GRID.subcarrier_frequencies
    np.testing.assert_allclose(h, (0.7 - 0.2j) * np.exp(-2j * np.pi * f * tau), rtol=1e-12)
    np.testing.assert_allclose(h[1:] / h[:-1], np.exp(-2j * np.pi * GRID.subcarrier_spacing_hz * tau))
    # Centre subcarrier (f = 0) carries the baseband gain itself.
    assert h[GRID.num_subcarriers // 2] == pytest.approx(0.7 - 0.2j)


def test_doppler_rotates_phase_by_nu_Ts_per_symbol():
    nu = 850.0
    h = _one_path(nu=nu, tau=0.0)[:, :, 0, 0]
    step = np.exp(2j * np.pi * nu * GRID.symbol_duration_s)
    np.testing.assert_allclose(h[1:] / h[:-1], step * np.ones((3, 64)), rtol=1e-12)


def test_single_path_mimo_is_rank_one_outer_product():
    rx, tx = PlanarArray(1, 2), PlanarArray(4, 8)
    ch = OFDMChannel(GRID, rx, tx, dtype=np.complex128)
    th_r, ph_r, th_t, ph_t = 1.2, 0.4, 1.9, -2.0
    h = ch([1.0], [10e-9], [0.0], [th_r], [ph_r], [th_t], [ph_t])
    assert h.shape == (4, 64, 2, 32)
    a_r = rx.steering_vectors([th_r], [ph_r])[0]
    a_t = tx.steering_vectors([th_t], [ph_t])[0]
    np.testing.assert_allclose(h[0, 32], np.outer(a_r, a_t), atol=1e-12)
    s = np.linalg.svd(h[2, 7], compute_uv=False)
    assert s[1] < 1e-9 * s[0]


def test_paths_superpose_and_variant_with_antenna_gains_agrees():
    rng = np.random.default_rng(3)
    rx, tx = PlanarArray(1, 2), PlanarArray(2, 2)
    L = 7
    b = rng.standard_normal(L) + 1j * rng.standard_normal(L)
    tau, nu = rng.uniform(5e-9, 200e-9, L), rng.uniform(-300, 300, L)
    ang = [rng.uniform(0.1, 3.0, L), rng.uniform(-3, 3, L), rng.uniform(0.1, 3.0, L), rng.uniform(-3, 3, L)]
    o_r, o_t = [0.3, 0.1, -0.2], [1.0, 0.0, 0.5]
    ch = OFDMChannel(GRID, rx, tx, dtype=np.complex128)
    h = ch(b, tau, nu, *ang, rx_orientation=o_r, tx_orientation=o_t)
    singles = sum(ch(b[i:i + 1], tau[i:i + 1], nu[i:i + 1], *[a[i:i + 1] for a in ang],
                     rx_orientation=o_r, tx_orientation=o_t) for i in range(L))
    np.testing.assert_allclose(h, singles, atol=1e-12)
    a_r = rx.steering_vectors(ang[0], ang[1], o_r)
    a_t = tx.steering_vectors(ang[2], ang[3], o_t)
    gains = b[:, None, None] * a_r[:, :, None] * a_t[:, None, :]
    np.testing.assert_allclose(cfr_from_antenna_gains(gains, tau, nu, GRID, np.complex128), h, atol=1e-12)


def _sionna_formula_reference(a, tau, doppler, k_t, k_r, pos_t_m, pos_r_m, fc, freqs, fs, K):
    """Per-path loop written from sionna/rt/path_solvers/paths.py (cir, cfr,
    _apply_synthetic_array): positions in metres, wavelength = c / fc."""
    lam = SPEED_OF_LIGHT / fc
    out = np.zeros((pos_r_m.shape[0], pos_t_m.shape[0], K, freqs.size), complex)
    for i in range(len(a)):
        for r in range(pos_r_m.shape[0]):
            for t in range(pos_t_m.shape[0]):
                ai = a[i] * np.exp(1j * 2 * np.pi * (pos_t_m[t] @ k_t[i] + pos_r_m[r] @ k_r[i]) / lam)
                ai = ai * np.exp(-2j * np.pi * fc * tau[i])
                tt = np.arange(K) / fs
                ai_t = ai * np.exp(2j * np.pi * doppler[i] * tt)
                out[r, t] += ai_t[:, None] * np.exp(-2j * np.pi * freqs * tau[i])[None, :]
    return out  # [Nr, Nt, K, N], Sionna layout minus the device axes


def test_matches_sionna_cfr_formula_with_synthetic_arrays():
    rng = np.random.default_rng(11)
    fc = 2.4e9
    grid = ResourceGrid(32, 78125.0, 3, cyclic_prefix_samples=16)
    rx, tx = PlanarArray(1, 2), PlanarArray(2, 4, vertical_spacing=0.5, horizontal_spacing=0.7)
    o_r, o_t = np.array([0.5, 0.0, 0.1]), np.array([-1.2, 0.3, 0.0])
    L = 5
    a = rng.standard_normal(L) + 1j * rng.standard_normal(L)
    tau, nu = rng.uniform(10e-9, 90e-9, L), rng.uniform(-50, 50, L)
    th_t, ph_t, th_r, ph_r = (rng.uniform(0.2, 2.9, L), rng.uniform(-3, 3, L),
                              rng.uniform(0.2, 2.9, L), rng.uniform(-3, 3, L))
    lam = SPEED_OF_LIGHT / fc
    pos_t = tx.positions(o_t) * lam
    pos_r = rx.positions(o_r) * lam
    ref = _sionna_formula_reference(a, tau, nu, r_hat(th_t, ph_t), r_hat(th_r, ph_r), pos_t, pos_r,
                                    fc, grid.subcarrier_frequencies, 1 / grid.symbol_duration_s,
                                    grid.num_symbols)
    h = OFDMChannel(grid, rx, tx, dtype=np.complex128)(
        baseband_gains(a, tau, fc), tau, nu, th_r, ph_r, th_t, ph_t, o_r, o_t)
    np.testing.assert_allclose(h, ref.transpose(2, 3, 0, 1), rtol=1e-9, atol=1e-12)
    h32 = OFDMChannel(grid, rx, tx)(baseband_gains(a, tau, fc), tau, nu, th_r, ph_r, th_t, ph_t, o_r, o_t)
    assert h32.dtype == np.complex64
    assert np.max(np.abs(h32 - h)) < 1e-5 * np.max(np.abs(h))


def test_far_field_steering_matches_exact_element_path_lengths():
    # LOS between two arrays 60 m apart: the synthetic (plane-wave) phases
    # equal exp(-j 2 pi fc d_ij / c) of the exact element-to-element distances
    # up to the common LOS term, to within the far-field error.
    fc = 2.4e9
    lam = SPEED_OF_LIGHT / fc
    tx, rx = PlanarArray(2, 4), PlanarArray(1, 2)
    p_t, p_r = np.array([0.0, 0.0, 3.0]), np.array([40.0, 44.0, 1.0])
    o_t, o_r = [0.2, 0.0, 0.0], [2.0, 0.0, 0.0]
    d = p_r - p_t
    dist = np.linalg.norm(d)
    k_t = d / dist
    k_r = -k_t
    el_t = p_t + tx.positions(o_t) * lam
    el_r = p_r + rx.positions(o_r) * lam
    dij = np.linalg.norm(el_r[:, None, :] - el_t[None, :, :], axis=-1)
    exact = np.exp(-2j * np.pi * (dij - dist) / lam)
    th = lambda v: np.arccos(v[2])  # noqa: E731
    ph = lambda v: np.arctan2(v[1], v[0])  # noqa: E731
    synth = np.outer(rx.steering_vectors([th(k_r)], [ph(k_r)], o_r)[0],
                     tx.steering_vectors([th(k_t)], [ph(k_t)], o_t)[0])
    assert np.max(np.abs(np.angle(exact / synth))) < 0.02  # rad
    # And the LOS delay the channel uses is distance / c.
    h = _one_path(tau=dist / SPEED_OF_LIGHT, b=1.0)[0, :, 0, 0]
    slope = np.angle(h[1:] / h[:-1]).mean() / (-2 * np.pi * GRID.subcarrier_spacing_hz)
    assert slope * SPEED_OF_LIGHT == pytest.approx(dist, rel=1e-9)


def test_no_paths_gives_zero_channel():
    ch = OFDMChannel(GRID, PlanarArray(1, 2), PlanarArray(1, 3))
    h = ch([], [], [], [], [], [], [])
    assert h.shape == (4, 64, 2, 3) and not h.any()


def test_bad_inputs():
    ch = OFDMChannel(GRID, PlanarArray(1, 1), PlanarArray(1, 1))
    ok = dict(b=[1.0, 1.0], tau=[1e-9, 2e-9], doppler=[0, 0], theta_r=[1, 1], phi_r=[0, 0],
              theta_t=[1, 1], phi_t=[0, 0])
    with pytest.raises(ValueError, match=r"same length L.*tau: 1"):
        ch(**{**ok, "tau": [1e-9]})
    with pytest.raises(ValueError, match="doppler contains NaN"):
        ch(**{**ok, "doppler": [0, np.nan]})
    with pytest.raises(ValueError, match="b contains NaN"):
        ch(**{**ok, "b": [1, complex(np.nan, 0)]})
    with pytest.raises(ValueError, match="tau must be real"):
        ch(**{**ok, "tau": [1j, 1]})
    with pytest.raises(ValueError, match="gains must have 3"):
        cfr_from_antenna_gains(np.ones((2, 2)), [0, 0], [0, 0], GRID)
    with pytest.raises(ValueError, match="dtype"):
        OFDMChannel(GRID, PlanarArray(1, 1), PlanarArray(1, 1), dtype=np.float32)


def test_per_antenna_pair_delays_variant():
    # Non-synthetic arrays: every antenna pair has its own delays.
    rng = np.random.default_rng(9)
    L, nr, nt = 4, 2, 3
    g = rng.standard_normal((L, nr, nt)) + 1j * rng.standard_normal((L, nr, nt))
    tau = rng.uniform(1e-9, 60e-9, (L, nr, nt))
    nu = rng.uniform(-40, 40, (L, nr, nt))
    h = cfr_from_antenna_gains(g, tau, nu, GRID, np.complex128)
    for r in range(nr):
        for t in range(nt):
            ref = cfr_from_antenna_gains(g[:, r:r + 1, t:t + 1], tau[:, r, t], nu[:, r, t], GRID,
                                         np.complex128)
            np.testing.assert_allclose(h[:, :, r, t], ref[:, :, 0, 0], atol=1e-12)
    with pytest.raises(ValueError, match="doppler must have the shape of tau"):
        cfr_from_antenna_gains(g, tau, nu[:, 0, 0], GRID)


def test_cfr_at_is_the_ofdm_channel_at_t0_on_chosen_subcarriers():
    """The snapshot variant (fingerprint CSI) is eq. 4 of OFDMChannel at t = 0."""
    from isac_twin.phy.channel import cfr_at
    rng = np.random.default_rng(4)
    L = 5
    b = rng.normal(size=L) + 1j * rng.normal(size=L)
    tau = rng.uniform(10e-9, 90e-9, L)
    ang = [rng.uniform(0.3, 2.8, L), rng.uniform(-3, 3, L), rng.uniform(0.3, 2.8, L),
           rng.uniform(-3, 3, L)]
    rx, tx = PlanarArray(1, 2), PlanarArray(2, 2)
    ori_r, ori_t = (0.4, 0.0, 0.0), (-1.2, 0.1, 0.0)
    full = OFDMChannel(GRID, rx, tx, dtype=np.complex128)(
        b, tau, np.zeros(L), *ang, rx_orientation=ori_r, tx_orientation=ori_t,
        times=np.zeros(1))[0]
    pick = np.arange(0, GRID.num_subcarriers, 7)
    snap = cfr_at(b, tau, *ang, GRID.subcarrier_frequencies[pick], rx, tx, ori_r, ori_t)
    np.testing.assert_allclose(snap, full[pick], rtol=1e-9, atol=1e-12)
    assert cfr_at(b[:0], tau[:0], *(a[:0] for a in ang), [1.0, 2.0], rx, tx).shape == (2, 2, 4)
