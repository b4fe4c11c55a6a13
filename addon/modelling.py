"""Room modelling as plain functions: rooms from a ground plan or a polygon, furniture, windows.

Everything here is callable from operators, ``bpy`` scripts and tests alike.
Lengths are metres, angles radians; the world frame is Z up. Meshes are
built with their dimensions baked in (object scale stays 1) so the exported
geometry equals what the user sees.
"""

from __future__ import annotations

import math
from typing import Sequence

import bpy

from . import materials

#: Furniture presets: size (x, y, z) in m, ITU material, slab thickness in m.
FURNITURE_PRESETS: dict[str, dict] = {
    "table": {"dimensions": (1.6, 0.8, 0.75), "material": "wood", "thickness": 0.03},
    "chair": {"dimensions": (0.5, 0.5, 0.9), "material": "wood", "thickness": 0.02},
    "cabinet": {"dimensions": (1.0, 0.5, 2.0), "material": "chipboard", "thickness": 0.02},
    "rack": {"dimensions": (0.6, 0.8, 1.8), "material": "metal", "thickness": 0.002},
    "switch_box": {"dimensions": (0.4, 0.3, 0.6), "material": "metal", "thickness": 0.002},
}

ROOM_COLLECTION = "Room"
FURNITURE_COLLECTION = "Furniture"


def _scene(scene):
    return scene if scene is not None else bpy.context.scene


def get_collection(scene, name: str):
    """The collection ``name`` under ``scene``'s master collection, created if missing."""
    scene = _scene(scene)
    coll = bpy.data.collections.get(name)
    if coll is None:
        coll = bpy.data.collections.new(name)
    if coll.name not in scene.collection.children:
        scene.collection.children.link(coll)
    return coll


def _check_positive(**values: float) -> None:
    for key, val in values.items():
        if not (isinstance(val, (int, float)) and val > 0 and math.isfinite(val)):
            raise ValueError(f"{key} must be a positive length in m, got {val!r}")


def signed_area(polygon: Sequence[Sequence[float]]) -> float:
    """Signed area of an XY polygon, m^2 (positive when counter-clockwise)."""
    n = len(polygon)
    return 0.5 * sum(polygon[i][0] * polygon[(i + 1) % n][1]
                     - polygon[(i + 1) % n][0] * polygon[i][1] for i in range(n))


def _ccw(polygon: Sequence[Sequence[float]]) -> list[tuple[float, float]]:
    pts = [(float(p[0]), float(p[1])) for p in polygon]
    return pts if signed_area(pts) > 0 else pts[::-1]


def prism_mesh(name: str, polygon: Sequence[Sequence[float]], z0: float, z1: float,
               origin: Sequence[float] | None = None):
    """A closed mesh: the XY ``polygon`` extruded from ``z0`` to ``z1`` (m), normals outward.

    Vertices are relative to ``origin`` (default: the bounding-box centre),
    so the object placed at that origin reproduces the given coordinates.

    Returns:
        ``(mesh, origin)`` with origin an (x, y, z) tuple in m.
    """
    pts = _ccw(polygon)
    n = len(pts)
    xs, ys = [p[0] for p in pts], [p[1] for p in pts]
    if origin is None:
        origin = ((min(xs) + max(xs)) / 2, (min(ys) + max(ys)) / 2, (z0 + z1) / 2)
    origin = tuple(float(c) for c in origin)
    verts = [(x - origin[0], y - origin[1], z0 - origin[2]) for x, y in pts]
    verts += [(x - origin[0], y - origin[1], z1 - origin[2]) for x, y in pts]
    faces = [tuple(range(n - 1, -1, -1)), tuple(range(n, 2 * n))]
    faces += [(i, (i + 1) % n, n + (i + 1) % n, n + i) for i in range(n)]
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata(verts, [], faces)
    mesh.validate()
    mesh.update()
    return mesh, origin


def _new_object(name: str, mesh, location, collection, material: str, thickness: float):
    obj = bpy.data.objects.new(name, mesh)
    obj.location = location
    collection.objects.link(obj)
    obj.isac.device_kind = "NONE"
    if material != materials.NO_MATERIAL:
        materials.tag_objects([obj], material, thickness)
    return obj


