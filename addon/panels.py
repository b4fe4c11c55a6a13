"""Sidebar panels (View3D > Sidebar > ISAC Twin). UI only: draw() reads, never computes."""

from __future__ import annotations

import bpy

from . import materials

CATEGORY = "ISAC Twin"


class _Base:
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = CATEGORY


class ISAC_UL_links(bpy.types.UIList):
    """One row per link: tx -> rx."""

    def draw_item(self, context, layout, data, item, icon, active_data, active_propname, index):
        row = layout.row(align=True)
        row.prop(item, "tx", text="", emboss=False)
        row.label(text="", icon="FORWARD")
        row.prop(item, "rx", text="", emboss=False)


class ISAC_PT_scene(_Base, bpy.types.Panel):
    """Carrier, numerology, band warnings and export."""

    bl_label = "Scene"
    bl_idname = "ISAC_PT_scene"

    def draw(self, context):
        layout = self.layout
        p = context.scene.isac
        col = layout.column(align=True)
        col.prop(p, "twin_name")
        col.prop(p, "frequency_hz")
        box = layout.box()
        box.label(text="OFDM")
        for key in ("num_subcarriers", "subcarrier_spacing_hz", "num_symbols",
                    "cyclic_prefix_samples"):
            box.prop(p, key)
        for text in materials.band_warnings(context.scene):
            layout.label(text=text, icon="ERROR")
        for text in filter(None, p.placement_warnings.split("\n")):
            layout.label(text=text, icon="ERROR")
        layout.operator("isac.check_placement", icon="CHECKMARK")
        layout.prop(p, "export_directory")
        layout.operator("isac.export_scene", icon="EXPORT")
        layout.operator("isac.apply_calibration", icon="IMPORT")


class ISAC_PT_modelling(_Base, bpy.types.Panel):
    """Room, furniture and device creation."""

    bl_label = "Modelling"
    bl_idname = "ISAC_PT_modelling"

    def draw(self, context):
        layout = self.layout
        col = layout.column(align=True)
        col.operator("isac.add_room", icon="MESH_CUBE")
        col.operator("isac.add_room_polygon", icon="MOD_BUILD")
        col.operator("isac.add_box", icon="CUBE")
        col.operator("isac.add_furniture", icon="OUTLINER_OB_MESH")
        col = layout.column(align=True)
        col.operator("isac.add_access_point", icon="OUTLINER_OB_LIGHTPROBE")
        col.operator("isac.add_robot", icon="OUTLINER_OB_ARMATURE")


class ISAC_PT_object(_Base, bpy.types.Panel):
    """Radio settings of the active object: material for geometry, array for devices."""

    bl_label = "Object"
    bl_idname = "ISAC_PT_object"

    def draw(self, context):
        layout = self.layout
        obj = context.active_object
        if obj is None:
            layout.label(text="No active object")
            return
        p = obj.isac
        layout.label(text=obj.name, icon="OBJECT_DATA")
        layout.prop(p, "device_kind")
        if p.device_kind == "NONE":
            layout.prop(p, "export_geometry")
            layout.prop_search(p, "custom_material", context.scene.isac, "radio_materials")
            if not p.custom_material:
                layout.prop(p, "itu_material")
                layout.prop(p, "thickness")
            layout.prop(p, "room_part")
            layout.operator("isac.tag_material", icon="MATERIAL")
            return
        layout.prop(p, "role")
        layout.prop(p, "power_dbm")
        if p.device_kind == "ROBOT":
            layout.prop(p, "robot_model")
            layout.prop(p, "antenna_offset")
            layout.prop(p, "path_kind")
            keys = {"circle": ("path_centre", "path_radius", "path_direction"),
                    "polyline": ("path_curve",), "figure_eight": ("path_centre", "path_size"),
                    "goal": ("path_goal",)}.get(p.path_kind, ())
            for key in keys + (("path_speed",) if keys else ()):
                layout.prop(p, key)
            layout.operator("isac.robot_path_preset", icon="CURVE_PATH")
        box = layout.box()
        box.label(text="Antenna array")
        row = box.row(align=True)
        row.prop(p, "array_rows")
        row.prop(p, "array_cols")
        row = box.row(align=True)
        row.prop(p, "vertical_spacing")
        row.prop(p, "horizontal_spacing")
        box.prop(p, "pattern")
        box.prop(p, "polarization")
        if p.role in ("tx", "txrx"):
            box = layout.box()
            box.label(text="Resource set (0, 0 = whole grid)")
            row = box.row(align=True)
            row.prop(p, "subcarrier_start")
            row.prop(p, "subcarrier_stop")
            row = box.row(align=True)
            row.prop(p, "symbol_start")
            row.prop(p, "symbol_stop")


