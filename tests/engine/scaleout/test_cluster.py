"""engine/scaleout/cluster.py on a real 2-worker local Dask cluster (spawned processes).

"Equal" to the single-process grid means: the same points and free mask, and
per point and AP the same paths -- the same number, the same interaction types
per bounce, delays equal to float32 rounding (rtol 1e-6; stored as float64
computed from float32), gains ``a``, angles and vertices equal to float32
rounding (rtol 1e-5, atol 1e-6 of the largest value); in the runs so far they
were bit-identical. Each AP's chains are enumerated once (chain reuse v3, no
sampling) and used by every worker, and tiles are whole ``trace_grid`` chunks
(docs/scaleout.md).
"""

from __future__ import annotations

import os
import signal

import numpy as np
import pytest

from isac_twin.scaleout.checkpoint import checkpoint_dir
from isac_twin.scaleout.cluster import trace_grid_tiled

from .conftest import CHUNK, SPACING, TILE

pytestmark = pytest.mark.slow


def assert_equal_grids(ref, got):
    a, b = ref.arrays, got.arrays
    np.testing.assert_array_equal(a["points"], b["points"])
    np.testing.assert_array_equal(a["free"], b["free"])
    np.testing.assert_array_equal(a["num_paths"], b["num_paths"])
    assert a["valid"].shape == b["valid"].shape
    np.testing.assert_array_equal(a["valid"], b["valid"])
    np.testing.assert_array_equal(a["interactions"], b["interactions"])
    np.testing.assert_allclose(a["tau"], b["tau"], rtol=1e-6, atol=0)
    for k in ("a", "theta_t", "phi_t", "theta_r", "phi_r", "vertices"):
        scale = float(np.abs(a[k]).max()) or 1.0
        np.testing.assert_allclose(b[k], a[k], rtol=1e-5, atol=1e-6 * scale, err_msg=k)
    assert ref.meta["tracer"]["method"] == got.meta["tracer"]["method"] == "chains"
    for k in ("origin", "shape", "height", "tx_names", "scene_hash", "frequency_hz"):
        assert ref.meta[k] == got.meta[k], k


def tiled(scene, client, tile_size=TILE, **kw):
    return trace_grid_tiled(scene, spacing=SPACING, client=client, tile_size=tile_size,
                            chunk_size=CHUNK, progress=False, **kw)


def test_tiled_grid_and_database_equal_the_single_process_ones(room_scene, single_grid,
                                                                client):
    from isac_twin.localization.fingerprints import from_grid

    summaries = []
    got = tiled(room_scene, client, on_tile=summaries.append)
    so = got.meta["scaleout"]
    assert so["tiles"] == len(range(0, int(single_grid.free.sum()), TILE)) > 4
    assert so["workers"] == 2 and so["tiles_traced"] == so["tiles"]
    runs = so["worker_runs"]  # where the time went, per worker process
    assert sum(r["tiles"] for r in runs) == so["tiles"]
    assert all(r["trace_s"] > 0 and r["cpu_s"] > 0 and r["idle_end_s"] >= 0 for r in runs)
    assert min(r["idle_end_s"] for r in runs) == 0.0
    assert set(so["seconds"]) == {"plan", "trace", "verify", "assemble"}
    assert got.meta["verification"] == {"points": 0}  # none asked for
    assert_equal_grids(single_grid, got)
    # each AP's chains were enumerated once, by one task, and every tile used
    # those: the chains the single process enumerated
    assert sorted(c["source"] for c in so["chains"]) == [0, 1]
    assert all(c["count"] > 0 and c["shoot_s"] > 0 for c in so["chains"])
    assert all(t["sources_shot"] == 0 for t in summaries)  # no worker shot in a tile
    n_chains = single_grid.meta["tracer"]["chains"]["chains"]
    assert got.meta["tracer"]["chains"]["chains"] == n_chains
    assert sum(c["count"] for c in so["chains"]) == n_chains
    da, db = from_grid(single_grid, room_scene), from_grid(got, room_scene)
    for k, v in da.arrays.items():
        np.testing.assert_allclose(db.arrays[k], v, rtol=1e-5, equal_nan=True, err_msg=k)


