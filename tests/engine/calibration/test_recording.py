"""isac_twin.calibration.recording: the recorder's real MCAP read back as measurements
reproduces the recorded channel in the calibrator's model at the truth, and each
snapshot's noise is estimated from the recorded subcarriers."""

import json

import numpy as np
import pytest

from isac_twin import CalibrationError, load_scene
from isac_twin.calibration import (
    Calibrator,
    Parameter,
    SolverSettings,
    measurements_from_recording,
)
from isac_twin.cli import main
from tests.engine.calibration.conftest import lap_room


@pytest.mark.slow
def test_recorded_csi_is_the_model_at_truth(recording):
    """Reading path check: poses, arrays, orientations, subcarriers of the recording
    reproduce the recorded channel exactly in the calibrator's Sionna model."""
    _, real, run = recording
    scene = load_scene(real)
    [((tx, rx), meas)] = measurements_from_recording(run, scene.config, max_snapshots=4,
                                                     max_subcarriers=8)
    assert (tx, rx) == ("AP1", "robot1") and meas.csi.shape == (4, 8, 2, 4)
    with pytest.raises(CalibrationError, match=r"of link AP2->robot1 \(recorded: AP1->robot1\)"):
        measurements_from_recording(run, scene.config, links=[("AP2", "robot1")])
    cal = Calibrator(scene, meas, [Parameter("permittivity", "brick")],
                     SolverSettings.from_tracer(scene.config.tracer))
    f, g, _ = cal.evaluate(cal.initial)
    assert f < 1e-5  # dB^2
    assert abs(g[0]) < 0.05


@pytest.mark.slow
def test_the_model_at_the_truth_is_the_recording_with_every_chain(tmp_path):
    """The recorder's tracer (``method = "auto"``: chain reuse) tries every chain of the
    AP's branching rays to every receiver; so does the calibrator's model of that
    scene (``SolverSettings.from_tracer``), and at the truth it is the recording. At
    depth 3 and 3,000 rays Sionna's candidate generator, the calibrator's model before
    (and with ``chains=False``), misses paths the recording has: a mismatch floor no
    fit can remove (lab: 0.079 dB^2 at the truth, 0.001 with chains)."""
    import dataclasses

    from isac_twin import Twin
    from isac_twin.transport.record import record_twin

    real = lap_room(tmp_path / "real", "brick", tracer={"samples_per_src": 3000, "max_depth": 3})
    record_twin(Twin.from_scene(real), 4, tmp_path / "run.mcap")
    scene = load_scene(real)
    [(_, meas)] = measurements_from_recording(tmp_path / "run.mcap", scene.config,
                                              max_snapshots=4, max_subcarriers=8)
    settings = SolverSettings.from_tracer(scene.config.tracer)
    assert settings.chains
    params = [Parameter("permittivity", "brick")]
    cal = Calibrator(scene, meas, params, settings)
    f = cal.evaluate(cal.initial, grad=False)[0]
    sampled = Calibrator(load_scene(real), meas, params,
                         dataclasses.replace(settings, chains=False))
    f_sampled = sampled.evaluate(sampled.initial, grad=False)[0]
    assert f < 1e-5 and f_sampled > 1e-3, (f, f_sampled)


@pytest.mark.slow
def test_noise_is_read_off_the_recording_and_added_to_the_model(recording, tmp_path, caplog):
    """A lap recorded at 20 dB SNR on 64 subcarriers 1.25 MHz apart (a delay tail beyond
    +-200 ns): each snapshot's noise variance is estimated from all its subcarriers
    within 15 % of the noise the recorder added (its power is the message's mean over
    10^2, so E|y|^2 = 1.01 x that), and with it added to the model's power the truth
    fits the noisy recording better than the exact model does (by 1 % here: at 20 dB
    the mismatch is mostly the noise's own spread, few fades sink below it). The
    module's noise-free
    recording (16 subcarriers 5 MHz apart: 200 ns, no tail) gets no estimate, logged."""
    from isac_twin import Twin
    from isac_twin.bus.msgs import Csi
    from isac_twin.transport.record import CsiRecording, read_messages, record_twin

    real = lap_room(tmp_path / "real", "brick")
    run = tmp_path / "noisy.mcap"
    record_twin(Twin.from_scene(real), 6, run,
                csi=CsiRecording(subcarrier_step=4, snr_db=20.0, seed=2))
    scene = load_scene(real)
    [(_, meas)] = measurements_from_recording(run, scene.config, max_snapshots=6,
                                              max_subcarriers=16)
    ys = [np.asarray(m.decode().h)[0] for m in read_messages(run)
          if m.type_name == Csi.ROS_TYPE]
    assert meas.csi.shape[:2] == (6, 16) and ys[0].shape[0] == 64
    want = np.array([np.mean(np.abs(y) ** 2) / 101.0 for y in ys])
    np.testing.assert_allclose(meas.noise_power, want, rtol=0.15)
    [(_, exact)] = measurements_from_recording(run, scene.config, max_snapshots=6,
                                               max_subcarriers=16, noise=False)
    assert exact.noise_power is None
    settings = SolverSettings.from_tracer(scene.config.tracer)
    with_noise = Calibrator(scene, meas, [Parameter("permittivity", "brick")], settings)
    f_noise = with_noise.evaluate(with_noise.initial, grad=False)[0]
    without = Calibrator(load_scene(real), exact, [Parameter("permittivity", "brick")], settings)
    f_exact = without.evaluate(without.initial, grad=False)[0]
    assert f_noise < f_exact, (f_noise, f_exact)
    # end to end: the report gives the estimates, and --no-noise turns them off
    for flag, out in (([], "with"), (["--no-noise"], "without")):
        assert main(["calibrate", str(real), "--measurements", str(run), "--out",
                     str(tmp_path / out), "--snapshots", "3", "--subcarriers", "8",
                     "--max-steps", "2", "--no-scan", *flag]) == 0
    [snr] = json.loads((tmp_path / "with" / "calibration.json").read_text())["noise_snr_db"]
    np.testing.assert_allclose(snr, 20.0, atol=1.0)  # dB (the estimate and the draw)
    assert json.loads((tmp_path / "without" / "calibration.json").read_text())[
        "noise_snr_db"] == [None]
    with pytest.raises(CalibrationError, match=r"noise_power must be \[N=6\]"):
        type(meas)(meas.tx_position, meas.rx_positions, meas.subcarrier_offsets_hz, meas.csi,
                   meas.tx_array, meas.rx_array, noise_power=[-1.0] * 6)
    # the module's recording: 16 subcarriers 5 MHz apart resolve 200 ns, no tail
    with caplog.at_level("WARNING", logger="isac_twin.calibration.recording"):
        [(_, m2)] = measurements_from_recording(recording[2], scene.config,
                                                max_snapshots=2, max_subcarriers=8)
    assert m2.noise_power is None and "no noise estimate" in caplog.text
