"""Tiles of a floor grid and how one worker process traces a tile.

The client lays out the same raster as :func:`isac_twin.raytrace.grid.trace_grid`
(:func:`plan_grid`: cell-centred points of the room's bounding box, the free
ones found by Mitsuba's up/down ray test) and splits the free points, in
index order, into tiles of ``tile_size`` points (:attr:`GridPlan.tiles`).
With one-chunk tiles (the default) the last full chunk is handed out last, as
:data:`TAIL_PARTS` tiles that each trace a share of its image-method calls:
with whole chunks only, the lab's 5 cm grid (16 chunks and one of 764 points)
keeps one of 2 workers busy for 8.75 chunks while the other is idle after 8.

A worker traces a tile with :func:`trace_tile`: the scene folder is loaded
once per worker process and kept with its :class:`~isac_twin.raytrace.chains.ChainTracer`
in a module-level cache keyed by the scene's content hash and the tracer
settings (:func:`worker_state`); a folder on the worker that hashes otherwise
than the client's scene is refused. The tile is traced exactly as
``trace_grid`` traces a chunk with chain reuse: the same
:class:`~isac_twin.raytrace.solver_core.SolverCore` settings,
``ChainTracer.trace`` over chunks of
:data:`~isac_twin.raytrace.grid.CHAIN_CHUNK_SIZE` points, then
:func:`~isac_twin.raytrace.grid.sorted_chunk`. Chain reuse gives every receiver
every chain of the transmitters (each AP's enumerated once, without sampling,
by one worker's :func:`shoot_source`, and used by every worker:
:mod:`isac_twin.scaleout.shared_chains`), so a point's paths do not depend on
which other tiles the process traced before; tiles are whole ``trace_grid`` chunks so that every point
shares its image-method calls with the same points as in one process (the
equality test in ``tests/engine/scaleout/test_cluster.py`` checks it against
the single-process grid). Shoot-and-bounce per receiver (``method = "sbr"``) is not tiled (see
:func:`plan_grid`).

Worker processes must be *spawned*, not forked, after Dr.Jit initialised
(Dask's default ``distributed.worker.multiprocessing-method`` is ``spawn``;
:func:`isac_twin.scaleout.cluster.local_cluster` sets it explicitly).
"""

from __future__ import annotations

import dataclasses
import logging
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..raytrace.base import device_poses, sionna_orientation, validate_poses
from ..raytrace.chains import MAX_PAIRS_PER_CALL
from ..raytrace.grid import (
    CHAIN_CHUNK_SIZE,
    GRID_ARRAYS,
    GRID_SPEC_TABLE_SIZE,
    grid_points,
    sorted_chunk,
)
from ..scene.config import TracerConfig
from .shared_chains import local, merge, portable

log = logging.getLogger(__name__)

#: Dr.Jit worker threads per worker process (one core per worker).
DEFAULT_WORKER_THREADS = 1

#: The grid's last full chunk is traced as this many tiles, each a share of
#: its image-method calls (:func:`trace_tile`), so that the end of a build,
#: when some workers are already idle, waits for smaller tiles.
TAIL_PARTS = 2


