"""isac_twin.calibration.problem: parameters, measurements, the mismatch and the checks
on what a calibrator is given."""

import numpy as np
import pytest

from isac_twin import CalibrationError
from isac_twin.calibration import Measurements, Parameter
from isac_twin.calibration.problem import mismatch_db2, unobserved
from tests.engine.calibration.conftest import OFFSETS, RX, TX


def test_mismatch_ignores_common_phase():
    rng = np.random.default_rng(0)
    h = rng.normal(size=(3, 5)) + 1j * rng.normal(size=(3, 5))
    phase = np.exp(1j * rng.uniform(0, 2 * np.pi, (3, 1)))
    assert mismatch_db2(h * phase, h) < 1e-20
    assert mismatch_db2(2 * h, h) == pytest.approx((20 * np.log10(2)) ** 2, rel=1e-6)


def test_unobserved_is_relative_to_the_best_seen():
    assert unobserved([3.0, -2e-7, 0.5], ["a", "b", "c"]) == ["b"]
    assert unobserved([0.0, 0.0], ["a", "b"]) == ["a", "b"]


def test_bad_input_is_refused():
    with pytest.raises(CalibrationError, match="kind 'height'"):
        Parameter("height", "Cabinet")
    with pytest.raises(CalibrationError, match="permittivity is >= 1"):
        Parameter("permittivity", "concrete", bounds=(0.5, 10))
    with pytest.raises(CalibrationError, match=r"csi must be \[N=4, K=6, Nr=1, Nt=1\]"):
        Measurements(TX, RX, OFFSETS, np.zeros((4, 5)))
