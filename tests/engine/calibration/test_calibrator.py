"""isac_twin.calibration.calibrator: the Calibrator wires the problem's checks, the
forward model and the searches; one link's measurements give one model, a list one
per link."""

import numpy as np
import pytest

from isac_twin import CalibrationError, load_scene
from isac_twin.calibration import Calibrator, Measurements, Parameter
from tests.engine.calibration.conftest import OFFSETS, RX, SETTINGS, TX, cabinet_room


def test_a_bad_problem_is_refused(tmp_path):
    meas = Measurements(TX, RX, OFFSETS, np.ones((4, 6)))
    scene = load_scene(cabinet_room(tmp_path / "twin"))
    with pytest.raises(CalibrationError, match="no parameters to fit"):
        Calibrator(scene, meas, [], SETTINGS)
    with pytest.raises(CalibrationError, match="given twice"):
        Calibrator(scene, meas, [Parameter("x", "Cabinet")] * 2, SETTINGS)
    with pytest.raises(CalibrationError, match="non-empty list"):
        Calibrator(scene, [], [Parameter("x", "Cabinet")], SETTINGS)
    with pytest.raises(CalibrationError, match="Cabinet.x: scale must be > 0"):
        Calibrator(scene, meas, [Parameter("x", "Cabinet", scale=-1.0)], SETTINGS)


@pytest.mark.slow
def test_one_link_gives_one_model_and_a_list_one_per_link(tmp_path):
    """The same link given alone and as a list of one: the same mismatch, gradient and
    model, the list's model a list; the typical changes are the parameters' own."""
    rng = np.random.default_rng(1)
    meas = Measurements(TX, RX, OFFSETS, rng.normal(size=(4, 6)) * 1e-4)
    params = [Parameter("permittivity", "concrete"), Parameter("x", "Cabinet")]
    one = Calibrator(load_scene(cabinet_room(tmp_path / "a")), meas, params, SETTINGS)
    many = Calibrator(load_scene(cabinet_room(tmp_path / "b")), [meas], params, SETTINGS)
    assert one.scales.tolist() == [0.1 * one.initial[0], 0.01]
    x = one.initial + [0.2 * one.initial[0], 0.01]
    f1, g1, m1 = one.evaluate(x)
    f2, g2, m2 = many.evaluate(x)
    assert isinstance(m2, list) and len(m2) == 1 and m1.shape == (4, 6, 1, 1)
    assert f1 == pytest.approx(f2, rel=1e-12) and np.allclose(g1, g2, rtol=1e-9, atol=0)
    np.testing.assert_allclose(m1, m2[0], rtol=1e-12)
    assert one.evaluations == 1 and len(one.step_seconds) == 1
    res = one.result(x, converged=True, message="m")
    assert res.residual_db.shape == (4,) and res.mismatch_final == pytest.approx(f1)
