"""engine/experiments/lab_calibration.py: the closing-the-loop case, shortened: a small room with a
wooden screen (3 cm, standing between the AP and the robot's path) and a metal cabinet,
both moved as the case study moves furniture, the screen's wood 30 % denser; half a lap
recorded, calibrated."""

import json

import numpy as np
import pytest

from isac_twin import load_scene
from isac_twin.calibration import SolverSettings
from isac_twin.experiments.lab_calibration import (
    closing_the_loop,
    lap_steps,
    per_fix_errors,
    real_room,
)
from isac_twin.scene import synthetic as syn


def room(folder):
    objs = syn.room_objects((5.0, 4.0, 3.0), {
        "Screen": ((1.0, 2.8, 0.0), (3.6, 2.83, 2.2), "wood", 0.03),
        "Cabinet": ((4.2, 0.4, 0.0), (4.8, 0.9, 1.6), "metal", 0.002)})
    path = {"kind": "polyline", "closed": True,
            "waypoints": [[1.2, 1.2], [3.4, 1.2], [3.4, 1.9], [1.2, 1.9]]}
    devs = [syn.SyntheticDevice("AP1", "access_point", "tx", (0.3, 3.7, 2.0), rows=2, cols=2),
            syn.SyntheticDevice("robot1", "robot", "rx", (1.2, 1.5, 0.0), cols=2,
                                extra={**syn.ROBOT_EXTRA, "path": path})]
    return syn.write_scene_folder(folder, objs, devs, [("AP1", "robot1")], frequency_hz=2.4e9,
                                  num_subcarriers=256, subcarrier_spacing_hz=312500.0,
                                  tracer={"samples_per_src": 10000, "max_depth": 2},
                                  room={"shell": [o.name for o in objs
                                                  if o.name not in ("Screen", "Cabinet")],
                                        "furniture": ["Screen", "Cabinet"]})


def test_real_room_moves_furniture_and_changes_the_material(tmp_path):
    folder = room(tmp_path / "twin")
    scene, truth = real_room(folder, seed=2, changed_material="wood-0.03")
    assert set(truth["moved"]) == {"Screen", "Cabinet"}
    assert scene.objects["Screen"].material == "wood-real"
    m = truth["material"]
    assert m["relative_permittivity"] == pytest.approx(1.3 * m["twin_permittivity"])
    mat = scene.sionna.objects["Screen"].radio_material
    assert float(mat.relative_permittivity.numpy()[0]) == pytest.approx(
        m["relative_permittivity"], rel=1e-6)
    assert scene.content_hash() != load_scene(folder, load_sionna=False).content_hash()
    assert lap_steps(scene.config, 1.0) == 28  # 5.8 m at the burger's 0.211 m/s
    with pytest.raises(ValueError, match="no object of material 'glass'"):
        real_room(folder, changed_material="glass")


@pytest.mark.slow
def test_closing_the_loop_shortened(tmp_path):
    folder = room(tmp_path / "twin")
    r = closing_the_loop(folder, tmp_path / "out", seed=2, changed_material="wood-0.03",
                         dt=1.0, laps=0.5, snapshots=4, subcarriers=8, max_steps=15,
                         solver=SolverSettings(max_depth=2, samples_per_src=10000))
    json.dumps(r)  # a JSON report
    assert r["steps"] == 14 and r["snr_db"] is None
    assert r["mismatch_db2"]["final"] < 0.8 * r["mismatch_db2"]["initial"]
    # at the real room's values the model is the recording (same tracer: self-consistency
    # of the reading path: 1.3e-6 dB^2), far below the fit here (0.024 dB^2)
    assert r["mismatch_db2"]["at_truth"] < 0.05 * r["mismatch_db2"]["final"], r["mismatch_db2"]
    m = r["material"]
    assert m["error_percent"] < 10.0  # the twin's guess was 23 % off
    assert set(r["objects"]) == {"Screen", "Cabinet"}
    # the cabinet is behind the screen from the AP: no traced path sees it
    assert r["objects"]["Cabinet"]["unobserved"] == ["x", "y", "yaw"]
    for o in r["objects"].values():
        assert np.isfinite(o["fitted_cm_deg"]).all()
    seen = r["observability"]["wood-0.03"]  # what the report says about the material
    assert len(seen["paths_per_snapshot"]) == 4 and sum(seen["paths_per_snapshot"]) > 0
    assert 0 < max(seen["power_share_per_snapshot"]) <= 1
    assert 0 < seen["uncertainty_percent"] < 100
    back = load_scene(r["calibrated_scene"], load_sionna=False)
    assert back.objects["Screen"].material == "wood-0.03-calibrated"
    # the twin at the real room's values, written as a calibration would: the true
    # permittivity, and the real room's channel (the mismatch at the truth above)
    true_room = load_scene(r["true_room_scene"], load_sionna=False)
    assert true_room.custom_materials["wood-0.03-calibrated"]["relative_permittivity"] == (
        pytest.approx(m["relative_permittivity"]))
    # every path crosses the screen; none touches the cabinet: only the screen has a
    # clear path, and the report says why the cabinet is not held to the target
    assert r["objects"]["Screen"]["clear_path"] and not r["objects"]["Cabinet"]["clear_path"]
    assert any(n.startswith("Cabinet: no clear path") for n in r["could_not_see"])

    # per-fix localization on the recorded lap, one observation per fix for every twin:
    # two copies of the original twin give the same errors, to the bit
    twins = {"original": load_scene(folder), "copy": load_scene(folder),
             "true room": real_room(folder, seed=2)[0]}
    pf = per_fix_errors(twins, real_room(folder, seed=2)[0], r["recording"], seed=2,
                        spacing=0.25, dt=2.0, methods=("MCA",), cache_dir=tmp_path / "cache")
    json.dumps(pf)
    assert pf["steps"] == 6  # the recorded half lap (13 s) every 2 s
    e = pf["errors_m"]
    assert set(e["original"]) == {"MCA/pilots", "MCA/tracer"}
    assert len(e["original"]["MCA/pilots"]) == 6
    assert np.isfinite(e["true room"]["MCA/pilots"]).all()
    assert e["original"] == e["copy"]
    # two observations per fix: the pilots' estimated delays and the traced ones
    assert e["original"]["MCA/pilots"] != e["original"]["MCA/tracer"]
    assert np.all(np.array(e["true room"]["MCA/tracer"]) < 6.4)  # inside the 5 x 4 m room
    with pytest.raises(ValueError, match="modes"):
        per_fix_errors(twins, twins["original"], r["recording"], modes=("radar",),
                       cache_dir=tmp_path / "cache")
