"""Export a Blender scene to an ISAC Twin scene folder (format: docs/config.md).

``export_scene(context_or_scene, folder)`` is the one entry point; the
operator, ``bpy`` scripts and tests all call it. It first validates the
whole scene and refuses with an :class:`ExportError` listing every problem
(each message names the object, device or link at fault), then writes:

- ``scene.xml`` + ``meshes/<name>.ply`` (what Sionna RT loads),
- ``twin.toml`` (devices, links, numerology),
- ``<scene>.dae``, ``<scene>.stl``, ``<scene>.usdc`` (interchange formats).
"""

from __future__ import annotations

import logging
import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace

import bpy

from .. import materials
from ..contract import schema
from ..contract.writers.geometry import WorldMesh, world_mesh, write_ply
from ..contract.writers.mitsuba_xml import custom_material_id, material_id, write_scene_xml
from ..contract.writers.numbers import clean
from ..contract.writers.twin_toml import write_twin_toml
from ..devices import curve_waypoints
from .interchange import write_dae, write_stl, write_usd

log = logging.getLogger(__name__)

SCHEMA_VERSION = schema.TWIN_TOML_SCHEMA
#: the add-on's device_kind enum identifiers -> twin.toml kinds (properties.DEVICE_KINDS)
_KIND = {k.upper(): k for k in schema.DEVICE_KINDS}


class ExportError(ValueError):
    """The scene cannot be exported; ``problems`` holds one message per fault."""

    def __init__(self, problems: list[str]):
        self.problems = list(problems)
        super().__init__("Export refused:\n  " + "\n  ".join(self.problems))


@dataclass
class ExportReport:
    """What :func:`export_scene` wrote.

    Attributes:
        folder: the scene folder.
        files: written files relative to ``folder``, sorted (POSIX separators).
        objects: exported geometry object names (file-safe), sorted.
        materials: material ids in scene.xml, sorted.
        devices: device names, sorted.
        links: (tx, rx) pairs in order.
        warnings: non-fatal remarks.
    """

    folder: Path
    files: list[str] = field(default_factory=list)
    objects: list[str] = field(default_factory=list)
    materials: list[str] = field(default_factory=list)
    devices: list[str] = field(default_factory=list)
    links: list[tuple[str, str]] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)


def safe_name(name: str) -> str:
    """Blender object name made file-safe: characters outside [A-Za-z0-9_-] become '_'."""
    return re.sub(r"[^A-Za-z0-9_-]", "_", name)


def _finite_positive(x: float) -> bool:
    return isinstance(x, (int, float)) and math.isfinite(x) and x > 0


def _resolve(context_or_scene):
    """(scene, context-like with view_layer, evaluated depsgraph)."""
    ctx = bpy.context
    if isinstance(context_or_scene, bpy.types.Scene):
        scene = context_or_scene
        if ctx.scene == scene:
            return scene, ctx, ctx.evaluated_depsgraph_get()
        view_layer = scene.view_layers[0]
        depsgraph = scene.view_layers[0].depsgraph
        depsgraph.update()
        return scene, SimpleNamespace(view_layer=view_layer), depsgraph
    ctx = context_or_scene
    return ctx.scene, ctx, ctx.evaluated_depsgraph_get()


def geometry_objects(scene) -> list:
    """Mesh objects that go into scene.xml (not devices, not helpers), sorted by name."""
    return sorted((o for o in scene.objects if o.type == "MESH"
                   and o.isac.device_kind == "NONE" and o.isac.export_geometry),
                  key=lambda o: o.name)


def validate_settings(scene) -> list[str]:
    """Problems with the scene-level radio settings (frequency Hz, OFDM numerology)."""
    p = scene.isac
    out = []
    if not _finite_positive(p.frequency_hz):
        out.append(f"Scene '{scene.name}': frequency must be > 0 Hz, got {p.frequency_hz}")
    for key in ("num_subcarriers", "num_symbols"):
        if getattr(p, key) < 1:
            out.append(f"Scene '{scene.name}': {key} must be >= 1, got {getattr(p, key)}")
    if not _finite_positive(p.subcarrier_spacing_hz):
        out.append(f"Scene '{scene.name}': subcarrier spacing must be > 0 Hz, "
                   f"got {p.subcarrier_spacing_hz}")
    if p.cyclic_prefix_samples < 0:
        out.append(f"Scene '{scene.name}': cyclic_prefix_samples must be >= 0, "
                   f"got {p.cyclic_prefix_samples}")
    return out


