"""Tests for isac_twin.phy.estimation: pilots, LS estimation, MDPs."""

import numpy as np
import pytest

from isac_twin.phy.arrays import PlanarArray
from isac_twin.phy.channel import OFDMChannel
from isac_twin.phy.estimation import (
    LSChannelEstimator,
    MdpEstimator,
    PilotPattern,
    ideal_mdp,
    noise_power_from_delay_tail,
)
from isac_twin.phy.link import receive
from isac_twin.phy.ofdm import ResourceGrid, ResourceSet
from isac_twin.phy.units import SPEED_OF_LIGHT as C

DF = 78125.0
PAPER_GRID = ResourceGrid(1024, DF, 14, cyclic_prefix_samples=72)
F = PAPER_GRID.subcarrier_frequencies


def _crandn(rng, *shape):
    return (rng.standard_normal(shape) + 1j * rng.standard_normal(shape)) / np.sqrt(2)


def _csi(d, amps, n0, rng):
    """CSI [N, S] of paths with lengths d [L] m and amplitudes [L, S] plus noise."""
    h = np.exp(-2j * np.pi * np.outer(F, np.asarray(d) / C)) @ amps
    return h + np.sqrt(n0) * _crandn(rng, *h.shape)


def _crb_distance(d, amps, n0):
    """Cramer-Rao bound [m] of each path length with unknown amplitudes
    ``amps [L, S]`` (Stoica-Nehorai deterministic CRB):
    ``CRB^-1 = 2/n0 Re[(D^H P_perp D) * (sum_s c_s c_s^H)^T]``."""
    fc = F / C
    e = np.exp(-2j * np.pi * np.outer(fc, d))  # [N, L]
    dd = (-2j * np.pi * fc)[:, None] * e  # d e / d distance
    p_perp = np.eye(F.size) - e @ np.linalg.pinv(e)
    amp_cov = amps @ np.conj(amps.T)  # [L, L]
    fim = 2 / n0 * np.real((np.conj(dd.T) @ p_perp @ dd) * amp_cov.T)
    return np.sqrt(np.diag(np.linalg.inv(fim)))


# ---------------------------------------------------------------- pilots + LS


def test_comb_pilots_are_orthogonal_per_port_and_inside_the_resource_set():
    grid = ResourceGrid(64, DF, 4)
    rs = ResourceSet(grid, (8, 40), (1, 4), name="AP1")
    pp = PilotPattern(rs, "comb", num_ports=2, subcarrier_stride=4, pilot_power=2.0)
    m = pp.mask
    assert m.shape == (2, 4, 64)
    assert not (m[0] & m[1]).any()
    assert not (m.any(axis=0) & ~rs.mask).any()
    np.testing.assert_array_equal(np.nonzero(m[0, 1])[0], np.arange(8, 40, 4))
    np.testing.assert_array_equal(np.nonzero(m[1, 1])[0], np.arange(9, 40, 4))
    np.testing.assert_allclose(np.abs(pp.symbols[m]) ** 2, 2.0)
    assert not pp.symbols[~m].any()
    blk = PilotPattern(rs, "block", symbol_stride=2)
    np.testing.assert_array_equal(np.nonzero(blk.mask[0].any(axis=1))[0], [1, 3])


def _ls_setup(snr_db, kind="comb", seed=0, nr=2):
    grid = ResourceGrid(256, DF, 4)
    rs = ResourceSet(grid, (0, 256), name="AP")
    pp = PilotPattern(rs, kind, subcarrier_stride=4, symbol_stride=3, pilot_power=1.0)
    ch = OFDMChannel(grid, PlanarArray(1, nr), PlanarArray(1, 1), dtype=np.complex128)
    h = ch([1.0, 0.5j], [15e-9, 40e-9], [30.0, -20.0], [1.5, 1.2], [0.3, 2.0], [1.5, 1.7], [0.0, 1.0])
    n0 = 10 ** (-snr_db / 10)
    y = receive([h], [pp.symbols[0][..., None]], n0, rng=np.random.default_rng(seed))
    return pp, h, n0, LSChannelEstimator(pp)(y)


