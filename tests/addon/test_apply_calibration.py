"""addon/calibration.py and custom radio materials: export of custom materials, and a
calibration folder written by the engine (isac_twin.calibration.write_calibrated_scene)
applied to the open scene in headless bpy."""

from __future__ import annotations

import math

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")

pytestmark = pytest.mark.blender


def _room(scene):
    from addon import devices, modelling

    modelling.create_room(4.0, 3.0, 2.5, 0.2, name="Room", scene=scene)
    devices.add_access_point("AP1", (0.3, 1.5, 2.0), (0.0, 0.0, 0.0), scene=scene)
    return modelling.add_furniture("cabinet", (2.5, 1.2, 0.0), math.radians(20), scene=scene)


def test_custom_material_is_exported_and_loaded_by_the_engine(scene, tmp_path):
    from addon import materials
    from addon.exporter import ExportError, export_scene
    from isac_twin import load_scene

    cab = _room(scene)
    materials.set_custom_material(scene, "damp_chipboard",
                                  {"relative_permittivity": 3.1, "conductivity": 0.04,
                                   "thickness": 0.025})
    materials.assign_custom_material([cab], scene, "damp_chipboard")
    export_scene(scene, tmp_path, interchange=False)
    xml = (tmp_path / "scene.xml").read_text()
    assert '<bsdf type="radio-material" id="mat-damp_chipboard">' in xml
    loaded = load_scene(tmp_path, load_sionna=False)
    assert loaded.objects["Cabinet"].material == "damp_chipboard"
    assert loaded.objects["Cabinet"].thickness == pytest.approx(0.025)
    assert loaded.custom_materials["damp_chipboard"]["conductivity"] == pytest.approx(0.04)
    # refusals: an unknown name, a bad value set from a script, an ITU name
    cab.isac.custom_material = "nope"
    with pytest.raises(ExportError, match="custom radio material 'nope' is not in the scene"):
        export_scene(scene, tmp_path / "bad", interchange=False)
    cab.isac.custom_material = "damp_chipboard"
    scene.isac.radio_materials["damp_chipboard"].relative_permittivity = 0.3
    with pytest.raises(ExportError, match="relative_permittivity: expected a value in"):
        export_scene(scene, tmp_path / "bad", interchange=False)
    with pytest.raises(ValueError, match="the name is an ITU material's"):
        materials.set_custom_material(scene, "wood", {"relative_permittivity": 2.0,
                                                      "conductivity": 0.0, "thickness": 0.1})
    materials.tag_objects([cab], "wood", 0.03)  # an ITU tag replaces the custom one
    assert cab.isac.custom_material == ""


def test_apply_calibration_moves_objects_and_sets_materials(scene, tmp_path):
    from addon.exporter import export_scene
    from isac_twin import load_scene
    from isac_twin.calibration import CalibrationResult, write_calibrated_scene
    from isac_twin.scene.meshes import read_ply

    cab = _room(scene)
    export_scene(scene, tmp_path / "twin", interchange=False)
    twin = load_scene(tmp_path / "twin", load_sionna=False)
    names = ["Cabinet.x", "Cabinet.y", "Cabinet.yaw", "concrete.permittivity"]
    res = CalibrationResult(names=names, initial=np.array([0, 0, 0, 5.24]),
                            final=np.array([0.031, -0.012, math.radians(2.5), 6.1]),
                            gradient_initial=np.ones(4), unobserved=[], mismatch_initial=1.0,
                            mismatch_final=0.0, residual_db=np.zeros(1), converged=True,
                            message="", evaluations=1, seconds_per_step=0.0)
    out = tmp_path / "cal"
    write_calibrated_scene(twin, res, out / "scene")
    (out / "calibration.json").write_text(__import__("json").dumps(
        {"parameters": [{"name": n, "final": float(v)} for n, v in zip(names, res.final)]}))

    # the operator (a file browser in the UI) calls the plain function
    assert bpy.ops.isac.apply_calibration(directory=str(out)) == {"FINISHED"}
    assert scene.isac.radio_materials["concrete-calibrated"].relative_permittivity == \
        pytest.approx(6.1)
    walls = [o for o in scene.objects if o.name.startswith("Room_Wall") or o.name == "Room_Floor"]
    assert len(walls) == 5
    assert all(o.isac.custom_material == "concrete-calibrated" for o in walls)
    assert scene.objects["Room_Ceiling"].isac.custom_material == ""  # ceiling board
    assert cab.isac.custom_material == ""  # the cabinet's chipboard was not fitted
    # re-exported, the .blend gives the calibrated folder's geometry and materials
    export_scene(scene, tmp_path / "again", interchange=False)
    want = read_ply(out / "scene" / "meshes" / "Cabinet.ply").vertices
    got = read_ply(tmp_path / "again" / "meshes" / "Cabinet.ply").vertices
    np.testing.assert_allclose(np.sort(got, axis=0), np.sort(want, axis=0), atol=1e-5)
    before = read_ply(tmp_path / "twin" / "meshes" / "Cabinet.ply").vertices
    assert np.abs(np.sort(before, axis=0) - np.sort(want, axis=0)).max() > 0.01
    again = load_scene(tmp_path / "again", load_sionna=False)
    assert again.custom_materials == load_scene(out / "scene",
                                                load_sionna=False).custom_materials
    assert again.objects["Room_Floor"].material == "concrete-calibrated"


def test_apply_calibration_refuses_bad_folders(scene, tmp_path):
    from addon import calibration

    _room(scene)
    with pytest.raises(calibration.CalibrationFileError, match="calibration.json: not found"):
        calibration.apply_calibration(scene, tmp_path)
    (tmp_path / "scene").mkdir()
    (tmp_path / "scene" / "scene.xml").write_text("<scene/>")
    (tmp_path / "calibration.json").write_text('{"parameters": [{"name": "Sofa.x", '
                                               '"final": 0.1}]}')
    loc = scene.objects["Cabinet"].location.copy()
    with pytest.raises(calibration.CalibrationFileError, match="objects this scene does not "
                                                               "have: Sofa"):
        calibration.apply_calibration(scene, tmp_path)
    (tmp_path / "calibration.json").write_text('{"parameters": [{"name": "Cabinet.x"}]}')
    with pytest.raises(calibration.CalibrationFileError, match=r"parameters\[0\]: expected"):
        calibration.apply_calibration(scene, tmp_path)
    assert scene.objects["Cabinet"].location == loc  # nothing moved
    with pytest.raises(RuntimeError, match="none/calibration.json: not found"):
        bpy.ops.isac.apply_calibration(directory=str(tmp_path / "none"))