def validate_device(obj) -> list[str]:
    """Problems with one device object's radio settings."""
    p = obj.isac
    out = []
    if p.array_rows < 1 or p.array_cols < 1:
        out.append(f"Device '{obj.name}': array rows and cols must be >= 1, "
                   f"got {p.array_rows} x {p.array_cols}")
    for key in ("vertical_spacing", "horizontal_spacing"):
        if not _finite_positive(getattr(p, key)):
            out.append(f"Device '{obj.name}': {key} must be > 0 wavelengths, "
                       f"got {getattr(p, key)}")
    if not math.isfinite(p.power_dbm):
        out.append(f"Device '{obj.name}': power_dbm must be finite, got {p.power_dbm}")
    for axis in ("subcarrier", "symbol"):
        start, stop = getattr(p, f"{axis}_start"), getattr(p, f"{axis}_stop")
        if (start or stop) and not 0 <= start < stop:
            out.append(f"Device '{obj.name}': {axis} range [{start}, {stop}) is empty "
                       "(use 0, 0 for the whole grid)")
    if p.device_kind == "ROBOT" and p.path_kind == "circle" and not p.path_radius > 0:
        out.append(f"Device '{obj.name}': path radius must be > 0 m, got {p.path_radius}")
    if p.device_kind == "ROBOT" and p.path_kind == "figure_eight" and not p.path_size > 0:
        out.append(f"Device '{obj.name}': figure-eight size must be > 0 m, got {p.path_size}")
    if p.device_kind == "ROBOT" and p.path_kind == "polyline":
        if p.path_curve is None:
            out.append(f"Device '{obj.name}': polyline path has no curve object "
                       "(pick one, or set the path to None)")
        else:
            pts, closed = curve_waypoints(p.path_curve)
            need = 3 if closed else 2
            if len(pts) < need:
                out.append(f"Device '{obj.name}': path curve '{p.path_curve.name}' has "
                           f"{len(pts)} points; a{' closed' if closed else 'n open'} "
                           f"polyline needs at least {need}")
            elif any(math.hypot(b[0] - a[0], b[1] - a[1]) < 1e-6
                     for a, b in zip(pts, pts[1:] + (pts[:1] if closed else []))):
                out.append(f"Device '{obj.name}': path curve '{p.path_curve.name}' has two "
                           "consecutive points at the same x, y")
    return out


def _collect(scene, depsgraph):
    """Validate everything; return (meshes, shapes, devices, links) or raise ExportError."""
    problems = validate_settings(scene)
    freq = float(scene.isac.frequency_hz)

    meshes: list[tuple[WorldMesh, str, float]] = []
    used: dict[str, str] = {}
    custom = materials.custom_table(scene)
    used_custom: set[str] = set()
    for obj in geometry_objects(scene):
        name = safe_name(obj.name)
        if name in used:
            problems.append(f"Object '{obj.name}': file-safe name '{name}' clashes with "
                            f"object '{used[name]}'; rename one of them")
            continue
        used[name] = obj.name
        mat, thickness = obj.isac.itu_material, float(obj.isac.thickness)
        if obj.isac.custom_material:
            mat = obj.isac.custom_material
            if mat not in custom:
                problems.append(f"Object '{obj.name}': custom radio material '{mat}' is not "
                                f"in the scene's list (have: {', '.join(custom) or 'none'})")
                continue
            thickness = custom[mat]["thickness"]
            used_custom.add(mat)
        elif mat == materials.NO_MATERIAL:
            problems.append(f"Object '{obj.name}': no ITU radio material assigned "
                            "(tag it, or untick 'Export geometry')")
            continue
        if mat not in custom and not materials.is_defined_at(mat, freq) and math.isfinite(freq):
            problems.append(materials.band_message(obj.name, mat, freq))
        if not _finite_positive(thickness):
            problems.append(f"Object '{obj.name}': material thickness must be > 0 m, "
                            f"got {thickness}")
        wm = world_mesh(obj, depsgraph, name)
        if wm.num_triangles == 0:
            problems.append(f"Object '{obj.name}': mesh is empty (no faces)")
            continue
        if wm.area <= 1e-12:
            problems.append(f"Object '{obj.name}': mesh has zero area "
                            "(zero dimension or collapsed faces)")
            continue
        meshes.append((wm, mat, thickness))
    for name in sorted(used_custom):
        problems += [f"Radio materials: {m}" for m in
                     schema.custom_material_problems(name, custom[name], materials.ITU_MATERIALS)]

    devices = []
    dev_names: dict[str, str] = {}
    for obj in sorted((o for o in scene.objects if o.isac.device_kind != "NONE"),
                      key=lambda o: o.name):
        key = safe_name(obj.name)
        if key in dev_names:
            problems.append(f"Device '{obj.name}': name duplicates device '{dev_names[key]}' "
                            "(names must stay unique when made file-safe)")
        elif key in used:
            problems.append(f"Device '{obj.name}': name duplicates geometry object "
                            f"'{used[key]}'")
        dev_names[key] = obj.name
        problems += validate_device(obj)
        devices.append(obj)

    by_name = {o.name: o for o in devices}
    links = []
    seen = set()
    for i, link in enumerate(scene.isac.links):
        tag = f"Link {i + 1} ({link.tx or '?'} -> {link.rx or '?'})"
        bad = False
        for end, name, roles in (("tx", link.tx, ("tx", "txrx")), ("rx", link.rx, ("rx", "txrx"))):
            if name not in by_name:
                problems.append(f"{tag}: {end} '{name}' is not a device in the scene")
                bad = True
            elif by_name[name].isac.role not in roles:
                problems.append(f"{tag}: device '{name}' has role "
                                f"'{by_name[name].isac.role}', cannot be the {end} end")
                bad = True
        if not bad and link.tx == link.rx:
            problems.append(f"{tag}: a device cannot link to itself")
        elif not bad and (link.tx, link.rx) in seen:
            problems.append(f"{tag}: duplicate link")
        seen.add((link.tx, link.rx))
        links.append((link.tx, link.rx))
    for i, sl in enumerate(getattr(scene.isac, "sensing_links", ())):
        tag = f"Sensing link {i + 1} ({sl.tx or '?'} -> {sl.rx or '?'})"
        for end, name in (("tx", sl.tx), ("rx", sl.rx)):
            if name not in by_name:
                problems.append(f"{tag}: {end} '{name}' is not a device in the scene")

    if problems:
        raise ExportError(problems)
    return meshes, devices, links


