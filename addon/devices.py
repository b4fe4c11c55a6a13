"""Access points, robots, links and scene-level radio settings as plain functions.

Devices are Blender *empties*: they carry radio settings in ``Object.isac``
but no geometry, so the exporter writes them to ``twin.toml`` and never into
``scene.xml``. Orientation follows the twin's convention [roll, pitch, yaw]
applied as Rz(yaw) Ry(pitch) Rx(roll), which is Blender's 'XYZ' Euler order;
an array's boresight is its local +x axis (as in Sionna).
"""

from __future__ import annotations

from typing import Sequence

import bpy

from .contract import schema
from .modelling import get_collection

DEVICE_COLLECTION = "Devices"


def _set_array(props, rows, cols, vertical_spacing, horizontal_spacing, pattern, polarization):
    props.array_rows = int(rows)
    props.array_cols = int(cols)
    props.vertical_spacing = float(vertical_spacing)
    props.horizontal_spacing = float(horizontal_spacing)
    props.pattern = pattern
    props.polarization = polarization


def _new_empty(name: str, location, orientation, display: str, size: float, scene):
    scene = scene if scene is not None else bpy.context.scene
    obj = bpy.data.objects.new(name, None)
    obj.empty_display_type = display
    obj.empty_display_size = size
    obj.location = tuple(location)
    obj.rotation_mode = "XYZ"
    obj.rotation_euler = tuple(orientation)
    get_collection(scene, DEVICE_COLLECTION).objects.link(obj)
    return obj


def add_access_point(
    name: str = "AP",
    location: Sequence[float] = (0.0, 0.0, 2.0),
    orientation: Sequence[float] = (0.0, 0.0, 0.0),
    *,
    rows: int = 1,
    cols: int = 1,
    vertical_spacing: float = schema.DEFAULT_ELEMENT_SPACING,
    horizontal_spacing: float = schema.DEFAULT_ELEMENT_SPACING,
    pattern: str = schema.DEFAULT_PATTERN,
    polarization: str = schema.DEFAULT_POLARIZATION,
    power_dbm: float = 20.0,
    role: str = "tx",
    subcarriers: Sequence[int] | None = None,
    symbols: Sequence[int] | None = None,
    scene=None,
):
    """An access point: an empty at the array centre whose +x axis is the boresight.

    Args:
        name: device name (the object name; Blender appends .001 on a clash).
        location: array centre, m.
        orientation: [roll, pitch, yaw], rad.
        rows, cols: planar array size (>= 1).
        vertical_spacing, horizontal_spacing: element spacing, wavelengths.
        pattern: a ``schema.PATTERNS`` name ("iso", "dipole", ...).
        polarization: a ``schema.POLARIZATIONS`` name ("V", "H", ...).
        power_dbm: total transmit power, dBm.
        role: "tx" | "rx" | "txrx".
        subcarriers, symbols: resource set as half-open ``[start, stop)`` ranges
            (None: the whole grid).

    Returns:
        The new empty object.
    """
    obj = _new_empty(name, location, orientation, "ARROWS", 0.2, scene)
    p = obj.isac
    p.device_kind = "ACCESS_POINT"
    p.role = role
    p.power_dbm = float(power_dbm)
    _set_array(p, rows, cols, vertical_spacing, horizontal_spacing, pattern, polarization)
    set_resources(obj, subcarriers, symbols)
    return obj


def set_resources(obj, subcarriers: Sequence[int] | None = None,
                  symbols: Sequence[int] | None = None) -> None:
    """Set a transmitter's resource set R_q: half-open ``[start, stop)`` ranges of
    subcarriers and OFDM symbols; None keeps the whole grid on that axis."""
    p = obj.isac
    p.subcarrier_start, p.subcarrier_stop = subcarriers if subcarriers else (0, 0)
    p.symbol_start, p.symbol_stop = symbols if symbols else (0, 0)


def set_circle_path(obj, centre: Sequence[float], radius: float, direction: str = "ccw",
                    speed: float | None = None) -> None:
    """Make a robot follow a circle (centre ``[2]`` m, radius m, ``"ccw"``/``"cw"``,
    cruise speed m/s or None for the model's limit) in the twin."""
    p = _path_robot(obj)
    p.path_kind = "circle"
    p.path_centre = tuple(centre)
    p.path_radius = float(radius)
    p.path_direction = direction
    p.path_speed = float(speed or 0.0)


