"""isac_twin.calibration.forward_model: the model channel is Sionna RT's own PathSolver +
Paths.cfr (arrays turned, objects moved, several links), and an evaluation at new
poses compiles nothing."""

import numpy as np
import pytest

from isac_twin import CalibrationError, load_scene
from isac_twin.calibration import Calibrator, Measurements, Parameter, SolverSettings
from isac_twin.calibration.problem import power_db
from tests.engine.calibration.conftest import (
    OFFSETS,
    RX,
    SETTINGS,
    TX,
    arrays_case,
    cabinet_room,
)


def test_unknown_material_or_object_is_refused(tmp_path):
    meas = Measurements(TX, RX, OFFSETS, np.ones((4, 6)))
    scene = load_scene(cabinet_room(tmp_path / "twin"))
    with pytest.raises(CalibrationError, match="no radio material 'glass'"):
        Calibrator(scene, meas, [Parameter("permittivity", "glass")], SETTINGS)
    with pytest.raises(CalibrationError, match="no object 'Sofa'"):
        Calibrator(scene, meas, [Parameter("x", "Sofa")], SETTINGS)


@pytest.mark.slow
def test_model_channel_is_sionnas_paths_cfr(tmp_path):
    """The calibrator sums the channel itself (fixed-size buffers): it must equal
    Sionna's own PathSolver + Paths.cfr (synthetic arrays, orientations) at moved poses."""
    import sionna.rt as rt

    cal = arrays_case(tmp_path / "twin")
    n, k = len(RX), len(OFFSETS)
    for x in ([0.0, 0.0, 0.0], [0.3, 0.02, np.radians(2.0)]):
        _, _, model = cal.evaluate(cal.initial + np.array(x) * [cal.initial[0], 1, 1],
                                   grad=False)  # leaves the scene at x
        paths = rt.PathSolver()(cal.model.sc, max_depth=SETTINGS.max_depth,
                                samples_per_src=SETTINGS.samples_per_src, synthetic_array=True,
                                los=True, specular_reflection=True, diffuse_reflection=False,
                                refraction=True, diffraction=False, seed=SETTINGS.seed)
        h = np.asarray(paths.cfr(frequencies=OFFSETS, normalize_delays=False,
                                 out_type="numpy"))  # [N, Nr, 1, Nt, 1, K]
        ref = power_db(h.reshape(n, 2, 4, k).transpose(0, 3, 1, 2))
        assert np.abs(model - ref).max() < 1e-3  # dB