def _device_entry(obj, depsgraph) -> dict:
    p = obj.isac
    mw = obj.evaluated_get(depsgraph).matrix_world
    pos = [clean(float(x), 1e-9) for x in mw.translation]
    rot = [clean(float(a)) for a in mw.to_euler("XYZ")]
    entry: dict = {"name": obj.name, "kind": _KIND[p.device_kind], "role": p.role}
    if p.device_kind == "ROBOT":
        entry["model"] = p.robot_model
        entry["antenna_offset"] = [clean(float(x), 1e-9) for x in p.antenna_offset]
    entry.update({
        "position": pos,
        "orientation": rot,
        "power_dbm": float(p.power_dbm),
    })
    if p.subcarrier_start or p.subcarrier_stop:
        entry["subcarriers"] = [int(p.subcarrier_start), int(p.subcarrier_stop)]
    if p.symbol_start or p.symbol_stop:
        entry["symbols"] = [int(p.symbol_start), int(p.symbol_stop)]
    entry.update({
        "array": {
            "rows": int(p.array_rows),
            "cols": int(p.array_cols),
            "vertical_spacing": float(p.vertical_spacing),
            "horizontal_spacing": float(p.horizontal_spacing),
            "pattern": p.pattern,
            "polarization": p.polarization,
        },
    })
    if p.device_kind == "ROBOT" and p.path_kind != "NONE":
        entry["path"] = path_entry(p)
    return entry


def path_entry(p) -> dict:
    """A robot's ``[devices.path]`` table from its properties (kinds: docs/config.md)."""
    xy = lambda v: [clean(float(x), 1e-9) for x in v]  # noqa: E731
    if p.path_kind == "circle":
        path = {"kind": "circle", "centre": xy(p.path_centre), "radius": float(p.path_radius),
                "direction": p.path_direction}
    elif p.path_kind == "figure_eight":
        path = {"kind": "figure_eight", "centre": xy(p.path_centre), "size": float(p.path_size)}
    elif p.path_kind == "goal":
        path = {"kind": "goal", "goal": xy(p.path_goal)}
    else:
        pts, closed = curve_waypoints(p.path_curve)
        # curve points are float32 in Blender: round to a micrometre (2.6999998 -> 2.7)
        path = {"kind": "polyline", "waypoints": [[round(x, 6) + 0.0 for x in q] for q in pts],
                "closed": closed}
    if p.path_speed > 0:
        path["speed"] = float(p.path_speed)
    return path


