"""Tests for isac_twin.phy.link: eqs. 1-2, precoding, power allocation, rates."""

import numpy as np
import pytest

from isac_twin.phy.link import (
    AchievableRate,
    EqualPower,
    Interferer,
    MRTPrecoder,
    SVDPrecoder,
    WaterFilling,
    channel_gains,
    receive,
    transmit,
    transmit_power,
    water_filling,
)
from isac_twin.phy.ofdm import ResourceGrid, ResourceSet
from isac_twin.phy.units import (
    BOLTZMANN,
    db_to_linear,
    dbm_to_watt,
    linear_to_db,
    thermal_noise_power,
    watt_to_dbm,
)


def _crandn(rng, *shape):
    return (rng.standard_normal(shape) + 1j * rng.standard_normal(shape)) / np.sqrt(2)


def _qpsk(rng, *shape):
    return np.exp(1j * (np.pi / 4 + np.pi / 2 * rng.integers(0, 4, shape)))


def _textbook_water_filling(eigs, p_total, n0):
    """Bisection on the water level: p_i = max(mu - n0/eig_i, 0), sum = P."""
    lo, hi = 0.0, p_total + np.max(n0 / eigs)
    for _ in range(200):
        mu = 0.5 * (lo + hi)
        if np.sum(np.maximum(mu - n0 / eigs, 0)) > p_total:
            hi = mu
        else:
            lo = mu
    return np.maximum(mu - n0 / eigs, 0)


# ---------------------------------------------------------------- units


def test_dbm_watt_conversions():
    assert dbm_to_watt(30.0) == pytest.approx(1.0)
    assert dbm_to_watt(0.0) == pytest.approx(1e-3)
    np.testing.assert_allclose(watt_to_dbm(dbm_to_watt(np.array([-90.0, 0.0, 23.0]))), [-90, 0, 23])
    assert watt_to_dbm(0.0) == -np.inf
    assert db_to_linear(linear_to_db(3.7)) == pytest.approx(3.7)
    with pytest.raises(ValueError, match="non-negative"):
        watt_to_dbm(-1.0)


def test_noise_power_is_kTB_times_noise_figure():
    df = 78125.0
    n0 = thermal_noise_power(df, temperature_k=290.0, noise_figure_db=7.0)
    assert n0 == pytest.approx(BOLTZMANN * 290.0 * df * 10 ** 0.7)
    # Textbook: -174 dBm/Hz + 10 log10(B) + NF (kT0 = -173.98 dBm/Hz).
    assert watt_to_dbm(n0) == pytest.approx(-173.98 + 10 * np.log10(df) + 7.0, abs=0.01)
    with pytest.raises(ValueError, match="temperature_k"):
        thermal_noise_power(df, temperature_k=-1.0)


# ---------------------------------------------------------------- rates


def test_siso_awgn_rate_equals_shannon_capacity():
    grid = ResourceGrid(64, 78125.0, 14, cyclic_prefix_samples=16)
    n0 = thermal_noise_power(grid.subcarrier_spacing_hz, 290.0, 7.0)
    p_total = dbm_to_watt(-40.0)
    mask = ResourceSet(grid).mask
    h = np.ones(grid.shape + (1, 1))
    p = EqualPower(p_total)(mask)
    w = MRTPrecoder()(h)
    res = AchievableRate(grid, n0)(h, w, p, mask)
    snr = p_total / mask.sum() / n0
    assert res.rate_bps == pytest.approx(64 * np.log2(1 + snr) / grid.symbol_duration_s, rel=1e-9)
    assert res.bits_per_step == pytest.approx(64 * 14 * np.log2(1 + snr), rel=1e-9)
    np.testing.assert_allclose(res.sinr[..., 0], snr, rtol=1e-9)


def test_mimo_water_filling_rate_matches_textbook_eigen_water_filling():
    rng = np.random.default_rng(5)
    grid = ResourceGrid(8, 1e5, 2)
    mask = np.zeros(grid.shape, bool)
    mask[:, 2:7] = True
    h = _crandn(rng, 2, 8, 2, 4)  # frequency-selective MIMO 2x4
    n0, p_total = 1e-3, 5e-3
    w = SVDPrecoder(2)(h, mask)
    g = channel_gains(h, w)
    p = WaterFilling(p_total, n0)(g, mask)
    res = AchievableRate(grid, n0)(h, w, p, mask)
    eigs = np.linalg.svd(h[mask], compute_uv=False).ravel() ** 2  # all eigenmodes in R
    p_ref = _textbook_water_filling(eigs, p_total, n0)
    cap = np.sum(np.log2(1 + p_ref * eigs / n0))
    assert res.bits_per_step == pytest.approx(cap, rel=1e-6)
    np.testing.assert_allclose(np.sort(p[mask].ravel()), np.sort(p_ref), atol=1e-9)
    # Water-filling beats equal power, and off-mask REs carry no rate.
    eq = AchievableRate(grid, n0)(h, w, EqualPower(p_total)(mask, 2), mask)
    assert res.bits_per_step >= eq.bits_per_step
    assert not res.spectral_efficiency[~mask].any()


