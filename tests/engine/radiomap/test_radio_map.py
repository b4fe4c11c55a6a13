"""engine/radiomap/radio_map.py: Sionna's RadioMapSolver on the floor plane, checked against Friis (LOS
only) and against Sionna's PathSolver (incoherent sum of the path powers at cell centres)."""

import numpy as np
import pytest

from isac_twin import load_scene
from isac_twin.radiomap.radio_map import (
    compute_radio_map,
    load_radio_map,
    radio_map_from_gain,
    save_radio_map,
)
from isac_twin.scene.synthetic import two_ap_lab

C = 299_792_458.0


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    folder = two_ap_lab(tmp_path_factory.mktemp("rm") / "lab",
                        furniture={"desk": ((2.0, 2.5, 0.0), (3.5, 3.5, 0.75))},
                        tracer={"samples_per_src": 100000, "max_depth": 2})
    return load_scene(folder)


@pytest.mark.slow
def test_los_only_map_matches_friis(lab):
    """max_depth 0: every cell holds the free-space gain (lambda / 4 pi d)^2 of its centre."""
    rm = compute_radio_map(lab, cell_size=0.25, max_depth=0, samples_per_tx=1_000_000)
    lam = C / lab.config.scene.frequency_hz
    centres = rm.cell_centers()
    inside = ((centres[..., 0] > 0.3) & (centres[..., 0] < 5.7) & (centres[..., 1] > 0.3)
              & (centres[..., 1] < 3.7))
    for i, p in enumerate(rm.tx_positions):
        d = np.linalg.norm(centres - p, axis=-1)
        friis = 20 * np.log10(lam / (4 * np.pi * d))
        # the desk shadows some cells of AP1/AP2; compare cells at >= 1.5 m that are lit
        sel = inside & (d > 1.5) & np.isfinite(rm.path_gain_db[i])
        diff = rm.path_gain_db[i][sel] - friis[sel]
        assert sel.sum() > 100
        assert abs(np.median(diff)) < 0.3, np.median(diff)
        assert np.percentile(np.abs(diff), 90) < 1.5
    # the 20 dBm APs: RSS is path gain + power
    lit = np.isfinite(rm.path_gain_db)
    assert np.allclose(rm.rss_dbm[lit] - rm.path_gain_db[lit], 20.0, atol=1e-4)
    assert np.array_equal(np.isneginf(rm.rss_dbm), np.isneginf(rm.path_gain_db))
    # cells inside the desk (0.75 m high) and the wall slabs are not free: NaN, not -inf
    assert np.array_equal(np.isnan(rm.rss_dbm), np.broadcast_to(~rm.free, rm.rss_dbm.shape))
    ix, iy = rm.cell_of((2.75, 3.0))[::-1]
    assert not rm.free[iy, ix] and rm.free[rm.cell_of((1.0, 1.0))]
    assert rm.best_server[iy, ix] == -1


def _pathsolver_gain(folder_scene, tx_pos, points, depth):
    """Incoherent sum of |a|^2 of Sionna's PathSolver paths, isotropic antennas: ``[M]``."""
    from isac_twin.raytrace.solver_core import load_sionna_rt

    rt = load_sionna_rt()
    sc = rt.load_scene(str(folder_scene.config.scene.file), merge_shapes=False)
    sc.frequency = folder_scene.config.scene.frequency_hz
    iso = rt.PlanarArray(num_rows=1, num_cols=1, pattern="iso", polarization="V")
    sc.tx_array = sc.rx_array = iso
    sc.add(rt.Transmitter("tx", position=[float(x) for x in tx_pos]))
    for k, q in enumerate(points):
        sc.add(rt.Receiver(f"rx{k}", position=[float(x) for x in q]))
    paths = rt.PathSolver()(sc, max_depth=depth, samples_per_src=200_000,
                            max_num_paths_per_src=200_000, refraction=True)
    a_re, a_im = (np.asarray(x.numpy()) for x in paths.a)   # [rx, 1, tx, 1, P]
    return (a_re ** 2 + a_im ** 2).reshape(len(points), -1).sum(-1)


@pytest.mark.slow
def test_map_matches_pathsolver_at_cell_centres(lab):
    """Median |map - incoherent path sum| at 30 cell centres within 2 dB (the issue's bound)."""
    rm = compute_radio_map(lab, cell_size=0.25, samples_per_tx=1_000_000)
    rng = np.random.default_rng(1)
    centres = rm.cell_centers().reshape(-1, 3)
    ok = ((centres[:, 0] > 0.3) & (centres[:, 0] < 5.7) & (centres[:, 1] > 0.3)
          & (centres[:, 1] < 3.7))
    ok &= ~((centres[:, 0] > 1.9) & (centres[:, 0] < 3.6) & (centres[:, 1] > 2.4)
            & (centres[:, 1] < 3.6))  # not under the desk
    idx = rng.choice(np.flatnonzero(ok), 30, replace=False)
    for i, name in enumerate(rm.tx_names):
        ref = 10 * np.log10(_pathsolver_gain(lab, rm.tx_positions[i], centres[idx], 2))
        got = rm.path_gain_db[i].reshape(-1)[idx]
        diff = got - ref
        print(name, "median |diff| dB", np.median(np.abs(diff)))
        assert np.median(np.abs(diff)) < 2.0


