"""Localizers and measurements: noise-free hits, pilot-mode MDP accuracy, clustering."""

import numpy as np
import pytest

from engine.localization.baselines import (MCA, KnnCsi, PdpMatch, cluster_lengths,
                                           observe_database_point)
from engine.localization.measurements import (FeatureSpec, PilotSettings, observe_pilots,
                                              observe_tracer)
from engine.raytrace.base import SPEED_OF_LIGHT, LinkPaths
from engine.scene import load_scene


@pytest.mark.slow
def test_baselines_find_the_point_on_noise_free_data(lab, lab_db):
    spec = FeatureSpec.from_config(load_scene(lab, load_sionna=False).config)
    locs = [MCA(lab_db, k=1, num_paths=9), KnnCsi(lab_db, spec, k=1), PdpMatch(lab_db, spec, k=1)]
    for i in lab_db.free_indices[::7]:
        obs = observe_database_point(lab_db, i, spec)
        for loc in locs:
            np.testing.assert_allclose(loc(obs)[:2], lab_db.points[i, :2], atol=1e-9,
                                       err_msg=loc.name)


def _link(lengths, amps, tx="AP1", rx="robot1"):
    L = len(lengths)
    tau = np.asarray(lengths, float) / SPEED_OF_LIGHT
    z = np.zeros(L)
    return LinkPaths(tx=tx, rx=rx, tx_position=np.zeros(3), rx_position=np.ones(3),
                     tx_orientation=np.zeros(3), rx_orientation=np.zeros(3),
                     frequency_hz=2.4e9, a=np.asarray(amps, complex), tau=tau, doppler=z,
                     theta_t=np.full(L, 1.4), phi_t=np.linspace(-0.5, 0.5, L),
                     theta_r=np.full(L, 1.7), phi_r=np.linspace(2.0, 3.0, L),
                     vertices=np.zeros((L, 1, 3)), interactions=np.zeros((L, 1), np.int32))


def test_pilot_mdp_matches_tracer_delays_at_high_snr(lab):
    from engine.phy.network import NetworkPHY

    cfg = load_scene(lab, load_sionna=False).config
    spec = FeatureSpec.from_config(cfg)
    phy = NetworkPHY(cfg)
    true = [5.0, 9.0, 14.0]
    links = [_link(true, [1e-3, 6e-4, 3e-4], "AP1"), _link([3.0, 7.5], [1e-3, 4e-4], "AP2")]
    chans = [phy.channel(lp) for lp in links]
    obs = observe_pilots(links, chans, spec, PilotSettings(snr_db=40.0), num_paths=9)
    ideal = observe_tracer(links, spec, num_paths=9)
    for a, want in enumerate((true, [3.0, 7.5])):
        got = np.sort(obs.lengths[a][np.isfinite(obs.lengths[a])])
        assert len(got) == len(want)
        np.testing.assert_allclose(got, want, atol=0.02)
        np.testing.assert_allclose(np.sort(ideal.lengths[a][np.isfinite(ideal.lengths[a])]),
                                   want, atol=1e-9)
    # the PDP from pilots peaks where the paths are
    b = spec.pdp_bins_m[np.argmax(obs.pdp_db[0])]
    assert abs(b - 5.0) <= 0.5


def test_cluster_lengths_merges_close_paths():
    lengths = np.array([[[4.70, 4.80, 9.0, np.nan]]])
    power = np.array([[[1.0, 1.0, 0.5, 0.0]]])
    cl = cluster_lengths(lengths, power, 0.5, 3)
    np.testing.assert_allclose(cl[0, 0, :2], [4.75, 9.0])
    assert np.isnan(cl[0, 0, 2])


def test_resource_allocation_helpers(lab):
    from engine.casestudy import allocation, disjoint_config, shared_config

    cfg = load_scene(lab, load_sionna=False).config
    assert allocation(cfg) == "disjoint"
    shared = shared_config(cfg)
    assert allocation(shared) == "shared REs"
    d = disjoint_config(shared)
    assert allocation(d) == "disjoint"
    assert [x.symbols for x in d.devices if x.kind == "access_point"] == [(0, 7), (7, 14)]
