"""export_scene on a small scene: files, content, determinism and refusals."""

from __future__ import annotations

import math
import struct
import tomllib
import xml.etree.ElementTree as ET

import pytest

bpy = pytest.importorskip("bpy")

pytestmark = pytest.mark.blender


def small_scene(scene):
    """A 4 x 3 x 2.5 m room, a rotated table, a chair with an array modifier, an AP and a robot."""
    from addon import devices, modelling

    modelling.create_room(4.0, 3.0, 2.5, 0.2, name="Room", scene=scene)
    modelling.add_furniture("table", (1.0, 1.0, 0.0), math.pi / 6, scene=scene)
    chair = modelling.add_furniture("chair", (3.0, 2.0, 0.0), name="Chair.001", scene=scene)
    mod = chair.modifiers.new("Row", "ARRAY")  # two chairs side by side after evaluation
    mod.count = 2
    mod.relative_offset_displace = (1.5, 0.0, 0.0)
    devices.add_access_point("AP1", (0.05, 1.5, 2.0), (0.0, 0.0, 0.0), rows=2, cols=2,
                             scene=scene)
    devices.add_robot("robot1", (2.0, 1.5, 0.0), math.pi / 2, cols=2, scene=scene)
    devices.add_link(scene, "AP1", "robot1")
    return scene


def read_ply(path):
    from addon.contract.writers.geometry import read_ply as rp

    return rp(path)


def test_export_small_scene(scene, tmp_path):
    from addon.exporter import export_scene

    report = export_scene(small_scene(scene), tmp_path)
    names = ["Chair_001", "Room_Ceiling", "Room_Floor", "Room_Wall_1", "Room_Wall_2",
             "Room_Wall_3", "Room_Wall_4", "Table"]
    assert report.objects == names
    assert report.devices == ["AP1", "robot1"]
    assert report.links == [("AP1", "robot1")]
    assert report.materials == ["mat-ceiling_board-0.2", "mat-concrete-0.2", "mat-wood-0.02",
                                "mat-wood-0.03"]
    for f in report.files:
        assert (tmp_path / f).is_file(), f
    assert {"scene.xml", "twin.toml", "Scene.dae", "Scene.stl", "Scene.usdc"} <= set(report.files)

    # scene.xml: deduplicated materials, one shape per object, refs resolve
    root = ET.parse(tmp_path / "scene.xml").getroot()
    bsdfs = {b.get("id"): b for b in root.findall("bsdf")}
    assert sorted(bsdfs) == report.materials
    assert all(b.get("type") == "itu-radio-material" for b in bsdfs.values())
    shapes = root.findall("shape")
    assert [s.get("id") for s in shapes] == [f"mesh-{n}" for n in names]
    for s in shapes:
        assert s.find("ref").get("id") in bsdfs
        assert s.find("string").get("value") == f"meshes/{s.get('id')[5:]}.ply"

    # PLY: binary little endian, world coordinates, triangles, modifiers applied
    data = (tmp_path / "meshes" / "Chair_001.ply").read_bytes()
    assert b"format binary_little_endian 1.0" in data[:200]
    chair = read_ply(tmp_path / "meshes" / "Chair_001.ply")
    assert chair.num_triangles == 24  # two boxes x 12 triangles: the array modifier is applied
    lo, hi = chair.bbox()
    assert lo == pytest.approx((2.75, 1.75, 0.0), abs=1e-6)
    assert hi == pytest.approx((2.75 + 0.5 + 0.75, 2.25, 0.9), abs=1e-6)
    table = read_ply(tmp_path / "meshes" / "Table.ply")
    c, s = math.cos(math.pi / 6), math.sin(math.pi / 6)
    half_x = 0.8 * c + 0.4 * s
    assert table.bbox()[0][0] == pytest.approx(1.0 - half_x, abs=1e-6)

    # twin.toml: the documented layout
    cfg = tomllib.loads((tmp_path / "twin.toml").read_text())
    assert cfg["schema"] == 1
    assert cfg["scene"] == {"name": "Scene", "file": "scene.xml", "frequency_hz": 2.4e9}
    assert cfg["ofdm"] == {"num_subcarriers": 1024, "subcarrier_spacing_hz": 78125.0,
                           "num_symbols": 14, "cyclic_prefix_samples": 72}
    ap, bot = cfg["devices"]
    assert ap == {"name": "AP1", "kind": "access_point", "role": "tx",
                  "position": [0.05, 1.5, 2.0], "orientation": [0.0, 0.0, 0.0],
                  "power_dbm": 20.0,
                  "array": {"rows": 2, "cols": 2, "vertical_spacing": 0.5,
                            "horizontal_spacing": 0.5, "pattern": "iso", "polarization": "V"}}
    assert bot["kind"] == "robot" and bot["model"] == "burger" and bot["role"] == "rx"
    assert bot["antenna_offset"] == [0.0, 0.0, 0.25]
    assert bot["orientation"] == [0.0, 0.0, pytest.approx(math.pi / 2, abs=1e-6)]
    assert cfg["links"] == [{"tx": "AP1", "rx": "robot1"}]


