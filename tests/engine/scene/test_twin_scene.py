"""engine/scene/twin_scene.py: loading a scene folder into Sionna RT, validation of objects and devices."""

import numpy as np
import pytest

from isac_twin import ConfigError, load_scene
from isac_twin.scene.meshes import read_ply
from isac_twin.scene.synthetic import (
    SyntheticDevice,
    SyntheticObject,
    box_mesh,
    box_room,
    write_ply,
    write_scene_folder,
)
from isac_twin.scene.twin_scene import itu_defined_at


@pytest.fixture()
def folder(tmp_path):
    return box_room(tmp_path / "room")


def test_loads_into_sionna_with_objects_separate(folder):
    scene = load_scene(folder)
    names = set(scene.sionna.objects)
    assert names == {"floor", "ceiling", "wall_xmin", "wall_xmax", "wall_ymin", "wall_ymax"}
    assert scene.sionna.frequency[0] == pytest.approx(2.4e9)
    floor = scene.sionna.objects["floor"]
    assert floor.radio_material.itu_type == "concrete"
    assert float(floor.radio_material.thickness[0]) == pytest.approx(0.2)
    np.testing.assert_allclose(scene.bounds_min, [-0.1, -0.1, -0.1], atol=1e-6)
    np.testing.assert_allclose(scene.bounds_max, [6.1, 4.1, 3.1], atol=1e-6)


def test_content_hash_tracks_geometry_and_material(tmp_path):
    a = load_scene(box_room(tmp_path / "a"), load_sionna=False)
    b = load_scene(box_room(tmp_path / "b"), load_sionna=False)
    assert a.content_hash() == b.content_hash()
    c = load_scene(box_room(tmp_path / "c", size=(6.0, 4.0, 3.01)), load_sionna=False)
    assert c.content_hash() != a.content_hash()
    d = load_scene(box_room(tmp_path / "d", material="brick"), load_sionna=False)
    assert d.content_hash() != a.content_hash()


def test_ply_reader_matches_written_mesh(tmp_path):
    v, f = box_mesh((0, 0, 0), (1, 2, 3))
    from isac_twin.scene.synthetic import write_ply
    write_ply(tmp_path / "b.ply", v, f)
    m = read_ply(tmp_path / "b.ply")
    np.testing.assert_allclose(m.vertices, v)
    np.testing.assert_array_equal(m.faces, f)


def test_itu_bands_from_sionna():
    assert itu_defined_at("concrete", 2.4e9)
    assert not itu_defined_at("floorboard", 2.4e9)
    assert itu_defined_at("floorboard", 60e9)


def _xml_edit(folder, old, new):
    p = folder / "scene.xml"
    t = p.read_text()
    assert old in t
    p.write_text(t.replace(old, new, 1))


def test_unknown_material(folder):
    _xml_edit(folder, 'value="concrete"', 'value="unobtainium"')
    with pytest.raises(ConfigError, match=r"scene\.xml: bsdf 'mat-concrete-0.2': unknown ITU material 'unobtainium'"):
        load_scene(folder, load_sionna=False)


def test_material_undefined_at_frequency(tmp_path):
    objs = [SyntheticObject("parquet", *box_mesh((0, 0, -0.1), (4, 4, 0)), material="floorboard"),
            SyntheticObject("wall", *box_mesh((0, 0, 0), (0.1, 4, 3)))]
    dev = [SyntheticDevice("AP1", "access_point", "tx", (1, 1, 1))]
    folder = write_scene_folder(tmp_path / "f", objs, dev, [])
    with pytest.raises(ConfigError, match=r"object 'parquet': material 'floorboard' is not defined at 2.4 GHz \(defined: 50-100 GHz"):
        load_scene(folder, load_sionna=False)


def test_missing_mesh(folder):
    (folder / "meshes" / "ceiling.ply").unlink()
    with pytest.raises(ConfigError,
                       match=r"object 'ceiling': .*ceiling\.ply: cannot read a PLY mesh file"):
        load_scene(folder, load_sionna=False)


