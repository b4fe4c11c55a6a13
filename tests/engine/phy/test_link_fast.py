"""Exact fast paths of isac_twin.phy.link (closed-form 2 x 2 SVD / log-det / SINR)
against the np.linalg reference, incl. rank-deficient and near-singular channels."""

import numpy as np
import pytest

from isac_twin.phy.link import (
    AchievableRate,
    Interferer,
    MRTPrecoder,
    SVDPrecoder,
    WaterFilling,
    channel_gains,
    rate_per_re,
    svd_streams,
    water_filling,
    water_level,
    water_levels,
)
from isac_twin.phy.ofdm import ResourceGrid

NTS = (1, 2, 3, 4, 8, 16, 32)


def _crandn(rng, *shape):
    return (rng.standard_normal(shape) + 1j * rng.standard_normal(shape)) / np.sqrt(2)


def _channels(rng, nr, nt, r=64):
    """Random [R, Nr, Nt] channels with hard cases mixed in: zero, rank-1 (exactly
    and up to 1e-5 / 1e-9 relative perturbations), equal singular values, huge
    dynamic range between REs."""
    h = _crandn(rng, r, nr, nt) * 10 ** rng.uniform(-6, 0, (r, 1, 1))
    h[0] = 0
    if nr == 2:
        h[1, 1] = (0.3 - 0.2j) * h[1, 0]  # rank 1
        h[2, 1] = 2j * h[2, 0] + 1e-5 * _crandn(rng, nt) * np.linalg.norm(h[2, 0])
        h[3, 1] = -h[3, 0] + 1e-9 * _crandn(rng, nt) * np.linalg.norm(h[3, 0])
        if nt >= 2:
            h[4] = 0
            h[4, 0, 0] = h[4, 1, 1] = 1e-3  # sigma_1 == sigma_2
        h[5, 1] = 0  # one dead receive antenna
    return h


def _reference_rate(h, n0, total):
    """np.linalg SVD + water-filling + slogdet on [1, R, Nr, Nt]."""
    grid = ResourceGrid(h.shape[1], 1e5, 1)
    nr, nt = h.shape[2:]
    s = min(nr, nt)
    w = SVDPrecoder(s, method="numpy")(h)
    p = WaterFilling(total, n0)(channel_gains(h, w), None)
    return AchievableRate(grid, n0, method="numpy")(h, w, p, None).bits_per_step


@pytest.mark.parametrize("nr", [1, 2])
@pytest.mark.parametrize("nt", NTS)
@pytest.mark.parametrize("dtype", [np.complex64, np.complex128])
def test_svd_streams_matches_lapack(nr, nt, dtype):
    rng = np.random.default_rng(100 * nr + nt)
    h = _channels(rng, nr, nt).astype(dtype)
    s = min(nr, nt)
    w, lam, f = svd_streams(h, s)
    assert w.dtype == dtype and w.shape == (h.shape[0], nt, s)
    hd = h.astype(np.complex128)
    sv = np.linalg.svd(hd, compute_uv=False)[:, :s]
    scale = sv[:, :1] ** 2
    # Eigenmode gains: float64 to ~1e-15 of the strongest mode of the RE.
    np.testing.assert_allclose(lam, sv ** 2, rtol=0, atol=1e-13 * scale.max())
    assert np.all(np.abs(lam - sv ** 2) <= 1e-13 * scale + 1e-300)
    # Orthonormal columns (complex64 W: single-precision rounding).
    tol = 1e-5 if dtype == np.complex64 else 1e-12
    wd = w.astype(np.complex128)
    gram = np.conj(wd).swapaxes(-1, -2) @ wd
    np.testing.assert_allclose(gram, np.broadcast_to(np.eye(s), gram.shape), atol=tol)
    # f = H W = U Sigma per RE (relative to sigma_1 of the RE), ||H w_s||^2 = lambda_s.
    hw = hd @ wd
    err = np.linalg.norm(np.abs(hw) - np.abs(f), axis=(1, 2))
    # A weak second mode (r = sigma_2 / sigma_1) is determined only to ~eps / r in
    # direction, so |H w_2| carries ~sigma_1 eps / r of rounding whatever the method
    # (LAPACK included); which BLAS kernels the CPU picks decides where in that
    # band a result lands (AMD EPYC: 4.7e-12 at r = 4.7e-6, 1.2x the old bound).
    r = sv[:, -1] / np.where(sv[:, 0] > 0, sv[:, 0], 1.0)
    cond = np.where(r > 0, 10 * np.finfo(np.float64).eps / np.maximum(r, 1e-300), 0.0)
    assert np.all(err <= (10 * tol + cond) * np.sqrt(scale[:, 0]) + 1e-300)
    np.testing.assert_allclose(np.sum(np.abs(hw) ** 2, axis=1), lam, rtol=0,
                               atol=10 * tol * scale.max())


