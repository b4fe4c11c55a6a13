"""isac-twin calibrate: a twin with concrete walls, calibrated from a recording made in a
room whose walls are brick (the recorder's real MCAP, the twin's own tracer and PHY),
recovers brick's ITU parameters (Sionna's own table, read independently)."""

import json
from pathlib import Path

import numpy as np
import pytest

from isac_twin import CalibrationError, load_scene
from isac_twin.calibration.calibrator import (
    CalibrationResult,
    Calibrator,
    Parameter,
    SolverSettings,
    local_minima,
)
from isac_twin.calibration.run import measurements_from_recording, write_calibrated_scene
from isac_twin.cli import main
from isac_twin.scene import synthetic as syn
from isac_twin.scene.meshes import read_ply

FREQ = 2.4e9


def room(folder, wall, cabinet_shift=(0.0, 0.0), second_ap=False,
         tracer=(("samples_per_src", 20000), ("max_depth", 2))):
    dx, dy = cabinet_shift
    objs = syn.room_objects((5.0, 4.0, 3.0),
                            {"Cabinet": ((3.0 + dx, 2.5 + dy, 0.0), (3.6 + dx, 3.0 + dy, 1.5),
                                         "metal", 0.002)},
                            material=wall)
    path = {"kind": "polyline", "closed": True,
            "waypoints": [[1.5, 1.5], [3.5, 1.5], [3.5, 2.2], [1.5, 2.2]]}
    devs = [syn.SyntheticDevice("AP1", "access_point", "tx", (0.5, 0.5, 2.0), rows=2, cols=2),
            syn.SyntheticDevice("robot1", "robot", "rx", (1.5, 2.0, 0.0), cols=2,
                                extra={**syn.ROBOT_EXTRA, "path": path})]
    links = [("AP1", "robot1")]
    if second_ap:  # on the other side of the cabinet's x-facing faces
        devs.append(syn.SyntheticDevice("AP2", "access_point", "tx", (2.0, 3.8, 2.5)))
        links.append(("AP2", "robot1"))
    return syn.write_scene_folder(folder, objs, devs, links, frequency_hz=FREQ,
                                  num_subcarriers=256, subcarrier_spacing_hz=312500.0,
                                  tracer=dict(tracer))


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """12 twin steps in the brick room, recorded with compact CSI."""
    from isac_twin import Twin
    from isac_twin.transport.record import record_twin

    d = tmp_path_factory.mktemp("calrun")
    real = room(d / "real", "brick")
    record_twin(Twin.from_scene(real), 12, d / "run.mcap")
    return d, real, d / "run.mcap"


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

    real = room(tmp_path / "real", "brick", tracer={"samples_per_src": 3000, "max_depth": 3})
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
def test_an_object_clear_at_the_start_keeps_its_clear_path(recording, monkeypatch):
    """A pose the fit got wrong can lose an object's paths (lab: SwitchBox_2, 1.4 % of a
    snapshot's power at the start, 0.92 % at a fit 1.8 deg off, then left out of the
    polish). With the start's shares given, the object has a clear path when it had
    one at either pose."""
    import isac_twin.calibration.run as cr

    _, real, run = recording
    scene = load_scene(real)
    [(_, meas)] = measurements_from_recording(run, scene.config, max_snapshots=4,
                                              max_subcarriers=8)
    cal = Calibrator(scene, meas, [Parameter(k, "Cabinet") for k in ("x", "y", "yaw")],
                     SolverSettings.from_tracer(scene.config.tracer))
    moved = np.array([0.0, 0.2, np.radians(10.0)])
    start, there = (max(cr.object_paths(cal, x)["Cabinet"]["power_share_per_snapshot"])
                    for x in (cal.initial, moved))
    assert start != there
    # the same values again are not traced again (the objects' paths and the materials'
    # observability both look at the fit)
    trace, calls = cal._trace, []
    cal._trace = lambda: calls.append(1) or trace()
    cr.object_paths(cal, moved)
    assert calls == []
    cr.object_paths(cal, cal.initial)
    assert calls == [1]
    # a threshold between the two shares: clear at one pose only
    monkeypatch.setattr(cr, "CLEAR_PATH_SHARE", 0.5 * (start + there))
    at_start = cr.object_paths(cal, cal.initial)
    lost, found = (cal.initial, moved) if start < there else (moved, cal.initial)
    alone = cr.object_paths(cal, lost)["Cabinet"]
    both = cr.object_paths(cal, lost, cr.object_paths(cal, found))["Cabinet"]
    assert not alone["clear_path"] and both["clear_path"]
    # (another trace at the same values: float32 field sums, not bit-identical)
    assert both["power_share_max_at_start"] == pytest.approx(max(start, there), rel=1e-5)
    assert at_start["Cabinet"]["clear_path"] == (start > there)


