"""The paper's interchange formats: COLLADA 1.4.1 (DAE), binary STL and USD.

These are for other tools, not for the engine. DAE and STL are written here
byte-deterministically from the same world meshes as the PLY files; USD goes
through Blender's own exporter.
"""

from __future__ import annotations

import math
import struct
import xml.etree.ElementTree as ET
from pathlib import Path

from ..contract.writers.geometry import WorldMesh
from ..contract.writers.mitsuba_xml import material_id
from ..contract.writers.numbers import fmt_float

COLLADA_NS = "http://www.collada.org/2005/11/COLLADASchema"

# display colours per ITU material (r, g, b), only for viewers of the DAE
_COLOURS = {"concrete": (0.6, 0.6, 0.6), "wood": (0.55, 0.35, 0.2), "glass": (0.6, 0.8, 0.9),
            "metal": (0.75, 0.75, 0.8), "ceiling_board": (0.9, 0.9, 0.85)}


def _f(x: float) -> str:
    return fmt_float(x).removesuffix(".0")


def _sub(parent, tag, text=None, **attrib):
    el = ET.SubElement(parent, tag, {k.rstrip("_"): v for k, v in attrib.items()})
    if text is not None:
        el.text = text
    return el


def write_dae(path: Path, meshes: list[tuple[WorldMesh, str, float]], scene_name: str) -> None:
    """COLLADA 1.4.1: one geometry + node per object (world coordinates, identity transforms).

    Args:
        meshes: (mesh, ITU type, thickness m) per object.
        scene_name: name of the visual scene.
    """
    root = ET.Element("COLLADA", {"xmlns": COLLADA_NS, "version": "1.4.1"})
    asset = _sub(root, "asset")
    _sub(_sub(asset, "contributor"), "authoring_tool", "ISAC Twin Blender add-on")
    # fixed stamps keep the file byte-identical across exports
    _sub(asset, "created", "1970-01-01T00:00:00Z")
    _sub(asset, "modified", "1970-01-01T00:00:00Z")
    _sub(asset, "unit", name="meter", meter="1")
    _sub(asset, "up_axis", "Z_UP")

    mats = sorted({material_id(t, d): t for _, t, d in meshes}.items())
    effects = _sub(root, "library_effects")
    materials = _sub(root, "library_materials")
    for mid, itu_type in mats:
        fx = _sub(effects, "effect", id=f"{mid}-effect")
        tech = _sub(_sub(fx, "profile_COMMON"), "technique", sid="common")
        rgb = _COLOURS.get(itu_type, (0.7, 0.7, 0.7))
        _sub(_sub(_sub(tech, "lambert"), "diffuse"), "color",
             " ".join(_f(c) for c in (*rgb, 1.0)), sid="diffuse")
        mat = _sub(materials, "material", id=mid, name=mid)
        _sub(mat, "instance_effect", url=f"#{mid}-effect")

    geoms = _sub(root, "library_geometries")
    for mesh, itu_type, thickness in meshes:
        gid = f"mesh-{mesh.name}"
        geom = _sub(geoms, "geometry", id=gid, name=mesh.name)
        m = _sub(geom, "mesh")
        src = _sub(m, "source", id=f"{gid}-positions")
        _sub(src, "float_array", " ".join(_f(v) for v in mesh.vertices),
             id=f"{gid}-positions-array", count=str(len(mesh.vertices)))
        acc = _sub(_sub(src, "technique_common"), "accessor", source=f"#{gid}-positions-array",
                   count=str(mesh.num_vertices), stride="3")
        for axis in "XYZ":
            _sub(acc, "param", name=axis, type="float")
        verts = _sub(m, "vertices", id=f"{gid}-vertices")
        _sub(verts, "input", semantic="POSITION", source=f"#{gid}-positions")
        tris = _sub(m, "triangles", material="radio", count=str(mesh.num_triangles))
        _sub(tris, "input", semantic="VERTEX", source=f"#{gid}-vertices", offset="0")
        _sub(tris, "p", " ".join(str(i) for i in mesh.triangles))

    scenes = _sub(root, "library_visual_scenes")
    vs = _sub(scenes, "visual_scene", id="Scene", name=scene_name)
    for mesh, itu_type, thickness in meshes:
        node = _sub(vs, "node", id=f"node-{mesh.name}", name=mesh.name, type="NODE")
        inst = _sub(node, "instance_geometry", url=f"#mesh-{mesh.name}")
        tc = _sub(_sub(inst, "bind_material"), "technique_common")
        _sub(tc, "instance_material", symbol="radio", target=f"#{material_id(itu_type, thickness)}")
    _sub(_sub(root, "scene"), "instance_visual_scene", url="#Scene")

    ET.indent(root, space=" ")
    Path(path).write_bytes(ET.tostring(root, encoding="utf-8", xml_declaration=True) + b"\n")


def write_stl(path: Path, meshes: list[WorldMesh], scene_name: str) -> None:
    """One binary STL with every object's triangles (world coordinates, m)."""
    header = f"ISAC Twin {scene_name} binary STL, metres".encode("ascii", "replace")[:80]
    chunks = [header.ljust(80, b" "), b""]
    count = 0
    for mesh in meshes:
        v, t = mesh.vertices, mesh.triangles
        for k in range(mesh.num_triangles):
            a, b, c = (v[3 * t[3 * k + i]:3 * t[3 * k + i] + 3] for i in range(3))
            u = [b[i] - a[i] for i in range(3)]
            w = [c[i] - a[i] for i in range(3)]
            n = [u[1] * w[2] - u[2] * w[1], u[2] * w[0] - u[0] * w[2], u[0] * w[1] - u[1] * w[0]]
            norm = math.sqrt(sum(x * x for x in n)) or 1.0
            chunks.append(struct.pack("<12fH", *(x / norm for x in n), *a, *b, *c, 0))
            count += 1
    chunks[1] = struct.pack("<I", count)
    Path(path).write_bytes(b"".join(chunks))


def write_usd(path: Path, objects, context=None) -> None:
    """USD (binary crate, .usdc) of ``objects`` through ``bpy.ops.wm.usd_export``.

    Selection is set to ``objects`` for the export and restored afterwards.
    """
    import bpy

    ctx = context or bpy.context
    view_layer = ctx.view_layer
    before_sel = [o for o in view_layer.objects if o.select_get()]
    before_active = view_layer.objects.active
    try:
        for o in before_sel:
            o.select_set(False)
        for o in objects:
            o.select_set(True)
        bpy.ops.wm.usd_export(
            filepath=str(path), check_existing=False, selected_objects_only=True,
            export_animation=False, export_materials=False, export_textures_mode="KEEP",
            export_uvmaps=False, export_normals=True, relative_paths=True,
            export_lights=False, export_cameras=False, evaluation_mode="RENDER",
            convert_world_material=False, export_custom_properties=False,
        )
    finally:
        for o in view_layer.objects:
            o.select_set(o in before_sel)
        view_layer.objects.active = before_active
