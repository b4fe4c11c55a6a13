"""Write small scene folders from code: analytic test rooms without Blender.

Used by the engine's tests and benchmarks (a closed box room, a single
reflector) so that the engine can be checked without ``bpy``. The files are
written by the contract's scene-folder writers (:mod:`isac_twin.contract.writers`),
the same functions the add-on's exporter calls: one writer of the scene-folder
format (``docs/config.md``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..contract import schema
from ..contract.writers import geometry, mitsuba_xml, twin_toml


def box_mesh(lo, hi) -> tuple[np.ndarray, np.ndarray]:
    """Closed axis-aligned box: vertices ``[8, 3]``, outward triangles ``[12, 3]``."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    v = np.array([[x, y, z] for z in (lo[2], hi[2]) for y in (lo[1], hi[1])
                  for x in (lo[0], hi[0])])
    f = np.array([[0, 2, 1], [1, 2, 3], [4, 5, 6], [5, 7, 6], [0, 1, 4], [1, 5, 4],
                  [2, 6, 3], [3, 6, 7], [0, 4, 2], [2, 4, 6], [1, 3, 5], [3, 7, 5]])
    return v, f


def quad_mesh(corners) -> tuple[np.ndarray, np.ndarray]:
    """Planar quad from 4 corners ``[4, 3]`` (counter-clockwise seen from the normal)."""
    return np.asarray(corners, float), np.array([[0, 1, 2], [0, 2, 3]])


