"""Apply live-link messages to a Blender scene, and find viewport edits to send back.

Plain functions (plus two small state holders) that :class:`~.live.LiveSession`
calls; no operator or panel logic. Everything the live view creates lives in
the collection :data:`COLLECTION` and is named ``ISAC_Live_*``:

* robots: a TurtleBot3-like proxy mesh (cylinder body, two wheels, a nose
  showing +x), the estimated position as a small marker, and two trails
  (truth, estimate);
* trails: every trail (robots' truth and estimate, radar tracks) is one curve of ONE
  hair-curves object (``ISAC_Live_Trails``) coloured by the point attribute
  ``trail_color``; a state moves its points in place (bevelled poly curves cost ten
  times as much to evaluate per state);
* rays: ONE hair-curves object (``ISAC_Live_Rays``) rebuilt per ``paths``
  message: one curve per path, tx -> interaction vertices -> rx, with a
  per-point colour attribute ``ray_color`` (by path power or by interaction
  type; alpha = opacity by power) read by the material, so Cycles, EEVEE and
  Workbench all show it, and a per-point ``radius`` (width by power); the
  strongest N paths per link;
* radar (``[[sensing]]`` links): detections as small magenta markers in one
  mesh (``ISAC_Live_Detections``, rebuilt when a ``state`` carries them), confirmed
  tracks as larger green markers (``ISAC_Live_Tracks``) with a trail per track id;
* link metrics (Shannon and MCS rates), step and connection state: on
  ``Scene.isac_live`` for the panel.
"""

from __future__ import annotations

import math
import time

import bpy
import numpy as np
from mathutils import Matrix, Vector

from . import legend
from .contract import schema
from .exporter import safe_name

COLLECTION = legend.COLLECTION
PREFIX = "ISAC_Live_"
RAYS = PREFIX + "Rays"
RAY_COLOR_ATTR = "ray_color"
#: Ray radius in the render, m (width by power off).
RAY_RADIUS_M = 0.004
#: Ray radius range with width by power, m: the scale's low end -> its high end.
RAY_RADIUS_RANGE_M = (0.0015, 0.009)
#: Alpha of a ray at (or below) the scale's low end with opacity by power.
RAY_ALPHA_MIN = 0.15
#: Fixed colour scale of ray power, path gain ``10 log10 |a|^2`` in dB (low, high): the
#: same power has the same colour in every frame and every scene (the legend shows it).
RAY_SCALE_DB = (-110.0, -40.0)
RAYS_LEGEND = PREFIX + "RaysLegend"
#: The hair-curves object of every trail, its colour attribute and radius (m).
TRAILS = PREFIX + "Trails"
TRAIL_COLOR_ATTR = "trail_color"
TRAIL_RADIUS_M = 0.008
#: Trail colours (RGBA): a robot's truth, its estimate, a radar track.
TRAIL_COLORS = {"truth": (0.1, 0.9, 0.9, 1.0), "estimate": (1.0, 0.3, 0.1, 1.0),
                "track": (0.2, 1.0, 0.2, 1.0)}
#: Text object with one line per link (SNR, Shannon and MCS rate), behind the scene's north edge.
METRICS_TEXT = PREFIX + "Metrics"
#: Emission strength of the rays (1: the colour map's colours, not washed out to white).
RAY_EMISSION = 1.0
#: Colours per interaction type (RGBA): LOS/none, specular, diffuse, refraction, diffraction.
TYPE_COLORS = {0: (1.0, 1.0, 1.0, 1.0), 1: (0.1, 0.6, 1.0, 1.0), 2: (0.9, 0.8, 0.1, 1.0),
               4: (0.2, 0.9, 0.3, 1.0), 8: (1.0, 0.2, 0.8, 1.0)}
#: Colour-map stops (t, RGB) for power: weak = dark blue, strong = yellow/white.
_POWER_STOPS = ((0.0, (0.05, 0.05, 0.4)), (0.4, (0.1, 0.5, 0.9)), (0.7, (0.2, 0.9, 0.4)),
                (1.0, (1.0, 0.95, 0.2)))


# --------------------------------------------------------------------------- state holders


class Trail:
    """The last ``maxlen`` points ``(x, y, z)`` (m) of a trail, oldest first, kept so that
    :meth:`array` is a contiguous ``[n, 3]`` float32 view without copying (each point is
    stored twice, ``maxlen`` apart, in a ring of ``2 maxlen``): a state's trail update is a
    slice, not a conversion of 500 tuples."""

    def __init__(self, maxlen: int, points=()):
        self.maxlen = int(maxlen)
        self._buf = np.zeros((2 * self.maxlen, 3), np.float32)
        self._head = 0  # index of the oldest point
        self._n = 0
        for p in points:
            self.append(p)

    def append(self, p) -> None:
        """Add the newest point (the oldest drops out at ``maxlen``)."""
        m = self.maxlen
        if self._n < m:
            i = self._head + self._n
            self._n += 1
        else:
            i = self._head + m
            self._head = (self._head + 1) % m
        i %= m
        self._buf[i] = self._buf[i + m] = p[:3]

    def array(self) -> np.ndarray:
        """The points, oldest first, ``[n, 3]`` float32 (a view: do not keep it)."""
        return self._buf[self._head:self._head + self._n]

    def __len__(self) -> int:
        return self._n

    def __iter__(self):
        return iter(map(tuple, self.array().tolist()))



