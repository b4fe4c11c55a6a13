"""Property groups stored on objects (``Object.isac``) and scenes (``Scene.isac``).

Only data definitions live here; every rule that uses them is in the plain
modules (``materials``, ``devices``, ``exporter``). Dimension-like integers
use ``soft_min`` rather than a hard ``min`` so a bad value set from a script
is reported by the exporter with the object's name instead of being clamped
silently.
"""

from __future__ import annotations

import bpy
from bpy.props import (
    BoolProperty,
    CollectionProperty,
    EnumProperty,
    FloatProperty,
    FloatVectorProperty,
    IntProperty,
    PointerProperty,
    StringProperty,
)

from . import materials
from .contract import schema


def _items(table: dict) -> list[tuple[str, str, str]]:
    """Enum items ``(identifier, label, description)`` of a ``schema`` table."""
    return [(k, label, desc) for k, (label, desc) in table.items()]


# The value lists are the schema's (addon/contract/schema.py, shared with the engine).
#: device kinds: "NONE" (scene geometry), then the schema's kinds upper-cased
DEVICE_KINDS = [("NONE", "Geometry",
                 "Scene geometry (exported to scene.xml when it has a radio material)")] + [
    (k.upper(), label, desc) for k, (label, desc) in schema.DEVICE_KINDS.items()]
ROLES = _items(schema.ROLES)
PATTERNS = _items(schema.PATTERNS)
POLARIZATIONS = _items(schema.POLARIZATIONS)
ROBOT_MODELS = [(k, body.label, "") for k, body in schema.ROBOT_MODELS.items()]
PATH_DIRECTIONS = _items(schema.PATH_DIRECTIONS)
ROOM_PARTS = [("AUTO", "Auto", "Decided by the engine from the geometry (large boundary "
                                "slabs and full-height walls are shell)"),
              ("SHELL", "Shell", "Walls, floor, ceiling, windows, doors: fixed structure"),
              ("FURNITURE", "Furniture", "Movable contents of the room")]

_MATERIAL_ITEMS = materials.material_enum_items()  # keep a reference: bpy needs it alive


class ISAC_ObjectProps(bpy.types.PropertyGroup):
    """Radio settings of one object: material for geometry, array and role for devices."""

    device_kind: EnumProperty(name="Kind", items=DEVICE_KINDS, default="NONE")
    export_geometry: BoolProperty(
        name="Export geometry", default=True,
        description="Write this mesh into scene.xml (off for helpers such as boolean cutters)")
    itu_material: EnumProperty(name="ITU material", items=_MATERIAL_ITEMS, default=0)
    custom_material: StringProperty(
        name="Custom material", default="",
        description="One of the scene's custom radio materials (Radio materials list); "
                    "when set it replaces the ITU material and thickness")
    thickness: FloatProperty(name="Thickness", default=materials.DEFAULT_THICKNESS_M,
                             soft_min=0.001, unit="LENGTH", precision=3,
                             description="Slab thickness of the radio material, m")
    room_part: EnumProperty(name="Room part", default="AUTO", items=ROOM_PARTS,
                            description="Shell (walls, floor, ceiling, windows: fixed) or "
                                        "furniture (moved in a perturbed room, drawn as an "
                                        "obstacle); written to twin.toml's [room]")
    # devices
    role: EnumProperty(name="Role", items=ROLES, default="tx")
    power_dbm: FloatProperty(name="Tx power (dBm)", default=20.0,
                             description="Total transmit power over the resource set, dBm")
    array_rows: IntProperty(name="Rows", default=1, soft_min=1, description="Array rows")
    array_cols: IntProperty(name="Columns", default=1, soft_min=1, description="Array columns")
    vertical_spacing: FloatProperty(name="Vertical spacing",
                                    default=schema.DEFAULT_ELEMENT_SPACING, soft_min=0.01,
                                    description="Element spacing between rows, wavelengths")
    horizontal_spacing: FloatProperty(name="Horizontal spacing",
                                      default=schema.DEFAULT_ELEMENT_SPACING, soft_min=0.01,
                                      description="Element spacing between columns, wavelengths")
    pattern: EnumProperty(name="Pattern", items=PATTERNS, default=schema.DEFAULT_PATTERN)
    polarization: EnumProperty(name="Polarization", items=POLARIZATIONS,
                               default=schema.DEFAULT_POLARIZATION)
    robot_model: EnumProperty(name="Robot model", items=ROBOT_MODELS,
                              default=schema.DEFAULT_ROBOT_MODEL)
    antenna_offset: FloatVectorProperty(name="Antenna offset", size=3,
                                        default=schema.DEFAULT_ANTENNA_OFFSET,
                                        subtype="TRANSLATION", unit="LENGTH",
                                        description="Array centre in base_link, m")
    # resource set R_q (transmitters): half-open ranges; all four 0 = the whole grid
    subcarrier_start: IntProperty(name="First subcarrier", default=0, min=0)
    subcarrier_stop: IntProperty(name="Stop subcarrier", default=0, min=0,
                                 description="One past the last subcarrier (0 = all)")
    symbol_start: IntProperty(name="First symbol", default=0, min=0)
    symbol_stop: IntProperty(name="Stop symbol", default=0, min=0,
                             description="One past the last OFDM symbol (0 = all)")
    # robots: the path the twin's controller follows
    path_kind: EnumProperty(name="Path", default="NONE", items=[
        ("NONE", "None", "No path: the robot stands until commanded"),
        ("circle", "Circle", "Pure pursuit on a circle"),
        ("polyline", "Polyline (curve)",
         "Pure pursuit along a Blender curve object's points (open or cyclic)"),
        ("figure_eight", "Figure eight", "Pure pursuit on a lemniscate, size wide"),
        ("goal", "Goal", "Drive straight to a goal point and stop")])
    path_curve: PointerProperty(name="Curve", type=bpy.types.Object,
                                poll=lambda self, obj: obj.type == "CURVE",
                                description="Curve object whose points (world XY) are the "
                                            "robot's waypoints; a cyclic spline is a closed loop")
    path_size: FloatProperty(name="Size", default=2.0, min=0.0, unit="LENGTH",
                             description="Figure eight: width along x, m (height is half)")
    path_goal: FloatVectorProperty(name="Goal", size=2, default=(0.0, 0.0), subtype="XYZ",
                                   unit="LENGTH", description="Goal point (x, y), m")
    path_centre: FloatVectorProperty(name="Centre", size=2, default=(0.0, 0.0),
                                     subtype="XYZ", unit="LENGTH")
    path_radius: FloatProperty(name="Radius", default=1.0, min=0.0, unit="LENGTH")
    path_direction: EnumProperty(name="Direction", default=schema.DEFAULT_PATH_DIRECTION,
                                 items=PATH_DIRECTIONS)
    path_speed: FloatProperty(name="Speed", default=0.0, min=0.0,
                              description="Cruise speed, m/s (0 = the model's limit)")