def test_twin_toml_loads_in_engine_config(scene, tmp_path):
    """Cross-check with the engine's loader (tests may import the engine; the add-on never does)."""
    config = pytest.importorskip("isac_twin.scene.config")
    from addon.exporter import export_scene

    export_scene(small_scene(scene), tmp_path, interchange=False)
    cfg = config.load_config(tmp_path / "twin.toml")
    assert [d.name for d in cfg.devices] == ["AP1", "robot1"]


def test_interchange_files(scene, tmp_path):
    collada = pytest.importorskip("collada")
    from addon.exporter import export_scene

    report = export_scene(small_scene(scene), tmp_path)
    dae = collada.Collada(str(tmp_path / "Scene.dae"))
    assert sorted(g.name for g in dae.geometries) == report.objects
    tris = {g.name: sum(len(p) for p in g.primitives) for g in dae.geometries}
    assert tris["Chair_001"] == 24 and tris["Room_Floor"] == 12
    nodes = {n.id for n in dae.scene.nodes}
    assert nodes == {f"node-{n}" for n in report.objects}
    stl = (tmp_path / "Scene.stl").read_bytes()
    (count,) = struct.unpack_from("<I", stl, 80)
    assert count == sum(tris.values()) and len(stl) == 84 + 50 * count
    assert (tmp_path / "Scene.usdc").read_bytes()[:8] == b"PXR-USDC"


