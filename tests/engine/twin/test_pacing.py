"""engine/twin/pacing.py: paced runs on the small lab: overruns named by their stage
or the caller, the start-up step outside the schedule, the per-stage clock."""

import gc
import time

import pytest

from isac_twin import Twin
from isac_twin.twin.pacing import STAGES

pytestmark = pytest.mark.slow


def test_paced_run_names_the_stage_of_each_overrun(lab):
    """A paced run counts an overrun against the step's longest stage, or against
    the caller when the consumer of a result held the loop (issue #19)."""
    tw = Twin.from_scene(lab, seed=1, phy=False)
    tw.estimators.append(lambda twin, res: time.sleep(0.4) if res.step == 1 else None)
    for res in tw.run(4, rate_hz=4.0):  # period 250 ms; normal steps take far less
        if res.step == 2:
            time.sleep(0.4)
    st = tw.stats
    assert st.overrun_stages.get("estimate") == 1 and st.overrun_stages.get("caller") == 1
    assert st.overruns == sum(st.overrun_stages.values()) and st.overrun_ms >= 2 * 150
    assert "estimate 1" in st.overrun_summary() and "caller 1" in st.table()
    with pytest.raises(ValueError, match="rate_hz"):
        list(tw.run(1, rate_hz=0))


def test_paced_run_starts_its_schedule_after_the_start_up_step(lab):
    """The twin's first step (chains, kernel recording: ~1.2 s for 4 robots) is
    the paced run's start-up, not an overrun; the schedule starts after it, and
    the objects alive then are frozen out of the cyclic GC (its full
    collections took ~30 ms, an overrun at 20 Hz). Before, step 0 was always
    an overrun of ~1.2 s."""
    tw = Twin.from_scene(lab, seed=1, phy=False)
    tw.estimators.append(lambda twin, res: time.sleep(0.4) if res.step == 0 else None)
    list(tw.run(3, rate_hz=4.0))
    st = tw.stats
    assert st.startup_s >= 0.4 and st.overruns == 0, st.overrun_summary()
    assert "start-up" in st.overrun_summary() and gc.get_freeze_count() > 0
    tw.estimators.append(lambda twin, res: time.sleep(0.4))
    list(tw.run(1, rate_hz=4.0))  # a later run has no start-up step: an overrun
    assert tw.stats.overruns == 1 and tw.stats.overrun_stages == {"estimate": 1}
    gc.unfreeze()


def test_a_slow_csi_consumer_is_timed_and_named_as_the_publish_stage(lab):
    """The step's result and its CSI publication (a recorder's synchronous
    callback) are a timed stage, ``publish``: an overrun there is named so, not
    charged to another stage (issue #19; before, that time was in no stage)."""
    tw = Twin.from_scene(lab, seed=1, sensing=False)
    tw.step()  # compiles the tracer's kernels
    tw.bus.node("slow_recorder").subscribe(
        "/robot1/csi", "isac_twin_msgs/msg/Csi",
        lambda m: time.sleep(0.4) if m.tx == "AP1" else None)
    res = list(tw.run(2, rate_hz=4.0))  # 250 ms period: the callback overruns it
    assert "publish" in STAGES and all(r.timings_s["publish"] >= 0.4 for r in res)
    assert tw.stats.stage_s["publish"] >= 0.8
    assert tw.stats.overrun_stages == {"publish": 2}

