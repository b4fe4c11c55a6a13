"""engine/scaleout/tiles.py: the tile layout and a chunk traced in shares of its
image-method calls, against the chain tracer itself (in this process)."""

from __future__ import annotations

import numpy as np
import pytest

from isac_twin.scaleout.tiles import TAIL_PARTS, TileJob, image_method_calls, plan_grid, trace_tile

from .conftest import CHUNK, SPACING


def test_image_method_calls_cut_where_the_next_target_would_overflow():
    assert image_method_calls([3, 3, 3], 6) == [(0, 2), (2, 3)]
    assert image_method_calls([3, 3, 3], 5) == [(0, 1), (1, 2), (2, 3)]
    assert image_method_calls([9, 1], 5) == [(0, 1), (1, 2)]  # one target may exceed it
    assert image_method_calls([0, 0], 5) == [(0, 2)]
    assert image_method_calls([], 5) == []


def test_the_last_full_chunk_comes_last_in_parts(room_scene):
    cfg = room_scene.config.tracer
    plan = plan_grid(room_scene, None, SPACING, None, 0.0, cfg, None, CHUNK, chunk_size=CHUNK)
    tiles = plan.tiles
    n = len(plan.todo)
    assert n % CHUNK and n > 2 * CHUNK  # a partial last chunk: the one split is the one before
    whole = [t for t in tiles if t.parts == 1]
    split = tiles[len(whole):]
    assert [(t.part, t.parts) for t in split] == [(j, TAIL_PARTS) for j in range(TAIL_PARTS)]
    last_full = plan.todo[(n // CHUNK - 1) * CHUNK:(n // CHUNK) * CHUNK]
    assert all(np.array_equal(t.index, last_full) for t in split)
    covered = np.sort(np.concatenate([t.index for t in whole] + [last_full]))
    np.testing.assert_array_equal(covered, plan.todo)
    # tiles of several chunks are not split
    plan2 = plan_grid(room_scene, None, SPACING, None, 0.0, cfg, None, 2 * CHUNK,
                      chunk_size=CHUNK)
    assert all(t.parts == 1 for t in plan2.tiles)


@pytest.mark.slow
def test_a_chunk_traced_in_shares_equals_the_whole_chunk(room_scene):
    """The shares' spans tile the chunk and their paths are bit-identical to one
    ``ChainTracer.trace`` of the chunk with the same ``max_pairs``, set so that
    the chunk takes several image-method calls."""
    import drjit as dr

    from isac_twin.raytrace.chains import ChainTracer
    from isac_twin.raytrace.grid import GRID_SPEC_TABLE_SIZE, sorted_chunk
    from isac_twin.raytrace.solver_core import SolverCore
    from isac_twin.scaleout.cluster import assemble
    from isac_twin.scaleout.tiles import scene_folder, storage_dtypes

    cfg = room_scene.config.tracer
    plan = plan_grid(room_scene, None, SPACING, None, 0.0, cfg, None, CHUNK, chunk_size=CHUNK)
    idx = plan.todo[:CHUNK]
    pts = plan.points[idx]
    sc = room_scene.sionna
    probe = ChainTracer(SolverCore(cfg, spec_table_size=GRID_SPEC_TABLE_SIZE))
    probe.trace(sc, plan.src, pts[:1], source_orientations=plan.src_orient)
    pairs = [len(p) for p in probe.prepare(sc, plan.src, pts)]
    max_pairs = sum(pairs) // 4
    assert len(image_method_calls(pairs, max_pairs)) >= 4
    ref_ct = ChainTracer(SolverCore(cfg, spec_table_size=GRID_SPEC_TABLE_SIZE),
                         max_pairs=max_pairs)
    ref = storage_dtypes(sorted_chunk(ref_ct.trace(sc, plan.src, pts,
                                                   source_orientations=plan.src_orient)))
    want = assemble(plan, [(idx, [ref])], cfg.max_depth)
    job = TileJob(scene_folder=str(scene_folder(room_scene)),
                  scene_hash=room_scene.content_hash(), config=cfg, src=plan.src,
                  src_orient=plan.src_orient, chunk_size=CHUNK, max_pairs=max_pairs,
                  worker_threads=dr.thread_count())  # keep this process's threads
    for parts in (2, 3):
        got = [trace_tile(job, 0, pts, j, parts) for j in range(parts)]
        spans = [g["span"] for g in got]
        assert spans[0][0] == 0 and spans[-1][1] == CHUNK
        assert all(s[1] == t[0] for s, t in zip(spans, spans[1:]))
        assert all(s[1] > s[0] for s in spans)  # >= 4 calls: no share is empty
        have = assemble(plan, [(idx[a:b], g["parts"]) for g, (a, b) in zip(got, spans)],
                        cfg.max_depth)
        for k, v in want.items():
            np.testing.assert_array_equal(have[k], v, err_msg=f"{parts} parts: {k}")
    with pytest.raises(ValueError, match="one chunk"):
        trace_tile(job, 0, plan.points[plan.todo[:CHUNK + 1]], 0, 2)
