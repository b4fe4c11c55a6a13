"""engine/scene/room.py: shell vs furniture on any room, placement against free space, floor plans."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from isac_twin import ConfigError, load_scene
from isac_twin.scene.room import locate, plan_polygons, room_parts
from isac_twin.scene.synthetic import (
    L_FOOTPRINT,
    SyntheticDevice,
    box_mesh,
    l_room,
    polygon_room_objects,
    write_scene_folder,
)

ROOT = Path(__file__).resolve().parents[3]


def test_l_room_parts_come_from_geometry_with_the_addons_names(tmp_path):
    s = load_scene(l_room(tmp_path / "l"), load_sionna=False)
    p = room_parts(s)
    assert p.floor == ("Room_Floor",) and p.ceiling == ("Room_Ceiling",)
    assert set(p.walls) == {f"Room_Wall_{i}" for i in range(1, 7)}
    assert set(p.furniture) == {"Desk", "Cabinet"}
    assert p.tagged == ()


def test_parts_do_not_depend_on_names(tmp_path):
    """The same room with meaningless names (no 'wall', 'floor', 'Lab_' anywhere), a
    window pane in a wall and a floor-to-ceiling-less tall shelf."""
    objs = polygon_room_objects(L_FOOTPRINT, name="Zz")
    for i, o in enumerate(objs):
        o.name = f"obj{i}"
    # a 1 cm pane inside the wall along y = 0 (obj2 spans y -0.2..0), a 2.2 m shelf
    objs.append(type(objs[0])("pane", *box_mesh((1, -0.105, 0.9), (2, -0.095, 2.1)),
                              material="glass", thickness=0.01))
    objs.append(type(objs[0])("shelf", *box_mesh((0.1, 4.5, 0), (1.1, 4.9, 2.2)),
                              material="wood", thickness=0.02))
    dev = [SyntheticDevice("AP1", "access_point", "tx", (2.0, 2.0, 2.0))]
    s = load_scene(write_scene_folder(tmp_path / "n", objs, dev, []), load_sionna=False)
    p = room_parts(s)
    assert p.floor == ("obj0",) and p.ceiling == ("obj1",)
    assert set(p.walls) == {f"obj{i}" for i in range(2, 8)} | {"pane"}
    assert p.furniture == ("shelf",)


def test_room_tags_override_the_geometry(tmp_path):
    s = load_scene(l_room(tmp_path / "t", room={"shell": ["Desk"],
                                                "furniture": ["Room_Wall_3"]}),
                   load_sionna=False)
    p = room_parts(s)
    assert "Desk" in p.shell and "Room_Wall_3" not in p.shell
    assert "Room_Wall_3" in p.furniture and set(p.tagged) == {"Desk", "Room_Wall_3"}


@pytest.mark.parametrize("room, needle", [
    ({"shell": ["Nope"]}, "room: 'Nope' is not an object of scene.xml"),
    ({"shell": ["Desk"], "furniture": ["Desk"]}, "'Desk' listed as both shell and furniture"),
    ({"shell": "Desk"}, "room.shell: expected a list of object names"),
    ({"walls": ["Desk"]}, "room.walls"),
])
def test_bad_room_tables_are_refused_by_name(tmp_path, room, needle):
    with pytest.raises(ConfigError) as e:
        load_scene(l_room(tmp_path / "b", room=room), load_sionna=False)
    assert needle in str(e.value) and "twin.toml" in str(e.value)
    assert "\n" not in str(e.value)


@pytest.mark.parametrize("robot, path, needle", [
    ((-0.1, 2.0, 0.0), None, "devices[2] (robot1).position: [-0.1, 2.0, 0.0] is not in free "
                             "space: its robot body (-0.10, 2.00, 0.10) lies in object "
                             "'Room_Wall_6'"),
    ((2.0, 4.0, 0.0), None, "lies in object 'Desk'"),
    ((5.0, 4.0, 0.0), None, "lies in no floor (outside the room's footprint)"),
    ((1.0, 1.0, 0.0), {"kind": "polyline", "waypoints": [[1.0, 1.0], [2.0, 4.2]]},
     "devices[2] (robot1).path: the polyline of 2 waypoints is not in free space: its point "
     "(1.82, 3.64) (2.76 m along it) lies in object 'Desk'"),
    ((1.0, 1.0, 0.0), {"kind": "goal", "goal": [5.0, 4.0]},
     "path: the straight drive to the goal (5.00, 4.00) is not in free space: its point "
     "(4.00, 3.25) (3.75 m along it) lies in object 'Room_Wall_4'"),
    ((2.0, 1.5, 0.0), {"kind": "circle", "centre": [3.5, 2.5], "radius": 1.2},
     "the circle centre (3.5, 2.5) radius 1.2 m is not in free space: its point (4.58, 3.03) "
     "(0.55 m along it) lies in object 'Room_Wall_3'"),  # the inner wall of the L's corner
    ((2.0, 1.5, 0.0), {"kind": "figure_eight", "centre": [4.5, 3.5], "size": 1.0},
     "lies in no floor (outside the room's footprint)"),
])
def test_misplaced_robot_or_path_is_refused_in_one_line(tmp_path, robot, path, needle):
    with pytest.raises(ConfigError) as e:
        load_scene(l_room(tmp_path / "p", robot=robot, path=path), load_sionna=False)
    msg = str(e.value)
    assert needle in msg, msg
    assert "\n" not in msg and "twin.toml" in msg


def test_path_crossing_a_wall_names_the_wall(tmp_path):
    f = l_room(tmp_path / "w", robot=(1.0, 1.0, 0.0),
               path={"kind": "polyline", "waypoints": [[1.0, 1.0], [3.0, 1.0], [3.0, 5.5]]})
    with pytest.raises(ConfigError) as e:
        load_scene(f, load_sionna=False)
    assert "lies in object 'Room_Wall_5'" in str(e.value)  # the wall along y = 5


def test_ap_inside_furniture_is_refused_and_cli_exits_2(tmp_path):
    f = l_room(tmp_path / "a")
    toml = (f / "twin.toml").read_text().replace("position = [5.0, 2.9, 2.2]",
                                                 "position = [5.5, 0.3, 1.0]")
    (f / "twin.toml").write_text(toml)
    r = subprocess.run([sys.executable, "-m", "isac_twin.cli", "info", str(f)], cwd=ROOT,
                       capture_output=True, text=True)
    assert r.returncode == 2
    err = r.stderr.strip().splitlines()
    assert len(err) == 1, r.stderr
    assert "devices[1] (AP2).position" in err[0] and "array centre" in err[0]
    assert "object 'Cabinet'" in err[0]


def test_free_room_loads_and_open_scenes_are_not_checked_for_a_floor(tmp_path):
    load_scene(l_room(tmp_path / "ok"), load_sionna=False)  # the default path is free
    # a lone reflecting quad (open mesh, no floor): nothing encloses anything
    from isac_twin.scene.synthetic import SyntheticObject, quad_mesh
    q = SyntheticObject("plate", *quad_mesh([(5, -1, 0), (5, 1, 0), (5, 1, 2), (5, -1, 2)]),
                        material="metal", thickness=0.01)
    dev = [SyntheticDevice("AP1", "access_point", "tx", (4.97, 0.0, 1.0))]
    s = load_scene(write_scene_folder(tmp_path / "q", [q], dev, []), load_sionna=False)
    assert locate(s, [[5.0, 0.0, 1.0]]) == [None]


@pytest.mark.slow
def test_locate_agrees_with_the_tracers_free_space_test(tmp_path):
    """Independent reference: grid.free_points (Mitsuba rays) on the same L room."""
    from isac_twin.raytrace.grid import free_points

    s = load_scene(l_room(tmp_path / "f"))
    xs, ys = np.arange(-0.47, 6.5, 0.31), np.arange(-0.43, 5.5, 0.29)
    pts = np.array([(x, y, z) for x in xs for y in ys for z in (0.31, 1.37)])
    ours = np.array([h is None for h in locate(s, pts)])
    ref = free_points(s.sionna, pts)
    assert ours.sum() > 200 and (~ours).sum() > 100
    assert (ours == ref).all(), pts[ours != ref][:5]


def test_plan_polygons_give_the_exact_l_footprint(tmp_path):
    s = load_scene(l_room(tmp_path / "pl"), load_sionna=False)
    plan = plan_polygons(s)
    ((name, floor),) = plan["floor"]
    assert name == "Room_Floor"
    area = np.abs(np.cross(floor[:, 1] - floor[:, 0], floor[:, 2] - floor[:, 0])).sum() / 2
    assert area == pytest.approx(2 * 26.0)  # top and bottom caps of 6 x 5 - 2 x 2 m^2
    assert len(plan["walls"]) == 6 and len(plan["furniture"]) == 2
    # the cut-out corner is covered by no floor triangle
    inside = [_in_tri(t, (5.0, 4.0)) for t in floor]
    assert not any(inside)


def _in_tri(t, p):
    d = lambda a, b, c: (a[0] - c[0]) * (b[1] - c[1]) - (b[0] - c[0]) * (a[1] - c[1])  # noqa
    d1, d2, d3 = d(p, t[0], t[1]), d(p, t[1], t[2]), d(p, t[2], t[0])
    return not ((d1 < 0 or d2 < 0 or d3 < 0) and (d1 > 0 or d2 > 0 or d3 > 0))
