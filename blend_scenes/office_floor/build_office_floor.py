"""Build the bundled building-scale office floor (5 GHz) and export its scene folder.

Run headless with the bpy module:

    .venv/bin/python blend_scenes/office_floor/build_office_floor.py

Writes ``office_floor.blend`` and ``scene/`` next to this file, with the
add-on's own functions (what its panel's operators call): an outer shell of
20 x 12 m (3 m high, 0.25 m concrete), a corridor along y 5..7 m, three
rooms south of it and two north of it separated by plasterboard partitions
(0.12 m) with door openings (1 m wide, 2.1 m high: the wall on each side
plus a lintel above), a desk per room, four ceiling access points and a
robot that patrols the corridor. It is the floor the scale-out benchmark
(``bench/bench_scaleout.py``) and tests trace on a Dask cluster.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import bpy  # noqa: E402

import addon  # noqa: E402
from addon import devices, modelling  # noqa: E402
from addon.exporter import export_scene  # noqa: E402

WIDTH, DEPTH, HEIGHT = 20.0, 12.0, 3.0
SHELL_WALL = 0.25
PARTITION, PARTITION_MAT = 0.12, "plasterboard"
DOOR_WIDTH, DOOR_HEIGHT = 1.0, 2.1
#: partitions stop this far short of the floor and the ceiling, m: no coplanar
#: faces (a ray meeting two coincident triangles may see either, which also
#: breaks the engine's inside/outside test of grid points)
GAP = 0.001
#: corridor between y = 5 and y = 7
CORRIDOR = (5.0, 7.0)

#: Partitions: (name, axis "x" (runs along x at fixed y) or "y", fixed coordinate,
#: from, to, door centres along the run) in m.
PARTITIONS = [
    ("Wall_Corridor_S", "x", CORRIDOR[0], 0.0, WIDTH, (3.5, 10.5, 17.0)),
    ("Wall_Corridor_N", "x", CORRIDOR[1], 0.0, WIDTH, (5.0, 15.0)),
    # room partitions end at the corridor walls' faces (no overlapping volumes)
    ("Wall_S12", "y", 7.0, 0.0, CORRIDOR[0] - PARTITION / 2, ()),
    ("Wall_S23", "y", 14.0, 0.0, CORRIDOR[0] - PARTITION / 2, ()),
    ("Wall_N12", "y", 10.0, CORRIDOR[1] + PARTITION / 2, DEPTH, ()),
]

#: one desk per room: (name, (x, y, z) bottom centre m, yaw rad)
DESKS = [("Desk_S1", (3.5, 1.2, 0.0), 0.0), ("Desk_S2", (10.5, 1.2, 0.0), 0.0),
         ("Desk_S3", (17.0, 1.2, 0.0), 0.0), ("Desk_N1", (5.0, 10.8, 0.0), 0.0),
         ("Desk_N2", (15.0, 10.8, 0.0), 0.0)]

#: ceiling APs (2 x 2, iso, V), 0.3 m below the ceiling, boresight down
APS = [("AP1", (3.5, 2.5, 2.7)), ("AP2", (17.0, 2.5, 2.7)), ("AP3", (5.0, 9.5, 2.7)),
       ("AP4", (15.0, 9.5, 2.7))]

#: the robot's closed patrol in the corridor (world x, y in m)
PATH = [(1.0, 5.6), (19.0, 5.6), (19.0, 6.4), (1.0, 6.4)]


def partition_boxes(name, axis, fixed, start, end, doors):
    """Boxes of one partition: wall pieces between the door openings plus a lintel
    above each door -> [(name, (dx, dy, dz), (x, y, z) bottom centre)]."""
    cuts = sorted(doors)
    edges = [start] + [v for c in cuts for v in (c - DOOR_WIDTH / 2, c + DOOR_WIDTH / 2)] + [end]
    boxes = []
    for k in range(0, len(edges), 2):
        a, b = edges[k], edges[k + 1]
        if b - a > 1e-6:
            boxes.append((f"{name}_{k // 2 + 1}", b - a, (a + b) / 2, GAP, HEIGHT - 2 * GAP))
    for k, c in enumerate(cuts):
        boxes.append((f"{name}_Lintel_{k + 1}", DOOR_WIDTH, c, DOOR_HEIGHT,
                      HEIGHT - GAP - DOOR_HEIGHT))
    out = []
    for bname, length, mid, z0, h in boxes:
        if axis == "x":
            out.append((bname, (length, PARTITION, h), (mid, fixed, z0)))
        else:
            out.append((bname, (PARTITION, length, h), (fixed, mid, z0)))
    return out


def build(scene=None):
    """Clear ``scene`` and build the floor in it; returns the scene."""
    scene = scene or bpy.context.scene
    for obj in list(bpy.data.objects):
        bpy.data.objects.remove(obj)
    for data in (bpy.data.meshes, bpy.data.curves, bpy.data.collections):
        for item in list(data):
            data.remove(item)
    scene.name = "office_floor"

    modelling.create_room(WIDTH, DEPTH, HEIGHT, SHELL_WALL, name="Floor",
                          wall_material="concrete", floor_material="concrete",
                          ceiling_material="plasterboard", scene=scene)
    for spec in PARTITIONS:
        for bname, dims, loc in partition_boxes(*spec):
            obj = modelling.add_box(bname, dims, loc, material=PARTITION_MAT,
                                    thickness=PARTITION,
                                    collection_name=modelling.ROOM_COLLECTION, scene=scene)
            obj.isac.room_part = "SHELL"
    for name, loc, yaw in DESKS:
        modelling.add_furniture("table", loc, yaw, name=name, scene=scene)

    for k, (name, pos) in enumerate(APS):
        # boresight (+x of the empty) pointing down: pitch +90 deg
        devices.add_access_point(name, pos, (0.0, math.pi / 2, 0.0), rows=2, cols=2,
                                 power_dbm=20.0, role="tx", symbols=(0, 14), scene=scene)
    robot = devices.add_robot("robot1", (*PATH[0], 0.0), 0.0, model="burger", cols=2,
                              antenna_offset=(0.0, 0.0, 0.25), power_dbm=10.0, role="rx",
                              scene=scene)
    curve = devices.add_path_curve("robot1_Path", PATH, closed=True, scene=scene)
    devices.set_polyline_path(robot, curve)
    devices.set_radio_settings(scene, frequency_hz=5.8e9, num_subcarriers=1024,
                               subcarrier_spacing_hz=78125.0, num_symbols=14,
                               cyclic_prefix_samples=72, twin_name="office_floor")
    scene.isac.links.clear()
    for name, _ in APS:
        devices.add_link(scene, name, "robot1")
    scene.isac.sensing_links.clear()
    scene.isac.export_directory = "//scene"
    return scene


def main() -> None:
    registered = hasattr(bpy.types.Scene, "isac")
    if not registered:
        addon.register()
    try:
        scene = build()
        report = export_scene(scene, HERE / "scene")
        bpy.context.preferences.filepaths.save_version = 0  # no .blend1 backup
        bpy.ops.wm.save_as_mainfile(filepath=str(HERE / "office_floor.blend"), compress=True)
        print(f"exported {len(report.objects)} objects, devices {report.devices}, "
              f"materials {report.materials} to {report.folder}")
    finally:
        if not registered:
            addon.unregister()


if __name__ == "__main__":
    main()
