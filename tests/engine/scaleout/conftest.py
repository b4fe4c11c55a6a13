"""One small scene and one 2-worker local Dask cluster shared by the scale-out tests."""

from __future__ import annotations

import pytest

import isac_twin  # noqa: F401 - sets DRJIT_LIBLLVM_PATH before mitsuba loads
from isac_twin.scene.synthetic import ROBOT_EXTRA, SyntheticDevice, room_objects, write_scene_folder

#: the grid the tests trace (coarse) and a chunking that splits it into several
#: chunks and tiles (as a 5 cm grid does with 1024 points)
SPACING, CHUNK, TILE = 0.25, 16, 32


def small_room(folder):
    """4 x 3 x 3 m concrete room with a cabinet and a table top, two ceiling APs."""
    furniture = {"cabinet": ((3.0, 0.2, 0.0), (3.6, 0.8, 1.2)),
                 "table": ((0.4, 2.0, 0.7), (1.4, 2.8, 0.75))}
    devices = [SyntheticDevice("AP1", "access_point", "tx", (0.5, 0.5, 2.5)),
               SyntheticDevice("AP2", "access_point", "tx", (3.5, 2.5, 2.5)),
               SyntheticDevice("robot1", "robot", "rx", (2.1, 1.5, 0.0), cols=2,
                               extra=ROBOT_EXTRA)]
    return write_scene_folder(folder, room_objects((4.0, 3.0, 3.0), furniture), devices,
                              [("AP1", "robot1"), ("AP2", "robot1")],
                              tracer={"samples_per_src": 20000})


@pytest.fixture(scope="module")
def room_folder(tmp_path_factory):
    return small_room(tmp_path_factory.mktemp("scaleout_room"))


@pytest.fixture(scope="module")
def room_scene(room_folder):
    from isac_twin import load_scene

    return load_scene(room_folder)


@pytest.fixture(scope="module")
def single_grid(room_scene):
    """The single-process reference: ``trace_grid`` with the default tracer."""
    from isac_twin.raytrace.grid import trace_grid

    return trace_grid(room_scene, spacing=SPACING, chunk_size=CHUNK, progress=False, verify=0)


@pytest.fixture(scope="package")
def client():
    """One local cluster for the whole package (a start costs seconds)."""
    from isac_twin.scaleout.cluster import cluster_client

    with cluster_client(workers=2) as c:
        yield c
