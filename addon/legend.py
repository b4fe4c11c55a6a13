"""Colour bars and labels in the 3-D scene: what makes a colour readable in a render.

Plain ``bpy`` helpers shared by the radio map (``radiomap_view``) and the rays
(``live_view``): an emissive textured rectangle, a flat text label, and
:func:`colour_bar` (a gradient bar with its title and the values at its ends
and middle). Everything lies flat at a given height, so an overview camera
from above reads it; emission makes Cycles, EEVEE and Workbench agree.
"""

from __future__ import annotations

import bpy

from .modelling import get_collection

#: Bar length and height, m.
BAR_SIZE_M = (3.0, 0.25)
#: Pixels along a bar's gradient image.
BAR_PIXELS = 64
#: Text size of labels, m.
TEXT_SIZE_M = 0.22
#: Distance of an access point's label from it towards the room's middle, m.
AP_LABEL_OFFSET_M = 0.45
#: Curve resolution of the glyphs (Blender's default 12 triples the cost of re-evaluating
#: the metrics text every state; 4 reads the same at label sizes).
TEXT_RESOLUTION = 4
#: The live view's collection (defined here, the lowest module that needs it;
#: ``live_view`` and ``radiomap_view`` import it).
COLLECTION = "ISAC Live"


def scene_object(scene, name: str, data):
    """The object ``name`` (made with ``data`` and linked into :data:`COLLECTION`
    when it does not exist yet)."""
    obj = bpy.data.objects.get(name)
    if obj is None:
        obj = bpy.data.objects.new(name, data)
        get_collection(scene, COLLECTION).objects.link(obj)
    return obj


def _emissive(name: str, rgba):
    mat = bpy.data.materials.get(name)
    if mat is None:
        mat = bpy.data.materials.new(name)
        mat.diffuse_color = rgba
        if bpy.app.version < (5, 0, 0):
            mat.use_nodes = True
        nt = mat.node_tree
        nt.nodes.clear()
        out = nt.nodes.new("ShaderNodeOutputMaterial")
        em = nt.nodes.new("ShaderNodeEmission")
        em.inputs["Color"].default_value = rgba
        nt.links.new(em.outputs[0], out.inputs["Surface"])
    return mat


def _label_material():
    return _emissive("ISAC_Live_LabelText", (1.0, 1.0, 1.0, 1.0))


def fmt(v: float) -> str:
    """A scale value as a label (whole dB)."""
    return f"{v:.0f}"


def image(name: str, width: int, height: int):
    """The image ``name`` of ``width`` x ``height`` pixels (replaced when the size changed)."""
    img = bpy.data.images.get(name)
    if img is not None and tuple(img.size) != (width, height):
        bpy.data.images.remove(img)
        img = None
    if img is None:
        img = bpy.data.images.new(name, width=width, height=height, alpha=True)
    return img


def textured_material(name: str, image):
    """Emission from ``image`` (nearest filtering), transparent where alpha is 0."""
    mat = bpy.data.materials.get(name)
    if mat is None:
        mat = bpy.data.materials.new(name)
        if bpy.app.version < (5, 0, 0):
            mat.use_nodes = True
        nt = mat.node_tree
        nt.nodes.clear()
        out = nt.nodes.new("ShaderNodeOutputMaterial")
        tex = nt.nodes.new("ShaderNodeTexImage")
        tex.name = "map"
        tex.interpolation = "Closest"
        em = nt.nodes.new("ShaderNodeEmission")
        em.inputs["Strength"].default_value = 1.0
        tr = nt.nodes.new("ShaderNodeBsdfTransparent")
        mix = nt.nodes.new("ShaderNodeMixShader")
        nt.links.new(tex.outputs["Color"], em.inputs["Color"])
        nt.links.new(tex.outputs["Alpha"], mix.inputs["Fac"])
        nt.links.new(tr.outputs[0], mix.inputs[1])
        nt.links.new(em.outputs[0], mix.inputs[2])
        nt.links.new(mix.outputs[0], out.inputs["Surface"])
        if hasattr(mat, "surface_render_method"):
            mat.surface_render_method = "BLENDED"
    mat.node_tree.nodes["map"].image = image
    return mat


def quad(scene, name: str, x0: float, y0: float, x1: float, y1: float, z: float, mat):
    """A horizontal rectangle ``[x0, x1] x [y0, y1]`` at height ``z`` (m), UV 0..1, with
    material ``mat`` (object and mesh named ``name``)."""
    mesh = bpy.data.meshes.get(name)
    if mesh is None:
        mesh = bpy.data.meshes.new(name)
    verts = [(x0, y0, z), (x1, y0, z), (x1, y1, z), (x0, y1, z)]
    if len(mesh.vertices) == 4:
        mesh.vertices.foreach_set("co", [c for v in verts for c in v])
    else:
        mesh.clear_geometry()
        mesh.from_pydata(verts, [], [(0, 1, 2, 3)])
        uv = mesh.uv_layers.new(name="UVMap")
        uv.data.foreach_set("uv", [0, 0, 1, 0, 1, 1, 0, 1])
    mesh.update()
    if mesh.materials:
        mesh.materials[0] = mat
    else:
        mesh.materials.append(mat)
    return scene_object(scene, name, mesh)