def test_water_filling_against_bisection_on_random_gains():
    rng = np.random.default_rng(0)
    for _ in range(20):
        g = rng.exponential(size=rng.integers(1, 40)) * rng.choice([0, 1], p=[0.2, 0.8], size=1)
        g = np.abs(g) + (rng.random(g.shape) < 0.1) * 0.0
        p_total = rng.uniform(0.01, 10)
        p = water_filling(g, p_total, 0.5)
        if not g.any():
            assert not p.any()
            continue
        pos = g > 0
        ref = _textbook_water_filling(g[pos], p_total, 0.5)
        np.testing.assert_allclose(p[pos], ref, atol=1e-8)
        assert p.sum() <= p_total * (1 + 1e-12)


@pytest.mark.parametrize("seed", range(10))
def test_power_budget_is_never_exceeded(seed):
    rng = np.random.default_rng(seed)
    k, n = rng.integers(1, 5), rng.integers(2, 40)
    grid = ResourceGrid(int(n), 1e4, int(k))
    nt, nr = rng.integers(1, 5), rng.integers(1, 4)
    s = int(rng.integers(1, min(nt, nr) + 1))
    lo = int(rng.integers(0, n - 1))
    rs = ResourceSet(grid, (lo, int(rng.integers(lo + 1, n + 1))), name="q")
    h = _crandn(rng, k, n, nr, nt) * rng.exponential(size=(k, n, 1, 1))
    p_total = 10 ** rng.uniform(-6, 1)
    for w in (SVDPrecoder(s)(h, rs.mask), SVDPrecoder(s, "wideband")(h, rs.mask),
              MRTPrecoder()(h)):
        ss = w.shape[-1]
        for p in (EqualPower(p_total)(rs.mask, ss),
                  WaterFilling(p_total, 10 ** rng.uniform(-8, 0))(channel_gains(h, w), rs.mask)):
            x = transmit(rs.mask, p, w, _qpsk(rng, k, n, ss))
            assert transmit_power(x) <= p_total * (1 + 1e-9)
            assert transmit_power(x, rs.mask) == pytest.approx(transmit_power(x))
            assert not x[~rs.mask].any()


# ---------------------------------------------------------------- precoders


def test_mrt_is_conjugate_channel_for_one_receive_antenna_and_maximises_gain():
    rng = np.random.default_rng(1)
    h = _crandn(rng, 2, 3, 1, 8)
    w = MRTPrecoder()(h)
    ref = np.conj(h[:, :, 0, :]) / np.linalg.norm(h[:, :, 0, :], axis=-1, keepdims=True)
    np.testing.assert_allclose(w[..., 0], ref, atol=1e-12)
    h2 = _crandn(rng, 1, 1, 2, 8)
    g_mrt = channel_gains(h2, MRTPrecoder()(h2))[0, 0, 0]
    for _ in range(50):
        v = _crandn(rng, 8)
        v /= np.linalg.norm(v)
        assert np.linalg.norm(h2[0, 0] @ v) ** 2 <= g_mrt * (1 + 1e-12)


def test_wideband_svd_precoder_on_flat_channel_spans_dominant_modes():
    rng = np.random.default_rng(2)
    h1 = _crandn(rng, 2, 4)
    h = np.broadcast_to(h1, (3, 5, 2, 4)).copy()
    w = SVDPrecoder(2, "wideband")(h)
    np.testing.assert_allclose(np.conj(w[1, 2].T) @ w[1, 2], np.eye(2), atol=1e-12)
    _, _, vh = np.linalg.svd(h1)
    proj = vh[:2] @ w[0, 0]  # same subspace as the right singular vectors
    np.testing.assert_allclose(np.abs(np.linalg.det(proj)), 1.0, atol=1e-9)


# ---------------------------------------------------------------- eq. 2 and interference


