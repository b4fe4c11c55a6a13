"""engine/raytrace/antenna_patterns.py: element patterns applied to iso-traced paths against
Sionna RT's own ``Paths.a`` and ``Paths.cfr`` traced with the same arrays."""

import numpy as np
import pytest

from isac_twin import LinkPaths
from isac_twin.phy import OFDMChannel, PlanarArray, ResourceGrid, baseband_gains
from isac_twin.raytrace.antenna_patterns import PATTERNS, AntennaPatterns, pattern_gains

FC = 2.4e9
# [yaw, pitch, roll] (Sionna order): tilted arrays, so the local frame matters
TX_O, RX_O = [0.4, -0.3, 0.2], [2.5, 0.15, -0.3]
TX_P, RX_P = [0.6, 3.0, 2.0], [5.0, 2.2, 0.4]


def test_pattern_peaks_and_nulls():
    th = np.array([np.pi / 2, 0.0, np.pi / 2])
    ph = np.array([0.0, 0.0, np.pi])
    assert PATTERNS["tr38901"](th, ph)[0] == pytest.approx(np.sqrt(10 ** 0.8))  # 8 dBi
    assert PATTERNS["tr38901"](th, ph)[2] == pytest.approx(np.sqrt(10 ** -2.2))  # 30 dB down
    assert PATTERNS["dipole"](th, ph)[1] == 0.0 and PATTERNS["hw_dipole"](th, ph)[1] == 0.0
    # an array yawed by +90 deg looks along +y: its boresight gain is towards +y
    g = pattern_gains("tr38901", [np.pi / 2, np.pi / 2], [np.pi / 2, 0.0], [np.pi / 2, 0, 0])
    assert g[0] == pytest.approx(np.sqrt(10 ** 0.8)) and g[1] < g[0] / 10


rt = pytest.importorskip("sionna.rt")


@pytest.fixture(scope="module")
def lab_scene():
    import isac_twin

    return str(isac_twin.bundled_scene_dir() / "scene.xml")


def _trace(xml, tx_arr, rx_arr):
    scene = rt.load_scene(xml, merge_shapes=False)
    scene.frequency = FC
    scene.tx_array = rt.PlanarArray(num_rows=tx_arr[0], num_cols=tx_arr[1], pattern=tx_arr[2],
                                    polarization="V")
    scene.rx_array = rt.PlanarArray(num_rows=rx_arr[0], num_cols=rx_arr[1], pattern=rx_arr[2],
                                    polarization="V")
    scene.add(rt.Transmitter("tx", position=TX_P, orientation=TX_O))
    scene.add(rt.Receiver("rx", position=RX_P, orientation=RX_O))
    return rt.PathSolver()(scene, max_depth=2, los=True, specular_reflection=True,
                           diffuse_reflection=False, refraction=True, synthetic_array=True,
                           seed=1)


def _link_paths(p) -> LinkPaths:
    a_re, a_im = p.a
    a = (a_re.numpy() + 1j * a_im.numpy())[0, 0, 0, 0].astype(complex)
    tau = p.tau.numpy()[0, 0].astype(float)
    ok = tau >= 0
    f = {k: getattr(p, k).numpy()[0, 0][ok].astype(float)
         for k in ("theta_t", "phi_t", "theta_r", "phi_r")}
    n = int(ok.sum())
    # the solver's path order varies between runs: sort by delay, then angles
    o = np.lexsort((f["phi_r"], f["theta_r"], f["phi_t"], f["theta_t"], tau[ok]))
    f = {k: v[o] for k, v in f.items()}
    return LinkPaths(tx="tx", rx="rx", tx_position=np.array(TX_P), rx_position=np.array(RX_P),
                     tx_orientation=np.array(TX_O[::-1]), rx_orientation=np.array(RX_O[::-1]),
                     frequency_hz=FC, a=a[ok][o], tau=tau[ok][o], doppler=np.zeros(n), **f,
                     vertices=np.zeros((n, 1, 3)), interactions=np.zeros((n, 1), np.int32))


@pytest.fixture(scope="module")
def iso_paths(lab_scene):
    return _link_paths(_trace(lab_scene, (1, 1, "iso"), (1, 1, "iso")))


@pytest.mark.slow
@pytest.mark.parametrize("pt, pr", [("tr38901", "dipole"), ("hw_dipole", "tr38901"),
                                    ("tr38901", "iso")])