@pytest.mark.parametrize("nr", [1, 2])
@pytest.mark.parametrize("nt", NTS)
def test_fast_rate_matches_reference_to_1e6(nr, nt):
    rng = np.random.default_rng(7 * nr + nt)
    h = _channels(rng, nr, nt, r=128)
    for n0 in (1e-3, 1e-9, 1e-14):  # up to ~140 dB SNR on the strongest REs
        ref = _reference_rate(h[None], n0, 1.0)
        for dtype in (np.complex128, np.complex64):
            hq = h.astype(dtype)
            ref_q = _reference_rate(hq.astype(np.complex128)[None], n0, 1.0)
            w, lam, f = svd_streams(hq, min(nr, nt))
            p = np.zeros(lam.shape)
            on = lam > 0
            p[on] = water_level(lam[on], 1.0, n0)
            se, _ = rate_per_re(f * np.sqrt(p)[:, None, :], [], n0)
            assert se.sum() == pytest.approx(ref_q, rel=1e-6, abs=1e-9)
        assert ref > 0


@pytest.mark.parametrize("nr", [1, 2])
@pytest.mark.parametrize("s_i", [1, 2])
def test_closed_form_rate_and_sinr_with_interference(nr, s_i):
    rng = np.random.default_rng(nr + 10 * s_i)
    grid = ResourceGrid(32, 1e5, 3)
    k, n = grid.shape
    mask = rng.random((k, n)) < 0.8
    nt = 4
    h = _crandn(rng, k, n, nr, nt)
    h[0, 0] = 0
    s = min(nr, nt)
    w = SVDPrecoder(s, method="numpy")(h)
    p = rng.exponential(size=(k, n, s)) * 1e-2
    p[1, 1] = 0
    itfs = []
    for _ in range(2):
        hi = _crandn(rng, k, n, nr, 3) * 3
        wi = SVDPrecoder(min(s_i, nr), method="numpy")(_crandn(rng, k, n, nr, 3))
        pi_ = rng.exponential(size=(k, n, wi.shape[-1]))
        itfs.append(Interferer(hi, wi, pi_, rng.random((k, n)) < 0.5))
    for n0 in (1.0, 1e-6):
        ref = AchievableRate(grid, n0, method="numpy")(h, w, p, mask, itfs)
        fast = AchievableRate(grid, n0)(h, w, p, mask, itfs)
        assert fast.bits_per_step == pytest.approx(ref.bits_per_step, rel=1e-10)
        np.testing.assert_allclose(fast.spectral_efficiency, ref.spectral_efficiency,
                                   rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(fast.sinr, ref.sinr, rtol=1e-7, atol=1e-12)


def test_precoders_fast_vs_numpy_give_the_same_rates():
    rng = np.random.default_rng(3)
    grid = ResourceGrid(16, 1e5, 2)
    for nr, nt in ((1, 5), (2, 1), (2, 2), (2, 32), (3, 2), (3, 1), (4, 4)):
        h = _crandn(rng, 2, 16, nr, nt)
        h[0, 0, -1] = 0 if nr > 1 else h[0, 0, -1]
        s = min(nr, nt)
        rates = []
        for method in ("auto", "numpy"):
            w = SVDPrecoder(s, method=method)(h)
            assert w.shape == (2, 16, nt, s) and w.dtype == np.complex128
            np.testing.assert_allclose(np.conj(w).swapaxes(-1, -2) @ w,
                                       np.broadcast_to(np.eye(s), (2, 16, s, s)), atol=1e-12)
            p = WaterFilling(1.0, 1e-4)(channel_gains(h, w), None)
            rates.append(AchievableRate(grid, 1e-4, method=method)(h, w, p, None).bits_per_step)
        assert rates[0] == pytest.approx(rates[1], rel=1e-10)
        wm = MRTPrecoder()(h)
        g = channel_gains(h, wm)[..., 0]
        np.testing.assert_allclose(g, np.linalg.svd(h, compute_uv=False)[..., 0] ** 2,
                                   rtol=1e-10)


def test_weightedwater_level_equals_expanded_water_filling():
    rng = np.random.default_rng(1)
    g = rng.exponential(size=50)
    wts = rng.integers(1, 6, size=50).astype(float)
    p = water_level(g, 3.0, 0.7, wts)
    ref = water_filling(np.repeat(g, wts.astype(int)), 3.0, 0.7)
    np.testing.assert_allclose(np.repeat(p, wts.astype(int)), ref, rtol=1e-12, atol=1e-15)
    assert np.dot(wts, p) <= 3.0 * (1 + 1e-12)


@pytest.mark.parametrize("weighted", [False, True])
def test_water_levels_rows_are_independent_budgets(weighted):
    """Issue 19: one call for several budgets, rows padded with zero gains, equals
    water-filling each row's positive gains alone (and the expanded form)."""
    rng = np.random.default_rng(4)
    g = rng.exponential(size=(4, 60))
    g[0, 40:] = 0  # a shorter row
    g[1, ::3] = 0
    g[2] = 0  # nothing to fill
    g[3, :59] = 0  # one entry
    totals = np.array([3.0, 0.5, 1.0, 2.0])
    wts = rng.integers(1, 6, size=60).astype(float) if weighted else None
    p = water_levels(g, totals, 0.7, wts)
    assert p.shape == g.shape and np.all(p[g <= 0] == 0) and np.all(p[2] == 0)
    for b in (0, 1, 3):
        on = g[b] > 0
        want = water_level(g[b, on], totals[b], 0.7, None if wts is None else wts[on])
        np.testing.assert_allclose(p[b, on], want, rtol=1e-12, atol=1e-15)
        spent = p[b].sum() if wts is None else np.dot(wts, p[b])
        assert spent == pytest.approx(totals[b], rel=1e-12) and spent <= totals[b]
        ref = water_filling(np.repeat(g[b], 1 if wts is None else wts.astype(int)),
                            totals[b], 0.7)
        np.testing.assert_allclose(np.repeat(p[b], 1 if wts is None else wts.astype(int)),
                                   ref, rtol=1e-12, atol=1e-15)
    assert p[3, 59] == pytest.approx(2.0 / (1.0 if wts is None else wts[59]))


@pytest.mark.parametrize("dtype", [np.complex64, np.complex128])
def test_many_rank_one_and_zero_channels_use_the_closed_form_completion(dtype):
    # > _LAPACK_MAX_REs rank-1 REs (a single-path channel) and all-zero REs.
    rng = np.random.default_rng(11)
    r, nt = 2000, 16
    a_r, a_t = _crandn(rng, r, 2), _crandn(rng, r, nt)
    h = (a_r[:, :, None] * a_t[:, None, :]).astype(dtype)
    h[:100] = 0
    w, lam, f = svd_streams(h, 2)
    wd = w.astype(np.complex128)
    np.testing.assert_allclose(np.conj(wd).swapaxes(-1, -2) @ wd,
                               np.broadcast_to(np.eye(2), (r, 2, 2)), atol=1e-5)
    hd = h.astype(np.complex128)
    sv = np.linalg.svd(hd, compute_uv=False)
    np.testing.assert_allclose(lam[:, 0], sv[:, 0] ** 2, rtol=1e-12)
    assert np.all(lam[:, 1] <= 1e-12 * sv[:, :1].max() ** 2)
    g = np.sum(np.abs(hd @ wd) ** 2, axis=1)
    np.testing.assert_allclose(g[:, 0], sv[:, 0] ** 2, rtol=1e-5)
    assert np.all(g[:, 1] <= 1e-10 * sv[:, 0] ** 2 + 1e-300)
    assert not lam[:100].any() and not f[:100].any()


@pytest.mark.parametrize("nt", [1, 2, 32])
def test_svd_streams_without_precoders_gives_the_same_gains(nt):
    """Issue 19: ``precoders=False`` skips W (Nr = 2) but changes neither the
    eigenmode gains nor the effective channels, also on weak, rank-1 (LAPACK
    fix-up) and zero REs."""
    rng = np.random.default_rng(7 + nt)
    h = _channels(rng, 2, nt).astype(np.complex64)
    a_r, a_t = _crandn(rng, 50, 2), _crandn(rng, 50, nt)
    h[:50] = (a_r[:, :, None] * a_t[:, None, :]).astype(np.complex64)  # rank 1
    h[50:60] = 0
    s = min(2, nt)
    w, lam, f = svd_streams(h, s)
    w0, lam0, f0 = svd_streams(h, s, precoders=False)
    assert w0 is None and w is not None
    np.testing.assert_array_equal(lam0, lam)
    np.testing.assert_array_equal(f0, f)
