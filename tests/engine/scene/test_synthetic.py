"""isac_twin.scene.synthetic writes scene folders through the contract's writers."""

import numpy as np

from isac_twin import load_config
from isac_twin.contract.writers import geometry, mitsuba_xml, twin_toml
from isac_twin.scene.synthetic import box_room, write_ply


def test_scene_folder_is_the_exporters_format(tmp_path):
    folder = box_room(tmp_path / "room", frequency_hz=3.5e9)
    toml = (folder / "twin.toml").read_text()
    cfg = load_config(folder)
    # byte-identical to the add-on's own writer fed the same data
    assert toml == twin_toml.dumps(cfg.raw)
    assert cfg.scene.frequency_hz == 3.5e9 and [d.name for d in cfg.devices] == ["AP1", "robot1"]
    xml = (folder / "scene.xml").read_text()
    assert xml == mitsuba_xml.scene_xml(
        [(n, "concrete", 0.2) for n in ("floor", "ceiling", "wall_xmin", "wall_xmax",
                                       "wall_ymin", "wall_ymax")])


def test_ply_reads_back_with_the_addons_reader(tmp_path):
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 2, 0], [0, 2, 0.5]], float)
    f = np.array([[0, 1, 2], [0, 2, 3]])
    write_ply(tmp_path / "q.ply", v, f)
    m = geometry.read_ply(tmp_path / "q.ply")
    np.testing.assert_allclose(np.reshape(m.vertices, (-1, 3)), v)
    assert list(m.triangles) == f.reshape(-1).tolist()
