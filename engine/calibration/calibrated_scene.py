"""The calibrated scene folder: a copy of the twin's folder with the fit applied.

:func:`write_calibrated_scene` copies the scene folder with the fitted object offsets
applied to the meshes and the fitted materials written as custom radio materials
(``<bsdf type="radio-material">``, docs/config.md) that the objects of the fitted
material now use (it loads like any other folder and gives the calibrated channel).

A fitted ITU material ``T`` becomes the custom material ``T-calibrated``
(``T-<thickness>-calibrated`` when objects use it at several thicknesses),
holding the fitted permittivity and conductivity (the ITU value at the carrier
for one not fitted) and the objects' thickness; a fitted custom material keeps
its name and gets the fitted values.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from .problem import MATERIAL_KINDS


def material_users(scene, target: str) -> list:
    """The objects (:class:`~isac_twin.scene.twin_scene.ObjectInfo`) whose material is
    ``target``: an ITU type or custom name (``"wood"``), or Sionna's name of one ITU material at one
    thickness (``"wood-0.03"``, the bsdf id without ``mat-``)."""
    return [o for o in scene.objects.values()
            if o.material == target or (o.material not in scene.custom_materials
                                        and f"{o.material}-{o.thickness:g}" == target)]


def calibrated_materials(scene, result) -> tuple[dict[str, dict[str, float]], dict[str, str]]:
    """The custom materials a calibration writes and the objects that use them.

    Args:
        scene: the scene that was calibrated (its objects and materials as loaded).
        result: :class:`~isac_twin.calibration.problem.CalibrationResult`.

    Returns:
        ``(materials, assign)``: ``name -> {"relative_permittivity", "conductivity" (S/m),
        "thickness" (m)}`` and ``object -> material name``, for every object whose
        material (ITU type or custom name) had a parameter fitted.
    """
    from sionna.rt.radio_materials.itu import itu_material

    fitted: dict[str, dict[str, float]] = {}
    for name, val in zip(result.names, result.final):
        target, kind = name.rsplit(".", 1)
        if kind in MATERIAL_KINDS:
            key = "relative_permittivity" if kind == "permittivity" else "conductivity"
            fitted.setdefault(target, {})[key] = float(val)
    f = scene.config.scene.frequency_hz
    materials: dict[str, dict[str, float]] = {}
    assign: dict[str, str] = {}
    for target, vals in fitted.items():
        users = material_users(scene, target)
        if target in scene.custom_materials:
            materials[target] = {**scene.custom_materials[target], **vals}
            assign.update({o.name: target for o in users})
            continue
        itu = users[0].material
        eps, sigma = (float(np.asarray(v).reshape(-1)[0]) for v in itu_material(itu, f))
        thicknesses = sorted({o.thickness for o in users})
        for d in thicknesses:
            mname = (f"{target}-calibrated" if len(thicknesses) == 1 and target != itu
                     else f"{itu}-calibrated" if len(thicknesses) == 1 else
                     f"{itu}-{d:g}-calibrated")
            materials[mname] = {"relative_permittivity": vals.get("relative_permittivity", eps),
                                "conductivity": vals.get("conductivity", sigma),
                                "thickness": float(d)}
            assign.update({o.name: mname for o in users if o.thickness == d})
    return materials, assign


def _write_materials(xml_path: Path, scene, materials: dict, assign: dict) -> None:
    """Rewrite ``xml_path`` (a copy of ``scene``'s scene.xml): the objects in ``assign``
    refer to their custom material, written as Sionna's ``radio-material`` bsdf; ITU
    bsdfs no object refers to any more are dropped."""
    import xml.etree.ElementTree as ET

    from ..contract import schema
    from ..contract.writers.numbers import fmt_float as fmt

    prefix = schema.MATERIAL_ID_PREFIX
    tree = ET.parse(xml_path)
    root = tree.getroot()
    shapes = list(root.iter("shape"))
    for s in shapes:
        sid = s.get("id", "")
        name = sid[5:] if sid.startswith("mesh-") else sid
        if name in assign:
            next(s.iter("ref")).set("id", prefix + assign[name])
    used = {r.get("id") for s in shapes for r in s.iter("ref")}
    parent = {c: p for p in root.iter() for c in p}
    for b in list(root.iter("bsdf")):
        if b.get("id") not in used or (b.get("type") == schema.CUSTOM_MATERIAL_PLUGIN
                                       and b.get("id")[len(prefix):] in materials):
            parent[b].remove(b)
    at = list(root).index(shapes[0]) if shapes else len(root)
    for mname in sorted(materials, reverse=True):
        b = ET.Element("bsdf", {"type": schema.CUSTOM_MATERIAL_PLUGIN, "id": prefix + mname})
        for key in schema.CUSTOM_MATERIAL_PROPERTIES:
            ET.SubElement(b, "float", {"name": key, "value": fmt(materials[mname][key])})
        root.insert(at, b)
    ET.indent(tree, "\t")
    tree.write(xml_path, encoding="utf-8")


def write_calibrated_scene(scene, result, out_dir: Path) -> Path:
    """Copy ``scene``'s folder to ``out_dir`` with the fitted x/y/yaw offsets applied to
    the objects' meshes (rotation about the mesh's bounding-box centre) and the fitted
    materials written (:func:`calibrated_materials`); return it."""
    from ..scene.meshes import read_ply
    from ..scene.synthetic import write_ply

    src = Path(scene.config.scene.file).parent
    if out_dir.exists():
        shutil.rmtree(out_dir)
    shutil.copytree(src, out_dir)
    materials, assign = calibrated_materials(scene, result)
    if materials:
        _write_materials(out_dir / Path(scene.config.scene.file).relative_to(src), scene,
                         materials, assign)
    offsets: dict[str, dict[str, float]] = {}
    for name, val in zip(result.names, result.final):
        target, kind = name.rsplit(".", 1)
        if kind in ("x", "y", "yaw"):
            offsets.setdefault(target, {})[kind] = float(val)
    for name, off in offsets.items():
        info = scene.objects[name]
        dest = out_dir / Path(info.mesh_file).relative_to(src)
        mesh = read_ply(info.mesh_file)
        v = mesh.vertices.copy()
        c = 0.5 * (v.min(axis=0) + v.max(axis=0))
        cs, sn = np.cos(off.get("yaw", 0.0)), np.sin(off.get("yaw", 0.0))
        x, y = v[:, 0] - c[0], v[:, 1] - c[1]
        v[:, 0] = c[0] + cs * x - sn * y + off.get("x", 0.0)
        v[:, 1] = c[1] + sn * x + cs * y + off.get("y", 0.0)
        write_ply(dest, v, mesh.faces)
    return out_dir