@pytest.mark.slow
def test_shared_scene_keeps_the_tracers_devices(lab):
    from isac_twin import device_poses
    from isac_twin.raytrace.sionna import SionnaTracer

    tracer = SionnaTracer(lab.config.tracer)
    before = tracer(lab, device_poses(lab.config))
    sc = lab.sionna
    tx, rx, arrays = dict(sc.transmitters), dict(sc.receivers), (sc.tx_array, sc.rx_array)
    compute_radio_map(lab, cell_size=0.5, samples_per_tx=20_000)
    assert dict(sc.transmitters) == tx and dict(sc.receivers) == rx
    assert all(sc.transmitters[k] is v for k, v in tx.items())
    assert (sc.tx_array, sc.rx_array) == arrays
    after = tracer(lab, device_poses(lab.config))
    for k in before:
        assert np.allclose(before[k].power, after[k].power)


def test_derived_quantities_by_hand():
    gain = np.array([[[1e-6, 0.0]], [[1e-7, 0.0]]])            # [S=2, ny=1, nx=2]
    rm = radio_map_from_gain(gain, ["A", "B"], origin=(0.5, 0.5), cell_size=1.0, height=0.2,
                             tx_positions=[[0, 0, 2], [5, 0, 2]], tx_power_dbm=[20.0, 30.0],
                             noise_dbm=-90.0)
    # both 20 dBm + (-60) = -40 dBm and 30 + (-70) = -40 dBm: a tie -> index 0 (A)
    assert rm.rss_dbm[:, 0, 0] == pytest.approx([-40.0, -40.0], abs=1e-4)
    assert rm.best_server[0, 0] == 0 and rm.best_server[0, 1] == -1
    noise_w = 1e-12
    assert rm.sinr_db[0, 0] == pytest.approx(10 * np.log10(1e-7 / (1e-7 + noise_w)), abs=1e-4)
    assert rm.snr_db[0, 0] == pytest.approx(50.0, abs=1e-4)
    assert np.isneginf(rm.sinr_db[0, 1]) and np.isneginf(rm.path_gain_db[0, 0, 1])
    assert rm.cell_of((1.2, 0.9)) == (0, 1)
    with pytest.raises(ValueError, match=r"outside the radio map"):
        rm.cell_of((3.0, 0.5))


def test_npz_round_trip_and_foreign_file(tmp_path):
    rm = radio_map_from_gain(np.full((1, 2, 3), 1e-5), ["A"], origin=(0, 0), cell_size=0.5,
                             height=0.2, tx_positions=[[0, 0, 1]], tx_power_dbm=[10.0],
                             noise_dbm=-90.0)
    back = load_radio_map(save_radio_map(rm, tmp_path / "m.npz"))
    assert back.shape == (2, 3) and back.tx_names == ["A"]
    assert np.array_equal(back.rss_dbm, rm.rss_dbm)
    np.savez(tmp_path / "x.npz", meta=np.array('{"format": "other", "version": 1}'))
    with pytest.raises(ValueError, match=r"x\.npz: format 'other'"):
        load_radio_map(tmp_path / "x.npz")


@pytest.mark.parametrize("kw, match", [
    ({"cell_size": 0.0}, r"cell_size: expected a positive number"),
    ({"tx_names": ["AP9"]}, r"unknown device 'AP9'"),
    ({"height": 7.0}, r"height: 7.0 m is outside the scene"),
    ({"samples_per_tx": 0}, r"samples_per_tx: expected >= 1"),
])
def test_bad_arguments_are_named(lab, kw, match):
    with pytest.raises(ValueError, match=match):
        compute_radio_map(lab, **kw)


@pytest.mark.slow
def test_map_matches_the_projects_grid_trace(lab):
    """The issue's check: map path gain against the incoherent sum of the grid trace's path
    powers at the grid points (isac_twin.raytrace.grid, chain reuse): median within 2 dB, with
    the default ray count (DEFAULT_SAMPLES)."""
    from isac_twin.raytrace.grid import trace_grid

    rm = compute_radio_map(lab, cell_size=0.25)
    g = trace_grid(lab, rm.tx_names, spacing=0.75, height=rm.height, progress=False, verify=0,
                   method="sbr")
    pw = (np.abs(g.arrays["a"]) ** 2 * g.arrays["valid"]).sum(-1)        # [N, S]
    diffs = []
    for i in np.flatnonzero(g.arrays["free"]):
        iy, ix = rm.cell_of(g.points[i, :2])
        for s in range(2):
            if rm.free[iy, ix] and np.isfinite(rm.path_gain_db[s, iy, ix]) and pw[i, s] > 0:
                diffs.append(rm.path_gain_db[s, iy, ix] - 10 * np.log10(pw[i, s]))
    assert len(diffs) > 40
    assert np.median(np.abs(diffs)) < 2.0
