"""isac_twin.calibration.calibrator: fit a material and an object's pose to channels of a changed room.

The "measurements" come from plain Sionna RT (its own PathSolver and
Paths.cfr, no calibration code) on a copy of the small synthetic room with
one known change: the walls' permittivity 30 % higher, or the metal cabinet's
mesh written 3 cm / 2 cm away. The fit must recover the change.
"""

import numpy as np
import pytest

from isac_twin import CalibrationError, load_scene
from isac_twin.calibration.calibrator import (
    Calibrator,
    Measurements,
    Parameter,
    SolverSettings,
    mismatch_db2,
)
from isac_twin.scene import synthetic as syn

FREQ = 2.4e9
OFFSETS = np.linspace(-40e6, 40e6, 6)  # 6 subcarriers over 80 MHz
TX = (0.5, 0.5, 2.0)
RX = np.array([(2.0, 2.0, 0.3), (1.2, 3.0, 0.5), (3.8, 1.2, 0.4), (2.6, 3.2, 0.3)])
SETTINGS = SolverSettings(max_depth=2, samples_per_src=4000, seed=1)
CABINET = ((3.0, 2.5, 0.0), (3.6, 3.0, 1.5))


def room(folder, cabinet_shift=(0.0, 0.0), cabinet_yaw=0.0):
    lo, hi = (np.array(c, float) for c in CABINET)
    d = np.array([*cabinet_shift, 0.0])
    objs = syn.room_objects((5.0, 4.0, 3.0),
                            {"Cabinet": (lo + d, hi + d, "metal", 0.002)})
    if cabinet_yaw:  # the mesh itself turned about its centre (not the calibration's code)
        cab = objs[-1]
        c = 0.5 * (lo + hi)
        cs, sn = np.cos(cabinet_yaw), np.sin(cabinet_yaw)
        x, y = cab.vertices[:, 0] - c[0], cab.vertices[:, 1] - c[1]
        cab.vertices = np.column_stack([c[0] + cs * x - sn * y, c[1] + sn * x + cs * y,
                                        cab.vertices[:, 2]])
    devs = [syn.SyntheticDevice("AP1", "access_point", "tx", TX),
            syn.SyntheticDevice("robot1", "robot", "rx", (2.0, 2.0, 0.0),
                                extra=dict(syn.ROBOT_EXTRA))]
    return syn.write_scene_folder(folder, objs, devs, [("AP1", "robot1")], frequency_hz=FREQ)


def measure(folder, permittivity_factor=1.0):
    """The reference channel [N, K]: Sionna's own solver on the changed room."""
    import mitsuba as mi
    import sionna.rt as rt

    sc = load_scene(folder).sionna
    if permittivity_factor != 1.0:
        for m in sc.radio_materials.values():
            if m.itu_type == "concrete":
                eps = float(m.relative_permittivity.numpy()[0])
                m.frequency_update_callback = None
                m.relative_permittivity = eps * permittivity_factor
    sc.tx_array = rt.PlanarArray(num_rows=1, num_cols=1, pattern="iso", polarization="V")
    sc.rx_array = rt.PlanarArray(num_rows=1, num_cols=1, pattern="iso", polarization="V")
    sc.add(rt.Transmitter("tx", position=mi.Point3f(*TX)))
    for i, p in enumerate(RX):
        sc.add(rt.Receiver(f"rx{i}", position=mi.Point3f(*map(float, p))))
    paths = rt.PathSolver()(sc, max_depth=2, samples_per_src=100000, synthetic_array=True,
                            los=True, specular_reflection=True, diffuse_reflection=False,
                            refraction=True, seed=7)
    h = paths.cfr(frequencies=OFFSETS, normalize_delays=False, out_type="numpy")
    return Measurements(TX, RX, OFFSETS, np.asarray(h).reshape(len(RX), len(OFFSETS)))


@pytest.mark.slow
def test_recovers_wall_permittivity(tmp_path):
    truth_factor = 1.3
    meas = measure(room(tmp_path / "real"), truth_factor)
    cal = Calibrator(load_scene(room(tmp_path / "twin")), meas,
                     [Parameter("permittivity", "concrete")], SETTINGS)
    eps0 = cal.initial[0]
    res = cal.fit(max_steps=20)
    print(res.to_json())
    assert res.converged, res.message
    assert res.gradient_initial[0] < 0  # walls too soft: raising eps lowers the mismatch
    assert abs(res.final[0] / (truth_factor * eps0) - 1) < 0.03
    assert res.mismatch_final < 0.05 * res.mismatch_initial
    assert res.residual_db.shape == (len(RX),)