class LiveView:
    """What the view keeps between messages: trails and the devices the scene announced."""

    def __init__(self, trail_length: int = 500):
        self.trail_length = trail_length
        self.trails: dict[str, Trail] = {}
        self.estimates: dict[str, Trail] = {}
        self.robot_models: dict[str, str] = {}
        self.last_step = -1
        self.rays_built = 0
        #: Engine publish -> applied here, s (from ``state.sent_at``; same-host clocks).
        self.last_latency_s: float | None = None
        #: ``(name, points)`` of each curve of the trails object, in order
        self.trail_layout: list[tuple[str, int]] = []
        #: radar track id -> positions (m), for the track trails
        self.tracks: dict[int, Trail] = {}
        self.num_detections = 0
        #: the last ``radiomap`` message (addon/radiomap_view.py shows its layers)
        self.radiomap: dict | None = None
        #: ``(x_min, y_min, x_max, y_max)`` m of the engine's objects (scene message)
        self.extent: tuple[float, float, float, float] | None = None
        #: highest z of the engine's objects, m (scene message)
        self.top_z = 0.0


def power_color(t: float) -> tuple[float, float, float, float]:
    """Colour-map ``t`` in [0, 1] (weak -> strong) to RGBA."""
    t = min(1.0, max(0.0, t))
    for (t0, c0), (t1, c1) in zip(_POWER_STOPS, _POWER_STOPS[1:]):
        if t <= t1:
            u = (t - t0) / (t1 - t0)
            return (c0[0] + u * (c1[0] - c0[0]), c0[1] + u * (c1[1] - c0[1]),
                    c0[2] + u * (c1[2] - c0[2]), 1.0)
    return (*_POWER_STOPS[-1][1], 1.0)


# --------------------------------------------------------------------------- geometry helpers


def _cylinder(cx, cy, cz, r, h, axis="z", n=16):
    """Closed cylinder centred at (cx, cy, cz): vertices, faces."""
    verts, faces = [], []
    for k in range(n):
        a = 2 * math.pi * k / n
        u, v = r * math.cos(a), r * math.sin(a)
        for s in (-h / 2, h / 2):
            if axis == "z":
                verts.append((cx + u, cy + v, cz + s))
            else:  # y axis (wheels)
                verts.append((cx + u, cy + s, cz + v))
    for k in range(n):
        a, b = 2 * k, 2 * ((k + 1) % n)
        faces.append((a, b, b + 1, a + 1))
    faces.append(tuple(2 * k for k in range(n)))
    faces.append(tuple(2 * k + 1 for k in reversed(range(n))))
    return verts, faces


def _box(lo, hi):
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    v = [(x, y, z) for z in (z0, z1) for y in (y0, y1) for x in (x0, x1)]
    f = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    return v, f


def robot_mesh(name: str, model: str = schema.DEFAULT_ROBOT_MODEL):
    """A TurtleBot3-like proxy mesh in base_link (x forward, z up, origin on the floor),
    sized from the model's body (``schema.ROBOT_MODELS``; an unknown model: the default's):
    a cylinder as wide as the base's narrower side, its top at the robot's height."""
    body = schema.ROBOT_MODELS.get(model) or schema.ROBOT_MODELS[schema.DEFAULT_ROBOT_MODEL]
    length, width, height = body.size
    wr, ww, track = body.wheel_radius, body.wheel_width, body.wheel_separation
    r, h = min(length, width) / 2, height - wr
    parts = [_cylinder(0.0, 0.0, wr + h / 2, r, h),
             _cylinder(0.0, track / 2, wr, wr, ww, axis="y"),
             _cylinder(0.0, -track / 2, wr, wr, ww, axis="y"),
             _box((r * 0.6, -0.015, wr + h), (r * 1.3, 0.015, wr + h + 0.03))]
    verts, faces = [], []
    for v, f in parts:
        base = len(verts)
        verts += v
        faces += [tuple(i + base for i in face) for face in f]
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata(verts, [], faces)
    mesh.update()
    return mesh


def _material(name: str, rgba, *, emission: bool = False, attribute: str | None = None):
    mat = bpy.data.materials.get(name)
    if mat is not None:
        return mat
    mat = bpy.data.materials.new(name)
    mat.diffuse_color = rgba
    if bpy.app.version < (5, 0, 0):  # always on (and deprecated) from Blender 5
        mat.use_nodes = True
    nt = mat.node_tree
    nt.nodes.clear()
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    if emission:
        sh = nt.nodes.new("ShaderNodeEmission")
        sh.inputs["Strength"].default_value = 3.0
    else:
        sh = nt.nodes.new("ShaderNodeBsdfPrincipled")
    color_in = sh.inputs["Color" if emission else "Base Color"]
    color_in.default_value = rgba
    if attribute:
        attr = nt.nodes.new("ShaderNodeAttribute")
        attr.attribute_name = attribute
        nt.links.new(attr.outputs["Color"], color_in)
    nt.links.new(sh.outputs[0], out.inputs["Surface"])
    return mat


def ensure_robot(scene, name: str, model: str = schema.DEFAULT_ROBOT_MODEL):
    """The proxy object of robot ``name`` (created on first use)."""
    oname = f"{PREFIX}{name}"
    obj = bpy.data.objects.get(oname)
    if obj is None:
        mesh = robot_mesh(oname, model)
        mesh.materials.append(_material(PREFIX + "Robot", (0.9, 0.35, 0.05, 1.0)))
        obj = legend.scene_object(scene, oname, mesh)
        obj.rotation_mode = "XYZ"
    return obj


