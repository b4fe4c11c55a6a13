"""Polarized elements (V, H, VH, cross) on traced paths: the tracer's 2 x 2
transfer matrices (engine/raytrace/polarization.py) and the per-port
coefficients of engine/raytrace/antenna_patterns.py, checked against Sionna RT's own
``Paths.a`` / ``Paths.cfr`` traced with the same arrays, and against free
space (Friis, cross-polar isolation)."""

import numpy as np
import pytest

from isac_twin import LinkPaths
from isac_twin.phy import OFDMChannel, PlanarArray, ResourceGrid, baseband_gains
from isac_twin.raytrace.antenna_patterns import (
    AntennaPatterns,
    element_fields,
    num_ports,
    port_coefficients,
)
from isac_twin.raytrace.base import DevicePose
from isac_twin.scene.config import TracerConfig

FC = 2.4e9
LAM = 299_792_458.0 / FC
# [yaw, pitch, roll] (Sionna order): tilted arrays, so the local frame matters
TX_O, RX_O = [0.4, -0.3, 0.2], [2.5, 0.15, -0.3]
TX_P, RX_P = [0.6, 3.0, 2.0], [5.0, 2.2, 0.4]


def test_element_fields_follow_the_slant_angles():
    th, ph = np.array([np.pi / 2]), np.array([0.0])
    assert np.array_equal(element_fields("iso", "V", th, ph)[0], [[1.0, 0.0]])
    assert np.array_equal(element_fields("iso", "H", th, ph)[0], [[0.0, 1.0]])
    assert np.array_equal(element_fields("iso", "VH", th, ph)[0], [[1.0, 0.0], [0.0, 1.0]])
    s = np.sqrt(0.5)
    np.testing.assert_allclose(element_fields("dipole", "cross", th, ph)[0],
                               np.sqrt(1.5) * np.array([[s, -s], [s, s]]))
    assert [num_ports(p) for p in ("V", "H", "VH", "cross")] == [1, 1, 2, 2]
    with pytest.raises(ValueError, match="polarization: expected one of"):
        num_ports("X")


def _free_space_link(pol, tx_o=(0.0, 0.0, 0.0), rx_o=(0.0, 0.0, 0.0)) -> LinkPaths:
    """One LOS path along +x at distance 10 m with transfer matrix ``pol``."""
    return LinkPaths(tx="tx", rx="rx", tx_position=np.zeros(3),
                     rx_position=np.array([10.0, 0, 0]), tx_orientation=np.array(tx_o),
                     rx_orientation=np.array(rx_o), frequency_hz=FC,
                     a=np.array([pol[0, 0]]), tau=np.array([10.0 / 299_792_458.0]),
                     doppler=np.zeros(1), theta_t=np.array([np.pi / 2]), phi_t=np.zeros(1),
                     theta_r=np.array([np.pi / 2]), phi_r=np.array([np.pi]),
                     vertices=np.zeros((1, 1, 3)), interactions=np.zeros((1, 1), np.int32),
                     pol=np.asarray(pol)[None])


def test_link_without_transfer_matrix_refuses_h():
    lp = _free_space_link(np.eye(2))
    lp = LinkPaths(**{**lp.__dict__, "pol": None})
    assert port_coefficients(lp, ("iso", "V"), ("dipole", "V")).shape == (1, 1, 1)
    with pytest.raises(ValueError, match="link tx->rx: polarization 'V'/'H' needs"):
        port_coefficients(lp, ("iso", "V"), ("iso", "H"))


