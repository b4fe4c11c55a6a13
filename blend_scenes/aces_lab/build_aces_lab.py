"""Build the bundled ACES lab (modelled after the paper's lab) and export its scene folder.

Run headless with the bpy module:

    .venv/bin/python blend_scenes/aces_lab/build_aces_lab.py

Writes ``aces_lab.blend`` and ``scene/`` next to this file. The room's
inside spans [0, 8] x [0, 6] x [0, 3] m with the origin at a floor corner.
A circle of centre (4, 3) and radius 1.5 m (plus a 0.35 m margin) stays
free of furniture: the robot drives it.
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

WIDTH, DEPTH, HEIGHT, WALL = 8.0, 6.0, 3.0, 0.2
FREE_CENTRE, FREE_RADIUS = (4.0, 3.0), 1.5 + 0.35

# (preset, name, (x, y, z) bottom centre in m, yaw in rad)
FURNITURE = [
    ("table", "Table_1", (1.2, 0.6, 0.0), 0.0),
    ("table", "Table_2", (3.4, 0.6, 0.0), 0.0),
    ("table", "Table_3", (0.6, 4.2, 0.0), math.pi / 2),
    ("chair", "Chair_1", (1.2, 1.3, 0.0), 0.0),
    ("chair", "Chair_2", (2.5, 1.3, 0.0), 0.0),
    ("chair", "Chair_3", (1.3, 4.2, 0.0), math.pi / 2),
    ("rack", "Rack_1", (7.4, 0.8, 0.0), 0.0),
    ("rack", "Rack_2", (7.4, 5.2, 0.0), 0.0),
    ("switch_box", "SwitchBox_1", (5.6, 0.16, 1.2), 0.0),
    ("switch_box", "SwitchBox_2", (7.84, 3.0, 1.2), math.pi / 2),
]


def distance_to_box(point, dims, location, yaw) -> float:
    """Distance (m) from an XY point to a furniture footprint (0 inside)."""
    c, s = math.cos(-yaw), math.sin(-yaw)
    px, py = point[0] - location[0], point[1] - location[1]
    lx, ly = c * px - s * py, s * px + c * py
    ex = max(abs(lx) - dims[0] / 2, 0.0)
    ey = max(abs(ly) - dims[1] / 2, 0.0)
    return math.hypot(ex, ey)


def build(scene=None):
    """Clear ``scene`` and build the lab in it; returns the scene."""
    scene = scene or bpy.context.scene
    for obj in list(bpy.data.objects):
        bpy.data.objects.remove(obj)
    for mesh in list(bpy.data.meshes):
        bpy.data.meshes.remove(mesh)
    for coll in list(bpy.data.collections):
        bpy.data.collections.remove(coll)
    scene.name = "aces_lab"

    room = modelling.create_room(WIDTH, DEPTH, HEIGHT, WALL, name="Lab",
                                 wall_material="concrete", floor_material="concrete",
                                 ceiling_material="ceiling_board", scene=scene)
    # north wall (Lab_Wall_3, y in [6, 6.2]): a 2 m x 1.2 m window, sill at 0.9 m
    modelling.add_window(room["walls"][2], (2.5, DEPTH + WALL / 2, 1.5), 2.0, 1.2,
                         name="Lab_Window", pane_thickness=0.01, scene=scene)

    for kind, name, loc, yaw in FURNITURE:
        dims = modelling.FURNITURE_PRESETS[kind]["dimensions"]
        gap = distance_to_box(FREE_CENTRE, dims, loc, yaw)
        if gap < FREE_RADIUS:
            raise RuntimeError(f"{name} intrudes into the robot's circle ({gap:.2f} m)")
        modelling.add_furniture(kind, loc, yaw, name=name, scene=scene)

    # AP1 on the west wall (x = 0) facing +x into the room; AP2 on the south wall facing +y.
    # They share the band but not the time: AP1 sends on OFDM symbols 0-6, AP2 on 7-13,
    # so each link's rate is its own (the paper plots them side by side, not interfering).
    devices.add_access_point("AP1", (0.05, 3.0, 2.0), (0.0, 0.0, 0.0), rows=4, cols=8,
                             vertical_spacing=0.5, horizontal_spacing=0.5, pattern="iso",
                             polarization="V", power_dbm=20.0, role="tx", symbols=(0, 7),
                             scene=scene)
    devices.add_access_point("AP2", (4.0, 0.05, 2.0), (0.0, 0.0, math.pi / 2), rows=1, cols=1,
                             pattern="iso", polarization="V", power_dbm=20.0, role="tx",
                             symbols=(7, 14), scene=scene)
    robot = devices.add_robot("robot1", (5.5, 3.0, 0.0), math.pi / 2, model="burger", rows=1,
                              cols=2, antenna_offset=(0.0, 0.0, 0.25), pattern="iso",
                              polarization="V", power_dbm=10.0, role="rx", scene=scene)
    # The paper's circular path (section IV), counter-clockwise from the start pose.
    devices.set_circle_path(robot, FREE_CENTRE, 1.5, "ccw")
    devices.set_radio_settings(scene, frequency_hz=2.4e9, num_subcarriers=1024,
                               subcarrier_spacing_hz=78125.0, num_symbols=14,
                               cyclic_prefix_samples=72, twin_name="aces_lab")
    scene.isac.links.clear()
    devices.add_link(scene, "AP1", "robot1")
    devices.add_link(scene, "AP2", "robot1")
    # Bistatic radar: AP2 (1x1) illuminates, AP1's 4x8 array receives (angles);
    # a quarter of the REs, every 10th step: 0.5 s between frames at the default
    # 50 ms step, the rate the tracker was validated at (docs/sensing.md).
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
        bpy.context.preferences.filepaths.save_version = 0  # no aces_lab.blend1 backup
        bpy.ops.wm.save_as_mainfile(filepath=str(HERE / "aces_lab.blend"), compress=True)
        print(f"exported {len(report.objects)} objects, devices {report.devices}, "
              f"materials {report.materials} to {report.folder}")
    finally:
        if not registered:
            addon.unregister()


if __name__ == "__main__":
    main()