def _ensure_marker(scene, name: str):
    oname = f"{PREFIX}{name}_estimate"
    obj = bpy.data.objects.get(oname)
    if obj is None:
        mesh = bpy.data.meshes.new(oname)
        s = 0.05
        v = [(s, 0, 0), (-s, 0, 0), (0, s, 0), (0, -s, 0), (0, 0, s), (0, 0, -s)]
        f = [(0, 2, 4), (2, 1, 4), (1, 3, 4), (3, 0, 4), (2, 0, 5), (1, 2, 5), (3, 1, 5),
             (0, 3, 5)]
        mesh.from_pydata(v, [], f)
        mesh.materials.append(_material(PREFIX + "Estimate", (1.0, 0.3, 0.1, 1.0),
                                        emission=True))
        obj = legend.scene_object(scene, oname, mesh)
    return obj


_OCTA_FACES = [(0, 2, 4), (2, 1, 4), (1, 3, 4), (3, 0, 4), (2, 0, 5), (1, 2, 5), (3, 1, 5),
               (0, 3, 5)]


def marker_geometry(points, size: float):
    """Octahedra of half-size ``size`` (m) at ``points`` ``[(x, y, z), ...]``:
    ``(vertices, faces)`` for one mesh."""
    verts, faces = [], []
    for x, y, z in points:
        base = len(verts)
        verts += [(x + size, y, z), (x - size, y, z), (x, y + size, z), (x, y - size, z),
                  (x, y, z + size), (x, y, z - size)]
        faces += [tuple(base + i for i in f) for f in _OCTA_FACES]
    return verts, faces


def _set_markers(scene, name: str, points, size: float, rgba) -> None:
    """Mesh ``ISAC_Live_<name>``: one octahedron per point (rebuilt each call)."""
    oname = f"{PREFIX}{name}"
    obj = bpy.data.objects.get(oname)
    if obj is None:
        mesh = bpy.data.meshes.new(oname)
        mesh.materials.append(_material(oname, rgba, emission=True))
        obj = legend.scene_object(scene, oname, mesh)
    mesh = obj.data
    mesh.clear_geometry()
    verts, faces = marker_geometry(points, size)
    mesh.from_pydata(verts, [], faces)
    mesh.update()


def apply_sensing(scene, msg: dict, view: LiveView) -> None:
    """``state`` radar fields: detections (located ones) and confirmed tracks
    with trails; a ``state`` without them leaves the last radar picture."""
    if "detections" in msg:
        pts = [tuple(d["position"]) for d in msg["detections"] if d["position"] is not None]
        _set_markers(scene, "Detections", pts, 0.04, (1.0, 0.1, 0.9, 1.0))
        view.num_detections = len(pts)
    if "tracks" in msg:
        z = 0.12  # just above a robot's body, so the marker is visible
        pts = [(t["position"][0], t["position"][1], z) for t in msg["tracks"]]
        _set_markers(scene, "Tracks", pts, 0.08, (0.2, 1.0, 0.2, 1.0))
        for t in msg["tracks"]:
            tr = view.tracks.setdefault(int(t["id"]), Trail(view.trail_length))
            tr.append((t["position"][0], t["position"][1], z))


def trail_list(view: "LiveView") -> list[tuple[str, Trail, tuple]]:
    """Every trail of the view, in the order of the trails object's curves:
    ``(name, points, rgba)``; names ``<robot>_trail``, ``<robot>_estimate_trail``,
    ``track_<id>_trail``."""
    out = [(f"{n}_trail", pts, TRAIL_COLORS["truth"]) for n, pts in view.trails.items()]
    out += [(f"{n}_estimate_trail", pts, TRAIL_COLORS["estimate"])
            for n, pts in view.estimates.items()]
    out += [(f"track_{i}_trail", pts, TRAIL_COLORS["track"]) for i, pts in view.tracks.items()]
    return out


def set_trails(scene, view: "LiveView") -> None:
    """The trails object (:data:`TRAILS`): one poly curve per trail of at least 2 points.
    Trails of unchanged lengths (every trail at its full length) only move their points;
    a new layout rebuilds the curves and their colours. Records the layout in
    ``view.trail_layout`` (names in curve order)."""
    trails = [(n, pts, c) for n, pts, c in trail_list(view) if len(pts) >= 2]
    obj = bpy.data.objects.get(TRAILS)
    if obj is None:
        cv = bpy.data.hair_curves.new(TRAILS)
        cv.materials.append(_material(TRAILS, (1.0, 1.0, 1.0, 1.0), emission=True,
                                      attribute=TRAIL_COLOR_ATTR))
        obj = legend.scene_object(scene, TRAILS, cv)
        obj.visible_shadow = False
    cv = obj.data
    sizes = [len(pts) for _, pts, _ in trails]
    layout = [(n, k) for (n, _, _), k in zip(trails, sizes)]
    if layout != view.trail_layout:
        if len(cv.curves):
            cv.remove_curves()
        view.trail_layout = layout
        if not trails:
            return
        cv.add_curves(sizes)
        cv.set_types(type="POLY")
        attrs = cv.attributes
        rad = attrs.get("radius") or attrs.new("radius", "FLOAT", "POINT")
        rad.data.foreach_set("value", np.full(sum(sizes), TRAIL_RADIUS_M, np.float32))
        col = attrs.get(TRAIL_COLOR_ATTR) or attrs.new(TRAIL_COLOR_ATTR, "FLOAT_COLOR", "POINT")
        col.data.foreach_set("color", np.repeat(np.array([c for _, _, c in trails], np.float32),
                                                sizes, axis=0).reshape(-1))
    if not trails:
        return
    pos = np.concatenate([pts.array() for _, pts, _ in trails])
    cv.attributes["position"].data.foreach_set("vector", pos.reshape(-1))
    cv.update_tag()