def text(scene, name: str, body: str, location, size: float = TEXT_SIZE_M):
    """A flat white text object ``name`` reading ``body`` at ``location`` (m)."""
    curve = bpy.data.curves.get(name)
    if curve is None:
        curve = bpy.data.curves.new(name, type="FONT")
        curve.size = size
        curve.resolution_u = TEXT_RESOLUTION
    if curve.body != body:
        curve.body = body
    obj = scene_object(scene, name, curve)
    if obj.visible_shadow:  # a label is read, not lit: its shadow on a wall doubles it
        obj.visible_shadow = False
    obj.location = location
    if not curve.materials:
        curve.materials.append(_label_material())
    return obj



def colour_bar(scene, name: str, color, lo: float, hi: float, title: str, corner,
               *, length: float = BAR_SIZE_M[0], height: float = BAR_SIZE_M[1]) -> list:
    """A horizontal colour bar from ``lo`` (left) to ``hi`` (right) with labels.

    Args:
        name: object name of the bar; labels are ``name + "_Title"``, ``"_Min"``,
            ``"_Mid"``, ``"_Max"``.
        color: ``t in [0, 1] -> (r, g, b)``, the colour map the bar shows.
        lo, hi: the values at the ends (the labels).
        title: what the colours mean, with the unit (right of the bar).
        corner: ``(x, y, z)`` m of the bar's lower-left corner.
        length, height: m.

    Returns:
        the bar and its four labels.
    """
    x0, y0, z = (float(c) for c in corner)
    grad = image(name, BAR_PIXELS, 1)
    px: list[float] = []
    for k in range(BAR_PIXELS):
        px.extend((*color(k / (BAR_PIXELS - 1)), 1.0))
    grad.pixels.foreach_set(px)
    grad.update()
    bar = quad(scene, name, x0, y0, x0 + length, y0 + height, z, textured_material(name, grad))
    ty = y0 - TEXT_SIZE_M - 0.05
    return [bar,
            text(scene, name + "_Title", title, (x0 + length + 0.15, y0, z)),
            text(scene, name + "_Min", fmt(lo), (x0, ty, z)),
            text(scene, name + "_Mid", fmt((lo + hi) / 2), (x0 + length / 2 - 0.15, ty, z)),
            text(scene, name + "_Max", fmt(hi), (x0 + length - 0.3, ty, z))]


def device_label(name: str, array=None) -> str:
    """A device's label: its name and, when known, its array ``[rows, cols]`` (``AP1 4x8``)."""
    if array is None:
        return name
    return f"{name} {int(array[0])}x{int(array[1])}"


def label_position(position, toward=None, offset: float = 0.1) -> tuple[float, float, float]:
    """Where a device's flat label sits (m): ``offset`` m from ``position`` towards the
    point ``toward`` ``(x, y)`` (the room's middle: an AP on a wall would otherwise write
    its label inside the wall), 5 cm above it; without ``toward``, +x +y."""
    x, y, z = (float(c) for c in position)
    if toward is None:
        return (x + offset, y + offset, z + 0.05)
    import math

    dx, dy = float(toward[0]) - x, float(toward[1]) - y
    n = math.hypot(dx, dy) or 1.0
    return (x + offset * dx / n, y + offset * dy / n, z + 0.05)


def mark_access_point(scene, name: str, position, label: str | None = None, *,
                      toward=None) -> list:
    """A red cone under access point ``name`` pointing at it and its label
    (``ISAC_Live_AP_<name>``, ``..._Label``) reading ``label`` (default: what the label
    already reads, else the name: a radio map's transmitter list does not erase the array
    size the ``scene`` message gave), placed by :func:`label_position` towards ``toward``."""
    oname = f"ISAC_Live_AP_{name}"
    mesh = bpy.data.meshes.get(oname)
    if mesh is None:
        import math

        mesh = bpy.data.meshes.new(oname)
        n, r, h = 12, 0.08, 0.16
        verts = [(0.0, 0.0, 0.0)] + [(r * math.cos(2 * math.pi * k / n),
                                      r * math.sin(2 * math.pi * k / n), -h) for k in range(n)]
        faces = [(0, 1 + k, 1 + (k + 1) % n) for k in range(n)] + [tuple(range(n, 0, -1))]
        mesh.from_pydata(verts, [], faces)
        mesh.update()
        mesh.materials.append(_emissive("ISAC_Live_APMarker", (1.0, 0.15, 0.1, 1.0)))
    cone = scene_object(scene, oname, mesh)
    cone.location = (position[0], position[1], position[2] - 0.02)
    if label is None:
        old = bpy.data.curves.get(oname + "_Label")
        label = old.body if old is not None else name
    label = text(scene, oname + "_Label", label,
                 label_position(position, toward, AP_LABEL_OFFSET_M if toward else 0.1))
    # a label west of its AP ends at the anchor, so it runs away from the wall, not into it
    align = "RIGHT" if toward is not None and float(toward[0]) < float(position[0]) else "LEFT"
    if label.data.align_x != align:
        label.data.align_x = align
    return [cone, label]
