"""Minimal PLY reader: enough to validate exported meshes and know their extent.

Reads the binary little-endian and ASCII PLY files the add-on writes (and
most others): vertex ``x y z`` plus any further scalar properties, and faces
as a list property. Every error names the file and what was wrong.

Mesh files are read only when they are regular files no larger than
:data:`MAX_MESH_BYTES` (a FIFO, a device such as ``/dev/zero`` or a huge file
is refused before a byte is read); :func:`confine` keeps a mesh path named by
a scene or a viewer inside its folder.
"""

from __future__ import annotations

import errno
import hashlib
from dataclasses import dataclass
from pathlib import Path, PurePosixPath, PureWindowsPath

import numpy as np

from ..errors import MeshError
from ..utils.files import read_regular_file

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


#: Largest mesh file read, bytes.
MAX_MESH_BYTES = 256 * 1024 * 1024


def confine(name: str | Path, folder: str | Path, *, roots=()) -> Path:
    """The file a mesh path names, kept inside ``folder``.

    Args:
        name: the path as written (scene.xml, an ``add`` edit): relative to
            ``folder``; absolute only when it lies inside one of ``roots``.
        folder: the folder relative paths start from (the scene folder).
        roots: further folders absolute paths may point into (asset folders).

    Returns:
        the resolved path (symbolic links followed), inside ``folder`` or a root.

    Raises:
        MeshError: naming ``name`` and why: empty, absolute outside ``roots``,
            a ``..`` component, or leaving the folder through a symbolic link.
    """
    text = str(name)
    if not text.strip() or "\0" in text:
        raise MeshError(f"mesh path {text!r}: empty or holds a NUL byte")
    posix, win = PurePosixPath(text), PureWindowsPath(text)
    if ".." in posix.parts or ".." in win.parts:
        raise MeshError(f"mesh path {text!r}: '..' is not allowed (meshes stay inside the "
                        "scene folder)")
    allowed = [Path(folder).resolve()] + [Path(r).resolve() for r in roots]
    if posix.is_absolute() or win.drive or win.root:
        if not roots:
            raise MeshError(f"mesh path {text!r}: absolute paths are not allowed (give it "
                            "relative to the scene folder)")
        target = _resolve(Path(text), text)
        allowed = allowed[1:]
    else:
        target = _resolve(allowed[0] / posix, text)
    if not any(target == r or target.is_relative_to(r) for r in allowed):
        raise MeshError(f"mesh path {text!r}: leaves the scene folder (through a symbolic "
                        "link)" if not (posix.is_absolute() or win.drive)
                        else f"mesh path {text!r}: not inside an asset folder")
    return target


def _resolve(path: Path, text: str) -> Path:
    """``path`` with its symbolic links followed; a loop is a :class:`MeshError`
    naming the path as written (Python raises RuntimeError or OSError for it)."""
    try:
        return path.resolve()
    except RuntimeError:  # Python < 3.13 on a loop
        raise MeshError(f"mesh path {text!r}: a symbolic-link loop") from None
    except OSError as exc:
        why = "a symbolic-link loop" if exc.errno == errno.ELOOP else exc.strerror
        raise MeshError(f"mesh path {text!r}: cannot be resolved ({why})") from None


def read_file(path: str | Path, max_bytes: int = MAX_MESH_BYTES) -> bytes:
    """The bytes of a regular file of at most ``max_bytes`` bytes
    (:func:`~isac_twin.utils.files.read_regular_file`: opened without blocking and
    checked on the open descriptor, so a FIFO, a device, a symbolic-link loop or a
    file swapped in meanwhile is refused before anything is read).

    Raises:
        MeshError: naming the file: missing/unreadable, not a regular file, too large.
    """
    return read_regular_file(path, max_bytes, error=MeshError, what="a PLY mesh file")