def room_entry(scene) -> dict:
    """``{"room": {"shell": [...], "furniture": [...]}}`` from the exported objects'
    Room part tags (nothing when every object is on Auto: the engine decides)."""
    shell, furniture = [], []
    for obj in geometry_objects(scene):
        if obj.isac.room_part == "SHELL":
            shell.append(safe_name(obj.name))
        elif obj.isac.room_part == "FURNITURE":
            furniture.append(safe_name(obj.name))
    room = {k: v for k, v in (("shell", shell), ("furniture", furniture)) if v}
    return {"room": room} if room else {}


def twin_data(scene, devices, links, depsgraph) -> dict:
    """The twin.toml content as nested dicts, in the key order of docs/config.md."""
    p = scene.isac
    return {
        "schema": SCHEMA_VERSION,
        "scene": {"name": p.twin_name or scene.name, "file": "scene.xml",
                  "frequency_hz": float(p.frequency_hz)},
        "ofdm": {"num_subcarriers": int(p.num_subcarriers),
                 "subcarrier_spacing_hz": float(p.subcarrier_spacing_hz),
                 "num_symbols": int(p.num_symbols),
                 "cyclic_prefix_samples": int(p.cyclic_prefix_samples)},
        "devices": [_device_entry(o, depsgraph) for o in devices],
        "links": [{"tx": tx, "rx": rx} for tx, rx in links],
        **_sensing_entries(p),
        **room_entry(scene),
    }


def _sensing_entries(p) -> dict:
    """``{"sensing": [...]}`` for the scene's sensing links (nothing when none)."""
    rows = [{"tx": s.tx, "rx": s.rx, "rho": float(s.rho), "every": int(s.every)}
            for s in getattr(p, "sensing_links", ())]
    return {"sensing": rows} if rows else {}


def export_scene(context_or_scene, folder, *, interchange: bool = True) -> ExportReport:
    """Validate and export a scene to a scene folder.

    Args:
        context_or_scene: a ``bpy.types.Context`` or ``bpy.types.Scene``.
        folder: target directory (created); stale ``meshes/*.ply`` are removed.
        interchange: also write ``<scene>.dae``, ``.stl`` and ``.usdc``.

    Returns:
        An :class:`ExportReport`.

    Raises:
        ExportError: the scene is invalid; nothing has been written.
    """
    folder_text = str(folder)
    if folder_text.startswith("//"):
        if not bpy.data.filepath:
            raise ExportError([f"Scene folder '{folder_text}' is relative to the .blend file, "
                               "which has not been saved: save it or choose an absolute folder"])
        folder_text = bpy.path.abspath(folder_text)
    scene, ctx, depsgraph = _resolve(context_or_scene)
    meshes, devices, links = _collect(scene, depsgraph)

    folder = Path(folder_text).resolve()
    mesh_dir = folder / "meshes"
    mesh_dir.mkdir(parents=True, exist_ok=True)
    report = ExportReport(folder=folder)
    keep = set()
    for wm, _, _ in meshes:
        write_ply(mesh_dir / f"{wm.name}.ply", wm)
        keep.add(f"{wm.name}.ply")
        report.files.append(f"meshes/{wm.name}.ply")
    for stale in mesh_dir.glob("*.ply"):
        if stale.name not in keep:
            stale.unlink()
    shapes = [(wm.name, t, d) for wm, t, d in meshes]
    write_scene_xml(folder / "scene.xml", shapes, materials.custom_table(scene))
    write_twin_toml(folder / "twin.toml", twin_data(scene, devices, links, depsgraph))
    report.files += ["scene.xml", "twin.toml"]

    if interchange:
        base = safe_name(scene.isac.twin_name or scene.name)
        write_dae(folder / f"{base}.dae", meshes, base)
        write_stl(folder / f"{base}.stl", [m for m, _, _ in meshes], base)
        by_safe = {safe_name(o.name): o for o in geometry_objects(scene)}
        write_usd(folder / f"{base}.usdc", [by_safe[m.name] for m, _, _ in meshes], ctx)
        report.files += [f"{base}.dae", f"{base}.stl", f"{base}.usdc"]

    report.files.sort()
    report.objects = sorted(s[0] for s in shapes)
    custom = materials.custom_table(scene)
    report.materials = sorted({custom_material_id(t) if t in custom else material_id(t, d)
                               for _, t, d in shapes})
    report.devices = sorted(o.name for o in devices)
    report.links = links
    log.info("exported %d objects, %d devices to %s", len(meshes), len(devices), folder)
    return report