def create_room_from_polygon(
    vertices: Sequence[Sequence[float]],
    height: float,
    wall_thickness: float = 0.2,
    *,
    name: str = "Room",
    floor_thickness: float | None = None,
    ceiling_thickness: float | None = None,
    wall_material: str = "concrete",
    floor_material: str = "concrete",
    ceiling_material: str = "ceiling_board",
    scene=None,
) -> dict:
    """Build floor, ceiling and one wall per footprint edge as separate closed meshes.

    The footprint is the room's *inside*: walls stand outside it (mitred at
    the corners so they neither overlap nor leave gaps), the floor slab lies
    below z = 0 and the ceiling slab above z = ``height``.

    Args:
        vertices: footprint corners [(x, y), ...] in m, either winding, >= 3, no repeats.
        height: inside height, m.
        wall_thickness: m; also the walls' radio-material thickness.
        name: prefix of the object names (``<name>_Floor``, ``<name>_Wall_1`` ...).
        floor_thickness: m, defaults to ``wall_thickness``.
        ceiling_thickness: m, defaults to ``wall_thickness``.
        wall_material, floor_material, ceiling_material: ITU material names.
        scene: target ``bpy.types.Scene`` (default: the context scene).

    Returns:
        ``{"floor": Object, "ceiling": Object, "walls": [Object, ...]}``.

    Raises:
        ValueError: fewer than 3 vertices, a degenerate footprint or a non-positive length.
    """
    floor_thickness = wall_thickness if floor_thickness is None else floor_thickness
    ceiling_thickness = wall_thickness if ceiling_thickness is None else ceiling_thickness
    _check_positive(height=height, wall_thickness=wall_thickness,
                    floor_thickness=floor_thickness, ceiling_thickness=ceiling_thickness)
    if len(vertices) < 3:
        raise ValueError(f"Room '{name}': a footprint needs at least 3 vertices, got {len(vertices)}")
    pts = _ccw(vertices)
    n = len(pts)
    for i in range(n):
        a, b = pts[i], pts[(i + 1) % n]
        if math.hypot(b[0] - a[0], b[1] - a[1]) < 1e-6:
            raise ValueError(f"Room '{name}': footprint vertices {i} and {(i + 1) % n} coincide")
    if abs(signed_area(pts)) < 1e-9:
        raise ValueError(f"Room '{name}': footprint has zero area")
    scene = _scene(scene)
    coll = get_collection(scene, ROOM_COLLECTION)

    normals = []
    for i in range(n):
        (x0, y0), (x1, y1) = pts[i], pts[(i + 1) % n]
        length = math.hypot(x1 - x0, y1 - y0)
        normals.append(((y1 - y0) / length, -(x1 - x0) / length))  # outward for CCW
    outer = []
    for i in range(n):
        (ax, ay), (bx, by) = normals[i - 1], normals[i]
        denom = 1.0 + ax * bx + ay * by
        if denom < 1e-6:
            raise ValueError(f"Room '{name}': footprint folds back on itself at vertex {i}")
        outer.append((pts[i][0] + wall_thickness * (ax + bx) / denom,
                      pts[i][1] + wall_thickness * (ay + by) / denom))

    mesh, origin = prism_mesh(f"{name}_Floor", pts, -floor_thickness, 0.0)
    floor = _new_object(f"{name}_Floor", mesh, origin, coll, floor_material, floor_thickness)
    mesh, origin = prism_mesh(f"{name}_Ceiling", pts, height, height + ceiling_thickness)
    ceiling = _new_object(f"{name}_Ceiling", mesh, origin, coll, ceiling_material,
                          ceiling_thickness)
    walls = []
    for i in range(n):
        j = (i + 1) % n
        quad = [pts[i], outer[i], outer[j], pts[j]]
        wname = f"{name}_Wall_{i + 1}"
        mesh, origin = prism_mesh(wname, quad, 0.0, height)
        walls.append(_new_object(wname, mesh, origin, coll, wall_material, wall_thickness))
    for obj in [floor, ceiling, *walls]:
        obj.isac.room_part = "SHELL"  # fixed structure, whatever the user renames it to
    return {"floor": floor, "ceiling": ceiling, "walls": walls}


def create_room(
    width: float,
    depth: float,
    height: float,
    wall_thickness: float = 0.2,
    *,
    origin: Sequence[float] = (0.0, 0.0),
    name: str = "Room",
    **kwargs,
) -> dict:
    """Rectangular room from a ground plan: inside spans origin + [0, width] x [0, depth] x [0, height].

    Walls are numbered south (y = min), east, north, west. Other keyword
    arguments are those of :func:`create_room_from_polygon`.

    Args:
        width: inside extent along x, m.
        depth: inside extent along y, m.
        height: inside height, m.
        wall_thickness: m.
        origin: (x, y) of the inside floor corner, m.
    """
    _check_positive(width=width, depth=depth, height=height, wall_thickness=wall_thickness)
    x0, y0 = float(origin[0]), float(origin[1])
    plan = [(x0, y0), (x0 + width, y0), (x0 + width, y0 + depth), (x0, y0 + depth)]
    return create_room_from_polygon(plan, height, wall_thickness, name=name, **kwargs)


