# SPDX-License-Identifier: Apache-2.0
"""Triangle meshes in world coordinates from the evaluated depsgraph, and a binary PLY writer."""

from __future__ import annotations

import array
import math
import struct
from dataclasses import dataclass
from pathlib import Path


@dataclass
class WorldMesh:
    """A triangulated mesh in world coordinates.

    Attributes:
        name: file-safe object name.
        vertices: flat [x0, y0, z0, x1, ...] in m, world frame.
        triangles: flat [i0, j0, k0, i1, ...] vertex indices.
        area: total triangle area, m^2.
    """

    name: str
    vertices: list[float]
    triangles: list[int]
    area: float

    @property
    def num_vertices(self) -> int:
        return len(self.vertices) // 3

    @property
    def num_triangles(self) -> int:
        return len(self.triangles) // 3

    def bbox(self) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
        """(min, max) corners of the world bounding box, m."""
        v = self.vertices
        lo = tuple(min(v[i::3]) for i in range(3))
        hi = tuple(max(v[i::3]) for i in range(3))
        return lo, hi


def world_mesh(obj, depsgraph, name: str) -> WorldMesh:
    """Evaluate ``obj`` (modifiers applied), triangulate it and transform it to world coordinates.

    Args:
        obj: a mesh ``bpy.types.Object``.
        depsgraph: an evaluated ``bpy.types.Depsgraph``.
        name: the file-safe name to store.
    """
    eval_obj = obj.evaluated_get(depsgraph)
    mesh = eval_obj.to_mesh()
    try:
        mesh.calc_loop_triangles()
        n = len(mesh.vertices)
        co = array.array("f", bytes(4 * 3 * n))
        mesh.vertices.foreach_get("co", co)
        m = len(mesh.loop_triangles)
        tris = array.array("i", bytes(4 * 3 * m))
        mesh.loop_triangles.foreach_get("vertices", tris)
        mw = [[float(eval_obj.matrix_world[r][c]) for c in range(4)] for r in range(4)]
    finally:
        eval_obj.to_mesh_clear()
    verts: list[float] = []
    for i in range(n):
        x, y, z = co[3 * i], co[3 * i + 1], co[3 * i + 2]
        for r in range(3):
            verts.append(mw[r][0] * x + mw[r][1] * y + mw[r][2] * z + mw[r][3])
    tri_list = tris.tolist()
    area = 0.0
    for t in range(m):
        a, b, c = (3 * tri_list[3 * t + k] for k in range(3))
        u = [verts[b + k] - verts[a + k] for k in range(3)]
        w = [verts[c + k] - verts[a + k] for k in range(3)]
        cx = u[1] * w[2] - u[2] * w[1]
        cy = u[2] * w[0] - u[0] * w[2]
        cz = u[0] * w[1] - u[1] * w[0]
        area += 0.5 * math.sqrt(cx * cx + cy * cy + cz * cz)
    return WorldMesh(name, verts, tri_list, area)


def write_ply(path: Path, mesh: WorldMesh) -> None:
    """Write :func:`ply_bytes` of ``mesh`` to ``path``."""
    path.write_bytes(ply_bytes(mesh))


def ply_bytes(mesh: WorldMesh) -> bytes:
    """Binary little-endian PLY: float32 x, y, z per vertex; uchar-count int triangle lists."""
    header = (
        "ply\n"
        "format binary_little_endian 1.0\n"
        f"comment ISAC Twin object {mesh.name}\n"
        f"element vertex {mesh.num_vertices}\n"
        "property float x\nproperty float y\nproperty float z\n"
        f"element face {mesh.num_triangles}\n"
        "property list uchar int vertex_indices\n"
        "end_header\n"
    ).encode("ascii")
    body = struct.pack(f"<{len(mesh.vertices)}f", *mesh.vertices)
    faces = struct.pack("<" + "B3i" * mesh.num_triangles,
                        *[x for t in range(mesh.num_triangles)
                          for x in (3, *mesh.triangles[3 * t:3 * t + 3])])
    return header + body + faces


def read_ply(path: Path) -> WorldMesh:
    """Read back a PLY written by :func:`write_ply` (for tests and round trips)."""
    data = Path(path).read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii").splitlines()
    nv = int(next(h for h in header if h.startswith("element vertex")).split()[-1])
    nf = int(next(h for h in header if h.startswith("element face")).split()[-1])
    verts = list(struct.unpack_from(f"<{3 * nv}f", data, end))
    raw = struct.unpack_from("<" + "B3i" * nf, data, end + 12 * nv)
    tris = [x for t in range(nf) for x in raw[4 * t + 1:4 * t + 4]]
    return WorldMesh(Path(path).stem, verts, tris, 0.0)
