"""Scene folders for the ray-tracing tests (engine.synthetic, no Blender)."""

from __future__ import annotations

import pytest

import engine  # noqa: F401 - sets DRJIT_LIBLLVM_PATH before mitsuba loads
from engine.synthetic import (ROBOT_EXTRA, SyntheticDevice, SyntheticObject, box_mesh,
                              quad_mesh, room_objects, write_scene_folder)


def furnished_room(folder, *, size=(4.0, 3.0, 3.0), tracer=None, robot=(2.1, 1.5, 0.0),
                   ap_rows=1, ap_cols=1, links=None, extra_devices=()):
    """4 x 3 x 3 m concrete room, a cabinet (closed box) and a table top; two
    ceiling APs and one robot with open LOS to both."""
    furniture = {"cabinet": ((3.0, 0.2, 0.0), (3.6, 0.8, 1.2)),
                 "table": ((0.4, 2.0, 0.7), (1.4, 2.8, 0.75))}
    devices = [SyntheticDevice("AP1", "access_point", "tx", (0.5, 0.5, 2.5), rows=ap_rows,
                               cols=ap_cols),
               SyntheticDevice("AP2", "access_point", "tx", (3.5, 2.5, 2.5), rows=ap_rows,
                               cols=ap_cols),
               SyntheticDevice("robot1", "robot", "rx", robot, cols=2, extra=ROBOT_EXTRA),
               *extra_devices]
    links = links or [("AP1", "robot1"), ("AP2", "robot1")]
    tr = {"samples_per_src": 20000}
    tr.update(tracer or {})
    return write_scene_folder(folder, room_objects(size, furniture), devices, links, tracer=tr)


def reflector_scene(folder):
    """A large metal plane z = 0 plus a tiny far-away marker box that extends the
    scene bounds upwards; tx at (0, 0, 1), rx at (2, 0, 1.5)."""
    plane = SyntheticObject("plane", *quad_mesh([(-10, -10, 0), (10, -10, 0), (10, 10, 0),
                                                 (-10, 10, 0)]), material="metal",
                            thickness=0.01)
    marker = SyntheticObject("marker", *box_mesh((9.8, 9.8, 2.9), (9.9, 9.9, 3.0)))
    devices = [SyntheticDevice("TX", "access_point", "tx", (0.0, 0.0, 1.0)),
               SyntheticDevice("RX", "access_point", "rx", (2.0, 0.0, 1.5))]
    return write_scene_folder(folder, [plane, marker], devices, [("TX", "RX")],
                              tracer={"max_depth": 1, "refraction": False,
                                      "samples_per_src": 20000})


@pytest.fixture(scope="session")
def room_folder(tmp_path_factory):
    return furnished_room(tmp_path_factory.mktemp("room"))


@pytest.fixture(scope="session")
def room_scene(room_folder):
    from engine.scene import load_scene

    return load_scene(room_folder)


@pytest.fixture(scope="session")
def room_grid(room_scene):
    from engine.raytrace.grid import trace_grid

    return trace_grid(room_scene, spacing=0.25, progress=False)