@pytest.mark.slow
def test_recovers_cabinet_shift(tmp_path):
    shift = (0.03, -0.02)
    meas = measure(room(tmp_path / "real", shift))
    cal = Calibrator(load_scene(room(tmp_path / "twin")), meas,
                     [Parameter("x", "Cabinet"), Parameter("y", "Cabinet")], SETTINGS)
    res = cal.fit(max_steps=30)
    print(res.to_json())
    assert res.converged, res.message
    assert np.abs(res.final - shift).max() < 0.01  # within 1 cm
    assert res.mismatch_final < 0.1 * res.mismatch_initial


@pytest.mark.slow
def test_recovers_cabinet_yaw(tmp_path):
    yaw = np.radians(3.0)
    meas = measure(room(tmp_path / "real", cabinet_yaw=yaw))
    cal = Calibrator(load_scene(room(tmp_path / "twin")), meas,
                     [Parameter("yaw", "Cabinet")], SETTINGS)
    res = cal.fit(max_steps=20)
    print(res.to_json())
    assert res.converged, res.message
    assert abs(res.final[0] - yaw) < np.radians(0.5)
    assert res.mismatch_final < 0.1 * res.mismatch_initial


def test_mismatch_ignores_common_phase():
    rng = np.random.default_rng(0)
    h = rng.normal(size=(3, 5)) + 1j * rng.normal(size=(3, 5))
    phase = np.exp(1j * rng.uniform(0, 2 * np.pi, (3, 1)))
    assert mismatch_db2(h * phase, h) < 1e-20
    assert mismatch_db2(2 * h, h) == pytest.approx((20 * np.log10(2)) ** 2, rel=1e-6)


def test_unobserved_is_relative_to_the_best_seen():
    from isac_twin.calibration.calibrator import unobserved

    assert unobserved([3.0, -2e-7, 0.5], ["a", "b", "c"]) == ["b"]
    assert unobserved([0.0, 0.0], ["a", "b"]) == ["a", "b"]


def test_bad_input_is_refused(tmp_path):
    with pytest.raises(CalibrationError, match="kind 'height'"):
        Parameter("height", "Cabinet")
    with pytest.raises(CalibrationError, match="permittivity is >= 1"):
        Parameter("permittivity", "concrete", bounds=(0.5, 10))
    with pytest.raises(CalibrationError, match=r"csi must be \[N=4, K=6, Nr=1, Nt=1\]"):
        Measurements(TX, RX, OFFSETS, np.zeros((4, 5)))
    meas = Measurements(TX, RX, OFFSETS, np.ones((4, 6)))
    scene = load_scene(room(tmp_path / "twin"))
    with pytest.raises(CalibrationError, match="no radio material 'glass'"):
        Calibrator(scene, meas, [Parameter("permittivity", "glass")], SETTINGS)
    with pytest.raises(CalibrationError, match="no object 'Sofa'"):
        Calibrator(scene, meas, [Parameter("x", "Sofa")], SETTINGS)


def _arrays_case(folder, settings=SETTINGS):
    """4 positions, a 2x2 AP turned (0.4, 0.1, 0) rad, 1x2 receivers turned differently."""
    n = len(RX)
    ori = np.column_stack([np.linspace(0.3, 2.0, n), np.zeros(n), np.zeros(n)])
    meas = Measurements(TX, RX, OFFSETS, np.ones((n, len(OFFSETS), 2, 4)),
                        tx_array=(2, 2, 0.5, 0.5), rx_array=(1, 2, 0.5, 0.5),
                        tx_orientation=(0.4, 0.1, 0.0), rx_orientations=ori)
    return Calibrator(load_scene(room(folder)), meas,
                      [Parameter("permittivity", "concrete"), Parameter("x", "Cabinet"),
                       Parameter("yaw", "Cabinet")], settings)


