"""Write small scene folders from code: analytic test rooms without Blender.

Used by the engine's tests and benchmarks (a closed box room, a single
reflector) so that the engine can be checked without ``bpy``. The files are
written by the add-on's own stdlib-only exporter functions
(``addon/exporter/{geometry,mitsuba_xml,twin_toml}.py``: one writer of the
scene-folder format, ``docs/config.md``), loaded by file path without ``bpy``.
"""

from __future__ import annotations

import importlib
import importlib.machinery
import importlib.util
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from engine.addon_shared import schema

#: the add-on's exporter package, loaded under this name without its bpy-bound __init__
EXPORTER_MODULE = "isac_twin_addon_exporter"
EXPORTER_DIR = Path(__file__).resolve().parents[1] / "addon" / "exporter"


def exporter(module: str):
    """The add-on exporter's stdlib-only submodule ``module`` (``"geometry"``,
    ``"mitsuba_xml"``, ``"twin_toml"``, ``"numbers"``).

    Raises:
        ImportError: the add-on sources are not beside the engine (e.g. an
            installed wheel), naming the folder looked in.
    """
    pkg = sys.modules.get(EXPORTER_MODULE)
    if pkg is None:
        if not (EXPORTER_DIR / f"{module}.py").is_file():
            raise ImportError(f"{EXPORTER_DIR}: the add-on's exporter is needed to write "
                              f"scene folders ({module}.py not found)")
        spec = importlib.machinery.ModuleSpec(EXPORTER_MODULE, None, is_package=True)
        pkg = importlib.util.module_from_spec(spec)
        pkg.__path__ = [str(EXPORTER_DIR)]
        sys.modules[EXPORTER_MODULE] = pkg
    return importlib.import_module(f"{EXPORTER_MODULE}.{module}")


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
    geo = exporter("geometry")
    v = np.asarray(vertices, float)
    mesh = geo.WorldMesh(Path(path).stem, [float(x) for x in v.reshape(-1)],
                         [int(i) for i in np.asarray(faces).reshape(-1)], 0.0)
    geo.write_ply(Path(path), mesh)


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
                       num_symbols: int = 14, tracer: dict | None = None) -> Path:
    """Write ``scene.xml``, ``meshes/*.ply`` and ``twin.toml``; return the folder."""
    folder = Path(folder)
    (folder / "meshes").mkdir(parents=True, exist_ok=True)
    for o in objects:
        write_ply(folder / "meshes" / f"{o.name}.ply", o.vertices, o.faces)
    exporter("mitsuba_xml").write_scene_xml(
        folder / "scene.xml", [(o.name, o.material, float(o.thickness)) for o in objects])
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
    exporter("twin_toml").write_twin_toml(folder / "twin.toml", data)
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