@pytest.mark.parametrize("kind", ["comb", "block"])
def test_ls_error_vanishes_at_high_snr(kind):
    errs = []
    for snr in (10, 30, 50, 70):
        _, h, _, h_hat = _ls_setup(snr, kind)
        errs.append(np.mean(np.abs(h_hat[..., 0] - h[..., 0]) ** 2) / np.mean(np.abs(h) ** 2))
    assert all(a > b for a, b in zip(errs, errs[1:]))
    assert errs[-1] < 1e-4  # what remains is the interpolation error of a smooth channel


def test_ls_error_matches_noise_over_pilot_power_theory():
    pp, h, n0, h_hat = _ls_setup(10.0, seed=1)
    err = np.abs(h_hat[..., 0] - h[..., 0]) ** 2  # [K, N, Nr]
    at_pilots = err[pp.mask[0]]
    assert np.mean(at_pilots) == pytest.approx(n0 / pp.pilot_power, rel=0.1)  # 512 samples
    # Half-way between comb pilots, linear interpolation averages two
    # independent errors with weights 1/2: variance n0 / (2 P).
    mid = np.zeros(pp.mask[0].shape, bool)
    mid[:, 2:252:4] = True
    assert np.mean(err[mid]) == pytest.approx(n0 / (2 * pp.pilot_power), rel=0.15)


def test_ls_two_ports_estimate_both_transmit_antennas():
    grid = ResourceGrid(128, DF, 2)
    rs = ResourceSet(grid)
    pp = PilotPattern(rs, "comb", num_ports=2, subcarrier_stride=2)
    ch = OFDMChannel(grid, PlanarArray(1, 2), PlanarArray(1, 2), dtype=np.complex128)
    h = ch([1.0], [20e-9], [0.0], [1.4], [0.2], [1.5], [-0.4])
    x = np.moveaxis(pp.symbols, 0, -1)  # port p -> antenna p
    h_hat = LSChannelEstimator(pp)(receive([h], [x], 0.0))
    np.testing.assert_allclose(h_hat, h, atol=0.02)


def test_ls_rejects_wrong_grid():
    pp = PilotPattern(ResourceSet(ResourceGrid(16, DF, 2)))
    with pytest.raises(ValueError, match=r"y must have shape \[K, N, Nr\]"):
        LSChannelEstimator(pp)(np.ones((2, 8, 1)))
    with pytest.raises(ValueError, match="subcarrier_stride"):
        PilotPattern(pp.resource_set, num_ports=3, subcarrier_stride=2)
    with pytest.raises(ValueError, match="kind"):
        PilotPattern(pp.resource_set, kind="lattice")


# ---------------------------------------------------------------- MDP


def test_ideal_mdp_is_path_lengths_sorted_by_power():
    tau = np.array([10e-9, 20e-9, 30e-9])
    b = np.array([0.1, 1.0, 0.5j])
    mdp = ideal_mdp(tau, b)
    np.testing.assert_allclose(mdp.distances_m, C * tau[[1, 2, 0]])
    np.testing.assert_allclose(mdp.powers, [1.0, 0.25, 0.01])
    np.testing.assert_allclose(mdp.delays_s, tau[[1, 2, 0]])
    assert len(ideal_mdp(tau, b, max_paths=2)) == 2
    assert len(ideal_mdp(tau, b, min_relative_power_db=10)) == 2
    with pytest.raises(ValueError, match="tau must be non-negative"):
        ideal_mdp([-1e-9], [1.0])
    with pytest.raises(ValueError, match="b must have L=2"):
        ideal_mdp([1e-9, 2e-9], [1.0])


def test_mdp_noiseless_single_path_is_exact():
    mdp = MdpEstimator(DF)(_csi([7.3456], np.ones((1, 1)), 0.0, np.random.default_rng(0))[:, 0])
    assert len(mdp) == 1
    assert mdp.distances_m[0] == pytest.approx(7.3456, abs=1e-6)
    assert mdp.powers[0] == pytest.approx(1.0, rel=1e-6)


