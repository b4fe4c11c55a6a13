"""Plain modelling functions: rooms (ground plan, polygon), furniture, windows."""

from __future__ import annotations

import math

import pytest

bpy = pytest.importorskip("bpy")

pytestmark = pytest.mark.blender


def world_bbox(obj):
    """(min, max) of the evaluated mesh's vertices in world coordinates, m."""
    dg = bpy.context.evaluated_depsgraph_get()
    ev = obj.evaluated_get(dg)
    pts = [ev.matrix_world @ v.co for v in ev.data.vertices]
    return (tuple(min(p[i] for p in pts) for i in range(3)),
            tuple(max(p[i] for p in pts) for i in range(3)))


def is_closed(obj) -> bool:
    """Every edge is shared by exactly two faces."""
    counts = {}
    for poly in obj.data.polygons:
        for key in poly.edge_keys:
            counts[key] = counts.get(key, 0) + 1
    return all(c == 2 for c in counts.values())


def test_rect_room_walls_outside_footprint(scene):
    from addon import modelling

    room = modelling.create_room(8.0, 6.0, 3.0, 0.2, name="Lab", scene=scene)
    assert len(room["walls"]) == 4
    lo, hi = world_bbox(room["floor"])
    assert lo == pytest.approx((0, 0, -0.2), abs=1e-6) and hi == pytest.approx((8, 6, 0), abs=1e-6)
    lo, hi = world_bbox(room["ceiling"])
    assert lo == pytest.approx((0, 0, 3), abs=1e-6) and hi == pytest.approx((8, 6, 3.2), abs=1e-6)
    south = world_bbox(room["walls"][0])
    assert south[0] == pytest.approx((-0.2, -0.2, 0), abs=1e-6)
    assert south[1] == pytest.approx((8.2, 0, 3), abs=1e-6)
    for obj in (room["floor"], room["ceiling"], *room["walls"]):
        assert is_closed(obj), obj.name
        assert tuple(obj.scale) == (1, 1, 1)
        assert obj.isac.thickness == pytest.approx(0.2)
    assert room["walls"][0].isac.itu_material == "concrete"
    assert room["ceiling"].isac.itu_material == "ceiling_board"


def test_polygon_room_concave_and_clockwise(scene):
    from addon import modelling

    # an L-shaped footprint given clockwise: the function must still put walls outside
    plan = [(0, 0), (0, 4), (2, 4), (2, 2), (5, 2), (5, 0)]
    room = modelling.create_room_from_polygon(plan, 2.5, 0.1, name="L", scene=scene)
    assert len(room["walls"]) == 6
    lo, hi = world_bbox(room["floor"])
    assert lo[:2] == pytest.approx((0, 0)) and hi[:2] == pytest.approx((5, 4))
    # the walls' union spans the footprint grown by the thickness
    los, his = zip(*(world_bbox(w) for w in room["walls"]))
    assert min(p[0] for p in los) == pytest.approx(-0.1, abs=1e-6)
    assert max(p[1] for p in his) == pytest.approx(4.1, abs=1e-6)
    floor_area = sum(p.area for p in room["floor"].data.polygons if p.normal.z > 0.5)
    assert floor_area == pytest.approx(2 * 4 + 3 * 2, rel=1e-6)  # 2 x 4 m plus 3 x 2 m
    assert all(is_closed(w) for w in room["walls"])


@pytest.mark.parametrize("kwargs, culprit", [
    (dict(width=0.0, depth=6.0, height=3.0), "width"),
    (dict(width=8.0, depth=-1.0, height=3.0), "depth"),
    (dict(width=8.0, depth=6.0, height=0.0), "height"),
    (dict(width=8.0, depth=6.0, height=3.0, wall_thickness=0.0), "wall_thickness"),
])
def test_room_rejects_non_positive_dimensions(scene, kwargs, culprit):
    from addon import modelling

    with pytest.raises(ValueError, match=culprit):
        modelling.create_room(scene=scene, **kwargs)


def test_polygon_rejects_degenerate(scene):
    from addon import modelling

    with pytest.raises(ValueError, match="at least 3"):
        modelling.create_room_from_polygon([(0, 0), (1, 0)], 3.0, scene=scene)
    with pytest.raises(ValueError, match="coincide"):
        modelling.create_room_from_polygon([(0, 0), (1, 0), (1, 0), (0, 1)], 3.0, scene=scene)
    with pytest.raises(ValueError, match="zero area"):
        modelling.create_room_from_polygon([(0, 0), (1, 0), (2, 0)], 3.0, scene=scene)


@pytest.mark.parametrize("kind", ["table", "chair", "cabinet", "rack", "switch_box"])
def test_furniture_presets(scene, kind):
    from addon import modelling

    preset = modelling.FURNITURE_PRESETS[kind]
    obj = modelling.add_furniture(kind, (2.0, 1.0, 0.0), math.pi / 2, scene=scene)
    assert obj.isac.itu_material == preset["material"]
    assert obj.isac.thickness == pytest.approx(preset["thickness"])
    dx, dy, dz = preset["dimensions"]
    lo, hi = world_bbox(obj)
    # turned by 90 degrees: x and y extents swap; it stands on z = 0
    assert lo == pytest.approx((2 - dy / 2, 1 - dx / 2, 0), abs=1e-6)
    assert hi == pytest.approx((2 + dy / 2, 1 + dx / 2, dz), abs=1e-6)
    assert is_closed(obj)


def test_furniture_rejects_bad_input(scene):
    from addon import modelling

    with pytest.raises(ValueError, match="sofa"):
        modelling.add_furniture("sofa", scene=scene)
    with pytest.raises(ValueError, match="Desk.*dimension y"):
        modelling.add_furniture("table", name="Desk", dimensions=(1.0, 0.0, 1.0), scene=scene)


def test_window_cuts_wall(scene):
    from addon import modelling

    room = modelling.create_room(4.0, 3.0, 2.5, 0.2, scene=scene)
    wall = room["walls"][2]  # north wall, y in [3, 3.2]
    pane = modelling.add_window(wall, (2.0, 3.1, 1.4), 1.0, 1.0, scene=scene)
    assert pane.isac.itu_material == "glass"
    cutter = scene.objects["Room_Wall_3_Window_Cutter"]
    assert cutter.isac.export_geometry is False
    dg = bpy.context.evaluated_depsgraph_get()
    assert len(wall.evaluated_get(dg).data.polygons) > len(wall.data.polygons)
    lo, hi = world_bbox(pane)
    assert lo == pytest.approx((1.5, 3.095, 0.9), abs=1e-6)
    assert hi == pytest.approx((2.5, 3.105, 1.9), abs=1e-6)
