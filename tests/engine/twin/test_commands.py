"""engine/twin/commands.py: commands to a twin (run, pause, step, reset, set_path,
set_goal, teleop) on the small lab, and bad ones refused by name."""

import pytest

from isac_twin import Command, Edit, Twin

pytestmark = pytest.mark.slow


def test_commands_and_bad_input(lab):
    tw = Twin.from_scene(lab, seed=1, phy=False)
    # run/pause/step are the twin's own run state (the live server reads it)
    tw.command(Command("step", {"count": 3}))
    assert (tw.running, tw.pending_steps) == (False, 3)
    assert tw.step().step == 0 and tw.pending_steps == 2
    tw.command(Command("pause"))
    assert tw.pending_steps == 0  # pause cancels the steps still pending
    tw.command(Command("run"))
    assert tw.running
    for bad, match in ((Command("step", {"count": "abc"}), "count: expected an integer"),
                       (Command("step", {"count": 10**9}), "count: expected an integer"),
                       (Command("teleop", {"robot": "robot1", "linear": float("nan"),
                                           "angular": 0}), "linear: expected a number"),
                       (Command("teleop", {"robot": "r9", "linear": 0, "angular": 0}),
                        "robot: expected one of robot1"),
                       (Command("set_goal", {"robot": "robot1", "goal": [1e308, 0]}),
                        "goal: expected \\[x, y\\] inside the room")):
        with pytest.raises(ValueError, match=match):
            tw.command(bad)
    assert tw.running and tw.pending_steps == 0  # a rejected command changed nothing
    tw.command(Command("teleop", {"robot": "robot1", "linear": 0.1, "angular": 0.0}))
    tw.step()
    r = tw.step()
    assert r.robots["robot1"].velocity[0] == pytest.approx(0.1, abs=0.02)
    tw.command(Command("reset"))
    assert tw.step_index == 0
    with pytest.raises(ValueError, match="unknown op 'fly'"):
        tw.command(Command("fly"))
    with pytest.raises(KeyError, match="no robot named 'r2'"):
        tw.set_path("r2", {"kind": "circle", "centre": [3, 2], "radius": 1})
    with pytest.raises(ValueError, match="outside|leaves|room"):
        tw.set_path("robot1", {"kind": "circle", "centre": [3, 2], "radius": 5})
    with pytest.raises(ValueError, match="edit explode 'cabinet': op"):
        tw.apply_edit(Edit(op="explode", target="cabinet"))
    with pytest.raises(ValueError, match="material: 'floorboard' is not defined at 2.4 GHz"):
        tw.apply_edit(Edit(op="material", target="cabinet", material="floorboard"))
    tw.step()  # the rejected edits were never queued: the twin keeps stepping


def test_set_path_is_checked_against_the_room_as_it_is_now(tmp_path):
    """A live set_path through the desk is refused by name; once the desk is moved away
    (an edit), the same path is accepted."""
    from isac_twin import PathError
    from isac_twin.scene.synthetic import l_room

    tw = Twin.from_scene(l_room(tmp_path / "l", robot=(1.0, 1.0, 0.0)), phy=False, seed=0)
    through = {"kind": "polyline", "waypoints": [[1.0, 1.0], [2.0, 4.2]]}
    with pytest.raises(PathError, match=r"set_path\(robot1\): the polyline .* lies in object "
                                        r"'Desk'"):
        tw.command(Command("set_path", {"robot": "robot1", "path": through}))
    with pytest.raises(PathError, match="lies in object 'Room_Wall_4'"):  # to the cut-out
        tw.set_path("robot1", {"kind": "goal", "goal": [5.0, 4.5]})
    tw.apply_edit(Edit(op="move", target="Desk", position=(3.1, 4.0, 0.375)))
    tw.step()
    tw.set_path("robot1", through)  # free now


def test_paths_and_names_from_a_viewer_are_bounded(lab):
    """A 300,000-waypoint set_path stalled every viewer for 3.6 s while it was checked
    against the room: now a polyline has at most ``MAX_WAYPOINTS`` waypoints, refused
    when the command is validated (the same bound applies to twin.toml paths). Object
    names an ``add`` gives are printable and of bounded length; the rejection quotes a
    long name cut short."""
    import numpy as np

    from isac_twin.contract.schema import MAX_NAME_CHARS, MAX_WAYPOINTS

    tw = Twin.from_scene(lab, seed=1, phy=False, sensing=False, localize=False)
    ring = [[3 + np.cos(a), 2 + np.sin(a)] for a in np.linspace(0, 6.2, 300_000)]
    with pytest.raises(ValueError, match=rf"command set_path: path: 300000 waypoints, beyond the "
                                         rf"limit of {MAX_WAYPOINTS}"):
        tw.validate_command(Command("set_path", {"robot": "robot1", "path": {
            "kind": "polyline", "waypoints": ring}}))
    ok = ring[::300_000 // MAX_WAYPOINTS][:MAX_WAYPOINTS]
    tw.command(Command("set_path", {"robot": "robot1", "path": {"kind": "polyline",
                                                                "waypoints": ok}}))
    data = next((lab / "meshes").glob("*.ply")).read_bytes()
    for name, why in (("", "the empty name"), ("   ", "the empty name"),
                      ("x" * (MAX_NAME_CHARS + 1), f"beyond the limit of {MAX_NAME_CHARS}"),
                      ("crate\n\x1b[2J", "not printable"), ("Bad\udcffName", "not printable")):
        with pytest.raises(ValueError, match=f"target: .*{why}") as err:
            tw.apply_edit(Edit(op="add", target=name, material="wood", mesh_data=data))
        assert len(str(err.value)) < 300 and "\n" not in str(err.value)
    tw.step()