SCENARIOS = [  # path lengths [m] (>= 2 m apart), powers [dB]
    ([4.1, 6.6, 9.0, 15.2], [0.0, -3.0, -6.0, -2.0]),
    ([3.0, 5.4, 12.7, 14.9], [-1.0, 0.0, -5.0, -4.0]),
]


@pytest.mark.parametrize("snr_db", [0, 10, 20, 30])
@pytest.mark.parametrize("scenario", range(len(SCENARIOS)))
def test_mdp_estimate_recovers_delays_within_crb_tolerance(snr_db, scenario):
    """Every path within 5 CRB (+5 mm) of the truth; the path count is
    exact from 10 dB; at 0 dB the strongest path still meets 5 CRB.
    CSI: N = 1024 x 78.125 kHz, 2 receive antennas as snapshots;
    SNR = mean |h|^2 / sigma^2 per subcarrier."""
    rng = np.random.default_rng(100 + scenario * 10 + snr_db)
    d, p_db = map(np.asarray, SCENARIOS[scenario])
    amps = np.sqrt(10 ** (p_db / 10))[:, None] * np.exp(2j * np.pi * rng.uniform(size=(len(d), 2)))
    clean = np.exp(-2j * np.pi * np.outer(F, d / C)) @ amps
    n0 = np.mean(np.abs(clean) ** 2) / 10 ** (snr_db / 10)
    mdp = MdpEstimator(DF, max_paths=9)(clean + np.sqrt(n0) * _crandn(rng, *clean.shape))
    crb = _crb_distance(d, amps, n0)
    err = np.array([np.min(np.abs(mdp.distances_m - x)) for x in d])
    tol = 5 * crb + 0.005
    if snr_db >= 10:
        assert len(mdp) == len(d)
        assert np.all(err <= tol), (err, tol)
    else:
        strongest = np.argmax(p_db)
        assert err[strongest] <= tol[strongest]


def test_mdp_resolves_paths_half_a_metre_apart_at_30db():
    rng = np.random.default_rng(7)
    d = np.array([10.0, 10.5, 17.0])
    amps = np.array([1.0, 0.9, 0.5])[:, None] * np.exp(2j * np.pi * rng.uniform(size=(3, 2)))
    clean = np.exp(-2j * np.pi * np.outer(F, d / C)) @ amps
    n0 = np.mean(np.abs(clean) ** 2) / 1e3
    mdp = MdpEstimator(DF)(clean + np.sqrt(n0) * _crandn(rng, *clean.shape))
    assert len(mdp) == 3
    np.testing.assert_allclose(np.sort(mdp.distances_m), d, atol=0.1)
    assert mdp.powers[0] >= mdp.powers[-1]  # sorted by power
    # Physical CSI scale (path gains ~1e-5) gives the same delays, powers scaled.
    tiny = MdpEstimator(DF)(1e-5 * (clean + np.sqrt(n0) * _crandn(np.random.default_rng(7), *clean.shape)))
    assert len(tiny) == 3
    np.testing.assert_allclose(np.sort(tiny.distances_m), d, atol=0.1)
    assert 0.5e-10 < tiny.powers[0] < 2e-10


def test_mdp_from_ls_estimated_csi_end_to_end():
    """Tracer-like paths -> eq. 4 channel -> pilots through eq. 2 -> LS ->
    ESPRIT: the LOS length comes back to within a few centimetres."""
    grid = ResourceGrid(1024, DF, 1, cyclic_prefix_samples=72)
    rs = ResourceSet(grid, name="AP2")
    pp = PilotPattern(rs, "comb", subcarrier_stride=1, pilot_power=1.0)
    rng = np.random.default_rng(3)
    d = np.array([5.2, 7.9, 11.3])
    tau = d / C
    b = np.array([1.0, 0.5, 0.3]) * np.exp(2j * np.pi * rng.uniform(size=3))
    ch = OFDMChannel(grid, PlanarArray(1, 2), PlanarArray(1, 1), dtype=np.complex128)
    h = ch(b, tau, np.zeros(3), [1.6, 1.2, 2.0], [0.1, 2.5, -1.0], [1.5, 1.0, 2.2], [0.0, 0.5, 3.0])
    n0 = np.mean(np.abs(h) ** 2) / 10 ** 1.5  # 15 dB
    y = receive([h], [pp.symbols[0][..., None]], n0, rng=rng)
    h_hat = LSChannelEstimator(pp)(y)[0, :, :, 0]  # [N, Nr]
    mdp = MdpEstimator(DF)(h_hat, frequencies_hz=grid.subcarrier_frequencies)
    assert len(mdp) == 3
    assert np.min(np.abs(mdp.distances_m - d[0])) < 0.05
    np.testing.assert_allclose(np.sort(mdp.distances_m), d, atol=0.15)


