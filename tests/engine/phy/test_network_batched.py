"""NetworkPHY(method="batched"), all links of a step in one stacked pass, against
the per-link closed forms (method="fast") and np.linalg (method="reference") on
the same paths: many robots, mixed arrays, interference and cross links."""

import dataclasses

import numpy as np
import pytest

import isac_twin
from isac_twin import LinkPaths, NetworkPHY, load_scene
from isac_twin.phy.network import METHODS


def _paths(rng, tx, rx, num_paths, doppler_hz, rx_yaw):
    L = num_paths
    a = (rng.standard_normal(L) + 1j * rng.standard_normal(L)) * 3e-4 * np.exp(-np.arange(L) / 10)
    return LinkPaths(
        tx=tx, rx=rx, tx_position=np.zeros(3), rx_position=np.ones(3),
        tx_orientation=np.array([0.0, 0.0, 0.3]), rx_orientation=np.array([0.0, 0.0, rx_yaw]),
        frequency_hz=2.4e9, a=a, tau=np.sort(rng.uniform(10e-9, 120e-9, L)),
        doppler=rng.uniform(-doppler_hz, doppler_hz, L),
        theta_t=rng.uniform(0.3, 2.8, L), phi_t=rng.uniform(-np.pi, np.pi, L),
        theta_r=rng.uniform(0.3, 2.8, L), phi_r=rng.uniform(-np.pi, np.pi, L),
        vertices=np.zeros((L, 1, 3)), interactions=np.zeros((L, 1), np.int32))


@pytest.fixture(scope="module")
def many_robots():
    """The lab (256 subcarriers) with 5 robots: robot1 (1 x 2) and copies with
    1 x 2 and 1 x 1 arrays, each heard by both APs (10 links); path counts differ
    per link (0 paths on one link)."""
    cfg = load_scene(isac_twin.bundled_scene_dir()).config
    ofdm = dataclasses.replace(cfg.ofdm, num_subcarriers=256)
    devs = [dataclasses.replace(d, subcarriers=(0, 256)) for d in cfg.devices]
    robot = next(d for d in devs if d.name == "robot1")
    for k, cols in ((2, 2), (3, 1), (4, 2), (5, 1)):
        devs.append(dataclasses.replace(robot, name=f"robot{k}",
                                        array=dataclasses.replace(robot.array, cols=cols)))
    cfg = dataclasses.replace(cfg, ofdm=ofdm, devices=tuple(devs))
    rng = np.random.default_rng(19)
    lp = {}
    for k in range(1, 6):
        for ap in ("AP1", "AP2"):
            n = 0 if (k, ap) == (4, "AP2") else int(rng.integers(5, 60))
            lp[(ap, f"robot{k}")] = _paths(rng, ap, f"robot{k}", n, 1.0, 0.4 * k)
    return cfg, lp


def _masks(cfg, ap1, ap2):
    sets = {"AP1": ap1, "AP2": ap2}
    return dataclasses.replace(cfg, devices=tuple(
        dataclasses.replace(d, **sets[d.name]) if d.name in sets else d for d in cfg.devices))


ALLOCATIONS = {
    "disjoint symbols": ({"symbols": (0, 7)}, {"symbols": (7, 14)}),
    "overlap": ({"subcarriers": (0, 200), "symbols": (0, 10)},
                {"subcarriers": (100, 256), "symbols": (5, 14)}),
    "full grid": ({}, {}),
}


@pytest.mark.parametrize("alloc", list(ALLOCATIONS))
@pytest.mark.parametrize("kw", [dict(), dict(time_invariant_tol=0.0),
                                dict(precoding="svd_wideband"),
                                dict(power_allocation="equal")], ids=str)