@dataclass(frozen=True)
class TileJob:
    """What every tile of one grid shares (sent to the workers, pickled).

    Attributes:
        scene_folder: the scene folder (the same path on every worker).
        scene_hash: the client's :meth:`~isac_twin.scene.twin_scene.TwinScene.content_hash`.
        config: tracer settings.
        src: ``[S, 3]`` m transmitter positions.
        src_orient: ``[S, 3]`` rad Sionna ``[yaw, pitch, roll]`` of the transmitters.
        deterministic: ``SolverCore(deterministic=...)``.
        spec_table_size: see :func:`~isac_twin.raytrace.grid.trace_grid`.
        keep_strongest: paths kept per point and transmitter (None: all).
        chunk_size: points per ``ChainTracer.trace`` call.
        worker_threads: Dr.Jit threads of a worker process.
        max_pairs: ``ChainTracer(max_pairs=...)``, candidate-target pairs per
            image-method call (``trace_grid``'s tracer uses the default).
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
    max_pairs: int = MAX_PAIRS_PER_CALL

    def settings(self) -> dict:
        """Everything that decides a tile's arrays, as JSON-able values (the
        checkpoint key and the worker cache key)."""
        return {"scene_hash": self.scene_hash, "config": dataclasses.asdict(self.config),
                "src": np.round(self.src, 9).tolist(),
                "src_orient": np.round(self.src_orient, 9).tolist(),
                "deterministic": self.deterministic,
                "spec_table_size": self.spec_table_size,
                "keep_strongest": self.keep_strongest, "chunk_size": self.chunk_size,
                "max_pairs": self.max_pairs}


@dataclass
class Tile:
    """One task: consecutive free points and which share of their image-method
    calls to trace.

    Attributes:
        index: ``[T]`` point indices (of :attr:`GridPlan.points`).
        part, parts: trace the ``part``-th of ``parts`` shares of the calls
            ``ChainTracer.trace`` makes for these points (``0, 1``: all of them;
            see :func:`trace_tile`).
    """

    index: np.ndarray
    part: int = 0
    parts: int = 1


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
        chunk_size: free points per ``ChainTracer.trace`` call.
        tail_parts: tiles the last full chunk is split into when tiles are
            one chunk (1: not split).
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
    chunk_size: int = CHAIN_CHUNK_SIZE
    tail_parts: int = 1

    @property
    def tiles(self) -> list[Tile]:
        """Every tile, in the order they are handed out: consecutive free
        points, ``tile_size`` of them; when a tile is one chunk, the last full
        chunk (or the only one) comes last, as :attr:`tail_parts` tiles."""
        t = self.tile_size
        tiles = [Tile(self.todo[i:i + t]) for i in range(0, len(self.todo), t)]
        if self.tail_parts > 1 and t == self.chunk_size and tiles:
            full = [k for k, x in enumerate(tiles) if len(x.index) == t]
            last = tiles.pop(full[-1] if full else len(tiles) - 1)
            tiles += [Tile(last.index, j, self.tail_parts) for j in range(self.tail_parts)]
        return tiles


def plan_grid(scene, tx_names: Sequence[str] | None, spacing: float, height: float | None,
              margin: float, config: TracerConfig, method: str | None,
              tile_size: int, chunk_size: int = CHAIN_CHUNK_SIZE,
              tail_parts: int = TAIL_PARTS) -> GridPlan:
    """The raster ``trace_grid`` would trace (same points, same free test),
    in tiles of ``tile_size`` free points (see :attr:`GridPlan.tiles`).

    Raises:
        ValueError: bad spacing or tile size, no transmitters, a bad pose, or a
            method other than chain reuse (``"sbr"`` is traced in one process only).
    """
    from ..raytrace.raw import free_points

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
                    free=free, todo=np.flatnonzero(free), tile_size=int(tile_size),
                    chunk_size=int(chunk_size), tail_parts=max(1, int(tail_parts)))


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

    from ..raytrace.chains import ChainTracer
    from ..raytrace.solver_core import SolverCore
    from ..scene.twin_scene import load_scene

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
    _STATE[key] = (scene, ChainTracer(core, max_pairs=job.max_pairs))
    log.info("worker %d: loaded %s (%s)", os.getpid(), job.scene_folder, have[:12])
    return _STATE[key]


def shoot_source(job: TileJob, source: int) -> dict:
    """Enumerate the chains of transmitter ``source`` of ``job`` in this worker
    process, for every worker's tiles (:mod:`isac_twin.scaleout.shared_chains`).

    The chains are those ``ChainTracer.trace`` enumerates for this source in a
    grid trace: the same tracer settings, the source at its float32 position
    (sources are enumerated one by one, independently).

    Returns:
        ``{"source", "chains": portable chains (``src`` = ``source``), "count",
        "pid", "setup_s" (scene load, 0 once this process has it), "shoot_s",
        "start", "end" (``time.time()``)}``.

    Raises:
        ValueError: no such source, or the worker's scene folder differs.
    """
    import time

    from ..raytrace.chains import ChainTracer

    start, t = time.time(), time.perf_counter()
    s = int(source)
    if not 0 <= s < len(job.src):
        raise ValueError(f"shoot_source: source {s}, the job has {len(job.src)} transmitters")
    scene, ct = worker_state(job)
    t_setup = time.perf_counter()
    shooter = ChainTracer(ct.core, mirror_filter=False)
    pos = np.asarray(job.src, np.float64)[s:s + 1].astype(np.float32).astype(np.float64)
    shooter.prepare(scene.sionna, pos, np.zeros((0, 3)))
    cols = dict(shooter.store.columns())
    cols["src"] = np.full(len(cols["src"]), s, np.uint32)
    chains = portable(cols, shooter.store.planes)
    t_end = time.perf_counter()
    return {"source": s, "chains": chains, "count": len(cols["src"]), "pid": os.getpid(),
            "setup_s": t_setup - t, "shoot_s": t_end - t_setup, "start": start,
            "end": start + (t_end - t)}


def use_shipped_chains(scene, ct, job: TileJob, shot: Sequence[dict]) -> None:
    """Give the chain tracer ``ct`` of this process the chains of every
    transmitter of ``job`` (:func:`shoot_source`'s results, any order)."""
    from ..raytrace.planes import PlaneIndex

    have = sorted(int(r["source"]) for r in shot)
    if have != list(range(len(job.src))):
        raise ValueError(f"shipped chains: sources {have}, the job has {len(job.src)} "
                         "transmitters")
    planes = PlaneIndex(scene.sionna.mi_scene)
    cols = local(merge([r["chains"] for r in shot]), planes)
    ct.use_chains(scene.sionna, job.src, cols, planes=planes)


def trace_tile(job: TileJob, index: int, points: np.ndarray, part: int = 0,
               parts: int = 1, chains: Sequence[dict] | None = None) -> dict:
    """Trace one tile in this worker process.

    Args:
        job: the grid's shared settings.
        index: the tile's number (returned, for the client's bookkeeping).
        points: ``[T, 3]`` m receiver positions (free points).
        part, parts: with ``parts > 1`` the points are one chunk
            (``job.chunk_size`` points or fewer) and only the ``part``-th of
            ``parts`` shares of the image-method calls ``ChainTracer.trace``
            makes for the chunk (:func:`image_method_calls`) is traced: the
            same calls with the same (chain, point) pairs as in one process,
            so the same paths (a point's paths can depend on which points share
            its call); a share can be empty.
        chains: :func:`shoot_source`'s results for every transmitter: a
            process without chains uses these (:func:`use_shipped_chains`)
            instead of enumerating them (None: it enumerates them).

    Returns:
        ``{"index", "span": [a, b] (the points traced: points[a:b]), "parts":
        [dict of [t, S, P] arrays as sorted_chunk returns, in the grid file's
        dtypes], "chains", "pid", "setup_s", "trace_s", "start", "end",
        "cpu_s", "chains_s", "sources_shot"}``:
        ``setup_s`` loading the scene and building the tracer (0 once this
        process has them), ``chains_s`` handing it the shipped chains (0 but
        in a process's first tile), ``trace_s`` tracing the tile (with
        ``chains_s``; without shipped chains a process's first tile
        includes enumerating them), ``sources_shot`` the sources this process
        enumerated chains of (0 with shipped chains), ``start``/``end``
        wall-clock (``time.time()``) of the task, ``cpu_s`` the process's CPU
        time in it (less than the wall time when the cores are shared).
    """
    import time

    start, t, cpu = time.time(), time.perf_counter(), time.process_time()
    scene, ct = worker_state(job)
    t_setup = time.perf_counter()
    if chains is not None and ct.store is None:
        use_shipped_chains(scene, ct, job, chains)
    t_chains = time.perf_counter()
    a, b = 0, len(points)
    if parts > 1:
        if len(points) > job.chunk_size:
            raise ValueError(f"tile {index}: {len(points)} points in {parts} parts; a tile "
                             f"traced in parts is one chunk (at most {job.chunk_size} points)")
        if ct.store is None:
            # a fresh tracer's first trace enumerates the chains (and would drop
            # what a prepare() before it enumerated)
            ct.trace(scene.sionna, job.src, points[:1], source_orientations=job.src_orient)
        per = ct.prepare(scene.sionna, job.src, points)
        calls = image_method_calls([len(p) for p in per], ct.max_pairs)
        lo, hi = part * len(calls) // parts, (part + 1) * len(calls) // parts
        a, b = (calls[lo][0], calls[hi - 1][1]) if hi > lo else (0, 0)
    out = []
    for i in range(a, b, job.chunk_size):
        raw = ct.trace(scene.sionna, job.src, points[i:min(b, i + job.chunk_size)],
                       source_orientations=job.src_orient)
        out.append(storage_dtypes(sorted_chunk(raw, job.keep_strongest)))
    t_end = time.perf_counter()
    return {"index": int(index), "span": [int(a), int(b)], "parts": out,
            "chains": len(ct.store) if ct.store is not None else 0, "pid": os.getpid(),
            "setup_s": t_setup - t, "trace_s": t_end - t_setup, "start": start,
            "end": start + (t_end - t), "cpu_s": time.process_time() - cpu,
            "chains_s": t_chains - t_setup, "sources_shot": int(ct.sources_shot)}


def point_paths(parts: Sequence[dict], j: int) -> dict[str, np.ndarray]:
    """The paths of the ``j``-th point a tile traced, from its parts (as
    :func:`trace_tile` returns them; the grid file's values): ``num_paths
    [S]``, ``a, tau [S, P]``, ``interactions [S, P, D]``, ``vertices [S, P, D, 3]``.

    Raises:
        IndexError: the parts hold fewer than ``j + 1`` points.
    """
    off = 0
    for part in parts:
        n = part["num_paths"].shape[0]
        if j < off + n:
            return {k: np.array(part[k][j - off])
                    for k in ("num_paths", "a", "tau", "interactions", "vertices")}
        off += n
    raise IndexError(f"point {j}: the tile's parts hold {off} points")


def verify_points(job: TileJob, index: Sequence[int], points: np.ndarray,
                  stored: Sequence[dict], top_n: int) -> dict:
    """Re-trace grid points directly in this worker process and compare with
    their traced paths (:func:`~isac_twin.raytrace.grid.verify_point`, as
    ``trace_grid``'s verification: the same solver settings).

    Args:
        job: the grid's shared settings.
        index: ``[n]`` grid indices of the points (returned).
        points: ``[n, 3]`` m.
        stored: per point, its paths (:func:`point_paths`).
        top_n: ``trace_grid``'s ``verify_top``.

    Returns:
        ``{"index": [n], "counts": [n dicts of VERIFY_COUNTS], "pid",
        "verify_s"}``.
    """
    import time

    from ..raytrace.grid import verify_point

    t = time.perf_counter()
    scene, ct = worker_state(job)
    confirm: dict = {}
    counts = [verify_point(ct.core, scene.sionna, job.src, job.src_orient, p, st, top_n,
                           job.keep_strongest, confirm)
              for p, st in zip(np.asarray(points, np.float64).reshape(-1, 3), stored)]
    return {"index": [int(i) for i in index], "counts": counts, "pid": os.getpid(),
            "verify_s": time.perf_counter() - t}


def image_method_calls(pairs: Sequence[int], max_pairs: int) -> list[tuple[int, int]]:
    """The target ranges ``[(a, b), ...]`` of the image-method calls that
    ``ChainTracer.trace`` makes for targets with ``pairs[t]`` candidate chains
    each: consecutive targets, a new call when the next target would take the
    call above ``max_pairs`` pairs (a single target may exceed it). Traced from
    a call's first target on, ``ChainTracer.trace`` makes the same calls again
    (``tests/engine/scaleout/test_tiles.py`` checks it against the tracer).
    """
    calls, a, size = [], 0, 0
    for t, n in enumerate(pairs):
        if t > a and size + n > max_pairs:
            calls.append((a, t))
            a, size = t, 0
        size += int(n)
    if len(pairs):
        calls.append((a, len(pairs)))
    return calls


def storage_dtypes(part: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """A :func:`~isac_twin.raytrace.grid.sorted_chunk` part cast to the dtypes of
    the grid file (:data:`~isac_twin.raytrace.grid.GRID_ARRAYS`: ``a`` complex64,
    angles float32, ``interactions`` uint8), as the assembly casts it anyway:
    the same values, ~30 % fewer bytes to send and to checkpoint."""
    return {k: v.astype(GRID_ARRAYS[k][0], copy=False) if k in GRID_ARRAYS else v
            for k, v in part.items()}


def scene_folder(scene) -> Path:
    """The folder of ``scene``'s ``twin.toml`` (what workers load)."""
    return Path(scene.config.folder).resolve()
