"""Checkpoints of a tiled grid trace: one NPZ per finished tile.

A build writes every finished tile to ``<folder>/<key>/tile-<k>.npz`` where
``key`` is a SHA-256 (16 hex digits) over the scene's content hash, the tracer
settings, the raster (spacing, height, margin, transmitters, number of points)
and the tile size (:func:`checkpoint_key`), so a checkpoint of another scene
state or other settings is never mixed in: it lives under another key. A rerun
with the same key loads the finished tiles and traces only the missing ones.
The folder is removed when the output file is written.

Tile files are written atomically (:func:`isac_twin.utils.npzfile.write_npz`), so an
interrupted write leaves no half tile; a tile file that cannot be read (or
holds another tile's points) is traced again, with a warning naming it.
"""

from __future__ import annotations

import hashlib
import json
import logging
import shutil
from pathlib import Path

import numpy as np

from ..utils.npzfile import read_npz, write_npz

log = logging.getLogger(__name__)

TILE_FORMAT = "isac-twin-grid-tile"
TILE_FORMAT_VERSION = 1


def checkpoint_key(settings: dict) -> str:
    """16 hex digits of SHA-256 over ``settings`` (JSON, sorted keys)."""
    text = json.dumps(settings, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def checkpoint_dir(out: str | Path) -> Path:
    """The checkpoint folder next to output file ``out``: ``<out>.tiles/``."""
    out = Path(out)
    return out.with_name(out.name + ".tiles")


class TileCheckpoints:
    """The finished tiles of one build (``folder / key``).

    Args:
        folder: the checkpoint folder (see :func:`checkpoint_dir`).
        key: :func:`checkpoint_key` of the build's settings.
    """

    def __init__(self, folder: str | Path, key: str):
        self.root = Path(folder)
        self.dir = self.root / key
        self.key = key

    def _file(self, index: int) -> Path:
        return self.dir / f"tile-{index:06d}.npz"

    def load(self, index: int, points: np.ndarray) -> tuple[list[dict], dict] | None:
        """The parts of tile ``index`` and its ``meta`` if checkpointed (None: trace it).

        ``points``: ``[T, 3]`` m the tile's points (a file holding others is ignored).
        """
        f = self._file(index)
        if not f.is_file():
            return None
        try:
            meta, data = read_npz(f, fmt=TILE_FORMAT, version=TILE_FORMAT_VERSION,
                                  required=("points",), what="grid tile checkpoint")
            if data["points"].shape != points.shape or not np.array_equal(data["points"], points):
                raise ValueError("it holds other points")
            parts = []
            for j in range(int(meta["parts"])):
                parts.append({k.split("/", 1)[1]: v for k, v in data.items()
                              if k.startswith(f"{j}/")})
            return parts, meta
        except (ValueError, KeyError, OSError) as exc:
            log.warning("%s: not a usable tile checkpoint (%s); tracing the tile again", f, exc)
            return None

    def save(self, index: int, points: np.ndarray, parts: list[dict], info: dict) -> Path:
        """Write tile ``index`` (its ``points [T, 3]`` and ``parts``) atomically."""
        arrays = {"points": points}
        for j, part in enumerate(parts):
            arrays.update({f"{j}/{k}": v for k, v in part.items()})
        meta = {"format": TILE_FORMAT, "version": TILE_FORMAT_VERSION, "key": self.key,
                "tile": int(index), "parts": len(parts), **info}
        return write_npz(self._file(index), meta, arrays)

    def remove(self) -> None:
        """Delete this build's checkpoints (and the folder when nothing else is in it)."""
        shutil.rmtree(self.dir, ignore_errors=True)
        try:
            self.root.rmdir()
        except OSError:
            pass
