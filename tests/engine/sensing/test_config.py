"""engine/sensing/config.py: typed ``[[sensing]]`` tables (parsed once by isac_twin.scene.config)."""

import dataclasses
from pathlib import Path

import pytest

from isac_twin import ConfigError, load_config
from isac_twin.sensing.config import parse_sensing

LAB = Path(__file__).resolve().parents[3] / "blend_scenes" / "aces_lab" / "scene"


def _with(tables):
    from isac_twin.scene.config import parse_config

    cfg = load_config(LAB)
    return parse_config(dict(cfg.raw, sensing=tables), cfg.path)


def test_parse_sensing_links():
    specs = parse_sensing(_with([{"tx": "AP2", "rx": "AP1", "rho": 0.25},
                                 {"tx": "AP1", "rx": "AP1", "subcarriers": [0, 512],
                                  "target_height_m": False}]))
    assert [s.name for s in specs] == ["AP2->AP1", "AP1->AP1"]
    assert specs[0].rx_array.num_ant == 32 and specs[0].power_dbm == 20.0
    assert specs[1].monostatic and specs[1].subcarriers == (0, 512)
    assert specs[1].target_height_m is None
    cfg = load_config(LAB)
    assert parse_sensing(dataclasses.replace(cfg, sensing=())) == []
    assert [s.name for s in parse_sensing(cfg)] == ["AP2->AP1"]  # the lab's link


@pytest.mark.parametrize("table, msg", [
    ({"tx": "AP2", "rx": "AP7"}, r"sensing\[0\]\.rx: unknown device 'AP7'"),
    ({"tx": "AP2", "rx": "AP1", "rho": 2}, r"sensing\[0\]\.rho"),
    ({"tx": "AP2", "rx": "AP1", "beam": 1}, r"sensing\[0\]\.beam: unknown key"),
    ({"tx": "AP2", "rx": "AP1", "symbols": [0]}, r"sensing\[0\]\.symbols"),
    ({"tx": "AP2", "rx": "AP1", "every": 0}, r"sensing\[0\]\.every"),
    ({"tx": "AP2", "rx": "AP1", "rho": "x"}, r"sensing\[0\]\.rho"),
])
def test_parse_sensing_errors(table, msg):
    with pytest.raises(ConfigError, match=msg):
        parse_sensing(_with([table]))


def test_load_config_accepts_and_validates_sensing_tables(tmp_path):
    """`[[sensing]]` is a known top-level key: good tables load, bad ones fail at load."""
    import pytest as _pytest

    from isac_twin import ConfigError, load_config
    from isac_twin.scene.synthetic import box_room

    folder = box_room(tmp_path / "room")
    p = folder / "twin.toml"
    p.write_text(p.read_text() + '\n[[sensing]]\ntx = "AP1"\nrx = "AP1"\nrho = 0.25\n')
    assert load_config(folder).sensing[0].rho == 0.25
    p.write_text(p.read_text().replace('rx = "AP1"\nrho', 'rx = "AP7"\nrho'))
    with _pytest.raises(ConfigError, match=r"sensing\[0\]\.rx: unknown device 'AP7'"):
        load_config(folder)


def test_demo_takes_its_link_and_robot_from_any_scene(tmp_path):
    """isac_twin.experiments.sensing_demo on a non-lab scene: the first [[sensing]] link (radar every step)
    and the first robot from twin.toml; a scene without [[sensing]] is refused by name."""
    from isac_twin.experiments.sensing_demo import first_robot, lab_link, scene_link
    from isac_twin.scene.synthetic import l_room

    lab = scene_link(load_config(LAB))
    ref = lab_link()
    for f in ("tx", "rx", "rx_array", "rx_orientation", "power_dbm", "rho", "every"):
        assert getattr(lab, f) == getattr(ref, f), f
    office = load_config(LAB.parents[1] / "l_office" / "scene")
    link = scene_link(office, rho=0.5)
    assert (link.tx, link.rx, link.rho, link.every) == ("AP2", "AP1", 0.5, 1)
    assert (link.rx_array.num_rows, link.rx_array.num_cols) == (4, 4)
    assert first_robot(office) == "robot1"
    bare = load_config(l_room(tmp_path / "l"))
    with pytest.raises(ConfigError, match=r"twin.toml: sensing: the sensing demo needs"):
        scene_link(bare)
