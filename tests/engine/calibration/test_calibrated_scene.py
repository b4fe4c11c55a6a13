"""isac_twin.calibration.calibrated_scene: the folder written moves the fitted objects,
writes the fitted materials for their objects only, and gives the calibrator's channel
at the fitted values."""

import numpy as np
import pytest

from isac_twin import load_scene
from isac_twin.calibration import (
    CalibrationResult,
    Calibrator,
    Parameter,
    SolverSettings,
    measurements_from_recording,
    write_calibrated_scene,
)
from isac_twin.calibration.calibrated_scene import calibrated_materials
from isac_twin.scene import synthetic as syn
from isac_twin.scene.meshes import read_ply
from tests.engine.calibration.conftest import lap_room


def test_calibrated_scene_moves_the_fitted_object(tmp_path):
    twin = lap_room(tmp_path / "twin", "concrete")
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


def test_a_material_at_one_thickness_is_written_for_its_objects_only(tmp_path):
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
    twin = lap_room(tmp_path / "twin", "concrete")
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