def trail_points(view: "LiveView", name: str) -> list[tuple[float, float, float]]:
    """The points of trail ``name`` as drawn (read back from the trails object)."""
    cv = bpy.data.objects[TRAILS].data
    start = 0
    for n, k in view.trail_layout:
        if n == name:
            return [tuple(cv.points[i].position) for i in range(start, start + k)]
        start += k
    raise KeyError(f"no trail {name!r} is drawn")


# --------------------------------------------------------------------------- rays


def _rays_material():
    """Emission coloured by the ``ray_color`` attribute, mixed with transparency by its alpha
    (opacity by power; alpha 1 everywhere when that is off)."""
    name = PREFIX + "Rays"
    mat = bpy.data.materials.get(name)
    if mat is not None and "alpha_mix" in mat.node_tree.nodes:
        return mat
    if mat is None:
        mat = bpy.data.materials.new(name)
    mat.diffuse_color = (1.0, 1.0, 1.0, 1.0)
    if bpy.app.version < (5, 0, 0):
        mat.use_nodes = True
    nt = mat.node_tree
    nt.nodes.clear()
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    attr = nt.nodes.new("ShaderNodeAttribute")
    attr.attribute_name = RAY_COLOR_ATTR
    em = nt.nodes.new("ShaderNodeEmission")
    em.inputs["Strength"].default_value = RAY_EMISSION
    tr = nt.nodes.new("ShaderNodeBsdfTransparent")
    mix = nt.nodes.new("ShaderNodeMixShader")
    mix.name = "alpha_mix"
    nt.links.new(attr.outputs["Color"], em.inputs["Color"])
    nt.links.new(attr.outputs["Alpha"], mix.inputs["Fac"])
    nt.links.new(tr.outputs[0], mix.inputs[1])
    nt.links.new(em.outputs[0], mix.inputs[2])
    nt.links.new(mix.outputs[0], out.inputs["Surface"])
    if hasattr(mat, "surface_render_method"):
        mat.surface_render_method = "BLENDED"
    return mat


def ensure_rays(scene):
    """The hair-curves object that holds every ray polyline."""
    obj = bpy.data.objects.get(RAYS)
    if obj is None:
        cv = bpy.data.hair_curves.new(RAYS)
        cv.materials.append(_rays_material())
        obj = legend.scene_object(scene, RAYS, cv)
        obj.visible_shadow = False  # light paths, not things: no shadows on the room
    return obj


def strongest_paths(paths: list, n: int) -> list:
    """The ``n`` strongest of a link's ``paths`` (by ``power_db``), strongest first;
    ``n <= 0``: all of them in their order (the engine sends them strongest first)."""
    if n <= 0:
        return paths
    if len(paths) <= n and all(a["power_db"] >= b["power_db"] for a, b in zip(paths, paths[1:])):
        return paths
    return sorted(paths, key=lambda p: -p["power_db"])[:n]


def ray_style(power_db: float, *, width: bool = True, opacity: bool = False
              ) -> tuple[float, float]:
    """``(radius m, alpha)`` of a ray of path gain ``power_db`` (dB) on the fixed scale
    :data:`RAY_SCALE_DB`: with ``width`` the radius grows linearly from
    ``RAY_RADIUS_RANGE_M[0]`` (at or below the scale's low end) to ``[1]`` (at or above its
    high end), else :data:`RAY_RADIUS_M`; with ``opacity`` alpha grows from
    :data:`RAY_ALPHA_MIN` to 1 the same way, else 1."""
    lo, hi = RAY_SCALE_DB
    t = min(1.0, max(0.0, (power_db - lo) / (hi - lo)))
    r0, r1 = RAY_RADIUS_RANGE_M
    return (r0 + t * (r1 - r0) if width else RAY_RADIUS_M,
            RAY_ALPHA_MIN + t * (1.0 - RAY_ALPHA_MIN) if opacity else 1.0)


def _link_arrays(lk: dict):
    """One link of a ``rays`` (packed, as :class:`wire.Decoder` delivers it: bytes) or
    ``paths`` (JSON lists) message as arrays: ``(sizes [C] int, points [P, 3] float32,
    types [P] uint8 (0 at each path's ends), power_db [C] float32)``."""
    if "count" in lk:  # packed (wire 1.3): straight from the bytes, no copy
        sizes = np.frombuffer(lk["sizes"], np.uint8).astype(np.intp)
        points = np.frombuffer(lk["points"], "<f4").reshape(-1, 3)
        inner = np.frombuffer(lk["types"], np.uint8)
        power = np.frombuffer(lk["power_db"], "<f4")
    else:
        paths = lk["paths"]
        sizes = np.fromiter((len(p["points"]) for p in paths), np.intp, len(paths))
        points = np.array([q for p in paths for q in p["points"]], np.float32).reshape(-1, 3)
        inner = np.fromiter((t for p in paths for t in p["types"]), np.uint8)
        power = np.fromiter((p["power_db"] for p in paths), np.float32, len(paths))
    types = np.zeros(len(points), np.uint8)
    if len(inner):
        ends = np.zeros(len(points), bool)
        stop = np.cumsum(sizes)
        ends[stop - 1] = True
        ends[stop - sizes] = True
        types[~ends] = inner
    return sizes, points, types, power