def box_mesh(name: str, dimensions: Sequence[float]):
    """A closed box mesh of size (x, y, z) m whose origin is the centre of its bottom face."""
    dx, dy, dz = (float(d) for d in dimensions)
    rect = [(-dx / 2, -dy / 2), (dx / 2, -dy / 2), (dx / 2, dy / 2), (-dx / 2, dy / 2)]
    mesh, _ = prism_mesh(name, rect, 0.0, dz, origin=(0.0, 0.0, 0.0))
    return mesh


def add_box(
    name: str,
    dimensions: Sequence[float],
    location: Sequence[float] = (0.0, 0.0, 0.0),
    rotation_z: float = 0.0,
    *,
    material: str = materials.NO_MATERIAL,
    thickness: float = materials.DEFAULT_THICKNESS_M,
    collection_name: str = FURNITURE_COLLECTION,
    scene=None,
):
    """A box object standing on ``location`` (bottom-face centre, m), turned ``rotation_z`` rad about Z.

    Raises:
        ValueError: a non-positive dimension (message names the object).
    """
    if len(dimensions) != 3:
        raise ValueError(f"Object '{name}': dimensions must be (x, y, z), got {dimensions!r}")
    for axis, d in zip("xyz", dimensions):
        if not (d > 0 and math.isfinite(d)):
            raise ValueError(f"Object '{name}': dimension {axis} must be > 0 m, got {d!r}")
    scene = _scene(scene)
    obj = _new_object(name, box_mesh(name, dimensions), tuple(location),
                      get_collection(scene, collection_name), material, thickness)
    obj.rotation_euler = (0.0, 0.0, float(rotation_z))
    return obj


def add_furniture(
    kind: str,
    location: Sequence[float] = (0.0, 0.0, 0.0),
    rotation_z: float = 0.0,
    *,
    name: str | None = None,
    dimensions: Sequence[float] | None = None,
    material: str | None = None,
    thickness: float | None = None,
    scene=None,
):
    """A furniture box from :data:`FURNITURE_PRESETS` (table, chair, cabinet, rack, switch_box).

    Args:
        kind: preset key.
        location: bottom-face centre (x, y, z), m.
        rotation_z: yaw about Z, rad.
        name: object name (default: the capitalised kind; Blender adds .001 on clashes).
        dimensions, material, thickness: override the preset (m, ITU name, m).

    Returns:
        The new ``bpy.types.Object``.
    """
    if kind not in FURNITURE_PRESETS:
        raise ValueError(f"Unknown furniture preset '{kind}'; choose one of "
                         f"{', '.join(FURNITURE_PRESETS)}")
    preset = FURNITURE_PRESETS[kind]
    obj = add_box(
        name or kind.title().replace("_", ""),
        preset["dimensions"] if dimensions is None else dimensions,
        location, rotation_z,
        material=preset["material"] if material is None else material,
        thickness=preset["thickness"] if thickness is None else thickness,
        scene=scene,
    )
    obj.isac.room_part = "FURNITURE"
    return obj


def add_window(
    wall,
    center: Sequence[float],
    width: float,
    height: float,
    rotation_z: float = 0.0,
    *,
    name: str | None = None,
    pane_thickness: float = 0.01,
    material: str = "glass",
    scene=None,
):
    """Cut a window into ``wall`` (boolean modifier) and fill it with a glass pane.

    The cutter is a helper object that is never exported; the evaluated
    wall (with the hole) is what the exporter writes.

    Args:
        wall: the wall object.
        center: window centre in world coordinates, m, on the wall's mid-plane.
        width: along the wall (local x after ``rotation_z``), m.
        height: m.
        rotation_z: rad; 0 for a wall parallel to the x axis.
        pane_thickness: glass thickness, m (geometry and radio thickness).

    Returns:
        The glass pane object.
    """
    _check_positive(width=width, height=height, pane_thickness=pane_thickness)
    name = name or f"{wall.name}_Window"
    depth = 4.0 * max(wall.isac.thickness, pane_thickness) + 0.1
    base = (center[0], center[1], center[2] - height / 2)
    scene = _scene(scene)
    cutter = add_box(f"{name}_Cutter", (width, depth, height), base, rotation_z,
                     collection_name=ROOM_COLLECTION, scene=scene)
    cutter.isac.export_geometry = False
    cutter.display_type = "WIRE"
    cutter.hide_render = True
    mod = wall.modifiers.new(name="Window", type="BOOLEAN")
    mod.operation = "DIFFERENCE"
    mod.object = cutter
    mod.solver = "EXACT"
    pane = add_box(name, (width, pane_thickness, height), base, rotation_z,
                   material=material, thickness=pane_thickness,
                   collection_name=ROOM_COLLECTION, scene=scene)
    pane.isac.room_part = "SHELL"  # part of the wall
    return pane
