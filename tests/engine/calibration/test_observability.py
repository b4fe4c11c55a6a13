"""isac_twin.calibration.observability: which objects have a clear path to the robot."""

import numpy as np
import pytest

from isac_twin import load_scene
from isac_twin.calibration import (
    Calibrator,
    Parameter,
    SolverSettings,
    measurements_from_recording,
)


@pytest.mark.slow
def test_an_object_clear_at_the_start_keeps_its_clear_path(recording, monkeypatch):
    """A pose the fit got wrong can lose an object's paths (lab: SwitchBox_2, 1.4 % of a
    snapshot's power at the start, 0.92 % at a fit 1.8 deg off, then left out of the
    polish). With the start's shares given, the object has a clear path when it had
    one at either pose."""
    import isac_twin.calibration.observability as cr

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
    trace, calls = cal.model.trace, []
    cal.model.trace = lambda: calls.append(1) or trace()
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