class ISAC_LinkItem(bpy.types.PropertyGroup):
    """One edge of the network graph: transmitter -> receiver (device object names)."""

    tx: StringProperty(name="Tx", description="Transmitting device (object name)")
    rx: StringProperty(name="Rx", description="Receiving device (object name)")


class ISAC_SensingItem(bpy.types.PropertyGroup):
    """One sensing (radar) link: tx -> rx (rx = tx: monostatic), written as [[sensing]]."""

    tx: StringProperty(name="Tx", description="Transmitting device (object name)")
    rx: StringProperty(name="Rx", description="Receiving device; the same as Tx: monostatic")
    rho: FloatProperty(name="Sensing share", default=0.25, min=0.001, max=1.0,
                       description="Share of the resource elements carrying sensing symbols")
    every: IntProperty(name="Every N steps", default=1, min=1,
                       description="Run the radar every this many twin steps")


def _custom_property(key: str, label: str, default: float, **kw):
    prop = schema.CUSTOM_MATERIAL_PROPERTIES[key]
    return FloatProperty(name=label, default=default, description=f"{prop.description}"
                         + (f", {prop.unit}" if prop.unit else ""), **kw)


class ISAC_CustomMaterial(bpy.types.PropertyGroup):
    """A custom radio material (``name`` is its name): values at the carrier, written to
    scene.xml as Sionna's ``radio-material`` (schema.CUSTOM_MATERIAL_PROPERTIES)."""

    relative_permittivity: _custom_property("relative_permittivity", "Permittivity", 4.0,
                                            soft_min=1.0)
    conductivity: _custom_property("conductivity", "Conductivity (S/m)", 0.0, soft_min=0.0)
    thickness: _custom_property("thickness", "Thickness", materials.DEFAULT_THICKNESS_M,
                                soft_min=0.001, unit="LENGTH", precision=3)


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
    sensing_links: CollectionProperty(type=ISAC_SensingItem)
    radio_materials: CollectionProperty(type=ISAC_CustomMaterial)
    placement_warnings: StringProperty(
        name="Placement warnings", default="",
        description="Devices or path points not in free space, one per line (Check Placement)")
    export_directory: StringProperty(name="Scene folder", subtype="DIR_PATH", default="//scene",
                                     options={"PATH_SUPPORTS_BLEND_RELATIVE"},
                                     description="Folder the exporter writes")


class ISAC_LiveLinkMetric(bpy.types.PropertyGroup):
    """One link's latest metrics from the live engine (read-only for the user)."""

    tx: StringProperty(name="Tx")
    rx: StringProperty(name="Rx")
    snr_db: FloatProperty(name="SNR (dB)", description="Mean received SNR, dB")
    rate_bps: FloatProperty(name="Rate (bit/s)", description="Achievable rate, bit/s")
    mcs_rate_bps: FloatProperty(name="MCS rate (bit/s)", default=float("nan"),
                                description="Rate through the MCS table (a modem's), bit/s")
    num_paths: IntProperty(name="Paths")
    los: BoolProperty(name="LOS")