def _sionna_db(sc, samples_per_src, max_depth=SETTINGS.max_depth):
    """Sionna's own PathSolver + Paths.cfr on the arrays case's scene, dB [N, K, 2, 4]."""
    import sionna.rt as rt

    from isac_twin.calibration.calibrator import power_db

    paths = rt.PathSolver()(sc, max_depth=max_depth, samples_per_src=samples_per_src,
                            synthetic_array=True, los=True, specular_reflection=True,
                            diffuse_reflection=False, refraction=True, diffraction=False,
                            seed=SETTINGS.seed)
    h = np.asarray(paths.cfr(frequencies=OFFSETS, normalize_delays=False, out_type="numpy"))
    return power_db(h.reshape(len(RX), 2, 4, len(OFFSETS)).transpose(0, 3, 1, 2))


@pytest.mark.slow
def test_chain_model_is_sionnas_paths_cfr_with_every_path(tmp_path):
    """With ``chains`` (the twin's chain tracer's way: every chain of the transmitter,
    tried to every receiver) the model is Sionna's PathSolver + Paths.cfr at 10^6 rays,
    where it finds every path of this room to depth 3, from 4,000 branching rays; at
    the same 4,000 rays Sionna's candidate generator misses some (the calibrator's
    other mode, which equals PathSolver at its own ray count). Chains enumerated at
    the start and kept over a 1 cm / 1 deg move stay within a few tenths of a dB."""
    import dataclasses

    settings = dataclasses.replace(SETTINGS, max_depth=3, chains=True)
    cal = _arrays_case(tmp_path / "twin", settings)
    moved = cal.initial + np.array([0.3 * cal.initial[0], 0.02, np.radians(2.0)])
    small = cal.initial + np.array([0.0, 0.01, np.radians(1.0)])
    cal.evaluate(cal.initial, grad=False)  # enumerates the chains at the scene's values
    _, _, kept = cal.evaluate(small, grad=False)  # and keeps them 1 cm / 1 deg later
    assert cal.chain_refreshes == 1
    cal.refresh_chains()
    _, _, fresh = cal.evaluate(small, grad=False)
    err = np.abs(kept - fresh)
    assert np.median(err) < 0.05 and err.max() < 1.0, (np.median(err), err.max())
    for x in (cal.initial, moved):
        cal.refresh_chains()
        _, _, model = cal.evaluate(x, grad=False)  # leaves the scene at x
        ref = _sionna_db(cal.sc, 1_000_000, 3)
        assert np.abs(model - ref).max() < 1e-3  # dB
        sampled = _sionna_db(cal.sc, 4000, 3)
    assert np.abs(sampled - ref).max() > 0.1  # what the sampled generator misses here
    assert cal.chain_refreshes == 4