def test_mdp_estimator_bad_inputs():
    est = MdpEstimator(DF)
    with pytest.raises(ValueError, match="csi contains NaN"):
        est(np.full(64, np.nan))
    with pytest.raises(ValueError, match=r"csi must have shape \[N\] or \[N, S\]"):
        est(np.ones((4, 4, 4)))
    with pytest.raises(ValueError, match="frequencies_hz must have shape"):
        est(np.ones(64), frequencies_hz=np.zeros(10))
    with pytest.raises(ValueError, match="uniformly spaced"):
        est(np.ones(4), frequencies_hz=[0.0, 1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="order"):
        MdpEstimator(DF, order="bic")
    assert len(est(np.zeros(64))) == 0


def test_mdp_with_64_antenna_snapshots_uses_them_all():
    """AP1 link (32 x 2 antennas flattened): paths share delays, amplitudes
    differ per antenna pair; every path within 5 CRB at 10 dB."""
    rng = np.random.default_rng(21)
    d = np.array([4.0, 6.5, 9.0, 15.0])
    amps = _crandn(rng, 4, 64)
    clean = np.exp(-2j * np.pi * np.outer(F, d / C)) @ amps
    n0 = np.mean(np.abs(clean) ** 2) / 10.0
    mdp = MdpEstimator(DF)(clean + np.sqrt(n0) * _crandn(rng, *clean.shape))
    assert len(mdp) == 4
    crb = _crb_distance(d, amps, n0)
    err = np.array([np.min(np.abs(mdp.distances_m - x)) for x in d])
    assert np.all(err <= 5 * crb + 0.005), (err, crb)


def test_mdp_small_subband_is_widened_not_crashed():
    """A subband shorter than 2k+1 used to crash TLS-ESPRIT (LinAlgError)."""
    from isac_twin.phy.estimation import MdpEstimator

    df, n = 78125.0, 64
    f = (np.arange(n) - n // 2) * df
    d_true = np.array([4.0, 9.0, 17.0])
    h = np.exp(-2j * np.pi * np.outer(f, d_true / 299792458.0)).sum(axis=1)
    mdp = MdpEstimator(df, max_paths=6, subband=8)(h)
    assert np.min(np.abs(mdp.distances_m[:, None] - d_true), axis=0).max() < 0.5


# ---------------------------------------------------------------- robust MDP (issue 13)


def _dense(seed, snr_db, n=128, df=8 * DF, num=40, s=2):
    """Dense multipath (line of sight at 3.5 m, ``num - 1`` paths at 5-30 m, power
    falling 10 dB per 5 m)
    on a comb of ``n`` subcarriers at ``df``, like AP2's pilots: more paths than
    any model order, so the estimator fits clusters. Returns (f, csi [n, s])."""
    rng = np.random.default_rng(seed)
    f = (np.arange(n) - n // 2) * df
    d = np.concatenate([[3.5], np.sort(rng.uniform(5.0, 30.0, num - 1))])
    phase = np.exp(2j * np.pi * rng.uniform(size=(num, s)))
    amps = np.sqrt(10 ** (-(d - 3.5) / 5))[:, None] * phase
    h = np.exp(-2j * np.pi * np.outer(f, d / C)) @ amps
    n0 = np.mean(np.abs(h) ** 2) / 10 ** (snr_db / 10)
    return f, h + np.sqrt(n0) * _crandn(rng, *h.shape)


@pytest.mark.parametrize("snr_db", [20, 30])
def test_mdp_dense_multipath_has_no_degenerate_cancelling_pairs(snr_db):
    """Failed before the fix: on 7 of these 8 seeds the estimator returned two
    (or three) equal lengths with powers 40-120 dB above the measured mean
    power, cancelling each other, ranked first."""
    cell = C / (128 * 8 * DF)
    for seed in range(8):
        f, h = _dense(seed, snr_db)
        mdp = MdpEstimator(8 * DF, subband=64)(h, frequencies_hz=f)
        total = np.mean(np.abs(h) ** 2)
        assert 1 <= len(mdp) <= 9
        assert mdp.powers.max() <= 4 * total, (seed, 10 * np.log10(mdp.powers.max() / total))
        gaps = np.diff(np.sort(mdp.distances_m))
        assert gaps.size == 0 or gaps.min() > 0.01 * cell, (seed, mdp.distances_m)
        # the line-of-sight cluster is found where it is
        assert np.min(np.abs(mdp.distances_m - 3.5)) < 0.8  # a fifth of the cell


def test_mdp_order_does_not_grow_with_snr_into_the_diffuse_tail():
    """Four specular paths plus 30 diffuse ones 35-45 dB below: from 20 to 60 dB
    the estimate keeps the four (the tail has no fingerprint counterpart).
    Failed before: the order grew to the cap with SNR."""
    rng = np.random.default_rng(5)
    d = np.array([4.1, 6.6, 9.0, 15.2])
    p_db = np.array([0.0, -3.0, -6.0, -2.0])
    tail = rng.uniform(3.0, 30.0, 30)
    dd = np.concatenate([d, tail])
    pp = np.concatenate([p_db, rng.uniform(-45.0, -35.0, 30)])
    amps = np.sqrt(10 ** (pp / 10))[:, None] * np.exp(2j * np.pi * rng.uniform(size=(dd.size, 2)))
    clean = np.exp(-2j * np.pi * np.outer(F, dd / C)) @ amps
    for snr_db in (20, 40, 60):
        n0 = np.mean(np.abs(clean) ** 2) / 10 ** (snr_db / 10)
        mdp = MdpEstimator(DF)(clean + np.sqrt(n0) * _crandn(rng, *clean.shape))
        assert len(mdp) == 4, (snr_db, mdp.distances_m)
        # the tail's 30 unmodelled paths bias the fit by up to ~0.3 m (6.6 -> 6.9)
        np.testing.assert_allclose(np.sort(mdp.distances_m), d, atol=0.35)


def test_mdp_noiseless_close_pair_is_resolved_not_merged():
    """Noise-free, two paths 30 cm apart (0.08 of the 3.75 m cell) that do not
    cancel: both come back exactly (merging is for cancelling roots only)."""
    d = np.array([6.0, 6.3, 11.0])
    amps = np.array([[1.0], [0.7 * np.exp(1j)], [0.4j]])
    mdp = MdpEstimator(DF)(_csi(d, amps, 0.0, np.random.default_rng(0)))
    assert len(mdp) == 3
    np.testing.assert_allclose(np.sort(mdp.distances_m), d, atol=1e-4)
    np.testing.assert_allclose(np.sort(mdp.powers), [0.16, 0.49, 1.0], rtol=1e-3)


def test_mdp_robustness_settings_are_checked():
    with pytest.raises(ValueError, match="min_separation"):
        MdpEstimator(DF, min_separation=1.5)
    with pytest.raises(ValueError, match="max_power_ratio"):
        MdpEstimator(DF, max_power_ratio=0.0)
    with pytest.raises(ValueError, match="dynamic_range_db"):
        MdpEstimator(DF, dynamic_range_db=-3.0)
    with pytest.raises(ValueError, match="refine must be True, False or 'final'"):
        MdpEstimator(DF, refine="always")


def test_mdp_refine_final_matches_refine_every_order():
    """refine='final' (least squares on the chosen order only, the per-fix budget
    setting) finds the same paths as refining every order."""
    rng = np.random.default_rng(8)
    d = np.array([4.1, 6.6, 9.0, 15.2])
    amps = np.exp(2j * np.pi * rng.uniform(size=(4, 2)))
    clean = np.exp(-2j * np.pi * np.outer(F, d / C)) @ amps
    h = clean + np.sqrt(np.mean(np.abs(clean) ** 2) / 100) * _crandn(rng, *clean.shape)
    every, final = MdpEstimator(DF)(h), MdpEstimator(DF, refine="final")(h)
    assert len(final) == len(every) == 4
    np.testing.assert_allclose(np.sort(final.distances_m), np.sort(every.distances_m), atol=1e-3)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_mdp_refinement_is_a_least_squares_optimum_by_scipy(seed):
    """The refined lengths (the estimator's own variable-projection LM, fixed
    order) minimise the fit residual: scipy's MINPACK Levenberg-Marquardt,
    started there on the full residual (amplitudes as free parameters),
    neither lowers the residual nor moves the lengths by more than a
    millimetre. Dense multipath at
    20 dB on AP2's comb: a large-residual fit, where a Gauss-Newton step
    without the full Jacobian converges slowest."""
    scipy_optimize = pytest.importorskip("scipy.optimize")
    f, h = _dense(seed, 20.0)
    order = 4
    mdp = MdpEstimator(8 * DF, subband=64, order=order, dynamic_range_db=None,
                       max_power_ratio=1e9)(h, frequencies_hz=f)
    assert len(mdp) == order
    d = mdp.distances_m
    e = np.exp(-2j * np.pi * np.outer(f / C, d))
    c, *_ = np.linalg.lstsq(e, h, rcond=None)  # [k, S]

    def resid(x):
        dd, amp = x[:order], x[order:].reshape(2, order, -1)
        r = h - np.exp(-2j * np.pi * np.outer(f / C, dd)) @ (amp[0] + 1j * amp[1])
        return np.concatenate([r.real.ravel(), r.imag.ravel()])

    x0 = np.concatenate([d, c.real.ravel(), c.imag.ravel()])
    sol = scipy_optimize.least_squares(resid, x0, method="lm", xtol=1e-12, ftol=1e-12)
    cost0 = np.sum(resid(x0) ** 2)
    assert 2 * sol.cost >= cost0 * (1 - 1e-7)
    # a flat valley (MINPACK's own stopping rule, ftol 1e-8, stops as far off):
    # a millimetre, against a 3.75 m cell and centimetres of noise
    np.testing.assert_allclose(sol.x[:order], d, atol=1e-3)


def test_noise_power_from_delay_tail_is_the_noise_added():
    """The noise variance read off the delay-domain tail of a multipath channel (the
    lab's recorded grid: 64 subcarriers 1.25 MHz apart, 4 x 8 antenna pairs) is the
    variance of the white noise added, at any SNR; a noise-free channel reads as its
    window leakage, far below."""
    rng = np.random.default_rng(5)
    f = F[::16]
    d = np.array([5.7, 9.1, 14.0, 22.5, 31.0])  # path lengths, m (depth-3 room paths)
    amps = np.array([1.0, 0.6, 0.4, 0.2, 0.1])[:, None] * _crandn(rng, 5, 32)
    h = (np.exp(-2j * np.pi * np.outer(f, d / C)) @ amps).T  # [32 pairs, 64]
    p = np.mean(np.abs(h) ** 2)
    assert noise_power_from_delay_tail(h, f) < p * 1e-6
    for snr_db in (0.0, 10.0, 20.0, 30.0):
        n0 = p / 10 ** (snr_db / 10)
        got = noise_power_from_delay_tail(h + np.sqrt(n0) * _crandn(rng, *h.shape), f)
        assert got == pytest.approx(n0, rel=0.1), snr_db


def test_noise_power_from_delay_tail_refuses_a_grid_without_a_tail():
    h = np.ones((2, 16), complex)
    with pytest.raises(ValueError, match="no tail beyond"):  # 16 x 5 MHz: 200 ns period
        noise_power_from_delay_tail(h, F[::64])
    with pytest.raises(ValueError, match="evenly spaced"):
        noise_power_from_delay_tail(h, np.r_[F[:8], F[100:108]])
    with pytest.raises(ValueError, match=r"h must be \[\.\.\., K=64\]"):
        noise_power_from_delay_tail(h, F[::16])
