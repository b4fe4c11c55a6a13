"""engine/twin/twin.py: Algorithm 1 end to end on a small real scene (Sionna tracing, PHY, robots)."""

import numpy as np
import pytest

from isac_twin import Twin

pytestmark = pytest.mark.slow


def _run(folder, steps, seed=3):
    tw = Twin.from_scene(folder, seed=seed)
    tw.set_path("robot1", {"kind": "circle", "centre": [3.0, 2.0], "radius": 1.0})
    return tw, list(tw.run(steps))


def test_step_produces_paths_rates_and_motion(lab):
    tw, res = _run(lab, 4)
    last = res[-1]
    assert last.step == 3 and last.time_s == pytest.approx(4 * tw.dt)
    rb = last.robots["robot1"]
    assert np.linalg.norm(rb.pose[:2] - [4.0, 2.0]) > 0.01  # it moved
    for lk in (("AP1", "robot1"), ("AP2", "robot1")):
        ls = last.links[lk]
        assert ls.paths.num_paths > 3 and ls.paths.los_delay is not None
        # LOS delay is the antenna distance over c.
        ant = rb.pose[:3] + [0, 0, 0.25]
        tx = np.array(tw.config.device(lk[0]).position)
        assert ls.paths.los_delay == pytest.approx(np.linalg.norm(ant - tx) / 299792458.0,
                                                   rel=1e-5)
        assert ls.rate_bps > 0 and np.isfinite(ls.snr_db)
    # Disjoint symbol sets: no interference, so the 2x2 AP (2 streams) beats the 1x1 AP.
    assert last.links[("AP1", "robot1")].rate_bps > last.links[("AP2", "robot1")].rate_bps
    sig = last.signals[("AP1", "robot1")]
    assert sig.h.shape == (14, 1024, 2, 4)
    assert set(last.timings_s) == {"agents", "trace", "phy", "publish", "sense", "estimate",
                                   "control"}
    # The robot's radio publishes the CSI of each link it receives, as a sensor.
    sub = tw.bus.node("probe").subscribe("/robot1/csi", "isac_twin_msgs/msg/Csi")
    nxt = tw.step()
    csi = {m.tx: m for m in sub.drain()}
    assert set(csi) == {"AP1", "AP2"} and csi["AP1"].header.stamp == pytest.approx(nxt.time_s)
    np.testing.assert_array_equal(csi["AP1"].h, nxt.signals[("AP1", "robot1")].h)
    assert "steps/s" in tw.stats.table()


def test_same_seed_same_run_other_seed_differs(lab):
    _, a = _run(lab, 3, seed=5)
    _, b = _run(lab, 3, seed=5)
    _, c = _run(lab, 3, seed=6)
    for ra, rb in zip(a, b):
        np.testing.assert_array_equal(ra.robots["robot1"].pose, rb.robots["robot1"].pose)
        for lk in ra.links:
            np.testing.assert_array_equal(ra.links[lk].paths.tau, rb.links[lk].paths.tau)
            np.testing.assert_array_equal(ra.links[lk].paths.a, rb.links[lk].paths.a)
            assert ra.links[lk].rate_bps == rb.links[lk].rate_bps
    assert not np.array_equal(a[-1].robots["robot1"].pose, c[-1].robots["robot1"].pose)


def test_hooks_state_source_and_trace_schedule(lab):
    """A sourced robot is placed (no motion model, no controller) and the trace
    schedule skips tracing on the steps it refuses; unhooking restores both."""
    from isac_twin.robots import KinematicState
    tw = Twin.from_scene(lab, seed=1, phy=False)
    tw.set_path("robot1", {"kind": "circle", "centre": [3.0, 2.0], "radius": 1.0})
    calls = []
    tw.set_state_source("robot1", lambda t, dt: calls.append((t, dt)) or KinematicState(
        pose=np.array([1.0 + t, 1.5, 0.0, 0.0, 0.0, 0.3]), v=1.0, w=0.0, t=t))
    tw.trace_schedule = lambda k: k % 2 == 0
    cmd = tw.bus.node("probe2").subscribe("/robot1/cmd_vel", "geometry_msgs/msg/Twist")
    res = list(tw.run(3))
    assert [t for t, _ in calls] == pytest.approx([0.05, 0.10, 0.15])
    np.testing.assert_allclose(res[1].robots["robot1"].pose[:2], [1.10, 1.5])
    assert [bool(r.links) for r in res] == [True, False, True]
    assert len(cmd.drain()) == 0  # a placed robot is not driven
    tw.reset()  # new agents, same hooks
    np.testing.assert_allclose(tw.step().robots["robot1"].pose[:2], [1.05, 1.5])
    with pytest.raises(KeyError, match="no robot named 'ghost'"):
        tw.set_state_source("ghost", None)
    tw.set_state_source("robot1", None)
    tw.trace_schedule = None
    cmd = tw.bus.node("probe3").subscribe("/robot1/cmd_vel", "geometry_msgs/msg/Twist")
    r = tw.step()
    assert r.links and len(cmd.drain()) == 1
    assert not np.allclose(r.robots["robot1"].pose[:2], [1.10, 1.5])

def test_csi_is_built_only_for_consumers_and_records_the_same(lab, tmp_path):
    """Issue 19: without a subscriber to ``/<robot>/csi`` the twin publishes no CSI and
    the PHY does not expand the channel over the symbols (one value per symbol
    group is kept); an MCAP recorded with ``--csi full`` and ``compact`` holds the
    channel the PHY computed, on every symbol, equal to the per-link synthesis
    (``NetworkPHY.channel``) at each symbol group's mean time."""
    from isac_twin.transport.record import CsiRecording, read_messages, record_twin

    tw, res = _run(lab, 2)
    assert tw.bus.registry().topic("/robot1/csi").messages == 0
    assert tw.bus.registry().topic("/robot1/scan").messages == 0  # nor scans (no subscriber)
    sig = res[-1].signals[("AP1", "robot1")]
    assert sig.time_invariant and sig.h_by_group.shape == (2, 1024, 2, 4)
    assert "h" not in vars(sig)  # not expanded: nobody read it
    assert sig.h.shape == (14, 1024, 2, 4)  # expanded on first read
    for mode, csi in (("full", CsiRecording.full()), ("compact", CsiRecording())):
        rec_tw = Twin.from_scene(lab, seed=3)
        rec_tw.set_path("robot1", {"kind": "circle", "centre": [3.0, 2.0], "radius": 1.0})
        out = tmp_path / f"{mode}.mcap"
        record_twin(rec_tw, 2, out, csi=csi)
        got = [m.decode() for m in read_messages(out, ["/robot1/csi"])]
        assert len(got) == 4  # 2 steps x 2 links
        for m in got:
            step = round(m.header.stamp / tw.dt) - 1
            s = res[step].signals[(m.tx, "robot1")]
            np.testing.assert_array_equal(m.h, s.h[::csi.symbol_step, ::csi.subcarrier_step])
            if mode == "full":  # the per-link synthesis, independent of the batched one
                t = tw.phy.grid.symbol_times
                times = np.bincount(s.group, weights=t) / np.bincount(s.group)
                ref = tw.phy.channel(res[step].links[(m.tx, "robot1")].paths, times)[s.group]
                np.testing.assert_allclose(m.h, ref, rtol=0,
                                           atol=1e-5 * np.abs(ref).max())

