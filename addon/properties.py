"""Property groups stored on objects (``Object.isac``) and scenes (``Scene.isac``).

Only data definitions live here; every rule that uses them is in the plain
modules (``materials``, ``devices``, ``exporter``). Dimension-like integers
use ``soft_min`` rather than a hard ``min`` so a bad value set from a script
is reported by the exporter with the object's name instead of being clamped
silently.
"""

from __future__ import annotations

import bpy
from bpy.props import (BoolProperty, CollectionProperty, EnumProperty, FloatProperty,
                       FloatVectorProperty, IntProperty, PointerProperty, StringProperty)

from . import materials

DEVICE_KINDS = [
    ("NONE", "Geometry", "Scene geometry (exported to scene.xml when it has a radio material)"),
    ("ACCESS_POINT", "Access point", "Radio access point (not exported as geometry)"),
    ("ROBOT", "Robot", "Mobile robot carrying an antenna array (not exported as geometry)"),
]
ROLES = [("tx", "Tx", "Transmitter"), ("rx", "Rx", "Receiver"),
         ("txrx", "Tx/Rx", "Transmitter and receiver")]
PATTERNS = [("iso", "Isotropic", ""), ("dipole", "Short dipole", ""),
            ("hw_dipole", "Half-wave dipole", ""), ("tr38901", "3GPP TR 38.901", "")]
POLARIZATIONS = [("V", "V", "Vertical"), ("H", "H", "Horizontal"),
                 ("VH", "VH", "Dual: vertical and horizontal"),
                 ("cross", "Cross", "Dual: +/-45 degrees")]
ROBOT_MODELS = [("burger", "TurtleBot3 Burger", ""), ("waffle", "TurtleBot3 Waffle", "")]

_MATERIAL_ITEMS = materials.material_enum_items()  # keep a reference: bpy needs it alive


class ISAC_ObjectProps(bpy.types.PropertyGroup):
    """Radio settings of one object: material for geometry, array and role for devices."""

    device_kind: EnumProperty(name="Kind", items=DEVICE_KINDS, default="NONE")
    export_geometry: BoolProperty(
        name="Export geometry", default=True,
        description="Write this mesh into scene.xml (off for helpers such as boolean cutters)")
    itu_material: EnumProperty(name="ITU material", items=_MATERIAL_ITEMS, default=0)
    thickness: FloatProperty(name="Thickness", default=materials.DEFAULT_THICKNESS_M,
                             soft_min=0.001, unit="LENGTH", precision=3,
                             description="Slab thickness of the radio material, m")
    # devices
    role: EnumProperty(name="Role", items=ROLES, default="tx")
    power_dbm: FloatProperty(name="Tx power (dBm)", default=20.0,
                             description="Total transmit power over the resource set, dBm")
    array_rows: IntProperty(name="Rows", default=1, soft_min=1, description="Array rows")
    array_cols: IntProperty(name="Columns", default=1, soft_min=1, description="Array columns")
    vertical_spacing: FloatProperty(name="Vertical spacing", default=0.5, soft_min=0.01,
                                    description="Element spacing between rows, wavelengths")
    horizontal_spacing: FloatProperty(name="Horizontal spacing", default=0.5, soft_min=0.01,
                                      description="Element spacing between columns, wavelengths")
    pattern: EnumProperty(name="Pattern", items=PATTERNS, default="iso")
    polarization: EnumProperty(name="Polarization", items=POLARIZATIONS, default="V")
    robot_model: EnumProperty(name="Robot model", items=ROBOT_MODELS, default="burger")
    antenna_offset: FloatVectorProperty(name="Antenna offset", size=3, default=(0.0, 0.0, 0.25),
                                        subtype="TRANSLATION", unit="LENGTH",
                                        description="Array centre in base_link, m")


class ISAC_LinkItem(bpy.types.PropertyGroup):
    """One edge of the network graph: transmitter -> receiver (device object names)."""

    tx: StringProperty(name="Tx", description="Transmitting device (object name)")
    rx: StringProperty(name="Rx", description="Receiving device (object name)")


class ISAC_SceneProps(bpy.types.PropertyGroup):
    """Scene-wide radio settings written to twin.toml."""

    twin_name: StringProperty(name="Twin name", default="",
                              description="[scene] name in twin.toml; empty = Blender scene name")
    frequency_hz: FloatProperty(name="Frequency (Hz)", default=2.4e9, soft_min=1e6,
                                description="Carrier frequency, Hz")
    num_subcarriers: IntProperty(name="Subcarriers N", default=1024, soft_min=1)
    subcarrier_spacing_hz: FloatProperty(name="Spacing (Hz)", default=78125.0, soft_min=1.0,
                                         description="Subcarrier spacing delta f, Hz")
    num_symbols: IntProperty(name="Symbols K", default=14, soft_min=1,
                             description="OFDM symbols per twin step")
    cyclic_prefix_samples: IntProperty(name="CP samples", default=72, soft_min=0)
    links: CollectionProperty(type=ISAC_LinkItem)
    links_index: IntProperty(name="Active link", default=0)
    export_directory: StringProperty(name="Scene folder", subtype="DIR_PATH", default="//scene",
                                     options={"PATH_SUPPORTS_BLEND_RELATIVE"},
                                     description="Folder the exporter writes")


CLASSES = (ISAC_ObjectProps, ISAC_LinkItem, ISAC_SceneProps)


def register() -> None:
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Object.isac = PointerProperty(type=ISAC_ObjectProps)
    bpy.types.Scene.isac = PointerProperty(type=ISAC_SceneProps)


def unregister() -> None:
    del bpy.types.Scene.isac
    del bpy.types.Object.isac
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