@pytest.mark.parametrize("damage,reason", [
    (lambda b: b[:-20], "truncated or corrupt"),
    (lambda b: b"garbage" + b, "not a PLY file"),
    (lambda b: b.replace(b"binary_little_endian", b"binary_big_endian"), "unsupported PLY format"),
])
def test_corrupt_mesh(folder, damage, reason):
    p = folder / "meshes" / "wall_xmin.ply"
    p.write_bytes(damage(p.read_bytes()))
    with pytest.raises(ConfigError, match=rf"object 'wall_xmin': .*wall_xmin\.ply: {reason}"):
        load_scene(folder, load_sionna=False)


def test_broken_xml(folder):
    _xml_edit(folder, "</scene>", "</scen>")
    with pytest.raises(ConfigError, match=r"scene\.xml: not valid XML"):
        load_scene(folder, load_sionna=False)


def test_device_outside_room(tmp_path):
    devs = [SyntheticDevice("AP1", "access_point", "tx", (7.5, 1.0, 2.0))]
    folder = box_room(tmp_path / "r", devices=devs, links=[])
    with pytest.raises(ConfigError, match=r"devices\[0\] \(AP1\)\.position: \[7\.5, 1\.0, 2\.0\] lies outside the room"):
        load_scene(folder, load_sionna=False)


def test_content_hash_is_cached_until_an_edit(tmp_path):
    scene = load_scene(box_room(tmp_path / "r"))
    h0 = scene.content_hash()
    assert scene.content_hash() is h0  # cached: same object, no rehash per step
    scene.move_object("floor", position=(3.0, 2.0, -0.04))
    h1 = scene.content_hash()
    assert h1 != h0
    scene.set_material("floor", "brick")
    assert scene.content_hash() not in (h0, h1)


def test_a_replica_replaying_the_edits_is_the_same_scene(tmp_path):
    """``TwinScene.edits`` logs every edit method; a scene loaded from the same
    folder that replays them (the radar's process does) hashes and traces the same."""
    folder = box_room(tmp_path / "r")
    scene = load_scene(folder)
    box = tmp_path / "box.ply"
    v, f = box_mesh((1.0, 1.0, 0.0), (1.5, 1.4, 0.8))
    write_ply(box, v, f)
    scene.move_object("floor", position=(3.0, 2.0, -0.04), orientation=(0.0, 0.0, 0.1))
    scene.define_material("wet", {"relative_permittivity": 9.0, "conductivity": 0.2,
                                  "thickness": 0.12})
    scene.set_material("ceiling", "wet")
    scene.add_object("crate", box, "wood")
    scene.remove_object("wall_xmin")
    with pytest.raises(KeyError):
        scene.remove_object("wall_xmin")  # a refused edit is not logged
    assert [e[0] for e in scene.edits] == ["move_object", "define_material", "set_material",
                                           "add_object", "remove_object"]
    replica = load_scene(folder)
    assert replica.content_hash() != scene.content_hash()
    replica.replay(scene.edits)
    assert replica.content_hash() == scene.content_hash()
    assert set(replica.sionna.objects) == set(scene.sionna.objects)
    np.testing.assert_allclose(replica.sionna.objects["floor"].position.numpy(),
                               scene.sionna.objects["floor"].position.numpy())
    with pytest.raises(ValueError, match=r"edits\[1\]: 'contains' is not an edit"):
        load_scene(folder, load_sionna=False).replay([scene.edits[1], ("contains", ((0, 0, 0),))])


def _fifo(folder):
    import os

    os.mkfifo(folder / "meshes" / "pipe.ply")
    return "meshes/pipe.ply"


def _link_out(folder):
    target = folder.parent / "elsewhere.ply"
    target.write_bytes((folder / "meshes" / "ceiling.ply").read_bytes())
    (folder / "meshes" / "link.ply").symlink_to(target)
    return "meshes/link.ply"


