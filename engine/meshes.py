"""Minimal PLY reader: enough to validate exported meshes and know their extent.

Reads the binary little-endian and ASCII PLY files the add-on writes (and
most others): vertex ``x y z`` plus any further scalar properties, and faces
as a list property. Every error names the file and what was wrong.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


class MeshError(ValueError):
    """A mesh file is missing, truncated or not a PLY the engine can read."""


@dataclass(frozen=True)
class Mesh:
    """A triangle mesh.

    Attributes:
        vertices: ``[V, 3]`` float64, metres.
        faces: ``[F, 3]`` int64 vertex indices (polygons are fan-triangulated).
    """

    vertices: np.ndarray
    faces: np.ndarray

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounding box ``(min [3], max [3])`` in metres."""
        return self.vertices.min(axis=0), self.vertices.max(axis=0)


def read_ply(path: str | Path) -> Mesh:
    """Read a PLY file.

    Raises:
        MeshError: naming the file and the problem (missing, bad header,
            truncated data, indices out of range, no triangles).
    """
    path = Path(path)
    try:
        blob = path.read_bytes()
    except OSError as exc:
        raise MeshError(f"{path}: cannot read mesh file ({exc.strerror})") from exc
    end = blob.find(b"end_header")
    if not blob.startswith(b"ply") or end < 0:
        raise MeshError(f"{path}: not a PLY file (expected 'ply' ... 'end_header')")
    nl = blob.find(b"\n", end)
    header = blob[:end].decode("ascii", errors="replace").splitlines()
    body = blob[nl + 1:] if nl >= 0 else b""

    fmt = None
    elements: list[tuple[str, int, list[tuple]]] = []
    for line in header[1:]:
        tok = line.split()
        if not tok or tok[0] in ("comment", "obj_info"):
            continue
        if tok[0] == "format":
            fmt = tok[1]
        elif tok[0] == "element":
            elements.append((tok[1], int(tok[2]), []))
        elif tok[0] == "property" and elements:
            if tok[1] == "list":
                elements[-1][2].append(("list", tok[4], _PLY_TYPES.get(tok[2]),
                                        _PLY_TYPES.get(tok[3])))
            else:
                elements[-1][2].append(("scalar", tok[2], _PLY_TYPES.get(tok[1])))
    if fmt not in ("binary_little_endian", "ascii"):
        raise MeshError(f"{path}: unsupported PLY format {fmt!r} "
                        "(expected binary_little_endian or ascii)")
    names = [e[0] for e in elements]
    if "vertex" not in names or "face" not in names:
        raise MeshError(f"{path}: PLY needs 'vertex' and 'face' elements, has {names}")
    try:
        if fmt == "ascii":
            verts, faces = _read_ascii(body, elements)
        else:
            verts, faces = _read_binary(body, elements)
    except (ValueError, IndexError, TypeError) as exc:
        raise MeshError(f"{path}: truncated or corrupt PLY data ({exc})") from exc
    if len(faces) == 0:
        raise MeshError(f"{path}: mesh has no faces")
    if faces.min() < 0 or faces.max() >= len(verts):
        raise MeshError(f"{path}: face index out of range (0..{len(verts) - 1})")
    if not np.isfinite(verts).all():
        raise MeshError(f"{path}: vertex coordinates are not finite")
    return Mesh(verts, faces)


def _fan(polys: list[np.ndarray]) -> np.ndarray:
    tris = [np.stack([p[[0] * (len(p) - 2)], p[1:-1], p[2:]], axis=1) for p in polys
            if len(p) >= 3]
    return np.concatenate(tris).astype(np.int64) if tris else np.zeros((0, 3), np.int64)


def _read_binary(body: bytes, elements) -> tuple[np.ndarray, np.ndarray]:
    off = 0
    verts = faces = None
    for name, count, props in elements:
        if all(p[0] == "scalar" for p in props):
            dt = np.dtype([(p[1], "<" + p[2]) for p in props])
            need = dt.itemsize * count
            if off + need > len(body):
                raise ValueError(f"element '{name}' needs {need} bytes, "
                                 f"{len(body) - off} left")
            arr = np.frombuffer(body, dtype=dt, count=count, offset=off)
            off += need
            if name == "vertex":
                verts = np.stack([arr["x"], arr["y"], arr["z"]], axis=1).astype(np.float64)
        elif name == "face" and len(props) == 1:
            _, _, ctype, itype = props[0]
            cdt, idt = np.dtype("<" + ctype), np.dtype("<" + itype)
            # Fast path: every face a triangle (what the exporter writes).
            stride = cdt.itemsize + 3 * idt.itemsize
            if off + stride * count <= len(body) and count > 0:
                rec = np.dtype([("n", cdt), ("i", idt, 3)])
                arr = np.frombuffer(body, dtype=rec, count=count, offset=off)
                if (arr["n"] == 3).all():
                    faces = arr["i"].astype(np.int64)
                    off += stride * count
                    continue
            polys = []
            for _ in range(count):
                n = int(np.frombuffer(body, cdt, 1, off)[0])
                off += cdt.itemsize
                if off + n * idt.itemsize > len(body):
                    raise ValueError("face list runs past the end of the file")
                polys.append(np.frombuffer(body, idt, n, off).astype(np.int64))
                off += n * idt.itemsize
            faces = _fan(polys)
        else:
            raise ValueError(f"element '{name}' has list properties the reader does not handle")
    return verts, faces


def _read_ascii(body: bytes, elements) -> tuple[np.ndarray, np.ndarray]:
    lines = body.decode("ascii").split("\n")
    pos = 0
    verts = faces = None
    for name, count, props in elements:
        rows = lines[pos:pos + count]
        if len(rows) < count:
            raise ValueError(f"element '{name}' has fewer than {count} rows")
        pos += count
        if name == "vertex":
            idx = [i for i, p in enumerate(props) if p[1] in ("x", "y", "z")]
            verts = np.array([[float(r.split()[i]) for i in idx] for r in rows])
        elif name == "face":
            faces = _fan([np.array(r.split()[1:1 + int(r.split()[0])], dtype=np.int64)
                          for r in rows])
    return verts, faces
