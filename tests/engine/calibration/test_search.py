"""isac_twin.calibration.search: the strategies recover a material and an object's pose
from channels of a changed room (plain Sionna RT on a copy of the cabinet room with one
known change: the walls' permittivity 30 % higher, or the metal cabinet's mesh moved or
turned)."""

import numpy as np
import pytest

from isac_twin import CalibrationError, load_scene
from isac_twin.calibration import Calibrator, Parameter
from isac_twin.calibration.search import local_minima
from tests.engine.calibration.conftest import FREQ, RX, SETTINGS, cabinet_room, measure


@pytest.mark.slow
def test_recovers_wall_permittivity(tmp_path):
    truth_factor = 1.3
    meas = measure(cabinet_room(tmp_path / "real"), truth_factor)
    cal = Calibrator(load_scene(cabinet_room(tmp_path / "twin")), meas,
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
    meas = measure(cabinet_room(tmp_path / "real", shift))
    cal = Calibrator(load_scene(cabinet_room(tmp_path / "twin")), meas,
                     [Parameter("x", "Cabinet"), Parameter("y", "Cabinet")], SETTINGS)
    res = cal.fit(max_steps=30)
    print(res.to_json())
    assert res.converged, res.message
    assert np.abs(res.final - shift).max() < 0.01  # within 1 cm
    assert res.mismatch_final < 0.1 * res.mismatch_initial


@pytest.mark.slow
def test_recovers_cabinet_yaw(tmp_path):
    yaw = np.radians(3.0)
    meas = measure(cabinet_room(tmp_path / "real", cabinet_yaw=yaw))
    cal = Calibrator(load_scene(cabinet_room(tmp_path / "twin")), meas,
                     [Parameter("yaw", "Cabinet")], SETTINGS)
    res = cal.fit(max_steps=20)
    print(res.to_json())
    assert res.converged, res.message
    assert abs(res.final[0] - yaw) < np.radians(0.5)
    assert res.mismatch_final < 0.1 * res.mismatch_initial


@pytest.mark.slow
def test_polish_recovers_yaw_where_the_mismatch_jumps(tmp_path):
    """The pattern search on traced values reaches the cabinet's true yaw (3 deg) from
    1.2 deg off, stepping 0.5 -> 0.0625 deg (to within its last step)."""
    yaw = np.radians(3.0)
    meas = measure(cabinet_room(tmp_path / "real", cabinet_yaw=yaw))
    cal = Calibrator(load_scene(cabinet_room(tmp_path / "twin")), meas,
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
    meas = measure(cabinet_room(tmp_path / "real", (shift, 0.0)))
    cal = Calibrator(load_scene(cabinet_room(tmp_path / "twin")), meas,
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
    import isac_twin.calibration.search as search

    monkeypatch.setattr(search, "HOP_GAIN_UNSEEN", 1.0)
    xu, fu, _ = cal.hop(x, [0], unseen=[0], span=(0.3, 1.0))
    assert not cal.hop_report["Cabinet.x"]["kept"] and np.array_equal(xu, x) and fu == f
    assert cal.hop_report["Cabinet.x"]["mismatch_after_db2"] == pytest.approx(fh)
    with pytest.raises(CalibrationError, match="unseen"):
        cal.hop(x, [0], unseen=[5])


def test_local_minima():
    assert local_minima(np.array([3.0, 1.0, 2.0, 0.5, 0.7, 0.2])).tolist() == [5, 3, 1]
