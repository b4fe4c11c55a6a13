"""Cross-check: eq. 4 synthesized by isac_twin.phy from our LinkPaths equals Sionna's
own ``Paths.cfr`` for the same scene with the real arrays (independent reference).

Setup: furnished room (cabinet, table), AP 4x8 (and 1x1) with a yawed and tilted
orientation, robot 1x2 moving (Doppler), K = 2 symbols, N = 1024 subcarriers.
Reference: a separate Sionna scene with ``tx_array``/``rx_array`` set to the real
planar arrays, ``PathSolver(deterministic=True)``, ``synthetic_array=True``,
``cfr(normalize_delays=False)``.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from isac_twin import device_poses, load_scene
from isac_twin.raytrace.base import DevicePose, sionna_orientation
from isac_twin.raytrace.sionna import SionnaTracer
from isac_twin.scene.synthetic import furnished_room

phy_channel = pytest.importorskip("isac_twin.phy.channel")
from isac_twin.phy.arrays import PlanarArray  # noqa: E402
from isac_twin.phy.ofdm import ResourceGrid  # noqa: E402

AP_ORIENT = (0.0, 0.3, 0.7)  # roll, pitch (down-tilt), yaw
ROBOT_VEL = (0.4, -0.25, 0.0)


def _sionna_reference(scene, poses, tx_shape, rx_shape, grid):
    import sionna.rt as rt
    from sionna.rt.utils import subcarrier_frequencies

    cfg = scene.config
    sc = rt.load_scene(str(cfg.scene.file), merge_shapes=False)
    sc.frequency = cfg.scene.frequency_hz
    sc.tx_array = rt.PlanarArray(num_rows=tx_shape[0], num_cols=tx_shape[1],
                                 vertical_spacing=0.5, horizontal_spacing=0.5,
                                 pattern="iso", polarization="V")
    sc.rx_array = rt.PlanarArray(num_rows=rx_shape[0], num_cols=rx_shape[1],
                                 vertical_spacing=0.5, horizontal_spacing=0.5,
                                 pattern="iso", polarization="V")
    ap, rob = poses["AP1"], poses["robot1"]
    sc.add(rt.Transmitter("AP1", position=ap.position,
                          orientation=sionna_orientation(ap.orientation)))
    sc.add(rt.Receiver("robot1", position=rob.position,
                       orientation=sionna_orientation(rob.orientation), velocity=rob.velocity))
    t = cfg.tracer
    paths = rt.PathSolver(deterministic=True)(
        sc, max_depth=t.max_depth, max_num_paths_per_src=t.max_num_paths_per_src,
        samples_per_src=t.samples_per_src, synthetic_array=True, los=t.los,
        specular_reflection=t.specular_reflection, diffuse_reflection=t.diffuse_reflection,
        refraction=t.refraction, diffraction=t.diffraction, seed=t.seed)
    f = subcarrier_frequencies(grid.num_subcarriers, grid.subcarrier_spacing_hz)
    h = paths.cfr(frequencies=f, sampling_frequency=1.0 / grid.symbol_duration_s,
                       num_time_steps=grid.num_symbols, normalize_delays=False,
                       out_type="numpy")
    h = np.asarray(h, np.complex128)  # [1, Nr, 1, Nt, K, N]
    return np.transpose(h[0, :, 0, :], (2, 3, 0, 1))  # [K, N, Nr, Nt]


@pytest.mark.slow
@pytest.mark.parametrize("tx_shape", [(4, 8), (1, 1)])
def test_phy_eq4_equals_sionna_cfr(tmp_path, tx_shape):
    scene = load_scene(furnished_room(tmp_path, ap_rows=tx_shape[0], ap_cols=tx_shape[1],
                                      links=[("AP1", "robot1")]))
    cfg = scene.config
    poses = device_poses(cfg)
    poses["AP1"] = DevicePose(poses["AP1"].position, orientation=AP_ORIENT)
    poses["robot1"] = DevicePose(poses["robot1"].position, orientation=(0.0, 0.0, 0.4),
                                 velocity=ROBOT_VEL)
    grid = ResourceGrid(cfg.ofdm.num_subcarriers, cfg.ofdm.subcarrier_spacing_hz, 2,
                        cfg.ofdm.cyclic_prefix_samples)

    # the direct tracer: Sionna's own sampling, so the reference holds the same
    # paths (chain reuse finds paths a 2e4-ray PathSolver misses)
    lp = SionnaTracer(replace(cfg.tracer, method="sbr"))(scene, poses)[("AP1", "robot1")]
    assert lp.num_paths > 10  # a multipath channel, not just LOS
    ch = phy_channel.OFDMChannel(grid, rx_array=PlanarArray(1, 2),
                                 tx_array=PlanarArray(*tx_shape), dtype=np.complex128)
    b = phy_channel.baseband_gains(lp.a, lp.tau, lp.frequency_hz)
    h = ch(b, lp.tau, lp.doppler, lp.theta_r, lp.phi_r, lp.theta_t, lp.phi_t,
           rx_orientation=sionna_orientation(lp.rx_orientation),
           tx_orientation=sionna_orientation(lp.tx_orientation))

    ref = _sionna_reference(scene, poses, tx_shape, (1, 2), grid)
    assert h.shape == ref.shape == (2, cfg.ofdm.num_subcarriers, 2, tx_shape[0] * tx_shape[1])
    err = (np.linalg.norm(h - ref, axis=(2, 3))
           / np.linalg.norm(ref, axis=(2, 3)))  # [K, N] per subcarrier and symbol
    print(f"\n{tx_shape} -> (1, 2): max relative error {err.max():.2e}, "
          f"median {np.median(err):.2e} over {err.size} (symbol, subcarrier) pairs")
    assert err.max() <= 1e-4
