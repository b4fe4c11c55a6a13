"""Cross-check of isac_twin.phy.channel against Sionna RT's own Paths.cfr().

Traces a bundled Sionna scene twice -- with single-element arrays (for the
path gains at the array centres) and with 4x8 / 1x2 synthetic arrays (for
the reference) -- and synthesises eq. 4 from the first trace. Only the test
imports Sionna; isac_twin.phy never does.
"""

import numpy as np
import pytest

rt = pytest.importorskip("sionna.rt")

from isac_twin.phy import OFDMChannel, PlanarArray, ResourceGrid, baseband_gains  # noqa: E402

pytestmark = pytest.mark.slow

FC = 2.4e9
TX_O, RX_O = [0.4, -0.2, 0.1], [2.5, 0.1, -0.3]  # [yaw, pitch, roll]


def _trace(rows_t, cols_t, rows_r, cols_r):
    scene = rt.load_scene(rt.scene.simple_street_canyon, merge_shapes=False)
    scene.frequency = FC
    scene.tx_array = rt.PlanarArray(num_rows=rows_t, num_cols=cols_t, vertical_spacing=0.5,
                                    horizontal_spacing=0.5, pattern="iso", polarization="V")
    scene.rx_array = rt.PlanarArray(num_rows=rows_r, num_cols=cols_r, vertical_spacing=0.5,
                                    horizontal_spacing=0.5, pattern="iso", polarization="V")
    scene.add(rt.Transmitter("tx", position=[-30, 2, 12], orientation=TX_O, velocity=[3, 1, 0]))
    scene.add(rt.Receiver("rx", position=[25, -3, 1.5], orientation=RX_O, velocity=[-1, 4, 0]))
    return rt.PathSolver()(scene, max_depth=2, los=True, specular_reflection=True,
                           diffuse_reflection=False, refraction=False, synthetic_array=True,
                           seed=1)


def test_eq4_matches_sionna_cfr_with_synthetic_arrays():
    grid = ResourceGrid(128, 78125.0, 4, cyclic_prefix_samples=72)
    ref_paths = _trace(4, 8, 1, 2)
    freqs = rt.subcarrier_frequencies(grid.num_subcarriers, grid.subcarrier_spacing_hz)
    h_ref = ref_paths.cfr(freqs, sampling_frequency=1 / grid.symbol_duration_s,
                          num_time_steps=grid.num_symbols, normalize_delays=False,
                          out_type="numpy")[0, :, 0, :].transpose(2, 3, 0, 1)
    p = _trace(1, 1, 1, 1)
    a_re, a_im = p.a
    a = (a_re.numpy() + 1j * a_im.numpy())[0, 0, 0, 0]
    tau = p.tau.numpy()[0, 0]
    ok = tau >= 0
    assert ok.sum() >= 3
    ang = [x.numpy()[0, 0][ok] for x in (p.theta_r, p.phi_r, p.theta_t, p.phi_t)]
    ch = OFDMChannel(grid, PlanarArray(1, 2), PlanarArray(4, 8))
    h = ch(baseband_gains(a[ok], tau[ok], FC), tau[ok], p.doppler.numpy()[0, 0][ok], *ang,
           rx_orientation=RX_O, tx_orientation=TX_O)
    assert h.shape == h_ref.shape == (4, 128, 2, 32)
    nmse = np.sum(np.abs(h - h_ref) ** 2) / np.sum(np.abs(h_ref) ** 2)
    assert nmse < 1e-6  # Sionna computes in float32 (phase 2 pi f_c tau ~ 3000 rad)
    assert np.max(np.abs(h - h_ref)) < 1e-3 * np.max(np.abs(h_ref))
