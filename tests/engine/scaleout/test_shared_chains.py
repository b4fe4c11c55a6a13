"""engine/scaleout/shared_chains.py and ChainTracer.use_chains: chains enumerated in
one scene load (a worker's) and used by a tracer of another load of the same folder
give the paths of a tracer that enumerated them itself.

Two loads of one folder in this process number their Mitsuba shapes differently
(checked below), as two worker processes can: the chains travel by plane index."""

from __future__ import annotations

import numpy as np
import pytest

from .conftest import CHUNK, SPACING

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def setup(room_scene):
    import drjit as dr

    from isac_twin.raytrace.grid import GRID_SPEC_TABLE_SIZE
    from isac_twin.scaleout.tiles import TileJob, plan_grid, scene_folder

    cfg = room_scene.config.tracer
    plan = plan_grid(room_scene, None, SPACING, None, 0.0, cfg, None, CHUNK, chunk_size=CHUNK)
    job = TileJob(scene_folder=str(scene_folder(room_scene)),
                  scene_hash=room_scene.content_hash(), config=cfg, src=plan.src,
                  src_orient=plan.src_orient, chunk_size=CHUNK,
                  spec_table_size=GRID_SPEC_TABLE_SIZE,
                  worker_threads=dr.thread_count())  # keep this process's threads
    return plan, job


def tracer(cfg):
    from isac_twin.raytrace.chains import ChainTracer
    from isac_twin.raytrace.grid import GRID_SPEC_TABLE_SIZE
    from isac_twin.raytrace.solver_core import SolverCore

    return ChainTracer(SolverCore(cfg, spec_table_size=GRID_SPEC_TABLE_SIZE))


def test_shipped_chains_give_the_paths_of_chains_shot_in_place(room_scene, setup):
    from isac_twin.raytrace.grid import sorted_chunk
    from isac_twin.raytrace.planes import PlaneIndex
    from isac_twin.scaleout.tiles import shoot_source, use_shipped_chains, worker_state

    plan, job = setup
    cfg = room_scene.config.tracer
    sc = room_scene.sionna
    pts = plan.points[plan.todo[:3 * CHUNK]]
    shooter = tracer(cfg)
    want = sorted_chunk(shooter.trace(sc, plan.src, pts, source_orientations=plan.src_orient))
    assert shooter.sources_shot == len(plan.src) == 2

    # the "worker": its own load of the folder, each AP enumerated by one task
    shot = [shoot_source(job, s) for s in reversed(range(len(plan.src)))]
    worker_scene, _ = worker_state(job)
    assert worker_scene is not room_scene
    here, there = PlaneIndex(sc.mi_scene), PlaneIndex(worker_scene.sionna.mi_scene)
    assert not np.array_equal(here.canonical_shape, there.canonical_shape)  # ids differ

    user = tracer(cfg)
    use_shipped_chains(room_scene, user, job, shot)
    got = sorted_chunk(user.trace(sc, plan.src, pts, source_orientations=plan.src_orient))
    assert user.sources_shot == 0  # used, not shot
    assert sum(r["count"] for r in shot) == len(user.store) == len(shooter.store)
    # the same chains in the same order, with this load's shape ids
    for k, v in shooter.store.columns().items():
        np.testing.assert_array_equal(user.store.columns()[k], v, err_msg=k)
    assert set(got) == set(want)
    for k, v in want.items():
        np.testing.assert_array_equal(got[k], v, err_msg=k)


def test_shipped_chains_of_another_scene_or_missing_an_ap_are_refused(room_scene, setup):
    from isac_twin.scaleout.shared_chains import merge
    from isac_twin.scaleout.tiles import shoot_source, use_shipped_chains

    plan, job = setup
    cfg = room_scene.config.tracer
    shot = [shoot_source(job, s) for s in range(len(plan.src))]
    with pytest.raises(ValueError, match=r"sources \[1\], the job has 2 transmitters"):
        use_shipped_chains(room_scene, tracer(cfg), job, shot[1:])
    other = [{**r, "chains": {**r["chains"], "planes": "0" * 40}} for r in shot]
    with pytest.raises(ValueError, match="other reflection planes"):
        use_shipped_chains(room_scene, tracer(cfg), job, other)
    with pytest.raises(ValueError, match="2 scenes with different reflection planes"):
        merge([shot[0]["chains"], other[1]["chains"]])
    with pytest.raises(ValueError, match="source 2, the job has 2"):
        shoot_source(job, 2)
    ct = tracer(cfg)
    with pytest.raises(ValueError, match="a chain of source 1, but 1 sources were given"):
        ct.use_chains(room_scene.sionna, plan.src[:1], shot[1]["chains"]["columns"])
