"""isac_twin.calibration.candidates: the candidates of the model's traces. With chains,
the model has every path Sionna finds at 10^6 rays; candidates kept over a move are
traced at the current geometry; fresh candidates at the same values give the same
mismatch and gradient to the bit; a fixed-size buffer keeps new poses from compiling
the evaluation anew."""

import numpy as np
import pytest

from isac_twin import load_scene
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


def _sionna_db(sc, samples_per_src, max_depth=SETTINGS.max_depth):
    """Sionna's own PathSolver + Paths.cfr on the arrays case's scene, dB [N, K, 2, 4]."""
    import sionna.rt as rt

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
    cal = arrays_case(tmp_path / "twin", settings)
    moved = cal.initial + np.array([0.3 * cal.initial[0], 0.02, np.radians(2.0)])
    small = cal.initial + np.array([0.0, 0.01, np.radians(1.0)])
    cal.evaluate(cal.initial, grad=False)  # enumerates the chains at the scene's values
    _, _, kept = cal.evaluate(small, grad=False)  # and keeps them 1 cm / 1 deg later
    assert cal.model.candidates.chain_refreshes == 1
    cal.refresh_chains()
    _, _, fresh = cal.evaluate(small, grad=False)
    err = np.abs(kept - fresh)
    assert np.median(err) < 0.05 and err.max() < 1.0, (np.median(err), err.max())
    for x in (cal.initial, moved):
        cal.refresh_chains()
        _, _, model = cal.evaluate(x, grad=False)  # leaves the scene at x
        ref = _sionna_db(cal.model.sc, 1_000_000, 3)
        assert np.abs(model - ref).max() < 1e-3  # dB
        sampled = _sionna_db(cal.model.sc, 4000, 3)
    assert np.abs(sampled - ref).max() > 0.1  # what the sampled generator misses here
    assert cal.model.candidates.chain_refreshes == 4


def _inputs(cal) -> dict:
    """The identities of the objects' vertex arrays the evaluation reads."""
    return {name: [id(a) for a in obj[3]] for name, obj in cal.model._objects.items()}


@pytest.mark.slow
def test_new_poses_keep_the_evaluations_buffers_and_inputs(tmp_path):
    """A trace at new object poses finds another number of candidates; Sionna's kernels
    bake that number in, so the evaluation pads them to a fixed buffer, and the
    objects' vertices are Dr.Jit arrays made once (arrays made afresh from NumPy
    landed at other alignments, and Dr.Jit keys a kernel on them): after the first
    gradient step no buffer grows and no input is made anew (before: ~12 kernels
    compiled per step, 13-16 s of LLVM on the lab). The kernels compiled per
    evaluation are counted by ``bench/bench_calibration.py --compiles``, not here:
    Dr.Jit's kernel history is the whole process's, and what its cache finds depends
    on the allocator's state, which other work changes."""
    cal = arrays_case(tmp_path / "twin")
    cal.evaluate(cal.initial)  # warm-up: every kernel once
    cal.evaluate(cal.initial + np.array([0.0, 0.004, 0.0]))
    sizes = list(cal.model.candidates.buffer_sizes)
    assert cal.buffer_size > 0
    inputs = _inputs(cal)
    for dx in (0.011, -0.027):
        cal.evaluate(cal.initial + np.array([0.1 * cal.initial[0], dx, np.radians(dx * 50)]))
        assert cal.model.candidates.buffer_sizes == sizes and cal.buffer_regrows == 0
        assert _inputs(cal) == inputs


@pytest.mark.slow
def test_frozen_candidates_are_traced_at_the_current_geometry(tmp_path):
    """A trust-box round keeps the candidate chains of its first trace; the image method
    still runs on the moved mesh: 1 cm and 1 deg later the channel is close to Sionna's
    own PathSolver + Paths.cfr there, not the start's (the kept chains' reflection
    points stay where the first trace found them: an approximation of second order in
    the move, up to a few tenths of a dB in a fade)."""
    import sionna.rt as rt

    cal = arrays_case(tmp_path / "twin")
    cal.model.candidates.freeze = True
    _, _, at_start = cal.evaluate(cal.initial, grad=False)
    x = cal.initial + np.array([0.0, 0.01, np.radians(1.0)])
    _, _, moved = cal.evaluate(x, grad=False)
    paths = rt.PathSolver()(cal.model.sc, max_depth=SETTINGS.max_depth,
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
    return calibrator(load_scene(cabinet_room(folder)), meas,
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

    import isac_twin.calibration.candidates as candidates

    if not deterministic:
        monkeypatch.setattr(candidates, "DETERMINISTIC_LANES", 1000)
    threads = dr.thread_count()
    dr.set_thread_count(2)
    try:
        cal = _determinism_case(tmp_path / "twin")
        assert cal.model.candidates.deterministic is deterministic
        solver = cal.model.candidates.solver
        spy = solver._candidate_generator = _ThreadSpy(solver._candidate_generator)
        x = cal.initial + np.array([0.0, 0.004, np.radians(0.7)])
        runs = [cal.evaluate(x) for _ in range(6)]
    finally:
        dr.set_thread_count(threads)
    assert spy.threads == [2 if deterministic else 1] * 6
    assert len({r[0] for r in runs}) == 1, [r[0] for r in runs]
    g = np.array([r[1] for r in runs])
    assert np.all(g == g[0]), g
