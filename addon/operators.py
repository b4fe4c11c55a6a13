"""Operators: thin, undoable wrappers around the plain functions."""

from __future__ import annotations

import math

import bpy
from bpy.props import (
    EnumProperty,
    FloatProperty,
    FloatVectorProperty,
    IntProperty,
    IntVectorProperty,
    StringProperty,
)

from . import (
    calibration,
    devices,
    live,
    live_view,
    materials,
    modelling,
    placement,
    radiomap_view,
)
from .contract import schema
from .exporter import ExportError, export_scene
from .properties import PATTERNS, POLARIZATIONS, ROBOT_MODELS, ROLES, ROOM_PARTS, addon_preferences

_OPTS = {"REGISTER", "UNDO"}
_FURNITURE_ITEMS = [(k, k.replace("_", " ").title(), "") for k in modelling.FURNITURE_PRESETS]
_MATERIAL_ITEMS = [i for i in materials.material_enum_items() if i[0] != materials.NO_MATERIAL]


def parse_polygon(text: str) -> list[tuple[float, float]]:
    """Parse ``"x0,y0; x1,y1; ..."`` (m) into [(x, y), ...]; raises ValueError on bad text."""
    pts = []
    for chunk in text.replace("\n", ";").split(";"):
        if chunk.strip():
            parts = chunk.replace(" ", "").split(",")
            if len(parts) != 2:
                raise ValueError(f"Bad vertex '{chunk.strip()}': expected 'x,y'")
            pts.append((float(parts[0]), float(parts[1])))
    return pts


class _Reporting:
    """Run ``self.run(context)``; turn ValueError into an operator error report."""

    def execute(self, context):
        try:
            self.run(context)
        except (ValueError, IndexError) as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        return {"FINISHED"}


class ISAC_OT_add_room(_Reporting, bpy.types.Operator):
    """Add a rectangular room (floor, ceiling, four walls) from a ground plan"""

    bl_idname = "isac.add_room"
    bl_label = "Add Room"
    bl_options = _OPTS

    width: FloatProperty(name="Width (x)", default=8.0, min=0.01, unit="LENGTH")
    depth: FloatProperty(name="Depth (y)", default=6.0, min=0.01, unit="LENGTH")
    height: FloatProperty(name="Height", default=3.0, min=0.01, unit="LENGTH")
    wall_thickness: FloatProperty(name="Wall thickness", default=0.2, min=0.001, unit="LENGTH")
    name: StringProperty(name="Name", default="Room")

    def run(self, context):
        modelling.create_room(self.width, self.depth, self.height, self.wall_thickness,
                              name=self.name, scene=context.scene)


class ISAC_OT_add_room_polygon(_Reporting, bpy.types.Operator):
    """Add a room whose footprint is a polygon given as 'x,y; x,y; ...' in metres"""

    bl_idname = "isac.add_room_polygon"
    bl_label = "Add Room from Footprint"
    bl_options = _OPTS

    vertices: StringProperty(name="Footprint", default="0,0; 6,0; 6,4; 3,6; 0,4")
    height: FloatProperty(name="Height", default=3.0, min=0.01, unit="LENGTH")
    wall_thickness: FloatProperty(name="Wall thickness", default=0.2, min=0.001, unit="LENGTH")
    name: StringProperty(name="Name", default="Room")
    wall_material: EnumProperty(name="Walls", items=_MATERIAL_ITEMS, default="concrete")
    floor_material: EnumProperty(name="Floor", items=_MATERIAL_ITEMS, default="concrete")
    ceiling_material: EnumProperty(name="Ceiling", items=_MATERIAL_ITEMS,
                                   default="ceiling_board")

    def run(self, context):
        modelling.create_room_from_polygon(parse_polygon(self.vertices), self.height,
                                           self.wall_thickness, name=self.name,
                                           wall_material=self.wall_material,
                                           floor_material=self.floor_material,
                                           ceiling_material=self.ceiling_material,
                                           scene=context.scene)


class ISAC_OT_add_box(_Reporting, bpy.types.Operator):
    """Add a plain box of any size and ITU material (a partition, a column, a cupboard)"""

    bl_idname = "isac.add_box"
    bl_label = "Add Box"
    bl_options = _OPTS

    name: StringProperty(name="Name", default="Box")
    dimensions: FloatVectorProperty(name="Size", size=3, default=(1.0, 1.0, 1.0), min=0.001,
                                    subtype="XYZ", unit="LENGTH")
    location: FloatVectorProperty(name="Location", size=3, subtype="TRANSLATION", unit="LENGTH",
                                  description="Bottom-face centre, m")
    rotation_z: FloatProperty(name="Rotation Z", subtype="ANGLE", unit="ROTATION")
    material: EnumProperty(name="ITU material", items=_MATERIAL_ITEMS, default="concrete")
    thickness: FloatProperty(name="Thickness", default=0.1, min=0.0001, unit="LENGTH")
    room_part: EnumProperty(name="Room part", items=ROOM_PARTS, default="AUTO")

    def run(self, context):
        obj = modelling.add_box(self.name, tuple(self.dimensions), tuple(self.location),
                                self.rotation_z, material=self.material,
                                thickness=self.thickness, scene=context.scene)
        obj.isac.room_part = self.room_part


