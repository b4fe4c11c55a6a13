"""engine/phy/mcs.py: MCS tables against the published values, EVM floor, the
capacity-average effective SINR, and NetworkPHY's modem rate beside Shannon."""

import dataclasses

import numpy as np
import pytest

import isac_twin
from isac_twin import ConfigError, LinkPaths, NetworkPHY, load_config
from isac_twin.phy.mcs import TABLES, McsRate
from isac_twin.scene.config import LinkAdaptationConfig, parse_config


def test_tables_match_the_standards():
    he, nr = TABLES["he"], TABLES["nr_cqi2"]
    # 802.11ax: MCS 7 = 64-QAM 5/6 (5 bit), MCS 11 = 1024-QAM 5/6; sensitivities
    # -64 / -52 dBm (Table 27-51) with NF 10 dB + 5 dB margin in 20 MHz
    assert he.efficiency[7] == pytest.approx(5.0) and he.efficiency[11] == pytest.approx(50 / 6)
    assert he.snr_db[7] == pytest.approx(-64 + 174 - 73.0103 - 15, abs=1e-3)
    assert he.snr_db[0] == pytest.approx(3.99, abs=0.01)
    # TS 38.214 Table 5.2.2.1-3: CQI 15 = 256-QAM 948/1024 (7.4063), CQI 1 QPSK 78
    assert nr.efficiency[-1] == pytest.approx(7.4063, abs=1e-4)
    assert nr.efficiency[0] == pytest.approx(0.1523, abs=1e-4)
    for t in (he, nr):
        assert np.all(np.diff(t.snr_db) > 0) and np.all(np.diff(t.efficiency) > 0)


def test_flat_awgn_picks_the_table_entry():
    rate = McsRate("he", evm_db=-60)
    sinr = np.full((100, 1), 10 ** 1.5)  # 15 dB: MCS 3 (12 dB) fits, MCS 4 (16 dB) not
    bits, mcs = rate(sinr, np.ones((100, 1)))
    assert list(mcs) == [3] and bits == pytest.approx(2.0 * 100)
    # weights: rows standing for 3 REs each
    bits3, _ = rate(sinr, np.ones((100, 1)), np.full(100, 3.0))
    assert bits3 == pytest.approx(600.0)


def test_evm_floor_caps_the_stream():
    sinr = np.full((10, 2), 1e6)  # 60 dB
    assert list(McsRate("he", -35)(sinr, np.ones((10, 2)))[1]) == [11, 11]  # <= 35 dB
    assert list(McsRate("he", -25)(sinr, np.ones((10, 2)))[1]) == [7, 7]    # ~25 dB
    assert list(McsRate("nr_cqi2", -25)(sinr, np.ones((10, 2)))[1]) == [9, 9]


def test_effective_sinr_is_the_capacity_average_and_skips_silent_streams():
    sinr = np.array([[1000.0, 5.0], [1.0, 5.0]])  # 30 dB and 0 dB on stream 0
    p = np.array([[1.0, 0.0], [1.0, 0.0]])        # stream 1 has no power
    bits, mcs = McsRate("he", -60)(sinr, p)
    eff = np.sqrt(1001.0 * 2.0) - 1   # 2^(mean log2(1 + sinr)) - 1 = 16.4 dB
    assert 10 * np.log10(eff) == pytest.approx(16.41, abs=0.01)
    # 16.4 dB: MCS 4 (16 dB, 3 bit) -- the mean in dB (15 dB) would give MCS 3
    assert list(mcs) == [4, -1] and bits == pytest.approx(2 * 3.0)
    assert McsRate("he")(np.full((4, 1), 0.5), np.ones((4, 1)))[0] == 0.0  # below MCS 0