def write_ply(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    """Binary little-endian PLY (float32 ``x y z``, uchar/int triangle lists), written
    by the add-on's ``geometry.write_ply``."""
    v = np.asarray(vertices, float)
    mesh = geometry.WorldMesh(Path(path).stem, [float(x) for x in v.reshape(-1)],
                         [int(i) for i in np.asarray(faces).reshape(-1)], 0.0)
    geometry.write_ply(Path(path), mesh)


@dataclass
class SyntheticObject:
    name: str
    vertices: np.ndarray
    faces: np.ndarray
    material: str = "concrete"
    thickness: float = 0.2


@dataclass
class SyntheticDevice:
    name: str
    kind: str
    role: str
    position: tuple[float, float, float]
    rows: int = 1
    cols: int = 1
    power_dbm: float = 20.0
    orientation: tuple[float, float, float] = (0.0, 0.0, 0.0)
    extra: dict = field(default_factory=dict)


def write_scene_folder(folder: str | Path, objects: list[SyntheticObject],
                       devices: list[SyntheticDevice], links: list[tuple[str, str]],
                       *, frequency_hz: float = 2.4e9, name: str = "synthetic",
                       num_subcarriers: int = 1024, subcarrier_spacing_hz: float = 78125.0,
                       num_symbols: int = 14, tracer: dict | None = None,
                       room: dict | None = None,
                       custom_materials: dict[str, dict] | None = None) -> Path:
    """Write ``scene.xml``, ``meshes/*.ply`` and ``twin.toml``; return the folder.
    ``room``: a ``[room]`` table (``{"shell": [...], "furniture": [...]}``).
    ``custom_materials``: custom radio materials objects may name, ``name ->
    {"relative_permittivity", "conductivity" (S/m), "thickness" (m)}``."""
    folder = Path(folder)
    (folder / "meshes").mkdir(parents=True, exist_ok=True)
    for o in objects:
        write_ply(folder / "meshes" / f"{o.name}.ply", o.vertices, o.faces)
    mitsuba_xml.write_scene_xml(
        folder / "scene.xml", [(o.name, o.material, float(o.thickness)) for o in objects],
        custom_materials)
    data: dict = {
        "schema": schema.TWIN_TOML_SCHEMA,
        "scene": {"name": name, "file": "scene.xml", "frequency_hz": float(frequency_hz)},
        "ofdm": {"num_subcarriers": int(num_subcarriers),
                 "subcarrier_spacing_hz": float(subcarrier_spacing_hz),
                 "num_symbols": int(num_symbols), "cyclic_prefix_samples": 72},
    }
    if tracer:
        data["tracer"] = dict(tracer)
    data["devices"] = [
        {"name": d.name, "kind": d.kind, "role": d.role,
         "position": [float(x) for x in d.position],
         "orientation": [float(x) for x in d.orientation], "power_dbm": float(d.power_dbm),
         **d.extra,
         "array": {"rows": d.rows, "cols": d.cols,
                   "vertical_spacing": schema.DEFAULT_ELEMENT_SPACING,
                   "horizontal_spacing": schema.DEFAULT_ELEMENT_SPACING,
                   "pattern": schema.DEFAULT_PATTERN,
                   "polarization": schema.DEFAULT_POLARIZATION}}
        for d in devices]
    if links:
        data["links"] = [{"tx": tx, "rx": rx} for tx, rx in links]
    if room:
        data["room"] = dict(room)
    twin_toml.write_twin_toml(folder / "twin.toml", data)
    return folder


ROBOT_EXTRA = {"model": schema.DEFAULT_ROBOT_MODEL,
               "antenna_offset": list(schema.DEFAULT_ANTENNA_OFFSET)}


def room_objects(size=(6.0, 4.0, 3.0), furniture=None, *, material: str = "concrete",
                 thickness: float = 0.2) -> list[SyntheticObject]:
    """A closed room ``[0, sx] x [0, sy] x [0, sz]`` as six slabs, plus furniture.

    Each slab is a 0.1 m box just outside the room volume, so its inner face lies
    exactly on the room boundary.

    Args:
        size: room extent ``(sx, sy, sz)``, m.
        furniture: ``name -> (lo [3], hi [3])`` boxes (wood, 5 cm), or
            ``name -> (lo, hi, material, thickness)``.
    """
    sx, sy, sz = size
    w = 0.1
    slabs = {
        "floor": ((0, 0, -w), (sx, sy, 0)), "ceiling": ((0, 0, sz), (sx, sy, sz + w)),
        "wall_xmin": ((-w, 0, 0), (0, sy, sz)), "wall_xmax": ((sx, 0, 0), (sx + w, sy, sz)),
        "wall_ymin": ((0, -w, 0), (sx, 0, sz)), "wall_ymax": ((0, sy, 0), (sx, sy + w, sz)),
    }
    objs = [SyntheticObject(n, *box_mesh(lo, hi), material=material, thickness=thickness)
            for n, (lo, hi) in slabs.items()]
    for n, spec in (furniture or {}).items():
        lo, hi, mat, th = (*spec, "wood", 0.05) if len(spec) == 2 else spec
        objs.append(SyntheticObject(n, *box_mesh(lo, hi), material=mat, thickness=th))
    return objs


def two_ap_lab(folder: str | Path, *, size=(6.0, 4.0, 3.0), furniture=None,
               ap1=(0.1, 2.0, 2.0), ap2=(3.0, 0.1, 2.0), robot=(4.0, 2.0, 0.0),
               **kw) -> Path:
    """The bundled lab in miniature: a furnished room, AP1 (2x2) on OFDM symbols
    0-6 and AP2 (1x1, facing +y) on 7-13, a Burger with two antennas facing +y,
    links AP1->robot1 and AP2->robot1. Keyword arguments go to
    :func:`write_scene_folder` (e.g. ``tracer``, ``frequency_hz``)."""
    devs = [SyntheticDevice("AP1", "access_point", "tx", ap1, rows=2, cols=2,
                            extra={"symbols": [0, 7]}),
            SyntheticDevice("AP2", "access_point", "tx", ap2, orientation=(0.0, 0.0, 1.5708),
                            extra={"symbols": [7, 14]}),
            SyntheticDevice("robot1", "robot", "rx", robot, cols=2,
                            orientation=(0.0, 0.0, 1.5708), extra=dict(ROBOT_EXTRA))]
    return write_scene_folder(folder, room_objects(size, furniture), devs,
                              [("AP1", "robot1"), ("AP2", "robot1")], **kw)


def box_room(folder: str | Path, size=(6.0, 4.0, 3.0), *, material: str = "concrete",
             devices: list[SyntheticDevice] | None = None,
             links: list[tuple[str, str]] | None = None, **kw) -> Path:
    """An empty closed room (:func:`room_objects`) with AP1 (2x2) and a robot."""
    sx, sy, _ = size
    if devices is None:
        devices = [SyntheticDevice("AP1", "access_point", "tx", (1.0, 1.0, 2.0), rows=2, cols=2),
                   SyntheticDevice("robot1", "robot", "rx", (sx / 2, sy / 2, 0.0), cols=2,
                                   extra=dict(ROBOT_EXTRA))]
        links = [("AP1", "robot1")]
    return write_scene_folder(folder, room_objects(size, material=material), devices,
                              links or [], **kw)


def prism_mesh(polygon, z0: float, z1: float) -> tuple[np.ndarray, np.ndarray]:
    """Closed prism: the XY ``polygon`` ``[n, 2]`` (either winding, simple) extruded from
    ``z0`` to ``z1`` m -> vertices ``[2n, 3]``, outward triangles ``[4n - 4, 3]``.
    Caps are ear-clipped, so non-convex footprints (an L) are exact."""
    pts = [tuple(map(float, p)) for p in polygon]
    area = 0.5 * sum(pts[i][0] * pts[(i + 1) % len(pts)][1]
                     - pts[(i + 1) % len(pts)][0] * pts[i][1] for i in range(len(pts)))
    if area < 0:
        pts = pts[::-1]
    n = len(pts)
    v = np.array([(x, y, z0) for x, y in pts] + [(x, y, z1) for x, y in pts])
    cap = _ear_clip(pts)
    faces = [(c, b, a) for a, b, c in cap] + [(a + n, b + n, c + n) for a, b, c in cap]
    for i in range(n):
        j = (i + 1) % n
        faces += [(i, j, j + n), (i, j + n, i + n)]
    return v, np.array(faces)


def _ear_clip(pts) -> list[tuple[int, int, int]]:
    """Triangles (ccw index triples) of a simple ccw polygon."""
    idx = list(range(len(pts)))
    out = []

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    while len(idx) > 3:
        for k in range(len(idx)):
            a, b, c = idx[k - 1], idx[k], idx[(k + 1) % len(idx)]
            if cross(pts[a], pts[b], pts[c]) <= 1e-12:
                continue
            if any(cross(pts[a], pts[b], pts[m]) >= 0 and cross(pts[b], pts[c], pts[m]) >= 0
                   and cross(pts[c], pts[a], pts[m]) >= 0 for m in idx if m not in (a, b, c)):
                continue
            out.append((a, b, c))
            idx.pop(k)
            break
        else:
            raise ValueError("polygon is not simple: no ear found")
    out.append(tuple(idx))
    return out


def polygon_room_objects(polygon, height: float = 3.0, wall: float = 0.2, *,
                         name: str = "Room", wall_material: str = "concrete",
                         floor_material: str = "concrete",
                         ceiling_material: str = "plasterboard",
                         furniture=None) -> list[SyntheticObject]:
    """A room on a footprint as the add-on's ``create_room_from_polygon`` builds it:
    ``<name>_Floor`` below z = 0, ``<name>_Ceiling`` above ``height``, one mitred wall
    ``<name>_Wall_<i>`` outside each footprint edge (all closed prisms), plus
    furniture boxes as in :func:`room_objects`."""
    pts = [tuple(map(float, p)) for p in polygon]
    area = 0.5 * sum(pts[i][0] * pts[(i + 1) % len(pts)][1]
                     - pts[(i + 1) % len(pts)][0] * pts[i][1] for i in range(len(pts)))
    pts = pts if area > 0 else pts[::-1]
    n = len(pts)
    normals = []
    for i in range(n):
        (x0, y0), (x1, y1) = pts[i], pts[(i + 1) % n]
        ln = np.hypot(x1 - x0, y1 - y0)
        normals.append(((y1 - y0) / ln, -(x1 - x0) / ln))
    outer = []
    for i in range(n):
        (ax, ay), (bx, by) = normals[i - 1], normals[i]
        d = 1.0 + ax * bx + ay * by
        outer.append((pts[i][0] + wall * (ax + bx) / d, pts[i][1] + wall * (ay + by) / d))
    objs = [SyntheticObject(f"{name}_Floor", *prism_mesh(pts, -wall, 0.0),
                            material=floor_material, thickness=wall),
            SyntheticObject(f"{name}_Ceiling", *prism_mesh(pts, height, height + wall),
                            material=ceiling_material, thickness=wall)]
    for i in range(n):
        j = (i + 1) % n
        objs.append(SyntheticObject(f"{name}_Wall_{i + 1}",
                                    *prism_mesh([pts[i], outer[i], outer[j], pts[j]], 0.0,
                                                height),
                                    material=wall_material, thickness=wall))
    for nm, spec in (furniture or {}).items():
        lo, hi, mat, th = (*spec, "wood", 0.05) if len(spec) == 2 else spec
        objs.append(SyntheticObject(nm, *box_mesh(lo, hi), material=mat, thickness=th))
    return objs


#: A 6 m x 5 m L-shaped footprint (the corner x > 4, y > 3 cut out), m.
L_FOOTPRINT = [(0.0, 0.0), (6.0, 0.0), (6.0, 3.0), (4.0, 3.0), (4.0, 5.0), (0.0, 5.0)]


def l_room(folder: str | Path, *, robot=(2.0, 1.5, 0.0), path: dict | None = None,
           furniture=None, room: dict | None = None, **kw) -> Path:
    """A small furnished L-shaped room (:data:`L_FOOTPRINT`, 3 m high) named the way the
    add-on names rooms (``Room_Floor``, ``Room_Wall_1`` ...), with AP1 (2x2, symbols
    0-6) and AP2 (1x1, 7-13) and robot1 on ``path`` (default a polyline loop around
    the desk; ``{}``: none). ``room``: a ``[room]`` table to write. Keyword arguments go to
    :func:`write_scene_folder`."""
    furniture = furniture if furniture is not None else {
        "Desk": ((1.2, 3.6, 0.0), (2.8, 4.4, 0.75)),
        "Cabinet": ((5.0, 0.1, 0.0), (5.9, 0.6, 2.0), "metal", 0.002)}
    path = path if path is not None else {
        "kind": "polyline", "closed": True,
        "waypoints": [[1.0, 1.0], [3.5, 1.0], [3.5, 2.5], [1.0, 2.5]]}
    devs = [SyntheticDevice("AP1", "access_point", "tx", (0.1, 2.5, 2.2), rows=2, cols=2,
                            extra={"symbols": [0, 7]}),
            SyntheticDevice("AP2", "access_point", "tx", (5.0, 2.9, 2.2),
                            orientation=(0.0, 0.0, -1.5708), extra={"symbols": [7, 14]}),
            SyntheticDevice("robot1", "robot", "rx", robot, cols=2,
                            orientation=(0.0, 0.0, 0.0),
                            extra={**ROBOT_EXTRA, "path": dict(path)} if path else
                            dict(ROBOT_EXTRA))]
    return write_scene_folder(folder, polygon_room_objects(L_FOOTPRINT, furniture=furniture),
                              devs, [("AP1", "robot1"), ("AP2", "robot1")], room=room, **kw)


def furnished_room(folder: str | Path, *, size=(4.0, 3.0, 3.0), tracer=None, robot=(2.1, 1.5, 0.0),
                   ap_rows=1, ap_cols=1, links=None, extra_devices=()):
    """4 x 3 x 3 m concrete room, a cabinet (closed box) and a table top; two
    ceiling APs and one robot with open LOS to both (the ray-tracing tests' room).

    Args:
        size: room ``(x, y, z)``, m.
        tracer: ``[tracer]`` keys over ``samples_per_src = 20000``.
        robot: the robot's position ``[3]``, m.
        ap_rows, ap_cols: the APs' array.
        links: ``(tx, rx)`` pairs (default AP1 and AP2 to robot1).
        extra_devices: more :class:`SyntheticDevice` s.
    """
    furniture = {"cabinet": ((3.0, 0.2, 0.0), (3.6, 0.8, 1.2)),
                 "table": ((0.4, 2.0, 0.7), (1.4, 2.8, 0.75))}
    devices = [SyntheticDevice("AP1", "access_point", "tx", (0.5, 0.5, 2.5), rows=ap_rows,
                               cols=ap_cols),
               SyntheticDevice("AP2", "access_point", "tx", (3.5, 2.5, 2.5), rows=ap_rows,
                               cols=ap_cols),
               SyntheticDevice("robot1", "robot", "rx", robot, cols=2, extra=ROBOT_EXTRA),
               *extra_devices]
    links = links or [("AP1", "robot1"), ("AP2", "robot1")]
    tr = {"samples_per_src": 20000}
    tr.update(tracer or {})
    return write_scene_folder(folder, room_objects(size, furniture), devices, links, tracer=tr)


def reflector_scene(folder: str | Path) -> Path:
    """A large metal plane z = 0 plus a tiny far-away marker box that extends the
    scene bounds upwards; tx at (0, 0, 1), rx at (2, 0, 1.5)."""
    plane = SyntheticObject("plane", *quad_mesh([(-10, -10, 0), (10, -10, 0), (10, 10, 0),
                                                 (-10, 10, 0)]), material="metal",
                            thickness=0.01)
    marker = SyntheticObject("marker", *box_mesh((9.8, 9.8, 2.9), (9.9, 9.9, 3.0)))
    devices = [SyntheticDevice("TX", "access_point", "tx", (0.0, 0.0, 1.0)),
               SyntheticDevice("RX", "access_point", "rx", (2.0, 0.0, 1.5))]
    return write_scene_folder(folder, [plane, marker], devices, [("TX", "RX")],
                              tracer={"max_depth": 1, "refraction": False,
                                      "samples_per_src": 20000})