class ISAC_OT_add_furniture(_Reporting, bpy.types.Operator):
    """Add a furniture box from a preset"""

    bl_idname = "isac.add_furniture"
    bl_label = "Add Furniture"
    bl_options = _OPTS

    kind: EnumProperty(name="Preset", items=_FURNITURE_ITEMS, default="table")
    location: FloatVectorProperty(name="Location", size=3, subtype="TRANSLATION", unit="LENGTH")
    rotation_z: FloatProperty(name="Rotation Z", subtype="ANGLE", unit="ROTATION")

    def run(self, context):
        modelling.add_furniture(self.kind, tuple(self.location), self.rotation_z,
                                scene=context.scene)


class _ArrayProps:
    rows: IntProperty(name="Rows", default=1, min=1)
    cols: IntProperty(name="Columns", default=1, min=1)
    vertical_spacing: FloatProperty(name="Vertical spacing",
                                    default=schema.DEFAULT_ELEMENT_SPACING, min=0.01,
                                    description="Element spacing between rows, wavelengths")
    horizontal_spacing: FloatProperty(name="Horizontal spacing",
                                      default=schema.DEFAULT_ELEMENT_SPACING, min=0.01,
                                      description="Element spacing between columns, "
                                                  "wavelengths")
    pattern: EnumProperty(name="Pattern", items=PATTERNS, default=schema.DEFAULT_PATTERN)
    polarization: EnumProperty(name="Polarization", items=POLARIZATIONS,
                               default=schema.DEFAULT_POLARIZATION)


class ISAC_OT_add_access_point(_Reporting, _ArrayProps, bpy.types.Operator):
    """Add an access point (empty; +x is the array boresight)"""

    bl_idname = "isac.add_access_point"
    bl_label = "Add Access Point"
    bl_options = _OPTS

    name: StringProperty(name="Name", default="AP")
    location: FloatVectorProperty(name="Location", size=3, default=(0.0, 0.0, 2.0),
                                  subtype="TRANSLATION", unit="LENGTH")
    yaw: FloatProperty(name="Yaw", subtype="ANGLE", unit="ROTATION")
    power_dbm: FloatProperty(name="Power (dBm)", default=20.0)
    role: EnumProperty(name="Role", items=ROLES, default="tx")
    subcarriers: IntVectorProperty(name="Subcarriers [start, stop)", size=2, default=(0, 0),
                                   min=0, description="Resource set; 0, 0 = the whole grid")
    symbols: IntVectorProperty(name="Symbols [start, stop)", size=2, default=(0, 0), min=0,
                               description="Resource set; 0, 0 = all OFDM symbols")

    def run(self, context):
        devices.add_access_point(self.name, tuple(self.location), (0.0, 0.0, self.yaw),
                                 rows=self.rows, cols=self.cols,
                                 vertical_spacing=self.vertical_spacing,
                                 horizontal_spacing=self.horizontal_spacing,
                                 pattern=self.pattern,
                                 polarization=self.polarization, power_dbm=self.power_dbm,
                                 role=self.role,
                                 subcarriers=tuple(self.subcarriers) if any(self.subcarriers)
                                 else None,
                                 symbols=tuple(self.symbols) if any(self.symbols) else None,
                                 scene=context.scene)


class ISAC_OT_add_robot(_Reporting, _ArrayProps, bpy.types.Operator):
    """Add a TurtleBot3 robot carrying an antenna array"""

    bl_idname = "isac.add_robot"
    bl_label = "Add Robot"
    bl_options = _OPTS

    name: StringProperty(name="Name", default="robot")
    location: FloatVectorProperty(name="Location", size=3, subtype="TRANSLATION", unit="LENGTH")
    yaw: FloatProperty(name="Yaw", subtype="ANGLE", unit="ROTATION", default=math.pi / 2)
    model: EnumProperty(name="Model", items=ROBOT_MODELS, default=schema.DEFAULT_ROBOT_MODEL)
    role: EnumProperty(name="Role", items=ROLES, default="rx")

    def run(self, context):
        devices.add_robot(self.name, tuple(self.location), self.yaw, model=self.model,
                          rows=self.rows, cols=self.cols, vertical_spacing=self.vertical_spacing,
                          horizontal_spacing=self.horizontal_spacing, pattern=self.pattern,
                          polarization=self.polarization, role=self.role, scene=context.scene)


