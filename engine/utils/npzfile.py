"""Versioned NPZ files: named arrays plus a JSON ``meta`` entry with format and version.

The engine's databases (path grids, fingerprint databases) share this
container so that every reader refuses a foreign or newer file with the
same clear messages.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass(frozen=True, eq=False)
class NpzRecord:
    """A database held as metadata plus named arrays; arrays read as attributes.

    Attributes:
        meta: the metadata dictionary (``format``, ``version``, ...).
        arrays: name -> numpy array.
        path: the file it was loaded from or saved to (None when fresh).
    """

    meta: dict
    arrays: dict
    path: Path | None = None

    def __getattr__(self, name):
        arrays = self.__dict__.get("arrays", {})
        if name in arrays:
            return arrays[name]
        raise AttributeError(name)


def write_npz(path: str | Path, meta: dict, arrays: dict, *, compress: bool = False) -> Path:
    """Write ``arrays`` and ``meta`` (as a JSON string) to ``path``; create its folder.

    Atomic: written to a temporary file in the same folder, then renamed over
    ``path``, so a reader (or a crash) never sees half a file and an old file
    stays whole until the new one is complete.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    save = np.savez_compressed if compress else np.savez
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as f:
            save(f, meta=np.array(json.dumps(meta)), **arrays)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def read_npz(path: str | Path, *, fmt: str, version: int, required, what: str
             ) -> tuple[dict, dict]:
    """Read a file written by :func:`write_npz` and check its format and version.

    Args:
        fmt: expected ``meta["format"]``.
        version: the version this engine reads.
        required: names of arrays that must be present.
        what: the kind of file, for messages (e.g. ``"path grid"``).

    Returns:
        ``(meta, arrays)``.

    Raises:
        ValueError: missing file, not an NPZ, foreign format, unknown version or a
            missing array; the message names the file.
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: no such {what} file")
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except Exception as exc:  # noqa: BLE001 - zip/format errors of all kinds
        raise ValueError(f"{path}: not a readable NPZ file: {exc}") from exc
    if "meta" not in data:
        raise ValueError(f"{path}: not an isac-twin {what} (no 'meta' entry)")
    try:
        meta = json.loads(str(data.pop("meta")))
    except ValueError as exc:
        raise ValueError(f"{path}: the 'meta' entry is not JSON ({exc})") from None
    if not isinstance(meta, dict):
        raise ValueError(f"{path}: the 'meta' entry is not a JSON object")
    if meta.get("format") != fmt:
        raise ValueError(f"{path}: format {meta.get('format')!r} is not {fmt!r}")
    if meta.get("version") != version:
        raise ValueError(f"{path}: {what} format version {meta.get('version')!r} is unknown "
                         f"(this engine reads version {version})")
    missing = [k for k in required if k not in data]
    if missing:
        raise ValueError(f"{path}: missing arrays {', '.join(missing)}")
    return meta, data