@pytest.mark.parametrize("path, reason", [
    (lambda f: "/dev/zero", "absolute paths are not allowed"),
    (lambda f: str((f / "meshes" / "ceiling.ply").resolve()), "absolute paths are not allowed"),
    (lambda f: "../room/meshes/ceiling.ply", "'..' is not allowed"),
    (lambda f: "meshes/../meshes/ceiling.ply", "'..' is not allowed"),
    (_link_out, "leaves the scene folder"),
    (_fifo, "not a regular file"),
])
def test_scene_mesh_paths_stay_in_the_folder(folder, path, reason):
    """Issue 22: a scene.xml naming /dev/zero or a FIFO hung ``info`` and ``trace``;
    absolute and ``..`` paths read anything on the host. One line naming the files."""
    name = path(folder)
    _xml_edit(folder, 'value="meshes/ceiling.ply"', f'value="{name}"')
    with pytest.raises(ConfigError) as err:
        load_scene(folder, load_sionna=False)
    msg = str(err.value)
    assert "\n" not in msg and "scene.xml: object 'ceiling'" in msg and reason in msg


def test_oversized_mesh_is_refused_before_reading(tmp_path):
    from isac_twin import MeshError

    big = tmp_path / "big.ply"
    with big.open("wb") as f:
        f.truncate(2000)
    with pytest.raises(MeshError,
                       match=r"big\.ply: 2000 bytes exceeds the size limit of 1000 bytes"):
        read_ply(big, max_bytes=1000)


# --------------------------------------------------------------- custom radio materials


def _concrete_at(f_hz):
    """ITU concrete's (eps_r, sigma S/m) at f from Sionna's own ITU-R P.2040 model."""
    from sionna.rt.radio_materials.itu import itu_material
    eps, sigma = itu_material("concrete", f_hz)
    return float(np.asarray(eps).reshape(-1)[0]), float(np.asarray(sigma).reshape(-1)[0])


def _custom_room(tmp_path, name, props, material_of_walls=None):
    from isac_twin.scene.synthetic import room_objects
    objs = room_objects((5.0, 4.0, 3.0), {})
    if material_of_walls:
        objs = [SyntheticObject(o.name, o.vertices, o.faces, material_of_walls, o.thickness)
                if o.name.startswith("wall") else o for o in objs]
    dev = [SyntheticDevice("AP1", "access_point", "tx", (1.0, 1.0, 2.0))]
    return write_scene_folder(tmp_path / name, objs, dev, [], custom_materials=props)


def test_custom_material_loads_as_sionna_radio_material(tmp_path):
    props = {"wet_wall": {"relative_permittivity": 7.5, "conductivity": 0.08, "thickness": 0.15}}
    folder = _custom_room(tmp_path, "c", props, "wet_wall")
    xml = (folder / "scene.xml").read_text()
    assert '<bsdf type="radio-material" id="mat-wet_wall">' in xml
    scene = load_scene(folder)
    assert scene.custom_materials == props
    assert scene.objects["wall_xmin"].material == "wet_wall"
    assert scene.objects["wall_xmin"].thickness == pytest.approx(0.15)
    m = scene.sionna.objects["wall_xmin"].radio_material
    assert float(m.relative_permittivity.numpy()[0]) == pytest.approx(7.5)
    assert float(m.conductivity.numpy()[0]) == pytest.approx(0.08)
    assert float(m.thickness.numpy()[0]) == pytest.approx(0.15)
    # the values are part of what the channel depends on
    props2 = {"wet_wall": dict(props["wet_wall"], relative_permittivity=7.6)}
    other = load_scene(_custom_room(tmp_path, "d", props2, "wet_wall"), load_sionna=False)
    assert other.content_hash() != scene.content_hash()


@pytest.mark.slow
def test_custom_material_with_itu_values_gives_the_itu_channel(tmp_path):
    """Reference: Sionna's ITU concrete. A custom material holding its values at the
    carrier must give the same paths' channel."""
    import mitsuba as mi
    import sionna.rt as rt
    eps, sigma = _concrete_at(2.4e9)
    props = {"concrete_like": {"relative_permittivity": eps, "conductivity": sigma,
                               "thickness": 0.2}}
    cfrs = []
    for name, mat in (("itu", None), ("custom", "concrete_like")):
        sc = load_scene(_custom_room(tmp_path, name, props, mat)).sionna
        sc.tx_array = sc.rx_array = rt.PlanarArray(num_rows=1, num_cols=1, pattern="iso",
                                                  polarization="V")
        sc.add(rt.Transmitter("t", position=mi.Point3f(1.0, 1.0, 2.0)))
        sc.add(rt.Receiver("r", position=mi.Point3f(3.5, 2.5, 1.0)))
        p = rt.PathSolver()(sc, max_depth=2, samples_per_src=20000, seed=1)
        h = p.cfr(frequencies=mi.Float(np.linspace(-5e6, 5e6, 8)), out_type="numpy")
        cfrs.append(np.asarray(h).reshape(-1))
    assert np.abs(cfrs[0]).max() > 0
    np.testing.assert_allclose(cfrs[1], cfrs[0], rtol=1e-4, atol=1e-4 * np.abs(cfrs[0]).max())