@pytest.mark.slow
def test_cli_recovers_brick_walls(recording, capsys):
    from sionna.rt.radio_materials.itu import itu_material

    d, _, run = recording
    twin = room(d / "twin", "concrete")
    code = main(["calibrate", str(twin), "--measurements", str(run), "--out", str(d / "out"),
                 "--snapshots", "4", "--subcarriers", "8", "--max-steps", "20"])
    assert code == 0
    out = capsys.readouterr().out
    assert "converged" in out and "concrete.permittivity" in out
    rep = json.loads((d / "out" / "calibration.json").read_text())
    eps, sigma = (float(np.asarray(v).reshape(-1)[0]) for v in itu_material("brick", FREQ))
    got = {p["name"]: p for p in rep["parameters"]}
    assert got["concrete.permittivity"]["final"] == pytest.approx(eps, rel=0.01)
    assert got["concrete.conductivity"]["final"] == pytest.approx(sigma, rel=0.05)
    assert rep["converged"]
    assert rep["mismatch_db2"]["final"] < 1e-3 * rep["mismatch_db2"]["initial"]
    # the scan saw more than one slab resonance: a single start could end elsewhere
    assert len(rep["permittivity_scans"]["concrete.permittivity"]["starts"]) > 1
    assert load_scene(d / "out" / "scene").objects.keys() == load_scene(twin).objects.keys()
    assert (d / "out" / "calibration.png").read_bytes()[:4] == b"\x89PNG"
    before = rep["residual_db_per_measurement_initial"]
    assert min(before) > 10 * max(rep["residual_db_per_measurement"])


@pytest.mark.slow
def test_cli_recovers_cabinet_offset_and_says_what_it_cannot_see(tmp_path, capsys):
    """60 steps recorded with the cabinet 3 cm further in x and 2 cm back in y: the
    paths to the robot's positions reflect off the cabinet's y-facing side, so y is
    recovered and x (a shift along that face) is reported as not seen."""
    from isac_twin import Twin
    from isac_twin.transport.record import record_twin

    real = room(tmp_path / "real", "concrete", (0.03, -0.02))
    record_twin(Twin.from_scene(real), 60, tmp_path / "run.mcap")
    twin = room(tmp_path / "twin", "concrete")
    code = main(["calibrate", str(twin), "--measurements", str(tmp_path / "run.mcap"),
                 "--out", str(tmp_path / "out"), "--params", "poses", "--objects", "Cabinet",
                 "--snapshots", "8", "--subcarriers", "8"])
    assert code == 0
    assert "not seen by the measurements: Cabinet.x" in capsys.readouterr().out
    rep = json.loads((tmp_path / "out" / "calibration.json").read_text())
    got = {p["name"]: p["final"] for p in rep["parameters"]}
    assert got["Cabinet.y"] == pytest.approx(-0.02, abs=0.002)
    assert abs(got["Cabinet.yaw"]) < np.radians(0.5)
    assert rep["unobserved"] == ["Cabinet.x"]
    assert rep["mismatch_db2"]["final"] < 1e-3 * rep["mismatch_db2"]["initial"]
    # the hop scanned both offsets and the yaw of the cabinet (it has a path to the
    # robot) and, at the truth already, found no lower basin
    hop = rep["hop"]
    assert hop["parameters"] == ["Cabinet.x", "Cabinet.y", "Cabinet.yaw"]
    assert hop["moved"] == [] and len(hop["rounds"]) == 1  # nothing moved: no second round
    scans = hop["rounds"][0]["scans"]
    assert all(len(scans[k]["mismatch_db2"]) == len(scans[k]["shifts_m"]) > 4
               for k in hop["parameters"])
    assert main(["calibrate", str(twin), "--measurements", str(tmp_path / "run.mcap"),
                 "--out", str(tmp_path / "out2"), "--params", "poses", "--objects", "Cabinet",
                 "--snapshots", "8", "--subcarriers", "8", "--no-hop"]) == 0
    rep2 = json.loads((tmp_path / "out2" / "calibration.json").read_text())
    assert rep2["hop"] is None and rep2["parameters"] == rep["parameters"]
    v = read_ply(tmp_path / "out" / "scene" / "meshes" / "Cabinet.ply").vertices
    assert v[:, 1].min() == pytest.approx(2.5 - 0.02, abs=0.002)


