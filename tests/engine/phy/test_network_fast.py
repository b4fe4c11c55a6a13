"""NetworkPHY: the fast path (closed forms, reuse, mask restriction, time-invariant
shortcut) against the np.linalg reference composition."""

import dataclasses

import numpy as np
import pytest

import isac_twin
from isac_twin import LinkPaths, NetworkPHY, load_scene


@pytest.fixture(scope="module")
def lab_config():
    cfg = load_scene(isac_twin.bundled_scene_dir()).config
    ofdm = dataclasses.replace(cfg.ofdm, num_subcarriers=256)
    devs = []
    for d in cfg.devices:
        devs.append(dataclasses.replace(d, subcarriers=(0, 256)))
    robot = next(d for d in devs if d.name == "robot1")
    devs.append(dataclasses.replace(robot, name="robot2",
                                    array=dataclasses.replace(robot.array, cols=1)))
    return dataclasses.replace(cfg, ofdm=ofdm, devices=tuple(devs))


def _paths(rng, tx, rx, num_paths=40, doppler_hz=2.0, los_only=False):
    L = 1 if los_only else num_paths
    z = np.zeros(L)
    a = (rng.standard_normal(L) + 1j * rng.standard_normal(L)) * 3e-4 \
        * np.exp(-np.arange(L) / 10)
    return LinkPaths(
        tx=tx, rx=rx, tx_position=np.zeros(3), rx_position=np.ones(3),
        tx_orientation=np.array([0.0, 0.0, 0.3]), rx_orientation=np.array([0.0, 0.0, 1.2]),
        frequency_hz=2.4e9, a=a, tau=np.sort(rng.uniform(10e-9, 120e-9, L)),
        doppler=rng.uniform(-doppler_hz, doppler_hz, L),
        theta_t=rng.uniform(0.3, 2.8, L), phi_t=rng.uniform(-np.pi, np.pi, L),
        theta_r=rng.uniform(0.3, 2.8, L), phi_r=rng.uniform(-np.pi, np.pi, L),
        vertices=np.zeros((L, 1, 3)), interactions=np.zeros((L, 1), np.int32) + 0 * z[:, None])


def _with_masks(cfg, **sets):
    devs = tuple(dataclasses.replace(d, **sets[d.name]) if d.name in sets else d
                 for d in cfg.devices)
    return dataclasses.replace(cfg, devices=devs)


def _compare(cfg, link_paths, rel=1e-6, **kw):
    ref = NetworkPHY(cfg, method="reference", **kw)(link_paths)
    fast = NetworkPHY(cfg, time_invariant_tol=0.0, **kw)(link_paths)
    assert set(ref) == set(fast)
    for lk, r in ref.items():
        f = fast[lk]
        assert f.rate_bps == pytest.approx(r.rate_bps, rel=rel)
        assert f.snr_db == pytest.approx(r.snr_db, abs=1e-4)
        assert f.sinr_db == pytest.approx(r.sinr_db, abs=1e-4)
        assert f.h.shape == r.h.shape and f.w.shape == r.w.shape and f.p.shape == r.p.shape
        m = r.mask
        np.testing.assert_allclose(np.sort(f.p[m].ravel()), np.sort(r.p[m].ravel()),
                                   rtol=1e-6, atol=1e-12 * r.p.max())
        assert not f.p[~m].any()
        # Precoders: orthonormal columns on the allocation; the power budget holds.
        wm = f.w[m].astype(np.complex128)
        s = wm.shape[-1]
        np.testing.assert_allclose(np.conj(wm).swapaxes(-1, -2) @ wm,
                                   np.broadcast_to(np.eye(s), (wm.shape[0], s, s)), atol=1e-5)
    return ref, fast


@pytest.mark.parametrize("los_only", [False, True])
def test_fast_network_matches_reference_full_grid(lab_config, los_only):
    rng = np.random.default_rng(1)
    lp = {("AP1", "robot1"): _paths(rng, "AP1", "robot1", los_only=los_only),
          ("AP2", "robot1"): _paths(rng, "AP2", "robot1", los_only=los_only)}
    _compare(lab_config, lp)