@pytest.mark.slow
def test_each_link_is_sionnas_paths_cfr_and_each_snapshot_counts_the_same(tmp_path):
    """Two links (transmitters) with other arrays: a 2x2 AP turned, and a one-antenna
    AP in the far corner seen at 3 of the positions. Each link's model is Sionna's own
    PathSolver + Paths.cfr of that transmitter to those receivers, with that link's
    arrays; the mismatch weighs every snapshot the same (the 2x2 link has 8 antenna
    pairs per snapshot, the other 2)."""
    import sionna.rt as rt

    n, k = len(RX), len(OFFSETS)
    ori = np.column_stack([np.linspace(0.3, 2.0, n), np.zeros(n), np.zeros(n)])
    rng = np.random.default_rng(3)
    a = Measurements(TX, RX, OFFSETS, rng.normal(size=(n, k, 2, 4)) * 1e-4,
                     tx_array=(2, 2, 0.5, 0.5), rx_array=(1, 2, 0.5, 0.5),
                     tx_orientation=(0.4, 0.1, 0.0), rx_orientations=ori)
    b = Measurements((4.5, 3.5, 2.0), RX[1:], OFFSETS, rng.normal(size=(n - 1, k, 2, 1)) * 1e-4,
                     rx_array=(1, 2, 0.5, 0.5), tx_orientation=(2.5, 0.0, 0.0),
                     rx_orientations=ori[1:])
    cal = Calibrator(load_scene(cabinet_room(tmp_path / "twin")), [a, b],
                     [Parameter("permittivity", "concrete"), Parameter("x", "Cabinet"),
                      Parameter("yaw", "Cabinet")], SETTINGS)
    f, _, models = cal.evaluate(cal.initial + np.array([0.3 * cal.initial[0], 0.02,
                                                        np.radians(2.0)]), grad=False)
    assert [m.shape for m in models] == [(n, k, 2, 4), (n - 1, k, 2, 1)]
    per_snapshot = [np.mean((mod - power_db(m.csi)) ** 2, axis=(1, 2, 3))
                    for mod, m in zip(models, (a, b))]
    assert f == pytest.approx(np.mean(np.concatenate(per_snapshot)), rel=1e-9)
    # Sionna traces every transmitter to every receiver with the scene's arrays: the
    # measured pairs, one link's arrays at a time
    rx_of = {0: np.arange(n), 1: n + np.arange(n - 1)}
    for j, (m, arrays) in enumerate(zip((a, b), (((2, 2), (1, 2)), ((1, 1), (1, 2))))):
        cal.model.sc.tx_array, cal.model.sc.rx_array = (
            rt.PlanarArray(num_rows=r, num_cols=c, vertical_spacing=0.5,
                           horizontal_spacing=0.5, pattern="iso", polarization="V")
            for r, c in arrays)
        paths = rt.PathSolver()(cal.model.sc, max_depth=SETTINGS.max_depth,
                                samples_per_src=SETTINGS.samples_per_src, synthetic_array=True,
                                los=True, specular_reflection=True, diffuse_reflection=False,
                                refraction=True, diffraction=False, seed=SETTINGS.seed)
        h = np.asarray(paths.cfr(frequencies=OFFSETS, normalize_delays=False,
                                 out_type="numpy"))  # [Nrx, Nr, T, Nt, 1, K]
        nt = arrays[0][0] * arrays[0][1]
        h = h[rx_of[j], :, j, :, 0, :]  # [N, Nr, Nt, K]
        ref = power_db(h.transpose(0, 3, 1, 2))
        assert np.abs(models[j] - ref).max() < 1e-3, j  # dB
        assert ref.shape == (len(m.rx_positions), k, 2, nt)
    with pytest.raises(CalibrationError, match="link 1's subcarriers differ"):
        Calibrator(load_scene(cabinet_room(tmp_path / "twin")),
                   [a, Measurements(TX, RX, OFFSETS + 1e6, np.ones((n, k)))],
                   [Parameter("x", "Cabinet")], SETTINGS)


@pytest.mark.slow
@pytest.mark.parametrize("chains", [False, True])
def test_traced_evaluations_at_new_poses_keep_their_buffers(chains):
    """The pattern search and the hop trace hundreds of poses without gradients; their
    kernels' widths must not follow the poses. On the lab (its 10 pieces of furniture
    fitted): with the candidate generator and with the chain model (chains enumerated
    again at new poses: another number of chains and pairs), every traced link keeps
    its padded buffer and the vertex inputs stay the arrays made at the start (before:
    made afresh from NumPy, they landed at other alignments and the vertex kernel was
    compiled twice per evaluation, 2 x 80 ms of 0.62 s). The kernels compiled are
    counted by ``bench/bench_calibration.py --compiles``: Dr.Jit's kernel history is
    the process's, and it held kernels of 1024 lanes when other processes loaded the
    cores."""
    from isac_twin.scene.bundled import bundled_scene_dir

    scene = load_scene(bundled_scene_dir("aces_lab"))
    objects = list(scene.config.room.furniture)
    rx = np.array([(2.0, 2.0, 0.3), (3.0, 1.5, 0.3), (4.0, 2.5, 0.3)])
    meas = Measurements((1.0, 1.0, 2.5), rx, OFFSETS, np.ones((len(rx), len(OFFSETS))))
    cal = Calibrator(scene, meas, [Parameter(k, o) for o in objects for k in ("x", "y", "yaw")],
                     SolverSettings(max_depth=2, samples_per_src=4000, seed=1, chains=chains))
    rng = np.random.default_rng(0)
    for _ in range(2):
        cal.refresh_chains()
        cal.evaluate(rng.normal(0.0, 0.01, len(cal.initial)), grad=False)
    cand = cal.model.candidates
    sizes = list(cand.buffer_sizes)

    def inputs():
        return {name: [id(a) for a in obj[3]] for name, obj in cal.model._objects.items()}

    before = inputs()
    for i in range(4):
        if i % 2:
            cal.refresh_chains()
        cal.evaluate(rng.normal(0.0, 0.01, len(cal.initial)), grad=False)
        assert cand.buffer_sizes == sizes and cal.buffer_regrows == 0
        assert inputs() == before
        if chains:
            assert all(len(c[1]) == size for c, size in zip(cand._chains, sizes)
                       if c is not None)