def _select(sizes, power, n: int):
    """Indices of the curves to draw: the ``n`` strongest (all when ``n <= 0``), strongest
    first; a prefix (a slice) when the link is already in that order (the engine's)."""
    c = len(sizes)
    if n <= 0:
        return slice(0, c)
    if c <= 1 or bool(np.all(power[:-1] >= power[1:])):
        return slice(0, min(n, c))
    return np.argsort(-power, kind="stable")[:n]


def _point_index(sizes, curves):
    """Point indices ``[P']`` of the curves ``curves`` (indices) of a link with ``sizes``."""
    starts = np.cumsum(sizes) - sizes
    lens = sizes[curves]
    first = np.repeat(starts[curves] - (np.cumsum(lens) - lens), lens)
    return first + np.arange(int(lens.sum()))


def _power_rgb(t):
    """:func:`power_color` over an array ``t`` in [0, 1]: RGB ``[N, 3]`` float32."""
    ts = [s[0] for s in _POWER_STOPS]
    return np.stack([np.interp(t, ts, [s[1][k] for s in _POWER_STOPS]) for k in range(3)],
                    axis=1).astype(np.float32)


_TYPE_LUT = np.array([TYPE_COLORS.get(k, TYPE_COLORS[0]) for k in range(256)], np.float32)


def ray_arrays(msg: dict, mode: str = "POWER", max_paths: int = 0, *,
               width_by_power: bool = False, opacity_by_power: bool = False):
    """Flatten a ``rays`` or ``paths`` message: curve sizes, positions, colours, radii.

    Args:
        msg: a ``rays`` message (packed arrays as bytes, what :class:`wire.Decoder`
            delivers) or a ``paths`` message.
        mode: ``"POWER"`` (colour by path power on :data:`RAY_SCALE_DB`, strong = yellow)
            or ``"TYPE"``
            (each point coloured by the interaction it is: specular blue,
            diffuse yellow, refraction green, diffraction magenta, ends white).
        max_paths: at most this many paths per link, the strongest
            (:func:`strongest_paths`; 0 = all that were sent).
        width_by_power, opacity_by_power: radius / alpha of each path from its power
            (:func:`ray_style`).

    Returns:
        ``(sizes [C] int, positions [P, 3], colours [P, 4] RGBA, radii [P] m)``, numpy
        arrays (float32; C curves, P points).
    """
    lo, hi = RAY_SCALE_DB
    r0, r1 = RAY_RADIUS_RANGE_M
    sizes, pos, col, rad = [], [], [], []
    for lk in msg["links"]:
        s, pts, types, power = _link_arrays(lk)
        curves = _select(s, power, max_paths)
        if isinstance(curves, slice):
            s, power = s[curves], power[curves]
            n = int(s.sum())
            pts, types = pts[:n], types[:n]
        else:
            idx = _point_index(s, curves)
            s, power = s[curves], power[curves]
            pts, types = pts[idx], types[idx]
        t = np.clip((power.astype(np.float64) - lo) / (hi - lo), 0.0, 1.0)
        alpha = (RAY_ALPHA_MIN + t * (1.0 - RAY_ALPHA_MIN) if opacity_by_power
                 else np.ones(len(s)))
        c = np.empty((len(pts), 4), np.float32)
        c[:, :3] = (_TYPE_LUT[types, :3] if mode == "TYPE"
                    else np.repeat(_power_rgb(t), s, axis=0))
        c[:, 3] = np.repeat(alpha, s)
        sizes.append(s)
        pos.append(pts)
        col.append(c)
        rad.append(np.repeat(r0 + t * (r1 - r0), s) if width_by_power
                   else np.full(len(pts), RAY_RADIUS_M))
    if not sizes:
        return (np.zeros(0, np.intp), np.zeros((0, 3), np.float32),
                np.zeros((0, 4), np.float32), np.zeros(0, np.float32))
    return (np.concatenate(sizes), np.concatenate(pos), np.concatenate(col),
            np.concatenate(rad).astype(np.float32))


def set_rays(scene, sizes, positions, colors, radii=None, *, visible: bool = True):
    """Rebuild the rays object from arrays (see :func:`ray_arrays`; ``radii`` None:
    :data:`RAY_RADIUS_M` everywhere)."""
    obj = ensure_rays(scene)
    cv = obj.data
    shown = bool(visible and len(sizes))
    if obj.hide_render == shown:
        obj.hide_render = obj.hide_viewport = not shown
    if not len(sizes):
        if len(cv.curves):
            cv.remove_curves()
        return obj
    sizes = np.asarray(sizes)
    old = len(cv.curves)
    if old != len(sizes) or not np.array_equal(_curve_sizes(cv), sizes):
        if old:
            cv.remove_curves()
        cv.add_curves(sizes.tolist())
        cv.set_types(type="POLY")  # straight segments between interactions (default: Catmull-Rom)
    attrs = cv.attributes
    attrs["position"].data.foreach_set(
        "vector", np.ascontiguousarray(positions, np.float32).reshape(-1))
    rad = attrs.get("radius") or attrs.new("radius", "FLOAT", "POINT")
    rad.data.foreach_set("value", np.full(len(cv.points), RAY_RADIUS_M, np.float32)
                         if radii is None else np.ascontiguousarray(radii, np.float32))
    colr = attrs.get(RAY_COLOR_ATTR) or attrs.new(RAY_COLOR_ATTR, "FLOAT_COLOR", "POINT")
    colr.data.foreach_set("color", np.ascontiguousarray(colors, np.float32).reshape(-1))
    cv.update_tag()
    return obj


def _curve_sizes(cv):
    """Points per curve of a hair-curves datablock ``[C]``."""
    off = np.empty(len(cv.curves) + 1, np.int32)
    cv.curve_offset_data.foreach_get("value", off)
    return np.diff(off)