@pytest.mark.parametrize("power_allocation", ["waterfilling", "equal"])
@pytest.mark.parametrize("precoding", ["svd", "svd_wideband"])
def test_fast_network_matches_reference_partial_masks_and_cross_links(
        lab_config, power_allocation, precoding):
    rng = np.random.default_rng(2)
    cfg = _with_masks(lab_config, AP1={"subcarriers": (0, 200), "symbols": (0, 10)},
                      AP2={"subcarriers": (100, 256), "symbols": (5, 14)})
    # robot2 (1 antenna) is served by AP2 but hears AP1 too: AP1's precoder aimed
    # at robot1 reaches robot2 through the cross channel (not reusable).
    lp = {("AP1", "robot1"): _paths(rng, "AP1", "robot1"),
          ("AP2", "robot1"): _paths(rng, "AP2", "robot1"),
          ("AP2", "robot2"): _paths(rng, "AP2", "robot2"),
          ("AP1", "robot2"): _paths(rng, "AP1", "robot2")}
    _compare(cfg, lp, power_allocation=power_allocation, precoding=precoding)


@pytest.mark.parametrize("symbols", [((0, 14), (0, 14)), ((0, 7), (7, 14)), ((0, 10), (4, 14))])
def test_time_invariant_shortcut_is_exact_within_tolerance(lab_config, symbols):
    rng = np.random.default_rng(3)
    cfg = _with_masks(lab_config, AP1={"symbols": symbols[0]}, AP2={"symbols": symbols[1]})
    base = NetworkPHY(cfg, time_invariant_tol=0.0)
    # Doppler such that the mid-step phase drift is just below 1e-3 rad.
    t = base.grid.symbol_times
    nu = 0.99e-3 / (2 * np.pi * 0.5 * (t[-1] - t[0]))
    if symbols == ((0, 7), (7, 14)):
        nu *= 2  # two groups of 7 symbols: half the span each
    lp = {("AP1", "robot1"): _paths(rng, "AP1", "robot1", doppler_hz=nu),
          ("AP2", "robot1"): _paths(rng, "AP2", "robot1", doppler_hz=nu)}
    assert base.max_doppler_phase(lp) <= 1e-3
    exact = base(lp)
    ref = NetworkPHY(cfg, method="reference")(lp)
    short = NetworkPHY(cfg)(lp)  # default tolerance 1e-3 rad: shortcut taken
    for lk in exact:
        s, e = short[lk], exact[lk]
        # Shortcut taken: one channel per symbol group (<= 3 groups here).
        assert s.time_invariant and not e.time_invariant
        assert len(np.unique(s.h.reshape(s.h.shape[0], -1), axis=0)) <= 3
        assert s.h.shape == e.h.shape and s.w.shape == e.w.shape and s.p.shape == e.p.shape
        # The bit count errs by O(tol^2): well below 1e-5 relative.
        assert s.rate_bps == pytest.approx(e.rate_bps, rel=1e-6)
        assert s.rate_bps == pytest.approx(ref[lk].rate_bps, rel=1e-6)
        assert s.snr_db == pytest.approx(e.snr_db, abs=1e-3)
        assert s.sinr_db == pytest.approx(e.sinr_db, abs=1e-3)
        # Power budget over the transmitter's allocation.
        total = 10 ** ((cfg.device(lk[0]).power_dbm - 30) / 10)
        assert s.p.sum() <= total * (1 + 1e-9)
        assert not s.p[~s.mask].any()
        # The channel is the exact one at the mid-step time for every symbol.
        assert np.max(np.abs(s.h - e.h)) <= 2e-3 * np.max(np.abs(e.h))
    # Above the tolerance the shortcut is not taken (result identical to tol = 0).
    fast_lp = {lk: dataclasses.replace(p, doppler=p.doppler * 3) for lk, p in lp.items()}
    a, b = NetworkPHY(cfg)(fast_lp), base(fast_lp)
    for lk in a:
        assert a[lk].rate_bps == b[lk].rate_bps and not a[lk].time_invariant
        assert len(np.unique(a[lk].h.reshape(a[lk].h.shape[0], -1), axis=0)) == 14


def test_bad_method_and_tolerance(lab_config):
    with pytest.raises(ValueError, match="method"):
        NetworkPHY(lab_config, method="magic")
    with pytest.raises(ValueError, match="time_invariant_tol"):
        NetworkPHY(lab_config, time_invariant_tol=-1)