def test_port_pairs_in_eq4_and_the_snapshot_cfr():
    """[L, Pr, Pt] gains: antenna p * E + e is port p of element e (Sionna's
    order); cfr_at and OFDMChannel agree; one port pair reduces to [L] gains."""
    from isac_twin.phy import cfr_at
    from isac_twin.phy.channel import port_pair_gains

    rng = np.random.default_rng(3)
    n = 5
    b = rng.standard_normal((n, 2, 2)) + 1j * rng.standard_normal((n, 2, 2))
    a_rx = np.exp(1j * rng.uniform(0, 6, (n, 2)))
    a_tx = np.exp(1j * rng.uniform(0, 6, (n, 3)))
    g = port_pair_gains(b, a_rx, a_tx)
    assert g.shape == (n, 4, 6)
    assert g[2, 1 * 2 + 1, 0 * 3 + 2] == pytest.approx(b[2, 1, 0] * a_rx[2, 1] * a_tx[2, 2])
    np.testing.assert_allclose(port_pair_gains(b[:, :1, :1], a_rx, a_tx),
                               port_pair_gains(b[:, 0, 0], a_rx, a_tx))
    grid = ResourceGrid(16, 78125.0, 1, cyclic_prefix_samples=4)
    tau = rng.uniform(10e-9, 60e-9, n)
    ang = [rng.uniform(0.3, 2.8, n) for _ in range(4)]
    rx_arr, tx_arr = PlanarArray(1, 2), PlanarArray(3, 1)
    h = OFDMChannel(grid, rx_arr, tx_arr, dtype=np.complex128)(
        b, tau, np.zeros(n), *ang, times=[0.0])[0]
    h0 = cfr_at(b, tau, *ang, grid.subcarrier_frequencies, rx_arr, tx_arr)
    assert h.shape == h0.shape == (16, 4, 6)
    np.testing.assert_allclose(h, h0, atol=1e-12)
    with pytest.raises(ValueError, match=r"b must have shape \[L\] or \[L, Pr, Pt\]"):
        OFDMChannel(grid, rx_arr, tx_arr)(b[:, 0], tau, np.zeros(n), *ang)


rt = pytest.importorskip("sionna.rt")


def test_slants_are_sionnas_for_every_offered_polarization():
    from sionna.rt.antenna_pattern import polarization_registry

    from isac_twin.contract import schema
    from isac_twin.raytrace.antenna_patterns import SLANTS

    assert list(SLANTS) == list(schema.POLARIZATIONS)
    assert [p for p in SLANTS if num_ports(p) == 2] == list(schema.DUAL_POLARIZATIONS)
    for name, slants in SLANTS.items():
        np.testing.assert_allclose(slants, polarization_registry.get(name), atol=1e-7)


@pytest.fixture(scope="module")
def lab_xml():
    import isac_twin

    return str(isac_twin.bundled_scene_dir() / "scene.xml")


@pytest.fixture(scope="module")
def free_space():
    """An empty Sionna scene (LOS only)."""
    from isac_twin.raytrace.solver_core import SolverCore

    scene = rt.load_scene()
    scene.frequency = FC
    return scene, SolverCore(TracerConfig(max_depth=0))


def _our_link(sc, core, tx_p, rx_p, tx_o, rx_o) -> LinkPaths:
    from isac_twin.raytrace.raw import link_paths

    raw = core.solve_endpoints(sc, [tx_p], [rx_p], 10_000, source_orientations=[tx_o],
                               target_orientations=[rx_o])
    return link_paths(raw, 0, 0, "tx", "rx", DevicePose(tuple(tx_p), tuple(tx_o[::-1])),
                      DevicePose(tuple(rx_p), tuple(rx_o[::-1])), FC)