@pytest.mark.slow
def test_model_channel_is_sionnas_paths_cfr(tmp_path):
    """The calibrator sums the channel itself (fixed-size buffers): it must equal
    Sionna's own PathSolver + Paths.cfr (synthetic arrays, orientations) at moved poses."""
    import sionna.rt as rt

    from isac_twin.calibration.calibrator import power_db

    cal = _arrays_case(tmp_path / "twin")
    n, k = len(RX), len(OFFSETS)
    for x in ([0.0, 0.0, 0.0], [0.3, 0.02, np.radians(2.0)]):
        _, _, model = cal.evaluate(cal.initial + np.array(x) * [cal.initial[0], 1, 1],
                                   grad=False)  # leaves the scene at x
        paths = rt.PathSolver()(cal.sc, max_depth=SETTINGS.max_depth,
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

    from isac_twin.calibration.calibrator import power_db

    n, k = len(RX), len(OFFSETS)
    ori = np.column_stack([np.linspace(0.3, 2.0, n), np.zeros(n), np.zeros(n)])
    rng = np.random.default_rng(3)
    a = Measurements(TX, RX, OFFSETS, rng.normal(size=(n, k, 2, 4)) * 1e-4,
                     tx_array=(2, 2, 0.5, 0.5), rx_array=(1, 2, 0.5, 0.5),
                     tx_orientation=(0.4, 0.1, 0.0), rx_orientations=ori)
    b = Measurements((4.5, 3.5, 2.0), RX[1:], OFFSETS, rng.normal(size=(n - 1, k, 2, 1)) * 1e-4,
                     rx_array=(1, 2, 0.5, 0.5), tx_orientation=(2.5, 0.0, 0.0),
                     rx_orientations=ori[1:])
    cal = Calibrator(load_scene(room(tmp_path / "twin")), [a, b],
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
        cal.sc.tx_array, cal.sc.rx_array = (
            rt.PlanarArray(num_rows=r, num_cols=c, vertical_spacing=0.5,
                           horizontal_spacing=0.5, pattern="iso", polarization="V")
            for r, c in arrays)
        paths = rt.PathSolver()(cal.sc, max_depth=SETTINGS.max_depth,
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
        Calibrator(load_scene(room(tmp_path / "twin")),
                   [a, Measurements(TX, RX, OFFSETS + 1e6, np.ones((n, k)))],
                   [Parameter("x", "Cabinet")], SETTINGS)


@pytest.mark.slow
def test_new_poses_do_not_recompile_the_evaluation(tmp_path):
    """A trace at new object poses finds another number of candidates; Sionna's kernels
    bake that number in, so the evaluation pads them to a fixed buffer: after the first
    gradient step no kernel as wide as the buffer is compiled again (before: ~12 per
    step, 13-16 s of LLVM on the lab)."""
    import drjit as dr

    cal = _arrays_case(tmp_path / "twin")
    cal.evaluate(cal.initial)  # warm-up: every kernel once
    cal.evaluate(cal.initial + np.array([0.0, 0.004, 0.0]))
    size = cal.buffer_size
    assert size > 0
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        for dx in (0.011, -0.027):
            dr.kernel_history()
            cal.evaluate(cal.initial + np.array([0.1 * cal.initial[0], dx, np.radians(dx * 50)]))
            wide = [h for h in dr.kernel_history() if h.get("type") == dr.KernelType.JIT
                    and not h.get("cache_hit") and h.get("size", 0) >= size]
            assert wide == [], [(h["size"], h.get("operation_count")) for h in wide]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert cal.buffer_size == size and cal.buffer_regrows == 0


@pytest.mark.slow
@pytest.mark.parametrize("chains", [False, True])
def test_traced_evaluations_at_new_poses_compile_nothing(tmp_path, chains):
    """The pattern search and the hop trace hundreds of poses without gradients; none
    may compile a kernel after the first. On the lab (its 10 pieces of furniture
    fitted) the objects' vertex kernel did, twice per evaluation: its inputs were made
    afresh from NumPy, landed at other memory alignments, and Dr.Jit keys a kernel on
    its inputs' alignment (2 x 80 ms of a 0.62 s evaluation). With the chain model,
    chains enumerated again at new poses (another number of chains and pairs) compile
    nothing either. In its own process: Dr.Jit's kernel history is the process's, and
    in the test session it twice held 3 kernels of 1024 lanes when other processes
    loaded the cores (another test's threads finishing late, a suspect)."""
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", _COMPILE_CHECK, str(chains)],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0 and out.stdout.strip().endswith("ok"), (
        out.stdout[-2000:] + out.stderr[-3000:])


_COMPILE_CHECK = """
import sys
import numpy as np
import isac_twin  # sets DRJIT_LIBLLVM_PATH before Dr.Jit loads
import drjit as dr
from isac_twin.calibration.calibrator import Calibrator, Measurements, Parameter, SolverSettings
from isac_twin.scene.bundled import bundled_scene_dir
from isac_twin.scene.twin_scene import load_scene

OFFSETS = np.linspace(-40e6, 40e6, 6)
chains = sys.argv[1] == "True"
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
dr.set_flag(dr.JitFlag.KernelHistory, True)
for i in range(4):
    if i % 2:
        cal.refresh_chains()
    dr.kernel_history()
    cal.evaluate(rng.normal(0.0, 0.01, len(cal.initial)), grad=False)
    built = [h for h in dr.kernel_history() if h.get("type") == dr.KernelType.JIT
             and not h.get("cache_hit")]
    assert built == [], [(h["size"], h.get("operation_count")) for h in built]
print("ok")
"""


@pytest.mark.slow
def test_frozen_candidates_are_traced_at_the_current_geometry(tmp_path):
    """A trust-box round keeps the candidate chains of its first trace; the image method
    still runs on the moved mesh: 1 cm and 1 deg later the channel is close to Sionna's
    own PathSolver + Paths.cfr there, not the start's (the kept chains' reflection
    points stay where the first trace found them: an approximation of second order in
    the move, up to a few tenths of a dB in a fade)."""
    import sionna.rt as rt

    from isac_twin.calibration.calibrator import power_db

    cal = _arrays_case(tmp_path / "twin")
    cal.freeze_candidates = True
    _, _, at_start = cal.evaluate(cal.initial, grad=False)
    x = cal.initial + np.array([0.0, 0.01, np.radians(1.0)])
    _, _, moved = cal.evaluate(x, grad=False)
    paths = rt.PathSolver()(cal.sc, max_depth=SETTINGS.max_depth,
                            samples_per_src=SETTINGS.samples_per_src, synthetic_array=True,
                            los=True, specular_reflection=True, diffuse_reflection=False,
                            refraction=True, diffraction=False, seed=SETTINGS.seed)
    h = np.asarray(paths.cfr(frequencies=OFFSETS, normalize_delays=False, out_type="numpy"))
    ref = power_db(h.reshape(len(RX), 2, 4, len(OFFSETS)).transpose(0, 3, 1, 2))
    err = np.abs(moved - ref)
    assert np.abs(moved - at_start).max() > 1.0  # the move changes the channel (dB)
    assert np.median(err) < 0.02 and err.max() < 0.5, (np.median(err), err.max())


def _determinism_case(folder, calibrator=Calibrator):
    """The cabinet room seen from 4 positions with 10^5 rays: enough that the candidate
    generator's two threads race for the same chain of planes (each wall is two
    coplanar triangles)."""
    meas = Measurements(TX, RX, OFFSETS, np.ones((len(RX), len(OFFSETS))))
    return calibrator(load_scene(room(folder)), meas,
                      [Parameter("permittivity", "concrete"), Parameter("x", "Cabinet"),
                       Parameter("yaw", "Cabinet")],
                      SolverSettings(max_depth=3, samples_per_src=100000, seed=1))


class _ThreadSpy:
    """Wraps a candidate generator; records Dr.Jit's thread count at each call."""

    def __init__(self, generator):
        self.generator, self.threads = generator, []

    def __call__(self, *args, **kwargs):
        import drjit as dr

        self.threads.append(dr.thread_count())
        return self.generator(*args, **kwargs)


@pytest.mark.slow
@pytest.mark.parametrize("deterministic", [True, False])
def test_repeated_evaluations_are_identical(tmp_path, monkeypatch, deterministic):
    """Fresh candidates at the same values give the same mismatch and the same
    gradient, to the last bit, with the candidate generator on every thread (Sionna's
    deterministic generator; the default one, used above ``DETERMINISTIC_LANES``, on
    one thread), the backward pass on one thread and the channel summed in float64.
    Before, the kept triangle of a coplanar face depended on thread timing and the line
    search drifted apart; then the backward pass's float32 atomics still moved the
    gradient's last bits, and fits of the same lap ended in different places; the
    generator then ran on one thread (0.33 s of a 0.42 s traced evaluation on the lab,
    against 0.14 s on two)."""
    import drjit as dr

    import isac_twin.calibration.calibrator as calibration

    if not deterministic:
        monkeypatch.setattr(calibration, "DETERMINISTIC_LANES", 1000)
    threads = dr.thread_count()
    dr.set_thread_count(2)
    try:
        cal = _determinism_case(tmp_path / "twin")
        assert cal.deterministic_candidates is deterministic
        spy = cal._solver._candidate_generator = _ThreadSpy(cal._solver._candidate_generator)
        x = cal.initial + np.array([0.0, 0.004, np.radians(0.7)])
        runs = [cal.evaluate(x) for _ in range(6)]
    finally:
        dr.set_thread_count(threads)
    assert spy.threads == [2 if deterministic else 1] * 6
    assert len({r[0] for r in runs}) == 1, [r[0] for r in runs]
    g = np.array([r[1] for r in runs])
    assert np.all(g == g[0]), g


@pytest.mark.slow
def test_polish_recovers_yaw_where_the_mismatch_jumps(tmp_path):
    """The pattern search on traced values reaches the cabinet's true yaw (3 deg) from
    1.2 deg off, stepping 0.5 -> 0.0625 deg (to within its last step)."""
    yaw = np.radians(3.0)
    meas = measure(room(tmp_path / "real", cabinet_yaw=yaw))
    cal = Calibrator(load_scene(room(tmp_path / "twin")), meas,
                     [Parameter("x", "Cabinet"), Parameter("yaw", "Cabinet")], SETTINGS)
    start = np.array([0.0, yaw - np.radians(1.2)])
    f0 = cal.evaluate(start, grad=False)[0]
    x, f, n = cal.polish(start, [1])
    assert x[0] == 0.0  # not free
    assert abs(np.degrees(x[1] - yaw)) <= 0.0625 + 1e-9, np.degrees(x[1])
    assert f < 0.5 * f0 and n <= 400
    assert cal.polish_trials["Cabinet.yaw"]  # the first step's trials, for the report
    with pytest.raises(CalibrationError, match="free"):
        cal.polish(start, [5])


@pytest.mark.slow
def test_hop_leaves_the_basin_the_polish_ends_in(tmp_path, monkeypatch):
    """The cabinet moved 7 cm in x. The magnitude mismatch repeats every ~10 cm of x
    here (its face seen obliquely: period wavelength / (2 cos theta)), so the polish
    from the twin's pose ends in the basin at -2.8 cm (4.8 dB^2), a period off. The hop
    scans the next basins and searches the lower one, the truth's. (Out to one
    wavelength here; the default ring, 0.3-0.6 wavelength, is for faces seen near
    normal incidence, as the lab's tables.)"""
    shift = 0.07
    meas = measure(room(tmp_path / "real", (shift, 0.0)))
    cal = Calibrator(load_scene(room(tmp_path / "twin")), meas,
                     [Parameter("x", "Cabinet"), Parameter("yaw", "Cabinet")], SETTINGS)
    x, f, _ = cal.polish(np.zeros(2), [0])
    assert abs(x[0] - shift) > 0.05 and f > 1.0, (x, f)  # a period off
    xh, fh, n = cal.hop(x, [0, 1], span=(0.3, 1.0))
    # in the truth's basin; its bottom is ragged here (a path comes and goes between
    # 7.05 and 7.2 cm: 0.6, 15.4, 2.2 dB^2), so the search ends 0.27 cm off
    assert abs(xh[0] - shift) <= 0.005 and fh < 0.05 * f, (xh, fh)
    # the yaw is scanned too (turns moving the cabinet's corners as far), and kept: the
    # truth's yaw is the start's
    assert list(cal.hop_report) == ["Cabinet.x", "Cabinet.yaw"]
    assert cal.hop_report["Cabinet.x"]["kept"] and not cal.hop_report["Cabinet.yaw"]["kept"]
    assert xh[1] == x[1]
    radius = np.hypot(0.3, 0.25)  # the cabinet's half-diagonal, m
    yaw_shifts = np.abs(cal.hop_report["Cabinet.yaw"]["shifts_m"]) * radius  # m at a corner
    x_shifts = np.abs(cal.hop_report["Cabinet.x"]["shifts_m"])
    step = 299792458.0 / FREQ / 12  # HOP_PER_WAVELENGTH
    # x from 0.3 wavelength on; a yaw's ring from one step on (turns have nearer basins)
    assert x_shifts[x_shifts > 0].min() == pytest.approx(4 * step, rel=1e-6)
    assert yaw_shifts[yaw_shifts > 0].min() == pytest.approx(step, rel=1e-6)
    assert cal.hop_report["Cabinet.x"]["mismatch_before_db2"] == pytest.approx(f)
    assert n > len(cal.hop_report["Cabinet.x"]["shifts_m"])  # the scan, then the search
    with pytest.raises(CalibrationError, match="free"):
        cal.hop(x, [7])
    # a coordinate the start gradient did not see must gain HOP_GAIN_UNSEEN: the same
    # search, not kept when that asks more than it gains
    import isac_twin.calibration.calibrator as calibration

    monkeypatch.setattr(calibration, "HOP_GAIN_UNSEEN", 1.0)
    xu, fu, _ = cal.hop(x, [0], unseen=[0], span=(0.3, 1.0))
    assert not cal.hop_report["Cabinet.x"]["kept"] and np.array_equal(xu, x) and fu == f
    assert cal.hop_report["Cabinet.x"]["mismatch_after_db2"] == pytest.approx(fh)
    with pytest.raises(CalibrationError, match="unseen"):
        cal.hop(x, [0], unseen=[5])