class ISAC_OT_robot_path_preset(_Reporting, bpy.types.Operator):
    """Give the active robot a path: a circle, a rectangle (an editable cyclic curve it
    follows as a polyline) or a figure eight, centred on a point"""

    bl_idname = "isac.robot_path_preset"
    bl_label = "Path Preset"
    bl_options = _OPTS

    preset: EnumProperty(name="Preset", default="rectangle", items=[
        ("circle", "Circle", "Radius = half the width"),
        ("rectangle", "Rectangle", "A closed polyline curve, width x depth"),
        ("figure_eight", "Figure eight", "Width along x, half as high")])
    centre: FloatVectorProperty(name="Centre", size=2, default=(2.0, 2.0), subtype="XYZ",
                                unit="LENGTH")
    width: FloatProperty(name="Width", default=2.0, min=0.01, unit="LENGTH")
    depth: FloatProperty(name="Depth", default=1.5, min=0.01, unit="LENGTH")

    def run(self, context):
        robot = context.active_object
        if robot is None or robot.isac.device_kind != "ROBOT":
            raise ValueError("Select a robot first: only robots follow paths")
        c = tuple(self.centre)
        if self.preset == "circle":
            devices.set_circle_path(robot, c, self.width / 2)
        elif self.preset == "figure_eight":
            devices.set_figure_eight_path(robot, c, self.width)
        else:
            devices.set_rectangle_path(robot, c, self.width, self.depth, scene=context.scene)


class ISAC_OT_tag_material(_Reporting, bpy.types.Operator):
    """Assign an ITU radio material and thickness to all selected meshes"""

    bl_idname = "isac.tag_material"
    bl_label = "Tag Selection"
    bl_options = _OPTS

    material: EnumProperty(name="ITU material", items=_MATERIAL_ITEMS, default="concrete")
    thickness: FloatProperty(name="Thickness", default=0.1, min=0.0001, unit="LENGTH")

    @classmethod
    def poll(cls, context):
        return bool(context.selected_objects)

    def run(self, context):
        n = materials.tag_objects(context.selected_objects, self.material, self.thickness)
        self.report({"INFO"}, f"Tagged {n} object(s) as {self.material}")


class ISAC_OT_add_link(_Reporting, bpy.types.Operator):
    """Add a link (edge of the network graph) from a transmitter to a receiver"""

    bl_idname = "isac.add_link"
    bl_label = "Add Link"
    bl_options = _OPTS

    tx: StringProperty(name="Tx device")
    rx: StringProperty(name="Rx device")

    def run(self, context):
        devices.add_link(context.scene, self.tx, self.rx)


class ISAC_OT_remove_link(_Reporting, bpy.types.Operator):
    """Remove the active link"""

    bl_idname = "isac.remove_link"
    bl_label = "Remove Link"
    bl_options = _OPTS

    index: IntProperty(name="Index", default=-1, description="Link to remove; -1 = active")

    def run(self, context):
        idx = self.index if self.index >= 0 else context.scene.isac.links_index
        devices.remove_link(context.scene, idx)


class ISAC_OT_export_scene(_Reporting, bpy.types.Operator):
    """Export the scene folder (scene.xml, meshes, twin.toml, DAE/STL/USD)"""

    bl_idname = "isac.export_scene"
    bl_label = "Export Scene Folder"
    bl_options = _OPTS

    directory: StringProperty(name="Folder", subtype="DIR_PATH",
                              description="Empty = the scene's export folder setting")

    def run(self, context):
        folder = self.directory or context.scene.isac.export_directory
        try:
            report = export_scene(context, folder)
        except ExportError as exc:
            for line in exc.problems:
                self.report({"ERROR"}, line)
            raise ValueError(str(exc)) from exc
        self.report({"INFO"}, f"Exported {len(report.objects)} objects, "
                              f"{len(report.devices)} devices to {report.folder}")
        for line in _store_placement(context):  # the engine will refuse these at load
            self.report({"WARNING"}, line)


class ISAC_OT_apply_calibration(_Reporting, bpy.types.Operator):
    """Move objects and set materials as fitted by `isac-twin calibrate --out DIR`"""

    bl_idname = "isac.apply_calibration"
    bl_label = "Apply Calibration"
    bl_options = _OPTS

    directory: StringProperty(name="Calibration folder", subtype="DIR_PATH",
                              description="The --out folder of isac-twin calibrate "
                                          "(calibration.json and scene/)")

    def invoke(self, context, event):
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def run(self, context):
        for line in calibration.apply_calibration(context.scene, self.directory):
            self.report({"INFO"}, line)


def _store_placement(context) -> list[str]:
    lines = placement.placement_warnings(context.scene, context.evaluated_depsgraph_get())
    context.scene.isac.placement_warnings = "\n".join(lines)
    return lines