def test_batched_equals_per_link(many_robots, alloc, kw):
    cfg, lp = many_robots
    cfg = _masks(cfg, *ALLOCATIONS[alloc])
    batched = NetworkPHY(cfg, **kw)(lp)  # the default method
    per_link = NetworkPHY(cfg, method="fast", **kw)(lp)
    assert NetworkPHY(cfg).method == "batched" and set(batched) == set(per_link) == set(lp)
    for lk, r in per_link.items():
        b = batched[lk]
        assert b.rate_bps == pytest.approx(r.rate_bps, rel=1e-6, abs=1e-6)
        assert b.mcs_rate_bps == pytest.approx(r.mcs_rate_bps, rel=1e-6, abs=1e-6)
        assert b.mcs == r.mcs and b.time_invariant == r.time_invariant
        assert b.snr_db == pytest.approx(r.snr_db, abs=1e-6)
        assert b.sinr_db == pytest.approx(r.sinr_db, abs=1e-6)
        np.testing.assert_allclose(b.h, r.h, rtol=0, atol=1e-6 * max(np.abs(r.h).max(), 1e-30))
        np.testing.assert_allclose(b.p, r.p, rtol=1e-6, atol=1e-12 * max(r.p.max(), 1e-30))
        # precoders formed on request (no interferer at another receiver needs
        # them here) equal the per-link ones (unit columns, complex64)
        np.testing.assert_allclose(b.w, r.w, rtol=0, atol=1e-4)
    # The stacked pass is not a copy of one link: links differ.
    rates = [r.rate_bps for r in per_link.values() if r.rate_bps > 0]
    assert len(set(rates)) == len(rates)


def test_batched_equals_reference_with_interference(many_robots):
    cfg, lp = many_robots
    cfg = _masks(cfg, *ALLOCATIONS["overlap"])
    ref = NetworkPHY(cfg, method="reference")(lp)
    batched = NetworkPHY(cfg, time_invariant_tol=0.0)(lp)
    for lk, r in ref.items():
        assert batched[lk].rate_bps == pytest.approx(r.rate_bps, rel=1e-6, abs=1e-6)


def test_channels_one_pass_equal_per_link(many_robots):
    cfg, lp = many_robots
    phy = NetworkPHY(cfg)
    hs = phy.channels(lp)
    for lk, p in lp.items():
        h = phy.channel(p)
        assert hs[lk].shape == h.shape and hs[lk].dtype == h.dtype
        np.testing.assert_allclose(hs[lk], h, rtol=0, atol=1e-6 * max(np.abs(h).max(), 1e-30))
    # The cached array positions follow an orientation change.
    turned = {lk: dataclasses.replace(p, rx_orientation=p.rx_orientation + [0, 0, 0.7])
              for lk, p in lp.items()}
    for lk, p in turned.items():
        np.testing.assert_allclose(phy.channels({lk: p})[lk], phy.channel(p), rtol=0,
                                   atol=1e-6 * max(np.abs(phy.channel(p)).max(), 1e-30))


@pytest.mark.parametrize("kw", [dict(), dict(time_invariant_tol=0.0)], ids=str)
def test_channel_off_the_allocation_is_computed_on_read(many_robots, kw):
    """Issue 19: on disjoint symbols the step synthesises each link only on its
    transmitter's symbols (groups); reading ``h`` adds the others, equal to one
    pass over every symbol (Taylor basis and Doppler bound of the step's batch)."""
    cfg, lp = many_robots
    cfg = _masks(cfg, *ALLOCATIONS["disjoint symbols"])
    phy = NetworkPHY(cfg, **kw)
    sig = phy(lp)
    g = sig[("AP1", "robot1")].group
    times = None if g is None else np.bincount(g, weights=phy.grid.symbol_times) / np.bincount(g)

    every = phy.channels(lp, times)
    for lk, s in sig.items():
        assert "h_by_group" not in vars(s)
        np.testing.assert_allclose(s.h_by_group, every[lk], rtol=0,
                                   atol=1e-6 * max(np.abs(every[lk]).max(), 1e-30))
    one = phy.channels(lp, times, rows={lk: [1] for lk in lp})
    for lk in lp:  # a symbol's value does not depend on which others are computed
        np.testing.assert_allclose(one[lk][0], every[lk][1], rtol=0,
                                   atol=1e-6 * max(np.abs(every[lk]).max(), 1e-30))


def test_method_refused_with_one_line(many_robots):
    with pytest.raises(ValueError, match="batched, fast, reference"):
        NetworkPHY(many_robots[0], method="per-link")
    assert METHODS == ("batched", "fast", "reference")
