"""The room as a floor plan: shell vs furniture, and placement checked against free space.

* **Shell or furniture.** The room's shell (walls, floor, ceiling, and what
  sits in a wall: windows, doors) is fixed structure; furniture is what a
  perturbed "real" room moves and what a floor plan draws as obstacles.
  ``twin.toml``'s ``[room] shell / furniture`` lists (written by the add-on
  from each object's *Room part* tag) decide first; any object named in
  neither is classified from its geometry (:func:`shell_objects`), never
  from its name.
* **Free space.** A device or a robot's path point is *placed* only if it
  lies inside no closed object mesh (a wall, a cabinet) and, when the room has
  a floor, above that floor (not in the cut-out corner of an L-shaped room).
  :func:`check_placement` refuses the first misplaced one with one line
  naming the device, the point and the object it lies in. The test is plain
  numpy on the scene's PLY meshes, so it runs before Mitsuba loads; the
  tests check it against the tracer's own free-space test
  (:func:`isac_twin.raytrace.grid.free_points`).

All lengths are metres in the world frame (Z up).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError, PathError
from .meshes import read_ply

#: Geometry rules for untagged objects (fractions of the room's extent).
SLAB_MAX_HEIGHT = 0.1     #: a floor/ceiling slab is at most this share of the room height thick
SLAB_MIN_AREA = 0.25      #: ... and covers at least this share of the room's plan bounding box
WALL_MIN_HEIGHT = 0.8     #: a wall spans at least this share of the inside height
IN_WALL_TOLERANCE_M = 0.02  #: an object whose box lies in a wall's box (+- this) is part of it

#: Height above a robot's base at which its body (and its path) must be free, m.
ROBOT_BODY_HEIGHT_M = 0.1
#: Spacing of the points checked along a robot's path, m.
PATH_CHECK_SPACING_M = 0.05

#: Ray direction jitter that keeps a vertical ray off shared triangle edges (m).
_JITTER = np.array([1.2345e-7, 2.7183e-7])


@dataclass(frozen=True)
class RoomParts:
    """Each object's part of the room.

    Attributes:
        floor, ceiling, walls: shell objects by role (names); ``walls`` also
            holds windows, doors and anything else in a wall.
        furniture: every other object.
        tagged: objects whose part came from ``[room]`` in twin.toml.
    """

    floor: tuple[str, ...]
    ceiling: tuple[str, ...]
    walls: tuple[str, ...]
    furniture: tuple[str, ...]
    tagged: tuple[str, ...] = ()

    @property
    def shell(self) -> frozenset[str]:
        """Names of the fixed structure (floor, ceiling, walls)."""
        return frozenset(self.floor + self.ceiling + self.walls)


def object_meshes(scene) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """``name -> (vertices [V, 3], faces [F, 3])`` of every object where it is now: its
    PLY, moved and turned as ``scene.object_poses`` says (an edited twin)."""
    out = {}
    for name, o in scene.objects.items():
        m = read_ply(o.mesh_file)
        v = m.vertices
        pose = getattr(scene, "object_poses", {}).get(name)
        if pose is not None:  # Sionna's sense: bbox centre as loaded -> position, turned
            c0 = (np.asarray(o.bounds_min) + np.asarray(o.bounds_max)) / 2
            r, p, y = pose[3:]
            cr, sr, cp, sp, cy, sy = (math.cos(r), math.sin(r), math.cos(p), math.sin(p),
                                      math.cos(y), math.sin(y))
            rot = np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                            [-sp, cp * sr, cp * cr]])
            v = (v - c0) @ rot.T + np.asarray(pose[:3])
        out[name] = (v, m.faces)
    return out


def room_parts(scene) -> RoomParts:
    """Classify every object of ``scene`` (a :class:`~isac_twin.scene.twin_scene.TwinScene`).

    Tags from ``[room]`` win. An untagged object is

    * a floor or ceiling if it is a horizontal slab (thinner than
      ``SLAB_MAX_HEIGHT`` of the room's height) covering at least
      ``SLAB_MIN_AREA`` of the plan's bounding box, below or above the room's
      middle height;
    * a wall if it spans at least ``WALL_MIN_HEIGHT`` of the inside height
      (floor top to ceiling underside);
    * part of a wall (window, door) if its box lies inside a wall's box;
    * furniture otherwise.
    """
    cfg_room = getattr(scene.config, "room", None)
    tag_shell = set(cfg_room.shell) if cfg_room else set()
    tag_furn = set(cfg_room.furniture) if cfg_room else set()
    lo, hi = np.asarray(scene.bounds_min, float), np.asarray(scene.bounds_max, float)
    height = max(hi[2] - lo[2], 1e-9)
    plan_area = max((hi[0] - lo[0]) * (hi[1] - lo[1]), 1e-9)
    mid = 0.5 * (lo[2] + hi[2])
    box = {n: (np.asarray(o.bounds_min, float), np.asarray(o.bounds_max, float))
           for n, o in scene.objects.items()}

    def slab(n):
        b0, b1 = box[n]
        e = b1 - b0
        return e[2] <= SLAB_MAX_HEIGHT * height and e[0] * e[1] >= SLAB_MIN_AREA * plan_area

    floor = [n for n in scene.objects if n not in tag_furn and slab(n) and box[n][1][2] <= mid]
    ceiling = [n for n in scene.objects if n not in tag_furn and slab(n) and box[n][0][2] > mid]
    in_lo = max((box[n][1][2] for n in floor), default=lo[2])
    in_hi = min((box[n][0][2] for n in ceiling), default=hi[2])
    inside_h = max(in_hi - in_lo, 1e-9)
    walls = [n for n in scene.objects if n not in tag_furn and n not in floor
             and n not in ceiling
             and (n in tag_shell or box[n][1][2] - box[n][0][2] >= WALL_MIN_HEIGHT * inside_h)]
    tol = IN_WALL_TOLERANCE_M
    for n in scene.objects:
        if n in tag_furn or n in walls or n in floor or n in ceiling:
            continue
        b0, b1 = box[n]
        if any(np.all(b0 >= box[w][0] - tol) and np.all(b1 <= box[w][1] + tol)
               for w in list(walls)):
            walls.append(n)
    shell = set(floor) | set(ceiling) | set(walls)
    furniture = [n for n in scene.objects if n not in shell]
    tagged = tuple(n for n in scene.objects if n in tag_shell or n in tag_furn)
    return RoomParts(tuple(floor), tuple(ceiling), tuple(w for w in scene.objects if w in walls),
                     tuple(furniture), tagged)


def shell_objects(scene) -> frozenset[str]:
    """Names of the room's fixed structure (see :func:`room_parts`)."""
    return room_parts(scene).shell


# --------------------------------------------------------------------------- free space


def _closed(faces: np.ndarray) -> bool:
    """Whether a triangle mesh is watertight (every edge shared by exactly two faces)."""
    if len(faces) < 4:
        return False
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    return bool(np.all(counts == 2))


def _xy_hits(tri: np.ndarray, pts: np.ndarray):
    """Vertical lines through ``pts`` ``[N, 3]`` against triangles ``[T, 3, 3]``:
    ``(inside [N, T] bool, z [N, T])`` where the line meets each triangle."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    p = pts[:, None, :2] + _JITTER
    v0, v1 = (b - a)[None, :, :2], (c - a)[None, :, :2]
    w = p - a[None, :, :2]
    den = v0[..., 0] * v1[..., 1] - v0[..., 1] * v1[..., 0]
    ok = np.abs(den) > 1e-15
    den = np.where(ok, den, 1.0)
    u = (w[..., 0] * v1[..., 1] - w[..., 1] * v1[..., 0]) / den
    v = (v0[..., 0] * w[..., 1] - v0[..., 1] * w[..., 0]) / den
    inside = ok & (u >= 0) & (v >= 0) & (u + v <= 1)
    z = a[None, :, 2] + u * (b - a)[None, :, 2] + v * (c - a)[None, :, 2]
    return inside, z


def locate(scene, points, meshes=None, parts: RoomParts | None = None) -> list[str | None]:
    """What each point ``[N, 3]`` (m) lies in: ``None`` for free space, else a short
    description (``"object 'Table_1'"``, ``"no floor (outside the room's footprint)"``).

    A point is inside a closed object mesh when a vertical ray from it crosses
    the mesh an odd number of times (open meshes, e.g. a single reflecting
    quad, enclose nothing). When the room has floor objects, a point must lie
    above one of them.
    """
    pts = np.atleast_2d(np.asarray(points, float))
    meshes = object_meshes(scene) if meshes is None else meshes
    parts = room_parts(scene) if parts is None else parts
    out: list[str | None] = [None] * len(pts)
    for name, (v, f) in meshes.items():
        lo, hi = v.min(axis=0), v.max(axis=0)
        cand = np.flatnonzero(np.all((pts >= lo) & (pts <= hi), axis=1))
        cand = [i for i in cand if out[i] is None]
        if not cand or not _closed(f):
            continue
        inside, z = _xy_hits(v[f], pts[cand])
        above = inside & (z > pts[cand, 2:3])
        for i, n in zip(cand, above.sum(axis=1)):
            if n % 2:
                out[i] = f"object '{name}'"
    if parts.floor:
        tri = np.concatenate([meshes[n][0][meshes[n][1]] for n in parts.floor])
        todo = np.flatnonzero([o is None for o in out])
        if len(todo):
            inside, _ = _xy_hits(tri, pts[todo])
            for i in todo[~inside.any(axis=1)]:
                out[i] = "no floor (outside the room's footprint)"
    return out


def _fmt(p) -> str:
    return "(" + ", ".join(f"{x:.2f}" for x in p) + ")"


def robot_path_points(device, spacing: float = PATH_CHECK_SPACING_M):
    """Points ``[M, 3]`` every ``spacing`` m along a robot's ``[devices.path]`` at its
    body height, with their arc lengths ``[M]`` (m); ``None`` without a path."""
    from ..robots.control import path_from_spec

    if device.path is None:
        return None
    path = path_from_spec(device.path, start=device.position[:2])
    n = max(2, int(math.ceil(path.length / spacing)) + 1)
    s = np.linspace(0.0, path.length, n, endpoint=not path.closed)
    xy = path.point(s)
    z = np.full((len(s), 1), device.position[2] + ROBOT_BODY_HEIGHT_M)
    return np.hstack([xy, z]), s, path


def path_obstruction(scene, spec: dict, start, z: float, *, meshes=None,
                     parts: RoomParts | None = None) -> str | None:
    """Where a robot path spec leaves free space, or None: checked every
    ``PATH_CHECK_SPACING_M`` at height ``z`` (m); ``start`` ``[2]`` m is the robot's
    position (a goal path runs from it). The text names the path, the first
    point off free space and what it lies in."""
    from ..robots.control import path_from_spec

    path = path_from_spec(spec, start=start)
    n = max(2, int(math.ceil(path.length / PATH_CHECK_SPACING_M)) + 1)
    s = np.linspace(0.0, path.length, n, endpoint=not path.closed)
    pts = np.column_stack([path.point(s), np.full(n, float(z))])
    hits = locate(scene, pts, meshes, parts)
    bad = next((j for j, h in enumerate(hits) if h is not None), None)
    if bad is None:
        return None
    what = (f"straight drive to the goal {_fmt(spec['goal'])}" if spec["kind"] == "goal"
            else path.describe())
    return (f"the {what} is not in free space: its point {_fmt(pts[bad][:2])} "
            f"({s[bad]:.2f} m along it) lies in {hits[bad]}")


def check_placement(scene, devices=None) -> None:
    """Refuse a device or robot path point that is not in free space (see :func:`locate`).

    Checked: every access point's array centre; every robot's body
    (``ROBOT_BODY_HEIGHT_M`` above its base) and its path every
    ``PATH_CHECK_SPACING_M`` m (a segment through a wall or a table is
    caught by the points inside it).

    Args:
        devices: the devices to check (default: all of twin.toml's), e.g. a robot
            with another path.

    Raises:
        ConfigError: one line naming twin.toml, the device (and path point),
            its position and what it lies in.
    """
    cfg = scene.config
    devices = cfg.devices if devices is None else devices
    if not devices:
        return
    meshes = object_meshes(scene)
    parts = room_parts(scene)
    index = {d.name: i for i, d in enumerate(cfg.devices)}
    for d in devices:
        where = f"{cfg.path}: devices[{index.get(d.name, '?')}] ({d.name})"
        p = np.asarray(d.position, float)
        body = p + [0.0, 0.0, ROBOT_BODY_HEIGHT_M] if d.kind == "robot" else p
        hit = locate(scene, body, meshes, parts)[0]
        if hit is not None:
            what = "robot body" if d.kind == "robot" else "array centre"
            raise ConfigError(f"{where}.position: {list(d.position)} is not in free space: "
                              f"its {what} {_fmt(body)} lies in {hit}")
        if d.kind != "robot" or d.path is None:
            continue
        try:
            msg = path_obstruction(scene, d.path, d.position[:2], body[2], meshes=meshes,
                                   parts=parts)
        except PathError as exc:  # a malformed path, e.g. two waypoints at one point
            raise ConfigError(f"{where}.path: {exc}") from None
        if msg is not None:
            raise ConfigError(f"{where}.path: {msg}")


# --------------------------------------------------------------------------- floor plan


def plan_polygons(scene, meshes=None, parts: RoomParts | None = None) -> dict[str, list]:
    """The floor plan as xy triangles ``[T, 3, 2]`` per category.

    Returns:
        ``{"floor": [...], "walls": [...], "furniture": [...]}``: per object
        ``(name, triangles [T, 3, 2])``, the projections of its non-vertical triangles (their union is the
        object's exact footprint, non-convex shapes included). The ceiling is
        left out (it would cover the plan).
    """
    meshes = object_meshes(scene) if meshes is None else meshes
    parts = room_parts(scene) if parts is None else parts
    out: dict[str, list] = {"floor": [], "walls": [], "furniture": []}
    for cat, names in (("floor", parts.floor), ("walls", parts.walls),
                       ("furniture", parts.furniture)):
        for n in names:
            v, f = meshes[n]
            tri = v[f][:, :, :2]
            area = np.abs(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]))
            if (area > 1e-9).any():
                out[cat].append((n, tri[area > 1e-9]))
    return out


def draw_plan(ax, scene, *, label_aps: bool = True) -> None:
    """Draw ``scene``'s floor plan on a matplotlib axis: floor (white), walls (dark),
    furniture (light grey), access points (triangles); limits set to the room."""
    from matplotlib.collections import PolyCollection

    meshes = object_meshes(scene)
    parts = room_parts(scene)
    polys = plan_polygons(scene, meshes, parts)
    style = {"floor": ("white", "white", 0), "furniture": ("0.82", "0.82", 1),
             "walls": ("0.35", "0.35", 2)}
    ax.set_facecolor("0.93")
    glass = "#9ecae1"  # windows, glass walls: light blue, so openings show in the plan
    for cat in ("floor", "furniture", "walls"):
        face, edge, z = style[cat]
        for name, tri in polys[cat]:
            is_glass = cat != "floor" and scene.objects[name].material == "glass"
            c = glass if is_glass else face
            ax.add_collection(PolyCollection(list(tri), facecolors=c,
                                             edgecolors=glass if is_glass else edge,
                                             linewidths=0.2, zorder=z + 0.5 * is_glass))
    if label_aps:
        for d in scene.config.devices:
            if d.kind == "access_point":
                ax.plot(*d.position[:2], "k^", ms=9, zorder=5)
                ax.annotate(d.name, d.position[:2], textcoords="offset points",
                            xytext=(6, 6), zorder=5)
    lo, hi = scene.bounds_min, scene.bounds_max
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