@pytest.mark.parametrize("weighted", [False, True])
def test_many_links_at_once_equal_one_at_a_time(weighted):
    """Issue 19: ``McsRate.many`` (the batched PHY's MCS over a stack of links)
    gives each link what it gets alone, silent REs and streams included."""
    rng = np.random.default_rng(3)
    sinr = 10 ** rng.uniform(-1, 4, size=(5, 64, 2))
    p = rng.uniform(0, 1, size=(5, 64, 2)) * (rng.uniform(size=(5, 64, 2)) > 0.2)
    p[2, :, 1] = 0  # a silent stream
    sinr[4] = 0.01  # nothing fits
    wts = rng.integers(1, 4, size=64).astype(float) if weighted else None
    rate = McsRate("he", -35)
    bits, idx = rate.many(sinr, p, wts)
    assert bits.shape == (5,) and idx.shape == (5, 2)
    for b in range(5):
        one_bits, one_idx = rate(sinr[b], p[b], wts)
        assert bits[b] == pytest.approx(one_bits, rel=1e-12) and list(idx[b]) == list(one_idx)
    assert idx[2, 1] == -1 and bits[4] == 0.0 and len(set(bits[:4])) == 4


def test_bad_link_adaptation_is_refused_at_load():
    cfg = load_config(isac_twin.bundled_scene_dir())
    assert cfg.link_adaptation == LinkAdaptationConfig("he", -35.0)
    for table, msg in [({"table": "lte"}, r"link_adaptation\.table: expected one of he, "
                                          r"nr_cqi2"),
                       ({"evm_db": 3}, r"link_adaptation\.evm_db"),
                       ({"gap": 1}, r"link_adaptation\.gap: unknown key")]:
        with pytest.raises(ConfigError, match=msg):
            parse_config(dict(cfg.raw, link_adaptation=table), cfg.path)
    got = parse_config(dict(cfg.raw, link_adaptation={"table": "nr_cqi2", "evm_db": -28}),
                       cfg.path).link_adaptation
    assert got == LinkAdaptationConfig("nr_cqi2", -28.0)


def _paths(rng, tx, rx, scale):
    L = 12
    return LinkPaths(
        tx=tx, rx=rx, tx_position=np.zeros(3), rx_position=np.ones(3),
        tx_orientation=np.zeros(3), rx_orientation=np.zeros(3), frequency_hz=2.4e9,
        a=(rng.standard_normal(L) + 1j * rng.standard_normal(L)) * scale,
        tau=np.sort(rng.uniform(10e-9, 120e-9, L)), doppler=np.zeros(L),
        theta_t=rng.uniform(0.3, 2.8, L), phi_t=rng.uniform(-np.pi, np.pi, L),
        theta_r=rng.uniform(0.3, 2.8, L), phi_r=rng.uniform(-np.pi, np.pi, L),
        vertices=np.zeros((L, 1, 3)), interactions=np.zeros((L, 1), np.int32))


@pytest.mark.parametrize("scale", [3e-4, 3e-7])
def test_network_modem_rate_below_shannon_and_fast_equals_reference(scale):
    cfg = load_config(isac_twin.bundled_scene_dir())
    cfg = dataclasses.replace(cfg, ofdm=dataclasses.replace(cfg.ofdm, num_subcarriers=128),
                              devices=tuple(dataclasses.replace(d, subcarriers=(0, 128))
                                            for d in cfg.devices))
    rng = np.random.default_rng(3)
    lp = {("AP1", "robot1"): _paths(rng, "AP1", "robot1", scale)}
    for table in ("he", "nr_cqi2"):
        c = dataclasses.replace(cfg, link_adaptation=LinkAdaptationConfig(table, -35.0))
        fast = NetworkPHY(c, time_invariant_tol=0.0)(lp)[("AP1", "robot1")]
        ref = NetworkPHY(c, method="reference")(lp)[("AP1", "robot1")]
        assert 0 < fast.mcs_rate_bps < fast.rate_bps
        assert fast.mcs_rate_bps == pytest.approx(ref.mcs_rate_bps, rel=1e-9)
        assert fast.mcs == ref.mcs and len(fast.mcs) == 2
        # bits = sum over streams of efficiency x REs the stream uses
        t = TABLES[table]
        n_re = (fast.p > 0).sum(axis=(0, 1))
        want = sum(t.efficiency[i] * n for i, n in zip(fast.mcs, n_re) if i >= 0)
        assert fast.mcs_rate_bps * NetworkPHY(c).grid.step_duration_s == pytest.approx(want)