def test_free_space_dipoles_friis_and_cross_polar_isolation(free_space):
    """V-V short dipoles side by side: Friis with 1.76 dBi each; V -> H: ~0."""
    sc, core = free_space
    lp = _our_link(sc, core, [0.0, 0.0, 1.0], [10.0, 0.0, 1.0], [0, 0, 0], [0, 0, 0])
    assert lp.num_paths == 1 and lp.pol.shape == (1, 2, 2)
    friis = LAM / (4 * np.pi * 10.0)  # |a| of isotropic elements
    vv = port_coefficients(lp, ("dipole", "V"), ("dipole", "V"))[0, 0, 0]
    assert abs(vv) == pytest.approx(1.5 * friis, rel=1e-5)
    vh = port_coefficients(lp, ("dipole", "V"), ("dipole", "H"))[0, 0, 0]
    hh = port_coefficients(lp, ("dipole", "H"), ("dipole", "H"))[0, 0, 0]
    assert abs(vh) < 1e-6 * abs(vv)
    assert abs(hh) == pytest.approx(1.5 * friis, rel=1e-5)
    # a V transmitter rolled by 90 deg about the path axis is an H transmitter
    rolled = _our_link(sc, core, [0.0, 0.0, 1.0], [10.0, 0.0, 1.0], [0, 0, np.pi / 2],
                       [0, 0, 0])
    assert abs(port_coefficients(rolled, ("dipole", "V"), ("dipole", "V"))[0, 0, 0]) \
        < 1e-6 * abs(vv)
    assert abs(port_coefficients(rolled, ("dipole", "V"), ("dipole", "H"))[0, 0, 0]) \
        == pytest.approx(1.5 * friis, rel=1e-5)
    # reciprocity: the reversed link carries the transposed matrix
    back = lp.reversed()
    np.testing.assert_allclose(back.pol[0], lp.pol[0].T)


def _sionna(xml, tx, rx):
    """Sionna's own trace with arrays ``(rows, cols, pattern, polarization)``."""
    scene = rt.load_scene(xml, merge_shapes=False)
    scene.frequency = FC
    scene.tx_array = rt.PlanarArray(num_rows=tx[0], num_cols=tx[1], pattern=tx[2],
                                    polarization=tx[3])
    scene.rx_array = rt.PlanarArray(num_rows=rx[0], num_cols=rx[1], pattern=rx[2],
                                    polarization=rx[3])
    scene.add(rt.Transmitter("tx", position=TX_P, orientation=TX_O))
    scene.add(rt.Receiver("rx", position=RX_P, orientation=RX_O))
    return rt.PathSolver()(scene, max_depth=2, los=True, specular_reflection=True,
                           diffuse_reflection=False, refraction=True, synthetic_array=True,
                           seed=1)


@pytest.fixture(scope="module")
def lab_link(lab_xml):
    from isac_twin.raytrace.solver_core import SolverCore

    sc = rt.load_scene(lab_xml, merge_shapes=False)
    sc.frequency = FC
    core = SolverCore(TracerConfig(max_depth=2, samples_per_src=1_000_000, seed=1,
                                   deterministic=False))
    return _our_link(sc, core, TX_P, RX_P, TX_O, RX_O)


CASES = [(("tr38901", "VH"), ("dipole", "cross")), (("iso", "H"), ("hw_dipole", "H")),
         (("tr38901", "cross"), ("iso", "V"))]


@pytest.mark.slow
@pytest.mark.parametrize("et, er", CASES)
def test_polarized_ports_match_sionna_a_and_cfr(lab_xml, lab_link, et, er):
    lp = AntennaPatterns({"tx": et[0], "rx": er[0]}, {"tx": et[1], "rx": er[1]}).apply(lab_link)
    ports = lp.extra["a_ports"]
    pr, pt = num_ports(er[1]), num_ports(et[1])
    assert ports.shape == (lp.num_paths, pr, pt) and lp.num_paths >= 5
    # per-path coefficients: Sionna with the same 1x1 arrays
    p = _sionna(lab_xml, (1, 1, *et), (1, 1, *er))
    a_re, a_im = p.a
    a = (a_re.numpy() + 1j * a_im.numpy())[0, :, 0, :]  # [Pr, Pt, P]
    tau = p.tau.numpy()[0, 0]
    ok = tau >= 0
    o = np.argsort(tau[ok])
    ref = np.moveaxis(a[:, :, ok][:, :, o], -1, 0)
    mine = ports[np.argsort(lp.tau)]
    np.testing.assert_allclose(np.sort(tau[ok]), np.sort(lp.tau), rtol=1e-6)
    assert np.max(np.abs(mine - ref)) <= 1e-4 * np.max(np.abs(ref))
    # channel: eq. 4 vs Sionna's cfr with 2x2 / 1x2 arrays (ports doubled when dual)
    grid = ResourceGrid(64, 78125.0, 2, cyclic_prefix_samples=72)
    p = _sionna(lab_xml, (2, 2, *et), (1, 2, *er))
    freqs = rt.subcarrier_frequencies(grid.num_subcarriers, grid.subcarrier_spacing_hz)
    h_ref = p.cfr(freqs, sampling_frequency=1 / grid.symbol_duration_s,
                  num_time_steps=grid.num_symbols, normalize_delays=False,
                  out_type="numpy")[0, :, 0, :].transpose(2, 3, 0, 1)
    ch = OFDMChannel(grid, PlanarArray(1, 2), PlanarArray(2, 2), dtype=np.complex128)
    h = ch(baseband_gains(ports, lp.tau, FC), lp.tau, lp.doppler, lp.theta_r, lp.phi_r,
           lp.theta_t, lp.phi_t, rx_orientation=RX_O, tx_orientation=TX_O)
    assert h.shape == h_ref.shape == (2, 64, 2 * pr, 4 * pt)
    rel = np.linalg.norm(h - h_ref) / np.linalg.norm(h_ref)
    assert rel <= 1e-4, rel