def _path_robot(obj):
    p = obj.isac
    if p.device_kind != "ROBOT":
        raise ValueError(f"'{obj.name}' is not a robot: only robots follow paths")
    return p


def set_polyline_path(obj, curve, speed: float | None = None) -> None:
    """Make a robot follow a Blender curve object's points (world x, y, m) as a
    polyline; the curve's first spline being cyclic makes it a closed loop."""
    p = _path_robot(obj)
    if curve is None or curve.type != "CURVE":
        raise ValueError(f"'{getattr(curve, 'name', curve)}' is not a curve object")
    p.path_kind = "polyline"
    p.path_curve = curve
    p.path_speed = float(speed or 0.0)


def set_figure_eight_path(obj, centre: Sequence[float], size: float,
                          speed: float | None = None) -> None:
    """Make a robot follow a figure eight (lemniscate of Gerono) ``size`` m wide along x,
    ``size / 2`` high, centred on ``centre`` ``[2]`` m."""
    p = _path_robot(obj)
    p.path_kind = "figure_eight"
    p.path_centre = tuple(centre)
    p.path_size = float(size)
    p.path_speed = float(speed or 0.0)


def set_goal_path(obj, goal: Sequence[float], speed: float | None = None) -> None:
    """Make a robot drive to ``goal`` ``[2]`` m and stop."""
    p = _path_robot(obj)
    p.path_kind = "goal"
    p.path_goal = tuple(goal)
    p.path_speed = float(speed or 0.0)


def add_path_curve(name: str, points: Sequence[Sequence[float]], *, closed: bool = False,
                   z: float = 0.0, scene=None):
    """A poly curve object through ``points`` ``[(x, y), ...]`` m (at height ``z``), in the
    Devices collection: a robot path the user can edit in the viewport."""
    if len(points) < 2:
        raise ValueError(f"Path '{name}': a polyline needs at least 2 points, got {len(points)}")
    scene = scene if scene is not None else bpy.context.scene
    data = bpy.data.curves.new(name, type="CURVE")
    data.dimensions = "3D"
    spline = data.splines.new("POLY")
    spline.points.add(len(points) - 1)
    for pt, (x, y, *_) in zip(spline.points, points):
        pt.co = (float(x), float(y), float(z), 1.0)
    spline.use_cyclic_u = bool(closed)
    obj = bpy.data.objects.new(name, data)
    get_collection(scene, DEVICE_COLLECTION).objects.link(obj)
    return obj


def set_rectangle_path(obj, centre: Sequence[float], width: float, depth: float,
                       speed: float | None = None, scene=None):
    """Make a robot drive a closed rectangle (``width`` along x, ``depth`` along y, m)
    counter-clockwise around ``centre``: a cyclic path curve it follows as a polyline.
    Returns the curve object."""
    for key, v in (("width", width), ("depth", depth)):
        if not v > 0:
            raise ValueError(f"Rectangle path: {key} must be > 0 m, got {v!r}")
    cx, cy = centre[0], centre[1]
    w, d = width / 2, depth / 2
    curve = add_path_curve(f"{obj.name}_Path", [(cx - w, cy - d), (cx + w, cy - d),
                                               (cx + w, cy + d), (cx - w, cy + d)],
                           closed=True, scene=scene)
    set_polyline_path(obj, curve, speed)
    return curve


def curve_waypoints(curve) -> tuple[list[list[float]], bool]:
    """World ``[[x, y], ...]`` (m) of a curve object's first spline and whether it is
    cyclic; Bezier splines give their control points."""
    if curve is None or not curve.data.splines:
        return [], False
    spline = curve.data.splines[0]
    mw = curve.matrix_world
    if spline.type == "BEZIER":
        cos = [bp.co for bp in spline.bezier_points]
    else:
        cos = [pt.co.xyz for pt in spline.points]
    pts = [list((mw @ c)[:2]) for c in cos]
    return [[float(x), float(y)] for x, y in pts], bool(spline.use_cyclic_u)


