"""engine/sensing on the bundled lab: Sionna RCS echoes, bistatic tracking, clutter.

Sensing link AP2 (1x1 tx) -> AP1 (4x8 rx, angles), 25 % of the REs
(subcarrier comb), 20 dBm, robot1 (sigma = 0.5 m^2 Burger-sized target)
on the circle centre (4, 3) r 1.5 at 0.2 m/s, dt = 0.5 s.
"""

import numpy as np
import pytest

from isac_twin.experiments.sensing_demo import lab_link, lab_twin, run_tracking
from isac_twin.sensing import Detections
from isac_twin.sensing.estimator import RadarEstimator

pytestmark = pytest.mark.slow

#: stated bound on the confirmed-track position RMSE with EMA background
#: subtraction over the first 36 steps (measured 0.17 m; full circle 0.23 m
#: EMA, 0.12 m with the empty-room reference, see docs/sensing.md)
TRACK_RMSE_M = 0.35


def test_bistatic_tracking_on_the_circle():
    m = run_tracking(36, 0.5, background="ema")
    assert m["false_tracks"] == 0
    assert m["track_rmse"] < TRACK_RMSE_M
    assert m["track_coverage"] >= 0.75
    # the estimator published its detections on the bus
    tw = m["twin"]
    assert tw.bus.topic_type("/sensing/detections") is Detections
    # echo paths are attributed to the robot target
    ep = m["estimator"].tracer(tw.device_poses(), [("AP2", "AP1")])[("AP2", "AP1")]
    assert ep.echo.num_paths > 0 and set(ep.target) == {"robot1"}
    assert ep.clutter.num_paths > 0
    t = m["truth"][-1]
    d_true = (np.linalg.norm(np.r_[t, 0.096] - [4.0, 0.05, 2.0])
              + np.linalg.norm(np.r_[t, 0.096] - [0.05, 3.0, 2.0]))
    assert ep.echo.tau[0] * 299_792_458.0 == pytest.approx(d_true, abs=0.05)


def test_static_furniture_gives_no_track():
    # Chair_2 tagged as a (static) target, no robot target: with background
    # subtraction nothing is tracked; without it the clutter is detected.
    tw = lab_twin(0.5, path=None)
    est = RadarEstimator([lab_link()], robot_targets=False, object_targets=("Chair_2",),
                         background="ema", publish=False)
    tw.estimators.append(est)
    raw = RadarEstimator([lab_link()], robot_targets=False, background="none",
                         publish=False)
    for _ in range(7):
        r = tw.step()
        assert not r.sensing.tracks
    tw.estimators = [raw]
    n_raw = 0
    for _ in range(4):
        r = tw.step()
        n_raw += sum(len(v) for v in r.sensing.detections.values())
    assert n_raw > 0, "without background subtraction the static room must be detected"


def test_sensing_link_errors_name_the_link():
    from isac_twin.errors import SensingError
    from isac_twin.phy import PlanarArray
    from isac_twin.sensing import SensingLinkSpec

    tw = lab_twin(0.5, path=None)
    bad = SensingLinkSpec(tx="AP1", rx="AP2", rx_array=PlanarArray(1, 1))
    tw.estimators.append(RadarEstimator([bad], publish=False))
    with pytest.raises(SensingError, match="AP1->AP2.*angles requested"):
        tw.step()
    tw.estimators = [RadarEstimator([SensingLinkSpec(tx="AP1", rx="AP9")], publish=False)]
    with pytest.raises(SensingError, match="AP1->AP9.*unknown device 'AP9'"):
        tw.step()


def test_monostatic_echo_and_clutter():
    from isac_twin.sensing.tracer import SensingTracer, TargetSpec

    tw = lab_twin(0.5, path=None)
    tr = SensingTracer(tw.scene, max_depth=1)
    t = np.array([5.5, 3.0, 0.096])
    tr.set_target(TargetSpec("robot1", position=t))
    ep = tr(tw.device_poses(), [("AP1", "AP1")])[("AP1", "AP1")]
    ap1 = np.array([0.05, 3.0, 2.0])
    assert ep.target == ["robot1"]
    assert ep.echo.tau[0] * 299_792_458.0 == pytest.approx(2 * np.linalg.norm(t - ap1), abs=0.02)
    # clutter of the full-duplex node: the dummy receiver's direct coupling is cancelled
    assert ep.clutter.num_paths > 0 and not ep.clutter.is_los.any()