def test_local_workers_import_the_tracer_stack_at_start_up(client):
    def state(dask_worker):
        import sys

        import dask
        import drjit as dr

        return ([p.name for p in dask_worker.preloads], "sionna.rt" in sys.modules,
                dr.thread_count(), dask.config.get("distributed.worker.profile.enabled"))

    for preloads, sionna_imported, threads, profiler in client.run(state).values():
        assert preloads == ["isac_twin.scaleout.preload"]
        assert sionna_imported and threads == 1
        assert profiler is False


def test_a_killed_worker_loses_no_tile(room_scene, single_grid, client):
    pids = client.run(os.getpid)  # {worker address: pid}
    killed = []

    def kill_other(tile):
        if not killed:  # after the first tile: SIGKILL the worker that did not finish it
            victim = next(p for p in pids.values() if p != tile["pid"])
            os.kill(victim, signal.SIGKILL)
            killed.append(victim)

    got = tiled(room_scene, client, on_tile=kill_other)
    assert killed
    assert got.meta["scaleout"]["tiles_traced"] == got.meta["scaleout"]["tiles"]
    assert_equal_grids(single_grid, got)
    client.wait_for_workers(2, timeout=60)  # the nanny restarted it
    assert killed[0] not in client.run(os.getpid).values()


def test_an_interrupted_build_resumes_with_the_missing_tiles(room_scene, single_grid, client,
                                                             tmp_path):
    # one-chunk tiles: the last full chunk is two tiles (shares of its
    # image-method calls), whose spans go through the checkpoint files too
    ckpt = checkpoint_dir(tmp_path / "grid.npz")
    n_tiles = -(-int(single_grid.free.sum()) // CHUNK) + 1
    seen = []

    def interrupt(tile):
        seen.append(tile["index"])
        if len(seen) == n_tiles - 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        tiled(room_scene, client, tile_size=CHUNK, checkpoints=ckpt, on_tile=interrupt)
    files = sorted(ckpt.rglob("tile-*.npz"))
    assert len(files) == n_tiles - 2
    traced = []
    got = tiled(room_scene, client, tile_size=CHUNK, checkpoints=ckpt, verify=4,
                out=tmp_path / "grid.npz", on_tile=lambda t: traced.append(t["index"]))
    so = got.meta["scaleout"]
    # points of resumed tiles are verified from their checkpointed paths
    assert got.meta["verification"]["points"] == 4 and got.meta["verification"]["links"] == 8
    assert so["tiles"] == n_tiles
    assert so["tiles_resumed"] == n_tiles - 2 and so["tiles_traced"] == 2
    assert sorted(traced) == sorted(set(range(so["tiles"])) - set(seen))
    assert_equal_grids(single_grid, got)
    assert not ckpt.exists()  # removed once the grid file is written
    assert (tmp_path / "grid.npz").is_file()


def test_a_worker_with_another_scene_state_is_refused(room_folder, client):
    from isac_twin import load_scene

    scene = load_scene(room_folder)
    scene.move_object("cabinet", position=(2.5, 0.6, 0.0))  # the folder on disk is unchanged
    with pytest.raises(ValueError, match=r"hashes to .*the client's scene"):
        tiled(scene, client)


def test_the_verification_runs_on_the_workers_as_in_one_process(room_scene, client):
    """``verify`` re-traces the same points on the workers and records the same
    ``meta["verification"]`` as ``trace_grid`` (the direct traces use the grid's
    seed)."""
    from isac_twin.raytrace.grid import trace_grid

    ref = trace_grid(room_scene, spacing=SPACING, chunk_size=CHUNK, progress=False, verify=3)
    got = tiled(room_scene, client, verify=3)
    v = got.meta["verification"]
    assert v["points"] == 3 and v["links"] == 6
    assert v["paths_grid"] > 0 and v["paths_single_calls"] > 0
    assert v == ref.meta["verification"]
    assert len(got.meta["scaleout"]["verify_s"]) == 3
