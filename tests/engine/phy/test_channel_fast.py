"""isac_twin.phy.channel fast synthesis (factored delay phases, Taylor-in-time Doppler)
against a direct full-kernel evaluation of eq. 4."""

import numpy as np
import pytest

from isac_twin.phy.arrays import PlanarArray
from isac_twin.phy.channel import OFDMChannel, _delay_phase, _taylor_order
from isac_twin.phy.ofdm import ResourceGrid


def _direct(grid, rx, tx, p, times=None):
    t = grid.symbol_times if times is None else np.asarray(times)
    f = grid.subcarrier_frequencies
    a_r = rx.steering_vectors(p["theta_r"], p["phi_r"])
    a_t = tx.steering_vectors(p["theta_t"], p["phi_t"])
    kern = np.exp(2j * np.pi * (t[:, None, None] * p["doppler"] - f[None, :, None] * p["tau"]))
    return np.einsum("knl,l,lr,lt->knrt", kern, p["b"], a_r, a_t)


@pytest.mark.parametrize("doppler", [0.0, 2.0, 20.0, 200.0, 5000.0])
@pytest.mark.parametrize("n", [1024, 300, 7])
def test_synthesis_matches_direct_kernel(doppler, n):
    rng = np.random.default_rng(int(doppler) + n)
    grid = ResourceGrid(n, 78125.0, 14, cyclic_prefix_samples=72)
    rx, tx = PlanarArray(1, 2), PlanarArray(2, 3)
    L = 25
    p = dict(b=rng.standard_normal(L) + 1j * rng.standard_normal(L),
             tau=rng.uniform(1e-8, 3e-7, L), doppler=rng.uniform(-doppler, doppler, L),
             theta_r=rng.uniform(0, np.pi, L), phi_r=rng.uniform(-np.pi, np.pi, L),
             theta_t=rng.uniform(0, np.pi, L), phi_t=rng.uniform(-np.pi, np.pi, L))
    ref = _direct(grid, rx, tx, p)
    scale = np.abs(p["b"]).sum()
    h = OFDMChannel(grid, rx, tx, dtype=np.complex128)(**p)
    assert np.abs(h - ref).max() <= 1e-9 * scale
    h32 = OFDMChannel(grid, rx, tx)(**p)
    assert h32.dtype == np.complex64
    assert np.abs(h32 - ref).max() <= 1e-6 * scale
    times = [3e-5, 1e-4]
    ht = OFDMChannel(grid, rx, tx, dtype=np.complex128)(**p, times=times)
    assert ht.shape == (2, n, 2, 6)
    assert np.abs(ht - _direct(grid, rx, tx, p, times)).max() <= 1e-9 * scale


def test_taylor_order():
    assert _taylor_order(0.0, 6) == 0
    assert _taylor_order(1e-3, 6) == 3  # (1e-3)^4 / 24 < 1e-10 < (1e-3)^3 / 6
    assert _taylor_order(1.0, 6) is None


@pytest.mark.parametrize("n", [1024, 300, 7, 1])
def test_delay_phase_table_to_float64_rounding(n):
    """Issue 19: the table from running products of reduced exponentials (3 per
    path) stays at float64 rounding of the direct exp(-j 2 pi f_n tau); the
    complex64 table is the complex128 one rounded once."""
    grid = ResourceGrid(n, 78125.0, 14, cyclic_prefix_samples=72)
    tau = np.random.default_rng(n).uniform(1e-9, 3e-7, 300)
    ref = np.exp(-2j * np.pi * np.mod(np.outer(grid.subcarrier_frequencies, tau), 1.0))
    d = _delay_phase(grid, tau)
    assert d.shape == (n, 300) and d.dtype == np.complex128
    assert np.abs(d - ref).max() <= 1e-13
    np.testing.assert_array_equal(_delay_phase(grid, tau, np.complex64), d.astype(np.complex64))
