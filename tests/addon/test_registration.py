"""Registration, properties, operators and panels of the add-on (headless bpy)."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path
from types import SimpleNamespace

import pytest

bpy = pytest.importorskip("bpy")

pytestmark = pytest.mark.blender

ADDON_DIR = Path(__file__).resolve().parents[2] / "addon"


def test_manifest_and_bl_info(addon_module):
    manifest = tomllib.loads((ADDON_DIR / "blender_manifest.toml").read_text())
    assert manifest["schema_version"] == "1.0.0"
    assert manifest["id"] == "isac_twin"
    assert manifest["blender_version_min"] == "4.2.0"
    # the Extensions Platform does not list Apache-2.0; the live view opens sockets
    assert manifest["license"] == ["SPDX:GPL-3.0-or-later"]
    assert "network" in manifest["permissions"]
    assert addon_module.bl_info["blender"] == (4, 2, 0)


def test_addon_never_imports_the_engine():
    """Standard library and what Blender ships only: numpy is part of every Blender's
    Python (and of the bpy module), and only the live view uses it (the packed rays of
    wire 1.3 go from the socket's bytes into the curves with numpy.frombuffer); the
    contract package the engine imports too stays stdlib-only, with relative imports."""
    for path in ADDON_DIR.rglob("*.py"):
        text = path.read_text()
        assert not re.search(r"^\s*(from|import)\s+isac_twin", text, re.M), path
        assert "import engine" not in text and "from engine" not in text, path
        if "contract" in path.parts:
            assert "import bpy" not in text and "from addon" not in text, path
        for heavy in ("sionna", "mitsuba"):
            assert f"import {heavy}" not in text and f"from {heavy}" not in text, path
        if path.name != "live_view.py":
            assert "import numpy" not in text and "from numpy" not in text, path


def test_registered_types(addon_module):
    assert hasattr(bpy.types.Object, "isac")
    assert hasattr(bpy.types.Scene, "isac")
    for name in ("ISAC_PT_scene", "ISAC_PT_modelling", "ISAC_PT_object", "ISAC_PT_links"):
        panel = getattr(bpy.types, name)
        assert panel.bl_space_type == "VIEW_3D" and panel.bl_category == "ISAC Twin"
    for op in ("add_room", "add_room_polygon", "add_furniture", "add_access_point", "add_robot",
               "tag_material", "add_link", "remove_link", "export_scene"):
        assert hasattr(bpy.ops.isac, op), op


def test_operators_are_undoable(addon_module):
    from addon import operators

    for cls in operators.CLASSES:
        assert {"REGISTER", "UNDO"} <= set(cls.bl_options), cls.bl_idname


def test_default_properties(scene):
    p = scene.isac
    assert p.frequency_hz == pytest.approx(2.4e9)
    assert (p.num_subcarriers, p.num_symbols, p.cyclic_prefix_samples) == (1024, 14, 72)
    assert p.subcarrier_spacing_hz == 78125.0
    cube = bpy.data.objects.new("c", bpy.data.meshes.new("c"))
    scene.collection.objects.link(cube)
    assert cube.isac.itu_material == "none" and cube.isac.device_kind == "NONE"
    cube.isac.itu_material = "floorboard"
    assert cube.isac.itu_material == "floorboard"


def test_operator_add_room_and_polygon(scene):
    assert bpy.ops.isac.add_room(width=4.0, depth=3.0, height=2.5, wall_thickness=0.1,
                                 name="R") == {"FINISHED"}
    names = {o.name for o in scene.objects}
    assert {"R_Floor", "R_Ceiling", "R_Wall_1", "R_Wall_4"} <= names
    assert bpy.ops.isac.add_room_polygon(vertices="0,0; 5,0; 5,5; 0,5; -2,2", height=3.0,
                                         name="P") == {"FINISHED"}
    assert "P_Wall_5" in {o.name for o in scene.objects}
    with pytest.raises(RuntimeError, match="at least 3 vertices"):
        bpy.ops.isac.add_room_polygon(vertices="0,0; 1,1", name="Bad")


def test_operator_furniture_devices_links(scene):
    assert bpy.ops.isac.add_furniture(kind="rack", location=(1, 2, 0), rotation_z=0.5) == {"FINISHED"}
    rack = scene.objects["Rack"]
    assert rack.isac.itu_material == "metal"
    assert rack.rotation_euler.z == pytest.approx(0.5)
    assert bpy.ops.isac.add_access_point(name="AP", rows=2, cols=4) == {"FINISHED"}
    assert bpy.ops.isac.add_robot(name="bot", model="waffle") == {"FINISHED"}
    ap, bot = scene.objects["AP"], scene.objects["bot"]
    assert ap.type == "EMPTY" and ap.isac.device_kind == "ACCESS_POINT"
    assert (ap.isac.array_rows, ap.isac.array_cols) == (2, 4)
    assert bot.isac.device_kind == "ROBOT" and bot.isac.robot_model == "waffle"
    assert bpy.ops.isac.add_link(tx="AP", rx="bot") == {"FINISHED"}
    assert [(li.tx, li.rx) for li in scene.isac.links] == [("AP", "bot")]
    assert bpy.ops.isac.remove_link() == {"FINISHED"}
    assert len(scene.isac.links) == 0


def test_operators_a_user_needs_without_scripting(scene):
    """Floor material of a polygon room, a plain box of any material and room part, AP
    spacing and resource set, and a path preset on the active robot."""
    assert bpy.ops.isac.add_room_polygon(vertices="0,0; 6,0; 6,3; 4,3; 4,5; 0,5", name="L",
                                         floor_material="wood",
                                         ceiling_material="plasterboard") == {"FINISHED"}
    assert scene.objects["L_Floor"].isac.itu_material == "wood"
    assert scene.objects["L_Ceiling"].isac.itu_material == "plasterboard"
    assert scene.objects["L_Wall_3"].isac.room_part == "SHELL"
    assert bpy.ops.isac.add_box(name="Partition", dimensions=(0.02, 2.0, 3.0),
                                location=(2.0, 1.0, 0.0), material="glass", thickness=0.02,
                                room_part="SHELL") == {"FINISHED"}
    box = scene.objects["Partition"]
    assert box.isac.itu_material == "glass" and box.isac.room_part == "SHELL"
    assert tuple(round(d, 6) for d in box.dimensions) == (0.02, 2.0, 3.0)
    assert bpy.ops.isac.add_access_point(name="AP", rows=2, cols=2, vertical_spacing=0.7,
                                         horizontal_spacing=0.6, subcarriers=(0, 512),
                                         symbols=(7, 14)) == {"FINISHED"}
    ap = scene.objects["AP"].isac
    assert (ap.vertical_spacing, ap.horizontal_spacing) == pytest.approx((0.7, 0.6))
    assert (ap.subcarrier_start, ap.subcarrier_stop, ap.symbol_start, ap.symbol_stop) == \
        (0, 512, 7, 14)
    bpy.ops.isac.add_robot(name="bot", location=(1.0, 1.0, 0.0))
    bot = scene.objects["bot"]
    with pytest.raises(RuntimeError, match="Select a robot first"):
        with bpy.context.temp_override(active_object=scene.objects["AP"]):
            bpy.ops.isac.robot_path_preset(preset="circle")
    with bpy.context.temp_override(active_object=bot):
        assert bpy.ops.isac.robot_path_preset(preset="rectangle", centre=(2.0, 2.0), width=2.0,
                                              depth=1.0) == {"FINISHED"}
    assert bot.isac.path_kind == "polyline" and bot.isac.path_curve.name == "bot_Path"
    from addon.devices import curve_waypoints

    assert curve_waypoints(bot.isac.path_curve) == (
        [[1.0, 1.5], [3.0, 1.5], [3.0, 2.5], [1.0, 2.5]], True)
    with bpy.context.temp_override(active_object=bot):
        bpy.ops.isac.robot_path_preset(preset="figure_eight", centre=(2.0, 2.0), width=1.5)
    assert bot.isac.path_kind == "figure_eight" and bot.isac.path_size == pytest.approx(1.5)


def test_operator_tag_material(scene):
    bpy.ops.isac.add_furniture(kind="table")
    bpy.ops.isac.add_furniture(kind="chair")
    objs = [scene.objects["Table"], scene.objects["Chair"]]
    with bpy.context.temp_override(selected_objects=objs):
        assert bpy.ops.isac.tag_material(material="plywood", thickness=0.05) == {"FINISHED"}
    assert all(o.isac.itu_material == "plywood" for o in objs)
    assert all(o.isac.thickness == pytest.approx(0.05) for o in objs)


def test_operator_export(scene, tmp_path):
    bpy.ops.isac.add_room(width=3.0, depth=3.0, height=2.0)
    assert bpy.ops.isac.export_scene(directory=str(tmp_path)) == {"FINISHED"}
    assert (tmp_path / "scene.xml").is_file() and (tmp_path / "twin.toml").is_file()
    scene.objects["Room_Floor"].isac.itu_material = "floorboard"
    with pytest.raises(RuntimeError, match="Room_Floor.*floorboard"):
        bpy.ops.isac.export_scene(directory=str(tmp_path / "bad"))


def test_scene_panel_draws_settings_and_band_warning(scene, layout_stub):
    from addon import panels

    bpy.ops.isac.add_room(width=3.0, depth=3.0, height=2.0)
    scene.objects["Room_Floor"].isac.itu_material = "floorboard"
    panels.ISAC_PT_scene.draw(SimpleNamespace(layout=layout_stub), SimpleNamespace(scene=scene))
    calls = layout_stub.calls
    for key in ("frequency_hz", "num_subcarriers", "subcarrier_spacing_hz", "num_symbols",
                "cyclic_prefix_samples", "export_directory"):
        assert ("prop", key) in calls, key
    assert ("operator", "isac.export_scene") in calls
    warnings = [c for c in calls if c[0] == "label" and c[2] == "ERROR"]
    assert len(warnings) == 1
    assert "Room_Floor" in warnings[0][1] and "floorboard" in warnings[0][1]
    assert "2.4 GHz" in warnings[0][1]


def test_object_panel_geometry_and_device(scene, layout_stub):
    from addon import devices, modelling, panels

    table = modelling.add_furniture("table", scene=scene)
    panels.ISAC_PT_object.draw(SimpleNamespace(layout=layout_stub),
                               SimpleNamespace(scene=scene, active_object=table))
    assert {("prop", "itu_material"), ("prop", "thickness"),
            ("operator", "isac.tag_material")} <= set(layout_stub.calls)
    layout_stub.calls.clear()
    bot = devices.add_robot("bot", scene=scene)
    panels.ISAC_PT_object.draw(SimpleNamespace(layout=layout_stub),
                               SimpleNamespace(scene=scene, active_object=bot))
    drawn = {c[1] for c in layout_stub.calls if c[0] == "prop"}
    assert {"role", "power_dbm", "robot_model", "antenna_offset", "array_rows", "array_cols",
            "vertical_spacing", "horizontal_spacing", "pattern", "polarization"} <= drawn
    assert "itu_material" not in drawn


def test_modelling_and_links_panels(scene, layout_stub):
    from addon import panels

    ctx = SimpleNamespace(scene=scene, active_object=None)
    panels.ISAC_PT_modelling.draw(SimpleNamespace(layout=layout_stub), ctx)
    panels.ISAC_PT_links.draw(SimpleNamespace(layout=layout_stub), ctx)
    panels.ISAC_PT_object.draw(SimpleNamespace(layout=layout_stub), ctx)
    ops = {c[1] for c in layout_stub.calls if c[0] == "operator"}
    assert {"isac.add_room", "isac.add_room_polygon", "isac.add_furniture",
            "isac.add_access_point", "isac.add_robot", "isac.add_link",
            "isac.remove_link"} <= ops
    assert ("template_list", "ISAC_UL_links", "links") in layout_stub.calls
    assert ("label", "No active object", "NONE") in layout_stub.calls
