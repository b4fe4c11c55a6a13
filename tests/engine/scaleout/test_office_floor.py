"""blend_scenes/office_floor: the building-scale bundled scene loads, its doors are
open and its partitions closed, and a coarse grid of it traces on the shared cluster."""

from __future__ import annotations

import numpy as np
import pytest

from isac_twin import bundled_scene_dir


@pytest.fixture(scope="module")
def floor():
    from isac_twin import load_scene

    return load_scene(bundled_scene_dir("office_floor"))


def test_rooms_doors_and_aps(floor):
    from isac_twin.raytrace.raw import free_points

    cfg = floor.config
    assert [d.name for d in cfg.devices if d.kind == "access_point"] == ["AP1", "AP2", "AP3",
                                                                          "AP4"]
    np.testing.assert_allclose(floor.bounds_max[:2] - floor.bounds_min[:2], (20.5, 12.5))
    z = 1.0
    pts = np.array([[3.5, 5.0, z],    # door in the corridor's south wall
                    [5.0, 7.0, z],    # door in its north wall
                    [1.0, 5.0, z],    # that wall between doors
                    [7.0, 2.5, z],    # partition between south rooms 1 and 2
                    [10.0, 9.5, z],   # partition between the north rooms
                    [3.5, 5.0, 2.5],  # lintel above the first door
                    [12.0, 6.0, z]])  # corridor
    np.testing.assert_array_equal(free_points(floor.sionna, pts),
                                  [True, True, False, False, False, False, True])


@pytest.mark.slow
def test_a_coarse_grid_of_the_floor_traces_on_the_cluster(floor, client):
    from isac_twin.scaleout.cluster import trace_grid_tiled
    from isac_twin.scaleout.tiles import TAIL_PARTS

    g = trace_grid_tiled(floor, spacing=4.0, client=client, tile_size=4, chunk_size=4,
                         progress=False)
    assert g.shape == (5, 3) and g.tx_names == ["AP1", "AP2", "AP3", "AP4"]
    # one-chunk tiles, the last full chunk in TAIL_PARTS shares
    assert g.meta["scaleout"]["tiles"] == -(-int(g.free.sum()) // 4) + TAIL_PARTS - 1
    n = g.arrays["num_paths"][g.free]
    # walls block: a point need not reach every AP, but every point reaches one
    # and every AP is reached
    assert n.shape[1] == 4 and (n.max(axis=1) > 0).all() and (n.max(axis=0) > 0).all()