# --------------------------------------------------------------------------- messages


def _props(scene):
    return getattr(scene, "isac_live", None)


def _set(props, key, value):
    """Assign only on change: every RNA write tags the scene for a redraw."""
    if props is not None and getattr(props, key) != value:
        setattr(props, key, value)


def _label_at(position) -> tuple[float, float, float]:
    """Where a robot's name label sits: beside and above its base, m."""
    return (position[0] + 0.15, position[1] + 0.15, position[2] + 0.3)


def apply_scene(scene, msg: dict, view: LiveView) -> None:
    """``scene``: remember devices, create robot proxies at their configured poses."""
    p = _props(scene)
    _set(p, "scene_name", msg["name"])
    _set(p, "scene_hash", msg["content_hash"][:16])
    view.trails.clear()
    view.estimates.clear()
    lows = [o["bounds_min"] for o in msg["objects"] if "bounds_min" in o]
    highs = [o["bounds_max"] for o in msg["objects"] if "bounds_max" in o]
    if lows and highs:
        view.extent = (min(q[0] for q in lows), min(q[1] for q in lows),
                       max(q[0] for q in highs), max(q[1] for q in highs))
        view.top_z = max(q[2] for q in highs)
    for d in msg["devices"]:
        if d["kind"] == "robot":
            view.robot_models[d["name"]] = d.get("model") or schema.DEFAULT_ROBOT_MODEL
            obj = ensure_robot(scene, d["name"], view.robot_models[d["name"]])
            obj.location = d["position"]
            obj.rotation_euler = d.get("orientation") or (0.0, 0.0, 0.0)
            legend.text(scene, f"{PREFIX}{d['name']}_Label",
                        legend.device_label(d["name"], d.get("array")), _label_at(d["position"]))
        elif d["kind"] == "access_point":
            mid = (None if view.extent is None else
                   ((view.extent[0] + view.extent[2]) / 2, (view.extent[1] + view.extent[3]) / 2))
            legend.mark_access_point(scene, d["name"], d["position"],
                                     legend.device_label(d["name"], d.get("array")), toward=mid)


def apply_state(scene, msg: dict, view: LiveView) -> None:
    """``state``: robot proxies to their poses, estimate markers, trails."""
    p = _props(scene)
    _set(p, "step", msg["step"])
    _set(p, "time_s", msg["time_s"])
    for r in msg["robots"]:
        name = r["name"]
        obj = ensure_robot(scene, name, view.robot_models.get(name, schema.DEFAULT_ROBOT_MODEL))
        pose = r["pose"]
        obj.location = pose[:3]
        obj.rotation_euler = pose[3:]
        label = bpy.data.objects.get(f"{PREFIX}{name}_Label")
        if label is not None:  # follows the robot, stays upright in the world
            label.location = _label_at(pose)
        trail = view.trails.setdefault(name, Trail(view.trail_length))
        trail.append((pose[0], pose[1], 0.01))
        est = r.get("estimate")
        if est is not None:
            m = _ensure_marker(scene, name)
            m.location = est
            etrail = view.estimates.setdefault(name, Trail(view.trail_length))
            etrail.append(tuple(est))
    apply_sensing(scene, msg, view)
    set_trails(scene, view)
    view.last_step = msg["step"]
    if "sent_at" in msg:
        view.last_latency_s = time.time() - msg["sent_at"]


def apply_paths(scene, msg: dict, view: LiveView) -> None:
    """``rays`` (packed, wire 1.3) or ``paths`` (JSON, from an engine before 1.3): rebuild
    the rays object."""
    p = _props(scene)
    mode = p.ray_color_mode if p is not None else "POWER"
    cap = p.max_paths_per_link if p is not None else 0
    visible = p.show_rays if p is not None else True
    sizes, pos, col, rad = ray_arrays(
        msg, mode, cap, width_by_power=p.ray_width_by_power if p is not None else True,
        opacity_by_power=p.ray_opacity_by_power if p is not None else False)
    set_rays(scene, sizes, pos, col, rad, visible=visible)
    show_rays_legend(scene, view, visible and mode == "POWER" and bool(len(sizes)))
    view.rays_built += 1
    _set(p, "num_rays", len(sizes))
    _set(p, "paths_step", msg["step"])


def show_rays_legend(scene, view: LiveView, visible: bool = True) -> list:
    """The colour bar of the rays' power scale (:data:`RAY_SCALE_DB`), built once, in front
    of the scene's south edge right of the radio map's bar; shown or hidden."""
    objs = [bpy.data.objects.get(RAYS_LEGEND + k) for k in ("", "_Title", "_Min", "_Mid", "_Max")]
    if visible and not all(objs):
        x0, y0 = (view.extent[0], view.extent[1]) if view.extent else (0.0, 0.0)
        lo, hi = RAY_SCALE_DB
        objs = legend.colour_bar(scene, RAYS_LEGEND, lambda t: power_color(t)[:3], lo, hi,
                                 "ray path gain (dB)", (x0 + 5.6, y0 - 0.6, 0.25),
                                 length=1.8)
    for o in objs:
        if o is not None and o.hide_render == visible:
            o.hide_render = o.hide_viewport = not visible
    return [o for o in objs if o is not None]


