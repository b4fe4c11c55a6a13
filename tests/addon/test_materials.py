"""ITU material table (vs Sionna's), tagging and frequency-band checks."""

from __future__ import annotations

import pytest

bpy = pytest.importorskip("bpy")

pytestmark = pytest.mark.blender


def test_table_matches_sionna():
    """The add-on's copy of the ITU table must not drift from Sionna's."""
    itu = pytest.importorskip("sionna.rt.radio_materials.itu")
    from addon.materials import ITU_MATERIALS

    theirs = {name: tuple(bands.keys()) for name, bands in itu.ITU_MATERIALS_PROPERTIES.items()}
    assert list(ITU_MATERIALS) == list(theirs)
    for name, bands in theirs.items():
        assert ITU_MATERIALS[name] == tuple((float(lo), float(hi)) for lo, hi in bands), name


def test_enum_offers_every_material(addon_module):
    from addon.materials import ITU_MATERIALS

    items = bpy.types.Object.bl_rna.properties["isac"].fixed_type.bl_rna \
        .properties["itu_material"].enum_items.keys()
    assert items == ["none", *ITU_MATERIALS]


@pytest.mark.parametrize("material, f_hz, ok", [
    ("floorboard", 2.4e9, False), ("floorboard", 60e9, True), ("concrete", 2.4e9, True),
    ("concrete", 105e9, False), ("wet_ground", 28e9, False), ("wood", 2e6, True),
    ("metal", 1e9, True), ("metal", 0.9e9, False), ("clear_acrylic", 2.4e9, False),
])
def test_is_defined_at(material, f_hz, ok):
    from addon.materials import is_defined_at

    assert is_defined_at(material, f_hz) is ok


def test_band_warnings_name_object_material_frequency(scene):
    from addon import materials, modelling

    room = modelling.create_room(4.0, 3.0, 2.5, floor_material="floorboard", scene=scene)
    modelling.add_furniture("chair", scene=scene)
    warnings = materials.band_warnings(scene)
    assert len(warnings) == 1
    assert "Room_Floor" in warnings[0] and "floorboard" in warnings[0]
    assert "2.4 GHz" in warnings[0] and "50-100 GHz" in warnings[0]
    scene.isac.frequency_hz = 60e9
    assert materials.band_warnings(scene) == []
    room["floor"].isac.itu_material = "concrete"
    scene.isac.frequency_hz = 2.4e9
    assert materials.band_warnings(scene) == []


def test_tag_objects_bulk(scene):
    from addon import devices, materials, modelling

    objs = [modelling.add_furniture("table", scene=scene) for _ in range(3)]
    ap = devices.add_access_point("AP", scene=scene)
    assert materials.tag_objects([*objs, ap], "marble", 0.04) == 3
    assert all(o.isac.itu_material == "marble" for o in objs)
    with pytest.raises(ValueError, match="unobtainium"):
        materials.tag_objects(objs, "unobtainium")
    with pytest.raises(ValueError, match="Thickness"):
        materials.tag_objects(objs, "wood", 0.0)
