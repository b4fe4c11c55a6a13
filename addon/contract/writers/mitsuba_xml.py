# SPDX-License-Identifier: Apache-2.0
"""The Mitsuba 3 scene file that plain Sionna RT loads (see docs/config.md)."""

from __future__ import annotations

from pathlib import Path
from xml.sax.saxutils import quoteattr

from .. import schema
from .numbers import fmt_float


def material_id(itu_type: str, thickness: float) -> str:
    """``mat-<type>-<thickness>``, one per distinct (ITU type, thickness in m)."""
    return f"{schema.MATERIAL_ID_PREFIX}{itu_type}-{fmt_float(thickness)}"


def custom_material_id(name: str) -> str:
    """``mat-<name>``: the bsdf id of custom radio material ``name``."""
    return f"{schema.MATERIAL_ID_PREFIX}{name}"


def scene_xml(shapes: list[tuple[str, str, float]], custom: dict[str, dict] | None = None) -> str:
    """Mitsuba XML text.

    Args:
        shapes: (file-safe name, material, thickness m) per object, in output order; the
            material is an ITU type or a key of ``custom`` (whose thickness is then its own).
            ITU materials are deduplicated by (type, thickness) and listed sorted.
        custom: custom radio materials, ``name -> {property: value}`` with every key of
            ``schema.CUSTOM_MATERIAL_PROPERTIES`` (permittivity, S/m, m); those used by a
            shape are written (sorted by name) as Sionna's ``radio-material``.

    Raises:
        ValueError: a custom material with a missing or out-of-range property.
    """
    custom = custom or {}
    used = sorted({t for _, t, _ in shapes if t in custom})
    for name in used:
        problems = schema.custom_material_problems(name, custom[name])
        if problems:
            raise ValueError(problems[0])

    def ref(mat, thickness):
        return custom_material_id(mat) if mat in custom else material_id(mat, thickness)

    mats = sorted({(t, fmt_float(d)): (t, d) for _, t, d in shapes if t not in custom}.items())
    lines = ['<scene version="2.1.0">', "", "<!-- Radio materials (ITU-R P.2040) -->", ""]
    for _, (itu_type, thickness) in mats:
        lines += [
            f'\t<bsdf type="{schema.ITU_MATERIAL_PLUGIN}" '
            f'id={quoteattr(material_id(itu_type, thickness))}>',
            f'\t\t<string name="type" value={quoteattr(itu_type)}/>',
            f'\t\t<float name="thickness" value="{fmt_float(thickness)}"/>',
            "\t</bsdf>",
        ]
    if used:
        lines += ["", "<!-- Custom radio materials (values at the carrier) -->", ""]
    for name in used:
        lines.append(f'\t<bsdf type="{schema.CUSTOM_MATERIAL_PLUGIN}" '
                     f'id={quoteattr(custom_material_id(name))}>')
        for key in schema.CUSTOM_MATERIAL_PROPERTIES:
            lines.append(f'\t\t<float name="{key}" value="{fmt_float(custom[name][key])}"/>')
        lines.append("\t</bsdf>")
    lines += ["", "<!-- Shapes: one per Blender object, world coordinates -->", ""]
    for name, mat, thickness in shapes:
        lines += [
            f'\t<shape type="ply" id={quoteattr("mesh-" + name)}>',
            f'\t\t<string name="filename" value={quoteattr("meshes/" + name + ".ply")}/>',
            '\t\t<boolean name="face_normals" value="true"/>',
            f'\t\t<ref id={quoteattr(ref(mat, thickness))} name="bsdf"/>',
            "\t</shape>",
        ]
    lines += ["</scene>", ""]
    return "\n".join(lines)


def write_scene_xml(path: Path, shapes: list[tuple[str, str, float]],
                    custom: dict[str, dict] | None = None) -> None:
    """Write :func:`scene_xml` to ``path`` (UTF-8, LF line ends)."""
    Path(path).write_bytes(scene_xml(shapes, custom).encode("utf-8"))
