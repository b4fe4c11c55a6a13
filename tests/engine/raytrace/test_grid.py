"""engine/raytrace/grid.py: grid tracing, free-space marking, truncation, file format."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from isac_twin import device_poses
from isac_twin.raytrace.grid import (
    GRID_ARRAYS,
    GRID_FORMAT_VERSION,
    grid_points,
    load_grid,
    save_grid,
    trace_grid,
)
from isac_twin.raytrace.raw import free_points
from isac_twin.raytrace.sionna import SionnaTracer


def test_grid_points_cell_centred():
    origin, shape = grid_points((0, 0), (1.0, 0.5), 0.1)
    assert shape == (10, 5)
    np.testing.assert_allclose(origin, (0.05, 0.05))
    origin, shape = grid_points((0, 0), (1.0, 0.5), 0.1, margin=0.1)
    assert shape == (8, 3)
    with pytest.raises(ValueError, match="smaller than the spacing"):
        grid_points((0, 0), (0.05, 1), 0.1)


def test_free_points_marks_furniture_and_outside(room_scene):
    pts = np.array([[2.0, 1.5, 0.25],    # open floor
                    [3.3, 0.5, 0.25],    # inside the cabinet
                    [0.9, 2.4, 0.25],    # under the table: free
                    [-0.05, 1.5, 0.25],  # inside a wall slab
                    [5.0, 1.5, 0.25]])   # outside the room
    np.testing.assert_array_equal(free_points(room_scene.sionna, pts),
                                  [True, False, True, False, False])


def test_grid_contents(room_grid, room_scene):
    g = room_grid
    n = np.prod(g.shape)
    assert set(GRID_ARRAYS) <= set(g.arrays)
    for k, (dtype, axes) in GRID_ARRAYS.items():
        assert g.arrays[k].dtype == np.dtype(dtype), k
        assert g.arrays[k].ndim == axes.count(",") + 1, k
    assert g.points.shape == (n, 3) and g.num_paths.shape == (n, 2)
    assert g.meta["scene_hash"] == room_scene.content_hash()
    assert g.meta["tracer"]["truncation_retries"] == 0
    v = g.meta["verification"]
    assert v["points"] == 8 and v["paths_single_calls"] > 0
    assert v["paths_missing"] <= 0.05 * v["paths_single_calls"]
    assert not g.free.all() and g.free.sum() > 0.8 * n  # the cabinet footprint is not free
    assert np.all(g.num_paths[~g.free] == 0)
    assert np.all(g.num_paths[g.free] > 0)
    np.testing.assert_array_equal(g.valid.sum(-1), g.num_paths)
    # valid paths first, sorted by delay
    i = int(np.flatnonzero(g.free)[0])
    k = g.num_paths[i, 0]
    assert np.all(np.diff(g.tau[i, 0, :k]) >= 0) and not g.valid[i, 0, k:].any()


def test_grid_point_matches_sionna_tracer(room_grid, room_scene):
    """The grid's endpoint solver equals the public-API tracer at a grid point."""
    g = room_grid
    i = int(np.flatnonzero(g.free)[len(np.flatnonzero(g.free)) // 2])
    poses = device_poses(room_scene.config)
    poses["robot1"] = replace(poses["robot1"], position=tuple(g.points[i]))
    res = SionnaTracer(replace(room_scene.config.tracer, deterministic=False))(room_scene, poses)
    for s, tx in enumerate(g.tx_names):
        lp, d = res[(tx, "robot1")], g.paths(i, s)
        # Paths found by random ray sampling may differ by a few weak ones; the
        # strong (specular, low-order) set must agree.
        assert abs(lp.num_paths - len(d["tau"])) <= max(2, 0.05 * lp.num_paths)
        assert d["tau"][0] == pytest.approx(lp.tau[0], rel=1e-6)
        assert abs(d["a"][0]) == pytest.approx(abs(lp.a[0]), rel=1e-5)


def test_save_load_roundtrip_and_version(room_grid, tmp_path):
    p = save_grid(room_grid, tmp_path / "g.npz")
    g = load_grid(p)
    assert g.meta == json.loads(json.dumps(room_grid.meta))
    for k in GRID_ARRAYS:
        np.testing.assert_array_equal(g.arrays[k], room_grid.arrays[k])
    bad = dict(room_grid.meta, version=GRID_FORMAT_VERSION + 1)
    save_grid(replace(room_grid, meta=bad), tmp_path / "bad.npz")
    with pytest.raises(ValueError, match="version .* is unknown"):
        load_grid(tmp_path / "bad.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="not a readable NPZ"):
        load_grid(tmp_path / "junk.npz")
    np.savez(tmp_path / "other.npz", x=np.zeros(2))
    with pytest.raises(ValueError, match="not an isac-twin path grid"):
        load_grid(tmp_path / "other.npz")


@pytest.mark.slow
def test_truncation_detected_and_split(room_scene, caplog):
    """A tiny cap is detected: chunks are split and the cap grown, no path is lost."""
    cfg = room_scene.config.tracer
    ref = trace_grid(room_scene, spacing=1.4, progress=False, config=cfg, method="sbr")
    tiny = replace(cfg, max_num_paths_per_src=150)  # one receiver needs ~200 per source
    g = trace_grid(room_scene, spacing=1.4, progress=False, config=tiny, max_cap=1000,
                   method="sbr")
    assert g.meta["tracer"]["truncation_retries"] > 0
    assert g.meta["tracer"]["method"] == "sbr"
    np.testing.assert_array_equal(g.num_paths, ref.num_paths)
    from isac_twin.errors import TruncationError
    with pytest.raises(TruncationError, match="single receiver"):
        trace_grid(room_scene, spacing=1.4, progress=False, config=tiny, max_cap=150,
                   method="sbr")


@pytest.mark.slow
def test_chain_reuse_has_no_candidate_cap(room_scene):
    """Chain reuse enumerates its chains without Sionna's candidate buffer, so a
    cap far below the ~1,300 chains per source loses nothing (no retry needed)."""
    cfg = room_scene.config.tracer
    ref = trace_grid(room_scene, spacing=1.4, progress=False, config=cfg, method="chains",
                     verify=0)
    tiny = replace(cfg, max_num_paths_per_src=150)
    g = trace_grid(room_scene, spacing=1.4, progress=False, config=tiny, max_cap=150,
                   method="chains", verify=0)
    assert g.meta["tracer"]["chains"]["chains"] > 1000
    assert g.meta["tracer"]["truncation_retries"] == 0
    np.testing.assert_array_equal(g.num_paths, ref.num_paths)
    np.testing.assert_array_equal(g.arrays["tau"], ref.arrays["tau"])


def test_verification_tells_an_invented_path_from_a_real_one(room_scene, room_grid):
    """The grid verification matches paths one by one: a stored path moved off its
    true delay and vertices is one missing and one extra path, and the 10x-ray
    confirmation (which turns real paths the direct trace's rays missed into
    ``paths_found_more``) does not vouch for it."""
    from isac_twin.raytrace import grid as G
    from isac_twin.raytrace.base import sionna_orientation
    from isac_twin.raytrace.solver_core import SolverCore

    g = room_grid
    poses = device_poses(room_scene.config)
    src = np.array([poses[n].position for n in g.tx_names])
    so = np.array([sionna_orientation(poses[n].orientation) for n in g.tx_names])
    core = SolverCore(room_scene.config.tracer, deterministic=False,
                      spec_table_size=G.GRID_SPEC_TABLE_SIZE)
    def at(arrays):
        return {k: arrays[k][i] for k in ("num_paths", "a", "tau", "interactions", "vertices")}

    # a point whose stored paths the direct trace finds, all: on an AVX-512 machine the
    # 6th free point held a path refracted exactly on the table top's bottom edge,
    # (0.8, 2.8, 0.7), which the rays' float rounding misses there (counted as
    # grazing, below)
    for i in np.flatnonzero(g.free)[3:12]:
        args = (core, room_scene.sionna, src, so, g.points[i])
        ok = G.verify_point(*args, at(g.arrays))
        if not any(ok[k] for k in ("paths_missing", "paths_extra", "paths_repeated",
                                   "paths_found_more", "paths_grazing")):
            break
    assert ok["paths_missing"] == 0 and ok["paths_extra"] == 0 and ok["paths_repeated"] == 0
    assert ok["paths_found_more"] == 0
    arrays = {k: v.copy() for k, v in g.arrays.items()}
    arrays["tau"][i, 0, 1] += 3e-9
    arrays["vertices"][i, 0, 1] += 0.5
    bad = G.verify_point(*args, at(arrays))
    assert (bad["paths_missing"], bad["paths_extra"], bad["paths_found_more"]) == (1, 1, 0)
    assert bad["paths_grazing"] == 0
    # the same invented path with its first interaction on the table top's edge: no
    # trace can say whether it is real (float rounding), so it is counted apart
    d = np.flatnonzero(arrays["interactions"][i, 0, 1])[0]
    arrays["vertices"][i, 0, 1, d] = (0.82, 2.0, 0.75)
    edge = G.verify_point(*args, at(arrays))
    assert (edge["paths_missing"], edge["paths_extra"], edge["paths_grazing"]) == (1, 0, 1)


def test_pipelined_grid_equals_sequential(room_scene, monkeypatch):
    """Chunks arranged in numpy by a second thread while the next is evaluated
    (PIPELINE_DEPTH) give the same arrays, in the same order, as one thread."""
    import isac_twin.raytrace.grid as grid_mod

    monkeypatch.setattr(grid_mod, "PIPELINE_DEPTH", 0)
    seq = grid_mod.trace_grid(room_scene, spacing=0.25, progress=False, verify=0,
                              chunk_size=7)
    monkeypatch.setattr(grid_mod, "PIPELINE_DEPTH", 2)
    piped = grid_mod.trace_grid(room_scene, spacing=0.25, progress=False, verify=0,
                                chunk_size=7)
    assert len(np.flatnonzero(seq.free)) > 3 * 7  # several chunks in flight
    for k in GRID_ARRAYS:
        np.testing.assert_array_equal(seq.arrays[k], piped.arrays[k], err_msg=k)