def apply_metrics(scene, msg: dict, view: LiveView) -> None:
    """``metrics``: one row per link on ``Scene.isac_live.links``."""
    p = _props(scene)
    if p is None:
        return
    rows = p.links
    if len(rows) != len(msg["links"]):
        rows.clear()
        for _ in msg["links"]:
            rows.add()
    for row, m in zip(rows, msg["links"]):
        _set(row, "tx", m["tx"])
        _set(row, "rx", m["rx"])
        _set(row, "snr_db", m["snr_db"] if m["snr_db"] is not None else float("nan"))
        _set(row, "rate_bps", m["rate_bps"] if m["rate_bps"] is not None else 0.0)
        mcs = m.get("mcs_rate_bps")
        _set(row, "mcs_rate_bps", mcs if mcs is not None else float("nan"))
        _set(row, "num_paths", int(m.get("num_paths", 0)))
        _set(row, "los", bool(m.get("los", False)))
    _set(p, "metrics_step", msg["step"])
    show_metrics_text(scene, msg, view)


def metrics_lines(msg: dict) -> list[str]:
    """One line per link of a ``metrics`` message: SNR (dB), Shannon and MCS rate (Mbit/s)."""
    out = []
    for m in msg["links"]:
        snr = "-" if m["snr_db"] is None else f"{m['snr_db']:.1f} dB"
        rate = "-" if m["rate_bps"] is None else f"{m['rate_bps'] / 1e6:.0f} Mbit/s"
        mcs = m.get("mcs_rate_bps")
        line = f"{m['tx']} -> {m['rx']}: SNR {snr}, {rate}"
        if mcs is not None:
            line += f" (MCS {mcs / 1e6:.0f} Mbit/s)"
        if m.get("los"):
            line += ", LOS"
        out.append(line)
    return out


def show_metrics_text(scene, msg: dict, view: LiveView):
    """The link metrics as text in the 3-D view (``ISAC_Live_Metrics``), flat beyond the
    scene's north edge at the height of its top (seen over the north wall from the south),
    with the step number."""
    x0, y1 = (view.extent[0], view.extent[3]) if view.extent else (0.0, 0.0)
    body = "\n".join([f"step {msg['step']}"] + metrics_lines(msg))
    lines = body.count("\n") + 1
    return legend.text(scene, METRICS_TEXT, body,
                       (x0, y1 + 0.3 + lines * legend.TEXT_SIZE_M * 1.2, view.top_z))


def apply_status(scene, msg: dict, view: LiveView) -> None:
    p = _props(scene)
    _set(p, "running", msg["running"])
    _set(p, "engine_step", msg["step"])
    _set(p, "edits_applied", msg.get("edits_applied", 0))


def apply_error(scene, msg: dict, view: LiveView) -> None:
    _set(_props(scene), "last_error", f"{msg['code']}: {msg['message']}"[:500])


def apply_hello(scene, msg: dict, view: LiveView) -> None:
    _set(_props(scene), "engine_name", msg.get("name", ""))


_APPLY = {"scene": apply_scene, "state": apply_state, "paths": apply_paths, "rays": apply_paths,
          "metrics": apply_metrics, "status": apply_status, "error": apply_error,
          "hello": apply_hello}


def apply_message(scene, msg: dict, view: LiveView) -> None:
    """Dispatch one decoded message to its ``apply_*`` function."""
    fn = _APPLY.get(msg["type"])
    if fn is not None:
        fn(scene, msg, view)


def store_connection(scene, state: str, error: str, rejections: dict) -> None:
    """Connection state and decoder rejections, for the panel."""
    p = _props(scene)
    _set(p, "connection", state)
    if error:
        _set(p, "last_error", error[:500])
    _set(p, "rejected", int(sum(rejections.values())))


def clear_error(scene) -> None:
    """Forget the panel's last error (a new connection: the old one's errors are stale)."""
    _set(_props(scene), "last_error", "")


def clear(scene) -> None:
    """Remove everything the live view created."""
    coll = bpy.data.collections.get(COLLECTION)
    if coll is not None:
        for obj in list(coll.objects):
            data = obj.data
            bpy.data.objects.remove(obj)
            if data is not None and data.users == 0:
                if isinstance(data, bpy.types.Mesh):
                    bpy.data.meshes.remove(data)
                elif isinstance(data, bpy.types.Curve):
                    bpy.data.curves.remove(data)
                elif isinstance(data, bpy.types.Curves):
                    bpy.data.hair_curves.remove(data)
        bpy.data.collections.remove(coll)


# --------------------------------------------------------------------------- edits


def _mat_key(obj) -> tuple[str, float]:
    """(material, thickness m) the engine is told: a custom radio material of the scene
    (its own thickness; the engine knows it when its scene.xml defines it) or the ITU tag."""
    custom = obj.isac.custom_material and bpy.context.scene.isac.radio_materials.get(
        obj.isac.custom_material)
    if custom:
        return (custom.name, round(float(custom.thickness), 9))
    return (obj.isac.itu_material, round(float(obj.isac.thickness), 9))


def _m_key(m: Matrix) -> tuple:
    return tuple(round(x, 7) for row in m for x in row)