@pytest.mark.slow
def test_a_second_access_point_sees_what_the_first_cannot(tmp_path, capsys):
    """The same run with a second AP whose paths reflect off the cabinet's x-facing
    side: calibrated from both recorded links (the default), x is seen and recovered;
    from AP1's link alone (``--links AP1,robot1``) it is not. (With this AP at
    (1.0, 3.6, 2.0) instead, x is seen too but the fit ends in a local minimum 1.7 cm
    off in y, at 0.13 dB^2: a second link also adds paths that come and go.)"""
    from isac_twin import Twin
    from isac_twin.transport.record import record_twin

    real = room(tmp_path / "real", "concrete", (0.03, -0.02), second_ap=True)
    record_twin(Twin.from_scene(real), 60, tmp_path / "run.mcap")
    twin = room(tmp_path / "twin", "concrete", second_ap=True)
    args = ["calibrate", str(twin), "--measurements", str(tmp_path / "run.mcap"),
            "--params", "poses", "--objects", "Cabinet", "--snapshots", "8",
            "--subcarriers", "8", "--no-hop"]
    assert main(args + ["--out", str(tmp_path / "both")]) == 0
    assert "not seen" not in capsys.readouterr().out
    rep = json.loads((tmp_path / "both" / "calibration.json").read_text())
    assert rep["links"] == [["AP1", "robot1"], ["AP2", "robot1"]] and rep["snapshots"] == [8, 8]
    assert len(rep["residual_db_per_measurement"]) == 16
    got = {p["name"]: p["final"] for p in rep["parameters"]}
    assert rep["unobserved"] == []
    assert got["Cabinet.x"] == pytest.approx(0.03, abs=0.002)
    assert got["Cabinet.y"] == pytest.approx(-0.02, abs=0.002)
    assert main(args + ["--out", str(tmp_path / "one"), "--links", "AP1,robot1"]) == 0
    assert "not seen by the measurements: Cabinet.x" in capsys.readouterr().out
    assert json.loads((tmp_path / "one" / "calibration.json").read_text())["links"] == [
        ["AP1", "robot1"]]


def test_calibrated_scene_moves_the_fitted_object(tmp_path):
    twin = room(tmp_path / "twin", "concrete")
    scene = load_scene(twin, load_sionna=False)
    res = CalibrationResult(
        names=["Cabinet.x", "Cabinet.y", "Cabinet.yaw", "concrete.permittivity"],
        initial=np.zeros(4), final=np.array([0.02, -0.01, np.pi / 2, 4.0]),
        gradient_initial=np.ones(4), unobserved=[], mismatch_initial=1.0, mismatch_final=0.0,
        residual_db=np.zeros(1), converged=True, message="", evaluations=1,
        seconds_per_step=0.0)
    out = write_calibrated_scene(scene, res, tmp_path / "out")
    v = read_ply(out / "meshes" / "Cabinet.ply").vertices
    # 0.6 x 0.5 footprint centred at (3.3, 2.75), turned 90 deg -> 0.5 x 0.6, then shifted
    assert np.allclose(v.min(axis=0), [3.3 - 0.25 + 0.02, 2.75 - 0.3 - 0.01, 0.0], atol=1e-5)
    assert np.allclose(v.max(axis=0), [3.3 + 0.25 + 0.02, 2.75 + 0.3 - 0.01, 1.5], atol=1e-5)
    assert np.allclose(read_ply(out / "meshes" / "floor.ply").vertices,
                       read_ply(twin / "meshes" / "floor.ply").vertices)
    load_scene(out, load_sionna=False)