@dataclass(frozen=True)
class Mesh:
    """A triangle mesh.

    Attributes:
        vertices: ``[V, 3]`` float64, metres.
        faces: ``[F, 3]`` int64 vertex indices (triangles only: Mitsuba, which loads the
            same files, refuses other polygons).
    """

    vertices: np.ndarray
    faces: np.ndarray
    #: hex SHA-256 of the file's bytes ("" when not read from a file)
    sha256: str = ""

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounding box ``(min [3], max [3])`` in metres."""
        return self.vertices.min(axis=0), self.vertices.max(axis=0)


def read_ply(path: str | Path, max_bytes: int = MAX_MESH_BYTES) -> Mesh:
    """Read a PLY file (a regular file of at most ``max_bytes`` bytes, :func:`read_file`).

    Raises:
        MeshError: naming the file and the problem (missing, not a regular file,
            too large, bad header, truncated data, indices out of range, no triangles).
    """
    path = Path(path)
    return parse_ply(read_file(path, max_bytes), path)


def parse_ply(blob: bytes, path: str | Path = "<mesh>") -> Mesh:
    """Parse the bytes of a PLY file; ``path`` names it in errors.

    Raises:
        MeshError: naming ``path`` and the problem (see :func:`read_ply`).
    """
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
            if len(tok) != 3 or not tok[2].isdigit() or len(tok[2]) > 12:
                raise MeshError(f"{path}: header line {line.strip()[:60]!r}: expected "
                                "'element NAME COUNT' with COUNT a non-negative integer")
            elements.append((tok[1], int(tok[2]), []))
        elif tok[0] == "property" and elements:
            ok = (len(tok) == 5 and tok[2] in _PLY_TYPES and tok[3] in _PLY_TYPES
                  if tok[1] == "list" else len(tok) == 3 and tok[1] in _PLY_TYPES)
            if not ok:
                raise MeshError(f"{path}: header line {line.strip()[:60]!r}: expected "
                                "'property TYPE NAME' or 'property list TYPE TYPE NAME' "
                                f"(types: {', '.join(_PLY_TYPES)})")
            if tok[1] == "list":
                elements[-1][2].append(("list", tok[4], _PLY_TYPES[tok[2]],
                                        _PLY_TYPES[tok[3]]))
            else:
                elements[-1][2].append(("scalar", tok[2], _PLY_TYPES[tok[1]]))
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
            verts, faces, used = _read_binary(body, elements)
    except (ValueError, IndexError, TypeError, KeyError) as exc:
        raise MeshError(f"{path}: truncated or corrupt PLY data ({exc})") from exc
    if fmt != "ascii" and used != len(body):
        raise MeshError(f"{path}: {len(body) - used} bytes after the last element "
                        "(Mitsuba refuses such a file)")
    if isinstance(faces, list):
        raise MeshError(f"{path}: face {faces[0]} has {faces[1]} vertices: only triangles "
                        "are accepted (Mitsuba's PLY loader refuses other polygons)")
    if len(faces) == 0:
        raise MeshError(f"{path}: mesh has no faces")
    if faces.min() < 0 or faces.max() >= len(verts):
        raise MeshError(f"{path}: face index out of range (0..{len(verts) - 1})")
    if not np.isfinite(verts).all():
        raise MeshError(f"{path}: vertex coordinates are not finite")
    return Mesh(verts, faces, hashlib.sha256(blob).hexdigest())


def _triangles(polys: list[np.ndarray]):
    """``[F, 3]`` faces, or ``[index, n]`` of the first face that is not a triangle."""
    for i, p in enumerate(polys):
        if len(p) != 3:
            return [i, len(p)]
    return _fan(polys)


def _fan(polys: list[np.ndarray]) -> np.ndarray:
    tris = [np.stack([p[[0] * (len(p) - 2)], p[1:-1], p[2:]], axis=1) for p in polys
            if len(p) >= 3]
    return np.concatenate(tris).astype(np.int64) if tris else np.zeros((0, 3), np.int64)


def _read_binary(body: bytes, elements) -> tuple[np.ndarray, np.ndarray, int]:
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
            faces = _triangles(polys)
        else:
            raise ValueError(f"element '{name}' has list properties the reader does not handle")
    return verts, faces, off


def _read_ascii(body: bytes, elements) -> tuple[np.ndarray, np.ndarray]:
    """The vertices and faces of an ASCII body, read as Mitsuba's loader reads it: a
    stream of tokens, line breaks not counted, every element's every property in
    header order, and no token left after the last element."""
    tokens = body.decode("ascii").split()
    pos = 0
    verts = faces = None

    def take(n: int) -> list[str]:
        nonlocal pos
        if pos + n > len(tokens):
            raise ValueError(f"the data ends {pos + n - len(tokens)} token(s) short")
        out = tokens[pos:pos + n]
        pos += n
        return out

    for name, count, props in elements:
        if all(p[0] == "scalar" for p in props):
            rows = np.array(take(count * len(props)), dtype=np.float64).reshape(count,
                                                                               len(props))
            if name == "vertex":
                idx = [i for i, p in enumerate(props) if p[1] in ("x", "y", "z")]
                verts = rows[:, idx]
            continue
        polys = []
        first_list = next(i for i, p in enumerate(props) if p[0] == "list")
        for _ in range(count):
            for i, p in enumerate(props):
                if p[0] == "scalar":
                    take(1)
                    continue
                items = np.array(take(int(take(1)[0])), dtype=np.int64)
                if i == first_list:  # a face's vertex indices
                    polys.append(items)
        if name == "face":
            faces = _triangles(polys)
    if pos != len(tokens):
        raise ValueError(f"{len(tokens) - pos} token(s) after the last element (Mitsuba "
                         "refuses such a file)")
    return verts, faces