class EditTracker:
    """Finds viewport changes to send: tick-based, so it works headless.

    :meth:`baseline` records, for every engine object and device, its world
    matrix, its world bounding-box centre and its radio material as they are
    when the engine's ``scene`` arrives (the two are assumed to agree then).
    :meth:`poll` compares against what was last sent and returns ``edit``
    messages: ``move`` with ``position`` = new world bounding-box centre of
    the geometry as loaded (``M_now M_base^-1 c_base``) and ``orientation`` =
    ``[roll, pitch, yaw]`` of ``R_now R_base^T`` (rotation relative to the
    loaded geometry); for devices the object's location and XYZ Euler
    angles; ``material`` when the ITU material or thickness changed;
    ``remove`` when the object was deleted; ``add`` (the world-coordinate mesh
    as PLY bytes in the message: the engine reads no file a viewer names outside
    its scene folder) for a new mesh once it has a radio material.

    :meth:`resend` is for an engine that restarted with the scene as baselined
    and so lost the edits: the next :meth:`poll` sends again every difference
    from the baseline (moves, materials, removals, additions).
    """

    def __init__(self):
        self._base: dict[str, tuple] = {}    # object name -> (kind, wire name, M_base, c_base)
        self._sent: dict[str, tuple] = {}    # object name -> (matrix key, material key)
        self._base_keys: dict[str, tuple] = {}  # object name -> keys as the engine loaded it
        self._removed: list[str] = []        # wire names removed by edits since the baseline
        self._new: set[str] = set()          # object names added by edits since the baseline
        self._pending: list[dict] = []       # edits poll() sends first (resend)
        self._known: set[str] = set()
        self.active = False

    @property
    def tracked(self) -> list[str]:
        return sorted(self._base)

    def _track_object(self, obj, wname: str) -> None:
        m = obj.matrix_world.copy()
        corners = [m @ Vector(c) for c in obj.bound_box]
        lo = Vector([min(c[i] for c in corners) for i in range(3)])
        hi = Vector([max(c[i] for c in corners) for i in range(3)])
        self._base[obj.name] = ("object", wname, m, (lo + hi) / 2)
        self._sent[obj.name] = self._base_keys[obj.name] = (_m_key(obj.matrix_world),
                                                            _mat_key(obj))

    def baseline(self, scene, object_names, device_names) -> None:
        self._base.clear()
        self._sent.clear()
        self._base_keys.clear()
        self._removed.clear()
        self._new.clear()
        self._pending.clear()
        self.active = True
        for obj in scene.objects:
            if obj.name.startswith(PREFIX):
                continue
            kind = obj.isac.device_kind
            wname = safe_name(obj.name)
            if kind == "NONE" and obj.type == "MESH" and wname in object_names:
                self._track_object(obj, wname)
            elif kind != "NONE" and obj.name in device_names:
                self._base[obj.name] = ("device", obj.name, obj.matrix_world.copy(), None)
                self._sent[obj.name] = self._base_keys[obj.name] = (
                    _m_key(obj.matrix_world), _mat_key(obj))
        self._known = set(scene.objects.keys())

    def resend(self) -> list[str]:
        """Make the next :meth:`poll` send again every edit made since the baseline
        (the engine restarted with the baselined scene). Returns the names concerned."""
        names = []
        for name in list(self._base):
            if name in self._new:  # added by an edit: poll() adds it again
                del self._base[name], self._sent[name], self._base_keys[name]
                self._known.discard(name)
                names.append(name)
            elif self._sent[name] != self._base_keys[name]:
                self._sent[name] = self._base_keys[name]
                names.append(name)
        self._new.clear()
        from .contract import wire

        self._pending = [wire.edit("remove", w) for w in self._removed]
        names += self._removed
        return names

    def _added(self, scene) -> list[dict]:
        """New radio-tagged meshes: ``add`` edits carrying the world mesh as PLY bytes."""
        from . import materials
        from .contract import wire
        from .contract.writers.geometry import ply_bytes, world_mesh

        out = []
        names = scene.objects.keys()
        if len(names) == len(self._known) and not set(names) - self._known:
            return out
        for name in set(names) - self._known:
            obj = scene.objects[name]
            if (name.startswith(PREFIX) or obj.type != "MESH" or obj.isac.device_kind != "NONE"
                    or (obj.isac.itu_material == materials.NO_MATERIAL
                        and not obj.isac.custom_material)
                    or not obj.isac.export_geometry):
                continue  # not (yet) radio geometry: looked at again when tagged
            wname = safe_name(name)
            data = ply_bytes(world_mesh(obj, bpy.context.evaluated_depsgraph_get(), wname))
            mat, thick = _mat_key(obj)
            out.append(wire.edit("add", wname, material=mat, thickness=thick, mesh_ply=data))
            self._track_object(obj, wname)
            self._known.add(name)
            self._new.add(name)
        self._known &= set(names) | set(self._base)
        return out

    def poll(self, scene) -> list[dict]:
        from .contract import wire

        if not self.active:
            return []
        out, self._pending = self._pending, []
        out += self._added(scene)
        objs = scene.objects
        for name, (kind, wname, m0, c0) in list(self._base.items()):
            obj = objs.get(name)
            if obj is None:
                out.append(wire.edit("remove", wname))
                del self._base[name], self._sent[name], self._base_keys[name]
                if name in self._new:
                    self._new.discard(name)
                else:
                    self._removed.append(wname)
                continue
            mk, matk = _m_key(obj.matrix_world), _mat_key(obj)
            last_m, last_mat = self._sent[name]
            if mk != last_m:
                m = obj.matrix_world
                if kind == "object":
                    delta = m @ m0.inverted()
                    pos = delta @ c0
                    rot = (delta.to_3x3().normalized()).to_euler("XYZ")
                else:
                    pos = m.to_translation()
                    rot = m.to_3x3().normalized().to_euler("XYZ")
                out.append(wire.edit("move", wname, position=tuple(pos),
                                     orientation=tuple(rot)))
            if kind == "object" and matk != last_mat:
                out.append(wire.edit("material", wname, material=matk[0], thickness=matk[1]))
            self._sent[name] = (mk, matk)
        return out
