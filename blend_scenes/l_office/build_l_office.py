"""Build the bundled L-shaped office at 5.8 GHz and export its scene folder.

Run headless with the bpy module:

    .venv/bin/python blend_scenes/l_office/build_l_office.py

Writes ``l_office.blend`` and ``scene/`` next to this file. Everything is
made with the add-on's own functions (what its panel's operators call): a
room from a polygon footprint, a window, a glass partition, furniture
presets, two access points and a robot that drives a closed path drawn as a
Blender curve. The room's inside is the L
(0, 0) - (10, 0) - (10, 4) - (6, 4) - (6, 7) - (0, 7), 3 m high; the corner
x > 6, y > 4 is outside.
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

FOOTPRINT = [(0.0, 0.0), (10.0, 0.0), (10.0, 4.0), (6.0, 4.0), (6.0, 7.0), (0.0, 7.0)]
HEIGHT, WALL = 3.0, 0.2
#: the robot's closed path (world x, y in m), drawn as a cyclic poly curve
PATH = [(1.5, 1.5), (8.0, 1.5), (8.0, 2.8), (4.5, 2.8), (4.5, 5.5), (1.5, 5.5)]
CLEARANCE = 0.35  #: furniture keeps this far from the path, m

# (preset, name, (x, y, z) bottom centre in m, yaw in rad, material override or None)
FURNITURE = [
    ("table", "Desk_1", (3.0, 4.2, 0.0), 0.0, None),
    ("chair", "Chair_1", (3.0, 3.45, 0.0), 0.0, None),
    ("table", "Desk_2", (6.0, 0.5, 0.0), 0.0, None),
    ("cabinet", "Cabinet_1", (0.6, 6.55, 0.0), 0.0, None),
    ("rack", "Rack_1", (9.5, 0.6, 0.0), 0.0, None),
    ("cabinet", "Shelf_1", (2.0, 6.7, 0.0), 0.0, "wood"),
]


def _segment_distance(p, a, b) -> float:
    ax, ay = b[0] - a[0], b[1] - a[1]
    t = max(0.0, min(1.0, ((p[0] - a[0]) * ax + (p[1] - a[1]) * ay) / (ax * ax + ay * ay)))
    return math.hypot(p[0] - a[0] - t * ax, p[1] - a[1] - t * ay)


def _box_path_gap(dims, loc, yaw) -> float:
    """Smallest distance (m) from the path to a furniture footprint's corners and centre
    (a coarse check of the build, the engine checks free space exactly at load)."""
    c, s = math.cos(yaw), math.sin(yaw)
    pts = [(loc[0] + c * x - s * y, loc[1] + s * x + c * y)
           for x in (-dims[0] / 2, 0.0, dims[0] / 2) for y in (-dims[1] / 2, 0.0, dims[1] / 2)]
    segs = list(zip(PATH, PATH[1:] + PATH[:1]))
    return min(_segment_distance(p, a, b) for p in pts for a, b in segs)


def build(scene=None):
    """Clear ``scene`` and build the office in it; returns the scene."""
    scene = scene or bpy.context.scene
    for obj in list(bpy.data.objects):
        bpy.data.objects.remove(obj)
    for data in (bpy.data.meshes, bpy.data.curves, bpy.data.collections):
        for item in list(data):
            data.remove(item)
    scene.name = "l_office"

    room = modelling.create_room_from_polygon(
        FOOTPRINT, HEIGHT, WALL, name="Room", wall_material="concrete",
        floor_material="concrete", ceiling_material="plasterboard", scene=scene)
    # south wall (Room_Wall_1, y in [-0.2, 0]): a 2.4 m x 1.4 m window, sill at 0.8 m
    modelling.add_window(room["walls"][0], (3.0, -WALL / 2, 1.5), 2.4, 1.4,
                         name="Room_Window", pane_thickness=0.01, scene=scene)
    # a full-height glass partition in the east arm, from its north wall down to y = 2.2
    glass = modelling.add_box("Glass_Partition", (0.02, 1.8, HEIGHT), (9.0, 3.1, 0.0),
                              material="glass", thickness=0.02,
                              collection_name=modelling.ROOM_COLLECTION, scene=scene)
    glass.isac.room_part = "SHELL"
    for kind, name, loc, yaw, mat in FURNITURE:
        dims = modelling.FURNITURE_PRESETS[kind]["dimensions"]
        gap = _box_path_gap(dims, loc, yaw)
        if gap < CLEARANCE:
            raise RuntimeError(f"{name} is {gap:.2f} m from the robot's path")
        modelling.add_furniture(kind, loc, yaw, name=name, material=mat, scene=scene)

    # AP1 (4 x 4) high on the west wing's north wall facing -y; AP2 (2 x 2) on the east
    # wall facing -x; disjoint OFDM symbols as in the lab.
    devices.add_access_point("AP1", (3.0, 6.95, 2.5), (0.0, 0.0, -math.pi / 2), rows=4,
                             cols=4, power_dbm=20.0, role="tx", symbols=(0, 7), scene=scene)
    devices.add_access_point("AP2", (9.95, 1.2, 2.5), (0.0, 0.0, math.pi), rows=2, cols=2,
                             power_dbm=20.0, role="tx", symbols=(7, 14), scene=scene)
    robot = devices.add_robot("robot1", (*PATH[0], 0.0), 0.0, model="burger", cols=2,
                              antenna_offset=(0.0, 0.0, 0.25), power_dbm=10.0, role="rx",
                              scene=scene)
    curve = devices.add_path_curve("robot1_Path", PATH, closed=True, scene=scene)
    devices.set_polyline_path(robot, curve)
    devices.set_radio_settings(scene, frequency_hz=5.8e9, num_subcarriers=1024,
                               subcarrier_spacing_hz=78125.0, num_symbols=14,
                               cyclic_prefix_samples=72, twin_name="l_office")
    scene.isac.links.clear()
    devices.add_link(scene, "AP1", "robot1")
    devices.add_link(scene, "AP2", "robot1")
    # bistatic radar: AP2 (2 x 2) illuminates, AP1's 4 x 4 array receives (angles);
    # a quarter of the REs, every 10th step, as in the lab
    scene.isac.sensing_links.clear()
    devices.add_sensing_link(scene, "AP2", "AP1", rho=0.25, every=10)
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
        bpy.ops.wm.save_as_mainfile(filepath=str(HERE / "l_office.blend"), compress=True)
        print(f"exported {len(report.objects)} objects, devices {report.devices}, "
              f"materials {report.materials} to {report.folder}")
    finally:
        if not registered:
            addon.unregister()


if __name__ == "__main__":
    main()