def test_patterned_paths_match_sionna_a_and_cfr(lab_scene, iso_paths, pt, pr):
    assert iso_paths.num_paths >= 5
    lp = AntennaPatterns({"tx": pt, "rx": pr}).apply(iso_paths)
    # path coefficients: Sionna traced with the patterns on 1x1 arrays
    ref = _link_paths(_trace(lab_scene, (1, 1, pt), (1, 1, pr)))
    np.testing.assert_allclose(ref.tau, lp.tau, rtol=1e-6)  # float32 solver, same paths
    assert np.max(np.abs(lp.a - ref.a)) <= 1e-4 * np.max(np.abs(ref.a))
    assert not np.allclose(np.abs(lp.a), np.abs(iso_paths.a), rtol=0.1)  # patterns matter
    # channel: eq. 4 with iso-geometry arrays vs Sionna's cfr with 4x8 / 1x2 arrays
    grid = ResourceGrid(64, 78125.0, 2, cyclic_prefix_samples=72)
    p = _trace(lab_scene, (4, 8, pt), (1, 2, pr))
    freqs = rt.subcarrier_frequencies(grid.num_subcarriers, grid.subcarrier_spacing_hz)
    h_ref = p.cfr(freqs, sampling_frequency=1 / grid.symbol_duration_s,
                  num_time_steps=grid.num_symbols, normalize_delays=False,
                  out_type="numpy")[0, :, 0, :].transpose(2, 3, 0, 1)
    ch = OFDMChannel(grid, PlanarArray(1, 2), PlanarArray(4, 8), dtype=np.complex128)
    h = ch(baseband_gains(lp.a, lp.tau, FC), lp.tau, lp.doppler, lp.theta_r, lp.phi_r,
           lp.theta_t, lp.phi_t, rx_orientation=RX_O, tx_orientation=TX_O)
    rel = np.linalg.norm(h - h_ref) / np.linalg.norm(h_ref)
    assert rel <= 1e-4, rel


@pytest.fixture
def room(tmp_path):
    from isac_twin.scene.synthetic import box_room

    return box_room(tmp_path / "room")


def _set_pattern(folder, pattern, polarization="V"):
    p = folder / "twin.toml"
    text = p.read_text()
    p.write_text(text.replace('pattern = "iso"\npolarization = "V"',
                              f'pattern = "{pattern}"\npolarization = "{polarization}"', 1))


@pytest.mark.slow
def test_directional_ap_changes_traced_gains_and_rates(room, tmp_path):
    import shutil

    from isac_twin import Twin

    iso = Twin.from_scene(room).step()
    other = tmp_path / "tr"
    shutil.copytree(room, other)
    _set_pattern(other, "tr38901")
    tr = Twin.from_scene(other).step()
    li, lt = iso.links[("AP1", "robot1")], tr.links[("AP1", "robot1")]
    # LOS: the gain changes by the TR 38.901 pattern towards the robot's antenna
    # (AP1 at (1, 1, 2) faces +x; departure azimuth / elevation from geometry)
    d = lt.paths.rx_position - lt.paths.tx_position
    az, el = np.arctan2(d[1], d[0]), np.arcsin(d[2] / np.linalg.norm(d))
    a_db = 8 - min(12 * (el / np.deg2rad(65)) ** 2 + 12 * (az / np.deg2rad(65)) ** 2, 30)
    ratio_db = 20 * np.log10(abs(lt.paths.a[0]) / abs(li.paths.a[0]))
    assert ratio_db == pytest.approx(a_db, abs=1e-4)  # float32 traced angles
    assert np.allclose(lt.paths.extra["a_iso"], li.paths.a)
    assert lt.snr_db != pytest.approx(li.snr_db, abs=0.1)
    assert lt.rate_bps != pytest.approx(li.rate_bps, rel=1e-3)


def test_dual_polarization_loads_and_what_is_not_modelled_is_refused_in_one_line(room,
                                                                                capsys):
    from isac_twin.cli import main

    _set_pattern(room, "dipole", "VH")
    assert main(["info", str(room)]) == 0
    assert "2x2 VH (8 ports)" in capsys.readouterr().out
    # a path grid stores no transfer matrices: refused at load, one line
    p = room / "twin.toml"
    p.write_text(p.read_text() + '\n[tracer]\nbackend = "grid"\ngrid_file = "g.npz"\n')
    assert main(["info", str(room)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "devices[0] (AP1).array.polarization: 'VH' needs the paths' polarization" in err


@pytest.mark.slow
def test_trace_cli_prints_patterned_gains(room, capsys):
    """`isac-twin trace` shows the directional AP's gain, not the isotropic one."""
    from isac_twin.cli import main

    def total_db():
        assert main(["trace", str(room)]) == 0
        row = next(x for x in capsys.readouterr().out.splitlines() if "AP1 -> robot1" in x)
        return float(row.split()[-1])

    iso = total_db()
    _set_pattern(room, "tr38901")
    assert total_db() - iso > 1.0  # the tr38901 main lobe faces the robot