class ISAC_PT_links(_Base, bpy.types.Panel):
    """The network graph's links."""

    bl_label = "Links"
    bl_idname = "ISAC_PT_links"

    def draw(self, context):
        layout = self.layout
        p = context.scene.isac
        layout.template_list("ISAC_UL_links", "", p, "links", p, "links_index", rows=3)
        row = layout.row(align=True)
        row.operator("isac.add_link", icon="ADD")
        row.operator("isac.remove_link", icon="REMOVE")


class ISAC_PT_live(_Base, bpy.types.Panel):
    """Live link: connect to the engine, control the loop, see link metrics."""

    bl_label = "Live"
    bl_idname = "ISAC_PT_live"

    def draw(self, context):
        layout = self.layout
        p = context.scene.isac_live
        row = layout.row(align=True)
        row.prop(p, "host")
        row.prop(p, "port")
        layout.prop(p, "token")
        row = layout.row(align=True)
        row.operator("isac.live_connect", icon="LINKED")
        row.operator("isac.live_disconnect", icon="UNLINKED")
        layout.operator("isac.live_start_engine", icon="PLAY")
        layout.label(text=f"{p.connection}: {p.engine_name or '-'} {p.scene_name}",
                     icon="CHECKMARK" if p.connection == "connected" else "ERROR")
        if p.last_error:
            layout.label(text=p.last_error, icon="ERROR")
        row = layout.row(align=True)
        for op, icon in (("run", "PLAY"), ("pause", "PAUSE"), ("step", "FRAME_NEXT"),
                         ("reset", "FILE_REFRESH")):
            row.operator("isac.live_command", text=op.title(), icon=icon).op = op
        layout.label(text=f"step {p.step}  t = {p.time_s:.2f} s  "
                          f"{'running' if p.running else 'paused'}  rays {p.num_rays}")
        box = layout.box()
        box.label(text="Links")
        for lk in p.links:
            box.label(text=f"{lk.tx} -> {lk.rx}: SNR {lk.snr_db:.1f} dB, "
                           f"{lk.rate_bps / 1e6:.1f} Mbit/s, {lk.num_paths} paths"
                           f"{' (LOS)' if lk.los else ''}")
            if lk.mcs_rate_bps == lk.mcs_rate_bps:  # not NaN: the engine sent it
                box.label(text=f"    MCS rate {lk.mcs_rate_bps / 1e6:.1f} Mbit/s")
        box = layout.box()
        box.prop(p, "show_radiomap")
        if p.radiomap_layers:
            row = box.row(align=True)
            for name in p.radiomap_layers.split(","):
                row.operator("isac.live_radiomap_layer", text=name,
                             depress=name == p.radiomap_layer).layer = name
        else:
            box.label(text="no radio map (engine: serve --radiomap 0.25)")
        col = layout.column(align=True)
        col.prop(p, "show_rays")
        col.prop(p, "ray_color_mode")
        col.prop(p, "max_paths_per_link")
        row = col.row(align=True)
        row.prop(p, "ray_width_by_power")
        row.prop(p, "ray_opacity_by_power")
        layout.operator("isac.live_clear", icon="TRASH")


CLASSES = (ISAC_UL_links, ISAC_PT_scene, ISAC_PT_modelling, ISAC_PT_object, ISAC_PT_links,
           ISAC_PT_live)


def register() -> None:
    for cls in CLASSES:
        bpy.utils.register_class(cls)


def unregister() -> None:
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
