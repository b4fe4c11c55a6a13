"""engine/experiments/demo.py: which room the demo runs on (the case study itself: tests/engine/localization)."""

from isac_twin.experiments.demo import bundled_blend, main


def test_bundled_rooms_have_their_blend():
    assert bundled_blend("aces_lab").is_file() and bundled_blend("l_office").is_file()


def test_unknown_scene_is_refused_in_one_line(tmp_path, capsys):
    assert main(["--scene", str(tmp_path / "nope"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "neither a bundled room (aces_lab, l_office, office_floor)" in err[0]


def test_scene_folder_with_a_misplaced_robot_exits_2(tmp_path, capsys):
    from isac_twin.scene.synthetic import l_room

    f = l_room(tmp_path / "l", robot=(5.0, 4.0, 0.0))  # in the L's cut-out corner
    assert main(["--scene", str(f), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no floor (outside the room's footprint)" in err[0]
