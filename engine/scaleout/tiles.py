"""Tiles of a floor grid and how one worker process traces a tile.

The client lays out the same raster as :func:`engine.raytrace.grid.trace_grid`
(:func:`plan_grid`: cell-centred points of the room's bounding box, the free
ones found by Mitsuba's up/down ray test) and splits the free points, in
index order, into tiles of ``tile_size`` points (:attr:`GridPlan.tiles`).

A worker traces a tile with :func:`trace_tile`: the scene folder is loaded
once per worker process and kept with its :class:`~engine.raytrace.chains.ChainTracer`
in a module-level cache keyed by the scene's content hash and the tracer
settings (:func:`worker_state`); a folder on the worker that hashes otherwise
than the client's scene is refused. The tile is traced exactly as
``trace_grid`` traces a chunk with chain reuse: the same
:class:`~engine.raytrace.solver_core.SolverCore` settings,
``ChainTracer.trace`` over chunks of
:data:`~engine.raytrace.grid.CHAIN_CHUNK_SIZE` points, then
:func:`~engine.raytrace.grid.sorted_chunk`. Chain reuse gives every receiver
every chain of the transmitters (enumerated once per worker process, without
sampling), so a point's paths do not depend on which other tiles the process
traced before; tiles are whole ``trace_grid`` chunks so that every point
shares its image-method calls with the same points as in one process (the
equality test in ``tests/engine/scaleout/test_cluster.py`` checks it against
the single-process grid). Shoot-and-bounce per receiver (``method = "sbr"``) is not tiled (see
:func:`plan_grid`).

Worker processes must be *spawned*, not forked, after Dr.Jit initialised
(Dask's default ``distributed.worker.multiprocessing-method`` is ``spawn``;
:func:`engine.scaleout.cluster.local_cluster` sets it explicitly).
"""

from __future__ import annotations

import dataclasses
import logging
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from engine.config import TracerConfig
from engine.raytrace.base import device_poses, sionna_orientation, validate_poses
from engine.raytrace.grid import (CHAIN_CHUNK_SIZE, GRID_ARRAYS, GRID_SPEC_TABLE_SIZE, grid_points,
                                  sorted_chunk)

log = logging.getLogger(__name__)

#: Dr.Jit worker threads per worker process (one core per worker).
DEFAULT_WORKER_THREADS = 1


@dataclass(frozen=True)
class TileJob:
    """What every tile of one grid shares (sent to the workers, pickled).

    Attributes:
        scene_folder: the scene folder (the same path on every worker).
        scene_hash: the client's :meth:`~engine.scene.TwinScene.content_hash`.
        config: tracer settings.
        src: ``[S, 3]`` m transmitter positions.
        src_orient: ``[S, 3]`` rad Sionna ``[yaw, pitch, roll]`` of the transmitters.
        deterministic: ``SolverCore(deterministic=...)``.
        spec_table_size: see :func:`~engine.raytrace.grid.trace_grid`.
        keep_strongest: paths kept per point and transmitter (None: all).
        chunk_size: points per ``ChainTracer.trace`` call.
        worker_threads: Dr.Jit threads of a worker process.
    """

    scene_folder: str
    scene_hash: str
    config: TracerConfig
    src: np.ndarray
    src_orient: np.ndarray
    deterministic: bool = False
    spec_table_size: int | None = GRID_SPEC_TABLE_SIZE
    keep_strongest: int | None = None
    chunk_size: int = CHAIN_CHUNK_SIZE
    worker_threads: int = DEFAULT_WORKER_THREADS

    def settings(self) -> dict:
        """Everything that decides a tile's arrays, as JSON-able values (the
        checkpoint key and the worker cache key)."""
        return {"scene_hash": self.scene_hash, "config": dataclasses.asdict(self.config),
                "src": np.round(self.src, 9).tolist(),
                "src_orient": np.round(self.src_orient, 9).tolist(),
                "deterministic": self.deterministic,
                "spec_table_size": self.spec_table_size,
                "keep_strongest": self.keep_strongest, "chunk_size": self.chunk_size}


@dataclass
class GridPlan:
    """The raster of a grid and its tiles (client side).

    Attributes:
        tx_names: transmitters traced.
        src, src_orient_cfg, src_orient: ``[S, 3]`` positions (m), config
            ``[roll, pitch, yaw]`` and Sionna ``[yaw, pitch, roll]`` (rad).
        origin: ``[2]`` m; shape: ``(nx, ny)``; height: z, m.
        points: ``[N, 3]`` m; free: ``[N]`` bool; todo: ``[F]`` free indices.
        tile_size: free points per tile.
    """

    tx_names: list[str]
    src: np.ndarray
    src_orient_cfg: np.ndarray
    src_orient: np.ndarray
    origin: np.ndarray
    shape: tuple[int, int]
    height: float
    points: np.ndarray
    free: np.ndarray
    todo: np.ndarray
    tile_size: int

    @property
    def tiles(self) -> list[np.ndarray]:
        """Point indices of every tile (consecutive free points)."""
        t = self.tile_size
        return [self.todo[i:i + t] for i in range(0, len(self.todo), t)]