RAY_COLOR_MODES = [("POWER", "Power", "Colour rays by path power (strongest yellow)"),
                   ("TYPE", "Interaction", "Colour ray points by interaction type")]


def _radiomap_visibility(props, context) -> None:
    from . import radiomap_view

    radiomap_view.set_visible(context.scene, props.show_radiomap)


class ISAC_LiveProps(bpy.types.PropertyGroup):
    """Live link settings and the latest engine state shown in the Live panel."""

    host: StringProperty(name="Host", default="127.0.0.1", description="Engine address")
    port: IntProperty(name="Port", default=8765, min=0, max=65535, description="Engine TCP port")
    token: StringProperty(name="Token", default="", subtype="PASSWORD",
                          description="Auth token the engine expects (empty = none)")
    ray_color_mode: EnumProperty(name="Ray colour", items=RAY_COLOR_MODES, default="POWER")
    show_rays: BoolProperty(name="Show rays", default=True)
    max_paths_per_link: IntProperty(name="Rays per link", default=0, min=0,
                                    description="Draw at most this many rays per link "
                                                "(the strongest; 0 = all sent)")
    ray_width_by_power: BoolProperty(name="Width by power", default=True,
                                     description="Thicker rays for stronger paths "
                                                 "(on the rays' dB scale)")
    ray_opacity_by_power: BoolProperty(name="Opacity by power", default=False,
                                       description="Weaker paths more transparent "
                                                   "(on the rays' dB scale)")
    show_radiomap: BoolProperty(name="Show radio map", default=True,
                                update=_radiomap_visibility,
                                description="Show the floor radio map and its colour scale "
                                            "(the engine sends one with serve --radiomap)")
    radiomap_layer: StringProperty(name="Radio map layer", default="",
                                   description="Layer shown: an access point's RSS, 'best' "
                                               "(best server) or 'sinr'")
    radiomap_layers: StringProperty(name="Radio map layers", default="",
                                    description="Layers of the last radio map (comma-separated)")
    # state written by the live view (addon/live_view.py)
    connection: StringProperty(name="Connection", default="idle")
    last_error: StringProperty(name="Last error", default="")
    engine_name: StringProperty(name="Engine")
    scene_name: StringProperty(name="Engine scene")
    scene_hash: StringProperty(name="Scene hash")
    running: BoolProperty(name="Running")
    step: IntProperty(name="Step")
    engine_step: IntProperty(name="Engine step")
    paths_step: IntProperty(name="Paths step", default=-1)
    metrics_step: IntProperty(name="Metrics step", default=-1)
    time_s: FloatProperty(name="Time (s)", unit="TIME_ABSOLUTE")
    num_rays: IntProperty(name="Rays drawn")
    edits_applied: IntProperty(name="Edits applied")
    rejected: IntProperty(name="Rejected frames")
    links: CollectionProperty(type=ISAC_LiveLinkMetric)


class ISAC_AddonPreferences(bpy.types.AddonPreferences):
    """Where the engine lives, for starting a local ``isac-twin serve`` from the Live panel."""

    bl_idname = __package__

    engine_python: StringProperty(
        name="Engine interpreter", subtype="FILE_PATH", default="",
        description="Python interpreter with the isac-twin engine installed "
                    "(e.g. <repo>/.venv/bin/python); empty = the interpreter running Blender")
    engine_scene: StringProperty(
        name="Engine scene", subtype="DIR_PATH", default="",
        description="Scene folder the local engine serves; empty = the engine's bundled lab")
    engine_args: StringProperty(name="Extra arguments", default="--rate 10",
                                description="More 'isac-twin serve' arguments")

    def draw(self, context):
        for key in ("engine_python", "engine_scene", "engine_args"):
            self.layout.prop(self, key)


def addon_preferences(context=None):
    """The add-on's preferences, or None when it is registered without being enabled."""
    context = context or bpy.context
    entry = context.preferences.addons.get(__package__)
    return entry.preferences if entry is not None else None


CLASSES = (ISAC_ObjectProps, ISAC_LinkItem, ISAC_SensingItem, ISAC_CustomMaterial,
           ISAC_SceneProps, ISAC_LiveLinkMetric, ISAC_LiveProps,
           ISAC_AddonPreferences)


def register() -> None:
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Object.isac = PointerProperty(type=ISAC_ObjectProps)
    bpy.types.Scene.isac = PointerProperty(type=ISAC_SceneProps)
    bpy.types.Scene.isac_live = PointerProperty(type=ISAC_LiveProps)


def unregister() -> None:
    del bpy.types.Scene.isac_live
    del bpy.types.Scene.isac
    del bpy.types.Object.isac
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
