"""Radio materials: the ITU-R P.2040 table Sionna RT supports, tagging and band checks.

The add-on cannot import Sionna, so the material names and their valid
frequency bands are copied here from
``sionna.rt.radio_materials.itu.ITU_MATERIALS_PROPERTIES`` (Sionna RT 2.2).
``tests/addon/test_materials.py`` compares this table against Sionna's so
any drift is caught.
"""

from __future__ import annotations

from typing import Iterable

from .contract import schema

# material name -> valid frequency bands as (min, max) in GHz, inclusive,
# in the same order as Sionna's table.
ITU_MATERIALS: dict[str, tuple[tuple[float, float], ...]] = {
    "vacuum": ((0.001, 100.0),),
    "concrete": ((1.0, 100.0), (110.0, 330.0)),
    "brick": ((1.0, 40.0), (110.0, 330.0)),
    "plasterboard": ((1.0, 100.0), (110.0, 330.0), (100.0, 400.0)),
    "wood": ((0.001, 100.0), (110.0, 330.0), (100.0, 400.0)),
    "glass": ((0.1, 100.0), (220.0, 450.0), (100.0, 400.0)),
    "clear_acrylic": ((110.0, 330.0),),
    "ceiling_board": ((1.0, 100.0), (220.0, 450.0), (100.0, 400.0)),
    "chipboard": ((1.0, 100.0), (100.0, 200.0)),
    "plywood": ((1.0, 40.0), (110.0, 330.0), (100.0, 400.0)),
    "marble": ((1.0, 60.0), (110.0, 330.0), (100.0, 400.0)),
    "floorboard": ((50.0, 100.0), (220.0, 300.0), (300.0, 400.0),
                   (400.0, 450.0), (100.0, 400.0)),
    "vinyl_tile": ((1.0, 40.0),),
    "carpet_tile": ((1.0, 40.0),),
    "asphalt_concrete": ((1.0, 40.0),),
    "metal": ((1.0, 100.0),),
    "very_dry_ground": ((1.0, 10.0),),
    "medium_dry_ground": ((1.0, 10.0),),
    "wet_ground": ((1.0, 10.0),),
}

#: Property value meaning "no radio material assigned yet".
NO_MATERIAL = "none"

#: Default slab thickness per material, m (used when tagging without one).
DEFAULT_THICKNESS_M = 0.1


def material_enum_items() -> list[tuple[str, str, str]]:
    """Items for a bpy ``EnumProperty``: unset first, then every ITU material."""
    items = [(NO_MATERIAL, "None", "No radio material: export refuses this object")]
    for name, bands in ITU_MATERIALS.items():
        label = name.replace("_", " ").title()
        items.append((name, label, f"ITU-R P.2040 {name}, valid at {format_bands(bands)}"))
    return items


def format_bands(bands: Iterable[tuple[float, float]]) -> str:
    """Human-readable band list, e.g. ``"1-100 GHz, 110-330 GHz"``."""
    return ", ".join(f"{_g(lo)}-{_g(hi)} GHz" for lo, hi in bands)


def _g(x: float) -> str:
    return f"{x:g}"


def is_defined_at(material: str, frequency_hz: float) -> bool:
    """True when Sionna defines ``material`` at ``frequency_hz`` (Hz).

    Same rule as Sionna's ``itu_material``: ``lo <= f_GHz <= hi`` for some band.
    """
    if material not in ITU_MATERIALS:
        return False
    f_ghz = frequency_hz / 1e9
    return any(lo <= f_ghz <= hi for lo, hi in ITU_MATERIALS[material])


def band_message(object_name: str, material: str, frequency_hz: float) -> str:
    """The warning/error text for a material used outside its bands."""
    bands = ITU_MATERIALS.get(material, ())
    return (f"Object '{object_name}': ITU material '{material}' is not defined at "
            f"{frequency_hz / 1e9:g} GHz (valid: {format_bands(bands)})")


def band_warnings(scene, objects=None) -> list[str]:
    """Warnings for every tagged object whose material is undefined at the scene frequency.

    Args:
        scene: ``bpy.types.Scene`` with ``scene.isac.frequency_hz`` (Hz).
        objects: objects to check; defaults to all objects of ``scene``.

    Returns:
        One message per offending object (names the object, material and
        frequency), sorted by object name. Empty when all is well.
    """
    freq = float(scene.isac.frequency_hz)
    objs = scene.objects if objects is None else objects
    out = []
    for obj in sorted(objs, key=lambda o: o.name):
        props = getattr(obj, "isac", None)
        if (props is None or obj.type != "MESH" or props.device_kind != "NONE"
                or props.custom_material):  # a custom material has no band
            continue
        mat = props.itu_material
        if mat != NO_MATERIAL and not is_defined_at(mat, freq):
            out.append(band_message(obj.name, mat, freq))
    return out


def tag_objects(objects, material: str, thickness: float = DEFAULT_THICKNESS_M) -> int:
    """Assign an ITU radio material and slab thickness to many objects at once.

    Args:
        objects: iterable of ``bpy.types.Object``; non-mesh objects are skipped.
        material: an ``ITU_MATERIALS`` key.
        thickness: slab thickness, m, > 0.

    Returns:
        Number of objects tagged.

    Raises:
        ValueError: unknown material or non-positive thickness.
    """
    if material not in ITU_MATERIALS:
        raise ValueError(f"Unknown ITU material '{material}'; "
                         f"choose one of {', '.join(ITU_MATERIALS)}")
    if not thickness > 0:
        raise ValueError(f"Thickness must be > 0 m, got {thickness}")
    n = 0
    for obj in objects:
        if obj.type != "MESH":
            continue
        obj.isac.itu_material = material
        obj.isac.thickness = thickness
        obj.isac.custom_material = ""  # the ITU tag is what the object now uses
        n += 1
    return n


def custom_table(scene) -> dict[str, dict[str, float]]:
    """The scene's custom radio materials, ``name -> {property: value}``
    (``schema.CUSTOM_MATERIAL_PROPERTIES``; permittivity, S/m, m)."""
    return {m.name: {k: float(getattr(m, k)) for k in schema.CUSTOM_MATERIAL_PROPERTIES}
            for m in scene.isac.radio_materials}


def set_custom_material(scene, name: str, values: dict) -> object:
    """Add custom radio material ``name`` to ``scene`` or update it; return its item.

    Args:
        values: every key of ``schema.CUSTOM_MATERIAL_PROPERTIES`` (permittivity,
            conductivity S/m, thickness m).

    Raises:
        ValueError: a bad name or value (the schema's message).
    """
    problems = schema.custom_material_problems(name, values, ITU_MATERIALS)
    if problems:
        raise ValueError(problems[0])
    coll = scene.isac.radio_materials
    item = coll.get(name)
    if item is None:
        item = coll.add()
        item.name = name
    for k in schema.CUSTOM_MATERIAL_PROPERTIES:
        setattr(item, k, float(values[k]))
    return item


def assign_custom_material(objects, scene, name: str) -> int:
    """Make ``objects`` (meshes; others skipped) use custom material ``name`` of ``scene``;
    return how many. Raises ValueError when the scene has no such material."""
    if scene.isac.radio_materials.get(name) is None:
        raise ValueError(f"No custom radio material '{name}' in the scene (have: "
                         f"{', '.join(m.name for m in scene.isac.radio_materials) or 'none'})")
    n = 0
    for obj in objects:
        if obj.type == "MESH":
            obj.isac.custom_material = name
            n += 1
    return n