def plan_grid(scene, tx_names: Sequence[str] | None, spacing: float, height: float | None,
              margin: float, config: TracerConfig, method: str | None,
              tile_size: int) -> GridPlan:
    """The raster ``trace_grid`` would trace (same points, same free test).

    Raises:
        ValueError: bad spacing or tile size, no transmitters, a bad pose, or a
            method other than chain reuse (``"sbr"`` is traced in one process only).
    """
    from engine.raytrace.raw import free_points

    cfg = scene.config
    if not (spacing > 0 and np.isfinite(spacing)):
        raise ValueError(f"spacing: expected a positive number of metres, got {spacing!r}")
    if int(tile_size) < 1:
        raise ValueError(f"tile_size: expected >= 1, got {tile_size!r}")
    if method not in (None, "auto", "chains", "sbr"):
        raise ValueError(f"method: expected 'auto', 'chains' or 'sbr', got {method!r}")
    chains = config.uses_chains if method in (None, "auto") else method == "chains"
    if not chains:
        raise ValueError("a cluster traces grids with chain reuse only (tracer.method "
                         "'chains' or 'auto' with diffuse reflection and diffraction off); "
                         "trace 'sbr' grids without --workers/--scheduler")
    tx_names = list(dict.fromkeys(lk.tx for lk in cfg.links)) if tx_names is None \
        else list(tx_names)
    if not tx_names:
        raise ValueError("trace_grid: no transmitters (give tx_names or add [[links]])")
    poses = dict(device_poses(cfg))
    validate_poses(scene, poses, tx_names)
    if height is None:
        robots = [d for d in cfg.devices if d.kind == "robot"]
        height = poses[robots[0].name].position[2] if robots else 1.0
    origin, (nx, ny) = grid_points(scene.bounds_min, scene.bounds_max, spacing, margin)
    ix, iy = np.meshgrid(np.arange(nx), np.arange(ny), indexing="ij")
    points = np.stack([origin[0] + ix.ravel() * spacing, origin[1] + iy.ravel() * spacing,
                       np.full(nx * ny, float(height))], axis=1)
    free = free_points(scene.sionna, points)
    orient = np.array([poses[n].orientation for n in tx_names], float)
    return GridPlan(tx_names=tx_names, src=np.array([poses[n].position for n in tx_names], float),
                    src_orient_cfg=orient,
                    src_orient=np.array([sionna_orientation(o) for o in orient]),
                    origin=origin, shape=(nx, ny), height=float(height), points=points,
                    free=free, todo=np.flatnonzero(free), tile_size=int(tile_size))


# --------------------------------------------------------------------------- worker side

#: Per worker process: cache key -> (TwinScene, ChainTracer). One entry: a
#: worker serves one grid at a time, and a scene holds ~100 MB.
_STATE: dict[str, tuple] = {}


def worker_state(job: TileJob):
    """The loaded scene and the chain tracer of this process for ``job`` (cached).

    Raises:
        ValueError: the scene folder on this worker hashes otherwise than the
            client's scene (another version of the room).
    """
    import json

    key = json.dumps(job.settings(), sort_keys=True)
    hit = _STATE.get(key)
    if hit is not None:
        return hit
    _STATE.clear()
    import drjit as dr

    from engine.raytrace.chains import ChainTracer
    from engine.raytrace.solver_core import SolverCore
    from engine.scene import load_scene

    dr.set_thread_count(int(job.worker_threads))
    scene = load_scene(job.scene_folder)
    have = scene.content_hash()
    if have != job.scene_hash:
        raise ValueError(
            f"worker {os.uname().nodename} pid {os.getpid()}: scene folder {job.scene_folder} "
            f"hashes to {have[:12]}, the client's scene to {job.scene_hash[:12]}: every worker "
            "needs the same scene folder (see docs/scaleout.md)")
    core = SolverCore(job.config, deterministic=job.deterministic,
                      spec_table_size=job.spec_table_size)
    _STATE[key] = (scene, ChainTracer(core))
    log.info("worker %d: loaded %s (%s)", os.getpid(), job.scene_folder, have[:12])
    return _STATE[key]


def trace_tile(job: TileJob, index: int, points: np.ndarray) -> dict:
    """Trace one tile in this worker process.

    Args:
        job: the grid's shared settings.
        index: the tile's number (returned, for the client's bookkeeping).
        points: ``[T, 3]`` m receiver positions (free points).

    Returns:
        ``{"index", "parts": [dict of [t, S, P] arrays as sorted_chunk returns,
        in the grid file's dtypes], "chains", "pid", "setup_s", "trace_s",
        "start", "end"}``: ``setup_s`` loading the scene and building the
        tracer (0 once this process has them), ``trace_s`` tracing the tile
        (the first tile of a process includes enumerating the chains),
        ``start``/``end`` wall-clock (``time.time()``) of the task.
    """
    import time

    start, t = time.time(), time.perf_counter()
    scene, ct = worker_state(job)
    t_setup = time.perf_counter()
    parts = []
    for i in range(0, len(points), job.chunk_size):
        raw = ct.trace(scene.sionna, job.src, points[i:i + job.chunk_size],
                       source_orientations=job.src_orient)
        parts.append(storage_dtypes(sorted_chunk(raw, job.keep_strongest)))
    t_end = time.perf_counter()
    return {"index": int(index), "parts": parts,
            "chains": len(ct.store) if ct.store is not None else 0, "pid": os.getpid(),
            "setup_s": t_setup - t, "trace_s": t_end - t_setup, "start": start,
            "end": start + (t_end - t)}


def storage_dtypes(part: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """A :func:`~engine.raytrace.grid.sorted_chunk` part cast to the dtypes of
    the grid file (:data:`~engine.raytrace.grid.GRID_ARRAYS`: ``a`` complex64,
    angles float32, ``interactions`` uint8), as the assembly casts it anyway:
    the same values, ~30 % fewer bytes to send and to checkpoint."""
    return {k: v.astype(GRID_ARRAYS[k][0], copy=False) if k in GRID_ARRAYS else v
            for k, v in part.items()}


def scene_folder(scene) -> Path:
    """The folder of ``scene``'s ``twin.toml`` (what workers load)."""
    return Path(scene.config.folder).resolve()
