"""engine/phy/threads.py: the twin steps with BLAS on one thread."""

from pathlib import Path

import numpy as np
import pytest
from threadpoolctl import threadpool_info

from engine.phy.threads import one_blas_thread

LAB = Path(__file__).resolve().parents[3] / "blend_scenes" / "aces_lab" / "scene"


def _blas_threads():
    np.ones((4, 4)) @ np.ones((4, 4))  # (numpy's BLAS is loaded)
    return [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]


def test_one_blas_thread_inside_and_the_old_count_after():
    before = _blas_threads()
    assert before
    with one_blas_thread():
        assert set(_blas_threads()) == {1}
    assert _blas_threads() == before


@pytest.mark.slow
def test_the_twin_steps_with_one_blas_thread():
    from engine.twin import Twin

    seen = []
    tw = Twin.from_scene(LAB, dt=0.05, sensing=False, localize=False,
                         estimators=[lambda twin, result: seen.append(_blas_threads())])
    tw.step()  # (its first step may import a library with a BLAS of its own)
    tw.step()
    assert len(seen) == 2 and set(seen[1]) == {1}