def test_pose_grid_steps():
    from isac_twin.calibration.run import pose_grid

    g = pose_grid(Parameter("y", "Cabinet"), 0.125)  # lambda at 2.4 GHz
    assert g[0] == pytest.approx(-0.1) and g[-1] == pytest.approx(0.1)
    assert np.diff(g).max() <= 0.125 / 8 + 1e-12 and len(g) == 14
    y = pose_grid(Parameter("yaw", "Cabinet"), 0.125)
    assert np.degrees(y).round(6).tolist() == list(range(-5, 6))
    narrow = pose_grid(Parameter("x", "Cabinet", bounds=(-0.02, 0.03)), 0.125)
    assert narrow[0] == pytest.approx(-0.02) and narrow[-1] == pytest.approx(0.03)


def test_local_minima():
    assert local_minima(np.array([3.0, 1.0, 2.0, 0.5, 0.7, 0.2])).tolist() == [5, 3, 1]


def test_parameter_choice_is_checked(tmp_path):
    from isac_twin import CalibrationError
    from isac_twin.calibration.run import default_parameters

    scene = load_scene(room(tmp_path / "twin", "concrete"), load_sionna=False)
    names = [p.name for p in default_parameters(scene, ("materials",), [])]
    assert names == ["concrete.permittivity", "concrete.conductivity"]  # metal is not fitted
    with pytest.raises(CalibrationError, match="needs --objects"):
        default_parameters(scene, ("poses",), [])
    with pytest.raises(CalibrationError, match="no object 'Sofa'"):
        default_parameters(scene, ("poses",), ["Sofa"])
    with pytest.raises(CalibrationError, match="'colours' is not one of"):
        default_parameters(scene, ("colours",), [])
    # one material at one thickness, by Sionna's name of it
    names = [p.name for p in default_parameters(scene, ("materials",), [], ["metal-0.002"])]
    assert names == ["metal-0.002.permittivity", "metal-0.002.conductivity"]
    with pytest.raises(CalibrationError, match="no object has material 'wood'"):
        default_parameters(scene, ("materials",), [], ["wood"])


def test_a_material_at_one_thickness_is_written_for_its_objects_only(tmp_path):
    from isac_twin.calibration.run import calibrated_materials

    objs = syn.room_objects((5.0, 4.0, 3.0), {"Shelf": ((3.0, 2.5, 0.0), (3.6, 3.0, 1.5),
                                                        "concrete", 0.05)})
    devs = [syn.SyntheticDevice("AP1", "access_point", "tx", (0.5, 0.5, 2.0))]
    scene = load_scene(syn.write_scene_folder(tmp_path / "r", objs, devs, []),
                       load_sionna=False)
    res = CalibrationResult(names=["concrete-0.05.permittivity"], initial=np.array([5.24]),
                            final=np.array([6.0]), gradient_initial=np.ones(1), unobserved=[],
                            mismatch_initial=1.0, mismatch_final=0.0, residual_db=np.zeros(1),
                            converged=True, message="", evaluations=1, seconds_per_step=0.0)
    mats, assign = calibrated_materials(scene, res)
    assert assign == {"Shelf": "concrete-0.05-calibrated"}
    assert mats["concrete-0.05-calibrated"]["relative_permittivity"] == 6.0
    assert mats["concrete-0.05-calibrated"]["thickness"] == pytest.approx(0.05)
    out = write_calibrated_scene(scene, res, tmp_path / "out")
    back = load_scene(out, load_sionna=False)
    assert back.objects["Shelf"].material == "concrete-0.05-calibrated"
    assert back.objects["floor"].material == "concrete"  # 0.2 m concrete untouched


