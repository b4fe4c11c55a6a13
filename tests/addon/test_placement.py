"""addon/placement.py: the panel's free-space warnings agree with the engine's load check."""

from __future__ import annotations

import pytest

bpy = pytest.importorskip("bpy")

pytestmark = pytest.mark.blender


def l_scene(scene):
    """An L room (corner x > 4, y > 3 cut out), a desk, an AP and a robot."""
    from addon import devices, modelling

    modelling.create_room_from_polygon([(0, 0), (6, 0), (6, 3), (4, 3), (4, 5), (0, 5)], 3.0,
                                       0.2, name="Room", scene=scene)
    modelling.add_furniture("table", (2.0, 4.0, 0.0), name="Desk", scene=scene)
    devices.add_access_point("AP1", (0.1, 2.5, 2.2), scene=scene)
    robot = devices.add_robot("robot1", (1.0, 1.0, 0.0), 0.0, scene=scene)
    devices.add_link(scene, "AP1", "robot1")
    return scene, robot


@pytest.mark.parametrize("case, want", [
    ("free", None),
    ("robot_in_desk", "Device 'robot1' at (2.00, 4.00, 0.00) lies in object 'Desk'"),
    ("robot_in_cutout", "Device 'robot1' at (5.00, 4.00, 0.00) lies in no floor"),
    ("ap_in_wall", "Device 'AP1' at (-0.10, 2.50, 2.20) lies in object 'Room_Wall_6'"),
    ("path_through_desk", "Device 'robot1': its polyline path point"),
    ("circle_into_wall", "Device 'robot1': its circle path point"),
])
def test_warnings_match_the_engine(scene, tmp_path, case, want):
    from addon import devices
    from addon.exporter import export_scene
    from addon.placement import placement_warnings
    from isac_twin import ConfigError, load_scene

    scene, robot = l_scene(scene)
    if case == "robot_in_desk":
        robot.location = (2.0, 4.0, 0.0)
    elif case == "robot_in_cutout":
        robot.location = (5.0, 4.0, 0.0)
    elif case == "ap_in_wall":
        scene.objects["AP1"].location = (-0.1, 2.5, 2.2)
    elif case == "path_through_desk":
        devices.set_polyline_path(robot, devices.add_path_curve(
            "P", [(1.0, 1.0), (2.0, 4.5)], scene=scene))
    elif case == "circle_into_wall":
        devices.set_circle_path(robot, (3.0, 2.0), 1.5)
    elif case == "free":
        devices.set_rectangle_path(robot, (2.0, 1.5), 2.0, 1.0, scene=scene)
    bpy.context.view_layer.update()
    lines = placement_warnings(scene, bpy.context.evaluated_depsgraph_get())
    export_scene(scene, tmp_path, interchange=False)  # export itself does not refuse
    if want is None:
        assert lines == []
        load_scene(tmp_path, load_sionna=False)
    else:
        assert len(lines) == 1 and lines[0].startswith(want), lines
        with pytest.raises(ConfigError, match="not in free space"):
            load_scene(tmp_path, load_sionna=False)


def test_check_operator_stores_warnings_for_the_panel(scene):
    scene, robot = l_scene(scene)
    robot.location = (2.0, 4.0, 0.0)
    bpy.context.view_layer.update()
    assert bpy.ops.isac.check_placement() == {"FINISHED"}
    assert "lies in object 'Desk'" in scene.isac.placement_warnings
    robot.location = (1.0, 1.0, 0.0)
    bpy.context.view_layer.update()
    bpy.ops.isac.check_placement()
    assert scene.isac.placement_warnings == ""
