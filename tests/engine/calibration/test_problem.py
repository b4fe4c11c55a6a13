"""isac_twin.calibration.problem: parameters, measurements, the mismatch and the checks
on what a calibrator is given."""

import numpy as np
import pytest

from isac_twin import CalibrationError
from isac_twin.calibration import Measurements, Parameter
from isac_twin.calibration.problem import (
    as_links,
    check_parameters,
    mismatch_db2,
    unobserved,
)
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


def test_parameters_and_links_are_checked():
    """What a calibrator is given: at least one parameter, none twice, a typical change
    > 0; one link's measurements or a list of links on the same subcarriers."""
    with pytest.raises(CalibrationError, match="no parameters to fit"):
        check_parameters([])
    with pytest.raises(CalibrationError, match="given twice"):
        check_parameters([Parameter("x", "Cabinet"), Parameter("x", "Cabinet")])
    assert Parameter("x", "Cabinet").typical_change(0.0) == 0.01  # m
    assert Parameter("yaw", "Cabinet").typical_change(0.0) == pytest.approx(np.radians(1.0))
    assert Parameter("permittivity", "concrete").typical_change(5.0) == pytest.approx(0.5)
    assert Parameter("conductivity", "concrete").typical_change(0.0) == 0.01  # S/m
    with pytest.raises(CalibrationError, match="scale must be > 0"):
        Parameter("x", "Cabinet", scale=0.0).typical_change(0.0)
    one = Measurements(TX, RX, OFFSETS, np.ones((4, 6)))
    assert as_links(one) == [one] and as_links([one, one]) == [one, one]
    with pytest.raises(CalibrationError, match="non-empty list"):
        as_links([])
    with pytest.raises(CalibrationError, match="non-empty list"):
        as_links([np.ones((4, 6))])
    with pytest.raises(CalibrationError, match="link 1's subcarriers differ"):
        as_links([one, Measurements(TX, RX, OFFSETS + 1e6, np.ones((4, 6)))])