class ISAC_OT_check_placement(_Reporting, bpy.types.Operator):
    """Check that every device and robot path lies in free space (not in a wall or furniture,
    above the floor): the engine refuses the scene at load otherwise"""

    bl_idname = "isac.check_placement"
    bl_label = "Check Placement"
    bl_options = _OPTS

    def run(self, context):
        lines = _store_placement(context)
        for line in lines:
            self.report({"WARNING"}, line)
        if not lines:
            self.report({"INFO"}, "Every device and robot path is in free space")


# --------------------------------------------------------------------------- live link


class ISAC_OT_live_connect(_Reporting, bpy.types.Operator):
    """Connect to a running engine (isac-twin serve) at the Live panel's host and port"""

    bl_idname = "isac.live_connect"
    bl_label = "Connect"

    def run(self, context):
        p = context.scene.isac_live
        live.open_session(context.scene, p.host, p.port, p.token or None)


class ISAC_OT_live_disconnect(_Reporting, bpy.types.Operator):
    """Disconnect from the engine (stops a local engine started from this panel)"""

    bl_idname = "isac.live_disconnect"
    bl_label = "Disconnect"

    def run(self, context):
        live.close_session()
        context.scene.isac_live.connection = "idle"


class ISAC_OT_live_start_engine(_Reporting, bpy.types.Operator):
    """Start a local engine (isac-twin serve) with the interpreter set in the preferences, then
    connect to it"""

    bl_idname = "isac.live_start_engine"
    bl_label = "Start Local Engine"

    def run(self, context):
        prefs = addon_preferences(context)
        python = bpy.path.abspath(prefs.engine_python) if prefs else ""
        scene_dir = bpy.path.abspath(prefs.engine_scene) if prefs and prefs.engine_scene else ""
        extra = tuple(prefs.engine_args.split()) if prefs else ()
        if context.scene.isac_live.token:
            extra += ("--token", context.scene.isac_live.token)
        try:
            proc = live.EngineProcess(python, scene_dir, extra)
        except OSError as exc:
            raise ValueError(f"cannot start the engine with {python or 'this interpreter'}: "
                             f"{exc}") from exc
        live.open_session(context.scene, "127.0.0.1", 0, context.scene.isac_live.token or None,
                          engine=proc)
        self.report({"INFO"}, f"Engine starting: {' '.join(proc.cmd)}")


class ISAC_OT_live_command(_Reporting, bpy.types.Operator):
    """Send a command to the engine: run, pause, single step or reset"""

    bl_idname = "isac.live_command"
    bl_label = "Engine Command"

    op: EnumProperty(name="Command", items=[("run", "Run", ""), ("pause", "Pause", ""),
                                            ("step", "Step", ""), ("reset", "Reset", "")])

    @classmethod
    def poll(cls, context):
        s = live.session()
        return s is not None and s.client.connected

    def run(self, context):
        live.session().send_command(self.op)


class ISAC_OT_live_radiomap_layer(_Reporting, bpy.types.Operator):
    """Show another layer of the radio map (an access point's RSS, best server or SINR)"""

    bl_idname = "isac.live_radiomap_layer"
    bl_label = "Radio Map Layer"

    layer: StringProperty(name="Layer")

    @classmethod
    def poll(cls, context):
        s = live.session()
        return s is not None and getattr(s.view, "radiomap", None) is not None

    def run(self, context):
        radiomap_view.select_layer(context.scene, live.session().view, self.layer)


class ISAC_OT_live_clear(_Reporting, bpy.types.Operator):
    """Remove the live view's robots, trails and rays from the scene"""

    bl_idname = "isac.live_clear"
    bl_label = "Clear Live View"

    def run(self, context):
        live_view.clear(context.scene)


CLASSES = (ISAC_OT_add_room, ISAC_OT_add_room_polygon, ISAC_OT_add_box, ISAC_OT_add_furniture,
           ISAC_OT_add_access_point, ISAC_OT_add_robot, ISAC_OT_robot_path_preset,
           ISAC_OT_tag_material,
           ISAC_OT_add_link, ISAC_OT_remove_link, ISAC_OT_export_scene,
           ISAC_OT_check_placement, ISAC_OT_apply_calibration)
#: Live-link operators: not undoable (they talk to a process, not to the scene's data).
LIVE_CLASSES = (ISAC_OT_live_connect, ISAC_OT_live_disconnect, ISAC_OT_live_start_engine,
                ISAC_OT_live_command, ISAC_OT_live_radiomap_layer, ISAC_OT_live_clear)


def register() -> None:
    for cls in CLASSES + LIVE_CLASSES:
        bpy.utils.register_class(cls)


def unregister() -> None:
    live.close_session()
    for cls in reversed(CLASSES + LIVE_CLASSES):
        bpy.utils.unregister_class(cls)