def add_robot(
    name: str = "robot",
    location: Sequence[float] = (0.0, 0.0, 0.0),
    yaw: float = 0.0,
    *,
    model: str = schema.DEFAULT_ROBOT_MODEL,
    rows: int = 1,
    cols: int = 1,
    vertical_spacing: float = schema.DEFAULT_ELEMENT_SPACING,
    horizontal_spacing: float = schema.DEFAULT_ELEMENT_SPACING,
    pattern: str = schema.DEFAULT_PATTERN,
    polarization: str = schema.DEFAULT_POLARIZATION,
    antenna_offset: Sequence[float] = schema.DEFAULT_ANTENNA_OFFSET,
    power_dbm: float = 10.0,
    role: str = "rx",
    scene=None,
):
    """A robot: an empty at base_link on the floor, heading ``yaw`` rad (x forward, REP-103).

    Args:
        location: base_link position, m (z = 0 on the floor).
        model: a ``schema.ROBOT_MODELS`` name (TurtleBot3 "burger", ...).
        antenna_offset: array centre in base_link, m.
        Other arguments as :func:`add_access_point`.
    """
    if model not in schema.ROBOT_MODELS:
        raise ValueError(f"robot model {model!r}: expected one of {', '.join(schema.ROBOT_MODELS)}")
    size = max(schema.ROBOT_MODELS[model].size) / 2
    obj = _new_empty(name, location, (0.0, 0.0, yaw), "CUBE", size, scene)
    p = obj.isac
    p.device_kind = "ROBOT"
    p.robot_model = model
    p.role = role
    p.power_dbm = float(power_dbm)
    p.antenna_offset = tuple(antenna_offset)
    _set_array(p, rows, cols, vertical_spacing, horizontal_spacing, pattern, polarization)
    return obj


def device_objects(scene) -> list:
    """Access points and robots of ``scene``, sorted by name."""
    return sorted((o for o in scene.objects if o.isac.device_kind != "NONE"),
                  key=lambda o: o.name)


def set_radio_settings(
    scene,
    *,
    frequency_hz: float | None = None,
    num_subcarriers: int | None = None,
    subcarrier_spacing_hz: float | None = None,
    num_symbols: int | None = None,
    cyclic_prefix_samples: int | None = None,
    twin_name: str | None = None,
) -> None:
    """Set the scene-level carrier (Hz) and OFDM numerology; ``None`` leaves a value as is."""
    p = scene.isac
    if frequency_hz is not None:
        p.frequency_hz = float(frequency_hz)
    if num_subcarriers is not None:
        p.num_subcarriers = int(num_subcarriers)
    if subcarrier_spacing_hz is not None:
        p.subcarrier_spacing_hz = float(subcarrier_spacing_hz)
    if num_symbols is not None:
        p.num_symbols = int(num_symbols)
    if cyclic_prefix_samples is not None:
        p.cyclic_prefix_samples = int(cyclic_prefix_samples)
    if twin_name is not None:
        p.twin_name = twin_name


def add_link(scene, tx: str, rx: str):
    """Append a link tx -> rx (device object names); checked at export. Returns the item."""
    item = scene.isac.links.add()
    item.tx = tx
    item.rx = rx
    scene.isac.links_index = len(scene.isac.links) - 1
    return item


def add_sensing_link(scene, tx: str, rx: str, *, rho: float = 0.25, every: int = 1):
    """Append a sensing (radar) link tx -> rx (``rx == tx``: monostatic), exported as
    a ``[[sensing]]`` table; checked at export. Returns the item."""
    item = scene.isac.sensing_links.add()
    item.tx, item.rx, item.rho, item.every = tx, rx, float(rho), int(every)
    return item


def remove_link(scene, index: int) -> None:
    """Remove link number ``index``; raises IndexError when out of range."""
    links = scene.isac.links
    if not 0 <= index < len(links):
        raise IndexError(f"No link number {index} (scene has {len(links)})")
    links.remove(index)
    scene.isac.links_index = min(scene.isac.links_index, max(len(links) - 1, 0))