def test_export_is_deterministic(scene, tmp_path):
    from addon.exporter import export_scene

    small_scene(scene)
    a = export_scene(scene, tmp_path / "a")
    b = export_scene(scene, tmp_path / "b")
    assert a.files == b.files
    for f in a.files:
        if f.endswith(".usdc"):
            # Blender's USD exporter writes prims in a different order on every run
            # (checked: .usda text too), so USD cannot be byte-identical; skip only it.
            continue
        assert (tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes(), f


def test_stale_meshes_removed(scene, tmp_path):
    from addon.exporter import export_scene

    small_scene(scene)
    export_scene(scene, tmp_path, interchange=False)
    bpy.data.objects.remove(scene.objects["Table"])
    export_scene(scene, tmp_path, interchange=False)
    assert not (tmp_path / "meshes" / "Table.ply").exists()


# --- refusals: each message names the culprit --------------------------------------------


def refused(scene, tmp_path) -> str:
    from addon.exporter import ExportError, export_scene

    with pytest.raises(ExportError) as info:
        export_scene(scene, tmp_path)
    assert not (tmp_path / "scene.xml").exists(), "nothing may be written on refusal"
    return str(info.value)


def test_refuses_material_outside_band(scene, tmp_path):
    small_scene(scene).objects["Room_Floor"].isac.itu_material = "floorboard"
    msg = refused(scene, tmp_path)
    assert "Room_Floor" in msg and "floorboard" in msg and "2.4 GHz" in msg


def test_refuses_untagged_mesh(scene, tmp_path):
    from addon import modelling

    small_scene(scene)
    modelling.add_box("Blob", (1, 1, 1), scene=scene)
    assert "'Blob'" in refused(scene, tmp_path)


def test_refuses_empty_and_zero_area_mesh(scene, tmp_path):
    small_scene(scene)
    empty = bpy.data.objects.new("Hollow", bpy.data.meshes.new("Hollow"))
    empty.isac.itu_material = "wood"
    scene.collection.objects.link(empty)
    flat = scene.objects["Table"]
    flat.scale = (1.0, 0.0, 0.0)  # squashed to a line: faces remain, area does not
    msg = refused(scene, tmp_path)
    assert "'Hollow': mesh is empty" in msg
    assert "'Table': mesh has zero area" in msg


def test_refuses_non_positive_thickness(scene, tmp_path):
    small_scene(scene).objects["Table"].isac.thickness = 0.0
    assert "'Table': material thickness" in refused(scene, tmp_path)


def test_refuses_duplicate_device_names(scene, tmp_path):
    from addon import devices

    small_scene(scene)
    devices.add_access_point("AP 2", scene=scene)
    devices.add_access_point("AP_2", scene=scene)
    devices.add_access_point("Room Floor", scene=scene)  # file-safe: the floor's name
    msg = refused(scene, tmp_path)
    assert "'AP_2'" in msg and "duplicates device 'AP 2'" in msg
    assert "Device 'Room Floor': name duplicates geometry object 'Room_Floor'" in msg


def test_refuses_unknown_link_end(scene, tmp_path):
    from addon import devices

    devices.add_link(small_scene(scene), "AP1", "ghost")
    msg = refused(scene, tmp_path)
    assert "rx 'ghost' is not a device" in msg


def test_refuses_wrong_role_and_self_link(scene, tmp_path):
    from addon import devices

    devices.add_link(small_scene(scene), "robot1", "AP1")
    msg = refused(scene, tmp_path)
    assert "device 'robot1' has role 'rx'" in msg and "device 'AP1' has role 'tx'" in msg


@pytest.mark.parametrize("key", ["array_rows", "array_cols"])
def test_refuses_array_smaller_than_one(scene, tmp_path, key):
    setattr(small_scene(scene).objects["AP1"].isac, key, 0)
    msg = refused(scene, tmp_path)
    assert "Device 'AP1': array rows and cols must be >= 1" in msg


def test_refuses_bad_numerology(scene, tmp_path):
    small_scene(scene).isac.num_subcarriers = 0
    scene.isac.frequency_hz = -1.0
    msg = refused(scene, tmp_path)
    assert "num_subcarriers" in msg and "frequency" in msg


def test_refuses_name_clash_after_sanitising(scene, tmp_path):
    from addon import modelling

    small_scene(scene)
    modelling.add_furniture("chair", name="Chair 001", scene=scene)
    assert "'Chair_001'" in refused(scene, tmp_path)


def test_refuses_blend_relative_folder_when_unsaved(scene):
    from addon.exporter import ExportError, export_scene

    small_scene(scene)
    assert bpy.data.filepath == ""
    with pytest.raises(ExportError, match="'//scene' is relative"):
        export_scene(scene, "//scene")


def test_resource_sets_and_robot_path_reach_twin_toml(scene, tmp_path):
    from addon import devices
    from addon.exporter import export_scene

    small_scene(scene)
    devices.set_resources(scene.objects["AP1"], subcarriers=(0, 512), symbols=(2, 9))
    devices.set_circle_path(scene.objects["robot1"], (2.0, 1.5), 0.5, "cw", speed=0.1)
    export_scene(scene, tmp_path / "out", interchange=False)
    data = tomllib.loads((tmp_path / "out" / "twin.toml").read_text())
    ap, robot = data["devices"][0], data["devices"][1]
    assert ap["subcarriers"] == [0, 512] and ap["symbols"] == [2, 9]
    assert "subcarriers" not in robot  # the default: the whole grid
    assert robot["path"] == {"kind": "circle", "centre": [2.0, 1.5], "radius": 0.5,
                             "direction": "cw", "speed": pytest.approx(0.1)}
    with pytest.raises(ValueError, match="only robots follow paths"):
        devices.set_circle_path(scene.objects["AP1"], (1, 1), 1.0)


def test_refuses_empty_resource_range(scene, tmp_path):
    from addon import devices
    from addon.exporter import ExportError, export_scene

    small_scene(scene)
    devices.set_resources(scene.objects["AP1"], symbols=(9, 3))
    with pytest.raises(ExportError, match=r"Device 'AP1': symbol range \[9, 3\) is empty"):
        export_scene(scene, tmp_path / "out", interchange=False)


def test_sensing_links_export_and_load_in_engine(scene, tmp_path):
    """A sensing link set in Blender becomes a [[sensing]] table the engine types."""
    config = pytest.importorskip("isac_twin.scene.config")
    from addon import devices
    from addon.exporter import export_scene

    s = small_scene(scene)
    devices.add_sensing_link(s, "AP1", "AP1", rho=0.5, every=3)  # monostatic
    export_scene(s, tmp_path, interchange=False)
    data = tomllib.loads((tmp_path / "twin.toml").read_text())
    assert data["sensing"] == [{"tx": "AP1", "rx": "AP1", "rho": 0.5, "every": 3}]
    cfg = config.load_config(tmp_path / "twin.toml")
    assert [(x.name, x.rho, x.every) for x in cfg.sensing] == [("AP1->AP1", 0.5, 3)]


def test_refuses_unknown_sensing_link_end(scene, tmp_path):
    from addon import devices

    devices.add_sensing_link(small_scene(scene), "AP1", "ghost")
    assert "Sensing link 1 (AP1 -> ghost): rx 'ghost' is not a device" in refused(scene, tmp_path)


def test_every_path_kind_reaches_twin_toml_and_the_engine(scene, tmp_path):
    """Polyline from a curve object (a rectangle preset, then moved), figure eight and goal:
    exported as [devices.path] and accepted by the engine's loader, free space included."""
    from addon import devices
    from addon.exporter import export_scene
    from isac_twin import load_scene
    from isac_twin.scene import config

    small_scene(scene)
    robot = scene.objects["robot1"]
    curve = devices.set_rectangle_path(robot, (2.2, 2.2), 0.8, 0.6, speed=0.15, scene=scene)
    curve.location = (0.1, 0.0, 0.0)  # the object's transform counts (world coordinates)
    cases = [
        (lambda: None, {"kind": "polyline", "closed": True, "speed": pytest.approx(0.15),
                        "waypoints": [[1.9, 1.9], [2.7, 1.9], [2.7, 2.5], [1.9, 2.5]]}),
        (lambda: devices.set_figure_eight_path(robot, (2.2, 2.0), 1.0),
         {"kind": "figure_eight", "centre": [2.2, 2.0], "size": pytest.approx(1.0)}),
        (lambda: devices.set_goal_path(robot, (2.5, 2.5)),
         {"kind": "goal", "goal": [2.5, 2.5]}),
    ]
    for i, (setup, want) in enumerate(cases):
        setup()
        out = tmp_path / f"k{i}"
        export_scene(scene, out, interchange=False)
        got = tomllib.loads((out / "twin.toml").read_text())["devices"][1]["path"]
        assert got == want
        assert config.load_config(out).device("robot1").path["kind"] == want["kind"]
        load_scene(out, load_sionna=False)  # free space: the paths avoid the table and chairs
    devices.set_goal_path(robot, (1.0, 1.0))  # into the table
    export_scene(scene, tmp_path / "bad", interchange=False)
    with pytest.raises(config.ConfigError, match="goal .* lies in object 'Table'"):
        load_scene(tmp_path / "bad", load_sionna=False)


def test_room_part_tags_are_exported_and_read_by_the_engine(scene, tmp_path):
    from addon.exporter import export_scene
    from isac_twin import load_scene
    from isac_twin.scene.room import room_parts

    small_scene(scene)
    scene.objects["Room_Wall_2"].name = "north side"  # a user's own name: the tag stays
    export_scene(scene, tmp_path, interchange=False)
    room = tomllib.loads((tmp_path / "twin.toml").read_text())["room"]
    assert "north_side" in room["shell"] and "Room_Floor" in room["shell"]
    assert room["furniture"] == ["Chair_001", "Table"]
    parts = room_parts(load_scene(tmp_path, load_sionna=False))
    assert "north_side" in parts.walls and set(parts.tagged) >= {"north_side", "Table"}


def test_refuses_polyline_without_enough_points(scene, tmp_path):
    from addon import devices

    small_scene(scene)
    robot = scene.objects["robot1"]
    robot.isac.path_kind = "polyline"
    assert "polyline path has no curve object" in refused(scene, tmp_path)
    devices.set_polyline_path(robot, devices.add_path_curve("P", [(1, 1), (1, 1)], scene=scene))
    assert "two consecutive points at the same x, y" in refused(scene, tmp_path)