@pytest.mark.slow
def test_calibrated_folder_gives_the_calibrators_channel_at_the_fitted_values(recording,
                                                                               tmp_path):
    """The folder written holds the fitted materials (custom radio materials) and poses:
    loaded anew, its channel is the calibrator's model at the fitted values."""
    _, _, run = recording
    twin = room(tmp_path / "twin", "concrete")
    scene = load_scene(twin)
    [(_, meas)] = measurements_from_recording(run, scene.config, max_snapshots=4,
                                              max_subcarriers=8)
    params = [Parameter("permittivity", "concrete"), Parameter("conductivity", "concrete"),
              Parameter("x", "Cabinet"), Parameter("y", "Cabinet"), Parameter("yaw", "Cabinet")]
    settings = SolverSettings.from_tracer(scene.config.tracer)
    cal = Calibrator(scene, meas, params, settings)
    fitted = np.array([4.3, 0.07, 0.013, -0.021, np.radians(1.7)])
    _, _, model = cal.evaluate(fitted, grad=False)
    res = CalibrationResult(names=[p.name for p in params], initial=cal.initial, final=fitted,
                            gradient_initial=np.ones(5), unobserved=[], mismatch_initial=1.0,
                            mismatch_final=0.0, residual_db=np.zeros(4), converged=True,
                            message="", evaluations=1, seconds_per_step=0.0)
    out = write_calibrated_scene(load_scene(twin, load_sionna=False), res, tmp_path / "out")
    xml = (out / "scene.xml").read_text()
    assert 'type="radio-material" id="mat-concrete-calibrated"' in xml
    assert "mat-concrete-0.2" not in xml  # no object refers to ITU concrete any more
    cscene = load_scene(out)
    assert cscene.custom_materials == {"concrete-calibrated": {
        "relative_permittivity": pytest.approx(4.3), "conductivity": pytest.approx(0.07),
        "thickness": pytest.approx(0.2)}}
    assert {o.material for o in cscene.objects.values()} == {"concrete-calibrated", "metal"}
    again = Calibrator(cscene, meas, [Parameter("permittivity", "concrete-calibrated")],
                       settings)
    assert again.initial[0] == pytest.approx(4.3, rel=1e-6)
    _, _, model2 = again.evaluate(again.initial, grad=False)
    assert np.ptp(model) > 5  # dB: a channel with structure, not a constant
    np.testing.assert_allclose(model2, model, atol=1e-3)  # dB
    # and away from the fitted values it differs (the check can fail)
    _, _, model0 = cal.evaluate(cal.initial, grad=False)
    assert np.abs(model0 - model).max() > 0.1


def test_permittivity_grid_is_fine_for_a_thin_slab(tmp_path):
    """3 cm of wood at 2.4 GHz: one resonance period (sqrt(eps) 2.08) is wider than the
    range eps/2 .. 2 eps, so 6 points per period gave 4 points 30-55 % apart."""
    from isac_twin.calibration.run import permittivity_grid

    scene = load_scene(Path(__file__).resolve().parents[3] / "blend_scenes" / "aces_lab"
                       / "scene", load_sionna=False)
    g = permittivity_grid(scene, "wood-0.03", 1.99)
    assert len(g) >= 12 and g[0] == pytest.approx(1.0) and g[-1] == pytest.approx(3.98)
    assert np.max(g[1:] / g[:-1]) < 1.2


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

    real = room(tmp_path / "real", "brick")
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
    with caplog.at_level("WARNING", logger="isac_twin.calibration.run"):
        [(_, m2)] = measurements_from_recording(recording[2], scene.config,
                                                max_snapshots=2, max_subcarriers=8)
    assert m2.noise_power is None and "no noise estimate" in caplog.text