@pytest.fixture
def room(tmp_path):
    from isac_twin.scene.synthetic import box_room

    return box_room(tmp_path / "room")


def _set_elements(folder, ap, robot):
    p = folder / "twin.toml"
    parts = p.read_text().split('pattern = "iso"\npolarization = "V"')
    assert len(parts) == 3
    p.write_text(parts[0] + f'pattern = "{ap[0]}"\npolarization = "{ap[1]}"' + parts[1]
                 + f'pattern = "{robot[0]}"\npolarization = "{robot[1]}"' + parts[2])


@pytest.mark.slow
def test_twin_step_with_dual_polarized_arrays(room, tmp_path):
    """VH at the AP (2x2 -> 8 ports), cross at the robot (1x2 -> 4 ports): the PHY
    gets the doubled port counts, the three PHY methods agree, the Csi-sized
    channel equals eq. 4 from the per-port coefficients."""
    import shutil

    from isac_twin import NetworkPHY, Twin

    other = tmp_path / "v"
    shutil.copytree(room, other)
    _set_elements(room, ("tr38901", "VH"), ("dipole", "cross"))
    twin = Twin.from_scene(room)
    res = twin.step()
    sig, link = res.signals[("AP1", "robot1")], res.links[("AP1", "robot1")]
    k_, n_ = twin.config.ofdm.num_symbols, twin.config.ofdm.num_subcarriers
    assert sig.h.shape == (k_, n_, 4, 8)
    assert link.paths.extra["a_ports"].shape == (link.paths.num_paths, 2, 2)
    assert np.isfinite(sig.rate_bps) and sig.rate_bps > 0
    paths = {("AP1", "robot1"): link.paths}
    rates = {m: NetworkPHY(twin.config, method=m)(paths)[("AP1", "robot1")].rate_bps
             for m in ("batched", "fast", "reference")}
    assert rates["fast"] == pytest.approx(rates["batched"], rel=1e-6)
    assert rates["reference"] == pytest.approx(rates["batched"], rel=1e-4)
    # single-polarized reference: V/V gives 4 x 2
    _set_elements(other, ("tr38901", "V"), ("dipole", "V"))
    sv = Twin.from_scene(other).step().signals[("AP1", "robot1")]
    assert sv.h.shape == (k_, n_, 2, 4)
    # the V ports of the dual arrays see the V/V channel: VH port 0 is V; the
    # robot's cross ports are (V -/+ H)/sqrt(2), so their sum / sqrt(2) is V
    hv = (sig.h[..., 0:2, 0:4] + sig.h[..., 2:4, 0:4]) / np.sqrt(2)
    np.testing.assert_allclose(hv, sv.h, atol=1e-4 * np.abs(sv.h).max())
