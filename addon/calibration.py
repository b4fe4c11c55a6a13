"""Apply a calibration (``isac-twin calibrate ... --out DIR``) to the open scene.

``DIR/calibration.json`` holds each fitted object offset (``<object>.x``/``.y``
in m, ``<object>.yaw`` in rad: a turn about the centre of the object's
world-space bounding box, then a shift) and ``DIR/scene/scene.xml`` the
calibrated radio materials (custom ``radio-material`` bsdfs, see
docs/config.md). :func:`apply_calibration` moves the objects and adds the
materials to the scene's list, assigning them to the objects that use them,
so the user sees what moved and re-exporting gives the calibrated folder.
Engine object names are the Blender names made file-safe (``exporter.safe_name``).
"""

from __future__ import annotations

import json
import math
import xml.etree.ElementTree as ET
from pathlib import Path

import bpy
from mathutils import Matrix, Vector

from . import materials
from .contract import schema
from .exporter import geometry_objects, safe_name


class CalibrationFileError(ValueError):
    """The calibration folder is missing a file or holds something unexpected."""


def read_calibration(folder) -> tuple[dict[str, dict[str, float]], dict[str, dict],
                                      dict[str, str]]:
    """Read ``folder`` (an ``isac-twin calibrate --out`` folder).

    Returns:
        ``(offsets, custom, material_of)``: ``object -> {"x": m, "y": m, "yaw": rad}``
        (fitted ones only), custom materials ``name -> {property: value}`` of its
        ``scene/scene.xml``, and ``object -> custom material`` for the shapes using one.

    Raises:
        CalibrationFileError: naming the file and what was expected.
    """
    folder = Path(bpy.path.abspath(str(folder)))
    rep_path, xml_path = folder / "calibration.json", folder / "scene" / "scene.xml"
    for p in (rep_path, xml_path):
        if not p.is_file():
            raise CalibrationFileError(f"{p}: not found (expected the output folder of "
                                       "`isac-twin calibrate --out DIR`)")
    try:
        rep = json.loads(rep_path.read_text(encoding="utf-8"))
        params = rep["parameters"]
    except (ValueError, KeyError, TypeError) as exc:
        raise CalibrationFileError(f"{rep_path}: not a calibration report "
                                   f"({type(exc).__name__}: {exc})") from None
    offsets: dict[str, dict[str, float]] = {}
    for i, p in enumerate(params):
        try:
            target, kind = str(p["name"]).rsplit(".", 1)
            value = float(p["final"])
        except (KeyError, TypeError, ValueError):
            raise CalibrationFileError(f"{rep_path}: parameters[{i}]: expected 'name' "
                                       "('<target>.<kind>') and a numeric 'final'") from None
        if kind in ("x", "y", "yaw"):
            if not math.isfinite(value):
                raise CalibrationFileError(f"{rep_path}: parameters[{i}] ({p['name']}): "
                                           f"final {value} is not finite")
            offsets.setdefault(target, {})[kind] = value
    try:
        root = ET.parse(xml_path).getroot()
    except ET.ParseError as exc:
        raise CalibrationFileError(f"{xml_path}: not valid XML: {exc}") from None
    custom: dict[str, dict] = {}
    prefix = schema.MATERIAL_ID_PREFIX
    for b in root.iter("bsdf"):
        if b.get("type") != schema.CUSTOM_MATERIAL_PLUGIN:
            continue
        name = b.get("id", "")[len(prefix):]
        try:
            vals = {c.get("name"): float(c.get("value")) for c in b if c.tag == "float"}
        except (TypeError, ValueError):
            raise CalibrationFileError(f"{xml_path}: bsdf {b.get('id')!r}: a value is not "
                                       "a number") from None
        problems = schema.custom_material_problems(name, vals, materials.ITU_MATERIALS)
        if problems:
            raise CalibrationFileError(f"{xml_path}: bsdf {b.get('id')!r}: {problems[0]}")
        custom[name] = vals
    material_of = {}
    for s in root.iter("shape"):
        sid = s.get("id", "")
        ref = next((r.get("id", "") for r in s.iter("ref")), "")
        if ref.startswith(prefix) and ref[len(prefix):] in custom:
            material_of[sid[5:] if sid.startswith("mesh-") else sid] = ref[len(prefix):]
    return offsets, custom, material_of


def offset_matrix(centre, dx: float, dy: float, yaw: float) -> Matrix:
    """World transform of a calibration offset: turn by ``yaw`` (rad) about the vertical
    through ``centre`` (m), then shift by ``(dx, dy)`` (m); 4 x 4."""
    c = Vector((float(centre[0]), float(centre[1]), 0.0))
    return (Matrix.Translation(c + Vector((dx, dy, 0.0))) @ Matrix.Rotation(yaw, 4, "Z")
            @ Matrix.Translation(-c))


def apply_calibration(scene, folder) -> list[str]:
    """Move the objects of ``scene`` by the fitted offsets of calibration ``folder`` and
    give them its calibrated materials (added to / updated in the scene's custom radio
    materials). Nothing is changed when the folder names an object the scene lacks.

    Returns:
        One line per change (for the operator's report).

    Raises:
        CalibrationFileError: bad folder (see :func:`read_calibration`), or an object of
            the calibration that is not in the scene.
    """
    offsets, custom, material_of = read_calibration(folder)
    by_safe = {safe_name(o.name): o for o in geometry_objects(scene)}
    missing = sorted(n for n in list(offsets) + list(material_of) if n not in by_safe)
    if missing:
        raise CalibrationFileError(f"{folder}: the calibration names objects this scene does "
                                   f"not have: {', '.join(missing)}")
    lines = []
    depsgraph = bpy.context.evaluated_depsgraph_get()
    for name, off in sorted(offsets.items()):
        obj = by_safe[name]
        ev = obj.evaluated_get(depsgraph)
        mesh = ev.to_mesh()
        try:  # the exported mesh is the evaluated one in world coordinates
            pts = [ev.matrix_world @ v.co for v in mesh.vertices]
        finally:
            ev.to_mesh_clear()
        if not pts:
            continue
        centre = [0.5 * (min(p[i] for p in pts) + max(p[i] for p in pts)) for i in (0, 1)]
        dx, dy, yaw = off.get("x", 0.0), off.get("y", 0.0), off.get("yaw", 0.0)
        obj.matrix_world = offset_matrix(centre, dx, dy, yaw) @ obj.matrix_world
        lines.append(f"{obj.name}: moved {dx * 100:+.2f} cm x, {dy * 100:+.2f} cm y, "
                     f"turned {math.degrees(yaw):+.3f} deg")
    for name, vals in sorted(custom.items()):
        materials.set_custom_material(scene, name, vals)
        lines.append(f"radio material {name}: permittivity {vals['relative_permittivity']:.4g}, "
                     f"conductivity {vals['conductivity']:.4g} S/m, {vals['thickness']:g} m")
    for name, mat in sorted(material_of.items()):
        materials.assign_custom_material([by_safe[name]], scene, mat)
    if material_of:
        lines.append(f"{len(material_of)} object(s) now use calibrated materials")
    return lines