@pytest.mark.parametrize("props, msg", [
    ({"relative_permittivity": 0.5, "conductivity": 0.0, "thickness": 0.1},
     r"bsdf 'mat-bad': custom material 'bad': relative_permittivity: expected a value in "
     r"\[1, 10000\]"),
    ({"relative_permittivity": 4.0, "conductivity": -1.0, "thickness": 0.1},
     r"bsdf 'mat-bad': custom material 'bad': conductivity"),
    ({"relative_permittivity": 4.0, "conductivity": 0.0, "thickness": 0.0},
     r"bsdf 'mat-bad': custom material 'bad': thickness: expected a value in \(0, 10\] m"),
])
def test_bad_custom_material_is_refused_naming_the_bsdf(tmp_path, props, msg):
    folder = _custom_room(tmp_path, "ok", {"bad": {"relative_permittivity": 4.0,
                                                   "conductivity": 0.0, "thickness": 0.1}},
                          "bad")
    xml = (folder / "scene.xml").read_text()
    for k, v in props.items():  # write the bad value past the exporter's own check
        start = xml.index(f'<float name="{k}" value="', xml.index('id="mat-bad"'))
        end = xml.index('"/>', start)
        xml = xml[:start] + f'<float name="{k}" value="{v}' + xml[end:]
    (folder / "scene.xml").write_text(xml)
    with pytest.raises(ConfigError, match=r"scene\.xml: " + msg):
        load_scene(folder, load_sionna=False)


def test_custom_material_name_and_children_checked(tmp_path):
    folder = _custom_room(tmp_path, "n", {"wet": {"relative_permittivity": 4.0,
                                                   "conductivity": 0.0, "thickness": 0.1}}, "wet")
    _xml_edit(folder, 'id="mat-wet"', 'id="mat-brick"')
    _xml_edit(folder, '<ref id="mat-wet"', '<ref id="mat-brick"')
    with pytest.raises(ConfigError, match="custom material 'brick': the name is an ITU"):
        load_scene(folder, load_sionna=False)
    folder = _custom_room(tmp_path, "m", {"wet": {"relative_permittivity": 4.0,
                                                   "conductivity": 0.0, "thickness": 0.1}}, "wet")
    _xml_edit(folder, '<float name="conductivity"', '<float name="roughness"')
    with pytest.raises(ConfigError, match=r"bsdf 'mat-wet': <float name='roughness'> is not "
                                          r"supported"):
        load_scene(folder, load_sionna=False)


def test_set_material_to_a_custom_material(tmp_path):
    props = {"wet": {"relative_permittivity": 9.0, "conductivity": 0.2, "thickness": 0.12}}
    scene = load_scene(_custom_room(tmp_path, "s", props, "wet"))
    h0 = scene.content_hash()
    scene.set_material("floor", "wet")
    assert scene.objects["floor"].material == "wet"
    assert scene.objects["floor"].thickness == pytest.approx(0.12)
    m = scene.sionna.objects["floor"].radio_material
    assert float(m.relative_permittivity.numpy()[0]) == pytest.approx(9.0)
    assert scene.content_hash() != h0
    with pytest.raises(ValueError, match="custom material 'wet' has its own thickness 0.12 m"):
        scene.set_material("ceiling", "wet", 0.3)
    with pytest.raises(ValueError, match=r"unknown material 'dry'.*custom one of the scene "
                                         r"\(wet\)"):
        scene.set_material("ceiling", "dry")
    scene.set_material("floor", "concrete", 0.2)  # and back to ITU
    assert scene.objects["floor"].material == "concrete"
