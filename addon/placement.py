"""Placement warnings before export: devices and robot paths in free space.

The engine refuses, at load, a device or robot path point inside a wall or a
piece of furniture or outside the room's footprint (``engine/scene/room.py``,
docs/config.md). This module finds the same faults in Blender first, so the
panel can warn before export: a point is inside an object when a vertical ray
up from it first meets that object's surface from behind (the inside of its
top), and outside the footprint when a ray down meets nothing. Points
checked: an access point's array centre, a robot's body (0.1 m above its
base) and its path every ``PATH_SPACING_M`` (the engine's spacing).
"""

from __future__ import annotations

import math

from mathutils import Vector

from .devices import curve_waypoints, device_objects

ROBOT_BODY_HEIGHT_M = 0.1  #: as engine/scene/room.py
PATH_SPACING_M = 0.05      #: as engine/scene/room.py
_UP, _DOWN = Vector((0.0, 0.0, 1.0)), Vector((0.0, 0.0, -1.0))


def _polyline(pts, closed: bool, spacing: float):
    pts = list(pts) + ([pts[0]] if closed and pts else [])
    out = []
    for a, b in zip(pts, pts[1:]):
        n = max(1, int(math.ceil(math.hypot(b[0] - a[0], b[1] - a[1]) / spacing)))
        out += [(a[0] + (b[0] - a[0]) * k / n, a[1] + (b[1] - a[1]) * k / n) for k in range(n)]
    return out + pts[-1:]


def path_points(obj, spacing: float = PATH_SPACING_M) -> list[tuple[float, float]]:
    """World ``(x, y)`` points (m) every ``spacing`` m along a robot's path (empty: none).
    The shapes are the engine's (``engine/robots/control.py``)."""
    p = obj.isac
    kind = p.path_kind
    if kind == "circle" and p.path_radius > 0:
        n = max(8, int(math.ceil(2 * math.pi * p.path_radius / spacing)))
        c = p.path_centre
        return [(c[0] + p.path_radius * math.cos(2 * math.pi * k / n),
                 c[1] + p.path_radius * math.sin(2 * math.pi * k / n)) for k in range(n)]
    if kind == "figure_eight" and p.path_size > 0:
        a, c = p.path_size / 2, p.path_centre
        n = max(16, int(math.ceil(3.1 * p.path_size / spacing)))
        return [(c[0] + a * math.sin(t), c[1] + a * math.sin(t) * math.cos(t))
                for t in (2 * math.pi * k / n for k in range(n))]
    if kind == "goal":
        loc = obj.matrix_world.translation
        return _polyline([(loc.x, loc.y), tuple(p.path_goal)], False, spacing)
    if kind == "polyline" and p.path_curve is not None:
        pts, closed = curve_waypoints(p.path_curve)
        return _polyline([tuple(q) for q in pts], closed, spacing) if len(pts) >= 2 else []
    return []


def _first_hit(scene, depsgraph, origin: Vector, direction: Vector):
    """First exported geometry object a ray meets: ``(object, normal)`` or ``(None, None)``
    (helpers such as boolean cutters and devices are passed through)."""
    o = origin.copy()
    for _ in range(32):
        hit, loc, normal, _, obj, _ = scene.ray_cast(depsgraph, o, direction)
        if not hit:
            return None, None
        if obj.type == "MESH" and obj.isac.device_kind == "NONE" and obj.isac.export_geometry:
            return obj, normal
        o = loc + direction * 1e-4
    return None, None


def locate(scene, depsgraph, point) -> str | None:
    """What a world point lies in (``"object 'Table'"``, ``"no floor ..."``) or None."""
    p = Vector(point)
    obj, normal = _first_hit(scene, depsgraph, p, _UP)
    if obj is not None and normal.dot(_UP) > 0:
        return f"object '{obj.name}'"
    obj, normal = _first_hit(scene, depsgraph, p, _DOWN)
    if obj is None:
        return "no floor (outside the room's footprint)"
    if normal.dot(_DOWN) > 0:
        return f"object '{obj.name}'"
    return None


def placement_warnings(scene, depsgraph) -> list[str]:
    """One line per device whose position, or first path point, is not in free space."""
    out = []
    for obj in device_objects(scene):
        loc = obj.matrix_world.translation.copy()
        robot = obj.isac.device_kind == "ROBOT"
        body = loc + Vector((0.0, 0.0, ROBOT_BODY_HEIGHT_M)) if robot else loc
        hit = locate(scene, depsgraph, body)
        if hit is not None:
            out.append(f"Device '{obj.name}' at ({loc.x:.2f}, {loc.y:.2f}, {loc.z:.2f}) "
                       f"lies in {hit}")
            continue
        if not robot:
            continue
        for x, y in path_points(obj):
            hit = locate(scene, depsgraph, (x, y, body.z))
            if hit is not None:
                out.append(f"Device '{obj.name}': its {obj.isac.path_kind} path point "
                           f"({x:.2f}, {y:.2f}) lies in {hit}")
                break
    return out