def test_receive_noiseless_superposition_and_noise_variance():
    rng = np.random.default_rng(3)
    h1, h2 = _crandn(rng, 2, 200, 2, 4), _crandn(rng, 2, 200, 2, 1)
    x1, x2 = _crandn(rng, 2, 200, 4), _crandn(rng, 2, 200, 1)
    y = receive([h1, h2], [x1, x2], 0.0)
    np.testing.assert_allclose(y, np.einsum("knrt,knt->knr", h1, x1) + h2[..., 0] * x2, atol=1e-12)
    n0 = 2.5e-3
    z = receive([h1], [np.zeros_like(x1)], n0, rng=np.random.default_rng(0))
    assert np.mean(np.abs(z) ** 2) == pytest.approx(n0, rel=0.05)  # 800 samples


def test_interference_lowers_sinr_exactly_where_resources_overlap():
    grid = ResourceGrid(16, 1e5, 2)
    a = ResourceSet(grid, (0, 10), name="AP1")
    b = ResourceSet(grid, (6, 16), name="AP2")
    rng = np.random.default_rng(4)
    h = _crandn(rng, 2, 16, 1, 1)
    g = _crandn(rng, 2, 16, 1, 1)
    n0, p1, p2 = 1e-2, 0.2, 0.3
    wa, wb = np.ones((2, 16, 1, 1)), np.ones((2, 16, 1, 1))
    pa, pb = EqualPower(p1)(a.mask), EqualPower(p2)(b.mask)
    rate = AchievableRate(grid, n0)
    clean = rate(h, wa, pa, a.mask)
    dirty = rate(h, wa, pa, a.mask, [Interferer(g, wb, pb, b.mask)])
    sig = pa[..., 0] * np.abs(h[..., 0, 0]) ** 2
    itf = pb[..., 0] * np.abs(g[..., 0, 0]) ** 2
    sinr_ref = np.where(a.mask, sig / (n0 + itf * b.mask), 0)
    np.testing.assert_allclose(dirty.sinr[..., 0], sinr_ref, rtol=1e-9)
    np.testing.assert_allclose(dirty.spectral_efficiency, np.log2(1 + sinr_ref), rtol=1e-9, atol=1e-12)
    only_a = a.mask & ~b.mask
    np.testing.assert_allclose(dirty.spectral_efficiency[only_a], clean.spectral_efficiency[only_a])
    assert np.all(dirty.spectral_efficiency[a.overlaps(b)] < clean.spectral_efficiency[a.overlaps(b)])
    assert dirty.rate_bps < clean.rate_bps


# ---------------------------------------------------------------- bad input


def test_bad_inputs_raise_clear_errors():
    k, n = 1, 4
    mask = np.ones((k, n), bool)
    w = np.ones((k, n, 2, 1))
    d = np.ones((k, n, 1))
    with pytest.raises(ValueError, match="p must be non-negative"):
        transmit(mask, -np.ones((k, n, 1)), w, d)
    with pytest.raises(ValueError, match=r"w must have shape \[K, N, Nt, S\]"):
        transmit(mask, np.ones((k, n, 1)), np.ones((k, n + 1, 2, 1)), d)
    with pytest.raises(ValueError, match=r"alpha must have shape"):
        transmit(np.ones((2, 2), bool), np.ones((k, n, 1)), w, d)
    with pytest.raises(ValueError, match="d contains NaN"):
        transmit(mask, np.ones((k, n, 1)), w, np.full((k, n, 1), np.nan))
    with pytest.raises(ValueError, match="H contains NaN"):
        MRTPrecoder()(np.full((1, 1, 1, 2), np.nan))
    with pytest.raises(ValueError, match="num_streams=3 exceeds"):
        SVDPrecoder(3)(np.ones((1, 1, 2, 4)))
    with pytest.raises(ValueError, match="total_power"):
        EqualPower(-1.0)
    with pytest.raises(ValueError, match="gains must be non-negative"):
        water_filling([-1.0, 2.0], 1.0)
    with pytest.raises(ValueError, match=r"signals\[0\] shape"):
        receive([np.ones((1, 4, 2, 2))], [np.ones((1, 4, 3))], 0.0)
    grid = ResourceGrid(n, 1e3, k)
    with pytest.raises(ValueError, match=r"interferers\[0\].p"):
        AchievableRate(grid, 1.0)(np.ones((k, n, 1, 2)), w, np.ones((k, n, 1)), mask,
                                  [Interferer(np.ones((k, n, 1, 2)), w, np.ones((k, n, 2)), mask)])
