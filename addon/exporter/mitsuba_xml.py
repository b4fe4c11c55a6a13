"""The Mitsuba 3 scene file that plain Sionna RT loads (see docs/config.md)."""

from __future__ import annotations

from pathlib import Path
from xml.sax.saxutils import quoteattr

from .numbers import fmt_float


def material_id(itu_type: str, thickness: float) -> str:
    """``mat-<type>-<thickness>``, one per distinct (ITU type, thickness in m)."""
    return f"mat-{itu_type}-{fmt_float(thickness)}"


def scene_xml(shapes: list[tuple[str, str, float]]) -> str:
    """Mitsuba XML text.

    Args:
        shapes: (file-safe name, ITU type, thickness m) per object, in output order.
            Materials are deduplicated by (type, thickness) and listed sorted.
    """
    mats = sorted({(t, fmt_float(d)): (t, d) for _, t, d in shapes}.items())
    lines = ['<scene version="2.1.0">', "", "<!-- Radio materials (ITU-R P.2040) -->", ""]
    for _, (itu_type, thickness) in mats:
        lines += [
            f'\t<bsdf type="itu-radio-material" id={quoteattr(material_id(itu_type, thickness))}>',
            f'\t\t<string name="type" value={quoteattr(itu_type)}/>',
            f'\t\t<float name="thickness" value="{fmt_float(thickness)}"/>',
            "\t</bsdf>",
        ]
    lines += ["", "<!-- Shapes: one per Blender object, world coordinates -->", ""]
    for name, itu_type, thickness in shapes:
        lines += [
            f'\t<shape type="ply" id={quoteattr("mesh-" + name)}>',
            f'\t\t<string name="filename" value={quoteattr("meshes/" + name + ".ply")}/>',
            '\t\t<boolean name="face_normals" value="true"/>',
            f'\t\t<ref id={quoteattr(material_id(itu_type, thickness))} name="bsdf"/>',
            "\t</shape>",
        ]
    lines += ["</scene>", ""]
    return "\n".join(lines)


def write_scene_xml(path: Path, shapes: list[tuple[str, str, float]]) -> None:
    """Write :func:`scene_xml` to ``path`` (UTF-8, LF line ends)."""
    Path(path).write_bytes(scene_xml(shapes).encode("utf-8"))
